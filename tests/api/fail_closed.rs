//! Misconfiguration fails closed, and erasure says what it covers.
//!
//! - `facegate serve` (the real binary) refuses to start, exits non-zero with a message naming the
//!   setting and never listens: an API-key setting given but holding no key (`--api-keys ",,"`, a
//!   key file of comments only), and a database sealed by one template key started without a key
//!   or with another one (SQLite and PostgreSQL). The right key starts it, and `/health` says what
//!   it knows. `--liveness enforce` without the liveness model, and a liveness threshold outside
//!   (0, 1), stop it too.
//! - `DELETE /subjects/{id}` answers 204 with `Facegate-Erasure`, and `/health` repeats it.
//! - The statement of docs/storage.md ("Erasure: what it covers"): a backup taken before a DELETE
//!   and restored with the same key brings the subject back, and it verifies; once the key is
//!   rotated away (`facegate rekey`) and the old key destroyed, that backup opens no more.

use std::path::PathBuf;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use facegate::startup::Application;
use facegate_core::SubjectId;
use facegate_core::template::Template;
use facegate_http::ApiConfig;
use facegate_store::{KeyCheck, KeyRing, Store};
use serde_json::Value;

use crate::on_both_backends;
use crate::support::{Db, StandInEngine, TestApp, pattern_jpeg};

const K1: &str = "1f1e1d1c1b1a191817161514131211100f0e0d0c0b0a09080706050403020100";
const K2: &str = "a5a4a3a2a1a09f9e9d9c9b9a999897969594939291908f8e8d8c8b8a89888786";

fn ring(text: &str) -> KeyRing {
    KeyRing::parse(text).unwrap()
}

/// A temporary folder, removed when dropped.
pub(crate) struct Scratch(pub(crate) PathBuf);

