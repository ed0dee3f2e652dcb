//! Which recognizer makes the templates, and the one the pipeline runs.

use serde::{Deserialize, Serialize};

use super::{ClassicalRecognizer, DlibRecognizer, EmbeddingRecognizer, OperatingPoint, Template};

/// Which recognizer makes the templates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub enum RecognizerKind {
    /// dlib's face embedding alone (`deep.bin` over `embedding.bin`; `--recognizer deep`).
    Dlib,
    /// Pixels + LBP through Direct LDA (`dlda.bin`): no third-party weights, less CPU.
    Classical,
    /// OpenCV Zoo's SFace network alone (`sface.bin` over `sface.onnx`).
    Sface,
    /// dlib's network and SFace, their cosines weighted (`fusion.bin`): the default, the most
    /// accurate at 1.4× dlib's CPU (docs/recognition.md).
    #[default]
    Fusion,
    /// The user's own ONNX network(s) (`custom.bin`, from `facegate convert onnx-embedding` and
    /// `facegate train embedding`).
    Custom,
}

impl RecognizerKind {
    /// The model file of a recognizer made of embedding networks ([`EmbeddingRecognizer`]).
    pub fn embedding_model_file(self) -> Option<&'static str> {
        match self {
            RecognizerKind::Sface => Some("sface.bin"),
            RecognizerKind::Fusion => Some("fusion.bin"),
            RecognizerKind::Custom => Some("custom.bin"),
            RecognizerKind::Dlib | RecognizerKind::Classical => None,
        }
    }
}

/// The recognizer the pipeline runs: one of the two, behind what the service needs of either
/// (the model version on templates, the score, the calibrated operating point).
pub enum Recognizer {
    Classical(ClassicalRecognizer),
    Dlib(Box<DlibRecognizer>),
    /// SFace, the fusion, or a user's networks; `kind` is the value it was loaded as.
    Embedding(Box<EmbeddingRecognizer>, RecognizerKind),
}

impl Recognizer {
    pub fn kind(&self) -> RecognizerKind {
        match self {
            Recognizer::Classical(_) => RecognizerKind::Classical,
            Recognizer::Dlib(_) => RecognizerKind::Dlib,
            Recognizer::Embedding(_, kind) => *kind,
        }
    }

    pub fn model_version(&self) -> &str {
        match self {
            Recognizer::Classical(r) => r.model_version(),
            Recognizer::Dlib(d) => &d.model.version,
            Recognizer::Embedding(e, _) => &e.model.version,
        }
    }

    pub fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
        match self {
            Recognizer::Classical(r) => r.score(probe, enrolled),
            Recognizer::Dlib(d) => d.score(probe, enrolled),
            Recognizer::Embedding(e, _) => e.score(probe, enrolled),
        }
    }

    pub fn operating_point(&self, fmr: f64, enrolled: usize) -> OperatingPoint {
        match self {
            Recognizer::Classical(r) => r.operating_point(fmr, enrolled),
            Recognizer::Dlib(d) => d.model.operating_point(fmr, enrolled),
            Recognizer::Embedding(e, _) => e.model.operating_point(fmr, enrolled),
        }
    }

    /// The classical recognizer, when it is the one loaded.
    pub fn classical(&self) -> Option<&ClassicalRecognizer> {
        match self {
            Recognizer::Classical(r) => Some(r),
            Recognizer::Dlib(_) | Recognizer::Embedding(..) => None,
        }
    }
}
