//! Face image quality: how likely a photo is to make a template that matches. Plain data in (the
//! recognizer's 150×150 chip, the eye centres, the 3DMM pose and fit residual), plain data out: a
//! few measured [`Components`] (on the deep path also how well the chip's and its mirror image's
//! embeddings agree) and a unified score in 0–100 from a small logistic model
//! ([`QualityModel`], `models/quality.bin`, trained by `facegate train quality`).
//!
//! Every image component is measured on the chip the deep recognizer sees (cut at the eye and
//! mouth centres, so the face's axis is the chip's centre column), on both recognizers' paths: the
//! frontal rendering of the issue exists only on the classical path, and one place of measurement
//! keeps the scales and the unified model the same whichever recognizer runs. Illumination
//! uniformity compares the chip's left and right halves about that axis.

use std::path::Path;

use serde::{Deserialize, Serialize};

use facegate_core::face::EyeMouthCentres;
use facegate_morph::Pose;
use facegate_nn::{FaceChip, MirrorPair};

/// The inner face of the 150-pixel chip (eyebrows to chin, cheek to cheek), where the image
/// components are measured: the chip's corners are background or black padding.
const INNER_X: (usize, usize) = (30, 120);
const INNER_Y: (usize, usize) = (25, 135);

/// The measured quality components of one face. Each has a fixed scale:
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Components {
    /// Distance between the eye centres in the photo, pixels (ISO/IEC 29794-5's inter-eye distance).
    pub inter_eye_px: f32,
    /// RMS of the 4-neighbour Laplacian of the grey chip over the inner face, grey levels:
    /// near 1–2 for a heavily blurred face, 5–15 for a sharp one.
    pub sharpness: f32,
    /// Mean grey level (0–255) of the inner face: exposure.
    pub brightness: f32,
    /// Standard deviation of the inner face's grey levels (0–127.5).
    pub contrast: f32,
    /// The darker half's mean grey over the brighter half's, left and right of the face's axis:
    /// 1 for even lighting, towards 0 for light from one side.
    pub illumination_uniformity: f32,
    /// |yaw| of the 3DMM fit, degrees; `None` without the 3DMM or when its fit failed.
    pub yaw_abs_deg: Option<f32>,
    /// |pitch| of the 3DMM fit, degrees; `None` as for yaw.
    pub pitch_abs_deg: Option<f32>,
    /// RMS distance between the 58 landmarks and the fitted 3DMM's points over the inter-eye
    /// distance (a landmark-fit confidence: small when the points form a plausible face); `None`
    /// as for yaw.
    pub fit_residual: Option<f32>,
    /// Cosine between the network's embeddings of the chip and of its mirror image (−1 to 1; in
    /// practice 0.8–1): a face and its mirror are the same person, so a well-aligned, sharp,
    /// frontal, unoccluded face embeds nearly alike both ways. `None` where no embedding is made
    /// (the classical recognizer, `/analyze`).
    pub mirror_agreement: Option<f32>,
    /// Euclidean norm of the mean of those two embeddings (the recognizer's embedding before its
    /// model normalises it): two embeddings that disagree average to a shorter one. `None` as for
    /// the mirror agreement.
    pub embedding_norm: Option<f32>,
}

impl Components {
    /// These components with the agreement of the chip's and its mirror image's embeddings.
    pub fn with_mirror(self, pair: &MirrorPair) -> Components {
        let mean = pair.mean();
        let norm = mean.0.iter().map(|v| v * v).sum::<f32>().sqrt();
        Components { mirror_agreement: Some(pair.agreement()), embedding_norm: Some(norm), ..self }
    }
}

/// A face's quality: the components and the unified score.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Quality {
    /// 0–100: the model's probability (in percent) that a genuine comparison with this photo
    /// clears the recognizer's threshold at FMR 1e-3.
    pub score: f32,
    #[serde(flatten)]
    pub components: Components,
}

