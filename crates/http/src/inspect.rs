//! `POST /analyze`, `POST /avatar`, `POST /frontalize`: what the service sees in a photo, nothing
//! stored. The work is the service's ([`facegate_service::Facegate::analyze`] and its neighbours),
//! with the limits and problem types of `/verify`.

use std::time::Instant;

use axum::Json;
use axum::body::Bytes;
use axum::extract::State;
use axum::http::header;
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};

use super::AppState;
use super::input::{Params, Upload};
use super::problem::Problem;
use facegate_core::elapsed_ms;
use facegate_vision::detect::Face;
use facegate_vision::landmarks::Landmarks;
use facegate_vision::morph::{AvatarFormat, Pose};
use facegate_vision::pipeline::FaceChoice;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct AnalyzeParams {
    faces: Option<FaceChoice>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct NoParams {}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct AvatarParams {
    format: Option<AvatarFormat>,
}

#[derive(Debug, Serialize)]
struct FaceTimings {
    landmarks_ms: f64,
    morph_ms: f64,
}

/// The landmarks with, per point, whether the fitted head shows it to the camera.
#[derive(Debug, Serialize)]
struct SeenLandmarks {
    #[serde(flatten)]
    landmarks: Landmarks,
    /// Null when the 3DMM is not loaded or could not be fitted.
    visible: Option<Vec<bool>>,
}

#[derive(Debug, Serialize)]
struct AnalyzedFace {
    face: Face,
    landmarks: SeenLandmarks,
    /// Null when the 3DMM is not loaded or could not be fitted.
    pose: Option<Pose>,
    fit_residual_px: Option<f32>,
    /// Face image quality: the components and the unified score (0–100).
    quality: facegate_vision::quality::Quality,
    /// Live face or presentation attack (reported, never refused here); absent when liveness is off.
    #[serde(skip_serializing_if = "Option::is_none")]
    liveness: Option<facegate_vision::liveness::Liveness>,
    timings: FaceTimings,
}

#[derive(Debug, Serialize)]
struct AnalyzeTimings {
    decode_ms: f64,
    detect_ms: f64,
    total_ms: f64,
}

#[derive(Debug, Serialize)]
struct AnalyzeResponse {
    faces_found: usize,
    faces: Vec<AnalyzedFace>,
    timings: AnalyzeTimings,
}

/// The one photo of an `/analyze`, `/avatar` or `/frontalize` request (no subject).
fn single_photo(upload: Upload) -> Result<Bytes, Problem> {
    upload.refuse_subject("this operation takes no subject, only the photo (field image)")?;
    upload.single_image()
}

/// `POST /analyze?faces=largest|all`: every face found (or the largest), with box, detector score,
/// 58 landmarks and key points, pose, 3DMM fit residual, quality, liveness (reported unless off,
/// never refused: an inspection) and stage timings.
pub async fn analyze(State(state): State<AppState>, Params(params): Params<AnalyzeParams>, upload: Upload) -> Result<Response, Problem> {
    let start = Instant::now();
    let image = single_photo(upload)?;
    let analysis = state.facegate().analyze(image, params.faces.unwrap_or_default()).await?;
    let reading = analysis.reading;
    let faces = reading
        .faces
        .into_iter()
        .map(|f| AnalyzedFace {
            face: f.face,
            landmarks: SeenLandmarks { landmarks: f.landmarks, visible: f.visible },
            pose: f.pose,
            fit_residual_px: f.fit_residual_px,
            quality: f.quality,
            liveness: f.liveness,
            timings: FaceTimings { landmarks_ms: f.landmarks_ms, morph_ms: f.morph_ms },
        })
        .collect();
    let timings = AnalyzeTimings { decode_ms: analysis.decode_ms, detect_ms: reading.detect_ms, total_ms: elapsed_ms(start) };
    Ok(Json(AnalyzeResponse { faces_found: reading.faces_found, faces, timings }).into_response())
}

/// `POST /avatar?format=glb|obj`: the largest face's textured 3D head, `model/gltf-binary` (or
/// the OBJ files in a zip archive).
pub async fn avatar(State(state): State<AppState>, Params(params): Params<AvatarParams>, upload: Upload) -> Result<Response, Problem> {
    let format = params.format.unwrap_or_default();
    let image = single_photo(upload)?;
    let bytes = state.facegate().avatar(image, format).await?;
    let (media, disposition) = match format {
        AvatarFormat::Glb => ("model/gltf-binary", "inline; filename=\"avatar.glb\""),
        AvatarFormat::Obj => ("application/zip", "attachment; filename=\"avatar.zip\""),
    };
    Ok(([(header::CONTENT_TYPE, media), (header::CONTENT_DISPOSITION, disposition)], bytes).into_response())
}

/// `POST /frontalize`: the largest face rendered from the front, PNG.
pub async fn frontalize(State(state): State<AppState>, Params(NoParams {}): Params<NoParams>, upload: Upload) -> Result<Response, Problem> {
    let image = single_photo(upload)?;
    let png = state.facegate().frontalize(image).await?;
    Ok(([(header::CONTENT_TYPE, "image/png")], png).into_response())
}
