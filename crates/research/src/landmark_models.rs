//! The landmark models' training: the point distribution models (generalised Procrustes
//! alignment and PCA of the training shapes, thesis 2.3.1; the 3D-ASM's per-view 3D models) and the
//! Gaussian texture models whose Mahalanobis distances the searches use (thesis eq. 2.2–2.3). The
//! service only applies what these learnt (`landmarks::pdm`, `landmarks::mahalanobis`,
//! `landmarks::asm3d::Pdm3d`).

use nalgebra::{DMatrix, SymmetricEigen};

use facegate_core::geometry::{Point, Similarity};
use facegate_vision::landmarks::asm3d::Pdm3d;
use facegate_vision::landmarks::mahalanobis::{FullGaussian, PcaGaussian};
use facegate_vision::landmarks::pdm::ShapeModel;

/// Generalised Procrustes alignment: the mean shape (centred, scaled so its x extent is
/// `ref_width`) and every shape aligned to it by a similarity.
pub fn procrustes(shapes: &[Vec<Point>], ref_width: f32) -> (Vec<Point>, Vec<Vec<Point>>) {
    let n = shapes[0].len();
    let normalize = |s: &[Point]| -> Vec<Point> {
        let c = facegate_core::geometry::centroid(s);
        let centred: Vec<Point> = s.iter().map(|p| [p[0] - c[0], p[1] - c[1]]).collect();
        let norm = centred.iter().map(|p| p[0] * p[0] + p[1] * p[1]).sum::<f32>().sqrt().max(1e-6);
        centred.iter().map(|p| [p[0] / norm, p[1] / norm]).collect()
    };
    let mut mean = normalize(&shapes[0]);
    for _ in 0..10 {
        let mut acc = vec![[0.0f64; 2]; n];
        for s in shapes {
            let t = Similarity::fit(s, &mean, None);
            for (a, p) in acc.iter_mut().zip(s) {
                let q = t.apply(*p);
                a[0] += q[0] as f64;
                a[1] += q[1] as f64;
            }
        }
        let m: Vec<Point> = acc.iter().map(|a| [(a[0] / shapes.len() as f64) as f32, (a[1] / shapes.len() as f64) as f32]).collect();
        // Re-anchor the orientation to the previous mean so the iteration cannot drift.
        let m = normalize(&m);
        let r = Similarity::fit(&m, &mean, None);
        let s = r.scale().max(1e-6);
        mean = m.iter().map(|p| r.apply(*p)).map(|p| [p[0] / s, p[1] / s]).collect();
        mean = normalize(&mean);
    }
    let (x0, x1) = mean.iter().fold((f32::MAX, f32::MIN), |(a, b), p| (a.min(p[0]), b.max(p[0])));
    let k = ref_width / (x1 - x0).max(1e-6);
    let mean: Vec<Point> = mean.iter().map(|p| [p[0] * k, p[1] * k]).collect();
    let aligned =
        shapes.iter().map(|s| Similarity::fit(s, &mean, None)).zip(shapes).map(|(t, s)| s.iter().map(|p| t.apply(*p)).collect()).collect();
    (mean, aligned)
}

/// PCA of `samples` (each written as its deviation from the mean into a `dim` vector by
/// `deviation`): the unit eigenvectors (row-major, f32) and eigenvalues of the sample covariance,
/// largest first, as many as explain `variance` of the total. f64 inside: the covariance of
/// pixel coordinates is badly conditioned.
fn principal_modes<S>(dim: usize, samples: &[S], variance: f64, mut deviation: impl FnMut(&S, &mut [f64])) -> (Vec<f32>, Vec<f32>) {
    let mut cov = DMatrix::<f64>::zeros(dim, dim);
    let mut d = vec![0.0f64; dim];
    for s in samples {
        deviation(s, &mut d);
        for i in 0..dim {
            for j in i..dim {
                cov[(i, j)] += d[i] * d[j];
            }
        }
    }
    let nf = (samples.len().max(2) - 1) as f64;
    for i in 0..dim {
        for j in i..dim {
            cov[(i, j)] /= nf;
            cov[(j, i)] = cov[(i, j)];
        }
    }
    let eig = SymmetricEigen::new(cov);
    let mut order: Vec<usize> = (0..dim).collect();
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let total: f64 = eig.eigenvalues.iter().map(|v| v.max(0.0)).sum();
    let (mut basis, mut eigenvalues, mut acc) = (Vec::new(), Vec::new(), 0.0);
    for &k in &order {
        if acc >= variance * total {
            break;
        }
        let lambda = eig.eigenvalues[k].max(0.0);
        acc += lambda;
        eigenvalues.push(lambda as f32);
        basis.extend(eig.eigenvectors.column(k).iter().map(|&v| v as f32));
    }
    (basis, eigenvalues)
}

