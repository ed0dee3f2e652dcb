//! Decision thresholds at fixed false match rates, from genuine and impostor scores of people not
//! used to train the projection. A comparison matches when `score >= threshold`.

use serde::{Deserialize, Serialize};

use super::OperatingPoint;

/// The false match rates every model is calibrated at. Models written before 1e-5 was added have
/// the first three only; asked for 1e-5, they answer at their 1e-4 point and say so.
pub const CALIBRATED_FMRS: [f64; 4] = [1e-2, 1e-3, 1e-4, 1e-5];
/// The points of a threshold table (`point`: its operating point closest to an FMR) at the
/// calibrated FMRs it has. A rate it lacks is answered by its closest point, which is left out
/// rather than repeated under the rate it does not hold (1e-5 of a model calibrated to 1e-4).
pub fn calibrated_points(point: impl Fn(f64) -> OperatingPoint) -> Vec<OperatingPoint> {
    CALIBRATED_FMRS.iter().filter_map(|&fmr| Some(point(fmr)).filter(|p| p.fmr == fmr)).collect()
}

/// The operating point used when none is asked for.
pub const DEFAULT_FMR: f64 = 1e-3;

/// One calibrated operating point with what was observed at it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CalibratedPoint {
    pub fmr: f64,
    pub threshold: f32,
    /// Impostor scores at or above the threshold, as a fraction (≤ `fmr`).
    pub observed_fmr: f64,
    /// Genuine scores below the threshold, as a fraction.
    pub observed_fnmr: f64,
    /// True when there were fewer than 1/`fmr` distinct impostor scores: the threshold is then
    /// (nearly) just above the highest impostor score seen, and the FMR it achieves is only
    /// bounded by 1/impostors. Distinct, because against enrolment sets one high impostor pair
    /// is the best of several sets and repeats.
    pub under_sampled: bool,
}

/// The threshold table shipped with a model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    pub points: Vec<CalibratedPoint>,
    pub genuine_count: usize,
    pub impostor_count: usize,
    /// Where the scores came from (persons, images, centre source).
    pub source: String,
}

/// Largest enrolment set with a threshold table of its own: IMM's six photos per person leave one
/// probe beside five enrolled ones.
pub const MAX_CALIBRATED_ENROLLMENT: usize = 5;

/// The thresholds for a subject enrolled with `enrolled` photos. Its score is the best of that many
/// comparisons, so an impostor clears the one-photo threshold about `enrolled` times as often: the
/// table is calibrated on scores against enrolment sets of that size instead.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EnrolledCalibration {
    pub enrolled: usize,
    pub calibration: Calibration,
}

/// The table for a subject with `enrolled` templates: the largest enrolment-size table not beyond
/// it, or the one-photo table.
pub fn table_for<'a>(one: &'a Calibration, tables: &'a [EnrolledCalibration], enrolled: usize) -> &'a Calibration {
    tables.iter().filter(|t| t.enrolled <= enrolled.max(1)).max_by_key(|t| t.enrolled).map_or(one, |t| &t.calibration)
}

/// The smallest f32 strictly greater than `v` (finite `v`).
fn next_up(v: f32) -> f32 {
    if v.is_nan() || v == f32::INFINITY {
        return v;
    }
    if v == 0.0 {
        return f32::from_bits(1);
    }
    let bits = v.to_bits();
    f32::from_bits(if v > 0.0 { bits + 1 } else { bits - 1 })
}

/// The lowest threshold whose false match rate on `impostor` is at most `fmr`.
pub fn threshold_at(impostor: &[f32], fmr: f64) -> f32 {
    let mut sorted: Vec<f32> = impostor.iter().copied().filter(|v| v.is_finite()).collect();
    if sorted.is_empty() {
        return f32::NEG_INFINITY;
    }
    sorted.sort_by(|a, b| b.total_cmp(a));
    // At most `allowed` impostors may reach the threshold: put it just above the next one.
    let allowed = (fmr * sorted.len() as f64).floor() as usize;
    if allowed >= sorted.len() {
        return *sorted.last().expect("non-empty");
    }
    next_up(sorted[allowed])
}

