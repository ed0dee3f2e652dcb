//! The service's settings and where the project finds its files: the one place that reads the
//! environment, and the one place the defaults are written. The runtime (stages, pipeline,
//! service, store, http) is handed plain values made here.
//!
//! Files (research data and the 3DMM are never part of the repository):
//! - `FACEGATE_SHARED`: the shared data folder (default `../shared` beside the crate).
//! - `FACEGATE_SFM`: the Surrey Face Model folder (default `<shared>/models/sfm`).
//! - `FACEGATE_MODELS`: the project's trained models (default `models` in the working directory,
//!   or the crate's own `models/` when that does not exist).
//!
//! The service: [`Settings`], one flag and one `FACEGATE_*` variable per setting.

use std::path::PathBuf;
use std::time::Duration;

use crate::choices;
use anyhow::Context;
use facegate_core::imaging::DecodeLimits;
use facegate_detect::DetectorKind;
use facegate_http::ApiConfig;
use facegate_http::server::ServerLimits;
use facegate_service::protection::ProtectionKey;
use facegate_service::{ChallengeConfig, LivenessPolicy, ServiceConfig};
use facegate_store::KeyRing;
use facegate_vision::liveness::LivenessModel;
use facegate_vision::pipeline::{Pipeline, PipelineConfig};
use facegate_vision::quality::QualityPolicy;
use facegate_vision::recognize::DEFAULT_FMR;
use facegate_vision::recognize::RecognizerKind;

// Where the files are (`FACEGATE_SHARED`, `FACEGATE_SFM`, `FACEGATE_MODELS` and their defaults) is
// written once, in `facegate-paths`, which the command line and the tests import too.
use facegate_paths::{models_dir, sfm_dir};

/// The pipeline's model folders: `facegate_paths::models_dir` and `sfm_dir`.
pub fn pipeline_config() -> PipelineConfig {
    PipelineConfig {
        models_dir: models_dir(),
        sfm_dir: Some(sfm_dir()),
        recognizer: RecognizerKind::default(),
        detector: Default::default(),
    }
}

const DEFAULT_BIND: &str = "127.0.0.1:8080";
pub(crate) const DEFAULT_DATABASE: &str = "sqlite://facegate.db";
const DEFAULT_QUEUE: usize = 64;
const DEFAULT_MAX_BODY_MB: usize = 16;
const DEFAULT_MAX_PIXELS: u64 = 16_000_000;
const DEFAULT_MAX_DECODE_MB: u64 = 256;
const DEFAULT_MAX_IMAGES: usize = 16;
const DEFAULT_TIMEOUT_SECS: f64 = 30.0;
const DEFAULT_CONSOLE: bool = true;
const DEFAULT_ENROLL_QUEUE: usize = 16;
const DEFAULT_ADMISSION_WAIT_MS: u64 = 1000;
const DEFAULT_MAX_BUFFERED_MB: usize = 128;
/// A quarter of the default body memory: two of the largest bodies at once.
const DEFAULT_MAX_BUFFERED_PER_ADDRESS_MB: usize = 32;
const DEFAULT_BODY_TIMEOUT_SECS: f64 = 15.0;
const DEFAULT_BODY_GRACE_SECS: f64 = 5.0;
const DEFAULT_MIN_BODY_RATE_KIB: u64 = 8;
const DEFAULT_MAX_UPLOADS_PER_ADDRESS: usize = 16;
const DEFAULT_CHALLENGE_LIFETIME_SECS: u64 = 120;
const DEFAULT_CHALLENGE_RATE: f64 = 10.0;
const DEFAULT_MAX_OPEN_CHALLENGES: u64 = 2_000;
const DEFAULT_HEADER_TIMEOUT_SECS: f64 = 10.0;
const DEFAULT_MAX_CONNECTIONS: usize = 1024;
/// A quarter of the default connection cap.
const DEFAULT_MAX_CONNECTIONS_PER_ADDRESS: usize = 256;
const DEFAULT_SHUTDOWN_GRACE_SECS: f64 = 10.0;
/// Shortest API key accepted: a shorter one is guessable and refused at start-up.
pub const MIN_API_KEY_LEN: usize = 16;

/// How the service writes its log.
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LogFormat {
    /// Human-readable lines.
    #[default]
    Text,
    /// One JSON object per line (fields of audit events as JSON fields).
    Json,
}

// The enrolment quality policy (docs/quality.md: what each refuses of IMM and ORL).
const DEFAULT_MIN_QUALITY: f32 = 50.0;
const DEFAULT_MIN_INTER_EYE_PX: f32 = 20.0;
const DEFAULT_MIN_SHARPNESS: f32 = 3.0;
const DEFAULT_MIN_BRIGHTNESS: f32 = 40.0;
const DEFAULT_MAX_BRIGHTNESS: f32 = 220.0;
const DEFAULT_MAX_YAW_DEG: f32 = 45.0;
const DEFAULT_MAX_PITCH_DEG: f32 = 30.0;

