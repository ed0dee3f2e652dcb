//! A SQLite database that vanishes under the running service is noticed: the file unlinked (or
//! emptied in place) makes `/health` answer 503 `store-unavailable` within 2 s and refuses every
//! enrolment with 503, so nothing is acknowledged into a file no restart sees; a file that is
//! not (or no longer) a database is 503 `store-unavailable` too, not 500 `internal`.

use std::time::{Duration, Instant};

use facegate::config::Settings;
use facegate_http::{Problem, ProblemKind};
use facegate_store::Store;

use crate::fail_closed::Scratch;
use crate::support::*;

async fn app() -> TestApp {
    let app = TestApp::start(StandInEngine::new("v1"), Settings::default().api_config().unwrap()).await;
    assert_eq!(app.post_form("/enroll", Some("alice"), &[pattern_jpeg(320, 240, 1)]).await.status, 201);
    assert_eq!(app.get("/health").await.status, 200);
    app
}

fn file_of(app: &TestApp) -> std::path::PathBuf {
    app.database_url.strip_prefix("sqlite://").expect("a SQLite app").into()
}

/// How long until `/health` answers 503 `store-unavailable` (panics after 5 s).
async fn until_unhealthy(app: &TestApp) -> Duration {
    let started = Instant::now();
    loop {
        let health = app.get("/health").await;
        if health.status == 503 {
            health.assert_problem(503, "store-unavailable");
            return started.elapsed();
        }
        assert!(started.elapsed() < Duration::from_secs(5), "/health still {} after 5 s", health.status);
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test]
async fn an_unlinked_sqlite_file_is_noticed_and_no_enrolment_is_acknowledged() {
    let app = app().await;
    let file = file_of(&app);
    std::fs::remove_file(&file).unwrap();
    let noticed = until_unhealthy(&app).await;
    assert!(noticed <= Duration::from_secs(2), "noticed after {noticed:?}");
    let refused = app.post_form("/enroll", Some("bob"), &[pattern_jpeg(320, 240, 2)]).await;
    refused.assert_problem(503, "store-unavailable");
    assert!(refused.headers.contains_key("retry-after"));
    // A file put back at the path is another file, not the one opened: still refused.
    std::fs::write(&file, b"").unwrap();
    app.post_form("/enroll", Some("carol"), &[pattern_jpeg(320, 240, 3)]).await.assert_problem(503, "store-unavailable");
}

#[tokio::test]
async fn an_emptied_sqlite_file_is_noticed() {
    let app = app().await;
    app.store.checkpoint().await.unwrap();
    // Truncated in place: the same inode, nothing in it.
    std::fs::OpenOptions::new().write(true).truncate(true).open(file_of(&app)).unwrap();
    let noticed = until_unhealthy(&app).await;
    assert!(noticed <= Duration::from_secs(2), "noticed after {noticed:?}");
    app.post_form("/enroll", Some("bob"), &[pattern_jpeg(320, 240, 2)]).await.assert_problem(503, "store-unavailable");
}

#[tokio::test]
async fn a_file_that_is_not_a_database_is_store_unavailable_not_internal() {
    let scratch = Scratch::new("notadb");
    let path = scratch.path("facegate.db");
    std::fs::write(&path, vec![0x55u8; 8192]).unwrap();
    let error = Store::connect(&scratch.url("facegate.db"), None).await.expect_err("not a database");
    assert!(error.is_unavailable(), "{error}");
    assert_eq!(Problem::from(error).kind, ProblemKind::StoreUnavailable);
}
