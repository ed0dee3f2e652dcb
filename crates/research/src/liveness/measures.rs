//! The liveness measures (ISO/IEC 30107-3) every liveness evaluation reads, over the score
//! measures of [`crate::measures`] (live scores as the genuine ones, attacks as the impostors):
//! the error rates at a threshold, where thresholds are put (equal rates, an APCER), and the share
//! of a camera's live photos its own calibration refuses.

use serde::Serialize;

use crate::measures::{error_curve, fnmr_at_fmr};

/// The ISO/IEC 30107-3 error rates at one threshold.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Rates {
    pub apcer: f64,
    pub bpcer: f64,
    pub acer: f64,
}

impl Rates {
    /// The rates at one `threshold` for every score (a score at the threshold is taken for live).
    pub fn at(live: &[f32], attacks: &[f32], threshold: f32) -> Rates {
        let apcer = attacks.iter().filter(|&&s| s >= threshold).count() as f64 / attacks.len().max(1) as f64;
        let bpcer = live.iter().filter(|&&s| s < threshold).count() as f64 / live.len().max(1) as f64;
        Rates { apcer, bpcer, acer: 0.5 * (apcer + bpcer) }
    }
}

/// The threshold where APCER and BPCER are closest.
pub fn eer_threshold(live: &[f32], attacks: &[f32]) -> f32 {
    error_curve(live, attacks).iter().min_by(|a, b| (a.fmr - a.fnmr).abs().total_cmp(&(b.fmr - b.fnmr).abs())).map_or(0.0, |p| p.threshold)
}

/// Where a model's threshold is put, on out-of-fold scores.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub enum OperatingPoint {
    /// APCER = BPCER.
    Eer,
    /// The lowest threshold with APCER at most this.
    Apcer(f64),
}

impl OperatingPoint {
    pub fn threshold(self, live: &[f32], attacks: &[f32]) -> f32 {
        match self {
            OperatingPoint::Eer => eer_threshold(live, attacks),
            OperatingPoint::Apcer(a) => fnmr_at_fmr(live, attacks, a).1,
        }
    }

    pub fn name(self) -> String {
        match self {
            OperatingPoint::Eer => "EER".to_string(),
            OperatingPoint::Apcer(a) => format!("APCER {}%", a * 100.0),
        }
    }
}

/// The operating points reported.
pub const OPERATING_POINTS: [OperatingPoint; 3] = [OperatingPoint::Eer, OperatingPoint::Apcer(0.05), OperatingPoint::Apcer(0.01)];

/// The share of the camera's live photos `facegate calibrate-liveness` refuses at most.
pub const CAMERA_BPCER: f64 = facegate_service::liveness_camera::DEFAULT_BPCER;
