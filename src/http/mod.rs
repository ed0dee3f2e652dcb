//! The HTTP API: an axum router over the face pipeline and the template store.
//!
//! Requests are read and checked on the async runtime; image decoding and the face pipeline run
//! on a bounded blocking pool ([`WorkPool`]): a fixed number of workers and a bounded queue, so
//! an overload is refused with 503 instead of piling up. Every error is `application/problem+json`
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
use tokio::sync::Semaphore;

use crate::core::imaging::{DecodeLimits, Photo};
use crate::pipeline::{FaceAnalysis, Pipeline, PipelineError};
use crate::recognize::{OperatingPoint, Template};
use crate::store::Store;

mod handlers;
pub mod input;
pub mod metrics;
pub mod problem;

pub use metrics::Metrics;
pub use problem::{Problem, ProblemKind};

/// The OpenAPI description served at `/openapi.yaml`.
pub const OPENAPI_YAML: &str = include_str!("../../openapi.yaml");

/// The face work behind the API: the real [`Pipeline`] in production. A seam so that the HTTP
/// layer (decoding, limits, errors, storage) can be tested on its own.
pub trait FaceEngine: Send + Sync + 'static {
    /// Detect, landmark, pose-correct and template the largest face of `photo`.
    fn analyze(&self, photo: &Photo) -> Result<FaceAnalysis, PipelineError>;
    /// The recognition model version stamped on every template this engine makes.
    fn model_version(&self) -> &str;
    /// Score of a probe against one subject's templates (higher is more alike).
    fn score(&self, probe: &Template, enrolled: &[Template]) -> f32;
    /// The calibrated operating point closest to `fmr` for a subject with `enrolled` templates
    /// (its score is the best of them, so the threshold depends on how many there are).
    fn operating_point(&self, fmr: f64, enrolled: usize) -> OperatingPoint;
}

impl FaceEngine for Pipeline {
    fn analyze(&self, photo: &Photo) -> Result<FaceAnalysis, PipelineError> {
        Pipeline::analyze(self, photo)
    }
    fn model_version(&self) -> &str {
        self.recognizer.model_version()
    }
    fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
        self.recognizer.score(probe, enrolled)
    }
    fn operating_point(&self, fmr: f64, enrolled: usize) -> OperatingPoint {
        self.recognizer.operating_point(fmr, enrolled)
    }
}

/// Limits and settings of the API.
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
}

impl Default for ApiConfig {
    fn default() -> Self {
        ApiConfig {
            max_body_bytes: 16 << 20,
            decode_limits: DecodeLimits { max_width: 8192, max_height: 8192, max_pixels: 16_000_000, max_alloc_bytes: 256 << 20 },
            max_images: 16,
            request_timeout: Duration::from_secs(30),
            workers: std::thread::available_parallelism().map(|n| n.get()).unwrap_or(2),
            queue_depth: 64,
            api_keys: Vec::new(),
            default_fmr: 1e-3,
        }
    }
}

/// A bounded pool for CPU work: `workers` jobs run at once on tokio's blocking threads, at most
/// `queue_depth` more wait, and any further job is refused at once with `overloaded`.
#[derive(Debug, Clone)]
pub struct WorkPool {
    admitted: Arc<Semaphore>,
    running: Arc<Semaphore>,
}

impl WorkPool {
    pub fn new(workers: usize, queue_depth: usize) -> WorkPool {
        let workers = workers.max(1);
        WorkPool { admitted: Arc::new(Semaphore::new(workers + queue_depth)), running: Arc::new(Semaphore::new(workers)) }
    }

    /// Run `job` on the pool. The permits move into the job, so a request that times out while
    /// its job runs still holds its place until the job ends: the bound holds.
    pub async fn run<T: Send + 'static>(&self, metrics: &Metrics, job: impl FnOnce() -> T + Send + 'static) -> Result<T, Problem> {
        let Ok(admitted) = self.admitted.clone().try_acquire_owned() else {
            metrics.queue_rejections.inc();
            return Err(Problem::new(ProblemKind::Overloaded, "the work queue is full; retry shortly"));
        };
        let running = self.running.clone().acquire_owned().await.map_err(Problem::internal)?;
        // Released when the job ends, even by a panic.
        let held = InFlight { _permits: (admitted, running), gauge: metrics.jobs_in_flight.clone() };
        held.gauge.inc();
        tokio::task::spawn_blocking(move || {
            let _held = held;
            job()
        })
        .await
        .map_err(Problem::internal)
    }
}

struct InFlight {
    _permits: (tokio::sync::OwnedSemaphorePermit, tokio::sync::OwnedSemaphorePermit),
    gauge: prometheus_client::metrics::gauge::Gauge,
}

impl Drop for InFlight {
    fn drop(&mut self) {
        self.gauge.dec();
    }
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

/// Everything a handler needs; cheap to clone.
#[derive(Clone)]
pub struct AppState(Arc<Shared>);

impl AppState {
    pub fn new(engine: Arc<dyn FaceEngine>, store: Store, config: ApiConfig) -> AppState {
        let pool = WorkPool::new(config.workers, config.queue_depth);
        AppState(Arc::new(Shared { engine, store, config, pool, metrics: Arc::new(Metrics::new()) }))
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

    #[tokio::test]
    async fn the_pool_refuses_work_beyond_its_queue() {
        let pool = WorkPool::new(1, 1);
        let metrics = Metrics::new();
        let (release, wait) = std::sync::mpsc::channel::<()>();
        let wait = Arc::new(std::sync::Mutex::new(wait));
        let blocker = {
            let (pool, wait) = (pool.clone(), wait.clone());
            tokio::spawn(async move {
                let m = Metrics::new();
                pool.run(&m, move || wait.lock().unwrap().recv().unwrap()).await
            })
        };
        // Let the first job take the only worker, then queue a second.
        while pool.running.available_permits() > 0 {
            tokio::task::yield_now().await;
        }
        let queued = {
            let pool = pool.clone();
            tokio::spawn(async move { pool.run(&Metrics::new(), || 7).await })
        };
        while pool.admitted.available_permits() > 0 {
            tokio::task::yield_now().await;
        }
        let refused = pool.run(&metrics, || 0).await.unwrap_err();
        assert_eq!(refused.kind, ProblemKind::Overloaded);
        assert_eq!(metrics.queue_rejections.get(), 1);
        release.send(()).unwrap();
        blocker.await.unwrap().unwrap();
        assert_eq!(queued.await.unwrap().unwrap(), 7);
    }
}
