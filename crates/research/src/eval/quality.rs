//! Face image quality research: every photo of IMM, ORL and LFW measured through the service's
//! own front end (the deep recognizer's landmarks, 3DMM fit, chip and embedding, then
//! [`facegate_vision::quality::components`]), kept in the research cache ([`crate::cache`]); and the
//! error-versus-discard characteristic (FNMR at the recognizer's fixed FMR-1e-3 threshold against the share of
//! lowest-quality photos discarded) on the held-out persons. The unified score's model is trained
//! on the training persons by [`crate::train_quality`].

use std::path::Path;

use rand::SeedableRng;
use rand::seq::SliceRandom;
use serde::{Deserialize, Serialize};

use super::protocol::{photos_by_person, unit_cosine};
use crate::Progress;
use crate::cache::{self, CacheKey, map_samples};
use crate::dataset::Split;
use crate::train_deep::{FrontEndModels, Sample, Set, cache_id};
use facegate_morph::FaceModel;
use facegate_nn::Embedder;
use facegate_vision::pipeline::FaceFinder;
use facegate_vision::quality::{Components, QualityModel};

/// One photo as the service sees it: its mirror-averaged embedding and its quality components.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Measured {
    pub embedding: Vec<f32>,
    pub components: Components,
}

/// The service's front end, for measuring photos.
pub struct QualityFrontEnd<'a> {
    pub finder: &'a FaceFinder,
    pub face_model: Option<&'a FaceModel>,
    pub network: &'a Embedder,
}

impl QualityFrontEnd<'_> {
    /// The largest face's embedding and quality components, as `Pipeline::analyze` computes them on
    /// the deep path; `None`: no face.
    pub fn measure(&self, photo: &facegate_core::imaging::Photo) -> Option<Measured> {
        let located = self.finder.locate(&photo.gray).ok()?;
        let fit = self.face_model.and_then(|m| m.fit(&located.landmarks.points, photo.width(), photo.height()).ok());
        let (chip, components) = facegate_vision::pipeline::quality_components(
            photo,
            &located.landmarks,
            fit.as_ref().map(|f| f.pose),
            fit.as_ref().map(|f| f.residual_px),
        );
        let mirror = facegate_vision::embed::chip_mirror_pair(self.network, &chip);
        Some(Measured { embedding: mirror.mean().0.to_vec(), components: components.with_mirror(&mirror) })
    }
}

/// [`QualityFrontEnd::measure`] of every sample, on `threads` threads.
pub fn measure_samples(front: &QualityFrontEnd, samples: &[Sample], threads: usize, progress: &dyn Progress) -> Vec<Option<Measured>> {
    map_samples(samples, threads, "measure", progress, |s| match facegate_core::imaging::open(&s.image) {
        Ok(photo) => front.measure(&photo),
        Err(e) => {
            progress.note(&format!("{}: {e}", s.image.display()));
            None
        }
    })
}

/// The key of a cache of [`measure_samples`] of `samples` by the front end of `models_dir` and
/// `sfm_dir` (a change to the components' definitions bumps [`crate::cache::FRONT_END_VERSION`]).
pub fn cache_key(models_dir: &Path, sfm_dir: &Path, samples: &[Sample]) -> CacheKey {
    CacheKey::new("quality-measurements", &FrontEndModels::files(models_dir, sfm_dir), &[], samples.iter().map(cache_id))
}

/// [`measure_samples`] through the research cache in `cache_dir` (see [`crate::cache`]): the
/// front end (`models_dir`, `sfm_dir`) is loaded and run only when the cache does not hold them.
pub fn measurements(
    cache_dir: &Path,
    models_dir: &Path,
    sfm_dir: &Path,
    samples: &[Sample],
    threads: usize,
    progress: &dyn Progress,
) -> anyhow::Result<Vec<Option<Measured>>> {
    let key = cache_key(models_dir, sfm_dir, samples);
    cache::get_or_compute(cache_dir, &key, samples.len(), progress, || {
        let models = FrontEndModels::load(models_dir, sfm_dir)?;
        let front = QualityFrontEnd { finder: &models.finder, face_model: models.face_model.as_ref(), network: &models.network };
        Ok(measure_samples(&front, samples, threads, progress))
    })
}

/// A photo with a face, ready for scoring: its person, unit template and components.
pub struct Scored<'a> {
    pub label: &'a str,
    pub template: Vec<f32>,
    pub components: Components,
}

/// The photos of `samples` that `keep` selects and where a face was found, each with the deep
/// model's template of its embedding.
pub fn scored<'a>(
    samples: &'a [Sample],
    measured: &[Option<Measured>],
    model: &facegate_vision::recognize::dlib::DlibModel,
    keep: &dyn Fn(&Sample) -> bool,
) -> Vec<Scored<'a>> {
    samples
        .iter()
        .zip(measured)
        .filter(|(s, _)| keep(s))
        .filter_map(|(s, m)| {
            let m = m.as_ref()?;
            let embedding = facegate_nn::Embedding(m.embedding.as_slice().try_into().ok()?);
            Some(Scored { label: s.label.as_str(), template: model.template(&embedding).vector, components: m.components })
        })
        .collect()
}

