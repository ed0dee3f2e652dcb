//! The embedding-network recognizers through the real app and the committed models: SFace alone
//! (`--recognizer sface`: `models/sface.bin` over `sface.onnx`) and its fusion with dlib's network
//! (`--recognizer fusion`, the default: `models/fusion.bin`), on IMM photos of held-out persons. The score
//! `/verify` answers is the one the pipeline's templates give (for the fusion, the members'
//! weighted cosines), and templates of one recognizer are never compared with another's.

use std::sync::{Arc, OnceLock};

use facegate_vision::pipeline::{Pipeline, PipelineConfig};
use facegate_vision::recognize::{Recognizer, RecognizerKind};
use serde_json::json;

use crate::support::*;

fn loaded(kind: RecognizerKind) -> Arc<Pipeline> {
    if kind == RecognizerKind::default() {
        return crate::pipeline::pipeline();
    }
    static SFACE: OnceLock<Arc<Pipeline>> = OnceLock::new();
    static DEEP: OnceLock<Arc<Pipeline>> = OnceLock::new();
    let cell = if kind == RecognizerKind::Sface { &SFACE } else { &DEEP };
    cell.get_or_init(|| {
        let config = PipelineConfig { recognizer: kind, ..facegate::config::pipeline_config() };
        Arc::new(Pipeline::load(&config).unwrap_or_else(|e| panic!("cannot load the {kind:?} pipeline: {e}")))
    })
    .clone()
}

fn template(pipeline: &Pipeline, photo: &[u8]) -> Vec<f32> {
    let photo = facegate_core::imaging::decode(photo, &Default::default()).unwrap();
    pipeline.analyze(&photo).unwrap().template.vector
}

async fn verifies_with(kind: RecognizerKind, members: usize) {
    let pipeline = loaded(kind);
    let Recognizer::Embedding(recognizer, loaded_kind) = &pipeline.recognizer else { panic!("{kind:?} is an embedding recognizer") };
    assert_eq!((*loaded_kind, recognizer.model.members.len()), (kind, members));
    let app = TestApp::start(pipeline.clone(), facegate::config::Settings::default().api_config().unwrap()).await;
    let r = app.post_form("/enroll", Some("imm-03"), &[imm("03-1m.jpg")]).await;
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["model_version"], recognizer.model.version.as_str(), "{}", r.json());
    assert!(recognizer.model.version.starts_with("emb-"));

    let same = app.post_form("/verify", Some("imm-03"), &[imm("03-2m.jpg")]).await.json();
    let other = app.post_form("/verify", Some("imm-03"), &[imm("05-2m.jpg")]).await.json();
    assert_eq!((&same["match"], &other["match"]), (&json!(true), &json!(false)), "{same} {other}");
    // The score is the cosine of the pipeline's own templates (the members' weighted cosines).
    let enrolled = template(&pipeline, &imm("03-1m.jpg"));
    let probe = template(&pipeline, &imm("03-2m.jpg"));
    assert_eq!(enrolled.len(), 128 * members);
    let cosine: f32 = enrolled.iter().zip(&probe).map(|(a, b)| a * b).sum();
    assert!((same["score"].as_f64().unwrap() as f32 - cosine).abs() < 1e-5, "{same} against {cosine}");
    let threshold = same["threshold"].as_f64().unwrap() as f32;
    assert_eq!(threshold, pipeline.recognizer.operating_point(1e-3, 1).threshold, "{same}");

    // The same database under dlib's network alone: nothing it can compare.
    let dlib = app.restarted_with(loaded(RecognizerKind::Dlib), facegate::config::Settings::default().api_config().unwrap()).await;
    dlib.post_form("/verify", Some("imm-03"), &[imm("03-2m.jpg")]).await.assert_problem(409, "model-mismatch");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sface_alone_verifies_by_its_own_cosine() {
    verifies_with(RecognizerKind::Sface, 1).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_fusion_verifies_by_the_weighted_cosines_of_both_networks() {
    verifies_with(RecognizerKind::Fusion, 2).await;
}

#[test]
fn a_fusion_whose_network_changed_is_refused_at_load() {
    // A copy of the models folder whose fusion model names another SFace file hash.
    let dir = std::env::temp_dir().join(format!("facegate-recognizers-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let models = facegate_paths::models_dir();
    for f in ["embedding.bin", "sface.onnx", "sface.json"] {
        std::fs::copy(models.join(f), dir.join(f)).unwrap();
    }
    let mut model = facegate_vision::recognize::embedding::EmbeddingModel::load(&models.join("fusion.bin")).unwrap();
    model.members[1].sha256 = "0".repeat(64);
    facegate_core::model_file::write_model(&dir.join("fusion.bin"), &model).unwrap();
    let err = facegate_vision::recognize::EmbeddingRecognizer::load(&dir, "fusion.bin").err().expect("refused");
    assert!(err.to_string().contains("is not the one the model was calibrated with"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}
