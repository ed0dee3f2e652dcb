//! Liveness on NUAA subjects never given, by a nested subject-wise protocol: for each subject (the
//! outer fold) the model is fitted on the other subjects, its threshold is chosen on those subjects
//! alone (from their own leave-one-subject-out scores, by a [`ThresholdRule`]), and only then is
//! the held-out subject scored. Every subject's APCER and BPCER is reported, and the worst.
//!
//! Why nested: a threshold read on pooled out-of-fold scores was set with the held-out subject's
//! scores among them, and by models that had trained on that subject; the figure it gives (ACER
//! about 1% by leave-one-subject-out) did not predict new people (half of their prints passed).

use serde::Serialize;

use crate::Progress;
use crate::cache::map_samples;
use crate::liveness::train::{LivenessData, Recipe, columns, fit_recipe};
use crate::measures::{eer, fnmr_at_fmr};
use facegate_vision::recognize::calibration::threshold_at;

/// How a threshold is chosen on development scores (never on the subject it is applied to).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub enum ThresholdRule {
    /// Where APCER and BPCER are equal on the development subjects' pooled scores.
    PooledEer,
    /// The lowest threshold with pooled APCER at most this.
    PooledApcer(f64),
    /// The lowest threshold that keeps *every* development subject's APCER at most this: the
    /// worst development fold decides, so that a subject whose prints look live is covered.
    WorstSubjectApcer(f64),
    /// The highest threshold that refuses at most this share of the development subjects' live
    /// frames, their prints unused: what `facegate calibrate-liveness` does with a camera's live
    /// captures ([`facegate_service::liveness_camera::live_threshold`]).
    LiveBpcer(f64),
}

/// The rules compared.
pub const RULES: [ThresholdRule; 5] = [
    ThresholdRule::PooledEer,
    ThresholdRule::PooledApcer(0.01),
    ThresholdRule::WorstSubjectApcer(0.05),
    ThresholdRule::WorstSubjectApcer(0.01),
    ThresholdRule::LiveBpcer(crate::liveness::measures::CAMERA_BPCER),
];

/// One frame's score: its subject (an index into the fold's subject list), whether it is live.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Scored {
    pub subject: usize,
    pub live: bool,
    pub score: f32,
}

impl ThresholdRule {
    pub fn threshold(self, development: &[Scored]) -> f32 {
        let (live, attacks): (Vec<&Scored>, Vec<&Scored>) = development.iter().partition(|s| s.live);
        let live: Vec<f32> = live.iter().map(|s| s.score).collect();
        let attacks_all: Vec<f32> = attacks.iter().map(|s| s.score).collect();
        match self {
            ThresholdRule::PooledEer => crate::liveness::measures::eer_threshold(&live, &attacks_all),
            ThresholdRule::PooledApcer(a) => threshold_at(&attacks_all, a),
            ThresholdRule::WorstSubjectApcer(a) => {
                let mut subjects: Vec<usize> = attacks.iter().map(|s| s.subject).collect();
                subjects.sort_unstable();
                subjects.dedup();
                subjects
                    .into_iter()
                    .map(|k| threshold_at(&attacks.iter().filter(|s| s.subject == k).map(|s| s.score).collect::<Vec<_>>(), a))
                    .fold(f32::NEG_INFINITY, f32::max)
            }
            // Too few live frames to place the share: the lowest live score refuses none of them.
            ThresholdRule::LiveBpcer(share) => facegate_service::liveness_camera::live_threshold(&live, share)
                .unwrap_or_else(|_| live.iter().copied().fold(f32::INFINITY, f32::min)),
        }
    }

    pub fn name(self) -> String {
        match self {
            ThresholdRule::PooledEer => "pooled EER".to_string(),
            ThresholdRule::PooledApcer(a) => format!("pooled APCER {}%", a * 100.0),
            ThresholdRule::WorstSubjectApcer(a) => format!("every subject's APCER {}%", a * 100.0),
            ThresholdRule::LiveBpcer(b) => format!("live frames only, BPCER {}%", b * 100.0),
        }
    }
}

/// One held-out subject: its frames scored by the model fitted without it, and the development
/// subjects' frames scored by models fitted without each of them in turn (what its threshold is
/// chosen on).
#[derive(Debug, Clone)]
pub struct Fold {
    pub subject: String,
    pub held_out: Vec<Scored>,
    pub development: Vec<Scored>,
}

/// A model that learns: scores of the frames `score` (NUAA indices) by a fit on the NUAA frames
/// `train` (`None`: no face in the frame). A fixed network ignores `train`.
pub type FitAndScore<'a> = dyn Fn(&[usize], &[usize]) -> Vec<Option<f32>> + Sync + 'a;

