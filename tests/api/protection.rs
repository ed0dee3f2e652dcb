//! Protected templates through the real binary: with `--template-protection-key-file` the stored
//! templates are keyed rotations (model version `…+rot-<key id>`), verification and identification match as before
//! at the same threshold, the database file holds no 16-byte piece of the plain template, and a
//! database of plain templates, of protected ones without the key, or of another secret's stops the
//! start-up with a message saying what to do.

use facegate_core::SubjectId;
use facegate_store::Store;
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
        // The identification gallery searches the same (protected) templates.
        let identified: Value = reqwest::Client::new()
            .post(format!("{}/identify", served.base))
            .json(&serde_json::json!({"image": crate::support::base64(&crate::support::imm("01-2m.jpg"))}))
            .send()
            .await
            .unwrap()
            .json()
            .await
            .unwrap();
        let best = &identified["candidates"][0];
        assert_eq!(best["subject"].as_str(), Some("alice"), "{identified}");
        assert!((best["score"].as_f64().unwrap() - verified["score"].as_f64().unwrap()).abs() < 1e-4, "{identified} {verified}");
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

/// alice's stored templates (model version, vector) opened with `template_key` when sealed.
async fn stored_with(database: &str, template_key: Option<&str>) -> Vec<(String, Vec<f32>)> {
    let keys = template_key.map(|k| facegate_store::KeyRing::parse(k).unwrap());
    let store = Store::connect(database, keys).await.unwrap();
    let templates = store.templates(&SubjectId::parse("alice").unwrap()).await.unwrap().unwrap();
    store.close().await;
    templates.into_iter().map(|t| (t.model_version, t.vector)).collect()
}