/// The service's settings: command-line flags, each also read from its `FACEGATE_*` variable.
#[derive(clap::Args, Debug, Clone, PartialEq)]
pub struct Settings {
    /// Address to listen on.
    #[arg(long, env = "FACEGATE_BIND", default_value = DEFAULT_BIND)]
    pub bind: String,
    /// Database URL: `sqlite://FILE` (created if missing) or `postgres://USER:PASSWORD@HOST/DB`.
    #[arg(long, env = "FACEGATE_DATABASE_URL", default_value = DEFAULT_DATABASE)]
    pub database: String,
    /// A file whose first line is the PostgreSQL password, merged into the `--database` URL at
    /// start-up (which then names the user but no password); never printed.
    #[arg(long, env = "FACEGATE_DATABASE_PASSWORD_FILE")]
    pub database_password_file: Option<PathBuf>,
    /// The project's trained models (default: `models/` in the working directory or the crate's).
    #[arg(long, env = "FACEGATE_MODELS")]
    pub models: Option<PathBuf>,
    /// The Surrey Face Model folder for 3DMM pose correction (missing: 2D alignment only).
    #[arg(long, env = "FACEGATE_SFM")]
    pub sfm: Option<PathBuf>,
    /// Which recognizer makes templates: dlib's and SFace's embeddings fused (`fusion.bin`, the
    /// default), either network alone (`deep.bin`, `sface.bin`), your own ONNX network
    /// (`custom.bin`) or the classical pixels + LBP Direct LDA (`dlda.bin`). Templates of one are
    /// never compared with another's.
    #[arg(long, env = "FACEGATE_RECOGNIZER", value_enum, default_value_t = choices::Recognizer::from(RecognizerKind::default()))]
    pub recognizer: choices::Recognizer,
    /// The face detector: YuNet (a multi-view CNN: frontal to full profile) or the thesis's
    /// Viola–Jones cascades (`haar`, frontal and profile) or SeetaFace (`seeta`).
    #[arg(long, env = "FACEGATE_DETECTOR", value_enum, default_value_t = choices::Detector::from(DetectorKind::default()))]
    pub detector: choices::Detector,
    /// Comma-separated API keys (at least 16 characters each); when neither this nor
    /// `--api-keys-file` is set the API is open to anyone who can reach it. Set but holding no key
    /// (only commas or blanks) stops the start-up; an empty value counts as not set. Keys given as
    /// a flag show in `ps`: prefer the file or the variable.
    #[arg(long, env = "FACEGATE_API_KEYS", value_delimiter = ',', hide_env_values = true)]
    pub api_keys: Vec<String>,
    /// A file of API keys: one per line; blank lines and lines starting with `#` are skipped. A
    /// file with no key in it stops the start-up.
    #[arg(long, env = "FACEGATE_API_KEYS_FILE")]
    pub api_keys_file: Option<PathBuf>,
    /// Photos analysed at once (default: the number of cores).
    #[arg(long, env = "FACEGATE_WORKERS")]
    pub workers: Option<usize>,
    /// Verifications, identifications and inspections that may wait for a worker before the
    /// service answers 503.
    #[arg(long, env = "FACEGATE_QUEUE", default_value_t = DEFAULT_QUEUE)]
    pub queue: usize,
    /// Enrolments that may wait for a worker (a queue of their own) before the service answers 503.
    #[arg(long = "enrol-queue", visible_alias = "enroll-queue", value_name = "ENROL_QUEUE", env = "FACEGATE_ENROL_QUEUE", default_value_t = DEFAULT_ENROLL_QUEUE)]
    pub enroll_queue: usize,
    /// Milliseconds a request waits (in arrival order) before the 503: for room in a full queue
    /// (its body unread), for a place among its address's arriving bodies, and for its place in
    /// the queue once its body has arrived; 0 refuses at once.
    #[arg(long, env = "FACEGATE_ADMISSION_WAIT_MS", default_value_t = DEFAULT_ADMISSION_WAIT_MS)]
    pub admission_wait_ms: u64,
    /// Request bodies held in memory at once, in MiB; a request that would exceed it gets 503.
    #[arg(long, env = "FACEGATE_MAX_BUFFERED_MB", default_value_t = DEFAULT_MAX_BUFFERED_MB)]
    pub max_buffered_mb: usize,
    /// Of --max-buffered-mb, most MiB held by the request bodies of one client address (IPv6: its
    /// /64); a request that would exceed it gets 503. At least --max-body-mb.
    #[arg(long, env = "FACEGATE_MAX_BUFFERED_PER_ADDRESS_MB", default_value_t = DEFAULT_MAX_BUFFERED_PER_ADDRESS_MB)]
    pub max_buffered_per_address_mb: usize,
    /// Largest request body, in MiB.
    #[arg(long, env = "FACEGATE_MAX_BODY_MB", default_value_t = DEFAULT_MAX_BODY_MB)]
    pub max_body_mb: usize,
    /// Largest photo, in pixels (width × height).
    #[arg(long, env = "FACEGATE_MAX_PIXELS", default_value_t = DEFAULT_MAX_PIXELS)]
    pub max_pixels: u64,
    /// Most memory the decoder may allocate per photo, in MiB.
    #[arg(long, env = "FACEGATE_MAX_DECODE_MB", default_value_t = DEFAULT_MAX_DECODE_MB)]
    pub max_decode_mb: u64,
    /// Most photos in one enrolment.
    #[arg(long, env = "FACEGATE_MAX_IMAGES", default_value_t = DEFAULT_MAX_IMAGES)]
    pub max_images: usize,
    /// Request timeout in seconds (answered with 504).
    #[arg(long, env = "FACEGATE_TIMEOUT_SECS", default_value_t = DEFAULT_TIMEOUT_SECS)]
    pub timeout_secs: f64,
    /// Seconds from the start of the request body for all of it to arrive (answered with 408); at
    /// most the request timeout.
    #[arg(long, env = "FACEGATE_BODY_TIMEOUT_SECS", default_value_t = DEFAULT_BODY_TIMEOUT_SECS)]
    pub body_timeout_secs: f64,
    /// Seconds a request body may take before --min-body-rate-kib applies.
    #[arg(long, env = "FACEGATE_BODY_GRACE_SECS", default_value_t = DEFAULT_BODY_GRACE_SECS)]
    pub body_grace_secs: f64,
    /// Least rate of a request body after the grace period, KiB/s over the last grace period's
    /// length (answered with 408 when slower); 0 checks no rate.
    #[arg(long, env = "FACEGATE_MIN_BODY_RATE_KIB", default_value_t = DEFAULT_MIN_BODY_RATE_KIB)]
    pub min_body_rate_kib: u64,
    /// Request bodies awaited (a head sent, its body not begun) or arriving at once from one client
    /// address (IPv6: its /64); more wait up to the admission wait, then get 503.
    #[arg(long, env = "FACEGATE_MAX_UPLOADS_PER_ADDRESS", default_value_t = DEFAULT_MAX_UPLOADS_PER_ADDRESS)]
    pub max_uploads_per_address: usize,
    /// Seconds for a connection to send a complete request head; also the longest a keep-alive
    /// connection stays idle. The connection is closed after it.
    #[arg(long, env = "FACEGATE_HEADER_TIMEOUT_SECS", default_value_t = DEFAULT_HEADER_TIMEOUT_SECS)]
    pub header_timeout_secs: f64,
    /// Connections open at once; further ones wait in the listen backlog.
    #[arg(long, env = "FACEGATE_MAX_CONNECTIONS", default_value_t = DEFAULT_MAX_CONNECTIONS)]
    pub max_connections: usize,
    /// Connections open at once from one client address (IPv6: its /64), at most
    /// --max-connections; a further one is answered 503 and closed. Behind a proxy that hides the
    /// clients' addresses, set it to --max-connections.
    #[arg(long, env = "FACEGATE_MAX_CONNECTIONS_PER_ADDRESS", default_value_t = DEFAULT_MAX_CONNECTIONS_PER_ADDRESS)]
    pub max_connections_per_address: usize,
    /// Seconds in-flight connections get to finish after SIGTERM or Ctrl-C before they are dropped.
    #[arg(long, env = "FACEGATE_SHUTDOWN_GRACE_SECS", default_value_t = DEFAULT_SHUTDOWN_GRACE_SECS)]
    pub shutdown_grace_secs: f64,
    /// Log format: `text` or `json` (one object per line).
    #[arg(long, env = "FACEGATE_LOG_FORMAT", value_enum, default_value_t = LogFormat::default())]
    pub log_format: LogFormat,
    /// Serve the web console at `/` (`--console false` serves the API only).
    #[arg(long, env = "FACEGATE_CONSOLE", default_value_t = DEFAULT_CONSOLE, action = clap::ArgAction::Set)]
    pub console: bool,
    /// Enrolment: least unified quality score (0–100) of a photo; 0 accepts any.
    #[arg(long, env = "FACEGATE_MIN_QUALITY", default_value_t = DEFAULT_MIN_QUALITY)]
    pub min_quality: f32,
    /// Enrolment: least distance between the eye centres, photo pixels.
    #[arg(long, env = "FACEGATE_MIN_INTER_EYE_PX", default_value_t = DEFAULT_MIN_INTER_EYE_PX)]
    pub min_inter_eye_px: f32,
    /// Enrolment: least sharpness (RMS Laplacian of the face chip, grey levels).
    #[arg(long, env = "FACEGATE_MIN_SHARPNESS", default_value_t = DEFAULT_MIN_SHARPNESS)]
    pub min_sharpness: f32,
    /// Enrolment: least mean grey level of the face (0–255).
    #[arg(long, env = "FACEGATE_MIN_BRIGHTNESS", default_value_t = DEFAULT_MIN_BRIGHTNESS)]
    pub min_brightness: f32,
    /// Enrolment: largest mean grey level of the face (0–255).
    #[arg(long, env = "FACEGATE_MAX_BRIGHTNESS", default_value_t = DEFAULT_MAX_BRIGHTNESS)]
    pub max_brightness: f32,
    /// Enrolment: largest |yaw| of the head, degrees (3DMM fit; not checked without it).
    #[arg(long, env = "FACEGATE_MAX_YAW_DEG", default_value_t = DEFAULT_MAX_YAW_DEG)]
    pub max_yaw_deg: f32,
    /// Enrolment: largest |pitch| of the head, degrees (3DMM fit; not checked without it).
    #[arg(long, env = "FACEGATE_MAX_PITCH_DEG", default_value_t = DEFAULT_MAX_PITCH_DEG)]
    pub max_pitch_deg: f32,
    /// Presentation-attack detection (a printed photo held to the camera): `off` runs no liveness
    /// model and reports none, `report` adds each face's `liveness` to the responses, `enforce`
    /// also refuses enrolment photos and verify/identify probes taken for an attack (422
    /// `presentation-attack`). `enforce` without `liveness.bin` in the models stops the start-up.
    #[arg(long, env = "FACEGATE_LIVENESS", value_enum, default_value_t = choices::Liveness::from(LivenessPolicy::default()))]
    pub liveness: choices::Liveness,
    /// Liveness score (strictly between 0 and 1) below which a face is an attack, in place of the
    /// model's operating point (the EER of its NUAA evaluation) and of the camera's stored one
    /// (`facegate calibrate-liveness`): for a camera whose live and printed-photo scores the
    /// operator has measured.
    #[arg(long, env = "FACEGATE_LIVENESS_THRESHOLD")]
    pub liveness_threshold: Option<f32>,
    /// Seconds a liveness challenge (POST /liveness/challenge) may be answered in.
    #[arg(long, env = "FACEGATE_CHALLENGE_LIFETIME_SECS", default_value_t = DEFAULT_CHALLENGE_LIFETIME_SECS)]
    pub challenge_lifetime_secs: u64,
    /// Challenges (POST /liveness/challenge) per second per client address (IPv6: its /64), in
    /// bursts of twice as many; beyond → 429. 0: no rate.
    #[arg(long, env = "FACEGATE_CHALLENGE_RATE", default_value_t = DEFAULT_CHALLENGE_RATE)]
    pub challenge_rate: f64,
    /// Most challenges open (issued, neither answered nor expired) at once in the database;
    /// beyond → 429.
    #[arg(long, env = "FACEGATE_MAX_OPEN_CHALLENGES", default_value_t = DEFAULT_MAX_OPEN_CHALLENGES)]
    pub max_open_challenges: u64,
    /// With `--liveness enforce`: `/verify` only with a passed head-turn challenge; a verification
    /// without `challenge` is refused (422 `invalid-challenge`). Identification and enrolment are
    /// not affected.
    #[arg(long, env = "FACEGATE_REQUIRE_CHALLENGE")]
    pub require_challenge: bool,
    #[command(flatten)]
    pub template_key: TemplateKeyArgs,
    #[command(flatten)]
    pub template_protection: TemplateProtectionArgs,
}

