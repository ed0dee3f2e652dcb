//! Face image quality research: every photo of IMM, ORL and LFW measured through the service's
//! own front end (the deep recognizer's landmarks, 3DMM fit, chip and embedding, then
//! [`facegate_vision::quality::components`]), kept in the research cache ([`crate::cache`]); the
//! unified score's logistic model trained on the training persons; and the error-versus-discard
//! characteristic (FNMR at the recognizer's fixed FMR-1e-3 threshold against the share of
//! lowest-quality photos discarded) on the held-out persons.

use std::path::Path;

use nalgebra::{DMatrix, DVector};
use rand::SeedableRng;
use rand::seq::SliceRandom;
use serde::{Deserialize, Serialize};

use super::protocol::photos_by_person;
use crate::Progress;
use crate::cache::{self, CacheKey, map_samples};
use crate::dataset::Split;
use crate::train_deep::{FrontEndModels, Sample, Set, cache_id};
use facegate_morph::FaceModel;
use facegate_vision::embed::Embedder;
use facegate_vision::pipeline::FaceFinder;
use facegate_vision::quality::{Components, QualityModel, features};

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
            let embedding = facegate_vision::embed::Embedding(m.embedding.as_slice().try_into().ok()?);
            Some(Scored { label: s.label.as_str(), template: model.template(&embedding).vector, components: m.components })
        })
        .collect()
}

fn cosine(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Each photo's share of genuine comparisons (against the person's other photos) that clear
/// `threshold`, and how many there are; photos of persons with one photo get (0, 0).
pub fn genuine_match_rates(photos: &[Scored], threshold: f32) -> Vec<(f64, usize)> {
    let labels: Vec<&str> = photos.iter().map(|p| p.label).collect();
    let mut out = vec![(0.0, 0); photos.len()];
    for indices in photos_by_person(&labels).values() {
        for &i in indices {
            let others = indices.iter().filter(|&&j| j != i);
            let (matched, n) = others.fold((0usize, 0usize), |(m, n), &j| {
                (m + usize::from(cosine(&photos[i].template, &photos[j].template) >= threshold), n + 1)
            });
            if n > 0 {
                out[i] = (matched as f64 / n as f64, n);
            }
        }
    }
    out
}

/// The unified score's model: [`UNIFIED`] (logistic regression of each training photo's genuine
/// match rate at `threshold` on its standardised [`features`], the embedding norm held out, the
/// intercept then refitted to the photos' mean rate) trained on `photos`; photos without a
/// genuine partner are left out.
pub fn train_model(photos: &[Scored], threshold: f32, trained_on: String) -> QualityModel {
    let rates = genuine_match_rates(photos, threshold);
    let cosines = genuine_cosine_stats(photos);
    let all: Vec<usize> = (0..photos.len()).collect();
    let fit = train_variant(&UNIFIED, photos, &all, &rates, &cosines);
    // The runtime scores the [`features`] as they are: only a variant over them can be the model.
    assert_eq!(fit.weights.len(), facegate_vision::quality::FEATURES, "UNIFIED must use the runtime's features");
    QualityModel {
        format: facegate_vision::quality::FORMAT,
        mean: fit.mean,
        scale: fit.scale,
        weights: fit.weights,
        bias: fit.bias,
        trained_on,
    }
}

/// A fitted logistic regression on standardised features.
#[derive(Debug, Clone, PartialEq)]
pub struct LogisticFit {
    pub mean: Vec<f64>,
    pub scale: Vec<f64>,
    pub weights: Vec<f64>,
    pub bias: f64,
}

impl LogisticFit {
    /// The linear predictor (the score's logit) of `x`.
    pub fn logit(&self, x: &[f64]) -> f64 {
        self.bias + x.iter().zip(&self.mean).zip(&self.scale).zip(&self.weights).map(|(((x, m), s), w)| w * (x - m) / s).sum::<f64>()
    }
}

