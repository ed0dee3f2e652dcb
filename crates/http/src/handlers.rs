//! Route handlers: each reads its request through typed extractors, calls the service's use case
//! ([`facegate_service::Facegate`]) and maps the result to JSON or problem+json.

use std::sync::Arc;
use std::time::Instant;

use axum::Json;
use axum::extract::{Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};

use super::audit::Audit;
use super::input::{Params, SubjectPath, Upload, subject_id, validate_fmr};
use super::problem::{Problem, ProblemKind};
use super::timeout::CommitPoint;
use super::{AppState, OPENAPI_YAML};
use facegate_core::elapsed_ms;
use facegate_service::AnalyzedPhoto;
use facegate_service::site::SiteCalibration;
use facegate_store::{Backend, SubjectDetail, SubjectSummary};
use facegate_vision::detect::Face;
use facegate_vision::landmarks::Landmarks;
use facegate_vision::liveness::Liveness;
use facegate_vision::morph::Pose;
use facegate_vision::pipeline::StageTimings;
use facegate_vision::quality::Quality;

/// Milliseconds spent on one photo, stage by stage: decoding, then the pipeline's stages.
#[derive(Debug, Clone, Copy, Serialize)]
struct PhotoTimings {
    decode_ms: f64,
    #[serde(flatten)]
    stages: StageTimings,
}

/// What the pipeline found in one photo.
#[derive(Debug, Serialize)]
struct FaceReport {
    /// Faces the detector found; the largest is the one used.
    faces_found: usize,
    face: Face,
    landmarks: Landmarks,
    /// Head pose in degrees from the 3DMM fit; null when the 3DMM is not loaded.
    pose: Option<Pose>,
    /// Face image quality: the components and the unified score (0–100).
    quality: Quality,
    /// Live face or presentation attack; absent when liveness is off (or no model is loaded).
    #[serde(skip_serializing_if = "Option::is_none")]
    liveness: Option<LivenessReport>,
}

/// A face's liveness; for a `/verify` capture with further frames, the capture's, fused over
/// them, with how many were fused and each one's own score (the probe's first).
#[derive(Debug, Serialize)]
struct LivenessReport {
    #[serde(flatten)]
    liveness: Liveness,
    #[serde(skip_serializing_if = "Option::is_none")]
    frames: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    frame_scores: Option<Vec<f32>>,
}

impl FaceReport {
    fn of(photo: &AnalyzedPhoto) -> FaceReport {
        let a = &photo.analysis;
        FaceReport {
            faces_found: a.faces_found,
            face: a.face,
            landmarks: a.landmarks.clone(),
            pose: a.pose,
            quality: a.quality,
            liveness: a.liveness.clone().map(|liveness| LivenessReport { liveness, frames: None, frame_scores: None }),
        }
    }

    /// The report of a `/verify` probe whose liveness was fused over the capture's `frame_scores`
    /// (the probe's first); a single photo's (no scores) is [`FaceReport::of`].
    fn of_capture(photo: &AnalyzedPhoto, frame_scores: &[f32]) -> FaceReport {
        let mut report = FaceReport::of(photo);
        if let Some(live) = report.liveness.as_mut().filter(|_| !frame_scores.is_empty()) {
            live.frames = Some(frame_scores.len());
            live.frame_scores = Some(frame_scores.to_vec());
        }
        report
    }
}

impl PhotoTimings {
    fn of(photo: &AnalyzedPhoto) -> PhotoTimings {
        PhotoTimings { decode_ms: photo.decode_ms, stages: photo.analysis.timings }
    }
}

