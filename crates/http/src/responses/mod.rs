//! The API's JSON bodies, owned by the HTTP layer and described by `openapi.yaml`. Each is made
//! from the service's result by a constructor or `From`, field by field: the domain types (the
//! stages', the store's, the service's) are never serialised as they are, so a change inside a
//! stage or the store does not change the API.

mod face;

use serde::Serialize;

use facegate_core::SubjectId;
use facegate_service::{Enrollment, Identification, IssuedChallenge, Verification};
use facegate_store::{Backend, SealingCounts, Store};

pub(crate) use face::QualityFailure;
use face::{AnalyzedFace, FaceReport, PhotoTimings};

#[derive(Debug, Serialize)]
struct ImageReport {
    index: usize,
    #[serde(flatten)]
    found: FaceReport,
    timings: PhotoTimings,
}

/// `POST /enroll`'s answer.
#[derive(Debug, Serialize)]
pub(crate) struct EnrollResponse {
    subject: String,
    /// Templates the subject has now (all model versions).
    templates: u32,
    /// Templates added by this request (one per photo).
    added: usize,
    model_version: String,
    images: Vec<ImageReport>,
}

impl EnrollResponse {
    pub(crate) fn new(subject: &SubjectId, enrollment: &Enrollment, model_version: &str) -> EnrollResponse {
        EnrollResponse {
            subject: subject.to_string(),
            templates: enrollment.templates,
            added: enrollment.photos.len(),
            model_version: model_version.to_string(),
            images: enrollment
                .photos
                .iter()
                .enumerate()
                .map(|(index, photo)| ImageReport { index, found: FaceReport::of(photo), timings: PhotoTimings::of(photo) })
                .collect(),
        }
    }
}

#[derive(Debug, Serialize)]
struct RequestTimings {
    #[serde(flatten)]
    photo: PhotoTimings,
    match_ms: f64,
    total_ms: f64,
}

/// `POST /verify`'s answer.
#[derive(Debug, Serialize)]
pub(crate) struct VerifyResponse {
    subject: String,
    #[serde(rename = "match")]
    is_match: bool,
    score: f32,
    threshold: f32,
    fmr: f64,
    model_version: String,
    /// The subject's templates compared (those of the current model version).
    templates_compared: usize,
    /// Which of them (0-based, in enrolment order) made the score.
    best_template: Option<usize>,
    #[serde(flatten)]
    found: FaceReport,
    timings: RequestTimings,
}

impl VerifyResponse {
    /// The answer of `verification` of `subject`, the request having taken `total_ms` so far.
    pub(crate) fn new(subject: &SubjectId, verification: &Verification, model_version: &str, total_ms: f64) -> VerifyResponse {
        let decision = &verification.decision;
        VerifyResponse {
            subject: subject.to_string(),
            is_match: decision.is_match,
            score: decision.score,
            threshold: decision.threshold,
            fmr: decision.fmr,
            model_version: model_version.to_string(),
            templates_compared: decision.templates_compared,
            best_template: decision.best_template,
            found: FaceReport::of_capture(&verification.photo, &verification.frame_scores, verification.challenge.as_ref()),
            timings: RequestTimings { photo: PhotoTimings::of(&verification.photo), match_ms: verification.match_ms, total_ms },
        }
    }
}

#[derive(Debug, Serialize)]
struct Candidate {
    subject: String,
    score: f32,
    #[serde(rename = "match")]
    is_match: bool,
    /// The threshold for this subject's number of templates.
    threshold: f32,
}

/// `POST /liveness/challenge`'s answer: the challenge's id, its lifetime in seconds and its
/// steps, each with the yaw range (degrees, `/analyze`'s convention) its frame must show.
#[derive(Debug, Serialize)]
pub(crate) struct ChallengeResponse {
    challenge: String,
    expires_in: u64,
    steps: Vec<ChallengeStepRange>,
    /// Most frames `/verify` takes for one step (`frame_steps`).
    max_frames_per_step: usize,
}

#[derive(Debug, Serialize)]
struct ChallengeStepRange {
    turn: &'static str,
    yaw_min: f32,
    yaw_max: f32,
}

impl From<IssuedChallenge> for ChallengeResponse {
    fn from(c: IssuedChallenge) -> ChallengeResponse {
        let steps = c.steps.iter().map(|s| ChallengeStepRange { turn: s.turn.name(), yaw_min: s.yaw_min, yaw_max: s.yaw_max }).collect();
        // Whole seconds, rounded up: a challenge is never announced as expired when it is not.
        let expires_in = (c.expires_in.as_millis() as u64).div_ceil(1000);
        ChallengeResponse { challenge: c.id, expires_in, steps, max_frames_per_step: facegate_service::MAX_FRAMES_PER_STEP }
    }
}

