//! The request path, stage by stage: decoded photo → face box → landmarks → (3DMM pose
//! correction) → normalised face → template. Used by the CLI, the HTTP API and the evaluation
//! tools alike. Everything here is synchronous and CPU-bound: callers in async code run it on a
//! blocking pool.

use std::borrow::Cow;
use std::path::{Path, PathBuf};
use std::time::Instant;

use facegate_core::elapsed_ms;

use serde::Serialize;

use crate::detect::{Detector, DetectorKind, Face};
use crate::embed::FaceChip;
use crate::landmarks::asm3d::{Asm3dLandmarker, DETECTOR_SEED_MIN_YAW, SERVICE_MIN_YAW};
use crate::landmarks::{Landmarker, Landmarks, Variant};
use crate::liveness::{Liveness, LivenessModel};
use crate::morph::key_points::HIDDEN_SIDE_YAW;
use crate::morph::{AVATAR_TEXTURE_SIZE, AvatarFormat, FRONTAL_VIEW_SIZE, FaceModel, FitOptions, FittedFace, Pose};
use crate::quality::{Components, Quality, QualityModel};
use crate::recognize::{
    ClassicalRecognizer, DeepRecognizer, EmbeddingRecognizer, Normalization, Recognizer, RecognizerKind, Template, Views,
};
use facegate_core::face::KeyPoints;
use facegate_core::geometry::{Point, Rect};
use facegate_core::imaging::{GrayF32, Photo};

/// Where the pipeline's models are.
#[derive(Debug, Clone)]
pub struct PipelineConfig {
    /// The project's trained models (cascades, `asm.bin`, `dlda.bin`).
    pub models_dir: PathBuf,
    /// The Surrey Face Model folder; `None` or missing files mean 2D alignment only.
    pub sfm_dir: Option<PathBuf>,
    /// The deep embedding (`deep.bin`) or the classical DLDA (`dlda.bin`).
    pub recognizer: RecognizerKind,
    /// The face detector.
    pub detector: DetectorKind,
}

/// The 2D-alignment recognition model used when the 3DMM is unavailable.
pub const TWO_D_MODEL_FILE: &str = "dlda-2d.bin";