/// Align `shapes`, keep the principal modes explaining `variance` of the total (thesis: 0.98).
pub fn train_shape_model(shapes: &[Vec<Point>], ref_width: f32, variance: f64, constrain: f32) -> ShapeModel {
    let (mean, aligned) = procrustes(shapes, ref_width);
    let dim = 2 * mean.len();
    let (basis, eigenvalues) = principal_modes(dim, &aligned, variance, |s: &Vec<Point>, d| {
        for (i, (p, m)) in s.iter().zip(&mean).enumerate() {
            d[2 * i] = (p[0] - m[0]) as f64;
            d[2 * i + 1] = (p[1] - m[1]) as f64;
        }
    });
    ShapeModel { mean, basis, eigenvalues, constrain }
}

/// PCA of 3D point sets (no alignment: all are in the 3DMM's frame), keeping `variance` of the
/// total.
pub fn train_pdm3d(shapes: &[Vec<[f32; 3]>], variance: f64, constrain: f32) -> Pdm3d {
    let n = shapes[0].len();
    let dim = 3 * n;
    let count = shapes.len() as f64;
    let mut mean = vec![0.0f64; dim];
    for s in shapes {
        for (i, p) in s.iter().enumerate() {
            for d in 0..3 {
                mean[3 * i + d] += p[d] as f64 / count;
            }
        }
    }
    let (basis, eigenvalues) = principal_modes(dim, shapes, variance, |s: &Vec<[f32; 3]>, x| {
        for (i, p) in s.iter().enumerate() {
            for d in 0..3 {
                x[3 * i + d] = p[d] as f64 - mean[3 * i + d];
            }
        }
    });
    let mean = mean.chunks_exact(3).map(|c| [c[0] as f32, c[1] as f32, c[2] as f32]).collect();
    Pdm3d { mean, basis, eigenvalues, constrain }
}

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

/// The full-covariance Gaussian of `samples`, its covariance regularised by `ridge` of its mean
/// variance.
pub fn train_full_gaussian(samples: &[Vec<f32>], ridge: f64) -> FullGaussian {
    let (mean, mut cov) = mean_and_covariance(samples);
    let dim = mean.len();
    let reg = ridge * cov.trace() / dim as f64 + 1e-9;
    for i in 0..dim {
        cov[(i, i)] += reg;
    }
    let inv = cov.try_inverse().unwrap_or_else(|| DMatrix::identity(dim, dim));
    FullGaussian { mean: mean.iter().map(|&v| v as f32).collect(), inverse: inv.iter().map(|&v| v as f32).collect() }
}

/// The PCA-reduced Gaussian of `samples` over at most `modes` principal components.
pub fn train_pca_gaussian(samples: &[Vec<f32>], modes: usize) -> PcaGaussian {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_a_synthetic_mode_and_clamps() {
        // Squares whose width varies: one mode, recovered whatever the pose.
        let shapes: Vec<Vec<Point>> = (0..20)
            .map(|i| {
                let w = 1.0 + 0.05 * i as f32;
                vec![[-w, -1.0], [w, -1.0], [w, 1.0], [-w, 1.0]]
            })
            .collect();
        let m = train_shape_model(&shapes, 100.0, 0.98, 3.0);
        assert_eq!(m.modes(), 1);
        let t = Similarity { a: 2.0 * 0.4f32.cos(), b: 2.0 * 0.4f32.sin(), tx: 10.0, ty: 5.0 };
        let target: Vec<Point> = shapes[7].iter().map(|p| t.apply(*p)).collect();
        let (fit, _, _) = m.fit(&target);
        for (a, b) in fit.iter().zip(&target) {
            assert!((a[0] - b[0]).abs() < 1e-2 && (a[1] - b[1]).abs() < 1e-2, "{a:?} vs {b:?}");
        }
        // A far wider rectangle is pulled back into ±3σ.
        let wide: Vec<Point> = vec![[-9.0, -1.0], [9.0, -1.0], [9.0, 1.0], [-9.0, 1.0]];
        let (_, _, b) = m.fit(&wide);
        assert!((b[0].abs() - 3.0 * m.eigenvalues[0].sqrt()).abs() < 1e-3);
    }

    #[test]
    fn distances_prefer_the_training_distribution() {
        let samples: Vec<Vec<f32>> = (0..50).map(|i| vec![(i as f32 * 0.37).sin(), 0.1 * (i as f32 * 0.91).cos(), 2.0]).collect();
        let full = train_full_gaussian(&samples, 0.01);
        let pca = train_pca_gaussian(&samples, 2);
        let mut scratch = [0.0; 3];
        let near = [0.0f32, 0.0, 2.0];
        let off_axis = [0.0f32, 0.5, 2.0];
        assert!(full.distance(&near) < full.distance(&off_axis));
        assert!(pca.distance(&near, &mut scratch) < pca.distance(&off_axis, &mut scratch));
    }
}
