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
//! - **Synthetic training views**: each annotated training photo is fitted by the 3DMM with its
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

use std::path::Path;

use nalgebra::{DMatrix, DVector};
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

use crate::dataset::{self, IMM_POINTS, ImmSample, JAW, KeyPoints};
use crate::detect::Detector;
use crate::geometry::{Point, Rect, centroid};
use crate::imaging::{self, GrayF32};
use crate::morph::{Camera, FaceModel, Pose, fit::estimate_camera, render};

use super::mahalanobis::{FullGaussian, PcaGaussian};
use super::pdm::{ShapeModel, principal_modes};
use super::search::{self, Frame, Level, Workspace, from_level, normals, pyramid, to_level};
use super::{AsmModel, BoxSource, LandmarkError, Placement, SearchParams, TrainInfo, Variant, profile, sift};

pub const ASM3D_FORMAT: u32 = 3;

/// A 3D point distribution model of the 58 IMM points (model millimetres: x to the subject's left,
/// y up, z towards the camera), coefficients limited to ±`constrain`·√λ.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Pdm3d {
    pub mean: Vec<[f32; 3]>,
    /// `modes × 3n` row-major: each row a unit eigenvector over (x0, y0, z0, x1, …).
    pub basis: Vec<f32>,
    pub eigenvalues: Vec<f32>,
    pub constrain: f32,
}

/// A fit of a [`Pdm3d`] to 2D points.
#[derive(Debug, Clone)]
pub struct Fit3d {
    pub camera: Camera,
    pub coefficients: Vec<f32>,
    /// The projected model points.
    pub points: Vec<Point>,
}

impl Pdm3d {
    /// PCA of 3D point sets (no alignment: all are in the 3DMM's frame), keeping `variance` of the
    /// total.
    pub fn train(shapes: &[Vec<[f32; 3]>], variance: f64, constrain: f32) -> Pdm3d {
        let n = shapes[0].len();
        let dim = 3 * n;
        let count = shapes.len() as f64;
        let mut mean = vec![0.0f64; dim];
        for s in shapes {
            for (i, p) in s.iter().enumerate() {
                for d in 0..3 {
                    mean[3 * i + d] += p[d] as f64 / count;
                }
            }
        }
        let (basis, eigenvalues) = principal_modes(dim, shapes, variance, |s: &Vec<[f32; 3]>, x| {
            for (i, p) in s.iter().enumerate() {
                for d in 0..3 {
                    x[3 * i + d] = p[d] as f64 - mean[3 * i + d];
                }
            }
        });
        let mean = mean.chunks_exact(3).map(|c| [c[0] as f32, c[1] as f32, c[2] as f32]).collect();
        Pdm3d { mean, basis, eigenvalues, constrain }
    }

    pub fn points(&self) -> usize {
        self.mean.len()
    }

    pub fn modes(&self) -> usize {
        self.eigenvalues.len()
    }

    /// The 3D points for coefficients `b`.
    pub fn shape(&self, b: &[f32]) -> Vec<[f64; 3]> {
        let dim = 3 * self.points();
        let mut out: Vec<[f64; 3]> = self.mean.iter().map(|p| [p[0] as f64, p[1] as f64, p[2] as f64]).collect();
        for (k, &bk) in b.iter().enumerate().take(self.modes()) {
            let row = &self.basis[k * dim..(k + 1) * dim];
            for (i, p) in out.iter_mut().enumerate() {
                for d in 0..3 {
                    p[d] += bk as f64 * row[3 * i + d] as f64;
                }
            }
        }
        out
    }

    /// Project the shape `b` with `camera`.
    pub fn project(&self, b: &[f32], camera: &Camera) -> Vec<Point> {
        self.shape(b).iter().map(|&p| camera.project(p)).map(|q| [q[0] as f32, q[1] as f32]).collect()
    }

    /// Fit to 2D `targets`: alternate the scaled orthographic camera and the coefficients (linear
    /// least squares with the prior `σ²/λ_k` on each, then clamped to the constraint box).
    /// `None` when the targets are degenerate (collinear, non-finite).
    pub fn fit(&self, targets: &[Point], sigma_px: f64, iterations: usize) -> Option<Fit3d> {
        let n = self.points();
        if targets.len() != n || targets.iter().any(|p| !p[0].is_finite() || !p[1].is_finite()) {
            return None;
        }
        let k = self.modes();
        let dim = 3 * n;
        let weights = vec![1.0f64; n];
        let mut b = vec![0.0f32; k];
        let mut lhs = DMatrix::<f64>::zeros(k, k);
        let mut rhs = DVector::<f64>::zeros(k);
        let (mut au, mut av) = (vec![0.0f64; k], vec![0.0f64; k]);
        for _ in 0..iterations.max(1) {
            let cam = estimate_camera(&self.shape(&b), targets, &weights).ok()?;
            if k == 0 {
                break;
            }
            lhs.fill(0.0);
            rhs.fill(0.0);
            let (r0, r1) = (cam.rotation[0], cam.rotation[1]);
            for i in 0..n {
                let m = self.mean[i];
                let pm = cam.rotate([m[0] as f64, m[1] as f64, m[2] as f64]);
                let ru = targets[i][0] as f64 - (cam.scale * pm[0] + cam.tx);
                let rv = (cam.ty - targets[i][1] as f64) - cam.scale * pm[1];
                for q in 0..k {
                    let row = &self.basis[q * dim + 3 * i..q * dim + 3 * i + 3];
                    au[q] = cam.scale * (r0[0] * row[0] as f64 + r0[1] * row[1] as f64 + r0[2] * row[2] as f64);
                    av[q] = cam.scale * (r1[0] * row[0] as f64 + r1[1] * row[1] as f64 + r1[2] * row[2] as f64);
                }
                for p in 0..k {
                    rhs[p] += au[p] * ru + av[p] * rv;
                    for q in p..k {
                        lhs[(p, q)] += au[p] * au[q] + av[p] * av[q];
                    }
                }
            }
            for p in 0..k {
                lhs[(p, p)] += sigma_px * sigma_px / (self.eigenvalues[p] as f64).max(1e-9);
                for q in 0..p {
                    lhs[(p, q)] = lhs[(q, p)];
                }
            }
            let sol = lhs.clone().cholesky()?.solve(&rhs);
            for (q, slot) in b.iter_mut().enumerate() {
                let lim = self.constrain * self.eigenvalues[q].sqrt();
                *slot = (sol[q] as f32).clamp(-lim, lim);
            }
        }
        let camera = estimate_camera(&self.shape(&b), targets, &weights).ok()?;
        let points = self.project(&b, &camera);
        if points.iter().any(|p| !p[0].is_finite() || !p[1].is_finite()) {
            return None;
        }
        Some(Fit3d { camera, coefficients: b, points })
    }
}

/// |cos| between a vertex normal and the viewing direction below which the vertex is on the
/// occluding outline (as in the morph fit).
const OUTLINE_COSINE: f64 = 0.25;

/// The vertex of each jaw point (IMM 0–12; the chin's is fixed) on a face seen from the front.
pub type JawVertices = [u32; 13];

/// The session-1 jaw convention: every other vertex of the model contour (`sfm_model_contours.json`),
/// from each side's first to the chin. Measured: it puts the jaw's upper ends far above where IMM
/// annotators mark them (at the temples rather than near the ear lobes), see [`annotated_jaw_vertices`].
pub fn contour_jaw_vertices(fm: &FaceModel) -> JawVertices {
    let mut jaw = [0u32; 13];
    for (j, slot) in jaw.iter_mut().enumerate() {
        let (contour, k) = if j < 6 { (&fm.contour_image_left, 2 * j + 1) } else { (&fm.contour_image_right, 2 * (12 - j) + 1) };
        *slot = if j == 6 {
            fm.imm_vertices[6]
        } else {
            contour.get(k.min(contour.len().saturating_sub(1))).copied().unwrap_or(fm.imm_vertices[j])
        };
    }
    jaw
}

/// The IMM annotators' jaw convention on the mesh: for each jaw point, the vertex the 3DMM fit gave
/// it (nearest projected contour or outline vertex to the annotation) most often over the
/// near-frontal fits (|yaw| < 10°; all fits when fewer than 3 are); the contour rule when there
/// are no fits.
pub fn annotated_jaw_vertices(fm: &FaceModel, fits: &[&crate::morph::FittedFace]) -> JawVertices {
    let frontal: Vec<&&crate::morph::FittedFace> = fits.iter().filter(|f| f.pose.yaw.abs() < 10.0).collect();
    let used: Vec<&crate::morph::FittedFace> = if frontal.len() >= 3 { frontal.into_iter().copied().collect() } else { fits.to_vec() };
    let mut jaw = contour_jaw_vertices(fm);
    for (j, slot) in jaw.iter_mut().enumerate() {
        let mut counts: std::collections::BTreeMap<u32, usize> = std::collections::BTreeMap::new();
        for f in &used {
            *counts.entry(f.correspondence[j]).or_default() += 1;
        }
        // Most frequent; ties to the smaller id (deterministic).
        if let Some((&v, _)) = counts.iter().max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(a.0))) {
            *slot = v;
        }
    }
    jaw
}

