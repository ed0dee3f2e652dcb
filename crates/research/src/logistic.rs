//! The one logistic regression of research: ridge-penalised, on standardised features, fitted by
//! Newton's method (faer's Cholesky for the Hessian: the liveness features are 1,300 wide), and
//! Platt's calibration over it. Liveness training and evaluation ([`fit_binary`]: live or attack,
//! a weight per row) and quality training (fractional targets through [`fit`]) both fit here.

use std::iter::Sum;
use std::ops::{Add, Div, Mul, Sub};

use faer::linalg::solvers::Solve;
use faer::{Mat, Side};
use serde::{Deserialize, Serialize};

/// The precision a fit is kept and scored in: `f32` where the runtime model scores in `f32`
/// (liveness), `f64` where it scores in `f64` (quality).
pub trait Real: Copy + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self> + Div<Output = Self> + Sum {
    fn of(v: f64) -> Self;
    fn to_f64(self) -> f64;
}

impl Real for f32 {
    fn of(v: f64) -> f32 {
        v as f32
    }
    fn to_f64(self) -> f64 {
        self as f64
    }
}

impl Real for f64 {
    fn of(v: f64) -> f64 {
        v
    }
    fn to_f64(self) -> f64 {
        self
    }
}

/// A logistic regression on standardised features: logit = bias + Σ weight·(x − mean)/scale.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LogisticFit<T = f32> {
    pub mean: Vec<T>,
    pub scale: Vec<T>,
    pub weights: Vec<T>,
    pub bias: T,
}

impl<T: Real> LogisticFit<T> {
    /// The linear predictor (the logit) of the features `x`.
    pub fn logit(&self, x: &[T]) -> T {
        self.logit_of(x.iter().copied())
    }

    /// The logit of the features `x` at `cols`: a fit on some columns scoring a wider row.
    pub fn logit_at(&self, cols: &[usize], x: &[T]) -> T {
        self.logit_of(cols.iter().map(|&c| x[c]))
    }

    fn logit_of(&self, x: impl Iterator<Item = T>) -> T {
        self.bias + x.zip(&self.mean).zip(&self.scale).zip(&self.weights).map(|(((x, &m), &s), &w)| w * (x - m) / s).sum::<T>()
    }
}

/// How a fit is set up and when Newton's method stops.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Options {
    /// Whether the features' means and scales are weighted by each row's weight (pass + fail), or
    /// every row counts alike.
    pub standardise_weighted: bool,
    /// The ridge penalty on the standardised weights (not the intercept), per unit of the
    /// standardisation's total weight (the row count when unweighted).
    pub ridge: f64,
    /// Newton steps at most, and the step length below which the fit has converged.
    pub iterations: usize,
    pub tolerance: f64,
}

/// Logistic regression of `rows` where row `i` counts `pass[i]` towards the positive outcome and
/// `fail[i]` towards the negative one: a weighted binary regression (one of the two zero), or a
/// fractional one (a target share split between them). Newton's method from zero, with a Cholesky
/// solve of the penalised Hessian (its intercept held positive definite by a 1e-9 jitter);
/// a Hessian that is not positive definite ends the fit where it stands.
pub fn fit<T: Real>(rows: &[&[T]], pass: &[f64], fail: &[f64], options: Options) -> LogisticFit<T> {
    let (n, d) = (rows.len(), rows.first().map_or(0, |r| r.len()));
    let standardising: Vec<f64> =
        if options.standardise_weighted { pass.iter().zip(fail).map(|(a, b)| a + b).collect() } else { vec![1.0; n] };
    let total: f64 = standardising.iter().sum::<f64>().max(1e-12);
    let mean: Vec<f64> = (0..d).map(|k| rows.iter().zip(&standardising).map(|(r, w)| w * r[k].to_f64()).sum::<f64>() / total).collect();
    let scale: Vec<f64> = (0..d)
        .map(|k| (rows.iter().zip(&standardising).map(|(r, w)| w * (r[k].to_f64() - mean[k]).powi(2)).sum::<f64>() / total).sqrt())
        .map(|s| if s > 1e-9 { s } else { 1.0 })
        .collect();
    let x = Mat::<f64>::from_fn(n, d + 1, |i, k| if k == 0 { 1.0 } else { (rows[i][k - 1].to_f64() - mean[k - 1]) / scale[k - 1] });
    let lambda = options.ridge * total;
    let mut w = Mat::<f64>::zeros(d + 1, 1);
    for _ in 0..options.iterations {
        let z = &x * &w;
        let p: Vec<f64> = (0..n).map(|i| 1.0 / (1.0 + (-z[(i, 0)]).exp())).collect();
        let residual = Mat::<f64>::from_fn(n, 1, |i, _| pass[i] * (1.0 - p[i]) - fail[i] * p[i]);
        let mut gradient = x.transpose() * &residual;
        let root = Mat::<f64>::from_fn(n, d + 1, |i, k| x[(i, k)] * ((pass[i] + fail[i]) * p[i] * (1.0 - p[i])).max(1e-12).sqrt());
        let mut hessian = root.transpose() * &root;
        for k in 1..=d {
            gradient[(k, 0)] -= lambda * w[(k, 0)];
            hessian[(k, k)] += lambda;
        }
        hessian[(0, 0)] += 1e-9 * total;
        let Ok(llt) = hessian.llt(Side::Lower) else { break };
        let step = llt.solve(&gradient);
        w += &step;
        let size = (0..=d).map(|k| step[(k, 0)].powi(2)).sum::<f64>().sqrt();
        if size < options.tolerance {
            break;
        }
    }
    LogisticFit {
        mean: mean.iter().map(|&v| T::of(v)).collect(),
        scale: scale.iter().map(|&v| T::of(v)).collect(),
        weights: (1..=d).map(|k| T::of(w[(k, 0)])).collect(),
        bias: T::of(w[(0, 0)]),
    }
}