/// The components of the face whose chip is `chip`, eye centres `centres` (photo pixels), 3DMM
/// pose and fit residual (pixels) as given.
pub fn components(chip: &FaceChip, centres: &EyeMouthCentres, pose: Option<Pose>, fit_residual_px: Option<f32>) -> Components {
    let [lx, ly] = centres.left_eye;
    let [rx, ry] = centres.right_eye;
    let inter_eye_px = ((lx - rx).powi(2) + (ly - ry).powi(2)).sqrt();
    let size = chip.size;
    // Grey as ITU-R BT.601 luma; chips smaller than the layout's 150 scale the inner face box.
    let grey: Vec<f32> = chip.rgb.chunks_exact(3).map(|p| 0.299 * p[0] as f32 + 0.587 * p[1] as f32 + 0.114 * p[2] as f32).collect();
    let scale = |v: usize| (v * size / crate::embed::CHIP_SIZE).clamp(1, size.saturating_sub(1).max(1));
    let (x0, x1, y0, y1) = (scale(INNER_X.0), scale(INNER_X.1), scale(INNER_Y.0), scale(INNER_Y.1));
    let axis = size / 2;
    let (mut sum, mut sum_sq, mut lap_sq, mut n) = (0.0f64, 0.0f64, 0.0f64, 0usize);
    let (mut left, mut right, mut n_left, mut n_right) = (0.0f64, 0.0f64, 0usize, 0usize);
    for y in y0..y1 {
        for x in x0..x1 {
            let at = y * size + x;
            let v = grey[at] as f64;
            sum += v;
            sum_sq += v * v;
            n += 1;
            let lap = 4.0 * grey[at] - grey[at - 1] - grey[at + 1] - grey[at - size] - grey[at + size];
            lap_sq += (lap as f64).powi(2);
            if x < axis {
                left += v;
                n_left += 1;
            } else {
                right += v;
                n_right += 1;
            }
        }
    }
    let n = n.max(1) as f64;
    let mean = sum / n;
    let (left, right) = (left / n_left.max(1) as f64, right / n_right.max(1) as f64);
    let brighter = left.max(right);
    Components {
        inter_eye_px,
        sharpness: (lap_sq / n).sqrt() as f32,
        brightness: mean as f32,
        contrast: (sum_sq / n - mean * mean).max(0.0).sqrt() as f32,
        illumination_uniformity: if brighter > 0.0 { (left.min(right) / brighter) as f32 } else { 1.0 },
        yaw_abs_deg: pose.map(|p| p.yaw.abs()),
        pitch_abs_deg: pose.map(|p| p.pitch.abs()),
        fit_residual: fit_residual_px.map(|r| r / inter_eye_px.max(1.0)),
        mirror_agreement: None,
        embedding_norm: None,
    }
}

/// How many features [`features`] makes of the components.
pub const FEATURES: usize = 13;

/// The features that exist only where the chip was embedded (mirror agreement, embedding norm):
/// without an embedding they count at the model's training mean (they add nothing to the score),
/// and the indicator after them says so.
pub const MIRROR_FEATURES: std::ops::Range<usize> = 10..12;

/// The names of [`features`], in order (for the model note and the evaluation).
pub const FEATURE_NAMES: [&str; FEATURES] = [
    "ln inter-eye px",
    "ln sharpness",
    "brightness",
    "(brightness − 128)²",
    "contrast",
    "illumination uniformity",
    "|yaw|",
    "|pitch|",
    "fit residual",
    "pose unknown",
    "mirror agreement",
    "ln embedding norm",
    "embedding unknown",
];

/// The logistic model's inputs: the components on roughly unit scales, the two-sided exposure as a
/// squared distance from mid-grey, a missing pose as zero angles plus an indicator, a missing
/// embedding as zero mirror agreement and norm plus an indicator ([`QualityModel::score`] leaves
/// those zeros out).
pub fn features(c: &Components) -> [f64; FEATURES] {
    let b = c.brightness as f64 / 255.0;
    [
        (c.inter_eye_px.max(1.0) as f64).ln(),
        (c.sharpness.max(0.1) as f64).ln(),
        b,
        (b - 0.5).powi(2),
        c.contrast as f64 / 64.0,
        c.illumination_uniformity as f64,
        c.yaw_abs_deg.unwrap_or(0.0) as f64 / 30.0,
        c.pitch_abs_deg.unwrap_or(0.0) as f64 / 30.0,
        c.fit_residual.unwrap_or(0.0) as f64,
        if c.yaw_abs_deg.is_none() { 1.0 } else { 0.0 },
        c.mirror_agreement.unwrap_or(0.0) as f64,
        c.embedding_norm.map_or(0.0, |n| (n.max(1e-3) as f64).ln()),
        if c.mirror_agreement.is_none() { 1.0 } else { 0.0 },
    ]
}

