//! OpenTelemetry traces of `facegate serve`, set up by the standard `OTEL_*` variables: with
//! `OTEL_EXPORTER_OTLP_ENDPOINT` (or `OTEL_EXPORTER_OTLP_TRACES_ENDPOINT`) set, every request's
//! span and its stages' spans go to that OTLP/HTTP receiver as protobuf (the SDK reads the
//! endpoint, headers, timeout, batch and sampler settings itself: `OTEL_EXPORTER_OTLP_HEADERS`,
//! `OTEL_BSP_SCHEDULE_DELAY`, `OTEL_TRACES_SAMPLER`, …), named `OTEL_SERVICE_NAME` (default
//! `facegate`), and a request's W3C `traceparent` is continued. Without an endpoint nothing is
//! set up: no layer, no propagator, no exporter thread.

use anyhow::{Context, bail};
use opentelemetry::trace::TracerProvider as _;
use opentelemetry_otlp::{Protocol, SpanExporter, WithExportConfig};
use opentelemetry_sdk::Resource;
use opentelemetry_sdk::propagation::TraceContextPropagator;
use opentelemetry_sdk::trace::SdkTracerProvider;

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
