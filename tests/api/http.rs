//! The HTTP layer with the stand-in engine: request formats, every bad-input class, limits,
//! API keys, timeouts, overload, storage and the subjects routes.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use facegate_core::imaging::DecodeLimits;
use facegate_http::ApiConfig;
use facegate_service::ServiceConfig;
use serde_json::json;
use sqlx::Connection;

use crate::on_both_backends;
use crate::support::*;

fn config() -> ApiConfig {
    let defaults = facegate::config::Settings::default().api_config().unwrap();
    ApiConfig {
        max_body_bytes: 2 << 20,
        // Overload tests expect a full queue to refuse at once.
        admission_wait: Duration::ZERO,
        service: ServiceConfig {
            decode_limits: DecodeLimits { max_pixels: 1_000_000, ..DecodeLimits::default() },
            max_images: 4,
            ..defaults.service
        },
        ..defaults
    }
}

async fn app() -> (TestApp, Arc<StandInEngine>) {
    app_on(Db::Sqlite).await
}

async fn app_on(db: Db) -> (TestApp, Arc<StandInEngine>) {
    let engine = StandInEngine::new("stand-in-1");
    (TestApp::start_on(db, engine.clone(), config()).await, engine)
}

on_both_backends!(enroll_verify_identify_and_subjects_round_trip);
async fn enroll_verify_identify_and_subjects_round_trip(db: Db) {
    let (app, _) = app_on(db).await;
    let alice = pattern_jpeg(320, 240, 1);
    let bob = pattern_jpeg(320, 240, 9);

    let r = app.post_form("/enroll", Some("alice"), &[alice.clone(), pattern_jpeg(320, 240, 2)]).await;
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let body = r.json();
    assert_eq!((body["subject"].as_str(), body["templates"].as_u64(), body["added"].as_u64()), (Some("alice"), Some(2), Some(2)));
    assert_eq!(body["images"].as_array().unwrap().len(), 2);
    assert_eq!(r.headers["location"], "/subjects/alice");
    // Enrolling again adds templates; JSON works as well as multipart.
    let r = app.post_json("/enroll", &json!({"subject": "alice", "images": [base64(&pattern_jpeg(320, 240, 3))]})).await;
    assert_eq!((r.status, r.json()["templates"].as_u64()), (201, Some(3)));
    let r = app.post_json("/enroll", &json!({"subject": "bob", "image": base64(&bob)})).await;
    assert_eq!(r.status, 201);

    let r = app.post_form("/verify", Some("alice"), &[alice.clone()]).await;
    assert_eq!(r.status, 200);
    let v = r.json();
    assert_eq!(v["match"], true);
    assert!(v["score"].as_f64().unwrap() > 0.999);
    // Three templates: the threshold of a three-photo enrolment, not the one-photo one.
    assert_eq!((v["threshold"].as_f64(), v["fmr"].as_f64(), v["templates_compared"].as_u64()), (Some(0.97), Some(1e-3), Some(3)));
    let r = app.post_json("/verify?fmr=0.01", &json!({"subject": "alice", "image": base64(&bob)})).await;
    assert_eq!((r.status, r.json()["match"].as_bool(), r.json()["fmr"].as_f64()), (200, Some(false), Some(1e-2)));

    let r = app.post_form("/identify?k=1", None, &[bob.clone()]).await;
    assert_eq!(r.status, 200);
    let i = r.json();
    assert_eq!(i["candidates"].as_array().unwrap().len(), 1);
    assert_eq!((i["candidates"][0]["subject"].as_str(), i["candidates"][0]["match"].as_bool()), (Some("bob"), Some(true)));
    // Each candidate is judged at the threshold for its number of templates (bob has one).
    assert_eq!((i["candidates"][0]["threshold"].as_f64(), i["threshold"].as_f64()), (Some(0.95), Some(0.95)));
    assert_eq!(i["subjects_searched"], 2);

    let r = app.get("/subjects").await;
    let ids: Vec<_> = r.json()["subjects"].as_array().unwrap().iter().map(|s| s["id"].as_str().unwrap().to_string()).collect();
    assert_eq!(ids, ["alice", "bob"]);
    let r = app.get("/subjects?limit=1").await;
    assert_eq!(r.json()["next_after"], "alice");
    let r = app.get("/subjects?limit=1&after=alice").await;
    assert_eq!(r.json()["subjects"][0]["id"], "bob");
    let r = app.get("/subjects/alice").await;
    assert_eq!((r.status, r.json()["templates"].as_u64()), (200, Some(3)));
    assert_eq!(r.json()["model_versions"][0]["model_version"], "stand-in-1");

    assert_eq!(app.delete("/subjects/alice").await.status, 204);
    app.get("/subjects/alice").await.assert_problem(404, "unknown-subject");
    app.delete("/subjects/alice").await.assert_problem(404, "unknown-subject");
    app.post_form("/verify", Some("alice"), &[alice]).await.assert_problem(404, "unknown-subject");
    // Deleting erased the templates, not only the subject row.
    assert_eq!(app.store.counts().await.unwrap(), (1, 1));
}