/// `POST /identify`'s answer.
#[derive(Debug, Serialize)]
pub(crate) struct IdentifyResponse {
    /// The best-scoring subjects, best first, at most `k`.
    candidates: Vec<Candidate>,
    /// The threshold for a subject with one template (each candidate carries its own).
    threshold: f32,
    fmr: f64,
    model_version: String,
    /// Subjects with templates of the current model version that were searched.
    subjects_searched: usize,
    #[serde(flatten)]
    found: FaceReport,
    timings: RequestTimings,
}

impl IdentifyResponse {
    /// The answer of `found`, the request having taken `total_ms` so far.
    pub(crate) fn new(found: Identification, model_version: &str, total_ms: f64) -> IdentifyResponse {
        let candidates = found
            .candidates
            .into_iter()
            .map(|c| Candidate {
                subject: c.subject,
                score: c.decision.score,
                is_match: c.decision.is_match,
                threshold: c.decision.threshold,
            })
            .collect();
        IdentifyResponse {
            candidates,
            threshold: found.operating_point.threshold,
            fmr: found.operating_point.fmr,
            model_version: model_version.to_string(),
            subjects_searched: found.subjects_searched,
            found: FaceReport::of(&found.photo),
            timings: RequestTimings { photo: PhotoTimings::of(&found.photo), match_ms: found.match_ms, total_ms },
        }
    }
}

#[derive(Debug, Serialize)]
struct AnalyzeTimings {
    decode_ms: f64,
    detect_ms: f64,
    total_ms: f64,
}

/// `POST /analyze`'s answer.
#[derive(Debug, Serialize)]
pub(crate) struct AnalyzeResponse {
    faces_found: usize,
    faces: Vec<AnalyzedFace>,
    timings: AnalyzeTimings,
}

impl AnalyzeResponse {
    /// The answer of `analysis`, the request having taken `total_ms` so far.
    pub(crate) fn new(analysis: facegate_service::inspect::Analysis, total_ms: f64) -> AnalyzeResponse {
        let reading = analysis.reading;
        AnalyzeResponse {
            faces_found: reading.faces_found,
            faces: reading
                .faces
                .into_iter()
                .zip(analysis.liveness.into_iter().chain(std::iter::repeat(None)))
                .map(AnalyzedFace::of)
                .collect(),
            timings: AnalyzeTimings { decode_ms: analysis.decode_ms, detect_ms: reading.detect_ms, total_ms },
        }
    }
}

/// One subject as listed: its id, how many templates it has, and when it was enrolled.
#[derive(Debug, Serialize)]
struct SubjectSummary {
    id: String,
    templates: u32,
    created_at: String,
    updated_at: String,
}

impl From<facegate_store::SubjectSummary> for SubjectSummary {
    fn from(s: facegate_store::SubjectSummary) -> SubjectSummary {
        SubjectSummary { id: s.id, templates: s.templates, created_at: s.created_at, updated_at: s.updated_at }
    }
}

/// `GET /subjects`'s answer: one page.
#[derive(Debug, Serialize)]
pub(crate) struct SubjectList {
    subjects: Vec<SubjectSummary>,
    /// Pass as `after` to get the next page; null on the last page.
    next_after: Option<String>,
}

impl SubjectList {
    /// A page of at most `limit` subjects: a full one has a next page after its last subject.
    pub(crate) fn page(subjects: Vec<facegate_store::SubjectSummary>, limit: u32) -> SubjectList {
        let next_after = (subjects.len() == limit as usize).then(|| subjects.last().map(|s| s.id.clone())).flatten();
        SubjectList { subjects: subjects.into_iter().map(SubjectSummary::from).collect(), next_after }
    }
}

/// Templates of one subject made by one model version.
#[derive(Debug, Serialize)]
struct VersionCount {
    model_version: String,
    templates: u32,
}

/// `GET /subjects/{id}`'s answer.
#[derive(Debug, Serialize)]
pub(crate) struct SubjectDetail {
    id: String,
    templates: u32,
    model_versions: Vec<VersionCount>,
    created_at: String,
    updated_at: String,
}

impl From<facegate_store::SubjectDetail> for SubjectDetail {
    fn from(s: facegate_store::SubjectDetail) -> SubjectDetail {
        let model_versions =
            s.model_versions.into_iter().map(|v| VersionCount { model_version: v.model_version, templates: v.templates }).collect();
        SubjectDetail { id: s.id, templates: s.templates, model_versions, created_at: s.created_at, updated_at: s.updated_at }
    }
}

/// The database behind the store.
#[derive(Debug, Clone, Copy, Serialize)]
#[serde(rename_all = "lowercase")]
enum StoreBackend {
    Sqlite,
    Postgres,
}

impl From<Backend> for StoreBackend {
    fn from(b: Backend) -> StoreBackend {
        match b {
            Backend::Sqlite => StoreBackend::Sqlite,
            Backend::Postgres => StoreBackend::Postgres,
        }
    }
}

/// One stated FMR's threshold on the site's impostor pairs.
#[derive(Debug, Clone, Copy, Serialize)]
struct SitePoint {
    fmr: f64,
    threshold: f32,
}

