//! `/verify` of a capture: a probe and up to four further frames of the same capture,
//! through the real app, pipeline and `models/liveness.bin` on NUAA frames of subject 0004. The
//! probe alone is matched; every frame must show a face of the probe's person (else 422 `no-face`
//! or `frames-mismatch`, naming the frame); the liveness is fused over the probe and the frames
//! (σ of the mean logit), and `--liveness enforce` refuses by the fused score.

use facegate::choices::Liveness as Choice;
use facegate::config::Settings;
use reqwest::multipart::{Form, Part};
use serde_json::{Value, json};

use crate::pipeline::pipeline;
use crate::support::*;

use crate::liveness::{LIVE_ENROL, LIVE_PROBE, PRINT, nuaa};

/// Further live frames of subject 0004, from the probe's capture.
const LIVE_FRAMES: [&str; 2] = ["real/0004/0004_01_00_01_246.jpg", "real/0004/0004_01_00_01_261.jpg"];
const SUBJECT: &str = "nuaa-0004";

/// An app with `liveness` on the shared pipeline, subject 0004 enrolled from a live frame.
async fn app(liveness: Choice) -> TestApp {
    let settings = Settings { liveness, ..Settings::default() };
    let app = TestApp::start(pipeline(), settings.api_config().unwrap()).await;
    let r = app.post_form("/enroll", Some(SUBJECT), &[nuaa(LIVE_ENROL)]).await;
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    app
}

/// POST /verify as multipart: the probe as `image`, then one `frame` part per frame, in order.
async fn verify_frames(app: &TestApp, probe: &[u8], frames: &[Vec<u8>]) -> Reply {
    let mut form = Form::new().text("subject", SUBJECT).part("image", Part::bytes(probe.to_vec()).file_name("probe.jpg"));
    for (i, frame) in frames.iter().enumerate() {
        form = form.part("frame", Part::bytes(frame.clone()).file_name(format!("frame{i}.jpg")));
    }
    app.send(app.client.post(app.url("/verify")).multipart(form)).await
}

fn live_frames() -> Vec<Vec<u8>> {
    LIVE_FRAMES.iter().map(|name| nuaa(name)).collect()
}

/// σ(mean over `scores` of logit(s)), s clamped into [1e-6, 1 − 1e-6]: the documented fusion.
fn fused(scores: &[f64]) -> f64 {
    let logit = |s: f64| {
        let s = s.clamp(1e-6, 1.0 - 1e-6);
        (s / (1.0 - s)).ln()
    };
    let mean = scores.iter().map(|&s| logit(s)).sum::<f64>() / scores.len() as f64;
    1.0 / (1.0 + (-mean).exp())
}

fn frame_scores(liveness: &Value) -> Vec<f64> {
    liveness["frame_scores"]
        .as_array()
        .unwrap_or_else(|| panic!("no frame_scores in {liveness}"))
        .iter()
        .map(|s| s.as_f64().unwrap())
        .collect()
}

