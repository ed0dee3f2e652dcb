//! The HTTP API: an axum router over the service's use cases ([`facegate_service::Facegate`]).
//!
//! Requests are read and checked on the async runtime; image decoding and the face pipeline run
//! on the service's bounded blocking pool ([`facegate_service::WorkPool`]): a fixed number of
//! workers and a bounded queue, so an overload is refused with 503 instead of piling up. What a
//! verification or an identification decides is the service's; handlers only translate requests
//! and responses. The JSON bodies are this crate's own types (`responses`), mapped from the
//! service's results field by field, so a change inside a stage or the store does not change the
//! API. Every error is `application/problem+json` ([`problem`]). `openapi.yaml` at the crate root
//! describes exactly the routes of [`operations`]; the integration tests hold the two together.

use axum::Router;
use axum::extract::{DefaultBodyLimit, Request, State};
use axum::http::{Method, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{MethodRouter, delete, get, post};
use sha2::{Digest, Sha256};

use self::audit::KeyId;

use facegate_service::WorkClass;

pub mod admission;
pub mod audit;
pub mod console;
mod handlers;
mod head_errors;
pub mod input;
mod inspect;
mod intake;
pub mod limits;
pub mod metrics;
pub mod problem;
pub mod rate;
mod responses;
pub mod server;
pub mod shedding;
mod state;
pub mod timeout;
pub mod trace;

pub use metrics::Metrics;
pub use problem::{Problem, ProblemKind};
pub use state::{ApiConfig, AppState};

/// The OpenAPI description served at `/openapi.yaml`.
pub const OPENAPI_YAML: &str = include_str!("../../../openapi.yaml");

/// SHA-256 digests of the accepted API keys, compared in constant time.
#[derive(Debug, Clone, Default)]
pub struct ApiKeys {
    digests: Vec<[u8; 32]>,
}

impl ApiKeys {
    pub fn new(keys: &[String]) -> ApiKeys {
        ApiKeys { digests: keys.iter().filter(|k| !k.is_empty()).map(|k| Sha256::digest(k.as_bytes()).into()).collect() }
    }

    /// No keys: every request is let in.
    pub fn is_open(&self) -> bool {
        self.digests.is_empty()
    }

    pub fn accepts(&self, key: &str) -> bool {
        self.key_id(key).is_some()
    }

    /// The id of `key` if it is accepted: the first 8 hex digits of its SHA-256, which names the
    /// key in the audit log without revealing it.
    pub fn key_id(&self, key: &str) -> Option<KeyId> {
        let presented: [u8; 32] = Sha256::digest(key.as_bytes()).into();
        // Fold over all keys and bytes so timing does not reveal which key or byte differed.
        let found =
            self.digests.iter().fold(false, |found, d| found | (d.iter().zip(&presented).fold(0u8, |acc, (a, b)| acc | (a ^ b)) == 0));
        found.then(|| KeyId(presented[..4].iter().map(|b| format!("{b:02x}")).collect()))
    }

    /// Does the request carry an accepted key (always, when the API is open)?
    pub fn admits(&self, headers: &axum::http::HeaderMap) -> bool {
        self.is_open() || presented_key(headers).is_some_and(|key| self.accepts(key))
    }
}

/// The key a request presents: `Authorization: Bearer KEY` or `X-API-Key: KEY`.
fn presented_key(headers: &axum::http::HeaderMap) -> Option<&str> {
    let bearer = headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("Bearer ").or_else(|| v.strip_prefix("bearer ")))
        .map(str::trim);
    bearer.or_else(|| headers.get("x-api-key").and_then(|v| v.to_str().ok()).map(str::trim))
}

/// One operation of the API: method, route, whether it needs an API key, the admission queue of
/// the photo work it runs (none for the others), whether each client address has a rate of it
/// ([`rate::limit_challenges`]), and its handler.
pub struct Operation {
    pub method: Method,
    pub path: &'static str,
    pub protected: bool,
    pub work: Option<WorkClass>,
    pub rate_limited: bool,
    handler: MethodRouter<AppState>,
}

