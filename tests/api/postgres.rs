//! A real PostgreSQL server for the tests: `FACEGATE_TEST_POSTGRES` (an admin URL such as
//! `postgres://postgres@127.0.0.1:5432/postgres`) when given, otherwise a throwaway cluster
//! started from Debian's `postgresql` package (`initdb` + `pg_ctl`) in a temporary directory, as
//! the unprivileged `postgres` user when the tests run as root. One server per test process; each
//! caller gets a fresh database in it ([`fresh_database`]).
//!
//! Where no server can be had, [`fresh_database`] returns `None` and the caller prints the reason
//! and skips ([`skip`]), never silently. CI sets `FACEGATE_REQUIRE_POSTGRES=1`, which turns the
//! skip into a failure, so a CI machine without a server fails rather than passing without testing.

use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::OnceLock;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// The server the tests share: how to reach it as its superuser, or why there is none.
struct Server {
    /// `postgres://user@host:port` (no database).
    base: String,
}

static SERVER: OnceLock<Result<Server, String>> = OnceLock::new();

/// A new, empty database on the test server, as a URL; `None` when no server can be started
/// (the reason is in [`unavailable`]).
pub fn fresh_database() -> Option<String> {
    static N: AtomicUsize = AtomicUsize::new(0);
    let server = SERVER.get_or_init(start).as_ref().ok()?;
    let name = format!("facegate_{}_{}", std::process::id(), N.fetch_add(1, Ordering::Relaxed));
    let admin = format!("{}/postgres", server.base);
    let out = Command::new(client_bin("psql"))
        .args([admin.as_str(), "-v", "ON_ERROR_STOP=1", "-qc", &format!("CREATE DATABASE {name}")])
        .output()
        .expect("psql runs");
    assert!(out.status.success(), "CREATE DATABASE {name}: {}", String::from_utf8_lossy(&out.stderr));
    Some(format!("{}/{name}", server.base))
}

/// Is there a test server (started now if not yet)? Creates no database.
pub fn available() -> bool {
    SERVER.get_or_init(start).is_ok()
}

/// Why there is no test server (after [`fresh_database`] returned `None`).
pub fn unavailable() -> String {
    match SERVER.get_or_init(start) {
        Ok(_) => "the server is available".to_string(),
        Err(why) => why.clone(),
    }
}

/// Print why a PostgreSQL test is skipped; panic instead when `FACEGATE_REQUIRE_POSTGRES` is set.
pub fn skip(test: &str) {
    let why = unavailable();
    if std::env::var_os("FACEGATE_REQUIRE_POSTGRES").is_some_and(|v| !v.is_empty() && v != "0") {
        panic!("{test}: PostgreSQL is required (FACEGATE_REQUIRE_POSTGRES) but unavailable: {why}");
    }
    eprintln!("SKIPPED {test}: no PostgreSQL server: {why}");
}

/// A fresh database, or skip the calling test with its reason printed.
#[macro_export]
macro_rules! postgres_or_skip {
    ($test:expr) => {
        match $crate::postgres::fresh_database() {
            Some(url) => url,
            None => {
                $crate::postgres::skip($test);
                return;
            }
        }
    };
}