/// The sorted NUAA subjects of `data`.
pub fn subjects(data: &LivenessData) -> Vec<String> {
    let mut s: Vec<String> = data.nuaa.iter().map(|s| s.subject.clone()).collect();
    s.sort_unstable();
    s.dedup();
    s
}

/// The folds of the nested protocol: one fit per held-out subject and one per (held-out,
/// development) pair, `threads` at a time.
pub fn folds(data: &LivenessData, fit_and_score: &FitAndScore, threads: usize, progress: &dyn Progress) -> Vec<Fold> {
    let subjects = subjects(data);
    let of = |k: usize| -> Vec<usize> { (0..data.nuaa.len()).filter(|&i| data.nuaa[i].subject == subjects[k]).collect() };
    // (held out, also left out of the training: a development subject scored, or none for the outer fit).
    let jobs: Vec<(usize, Option<usize>)> = (0..subjects.len())
        .flat_map(|k| std::iter::once((k, None)).chain((0..subjects.len()).filter(move |&j| j != k).map(move |j| (k, Some(j)))))
        .collect();
    let scored: Vec<Vec<Scored>> = map_samples(&jobs, threads, "nested subject folds", progress, |&(k, inner)| {
        let target = inner.unwrap_or(k);
        let train: Vec<usize> = (0..data.nuaa.len())
            .filter(|&i| data.nuaa[i].subject != subjects[k] && Some(data.nuaa[i].subject.as_str()) != inner.map(|j| subjects[j].as_str()))
            .collect();
        let frames = of(target);
        let scores = fit_and_score(&train, &frames);
        frames.iter().zip(scores).filter_map(|(&i, s)| Some(Scored { subject: target, live: data.nuaa[i].live, score: s? })).collect()
    });
    (0..subjects.len())
        .map(|k| {
            let mine = jobs.iter().zip(&scored).filter(|((o, _), _)| *o == k);
            let mut fold = Fold { subject: subjects[k].clone(), held_out: Vec::new(), development: Vec::new() };
            for ((_, inner), s) in mine {
                match inner {
                    None => fold.held_out.extend_from_slice(s),
                    Some(_) => fold.development.extend_from_slice(s),
                }
            }
            fold
        })
        .collect()
}

/// The logistic `recipe` as a [`FitAndScore`]: its logits.
pub fn recipe_scores<'a>(data: &'a LivenessData, recipe: &'a Recipe) -> impl Fn(&[usize], &[usize]) -> Vec<Option<f32>> + Sync + 'a {
    let cols = columns(&recipe.blocks);
    move |train, score| {
        let fit = fit_recipe(data, recipe, train);
        score.iter().map(|&i| data.nuaa_features[i].as_ref().map(|f| fit.logit_at(&cols, f))).collect()
    }
}

/// One unseen subject's error rates at the threshold chosen without it.
#[derive(Debug, Clone, Serialize)]
pub struct SubjectRates {
    pub subject: String,
    pub threshold: f32,
    pub live: usize,
    pub attacks: usize,
    pub apcer: f64,
    pub bpcer: f64,
}

/// A model under the nested protocol with one threshold rule.
#[derive(Debug, Clone, Serialize)]
pub struct NestedReport {
    pub name: String,
    pub rule: String,
    pub subjects: Vec<SubjectRates>,
    /// Over every held-out frame, each at its own fold's threshold.
    pub apcer: f64,
    pub bpcer: f64,
    pub acer: f64,
    /// The subject with the highest APCER, and that APCER; the highest BPCER of any subject.
    pub worst_apcer_subject: String,
    pub worst_apcer: f64,
    pub worst_bpcer_subject: String,
    pub worst_bpcer: f64,
    /// The held-out scores pooled (each from the model that never saw its subject): the EER and
    /// BPCER at APCER 1%, whose threshold is read on those very scores (the ranking, not a
    /// threshold a new subject would meet).
    pub pooled_eer: f64,
    pub pooled_bpcer_at_apcer_1: f64,
}

