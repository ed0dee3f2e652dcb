//! End to end through the real face pipeline and the committed models: IMM photos of held-out
//! persons (1, 2, 3, 5: never used in training).

use std::sync::{Arc, OnceLock};

use facegate_vision::pipeline::{Pipeline, PipelineConfig};
use facegate_vision::recognize::RecognizerKind;
use serde_json::json;

use crate::support::*;

pub fn pipeline() -> Arc<Pipeline> {
    static PIPELINE: OnceLock<Arc<Pipeline>> = OnceLock::new();
    PIPELINE
        .get_or_init(|| {
            Arc::new(Pipeline::load(&facegate::config::pipeline_config()).unwrap_or_else(|e| panic!("cannot load the pipeline: {e}")))
        })
        .clone()
}

/// The classical recognizer's pipeline (`--recognizer classical`).
fn classical() -> Arc<Pipeline> {
    static PIPELINE: OnceLock<Arc<Pipeline>> = OnceLock::new();
    PIPELINE
        .get_or_init(|| {
            let config = PipelineConfig { recognizer: RecognizerKind::Classical, ..facegate::config::pipeline_config() };
            Arc::new(Pipeline::load(&config).unwrap_or_else(|e| panic!("cannot load the classical pipeline: {e}")))
        })
        .clone()
}

async fn app() -> TestApp {
    let pipeline = pipeline();
    TestApp::start(pipeline, facegate::config::Settings::default().api_config().unwrap()).await
}

/// Two IMM photos side by side: two faces in one picture.
fn two_people() -> Vec<u8> {
    let a = image::load_from_memory(&imm("01-1m.jpg")).unwrap().to_rgb8();
    let b = image::load_from_memory(&imm("02-1m.jpg")).unwrap().to_rgb8();
    let mut both = image::RgbImage::new(a.width() + b.width(), a.height().max(b.height()));
    image::imageops::replace(&mut both, &a, 0, 0);
    image::imageops::replace(&mut both, &b, a.width() as i64, 0);
    encode(&image::DynamicImage::ImageRgb8(both), image::ImageFormat::Jpeg)
}

