//! Scalar kernels `k0(x, x')` and their derivatives.
//!
//! The relative-degree-2 moments need `∂k/∂x`, `∂²k/∂x∂x'` and `∂²k/∂x²`
//! (paper, Sec. VI, Lemma 5); the Lipschitz bound needs the same (Lemma 3);
//! hyperparameter learning needs `∂k/∂ log θ`.

use crate::error::{check_positive, InputError};

/// A stationary or non-stationary scalar kernel on `R^d`.
///
/// Matrices are written row-major `d × d`. Hyperparameters are handled on a
/// log scale so that optimisers work on an unconstrained space.
pub trait Kernel: Clone + Send + Sync + std::fmt::Debug {
    /// Input dimension `d`.
    fn input_dim(&self) -> usize;
    /// `k(x, y)`.
    fn value(&self, x: &[f64], y: &[f64]) -> f64;
    /// Writes `∂k/∂x` into `out` (length `d`) and returns `k(x, y)`.
    fn grad_x(&self, x: &[f64], y: &[f64], out: &mut [f64]) -> f64;
    /// Writes `∂²k/∂x_i∂y_j` into `out` (row-major `d × d`), returns `k(x, y)`.
    fn hess_xy(&self, x: &[f64], y: &[f64], out: &mut [f64]) -> f64;
    /// Writes `∂²k/∂x_i∂x_j` into `out` (row-major `d × d`), returns `k(x, y)`.
    fn hess_xx(&self, x: &[f64], y: &[f64], out: &mut [f64]) -> f64;
    /// The shortest input distance over which `k` changes by a fraction of
    /// order one (the smallest lengthscale of the RBF): finite differences
    /// of the posterior need steps well below it.
    fn shortest_scale(&self) -> f64;
    /// Number of hyperparameters.
    fn n_hyper(&self) -> usize;
    /// Hyperparameters on a log scale.
    fn log_hyper(&self) -> Vec<f64>;
    /// Sets the hyperparameters from a log scale.
    fn set_log_hyper(&mut self, theta: &[f64]) -> Result<(), InputError>;
    /// Writes `∂k/∂ log θ` into `out` (length [`n_hyper`](Self::n_hyper)), returns `k(x, y)`.
    fn grad_log_hyper(&self, x: &[f64], y: &[f64], out: &mut [f64]) -> f64;
    /// Adds `w ∂k/∂ log θ (x, y)` to `acc` (length
    /// [`n_hyper`](Self::n_hyper)), given `value = k(x, y)`: the inner loop
    /// of the likelihood gradients, where `k(x, y)` is already known. The
    /// default calls [`grad_log_hyper`](Self::grad_log_hyper) with
    /// `scratch` (length `n_hyper`); a kernel overrides it to reuse
    /// `value`.
    fn add_grad_log_hyper(
        &self,
        x: &[f64],
        y: &[f64],
        value: f64,
        w: f64,
        acc: &mut [f64],
        scratch: &mut [f64],
    ) {
        let _ = value;
        self.grad_log_hyper(x, y, scratch);
        for (a, g) in acc.iter_mut().zip(scratch.iter()) {
            *a += w * g;
        }
    }
    /// Adds `Σ_i w_i ∂k/∂ log θ (x_i, y)` to `acc` (length
    /// [`n_hyper`](Self::n_hyper)) over the rows `x_i` of `xs` (row-major,
    /// `y.len()` columns), given `values[i] = k(x_i, y)`: one column of the
    /// likelihood gradient. The default calls
    /// [`add_grad_log_hyper`](Self::add_grad_log_hyper) row by row.
    fn add_grad_log_hyper_rows(
        &self,
        xs: &[f64],
        y: &[f64],
        values: &[f64],
        w: &[f64],
        acc: &mut [f64],
        scratch: &mut [f64],
    ) {
        for ((x, v), wi) in xs.chunks_exact(y.len()).zip(values).zip(w) {
            self.add_grad_log_hyper(x, y, *v, *wi, acc, scratch);
        }
    }
    /// Index of the hyperparameter that is a pure output scale (redundant with
    /// the MVGP's `B`), which training holds fixed.
    fn scale_index(&self) -> Option<usize> {
        None
    }
}

/// Automatic-relevance-determination squared-exponential kernel
/// `k0(x, x') = s · exp(−½ Σ_i (x_i − x'_i)² / ℓ_i²)`.
///
/// Log hyperparameters: `[log ℓ_1, …, log ℓ_d, log s]`.
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct Rbf {
    lengthscales: Vec<f64>,
    inv_l2: Vec<f64>,
    variance: f64,
}

