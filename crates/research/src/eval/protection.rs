//! Protected templates (`facegate eval protection`; ISO/IEC 24745): accuracy,
//! unlinkability and irreversibility of the service's keyed rotation
//! ([`facegate_service::protection`]) on held-out persons (LFW's test persons by default).
//!
//! Every photo goes through the service's one pipeline (the default recognizer, the fusion); its
//! plain template is kept in the research cache ([`crate::cache`], kind `protection-templates`)
//! and protected by the service's own [`ProtectedEngine`] under secrets drawn from `--seed`. Pairs
//! are scored by the engine's own score (the best cosine). Photos without a face are left out of
//! every pair (counted in `photos` against `templates`).
//!
//! - **Accuracy:** EER and FNMR at FMR 1e-3 (the threshold from the pairs' own impostor scores) of
//!   every pair of two photos (one enrolled, one probe), plain and protected under one secret.
//! - **Unlinkability:** D↔sys of Gomez-Barrero et al., *General framework to evaluate
//!   unlinkability in biometric template protection systems*, IEEE TIFS 13(6), 2018 ([`dsys`]),
//!   from the scores of mated pairs (one person's two different photos, one protected under secret
//!   A and the other under B, both orders) against non-mated ones (two persons' photos, A and B).
//!   `dsys_same_secret` is the same under A and A (the linkable reference: what a database's own
//!   templates give), `dsys_plain_cross_deployment` plain against plain (two deployments without
//!   protection store the same templates), and `dsys_noise_floor` the estimator's bias: two draws
//!   from the one non-mated distribution, the first as large as the mated set.
//! - **Irreversibility:** the attacker holds ONE protected template. With the secret it computes
//!   the rotation and its transpose, `x̂ = R_Aᵀ t` (the best attack there is: exact); the rate is
//!   over every (attacked template, another photo of the same person) pair whose plain template
//!   `x̂` reaches the plain FMR 1e-3 threshold (`inversion_match_rate`; `inversion_template_rate`:
//!   attacked templates matching at least one other photo). Without the secret it guesses one
//!   (`inversion_match_rate_without_secret`, a random secret C: `R_Cᵀ t`). And with no secret but
//!   pairs of plain and protected templates of persons it knows (another half of the persons: an
//!   insider, or leaked enrolments), it fits the rotation by orthogonal Procrustes
//!   (`inversion_match_rate_known_pairs`, `known_pairs` of them): a rotation is a linear map, and
//!   `d` independent pairs determine it.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

use rand::{RngCore as _, SeedableRng as _};
use serde::Serialize;

use facegate_core::template::Template;
use facegate_service::protection::{ProtectedEngine, ProtectionKey};
use facegate_service::{FaceEngine, Matcher};
use facegate_vision::pipeline::{Pipeline, PipelineConfig};

use crate::Progress;
use crate::cache::{self, CacheKey, ModelFiles};
use crate::eval::protocol::all_pairs_by;
use crate::measures::{eer, fnmr_at_fmr};
use crate::train_deep::Sample;

/// Histogram bins of [`dsys`] over the common range of the two score sets (as the reference
/// study, scripts/protection-reference/protect.py `dsys_hist`).
pub const DSYS_BINS: usize = 100;

/// The false match rate the thresholds are set at.
pub const FMR: f64 = 1e-3;

