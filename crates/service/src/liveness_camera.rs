//! The liveness threshold of a deployment's own camera (`facegate calibrate-liveness`).
//!
//! The passive model's operating point was chosen on NUAA's webcam. On another camera its live
//! faces can score lower (a model that never saw IMM's, ORL's or LFW's photos refused up to 31% of
//! them at that point) or higher, so a threshold that suits one camera refuses live people or
//! passes prints on the next (docs/liveness.md). What an operator can collect is live captures of
//! their own camera: staff, volunteers, consenting users. From those alone a
//! [`LivenessCalibration`] sets the threshold that refuses at most a stated share of them
//! ([`live_threshold`]), and the service applies it at start-up in place of the model's own
//! ([`LivenessCalibration::point`]). It says nothing of the prints that camera will see: the share
//! of prints it passes was measured on people and cameras apart from the ones calibrated
//! (docs/liveness.md, "A threshold per camera").

use serde::{Deserialize, Serialize};

use facegate_store::{Store, StoreError};
use facegate_vision::liveness::LivenessModel;

use crate::liveness::{LivenessPoint, ThresholdSource};

/// The share of the camera's live captures a calibration refuses at most, unless told otherwise:
/// the most a deployment can bear to turn away (the passive check's target).
pub const DEFAULT_BPCER: f64 = 0.02;

/// Why live captures make no threshold.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibrationError {
    #[error("the share of live faces to refuse must be strictly between 0 and 0.5, got {0}")]
    Share(f64),
    #[error(
        "{faces} live face(s) cannot show a refusal rate of {share}: at least {needed} are needed (one refused at that rate); \
         add live captures of the camera or allow a larger share"
    )]
    TooFew { faces: usize, share: f64, needed: usize },
}

/// The live faces needed to place a refusal rate of `share`: enough that one face is that share.
pub fn faces_needed(share: f64) -> usize {
    (1.0 / share).ceil() as usize
}

/// The highest threshold that refuses at most `share` of the live `scores`: the score of the
/// `⌊share · n⌋`-th lowest face (counting from 0), so the faces below it, at most that many, are
/// refused (a face is refused when its score is below the threshold). Any score scale that grows
/// with liveness will do (probabilities, logits): the research measures it on logits.
pub fn live_threshold(scores: &[f32], share: f64) -> Result<f32, CalibrationError> {
    if !(share > 0.0 && share < 0.5) {
        return Err(CalibrationError::Share(share));
    }
    let needed = faces_needed(share);
    let mut sorted: Vec<f32> = scores.iter().copied().filter(|s| s.is_finite()).collect();
    if sorted.len() < needed {
        return Err(CalibrationError::TooFew { faces: sorted.len(), share, needed });
    }
    sorted.sort_by(f32::total_cmp);
    let k = ((share * sorted.len() as f64).floor() as usize).min(sorted.len() - 1);
    Ok(sorted[k])
}

/// A camera's liveness threshold for one liveness model, with what it was measured on. Aggregates
/// only: no photo, face or person is kept, so erasing a subject leaves nothing of it here.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LivenessCalibration {
    /// The liveness model calibrated (`liveness.model` in responses).
    pub model: String,
    /// The share of the live faces the threshold may refuse.
    pub bpcer: f64,
    /// Live faces scored (photos where no face was found are not among them).
    pub live_faces: usize,
    /// Of those, how many score below the threshold.
    pub refused: usize,
    pub threshold: f32,
    /// The model's own operating point, which this one replaces.
    pub model_threshold: f32,
    /// How many of the live faces the model's own threshold refuses.
    pub refused_at_model_threshold: usize,
}

impl LivenessCalibration {
    /// The calibration of `model` on a camera's live faces' `scores` (its probabilities), refusing
    /// at most `bpcer`; the threshold kept strictly inside (0, 1), where a threshold means something.
    pub fn from_scores(model: &LivenessModel, scores: &[f32], bpcer: f64) -> Result<LivenessCalibration, CalibrationError> {
        let threshold = live_threshold(scores, bpcer)?.clamp(f32::EPSILON, 1.0 - f32::EPSILON);
        let below = |t: f32| scores.iter().filter(|&&s| s < t).count();
        Ok(LivenessCalibration {
            model: model.name.clone(),
            bpcer,
            live_faces: scores.len(),
            refused: below(threshold),
            threshold,
            model_threshold: model.threshold,
            refused_at_model_threshold: below(model.threshold),
        })
    }

    /// The threshold this camera's calibration sets in place of the liveness model's own point
    /// `model`, its operating point saying so (a refusal quotes it). A calibration of another
    /// model sets none.
    pub fn point(&self, model: &LivenessPoint) -> Option<LivenessPoint> {
        if model.model != self.model {
            return None;
        }
        let operating_point = format!(
            "this camera's threshold (facegate calibrate-liveness: {} of {} live faces refused, at most {}%) in place of the \
             model's {:.3}, the {}",
            self.refused,
            self.live_faces,
            self.bpcer * 100.0,
            model.threshold,
            model.operating_point
        );
        Some(LivenessPoint { threshold: self.threshold, source: ThresholdSource::Camera, model: self.model.clone(), operating_point })
    }
}