impl Rbf {
    /// A kernel with the given lengthscales `ℓ_i > 0` and variance `s > 0`.
    pub fn new(lengthscales: Vec<f64>, variance: f64) -> Result<Self, InputError> {
        if lengthscales.is_empty() {
            return Err(InputError::shape(
                "kernel.lengthscales",
                "at least 1 entry",
                0,
            ));
        }
        for (i, &l) in lengthscales.iter().enumerate() {
            check_positive(&format!("kernel.lengthscales[{i}]"), l)?;
            if !(1.0 / (l * l)).is_finite() {
                return Err(InputError::invalid(
                    &format!("kernel.lengthscales[{i}]"),
                    l,
                    "too small: 1/ℓ² overflows (ℓ ≥ 1e-150)",
                ));
            }
        }
        check_positive("kernel.variance", variance)?;
        let inv_l2 = lengthscales.iter().map(|l| 1.0 / (l * l)).collect();
        Ok(Self {
            lengthscales,
            inv_l2,
            variance,
        })
    }

    /// Lengthscales `ℓ`.
    pub fn lengthscales(&self) -> &[f64] {
        &self.lengthscales
    }

    /// Variance `s`.
    pub fn variance(&self) -> f64 {
        self.variance
    }

    #[inline]
    fn scaled_diff(&self, x: &[f64], y: &[f64], r: &mut [f64]) -> f64 {
        // r_i = (x_i − y_i)/ℓ_i², returns k
        let mut q = 0.0;
        for i in 0..x.len() {
            let d = x[i] - y[i];
            q += d * d * self.inv_l2[i];
            r[i] = d * self.inv_l2[i];
        }
        self.variance * exp_neg_half(q)
    }
}

/// `Σ_{i<n} f(i)` with four independent partial sums: a reduction that is
/// not one chain of dependent additions runs several times faster.
#[inline]
pub(crate) fn sum_by_4(n: usize, f: impl Fn(usize) -> f64) -> f64 {
    let mut acc = [0.0; 4];
    let whole = n / 4 * 4;
    for i in (0..whole).step_by(4) {
        acc[0] += f(i);
        acc[1] += f(i + 1);
        acc[2] += f(i + 2);
        acc[3] += f(i + 3);
    }
    for i in whole..n {
        acc[0] += f(i);
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3])
}

/// `exp(−q/2)`, flushed to zero below `e^{−700}`: libm's slow path for
/// results in the subnormal range otherwise dominates the cost of Gram
/// matrices with small lengthscales.
#[inline]
fn exp_neg_half(q: f64) -> f64 {
    if q > 1400.0 {
        0.0
    } else {
        (-0.5 * q).exp()
    }
}

impl Kernel for Rbf {
    fn input_dim(&self) -> usize {
        self.lengthscales.len()
    }

    fn shortest_scale(&self) -> f64 {
        self.lengthscales
            .iter()
            .copied()
            .fold(f64::INFINITY, f64::min)
    }

    #[inline]
    fn value(&self, x: &[f64], y: &[f64]) -> f64 {
        let mut q = 0.0;
        for i in 0..x.len() {
            let d = x[i] - y[i];
            q += d * d * self.inv_l2[i];
        }
        self.variance * exp_neg_half(q)
    }

    fn grad_x(&self, x: &[f64], y: &[f64], out: &mut [f64]) -> f64 {
        let k = self.scaled_diff(x, y, out);
        for o in out.iter_mut() {
            *o *= -k;
        }
        k
    }

    fn hess_xy(&self, x: &[f64], y: &[f64], out: &mut [f64]) -> f64 {
        let d = x.len();
        let mut r = [0.0; 16];
        let mut rv;
        let r: &mut [f64] = if d <= 16 {
            &mut r[..d]
        } else {
            rv = vec![0.0; d];
            &mut rv
        };
        let k = self.scaled_diff(x, y, r);
        for i in 0..d {
            for j in 0..d {
                let delta = if i == j { self.inv_l2[i] } else { 0.0 };
                out[i * d + j] = k * (delta - r[i] * r[j]);
            }
        }
        k
    }

    fn hess_xx(&self, x: &[f64], y: &[f64], out: &mut [f64]) -> f64 {
        let k = self.hess_xy(x, y, out);
        for o in out.iter_mut() {
            *o = -*o;
        }
        k
    }

    fn n_hyper(&self) -> usize {
        self.lengthscales.len() + 1
    }

    fn log_hyper(&self) -> Vec<f64> {
        let mut v: Vec<f64> = self.lengthscales.iter().map(|l| l.ln()).collect();
        v.push(self.variance.ln());
        v
    }

    fn set_log_hyper(&mut self, theta: &[f64]) -> Result<(), InputError> {
        let d = self.lengthscales.len();
        if theta.len() != d + 1 {
            return Err(InputError::shape(
                "kernel hyperparameters",
                d + 1,
                theta.len(),
            ));
        }
        *self = Rbf::new(theta[..d].iter().map(|t| t.exp()).collect(), theta[d].exp())?;
        Ok(())
    }

    fn grad_log_hyper(&self, x: &[f64], y: &[f64], out: &mut [f64]) -> f64 {
        let k = self.value(x, y);
        let d = x.len();
        for i in 0..d {
            let di = x[i] - y[i];
            out[i] = k * di * di * self.inv_l2[i];
        }
        out[d] = k;
        k
    }

