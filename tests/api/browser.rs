//! The web console in a real browser: headless Chromium (Debian's `chromium` and
//! `chromium-driver`) driven over WebDriver (fantoccini) against the real app and pipeline.
//!
//! Scenario: enrol two photos of one IMM person through the page, verify a third (match and the
//! probe's liveness shown), verify another person (no match shown), identify, open the avatar view
//! (the WebGL canvas renders, no console errors), inspect and delete the subject; the verify view
//! again at phone width. Screenshots of each view go to `target/tmp/console/`, or to the folder named by
//! `FACEGATE_CONSOLE_SCREENSHOTS` (the README's images: `FACEGATE_CONSOLE_SCREENSHOTS=docs/img/console
//! cargo test --test api browser::`).
//!
//! The camera view ("Verify with the camera", the head-turn challenge) runs on Chromium's fake camera
//! playing a Y4M clip of IMM photos the test writes to a temporary folder: a person looking ahead
//! and turning to each side passes the challenge; a still photo fails it with the server's reason;
//! with another person's larger face beside them, turned before each of their turns, the page
//! follows the person's face and still passes (taking the larger face's frames, it failed the
//! same-person check). The person is IMM 05 (held out of training). The page sends each step's
//! burst of frames with `frame_steps`; a clip whose turns never reach the bursts' band (20°–45°)
//! has its in-range frames sent when a step's wait runs out.
//!
//! Without Chromium the tests print why and pass, except under CI (`CI=true`), where they fail.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use fantoccini::elements::Element;
use fantoccini::wd::WebDriverCompatibleCommand;
use fantoccini::{Client, ClientBuilder, Locator};
use serde_json::{Value, json};

use crate::support::{TestApp, two_faces};

const CHROMIUM: [&str; 2] = ["/usr/lib/chromium/chromium", "/usr/bin/chromium"];
const CHROMEDRIVER: [&str; 2] = ["/usr/bin/chromedriver", "/usr/lib/chromium/chromedriver"];
/// The longest wait for one step of the page (a pipeline call in the dev profile takes < 1 s).
const STEP: Duration = Duration::from_secs(30);
/// The longest wait for a whole head-turn challenge: the probe and up to 4 steps of at most 20 s
/// each (the page's own timeout), a look at the camera taking an `/analyze` call, then `/verify`.
const CHALLENGE: Duration = Duration::from_secs(240);

fn first_existing(candidates: &[&str]) -> Option<PathBuf> {
    candidates.iter().map(PathBuf::from).find(|p| p.is_file())
}

/// Chromium and chromedriver; None (the test prints why and passes) where they are not installed,
/// except under CI, where the test fails.
fn browser_binaries() -> Option<(PathBuf, PathBuf)> {
    let ci = std::env::var("CI").is_ok_and(|v| v == "true");
    let (Some(chromium), Some(chromedriver)) = (first_existing(&CHROMIUM), first_existing(&CHROMEDRIVER)) else {
        let reason = "Chromium or chromedriver is not installed (apt-get install chromium chromium-driver)";
        assert!(!ci, "{reason}: the browser test cannot be skipped in CI");
        println!("browser test skipped: {reason}");
        return None;
    };
    Some((chromium, chromedriver))
}

/// The folder for screenshots: `FACEGATE_CONSOLE_SCREENSHOTS`, else `target/tmp/console/`.
fn screenshot_folder() -> PathBuf {
    let shots = std::env::var_os("FACEGATE_CONSOLE_SCREENSHOTS")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("console"));
    std::fs::create_dir_all(&shots).unwrap();
    shots
}

/// A WebDriver session with headless Chromium (its profile in `profile`), with `extra` flags.
async fn session(driver: &Driver, chromium: &Path, profile: &Path, extra: &[String]) -> Client {
    let _ = std::fs::remove_dir_all(profile);
    let mut args: Vec<String> = [
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--no-first-run",
        "--no-default-browser-check",
        "--disable-extensions",
        // WebGL on the CPU (SwiftShader): there is no GPU here.
        "--enable-unsafe-swiftshader",
        "--use-angle=swiftshader",
        "--window-size=1280,1100",
        "--hide-scrollbars",
    ]
    .map(String::from)
    .to_vec();
    args.push(format!("--user-data-dir={}", profile.display()));
    args.extend_from_slice(extra);
    let capabilities = json!({
        "browserName": "chrome",
        "goog:chromeOptions": {"binary": chromium, "args": args},
        "goog:loggingPrefs": {"browser": "ALL"},
    });
    let Value::Object(capabilities) = capabilities else { unreachable!() };
    ClientBuilder::new(hyper_util::client::legacy::connect::HttpConnector::new())
        .capabilities(capabilities)
        .connect(&driver.url)
        .await
        .expect("a WebDriver session with headless Chromium")
}