/// Logistic regression of targets in [0, 1] (`rows`: features, target, row weight) by Newton's
/// method with a small ridge penalty on the standardised features. The target's "match" part is
/// weighted by `positive`, its "miss" part by `negative` (1 and 1: plain fractional logistic
/// regression).
pub fn fit_logistic(rows: &[(Vec<f64>, f64, f64)], positive: f64, negative: f64) -> LogisticFit {
    let features = rows.first().map_or(0, |r| r.0.len());
    let n = rows.len().max(1) as f64;
    let mean: Vec<f64> = (0..features).map(|k| rows.iter().map(|r| r.0[k]).sum::<f64>() / n).collect();
    let scale: Vec<f64> = (0..features)
        .map(|k| (rows.iter().map(|r| (r.0[k] - mean[k]).powi(2)).sum::<f64>() / n).sqrt())
        .map(|s| if s > 1e-9 { s } else { 1.0 })
        .collect();
    let x = DMatrix::from_fn(rows.len(), features + 1, |i, k| if k == 0 { 1.0 } else { (rows[i].0[k - 1] - mean[k - 1]) / scale[k - 1] });
    let matched: Vec<f64> = rows.iter().map(|r| r.2 * positive * r.1).collect();
    let missed: Vec<f64> = rows.iter().map(|r| r.2 * negative * (1.0 - r.1)).collect();
    let ridge = 1e-3 * n;
    let mut w = DVector::zeros(features + 1);
    for _ in 0..50 {
        let z = &x * &w;
        let p = z.map(|z| 1.0 / (1.0 + (-z).exp()));
        let mut penalty = DVector::zeros(features + 1);
        let mut hessian = DMatrix::zeros(features + 1, features + 1);
        for k in 1..=features {
            penalty[k] = ridge * w[k];
            hessian[(k, k)] = ridge;
        }
        let residual = DVector::from_fn(rows.len(), |i, _| matched[i] * (1.0 - p[i]) - missed[i] * p[i]);
        let gradient = x.transpose() * residual - penalty;
        let curvature = DVector::from_fn(rows.len(), |i, _| ((matched[i] + missed[i]) * p[i] * (1.0 - p[i])).max(1e-9));
        let weighted = DMatrix::from_fn(rows.len(), features + 1, |i, k| x[(i, k)] * curvature[i]);
        hessian += x.transpose() * weighted;
        let Some(step) = hessian.lu().solve(&gradient) else { break };
        w += &step;
        if step.norm() < 1e-9 {
            break;
        }
    }
    LogisticFit { mean, scale, weights: w.iter().skip(1).copied().collect(), bias: w[0] }
}

/// Each photo's genuine cosines (against the person's other photos): their mean and minimum,
/// and how many there are; photos of persons with one photo get (0, 0, 0).
pub fn genuine_cosine_stats(photos: &[Scored]) -> Vec<(f64, f64, usize)> {
    let labels: Vec<&str> = photos.iter().map(|p| p.label).collect();
    let mut out = vec![(0.0, 0.0, 0); photos.len()];
    for indices in photos_by_person(&labels).values() {
        for &i in indices {
            let cosines: Vec<f64> =
                indices.iter().filter(|&&j| j != i).map(|&j| cosine(&photos[i].template, &photos[j].template) as f64).collect();
            if !cosines.is_empty() {
                let mean = cosines.iter().sum::<f64>() / cosines.len() as f64;
                out[i] = (mean, cosines.iter().copied().fold(f64::INFINITY, f64::min), cosines.len());
            }
        }
    }
    out
}

/// What a candidate unified model is trained to predict per photo.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Target {
    /// The share of its genuine comparisons that clear the threshold (the runtime model's).
    MatchShare,
    /// Its mean genuine cosine, mapped from [−1, 1] to [0, 1].
    MeanGenuineCosine,
    /// Its lowest genuine cosine, mapped as the mean.
    MinGenuineCosine,
}

/// How a candidate weighs the training photos.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Weighting {
    /// Every photo alike.
    Equal,
    /// By its number of genuine comparisons: the error-versus-discard characteristic counts pairs,
    /// so a photo with many partners moves it more.
    ByComparisons,
    /// Matches and misses weighted to equal totals (the rare misses count as much as the matches).
    Balanced,
    /// By comparisons, then matches and misses to equal totals.
    BalancedByComparisons,
}

/// The feature sets the candidates draw on. Each starts from the runtime's [`features`] (so that
/// one over them alone can be `models/quality.bin`); a feature a set leaves out is held at zero, a
/// constant the fit gives no weight.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FeatureSet {
    /// The ten features of the components alone (no mirror agreement, no embedding norm).
    Committed,
    /// The ten and the mirror agreement as ln(1 − agreement) (it crowds just below 1).
    MirrorAgreement,
    /// The ten and the mirror agreement as the cosine itself (the runtime's feature).
    MirrorAgreementRaw,
    /// The ten and ln embedding norm.
    EmbeddingNorm,
    /// The ten, ln(1 − mirror agreement) and ln embedding norm.
    Mirror,
    /// The fit residual replaced by its logarithm.
    LnFitResidual,
    /// The ten plus fit residual × |yaw|.
    FitYawInteraction,
    /// ln fit residual and ln fit residual × |yaw|.
    LnFitResidualYawInteraction,
    /// The ten plus the fit residual squared: a miss rate that climbs faster than linearly in
    /// the residual.
    FitResidualSquared,
}

