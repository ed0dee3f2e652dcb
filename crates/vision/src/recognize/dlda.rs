//! Direct LDA (Yu & Yang 2001, "A direct LDA algorithm for high-dimensional data").
//!
//! 1. Diagonalise the between-class scatter S_b = Φ_b Φ_bᵀ through the small C×C matrix Φ_bᵀ Φ_b,
//!    drop its null space and whiten: Z = Y D_b^{-1/2}, so that Zᵀ S_b Z = I.
//! 2. Diagonalise Zᵀ S_w Z = U D_w Uᵀ and keep the directions of *smallest* within-class variance,
//!    scaled by (D_w + ε)^{-1/2}: the projection is Wᵀ = (D_w + ε)^{-1/2} Uᵀ Zᵀ.
//!
//! The null space of S_w, which holds most of the discriminant information when there are fewer
//! samples than pixels, is kept (unlike PCA+LDA); ε regularises the inverse square root.
//! The projection is trained offline (`research::dlda`); here it is applied. Stored in f32.

use serde::{Deserialize, Serialize};

/// A trained projection: `y = P (x − mean)`, `P` stored row-major (`dims × input_dims`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Dlda {
    pub input_dims: usize,
    pub dims: usize,
    pub mean: Vec<f32>,
    pub projection: Vec<f32>,
    /// Within-class eigenvalues of the kept directions (whitened S_b space), ascending.
    pub within_eigenvalues: Vec<f64>,
}

impl Dlda {
    /// Project one feature vector into `out` (length `dims`). No allocation.
    pub fn project_into(&self, x: &[f32], out: &mut [f32]) {
        debug_assert_eq!(x.len(), self.input_dims);
        debug_assert_eq!(out.len(), self.dims);
        for (j, o) in out.iter_mut().enumerate() {
            let row = &self.projection[j * self.input_dims..(j + 1) * self.input_dims];
            // Eight independent partial sums, so that the compiler can vectorise the dot product
            // (a single f32 accumulator forces sequential adds).
            const LANES: usize = 8;
            let mut acc = [0.0f32; LANES];
            let (rc, xc, mc) = (row.chunks_exact(LANES), x.chunks_exact(LANES), self.mean.chunks_exact(LANES));
            let (rr, xr, mr) = (rc.remainder(), xc.remainder(), mc.remainder());
            for ((p, v), m) in rc.zip(xc).zip(mc) {
                for l in 0..LANES {
                    acc[l] += p[l] * (v[l] - m[l]);
                }
            }
            let mut tail = 0.0f32;
            for ((&p, &v), &m) in rr.iter().zip(xr).zip(mr) {
                tail += p * (v - m);
            }
            *o = acc.iter().sum::<f32>() + tail;
        }
    }

    /// Whether the projection takes `input_dims`-long feature vectors and is complete (a model
    /// file's consistency check).
    pub fn accepts(&self, input_dims: usize) -> bool {
        self.input_dims == input_dims && self.projection.len() == self.dims * input_dims && self.mean.len() == input_dims
    }

    /// `P · mean`, so that a projection is `P x − offsets` (one multiply-add per weight instead of a
    /// subtraction too): see [`Dlda::project_with_offsets`].
    pub fn offsets(&self) -> Vec<f32> {
        self.projection
            .chunks_exact(self.input_dims)
            .map(|row| row.iter().zip(&self.mean).map(|(&p, &m)| p as f64 * m as f64).sum::<f64>() as f32)
            .collect()
    }

    /// [`Dlda::project`] with the [`Dlda::offsets`] precomputed (equal up to rounding).
    pub fn project_with_offsets(&self, x: &[f32], offsets: &[f32]) -> Vec<f32> {
        debug_assert_eq!(x.len(), self.input_dims);
        const LANES: usize = 8;
        self.projection
            .chunks_exact(self.input_dims)
            .zip(offsets)
            .map(|(row, &offset)| {
                // Eight independent partial sums, so that the dot product vectorises.
                let mut acc = [0.0f32; LANES];
                let (rc, xc) = (row.chunks_exact(LANES), x.chunks_exact(LANES));
                let tail: f32 = rc.remainder().iter().zip(xc.remainder()).map(|(p, v)| p * v).sum();
                for (p, v) in rc.zip(xc) {
                    for l in 0..LANES {
                        acc[l] += p[l] * v[l];
                    }
                }
                acc.iter().sum::<f32>() + tail - offset
            })
            .collect()
    }

    pub fn project(&self, x: &[f32]) -> Vec<f32> {
        let mut out = vec![0.0; self.dims];
        self.project_into(x, &mut out);
        out
    }
}