impl Scratch {
    pub(crate) fn new(name: &str) -> Scratch {
        static N: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!("facegate-fail-closed-{name}-{}-{n}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        Scratch(dir)
    }

    pub(crate) fn path(&self, name: &str) -> String {
        self.0.join(name).display().to_string()
    }

    pub(crate) fn url(&self, name: &str) -> String {
        format!("sqlite://{}", self.path(name))
    }

    /// Write `text` to `name`; its path.
    pub(crate) fn file(&self, name: &str, text: &str) -> String {
        std::fs::write(self.0.join(name), text).unwrap();
        self.path(name)
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// `facegate` with `args`, none of the key settings inherited from the environment, run from the
/// crate (where the models are); its output. Killed (and the test failed) after 120 s.
pub(crate) fn facegate(args: &[&str]) -> Output {
    let child = Command::new(env!("CARGO_BIN_EXE_facegate"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .env_remove("FACEGATE_API_KEYS")
        .env_remove("FACEGATE_API_KEYS_FILE")
        .env_remove("FACEGATE_TEMPLATE_KEY_FILE")
        .env_remove("FACEGATE_DATABASE_URL")
        .env("RUST_LOG", "info")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let id = child.id();
    let (done, waited) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = done.send(child.wait_with_output());
    });
    match waited.recv_timeout(Duration::from_secs(120)) {
        Ok(output) => output.unwrap(),
        Err(_) => {
            let _ = Command::new("kill").arg(id.to_string()).status();
            panic!("facegate {args:?} did not exit within 120 s");
        }
    }
}

/// A loopback port nothing listens on (yet).
fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// `facegate serve` on `database` with `extra` arguments must refuse to start: a non-zero exit,
/// an error containing each of `expected`, and no listening socket at any time. Returns the error.
pub(crate) fn serve_is_refused(database: &str, extra: &[&str], expected: &[&str]) -> String {
    let port = free_port();
    let bind = format!("127.0.0.1:{port}");
    let mut args = vec!["serve", "--bind", &bind, "--database", database, "--workers", "1"];
    args.extend_from_slice(extra);
    let out = facegate(&args);
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    let log = format!("{stdout}\n{stderr}");
    assert!(!out.status.success(), "started with {extra:?}:\n{log}");
    let error = stderr.lines().find(|l| l.contains("facegate: error:")).unwrap_or_else(|| panic!("no error line:\n{log}")).to_string();
    for needle in expected {
        assert!(error.contains(needle), "{needle:?} not in the error: {error}");
    }
    assert!(!log.contains("listening on"), "it listened:\n{log}");
    assert!(std::net::TcpStream::connect_timeout(&bind.parse().unwrap(), Duration::from_millis(500)).is_err());
    error
}

/// `facegate serve` on `database` with `extra` arguments, running until dropped.
pub(crate) struct Served {
    pub(crate) base: String,
    process: std::process::Child,
    log: PathBuf,
}

impl Served {
    pub(crate) async fn start(database: &str, extra: &[&str], log: PathBuf) -> Served {
        Served::start_with_env(database, extra, log, &[]).await
    }

    /// [`Served::start`] with `env` set for the process.
    pub(crate) async fn start_with_env(database: &str, extra: &[&str], log: PathBuf, env: &[(&str, &str)]) -> Served {
        let port = free_port();
        let mut args = vec!["serve".to_string(), "--bind".into(), format!("127.0.0.1:{port}"), "--database".into(), database.into()];
        args.extend(["--workers".into(), "1".into()]);
        args.extend(extra.iter().map(|s| s.to_string()));
        let process = Command::new(env!("CARGO_BIN_EXE_facegate"))
            .args(&args)
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .env_remove("FACEGATE_API_KEYS")
            .env_remove("FACEGATE_API_KEYS_FILE")
            .env_remove("FACEGATE_TEMPLATE_KEY_FILE")
            .env("RUST_LOG", "info")
            .envs(env.iter().copied())
            .stdin(Stdio::null())
            .stdout(std::fs::File::create(&log).unwrap())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let mut served = Served { base: format!("http://127.0.0.1:{port}"), process, log };
        let started = Instant::now();
        loop {
            if reqwest::get(format!("{}/health", served.base)).await.is_ok_and(|r| r.status() == 200) {
                return served;
            }
            assert!(served.process.try_wait().unwrap().is_none(), "the service exited: {}", served.log());
            assert!(started.elapsed() < Duration::from_secs(120), "the service did not come up: {}", served.log());
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    pub(crate) fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// POST alice with the IMM photo `photo` (JSON) to `path`.
    pub(crate) async fn post_alice(&self, path: &str, photo: &str) -> reqwest::Response {
        reqwest::Client::new()
            .post(format!("{}{path}", self.base))
            .json(&serde_json::json!({"subject": "alice", "image": crate::support::base64(&crate::support::imm(photo))}))
            .send()
            .await
            .unwrap()
    }
}

impl Drop for Served {
    fn drop(&mut self) {
        let _ = self.process.kill();
        let _ = self.process.wait();
    }
}

#[test]
fn an_api_key_setting_that_holds_no_key_stops_the_start_up() {
    let dir = Scratch::new("api-keys");
    let database = dir.url("facegate.db");
    for keys in [",,", " ", " , "] {
        serve_is_refused(&database, &["--api-keys", keys], &["--api-keys", "holds no key"]);
    }
    let comments = dir.file("api-keys", "# ops: one key per line\n\n   \n# (none yet)\n");
    let error = serve_is_refused(&database, &["--api-keys-file", &comments], &["--api-keys-file", "holds no key", &comments]);
    assert!(error.contains("FACEGATE_API_KEYS_FILE"), "{error}");
    // Keys given elsewhere do not excuse an empty file.
    serve_is_refused(&database, &["--api-keys-file", &comments, "--api-keys", "0123456789abcdef-flag"], &["--api-keys-file"]);
    // A short key still stops it (its place named, the key not shown).
    let error = serve_is_refused(&database, &["--api-keys", "short-secret"], &["--api-keys entry 1", "at least 16"]);
    assert!(!error.contains("short-secret"), "{error}");
}

/// Liveness enforced with no model to enforce it, or a threshold that is no probability, stops the
/// start-up rather than letting faces through unchecked.
#[test]
fn liveness_that_cannot_be_enforced_stops_the_start_up() {
    let dir = Scratch::new("liveness");
    let database = dir.url("facegate.db");
    // The committed models without liveness.bin (linked, not copied).
    let models = dir.0.join("models");
    std::fs::create_dir_all(&models).unwrap();
    for entry in std::fs::read_dir(facegate_paths::models_dir()).unwrap() {
        let entry = entry.unwrap();
        if entry.file_name() != facegate_vision::liveness::FILE {
            std::os::unix::fs::symlink(entry.path().canonicalize().unwrap(), models.join(entry.file_name())).unwrap();
        }
    }
    let models = models.display().to_string();
    serve_is_refused(&database, &["--models", &models, "--liveness", "enforce"], &["--liveness enforce", "liveness.bin"]);
    serve_is_refused(&database, &["--models", &models, "--liveness-threshold", "0.5"], &["--liveness-threshold", "no liveness model"]);
    for bad in ["--liveness-threshold=1.5", "--liveness-threshold=0", "--liveness-threshold=-0.2"] {
        serve_is_refused(&database, &[bad], &["--liveness-threshold", "between 0 and 1"]);
    }
}

fn template(seed: f32) -> Template {
    Template::new("v1", (0..16).map(|i| (i as f32 + seed).sin()).collect())
}

fn subject(s: &str) -> SubjectId {
    SubjectId::parse(s).unwrap()
}

/// A fresh database on `db`: a SQLite file in `dir`, or a PostgreSQL database.
fn fresh_database(db: Db, dir: &Scratch) -> String {
    match db {
        Db::Sqlite => dir.url("sealed.db"),
        Db::Postgres => crate::postgres::fresh_database().expect("the caller checked that PostgreSQL is available"),
    }
}

on_both_backends!(a_sealed_database_never_starts_without_the_key_that_opens_it);
async fn a_sealed_database_never_starts_without_the_key_that_opens_it(db: Db) {
    let dir = Scratch::new("sealed");
    let database = fresh_database(db, &dir);
    let sealed = Store::connect(&database, Some(ring(K1))).await.unwrap();
    for s in ["alice", "bob"] {
        sealed.enroll(&subject(s), &[template(1.0), template(2.0)]).await.unwrap();
    }
    let k1_id = sealed.template_key_id().unwrap().to_string();
    sealed.close().await;

    let error = serve_is_refused(&database, &[], &["--template-key-file", "no template key is configured", "2 subject(s)"]);
    assert!(error.contains("FACEGATE_TEMPLATE_KEY_FILE"), "{error}");
    let wrong = dir.file("wrong.key", &format!("{K2}\n"));
    serve_is_refused(&database, &["--template-key-file", &wrong], &["--template-key-file", &wrong, "cannot open", &k1_id]);
    // Nothing was written meanwhile: no subject stored plain.
    let check = Store::connect(&database, Some(ring(K1))).await.unwrap();
    assert_eq!(check.check_template_keys().await.unwrap(), KeyCheck::Opens { sealed_subjects: 2 });
    assert_eq!(check.sealing_counts().await.unwrap().plain, 0);
    check.close().await;

    // The right key starts it; `/health` (open mode: counts shown) says what it knows.
    let right = dir.file("right.key", &format!("# current\n{K1}\n"));
    let served = Served::start(&database, &["--template-key-file", &right], dir.0.join("serve.log")).await;
    let health: Value = reqwest::get(format!("{}/health", served.base)).await.unwrap().json().await.unwrap();
    let erasure = match db {
        Db::Sqlite => "live-database; backups-until-key-rotation",
        Db::Postgres => "queries; disk-and-backups-until-key-rotation",
    };
    assert_eq!(health["templates_encrypted"], true, "{health}");
    assert_eq!(health["template_key_id"].as_str(), Some(k1_id.as_str()), "{health}");
    assert_eq!((health["subjects_unencrypted"].as_u64(), health["subjects_on_older_keys"].as_u64()), (Some(0), Some(0)), "{health}");
    assert_eq!(health["erasure"], erasure, "{health}");
    assert!(served.log().contains("the template key opens the sealed subjects"), "{}", served.log());
}

fn config() -> ApiConfig {
    facegate::config::Settings::default().api_config().unwrap()
}

on_both_backends!(a_delete_says_what_it_erases);
async fn a_delete_says_what_it_erases(db: Db) {
    for keys in [None, Some(ring(K1))] {
        let encrypted = keys.is_some();
        let app = TestApp::start_with_keys(db, StandInEngine::new("v1"), config(), keys).await;
        assert_eq!(app.post_form("/enroll", Some("alice"), &[pattern_jpeg(320, 240, 1)]).await.status, 201);
        let r = app.delete("/subjects/alice").await;
        let expected = match (db, encrypted) {
            (Db::Sqlite, true) => "live-database; backups-until-key-rotation",
            (Db::Sqlite, false) => "live-database; backups-not-erased",
            (Db::Postgres, true) => "queries; disk-and-backups-until-key-rotation",
            (Db::Postgres, false) => "queries; disk-and-backups-not-erased",
        };
        assert_eq!(r.status, 204);
        assert_eq!(r.headers.get("facegate-erasure").and_then(|v| v.to_str().ok()), Some(expected), "{:?}", r.headers);
        let health = app.get("/health").await.json();
        assert_eq!(health["erasure"], expected, "{health}");
        assert_eq!(health.get("template_key_id").is_some(), encrypted, "{health}");
        assert_eq!((health["subjects_unencrypted"].as_u64(), health["subjects_on_older_keys"].as_u64()), (Some(0), Some(0)), "{health}");
        // Unknown: 404, no erasure claimed.
        let r = app.delete("/subjects/alice").await;
        r.assert_problem(404, "unknown-subject");
        assert!(r.headers.get("facegate-erasure").is_none());
    }
}

/// The app on `store`, opened on `database`, as `facegate serve` builds and runs it (without the
/// document checks of [`TestApp`], which always starts on a fresh database).
async fn serve_store(database: &str, store: Store) -> (String, tokio::task::JoinHandle<()>) {
    let app = Application::builder(crate::support::settings(database))
        .store(store)
        .engine(StandInEngine::new("v1"))
        .api_config(config())
        .build()
        .await
        .unwrap();
    let base = format!("http://{}", app.address());
    let server = tokio::spawn(app.run_until_stopped(std::future::pending()));
    (base, server)
}

async fn verify(base: &str, who: &str, photo: &[u8]) -> (u16, Value) {
    let form = reqwest::multipart::Form::new()
        .text("subject", who.to_string())
        .part("image", reqwest::multipart::Part::bytes(photo.to_vec()).file_name("probe.jpg"));
    let r = reqwest::Client::new().post(format!("{base}/verify")).multipart(form).send().await.unwrap();
    (r.status().as_u16(), r.json().await.unwrap_or(Value::Null))
}

/// `facegate` with `args` must succeed; its last stdout line as JSON.
fn facegate_ok(args: &[&str]) -> Value {
    let out = facegate(args);
    assert!(out.status.success(), "facegate {args:?}: {}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_str(String::from_utf8_lossy(&out.stdout).lines().last().unwrap()).unwrap()
}

/// docs/storage.md, "Erasure: what it covers": a DELETE reaches the live database, not a backup
/// taken before it; restored with the same key, the backup brings the subject back and it
/// verifies. Rotating the key (`facegate rekey`) and destroying the old one is what closes the
/// backup, and then all of it: the service refuses to start on it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_backup_from_before_a_delete_brings_the_subject_back_until_the_key_is_rotated() {
    let dir = Scratch::new("backup");
    let app = TestApp::start_with_keys(Db::Sqlite, StandInEngine::new("v1"), config(), Some(ring(K1))).await;
    let live = app.database_url.clone();
    let (alice, bob) = (pattern_jpeg(320, 240, 1), pattern_jpeg(320, 240, 9));
    assert_eq!(app.post_form("/enroll", Some("alice"), std::slice::from_ref(&alice)).await.status, 201);
    assert_eq!(app.post_form("/enroll", Some("bob"), std::slice::from_ref(&bob)).await.status, 201);

    let backup = dir.path("before-delete.db");
    assert_eq!(facegate_ok(&["backup", &backup, "--database", &live])["subjects"], 2);
    let r = app.delete("/subjects/alice").await;
    assert_eq!((r.status, r.headers["facegate-erasure"].to_str().unwrap()), (204, "live-database; backups-until-key-rotation"));
    app.post_form("/verify", Some("alice"), std::slice::from_ref(&alice)).await.assert_problem(404, "unknown-subject");

    // Restored with the same key: alice is back, and verifies.
    let restored = dir.url("restored.db");
    assert_eq!(facegate_ok(&["restore", &backup, "--database", &restored])["subjects"], 2);
    let store = Store::connect(&restored, Some(ring(K1))).await.unwrap();
    assert_eq!(store.check_template_keys().await.unwrap(), KeyCheck::Opens { sealed_subjects: 2 });
    let (base, server) = serve_store(&restored, store.clone()).await;
    let (status, answer) = verify(&base, "alice", &alice).await;
    assert_eq!((status, answer["match"].as_bool()), (200, Some(true)), "{answer}");
    server.abort();
    store.close().await;

    // Rotation: K2 first, K1 below; rekey; then K1 destroyed (K2 alone in the file).
    let both = dir.file("both.key", &format!("{K2}\n{K1}\n"));
    let report = facegate_ok(&["rekey", "--database", &live, "--template-key-file", &both]);
    assert_eq!((report["rewrapped"].as_u64(), report["sealed"].as_u64()), (Some(1), Some(0)), "{report}");
    let k2_only = dir.file("k2.key", &format!("{K2}\n"));
    let after = Store::connect(&live, Some(ring(K2))).await.unwrap();
    assert_eq!(after.check_template_keys().await.unwrap(), KeyCheck::Opens { sealed_subjects: 1 });
    assert_eq!(after.templates(&subject("bob")).await.unwrap().map(|t| t.len()), Some(1), "the live database opens with K2 alone");
    let k1_id = ring(K1).current_id().to_string();
    after.close().await;

    // The backup from before the rotation opens no more: not alice, and not bob either.
    let restored_again = dir.url("restored-after-rotation.db");
    facegate_ok(&["restore", &backup, "--database", &restored_again]);
    let store = Store::connect(&restored_again, Some(ring(K2))).await.unwrap();
    assert!(store.templates(&subject("alice")).await.is_err());
    assert!(store.templates(&subject("bob")).await.is_err());
    store.close().await;
    serve_is_refused(&restored_again, &["--template-key-file", &k2_only], &["--template-key-file", "cannot open", &k1_id]);
}
