//! Errors as `application/problem+json` (RFC 9457), one problem type per failure class.
//!
//! Every failure caused by the client's input has its own type URI and a 4xx status; a 5xx
//! means the server (or its capacity) failed, never the request.

use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Serialize;

use facegate_core::imaging::DecodeError;
use facegate_service::{FramesMismatch, PhotoError, PoolError, PresentationAttack, ServiceError};

use super::responses::QualityFailure;

/// The base of every problem type URI.
pub const PROBLEM_BASE: &str = "https://facegate.dev/problems/";

/// The failure classes the API reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ProblemKind {
    /// The bytes are not an image of any known format.
    NotAnImage,
    /// An image format we do not decode (only JPEG, PNG, GIF, BMP, PGM/PPM are).
    UnsupportedFormat,
    /// The request's Content-Type is neither multipart/form-data nor JSON.
    UnsupportedMediaType,
    /// Body over the size limit, or an image over the pixel or decode-memory limit.
    TooLarge,
    /// The image header is recognised but the data is corrupt or truncated.
    CorruptImage,
    /// No face was found in a photo.
    NoFace,
    /// Several faces in an enrolment photo (enrolment refuses; verify uses the largest).
    SeveralFaces,
    /// An enrolment photo below the quality policy.
    LowQuality,
    /// Liveness is enforced and the face was taken for a printed photo (enrol, verify, identify).
    PresentationAttack,
    /// A further frame of a `/verify` capture does not show the probe's person.
    FramesMismatch,
    /// The liveness challenge a `/verify` answers is unknown, already used or expired (or liveness
    /// is off): it never passes.
    InvalidChallenge,
    /// The 3D morphable model the operation needs is not loaded (avatar, frontal rendering).
    NoFaceModel,
    /// The 3D morphable model could not be fitted to the face's landmarks.
    FitFailed,
    /// The subject id is not enrolled.
    UnknownSubject,
    /// The subject's templates were all made by another recognition model version.
    ModelMismatch,
    /// A missing or invalid field, parameter, subject id or base64 string.
    MalformedRequest,
    /// A missing or invalid API key.
    Unauthorized,
    /// No route with this path.
    NotFound,
    /// The route exists but not with this method.
    MethodNotAllowed,
    /// `POST /liveness/challenge` from an address over its rate, or with as many challenges open
    /// as the store keeps: retry after `Retry-After`.
    TooManyChallenges,
    /// The bounded work queue is full: retry later.
    Overloaded,
    /// The template database cannot be reached: retry later.
    StoreUnavailable,
    /// The request took longer than the request timeout.
    Timeout,
    /// The request body did not arrive within the body timeout (the client's fault).
    RequestTimeout,
    /// The request target is longer than the server reads.
    UriTooLong,
    /// Too many request headers, or too many bytes of them.
    HeadersTooLarge,
    /// A fault of the server itself.
    Internal,
}

impl ProblemKind {
    pub const ALL: [ProblemKind; 27] = [
        ProblemKind::NotAnImage,
        ProblemKind::UnsupportedFormat,
        ProblemKind::UnsupportedMediaType,
        ProblemKind::TooLarge,
        ProblemKind::CorruptImage,
        ProblemKind::NoFace,
        ProblemKind::SeveralFaces,
        ProblemKind::LowQuality,
        ProblemKind::PresentationAttack,
        ProblemKind::FramesMismatch,
        ProblemKind::InvalidChallenge,
        ProblemKind::NoFaceModel,
        ProblemKind::FitFailed,
        ProblemKind::UnknownSubject,
        ProblemKind::ModelMismatch,
        ProblemKind::MalformedRequest,
        ProblemKind::Unauthorized,
        ProblemKind::NotFound,
        ProblemKind::MethodNotAllowed,
        ProblemKind::TooManyChallenges,
        ProblemKind::Overloaded,
        ProblemKind::StoreUnavailable,
        ProblemKind::Timeout,
        ProblemKind::RequestTimeout,
        ProblemKind::UriTooLong,
        ProblemKind::HeadersTooLarge,
        ProblemKind::Internal,
    ];