/// Where the template protection secret comes from (shared by `serve` and `calibrate`).
#[derive(clap::Args, Debug, Clone, Default, PartialEq)]
pub struct TemplateProtectionArgs {
    /// File of the template protection secret, 64 hex digits (`openssl rand -hex 32`): every
    /// template is then a keyed rotation of the networks' embedding, unlinkable to the same
    /// person's templates under another secret, and only that is stored and compared. Keep it
    /// out of the database, as the template key. A database holds plain or protected templates,
    /// of one secret: a mismatch stops the start-up.
    #[arg(long, env = "FACEGATE_TEMPLATE_PROTECTION_KEY_FILE")]
    pub template_protection_key_file: Option<PathBuf>,
}

impl TemplateProtectionArgs {
    /// The secret of the key file, if one is given.
    pub fn key(&self) -> anyhow::Result<Option<ProtectionKey>> {
        let Some(path) = &self.template_protection_key_file else { return Ok(None) };
        let text =
            std::fs::read_to_string(path).with_context(|| format!("cannot read the template protection key file {}", path.display()))?;
        let key = ProtectionKey::parse(&text).map_err(|e| anyhow::anyhow!("template protection key file {}: {e}", path.display()))?;
        Ok(Some(key))
    }
}

/// Where the template key comes from (shared by `serve`, `rekey`, `backup` and `restore`).
#[derive(clap::Args, Debug, Clone, Default, PartialEq)]
pub struct TemplateKeyArgs {
    /// File of template keys, one per line as 64 hex digits (32 bytes), the current key first, then
    /// older keys still to be read; `#` lines are comments. Without it templates are stored unencrypted.
    #[arg(long, env = "FACEGATE_TEMPLATE_KEY_FILE")]
    pub template_key_file: Option<PathBuf>,
}

