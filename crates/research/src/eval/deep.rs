//! Research on the deep embedding: the scoring variants (the embedding's own distance and cosine,
//! Direct LDA over embeddings, their fusion) by cross-validation over the training persons and on
//! the held-out persons, chip placement variants, and the committed model's held-out report.

use serde::Serialize;
use sha2::Digest;

use super::protocol::{all_pairs_by, enrollment_scores_by};
use super::verification::{VerificationSummary, summarize};
use crate::dataset::Split;
use crate::dlda::DldaParams;
use crate::train_deep::{PhotoEmbeddings, Sample, Set};
use facegate_core::template::OperatingPoint;
use facegate_core::vector::{dot, unit};
use facegate_nn::{Embedder, Embedding};
use facegate_vision::embed::{CHIP_SIZE, chip};
use facegate_vision::pipeline::FaceFinder;
use facegate_vision::recognize::Combine;
use facegate_vision::recognize::Dlda;
use facegate_vision::recognize::calibration::calibrated_points;
use facegate_vision::recognize::dlib::DlibModel;

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
            _ => super::protocol::unit_cosine(a, b),
        }
    }
}

/// Trains DLDA over embeddings of the given (label, embedding) pairs.
pub fn train_dlda(items: &[(&str, &[f32])], params: &DldaParams) -> Result<Dlda, crate::dlda::DldaError> {
    let mut labels: Vec<&str> = items.iter().map(|(l, _)| *l).collect();
    labels.sort_unstable();
    labels.dedup();
    let index = |l: &str| labels.binary_search(&l).expect("label listed");
    let samples: Vec<Vec<f32>> = items.iter().map(|(_, e)| e.to_vec()).collect();
    let ids: Vec<usize> = items.iter().map(|(l, _)| index(l)).collect();
    crate::dlda::train(&samples, &ids, params)
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

/// The eye and mouth centres (image-left eye, image-right eye, mouth centre) the service's front end finds
/// in each sample, `None` where no face was found; on `threads` threads.
pub fn centres(finder: &FaceFinder, samples: &[Sample], threads: usize, progress: &dyn crate::Progress) -> Vec<Option<[[f32; 2]; 3]>> {
    crate::cache::map_samples(samples, threads, "key points", progress, |s| {
        facegate_core::imaging::open(&s.image)
            .ok()
            .and_then(|photo| finder.locate(&photo.gray).ok())
            .map(|located| located.landmarks.centres)
            .map(|k| [k.left_eye, k.right_eye, k.mouth])
    })
}

/// [`centres`] through the research cache in `cache_dir` ([`crate::cache`]): the finder is
/// loaded from `models_dir` and run only when the cache does not hold them.
pub fn cached_centres(
    cache_dir: &std::path::Path,
    models_dir: &std::path::Path,
    samples: &[Sample],
    threads: usize,
    progress: &dyn crate::Progress,
) -> anyhow::Result<Vec<Option<[[f32; 2]; 3]>>> {
    let files = crate::cache::ModelFiles::new().finder(models_dir);
    let key = crate::cache::CacheKey::new("deep-key-points", &files, &[], samples.iter().map(crate::train_deep::cache_id));
    crate::cache::get_or_compute(cache_dir, &key, samples.len(), progress, || {
        Ok(centres(&FaceFinder::load(models_dir)?, samples, threads, progress))
    })
}

/// A variant of the chip's placement: the face zoomed by `scale` about the chip centre and moved
/// down by `dy` chip pixels; `flip`: the embedding is the mean of the chip's and its mirror's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChipVariant {
    pub scale: f32,
    pub dy: f32,
    pub flip: bool,
}

/// Embeddings of photos (with their centres) under a chip variant, on `threads` threads.
pub fn embed_variant(
    embedder: &Embedder,
    photos: &[(&image::RgbImage, [[f32; 2]; 3])],
    variant: ChipVariant,
    threads: usize,
) -> Vec<Vec<f32>> {
    let c = CHIP_SIZE as f32 / 2.0;
    // Chip pixel → chip pixel of the standard placement: zoom about the centre, then shift.
    let adjust =
        facegate_core::geometry::Similarity { a: 1.0 / variant.scale, b: 0.0, tx: c - c / variant.scale, ty: -variant.dy / variant.scale };
    crate::par_map(photos, threads, |(img, k)| {
        let t = chip::chip_to_photo(CHIP_SIZE, k[0], k[1], k[2]).compose(&adjust);
        let ch = chip::extract(img, &t, CHIP_SIZE);
        let mut ws = embedder.take_workspace();
        let e = if variant.flip { embedder.embed_mirrored(&ch, &mut ws) } else { embedder.forward(&ch, &mut ws) };
        embedder.give_back(ws);
        e.0.to_vec()
    })
}