    /// The last segment of the type URI.
    pub fn slug(self) -> &'static str {
        match self {
            ProblemKind::NotAnImage => "not-an-image",
            ProblemKind::UnsupportedFormat => "unsupported-format",
            ProblemKind::UnsupportedMediaType => "unsupported-media-type",
            ProblemKind::TooLarge => "too-large",
            ProblemKind::CorruptImage => "corrupt-image",
            ProblemKind::NoFace => "no-face",
            ProblemKind::SeveralFaces => "several-faces",
            ProblemKind::LowQuality => "low-quality",
            ProblemKind::PresentationAttack => "presentation-attack",
            ProblemKind::FramesMismatch => "frames-mismatch",
            ProblemKind::InvalidChallenge => "invalid-challenge",
            ProblemKind::NoFaceModel => "no-face-model",
            ProblemKind::FitFailed => "fit-failed",
            ProblemKind::UnknownSubject => "unknown-subject",
            ProblemKind::ModelMismatch => "model-mismatch",
            ProblemKind::MalformedRequest => "malformed-request",
            ProblemKind::Unauthorized => "unauthorized",
            ProblemKind::NotFound => "not-found",
            ProblemKind::MethodNotAllowed => "method-not-allowed",
            ProblemKind::TooManyChallenges => "too-many-challenges",
            ProblemKind::Overloaded => "overloaded",
            ProblemKind::StoreUnavailable => "store-unavailable",
            ProblemKind::Timeout => "timeout",
            ProblemKind::RequestTimeout => "request-timeout",
            ProblemKind::UriTooLong => "uri-too-long",
            ProblemKind::HeadersTooLarge => "headers-too-large",
            ProblemKind::Internal => "internal",
        }
    }

    pub fn type_uri(self) -> String {
        format!("{PROBLEM_BASE}{}", self.slug())
    }

    pub fn title(self) -> &'static str {
        match self {
            ProblemKind::NotAnImage => "Not an image",
            ProblemKind::UnsupportedFormat => "Unsupported image format",
            ProblemKind::UnsupportedMediaType => "Unsupported media type",
            ProblemKind::TooLarge => "Too large",
            ProblemKind::CorruptImage => "Corrupt image",
            ProblemKind::NoFace => "No face found",
            ProblemKind::SeveralFaces => "Several faces found",
            ProblemKind::LowQuality => "Photo quality too low",
            ProblemKind::PresentationAttack => "Presentation attack",
            ProblemKind::FramesMismatch => "Frames of another person",
            ProblemKind::InvalidChallenge => "Invalid liveness challenge",
            ProblemKind::NoFaceModel => "No 3D morphable model",
            ProblemKind::FitFailed => "3D morphable model fit failed",
            ProblemKind::UnknownSubject => "Unknown subject",
            ProblemKind::ModelMismatch => "Templates of another model version",
            ProblemKind::MalformedRequest => "Malformed request",
            ProblemKind::Unauthorized => "Unauthorized",
            ProblemKind::NotFound => "Not found",
            ProblemKind::MethodNotAllowed => "Method not allowed",
            ProblemKind::TooManyChallenges => "Too many challenges",
            ProblemKind::Overloaded => "Overloaded",
            ProblemKind::StoreUnavailable => "Template database unavailable",
            ProblemKind::Timeout => "Request timeout",
            ProblemKind::RequestTimeout => "Request body timeout",
            ProblemKind::UriTooLong => "URI too long",
            ProblemKind::HeadersTooLarge => "Request headers too large",
            ProblemKind::Internal => "Internal error",
        }
    }

    pub fn status(self) -> StatusCode {
        match self {
            ProblemKind::NotAnImage
            | ProblemKind::CorruptImage
            | ProblemKind::NoFace
            | ProblemKind::SeveralFaces
            | ProblemKind::LowQuality
            | ProblemKind::PresentationAttack
            | ProblemKind::FramesMismatch
            | ProblemKind::InvalidChallenge
            | ProblemKind::NoFaceModel
            | ProblemKind::FitFailed => StatusCode::UNPROCESSABLE_ENTITY,
            ProblemKind::UnsupportedFormat | ProblemKind::UnsupportedMediaType => StatusCode::UNSUPPORTED_MEDIA_TYPE,
            ProblemKind::TooLarge => StatusCode::PAYLOAD_TOO_LARGE,
            ProblemKind::UnknownSubject | ProblemKind::NotFound => StatusCode::NOT_FOUND,
            ProblemKind::ModelMismatch => StatusCode::CONFLICT,
            ProblemKind::MalformedRequest => StatusCode::BAD_REQUEST,
            ProblemKind::Unauthorized => StatusCode::UNAUTHORIZED,
            ProblemKind::MethodNotAllowed => StatusCode::METHOD_NOT_ALLOWED,
            ProblemKind::TooManyChallenges => StatusCode::TOO_MANY_REQUESTS,
            ProblemKind::Overloaded | ProblemKind::StoreUnavailable => StatusCode::SERVICE_UNAVAILABLE,
            ProblemKind::Timeout => StatusCode::GATEWAY_TIMEOUT,
            ProblemKind::RequestTimeout => StatusCode::REQUEST_TIMEOUT,
            ProblemKind::UriTooLong => StatusCode::URI_TOO_LONG,
            ProblemKind::HeadersTooLarge => StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
            ProblemKind::Internal => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }
}

