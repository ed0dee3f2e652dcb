//! The database going away under a running service: a TCP proxy between the service and a real
//! PostgreSQL server is cut and restored. While it is cut every request that needs the database
//! is answered within 2 s, 503 `store-unavailable` with `Retry-After`, `/health` within 1 s; once
//! it is back, requests succeed again within a few seconds; nothing acknowledged is lost.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use facegate_core::imaging::DecodeLimits;
use facegate_http::ApiConfig;
use facegate_service::ServiceConfig;
use tokio::net::{TcpListener, TcpStream};

use crate::support::*;

/// A TCP proxy to `target` on a fixed local port that can be cut (listener closed, every
/// connection dropped) and restored.
struct Proxy {
    port: u16,
    target: String,
    up: Arc<AtomicBool>,
    task: Option<tokio::task::JoinHandle<()>>,
}

impl Proxy {
    async fn start(target: String) -> Proxy {
        let port = TcpListener::bind("127.0.0.1:0").await.unwrap().local_addr().unwrap().port();
        let mut proxy = Proxy { port, target, up: Arc::new(AtomicBool::new(false)), task: None };
        proxy.restore().await;
        proxy
    }

    async fn restore(&mut self) {
        let listener = TcpListener::bind(("127.0.0.1", self.port)).await.unwrap();
        let (target, up) = (self.target.clone(), self.up.clone());
        up.store(true, Ordering::SeqCst);
        self.task = Some(tokio::spawn(async move {
            let mut pipes = tokio::task::JoinSet::new();
            loop {
                let Ok((mut inbound, _)) = listener.accept().await else { break };
                let target = target.clone();
                pipes.spawn(async move {
                    if let Ok(mut outbound) = TcpStream::connect(&target).await {
                        let _ = tokio::io::copy_bidirectional(&mut inbound, &mut outbound).await;
                    }
                });
            }
        }));
    }

    /// Close the listener and every connection through it (the JoinSet aborts them on drop).
    async fn cut(&mut self) {
        self.up.store(false, Ordering::SeqCst);
        if let Some(task) = self.task.take() {
            task.abort();
            let _ = task.await;
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lost_database_is_refused_fast_and_the_service_recovers() {
    let url = crate::postgres_or_skip!("store_outage::a_lost_database_is_refused_fast_and_the_service_recovers");
    let (server, name) = url.rsplit_once('/').unwrap();
    let authority = server.rsplit_once('@').map_or(server, |(_, a)| a).trim_start_matches("postgres://").to_string();
    let mut proxy = Proxy::start(authority.clone()).await;
    let proxied = url.replacen(&authority, &format!("127.0.0.1:{}", proxy.port), 1);
    assert_ne!(proxied, url, "{url}");
    let _ = name;
    let defaults = facegate::config::Settings::default().api_config().unwrap();
    let config = ApiConfig {
        service: ServiceConfig { decode_limits: DecodeLimits { max_pixels: 1_000_000, ..DecodeLimits::default() }, ..defaults.service },
        ..defaults
    };
    let app = TestApp::start_on_database(StandInEngine::new("v1"), proxied, config).await;
    let photo = pattern_jpeg(320, 240, 4);
    assert_eq!(app.post_form("/enroll", Some("ana"), std::slice::from_ref(&photo)).await.status, 201);

    proxy.cut().await;
    let mut refused = 0;
    let down_since = Instant::now();
    while down_since.elapsed() < Duration::from_secs(6) {
        let start = Instant::now();
        let verify = app.post_form("/verify", Some("ana"), std::slice::from_ref(&photo)).await;
        assert!(start.elapsed() < Duration::from_secs(2), "verify took {:?}", start.elapsed());
        verify.assert_problem(503, "store-unavailable");
        assert_eq!(verify.headers["retry-after"], "1");
        let start = Instant::now();
        let health = app.get("/health").await;
        assert!(start.elapsed() < Duration::from_millis(1500), "health took {:?}", start.elapsed());
        health.assert_problem(503, "store-unavailable");
        // The liveness probe's route asks no database: a replica whose database is down is alive.
        let alive = app.get("/livez").await;
        assert_eq!((alive.status, alive.json()["status"].as_str()), (200, Some("alive")));
        let enroll = app.post_form("/enroll", Some("ben"), std::slice::from_ref(&photo)).await;
        enroll.assert_problem(503, "store-unavailable");
        refused += 1;
    }
    assert!(refused >= 3, "{refused}");

    proxy.restore().await;
    let back = Instant::now();
    loop {
        let verify = app.post_form("/verify", Some("ana"), std::slice::from_ref(&photo)).await;
        if verify.status == 200 {
            assert_eq!(verify.json()["match"], true);
            break;
        }
        verify.assert_problem(503, "store-unavailable");
        assert!(back.elapsed() < Duration::from_secs(5), "not recovered within 5 s");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(app.get("/health").await.status, 200);
    // Refused enrolments stored nothing; the acknowledged one is there.
    app.get("/subjects/ben").await.assert_problem(404, "unknown-subject");
    assert_eq!(app.get("/subjects/ana").await.status, 200);
}