impl TemplateKeyArgs {
    /// The key ring of the key file, if one is given.
    pub fn key_ring(&self) -> anyhow::Result<Option<KeyRing>> {
        let Some(path) = &self.template_key_file else { return Ok(None) };
        let text = std::fs::read_to_string(path).with_context(|| format!("cannot read the template key file {}", path.display()))?;
        Ok(Some(KeyRing::parse(&text).with_context(|| format!("template key file {}", path.display()))?))
    }
}

impl Default for Settings {
    /// The defaults, as the flags have them (without reading the environment).
    fn default() -> Settings {
        Settings {
            bind: DEFAULT_BIND.into(),
            database: DEFAULT_DATABASE.into(),
            database_password_file: None,
            models: None,
            sfm: None,
            recognizer: RecognizerKind::default().into(),
            detector: DetectorKind::default().into(),
            api_keys: Vec::new(),
            api_keys_file: None,
            workers: None,
            queue: DEFAULT_QUEUE,
            enroll_queue: DEFAULT_ENROLL_QUEUE,
            admission_wait_ms: DEFAULT_ADMISSION_WAIT_MS,
            max_buffered_mb: DEFAULT_MAX_BUFFERED_MB,
            max_buffered_per_address_mb: DEFAULT_MAX_BUFFERED_PER_ADDRESS_MB,
            max_body_mb: DEFAULT_MAX_BODY_MB,
            max_pixels: DEFAULT_MAX_PIXELS,
            max_decode_mb: DEFAULT_MAX_DECODE_MB,
            max_images: DEFAULT_MAX_IMAGES,
            timeout_secs: DEFAULT_TIMEOUT_SECS,
            body_timeout_secs: DEFAULT_BODY_TIMEOUT_SECS,
            body_grace_secs: DEFAULT_BODY_GRACE_SECS,
            min_body_rate_kib: DEFAULT_MIN_BODY_RATE_KIB,
            max_uploads_per_address: DEFAULT_MAX_UPLOADS_PER_ADDRESS,
            header_timeout_secs: DEFAULT_HEADER_TIMEOUT_SECS,
            max_connections: DEFAULT_MAX_CONNECTIONS,
            max_connections_per_address: DEFAULT_MAX_CONNECTIONS_PER_ADDRESS,
            shutdown_grace_secs: DEFAULT_SHUTDOWN_GRACE_SECS,
            log_format: LogFormat::default(),
            console: DEFAULT_CONSOLE,
            template_key: TemplateKeyArgs::default(),
            template_protection: TemplateProtectionArgs::default(),
            min_quality: DEFAULT_MIN_QUALITY,
            min_inter_eye_px: DEFAULT_MIN_INTER_EYE_PX,
            min_sharpness: DEFAULT_MIN_SHARPNESS,
            min_brightness: DEFAULT_MIN_BRIGHTNESS,
            max_brightness: DEFAULT_MAX_BRIGHTNESS,
            max_yaw_deg: DEFAULT_MAX_YAW_DEG,
            max_pitch_deg: DEFAULT_MAX_PITCH_DEG,
            liveness: LivenessPolicy::default().into(),
            liveness_threshold: None,
            challenge_lifetime_secs: DEFAULT_CHALLENGE_LIFETIME_SECS,
            challenge_rate: DEFAULT_CHALLENGE_RATE,
            max_open_challenges: DEFAULT_MAX_OPEN_CHALLENGES,
            require_challenge: false,
        }
    }
}

