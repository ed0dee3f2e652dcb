//! The JSON form of an upload: `{"subject", "image", "images", "frames", "frame_steps", "challenge"}`, an object and nothing
//! else (an array in the fields' order, which serde's derive would take for the struct, is
//! malformed like any other body that is not the object), each field optional and `null` the same
//! as leaving it out. It is parsed and its base64 decoded on the blocking pool, never on the async
//! runtime. The parse counts the `images` entries as it goes and refuses the body at the first
//! entry past the most photos any operation takes ([`JsonLimit`]), and the `frames` entries
//! (`/verify`'s further frames of the probe's capture) past [`MAX_CAPTURE_FRAMES`]; until then each entry
//! stays a slice of the body (a copy only where the JSON string has escapes), so a body of millions
//! of tiny photos costs neither memory nor time beyond the body itself.

use std::borrow::Cow;
use std::cell::Cell;
use std::fmt;

use axum::body::Bytes;
use axum::extract::{FromRequest, Request};
use axum::http::StatusCode;
use base64::Engine as _;
use serde::Deserialize;
use serde::de::{self, DeserializeSeed, MapAccess, SeqAccess, Visitor};

use super::{Upload, too_many_frames, too_many_photos};
use crate::problem::{Problem, ProblemKind};
use facegate_service::MAX_CAPTURE_FRAMES;

/// Read a JSON body, then parse it and decode its photos on the blocking pool: a large body takes
/// no time from the async runtime's other requests.
pub(super) async fn read_json(request: Request, max_photos: usize) -> Result<Upload, Problem> {
    let body = Bytes::from_request(request, &()).await.map_err(|e| {
        if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
            Problem::new(ProblemKind::TooLarge, "the request body exceeds the size limit")
        } else {
            Problem::malformed(format!("cannot read the body: {}", e.body_text()))
        }
    })?;
    tokio::task::spawn_blocking(move || parse_json(&body, max_photos)).await.map_err(Problem::internal)?
}

/// Parse a JSON body (at most `max_photos` entries in `images`, [`MAX_CAPTURE_FRAMES`] in `frames`) and
/// decode its photos, `image` first, then its frames.
fn parse_json(body: &[u8], max_photos: usize) -> Result<Upload, Problem> {
    let (over, frames_over) = (Cell::new(false), Cell::new(false));
    let mut de = serde_json::Deserializer::from_slice(body);
    let limit = JsonLimit { max_photos, over: &over, frames_over: &frames_over };
    let parsed = limit.deserialize(&mut de).and_then(|json| de.end().map(|()| json));
    let json = parsed.map_err(|e| {
        if over.get() {
            too_many_photos("images", max_photos)
        } else if frames_over.get() {
            too_many_frames("frames")
        } else {
            Problem::malformed(format!("invalid JSON body: {e}"))
        }
    })?;
    let strings = json.image.into_iter().chain(json.images.into_iter().flatten());
    let images = strings.enumerate().map(|(index, s)| decode_base64(&s.0).map_err(|p| p.for_image(index))).collect::<Result<_, _>>()?;
    let frames = json.frames.iter().flatten().enumerate().map(|(index, s)| decode_base64(&s.0).map_err(|p| p.for_frame(index)));
    let challenge = json.challenge.map(|c| c.chars().take(64).collect());
    let frame_steps = json.frame_steps.map(|v| v.into_iter().map(usize::from).collect());
    Ok(Upload { subject: json.subject, images, frames: frames.collect::<Result<_, _>>()?, frame_steps, challenge })
}

/// The JSON form of a request: base64 photos (a `data:` URL prefix is allowed), each still the
/// body's text. Unknown fields are refused; `images` and `frames`, when present and not null, must
/// be arrays.
#[derive(Debug)]
struct JsonUpload<'a> {
    subject: Option<String>,
    image: Option<Base64Text<'a>>,
    images: Option<Vec<Base64Text<'a>>>,
    frames: Option<Vec<Base64Text<'a>>>,
    challenge: Option<String>,
    frame_steps: Option<Vec<u8>>,
}

const FIELDS: &[&str] = &["subject", "image", "images", "frames", "challenge", "frame_steps"];

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
/// (same errors), except that an array is refused (the derive takes one as the struct's fields in
/// order) and that `images` is refused at its entry `max_photos + 1` and `frames` at its entry
/// `MAX_CAPTURE_FRAMES + 1`, before that entry is kept; `over` or `frames_over` then says so.
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
        let mut json = JsonUpload { subject: None, image: None, images: None, frames: None, challenge: None, frame_steps: None };
        let mut seen = [false; FIELDS.len()];
        while let Some(Field(index)) = map.next_key::<Field>()? {
            if std::mem::replace(&mut seen[index], true) {
                return Err(de::Error::duplicate_field(FIELDS[index]));
            }
            match index {
                0 => json.subject = map.next_value()?,
                1 => json.image = map.next_value()?,
                2 => json.images = map.next_value_seed(NullOr(PhotoList { max: self.max_photos, over: self.over }))?,
                4 => json.challenge = map.next_value()?,
                5 => json.frame_steps = map.next_value_seed(NullOr(StepList))?,
                _ => json.frames = map.next_value_seed(NullOr(PhotoList { max: MAX_CAPTURE_FRAMES, over: self.frames_over }))?,
            }
        }
        Ok(json)
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

