//! Face detection. (Stub API: the detection issue fills it in.)

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::geometry::Rect;
use crate::imaging::GrayF32;

/// A detected face: its box in pixels of the input image and a confidence (higher is surer).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Face {
    #[serde(rename = "box")]
    pub rect: Rect,
    pub score: f32,
}

#[derive(Debug, thiserror::Error)]
pub enum DetectError {
    #[error("cannot load the detector model {path}: {message}")]
    Model { path: String, message: String },
}

/// The default face detector, shareable across threads.
pub struct Detector {}

impl Detector {
    /// Load the default detector from the models folder.
    pub fn load(models_dir: &Path) -> Result<Detector, DetectError> {
        Err(DetectError::Model { path: models_dir.display().to_string(), message: "detection has not landed yet".into() })
    }

    /// Faces in the image, largest first.
    pub fn detect(&self, _gray: &GrayF32) -> Vec<Face> {
        Vec::new()
    }
}
