//! Route handlers. Each reads and checks its request first (cheap), looks up what it needs in
//! the store, and only then sends the photo work to the bounded pool.

use std::sync::Arc;
use std::time::Instant;

use crate::core::elapsed_ms;

use axum::Json;
use axum::body::Bytes;
use axum::extract::rejection::PathRejection;
use axum::extract::{Extension, Path, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};

use super::audit::Audit;
use super::input::{read_query, read_upload, subject_id, validate_fmr};
use super::problem::{Problem, ProblemKind};
use super::{AppState, FaceEngine, OPENAPI_YAML};
use crate::core::imaging::{self, DecodeLimits};
use crate::detect::Face;
use crate::landmarks::Landmarks;
use crate::morph::Pose;
use crate::pipeline::{FaceAnalysis, PipelineError, StageTimings};
use crate::quality::Quality;
use crate::service::{self, SubjectId, VerifyError};
use crate::store::{Backend, SubjectDetail, SubjectSummary};

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
}

struct Analysed {
    analysis: FaceAnalysis,
    timings: PhotoTimings,
}

impl Analysed {
    fn report(&self) -> FaceReport {
        let a = &self.analysis;
        FaceReport { faces_found: a.faces_found, face: a.face, landmarks: a.landmarks.clone(), pose: a.pose, quality: a.quality }
    }
}

/// Decode one photo within the limits and run the pipeline on it (on a pool thread).
fn analyse_photo(engine: &dyn FaceEngine, bytes: &[u8], limits: &DecodeLimits) -> Result<Analysed, Problem> {
    let start = Instant::now();
    let photo = imaging::decode(bytes, limits).map_err(|e| Problem::from_decode(&e))?;
    let decode_ms = elapsed_ms(start);
    let analysis = engine.analyze(&photo).map_err(|e| match e {
        PipelineError::NoFace => Problem::new(ProblemKind::NoFace, "no face was found in the photo"),
        // Landmarks the 3DMM cannot be fitted to: no usable face, as far as the client can act on it.
        PipelineError::PoseCorrection(e) => Problem::new(ProblemKind::NoFace, format!("the face found could not be pose-corrected: {e}")),
        other => Problem::internal(other),
    })?;
    let timings = PhotoTimings { decode_ms, stages: analysis.timings };
    Ok(Analysed { analysis, timings })
}