on_both_backends!(bad_images_are_refused_with_their_problem_types);
async fn bad_images_are_refused_with_their_problem_types(db: Db) {
    let (app, engine) = app_on(db).await;
    let post = |bytes: Vec<u8>| {
        let app = &app;
        async move { app.post_form("/enroll", Some("carol"), &[bytes]).await }
    };
    post(b"this is plain text, not a photo".to_vec()).await.assert_problem(422, "not-an-image");
    post(Vec::new()).await.assert_problem(422, "not-an-image");
    // TIFF and WebP are recognised but not decoded.
    post(b"II*\x00\x08\x00\x00\x00\x00\x00\x00\x00".to_vec()).await.assert_problem(415, "unsupported-format");
    post(b"RIFF\x24\x00\x00\x00WEBPVP8 \x18\x00\x00\x00".to_vec()).await.assert_problem(415, "unsupported-format");
    let jpeg = pattern_jpeg(320, 240, 4);
    // A JPEG cut inside its header (the decoder pads a cut in the scan data with grey, so cut early).
    post(jpeg[..64].to_vec()).await.assert_problem(422, "corrupt-image");
    // Over the pixel limit (1 Mpx in these tests) though small in bytes.
    let big = encode(&image::DynamicImage::ImageLuma8(image::GrayImage::new(1200, 1000)), image::ImageFormat::Png);
    assert!(big.len() < 100_000);
    post(big).await.assert_problem(413, "too-large");
    // A PNG header claiming a huge image (a decompression bomb) is refused from the header alone.
    let mut bomb = encode(&pattern(16, 16, 1), image::ImageFormat::Png);
    bomb[16..20].copy_from_slice(&60000u32.to_be_bytes());
    bomb[20..24].copy_from_slice(&60000u32.to_be_bytes());
    let crc = crc32(&bomb[12..29]);
    bomb[29..33].copy_from_slice(&crc.to_be_bytes());
    post(bomb).await.assert_problem(413, "too-large");
    // Over the body limit (2 MiB in these tests).
    let r = app.post_form("/verify", Some("carol"), &[vec![0u8; 3 << 20]]).await;
    r.assert_problem(413, "too-large");
    let r = app.post_json("/verify", &json!({"subject": "carol", "image": base64(&vec![0u8; 3 << 20])})).await;
    r.assert_problem(413, "too-large");
    // No photo reached the engine, and nothing was stored.
    assert_eq!(engine.calls.load(Ordering::SeqCst), 0);
    assert_eq!(app.store.counts().await.unwrap(), (0, 0));
}