/// D↔sys (Gomez-Barrero et al. 2018, eq. 5–6, ω = 1): the local linkability
/// `D↔(s) = 2·LR(s)/(1 + LR(s)) − 1` where `LR(s) = p(s|mated)/p(s|non-mated) > 1`, else 0,
/// integrated over the mated score density: `Σ p(s|mated)·D↔(s)`. The densities are histograms of
/// `bins` equal bins over the common range of both sets (a bin without non-mated scores but with
/// mated ones has LR = ∞, D↔ = 1). 0: the two sets are the same distribution (unlinkable); 1:
/// they do not overlap (fully linkable). Non-finite scores are left out.
pub fn dsys(mated: &[f32], non_mated: &[f32], bins: usize) -> f64 {
    let finite = |v: &[f32]| v.iter().copied().filter(|s| s.is_finite()).collect::<Vec<f32>>();
    let (mated, non_mated) = (finite(mated), finite(non_mated));
    if mated.is_empty() || non_mated.is_empty() || bins == 0 {
        return 0.0;
    }
    let lo = mated.iter().chain(&non_mated).copied().fold(f32::INFINITY, f32::min) as f64;
    let hi = mated.iter().chain(&non_mated).copied().fold(f32::NEG_INFINITY, f32::max) as f64;
    if hi <= lo {
        return 0.0;
    }
    let histogram = |scores: &[f32]| {
        let mut h = vec![0.0f64; bins];
        for &s in scores {
            let bin = (((s as f64 - lo) / (hi - lo)) * bins as f64).floor() as usize;
            h[bin.min(bins - 1)] += 1.0 / scores.len() as f64;
        }
        h
    };
    let (pm, pn) = (histogram(&mated), histogram(&non_mated));
    pm.iter()
        .zip(&pn)
        .map(|(&m, &n)| {
            let local = if n == 0.0 {
                if m > 0.0 { 1.0 } else { 0.0 }
            } else {
                let lr = m / n;
                if lr <= 1.0 { 0.0 } else { 2.0 * lr / (1.0 + lr) - 1.0 }
            };
            m * local
        })
        .sum()
}

/// The plain templates of `samples`' photos through `pipeline` (`None`: no face), from the cache
/// in `cache_dir` when it holds them (keyed by every file of the models folder, the 3DMM's, the
/// pipeline's settings and the photos).
pub fn plain_templates(
    pipeline: &Pipeline,
    config: &PipelineConfig,
    samples: &[Sample],
    cache_dir: &Path,
    threads: usize,
    progress: &dyn Progress,
) -> anyhow::Result<Vec<Option<Vec<f32>>>> {
    let mut files = ModelFiles::new().finder(&config.models_dir);
    let mut names: Vec<String> = std::fs::read_dir(&config.models_dir)?
        .flatten()
        .filter(|e| e.path().is_file())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    for name in &names {
        files = files.model(&config.models_dir, name);
    }
    if let Some(sfm) = &config.sfm_dir {
        files = files.sfm(sfm);
    }
    let settings = format!("{:?} {:?} {}", config.recognizer, config.detector, Matcher::model_version(pipeline));
    let key = CacheKey::new("protection-templates", &files, settings.as_bytes(), samples.iter().map(|s| s.image.display().to_string()));
    cache::get_or_compute(cache_dir, &key, samples.len(), progress, || {
        Ok(cache::map_samples(samples, threads, "photos", progress, |s| {
            let photo = facegate_core::imaging::open(&s.image).ok()?;
            pipeline.analyze(&photo).ok().map(|a| a.template.vector)
        }))
    })
}

/// The measurements (module docs); rates are fractions.
#[derive(Debug, Clone, Serialize)]
pub struct ProtectionReport {
    pub set: String,
    pub photos: usize,
    /// Photos whose face was found: the templates measured.
    pub templates: usize,
    pub persons: usize,
    pub model_version: String,
    pub protected_model_version: String,
    pub secret_ids: [String; 2],
    pub genuine_pairs: usize,
    pub impostor_pairs: usize,
    pub eer_plain: f64,
    pub eer_protected: f64,
    pub fnmr_plain: f64,
    pub fnmr_protected: f64,
    pub threshold_plain: f32,
    pub threshold_protected: f32,
    /// Largest |plain − protected| score over every pair (float rounding).
    pub max_score_difference: f32,
    pub dsys_bins: usize,
    pub mated_pairs: usize,
    pub non_mated_pairs: usize,
    pub dsys_cross_secret: f64,
    pub dsys_same_secret: f64,
    pub dsys_plain_cross_deployment: f64,
    pub dsys_noise_floor: f64,
    pub inversion_attempts: usize,
    pub inversion_templates: usize,
    pub inversion_match_rate: f64,
    pub inversion_template_rate: f64,
    /// Mean cosine of the recovered embedding with the attacked photo's own plain template.
    pub inversion_mean_cosine: f64,
    /// The service's own threshold at FMR 1e-3 (one template enrolled), and the rate at it.
    pub service_threshold: f32,
    pub inversion_match_rate_service_threshold: f64,
    pub inversion_match_rate_without_secret: f64,
    pub known_pairs: usize,
    pub inversion_attempts_known_pairs: usize,
    pub inversion_match_rate_known_pairs: f64,
}

