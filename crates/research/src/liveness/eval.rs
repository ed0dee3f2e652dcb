//! Liveness measures (ISO/IEC 30107-3) on NUAA by leave-one-subject-out folds: APCER (attacks
//! taken for live faces), BPCER (live faces taken for attacks), their mean ACER, BPCER at APCER 1%
//! and 5%, by print condition and live session, and how often the live photos of the IMM, ORL and
//! LFW test persons (other cameras, people the model never saw) are refused at each operating point.
//! A frame counts as a live face when its score is at or above the threshold.

use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;

use crate::Progress;
use crate::dataset::Split;
use crate::eval::plot::{Chart, Scale, Series, line_chart};
use crate::liveness::measures::{CAMERA_BPCER, OPERATING_POINTS, OperatingPoint, Rates, eer_threshold};
use crate::liveness::train::{LivenessData, Recipe, columns, fit_recipe, fit_recipe_without, homography_residual, out_of_fold_logits};
use crate::logistic::{LogisticFit, platt, platt_probability};
use crate::measures::{eer, error_curve, fnmr_at_fmr};
use crate::train_deep::Set;

/// The rates with each score's own threshold, that of its subject fold.
fn rates(live: &[f32], attacks: &[f32], threshold: impl Fn(usize) -> f32, live_fold: &[usize], attack_fold: &[usize]) -> Rates {
    let apcer = attacks.iter().zip(attack_fold).filter(|(s, f)| **s >= threshold(**f)).count() as f64 / attacks.len().max(1) as f64;
    let bpcer = live.iter().zip(live_fold).filter(|(s, f)| **s < threshold(**f)).count() as f64 / live.len().max(1) as f64;
    Rates { apcer, bpcer, acer: 0.5 * (apcer + bpcer) }
}

/// One recipe's measures.
#[derive(Debug, Clone, Serialize)]
pub struct LivenessReport {
    pub name: String,
    pub recipe: Recipe,
    pub live_frames: usize,
    pub attack_frames: usize,
    /// NUAA frames without a face found (left out of the rates; the service refuses them anyway).
    pub live_without_face: usize,
    pub attacks_without_face: usize,
    /// Pooled out-of-fold scores.
    pub eer: f64,
    pub bpcer_at_apcer_1: f64,
    pub bpcer_at_apcer_5: f64,
    /// Each subject's frames at the threshold of equal rates on the other subjects' scores.
    pub at_eer_of_other_subjects: Rates,
    /// At that threshold, by print condition (APCER) and by live session (BPCER).
    pub apcer_by_print_condition: BTreeMap<String, f64>,
    pub bpcer_by_live_session: BTreeMap<String, f64>,
    /// Live photos of other cameras' test persons refused, by set and operating point, for the
    /// model fitted on every NUAA subject.
    pub other_cameras_refused: Vec<Refusals>,
    /// The IMM, ORL and LFW test persons' photos as simulated prints and screens, taken for live
    /// faces by the model fitted on every NUAA subject, at each operating point: APCER on people,
    /// cameras and attacks NUAA never had.
    pub simulated_accepted: Vec<SimulatedAcceptance>,
    /// Each camera's own threshold from its live photos ([`CameraThreshold`]; recipes trained with
    /// the other cameras' live photos).
    pub camera_thresholds: Vec<CameraThreshold>,
    /// The reverse, for recipes trained with simulated attacks: a model fitted without any NUAA
    /// frame, measured on NUAA's real prints and live frames.
    pub reverse: Option<ReverseCheck>,
    /// Real video's live frames refused at the EER threshold, per clip.
    pub video_refused: Vec<crate::liveness::video_refusals::VideoRefusal>,
    /// Platt's calibration of the out-of-fold logits.
    pub calibration: (f32, f32),
    /// The same frames fused [`SEQUENCE_FRAMES`] at a time: the mean logit of consecutive frames
    /// of one capture (NUAA keeps every third frame, so they span about a third of a second).
    pub sequences: SequenceMeasures,
}

/// Frames fused per sequence decision.
pub const SEQUENCE_FRAMES: usize = 3;

