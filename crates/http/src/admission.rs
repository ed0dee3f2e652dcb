//! Admission before work, by the bytes that arrive rather than the bytes declared. A request to a
//! route that runs photo work:
//!
//! 1. is refused from its head (413) when it declares a body over the size limit;
//! 2. takes a place among the bodies awaited or arriving from its client address
//!    (`--max-uploads-per-address`, waiting at most the admission wait, else 503), and becomes a
//!    holder that connection pressure may cut, slowest first ([`crate::shedding`], 503);
//! 3. waits at most [`FIRST_BYTE_WAIT`] for its body to begin, else 408 holding nothing;
//! 4. is refused (503 `overloaded`, `Retry-After`, its body unread) when its queue stays full for
//!    the admission wait — it only looks: no place is kept while the body arrives;
//! 5. receives its body ([`intake::receive`]): the body budget and its address's share of it
//!    charged as the bytes arrive (503 naming which is spent), a minimum rate over a moving window
//!    after a grace period and the body timeout (408), the body limit (413);
//! 6. only then takes its place in the work queue ([`WorkPool::admit_within`], the admission wait,
//!    else 503) and runs with the body in memory.
//!
//! So a client that trickles or stalls its body holds no queue place and budget only for what it
//! has sent, is cut after the grace period, and can open only so many such requests from one
//! address (a stalled head counts as one). A refusal answers at once and discards (never keeps)
//! what the client sends meanwhile, bounded, so that the answer is not lost to a connection
//! reset; a refusal under a flood waits the admission wait first, which keeps the successful
//! throughput near its peak when far more clients arrive than the workers can serve.

use std::net::SocketAddr;
use std::time::Duration;

use axum::body::Body;
use axum::extract::{ConnectInfo, Request, State};
use axum::http::{HeaderValue, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use futures_util::StreamExt as _;
use http_body_util::BodyExt;

use super::AppState;
use super::intake::{self, Cut, Pace};
use super::problem::{Problem, ProblemKind};
use super::shedding::Holders;
use facegate_service::WorkClass;

pub use super::intake::BodyBudget;

/// Longest a request head waits for the first bytes of its body before it is answered 408 (at
/// most the body timeout). Clients send the body right behind the head (or right after hyper's
/// `100 Continue`, which reading the body triggers), so a longer gap is a stalled client.
pub const FIRST_BYTE_WAIT: Duration = Duration::from_secs(5);

/// The body length the request head declares (`Content-Length`), if any.
fn declared_length(request: &Request) -> Option<u64> {
    request.headers().get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()).and_then(|v| v.trim().parse::<u64>().ok())
}

/// Most bytes of a refused request's body discarded so that its 503 arrives ...
const DISCARD_BYTES: usize = 1 << 20;
/// ... and for how long.
const DISCARD_TIME: Duration = Duration::from_secs(1);

/// The admission layer of one route: `class` says which queue it waits in.
pub async fn admit(State((state, class)): State<(AppState, WorkClass)>, request: Request, next: Next) -> Response {
    let config = &state.0.config;
    let limit = config.max_body_bytes;
    let declared = declared_length(&request);
    if declared.is_some_and(|n| n > limit as u64) {
        let detail = format!("the request body is declared larger than the {} MiB limit", limit as f64 / (1 << 20) as f64);
        return closing(refuse(request, Problem::new(ProblemKind::TooLarge, detail)));
    }
    // From here the request holds a connection for its body: it is counted against its address
    // and, under connection pressure, may be cut for the slowest.
    let address = request.extensions().get::<ConnectInfo<SocketAddr>>().map(|ConnectInfo(a)| a.ip());
    let holding = request.extensions().get::<Holders>().cloned().unwrap_or_default().hold();
    let budget = &state.0.body_budget;
    let slot = match address {
        Some(address) => match budget.arrival_slot(address, config.max_uploads_per_address, config.admission_wait).await {
            Some(slot) => Some(slot),
            None => {
                state.0.metrics.queue_rejections.inc();
                return refuse(request, too_many_arriving(config.max_uploads_per_address));
            }
        },
        None => None,
    };
    let request = match body_begun(request, FIRST_BYTE_WAIT.min(config.body_timeout), &holding.cut).await {
        Ok(request) => request,
        Err((request, Cut::Shed)) => return refuse_cut(Cut::Shed, request.into_body(), &state),
        Err((request, _)) => return refuse(request, body_timed_out()),
    };
    // Room in the queue, or the refusal before the body; the place itself is taken once the body
    // has arrived, so a slow body holds none.
    let pool = state.0.facegate.pool();
    if let Err(e) = pool.admit_within(class, config.admission_wait).await {
        return refuse(request, Problem::from(e));
    }
    let (parts, mut body) = request.into_parts();
    let pace = Pace { timeout: config.body_timeout, grace: config.body_grace, min_rate: config.min_body_rate };
    let share = budget.share(address);
    let received = intake::receive(&mut body, declared, limit, pace, budget, share, &holding.progress, &holding.cut).await;
    let (bytes, share) = match received {
        Ok(received) => (received.bytes, received.share),
        Err(cut) => return refuse_cut(cut, body, &state),
    };
    drop((slot, body, holding));
    let admission = match pool.admit_within(class, config.admission_wait).await {
        Ok(admission) => admission,
        Err(e) => return Problem::from(e).into_response(),
    };
    let response = admission.scope(next.run(Request::from_parts(parts, Body::from(bytes)))).await;
    // The body's share of the budget is held until the request is answered.
    drop(share);
    response
}

