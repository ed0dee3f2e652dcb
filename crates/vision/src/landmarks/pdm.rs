//! Point distribution model (thesis 2.3.1): generalised Procrustes alignment of the training
//! shapes, PCA of the aligned coordinates, and the constrained fit of the model to a cloud of points.

use nalgebra::{DMatrix, SymmetricEigen};
use serde::{Deserialize, Serialize};

use facegate_core::geometry::{Point, Similarity};

/// A linear shape model `x = mean + Σ b_k φ_k` in a reference frame (pixels of the search crop),
/// with each `b_k` limited to `±constrain·sqrt(λ_k)`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ShapeModel {
    /// Mean shape, centred at the origin, in reference pixels.
    pub mean: Vec<Point>,
    /// `modes × 2n` row-major: each row a unit eigenvector over (x0, y0, x1, y1, …).
    pub basis: Vec<f32>,
    pub eigenvalues: Vec<f32>,
    /// S_constrain: the number of standard deviations a coefficient may reach (thesis: 3).
    pub constrain: f32,
}

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
pub(crate) fn principal_modes<S>(
    dim: usize,
    samples: &[S],
    variance: f64,
    mut deviation: impl FnMut(&S, &mut [f64]),
) -> (Vec<f32>, Vec<f32>) {
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

impl ShapeModel {
    /// Align `shapes`, keep the principal modes explaining `variance` of the total (thesis: 0.98).
    pub fn train(shapes: &[Vec<Point>], ref_width: f32, variance: f64, constrain: f32) -> ShapeModel {
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

    pub fn points(&self) -> usize {
        self.mean.len()
    }

    pub fn modes(&self) -> usize {
        self.eigenvalues.len()
    }

    /// Shape in the model frame for coefficients `b`.
    pub fn shape(&self, b: &[f32]) -> Vec<Point> {
        let mut out = self.mean.clone();
        for (k, &bk) in b.iter().enumerate() {
            let row = &self.basis[k * 2 * out.len()..(k + 1) * 2 * out.len()];
            for (i, p) in out.iter_mut().enumerate() {
                p[0] += bk * row[2 * i];
                p[1] += bk * row[2 * i + 1];
            }
        }
        out
    }

    /// Coefficients of a shape already in the model frame, clamped to the constraint box.
    pub fn project(&self, shape: &[Point]) -> Vec<f32> {
        let n = self.mean.len();
        (0..self.modes())
            .map(|k| {
                let row = &self.basis[k * 2 * n..(k + 1) * 2 * n];
                let v: f32 =
                    (0..n).map(|i| row[2 * i] * (shape[i][0] - self.mean[i][0]) + row[2 * i + 1] * (shape[i][1] - self.mean[i][1])).sum();
                let lim = self.constrain * self.eigenvalues[k].sqrt();
                v.clamp(-lim, lim)
            })
            .collect()
    }

    /// The nearest plausible shape to `target` (thesis 2.3.3 step 3): alternate the pose
    /// (similarity) and the clamped shape coefficients. Returns the shape in the target's frame,
    /// the pose and the coefficients.
    pub fn fit(&self, target: &[Point]) -> (Vec<Point>, Similarity, Vec<f32>) {
        let mut b = vec![0.0f32; self.modes()];
        let mut local = self.mean.clone();
        for _ in 0..8 {
            let pose = Similarity::fit(&local, target, None);
            let inv = pose.inverse();
            let y: Vec<Point> = target.iter().map(|p| inv.apply(*p)).collect();
            let nb = self.project(&y);
            let change: f32 = nb.iter().zip(&b).map(|(a, c)| (a - c).abs()).fold(0.0, f32::max);
            b = nb;
            local = self.shape(&b);
            if change < 1e-3 {
                break;
            }
        }
        let pose = Similarity::fit(&local, target, None);
        (local.iter().map(|p| pose.apply(*p)).collect(), pose, b)
    }
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
        let m = ShapeModel::train(&shapes, 100.0, 0.98, 3.0);
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
}
