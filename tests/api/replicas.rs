//! Two `facegate serve` processes (the real binary, the real pipeline) on one PostgreSQL
//! database: started together, so their migrations race; what one enrols or deletes, the other's
//! `/verify` and `/identify` see at once.

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use reqwest::multipart::{Form, Part};
use serde_json::Value;

use crate::postgres_or_skip;
use crate::support::imm;

/// A `facegate serve` process, killed when dropped.
struct Replica {
    base: String,
    process: Child,
    log: std::path::PathBuf,
}

impl Replica {
    fn start(name: &str, database: &str, dir: &std::path::Path) -> Replica {
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let log = dir.join(format!("{name}.log"));
        let process = Command::new(env!("CARGO_BIN_EXE_facegate"))
            .args(["serve", "--bind", &format!("127.0.0.1:{port}"), "--database", database, "--workers", "1"])
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .env("FACEGATE_API_KEYS", "")
            .env_remove("FACEGATE_API_KEYS_FILE")
            .env_remove("FACEGATE_TEMPLATE_KEY_FILE")
            .env("RUST_LOG", "info")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap();
        Replica { base: format!("http://127.0.0.1:{port}"), process, log }
    }

    fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    async fn wait_healthy(&mut self, client: &reqwest::Client) -> Value {
        let started = Instant::now();
        loop {
            if let Ok(r) = client.get(format!("{}/health", self.base)).send().await
                && r.status() == 200
            {
                return r.json().await.unwrap();
            }
            assert!(self.process.try_wait().unwrap().is_none(), "the replica exited: {}", self.log());
            assert!(started.elapsed() < Duration::from_secs(180), "the replica did not come up: {}", self.log());
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    async fn post(&self, client: &reqwest::Client, path: &str, subject: Option<&str>, photo: &str) -> (u16, Value) {
        let mut form = Form::new().part("image", Part::bytes(imm(photo)).file_name(photo.to_string()).mime_str("image/jpeg").unwrap());
        if let Some(subject) = subject {
            form = form.text("subject", subject.to_string());
        }
        let r = client.post(format!("{}{path}", self.base)).multipart(form).send().await.unwrap();
        (r.status().as_u16(), r.json().await.unwrap_or(Value::Null))
    }
}

impl Drop for Replica {
    fn drop(&mut self) {
        let _ = self.process.kill();
        let _ = self.process.wait();
    }
}

/// The best candidate of an `/identify` answer and whether it matched, with the subjects searched.
fn best(answer: &Value) -> (Option<&str>, Option<bool>, Option<u64>) {
    let first = &answer["candidates"][0];
    (first["subject"].as_str(), first["match"].as_bool(), answer["subjects_searched"].as_u64())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_replicas_on_one_database_agree_at_once() {
    let database = postgres_or_skip!("replicas::two_replicas_on_one_database_agree_at_once");
    let dir = std::env::temp_dir().join(format!("facegate-replicas-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // Started together on an empty database: both try to migrate it at once.
    let mut a = Replica::start("a", &database, &dir);
    let mut b = Replica::start("b", &database, &dir);
    let client = reqwest::Client::new();
    for replica in [&mut a, &mut b] {
        let health = replica.wait_healthy(&client).await;
        assert_eq!((health["store_backend"].as_str(), health["subjects"].as_u64()), (Some("postgres"), Some(0)), "{health}");
    }

    // Enrolled on A: B verifies and identifies it at once (B loaded its gallery before).
    let (status, enrolled) = a.post(&client, "/enroll", Some("imm-01"), "01-1m.jpg").await;
    assert_eq!(status, 201, "{enrolled}\n{}", a.log());
    let (status, verified) = b.post(&client, "/verify", Some("imm-01"), "01-2m.jpg").await;
    assert_eq!((status, verified["match"].as_bool()), (200, Some(true)), "{verified}");
    let (status, identified) = b.post(&client, "/identify", None, "01-2m.jpg").await;
    assert_eq!((status, best(&identified)), (200, (Some("imm-01"), Some(true), Some(1))), "{identified}");
    // Another person is not taken for it.
    let (_, other) = b.post(&client, "/identify", None, "02-1m.jpg").await;
    assert_eq!(best(&other), (Some("imm-01"), Some(false), Some(1)), "{other}");

    // Deleted on B: gone on A at once, for every route.
    let r = client.delete(format!("{}/subjects/imm-01", b.base)).send().await.unwrap();
    assert_eq!(r.status(), 204);
    let r = client.get(format!("{}/subjects/imm-01", a.base)).send().await.unwrap();
    assert_eq!(r.status(), 404);
    let (status, _) = a.post(&client, "/verify", Some("imm-01"), "01-2m.jpg").await;
    assert_eq!(status, 404);
    let (status, identified) = a.post(&client, "/identify", None, "01-2m.jpg").await;
    assert_eq!((status, best(&identified)), (200, (None, None, Some(0))), "{identified}");

    // Enrolled on B again: A's gallery has it back.
    let (status, _) = b.post(&client, "/enroll", Some("imm-01"), "01-1m.jpg").await;
    assert_eq!(status, 201);
    let (_, identified) = a.post(&client, "/identify", None, "01-2m.jpg").await;
    assert_eq!(best(&identified), (Some("imm-01"), Some(true), Some(1)), "{identified}");
    for replica in [&a, &b] {
        assert!(!replica.log().contains("has not applied"), "no identification waited out its bound: {}", replica.log());
    }
    drop((a, b));
    std::fs::remove_dir_all(dir).unwrap();
}

/// The gallery's listening connection is cut while another replica enrols: the notification is
/// lost, the feed reconnects and says so, and the gallery reloads everything, so an identification
/// still sees the enrolment.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_gallery_reloads_after_its_listening_connection_is_cut() {
    use facegate_core::SubjectId;
    use facegate_core::template::Template;
    use facegate_service::gallery::LiveGallery;
    use facegate_store::Store;
    use sqlx::Connection;

    let url = postgres_or_skip!("replicas::the_gallery_reloads_after_its_listening_connection_is_cut");
    let here = Store::connect(&url, None).await.unwrap();
    let other = Store::connect(&url, None).await.unwrap();
    let live = LiveGallery::new(here.clone(), "v1", facegate_service::gallery::Precision::Quantised);
    live.load().await.unwrap();
    let template = |seed: f32| Template::new("v1", (0..16).map(|i| (i as f32 + seed).sin()).collect());
    let id = |s: &str| SubjectId::parse(s).unwrap();

    other.enroll(&id("first"), &[template(1.0)]).await.unwrap();
    live.wait_until_applied(live.change_version().await.unwrap()).await;
    assert_eq!(live.size(), (1, 1));

    let mut admin = sqlx::PgConnection::connect(&url).await.unwrap();
    let cut: Vec<i32> = sqlx::query_scalar(
        "SELECT pid FROM pg_stat_activity WHERE datname = current_database() AND query LIKE 'LISTEN%' AND pid <> pg_backend_pid()",
    )
    .fetch_all(&mut admin)
    .await
    .unwrap();
    assert_eq!(cut.len(), 1, "one listening connection: the gallery's");
    sqlx::query("SELECT pg_terminate_backend($1)").bind(cut[0]).execute(&mut admin).await.unwrap();
    // Committed while nobody listens: its notification is lost.
    other.enroll(&id("second"), &[template(2.0)]).await.unwrap();
    let version = live.change_version().await.unwrap();
    assert!(version.is_some());
    let started = Instant::now();
    while live.size() != (2, 2) && started.elapsed() < Duration::from_secs(10) {
        live.wait_until_applied(version).await;
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(live.size(), (2, 2), "reloaded after the reconnect");
    admin.close().await.unwrap();
    live.stop_following();
    here.close().await;
    other.close().await;
}