fn start() -> Result<Server, String> {
    if let Ok(url) = std::env::var("FACEGATE_TEST_POSTGRES") {
        let base = url.trim_end_matches('/').rsplit_once('/').map(|(base, _db)| base.to_string()).unwrap_or(url.clone());
        return Ok(Server { base });
    }
    let bin = server_bin_dir().ok_or("no initdb on PATH or under /usr/lib/postgresql/*/bin (apt-get install postgresql)")?;
    let dir = std::env::temp_dir().join(format!("facegate-pg-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let as_user = if is_root() { Some("postgres") } else { None };
    if let Some(user) = as_user {
        let ok = Command::new("chown").args([user, dir.to_str().unwrap()]).status().map(|s| s.success()).unwrap_or(false);
        if !ok {
            return Err(format!("running as root, and cannot hand {} to the {user} user", dir.display()));
        }
    }
    let data = dir.join("data");
    let port = free_port().map_err(|e| format!("no free port: {e}"))?;
    run(as_user, &bin.join("initdb"), &["-D", data.to_str().unwrap(), "-A", "trust", "-U", "postgres", "-E", "UTF8", "--no-sync"])?;
    // fsync off: the tests never cut the power, and it keeps them fast on a shared disk.
    let options = format!("-p {port} -k {} -c listen_addresses=127.0.0.1 -c fsync=off -c max_connections=200", dir.display());
    let log = dir.join("server.log");
    run(
        as_user,
        &bin.join("pg_ctl"),
        &["-D", data.to_str().unwrap(), "-l", log.to_str().unwrap(), "-o", &options, "-w", "-t", "60", "start"],
    )?;
    watch_over(as_user, &bin, &data, &dir);
    let base = format!("postgres://postgres@127.0.0.1:{port}");
    wait_ready(&format!("{base}/postgres"))?;
    Ok(Server { base })
}

/// Stop the cluster and remove its directory once this test process has exited (statics are
/// never dropped, so a detached shell waits for the process to go).
fn watch_over(as_user: Option<&str>, bin: &Path, data: &Path, dir: &Path) {
    let stop = format!("{} -D {} stop -m immediate", bin.join("pg_ctl").display(), data.display());
    let stop = match as_user {
        Some(user) => format!("runuser -u {user} -- {stop}"),
        None => stop,
    };
    let script =
        format!("while kill -0 {} 2>/dev/null; do sleep 1; done; {stop} >/dev/null 2>&1; rm -rf {}", std::process::id(), dir.display());
    let _ = Command::new("sh").args(["-c", &script]).stdin(Stdio::null()).stdout(Stdio::null()).stderr(Stdio::null()).spawn();
}

fn run(as_user: Option<&str>, program: &Path, args: &[&str]) -> Result<(), String> {
    let mut command = match as_user {
        Some(user) => {
            let mut c = Command::new("runuser");
            c.args(["-u", user, "--"]).arg(program);
            c
        }
        None => Command::new(program),
    };
    let out = command.args(args).stdin(Stdio::null()).output().map_err(|e| format!("{}: {e}", program.display()))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!("{} failed: {}{}", program.display(), String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr)))
    }
}

fn wait_ready(url: &str) -> Result<(), String> {
    let started = Instant::now();
    loop {
        let out = Command::new(client_bin("psql")).args([url, "-qAtc", "SELECT 1"]).output().map_err(|e| format!("psql: {e}"))?;
        if out.status.success() {
            return Ok(());
        }
        if started.elapsed() > Duration::from_secs(30) {
            return Err(format!("the server did not answer: {}", String::from_utf8_lossy(&out.stderr)));
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// The directory holding `initdb` and `pg_ctl`: on PATH, or Debian's versioned directory.
fn server_bin_dir() -> Option<PathBuf> {
    let on_path = std::env::var_os("PATH")
        .into_iter()
        .flat_map(|p| std::env::split_paths(&p).collect::<Vec<_>>())
        .find(|d| d.join("initdb").is_file() && d.join("pg_ctl").is_file());
    on_path.or_else(|| {
        let mut versions: Vec<PathBuf> = std::fs::read_dir("/usr/lib/postgresql").ok()?.flatten().map(|e| e.path().join("bin")).collect();
        versions.sort();
        versions.into_iter().rev().find(|d| d.join("initdb").is_file())
    })
}

/// `psql` (and friends): next to the server binaries when found there, else from PATH.
fn client_bin(name: &str) -> PathBuf {
    server_bin_dir().map(|d| d.join(name)).filter(|p| p.is_file()).unwrap_or_else(|| PathBuf::from(name))
}

fn is_root() -> bool {
    Command::new("id").arg("-u").output().map(|o| String::from_utf8_lossy(&o.stdout).trim() == "0").unwrap_or(false)
}

fn free_port() -> std::io::Result<u16> {
    Ok(TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
}

#[test]
fn a_fresh_database_answers() {
    let Some(url) = fresh_database() else {
        skip("postgres::a_fresh_database_answers");
        return;
    };
    let out = Command::new(client_bin("psql")).args([url.as_str(), "-qAtc", "SELECT current_database()"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(url.ends_with(String::from_utf8_lossy(&out.stdout).trim()), "{url}");
}
