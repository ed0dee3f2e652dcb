//! Reading requests, as axum extractors that reject with the app's [`Problem`]: [`Upload`] (photos
//! as `multipart/form-data` or base64 in JSON, and the subject id), [`Params`] (query parameters,
//! unknown ones refused), [`SubjectPath`] (a subject id in the path). Every way a request can be
//! malformed ends in a [`Problem`], never a panic.
//!
//! A JSON body is parsed and its base64 decoded on the blocking pool, never on the async runtime.
//! The parse counts the `images` entries as it goes and refuses the body at the first entry past
//! the most photos any operation takes ([`JsonLimit`]), and the `frames` entries (`/verify`'s
//! further frames of the probe's capture) past [`MAX_FRAMES`]; until then each entry stays a slice
//! of the body (a copy only where the JSON string has escapes), so a body of millions of tiny
//! photos costs neither memory nor time beyond the body itself.

use std::borrow::Cow;
use std::cell::Cell;
use std::fmt;

use axum::body::Bytes;
use axum::extract::rejection::PathRejection;
use axum::extract::{FromRequest, FromRequestParts, Multipart, Path, Query, Request};
use axum::http::request::Parts;
use axum::http::{StatusCode, header};
use base64::Engine as _;
use serde::Deserialize;
use serde::de::{self, DeserializeOwned, DeserializeSeed, MapAccess, SeqAccess, Visitor};

use super::AppState;
use super::admission::{BodyDeadline, body_timed_out};
use super::problem::{Problem, ProblemKind};
use facegate_service::{MAX_FRAMES, SubjectId};

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
    /// [`MAX_FRAMES`]; only `/verify` takes them.
    pub frames: Vec<Bytes>,
}

impl FromRequest<AppState> for Upload {
    type Rejection = Problem;

    /// The most photos any operation takes is an enrolment's (`ApiConfig::max_images`): a JSON
    /// body with more in `images` is refused while it is parsed.
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
/// applies while reading; exceeding it is a `too-large` problem. A body still arriving at the
/// admission layer's deadline ([`BodyDeadline`]) is a `request-timeout` problem (408). A JSON body
/// with more than `max_photos` entries in `images`, or either form with more than [`MAX_FRAMES`]
/// frames, is malformed, refused as soon as the read reaches the first one too many.
pub async fn read_upload(request: Request, max_photos: usize) -> Result<Upload, Problem> {
    match request.extensions().get::<BodyDeadline>().copied() {
        Some(BodyDeadline(deadline)) => {
            tokio::time::timeout_at(deadline, read_body(request, max_photos)).await.map_err(|_| body_timed_out())?
        }
        None => read_body(request, max_photos).await,
    }
}

async fn read_body(request: Request, max_photos: usize) -> Result<Upload, Problem> {
    let content_type = request.headers().get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("").to_ascii_lowercase();
    let essence = content_type.split(';').next().unwrap_or("").trim().to_string();
    if essence == "multipart/form-data" {
        read_multipart(request).await
    } else if essence == "application/json" || essence.ends_with("+json") {
        read_json(request, max_photos).await
    } else {
        Err(Problem::new(
            ProblemKind::UnsupportedMediaType,
            format!(
                "Content-Type {:?} is not accepted: send multipart/form-data (fields subject, image, frame) or application/json",
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
            "frame" => {
                // Refused at the first frame too many, before its bytes are read.
                if upload.frames.len() == MAX_FRAMES {
                    return Err(too_many_frames("frame"));
                }
                let bytes = field.bytes().await.map_err(multipart_problem)?;
                upload.frames.push(bytes);
            }
            other => {
                return Err(Problem::malformed(format!(
                    "unknown form field {:?}: the fields are subject, image and (/verify) frame",
                    truncate(other, 40)
                )));
            }
        }
    }
    Ok(upload)
}

fn too_many_frames(field: &str) -> Problem {
    Problem::malformed(format!("at most {MAX_FRAMES} frames besides the probe (field {field}), got more than {MAX_FRAMES}"))
}

fn multipart_problem(e: axum::extract::multipart::MultipartError) -> Problem {
    if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
        Problem::new(ProblemKind::TooLarge, format!("the request body exceeds the size limit: {}", e.body_text()))
    } else {
        Problem::malformed(format!("invalid multipart body: {}", e.body_text()))
    }
}

/// Read a JSON body, then parse it and decode its photos on the blocking pool: a large body takes
/// no time from the async runtime's other requests.
async fn read_json(request: Request, max_photos: usize) -> Result<Upload, Problem> {
    let body = Bytes::from_request(request, &()).await.map_err(|e| {
        if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
            Problem::new(ProblemKind::TooLarge, "the request body exceeds the size limit")
        } else {
            Problem::malformed(format!("cannot read the body: {}", e.body_text()))
        }
    })?;
    tokio::task::spawn_blocking(move || parse_json(&body, max_photos)).await.map_err(Problem::internal)?
}

/// Parse a JSON body (at most `max_photos` entries in `images`, [`MAX_FRAMES`] in `frames`) and
/// decode its photos, `image` first, then its frames.
fn parse_json(body: &[u8], max_photos: usize) -> Result<Upload, Problem> {
    let (over, frames_over) = (Cell::new(false), Cell::new(false));
    let mut de = serde_json::Deserializer::from_slice(body);
    let limit = JsonLimit { max_photos, over: &over, frames_over: &frames_over };
    let parsed = limit.deserialize(&mut de).and_then(|json| de.end().map(|()| json));
    let json = parsed.map_err(|e| {
        if over.get() {
            Problem::malformed(format!("at most {max_photos} photos per request (field images), got more than {max_photos}"))
        } else if frames_over.get() {
            too_many_frames("frames")
        } else {
            Problem::malformed(format!("invalid JSON body: {e}"))
        }
    })?;
    let strings = json.image.into_iter().chain(json.images.into_iter().flatten());
    let images = strings.enumerate().map(|(index, s)| decode_base64(&s.0).map_err(|p| p.for_image(index))).collect::<Result<_, _>>()?;
    let frames = json.frames.iter().enumerate().map(|(index, s)| decode_base64(&s.0).map_err(|p| p.for_frame(index)));
    Ok(Upload { subject: json.subject, images, frames: frames.collect::<Result<_, _>>()? })
}

/// The JSON form of a request: base64 photos (a `data:` URL prefix is allowed), each still the
/// body's text. Unknown fields are refused; `frames`, when present, must be an array.
#[derive(Debug)]
struct JsonUpload<'a> {
    subject: Option<String>,
    image: Option<Base64Text<'a>>,
    images: Option<Vec<Base64Text<'a>>>,
    frames: Vec<Base64Text<'a>>,
}

