//! Starting the real app (built by the composition root `facegate serve` uses) on a random port
//! with a fresh database, a client that checks every response against `openapi.yaml`, test
//! photos, and a stand-in face engine for the HTTP-layer tests.

use std::io::Cursor;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use facegate::config::Settings;
use facegate::startup::{Application, ApplicationBuilder};
use facegate_core::face::EyeMouthCentres;
use facegate_core::geometry::Rect;
use facegate_core::imaging::Photo;
use facegate_core::template::{OperatingPoint, Template};
use facegate_detect::Face;
use facegate_http::ApiConfig;
use facegate_http::server::ServerLimits;
use facegate_morph::AvatarFormat;
use facegate_service::FaceEngine;
use facegate_service::{LivenessPoint, Matcher};
use facegate_store::{KeyRing, Store};
use facegate_vision::landmarks::Landmarks;
use facegate_vision::pipeline::{FaceAnalysis, FaceChoice, FaceReading, FollowedFace, PhotoReading, PipelineError, StageTimings};
use facegate_vision::quality::Quality;
use reqwest::multipart::{Form, Part};
use serde_json::Value;

use crate::openapi::spec;

/// A running app: its base URL, its database, and a client.
pub struct TestApp {
    pub base: String,
    pub client: reqwest::Client,
    pub store: Store,
    /// The database's URL (`sqlite://…` or `postgres://…`).
    pub database_url: String,
    dir: PathBuf,
    server: tokio::task::JoinHandle<()>,
}

/// Which database a [`TestApp`] runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Db {
    /// A SQLite file in the app's temporary folder.
    Sqlite,
    /// A fresh database on the test PostgreSQL server ([`crate::postgres`]).
    Postgres,
}

/// One test body, `async fn name(db: Db)`, run on each backend: `name::sqlite` and
/// `name::postgres` (the latter skipped with a printed reason where no server can be had).
#[macro_export]
macro_rules! on_both_backends {
    ($name:ident) => {
        mod $name {
            #[tokio::test]
            async fn sqlite() {
                super::$name($crate::support::Db::Sqlite).await
            }

            #[tokio::test]
            async fn postgres() {
                if !$crate::postgres::available() {
                    $crate::postgres::skip(concat!(module_path!(), "::postgres"));
                    return;
                }
                super::$name($crate::support::Db::Postgres).await
            }
        }
    };
}

/// A response, already checked against `openapi.yaml`.
#[derive(Debug)]
pub struct Reply {
    pub status: u16,
    pub headers: reqwest::header::HeaderMap,
    pub body: Vec<u8>,
}

impl Reply {
    pub fn json(&self) -> Value {
        serde_json::from_slice(&self.body).unwrap_or_else(|e| panic!("not JSON ({e}): {}", String::from_utf8_lossy(&self.body)))
    }

    /// The problem type's last segment, after checking the media type.
    pub fn problem(&self) -> String {
        assert_eq!(self.headers["content-type"], "application/problem+json", "{} {}", self.status, String::from_utf8_lossy(&self.body));
        let t = self.json()["type"].as_str().unwrap().to_string();
        t.strip_prefix(facegate_http::problem::PROBLEM_BASE).unwrap().to_string()
    }

    /// Assert status and problem type together (the message shows the body when they differ).
    pub fn assert_problem(&self, status: u16, slug: &str) {
        assert_eq!((self.status, self.problem()), (status, slug.to_string()), "{}", String::from_utf8_lossy(&self.body));
    }
}

/// The connection loop's limits as `facegate serve` has them by default.
fn default_limits() -> ServerLimits {
    Settings::default().server_limits().unwrap()
}

/// The serve defaults on `database_url`, listening on a free loopback port.
pub fn settings(database_url: &str) -> Settings {
    Settings { bind: "127.0.0.1:0".into(), database: database_url.into(), ..Settings::default() }
}

impl TestApp {
    pub async fn start(engine: Arc<dyn FaceEngine>, config: ApiConfig) -> TestApp {
        Self::start_full(engine, config, default_limits(), None, Db::Sqlite).await
    }

