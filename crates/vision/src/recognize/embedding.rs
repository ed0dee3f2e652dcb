//! Recognizers made of one or more embedding networks: SFace alone (`sface.bin`), SFace fused with
//! dlib's network (`fusion.bin`), or a user's own ONNX model (`custom.bin`). Each member network's
//! unit embedding is scaled by the square root of its weight and the scaled vectors are joined,
//! so the template's cosine is the weighted sum of the members' cosines (weights sum to one):
//! score-level fusion that the store, the identification scan and the calibration see as one
//! template. The model file names the members (and the SHA-256 of each network), the weights, the
//! calibrated thresholds and the version its templates carry.

use std::path::Path;

use image::RgbImage;
use serde::{Deserialize, Serialize};

use super::calibration::{Calibration, EnrolledCalibration};
use super::dlib::DeepProvenance;
use super::template::Combine;
use super::{OperatingPoint, RecognizeError, Template};
use crate::embed::onnx::OnnxEmbedder;
use facegate_core::face::EyeMouthCentres;
use facegate_core::geometry::Point;
use facegate_core::model_file::read_model;
use facegate_nn::{Embedder, FaceChip, MirrorPair};

pub const FORMAT: u32 = 1;

/// A member network.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Network {
    /// dlib's ResNet (`embedding.bin`), on its own chip, mirror-averaged.
    Dlib,
    /// An ONNX network `<name>.onnx` with its manifest `<name>.json`.
    Onnx(String),
}

impl std::fmt::Display for Network {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Network::Dlib => f.write_str("dlib"),
            Network::Onnx(name) => f.write_str(name),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Member {
    pub network: Network,
    /// SHA-256 of the network's file (dlib: of its package file, as `embedding.bin` records it).
    pub sha256: String,
    /// Share of this member's cosine in the score.
    pub weight: f32,
    /// How the face is prepared for the network ([`crate::embed::onnx::Manifest::preprocessing`];
    /// [`DLIB_PREPROCESSING`] for dlib's network): part of the version, and checked at load.
    pub preprocessing: String,
}

/// dlib's network's preparation: its chip at the eye and mouth centres, mirror-averaged.
pub const DLIB_PREPROCESSING: &str = "dlib chip 150 mirror true";

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EmbeddingModel {
    pub format: u32,
    /// `emb-` and the first 12 hex digits of the SHA-256 of the members: templates of different
    /// versions are never compared.
    pub version: String,
    pub members: Vec<Member>,
    /// The one-photo table.
    pub calibration: Calibration,
    /// Tables for 2 … 5 enrolled photos.
    pub enrolled_calibration: Vec<EnrolledCalibration>,
    pub provenance: DeepProvenance,
}

impl EmbeddingModel {
    pub fn version_of(members: &[Member]) -> String {
        super::model_version("emb", &postcard::to_stdvec(members).expect("serialisable"))
    }

    pub fn load(path: &Path) -> Result<EmbeddingModel, RecognizeError> {
        let fail = |message: String| RecognizeError::Model { path: path.display().to_string(), message };
        let model: EmbeddingModel =
            read_model(path, "embedding recognition model", FORMAT, "facegate train embedding (see docs/models.md)").map_err(fail)?;
        let total: f32 = model.members.iter().map(|m| m.weight).sum();
        if model.members.is_empty() || model.members.iter().any(|m| !(0.0..=1.0).contains(&m.weight)) || (total - 1.0).abs() > 1e-4 {
            return Err(fail("member weights must lie in 0–1 and sum to 1".into()));
        }
        Ok(model)
    }

    /// The template of the members' unit embeddings, in the members' order.
    pub fn template(&self, embeddings: &[Vec<f32>]) -> Template {
        Template::new(&self.version, fuse(&self.members, embeddings))
    }

    /// The thresholds for a subject with `enrolled` templates (the largest table beyond it).
    pub fn calibration_for(&self, enrolled: usize) -> &Calibration {
        super::calibration::table_for(&self.calibration, &self.enrolled_calibration, enrolled)
    }

    pub fn operating_point(&self, fmr: f64, enrolled: usize) -> OperatingPoint {
        self.calibration_for(enrolled).operating_point(fmr)
    }
}

/// The members' unit embeddings scaled by the square roots of their weights and joined: its dot
/// product with another such vector is the weighted sum of the members' cosines.
pub fn fuse(members: &[Member], embeddings: &[Vec<f32>]) -> Vec<f32> {
    assert_eq!(members.len(), embeddings.len(), "one embedding per member");
    let mut out = Vec::with_capacity(embeddings.iter().map(Vec::len).sum());
    for (m, e) in members.iter().zip(embeddings) {
        let scale = m.weight.sqrt() / e.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-12);
        out.extend(e.iter().map(|x| x * scale));
    }
    out
}

/// A loaded member network.
pub enum MemberNetwork {
    Dlib(Embedder),
    Onnx(OnnxEmbedder),
}

/// What a photo's face gave: the template, and dlib's mirror pair when dlib is a member (the
/// quality score's mirror components).
pub struct EmbeddedFace {
    pub template: Template,
    pub dlib_pair: Option<MirrorPair>,
}

pub struct EmbeddingRecognizer {
    pub model: EmbeddingModel,
    pub networks: Vec<MemberNetwork>,
}

impl EmbeddingRecognizer {
    /// `<models_dir>/<file>` and its member networks from the same folder; refused when a network
    /// is not the one the model was calibrated with.
    pub fn load(models_dir: &Path, file: &str) -> Result<EmbeddingRecognizer, RecognizeError> {
        let model = EmbeddingModel::load(&models_dir.join(file))?;
        let networks = model.members.iter().map(|m| load_member(models_dir, m)).collect::<Result<Vec<_>, _>>()?;
        Ok(EmbeddingRecognizer { model, networks })
    }