/// A secret drawn from `rng` (what `openssl rand -hex 32` gives an operator).
fn draw_key(rng: &mut rand_chacha::ChaCha20Rng) -> ProtectionKey {
    let mut bytes = [0u8; 32];
    rng.fill_bytes(&mut bytes);
    let hex: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
    ProtectionKey::parse(&hex).expect("64 hex digits")
}

/// Ordered pairs (i, j), i ≠ j, of two photos: mated (one person) and non-mated, scored by `score`.
fn ordered_pairs(labels: &[&str], score: &(dyn Fn(usize, usize) -> f32 + Sync)) -> (Vec<f32>, Vec<f32>) {
    let (mut mated, mut non_mated) = (Vec::new(), Vec::new());
    for i in 0..labels.len() {
        for j in 0..labels.len() {
            if i != j {
                if labels[i] == labels[j] { mated.push(score(i, j)) } else { non_mated.push(score(i, j)) }
            }
        }
    }
    (mated, non_mated)
}

/// Every measurement of `vectors` (plain templates of the one recognizer `engine` scores, with
/// their persons' `labels`) under secrets drawn from `seed`.
pub fn evaluate(
    set: &str,
    photos: usize,
    engine: Arc<dyn FaceEngine>,
    labels: &[&str],
    vectors: &[Vec<f32>],
    seed: u64,
) -> ProtectionReport {
    let mut rng = rand_chacha::ChaCha20Rng::seed_from_u64(seed);
    let (key_a, key_b, key_c) = (draw_key(&mut rng), draw_key(&mut rng), draw_key(&mut rng));
    let version = engine.model_version().to_string();
    let plain: Vec<Template> = vectors.iter().map(|v| Template { model_version: version.clone(), vector: v.clone() }).collect();
    let a = ProtectedEngine::new(engine.clone(), key_a.clone()).expect("a cosine-scored recognizer");
    let b = ProtectedEngine::new(engine.clone(), key_b.clone()).expect("a cosine-scored recognizer");
    let protected_a: Vec<Template> = plain.iter().map(|t| a.protect(t)).collect();
    let protected_b: Vec<Template> = plain.iter().map(|t| b.protect(t)).collect();
    let pair = |m: &dyn Matcher, x: &[Template], y: &[Template], i: usize, j: usize| m.score(&x[i], std::slice::from_ref(&y[j]));

    // Accuracy: every unordered pair, plain and protected under A.
    let (gp, ip) = all_pairs_by(labels, &|i, j| pair(engine.as_ref(), &plain, &plain, i, j));
    let (ga, ia) = all_pairs_by(labels, &|i, j| pair(&a, &protected_a, &protected_a, i, j));
    let max_score_difference = gp.iter().chain(&ip).zip(ga.iter().chain(&ia)).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
    let (fnmr_plain, threshold_plain) = fnmr_at_fmr(&gp, &ip, FMR);
    let (fnmr_protected, threshold_protected) = fnmr_at_fmr(&ga, &ia, FMR);

    // Unlinkability: ordered pairs of two different photos.
    let (mated_ab, non_mated_ab) = ordered_pairs(labels, &|i, j| pair(&a, &protected_a, &protected_b, i, j));
    let (mated_aa, non_mated_aa) = ordered_pairs(labels, &|i, j| pair(&a, &protected_a, &protected_a, i, j));
    let (mated_pp, non_mated_pp) = ordered_pairs(labels, &|i, j| pair(engine.as_ref(), &plain, &plain, i, j));
    let floor_draw: Vec<f32> = rand::seq::index::sample(&mut rng, non_mated_ab.len(), mated_ab.len().min(non_mated_ab.len()))
        .into_iter()
        .map(|k| non_mated_ab[k])
        .collect();

    let service_threshold = engine.operating_point(FMR, 1).threshold;
    let attack = Attack { engine: engine.as_ref(), labels, plain: &plain };
    let rotation = key_a.rotation(rotation_dimension(&plain));
    let with_secret = attack.run(&protected_a, &|t| rotation.invert(t), None);
    let guessed = key_c.rotation(rotation_dimension(&plain));
    let without_secret = attack.run(&protected_a, &|t| guessed.invert(t), None);
    let (known, fitted) = known_pair_rotation(labels, &plain, &protected_a);
    let known_pairs = attack.run(&protected_a, &|t| fitted.invert(t), Some(&known));
    let persons = labels.iter().collect::<std::collections::BTreeSet<_>>().len();
    ProtectionReport {
        set: set.to_string(),
        photos,
        templates: plain.len(),
        persons,
        model_version: version,
        protected_model_version: a.model_version().to_string(),
        secret_ids: [key_a.id(), key_b.id()],
        genuine_pairs: gp.len(),
        impostor_pairs: ip.len(),
        eer_plain: eer(&gp, &ip),
        eer_protected: eer(&ga, &ia),
        fnmr_plain,
        fnmr_protected,
        threshold_plain,
        threshold_protected,
        max_score_difference,
        dsys_bins: DSYS_BINS,
        mated_pairs: mated_ab.len(),
        non_mated_pairs: non_mated_ab.len(),
        dsys_cross_secret: dsys(&mated_ab, &non_mated_ab, DSYS_BINS),
        dsys_same_secret: dsys(&mated_aa, &non_mated_aa, DSYS_BINS),
        dsys_plain_cross_deployment: dsys(&mated_pp, &non_mated_pp, DSYS_BINS),
        dsys_noise_floor: dsys(&floor_draw, &non_mated_ab, DSYS_BINS),
        inversion_attempts: with_secret.attempts,
        inversion_templates: with_secret.templates,
        inversion_match_rate: with_secret.rate(threshold_plain),
        inversion_template_rate: with_secret.template_rate(threshold_plain),
        inversion_mean_cosine: with_secret.mean_cosine,
        service_threshold,
        inversion_match_rate_service_threshold: with_secret.rate(service_threshold),
        inversion_match_rate_without_secret: without_secret.rate(threshold_plain),
        known_pairs: known.iter().filter(|k| **k).count(),
        inversion_attempts_known_pairs: known_pairs.attempts,
        inversion_match_rate_known_pairs: known_pairs.rate(threshold_plain),
    }
}

