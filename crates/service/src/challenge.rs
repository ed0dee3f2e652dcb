//! Active liveness: the head-turn challenge's rules. [`draw_steps`] draws 3 or 4 steps (front,
//! left, right, at least one turn to each side, never the same turn twice in a row) under a
//! random id ([`new_challenge_id`]); [`frame_steps_of`] groups the frames that answer them into
//! each step's burst, and [`judge`] decides. The challenge's limits all live here, beside the
//! decision (the service's side, issuing, taking and answering a challenge, is
//! `facegate/challenge.rs`):
//!
//! - each step's median yaw lies in its range ([`Turn::yaw_range`]; stops the still photo, the
//!   wrong order, and a flat photo turned, whose key points' yaw stays under the turn range);
//! - each turn's narrowing agrees with its yaw ([`MAX_EXCESS_TURN`]; stops a picture turned so
//!   far, 60° or so, that its key points read a turn);
//! - one capture, one person: every frame matches the probe, and the frames of every other step,
//!   at [`CAPTURE_FMR`] (stops a stranger's photo in a step);
//! - a head, not a plane ([`head_turn::depth_test`]): the nose crosses the face the way the turns
//!   ask by at least [`SHIFT_MIN`] eye distances per step of turn, and by at least [`Z_MIN`]
//!   standard errors of the noise the frames show ([`NOISE_FLOOR`] at the least). Neither reads
//!   a person's nose depth: a live head whose key points read the turns' least yaw (12°) has
//!   crossed about 0.15 (docs/liveness-challenge.md).
//!
//! - a camera's face, not a rendered head: the rendered-head detector (`render.bin`), fused over
//!   the frames, at [`RENDER_MIN`] (a good 3D render turns like a head: the depth test cannot
//!   tell it).

use std::time::Duration;

use rand::Rng;
use rand::seq::IndexedRandom;
use serde::Serialize;

use facegate_core::template::Template;
use facegate_vision::liveness::Liveness;
use facegate_vision::liveness::head_turn::{self, DepthTest, FramePose, HeadTurn, Step, StepReading, Turn};
use facegate_vision::pipeline::FaceAnalysis;

use crate::Matcher;

/// Most degrees a turned step's narrowing may say the face turned beyond its yaw
/// ([`StepReading::excess_turn`]): a head's eyes draw together about as much as its nose says it
/// turned; a picture turned far enough for its key points to read a turn narrows far more.
/// Chosen on the development material (docs/liveness-challenge.md).
pub const MAX_EXCESS_TURN: f32 = 30.0;
/// Least crossing of the nose per step of turn ([`DepthTest::shift`], eye distances). A plane
/// shows 0; a bent sheet a few hundredths; a live head whose key points read 12° about 0.15.
/// Chosen on the development material (`facegate eval challenge`; docs/liveness-challenge.md).
pub const SHIFT_MIN: f64 = 0.06;
/// Least [`DepthTest::z`]: the crossing in standard errors of the frames' own noise (√F of the
/// plane against the head).
pub const Z_MIN: f64 = 4.0;
/// Least noise one frame's canonical nose is taken to have (eye distances): the detector's key
/// points move about this much between video frames of a still head, so identical frames (a
/// print held still) do not make a small crossing count.
pub const NOISE_FLOOR: f64 = 0.02;
/// The operating point at which every frame must match the probe and the other steps' frames:
/// the strictest calibrated one (the frames are seconds apart under one camera). A model
/// calibrated down to 1e-4 only is held to its 1e-4 point.
pub const CAPTURE_FMR: f64 = 1e-5;
/// Most frames answering one step (`frame_steps`); announced as `max_frames_per_step`.
pub const MAX_FRAMES_PER_STEP: usize = 5;
/// Most steps a challenge has ([`draw_steps`]).
pub const MAX_STEPS: usize = 4;
/// Most frames a capture takes beside its probe: a challenge's bursts, and as many on a plain
/// `/verify` (its passive liveness is fused over them, [`crate::fuse_liveness`]), so that one limit
/// holds whether or not a challenge is named.
pub const MAX_CAPTURE_FRAMES: usize = MAX_STEPS * MAX_FRAMES_PER_STEP;
/// Least probability that the frames show a face seen by a camera rather than a head rendered
/// from a photo (the rendered-head detector, `render.bin`, fused over the frames as the passive
/// liveness is): even odds, the detector being trained on equal weights of both.
pub const RENDER_MIN: f32 = 0.5;

/// How long an issued challenge may be answered.
pub const DEFAULT_LIFETIME: Duration = Duration::from_secs(120);

/// The operator's challenge settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChallengeConfig {
    /// How long an issued challenge may be answered.
    pub lifetime: Duration,
}

impl Default for ChallengeConfig {
    fn default() -> ChallengeConfig {
        ChallengeConfig { lifetime: DEFAULT_LIFETIME }
    }
}