#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error("the recognition model needs the 3D morphable model, which is unavailable, and {0} is not a 2D model")]
    NoTwoDModel(String),
    #[error("no face was found in the image")]
    NoFace,
    #[error("the face could not be pose-corrected: {0}")]
    PoseCorrection(crate::morph::MorphError),
    #[error("this needs the 3D morphable model, which is not loaded (the Surrey Face Model folder: --sfm, FACEGATE_SFM)")]
    NoFaceModel,
    #[error(transparent)]
    Detect(#[from] crate::detect::DetectError),
    #[error(transparent)]
    Landmarks(#[from] crate::landmarks::LandmarkError),
    #[error(transparent)]
    Recognize(#[from] crate::recognize::RecognizeError),
    #[error(transparent)]
    Quality(#[from] crate::quality::QualityModelError),
    #[error(transparent)]
    Liveness(#[from] crate::liveness::LivenessModelError),
}

/// Milliseconds spent in each stage of one analysis.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct StageTimings {
    pub detect_ms: f64,
    pub landmarks_ms: f64,
    pub morph_ms: f64,
    pub template_ms: f64,
    pub quality_ms: f64,
    pub liveness_ms: f64,
}

/// Everything the pipeline learnt about the face it used.
#[derive(Debug, Clone)]
pub struct FaceAnalysis {
    /// The face used: the largest one found.
    pub face: Face,
    /// How many faces the detector found.
    pub faces_found: usize,
    pub landmarks: Landmarks,
    /// Head pose from the 3DMM fit, when the model is loaded.
    pub pose: Option<Pose>,
    pub template: Template,
    /// The face image quality components and unified score.
    pub quality: Quality,
    /// Live face or printed photo; `None` when no liveness model is loaded.
    pub liveness: Option<Liveness>,
    pub timings: StageTimings,
}

/// Which faces of a photo [`Pipeline::read_faces`] reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FaceChoice {
    /// The largest face only.
    #[default]
    Largest,
    /// Every face found, largest first.
    All,
}

/// One face read in full: where it is, its landmarks, and the 3DMM fit's pose and residual.
#[derive(Debug, Clone)]
pub struct FaceReading {
    pub face: Face,
    pub landmarks: Landmarks,
    /// Head pose from the 3DMM fit; `None` when the model is not loaded or the fit failed.
    pub pose: Option<Pose>,
    /// RMS distance in pixels between the landmarks and the fitted model's points.
    pub fit_residual_px: Option<f32>,
    /// Per landmark, whether the fitted head shows it to the camera (`None` without a fit).
    pub visible: Option<Vec<bool>>,
    pub quality: Quality,
    /// Live face or printed photo; `None` when no liveness model is loaded.
    pub liveness: Option<Liveness>,
    pub landmarks_ms: f64,
    pub morph_ms: f64,
}

/// What [`Pipeline::read_faces`] found in a photo.
#[derive(Debug, Clone)]
pub struct PhotoReading {
    pub faces_found: usize,
    /// Largest first: one face or all of them, as asked.
    pub faces: Vec<FaceReading>,
    pub detect_ms: f64,
}

/// The stages that find a face and its 58 landmarks: the detector, the C-ASM and, on turned
/// faces, the 3D-ASM. The service's [`Pipeline`] and the training and evaluation tools use this one
/// chain, so their landmarks are the same.
pub struct FaceFinder {
    pub detector: Detector,
    pub landmarker: Landmarker,
    /// The 3D-ASM (`asm3d.bin`), used instead of the C-ASM on turned faces; `None` when the file
    /// is missing: C-ASM only.
    pub asm3d: Option<Asm3dLandmarker>,
    /// The 3D-ASM with views to full profile (`asm3d-profile.bin`), seeded by the detector's five
    /// points on heads turned past [`FaceFinder::detector_seed_min_yaw`]; `None` when the file is
    /// missing.
    pub profile: Option<Asm3dLandmarker>,
    /// Where the eye and mouth centres the chip is cut at come from.
    pub keypoints: KeypointSource,
    /// |yaw| (degrees) of the detector's five points from which the 3D-ASM is seeded by them
    /// ([`Asm3dLandmarker::fit_from_detector`]) instead of by the C-ASM; `None`: never.
    pub detector_seed_min_yaw: Option<f32>,
}

/// Where the recognizer's eye and mouth centres come from, for a face whose detector gave its own
/// five points (YuNet); faces without them always take the landmarks'.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum KeypointSource {
    /// The 58 landmarks' eye and mouth centres.
    Landmarks,
    /// The detector's eyes and the middle of its mouth corners.
    Detector,
    /// The detector's when its points show the head turned by at least this much (the nose tip's
    /// offset from the eyes' midpoint over the eye distance), the landmarks' otherwise.
    DetectorWhenTurned(f32),
}

impl Default for KeypointSource {
    fn default() -> Self {
        KeypointSource::Landmarks
    }
}

/// How far the detector's five points show the head turned: the nose tip's horizontal offset from
/// the eyes' midpoint, over the distance between the eyes (0 facing the camera, about ±0.5 at
/// 45°, larger still as the far eye closes in on the nose).
pub fn detector_turn(points: &[Point; 5]) -> f32 {
    let [left_eye, right_eye, nose, _, _] = *points;
    let eye_distance = ((right_eye[0] - left_eye[0]).powi(2) + (right_eye[1] - left_eye[1]).powi(2)).sqrt().max(1e-3);
    (nose[0] - 0.5 * (left_eye[0] + right_eye[0])) / eye_distance
}

/// The box the Viola–Jones cascade would draw around a face with these five points: the landmark
/// models were trained from cascade boxes, and YuNet's boxes sit elsewhere on the head (seeded from
/// them the C-ASM lost most of its accuracy). Measured over 975 IMM, ORL and LFW faces both
/// detectors found: the cascade's side is 2.64 times the distance from the eyes' midpoint to the
/// mouth's (IMM; 2.55 on LFW, 2.40 on ORL) and its centre lies 0.27 of that distance from the
/// eyes towards the mouth, with no sideways offset.
pub fn cascade_like_box(points: &[Point; 5]) -> Rect {
    let k = detector_keypoints(points);
    let eyes = [0.5 * (k.left_eye[0] + k.right_eye[0]), 0.5 * (k.left_eye[1] + k.right_eye[1])];
    let (dx, dy) = (k.mouth[0] - eyes[0], k.mouth[1] - eyes[1]);
    let d = (dx * dx + dy * dy).sqrt();
    let side = 2.64 * d;
    let centre = [eyes[0] + 0.27 * dx, eyes[1] + 0.27 * dy];
    Rect::new(centre[0] - 0.5 * side, centre[1] - 0.5 * side, side, side)
}

/// The box the landmark search starts from: the detector's own, or for a face with five points,
/// the [`cascade_like_box`] around them.
pub fn seed_box(face: &Face) -> Rect {
    face.points.as_ref().map_or(face.rect, cascade_like_box)
}

/// The eye and mouth centres of a detector's five points.
pub fn detector_keypoints(points: &[Point; 5]) -> KeyPoints {
    let [left_eye, right_eye, _, mouth_left, mouth_right] = *points;
    KeyPoints { left_eye, right_eye, mouth: [0.5 * (mouth_left[0] + mouth_right[0]), 0.5 * (mouth_left[1] + mouth_right[1])] }
}

impl FaceFinder {
    /// The cascades (or SeetaFace), `asm.bin` and, when the files exist, `asm3d.bin` and
    /// `asm3d-profile.bin` of `models_dir`.
    pub fn load(models_dir: &Path) -> Result<FaceFinder, PipelineError> {
        FaceFinder::load_with(models_dir, DetectorKind::default())
    }

    /// [`FaceFinder::load`] with the detector `kind`.
    pub fn load_with(models_dir: &Path, kind: DetectorKind) -> Result<FaceFinder, PipelineError> {
        let detector = Detector::load_kind(models_dir, kind)?;
        let landmarker = Landmarker::load(&models_dir.join("asm.bin"))?;
        let asm3d_path = models_dir.join("asm3d.bin");
        let asm3d = if asm3d_path.exists() { Some(Asm3dLandmarker::load(&asm3d_path)?) } else { None };
        let profile_path = models_dir.join("asm3d-profile.bin");
        let profile = if profile_path.exists() { Some(Asm3dLandmarker::load_profile(&profile_path)?) } else { None };
        Ok(FaceFinder {
            detector,
            landmarker,
            asm3d,
            profile,
            keypoints: KeypointSource::default(),
            detector_seed_min_yaw: Some(DETECTOR_SEED_MIN_YAW),
        })
    }

    /// The faces in `gray`, largest first.
    pub fn detect(&self, gray: &GrayF32) -> Vec<Face> {
        self.detector.detect(gray)
    }

    /// The service's 58 landmarks of the face in `face`: the C-ASM's, or, when the 3D-ASM is
    /// loaded and the C-ASM's points are turned by at least [`SERVICE_MIN_YAW`], the 3D-ASM's
    /// refined by the C-ASM (the crossover measured in docs/asm3d.md).
    pub fn landmarks(&self, gray: &GrayF32, face: &Rect) -> Landmarks {
        let casm = self.landmarker.fit(gray, face, Variant::Casm);
        match &self.asm3d {
            Some(asm3d) => asm3d.switch(gray, face, &self.landmarker, casm, SERVICE_MIN_YAW).0,
            None => casm,
        }
    }

    /// The landmarks of a detected face: [`FaceFinder::landmarks`] in its box; on a head whose
    /// five detector points show it turned by [`FaceFinder::detector_seed_min_yaw`] or more, the
    /// points are replaced by the 3D-ASM's seeded by those points (its views go to full profile),
    /// the key points kept. The key points are taken from the detector's own points where
    /// [`FaceFinder::keypoints`] says so.
    pub fn landmarks_of(&self, gray: &GrayF32, face: &Face) -> Landmarks {
        let mut landmarks = self.landmarks(gray, &seed_box(face));
        if let Some(profile) = self.profile_landmarks(gray, face) {
            // The points are the profile search's; the chip keeps the C-ASM path's eye and mouth
            // centres. Measured on UMIST s01–s10 (`facegate eval pose`, fusion): chips cut at the
            // profile search's centres, whose far eye is foreshortened behind the nose, took the
            // EER from 10.5% to 28.0% over all pairs.
            landmarks.points = profile.points;
        }
        if let Some(points) = &face.points {
            let use_detector = match self.keypoints {
                KeypointSource::Landmarks => false,
                KeypointSource::Detector => true,
                KeypointSource::DetectorWhenTurned(turn) => detector_turn(points).abs() >= turn,
            };
            if use_detector {
                landmarks.keypoints = detector_keypoints(points);
            }
        }
        landmarks
    }

    /// Whether the face's landmarks come from the profile model seeded by its five detector
    /// points: the model is loaded and the points show the head turned by at least
    /// [`FaceFinder::detector_seed_min_yaw`].
    pub fn profile_seeded(&self, face: &Face) -> bool {
        let (Some(profile), Some(points), Some(min_yaw)) = (&self.profile, &face.points, self.detector_seed_min_yaw) else { return false };
        profile.detector_yaw(points).is_some_and(|yaw| yaw.abs() >= min_yaw)
    }

    /// The 3D-ASM's landmarks seeded by the detector's five points, when the face has them and
    /// they show the head turned by at least [`FaceFinder::detector_seed_min_yaw`].
    fn profile_landmarks(&self, gray: &GrayF32, face: &Face) -> Option<Landmarks> {
        if !self.profile_seeded(face) {
            return None;
        }
        let found = self.profile.as_ref()?.fit_from_detector(gray, face.points.as_ref()?, &self.landmarker.model)?;
        Some(Landmarks { points: found.points, keypoints: found.keypoints })
    }

    /// The largest face of `gray` and its landmarks.
    pub fn locate(&self, gray: &GrayF32) -> Result<Located, PipelineError> {
        let faces = self.detect(gray);
        let face = *faces.first().ok_or(PipelineError::NoFace)?;
        Ok(Located { face, faces_found: faces.len(), landmarks: self.landmarks_of(gray, &face) })
    }
}

/// The face [`FaceFinder::locate`] chose, with its landmarks.
#[derive(Debug, Clone)]
pub struct Located {
    /// The largest face found.
    pub face: Face,
    pub faces_found: usize,
    pub landmarks: Landmarks,
}

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

/// The stages assembled: photo → face → landmarks → (3DMM pose correction) → template.
pub struct Pipeline {
    pub finder: FaceFinder,
    /// `None` when the Surrey Face Model is not available: 2D alignment only.
    pub face_model: Option<FaceModel>,
    pub recognizer: Recognizer,
    /// The unified quality score's model (`quality.bin`).
    pub quality: QualityModel,
    /// The liveness model (`liveness.bin`); `None` when the file is missing, or when the caller
    /// has no use for it (the service with liveness off drops it: no time is spent on it).
    pub liveness: Option<LivenessModel>,
}

impl Pipeline {
    /// Load every stage. The deep recognizer is `deep.bin` over `embedding.bin`. The classical
    /// one is `dlda.bin`; when it was trained on 3DMM frontal renderings and the Surrey Face Model
    /// is unavailable, the 2D model `dlda-2d.bin` is used instead (with a warning), so that
    /// templates are never scored against thresholds calibrated for the other normalisation. Every
    /// model's templates carry its own version, so subjects enrolled under one model are not
    /// compared with probes of another.
    pub fn load(config: &PipelineConfig) -> Result<Pipeline, PipelineError> {
        let finder = FaceFinder::load_with(&config.models_dir, config.detector)?;
        let face_model = load_face_model(config.sfm_dir.as_deref());
        let recognizer = match config.recognizer {
            RecognizerKind::Deep => Recognizer::Deep(Box::new(DeepRecognizer::load(&config.models_dir)?)),
            RecognizerKind::Classical => Recognizer::Classical(load_classical(config, face_model.is_some())?),
            kind @ (RecognizerKind::Sface | RecognizerKind::Fusion | RecognizerKind::Custom) => {
                let file = kind.embedding_model_file().expect("an embedding recognizer");
                Recognizer::Embedding(Box::new(EmbeddingRecognizer::load(&config.models_dir, file)?), kind)
            }
        };
        let quality = QualityModel::load(&config.models_dir.join(crate::quality::FILE))?;
        let liveness_path = config.models_dir.join(crate::liveness::FILE);
        let liveness = if liveness_path.exists() { Some(LivenessModel::load(&liveness_path)?) } else { None };
        Ok(Pipeline { finder, face_model, recognizer, quality, liveness })
    }

    /// Detect, landmark, pose-correct and template the largest face of `photo`.
    pub fn analyze(&self, photo: &Photo) -> Result<FaceAnalysis, PipelineError> {
        let mut timings = StageTimings::default();
        let t = Instant::now();
        let faces = self.finder.detect(&photo.gray);
        timings.detect_ms = elapsed_ms(t);
        let face = *faces.first().ok_or(PipelineError::NoFace)?;

        let t = Instant::now();
        let landmarks = self.finder.landmarks_of(&photo.gray, &face);
        timings.landmarks_ms = elapsed_ms(t);

        let (template, pose, quality) = match &self.recognizer {
            Recognizer::Classical(recognizer) => self.classical_template(recognizer, photo, &landmarks, &mut timings)?,
            _ => self.embedding_template(photo, &face, &landmarks, &mut timings)?,
        };
        let t = Instant::now();
        let liveness = self.liveness_of(photo, &landmarks);
        timings.liveness_ms = elapsed_ms(t);
        Ok(FaceAnalysis { face, faces_found: faces.len(), landmarks, pose, template, quality, liveness, timings })
    }

    /// The deep recognizers' template (dlib's network, SFace, their fusion, a user's network)
    /// with the head pose and the quality.
    fn embedding_template(
        &self,
        photo: &Photo,
        face: &Face,
        landmarks: &Landmarks,
        timings: &mut StageTimings,
    ) -> Result<(Template, Option<Pose>, Quality), PipelineError> {
        // The networks see the photo itself (the 3DMM frontal rendering measured worse as the
        // dlib network's input: docs/recognition.md); the fit still reports the head pose.
        let t = Instant::now();
        let mut input = recognition_input(self.face_model.as_ref(), photo, landmarks, Normalization::TwoD)?;
        if let Some(fit) = self.profile_fit(photo, face) {
            (input.pose, input.fit_residual_px) = (Some(fit.pose), Some(fit.residual_px));
        }
        timings.morph_ms = elapsed_ms(t);
        let t = Instant::now();
        // The quality components are measured on dlib's chip whichever network embeds.
        let chip = crate::embed::face_chip(&photo.rgb, &landmarks.keypoints);
        let (template, mirror) = match &self.recognizer {
            Recognizer::Embedding(recognizer, _) => {
                let embedded = recognizer.embed(&photo.rgb, &landmarks.keypoints, face.points.as_ref(), Some(&chip));
                (embedded.template, embedded.dlib_pair)
            }
            Recognizer::Deep(deep) => {
                let (template, mirror) = deep.template_and_mirror_pair(&chip);
                (template, Some(mirror))
            }
            Recognizer::Classical(recognizer) => return self.classical_template(recognizer, photo, landmarks, timings),
        };
        timings.template_ms = elapsed_ms(t);
        let t = Instant::now();
        let components = crate::quality::components(&chip, &landmarks.keypoints, input.pose, input.fit_residual_px);
        let components = match &mirror {
            Some(mirror) => components.with_mirror(mirror),
            None => components,
        };
        let quality = self.quality.assess(components);
        timings.quality_ms = elapsed_ms(t);
        Ok((template, input.pose, quality))
    }

    /// Every face of `photo` (or the largest) with its landmarks and 3DMM fit; no template is made.
    pub fn read_faces(&self, photo: &Photo, choice: FaceChoice) -> Result<PhotoReading, PipelineError> {
        let t = Instant::now();
        let faces = self.finder.detect(&photo.gray);
        let detect_ms = elapsed_ms(t);
        if faces.is_empty() {
            return Err(PipelineError::NoFace);
        }
        let wanted = if choice == FaceChoice::All { faces.len() } else { 1 };
        let readings = faces[..wanted]
            .iter()
            .map(|&face| {
                let t = Instant::now();
                let landmarks = self.finder.landmarks_of(&photo.gray, &face);
                let landmarks_ms = elapsed_ms(t);
                let t = Instant::now();
                let fit = self
                    .profile_fit(photo, &face)
                    .or_else(|| self.face_model.as_ref().and_then(|m| m.fit(&landmarks.points, photo.width(), photo.height()).ok()));
                let morph_ms = elapsed_ms(t);
                let (pose, fit_residual_px) = (fit.as_ref().map(|f| f.pose), fit.as_ref().map(|f| f.residual_px));
                let visible = self.face_model.as_ref().zip(fit.as_ref()).map(|(m, f)| m.landmark_visibility(f));
                let quality = self.quality.assess(quality_components(photo, &landmarks, pose, fit_residual_px).1);
                let liveness = self.liveness_of(photo, &landmarks);
                FaceReading { face, landmarks, pose, fit_residual_px, visible, quality, liveness, landmarks_ms, morph_ms }
            })
            .collect();
        Ok(PhotoReading { faces_found: faces.len(), faces: readings, detect_ms })
    }

    /// On a head the detector's five points show turned past [`HIDDEN_SIDE_YAW`] whose landmarks
    /// are the C-ASM's (no profile model loaded), the mean face fitted to those points: there the
    /// C-ASM's 58 points, and the fit to them, are unreliable. With the profile model's landmarks
    /// the 3DMM fit to them stands: on renders of held-out faces its yaw was 7–18° off at 60–90°,
    /// the five-point fit's 18–33° (`facegate eval landmarks`, docs/pose.md).
    fn profile_fit(&self, photo: &Photo, face: &Face) -> Option<FittedFace> {
        if self.finder.profile_seeded(face) {
            return None;
        }
        let fit = self.face_model.as_ref()?.fit_key_points(face.points.as_ref()?, photo.width(), photo.height()).ok()?;
        (fit.pose.yaw.abs() >= HIDDEN_SIDE_YAW).then_some(fit)
    }

    /// The liveness of the face with `landmarks`, measured where the recognizer cuts its chip.
    fn liveness_of(&self, photo: &Photo, landmarks: &Landmarks) -> Option<Liveness> {
        self.liveness.as_ref().map(|model| model.assess(&photo.rgb, &landmarks.keypoints))
    }

    fn face_model(&self) -> Result<&FaceModel, PipelineError> {
        self.face_model.as_ref().ok_or(PipelineError::NoFaceModel)
    }

    /// The textured 3D head of the largest face as a glTF binary file, or the OBJ files zipped: the
    /// bytes `facegate reconstruct --out avatar.glb` (or the files `--out avatar.obj`) writes for
    /// the same photo ([`reconstruct`]).
    pub fn avatar(&self, photo: &Photo, format: AvatarFormat) -> Result<Vec<u8>, PipelineError> {
        let model = self.face_model()?;
        let avatar = reconstruct(&self.finder, model, photo, &FitOptions::default(), AVATAR_TEXTURE_SIZE)?;
        model.avatar_file(&avatar, format).map_err(PipelineError::PoseCorrection)
    }

    /// The frontal rendering of the largest face as PNG: the bytes `facegate frontalize --out X.png`
    /// writes for the same photo.
    pub fn frontal_png(&self, photo: &Photo) -> Result<Vec<u8>, PipelineError> {
        let model = self.face_model()?;
        let located = self.finder.locate(&photo.gray)?;
        let fitted = model.fit(&located.landmarks.points, photo.width(), photo.height()).map_err(PipelineError::PoseCorrection)?;
        Ok(model.frontal_png(photo, &fitted, FRONTAL_VIEW_SIZE).map_err(PipelineError::PoseCorrection)?.1)
    }

    /// The classical recognizer's template: the 3DMM frontal rendering and/or the 2D-aligned photo,
    /// normalised, projected.
    fn classical_template(
        &self,
        recognizer: &ClassicalRecognizer,
        photo: &Photo,
        landmarks: &Landmarks,
        timings: &mut StageTimings,
    ) -> Result<(Template, Option<Pose>, Quality), PipelineError> {
        let t = Instant::now();
        let input = recognition_input(self.face_model.as_ref(), photo, landmarks, recognizer.normalization())?;
        timings.morph_ms = elapsed_ms(t);

        let t = Instant::now();
        let crop = |input: &RecognitionInput| recognizer.normalized_crop(&input.gray, &input.keypoints);
        let template = match recognizer.paths().get(1) {
            // A fused model also sees the face on its second path (2D: the photo itself, no fit).
            Some(&second) => {
                let other =
                    recognition_input(self.face_model.as_ref().filter(|_| second == Normalization::Morph), photo, landmarks, second)?;
                recognizer.template(Views::Fused { primary: &crop(&input), secondary: &crop(&other) })?
            }
            None => recognizer.template(Views::Single(&crop(&input)))?,
        };
        timings.template_ms = elapsed_ms(t);
        // Quality is measured on the deep recognizer's chip here too (one scale for both paths).
        let t = Instant::now();
        let quality = self.quality.assess(quality_components(photo, landmarks, input.pose, input.fit_residual_px).1);
        timings.quality_ms = elapsed_ms(t);
        Ok((template, input.pose, quality))
    }
}

/// `dlda.bin`, or `dlda-2d.bin` when the former needs the 3DMM and it is not loaded.
fn load_classical(config: &PipelineConfig, have_face_model: bool) -> Result<ClassicalRecognizer, PipelineError> {
    let mut recognizer = ClassicalRecognizer::load(&config.models_dir)?;
    if recognizer.normalization() == Normalization::Morph && !have_face_model {
        let fallback = config.models_dir.join(TWO_D_MODEL_FILE);
        recognizer = ClassicalRecognizer::load_file(&fallback)?;
        if recognizer.normalization() != Normalization::TwoD {
            return Err(PipelineError::NoTwoDModel(fallback.display().to_string()));
        }
        tracing::warn!(
            "recognition uses the 2D model {} ({}): templates enrolled with the 3DMM model are not comparable",
            fallback.display(),
            recognizer.model_version()
        );
    }
    Ok(recognizer)
}

/// The avatar of the largest face of `photo`: the service's landmarks ([`FaceFinder::locate`]),
/// then [`FaceModel::avatar`]. `POST /avatar` and `facegate reconstruct` both come here.
pub fn reconstruct(
    finder: &FaceFinder,
    model: &FaceModel,
    photo: &Photo,
    options: &FitOptions,
    texture_size: usize,
) -> Result<crate::morph::Avatar, PipelineError> {
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
    let chip = crate::embed::face_chip(&photo.rgb, &landmarks.keypoints);
    let components = crate::quality::components(&chip, &landmarks.keypoints, pose, fit_residual_px);
    (chip, components)
}

/// What the recognizer normalises: a grey image, the eye and mouth centres in it, and the head pose
/// and fit residual when the 3DMM was fitted.
pub struct RecognitionInput<'a> {
    pub gray: Cow<'a, GrayF32>,
    pub keypoints: KeyPoints,
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
            Ok(RecognitionInput {
                gray: Cow::Owned(GrayF32::from_rgb(&frontal.image)),
                keypoints: frontal.keypoints,
                pose,
                fit_residual_px,
            })
        }
        _ => Ok(RecognitionInput { gray: Cow::Borrowed(&photo.gray), keypoints: landmarks.keypoints, pose, fit_residual_px }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pipeline_config() -> PipelineConfig {
        PipelineConfig {
            models_dir: facegate_paths::models_dir(),
            sfm_dir: Some(facegate_paths::sfm_dir()),
            recognizer: RecognizerKind::default(),
            detector: DetectorKind::default(),
        }
    }

    fn photo(name: &str) -> Photo {
        facegate_core::imaging::open(&facegate_paths::shared_dir().join("data/imm").join(name)).unwrap()
    }

    /// A full profile (UMIST photo 01) is found, landmarked by the profile model seeded by the
    /// detector's five points (the C-ASM's 58 points are unreliable there), posed by the 3DMM
    /// fitted to them and its far side reported hidden; a frontal face shows nearly every
    /// landmark and is not seeded by the detector.
    #[test]
    fn a_full_profile_is_found_posed_and_its_far_side_hidden() {
        let pipeline = Pipeline::load(&PipelineConfig { detector: DetectorKind::Yunet, ..pipeline_config() }).unwrap();
        let umist = facegate_paths::shared_dir().join("data/umist");
        for person in ["s01", "s05"] {
            let profile = facegate_core::imaging::open(&umist.join(person).join("01.pgm")).unwrap();
            let reading = pipeline.read_faces(&profile, FaceChoice::Largest).unwrap();
            let face = &reading.faces[0];
            // Landmarked by the profile model from YuNet's points, posed by the 3DMM fitted to them.
            assert!(pipeline.finder.profile_seeded(&face.face), "{person}");
            let casm = pipeline.finder.landmarks(&profile.gray, &seed_box(&face.face));
            assert_ne!(face.landmarks.points, casm.points, "{person}: the profile model's points");
            assert_eq!(face.landmarks.keypoints, casm.keypoints, "{person}: the chip's centres stay the C-ASM path's");
            let yaw = face.pose.expect("posed").yaw;
            assert!(yaw.abs() > 50.0, "{person}: a full profile posed at {yaw}°");
            let visible = face.visible.as_ref().expect("visibility");
            let hidden = visible.iter().filter(|v| !**v).count();
            assert!((10..48).contains(&hidden), "{person}: {hidden} of 58 landmarks hidden at {yaw}°");
            // The probe's template is made all the same.
            assert!(pipeline.analyze(&profile).is_ok_and(|a| a.pose.is_some_and(|p| p.yaw.abs() > 50.0)), "{person}");
        }
        let frontal = pipeline.read_faces(&photo("01-1m.jpg"), FaceChoice::Largest).unwrap();
        let face = &frontal.faces[0];
        assert!(!pipeline.finder.profile_seeded(&face.face));
        assert!(face.pose.expect("posed").yaw.abs() < 20.0, "{:?}", face.pose);
        let shown = face.visible.as_ref().expect("visibility").iter().filter(|v| **v).count();
        assert!(shown >= 50, "{shown} of 58 landmarks visible on a frontal face");
    }

    /// Live webcam frames and frames of printed photos (NUAA; the committed model was trained on
    /// these subjects, so this checks the wiring, crops and features end to end, not accuracy:
    /// `facegate eval liveness` measures that on subjects left out).
    #[test]
    fn liveness_tells_printed_photos_from_live_faces() {
        let pipeline = Pipeline::load(&pipeline_config()).unwrap();
        let nuaa = facegate_paths::shared_dir().join("data/nuaa");
        for (path, live) in [
            ("real/0004/0004_01_00_01_109.jpg", true),
            ("real/0007/0007_00_00_01_101.jpg", true),
            ("print/0004/0004_01_01_03_211.jpg", false),
            ("print/0007/0007_01_00_01_111.jpg", false),
        ] {
            let a = pipeline.analyze(&facegate_core::imaging::open(&nuaa.join(path)).unwrap()).unwrap();
            let liveness = a.liveness.expect("models/liveness.bin is loaded");
            assert_eq!(liveness.attack, !live, "{path}: score {}", liveness.score);
            assert!((0.0..=1.0).contains(&liveness.score));
        }
        let mut without = pipeline;
        without.liveness = None;
        assert!(without.analyze(&photo("05-1m.jpg")).unwrap().liveness.is_none());
    }

    #[test]
    fn full_pipeline_reports_every_stage() {
        let pipeline = Pipeline::load(&pipeline_config()).unwrap();
        assert!(pipeline.face_model.is_some());
        let a = pipeline.analyze(&photo("05-1m.jpg")).unwrap();
        assert_eq!(a.faces_found, 1);
        assert_eq!(a.landmarks.points.len(), 58);
        assert!(a.face.rect.contains(a.landmarks.keypoints.left_eye) && a.face.rect.contains(a.landmarks.keypoints.mouth));
        assert!(a.pose.is_some());
        assert_eq!(a.template.model_version, pipeline.recognizer.model_version());
        let norm: f32 = a.template.vector.iter().map(|v| v * v).sum::<f32>().sqrt();
        assert!((norm - 1.0).abs() < 1e-3, "templates are unit vectors, got norm {norm}");
        assert!(a.timings.detect_ms > 0.0 && a.timings.landmarks_ms > 0.0);
    }

    #[test]
    fn deep_and_classical_templates_carry_their_own_versions() {
        let deep = Pipeline::load(&PipelineConfig { recognizer: RecognizerKind::Deep, ..pipeline_config() }).unwrap();
        let classical = Pipeline::load(&PipelineConfig { recognizer: RecognizerKind::Classical, ..pipeline_config() }).unwrap();
        let p = photo("05-1m.jpg");
        let (a, b) = (deep.analyze(&p).unwrap(), classical.analyze(&p).unwrap());
        assert!(a.template.model_version.starts_with("deep-") && b.template.model_version.starts_with("dlda-"));
        assert_eq!(a.template.vector.len(), crate::embed::EMBEDDING_DIMS);
        assert_eq!((a.face, &a.landmarks), (b.face, &b.landmarks), "one front end for both");
        // The mirror agreement exists where the chip is embedded (deep), not on the classical path,
        // whose other components are the same (one chip for both).
        let (qa, qb) = (a.quality.components, b.quality.components);
        assert!(qa.mirror_agreement.is_some_and(|m| m > 0.5 && m <= 1.0) && qa.embedding_norm.is_some_and(|n| n > 0.0), "{qa:?}");
        assert_eq!((qb.mirror_agreement, qb.embedding_norm), (None, None));
        assert_eq!((qa.sharpness, qa.fit_residual), (qb.sharpness, qb.fit_residual));
        // Without the 3DMM the deep recognizer is unchanged (it never needed the rendering); the
        // pose is then unknown.
        let flat = Pipeline::load(&PipelineConfig { sfm_dir: None, recognizer: RecognizerKind::Deep, ..pipeline_config() }).unwrap();
        let c = flat.analyze(&p).unwrap();
        assert_eq!((c.template.clone(), c.pose), (a.template, None));
    }

    #[test]
    fn the_default_fusion_joins_both_networks_and_keeps_the_mirror_agreement() {
        let fusion = Pipeline::load(&pipeline_config()).unwrap();
        assert_eq!(fusion.recognizer.kind(), RecognizerKind::Fusion);
        let a = fusion.analyze(&photo("05-1m.jpg")).unwrap();
        assert!(a.template.model_version.starts_with("emb-"), "{}", a.template.model_version);
        assert_eq!(a.template.vector.len(), 2 * crate::embed::EMBEDDING_DIMS, "dlib's 128 values and SFace's 128");
        // dlib's half carries √0.8 of the unit vector, SFace's √0.2.
        let (dlib, sface) = a.template.vector.split_at(crate::embed::EMBEDDING_DIMS);
        let norm = |v: &[f32]| v.iter().map(|x| x * x).sum::<f32>();
        assert!((norm(dlib) - 0.8).abs() < 1e-3 && (norm(sface) - 0.2).abs() < 1e-3, "{} {}", norm(dlib), norm(sface));
        assert!(a.quality.components.mirror_agreement.is_some_and(|m| m > 0.5), "dlib's mirror pair feeds the quality score");
    }

    #[test]
    fn without_the_3dmm_the_classical_pipeline_uses_a_2d_model() {
        let config = PipelineConfig { sfm_dir: None, recognizer: RecognizerKind::Classical, ..pipeline_config() };
        let pipeline = Pipeline::load(&config).unwrap();
        assert!(pipeline.face_model.is_none());
        assert_eq!(pipeline.recognizer.classical().map(|r| r.normalization()), Some(Normalization::TwoD));
        let a = pipeline.analyze(&photo("05-1m.jpg")).unwrap();
        assert!(a.pose.is_none());
        assert_eq!(a.template.model_version, pipeline.recognizer.model_version());
    }

    #[test]
    fn turned_faces_take_the_3d_asm_points_frontal_ones_the_c_asm() {
        let pipeline = Pipeline::load(&pipeline_config()).unwrap();
        let asm3d = pipeline.finder.asm3d.as_ref().expect("models/asm3d.bin");
        for (name, turned) in [("01-1m.jpg", false), ("02-3m.jpg", true)] {
            let p = photo(name);
            let a = pipeline.analyze(&p).unwrap();
            let casm = pipeline.finder.landmarker.fit(&p.gray, &seed_box(&a.face), Variant::Casm);
            let yaw = asm3d.yaw_of(&casm.points).unwrap();
            assert_eq!(yaw.abs() >= SERVICE_MIN_YAW, turned, "{name}: C-ASM yaw {yaw}");
            if turned {
                let three = asm3d.fit_seeded(&p.gray, &seed_box(&a.face), &casm.points, &pipeline.finder.landmarker.model);
                assert_eq!(a.landmarks.points, three.points, "{name}");
                assert_ne!(a.landmarks.points, casm.points, "{name}: the 3D-ASM's points, not the C-ASM's");
            } else {
                assert_eq!(a.landmarks, casm, "{name}");
            }
        }
    }

    #[test]
    fn a_photo_without_a_face_is_no_face() {
        let pipeline = Pipeline::load(&pipeline_config()).unwrap();
        let blank = Photo::from_dynamic(image::DynamicImage::ImageLuma8(image::GrayImage::from_pixel(320, 240, image::Luma([128]))));
        assert!(matches!(pipeline.analyze(&blank), Err(PipelineError::NoFace)));
    }
}
