//! Research on the deep embedding: the samples of IMM, ORL and LFW with their person-disjoint
//! split, their embeddings through facegate's own front end (detection, landmarks, chip; and the
//! 3DMM frontal rendering's chip), and the scoring variants compared by cross-validation and on
//! held-out persons. Progress goes through a callback; nothing here prints.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::Digest;

use crate::dataset::{self, imm_is_test_person};
use crate::embed::{CHIP_SIZE, EMBEDDING_DIMS, Embedder, Embedding, FaceChip, chip};
use crate::eval::verification::{VerificationSummary, summarize};
use crate::imaging::Photo;
use crate::pipeline::{Pipeline, find_landmarks};
use crate::recognize::{Dlda, DldaParams};

/// Which part of the person-disjoint split a person belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Split {
    /// Trains projections.
    Train,
    /// Sets thresholds (LFW only: IMM and ORL calibrate on their held-out persons, as the
    /// classical model does).
    Calibration,
    /// Held out of everything that is reported as accuracy on people never seen.
    Test,
}

/// LFW's person-disjoint split, by a hash of the person's name: 60% train, 20% calibration,
/// 20% test. Stable across machines and independent of the listing order.
pub fn lfw_split(person: &str) -> Split {
    let h = sha2::Sha256::digest(person.as_bytes());
    match h[0] % 10 {
        0..=5 => Split::Train,
        6 | 7 => Split::Calibration,
        _ => Split::Test,
    }
}

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

/// The chip of a photo through the service's front end: largest face, the service's landmarks.
pub fn photo_chips(pipeline: &Pipeline, photo: &Photo) -> Option<(FaceChip, Option<FaceChip>)> {
    let face = *pipeline.detector.detect(&photo.gray).first()?;
    let lm = find_landmarks(&pipeline.landmarker, pipeline.asm3d.as_ref(), &photo.gray, &face.rect);
    let k = lm.keypoints;
    let direct = chip::extract(&photo.rgb, &chip::chip_to_photo(CHIP_SIZE, k.left_eye, k.right_eye, k.mouth), CHIP_SIZE);
    let frontal = pipeline.face_model.as_ref().and_then(|model| {
        let fit = model.fit(&lm.points, photo.width(), photo.height()).ok()?;
        let f = model.frontalize(photo, &fit).ok()?;
        let fk = f.keypoints;
        Some(chip::extract(&f.image, &chip::chip_to_photo(CHIP_SIZE, fk.left_eye, fk.right_eye, fk.mouth), CHIP_SIZE))
    });
    Some((direct, frontal))
}

