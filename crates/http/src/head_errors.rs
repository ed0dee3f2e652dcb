//! Problem+json for the request heads hyper refuses itself.
//!
//! Hyper parses the request head before any service sees it. A head it cannot parse (a malformed
//! request line or header), one over its read buffer (414 for a long target, else 431) or with
//! more headers than it allows (431) is answered by hyper alone, with an empty body, and the
//! connection closed; no hook lets a service fill that answer. The router's own head limits
//! (`limits::check_head`) sit below hyper's, so most oversized heads get the router's
//! problem+json; this writer covers the rest. It watches what hyper writes to the connection and,
//! when that is one of hyper's bodiless error heads, sends the same status with a problem+json
//! body instead. Those heads are recognised exactly: `connection: close` and `content-length: 0`
//! right after a 400, 414 or 431 status line, which no response of the router has (each of its
//! 400, 414 and 431 answers carries a problem+json body).

use std::io;
use std::pin::Pin;
use std::task::{Context, Poll, ready};

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};

use super::problem::{Problem, ProblemKind};

/// The connection's byte stream, with hyper's bodiless error heads replaced (see the module).
pub struct ProblemHeads<S> {
    inner: S,
    replacing: Option<Replacement>,
}

/// A replacement being written: its bytes, how many are written, and how many bytes of hyper's
/// buffer it stands for (reported as written once it is all out).
struct Replacement {
    bytes: Vec<u8>,
    written: usize,
    covers: usize,
}

impl<S> ProblemHeads<S> {
    pub fn new(inner: S) -> ProblemHeads<S> {
        ProblemHeads { inner, replacing: None }
    }
}

/// The problem hyper's bodiless answer with this status stands for.
fn problem_for(status: &[u8]) -> Option<Problem> {
    Some(match status {
        b"400" => Problem::malformed("the request head could not be parsed (request line or header syntax)"),
        b"414" => Problem::new(ProblemKind::UriTooLong, "the request target is longer than the server reads"),
        b"431" => Problem::new(ProblemKind::HeadersTooLarge, "the request head has more or longer headers than the server reads"),
        _ => return None,
    })
}

/// When `written` is exactly one of hyper's bodiless error heads, the whole answer to send instead:
/// the same status line and headers, `content-length: 0` replaced by the problem+json body's.
pub fn replacement_for(written: &[u8]) -> Option<Vec<u8>> {
    let rest = written.strip_prefix(b"HTTP/1.1 ")?;
    let problem = problem_for(rest.get(..3)?)?;
    let line_end = rest.windows(2).position(|w| w == b"\r\n")?;
    let headers = &rest[line_end + 2..];
    // One whole head and nothing after it.
    let head_end = headers.windows(4).position(|w| w == b"\r\n\r\n")?;
    if head_end + 4 != headers.len() {
        return None;
    }
    let after = headers.strip_prefix(b"connection: close\r\ncontent-length: 0\r\n".as_slice())?;
    let body = problem.json();
    let mut out = Vec::with_capacity(written.len() + body.len() + 96);
    out.extend_from_slice(&written[..9 + line_end + 2]);
    out.extend_from_slice(b"connection: close\r\ncontent-type: application/problem+json\r\ncache-control: no-store\r\n");
    out.extend_from_slice(format!("content-length: {}\r\n", body.len()).as_bytes());
    out.extend_from_slice(after);
    out.extend_from_slice(&body);
    Some(out)
}

impl<S: AsyncRead + Unpin> AsyncRead for ProblemHeads<S> {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl<S: AsyncWrite + Unpin> AsyncWrite for ProblemHeads<S> {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        let this = &mut *self;
        if this.replacing.is_none() {
            match replacement_for(buf) {
                Some(bytes) => this.replacing = Some(Replacement { bytes, written: 0, covers: buf.len() }),
                None => return Pin::new(&mut this.inner).poll_write(cx, buf),
            }
        }
        let replacement = this.replacing.as_mut().expect("set above");
        while replacement.written < replacement.bytes.len() {
            match ready!(Pin::new(&mut this.inner).poll_write(cx, &replacement.bytes[replacement.written..])) {
                Ok(0) => return Poll::Ready(Err(io::ErrorKind::WriteZero.into())),
                Ok(n) => replacement.written += n,
                Err(e) => return Poll::Ready(Err(e)),
            }
        }
        let covers = replacement.covers;
        this.replacing = None;
        Poll::Ready(Ok(covers))
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }

    // Not vectored: hyper then writes each answer's head as one buffer, which is what is matched.
    fn is_write_vectored(&self) -> bool {
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_hypers_bodiless_error_heads_are_replaced() {
        let hyper = b"HTTP/1.1 400 Bad Request\r\nconnection: close\r\ncontent-length: 0\r\ndate: Tue, 24 Nov 2026 12:57:45 GMT\r\n\r\n";
        let out = String::from_utf8(replacement_for(hyper).unwrap()).unwrap();
        let (head, body) = out.split_once("\r\n\r\n").unwrap();
        assert!(head.starts_with("HTTP/1.1 400 Bad Request\r\n") && head.ends_with("date: Tue, 24 Nov 2026 12:57:45 GMT"), "{head}");
        assert!(head.contains("content-type: application/problem+json") && head.contains(&format!("content-length: {}", body.len())));
        let json: serde_json::Value = serde_json::from_str(body).unwrap();
        assert_eq!(json["type"], ProblemKind::MalformedRequest.type_uri());
        for (status, kind) in
            [("414 URI Too Long", ProblemKind::UriTooLong), ("431 Request Header Fields Too Large", ProblemKind::HeadersTooLarge)]
        {
            let head = format!("HTTP/1.1 {status}\r\nconnection: close\r\ncontent-length: 0\r\ndate: x\r\n\r\n");
            let out = String::from_utf8(replacement_for(head.as_bytes()).unwrap()).unwrap();
            assert!(out.contains(&kind.type_uri()), "{out}");
        }
        // Answers of the router (a body, or another status) and partial heads pass untouched.
        for other in [
            &b"HTTP/1.1 400 Bad Request\r\ncontent-type: application/problem+json\r\ncontent-length: 10\r\n\r\n"[..],
            b"HTTP/1.1 200 OK\r\nconnection: close\r\ncontent-length: 0\r\n\r\n",
            b"HTTP/1.1 400 Bad Request\r\nconnection: close\r\ncontent-length: 0\r\n",
            b"HTTP/1.1 400 Bad Request\r\nconnection: close\r\ncontent-length: 0\r\n\r\nHTTP/1.1 200 OK\r\n\r\n",
        ] {
            assert!(replacement_for(other).is_none(), "{}", String::from_utf8_lossy(other));
        }
    }
}
