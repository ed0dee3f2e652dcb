//! Point distribution model (thesis 2.3.1): a linear shape model (trained offline by generalised
//! Procrustes alignment and PCA, `research::landmark_models`) and its constrained fit to a cloud of
//! points.

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

impl ShapeModel {
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
