//! The head-turn liveness challenge through the real app and pipeline: `POST /liveness/challenge`
//! draws 3 or 4 steps with a turn to each side; `/verify` answering it with IMM person 15's own
//! photos in step order passes and matches, each step's yaw the frame's `/analyze`
//! `key_point_pose.yaw`; the same challenge again, an unknown or malformed
//! one, and an expired one are `invalid-challenge`; the photo held still and the right photos in
//! the wrong order fail it (reported under `report`, refused as `presentation-attack` with the
//! reason under `enforce`); a wrong number of frames is malformed; with liveness off there are no
//! challenges. The JSON form takes the same fields. Bursts: `frame_steps` names each frame's
//! step; a burst with a stranger's photo fails the one-person check, and ill-formed `frame_steps`
//! are malformed. A larger face beside the person's is not taken for theirs: the server follows
//! the person's face from the probe. With `--require-challenge` a plain `/verify` is refused, and
//! the audit log names each issued challenge and the verdict on its answer.

use std::time::Duration;

use facegate::choices::Liveness as Choice;
use facegate::config::Settings;
use facegate_http::ApiConfig;
use facegate_service::ChallengeConfig;
use reqwest::multipart::{Form, Part};
use serde_json::{Value, json};

use crate::pipeline::pipeline;
use crate::support::*;

const SUBJECT: &str = "imm-15";

async fn app_with(config: ApiConfig) -> TestApp {
    let app = TestApp::start(pipeline(), config).await;
    let r = app.post_form("/enroll", Some(SUBJECT), &[imm("15-1f.jpg")]).await;
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    app
}

async fn app(liveness: Choice) -> TestApp {
    app_with(Settings { liveness, ..Settings::default() }.api_config().unwrap()).await
}

async fn challenge(app: &TestApp) -> Value {
    let r = app.send(app.client.post(app.url("/liveness/challenge"))).await;
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    r.json()
}

fn turns_of(challenge: &Value) -> Vec<String> {
    challenge["steps"].as_array().unwrap().iter().map(|s| s["turn"].as_str().unwrap().to_string()).collect()
}

/// Person 15's photo for each step: the front alternately views 5 and 1, left view 4, right view 3.
fn live_frames(turns: &[String]) -> Vec<Vec<u8>> {
    let mut fronts = 0;
    turns
        .iter()
        .map(|turn| match turn.as_str() {
            "front" => {
                fronts += 1;
                imm(if fronts % 2 == 1 { "15-5f.jpg" } else { "15-1f.jpg" })
            }
            "left" => imm("15-4f.jpg"),
            "right" => imm("15-3f.jpg"),
            other => panic!("unknown turn {other}"),
        })
        .collect()
}

async fn verify(app: &TestApp, challenge: &str, frames: &[Vec<u8>]) -> Reply {
    verify_bursts(app, challenge, frames, None).await
}

async fn verify_bursts(app: &TestApp, challenge: &str, frames: &[Vec<u8>], frame_steps: Option<&str>) -> Reply {
    let mut form = Form::new()
        .text("subject", SUBJECT)
        .part("image", Part::bytes(imm("15-2f.jpg")).file_name("probe.jpg"))
        .text("challenge", challenge.to_string());
    if let Some(steps) = frame_steps {
        form = form.text("frame_steps", steps.to_string());
    }
    for (i, frame) in frames.iter().enumerate() {
        form = form.part("frame", Part::bytes(frame.clone()).file_name(format!("frame{i}.jpg")));
    }
    app.send(app.client.post(app.url("/verify")).multipart(form)).await
}

