//! Direct LDA's training (Yu & Yang 2001, "A direct LDA algorithm for high-dimensional data"):
//! the projection [`Dlda`] the classical and deep recognizers apply, learnt from labelled samples.
//!
//! 1. Diagonalise the between-class scatter S_b = Φ_b Φ_bᵀ through the small C×C matrix Φ_bᵀ Φ_b,
//!    drop its null space and whiten: Z = Y D_b^{-1/2}, so that Zᵀ S_b Z = I.
//! 2. Diagonalise Zᵀ S_w Z = U D_w Uᵀ and keep the directions of *smallest* within-class variance,
//!    scaled by (D_w + ε)^{-1/2}: the projection is Wᵀ = (D_w + ε)^{-1/2} Uᵀ Zᵀ.
//!
//! Eigenproblems in f64 (faer); the stored projection is f32.

use faer::{Mat, Side};
use serde::{Deserialize, Serialize};

use facegate_vision::recognize::Dlda;

#[derive(Debug, thiserror::Error)]
pub enum DldaError {
    #[error("DLDA needs at least two classes with samples, got {0}")]
    TooFewClasses(usize),
    #[error("samples have {found} features, expected {expected}")]
    Dimension { expected: usize, found: usize },
    #[error("eigendecomposition failed: {0}")]
    Eigen(String),
    #[error("the between-class scatter is zero: the classes have identical means")]
    NoBetweenClassScatter,
}

/// Training parameters.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DldaParams {
    /// Output dimensions at most (the C−1 bound of S_b applies too).
    pub max_dims: usize,
    /// ε as a fraction of the mean within-class eigenvalue, added before the inverse square root.
    pub regularization: f64,
    /// When non-zero, the samples are first reduced to this many principal components and whitened
    /// (each component scaled to equal variance), and DLDA runs in that space; the two linear maps
    /// are composed into one stored projection, so templates cost the same. 0: DLDA on the raw
    /// features (the thesis).
    pub pca_dims: usize,
}

impl Default for DldaParams {
    fn default() -> Self {
        DldaParams { max_dims: 100, regularization: 0.01, pca_dims: 0 }
    }
}

