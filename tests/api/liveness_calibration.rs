//! `facegate calibrate-liveness`: the real binary scores a camera's live captures with the
//! liveness model, stores the threshold that refuses at most the share asked; `facegate serve`
//! decides with it in place of the model's, `--liveness-threshold` wins over it, and `--clear`
//! takes it back.

use serde_json::Value;

use crate::fail_closed::{Scratch, Served};
use crate::support::imm;

/// Run `facegate` with `args`: its exit status, JSON lines and standard error.
fn facegate(args: &[&str]) -> (bool, Vec<Value>, String) {
    let out =
        std::process::Command::new(env!("CARGO_BIN_EXE_facegate")).args(args).current_dir(env!("CARGO_MANIFEST_DIR")).output().unwrap();
    let lines = String::from_utf8_lossy(&out.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    (out.status.success(), lines, String::from_utf8_lossy(&out.stderr).into_owned())
}

/// POST `photo` (an IMM file) to `path` for alice: the status and the body.
async fn post(served: &Served, path: &str, photo: &str) -> (u16, Value) {
    let r = served.post_alice(path, photo).await;
    (r.status().as_u16(), r.json().await.unwrap())
}

/// `/health`'s `liveness`: the threshold in force and how it was set, in words and by whom.
async fn health_liveness(served: &Served) -> (f64, String, String) {
    let health: Value = reqwest::get(format!("{}/health", served.base)).await.unwrap().json().await.unwrap();
    let liveness = &health["liveness"];
    let text = |field: &str| liveness[field].as_str().unwrap().to_string();
    (liveness["threshold"].as_f64().unwrap(), text("operating_point"), text("source"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cameras_live_captures_set_the_served_liveness_threshold() {
    let dir = Scratch::new("liveness-calibration");
    let database = dir.url("facegate.db");
    // Twelve frontal photos of four IMM persons: the camera's live captures, in a folder with a
    // file that is no image (left alone).
    let captures = dir.0.join("captures");
    std::fs::create_dir_all(&captures).unwrap();
    let photos: Vec<String> = (1..=4).flat_map(|p| [1, 2, 5].map(|v| format!("{p:02}-{v}m.jpg"))).collect();
    for photo in &photos {
        std::fs::write(captures.join(photo), imm(photo)).unwrap();
    }
    std::fs::write(captures.join("notes.txt"), "taken at the front desk").unwrap();

    // The model's threshold first: every one of them is live, and their own scores.
    let served = Served::start(&database, &["--liveness", "enforce"], dir.0.join("serve-1.log")).await;
    assert_eq!(post(&served, "/enroll", "01-1m.jpg").await.0, 201, "{}", served.log());
    let mut scores = Vec::new();
    for photo in &photos {
        let (status, body) = post(&served, "/verify", photo).await;
        assert_eq!(status, 200, "{photo}: {body}");
        scores.push((body["liveness"]["score"].as_f64().unwrap(), photo.clone()));
    }
    assert!(served.log().contains("no liveness calibration"), "{}", served.log());
    let (model_threshold, how, source) = health_liveness(&served).await;
    assert!(!how.contains("calibrate-liveness") && source == "model", "{how} ({source})");
    drop(served);
    scores.sort_by(|a, b| a.0.total_cmp(&b.0));
    assert!(scores[0].0 < scores[1].0, "the lowest score is one photo's: {scores:?}");

    // A mistyped database is refused before any photo is scored, and none is made there.
    let missing = dir.0.join("missing.db");
    let missing_url = format!("sqlite://{}", missing.display());
    let (ok, _, error) = facegate(&["calibrate-liveness", "--database", &missing_url, captures.to_str().unwrap()]);
    assert!(!ok && error.contains("no database") && !missing.exists(), "{error}");
    // Too few faces for the share asked: refused, nothing stored.
    let (ok, _, error) = facegate(&["calibrate-liveness", "--database", &database, captures.to_str().unwrap()]);
    assert!(!ok && error.contains("at least 50 are needed"), "{error}");
    // At most 10% of 12: the lowest photo is refused, the threshold is the second lowest score.
    let (ok, lines, error) = facegate(&["calibrate-liveness", "--database", &database, "--bpcer", "0.1", captures.to_str().unwrap()]);
    assert!(ok, "{error}");
    let calibration = &lines[0];
    assert_eq!(
        (calibration["photos"].as_u64(), calibration["live_faces"].as_u64(), calibration["refused"].as_u64()),
        (Some(12), Some(12), Some(1))
    );
    assert_eq!((calibration["stored"].as_bool(), calibration["refused_at_model_threshold"].as_u64()), (Some(true), Some(0)));
    let threshold = calibration["threshold"].as_f64().unwrap();
    // A dry run measures the same and stores nothing (nor needs the database).
    let (ok, lines, error) =
        facegate(&["calibrate-liveness", "--dry-run", "--database", &missing_url, "--bpcer", "0.1", captures.to_str().unwrap()]);
    assert!(ok, "{error}");
    assert_eq!((lines[0]["threshold"].as_f64(), lines[0]["stored"].as_bool()), (Some(threshold), Some(false)));
    assert!((threshold - scores[1].0).abs() < 1e-6, "{threshold} against the second lowest {:?}", scores[1]);

    // Served: the lowest photo is now taken for an attack, saying by which threshold; the others pass.
    let served = Served::start(&database, &["--liveness", "enforce"], dir.0.join("serve-2.log")).await;
    assert!(served.log().contains("liveness threshold of this camera"), "{}", served.log());
    let (served_threshold, how, source) = health_liveness(&served).await;
    assert!((served_threshold - threshold).abs() < 1e-6 && how.contains("1 of 12 live faces refused"), "{served_threshold} {how}");
    assert_eq!(source, "camera");
    let (status, problem) = post(&served, "/verify", &scores[0].1).await;
    assert_eq!((status, problem["type"].as_str().map(|t| t.ends_with("presentation-attack"))), (422, Some(true)), "{problem}");
    assert!(problem.to_string().contains("facegate calibrate-liveness"), "{problem}");
    assert_eq!(post(&served, "/verify", &scores[1].1).await.0, 200);
    drop(served);

    // The operator's --liveness-threshold wins over the stored one.
    let served = Served::start(&database, &["--liveness", "enforce", "--liveness-threshold", "0.01"], dir.0.join("serve-3.log")).await;
    assert!(served.log().contains("stored liveness calibration is not used"), "{}", served.log());
    let (served_threshold, how, source) = health_liveness(&served).await;
    assert_eq!((served_threshold, source.as_str()), (0.01, "operator"), "{how}");
    assert!(how.contains("in place of the camera's"), "the operator's threshold says what it replaced: {how}");
    assert_eq!(post(&served, "/verify", &scores[0].1).await.0, 200);
    drop(served);

    // Cleared: the model's threshold again.
    let (ok, lines, error) = facegate(&["calibrate-liveness", "--database", &database, "--clear"]);
    assert!(ok, "{error}");
    assert_eq!(lines[0]["removed"].as_bool(), Some(true));
    let served = Served::start(&database, &["--liveness", "enforce"], dir.0.join("serve-4.log")).await;
    assert!(served.log().contains("no liveness calibration"), "{}", served.log());
    let (served_threshold, _, source) = health_liveness(&served).await;
    assert_eq!((served_threshold, source.as_str()), (model_threshold, "model"));
    assert_eq!(post(&served, "/verify", &scores[0].1).await.0, 200);
    drop(served);
    // Liveness off: no threshold in force.
    let served = Served::start(&database, &["--liveness", "off"], dir.0.join("serve-5.log")).await;
    let health: Value = reqwest::get(format!("{}/health", served.base)).await.unwrap().json().await.unwrap();
    assert!(health.get("liveness").is_none(), "{health}");
}
