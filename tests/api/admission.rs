//! Admission that idle and slow clients cannot hold: a declared body over the limit is refused
//! from the head, heads whose bodies never begin hold no queue place and no body budget, bodies
//! that trickle hold no queue place and only the budget of what they sent, are cut after the grace
//! period and are capped per client address, one address has its share of the connections, a
//! body sent fast then stalled holds its share of the budget only a window long, under connection
//! pressure the slowest bodies are cut for a new client, and the request deadline never answers
//! 504 for an enrolment that is stored.

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use facegate_core::imaging::DecodeLimits;
use facegate_http::ApiConfig;
use facegate_service::ServiceConfig;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};

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
    // heads that never send their body took every place until the body timeout. The heads come
    // from another address: an address's own stalled heads count against its own places.
    let tight = ApiConfig { workers: 2, queue_depth: 2, enroll_queue_depth: 2, max_buffered_bytes: 8 << 20, ..config() };
    let app = TestApp::start(StandInEngine::new("v1"), tight).await;
    let photo = pattern_jpeg(320, 240, 4);
    assert_eq!(app.post_form("/enroll", Some("ana"), std::slice::from_ref(&photo)).await.status, 201);
    let mut attackers = Vec::new();
    for (i, path) in ["/verify", "/enroll", "/identify", "/analyze"].iter().cycle().take(70).enumerate() {
        let mut s = connect_from(&app, [127, 0, 0, 2]).await;
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

/// A connection to `app` from the loopback address `from` (127.0.0.1 is the other clients').
async fn connect_from(app: &TestApp, from: [u8; 4]) -> TcpStream {
    let socket = TcpSocket::new_v4().unwrap();
    socket.bind(SocketAddr::from((from, 0))).unwrap();
    socket.connect(app.base.trim_start_matches("http://").parse().unwrap()).await.unwrap()
}

/// Trickle uploads from `from` until `stop`: each a head of `path` declaring `length` bytes, then
/// one byte every 100 ms, opened again once answered; the answers' status lines are counted.
fn trickle(app: &TestApp, from: [u8; 4], path: &'static str, length: usize, stop: Arc<AtomicBool>) -> tokio::task::JoinHandle<Vec<String>> {
    let base = app.base.clone();
    tokio::spawn(async move {
        let app_addr: SocketAddr = base.trim_start_matches("http://").parse().unwrap();
        let mut answers = Vec::new();
        while !stop.load(Ordering::Relaxed) {
            let socket = TcpSocket::new_v4().unwrap();
            socket.bind(SocketAddr::from((from, 0))).unwrap();
            let Ok(mut s) = socket.connect(app_addr).await else { continue };
            let _ = s.write_all(&stalled_head(path, length)).await;
            let mut reply = [0u8; 512];
            loop {
                if s.write_all(b"-").await.is_err() {
                    break;
                }
                match tokio::time::timeout(Duration::from_millis(100), s.read(&mut reply)).await {
                    Ok(Ok(n)) => {
                        let line = String::from_utf8_lossy(&reply[..n]).lines().next().unwrap_or("closed").to_string();
                        answers.push(if line.is_empty() { "closed".into() } else { line });
                        break;
                    }
                    Ok(Err(_)) => break,
                    Err(_) if stop.load(Ordering::Relaxed) => break,
                    Err(_) => {}
                }
            }
        }
        answers
    })
}

#[tokio::test]
async fn trickled_bodies_hold_no_queue_place_and_only_the_budget_of_what_arrived() {
    // Two workers, two waiting places per queue, a body budget of four full bodies; the trickles
    // are cut once they fall below 8 KiB/s after 0.5 s. Before, eight trickles declaring the
    // limit took the whole budget, and four took every place, until the body timeout.
    let tight = ApiConfig {
        workers: 2,
        queue_depth: 2,
        enroll_queue_depth: 2,
        max_buffered_bytes: 8 << 20,
        body_grace: Duration::from_millis(500),
        ..config()
    };
    let app = TestApp::start(StandInEngine::new("v1"), tight).await;
    let photo = pattern_jpeg(320, 240, 4);
    assert_eq!(app.post_form("/enroll", Some("ana"), std::slice::from_ref(&photo)).await.status, 201);
    let stop = Arc::new(AtomicBool::new(false));
    // Eight from this client's own address (within its cap of 16), on both queues.
    let trickles: Vec<_> =
        (0..8).map(|i| trickle(&app, [127, 0, 0, 1], if i % 2 == 0 { "/verify" } else { "/enroll" }, 2 << 20, stop.clone())).collect();
    tokio::time::sleep(Duration::from_millis(200)).await;
    let started = Instant::now();
    let mut ok = 0;
    for i in 0..20 {
        ok += usize::from(app.post_form("/verify", Some("ana"), std::slice::from_ref(&photo)).await.status == 200);
        if i % 5 == 0 {
            ok += usize::from(app.post_form("/enroll", Some(&format!("e{i}")), std::slice::from_ref(&photo)).await.status == 201);
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let took = started.elapsed();
    stop.store(true, Ordering::Relaxed);
    let mut answers = Vec::new();
    for t in trickles {
        answers.extend(t.await.unwrap());
    }
    assert_eq!(ok, 24, "verifications and enrolments answered 200/201 while the bodies trickled (in {took:?})");
    // The trickles were cut by the rate (408), opened again and cut again meanwhile.
    let cut = answers.iter().filter(|a| a.starts_with("HTTP/1.1 408")).count();
    assert!(cut >= 8 && cut == answers.len(), "{answers:?}");
}

#[tokio::test]
async fn a_client_address_has_at_most_its_cap_of_bodies_arriving() {
    let capped = ApiConfig { max_uploads_per_address: 4, body_grace: Duration::from_millis(600), ..config() };
    let app = TestApp::start(StandInEngine::new("v1"), capped).await;
    let photo = pattern_jpeg(320, 240, 4);
    assert_eq!(app.post_form("/enroll", Some("ana"), std::slice::from_ref(&photo)).await.status, 201);
    let mut held = Vec::new();
    for _ in 0..4 {
        let mut s = connect_from(&app, [127, 0, 0, 2]).await;
        s.write_all(&stalled_head("/verify", 100_000)).await.unwrap();
        s.write_all(b"--b\r\n").await.unwrap();
        held.push(s);
    }
    tokio::time::sleep(Duration::from_millis(100)).await;
    // A fifth from that address is refused at once; another address is served meanwhile.
    let mut fifth = connect_from(&app, [127, 0, 0, 2]).await;
    fifth.write_all(&stalled_head("/verify", 100_000)).await.unwrap();
    fifth.write_all(b"--b\r\n").await.unwrap();
    let refused = read_to_close(&mut fifth).await;
    assert!(refused.starts_with("HTTP/1.1 503") && refused.to_ascii_lowercase().contains("retry-after: 1"), "{refused}");
    assert!(refused.contains("overloaded") && refused.contains("already has 4 request bodies arriving"), "{refused}");
    assert_eq!(app.post_form("/verify", Some("ana"), std::slice::from_ref(&photo)).await.status, 200);
    // The four fall below 8 KiB/s once the grace period is over: 408, which names the rate.
    for s in &mut held {
        let cut = read_to_close(s).await;
        assert!(cut.starts_with("HTTP/1.1 408") && cut.contains("request-timeout"), "{cut}");
        assert!(cut.contains("slower than 8 KiB/s after its first 0.6 s"), "{cut}");
    }
    // Then the address has its places again.
    let mut again = connect_from(&app, [127, 0, 0, 2]).await;
    let body = "--b\r\nContent-Disposition: form-data; name=\"subject\"\r\n\r\nana\r\n--b--\r\n";
    let head = "POST /verify HTTP/1.1\r\nHost: x\r\nConnection: close\r\nContent-Type: multipart/form-data; boundary=b\r\n";
    again.write_all(format!("{head}Content-Length: {}\r\n\r\n{body}", body.len()).as_bytes()).await.unwrap();
    let answered = read_to_close(&mut again).await;
    assert!(answered.starts_with("HTTP/1.1 400") && answered.contains("the photo is missing"), "{answered}");
}

/// What arrives on `s` until the server closes it (at most 5 s).
async fn read_to_close(s: &mut TcpStream) -> String {
    let mut out = Vec::new();
    let _ = tokio::time::timeout(Duration::from_secs(5), s.read_to_end(&mut out)).await;
    String::from_utf8_lossy(&out).into_owned()
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
    let limits = facegate_http::server::ServerLimits {
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

#[tokio::test]
async fn one_address_has_its_share_of_the_connections_and_the_others_are_served() {
    let limits = facegate_http::server::ServerLimits {
        max_connections: 40,
        max_connections_per_address: 8,
        ..facegate::config::Settings::default().server_limits().unwrap()
    };
    let app = TestApp::start_with(StandInEngine::new("v1"), config(), limits).await;
    let photo = pattern_jpeg(320, 240, 4);
    assert_eq!(app.post_form("/enroll", Some("ana"), std::slice::from_ref(&photo)).await.status, 201);
    // Eight heads from 127.0.0.2 without their bodies: its share.
    let mut held = Vec::new();
    for _ in 0..8 {
        let mut s = connect_from(&app, [127, 0, 0, 2]).await;
        s.write_all(&stalled_head("/verify", 100_000)).await.unwrap();
        held.push(s);
    }
    tokio::time::sleep(Duration::from_millis(100)).await;
    // A ninth is answered at once, before it sends anything, and closed.
    let mut ninth = connect_from(&app, [127, 0, 0, 2]).await;
    let refused = read_to_close(&mut ninth).await;
    assert!(refused.starts_with("HTTP/1.1 503") && refused.contains("application/problem+json"), "{refused}");
    assert!(refused.contains("/problems/overloaded") && refused.contains("already has 8 connections open"), "{refused}");
    let body = &refused[refused.find("\r\n\r\n").unwrap() + 4..];
    let problem: serde_json::Value = serde_json::from_str(body).unwrap();
    assert_eq!((problem["status"].as_u64(), problem["title"].as_str()), (Some(503), Some("Overloaded")), "{problem}");
    // Another address is served meanwhile, and the address has its places again once they close.
    assert_eq!(app.post_form("/verify", Some("ana"), std::slice::from_ref(&photo)).await.status, 200);
    drop(held);
    tokio::time::sleep(Duration::from_millis(200)).await;
    let mut again = connect_from(&app, [127, 0, 0, 2]).await;
    let head = "GET /livez HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n";
    again.write_all(head.as_bytes()).await.unwrap();
    let answered = read_to_close(&mut again).await;
    assert!(answered.starts_with("HTTP/1.1 200"), "{answered}");
}

#[tokio::test]
async fn under_connection_pressure_the_slowest_bodies_are_cut_for_a_new_client() {
    // 32 connections, all held by bodies from 127.0.0.2 crawling at 10 KiB/s (above the minimum
    // rate, within a 30 s body timeout): before, a new client waited in the backlog until the
    // body timeout cut them.
    let limits =
        facegate_http::server::ServerLimits { max_connections: 32, ..facegate::config::Settings::default().server_limits().unwrap() };
    let patient = ApiConfig {
        max_uploads_per_address: 64,
        body_timeout: Duration::from_secs(30),
        request_timeout: Duration::from_secs(30),
        ..config()
    };
    let app = TestApp::start_with(StandInEngine::new("v1"), patient, limits).await;
    let photo = pattern_jpeg(320, 240, 4);
    assert_eq!(app.post_form("/enroll", Some("ana"), std::slice::from_ref(&photo)).await.status, 201);
    let stop = Arc::new(AtomicBool::new(false));
    let mut crawlers = Vec::new();
    for _ in 0..32 {
        let mut s = connect_from(&app, [127, 0, 0, 2]).await;
        let stop = stop.clone();
        crawlers.push(tokio::spawn(async move {
            s.write_all(&stalled_head("/verify", 1 << 20)).await.unwrap();
            let mut reply = [0u8; 1024];
            while !stop.load(Ordering::Relaxed) {
                if s.write_all(&[b'-'; 1024]).await.is_err() {
                    break;
                }
                if let Ok(Ok(n)) = tokio::time::timeout(Duration::from_millis(100), s.read(&mut reply)).await {
                    return String::from_utf8_lossy(&reply[..n]).into_owned();
                }
            }
            String::new()
        }));
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    let started = Instant::now();
    // A new client, on a new connection (the enrolment's keep-alive connection is not used).
    let form = reqwest::multipart::Form::new()
        .text("subject", "ana")
        .part("image", reqwest::multipart::Part::bytes(photo.clone()).file_name("probe.jpg"));
    let request = reqwest::Client::new().post(app.url("/verify")).multipart(form).send();
    let reply = tokio::time::timeout(Duration::from_secs(10), request).await;
    let took = started.elapsed();
    stop.store(true, Ordering::Relaxed);
    assert_eq!(reply.expect("answered before the body timeout").unwrap().status(), 200);
    assert!(took < Duration::from_secs(4), "the new client waited {took:?}");
    let mut cut = Vec::new();
    for c in crawlers {
        cut.push(c.await.unwrap());
    }
    let shed = cut.iter().filter(|r| r.starts_with("HTTP/1.1 503") && r.contains("arrived the slowest")).count();
    assert!(shed >= 1, "{cut:?}");
}