/// Ridge-penalised logistic regression of `positive` on `rows`, each row weighted by `weights`
/// (the features standardised under the same weights); `ridge` is the penalty per unit of total
/// weight. Thirty Newton steps at most, to a step of 1e-6.
pub fn fit_binary(rows: &[&[f32]], positive: &[bool], weights: &[f64], ridge: f64) -> LogisticFit<f32> {
    let pass: Vec<f64> = positive.iter().zip(weights).map(|(&p, &w)| if p { w } else { 0.0 }).collect();
    let fail: Vec<f64> = positive.iter().zip(weights).map(|(&p, &w)| if p { 0.0 } else { w }).collect();
    fit(rows, &pass, &fail, Options { standardise_weighted: true, ridge, iterations: 30, tolerance: 1e-6 })
}

/// Platt's calibration: the slope and offset of a one-feature logistic regression of `positive`
/// on `logits`, the two classes weighted to equal totals (a probability at even prior odds).
pub fn platt(logits: &[f32], positive: &[bool]) -> (f32, f32) {
    let rows: Vec<[f32; 1]> = logits.iter().map(|&l| [l]).collect();
    let refs: Vec<&[f32]> = rows.iter().map(|r| &r[..]).collect();
    let n = positive.len() as f64;
    let count = |class: bool| positive.iter().filter(|&&p| p == class).count() as f64;
    let (yes, no) = (count(true), count(false));
    let weights: Vec<f64> = positive.iter().map(|&p| 0.5 * n / if p { yes } else { no }).collect();
    let fit = fit_binary(&refs, positive, &weights, 1e-6);
    // logit' = bias + w·(l − m)/s = (w/s)·l + (bias − w·m/s).
    let slope = fit.weights[0] / fit.scale[0];
    (slope, fit.bias - slope * fit.mean[0])
}

/// The probability of the positive class from a `logit` under [`platt`]'s `(slope, offset)`, as
/// the runtime liveness model's `probability` computes it.
pub fn platt_probability((slope, offset): (f32, f32), logit: f32) -> f32 {
    1.0 / (1.0 + (-(slope * logit + offset)).exp())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_fit_scores_the_columns_it_was_fitted_on() {
        let fit: LogisticFit<f32> = LogisticFit { mean: vec![1.0, -2.0], scale: vec![2.0, 0.5], weights: vec![0.3, -1.5], bias: 0.25 };
        let all = [9.0, 3.0, 7.0, -1.0];
        // Columns 2 and 3: 0.25 + 0.3·(7 − 1)/2 − 1.5·(−1 + 2)/0.5 = 0.25 + 0.9 − 3.0.
        assert_eq!(fit.logit_at(&[2, 3], &all), fit.logit(&[7.0, -1.0]));
        assert!((fit.logit_at(&[2, 3], &all) - (-1.85)).abs() < 1e-6);
        assert!((platt_probability((2.0, -1.0), 0.5) - 0.5).abs() < 1e-6, "a logit calibrated to 0 is even odds");
    }

    #[test]
    fn the_logistic_fit_separates_and_platt_keeps_the_order() {
        // Two Gaussian-ish clouds on the first feature; the second is noise.
        let rows: Vec<[f32; 2]> = (0..200).map(|i| [if i % 2 == 0 { 1.0 } else { -1.0 } + (i % 7) as f32 * 0.1, (i % 5) as f32]).collect();
        let live: Vec<bool> = (0..200).map(|i| i % 2 == 0).collect();
        let refs: Vec<&[f32]> = rows.iter().map(|r| &r[..]).collect();
        let fit = fit_binary(&refs, &live, &vec![1.0; 200], 1e-3);
        assert!(fit.weights[0].abs() > 4.0 * fit.weights[1].abs(), "{fit:?}");
        let logits: Vec<f32> = refs.iter().map(|r| fit.logit(r)).collect();
        assert!(logits.iter().zip(&live).all(|(l, live)| (*l > 0.0) == *live));
        let (slope, _) = platt(&logits, &live);
        assert!(slope > 0.0);
    }
}
