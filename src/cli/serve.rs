//! `facegate serve`: the HTTP service on axum and tokio.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;

use crate::config::{LogFormat, Settings};
use crate::http::server::{self, ServerLimits, Stopped};
use crate::http::{self, ApiConfig, AppState};
use crate::pipeline::Pipeline;
use crate::store::Store;

#[derive(clap::Args, Debug)]
pub struct ServeArgs {
    #[command(flatten)]
    pub settings: Settings,
    /// Probe a running server's `/health` at `--bind` and exit 0 if it answers 200 (for container
    /// health checks, so the runtime image needs no curl).
    #[arg(long)]
    pub healthcheck: bool,
}

pub fn run(args: ServeArgs) -> anyhow::Result<ExitCode> {
    if args.healthcheck {
        return healthcheck(&args.settings.bind);
    }
    let filter = tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into());
    let _ = match args.settings.log_format {
        LogFormat::Text => tracing_subscriber::fmt().with_env_filter(filter).try_init(),
        LogFormat::Json => tracing_subscriber::fmt().json().with_env_filter(filter).try_init(),
    };
    let config = args.settings.api_config()?;
    let limits = args.settings.server_limits()?;
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().context("cannot start the async runtime")?;
    runtime.block_on(serve(args.settings, config, limits))?;
    // Pool jobs still running after the grace period are not waited for.
    runtime.shutdown_timeout(Duration::from_secs(1));
    Ok(ExitCode::SUCCESS)
}

async fn serve(args: Settings, config: ApiConfig, limits: ServerLimits) -> anyhow::Result<()> {
    let pipeline_config = args.pipeline_config();
    tracing::info!(models = %pipeline_config.models_dir.display(), "loading the face pipeline");
    let pipeline =
        tokio::task::spawn_blocking(move || Pipeline::load(&pipeline_config)).await?.context("cannot load the face pipeline models")?;
    tracing::info!(model_version = pipeline.recognizer.model_version(), with_3dmm = pipeline.face_model.is_some(), "pipeline loaded");
    let keys = args.template_key.key_ring()?;
    match &keys {
        Some(keys) => tracing::info!(key_id = keys.current_id(), "templates are encrypted at rest"),
        None => tracing::warn!("no template key (FACEGATE_TEMPLATE_KEY_FILE): templates are stored UNENCRYPTED"),
    }
    let store = Store::connect(&args.database, keys).await.with_context(|| format!("cannot open the database {}", args.database))?;
    if config.api_keys.is_empty() {
        tracing::warn!(
            "no API keys configured (FACEGATE_API_KEYS_FILE, FACEGATE_API_KEYS): the API is OPEN to anyone who can reach {}",
            args.bind
        );
    } else {
        tracing::info!("{} API key(s) configured", config.api_keys.len());
    }
    tracing::info!(workers = config.workers, queue = config.queue_depth, enroll_queue = config.enroll_queue_depth, "bounded work pool");
    let state = AppState::new(Arc::new(pipeline), store.clone(), config);
    let loading = std::time::Instant::now();
    for (subject, why) in state.facegate().load_gallery().await? {
        tracing::error!(subject, "templates cannot be read; /identify refuses until the subject is erased: {why}");
    }
    let (subjects, templates) = state.facegate().gallery_size();
    tracing::info!(subjects, templates, load_ms = loading.elapsed().as_millis() as u64, backend = ?store.backend(), "identify gallery loaded");
    let listener = tokio::net::TcpListener::bind(&args.bind).await.with_context(|| format!("cannot listen on {}", args.bind))?;
    tracing::info!(
        max_connections = limits.max_connections,
        header_timeout_s = limits.header_timeout.as_secs_f64(),
        "listening on http://{}",
        listener.local_addr()?
    );
    match server::serve(listener, http::router(state.clone()), limits, shutdown_signal()).await {
        Stopped::Drained => tracing::info!("every connection finished"),
        Stopped::GraceExpired => {
            tracing::warn!(grace_s = limits.shutdown_grace.as_secs_f64(), "connections still open after the grace period were dropped")
        }
    }
    state.facegate().stop_following();
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
