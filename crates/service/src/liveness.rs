//! What the service does with a face's liveness (presentation-attack detection): the one owner
//! of the decision. Vision measures a score (`facegate_vision::liveness`); the service holds the
//! operator's [`LivenessPolicy`] and the one threshold in force ([`LivenessPoint`]: the model's,
//! a camera's calibration or the operator's, and which of them, [`ThresholdSource`]), and decides
//! once per photo or capture ([`LivenessPoint::judge`], [`check_liveness`]). Every enrolment
//! photo and every verify or identify probe is held to it; `/analyze` reports the verdict and
//! never refuses. A verification may bring further frames of the same capture:
//! [`fuse_liveness`] makes one measured liveness of them all, which is then judged.

use serde::Serialize;

use facegate_vision::liveness::{Liveness, LivenessModel};

use crate::PhotoError;

/// What the service does with a face's liveness (the binary's `--liveness`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LivenessPolicy {
    /// No liveness: the binary drops the model, nothing is computed, responses carry none.
    Off,
    /// Every face reports its liveness; nothing is refused.
    #[default]
    Report,
    /// As `Report`, and enrolment, verify and identify refuse a face taken for an attack
    /// ([`PhotoError::PresentationAttack`], 422 `presentation-attack`).
    Enforce,
}

/// Who set the liveness threshold in force (`/health`'s `liveness.source`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ThresholdSource {
    /// The liveness model's own operating point, chosen when it was trained.
    Model,
    /// This camera's calibration (`facegate calibrate-liveness`), stored in the database.
    Camera,
    /// The operator's `--liveness-threshold`.
    Operator,
}

/// The liveness threshold in force: the score below which a face is an attack, who set it and
/// what it is, for a refusal to explain itself and `/health` to report.
#[derive(Debug, Clone, PartialEq)]
pub struct LivenessPoint {
    pub threshold: f32,
    pub source: ThresholdSource,
    /// The liveness model whose scores it holds (`liveness.model` in responses).
    pub model: String,
    /// How the threshold was chosen ("EER of leave-one-subject-out NUAA scores", the camera's
    /// calibration, or the operator's own), in words.
    pub operating_point: String,
}

impl LivenessPoint {
    /// The operating point `model` was trained at.
    pub fn of_model(model: &LivenessModel) -> LivenessPoint {
        LivenessPoint {
            threshold: model.threshold,
            source: ThresholdSource::Model,
            model: model.name.clone(),
            operating_point: model.operating_point.clone(),
        }
    }

    /// This point with the operator's `threshold` in its place, saying what it replaced.
    pub fn operator(self, threshold: f32) -> LivenessPoint {
        LivenessPoint {
            threshold,
            source: ThresholdSource::Operator,
            model: self.model.clone(),
            operating_point: format!(
                "the operator's threshold (--liveness-threshold {threshold}) in place of the {}'s {:.3}, the {}",
                self.source.name(),
                self.threshold,
                self.operating_point
            ),
        }
    }

    /// The verdict on a `measured` liveness: an attack when its score is below the threshold.
    pub fn judge(&self, measured: &Liveness) -> LivenessVerdict {
        LivenessVerdict { score: measured.score, attack: measured.score < self.threshold, model: measured.model.clone() }
    }
}

/// The one threshold the service decides by, from the liveness `model`'s own point: the
/// operator's `--liveness-threshold` wins, else this `camera`'s calibration, else the model's.
pub fn threshold_in_force(model: LivenessPoint, camera: Option<LivenessPoint>, operator: Option<f32>) -> LivenessPoint {
    let start = camera.unwrap_or(model);
    match operator {
        Some(threshold) => start.operator(threshold),
        None => start,
    }
}

impl ThresholdSource {
    /// Its name in words and in `/health`.
    pub fn name(self) -> &'static str {
        match self {
            ThresholdSource::Model => "model",
            ThresholdSource::Camera => "camera",
            ThresholdSource::Operator => "operator",
        }
    }
}

/// The service's verdict on a face's (or a capture's) liveness: its score, whether it is taken
/// for an attack, and the model that measured it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LivenessVerdict {
    /// The calibrated probability that the face is live, 0–1.
    pub score: f32,
    /// Below the threshold in force (or, for a challenged capture, a failed challenge).
    pub attack: bool,
    pub model: String,
}

