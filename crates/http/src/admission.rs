//! Admission before work: a request to a route that runs photo work takes its place in the work
//! queue ([`WorkPool::admit`]) and its share of the body-memory budget once its body has begun
//! to arrive, and before the body is read on. A head that declares a body over the size limit is
//! refused at once (413), and a head whose body does not begin within [`FIRST_BYTE_WAIT`] gets 408
//! holding nothing: a client that sends request heads and stalls cannot take the queue's places
//! or the body budget from others. A refusal (503 `overloaded`, `Retry-After`) therefore costs no body buffering,
//! no multipart parse and no database query (what the client already sent is discarded, bounded,
//! so that the answer is not lost to a connection reset), which keeps the successful throughput
//! near its peak when far more clients arrive than the workers can serve.
//!
//! The body must then arrive within the body timeout (counted from admission): a stalled upload
//! is the client's fault and is answered 408 `request-timeout` ([`BodyDeadline`], applied where
//! the body is read, `input::read_upload`).

use std::sync::Arc;
use std::time::Duration;

use axum::body::Body;
use axum::extract::{Request, State};
use axum::http::header;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use futures_util::StreamExt as _;
use http_body_util::BodyExt;
use tokio::sync::Semaphore;
use tokio::time::Instant;

use super::AppState;
use super::problem::{Problem, ProblemKind};
use facegate_service::{PoolError, WorkClass};

/// Longest a request head waits for the first bytes of its body before it is answered 408 (at
/// most the body timeout). Clients send the body right behind the head (or right after hyper's
/// `100 Continue`, which reading the body triggers), so a longer gap is a stalled client.
pub const FIRST_BYTE_WAIT: Duration = Duration::from_secs(5);

/// The instant by which the request body must have been read (a request extension).
#[derive(Debug, Clone, Copy)]
pub struct BodyDeadline(pub Instant);

/// Bytes of request bodies held in memory at once, in KiB permits (a semaphore counts `u32`s).
#[derive(Debug, Clone)]
pub struct BodyBudget {
    kib: Arc<Semaphore>,
    max_body_bytes: usize,
}

impl BodyBudget {
    pub fn new(max_buffered_bytes: usize, max_body_bytes: usize) -> BodyBudget {
        BodyBudget { kib: Arc::new(Semaphore::new(kib(max_buffered_bytes).min(Semaphore::MAX_PERMITS))), max_body_bytes }
    }

    /// The share a request needs: its declared length, or the body limit when it declares none.
    fn take(&self, request: &Request) -> Option<tokio::sync::OwnedSemaphorePermit> {
        let declared = declared_length(request).map_or(self.max_body_bytes, |n| usize::try_from(n).unwrap_or(usize::MAX));
        let bytes = declared.min(self.max_body_bytes);
        let share = u32::try_from(kib(bytes)).unwrap_or(u32::MAX);
        self.kib.clone().try_acquire_many_owned(share).ok()
    }
}

/// The body length the request head declares (`Content-Length`), if any.
fn declared_length(request: &Request) -> Option<u64> {
    request.headers().get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()).and_then(|v| v.trim().parse::<u64>().ok())
}

fn kib(bytes: usize) -> usize {
    bytes.div_ceil(1024)
}

/// Most bytes of a refused request's body discarded so that its 503 arrives ...
const DISCARD_BYTES: usize = 1 << 20;
/// ... and for how long.
const DISCARD_TIME: Duration = Duration::from_secs(1);

/// The admission layer of one route: `class` says which queue it waits in.
pub async fn admit(State((state, class)): State<(AppState, WorkClass)>, request: Request, next: Next) -> Response {
    let limit = state.0.config.max_body_bytes;
    if declared_length(&request).is_some_and(|n| n > limit as u64) {
        let detail = format!("the request body is declared larger than the {} MiB limit", limit as f64 / (1 << 20) as f64);
        let mut response = refuse(request, Problem::new(ProblemKind::TooLarge, detail));
        // The body is not read: this connection cannot carry another request.
        response.headers_mut().insert(header::CONNECTION, header::HeaderValue::from_static("close"));
        return response;
    }
    let mut request = match body_begun(request, FIRST_BYTE_WAIT.min(state.0.config.body_timeout)).await {
        Ok(request) => request,
        Err(request) => return refuse(request, body_timed_out()),
    };
    let admission = match state.0.facegate.pool().admit_within(class, state.0.config.admission_wait).await {
        Ok(admission) => admission,
        Err(e) => return refuse(request, Problem::from(e)),
    };
    let Some(body_share) = state.0.body_budget.take(&request) else {
        state.0.metrics.queue_rejections.inc();
        return refuse(request, Problem::new(ProblemKind::Overloaded, PoolError::Overloaded.to_string()));
    };
    request.extensions_mut().insert(BodyDeadline(Instant::now() + state.0.config.body_timeout));
    let response = admission.scope(next.run(request)).await;
    drop(body_share);
    response
}

/// `request` once the first frame of its body has arrived (or the body has ended), that frame put
/// back in front of the rest; the request itself when nothing arrived within `wait`.
async fn body_begun(request: Request, wait: Duration) -> Result<Request, Request> {
    let (parts, mut body) = request.into_parts();
    let first = match tokio::time::timeout(wait, body.frame()).await {
        Ok(first) => first,
        Err(_) => return Err(Request::from_parts(parts, body)),
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