const FIELDS: &[&str] = &["subject", "image", "images", "frames"];

/// One photo's base64 text, borrowed from the body (owned only when the JSON string has escapes).
#[derive(Debug)]
struct Base64Text<'a>(Cow<'a, str>);

impl<'de> Deserialize<'de> for Base64Text<'de> {
    fn deserialize<D: de::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct TextVisitor;
        impl<'de> Visitor<'de> for TextVisitor {
            type Value = Base64Text<'de>;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a string")
            }
            fn visit_borrowed_str<E: de::Error>(self, v: &'de str) -> Result<Self::Value, E> {
                Ok(Base64Text(Cow::Borrowed(v)))
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<Self::Value, E> {
                Ok(Base64Text(Cow::Owned(v.to_owned())))
            }
            fn visit_string<E: de::Error>(self, v: String) -> Result<Self::Value, E> {
                Ok(Base64Text(Cow::Owned(v)))
            }
        }
        deserializer.deserialize_str(TextVisitor)
    }
}

/// Deserializes a [`JsonUpload`] as `#[derive(Deserialize)] #[serde(deny_unknown_fields)]` would
/// (same errors; `frames` as a `#[serde(default)]` field), except that `images` is refused at its
/// entry `max_photos + 1` and `frames` at its entry `MAX_FRAMES + 1`, before that entry is kept;
/// `over` or `frames_over` then says so.
#[derive(Clone, Copy)]
struct JsonLimit<'c> {
    max_photos: usize,
    over: &'c Cell<bool>,
    frames_over: &'c Cell<bool>,
}

impl<'de> DeserializeSeed<'de> for JsonLimit<'_> {
    type Value = JsonUpload<'de>;

    fn deserialize<D: de::Deserializer<'de>>(self, deserializer: D) -> Result<JsonUpload<'de>, D::Error> {
        deserializer.deserialize_struct("JsonUpload", FIELDS, self)
    }
}