/// Train from `samples` (equal length) with class `labels` (any integers).
pub fn train(samples: &[Vec<f32>], labels: &[usize], params: &DldaParams) -> Result<Dlda, DldaError> {
    assert_eq!(samples.len(), labels.len(), "one label per sample");
    let d = samples.first().map_or(0, |s| s.len());
    if let Some(bad) = samples.iter().find(|s| s.len() != d) {
        return Err(DldaError::Dimension { expected: d, found: bad.len() });
    }
    let mut classes: Vec<usize> = labels.to_vec();
    classes.sort_unstable();
    classes.dedup();
    let c = classes.len();
    if c < 2 || d == 0 {
        return Err(DldaError::TooFewClasses(c));
    }
    if params.pca_dims > 0 {
        return train_whitened(samples, labels, params);
    }
    let class_of: Vec<usize> = labels.iter().map(|l| classes.binary_search(l).expect("label listed")).collect();
    let n = samples.len();

    // Means in f64.
    let mut mean = vec![0.0f64; d];
    let mut class_mean = vec![vec![0.0f64; d]; c];
    let mut count = vec![0usize; c];
    for (s, &k) in samples.iter().zip(&class_of) {
        count[k] += 1;
        for ((m, cm), &v) in mean.iter_mut().zip(class_mean[k].iter_mut()).zip(s) {
            *m += v as f64;
            *cm += v as f64;
        }
    }
    mean.iter_mut().for_each(|m| *m /= n as f64);
    for (cm, &nk) in class_mean.iter_mut().zip(&count) {
        cm.iter_mut().for_each(|v| *v /= nk as f64);
    }

    // Φ_b (d × C), columns √n_c (μ_c − μ).
    let phi_b = Mat::<f64>::from_fn(d, c, |i, k| (count[k] as f64).sqrt() * (class_mean[k][i] - mean[i]));
    let gram = phi_b.transpose() * &phi_b;
    let eig = gram.self_adjoint_eigen(Side::Lower).map_err(|e| DldaError::Eigen(format!("{e:?}")))?;
    let values: Vec<f64> = (0..c).map(|i| eig.S().column_vector()[i]).collect();
    let largest = values.iter().cloned().fold(0.0f64, f64::max);
    if largest <= 0.0 {
        return Err(DldaError::NoBetweenClassScatter);
    }
    let kept: Vec<usize> = (0..c).filter(|&i| values[i] > 1e-9 * largest).collect();
    let m = kept.len();
    // Z = Φ_b v_i / λ_i (unit eigenvector of S_b, Φ_b v_i / √λ_i, divided again by √λ_i).
    let v = eig.U();
    let coeffs = Mat::<f64>::from_fn(c, m, |k, j| v[(k, kept[j])] / values[kept[j]]);
    let z = &phi_b * &coeffs;

    // Zᵀ S_w Z through H = Zᵀ (x_i − μ_{c(i)}), m × n.
    let xc = Mat::<f64>::from_fn(d, n, |i, s| samples[s][i] as f64 - class_mean[class_of[s]][i]);
    let h = z.transpose() * &xc;
    let sw = &h * h.transpose();
    let eig_w = sw.self_adjoint_eigen(Side::Lower).map_err(|e| DldaError::Eigen(format!("{e:?}")))?;
    let within: Vec<f64> = (0..m).map(|i| eig_w.S().column_vector()[i].max(0.0)).collect();
    let mean_within = within.iter().sum::<f64>() / m as f64;
    let eps = params.regularization * mean_within + 1e-12;
    let dims = params.max_dims.min(m).max(1);
    // Smallest within-class variance first (faer sorts ascending).
    let u = eig_w.U();
    let scaled = Mat::<f64>::from_fn(m, dims, |i, j| u[(i, j)] / (within[j] + eps).sqrt());
    let w = &z * &scaled; // d × dims
    let mut projection = Vec::with_capacity(dims * d);
    for j in 0..dims {
        for i in 0..d {
            projection.push(w[(i, j)] as f32);
        }
    }
    Ok(Dlda {
        input_dims: d,
        dims,
        mean: mean.iter().map(|&v| v as f32).collect(),
        projection,
        within_eigenvalues: within[..dims].to_vec(),
    })
}

