//! What the service does, without HTTP: the use cases ([`Facegate`]: enroll, verify, identify,
//! delete, analyze, avatar, frontalize), the face engine behind them ([`FaceEngine`]), which photos
//! can be enrolled ([`check_enrollment_photo`], [`check_enrollment_quality`]), which faces are let
//! through as live ([`liveness`]: the policy, the threshold in force, [`check_liveness`]), what a decision is
//! ([`comparable_templates`], [`decide`]: which templates count, the threshold for the subject's
//! number of templates), the identification gallery ([`gallery`]) and the bounded work pool
//! ([`WorkPool`]). The HTTP layer and the command line both go through here.
//!
//! A template carries the version of the model that made it, and the decision only sees
//! [`Matcher`]: the score of a probe against a subject's templates and the calibrated operating
//! point. A second recognizer (another way of computing templates) plugs in by implementing
//! [`Matcher`]; templates of one model version are never compared with another's.

pub mod challenge;
mod facegate;
pub mod gallery;
pub mod inspect;
pub mod liveness;
pub mod liveness_camera;
pub mod pool;
pub mod protection;
pub mod site;

use serde::Serialize;

use facegate_core::imaging::Photo;
use facegate_core::template::{OperatingPoint, Template};
use facegate_morph::AvatarFormat;
use facegate_vision::pipeline::{FaceAnalysis, FaceChoice, FollowedFace, PhotoReading, Pipeline, PipelineError};
use facegate_vision::quality::{Failure, Quality, QualityPolicy};
use facegate_vision::recognize::{ClassicalRecognizer, Recognizer};

pub use challenge::{ChallengeConfig, ChallengeOutcome, InvalidChallenge, IssuedChallenge, MAX_CAPTURE_FRAMES, MAX_FRAMES_PER_STEP};
pub use facegate::{
    AnalyzedPhoto, Enrollment, Facegate, FramesMismatch, Health, Identification, PhotoError, PreparedEnrollment, ServiceConfig,
    ServiceError, Verification, analyze_photo,
};
use facegate_core::SubjectId;
pub use liveness::{LivenessPoint, LivenessPolicy, LivenessVerdict, PresentationAttack, ThresholdSource, check_liveness, fuse_liveness};
pub use pool::{Admission, PoolError, WorkClass, WorkPool};

/// How templates are compared: what the verify and identify decisions need of a recognizer.
pub trait Matcher {
    /// The model version stamped on every template this recognizer makes.
    fn model_version(&self) -> &str;
    /// Score of a probe against one subject's templates (higher is more alike).
    fn score(&self, probe: &Template, enrolled: &[Template]) -> f32;
    /// The calibrated operating point closest to `fmr` for a subject with `enrolled` templates
    /// (its score is the best of them, so the threshold depends on how many there are).
    fn operating_point(&self, fmr: f64, enrolled: usize) -> OperatingPoint;
    /// Is [`Matcher::score`] the best cosine of the probe with the enrolled templates? Then the
    /// gallery scores from its matrix ([`gallery::Gallery::search`]); otherwise it calls `score`.
    fn max_cosine_scoring(&self) -> bool {
        false
    }
}

impl Matcher for ClassicalRecognizer {
    fn model_version(&self) -> &str {
        ClassicalRecognizer::model_version(self)
    }
    fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
        ClassicalRecognizer::score(self, probe, enrolled)
    }
    fn operating_point(&self, fmr: f64, enrolled: usize) -> OperatingPoint {
        ClassicalRecognizer::operating_point(self, fmr, enrolled)
    }
}

/// The face work behind the service: the real [`Pipeline`] in production. A seam so that the HTTP
/// layer (decoding, limits, errors, storage) can be tested on its own.
pub trait FaceEngine: Matcher + Send + Sync + 'static {
    /// Detect, landmark, pose-correct and template the largest face of `photo`.
    fn analyze(&self, photo: &Photo) -> Result<FaceAnalysis, PipelineError>;
    /// [`FaceEngine::analyze`] of the face followed from the last frame of a capture
    /// ([`FollowedFace::pick`]; `NoFace` when none lies there): a challenge's frames, so that a
    /// larger face beside the person's is not taken for theirs.
    fn analyze_following(&self, photo: &Photo, last: &FollowedFace) -> Result<FaceAnalysis, PipelineError>;
    /// Every face (or the largest) with landmarks, pose and fit residual; no template.
    fn read_faces(&self, photo: &Photo, choice: FaceChoice) -> Result<PhotoReading, PipelineError>;
    /// The textured 3D head of the largest face: glTF binary, or the OBJ files zipped.
    fn avatar(&self, photo: &Photo, format: AvatarFormat) -> Result<Vec<u8>, PipelineError>;
    /// The frontal rendering of the largest face, PNG.
    fn frontal_png(&self, photo: &Photo) -> Result<Vec<u8>, PipelineError>;
    /// The operating point the liveness model behind the analyses' `liveness` was trained at:
    /// where the service's threshold starts (the composition root may replace it by a camera's
    /// or the operator's). `None` when no liveness model is loaded (then no analysis carries one).
    fn liveness_model_point(&self) -> Option<LivenessPoint>;
    /// A face seen by a camera or a head rendered from a photo: the probability of the former
    /// (`render.bin`); `None` without the model. Only a challenge's frames are checked.
    fn render_check(&self, _photo: &Photo, _analysis: &FaceAnalysis) -> Option<facegate_vision::liveness::Liveness> {
        None
    }
}