/// Embeddings of every sample, on `threads` threads; `tick` is called once per sample.
pub fn embed_samples(
    pipeline: &Pipeline,
    embedder: &Embedder,
    samples: &[Sample],
    threads: usize,
    tick: &(dyn Fn() + Sync),
) -> Vec<PhotoEmbeddings> {
    let mut out = vec![PhotoEmbeddings::default(); samples.len()];
    let per = samples.len().div_ceil(threads.max(1)).max(1);
    std::thread::scope(|scope| {
        for (chunk, dst) in samples.chunks(per).zip(out.chunks_mut(per)) {
            scope.spawn(move || {
                let mut ws = crate::embed::Workspace::default();
                for (s, d) in chunk.iter().zip(dst) {
                    if let Ok(photo) = crate::imaging::open(&s.image)
                        && let Some((direct, frontal)) = photo_chips(pipeline, &photo)
                    {
                        d.photo = Some(embedder.embed_mirrored(&direct, &mut ws).0.to_vec());
                        d.frontal = frontal.map(|f| embedder.embed_mirrored(&f, &mut ws).0.to_vec());
                    }
                    tick();
                }
            });
        }
    });
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

/// How two embeddings are scored (higher: more alike).
#[derive(Debug, Clone)]
pub enum Scoring {
    /// Minus the Euclidean distance (dlib's own rule: same person below 0.6).
    Euclidean,
    /// Cosine of the raw embeddings.
    Cosine,
    /// Cosine of the DLDA projections.
    Dlda(Dlda),
    /// `w · cosine(raw) + (1 − w) · cosine(DLDA)`, as one cosine of concatenated scaled units.
    Fused(Dlda, f32),
}

impl Scoring {
    /// The vector whose cosine (or, for Euclidean, negated distance) is the score.
    pub fn prepare(&self, e: &[f32]) -> Vec<f32> {
        match self {
            Scoring::Euclidean => e.to_vec(),
            Scoring::Cosine => unit(e.to_vec()),
            Scoring::Dlda(d) => unit(d.project(e)),
            Scoring::Fused(d, w) => {
                let mut v: Vec<f32> = unit(e.to_vec()).iter().map(|x| x * w.sqrt()).collect();
                v.extend(unit(d.project(e)).iter().map(|x| x * (1.0 - w).sqrt()));
                v
            }
        }
    }

    pub fn score(&self, a: &[f32], b: &[f32]) -> f32 {
        match self {
            Scoring::Euclidean => -Embedding(a.try_into().expect("128")).distance(&Embedding(b.try_into().expect("128"))),
            _ => a.iter().zip(b).map(|(x, y)| x * y).sum(),
        }
    }
}

fn unit(mut v: Vec<f32>) -> Vec<f32> {
    let n = v.iter().map(|x| x * x).sum::<f32>().sqrt().max(f32::MIN_POSITIVE);
    v.iter_mut().for_each(|x| *x /= n);
    v
}

/// Trains DLDA over embeddings of the given (label, embedding) pairs.
pub fn train_dlda(items: &[(&str, &[f32])], params: &DldaParams) -> Result<Dlda, crate::recognize::dlda::DldaError> {
    let mut labels: Vec<&str> = items.iter().map(|(l, _)| *l).collect();
    labels.sort_unstable();
    labels.dedup();
    let index = |l: &str| labels.binary_search(&l).expect("label listed");
    let samples: Vec<Vec<f32>> = items.iter().map(|(_, e)| e.to_vec()).collect();
    let ids: Vec<usize> = items.iter().map(|(l, _)| index(l)).collect();
    Dlda::train(&samples, &ids, params)
}

/// Genuine and impostor scores of all pairs among `items` (label, embedding).
pub fn all_pair_scores(items: &[(&str, &[f32])], scoring: &Scoring) -> (Vec<f32>, Vec<f32>) {
    let prepared: Vec<Vec<f32>> = items.iter().map(|(_, e)| scoring.prepare(e)).collect();
    let (mut genuine, mut impostor) = (Vec::new(), Vec::new());
    for i in 0..items.len() {
        for j in i + 1..items.len() {
            let s = scoring.score(&prepared[i], &prepared[j]);
            if items[i].0 == items[j].0 { genuine.push(s) } else { impostor.push(s) }
        }
    }
    (genuine, impostor)
}

/// Pair summary of `items` under `scoring`.
pub fn pair_summary(items: &[(&str, &[f32])], scoring: &Scoring) -> VerificationSummary {
    let (g, i) = all_pair_scores(items, scoring);
    summarize(&g, &i)
}

/// `k`-fold cross-validation over the persons of `items`: DLDA (with `params`) trained on the
/// other folds, all pairs of the fold scored; the folds' genuine and impostor scores pooled.
/// With `params == None` the raw cosine is scored on the same folds.
pub fn cross_validate(items: &[(&str, &[f32])], k: usize, params: Option<&DldaParams>, raw_weight: f32) -> VerificationSummary {
    let fold_of = |label: &str| sha2::Sha256::digest(label.as_bytes())[1] as usize % k;
    let (mut genuine, mut impostor) = (Vec::new(), Vec::new());
    for fold in 0..k {
        let train: Vec<(&str, &[f32])> = items.iter().copied().filter(|(l, _)| fold_of(l) != fold).collect();
        let test: Vec<(&str, &[f32])> = items.iter().copied().filter(|(l, _)| fold_of(l) == fold).collect();
        let scoring = match params {
            Some(p) => match train_dlda(&train, p) {
                Ok(d) if raw_weight > 0.0 => Scoring::Fused(d, raw_weight),
                Ok(d) => Scoring::Dlda(d),
                Err(_) => continue,
            },
            None => Scoring::Cosine,
        };
        let (g, i) = all_pair_scores(&test, &scoring);
        genuine.extend(g);
        impostor.extend(i);
    }
    summarize(&genuine, &impostor)
}

/// The embedding dimension, for callers that size buffers.
pub const DIMS: usize = EMBEDDING_DIMS;

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
    }
}

