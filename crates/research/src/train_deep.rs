//! The deep recognizer's data and calibration: IMM, ORL and LFW with a person-disjoint split
//! (LFW split by a hash of the name), the embeddings of every photo through the service's own
//! front end ([`FaceFinder`], then [`facegate_vision::embed::face_embedding`] as [`DlibRecognizer`]
//! computes them), kept in the research cache ([`crate::cache`]), and the threshold tables per
//! enrolment size that `facegate train deep` writes into the model.
//!
//! [`DlibRecognizer`]: facegate_vision::recognize::DlibRecognizer

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::Progress;
use super::cache::{self, CacheKey, ModelFiles, map_samples};
use super::dataset::{self, Split, imm_is_test_person, lfw_split};
use super::eval::protocol::{all_pairs_by, enrollment_scores_by};
use facegate_morph::FaceModel;
use facegate_nn::Embedder;
use facegate_vision::embed::face_embedding;
use facegate_vision::pipeline::{FaceFinder, load_face_model};
use facegate_vision::recognize::Combine;
use facegate_vision::recognize::calibration::CALIBRATED_FMRS;
use facegate_vision::recognize::dlib::{ChipSource, DeepProvenance, DlibModel, FORMAT};
use facegate_vision::recognize::{Calibration, Dlda, EnrolledCalibration, MAX_CALIBRATED_ENROLLMENT};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Set {
    Imm,
    Orl,
    Lfw,
}

impl Set {
    pub const ALL: [Set; 3] = [Set::Imm, Set::Orl, Set::Lfw];

    /// Its name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Set::Imm => "IMM",
            Set::Orl => "ORL",
            Set::Lfw => "LFW",
        }
    }
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

/// The models the deep and quality front ends run on, loaded: the service's face finder, the 3DMM
/// (when the Surrey Face Model loads) and the network.
pub struct FrontEndModels {
    pub finder: FaceFinder,
    pub face_model: Option<FaceModel>,
    pub network: Embedder,
}

impl FrontEndModels {
    /// The finder and the network from `models_dir`, the 3DMM from `sfm_dir`.
    pub fn load(models_dir: &Path, sfm_dir: &Path) -> anyhow::Result<FrontEndModels> {
        let finder = FaceFinder::load(models_dir)?;
        let face_model = load_face_model(Some(sfm_dir));
        Ok(FrontEndModels { finder, face_model, network: facegate_vision::embed::load(models_dir)? })
    }

    /// The files [`FrontEndModels::load`] reads: the key of a cache of what they compute.
    pub fn files(models_dir: &Path, sfm_dir: &Path) -> ModelFiles {
        ModelFiles::new().finder(models_dir).model(models_dir, facegate_nn::weights::FILE).sfm(sfm_dir)
    }

    pub fn deep(&self) -> DeepFrontEnd<'_> {
        DeepFrontEnd { finder: &self.finder, face_model: self.face_model.as_ref(), network: &self.network }
    }
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
    pub fn embed(&self, photo: &facegate_core::imaging::Photo) -> PhotoEmbeddings {
        let Ok(located) = self.finder.locate(&photo.gray) else { return PhotoEmbeddings::default() };
        let lm = &located.landmarks;
        let frontal = self.face_model.and_then(|model| {
            let fit = model.fit(&lm.points, photo.width(), photo.height()).ok()?;
            let f = model.frontalize(photo, &fit).ok()?;
            Some(face_embedding(self.network, &f.image, &f.centres).0.to_vec())
        });
        PhotoEmbeddings { photo: Some(face_embedding(self.network, &photo.rgb, &lm.centres).0.to_vec()), frontal }
    }
}

/// Embeddings of every sample, on `threads` threads.
pub fn embed_samples(front: &DeepFrontEnd, samples: &[Sample], threads: usize, progress: &dyn Progress) -> Vec<PhotoEmbeddings> {
    map_samples(samples, threads, "embed", progress, |s| match facegate_core::imaging::open(&s.image) {
        Ok(photo) => front.embed(&photo),
        Err(e) => {
            progress.note(&format!("{}: {e}", s.image.display()));
            PhotoEmbeddings::default()
        }
    })
}

/// What names a sample in a cache key: its photo's path.
pub fn cache_id(s: &Sample) -> String {
    s.image.display().to_string()
}

/// [`embed_samples`] through the research cache in `cache_dir` (see [`crate::cache`]): the front
/// end (`models_dir`, `sfm_dir`) is loaded and run only when the cache does not hold the results.
pub fn embeddings(
    cache_dir: &Path,
    models_dir: &Path,
    sfm_dir: &Path,
    samples: &[Sample],
    threads: usize,
    progress: &dyn Progress,
) -> anyhow::Result<Vec<PhotoEmbeddings>> {
    let key = CacheKey::new("deep-embeddings", &FrontEndModels::files(models_dir, sfm_dir), &[], samples.iter().map(cache_id));
    cache::get_or_compute(cache_dir, &key, samples.len(), progress, || {
        let models = FrontEndModels::load(models_dir, sfm_dir)?;
        Ok(embed_samples(&models.deep(), samples, threads, progress))
    })
}

/// Calibrates the deep model's threshold tables (1 … [`MAX_CALIBRATED_ENROLMENT`] photos
/// enrolled) on `calibration` (label, unit template), scored as the service scores: the cosine, the
/// best of a subject's templates.
pub fn calibrate(calibration: &[(&str, Vec<f32>)], source: &str) -> (Calibration, Vec<EnrolledCalibration>) {
    let labels: Vec<&str> = calibration.iter().map(|(l, _)| *l).collect();
    let score = |a: usize, b: usize| crate::eval::protocol::unit_cosine(&calibration[a].1, &calibration[b].1);
    let table = |k: usize| {
        let (g, i) = if k == 1 { all_pairs_by(&labels, &score) } else { enrollment_scores_by(&labels, k, Combine::Max, &score) };
        Calibration::from_scores(&g, &i, &CALIBRATED_FMRS, &format!("{source}; {k} photo(s) enrolled"))
    };
    let one = table(1);
    let enrolled = (2..=MAX_CALIBRATED_ENROLLMENT).map(|k| EnrolledCalibration { enrolled: k, calibration: table(k) }).collect();
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
) -> DlibModel {
    let version = DlibModel::version_of(projection.as_ref(), ChipSource::Photo, network_sha256);
    let mut model = DlibModel {
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
                .map(|v| (s.label.as_str(), model.template(&facegate_nn::Embedding(v.try_into().expect("128 values"))).vector))
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
        let samples = list_samples(&facegate_paths::shared_dir()).unwrap();
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
        let faces = crate::train_dlda::list_faces(&[facegate_paths::shared_dir().join("data/lfw")]).unwrap();
        assert_eq!(faces.len(), 4990);
        for f in &faces {
            let person = f.label.strip_prefix("lfw-").unwrap();
            assert_eq!(f.held_out, lfw_split(person) != Split::Train, "{}", f.label);
        }
    }
}