on_both_backends!(faces_policy_no_face_and_several_faces);
async fn faces_policy_no_face_and_several_faces(db: Db) {
    let (app, _) = app_on(db).await;
    let flat =
        encode(&image::DynamicImage::ImageLuma8(image::GrayImage::from_pixel(320, 240, image::Luma([128]))), image::ImageFormat::Png);
    let wide = pattern_jpeg(640, 240, 5);
    app.post_form("/enroll", Some("dave"), &[flat.clone()]).await.assert_problem(422, "no-face");
    // Enrolment refuses several faces and names the photo; nothing of the request is stored.
    let r = app.post_form("/enroll", Some("dave"), &[pattern_jpeg(320, 240, 6), wide.clone()]).await;
    r.assert_problem(422, "several-faces");
    assert_eq!(r.json()["image"], 1);
    assert_eq!(app.store.counts().await.unwrap(), (0, 0));
    // Verify and identify use the largest face and say how many there were.
    assert_eq!(app.post_form("/enroll", Some("dave"), &[pattern_jpeg(320, 240, 6)]).await.status, 201);
    let r = app.post_form("/verify", Some("dave"), &[wide.clone()]).await;
    assert_eq!((r.status, r.json()["faces_found"].as_u64()), (200, Some(2)));
    let r = app.post_form("/identify", None, &[wide]).await;
    assert_eq!((r.status, r.json()["faces_found"].as_u64()), (200, Some(2)));
    app.post_form("/verify", Some("dave"), &[flat.clone()]).await.assert_problem(422, "no-face");
    app.post_form("/identify", None, &[flat]).await.assert_problem(422, "no-face");
}

/// The pattern photo darkened to a tenth of its grey levels.
fn dark_pattern_jpeg(seed: u32) -> Vec<u8> {
    let mut img = pattern(320, 240, seed).to_luma8();
    img.pixels_mut().for_each(|p| p.0[0] /= 10);
    encode(&image::DynamicImage::ImageLuma8(img), image::ImageFormat::Jpeg)
}

on_both_backends!(every_analyzed_face_has_quality_and_enrollment_refuses_a_photo_below_the_policy);
async fn every_analyzed_face_has_quality_and_enrollment_refuses_a_photo_below_the_policy(db: Db) {
    let (app, _) = app_on(db).await;
    let good = pattern_jpeg(320, 240, 4);
    let dark = dark_pattern_jpeg(4);
    // A dark photo among good ones refuses the whole enrolment, names the photo and lists the
    // broken limit with its value; nothing is stored.
    let r = app.post_form("/enroll", Some("erin"), &[good.clone(), dark.clone()]).await;
    r.assert_problem(422, "low-quality");
    let p = r.json();
    assert_eq!(p["image"], 1);
    let failures = p["failures"].as_array().unwrap();
    let brightness = failures.iter().find(|f| f["component"] == "brightness").unwrap_or_else(|| panic!("{p}"));
    assert_eq!((brightness["bound"].as_str(), brightness["limit"].as_f64()), (Some("min"), Some(40.0)));
    assert!(brightness["value"].as_f64().unwrap() < 40.0, "{p}");
    assert!(p["detail"].as_str().unwrap().contains("brightness"), "{p}");
    assert_eq!(app.store.counts().await.unwrap(), (0, 0));
    app.get("/subjects/erin").await.assert_problem(404, "unknown-subject");
    // There is no opt-out: the policy is the operator's setting.
    app.post_form("/enroll?quality=off", Some("erin"), std::slice::from_ref(&dark)).await.assert_problem(400, "malformed-request");
    // A server configured without a brightness floor enrols it.
    let strict = config();
    let quality_policy = facegate_vision::quality::QualityPolicy { min_brightness: None, ..strict.service.quality_policy };
    let lenient = ApiConfig { service: ServiceConfig { quality_policy, ..strict.service }, ..strict };
    let relaxed = app.restarted_with(StandInEngine::new("stand-in-1"), lenient).await;
    assert_eq!(relaxed.post_form("/enroll", Some("erin"), std::slice::from_ref(&dark)).await.status, 201);

    // The good photo enrols; enrol, verify, identify and analyze report its quality.
    let r = app.post_form("/enroll", Some("erin"), std::slice::from_ref(&good)).await;
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let enrolled = &r.json()["images"][0]["quality"];
    let score = enrolled["score"].as_f64().unwrap();
    assert!((0.0..=100.0).contains(&score) && enrolled["brightness"].as_f64().unwrap() > 40.0, "{enrolled}");
    assert_eq!(r.json()["images"][0]["timings"]["quality_ms"], 0.0);
    for path in ["/verify", "/identify"] {
        let r = app.post_form(path, (path == "/verify").then_some("erin"), std::slice::from_ref(&good)).await;
        assert_eq!(&r.json()["quality"], enrolled, "{path}");
    }
    let r = app.post_form("/analyze", None, &[dark]).await;
    assert!(r.json()["faces"][0]["quality"]["brightness"].as_f64().unwrap() < 40.0);
}

