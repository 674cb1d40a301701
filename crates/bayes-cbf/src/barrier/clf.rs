//! Control Lyapunov functions, possibly time-varying through a reference
//! `x_d(t)` with derivative `ẋ_d(t)`.

use crate::error::InputError;
use num_dual::{Dual64, DualNum};

/// A control Lyapunov function `V(x, x_d)`.
///
/// The condition is `CLC = ∇ₓVᵀ F(x)u̲ + ∇_{x_d}Vᵀ ẋ_d + γ V ≤ δ`
/// (paper, Sec. VII-B).
pub trait Lyapunov: Send + Sync {
    /// State dimension.
    fn state_dim(&self) -> usize;
    /// `V(x, x_d)`; `xd` has the state dimension.
    fn v<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D], xd: &[D]) -> D;
    /// Decay rate `γ`.
    fn gamma(&self) -> f64;
}

/// Object-safe view of a [`Lyapunov`] function.
pub trait DynLyapunov: Send + Sync {
    /// State dimension.
    fn state_dim(&self) -> usize;
    /// `V` on dual numbers.
    fn v_dual(&self, x: &[Dual64], xd: &[Dual64]) -> Dual64;
    /// `γ`.
    fn gamma(&self) -> f64;

    /// `∇ₓV` into `grad`, returns `(V, ∇_{x_d}Vᵀ ẋ_d)`. Scratch length `2n`.
    ///
    /// # Panics
    /// If `grad` is shorter than `x`, `scratch` shorter than `2n`, or `xd`
    /// or `xd_dot` shorter than `x`.
    fn gradient(
        &self,
        x: &[f64],
        xd: &[f64],
        xd_dot: &[f64],
        grad: &mut [f64],
        scratch: &mut [Dual64],
    ) -> (f64, f64) {
        let n = x.len();
        super::check_buffers(n, grad.len(), 2 * n, scratch.len());
        assert!(
            xd.len() >= n && xd_dot.len() >= n,
            "xd and xd_dot need {n} entries, they have {} and {}",
            xd.len(),
            xd_dot.len()
        );
        let (sx, sd) = scratch.split_at_mut(n);
        let mut v = 0.0;
        for j in 0..n {
            crate::autodiff::seed_dual(x, j, &mut sx[..n]);
            for i in 0..n {
                sd[i] = Dual64::from(xd[i]);
            }
            let r = self.v_dual(sx, &sd[..n]);
            grad[j] = r.eps;
            v = r.re;
        }
        // directional derivative along ẋ_d
        for i in 0..n {
            sx[i] = Dual64::from(x[i]);
            sd[i] = Dual64::new(xd[i], xd_dot[i]);
        }
        let r = self.v_dual(sx, &sd[..n]);
        (v, r.eps)
    }
}

impl<T: Lyapunov> DynLyapunov for T {
    fn state_dim(&self) -> usize {
        Lyapunov::state_dim(self)
    }
    fn v_dual(&self, x: &[Dual64], xd: &[Dual64]) -> Dual64 {
        self.v(x, xd)
    }
    fn gamma(&self) -> f64 {
        Lyapunov::gamma(self)
    }
}

/// The Ackermann CLF of Sec. VII-B: `V = w1/2 ρ² + w2 (1 − cos α)`, with
/// `ρ = ‖x_d[0:2] − x[0:2]‖` and `α = θ − atan2(y_d − y, x_d − x)`
/// (`α = θ − θ_d` when `ρ < 10⁻⁶`, where the bearing is undefined).
#[derive(Debug, Clone, PartialEq)]
pub struct AckermannClf {
    /// Weight of the distance term.
    pub w1: f64,
    /// Weight of the heading term.
    pub w2: f64,
    /// Decay rate `γ_V`.
    pub gamma: f64,
}

impl AckermannClf {
    /// Validated constructor.
    pub fn new(w1: f64, w2: f64, gamma: f64) -> Result<Self, InputError> {
        for (name, v) in [("w1", w1), ("w2", w2), ("gamma", gamma)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(InputError::invalid(name, v, "must be finite and ≥ 0"));
            }
        }
        Ok(Self { w1, w2, gamma })
    }
}

impl Lyapunov for AckermannClf {
    fn state_dim(&self) -> usize {
        3
    }
    fn v<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D], xd: &[D]) -> D {
        let dx = xd[0] - x[0];
        let dy = xd[1] - x[1];
        let rho2 = dx * dx + dy * dy;
        // On top of the reference point the bearing atan2(dy, dx) is
        // undefined (its derivative is 0/0); the reference heading x_d[2]
        // takes its place there.
        let bearing = if rho2.re() < 1e-12 {
            xd[2]
        } else {
            super::atan2(dy, dx)
        };
        let alpha = x[2] - bearing;
        rho2 * (0.5 * self.w1) + (D::from(1.0) - alpha.cos()) * self.w2
    }
    fn gamma(&self) -> f64 {
        self.gamma
    }
}