/// Measures of fused frame sequences.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SequenceMeasures {
    pub frames: usize,
    pub live_sequences: usize,
    pub attack_sequences: usize,
    pub eer: f64,
    pub bpcer_at_apcer_1: f64,
    pub bpcer_at_apcer_5: f64,
}

/// Consecutive, non-overlapping runs of `frames` frames with a face of each NUAA capture (one
/// subject, glasses, condition and session), ordered by frame number: their mean logits, split
/// into live and attack.
fn sequence_scores(data: &LivenessData, logits: &[Option<f32>], frames: usize) -> (Vec<f32>, Vec<f32>) {
    let mut captures: BTreeMap<(bool, String, bool, String, String), Vec<(u32, f32)>> = BTreeMap::new();
    for (s, l) in data.nuaa.iter().zip(logits) {
        let (Some(l), Some(frame)) = (l, frame_number(&s.image)) else { continue };
        captures.entry((s.live, s.subject.clone(), s.glasses, s.condition.clone(), s.session.clone())).or_default().push((frame, *l));
    }
    let (mut live, mut attacks) = (Vec::new(), Vec::new());
    for ((is_live, ..), mut run) in captures {
        run.sort_by_key(|(f, _)| *f);
        for chunk in run.chunks_exact(frames) {
            let mean = chunk.iter().map(|(_, l)| l).sum::<f32>() / frames as f32;
            if is_live { live.push(mean) } else { attacks.push(mean) }
        }
    }
    (live, attacks)
}

/// The motion test on its own: NUAA's captures in runs of [`SEQUENCE_FRAMES`] frames, scored by how
/// badly one homography maps the first frame's 58 landmarks onto each later frame's (mean of
/// [`homography_residual`]; a live head should score higher than a print).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct MotionMeasures {
    pub live_sequences: usize,
    pub attack_sequences: usize,
    pub eer: f64,
    pub bpcer_at_apcer_1: f64,
    /// Median residual (over the inter-ocular distance) of live and of print sequences.
    pub live_median: f64,
    pub attack_median: f64,
}

/// [`MotionMeasures`] from each NUAA frame's landmarks (`None`: no face).
pub fn motion_measures(data: &LivenessData, landmarks: &[Option<Vec<facegate_core::geometry::Point>>]) -> MotionMeasures {
    let mut captures: BTreeMap<(bool, String, bool, String, String), Vec<(u32, &Vec<facegate_core::geometry::Point>)>> = BTreeMap::new();
    for (s, l) in data.nuaa.iter().zip(landmarks) {
        let (Some(l), Some(frame)) = (l, frame_number(&s.image)) else { continue };
        captures.entry((s.live, s.subject.clone(), s.glasses, s.condition.clone(), s.session.clone())).or_default().push((frame, l));
    }
    let (mut live, mut attacks) = (Vec::new(), Vec::new());
    for ((is_live, ..), mut run) in captures {
        run.sort_by_key(|(f, _)| *f);
        for chunk in run.chunks_exact(SEQUENCE_FRAMES) {
            let residuals: Vec<f64> = chunk[1..].iter().filter_map(|(_, p)| homography_residual(chunk[0].1, p)).collect();
            if residuals.len() + 1 == SEQUENCE_FRAMES {
                let mean = (residuals.iter().sum::<f64>() / residuals.len() as f64) as f32;
                if is_live { live.push(mean) } else { attacks.push(mean) }
            }
        }
    }
    let median = |v: &[f32]| {
        let mut v = v.to_vec();
        v.sort_by(f32::total_cmp);
        v.get(v.len() / 2).copied().unwrap_or(0.0) as f64
    };
    MotionMeasures {
        live_sequences: live.len(),
        attack_sequences: attacks.len(),
        eer: eer(&live, &attacks),
        bpcer_at_apcer_1: fnmr_at_fmr(&live, &attacks, 0.01).0,
        live_median: median(&live),
        attack_median: median(&attacks),
    }
}

/// The frame number at the end of a NUAA file name (`…_frame.jpg`).
fn frame_number(path: &Path) -> Option<u32> {
    path.file_stem()?.to_str()?.rsplit('_').next()?.parse().ok()
}