/// The vertex of every IMM point as an annotator would see it through `camera`: internal points and
/// the chin at their fixed vertices; each other jaw point at its vertex of `jaw` while that vertex
/// faces the camera or lies on the occluding outline, otherwise (turned away) at the vertex of the occluding outline (cheek vertices with
/// |cos(normal, view)| < 0.25) whose projection is nearest to it. `vertex(v)` gives the shape's
/// vertex `v` (the normals are the mean shape's).
pub fn view_correspondence(fm: &FaceModel, vertex: &dyn Fn(u32) -> [f64; 3], camera: &Camera, jaw: &JawVertices) -> [u32; IMM_POINTS] {
    let mut corr = fm.imm_vertices;
    let r2 = camera.rotation[2];
    let facing = |v: u32| {
        let n = fm.mean_normals[v as usize];
        r2[0] * n[0] as f64 + r2[1] * n[1] as f64 + r2[2] * n[2] as f64
    };
    let proj = |v: u32| {
        let q = camera.project(vertex(v));
        [q[0], q[1]]
    };
    for (left, cheek) in [(true, &fm.cheek_image_left), (false, &fm.cheek_image_right)] {
        let outline: Vec<(u32, [f64; 2])> =
            cheek.iter().copied().filter(|&c| facing(c).abs() < OUTLINE_COSINE).map(|c| (c, proj(c))).collect();
        for j in JAW {
            if j == 6 || (j < 6) != left {
                continue;
            }
            let v = jaw[j];
            // Facing the camera, or itself on the outline: kept.
            if facing(v) > -OUTLINE_COSINE || outline.is_empty() {
                corr[j] = v;
                continue;
            }
            let t = proj(v);
            let best = outline.iter().min_by(|a, b| {
                let da = (a.1[0] - t[0]).powi(2) + (a.1[1] - t[1]).powi(2);
                let db = (b.1[0] - t[0]).powi(2) + (b.1[1] - t[1]).powi(2);
                da.total_cmp(&db)
            });
            corr[j] = best.map_or(v, |b| b.0);
        }
    }
    corr
}

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

/// Training settings.
#[derive(Debug, Clone)]
pub struct Asm3dTrainOptions {
    pub params: SearchParams,
    /// Yaw bin centres (thesis: 7 views, −45°…+45°).
    pub yaws: Vec<f32>,
    /// Random 3DMM shapes the 3D PDM is built from.
    pub pdm_shapes: usize,
    pub shape_variance: f64,
    pub constrain: f32,
    /// Principal components of the internal points' SIFT models (the jaw points use profiles; their
    /// SIFT models keep one component, unused by the search).
    pub sift_modes: usize,
    pub profile_ridge: f64,
    /// UV texture side for the synthetic renders.
    pub texture_size: usize,
    /// Largest relative gain of the horizontal illumination gradient on synthetic renders.
    pub lighting: f32,
    /// Renders train only the views with fewer real training photos than this (the others learn
    /// from their real photos alone); `usize::MAX`: every view gets renders. Default 40: only the
    /// frontal view (79 real photos of the 21 training persons, 109 of all 30; the next largest
    /// has 16/20) goes without. Measured on held-out persons, refined by C-ASM: frontal views mean
    /// d_eye 0.0178 → 0.0165 (C-ASM 0.0170), turned 0.0214 → 0.0218, spot light/free 0.0252 →
    /// 0.0260, all 0.0215 → 0.0214; real photos alone also for the ±30° views (threshold 10):
    /// turned 0.0227, and the view refinement lost turned photos.
    pub renders_below_real: usize,
    pub seed: u64,
}

impl Default for Asm3dTrainOptions {
    fn default() -> Self {
        Self {
            params: SearchParams::default(),
            yaws: (-3..=3).map(|k| 15.0 * k as f32).collect(),
            pdm_shapes: 300,
            shape_variance: 0.98,
            constrain: 3.0,
            sift_modes: 12,
            profile_ridge: 0.05,
            texture_size: 512,
            lighting: 0.3,
            renders_below_real: 40,
            seed: 7,
        }
    }
}

fn nearest_view(yaws: &[f32], yaw: f32) -> usize {
    let mut best = 0;
    for (i, &y) in yaws.iter().enumerate() {
        if (y - yaw).abs() < (yaws[best] - yaw).abs() {
            best = i;
        }
    }
    best
}

fn median(v: &mut [f32]) -> Option<f32> {
    v.sort_by(|a, b| a.total_cmp(b));
    if v.is_empty() { None } else { Some(v[v.len() / 2]) }
}

/// 3D PDMs for every yaw: `count` shapes drawn from the 3DMM (standard normal coefficients,
/// `seed`), their 58 points at the vertices an annotator would mark at that yaw. (Measured: giving
/// half of the shapes a random expression blendshape made the held-out mouth error worse.)
pub fn train_pdms(fm: &FaceModel, yaws: &[f32], jaw: &JawVertices, count: usize, variance: f64, constrain: f32, seed: u64) -> Vec<Pdm3d> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let m = fm.shape.component_count();
    let mut per_view: Vec<Vec<Vec<[f32; 3]>>> = vec![Vec::with_capacity(count); yaws.len()];
    for _ in 0..count {
        let alpha: Vec<f64> = (0..m).map(|_| rng.sample::<f64, _>(StandardNormal)).collect();
        let psi: [f64; 0] = [];
        // The vertices the correspondence can use, computed once per shape.
        let mut cache: std::collections::HashMap<u32, [f64; 3]> = std::collections::HashMap::new();
        for &v in fm
            .imm_vertices
            .iter()
            .chain(&fm.contour_image_left)
            .chain(&fm.contour_image_right)
            .chain(&fm.cheek_image_left)
            .chain(&fm.cheek_image_right)
            .chain(jaw)
        {
            cache.entry(v).or_insert_with(|| fm.vertex(v as usize, &alpha, &psi));
        }
        let vertex = |v: u32| cache.get(&v).copied().unwrap_or_else(|| fm.vertex(v as usize, &alpha, &psi));
        for (slot, &yaw) in per_view.iter_mut().zip(yaws) {
            let cam = Camera::from_pose(Pose { yaw, pitch: 0.0, roll: 0.0 }, 1.0, 0.0, 0.0);
            let corr = view_correspondence(fm, &vertex, &cam, jaw);
            slot.push(corr.iter().map(|&v| vertex(v)).map(|p| [p[0] as f32, p[1] as f32, p[2] as f32]).collect());
        }
    }
    per_view.iter().map(|shapes| Pdm3d::train(shapes, variance, constrain)).collect()
}

/// A synthetic training view: the render, its exact landmarks and the camera that made it.
pub struct SyntheticView {
    pub gray: GrayF32,
    pub points: Vec<Point>,
    pub camera: Camera,
}

/// Render a fitted, textured face at `pose` in an image of the photo's size, at the photo's scale,
/// with its landmark centroid where the photo's was; `gain` is the relative illumination change
/// from the face centre to one face-width to the right (a side light).
/// `jaw`: the jaw vertices on the face seen from the front ([`photo_jaw_vertices`]). `offsets`
/// (model mm, per IMM point) move each point from its vertex to where the photo's annotator put it
/// (see [`annotation_offsets`]); a jaw point gets its offset only while it keeps its vertex of
/// `jaw` (not when it moved to the occluding outline).
#[allow(clippy::too_many_arguments)]
pub fn synthesise_view(
    fm: &FaceModel,
    fit: &crate::morph::FittedFace,
    texture: &image::RgbaImage,
    pose: Pose,
    background: [u8; 3],
    gain: f32,
    jaw: &JawVertices,
    offsets: &[[f64; 3]],
) -> SyntheticView {
    let (w, h) = (fit.image_width as usize, fit.image_height as usize);
    let at = |v: u32| {
        let p = fit.vertices[v as usize];
        [p[0] as f64, p[1] as f64, p[2] as f64]
    };
    let mut camera = Camera::from_pose(pose, fit.camera.scale, 0.0, 0.0);
    let centre3: [f64; 3] = {
        let mut c = [0.0; 3];
        for &v in &fit.correspondence {
            let p = at(v);
            (0..3).for_each(|d| c[d] += p[d] / IMM_POINTS as f64);
        }
        c
    };
    let (was, now) = (fit.camera.project(centre3), camera.project(centre3));
    camera.tx += was[0] - now[0];
    camera.ty += was[1] - now[1];
    let projected = fm.project(&fit.vertices, &camera);
    let rgb = render::render_textured(&projected, &fm.shape.triangles, &fm.shape.texcoords, texture, w, h, background);
    let mut gray = GrayF32::from_rgb(&rgb);
    let corr = view_correspondence(fm, &at, &camera, jaw);
    let points: Vec<Point> = corr
        .iter()
        .enumerate()
        .map(|(i, &v)| {
            let mut p = at(v);
            if let Some(d) = offsets.get(i).filter(|_| !JAW.contains(&i) || v == jaw[i]) {
                (0..3).for_each(|k| p[k] += d[k]);
            }
            camera.project(p)
        })
        .map(|q| [q[0] as f32, q[1] as f32])
        .collect();
    if gain != 0.0 {
        let c = centroid(&points);
        let width = (fit.camera.scale * 140.0) as f32;
        for y in 0..h {
            for x in 0..w {
                let g = (1.0 + gain * (x as f32 - c[0]) / width).clamp(0.3, 1.7);
                let px = &mut gray.data[y * w + x];
                *px = (*px * g).clamp(0.0, 255.0);
            }
        }
    }
    SyntheticView { gray, points, camera }
}

/// The jaw vertices of a fitted training photo seen from the front: the fit's own (the vertex
/// nearest to the photo's annotation) where it is on the model contour, else (a point the fit put on
/// the occluding outline of a turned face: not where it would be from the front) the learnt
/// convention `annotated`; near-frontal photos (|yaw| < 10°) keep all of theirs.
pub fn photo_jaw_vertices(fm: &FaceModel, fit: &crate::morph::FittedFace, annotated: &JawVertices) -> JawVertices {
    let mut jaw = *annotated;
    for (j, slot) in jaw.iter_mut().enumerate() {
        let v = fit.correspondence[j];
        let contour = if j < 6 { &fm.contour_image_left } else { &fm.contour_image_right };
        if j == 6 || contour.contains(&v) || fit.pose.yaw.abs() < 10.0 {
            *slot = v;
        }
    }
    jaw
}