/// A field that is null (as if left out) or what `S` reads: the `images` and `frames` arrays of
/// photos ([`PhotoList`]), the `frame_steps` array of step numbers ([`StepList`]).
struct NullOr<S>(S);

impl<'de, S: DeserializeSeed<'de>> DeserializeSeed<'de> for NullOr<S> {
    type Value = Option<S::Value>;

    fn deserialize<D: de::Deserializer<'de>>(self, deserializer: D) -> Result<Self::Value, D::Error> {
        deserializer.deserialize_option(self)
    }
}

impl<'de, S: DeserializeSeed<'de>> Visitor<'de> for NullOr<S> {
    type Value = Option<S::Value>;

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
        self.0.deserialize(deserializer).map(Some)
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

/// The `frame_steps` array of step numbers, refused past [`MAX_CAPTURE_FRAMES`] entries before
/// they are kept.
struct StepList;

impl<'de> DeserializeSeed<'de> for StepList {
    type Value = Vec<u8>;

    fn deserialize<D: de::Deserializer<'de>>(self, deserializer: D) -> Result<Self::Value, D::Error> {
        deserializer.deserialize_seq(self)
    }
}

impl<'de> Visitor<'de> for StepList {
    type Value = Vec<u8>;

    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("an array of step numbers (0-based), one per frame")
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
        let mut steps = Vec::new();
        while let Some(StepNumber(step)) = seq.next_element()? {
            if steps.len() == MAX_CAPTURE_FRAMES {
                return Err(de::Error::custom(format_args!("frame_steps names more than {MAX_CAPTURE_FRAMES} frames")));
            }
            steps.push(step);
        }
        Ok(steps)
    }
}

/// One step number, 0 to 255: JSON Schema's integer, so `2.0` is the step 2 as `2` is.
#[derive(Debug)]
struct StepNumber(u8);

impl<'de> Deserialize<'de> for StepNumber {
    fn deserialize<D: de::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct Step;
        impl Visitor<'_> for Step {
            type Value = StepNumber;

            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a step number, an integer from 0 to 255")
            }

            fn visit_u64<E: de::Error>(self, v: u64) -> Result<StepNumber, E> {
                u8::try_from(v).map(StepNumber).map_err(|_| E::invalid_value(de::Unexpected::Unsigned(v), &self))
            }

            fn visit_i64<E: de::Error>(self, v: i64) -> Result<StepNumber, E> {
                u8::try_from(v).map(StepNumber).map_err(|_| E::invalid_value(de::Unexpected::Signed(v), &self))
            }

            fn visit_f64<E: de::Error>(self, v: f64) -> Result<StepNumber, E> {
                if v.fract() == 0.0 && (0.0..=255.0).contains(&v) {
                    Ok(StepNumber(v as u8))
                } else {
                    Err(E::invalid_value(de::Unexpected::Float(v), &self))
                }
            }
        }
        deserializer.deserialize_any(Step)
    }
}

