//! Normalisation, Direct LDA templates, scores and calibrated thresholds (thesis 2.6).
//!
//! A face comes in as a grey image and its eye and mouth centres ([`KeyPoints`]); [`normalize`]
//! aligns and relights it into a small crop, [`features`] turns the crop into a vector, [`dlda`]
//! projects it, and the unit projection is the [`Template`]. Templates compare by cosine
//! similarity; a decision uses a threshold calibrated at a false match rate ([`calibration`]).
//! Everything a template depends on is in one model file, `models/dlda.bin` (postcard), whose
//! content hash is the model version carried by every template.

pub mod calibration;
pub mod dlda;
pub mod features;
pub mod normalize;
pub mod template;
pub mod train;

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::dataset::KeyPoints;
use crate::imaging::GrayF32;

pub use calibration::{Calibration, DEFAULT_FMR};
pub use dlda::{Dlda, DldaParams};
pub use features::FeatureKind;
pub use normalize::{NormalizeParams, Photometric};
pub use template::{Combine, Template};

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
    #[error("template from model {found} cannot be compared with model {expected}: re-enrol with the current model")]
    ModelVersionMismatch { expected: String, found: String },
    #[error("template has {found} dimensions, the model makes {expected}")]
    TemplateDimension { expected: usize, found: usize },
    #[error("no templates to compare against")]
    NoTemplates,
    #[error("malformed template bytes: {0}")]
    TemplateFormat(String),
}

/// Where a model's training and calibration data came from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Provenance {
    /// `imm-annotations` (eye/mouth centres from the `.asf` files) or `pipeline` (detector + ASM).
    pub keypoint_source: String,
    pub data: Vec<String>,
    pub train_persons: Vec<String>,
    pub train_images: usize,
    pub calibration_persons: Vec<String>,
    pub calibration_images: usize,
    /// Mirrored copies of the training crops were added.
    pub mirrored: bool,
}

/// Everything a template depends on, saved as `models/dlda.bin`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Model {
    pub format: u32,
    pub normalization: Normalization,
    pub normalize: NormalizeParams,
    pub features: FeatureKind,
    pub dlda: Dlda,
    pub combine: Combine,
    pub calibration: Calibration,
    pub provenance: Provenance,
}

const MODEL_FORMAT: u32 = 1;
pub const MODEL_FILE: &str = "dlda.bin";

impl Model {
    pub fn new(
        normalization: Normalization,
        normalize: NormalizeParams,
        features: FeatureKind,
        dlda: Dlda,
        provenance: Provenance,
    ) -> Model {
        Model {
            format: MODEL_FORMAT,
            normalization,
            normalize,
            features,
            dlda,
            combine: Combine::Max,
            calibration: Calibration { points: Vec::new(), genuine_count: 0, impostor_count: 0, source: String::new() },
            provenance,
        }
    }

    /// `dlda-` and 12 hex digits of the SHA-256 of everything that shapes a template (normalisation,
    /// features, projection); calibration and provenance do not change templates, so not the version.
    pub fn version(&self) -> String {
        let bytes = postcard::to_stdvec(&(&self.normalization, &self.normalize, &self.features, &self.dlda)).expect("model serialises");
        let digest = Sha256::digest(&bytes);
        let hex: String = digest.iter().take(6).map(|b| format!("{b:02x}")).collect();
        format!("dlda-{hex}")
    }

    pub fn save(&self, path: &Path) -> anyhow::Result<()> {
        crate::config::write_model(path, self).map_err(|e| anyhow::anyhow!("cannot write {}: {e}", path.display()))
    }

    pub fn load(path: &Path) -> Result<Model, RecognizeError> {
        let err = |message: String| RecognizeError::Model { path: path.display().to_string(), message };
        let bytes = std::fs::read(path).map_err(|e| err(e.to_string()))?;
        let model: Model = postcard::from_bytes(&bytes).map_err(|e| err(format!("not a facegate DLDA model ({e})")))?;
        if model.format != MODEL_FORMAT {
            return Err(err(format!("model format {} (this build reads {MODEL_FORMAT})", model.format)));
        }
        let mask = model.normalize.mask();
        let dims = model.features.dims(model.normalize.width, model.normalize.height, &mask);
        if dims != model.dlda.input_dims || model.dlda.projection.len() != model.dlda.dims * dims || model.dlda.mean.len() != dims {
            return Err(err("projection does not match the feature layout".into()));
        }
        Ok(model)
    }
}

