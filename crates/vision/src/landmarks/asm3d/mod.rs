//! 3D-ASM (thesis chapter 3): landmarks on turned heads from a 3D point distribution model and
//! view-based local texture models.
//!
//! - **3D PDM** ([`Pdm3d`]): the 58 IMM points read at their vertices of the Surrey Face Model for
//!   shapes drawn at random from the model (standard normal coefficients, fixed seed), PCA of the
//!   3D point sets. The jaw points are the *visible* outline, which moves over the mesh as the head
//!   turns, so each view (yaw bin) has its own 3D PDM whose jaw vertices were chosen for that yaw
//!   (each jaw point's vertex of the annotators' convention, learnt from the 3DMM fits of the
//!   near-frontal training photos, while it faces the camera, else the nearest vertex on the
//!   occluding outline). Fitted to 2D candidates by alternating a scaled
//!   orthographic camera (`morph::fit::estimate_camera`) and regularised, clamped 3D coefficients.
//! - **View-based texture models**: 7 yaw bins (−45°…+45° in 15° steps), each a complete 2D C-ASM
//!   texture set (SIFT for the 45 internal points, grey-level profiles for the 13 jaw points, two
//!   pyramid levels), searched by the C-ASM candidate search `search::suggest`; the bin used at each
//!   iteration is the one nearest to the current yaw of the 3D fit.
//! - **Synthetic training views** (`research::asm3d_synth`, for `research::train_asm3d`): each annotated training photo is fitted by the 3DMM with its
//!   manual landmarks, its texture extracted (symmetry completed), and the textured shape rendered at
//!   every bin's yaw (with a random horizontal illumination gradient); the landmarks of the renders
//!   are the projected model points, exact by construction. The photo itself also trains the bin of
//!   its fitted yaw.
//! - **Search**: the crop is taken at a fixed scale in pixels per millimetre (the 3D fit gives the
//!   face's scale in mm, so all views share one crop scale); every bin's mean shape, upright and
//!   tilted ±12°, placed from the detector box, is ranked by its texture cost on the coarse level;
//!   the best starts of the 3 best-ranked views get 2 coarse iterations {candidates by the current
//!   view's textures → 3D fit → view from its yaw}, the best goes on to convergence on the coarse
//!   level; then a 2D C-ASM refines the points coarse to fine ([`Refinement`]: the service's C-ASM,
//!   trained on real photos, or the chosen view's own), and the 3D PDM fitted to them gives the
//!   pose. The service switches to the 3D-ASM when the C-ASM's points are turned beyond
//!   [`SERVICE_MIN_YAW`] ([`Asm3dLandmarker::switch`]).
//! - **Profile model** ([`ProfileModel`], `models/asm3d-profile.bin`): the same search with 13
//!   views from −90° to +90° (those beyond ±45° trained on renders alone), each view's visibility
//!   (hidden points weighted down in its 3D fits) and the mean face's five detector points, from
//!   which [`Asm3dLandmarker::fit_from_detector`] starts on heads turned past
//!   [`DETECTOR_SEED_MIN_YAW`].

mod landmarker;
mod pdm3d;

pub use landmarker::*;
pub use pdm3d::*;

use serde::{Deserialize, Serialize};

use crate::landmarks::{AsmModel, BoxSource, Placement, SearchParams};

pub const ASM3D_FORMAT: u32 = 3;
/// Format of `models/asm3d-profile.bin` ([`ProfileModel`]).
pub const PROFILE_FORMAT: u32 = 1;

/// One view (yaw bin): its 3D PDM (jaw vertices for this yaw), its texture models and where its
/// start goes relative to the face box.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct View3d {
    /// Yaw of the bin centre in degrees (the morph module's sign: > 0 nose towards the image right).
    pub yaw: f32,
    pub pdm: Pdm3d,
    /// The view's texture models, stored as a view-specific 2D C-ASM (profiles and SIFT per level
    /// and point; its 2D shape models trained on the view's shapes) so that the C-ASM candidate
    /// search serves it unchanged. Its `starts` are empty: the 3D search places its own.
    pub textures: AsmModel,
    /// Start placement: `scale_per_width` is the face's scale in pixels per mm per box width; `dx`,
    /// `dy` the landmarks' centroid minus the box centre, in box widths.
    pub placement: Placement,
    /// Size of the start shape (the 3D PDM's mean) relative to `placement.scale_per_width`: the
    /// median over the view's real photos of the least-squares scale that maps the mean, seen
    /// under the photo's fitted rotation, onto its annotation, divided by the fitted 3DMM's camera
    /// scale. (The camera scale belongs to the fitted face, whose own shape is larger or smaller
    /// than the mean: placing the mean at that scale started it too large, the mouth on the lower
    /// lip or chin edge.)
    pub start_scale: f32,
    /// Photos (real and synthetic) the textures were trained on.
    pub samples: usize,
    /// Real photos whose fitted yaw fell into this bin.
    pub real_photos: usize,
    /// Mean texture cost of the view's training samples on the coarsest level under its own models:
    /// subtracted when starts of different views are compared.
    pub typical_cost: f32,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Asm3dInfo {
    pub photos: usize,
    pub persons: Vec<u32>,
    pub box_source: BoxSource,
    pub detector_misses: usize,
    /// Photos the 3DMM could not be fitted to (left out).
    pub fit_failures: usize,
    pub pdm_shapes: usize,
    pub seed: u64,
}

/// The trained 3D-ASM (`models/asm3d.bin`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Asm3dModel {
    pub format: u32,
    pub params: SearchParams,
    /// Crop pixels per model millimetre (the crop's fixed scale).
    pub crop_px_per_mm: f32,
    /// Landmark noise σ (crop pixels) of the 3D fit's coefficient prior.
    pub sigma_px: f32,
    /// Views by increasing yaw.
    pub views: Vec<View3d>,
    pub info: Asm3dInfo,
}

/// The 3D-ASM with views from −90° to +90° (`models/asm3d-profile.bin`), searched from a
/// multi-view detector's five points on heads turned too far for the C-ASM
/// ([`Asm3dLandmarker::fit_from_detector`]). Its views within ±45° are trained as the thesis's
/// (`models/asm3d.bin`); those beyond learn from renders alone.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ProfileModel {
    pub format: u32,
    pub asm3d: Asm3dModel,
    /// Per view, per point, whether the view shows it (`view_visibility`): a hidden point's
    /// texture candidate is the surface in front of it, so the 3D fit weights it by
    /// [`HIDDEN_POINT_WEIGHT`].
    pub visible: Vec<Vec<bool>>,
    /// The 3DMM mean face's points for a detector's five (`FaceModel::key_point_vertices`: eyes,
    /// nose tip, mouth corners), model mm, in the 3D PDMs' frame: they pose the search's start.
    pub key_points: [[f32; 3]; 5],
}

pub fn nearest_view(yaws: &[f32], yaw: f32) -> usize {
    let mut best = 0;
    for (i, &y) in yaws.iter().enumerate() {
        if (y - yaw).abs() < (yaws[best] - yaw).abs() {
            best = i;
        }
    }
    best
}
