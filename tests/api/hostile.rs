//! The service under hostile clients, over raw TCP where a well-behaved client cannot misbehave:
//! half-open and idle connections, stalled bodies, admission before the body, head limits, keys
//! on the operational routes, the audit log, and the contract fixes schemathesis found.

use std::io::Write;
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use facegate_core::imaging::DecodeLimits;
use facegate_http::ApiConfig;
use facegate_http::server::ServerLimits;
use facegate_service::ServiceConfig;
use serde_json::{Value, json};
use sha2::Digest as _;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use crate::support::*;

fn config() -> ApiConfig {
    let defaults = facegate::config::Settings::default().api_config().unwrap();
    ApiConfig {
        max_body_bytes: 2 << 20,
        admission_wait: Duration::ZERO,
        service: ServiceConfig { decode_limits: DecodeLimits { max_pixels: 1_000_000, ..DecodeLimits::default() }, ..defaults.service },
        ..defaults
    }
}

fn quick_limits() -> ServerLimits {
    ServerLimits { header_timeout: Duration::from_millis(400), ..facegate::config::Settings::default().server_limits().unwrap() }
}

async fn connect(app: &TestApp) -> TcpStream {
    TcpStream::connect(app.base.trim_start_matches("http://")).await.unwrap()
}

/// Read until the server closes the connection (or `limit` passes); what arrived.
async fn read_to_close(stream: &mut TcpStream, limit: Duration) -> Option<String> {
    let mut out = Vec::new();
    match tokio::time::timeout(limit, stream.read_to_end(&mut out)).await {
        Ok(_) => Some(String::from_utf8_lossy(&out).into_owned()),
        Err(_) => None,
    }
}

/// The problem type of a raw HTTP response.
fn raw_problem(response: &str) -> String {
    let body = response.split("\r\n\r\n").nth(1).unwrap_or("");
    let json: Value = serde_json::from_str(body).unwrap_or_else(|e| panic!("{e}: {response}"));
    json["type"].as_str().unwrap().rsplit('/').next().unwrap().to_string()
}

#[tokio::test]
async fn half_open_and_idle_connections_are_closed_after_the_header_timeout() {
    let app = TestApp::start_with(StandInEngine::new("v1"), config(), quick_limits()).await;
    let start = Instant::now();
    let mut half_open = Vec::new();
    for _ in 0..50 {
        let mut s = connect(&app).await;
        s.write_all(b"GET /health HTTP/1.1\r\nX: ").await.unwrap();
        half_open.push(s);
    }
    // A keep-alive connection that finished a request and then sends nothing.
    let mut idle = connect(&app).await;
    idle.write_all(b"GET /health HTTP/1.1\r\nHost: x\r\n\r\n").await.unwrap();
    for s in &mut half_open {
        let seen = read_to_close(s, Duration::from_secs(5)).await.expect("a half-open connection stayed open past the header timeout");
        assert!(!seen.contains("HTTP/1.1 2"), "{seen}");
    }
    let seen = read_to_close(&mut idle, Duration::from_secs(5)).await.expect("an idle connection stayed open past the header timeout");
    assert!(seen.starts_with("HTTP/1.1 200"), "{seen}");
    assert!(start.elapsed() < Duration::from_secs(3), "{:?}", start.elapsed());
}

