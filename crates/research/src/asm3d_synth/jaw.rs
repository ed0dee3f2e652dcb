//! Which 3DMM vertex each IMM point sits on, per view: the jaw follows the visible outline.

use facegate_core::face::{IMM_POINTS, JAW};
use facegate_core::geometry::Point;
use facegate_morph::{Camera, FaceModel};

/// |cos| between a vertex normal and the viewing direction below which the vertex is on the
/// occluding outline (as in the morph fit).
const OUTLINE_COSINE: f64 = 0.25;

/// The vertex of each jaw point (IMM 0–12; the chin's is fixed) on a face seen from the front.
pub type JawVertices = [u32; 13];

/// The contour jaw convention: every other vertex of the model contour (`sfm_model_contours.json`),
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
pub fn annotated_jaw_vertices(fm: &FaceModel, fits: &[&facegate_morph::FittedFace]) -> JawVertices {
    let frontal: Vec<&&facegate_morph::FittedFace> = fits.iter().filter(|f| f.pose.yaw.abs() < 10.0).collect();
    let used: Vec<&facegate_morph::FittedFace> = if frontal.len() >= 3 { frontal.into_iter().copied().collect() } else { fits.to_vec() };
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

/// The jaw vertices of a fitted training photo seen from the front: the fit's own (the vertex
/// nearest to the photo's annotation) where it is on the model contour, else (a point the fit put on
/// the occluding outline of a turned face: not where it would be from the front) the learnt
/// convention `annotated`; near-frontal photos (|yaw| < 10°) keep all of theirs.
pub fn photo_jaw_vertices(fm: &FaceModel, fit: &facegate_morph::FittedFace, annotated: &JawVertices) -> JawVertices {
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
pub fn annotation_offsets(fm: &FaceModel, fit: &facegate_morph::FittedFace, annotated: &[Point]) -> Vec<[f64; 3]> {
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