/// The annotation's offsets from the fitted model's points, lifted into model millimetres (in the
/// plane facing the photo's camera): the 3DMM cannot follow the IMM annotation convention exactly
/// (about 4 px RMS residual), and moving the synthetic landmarks by these offsets keeps the texture
/// models on the annotated positions rather than on the mapped vertices.
pub fn annotation_offsets(fm: &FaceModel, fit: &crate::morph::FittedFace, annotated: &[Point]) -> Vec<[f64; 3]> {
    let projected = fm.projected_landmarks(fit);
    let (r0, r1, s) = (fit.camera.rotation[0], fit.camera.rotation[1], fit.camera.scale.max(1e-9));
    projected
        .iter()
        .zip(annotated)
        .map(|(q, a)| {
            let (du, dv) = ((a[0] - q[0]) as f64 / s, -((a[1] - q[1]) as f64) / s);
            [du * r0[0] + dv * r1[0], du * r0[1] + dv * r1[1], du * r0[2] + dv * r1[2]]
        })
        .collect()
}

/// Mean colour of the photo's top-left corner (IMM: the plain studio background).
pub fn background_colour(rgb: &image::RgbImage) -> [u8; 3] {
    let n = 16.min(rgb.width()).min(rgb.height());
    let mut acc = [0u32; 3];
    for y in 0..n {
        for x in 0..n {
            let p = rgb.get_pixel(x, y).0;
            (0..3).for_each(|k| acc[k] += p[k] as u32);
        }
    }
    let count = (n * n).max(1);
    acc.map(|a| (a / count) as u8)
}

/// Per-view texture statistics accumulated during training.
struct ViewSamples {
    profiles: Vec<Vec<Vec<Vec<f32>>>>,
    sifts: Vec<Vec<Vec<Vec<f32>>>>,
    shapes: Vec<Vec<Point>>,
    real: usize,
    scale_per_width: Vec<f32>,
    dx: Vec<f32>,
    dy: Vec<f32>,
}

impl ViewSamples {
    fn new(levels: usize) -> ViewSamples {
        ViewSamples {
            profiles: vec![vec![Vec::new(); IMM_POINTS]; levels],
            sifts: vec![vec![Vec::new(); IMM_POINTS]; levels],
            shapes: Vec::new(),
            real: 0,
            scale_per_width: Vec::new(),
            dx: Vec::new(),
            dy: Vec::new(),
        }
    }

    /// Texture samples at `points` of `gray`, in the crop at the model's fixed scale.
    fn add(
        &mut self,
        gray: &GrayF32,
        points: &[Point],
        px_per_mm: f64,
        crop_px_per_mm: f32,
        params: &SearchParams,
        neighbours: &[[u16; 2]],
    ) {
        let frame = crop_frame(crop_px_per_mm / px_per_mm as f32, centroid(points), params.crop_size);
        let levels = pyramid(frame.crop(gray, params.crop_size), params.levels);
        let in_crop: Vec<Point> = points.iter().map(|&q| frame.to_crop(q)).collect();
        let mut nrm = Vec::new();
        for (l, lvl) in levels.iter().enumerate() {
            let pts: Vec<Point> = in_crop.iter().map(|&q| to_level(q, l)).collect();
            normals(&pts, neighbours, &mut nrm);
            for i in 0..IMM_POINTS {
                self.profiles[l][i].push(profile::profile(&lvl.image, pts[i], nrm[i]).to_vec());
                self.sifts[l][i].push(sift::descriptor(&lvl.gradients, pts[i], nrm[i]).to_vec());
            }
        }
        self.shapes.push(points.to_vec());
    }
}

/// The crop frame with `scale` crop pixels per image pixel and `centre` (image) in the middle.
fn crop_frame(scale: f32, centre: Point, crop_size: usize) -> Frame {
    let half = 0.5 * crop_size as f32;
    Frame { scale, origin: [centre[0] - half / scale, centre[1] - half / scale] }
}

/// Neighbours of each point on its contour, from the `.asf` connectivity.
fn neighbours(sample: &ImmSample) -> Result<Vec<[u16; 2]>, LandmarkError> {
    let shape = dataset::read_asf(&sample.asf, 1.0, 1.0).map_err(|e| LandmarkError::Training(e.to_string()))?;
    Ok(shape.points.iter().map(|p| [p.from.min(57) as u16, p.to.min(57) as u16]).collect())
}

/// A view's texture models (and its 2D shape models) from its samples, as a 2D C-ASM model.
fn view_textures(v: &ViewSamples, p: &SearchParams, neighbours: &[[u16; 2]], options: &Asm3dTrainOptions, info: &TrainInfo) -> AsmModel {
    let full = ShapeModel::train(&v.shapes, p.ref_width, options.shape_variance, options.constrain);
    let group = |range: std::ops::Range<usize>| {
        let sub: Vec<Vec<Point>> = v.shapes.iter().map(|s| s[range.clone()].to_vec()).collect();
        let (x0, x1) = full.mean[range].iter().fold((f32::MAX, f32::MIN), |(a, b), q| (a.min(q[0]), b.max(q[0])));
        ShapeModel::train(&sub, x1 - x0, options.shape_variance, options.constrain)
    };
    let (contour, internal) = (group(JAW), group(dataset::INTERNAL));
    let profiles = v.profiles.iter().map(|lv| lv.iter().map(|s| FullGaussian::train(s, options.profile_ridge)).collect()).collect();
    let sifts = v
        .sifts
        .iter()
        .map(|lv| {
            lv.iter().enumerate().map(|(i, s)| PcaGaussian::train(s, if JAW.contains(&i) { 1 } else { options.sift_modes })).collect()
        })
        .collect();
    AsmModel {
        format: super::MODEL_FORMAT,
        params: p.clone(),
        neighbours: neighbours.to_vec(),
        full,
        internal,
        contour,
        profiles,
        sifts,
        starts: Vec::new(),
        info: info.clone(),
    }
}

/// Mean C-ASM texture cost (SIFT for internal points, profiles for the jaw) of a view's own
/// samples on the coarsest level.
fn typical_cost(textures: &AsmModel, v: &ViewSamples) -> f32 {
    let top = textures.sifts.len() - 1;
    let n = v.shapes.len();
    let mut scratch = vec![0.0f32; sift::DESCRIPTOR_LEN];
    let mut total = 0.0f64;
    for k in 0..n {
        for i in 0..IMM_POINTS {
            total += if JAW.contains(&i) {
                textures.profiles[top][i].distance(&v.profiles[top][i][k])
            } else {
                textures.sifts[top][i].distance(&v.sifts[top][i][k], &mut scratch)
            } as f64;
        }
    }
    (total / n.max(1) as f64) as f32
}

