//! OpenTelemetry traces of `facegate serve`, set up by the standard `OTEL_*` variables: with
//! `OTEL_EXPORTER_OTLP_ENDPOINT` (or `OTEL_EXPORTER_OTLP_TRACES_ENDPOINT`) set, every request's
//! span and its stages' spans go to that OTLP/HTTP receiver as protobuf (the SDK reads the
//! endpoint, headers, timeout, batch and sampler settings itself: `OTEL_EXPORTER_OTLP_HEADERS`,
//! `OTEL_BSP_SCHEDULE_DELAY`, `OTEL_TRACES_SAMPLER`, …), named `OTEL_SERVICE_NAME` (default
//! `facegate`), and a request's W3C `traceparent` is continued. Without an endpoint nothing is
//! set up: no layer, no propagator, no exporter thread.
//!
//! A failed export (a collector refused, unreachable or slow) costs the service nothing but the
//! batch; it is logged as a warning at most once per [`FAILURE_LOG_INTERVAL`], with how many
//! batches and spans were lost since the last such line, so that a collector down for an hour
//! writes a line a minute rather than ten a second, and never nothing.

use std::sync::Mutex;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use opentelemetry::trace::TracerProvider as _;
use opentelemetry_otlp::{Protocol, SpanExporter, WithExportConfig};
use opentelemetry_sdk::Resource;
use opentelemetry_sdk::error::OTelSdkResult;
use opentelemetry_sdk::propagation::TraceContextPropagator;
use opentelemetry_sdk::trace::{SdkTracerProvider, SpanData};

use crate::config::TraceSettings;

/// The service's name in its traces unless `OTEL_SERVICE_NAME` names it.
pub const DEFAULT_SERVICE_NAME: &str = "facegate";

/// The exporting tracer provider; flushed and shut down when dropped.
pub struct Traces {
    provider: SdkTracerProvider,
}

impl Traces {
    /// The exporter `settings` ask for; `None` when no endpoint is set (or `OTEL_SDK_DISABLED`).
    pub fn start(settings: &TraceSettings) -> anyhow::Result<Option<Traces>> {
        if settings.sdk_disabled || settings.endpoint.is_none() {
            return Ok(None);
        }
        match settings.protocol.as_deref() {
            None | Some("http/protobuf") => {}
            Some(other) => bail!(
                "OTEL_EXPORTER_OTLP_PROTOCOL={other} is not supported: facegate exports traces over OTLP/HTTP as protobuf \
                 (http/protobuf)"
            ),
        }
        let exporter = SpanExporter::builder()
            .with_http()
            .with_protocol(Protocol::HttpBinary)
            .build()
            .context("cannot set up the OTLP trace exporter (OTEL_EXPORTER_OTLP_ENDPOINT)")?;
        let mut resource = Resource::builder();
        if settings.service_name.is_none() {
            resource = resource.with_service_name(DEFAULT_SERVICE_NAME);
        }
        let exporter = LoggedExporter { inner: exporter, failures: Mutex::default() };
        let provider = SdkTracerProvider::builder().with_batch_exporter(exporter).with_resource(resource.build()).build();
        opentelemetry::global::set_text_map_propagator(TraceContextPropagator::new());
        Ok(Some(Traces { provider }))
    }

    /// The tracing layer that turns spans into OpenTelemetry spans of this provider.
    pub fn layer<S>(&self) -> impl tracing_subscriber::Layer<S> + use<S>
    where
        S: tracing::Subscriber + for<'span> tracing_subscriber::registry::LookupSpan<'span>,
    {
        tracing_opentelemetry::layer().with_tracer(self.provider.tracer("facegate"))
    }
}

impl Drop for Traces {
    fn drop(&mut self) {
        // Exports what is still batched.
        let _ = self.provider.shutdown();
    }
}

/// Longest time between two log lines about failed exports.
pub const FAILURE_LOG_INTERVAL: Duration = Duration::from_secs(60);

/// The failed exports since the last line logged about them.
#[derive(Debug, Default)]
struct FailureLog {
    last_line: Option<Instant>,
    batches: u64,
    spans: u64,
}

impl FailureLog {
    /// Counts a failed export of `spans` spans at `now`; the line to log when one is due (the
    /// first failure, then at most one per [`FAILURE_LOG_INTERVAL`]), which starts a new count.
    fn failed(&mut self, spans: usize, error: &str, now: Instant) -> Option<String> {
        self.batches += 1;
        self.spans += spans as u64;
        if self.last_line.is_some_and(|at| now.duration_since(at) < FAILURE_LOG_INTERVAL) {
            return None;
        }
        let line = format!(
            "trace export failed: {error}; {} batch(es), {} span(s) lost since the last such line (logged at most once per {} s)",
            self.batches,
            self.spans,
            FAILURE_LOG_INTERVAL.as_secs()
        );
        (self.last_line, self.batches, self.spans) = (Some(now), 0, 0);
        Some(line)
    }
}

/// The OTLP exporter, its failures logged through [`FailureLog`].
#[derive(Debug)]
struct LoggedExporter {
    inner: SpanExporter,
    failures: Mutex<FailureLog>,
}

impl opentelemetry_sdk::trace::SpanExporter for LoggedExporter {
    async fn export(&self, batch: Vec<SpanData>) -> OTelSdkResult {
        let spans = batch.len();
        let result = self.inner.export(batch).await;
        if let Err(e) = &result {
            let line = self.failures.lock().unwrap_or_else(|e| e.into_inner()).failed(spans, &e.to_string(), Instant::now());
            if let Some(line) = line {
                tracing::warn!("{line}");
            }
        }
        result
    }

    fn shutdown_with_timeout(&mut self, timeout: Duration) -> OTelSdkResult {
        self.inner.shutdown_with_timeout(timeout)
    }

    fn force_flush(&mut self) -> OTelSdkResult {
        self.inner.force_flush()
    }

    fn set_resource(&mut self, resource: &Resource) {
        self.inner.set_resource(resource);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn export_failures_are_logged_once_per_interval_with_what_was_lost_meanwhile() {
        let mut log = FailureLog::default();
        let start = Instant::now();
        let first = log.failed(10, "refused", start).expect("the first failure is logged");
        assert!(first.contains("refused") && first.contains("1 batch(es), 10 span(s)"), "{first}");
        for i in 1..=5 {
            assert_eq!(log.failed(4, "refused", start + Duration::from_secs(i)), None);
        }
        let next = log.failed(2, "timed out", start + FAILURE_LOG_INTERVAL).expect("an interval later");
        assert!(next.contains("timed out") && next.contains("6 batch(es), 22 span(s)"), "{next}");
        assert_eq!(log.failed(1, "refused", start + FAILURE_LOG_INTERVAL + Duration::from_secs(1)), None);
    }
}