impl FeatureSet {
    pub fn features(self, c: &Components) -> Vec<f64> {
        let mut x = features(c).to_vec();
        let (agreement, norm) = (facegate_vision::quality::MIRROR_FEATURES.start, facegate_vision::quality::MIRROR_FEATURES.start + 1);
        let disagreement = (1.0 - c.mirror_agreement.unwrap_or(0.0) as f64).max(1e-4).ln();
        match self {
            FeatureSet::Mirror => x[agreement] = disagreement,
            FeatureSet::MirrorAgreement => {
                x[agreement] = disagreement;
                x[norm] = 0.0;
            }
            FeatureSet::MirrorAgreementRaw => x[norm] = 0.0,
            FeatureSet::EmbeddingNorm => x[agreement] = 0.0,
            _ => {
                x[agreement] = 0.0;
                x[norm] = 0.0;
            }
        }
        // A missing fit (no 3DMM) is already the pose-unknown indicator; its residual sits at a
        // typical value so that the logarithm stays finite.
        let ln_fit = (c.fit_residual.unwrap_or(0.05).max(1e-3) as f64).ln();
        let yaw = c.yaw_abs_deg.unwrap_or(0.0) as f64 / 30.0;
        match self {
            FeatureSet::Committed
            | FeatureSet::MirrorAgreement
            | FeatureSet::MirrorAgreementRaw
            | FeatureSet::EmbeddingNorm
            | FeatureSet::Mirror => {}
            FeatureSet::LnFitResidual => x[8] = ln_fit,
            FeatureSet::FitYawInteraction => x.push(x[8] * yaw),
            FeatureSet::LnFitResidualYawInteraction => {
                x[8] = ln_fit;
                x.push(ln_fit * yaw);
            }
            FeatureSet::FitResidualSquared => x.push(x[8] * x[8]),
        }
        x
    }
}

/// A candidate unified model: features, target and weighting.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Variant {
    pub name: &'static str,
    pub features: FeatureSet,
    pub target: Target,
    pub weighting: Weighting,
}

/// The variant `models/quality.bin` is trained as (chosen by `facegate eval quality-cv`): the
/// ten features of the components and the mirror agreement (the embedding norm left out), the
/// match share, every photo weighted alike.
pub const UNIFIED: Variant = Variant {
    name: "+ mirror agreement (raw cosine)",
    features: FeatureSet::MirrorAgreementRaw,
    target: Target::MatchShare,
    weighting: Weighting::Equal,
};

