//! SQLite's files: sealed bytes in the file, erasure, durability settings, backup and restore.
//!
//! A module of the crate root, not of `sqlite`, so the tests keep the names docs/storage.md cites
//! (`at_rest::…`).

use std::path::PathBuf;

use facegate_core::SubjectId;
use facegate_core::template::Template;

use crate::{KeyRing, Store, StoreError, restore, vector_to_blob};

const K1: &str = "000102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1e1f";

fn ring(text: &str) -> Option<KeyRing> {
    Some(KeyRing::parse(text).unwrap())
}

fn id(s: &str) -> SubjectId {
    SubjectId::parse(s).unwrap()
}

/// A vector whose bytes are easy to find in a file, different per `seed`.
fn marked(seed: f32) -> Template {
    Template { model_version: "m1".into(), vector: (0..32).map(|i| 1234.5678 + seed + i as f32 * 0.001).collect() }
}

struct Dir(PathBuf);

impl Dir {
    fn new() -> Dir {
        static N: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!("facegate-at-rest-{}-{n}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        Dir(dir)
    }
    fn url(&self, name: &str) -> String {
        format!("sqlite://{}", self.0.join(name).display())
    }
    /// The database file and its WAL, as bytes.
    fn raw(&self, name: &str) -> Vec<u8> {
        let mut bytes = std::fs::read(self.0.join(name)).unwrap();
        bytes.extend(std::fs::read(self.0.join(format!("{name}-wal"))).unwrap_or_default());
        bytes
    }
}

impl Drop for Dir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn contains(haystack: &[u8], needle: &[u8]) -> bool {
    haystack.windows(needle.len()).any(|w| w == needle)
}

/// Sealed vectors never reach the file (their round trip, wrong keys and tampered rows are
/// tested on both backends in tests/api/store_backends.rs).
#[tokio::test]
async fn sealed_templates_never_show_in_the_file() {
    let dir = Dir::new();
    let store = Store::connect(&dir.url("t.db"), ring(K1)).await.unwrap();
    store.enroll(&id("alice"), &[marked(0.0), marked(1.0)]).await.unwrap();
    assert_eq!(store.templates(&id("alice")).await.unwrap().unwrap(), [marked(0.0), marked(1.0)]);
    assert!(store.checkpoint().await.unwrap());
    let raw = dir.raw("t.db");
    assert!(contains(&raw, b"alice"));
    for template in [marked(0.0), marked(1.0)] {
        assert!(!contains(&raw, &vector_to_blob(&template.vector)[..16]), "a plain vector in the file");
    }
    store.close().await;
}

#[tokio::test]
async fn a_deleted_subject_leaves_nothing_in_the_files() {
    let dir = Dir::new();
    let store = Store::connect(&dir.url("t.db"), None).await.unwrap();
    let (secure, synchronous): (i64, i64) = (
        sqlx::query_scalar("PRAGMA secure_delete").fetch_one(&store.pool).await.unwrap(),
        sqlx::query_scalar("PRAGMA synchronous").fetch_one(&store.pool).await.unwrap(),
    );
    assert_eq!((secure, synchronous), (1, 2), "secure_delete on, synchronous FULL");
    let mode: String = sqlx::query_scalar("PRAGMA journal_mode").fetch_one(&store.pool).await.unwrap();
    assert_eq!(mode, "wal");
    let erased = "erasure-subject-7f3a";
    let erased_vectors = [marked(10.0), marked(20.0)];
    store.enroll(&id("keeper"), &[marked(30.0)]).await.unwrap();
    store.enroll(&id(erased), &erased_vectors).await.unwrap();
    store.enroll(&id("later"), &[marked(40.0)]).await.unwrap();
    let needles: Vec<Vec<u8>> = std::iter::once(erased.as_bytes().to_vec())
        .chain(erased_vectors.iter().flat_map(|t| vector_to_blob(&t.vector).chunks(16).map(<[u8]>::to_vec).collect::<Vec<_>>()))
        .collect();
    store.checkpoint().await.unwrap();
    let before = dir.raw("t.db");
    assert!(needles.iter().all(|n| contains(&before, n)), "the test must see the plain bytes before the deletion");

    assert_eq!(store.delete_subject(&id(erased)).await.unwrap(), Some(2));
    let after = dir.raw("t.db");
    for needle in &needles {
        assert!(!contains(&after, needle), "{needle:?} is still in the database files");
    }
    assert!(contains(&after, &vector_to_blob(&marked(30.0).vector)[..16]), "the others stay");
    store.close().await;
    let after_close = dir.raw("t.db");
    assert!(!needles.iter().any(|n| contains(&after_close, n)));
}

/// The pool opens the file the URL names, also with characters a URL escapes (`%25` is `%`),
/// and after `close` that file holds everything (no WAL content is left beside it).
#[tokio::test]
async fn the_file_named_is_the_file_opened() {
    let dir = Dir::new();
    for (name, file) in [("with space.db", "with space.db"), ("per%25cent #1.db", "per%cent #1.db"), ("ünï.db", "ünï.db")] {
        let store = Store::connect(&dir.url(name), None).await.unwrap();
        store.enroll(&id("alice"), &[marked(0.0)]).await.unwrap();
        store.close().await;
        let mut files: Vec<String> = std::fs::read_dir(&dir.0).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
        files.sort();
        assert_eq!(files[0], file, "{files:?}");
        assert!(files[1..].iter().all(|f| *f == format!("{file}-shm") || *f == format!("{file}-wal")), "{files:?}");
        assert_eq!(std::fs::metadata(dir.0.join(format!("{file}-wal"))).map_or(0, |m| m.len()), 0, "the WAL is empty");
        let reopened = Store::connect(&dir.url(name), None).await.unwrap();
        assert_eq!(reopened.templates(&id("alice")).await.unwrap().unwrap(), [marked(0.0)]);
        reopened.close().await;
        // SQLite removes the -wal and -shm files when its last connection closes, on the
        // connection's worker thread, which may still be running: one may vanish meanwhile.
        for entry in std::fs::read_dir(&dir.0).unwrap() {
            match std::fs::remove_file(entry.unwrap().path()) {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => panic!("{e}"),
                _ => {}
            }
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn backup_while_in_use_then_restore() {
    let dir = Dir::new();
    let store = Store::connect(&dir.url("live.db"), ring(K1)).await.unwrap();
    for i in 0..40 {
        store.enroll(&id(&format!("s{i:02}")), &[marked(i as f32), marked(i as f32 + 0.5)]).await.unwrap();
    }
    // Enrolments keep coming while the backup runs.
    let writer = {
        let store = store.clone();
        tokio::spawn(async move {
            for i in 0..200 {
                store.enroll(&id(&format!("w{i:03}")), &[marked(100.0 + i as f32)]).await.unwrap();
            }
        })
    };
    let backup = dir.0.join("backup.db");
    store.backup(&backup).await.unwrap();
    assert!(matches!(store.backup(&backup).await, Err(StoreError::Refused(_))), "never overwrites");
    writer.await.unwrap();
    let (live_subjects, _) = store.counts().await.unwrap();
    assert_eq!(live_subjects, 240);

    // Restore to a new place: every subject of the backup reads back the same.
    let (subjects, templates) = restore(&backup, &dir.url("restored.db"), false).await.unwrap();
    assert!((40..=240).contains(&subjects) && templates == 80 + (subjects - 40), "{subjects} {templates}");
    let restored = Store::connect(&dir.url("restored.db"), ring(K1)).await.unwrap();
    for i in 0..40 {
        let s = id(&format!("s{i:02}"));
        assert_eq!(restored.templates(&s).await.unwrap(), store.templates(&s).await.unwrap());
    }
    assert_eq!(restored.counts().await.unwrap(), (subjects, templates));

    // Not over an existing database unless told, and never over one in use.
    assert!(matches!(restore(&backup, &dir.url("live.db"), false).await, Err(StoreError::Refused(_))));
    let refused = restore(&backup, &dir.url("restored.db"), true).await;
    assert!(matches!(refused, Err(StoreError::Refused(ref m)) if m.contains("in use")), "{refused:?}");
    restored.close().await;
    store.close().await;
    assert_eq!(restore(&backup, &dir.url("live.db"), true).await.unwrap(), (subjects, templates));
    let back = Store::connect(&dir.url("live.db"), ring(K1)).await.unwrap();
    assert_eq!(back.counts().await.unwrap(), (subjects, templates));
    assert_eq!(back.templates(&id("s07")).await.unwrap().unwrap(), [marked(7.0), marked(7.5)]);
    back.close().await;
    // Not a database at all.
    std::fs::write(dir.0.join("junk.db"), b"not sqlite").unwrap();
    assert!(restore(&dir.0.join("junk.db"), &dir.url("other.db"), false).await.is_err());
}

/// The start-up check: whether the configured keys open what the database holds, and the counts
/// `/health` reports.
#[tokio::test]
async fn the_key_check_tells_a_missing_or_wrong_key_from_the_right_one() {
    use crate::{KeyCheck, SealingCounts};
    const K2: &str = "ff0102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1eff";
    let dir = Dir::new();
    let url = dir.url("t.db");
    let plain = Store::connect(&url, None).await.unwrap();
    assert!(!plain.holds_sealed_templates().await.unwrap());
    assert_eq!(plain.check_template_keys().await.unwrap(), KeyCheck::NothingSealed);
    plain.enroll(&id("plain"), &[marked(0.0)]).await.unwrap();
    assert_eq!(plain.check_template_keys().await.unwrap(), KeyCheck::NothingSealed, "plain subjects need no key");
    assert_eq!(plain.sealing_counts().await.unwrap(), SealingCounts { plain: 1, current_key: 0, other_keys: 0 });
    assert_eq!(plain.template_key_id(), None);
    plain.close().await;

    let k1 = Store::connect(&url, ring(K1)).await.unwrap();
    assert_eq!(k1.check_template_keys().await.unwrap(), KeyCheck::NothingSealed);
    for s in ["a", "b", "c", "d"] {
        k1.enroll(&id(s), &[marked(1.0)]).await.unwrap();
    }
    assert!(k1.holds_sealed_templates().await.unwrap());
    assert_eq!(k1.check_template_keys().await.unwrap(), KeyCheck::Opens { sealed_subjects: 4 });
    assert_eq!(k1.sealing_counts().await.unwrap(), SealingCounts { plain: 1, current_key: 4, other_keys: 0 });
    let k1_id = k1.template_key_id().unwrap().to_string();

    // One damaged wrapped data key (the first sampled) is that subject's problem, not a wrong key.
    let mut wrapped: Vec<u8> = sqlx::query_scalar("SELECT data_key FROM subjects WHERE id = 'a'").fetch_one(&k1.pool).await.unwrap();
    wrapped[20] ^= 1;
    sqlx::query("UPDATE subjects SET data_key = $1 WHERE id = 'a'").bind(wrapped).execute(&k1.pool).await.unwrap();
    assert_eq!(k1.check_template_keys().await.unwrap(), KeyCheck::Opens { sealed_subjects: 4 });
    k1.close().await;

    let none = Store::connect(&url, None).await.unwrap();
    assert_eq!(none.check_template_keys().await.unwrap(), KeyCheck::NoKey { sealed_subjects: 4 });
    none.close().await;
    let wrong = Store::connect(&url, ring(K2)).await.unwrap();
    let check = wrong.check_template_keys().await.unwrap();
    assert!(
        matches!(&check, KeyCheck::CannotOpen { key_id, subjects: 4, reason: crate::CipherError::UnknownKey(_) } if *key_id == k1_id),
        "{check:?}"
    );
    wrong.close().await;

    // Rotating: K2 current with K1 below opens both; after rekey K2 alone does.
    let rotating = Store::connect(&url, ring(&format!("{K2}\n{K1}"))).await.unwrap();
    rotating.enroll(&id("e"), &[marked(2.0)]).await.unwrap();
    assert_eq!(rotating.check_template_keys().await.unwrap(), KeyCheck::Opens { sealed_subjects: 5 });
    assert_eq!(rotating.sealing_counts().await.unwrap(), SealingCounts { plain: 1, current_key: 1, other_keys: 4 });
    // `a`'s damaged key stops its own re-wrap; the others are re-wrapped.
    assert!(rotating.rekey(|_| {}).await.is_err());
    sqlx::query("DELETE FROM subjects WHERE id = 'a'").execute(&rotating.pool).await.unwrap();
    rotating.rekey(|_| {}).await.unwrap();
    assert_eq!(rotating.sealing_counts().await.unwrap(), SealingCounts { plain: 0, current_key: 5, other_keys: 0 });
    rotating.close().await;
    let k2 = Store::connect(&url, ring(K2)).await.unwrap();
    assert_eq!(k2.check_template_keys().await.unwrap(), KeyCheck::Opens { sealed_subjects: 5 });
    k2.close().await;
    let old = Store::connect(&url, ring(K1)).await.unwrap();
    assert!(matches!(old.check_template_keys().await.unwrap(), KeyCheck::CannotOpen { subjects: 5, .. }));
    old.close().await;
}

/// A database that cannot be reached fails within the acquire timeout and says it is unavailable;
/// a refused request does not.
#[tokio::test]
async fn an_unreachable_database_fails_fast_and_is_told_apart() {
    // Nothing listens on a port just released.
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let started = std::time::Instant::now();
    let error = Store::connect(&format!("postgres://facegate@127.0.0.1:{port}/facegate"), None).await.unwrap_err();
    let waited = started.elapsed();
    assert!(error.is_unavailable(), "{error:?}");
    assert!(waited < crate::ACQUIRE_TIMEOUT + std::time::Duration::from_secs(3), "waited {waited:?}");

    let dir = Dir::new();
    let store = Store::connect(&dir.url("t.db"), None).await.unwrap();
    let refused = sqlx::query("INSERT INTO subjects (id) VALUES (NULL)").execute(&store.pool).await.map_err(StoreError::from).unwrap_err();
    assert!(!refused.is_unavailable(), "{refused:?}");
    assert!(!StoreError::NoKey { subject: "a".into() }.is_unavailable());
    store.close().await;
    let closed = store.ping().await.unwrap_err();
    assert!(closed.is_unavailable(), "{closed:?}");
    // SQLite's file cannot be opened (its folder is a file).
    std::fs::write(dir.0.join("not-a-dir"), b"").unwrap();
    let error = Store::connect(&dir.url("not-a-dir/t.db"), None).await.unwrap_err();
    assert!(error.is_unavailable(), "{error:?}");
}
