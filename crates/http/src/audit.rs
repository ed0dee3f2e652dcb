//! The audit log: one structured event per enrolment, verification, identification, deletion and
//! issued liveness challenge, refusals included, on the tracing target [`AUDIT_TARGET`]. It names
//! who asked (the key id, a prefix of the key's SHA-256, never the key), the request id, the
//! subject, the decision with its score, threshold and model version, the challenge a
//! verification answered (its id, passed or not and why), and the outcome (`ok` or the problem
//! type); never photo bytes. A challenge's id is a one-time nonce, worthless once used or
//! expired: logged, it ties the verification to the issue that drew it.
//!
//! The layer ([`record`]) wraps the audited routes outside the API-key check, so refused keys are
//! logged too. Handlers add what they learn to the request's [`Audit`] as they go.

use std::sync::{Arc, Mutex};

use axum::extract::{FromRequestParts, MatchedPath, Request};
use axum::http::Method;
use axum::http::request::Parts;
use axum::middleware::Next;
use axum::response::Response;

use super::limits::RequestId;
use super::problem::ProblemKind;

/// The tracing target of audit events (filter with `RUST_LOG=facegate::audit=info`).
pub const AUDIT_TARGET: &str = "facegate::audit";

/// The id of the API key a request was let in with: the first 8 hex digits of its SHA-256.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct KeyId(pub String);

/// What a handler learnt about the request, for its audit event.
#[derive(Debug, Default, Clone)]
struct Facts {
    subject: Option<String>,
    score: Option<f32>,
    threshold: Option<f32>,
    is_match: Option<bool>,
    model_version: Option<String>,
    templates_added: Option<usize>,
    candidates: Option<usize>,
    challenge: Option<String>,
    challenge_passed: Option<bool>,
    challenge_reason: Option<String>,
}

/// A request's audit facts, shared between the layer and the handler (a request extension).
#[derive(Debug, Clone, Default)]
pub struct Audit(Arc<Mutex<Facts>>);

/// The request's audit record (a detached one when the route is not audited).
impl<S: Send + Sync> FromRequestParts<S> for Audit {
    type Rejection = std::convert::Infallible;

    async fn from_request_parts(parts: &mut Parts, _state: &S) -> Result<Audit, Self::Rejection> {
        Ok(parts.extensions.get::<Audit>().cloned().unwrap_or_default())
    }
}

impl Audit {
    fn update(&self, f: impl FnOnce(&mut Facts)) {
        f(&mut self.0.lock().unwrap_or_else(|e| e.into_inner()));
    }

    pub fn subject(&self, subject: impl std::fmt::Display) {
        self.update(|facts| facts.subject = Some(subject.to_string()));
    }

    pub fn model_version(&self, version: &str) {
        self.update(|facts| facts.model_version = Some(version.to_string()));
    }

    pub fn decision(&self, score: f32, threshold: f32, is_match: bool) {
        self.update(|facts| (facts.score, facts.threshold, facts.is_match) = (Some(score), Some(threshold), Some(is_match)));
    }

    pub fn templates_added(&self, added: usize) {
        self.update(|facts| facts.templates_added = Some(added));
    }

    pub fn candidates(&self, candidates: usize) {
        self.update(|facts| facts.candidates = Some(candidates));
    }

    /// The liveness challenge the request issued or answers.
    pub fn challenge(&self, id: &str) {
        self.update(|facts| facts.challenge = Some(id.to_string()));
    }

    /// The verdict on the capture that answered the challenge.
    pub fn challenge_outcome(&self, passed: bool, reason: Option<&str>) {
        self.update(|facts| (facts.challenge_passed, facts.challenge_reason) = (Some(passed), reason.map(str::to_string)));
    }
}

/// The operation an audited route performs, by method and route template.
fn operation(method: &Method, route: &str) -> Option<&'static str> {
    match (method.as_str(), route) {
        ("POST", "/enroll") => Some("enroll"),
        ("POST", "/verify") => Some("verify"),
        ("POST", "/identify") => Some("identify"),
        ("DELETE", "/subjects/{id}") => Some("delete"),
        ("POST", "/liveness/challenge") => Some("challenge"),
        _ => None,
    }
}

/// The audit layer: emits one event per audited request once its response is made.
pub async fn record(mut request: Request, next: Next) -> Response {
    let route = request.extensions().get::<MatchedPath>().map(|p| p.as_str().to_string()).unwrap_or_default();
    let Some(op) = operation(request.method(), &route) else {
        return next.run(request).await;
    };
    let request_id = request.extensions().get::<RequestId>().map(|id| id.0.clone());
    let audit = Audit::default();
    request.extensions_mut().insert(audit.clone());
    let response = next.run(request).await;
    let facts = audit.0.lock().unwrap_or_else(|e| e.into_inner()).clone();
    let outcome = response.extensions().get::<ProblemKind>().map(|kind| kind.slug()).unwrap_or("ok");
    let key_id = response.extensions().get::<KeyId>().map(|k| k.0.as_str());
    let decision = facts.is_match.map(|m| if m { "match" } else { "no-match" });
    tracing::info!(
        target: AUDIT_TARGET,
        op,
        outcome,
        status = response.status().as_u16(),
        subject = facts.subject.as_deref(),
        decision,
        score = facts.score,
        threshold = facts.threshold,
        model_version = facts.model_version.as_deref(),
        templates_added = facts.templates_added,
        candidates = facts.candidates,
        challenge = facts.challenge.as_deref(),
        challenge_passed = facts.challenge_passed,
        challenge_reason = facts.challenge_reason.as_deref(),
        key_id,
        request_id = request_id.as_deref(),
        "audit"
    );
    response
}
