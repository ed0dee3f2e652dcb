//! Landmarks on the 58-point IMM template (thesis chapter 2): the plain Active Shape Model (grey-level
//! profiles), SIFT-ASM (SIFT descriptors oriented by the contour normal) and the Combined ASM
//! (C-ASM: the 45 internal points matched by SIFT, the 13 jaw points by profiles, each group with
//! its own shape model, combined and constrained by the full 58-point model).
//!
//! - [`pdm`]: point distribution model (Procrustes, PCA, constrained fit).
//! - [`profile`], [`sift`]: the two local texture models' features; [`mahalanobis`]: their
//!   Gaussian models.
//! - [`search`]: the face crop (rescaled like the thesis's 260×260 region), the 2-level pyramid and
//!   the coarse-to-fine matching.
//! - [`asm3d`]: the 3D-ASM for turned heads.
//!
//! Training lives in `research::train_asm` (and `research::train_asm3d`).

pub mod asm3d;
pub mod mahalanobis;
pub mod pdm;
pub mod profile;
pub mod search;
pub mod sift;
mod simd;

use std::path::Path;

use serde::{Deserialize, Serialize};

use facegate_core::face::EyeMouthCentres;
use facegate_core::geometry::{Point, Rect};
use facegate_core::imaging::GrayF32;

use mahalanobis::{FullGaussian, PcaGaussian};
use pdm::ShapeModel;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Variant {
    Asm,
    Sift,
    #[default]
    Casm,
    /// 3D-ASM (`asm3d::Asm3dLandmarker`, `models/asm3d.bin`); the 2D [`Landmarker`] searches it as C-ASM.
    Asm3d,
}

impl Variant {
    pub const ALL: [Variant; 3] = [Variant::Asm, Variant::Sift, Variant::Casm];

    pub fn name(&self) -> &'static str {
        match self {
            Variant::Asm => "asm",
            Variant::Sift => "sift",
            Variant::Casm => "casm",
            Variant::Asm3d => "asm3d",
        }
    }

    pub fn parse(s: &str) -> Option<Variant> {
        Variant::ALL.into_iter().chain([Variant::Asm3d]).find(|v| v.name() == s)
    }
}

/// The 58 IMM points in image pixels, with the eye and mouth centres.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Landmarks {
    pub points: Vec<Point>,
    #[serde(rename = "keypoints")]
    pub centres: EyeMouthCentres,
}

#[derive(Debug, thiserror::Error)]
pub enum LandmarkError {
    #[error("cannot load the landmark model {path}: {message}")]
    Model { path: String, message: String },
    #[error("cannot train the landmark model: {0}")]
    Training(String),
}

/// Search parameters; the defaults are the thesis's where it gives them.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SearchParams {
    /// Side of the square face crop the search runs in (thesis: 260×260).
    pub crop_size: usize,
    /// x extent of the mean shape in crop pixels.
    pub ref_width: f32,
    /// Gaussian pyramid levels searched coarse to fine (thesis: 2).
    pub levels: usize,
    /// Candidates along the normal on each side for grey-level profiles.
    pub profile_radius: usize,
    /// Half side of the 2D SIFT candidate window, per level (finest first).
    pub sift_radius: Vec<usize>,
    pub max_iterations: usize,
    /// Stop when this share of points moved less than a pixel (thesis: ~90%).
    pub converged_share: f32,
    /// Training photos whose first shape coefficient is beyond ± this many standard deviations
    /// form the turned start groups; 0 disables them (one start, the mean shape).
    pub yaw_start: f32,
    /// Extra starts tilted in the image plane by ± this many degrees; 0 disables them.
    pub roll_start: f32,
    /// Iterations each start gets on the coarsest level before the best one is kept.
    pub probe_iterations: usize,
}

