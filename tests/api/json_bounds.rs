//! Bodies of many photos: the JSON `images` array and the multipart `image` parts are counted
//! while they are parsed and refused at the first one past the most photos any operation takes
//! (`max_images`), before anything of it is copied or decoded; a body at that bound still reaches
//! the operation's own count. And one JSON shape: an object, `null` the same as a field left out.

use std::sync::atomic::Ordering;

use facegate_http::ApiConfig;
use facegate_service::ServiceConfig;
use serde_json::json;

use crate::support::*;

/// The serve defaults: a 16 MiB body limit and at most 16 photos per enrolment.
fn defaults() -> ApiConfig {
    facegate::config::Settings::default().api_config().unwrap()
}

/// `{"subject":"a","images":[E,E,…]}` with `n` copies of the JSON text `entry`.
fn many_photos(n: usize, entry: &str) -> String {
    let mut body = String::with_capacity(n * (entry.len() + 1) + 32);
    body.push_str(r#"{"subject":"a","images":["#);
    for i in 0..n {
        if i > 0 {
            body.push(',');
        }
        body.push_str(entry);
    }
    body.push_str("]}");
    body
}

async fn post_raw(app: &TestApp, path: &str, body: String) -> Reply {
    app.send(app.client.post(app.url(path)).header("content-type", "application/json").body(body)).await
}

fn detail(r: &Reply) -> String {
    r.json()["detail"].as_str().unwrap().to_string()
}

#[tokio::test]
async fn millions_of_tiny_photos_are_refused_at_the_cap() {
    let config = defaults();
    assert_eq!(config.service.max_images, 16);
    let engine = StandInEngine::new("v1");
    let app = TestApp::start(engine.clone(), config.clone()).await;
    // 3,000,000 one-byte photos (`"AA"`), 15 MB: under the 16 MiB body limit.
    let body = many_photos(3_000_000, r#""AA""#);
    assert!(body.len() > 14_000_000 && body.len() < config.max_body_bytes, "{}", body.len());
    for path in ["/enroll", "/verify", "/identify"] {
        let r = post_raw(&app, path, body.clone()).await;
        r.assert_problem(400, "malformed-request");
        assert_eq!(detail(&r), "at most 16 photos per request (field images), got more than 16", "{path}");
        assert!(r.json().get("image").is_none(), "{path}: no photo is to blame");
    }
    // Empty strings (not even base64 yet) are counted the same way.
    let r = post_raw(&app, "/enroll", many_photos(3_000_000, r#""""#)).await;
    r.assert_problem(400, "malformed-request");
    assert_eq!(detail(&r), "at most 16 photos per request (field images), got more than 16");
    assert_eq!(engine.calls.load(Ordering::SeqCst), 0, "no photo reached the engine");
    assert_eq!(app.get("/health").await.status, 200);
}

/// A multipart body of `n` `image` parts of one byte each (boundary `b`), and its Content-Type.
fn many_parts(n: usize) -> Vec<u8> {
    let mut body = Vec::with_capacity(n * 60 + 8);
    for _ in 0..n {
        body.extend_from_slice(b"--b\r\nContent-Disposition: form-data; name=\"image\"\r\n\r\nx\r\n");
    }
    body.extend_from_slice(b"--b--\r\n");
    body
}

#[tokio::test]
async fn a_hundred_and_fifty_thousand_multipart_photos_are_refused_at_the_cap() {
    let engine = StandInEngine::new("v1");
    let app = TestApp::start(engine.clone(), defaults()).await;
    let body = many_parts(150_000);
    assert!(body.len() > 7_000_000 && body.len() < 16 << 20, "{}", body.len());
    for path in ["/enroll", "/verify", "/analyze"] {
        let started = std::time::Instant::now();
        let request = app.client.post(app.url(path)).header("content-type", "multipart/form-data; boundary=b").body(body.clone());
        let r = app.send(request).await;
        r.assert_problem(400, "malformed-request");
        assert_eq!(detail(&r), "at most 16 photos per request (field image), got more than 16", "{path}");
        assert!(started.elapsed() < std::time::Duration::from_secs(5), "{path}: {:?}", started.elapsed());
    }
    // Sixteen parts still reach the operation's own count.
    let request = app.client.post(app.url("/analyze")).header("content-type", "multipart/form-data; boundary=b").body(many_parts(16));
    let r = app.send(request).await;
    r.assert_problem(400, "malformed-request");
    assert_eq!(detail(&r), "exactly one photo is expected, got 16");
    assert_eq!(engine.calls.load(Ordering::SeqCst), 0, "no photo reached the engine");
}

#[tokio::test]
async fn one_json_shape_an_object_with_null_as_absent() {
    let app = TestApp::start(StandInEngine::new("v1"), defaults()).await;
    let photo = base64(&pattern_jpeg(320, 240, 4));
    let r = app.post_json("/enroll", &json!({"subject": "ada", "image": photo, "images": null})).await;
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    // `frames: null` is no frames, as `images: null` is no further photos.
    let r = app.post_json("/verify", &json!({"subject": "ada", "image": photo, "frames": null})).await;
    assert_eq!((r.status, r.json()["match"].as_bool()), (200, Some(true)), "{}", String::from_utf8_lossy(&r.body));
    // The same fields as an array, which serde's derive would take for the struct: malformed.
    for (path, array) in
        [("/verify", json!(["ada", photo])), ("/enroll", json!(["ada", photo, null])), ("/verify", json!(["ada", photo, null, null]))]
    {
        let r = post_raw(&app, path, array.to_string()).await;
        r.assert_problem(400, "malformed-request");
        assert!(detail(&r).starts_with("invalid JSON body: invalid type: sequence"), "{path}: {}", detail(&r));
    }
}

#[tokio::test]
async fn a_body_at_the_cap_reaches_the_operations_count() {
    let app = TestApp::start(StandInEngine::new("v1"), defaults()).await;
    let tiny = r#""AA""#;
    // Exactly 16: parsed and decoded; verification takes one photo and says how many it got.
    let r = post_raw(&app, "/verify", many_photos(16, tiny)).await;
    r.assert_problem(400, "malformed-request");
    assert_eq!(detail(&r), "exactly one photo is expected, got 16");
    // 16 in `images` and one in `image`: the enrolment counts all 17.
    let body = many_photos(16, tiny).replacen('{', r#"{"image":"AA","#, 1);
    let r = post_raw(&app, "/enroll", body).await;
    r.assert_problem(400, "malformed-request");
    assert_eq!(detail(&r), "at most 16 photos per enrolment, got 17");
    // 17 in `images`: refused by the parse.
    let r = post_raw(&app, "/enroll", many_photos(17, tiny)).await;
    r.assert_problem(400, "malformed-request");
    assert_eq!(detail(&r), "at most 16 photos per request (field images), got more than 16");

    // The cap is the setting: with `max_images` 3, three real photos enrol and a fourth is refused.
    let app = TestApp::start(
        StandInEngine::new("v1"),
        ApiConfig { service: ServiceConfig { max_images: 3, ..defaults().service }, ..defaults() },
    )
    .await;
    let photos: Vec<String> = (0..4).map(|seed| base64(&pattern_jpeg(320, 240, seed))).collect();
    let r = app.post_json("/enroll", &json!({"subject": "ada", "images": photos[..3]})).await;
    assert_eq!((r.status, r.json()["added"].as_u64()), (201, Some(3)), "{}", String::from_utf8_lossy(&r.body));
    let r = app.post_json("/enroll", &json!({"subject": "ada", "images": photos})).await;
    r.assert_problem(400, "malformed-request");
    assert_eq!(detail(&r), "at most 3 photos per request (field images), got more than 3");
    // A bad photo within the cap is still named by its index, `image` first.
    let r = app.post_json("/enroll", &json!({"subject": "ada", "image": photos[0], "images": [photos[1], "***"]})).await;
    r.assert_problem(400, "malformed-request");
    assert_eq!(r.json()["image"], 2);
}
