//! Reading requests, as axum extractors that reject with the app's [`Problem`]: [`Upload`] (photos
//! as `multipart/form-data` or base64 in JSON, and the subject id), [`Params`] (query parameters,
//! unknown ones refused), [`SubjectPath`] (a subject id in the path). Every way a request can be
//! malformed ends in a [`Problem`], never a panic.
//!
//! The photo routes' bodies have arrived whole before the extractors run (`admission::admit`
//! received them at their pace and within the body budget); reading them here is parsing. Both
//! forms count the photos as they go and refuse the request at the first one past the most any
//! operation takes, before it is kept: the `image` parts of a multipart body, the `images` entries
//! of a JSON one ([`json`]), and the frames past [`MAX_CAPTURE_FRAMES`]; so a body of thousands of tiny
//! photos costs no memory beyond the body itself.

use axum::body::Bytes;
use axum::extract::rejection::PathRejection;
use axum::extract::{FromRequest, FromRequestParts, Multipart, Path, Query, Request};
use axum::http::request::Parts;
use axum::http::{StatusCode, header};
use serde::de::DeserializeOwned;

use super::AppState;
use super::problem::{Problem, ProblemKind};
use facegate_core::SubjectId;
use facegate_service::MAX_CAPTURE_FRAMES;

mod json;

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
    /// Further frames of the probe's capture (`frame` parts, `frames` entries), at most
    /// [`MAX_CAPTURE_FRAMES`] (a challenge's bursts); only `/verify` takes them.
    pub frames: Vec<Bytes>,
    /// The 0-based challenge step of each frame (`frame_steps`: multipart, comma-separated; JSON,
    /// an array); only `/verify` with a challenge takes it.
    pub frame_steps: Option<Vec<usize>>,
    /// The liveness challenge the frames answer (`challenge`); only `/verify` takes one.
    pub challenge: Option<String>,
}

impl FromRequest<AppState> for Upload {
    type Rejection = Problem;

    /// The most photos any operation takes is an enrolment's (`ApiConfig::max_images`): a body
    /// with more is refused while it is parsed.
    async fn from_request(request: Request, state: &AppState) -> Result<Upload, Problem> {
        read_upload(request, state.max_images().max(1)).await
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
/// applies while reading; exceeding it is a `too-large` problem. A body with more than
/// `max_photos` photos (multipart `image` parts, JSON `images` entries), or more than
/// [`MAX_CAPTURE_FRAMES`] frames, is malformed, refused as soon as the read reaches the first one too many.
pub async fn read_upload(request: Request, max_photos: usize) -> Result<Upload, Problem> {
    let content_type = request.headers().get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("").to_ascii_lowercase();
    let essence = content_type.split(';').next().unwrap_or("").trim().to_string();
    if essence == "multipart/form-data" {
        read_multipart(request, max_photos).await
    } else if essence == "application/json" || essence.ends_with("+json") {
        json::read_json(request, max_photos).await
    } else {
        Err(Problem::new(
            ProblemKind::UnsupportedMediaType,
            format!(
                "Content-Type {:?} is not accepted: send multipart/form-data (fields subject, image, frame, challenge) or application/json",
                truncate(&content_type, 80)
            ),
        ))
    }
}

async fn read_multipart(request: Request, max_photos: usize) -> Result<Upload, Problem> {
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
                // Refused at the first photo too many, before its bytes are copied.
                if upload.images.len() == max_photos {
                    return Err(too_many_photos("image", max_photos));
                }
                let bytes = field.bytes().await.map_err(multipart_problem)?;
                upload.images.push(bytes);
            }
            "challenge" => {
                if upload.challenge.is_some() {
                    return Err(Problem::malformed("the field challenge is given more than once"));
                }
                // A challenge id is 32 characters: a longer field is not one, and is not kept.
                let text = field.text().await.map_err(multipart_problem)?;
                upload.challenge = Some(truncate(&text, 64));
            }
            "frame" => {
                // Refused at the first frame too many, before its bytes are copied.
                if upload.frames.len() == MAX_CAPTURE_FRAMES {
                    return Err(too_many_frames("frame"));
                }
                let bytes = field.bytes().await.map_err(multipart_problem)?;
                upload.frames.push(bytes);
            }
            "frame_steps" => {
                if upload.frame_steps.is_some() {
                    return Err(Problem::malformed("the field frame_steps is given more than once"));
                }
                let text = field.text().await.map_err(multipart_problem)?;
                upload.frame_steps = Some(parse_frame_steps(&text)?);
            }
            other => {
                return Err(Problem::malformed(format!(
                    "unknown form field {:?}: the fields are subject, image and (/verify) frame, frame_steps and challenge",
                    truncate(other, 40)
                )));
            }
        }
    }
    Ok(upload)
}

fn too_many_photos(field: &str, max_photos: usize) -> Problem {
    Problem::malformed(format!("at most {max_photos} photos per request (field {field}), got more than {max_photos}"))
}

fn too_many_frames(field: &str) -> Problem {
    Problem::malformed(format!("at most {MAX_CAPTURE_FRAMES} frames besides the probe (field {field}), got more than {MAX_CAPTURE_FRAMES}"))
}

/// The multipart `frame_steps`: comma-separated 0-based step numbers, one per frame (spaces
/// allowed), at most [`MAX_CAPTURE_FRAMES`] of them.
fn parse_frame_steps(text: &str) -> Result<Vec<usize>, Problem> {
    let entries: Vec<&str> = text.split(',').map(str::trim).collect();
    if entries.len() > MAX_CAPTURE_FRAMES {
        return Err(Problem::malformed(format!("frame_steps names more than {MAX_CAPTURE_FRAMES} frames")));
    }
    entries
        .iter()
        .map(|e| {
            // Up to 999, as the schema's pattern allows: a step past the challenge's is the
            // service's to refuse, after the challenge itself is looked up.
            e.parse::<u16>().map(usize::from).map_err(|_| {
                Problem::malformed(format!(
                    "frame_steps must be comma-separated step numbers (0-based), one per frame, e.g. 0,0,1,1,2; got {:?}",
                    truncate(e, 20)
                ))
            })
        })
        .collect()
}

fn multipart_problem(e: axum::extract::multipart::MultipartError) -> Problem {
    if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
        Problem::new(ProblemKind::TooLarge, format!("the request body exceeds the size limit: {}", e.body_text()))
    } else {
        Problem::malformed(format!("invalid multipart body: {}", e.body_text()))
    }
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

    /// No further frames and no challenge: only `/verify` takes them (it takes them out of the
    /// upload first).
    pub fn refuse_frames(&self) -> Result<(), Problem> {
        if self.challenge.is_some() {
            Err(Problem::malformed("only /verify takes a liveness challenge (field challenge)"))
        } else if self.frame_steps.is_some() {
            Err(Problem::malformed("frame_steps goes with a liveness challenge (field challenge) on /verify"))
        } else if self.frames.is_empty() {
            Ok(())
        } else {
            Err(Problem::malformed("only /verify takes further frames of a capture (field frame, or frames in JSON)"))
        }
    }

    /// Exactly one photo, and no further frames.
    pub fn single_image(mut self) -> Result<Bytes, Problem> {
        self.refuse_frames()?;
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
    fn fmr_range() {
        assert!(validate_fmr(Some(1e-3)).is_ok());
        assert!(validate_fmr(None).unwrap().is_none());
        for bad in [0.0, 1.0, -1.0, f64::NAN] {
            assert!(validate_fmr(Some(bad)).is_err());
        }
    }
}