/// The liveness the pipeline itself gives the largest face of `photo`.
fn own_score(photo: &[u8]) -> f32 {
    let photo = facegate_core::imaging::decode(photo, &Default::default()).unwrap();
    pipeline().analyze(&photo).unwrap().liveness.expect("a liveness model is loaded").score
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn live_frames_of_the_probes_capture_fuse_their_liveness() {
    let app = app(Choice::Report).await;
    let single = app.post_form("/verify", Some(SUBJECT), &[nuaa(LIVE_PROBE)]).await;
    assert_eq!(single.status, 200, "{}", String::from_utf8_lossy(&single.body));
    let single = single.json();
    assert!(single["liveness"].get("frames").is_none() && single["liveness"].get("frame_scores").is_none(), "{single}");

    let r = verify_frames(&app, &nuaa(LIVE_PROBE), &live_frames()).await;
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let body = r.json();
    // The probe alone is matched: the decision is the single photo's.
    for key in ["match", "score", "threshold", "templates_compared", "best_template", "face", "quality"] {
        assert_eq!(body[key], single[key], "{key}: {body}");
    }
    assert_eq!(body["match"], true, "{body}");
    let liveness = &body["liveness"];
    assert_eq!(liveness["frames"], 3, "{body}");
    let scores = frame_scores(liveness);
    assert_eq!(scores.len(), 3, "{body}");
    // Each photo's own score, the probe's first, as the pipeline gives it.
    let own: Vec<f32> = [nuaa(LIVE_PROBE), nuaa(LIVE_FRAMES[0]), nuaa(LIVE_FRAMES[1])].iter().map(|p| own_score(p)).collect();
    assert_eq!(scores.iter().map(|&s| s as f32).collect::<Vec<_>>(), own, "{body}");
    assert_eq!(scores[0], single["liveness"]["score"].as_f64().unwrap(), "{body}");
    let score = liveness["score"].as_f64().unwrap();
    assert!((score - fused(&scores)).abs() < 1e-4, "fused {score}, expected {} from {scores:?}", fused(&scores));
    assert_eq!(liveness["attack"], false, "{body}");

    // The same capture as JSON: the same answer.
    let frames: Vec<String> = live_frames().iter().map(|f| base64(f)).collect();
    let r = app.post_json("/verify", &json!({"subject": SUBJECT, "image": base64(&nuaa(LIVE_PROBE)), "frames": frames})).await;
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let as_json = r.json();
    assert_eq!((&as_json["score"], &as_json["liveness"]), (&body["score"], liveness), "{as_json}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn enforce_judges_a_print_with_live_frames_by_the_fused_score() {
    let pipeline = pipeline();
    let threshold = f64::from(pipeline.liveness.as_ref().expect("the committed liveness model is loaded").threshold);
    // Report first: each photo's own score, and the fusion the service makes of them.
    let report = app(Choice::Report).await;
    let r = verify_frames(&report, &nuaa(PRINT), &live_frames()).await;
    assert_eq!(r.status, 200, "the print and the live frames show one person: {}", String::from_utf8_lossy(&r.body));
    let reported = r.json();
    let scores = frame_scores(&reported["liveness"]);
    let expected = fused(&scores);
    assert!(scores[0] < threshold && scores[1..].iter().all(|&s| s >= threshold), "print first, then live frames: {scores:?}");
    let score = reported["liveness"]["score"].as_f64().unwrap();
    assert!((score - expected).abs() < 1e-4, "fused {score}, expected {expected} from {scores:?}");
    assert_eq!(reported["liveness"]["attack"], expected < threshold, "attack is the fused score below {threshold}: {reported}");

    // Enforce decides by that fused score: refused with it when below the threshold, else
    // answered (the print alone is refused: tests/api/liveness.rs). With the committed model the
    // two confident live frames outvote the print (scores about 3e-5, 0.999997 and 0.9996 fuse to
    // 0.97): the capture is answered, as docs/http-api.md says.
    let enforce =
        report.restarted_with(pipeline.clone(), Settings { liveness: Choice::Enforce, ..Settings::default() }.api_config().unwrap()).await;
    let r = verify_frames(&enforce, &nuaa(PRINT), &live_frames()).await;
    if expected < threshold {
        r.assert_problem(422, "presentation-attack");
        let problem = r.json();
        assert!((problem["score"].as_f64().unwrap() - expected).abs() < 1e-4, "the fused score: {problem}");
        assert!((problem["threshold"].as_f64().unwrap() - threshold).abs() < 1e-6, "{problem}");
    } else {
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        let answered = r.json();
        assert_eq!(answered["liveness"], reported["liveness"], "{answered}");
        assert_eq!(answered["liveness"]["attack"], false, "{answered}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_frame_of_another_person_or_without_a_face_is_refused_by_its_index() {
    let app = app(Choice::Report).await;
    // An IMM person as the second frame of a NUAA capture.
    let r = verify_frames(&app, &nuaa(LIVE_PROBE), &[nuaa(LIVE_FRAMES[0]), imm("01-1m.jpg")]).await;
    r.assert_problem(422, "frames-mismatch");
    let problem = r.json();
    assert_eq!((&problem["frame"], problem.get("image")), (&json!(1), None), "{problem}");
    assert!(problem["detail"].as_str().unwrap().contains("does not show the person of the probe"), "{problem}");

    // A blank frame: no face, named by its index among the frames.
    let blank = encode(
        &image::DynamicImage::ImageRgb8(image::RgbImage::from_pixel(640, 480, image::Rgb([128, 128, 128]))),
        image::ImageFormat::Jpeg,
    );
    let r = verify_frames(&app, &nuaa(LIVE_PROBE), &[nuaa(LIVE_FRAMES[0]), nuaa(LIVE_FRAMES[1]), blank.clone()]).await;
    r.assert_problem(422, "no-face");
    assert_eq!((&r.json()["frame"], r.json().get("image")), (&json!(2), None), "{}", r.json());
    let r = app.post_json("/verify", &json!({"subject": SUBJECT, "image": base64(&nuaa(LIVE_PROBE)), "frames": [base64(&blank)]})).await;
    r.assert_problem(422, "no-face");
    assert_eq!(r.json()["frame"], 0, "{}", r.json());
    // The probe without a face is the probe's problem, as for a single photo: no `frame`.
    let r = verify_frames(&app, &blank, &live_frames()).await;
    r.assert_problem(422, "no-face");
    assert!(r.json().get("frame").is_none(), "{}", r.json());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn frames_past_twenty_or_frames_elsewhere_than_verify_are_malformed() {
    let app = app(Choice::Report).await;
    // A plain capture takes as many frames as a challenge's bursts: 20 besides the probe.
    let many: Vec<Vec<u8>> = (0..21).map(|i| nuaa(LIVE_FRAMES[i % LIVE_FRAMES.len()])).collect();
    let r = verify_frames(&app, &nuaa(LIVE_PROBE), &many).await;
    r.assert_problem(400, "malformed-request");
    assert!(r.json()["detail"].as_str().unwrap().contains("at most 20 frames"), "{}", r.json());
    let frames: Vec<String> = many.iter().map(|f| base64(f)).collect();
    let r = app.post_json("/verify", &json!({"subject": SUBJECT, "image": base64(&nuaa(LIVE_PROBE)), "frames": frames})).await;
    r.assert_problem(400, "malformed-request");
    assert!(r.json()["detail"].as_str().unwrap().contains("at most 20 frames"), "{}", r.json());
    // Twenty are taken, and fused with the probe.
    let r = verify_frames(&app, &nuaa(LIVE_PROBE), &many[..20]).await;
    assert_eq!((r.status, &r.json()["liveness"]["frames"]), (200, &json!(21)), "{}", String::from_utf8_lossy(&r.body));
    // Only /verify takes frames.
    let frame = json!([base64(&nuaa(LIVE_FRAMES[0]))]);
    for (path, body) in [
        ("/enroll", json!({"subject": "other", "image": base64(&nuaa(LIVE_PROBE)), "frames": frame})),
        ("/identify", json!({"image": base64(&nuaa(LIVE_PROBE)), "frames": frame})),
        ("/analyze", json!({"image": base64(&nuaa(LIVE_PROBE)), "frames": frame})),
    ] {
        let r = app.post_json(path, &body).await;
        r.assert_problem(400, "malformed-request");
        assert!(r.json()["detail"].as_str().unwrap().contains("only /verify"), "{path}: {}", r.json());
    }
}
