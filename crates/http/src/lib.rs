//! The HTTP API: an axum router over the service's use cases ([`Facegate`]).
//!
//! Requests are read and checked on the async runtime; image decoding and the face pipeline run
//! on the service's bounded blocking pool ([`WorkPool`]): a fixed number of workers and a bounded
//! queue, so an overload is refused with 503 instead of piling up. What a verification or an
//! identification decides is the service's; handlers only translate requests and responses. Every error is `application/problem+json`
//! ([`problem`]). `openapi.yaml` at the crate root describes exactly the routes of [`operations`];
//! the integration tests hold the two together.

use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use axum::extract::{DefaultBodyLimit, Request, State};
use axum::http::{Method, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{MethodRouter, delete, get, post};
use sha2::{Digest, Sha256};

use self::admission::BodyBudget;
use self::audit::KeyId;

use facegate_core::imaging::DecodeLimits;
use facegate_service::{Facegate, LivenessPolicy, ServiceConfig, WorkClass, WorkPool};
use facegate_store::Store;

pub use facegate_service::FaceEngine;

pub mod admission;
pub mod audit;
pub mod console;
mod handlers;
mod head_errors;
pub mod input;
mod inspect;
pub mod limits;
pub mod metrics;
pub mod problem;
pub mod server;
pub mod timeout;

pub use metrics::Metrics;
pub use problem::{Problem, ProblemKind};

/// The OpenAPI description served at `/openapi.yaml`.
pub const OPENAPI_YAML: &str = include_str!("../../../openapi.yaml");

/// Limits and settings of the API (made from `config::Settings`, where the defaults are).
#[derive(Debug, Clone)]
pub struct ApiConfig {
    /// Largest request body accepted, in bytes.
    pub max_body_bytes: usize,
    /// Pixel-count, dimension and decode-memory limits per photo.
    pub decode_limits: DecodeLimits,
    /// Most photos in one enrolment.
    pub max_images: usize,
    /// Whole-request deadline (queueing and reading the body included); exceeded → 504.
    pub request_timeout: Duration,
    /// Time from admission to the end of the body; exceeded → 408 (the client's fault).
    pub body_timeout: Duration,
    /// Photos analysed at once on the blocking pool.
    pub workers: usize,
    /// Probe requests (verify, identify, inspection) that may wait for a worker; beyond → 503.
    pub queue_depth: usize,
    /// Enrollments that may wait for a worker, a queue of their own; beyond → 503.
    pub enroll_queue_depth: usize,
    /// How long a request waits for a place when its queue is full, before the 503 (its body
    /// still unread). Zero refuses at once.
    pub admission_wait: Duration,
    /// Request bodies held in memory at once, in bytes (each admitted request counts its
    /// Content-Length, or the body limit without one); beyond → 503.
    pub max_buffered_bytes: usize,
    /// Accepted API keys; empty means the API is open (`config` refuses keys under 16 characters).
    pub api_keys: Vec<String>,
    /// The false match rate whose operating point decides a match unless a request asks otherwise.
    pub default_fmr: f64,
    /// Serve the web console at `/` (pages only; the API is the same either way).
    pub console: bool,
    /// The least quality an enrolment photo must have (else `low-quality`, 422).
    pub quality_policy: facegate_vision::quality::QualityPolicy,
    /// Liveness off, reported, or enforced (enrol, verify, identify refuse an attack:
    /// `presentation-attack`, 422).
    pub liveness: LivenessPolicy,
}

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

struct Shared {
    facegate: Facegate,
    config: ApiConfig,
    keys: ApiKeys,
    body_budget: BodyBudget,
    metrics: Arc<Metrics>,
}

/// Everything a handler needs: the service and the HTTP layer's own settings; cheap to clone.
#[derive(Clone)]
pub struct AppState(Arc<Shared>);

impl AppState {
    /// The service over `engine` and `store`, with its work pool sized by `config` and counted in
    /// the API's metrics.
    pub fn new(engine: Arc<dyn FaceEngine>, store: Store, config: ApiConfig) -> AppState {
        let metrics = Arc::new(Metrics::new());
        let pool = WorkPool::new(
            config.workers,
            config.queue_depth,
            config.enroll_queue_depth,
            metrics.queue_rejections.clone(),
            metrics.jobs_in_flight.clone(),
        );
        let service = ServiceConfig {
            decode_limits: config.decode_limits,
            max_images: config.max_images,
            quality_policy: config.quality_policy,
            default_fmr: config.default_fmr,
            liveness: config.liveness,
        };
        let facegate = Facegate::new(engine, store, pool, service);
        let keys = ApiKeys::new(&config.api_keys);
        let body_budget = BodyBudget::new(config.max_buffered_bytes, config.max_body_bytes);
        AppState(Arc::new(Shared { facegate, config, keys, body_budget, metrics }))
    }

    /// The use cases.
    pub fn facegate(&self) -> &Facegate {
        &self.0.facegate
    }

    pub fn store(&self) -> &Store {
        self.0.facegate.store()
    }

    pub fn metrics(&self) -> &Arc<Metrics> {
        &self.0.metrics
    }

    fn keys(&self) -> &ApiKeys {
        &self.0.keys
    }

    /// The most photos one enrolment takes (`ApiConfig::max_images`).
    pub(crate) fn max_images(&self) -> usize {
        self.0.config.max_images
    }
}

/// One operation of the API: method, route, whether it needs an API key, the admission queue of
/// the photo work it runs (none for the others), and its handler.
pub struct Operation {
    pub method: Method,
    pub path: &'static str,
    pub protected: bool,
    pub work: Option<WorkClass>,
    handler: MethodRouter<AppState>,
}

/// Every operation served. The router is built from this list alone, and `openapi.yaml` must
/// list exactly these (the integration tests check it).
pub fn operations() -> Vec<Operation> {
    let op = |method: Method, path, protected, handler| Operation { method, path, protected, work: None, handler };
    let work = |method: Method, path, class, handler| Operation { method, path, protected: true, work: Some(class), handler };
    vec![
        work(Method::POST, "/enroll", WorkClass::Enroll, post(handlers::enroll)),
        work(Method::POST, "/verify", WorkClass::Probe, post(handlers::verify)),
        work(Method::POST, "/identify", WorkClass::Probe, post(handlers::identify)),
        work(Method::POST, "/analyze", WorkClass::Probe, post(inspect::analyze)),
        work(Method::POST, "/avatar", WorkClass::Probe, post(inspect::avatar)),
        work(Method::POST, "/frontalize", WorkClass::Probe, post(inspect::frontalize)),
        op(Method::GET, "/subjects", true, get(handlers::list_subjects)),
        op(Method::GET, "/subjects/{id}", true, get(handlers::get_subject)),
        op(Method::DELETE, "/subjects/{id}", true, delete(handlers::delete_subject)),
        // Without a key, /health answers whether the service is up and nothing more.
        op(Method::GET, "/health", false, get(handlers::health)),
        op(Method::GET, "/metrics", true, get(handlers::metrics)),
        op(Method::GET, "/openapi.yaml", false, get(handlers::openapi)),
    ]
}

/// The application: routes, API keys, admission, audit, body limit, request timeout, metrics, and
/// the head limits, request id and `Cache-Control` of [`limits::edge`]. In request order:
/// edge → metrics → audit → API key → request timeout → admission → handler (the timeout inside
/// the audit, so that a request it ends is audited).
pub fn router(state: AppState) -> Router {
    let keys = state.0.keys.clone();
    let mut protected = Router::new();
    let mut public = Router::new();
    for operation in operations() {
        let handler = match operation.work {
            Some(class) => operation.handler.route_layer(middleware::from_fn_with_state((state.clone(), class), admission::admit)),
            None => operation.handler,
        };
        if operation.protected {
            protected = protected.route(operation.path, handler);
        } else {
            public = public.route(operation.path, handler);
        }
    }
    let timeout = middleware::from_fn_with_state(state.0.config.request_timeout, timeout::request_timeout);
    let protected = protected
        .route_layer(timeout.clone())
        .route_layer(middleware::from_fn_with_state(keys, require_api_key))
        .route_layer(middleware::from_fn(audit::record));
    let mut public = public.route_layer(timeout);
    if state.0.config.console {
        public = public.merge(console::routes());
    }
    let metrics = state.0.metrics.clone();
    Router::new()
        .merge(protected)
        .merge(public)
        .fallback(handlers::not_found)
        .method_not_allowed_fallback(handlers::method_not_allowed)
        .with_state(state.clone())
        .layer(DefaultBodyLimit::max(state.0.config.max_body_bytes))
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