/// The key points (image-left eye, image-right eye, mouth centre) the service's front end finds
/// in each sample, `None` where no face was found; on `threads` threads.
pub fn key_points(pipeline: &Pipeline, samples: &[Sample], threads: usize, tick: &(dyn Fn() + Sync)) -> Vec<Option<[[f32; 2]; 3]>> {
    let mut out = vec![None; samples.len()];
    let per = samples.len().div_ceil(threads.max(1)).max(1);
    std::thread::scope(|scope| {
        for (chunk, dst) in samples.chunks(per).zip(out.chunks_mut(per)) {
            scope.spawn(move || {
                for (s, d) in chunk.iter().zip(dst) {
                    if let Ok(photo) = crate::imaging::open(&s.image)
                        && let Some(face) = pipeline.detector.detect(&photo.gray).first()
                    {
                        let k = find_landmarks(&pipeline.landmarker, pipeline.asm3d.as_ref(), &photo.gray, &face.rect).keypoints;
                        *d = Some([k.left_eye, k.right_eye, k.mouth]);
                    }
                    tick();
                }
            });
        }
    });
    out
}

/// A variant of the chip's placement: the face zoomed by `scale` about the chip centre and moved
/// down by `dy` chip pixels; `flip`: the embedding is the mean of the chip's and its mirror's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChipVariant {
    pub scale: f32,
    pub dy: f32,
    pub flip: bool,
}

/// Embeddings of `samples` (with their key points) under a chip variant, on `threads` threads.
pub fn embed_variant(
    embedder: &Embedder,
    photos: &[(usize, &image::RgbImage, [[f32; 2]; 3])],
    variant: ChipVariant,
    threads: usize,
) -> Vec<Vec<f32>> {
    let mut out = vec![Vec::new(); photos.len()];
    let per = photos.len().div_ceil(threads.max(1)).max(1);
    let c = CHIP_SIZE as f32 / 2.0;
    // Chip pixel → chip pixel of the standard placement: zoom about the centre, then shift.
    let adjust = crate::geometry::Similarity { a: 1.0 / variant.scale, b: 0.0, tx: c - c / variant.scale, ty: -variant.dy / variant.scale };
    std::thread::scope(|scope| {
        for (chunk, dst) in photos.chunks(per).zip(out.chunks_mut(per)) {
            scope.spawn(move || {
                let mut ws = crate::embed::Workspace::default();
                for ((_, img, k), d) in chunk.iter().zip(dst) {
                    let t = chip::chip_to_photo(CHIP_SIZE, k[0], k[1], k[2]).compose(&adjust);
                    let ch = chip::extract(img, &t, CHIP_SIZE);
                    let e = if variant.flip { embedder.embed_mirrored(&ch, &mut ws) } else { embedder.forward(&ch, &mut ws) };
                    *d = e.0.to_vec();
                }
            });
        }
    });
    out
}

/// Genuine and impostor scores of the service's protocol with `k` photos enrolled per person
/// (the best of the set, as `/verify` scores a subject): each person's photos in listing order
/// give one enrolment set per rotation (photos r … r+k−1, cyclically); the person's other photos
/// are its genuine probes, every other person's photos its impostor probes. Persons with no more
/// than `k` photos are left out as enrolled subjects (their photos still probe as impostors).
pub fn enrolment_scores(labels: &[&str], k: usize, score: &(dyn Fn(usize, usize) -> f32 + Sync)) -> (Vec<f32>, Vec<f32>) {
    let mut by_person: std::collections::BTreeMap<&str, Vec<usize>> = std::collections::BTreeMap::new();
    for (i, l) in labels.iter().enumerate() {
        by_person.entry(l).or_default().push(i);
    }
    let k = k.max(1);
    let (mut genuine, mut impostor) = (Vec::new(), Vec::new());
    for (person, photos) in by_person.iter().filter(|(_, p)| p.len() > k) {
        for r in 0..photos.len() {
            let enrolled: Vec<usize> = (0..k).map(|j| photos[(r + j) % photos.len()]).collect();
            for (p, label) in labels.iter().enumerate().filter(|(p, _)| !enrolled.contains(p)) {
                let s = enrolled.iter().map(|&e| score(p, e)).fold(f32::NEG_INFINITY, f32::max);
                if label == person { genuine.push(s) } else { impostor.push(s) }
            }
        }
    }
    (genuine, impostor)
}