impl<'de> Visitor<'de> for JsonLimit<'_> {
    type Value = JsonUpload<'de>;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("struct JsonUpload")
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<JsonUpload<'de>, A::Error> {
        let mut json = JsonUpload { subject: None, image: None, images: None, frames: Vec::new() };
        let mut seen = [false; 4];
        while let Some(Field(index)) = map.next_key::<Field>()? {
            if std::mem::replace(&mut seen[index], true) {
                return Err(de::Error::duplicate_field(FIELDS[index]));
            }
            match index {
                0 => json.subject = map.next_value()?,
                1 => json.image = map.next_value()?,
                2 => json.images = map.next_value_seed(ImagesSeed(self))?,
                _ => json.frames = map.next_value_seed(self.frames())?,
            }
        }
        Ok(json)
    }

    /// The struct as an array `[subject, image, images, frames]` (`frames` may be left out), as
    /// serde's derive accepts it.
    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<JsonUpload<'de>, A::Error> {
        let missing = |i: usize| <A::Error as de::Error>::invalid_length(i, &"struct JsonUpload with 4 elements");
        let subject = seq.next_element()?.ok_or_else(|| missing(0))?;
        let image = seq.next_element()?.ok_or_else(|| missing(1))?;
        let images = seq.next_element_seed(ImagesSeed(self))?.ok_or_else(|| missing(2))?;
        let frames = seq.next_element_seed(self.frames())?.unwrap_or_default();
        Ok(JsonUpload { subject, image, images, frames })
    }
}

impl<'c> JsonLimit<'c> {
    /// The reader of `frames`: an array of at most [`MAX_FRAMES`] strings.
    fn frames(self) -> PhotoList<'c> {
        PhotoList { max: MAX_FRAMES, over: self.frames_over }
    }
}

/// A field name of [`JsonUpload`], as its index in [`FIELDS`]; an unknown one is an error.
struct Field(usize);

impl<'de> Deserialize<'de> for Field {
    fn deserialize<D: de::Deserializer<'de>>(deserializer: D) -> Result<Field, D::Error> {
        struct FieldVisitor;
        impl Visitor<'_> for FieldVisitor {
            type Value = Field;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("field identifier")
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<Field, E> {
                FIELDS.iter().position(|f| *f == v).map(Field).ok_or_else(|| E::unknown_field(v, FIELDS))
            }
        }
        deserializer.deserialize_identifier(FieldVisitor)
    }
}

/// The `images` field: null or an array of at most `max_photos` strings.
struct ImagesSeed<'c>(JsonLimit<'c>);

impl<'de> DeserializeSeed<'de> for ImagesSeed<'_> {
    type Value = Option<Vec<Base64Text<'de>>>;

    fn deserialize<D: de::Deserializer<'de>>(self, deserializer: D) -> Result<Self::Value, D::Error> {
        deserializer.deserialize_option(self)
    }
}

impl<'de> Visitor<'de> for ImagesSeed<'_> {
    type Value = Option<Vec<Base64Text<'de>>>;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("option")
    }

    fn visit_none<E: de::Error>(self) -> Result<Self::Value, E> {
        Ok(None)
    }

    fn visit_unit<E: de::Error>(self) -> Result<Self::Value, E> {
        Ok(None)
    }

    fn visit_some<D: de::Deserializer<'de>>(self, deserializer: D) -> Result<Self::Value, D::Error> {
        deserializer.deserialize_seq(PhotoList { max: self.0.max_photos, over: self.0.over }).map(Some)
    }
}

/// An array of photos (`images`, `frames`), counted while it is read: refused at its entry
/// `max + 1`, which `over` then says.
struct PhotoList<'c> {
    max: usize,
    over: &'c Cell<bool>,
}

impl<'de> DeserializeSeed<'de> for PhotoList<'_> {
    type Value = Vec<Base64Text<'de>>;

    fn deserialize<D: de::Deserializer<'de>>(self, deserializer: D) -> Result<Self::Value, D::Error> {
        deserializer.deserialize_seq(self)
    }
}