/// Record a photo's stage timings in the metrics.
fn observe(state: &AppState, photo: &AnalyzedPhoto) {
    state.metrics().observe_stages(photo.decode_ms, &photo.analysis.timings);
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct NoParams {}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct MatchParams {
    fmr: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct IdentifyParams {
    fmr: Option<f64>,
    k: Option<usize>,
}

#[derive(Debug, Serialize)]
struct ImageReport {
    index: usize,
    #[serde(flatten)]
    found: FaceReport,
    timings: PhotoTimings,
}

#[derive(Debug, Serialize)]
struct EnrollResponse {
    subject: String,
    /// Templates the subject has now (all model versions).
    templates: u32,
    /// Templates added by this request (one per photo).
    added: usize,
    model_version: String,
    images: Vec<ImageReport>,
}

/// `POST /enroll`: all photos must each show exactly one face, meet the quality policy and (liveness
/// enforced) be taken for a live face; then all templates are stored in one transaction. Any bad
/// photo refuses the whole enrollment and names the photo (`image`). There is no `?quality=off`:
/// the policy is the operator's (settings), and a photo it refuses can be retaken, while a poor
/// template costs every later verification.
pub async fn enroll(
    State(state): State<AppState>,
    audit: Audit,
    commit: CommitPoint,
    Params(NoParams {}): Params<NoParams>,
    upload: Upload,
) -> Result<Response, Problem> {
    let facegate = state.facegate();
    audit.model_version(facegate.model_version());
    let subject = upload.require_subject()?;
    audit.subject(&subject);
    upload.refuse_frames()?;
    let prepared = facegate.prepare_enrollment(&subject, upload.images).await?;
    // From here the answer is the store's: the request deadline waits for it (never a 504 for an
    // enrollment that is committed).
    commit.pass();
    let enrollment = prepared.commit().await?;
    enrollment.photos.iter().for_each(|photo| observe(&state, photo));
    audit.templates_added(enrollment.photos.len());
    let body = EnrollResponse {
        subject: subject.to_string(),
        templates: enrollment.templates,
        added: enrollment.photos.len(),
        model_version: facegate.model_version().to_string(),
        images: enrollment
            .photos
            .iter()
            .enumerate()
            .map(|(index, photo)| ImageReport { index, found: FaceReport::of(photo), timings: PhotoTimings::of(photo) })
            .collect(),
    };
    let mut response = (StatusCode::CREATED, Json(body)).into_response();
    if let Ok(location) = HeaderValue::from_str(&format!("/subjects/{subject}")) {
        response.headers_mut().insert(header::LOCATION, location);
    }
    Ok(response)
}

#[derive(Debug, Serialize)]
struct RequestTimings {
    #[serde(flatten)]
    photo: PhotoTimings,
    match_ms: f64,
    total_ms: f64,
}

#[derive(Debug, Serialize)]
struct VerifyResponse {
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

/// `POST /verify`: is the probe's largest face the enrolled subject? Up to four further frames of
/// the same capture (`frame` parts, `frames` in JSON) must show the probe's person and lend their
/// liveness to the probe's: the response's `liveness` is then fused over all of them.
pub async fn verify(
    State(state): State<AppState>,
    audit: Audit,
    Params(params): Params<MatchParams>,
    mut upload: Upload,
) -> Result<Response, Problem> {
    let start = Instant::now();
    let facegate = state.facegate();
    audit.model_version(facegate.model_version());
    let fmr = validate_fmr(params.fmr)?;
    let subject = upload.require_subject()?;
    audit.subject(&subject);
    let frames = std::mem::take(&mut upload.frames);
    let image = upload.single_image()?;
    let verification = facegate.verify_capture(&subject, image, frames, fmr).await?;
    std::iter::once(&verification.photo).chain(&verification.frames).for_each(|photo| observe(&state, photo));
    let decision = verification.decision;
    audit.decision(decision.score, decision.threshold, decision.is_match);
    let body = VerifyResponse {
        subject: subject.to_string(),
        is_match: decision.is_match,
        score: decision.score,
        threshold: decision.threshold,
        fmr: decision.fmr,
        model_version: facegate.model_version().to_string(),
        templates_compared: decision.templates_compared,
        best_template: decision.best_template,
        found: FaceReport::of_capture(&verification.photo, &verification.frame_scores),
        timings: RequestTimings {
            photo: PhotoTimings::of(&verification.photo),
            match_ms: verification.match_ms,
            total_ms: elapsed_ms(start),
        },
    };
    Ok(Json(body).into_response())
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

#[derive(Debug, Serialize)]
struct IdentifyResponse {
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

/// Most candidates `/identify` returns.
const MAX_K: usize = 100;

/// `POST /identify`: the top-k enrolled subjects for the probe's largest face.
pub async fn identify(
    State(state): State<AppState>,
    audit: Audit,
    Params(params): Params<IdentifyParams>,
    upload: Upload,
) -> Result<Response, Problem> {
    let start = Instant::now();
    let facegate = state.facegate();
    audit.model_version(facegate.model_version());
    let fmr = validate_fmr(params.fmr)?;
    let k = params.k.unwrap_or(5);
    if !(1..=MAX_K).contains(&k) {
        return Err(Problem::malformed(format!("k must be between 1 and {MAX_K}, got {k}")));
    }
    upload.refuse_subject("identify takes no subject; use /verify to check one subject")?;
    let image = upload.single_image()?;
    let found = facegate.identify(image, fmr, k).await?;
    observe(&state, &found.photo);
    // The audit names the best candidate and its decision.
    audit.candidates(found.candidates.len());
    if let Some(best) = found.candidates.first() {
        audit.subject(&best.subject);
        audit.decision(best.decision.score, best.decision.threshold, best.decision.is_match);
    }
    let candidates = found
        .candidates
        .into_iter()
        .map(|c| Candidate { subject: c.subject, score: c.decision.score, is_match: c.decision.is_match, threshold: c.decision.threshold })
        .collect();
    let body = IdentifyResponse {
        candidates,
        threshold: found.operating_point.threshold,
        fmr: found.operating_point.fmr,
        model_version: facegate.model_version().to_string(),
        subjects_searched: found.subjects_searched,
        found: FaceReport::of(&found.photo),
        timings: RequestTimings { photo: PhotoTimings::of(&found.photo), match_ms: found.match_ms, total_ms: elapsed_ms(start) },
    };
    Ok(Json(body).into_response())
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ListParams {
    limit: Option<u32>,
    after: Option<String>,
}

#[derive(Debug, Serialize)]
struct SubjectList {
    subjects: Vec<SubjectSummary>,
    /// Pass as `after` to get the next page; null on the last page.
    next_after: Option<String>,
}

/// `GET /subjects`: subjects ordered by id, paged by `limit` (default 100, at most 1000) and `after`.
pub async fn list_subjects(State(state): State<AppState>, Params(params): Params<ListParams>) -> Result<Response, Problem> {
    let limit = params.limit.unwrap_or(100);
    if !(1..=1000).contains(&limit) {
        return Err(Problem::malformed(format!("limit must be between 1 and 1000, got {limit}")));
    }
    let after = params.after.as_deref().map(subject_id).transpose()?;
    let subjects = state.facegate().subjects(after.as_ref(), limit).await?;
    let next_after = (subjects.len() == limit as usize).then(|| subjects.last().map(|s| s.id.clone())).flatten();
    Ok(Json(SubjectList { subjects, next_after }).into_response())
}

/// `GET /subjects/{id}`.
pub async fn get_subject(State(state): State<AppState>, SubjectPath(id): SubjectPath) -> Result<Json<SubjectDetail>, Problem> {
    Ok(Json(state.facegate().subject(&id).await?))
}

/// `DELETE /subjects/{id}`: erase the subject and all its templates. The 204 says what the erasure
/// covers in [`ERASURE_HEADER`] ([`erasure_scope`]).
pub async fn delete_subject(
    State(state): State<AppState>,
    audit: Audit,
    commit: CommitPoint,
    SubjectPath(id): SubjectPath,
) -> Result<Response, Problem> {
    audit.subject(&id);
    // The deletion's answer is the store's: never a 504 for a subject that is erased.
    commit.pass();
    match state.facegate().delete(&id).await? {
        Some(_) => Ok((StatusCode::NO_CONTENT, [(ERASURE_HEADER, erasure_scope(state.store()))]).into_response()),
        None => Err(Problem::new(ProblemKind::UnknownSubject, format!("subject {id} is not enrolled"))),
    }
}

/// The header of a `DELETE /subjects/{id}` answer saying what the erasure covers.
pub const ERASURE_HEADER: &str = "facegate-erasure";

/// What a deletion erases on this store, then what still holds the subject and until when
/// (docs/service.md, "Erasure: what it covers"):
/// - `live-database`: SQLite's files (the database and its WAL) no longer hold any byte of it;
///   `queries`: on PostgreSQL no query, replica or later dump sees it, but its dead rows stay in
///   the server's files ("disk") until overwritten;
/// - `…-until-key-rotation`: with a template key, copies made before (backups, and on PostgreSQL
///   the dead rows, WAL and archives) hold it sealed, with its wrapped data key, and open with
///   that key until it is rotated away (`facegate rekey`) and destroyed; `…-not-erased`: without
///   a key they hold it plain for as long as they exist.
pub fn erasure_scope(store: &facegate_store::Store) -> &'static str {
    match (store.backend(), store.encrypts()) {
        (Backend::Sqlite, true) => "live-database; backups-until-key-rotation",
        (Backend::Sqlite, false) => "live-database; backups-not-erased",
        (Backend::Postgres, true) => "queries; disk-and-backups-until-key-rotation",
        (Backend::Postgres, false) => "queries; disk-and-backups-not-erased",
    }
}

#[derive(Debug, Serialize)]
pub struct Health {
    status: &'static str,
    model_version: String,
    /// Only for a request with an accepted key when keys are set (counts are not public).
    #[serde(skip_serializing_if = "Option::is_none")]
    subjects: Option<u64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    templates: Option<u64>,
    /// Whether template vectors are sealed at rest (a template key is configured).
    templates_encrypted: bool,
    /// The database behind the store.
    store_backend: Backend,
    /// What `DELETE /subjects/{id}` erases here ([`erasure_scope`], its `Facegate-Erasure` header).
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
    /// The site calibration raising the thresholds (`facegate calibrate`); with an accepted key,
    /// like the counts (its subject count is the gallery's).
    #[serde(skip_serializing_if = "Option::is_none")]
    site_calibration: Option<std::sync::Arc<SiteCalibration>>,
    /// Subjects with a template of the current model version, those verify and identify can find
    /// (with an accepted key, like the counts). Fewer than `subjects` after a model upgrade: the
    /// others must enrol again.
    #[serde(skip_serializing_if = "Option::is_none")]
    subjects_current_model: Option<u64>,
}

/// `GET /health`: the database answers and the models are loaded. The service started only if its
/// template keys open the sealed subjects (or there are none), so the sealing counts say what is
/// left to do, not whether reads work.
pub async fn health(State(state): State<AppState>, headers: HeaderMap) -> Result<Json<Health>, Problem> {
    // Within a second, whatever the database does: a slow answer is a database that is down.
    let down = || Problem::new(ProblemKind::StoreUnavailable, format!("the template database did not answer within {HEALTH_WAIT:?}"));
    tokio::time::timeout(HEALTH_WAIT, health_of(&state, &headers)).await.unwrap_or_else(|_| Err(down()))
}

/// Longest `/health` waits for the database.
const HEALTH_WAIT: std::time::Duration = std::time::Duration::from_secs(1);

async fn health_of(state: &AppState, headers: &HeaderMap) -> Result<Json<Health>, Problem> {
    let health = state.facegate().health().await?;
    let admitted = state.keys().admits(headers);
    let store = state.store();
    let sealing = if admitted { Some(store.sealing_counts().await?) } else { None };
    Ok(Json(Health {
        status: "ok",
        model_version: health.model_version,
        subjects: admitted.then_some(health.subjects),
        templates: admitted.then_some(health.templates),
        templates_encrypted: health.templates_encrypted,
        store_backend: health.store_backend,
        erasure: erasure_scope(store),
        template_key_id: store.template_key_id().filter(|_| admitted).map(String::from),
        subjects_unencrypted: sealing.map(|s| s.plain),
        subjects_on_older_keys: sealing.map(|s| s.other_keys),
        site_calibration: health.site_calibration.filter(|_| admitted),
        subjects_current_model: admitted.then_some(health.subjects_current_model),
    }))
}

/// `GET /metrics`: Prometheus (OpenMetrics text) exposition.
pub async fn metrics(State(state): State<AppState>) -> Response {
    if let Ok(health) = state.facegate().health().await {
        state.metrics().subjects.set(health.subjects as i64);
        state.metrics().templates.set(health.templates as i64);
    }
    let metrics: &Arc<super::Metrics> = state.metrics();
    ([(header::CONTENT_TYPE, "application/openmetrics-text; version=1.0.0; charset=utf-8")], metrics.encode()).into_response()
}

/// `GET /openapi.yaml`.
pub async fn openapi() -> Response {
    ([(header::CONTENT_TYPE, "application/yaml")], OPENAPI_YAML).into_response()
}

pub async fn not_found(request: Request) -> Problem {
    Problem::new(ProblemKind::NotFound, format!("no route {}", request.uri().path()))
}

pub async fn method_not_allowed(request: Request) -> Problem {
    Problem::new(ProblemKind::MethodNotAllowed, format!("{} is not allowed on {}", request.method(), request.uri().path()))
}