    /// [`TestApp::start`] on the database `db`.
    pub async fn start_on(db: Db, engine: Arc<dyn FaceEngine>, config: ApiConfig) -> TestApp {
        Self::start_full(engine, config, default_limits(), None, db).await
    }

    /// [`TestApp::start`] with the connection loop's limits given.
    pub async fn start_with(engine: Arc<dyn FaceEngine>, config: ApiConfig, limits: ServerLimits) -> TestApp {
        Self::start_full(engine, config, limits, None, Db::Sqlite).await
    }

    /// An app whose store seals templates under `keys`.
    pub async fn start_with_keys(db: Db, engine: Arc<dyn FaceEngine>, config: ApiConfig, keys: Option<KeyRing>) -> TestApp {
        Self::start_full(engine, config, default_limits(), keys, db).await
    }

    async fn start_full(engine: Arc<dyn FaceEngine>, config: ApiConfig, limits: ServerLimits, keys: Option<KeyRing>, db: Db) -> TestApp {
        static N: AtomicUsize = AtomicUsize::new(0);
        let dir = std::env::temp_dir().join(format!("facegate-api-{}-{}", std::process::id(), N.fetch_add(1, Ordering::Relaxed)));
        std::fs::create_dir_all(&dir).unwrap();
        let url = match db {
            Db::Sqlite => format!("sqlite://{}", dir.join("facegate.db").display()),
            Db::Postgres => crate::postgres::fresh_database().expect("the caller checked that PostgreSQL is available"),
        };
        let app = Application::builder(settings(&url)).template_keys(keys);
        Self::serve(app, engine, url, config, limits, dir).await
    }

    /// An app on the database at `database_url` (an existing one, or one behind a proxy).
    pub async fn start_on_database(engine: Arc<dyn FaceEngine>, database_url: String, config: ApiConfig) -> TestApp {
        static N: AtomicUsize = AtomicUsize::new(0);
        let dir = std::env::temp_dir().join(format!("facegate-api-store-{}-{}", std::process::id(), N.fetch_add(1, Ordering::Relaxed)));
        std::fs::create_dir_all(&dir).unwrap();
        let app = Application::builder(settings(&database_url));
        Self::serve(app, engine, database_url, config, default_limits(), dir).await
    }

    /// A second app on this one's database with another engine (a service restarted with another
    /// recognizer); the database folder stays until this app is dropped.
    pub async fn restarted_with(&self, engine: Arc<dyn FaceEngine>, config: ApiConfig) -> TestApp {
        let scratch = self.dir.join(format!("restart-{}", std::process::id()));
        std::fs::create_dir_all(&scratch).unwrap();
        let app = Application::builder(settings(&self.database_url)).store(self.store.clone());
        Self::serve(app, engine, self.database_url.clone(), config, default_limits(), scratch).await
    }

    /// The app `facegate serve` runs (the composition root, `facegate::startup`) with `engine`,
    /// `config` and `limits`, behind the service's own connection loop.
    async fn serve(
        app: ApplicationBuilder,
        engine: Arc<dyn FaceEngine>,
        database_url: String,
        config: ApiConfig,
        limits: ServerLimits,
        dir: PathBuf,
    ) -> TestApp {
        let app = app.engine(engine).api_config(config).server_limits(limits).build().await.unwrap();
        let base = format!("http://{}", app.address());
        let store = app.state().store().clone();
        let server = tokio::spawn(app.run_until_stopped(std::future::pending()));
        TestApp { base, client: reqwest::Client::new(), store, database_url, dir, server }
    }

