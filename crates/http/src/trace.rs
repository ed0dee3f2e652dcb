//! A span per request (OpenTelemetry's server span when the binary exports traces), continuing
//! the caller's W3C trace context (`traceparent`, `tracestate`) when it sends one. Its attributes
//! are the route template (never the path: it can hold a subject id), the method, the request id,
//! the status and the outcome (`ok` or the problem's type); never a photo, a template or a subject.
//! The stages a request runs open their own spans inside it (`facegate_vision`'s pipeline, the
//! service's decode, store and gallery), on the work pool's threads too.
//!
//! Without an exporter no OpenTelemetry layer is installed: the propagator is the no-op one and
//! the span is tracing's own, as cheap as any other.

use axum::extract::{MatchedPath, Request};
use axum::http::HeaderMap;
use axum::middleware::Next;
use axum::response::Response;
use opentelemetry::propagation::Extractor;
use tracing::Instrument;
use tracing::field::Empty;
use tracing_opentelemetry::OpenTelemetrySpanExt;

use crate::limits::RequestId;
use crate::problem::ProblemKind;

/// The request's headers as the propagator reads them.
struct Headers<'a>(&'a HeaderMap);

impl Extractor for Headers<'_> {
    fn get(&self, key: &str) -> Option<&str> {
        self.0.get(key).and_then(|v| v.to_str().ok())
    }

    fn keys(&self) -> Vec<&str> {
        self.0.keys().map(|k| k.as_str()).collect()
    }
}

/// Run the request inside its span (a route layer: the route template is known).
pub async fn request_span(request: Request, next: Next) -> Response {
    let route = request.extensions().get::<MatchedPath>().map_or("", |p| p.as_str()).to_owned();
    let method = request.method().as_str().to_owned();
    let id = request.extensions().get::<RequestId>().map(|id| id.0.clone()).unwrap_or_default();
    let span = tracing::info_span!(
        "request",
        otel.name = %format_args!("{method} {route}"),
        otel.kind = "server",
        otel.status_code = Empty,
        http.request.method = %method,
        http.route = %route,
        request_id = %id,
        http.response.status_code = Empty,
        outcome = Empty,
    );
    let parent = opentelemetry::global::get_text_map_propagator(|propagator| propagator.extract(&Headers(request.headers())));
    let _ = span.set_parent(parent);
    let response = next.run(request).instrument(span.clone()).await;
    let status = response.status();
    let outcome = response.extensions().get::<ProblemKind>().map_or("ok", |kind| kind.slug());
    span.record("http.response.status_code", status.as_u16());
    span.record("outcome", outcome);
    if status.is_server_error() {
        span.record("otel.status_code", "error");
    }
    response
}
