//! Training the IMM point → Surrey Face Model vertex table from annotated photos
//! (`facegate train imm-sfm`, `models/imm_to_sfm.txt`).

use facegate_core::face::IMM_POINTS;
use facegate_morph::correspondence::{Anchor, imm_anchors};
use facegate_morph::{FaceModel, FittedFace, MorphError};

/// Refine the fixed correspondences on annotated photos (step 2 of the method, data-driven): fit
/// every shape, then move each fixed IMM point (all but the 12 sliding jaw points) to the vertex,
/// within `radius_mm` of its current one on the mean shape, whose projections in all fits lie
/// nearest (least squares) to the annotated points; repeat for `rounds`.
/// Returns the table and the RMS landmark residual (px) before and after.
pub fn derive_from_annotations(
    model: &mut FaceModel,
    shapes: &[(Vec<facegate_core::geometry::Point>, u32, u32)],
    rounds: usize,
    radius_mm: f32,
) -> Result<([u32; IMM_POINTS], f32, f32), MorphError> {
    let mean = model.shape.mean.clone();
    let nv = mean.len() / 3;
    let anchors = imm_anchors();
    let rms = |model: &FaceModel| -> Result<f32, MorphError> {
        let mut sq = 0.0f64;
        for (pts, w, h) in shapes {
            let f = model.fit(pts, *w, *h)?;
            sq += (f.residual_px as f64).powi(2);
        }
        Ok((sq / shapes.len().max(1) as f64).sqrt() as f32)
    };
    let before = rms(model)?;
    for _ in 0..rounds {
        let fits: Vec<FittedFace> = shapes.iter().map(|(p, w, h)| model.fit(p, *w, *h)).collect::<Result<_, _>>()?;
        let mut table = model.imm_vertices;
        for (i, anchor) in anchors.iter().enumerate() {
            if matches!(anchor, Anchor::Contour { .. }) {
                continue;
            }
            let c = table[i] as usize;
            let (cx, cy, cz) = (mean[3 * c], mean[3 * c + 1], mean[3 * c + 2]);
            let mut best = (table[i], f64::INFINITY);
            for v in 0..nv {
                let d2 = (mean[3 * v] - cx).powi(2) + (mean[3 * v + 1] - cy).powi(2) + (mean[3 * v + 2] - cz).powi(2);
                if d2 > radius_mm * radius_mm {
                    continue;
                }
                let mut cost = 0.0f64;
                for ((pts, _, _), f) in shapes.iter().zip(&fits) {
                    let p = f.vertices[v];
                    let q = f.camera.project([p[0] as f64, p[1] as f64, p[2] as f64]);
                    cost += (q[0] - pts[i][0] as f64).powi(2) + (q[1] - pts[i][1] as f64).powi(2);
                }
                if cost < best.1 {
                    best = (v as u32, cost);
                }
            }
            table[i] = best.0;
        }
        model.imm_vertices = table;
    }
    let after = rms(model)?;
    Ok((model.imm_vertices, before, after))
}
