//! dlib's network as a recognizer alone (`--recognizer deep`, `models/deep.bin`): which chip feeds
//! the network, the Direct LDA projection trained over its embeddings, the calibrated thresholds
//! per enrolment size, and the model version its templates carry. The network itself is
//! `models/embedding.bin` ([`crate::embed`]); this file is bound to it by the SHA-256 of the
//! package file it came from.

use std::path::Path;

use image::RgbImage;
use serde::{Deserialize, Serialize};

use super::calibration::{Calibration, EnrolledCalibration};
use super::template::Combine;
use super::{Dlda, OperatingPoint, RecognizeError, Template};
use facegate_core::face::EyeMouthCentres;
use facegate_core::model_file::read_model;
use facegate_nn::{Embedder, Embedding};

pub const FILE: &str = "deep.bin";
pub const FORMAT: u32 = 1;

/// What the network sees.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum ChipSource {
    /// The photo itself, aligned by the landmarks.
    Photo,
    /// The 3DMM frontal rendering, aligned by its centres.
    Frontal,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DeepProvenance {
    /// Persons and photos the projection was trained on.
    pub trained_on: String,
    /// The command that rebuilds the file.
    pub command: String,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DlibModel {
    pub format: u32,
    /// `deep-` and the first 12 hex digits of the SHA-256 of the projection and chip source:
    /// templates of different versions are never compared.
    pub version: String,
    /// SHA-256 of the network's package file (`embedding.bin`'s provenance).
    pub network_sha256: String,
    pub chip_source: ChipSource,
    /// `None`: the raw embedding's cosine.
    pub projection: Option<Dlda>,
    /// The one-photo table.
    pub calibration: Calibration,
    /// Tables for 2 … 5 enrolled photos.
    pub enrolled_calibration: Vec<EnrolledCalibration>,
    pub provenance: DeepProvenance,
}

impl DlibModel {
    /// The version string of a projection and chip source.
    pub fn version_of(projection: Option<&Dlda>, chip_source: ChipSource, network_sha256: &str) -> String {
        super::model_version("deep", &postcard::to_stdvec(&(projection, chip_source, network_sha256)).expect("serialisable"))
    }

    pub fn load(path: &Path) -> Result<DlibModel, RecognizeError> {
        let fail = |message: String| RecognizeError::Model { path: path.display().to_string(), message };
        let model: DlibModel =
            read_model(path, "deep recognition model", FORMAT, "facegate train deep (see models/deep.md)").map_err(fail)?;
        if model.projection.as_ref().is_some_and(|d| !d.accepts(facegate_nn::EMBEDDING_DIMS)) {
            return Err(fail("the projection does not take 128-value embeddings".into()));
        }
        Ok(model)
    }

    /// The unit template of an embedding.
    pub fn template(&self, embedding: &Embedding) -> Template {
        let vector = match &self.projection {
            Some(d) => d.project(&embedding.0),
            None => embedding.0.to_vec(),
        };
        Template::new(&self.version, vector)
    }

    /// The thresholds for a subject with `enrolled` templates (the largest table beyond it).
    pub fn calibration_for(&self, enrolled: usize) -> &Calibration {
        super::calibration::table_for(&self.calibration, &self.enrolled_calibration, enrolled)
    }

    pub fn operating_point(&self, fmr: f64, enrolled: usize) -> OperatingPoint {
        self.calibration_for(enrolled).operating_point(fmr)
    }
}

/// The deep recognizer: the embedding network and its model, with what makes a template of a
/// photo: the chip cut at the landmarks' eye and mouth centres, the mirror-averaged embedding, the
/// model's projection (none by default), a unit vector tagged with the model version.
pub struct DlibRecognizer {
    pub model: DlibModel,
    pub network: Embedder,
}

impl DlibRecognizer {
    /// `deep.bin` and `embedding.bin` of `models_dir`; refused when the model was calibrated on
    /// another network than the one in the folder.
    pub fn load(models_dir: &Path) -> Result<DlibRecognizer, RecognizeError> {
        let model = DlibModel::load(&models_dir.join(FILE))?;
        let path = models_dir.join(facegate_nn::weights::FILE);
        let fail = |message: String| RecognizeError::Model { path: path.display().to_string(), message };
        let file = crate::embed::read_file(&path).map_err(|e| fail(e.to_string()))?;
        if file.provenance.sha256 != model.network_sha256 {
            return Err(fail(format!(
                "network {} is not the one {} was calibrated with ({}); run `facegate train deep`",
                file.provenance.sha256, FILE, model.network_sha256
            )));
        }
        let mut network = Embedder::new(&file).map_err(|e| fail(e.to_string()))?;
        network.release_float_weights();
        Ok(DlibRecognizer { model, network })
    }

    pub fn template(&self, photo: &RgbImage, centres: &EyeMouthCentres) -> Template {
        self.model.template(&crate::embed::face_embedding(&self.network, photo, centres))
    }

    /// The template of a chip already cut ([`crate::embed::face_chip`]): what [`Self::template`]
    /// computes, for a caller that also measures the chip.
    pub fn template_of_chip(&self, chip: &facegate_nn::FaceChip) -> Template {
        self.template_and_mirror_pair(chip).0
    }

    /// [`Self::template_of_chip`] and the two embeddings its mean was made of (the chip's and its
    /// mirror image's), for the quality components that compare them.
    pub fn template_and_mirror_pair(&self, chip: &facegate_nn::FaceChip) -> (Template, facegate_nn::MirrorPair) {
        let pair = crate::embed::chip_mirror_pair(&self.network, chip);
        (self.model.template(&pair.mean()), pair)
    }

    /// The best cosine of `probe` against the subject's templates.
    pub fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
        Combine::Max.apply(enrolled.iter().map(|t| probe.cosine(t))).unwrap_or(f32::NEG_INFINITY)
    }
}
