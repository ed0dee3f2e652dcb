//! The connection loop: hyper's HTTP/1.1 server under the axum router, with the limits a hostile
//! client would otherwise exploit and that `axum::serve` does not expose.
//!
//! - A connection cap: a permit is taken before `accept`, so beyond the cap new connections wait
//!   in the kernel's backlog instead of costing memory here.
//! - A share of it per client address (IPv6: its /64): a connection beyond its address's share
//!   is answered a canned 503 problem and closed before any of its request is read, so one client
//!   cannot hold the connections every other client needs.
//! - Under pressure (fewer than [`shedding::reserve`] connections free), the requests whose
//!   bodies arrive slowest are cut first ([`shedding`]), so connections held by stalled or
//!   crawling uploads from many addresses turn over.
//! - A header-read timeout: a connection that has not sent a complete request head within it is
//!   closed. Hyper starts this timer whenever it waits for a request head, so it also bounds how
//!   long an idle keep-alive connection stays open.
//! - Hyper's own hard limits (head buffer, header count) set above the router's
//!   (`limits::check_head`), so the client gets problem+json for what the router checks; what
//!   hyper refuses itself (a head over its buffer, a malformed request line) it answers with an
//!   empty body, which hyper offers no way to fill: `head_errors::ProblemHeads` replaces that
//!   answer with problem+json on its way out.
//! - The client's address on each request (`ConnectInfo<SocketAddr>`), which admission counts
//!   arriving bodies by, and the registry of body holders ([`shedding::Holders`]).
//! - Graceful shutdown: on the signal, stop accepting, let in-flight requests finish, and give up
//!   on connections still open after the grace period (idle keep-alives, stalled uploads).

use std::convert::Infallible;
use std::future::Future;
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use axum::extract::ConnectInfo;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::server::graceful::GracefulShutdown;
use tokio::io::AsyncWriteExt as _;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;
use tower_service::Service as _;

use super::head_errors::ProblemHeads;
use super::intake::{AddressTally, client_key};
use super::problem::{Problem, ProblemKind};
use super::shedding::{self, Holders};

/// Connection-level limits (made from `config::Settings`, where the defaults are).
#[derive(Debug, Clone, Copy)]
pub struct ServerLimits {
    /// Most connections open at once.
    pub max_connections: usize,
    /// Most of them from one client address (IPv6: its /64).
    pub max_connections_per_address: usize,
    /// Time to receive a complete request head, and most time a keep-alive connection stays idle.
    pub header_timeout: Duration,
    /// After the shutdown signal, how long in-flight connections may take before they are dropped.
    pub shutdown_grace: Duration,
}

/// Hyper's header-count limit: above the router's own (`limits::MAX_HEADERS`), so that the
/// router, which answers with problem+json, is the one that refuses.
const HYPER_MAX_HEADERS: usize = 2 * super::limits::MAX_HEADERS;
/// Hyper's read buffer, which bounds a request head: above the router's URI and header limits.
const HYPER_MAX_BUF: usize = 4 * (super::limits::MAX_URI_BYTES + super::limits::MAX_HEADER_BYTES);

/// A connection accepted while half the connection cap is in use gets this long
/// (or the header timeout, if shorter) for each request head and between requests: a flood of
/// half-open or idle connections then turns over within it, so a real client (a `/health` probe)
/// waits about this long for a place instead of the whole header timeout.
const PRESSED_HEADER_TIMEOUT: Duration = Duration::from_secs(1);

/// `router` as hyper's service of one connection, each request carrying the client's address and
/// the body holders' registry.
fn with_peer(
    router: Router,
    peer: SocketAddr,
    holders: Holders,
) -> impl hyper::service::Service<hyper::Request<Incoming>, Response = axum::response::Response, Error = Infallible, Future: Send> {
    hyper::service::service_fn(move |mut request: hyper::Request<Incoming>| {
        request.extensions_mut().insert(ConnectInfo(peer));
        request.extensions_mut().insert(holders.clone());
        router.clone().call(request.map(axum::body::Body::new))
    })
}

/// A connection counted against its address until dropped.
struct Counted {
    per_address: AddressTally,
    key: IpAddr,
}