/// Person 15's bursts: each front step both frontal views (5 and 1), each turn its view twice (a
/// head held still for two frames), and `frame_steps` naming them.
fn live_bursts(turns: &[String]) -> (Vec<Vec<u8>>, String) {
    let (mut frames, mut steps) = (Vec::new(), Vec::new());
    for (i, turn) in turns.iter().enumerate() {
        let burst: [&str; 2] = match turn.as_str() {
            "front" => ["15-5f.jpg", "15-1f.jpg"],
            "left" => ["15-4f.jpg", "15-4f.jpg"],
            _ => ["15-3f.jpg", "15-3f.jpg"],
        };
        for name in burst {
            frames.push(imm(name));
            steps.push(i.to_string());
        }
    }
    (frames, steps.join(","))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_challenge_has_three_or_four_steps_with_a_turn_to_each_side() {
    let app = app(Choice::Report).await;
    let mut ids = std::collections::BTreeSet::new();
    for _ in 0..12 {
        let c = challenge(&app).await;
        let id = c["challenge"].as_str().unwrap();
        assert!(id.len() == 32 && id.bytes().all(|b| b.is_ascii_hexdigit()), "{c}");
        ids.insert(id.to_string());
        assert_eq!(c["expires_in"], 120, "{c}");
        let turns = turns_of(&c);
        assert!((3..=4).contains(&turns.len()) && turns.contains(&"left".into()) && turns.contains(&"right".into()), "{c}");
        for step in c["steps"].as_array().unwrap() {
            let (min, max) = (step["yaw_min"].as_f64().unwrap(), step["yaw_max"].as_f64().unwrap());
            match step["turn"].as_str().unwrap() {
                "front" => assert!(min < 0.0 && max > 0.0 && min == -max, "{step}"),
                "left" => assert!(min > 0.0 && max > min, "{step}: yaw > 0 is a head turned to its own left"),
                _ => assert!(max < 0.0 && min < max, "{step}"),
            }
        }
    }
    assert_eq!(ids.len(), 12, "every challenge has its own id");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_persons_own_turns_pass_once_and_the_challenge_is_used_up() {
    let app = app(Choice::Enforce).await;
    let c = challenge(&app).await;
    let (id, turns) = (c["challenge"].as_str().unwrap(), turns_of(&c));
    let r = verify(&app, id, &live_frames(&turns)).await;
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let body = r.json();
    assert_eq!(body["match"], true, "{body}");
    let verdict = &body["liveness"]["challenge"];
    assert_eq!(verdict["passed"], true, "{body}");
    assert!(verdict["reason"].is_null(), "{body}");
    assert_eq!(body["liveness"]["attack"], false, "{body}");
    assert_eq!(body["liveness"]["frames"], turns.len() + 1, "the passive score is fused over the probe and every frame: {body}");
    let steps = verdict["steps"].as_array().unwrap();
    assert_eq!(steps.len(), turns.len());
    for (step, turn) in steps.iter().zip(&turns) {
        assert_eq!((step["turn"].as_str().unwrap(), step["ok"].as_bool().unwrap()), (turn.as_str(), true), "{body}");
        let yaw = step["yaw"].as_f64().unwrap();
        match turn.as_str() {
            "left" => assert!(yaw > 12.0, "{body}"),
            "right" => assert!(yaw < -12.0, "{body}"),
            _ => assert!(yaw.abs() < 12.0, "{body}"),
        }
    }
    // A client checks its frames with `/analyze`: each step's yaw is the frame's
    // `key_point_pose.yaw` there, the yaw the steps' ranges are in.
    for (step, frame) in steps.iter().zip(live_frames(&turns)) {
        let analyzed = app.post_form("/analyze", None, &[frame]).await.json();
        let yaw = analyzed["faces"][0]["key_point_pose"]["yaw"].as_f64().expect("YuNet's key points and the 3DMM give a pose");
        assert!((yaw - step["yaw"].as_f64().unwrap()).abs() < 1e-3, "{analyzed} against {step}");
    }
    // The same challenge again, whatever the frames: it was taken by the first answer.
    verify(&app, id, &live_frames(&turns)).await.assert_problem(422, "invalid-challenge");
    // Never issued, and not even an id.
    verify(&app, &"0".repeat(32), &live_frames(&turns)).await.assert_problem(422, "invalid-challenge");
    verify(&app, "' OR 1=1 --", &live_frames(&turns)).await.assert_problem(422, "invalid-challenge");
    // Steps the schema allows (up to three digits) but no challenge has: the unknown challenge is
    // what is wrong, found before its steps are counted.
    let frames = live_frames(&turns);
    verify_bursts(&app, &"0".repeat(32), &frames, Some("0, 5,\t979")).await.assert_problem(422, "invalid-challenge");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_still_photo_and_the_wrong_order_fail_the_challenge() {
    // Report: answered 200 with the verdict, the liveness an attack.
    let app = app(Choice::Report).await;
    let c = challenge(&app).await;
    let turns = turns_of(&c);
    let still = vec![imm("15-2f.jpg"); turns.len()];
    let r = verify(&app, c["challenge"].as_str().unwrap(), &still).await;
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let body = r.json();
    assert_eq!(body["liveness"]["challenge"]["passed"], false, "{body}");
    assert_eq!(body["liveness"]["attack"], true, "{body}");
    assert!(body["liveness"]["challenge"]["reason"].as_str().unwrap().contains("yaw"), "{body}");
    assert_eq!(body["match"], true, "the probe itself still matches: {body}");

    // Enforce: the right photos with left and right exchanged are refused, with the reason.
    let app = app_with(Settings { liveness: Choice::Enforce, ..Settings::default() }.api_config().unwrap()).await;
    let c = challenge(&app).await;
    let swapped: Vec<String> = turns_of(&c)
        .iter()
        .map(|t| match t.as_str() {
            "left" => "right".to_string(),
            "right" => "left".to_string(),
            other => other.to_string(),
        })
        .collect();
    let r = verify(&app, c["challenge"].as_str().unwrap(), &live_frames(&swapped)).await;
    r.assert_problem(422, "presentation-attack");
    let problem = r.json();
    assert!(problem["reason"].as_str().unwrap().contains("outside"), "{problem}");
}

/// A passed challenge is held to the passive score only at a threshold set for the deployment:
/// at the model's own point the fused score is reported, at the operator's it decides.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_passed_challenge_is_held_to_the_operators_passive_threshold_not_the_models() {
    for (threshold, attack) in [(None, false), (Some(0.999_999), true)] {
        let settings = Settings { liveness: Choice::Report, liveness_threshold: threshold, ..Settings::default() };
        let app = app_with(settings.api_config().unwrap()).await;
        let c = challenge(&app).await;
        let r = verify(&app, c["challenge"].as_str().unwrap(), &live_frames(&turns_of(&c))).await;
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        let body = r.json();
        assert_eq!(body["liveness"]["challenge"]["passed"], true, "{body}");
        let score = body["liveness"]["score"].as_f64().unwrap();
        assert!(score < 0.999_999, "{body}");
        assert_eq!(body["liveness"]["attack"], attack, "threshold {threshold:?}: {body}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_frame_count_is_malformed_and_json_takes_the_same_fields() {
    let app = app(Choice::Report).await;
    let c = challenge(&app).await;
    let turns = turns_of(&c);
    let mut frames = live_frames(&turns);
    frames.pop();
    let r = verify(&app, c["challenge"].as_str().unwrap(), &frames).await;
    r.assert_problem(400, "malformed-request");
    assert!(r.json()["detail"].as_str().unwrap().contains(&format!("has {} steps", turns.len())), "{}", String::from_utf8_lossy(&r.body));

    let c = challenge(&app).await;
    let frames: Vec<String> = live_frames(&turns_of(&c)).iter().map(|f| base64(f)).collect();
    let body = json!({"subject": SUBJECT, "image": base64(&imm("15-2f.jpg")), "challenge": c["challenge"], "frames": frames});
    let r = app.post_json("/verify", &body).await;
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["liveness"]["challenge"]["passed"], true, "{}", String::from_utf8_lossy(&r.body));

    // Only /verify takes a challenge.
    let form = Form::new().part("image", Part::bytes(imm("15-2f.jpg")).file_name("a.jpg")).text("challenge", "0".repeat(32));
    app.send(app.client.post(app.url("/identify")).multipart(form)).await.assert_problem(400, "malformed-request");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_expired_challenge_never_passes_and_liveness_off_issues_none() {
    let defaults = Settings::default().api_config().unwrap();
    let mut service = defaults.service.clone();
    service.challenge = ChallengeConfig { lifetime: Duration::from_millis(300) };
    let app = app_with(ApiConfig { service, ..defaults }).await;
    let c = challenge(&app).await;
    assert_eq!(c["expires_in"], 1, "0.3 s announced as 1 s, rounded up: {c}");
    tokio::time::sleep(Duration::from_millis(600)).await;
    let r = verify(&app, c["challenge"].as_str().unwrap(), &live_frames(&turns_of(&c))).await;
    r.assert_problem(422, "invalid-challenge");
    assert!(r.json()["detail"].as_str().unwrap().contains("expired"), "{}", String::from_utf8_lossy(&r.body));

    let off = app_with(Settings { liveness: Choice::Off, ..Settings::default() }.api_config().unwrap()).await;
    off.send(off.client.post(off.url("/liveness/challenge"))).await.assert_problem(422, "invalid-challenge");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bursts_with_frame_steps_pass_and_a_stranger_in_a_burst_does_not() {
    let app = app(Choice::Enforce).await;
    let c = challenge(&app).await;
    assert!(c["max_frames_per_step"].as_u64().unwrap() >= 5, "{c}");
    let turns = turns_of(&c);
    let (frames, steps) = live_bursts(&turns);
    let r = verify_bursts(&app, c["challenge"].as_str().unwrap(), &frames, Some(&steps)).await;
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let body = r.json();
    let verdict = &body["liveness"]["challenge"];
    assert_eq!((verdict["passed"].as_bool(), body["match"].as_bool()), (Some(true), Some(true)), "{body}");
    assert!(verdict["steps"].as_array().unwrap().iter().all(|s| s["frames"] == 2), "{body}");
    assert_eq!(body["liveness"]["frames"], frames.len() + 1, "{body}");

    // Another person's turned photo in the last turned burst: refused, whatever its pose.
    let c = challenge(&app).await;
    let turns = turns_of(&c);
    let (mut frames, steps) = live_bursts(&turns);
    let last_turn = turns.iter().rposition(|t| t != "front").unwrap();
    let stranger = if turns[last_turn] == "left" { "05-4m.jpg" } else { "05-3m.jpg" };
    frames[2 * last_turn + 1] = imm(stranger);
    let r = verify_bursts(&app, c["challenge"].as_str().unwrap(), &frames, Some(&steps)).await;
    r.assert_problem(422, "presentation-attack");
    assert!(r.json()["reason"].as_str().unwrap().contains("another person"), "{}", String::from_utf8_lossy(&r.body));

    // Ill-formed frame_steps: each malformed, and each uses its challenge up.
    let report = app_with(Settings { liveness: Choice::Report, ..Settings::default() }.api_config().unwrap()).await;
    for (bad, why) in [("1,0", "must not decrease"), ("0,9", "names step 9"), ("0", "names 1 frames"), ("0,x", "comma-separated")] {
        let c = challenge(&report).await;
        let frames = vec![imm("15-5f.jpg"); bad.split(',').count().max(2)];
        let r = verify_bursts(&report, c["challenge"].as_str().unwrap(), &frames, Some(bad)).await;
        r.assert_problem(400, "malformed-request");
        assert!(r.json()["detail"].as_str().unwrap().contains(why), "{bad}: {}", String::from_utf8_lossy(&r.body));
    }
    let c = challenge(&report).await;
    let n = turns_of(&c).len();
    let steps: Vec<String> = (0..n).flat_map(|i| std::iter::repeat_n(i.to_string(), if i == 0 { 6 } else { 1 })).collect();
    let frames = vec![imm("15-5f.jpg"); steps.len()];
    let r = verify_bursts(&report, c["challenge"].as_str().unwrap(), &frames, Some(&steps.join(","))).await;
    r.assert_problem(400, "malformed-request");
    assert!(r.json()["detail"].as_str().unwrap().contains("at most 5 a step"), "{}", String::from_utf8_lossy(&r.body));
    // frame_steps without a challenge has no steps to name: it is not read, and the verification
    // is a plain one.
    let form =
        Form::new().text("subject", SUBJECT).part("image", Part::bytes(imm("15-2f.jpg")).file_name("p.jpg")).text("frame_steps", "0");
    let r = report.send(report.client.post(report.url("/verify")).multipart(form)).await;
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert!(r.json()["liveness"].get("challenge").is_none(), "{}", String::from_utf8_lossy(&r.body));
}

/// The server follows the person's face from the probe through the frames: person 15 at half size
/// on the left of each frame, and in the turned steps person 05 beside them, larger and turned
/// the same way. Judged by the largest face, those steps would be person 05's (another person);
/// followed, the capture is person 15's and passes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_server_follows_the_persons_face_past_a_larger_one_beside_it() {
    let app = app(Choice::Enforce).await;
    let c = challenge(&app).await;
    let turns = turns_of(&c);
    let jpeg = |frame: image::RgbImage| encode(&image::DynamicImage::ImageRgb8(frame), image::ImageFormat::Jpeg);
    let mut fronts = 0;
    let frames: Vec<Vec<u8>> = turns
        .iter()
        .map(|turn| match turn.as_str() {
            "front" => {
                fronts += 1;
                jpeg(two_faces(if fronts % 2 == 1 { "15-5f.jpg" } else { "15-1f.jpg" }, None))
            }
            "left" => jpeg(two_faces("15-4f.jpg", Some("05-4m.jpg"))),
            _ => jpeg(two_faces("15-3f.jpg", Some("05-3m.jpg"))),
        })
        .collect();
    let mut form = Form::new()
        .text("subject", SUBJECT)
        .part("image", Part::bytes(jpeg(two_faces("15-2f.jpg", None))).file_name("probe.jpg"))
        .text("challenge", c["challenge"].as_str().unwrap().to_string());
    for (i, frame) in frames.iter().enumerate() {
        form = form.part("frame", Part::bytes(frame.clone()).file_name(format!("frame{i}.jpg")));
    }
    let r = app.send(app.client.post(app.url("/verify")).multipart(form)).await;
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let body = r.json();
    assert_eq!((body["liveness"]["challenge"]["passed"].as_bool(), body["match"].as_bool()), (Some(true), Some(true)), "{body}");
}

/// The audit events of this binary's log whose request id starts with `prefix`, by request id.
fn audit_events(prefix: &str) -> std::collections::BTreeMap<String, Value> {
    let text = String::from_utf8(crate::hostile::captured_log().0.lock().unwrap().clone()).unwrap();
    text.lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter(|v| v["target"] == "facegate::audit")
        .map(|v| v["fields"].clone())
        .filter_map(|f| Some((f["request_id"].as_str()?.to_string(), f.clone())))
        .filter(|(id, _)| id.starts_with(prefix))
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_required_challenge_refuses_a_plain_verify_and_the_audit_log_follows_each_challenge() {
    crate::hostile::captured_log();
    assert!(
        Settings { liveness: Choice::Report, require_challenge: true, ..Settings::default() }.api_config().is_err(),
        "only enforce can require a challenge: under report its verdict refuses nothing"
    );
    let app = app_with(Settings { liveness: Choice::Enforce, require_challenge: true, ..Settings::default() }.api_config().unwrap()).await;
    let with_id = |form: Form, id: &str| app.client.post(app.url("/verify")).header("x-request-id", id).multipart(form);

    // A verification without a challenge, even of the person's own photo with frames.
    let plain = Form::new()
        .text("subject", SUBJECT)
        .part("image", Part::bytes(imm("15-2f.jpg")).file_name("probe.jpg"))
        .part("frame", Part::bytes(imm("15-1f.jpg")).file_name("frame.jpg"));
    let r = app.send(with_id(plain, "challenge-audit-plain")).await;
    r.assert_problem(422, "invalid-challenge");
    assert!(r.json()["detail"].as_str().unwrap().contains("requires a head-turn challenge"), "{}", String::from_utf8_lossy(&r.body));

    // A challenge answered by the person's turns, and one answered by a photo held still.
    let mut issued = Vec::new();
    for (answer, issue_id) in [("live", "challenge-audit-issue-live"), ("still", "challenge-audit-issue-still")] {
        let r = app.send(app.client.post(app.url("/liveness/challenge")).header("x-request-id", issue_id)).await;
        assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
        let c = r.json();
        let (id, turns) = (c["challenge"].as_str().unwrap().to_string(), turns_of(&c));
        let frames = if answer == "live" { live_frames(&turns) } else { vec![imm("15-2f.jpg"); turns.len()] };
        let mut form = Form::new()
            .text("subject", SUBJECT)
            .part("image", Part::bytes(imm("15-2f.jpg")).file_name("probe.jpg"))
            .text("challenge", id.clone());
        for frame in frames {
            form = form.part("frame", Part::bytes(frame).file_name("frame.jpg"));
        }
        let r = app.send(with_id(form, &format!("challenge-audit-verify-{answer}"))).await;
        match answer {
            "live" => assert_eq!((r.status, r.json()["liveness"]["challenge"]["passed"].as_bool()), (200, Some(true))),
            _ => r.assert_problem(422, "presentation-attack"),
        }
        issued.push(id);
    }

    let events = audit_events("challenge-audit-");
    assert_eq!(events.len(), 5, "{events:?}");
    let plain = &events["challenge-audit-plain"];
    assert_eq!((plain["op"].as_str(), plain["outcome"].as_str()), (Some("verify"), Some("invalid-challenge")), "{plain}");
    assert!(plain["challenge"].is_null(), "{plain}");
    for (answer, id) in ["live", "still"].iter().zip(&issued) {
        let issue = &events[&format!("challenge-audit-issue-{answer}")];
        assert_eq!(
            (issue["op"].as_str(), issue["outcome"].as_str(), issue["challenge"].as_str()),
            (Some("challenge"), Some("ok"), Some(id.as_str()))
        );
        let verify = &events[&format!("challenge-audit-verify-{answer}")];
        assert_eq!((verify["op"].as_str(), verify["challenge"].as_str()), (Some("verify"), Some(id.as_str())), "{verify}");
        assert_eq!(verify["challenge_passed"].as_bool(), Some(*answer == "live"), "{verify}");
        match *answer {
            "live" => assert!(verify["challenge_reason"].is_null() && verify["decision"] == "match", "{verify}"),
            _ => assert!(
                verify["challenge_reason"].as_str().unwrap().contains("yaw") && verify["outcome"] == "presentation-attack",
                "{verify}"
            ),
        }
    }
}