/// A challenge as issued to a client.
#[derive(Debug, Clone, PartialEq)]
pub struct IssuedChallenge {
    /// Opaque: 32 lowercase hex digits, 128 random bits.
    pub id: String,
    pub expires_in: Duration,
    pub steps: Vec<Step>,
}

/// Why a challenge cannot be answered: it never passes.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum InvalidChallenge {
    #[error("the challenge is unknown or was already used; ask for a new one (POST /liveness/challenge)")]
    Unknown,
    #[error("the challenge expired {0} s ago; ask for a new one (POST /liveness/challenge)")]
    Expired(i64),
    #[error("liveness is off on this server: it issues and judges no challenges")]
    LivenessOff,
    /// A `/verify` without a challenge where the server requires one
    /// ([`crate::ServiceConfig::require_challenge`]).
    #[error(
        "this server requires a head-turn challenge on /verify: ask for one (POST /liveness/challenge) and send its id as `challenge` with the frames of its steps"
    )]
    Required,
}

/// The verdict on a capture answering a challenge.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ChallengeOutcome {
    pub passed: bool,
    /// Why it failed (the first check that failed); `None` when it passed.
    pub reason: Option<String>,
    pub steps: Vec<StepReading>,
    /// The plane against the head over the capture's frames ([`head_turn::depth_test`]).
    pub depth: Option<DepthTest>,
    /// The frames' fused probability of a camera's view rather than a rendered head; `None`
    /// without the detector.
    pub rendered: Option<f32>,
}

/// A frame that does not show the probe's person at [`CAPTURE_FMR`]: which (0-based among the
/// frames), against what, and the score.
#[derive(Debug, Clone, PartialEq)]
pub struct Mismatch {
    pub frame: usize,
    /// "the probe", or "step N's frames".
    pub against: String,
    pub score: f32,
    pub threshold: f32,
}

/// 3 or 4 steps, each turn drawn among the two that differ from the step before, until the
/// sequence holds a turn to each side.
pub fn draw_steps(rng: &mut impl Rng) -> Vec<Step> {
    loop {
        let n = rng.random_range(3..=4);
        let mut turns: Vec<Turn> = Vec::with_capacity(n);
        for _ in 0..n {
            let choices: Vec<Turn> = [Turn::Front, Turn::Left, Turn::Right].into_iter().filter(|t| turns.last() != Some(t)).collect();
            turns.push(*choices.choose(rng).expect("two turns to choose from"));
        }
        if turns.contains(&Turn::Left) && turns.contains(&Turn::Right) {
            return turns.into_iter().map(Step::of).collect();
        }
    }
}

