//! The service's side of the head-turn challenge ([`crate::challenge`] holds its rules):
//! [`Facegate::issue_challenge`] keeps a drawn challenge in the store for
//! [`ChallengeConfig::lifetime`](crate::challenge::ChallengeConfig::lifetime);
//! [`Facegate::verify_challenge`] takes it out of the store (once, on any replica), analyzes the
//! probe and each step's burst of frames, and [`judge`]s the capture. The passive score of every
//! frame is fused as for any capture ([`crate::fuse_liveness`]) and held as
//! [`crate::liveness::check_challenged_liveness`] says: the capture is an attack when the
//! challenge fails, or when the fused score falls below a threshold set for this deployment.

use std::time::{SystemTime, UNIX_EPOCH};

use bytes::Bytes;

use facegate_core::SubjectId;
use facegate_core::template::Template;
use facegate_vision::liveness::Liveness;
use facegate_vision::liveness::head_turn::Step;
use facegate_vision::pipeline::{FaceAnalysis, FollowedFace};

use super::{AnalyzedPhoto, Facegate, PhotoError, ServiceError, Verification, capture_liveness, decode_and_analyze};
use crate::challenge::{
    CAPTURE_FMR, ChallengeOutcome, InvalidChallenge, IssuedChallenge, draw_steps, frame_steps_of, judge, new_challenge_id, one_person,
    well_formed_id,
};
use crate::liveness::LivenessPolicy;
use crate::{FaceEngine, Matcher};

fn unix_ms(at: SystemTime) -> i64 {
    at.duration_since(UNIX_EPOCH).map_or(0, |d| d.as_millis() as i64)
}

impl Facegate {
    /// Draw a challenge and keep it in the store until it is answered or expires; refused with
    /// [`ServiceError::TooManyChallenges`] while [`crate::ServiceConfig::max_open_challenges`] are open.
    pub async fn issue_challenge(&self) -> Result<IssuedChallenge, ServiceError> {
        if self.config().liveness == LivenessPolicy::Off {
            return Err(ServiceError::InvalidChallenge(InvalidChallenge::LivenessOff));
        }
        let (id, steps) = {
            let mut rng = rand::rng();
            (new_challenge_id(&mut rng), draw_steps(&mut rng))
        };
        let lifetime = self.config().challenge.lifetime;
        let now = SystemTime::now();
        let text = serde_json::to_string(&steps).expect("steps serialise");
        let (expires, now_ms) = (unix_ms(now + lifetime), unix_ms(now));
        let open = self.config().max_open_challenges;
        if !self.with_store(self.store().insert_challenge_within(&id, &text, expires, now_ms, open)).await? {
            // Room comes back when the first open challenge expires (or sooner, when one is taken).
            let first = self.with_store(self.store().next_challenge_expiry(now_ms)).await?;
            let wait_ms = first.map_or(1000, |at| (at - now_ms).clamp(1000, (expires - now_ms).max(1000)));
            let retry_after = std::time::Duration::from_secs((wait_ms as u64).div_ceil(1000));
            return Err(ServiceError::TooManyChallenges { open, retry_after });
        }
        Ok(IssuedChallenge { id, expires_in: lifetime, steps })
    }

    /// [`Facegate::verify_capture`] answering the challenge `challenge`: the challenge is taken
    /// from the store first (used once, whatever the outcome), then the probe and each step's
    /// frames (`frame_steps`, or one frame per step) are analyzed, the probe matched against the
    /// subject and the capture [`judge`]d. The liveness of the verification is the capture's
    /// fused passive score, an attack when the challenge fails or the score is below a threshold
    /// set for this deployment ([`crate::liveness::check_challenged_liveness`]); under `enforce`
    /// a failed challenge is refused with its reason.
    pub async fn verify_challenge(
        &self,
        subject: &SubjectId,
        image: Bytes,
        frames: Vec<Bytes>,
        frame_steps: Option<Vec<usize>>,
        challenge: &str,
        fmr: Option<f64>,
    ) -> Result<Verification, ServiceError> {
        let policy = self.config().liveness;
        if policy == LivenessPolicy::Off {
            return Err(ServiceError::InvalidChallenge(InvalidChallenge::LivenessOff));
        }
        let fmr = self.fmr(fmr);
        let (matcher, comparable) = self.comparable_of(subject).await?;
        let steps = self.take_challenge(challenge).await?;
        let bursts = frame_steps_of(steps.len(), frames.len(), frame_steps.as_deref())
            .map_err(|why| ServiceError::Invalid(format!("{why}; the challenge is used up, ask for a new one")))?;
        let (limits, scoring) = (self.config().decode_limits, matcher.clone());
        let (mut probe, analyzed, outcome) =
            self.pool().run(move || challenge_photos(&scoring, &steps, &bursts, &image, &frames, &limits)).await??;
        if policy == LivenessPolicy::Enforce && !outcome.passed {
            return Err(PhotoError::ChallengeFailed(outcome).into());
        }
        let point = self.liveness_point();
        let each = capture_liveness(&probe, &analyzed);
        let (fused, frame_scores) = crate::liveness::check_challenged_liveness(policy, point.as_deref(), each, outcome.passed)?;
        probe.liveness = fused;
        Ok(Verification {
            frames: analyzed,
            frame_scores,
            challenge: Some(outcome),
            ..Verification::of_probe(&matcher, &comparable, fmr, probe)
        })
    }

