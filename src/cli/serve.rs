//! `facegate serve`: the HTTP service on axum and tokio.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;

use crate::api::{self, ApiConfig, AppState};
use crate::core::imaging::DecodeLimits;
use crate::pipeline::{Pipeline, PipelineConfig};
use crate::store::Store;

#[derive(clap::Args, Debug)]
pub struct ServeArgs {
    /// Address to listen on.
    #[arg(long, env = "FACEGATE_BIND", default_value = "127.0.0.1:8080")]
    pub bind: String,
    /// Database URL (SQLite; the file is created if missing).
    #[arg(long, env = "FACEGATE_DATABASE_URL", default_value = "sqlite://facegate.db")]
    pub database: String,
    /// The project's trained models (default: `models/` in the working directory or the crate's).
    #[arg(long, env = "FACEGATE_MODELS")]
    pub models: Option<PathBuf>,
    /// The Surrey Face Model folder for 3DMM pose correction (missing: 2D alignment only).
    #[arg(long, env = "FACEGATE_SFM")]
    pub sfm: Option<PathBuf>,
    /// Comma-separated API keys; when none are given the API is open to anyone who can reach it.
    #[arg(long, env = "FACEGATE_API_KEYS", value_delimiter = ',', hide_env_values = true)]
    pub api_keys: Vec<String>,
    /// Photos analysed at once (default: the number of cores).
    #[arg(long, env = "FACEGATE_WORKERS")]
    pub workers: Option<usize>,
    /// Requests that may wait for a worker before the service answers 503.
    #[arg(long, env = "FACEGATE_QUEUE", default_value_t = 64)]
    pub queue: usize,
    /// Largest request body, in MiB.
    #[arg(long, env = "FACEGATE_MAX_BODY_MB", default_value_t = 16)]
    pub max_body_mb: usize,
    /// Largest photo, in pixels (width × height).
    #[arg(long, env = "FACEGATE_MAX_PIXELS", default_value_t = 16_000_000)]
    pub max_pixels: u64,
    /// Most memory the decoder may allocate per photo, in MiB.
    #[arg(long, env = "FACEGATE_MAX_DECODE_MB", default_value_t = 256)]
    pub max_decode_mb: u64,
    /// Most photos in one enrolment.
    #[arg(long, env = "FACEGATE_MAX_IMAGES", default_value_t = 16)]
    pub max_images: usize,
    /// Request timeout in seconds (answered with 504).
    #[arg(long, env = "FACEGATE_TIMEOUT_SECS", default_value_t = 30.0)]
    pub timeout_secs: f64,
    /// Probe a running server's `/health` at `--bind` and exit 0 if it answers 200 (for container
    /// health checks, so the runtime image needs no curl).
    #[arg(long)]
    pub healthcheck: bool,
}

impl ServeArgs {
    pub fn api_config(&self) -> anyhow::Result<ApiConfig> {
        let defaults = ApiConfig::default();
        anyhow::ensure!(self.timeout_secs > 0.0 && self.timeout_secs.is_finite(), "--timeout-secs must be positive");
        anyhow::ensure!(self.max_images >= 1, "--max-images must be at least 1");
        Ok(ApiConfig {
            max_body_bytes: self.max_body_mb << 20,
            decode_limits: DecodeLimits {
                max_pixels: self.max_pixels,
                max_alloc_bytes: self.max_decode_mb << 20,
                ..defaults.decode_limits
            },
            max_images: self.max_images,
            request_timeout: Duration::from_secs_f64(self.timeout_secs),
            workers: self.workers.unwrap_or(defaults.workers).max(1),
            queue_depth: self.queue,
            api_keys: self.api_keys.iter().map(|k| k.trim().to_string()).filter(|k| !k.is_empty()).collect(),
            default_fmr: defaults.default_fmr,
        })
    }

    pub fn pipeline_config(&self) -> PipelineConfig {
        let defaults = PipelineConfig::default();
        PipelineConfig { models_dir: self.models.clone().unwrap_or(defaults.models_dir), sfm_dir: self.sfm.clone().or(defaults.sfm_dir) }
    }
}

pub fn run(args: ServeArgs) -> anyhow::Result<ExitCode> {
    if args.healthcheck {
        return healthcheck(&args.bind);
    }
    let _ = tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()))
        .try_init();
    let config = args.api_config()?;
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().context("cannot start the async runtime")?;
    runtime.block_on(serve(args, config))?;
    Ok(ExitCode::SUCCESS)
}

async fn serve(args: ServeArgs, config: ApiConfig) -> anyhow::Result<()> {
    let pipeline_config = args.pipeline_config();
    tracing::info!(models = %pipeline_config.models_dir.display(), "loading the face pipeline");
    let pipeline =
        tokio::task::spawn_blocking(move || Pipeline::load(&pipeline_config)).await?.context("cannot load the face pipeline models")?;
    tracing::info!(model_version = pipeline.recognizer.model_version(), with_3dmm = pipeline.face_model.is_some(), "pipeline loaded");
    let store = Store::connect(&args.database).await.with_context(|| format!("cannot open the database {}", args.database))?;
    if config.api_keys.is_empty() {
        tracing::warn!("no API keys configured (FACEGATE_API_KEYS): the API is OPEN to anyone who can reach {}", args.bind);
    } else {
        tracing::info!("{} API key(s) configured", config.api_keys.len());
    }
    tracing::info!(workers = config.workers, queue = config.queue_depth, "bounded work pool");
    let state = AppState::new(Arc::new(pipeline), store.clone(), config);
    let listener = tokio::net::TcpListener::bind(&args.bind).await.with_context(|| format!("cannot listen on {}", args.bind))?;
    tracing::info!("listening on http://{}", listener.local_addr()?);
    axum::serve(listener, api::router(state)).with_graceful_shutdown(shutdown_signal()).await?;
    store.close().await;
    tracing::info!("stopped");
    Ok(())
}

async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = terminate => {},
    }
    tracing::info!("shutting down");
}

/// A minimal HTTP/1.1 GET of `/health`; an unspecified listen address is probed on loopback.
fn healthcheck(bind: &str) -> anyhow::Result<ExitCode> {
    let mut addr: SocketAddr = bind.to_socket_addrs()?.next().context("the bind address resolves to nothing")?;
    if addr.ip().is_unspecified() {
        addr.set_ip(if addr.is_ipv4() { [127, 0, 0, 1].into() } else { std::net::Ipv6Addr::LOCALHOST.into() });
    }
    let mut stream = TcpStream::connect_timeout(&addr, Duration::from_secs(3))?;
    stream.set_read_timeout(Some(Duration::from_secs(5)))?;
    write!(stream, "GET /health HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n")?;
    let mut response = String::new();
    stream.read_to_string(&mut response)?;
    let healthy = response.starts_with("HTTP/1.1 200");
    eprintln!("{}", response.lines().next().unwrap_or("no response"));
    Ok(if healthy { ExitCode::SUCCESS } else { ExitCode::FAILURE })
}
