//! Reading requests, as axum extractors that reject with the app's [`Problem`]: [`Upload`] (photos
//! as `multipart/form-data` or base64 in JSON, and the subject id), [`Params`] (query parameters,
//! unknown ones refused), [`SubjectPath`] (a subject id in the path). Every way a request can be
//! malformed ends in a [`Problem`], never a panic.

use axum::body::Bytes;
use axum::extract::rejection::PathRejection;
use axum::extract::{FromRequest, FromRequestParts, Multipart, Path, Query, Request};
use axum::http::request::Parts;
use axum::http::{StatusCode, header};
use base64::Engine as _;
use serde::Deserialize;
use serde::de::DeserializeOwned;

use super::admission::{BodyDeadline, body_timed_out};
use super::problem::{Problem, ProblemKind};
use facegate_service::SubjectId;

/// A subject id of a request, parsed once ([`SubjectId::parse`]); an invalid one is malformed.
pub fn subject_id(id: &str) -> Result<SubjectId, Problem> {
    SubjectId::parse(id).map_err(|e| Problem::malformed(e.to_string()))
}

fn truncate(s: &str, n: usize) -> String {
    s.chars().take(n).collect()
}

/// A request's subject id (if any) and photos, as raw bytes in request order.
#[derive(Debug, Default)]
pub struct Upload {
    pub subject: Option<String>,
    pub images: Vec<Bytes>,
}

/// The JSON form of a request: base64 photos (a `data:` URL prefix is allowed).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonUpload {
    subject: Option<String>,
    image: Option<String>,
    images: Option<Vec<String>>,
}

impl<S: Send + Sync> FromRequest<S> for Upload {
    type Rejection = Problem;

    async fn from_request(request: Request, _state: &S) -> Result<Upload, Problem> {
        read_upload(request).await
    }
}

/// Query parameters of type `T` (which denies unknown fields), refused as malformed when unknown
/// or ill-typed.
#[derive(Debug)]
pub struct Params<T>(pub T);

impl<S: Send + Sync, T: DeserializeOwned> FromRequestParts<S> for Params<T> {
    type Rejection = Problem;

    async fn from_request_parts(parts: &mut Parts, _state: &S) -> Result<Params<T>, Problem> {
        Query::<T>::try_from_uri(&parts.uri)
            .map(|q| Params(q.0))
            .map_err(|e| Problem::malformed(format!("invalid query: {}", e.body_text())))
    }
}

/// The subject id of a `/subjects/{id}` path, parsed once.
#[derive(Debug)]
pub struct SubjectPath(pub SubjectId);

impl<S: Send + Sync> FromRequestParts<S> for SubjectPath {
    type Rejection = Problem;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<SubjectPath, Problem> {
        let path: Result<Path<String>, PathRejection> = Path::from_request_parts(parts, state).await;
        let Path(id) = path.map_err(|e| Problem::malformed(format!("invalid subject id in the path: {}", e.body_text())))?;
        subject_id(&id).map(SubjectPath)
    }
}

/// Read the body of `request` as multipart or JSON. The body limit (axum's `DefaultBodyLimit`)
/// applies while reading; exceeding it is a `too-large` problem. A body still arriving at the
/// admission layer's deadline ([`BodyDeadline`]) is a `request-timeout` problem (408).
pub async fn read_upload(request: Request) -> Result<Upload, Problem> {
    match request.extensions().get::<BodyDeadline>().copied() {
        Some(BodyDeadline(deadline)) => tokio::time::timeout_at(deadline, read_body(request)).await.map_err(|_| body_timed_out())?,
        None => read_body(request).await,
    }
}

async fn read_body(request: Request) -> Result<Upload, Problem> {
    let content_type = request.headers().get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("").to_ascii_lowercase();
    let essence = content_type.split(';').next().unwrap_or("").trim().to_string();
    if essence == "multipart/form-data" {
        read_multipart(request).await
    } else if essence == "application/json" || essence.ends_with("+json") {
        read_json(request).await
    } else {
        Err(Problem::new(
            ProblemKind::UnsupportedMediaType,
            format!(
                "Content-Type {:?} is not accepted: send multipart/form-data (fields subject, image) or application/json",
                truncate(&content_type, 80)
            ),
        ))
    }
}

async fn read_multipart(request: Request) -> Result<Upload, Problem> {
    let mut multipart = Multipart::from_request(request, &()).await.map_err(|e| Problem::malformed(e.body_text()))?;
    let mut upload = Upload::default();
    loop {
        let field = match multipart.next_field().await {
            Ok(Some(field)) => field,
            Ok(None) => break,
            Err(e) => return Err(multipart_problem(e)),
        };
        let name = field.name().unwrap_or("").to_string();
        match name.as_str() {
            "subject" => {
                if upload.subject.is_some() {
                    return Err(Problem::malformed("the field subject is given more than once"));
                }
                let text = field.text().await.map_err(multipart_problem)?;
                upload.subject = Some(text);
            }
            "image" => {
                let bytes = field.bytes().await.map_err(multipart_problem)?;
                upload.images.push(bytes);
            }
            other => {
                return Err(Problem::malformed(format!("unknown form field {:?}: the fields are subject and image", truncate(other, 40))));
            }
        }
    }
    Ok(upload)
}