/// A face refused as a presentation attack: its score and the operating point it fell below.
#[derive(Debug, Clone, PartialEq)]
pub struct PresentationAttack {
    /// The calibrated probability of a live face, 0–1.
    pub score: f32,
    pub threshold: f32,
    pub operating_point: String,
    /// The liveness model that scored it.
    pub model: String,
}

impl std::fmt::Display for PresentationAttack {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "the face was taken for a presentation attack (a printed photo held to the camera), not a live face: its liveness \
             score {:.3} is below the threshold {:.3} ({}); present the live face itself",
            self.score, self.threshold, self.operating_point
        )
    }
}

/// Hold one face's `measured` liveness against `policy` at `point`, the threshold in force:
/// `Off` gives no verdict (nothing is reported), `Report` the verdict, `Enforce` refuses an
/// attack. Enforcing without a measure or a threshold (no model loaded, which the binary
/// refuses at start-up) fails closed: the face is not let through unchecked.
pub fn check_liveness(
    policy: LivenessPolicy,
    point: Option<&LivenessPoint>,
    measured: Option<&Liveness>,
) -> Result<Option<LivenessVerdict>, PhotoError> {
    match (policy, point, measured) {
        (LivenessPolicy::Off, _, _) => Ok(None),
        (LivenessPolicy::Report, Some(point), Some(measured)) => Ok(Some(point.judge(measured))),
        (LivenessPolicy::Report, _, _) => Ok(None),
        (LivenessPolicy::Enforce, Some(point), Some(measured)) => {
            let verdict = point.judge(measured);
            if !verdict.attack {
                return Ok(Some(verdict));
            }
            Err(PhotoError::PresentationAttack(PresentationAttack {
                score: verdict.score,
                threshold: point.threshold,
                operating_point: point.operating_point.clone(),
                model: verdict.model,
            }))
        }
        (LivenessPolicy::Enforce, _, _) => Err(PhotoError::LivenessUnavailable),
    }
}

/// Scores are clamped into `[SCORE_CLAMP, 1 − SCORE_CLAMP]` before their logit, so that a score of
/// exactly 0 or 1 cannot outvote every other frame.
const SCORE_CLAMP: f64 = 1e-6;

/// The measured liveness of one capture from the liveness of each of its frames (the probe
/// first): the mean of the frames' log-odds, `score = σ(mean over i of logit(score_i))` with
/// `logit(s) = ln(s / (1 − s))`. Averaging log-odds is averaging the evidence of independent
/// looks at one face (docs/liveness.md: three frames of one capture lower the EER from 0.72% to
/// 0.52%). `None` for no frames; the model is the first frame's. A measure, judged like any
/// other ([`check_capture_liveness`]).
pub fn fuse_liveness(frames: &[Liveness]) -> Option<Liveness> {
    let first = frames.first()?;
    let logit = |s: f32| {
        let s = f64::from(s).clamp(SCORE_CLAMP, 1.0 - SCORE_CLAMP);
        (s / (1.0 - s)).ln()
    };
    let mean = frames.iter().map(|f| logit(f.score)).sum::<f64>() / frames.len() as f64;
    let score = (1.0 / (1.0 + (-mean).exp())) as f32;
    Some(Liveness { score, model: first.model.clone() })
}

/// The liveness of a capture held against `policy`: `each` photo's own (the probe's first; `None`
/// when one has none) fused by [`fuse_liveness`], then [`check_liveness`] at `point`. Returns the
/// verdict and each photo's own score (empty when nothing is reported).
pub fn check_capture_liveness(
    policy: LivenessPolicy,
    point: Option<&LivenessPoint>,
    each: Option<Vec<Liveness>>,
) -> Result<(Option<LivenessVerdict>, Vec<f32>), PhotoError> {
    let fused = each.as_deref().and_then(fuse_liveness);
    let verdict = check_liveness(policy, point, fused.as_ref())?;
    let scores = match (&verdict, each) {
        (Some(_), Some(each)) => each.iter().map(|l| l.score).collect(),
        _ => Vec::new(),
    };
    Ok((verdict, scores))
}