/// The DLDA projection with its calibration table, shareable across threads.
pub struct Recognizer {
    model: Model,
    version: String,
    mask: Vec<bool>,
}

impl Recognizer {
    /// Load `dlda.bin` from the models folder.
    pub fn load(models_dir: &Path) -> Result<Recognizer, RecognizeError> {
        Recognizer::load_file(&models_dir.join(MODEL_FILE))
    }

    pub fn load_file(path: &Path) -> Result<Recognizer, RecognizeError> {
        Ok(Recognizer::from_model(Model::load(path)?))
    }

    pub fn from_model(model: Model) -> Recognizer {
        let version = model.version();
        let mask = model.normalize.mask();
        Recognizer { model, version, mask }
    }

    pub fn model(&self) -> &Model {
        &self.model
    }

    pub fn model_version(&self) -> &str {
        &self.version
    }

    pub fn normalization(&self) -> Normalization {
        self.model.normalization
    }

    /// The normalised crop of a face (geometric and photometric), as the model sees it.
    pub fn normalized_crop(&self, gray: &GrayF32, keypoints: &KeyPoints) -> GrayF32 {
        normalize::normalize(gray, keypoints, &self.model.normalize)
    }

    /// Template of a normalised crop (see [`Recognizer::normalized_crop`]).
    pub fn template_of_crop(&self, crop: &GrayF32) -> Template {
        let features = self.model.features.extract(crop, &self.mask);
        Template::new(&self.version, self.model.dlda.project(&features))
    }

    /// Template of a face in `gray` whose eye and mouth centres are `keypoints`.
    pub fn template(&self, gray: &GrayF32, keypoints: &KeyPoints) -> Template {
        self.template_of_crop(&self.normalized_crop(gray, keypoints))
    }

    /// Score of a probe against one subject's templates (higher is more alike), combining
    /// several templates by the model's measured rule (max or mean of the cosines).
    ///
    /// Templates made by another model version (or of another length) cannot be compared: they
    /// are left out, and when nothing comparable is left the score is −1, the lowest cosine, which
    /// never reaches a threshold. Use [`Recognizer::try_score`] to get that as an error.
    pub fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
        if !self.comparable(probe) {
            return -1.0;
        }
        self.model.combine.apply(enrolled.iter().filter(|t| self.comparable(t)).map(|t| probe.cosine(t))).unwrap_or(-1.0)
    }

    /// [`Recognizer::score`] with a typed error for templates of another model version.
    pub fn try_score(&self, probe: &Template, enrolled: &[Template]) -> Result<f32, RecognizeError> {
        if enrolled.is_empty() {
            return Err(RecognizeError::NoTemplates);
        }
        for t in std::iter::once(probe).chain(enrolled) {
            self.check(t)?;
        }
        Ok(self.score(probe, enrolled))
    }

    /// Whether `template` was made by this model.
    pub fn check(&self, template: &Template) -> Result<(), RecognizeError> {
        if template.model_version != self.version {
            return Err(RecognizeError::ModelVersionMismatch { expected: self.version.clone(), found: template.model_version.clone() });
        }
        if template.vector.len() != self.model.dlda.dims {
            return Err(RecognizeError::TemplateDimension { expected: self.model.dlda.dims, found: template.vector.len() });
        }
        Ok(())
    }

    fn comparable(&self, t: &Template) -> bool {
        self.check(t).is_ok()
    }

    /// The calibrated operating point closest to `fmr` (the default is 1e-3).
    pub fn operating_point(&self, fmr: f64) -> OperatingPoint {
        self.model.calibration.operating_point(fmr)
    }
}

/// The default location of the committed model.
pub fn default_model_path() -> PathBuf {
    crate::config::models_dir().join(MODEL_FILE)
}