/// The candidates the cross-validation compares ([`UNIFIED`] among them).
pub const VARIANTS: &[Variant] = &[
    Variant {
        name: "plain (match share, 10 features, equal weights)",
        features: FeatureSet::Committed,
        target: Target::MatchShare,
        weighting: Weighting::Equal,
    },
    Variant { name: "ln fit residual", features: FeatureSet::LnFitResidual, target: Target::MatchShare, weighting: Weighting::Equal },
    Variant {
        name: "+ fit residual × |yaw|",
        features: FeatureSet::FitYawInteraction,
        target: Target::MatchShare,
        weighting: Weighting::Equal,
    },
    Variant {
        name: "ln fit residual + ln fit × |yaw|",
        features: FeatureSet::LnFitResidualYawInteraction,
        target: Target::MatchShare,
        weighting: Weighting::Equal,
    },
    Variant {
        name: "target: mean genuine cosine",
        features: FeatureSet::Committed,
        target: Target::MeanGenuineCosine,
        weighting: Weighting::Equal,
    },
    Variant {
        name: "target: min genuine cosine",
        features: FeatureSet::Committed,
        target: Target::MinGenuineCosine,
        weighting: Weighting::Equal,
    },
    Variant {
        name: "weighted by comparisons",
        features: FeatureSet::Committed,
        target: Target::MatchShare,
        weighting: Weighting::ByComparisons,
    },
    Variant { name: "class-balanced", features: FeatureSet::Committed, target: Target::MatchShare, weighting: Weighting::Balanced },
    Variant {
        name: "ln fit residual, weighted",
        features: FeatureSet::LnFitResidual,
        target: Target::MatchShare,
        weighting: Weighting::ByComparisons,
    },
    Variant { name: "+ fit residual²", features: FeatureSet::FitResidualSquared, target: Target::MatchShare, weighting: Weighting::Equal },
    Variant {
        name: "+ fit residual², weighted",
        features: FeatureSet::FitResidualSquared,
        target: Target::MatchShare,
        weighting: Weighting::ByComparisons,
    },
    Variant {
        name: "+ fit residual × |yaw|, weighted",
        features: FeatureSet::FitYawInteraction,
        target: Target::MatchShare,
        weighting: Weighting::ByComparisons,
    },
    Variant {
        name: "weighted and class-balanced",
        features: FeatureSet::Committed,
        target: Target::MatchShare,
        weighting: Weighting::BalancedByComparisons,
    },
    Variant { name: "+ mirror agreement", features: FeatureSet::MirrorAgreement, target: Target::MatchShare, weighting: Weighting::Equal },
    Variant {
        name: "+ mirror agreement, weighted",
        features: FeatureSet::MirrorAgreement,
        target: Target::MatchShare,
        weighting: Weighting::ByComparisons,
    },
    Variant {
        name: "+ mirror agreement (raw cosine), weighted",
        features: FeatureSet::MirrorAgreementRaw,
        target: Target::MatchShare,
        weighting: Weighting::ByComparisons,
    },
    Variant {
        name: "+ mirror agreement (raw cosine)",
        features: FeatureSet::MirrorAgreementRaw,
        target: Target::MatchShare,
        weighting: Weighting::Equal,
    },
    Variant {
        name: "+ ln embedding norm, weighted",
        features: FeatureSet::EmbeddingNorm,
        target: Target::MatchShare,
        weighting: Weighting::ByComparisons,
    },
    Variant {
        name: "+ mirror agreement + ln embedding norm",
        features: FeatureSet::Mirror,
        target: Target::MatchShare,
        weighting: Weighting::Equal,
    },
    Variant {
        name: "+ mirror agreement + ln embedding norm, weighted",
        features: FeatureSet::Mirror,
        target: Target::MatchShare,
        weighting: Weighting::ByComparisons,
    },
    Variant {
        name: "+ mirror agreement + ln embedding norm, weighted and class-balanced",
        features: FeatureSet::Mirror,
        target: Target::MatchShare,
        weighting: Weighting::BalancedByComparisons,
    },
];

/// `variant` trained on the photos `train` selects (indices into `photos`), given each photo's
/// match share and genuine cosine statistics; photos without a genuine partner are left out.
pub fn train_variant(
    variant: &Variant,
    photos: &[Scored],
    train: &[usize],
    rates: &[(f64, usize)],
    cosines: &[(f64, f64, usize)],
) -> LogisticFit {
    let rows: Vec<(Vec<f64>, f64, f64)> = train
        .iter()
        .filter(|&&i| rates[i].1 > 0)
        .map(|&i| {
            let y = match variant.target {
                Target::MatchShare => rates[i].0,
                Target::MeanGenuineCosine => (cosines[i].0 + 1.0) / 2.0,
                Target::MinGenuineCosine => (cosines[i].1 + 1.0) / 2.0,
            };
            let weight = match variant.weighting {
                Weighting::ByComparisons | Weighting::BalancedByComparisons => rates[i].1 as f64,
                Weighting::Equal | Weighting::Balanced => 1.0,
            };
            (variant.features.features(&photos[i].components), y.clamp(0.0, 1.0), weight)
        })
        .collect();
    // Row weights averaging 1 keep the ridge penalty's strength the same for every weighting.
    let mean_weight = rows.iter().map(|r| r.2).sum::<f64>() / rows.len().max(1) as f64;
    let rows: Vec<_> = rows.into_iter().map(|(x, y, w)| (x, y, w / mean_weight.max(1e-12))).collect();
    let (positive, negative) = match variant.weighting {
        Weighting::Balanced | Weighting::BalancedByComparisons => {
            let total: f64 = rows.iter().map(|r| r.2).sum();
            let matched: f64 = rows.iter().map(|r| r.2 * r.1).sum();
            (0.5 * total / matched.max(1e-12), 0.5 * total / (total - matched).max(1e-12))
        }
        _ => (1.0, 1.0),
    };
    let mut fit = fit_logistic(&rows, positive, negative);
    // Weighting tilts the intercept (class balancing towards a mean score of 50): refit it, the
    // weights fixed, so that the mean predicted score over the training photos is their mean
    // observed target again and the score keeps its meaning; the order of photos is unchanged.
    let logits: Vec<f64> = rows.iter().map(|r| fit.logit(&r.0) - fit.bias).collect();
    let observed = rows.iter().map(|r| r.1).sum::<f64>();
    for _ in 0..50 {
        let p: Vec<f64> = logits.iter().map(|z| 1.0 / (1.0 + (-(z + fit.bias)).exp())).collect();
        let gap = observed - p.iter().sum::<f64>();
        let slope = p.iter().map(|p| p * (1.0 - p)).sum::<f64>().max(1e-9);
        fit.bias += gap / slope;
        if (gap / slope).abs() < 1e-10 {
            break;
        }
    }
    fit
}