/// The mean FNMR of `curve` over its discard shares from 0 to `upto` (trapezoids): the partial
/// area under the error-versus-discard curve over that span, divided by its width.
pub fn partial_area(curve: &[EdcPoint], upto: f64) -> f64 {
    let points: Vec<&EdcPoint> = curve.iter().filter(|p| p.discarded <= upto + 1e-9).collect();
    let area: f64 = points.windows(2).map(|w| (w[1].discarded - w[0].discarded) * (w[0].fnmr + w[1].fnmr) / 2.0).sum();
    area / upto
}

/// A quality measure under evaluation: a name and, per photo, a value where higher is better.
pub struct Measure {
    pub name: String,
    pub values: Vec<f64>,
}

/// The measures the evaluation compares: the unified score, then each component oriented so that
/// higher is better (a missing pose or embedding counts as the worst).
pub fn measures(photos: &[Scored], model: &QualityModel) -> Vec<Measure> {
    type Pick = fn(&Components) -> f64;
    let components: [(&str, Pick); 10] = [
        ("inter-eye distance", |c| c.inter_eye_px as f64),
        ("sharpness", |c| c.sharpness as f64),
        ("exposure (−|brightness − 128|)", |c| -(c.brightness as f64 - 128.0).abs()),
        ("contrast", |c| c.contrast as f64),
        ("illumination uniformity", |c| c.illumination_uniformity as f64),
        ("−|yaw|", |c| -(c.yaw_abs_deg.unwrap_or(90.0) as f64)),
        ("−|pitch|", |c| -(c.pitch_abs_deg.unwrap_or(90.0) as f64)),
        ("−fit residual", |c| -(c.fit_residual.unwrap_or(f32::MAX) as f64)),
        ("mirror agreement", |c| c.mirror_agreement.unwrap_or(-1.0) as f64),
        ("embedding norm", |c| c.embedding_norm.unwrap_or(0.0) as f64),
    ];
    let mut out =
        vec![Measure { name: "unified score".into(), values: photos.iter().map(|p| model.score(&p.components) as f64).collect() }];
    out.extend(
        components
            .iter()
            .map(|(name, pick)| Measure { name: name.to_string(), values: photos.iter().map(|p| pick(&p.components)).collect() }),
    );
    out
}

/// The genuine comparisons (all pairs of a person's photos) of `photos`: indices and whether the
/// pair clears `threshold`.
pub fn genuine_pairs(photos: &[Scored], threshold: f32) -> Vec<(usize, usize, bool)> {
    let labels: Vec<&str> = photos.iter().map(|p| p.label).collect();
    let mut out = Vec::new();
    for indices in photos_by_person(&labels).values() {
        for (a, &i) in indices.iter().enumerate() {
            for &j in &indices[a + 1..] {
                out.push((i, j, unit_cosine(&photos[i].template, &photos[j].template) >= threshold));
            }
        }
    }
    out
}

/// One point of an error-versus-discard curve.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct EdcPoint {
    /// Share of the photos discarded (the lowest-quality ones).
    pub discarded: f64,
    /// FNMR of the genuine pairs left (both photos kept).
    pub fnmr: f64,
    pub genuine_pairs: usize,
}

/// The error-versus-discard characteristic of `order` (photo indices, lowest quality first): for
/// each share in `discard`, the FNMR of the genuine pairs whose photos are both kept.
pub fn edc(pairs: &[(usize, usize, bool)], order: &[usize], discard: &[f64]) -> Vec<EdcPoint> {
    let mut rank = vec![0usize; order.len()];
    for (r, &i) in order.iter().enumerate() {
        rank[i] = r;
    }
    discard
        .iter()
        .map(|&share| {
            let cut = (share * order.len() as f64).round() as usize;
            let kept: Vec<bool> = pairs.iter().filter(|(i, j, _)| rank[*i] >= cut && rank[*j] >= cut).map(|p| p.2).collect();
            let misses = kept.iter().filter(|m| !**m).count();
            EdcPoint { discarded: share, fnmr: misses as f64 / kept.len().max(1) as f64, genuine_pairs: kept.len() }
        })
        .collect()
}

/// Photo indices by `values`, lowest first (ties by index).
pub fn lowest_first(values: &[f64]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..values.len()).collect();
    order.sort_by(|&a, &b| values[a].total_cmp(&values[b]).then(a.cmp(&b)));
    order
}