impl Matcher for Pipeline {
    fn model_version(&self) -> &str {
        self.recognizer.model_version()
    }
    fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
        self.recognizer.score(probe, enrolled)
    }
    fn operating_point(&self, fmr: f64, enrolled: usize) -> OperatingPoint {
        self.recognizer.operating_point(fmr, enrolled)
    }
    fn max_cosine_scoring(&self) -> bool {
        Matcher::max_cosine_scoring(&self.recognizer)
    }
}

impl Matcher for Recognizer {
    fn model_version(&self) -> &str {
        Recognizer::model_version(self)
    }
    fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
        Recognizer::score(self, probe, enrolled)
    }
    fn operating_point(&self, fmr: f64, enrolled: usize) -> OperatingPoint {
        Recognizer::operating_point(self, fmr, enrolled)
    }
    fn max_cosine_scoring(&self) -> bool {
        // The deep recognizers' score is the best cosine (`DlibRecognizer::score`); the classical
        // one may S-normalise against a cohort and average, so it keeps its own `score`.
        matches!(self, Recognizer::Dlib(_) | Recognizer::Embedding(..))
    }
}

impl FaceEngine for Pipeline {
    fn analyze(&self, photo: &Photo) -> Result<FaceAnalysis, PipelineError> {
        Pipeline::analyze(self, photo)
    }
    fn analyze_following(&self, photo: &Photo, last: &FollowedFace) -> Result<FaceAnalysis, PipelineError> {
        Pipeline::analyze_following(self, photo, last)
    }
    fn read_faces(&self, photo: &Photo, choice: FaceChoice) -> Result<PhotoReading, PipelineError> {
        Pipeline::read_faces(self, photo, choice)
    }
    fn avatar(&self, photo: &Photo, format: AvatarFormat) -> Result<Vec<u8>, PipelineError> {
        Pipeline::avatar(self, photo, format)
    }
    fn frontal_png(&self, photo: &Photo) -> Result<Vec<u8>, PipelineError> {
        Pipeline::frontal_png(self, photo)
    }
    fn liveness_model_point(&self) -> Option<LivenessPoint> {
        self.liveness.as_ref().map(LivenessPoint::of_model)
    }
    fn render_check(&self, photo: &Photo, analysis: &FaceAnalysis) -> Option<facegate_vision::liveness::Liveness> {
        Pipeline::render_check(self, photo, analysis)
    }
}

/// An enrolment photo must show exactly one face (a probe may show several: the largest is used).
pub fn check_enrollment_photo(faces_found: usize) -> Result<(), PhotoError> {
    if faces_found > 1 { Err(PhotoError::SeveralFaces(faces_found)) } else { Ok(()) }
}

/// An enrolment photo must meet the quality policy: the limits it breaks, none when it passes.
pub fn check_enrollment_quality(policy: &QualityPolicy, quality: &Quality) -> Result<(), Vec<Failure>> {
    let failures = policy.failures(quality);
    if failures.is_empty() { Ok(()) } else { Err(failures) }
}

/// A match decision: the score, the threshold it was held against, and the outcome.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Decision {
    pub score: f32,
    pub threshold: f32,
    /// The calibrated false match rate of the threshold.
    pub fmr: f64,
    #[serde(rename = "match")]
    pub is_match: bool,
    /// The subject's templates compared (those of the current model version).
    pub templates_compared: usize,
    /// Which of them (0-based, in enrolment order) made the score, when the decision compared
    /// templates one by one (verify); `None` for a gallery's decisions.
    pub best_template: Option<usize>,
}

/// Why a subject cannot be verified.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum VerifyError {
    #[error("subject {subject} has no template of the current model version {model_version}; enrol the subject again")]
    ModelMismatch { subject: String, model_version: String },
}

