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
use crate::service::site::SiteStatus;
use crate::service::{Facegate, LivenessPolicy, Matcher};
use crate::store::{KeyCheck, Store};

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

/// The site calibration in use, and the default operating point it gives against the model's.
fn log_site_calibration(facegate: &Facegate, status: &SiteStatus) {
    let fmr = crate::recognize::DEFAULT_FMR;
    let matcher = facegate.matcher();
    let model = matcher.inner.operating_point(fmr, 1).threshold;
    match status {
        SiteStatus::InUse(site) => tracing::info!(
            subjects = site.subjects,
            impostor_pairs = site.impostor_pairs,
            duplicate_pairs_left_out = site.duplicate_pairs_left_out,
            model_threshold = model,
            threshold = matcher.operating_point(fmr, 1).threshold,
            "site calibration (facegate calibrate): thresholds at FMR {fmr:e} raised to the deployment's own impostors where they are higher"
        ),
        SiteStatus::NotForThisMatcher => {
            tracing::warn!("the site calibration is for cosine-scored recognizers; the classical one keeps its own thresholds")
        }
        SiteStatus::None => tracing::info!(threshold = model, "no site calibration (facegate calibrate): the model's thresholds"),
    }
}

async fn serve(args: Settings, config: ApiConfig, limits: ServerLimits) -> anyhow::Result<()> {
    // The store and its keys first: a database the keys cannot read stops the start-up before the
    // models are loaded.
    let keys = args.template_key.key_ring()?;
    match &keys {
        Some(keys) => tracing::info!(key_id = keys.current_id(), "templates are encrypted at rest"),
        None => tracing::warn!("no template key (FACEGATE_TEMPLATE_KEY_FILE): templates are stored UNENCRYPTED"),
    }
    let store = Store::connect(&args.database, keys).await.with_context(|| format!("cannot open the database {}", args.database))?;
    if let Err(refused) = template_keys_open_the_store(&store, &args).await {
        store.close().await;
        return Err(refused);
    }
    if config.api_keys.is_empty() {
        tracing::warn!(
            "no API keys configured (FACEGATE_API_KEYS_FILE, FACEGATE_API_KEYS): the API is OPEN to anyone who can reach {}",
            args.bind
        );
    } else {
        tracing::info!("{} API key(s) configured", config.api_keys.len());
    }
    let pipeline_config = args.pipeline_config();
    tracing::info!(models = %pipeline_config.models_dir.display(), "loading the face pipeline");
    let loaded = tokio::task::spawn_blocking(move || Pipeline::load(&pipeline_config)).await?;
    // The liveness settings shape the loaded pipeline: off drops the model, a threshold replaces its own.
    let configured = loaded.context("cannot load the face pipeline models").and_then(|mut pipeline| {
        args.configure_liveness(&mut pipeline)?;
        Ok(pipeline)
    });
    let pipeline = match configured {
        Ok(pipeline) => pipeline,
        Err(e) => {
            store.close().await;
            return Err(e);
        }
    };
    tracing::info!(model_version = pipeline.recognizer.model_version(), with_3dmm = pipeline.face_model.is_some(), "pipeline loaded");
    match &pipeline.liveness {
        Some(model) => tracing::info!(
            policy = ?config.liveness,
            model = model.name,
            threshold = model.threshold,
            operating_point = model.operating_point,
            "liveness (presentation-attack detection)"
        ),
        None if config.liveness == LivenessPolicy::Off => tracing::info!("liveness off: no face is checked for a presentation attack"),
        None => tracing::warn!("no liveness model ({}): faces report no liveness", crate::liveness::FILE),
    }
    tracing::info!(workers = config.workers, queue = config.queue_depth, enroll_queue = config.enroll_queue_depth, "bounded work pool");
    let state = AppState::new(Arc::new(pipeline), store.clone(), config);
    let site = state.facegate().load_site_calibration().await.context("cannot read the site calibration")?;
    log_site_calibration(state.facegate(), &site);
    let loading = std::time::Instant::now();
    for (subject, why) in state.facegate().load_gallery().await? {
        tracing::error!(subject, "templates cannot be read; /identify refuses until the subject is erased: {why}");
    }
    let (subjects, templates) = state.facegate().gallery_size();
    tracing::info!(subjects, templates, load_ms = loading.elapsed().as_millis() as u64, backend = ?store.backend(), "identify gallery loaded");
    let (enrolled, _) = store.counts().await.context("cannot count the enrolled subjects")?;
    if (subjects as u64) < enrolled {
        tracing::warn!(
            subjects_current_model = subjects,
            subjects = enrolled,
            model_version = state.facegate().model_version(),
            "{} subject(s) have no template of the current model version: verify answers model-mismatch and identify does not search them until they enrol again",
            enrolled - subjects as u64
        );
    }
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

/// Refuse to serve a database whose sealed templates the configured template keys cannot open: with
/// no key, every sealed subject would answer 500 and new enrolments would be stored unencrypted
/// beside them; with the wrong key, every sealed subject would answer 500. Logs what the keys
/// leave to do (plain subjects to seal, subjects under an older key to re-wrap).
async fn template_keys_open_the_store(store: &Store, args: &Settings) -> anyhow::Result<()> {
    let key_file = || args.template_key.template_key_file.as_ref().map_or_else(String::new, |p| format!(" {}", p.display()));
    match store.check_template_keys().await.context("cannot check the database's sealed templates")? {
        KeyCheck::NothingSealed => {}
        KeyCheck::Opens { sealed_subjects } => tracing::info!(sealed_subjects, "the template key opens the sealed subjects"),
        KeyCheck::NoKey { sealed_subjects } => anyhow::bail!(
            "the database holds {sealed_subjects} subject(s) whose templates are sealed with a template key, but no template key \
             is configured: start with --template-key-file (FACEGATE_TEMPLATE_KEY_FILE) naming the key file that sealed them \
             (without it every sealed subject would answer 500 and new enrolments would be stored unencrypted)"
        ),
        KeyCheck::CannotOpen { key_id, subjects, reason } => anyhow::bail!(
            "the template key file{} (--template-key-file, FACEGATE_TEMPLATE_KEY_FILE) cannot open the {subjects} subject(s) sealed \
             under template key {key_id}: {reason}; give the key file that holds that key (an older key stays below the current \
             one until `facegate rekey` has re-wrapped every subject)",
            key_file()
        ),
    }
    if store.encrypts() {
        let counts = store.sealing_counts().await?;
        if counts.plain > 0 {
            tracing::warn!(
                subjects = counts.plain,
                "subjects enrolled before the template key are still stored plain: run `facegate rekey`"
            );
        }
        if counts.other_keys > 0 {
            tracing::warn!(
                subjects = counts.other_keys,
                "subjects are sealed under an older template key: run `facegate rekey` before removing it from the key file"
            );
        }
    }
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