#[tokio::test]
async fn a_stalled_body_gets_408_and_a_refused_request_is_answered_before_its_body() {
    let stalled = ApiConfig { body_timeout: Duration::from_millis(300), ..config() };
    let app = TestApp::start(StandInEngine::new("v1"), stalled).await;
    let mut s = connect(&app).await;
    s.write_all(
        b"POST /verify HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\nContent-Length: 100000\r\n\r\n--b\r\n",
    )
    .await
    .unwrap();
    let response = read_to_close(&mut s, Duration::from_secs(5)).await.expect("a stalled body is answered");
    assert!(response.starts_with("HTTP/1.1 408"), "{response}");
    assert_eq!(raw_problem(&response), "request-timeout");
    assert!(response.to_ascii_lowercase().contains("cache-control: no-store"), "{response}");

    // One worker, no queue, a slow engine: while a verification runs, another is refused with
    // 503 as soon as its body begins (the client has sent a few bytes of a megabyte); an
    // enrolment, in its own queue, is still admitted.
    let one = ApiConfig { workers: 1, queue_depth: 0, enroll_queue_depth: 1, ..config() };
    let app = TestApp::start(StandInEngine::slow(Duration::from_millis(800)), one).await;
    let photo = pattern_jpeg(320, 240, 4);
    assert_eq!(app.post_form("/enroll", Some("hana"), std::slice::from_ref(&photo)).await.status, 201);
    let images = [photo.clone()];
    let (busy, refused, enrolled) = tokio::join!(
        app.post_form("/verify", Some("hana"), &images),
        async {
            tokio::time::sleep(Duration::from_millis(200)).await;
            let mut s = connect(&app).await;
            s.write_all(
                b"POST /verify HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\nContent-Length: 1000000\r\n\r\n--b\r\n",
            )
            .await
            .unwrap();
            let mut head = vec![0u8; 4096];
            let n = tokio::time::timeout(Duration::from_millis(500), s.read(&mut head)).await.expect("refused without the body").unwrap();
            String::from_utf8_lossy(&head[..n]).into_owned()
        },
        async {
            tokio::time::sleep(Duration::from_millis(300)).await;
            app.post_form("/enroll", Some("hana"), &images).await
        }
    );
    assert_eq!(busy.status, 200);
    assert!(refused.starts_with("HTTP/1.1 503") && refused.to_ascii_lowercase().contains("retry-after: 1"), "{refused}");
    assert_eq!(raw_problem(&refused), "overloaded");
    assert_eq!(enrolled.status, 201, "{}", String::from_utf8_lossy(&enrolled.body));
}

#[tokio::test]
async fn heads_over_the_limits_get_problem_json_and_every_answer_has_no_store_and_a_request_id() {
    let app = TestApp::start(StandInEngine::new("v1"), config()).await;
    let r = app.get(&format!("/subjects?after={}", "a".repeat(9000))).await;
    r.assert_problem(414, "uri-too-long");
    let mut request = app.client.get(app.url("/health"));
    for i in 0..70 {
        request = request.header(format!("x-h{i}"), "v");
    }
    app.send(request).await.assert_problem(431, "headers-too-large");
    let r = app.send(app.client.get(app.url("/health")).header("x-big", "v".repeat(20_000))).await;
    r.assert_problem(431, "headers-too-large");

    let r = app.send(app.client.get(app.url("/health")).header("x-request-id", "trace-42")).await;
    assert_eq!(
        (r.status, r.headers["x-request-id"].to_str().unwrap(), r.headers["cache-control"].to_str().unwrap()),
        (200, "trace-42", "no-store")
    );
    let r = app.get("/subjects/nobody").await;
    r.assert_problem(404, "unknown-subject");
    let generated = r.headers["x-request-id"].to_str().unwrap();
    assert!(generated.len() == 32 && generated.chars().all(|c| c.is_ascii_hexdigit()), "{generated}");
    assert_eq!(r.headers["cache-control"], "no-store");
}

/// Heads hyper refuses before the router sees them (a malformed request line, a target over its
/// 64 KiB limit, more headers than it parses) are answered with problem+json too.
#[tokio::test]
async fn heads_hyper_refuses_itself_are_answered_with_problem_json() {
    let app = TestApp::start(StandInEngine::new("v1"), config()).await;
    let too_many_headers: String = (0..300).map(|i| format!("x-h{i}: v\r\n")).collect();
    for (head, status, slug) in [
        ("GARBAGE LINE\r\n\r\n".to_string(), 400, "malformed-request"),
        (format!("GET /{} HTTP/1.1\r\nhost: x\r\n\r\n", "a".repeat(70_000)), 414, "uri-too-long"),
        (format!("GET /health HTTP/1.1\r\nhost: x\r\n{too_many_headers}\r\n"), 431, "headers-too-large"),
    ] {
        let mut stream = connect(&app).await;
        stream.write_all(head.as_bytes()).await.unwrap();
        let response = read_to_close(&mut stream, Duration::from_secs(5)).await.expect("the server answers and closes");
        assert!(response.starts_with(&format!("HTTP/1.1 {status} ")), "{response}");
        assert!(response.contains("content-type: application/problem+json"), "{response}");
        assert_eq!(raw_problem(&response), slug);
    }
}

