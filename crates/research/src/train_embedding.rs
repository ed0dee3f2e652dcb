//! Recognizers of one or more embedding networks (SFace, dlib's, a user's ONNX model, their
//! fusion): the ONNX networks' embeddings of every IMM, ORL and LFW photo through the service's
//! front end (cached), the fusion weight chosen by person-disjoint cross-validation over LFW's
//! training persons, and the thresholds `facegate train embedding` writes into the model.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::Progress;
use super::cache::{self, CacheKey, ModelFiles, map_samples};
use super::dataset::Split;
use super::eval::protocol::all_pairs_by;
use super::eval::verification::{VerificationSummary, summarize};
use super::train_deep::{PhotoEmbeddings, Sample, Set, cache_id, is_calibration};
use facegate_vision::embed::onnx::OnnxEmbedder;
use facegate_vision::pipeline::FaceFinder;
use facegate_vision::recognize::dlib::DeepProvenance;
use facegate_vision::recognize::embedding::{EmbeddingModel, FORMAT, Member, Network, fuse};

/// One photo through an ONNX network: the unit embedding of the face aligned by the detector's
/// five points (when it gave them; else by the eye and mouth centres), of its mirror image, and of
/// the face aligned by the landmarks' eye and mouth centres. `None`: no face found.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct OnnxPhotoEmbeddings {
    pub five_points: Option<Vec<f32>>,
    pub five_points_mirrored: Option<Vec<f32>>,
    pub centres: Option<Vec<f32>>,
}

/// How an ONNX network's input is aligned and whether the mirror image is averaged in: the
/// variants [`OnnxPhotoEmbeddings`] holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum OnnxVariant {
    FivePoints,
    FivePointsMirrorAveraged,
    Centres,
}

impl OnnxPhotoEmbeddings {
    pub fn variant(&self, v: OnnxVariant) -> Option<Vec<f32>> {
        match v {
            OnnxVariant::FivePoints => self.five_points.clone(),
            OnnxVariant::Centres => self.centres.clone(),
            OnnxVariant::FivePointsMirrorAveraged => {
                let (a, b) = (self.five_points.as_ref()?, self.five_points_mirrored.as_ref()?);
                Some(facegate_core::vector::unit(a.iter().zip(b).map(|(x, y)| x + y).collect()))
            }
        }
    }

    /// The variant the runtime computes for a network whose manifest says `mirror`.
    pub fn runtime(&self, mirror: bool) -> Option<Vec<f32>> {
        self.variant(if mirror { OnnxVariant::FivePointsMirrorAveraged } else { OnnxVariant::FivePoints })
    }
}

/// The version of the ONNX engines' kernels (facegate's own chain kernels, tract's) in the cache key.
const ENGINE: &str = "chain-1/tract-0.23.9";

/// The embeddings of every sample through `<models_dir>/<name>.onnx`, through the research cache.
pub fn onnx_embeddings(
    cache_dir: &Path,
    models_dir: &Path,
    name: &str,
    samples: &[Sample],
    threads: usize,
    progress: &dyn Progress,
) -> anyhow::Result<Vec<OnnxPhotoEmbeddings>> {
    let files = ModelFiles::new().finder(models_dir).model(models_dir, &format!("{name}.onnx")).model(models_dir, &format!("{name}.json"));
    // The engine that runs the network is part of the key: its kernels decide the last digits.
    let key = CacheKey::new(&format!("onnx-embeddings-{name}"), &files, ENGINE.as_bytes(), samples.iter().map(cache_id));
    cache::get_or_compute(cache_dir, &key, samples.len(), progress, || {
        let finder = FaceFinder::load(models_dir)?;
        let network = OnnxEmbedder::load(models_dir, name)?;
        Ok(map_samples(samples, threads, name, progress, |s| {
            let Ok(photo) = facegate_core::imaging::open(&s.image) else { return OnnxPhotoEmbeddings::default() };
            let Ok(located) = finder.locate(&photo.gray) else { return OnnxPhotoEmbeddings::default() };
            let k = &located.landmarks.centres;
            let chip = network.chip(&photo.rgb, k, located.face.points.as_ref());
            let plain = |chip: &facegate_nn::FaceChip| network.embed_once(chip);
            OnnxPhotoEmbeddings {
                five_points: Some(plain(&chip)),
                five_points_mirrored: Some(plain(&chip.mirrored())),
                centres: Some(plain(&network.chip(&photo.rgb, k, None))),
            }
        }))
    })
}

/// The unit embeddings of the members for every sample (`None` where any member found no face).
pub fn member_embeddings(members: &[Vec<Option<Vec<f32>>>], samples: usize) -> Vec<Option<Vec<Vec<f32>>>> {
    (0..samples).map(|i| members.iter().map(|m| m[i].clone()).collect::<Option<Vec<_>>>()).collect()
}

/// Dlib's embeddings as a member's column (the photo's own chip, mirror-averaged).
pub fn dlib_column(embeddings: &[PhotoEmbeddings]) -> Vec<Option<Vec<f32>>> {
    embeddings.iter().map(|e| e.photo.clone()).collect()
}