/// A new challenge id: 128 bits from the thread's CSPRNG, as 32 lowercase hex digits.
pub fn new_challenge_id(rng: &mut impl Rng) -> String {
    let bytes: [u8; 16] = rng.random();
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Could `id` be one of ours? Anything else is refused before the store is asked.
pub fn well_formed_id(id: &str) -> bool {
    id.len() == 32 && id.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f'))
}

/// Which step each frame answers: `given` (`frame_steps`: one 0-based step per frame,
/// non-decreasing, every step answered, at most [`MAX_FRAMES_PER_STEP`] frames a step) or, without
/// it, one frame per step in order. The frames' indices grouped by step.
pub fn frame_steps_of(steps: usize, frames: usize, given: Option<&[usize]>) -> Result<Vec<Vec<usize>>, String> {
    let Some(given) = given else {
        if frames != steps {
            return Err(format!(
                "the challenge has {steps} steps: send {steps} frames (field frame, or frames in JSON) in step order, or bursts with frame_steps, got {frames}"
            ));
        }
        return Ok((0..steps).map(|i| vec![i]).collect());
    };
    if given.len() != frames {
        return Err(format!("frame_steps names {} frames, but {frames} were sent: one step per frame", given.len()));
    }
    if given.windows(2).any(|w| w[1] < w[0]) {
        return Err("frame_steps must not decrease: the frames of each step in turn, in step order".into());
    }
    let mut bursts = vec![Vec::new(); steps];
    for (frame, &step) in given.iter().enumerate() {
        let burst =
            bursts.get_mut(step).ok_or_else(|| format!("frame_steps names step {step}, but the challenge has steps 0 to {}", steps - 1))?;
        burst.push(frame);
    }
    if let Some(step) = bursts.iter().position(Vec::is_empty) {
        return Err(format!("step {step} has no frame: every step needs at least one"));
    }
    if let Some(step) = bursts.iter().position(|b| b.len() > MAX_FRAMES_PER_STEP) {
        return Err(format!("step {step} has {} frames: at most {MAX_FRAMES_PER_STEP} a step", bursts[step].len()));
    }
    Ok(bursts)
}

/// One capture, one person: every frame against the probe, then against the frames of every
/// other step (its best score there), at the operating point [`CAPTURE_FMR`] for that many
/// templates. The first frame that fails, if any.
pub fn one_person(matcher: &dyn Matcher, probe: &Template, frames: &[&Template], bursts: &[Vec<usize>]) -> Option<Mismatch> {
    let by_step: Vec<Vec<Template>> = bursts.iter().map(|b| b.iter().map(|&j| frames[j].clone()).collect()).collect();
    for (own, burst) in bursts.iter().enumerate() {
        for &i in burst {
            let d = crate::decide(matcher, frames[i], std::slice::from_ref(probe), CAPTURE_FMR);
            if !d.is_match {
                return Some(Mismatch { frame: i, against: "the probe".into(), score: d.score, threshold: d.threshold });
            }
            for (step, others) in by_step.iter().enumerate().filter(|(step, _)| *step != own) {
                let d = crate::decide(matcher, frames[i], others, CAPTURE_FMR);
                if !d.is_match {
                    return Some(Mismatch {
                        frame: i,
                        against: format!("step {}'s frames", step + 1),
                        score: d.score,
                        threshold: d.threshold,
                    });
                }
            }
        }
    }
    None
}

/// The verdict on `bursts` (each step's frames, in order) answering `steps`, with `mismatch` the
/// first frame that does not show the probe's person ([`one_person`]) and `rendered` the frames'
/// rendered-head checks (`None` without the detector).
pub fn judge(
    steps: &[Step],
    probe: &FaceAnalysis,
    bursts: &[Vec<&FaceAnalysis>],
    mismatch: Option<&Mismatch>,
    rendered: Option<&[Liveness]>,
) -> ChallengeOutcome {
    let poses: Vec<Vec<FramePose>> = bursts.iter().map(|b| b.iter().map(|a| frame_pose(a)).collect()).collect();
    let HeadTurn { steps: readings, depth } = head_turn::read_head_turn(steps, frame_pose(probe), &poses);
    let narrowed = readings
        .iter()
        .enumerate()
        .filter(|(_, r)| r.turn != Turn::Front)
        .find(|(_, r)| r.excess_turn().is_some_and(|e| e > MAX_EXCESS_TURN));
    let render = rendered.and_then(crate::fuse_liveness);
    let reason = if let Some((i, r)) = readings.iter().enumerate().find(|(_, r)| !r.ok) {
        let step = &steps[i];
        Some(match r.yaw {
            Some(yaw) => format!(
                "step {} ({}): the head's yaw {yaw:.1}° is outside {:.0}° to {:.0}°",
                i + 1,
                step.turn.name(),
                step.yaw_min,
                step.yaw_max
            ),
            None => format!("step {} ({}): the head's pose could not be read", i + 1, step.turn.name()),
        })
    } else if let Some((i, r)) = narrowed {
        Some(format!(
            "step {} ({}): the face narrowed as if turned {:.0}° further than its yaw {:.1}° (a picture turned in front of the camera), over {MAX_EXCESS_TURN:.0}°",
            i + 1,
            r.turn.name(),
            r.excess_turn().unwrap_or(0.0),
            r.yaw.unwrap_or(0.0)
        ))
    } else if let Some(m) = mismatch {
        Some(format!(
            "frame {} shows another person than {}: score {:.3} below the threshold {:.3}",
            m.frame + 1,
            m.against,
            m.score,
            m.threshold
        ))
    } else {
        match depth {
            Some(_) if render.as_ref().is_some_and(|r| r.score < RENDER_MIN) => Some(format!(
                "the frames look like a head rendered from a photo, not a camera's view of one: {:.3} below {RENDER_MIN:.2} ({})",
                render.as_ref().map_or(0.0, |r| r.score),
                render.as_ref().map_or("", |r| r.model.as_str())
            )),
            Some(d) if d.shift >= SHIFT_MIN && d.z(NOISE_FLOOR) >= Z_MIN => None,
            Some(d) => Some(format!(
                "the turns show no head's depth (a picture moved in front of the camera): the nose crossed the face by {:.3} eye distances a turn ({:.1} standard errors), under {SHIFT_MIN:.2} or {Z_MIN:.0}",
                d.shift,
                d.z(NOISE_FLOOR)
            )),
            None => Some("no turned frame could be measured (no key points)".to_string()),
        }
    };
    ChallengeOutcome { passed: reason.is_none(), reason, steps: readings, depth, rendered: render.map(|r| r.score) }
}

/// A frame's yaw is its key-point pose's ([`facegate_vision::pipeline::Pipeline::key_point_fit`]).
fn frame_pose(a: &FaceAnalysis) -> FramePose {
    FramePose { yaw: a.key_point_pose.map(|p| p.yaw), keypoints: a.face.points }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn every_draw_has_three_or_four_steps_a_turn_to_each_side_and_no_repeat() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut lengths = [0usize; 5];
        let mut sequences = std::collections::BTreeSet::new();
        for _ in 0..2000 {
            let steps = draw_steps(&mut rng);
            lengths[steps.len()] += 1;
            let turns: Vec<Turn> = steps.iter().map(|s| s.turn).collect();
            assert!(turns.contains(&Turn::Left) && turns.contains(&Turn::Right), "{turns:?}");
            assert!(turns.windows(2).all(|w| w[0] != w[1]), "{turns:?}");
            assert!(steps.iter().all(|s| (s.yaw_min, s.yaw_max) == s.turn.yaw_range()));
            sequences.insert(format!("{turns:?}"));
        }
        assert_eq!(lengths[0] + lengths[1] + lengths[2], 0);
        assert!(lengths[3] > 300 && lengths[4] > 300, "{lengths:?}");
        // Of the 12 three-step and 24 four-step sequences without a repeat, those without a left
        // (FRF, RFR; FRFR, RFRF) or without a right are never drawn; all 8 + 20 others are.
        assert_eq!(sequences.len(), 8 + 20, "{sequences:?}");
    }

    #[test]
    fn frame_steps_group_the_frames_by_step_and_refuse_what_is_ill_formed() {
        assert_eq!(frame_steps_of(3, 3, None).unwrap(), vec![vec![0], vec![1], vec![2]]);
        assert!(frame_steps_of(3, 4, None).unwrap_err().contains("has 3 steps"));
        assert_eq!(frame_steps_of(3, 6, Some(&[0, 0, 1, 2, 2, 2])).unwrap(), vec![vec![0, 1], vec![2], vec![3, 4, 5]]);
        for (given, frames, why) in [
            (&[0, 1][..], 3, "names 2 frames"),
            (&[1, 0, 2], 3, "must not decrease"),
            (&[0, 2, 2], 3, "step 1 has no frame"),
            (&[0, 1, 3], 3, "names step 3"),
            (&[0, 0, 0, 0, 0, 0, 1, 2], 8, "at most 5 a step"),
        ] {
            let err = frame_steps_of(3, frames, Some(given)).unwrap_err();
            assert!(err.contains(why), "{given:?}: {err}");
        }
        assert_eq!(MAX_CAPTURE_FRAMES, 20);
    }

    #[test]
    fn ids_are_128_random_bits_in_hex_and_nothing_else_is_taken_for_one() {
        let mut rng = rand::rng();
        let (a, b) = (new_challenge_id(&mut rng), new_challenge_id(&mut rng));
        assert!(well_formed_id(&a) && well_formed_id(&b) && a != b, "{a} {b}");
        for bad in ["", "0123", &a.to_uppercase(), &format!("{a}0"), "g0000000000000000000000000000000", "' OR 1=1 --"] {
            assert!(!well_formed_id(bad), "{bad:?}");
        }
    }

    #[test]
    fn a_capture_is_held_at_the_strictest_point_the_model_has() {
        /// Scores are 1 less the first coordinates' distance (the best enrolled); thresholds 0.80
        /// at 1e-4 and 0.85 at 1e-5 (when the model has it), the closest point answering, as a
        /// calibration's does.
        struct Points(bool);
        impl Matcher for Points {
            fn model_version(&self) -> &str {
                "m"
            }
            fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
                enrolled.iter().map(|t| 1.0 - (probe.vector[0] - t.vector[0]).abs()).fold(f32::NEG_INFINITY, f32::max)
            }
            fn operating_point(&self, fmr: f64, _: usize) -> facegate_core::template::OperatingPoint {
                use facegate_core::template::OperatingPoint;
                if self.0 && fmr < 3e-5 {
                    OperatingPoint { fmr: 1e-5, threshold: 0.85 }
                } else {
                    OperatingPoint { fmr: 1e-4, threshold: 0.80 }
                }
            }
        }
        let t = |x: f32| Template { model_version: "m".into(), vector: vec![x] };
        let (probe, same, like) = (t(1.0), t(0.99), t(0.82));
        let bursts = [vec![0], vec![1], vec![2]];
        // A frame at 0.82 against the probe (0.83 against the others): a match at 1e-4, not at 1e-5.
        let frames = [&like, &same, &same];
        let miss = one_person(&Points(true), &probe, &frames, &bursts).expect("held at 1e-5");
        assert_eq!((miss.frame, miss.against.as_str(), miss.threshold), (0, "the probe", 0.85));
        // A model calibrated down to 1e-4 only holds it at its 1e-4 point.
        assert_eq!(one_person(&Points(false), &probe, &frames, &bursts), None);
        assert_eq!(one_person(&Points(true), &probe, &[&same, &same, &same], &bursts), None);
    }
}
