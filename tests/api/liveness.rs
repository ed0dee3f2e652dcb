//! Liveness (presentation-attack detection) through the real app, pipeline and committed
//! `models/liveness.bin`, on NUAA frames of subject 0004: a printed photo of the subject held to
//! the camera and live frames of the same person. Under `--liveness enforce` the print is refused
//! (422 `presentation-attack`) by enrol, verify and identify while the live face enrols and
//! verifies; under `report` (the default) it is answered with `liveness.attack`; under `off` no
//! liveness is computed or reported. The settings reach the service as `facegate serve` wires them
//! (`Settings::api_config`, `Settings::configure_liveness`).

use facegate::choices::Liveness as Choice;
use facegate::config::Settings;
use facegate_vision::pipeline::Pipeline;
use serde_json::{Value, json};

use crate::pipeline::pipeline;
use crate::support::*;

/// A NUAA frame from the shared data (read from its path, never copied).
pub(crate) fn nuaa(name: &str) -> Vec<u8> {
    let path = facegate_paths::shared_dir().join("data/nuaa").join(name);
    std::fs::read(&path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()))
}

/// A printed photo of subject 0004 held to the camera.
pub(crate) const PRINT: &str = "print/0004/0004_01_01_03_211.jpg";
/// Live frames of subject 0004: one to enrol, two to verify.
pub(crate) const LIVE_ENROL: &str = "real/0004/0004_01_00_02_134.jpg";
pub(crate) const LIVE_PROBE: &str = "real/0004/0004_01_00_01_235.jpg";
const LIVE_OTHER: &str = "real/0004/0004_01_00_01_0.jpg";

fn settings(liveness: Choice, liveness_threshold: Option<f32>) -> Settings {
    Settings { liveness, liveness_threshold, ..Settings::default() }
}

/// The liveness the pipeline itself gives the largest face of `photo`.
fn scored(pipeline: &Pipeline, photo: &[u8]) -> facegate_vision::liveness::Liveness {
    let photo = facegate_core::imaging::decode(photo, &Default::default()).unwrap();
    pipeline.analyze(&photo).unwrap().liveness.expect("a liveness model is loaded")
}

/// A fresh pipeline shaped by `settings`, as `facegate serve` loads and configures it.
fn configured_pipeline(settings: &Settings) -> Pipeline {
    let mut pipeline = Pipeline::load(&settings.pipeline_config()).unwrap();
    settings.configure_liveness(&mut pipeline).unwrap();
    pipeline
}

/// A JSON number as the f32 it was serialised from.
fn f32_of(v: &Value) -> Option<f32> {
    v.as_f64().map(|x| x as f32)
}