fn rotation_dimension(plain: &[Template]) -> usize {
    plain.first().map_or(0, |t| t.vector.len())
}

/// The inversion attacks' common protocol: one protected template in, an embedding out, scored
/// against the plain templates of the person's other photos.
struct Attack<'a> {
    engine: &'a dyn FaceEngine,
    labels: &'a [&'a str],
    plain: &'a [Template],
}

/// An attack's scores: per attacked template, its scores against the person's other photos.
struct AttackScores {
    attempts: usize,
    templates: usize,
    per_template: Vec<Vec<f32>>,
    mean_cosine: f64,
}

impl AttackScores {
    fn rate(&self, threshold: f32) -> f64 {
        let hits = self.per_template.iter().flatten().filter(|s| **s >= threshold).count();
        hits as f64 / self.attempts.max(1) as f64
    }
    fn template_rate(&self, threshold: f32) -> f64 {
        let hits = self.per_template.iter().filter(|s| s.iter().any(|s| *s >= threshold)).count();
        hits as f64 / self.templates.max(1) as f64
    }
}

impl Attack<'_> {
    /// `invert` on each protected template of a person with another photo (not one of the
    /// attacker's `known` templates, when given).
    fn run(&self, protected: &[Template], invert: &(dyn Fn(&[f32]) -> Vec<f32> + Sync), known: Option<&[bool]>) -> AttackScores {
        let version = self.engine.model_version().to_string();
        let mut by_person: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
        for (i, l) in self.labels.iter().enumerate() {
            by_person.entry(l).or_default().push(i);
        }
        let (mut per_template, mut cosines) = (Vec::new(), Vec::new());
        for (i, t) in protected.iter().enumerate() {
            let others: Vec<usize> = by_person[self.labels[i]].iter().copied().filter(|&j| j != i).collect();
            if others.is_empty() || known.is_some_and(|k| k[i]) {
                continue;
            }
            let recovered = Template::new(&version, invert(&t.vector));
            cosines.push(recovered.cosine(&self.plain[i]) as f64);
            per_template.push(others.iter().map(|&j| self.engine.score(&recovered, std::slice::from_ref(&self.plain[j]))).collect());
        }
        AttackScores {
            attempts: per_template.iter().map(Vec::len).sum(),
            templates: per_template.len(),
            per_template,
            mean_cosine: cosines.iter().sum::<f64>() / cosines.len().max(1) as f64,
        }
    }
}

