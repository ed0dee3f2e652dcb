//! C-ASM against the 3D-ASM on turned renders of held-out faces: the |yaw| from which on the
//! 3D-ASM is the better search (`facegate eval landmarks`).

use std::io::Write;

use serde::Serialize;

use crate::dataset::ImmSample;

use facegate_core::face::EyeMouthCentres;
use facegate_detect::Detector;
use facegate_vision::landmarks::{Landmarker, Variant};

use super::{CentreSearch, d_eye};

/// Yaws (degrees) of the crossover renders.
pub const CROSSOVER_YAWS: [f32; 9] = [-60.0, -45.0, -30.0, -15.0, 0.0, 15.0, 30.0, 45.0, 60.0];

/// One |yaw| of the crossover measurement: C-ASM and the 3D-ASM on the same renders and boxes.
#[derive(Debug, Clone, Serialize)]
pub struct CrossoverRow {
    pub yaw: f32,
    pub renders: usize,
    /// Renders where the detector found no face (failures for both searches).
    pub detector_misses: usize,
    pub casm_d_eye_005: f64,
    pub casm_d_eye_01: f64,
    pub casm_mean_d_eye: f64,
    pub asm3d_d_eye_005: f64,
    pub asm3d_d_eye_01: f64,
    pub asm3d_mean_d_eye: f64,
}

/// C-ASM against the 3D-ASM on turned renders of held-out faces: every near-frontal photo
/// (|yaw| < 10° by the 3DMM fitted to its manual landmarks) of `test` is fitted by the 3DMM,
/// textured and rendered at each of [`CROSSOVER_YAWS`] (its pitch, no roll, no lighting change) by
/// the 3D-ASM training's renderer (`asm3d_synth::synthesise_view`, landmarks = projected model points
/// moved by the photo's annotation residual); both searches start from the detector's box on the
/// render. Rows by |yaw|. (The renders favour the 3D-ASM, whose view models were trained on
/// renders of other persons.)
pub fn crossover(
    fm: &facegate_morph::FaceModel,
    test: &[ImmSample],
    detector: &Detector,
    casm: &Landmarker,
    asm3d: CentreSearch,
) -> anyhow::Result<Vec<CrossoverRow>> {
    let bands = super::super::profile::bands(&CROSSOVER_YAWS);
    // Per band: (C-ASM d_eye, 3D-ASM d_eye) per render, infinite for a detector miss.
    let mut errors: Vec<Vec<(f64, f64)>> = vec![Vec::new(); bands.len()];
    let mut misses = vec![0usize; bands.len()];
    super::super::profile::for_each_render(fm, test, &CROSSOVER_YAWS, &mut |yaw, view| {
        let band = bands.iter().position(|&b| b == yaw.abs()).expect("a band per yaw");
        let truth_k = EyeMouthCentres::from_imm(&view.points);
        let Some(rect) = detector.detect(&view.gray).first().map(facegate_vision::pipeline::seed_box) else {
            misses[band] += 1;
            errors[band].push((f64::INFINITY, f64::INFINITY));
            return;
        };
        let c = casm.fit(&view.gray, &rect, Variant::Casm).centres;
        let a = asm3d(&view.gray, &rect);
        errors[band].push((d_eye(&c, &truth_k), d_eye(&a, &truth_k)));
    })?;
    let rows = bands
        .iter()
        .zip(errors)
        .zip(misses)
        .map(|((&yaw, e), detector_misses)| {
            let pct = |f: &dyn Fn(&(f64, f64)) -> f64, t: f64| e.iter().filter(|x| f(x) < t).count() as f64 / e.len().max(1) as f64;
            let mean = |f: &dyn Fn(&(f64, f64)) -> f64| {
                let v: Vec<f64> = e.iter().map(f).filter(|x| x.is_finite()).collect();
                v.iter().sum::<f64>() / v.len().max(1) as f64
            };
            CrossoverRow {
                yaw,
                renders: e.len(),
                detector_misses,
                casm_d_eye_005: pct(&|x| x.0, 0.05),
                casm_d_eye_01: pct(&|x| x.0, 0.1),
                casm_mean_d_eye: mean(&|x| x.0),
                asm3d_d_eye_005: pct(&|x| x.1, 0.05),
                asm3d_d_eye_01: pct(&|x| x.1, 0.1),
                asm3d_mean_d_eye: mean(&|x| x.1),
            }
        })
        .collect();
    Ok(rows)
}

