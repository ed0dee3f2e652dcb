//! OpenTelemetry traces through the real binary: an OTLP/HTTP receiver started here (axum on a
//! free port; the protobuf decoded with `opentelemetry-proto`'s types), `facegate serve` pointed
//! at it by `OTEL_EXPORTER_OTLP_ENDPOINT`, and a `/verify` sent with a W3C `traceparent`. Its
//! spans arrive under that trace id: the request's server span, a child of the caller's span,
//! with the route, the request id and the outcome, and the stages' spans inside it; none carries
//! a photo, a template or the subject. A collector that refuses every export costs no request,
//! and its failures are logged, once per interval.

use std::collections::BTreeSet;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::body::Bytes;
use axum::extract::State;
use opentelemetry_proto::tonic::collector::trace::v1::ExportTraceServiceRequest;
use opentelemetry_proto::tonic::common::v1::any_value::Value as AnyValue;
use opentelemetry_proto::tonic::trace::v1::Span;
use prost::Message;

use crate::fail_closed::{Scratch, Served};
use crate::support::imm;

type Received = Arc<Mutex<Vec<ExportTraceServiceRequest>>>;

/// An OTLP/HTTP trace receiver on a free loopback port: every export it is sent, decoded.
async fn receiver() -> (String, Received) {
    let received: Received = Arc::default();
    async fn export(State(received): State<Received>, body: Bytes) -> axum::http::StatusCode {
        match ExportTraceServiceRequest::decode(body) {
            Ok(request) => {
                received.lock().unwrap().push(request);
                axum::http::StatusCode::OK
            }
            Err(_) => axum::http::StatusCode::BAD_REQUEST,
        }
    }
    let app = axum::Router::new().route("/v1/traces", axum::routing::post(export)).with_state(received.clone());
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    tokio::spawn(async move { axum::serve(listener, app).await.unwrap() });
    (url, received)
}

/// Every span received so far, with its resource's `service.name`.
fn spans(received: &Received) -> Vec<(String, Span)> {
    let mut out = Vec::new();
    for request in received.lock().unwrap().iter() {
        for resource in &request.resource_spans {
            let service = resource.resource.as_ref().and_then(|r| r.attributes.iter().find(|a| a.key == "service.name"));
            let service = service.and_then(|a| a.value.as_ref()).and_then(|v| v.value.as_ref());
            let name = match service {
                Some(AnyValue::StringValue(s)) => s.clone(),
                _ => String::new(),
            };
            for scope in &resource.scope_spans {
                out.extend(scope.spans.iter().map(|span| (name.clone(), span.clone())));
            }
        }
    }
    out
}

