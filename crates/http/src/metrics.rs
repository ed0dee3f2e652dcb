//! Prometheus metrics: requests by route and status, request latency, pipeline stage timings,
//! the work queue, and the number of enrolled subjects and templates.

use std::sync::Arc;
use std::time::Instant;

use axum::extract::{MatchedPath, Request, State};
use axum::middleware::Next;
use axum::response::Response;
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;

use facegate_vision::pipeline::StageTimings;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct RequestLabels {
    pub method: String,
    /// The route template (`/subjects/{id}`), never the raw path, to bound cardinality.
    pub route: String,
    pub status: u16,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct RouteLabels {
    pub route: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct StageLabels {
    pub stage: &'static str,
}

type HistogramFamily<L> = Family<L, Histogram, fn() -> Histogram>;

fn latency_histogram() -> Histogram {
    // 0.5 ms .. ~16 s
    Histogram::new(exponential_buckets(0.0005, 2.0, 16))
}

pub struct Metrics {
    registry: Registry,
    pub requests: Family<RequestLabels, Counter>,
    pub latency: HistogramFamily<RouteLabels>,
    pub stages: HistogramFamily<StageLabels>,
    pub queue_rejections: Counter,
    pub jobs_in_flight: Gauge,
    pub subjects: Gauge,
    pub templates: Gauge,
}

impl Metrics {
    pub fn new() -> Metrics {
        let mut registry = Registry::with_prefix("facegate");
        let requests = Family::<RequestLabels, Counter>::default();
        registry.register("http_requests", "HTTP requests by method, route and status", requests.clone());
        let latency: HistogramFamily<RouteLabels> = Family::new_with_constructor(latency_histogram);
        registry.register("http_request_duration_seconds", "HTTP request latency by route", latency.clone());
        let stages: HistogramFamily<StageLabels> = Family::new_with_constructor(latency_histogram);
        registry.register("pipeline_stage_duration_seconds", "Time spent per pipeline stage and photo", stages.clone());
        let queue_rejections = Counter::default();
        registry.register("queue_rejections", "Requests refused with 503 because the work queue was full", queue_rejections.clone());
        let jobs_in_flight = Gauge::default();
        registry.register("jobs_in_flight", "Image jobs queued or running on the blocking pool", jobs_in_flight.clone());
        let subjects = Gauge::default();
        registry.register("subjects", "Enrolled subjects", subjects.clone());
        let templates = Gauge::default();
        registry.register("templates", "Stored templates", templates.clone());
        Metrics { registry, requests, latency, stages, queue_rejections, jobs_in_flight, subjects, templates }
    }

    /// Record the stage timings of one analysed photo (decode time included).
    pub fn observe_stages(&self, decode_ms: f64, timings: &StageTimings) {
        for (stage, ms) in [
            ("decode", decode_ms),
            ("detect", timings.detect_ms),
            ("landmarks", timings.landmarks_ms),
            ("morph", timings.morph_ms),
            ("template", timings.template_ms),
            ("quality", timings.quality_ms),
            ("liveness", timings.liveness_ms),
        ] {
            self.stages.get_or_create(&StageLabels { stage }).observe(ms / 1e3);
        }
    }

    /// The text exposition format.
    pub fn encode(&self) -> String {
        let mut out = String::new();
        prometheus_client::encoding::text::encode(&mut out, &self.registry).expect("writing to a String cannot fail");
        out
    }
}

impl Default for Metrics {
    fn default() -> Self {
        Metrics::new()
    }
}

/// Middleware counting every response (including refusals by the other layers) and its latency.
pub async fn track(State(metrics): State<Arc<Metrics>>, request: Request, next: Next) -> Response {
    let start = Instant::now();
    let method = request.method().to_string();
    let route = request.extensions().get::<MatchedPath>().map(|p| p.as_str().to_string()).unwrap_or_else(|| "unmatched".into());
    let response = next.run(request).await;
    let status = response.status().as_u16();
    metrics.requests.get_or_create(&RequestLabels { method, route: route.clone(), status }).inc();
    metrics.latency.get_or_create(&RouteLabels { route }).observe(start.elapsed().as_secs_f64());
    response
}
