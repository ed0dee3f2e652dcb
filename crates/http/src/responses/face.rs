//! What the API says about one face: its box, landmarks, pose, quality and liveness, and the time
//! each stage took. Each type is mapped field by field from the stage's own result, so a field a
//! stage gains stays inside the stage until it is added here (and to `openapi.yaml`).

use serde::Serialize;

use facegate_service::{AnalyzedPhoto, ChallengeOutcome, LivenessVerdict};
use facegate_vision::{landmarks, pipeline, quality};

/// A point in image pixels, `[x, y]`.
type Point = [f32; 2];

/// An axis-aligned box in image pixels, origin top left.
#[derive(Debug, Clone, Copy, Serialize)]
pub(crate) struct Rect {
    x: f32,
    y: f32,
    width: f32,
    height: f32,
}

impl From<facegate_core::geometry::Rect> for Rect {
    fn from(r: facegate_core::geometry::Rect) -> Rect {
        Rect { x: r.x, y: r.y, width: r.width, height: r.height }
    }
}

/// A detected face: its box, the detector's confidence and, from detectors that locate them, its
/// five key points.
#[derive(Debug, Clone, Copy, Serialize)]
pub(crate) struct Face {
    #[serde(rename = "box")]
    rect: Rect,
    score: f32,
    #[serde(skip_serializing_if = "Option::is_none")]
    points: Option<[Point; 5]>,
}

impl From<facegate_detect::Face> for Face {
    fn from(f: facegate_detect::Face) -> Face {
        Face { rect: f.rect.into(), score: f.score, points: f.points }
    }
}

/// The eye and mouth centres.
#[derive(Debug, Clone, Copy, Serialize)]
pub(crate) struct EyeMouthCentres {
    left_eye: Point,
    right_eye: Point,
    mouth: Point,
}

impl From<facegate_core::face::EyeMouthCentres> for EyeMouthCentres {
    fn from(k: facegate_core::face::EyeMouthCentres) -> EyeMouthCentres {
        EyeMouthCentres { left_eye: k.left_eye, right_eye: k.right_eye, mouth: k.mouth }
    }
}

/// The 58 IMM points with the eye and mouth centres.
#[derive(Debug, Clone, Serialize)]
pub(crate) struct Landmarks {
    points: Vec<Point>,
    #[serde(rename = "keypoints")]
    centres: EyeMouthCentres,
}

impl From<landmarks::Landmarks> for Landmarks {
    fn from(l: landmarks::Landmarks) -> Landmarks {
        Landmarks { points: l.points, centres: l.centres.into() }
    }
}

/// Head pose in degrees.
#[derive(Debug, Clone, Copy, Serialize)]
pub(crate) struct Pose {
    yaw: f32,
    pitch: f32,
    roll: f32,
}

impl From<facegate_morph::Pose> for Pose {
    fn from(p: facegate_morph::Pose) -> Pose {
        Pose { yaw: p.yaw, pitch: p.pitch, roll: p.roll }
    }
}

/// Face image quality: the unified score (0–100) and the components it was made from (null where
/// a component was not measured).
#[derive(Debug, Clone, Copy, Serialize)]
pub(crate) struct Quality {
    score: f32,
    inter_eye_px: f32,
    sharpness: f32,
    brightness: f32,
    contrast: f32,
    illumination_uniformity: f32,
    yaw_abs_deg: Option<f32>,
    pitch_abs_deg: Option<f32>,
    fit_residual: Option<f32>,
    mirror_agreement: Option<f32>,
    embedding_norm: Option<f32>,
}

impl From<quality::Quality> for Quality {
    fn from(q: quality::Quality) -> Quality {
        let c = q.components;
        Quality {
            score: q.score,
            inter_eye_px: c.inter_eye_px,
            sharpness: c.sharpness,
            brightness: c.brightness,
            contrast: c.contrast,
            illumination_uniformity: c.illumination_uniformity,
            yaw_abs_deg: c.yaw_abs_deg,
            pitch_abs_deg: c.pitch_abs_deg,
            fit_residual: c.fit_residual,
            mirror_agreement: c.mirror_agreement,
            embedding_norm: c.embedding_norm,
        }
    }
}

/// One limit of the enrolment quality policy a photo breaks (a `low-quality` problem's
/// `failures`): the component as named in the `quality` object, its value, the limit, and whether
/// the limit is a minimum or a maximum.
#[derive(Debug, Clone, Copy, Serialize)]
pub(crate) struct QualityFailure {
    component: &'static str,
    value: f32,
    limit: f32,
    bound: Bound,
}

/// Which side of a limit a value must stay on.
#[derive(Debug, Clone, Copy, Serialize)]
#[serde(rename_all = "lowercase")]
enum Bound {
    Min,
    Max,
}

impl From<&quality::Failure> for QualityFailure {
    fn from(f: &quality::Failure) -> QualityFailure {
        let bound = match f.bound {
            quality::Bound::Min => Bound::Min,
            quality::Bound::Max => Bound::Max,
        };
        QualityFailure { component: f.component, value: f.value, limit: f.limit, bound }
    }
}

/// A face's liveness; for a `/verify` capture with further frames, the capture's, fused over
/// them, with how many were fused and each one's own score (the probe's first).
#[derive(Debug, Clone, Serialize)]
pub(crate) struct Liveness {
    score: f32,
    attack: bool,
    model: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    frames: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    frame_scores: Option<Vec<f32>>,
    /// The verdict on a capture answering a liveness challenge.
    #[serde(skip_serializing_if = "Option::is_none")]
    challenge: Option<Challenge>,
}

/// A liveness challenge's verdict: passed, why not, and each step as read.
#[derive(Debug, Clone, Serialize)]
pub(crate) struct Challenge {
    passed: bool,
    reason: Option<String>,
    steps: Vec<ChallengeStep>,
}