fn flat_grey() -> Vec<u8> {
    encode(&image::DynamicImage::ImageRgb8(image::RgbImage::from_pixel(640, 480, image::Rgb([128, 128, 128]))), image::ImageFormat::Jpeg)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn enroll_an_imm_photo_then_verify_the_same_and_another_person() {
    let app = app().await;
    // Two photos (frontal, and turned to the side) of person 01.
    let r = app.post_form("/enroll", Some("imm-01"), &[imm("01-1m.jpg"), imm("01-3m.jpg")]).await;
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["templates"], 2);
    for image in r.json()["images"].as_array().unwrap() {
        assert_eq!(image["faces_found"], 1);
        assert_eq!(image["landmarks"]["points"].as_array().unwrap().len(), 58);
    }
    let r = app.post_json("/enroll", &json!({"subject": "imm-02", "images": [base64(&imm("02-1m.jpg"))]})).await;
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));

    // Another photo of the same person (lit from the side) matches.
    let r = app.post_form("/verify", Some("imm-01"), &[imm("01-5m.jpg")]).await;
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let same = r.json();
    assert_eq!(same["match"], true, "{same}");
    assert_eq!(same["templates_compared"], 2);
    // Photo 6 (head turned, as in 01-3m) is best matched by the turned enrolment photo, the second.
    let turned = app.post_form("/verify", Some("imm-01"), &[imm("01-6m.jpg")]).await.json();
    assert_eq!((turned["match"].as_bool(), turned["best_template"].as_u64()), (Some(true), Some(1)), "{turned}");
    // The threshold is the committed model's for a subject with two templates, stricter than the
    // one-photo threshold (the best of two comparisons).
    let recognizer = &pipeline().recognizer;
    let (two, one) = (recognizer.operating_point(1e-3, 2), recognizer.operating_point(1e-3, 1));
    assert_eq!((same["threshold"].as_f64().map(|t| t as f32), same["fmr"].as_f64()), (Some(two.threshold), Some(1e-3)));
    assert!(two.threshold > one.threshold, "{} against {}", two.threshold, one.threshold);
    let face = &same["face"]["box"];
    let (x, y, w, h) =
        (face["x"].as_f64().unwrap(), face["y"].as_f64().unwrap(), face["width"].as_f64().unwrap(), face["height"].as_f64().unwrap());
    assert!(x >= -1.0 && y >= -1.0 && w > 50.0 && h > 50.0 && x + w <= 641.0 && y + h <= 481.0, "{face}");
    for stage in ["decode_ms", "detect_ms", "landmarks_ms", "template_ms", "total_ms"] {
        assert!(same["timings"][stage].as_f64().unwrap() >= 0.0);
    }

    // A photo of another person does not.
    let r = app.post_form("/verify", Some("imm-01"), &[imm("03-1m.jpg")]).await;
    assert_eq!(r.status, 200);
    let other = r.json();
    assert_eq!(other["match"], false, "{other}");
    assert!(other["score"].as_f64().unwrap() < same["score"].as_f64().unwrap());

    // Identification ranks the right person first.
    let r = app.post_form("/identify?k=2", None, &[imm("02-6m.jpg")]).await;
    assert_eq!(r.status, 200);
    assert_eq!(r.json()["candidates"][0]["subject"], "imm-02", "{}", r.json());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_bad_input_class_with_the_real_pipeline() {
    let app = app().await;
    let photo = imm("05-1m.jpg");
    // Faces: none, or several (enrolment refuses; verify uses the largest and says how many).
    app.post_form("/enroll", Some("imm-05"), &[flat_grey()]).await.assert_problem(422, "no-face");
    let r = app.post_form("/enroll", Some("imm-05"), &[photo.clone(), two_people()]).await;
    r.assert_problem(422, "several-faces");
    assert_eq!(r.json()["image"], 1);
    assert_eq!(app.store.counts().await.unwrap(), (0, 0));
    assert_eq!(app.post_form("/enroll", Some("imm-05"), &[photo.clone()]).await.status, 201);
    let r = app.post_form("/verify", Some("imm-05"), &[two_people()]).await;
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert!(r.json()["faces_found"].as_u64().unwrap() >= 2);
    app.post_form("/verify", Some("imm-05"), &[flat_grey()]).await.assert_problem(422, "no-face");

    // Bytes that are not a usable photo.
    app.post_form("/verify", Some("imm-05"), &[b"not a photo".to_vec()]).await.assert_problem(422, "not-an-image");
    app.post_form("/verify", Some("imm-05"), &[b"II*\x00\x08\x00\x00\x00".to_vec()]).await.assert_problem(415, "unsupported-format");
    app.post_form("/verify", Some("imm-05"), &[photo[..64].to_vec()]).await.assert_problem(422, "corrupt-image");
    let huge = encode(&image::DynamicImage::ImageLuma8(image::GrayImage::new(5000, 4000)), image::ImageFormat::Png);
    app.post_form("/verify", Some("imm-05"), &[huge]).await.assert_problem(413, "too-large");
    // Requests that are wrong.
    app.post_form("/verify", Some("nobody"), &[photo.clone()]).await.assert_problem(404, "unknown-subject");
    app.post_form("/verify", Some("no spaces"), &[photo.clone()]).await.assert_problem(400, "malformed-request");
    app.post_json("/verify", &json!({"subject": "imm-05"})).await.assert_problem(400, "malformed-request");
    let r = app.send(app.client.post(app.url("/verify")).header("content-type", "image/jpeg").body(photo)).await;
    r.assert_problem(415, "unsupported-media-type");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn both_recognizers_verify_and_never_compare_each_others_templates() {
    let config = facegate::config::Settings::default().api_config().unwrap();
    let deep = pipeline();
    assert_eq!(deep.recognizer.kind(), RecognizerKind::Fusion, "the default recognizer is the fusion of dlib's network and SFace");
    // Enrolled under the classical recognizer, verified there.
    let old = TestApp::start(classical(), config.clone()).await;
    let r = old.post_form("/enroll", Some("imm-05"), &[imm("05-1m.jpg"), imm("05-2m.jpg")]).await;
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let classical_version = r.json()["model_version"].as_str().unwrap().to_string();
    assert!(classical_version.starts_with("dlda-"), "{classical_version}");
    let r = old.post_form("/verify", Some("imm-05"), &[imm("05-6m.jpg")]).await;
    assert_eq!(r.json()["match"], true, "{}", r.json());
    // The same database under the deep recognizer: the subject has no template it can compare.
    let new = old.restarted_with(deep.clone(), config).await;
    new.post_form("/verify", Some("imm-05"), &[imm("05-6m.jpg")]).await.assert_problem(409, "model-mismatch");
    assert_eq!(new.post_form("/identify", None, &[imm("05-6m.jpg")]).await.json()["candidates"].as_array().unwrap().len(), 0);
    // Enrolled again, the deep templates join the old ones and the deep recognizer decides.
    let r = new.post_form("/enroll", Some("imm-05"), &[imm("05-1m.jpg")]).await;
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    assert!(r.json()["model_version"].as_str().unwrap().starts_with("emb-"));
    let r = new.post_form("/verify", Some("imm-05"), &[imm("05-6m.jpg")]).await;
    let v = r.json();
    assert_eq!((v["match"].clone(), v["templates_compared"].clone()), (json!(true), json!(1)), "{v}");
    let versions = new.get("/subjects/imm-05").await.json();
    assert_eq!(versions["templates"], 3, "{versions}");
}

/// Run `facegate` (the binary cargo built for these tests) and return its output file.
fn cli(args: &[&str], out: &std::path::Path) -> Vec<u8> {
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_facegate"))
        .args(args)
        .arg("--out")
        .arg(out)
        .stdout(std::process::Stdio::null())
        .status()
        .unwrap();
    assert!(status.success(), "facegate {args:?} failed");
    std::fs::read(out).unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn analyze_avatar_and_frontalize_a_real_photo() {
    let app = app().await;
    // A turned face (IMM view 3): the landmarks come from the 3D-ASM, the 3DMM reads the yaw.
    let name = "01-3m.jpg";
    let path = facegate_paths::shared_dir().join("data/imm").join(name);
    let r = app.post_form("/analyze?faces=all", None, &[imm(name)]).await;
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let a = r.json();
    assert_eq!((a["faces_found"].as_u64(), a["faces"].as_array().unwrap().len()), (Some(1), 1), "{a}");
    let face = &a["faces"][0];
    assert_eq!(face["landmarks"]["points"].as_array().unwrap().len(), 58);
    let yaw = face["pose"]["yaw"].as_f64().unwrap();
    assert!(yaw.abs() > 10.0 && yaw.abs() < 45.0, "a turned face: yaw {yaw}");
    let residual = face["fit_residual_px"].as_f64().unwrap();
    assert!(residual > 0.0 && residual < 10.0, "fit residual {residual} px");
    assert!(face["face"]["score"].as_f64().is_some() && face["timings"]["morph_ms"].as_f64().unwrap() > 0.0);
    assert_eq!(app.store.counts().await.unwrap(), (0, 0));

    // The avatar: a glTF binary that parses, one textured mesh of the model's vertices, and the
    // very bytes `facegate reconstruct` writes for the photo.
    let r = app.post_form("/avatar", None, &[imm(name)]).await;
    assert_eq!((r.status, r.headers["content-type"].to_str().unwrap()), (200, "model/gltf-binary"));
    let gltf = gltf::Gltf::from_slice(&r.body).expect("a valid glb");
    let mesh = gltf.meshes().next().expect("a mesh");
    let primitive = mesh.primitives().next().unwrap();
    let positions = primitive.get(&gltf::Semantic::Positions).unwrap();
    assert_eq!(positions.count(), pipeline().face_model.as_ref().unwrap().vertex_count());
    assert!(primitive.material().pbr_metallic_roughness().base_color_texture().is_some());
    let image = gltf.images().next().unwrap();
    let gltf::image::Source::View { view, mime_type } = image.source() else { panic!("an embedded texture") };
    assert_eq!(mime_type, "image/png");
    let blob = gltf.blob.as_ref().unwrap();
    let texture = image::load_from_memory(&blob[view.offset()..view.offset() + view.length()]).unwrap();
    assert_eq!((texture.width(), texture.height()), (512, 512));
    let dir = std::env::temp_dir().join(format!("facegate-avatar-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let cli_glb = cli(&["reconstruct", path.to_str().unwrap()], &dir.join("cli.glb"));
    assert!(cli_glb == r.body, "POST /avatar and facegate reconstruct differ ({} and {} bytes)", r.body.len(), cli_glb.len());

    // The OBJ avatar: a zip of avatar.obj, avatar.mtl and avatar.png, the files `facegate
    // reconstruct --out avatar.obj` writes.
    let r = app.post_form("/avatar?format=obj", None, &[imm(name)]).await;
    assert_eq!((r.status, r.headers["content-type"].to_str().unwrap()), (200, "application/zip"));
    let mut archive = zip::ZipArchive::new(std::io::Cursor::new(r.body)).expect("a zip archive");
    assert_eq!(archive.len(), 3);
    cli(&["reconstruct", path.to_str().unwrap()], &dir.join("avatar.obj"));
    for file in ["avatar.obj", "avatar.mtl", "avatar.png"] {
        let mut zipped = Vec::new();
        std::io::Read::read_to_end(&mut archive.by_name(file).unwrap(), &mut zipped).unwrap();
        assert!(zipped == std::fs::read(dir.join(file)).unwrap(), "{file} differs from the CLI's");
    }

    // The frontal rendering: a 256 × 256 PNG, the bytes `facegate frontalize` writes.
    let r = app.post_json("/frontalize", &json!({"image": base64(&imm(name))})).await;
    assert_eq!((r.status, r.headers["content-type"].to_str().unwrap()), (200, "image/png"));
    let png = image::load_from_memory_with_format(&r.body, image::ImageFormat::Png).unwrap().to_rgb8();
    assert_eq!(png.dimensions(), (256, 256));
    let lit = png.pixels().filter(|p| p.0.iter().any(|&c| c > 30)).count();
    assert!(lit > 256 * 256 / 4, "the face covers the rendering: {lit} lit pixels");
    let cli_png = cli(&["frontalize", path.to_str().unwrap()], &dir.join("cli.png"));
    assert!(cli_png == r.body, "POST /frontalize and facegate frontalize differ");
    // `--yaw`: the fitted head turned, as an attack on the liveness challenge would show it; the
    // pipeline reads it turned that way (a 400-pixel render on black, as `/analyze` would get it).
    for (yaw, side) in [("25", 1.0), ("-25", -1.0)] {
        let png = cli(&["frontalize", "--yaw", yaw, "--size", "400", path.to_str().unwrap()], &dir.join("turned.png"));
        let photo = facegate_core::imaging::decode(&png, &Default::default()).unwrap();
        let read = pipeline().analyze(&photo).unwrap().pose.expect("posed").yaw;
        assert!(side * read > 12.0 && side * read < 40.0, "rendered at {yaw}°, read {read}°");
    }
    let refused = std::process::Command::new(env!("CARGO_BIN_EXE_facegate"))
        .args(["frontalize", "--yaw", "120", path.to_str().unwrap(), "--out"])
        .arg(dir.join("no.png"))
        .output()
        .unwrap();
    assert!(!refused.status.success() && String::from_utf8_lossy(&refused.stderr).contains("--yaw must be between"));
    let _ = std::fs::remove_dir_all(&dir);

    // No face, and the photo checks of /verify.
    app.post_form("/avatar", None, &[flat_grey()]).await.assert_problem(422, "no-face");
    app.post_form("/frontalize", None, &[b"not a photo".to_vec()]).await.assert_problem(422, "not-an-image");
}

/// `name` from IMM with `f` applied to the decoded photo, as JPEG.
fn altered_imm(name: &str, f: impl Fn(image::DynamicImage) -> image::DynamicImage) -> Vec<u8> {
    encode(&f(image::load_from_memory(&imm(name)).unwrap()), image::ImageFormat::Jpeg)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn enrollment_refuses_a_darkened_or_blurred_photo_and_accepts_its_original() {
    let app = app().await;
    let darkened = altered_imm("03-1m.jpg", |img| {
        let mut rgb = img.to_rgb8();
        rgb.pixels_mut().for_each(|p| p.0.iter_mut().for_each(|v| *v /= 8));
        image::DynamicImage::ImageRgb8(rgb)
    });
    let blurred = altered_imm("03-1m.jpg", |img| img.blur(4.0));
    for (photo, what, component) in [(darkened, "darkened", "brightness"), (blurred, "blurred", "sharpness")] {
        let r = app.post_form("/enroll", Some("imm-03"), std::slice::from_ref(&photo)).await;
        r.assert_problem(422, "low-quality");
        let failures = r.json()["failures"].as_array().unwrap().clone();
        assert!(failures.iter().any(|f| f["component"] == component), "{what}: {failures:?}");
        // What /analyze reports is what the policy saw.
        let r = app.post_form("/analyze", None, &[photo]).await;
        let quality = &r.json()["faces"][0]["quality"];
        let f = failures.iter().find(|f| f["component"] == component).unwrap();
        assert_eq!(quality[component].as_f64(), f["value"].as_f64(), "{what}: {quality}");
    }
    assert_eq!(app.store.counts().await.unwrap(), (0, 0));
    let r = app.post_form("/enroll", Some("imm-03"), &[imm("03-1m.jpg")]).await;
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let quality = &r.json()["images"][0]["quality"];
    let policy = facegate::config::Settings::default();
    assert!(quality["score"].as_f64().unwrap() >= policy.min_quality as f64, "{quality}");
    assert!(quality["yaw_abs_deg"].as_f64().unwrap() < 10.0 && quality["fit_residual"].as_f64().is_some(), "{quality}");
    // The same photo as a probe carries the same measurements.
    let r = app.post_form("/verify", Some("imm-03"), &[imm("03-1m.jpg")]).await;
    assert_eq!(&r.json()["quality"], quality);
}
