//! Landmarks on the 58-point IMM template. (Stub API: the landmarks issue fills it in.)

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::dataset::KeyPoints;
use crate::geometry::{Point, Rect};
use crate::imaging::GrayF32;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Variant {
    Asm,
    Sift,
    #[default]
    Casm,
}

/// The 58 IMM points in image pixels, with the eye and mouth centres.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Landmarks {
    pub points: Vec<Point>,
    pub keypoints: KeyPoints,
}

#[derive(Debug, thiserror::Error)]
pub enum LandmarkError {
    #[error("cannot load the landmark model {path}: {message}")]
    Model { path: String, message: String },
}

/// Trained shape and texture models of all variants (`models/asm.bin`), shareable across threads.
pub struct Landmarker {}

impl Landmarker {
    pub fn load(path: &Path) -> Result<Landmarker, LandmarkError> {
        Err(LandmarkError::Model { path: path.display().to_string(), message: "landmarks have not landed yet".into() })
    }

    /// Search the 58 points of the face in `face` (a detector box).
    pub fn fit(&self, _gray: &GrayF32, _face: &Rect, _variant: Variant) -> Landmarks {
        unimplemented!("landmarks have not landed yet")
    }
}
