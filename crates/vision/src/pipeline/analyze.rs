//! The pipeline proper: the stages assembled, from a photo to a template, its quality and liveness
//! ([`Pipeline::analyze`]), or to every face's reading without a template ([`Pipeline::read_faces`]).

use std::sync::Arc;
use std::time::Instant;

use facegate_core::elapsed_ms;
use facegate_core::imaging::Photo;
use serde::Serialize;

use super::finder::FaceFinder;
use super::follow::FollowedFace;
use super::input::{RecognitionInput, load_face_model, quality_components, recognition_input, reconstruct};
use super::{PipelineConfig, PipelineError, TWO_D_MODEL_FILE};
use crate::landmarks::Landmarks;
use crate::liveness::{Liveness, LivenessModel};
use crate::quality::{Quality, QualityModel};
use crate::recognize::{ClassicalRecognizer, DlibRecognizer, EmbeddingRecognizer, Normalization, Recognizer, RecognizerKind, Views};
use facegate_core::template::Template;
use facegate_detect::Face;
use facegate_morph::key_points::HIDDEN_SIDE_YAW;
use facegate_morph::{AVATAR_TEXTURE_SIZE, AvatarFormat, FRONTAL_VIEW_SIZE, FaceModel, FitOptions, FittedFace, Pose};

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
    /// The face used: the largest one found (or the followed one, [`Pipeline::analyze_following`]).
    pub face: Face,
    /// How many faces the detector found.
    pub faces_found: usize,
    pub landmarks: Landmarks,
    /// Head pose from the 3DMM fit, when the model is loaded.
    pub pose: Option<Pose>,
    /// Head pose of the 3DMM's mean face fitted to the detector's five key points
    /// ([`Pipeline::key_point_fit`]); `None` without key points or the model.
    pub key_point_pose: Option<Pose>,
    pub template: Template,
    /// The face image quality components and unified score.
    pub quality: Quality,
    /// Live face or printed photo; `None` when no liveness model is loaded.
    pub liveness: Option<Liveness>,
    /// The passive model's features of this face, kept for the rendered-head check
    /// ([`Pipeline::render_check`]), which reads the same features where the passive model does.
    pub liveness_features: Option<Arc<[f32]>>,
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
    /// Head pose of the 3DMM's mean face fitted to the detector's five key points
    /// ([`Pipeline::key_point_fit`]).
    pub key_point_pose: Option<Pose>,
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
    /// The rendered-head detector (`render.bin`), for the head-turn challenge's frames only
    /// ([`Pipeline::render_check`]); `None` when the file is missing.
    pub render: Option<LivenessModel>,
}

impl Pipeline {
    /// Load every stage. The deep recognizer is `deep.bin` over `embedding.bin`. The classical
    /// one is `dlda.bin`; when it was trained on 3DMM frontal renderings and the Surrey Face Model
    /// is unavailable, the 2D model `dlda-2d.bin` is used instead (with a warning), so that
    /// templates are never scored against thresholds calibrated for the other normalisation. Every
    /// model's templates carry its own version, so subjects enrolled under one model are not
    /// compared with probes of another.
    pub fn load(config: &PipelineConfig) -> Result<Pipeline, PipelineError> {
        // The recognizer loads before the detector and landmark models: parsing its ONNX file is
        // the largest passing allocation of the load, and made first it does not stack on their
        // resident size (the start-up peak, docs/speed.md "Memory of one replica").
        let face_model = load_face_model(config.sfm_dir.as_deref());
        let recognizer = match config.recognizer {
            RecognizerKind::Dlib => Recognizer::Dlib(Box::new(DlibRecognizer::load(&config.models_dir)?)),
            RecognizerKind::Classical => Recognizer::Classical(load_classical(config, face_model.is_some())?),
            kind @ (RecognizerKind::Sface | RecognizerKind::Fusion | RecognizerKind::Custom) => {
                let file = kind.embedding_model_file().expect("an embedding recognizer");
                Recognizer::Embedding(Box::new(EmbeddingRecognizer::load(&config.models_dir, file)?), kind)
            }
        };
        let finder = FaceFinder::load_with(&config.models_dir, config.detector)?;
        let quality = QualityModel::load(&config.models_dir.join(crate::quality::FILE))?;
        let liveness_path = config.models_dir.join(crate::liveness::FILE);
        let liveness = if liveness_path.exists() { Some(LivenessModel::load(&liveness_path)?) } else { None };
        let render_path = config.models_dir.join(crate::liveness::RENDER_FILE);
        let render = if render_path.exists() { Some(LivenessModel::load(&render_path)?) } else { None };
        Ok(Pipeline { finder, face_model, recognizer, quality, liveness, render })
    }