on_both_backends!(malformed_requests_are_400_and_wrong_media_types_415);
async fn malformed_requests_are_400_and_wrong_media_types_415(db: Db) {
    let (app, engine) = app_on(db).await;
    let photo = pattern_jpeg(320, 240, 7);
    let b64 = base64(&photo);
    app.post_form("/enroll", None, &[photo.clone()]).await.assert_problem(400, "malformed-request");
    app.post_form("/enroll", Some("bad id!"), &[photo.clone()]).await.assert_problem(400, "malformed-request");
    app.post_form("/enroll", Some(&"x".repeat(129)), &[photo.clone()]).await.assert_problem(400, "malformed-request");
    app.post_form("/enroll", Some("erin"), &[]).await.assert_problem(400, "malformed-request");
    app.post_form("/enroll", Some("erin"), &vec![photo.clone(); 5]).await.assert_problem(400, "malformed-request");
    app.post_form("/verify", Some("erin"), &[photo.clone(), photo.clone()]).await.assert_problem(400, "malformed-request");
    app.post_form("/identify", Some("erin"), &[photo.clone()]).await.assert_problem(400, "malformed-request");
    app.post_json("/verify", &json!({"subject": "erin", "image": "***not base64***"})).await.assert_problem(400, "malformed-request");
    app.post_json("/verify", &json!({"subject": "erin", "image": b64, "extra": 1})).await.assert_problem(400, "malformed-request");
    app.post_json("/verify", &json!({"subject": 42, "image": b64})).await.assert_problem(400, "malformed-request");
    app.post_json("/verify?fmr=2", &json!({"subject": "erin", "image": b64})).await.assert_problem(400, "malformed-request");
    app.post_json("/verify?unknown=1", &json!({"subject": "erin", "image": b64})).await.assert_problem(400, "malformed-request");
    app.post_json("/identify?k=0", &json!({"image": b64})).await.assert_problem(400, "malformed-request");
    app.get("/subjects?limit=0").await.assert_problem(400, "malformed-request");
    app.get("/subjects/bad%20id").await.assert_problem(400, "malformed-request");
    let r = app.send(app.client.post(app.url("/verify")).header("content-type", "application/json").body("{not json")).await;
    r.assert_problem(400, "malformed-request");
    let r = app.send(app.client.post(app.url("/verify")).header("content-type", "multipart/form-data; boundary=x").body("garbage")).await;
    r.assert_problem(400, "malformed-request");
    let form = reqwest::multipart::Form::new().text("subject", "erin").text("photo", "x");
    app.send(app.client.post(app.url("/enroll")).multipart(form)).await.assert_problem(400, "malformed-request");
    let r = app.send(app.client.post(app.url("/verify")).header("content-type", "text/plain").body("hello")).await;
    r.assert_problem(415, "unsupported-media-type");
    let r = app.send(app.client.post(app.url("/verify")).body(photo.clone())).await;
    r.assert_problem(415, "unsupported-media-type");
    // Unknown routes and methods are problems too.
    app.get("/nowhere").await.assert_problem(404, "not-found");
    app.send(app.client.put(app.url("/verify"))).await.assert_problem(405, "method-not-allowed");
    assert_eq!(engine.calls.load(Ordering::SeqCst), 0);
}