/// The verification summary of the samples `filter` keeps, every pair, members fused by `members`.
pub fn summary_of(
    samples: &[Sample],
    embeddings: &[Option<Vec<Vec<f32>>>],
    members: &[Member],
    filter: &dyn Fn(&Sample) -> bool,
) -> VerificationSummary {
    let items: Vec<(&str, Vec<f32>)> = samples
        .iter()
        .zip(embeddings)
        .filter(|(s, _)| filter(s))
        .filter_map(|(s, e)| e.as_ref().map(|e| (s.label.as_str(), fuse(members, e))))
        .collect();
    let labels: Vec<&str> = items.iter().map(|(l, _)| *l).collect();
    let (g, i) = all_pairs_by(&labels, &|a, b| crate::eval::protocol::unit_cosine(&items[a].1, &items[b].1));
    summarize(&g, &i)
}

/// Person fold of an LFW person (by the same hash family as the split, another byte).
pub fn person_fold(label: &str, folds: usize) -> usize {
    use sha2::Digest;
    let h = sha2::Sha256::digest(format!("fold:{label}").as_bytes());
    h[0] as usize % folds.max(1)
}

/// One weight's cross-validation: the summary on each fold of LFW's training persons.
#[derive(Debug, Clone, Serialize)]
pub struct WeightRow {
    /// The second member's weight (the first's is 1 − w).
    pub weight: f32,
    pub folds: Vec<VerificationSummary>,
    pub mean_eer: f64,
    pub mean_fnmr_at_fmr_1e3: f64,
}

/// The two-member fusion's weight on a grid, scored fold by fold over LFW's training persons (a
/// pair is scored within a fold: its persons are disjoint from the others'); the chosen weight
/// has the lowest mean FNMR at FMR 1e-3 plus EER.
pub fn fusion_weight_cv(
    samples: &[Sample],
    embeddings: &[Option<Vec<Vec<f32>>>],
    networks: [&Network; 2],
    folds: usize,
) -> (f32, Vec<WeightRow>) {
    let rows: Vec<WeightRow> = (0..=10)
        .map(|step| {
            let w = step as f32 / 10.0;
            let members = [
                Member { network: networks[0].clone(), sha256: String::new(), weight: 1.0 - w, preprocessing: String::new() },
                Member { network: networks[1].clone(), sha256: String::new(), weight: w, preprocessing: String::new() },
            ];
            let summaries: Vec<VerificationSummary> = (0..folds)
                .map(|f| {
                    summary_of(samples, embeddings, &members, &|s| {
                        s.set == Set::Lfw && s.split == Split::Train && person_fold(&s.label, folds) == f
                    })
                })
                .collect();
            let mean = |g: &dyn Fn(&VerificationSummary) -> f64| summaries.iter().map(g).sum::<f64>() / folds as f64;
            WeightRow { weight: w, mean_eer: mean(&|s| s.eer), mean_fnmr_at_fmr_1e3: mean(&|s| s.fnmr_at_fmr_1e3), folds: summaries }
        })
        .collect();
    let best = rows
        .iter()
        .min_by(|a, b| (a.mean_eer + a.mean_fnmr_at_fmr_1e3).total_cmp(&(b.mean_eer + b.mean_fnmr_at_fmr_1e3)))
        .map_or(0.5, |r| r.weight);
    (best, rows)
}

/// The model of `members` (weights set), calibrated on the calibration persons as the deep model is.
pub fn train(samples: &[Sample], embeddings: &[Option<Vec<Vec<f32>>>], members: Vec<Member>, provenance: DeepProvenance) -> EmbeddingModel {
    let calibration: Vec<(&str, Vec<f32>)> = samples
        .iter()
        .zip(embeddings)
        .filter(|(s, _)| is_calibration(s))
        .filter_map(|(s, e)| e.as_ref().map(|e| (s.label.as_str(), fuse(&members, e))))
        .collect();
    let source =
        format!("{} photos: LFW calibration persons, IMM and ORL held-out persons (1, 2, 3, 5, 10, 15, 20, 25, 30)", calibration.len());
    let (one, enrolled) = super::train_deep::calibrate(&calibration, &source);
    EmbeddingModel {
        format: FORMAT,
        version: EmbeddingModel::version_of(&members),
        members,
        calibration: one,
        enrolled_calibration: enrolled,
        provenance,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn person_folds_cover_every_fold_and_keep_a_person_in_one() {
        let names: Vec<String> = (0..200).map(|i| format!("lfw-person{i}")).collect();
        let folds: Vec<usize> = names.iter().map(|n| person_fold(n, 5)).collect();
        assert!((0..5).all(|f| folds.contains(&f)));
        assert_eq!(person_fold("lfw-person7", 5), folds[7]);
    }

    #[test]
    fn a_photo_missing_in_any_member_is_missing_in_the_fusion() {
        let a = vec![Some(vec![1.0]), None];
        let b = vec![Some(vec![2.0]), Some(vec![3.0])];
        let joined = member_embeddings(&[a, b], 2);
        assert_eq!(joined[0], Some(vec![vec![1.0], vec![2.0]]));
        assert_eq!(joined[1], None);
    }
}