/// Calibrates the deep model's threshold tables (1 … [`crate::recognize::MAX_CALIBRATED_ENROLMENT`]
/// photos enrolled) on `calibration` (label, unit template) with the cosine score.
pub fn calibrate(
    calibration: &[(&str, Vec<f32>)],
    source: &str,
) -> (crate::recognize::Calibration, Vec<crate::recognize::EnrolledCalibration>) {
    use crate::recognize::calibration::CALIBRATED_FMRS;
    use crate::recognize::{Calibration, EnrolledCalibration, MAX_CALIBRATED_ENROLMENT};
    let labels: Vec<&str> = calibration.iter().map(|(l, _)| *l).collect();
    let score = |a: usize, b: usize| calibration[a].1.iter().zip(&calibration[b].1).map(|(x, y)| x * y).sum::<f32>();
    let table = |k: usize| {
        let (g, i) = if k == 1 {
            let items: Vec<(&str, &[f32])> = calibration.iter().map(|(l, v)| (*l, v.as_slice())).collect();
            all_pair_scores(&items, &Scoring::Cosine)
        } else {
            enrolment_scores(&labels, k, &score)
        };
        Calibration::from_scores(&g, &i, &CALIBRATED_FMRS, &format!("{source}; {k} photo(s) enrolled"))
    };
    let one = table(1);
    let enrolled = (2..=MAX_CALIBRATED_ENROLMENT).map(|k| EnrolledCalibration { enrolled: k, calibration: table(k) }).collect();
    (one, enrolled)
}

/// One line of the deep recognizer's held-out report.
#[derive(Debug, Clone, Serialize)]
pub struct HeldOutLine {
    pub set: String,
    pub enrolled: usize,
    pub photos: usize,
    pub summary: VerificationSummary,
    /// FNMR and FMR at the model's own calibrated threshold for FMR 1e-3 (the decision `/verify`
    /// takes), so a reader sees whether the calibration holds on persons it never saw.
    pub fnmr_at_threshold: f64,
    pub fmr_at_threshold: f64,
}

/// The deep model on each held-out set (LFW test persons, IMM and ORL held-out persons): one photo
/// against one, and `k` = 3 photos enrolled per person (the best of the set).
pub fn held_out_report(model: &crate::recognize::deep::DeepModel, samples: &[Sample], embeddings: &[PhotoEmbeddings]) -> Vec<HeldOutLine> {
    let sets: [(&str, Box<dyn Fn(&Sample) -> bool>); 5] = [
        ("LFW test persons", Box::new(|s| s.set == Set::Lfw && s.split == Split::Test)),
        ("IMM held-out, all views", Box::new(|s| s.set == Set::Imm && s.split == Split::Test)),
        ("IMM held-out, frontal views 1-2", Box::new(|s| s.set == Set::Imm && s.split == Split::Test && matches!(s.view, Some(1 | 2)))),
        ("ORL held-out", Box::new(|s| s.set == Set::Orl && s.split == Split::Test)),
        ("IMM + ORL held-out", Box::new(|s| s.set != Set::Lfw && s.split == Split::Test)),
    ];
    let mut out = Vec::new();
    for (name, filter) in &sets {
        let items: Vec<(&str, Vec<f32>)> = samples
            .iter()
            .zip(embeddings)
            .filter(|(s, _)| filter(s))
            .filter_map(|(s, e)| {
                e.photo.as_ref().map(|v| (s.label.as_str(), model.template(&Embedding(v.as_slice().try_into().expect("128"))).vector))
            })
            .collect();
        let labels: Vec<&str> = items.iter().map(|(l, _)| *l).collect();
        let score = |a: usize, b: usize| items[a].1.iter().zip(&items[b].1).map(|(x, y)| x * y).sum::<f32>();
        for k in [1, 3] {
            let (g, i) = if k == 1 {
                let refs: Vec<(&str, &[f32])> = items.iter().map(|(l, v)| (*l, v.as_slice())).collect();
                all_pair_scores(&refs, &Scoring::Cosine)
            } else {
                enrolment_scores(&labels, k, &score)
            };
            if g.is_empty() {
                continue;
            }
            let t = model.operating_point(1e-3, k).threshold;
            out.push(HeldOutLine {
                set: name.to_string(),
                enrolled: k,
                photos: items.len(),
                summary: summarize(&g, &i),
                fnmr_at_threshold: g.iter().filter(|&&s| s < t).count() as f64 / g.len() as f64,
                fmr_at_threshold: i.iter().filter(|&&s| s >= t).count() as f64 / i.len().max(1) as f64,
            });
        }
    }
    out
}