/// Train the 3D-ASM on annotated IMM photos. `tick` is called once per photo.
pub fn train(
    samples: &[ImmSample],
    fm: &FaceModel,
    detector: Option<&Detector>,
    options: &Asm3dTrainOptions,
    tick: &dyn Fn(),
) -> Result<Asm3dModel, LandmarkError> {
    if samples.len() < 3 {
        return Err(LandmarkError::Training(format!("{} annotated photos; at least 3 are needed", samples.len())));
    }
    if options.yaws.is_empty() {
        return Err(LandmarkError::Training("no view bins".into()));
    }
    let p = &options.params;
    // The 3DMM fitted to every photo's annotation first: the fits' jaw vertices give the
    // annotators' jaw convention on the mesh, which the 3D PDMs and the renders follow.
    let mut fits: Vec<Option<crate::morph::FittedFace>> = Vec::with_capacity(samples.len());
    for sample in samples {
        let shape = sample.landmarks().map_err(|e| LandmarkError::Training(e.to_string()))?;
        let (w, h) = image::image_dimensions(&sample.image).map_err(|e| LandmarkError::Training(e.to_string()))?;
        fits.push(fm.fit(&shape, w, h).ok());
    }
    let jaw = annotated_jaw_vertices(fm, &fits.iter().flatten().collect::<Vec<_>>());
    let mut real_per_view = vec![0usize; options.yaws.len()];
    for f in fits.iter().flatten() {
        real_per_view[nearest_view(&options.yaws, f.pose.yaw)] += 1;
    }
    let mut pdms = train_pdms(fm, &options.yaws, &jaw, options.pdm_shapes.max(10), options.shape_variance, options.constrain, options.seed);
    // The crop scale: the frontal mean's x extent at the 2D models' reference width.
    let frontal = &pdms[nearest_view(&options.yaws, 0.0)];
    let (x0, x1) = frontal.mean.iter().fold((f32::MAX, f32::MIN), |(a, b), q| (a.min(q[0]), b.max(q[0])));
    let crop_px_per_mm = p.ref_width / (x1 - x0).max(1.0);
    let neighbours = neighbours(&samples[0])?;
    let mut views: Vec<ViewSamples> = options.yaws.iter().map(|_| ViewSamples::new(p.levels)).collect();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(options.seed ^ 0x5eed);
    let (mut misses, mut detected, mut failures) = (0usize, 0usize, 0usize);
    let mut annotation_boxes: Vec<(usize, f32, Rect, Point)> = Vec::new();
    // (view, fitted camera, annotation) of every real photo, for the start scale.
    let mut real_fits: Vec<(usize, Camera, Vec<Point>)> = Vec::new();
    let mut mean_offset = vec![[0.0f64; 3]; IMM_POINTS];
    let mut fitted_photos = 0usize;
    for (sample, fit) in samples.iter().zip(fits) {
        let photo = imaging::open(&sample.image).map_err(|e| LandmarkError::Training(e.to_string()))?;
        let shape = sample.landmarks().map_err(|e| LandmarkError::Training(e.to_string()))?;
        let Some(fit) = fit else {
            failures += 1;
            tick();
            continue;
        };
        // The photo itself trains the view of its fitted yaw, and places that view's start.
        let real_view = nearest_view(&options.yaws, fit.pose.yaw);
        views[real_view].add(&photo.gray, &shape, fit.camera.scale, crop_px_per_mm, p, &neighbours);
        views[real_view].real += 1;
        let c = centroid(&shape);
        annotation_boxes.push((real_view, fit.camera.scale as f32, super::train::annotation_box(&shape), c));
        real_fits.push((real_view, fit.camera, shape.clone()));
        if let Some(det) = detector {
            match super::train::detector_box(det, &photo.gray, &shape) {
                Some(b) => {
                    detected += 1;
                    let v = &mut views[real_view];
                    v.scale_per_width.push(fit.camera.scale as f32 / b.width);
                    v.dx.push((c[0] - b.center()[0]) / b.width);
                    v.dy.push((c[1] - b.center()[1]) / b.width);
                }
                None => misses += 1,
            }
        }
        let mut offsets = annotation_offsets(fm, &fit, &shape);
        let photo_jaw = photo_jaw_vertices(fm, &fit, &jaw);
        // A jaw point moved to the learnt vertex has no offset from it.
        for j in JAW.filter(|&j| photo_jaw[j] != fit.correspondence[j]) {
            offsets[j] = [0.0; 3];
        }
        for (acc, d) in mean_offset.iter_mut().zip(&offsets) {
            (0..3).for_each(|k| acc[k] += d[k]);
        }
        fitted_photos += 1;
        let texture = fm.extract_texture(&photo.rgb, &fit, options.texture_size);
        let background = background_colour(&photo.rgb);
        for (vi, &yaw) in options.yaws.iter().enumerate() {
            // Drawn for every view, so that leaving renders out does not change the others' lighting.
            let gain = options.lighting * (2.0 * rng.random::<f32>() - 1.0);
            if real_per_view[vi] >= options.renders_below_real {
                continue;
            }
            let pose = Pose { yaw, pitch: fit.pose.pitch, roll: 0.0 };
            let view = synthesise_view(fm, &fit, &texture, pose, background, gain, &photo_jaw, &offsets);
            views[vi].add(&view.gray, &view.points, view.camera.scale, crop_px_per_mm, p, &neighbours);
        }
        tick();
    }
    // The 3D PDMs' means follow the annotation convention too: the mean offset of the internal
    // points and the chin over the training photos.
    for pdm in pdms.iter_mut() {
        for (i, (m, d)) in pdm.mean.iter_mut().zip(&mean_offset).enumerate() {
            if fitted_photos > 0 && (!JAW.contains(&i) || i == 6) {
                (0..3).for_each(|k| m[k] += (d[k] / fitted_photos as f64) as f32);
            }
        }
    }
    let start_scales = start_scales(&pdms, &real_fits);
    let box_source = if detected >= 3 { BoxSource::Detector } else { BoxSource::Annotation };
    if box_source == BoxSource::Annotation {
        for v in views.iter_mut() {
            v.scale_per_width.clear();
            v.dx.clear();
            v.dy.clear();
        }
        for (vi, scale, b, c) in &annotation_boxes {
            let v = &mut views[*vi];
            v.scale_per_width.push(scale / b.width);
            v.dx.push((c[0] - b.center()[0]) / b.width);
            v.dy.push((c[1] - b.center()[1]) / b.width);
        }
    }
    // Placements: the view's own photos when it has 3 or more, else the nearest view that has.
    let own: Vec<Option<Placement>> = views
        .iter_mut()
        .map(|v| {
            if v.scale_per_width.len() < 3 {
                return None;
            }
            Some(Placement { scale_per_width: median(&mut v.scale_per_width)?, dx: median(&mut v.dx)?, dy: median(&mut v.dy)? })
        })
        .collect();
    if own.iter().all(|o| o.is_none()) {
        return Err(LandmarkError::Training("no view has 3 photos with a face box".into()));
    }
    let mut persons: Vec<u32> = samples.iter().map(|s| s.person).collect();
    persons.dedup();
    let info = TrainInfo { images: samples.len(), persons: persons.clone(), box_source, detector_misses: misses };
    let mut out_views = Vec::with_capacity(views.len());
    for (vi, (v, pdm)) in views.into_iter().zip(pdms).enumerate() {
        if v.shapes.len() < 3 {
            return Err(LandmarkError::Training(format!("view {} has {} training shapes", options.yaws[vi], v.shapes.len())));
        }
        let placement = (0..own.len())
            .filter_map(|k| own[k].map(|pl| (k.abs_diff(vi), pl)))
            .min_by_key(|(d, _)| *d)
            .map(|(_, pl)| pl)
            .expect("one view has a placement");
        let textures = view_textures(&v, p, &neighbours, options, &info);
        let typical_cost = typical_cost(&textures, &v);
        out_views.push(View3d {
            yaw: options.yaws[vi],
            pdm,
            textures,
            placement,
            start_scale: start_scales[vi],
            samples: v.shapes.len(),
            real_photos: v.real,
            typical_cost,
        });
    }
    Ok(Asm3dModel {
        format: ASM3D_FORMAT,
        params: p.clone(),
        crop_px_per_mm,
        sigma_px: 4.0,
        views: out_views,
        info: Asm3dInfo {
            photos: samples.len(),
            persons,
            box_source,
            detector_misses: misses,
            fit_failures: failures,
            pdm_shapes: options.pdm_shapes,
            seed: options.seed,
        },
    })
}

/// The 58 points found by the 3D-ASM, with the fitted head pose.
#[derive(Debug, Clone)]
pub struct Asm3dLandmarks {
    pub points: Vec<Point>,
    pub keypoints: KeyPoints,
    /// Pose of the fitted 3D shape (degrees, the morph module's convention).
    pub pose: Pose,
    /// Yaw of the view whose texture models were used last.
    pub view_yaw: f32,
}

/// The trained 3D-ASM, shareable across threads.
pub struct Asm3dLandmarker {
    pub model: Asm3dModel,
}

/// Distinct views whose best start is searched on the coarse level (measured with the start
/// scale and 2 probe iterations, 0.2 minimum-face boxes: 3 views against 2 lifted held-out
/// d_eye < 0.05 from 94.4% to 96.3% and mouth < 0.1 from 96.3% to 98.1% for ≈ 1.8 ms in the dev
/// profile; with 1 probe iteration 3 views were worse than 2; 1 view lost frontal and spot-light
/// photos in session 1).
const SEARCHED_VIEWS: usize = 3;

/// Coarse-level iterations each searched view gets before the best one goes on (measured with the
/// start scale: 2 against 1 lifted held-out d_eye < 0.05 from 90.7% to 94.4%, turned views from
/// 83.3% to 94.4%, for ≈ 0.8 ms).
const PROBE_ITERATIONS: usize = 2;

/// The starts are ranked on every other point (measured: same held-out accuracy as all points at
/// half the ranking time, 2.5 ms against 4.9).
const RANK_POINT_STEP: usize = 2;

/// Per view, the median ratio of the least-squares scale of the view's PDM mean onto a real
/// photo's annotation (under the photo's fitted rotation) to the photo's fitted camera scale; views
/// with fewer than 3 real photos take the nearest view's that has, 1 when none has.
fn start_scales(pdms: &[Pdm3d], real_fits: &[(usize, Camera, Vec<Point>)]) -> Vec<f32> {
    let mut ratios: Vec<Vec<f32>> = vec![Vec::new(); pdms.len()];
    for (view, camera, shape) in real_fits {
        let unit = Camera { scale: 1.0, tx: 0.0, ty: 0.0, ..*camera };
        let mean = pdms[*view].project(&vec![0.0; pdms[*view].modes()], &unit);
        let (qc, ac) = (centroid(&mean), centroid(shape));
        let (mut num, mut den) = (0.0f64, 0.0f64);
        for (q, a) in mean.iter().zip(shape) {
            let (qx, qy) = ((q[0] - qc[0]) as f64, (q[1] - qc[1]) as f64);
            num += qx * (a[0] - ac[0]) as f64 + qy * (a[1] - ac[1]) as f64;
            den += qx * qx + qy * qy;
        }
        let ratio = num / den / camera.scale;
        if den > 0.0 && ratio.is_finite() && ratio > 0.0 {
            ratios[*view].push(ratio as f32);
        }
    }
    let own: Vec<Option<f32>> = ratios.iter_mut().map(|r| if r.len() >= 3 { median(r) } else { None }).collect();
    (0..pdms.len())
        .map(|vi| (0..own.len()).filter_map(|k| own[k].map(|r| (k.abs_diff(vi), r))).min_by_key(|(d, _)| *d).map_or(1.0, |(_, r)| r))
        .collect()
}

/// |yaw| (degrees) of the C-ASM's points ([`Asm3dLandmarker::yaw_of`]) from which the service uses
/// the 3D-ASM (refined by the C-ASM) instead. The crossover measured on renders of held-out faces
/// (`facegate eval landmarks`, `eval::landmarks::crossover`) is at a true |yaw| of 15°: from there
/// on the 3D-ASM has a mean d_eye at least 5% lower and as many d_eye < 0.1; at 0° they are
/// equal. But the C-ASM's points understate the turn (a true 15° gives 5–8°, 45° gives 35–38°, or
/// 8–15° where the C-ASM collapsed to a frontal shape), so the threshold on their yaw is lower:
/// measured d_eye < 0.1 of the switch on the 45° renders 76.6% with 15°, 90.6% with 10°, 93.8%
/// with 5° (the 3D-ASM on every face: 93.8%); held-out IMM photos mean d_eye 0.0213 / 0.0214 /
/// 0.0212 (C-ASM alone 0.0218), frontal views 0.0170 / 0.0170 / 0.0169 (C-ASM 0.0170).
pub const SERVICE_MIN_YAW: f32 = 5.0;

/// Views seeded from the C-ASM's points in the switched path ([`Asm3dLandmarker::fit_seeded`]):
/// the nearest to their yaw and the next on the turned side, each probed with
/// `PROBE_ITERATIONS`, the better one iterated on (measured, held-out views 3–4 mean d_eye /
/// d_eye < 0.05: 1 view 0.0226 / 94.4%; 2 views fully iterated 0.0225 / 94.4%; 2 views probed
/// 0.0218 / 94.4%; the blind search 0.0218 / 100%).
const SEEDED_VIEWS: usize = 2;