/// Every operation served. The router is built from this list alone, and `openapi.yaml` must
/// list exactly these (the integration tests check it).
pub fn operations() -> Vec<Operation> {
    let op = |method: Method, path, protected, handler| Operation { method, path, protected, work: None, rate_limited: false, handler };
    let work =
        |method: Method, path, class, handler| Operation { method, path, protected: true, work: Some(class), rate_limited: false, handler };
    vec![
        work(Method::POST, "/enroll", WorkClass::Enroll, post(handlers::enroll)),
        work(Method::POST, "/verify", WorkClass::Probe, post(handlers::verify)),
        work(Method::POST, "/identify", WorkClass::Probe, post(handlers::identify)),
        work(Method::POST, "/analyze", WorkClass::Probe, post(inspect::analyze)),
        work(Method::POST, "/avatar", WorkClass::Probe, post(inspect::avatar)),
        work(Method::POST, "/frontalize", WorkClass::Probe, post(inspect::frontalize)),
        // Each issue stores a row: a rate per address, and a cap on the rows (the service's).
        Operation { rate_limited: true, ..op(Method::POST, "/liveness/challenge", true, post(handlers::issue_challenge)) },
        op(Method::GET, "/subjects", true, get(handlers::list_subjects)),
        op(Method::GET, "/subjects/{id}", true, get(handlers::get_subject)),
        op(Method::DELETE, "/subjects/{id}", true, delete(handlers::delete_subject)),
        // Without a key, /health answers whether the service is up and nothing more.
        op(Method::GET, "/health", false, get(handlers::health)),
        // The process answers: no database, no work pool (an orchestrator's liveness probe).
        op(Method::GET, "/livez", false, get(handlers::livez)),
        op(Method::GET, "/metrics", true, get(handlers::metrics)),
        op(Method::GET, "/openapi.yaml", false, get(handlers::openapi)),
    ]
}

/// The application: routes, API keys, admission, audit, body limit, request timeout, metrics, and
/// the head limits, request id and `Cache-Control` of [`limits::edge`]. In request order:
/// edge → metrics → request span (`trace`) → audit → API key → request timeout → admission →
/// handler (the timeout inside
/// the audit, so that a request it ends is audited).
pub fn router(state: AppState) -> Router {
    let keys = state.keys().clone();
    let mut protected = Router::new();
    let mut public = Router::new();
    for operation in operations() {
        let handler = match operation.work {
            Some(class) => operation.handler.route_layer(middleware::from_fn_with_state((state.clone(), class), admission::admit)),
            None if operation.rate_limited => {
                operation.handler.route_layer(middleware::from_fn_with_state(state.clone(), rate::limit_challenges))
            }
            None => operation.handler,
        };
        if operation.protected {
            protected = protected.route(operation.path, handler);
        } else {
            public = public.route(operation.path, handler);
        }
    }
    let timeout = middleware::from_fn_with_state(state.config().request_timeout, timeout::request_timeout);
    let protected = protected
        .route_layer(timeout.clone())
        .route_layer(middleware::from_fn_with_state(keys, require_api_key))
        .route_layer(middleware::from_fn(audit::record))
        .route_layer(middleware::from_fn(trace::request_span));
    let mut public = public.route_layer(timeout).route_layer(middleware::from_fn(trace::request_span));
    if state.config().console {
        public = public.merge(console::routes());
    }
    let metrics = state.metrics().clone();
    Router::new()
        .merge(protected)
        .merge(public)
        .fallback(handlers::not_found)
        .method_not_allowed_fallback(handlers::method_not_allowed)
        .with_state(state.clone())
        .layer(DefaultBodyLimit::max(state.config().max_body_bytes))
        .layer(middleware::from_fn_with_state(metrics, metrics::track))
        .layer(middleware::from_fn(limits::edge))
}

/// API keys are accepted as `Authorization: Bearer KEY` or `X-API-Key: KEY`. The accepted key's
/// id goes into the response's extensions for the audit log.
async fn require_api_key(State(keys): State<ApiKeys>, request: Request, next: Next) -> Response {
    if keys.is_open() {
        return next.run(request).await;
    }
    match presented_key(request.headers()).map(|key| keys.key_id(key)) {
        Some(Some(key_id)) => {
            let mut response = next.run(request).await;
            response.extensions_mut().insert(key_id);
            response
        }
        Some(None) => Problem::new(ProblemKind::Unauthorized, "the API key is not valid").into_response(),
        None => Problem::new(ProblemKind::Unauthorized, "an API key is required: send Authorization: Bearer KEY or X-API-Key: KEY")
            .into_response(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn api_keys_accept_only_listed_keys() {
        let keys = ApiKeys::new(&["alpha".into(), "beta".into(), String::new()]);
        assert!(!keys.is_open());
        assert!(keys.accepts("alpha") && keys.accepts("beta"));
        assert!(!keys.accepts("") && !keys.accepts("alph") && !keys.accepts("gamma"));
        assert!(ApiKeys::new(&[]).is_open());
        let id = keys.key_id("alpha").unwrap().0;
        assert_eq!(id, "8ed3f6ad", "the first 8 hex digits of SHA-256(alpha)");
        assert!(keys.key_id("gamma").is_none());
    }
}
