//! Verification and identification measures: ROC and DET curves, the summary of a verification
//! run, rank-1 identification rate, over the error curve of [`crate::measures`]. A comparison
//! matches when `score >= threshold`.

use std::path::Path;

use crate::eval::plot::{Chart, Scale, Series, line_chart};
use crate::measures::{ErrorPoint, eer, error_curve, fnmr_at_fmr};

/// Rank-1 identification rate: the fraction of probes whose best-scoring gallery identity is their own.
/// `scores[p][g]` is the score of probe `p` against gallery identity `g`.
pub fn rank1(scores: &[Vec<f32>], probe_identity: &[usize]) -> f64 {
    if scores.is_empty() {
        return 0.0;
    }
    let hits = scores
        .iter()
        .zip(probe_identity)
        .filter(|(row, truth)| row.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).map(|(g, _)| g) == Some(**truth))
        .count();
    hits as f64 / scores.len() as f64
}

/// Summary of one verification run.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct VerificationSummary {
    pub genuine: usize,
    pub impostor: usize,
    pub eer: f64,
    pub fnmr_at_fmr_1e2: f64,
    pub fnmr_at_fmr_1e3: f64,
}

pub fn summarize(genuine: &[f32], impostor: &[f32]) -> VerificationSummary {
    VerificationSummary {
        genuine: genuine.len(),
        impostor: impostor.len(),
        eer: eer(genuine, impostor),
        fnmr_at_fmr_1e2: fnmr_at_fmr(genuine, impostor, 1e-2).0,
        fnmr_at_fmr_1e3: fnmr_at_fmr(genuine, impostor, 1e-3).0,
    }
}

/// Write a ROC (FMR against true match rate, log FMR axis) and a DET (FMR against FNMR, both log)
/// plot of named score sets.
pub fn write_roc_det(roc_path: &Path, det_path: &Path, sets: &[(&str, &[f32], &[f32])]) -> anyhow::Result<()> {
    let curves: Vec<(&str, Vec<ErrorPoint>, usize)> = sets.iter().map(|(n, g, i)| (*n, error_curve(g, i), i.len())).collect();
    // The smallest FMR a set can show is one impostor in all of them.
    let min_fmr = curves.iter().map(|(_, _, ni)| 1.0 / (*ni).max(1) as f64).fold(1e-2, f64::min).max(1e-6);
    let roc: Vec<Series> = curves
        .iter()
        .map(|(name, c, _)| Series { name, points: c.iter().filter(|p| p.fmr > 0.0).map(|p| (p.fmr, 1.0 - p.fnmr)).collect() })
        .collect();
    line_chart(
        roc_path,
        &Chart {
            title: "ROC (held-out persons)",
            x_label: "false match rate",
            y_label: "true match rate",
            x_range: (min_fmr, 1.0),
            y_range: (0.0, 1.0),
            x_scale: Scale::Log,
            y_scale: Scale::Linear,
        },
        &roc,
    )?;
    let min_fnmr = curves.iter().flat_map(|(_, c, _)| c.iter().map(|p| p.fnmr)).filter(|&v| v > 0.0).fold(1e-2, f64::min).max(1e-5);
    let det: Vec<Series> = curves
        .iter()
        .map(|(name, c, _)| Series { name, points: c.iter().filter(|p| p.fmr > 0.0 && p.fnmr > 0.0).map(|p| (p.fmr, p.fnmr)).collect() })
        .collect();
    line_chart(
        det_path,
        &Chart {
            title: "DET (held-out persons)",
            x_label: "false match rate",
            y_label: "false non-match rate",
            x_range: (min_fmr, 1.0),
            y_range: (min_fnmr, 1.0),
            x_scale: Scale::Log,
            y_scale: Scale::Log,
        },
        &det,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rank1_counts_best_gallery_hits() {
        let scores = vec![vec![0.9, 0.1], vec![0.2, 0.3], vec![0.5, 0.4]];
        assert!((rank1(&scores, &[0, 1, 1]) - 2.0 / 3.0).abs() < 1e-12);
    }
}