/// The 2D model that refines the 3D search's coarse result (coarse to fine, `search::search_levels`).
#[derive(Debug, Clone, Copy)]
pub enum Refinement<'a> {
    /// The chosen view's 2D C-ASM: its texture models under its 2D shape models, trained on the
    /// view's real photos and renders.
    View,
    /// A 2D C-ASM (the service's, trained on real photos of all views) from the 3D result.
    Casm(&'a AsmModel),
}

/// The search state: current view, points (level-0 crop pixels) and the last 3D fit.
struct State {
    view: usize,
    points: Vec<Point>,
    camera: Camera,
}

impl Asm3dLandmarker {
    pub fn load(path: &Path) -> Result<Asm3dLandmarker, LandmarkError> {
        let err = |message: String| LandmarkError::Model { path: path.display().to_string(), message };
        let model: Asm3dModel = crate::config::read_model(path, "3D-ASM model", ASM3D_FORMAT, "facegate train asm3d").map_err(err)?;
        let ok = !model.views.is_empty()
            && model.views.iter().all(|v| {
                v.pdm.points() == IMM_POINTS
                    && v.textures.neighbours.len() == IMM_POINTS
                    && v.textures.sifts.len() == model.params.levels.max(1)
                    && v.textures.profiles.len() == model.params.levels.max(1)
                    && v.textures.sifts.iter().all(|l| l.len() == IMM_POINTS)
                    && v.textures.profiles.iter().all(|l| l.len() == IMM_POINTS)
            });
        if !ok {
            return Err(err("the model does not have 58 points and a texture model per level in every view".into()));
        }
        Ok(Asm3dLandmarker { model })
    }

    pub fn save(&self, path: &Path) -> Result<(), LandmarkError> {
        crate::config::write_model(path, &self.model).map_err(|message| LandmarkError::Model { path: path.display().to_string(), message })
    }

    fn yaws(&self) -> Vec<f32> {
        self.model.views.iter().map(|v| v.yaw).collect()
    }

    /// Start shapes (level-0 crop pixels): every view's mean, upright and tilted ±`roll_start`.
    fn starts(&self, face: &Rect, frame: &Frame) -> Vec<State> {
        let m = &self.model;
        let roll = m.params.roll_start;
        let front = nearest_view(&self.yaws(), 0.0);
        let reference = m.views[front].placement.scale_per_width;
        let mut out = Vec::new();
        for (vi, view) in m.views.iter().enumerate() {
            let pl = &view.placement;
            let scale = (m.crop_px_per_mm * pl.scale_per_width / reference.max(1e-9) * view.start_scale) as f64;
            let c = face.center();
            let target = frame.to_crop([c[0] + pl.dx * face.width, c[1] + pl.dy * face.width]);
            // Tilted starts for every view (measured: with tilts for the frontal view only, two
            // more turned held-out photos failed).
            let rolls: &[f32] = if roll > 0.0 { &[0.0, 1.0, -1.0] } else { &[0.0] };
            for &r in rolls {
                let mut camera = Camera::from_pose(Pose { yaw: view.yaw, pitch: 0.0, roll: r * roll }, scale, 0.0, 0.0);
                let zero = vec![0.0f32; view.pdm.modes()];
                let pts = view.pdm.project(&zero, &camera);
                let got = centroid(&pts);
                camera.tx += (target[0] - got[0]) as f64;
                camera.ty += (target[1] - got[1]) as f64;
                out.push(State { view: vi, points: view.pdm.project(&zero, &camera), camera });
            }
        }
        out
    }

    /// One iteration on `level`: candidates by the current view's textures, 3D fit, view from its
    /// yaw (refitted with that view's PDM when it changed). Returns the texture cost and whether
    /// the configured share of points moved less than a (level) pixel.
    fn iterate(&self, levels: &[Level], level: usize, st: &mut State, ws: &mut Workspace, suggested: &mut Vec<Point>) -> (f32, bool) {
        let m = &self.model;
        let at_level: Vec<Point> = st.points.iter().map(|&p| to_level(p, level)).collect();
        let cost = search::suggest(&m.views[st.view].textures, &levels[level], level, &at_level, Variant::Casm, ws, suggested);
        let targets: Vec<Point> = suggested.iter().map(|&p| from_level(p, level)).collect();
        let Some(mut fit) = m.views[st.view].pdm.fit(&targets, m.sigma_px as f64, 4) else { return (cost, true) };
        let view = nearest_view(&self.yaws(), fit.camera.pose().yaw);
        if view != st.view {
            if let Some(f) = m.views[view].pdm.fit(&targets, m.sigma_px as f64, 4) {
                fit = f;
                st.view = view;
            }
        }
        let pixel = (1 << level) as f32;
        let still = fit.points.iter().zip(&st.points).filter(|(a, b)| crate::geometry::distance(**a, **b) < pixel).count();
        st.points = fit.points;
        st.camera = fit.camera;
        (cost, still as f32 >= m.params.converged_share * IMM_POINTS as f32)
    }

    /// Search the 58 points of the face in `face` (the detector's box), refined by the chosen
    /// view's own 2D model. Never panics: degenerate boxes fall back to the whole image, tiny
    /// images give the placed frontal mean.
    pub fn fit(&self, gray: &GrayF32, face: &Rect) -> Asm3dLandmarks {
        self.fit_with(gray, face, Refinement::View)
    }

    /// Head yaw (degrees, the morph module's sign) of 58 points in image pixels: the frontal view's
    /// 3D PDM fitted to them. `None` for degenerate points.
    pub fn yaw_of(&self, points: &[Point]) -> Option<f32> {
        let m = &self.model;
        let view = &m.views[nearest_view(&self.yaws(), 0.0)];
        // The PDM's prior σ is in crop pixels: fit in the crop's scale.
        let c = centroid(points);
        let scale = {
            let (x0, x1) = points.iter().fold((f32::MAX, f32::MIN), |(a, b), q| (a.min(q[0]), b.max(q[0])));
            m.params.ref_width / (x1 - x0).max(1e-3)
        };
        let local: Vec<Point> = points.iter().map(|p| [scale * (p[0] - c[0]), scale * (p[1] - c[1])]).collect();
        view.pdm.fit(&local, m.sigma_px as f64, 4).map(|f| f.camera.pose().yaw)
    }

    /// The service's landmarks: the C-ASM's (`casm`, already searched by `landmarker` in `face`)
    /// while their [`yaw_of`](Self::yaw_of) is below `min_yaw` degrees, else the 3D-ASM's seeded by
    /// them and refined by the C-ASM ([`fit_seeded`](Self::fit_seeded)). Returns the points and
    /// whether the 3D-ASM was used.
    pub fn switch(
        &self,
        gray: &GrayF32,
        face: &Rect,
        landmarker: &super::Landmarker,
        casm: super::Landmarks,
        min_yaw: f32,
    ) -> (super::Landmarks, bool) {
        match self.yaw_of(&casm.points) {
            Some(yaw) if yaw.abs() >= min_yaw => {
                let r = self.fit_seeded(gray, face, &casm.points, &landmarker.model);
                (super::Landmarks { points: r.points, keypoints: r.keypoints }, true)
            }
            _ => (casm, false),
        }
    }

    /// The search's box (degenerate boxes replaced by the whole image) and crop frame.
    fn search_frame(&self, gray: &GrayF32, face: &Rect) -> (Rect, Frame) {
        let m = &self.model;
        let finite = face.x.is_finite() && face.y.is_finite() && face.width.is_finite() && face.height.is_finite();
        let face = if finite && face.width >= 1.0 && face.height >= 1.0 && face.width < 1e6 {
            *face
        } else {
            Rect::new(0.0, 0.0, gray.width.max(1) as f32, gray.height.max(1) as f32)
        };
        let front = nearest_view(&self.yaws(), 0.0);
        let pl = &m.views[front].placement;
        let px_per_mm = (pl.scale_per_width * face.width).max(1e-6);
        let c = face.center();
        let frame = crop_frame(m.crop_px_per_mm / px_per_mm, [c[0] + pl.dx * face.width, c[1] + pl.dy * face.width], m.params.crop_size);
        (face, frame)
    }

    /// The 3D-ASM seeded by the C-ASM's result (`casm_points`, image pixels, found in `face` by
    /// the C-ASM `casm`), refined by that C-ASM: the service's switched path. Instead of ranking
    /// every view's start and probing three views ([`fit_with`](Self::fit_with)), the 3D PDMs of
    /// the view nearest the C-ASM points' yaw and of the next view on the turned side are fitted to
    /// those points, each probed on the coarse level, and the one with the lower texture cost is
    /// iterated on and refined by the C-ASM coarse to fine. Falls back to [`fit_with`](Self::fit_with) when the
    /// points are unusable.
    pub fn fit_seeded(&self, gray: &GrayF32, face: &Rect, casm_points: &[Point], casm: &AsmModel) -> Asm3dLandmarks {
        let m = &self.model;
        let blind = || self.fit_with(gray, face, Refinement::Casm(casm));
        if gray.width < 2 || gray.height < 2 || gray.data.len() != gray.width * gray.height || casm_points.len() != IMM_POINTS {
            return blind();
        }
        let (_, frame) = self.search_frame(gray, face);
        let seed: Vec<Point> = casm_points.iter().map(|&p| frame.to_crop(p)).collect();
        let yaws = self.yaws();
        let sigma = m.sigma_px as f64;
        let Some(yaw) = m.views[nearest_view(&yaws, 0.0)].pdm.fit(&seed, sigma, 4).map(|f| f.camera.pose().yaw) else { return blind() };
        // The view nearest the seed's yaw and, since the C-ASM's points understate the turn, the
        // next view on the turned side.
        let near = nearest_view(&yaws, yaw);
        let mut views = vec![near];
        if SEEDED_VIEWS > 1 {
            let turned = (0..yaws.len())
                .filter(|&v| v != near && (yaws[v] - yaws[near]) * yaw.signum() > 0.0)
                .min_by(|&a, &b| (yaws[a] - yaws[near]).abs().total_cmp(&(yaws[b] - yaws[near]).abs()));
            views.extend(turned);
        }
        let levels = pyramid(frame.crop(gray, m.params.crop_size), m.params.levels);
        let mut ws = Workspace::default();
        let probe = views.len() > 1;
        let seeded: Vec<State> = views
            .into_iter()
            .filter_map(|vi| m.views[vi].pdm.fit(&seed, sigma, 4).map(|fit| State { view: vi, points: fit.points, camera: fit.camera }))
            .collect();
        // As the blind search: `PROBE_ITERATIONS` per seeded view, the rest of `max_iterations`
        // for the better one (measured, held-out views 3–4 mean d_eye: every seeded view iterated
        // to `max_iterations` 0.0225, to 2 only 0.0227, probed 0.0218).
        let Some(st) = self.search_coarse(&levels, seeded, probe, &mut ws) else { return blind() };
        self.refine(&levels, &frame, st, casm, &mut ws)
    }

