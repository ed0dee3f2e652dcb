//! What the service does, without HTTP: subject ids parsed once ([`SubjectId`]), the face engine
//! behind it ([`FaceEngine`]), which photos can be enrolled ([`check_enrolment_photo`],
//! [`check_enrolment_quality`]), what
//! "verify" and "identify" mean ([`verify`], [`identify`]: which
//! templates count, the threshold for the subject's number of templates, the decision) and the
//! bounded work pool ([`WorkPool`]). The HTTP layer and the `compare` command both decide through
//! here.
//!
//! A template carries the version of the model that made it, and the decision only sees
//! [`Matcher`]: the score of a probe against a subject's templates and the calibrated operating
//! point. A second recognizer (another way of computing templates) plugs in by implementing
//! [`Matcher`]; templates of one model version are never compared with another's.

pub mod gallery;
pub mod inspect;
pub mod pool;

use serde::Serialize;

use crate::core::imaging::Photo;
use crate::morph::AvatarFormat;
use crate::pipeline::{FaceAnalysis, FaceChoice, PhotoReading, Pipeline, PipelineError};
use crate::quality::{Failure, Quality, QualityPolicy};
use crate::recognize::{AnyRecognizer, OperatingPoint, Recognizer, Template};

pub use pool::{Admission, PoolError, WorkClass, WorkPool};

/// Longest subject id accepted.
pub const MAX_SUBJECT_LEN: usize = 128;

/// A subject id: 1–128 characters of `[A-Za-z0-9._-]` (safe in URLs, logs and file names), except
/// `.` and `..`, which URL clients resolve as path segments so `/subjects/{id}` could not reach
/// them. Made only by [`SubjectId::parse`], so a value of this type is valid.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize)]
#[serde(transparent)]
pub struct SubjectId(String);

/// Why a string is not a [`SubjectId`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("subject id {shown:?} is invalid: 1 to {MAX_SUBJECT_LEN} characters from A-Z a-z 0-9 . _ -, not . or ..")]
pub struct InvalidSubjectId {
    /// The start of the refused id (40 characters at most).
    pub shown: String,
}

impl SubjectId {
    pub fn parse(id: &str) -> Result<SubjectId, InvalidSubjectId> {
        let ok_char = |c: char| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-');
        if id.is_empty() || id.len() > MAX_SUBJECT_LEN || !id.chars().all(ok_char) || id == "." || id == ".." {
            return Err(InvalidSubjectId { shown: id.chars().take(40).collect() });
        }
        Ok(SubjectId(id.to_string()))
    }

    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl std::fmt::Display for SubjectId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

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
}

/// The face work behind the service: the real [`Pipeline`] in production. A seam so that the HTTP
/// layer (decoding, limits, errors, storage) can be tested on its own.
pub trait FaceEngine: Matcher + Send + Sync + 'static {
    /// Detect, landmark, pose-correct and template the largest face of `photo`.
    fn analyze(&self, photo: &Photo) -> Result<FaceAnalysis, PipelineError>;
    /// Every face (or the largest) with landmarks, pose and fit residual; no template.
    fn read_faces(&self, photo: &Photo, choice: FaceChoice) -> Result<PhotoReading, PipelineError>;
    /// The textured 3D head of the largest face: glTF binary, or the OBJ files zipped.
    fn avatar(&self, photo: &Photo, format: AvatarFormat) -> Result<Vec<u8>, PipelineError>;
    /// The frontal rendering of the largest face, PNG.
    fn frontal_png(&self, photo: &Photo) -> Result<Vec<u8>, PipelineError>;
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
        // The deep recognizer's score is the best cosine (`DeepRecognizer::score`); the classical
        // one may S-normalise against a cohort and average, so it keeps its own `score`.
        matches!(self.recognizer, AnyRecognizer::Deep(_))
    }
}

impl FaceEngine for Pipeline {
    fn analyze(&self, photo: &Photo) -> Result<FaceAnalysis, PipelineError> {
        Pipeline::analyze(self, photo)
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
}

/// Why a photo cannot be enrolled.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum EnrolError {
    #[error("{0} faces were found; an enrolment photo must show exactly one face, since a template of the wrong person is costly")]
    SeveralFaces(usize),
}

