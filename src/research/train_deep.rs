//! The deep recognizer's data and calibration: IMM, ORL and LFW with a person-disjoint split
//! (LFW split by a hash of the name), the embeddings of every photo through the service's own
//! front end ([`FaceFinder`], then [`crate::embed::face_embedding`] as [`DeepRecognizer`] computes
//! them), cached on disk, and the threshold tables per enrolment size that `facegate train deep`
//! writes into the model.
//!
//! [`DeepRecognizer`]: crate::recognize::DeepRecognizer

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::Digest;

use super::Progress;
use super::dataset::{self, Split, imm_is_test_person, lfw_split};
use super::eval::protocol::{all_pairs_by, enrolment_scores_by};
use crate::embed::{Embedder, face_embedding};
use crate::morph::FaceModel;
use crate::pipeline::FaceFinder;
use crate::recognize::calibration::CALIBRATED_FMRS;
use crate::recognize::deep::{ChipSource, DeepModel, DeepProvenance, FORMAT};
use crate::recognize::template::Combine;
use crate::recognize::{Calibration, Dlda, EnrolledCalibration, MAX_CALIBRATED_ENROLMENT};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Set {
    Imm,
    Orl,
    Lfw,
}

#[derive(Debug, Clone)]
pub struct Sample {
    pub label: String,
    pub image: PathBuf,
    pub set: Set,
    /// IMM view (1–6), when the set has views.
    pub view: Option<u32>,
    pub split: Split,
}

/// IMM, ORL and LFW under `shared/data`, labelled and split by person.
pub fn list_samples(shared: &Path) -> Result<Vec<Sample>, dataset::DatasetError> {
    let mut out = Vec::new();
    for (set, name) in [(Set::Imm, "imm"), (Set::Orl, "orl"), (Set::Lfw, "lfw")] {
        for item in dataset::list_labelled(&shared.join("data").join(name))? {
            let person = item.label.split_once('-').map_or("", |(_, p)| p).to_string();
            let split = match set {
                Set::Lfw => lfw_split(&person),
                _ => {
                    let n: Option<u32> = person.trim_start_matches('s').parse().ok();
                    if n.is_some_and(imm_is_test_person) { Split::Test } else { Split::Train }
                }
            };
            let view = (set == Set::Imm)
                .then(|| dataset::parse_imm_name(&item.image.file_name().unwrap_or_default().to_string_lossy()).map(|(_, v)| v))
                .flatten();
            out.push(Sample { label: item.label, image: item.image, set, view, split });
        }
    }
    Ok(out)
}

/// The embeddings of one photo (mirror-averaged, as the deep recognizer computes them): of the
/// photo's own chip, and of the chip of the 3DMM frontal rendering (when the model is loaded and
/// the fit succeeds). `None`: no face found.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct PhotoEmbeddings {
    pub photo: Option<Vec<f32>>,
    pub frontal: Option<Vec<f32>>,
}

/// What the deep front end needs: the service's face finder, the 3DMM (for the frontal
/// rendering's embedding, a research comparison) and the network.
pub struct DeepFrontEnd<'a> {
    pub finder: &'a FaceFinder,
    pub face_model: Option<&'a FaceModel>,
    pub network: &'a Embedder,
}

impl DeepFrontEnd<'_> {
    /// The embeddings of one photo: the largest face, the service's landmarks, then the photo's
    /// chip and (with the 3DMM) the frontal rendering's chip.
    pub fn embed(&self, photo: &crate::core::imaging::Photo) -> PhotoEmbeddings {
        let Ok(located) = self.finder.locate(&photo.gray) else { return PhotoEmbeddings::default() };
        let lm = &located.landmarks;
        let frontal = self.face_model.and_then(|model| {
            let fit = model.fit(&lm.points, photo.width(), photo.height()).ok()?;
            let f = model.frontalize(photo, &fit).ok()?;
            Some(face_embedding(self.network, &f.image, &f.keypoints).0.to_vec())
        });
        PhotoEmbeddings { photo: Some(face_embedding(self.network, &photo.rgb, &lm.keypoints).0.to_vec()), frontal }
    }
}

/// Embeddings of every sample, on `threads` threads.
pub fn embed_samples(front: &DeepFrontEnd, samples: &[Sample], threads: usize, progress: &dyn Progress) -> Vec<PhotoEmbeddings> {
    progress.begin(samples.len() as u64, "embed");
    let out = super::par_map(samples, threads, |s| {
        let e = match crate::core::imaging::open(&s.image) {
            Ok(photo) => front.embed(&photo),
            Err(e) => {
                progress.note(&format!("{}: {e}", s.image.display()));
                PhotoEmbeddings::default()
            }
        };
        progress.step();
        e
    });
    progress.end();
    out
}

/// A cache of [`embed_samples`] keyed by image path and by the model files that made it.
#[derive(Serialize, Deserialize)]
struct Cache {
    key: String,
    entries: Vec<(String, PhotoEmbeddings)>,
}

/// The key of the front end's models: a change to any of them invalidates a cache.
pub fn models_key(models_dir: &Path) -> String {
    let mut h = sha2::Sha256::new();
    for f in ["asm.bin", "asm3d.bin", "embedding.bin"] {
        h.update(std::fs::read(models_dir.join(f)).unwrap_or_default());
    }
    h.update(b"mirror-averaged");
    h.finalize().iter().take(8).map(|b| format!("{b:02x}")).collect()
}

