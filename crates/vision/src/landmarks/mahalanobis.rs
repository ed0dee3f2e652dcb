//! Gaussian texture models and their Mahalanobis distances (thesis eq. 2.2–2.3): a full
//! regularised covariance for the short grey-level profiles, a PCA-reduced one for the 128-value
//! SIFT descriptors (distance in the principal subspace plus the residual off it).

use facegate_core::vector::dot;
use nalgebra::{DMatrix, SymmetricEigen};
use serde::{Deserialize, Serialize};

fn mean_and_covariance(samples: &[Vec<f32>]) -> (Vec<f64>, DMatrix<f64>) {
    let dim = samples[0].len();
    let n = samples.len() as f64;
    let mut mean = vec![0.0f64; dim];
    for s in samples {
        for (m, &v) in mean.iter_mut().zip(s) {
            *m += v as f64 / n;
        }
    }
    let mut cov = DMatrix::<f64>::zeros(dim, dim);
    let mut d = vec![0.0f64; dim];
    for s in samples {
        for i in 0..dim {
            d[i] = s[i] as f64 - mean[i];
        }
        for i in 0..dim {
            for j in i..dim {
                cov[(i, j)] += d[i] * d[j];
            }
        }
    }
    let denom = (n - 1.0).max(1.0);
    for i in 0..dim {
        for j in i..dim {
            cov[(i, j)] /= denom;
            cov[(j, i)] = cov[(i, j)];
        }
    }
    (mean, cov)
}

/// Full-covariance Gaussian: `(g − ḡ)ᵀ C⁻¹ (g − ḡ)` with `C` regularised by a share of its trace.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FullGaussian {
    pub mean: Vec<f32>,
    /// Row-major inverse covariance.
    pub inverse: Vec<f32>,
}

impl FullGaussian {
    pub fn train(samples: &[Vec<f32>], ridge: f64) -> FullGaussian {
        let (mean, mut cov) = mean_and_covariance(samples);
        let dim = mean.len();
        let reg = ridge * cov.trace() / dim as f64 + 1e-9;
        for i in 0..dim {
            cov[(i, i)] += reg;
        }
        let inv = cov.try_inverse().unwrap_or_else(|| DMatrix::identity(dim, dim));
        FullGaussian { mean: mean.iter().map(|&v| v as f32).collect(), inverse: inv.iter().map(|&v| v as f32).collect() }
    }

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
    pub fn train(samples: &[Vec<f32>], modes: usize) -> PcaGaussian {
        let (mean, cov) = mean_and_covariance(samples);
        let dim = mean.len();
        let eig = SymmetricEigen::new(cov);
        let mut order: Vec<usize> = (0..dim).collect();
        order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
        let modes = modes.min(dim).min(samples.len().saturating_sub(1)).max(1);
        let total: f64 = eig.eigenvalues.iter().map(|v| v.max(0.0)).sum::<f64>().max(1e-12);
        let rest: f64 = order[modes..].iter().map(|&k| eig.eigenvalues[k].max(0.0)).sum();
        // Floor the residual variance so that a few training samples cannot make it vanish.
        let residual = (rest / (dim - modes).max(1) as f64).max(1e-3 * total / dim as f64);
        let mut basis = Vec::with_capacity(modes * dim);
        let mut inv_eigenvalues = Vec::with_capacity(modes);
        for &k in &order[..modes] {
            basis.extend(eig.eigenvectors.column(k).iter().map(|&v| v as f32));
            inv_eigenvalues.push((1.0 / eig.eigenvalues[k].max(residual)) as f32);
        }
        PcaGaussian { mean: mean.iter().map(|&v| v as f32).collect(), basis, inv_eigenvalues, inv_residual: (1.0 / residual) as f32 }
    }

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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distances_prefer_the_training_distribution() {
        let samples: Vec<Vec<f32>> = (0..50).map(|i| vec![(i as f32 * 0.37).sin(), 0.1 * (i as f32 * 0.91).cos(), 2.0]).collect();
        let full = FullGaussian::train(&samples, 0.01);
        let pca = PcaGaussian::train(&samples, 2);
        let mut scratch = [0.0; 3];
        let near = [0.0f32, 0.0, 2.0];
        let off_axis = [0.0f32, 0.5, 2.0];
        assert!(full.distance(&near) < full.distance(&off_axis));
        assert!(pca.distance(&near, &mut scratch) < pca.distance(&off_axis, &mut scratch));
    }
}