/// The smallest |yaw| of `rows` from which on the 3D-ASM is better than C-ASM at every larger
/// |yaw| too (share with d_eye < 0.1 not lower, mean d_eye lower by at least 5%: a smaller
/// difference is within the photo-to-photo noise); `None` when it is not better at the largest.
pub fn crossover_yaw(rows: &[CrossoverRow]) -> Option<f32> {
    let wins = |r: &CrossoverRow| r.asm3d_d_eye_01 >= r.casm_d_eye_01 && r.asm3d_mean_d_eye < 0.95 * r.casm_mean_d_eye;
    let mut sorted: Vec<&CrossoverRow> = rows.iter().collect();
    sorted.sort_by(|a, b| a.yaw.total_cmp(&b.yaw));
    let mut from = None;
    for r in sorted.iter().rev() {
        if !wins(r) {
            break;
        }
        from = Some(r.yaw);
    }
    from
}

/// Print the crossover table.
pub fn print_crossover(rows: &[CrossoverRow], report: &mut dyn Write) -> std::io::Result<()> {
    writeln!(report, "crossover on renders of held-out faces (d_eye < 0.05 / < 0.1 / mean; detector misses count as failures)")?;
    writeln!(report, "{:>6} {:>8} {:>7} {:>26} {:>26}", "|yaw|", "renders", "misses", "C-ASM", "3D-ASM")?;
    for r in rows {
        let cell = |a: f64, b: f64, m: f64| format!("{:.1}% / {:.1}% / {:.4}", 100.0 * a, 100.0 * b, m);
        writeln!(
            report,
            "{:>6.0} {:>8} {:>7} {:>26} {:>26}",
            r.yaw,
            r.renders,
            r.detector_misses,
            cell(r.casm_d_eye_005, r.casm_d_eye_01, r.casm_mean_d_eye),
            cell(r.asm3d_d_eye_005, r.asm3d_d_eye_01, r.asm3d_mean_d_eye)
        )?;
    }
    match crossover_yaw(rows) {
        Some(y) => writeln!(report, "3D-ASM better than C-ASM from |yaw| {y:.0}° on")?,
        None => writeln!(report, "no crossover: C-ASM as good or better at the largest |yaw|")?,
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crossover_is_where_the_3d_asm_wins_from_on() {
        let row = |yaw: f32, c: f64, a: f64| CrossoverRow {
            yaw,
            renders: 10,
            detector_misses: 0,
            casm_d_eye_005: 1.0,
            casm_d_eye_01: 1.0,
            casm_mean_d_eye: c,
            asm3d_d_eye_005: 1.0,
            asm3d_d_eye_01: 1.0,
            asm3d_mean_d_eye: a,
        };
        // A 1% lower mean at 0° is no win.
        let rows = [row(0.0, 0.0202, 0.0200), row(30.0, 0.03, 0.02), row(15.0, 0.02, 0.03), row(45.0, 0.05, 0.03), row(60.0, 0.08, 0.04)];
        assert_eq!(crossover_yaw(&rows[..2]), Some(30.0));
        assert_eq!(crossover_yaw(&[rows[0].clone(), rows[2].clone(), rows[1].clone(), rows[3].clone(), rows[4].clone()]), Some(30.0));
        let mut lose = rows.clone();
        lose[1].asm3d_mean_d_eye = 0.04;
        // Wins at 45 and 60 but not at 30: the crossover is 45.
        assert_eq!(crossover_yaw(&lose), Some(45.0));
        // Losing at the largest |yaw|: none.
        lose[4].asm3d_d_eye_01 = 0.9;
        assert_eq!(crossover_yaw(&lose), None);
    }
}