impl Settings {
    /// The HTTP layer's limits; refuses a timeout that is not positive, an enrolment of no photo,
    /// an unreadable keys file, a key setting that holds no key, a key shorter than
    /// [`MIN_API_KEY_LEN`] and a liveness threshold outside (0, 1).
    pub fn api_config(&self) -> anyhow::Result<ApiConfig> {
        if let Some(threshold) = self.liveness_threshold {
            liveness_threshold(threshold)?;
        }
        let timeout = seconds("--timeout-secs", self.timeout_secs)?;
        let body_timeout = seconds("--body-timeout-secs", self.body_timeout_secs)?;
        anyhow::ensure!(body_timeout <= timeout, "--body-timeout-secs must not exceed --timeout-secs");
        anyhow::ensure!(self.max_images >= 1, "--max-images must be at least 1");
        anyhow::ensure!((10..=3600).contains(&self.challenge_lifetime_secs), "--challenge-lifetime-secs must be between 10 and 3600");
        anyhow::ensure!(self.max_uploads_per_address >= 1, "--max-uploads-per-address must be at least 1");
        anyhow::ensure!(
            self.max_buffered_per_address_mb >= self.max_body_mb,
            "--max-buffered-per-address-mb must be at least --max-body-mb: else a body at the limit could never be held"
        );
        anyhow::ensure!(self.challenge_rate.is_finite() && self.challenge_rate >= 0.0, "--challenge-rate must be 0 or more");
        anyhow::ensure!(self.max_open_challenges >= 1, "--max-open-challenges must be at least 1");
        anyhow::ensure!(
            !self.require_challenge || LivenessPolicy::from(self.liveness) == LivenessPolicy::Enforce,
            "--require-challenge (FACEGATE_REQUIRE_CHALLENGE) needs --liveness enforce: a challenge is only required where its verdict is"
        );
        Ok(ApiConfig {
            max_body_bytes: self.max_body_mb << 20,
            request_timeout: timeout,
            body_timeout,
            body_grace: seconds("--body-grace-secs", self.body_grace_secs)?,
            min_body_rate: self.min_body_rate_kib.saturating_mul(1024),
            max_uploads_per_address: self.max_uploads_per_address,
            challenge_rate: self.challenge_rate,
            workers: self.workers.unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get()).unwrap_or(2)).max(1),
            queue_depth: self.queue,
            enroll_queue_depth: self.enroll_queue,
            admission_wait: Duration::from_millis(self.admission_wait_ms),
            max_buffered_bytes: self.max_buffered_mb << 20,
            max_buffered_per_address: self.max_buffered_per_address_mb << 20,
            api_keys: self.api_keys()?,
            console: self.console,
            service: ServiceConfig {
                // The largest side is the decoder's own limit.
                decode_limits: DecodeLimits {
                    max_pixels: self.max_pixels,
                    max_alloc_bytes: self.max_decode_mb << 20,
                    ..DecodeLimits::default()
                },
                max_images: self.max_images,
                quality_policy: self.quality_policy(),
                default_fmr: DEFAULT_FMR,
                liveness: self.liveness.into(),
                liveness_threshold: self.liveness_threshold,
                challenge: ChallengeConfig { lifetime: Duration::from_secs(self.challenge_lifetime_secs) },
                max_open_challenges: self.max_open_challenges,
                require_challenge: self.require_challenge,
            },
        })
    }

    /// The liveness model the pipeline keeps of the one it loaded (`None` when `liveness.bin` is
    /// missing): none with `--liveness off`, so no time is spent on it. `enforce` without a model,
    /// and a `--liveness-threshold` with no model to apply it to, stop the start-up. The threshold
    /// itself is the service's ([`facegate_service::liveness::threshold_in_force`]), not the model's.
    pub fn liveness_model(&self, model: Option<LivenessModel>) -> anyhow::Result<Option<LivenessModel>> {
        let policy = LivenessPolicy::from(self.liveness);
        if policy == LivenessPolicy::Off {
            return Ok(None);
        }
        let file = facegate_vision::liveness::FILE;
        if model.is_none() {
            anyhow::ensure!(
                policy != LivenessPolicy::Enforce,
                "--liveness enforce (FACEGATE_LIVENESS) needs the liveness model {file} in the models folder (`facegate train \
                 liveness` makes it): without it no face could be checked"
            );
            anyhow::ensure!(
                self.liveness_threshold.is_none(),
                "--liveness-threshold (FACEGATE_LIVENESS_THRESHOLD) is set but there is no liveness model ({file}) to apply it to"
            );
        }
        Ok(model)
    }

    /// [`Settings::liveness_model`] applied to a loaded pipeline.
    pub fn configure_liveness(&self, pipeline: &mut Pipeline) -> anyhow::Result<()> {
        pipeline.liveness = self.liveness_model(pipeline.liveness.take())?;
        Ok(())
    }

    /// The enrolment quality policy.
    pub fn quality_policy(&self) -> QualityPolicy {
        QualityPolicy {
            min_score: Some(self.min_quality),
            min_inter_eye_px: Some(self.min_inter_eye_px),
            min_sharpness: Some(self.min_sharpness),
            min_brightness: Some(self.min_brightness),
            max_brightness: Some(self.max_brightness),
            max_yaw_deg: Some(self.max_yaw_deg),
            max_pitch_deg: Some(self.max_pitch_deg),
        }
    }

    /// The connection loop's limits.
    pub fn server_limits(&self) -> anyhow::Result<ServerLimits> {
        anyhow::ensure!(self.max_connections >= 1, "--max-connections must be at least 1");
        anyhow::ensure!(self.max_connections_per_address >= 1, "--max-connections-per-address must be at least 1");
        Ok(ServerLimits {
            max_connections: self.max_connections,
            max_connections_per_address: self.max_connections_per_address.min(self.max_connections),
            header_timeout: seconds("--header-timeout-secs", self.header_timeout_secs)?,
            shutdown_grace: seconds("--shutdown-grace-secs", self.shutdown_grace_secs)?,
        })
    }

    /// The keys of `--api-keys` and of `--api-keys-file`, each at least [`MIN_API_KEY_LEN`]
    /// characters (the error names the key's place, never the key). A setting that is given but
    /// holds no key (`--api-keys ",,"` or blanks; a keys file of only comments and blank lines)
    /// stops the start-up: it was meant to close the API, and must not leave it open. An empty
    /// value (`FACEGATE_API_KEYS=""`) is no setting, as an absent one: the explicit open mode.
    fn api_keys(&self) -> anyhow::Result<Vec<String>> {
        let mut keys: Vec<(String, String)> = Vec::new();
        let flag_given = self.api_keys.len() > 1 || self.api_keys.iter().any(|k| !k.is_empty());
        for (i, key) in self.api_keys.iter().enumerate() {
            if !key.trim().is_empty() {
                keys.push((format!("--api-keys entry {}", i + 1), key.trim().to_string()));
            }
        }
        anyhow::ensure!(
            !flag_given || !keys.is_empty(),
            "--api-keys (FACEGATE_API_KEYS) is set but holds no key, only commas or blanks: give at least one key of \
             {MIN_API_KEY_LEN} or more characters, or remove the setting to run the API open"
        );
        if let Some(path) = &self.api_keys_file {
            let text =
                std::fs::read_to_string(path).map_err(|e| anyhow::anyhow!("cannot read the API keys file {}: {e}", path.display()))?;
            let before = keys.len();
            for (n, line) in text.lines().enumerate() {
                let line = line.trim();
                if !line.is_empty() && !line.starts_with('#') {
                    keys.push((format!("{} line {}", path.display(), n + 1), line.to_string()));
                }
            }
            anyhow::ensure!(
                keys.len() > before,
                "the API keys file {} (--api-keys-file, FACEGATE_API_KEYS_FILE) holds no key, only blank lines and # comments: \
                 put at least one key of {MIN_API_KEY_LEN} or more characters in it, or remove the setting to run the API open",
                path.display()
            );
        }
        for (place, key) in &keys {
            let len = key.chars().count();
            anyhow::ensure!(
                len >= MIN_API_KEY_LEN,
                "the API key at {place} has {len} characters; keys must have at least {MIN_API_KEY_LEN}"
            );
        }
        Ok(keys.into_iter().map(|(_, k)| k).collect())
    }

    /// The pipeline's model folders: the flags' when given, else [`pipeline_config`]'s.
    pub fn pipeline_config(&self) -> PipelineConfig {
        let defaults = pipeline_config();
        PipelineConfig {
            models_dir: self.models.clone().unwrap_or(defaults.models_dir),
            sfm_dir: self.sfm.clone().or(defaults.sfm_dir),
            recognizer: self.recognizer.into(),
            detector: self.detector.into(),
        }
    }
}