impl<'de> Visitor<'de> for PhotoList<'_> {
    type Value = Vec<Base64Text<'de>>;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("a sequence")
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
        let PhotoList { max, over } = self;
        let mut photos = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(max));
        while let Some(photo) = seq.next_element()? {
            if photos.len() == max {
                over.set(true);
                return Err(de::Error::custom(format_args!("more than {max} photos")));
            }
            photos.push(photo);
        }
        Ok(photos)
    }
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

    /// No further frames: only `/verify` takes them (it takes them out of the upload first).
    pub fn refuse_frames(&self) -> Result<(), Problem> {
        if self.frames.is_empty() {
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
    fn base64_with_and_without_padding_or_data_url() {
        assert_eq!(&decode_base64("aGVsbG8=").unwrap()[..], b"hello");
        assert_eq!(&decode_base64("aGVsbG8").unwrap()[..], b"hello");
        assert_eq!(&decode_base64("data:image/png;base64,aGVsbG8=").unwrap()[..], b"hello");
        assert_eq!(&decode_base64("00").unwrap()[..], &[0xd3]);
        assert!(decode_base64("not base64!").is_err() && decode_base64("A").is_err());
        assert!(decode_base64("").is_err() && decode_base64("data:image/png;base64,").is_err());
    }

    /// The derived form `parse_json` replaced: its errors are the reference.
    #[derive(Debug, Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct JsonUpload {
        subject: Option<String>,
        image: Option<String>,
        images: Option<Vec<String>>,
        #[serde(default)]
        frames: Vec<String>,
    }

    fn detail(body: &str, max_photos: usize) -> String {
        parse_json(body.as_bytes(), max_photos).unwrap_err().detail
    }

    #[test]
    fn json_errors_are_the_derived_ones() {
        let bodies = [
            "{not json",
            "",
            "[]",
            "\"x\"",
            "42",
            r#"{"subject": "a", "image": "aGVsbG8=", "extra": 1}"#,
            r#"{"subject": 42, "image": "aGVsbG8="}"#,
            r#"{"subject": "a", "subject": "b"}"#,
            r#"{"subject": null, "subject": "b"}"#,
            r#"{"image": "aGVsbG8=", "image": "aGVsbG8="}"#,
            r#"{"images": [], "images": []}"#,
            r#"{"images": "aGVsbG8="}"#,
            r#"{"images": [1]}"#,
            r#"{"images": ["aGVsbG8=", null]}"#,
            r#"{"images": {"a": 1}}"#,
            r#"{"image": ["aGVsbG8="]}"#,
            r#"{"image": 1.5}"#,
            r#"{"images": ["aGVsbG8="],}"#,
            r#"{"subject": "a"} trailing"#,
            r#"{"subject": "a"}{}"#,
            r#"["a"]"#,
            r#"["a", null]"#,
            r#"["a", null, null, 1]"#,
            r#"["a", null, [2]]"#,
            r#"{"subject": "\ud800"}"#,
            r#"{"images": ["\ud800"]}"#,
            r#"{"images": ["aGVs\q"]}"#,
            r#"{"images": ["aGVsbG8="]"#,
            r#"{"frames": null}"#,
            r#"{"frames": "aGVsbG8="}"#,
            r#"{"frames": [1]}"#,
            r#"{"frames": [], "frames": []}"#,
            r#"{"frames": ["aGVsbG8="], "extra": 1}"#,
            r#"["a", null, null, [2]]"#,
            r#"["a", null, null, [], 5]"#,
        ];
        for body in bodies {
            let reference = serde_json::from_str::<JsonUpload>(body).expect_err(body);
            assert_eq!(detail(body, 16), format!("invalid JSON body: {reference}"), "{body}");
        }
    }

    #[test]
    fn json_photos_in_order_with_escapes_data_urls_and_nulls() {
        let body = r#"{"images": ["d29ybGQ=", "data:image\/png;base64,IQ\u003d\u003d"], "subject": "a", "image": "aGVsbG8"}"#;
        let upload = parse_json(body.as_bytes(), 2).unwrap();
        assert_eq!(upload.subject.as_deref(), Some("a"));
        let images: Vec<&[u8]> = upload.images.iter().map(|b| &b[..]).collect();
        assert_eq!(images, [&b"hello"[..], b"world", b"!"]);
        for body in [r#"{"subject": "a", "images": null, "image": null}"#, "{}", r#"[null, null, null]"#] {
            let upload = parse_json(body.as_bytes(), 2).unwrap();
            assert!(upload.images.is_empty(), "{body}");
        }
        let upload = parse_json(br#"["a", "aGVsbG8=", ["d29ybGQ="]]"#, 2).unwrap();
        assert_eq!((upload.subject.as_deref(), upload.images.len()), (Some("a"), 2));
    }

    #[test]
    fn json_frames_in_order_apart_from_the_photos() {
        let body = r#"{"frames": ["d29ybGQ=", "data:image/png;base64,IQ=="], "subject": "a", "image": "aGVsbG8"}"#;
        let upload = parse_json(body.as_bytes(), 1).unwrap();
        let frames: Vec<&[u8]> = upload.frames.iter().map(|b| &b[..]).collect();
        assert_eq!((upload.images.len(), frames), (1, vec![&b"world"[..], b"!"]));
        for body in [r#"{"image": "aGVsbG8", "frames": []}"#, r#"{"image": "aGVsbG8"}"#, r#"["a", "aGVsbG8", null, []]"#] {
            assert!(parse_json(body.as_bytes(), 1).unwrap().frames.is_empty(), "{body}");
        }
        // A frame that is not base64 is named by its index among the frames.
        let p = parse_json(br#"{"image": "aGVsbG8=", "images": ["d29ybGQ="], "frames": ["d29ybGQ=", "***"]}"#, 16).unwrap_err();
        assert_eq!((p.image, p.frame, p.detail.starts_with("the image is not valid base64")), (None, Some(1), true), "{}", p.detail);
        // Frames are taken by /verify alone.
        let upload = parse_json(br#"{"image": "aGVsbG8=", "frames": ["d29ybGQ="]}"#, 16).unwrap();
        assert_eq!(upload.refuse_frames().unwrap_err().kind, ProblemKind::MalformedRequest);
        assert_eq!(upload.single_image().unwrap_err().kind, ProblemKind::MalformedRequest);
    }

    #[test]
    fn json_frames_are_refused_past_four_while_parsed() {
        let many = |n: usize, tail: &str| format!(r#"{{"image": "AA", "frames": [{}]{tail}"#, vec![r#""AA""#; n].join(","));
        assert_eq!(parse_json(many(MAX_FRAMES, "}").as_bytes(), 16).unwrap().frames.len(), 4);
        let over = "at most 4 frames besides the probe (field frames), got more than 4";
        for body in [many(5, "}"), many(5, ", not json at all"), many(3_000_000, "}")] {
            let p = parse_json(body.as_bytes(), 16).unwrap_err();
            assert_eq!((p.kind, p.detail.as_str(), p.frame), (ProblemKind::MalformedRequest, over, None));
        }
    }

    #[test]
    fn json_photo_errors_name_the_photo() {
        let p = parse_json(br#"{"image": "aGVsbG8=", "images": ["d29ybGQ=", "***"]}"#, 16).unwrap_err();
        assert_eq!((p.image, p.detail.starts_with("the image is not valid base64")), (Some(2), true), "{}", p.detail);
        let p = parse_json(br#"{"images": ["d29ybGQ=", " "]}"#, 16).unwrap_err();
        assert_eq!((p.image, p.detail.as_str()), (Some(1), "the image is empty"));
    }

    #[test]
    fn json_images_are_refused_past_the_cap_while_parsed() {
        let many = |n: usize, tail: &str| format!(r#"{{"subject": "a", "images": [{}]{tail}"#, vec![r#""AA""#; n].join(","));
        // At the cap: parsed and decoded; the operation counts them (with `image`, one more).
        assert_eq!(parse_json(many(3, "}").as_bytes(), 3).unwrap().images.len(), 3);
        let with_image = format!(r#"{{"image": "AA", "images": [{}]}}"#, [r#""AA""#; 3].join(","));
        assert_eq!(parse_json(with_image.as_bytes(), 3).unwrap().images.len(), 4);
        // One past the cap: refused, whatever follows (the rest is never read).
        let over = "at most 3 photos per request (field images), got more than 3";
        for body in [many(4, "}"), many(4, ", \"extra\": 1}"), many(4, ", not json at all"), many(3_000_000, "}")] {
            let p = parse_json(body.as_bytes(), 3).unwrap_err();
            assert_eq!((p.kind, p.detail.as_str(), p.image), (ProblemKind::MalformedRequest, over, None));
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
