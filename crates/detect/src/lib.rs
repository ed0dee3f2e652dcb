//! Face detection: the YuNet CNN (through `tract`), which finds faces from frontal to full
//! profile and is the default, the thesis's OpenCV Viola–Jones cascades (2.5.1), and SeetaFace
//! (`rustface`) as a measured alternative.
//!
//! The Haar detector runs `haarcascade_frontalface_alt2.xml`; when it finds nothing (the default
//! [`ProfileMode::Fallback`]) it also runs `haarcascade_profileface.xml` on the image and on its
//! mirror, for heads turned either way. Boxes come back largest first, in pixels of the input
//! image. See `docs/detection.md` for the measured detection rates and times.

pub mod cascade;
pub mod seeta;
pub mod yunet;

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use facegate_core::geometry::{Point, Rect};
use facegate_core::imaging::GrayF32;

pub use cascade::{Cascade, ScanOptions};

/// A detected face: its box in pixels of the input image and a confidence (higher is surer).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Face {
    #[serde(rename = "box")]
    pub rect: Rect,
    pub score: f32,
    /// Five key points in pixels of the input image, from detectors that locate them (YuNet):
    /// the image-left eye, the image-right eye, the nose tip, the image-left and the image-right
    /// mouth corner. For an upright, unmirrored face the image-left eye is the subject's right.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub points: Option<[Point; 5]>,
}

#[derive(Debug, thiserror::Error)]
pub enum DetectError {
    #[error("cannot load the detector model {path}: {message}")]
    Model { path: String, message: String },
}

/// File names of the shipped models, under `<models_dir>/cascades/`.
pub const FRONTAL_CASCADE: &str = "haarcascade_frontalface_alt2.xml";
pub const PROFILE_CASCADE: &str = "haarcascade_profileface.xml";
pub const SEETA_MODEL: &str = "seeta_fd_frontal_v1.0.bin";
/// YuNet's ONNX file, directly under `<models_dir>/` (see `models/yunet.md`).
pub const YUNET_MODEL: &str = "yunet.onnx";

/// Copies compiled into the binary, used when the models folder does not hold the files (so the
/// service and the CLI work from any directory).
pub const EMBEDDED_FRONTAL: &str = include_str!("../../../models/cascades/haarcascade_frontalface_alt2.xml");
pub const EMBEDDED_PROFILE: &str = include_str!("../../../models/cascades/haarcascade_profileface.xml");
pub const EMBEDDED_SEETA: &[u8] = include_bytes!("../../../models/cascades/seeta_fd_frontal_v1.0.bin");
pub const EMBEDDED_YUNET: &[u8] = include_bytes!("../../../models/yunet.onnx");

/// Which detector to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DetectorKind {
    /// OpenCV Viola–Jones Haar cascades (frontal, then profile and mirrored profile): the
    /// thesis's detector.
    Haar,
    /// SeetaFace funnel-structured cascade through the `rustface` crate.
    Seeta,
    /// YuNet, a multi-view CNN with five key points (OpenCV Zoo, run through `tract`): finds
    /// faces from frontal to full profile (docs/pose.md), so it is the default.
    #[default]
    Yunet,
}

/// When the Haar detector also runs the profile cascade.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ProfileMode {
    /// Frontal cascade only.
    Off,
    /// Profile cascades only when the frontal one finds nothing (cheap on frontal photos).
    #[default]
    Fallback,
    /// Always run the profile cascades too and merge.
    Always,
}