/// How many live photos of other cameras a model refuses at one operating point.
#[derive(Debug, Clone, Serialize)]
pub struct Refusals {
    pub operating_point: String,
    /// The calibrated score threshold.
    pub threshold: f32,
    pub imm: f64,
    pub orl: f64,
    pub lfw: f64,
    pub photos: usize,
    /// Each of IMM, ORL and LFW refused by a model trained without that set's live photos: a
    /// camera the model never saw (only for recipes that use the other cameras).
    pub imm_unseen: Option<f64>,
    pub orl_unseen: Option<f64>,
    pub lfw_unseen: Option<f64>,
    /// UMIST's photos (s01–s10, profile to frontal; no passive model is trained with them).
    pub umist: f64,
}

/// Simulated attacks of the test persons taken for live faces at one operating point.
#[derive(Debug, Clone, Serialize)]
pub struct SimulatedAcceptance {
    pub operating_point: String,
    pub threshold: f32,
    /// APCER on the simulated prints and on the simulated screens.
    pub print: f64,
    pub screen: f64,
    pub photos: usize,
}

/// A camera's own threshold, as `facegate calibrate-liveness` sets it
/// ([`facegate_service::liveness_camera::live_threshold`]): from the live photos of one data set's
/// persons outside its test split, by a model that never saw that data set, measured on its test
/// persons (their live photos and their simulated prints and screens), beside NUAA's threshold
/// on the same photos.
#[derive(Debug, Clone, Serialize)]
pub struct CameraThreshold {
    pub model: String,
    pub set: String,
    /// The share of the calibration faces the threshold may refuse.
    pub bpcer: f64,
    pub calibration_faces: usize,
    pub threshold: f32,
    pub test_live: usize,
    pub live_refused: f64,
    pub print_accepted: f64,
    pub screen_accepted: f64,
    /// The same at the model's NUAA threshold.
    pub nuaa_threshold: f32,
    pub nuaa_live_refused: f64,
    pub nuaa_print_accepted: f64,
    pub nuaa_screen_accepted: f64,
}

/// [`CameraThreshold`] of scores: the calibration persons' live faces, the test persons' live
/// faces and their simulated prints and screens; `None` when too few faces calibrate.
pub fn camera_threshold(
    (model, set): (&str, &str),
    calibration: &[f32],
    test: [&[f32]; 3],
    nuaa_threshold: f32,
) -> Option<CameraThreshold> {
    let threshold = facegate_service::liveness_camera::live_threshold(calibration, CAMERA_BPCER).ok()?;
    let [live, prints, screens] = test;
    let share = |v: &[f32], f: &dyn Fn(f32) -> bool| v.iter().filter(|&&s| f(s)).count() as f64 / v.len().max(1) as f64;
    Some(CameraThreshold {
        model: model.to_string(),
        set: set.to_string(),
        bpcer: CAMERA_BPCER,
        calibration_faces: calibration.len(),
        threshold,
        test_live: live.len(),
        live_refused: share(live, &|s| s < threshold),
        print_accepted: share(prints, &|s| s >= threshold),
        screen_accepted: share(screens, &|s| s >= threshold),
        nuaa_threshold,
        nuaa_live_refused: share(live, &|s| s < nuaa_threshold),
        nuaa_print_accepted: share(prints, &|s| s >= nuaa_threshold),
        nuaa_screen_accepted: share(screens, &|s| s >= nuaa_threshold),
    })
}

/// For a recipe trained with the other cameras' live photos: per data set, the recipe fitted on
/// every NUAA frame and the other sets' live photos, that set's left out so that its camera is new
/// (none for other recipes). The other-camera refusals and the camera thresholds both read them.
pub fn unseen_camera_fits(data: &LivenessData, recipe: &Recipe) -> Vec<(Set, LogisticFit)> {
    if !recipe.other_cameras {
        return Vec::new();
    }
    let all: Vec<usize> = (0..data.nuaa.len()).collect();
    Set::ALL.into_iter().map(|set| (set, fit_recipe_without(data, recipe, &all, Some(set)))).collect()
}