/// The unified score's model file.
pub const FILE: &str = "quality.bin";
/// The layout of [`QualityModel`].
pub const FORMAT: u32 = 2;

/// Logistic regression of "a genuine comparison clears the threshold" on the standardised
/// [`features`]: `score = 100 · σ(bias + Σ weight · (feature − mean) / scale)`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct QualityModel {
    pub format: u32,
    pub mean: Vec<f64>,
    pub scale: Vec<f64>,
    pub weights: Vec<f64>,
    pub bias: f64,
    /// What it was trained on and the command that rebuilds it.
    pub trained_on: String,
}

#[derive(Debug, thiserror::Error)]
#[error("quality model {path}: {message}")]
pub struct QualityModelError {
    pub path: String,
    pub message: String,
}

impl QualityModel {
    pub fn load(path: &Path) -> Result<QualityModel, QualityModelError> {
        let fail = |message: String| QualityModelError { path: path.display().to_string(), message };
        let model: QualityModel =
            facegate_core::model_file::read_model(path, "quality model", FORMAT, "facegate train quality").map_err(fail)?;
        let n = FEATURES;
        if model.mean.len() != n || model.scale.len() != n || model.weights.len() != n {
            return Err(fail(format!("expected {n} features")));
        }
        Ok(model)
    }

    /// The unified score (0–100) of `components`. Without an embedding the mirror features count
    /// at the training photos' mean (every training photo has one): the score of a photo whose
    /// mirror agreement is typical.
    pub fn score(&self, components: &Components) -> f32 {
        let x = features(components);
        let unknown = components.mirror_agreement.is_none();
        let z = self.bias
            + (0..FEATURES)
                .filter(|k| !(unknown && MIRROR_FEATURES.contains(k)))
                .map(|k| self.weights[k] * (x[k] - self.mean[k]) / self.scale[k])
                .sum::<f64>();
        (100.0 / (1.0 + (-z).exp())) as f32
    }

    /// Components and unified score.
    pub fn assess(&self, components: Components) -> Quality {
        Quality { score: self.score(&components), components }
    }
}

/// The enrolment policy: the least unified score and per-component limits a photo must meet to be
/// enrolled. A limit of `None` is not checked.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct QualityPolicy {
    pub min_score: Option<f32>,
    pub min_inter_eye_px: Option<f32>,
    pub min_sharpness: Option<f32>,
    pub min_brightness: Option<f32>,
    pub max_brightness: Option<f32>,
    pub max_yaw_deg: Option<f32>,
    pub max_pitch_deg: Option<f32>,
}

impl QualityPolicy {
    /// No limit at all: every photo passes.
    pub const NONE: QualityPolicy = QualityPolicy {
        min_score: None,
        min_inter_eye_px: None,
        min_sharpness: None,
        min_brightness: None,
        max_brightness: None,
        max_yaw_deg: None,
        max_pitch_deg: None,
    };

    /// The limits `quality` breaks; empty: it passes. An unknown pose breaks no pose limit.
    pub fn failures(&self, quality: &Quality) -> Vec<Failure> {
        let c = &quality.components;
        let checks: [(&'static str, Option<f32>, Option<f32>, Bound); 7] = [
            ("score", Some(quality.score), self.min_score, Bound::Min),
            ("inter_eye_px", Some(c.inter_eye_px), self.min_inter_eye_px, Bound::Min),
            ("sharpness", Some(c.sharpness), self.min_sharpness, Bound::Min),
            ("brightness", Some(c.brightness), self.min_brightness, Bound::Min),
            ("brightness", Some(c.brightness), self.max_brightness, Bound::Max),
            ("yaw_abs_deg", c.yaw_abs_deg, self.max_yaw_deg, Bound::Max),
            ("pitch_abs_deg", c.pitch_abs_deg, self.max_pitch_deg, Bound::Max),
        ];
        checks
            .into_iter()
            .filter_map(|(component, value, limit, bound)| {
                let (value, limit) = (value?, limit?);
                let fails = match bound {
                    Bound::Min => value < limit,
                    Bound::Max => value > limit,
                };
                fails.then_some(Failure { component, value, limit, bound })
            })
            .collect()
    }
}

/// Which side of a limit a value must stay on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Bound {
    Min,
    Max,
}

