//! The measures of two score distributions that recognition and liveness both read: the error
//! curve (FMR and FNMR at every threshold), the equal error rate and the FNMR at a fixed FMR. The
//! "genuine" scores are the ones that should pass (a person's own comparisons, live faces), the
//! "impostor" ones those that should not (other persons, attacks); a score passes when
//! `score >= threshold`. Recognition's summaries and plots are [`crate::eval::verification`]'s,
//! liveness's rates and operating points [`crate::liveness::measures`]'.

use facegate_vision::recognize::calibration::threshold_at;

/// One point of an error trade-off curve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ErrorPoint {
    pub threshold: f32,
    pub fmr: f64,
    pub fnmr: f64,
}

/// FMR and FNMR at every distinct score used as a threshold, from the lowest threshold (everything
/// matches: FMR 1) to above the highest (nothing matches: FMR 0).
pub fn error_curve(genuine: &[f32], impostor: &[f32]) -> Vec<ErrorPoint> {
    let mut all: Vec<(f32, bool)> =
        genuine.iter().map(|&s| (s, true)).chain(impostor.iter().map(|&s| (s, false))).filter(|(s, _)| s.is_finite()).collect();
    all.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (ng, ni) = (genuine.len().max(1) as f64, impostor.len().max(1) as f64);
    let mut out = Vec::with_capacity(all.len() + 1);
    // Scores below the threshold: genuine ones are false non-matches; impostors at or above are false matches.
    let (mut gen_below, mut imp_below) = (0usize, 0usize);
    let mut i = 0;
    while i < all.len() {
        let t = all[i].0;
        out.push(ErrorPoint { threshold: t, fmr: (impostor.len() - imp_below) as f64 / ni, fnmr: gen_below as f64 / ng });
        while i < all.len() && all[i].0 == t {
            if all[i].1 {
                gen_below += 1
            } else {
                imp_below += 1
            }
            i += 1;
        }
    }
    let above = all.last().map_or(0.0, |l| l.0) + 1e-6;
    out.push(ErrorPoint { threshold: above, fmr: (impostor.len() - imp_below) as f64 / ni, fnmr: gen_below as f64 / ng });
    out
}

/// Equal error rate: where FMR and FNMR cross, interpolated between the two curve points around
/// the crossing.
pub fn eer(genuine: &[f32], impostor: &[f32]) -> f64 {
    let curve = error_curve(genuine, impostor);
    for w in curve.windows(2) {
        let (a, b) = (w[0], w[1]);
        let (da, db) = (a.fmr - a.fnmr, b.fmr - b.fnmr);
        if da >= 0.0 && db <= 0.0 {
            if (da - db).abs() < 1e-15 {
                return 0.5 * (a.fmr + a.fnmr);
            }
            // Linear interpolation of both rates along the step.
            let t = da / (da - db);
            return 0.5 * ((a.fmr + t * (b.fmr - a.fmr)) + (a.fnmr + t * (b.fnmr - a.fnmr)));
        }
    }
    curve.first().map_or(0.0, |p| 0.5 * (p.fmr + p.fnmr))
}

/// FNMR at the lowest threshold whose FMR on `impostor` is at most `fmr`, and that threshold.
pub fn fnmr_at_fmr(genuine: &[f32], impostor: &[f32], fmr: f64) -> (f64, f32) {
    let t = threshold_at(impostor, fmr);
    (genuine.iter().filter(|&&s| s < t).count() as f64 / genuine.len().max(1) as f64, t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eer_and_fnmr_on_known_distributions() {
        // Perfectly separated: EER 0, FNMR 0 at any FMR.
        let g: Vec<f32> = (0..100).map(|i| 0.6 + i as f32 * 0.001).collect();
        let imp: Vec<f32> = (0..1000).map(|i| i as f32 * 0.0005).collect();
        assert!(eer(&g, &imp) < 1e-9);
        assert_eq!(fnmr_at_fmr(&g, &imp, 1e-3).0, 0.0);
        // Uniform genuine on [0.5, 1.5), impostor on [0, 1): the curves cross at 0.75 with 25 % error.
        let g: Vec<f32> = (0..1000).map(|i| 0.5 + i as f32 / 1000.0).collect();
        let imp: Vec<f32> = (0..1000).map(|i| i as f32 / 1000.0).collect();
        assert!((eer(&g, &imp) - 0.25).abs() < 0.002, "{}", eer(&g, &imp));
        let (fnmr, t) = fnmr_at_fmr(&g, &imp, 1e-2);
        assert!((t - 0.99).abs() < 0.0015 && (fnmr - 0.49).abs() < 0.002, "{t} {fnmr}");
        let curve = error_curve(&g, &imp);
        assert_eq!((curve[0].fmr, curve[0].fnmr), (1.0, 0.0));
        assert_eq!((curve.last().unwrap().fmr, curve.last().unwrap().fnmr), (0.0, 1.0));
    }
}