    #[inline]
    fn add_grad_log_hyper(
        &self,
        x: &[f64],
        y: &[f64],
        value: f64,
        w: f64,
        acc: &mut [f64],
        _scratch: &mut [f64],
    ) {
        // ∂k/∂ log ℓ_i = k (x_i − y_i)²/ℓ_i², ∂k/∂ log s = k
        let wk = w * value;
        let d = x.len();
        for i in 0..d {
            let di = x[i] - y[i];
            acc[i] += wk * di * di * self.inv_l2[i];
        }
        acc[d] += wk;
    }

    fn add_grad_log_hyper_rows(
        &self,
        xs: &[f64],
        y: &[f64],
        values: &[f64],
        w: &[f64],
        acc: &mut [f64],
        _scratch: &mut [f64],
    ) {
        let d = y.len();
        let m = values.len().min(w.len());
        let (values, w) = (&values[..m], &w[..m]);
        assert!(xs.len() >= m * d, "add_grad_log_hyper_rows: rows");
        for (e, (ye, il)) in y.iter().zip(&self.inv_l2).enumerate() {
            let s = sum_by_4(m, |i| {
                let t = xs[i * d + e] - ye;
                w[i] * values[i] * t * t
            });
            acc[e] += s * il;
        }
        acc[d] += sum_by_4(m, |i| values[i] * w[i]);
    }

    fn scale_index(&self) -> Option<usize> {
        Some(self.lengthscales.len())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fd_check(f: impl Fn(&[f64]) -> f64, x: &[f64], g: &[f64]) {
        let h = 1e-6;
        for i in 0..x.len() {
            let mut xp = x.to_vec();
            let mut xm = x.to_vec();
            xp[i] += h;
            xm[i] -= h;
            let fd = (f(&xp) - f(&xm)) / (2.0 * h);
            assert!(
                (fd - g[i]).abs() < 1e-7 * (1.0 + g[i].abs()),
                "i={i} fd={fd} g={}",
                g[i]
            );
        }
    }

    #[test]
    fn rbf_derivatives_match_finite_differences() {
        let k = Rbf::new(vec![0.7, 1.3, 0.4], 1.7).unwrap();
        let x = [0.3, -0.2, 0.1];
        let y = [0.1, 0.4, -0.2];
        let mut g = [0.0; 3];
        k.grad_x(&x, &y, &mut g);
        fd_check(|x| k.value(x, &y), &x, &g);
        let mut hxy = [0.0; 9];
        let mut hxx = [0.0; 9];
        k.hess_xy(&x, &y, &mut hxy);
        k.hess_xx(&x, &y, &mut hxx);
        for i in 0..3 {
            // ∂/∂y_j of (∂k/∂x_i)
            let row: Vec<f64> = (0..3).map(|j| hxy[i * 3 + j]).collect();
            fd_check(
                |yy| {
                    let mut g = [0.0; 3];
                    k.grad_x(&x, yy, &mut g);
                    g[i]
                },
                &y,
                &row,
            );
            let row: Vec<f64> = (0..3).map(|j| hxx[i * 3 + j]).collect();
            fd_check(
                |xx| {
                    let mut g = [0.0; 3];
                    k.grad_x(xx, &y, &mut g);
                    g[i]
                },
                &x,
                &row,
            );
        }
        let mut gh = [0.0; 4];
        k.grad_log_hyper(&x, &y, &mut gh);
        // the accumulating form, from the value, agrees
        let mut acc = [1.0; 4];
        k.add_grad_log_hyper(&x, &y, k.value(&x, &y), 0.5, &mut acc, &mut [0.0; 4]);
        for i in 0..4 {
            assert!((acc[i] - 1.0 - 0.5 * gh[i]).abs() < 1e-15);
        }
        // and over rows: the Rbf override against the default (pair by pair)
        let xs = [0.3, -0.2, 0.1, 0.5, 0.0, -0.4, -0.7, 0.2, 0.9];
        let values: Vec<f64> = xs.chunks(3).map(|x| k.value(x, &y)).collect();
        let w = [0.7, -1.2, 0.4];
        let (mut fast, mut slow) = ([0.0; 4], [0.0; 4]);
        k.add_grad_log_hyper_rows(&xs, &y, &values, &w, &mut fast, &mut [0.0; 4]);
        for ((x, v), wi) in xs.chunks(3).zip(&values).zip(&w) {
            k.add_grad_log_hyper(x, &y, *v, *wi, &mut slow, &mut [0.0; 4]);
        }
        for i in 0..4 {
            assert!((fast[i] - slow[i]).abs() < 1e-14, "{fast:?} {slow:?}");
        }
        let th = k.log_hyper();
        fd_check(
            |t| {
                let mut kk = k.clone();
                kk.set_log_hyper(t).unwrap();
                kk.value(&x, &y)
            },
            &th,
            &gh,
        );
    }

    #[test]
    fn rbf_rejects_bad_hyperparameters() {
        assert!(Rbf::new(vec![0.0], 1.0).is_err());
        assert!(Rbf::new(vec![1.0], -1.0).is_err());
        assert!(Rbf::new(vec![f64::NAN], 1.0).is_err());
        assert!(Rbf::new(vec![], 1.0).is_err());
    }
}