/// PCA whitening to `params.pca_dims` components, DLDA there, then both maps composed.
///
/// With n samples the principal directions come from the n×n Gram matrix G = X_cᵀ X_c = V Λ Vᵀ:
/// the whitened coordinates of the training samples are the rows of Vᵀ (up to one common
/// factor), and the map from features is W = X_c V Λ^{-1} (d × k).
fn train_whitened(samples: &[Vec<f32>], labels: &[usize], params: &DldaParams) -> Result<Dlda, DldaError> {
    let d = samples[0].len();
    let n = samples.len();
    let mut mean = vec![0.0f64; d];
    for s in samples {
        for (m, &v) in mean.iter_mut().zip(s) {
            *m += v as f64;
        }
    }
    mean.iter_mut().for_each(|m| *m /= n as f64);
    let xc = Mat::<f64>::from_fn(d, n, |i, s| samples[s][i] as f64 - mean[i]);
    let gram = xc.transpose() * &xc;
    let eig = gram.self_adjoint_eigen(Side::Lower).map_err(|e| DldaError::Eigen(format!("{e:?}")))?;
    let values: Vec<f64> = (0..n).map(|i| eig.S().column_vector()[i]).collect();
    let largest = values.iter().cloned().fold(0.0f64, f64::max);
    if largest <= 0.0 {
        return Err(DldaError::NoBetweenClassScatter);
    }
    // Largest eigenvalues last (ascending order); keep at most pca_dims non-degenerate ones.
    let kept: Vec<usize> = (0..n).rev().filter(|&i| values[i] > 1e-9 * largest).take(params.pca_dims).collect();
    let k = kept.len();
    let v = eig.U();
    // Whitened training samples: y_s[j] = √n · v_j[s] (unit variance per component).
    let scale = (n as f64).sqrt();
    let reduced: Vec<Vec<f32>> = (0..n).map(|s| kept.iter().map(|&j| (scale * v[(s, j)]) as f32).collect()).collect();
    let inner = train(&reduced, labels, &DldaParams { pca_dims: 0, ..*params })?;
    // W = X_c V_k Λ_k^{-1} √n, so that Wᵀ x_c reproduces the whitened coordinates above.
    let coeffs = Mat::<f64>::from_fn(n, k, |s, j| scale * v[(s, kept[j])] / values[kept[j]]);
    let w = &xc * &coeffs; // d × k
    let p_inner = Mat::<f64>::from_fn(k, inner.dims, |j, r| inner.projection[r * k + j] as f64);
    let total = &w * &p_inner; // d × dims
    // The inner mean (whitened coordinates of the sample mean) is zero: each v_j with λ_j > 0 is
    // orthogonal to the all-ones vector, which spans G's null space for centred samples.
    let mut projection = Vec::with_capacity(inner.dims * d);
    for r in 0..inner.dims {
        for i in 0..d {
            projection.push(total[(i, r)] as f32);
        }
    }
    Ok(Dlda {
        input_dims: d,
        dims: inner.dims,
        mean: mean.iter().map(|&m| m as f32).collect(),
        projection,
        within_eigenvalues: inner.within_eigenvalues,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_distr::{Distribution, Normal};

    /// Three classes that differ only along axis 10 (σ 0.5 noise), under large nuisance variance on
    /// axes 0..5 (σ = 10, say illumination) that every class shares: each class gets the same
    /// nuisance draws, so the class means carry none of it, as with a balanced design.
    fn synthetic(seed: u64, per_class: usize) -> (Vec<Vec<f32>>, Vec<usize>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let unit = Normal::new(0.0f32, 1.0).unwrap();
        let nuisance: Vec<Vec<f32>> = (0..per_class).map(|_| (0..5).map(|_| 10.0 * unit.sample(&mut rng)).collect()).collect();
        let mut xs = Vec::new();
        let mut ys = Vec::new();
        for class in 0..3usize {
            for shared in &nuisance {
                let mut x: Vec<f32> = (0..20).map(|_| 0.5 * unit.sample(&mut rng)).collect();
                // The nuisance axes carry only the shared draws.
                x[..5].copy_from_slice(shared);
                x[10] += 3.0 * (class as f32 - 1.0) + 0.5 * rng.random::<f32>();
                xs.push(x);
                ys.push(class);
            }
        }
        (xs, ys)
    }

    /// Nearest-class-mean accuracy of projected test samples, class means from projected training samples.
    fn accuracy(project: &dyn Fn(&[f32]) -> Vec<f32>, train: &(Vec<Vec<f32>>, Vec<usize>), test: &(Vec<Vec<f32>>, Vec<usize>)) -> f64 {
        let mut means: Vec<(Vec<f32>, usize)> = vec![(Vec::new(), 0); 3];
        for (x, &y) in train.0.iter().zip(&train.1) {
            let p = project(x);
            if means[y].0.is_empty() {
                means[y].0 = vec![0.0; p.len()];
            }
            means[y].0.iter_mut().zip(&p).for_each(|(m, v)| *m += v);
            means[y].1 += 1;
        }
        let means: Vec<Vec<f32>> = means.into_iter().map(|(m, n)| m.into_iter().map(|v| v / n as f32).collect()).collect();
        let correct = test
            .0
            .iter()
            .zip(&test.1)
            .filter(|(x, y)| {
                let p = project(x);
                let dist = |m: &Vec<f32>| m.iter().zip(&p).map(|(a, b)| (a - b).powi(2)).sum::<f32>();
                (0..3).min_by(|&a, &b| dist(&means[a]).total_cmp(&dist(&means[b]))).unwrap() == **y
            })
            .count();
        correct as f64 / test.0.len() as f64
    }

    #[test]
    fn dlda_separates_synthetic_classes_that_pca_cannot() {
        let train = synthetic(1, 40);
        let test = synthetic(2, 40);
        let dlda = super::train(&train.0, &train.1, &DldaParams::default()).unwrap();
        assert_eq!(dlda.dims, 2, "C − 1 directions");
        let dlda_acc = accuracy(&|x| dlda.project(x), &train, &test);

        // PCA to the same number of dimensions: the leading components are the nuisance axes.
        let d = 20;
        let n = train.0.len();
        let mean: Vec<f64> = (0..d).map(|i| train.0.iter().map(|x| x[i] as f64).sum::<f64>() / n as f64).collect();
        let xc = Mat::<f64>::from_fn(d, n, |i, s| train.0[s][i] as f64 - mean[i]);
        let cov = &xc * xc.transpose();
        let eig = cov.self_adjoint_eigen(Side::Lower).unwrap();
        let u = eig.U().to_owned();
        let pca = |x: &[f32]| -> Vec<f32> {
            (0..2).map(|j| (0..d).map(|i| u[(i, d - 1 - j)] * (x[i] as f64 - mean[i])).sum::<f64>() as f32).collect()
        };
        let pca_acc = accuracy(&pca, &train, &test);

        assert!(dlda_acc > 0.95, "DLDA accuracy {dlda_acc}");
        assert!(pca_acc < 0.6, "PCA accuracy {pca_acc}");
    }

    /// PCA whitening before DLDA, composed into one projection: the stored map must equal whitening
    /// followed by the inner DLDA (checked through the class separation, and the mean mapping to 0).
    #[test]
    fn whitened_dlda_separates_and_composes() {
        let train = synthetic(1, 40);
        let test = synthetic(2, 40);
        let dlda = super::train(&train.0, &train.1, &DldaParams { pca_dims: 12, ..DldaParams::default() }).unwrap();
        assert_eq!((dlda.input_dims, dlda.dims), (20, 2));
        assert!(dlda.project(&dlda.mean).iter().all(|v| v.abs() < 1e-4));
        let acc = accuracy(&|x| dlda.project(x), &train, &test);
        assert!(acc > 0.95, "whitened DLDA accuracy {acc}");
    }

    #[test]
    fn projection_with_offsets_equals_projection() {
        let train = synthetic(4, 10);
        let dlda = super::train(&train.0, &train.1, &DldaParams::default()).unwrap();
        let offsets = dlda.offsets();
        for x in &train.0 {
            let (a, b) = (dlda.project(x), dlda.project_with_offsets(x, &offsets));
            assert!(a.iter().zip(&b).all(|(p, q)| (p - q).abs() < 1e-3 * (1.0 + p.abs())), "{a:?} {b:?}");
        }
    }

    #[test]
    fn projection_is_linear_and_rejects_bad_input() {
        let train = synthetic(3, 10);
        let dlda = super::train(&train.0, &train.1, &DldaParams { max_dims: 1, regularization: 0.1, pca_dims: 0 }).unwrap();
        assert_eq!(dlda.dims, 1);
        let y = dlda.project(&dlda.mean);
        assert!(y.iter().all(|v| v.abs() < 1e-4), "the mean projects to the origin");
        assert!(matches!(super::train(&train.0, &vec![0; train.0.len()], &DldaParams::default()), Err(DldaError::TooFewClasses(1))));
        let mut bad = train.0.clone();
        bad[3].pop();
        assert!(matches!(super::train(&bad, &train.1, &DldaParams::default()), Err(DldaError::Dimension { .. })));
    }
}