#[derive(Debug, Clone, Serialize)]
pub(crate) struct ChallengeStep {
    turn: &'static str,
    yaw: Option<f32>,
    ok: bool,
    /// How many frames answered the step.
    frames: usize,
}

impl From<&ChallengeOutcome> for Challenge {
    fn from(o: &ChallengeOutcome) -> Challenge {
        let steps = o.steps.iter().map(|s| ChallengeStep { turn: s.turn.name(), yaw: s.yaw, ok: s.ok, frames: s.frames }).collect();
        Challenge { passed: o.passed, reason: o.reason.clone(), steps }
    }
}

impl From<LivenessVerdict> for Liveness {
    /// A single photo's liveness verdict (no frames).
    fn from(l: LivenessVerdict) -> Liveness {
        Liveness { score: l.score, attack: l.attack, model: l.model, frames: None, frame_scores: None, challenge: None }
    }
}

/// Milliseconds spent on one photo, stage by stage: decoding, then the pipeline's stages.
#[derive(Debug, Clone, Copy, Serialize)]
pub(crate) struct PhotoTimings {
    decode_ms: f64,
    detect_ms: f64,
    landmarks_ms: f64,
    morph_ms: f64,
    template_ms: f64,
    quality_ms: f64,
    liveness_ms: f64,
}

impl PhotoTimings {
    pub(crate) fn of(photo: &AnalyzedPhoto) -> PhotoTimings {
        let t: &pipeline::StageTimings = &photo.analysis.timings;
        PhotoTimings {
            decode_ms: photo.decode_ms,
            detect_ms: t.detect_ms,
            landmarks_ms: t.landmarks_ms,
            morph_ms: t.morph_ms,
            template_ms: t.template_ms,
            quality_ms: t.quality_ms,
            liveness_ms: t.liveness_ms,
        }
    }
}

/// What the pipeline found in one photo.
#[derive(Debug, Serialize)]
pub(crate) struct FaceReport {
    /// Faces the detector found; the largest is the one used.
    faces_found: usize,
    face: Face,
    landmarks: Landmarks,
    /// Head pose in degrees from the 3DMM fit; null when the 3DMM is not loaded.
    pose: Option<Pose>,
    quality: Quality,
    /// Absent when liveness is off (or no model is loaded).
    #[serde(skip_serializing_if = "Option::is_none")]
    liveness: Option<Liveness>,
}

impl FaceReport {
    pub(crate) fn of(photo: &AnalyzedPhoto) -> FaceReport {
        let a = &photo.analysis;
        FaceReport {
            faces_found: a.faces_found,
            face: a.face.into(),
            landmarks: a.landmarks.clone().into(),
            pose: a.pose.map(Pose::from),
            quality: a.quality.into(),
            liveness: photo.liveness.clone().map(Liveness::from),
        }
    }

    /// The report of a `/verify` probe whose liveness was fused over the capture's `frame_scores`
    /// (the probe's first), with the verdict on the `challenge` it answered, if any; a single
    /// photo's (no scores) is [`FaceReport::of`].
    pub(crate) fn of_capture(photo: &AnalyzedPhoto, frame_scores: &[f32], challenge: Option<&ChallengeOutcome>) -> FaceReport {
        let mut report = FaceReport::of(photo);
        if let Some(live) = report.liveness.as_mut().filter(|_| !frame_scores.is_empty()) {
            live.frames = Some(frame_scores.len());
            live.frame_scores = Some(frame_scores.to_vec());
        }
        if let Some(live) = report.liveness.as_mut() {
            live.challenge = challenge.map(Challenge::from);
        }
        report
    }
}

/// The landmarks with, per point, whether the fitted head shows it to the camera.
#[derive(Debug, Serialize)]
pub(crate) struct SeenLandmarks {
    points: Vec<Point>,
    #[serde(rename = "keypoints")]
    centres: EyeMouthCentres,
    /// Null when the 3DMM is not loaded or could not be fitted.
    visible: Option<Vec<bool>>,
}

#[derive(Debug, Serialize)]
struct FaceTimings {
    landmarks_ms: f64,
    morph_ms: f64,
}

/// One face of an `/analyze`.
#[derive(Debug, Serialize)]
pub(crate) struct AnalyzedFace {
    face: Face,
    landmarks: SeenLandmarks,
    /// Null when the 3DMM is not loaded or could not be fitted.
    pose: Option<Pose>,
    /// The pose of the 3DMM's mean face fitted to the detector's five key points: what the
    /// head-turn challenge judges. Null without key points or the 3DMM.
    key_point_pose: Option<Pose>,
    fit_residual_px: Option<f32>,
    quality: Quality,
    /// Reported, never refused here; absent when liveness is off.
    #[serde(skip_serializing_if = "Option::is_none")]
    liveness: Option<Liveness>,
    timings: FaceTimings,
}

impl AnalyzedFace {
    /// The face `f` as read, with the service's verdict on its liveness.
    pub(crate) fn of((f, liveness): (pipeline::FaceReading, Option<LivenessVerdict>)) -> AnalyzedFace {
        let landmarks = Landmarks::from(f.landmarks);
        AnalyzedFace {
            face: f.face.into(),
            landmarks: SeenLandmarks { points: landmarks.points, centres: landmarks.centres, visible: f.visible },
            pose: f.pose.map(Pose::from),
            key_point_pose: f.key_point_pose.map(Pose::from),
            fit_residual_px: f.fit_residual_px,
            quality: f.quality.into(),
            liveness: liveness.map(Liveness::from),
            timings: FaceTimings { landmarks_ms: f.landmarks_ms, morph_ms: f.morph_ms },
        }
    }
}
