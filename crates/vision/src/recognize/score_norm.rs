//! Cohort score normalisation (symmetric S-norm, and its adaptive variant AS-norm).
//!
//! A raw cosine means different things for different faces: a probe whose photo conditions (data
//! set, resolution, centre quality) resemble many faces scores high against everybody. S-norm
//! measures that per face against a fixed cohort of *other* people's templates (templates of the
//! training persons, shipped in the model) and standardises the score from both sides:
//!
//! s' = ½ ((s − μ_a) / σ_a + (s − μ_b) / σ_b),
//!
//! where μ_a, σ_a are the mean and standard deviation of face a's cosines against the cohort (and
//! likewise for b). AS-norm (`top_k > 0`) uses only the `top_k` highest cohort cosines of each face,
//! the cohort members most like it (Sturim & Reynolds 2005; Matějka et al. 2017). Scores are then
//! no longer cosines: thresholds are calibrated on normalised scores.

use serde::{Deserialize, Serialize};

/// The cohort: unit template vectors of training persons, row-major (`len × dims`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Cohort {
    pub dims: usize,
    pub vectors: Vec<f32>,
    /// 0: statistics over the whole cohort (S-norm); otherwise over the `top_k` highest cosines
    /// of each face (AS-norm).
    pub top_k: usize,
}

/// A face's cosine statistics against the cohort.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CohortStats {
    pub mean: f32,
    pub inv_std: f32,
}

impl Cohort {
    /// A cohort of `vectors` (each `dims` long; each is scaled to unit length).
    pub fn new(dims: usize, vectors: &[Vec<f32>], top_k: usize) -> Cohort {
        let mut flat = Vec::with_capacity(dims * vectors.len());
        for v in vectors {
            assert_eq!(v.len(), dims, "cohort vectors have the template dimension");
            let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
            let inv = if norm > 0.0 { 1.0 / norm } else { 0.0 };
            flat.extend(v.iter().map(|x| x * inv));
        }
        Cohort { dims, vectors: flat, top_k }
    }

    pub fn len(&self) -> usize {
        self.vectors.len() / self.dims.max(1)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Mean and inverse standard deviation of `vector`'s cosines against the cohort (or its
    /// `top_k` highest). `vector` must have the cohort's dimension.
    pub fn stats(&self, vector: &[f32]) -> CohortStats {
        let norm = vector.iter().map(|x| x * x).sum::<f32>().sqrt();
        if self.is_empty() || vector.len() != self.dims || norm <= 0.0 || !norm.is_finite() {
            return CohortStats { mean: 0.0, inv_std: 1.0 };
        }
        let mut scores: Vec<f32> =
            self.vectors.chunks_exact(self.dims).map(|c| c.iter().zip(vector).map(|(a, b)| a * b).sum::<f32>() / norm).collect();
        let k = if self.top_k == 0 || self.top_k >= scores.len() { scores.len() } else { self.top_k };
        if k < scores.len() {
            scores.select_nth_unstable_by(k - 1, |a, b| b.total_cmp(a));
            scores.truncate(k);
        }
        let n = scores.len() as f32;
        let mean = scores.iter().sum::<f32>() / n;
        let var = scores.iter().map(|s| (s - mean).powi(2)).sum::<f32>() / n;
        // A floor on σ so that a degenerate cohort cannot blow a score up.
        CohortStats { mean, inv_std: 1.0 / var.sqrt().max(1e-3) }
    }
}

/// The symmetric normalisation of the raw cosine `score` of faces with statistics `a` and `b`.
pub fn s_norm(score: f32, a: CohortStats, b: CohortStats) -> f32 {
    0.5 * ((score - a.mean) * a.inv_std + (score - b.mean) * b.inv_std)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn s_norm_standardises_from_both_sides() {
        // Cohort of the two axes of the plane; a face on the diagonal scores 1/√2 against both.
        let cohort = Cohort::new(2, &[vec![1.0, 0.0], vec![0.0, 2.0]], 0);
        assert_eq!(cohort.len(), 2);
        let d = cohort.stats(&[1.0, 1.0]);
        assert!((d.mean - std::f32::consts::FRAC_1_SQRT_2).abs() < 1e-6);
        assert!((d.inv_std - 1e3).abs() < 0.1, "zero spread is floored: {}", d.inv_std);
        let x = cohort.stats(&[3.0, 0.0]);
        assert!((x.mean - 0.5).abs() < 1e-6 && (x.inv_std - 2.0).abs() < 1e-5);
        // Symmetric, and a raw score at both means normalises to zero.
        assert_eq!(s_norm(0.3, d, x), s_norm(0.3, x, d));
        let same = CohortStats { mean: 0.2, inv_std: 4.0 };
        assert!(s_norm(0.2, same, same).abs() < 1e-7);
        assert!((s_norm(0.7, same, same) - 2.0).abs() < 1e-6);
        // AS-norm keeps the top k: against the best axis only.
        let top1 = Cohort { top_k: 1, ..cohort.clone() };
        let t = top1.stats(&[3.0, 1.0]);
        assert!((t.mean - 3.0 / 10f32.sqrt()).abs() < 1e-6);
        // Wrong dimension or a zero vector: neutral statistics, never a panic.
        assert_eq!(cohort.stats(&[1.0]), CohortStats { mean: 0.0, inv_std: 1.0 });
        assert_eq!(cohort.stats(&[0.0, 0.0]), CohortStats { mean: 0.0, inv_std: 1.0 });
    }
}