    /// Send a request and check the response against the document.
    pub async fn send(&self, request: reqwest::RequestBuilder) -> Reply {
        let request = request.build().unwrap();
        let (method, path) = (request.method().to_string(), request.url().path().to_string());
        let response = self.client.execute(request).await.unwrap();
        let status = response.status().as_u16();
        let headers = response.headers().clone();
        let body = response.bytes().await.unwrap().to_vec();
        let content_type = headers.get("content-type").map(|v| v.to_str().unwrap().to_string());
        if spec().template_for(&path).is_some() && status != 405 {
            spec().check_response(&method, &path, status, content_type.as_deref(), &body);
        }
        Reply { status, headers, body }
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    pub async fn get(&self, path: &str) -> Reply {
        self.send(self.client.get(self.url(path))).await
    }

    pub async fn delete(&self, path: &str) -> Reply {
        self.send(self.client.delete(self.url(path))).await
    }

    /// POST multipart: an optional subject and `image` fields.
    pub async fn post_form(&self, path: &str, subject: Option<&str>, images: &[Vec<u8>]) -> Reply {
        let mut form = Form::new();
        if let Some(s) = subject {
            form = form.text("subject", s.to_string());
        }
        for (i, bytes) in images.iter().enumerate() {
            form = form.part("image", Part::bytes(bytes.clone()).file_name(format!("photo{i}.jpg")));
        }
        self.send(self.client.post(self.url(path)).multipart(form)).await
    }

    pub async fn post_json(&self, path: &str, body: &Value) -> Reply {
        self.send(self.client.post(self.url(path)).json(body)).await
    }
}

impl Drop for TestApp {
    fn drop(&mut self) {
        self.server.abort();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

pub fn base64(bytes: &[u8]) -> String {
    use base64::Engine as _;
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

pub fn encode(img: &image::DynamicImage, format: image::ImageFormat) -> Vec<u8> {
    let mut out = Vec::new();
    img.write_to(&mut Cursor::new(&mut out), format).unwrap();
    out
}

/// A textured grey image (no face in it) of the given size.
pub fn pattern(width: u32, height: u32, seed: u32) -> image::DynamicImage {
    image::DynamicImage::ImageLuma8(image::GrayImage::from_fn(width, height, |x, y| {
        image::Luma([((x * (3 + seed) + y * (5 + 2 * seed) + (x * y) % (7 + seed)) % 251) as u8])
    }))
}

pub fn pattern_jpeg(width: u32, height: u32, seed: u32) -> Vec<u8> {
    encode(&pattern(width, height, seed), image::ImageFormat::Jpeg)
}

/// An IMM photo from the shared data (read from its path, never copied).
pub fn imm(name: &str) -> Vec<u8> {
    let path = facegate_paths::shared_dir().join("data/imm").join(name);
    std::fs::read(&path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()))
}

/// A 640 × 480 camera frame of IMM photo `person` at half size on the left and, when `beside` is
/// given, that photo at 0.7 of its size on the right: a second face, larger than the person's.
pub fn two_faces(person: &str, beside: Option<&str>) -> image::RgbImage {
    let photo = |name: &str, scale: f32| {
        let rgb = image::load_from_memory(&imm(name)).unwrap().to_rgb8();
        let (w, h) = ((640.0 * scale) as u32, (480.0 * scale) as u32);
        image::imageops::resize(&rgb, w, h, image::imageops::FilterType::Triangle)
    };
    let mut frame = image::RgbImage::from_pixel(640, 480, image::Rgb([128, 128, 128]));
    image::imageops::replace(&mut frame, &photo(person, 0.5), 0, 120);
    if let Some(other) = beside {
        image::imageops::replace(&mut frame, &photo(other, 0.7), 320, 72);
    }
    frame
}

/// A stand-in for the face pipeline, so the HTTP layer can be tested on its own: a uniform photo
/// has no face, a photo at least twice as wide as high has two, any other one face. Its template
/// is the photo's 8×8 thumbnail, centred and normalised; the score is the best cosine. Its quality
/// components are the real ones of a chip cut at fixed centres (no pose); its unified score is
/// `min(100, 10 · sharpness)`, so a dark or flat photo is refused as the real one would be.
pub struct StandInEngine {
    pub version: String,
    /// Simulated work per photo, for timeout and overload tests.
    pub delay: Duration,
    pub calls: AtomicUsize,
}

impl StandInEngine {
    pub fn new(version: &str) -> Arc<StandInEngine> {
        Arc::new(StandInEngine { version: version.into(), delay: Duration::ZERO, calls: AtomicUsize::new(0) })
    }

    pub fn slow(delay: Duration) -> Arc<StandInEngine> {
        Arc::new(StandInEngine { version: "stand-in".into(), delay, calls: AtomicUsize::new(0) })
    }
}

impl FaceEngine for StandInEngine {
    fn analyze(&self, photo: &Photo) -> Result<FaceAnalysis, PipelineError> {
        self.calls.fetch_add(1, Ordering::SeqCst);
        std::thread::sleep(self.delay);
        let g = &photo.gray;
        let thumb = g.resize(8, 8);
        let mean = thumb.data.iter().sum::<f32>() / 64.0;
        let mut vector: Vec<f32> = thumb.data.iter().map(|v| v - mean).collect();
        let norm = vector.iter().map(|v| v * v).sum::<f32>().sqrt();
        let (min, max) = g.data.iter().fold((f32::MAX, f32::MIN), |(a, b), &v| (a.min(v), b.max(v)));
        if max - min < 1.0 || norm < 1e-3 {
            return Err(PipelineError::NoFace);
        }
        vector.iter_mut().for_each(|v| *v /= norm);
        let (w, h) = (g.width as f32, g.height as f32);
        let faces_found = if w >= 2.0 * h { 2 } else { 1 };
        let centres = EyeMouthCentres { left_eye: [0.35 * w, 0.4 * h], right_eye: [0.65 * w, 0.4 * h], mouth: [0.5 * w, 0.75 * h] };
        let landmarks = Landmarks { points: vec![[0.5 * w, 0.5 * h]; 58], centres };
        let components = facegate_vision::pipeline::quality_components(photo, &landmarks, None, None).1;
        let quality = Quality { score: (10.0 * components.sharpness).min(100.0), components };
        Ok(FaceAnalysis {
            face: Face { rect: Rect::new(0.0, 0.0, w, h), score: 1.0, points: None },
            faces_found,
            landmarks,
            pose: None,
            key_point_pose: None,
            template: Template { model_version: self.version.clone(), vector },
            quality,
            liveness: None,
            liveness_features: None,
            timings: StageTimings::default(),
        })
    }

    /// The stand-in sees one face filling the photo: there is nothing else to follow.
    fn analyze_following(&self, photo: &Photo, _last: &FollowedFace) -> Result<FaceAnalysis, PipelineError> {
        self.analyze(photo)
    }

    fn read_faces(&self, photo: &Photo, choice: FaceChoice) -> Result<PhotoReading, PipelineError> {
        let a = self.analyze(photo)?;
        let wanted = if choice == FaceChoice::All { a.faces_found } else { 1 };
        let reading = FaceReading {
            face: a.face,
            landmarks: a.landmarks,
            pose: None,
            key_point_pose: None,
            fit_residual_px: None,
            visible: None,
            quality: a.quality,
            liveness: None,
            landmarks_ms: 0.0,
            morph_ms: 0.0,
        };
        Ok(PhotoReading { faces_found: a.faces_found, faces: vec![reading; wanted], detect_ms: 0.0 })
    }

    /// The stand-in has no 3D morphable model.
    fn avatar(&self, photo: &Photo, _format: AvatarFormat) -> Result<Vec<u8>, PipelineError> {
        self.analyze(photo)?;
        Err(PipelineError::NoFaceModel)
    }

    fn frontal_png(&self, photo: &Photo) -> Result<Vec<u8>, PipelineError> {
        self.analyze(photo)?;
        Err(PipelineError::NoFaceModel)
    }

    /// The stand-in has no liveness model: its faces carry no liveness.
    fn liveness_model_point(&self) -> Option<LivenessPoint> {
        None
    }
}

impl Matcher for StandInEngine {
    fn model_version(&self) -> &str {
        &self.version
    }

    fn score(&self, probe: &Template, enrolled: &[Template]) -> f32 {
        enrolled.iter().map(|t| t.vector.iter().zip(&probe.vector).map(|(a, b)| a * b).sum::<f32>()).fold(f32::MIN, f32::max)
    }

    /// Like a calibrated model: a stricter threshold for a subject with more templates.
    fn operating_point(&self, fmr: f64, enrolled: usize) -> OperatingPoint {
        let threshold = match (fmr < 5e-3, enrolled > 1) {
            (true, false) => 0.95,
            (true, true) => 0.97,
            (false, false) => 0.9,
            (false, true) => 0.92,
        };
        OperatingPoint { fmr: if fmr < 5e-3 { 1e-3 } else { 1e-2 }, threshold }
    }
}