/// Analyse one probe photo on the pool and record its stage timings.
async fn analyse_probe(state: &AppState, image: Bytes) -> Result<Analysed, Problem> {
    let engine = state.0.engine.clone();
    let limits = state.0.config.decode_limits;
    let analysed = state.0.pool.run(move || analyse_photo(engine.as_ref(), &image, &limits)).await??;
    state.0.metrics.observe_stages(analysed.timings.decode_ms, &analysed.timings.stages);
    Ok(analysed)
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct NoParams {}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct MatchParams {
    fmr: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct IdentifyParams {
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

/// `POST /enroll`: all photos must each show exactly one face and meet the quality policy; then all
/// templates are stored in one transaction. Any bad photo refuses the whole enrolment and names the
/// photo (`image`). There is no `?quality=off`: the policy is the operator's (settings), and a
/// photo it refuses can be retaken, while a poor template costs every later verification.
pub async fn enroll(State(state): State<AppState>, request: Request) -> Result<Response, Problem> {
    let audit = Audit::of(&request);
    audit.model_version(state.0.engine.model_version());
    let _: NoParams = read_query(&request)?;
    let upload = read_upload(request).await?;
    let subject = upload.require_subject()?;
    audit.subject(&subject);
    let max = state.0.config.max_images;
    match upload.images.len() {
        0 => return Err(Problem::malformed("at least one photo is required (field image)")),
        n if n > max => return Err(Problem::malformed(format!("at most {max} photos per enrolment, got {n}"))),
        _ => {}
    }
    let engine = state.0.engine.clone();
    let limits = state.0.config.decode_limits;
    let policy = state.0.config.quality_policy;
    let images = upload.images;
    let analysed = state
        .0
        .pool
        .run(move || {
            let mut out = Vec::with_capacity(images.len());
            for (index, bytes) in images.iter().enumerate() {
                let analysed = analyse_photo(engine.as_ref(), bytes, &limits).map_err(|p| p.for_image(index))?;
                service::check_enrolment_photo(analysed.analysis.faces_found)
                    .map_err(|e| Problem::new(ProblemKind::SeveralFaces, e.to_string()).for_image(index))?;
                service::check_enrolment_quality(&policy, &analysed.analysis.quality)
                    .map_err(|failures| Problem::low_quality(failures).for_image(index))?;
                out.push(analysed);
            }
            Ok::<_, Problem>(out)
        })
        .await??;
    for a in &analysed {
        state.0.metrics.observe_stages(a.timings.decode_ms, &a.timings.stages);
    }
    let templates: Vec<_> = analysed.iter().map(|a| a.analysis.template.clone()).collect();
    let count = state.0.gallery.enroll(&subject, templates.clone()).await?;
    audit.templates_added(templates.len());
    let body = EnrollResponse {
        subject: subject.to_string(),
        templates: count,
        added: templates.len(),
        model_version: state.0.engine.model_version().to_string(),
        images: analysed.iter().enumerate().map(|(index, a)| ImageReport { index, found: a.report(), timings: a.timings }).collect(),
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
    #[serde(flatten)]
    found: FaceReport,
    timings: RequestTimings,
}

/// `POST /verify`: is the probe's largest face the enrolled subject?
pub async fn verify(State(state): State<AppState>, request: Request) -> Result<Response, Problem> {
    let start = Instant::now();
    let audit = Audit::of(&request);
    audit.model_version(state.0.engine.model_version());
    let params: MatchParams = read_query(&request)?;
    let fmr = validate_fmr(params.fmr)?.unwrap_or(state.0.config.default_fmr);
    let upload = read_upload(request).await?;
    let subject = upload.require_subject()?;
    audit.subject(&subject);
    let image = upload.single_image()?;
    // Look the subject up before the expensive work.
    let enrolled = state.0.store.templates(&subject).await?.ok_or_else(|| unknown_subject(&subject))?;
    let engine = &state.0.engine;
    let comparable = service::comparable_templates(engine.as_ref(), &subject, enrolled).map_err(|e| match e {
        VerifyError::ModelMismatch { .. } => Problem::new(ProblemKind::ModelMismatch, e.to_string()),
    })?;
    let analysed = analyse_probe(&state, image).await?;
    let t = Instant::now();
    let decision = service::decide(engine.as_ref(), &analysed.analysis.template, &comparable, fmr);
    audit.decision(decision.score, decision.threshold, decision.is_match);
    let match_ms = elapsed_ms(t);
    let body = VerifyResponse {
        subject: subject.to_string(),
        is_match: decision.is_match,
        score: decision.score,
        threshold: decision.threshold,
        fmr: decision.fmr,
        model_version: engine.model_version().to_string(),
        templates_compared: decision.templates_compared,
        found: analysed.report(),
        timings: RequestTimings { photo: analysed.timings, match_ms, total_ms: elapsed_ms(start) },
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
pub async fn identify(State(state): State<AppState>, request: Request) -> Result<Response, Problem> {
    let start = Instant::now();
    let audit = Audit::of(&request);
    audit.model_version(state.0.engine.model_version());
    let params: IdentifyParams = read_query(&request)?;
    let fmr = validate_fmr(params.fmr)?.unwrap_or(state.0.config.default_fmr);
    let k = params.k.unwrap_or(5);
    if !(1..=MAX_K).contains(&k) {
        return Err(Problem::malformed(format!("k must be between 1 and {MAX_K}, got {k}")));
    }
    let upload = read_upload(request).await?;
    if upload.subject.is_some() {
        return Err(Problem::malformed("identify takes no subject; use /verify to check one subject"));
    }
    let image = upload.single_image()?;
    let gallery = state.0.gallery.clone();
    // What the store holds as the request comes in (other replicas' enrolments and deletions
    // included) is what the search must see; the gallery catches up while the probe is analysed.
    let store_version = gallery.change_version().await?;
    let analysed = analyse_probe(&state, image).await?;
    let t = Instant::now();
    let engine = state.0.engine.clone();
    gallery.load().await?;
    gallery.wait_until_applied(store_version).await;
    let probe = analysed.analysis.template.clone();
    let matcher = engine.clone();
    // Scoring the whole gallery is CPU work too: it runs on the pool.
    let (found, subjects_searched) =
        state.0.pool.run(move || gallery.search(matcher.as_ref(), &probe, fmr, k)).await?.map_err(Problem::internal)?;
    let point = engine.operating_point(fmr, 1);
    // The audit names the best candidate and its decision.
    audit.candidates(found.len());
    if let Some(best) = found.first() {
        audit.subject(&best.subject);
        audit.decision(best.decision.score, best.decision.threshold, best.decision.is_match);
    }
    let candidates = found
        .into_iter()
        .map(|c| Candidate { subject: c.subject, score: c.decision.score, is_match: c.decision.is_match, threshold: c.decision.threshold })
        .collect();
    let match_ms = elapsed_ms(t);
    let body = IdentifyResponse {
        candidates,
        threshold: point.threshold,
        fmr: point.fmr,
        model_version: engine.model_version().to_string(),
        subjects_searched,
        found: analysed.report(),
        timings: RequestTimings { photo: analysed.timings, match_ms, total_ms: elapsed_ms(start) },
    };
    Ok(Json(body).into_response())
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ListParams {
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
pub async fn list_subjects(State(state): State<AppState>, request: Request) -> Result<Response, Problem> {
    let params: ListParams = read_query(&request)?;
    let limit = params.limit.unwrap_or(100);
    if !(1..=1000).contains(&limit) {
        return Err(Problem::malformed(format!("limit must be between 1 and 1000, got {limit}")));
    }
    let after = params.after.as_deref().map(subject_id).transpose()?;
    let subjects = state.0.store.list_subjects(after.as_ref(), limit).await?;
    let next_after = (subjects.len() == limit as usize).then(|| subjects.last().map(|s| s.id.clone())).flatten();
    Ok(Json(SubjectList { subjects, next_after }).into_response())
}

fn subject_in_path(path: Result<Path<String>, PathRejection>) -> Result<SubjectId, Problem> {
    let Path(id) = path.map_err(|e| Problem::malformed(format!("invalid subject id in the path: {}", e.body_text())))?;
    subject_id(&id)
}

fn unknown_subject(id: &SubjectId) -> Problem {
    Problem::new(ProblemKind::UnknownSubject, format!("subject {id} is not enrolled"))
}

/// `GET /subjects/{id}`.
pub async fn get_subject(State(state): State<AppState>, path: Result<Path<String>, PathRejection>) -> Result<Json<SubjectDetail>, Problem> {
    let id = subject_in_path(path)?;
    state.0.store.subject(&id).await?.map(Json).ok_or_else(|| unknown_subject(&id))
}

/// `DELETE /subjects/{id}`: erase the subject and all its templates.
pub async fn delete_subject(
    State(state): State<AppState>,
    audit: Option<Extension<Audit>>,
    path: Result<Path<String>, PathRejection>,
) -> Result<StatusCode, Problem> {
    let id = subject_in_path(path)?;
    if let Some(Extension(audit)) = audit {
        audit.subject(&id);
    }
    state.0.gallery.delete(&id).await?.map(|_| StatusCode::NO_CONTENT).ok_or_else(|| unknown_subject(&id))
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
}

/// `GET /health`: the database answers and the models are loaded.
pub async fn health(State(state): State<AppState>, headers: HeaderMap) -> Result<Json<Health>, Problem> {
    let (subjects, templates) = state.0.store.counts().await?;
    let (subjects, templates) = if state.0.keys.admits(&headers) { (Some(subjects), Some(templates)) } else { (None, None) };
    let templates_encrypted = state.0.store.encrypts();
    let store_backend = state.0.store.backend();
    let model_version = state.0.engine.model_version().to_string();
    Ok(Json(Health { status: "ok", model_version, subjects, templates, templates_encrypted, store_backend }))
}

/// `GET /metrics`: Prometheus (OpenMetrics text) exposition.
pub async fn metrics(State(state): State<AppState>) -> Response {
    if let Ok((subjects, templates)) = state.0.store.counts().await {
        state.0.metrics.subjects.set(subjects as i64);
        state.0.metrics.templates.set(templates as i64);
    }
    let metrics: &Arc<super::Metrics> = &state.0.metrics;
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
