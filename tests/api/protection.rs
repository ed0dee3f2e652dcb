//! Protected templates through the real binary: with `--template-protection-key-file` the stored
//! templates are keyed rotations (model version `…+rot-<key id>`), verification matches as before
//! at the same threshold, the database file holds no 16-byte piece of the plain template, and a
//! database of plain templates, of protected ones without the key, or of another secret's stops the
//! start-up with a message saying what to do.

use facegate::service::SubjectId;
use facegate::store::Store;
use serde_json::Value;

use crate::fail_closed::{Scratch, Served, serve_is_refused};

const SECRET_A: &str = "5e5e5e5e000102030405060708090a0b0c0d0e0f101112131415161718191a1b";
const SECRET_B: &str = "7a7a7a7a000102030405060708090a0b0c0d0e0f101112131415161718191a1b";

/// alice's stored templates' model version and vector bytes (little-endian f32).
async fn stored(database: &str) -> (String, Vec<u8>) {
    let store = Store::connect(database, None).await.unwrap();
    let templates = store.templates(&SubjectId::parse("alice").unwrap()).await.unwrap().unwrap();
    store.close().await;
    (templates[0].model_version.clone(), templates[0].vector.iter().flat_map(|v| v.to_le_bytes()).collect())
}

/// Whether any 16-byte piece of `needle` occurs in `haystack`.
fn holds_any_piece(haystack: &[u8], needle: &[u8]) -> bool {
    needle.windows(16).any(|piece| haystack.windows(16).any(|w| w == piece))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn protected_templates_verify_as_plain_ones_and_hold_nothing_of_them() {
    let dir = Scratch::new("protection");
    let key_a = dir.file("protection-a.key", &format!("# openssl rand -hex 32\n{SECRET_A}\n"));
    let key_b = dir.file("protection-b.key", SECRET_B);
    let (plain_db, protected_db) = (dir.url("plain.db"), dir.url("protected.db"));

    // The same enrolment and verification, plain and protected.
    let mut answers = Vec::new();
    for (database, extra) in [(&plain_db, vec![]), (&protected_db, vec!["--template-protection-key-file", key_a.as_str()])] {
        let served = Served::start(database, &extra, dir.0.join(format!("serve-{}.log", answers.len()))).await;
        assert_eq!(served.post_alice("/enroll", "01-1m.jpg").await.status(), 201, "{}", served.log());
        let verified: Value = served.post_alice("/verify", "01-2m.jpg").await.json().await.unwrap();
        let stranger: Value = served.post_alice("/verify", "05-1m.jpg").await.json().await.unwrap();
        answers.push((verified, stranger, served.log()));
    }
    let ((plain, plain_stranger, _), (protected, protected_stranger, log)) = (&answers[0], &answers[1]);
    assert_eq!((plain["match"].as_bool(), protected["match"].as_bool()), (Some(true), Some(true)), "{protected}");
    assert_eq!((plain_stranger["match"].as_bool(), protected_stranger["match"].as_bool()), (Some(false), Some(false)));
    // A rotation keeps every cosine: the same score (to float rounding) and the same threshold.
    assert!((plain["score"].as_f64().unwrap() - protected["score"].as_f64().unwrap()).abs() < 1e-4, "{plain} {protected}");
    assert_eq!(plain["threshold"], protected["threshold"]);
    assert!(log.contains("templates are protected"), "{log}");

    let (plain_version, plain_bytes) = stored(&plain_db).await;
    let (protected_version, protected_bytes) = stored(&protected_db).await;
    assert!(protected_version.starts_with(&format!("{plain_version}+rot-")), "{protected_version}");
    assert_eq!(protected["model_version"].as_str(), Some(protected_version.as_str()), "{protected}");
    assert_eq!(plain_bytes.len(), protected_bytes.len());
    // Nothing of the plain template in the protected database's file (the control: the plain
    // database's file holds it).
    let file = |url: &str| std::fs::read(url.trim_start_matches("sqlite://")).unwrap();
    assert!(holds_any_piece(&file(&plain_db), &plain_bytes), "the scan finds a plain template where there is one");
    assert!(!holds_any_piece(&file(&protected_db), &plain_bytes), "a 16-byte piece of the plain template is stored");

    // One kind of template per database, of one secret.
    serve_is_refused(&plain_db, &["--template-protection-key-file", &key_a], &["holds plain templates", "enrol the subjects again"]);
    serve_is_refused(&protected_db, &[], &["holds protected templates", "--template-protection-key-file"]);
    serve_is_refused(&protected_db, &["--template-protection-key-file", &key_b], &["another secret"]);
    let bad = dir.file("bad.key", "not a key");
    serve_is_refused(&protected_db, &["--template-protection-key-file", &bad], &["not 64 hex digits"]);
}