fn attribute(span: &Span, key: &str) -> Option<String> {
    let value = span.attributes.iter().find(|a| a.key == key)?.value.as_ref()?.value.as_ref()?;
    Some(match value {
        AnyValue::StringValue(s) => s.clone(),
        AnyValue::IntValue(i) => i.to_string(),
        other => format!("{other:?}"),
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_verify_with_a_traceparent_sends_its_spans_under_that_trace() {
    let (endpoint, received) = receiver().await;
    let dir = Scratch::new("traces");
    let env = [
        ("OTEL_EXPORTER_OTLP_ENDPOINT", endpoint.as_str()),
        ("OTEL_EXPORTER_OTLP_PROTOCOL", "http/protobuf"),
        ("OTEL_BSP_SCHEDULE_DELAY", "100"),
    ];
    let served = Served::start_with_env(&dir.url("facegate.db"), &[], dir.0.join("serve.log"), &env).await;
    let client = reqwest::Client::new();
    let form = reqwest::multipart::Form::new()
        .text("subject", "imm-02")
        .part("image", reqwest::multipart::Part::bytes(imm("02-1m.jpg")).file_name("a.jpg"));
    let r = client.post(format!("{}/enroll", served.base)).multipart(form).send().await.unwrap();
    assert_eq!(r.status(), 201);

    let (trace_id, parent_id) = ("4bf92f3577b34da6a3ce929d0e0e4736", "00f067aa0ba902b7");
    let form = reqwest::multipart::Form::new()
        .text("subject", "imm-02")
        .part("image", reqwest::multipart::Part::bytes(imm("02-2m.jpg")).file_name("b.jpg"));
    let r = client
        .post(format!("{}/verify", served.base))
        .header("traceparent", format!("00-{trace_id}-{parent_id}-01"))
        .header("x-request-id", "trace-test-1")
        .multipart(form)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);

    // The batch is exported every 100 ms.
    let started = Instant::now();
    let ours = loop {
        let ours: Vec<(String, Span)> = spans(&received).into_iter().filter(|(_, s)| hex(&s.trace_id) == trace_id).collect();
        let has_request = ours.iter().any(|(_, s)| s.name == "POST /verify");
        if has_request && ours.len() >= 6 || started.elapsed() > Duration::from_secs(20) {
            break ours;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    let request = ours
        .iter()
        .map(|(_, s)| s)
        .find(|s| s.name == "POST /verify")
        .unwrap_or_else(|| panic!("no request span: {ours:?}\n{}", served.log()));
    assert_eq!(hex(&request.parent_span_id), parent_id, "the request span continues the caller's");
    assert_eq!(attribute(request, "http.route").as_deref(), Some("/verify"));
    assert_eq!(attribute(request, "request_id").as_deref(), Some("trace-test-1"));
    assert_eq!(attribute(request, "outcome").as_deref(), Some("ok"));
    assert_eq!(attribute(request, "http.response.status_code").as_deref(), Some("200"));
    assert!(ours.iter().all(|(service, _)| service == "facegate"), "service.name defaults to facegate");
    let stages: BTreeSet<&str> = ours.iter().map(|(_, s)| s.name.as_str()).collect();
    for stage in ["decode", "detect", "landmarks", "morph", "template", "quality", "liveness", "store"] {
        assert!(stages.contains(stage), "no {stage} span in {stages:?}");
    }
    // Nothing of the photo, the template or the subject.
    for (_, span) in &ours {
        for a in &span.attributes {
            let value = format!("{:?}", a.value);
            assert!(value.len() < 200 && !value.contains("imm-02"), "{}: {value}", a.key);
        }
    }
    // The enrolment was its own trace, not this one.
    assert!(spans(&received).iter().any(|(_, s)| s.name == "POST /enroll" && hex(&s.trace_id) != trace_id));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refusing_collector_costs_no_request_and_its_failures_are_logged_once_per_interval() {
    // A port that was just free: connections to it are refused.
    let refused = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap();
    let endpoint = format!("http://{refused}");
    let dir = Scratch::new("traces-refused");
    let env = [("OTEL_EXPORTER_OTLP_ENDPOINT", endpoint.as_str()), ("OTEL_BSP_SCHEDULE_DELAY", "100")];
    let served = Served::start_with_env(&dir.url("facegate.db"), &[], dir.0.join("serve.log"), &env).await;
    let client = reqwest::Client::new();
    // Batches of spans every 100 ms for 2 s, every one refused.
    let started = Instant::now();
    while started.elapsed() < Duration::from_secs(2) {
        let r = client.get(format!("{}/health", served.base)).send().await.unwrap();
        assert_eq!(r.status(), 200);
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let log = served.log();
    let lines: Vec<&str> = log.lines().filter(|l| l.contains("trace export failed")).collect();
    assert_eq!(lines.len(), 1, "one line per {} s, however many batches fail:\n{log}", facegate::telemetry::FAILURE_LOG_INTERVAL.as_secs());
    assert!(lines[0].contains("WARN") && lines[0].contains("1 batch(es)"), "{}", lines[0]);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unsupported_otlp_protocol_stops_the_start_up() {
    let dir = Scratch::new("traces-grpc");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_facegate"))
        .args(["serve", "--bind", "127.0.0.1:0", "--database", &dir.url("facegate.db")])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .env("OTEL_EXPORTER_OTLP_ENDPOINT", "http://127.0.0.1:4317")
        .env("OTEL_EXPORTER_OTLP_PROTOCOL", "grpc")
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("OTEL_EXPORTER_OTLP_PROTOCOL=grpc is not supported"));
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}