/// A liveness threshold: a probability strictly between 0 and 1 (0 would let every print through,
/// 1 refuse every face).
fn liveness_threshold(value: f32) -> anyhow::Result<f32> {
    anyhow::ensure!(
        value > 0.0 && value < 1.0,
        "--liveness-threshold (FACEGATE_LIVENESS_THRESHOLD) must be strictly between 0 and 1, got {value}"
    );
    Ok(value)
}

fn seconds(flag: &str, value: f64) -> anyhow::Result<Duration> {
    anyhow::ensure!(value > 0.0 && value.is_finite(), "{flag} must be positive");
    Ok(Duration::from_secs_f64(value))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The defaults written once: what `Settings::default` holds is what the flags parse to.
    #[test]
    fn default_settings_are_the_flags_defaults() {
        use clap::Parser;
        #[derive(Parser)]
        struct Cli {
            #[command(flatten)]
            settings: Settings,
        }
        let parsed = Cli::try_parse_from(["facegate"]).unwrap().settings;
        let env_set = |name: &str| std::env::var_os(name).is_some();
        if !["BIND", "DATABASE_URL", "MODELS", "SFM", "API_KEYS", "WORKERS", "QUEUE", "MAX_BODY_MB", "MAX_PIXELS", "MAX_DECODE_MB"]
            .iter()
            .chain(&["MAX_IMAGES", "TIMEOUT_SECS", "CONSOLE", "API_KEYS_FILE", "ENROL_QUEUE", "MAX_BUFFERED_MB", "BODY_TIMEOUT_SECS"])
            .chain(&["ADMISSION_WAIT_MS", "BODY_GRACE_SECS", "MIN_BODY_RATE_KIB", "MAX_UPLOADS_PER_ADDRESS"])
            .chain(&["HEADER_TIMEOUT_SECS", "MAX_CONNECTIONS", "SHUTDOWN_GRACE_SECS", "LOG_FORMAT", "TEMPLATE_KEY_FILE"])
            .chain(&[
                "MIN_QUALITY",
                "MIN_INTER_EYE_PX",
                "MIN_SHARPNESS",
                "MIN_BRIGHTNESS",
                "MAX_BRIGHTNESS",
                "MAX_YAW_DEG",
                "MAX_PITCH_DEG",
                "LIVENESS",
                "LIVENESS_THRESHOLD",
            ])
            .any(|v| env_set(&format!("FACEGATE_{v}")))
        {
            assert_eq!(parsed, Settings::default());
        }
        let api = Settings::default().api_config().unwrap();
        assert_eq!((api.max_body_bytes, api.service.max_images, api.queue_depth, api.service.default_fmr), (16 << 20, 16, 64, 1e-3));
        assert_eq!(api.service.decode_limits.max_alloc_bytes, 256 << 20);
        assert!(Settings { timeout_secs: 0.0, ..Settings::default() }.api_config().is_err());
        assert!(Settings { body_timeout_secs: 60.0, ..Settings::default() }.api_config().is_err());
        assert_eq!((api.body_grace, api.min_body_rate, api.max_uploads_per_address), (Duration::from_secs(5), 8192, 16));
        assert!(Settings { body_grace_secs: 0.0, ..Settings::default() }.api_config().is_err());
        assert!(Settings { max_uploads_per_address: 0, ..Settings::default() }.api_config().is_err());
        assert_eq!(api.service.liveness, LivenessPolicy::Report);
        let server = Settings::default().server_limits().unwrap();
        assert_eq!(
            (server.max_connections, server.header_timeout, server.shutdown_grace),
            (1024, Duration::from_secs(10), Duration::from_secs(10))
        );
    }

    /// Keys come from the flag and the file (comments and blank lines skipped); a short one stops
    /// the start-up with its place named and the key itself not shown.
    #[test]
    fn api_keys_from_the_flag_and_the_file_at_least_16_characters() {
        let dir = std::env::temp_dir().join(format!("facegate-keys-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("keys");
        std::fs::write(&file, "# ops team\n\n  0123456789abcdef-file  \n").unwrap();
        let settings =
            Settings { api_keys: vec!["0123456789abcdef-flag".into()], api_keys_file: Some(file.clone()), ..Settings::default() };
        assert_eq!(settings.api_config().unwrap().api_keys, ["0123456789abcdef-flag", "0123456789abcdef-file"]);

        std::fs::write(&file, "0123456789abcdef-file\nshort-secret\n").unwrap();
        let error = settings.api_config().unwrap_err().to_string();
        assert!(error.contains("line 2") && error.contains("at least 16") && !error.contains("short-secret"), "{error}");
        let error = Settings { api_keys: vec!["tiny".into()], ..Settings::default() }.api_config().unwrap_err().to_string();
        assert!(error.contains("--api-keys entry 1") && !error.contains("tiny"), "{error}");
        assert!(Settings { api_keys_file: Some(dir.join("missing")), ..Settings::default() }.api_config().is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A key setting given but holding no key stops the start-up (naming the setting); an empty
    /// value, like no setting, is the explicit open mode. Parsed as clap parses the flag (the
    /// variable's value goes through the same splitting).
    #[test]
    fn a_key_setting_that_holds_no_key_stops_the_start_up() {
        use clap::Parser;
        #[derive(Parser)]
        struct Cli {
            #[command(flatten)]
            settings: Settings,
        }
        let settings = |keys: &str| Cli::try_parse_from(["facegate", "--api-keys", keys]).unwrap().settings;
        for empty in [",,", ",", " ", " , \t"] {
            let error = settings(empty).api_config().unwrap_err().to_string();
            assert!(error.contains("--api-keys") && error.contains("holds no key"), "{empty:?}: {error}");
        }
        assert!(settings("").api_config().unwrap().api_keys.is_empty(), "an empty value is no setting");
        assert_eq!(settings(",0123456789abcdef-flag,").api_config().unwrap().api_keys, ["0123456789abcdef-flag"]);

        let dir = std::env::temp_dir().join(format!("facegate-empty-keys-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("keys");
        for text in ["", "# the ops team's key goes here\n", "\n  \n# none yet\n"] {
            std::fs::write(&file, text).unwrap();
            let error = Settings { api_keys_file: Some(file.clone()), ..Settings::default() }.api_config().unwrap_err().to_string();
            assert!(error.contains("--api-keys-file") && error.contains("holds no key"), "{text:?}: {error}");
            // Keys given elsewhere do not excuse an empty file.
            let both =
                Settings { api_keys: vec!["0123456789abcdef-flag".into()], api_keys_file: Some(file.clone()), ..Settings::default() };
            assert!(both.api_config().is_err());
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// `off` drops the model, `report` and `enforce` keep it as it is (the operator's threshold is
    /// the service's, not the model's), and what cannot be honoured stops the start-up.
    #[test]
    fn the_liveness_settings_shape_the_model_the_pipeline_keeps() {
        use crate::choices::Liveness;
        let model = || Some(LivenessModel::load(&models_dir().join(facegate_vision::liveness::FILE)).unwrap());
        let with = |liveness, liveness_threshold| Settings { liveness, liveness_threshold, ..Settings::default() };
        assert!(with(Liveness::Off, None).liveness_model(model()).unwrap().is_none());
        assert!(with(Liveness::Off, Some(0.3)).liveness_model(model()).unwrap().is_none(), "off wins over a threshold");
        for policy in [Liveness::Report, Liveness::Enforce] {
            assert_eq!(with(policy, None).liveness_model(model()).unwrap(), model());
            assert_eq!(with(policy, Some(0.25)).liveness_model(model()).unwrap(), model(), "the model keeps its own point");
        }
        // No model: reported as none, refused where it was needed.
        assert!(with(Liveness::Report, None).liveness_model(None).unwrap().is_none());
        let error = with(Liveness::Enforce, None).liveness_model(None).unwrap_err().to_string();
        assert!(error.contains("--liveness enforce") && error.contains("liveness.bin"), "{error}");
        let error = with(Liveness::Report, Some(0.5)).liveness_model(None).unwrap_err().to_string();
        assert!(error.contains("--liveness-threshold"), "{error}");
        // The threshold is a probability strictly inside (0, 1).
        for bad in [0.0, 1.0, 1.5, -0.1, f32::NAN] {
            let error = with(Liveness::Report, Some(bad)).api_config().unwrap_err().to_string();
            assert!(error.contains("--liveness-threshold") && error.contains("between 0 and 1"), "{bad}: {error}");
        }
        assert_eq!(with(Liveness::Enforce, Some(0.5)).api_config().unwrap().service.liveness, LivenessPolicy::Enforce);
    }

    #[test]
    fn the_template_key_file_is_read_into_a_key_ring() {
        let dir = std::env::temp_dir().join(format!("facegate-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("template.key");
        std::fs::write(&path, format!("# current\n{}\n", "ab".repeat(32))).unwrap();
        let args = TemplateKeyArgs { template_key_file: Some(path.clone()) };
        assert_eq!(args.key_ring().unwrap().unwrap().current_id().len(), 16);
        assert!(TemplateKeyArgs::default().key_ring().unwrap().is_none());
        std::fs::write(&path, "not a key").unwrap();
        assert!(args.key_ring().is_err());
        assert!(TemplateKeyArgs { template_key_file: Some(dir.join("missing")) }.key_ring().is_err());
        std::fs::remove_dir_all(dir).unwrap();
    }
}

/// What the `OTEL_*` environment asks of traces; the OpenTelemetry SDK reads the rest (headers,
/// timeout, batching, sampler) itself.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TraceSettings {
    /// `OTEL_EXPORTER_OTLP_TRACES_ENDPOINT`, else `OTEL_EXPORTER_OTLP_ENDPOINT`: traces are
    /// exported only when one is set.
    pub endpoint: Option<String>,
    /// `OTEL_EXPORTER_OTLP_TRACES_PROTOCOL`, else `OTEL_EXPORTER_OTLP_PROTOCOL`.
    pub protocol: Option<String>,
    /// `OTEL_SERVICE_NAME`, or `service.name` in `OTEL_RESOURCE_ATTRIBUTES`.
    pub service_name: Option<String>,
    /// `OTEL_SDK_DISABLED=true`.
    pub sdk_disabled: bool,
}

impl TraceSettings {
    pub fn from_env() -> TraceSettings {
        let var = |key: &str| std::env::var(key).ok().map(|v| v.trim().to_string()).filter(|v| !v.is_empty());
        let from_attributes = var("OTEL_RESOURCE_ATTRIBUTES")
            .and_then(|attributes| attributes.split(',').find_map(|pair| pair.trim().strip_prefix("service.name=").map(str::to_string)));
        TraceSettings {
            endpoint: var("OTEL_EXPORTER_OTLP_TRACES_ENDPOINT").or_else(|| var("OTEL_EXPORTER_OTLP_ENDPOINT")),
            protocol: var("OTEL_EXPORTER_OTLP_TRACES_PROTOCOL").or_else(|| var("OTEL_EXPORTER_OTLP_PROTOCOL")),
            service_name: var("OTEL_SERVICE_NAME").or(from_attributes),
            sdk_disabled: var("OTEL_SDK_DISABLED").is_some_and(|v| v.eq_ignore_ascii_case("true")),
        }
    }
}