/// Per data set, the recipe's fit without it ([`unseen_camera_fits`]), its threshold set on the
/// set's non-test persons' live photos, measured on its test persons.
fn camera_thresholds(
    data: &LivenessData,
    recipe: &Recipe,
    unseen_fits: &[(Set, LogisticFit)],
    f: &FoldScores,
    calibration: (f32, f32),
) -> Vec<CameraThreshold> {
    let cols = columns(&recipe.blocks);
    let calibrated = |l: f32| platt_probability(calibration, l);
    let nuaa_threshold = calibrated(OperatingPoint::Eer.threshold(&f.live, &f.attacks));
    unseen_fits
        .iter()
        .filter_map(|(set, fit)| {
            let set = *set;
            let score = |x: &Vec<f32>| calibrated(fit.logit_at(&cols, x));
            let of_set = |test: bool| {
                (0..data.others.len()).filter(move |&i| data.others[i].set == set && (data.others[i].split == Split::Test) == test)
            };
            let live = |test: bool| -> Vec<f32> { of_set(test).filter_map(|i| data.other_features[i].as_ref()).map(score).collect() };
            let simulated =
                |kind: usize| -> Vec<f32> { of_set(true).filter_map(|i| data.simulated_features[kind][i].as_ref()).map(score).collect() };
            let (prints, screens) = (simulated(0), simulated(1));
            camera_threshold(
                ("shipped recipe, this camera left out", set.name()),
                &live(false),
                [&live(true), &prints, &screens],
                nuaa_threshold,
            )
        })
        .collect()
}

/// A model that never saw NUAA (the other cameras' training persons, live against their simulated
/// attacks) on NUAA's frames: the ranking (EER, BPCER at APCER 1%, on NUAA's own scores) and the
/// rates at the threshold of equal rates on the test persons' live photos and simulated attacks
/// (chosen without NUAA).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct ReverseCheck {
    pub eer: f64,
    pub bpcer_at_apcer_1: f64,
    pub threshold: f32,
    pub at_threshold: Rates,
}

fn simulated_acceptance(
    data: &LivenessData,
    recipe: &Recipe,
    full: &LogisticFit,
    f: &FoldScores,
    calibration: (f32, f32),
) -> Vec<SimulatedAcceptance> {
    let cols = columns(&recipe.blocks);
    let calibrated = |l: f32| platt_probability(calibration, l);
    let test = data.others_in(Split::Test);
    let scores: Vec<Vec<f32>> = data
        .simulated_features
        .iter()
        .map(|kind| test.iter().filter_map(|&i| kind[i].as_ref()).map(|x| calibrated(full.logit_at(&cols, x))).collect())
        .collect();
    let accepted = |v: &[f32], t: f32| v.iter().filter(|&&s| s >= t).count() as f64 / v.len().max(1) as f64;
    OPERATING_POINTS
        .iter()
        .map(|op| {
            let threshold = calibrated(op.threshold(&f.live, &f.attacks));
            SimulatedAcceptance {
                operating_point: op.name(),
                threshold,
                print: accepted(&scores[0], threshold),
                screen: accepted(&scores[1], threshold),
                photos: scores[0].len(),
            }
        })
        .collect()
}

fn reverse_check(data: &LivenessData, recipe: &Recipe) -> Option<ReverseCheck> {
    if !(recipe.simulated_attacks && recipe.other_cameras) {
        return None;
    }
    let cols = columns(&recipe.blocks);
    let fit = fit_recipe(data, recipe, &[]);
    let logit = |x: &Vec<f32>| fit.logit_at(&cols, x);
    let test = data.others_in(Split::Test);
    let test_live: Vec<f32> = test.iter().filter_map(|&i| data.other_features[i].as_ref()).map(logit).collect();
    let test_attacks: Vec<f32> =
        data.simulated_features.iter().flat_map(|kind| test.iter().filter_map(|&i| kind[i].as_ref())).map(logit).collect();
    let threshold = eer_threshold(&test_live, &test_attacks);
    let (mut live, mut attacks) = (Vec::new(), Vec::new());
    for (s, x) in data.nuaa.iter().zip(&data.nuaa_features) {
        let Some(x) = x else { continue };
        if s.live { live.push(logit(x)) } else { attacks.push(logit(x)) }
    }
    Some(ReverseCheck {
        eer: eer(&live, &attacks),
        bpcer_at_apcer_1: fnmr_at_fmr(&live, &attacks, 0.01).0,
        threshold,
        at_threshold: Rates::at(&live, &attacks, threshold),
    })
}