/// chromedriver on a free port, killed when dropped.
struct Driver {
    child: Child,
    url: String,
}

impl Driver {
    fn start(binary: &Path) -> Driver {
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let child = Command::new(binary)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {}: {e}", binary.display()));
        let deadline = Instant::now() + Duration::from_secs(20);
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(Instant::now() < deadline, "chromedriver did not listen on port {port}");
            std::thread::sleep(Duration::from_millis(50));
        }
        Driver { child, url: format!("http://127.0.0.1:{port}") }
    }
}

impl Drop for Driver {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// chromedriver's browser log (console messages, failed loads, CSP refusals).
#[derive(Debug)]
struct BrowserLog;

impl WebDriverCompatibleCommand for BrowserLog {
    fn endpoint(&self, base: &url::Url, session: Option<&str>) -> Result<url::Url, url::ParseError> {
        base.join(&format!("session/{}/se/log", session.unwrap_or_default()))
    }

    fn method_and_body(&self, _url: &url::Url) -> (http::Method, Option<String>) {
        (http::Method::POST, Some(json!({"type": "browser"}).to_string()))
    }
}

struct Page {
    client: Client,
    shots: PathBuf,
}

impl Page {
    async fn find(&self, css: &str) -> Element {
        self.client.wait().at_most(STEP).for_element(Locator::Css(css)).await.unwrap_or_else(|e| panic!("no {css} on the page: {e}"))
    }

    /// Wait until `script` (a JavaScript expression) is truthy.
    async fn until(&self, what: &str, script: &str) {
        self.until_within(what, script, STEP).await
    }