fn multipart_problem(e: axum::extract::multipart::MultipartError) -> Problem {
    if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
        Problem::new(ProblemKind::TooLarge, format!("the request body exceeds the size limit: {}", e.body_text()))
    } else {
        Problem::malformed(format!("invalid multipart body: {}", e.body_text()))
    }
}

async fn read_json(request: Request) -> Result<Upload, Problem> {
    let body = Bytes::from_request(request, &()).await.map_err(|e| {
        if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
            Problem::new(ProblemKind::TooLarge, "the request body exceeds the size limit")
        } else {
            Problem::malformed(format!("cannot read the body: {}", e.body_text()))
        }
    })?;
    let json: JsonUpload = serde_json::from_slice(&body).map_err(|e| Problem::malformed(format!("invalid JSON body: {e}")))?;
    let mut upload = Upload { subject: json.subject, images: Vec::new() };
    let strings = json.image.into_iter().chain(json.images.into_iter().flatten());
    for (index, s) in strings.enumerate() {
        upload.images.push(decode_base64(&s).map_err(|p| p.for_image(index))?);
    }
    Ok(upload)
}

fn decode_base64(s: &str) -> Result<Bytes, Problem> {
    // Accept `data:image/jpeg;base64,...` as browsers produce it.
    let payload = if s.starts_with("data:") { s.split_once(',').map(|(_, p)| p).unwrap_or("") } else { s };
    let payload = payload.trim();
    if payload.is_empty() {
        return Err(Problem::malformed("the image is empty"));
    }
    // Padding optional and the unused bits of the last symbol ignored: what openapi.yaml's pattern
    // admits is exactly what decodes.
    const LENIENT: base64::engine::GeneralPurpose = base64::engine::GeneralPurpose::new(
        &base64::alphabet::STANDARD,
        base64::engine::GeneralPurposeConfig::new()
            .with_decode_padding_mode(base64::engine::DecodePaddingMode::Indifferent)
            .with_decode_allow_trailing_bits(true),
    );
    LENIENT.decode(payload).map(Bytes::from).map_err(|e| Problem::malformed(format!("the image is not valid base64: {e}")))
}

/// The requested false match rate, if any: a number in (0, 1).
pub fn validate_fmr(fmr: Option<f64>) -> Result<Option<f64>, Problem> {
    match fmr {
        Some(f) if !(f > 0.0 && f < 1.0) => Err(Problem::malformed(format!("fmr must be in (0, 1), got {f}"))),
        other => Ok(other),
    }
}

impl Upload {
    /// The subject id, required and valid.
    pub fn require_subject(&self) -> Result<SubjectId, Problem> {
        let subject = self.subject.as_deref().ok_or_else(|| Problem::malformed("the subject id is missing (field subject)"))?;
        subject_id(subject)
    }

    /// No subject id: the operation takes a photo only.
    pub fn refuse_subject(&self, why: &str) -> Result<(), Problem> {
        if self.subject.is_some() { Err(Problem::malformed(why.to_string())) } else { Ok(()) }
    }

    /// Exactly one photo.
    pub fn single_image(mut self) -> Result<Bytes, Problem> {
        match self.images.len() {
            1 => Ok(self.images.pop().expect("one image")),
            0 => Err(Problem::malformed("the photo is missing (field image)")),
            n => Err(Problem::malformed(format!("exactly one photo is expected, got {n}"))),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn subject_ids() {
        for ok in ["a", "person-01", "A.b_c-9", "...", ".a", &"x".repeat(128)] {
            assert_eq!(subject_id(ok).unwrap().as_str(), ok);
        }
        for bad in ["", "with space", " padded", "padded\n", "slash/x", "ünï", "semi;colon", ".", "..", &"x".repeat(129)] {
            assert_eq!(subject_id(bad).unwrap_err().kind, ProblemKind::MalformedRequest, "{bad}");
        }
    }

    #[test]
    fn base64_with_and_without_padding_or_data_url() {
        assert_eq!(&decode_base64("aGVsbG8=").unwrap()[..], b"hello");
        assert_eq!(&decode_base64("aGVsbG8").unwrap()[..], b"hello");
        assert_eq!(&decode_base64("data:image/png;base64,aGVsbG8=").unwrap()[..], b"hello");
        assert_eq!(&decode_base64("00").unwrap()[..], &[0xd3]);
        assert!(decode_base64("not base64!").is_err() && decode_base64("A").is_err());
        assert!(decode_base64("").is_err() && decode_base64("data:image/png;base64,").is_err());
    }

    #[test]
    fn fmr_range() {
        assert!(validate_fmr(Some(1e-3)).is_ok());
        assert!(validate_fmr(None).unwrap().is_none());
        for bad in [0.0, 1.0, -1.0, f64::NAN] {
            assert!(validate_fmr(Some(bad)).is_err());
        }
    }
}