/// The out-of-fold logits of `data`'s NUAA frames split into live and attack scores, with each
/// score's subject fold.
struct FoldScores {
    live: Vec<f32>,
    attacks: Vec<f32>,
    live_fold: Vec<usize>,
    attack_fold: Vec<usize>,
    subjects: Vec<String>,
}

fn fold_scores(data: &LivenessData, logits: &[Option<f32>]) -> FoldScores {
    let subjects = crate::liveness::subjects::subjects(data);
    let mut f = FoldScores { live: vec![], attacks: vec![], live_fold: vec![], attack_fold: vec![], subjects };
    for (s, l) in data.nuaa.iter().zip(logits) {
        let Some(l) = l else { continue };
        let fold = f.subjects.iter().position(|x| *x == s.subject).unwrap_or(0);
        if s.live {
            f.live.push(*l);
            f.live_fold.push(fold);
        } else {
            f.attacks.push(*l);
            f.attack_fold.push(fold);
        }
    }
    f
}

/// Per subject, the threshold of equal rates on the other subjects' scores.
fn thresholds_from_other_subjects(f: &FoldScores) -> Vec<f32> {
    (0..f.subjects.len())
        .map(|k| {
            let live: Vec<f32> = f.live.iter().zip(&f.live_fold).filter(|(_, x)| **x != k).map(|(s, _)| *s).collect();
            let attacks: Vec<f32> = f.attacks.iter().zip(&f.attack_fold).filter(|(_, x)| **x != k).map(|(s, _)| *s).collect();
            eer_threshold(&live, &attacks)
        })
        .collect()
}

/// The measures of `recipe` on `data`, and its out-of-fold logits.
pub fn evaluate(data: &LivenessData, name: &str, recipe: &Recipe, progress: &dyn Progress) -> (LivenessReport, Vec<Option<f32>>) {
    let logits = out_of_fold_logits(data, recipe, progress);
    let f = fold_scores(data, &logits);
    let thresholds = thresholds_from_other_subjects(&f);
    let at = rates(&f.live, &f.attacks, |k| thresholds[k], &f.live_fold, &f.attack_fold);
    let mut by_condition: BTreeMap<String, (usize, usize)> = BTreeMap::new();
    let mut by_session: BTreeMap<String, (usize, usize)> = BTreeMap::new();
    for (s, l) in data.nuaa.iter().zip(&logits) {
        let Some(l) = l else { continue };
        let t = thresholds[f.subjects.iter().position(|x| *x == s.subject).unwrap_or(0)];
        let (key, wrong, map) = if s.live {
            (format!("session {}", s.session), *l < t, &mut by_session)
        } else {
            (format!("condition {}", s.condition), *l >= t, &mut by_condition)
        };
        let e = map.entry(key).or_default();
        e.0 += usize::from(wrong);
        e.1 += 1;
    }
    let share = |m: BTreeMap<String, (usize, usize)>| m.into_iter().map(|(k, (w, n))| (k, w as f64 / n.max(1) as f64)).collect();
    let live_frames = data.nuaa.iter().filter(|s| s.live).count();
    let calibration = platt(
        &f.live.iter().chain(&f.attacks).copied().collect::<Vec<_>>(),
        &f.live.iter().map(|_| true).chain(f.attacks.iter().map(|_| false)).collect::<Vec<_>>(),
    );
    // The model fitted on every NUAA subject: the other cameras and the simulated attacks both read it.
    let full = fit_recipe(data, recipe, &(0..data.nuaa.len()).collect::<Vec<_>>());
    let unseen_fits = unseen_camera_fits(data, recipe);
    let report = LivenessReport {
        name: name.to_string(),
        recipe: recipe.clone(),
        live_frames,
        attack_frames: data.nuaa.len() - live_frames,
        live_without_face: data.nuaa.iter().zip(&logits).filter(|(s, l)| s.live && l.is_none()).count(),
        attacks_without_face: data.nuaa.iter().zip(&logits).filter(|(s, l)| !s.live && l.is_none()).count(),
        eer: eer(&f.live, &f.attacks),
        bpcer_at_apcer_1: fnmr_at_fmr(&f.live, &f.attacks, 0.01).0,
        bpcer_at_apcer_5: fnmr_at_fmr(&f.live, &f.attacks, 0.05).0,
        at_eer_of_other_subjects: at,
        apcer_by_print_condition: share(by_condition),
        bpcer_by_live_session: share(by_session),
        other_cameras_refused: other_camera_refusals(data, recipe, &full, &unseen_fits, &f, calibration),
        simulated_accepted: simulated_acceptance(data, recipe, &full, &f, calibration),
        camera_thresholds: camera_thresholds(data, recipe, &unseen_fits, &f, calibration),
        reverse: reverse_check(data, recipe),
        video_refused: crate::liveness::video_refusals::video_refusals(
            data,
            recipe,
            &full,
            calibration,
            platt_probability(calibration, OperatingPoint::Eer.threshold(&f.live, &f.attacks)),
        ),
        calibration,
        sequences: {
            let (live, attacks) = sequence_scores(data, &logits, SEQUENCE_FRAMES);
            SequenceMeasures {
                frames: SEQUENCE_FRAMES,
                live_sequences: live.len(),
                attack_sequences: attacks.len(),
                eer: eer(&live, &attacks),
                bpcer_at_apcer_1: fnmr_at_fmr(&live, &attacks, 0.01).0,
                bpcer_at_apcer_5: fnmr_at_fmr(&live, &attacks, 0.05).0,
            }
        },
    };
    (report, logits)
}

