//! Normalisation, Direct LDA templates, scores and calibrated thresholds.
//! (Stub API: the recognition issue fills it in.)

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::dataset::KeyPoints;
use crate::imaging::GrayF32;

/// A face template: a unit vector in DLDA space, tagged with the model that made it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Template {
    pub model_version: String,
    pub vector: Vec<f32>,
}

/// Which normalisation a recognition model was trained for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Normalization {
    /// Similarity alignment of eye and mouth centres in the photo.
    #[serde(rename = "2d")]
    TwoD,
    /// The 3DMM's frontal rendering, then the same alignment.
    #[serde(rename = "3dmm")]
    Morph,
}

/// A decision threshold at a false match rate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct OperatingPoint {
    pub fmr: f64,
    pub threshold: f32,
}

#[derive(Debug, thiserror::Error)]
pub enum RecognizeError {
    #[error("cannot load the recognition model {path}: {message}")]
    Model { path: String, message: String },
}

/// The DLDA projection with its calibration table, shareable across threads.
pub struct Recognizer {}

impl Recognizer {
    pub fn load(models_dir: &Path) -> Result<Recognizer, RecognizeError> {
        Err(RecognizeError::Model { path: models_dir.display().to_string(), message: "recognition has not landed yet".into() })
    }

    pub fn model_version(&self) -> &str {
        ""
    }

    pub fn normalization(&self) -> Normalization {
        Normalization::TwoD
    }

    /// Template of a face in `gray` whose eye and mouth centres are `keypoints`.
    pub fn template(&self, _gray: &GrayF32, _keypoints: &KeyPoints) -> Template {
        unimplemented!("recognition has not landed yet")
    }

    /// Score of a probe against one subject's templates (higher is more alike).
    pub fn score(&self, _probe: &Template, _enrolled: &[Template]) -> f32 {
        unimplemented!("recognition has not landed yet")
    }

    /// The calibrated operating point closest to `fmr` (the default is 1e-3).
    pub fn operating_point(&self, _fmr: f64) -> OperatingPoint {
        unimplemented!("recognition has not landed yet")
    }
}
