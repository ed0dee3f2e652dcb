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

use crate::core::imaging::DecodeLimits;
use crate::http::ApiConfig;
use crate::pipeline::PipelineConfig;
use crate::quality::QualityPolicy;
use crate::recognize::DEFAULT_FMR;
use crate::recognize::RecognizerKind;

fn env_path(name: &str) -> Option<PathBuf> {
    std::env::var_os(name).filter(|v| !v.is_empty()).map(PathBuf::from)
}

/// The shared research data (IMM, ORL, cascades, SFM), read-only.
pub fn shared_dir() -> PathBuf {
    env_path("FACEGATE_SHARED").unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared"))
}

/// The Surrey Face Model folder (`sfm_shape_3448.bin` and companions).
pub fn sfm_dir() -> PathBuf {
    env_path("FACEGATE_SFM").unwrap_or_else(|| shared_dir().join("models/sfm"))
}

/// The project's own trained models (`asm.bin`, `dlda.bin`, cascades, calibration).
pub fn models_dir() -> PathBuf {
    if let Some(p) = env_path("FACEGATE_MODELS") {
        return p;
    }
    let local = PathBuf::from("models");
    if local.is_dir() { local } else { PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models") }
}

/// The pipeline's model folders: [`models_dir`] and [`sfm_dir`].
pub fn pipeline_config() -> PipelineConfig {
    PipelineConfig { models_dir: models_dir(), sfm_dir: Some(sfm_dir()), recognizer: RecognizerKind::default() }
}

const DEFAULT_BIND: &str = "127.0.0.1:8080";
const DEFAULT_DATABASE: &str = "sqlite://facegate.db";
const DEFAULT_QUEUE: usize = 64;
const DEFAULT_MAX_BODY_MB: usize = 16;
const DEFAULT_MAX_PIXELS: u64 = 16_000_000;
const DEFAULT_MAX_DECODE_MB: u64 = 256;
const DEFAULT_MAX_IMAGES: usize = 16;
const DEFAULT_TIMEOUT_SECS: f64 = 30.0;
const DEFAULT_CONSOLE: bool = true;
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
    /// Database URL (SQLite; the file is created if missing).
    #[arg(long, env = "FACEGATE_DATABASE_URL", default_value = DEFAULT_DATABASE)]
    pub database: String,
    /// The project's trained models (default: `models/` in the working directory or the crate's).
    #[arg(long, env = "FACEGATE_MODELS")]
    pub models: Option<PathBuf>,
    /// The Surrey Face Model folder for 3DMM pose correction (missing: 2D alignment only).
    #[arg(long, env = "FACEGATE_SFM")]
    pub sfm: Option<PathBuf>,
    /// Which recognizer makes templates: the deep face embedding (`deep.bin`) or the classical
    /// pixels + LBP Direct LDA (`dlda.bin`). Templates of one are never compared with the other's.
    #[arg(long, env = "FACEGATE_RECOGNIZER", value_enum, default_value_t = RecognizerKind::default())]
    pub recognizer: RecognizerKind,
    /// Comma-separated API keys; when none are given the API is open to anyone who can reach it.
    #[arg(long, env = "FACEGATE_API_KEYS", value_delimiter = ',', hide_env_values = true)]
    pub api_keys: Vec<String>,
    /// Photos analysed at once (default: the number of cores).
    #[arg(long, env = "FACEGATE_WORKERS")]
    pub workers: Option<usize>,
    /// Requests that may wait for a worker before the service answers 503.
    #[arg(long, env = "FACEGATE_QUEUE", default_value_t = DEFAULT_QUEUE)]
    pub queue: usize,
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
}

impl Default for Settings {
    /// The defaults, as the flags have them (without reading the environment).
    fn default() -> Settings {
        Settings {
            bind: DEFAULT_BIND.into(),
            database: DEFAULT_DATABASE.into(),
            models: None,
            sfm: None,
            recognizer: RecognizerKind::default(),
            api_keys: Vec::new(),
            workers: None,
            queue: DEFAULT_QUEUE,
            max_body_mb: DEFAULT_MAX_BODY_MB,
            max_pixels: DEFAULT_MAX_PIXELS,
            max_decode_mb: DEFAULT_MAX_DECODE_MB,
            max_images: DEFAULT_MAX_IMAGES,
            timeout_secs: DEFAULT_TIMEOUT_SECS,
            console: DEFAULT_CONSOLE,
            min_quality: DEFAULT_MIN_QUALITY,
            min_inter_eye_px: DEFAULT_MIN_INTER_EYE_PX,
            min_sharpness: DEFAULT_MIN_SHARPNESS,
            min_brightness: DEFAULT_MIN_BRIGHTNESS,
            max_brightness: DEFAULT_MAX_BRIGHTNESS,
            max_yaw_deg: DEFAULT_MAX_YAW_DEG,
            max_pitch_deg: DEFAULT_MAX_PITCH_DEG,
        }
    }
}

impl Settings {
    /// The HTTP layer's limits; refuses a timeout that is not positive and an enrolment of no photo.
    pub fn api_config(&self) -> anyhow::Result<ApiConfig> {
        anyhow::ensure!(self.timeout_secs > 0.0 && self.timeout_secs.is_finite(), "--timeout-secs must be positive");
        anyhow::ensure!(self.max_images >= 1, "--max-images must be at least 1");
        Ok(ApiConfig {
            max_body_bytes: self.max_body_mb << 20,
            // The largest side is the decoder's own limit.
            decode_limits: DecodeLimits {
                max_pixels: self.max_pixels,
                max_alloc_bytes: self.max_decode_mb << 20,
                ..DecodeLimits::default()
            },
            max_images: self.max_images,
            request_timeout: Duration::from_secs_f64(self.timeout_secs),
            workers: self.workers.unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get()).unwrap_or(2)).max(1),
            queue_depth: self.queue,
            api_keys: self.api_keys.iter().map(|k| k.trim().to_string()).filter(|k| !k.is_empty()).collect(),
            default_fmr: DEFAULT_FMR,
            console: self.console,
            quality_policy: self.quality_policy(),
        })
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

    /// The pipeline's model folders: the flags' when given, else [`pipeline_config`]'s.
    pub fn pipeline_config(&self) -> PipelineConfig {
        let defaults = pipeline_config();
        PipelineConfig {
            models_dir: self.models.clone().unwrap_or(defaults.models_dir),
            sfm_dir: self.sfm.clone().or(defaults.sfm_dir),
            recognizer: self.recognizer,
        }
    }
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
            .chain(&["MAX_IMAGES", "TIMEOUT_SECS", "CONSOLE"])
            .chain(&[
                "MIN_QUALITY",
                "MIN_INTER_EYE_PX",
                "MIN_SHARPNESS",
                "MIN_BRIGHTNESS",
                "MAX_BRIGHTNESS",
                "MAX_YAW_DEG",
                "MAX_PITCH_DEG",
            ])
            .any(|v| env_set(&format!("FACEGATE_{v}")))
        {
            assert_eq!(parsed, Settings::default());
        }
        let api = Settings::default().api_config().unwrap();
        assert_eq!((api.max_body_bytes, api.max_images, api.queue_depth, api.default_fmr), (16 << 20, 16, 64, 1e-3));
        assert_eq!(api.decode_limits.max_alloc_bytes, 256 << 20);
        assert!(Settings { timeout_secs: 0.0, ..Settings::default() }.api_config().is_err());
    }
}
