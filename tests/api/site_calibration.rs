//! `facegate calibrate`: the real binary measures the enrolled subjects' impostor pairs and stores
//! the site calibration; `facegate serve` raises its thresholds to it, and `--clear` takes it back.

use facegate_core::SubjectId;
use facegate_core::template::Template;
use facegate_store::Store;
use serde_json::{Value, json};

use crate::fail_closed::{Scratch, Served};

/// Run `facegate` with `args`: whether it succeeded and its JSON lines.
fn facegate(args: &[&str]) -> (bool, Vec<Value>) {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_facegate")).args(args).output().unwrap();
    assert!(out.status.success(), "facegate {args:?}: {}", String::from_utf8_lossy(&out.stderr));
    (out.status.success(), String::from_utf8_lossy(&out.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect())
}

/// `/health`'s `site_calibration` (null when absent).
async fn health_site(served: &Served) -> Value {
    let health: Value = reqwest::get(format!("{}/health", served.base)).await.unwrap().json().await.unwrap();
    health["site_calibration"].clone()
}

/// POST alice with the IMM photo `photo` to `path`: the answer, its status checked to be `status`.
async fn post_alice(served: &Served, path: &str, photo: &str, status: u16) -> reqwest::Response {
    let r = served.post_alice(path, photo).await;
    assert_eq!(r.status(), status, "{}", served.log());
    r
}

/// Verify IMM 01's second photo against alice: (threshold, match).
async fn verify_alice(served: &Served) -> (f64, bool) {
    verify_alice_at(served, "/verify").await
}

/// [`verify_alice`] through `path` (e.g. with `?fmr=`).
async fn verify_alice_at(served: &Served, path: &str) -> (f64, bool) {
    let r = post_alice(served, path, "01-2m.jpg", 200).await;
    let v: Value = r.json().await.unwrap();
    (v["threshold"].as_f64().unwrap(), v["match"].as_bool().unwrap())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_site_calibration_raises_the_served_threshold_and_clear_takes_it_back() {
    let dir = Scratch::new("site-calibration");
    let database = dir.url("facegate.db");
    let served = Served::start(&database, &[], dir.0.join("serve-1.log")).await;
    post_alice(&served, "/enroll", "01-1m.jpg", 201).await;
    let (model_threshold, matched) = verify_alice(&served).await;
    assert!(matched, "the same person, the model's threshold");
    assert!(served.log().contains("no site calibration"), "{}", served.log());
    assert_eq!(health_site(&served).await, Value::Null);

    // The model's duplicate threshold: its impostor tail a decade past 1e-4.
    let (at_1e4, _) = verify_alice_at(&served, "/verify?fmr=0.0001").await;
    let duplicate = at_1e4 + (at_1e4 - model_threshold);
    drop(served);

    // 150 subjects whose templates are all equally alike, well above the model's threshold but
    // below its duplicate threshold: a deployment whose impostors look far more alike than the
    // model's calibration persons. And alice enrolled a second time, under another id.
    let lookalike = (model_threshold + 0.6 * (duplicate - model_threshold)) as f32;
    let store = Store::connect(&database, None).await.unwrap();
    let alice = store.templates(&SubjectId::parse("alice").unwrap()).await.unwrap().unwrap();
    let (version, dims) = (alice[0].model_version.clone(), alice[0].vector.len());
    assert!(dims > 160, "{dims} dimensions");
    for s in 0..150 {
        // sqrt(c)·u + sqrt(1 - c)·e_s, with u spread over the dimensions past the 150 e_s: any
        // two have cosine c.
        let u = (1.0 / (dims - 150) as f32).sqrt();
        let vector: Vec<f32> = (0..dims)
            .map(|i| {
                if i == s {
                    (1.0 - lookalike).sqrt()
                } else if i >= 150 {
                    lookalike.sqrt() * u
                } else {
                    0.0
                }
            })
            .collect();
        store.enroll(&SubjectId::parse(&format!("lookalike-{s}")).unwrap(), &[Template::new(&version, vector)]).await.unwrap();
    }
    store.enroll(&SubjectId::parse("alice-again").unwrap(), &alice).await.unwrap();
    store.close().await;

    // A mistyped database path is refused, and no database is left there.
    let missing = dir.0.join("missing.db");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_facegate"))
        .args(["calibrate", "--database", &format!("sqlite://{}", missing.display())])
        .output()
        .unwrap();
    assert!(!out.status.success() && !missing.exists(), "{}", String::from_utf8_lossy(&out.stderr));

    let (_, lines) = facegate(&["calibrate", "--database", &database, "--dry-run"]);
    assert_eq!((lines.len(), lines[0]["stored"].as_bool()), (1, Some(false)));
    // The look-alikes raise 1e-3 past --max-raise: printed with the ids carrying the tail, and
    // not stored without --accept-raise (exit status 3).
    let csv = dir.0.join("duplicates.csv");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_facegate"))
        .args(["calibrate", "--database", &database, "--max-raise", "0.005", "--duplicates-csv", csv.to_str().unwrap()])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{stderr}");
    assert!(stderr.contains("more than --max-raise 0.005") && stderr.contains("--accept-raise"), "{stderr}");
    assert!(stderr.contains("ids in most of those pairs: lookalike-"), "{stderr}");
    let refused: Value = serde_json::from_str(String::from_utf8_lossy(&out.stdout).lines().next().unwrap()).unwrap();
    assert_eq!(refused["stored"].as_bool(), Some(false));
    let pull = &refused["pull"][1];
    assert_eq!(pull["fmr"].as_f64(), Some(1e-3), "{refused}");
    assert!((pull["model_threshold"].as_f64().unwrap() - model_threshold).abs() < 1e-5, "{pull}");
    assert!(pull["raise"].as_f64().unwrap() > 0.005 && pull["tail_pairs"].as_u64().unwrap() > 100, "{pull}");
    assert!(pull["tail_ids"].as_array().unwrap().iter().all(|t| t["subject"].as_str().unwrap().starts_with("lookalike-")), "{pull}");
    assert_eq!(std::fs::read_to_string(&csv).unwrap().lines().collect::<Vec<_>>()[..2][0], "subject_a,subject_b,score");
    assert!(std::fs::read_to_string(&csv).unwrap().lines().nth(1).unwrap().starts_with("alice,alice-again,"));
    let (_, lines) = facegate(&["calibrate", "--database", &database, "--max-raise", "0.005", "--accept-raise"]);
    let site = &lines[0];
    assert_eq!(
        (site["model_version"].as_str(), site["subjects"].as_u64(), site["stored"].as_bool()),
        (Some(version.as_str()), Some(152), Some(true))
    );
    // alice and alice-again are one person: their pair is left out, and named.
    assert_eq!(site["impostor_pairs"].as_u64(), Some(152 * 151 / 2 - 1));
    assert_eq!((site["duplicate_pairs_left_out"].as_u64(), site["duplicate_id_pairs"].as_u64()), (Some(1), Some(1)));
    assert_eq!(site["suspected_duplicates"][0]["subjects"], json!(["alice", "alice-again"]));
    // 11,475 pairs show 1e-2 and 1e-3 (at least ten false matches each), not 1e-4.
    let points: Vec<f64> = site["points"].as_array().unwrap().iter().map(|p| p["fmr"].as_f64().unwrap()).collect();
    assert_eq!(points, [1e-2, 1e-3]);
    let site_threshold = site["points"][1]["threshold"].as_f64().unwrap();
    assert!(
        site_threshold > model_threshold + 0.5 * (duplicate - model_threshold) && site_threshold < duplicate,
        "site {site_threshold} against the model's {model_threshold} (duplicates from {duplicate})"
    );

    let served = Served::start(&database, &[], dir.0.join("serve-2.log")).await;
    let (threshold, _) = verify_alice(&served).await;
    assert!((threshold - site_threshold).abs() < 1e-5, "one template: the site's threshold, {threshold} against {site_threshold}");
    assert!(served.log().contains("site calibration (facegate calibrate)"), "{}", served.log());
    let in_use = health_site(&served).await;
    // The same points (as f32: the command prints them through f64, the service as f32).
    let points = |v: &Value| -> Vec<(f64, f32)> {
        v["points"].as_array().unwrap().iter().map(|p| (p["fmr"].as_f64().unwrap(), p["threshold"].as_f64().unwrap() as f32)).collect()
    };
    assert_eq!((in_use["impostor_pairs"].as_u64(), points(&in_use)), (Some(152 * 151 / 2 - 1), points(site)));
    // The stored calibration keeps the count of suspected pairs of ids, not their names.
    assert_eq!((in_use["duplicate_id_pairs"].as_u64(), in_use.get("suspected_duplicates")), (Some(1), None));
    drop(served);

    let (_, lines) = facegate(&["calibrate", "--database", &database, "--clear"]);
    assert_eq!(lines[0]["removed"].as_bool(), Some(true));
    let served = Served::start(&database, &[], dir.0.join("serve-3.log")).await;
    assert_eq!(verify_alice(&served).await, (model_threshold, true));
    assert_eq!(health_site(&served).await, Value::Null);
    drop(served);
}