impl Drop for Counted {
    fn drop(&mut self) {
        self.per_address.sub(self.key, 1);
    }
}

/// A count for a new connection from `peer`, unless its address has `cap` open.
fn admit_connection(per_address: &AddressTally, peer: IpAddr, cap: usize) -> Option<Counted> {
    let key = client_key(peer);
    per_address.try_add(key, 1, cap).then(|| Counted { per_address: per_address.clone(), key })
}

/// The answer to a connection beyond its address's share, written before any request is read.
fn over_share(cap: usize) -> Vec<u8> {
    let detail =
        format!("this client address already has {cap} connections open, the most one address may have; reuse them or retry shortly");
    let body = Problem::new(ProblemKind::Overloaded, detail).json();
    let head = format!(
        "HTTP/1.1 503 Service Unavailable\r\ncontent-type: application/problem+json\r\ncache-control: no-store\r\nretry-after: 1\r\nconnection: close\r\ncontent-length: {}\r\n\r\n",
        body.len()
    );
    [head.into_bytes(), body].concat()
}

/// Longest a refused connection is given to take its 503.
const REFUSAL_WRITE: Duration = Duration::from_secs(1);

/// Answer `stream` with `answer` and close it, in the background.
fn refuse_connection(mut stream: TcpStream, answer: Vec<u8>) {
    tokio::spawn(async move {
        let _ = tokio::time::timeout(REFUSAL_WRITE, async {
            stream.write_all(&answer).await?;
            stream.shutdown().await
        })
        .await;
    });
}

/// How the server stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stopped {
    /// Every connection finished within the grace period.
    Drained,
    /// The grace period ended with connections still open; they were dropped.
    GraceExpired,
}

/// Serve `router` on `listener` until `shutdown` completes, then drain within the grace period.
pub async fn serve(listener: TcpListener, router: Router, limits: ServerLimits, shutdown: impl Future<Output = ()>) -> Stopped {
    let connections = Arc::new(Semaphore::new(limits.max_connections.max(1)));
    let graceful = GracefulShutdown::new();
    let mut builder = hyper::server::conn::http1::Builder::new();
    builder.timer(TokioTimer::new()).header_read_timeout(limits.header_timeout).max_headers(HYPER_MAX_HEADERS).max_buf_size(HYPER_MAX_BUF);
    let mut pressed = builder.clone();
    pressed.header_read_timeout(limits.header_timeout.min(PRESSED_HEADER_TIMEOUT));
    let pressure_below = limits.max_connections.max(1) / 2;
    let (holders, per_address) = (Holders::default(), AddressTally::default());
    let shedder =
        tokio::spawn(shedding::shed_under_pressure(connections.clone(), holders.clone(), shedding::reserve(limits.max_connections)));
    tokio::pin!(shutdown);
    loop {
        let permit = tokio::select! {
            permit = connections.clone().acquire_owned() => permit.expect("the connection semaphore is never closed"),
            _ = &mut shutdown => break,
        };
        let (stream, peer) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                Err(e) => {
                    // Out of file descriptors and the like: wait a little rather than spin.
                    tracing::warn!("accept failed: {e}");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
            _ = &mut shutdown => break,
        };
        let _ = stream.set_nodelay(true);
        let Some(counted) = admit_connection(&per_address, peer.ip(), limits.max_connections_per_address.max(1)) else {
            refuse_connection(stream, over_share(limits.max_connections_per_address));
            drop(permit);
            continue;
        };
        let service = with_peer(router.clone(), peer, holders.clone());
        let builder = if connections.available_permits() < pressure_below { &pressed } else { &builder };
        let connection = graceful.watch(builder.serve_connection(TokioIo::new(ProblemHeads::new(stream)), service));
        tokio::spawn(async move {
            // Errors here are the client's (reset, timeout, malformed head): nothing to report.
            let _ = connection.await;
            drop((permit, counted));
        });
    }
    shedder.abort();
    drop(listener);
    tokio::select! {
        _ = graceful.shutdown() => Stopped::Drained,
        _ = tokio::time::sleep(limits.shutdown_grace) => Stopped::GraceExpired,
    }
}