    /// The template of the face with eye and mouth centres `centres` (and the detector's five
    /// points, when it gave them) in `photo`. `dlib_chip`: dlib's chip when the caller cut it.
    pub fn embed(
        &self,
        photo: &RgbImage,
        centres: &EyeMouthCentres,
        points: Option<&[Point; 5]>,
        dlib_chip: Option<&FaceChip>,
    ) -> EmbeddedFace {
        let mut dlib_pair = None;
        let embeddings: Vec<Vec<f32>> = self
            .networks
            .iter()
            .map(|network| {
                let (embedding, pair) = self.embed_with(network, photo, centres, points, dlib_chip);
                dlib_pair = dlib_pair.or(pair);
                embedding
            })
            .collect();
        EmbeddedFace { template: self.model.template(&embeddings), dlib_pair }
    }

    /// One member network's embedding of the face (before the fusion's weighting), and dlib's
    /// mirror pair when the network is dlib's.
    pub fn embed_with(
        &self,
        network: &MemberNetwork,
        photo: &RgbImage,
        centres: &EyeMouthCentres,
        points: Option<&[Point; 5]>,
        dlib_chip: Option<&FaceChip>,
    ) -> (Vec<f32>, Option<MirrorPair>) {
        match network {
            MemberNetwork::Dlib(net) => {
                let owned;
                let chip = match dlib_chip {
                    Some(chip) => chip,
                    None => {
                        owned = crate::embed::face_chip(photo, centres);
                        &owned
                    }
                };
                let pair = crate::embed::chip_mirror_pair(net, chip);
                (pair.mean().0.to_vec(), Some(pair))
            }
            MemberNetwork::Onnx(net) => (net.embed(&net.chip(photo, centres, points)), None),
        }
    }

    /// The best cosine of `probe` against the subject's templates.
    pub fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
        Combine::Max.apply(enrolled.iter().map(|t| probe.cosine(t))).unwrap_or(f32::NEG_INFINITY)
    }
}

fn load_member(models_dir: &Path, member: &Member) -> Result<MemberNetwork, RecognizeError> {
    let mismatch = |path: &Path, found: &str| RecognizeError::Model {
        path: path.display().to_string(),
        message: format!(
            "network {found} is not the one the model was calibrated with ({}); run `facegate train embedding`",
            member.sha256
        ),
    };
    match &member.network {
        Network::Dlib => {
            let path = models_dir.join(facegate_nn::weights::FILE);
            let fail = |message: String| RecognizeError::Model { path: path.display().to_string(), message };
            let file = crate::embed::read_file(&path).map_err(|e| fail(e.to_string()))?;
            if file.provenance.sha256 != member.sha256 {
                return Err(mismatch(&path, &file.provenance.sha256));
            }
            // A recognizer never changes its networks' arithmetic: their float copies can go.
            let mut network = Embedder::new(&file).map_err(|e| fail(e.to_string()))?;
            network.release_float_weights();
            Ok(MemberNetwork::Dlib(network))
        }
        Network::Onnx(name) => {
            let mut net = OnnxEmbedder::load(models_dir, name)
                .map_err(|e| RecognizeError::Model { path: models_dir.join(name).display().to_string(), message: e.to_string() })?;
            net.release_float_weights();
            if !net.manifest.sha256.eq_ignore_ascii_case(&member.sha256) {
                return Err(mismatch(&models_dir.join(format!("{name}.onnx")), &net.manifest.sha256));
            }
            if net.manifest.preprocessing() != member.preprocessing {
                return Err(RecognizeError::Model {
                    path: models_dir.join(format!("{name}.json")).display().to_string(),
                    message: format!(
                        "the manifest prepares faces as \"{}\", the model was calibrated with \"{}\"; run `facegate train embedding`",
                        net.manifest.preprocessing(),
                        member.preprocessing
                    ),
                });
            }
            Ok(MemberNetwork::Onnx(net))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn member(weight: f32) -> Member {
        Member { network: Network::Dlib, sha256: String::new(), weight, preprocessing: DLIB_PREPROCESSING.into() }
    }

    #[test]
    fn fused_dot_product_is_the_weighted_sum_of_cosines() {
        let members = [member(0.3), Member { network: Network::Onnx("sface".into()), ..member(0.7) }];
        let a = vec![vec![3.0, 4.0], vec![1.0, 0.0, 0.0]];
        let b = vec![vec![4.0, 3.0], vec![0.0, 1.0, 0.0]];
        let (fa, fb) = (fuse(&members, &a), fuse(&members, &b));
        let dot: f32 = fa.iter().zip(&fb).map(|(x, y)| x * y).sum();
        assert!((dot - (0.3 * 24.0 / 25.0 + 0.7 * 0.0)).abs() < 1e-6, "{dot}");
        let norm: f32 = fa.iter().map(|x| x * x).sum();
        assert!((norm - 1.0).abs() < 1e-6);
    }

    #[test]
    fn the_version_names_the_members_and_weights() {
        let one = EmbeddingModel::version_of(&[member(1.0)]);
        assert!(one.starts_with("emb-") && one.len() == 16);
        assert_ne!(one, EmbeddingModel::version_of(&[member(0.5), member(0.5)]));
        assert_eq!(one, EmbeddingModel::version_of(&[member(1.0)]));
    }
}
