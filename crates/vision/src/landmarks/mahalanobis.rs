//! Gaussian texture models and their Mahalanobis distances (thesis eq. 2.2–2.3): a full
//! regularised covariance for the short grey-level profiles, a PCA-reduced one for the 128-value
//! SIFT descriptors (distance in the principal subspace plus the residual off it). Trained offline
//! (`research::landmark_models`).

use facegate_core::vector::dot;
use serde::{Deserialize, Serialize};

/// Full-covariance Gaussian: `(g − ḡ)ᵀ C⁻¹ (g − ḡ)` with `C` regularised by a share of its trace.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FullGaussian {
    pub mean: Vec<f32>,
    /// Row-major inverse covariance.
    pub inverse: Vec<f32>,
}

impl FullGaussian {
    pub fn distance(&self, g: &[f32]) -> f32 {
        let dim = self.mean.len();
        let mut acc = 0.0;
        for i in 0..dim {
            let di = g[i] - self.mean[i];
            let row = &self.inverse[i * dim..(i + 1) * dim];
            let mut s = 0.0;
            for j in 0..dim {
                s += row[j] * (g[j] - self.mean[j]);
            }
            acc += di * s;
        }
        acc
    }
}

/// PCA-reduced Gaussian: Σ y_k²/λ_k over the `modes` principal components plus the squared
/// residual off that subspace divided by the mean discarded eigenvalue.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PcaGaussian {
    pub mean: Vec<f32>,
    /// `modes × dim` row-major.
    pub basis: Vec<f32>,
    pub inv_eigenvalues: Vec<f32>,
    pub inv_residual: f32,
}

impl PcaGaussian {
    /// Distance of `x`; `scratch` must hold `dim` values (no allocation per candidate).
    pub fn distance(&self, x: &[f32], scratch: &mut [f32]) -> f32 {
        #[cfg(target_arch = "x86_64")]
        if super::simd::avx2() {
            // SAFETY: the CPU has AVX2 (checked at run time).
            return unsafe { self.distance_avx2(x, scratch) };
        }
        self.distance_body(x, scratch)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn distance_avx2(&self, x: &[f32], scratch: &mut [f32]) -> f32 {
        self.distance_body(x, scratch)
    }

    #[inline(always)]
    fn distance_body(&self, x: &[f32], scratch: &mut [f32]) -> f32 {
        let dim = self.mean.len();
        let d = &mut scratch[..dim];
        for ((di, &xi), &mi) in d.iter_mut().zip(&x[..dim]).zip(&self.mean) {
            *di = xi - mi;
        }
        let norm2 = dot(d, d);
        let mut inside = 0.0;
        let mut proj2 = 0.0;
        for (k, &il) in self.inv_eigenvalues.iter().enumerate() {
            let y = dot(&self.basis[k * dim..(k + 1) * dim], d);
            inside += y * y * il;
            proj2 += y * y;
        }
        inside + (norm2 - proj2).max(0.0) * self.inv_residual
    }
}