    /// Detect, landmark, pose-correct and template the largest face of `photo`. Each stage runs
    /// in a span of its own name (`detect`, `landmarks`, `morph` (the 3D fit), `template`, `quality`,
    /// `liveness`; the classical recognizer's quality runs inside its `template`), which the
    /// service's traces carry.
    pub fn analyze(&self, photo: &Photo) -> Result<FaceAnalysis, PipelineError> {
        self.analyze_chosen(photo, |_| Some(0))
    }

    /// [`Pipeline::analyze`] of the face a camera has been following ([`FollowedFace::pick`]):
    /// a challenge's frames, each after the last. [`PipelineError::NoFace`] when no face found
    /// lies where the followed one was.
    pub fn analyze_following(&self, photo: &Photo, last: &FollowedFace) -> Result<FaceAnalysis, PipelineError> {
        self.analyze_chosen(photo, |faces| last.pick(faces, photo.width(), photo.height()))
    }

    /// The analysis of the face `choose` picks among those found (largest first); `NoFace` when
    /// it picks none.
    fn analyze_chosen(&self, photo: &Photo, choose: impl FnOnce(&[Face]) -> Option<usize>) -> Result<FaceAnalysis, PipelineError> {
        let mut timings = StageTimings::default();
        let t = Instant::now();
        let faces = tracing::info_span!("detect").in_scope(|| self.finder.detect(&photo.gray));
        timings.detect_ms = elapsed_ms(t);
        let face = *choose(&faces).and_then(|i| faces.get(i)).ok_or(PipelineError::NoFace)?;

        let t = Instant::now();
        let landmarks = tracing::info_span!("landmarks").in_scope(|| self.finder.landmarks_of(&photo.gray, &face));
        timings.landmarks_ms = elapsed_ms(t);

        // One fit of the mean face to the detector's points: the challenge's pose, and the pose of
        // a profile the C-ASM landmarked (`profile_fit`).
        let key_point_fit = self.key_point_fit(photo, &face);
        let key_point_pose = key_point_fit.as_ref().map(|f| f.pose);
        let (template, pose, quality) = match &self.recognizer {
            Recognizer::Classical(recognizer) => self.classical_template(recognizer, photo, &landmarks, &mut timings)?,
            _ => self.embedding_template(photo, &face, &landmarks, key_point_fit, &mut timings)?,
        };
        let t = Instant::now();
        let (liveness, features) = tracing::info_span!("liveness").in_scope(|| self.liveness_of(photo, &landmarks)).unzip();
        let liveness_features = features.map(Arc::from);
        timings.liveness_ms = elapsed_ms(t);
        Ok(FaceAnalysis {
            face,
            faces_found: faces.len(),
            landmarks,
            pose,
            key_point_pose,
            template,
            quality,
            liveness,
            liveness_features,
            timings,
        })
    }

