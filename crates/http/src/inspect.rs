//! `POST /analyze`, `POST /avatar`, `POST /frontalize`: what the service sees in a photo, nothing
//! stored. The work is the service's ([`facegate_service::Facegate::analyze`] and its neighbours),
//! with the limits and problem types of `/verify`.

use std::time::Instant;

use axum::Json;
use axum::body::Bytes;
use axum::extract::State;
use axum::http::header;
use axum::response::{IntoResponse, Response};
use serde::Deserialize;

use super::AppState;
use super::input::{Params, Upload};
use super::problem::Problem;
use super::responses::AnalyzeResponse;
use facegate_core::elapsed_ms;
use facegate_morph::AvatarFormat;
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

/// The one photo of an `/analyze`, `/avatar` or `/frontalize` request (no subject).
fn single_photo(upload: Upload) -> Result<Bytes, Problem> {
    upload.refuse_subject("this operation takes no subject, only the photo (field image)")?;
    upload.single_image()
}

/// `POST /analyze?faces=largest|all`: every face found (or the largest), with box, detector score,
/// 58 landmarks and eye and mouth centres, pose, 3DMM fit residual, quality, liveness (reported unless off,
/// never refused: an inspection) and stage timings.
pub async fn analyze(State(state): State<AppState>, Params(params): Params<AnalyzeParams>, upload: Upload) -> Result<Response, Problem> {
    let start = Instant::now();
    let image = single_photo(upload)?;
    let analysis = state.facegate().analyze(image, params.faces.unwrap_or_default()).await?;
    Ok(Json(AnalyzeResponse::new(analysis, elapsed_ms(start))).into_response())
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