/// `/verify`'s (or `/enroll`'s first photo's) liveness, checked against the pipeline's.
fn liveness_of(body: &Value) -> &Value {
    let liveness = if body["images"].is_array() { &body["images"][0]["liveness"] } else { &body["liveness"] };
    assert!(liveness.is_object(), "no liveness in {body}");
    liveness
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn enforce_refuses_a_printed_photo_and_lets_the_live_face_through() {
    let pipeline = pipeline();
    let model = pipeline.liveness.as_ref().expect("the committed liveness model is loaded");
    // What the model says of the frames, before any policy.
    let print = scored(&pipeline, &nuaa(PRINT));
    assert!(print.score < model.threshold, "the print scores {print:?} against {}", model.threshold);
    for live in [LIVE_ENROL, LIVE_PROBE] {
        let live = scored(&pipeline, &nuaa(live));
        assert!(live.score >= model.threshold, "a live frame scores {live:?} against {}", model.threshold);
    }

    let app = TestApp::start(pipeline.clone(), settings(Choice::Enforce, None).api_config().unwrap()).await;
    // The live face enrols and verifies, each answer carrying its liveness.
    let r = app.post_form("/enroll", Some("nuaa-0004"), &[nuaa(LIVE_ENROL)]).await;
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(liveness_of(&r.json())["attack"], false, "{}", r.json());
    let r = app.post_form("/verify", Some("nuaa-0004"), &[nuaa(LIVE_PROBE)]).await;
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let verified = r.json();
    assert_eq!(verified["match"], true, "{verified}");
    let liveness = liveness_of(&verified);
    assert_eq!((&liveness["attack"], &liveness["model"]), (&json!(false), &json!(model.name)), "{verified}");
    assert!(f32_of(&liveness["score"]).unwrap() >= model.threshold, "{verified}");
    assert!(verified["timings"]["liveness_ms"].as_f64().unwrap() > 0.0, "{verified}");

    // The print is refused by verify and identify, with the score and the operating point.
    for r in [
        app.post_form("/verify", Some("nuaa-0004"), &[nuaa(PRINT)]).await,
        app.post_json("/identify", &json!({"image": base64(&nuaa(PRINT))})).await,
    ] {
        r.assert_problem(422, "presentation-attack");
        let problem = r.json();
        let score = f32_of(&problem["score"]).unwrap();
        assert_eq!(score, print.score, "the score the pipeline gives the print: {problem}");
        assert!(score < f32_of(&problem["threshold"]).unwrap(), "{problem}");
        assert_eq!(f32_of(&problem["threshold"]), Some(model.threshold), "{problem}");
        assert_eq!(problem["operating_point"], model.operating_point.as_str(), "{problem}");
        assert_eq!(problem["model"], model.name.as_str(), "{problem}");
        assert!(problem.get("image").is_none(), "{problem}");
    }
    // An enrolment with the print among its photos is refused whole, naming the photo.
    let r = app.post_form("/enroll", Some("nuaa-0004"), &[nuaa(LIVE_OTHER), nuaa(PRINT)]).await;
    r.assert_problem(422, "presentation-attack");
    assert_eq!(r.json()["image"], 1, "{}", r.json());
    assert_eq!(app.store.counts().await.unwrap(), (1, 1), "nothing of the refused enrolment is stored");
    // /analyze is an inspection: it reports the attack and refuses nothing.
    let r = app.post_form("/analyze", None, &[nuaa(PRINT)]).await;
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let face = &r.json()["faces"][0];
    assert_eq!((&face["liveness"]["attack"], f32_of(&face["liveness"]["score"])), (&json!(true), Some(print.score)), "{face}");

    // Report (the default) on the same database: the print is answered, marked as an attack; to
    // the recognizer it is the subject's face, which is why enforcement exists.
    let report = app.restarted_with(pipeline.clone(), Settings::default().api_config().unwrap()).await;
    let r = report.post_form("/verify", Some("nuaa-0004"), &[nuaa(PRINT)]).await;
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let answered = r.json();
    assert_eq!(liveness_of(&answered)["attack"], true, "{answered}");
    assert_eq!(f32_of(&liveness_of(&answered)["score"]), Some(print.score), "{answered}");
    assert_eq!(answered["match"], true, "the print passes as its owner to the recognizer: {answered}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn off_computes_and_reports_no_liveness_and_refuses_nothing() {
    let off = settings(Choice::Off, None);
    let pipeline = std::sync::Arc::new(configured_pipeline(&off));
    assert!(pipeline.liveness.is_none(), "off drops the model: no time is spent on it");
    let app = TestApp::start(pipeline, off.api_config().unwrap()).await;
    let r = app.post_form("/enroll", Some("nuaa-0004"), &[nuaa(LIVE_ENROL)]).await;
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    assert!(r.json()["images"][0].get("liveness").is_none(), "{}", r.json());
    for r in [app.post_form("/verify", Some("nuaa-0004"), &[nuaa(PRINT)]).await, app.post_form("/identify", None, &[nuaa(PRINT)]).await] {
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        assert!(r.json().get("liveness").is_none(), "{}", r.json());
    }
    let r = app.post_form("/analyze", None, &[nuaa(PRINT)]).await;
    assert!(r.json()["faces"][0].get("liveness").is_none(), "{}", r.json());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_operators_threshold_replaces_the_models() {
    // A threshold just above a live frame's score: that frame is now taken for an attack.
    let live = scored(&pipeline(), &nuaa(LIVE_OTHER));
    assert!(live.score < 0.999, "{live:?}");
    let threshold = (live.score + 1.0) / 2.0;
    let strict = settings(Choice::Enforce, Some(threshold));
    let pipeline = std::sync::Arc::new(configured_pipeline(&strict));
    assert!(pipeline.liveness.as_ref().is_some_and(|m| m.threshold != threshold), "the model keeps its own point");
    let app = TestApp::start(pipeline, strict.api_config().unwrap()).await;
    let r = app.post_form("/enroll", Some("nuaa-0004"), &[nuaa(LIVE_ENROL), nuaa(LIVE_OTHER)]).await;
    r.assert_problem(422, "presentation-attack");
    let problem = r.json();
    assert_eq!((problem["image"].as_u64(), f32_of(&problem["threshold"])), (Some(1), Some(threshold)), "{problem}");
    assert_eq!(f32_of(&problem["score"]), Some(live.score), "{problem}");
    assert!(problem["operating_point"].as_str().unwrap().contains("--liveness-threshold"), "{problem}");
}
