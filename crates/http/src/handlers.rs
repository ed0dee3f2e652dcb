//! Route handlers: each reads its request through typed extractors, calls the service's use case
//! ([`facegate_service::Facegate`]) and maps the result to JSON or problem+json.

use std::sync::Arc;
use std::time::Instant;

use axum::Json;
use axum::extract::{Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;

use super::audit::Audit;
use super::input::{Params, SubjectPath, Upload, subject_id, validate_fmr};
use super::problem::{Problem, ProblemKind};
use super::responses::{ChallengeResponse, EnrollResponse, Health, IdentifyResponse, SubjectDetail, SubjectList, VerifyResponse};
use super::timeout::CommitPoint;
use super::{AppState, OPENAPI_YAML};
use facegate_core::elapsed_ms;
use facegate_service::{AnalyzedPhoto, PhotoError, ServiceError};
use facegate_store::Backend;

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

/// `POST /enroll`: all photos must each show exactly one face, meet the quality policy and (liveness
/// enforced) be taken for a live face; then all templates are stored in one transaction. Any bad
/// photo refuses the whole enrolment and names the photo (`image`). There is no `?quality=off`:
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
    // enrolment that is committed).
    commit.pass();
    let enrollment = prepared.commit().await?;
    enrollment.photos.iter().for_each(|photo| observe(&state, photo));
    audit.templates_added(enrollment.photos.len());
    let body = EnrollResponse::new(&subject, &enrollment, facegate.model_version());
    let mut response = (StatusCode::CREATED, Json(body)).into_response();
    if let Ok(location) = HeaderValue::from_str(&format!("/subjects/{subject}")) {
        response.headers_mut().insert(header::LOCATION, location);
    }
    Ok(response)
}

/// `POST /verify`: is the probe's largest face the enrolled subject? Up to four further frames of
/// the same capture (`frame` parts, `frames` in JSON) must show the probe's person and lend their
/// liveness to the probe's: the response's `liveness` is then fused over all of them. With a
/// `challenge` (`POST /liveness/challenge`) the frames are its steps' in order (one each, or
/// bursts with `frame_steps`) and the response's `liveness.challenge` carries the verdict.
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
    let challenge = upload.challenge.take();
    // `frame_steps` names the challenge's steps: without a challenge it has nothing to name and
    // is not read (openapi.yaml: "With `challenge`").
    let frame_steps = upload.frame_steps.take().filter(|_| challenge.is_some());
    let image = upload.single_image()?;
    let verification = match challenge {
        Some(challenge) => {
            audit.challenge(&challenge);
            let verified = facegate.verify_challenge(&subject, image, frames, frame_steps, &challenge, fmr).await;
            let outcome = match &verified {
                Ok(verification) => verification.challenge.as_ref(),
                Err(ServiceError::Photo { error: PhotoError::ChallengeFailed(outcome), .. }) => Some(outcome),
                Err(_) => None,
            };
            if let Some(outcome) = outcome {
                audit.challenge_outcome(outcome.passed, outcome.reason.as_deref());
            }
            verified?
        }
        None => facegate.verify_capture(&subject, image, frames, fmr).await?,
    };
    std::iter::once(&verification.photo).chain(&verification.frames).for_each(|photo| observe(&state, photo));
    let decision = &verification.decision;
    audit.decision(decision.score, decision.threshold, decision.is_match);
    let body = VerifyResponse::new(&subject, &verification, facegate.model_version(), elapsed_ms(start));
    Ok(Json(body).into_response())
}

/// `POST /liveness/challenge`: a new head-turn challenge, 201 with its id, lifetime and steps.
pub async fn issue_challenge(
    State(state): State<AppState>,
    audit: Audit,
    Params(NoParams {}): Params<NoParams>,
) -> Result<Response, Problem> {
    let issued = state.facegate().issue_challenge().await?;
    audit.challenge(&issued.id);
    Ok((StatusCode::CREATED, Json(ChallengeResponse::from(issued))).into_response())
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
    let body = IdentifyResponse::new(found, facegate.model_version(), elapsed_ms(start));
    Ok(Json(body).into_response())
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ListParams {
    limit: Option<u32>,
    after: Option<String>,
}

/// `GET /subjects`: subjects ordered by id, paged by `limit` (default 100, at most 1000) and `after`.
pub async fn list_subjects(State(state): State<AppState>, Params(params): Params<ListParams>) -> Result<Response, Problem> {
    let limit = params.limit.unwrap_or(100);
    if !(1..=1000).contains(&limit) {
        return Err(Problem::malformed(format!("limit must be between 1 and 1000, got {limit}")));
    }
    let after = params.after.as_deref().map(subject_id).transpose()?;
    let subjects = state.facegate().subjects(after.as_ref(), limit).await?;
    Ok(Json(SubjectList::page(subjects, limit)).into_response())
}

/// `GET /subjects/{id}`.
pub async fn get_subject(State(state): State<AppState>, SubjectPath(id): SubjectPath) -> Result<Json<SubjectDetail>, Problem> {
    Ok(Json(state.facegate().subject(&id).await?.into()))
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
/// (docs/storage.md, "Erasure: what it covers"):
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

/// `GET /livez`: the process answers. It touches neither the database nor the work pool, so a
/// replica that is busy, or whose database is down (`/health` answers 503 then), is not taken for
/// a dead one by a liveness probe.
pub async fn livez() -> Json<serde_json::Value> {
    Json(serde_json::json!({ "status": "alive" }))
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
    Ok(Json(Health::new(health, store, erasure_scope(store), admitted, sealing)))
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