/// Tunable detection options; the defaults are the measured operating point of `docs/detection.md`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DetectOptions {
    /// Smallest face searched, in pixels.
    pub min_face: u32,
    /// Smallest face as a fraction of the image's shorter side (the larger of the two limits
    /// applies): a portrait photo does not hold thumbnail-sized faces, and skipping them is what
    /// keeps a 640×480 scan within a few milliseconds.
    pub min_face_fraction: f32,
    pub profile: ProfileMode,
    /// Raw windows needed for a detection (OpenCV's `minNeighbors`).
    pub min_neighbours: usize,
    /// Ratio between pyramid scales.
    pub scale_step: f32,
    /// Window step in pixels of each pyramid level.
    pub step: usize,
    /// When the scan at `step` finds nothing, scan again with step 1 before trying the profile
    /// cascades: a large face can fall between coarse window positions, and the finer scan costs
    /// time only on images without a face found.
    pub fine_rescan: bool,
    /// Images whose shorter side is below this (e.g. ORL's 92×112 crops, where the face fills the
    /// frame) are scanned with step 1 and a replicated border, so a face as large as the frame
    /// still gets enough overlapping windows; YuNet gives them a zero border, room around the head.
    pub small_image_side: u32,
    /// Border added on each side of a small image, as a fraction of its size (Haar and YuNet).
    pub small_image_pad: f32,
    /// On small images, pyramid levels at a scale above this are scanned at every pixel and the
    /// others with step 2 (OpenCV's own rule). Faces filling a small frame are found on the fine
    /// levels; the coarse ones only hold windows far smaller than the frame. 0 scans every level
    /// at step 1.
    pub small_image_fine_above_scale: f32,
    /// YuNet's largest input side in pixels (a multiple of 32; read when the detector is loaded).
    pub yunet_input_size: u32,
    /// YuNet's input is no larger than makes the smallest face searched ([`Self::min_size_for`])
    /// this many input pixels tall (a smaller input, less work); 0 always fills the
    /// `yunet_input_size` square, as small images (below `small_image_side`) always do.
    pub yunet_min_face_px: f32,
    /// YuNet's score threshold (√(class · objectness), 0–1).
    pub yunet_score: f32,
}

impl Default for DetectOptions {
    fn default() -> Self {
        Self {
            min_face: 24,
            min_face_fraction: 0.2,
            profile: ProfileMode::Fallback,
            min_neighbours: 3,
            scale_step: 1.1,
            step: 2,
            fine_rescan: true,
            small_image_side: 200,
            small_image_pad: 0.1,
            small_image_fine_above_scale: 1.75,
            yunet_input_size: 320,
            yunet_min_face_px: 36.0,
            yunet_score: 0.6,
        }
    }
}

impl DetectOptions {
    /// The smallest face side searched in an image of this size.
    pub fn min_size_for(&self, width: usize, height: usize) -> f32 {
        (self.min_face.max(1) as f32).max(self.min_face_fraction * width.min(height) as f32)
    }
}

enum Engine {
    Haar { frontal: Cascade, profile: Cascade, profile_mirrored: Cascade },
    Seeta(seeta::SeetaDetector),
    Yunet(yunet::YunetDetector),
}

/// A face detector, shareable across threads (`Send + Sync`; `detect` takes `&self`).
pub struct Detector {
    engine: Engine,
    pub options: DetectOptions,
}

