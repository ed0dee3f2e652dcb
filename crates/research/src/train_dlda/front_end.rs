//! Where a photo's landmarks and its view for the recognizer come from.

use std::path::{Path, PathBuf};

use serde::Serialize;

use super::*;
use crate::cache::ModelFiles;
use crate::dataset;
use facegate_core::face::{EyeMouthCentres, IMM_POINTS};
use facegate_core::imaging::{self, GrayF32};
use facegate_morph::{FaceModel, Pose};
use facegate_vision::landmarks::Landmarks;
use facegate_vision::pipeline::{FaceFinder, PipelineError, load_face_model, recognition_input};
use facegate_vision::recognize::Normalization;

/// Where the centres of a photo come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum CentreOrigin {
    /// IMM `.asf` annotations where present, else the automatic front end (detector + ASM, or
    /// detector-box centres while the ASM is not available).
    Annotated,
    /// The automatic front end for every photo.
    Pipeline,
}

#[derive(Debug, thiserror::Error)]
pub enum FrontEndError {
    #[error(transparent)]
    Decode(#[from] imaging::DecodeError),
    #[error(transparent)]
    Dataset(#[from] dataset::DatasetError),
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    #[error("no annotation and no automatic front end loaded")]
    NoCentres,
    #[error("the re-posed copies need the Surrey Face Model, which is not loaded")]
    NoFaceModel,
    #[error("the 3DMM cannot be fitted to the landmarks: {0}")]
    Fit(#[from] facegate_morph::MorphError),
}

/// A photo ready for normalisation: the grey image (the frontal rendering on the 3DMM path), the
/// eye and mouth centres in it, and the head pose when the 3DMM was fitted.
pub struct Prepared {
    pub gray: GrayF32,
    pub centres: EyeMouthCentres,
    pub pose: Option<Pose>,
    /// `imm-annotations` or `pipeline`.
    pub centre_source: &'static str,
}

/// As many threads as the machine runs at once.
fn default_threads() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

/// Where training and evaluation get a photo's landmarks and its view for the recognizer: the IMM
/// annotations, or the service's own stages ([`FaceFinder`]: detector, C-ASM, 3D-ASM), then the
/// service's [`recognition_input`] (3DMM fit and frontal rendering). Crops are thereby made as the
/// service makes them.
pub struct FrontEnd {
    pub source: CentreOrigin,
    /// The service's face finder; `None` when its models cannot be loaded (annotations only).
    pub finder: Option<FaceFinder>,
    pub face_model: Option<FaceModel>,
    /// The folder the finder's models were loaded from (its files key the crop cache).
    pub models_dir: Option<PathBuf>,
    /// The folder the 3DMM was loaded from (its files key the crop cache).
    pub sfm_dir: Option<PathBuf>,
    /// Threads the photos are prepared on.
    pub threads: usize,
}

impl FrontEnd {
    /// Annotations only (no automatic front end, no 3DMM).
    pub fn annotations_only() -> FrontEnd {
        let threads = default_threads();
        FrontEnd { source: CentreOrigin::Annotated, finder: None, face_model: None, models_dir: None, sfm_dir: None, threads }
    }

    /// The service's face finder from `models_dir` and the 3DMM from `sfm_dir`, each when it loads;
    /// a missing part only matters for the photos that need it. Photos are prepared on as many
    /// threads as the machine runs at once ([`FrontEnd::with_threads`] to choose).
    pub fn load(source: CentreOrigin, models_dir: &Path, sfm_dir: Option<&Path>) -> FrontEnd {
        let finder = FaceFinder::load(models_dir).map_err(|e| tracing::info!("automatic front end unavailable: {e}")).ok();
        let models_dir = finder.as_ref().map(|_| models_dir.to_path_buf());
        let face_model = load_face_model(sfm_dir);
        let sfm_dir = face_model.as_ref().and(sfm_dir).map(Path::to_path_buf);
        FrontEnd { source, finder, face_model, models_dir, sfm_dir, threads: default_threads() }
    }

    /// The same front end on `threads` threads.
    pub fn with_threads(self, threads: usize) -> FrontEnd {
        FrontEnd { threads: threads.max(1), ..self }
    }

    /// The model files this front end read: the finder's and the 3DMM's, those that loaded.
    pub fn model_files(&self) -> ModelFiles {
        let files = ModelFiles::new();
        let files = match &self.models_dir {
            Some(dir) => files.finder(dir),
            None => files,
        };
        match &self.sfm_dir {
            Some(dir) => files.sfm(dir),
            None => files,
        }
    }

    /// The 58 landmarks of a photo from the configured source, and which source gave them.
    pub(crate) fn landmarks(&self, face: &FaceImage, photo: &imaging::Photo) -> Result<(Landmarks, &'static str), FrontEndError> {
        if let (CentreOrigin::Annotated, Some(asf)) = (self.source, &face.asf) {
            let shape = dataset::read_asf(asf, photo.width() as f32, photo.height() as f32)?;
            if shape.points.len() == IMM_POINTS {
                let points = shape.xy();
                let centres = EyeMouthCentres::from_imm(&points);
                return Ok((Landmarks { points, centres }, "imm-annotations"));
            }
        }
        let finder = self.finder.as_ref().ok_or(FrontEndError::NoCentres)?;
        Ok((finder.locate(&photo.gray)?.landmarks, "pipeline"))
    }

    /// The face of a photo re-posed by the 3DMM: fitted to its landmarks, textured from the photo
    /// and rendered at its fitted pose plus each (yaw, pitch) offset in degrees, on a flat
    /// background of the photo's mean grey, at the photo's scale and place, with the 58 landmarks
    /// of each rendering (moved by the photo's annotation offsets, as the 3D-ASM's synthetic
    /// views are, so that they follow the same convention as the photo's own landmarks).
    pub fn reposed_views(&self, face: &FaceImage, offsets: &[(f32, f32)]) -> Result<Vec<(imaging::Photo, Landmarks)>, FrontEndError> {
        let photo = imaging::open(&face.image)?;
        let (landmarks, _) = self.landmarks(face, &photo)?;
        let model = self.face_model.as_ref().ok_or(FrontEndError::NoFaceModel)?;
        let fit = model.fit(&landmarks.points, photo.width(), photo.height())?;
        let poses: Vec<Pose> = offsets
            .iter()
            .map(|&(yaw, pitch)| Pose { yaw: fit.pose.yaw + yaw, pitch: fit.pose.pitch + pitch, roll: fit.pose.roll })
            .collect();
        Ok(crate::synthetic::render_at(model, &photo, &fit, &landmarks.points, &poses))
    }

    /// The image and centres the recognizer normalises, as the service's pipeline makes them.
    pub fn prepare(&self, face: &FaceImage, normalization: Normalization) -> Result<Prepared, FrontEndError> {
        let photo = imaging::open(&face.image)?;
        let (landmarks, centre_source) = self.landmarks(face, &photo)?;
        let input = recognition_input(self.face_model.as_ref(), &photo, &landmarks, normalization)?;
        Ok(Prepared { gray: input.gray.into_owned(), centres: input.centres, pose: input.pose, centre_source })
    }
}
