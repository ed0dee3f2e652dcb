//! Training the unified quality score (`facegate train quality`, and the candidates `facegate eval
//! quality-cv` compares): each training photo's genuine match rate at the recognizer's threshold
//! regressed on its quality [`features`] by [`crate::logistic`], on the photos
//! [`crate::eval::quality`] measures through the service's front end.

use rand::SeedableRng;
use rand::seq::SliceRandom;

use crate::dataset::Split;
use crate::eval::protocol::{photos_by_person, unit_cosine};
use crate::eval::quality::Scored;
use crate::logistic::{self, LogisticFit, Options};
use crate::train_deep::Sample;
use facegate_vision::quality::{Components, QualityModel, features};

/// Each photo's share of genuine comparisons (against the person's other photos) that clear
/// `threshold`, and how many there are; photos of persons with one photo get (0, 0).
pub fn genuine_match_rates(photos: &[Scored], threshold: f32) -> Vec<(f64, usize)> {
    let labels: Vec<&str> = photos.iter().map(|p| p.label).collect();
    let mut out = vec![(0.0, 0); photos.len()];
    for indices in photos_by_person(&labels).values() {
        for &i in indices {
            let others = indices.iter().filter(|&&j| j != i);
            let (matched, n) = others.fold((0usize, 0usize), |(m, n), &j| {
                (m + usize::from(unit_cosine(&photos[i].template, &photos[j].template) >= threshold), n + 1)
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

/// Each photo's genuine cosines (against the person's other photos): their mean and minimum,
/// and how many there are; photos of persons with one photo get (0, 0, 0).
pub fn genuine_cosine_stats(photos: &[Scored]) -> Vec<(f64, f64, usize)> {
    let labels: Vec<&str> = photos.iter().map(|p| p.label).collect();
    let mut out = vec![(0.0, 0.0, 0); photos.len()];
    for indices in photos_by_person(&labels).values() {
        for &i in indices {
            let cosines: Vec<f64> =
                indices.iter().filter(|&&j| j != i).map(|&j| unit_cosine(&photos[i].template, &photos[j].template) as f64).collect();
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
) -> LogisticFit<f64> {
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
    let mut fit = fit_rows(&rows, positive, negative);
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

/// Which photos train the unified score: the training persons of all three sets.
pub fn is_training(s: &Sample) -> bool {
    s.split == Split::Train
}

/// Logistic regression of targets in [0, 1] (`rows`: features, target, row weight) with a small
/// ridge penalty (1e-3 per row) on the features standardised over the rows alike. The target's
/// "match" part is weighted by `positive`, its "miss" part by `negative` (1 and 1: plain
/// fractional logistic regression).
fn fit_rows(rows: &[(Vec<f64>, f64, f64)], positive: f64, negative: f64) -> LogisticFit<f64> {
    let x: Vec<&[f64]> = rows.iter().map(|r| r.0.as_slice()).collect();
    let matched: Vec<f64> = rows.iter().map(|r| r.2 * positive * r.1).collect();
    let missed: Vec<f64> = rows.iter().map(|r| r.2 * negative * (1.0 - r.1)).collect();
    logistic::fit(&x, &matched, &missed, Options { standardise_weighted: false, ridge: 1e-3, iterations: 50, tolerance: 1e-9 })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::quality::tests::photo;

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
