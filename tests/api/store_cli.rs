//! `facegate rekey`, `facegate backup` and `facegate restore`: the real binary on a real database.

use std::path::Path;

use facegate_core::SubjectId;
use facegate_core::template::Template;
use facegate_store::{KeyRing, Store};
use serde_json::Value;

/// Run `facegate` with `args`; its exit status and stdout's JSON line (null when none).
fn facegate(args: &[&str]) -> (bool, Value) {
    let (ok, json, _) = facegate_with_stderr(args);
    (ok, json)
}

/// [`facegate`], with what it wrote to stderr (for the message of a failed assertion).
fn facegate_with_stderr(args: &[&str]) -> (bool, Value, String) {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_facegate")).args(args).output().unwrap();
    let json = String::from_utf8_lossy(&out.stdout).lines().last().map_or(Value::Null, |l| serde_json::from_str(l).unwrap());
    (out.status.success(), json, String::from_utf8_lossy(&out.stderr).into_owned())
}

fn template(seed: f32) -> Template {
    Template::new("v1", (0..16).map(|i| (i as f32 + seed).sin()).collect())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rekey_backup_and_restore_from_the_command_line() {
    let dir = std::env::temp_dir().join(format!("facegate-store-cli-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let path = |name: &str| dir.join(name).display().to_string();
    let url = |name: &str| format!("sqlite://{}", path(name));
    let subjects: Vec<(SubjectId, Vec<Template>)> =
        (0..3).map(|i| (SubjectId::parse(&format!("s{i}")).unwrap(), vec![template(i as f32), template(i as f32 + 0.5)])).collect();
    let plain = Store::connect(&url("live.db"), None).await.unwrap();
    for (subject, templates) in &subjects {
        plain.enroll(subject, templates).await.unwrap();
    }
    plain.close().await;

    let key = "3c".repeat(32);
    std::fs::write(dir.join("key"), format!("{key}\n")).unwrap();
    let (ok, report) = facegate(&["rekey", "--database", &url("live.db"), "--template-key-file", &path("key")]);
    assert!(ok);
    assert_eq!((report["sealed"].as_u64(), report["templates_sealed"].as_u64(), report["rewrapped"].as_u64()), (Some(3), Some(6), Some(0)));
    assert!(!facegate(&["rekey", "--database", &url("live.db")]).0, "rekey needs a key");

    // The backup is taken while the database is open by another process's pool (this test's).
    let live = Store::connect(&url("live.db"), Some(KeyRing::parse(&key).unwrap())).await.unwrap();
    let (ok, report) = facegate(&["backup", &path("backup.db"), "--database", &url("live.db")]);
    assert!(ok);
    assert_eq!((report["subjects"].as_u64(), report["templates"].as_u64()), (Some(3), Some(6)));
    assert!(!facegate(&["backup", &path("backup.db"), "--database", &url("live.db")]).0, "a backup never overwrites");

    assert!(!facegate(&["restore", &path("backup.db"), "--database", &url("live.db")]).0, "not over a database unless told");
    assert!(!facegate(&["restore", &path("backup.db"), "--database", &url("live.db"), "--force"]).0, "never over one in use");
    let (ok, report) = facegate(&["restore", &path("backup.db"), "--database", &url("restored.db")]);
    assert!(ok && report["subjects"] == 3, "{report}");
    let restored = Store::connect(&url("restored.db"), Some(KeyRing::parse(&key).unwrap())).await.unwrap();
    for (subject, templates) in &subjects {
        assert_eq!(restored.templates(subject).await.unwrap().as_ref(), Some(templates));
        assert_eq!(live.templates(subject).await.unwrap().as_ref(), Some(templates));
    }
    restored.close().await;
    live.close().await;
    let (ok, _, stderr) = facegate_with_stderr(&["restore", &path("backup.db"), "--database", &url("live.db"), "--force"]);
    assert!(ok, "restore over the closed database: {stderr}");
    assert!(Path::new(&path("live.db")).exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// On PostgreSQL, `rekey` works as on SQLite; `backup` and `restore` (SQLite file operations)
/// refuse, naming pg_dump and pg_restore.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn on_postgres_rekey_works_and_backup_restore_name_pg_dump() {
    let url = crate::postgres_or_skip!("store_cli::on_postgres_rekey_works_and_backup_restore_name_pg_dump");
    let dir = std::env::temp_dir().join(format!("facegate-store-cli-pg-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let path = |name: &str| dir.join(name).display().to_string();
    let plain = Store::connect(&url, None).await.unwrap();
    let subject = SubjectId::parse("s0").unwrap();
    plain.enroll(&subject, &[template(0.0), template(1.0)]).await.unwrap();
    plain.close().await;

    let key = "5d".repeat(32);
    std::fs::write(dir.join("key"), format!("{key}\n")).unwrap();
    let (ok, report, stderr) = facegate_with_stderr(&["rekey", "--database", &url, "--template-key-file", &path("key")]);
    assert!(ok, "{stderr}");
    assert_eq!((report["sealed"].as_u64(), report["templates_sealed"].as_u64()), (Some(1), Some(2)));
    let keyed = Store::connect(&url, Some(KeyRing::parse(&key).unwrap())).await.unwrap();
    assert_eq!(keyed.templates(&subject).await.unwrap().unwrap(), [template(0.0), template(1.0)]);
    keyed.close().await;

    let (ok, _, stderr) = facegate_with_stderr(&["backup", &path("backup.db"), "--database", &url]);
    assert!(!ok && stderr.contains("pg_dump"), "{stderr}");
    assert!(!Path::new(&path("backup.db")).exists());
    std::fs::write(dir.join("backup.db"), b"anything").unwrap();
    let (ok, _, stderr) = facegate_with_stderr(&["restore", &path("backup.db"), "--database", &url, "--force"]);
    assert!(!ok && stderr.contains("pg_restore"), "{stderr}");
    std::fs::remove_dir_all(&dir).unwrap();
}