impl Default for SearchParams {
    fn default() -> Self {
        Self {
            crop_size: 260,
            ref_width: 170.0,
            levels: 2,
            profile_radius: 3,
            sift_radius: vec![1, 3],
            max_iterations: 4,
            converged_share: 0.9,
            yaw_start: 1.0,
            roll_start: 12.0,
            probe_iterations: 0,
        }
    }
}

/// Where a starting shape goes relative to the face box: learnt from the training photos' boxes.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
pub struct Placement {
    /// Scale of the starting shape per box width.
    pub scale_per_width: f32,
    /// Shape centre minus box centre, in box widths.
    pub dx: f32,
    pub dy: f32,
}

/// A starting shape: the mean shape of a group of training photos (by their first shape
/// coefficient, yaw on IMM: turned one way, frontal, turned the other way) and its placement.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Start {
    /// Full-model coefficients of the start shape.
    pub b: Vec<f32>,
    pub placement: Placement,
    /// Training photos in the group.
    pub photos: usize,
}

/// What kind of box the placement was learnt from (the search expects the same kind).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BoxSource {
    /// The face detector's boxes (photos it missed were left out of the placement statistics).
    Detector,
    /// Bounding boxes of the annotated points (no detector available at training time).
    Annotation,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TrainInfo {
    pub images: usize,
    pub persons: Vec<u32>,
    pub box_source: BoxSource,
    /// Photos where the detector found no face over the annotation (not used for placement).
    pub detector_misses: usize,
}

/// The trained models of all three variants (`models/asm.bin`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct AsmModel {
    pub format: u32,
    pub params: SearchParams,
    /// For each point, its previous and next neighbour on its contour (the normal is
    /// perpendicular to the line between them).
    pub neighbours: Vec<[u16; 2]>,
    pub full: ShapeModel,
    /// C-ASM's facial internal region model (IMM points 13..58).
    pub internal: ShapeModel,
    /// C-ASM's facial contour model (IMM points 0..13).
    pub contour: ShapeModel,
    /// `[level][point]` grey-level profile models.
    pub profiles: Vec<Vec<FullGaussian>>,
    /// `[level][point]` SIFT models.
    pub sifts: Vec<Vec<PcaGaussian>>,
    /// Starting shapes, the frontal one first.
    pub starts: Vec<Start>,
    pub info: TrainInfo,
}

pub const MODEL_FORMAT: u32 = 1;

/// Trained shape and texture models of all variants (`models/asm.bin`), shareable across threads.
pub struct Landmarker {
    pub model: AsmModel,
}

impl Landmarker {
    pub fn load(path: &Path) -> Result<Landmarker, LandmarkError> {
        let err = |message: String| LandmarkError::Model { path: path.display().to_string(), message };
        let model: AsmModel =
            facegate_core::model_file::read_model(path, "landmark model", MODEL_FORMAT, "facegate train asm").map_err(err)?;
        if model.full.points() != facegate_core::face::IMM_POINTS || model.neighbours.len() != facegate_core::face::IMM_POINTS {
            return Err(err("the model does not have 58 points".into()));
        }
        Ok(Landmarker { model })
    }

    pub fn save(&self, path: &Path) -> Result<(), LandmarkError> {
        facegate_core::model_file::write_model(path, &self.model)
            .map_err(|message| LandmarkError::Model { path: path.display().to_string(), message })
    }

    /// Search the 58 points of the face in `face` (a box of the kind the model was trained with,
    /// normally the detector's). Never panics: a degenerate box or image gives the placed mean shape.
    pub fn fit(&self, gray: &GrayF32, face: &Rect, variant: Variant) -> Landmarks {
        let points = search::fit(&self.model, gray, face, variant);
        let centres = EyeMouthCentres::from_imm(&points);
        Landmarks { points, centres }
    }

    /// The initial shape (mean shape placed from the box), in image pixels.
    pub fn initial_shape(&self, face: &Rect) -> Vec<Point> {
        search::place(&self.model, face)
    }
}