/// The answer to a body [`intake::receive`] cut short.
fn refuse_cut(cut: Cut, body: Body, state: &AppState) -> Response {
    let problem = match cut {
        Cut::TooLarge => {
            let limit = state.0.config.max_body_bytes as f64 / (1 << 20) as f64;
            let problem = Problem::new(ProblemKind::TooLarge, format!("the request body exceeds the {limit} MiB limit"));
            return closing(problem.into_response());
        }
        Cut::TimedOut => body_timed_out(),
        Cut::TooSlow => {
            let config = &state.0.config;
            Problem::new(
                ProblemKind::RequestTimeout,
                format!(
                    "the request body arrived slower than {} KiB/s after its first {} s (over the last {} s); send it faster or smaller",
                    config.min_body_rate as f64 / 1024.0,
                    config.body_grace.as_secs_f64(),
                    config.body_grace.as_secs_f64()
                ),
            )
        }
        Cut::BudgetSpent | Cut::AddressBudgetSpent | Cut::Shed => {
            state.0.metrics.queue_rejections.inc();
            let detail = match cut {
                Cut::BudgetSpent => format!(
                    "the {} MiB the server keeps for request bodies are in use by bodies arriving or waiting for their answers; retry shortly",
                    state.0.config.max_buffered_bytes >> 20
                ),
                Cut::AddressBudgetSpent => format!(
                    "this client address holds its share ({} MiB) of the memory the server keeps for request bodies; retry when its other requests are answered",
                    state.0.config.max_buffered_per_address >> 20
                ),
                _ => "the server is at its connection cap and this request's body arrived the slowest; retry shortly".to_string(),
            };
            return closing(refuse(Request::new(body), Problem::new(ProblemKind::Overloaded, detail)));
        }
        Cut::Broken(e) => return closing(Problem::malformed(format!("cannot read the body: {e}")).into_response()),
    };
    problem.into_response()
}

/// The 503 of a client address with as many bodies arriving as it may have.
fn too_many_arriving(cap: usize) -> Problem {
    Problem::new(
        ProblemKind::Overloaded,
        format!("this client address already has {cap} request bodies arriving, the most it may have at once; retry shortly"),
    )
}

/// `response` with `Connection: close`: the body was not read to its end, so this connection
/// cannot carry another request.
fn closing(mut response: Response) -> Response {
    response.headers_mut().insert(header::CONNECTION, HeaderValue::from_static("close"));
    response
}

/// `request` once the first frame of its body has arrived (or the body has ended), that frame put
/// back in front of the rest; the request itself, with why, when nothing arrived within `wait`
/// (`Cut::TimedOut`) or `cut` was notified first (`Cut::Shed`).
async fn body_begun(request: Request, wait: Duration, cut: &tokio::sync::Notify) -> Result<Request, (Request, Cut)> {
    let (parts, mut body) = request.into_parts();
    let first = tokio::select! {
        first = tokio::time::timeout(wait, body.frame()) => first,
        () = cut.notified() => return Err((Request::from_parts(parts, body), Cut::Shed)),
    };
    let first = match first {
        Ok(first) => first,
        Err(_) => return Err((Request::from_parts(parts, body), Cut::TimedOut)),
    };
    let Some(first) = first else { return Ok(Request::from_parts(parts, Body::empty())) };
    let first = first.map(|frame| frame.into_data().unwrap_or_default());
    let rest = body.into_data_stream();
    Ok(Request::from_parts(parts, Body::from_stream(futures_util::stream::once(async move { first }).chain(rest))))
}

/// Answer a refused request at once, and discard (never keep) what its client sends meanwhile, in
/// the background and bounded: a socket closed with unread bytes is reset, and the reset can reach
/// the client before the 503 does. A body within the bounds is read to its end, so the connection
/// can carry the client's next request.
fn refuse(request: Request, problem: Problem) -> Response {
    let mut body = request.into_body();
    tokio::spawn(tokio::time::timeout(DISCARD_TIME, async move {
        let mut discarded = 0;
        while let Some(Ok(frame)) = body.frame().await {
            discarded += frame.data_ref().map_or(0, |d| d.len());
            if discarded > DISCARD_BYTES {
                break;
            }
        }
    }));
    problem.into_response()
}

/// The 408 of a body that did not arrive in time.
pub fn body_timed_out() -> Problem {
    Problem::new(ProblemKind::RequestTimeout, "the request body did not arrive within the body timeout; send it faster or smaller")
}