/// Reads the cached embeddings of `samples` if `path` holds them for `key`.
pub fn read_cache(path: &Path, key: &str, samples: &[Sample]) -> Option<Vec<PhotoEmbeddings>> {
    let cache: Cache = postcard::from_bytes(&std::fs::read(path).ok()?).ok()?;
    if cache.key != key {
        return None;
    }
    let map: std::collections::HashMap<String, PhotoEmbeddings> = cache.entries.into_iter().collect();
    samples.iter().map(|s| map.get(&s.image.display().to_string()).cloned()).collect()
}

pub fn write_cache(path: &Path, key: &str, samples: &[Sample], embeddings: &[PhotoEmbeddings]) -> std::io::Result<()> {
    let entries = samples.iter().zip(embeddings).map(|(s, e)| (s.image.display().to_string(), e.clone())).collect();
    let bytes = postcard::to_stdvec(&Cache { key: key.to_string(), entries }).map_err(std::io::Error::other)?;
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(path, bytes)
}

/// Calibrates the deep model's threshold tables (1 … [`MAX_CALIBRATED_ENROLMENT`] photos
/// enrolled) on `calibration` (label, unit template), scored as the service scores: the cosine, the
/// best of a subject's templates.
pub fn calibrate(calibration: &[(&str, Vec<f32>)], source: &str) -> (Calibration, Vec<EnrolledCalibration>) {
    let labels: Vec<&str> = calibration.iter().map(|(l, _)| *l).collect();
    let score = |a: usize, b: usize| calibration[a].1.iter().zip(&calibration[b].1).map(|(x, y)| x * y).sum::<f32>();
    let table = |k: usize| {
        let (g, i) = if k == 1 { all_pairs_by(&labels, &score) } else { enrolment_scores_by(&labels, k, Combine::Max, &score) };
        Calibration::from_scores(&g, &i, &CALIBRATED_FMRS, &format!("{source}; {k} photo(s) enrolled"))
    };
    let one = table(1);
    let enrolled = (2..=MAX_CALIBRATED_ENROLMENT).map(|k| EnrolledCalibration { enrolled: k, calibration: table(k) }).collect();
    (one, enrolled)
}

/// Is this sample one of the calibration persons: LFW's calibration split, IMM's and ORL's
/// held-out persons (as the classical model calibrates)?
pub fn is_calibration(s: &Sample) -> bool {
    match s.set {
        Set::Lfw => s.split == Split::Calibration,
        _ => s.split == Split::Test,
    }
}

/// The deep model: `projection` (none: the embedding's cosine), its version, and the thresholds
/// calibrated on the calibration persons' embeddings.
pub fn train(
    samples: &[Sample],
    embeddings: &[PhotoEmbeddings],
    projection: Option<Dlda>,
    network_sha256: &str,
    provenance: DeepProvenance,
) -> DeepModel {
    let version = DeepModel::version_of(projection.as_ref(), ChipSource::Photo, network_sha256);
    let mut model = DeepModel {
        format: FORMAT,
        version,
        network_sha256: network_sha256.to_string(),
        chip_source: ChipSource::Photo,
        projection,
        calibration: Calibration::from_scores(&[], &[], &[], ""),
        enrolled_calibration: Vec::new(),
        provenance,
    };
    let calibration: Vec<(&str, Vec<f32>)> = samples
        .iter()
        .zip(embeddings)
        .filter(|(s, _)| is_calibration(s))
        .filter_map(|(s, e)| {
            e.photo
                .as_deref()
                .map(|v| (s.label.as_str(), model.template(&crate::embed::Embedding(v.try_into().expect("128 values"))).vector))
        })
        .collect();
    let source =
        format!("{} photos: LFW calibration persons, IMM and ORL held-out persons (1, 2, 3, 5, 10, 15, 20, 25, 30)", calibration.len());
    (model.calibration, model.enrolled_calibration) = calibrate(&calibration, &source);
    model
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lfw_split_is_person_disjoint_and_near_60_20_20() {
        let samples = list_samples(&crate::config::shared_dir()).unwrap();
        let lfw: Vec<&Sample> = samples.iter().filter(|s| s.set == Set::Lfw).collect();
        assert_eq!(lfw.len(), 4990);
        let mut persons: Vec<(&str, Split)> = lfw.iter().map(|s| (s.label.as_str(), s.split)).collect();
        persons.sort_by(|a, b| a.0.cmp(b.0));
        persons.dedup();
        // One split per person.
        assert!(persons.windows(2).all(|w| w[0].0 != w[1].0));
        let n = persons.len() as f64;
        let share = |split| persons.iter().filter(|p| p.1 == split).count() as f64 / n;
        assert!((share(Split::Train) - 0.6).abs() < 0.05 && (share(Split::Test) - 0.2).abs() < 0.05);
        // IMM and ORL keep the project's held-out persons.
        assert!(samples.iter().filter(|s| s.set == Set::Imm && s.split == Split::Test).count() == 9 * 6);
        // The classical training holds out the same LFW persons.
        let faces = crate::research::train_dlda::list_faces(&[crate::config::shared_dir().join("data/lfw")]).unwrap();
        assert_eq!(faces.len(), 4990);
        for f in &faces {
            let person = f.label.strip_prefix("lfw-").unwrap();
            assert_eq!(f.held_out, lfw_split(person) != Split::Train, "{}", f.label);
        }
    }
}
