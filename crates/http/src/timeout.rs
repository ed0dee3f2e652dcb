//! The whole-request deadline (504 `timeout`), which never tells a client that an enrolment
//! failed while its store commit goes on: a handler marks the point after which its request's
//! outcome is the store's ([`CommitPoint::pass`]); past it, the deadline waits for the real
//! answer instead of dropping the request. The layer sits inside the audit layer, so a request it
//! ends is audited with the outcome `timeout`.

use std::convert::Infallible;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use axum::extract::{FromRequestParts, Request, State};
use axum::http::request::Parts;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::problem::{Problem, ProblemKind};

/// A request's point of no return (a request extension, and an extractor for handlers).
#[derive(Debug, Clone, Default)]
pub struct CommitPoint(Arc<AtomicBool>);

impl CommitPoint {
    /// From here on the request changes stored data: its answer must be the store's.
    pub fn pass(&self) {
        self.0.store(true, Ordering::SeqCst);
    }

    fn passed(&self) -> bool {
        self.0.load(Ordering::SeqCst)
    }
}

impl<S: Send + Sync> FromRequestParts<S> for CommitPoint {
    type Rejection = Infallible;

    async fn from_request_parts(parts: &mut Parts, _state: &S) -> Result<CommitPoint, Infallible> {
        Ok(parts.extensions.get::<CommitPoint>().cloned().unwrap_or_default())
    }
}

/// The layer: the request within `timeout`, or 504 — unless it has passed its commit point, when
/// its own answer is awaited (the commit is bounded by the store's acquire and statement time).
pub async fn request_timeout(State(timeout): State<Duration>, mut request: Request, next: Next) -> Response {
    let commit = CommitPoint::default();
    request.extensions_mut().insert(commit.clone());
    let mut response = std::pin::pin!(next.run(request));
    match tokio::time::timeout(timeout, &mut response).await {
        Ok(response) => response,
        Err(_) if commit.passed() => response.await,
        Err(_) => Problem::new(ProblemKind::Timeout, format!("the request took longer than {} s", timeout.as_secs_f64())).into_response(),
    }
}