/// The liveness of a capture that answered a head-turn challenge (`passed`: the challenge's
/// outcome): the frames' passive scores fused as for any capture ([`check_capture_liveness`]),
/// an attack when the challenge failed. The challenge's geometry stops flat attacks by itself,
/// so the passive score decides here only at a threshold set for this deployment (the camera's
/// calibration or the operator's): the model's own point was set on NUAA's camera and refuses
/// most live faces of a camera it never saw (a webcam's clips: 92 % of their frames,
/// docs/liveness-challenge.md), while no attack that passes the challenge's other checks was
/// stopped by it. At the model's point the fused score is reported, not held.
pub fn check_challenged_liveness(
    policy: LivenessPolicy,
    point: Option<&LivenessPoint>,
    each: Option<Vec<Liveness>>,
    passed: bool,
) -> Result<(Option<LivenessVerdict>, Vec<f32>), PhotoError> {
    let deployment_point = point.is_some_and(|p| p.source != ThresholdSource::Model);
    let held = if deployment_point || policy == LivenessPolicy::Off { policy } else { LivenessPolicy::Report };
    let (verdict, scores) = check_capture_liveness(held, point, each)?;
    if policy == LivenessPolicy::Enforce && verdict.is_none() {
        // Enforcing without a measure or a threshold fails closed, as for any capture.
        return Err(PhotoError::LivenessUnavailable);
    }
    let verdict = verdict.map(|v| LivenessVerdict { attack: (deployment_point && v.attack) || !passed, ..v });
    Ok((verdict, scores))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_capture_is_the_mean_of_its_frames_log_odds() {
        let frame = |score: f32| Liveness { score, model: "m-1".into() };
        assert_eq!(fuse_liveness(&[]), None);
        // One frame is itself (up to rounding).
        let one = fuse_liveness(&[frame(0.83)]).unwrap();
        assert!((one.score - 0.83).abs() < 1e-6 && one.model == "m-1", "{one:?}");
        // Log-odds 2 ln 9, −ln 9 and 2 ln 9 (scores 81/82, 0.1, 81/82): mean ln 9, score 0.9.
        let fused = fuse_liveness(&[frame(81.0 / 82.0), frame(0.1), frame(81.0 / 82.0)]).unwrap();
        assert!((fused.score - 0.9).abs() < 1e-6, "{fused:?}");
        assert!(!point().unwrap().judge(&fused).attack, "one doubtful frame among confident live ones is outvoted");
        // Not the mean of the scores: 0.5 and 81/82 fuse to σ(ln 81 / 2) = 0.9, not 0.744.
        let fused = fuse_liveness(&[frame(0.5), frame(81.0 / 82.0)]).unwrap();
        assert!((fused.score - 0.9).abs() < 1e-6, "{fused:?}");
        // Scores of exactly 0 and 1 are clamped (finite log-odds) and cancel out.
        let fused = fuse_liveness(&[frame(0.0), frame(1.0)]).unwrap();
        assert!((fused.score - 0.5).abs() < 1e-6, "{fused:?}");
        // Clamped at 1e-6: two frames scored 0 and one scored 1 fuse to σ(−ln(10⁶ − 1) / 3) ≈ 1/101.
        let fused = fuse_liveness(&[frame(0.0), frame(0.0), frame(1.0)]).unwrap();
        assert!((fused.score - 1.0 / 101.0).abs() < 1e-5, "{fused:?}");
    }

    fn liveness(score: f32) -> Liveness {
        Liveness { score, model: "m-1".into() }
    }

    fn verdict(score: f32, attack: bool) -> Option<LivenessVerdict> {
        Some(LivenessVerdict { score, attack, model: "m-1".into() })
    }

    fn point() -> Option<LivenessPoint> {
        Some(LivenessPoint { threshold: 0.7, source: ThresholdSource::Model, model: "m-1".into(), operating_point: "EER of NUAA".into() })
    }

    #[test]
    fn enforce_refuses_an_attack_report_reports_it_off_drops_it() {
        // An attack: refused only under enforce, with the score and the operating point.
        let attack = liveness(0.01);
        let refused = check_liveness(LivenessPolicy::Enforce, point().as_ref(), Some(&attack)).unwrap_err();
        let PhotoError::PresentationAttack(why) = &refused else { panic!("{refused:?}") };
        assert_eq!(why, &PresentationAttack { score: 0.01, threshold: 0.7, operating_point: "EER of NUAA".into(), model: "m-1".into() });
        assert!(refused.to_string().contains("0.010 is below the threshold 0.700 (EER of NUAA)"), "{refused}");
        let reported = check_liveness(LivenessPolicy::Report, point().as_ref(), Some(&attack)).unwrap();
        assert_eq!(reported, verdict(0.01, true), "report keeps the verdict for the response");
        assert_eq!(check_liveness(LivenessPolicy::Off, point().as_ref(), Some(&attack)).unwrap(), None, "off reports nothing");

        // A live face passes every policy; the threshold in force decides, at its edge too.
        for policy in [LivenessPolicy::Enforce, LivenessPolicy::Report] {
            assert_eq!(check_liveness(policy, point().as_ref(), Some(&liveness(0.99))).unwrap(), verdict(0.99, false));
            assert_eq!(check_liveness(policy, point().as_ref(), Some(&liveness(0.7))).unwrap(), verdict(0.7, false));
        }
        let lower = point().map(|p| p.operator(0.005));
        assert_eq!(check_liveness(LivenessPolicy::Enforce, lower.as_ref(), Some(&attack)).unwrap(), verdict(0.01, false));
    }

    #[test]
    fn the_operator_wins_then_the_camera_then_the_model() {
        let model = point().unwrap();
        let camera =
            LivenessPoint { threshold: 0.4, source: ThresholdSource::Camera, operating_point: "this camera's".into(), ..model.clone() };
        assert_eq!(threshold_in_force(model.clone(), None, None), model);
        assert_eq!(threshold_in_force(model.clone(), Some(camera.clone()), None), camera);
        for camera in [None, Some(camera)] {
            let operator = threshold_in_force(model.clone(), camera.clone(), Some(0.25));
            assert_eq!((operator.threshold, operator.source, operator.model.as_str()), (0.25, ThresholdSource::Operator, "m-1"));
            let replaced = match &camera {
                Some(_) => "in place of the camera's 0.400, the this camera's",
                None => "in place of the model's 0.700, the EER of NUAA",
            };
            assert!(operator.operating_point.contains(replaced), "{}", operator.operating_point);
        }
    }

    #[test]
    fn a_passed_challenge_holds_the_passive_score_only_at_a_deployments_threshold() {
        let each = || Some(vec![liveness(0.3), liveness(0.3)]);
        let model = point().unwrap();
        let camera = LivenessPoint { source: ThresholdSource::Camera, ..model.clone() };
        let operator = model.clone().operator(0.7);
        // At the model's own point (0.7) a webcam's 0.3 is reported, not refused: the challenge decides.
        let (verdict, scores) = check_challenged_liveness(LivenessPolicy::Enforce, Some(&model), each(), true).unwrap();
        assert_eq!((verdict.as_ref().map(|v| (v.attack, v.score)), scores.len()), (Some((false, 0.3)), 2), "{verdict:?}");
        // A failed challenge is an attack whatever the score (enforce refuses it before, with its reason).
        let (verdict, _) = check_challenged_liveness(LivenessPolicy::Report, Some(&model), Some(vec![liveness(0.99)]), false).unwrap();
        assert_eq!(verdict.map(|v| v.attack), Some(true));
        // At the camera's or the operator's threshold the passive score decides as for any capture.
        for point in [&camera, &operator] {
            let refused = check_challenged_liveness(LivenessPolicy::Enforce, Some(point), each(), true).unwrap_err();
            assert!(matches!(refused, PhotoError::PresentationAttack(_)), "{refused:?}");
            let (verdict, _) = check_challenged_liveness(LivenessPolicy::Report, Some(point), each(), true).unwrap();
            assert_eq!(verdict.map(|v| v.attack), Some(true), "{point:?}");
            let (verdict, _) = check_challenged_liveness(LivenessPolicy::Enforce, Some(point), Some(vec![liveness(0.9)]), true).unwrap();
            assert_eq!(verdict.map(|v| v.attack), Some(false), "{point:?}");
        }
        // Enforcing without a measure fails closed; off reports nothing.
        let unavailable = check_challenged_liveness(LivenessPolicy::Enforce, Some(&model), None, true).unwrap_err();
        assert!(matches!(unavailable, PhotoError::LivenessUnavailable), "{unavailable:?}");
        assert_eq!(check_challenged_liveness(LivenessPolicy::Off, Some(&model), each(), true).unwrap(), (None, Vec::new()));
    }

    #[test]
    fn enforce_without_a_liveness_fails_closed() {
        let unavailable = |point: Option<LivenessPoint>, measured: Option<Liveness>| {
            matches!(check_liveness(LivenessPolicy::Enforce, point.as_ref(), measured.as_ref()), Err(PhotoError::LivenessUnavailable))
        };
        assert!(unavailable(None, None));
        assert!(unavailable(point(), None));
        assert!(unavailable(None, Some(liveness(0.01))));
        assert_eq!(check_liveness(LivenessPolicy::Report, None, None).unwrap(), None);
        assert_eq!(LivenessPolicy::default(), LivenessPolicy::Report);
    }
}