    /// [`Page::until`] with its own longest wait.
    async fn until_within(&self, what: &str, script: &str, wait: Duration) {
        let deadline = Instant::now() + wait;
        loop {
            let value = self.client.execute(&format!("return {script};"), vec![]).await.unwrap();
            if value.as_bool() == Some(true) || value.as_str().is_some_and(|s| !s.is_empty()) {
                return;
            }
            if Instant::now() > deadline {
                let errors = self.client.execute("return document.querySelector('.problem')?.textContent || '';", vec![]).await;
                panic!("timed out waiting for {what} ({script}); problem shown: {errors:?}");
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    async fn text(&self, css: &str) -> String {
        self.find(css).await.text().await.unwrap()
    }

    async fn click(&self, css: &str) {
        self.find(css).await.click().await.unwrap_or_else(|e| panic!("cannot click {css}: {e}"));
    }

    async fn type_into(&self, css: &str, text: &str) {
        let input = self.find(css).await;
        input.clear().await.unwrap();
        input.send_keys(text).await.unwrap();
    }

    /// Choose a photo in a picker's file input (what a click on "Choose a photo" leads to).
    async fn choose(&self, picker: &str, photo: &Path) {
        self.find(&format!("#{picker}-file")).await.send_keys(photo.to_str().unwrap()).await.unwrap();
    }

    async fn view(&self, name: &str) {
        self.click(&format!("nav a[data-view=\"{name}\"]")).await;
        self.until(&format!("the {name} view"), &format!("!document.querySelector('#view-{name}').hidden")).await;
    }

    async fn screenshot(&self, name: &str) {
        let png = self.client.screenshot().await.unwrap();
        std::fs::write(self.shots.join(name), png).unwrap();
    }

    /// Errors the page collected and the browser logged at level SEVERE.
    async fn errors(&self) -> Vec<String> {
        let page: Vec<String> =
            serde_json::from_value(self.client.execute("return window.facegateErrors;", vec![]).await.unwrap()).unwrap();
        let log = self.client.issue_cmd(BrowserLog).await.unwrap();
        let severe = log.as_array().into_iter().flatten().filter(|e| e["level"] == "SEVERE").map(|e| e["message"].to_string());
        page.into_iter().chain(severe).collect()
    }
}

fn imm_path(name: &str) -> PathBuf {
    let path = facegate_paths::shared_dir().join("data/imm").join(name);
    assert!(path.is_file(), "{} is missing", path.display());
    path.canonicalize().unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_console_enrolls_verifies_shows_the_avatar_and_deletes_in_chromium() {
    let Some((chromium, chromedriver)) = browser_binaries() else { return };
    let shots = screenshot_folder();

    let app = TestApp::start(crate::pipeline::pipeline(), facegate::config::Settings::default().api_config().unwrap()).await;
    let driver = Driver::start(&chromedriver);
    let profile = std::env::temp_dir().join(format!("facegate-chromium-{}", std::process::id()));
    let client = session(&driver, &chromium, &profile, &[]).await;
    let page = Page { client, shots: shots.clone() };

    page.client.goto(&app.url("/#enrol")).await.unwrap();
    page.until("the page script", "document.body.dataset.ready === 'true'").await;
    page.until("the health line", "document.querySelector('#health').textContent.includes('model emb-')").await;

    // Enrol two photos of IMM person 02 (held out of training).
    page.type_into("#enrol-subject", "imm-02").await;
    page.choose("enrol-picker", &imm_path("02-1m.jpg")).await;
    page.choose("enrol-picker", &imm_path("02-2m.jpg")).await;
    page.until("two thumbnails", "document.querySelectorAll('#enrol-picker .thumbs img').length === 2").await;
    page.click("#enrol-form button[type=submit]").await;
    page.until("the enrolment", "document.querySelector('#enrol-outcome')?.textContent").await;
    assert!(page.text("#enrol-outcome").await.contains("2 photo(s) added"));
    page.until("two overlays", "document.querySelectorAll('#enrol-result canvas.overlay').length === 2").await;
    page.screenshot("enrol.png").await;
    assert_eq!(app.store.counts().await.unwrap(), (1, 2));

    // Verify a third photo of the same person: a match, with the 58 points drawn.
    page.view("verify").await;
    page.type_into("#verify-subject", "imm-02").await;
    page.choose("verify-picker", &imm_path("02-4m.jpg")).await;
    page.click("#verify-form button[type=submit]").await;
    page.until("a decision", "document.querySelector('#verify-decision')?.textContent").await;
    let decision = page.text("#verify-decision").await;
    assert!(decision.starts_with("Match"), "{decision}");
    page.until("the overlay", "document.querySelector('#verify-result canvas.overlay')?.dataset.points === '58'").await;
    assert!(page.text("#verify-result").await.contains("threshold"));
    assert!(page.text("#verify-result").await.contains("Quality score"));
    assert!(page.text("#verify-result").await.contains("best against enrolled photo"), "the enrolled photo that made the score");
    // The probe's liveness (reported by default), as the pipeline scores the photo.
    let probe = facegate_core::imaging::decode(&std::fs::read(imm_path("02-4m.jpg")).unwrap(), &Default::default()).unwrap();
    let pipeline = crate::pipeline::pipeline();
    let liveness = pipeline.analyze(&probe).unwrap().liveness.expect("the committed liveness model is loaded");
    let attack = liveness.score < pipeline.liveness.as_ref().expect("loaded").threshold;
    let shown = format!("{} (score {:.3})", if attack { "attack" } else { "live" }, liveness.score);
    let text = page.text("#verify-result").await;
    assert!(text.contains("Liveness") && text.contains(&shown), "{shown:?} not shown: {text}");
    page.screenshot("verify-match.png").await;

    // Another person: no match.
    page.choose("verify-picker", &imm_path("03-1m.jpg")).await;
    page.click("#verify-form button[type=submit]").await;
    page.until("the second decision", "document.querySelector('#verify-decision')?.textContent.startsWith('No match')").await;
    page.screenshot("verify-no-match.png").await;
    let errors = page.errors().await;
    assert!(errors.is_empty(), "console errors: {errors:?}");

    // A refusal shows the problem's reason.
    page.choose("verify-picker", &imm_path("03-1m.jpg")).await;
    page.type_into("#verify-subject", "nobody").await;
    page.click("#verify-form button[type=submit]").await;
    page.until("the refusal", "document.querySelector('#verify-result .problem')?.textContent.includes('unknown-subject')").await;
    // The browser logs the refused request itself, and nothing else.
    let logged = page.errors().await;
    assert!(logged.iter().all(|e| e.contains("/verify?fmr=0.001") && e.contains("404")), "console errors: {logged:?}");

    // An enrolment photo below the quality policy: the refusal lists the broken limits. The
    // darkened copy is written to the test's temporary folder, never into the repository.
    let dark = std::env::temp_dir().join(format!("facegate-console-dark-{}.jpg", std::process::id()));
    let mut img = image::open(imm_path("03-1m.jpg")).unwrap().to_rgb8();
    img.pixels_mut().for_each(|p| p.0.iter_mut().for_each(|v| *v /= 8));
    img.save(&dark).unwrap();
    page.view("enrol").await;
    page.type_into("#enrol-subject", "imm-03").await;
    page.choose("enrol-picker", &dark).await;
    page.click("#enrol-form button[type=submit]").await;
    page.until("the quality refusal", "document.querySelector('#enrol-result .problem')?.textContent.includes('low-quality')").await;
    assert!(page.text("#enrol-result .problem .failures").await.contains("brightness"));
    std::fs::remove_file(&dark).unwrap();
    assert_eq!(app.store.counts().await.unwrap(), (1, 2));
    let logged = page.errors().await;
    assert!(logged.iter().all(|e| e.contains("/enroll") && e.contains("422")), "console errors: {logged:?}");

    // Identify.
    page.view("identify").await;
    page.choose("identify-picker", &imm_path("02-6m.jpg")).await;
    page.click("#identify-form button[type=submit]").await;
    page.until("the candidates", "document.querySelector('#identify-decision')?.textContent").await;
    assert_eq!(page.text("#identify-decision").await, "Match: imm-02");
    page.screenshot("identify.png").await;

    // The avatar: the WebGL canvas draws the textured head; the frontal rendering is a 256 px PNG.
    page.view("avatar").await;
    page.choose("avatar-picker", &imm_path("02-3m.jpg")).await;
    page.click("#avatar-form button[type=submit]").await;
    page.until("the avatar", "document.querySelector('#avatar-outcome')?.textContent").await;
    page.until("a rendered frame", "document.querySelector('#viewer-canvas')?.dataset.rendered === 'true'").await;
    page.until("the frontal rendering", "document.querySelector('#frontal').naturalWidth === 256").await;
    // Pixels of the head (not the background colour) in the WebGL canvas.
    let drawn = page
        .client
        .execute(
            "const c = document.querySelector('#viewer-canvas'); const t = document.createElement('canvas');
             t.width = c.width; t.height = c.height; const g = t.getContext('2d'); g.drawImage(c, 0, 0);
             const d = g.getImageData(0, 0, t.width, t.height).data; let n = 0;
             for (let i = 0; i < d.length; i += 4) { if (Math.abs(d[i] - 0x20) + Math.abs(d[i+1] - 0x24) + Math.abs(d[i+2] - 0x2a) > 30) n++; }
             return n / (t.width * t.height);",
            vec![],
        )
        .await
        .unwrap()
        .as_f64()
        .unwrap();
    assert!(drawn > 0.05, "the head covers {:.1}% of the viewer", 100.0 * drawn);
    // Rotate with the keyboard.
    page.find("#viewer").await.send_keys("\u{E012}\u{E012}").await.unwrap();
    page.screenshot("avatar.png").await;
    let errors = page.errors().await;
    assert!(errors.is_empty(), "console errors: {errors:?}");

    // Subjects: inspect, then delete with confirmation.
    page.view("subjects").await;
    page.find("#subjects-table tr[data-subject=\"imm-02\"]").await;
    page.click("button[aria-label=\"Inspect imm-02\"]").await;
    page.until("the detail", "document.querySelector('#subject-detail h3')?.textContent === 'imm-02'").await;
    assert!(page.text("#subject-detail").await.contains("emb-"));
    page.screenshot("subjects.png").await;
    page.click("button[data-subject=\"imm-02\"]").await;
    page.until("the confirmation", "document.querySelector('#delete-dialog').open").await;
    page.screenshot("delete-confirm.png").await;
    page.click("#delete-confirm").await;
    page.until("the deletion", "document.querySelector('#delete-outcome')?.textContent").await;
    page.find("#subjects-empty").await;
    assert_eq!(app.store.counts().await.unwrap(), (0, 0));

    // Phone width: nothing wider than the screen.
    page.client.set_window_size(390, 844).await.unwrap();
    page.view("verify").await;
    let overflow = page.client.execute("return document.documentElement.scrollWidth - window.innerWidth;", vec![]).await.unwrap();
    if overflow.as_i64().unwrap() > 0 {
        let wide = page
            .client
            .execute(
                "return [...document.querySelectorAll('body *')].filter(e => e.getBoundingClientRect().right > window.innerWidth + 1)
                   .slice(0, 5).map(e => e.tagName + '#' + e.id + '.' + e.className + ' ' + Math.round(e.getBoundingClientRect().right));",
                vec![],
            )
            .await
            .unwrap();
        panic!("the page is {overflow} px wider than a phone: {wide}");
    }
    page.screenshot("phone.png").await;
    let errors = page.errors().await;
    assert!(errors.is_empty(), "console errors: {errors:?}");

    page.client.close().await.unwrap();
    drop(driver);
    let _ = std::fs::remove_dir_all(&profile);
    println!("browser test: screenshots in {}", shots.display());
}

/// A Y4M clip (640 × 480, C420, 2 frames a second) of the IMM photos `names`, each held for
/// `hold` frames, for Chromium's fake camera, which plays it in a loop. The planes are BT.601
/// studio-range YCbCr of the photos' RGB, chroma averaged over 2 × 2 pixels.
fn y4m_clip(path: &Path, names: &[&str], hold: usize) {
    let photos: Vec<image::RgbImage> = names.iter().map(|name| image::open(imm_path(name)).unwrap().to_rgb8()).collect();
    y4m_frames(path, &photos, hold, 2);
}

/// A Y4M clip of `frames` (each held for `hold` frames) at `fps` frames a second, 640 × 480.
fn y4m_frames(path: &Path, frames: &[image::RgbImage], hold: usize, fps: u32) {
    const W: u32 = 640;
    const H: u32 = 480;
    let mut clip = format!("YUV4MPEG2 W{W} H{H} F{fps}:1 Ip A1:1 C420\n").into_bytes();
    for frame in frames {
        let mut rgb = frame.clone();
        if rgb.dimensions() != (W, H) {
            rgb = image::imageops::resize(&rgb, W, H, image::imageops::FilterType::Triangle);
        }
        let (mut y, mut u, mut v) = (Vec::new(), Vec::new(), Vec::new());
        for p in rgb.pixels() {
            let [r, g, b] = p.0.map(f32::from);
            y.push((16.0 + (65.738 * r + 129.057 * g + 25.064 * b) / 256.0).round().clamp(0.0, 255.0) as u8);
        }
        for cy in (0..H).step_by(2) {
            for cx in (0..W).step_by(2) {
                let mut sum = [0.0f32; 3];
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let p = rgb.get_pixel(cx + dx, cy + dy).0;
                    sum.iter_mut().zip(p).for_each(|(s, c)| *s += f32::from(c) / 4.0);
                }
                let [r, g, b] = sum;
                u.push((128.0 + (-37.945 * r - 74.494 * g + 112.439 * b) / 256.0).round().clamp(0.0, 255.0) as u8);
                v.push((128.0 + (112.439 * r - 94.154 * g - 18.285 * b) / 256.0).round().clamp(0.0, 255.0) as u8);
            }
        }
        for _ in 0..hold {
            clip.extend_from_slice(b"FRAME\n");
            clip.extend_from_slice(&y);
            clip.extend_from_slice(&u);
            clip.extend_from_slice(&v);
        }
    }
    std::fs::write(path, clip).unwrap();
}

/// The camera view on Chromium's fake camera playing `clip`: starts the challenge for `subject`
/// and waits for the outcome; returns the page (its session still open).
async fn camera_challenge(app: &TestApp, driver: &Driver, chromium: &Path, clip: &Path, name: &str, subject: &str) -> Page {
    let profile = std::env::temp_dir().join(format!("facegate-chromium-{}-{name}", std::process::id()));
    let camera = [
        "--use-fake-ui-for-media-stream".to_string(),
        "--use-fake-device-for-media-stream".to_string(),
        format!("--use-file-for-fake-video-capture={}", clip.display()),
    ];
    let client = session(driver, chromium, &profile, &camera).await;
    let page = Page { client, shots: screenshot_folder() };
    page.client.goto(&app.url("/#camera")).await.unwrap();
    page.until("the page script", "document.body.dataset.ready === 'true'").await;
    page.until("the camera view", "!document.querySelector('#view-camera').hidden").await;
    page.type_into("#camera-subject", subject).await;
    page.click("#camera-start").await;
    page.until("the challenge's steps", "document.querySelector('#camera-steps').dataset.steps").await;
    page.until("the camera preview", "document.querySelector('#camera-video').videoWidth === 640").await;
    page.screenshot(&format!("{name}-capture.png")).await;
    page.until_within(
        "the outcome of the challenge",
        "document.querySelector('#camera-decision')?.textContent || document.querySelector('#camera-result .problem')?.textContent",
        CHALLENGE,
    )
    .await;
    page.screenshot(&format!("{name}.png")).await;
    page
}

/// Errors the page collected, except the browser's own log of an `/analyze` that found no face
/// in a camera frame (the page then looks at the next frame).
async fn camera_errors(page: &Page) -> Vec<String> {
    page.errors().await.into_iter().filter(|e| !(e.contains("/analyze") && e.contains("422"))).collect()
}

async fn script_i64(page: &Page, script: &str) -> i64 {
    let value = page.client.execute(&format!("return {script};"), vec![]).await.unwrap();
    value.as_i64().unwrap_or_else(|| panic!("{script} is {value}"))
}

/// The camera tests' start: the app with IMM person 05 enrolled (photos 1 and 2), a scratch
/// folder `facegate-<name>-<pid>` for the clips, and a chromedriver.
async fn camera_setup(chromedriver: &Path, name: &str) -> (TestApp, PathBuf, Driver) {
    let app = TestApp::start(crate::pipeline::pipeline(), facegate::config::Settings::default().api_config().unwrap()).await;
    let enrolled = app.post_form("/enroll", Some("imm-05"), &[crate::support::imm("05-1m.jpg"), crate::support::imm("05-2m.jpg")]).await;
    assert_eq!(enrolled.status, 201, "{}", String::from_utf8_lossy(&enrolled.body));
    let clips = std::env::temp_dir().join(format!("facegate-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&clips).unwrap();
    (app, clips, Driver::start(chromedriver))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_camera_view_passes_a_head_turn_challenge_and_fails_a_still_photo_in_chromium() {
    let Some((chromium, chromedriver)) = browser_binaries() else { return };
    let (app, clips, driver) = camera_setup(&chromedriver, "camera").await;

    // IMM person 05 looking ahead, turned to their left (view 4), ahead, turned to their right
    // (view 3): every step of any challenge finds its pose within one loop of the clip.
    let turns = clips.join("turns.y4m");
    y4m_clip(&turns, &["05-5m.jpg", "05-4m.jpg", "05-6m.jpg", "05-3m.jpg"], 3);
    let page = camera_challenge(&app, &driver, &chromium, &turns, "camera-challenge", "imm-05").await;
    let decision = page.text("#camera-result").await;
    assert!(page.text("#camera-decision").await.starts_with("Match: imm-05"), "{decision}");
    assert_eq!(page.text("#camera-challenge").await, "Challenge passed", "{decision}");
    let steps = script_i64(&page, "Number(document.querySelector('#camera-steps').dataset.steps)").await;
    assert!((3..=4).contains(&steps), "{steps} steps");
    // The server's outcome: one row per step, every frame in its range.
    assert_eq!(script_i64(&page, "document.querySelectorAll('#camera-challenge-steps tr[data-ok]').length").await, steps);
    assert_eq!(script_i64(&page, "document.querySelectorAll('#camera-challenge-steps tr[data-ok=\"true\"]').length").await, steps);
    for turn in ["left", "right"] {
        let rows = format!(
            "[...document.querySelectorAll('#camera-challenge-steps tr[data-ok]')].filter(r => r.cells[1].textContent === '{turn}').length"
        );
        assert!(script_i64(&page, &rows).await >= 1, "no {turn} step: {decision}");
    }
    page.until("the probe's overlay", "document.querySelector('#camera-result canvas.overlay')?.dataset.points === '58'").await;
    let errors = camera_errors(&page).await;
    assert!(errors.is_empty(), "console errors: {errors:?}");
    page.client.close().await.unwrap();

    // One still photo looking ahead: the turns never come, each turned step's frame is taken
    // when its time is up, and the server fails the challenge, saying why.
    let still = clips.join("still.y4m");
    y4m_clip(&still, &["05-5m.jpg"], 1);
    let page = camera_challenge(&app, &driver, &chromium, &still, "camera-challenge-failed", "imm-05").await;
    let outcome = page.text("#camera-result").await;
    let challenge = page.text("#camera-challenge").await;
    let reason = challenge.strip_prefix("Challenge failed: ").unwrap_or_else(|| panic!("{outcome}"));
    assert!(!reason.is_empty() && reason != "no reason given", "{outcome}");
    assert!(script_i64(&page, "document.querySelectorAll('#camera-challenge-steps tr[data-ok=\"false\"]').length").await >= 2, "{outcome}");
    assert!(script_i64(&page, "document.querySelectorAll('#camera-steps li[data-state=\"timeout\"]').length").await >= 2, "{outcome}");
    // A failed challenge is an attack, as the liveness table says.
    assert!(outcome.contains("Liveness") && outcome.contains("attack ("), "{outcome}");
    let errors = camera_errors(&page).await;
    assert!(errors.is_empty(), "console errors: {errors:?}");
    page.client.close().await.unwrap();

    drop(driver);
    let _ = std::fs::remove_dir_all(&clips);
    for name in ["camera-challenge", "camera-challenge-failed"] {
        let _ = std::fs::remove_dir_all(std::env::temp_dir().join(format!("facegate-chromium-{}-{name}", std::process::id())));
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_camera_view_takes_no_frame_whose_larger_face_is_someone_elses_in_chromium() {
    let Some((chromium, chromedriver)) = browser_binaries() else { return };
    let (app, clips, driver) = camera_setup(&chromedriver, "camera-beside").await;

    // IMM person 05 on the left, looking ahead, turning left, ahead, turning right; before each
    // of their turns, IMM person 01 beside them, larger, turned that way already. A page that
    // took person 01's turned frames for person 05's would send frames where person 05 is not
    // turned (when the page judged by the largest face only, it failed the same-person check);
    // the page follows person 05's face from the probe on and waits for their own turns.
    let frames = [
        two_faces("05-5m.jpg", None),
        two_faces("05-5m.jpg", Some("01-4m.jpg")),
        two_faces("05-4m.jpg", None),
        two_faces("05-6m.jpg", None),
        two_faces("05-6m.jpg", Some("01-3m.jpg")),
        two_faces("05-3m.jpg", None),
    ];
    let clip = clips.join("beside.y4m");
    y4m_frames(&clip, &frames, 4, 2);
    let page = camera_challenge(&app, &driver, &chromium, &clip, "camera-challenge-beside", "imm-05").await;
    let decision = page.text("#camera-result").await;
    assert!(page.text("#camera-decision").await.starts_with("Match: imm-05"), "{decision}");
    assert_eq!(page.text("#camera-challenge").await, "Challenge passed", "{decision}");
    let errors = camera_errors(&page).await;
    assert!(errors.is_empty(), "console errors: {errors:?}");
    page.client.close().await.unwrap();
    drop(driver);
    let _ = std::fs::remove_dir_all(&clips);
    let _ = std::fs::remove_dir_all(std::env::temp_dir().join(format!("facegate-chromium-{}-camera-challenge-beside", std::process::id())));
}

/// Frames per direction of a video clip played to the fake camera, and its rate: each direction
/// lasts 8 s, so every pose of the clip (turned one way, then mirrored the other) comes round
/// within any 16 s, inside the page's 20 s wait for a step.
const VIDEO_FRAMES: usize = 80;
const VIDEO_FPS: u32 = 10;

/// A measurement, not a check (`cargo test --test api -- --ignored --nocapture
/// the_camera_view_on_real_video`, about 15 minutes on 2 cores): the camera view under
/// `--liveness enforce`, on Chromium's fake camera playing each clip of `data/video` as a person
/// answering at the camera would be seen: the clip's frames in order (80 evenly spaced, at 10 a
/// second), then the same frames mirrored (the head turning the other way), in a loop. Each clip
/// enrols its two frames nearest to frontal (by `key_point_pose`). Prints one line per clip and
/// the count passed (match and challenge); docs/liveness-challenge.md has the run. The clips are
/// the development material: none is held out from the challenge's limits.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "a measurement of about 15 minutes: docs/liveness-challenge.md"]
async fn the_camera_view_on_real_video() {
    let Some((chromium, chromedriver)) = browser_binaries() else { return };
    let pipeline = crate::pipeline::pipeline();
    let settings = facegate::config::Settings { liveness: facegate::choices::Liveness::Enforce, ..Default::default() };
    let app = TestApp::start(pipeline.clone(), settings.api_config().unwrap()).await;
    let driver = Driver::start(&chromedriver);
    let scratch = std::env::temp_dir().join(format!("facegate-camera-video-{}", std::process::id()));
    std::fs::create_dir_all(&scratch).unwrap();
    let video = facegate_paths::shared_dir().join("data/video");
    let mut clips: Vec<PathBuf> = std::fs::read_dir(&video).unwrap().map(|e| e.unwrap().path()).filter(|p| p.is_dir()).collect();
    clips.sort();
    let (mut passed, mut lines) = (0, Vec::new());
    for dir in &clips {
        let name = dir.file_name().unwrap().to_string_lossy().into_owned();
        let mut files: Vec<PathBuf> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
        files.sort();
        let step = files.len().div_ceil(VIDEO_FRAMES).max(1);
        let frames: Vec<image::RgbImage> = files.iter().step_by(step).map(|f| image::open(f).unwrap().to_rgb8()).collect();
        let mirrored: Vec<image::RgbImage> = frames.iter().map(image::imageops::flip_horizontal).collect();
        // The enrolment: the two frames (either way round) whose key-point yaw is nearest to 0.
        let mut frontal: Vec<(f32, &image::RgbImage)> = frames
            .iter()
            .chain(&mirrored)
            .filter_map(|rgb| {
                let photo = facegate_core::imaging::Photo::from_dynamic(image::DynamicImage::ImageRgb8(rgb.clone()));
                let yaw = pipeline.analyze(&photo).ok()?.key_point_pose?.yaw;
                Some((yaw.abs(), rgb))
            })
            .collect();
        frontal.sort_by(|a, b| a.0.total_cmp(&b.0));
        let photos: Vec<Vec<u8>> = frontal.iter().take(2).map(|(_, rgb)| jpeg(rgb)).collect();
        let enrolled = app.post_form("/enroll", Some(&name), &photos).await;
        if enrolled.status != 201 {
            lines.push(format!("{name}: not enrolled ({})", String::from_utf8_lossy(&enrolled.body)));
            continue;
        }
        let clip = scratch.join(format!("{name}.y4m"));
        let played: Vec<image::RgbImage> = frames.iter().chain(&mirrored).cloned().collect();
        y4m_frames(&clip, &played, 1, VIDEO_FPS);
        let page = camera_challenge(&app, &driver, &chromium, &clip, &format!("camera-video-{name}"), &name).await;
        let text = |css: &str| format!("return document.querySelector('{css}')?.textContent ?? '';");
        let mut read = Vec::new();
        for css in ["#camera-decision", "#camera-challenge", "#camera-result"] {
            let value = page.client.execute(&text(css), vec![]).await.unwrap();
            read.push(value.as_str().unwrap_or_default().to_string());
        }
        let [decision, challenge, outcome] = <[String; 3]>::try_from(read).unwrap();
        let ok = decision.starts_with("Match") && challenge == "Challenge passed";
        passed += usize::from(ok);
        let seen = if ok {
            "passed".to_string()
        } else {
            format!("refused: {decision} {challenge} {}", outcome.lines().take(3).collect::<Vec<_>>().join(" / "))
        };
        lines.push(format!("{name}: {seen}"));
        page.client.close().await.unwrap();
        let _ = std::fs::remove_file(&clip);
        let _ = std::fs::remove_dir_all(std::env::temp_dir().join(format!("facegate-chromium-{}-camera-video-{name}", std::process::id())));
    }
    for line in &lines {
        println!("camera view on video: {line}");
    }
    println!("camera view on video: {passed} of {} clips passed (match and challenge, --liveness enforce)", clips.len());
    assert_eq!(lines.len(), clips.len(), "every clip was tried");
    drop(driver);
    let _ = std::fs::remove_dir_all(&scratch);
}

/// `rgb` as JPEG bytes.
fn jpeg(rgb: &image::RgbImage) -> Vec<u8> {
    let mut bytes = std::io::Cursor::new(Vec::new());
    rgb.write_to(&mut bytes, image::ImageFormat::Jpeg).unwrap();
    bytes.into_inner()
}