    /// [`fit`](Self::fit) with the 2D model of the refinement stage chosen by `refinement`.
    pub fn fit_with(&self, gray: &GrayF32, face: &Rect, refinement: Refinement) -> Asm3dLandmarks {
        let m = &self.model;
        let (face, frame) = self.search_frame(gray, face);
        let front = nearest_view(&self.yaws(), 0.0);
        let mut states = self.starts(&face, &frame);
        let finish = |st: &State| {
            let points: Vec<Point> = st.points.iter().map(|&p| frame.to_image(p)).collect();
            let keypoints = KeyPoints::from_imm(&points);
            Asm3dLandmarks { points, keypoints, pose: st.camera.pose(), view_yaw: m.views[st.view].yaw }
        };
        if gray.width < 2 || gray.height < 2 || gray.data.len() != gray.width * gray.height {
            let k = states.iter().position(|st| st.view == front).unwrap_or(0);
            return finish(&states.swap_remove(k));
        }
        let levels = pyramid(frame.crop(gray, m.params.crop_size), m.params.levels);
        let mut ws = Workspace::default();
        // Rank the starts by the texture cost where they stand under their own view's models,
        // less that view's typical cost on its training samples.
        let mut ranked: Vec<(f32, State)> = states.into_iter().map(|st| (self.ranking_cost(&levels, &st, &mut ws), st)).collect();
        ranked.sort_by(|a, b| a.0.total_cmp(&b.0));
        // The best starts of the `SEARCHED_VIEWS` best-ranked distinct views are searched on the
        // coarse level; the one with the lowest cost where it converged goes on.
        let mut chosen: Vec<State> = Vec::new();
        for (_, st) in ranked {
            if chosen.len() < SEARCHED_VIEWS && chosen.iter().all(|c| c.view != st.view) {
                chosen.push(st);
            }
        }
        let Some(st) = self.search_coarse(&levels, chosen, true, &mut ws) else {
            return finish(&self.starts(&face, &frame).swap_remove(0));
        };
        // Refinement: the 3D search gives the view and a shape on the coarse level; the view's 2D
        // C-ASM (its texture models under its 2D shape models, trained on the view's real and
        // synthetic shapes, so annotation-convention variation is in them) searches coarse to fine
        // from there. Measured: the 3D PDM alone on the fine level left the points ≈ 4 px off the
        // annotation convention (mean d_eye 0.040 → 0.027); a fine-level-only refinement helped
        // half as much.
        // Measured alternatives to refining in the 3D search's crop (held-out, dev): the C-ASM
        // from the 3D result and its own box-placed starts, cost-ranked: identical (the 3D start
        // always won); the C-ASM in a new crop at its training scale from the 3D result: mean
        // d_eye 0.0216 against 0.0215, d_eye < 0.05 96.3% against 100%.
        let model2d = match refinement {
            Refinement::View => &m.views[st.view].textures,
            Refinement::Casm(casm) => casm,
        };
        self.refine(&levels, &frame, st, model2d, &mut ws)
    }

    /// The texture cost of `st` on the coarse level under its own view's models (every
    /// `RANK_POINT_STEP`-th point), less that view's typical cost for as many points: how the
    /// starts and the probed views are ranked.
    fn ranking_cost(&self, levels: &[Level], st: &State, ws: &mut Workspace) -> f32 {
        let top = levels.len() - 1;
        let pts: Vec<Point> = st.points.iter().map(|&p| to_level(p, top)).collect();
        let view = &self.model.views[st.view];
        let cost = search::texture_cost(&view.textures, &levels[top], top, &pts, RANK_POINT_STEP, Variant::Casm, ws);
        // The typical cost is over all points: scale it to the points ranked on.
        cost - view.typical_cost * pts.len().div_ceil(RANK_POINT_STEP) as f32 / IMM_POINTS as f32
    }

    /// The 3D search on the coarse level from `candidates`: with `probe`, each gets
    /// `PROBE_ITERATIONS` and the one with the lowest [`ranking_cost`](Self::ranking_cost) then
    /// goes on to `max_iterations`; without, the first is iterated to `max_iterations` at once.
    /// `None` without candidates.
    fn search_coarse(&self, levels: &[Level], candidates: Vec<State>, probe: bool, ws: &mut Workspace) -> Option<State> {
        let max = self.model.params.max_iterations;
        let top = levels.len() - 1;
        let mut suggested = Vec::with_capacity(IMM_POINTS);
        let mut run = |st: &mut State, iterations: std::ops::Range<usize>, ws: &mut Workspace| {
            for _ in iterations {
                if self.iterate(levels, top, st, ws, &mut suggested).1 {
                    break;
                }
            }
        };
        if !probe {
            let mut st = candidates.into_iter().next()?;
            run(&mut st, 0..max, ws);
            return Some(st);
        }
        let mut best: Option<(f32, State)> = None;
        for mut st in candidates {
            run(&mut st, 0..PROBE_ITERATIONS.min(max), ws);
            let cost = self.ranking_cost(levels, &st, ws);
            if best.as_ref().is_none_or(|b| cost < b.0) {
                best = Some((cost, st));
            }
        }
        let (_, mut st) = best?;
        run(&mut st, PROBE_ITERATIONS..max, ws);
        Some(st)
    }

    /// `st` refined coarse to fine by the 2D model `model2d` (`search::search_levels`), the pose
    /// from its view's 3D PDM fitted to the refined points, in image pixels.
    fn refine(&self, levels: &[Level], frame: &Frame, mut st: State, model2d: &AsmModel, ws: &mut Workspace) -> Asm3dLandmarks {
        let view = &self.model.views[st.view];
        st.points = search::search_levels(model2d, levels, &[st.points.clone()], Variant::Casm, ws);
        // The pose reported is the 3D PDM's fitted to the refined points.
        if let Some(fit) = view.pdm.fit(&st.points, self.model.sigma_px as f64, 4) {
            st.camera = fit.camera;
        }
        let points: Vec<Point> = st.points.iter().map(|&p| frame.to_image(p)).collect();
        let keypoints = KeyPoints::from_imm(&points);
        Asm3dLandmarks { points, keypoints, pose: st.camera.pose(), view_yaw: view.yaw }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::list_imm;
    use std::sync::OnceLock;

    fn face_model() -> &'static FaceModel {
        static M: OnceLock<FaceModel> = OnceLock::new();
        M.get_or_init(|| FaceModel::load(&crate::config::sfm_dir()).expect("the Surrey Face Model"))
    }

    #[test]
    fn pdm3d_recovers_a_projected_model_shape_and_pose() {
        let fm = face_model();
        let pdms = train_pdms(fm, &[0.0, 30.0], &contour_jaw_vertices(fm), 120, 0.98, 3.0, 3);
        let pdm = &pdms[1];
        assert!(pdm.modes() >= 5 && pdm.modes() < 100, "{} modes", pdm.modes());
        // A shape inside the model at a known pose is fitted back: pose within 2°, points within 1.5 px (the prior shrinks the coefficients a little).
        let b: Vec<f32> = pdm
            .eigenvalues
            .iter()
            .enumerate()
            .map(|(k, l)| if k < 4 { 0.8 * l.sqrt() * if k % 2 == 0 { 1.0 } else { -1.0 } } else { 0.0 })
            .collect();
        let cam = Camera::from_pose(Pose { yaw: 28.0, pitch: 4.0, roll: -6.0 }, 2.0, 200.0, 180.0);
        let target = pdm.project(&b, &cam);
        let fit = pdm.fit(&target, 0.5, 10).unwrap();
        let pose = fit.camera.pose();
        assert!((pose.yaw - 28.0).abs() < 2.0 && (pose.pitch - 4.0).abs() < 2.0 && (pose.roll + 6.0).abs() < 2.0, "{pose:?}");
        let worst = fit.points.iter().zip(&target).map(|(a, b)| crate::geometry::distance(*a, *b)).fold(0.0, f32::max);
        assert!(worst < 1.5, "worst point error {worst} px (face about 280 px wide)");
        // Degenerate targets give None, not a panic.
        assert!(pdm.fit(&vec![[1.0, 1.0]; IMM_POINTS], 1.0, 3).is_none());
        assert!(pdm.fit(&vec![[f32::NAN, 1.0]; IMM_POINTS], 1.0, 3).is_none());
        assert!(pdm.fit(&target[..10], 1.0, 3).is_none());
    }

