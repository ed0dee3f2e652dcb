//! The 3D point distribution model of the 58 IMM points and its fit to 2D points.

use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

use facegate_core::geometry::Point;
use facegate_morph::{Camera, fit::estimate_camera};

/// A 3D point distribution model of the 58 IMM points (model millimetres: x to the subject's left,
/// y up, z towards the camera), coefficients limited to ±`constrain`·√λ.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Pdm3d {
    pub mean: Vec<[f32; 3]>,
    /// `modes × 3n` row-major: each row a unit eigenvector over (x0, y0, z0, x1, …).
    pub basis: Vec<f32>,
    pub eigenvalues: Vec<f32>,
    pub constrain: f32,
}

/// A fit of a [`Pdm3d`] to 2D points.
#[derive(Debug, Clone)]
pub struct Fit3d {
    pub camera: Camera,
    pub coefficients: Vec<f32>,
    /// The projected model points.
    pub points: Vec<Point>,
}

impl Pdm3d {
    pub fn points(&self) -> usize {
        self.mean.len()
    }

    pub fn modes(&self) -> usize {
        self.eigenvalues.len()
    }

    /// The 3D points for coefficients `b`.
    pub fn shape(&self, b: &[f32]) -> Vec<[f64; 3]> {
        let dim = 3 * self.points();
        let mut out: Vec<[f64; 3]> = self.mean.iter().map(|p| [p[0] as f64, p[1] as f64, p[2] as f64]).collect();
        for (k, &bk) in b.iter().enumerate().take(self.modes()) {
            let row = &self.basis[k * dim..(k + 1) * dim];
            for (i, p) in out.iter_mut().enumerate() {
                for d in 0..3 {
                    p[d] += bk as f64 * row[3 * i + d] as f64;
                }
            }
        }
        out
    }

    /// Project the shape `b` with `camera`.
    pub fn project(&self, b: &[f32], camera: &Camera) -> Vec<Point> {
        self.shape(b).iter().map(|&p| camera.project(p)).map(|q| [q[0] as f32, q[1] as f32]).collect()
    }

    /// Fit to 2D `targets`: alternate the scaled orthographic camera and the coefficients (linear
    /// least squares with the prior `σ²/λ_k` on each, then clamped to the constraint box).
    /// `None` when the targets are degenerate (collinear, non-finite).
    pub fn fit(&self, targets: &[Point], sigma_px: f64, iterations: usize) -> Option<Fit3d> {
        self.fit_weighted(targets, &vec![1.0; self.points()], sigma_px, iterations)
    }

    /// [`fit`](Self::fit) with a weight per point in the camera and in the coefficients' least
    /// squares: a point the view hides counts for little, since its texture candidate is the
    /// surface in front of it.
    pub fn fit_weighted(&self, targets: &[Point], weights: &[f64], sigma_px: f64, iterations: usize) -> Option<Fit3d> {
        let n = self.points();
        if targets.len() != n || weights.len() != n || targets.iter().any(|p| !p[0].is_finite() || !p[1].is_finite()) {
            return None;
        }
        let k = self.modes();
        let dim = 3 * n;
        let mut b = vec![0.0f32; k];
        let mut lhs = DMatrix::<f64>::zeros(k, k);
        let mut rhs = DVector::<f64>::zeros(k);
        let (mut au, mut av) = (vec![0.0f64; k], vec![0.0f64; k]);
        for _ in 0..iterations.max(1) {
            let cam = estimate_camera(&self.shape(&b), targets, weights).ok()?;
            if k == 0 {
                break;
            }
            lhs.fill(0.0);
            rhs.fill(0.0);
            let (r0, r1) = (cam.rotation[0], cam.rotation[1]);
            for i in 0..n {
                let m = self.mean[i];
                let pm = cam.rotate([m[0] as f64, m[1] as f64, m[2] as f64]);
                let ru = targets[i][0] as f64 - (cam.scale * pm[0] + cam.tx);
                let rv = (cam.ty - targets[i][1] as f64) - cam.scale * pm[1];
                for q in 0..k {
                    let row = &self.basis[q * dim + 3 * i..q * dim + 3 * i + 3];
                    au[q] = cam.scale * (r0[0] * row[0] as f64 + r0[1] * row[1] as f64 + r0[2] * row[2] as f64);
                    av[q] = cam.scale * (r1[0] * row[0] as f64 + r1[1] * row[1] as f64 + r1[2] * row[2] as f64);
                }
                let w = weights[i];
                for p in 0..k {
                    rhs[p] += w * (au[p] * ru + av[p] * rv);
                    for q in p..k {
                        lhs[(p, q)] += w * (au[p] * au[q] + av[p] * av[q]);
                    }
                }
            }
            for p in 0..k {
                lhs[(p, p)] += sigma_px * sigma_px / (self.eigenvalues[p] as f64).max(1e-9);
                for q in 0..p {
                    lhs[(p, q)] = lhs[(q, p)];
                }
            }
            let sol = lhs.clone().cholesky()?.solve(&rhs);
            for (q, slot) in b.iter_mut().enumerate() {
                let lim = self.constrain * self.eigenvalues[q].sqrt();
                *slot = (sol[q] as f32).clamp(-lim, lim);
            }
        }
        let camera = estimate_camera(&self.shape(&b), targets, weights).ok()?;
        let points = self.project(&b, &camera);
        if points.iter().any(|p| !p[0].is_finite() || !p[1].is_finite()) {
            return None;
        }
        Some(Fit3d { camera, coefficients: b, points })
    }
}
