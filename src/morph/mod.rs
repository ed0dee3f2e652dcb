//! The 3D morphable model: fitting, texture, frontal rendering, avatars.
//! (Stub API: the 3DMM issue fills it in.)

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::dataset::KeyPoints;
use crate::geometry::Point;
use crate::imaging::Photo;

/// Head pose in degrees. Sign convention documented in the 3DMM issue's implementation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
pub struct Pose {
    pub yaw: f32,
    pub pitch: f32,
    pub roll: f32,
}

#[derive(Debug, thiserror::Error)]
pub enum MorphError {
    #[error("cannot load the 3D morphable model from {path}: {message}")]
    Model { path: String, message: String },
}

/// The Surrey Face Model with the IMM correspondence, shareable across threads.
pub struct FaceModel {}

/// The result of fitting the model to 58 IMM landmarks.
#[derive(Debug, Clone)]
pub struct FittedFace {
    pub pose: Pose,
    pub residual_px: f32,
}

/// A frontal rendering and where the eye and mouth centres fall in it.
#[derive(Debug, Clone)]
pub struct Frontal {
    pub image: image::RgbImage,
    pub keypoints: KeyPoints,
}

impl FaceModel {
    pub fn load(sfm_dir: &Path) -> Result<FaceModel, MorphError> {
        Err(MorphError::Model { path: sfm_dir.display().to_string(), message: "the 3DMM has not landed yet".into() })
    }

    pub fn fit(&self, _points: &[Point], _image_width: u32, _image_height: u32) -> FittedFace {
        unimplemented!("the 3DMM has not landed yet")
    }

    pub fn frontalize(&self, _photo: &Photo, _fit: &FittedFace) -> Frontal {
        unimplemented!("the 3DMM has not landed yet")
    }
}