    /// The deep recognizers' template (dlib's network, SFace, their fusion, a user's network)
    /// with the head pose and the quality.
    fn embedding_template(
        &self,
        photo: &Photo,
        face: &Face,
        landmarks: &Landmarks,
        key_point_fit: Option<FittedFace>,
        timings: &mut StageTimings,
    ) -> Result<(Template, Option<Pose>, Quality), PipelineError> {
        // The networks see the photo itself (the 3DMM frontal rendering measured worse as the
        // dlib network's input: docs/recognition.md); the fit still reports the head pose.
        let t = Instant::now();
        let fitting = tracing::info_span!("morph").entered();
        let mut input = recognition_input(self.face_model.as_ref(), photo, landmarks, Normalization::TwoD)?;
        if let Some(fit) = self.profile_fit(face, key_point_fit) {
            (input.pose, input.fit_residual_px) = (Some(fit.pose), Some(fit.residual_px));
        }
        drop(fitting);
        timings.morph_ms = elapsed_ms(t);
        let t = Instant::now();
        let templating = tracing::info_span!("template").entered();
        // The quality components are measured on dlib's chip whichever network embeds.
        let chip = crate::embed::face_chip(&photo.rgb, &landmarks.centres);
        let (template, mirror) = match &self.recognizer {
            Recognizer::Embedding(recognizer, _) => {
                let embedded = recognizer.embed(&photo.rgb, &landmarks.centres, face.points.as_ref(), Some(&chip));
                (embedded.template, embedded.dlib_pair)
            }
            Recognizer::Dlib(deep) => {
                let (template, mirror) = deep.template_and_mirror_pair(&chip);
                (template, Some(mirror))
            }
            Recognizer::Classical(recognizer) => return self.classical_template(recognizer, photo, landmarks, timings),
        };
        drop(templating);
        timings.template_ms = elapsed_ms(t);
        let t = Instant::now();
        let _assessing = tracing::info_span!("quality").entered();
        let components = crate::quality::components(&chip, &landmarks.centres, input.pose, input.fit_residual_px);
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
                let key_point_fit = self.key_point_fit(photo, &face);
                let key_point_pose = key_point_fit.as_ref().map(|f| f.pose);
                let fit = self
                    .profile_fit(&face, key_point_fit)
                    .or_else(|| self.face_model.as_ref().and_then(|m| m.fit(&landmarks.points, photo.width(), photo.height()).ok()));
                let morph_ms = elapsed_ms(t);
                let (pose, fit_residual_px) = (fit.as_ref().map(|f| f.pose), fit.as_ref().map(|f| f.residual_px));
                let visible = self.face_model.as_ref().zip(fit.as_ref()).map(|(m, f)| m.landmark_visibility(f));
                let quality = self.quality.assess(quality_components(photo, &landmarks, pose, fit_residual_px).1);
                let liveness = self.liveness_of(photo, &landmarks).map(|(l, _)| l);
                FaceReading { face, landmarks, pose, key_point_pose, fit_residual_px, visible, quality, liveness, landmarks_ms, morph_ms }
            })
            .collect();
        Ok(PhotoReading { faces_found: faces.len(), faces: readings, detect_ms })
    }

    /// On a head the detector's five points show turned past [`HIDDEN_SIDE_YAW`] whose landmarks
    /// are the C-ASM's (no profile model loaded), the mean face fitted to those points
    /// (`key_point_fit`, [`Pipeline::key_point_fit`]): there the C-ASM's 58 points, and the fit to
    /// them, are unreliable. With the profile model's landmarks the 3DMM fit to them stands: on
    /// renders of held-out faces its yaw was 7–18° off at 60–90°, the five-point fit's 18–33°
    /// (`facegate eval landmarks`, docs/pose.md).
    fn profile_fit(&self, face: &Face, key_point_fit: Option<FittedFace>) -> Option<FittedFace> {
        if self.finder.profile_seeded(face) {
            return None;
        }
        key_point_fit.filter(|fit| fit.pose.yaw.abs() >= HIDDEN_SIDE_YAW)
    }

    /// The 3DMM's mean face fitted to the detector's five key points (scaled orthographic,
    /// `FaceModel::fit_key_points`). Its pose is the yaw the head-turn challenge judges its steps
    /// by. On the IMM training persons' photos and their mirror images it kept every frontal view
    /// (1, 2, 5) within 9.3° and every turned one (3, 4) at 14.0° or more, where the 58-landmark
    /// fit read frontal views up to 12.0° and turned ones down to 10.0°: the C-ASM's points
    /// sometimes settle on a frontal shape on a head turned 20–30°, and the fit follows them
    /// (docs/liveness-challenge.md, "Which yaw"). `None` without key points (the cascade
    /// detectors) or without the model.
    pub fn key_point_fit(&self, photo: &Photo, face: &Face) -> Option<FittedFace> {
        self.face_model.as_ref()?.fit_key_points(face.points.as_ref()?, photo.width(), photo.height()).ok()
    }

    /// A face seen by a camera, or a head rendered from a photo ([`crate::liveness::RENDER_FILE`]),
    /// measured where the liveness is (the eye and mouth centres of `analysis`); `None` without
    /// the model. Not part of [`Pipeline::analyze`]: only a challenge's frames need it.
    pub fn render_check(&self, photo: &Photo, analysis: &FaceAnalysis) -> Option<Liveness> {
        let model = self.render.as_ref()?;
        // The detector is trained on the passive model's features: when the two read the same
        // blocks, the analysis's features are scored again instead of computed again (they are
        // most of either model's cost).
        let shared = self.liveness.as_ref().is_some_and(|passive| passive.blocks == model.blocks);
        Some(match analysis.liveness_features.as_deref().filter(|_| shared) {
            Some(x) => model.assess_features(x),
            None => model.assess(&photo.rgb, &analysis.landmarks.centres),
        })
    }

    /// The liveness of the face with `landmarks`, measured where the recognizer cuts its chip,
    /// and the features it was read from.
    fn liveness_of(&self, photo: &Photo, landmarks: &Landmarks) -> Option<(Liveness, Vec<f32>)> {
        self.liveness.as_ref().map(|model| {
            let x = model.features(&photo.rgb, &landmarks.centres);
            (model.assess_features(&x), x)
        })
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
        let fitting = tracing::info_span!("morph").entered();
        let input = recognition_input(self.face_model.as_ref(), photo, landmarks, recognizer.normalization())?;
        drop(fitting);
        timings.morph_ms = elapsed_ms(t);

        let t = Instant::now();
        let _templating = tracing::info_span!("template").entered();
        let crop = |input: &RecognitionInput| recognizer.normalized_crop(&input.gray, &input.centres);
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
