//! What every handler is handed: the service ([`Facegate`]) and the HTTP layer's settings
//! ([`ApiConfig`]), with what the router derives from them once (the API keys' digests, the body
//! budget, the metrics).

use std::sync::Arc;
use std::time::Duration;

use facegate_service::{FaceEngine, Facegate, ServiceConfig, WorkPool};
use facegate_store::Store;

use super::admission::BodyBudget;
use super::rate::RateLimiter;
use super::{ApiKeys, Metrics};

/// Limits and settings of the API (made from `config::Settings`, where the defaults are).
#[derive(Debug, Clone)]
pub struct ApiConfig {
    /// Largest request body accepted, in bytes.
    pub max_body_bytes: usize,
    /// Whole-request deadline (queueing and reading the body included); exceeded → 504.
    pub request_timeout: Duration,
    /// Time from the start of the body to its end; exceeded → 408 (the client's fault).
    pub body_timeout: Duration,
    /// Time a body may take before `min_body_rate` applies.
    pub body_grace: Duration,
    /// Least rate of a body after `body_grace`, bytes per second over the last `body_grace` (0:
    /// none); slower → 408.
    pub min_body_rate: u64,
    /// Request bodies awaited (a head waiting for its first byte) or arriving at once from one
    /// client address (IPv6: its /64); beyond → 503.
    pub max_uploads_per_address: usize,
    /// `POST /liveness/challenge` per second per client address (IPv6: its /64), in bursts of
    /// twice as many; beyond → 429 `too-many-challenges`. 0: no limit.
    pub challenge_rate: f64,
    /// Photos analysed at once on the blocking pool.
    pub workers: usize,
    /// Probe requests (verify, identify, inspection) that may wait for a worker; beyond → 503.
    pub queue_depth: usize,
    /// Enrolments that may wait for a worker, a queue of their own; beyond → 503.
    pub enroll_queue_depth: usize,
    /// How long a request waits, before the 503, for room when its queue is full (its body still
    /// unread), for a place among its client address's arriving bodies, and for its place in the
    /// queue once its body has arrived. Zero refuses at once.
    pub admission_wait: Duration,
    /// Request bodies held in memory at once, in bytes (each request counts what has arrived of
    /// its body, from its first byte until it is answered); beyond → 503.
    pub max_buffered_bytes: usize,
    /// Of `max_buffered_bytes`, most held by the bodies of one client address (IPv6: its /64);
    /// beyond → 503.
    pub max_buffered_per_address: usize,
    /// Accepted API keys; empty means the API is open (`config` refuses keys under 16 characters).
    pub api_keys: Vec<String>,
    /// Serve the web console at `/` (pages only; the API is the same either way).
    pub console: bool,
    /// The use cases' policies: decode limits, most photos per enrolment (which also bounds a
    /// JSON body's `images` as it is read), the enrolment quality policy, the default false match
    /// rate and the liveness policy. Handed to the service as they are.
    pub service: ServiceConfig,
}

/// The shared part of [`AppState`]. Its fields are the crate's: the admission layer reads the
/// settings, the pool, the body budget and the rejection counter directly.
pub(crate) struct Shared {
    pub(crate) facegate: Facegate,
    pub(crate) config: ApiConfig,
    pub(crate) keys: ApiKeys,
    pub(crate) body_budget: BodyBudget,
    pub(crate) challenge_rate: RateLimiter,
    pub(crate) metrics: Arc<Metrics>,
}

/// Everything a handler needs: the service and the HTTP layer's own settings; cheap to clone.
#[derive(Clone)]
pub struct AppState(pub(crate) Arc<Shared>);

impl AppState {
    /// The service over `engine` and `store`, with the policies of `config.service` and a work
    /// pool sized by `config`, counted in the API's metrics.
    pub fn new(engine: Arc<dyn FaceEngine>, store: Store, config: ApiConfig) -> AppState {
        let metrics = Arc::new(Metrics::new());
        let pool = WorkPool::new(
            config.workers,
            config.queue_depth,
            config.enroll_queue_depth,
            metrics.queue_rejections.clone(),
            metrics.jobs_in_flight.clone(),
        );
        // The service owns its policies; the state keeps the whole configuration it was made from.
        let facegate = Facegate::new(engine, store, pool, config.service.clone());
        let keys = ApiKeys::new(&config.api_keys);
        let body_budget = BodyBudget::new(config.max_buffered_bytes, config.max_buffered_per_address, config.max_body_bytes);
        let challenge_rate = RateLimiter::new(config.challenge_rate, (config.challenge_rate * 2.0).ceil().min(f64::from(u32::MAX)) as u32);
        AppState(Arc::new(Shared { facegate, config, keys, body_budget, challenge_rate, metrics }))
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

    /// The settings the state was made from.
    pub fn config(&self) -> &ApiConfig {
        &self.0.config
    }

    pub(crate) fn keys(&self) -> &ApiKeys {
        &self.0.keys
    }

    /// The most photos one enrolment takes (`ServiceConfig::max_images`).
    pub(crate) fn max_images(&self) -> usize {
        self.0.config.service.max_images
    }
}