/// The rotation an attacker without the secret fits to the (plain, protected) template pairs of
/// the persons it knows (every other person, by name order): orthogonal Procrustes, `R̂ = U Vᵀ`
/// of the SVD of `Σ t xᵀ`. Returns which templates were known, and `R̂` as a [`Fitted`] map.
fn known_pair_rotation(labels: &[&str], plain: &[Template], protected: &[Template]) -> (Vec<bool>, Fitted) {
    let persons: Vec<&str> = labels.iter().copied().collect::<std::collections::BTreeSet<_>>().into_iter().collect();
    let known_persons: std::collections::BTreeSet<&str> = persons.iter().copied().step_by(2).collect();
    let known: Vec<bool> = labels.iter().map(|l| known_persons.contains(l)).collect();
    let d = rotation_dimension(plain);
    let mut m = nalgebra::DMatrix::<f64>::zeros(d, d);
    for (i, _) in known.iter().enumerate().filter(|(_, k)| **k) {
        let (x, t) = (&plain[i].vector, &protected[i].vector);
        for r in 0..d {
            for c in 0..d {
                m[(r, c)] += t[r] as f64 * x[c] as f64;
            }
        }
    }
    let svd = m.svd(true, true);
    let rotation = svd.u.expect("U asked for") * svd.v_t.expect("Vᵀ asked for");
    (known, Fitted { rotation })
}

/// A fitted linear map (the attacker's estimate of the rotation).
struct Fitted {
    rotation: nalgebra::DMatrix<f64>,
}

impl Fitted {
    /// `R̂ᵀ t`.
    fn invert(&self, t: &[f32]) -> Vec<f32> {
        let t = nalgebra::DVector::from_iterator(t.len(), t.iter().map(|v| *v as f64));
        (self.rotation.transpose() * t).iter().map(|v| *v as f32).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dsys_is_0_for_one_distribution_and_1_for_disjoint_ones() {
        let spread: Vec<f32> = (0..1000).map(|i| (i as f32 * 0.618).fract()).collect();
        assert!(dsys(&spread, &spread, DSYS_BINS).abs() < 1e-12, "the same scores link nothing");
        let shifted: Vec<f32> = spread.iter().map(|s| s + 2.0).collect();
        assert!((dsys(&shifted, &spread, DSYS_BINS) - 1.0).abs() < 1e-12, "disjoint scores link fully");
    }

    #[test]
    fn dsys_weighs_the_local_measure_by_the_mated_density() {
        // Two bins: half the mated scores where no non-mated one is (D↔ = 1), half where the
        // non-mated ones are twice as dense (LR = 1/2: D↔ = 0) → 0.5.
        let mated: Vec<f32> = [0.5f32; 50].into_iter().chain([1.5f32; 50]).collect();
        let non_mated: Vec<f32> = [1.5f32; 50].into_iter().chain([2.5f32; 50]).collect();
        assert!((dsys(&mated, &non_mated, 2) - 0.5).abs() < 1e-12, "{}", dsys(&mated, &non_mated, 2));
        // One bin where LR = 3: D↔ = 2·3/4 − 1 = 0.5, over all the mated mass; elsewhere LR < 1.
        let mated: Vec<f32> = [0.0f32; 75].into_iter().chain([1.0f32; 25]).collect();
        let non_mated: Vec<f32> = [0.0f32; 25].into_iter().chain([1.0f32; 75]).collect();
        assert!((dsys(&mated, &non_mated, 2) - 0.75 * 0.5).abs() < 1e-12, "{}", dsys(&mated, &non_mated, 2));
        assert_eq!(dsys(&[], &non_mated, 2), 0.0);
    }
}
