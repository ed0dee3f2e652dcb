//! The request path, stage by stage: decoded photo → face box → landmarks → (3DMM pose
//! correction) → normalised face → template. Used by the CLI, the HTTP API and the evaluation
//! tools alike. Everything here is synchronous and CPU-bound: callers in async code run it on a
//! blocking pool.

use std::path::PathBuf;
use std::time::Instant;

use serde::Serialize;

use crate::detect::{Detector, Face};
use crate::imaging::{GrayF32, Photo};
use crate::landmarks::{Landmarker, Landmarks, Variant};
use crate::morph::{FaceModel, Pose};
use crate::recognize::{Normalization, Recognizer, Template};

/// Where the pipeline's models are.
#[derive(Debug, Clone)]
pub struct PipelineConfig {
    /// The project's trained models (cascades, `asm.bin`, `dlda.bin`).
    pub models_dir: PathBuf,
    /// The Surrey Face Model folder; `None` or missing files mean 2D alignment only.
    pub sfm_dir: Option<PathBuf>,
}

impl Default for PipelineConfig {
    fn default() -> Self {
        Self { models_dir: crate::config::models_dir(), sfm_dir: Some(crate::config::sfm_dir()) }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error("no face was found in the image")]
    NoFace,
    #[error(transparent)]
    Detect(#[from] crate::detect::DetectError),
    #[error(transparent)]
    Landmarks(#[from] crate::landmarks::LandmarkError),
    #[error(transparent)]
    Recognize(#[from] crate::recognize::RecognizeError),
}

/// Milliseconds spent in each stage of one analysis.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct StageTimings {
    pub detect_ms: f64,
    pub landmarks_ms: f64,
    pub morph_ms: f64,
    pub template_ms: f64,
}

/// Everything the pipeline learnt about the face it used.
#[derive(Debug, Clone)]
pub struct FaceAnalysis {
    /// The face used: the largest one found.
    pub face: Face,
    /// How many faces the detector found.
    pub faces_found: usize,
    pub landmarks: Landmarks,
    /// Head pose from the 3DMM fit, when the model is loaded.
    pub pose: Option<Pose>,
    pub template: Template,
    pub timings: StageTimings,
}

pub struct Pipeline {
    pub detector: Detector,
    pub landmarker: Landmarker,
    /// `None` when the Surrey Face Model is not available: 2D alignment only.
    pub face_model: Option<FaceModel>,
    pub recognizer: Recognizer,
}

impl Pipeline {
    pub fn load(config: &PipelineConfig) -> Result<Pipeline, PipelineError> {
        let detector = Detector::load(&config.models_dir)?;
        let landmarker = Landmarker::load(&config.models_dir.join("asm.bin"))?;
        let recognizer = Recognizer::load(&config.models_dir)?;
        let face_model = match &config.sfm_dir {
            Some(dir) => match FaceModel::load(dir) {
                Ok(model) => Some(model),
                Err(e) => {
                    tracing::warn!("3D morphable model unavailable ({e}); falling back to 2D alignment");
                    None
                }
            },
            None => None,
        };
        Ok(Pipeline { detector, landmarker, face_model, recognizer })
    }

    /// Detect, landmark, pose-correct and template the largest face of `photo`.
    pub fn analyze(&self, photo: &Photo) -> Result<FaceAnalysis, PipelineError> {
        let mut timings = StageTimings::default();
        let t = Instant::now();
        let faces = self.detector.detect(&photo.gray);
        timings.detect_ms = ms(t);
        let face = *faces.first().ok_or(PipelineError::NoFace)?;

        let t = Instant::now();
        let landmarks = self.landmarker.fit(&photo.gray, &face.rect, Variant::Casm);
        timings.landmarks_ms = ms(t);

        let t = Instant::now();
        // A failed fit (degenerate landmarks) falls back to 2D alignment, like a missing model.
        let fitted = self.face_model.as_ref().and_then(|m| m.fit(&landmarks.points, photo.width(), photo.height()).ok().map(|f| (m, f)));
        let pose = fitted.as_ref().map(|(_, f)| f.pose);
        let frontal = match (&fitted, self.recognizer.normalization()) {
            (Some((model, fit)), Normalization::Morph) => model.frontalize(photo, fit).ok(),
            _ => None,
        };
        timings.morph_ms = ms(t);

        let t = Instant::now();
        let template = match &frontal {
            Some(f) => self.recognizer.template(&GrayF32::from_rgb(&f.image), &f.keypoints),
            None => self.recognizer.template(&photo.gray, &landmarks.keypoints),
        };
        timings.template_ms = ms(t);

        Ok(FaceAnalysis { face, faces_found: faces.len(), landmarks, pose, template, timings })
    }
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}