#[tokio::test]
async fn with_keys_metrics_need_one_and_health_shows_no_counts_without_one() {
    let key = "0123456789abcdef-ops";
    let app = TestApp::start(StandInEngine::new("v1"), ApiConfig { api_keys: vec![key.into()], ..config() }).await;
    app.get("/metrics").await.assert_problem(401, "unauthorized");
    assert_eq!(app.send(app.client.get(app.url("/metrics")).bearer_auth(key)).await.status, 200);
    let open = app.get("/health").await.json();
    assert_eq!((open["status"].as_str(), open.get("subjects"), open.get("templates")), (Some("ok"), None, None), "{open}");
    let keyed = app.send(app.client.get(app.url("/health")).bearer_auth(key)).await.json();
    assert_eq!((keyed["subjects"].as_u64(), keyed["templates"].as_u64()), (Some(0), Some(0)), "{keyed}");
    let wrong = app.send(app.client.get(app.url("/health")).bearer_auth("0123456789abcdef-bad")).await.json();
    assert!(wrong.get("subjects").is_none(), "{wrong}");
    // Without keys, everything stays open, counts included.
    let app = TestApp::start(StandInEngine::new("v1"), config()).await;
    assert_eq!(app.get("/metrics").await.status, 200);
    assert_eq!(app.get("/health").await.json()["subjects"].as_u64(), Some(0));
}

#[tokio::test]
async fn subject_ids_clients_cannot_address_are_refused_the_same_way_in_json_and_multipart() {
    let app = TestApp::start(StandInEngine::new("v1"), config()).await;
    let photo = pattern_jpeg(320, 240, 1);
    for bad in [".", "..", " padded", "padded ", "tab\t"] {
        app.post_form("/enroll", Some(bad), std::slice::from_ref(&photo)).await.assert_problem(400, "malformed-request");
        app.post_json("/enroll", &json!({"subject": bad, "image": base64(&photo)})).await.assert_problem(400, "malformed-request");
    }
    // A subject and no photo: refused, and the schema says so too (tests/api/openapi.rs).
    app.post_json("/enroll", &json!({"subject": "x"})).await.assert_problem(400, "malformed-request");
    app.post_json("/enroll", &json!({"subject": "x", "image": ""})).await.assert_problem(400, "malformed-request");
    assert_eq!(app.store.counts().await.unwrap(), (0, 0));
    assert_eq!(app.post_form("/enroll", Some("..."), &[photo]).await.status, 201);
    assert_eq!(app.get("/subjects/...").await.status, 200);
}

/// A `MakeWriter` collecting the log in memory.
#[derive(Clone, Default)]
pub(crate) struct Captured(pub(crate) Arc<Mutex<Vec<u8>>>);