fn read_or_embedded(path: &Path, embedded: &'static [u8]) -> Result<std::borrow::Cow<'static, [u8]>, DetectError> {
    match std::fs::read(path) {
        Ok(bytes) => Ok(bytes.into()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(embedded.into()),
        Err(e) => Err(DetectError::Model { path: path.display().to_string(), message: e.to_string() }),
    }
}

fn cascade_from(path: PathBuf, embedded: &'static str) -> Result<Cascade, DetectError> {
    let bytes = read_or_embedded(&path, embedded.as_bytes())?;
    let text = std::str::from_utf8(&bytes).map_err(|e| DetectError::Model { path: path.display().to_string(), message: e.to_string() })?;
    Cascade::parse(text, &path.display().to_string())
}

impl Detector {
    /// Load the default detector from the models folder (`<models_dir>/cascades/`), falling back
    /// to the copies compiled into the binary when the files are absent.
    pub fn load(models_dir: &Path) -> Result<Detector, DetectError> {
        Detector::load_kind(models_dir, DetectorKind::default())
    }

    pub fn load_kind(models_dir: &Path, kind: DetectorKind) -> Result<Detector, DetectError> {
        Detector::load_with(models_dir, kind, DetectOptions::default())
    }

    pub fn load_with(models_dir: &Path, kind: DetectorKind, options: DetectOptions) -> Result<Detector, DetectError> {
        let dir = models_dir.join("cascades");
        let engine = match kind {
            DetectorKind::Haar => {
                let frontal = cascade_from(dir.join(FRONTAL_CASCADE), EMBEDDED_FRONTAL)?;
                let profile = cascade_from(dir.join(PROFILE_CASCADE), EMBEDDED_PROFILE)?;
                let profile_mirrored = profile.mirrored();
                Engine::Haar { frontal, profile, profile_mirrored }
            }
            DetectorKind::Seeta => {
                let path = dir.join(SEETA_MODEL);
                let bytes = read_or_embedded(&path, EMBEDDED_SEETA)?;
                Engine::Seeta(seeta::SeetaDetector::from_bytes(&bytes, &path.display().to_string())?)
            }
            DetectorKind::Yunet => {
                let path = models_dir.join(YUNET_MODEL);
                let bytes = read_or_embedded(&path, EMBEDDED_YUNET)?;
                let side = options.yunet_input_size as usize;
                Engine::Yunet(yunet::YunetDetector::from_bytes(&bytes, &path.display().to_string(), side)?)
            }
        };
        Ok(Detector { engine, options })
    }

    pub fn kind(&self) -> DetectorKind {
        match self.engine {
            Engine::Haar { .. } => DetectorKind::Haar,
            Engine::Seeta(_) => DetectorKind::Seeta,
            Engine::Yunet(_) => DetectorKind::Yunet,
        }
    }

    /// Faces in the image, largest first.
    pub fn detect(&self, gray: &GrayF32) -> Vec<Face> {
        if gray.width == 0 || gray.height == 0 {
            return Vec::new();
        }
        let opts = &self.options;
        let min_size = opts.min_size_for(gray.width, gray.height);
        let mut faces = match &self.engine {
            Engine::Haar { frontal, profile, profile_mirrored } => {
                let small = gray.width.min(gray.height) < opts.small_image_side as usize;
                let padded;
                let (gray, offset) = if small && opts.small_image_pad > 0.0 {
                    let (px, py) = (
                        (gray.width as f32 * opts.small_image_pad).round() as usize,
                        (gray.height as f32 * opts.small_image_pad).round() as usize,
                    );
                    padded = GrayF32::from_fn(gray.width + 2 * px, gray.height + 2 * py, |x, y| {
                        gray.get_clamped(x as isize - px as isize, y as isize - py as isize)
                    });
                    (&padded, [px as f32, py as f32])
                } else {
                    (gray, [0.0, 0.0])
                };
                let scan = ScanOptions {
                    min_size,
                    max_size: f32::INFINITY,
                    scale_step: opts.scale_step,
                    // Small photos are scanned at every pixel on the levels where a face fills
                    // the frame: a stride of 2 there moves ORL's boxes enough that the classical
                    // recognizer, retrained on them, lost 2 points of held-out EER (5.74 → 7.83 %;
                    // docs/recognition.md). The levels of small windows keep step 2, which leaves
                    // the largest box unchanged (docs/detection.md).
                    step: if small { 2 } else { opts.step },
                    fine_above_scale: if small { opts.small_image_fine_above_scale } else { f32::INFINITY },
                    min_neighbours: opts.min_neighbours,
                    group_eps: 0.2,
                };
                let to_faces = |hits: Vec<cascade::Hit>| {
                    hits.into_iter().map(|h| Face { rect: h.rect, score: h.neighbours as f32, points: None }).collect::<Vec<_>>()
                };
                let mut faces = to_faces(frontal.detect(gray, &scan));
                if faces.is_empty() && opts.fine_rescan && scan.step > 1 {
                    faces = to_faces(frontal.detect(gray, &ScanOptions { step: 1, ..scan }));
                }
                let run_profile = match opts.profile {
                    ProfileMode::Off => false,
                    ProfileMode::Fallback => faces.is_empty(),
                    ProfileMode::Always => true,
                };
                if run_profile {
                    let mut turned: Vec<Face> = profile
                        .detect(gray, &scan)
                        .into_iter()
                        .chain(profile_mirrored.detect(gray, &scan))
                        .map(|h| Face { rect: h.rect, score: h.neighbours as f32, points: None })
                        .collect();
                    // The strongest profile box of a head wins over its mirror-image twin.
                    turned.sort_by(|a, b| b.score.total_cmp(&a.score));
                    for t in turned {
                        if !faces.iter().any(|f| same_face(&f.rect, &t.rect)) {
                            faces.push(t);
                        }
                    }
                }
                for f in &mut faces {
                    f.rect.x -= offset[0];
                    f.rect.y -= offset[1];
                }
                faces
            }
            Engine::Seeta(seeta) => seeta.detect(gray, min_size),
            Engine::Yunet(yunet) => yunet.detect(gray, opts, min_size),
        };
        faces.sort_by(|a, b| b.rect.area().total_cmp(&a.rect.area()).then(b.score.total_cmp(&a.score)));
        faces
    }
}

/// Two boxes of one head: they overlap well, or one's centre lies inside the other.
fn same_face(a: &Rect, b: &Rect) -> bool {
    a.iou(b) > 0.3 || a.contains(b.center()) || b.contains(a.center())
}