on_both_backends!(templates_of_another_model_version_are_not_compared);
async fn templates_of_another_model_version_are_not_compared(db: Db) {
    let first = TestApp::start_on(db, StandInEngine::new("v1"), config()).await;
    let photo = pattern_jpeg(320, 240, 8);
    assert_eq!(first.post_form("/enroll", Some("frank"), &[photo.clone()]).await.status, 201);
    // The same database served by a newer model.
    let app = TestApp::start_on(db, StandInEngine::new("v2"), config()).await;
    let old = first.store.templates(&facegate_core::SubjectId::parse("frank").unwrap()).await.unwrap().unwrap();
    app.store.enroll(&facegate_core::SubjectId::parse("frank").unwrap(), &old).await.unwrap();
    app.post_form("/verify", Some("frank"), &[photo.clone()]).await.assert_problem(409, "model-mismatch");
    let r = app.post_form("/identify", None, &[photo.clone()]).await;
    assert_eq!((r.status, r.json()["subjects_searched"].as_u64()), (200, Some(0)));
    // Re-enrolment with the new model makes the subject comparable again; old templates are skipped.
    assert_eq!(app.post_form("/enroll", Some("frank"), &[photo.clone()]).await.status, 201);
    let r = app.post_form("/verify", Some("frank"), &[photo]).await;
    assert_eq!((r.status, r.json()["templates_compared"].as_u64(), r.json()["match"].as_bool()), (200, Some(1), Some(true)));
    assert_eq!(app.get("/subjects/frank").await.json()["model_versions"].as_array().unwrap().len(), 2);
}

#[tokio::test]
async fn api_keys_guard_everything_but_health_livez_and_openapi() {
    let keyed = ApiConfig { api_keys: vec!["s3cret".into(), "other".into()], ..config() };
    let app = TestApp::start(StandInEngine::new("v1"), keyed).await;
    app.get("/subjects").await.assert_problem(401, "unauthorized");
    let r = app.send(app.client.get(app.url("/subjects")).bearer_auth("wrong")).await;
    r.assert_problem(401, "unauthorized");
    assert!(r.headers.contains_key("www-authenticate"));
    app.post_form("/verify", Some("x"), &[vec![1, 2, 3]]).await.assert_problem(401, "unauthorized");
    assert_eq!(app.send(app.client.get(app.url("/subjects")).bearer_auth("s3cret")).await.status, 200);
    assert_eq!(app.send(app.client.get(app.url("/subjects")).header("x-api-key", "other")).await.status, 200);
    for open in ["/health", "/livez", "/openapi.yaml"] {
        assert_eq!(app.get(open).await.status, 200, "{open}");
    }
    app.get("/metrics").await.assert_problem(401, "unauthorized");
}

#[tokio::test]
async fn slow_work_times_out_with_504_and_overload_is_refused_with_503() {
    let slow = ApiConfig { request_timeout: Duration::from_millis(300), workers: 1, queue_depth: 0, ..config() };
    let app = TestApp::start(StandInEngine::slow(Duration::from_millis(1200)), slow).await;
    let photo = pattern_jpeg(320, 240, 3);
    let images = [photo];
    let (a, b) = tokio::join!(app.post_form("/identify", None, &images), async {
        tokio::time::sleep(Duration::from_millis(100)).await;
        app.post_form("/identify", None, &images).await
    });
    a.assert_problem(504, "timeout");
    // The first job still holds the only worker after its request timed out: the bound holds.
    b.assert_problem(503, "overloaded");
    assert_eq!(b.headers["retry-after"], "1");
    let metrics = String::from_utf8(app.get("/metrics").await.body).unwrap();
    assert!(metrics.contains("facegate_queue_rejections_total 1"), "{metrics}");
}