/// The subject's templates that can be compared with the current model's probes: those of its
/// version. None is a [`VerifyError::ModelMismatch`] (the subject was enrolled under another model).
pub fn comparable_templates(matcher: &dyn Matcher, subject: &SubjectId, enrolled: Vec<Template>) -> Result<Vec<Template>, VerifyError> {
    let version = matcher.model_version();
    let comparable: Vec<Template> = enrolled.into_iter().filter(|t| t.model_version == version).collect();
    if comparable.is_empty() {
        return Err(VerifyError::ModelMismatch { subject: subject.to_string(), model_version: version.to_string() });
    }
    Ok(comparable)
}

/// Is `probe` the subject of the `comparable` templates (see [`comparable_templates`])? The score is
/// held against the threshold at `fmr` for a subject with that many templates.
pub fn decide(matcher: &dyn Matcher, probe: &Template, comparable: &[Template], fmr: f64) -> Decision {
    // Each template scored once (a comparison in `max_by` would score both sides every time).
    let per_template: Vec<f32> = comparable.iter().map(|t| matcher.score(probe, std::slice::from_ref(t))).collect();
    let best = per_template.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).map(|(i, _)| i);
    Decision { best_template: best, ..Decision::at(matcher, matcher.score(probe, comparable), comparable.len(), fmr) }
}

impl Decision {
    /// `score` of a subject with `templates` templates, held against the threshold at `fmr` for
    /// that many templates: the one rule verify, identify and the gallery decide by.
    pub fn at(matcher: &dyn Matcher, score: f32, templates: usize, fmr: f64) -> Decision {
        let point = matcher.operating_point(fmr, templates);
        Decision {
            score,
            threshold: point.threshold,
            fmr: point.fmr,
            is_match: score >= point.threshold,
            templates_compared: templates,
            best_template: None,
        }
    }
}

/// One candidate of an identification: a subject and its decision.
#[derive(Debug, Clone, PartialEq)]
pub struct Candidate {
    pub subject: String,
    pub decision: Decision,
}

/// Why two photos could not be compared: which photo (0 the probe, 1 the enrolled) and why.
#[derive(Debug, thiserror::Error)]
#[error("photo {photo}: {source}")]
pub struct CompareError {
    pub photo: usize,
    pub source: PipelineError,
}

/// Is the largest face of `probe` the person of `enrolled`, held as a subject enrolled with that
/// one photo? The service's own analysis and decision, without a store (`facegate compare`).
pub fn compare(engine: &dyn FaceEngine, probe: &Photo, enrolled: &Photo, fmr: f64) -> Result<Decision, CompareError> {
    let template = |photo: usize, p: &Photo| engine.analyze(p).map(|a| a.template).map_err(|source| CompareError { photo, source });
    let (probe, enrolled) = (template(0, probe)?, template(1, enrolled)?);
    Ok(decide(engine, &probe, std::slice::from_ref(&enrolled), fmr))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Scores are the first vector component of the best template; thresholds rise with the number
    /// of templates.
    struct Stub;

    impl Matcher for Stub {
        fn model_version(&self) -> &str {
            "v1"
        }
        fn score(&self, _probe: &Template, enrolled: &[Template]) -> f32 {
            enrolled.iter().map(|t| t.vector[0]).fold(-1.0, f32::max)
        }
        fn operating_point(&self, fmr: f64, enrolled: usize) -> OperatingPoint {
            OperatingPoint { fmr, threshold: 0.4 + 0.1 * enrolled as f32 }
        }
    }

    #[test]
    fn verify_compares_current_templates_at_the_threshold_for_their_count() {
        let subject = SubjectId::parse("s").unwrap();
        let t = |version: &str, score: f32| Template { model_version: version.into(), vector: vec![score, 0.0] };
        let probe = t("v1", 1.0);
        let verify = |enrolled| comparable_templates(&Stub, &subject, enrolled).map(|c| decide(&Stub, &probe, &c, 1e-3));
        let d = verify(vec![t("v1", 0.55), t("v0", 0.99)]).unwrap();
        assert_eq!((d.score, d.threshold, d.is_match, d.templates_compared), (0.55, 0.5, true, 1));
        let d = verify(vec![t("v1", 0.55), t("v1", 0.45)]).unwrap();
        assert_eq!((d.threshold, d.is_match, d.templates_compared), (0.6, false, 2));
        assert!(matches!(verify(vec![t("v0", 0.9)]), Err(VerifyError::ModelMismatch { .. })));
    }
}