    #[test]
    fn jaw_follows_the_outline_as_the_head_turns() {
        // At yaw +40° (nose to the image right) the image-right jaw points leave the frontal contour
        // for the occluding outline, which projects further out than the frontal contour vertex.
        let fm = face_model();
        let at = |v: u32| fm.vertex(v as usize, &[], &[]);
        let jaw = contour_jaw_vertices(fm);
        let frontal = view_correspondence(fm, &at, &Camera::from_pose(Pose::default(), 1.0, 0.0, 0.0), &jaw);
        let cam = Camera::from_pose(Pose { yaw: 40.0, pitch: 0.0, roll: 0.0 }, 1.0, 0.0, 0.0);
        let turned = view_correspondence(fm, &at, &cam, &jaw);
        assert_eq!(frontal[13..], turned[13..]);
        let moved: Vec<usize> = (7..13).filter(|&j| turned[j] != frontal[j]).collect();
        assert!(!moved.is_empty(), "no image-right jaw point moved");
        for j in moved {
            let (a, b) = (cam.project(at(frontal[j])), cam.project(at(turned[j])));
            assert!(b[0] > a[0] - 1.0, "jaw {j}: outline at x {} inside the contour vertex at {}", b[0], a[0]);
        }
    }

    #[test]
    fn learnt_jaw_vertices_follow_the_annotation() {
        // Frontal photos of training persons: the jaw at the learnt vertices of each photo's fitted
        // shape is near the annotated jaw; the contour rule of session 1 was far above it.
        let fm = face_model();
        let samples: Vec<ImmSample> = list_imm(&crate::config::shared_dir().join("data/imm"))
            .unwrap()
            .into_iter()
            .filter(|s| s.view == 1 && !dataset::imm_is_test_person(s.person))
            .take(8)
            .collect();
        let shapes: Vec<Vec<Point>> = samples.iter().map(|s| s.landmarks().unwrap()).collect();
        let fits: Vec<crate::morph::FittedFace> = shapes.iter().map(|p| fm.fit(p, 640, 480).unwrap()).collect();
        let learnt = annotated_jaw_vertices(fm, &fits.iter().collect::<Vec<_>>());
        let contour = contour_jaw_vertices(fm);
        let error = |jaw: &JawVertices| {
            let mut total = 0.0;
            for (fit, truth) in fits.iter().zip(&shapes) {
                let k = KeyPoints::from_imm(truth);
                let eyes = crate::geometry::distance(k.left_eye, k.right_eye);
                for j in JAW {
                    let p = fit.vertices[jaw[j] as usize];
                    let q = fit.camera.project([p[0] as f64, p[1] as f64, p[2] as f64]);
                    total += crate::geometry::distance([q[0] as f32, q[1] as f32], truth[j]) / eyes;
                }
            }
            total / (fits.len() * JAW.len()) as f32
        };
        let (e_learnt, e_contour) = (error(&learnt), error(&contour));
        eprintln!("jaw error / eye distance: learnt {e_learnt:.3}, contour rule {e_contour:.3}");
        assert!(e_learnt < 0.1 && e_learnt < 0.5 * e_contour, "learnt {e_learnt:.3}, contour rule {e_contour:.3}");
        assert_eq!(learnt[6], fm.imm_vertices[6]);
    }

    #[test]
    fn synthetic_views_put_the_landmarks_on_the_rendered_face() {
        // The rendered eye region is darker than the cheeks in a grey render; simpler and stronger:
        // the landmark positions move the right way with yaw, and the face is drawn where they are.
        let fm = face_model();
        let s =
            list_imm(&crate::config::shared_dir().join("data/imm")).unwrap().into_iter().find(|s| s.person == 7 && s.view == 1).unwrap();
        let photo = imaging::open(&s.image).unwrap();
        let shape = s.landmarks().unwrap();
        let fit = fm.fit(&shape, photo.width(), photo.height()).unwrap();
        let texture = fm.extract_texture(&photo.rgb, &fit, 128);
        let bg = [0u8, 0, 0];
        let jaw = photo_jaw_vertices(fm, &fit, &contour_jaw_vertices(fm));
        let left = synthesise_view(fm, &fit, &texture, Pose { yaw: -30.0, pitch: 0.0, roll: 0.0 }, bg, 0.0, &jaw, &[]);
        let right = synthesise_view(fm, &fit, &texture, Pose { yaw: 30.0, pitch: 0.0, roll: 0.0 }, bg, 0.0, &jaw, &[]);
        // With the annotation offsets, the frontal re-render at the photo's own pose puts every
        // point, the jaw included (a frontal photo keeps its fitted jaw vertices), back on the
        // annotation.
        let offsets = annotation_offsets(fm, &fit, &shape);
        let same = synthesise_view(fm, &fit, &texture, fit.pose, bg, 0.0, &jaw, &offsets);
        for i in 0..58 {
            assert!(crate::geometry::distance(same.points[i], shape[i]) < 0.5, "point {i}: {:?} vs {:?}", same.points[i], shape[i]);
        }
        // Nose tip (IMM 52 lies on the nose ridge/tip region) moves to the image right with positive yaw.
        let nose = |v: &SyntheticView| centroid(&v.points[dataset::NOSE]);
        assert!(nose(&right)[0] > nose(&left)[0] + 10.0);
        for v in [&left, &right] {
            // Every internal landmark is on the rendered face (not the black background).
            for p in &v.points[13..] {
                assert!(v.gray.sample(p[0], p[1]) > 5.0, "landmark {p:?} off the render");
            }
            // The fit of the 3DMM to the synthetic landmarks gives back the rendered yaw.
            let back = fm.fit(&v.points, photo.width(), photo.height()).unwrap();
            let want = v.camera.pose().yaw;
            assert!((back.pose.yaw - want).abs() < 5.0, "rendered at {want}, fitted {}", back.pose.yaw);
        }
    }

    #[test]
    fn small_model_round_trips_and_survives_degenerate_input() {
        let fm = face_model();
        let samples: Vec<ImmSample> = list_imm(&crate::config::shared_dir().join("data/imm"))
            .unwrap()
            .into_iter()
            .filter(|s| s.person == 4 || s.person == 6)
            .collect();
        let options = Asm3dTrainOptions { pdm_shapes: 40, texture_size: 128, ..Default::default() };
        let model = train(&samples, fm, None, &options, &|| {}).unwrap();
        assert_eq!(model.views.len(), 7);
        assert_eq!(model.info.box_source, BoxSource::Annotation);
        let lm = Asm3dLandmarker { model };
        let dir = std::env::temp_dir().join(format!("facegate-asm3d-{}", std::process::id()));
        let path = dir.join("asm3d.bin");
        lm.save(&path).unwrap();
        let back = Asm3dLandmarker::load(&path).unwrap();
        assert_eq!(back.model.views[3].pdm.mean, lm.model.views[3].pdm.mean);
        std::fs::write(&path, b"not a model").unwrap();
        assert!(matches!(Asm3dLandmarker::load(&path), Err(LandmarkError::Model { .. })));
        std::fs::remove_dir_all(&dir).unwrap();
        // A training photo searched from its annotation box comes back near its annotation.
        let s = &samples[0];
        let photo = imaging::open(&s.image).unwrap();
        let truth = s.landmarks().unwrap();
        let found = lm.fit(&photo.gray, &super::super::train::annotation_box(&truth));
        let de = crate::eval::landmarks::d_eye(&found.keypoints, &KeyPoints::from_imm(&truth));
        assert!(de < 0.1, "d_eye {de}");
        // The yaw of a projected model shape comes back, at any image scale.
        let view = &lm.model.views[3];
        for (yaw, scale) in [(0.0f32, 2.0), (30.0, 1.2), (-25.0, 3.0)] {
            let cam = Camera::from_pose(Pose { yaw, pitch: 5.0, roll: 3.0 }, scale, 300.0, 240.0);
            let pts = view.pdm.project(&vec![0.0; view.pdm.modes()], &cam);
            let got = lm.yaw_of(&pts).unwrap();
            assert!((got - yaw).abs() < 3.0, "yaw {yaw}: estimated {got}");
        }
        assert!(lm.yaw_of(&vec![[5.0, 5.0]; IMM_POINTS]).is_none());
        // The service switch keeps the C-ASM's points below the yaw threshold and replaces them
        // beyond it.
        let casm = super::super::Landmarker {
            model: super::super::train::train(&samples, None, &super::super::train::TrainOptions::default(), &|| {}).unwrap(),
        };
        let face = super::super::train::annotation_box(&truth);
        let c = casm.fit(&photo.gray, &face, Variant::Casm);
        let (kept, used) = lm.switch(&photo.gray, &face, &casm, c.clone(), 90.0);
        assert!(!used && kept == c);
        let (replaced, used) = lm.switch(&photo.gray, &face, &casm, c.clone(), 0.0);
        assert!(used && replaced.points != c.points);
        let de = crate::eval::landmarks::d_eye(&replaced.keypoints, &KeyPoints::from_imm(&truth));
        assert!(de < 0.1, "switched d_eye {de}");
        let img = GrayF32::from_fn(92, 112, |x, y| ((x * 3 + y * 5) % 17) as f32 * 10.0);
        for b in [
            Rect::new(10.0, 20.0, 60.0, 60.0),
            Rect::new(-500.0, -500.0, 40.0, 40.0),
            Rect::new(0.0, 0.0, 0.0, 0.0),
            Rect::new(f32::NAN, 3.0, f32::INFINITY, -2.0),
            Rect::new(1.0, 1.0, 1e9, 1e9),
        ] {
            let out = lm.fit(&img, &b);
            assert_eq!(out.points.len(), 58);
        }
        for (w, h) in [(1, 1), (2, 2), (0, 0)] {
            assert_eq!(lm.fit(&GrayF32::new(w, h), &Rect::new(0.0, 0.0, 2.0, 2.0)).points.len(), 58);
        }
    }