    /// The steps of the challenge `id`, taken out of the store: unknown, used and expired
    /// challenges are refused.
    async fn take_challenge(&self, id: &str) -> Result<Vec<Step>, ServiceError> {
        if !well_formed_id(id) {
            return Err(ServiceError::InvalidChallenge(InvalidChallenge::Unknown));
        }
        let taken = self.with_store(self.store().take_challenge(id)).await?;
        let taken = taken.ok_or(ServiceError::InvalidChallenge(InvalidChallenge::Unknown))?;
        let late_ms = unix_ms(SystemTime::now()) - taken.expires_at_ms;
        if late_ms > 0 {
            return Err(ServiceError::InvalidChallenge(InvalidChallenge::Expired((late_ms + 999) / 1000)));
        }
        serde_json::from_str(&taken.steps).map_err(|_| ServiceError::InvalidChallenge(InvalidChallenge::Unknown))
    }
}

/// Analyze a challenge's probe and frames (a frame with no usable face is refused with its
/// index), hold every frame against the probe and the other steps ([`one_person`]) and judge
/// the capture. The probe's face is its largest; each frame's is its largest too unless that is
/// not the probe's person and the face followed from the frame before (from the probe for the
/// first: [`FollowedFace::pick`]) is, so that a larger face beside the person is not judged as
/// theirs ([`analyze_frame`]).
fn challenge_photos(
    matcher: &crate::site::CalibratedMatcher<dyn FaceEngine>,
    steps: &[Step],
    bursts: &[Vec<usize>],
    image: &[u8],
    frames: &[Bytes],
    limits: &facegate_core::imaging::DecodeLimits,
) -> Result<(AnalyzedPhoto, Vec<AnalyzedPhoto>, ChallengeOutcome), ServiceError> {
    let engine = matcher.inner.as_ref();
    let (photo, probe) = decode_and_analyze(engine, image, limits)?;
    let mut last = FollowedFace::of(&probe.analysis.face.rect, photo.width(), photo.height());
    drop(photo);
    let (mut analyzed, mut rendered) = (Vec::with_capacity(frames.len()), Vec::with_capacity(frames.len()));
    for (i, bytes) in frames.iter().enumerate() {
        let (frame, render, followed) =
            analyze_frame(engine, matcher, &probe.analysis.template, bytes, limits, &last).map_err(|e| e.at_frame(i))?;
        analyzed.push(frame);
        rendered.push(render);
        last = followed;
    }
    let outcome = tracing::info_span!("challenge").in_scope(|| {
        let templates: Vec<&Template> = analyzed.iter().map(|p| &p.analysis.template).collect();
        let mismatch = one_person(matcher as &dyn Matcher, &probe.analysis.template, &templates, bursts);
        let by_step: Vec<Vec<&FaceAnalysis>> = bursts.iter().map(|b| b.iter().map(|&i| &analyzed[i].analysis).collect()).collect();
        let rendered: Option<Vec<Liveness>> = rendered.into_iter().collect();
        judge(steps, &probe.analysis, &by_step, mismatch.as_ref(), rendered.as_deref())
    });
    Ok((probe, analyzed, outcome))
}

/// A challenge frame analyzed at the person's face, checked for a rendered head, and where its
/// face is for the next frame. The person's face is the largest, as in any photo, unless the
/// frame shows several faces, the largest is not the `probe`'s person (at [`CAPTURE_FMR`]) and
/// the face followed from `last` is: a bystander larger than the person. Position alone would not
/// do: a person who moves further than a face width between two frames sent (a camera that cut,
/// a clip replayed mirrored) leaves another face where theirs was. Either face judged must pass
/// every check of the challenge itself, so the choice gives an attacker nothing a single face
/// would not.
fn analyze_frame(
    engine: &dyn FaceEngine,
    matcher: &dyn Matcher,
    probe: &Template,
    bytes: &[u8],
    limits: &facegate_core::imaging::DecodeLimits,
    last: &FollowedFace,
) -> Result<(AnalyzedPhoto, Option<Liveness>, FollowedFace), PhotoError> {
    let (photo, decode_ms) = crate::inspect::decode_photo(bytes, limits)?;
    let probes_person = |a: &FaceAnalysis| crate::decide(matcher, &a.template, std::slice::from_ref(probe), CAPTURE_FMR).is_match;
    let mut analysis = engine.analyze(&photo).map_err(PhotoError::of_analysis)?;
    if analysis.faces_found > 1 && !probes_person(&analysis) {
        if let Some(followed) =
            engine.analyze_following(&photo, last).ok().filter(|f| f.face.rect != analysis.face.rect && probes_person(f))
        {
            analysis = followed;
        }
    }
    let rendered = engine.render_check(&photo, &analysis);
    let followed = FollowedFace::of(&analysis.face.rect, photo.width(), photo.height());
    Ok((AnalyzedPhoto { analysis, decode_ms, liveness: None }, rendered, followed))
}
