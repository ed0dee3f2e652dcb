//! Admission that idle clients cannot hold: a declared body over the limit is refused from the
//! head, heads whose bodies never begin hold no queue place and no body budget, and the request
//! deadline never answers 504 for an enrollment that is stored.

use std::time::{Duration, Instant};

use facegate::core::imaging::DecodeLimits;
use facegate::http::ApiConfig;
use facegate::service::ServiceConfig;
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

async fn connect(app: &TestApp) -> TcpStream {
    TcpStream::connect(app.base.trim_start_matches("http://")).await.unwrap()
}

/// A head of `path` declaring `length` bytes of multipart body, and nothing more.
fn stalled_head(path: &str, length: usize) -> Vec<u8> {
    format!("POST {path} HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=b\r\nContent-Length: {length}\r\n\r\n")
        .into_bytes()
}

#[tokio::test]
async fn a_body_declared_over_the_limit_is_refused_413_from_its_head() {
    let app = TestApp::start(StandInEngine::new("v1"), config()).await;
    for length in [(2 << 20) + 1, 16 << 20, 1 << 30] {
        let mut s = connect(&app).await;
        s.write_all(&stalled_head("/verify", length)).await.unwrap();
        let start = Instant::now();
        let mut head = vec![0u8; 4096];
        let n = tokio::time::timeout(Duration::from_secs(2), s.read(&mut head)).await.expect("answered from the head").unwrap();
        let response = String::from_utf8_lossy(&head[..n]).into_owned();
        assert!(response.starts_with("HTTP/1.1 413"), "{length}: {response}");
        assert!(response.contains("too-large"), "{response}");
        assert!(start.elapsed() < Duration::from_millis(500), "{:?}", start.elapsed());
    }
}

#[tokio::test]
async fn stalled_heads_hold_no_queue_place_and_no_body_budget() {
    // Two workers, two waiting places, a body budget of four full bodies: before, a handful of
    // heads that never send their body took every place until the body timeout.
    let tight = ApiConfig { workers: 2, queue_depth: 2, enroll_queue_depth: 2, max_buffered_bytes: 8 << 20, ..config() };
    let app = TestApp::start(StandInEngine::new("v1"), tight).await;
    let photo = pattern_jpeg(320, 240, 4);
    assert_eq!(app.post_form("/enroll", Some("ana"), std::slice::from_ref(&photo)).await.status, 201);
    let mut attackers = Vec::new();
    for (i, path) in ["/verify", "/enroll", "/identify", "/analyze"].iter().cycle().take(70).enumerate() {
        let mut s = connect(&app).await;
        let length = if i % 2 == 0 { 2 << 20 } else { 125_000 };
        s.write_all(&stalled_head(path, length)).await.unwrap();
        attackers.push(s);
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    let mut ok = 0;
    for _ in 0..20 {
        let reply = app.post_form("/verify", Some("ana"), std::slice::from_ref(&photo)).await;
        ok += usize::from(reply.status == 200);
    }
    assert_eq!(ok, 20, "legitimate verifications answered 200 while 70 heads stalled");
    assert_eq!(app.post_form("/enroll", Some("ben"), std::slice::from_ref(&photo)).await.status, 201);
    drop(attackers);
}

#[tokio::test]
async fn a_head_whose_body_never_begins_gets_408() {
    let quick = ApiConfig { body_timeout: Duration::from_millis(300), ..config() };
    let app = TestApp::start(StandInEngine::new("v1"), quick).await;
    let mut s = connect(&app).await;
    s.write_all(&stalled_head("/verify", 100_000)).await.unwrap();
    let mut out = Vec::new();
    tokio::time::timeout(Duration::from_secs(3), s.read_to_end(&mut out)).await.expect("answered and closed").unwrap();
    let response = String::from_utf8_lossy(&out);
    assert!(response.starts_with("HTTP/1.1 408") && response.contains("request-timeout"), "{response}");
}

#[tokio::test]
async fn an_enrollment_cut_by_the_deadline_before_its_commit_stores_nothing() {
    // The photo work outlasts the deadline: 504, and the subject never appears.
    let short = ApiConfig { request_timeout: Duration::from_millis(300), ..config() };
    let app = TestApp::start(StandInEngine::slow(Duration::from_millis(900)), short).await;
    let reply = app.post_form("/enroll", Some("late"), &[pattern_jpeg(320, 240, 4)]).await;
    reply.assert_problem(504, "timeout");
    tokio::time::sleep(Duration::from_millis(1200)).await;
    app.get("/subjects/late").await.assert_problem(404, "unknown-subject");
    assert_eq!(app.store.counts().await.unwrap(), (0, 0));
}

#[tokio::test]
async fn a_flood_of_half_open_connections_over_the_cap_does_not_starve_health() {
    // A cap of 40 connections and a 10 s header timeout; 60 attackers keep reopening half-open
    // connections. New connections past half the cap get 1 s for their head, so a
    // health probe gets a place within about that.
    let limits = facegate::http::server::ServerLimits {
        max_connections: 40,
        header_timeout: Duration::from_secs(10),
        ..facegate::config::Settings::default().server_limits().unwrap()
    };
    let app = TestApp::start_with(StandInEngine::new("v1"), config(), limits).await;
    let addr = app.base.trim_start_matches("http://").to_string();
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let mut attackers = Vec::new();
    for _ in 0..60 {
        let (addr, stop) = (addr.clone(), stop.clone());
        attackers.push(tokio::spawn(async move {
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                let Ok(mut s) = TcpStream::connect(&addr).await else { continue };
                let _ = s.write_all(b"GET /health HTTP/1.1\r\nX: ").await;
                let mut sink = [0u8; 64];
                let _ = tokio::time::timeout(Duration::from_secs(15), s.read(&mut sink)).await;
            }
        }));
    }
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let mut slowest = Duration::ZERO;
    for _ in 0..5 {
        let start = Instant::now();
        let reply = tokio::time::timeout(Duration::from_secs(8), reqwest::Client::new().get(app.url("/health")).send())
            .await
            .expect("health answered within 8 s")
            .unwrap();
        assert_eq!(reply.status(), 200);
        slowest = slowest.max(start.elapsed());
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    attackers.iter().for_each(|a| a.abort());
    assert!(slowest < Duration::from_millis(3000), "health took {slowest:?} under the flood");
}