pub(super) fn decode_base64(s: &str) -> Result<Bytes, Problem> {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_with_and_without_padding_or_data_url() {
        assert_eq!(&decode_base64("aGVsbG8=").unwrap()[..], b"hello");
        assert_eq!(&decode_base64("aGVsbG8").unwrap()[..], b"hello");
        assert_eq!(&decode_base64("data:image/png;base64,aGVsbG8=").unwrap()[..], b"hello");
        assert_eq!(&decode_base64("00").unwrap()[..], &[0xd3]);
        assert!(decode_base64("not base64!").is_err() && decode_base64("A").is_err());
        assert!(decode_base64("").is_err() && decode_base64("data:image/png;base64,").is_err());
    }

    /// The derived form `parse_json` replaced: its errors are the reference (for objects).
    #[derive(Debug, Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct JsonUpload {
        subject: Option<String>,
        image: Option<String>,
        images: Option<Vec<String>>,
        frames: Option<Vec<String>>,
        challenge: Option<String>,
        frame_steps: Option<Vec<StepNumber>>,
    }

    fn detail(body: &str, max_photos: usize) -> String {
        parse_json(body.as_bytes(), max_photos).unwrap_err().detail
    }

    #[test]
    fn json_errors_are_the_derived_ones() {
        let bodies = [
            "{not json",
            "",
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
            r#"{"subject": "\ud800"}"#,
            r#"{"images": ["\ud800"]}"#,
            r#"{"images": ["aGVs\q"]}"#,
            r#"{"images": ["aGVsbG8="]"#,
            r#"{"frames": "aGVsbG8="}"#,
            r#"{"frames": [1]}"#,
            r#"{"frames": [], "frames": []}"#,
            r#"{"frames": ["aGVsbG8="], "extra": 1}"#,
            r#"{"challenge": 1}"#,
            r#"{"challenge": "a", "challenge": "b"}"#,
            r#"{"frame_steps": [0], "frame_steps": [0]}"#,
            r#"{"frame_steps": ["0"]}"#,
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
        for body in [r#"{"subject": "a", "images": null, "image": null}"#, "{}", r#"{"images": null, "frames": null}"#] {
            let upload = parse_json(body.as_bytes(), 2).unwrap();
            assert!(upload.images.is_empty() && upload.frames.is_empty(), "{body}");
        }
    }

    /// One shape: the array serde's derive would take for the struct is malformed, as any other
    /// body that is not the object, whatever it holds.
    #[test]
    fn json_arrays_are_refused() {
        for body in ["[]", r#"["a"]"#, r#"[null, null, null]"#, r#"["a", "aGVsbG8=", ["d29ybGQ="]]"#, r#"["a", "aGVsbG8", null, []]"#] {
            let p = parse_json(body.as_bytes(), 2).unwrap_err();
            assert_eq!(p.kind, ProblemKind::MalformedRequest, "{body}");
            assert!(p.detail.starts_with("invalid JSON body: invalid type: sequence, expected struct JsonUpload"), "{body}: {}", p.detail);
        }
    }

    #[test]
    fn json_frames_in_order_apart_from_the_photos() {
        let body = r#"{"frames": ["d29ybGQ=", "data:image/png;base64,IQ=="], "subject": "a", "image": "aGVsbG8"}"#;
        let upload = parse_json(body.as_bytes(), 1).unwrap();
        let frames: Vec<&[u8]> = upload.frames.iter().map(|b| &b[..]).collect();
        assert_eq!((upload.images.len(), frames), (1, vec![&b"world"[..], b"!"]));
        for body in [r#"{"image": "aGVsbG8", "frames": []}"#, r#"{"image": "aGVsbG8"}"#, r#"{"image": "aGVsbG8", "frames": null}"#] {
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
    fn json_frames_are_refused_past_a_challenges_bursts_while_parsed() {
        let many = |n: usize, tail: &str| format!(r#"{{"image": "AA", "frames": [{}]{tail}"#, vec![r#""AA""#; n].join(","));
        assert_eq!(parse_json(many(MAX_CAPTURE_FRAMES, "}").as_bytes(), 16).unwrap().frames.len(), 20);
        let over = "at most 20 frames besides the probe (field frames), got more than 20";
        for body in [many(21, "}"), many(21, ", not json at all"), many(3_000_000, "}")] {
            let p = parse_json(body.as_bytes(), 16).unwrap_err();
            assert_eq!((p.kind, p.detail.as_str(), p.frame), (ProblemKind::MalformedRequest, over, None));
        }
    }

    #[test]
    fn json_frame_steps_are_step_numbers_or_null_and_bounded() {
        let upload = parse_json(br#"{"image": "AA", "frames": ["AA", "AA"], "frame_steps": [0, 1]}"#, 16).unwrap();
        assert_eq!(upload.frame_steps, Some(vec![0, 1]));
        let upload = parse_json(br#"{"image": "AA", "frame_steps": null}"#, 16).unwrap();
        assert_eq!(upload.frame_steps, None);
        // JSON Schema's integers: 2.0 is 2.
        let upload = parse_json(br#"{"image": "AA", "frame_steps": [0, 1.0, 2e0]}"#, 16).unwrap();
        assert_eq!(upload.frame_steps, Some(vec![0, 1, 2]));
        let refused =
            [r#"{"frame_steps": [-1]}"#, r#"{"frame_steps": [256]}"#, r#"{"frame_steps": [256.0]}"#, r#"{"frame_steps": [-1.0]}"#];
        for body in refused.into_iter().chain([r#"{"frame_steps": "0,1"}"#, r#"{"frame_steps": [0.5]}"#, r#"{"frame_steps": [null]}"#]) {
            assert_eq!(parse_json(body.as_bytes(), 16).unwrap_err().kind, ProblemKind::MalformedRequest, "{body}");
        }
        let many = format!(r#"{{"frame_steps": [{}]}}"#, vec!["0"; 21].join(","));
        assert!(parse_json(many.as_bytes(), 16).unwrap_err().detail.contains("more than 20"));
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
}