impl Write for Captured {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().extend_from_slice(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl<'a> tracing_subscriber::fmt::MakeWriter<'a> for Captured {
    type Writer = Captured;
    fn make_writer(&'a self) -> Captured {
        self.clone()
    }
}

/// The test binary's log, as JSON lines in memory. A global subscriber, set once: a thread-local
/// one (`set_default`) misses events when another test thread registers the same callsites first.
pub(crate) fn captured_log() -> &'static Captured {
    static LOG: OnceLock<Captured> = OnceLock::new();
    LOG.get_or_init(|| {
        let log = Captured::default();
        let subscriber = tracing_subscriber::fmt().json().with_writer(log.clone()).with_max_level(tracing::Level::INFO).finish();
        tracing::subscriber::set_global_default(subscriber).expect("no other test sets a global subscriber");
        log
    })
}

#[tokio::test]
async fn the_audit_log_has_one_json_line_per_enroll_verify_identify_delete_with_key_and_request_ids() {
    let log = captured_log();
    let key = "0123456789abcdef-audit";
    let app = TestApp::start(StandInEngine::new("v1"), ApiConfig { api_keys: vec![key.into()], ..config() }).await;
    let photo = pattern_jpeg(320, 240, 1);
    let post = |path: &str, subject: Option<&str>, id: &str| {
        let mut form = reqwest::multipart::Form::new().part("image", reqwest::multipart::Part::bytes(photo.clone()).file_name("p.jpg"));
        if let Some(s) = subject {
            form = form.text("subject", s.to_string());
        }
        app.client.post(app.url(path)).bearer_auth(key).header("x-request-id", id).multipart(form)
    };
    assert_eq!(app.send(post("/enroll", Some("ivy"), "audit-enrol")).await.status, 201);
    assert_eq!(app.send(post("/verify", Some("ivy"), "audit-verify")).await.status, 200);
    assert_eq!(app.send(post("/verify", Some("nobody"), "audit-unknown")).await.status, 404);
    assert_eq!(app.send(post("/identify", None, "audit-identify")).await.status, 200);
    assert_eq!(
        app.send(app.client.delete(app.url("/subjects/ivy")).bearer_auth(key).header("x-request-id", "audit-delete")).await.status,
        204
    );
    assert_eq!(app.send(app.client.delete(app.url("/subjects/ivy")).header("x-request-id", "audit-nokey")).await.status, 401);
    assert_eq!(app.get("/subjects").await.status, 401, "not audited: not an enrol/verify/identify/delete");

    let text = String::from_utf8(log.0.lock().unwrap().clone()).unwrap();
    let audit: Vec<Value> = text
        .lines()
        .map(|l| serde_json::from_str::<Value>(l).unwrap_or_else(|e| panic!("{e}: {l}")))
        .filter(|v| v["target"] == "facegate::audit")
        .map(|v| v["fields"].clone())
        // The log is the whole test binary's: this test's requests are the `audit-` ids.
        .filter(|f| f["request_id"].as_str().is_some_and(|id| id.starts_with("audit-")))
        .collect();
    let key_id = format!("{:x}", sha2::Sha256::digest(key.as_bytes()))[..8].to_string();
    let by_id = |id: &str| audit.iter().find(|f| f["request_id"] == id).unwrap_or_else(|| panic!("no audit line for {id}: {text}")).clone();
    assert_eq!(audit.len(), 6, "{text}");
    let enroll = by_id("audit-enrol");
    assert_eq!((enroll["op"].as_str(), enroll["outcome"].as_str(), enroll["subject"].as_str()), (Some("enroll"), Some("ok"), Some("ivy")));
    assert_eq!(
        (enroll["templates_added"].as_u64(), enroll["model_version"].as_str(), enroll["key_id"].as_str()),
        (Some(1), Some("v1"), Some(&*key_id))
    );
    let verify = by_id("audit-verify");
    assert_eq!((verify["decision"].as_str(), verify["status"].as_u64()), (Some("match"), Some(200)));
    assert!(verify["score"].as_f64().unwrap() > 0.99 && verify["threshold"].as_f64().is_some(), "{verify}");
    let unknown = by_id("audit-unknown");
    assert_eq!(
        (unknown["outcome"].as_str(), unknown["subject"].as_str(), unknown.get("score")),
        (Some("unknown-subject"), Some("nobody"), None)
    );
    let identify = by_id("audit-identify");
    assert_eq!(
        (identify["op"].as_str(), identify["subject"].as_str(), identify["candidates"].as_u64()),
        (Some("identify"), Some("ivy"), Some(1))
    );
    assert_eq!((by_id("audit-delete")["op"].as_str(), by_id("audit-delete")["subject"].as_str()), (Some("delete"), Some("ivy")));
    let refused = by_id("audit-nokey");
    assert_eq!((refused["outcome"].as_str(), refused.get("key_id")), (Some("unauthorized"), None));
    // No photo bytes: every line is short, whatever the photo's size.
    assert!(text.lines().all(|l| l.len() < 1000), "{text}");
}

/// A request the deadline ends is audited too (the timeout layer sits inside the audit's), with
/// the outcome `timeout` and what the handler had learnt by then.
#[tokio::test]
async fn a_request_ended_by_the_timeout_is_audited() {
    let log = captured_log();
    let short = ApiConfig { request_timeout: Duration::from_millis(300), ..config() };
    let app = TestApp::start(StandInEngine::slow(Duration::from_millis(900)), short).await;
    let form = reqwest::multipart::Form::new()
        .text("subject", "late-audit")
        .part("image", reqwest::multipart::Part::bytes(pattern_jpeg(320, 240, 2)).file_name("p.jpg"));
    let reply = app.send(app.client.post(app.url("/enroll")).header("x-request-id", "timed-out-audit").multipart(form)).await;
    reply.assert_problem(504, "timeout");
    let text = String::from_utf8(log.0.lock().unwrap().clone()).unwrap();
    let line = text
        .lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter(|v| v["target"] == "facegate::audit")
        .map(|v| v["fields"].clone())
        .find(|f| f["request_id"] == "timed-out-audit")
        .unwrap_or_else(|| panic!("no audit line for the timed-out request: {text}"));
    assert_eq!(
        (line["op"].as_str(), line["outcome"].as_str(), line["status"].as_u64(), line["subject"].as_str()),
        (Some("enroll"), Some("timeout"), Some(504), Some("late-audit"))
    );
}