/// One problem: its class, a human-readable detail, and for multi-image requests the index of
/// the image at fault (or, for a `/verify` capture's further frames, of the frame).
#[derive(Debug, Clone)]
pub struct Problem {
    pub kind: ProblemKind,
    pub detail: String,
    pub image: Option<usize>,
    /// The 0-based index among a `/verify` request's further frames (`frame` parts, `frames`
    /// entries) of the frame at fault (the body's `frame` member).
    pub frame: Option<usize>,
    /// `low-quality`: the limits the photo breaks (the body's `failures` member).
    pub failures: Vec<facegate_vision::quality::Failure>,
    /// `presentation-attack`: the liveness score and the operating point it fell below (the
    /// body's `score`, `threshold`, `operating_point` and `model` members).
    pub attack: Option<Box<PresentationAttack>>,
    /// `presentation-attack` of a failed liveness challenge: why it failed (the body's `reason`).
    pub reason: Option<String>,
    /// Seconds for the `Retry-After` header of a 429 or 503 (1 when not set).
    pub retry_after: Option<u64>,
}

/// The JSON body of a problem response.
#[derive(Debug, Serialize)]
struct ProblemBody<'a> {
    #[serde(rename = "type")]
    type_uri: String,
    title: &'static str,
    status: u16,
    detail: &'a str,
    #[serde(skip_serializing_if = "Option::is_none")]
    image: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    frame: Option<usize>,
    #[serde(skip_serializing_if = "Vec::is_empty")]
    failures: Vec<QualityFailure>,
    #[serde(skip_serializing_if = "Option::is_none")]
    score: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    threshold: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    operating_point: Option<&'a str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    model: Option<&'a str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    reason: Option<&'a str>,
}

impl Problem {
    pub fn new(kind: ProblemKind, detail: impl Into<String>) -> Problem {
        Problem {
            kind,
            detail: detail.into(),
            image: None,
            frame: None,
            failures: Vec::new(),
            attack: None,
            reason: None,
            retry_after: None,
        }
    }

    /// `too-many-challenges`: retry after `wait` (whole seconds, at least 1).
    pub fn too_many_challenges(detail: impl Into<String>, wait: std::time::Duration) -> Problem {
        let seconds = wait.as_secs() + u64::from(wait.subsec_nanos() > 0);
        Problem { retry_after: Some(seconds.max(1)), ..Problem::new(ProblemKind::TooManyChallenges, detail) }
    }

    /// `presentation-attack`: the face's liveness score fell below the operating point.
    pub fn presentation_attack(attack: PresentationAttack) -> Problem {
        Problem { detail: attack.to_string(), attack: Some(Box::new(attack)), ..Problem::new(ProblemKind::PresentationAttack, "") }
    }

    /// `low-quality`: the photo breaks `failures` of the enrolment policy.
    pub fn low_quality(failures: Vec<facegate_vision::quality::Failure>) -> Problem {
        let list: Vec<String> = failures
            .iter()
            .map(|f| {
                let side = if f.bound == facegate_vision::quality::Bound::Min { "below its minimum" } else { "above its maximum" };
                format!("{} {:.1} is {side} {:.1}", f.component, f.value, f.limit)
            })
            .collect();
        let detail = format!("the photo is below the enrolment quality policy: {}", list.join("; "));
        Problem { failures, ..Problem::new(ProblemKind::LowQuality, detail) }
    }

    /// The same problem, attributed to the image at `index` (0-based, in request order).
    pub fn for_image(mut self, index: usize) -> Problem {
        self.image = Some(index);
        self
    }

    /// The same problem, attributed to the further frame at `index` of a `/verify` capture
    /// (0-based among the frames, in request order; the probe is not counted).
    pub fn for_frame(mut self, index: usize) -> Problem {
        self.frame = Some(index);
        self
    }

    /// `frames-mismatch`: a further frame does not show the probe's person.
    pub fn frames_mismatch(mismatch: &FramesMismatch) -> Problem {
        Problem::new(ProblemKind::FramesMismatch, mismatch.to_string()).for_frame(mismatch.frame)
    }

    pub fn malformed(detail: impl Into<String>) -> Problem {
        Problem::new(ProblemKind::MalformedRequest, detail)
    }