impl Calibration {
    pub fn from_scores(genuine: &[f32], impostor: &[f32], fmrs: &[f64], source: &str) -> Calibration {
        let distinct = {
            let mut v: Vec<u32> = impostor.iter().map(|s| s.to_bits()).collect();
            v.sort_unstable();
            v.dedup();
            v.len()
        };
        let points = fmrs
            .iter()
            .map(|&fmr| {
                let threshold = threshold_at(impostor, fmr);
                let observed_fmr = impostor.iter().filter(|&&s| s >= threshold).count() as f64 / impostor.len().max(1) as f64;
                let observed_fnmr = genuine.iter().filter(|&&s| s < threshold).count() as f64 / genuine.len().max(1) as f64;
                CalibratedPoint { fmr, threshold, observed_fmr, observed_fnmr, under_sampled: (distinct as f64) * fmr < 1.0 }
            })
            .collect();
        Calibration { points, genuine_count: genuine.len(), impostor_count: impostor.len(), source: source.to_string() }
    }

    /// The calibrated point whose FMR is closest to `fmr` on a log scale.
    pub fn operating_point(&self, fmr: f64) -> OperatingPoint {
        let target = fmr.max(1e-12).log10();
        self.points
            .iter()
            .min_by(|a, b| (a.fmr.log10() - target).abs().total_cmp(&(b.fmr.log10() - target).abs()))
            .map(|p| OperatingPoint { fmr: p.fmr, threshold: p.threshold })
            .unwrap_or(OperatingPoint { fmr, threshold: f32::INFINITY })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn calibration_meets_its_fmr_on_the_scores_it_was_given() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        // Enough for 1e-5: 200,000 scores, 2 of them above its threshold.
        let impostor: Vec<f32> = (0..200_000).map(|_| rng.random::<f32>() * 0.6 - 0.2).collect();
        // Ties, which a careless threshold would count on the wrong side.
        let mut impostor_tied = impostor.clone();
        impostor_tied.extend(std::iter::repeat_n(0.39, 40));
        let genuine: Vec<f32> = (0..2_000).map(|_| 0.3 + rng.random::<f32>() * 0.7).collect();
        for imp in [&impostor, &impostor_tied] {
            let cal = Calibration::from_scores(&genuine, imp, &CALIBRATED_FMRS, "test");
            for p in &cal.points {
                let fm = imp.iter().filter(|&&s| s >= p.threshold).count() as f64 / imp.len() as f64;
                assert!(fm <= p.fmr, "FMR {fm} above {}", p.fmr);
                assert_eq!(fm, p.observed_fmr);
                // And it is the lowest such threshold: one step below lets more impostors through.
                let below = imp.iter().filter(|&&s| s >= p.threshold - 1e-6).count() as f64 / imp.len() as f64;
                assert!(below > fm || p.threshold <= -0.2, "threshold {} is not tight", p.threshold);
                assert!(!p.under_sampled);
            }
            assert!(cal.points.windows(2).all(|w| w[0].threshold <= w[1].threshold) && cal.points[0].threshold < cal.points[1].threshold);
            assert_eq!(cal.operating_point(1e-3).fmr, 1e-3);
            assert_eq!(cal.operating_point(2e-4).fmr, 1e-4);
            assert_eq!(cal.operating_point(1e-6).fmr, 1e-5);
            assert_eq!(calibrated_points(|fmr| cal.operating_point(fmr)).len(), 4);
        }
        // A table calibrated down to 1e-4 only: its 1e-4 point once, not again under 1e-5.
        let older = Calibration::from_scores(&genuine, &impostor, &CALIBRATED_FMRS[..3], "older");
        let points = calibrated_points(|fmr| older.operating_point(fmr));
        assert_eq!(points.iter().map(|p| p.fmr).collect::<Vec<_>>(), CALIBRATED_FMRS[..3]);
        // Few impostors: flagged, and the threshold is above all of them.
        let cal = Calibration::from_scores(&genuine, &impostor[..500], &CALIBRATED_FMRS, "few");
        assert!(cal.points[1].under_sampled);
        assert!(impostor[..500].iter().all(|&s| s < cal.points[1].threshold));
        // Many scores but few distinct ones (one pair repeated): still under-sampled.
        let repeated: Vec<f32> = impostor[..500].iter().cycle().take(5000).copied().collect();
        assert!(Calibration::from_scores(&genuine, &repeated, &CALIBRATED_FMRS, "repeated").points[1].under_sampled);
    }
}
