//! The head pose from a detector's five key points (eyes, nose tip, mouth corners): a rigid fit
//! of the model's mean face. The 58-point fit needs landmarks the C-ASM cannot find on a profile;
//! five points a multi-view detector finds at any yaw are enough for the camera, and the far eye
//! and mouth corner, which the detector can only guess on a turned head, are down-weighted once
//! the first fit shows them hidden.

use facegate_core::face::{EYE_IMAGE_LEFT, EYE_IMAGE_RIGHT, IMM_POINTS};
use facegate_core::geometry::Point;

use super::fit::estimate_camera;
use super::{Camera, FaceModel, FittedFace, MorphError};

/// IMM points of the image-left and image-right mouth corners.
const MOUTH_CORNERS: [usize; 2] = [39, 43];

/// Beyond this yaw (degrees) the far eye and mouth corner are behind the nose and the cheek.
pub const HIDDEN_SIDE_YAW: f32 = 40.0;

/// Weight of a guessed, hidden point in the second fit.
const HIDDEN_WEIGHT: f64 = 0.2;

/// The scaled orthographic camera that maps `model` (a face's five key points, model mm, in the
/// detector's order) onto the detector's `points`; on a head turned past [`HIDDEN_SIDE_YAW`] the
/// far side's eye and mouth corner count for [`HIDDEN_WEIGHT`] in a second fit. The pipeline's
/// five-point pose and the profile landmark search's start both use it.
pub fn key_point_camera(model: &[[f64; 3]; 5], points: &[Point; 5]) -> Result<Camera, MorphError> {
    let mut weights = [1.0f64; 5];
    let mut camera = estimate_camera(model, points, &weights)?;
    let yaw = camera.pose().yaw;
    if yaw.abs() > HIDDEN_SIDE_YAW {
        // Which side is far: the one whose eye the camera sees deeper (smaller depth).
        let far_left = camera.project(model[0])[2] < camera.project(model[1])[2];
        let (eye, mouth) = if far_left { (0, 3) } else { (1, 4) };
        weights[eye] = HIDDEN_WEIGHT;
        weights[mouth] = HIDDEN_WEIGHT;
        camera = estimate_camera(model, points, &weights)?;
    }
    Ok(camera)
}

impl FaceModel {
    /// The mean face's points for the detector's five, in its order (image-left eye, image-right
    /// eye, nose tip, image-left and image-right mouth corner); the eyes are the means of their
    /// outline vertices, the nose tip the mean shape's front-most vertex.
    pub fn key_point_vertices(&self) -> [[f64; 3]; 5] {
        let mean = |v: u32| {
            let i = 3 * v as usize;
            [self.shape.mean[i] as f64, self.shape.mean[i + 1] as f64, self.shape.mean[i + 2] as f64]
        };
        let centre = |range: std::ops::Range<usize>| {
            let n = range.len() as f64;
            range.map(|i| mean(self.imm_vertices[i])).fold([0.0; 3], |a, p| [a[0] + p[0] / n, a[1] + p[1] / n, a[2] + p[2] / n])
        };
        let tip = (0..self.vertex_count() as u32).max_by(|&a, &b| mean(a)[2].total_cmp(&mean(b)[2])).unwrap_or(0);
        [
            centre(EYE_IMAGE_LEFT),
            centre(EYE_IMAGE_RIGHT),
            mean(tip),
            mean(self.imm_vertices[MOUTH_CORNERS[0]]),
            mean(self.imm_vertices[MOUTH_CORNERS[1]]),
        ]
    }

    /// The mean face posed by the camera that best maps its five key points onto `points`
    /// (scaled orthographic). On a head turned past [`HIDDEN_SIDE_YAW`] the far side's eye and
    /// mouth corner count for [`HIDDEN_WEIGHT`] in a second fit. The result's shape is the mean
    /// (no coefficients); its residual is over the five points.
    pub fn fit_key_points(&self, points: &[Point; 5], image_width: u32, image_height: u32) -> Result<FittedFace, MorphError> {
        if points.iter().any(|p| !p[0].is_finite() || !p[1].is_finite()) {
            return Err(MorphError::Input("non-finite key point coordinates".into()));
        }
        let model = self.key_point_vertices();
        let camera = key_point_camera(&model, points)?;
        let residual = model.iter().zip(points).map(|(m, p)| {
            let q = camera.project(*m);
            (q[0] - p[0] as f64).powi(2) + (q[1] - p[1] as f64).powi(2)
        });
        let residual_px = (residual.sum::<f64>() / 5.0).sqrt() as f32;
        let vertices: Vec<[f32; 3]> = self.shape.mean.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect();
        Ok(FittedFace {
            pose: camera.pose(),
            residual_px,
            camera,
            coefficients: vec![0.0; self.shape.component_count()],
            expression: Vec::new(),
            correspondence: self.imm_vertices,
            vertices,
            image_width,
            image_height,
        })
    }
}

const _: () = assert!(MOUTH_CORNERS[1] < IMM_POINTS);
