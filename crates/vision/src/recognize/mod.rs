//! Normalisation, Direct LDA templates, scores and calibrated thresholds (thesis 2.6).
//!
//! A face comes in as a grey image and its eye and mouth centres
//! ([`EyeMouthCentres`](facegate_core::face::EyeMouthCentres)); [`normalize`] aligns and relights it into a
//! small crop, [`features`] turns the crop into a vector, [`dlda`] projects it, and the unit
//! projection is the [`Template`]. Templates compare by cosine similarity; a decision uses a
//! threshold calibrated at a false match rate ([`calibration`]). Everything a template depends on
//! is in one model file, `models/dlda.bin` (postcard), whose content hash is the model version
//! carried by every template: the [`classical`] model and its recognizer. Beside it, the [`deep`]
//! and [`embedding`] recognizers, and [`Recognizer`], the one the pipeline runs; here, what they
//! share (normalisation paths, operating points, views, errors).

pub mod calibration;
pub mod classical;
pub mod dlda;
pub mod dlib;
pub mod embedding;
pub mod features;
pub mod normalize;
mod recognizer;
pub mod score_norm;
mod template;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

pub use calibration::{Calibration, DEFAULT_FMR, EnrolledCalibration, MAX_CALIBRATED_ENROLLMENT};
pub use classical::{ClassicalModel, ClassicalRecognizer, LocalPart, MODEL_FILE, Provenance, SecondaryPath};
pub use dlda::Dlda;
pub use features::{FeatureKind, Region};
pub use normalize::{NormalizeParams, Photometric};
pub use score_norm::{Cohort, CohortStats};
pub use template::Combine;
// Template and OperatingPoint are core's, named from there by every crate; imported here for the
// recognizers below.
use facegate_core::template::{OperatingPoint, Template};

pub use dlib::DlibRecognizer;
pub use embedding::EmbeddingRecognizer;
pub use recognizer::{Recognizer, RecognizerKind};

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

impl std::fmt::Display for Normalization {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Normalization::TwoD => "2d",
            Normalization::Morph => "3dmm",
        })
    }
}

/// A face as each normalisation path of a model sees it. A fused model has two paths (its
/// primary, the 3DMM frontal rendering, and its second, the 2D-aligned photo) and needs both
/// views; a single-path model needs one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Views<T> {
    Single(T),
    Fused { primary: T, secondary: T },
}

impl<T> Views<T> {
    /// The same views through `f`, path by path.
    pub fn map<U>(self, mut f: impl FnMut(T) -> U) -> Views<U> {
        match self {
            Views::Single(v) => Views::Single(f(v)),
            Views::Fused { primary, secondary } => Views::Fused { primary: f(primary), secondary: f(secondary) },
        }
    }

    pub fn as_ref(&self) -> Views<&T> {
        match self {
            Views::Single(v) => Views::Single(v),
            Views::Fused { primary, secondary } => Views::Fused { primary, secondary },
        }
    }

    /// How many paths: 1 or 2.
    pub fn count(&self) -> usize {
        match self {
            Views::Single(_) => 1,
            Views::Fused { .. } => 2,
        }
    }

    /// The views, primary first.
    pub fn into_vec(self) -> Vec<T> {
        match self {
            Views::Single(v) => vec![v],
            Views::Fused { primary, secondary } => vec![primary, secondary],
        }
    }
}

/// A model version: `prefix`, a dash and the first 12 hex digits of the SHA-256 of `shape` (the
/// serialised parts of a model that shape its templates). Templates of different versions are
/// never compared, so a version must not change while the model's templates do not.
pub(crate) fn model_version(prefix: &str, shape: &[u8]) -> String {
    let hex: String = Sha256::digest(shape).iter().take(6).map(|b| format!("{b:02x}")).collect();
    format!("{prefix}-{hex}")
}

#[derive(Debug, thiserror::Error)]
pub enum RecognizeError {
    #[error("cannot write {path}: {message}")]
    Save { path: String, message: String },
    #[error("cannot load the recognition model {path}: {message}")]
    Model { path: String, message: String },
    #[error("template from model {found} cannot be compared with model {expected}: re-enrol with the current model")]
    ModelVersionMismatch { expected: String, found: String },
    #[error("template has {found} dimensions, the model makes {expected}")]
    TemplateDimension { expected: usize, found: usize },
    #[error("the model makes templates from {expected} normalised views (one per path), got {found}")]
    Views { expected: usize, found: usize },
    #[error("no templates to compare against")]
    NoTemplates,
}
