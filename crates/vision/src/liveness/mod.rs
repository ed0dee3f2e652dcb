//! Passive liveness on one photo: is the face in front of the camera a live one or a printed
//! photo of one (a presentation attack, ISO/IEC 30107)? Plain data in (the photo, the
//! recognizer's eye and mouth centres), plain data out ([`Liveness`]): the calibrated probability
//! of a live face from a logistic model ([`LivenessModel`], `models/liveness.bin`, trained by
//! `facegate train liveness`) over texture, colour and frequency features of the face and its
//! surround ([`features`]). Vision measures and never decides: whether a score is an attack is
//! the service's call, from the one threshold it holds (`facegate_service::liveness`); the
//! model's own operating point ([`LivenessModel::threshold`]) is only where that threshold starts.

pub mod features;
pub mod head_turn;
pub mod lbp;
pub mod minifasnet;

use std::path::Path;

use facegate_core::face::EyeMouthCentres;
use image::RgbImage;
use serde::{Deserialize, Serialize};

pub use features::Block;

/// The liveness model's file.
pub const FILE: &str = "liveness.bin";
/// The rendered-head detector's file: a [`LivenessModel`] whose live class is a face seen by a
/// camera and whose attack class is a 3D head rendered from a photo (`facegate train render`);
/// the head-turn challenge holds its frames against it.
pub const RENDER_FILE: &str = "render.bin";
/// The layout of [`LivenessModel`].
pub const FORMAT: u32 = 1;

/// The liveness of one face as measured: a score, not a verdict.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Liveness {
    /// The calibrated probability that the face is live, 0–1.
    pub score: f32,
    /// The model that measured it.
    pub model: String,
}

/// A logistic model on standardised [`features`]: `logit = bias + Σ weight · (x − mean) / scale`,
/// then Platt's calibration `score = σ(slope · logit + offset)`, fitted on out-of-fold logits so
/// that the score is a probability on subjects the model never saw.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LivenessModel {
    pub format: u32,
    /// Its name in responses (`liveness.model`).
    pub name: String,
    /// The feature blocks, in order.
    pub blocks: Vec<Block>,
    pub mean: Vec<f32>,
    pub scale: Vec<f32>,
    pub weights: Vec<f32>,
    pub bias: f32,
    pub slope: f32,
    pub offset: f32,
    /// The operating point chosen by `facegate train liveness`: the score below which a face is an
    /// attack unless a camera's calibration or the operator sets another. The service decides
    /// by it; vision never reads it.
    pub threshold: f32,
    /// What the operating point is, for the refusal's message ("APCER 1% on NUAA, …").
    pub operating_point: String,
    /// What it was trained on and the command that rebuilds it.
    pub trained_on: String,
}

#[derive(Debug, thiserror::Error)]
#[error("liveness model {path}: {message}")]
pub struct LivenessModelError {
    pub path: String,
    pub message: String,
}

impl LivenessModel {
    pub fn load(path: &Path) -> Result<LivenessModel, LivenessModelError> {
        let fail = |message: String| LivenessModelError { path: path.display().to_string(), message };
        let model: LivenessModel =
            facegate_core::model_file::read_model(path, "liveness model", FORMAT, "facegate train liveness").map_err(fail)?;
        let n: usize = model.blocks.iter().map(|b| b.len()).sum();
        if model.mean.len() != n || model.scale.len() != n || model.weights.len() != n {
            return Err(fail(format!("expected {n} features for its blocks")));
        }
        Ok(model)
    }

    /// The model's logit of the features `x` (before calibration).
    pub fn logit(&self, x: &[f32]) -> f32 {
        self.bias + x.iter().zip(&self.mean).zip(&self.scale).zip(&self.weights).map(|(((x, m), s), w)| w * (x - m) / s).sum::<f32>()
    }

    /// The calibrated probability of a live face from a logit.
    pub fn probability(&self, logit: f32) -> f32 {
        1.0 / (1.0 + (-(self.slope * logit + self.offset)).exp())
    }

    /// The liveness of the face at `centres` in `photo`.
    pub fn assess(&self, photo: &RgbImage, centres: &EyeMouthCentres) -> Liveness {
        self.assess_features(&self.features(photo, centres))
    }

    /// The features of the face at `centres` in `photo`, the model's blocks in order.
    pub fn features(&self, photo: &RgbImage, centres: &EyeMouthCentres) -> Vec<f32> {
        features::features(&features::crops(photo, centres), &self.blocks)
    }

    /// The liveness of a face from its [`LivenessModel::features`] (of a model with the same
    /// blocks: another model's features are reused only then).
    pub fn assess_features(&self, x: &[f32]) -> Liveness {
        Liveness { score: self.probability(self.logit(x)), model: self.name.clone() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_committed_model_loads_and_tells_a_print_from_a_live_face() {
        let model = LivenessModel::load(&facegate_paths::models_dir().join(FILE)).unwrap();
        assert!(model.threshold > 0.0 && model.threshold < 1.0);
        // A monotone calibration: a higher logit is a likelier live face.
        assert!(model.probability(1.0) > model.probability(-1.0));
        let bad = std::env::temp_dir().join(format!("facegate-liveness-{}.bin", std::process::id()));
        facegate_core::model_file::write_model(&bad, &LivenessModel { weights: vec![1.0], ..model.clone() }).unwrap();
        let e = LivenessModel::load(&bad).unwrap_err().to_string();
        assert!(e.contains("features"), "{e}");
        std::fs::remove_file(&bad).unwrap();
    }
}
