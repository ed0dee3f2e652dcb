//! The HTTP API: an axum router over the service (`crate::service`) and the template store.
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

use crate::core::imaging::DecodeLimits;
use crate::service::{PoolError, WorkPool};
use crate::store::Store;

pub use crate::service::FaceEngine;

pub mod console;
mod handlers;
pub mod input;
mod inspect;
pub mod metrics;
pub mod problem;

pub use metrics::Metrics;
pub use problem::{Problem, ProblemKind};

/// The OpenAPI description served at `/openapi.yaml`.
pub const OPENAPI_YAML: &str = include_str!("../../openapi.yaml");

/// Limits and settings of the API (made from `config::Settings`, where the defaults are).
#[derive(Debug, Clone)]
pub struct ApiConfig {
    /// Largest request body accepted, in bytes.
    pub max_body_bytes: usize,
    /// Pixel-count, dimension and decode-memory limits per photo.
    pub decode_limits: DecodeLimits,
    /// Most photos in one enrolment.
    pub max_images: usize,
    /// Whole-request deadline (reading the body included); exceeded → 504.
    pub request_timeout: Duration,
    /// Photos analysed at once on the blocking pool.
    pub workers: usize,
    /// Requests that may wait for a worker; beyond that → 503.
    pub queue_depth: usize,
    /// Accepted API keys; empty means the API is open.
    pub api_keys: Vec<String>,
    /// The false match rate whose operating point decides a match unless a request asks otherwise.
    pub default_fmr: f64,
    /// Serve the web console at `/` (pages only; the API is the same either way).
    pub console: bool,
    /// The least quality an enrolment photo must have (else `low-quality`, 422).
    pub quality_policy: crate::quality::QualityPolicy,
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
        let presented: [u8; 32] = Sha256::digest(key.as_bytes()).into();
        // Fold over all keys and bytes so timing does not reveal which key or byte differed.
        self.digests.iter().fold(false, |found, d| found | (d.iter().zip(&presented).fold(0u8, |acc, (a, b)| acc | (a ^ b)) == 0))
    }
}

struct Shared {
    engine: Arc<dyn FaceEngine>,
    store: Store,
    config: ApiConfig,
    pool: WorkPool,
    metrics: Arc<Metrics>,
}

impl From<PoolError> for Problem {
    fn from(error: PoolError) -> Problem {
        match error {
            PoolError::Overloaded => Problem::new(ProblemKind::Overloaded, error.to_string()),
            PoolError::Failed(e) => Problem::internal(e),
        }
    }
}

/// Everything a handler needs; cheap to clone.
#[derive(Clone)]
pub struct AppState(Arc<Shared>);

impl AppState {
    pub fn new(engine: Arc<dyn FaceEngine>, store: Store, config: ApiConfig) -> AppState {
        let metrics = Arc::new(Metrics::new());
        let pool = WorkPool::new(config.workers, config.queue_depth, metrics.queue_rejections.clone(), metrics.jobs_in_flight.clone());
        AppState(Arc::new(Shared { engine, store, config, pool, metrics }))
    }

    pub fn store(&self) -> &Store {
        &self.0.store
    }

    pub fn metrics(&self) -> &Arc<Metrics> {
        &self.0.metrics
    }
}

/// One operation of the API: method, route, whether it needs an API key, and its handler.
pub struct Operation {
    pub method: Method,
    pub path: &'static str,
    pub protected: bool,
    handler: MethodRouter<AppState>,
}

/// Every operation served. The router is built from this list alone, and `openapi.yaml` must
/// list exactly these (the integration tests check it).
pub fn operations() -> Vec<Operation> {
    let op = |method: Method, path, protected, handler| Operation { method, path, protected, handler };
    vec![
        op(Method::POST, "/enroll", true, post(handlers::enroll)),
        op(Method::POST, "/verify", true, post(handlers::verify)),
        op(Method::POST, "/identify", true, post(handlers::identify)),
        op(Method::POST, "/analyze", true, post(inspect::analyze)),
        op(Method::POST, "/avatar", true, post(inspect::avatar)),
        op(Method::POST, "/frontalize", true, post(inspect::frontalize)),
        op(Method::GET, "/subjects", true, get(handlers::list_subjects)),
        op(Method::GET, "/subjects/{id}", true, get(handlers::get_subject)),
        op(Method::DELETE, "/subjects/{id}", true, delete(handlers::delete_subject)),
        op(Method::GET, "/health", false, get(handlers::health)),
        op(Method::GET, "/metrics", false, get(handlers::metrics)),
        op(Method::GET, "/openapi.yaml", false, get(handlers::openapi)),
    ]
}

/// The application: routes, API keys, body limit, request timeout and metrics.
pub fn router(state: AppState) -> Router {
    let keys = ApiKeys::new(&state.0.config.api_keys);
    let mut protected = Router::new();
    let mut public = Router::new();
    for operation in operations() {
        if operation.protected {
            protected = protected.route(operation.path, operation.handler);
        } else {
            public = public.route(operation.path, operation.handler);
        }
    }
    let protected = protected.route_layer(middleware::from_fn_with_state(keys, require_api_key));
    if state.0.config.console {
        public = public.merge(console::routes());
    }
    let timeout = state.0.config.request_timeout;
    let metrics = state.0.metrics.clone();
    Router::new()
        .merge(protected)
        .merge(public)
        .fallback(handlers::not_found)
        .method_not_allowed_fallback(handlers::method_not_allowed)
        .with_state(state.clone())
        .layer(DefaultBodyLimit::max(state.0.config.max_body_bytes))
        .layer(middleware::from_fn_with_state(timeout, request_timeout))
        .layer(middleware::from_fn_with_state(metrics, metrics::track))
}

/// API keys are accepted as `Authorization: Bearer KEY` or `X-API-Key: KEY`.
async fn require_api_key(State(keys): State<ApiKeys>, request: Request, next: Next) -> Response {
    if keys.is_open() {
        return next.run(request).await;
    }
    let headers = request.headers();
    let bearer = headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("Bearer ").or_else(|| v.strip_prefix("bearer ")))
        .map(str::trim);
    let key = bearer.or_else(|| headers.get("x-api-key").and_then(|v| v.to_str().ok()).map(str::trim));
    match key {
        Some(key) if keys.accepts(key) => next.run(request).await,
        Some(_) => Problem::new(ProblemKind::Unauthorized, "the API key is not valid").into_response(),
        None => Problem::new(ProblemKind::Unauthorized, "an API key is required: send Authorization: Bearer KEY or X-API-Key: KEY")
            .into_response(),
    }
}

async fn request_timeout(State(timeout): State<Duration>, request: Request, next: Next) -> Response {
    match tokio::time::timeout(timeout, next.run(request)).await {
        Ok(response) => response,
        Err(_) => Problem::new(ProblemKind::Timeout, format!("the request took longer than {} s", timeout.as_secs_f64())).into_response(),
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
    }
}
