//! What every request and response goes through first and last: the request head's limits
//! (answered with problem+json, below hyper's own limits: what hyper refuses itself gets its
//! problem+json body from `head_errors`), the
//! request id, and `Cache-Control: no-store` (answers carry biometric decisions and subject ids,
//! which no cache on the way should keep).

use axum::extract::Request;
use axum::http::{HeaderValue, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::problem::{Problem, ProblemKind};

/// Longest request target (path and query) read, in bytes; longer → 414 `uri-too-long`.
pub const MAX_URI_BYTES: usize = 8 * 1024;
/// Most request headers; more → 431 `headers-too-large`.
pub const MAX_HEADERS: usize = 64;
/// Most bytes of request header names and values together; more → 431 `headers-too-large`.
pub const MAX_HEADER_BYTES: usize = 16 * 1024;

/// The header a request id is read from and returned in.
pub const REQUEST_ID_HEADER: &str = "x-request-id";
/// Longest client request id kept; a longer or non-printable one is replaced by a generated id.
const MAX_REQUEST_ID: usize = 128;

/// The id of one request: the client's `X-Request-Id` when it is 1–128 printable ASCII
/// characters, else a generated one. Logged in the audit line and returned in the response.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RequestId(pub String);

impl RequestId {
    fn of(request: &Request) -> RequestId {
        let given = request
            .headers()
            .get(REQUEST_ID_HEADER)
            .and_then(|v| v.to_str().ok())
            .filter(|v| (1..=MAX_REQUEST_ID).contains(&v.len()) && v.bytes().all(|b| b.is_ascii_graphic()));
        RequestId(given.map(str::to_string).unwrap_or_else(|| format!("{:032x}", rand::random::<u128>())))
    }
}

/// Problem+json for a request head over the router's limits, if it is.
fn check_head(request: &Request) -> Option<Problem> {
    let uri = request.uri().path_and_query().map(|pq| pq.as_str().len()).unwrap_or(0);
    if uri > MAX_URI_BYTES {
        return Some(Problem::new(
            ProblemKind::UriTooLong,
            format!("the request target has {uri} bytes; at most {MAX_URI_BYTES} are read"),
        ));
    }
    let headers = request.headers();
    if headers.len() > MAX_HEADERS {
        return Some(Problem::new(
            ProblemKind::HeadersTooLarge,
            format!("the request has {} headers; at most {MAX_HEADERS} are read", headers.len()),
        ));
    }
    let bytes: usize = headers.iter().map(|(name, value)| name.as_str().len() + value.len()).sum();
    if bytes > MAX_HEADER_BYTES {
        return Some(Problem::new(
            ProblemKind::HeadersTooLarge,
            format!("the request headers have {bytes} bytes; at most {MAX_HEADER_BYTES} are read"),
        ));
    }
    None
}

/// The outermost layer: head limits, request id, `Cache-Control: no-store`.
pub async fn edge(mut request: Request, next: Next) -> Response {
    let id = RequestId::of(&request);
    let mut response = match check_head(&request) {
        Some(problem) => problem.into_response(),
        None => {
            request.extensions_mut().insert(id.clone());
            next.run(request).await
        }
    };
    let headers = response.headers_mut();
    if let Ok(value) = HeaderValue::from_str(&id.0) {
        headers.insert(REQUEST_ID_HEADER, value);
    }
    headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    response
}