/// Person-disjoint folds: each person of `photos` to one of `folds` folds by a shuffle seeded
/// with `seed`; per photo its fold.
pub fn person_folds(photos: &[Scored], folds: usize, seed: u64) -> Vec<usize> {
    let mut persons: Vec<&str> = photos.iter().map(|p| p.label).collect();
    persons.sort_unstable();
    persons.dedup();
    persons.shuffle(&mut rand_chacha::ChaCha8Rng::seed_from_u64(seed));
    let fold_of: std::collections::HashMap<&str, usize> = persons.iter().enumerate().map(|(k, p)| (*p, k % folds.max(1))).collect();
    photos.iter().map(|p| fold_of[p.label]).collect()
}

/// Out-of-fold logits of `variant`: each photo scored by the model trained on the other folds.
pub fn out_of_fold_logits(
    variant: &Variant,
    photos: &[Scored],
    fold: &[usize],
    folds: usize,
    rates: &[(f64, usize)],
    cosines: &[(f64, f64, usize)],
) -> Vec<f64> {
    let mut out = vec![0.0; photos.len()];
    for f in 0..folds {
        let train: Vec<usize> = (0..photos.len()).filter(|&i| fold[i] != f).collect();
        let fit = train_variant(variant, photos, &train, rates, cosines);
        for i in (0..photos.len()).filter(|&i| fold[i] == f) {
            out[i] = fit.logit(&variant.features.features(&photos[i].components));
        }
    }
    out
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
                out.push((i, j, cosine(&photos[i].template, &photos[j].template) >= threshold));
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

/// Which photos train the unified score: the training persons of all three sets.
pub fn is_training(s: &Sample) -> bool {
    s.split == Split::Train
}

#[cfg(test)]
mod tests {
    use super::*;

    fn photo(label: &'static str, template: Vec<f32>, sharpness: f32) -> Scored<'static> {
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

    #[test]
    fn the_trained_score_ranks_the_failing_photos_lowest() {
        // Sharp photos of each person match; blurred ones (one per person) do not.
        let mut photos = Vec::new();
        let labels = ["p0", "p1", "p2", "p3", "p4", "p5", "p6", "p7"];
        for (k, label) in labels.iter().enumerate() {
            let angle = k as f32;
            let good = vec![angle.cos(), angle.sin(), 0.0];
            for s in [8.0, 9.0, 10.0, 11.0] {
                photos.push(photo(label, good.clone(), s + k as f32 * 0.1));
            }
            photos.push(photo(label, vec![0.0, 0.0, 1.0], 1.0 + k as f32 * 0.1));
        }
        let model = train_model(&photos, 0.9, "test".into());
        let blurred = photos.iter().filter(|p| p.components.sharpness < 2.0).map(|p| model.score(&p.components)).fold(0.0, f32::max);
        let sharp = photos.iter().filter(|p| p.components.sharpness > 7.0).map(|p| model.score(&p.components)).fold(100.0, f32::min);
        assert!(blurred < sharp, "blurred ≤ {blurred}, sharp ≥ {sharp}");
        assert!(model.weights[1] > 0.0, "{:?}", model.weights);
        let rates = genuine_match_rates(&photos, 0.9);
        let observed = rates.iter().map(|r| r.0).sum::<f64>() / rates.len() as f64;
        let predicted = photos.iter().map(|p| model.score(&p.components) as f64 / 100.0).sum::<f64>() / photos.len() as f64;
        assert!((predicted - observed).abs() < 1e-3, "mean score {predicted}, mean match rate {observed}");
    }
}