    /// A server fault: logged in full, reported without internals.
    pub fn internal(error: impl std::fmt::Display) -> Problem {
        tracing::error!("internal error: {error}");
        Problem::new(ProblemKind::Internal, "the server failed to process the request; see its log")
    }

    pub fn from_decode(error: &DecodeError) -> Problem {
        let kind = match error {
            DecodeError::NotAnImage => ProblemKind::NotAnImage,
            DecodeError::Unsupported(_) => ProblemKind::UnsupportedFormat,
            DecodeError::TooLarge { .. } => ProblemKind::TooLarge,
            DecodeError::Corrupt(_) | DecodeError::Io { .. } => ProblemKind::CorruptImage,
        };
        Problem::new(kind, error.to_string())
    }

    /// The problem+json body.
    pub fn json(&self) -> Vec<u8> {
        let body = ProblemBody {
            type_uri: self.kind.type_uri(),
            title: self.kind.title(),
            status: self.kind.status().as_u16(),
            detail: &self.detail,
            image: self.image,
            frame: self.frame,
            failures: self.failures.iter().map(QualityFailure::from).collect(),
            score: self.attack.as_ref().map(|a| a.score),
            threshold: self.attack.as_ref().map(|a| a.threshold),
            operating_point: self.attack.as_ref().map(|a| a.operating_point.as_str()),
            model: self.attack.as_ref().map(|a| a.model.as_str()),
            reason: self.reason.as_deref(),
        };
        serde_json::to_vec(&body).expect("problem bodies serialise")
    }
}

impl From<facegate_store::StoreError> for Problem {
    fn from(error: facegate_store::StoreError) -> Problem {
        if error.is_unavailable() {
            Problem::new(ProblemKind::StoreUnavailable, format!("the template database is unavailable; retry shortly ({error})"))
        } else {
            Problem::internal(error)
        }
    }
}

impl From<PoolError> for Problem {
    fn from(error: PoolError) -> Problem {
        match error {
            PoolError::Overloaded => Problem::new(ProblemKind::Overloaded, error.to_string()),
            PoolError::Failed(e) => Problem::internal(e),
        }
    }
}

impl From<PhotoError> for Problem {
    fn from(error: PhotoError) -> Problem {
        match error {
            PhotoError::Decode(e) => Problem::from_decode(&e),
            PhotoError::NoFace | PhotoError::NotPoseCorrected(_) => Problem::new(ProblemKind::NoFace, error.to_string()),
            PhotoError::FitFailed(_) => Problem::new(ProblemKind::FitFailed, error.to_string()),
            PhotoError::NoFaceModel(_) => Problem::new(ProblemKind::NoFaceModel, error.to_string()),
            PhotoError::SeveralFaces(_) => Problem::new(ProblemKind::SeveralFaces, error.to_string()),
            PhotoError::LowQuality(failures) => Problem::low_quality(failures),
            PhotoError::PresentationAttack(attack) => Problem::presentation_attack(attack),
            PhotoError::ChallengeFailed(ref outcome) => {
                let reason = outcome.reason.clone();
                Problem { reason, ..Problem::new(ProblemKind::PresentationAttack, error.to_string()) }
            }
            PhotoError::LivenessUnavailable => Problem::internal(error),
            PhotoError::Internal(e) => Problem::internal(e),
        }
    }
}

impl From<ServiceError> for Problem {
    fn from(error: ServiceError) -> Problem {
        match error {
            ServiceError::Photo { index: Some(index), error } => Problem::from(error).for_image(index),
            ServiceError::Photo { index: None, error } => Problem::from(error),
            ServiceError::Frame { index, error } => Problem::from(error).for_frame(index),
            ServiceError::FramesMismatch(mismatch) => Problem::frames_mismatch(&mismatch),
            ServiceError::InvalidChallenge(e) => Problem::new(ProblemKind::InvalidChallenge, e.to_string()),
            ServiceError::Invalid(detail) => Problem::malformed(detail),
            ServiceError::TooManyChallenges { retry_after, .. } => Problem::too_many_challenges(error.to_string(), retry_after),
            ServiceError::UnknownSubject(id) => Problem::new(ProblemKind::UnknownSubject, format!("subject {id} is not enrolled")),
            ServiceError::ModelMismatch(e) => Problem::new(ProblemKind::ModelMismatch, e.to_string()),
            ServiceError::Pool(e) => Problem::from(e),
            ServiceError::StoreUnavailable | ServiceError::OutcomeUnknown => Problem::new(ProblemKind::StoreUnavailable, error.to_string()),
            ServiceError::Store(e) => Problem::from(e),
            ServiceError::Gallery(e) => Problem::internal(e),
        }
    }
}