/// An enrolment photo must show exactly one face (a probe may show several: the largest is used).
pub fn check_enrolment_photo(faces_found: usize) -> Result<(), EnrolError> {
    if faces_found > 1 { Err(EnrolError::SeveralFaces(faces_found)) } else { Ok(()) }
}

/// An enrolment photo must meet the quality policy: the limits it breaks, none when it passes.
pub fn check_enrolment_quality(policy: &QualityPolicy, quality: &Quality) -> Result<(), Vec<Failure>> {
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
    Decision::at(matcher, matcher.score(probe, comparable), comparable.len(), fmr)
}

impl Decision {
    /// `score` of a subject with `templates` templates, held against the threshold at `fmr` for
    /// that many templates: the one rule verify, identify and the gallery decide by.
    pub fn at(matcher: &dyn Matcher, score: f32, templates: usize, fmr: f64) -> Decision {
        let point = matcher.operating_point(fmr, templates);
        Decision { score, threshold: point.threshold, fmr: point.fmr, is_match: score >= point.threshold, templates_compared: templates }
    }
}

/// Verification of a probe against a subject's enrolled templates: [`comparable_templates`], then
/// [`decide`].
pub fn verify(
    matcher: &dyn Matcher,
    subject: &SubjectId,
    probe: &Template,
    enrolled: Vec<Template>,
    fmr: f64,
) -> Result<Decision, VerifyError> {
    let comparable = comparable_templates(matcher, subject, enrolled)?;
    Ok(decide(matcher, probe, &comparable, fmr))
}

/// One candidate of an identification: a subject and its decision.
#[derive(Debug, Clone, PartialEq)]
pub struct Candidate {
    pub subject: String,
    pub decision: Decision,
}

/// The best `k` subjects of `gallery` (subjects with their templates of the current model version)
/// for `probe`, best first, each decided at the threshold for its number of templates.
pub fn identify(matcher: &dyn Matcher, probe: &Template, gallery: Vec<(String, Vec<Template>)>, fmr: f64, k: usize) -> Vec<Candidate> {
    let mut scored: Vec<(String, f32, usize)> =
        gallery.into_iter().map(|(subject, templates)| (subject, matcher.score(probe, &templates), templates.len())).collect();
    scored.sort_by(|a, b| b.1.total_cmp(&a.1));
    scored.truncate(k);
    scored
        .into_iter()
        .map(|(subject, score, templates)| Candidate { subject, decision: Decision::at(matcher, score, templates, fmr) })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn subject_ids_are_checked_once() {
        for ok in ["a", "alice", "A-1_b.c", &"x".repeat(MAX_SUBJECT_LEN)] {
            assert_eq!(SubjectId::parse(ok).unwrap().as_str(), ok);
        }
        for bad in ["", "a b", "ä", "a/b", "../x", &"x".repeat(MAX_SUBJECT_LEN + 1)] {
            assert!(SubjectId::parse(bad).is_err(), "{bad}");
        }
    }

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
        let d = verify(&Stub, &subject, &probe, vec![t("v1", 0.55), t("v0", 0.99)], 1e-3).unwrap();
        assert_eq!((d.score, d.threshold, d.is_match, d.templates_compared), (0.55, 0.5, true, 1));
        let d = verify(&Stub, &subject, &probe, vec![t("v1", 0.55), t("v1", 0.45)], 1e-3).unwrap();
        assert_eq!((d.threshold, d.is_match, d.templates_compared), (0.6, false, 2));
        assert!(matches!(verify(&Stub, &subject, &probe, vec![t("v0", 0.9)], 1e-3), Err(VerifyError::ModelMismatch { .. })));
        let gallery =
            vec![("a".into(), vec![t("v1", 0.3)]), ("b".into(), vec![t("v1", 0.65), t("v1", 0.1)]), ("c".into(), vec![t("v1", 0.52)])];
        let found = identify(&Stub, &probe, gallery, 1e-3, 2);
        let summary: Vec<_> = found.iter().map(|c| (c.subject.as_str(), c.decision.is_match, c.decision.threshold)).collect();
        assert_eq!(summary, [("b", true, 0.6), ("c", true, 0.5)]);
    }
}