on_both_backends!(health_metrics_and_openapi_are_served);
async fn health_metrics_and_openapi_are_served(db: Db) {
    let (app, _) = app_on(db).await;
    let r = app.get("/health").await;
    assert_eq!((r.status, r.json()["status"].as_str(), r.json()["model_version"].as_str()), (200, Some("ok"), Some("stand-in-1")));
    let backend = match db {
        Db::Sqlite => "sqlite",
        Db::Postgres => "postgres",
    };
    assert_eq!(r.json()["store_backend"], backend);
    assert_eq!(app.post_form("/enroll", Some("gina"), &[pattern_jpeg(320, 240, 1)]).await.status, 201);
    let r = app.get("/metrics").await;
    let text = String::from_utf8(r.body).unwrap();
    assert!(text.contains(r#"facegate_http_requests_total{method="POST",route="/enroll",status="201"} 1"#), "{text}");
    assert!(text.contains(r#"facegate_pipeline_stage_duration_seconds_count{stage="decode"} 1"#), "{text}");
    assert!(text.contains("facegate_subjects 1") && text.contains("facegate_templates 1"), "{text}");
    let r = app.get("/openapi.yaml").await;
    assert_eq!(r.body, facegate_http::OPENAPI_YAML.as_bytes());
}

on_both_backends!(identify_follows_enroll_and_delete_and_tampered_templates_are_refused);
/// `/identify` answers from the in-memory gallery, which follows enrolments and deletions; with a
/// template key the templates are sealed, `/health` says so, and a tampered template is refused
/// with a 500 problem (never scored) by `/verify` and, once loaded, by `/identify`.
async fn identify_follows_enroll_and_delete_and_tampered_templates_are_refused(db: Db) {
    let plain = TestApp::start_on(db, StandInEngine::new("v1"), config()).await;
    assert_eq!(plain.get("/health").await.json()["templates_encrypted"], false);

    let keys = facegate_store::KeyRing::parse(&"5a".repeat(32)).unwrap();
    let app = TestApp::start_with_keys(db, StandInEngine::new("v1"), config(), Some(keys)).await;
    assert_eq!(app.get("/health").await.json()["templates_encrypted"], true);
    let (alice, bob, carol) = (pattern_jpeg(320, 240, 1), pattern_jpeg(320, 240, 9), pattern_jpeg(320, 240, 5));
    let top = |r: Reply| {
        let i = r.json();
        (i["candidates"][0]["subject"].as_str().map(String::from), i["candidates"][0]["match"].as_bool(), i["subjects_searched"].as_u64())
    };
    let r = app.post_form("/identify", None, &[bob.clone()]).await;
    assert_eq!((r.status, r.json()["candidates"].as_array().unwrap().len(), r.json()["subjects_searched"].as_u64()), (200, 0, Some(0)));
    for (subject, photo) in [("alice", &alice), ("bob", &bob), ("carol", &carol)] {
        assert_eq!(app.post_form("/enroll", Some(subject), &[photo.clone()]).await.status, 201);
    }
    assert_eq!(top(app.post_form("/identify", None, &[bob.clone()]).await), (Some("bob".into()), Some(true), Some(3)));
    assert_eq!(app.delete("/subjects/bob").await.status, 204);
    let (best, is_match, searched) = top(app.post_form("/identify", None, &[bob.clone()]).await);
    assert_ne!(best.as_deref(), Some("bob"));
    assert_eq!((is_match, searched), (Some(false), Some(2)));
    assert_eq!(app.post_form("/enroll", Some("bob"), &[bob.clone()]).await.status, 201);
    assert_eq!(top(app.post_form("/identify", None, &[bob.clone()]).await), (Some("bob".into()), Some(true), Some(3)));

    // One bit of alice's sealed template flipped in the database.
    match db {
        Db::Sqlite => {
            let mut db = sqlx::SqliteConnection::connect(&app.database_url).await.unwrap();
            let mut vector: Vec<u8> =
                sqlx::query_scalar("SELECT vector FROM templates WHERE subject_id = 'alice'").fetch_one(&mut db).await.unwrap();
            vector[30] ^= 0x10;
            sqlx::query("UPDATE templates SET vector = ?1 WHERE subject_id = 'alice'").bind(vector).execute(&mut db).await.unwrap();
            db.close().await.unwrap();
        }
        Db::Postgres => {
            let mut db = sqlx::PgConnection::connect(&app.database_url).await.unwrap();
            let mut vector: Vec<u8> =
                sqlx::query_scalar("SELECT vector FROM templates WHERE subject_id = 'alice'").fetch_one(&mut db).await.unwrap();
            vector[30] ^= 0x10;
            sqlx::query("UPDATE templates SET vector = $1 WHERE subject_id = 'alice'").bind(vector).execute(&mut db).await.unwrap();
            db.close().await.unwrap();
        }
    }
    app.post_form("/verify", Some("alice"), &[alice.clone()]).await.assert_problem(500, "internal");
    assert_eq!(app.post_form("/verify", Some("carol"), &[carol.clone()]).await.json()["match"], true, "others verify");
    // A service started on this database refuses to identify until alice is erased.
    let restarted = app.restarted_with(StandInEngine::new("v1"), config()).await;
    restarted.post_form("/identify", None, &[alice.clone()]).await.assert_problem(500, "internal");
    assert_eq!(restarted.delete("/subjects/alice").await.status, 204);
    assert_eq!(top(restarted.post_form("/identify", None, &[carol.clone()]).await), (Some("carol".into()), Some(true), Some(2)));
}

/// CRC-32 (IEEE) as PNG chunks use it, to forge a consistent header.
fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = 0xffff_ffffu32;
    for &b in bytes {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 { (crc >> 1) ^ 0xedb8_8320 } else { crc >> 1 };
        }
    }
    !crc
}

#[tokio::test]
async fn analyze_reports_the_largest_face_or_all_of_them() {
    let (app, _) = app().await;
    let wide = pattern_jpeg(640, 240, 5);
    let r = app.post_form("/analyze", None, &[wide.clone()]).await;
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let a = r.json();
    assert_eq!((a["faces_found"].as_u64(), a["faces"].as_array().unwrap().len()), (Some(2), 1));
    let face = &a["faces"][0];
    assert_eq!(face["landmarks"]["points"].as_array().unwrap().len(), 58);
    assert_eq!(face["face"]["box"]["width"], 640.0);
    // The stand-in has no 3D morphable model: no pose, no fit.
    assert!(face["pose"].is_null() && face["fit_residual_px"].is_null(), "{face}");
    for stage in ["decode_ms", "detect_ms", "total_ms"] {
        assert!(a["timings"][stage].as_f64().unwrap() >= 0.0, "{stage}");
    }
    let r = app.post_json("/analyze?faces=all", &json!({"image": base64(&wide)})).await;
    assert_eq!((r.status, r.json()["faces"].as_array().unwrap().len()), (200, 2));
    let r = app.post_form("/analyze?faces=largest", None, &[pattern_jpeg(320, 240, 1)]).await;
    assert_eq!((r.status, r.json()["faces_found"].as_u64()), (200, Some(1)));
    // Nothing is stored.
    assert_eq!(app.store.counts().await.unwrap(), (0, 0));
    let flat =
        encode(&image::DynamicImage::ImageLuma8(image::GrayImage::from_pixel(320, 240, image::Luma([128]))), image::ImageFormat::Png);
    app.post_form("/analyze", None, &[flat]).await.assert_problem(422, "no-face");
    app.post_form("/analyze?faces=some", None, &[wide.clone()]).await.assert_problem(400, "malformed-request");
    app.post_form("/analyze", Some("alice"), &[wide.clone()]).await.assert_problem(400, "malformed-request");
    app.post_form("/analyze", None, &[wide.clone(), wide]).await.assert_problem(400, "malformed-request");
    app.post_form("/analyze", None, &[b"plain text".to_vec()]).await.assert_problem(422, "not-an-image");
}

#[tokio::test]
async fn avatar_and_frontalize_need_the_3d_model_and_share_the_photo_checks() {
    let (app, engine) = app().await;
    let photo = pattern_jpeg(320, 240, 2);
    for route in ["/avatar", "/frontalize"] {
        let r = app.post_form(route, None, &[photo.clone()]).await;
        r.assert_problem(422, "no-face-model");
        assert!(r.json()["detail"].as_str().unwrap().contains("3D morphable model"), "{}", r.json());
        app.post_json(route, &json!({"image": base64(&photo)})).await.assert_problem(422, "no-face-model");
        app.post_form(route, None, &[b"plain text".to_vec()]).await.assert_problem(422, "not-an-image");
        app.post_form(route, None, &[photo[..64].to_vec()]).await.assert_problem(422, "corrupt-image");
        app.post_form(route, None, &[vec![0u8; 3 << 20]]).await.assert_problem(413, "too-large");
        app.post_form(route, None, &[]).await.assert_problem(400, "malformed-request");
        app.post_form(&format!("{route}?format=stl"), None, &[photo.clone()]).await.assert_problem(400, "malformed-request");
        let r = app.send(app.client.post(app.url(route)).header("content-type", "text/plain").body("x")).await;
        r.assert_problem(415, "unsupported-media-type");
    }
    app.post_form("/avatar?format=obj", None, &[photo.clone()]).await.assert_problem(422, "no-face-model");
    app.post_form("/frontalize?format=obj", None, &[photo.clone()]).await.assert_problem(400, "malformed-request");
    // Two photos reached the engine per route (the multipart and the JSON request), and the OBJ one.
    assert_eq!(engine.calls.load(Ordering::SeqCst), 5);
    // The same work pool as /verify: a full queue refuses at once.
    let slow = ApiConfig { workers: 1, queue_depth: 0, ..config() };
    let app = TestApp::start(StandInEngine::slow(Duration::from_millis(600)), slow).await;
    let images = [photo];
    let (a, b) = tokio::join!(app.post_form("/avatar", None, &images), async {
        tokio::time::sleep(Duration::from_millis(150)).await;
        app.post_form("/frontalize", None, &images).await
    });
    a.assert_problem(422, "no-face-model");
    b.assert_problem(503, "overloaded");
}

#[tokio::test]
async fn the_console_is_served_at_the_root_and_other_paths_stay_problems() {
    let keyed = ApiConfig { api_keys: vec!["s3cret".into()], ..config() };
    let app = TestApp::start(StandInEngine::new("v1"), keyed).await;
    // Pages need no key (the page asks for one); the API still does.
    let r = app.get("/").await;
    assert_eq!(r.status, 200);
    assert_eq!(r.headers["content-type"], "text/html; charset=utf-8");
    assert!(r.headers["content-security-policy"].to_str().unwrap().contains("script-src 'self'"));
    let html = String::from_utf8(r.body).unwrap();
    assert!(html.contains(r#"<script type="module" src="/console/console.js">"#), "{html}");
    for (path, media) in [
        ("/console/console.js", "text/javascript; charset=utf-8"),
        ("/console/console.css", "text/css; charset=utf-8"),
        ("/console/vendor/viewer.js", "text/javascript; charset=utf-8"),
    ] {
        let r = app.get(path).await;
        assert_eq!((r.status, r.headers["content-type"].to_str().unwrap()), (200, media), "{path}");
        assert!(r.body.len() > 1000, "{path}");
    }
    // Nothing the page loads comes from elsewhere.
    for asset in facegate_http::console::ASSETS {
        let text = String::from_utf8_lossy(asset.body);
        for pattern in ["src=\"http", "href=\"http", "import(\"http", "from\"http", "from 'http", "url(http"] {
            assert!(!text.contains(pattern), "{} refers to {pattern}…", asset.path);
        }
    }
    app.post_form("/analyze", None, &[pattern_jpeg(320, 240, 1)]).await.assert_problem(401, "unauthorized");
    app.get("/console/missing.js").await.assert_problem(404, "not-found");
    app.get("/index.html").await.assert_problem(404, "not-found");
    app.send(app.client.post(app.url("/"))).await.assert_problem(405, "method-not-allowed");
    // With the console switched off, the root is an unknown route like any other.
    let app = TestApp::start(StandInEngine::new("v1"), ApiConfig { console: false, ..config() }).await;
    app.get("/").await.assert_problem(404, "not-found");
    app.get("/console/console.js").await.assert_problem(404, "not-found");
}