/// The site calibration raising the thresholds (`facegate calibrate`).
#[derive(Debug, Clone, Serialize)]
struct SiteCalibration {
    model_version: String,
    /// Subjects and templates whose pairs were scored.
    subjects: usize,
    templates: usize,
    /// Impostor pairs scored.
    impostor_pairs: usize,
    /// The calibrated FMRs the pairs allow, lowest threshold first.
    points: Vec<SitePoint>,
    /// The score at or above which two ids were taken for one person; absent in calibrations
    /// stored before duplicates were looked for.
    #[serde(skip_serializing_if = "Option::is_none")]
    duplicate_threshold: Option<f32>,
    /// Template pairs left out as suspected duplicates.
    duplicate_pairs_left_out: usize,
    /// Pairs of ids suspected to be one person.
    duplicate_id_pairs: usize,
}

impl From<&facegate_service::site::SiteCalibration> for SiteCalibration {
    fn from(s: &facegate_service::site::SiteCalibration) -> SiteCalibration {
        SiteCalibration {
            model_version: s.model_version.clone(),
            subjects: s.subjects,
            templates: s.templates,
            impostor_pairs: s.impostor_pairs,
            points: s.points.iter().map(|p| SitePoint { fmr: p.fmr, threshold: p.threshold }).collect(),
            duplicate_threshold: s.duplicate_threshold,
            duplicate_pairs_left_out: s.duplicate_pairs_left_out,
            duplicate_id_pairs: s.duplicate_id_pairs,
        }
    }
}

/// `GET /health`'s answer.
#[derive(Debug, Serialize)]
pub(crate) struct Health {
    status: &'static str,
    model_version: String,
    /// Only for a request with an accepted key when keys are set (counts are not public).
    #[serde(skip_serializing_if = "Option::is_none")]
    subjects: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    templates: Option<u64>,
    /// Whether template vectors are sealed at rest (a template key is configured).
    templates_encrypted: bool,
    store_backend: StoreBackend,
    /// What `DELETE /subjects/{id}` erases here (its `Facegate-Erasure` header).
    erasure: &'static str,
    /// The id of the current template key (never the key); with an accepted key, when one is set.
    #[serde(skip_serializing_if = "Option::is_none")]
    template_key_id: Option<String>,
    /// Subjects whose templates are stored plain (with an accepted key, like the counts).
    #[serde(skip_serializing_if = "Option::is_none")]
    subjects_unencrypted: Option<u64>,
    /// Subjects sealed under an older template key (`facegate rekey` has not re-wrapped them yet);
    /// with an accepted key, like the counts.
    #[serde(skip_serializing_if = "Option::is_none")]
    subjects_on_older_keys: Option<u64>,
    /// With an accepted key, like the counts (its subject count is the gallery's).
    #[serde(skip_serializing_if = "Option::is_none")]
    site_calibration: Option<SiteCalibration>,
    /// Subjects with a template of the current model version, those verify and identify can find
    /// (with an accepted key, like the counts). Fewer than `subjects` after a model upgrade: the
    /// others must enrol again.
    #[serde(skip_serializing_if = "Option::is_none")]
    subjects_current_model: Option<u64>,
    /// The liveness threshold in force; absent with liveness off or no model.
    #[serde(skip_serializing_if = "Option::is_none")]
    liveness: Option<HealthLiveness>,
}

/// `/health`'s `liveness`: the threshold a face's score is held to and how it was set.
#[derive(Debug, Serialize)]
pub(crate) struct HealthLiveness {
    threshold: f32,
    /// Who set it: `model` (the liveness model's own operating point), `camera` (this camera's
    /// calibration, `facegate calibrate-liveness`) or `operator` (`--liveness-threshold`).
    source: &'static str,
    operating_point: String,
}

impl Health {
    /// The service's `health` of `store`, whose deletions erase `erasure`. What is not public
    /// (counts, key id, the site calibration) only when the request was `admitted` with a key;
    /// `sealing` is read only then.
    pub(crate) fn new(
        health: facegate_service::Health,
        store: &Store,
        erasure: &'static str,
        admitted: bool,
        sealing: Option<SealingCounts>,
    ) -> Health {
        Health {
            status: "ok",
            model_version: health.model_version,
            subjects: admitted.then_some(health.subjects),
            templates: admitted.then_some(health.templates),
            templates_encrypted: health.templates_encrypted,
            store_backend: health.store_backend.into(),
            erasure,
            template_key_id: store.template_key_id().filter(|_| admitted).map(String::from),
            subjects_unencrypted: sealing.map(|s| s.plain),
            subjects_on_older_keys: sealing.map(|s| s.other_keys),
            site_calibration: health.site_calibration.as_deref().filter(|_| admitted).map(SiteCalibration::from),
            subjects_current_model: admitted.then_some(health.subjects_current_model),
            liveness: health.liveness.map(|p| HealthLiveness {
                threshold: p.threshold,
                source: p.source.name(),
                operating_point: p.operating_point,
            }),
        }
    }
}
