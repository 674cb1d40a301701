//! Control-affine systems `ẋ = f(x) + g(x)u = F(x)u̲` (paper, Sec. III, Eq. 1).
//!
//! Users implement [`ControlAffine`] once, generic over dual numbers, and get
//! exact Jacobians of `F` from forward-mode automatic differentiation
//! (num-dual). The object-safe [`DynSystem`] is implemented for every
//! [`ControlAffine`] so systems can be stored as `Arc<dyn DynSystem>` (for
//! example as the prior mean of a GP). [`GpSample`] is a draw of the MVGP
//! prior itself (random Fourier features), a truth for which a model with
//! the same prior is exactly right.
//!
//! ## Layout
//! `F(x) = [f(x) g(x)]` is `n × (1+m)` and is written **column-major** into a
//! slice of length `n(1+m)`: entry `(i, c)` is at `i + n c`. This is exactly
//! `vec F(x)`, the ordering used by the paper's Kronecker covariances.

mod ackermann;
mod expression;
mod gp_sample;
mod pendulum;

pub use ackermann::Ackermann;
pub use expression::ExpressionSystem;
pub use gp_sample::GpSample;
pub use pendulum::Pendulum;

use num_dual::{Dual64, DualNum};

/// A control-affine system `ẋ = f(x) + g(x) u`.
///
/// Only [`state_dim`](Self::state_dim), [`control_dim`](Self::control_dim) and
/// [`dynamics`](Self::dynamics) are required.
///
/// ## Reference
/// Paper, Sec. III, Eq. (1): `F(x) = [f(x) g(x)] ∈ R^{n×(1+m)}`, `u̲ = [1; u]`.
pub trait ControlAffine: Send + Sync {
    /// State dimension `n`.
    fn state_dim(&self) -> usize;
    /// Control dimension `m`.
    fn control_dim(&self) -> usize;
    /// Writes `vec F(x)` (column-major `n × (1+m)`) into `out`.
    ///
    /// `x.len() == n` and `out.len() == n(1+m)` are guaranteed by callers.
    fn dynamics<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D], out: &mut [D]);
    /// Indices of state components that are angles, wrapped to `[-π, π)` by
    /// the simulator and by finite differencing.
    fn angle_indices(&self) -> &[usize] {
        &[]
    }
    /// The first failed evaluation on this thread since its last call, for systems whose
    /// evaluation can fail (an expression that is not finite at some state:
    /// [`ExpressionSystem`]); `None` for systems written in Rust.
    fn take_error(&self) -> Option<String> {
        None
    }
}

/// Object-safe view of a [`ControlAffine`] system, implemented for all of them.
pub trait DynSystem: Send + Sync {
    /// State dimension `n`.
    fn state_dim(&self) -> usize;
    /// Control dimension `m`.
    fn control_dim(&self) -> usize;
    /// `vec F(x)` at a real point.
    fn eval_f64(&self, x: &[f64], out: &mut [f64]);
    /// `vec F(x)` on dual numbers (one directional derivative).
    fn eval_dual(&self, x: &[Dual64], out: &mut [Dual64]);
    /// Angle components.
    fn angle_indices(&self) -> &[usize];
    /// The first failed evaluation since the last call
    /// ([`ControlAffine::take_error`]).
    fn take_error(&self) -> Option<String>;

    /// Jacobian `∂ vec F / ∂x`, written column-major as `(n(1+m)) × n`
    /// (entry `(r, j)` at `r + n(1+m) j`), by `n` forward passes.
    /// `scratch_x` needs length `n`, `scratch_out` length `n(1+m)`.
    fn jacobian_into(
        &self,
        x: &[f64],
        jac: &mut [f64],
        scratch_x: &mut [Dual64],
        scratch_out: &mut [Dual64],
    ) {
        let n = self.state_dim();
        let rows = n * (1 + self.control_dim());
        for j in 0..n {
            crate::autodiff::seed_dual(x, j, scratch_x);
            self.eval_dual(scratch_x, scratch_out);
            for r in 0..rows {
                jac[r + rows * j] = scratch_out[r].eps;
            }
        }
    }

    /// `ẋ = F(x) u̲` for a real state and control (`u` without the leading 1).
    fn xdot(&self, x: &[f64], u: &[f64], f_buf: &mut [f64], out: &mut [f64]) {
        let n = self.state_dim();
        self.eval_f64(x, f_buf);
        for i in 0..n {
            let mut v = f_buf[i];
            for (c, uc) in u.iter().enumerate() {
                v += f_buf[i + n * (c + 1)] * uc;
            }
            out[i] = v;
        }
    }
}

impl<T: ControlAffine> DynSystem for T {
    fn state_dim(&self) -> usize {
        ControlAffine::state_dim(self)
    }
    fn control_dim(&self) -> usize {
        ControlAffine::control_dim(self)
    }
    fn eval_f64(&self, x: &[f64], out: &mut [f64]) {
        self.dynamics(x, out)
    }
    fn eval_dual(&self, x: &[Dual64], out: &mut [Dual64]) {
        self.dynamics(x, out)
    }
    fn angle_indices(&self) -> &[usize] {
        ControlAffine::angle_indices(self)
    }
    fn take_error(&self) -> Option<String> {
        ControlAffine::take_error(self)
    }
}

/// Wraps an angle to `[-π, π)`.
pub fn wrap_angle(a: f64) -> f64 {
    let two_pi = 2.0 * std::f64::consts::PI;
    let mut r = (a + std::f64::consts::PI).rem_euclid(two_pi) - std::f64::consts::PI;
    if r >= std::f64::consts::PI {
        r -= two_pi;
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrap_angle_range() {
        for a in [-10.0, -3.2, -std::f64::consts::PI, 0.0, 3.2, 7.0, 100.0] {
            let w = wrap_angle(a);
            assert!((-std::f64::consts::PI..std::f64::consts::PI).contains(&w));
            let k = ((a - w) / (2.0 * std::f64::consts::PI)).round();
            assert!((a - w - k * 2.0 * std::f64::consts::PI).abs() < 1e-12);
        }
    }
}