    /// Train on the training persons, measure on held-out persons (all views, from the detector's
    /// box), print every photo and the per-group table of the 3D-ASM beside C-ASM.
    /// `ASM3D_CACHE` / `ASM_CACHE`: files to keep the trained models in between runs.
    #[test]
    #[ignore]
    fn held_out_accuracy() {
        use crate::eval::landmarks::{d_eye, d_mouth};
        let fm = face_model();
        let all = list_imm(&crate::config::shared_dir().join("data/imm")).unwrap();
        let (test, training): (Vec<ImmSample>, Vec<ImmSample>) = all.into_iter().partition(|s| dataset::imm_is_test_person(s.person));
        let det = Detector::load(&crate::config::models_dir()).ok();
        let t = std::time::Instant::now();
        let cache = std::env::var("ASM3D_CACHE").ok();
        let model = match cache.as_ref().and_then(|c| Asm3dLandmarker::load(Path::new(c)).ok()) {
            Some(lm) => lm.model,
            None => {
                // `ASM3D_RENDERS_BELOW`: `renders_below_real` of the training.
                let mut options = Asm3dTrainOptions::default();
                if let Some(n) = std::env::var("ASM3D_RENDERS_BELOW").ok().and_then(|v| v.parse().ok()) {
                    options.renders_below_real = n;
                }
                let m = train(&training, fm, det.as_ref(), &options, &|| {}).unwrap();
                if let Some(c) = &cache {
                    Asm3dLandmarker { model: m.clone() }.save(Path::new(c)).unwrap();
                }
                m
            }
        };
        eprintln!(
            "trained in {:.1}s; start scales {:?}; modes {:?}; real {:?}",
            t.elapsed().as_secs_f32(),
            model.views.iter().map(|v| v.start_scale).collect::<Vec<_>>(),
            model.views.iter().map(|v| v.pdm.modes()).collect::<Vec<_>>(),
            model.views.iter().map(|v| v.real_photos).collect::<Vec<_>>()
        );
        let casm_cache = std::env::var("ASM_CACHE").ok();
        let casm = match casm_cache.as_ref().and_then(|c| super::super::Landmarker::load(Path::new(c)).ok()) {
            Some(lm) => lm,
            None => {
                let m = super::super::train::train(&training, det.as_ref(), &super::super::train::TrainOptions::default(), &|| {}).unwrap();
                let lm = super::super::Landmarker { model: m };
                if let Some(c) = &casm_cache {
                    lm.save(Path::new(c)).unwrap();
                }
                lm
            }
        };
        let lm = Asm3dLandmarker { model };
        let only = std::env::var("ASM3D_ONLY").ok();
        // The searches compared: the 3D-ASM with each refinement, and the C-ASM alone.
        let names = ["3D-ASM", "3D+C-ASM", "C-ASM", "switch"];
        // `ASM3D_MIN_YAW`: the switch's threshold (default the service's).
        let min_yaw: f32 = std::env::var("ASM3D_MIN_YAW").ok().and_then(|v| v.parse().ok()).unwrap_or(SERVICE_MIN_YAW);
        let search = |k: usize, g: &GrayF32, b: &Rect| -> (Vec<Point>, Option<Asm3dLandmarks>) {
            let r = match k {
                0 => lm.fit(g, b),
                1 => lm.fit_with(g, b, Refinement::Casm(&casm.model)),
                2 => return (casm.fit(g, b, Variant::Casm).points, None),
                _ => return (lm.switch(g, b, &casm, casm.fit(g, b, Variant::Casm), min_yaw).0.points, None),
            };
            (r.points.clone(), Some(r))
        };
        // Point groups of the per-group diagnosis.
        let point_groups: [(&str, std::ops::Range<usize>); 4] =
            [("jaw", JAW), ("eyes+brows", 13..39), ("mouth", dataset::MOUTH), ("nose", dataset::NOSE)];
        // Per photo: view, |yaw|, and per search: d_eye, mouth, ms, mean point error / eye distance per point group.
        struct Row {
            view: u32,
            yaw: f32,
            d_eye: Vec<f64>,
            mouth: Vec<f64>,
            ms: Vec<f64>,
            groups: Vec<[f64; 4]>,
        }
        let mut rows: Vec<Row> = Vec::new();
        for s in test.iter().filter(|s| only.as_ref().is_none_or(|o| o.split(',').any(|x| x == format!("{:02}-{}", s.person, s.view)))) {
            let photo = imaging::open(&s.image).unwrap();
            let truth_points = s.landmarks().unwrap();
            let truth = KeyPoints::from_imm(&truth_points);
            let eyes = crate::geometry::distance(truth.left_eye, truth.right_eye) as f64;
            // The photo's head yaw: the 3DMM fitted to its manual landmarks.
            let yaw = fm.fit(&truth_points, photo.width(), photo.height()).map_or(f32::NAN, |f| f.pose.yaw);
            let Some(b) = det.as_ref().and_then(|d| d.detect(&photo.gray).first().map(|f| f.rect)) else { continue };
            let mut row = Row { view: s.view, yaw: yaw.abs(), d_eye: vec![], mouth: vec![], ms: vec![], groups: vec![] };
            let mut line = format!("{:02}-{} yaw {yaw:5.1}", s.person, s.view);
            for k in 0..names.len() {
                let t0 = crate::eval::thread_cpu_ns().unwrap_or(0);
                let (points, r3) = search(k, &photo.gray, &b);
                let ms = (crate::eval::thread_cpu_ns().unwrap_or(0) - t0) as f64 * 1e-6;
                let found = KeyPoints::from_imm(&points);
                let (de, dm) = (d_eye(&found, &truth), d_mouth(&found, &truth));
                let mut g = [0.0; 4];
                for (slot, (_, range)) in g.iter_mut().zip(&point_groups) {
                    let sum: f64 = range.clone().map(|i| crate::geometry::distance(points[i], truth_points[i]) as f64).sum();
                    *slot = sum / range.len() as f64 / eyes;
                }
                if std::env::var("ASM3D_JAW").is_ok() {
                    let e: Vec<String> = JAW
                        .map(|i| format!("{:.0},{:.0}/{:.0},{:.0}", points[i][0], points[i][1], truth_points[i][0], truth_points[i][1]))
                        .collect();
                    eprintln!("{} jaw found/truth {}", names[k], e.join(" "));
                }
                line += &format!(" | {} {de:.3} m {dm:.3}", names[k]);
                if let Some(r) = r3 {
                    line += &format!(" v{} y{:.0}", r.view_yaw, r.pose.yaw);
                }
                row.d_eye.push(de);
                row.mouth.push(dm);
                row.ms.push(ms);
                row.groups.push(g);
            }
            eprintln!("{line}");
            rows.push(row);
        }
        let pct = |v: &[f64], t: f64| 100.0 * v.iter().filter(|&&x| x < t).count() as f64 / v.len().max(1) as f64;
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
        let groups: [(&str, &dyn Fn(u32, f32) -> bool); 8] = [
            ("frontal 1-2", &|v, _| matches!(v, 1 | 2)),
            ("turned 3-4", &|v, _| matches!(v, 3 | 4)),
            ("light/free 5-6", &|v, _| matches!(v, 5 | 6)),
            ("|yaw| < 10", &|_, y| y < 10.0),
            ("|yaw| 10-20", &|_, y| (10.0..20.0).contains(&y)),
            ("|yaw| 20-30", &|_, y| (20.0..30.0).contains(&y)),
            ("|yaw| >= 30", &|_, y| y >= 30.0),
            ("all", &|_, _| true),
        ];
        eprintln!("d_eye<0.05 d_eye<0.1 mean-d_eye mouth<0.1 per search: {names:?}");
        for (name, keep) in &groups {
            let sel: Vec<&Row> = rows.iter().filter(|r| keep(r.view, r.yaw)).collect();
            let mut line = format!("{name:16} ({:2})", sel.len());
            for k in 0..names.len() {
                let (a, m): (Vec<f64>, Vec<f64>) = sel.iter().map(|r| (r.d_eye[k], r.mouth[k])).unzip();
                line += &format!(" | {:5.1}% {:5.1}% {:.4} {:5.1}%", pct(&a, 0.05), pct(&a, 0.1), mean(&a), pct(&m, 0.1));
            }
            eprintln!("{line}");
        }
        eprintln!("mean point error / eye distance per point group {:?}, per search {names:?}", point_groups.map(|g| g.0));
        for (name, keep) in &groups[..3] {
            let sel: Vec<&Row> = rows.iter().filter(|r| keep(r.view, r.yaw)).collect();
            let mut line = format!("{name:16}");
            for k in 0..names.len() {
                let cells: Vec<String> =
                    (0..4).map(|g| format!("{:.3}", mean(&sel.iter().map(|r| r.groups[k][g]).collect::<Vec<_>>()))).collect();
                line += &format!(" | {}", cells.join(" "));
            }
            eprintln!("{line}");
        }
        let ms: Vec<String> =
            (0..names.len()).map(|k| format!("{} {:.1}", names[k], mean(&rows.iter().map(|r| r.ms[k]).collect::<Vec<_>>()))).collect();
        eprintln!("thread CPU ms/face (this build's profile): {}", ms.join(", "));
        // `ASM3D_CROSSOVER=1` (or `=switch`): C-ASM against the 3D-ASM (each refinement) on renders of the
        // held-out faces at yaw 0…±60°.
        if std::env::var("ASM3D_CROSSOVER").is_ok() {
            let det = det.as_ref().expect("the face detector");
            let searches: [(&str, &dyn Fn(&GrayF32, &Rect) -> KeyPoints); 3] = [
                ("3D-ASM with the C-ASM refinement", &|g, b| lm.fit_with(g, b, Refinement::Casm(&casm.model)).keypoints),
                ("3D-ASM with the view refinement", &|g, b| lm.fit_with(g, b, Refinement::View).keypoints),
                ("the service switch", &|g, b| lm.switch(g, b, &casm, casm.fit(g, b, Variant::Casm), min_yaw).0.keypoints),
            ];
            // `ASM3D_CROSSOVER=switch`: the service switch only.
            let only_switch = std::env::var("ASM3D_CROSSOVER").is_ok_and(|v| v == "switch");
            for (name, search) in searches.into_iter().skip(if only_switch { 2 } else { 0 }) {
                println!("{name}:");
                let rows = crate::eval::landmarks::crossover(fm, &test, det, &casm, search).unwrap();
                crate::eval::landmarks::print_crossover(&rows);
            }
        }
    }
}
