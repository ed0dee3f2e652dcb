//! The face finder: the detector and the landmark searches, from a grey photo to faces and their
//! 58 landmarks. The service and the training and evaluation tools share it.

use std::path::Path;

use facegate_core::face::EyeMouthCentres;
use facegate_core::geometry::{Point, Rect};
use facegate_core::imaging::GrayF32;

use super::PipelineError;
use crate::landmarks::asm3d::{Asm3dLandmarker, DETECTOR_SEED_MIN_YAW, SERVICE_MIN_YAW};
use crate::landmarks::{Landmarker, Landmarks, Variant};
use facegate_detect::{Detector, DetectorKind, Face};

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
    pub centre_source: CentreSource,
    /// |yaw| (degrees) of the detector's five points from which the 3D-ASM is seeded by them
    /// ([`Asm3dLandmarker::fit_from_detector`]) instead of by the C-ASM; `None`: never.
    pub detector_seed_min_yaw: Option<f32>,
}

/// Where the recognizer's eye and mouth centres come from, for a face whose detector gave its own
/// five points (YuNet); faces without them always take the landmarks'.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CentreSource {
    /// The 58 landmarks' eye and mouth centres.
    Landmarks,
    /// The detector's eyes and the middle of its mouth corners.
    Detector,
    /// The detector's when its points show the head turned by at least this much (the nose tip's
    /// offset from the eyes' midpoint over the eye distance), the landmarks' otherwise.
    DetectorWhenTurned(f32),
}

impl Default for CentreSource {
    fn default() -> Self {
        CentreSource::Landmarks
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
    let k = centres_from_detector(points);
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
pub fn centres_from_detector(points: &[Point; 5]) -> EyeMouthCentres {
    let [left_eye, right_eye, _, mouth_left, mouth_right] = *points;
    EyeMouthCentres { left_eye, right_eye, mouth: [0.5 * (mouth_left[0] + mouth_right[0]), 0.5 * (mouth_left[1] + mouth_right[1])] }
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
            centre_source: CentreSource::default(),
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
    /// the centres kept. The centres are taken from the detector's own points where
    /// [`FaceFinder::centre_source`] says so.
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
            let use_detector = match self.centre_source {
                CentreSource::Landmarks => false,
                CentreSource::Detector => true,
                CentreSource::DetectorWhenTurned(turn) => detector_turn(points).abs() >= turn,
            };
            if use_detector {
                landmarks.centres = centres_from_detector(points);
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
        Some(Landmarks { points: found.points, centres: found.centres })
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
