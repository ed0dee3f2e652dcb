//! The request path, stage by stage: decoded photo → face box → landmarks → (3DMM pose
//! correction) → normalised face → template. Used by the CLI, the HTTP API and the evaluation
//! tools alike. Everything here is synchronous and CPU-bound: callers in async code run it on a
//! blocking pool.
//!
//! In four parts, re-exported here: `finder`, the face and its landmarks ([`FaceFinder`]);
//! `follow`, which face of a frame is the person followed from the last ([`FollowedFace`]);
//! `input`, what the recognizers are handed ([`recognition_input`], the quality's chip, the
//! avatar); `analyze`, the stages assembled ([`Pipeline`]).

use std::path::PathBuf;

use crate::recognize::RecognizerKind;
use facegate_detect::DetectorKind;

mod analyze;
mod finder;
mod follow;
mod input;
#[cfg(test)]
mod tests;

pub use analyze::{FaceAnalysis, FaceChoice, FaceReading, PhotoReading, Pipeline, StageTimings};
pub use finder::{CentreSource, FaceFinder, Located, cascade_like_box, centres_from_detector, detector_turn, seed_box};
pub use follow::FollowedFace;
pub use input::{RecognitionInput, load_face_model, quality_components, recognition_input, reconstruct};

/// Where the pipeline's models are.
#[derive(Debug, Clone)]
pub struct PipelineConfig {
    /// The project's trained models (cascades, `asm.bin`, `dlda.bin`).
    pub models_dir: PathBuf,
    /// The Surrey Face Model folder; `None` or missing files mean 2D alignment only.
    pub sfm_dir: Option<PathBuf>,
    /// The deep embedding (`deep.bin`) or the classical DLDA (`dlda.bin`).
    pub recognizer: RecognizerKind,
    /// The face detector.
    pub detector: DetectorKind,
}

/// The 2D-alignment recognition model used when the 3DMM is unavailable.
pub const TWO_D_MODEL_FILE: &str = "dlda-2d.bin";

#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error("the recognition model needs the 3D morphable model, which is unavailable, and {0} is not a 2D model")]
    NoTwoDModel(String),
    #[error("no face was found in the image")]
    NoFace,
    #[error("the face could not be pose-corrected: {0}")]
    PoseCorrection(facegate_morph::MorphError),
    #[error("this needs the 3D morphable model, which is not loaded (the Surrey Face Model folder: --sfm, FACEGATE_SFM)")]
    NoFaceModel,
    #[error(transparent)]
    Detect(#[from] facegate_detect::DetectError),
    #[error(transparent)]
    Landmarks(#[from] crate::landmarks::LandmarkError),
    #[error(transparent)]
    Recognize(#[from] crate::recognize::RecognizeError),
    #[error(transparent)]
    Quality(#[from] crate::quality::QualityModelError),
    #[error(transparent)]
    Liveness(#[from] crate::liveness::LivenessModelError),
}
