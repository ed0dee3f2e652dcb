//! What the recognizers and the quality model are handed: the 3DMM fit and frontal rendering
//! ([`recognition_input`]), dlib's chip with the quality components, and the avatar.

use std::borrow::Cow;
use std::path::Path;

use facegate_core::face::EyeMouthCentres;
use facegate_core::imaging::{GrayF32, Photo};

use super::PipelineError;
use super::finder::FaceFinder;
use crate::landmarks::Landmarks;
use crate::quality::Components;
use crate::recognize::Normalization;
use facegate_morph::{FaceModel, FitOptions, Pose};
use facegate_nn::FaceChip;

/// The face [`FaceModel`] when `sfm_dir` holds one; `None` (with a warning) when it does not:
/// 2D alignment only.
pub fn load_face_model(sfm_dir: Option<&Path>) -> Option<FaceModel> {
    match FaceModel::load(sfm_dir?) {
        Ok(model) => Some(model),
        Err(e) => {
            tracing::warn!("3D morphable model unavailable ({e}); falling back to 2D alignment");
            None
        }
    }
}

/// The avatar of the largest face of `photo`: the service's landmarks ([`FaceFinder::locate`]),
/// then [`FaceModel::avatar`]. `POST /avatar` and `facegate reconstruct` both come here.
pub fn reconstruct(
    finder: &FaceFinder,
    model: &FaceModel,
    photo: &Photo,
    options: &FitOptions,
    texture_size: usize,
) -> Result<facegate_morph::Avatar, PipelineError> {
    let located = finder.locate(&photo.gray)?;
    model.avatar(photo, &located.landmarks.points, options, texture_size).map_err(PipelineError::PoseCorrection)
}

/// The quality components of the face with `landmarks` in `photo`, measured on the deep
/// recognizer's chip (returned too, for a caller that embeds it). The service and the quality
/// research both come here.
pub fn quality_components(
    photo: &Photo,
    landmarks: &Landmarks,
    pose: Option<Pose>,
    fit_residual_px: Option<f32>,
) -> (FaceChip, Components) {
    let chip = crate::embed::face_chip(&photo.rgb, &landmarks.centres);
    let components = crate::quality::components(&chip, &landmarks.centres, pose, fit_residual_px);
    (chip, components)
}

/// What the recognizer normalises: a grey image, the eye and mouth centres in it, and the head pose
/// and fit residual when the 3DMM was fitted.
pub struct RecognitionInput<'a> {
    pub gray: Cow<'a, GrayF32>,
    pub centres: EyeMouthCentres,
    pub pose: Option<Pose>,
    pub fit_residual_px: Option<f32>,
}

/// Fit the 3DMM to the landmarks (when the model is loaded) for the head pose and, on the 3DMM path,
/// render the frontal view: that rendering and its eye/mouth centres are what the recognizer
/// normalises; on the 2D path it is the photo and the landmarks' centres. On the 3DMM path a failed
/// fit is an error, never a silent 2D template scored against 3DMM thresholds.
pub fn recognition_input<'a>(
    face_model: Option<&FaceModel>,
    photo: &'a Photo,
    landmarks: &Landmarks,
    normalization: Normalization,
) -> Result<RecognitionInput<'a>, PipelineError> {
    let fitted = match (face_model, normalization) {
        (Some(model), Normalization::Morph) => {
            Some(model.fit(&landmarks.points, photo.width(), photo.height()).map_err(PipelineError::PoseCorrection)?)
        }
        // On the 2D path the fit only reports the pose: a failure leaves it unknown.
        (Some(model), Normalization::TwoD) => model.fit(&landmarks.points, photo.width(), photo.height()).ok(),
        (None, Normalization::Morph) => return Err(PipelineError::NoFaceModel),
        (None, Normalization::TwoD) => None,
    };
    let pose = fitted.as_ref().map(|f| f.pose);
    let fit_residual_px = fitted.as_ref().map(|f| f.residual_px);
    match (normalization, face_model.zip(fitted)) {
        (Normalization::Morph, Some((model, fit))) => {
            let frontal = model.frontalize(photo, &fit).map_err(PipelineError::PoseCorrection)?;
            Ok(RecognitionInput { gray: Cow::Owned(GrayF32::from_rgb(&frontal.image)), centres: frontal.centres, pose, fit_residual_px })
        }
        _ => Ok(RecognitionInput { gray: Cow::Borrowed(&photo.gray), centres: landmarks.centres, pose, fit_residual_px }),
    }
}
