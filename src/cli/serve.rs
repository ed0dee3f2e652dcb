//! `facegate serve`: the HTTP service on axum and tokio, as the composition root
//! ([`crate::startup`]) builds it from the settings.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context;

use crate::config::{LogFormat, Settings, TraceSettings};
use crate::startup::Application;
use crate::telemetry::Traces;

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
    limit_malloc_arenas();
    let traces = Traces::start(&TraceSettings::from_env())?;
    install_subscriber(args.settings.log_format, traces.as_ref());
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().context("cannot start the async runtime")?;
    runtime.block_on(async {
        let app = Application::build(args.settings).await?;
        app.run_until_stopped(shutdown_signal()).await;
        anyhow::Ok(())
    })?;
    // Pool jobs still running after the grace period are not waited for.
    runtime.shutdown_timeout(Duration::from_secs(1));
    // Exports the spans still batched.
    drop(traces);
    Ok(ExitCode::SUCCESS)
}

/// glibc gives a thread that allocates while another holds the lock an arena of its own (up to 8
/// per core), and each arena keeps what its requests freed for its own later use: under 200
/// connections the process peaked at 221–264 MB with the default, 208–221 MB with two arenas and
/// 184 MB with one, at the same CPU per verification (`scripts/memory.sh`, `scripts/loadtest.sh`;
/// docs/speed.md "Memory of one replica"). So one arena, set before any thread starts, unless the
/// operator set glibc's own `MALLOC_ARENA_MAX` (which glibc then applies itself): a replica with
/// many workers may trade memory for less lock contention that way.
fn limit_malloc_arenas() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    if std::env::var_os("MALLOC_ARENA_MAX").is_none() {
        // SAFETY: mallopt only sets an allocator parameter; no other thread exists yet.
        unsafe {
            libc::mallopt(libc::M_ARENA_MAX, 1);
        }
    }
}

/// The log lines (`RUST_LOG`, default `info`; events only, so a line never carries its spans'
/// fields) and, when traces are exported, the spans.
fn install_subscriber(format: LogFormat, traces: Option<&Traces>) {
    use tracing_subscriber::layer::{Layer, SubscriberExt};
    use tracing_subscriber::util::SubscriberInitExt;
    let filter = tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into());
    let lines = match format {
        LogFormat::Text => tracing_subscriber::fmt::layer().boxed(),
        LogFormat::Json => tracing_subscriber::fmt::layer().json().boxed(),
    };
    let events = tracing_subscriber::filter::filter_fn(|metadata| metadata.is_event());
    let spans = traces.map(|t| t.layer().with_filter(tracing_subscriber::filter::LevelFilter::INFO));
    let _ = tracing_subscriber::registry().with(lines.with_filter(filter).with_filter(events)).with(spans).try_init();
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