/// `facegate renew-protection` with `args`: its success and its JSON line (null when none), and stderr.
fn renew(args: &[&str]) -> (bool, Value, String) {
    let mut all = vec!["renew-protection"];
    all.extend_from_slice(args);
    let out = crate::fail_closed::facegate(&all);
    let json = String::from_utf8_lossy(&out.stdout).lines().last().map_or(Value::Null, |l| serde_json::from_str(l).unwrap());
    (out.status.success(), json, String::from_utf8_lossy(&out.stderr).into_owned())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_new_secret_renews_the_stored_templates_without_the_photos() {
    use facegate_service::protection::ProtectionKey;
    let dir = Scratch::new("renewal");
    let key_a = dir.file("protection-a.key", SECRET_A);
    let key_b = dir.file("protection-b.key", SECRET_B);
    let key_c = dir.file("protection-c.key", &"c0".repeat(32));
    let database = dir.url("renewed.db");
    let id_b = ProtectionKey::parse(SECRET_B).unwrap().id();

    // Enrolled under secret A.
    let served = Served::start(&database, &["--template-protection-key-file", &key_a], dir.0.join("serve-a.log")).await;
    assert_eq!(served.post_alice("/enroll", "01-1m.jpg").await.status(), 201, "{}", served.log());
    let before: Value = served.post_alice("/verify", "01-2m.jpg").await.json().await.unwrap();
    drop(served);
    let (version_a, bytes_a) = stored(&database).await;
    // A site calibration of A's templates (as `facegate calibrate` stores it), to be carried over.
    let calibration = serde_json::json!({
        "model_version": version_a, "subjects": 1, "templates": 1, "impostor_pairs": 0,
        "points": [{"fmr": 1e-3, "threshold": -1.0}]
    });
    let store = Store::connect(&database, None).await.unwrap();
    store.set_site_calibration(&version_a, &calibration.to_string()).await.unwrap();
    store.close().await;

    let (ok, report, stderr) = renew(&["--database", &database, "--old-key-file", &key_a, "--new-key-file", &key_b]);
    assert!(ok, "{stderr}");
    assert_eq!((report["subjects"].as_u64(), report["templates"].as_u64()), (Some(1), Some(1)), "{report}");
    assert_eq!(report["versions"][0]["calibration"], true, "{report}");

    // Another model version, other bytes: nothing of the old template is left.
    let (version_b, bytes_b) = stored(&database).await;
    assert_eq!(version_b, version_a.replace(&version_a[version_a.len() - 8..], &id_b), "{version_a} → {version_b}");
    assert!(!holds_any_piece(&bytes_b, &bytes_a), "a 16-byte piece of the old protected template is still stored");
    let file = std::fs::read(database.trim_start_matches("sqlite://")).unwrap();
    assert!(!holds_any_piece(&file, &bytes_a), "a 16-byte piece of the old protected template is left in the file");
    let store = Store::connect(&database, None).await.unwrap();
    assert_eq!(store.site_calibration(&version_a).await.unwrap(), None);
    let moved: Value = serde_json::from_str(&store.site_calibration(&version_b).await.unwrap().unwrap()).unwrap();
    assert_eq!(moved["model_version"].as_str(), Some(version_b.as_str()), "{moved}");
    store.close().await;

    // The old secret no longer starts the service; the new one verifies the same subject.
    serve_is_refused(&database, &["--template-protection-key-file", &key_a], &["another secret", "renew-protection"]);
    let served = Served::start(&database, &["--template-protection-key-file", &key_b], dir.0.join("serve-b.log")).await;
    let after: Value = served.post_alice("/verify", "01-2m.jpg").await.json().await.unwrap();
    let stranger: Value = served.post_alice("/verify", "05-1m.jpg").await.json().await.unwrap();
    drop(served);
    assert_eq!((after["match"].as_bool(), stranger["match"].as_bool()), (Some(true), Some(false)), "{after} {stranger}");
    assert!((before["score"].as_f64().unwrap() - after["score"].as_f64().unwrap()).abs() < 1e-4, "{before} {after}");
    assert_eq!(after["model_version"].as_str(), Some(version_b.as_str()));

    // Done once: again, nothing changes; a secret the database was never under is refused.
    let (ok, again, stderr) = renew(&["--database", &database, "--old-key-file", &key_a, "--new-key-file", &key_b]);
    assert!(ok && again["already_renewed"] == true && again["templates"] == 0, "{again} {stderr}");
    let (ok, _, stderr) = renew(&["--database", &database, "--old-key-file", &key_c, "--new-key-file", &key_a]);
    assert!(!ok && stderr.contains("holds no template protected under the old secret"), "{stderr}");
    let (ok, _, stderr) = renew(&["--database", &database, "--old-key-file", &key_b, "--new-key-file", &key_b]);
    assert!(!ok && stderr.contains("the same"), "{stderr}");
    assert_eq!(stored(&database).await, (version_b, bytes_b));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn plain_templates_are_protected_in_place_sealed_ones_sealed_again() {
    let dir = Scratch::new("from-plain");
    let key_b = dir.file("protection-b.key", SECRET_B);
    let template_key = "3c".repeat(32);
    let template_key_file = dir.file("templates.key", &template_key);
    let database = dir.url("plain.db");
    let sealed = ["--template-key-file", template_key_file.as_str()];

    let served = Served::start(&database, &sealed, dir.0.join("serve-plain.log")).await;
    assert_eq!(served.post_alice("/enroll", "01-1m.jpg").await.status(), 201, "{}", served.log());
    let before: Value = served.post_alice("/verify", "01-2m.jpg").await.json().await.unwrap();
    drop(served);
    let plain = stored_with(&database, Some(&template_key)).await;

    // Without the template key the sealed vectors cannot be read: refused, nothing changed.
    let (ok, _, stderr) = renew(&["--database", &database, "--from-plain", "--new-key-file", &key_b]);
    assert!(!ok && stderr.contains("nothing was changed"), "{stderr}");
    assert_eq!(stored_with(&database, Some(&template_key)).await, plain);

    let (ok, report, stderr) =
        renew(&["--database", &database, "--from-plain", "--new-key-file", &key_b, "--template-key-file", &template_key_file]);
    assert!(ok && report["templates"] == 1, "{report} {stderr}");
    let protected = stored_with(&database, Some(&template_key)).await;
    assert!(protected[0].0.starts_with(&format!("{}+rot-", plain[0].0)), "{}", protected[0].0);
    let cosine: f32 = plain[0].1.iter().zip(&protected[0].1).map(|(a, b)| a * b).sum();
    assert!(cosine.abs() < 0.3, "the protected template is unlike the plain one: {cosine}");

    serve_is_refused(&database, &sealed, &["holds protected templates"]);
    let mut extra = sealed.to_vec();
    extra.extend(["--template-protection-key-file", key_b.as_str()]);
    let served = Served::start(&database, &extra, dir.0.join("serve-b.log")).await;
    let after: Value = served.post_alice("/verify", "01-2m.jpg").await.json().await.unwrap();
    drop(served);
    assert_eq!(after["match"].as_bool(), Some(true), "{after}");
    assert!((before["score"].as_f64().unwrap() - after["score"].as_f64().unwrap()).abs() < 1e-4, "{before} {after}");
}