/// The model fitted on every NUAA subject, calibrated, at each [`OPERATING_POINTS`] threshold (put
/// on the out-of-fold scores): the share of the IMM, ORL and LFW test persons' live photos refused.
fn other_camera_refusals(
    data: &LivenessData,
    recipe: &Recipe,
    full: &LogisticFit,
    unseen_fits: &[(Set, LogisticFit)],
    f: &FoldScores,
    calibration: (f32, f32),
) -> Vec<Refusals> {
    let cols = columns(&recipe.blocks);
    let test = data.others_in(Split::Test);
    let calibrated = |l: f32| platt_probability(calibration, l);
    // The scores of the test persons' photos of `set` by `fit`.
    let scores_of = |fit: &LogisticFit, set: Set| -> Vec<f32> {
        test.iter()
            .filter(|&&i| data.others[i].set == set)
            .map(|&i| calibrated(fit.logit_at(&cols, data.other_features[i].as_ref().expect("with features"))))
            .collect()
    };
    let umist: Vec<f32> = data.unseen_features.iter().flatten().map(|x| calibrated(full.logit_at(&cols, x))).collect();
    let by_set: Vec<(Set, Vec<f32>)> = Set::ALL.into_iter().map(|set| (set, scores_of(full, set))).collect();
    let unseen: Vec<(Set, Vec<f32>)> = unseen_fits.iter().map(|(set, fit)| (*set, scores_of(fit, *set))).collect();
    let share_below = |v: &[f32], t: f32| v.iter().filter(|&&s| s < t).count() as f64 / v.len().max(1) as f64;
    OPERATING_POINTS
        .iter()
        .map(|op| {
            let threshold = calibrated(op.threshold(&f.live, &f.attacks));
            let of = |list: &[(Set, Vec<f32>)], set: Set| list.iter().find(|(s, _)| *s == set).map(|(_, v)| share_below(v, threshold));
            Refusals {
                operating_point: op.name(),
                threshold,
                imm: of(&by_set, Set::Imm).unwrap_or(0.0),
                orl: of(&by_set, Set::Orl).unwrap_or(0.0),
                lfw: of(&by_set, Set::Lfw).unwrap_or(0.0),
                photos: test.len(),
                imm_unseen: of(&unseen, Set::Imm),
                orl_unseen: of(&unseen, Set::Orl),
                lfw_unseen: of(&unseen, Set::Lfw),
                umist: share_below(&umist, threshold),
            }
        })
        .collect()
}