/// One line of the deep recognizers' held-out report.
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
    /// At each calibrated FMR the model has (1e-2 … 1e-4, and 1e-5 where calibrated): the stated
    /// FMR, the FMR observed at its threshold, and the impostor comparisons it was counted over.
    pub observed: Vec<ObservedFmr>,
}

/// The false match rate a threshold states and the one it gives on a set.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct ObservedFmr {
    pub stated: f64,
    pub observed: f64,
    pub impostors: usize,
    /// False matches counted.
    pub false_matches: usize,
}

/// The held-out sets of the deep recognizers' report.
pub fn held_out_sets() -> [(&'static str, Box<dyn Fn(&Sample) -> bool>); 6] {
    [
        ("LFW test persons", Box::new(|s| s.set == Set::Lfw && s.split == Split::Test)),
        ("IMM held-out, all views", Box::new(|s| s.set == Set::Imm && s.split == Split::Test)),
        ("IMM held-out, frontal views 1-2", Box::new(|s| s.set == Set::Imm && s.split == Split::Test && matches!(s.view, Some(1 | 2)))),
        ("ORL held-out", Box::new(|s| s.set == Set::Orl && s.split == Split::Test)),
        ("IMM + ORL held-out", Box::new(|s| s.set != Set::Lfw && s.split == Split::Test)),
        ("pooled: LFW test, IMM + ORL held-out", Box::new(|s| s.split == Split::Test)),
    ]
}

/// The deep model on each held-out set (LFW test persons, IMM and ORL held-out persons): one photo
/// against one, and `k` = 3 photos enrolled per person (the best of the set).
pub fn held_out_report(model: &DlibModel, samples: &[Sample], embeddings: &[PhotoEmbeddings]) -> Vec<HeldOutLine> {
    let templates: Vec<Option<Vec<f32>>> = embeddings
        .iter()
        .map(|e| e.photo.as_ref().map(|v| model.template(&Embedding(v.as_slice().try_into().expect("128"))).vector))
        .collect();
    held_out_report_of(samples, &templates, &|fmr, k| model.operating_point(fmr, k))
}

/// The held-out report of unit `templates` (one per sample; `None`: no face) scored by cosine
/// against the operating points `point(fmr, enrolled)` (the closest calibrated one: a rate the
/// model lacks is left out of `observed`).
pub fn held_out_report_of(
    samples: &[Sample],
    templates: &[Option<Vec<f32>>],
    point: &dyn Fn(f64, usize) -> OperatingPoint,
) -> Vec<HeldOutLine> {
    let mut out = Vec::new();
    for (name, filter) in &held_out_sets() {
        let items: Vec<(&str, &[f32])> = samples
            .iter()
            .zip(templates)
            .filter(|(s, _)| filter(s))
            .filter_map(|(s, t)| t.as_deref().map(|t| (s.label.as_str(), t)))
            .collect();
        let labels: Vec<&str> = items.iter().map(|(l, _)| *l).collect();
        let score = |a: usize, b: usize| dot(items[a].1, items[b].1);
        for k in [1, 3] {
            let (g, i) = if k == 1 { all_pairs_by(&labels, &score) } else { enrollment_scores_by(&labels, k, Combine::Max, &score) };
            if g.is_empty() {
                continue;
            }
            let t = point(1e-3, k).threshold;
            let observed = calibrated_points(|fmr| point(fmr, k))
                .into_iter()
                .map(|OperatingPoint { fmr, threshold: t }| {
                    let false_matches = i.iter().filter(|&&s| s >= t).count();
                    ObservedFmr { stated: fmr, observed: false_matches as f64 / i.len().max(1) as f64, impostors: i.len(), false_matches }
                })
                .collect();
            out.push(HeldOutLine {
                set: name.to_string(),
                enrolled: k,
                photos: items.len(),
                summary: summarize(&g, &i),
                fnmr_at_threshold: g.iter().filter(|&&s| s < t).count() as f64 / g.len() as f64,
                fmr_at_threshold: i.iter().filter(|&&s| s >= t).count() as f64 / i.len().max(1) as f64,
                observed,
            });
        }
    }
    out
}

/// Rank-1 hits by IMM view group.
pub struct RankTable {
    /// Persons in the gallery (held-out persons, and distractors).
    pub gallery: usize,
    /// View group → (probes, rank-1 hits).
    pub groups: std::collections::BTreeMap<String, (usize, usize)>,
}

/// Rank-1 identification through the service's pipeline: gallery view 1 of the IMM held-out
/// persons (and, with `distractors`, of the training persons), probes their other views; a probe
/// is a hit when its best-scoring gallery template is its own person's.
pub fn rank1_by_view(
    pipeline: &facegate_vision::pipeline::Pipeline,
    imm: &[Sample],
    distractors: bool,
    progress: &dyn crate::Progress,
) -> anyhow::Result<RankTable> {
    progress.begin(imm.len() as u64, "identify");
    let mut gallery: Vec<(&str, facegate_core::template::Template)> = Vec::new();
    let mut probes: Vec<(&Sample, facegate_core::template::Template)> = Vec::new();
    for s in imm {
        let in_gallery = s.view == Some(1) && (s.split == Split::Test || distractors);
        if in_gallery || s.split == Split::Test {
            let photo = facegate_core::imaging::open(&s.image)?;
            let t = pipeline.analyze(&photo)?.template;
            if in_gallery { gallery.push((s.label.as_str(), t)) } else { probes.push((s, t)) }
        }
        progress.step();
    }
    progress.end();
    let mut groups = std::collections::BTreeMap::new();
    for (s, t) in &probes {
        let best = gallery
            .iter()
            .max_by(|a, b| {
                pipeline
                    .recognizer
                    .score(t, std::slice::from_ref(&a.1))
                    .total_cmp(&pipeline.recognizer.score(t, std::slice::from_ref(&b.1)))
            })
            .map(|(l, _)| *l);
        let group = match s.view {
            Some(2) => "view 2 (frontal)",
            Some(3 | 4) => "views 3-4 (turned ±30°)",
            Some(5) => "view 5 (spot light)",
            _ => "view 6 (free)",
        };
        let e: &mut (usize, usize) = groups.entry(group.to_string()).or_default();
        e.0 += 1;
        e.1 += (best == Some(s.label.as_str())) as usize;
    }
    Ok(RankTable { gallery: gallery.len(), groups })
}

/// The classical recognizer's template of each sample `keep` selects (through the service's
/// pipeline; `None`: no face, or not selected), on `threads` threads.
pub fn classical_templates(
    pipeline: &facegate_vision::pipeline::Pipeline,
    samples: &[Sample],
    keep: &(dyn Fn(&Sample) -> bool + Sync),
    threads: usize,
    progress: &dyn crate::Progress,
) -> Vec<Option<Vec<f32>>> {
    crate::cache::map_samples(samples, threads, "classical", progress, |s| {
        keep(s)
            .then(|| facegate_core::imaging::open(&s.image).ok())
            .flatten()
            .and_then(|photo| pipeline.analyze(&photo).ok())
            .map(|a| a.template.vector)
    })
}

/// One photo for score fusion: its label, deep unit template and classical template.
pub type FusionItem<'a> = (&'a str, Vec<f32>, &'a [f32]);

/// Mean and standard deviation of the impostor scores of each recognizer on `items`: the
/// z-normalisation that puts the deep cosines (≈ 0.9 for a match) and the classical ones (≈ 0.4)
/// on one scale before they are added.
pub fn impostor_stats(items: &[FusionItem]) -> [(f64, f64); 2] {
    let mut acc = [(0.0f64, 0.0f64, 0usize); 2];
    for i in 0..items.len() {
        for j in i + 1..items.len() {
            if items[i].0 == items[j].0 {
                continue;
            }
            for (k, s) in [dot(&items[i].1, &items[j].1), dot(items[i].2, items[j].2)].into_iter().enumerate() {
                acc[k].0 += s as f64;
                acc[k].1 += (s as f64) * (s as f64);
                acc[k].2 += 1;
            }
        }
    }
    acc.map(|(s, sq, n)| {
        let n = n.max(1) as f64;
        let mean = s / n;
        (mean, (sq / n - mean * mean).max(1e-12).sqrt())
    })
}

/// All-pairs summary of `w · z(deep) + (1 − w) · z(classical)` with the given impostor statistics.
pub fn fused_summary(items: &[FusionItem], stats: [(f64, f64); 2], w: f64) -> VerificationSummary {
    let labels: Vec<&str> = items.iter().map(|(l, _, _)| *l).collect();
    let score = |a: usize, b: usize| {
        let zd = (dot(&items[a].1, &items[b].1) as f64 - stats[0].0) / stats[0].1;
        let zc = (dot(items[a].2, items[b].2) as f64 - stats[1].0) / stats[1].1;
        (w * zd + (1.0 - w) * zc) as f32
    };
    let (g, i) = all_pairs_by(&labels, &score);
    summarize(&g, &i)
}

/// How one network input fared on the renders of one yaw offset.
#[derive(Debug, Clone, Copy, Default)]
pub struct RenderScore {
    pub probes: usize,
    /// Probes whose best gallery photo is their own person's.
    pub rank1: usize,
    /// Sum of the genuine cosines (own person's gallery photo).
    pub genuine_sum: f32,
    /// The smallest margin of a probe: its genuine cosine minus its best impostor cosine.
    pub min_margin: f32,
}

impl RenderScore {
    fn add(&mut self, e: Option<&Embedding>, own: &str, gallery: &[(&str, Embedding)]) {
        if self.probes == 0 {
            self.min_margin = f32::INFINITY;
        }
        self.probes += 1;
        let Some(e) = e else {
            self.min_margin = f32::NEG_INFINITY;
            return;
        };
        let genuine = gallery.iter().filter(|(l, _)| *l == own).map(|(_, g)| e.cosine(g)).fold(f32::NEG_INFINITY, f32::max);
        let impostor = gallery.iter().filter(|(l, _)| *l != own).map(|(_, g)| e.cosine(g)).fold(f32::NEG_INFINITY, f32::max);
        self.rank1 += (genuine > impostor) as usize;
        self.genuine_sum += genuine;
        self.min_margin = self.min_margin.min(genuine - impostor);
    }

    pub fn mean_genuine(&self) -> f32 {
        self.genuine_sum / self.probes.max(1) as f32
    }
}

/// Turned renders, per yaw offset: (yaw in degrees, the photo's chip, the 3DMM frontal rendering's chip).
pub struct RenderTable {
    pub rows: Vec<(f32, RenderScore, RenderScore)>,
    pub gallery: usize,
}

/// Does the 3DMM frontal rendering help the network on strongly turned faces? Each IMM held-out
/// person's view 1 is fitted, textured and rendered at its pose plus each yaw offset (the
/// re-posing of `train_dlda::FrontEnd::reposed_views`); the service's front end then finds the
/// face and landmarks on the render, and the network sees either the render's own chip or the
/// chip of the 3DMM frontal rendering fitted to those landmarks. Gallery: every IMM person's view 2
/// photo (9 held-out, 21 distractors), embedded as the service enrols. A probe the front end
/// cannot find counts as a miss.
pub fn turned_render_rank1(
    front: &crate::train_dlda::FrontEnd,
    network: &Embedder,
    imm: &[crate::train_dlda::FaceImage],
    yaws: &[f32],
) -> anyhow::Result<RenderTable> {
    use facegate_vision::embed::face_embedding;
    let finder = front.finder.as_ref().ok_or_else(|| anyhow::anyhow!("the face finder's models are missing"))?;
    let model = front.face_model.as_ref().ok_or_else(|| anyhow::anyhow!("the Surrey Face Model is missing"))?;
    let mut gallery: Vec<(&str, Embedding)> = Vec::new();
    for f in imm.iter().filter(|f| f.view == Some(2)) {
        let photo = facegate_core::imaging::open(&f.image)?;
        if let Ok(located) = finder.locate(&photo.gray) {
            gallery.push((f.label.as_str(), face_embedding(network, &photo.rgb, &located.landmarks.centres)));
        }
    }
    let offsets: Vec<(f32, f32)> = yaws.iter().map(|&y| (y, 0.0)).collect();
    let mut rows: Vec<(f32, RenderScore, RenderScore)> =
        yaws.iter().map(|&y| (y, RenderScore::default(), RenderScore::default())).collect();
    for f in imm.iter().filter(|f| f.held_out && f.view == Some(1)) {
        let views = front.reposed_views(f, &offsets)?;
        for ((photo, _), row) in views.iter().zip(rows.iter_mut()) {
            let located = finder.locate(&photo.gray).ok();
            let direct = located.as_ref().map(|l| face_embedding(network, &photo.rgb, &l.landmarks.centres));
            row.1.add(direct.as_ref(), &f.label, &gallery);
            let frontal = located.as_ref().and_then(|l| {
                let fit = model.fit(&l.landmarks.points, photo.width(), photo.height()).ok()?;
                let fr = model.frontalize(photo, &fit).ok()?;
                Some(face_embedding(network, &fr.image, &fr.centres))
            });
            row.2.add(frontal.as_ref(), &f.label, &gallery);
        }
    }
    Ok(RenderTable { rows, gallery: gallery.len() })
}
