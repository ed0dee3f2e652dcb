//! What the service shows of a photo without storing anything: every face with its landmarks,
//! pose and 3DMM fit ([`analyze`]), the textured 3D head ([`avatar`]) and the frontal rendering
//! ([`frontalize`]). Each decodes the photo within the limits and runs the engine; callers in
//! async code run them on the [`super::WorkPool`].

use std::time::Instant;

use super::FaceEngine;
use facegate_core::elapsed_ms;
use facegate_core::imaging::{self, DecodeError, DecodeLimits, Photo};
use facegate_morph::AvatarFormat;
use facegate_vision::pipeline::{FaceChoice, PhotoReading, PipelineError};

/// Why a photo could not be shown.
#[derive(Debug, thiserror::Error)]
pub enum InspectError {
    #[error(transparent)]
    Decode(#[from] DecodeError),
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
}

/// An analysis, the time spent decoding the photo, and the service's verdict on each face's
/// liveness.
#[derive(Debug, Clone)]
pub struct Analysis {
    pub reading: PhotoReading,
    pub decode_ms: f64,
    /// One per face of `reading`, in order: `None` with liveness off or no model.
    pub liveness: Vec<Option<crate::LivenessVerdict>>,
}

/// The photo of `bytes` decoded within `limits`, and the milliseconds it took: the one decoding
/// step of every use case ([`crate::analyze_photo`] too).
pub fn decode_photo(bytes: &[u8], limits: &DecodeLimits) -> Result<(Photo, f64), DecodeError> {
    let start = Instant::now();
    let photo = tracing::info_span!("decode").in_scope(|| imaging::decode(bytes, limits))?;
    Ok((photo, elapsed_ms(start)))
}

/// Every face of the photo (or the largest), each with its 58 landmarks, pose and fit residual.
pub fn analyze(engine: &dyn FaceEngine, bytes: &[u8], limits: &DecodeLimits, choice: FaceChoice) -> Result<Analysis, InspectError> {
    let (photo, decode_ms) = decode_photo(bytes, limits)?;
    Ok(Analysis { reading: engine.read_faces(&photo, choice)?, decode_ms, liveness: Vec::new() })
}

/// The textured 3D head of the largest face as a glTF binary file, or the OBJ files zipped.
pub fn avatar(engine: &dyn FaceEngine, bytes: &[u8], limits: &DecodeLimits, format: AvatarFormat) -> Result<Vec<u8>, InspectError> {
    let (photo, _) = decode_photo(bytes, limits)?;
    Ok(engine.avatar(&photo, format)?)
}

/// The frontal rendering of the largest face as PNG.
pub fn frontalize(engine: &dyn FaceEngine, bytes: &[u8], limits: &DecodeLimits) -> Result<Vec<u8>, InspectError> {
    let (photo, _) = decode_photo(bytes, limits)?;
    Ok(engine.frontal_png(&photo)?)
}