impl IntoResponse for Problem {
    fn into_response(self) -> Response {
        let status = self.kind.status();
        let mut response = (status, self.json()).into_response();
        // The audit log reads the outcome of a refused request from here.
        response.extensions_mut().insert(self.kind);
        let headers = response.headers_mut();
        headers.insert(header::CONTENT_TYPE, HeaderValue::from_static("application/problem+json"));
        match self.kind {
            ProblemKind::Unauthorized => {
                headers.insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer realm=\"facegate\""));
            }
            ProblemKind::Overloaded | ProblemKind::StoreUnavailable | ProblemKind::TooManyChallenges => {
                headers.insert(header::RETRY_AFTER, HeaderValue::from(self.retry_after.unwrap_or(1)));
            }
            // The body may still be arriving: this connection cannot carry another request.
            ProblemKind::RequestTimeout => {
                headers.insert(header::CONNECTION, HeaderValue::from_static("close"));
            }
            _ => {}
        }
        response
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_kind_has_a_distinct_type_and_a_client_status_for_client_faults() {
        let mut slugs: Vec<_> = ProblemKind::ALL.iter().map(|k| k.slug()).collect();
        slugs.sort();
        slugs.dedup();
        assert_eq!(slugs.len(), ProblemKind::ALL.len());
        for kind in ProblemKind::ALL {
            let server_side =
                matches!(kind, ProblemKind::Overloaded | ProblemKind::StoreUnavailable | ProblemKind::Timeout | ProblemKind::Internal);
            assert_eq!(kind.status().is_server_error(), server_side, "{kind:?}");
        }
    }

    #[test]
    fn a_presentation_attack_carries_its_score_and_operating_point() {
        let attack = PresentationAttack { score: 0.25, threshold: 0.75, operating_point: "EER".into(), model: "m-1".into() };
        let problem = Problem::from(ServiceError::Photo { index: Some(2), error: PhotoError::PresentationAttack(attack) });
        let body: serde_json::Value = serde_json::from_slice(&problem.json()).unwrap();
        assert_eq!(
            body,
            serde_json::json!({
                "type": "https://facegate.dev/problems/presentation-attack", "title": "Presentation attack", "status": 422,
                "detail": problem.detail, "image": 2, "score": 0.25, "threshold": 0.75, "operating_point": "EER", "model": "m-1",
            })
        );
        // Other problems carry none of these members.
        let other: serde_json::Value = serde_json::from_slice(&Problem::new(ProblemKind::NoFace, "none").json()).unwrap();
        assert!(["score", "threshold", "operating_point", "model"].iter().all(|k| other.get(k).is_none()), "{other}");
        assert_eq!(Problem::from(PhotoError::LivenessUnavailable).kind, ProblemKind::Internal);
    }

    #[test]
    fn a_frame_at_fault_is_named_by_its_index() {
        let body = |error: ServiceError| serde_json::from_slice::<serde_json::Value>(&Problem::from(error).json()).unwrap();
        let no_face = body(ServiceError::Frame { index: 3, error: PhotoError::NoFace });
        assert_eq!(
            (&no_face["type"], &no_face["frame"], no_face.get("image")),
            (&"https://facegate.dev/problems/no-face".into(), &3.into(), None)
        );
        let mismatch = body(ServiceError::FramesMismatch(FramesMismatch { frame: 1, score: 0.125, threshold: 0.5 }));
        assert_eq!(
            mismatch,
            serde_json::json!({
                "type": "https://facegate.dev/problems/frames-mismatch", "title": "Frames of another person", "status": 422,
                "detail": "frame 1 does not show the person of the probe: its score against the probe, 0.125, is below the verification \
                           threshold 0.500; every frame must be of the same capture of the same face",
                "frame": 1,
            })
        );
        assert!(body(ServiceError::Photo { index: Some(2), error: PhotoError::NoFace }).get("frame").is_none());
    }

    #[test]
    fn decode_errors_map_to_their_problem_types() {
        let kind = |e: DecodeError| Problem::from_decode(&e).kind;
        assert_eq!(kind(DecodeError::NotAnImage), ProblemKind::NotAnImage);
        assert_eq!(kind(DecodeError::Unsupported("Tiff".into())), ProblemKind::UnsupportedFormat);
        assert_eq!(kind(DecodeError::TooLarge { width: 1, height: 1, limit: "x".into() }), ProblemKind::TooLarge);
        assert_eq!(kind(DecodeError::Corrupt("eof".into())), ProblemKind::CorruptImage);
    }
}