/// A DET plot (APCER against BPCER, both logarithmic) of named out-of-fold score sets.
pub fn write_det(path: &Path, data: &LivenessData, sets: &[(&str, &[Option<f32>])]) -> anyhow::Result<()> {
    let series: Vec<Series> = sets
        .iter()
        .map(|(name, logits)| {
            let f = fold_scores(data, logits);
            Series {
                name,
                points: error_curve(&f.live, &f.attacks).iter().filter(|p| p.fmr > 0.0 && p.fnmr > 0.0).map(|p| (p.fmr, p.fnmr)).collect(),
            }
        })
        .collect();
    line_chart(
        path,
        &Chart {
            title: "Liveness DET on NUAA (leave one subject out)",
            x_label: "APCER (prints taken for live faces)",
            y_label: "BPCER (live faces refused)",
            x_range: (1e-4, 1.0),
            y_range: (1e-4, 1.0),
            x_scale: Scale::Log,
            y_scale: Scale::Log,
        },
        &series,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rates_count_accepted_attacks_and_refused_live_faces() {
        let live = [0.9, 0.8, 0.2, 0.7];
        let attacks = [0.1, 0.6, 0.3, 0.05];
        let r = rates(&live, &attacks, |_| 0.5, &[0; 4], &[0; 4]);
        assert_eq!((r.apcer, r.bpcer, r.acer), (0.25, 0.25, 0.25));
        assert_eq!(Rates::at(&live, &attacks, 0.5), r);
        // A score at the threshold is taken for live.
        let r = Rates::at(&[-1.0, 0.0, 2.0, 3.0], &[0.0, -2.0], 0.0);
        assert_eq!((r.apcer, r.bpcer, r.acer), (0.5, 0.25, 0.375));
        let t = eer_threshold(&live, &attacks);
        assert!(t > 0.3 && t <= 0.7, "{t}");
        // The lowest threshold with no accepted attack sits just above the highest attack.
        assert!(OperatingPoint::Apcer(0.0).threshold(&live, &attacks) > 0.6);
    }

    #[test]
    fn sequences_are_runs_of_one_capture_in_frame_order() {
        use crate::liveness::train::NuaaSample;
        let frame = |live: bool, session: &str, n: u32| NuaaSample {
            subject: "0001".into(),
            live,
            glasses: false,
            condition: "00".into(),
            session: session.into(),
            image: format!("x/0001_00_00_{session}_{n}.jpg").into(),
        };
        assert_eq!(frame_number(Path::new("real/0001/0001_00_00_01_145.jpg")), Some(145));
        // One live capture of four frames (scored out of order), one of two; one print capture of three.
        let nuaa = vec![
            frame(true, "01", 9),
            frame(true, "01", 0),
            frame(true, "01", 3),
            frame(true, "01", 6),
            frame(true, "02", 0),
            frame(true, "02", 3),
            frame(false, "01", 0),
            frame(false, "01", 3),
            frame(false, "01", 6),
        ];
        let logits = [Some(100.0), Some(1.0), Some(2.0), Some(3.0), Some(5.0), Some(5.0), Some(-1.0), None, Some(-3.0)];
        let data = LivenessData {
            nuaa,
            nuaa_features: vec![],
            others: vec![],
            other_features: vec![],
            unseen: vec![],
            unseen_features: vec![],
            simulated_features: vec![],
            video: vec![],
            video_features: vec![],
        };
        let (live, attacks) = sequence_scores(&data, &logits, 2);
        // Frames 0, 3 | 6, 9 of the first capture; 0, 3 of the second; the print's frame without a face is skipped.
        assert_eq!(live, vec![1.5, 51.5, 5.0]);
        assert_eq!(attacks, vec![-2.0]);
    }
}
