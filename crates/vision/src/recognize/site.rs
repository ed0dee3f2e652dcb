//! Site calibration: the thresholds raised to what a deployment's own photos need.
//!
//! A model's threshold tables are calibrated on other people's photos (LFW's news photos with IMM's
//! and ORL's lab photos). Where a deployment's photos come from one camera, one light and one
//! background, impostors look more alike than in that mix: the stated FMR 1e-3 came out 3.9e-3 on
//! lab photos of persons never used (docs/recognition.md). Yet impostor scores between a
//! deployment's own enrolled subjects predict its new persons' well: thresholds from the IMM and
//! ORL training persons' pairs held the stated rate on their held-out persons (0.6–1.1×).
//!
//! So a [`SiteCalibration`] is the threshold at each calibrated FMR on the impostor pairs of the
//! enrolled subjects (every pair of templates of two different subjects), kept where the pairs
//! are enough to show the rate ([`MIN_FALSE_MATCHES`]). It only ever *raises* a decision's
//! threshold ([`SiteCalibration::raise`]): by how far the site's threshold lies above the model's
//! one-template threshold at that FMR, for any enrolment size. A deployment whose impostors are
//! no more alike than the model's keeps the model's thresholds, and a gallery (or an attacker
//! enrolling subjects) can make a decision stricter, never looser. Subjects enrolled twice under
//! two ids count as impostors and raise it too (towards fewer false matches).

use serde::{Deserialize, Serialize};

use super::OperatingPoint;
use super::calibration::{CALIBRATED_FMRS, threshold_at};

/// A site threshold is kept only where its impostor pairs allow at least this many false matches
/// at its FMR: fewer cannot place the rate (with 10 the threshold's FMR is within about ±30 %).
pub const MIN_FALSE_MATCHES: f64 = 10.0;

/// Templates a calibration pairs at most (all pairs of up to this many, about 18 M); a larger
/// gallery is sampled evenly ([`impostor_scores`]).
pub const MAX_TEMPLATES: usize = 6_000;

/// One stated FMR's threshold on the site's impostor pairs.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SitePoint {
    pub fmr: f64,
    pub threshold: f32,
}

/// A deployment's own impostor thresholds for one model version (module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SiteCalibration {
    pub model_version: String,
    /// Subjects and templates whose pairs were scored.
    pub subjects: usize,
    pub templates: usize,
    /// Impostor pairs scored (pairs of templates of two different subjects).
    pub impostor_pairs: usize,
    /// The calibrated FMRs the pairs allow, lowest threshold first.
    pub points: Vec<SitePoint>,
}

impl SiteCalibration {
    /// The thresholds of `impostor` scores at the calibrated FMRs the count allows.
    pub fn from_impostor_scores(model_version: &str, subjects: usize, templates: usize, impostor: &[f32]) -> SiteCalibration {
        let points = CALIBRATED_FMRS
            .iter()
            .filter(|&&fmr| impostor.len() as f64 * fmr >= MIN_FALSE_MATCHES)
            .map(|&fmr| SitePoint { fmr, threshold: threshold_at(impostor, fmr) })
            .collect();
        SiteCalibration { model_version: model_version.to_string(), subjects, templates, impostor_pairs: impostor.len(), points }
    }

    /// `point` (the model's, for some enrolment size) raised by how far the site's threshold at
    /// its FMR lies above `one_template` (the model's one-template threshold at that FMR); unchanged
    /// where the site has no threshold there or its threshold is not above.
    pub fn raise(&self, point: OperatingPoint, one_template: f32) -> OperatingPoint {
        let site = self.points.iter().find(|p| p.fmr == point.fmr);
        match site {
            Some(site) if site.threshold > one_template => {
                OperatingPoint { threshold: point.threshold + (site.threshold - one_template), ..point }
            }
            _ => point,
        }
    }
}

/// Cosines of every pair of rows of different subjects: `rows` are unit vectors (`dimension` each)
/// with `owners` their subject slots. With more than [`MAX_TEMPLATES`] rows, every n-th row is
/// taken (rows in subject order spread the sample over the subjects) and those are paired.
pub fn impostor_scores(rows: &[f32], dimension: usize, owners: &[u32]) -> Vec<f32> {
    let count = owners.len();
    let step = count.div_ceil(MAX_TEMPLATES).max(1);
    let taken: Vec<usize> = (0..count).step_by(step).collect();
    let row = |i: usize| &rows[i * dimension..(i + 1) * dimension];
    let mut scores = Vec::new();
    for (a, &i) in taken.iter().enumerate() {
        for &j in &taken[a + 1..] {
            if owners[i] != owners[j] {
                scores.push(facegate_core::vector::dot(row(i), row(j)));
            }
        }
    }
    scores
}

#[cfg(test)]
mod tests {
    use super::*;

    fn site(points: &[(f64, f32)]) -> SiteCalibration {
        SiteCalibration {
            model_version: "m".into(),
            subjects: 0,
            templates: 0,
            impostor_pairs: 0,
            points: points.iter().map(|&(fmr, threshold)| SitePoint { fmr, threshold }).collect(),
        }
    }

    #[test]
    fn a_site_raises_thresholds_by_its_margin_and_never_lowers_them() {
        let s = site(&[(1e-2, 0.80), (1e-3, 0.70)]);
        // 1e-2: the site's 0.80 is 0.05 above the model's one-template 0.75; a five-template
        // threshold of 0.78 moves by the same.
        let raised = s.raise(OperatingPoint { fmr: 1e-2, threshold: 0.78 }, 0.75);
        assert!((raised.threshold - 0.83).abs() < 1e-6 && raised.fmr == 1e-2);
        // 1e-3: the site's threshold is below the model's: unchanged.
        assert_eq!(s.raise(OperatingPoint { fmr: 1e-3, threshold: 0.8 }, 0.8).threshold, 0.8);
        // 1e-4: the site's pairs did not allow it: unchanged.
        assert_eq!(s.raise(OperatingPoint { fmr: 1e-4, threshold: 0.9 }, 0.9).threshold, 0.9);
    }

    #[test]
    fn only_the_rates_the_pairs_can_show_are_kept() {
        let scores: Vec<f32> = (0..2_000).map(|i| i as f32 / 2_000.0).collect();
        let s = SiteCalibration::from_impostor_scores("m", 50, 100, &scores);
        // 2,000 pairs: 20 false matches at 1e-2, 2 at 1e-3.
        assert_eq!(s.points.len(), 1);
        assert_eq!(s.points[0].fmr, 1e-2);
        let above = scores.iter().filter(|&&v| v >= s.points[0].threshold).count();
        assert_eq!(above, 20, "the lowest threshold with 1 % of the pairs at or above");
    }

    #[test]
    fn impostor_pairs_are_the_pairs_of_different_subjects() {
        // Three rows: two of subject 0 (identical), one of subject 1.
        let rows = [1.0, 0.0, 1.0, 0.0, 0.6, 0.8];
        let mut scores = impostor_scores(&rows, 2, &[0, 0, 1]);
        scores.sort_by(f32::total_cmp);
        assert_eq!(scores, [0.6, 0.6]);
    }

    #[test]
    fn a_large_gallery_is_sampled_evenly() {
        let count = 2 * MAX_TEMPLATES + 1;
        let rows: Vec<f32> = (0..count).flat_map(|i| [(i as f32).cos(), (i as f32).sin()]).collect();
        let owners: Vec<u32> = (0..count as u32).collect();
        let taken = count.div_ceil(3);
        assert_eq!(impostor_scores(&rows, 2, &owners).len(), taken * (taken - 1) / 2);
    }
}