/// The error-versus-discard curve of random discarding: the mean over `runs` shuffles.
pub fn random_edc(pairs: &[(usize, usize, bool)], photos: usize, discard: &[f64], runs: usize) -> Vec<EdcPoint> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(18);
    let mut sum = vec![EdcPoint { discarded: 0.0, fnmr: 0.0, genuine_pairs: 0 }; discard.len()];
    for _ in 0..runs {
        let mut order: Vec<usize> = (0..photos).collect();
        order.shuffle(&mut rng);
        for (s, p) in sum.iter_mut().zip(edc(pairs, &order, discard)) {
            s.discarded = p.discarded;
            s.fnmr += p.fnmr / runs as f64;
            s.genuine_pairs += p.genuine_pairs;
        }
    }
    sum.iter_mut().for_each(|s| s.genuine_pairs /= runs.max(1));
    sum
}

/// Which held-out photos of `set` the evaluation uses: LFW's test persons, IMM's and ORL's
/// held-out persons.
pub fn is_held_out(s: &Sample, set: Set) -> bool {
    s.set == set && s.split == Split::Test
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::train_quality::genuine_match_rates;

    pub(crate) fn photo(label: &'static str, template: Vec<f32>, sharpness: f32) -> Scored<'static> {
        let components = Components {
            inter_eye_px: 60.0,
            sharpness,
            brightness: 120.0,
            contrast: 40.0,
            illumination_uniformity: 0.9,
            yaw_abs_deg: Some(5.0),
            pitch_abs_deg: Some(3.0),
            fit_residual: Some(0.05),
            mirror_agreement: Some(0.95),
            embedding_norm: Some(1.0),
        };
        Scored { label, template, components }
    }

    #[test]
    fn the_measurement_cache_is_read_back_only_under_its_own_key() {
        let dir = std::env::temp_dir().join(format!("facegate-quality-cache-{}", std::process::id()));
        let (cache_dir, models, sfm) = (dir.join("cache"), dir.join("models"), dir.join("sfm"));
        std::fs::create_dir_all(&models).unwrap();
        std::fs::write(models.join("asm.bin"), b"x").unwrap();
        let sample = |name: &str| Sample {
            label: "p".into(),
            image: std::path::PathBuf::from(name),
            set: Set::Lfw,
            view: None,
            split: Split::Train,
        };
        let samples = vec![sample("a.jpg"), sample("b.jpg")];
        let measured = vec![Some(Measured { embedding: vec![0.5; 4], components: photo("p", vec![], 7.0).components }), None];
        let key = cache_key(&models, &sfm, &samples);
        cache::write(&cache_dir, &key, &measured).unwrap();
        assert_eq!(cache::read(&cache_dir, &key, samples.len()), Some(measured.clone()));
        // Read back without loading the front end (whose models here are no models at all).
        assert_eq!(measurements(&cache_dir, &models, &sfm, &samples, 1, &crate::Quiet).unwrap(), measured);
        // Other models: measured again, never read stale.
        std::fs::write(models.join("asm.bin"), b"y").unwrap();
        let other_models = cache_key(&models, &sfm, &samples);
        assert_ne!(other_models, key);
        assert_eq!(cache::read::<Option<Measured>>(&cache_dir, &other_models, samples.len()), None);
        std::fs::write(models.join("asm.bin"), b"x").unwrap();
        assert_eq!(cache_key(&models, &sfm, &samples), key);
        // Another list of photos (one the cache does not hold, fewer, another order): measured again.
        let lists = [vec![sample("a.jpg"), sample("c.jpg")], vec![sample("a.jpg")], vec![sample("b.jpg"), sample("a.jpg")]];
        for list in lists {
            let other = cache_key(&models, &sfm, &list);
            assert_ne!(other, key);
            assert_eq!(cache::read::<Option<Measured>>(&cache_dir, &other, list.len()), None);
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn discarding_the_photo_that_fails_removes_its_pairs_misses() {
        // Person a: photos 0, 1 match; photo 2 is unlike both. Person b: 3, 4 match.
        let photos = vec![
            photo("a", vec![1.0, 0.0], 10.0),
            photo("a", vec![1.0, 0.0], 9.0),
            photo("a", vec![0.0, 1.0], 1.0),
            photo("b", vec![0.6, 0.8], 8.0),
            photo("b", vec![0.6, 0.8], 7.0),
        ];
        let pairs = genuine_pairs(&photos, 0.5);
        assert_eq!(pairs.len(), 4);
        let order = lowest_first(&[10.0, 9.0, 1.0, 8.0, 7.0]);
        let curve = edc(&pairs, &order, &[0.0, 0.2]);
        assert!((curve[0].fnmr - 0.5).abs() < 1e-12 && curve[0].genuine_pairs == 4);
        assert_eq!((curve[1].fnmr, curve[1].genuine_pairs), (0.0, 2));
        let rates = genuine_match_rates(&photos, 0.5);
        assert_eq!(rates[0], (0.5, 2));
        assert_eq!(rates[2], (0.0, 2));
    }
}