/// The rates of every fold at the threshold `rule` chooses on its development scores.
pub fn report(name: &str, folds: &[Fold], rule: ThresholdRule) -> NestedReport {
    let mut subjects = Vec::new();
    let (mut wrong_attacks, mut attacks, mut wrong_live, mut live) = (0usize, 0usize, 0usize, 0usize);
    for fold in folds {
        let t = rule.threshold(&fold.development);
        let n_attacks = fold.held_out.iter().filter(|s| !s.live).count();
        let n_live = fold.held_out.len() - n_attacks;
        let accepted = fold.held_out.iter().filter(|s| !s.live && s.score >= t).count();
        let refused = fold.held_out.iter().filter(|s| s.live && s.score < t).count();
        (wrong_attacks, attacks, wrong_live, live) = (wrong_attacks + accepted, attacks + n_attacks, wrong_live + refused, live + n_live);
        let share = |w: usize, n: usize| w as f64 / n.max(1) as f64;
        subjects.push(SubjectRates {
            subject: fold.subject.clone(),
            threshold: t,
            live: n_live,
            attacks: n_attacks,
            apcer: share(accepted, n_attacks),
            bpcer: share(refused, n_live),
        });
    }
    let worst = |key: fn(&SubjectRates) -> f64| {
        subjects.iter().max_by(|a, b| key(a).total_cmp(&key(b))).map_or((String::new(), 0.0), |s| (s.subject.clone(), key(s)))
    };
    let (worst_apcer_subject, worst_apcer) = worst(|s| s.apcer);
    let (worst_bpcer_subject, worst_bpcer) = worst(|s| s.bpcer);
    let pooled =
        |want_live: bool| -> Vec<f32> { folds.iter().flat_map(|f| &f.held_out).filter(|s| s.live == want_live).map(|s| s.score).collect() };
    let (pooled_live, pooled_attacks) = (pooled(true), pooled(false));
    let (apcer, bpcer) = (wrong_attacks as f64 / attacks.max(1) as f64, wrong_live as f64 / live.max(1) as f64);
    NestedReport {
        name: name.to_string(),
        rule: rule.name(),
        subjects,
        apcer,
        bpcer,
        acer: 0.5 * (apcer + bpcer),
        worst_apcer_subject,
        worst_apcer,
        worst_bpcer_subject,
        worst_bpcer,
        pooled_eer: eer(&pooled_live, &pooled_attacks),
        pooled_bpcer_at_apcer_1: fnmr_at_fmr(&pooled_live, &pooled_attacks, 0.01).0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scored(subject: usize, live: bool, scores: &[f32]) -> Vec<Scored> {
        scores.iter().map(|&score| Scored { subject, live, score }).collect()
    }

    #[test]
    fn the_worst_subject_rule_covers_the_subject_whose_prints_score_high() {
        // Subject 0's prints sit low; subject 1's prints reach 0.8: pooled, they are 1 in 10 of
        // the attacks, so a pooled APCER 10% rule lets them through, the worst-subject rule not.
        let mut dev = scored(0, false, &[0.1; 9]);
        dev.extend(scored(1, false, &[0.8]));
        dev.extend(scored(0, true, &[0.9; 5]));
        let pooled = ThresholdRule::PooledApcer(0.1).threshold(&dev);
        let worst = ThresholdRule::WorstSubjectApcer(0.1).threshold(&dev);
        assert!(pooled <= 0.8, "{pooled}");
        assert!(worst > 0.8, "{worst}");
    }

    #[test]
    fn the_live_only_rule_reads_no_print() {
        // 100 development live frames 0.01 … 1.00: at 2% the third lowest, whatever the prints.
        let live: Vec<f32> = (1..=100).map(|i| i as f32 / 100.0).collect();
        let mut dev = scored(0, true, &live);
        let rule = ThresholdRule::LiveBpcer(0.02);
        assert_eq!(rule.threshold(&dev), 0.03);
        dev.extend(scored(1, false, &[0.99; 50]));
        assert_eq!(rule.threshold(&dev), 0.03, "prints do not move it");
        // Too few live frames for the share: none of them is refused.
        assert_eq!(rule.threshold(&scored(0, true, &[0.4, 0.7])), 0.4);
    }

    #[test]
    fn each_subject_is_judged_at_its_own_folds_threshold() {
        // Fold A's development puts the threshold above 0.5; fold B's below 0.3.
        let a = Fold {
            subject: "a".into(),
            held_out: [scored(0, false, &[0.4]), scored(0, true, &[0.6, 0.7])].concat(),
            development: [scored(1, false, &[0.5, 0.55]), scored(1, true, &[0.9])].concat(),
        };
        let b = Fold {
            subject: "b".into(),
            held_out: [scored(1, false, &[0.4]), scored(1, true, &[0.35])].concat(),
            development: [scored(0, false, &[0.1, 0.2]), scored(0, true, &[0.3])].concat(),
        };
        let r = report("m", &[a, b], ThresholdRule::PooledApcer(0.0));
        assert_eq!(r.subjects[0].apcer, 0.0);
        assert_eq!(r.subjects[0].bpcer, 0.0);
        assert_eq!(r.subjects[1].apcer, 1.0);
        assert_eq!(r.subjects[1].bpcer, 0.0);
        assert_eq!(r.worst_apcer_subject, "b");
        assert_eq!((r.apcer, r.bpcer), (0.5, 0.0));
    }
}
