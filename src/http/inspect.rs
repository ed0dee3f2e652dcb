//! `POST /analyze`, `POST /avatar`, `POST /frontalize`: what the service sees in a photo, nothing
//! stored. The work is the service's ([`crate::service::inspect`]) and runs on the bounded pool,
//! with the limits and problem types of `/verify`.

use std::time::Instant;

use axum::Json;
use axum::extract::{Request, State};
use axum::http::header;
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};

use super::AppState;
use super::input::{read_query, read_upload};
use super::problem::{Problem, ProblemKind};
use crate::core::elapsed_ms;
use crate::detect::Face;
use crate::landmarks::Landmarks;
use crate::morph::{AvatarFormat, Pose};
use crate::pipeline::{FaceChoice, PipelineError};
use crate::service::inspect::{self, InspectError};

impl From<InspectError> for Problem {
    fn from(error: InspectError) -> Problem {
        match error {
            InspectError::Decode(e) => Problem::from_decode(&e),
            InspectError::Pipeline(PipelineError::NoFace) => Problem::new(ProblemKind::NoFace, "no face was found in the photo"),
            InspectError::Pipeline(e @ PipelineError::NoFaceModel) => Problem::new(ProblemKind::NoFaceModel, e.to_string()),
            InspectError::Pipeline(PipelineError::PoseCorrection(e)) => {
                Problem::new(ProblemKind::FitFailed, format!("the 3D morphable model could not be fitted to the face: {e}"))
            }
            InspectError::Pipeline(other) => Problem::internal(other),
        }
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct AnalyzeParams {
    faces: Option<FaceChoice>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct NoParams {}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct AvatarParams {
    format: Option<AvatarFormat>,
}

#[derive(Debug, Serialize)]
struct FaceTimings {
    landmarks_ms: f64,
    morph_ms: f64,
}

#[derive(Debug, Serialize)]
struct AnalyzedFace {
    face: Face,
    landmarks: Landmarks,
    /// Null when the 3DMM is not loaded or could not be fitted.
    pose: Option<Pose>,
    fit_residual_px: Option<f32>,
    /// Face image quality: the components and the unified score (0–100).
    quality: crate::quality::Quality,
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
async fn single_photo(request: Request) -> Result<axum::body::Bytes, Problem> {
    let upload = read_upload(request).await?;
    if upload.subject.is_some() {
        return Err(Problem::malformed("this operation takes no subject, only the photo (field image)"));
    }
    upload.single_image()
}

/// `POST /analyze?faces=largest|all`: every face found (or the largest), with box, detector score,
/// 58 landmarks and key points, pose, 3DMM fit residual and stage timings.
pub async fn analyze(State(state): State<AppState>, request: Request) -> Result<Response, Problem> {
    let start = Instant::now();
    let params: AnalyzeParams = read_query(&request)?;
    let image = single_photo(request).await?;
    let (engine, limits) = (state.0.engine.clone(), state.0.config.decode_limits);
    let choice = params.faces.unwrap_or_default();
    let analysis = state.0.pool.run(move || inspect::analyze(engine.as_ref(), &image, &limits, choice)).await??;
    let reading = analysis.reading;
    let faces = reading
        .faces
        .into_iter()
        .map(|f| AnalyzedFace {
            face: f.face,
            landmarks: f.landmarks,
            pose: f.pose,
            fit_residual_px: f.fit_residual_px,
            quality: f.quality,
            timings: FaceTimings { landmarks_ms: f.landmarks_ms, morph_ms: f.morph_ms },
        })
        .collect();
    let timings = AnalyzeTimings { decode_ms: analysis.decode_ms, detect_ms: reading.detect_ms, total_ms: elapsed_ms(start) };
    Ok(Json(AnalyzeResponse { faces_found: reading.faces_found, faces, timings }).into_response())
}

/// `POST /avatar?format=glb|obj`: the largest face's textured 3D head, `model/gltf-binary` (or
/// the OBJ files in a zip archive).
pub async fn avatar(State(state): State<AppState>, request: Request) -> Result<Response, Problem> {
    let params: AvatarParams = read_query(&request)?;
    let format = params.format.unwrap_or_default();
    let image = single_photo(request).await?;
    let (engine, limits) = (state.0.engine.clone(), state.0.config.decode_limits);
    let bytes = state.0.pool.run(move || inspect::avatar(engine.as_ref(), &image, &limits, format)).await??;
    let (media, disposition) = match format {
        AvatarFormat::Glb => ("model/gltf-binary", "inline; filename=\"avatar.glb\""),
        AvatarFormat::Obj => ("application/zip", "attachment; filename=\"avatar.zip\""),
    };
    Ok(([(header::CONTENT_TYPE, media), (header::CONTENT_DISPOSITION, disposition)], bytes).into_response())
}

/// `POST /frontalize`: the largest face rendered from the front, PNG.
pub async fn frontalize(State(state): State<AppState>, request: Request) -> Result<Response, Problem> {
    let _: NoParams = read_query(&request)?;
    let image = single_photo(request).await?;
    let (engine, limits) = (state.0.engine.clone(), state.0.config.decode_limits);
    let png = state.0.pool.run(move || inspect::frontalize(engine.as_ref(), &image, &limits)).await??;
    Ok(([(header::CONTENT_TYPE, "image/png")], png).into_response())
}