/// Store `calibration` for its model, replacing the one before.
pub async fn save(store: &Store, calibration: &LivenessCalibration) -> Result<(), StoreError> {
    let json = serde_json::to_string(calibration).map_err(|e| StoreError::Refused(e.to_string()))?;
    store.set_liveness_calibration(&calibration.model, &json).await
}

/// The stored calibration of the liveness model named `model`, if any.
pub async fn load(store: &Store, model: &str) -> Result<Option<LivenessCalibration>, StoreError> {
    let Some(json) = store.liveness_calibration(model).await? else { return Ok(None) };
    serde_json::from_str(&json)
        .map(Some)
        .map_err(|e| StoreError::Refused(format!("the liveness calibration of {model} is unreadable: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model(threshold: f32) -> LivenessModel {
        LivenessModel {
            format: 1,
            name: "lbp-test".into(),
            blocks: Vec::new(),
            mean: Vec::new(),
            scale: Vec::new(),
            weights: Vec::new(),
            bias: 0.0,
            slope: 1.0,
            offset: 0.0,
            threshold,
            operating_point: "EER on NUAA".into(),
            trained_on: String::new(),
        }
    }

    #[test]
    fn the_threshold_refuses_at_most_the_share_asked() {
        // 100 live faces scoring 0.01 … 1.00: at 2% the third lowest is the threshold and two are refused.
        let scores: Vec<f32> = (1..=100).rev().map(|i| i as f32 / 100.0).collect();
        assert_eq!(live_threshold(&scores, 0.02).unwrap(), 0.03);
        let refused = |t: f32| scores.iter().filter(|&&s| s < t).count();
        for share in [0.01, 0.02, 0.05, 0.1, 0.25] {
            let t = live_threshold(&scores, share).unwrap();
            assert!(refused(t) as f64 <= share * 100.0 + 1e-9, "{share}: {t} refuses {}", refused(t));
            // And no higher threshold among the scores would still keep to the share.
            let next = scores.iter().copied().filter(|&s| s > t).fold(f32::INFINITY, f32::min);
            assert!(refused(next) as f64 > share * 100.0, "{share}: {next} would do too");
        }
        // Faces scoring alike: ties are never split, so fewer may be refused, never more.
        let tied = [0.9f32; 60];
        assert_eq!(live_threshold(&tied, 0.02).unwrap(), 0.9);
        // Non-finite scores are no faces' (and may leave too few).
        assert_eq!(live_threshold(&[f32::NAN; 60], 0.02), Err(CalibrationError::TooFew { faces: 0, share: 0.02, needed: 50 }));
    }

    #[test]
    fn too_few_faces_or_a_senseless_share_make_no_threshold() {
        let scores = vec![0.9f32; 49];
        assert_eq!(live_threshold(&scores, 0.02), Err(CalibrationError::TooFew { faces: 49, share: 0.02, needed: 50 }));
        assert!(live_threshold(&scores, 0.05).is_ok());
        for share in [0.0, -0.1, 0.5, f64::NAN] {
            assert!(matches!(live_threshold(&scores, share), Err(CalibrationError::Share(_))), "{share}");
        }
    }

    #[test]
    fn a_calibration_replaces_its_models_threshold_and_no_other() {
        // Binary fractions, so that the thresholds compare exactly.
        let scores: Vec<f32> = (0..50).map(|i| 0.5 + i as f32 / 128.0).collect();
        let calibration = LivenessCalibration::from_scores(&model(0.64), &scores, 0.1).unwrap();
        assert_eq!((calibration.threshold, calibration.refused, calibration.live_faces), (scores[5], 5, 50));
        assert_eq!((calibration.model_threshold, calibration.refused_at_model_threshold), (0.64, 18));
        let served = calibration.point(&LivenessPoint::of_model(&model(0.64))).unwrap();
        assert_eq!((served.threshold, served.source, served.model.as_str()), (scores[5], ThresholdSource::Camera, "lbp-test"));
        assert!(served.operating_point.contains("5 of 50") && served.operating_point.contains("0.640"), "{}", served.operating_point);
        let other = LivenessModel { name: "another".into(), ..model(0.64) };
        assert_eq!(calibration.point(&LivenessPoint::of_model(&other)), None);
        // Saturated probabilities keep the threshold inside (0, 1).
        assert!(LivenessCalibration::from_scores(&model(0.64), &[1.0; 60], 0.02).unwrap().threshold < 1.0);
        assert!(LivenessCalibration::from_scores(&model(0.64), &[0.0; 60], 0.02).unwrap().threshold > 0.0);
        // What is stored reads back the same.
        let json = serde_json::to_string(&calibration).unwrap();
        assert_eq!(serde_json::from_str::<LivenessCalibration>(&json).unwrap(), calibration);
    }
}