/// One broken limit: the component (as named in the `quality` object), its value, the limit and
/// whether the limit is a minimum or a maximum.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Failure {
    pub component: &'static str,
    pub value: f32,
    pub limit: f32,
    pub bound: Bound,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chip_of(f: impl Fn(usize, usize) -> u8) -> FaceChip {
        let size = crate::embed::CHIP_SIZE;
        let mut rgb = Vec::with_capacity(size * size * 3);
        for y in 0..size {
            for x in 0..size {
                let v = f(x, y);
                rgb.extend([v, v, v]);
            }
        }
        FaceChip { size, rgb }
    }

    fn centres(inter_eye: f32) -> EyeMouthCentres {
        EyeMouthCentres { left_eye: [100.0, 100.0], right_eye: [100.0 + inter_eye, 100.0], mouth: [100.0 + inter_eye / 2.0, 160.0] }
    }

    #[test]
    fn flat_grey_is_unsharp_uniform_and_without_contrast() {
        let c = components(&chip_of(|_, _| 100), &centres(60.0), None, None);
        assert_eq!(c.inter_eye_px, 60.0);
        assert!(c.sharpness < 1e-3 && c.contrast < 1e-3);
        assert!((c.brightness - 100.0).abs() < 0.5);
        assert!((c.illumination_uniformity - 1.0).abs() < 1e-4);
        assert_eq!((c.yaw_abs_deg, c.fit_residual), (None, None));
    }

    #[test]
    fn texture_is_sharp_and_one_sided_light_is_not_uniform() {
        let checker = components(&chip_of(|x, y| if (x + y) % 2 == 0 { 60 } else { 180 }), &centres(60.0), None, None);
        assert!(checker.sharpness > 100.0 && checker.contrast > 50.0, "{checker:?}");
        let lit_left = components(&chip_of(|x, _| if x < 75 { 200 } else { 50 }), &centres(60.0), None, None);
        assert!((lit_left.illumination_uniformity - 0.25).abs() < 0.01, "{lit_left:?}");
        let pose = Pose { yaw: -20.0, pitch: 5.0, roll: 1.0 };
        let posed = components(&chip_of(|_, _| 90), &centres(50.0), Some(pose), Some(2.5));
        assert_eq!((posed.yaw_abs_deg, posed.pitch_abs_deg, posed.fit_residual), (Some(20.0), Some(5.0), Some(0.05)));
    }

    #[test]
    fn the_policy_lists_each_broken_limit_with_value_and_limit() {
        let model = QualityModel {
            format: FORMAT,
            mean: vec![0.0; FEATURES],
            scale: vec![1.0; FEATURES],
            weights: vec![0.0; FEATURES],
            bias: 0.0,
            trained_on: String::new(),
        };
        let dark = model.assess(components(&chip_of(|_, _| 20), &centres(30.0), Some(Pose { yaw: 50.0, pitch: 0.0, roll: 0.0 }), None));
        assert_eq!(dark.score, 50.0);
        let policy = QualityPolicy {
            min_score: Some(40.0),
            min_inter_eye_px: Some(25.0),
            min_brightness: Some(40.0),
            max_yaw_deg: Some(45.0),
            ..QualityPolicy::NONE
        };
        let failures = policy.failures(&dark);
        assert_eq!(failures.len(), 2, "{failures:?}");
        assert_eq!((failures[0].component, failures[0].limit, failures[0].bound), ("brightness", 40.0, Bound::Min));
        assert_eq!((failures[1].component, failures[1].value, failures[1].bound), ("yaw_abs_deg", 50.0, Bound::Max));
        assert!(QualityPolicy::NONE.failures(&dark).is_empty());
    }

    fn mirror_pair(direct: [f32; 2], mirrored: [f32; 2]) -> MirrorPair {
        let embed = |v: [f32; 2]| {
            let mut e = [0.0; facegate_nn::EMBEDDING_DIMS];
            e[..2].copy_from_slice(&v);
            facegate_nn::Embedding(e)
        };
        MirrorPair { direct: embed(direct), mirrored: embed(mirrored) }
    }

    #[test]
    fn the_mirror_components_are_the_agreement_and_the_mean_norm_and_null_without_an_embedding() {
        let plain = components(&chip_of(|_, _| 100), &centres(60.0), None, None);
        assert_eq!((plain.mirror_agreement, plain.embedding_norm), (None, None), "the classical path embeds nothing");
        let same = plain.with_mirror(&mirror_pair([0.6, 0.8], [0.6, 0.8]));
        assert_eq!(same.mirror_agreement, Some(1.0));
        assert!((same.embedding_norm.unwrap() - 1.0).abs() < 1e-6);
        // Orthogonal unit embeddings: cosine 0, their mean has norm √½.
        let apart = plain.with_mirror(&mirror_pair([1.0, 0.0], [0.0, 1.0]));
        assert!(apart.mirror_agreement.unwrap().abs() < 1e-6);
        assert!((apart.embedding_norm.unwrap() - 0.5f32.sqrt()).abs() < 1e-6);
        assert_eq!((apart.sharpness, apart.inter_eye_px), (plain.sharpness, plain.inter_eye_px));
        let x = features(&apart);
        assert_eq!((x[10], x[12]), (0.0, 0.0), "the cosine and the indicator");
        assert_eq!(features(&plain)[12], 1.0);
    }

    #[test]
    fn without_an_embedding_the_mirror_features_count_at_the_training_mean() {
        let mut weights = vec![0.0; FEATURES];
        weights[10] = 5.0; // mirror agreement
        weights[11] = 1.0; // ln embedding norm
        let mut mean = vec![0.0; FEATURES];
        mean[10] = 0.9;
        mean[11] = 0.5f64.ln();
        let model = QualityModel { format: FORMAT, mean, scale: vec![1.0; FEATURES], weights, bias: 0.0, trained_on: String::new() };
        let plain = components(&chip_of(|_, _| 100), &centres(60.0), None, None);
        assert_eq!(model.score(&plain), 50.0, "unknown: the mean's score");
        let typical = plain.with_mirror(&mirror_pair([1.0, 0.0], [0.9, 0.19f32.sqrt()]));
        assert!((typical.mirror_agreement.unwrap() - 0.9).abs() < 1e-5);
        let agreeing = plain.with_mirror(&mirror_pair([0.6, 0.8], [0.6, 0.8]));
        let disagreeing = plain.with_mirror(&mirror_pair([1.0, 0.0], [0.0, 1.0]));
        assert!(model.score(&agreeing) > model.score(&typical) && model.score(&typical) > model.score(&disagreeing));
    }

    #[test]
    fn the_model_file_round_trips_and_a_wrong_feature_count_is_refused() {
        let dir = std::env::temp_dir().join(format!("facegate-quality-model-{}", std::process::id()));
        let model = QualityModel {
            format: FORMAT,
            mean: (0..FEATURES).map(|k| k as f64).collect(),
            scale: vec![2.0; FEATURES],
            weights: (0..FEATURES).map(|k| 0.1 * k as f64 - 0.5).collect(),
            bias: 1.5,
            trained_on: "test".into(),
        };
        let path = dir.join(FILE);
        facegate_core::model_file::write_model(&path, &model).unwrap();
        assert_eq!(QualityModel::load(&path).unwrap(), model);
        let short = QualityModel { weights: vec![0.0; FEATURES - 3], ..model.clone() };
        facegate_core::model_file::write_model(&path, &short).unwrap();
        assert!(QualityModel::load(&path).unwrap_err().message.contains("features"));
        let old = QualityModel { format: FORMAT - 1, ..model };
        facegate_core::model_file::write_model(&path, &old).unwrap();
        assert!(QualityModel::load(&path).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_higher_weighted_feature_raises_the_score() {
        let mut weights = vec![0.0; FEATURES];
        weights[1] = 3.0; // ln sharpness
        let model = QualityModel {
            format: FORMAT,
            mean: vec![0.0; FEATURES],
            scale: vec![1.0; FEATURES],
            weights,
            bias: 0.0,
            trained_on: String::new(),
        };
        let blurred = components(&chip_of(|_, _| 100), &centres(60.0), None, None);
        let sharp = components(&chip_of(|x, y| if (x + y) % 2 == 0 { 60 } else { 180 }), &centres(60.0), None, None);
        assert!(model.score(&sharp) > 99.0 && model.score(&blurred) < 1.0);
    }
}
