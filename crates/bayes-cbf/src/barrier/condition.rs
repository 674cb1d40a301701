//! The barrier condition with known dynamics: what the stochastic
//! condition of Secs. V–VI estimates under the GP posterior.

use super::DynBarrier;
use crate::error::InputError;
use crate::systems::DynSystem;
use num_dual::{Dual64, HyperDual64};

/// The barrier condition of `barrier` at `(x, u)` under the dynamics
/// `ẋ = F(x)u̲` of `system` (no uncertainty), by automatic differentiation:
///
/// - relative degree 1: `CBC = ∇h(x)ᵀ F(x)u̲ + α h(x)`;
/// - relative degree 2: `CBC⁽²⁾ = ∇(L_f h)(x)ᵀ F(x)u̲ + k₀ h(x) + k₁ L_f h(x)`
///   with `L_f h = ∇hᵀ f` and `∇(L_f h) = ∇²h f + J_fᵀ ∇h`
///   (interfaces.md; paper, Sec. VI).
///
/// Used to check, after a run, whether the condition the controller
/// enforced in probability held for the true system. Relative degree > 2
/// is an error.
pub fn true_condition(
    system: &dyn DynSystem,
    barrier: &dyn DynBarrier,
    x: &[f64],
    u: &[f64],
) -> Result<f64, InputError> {
    let (n, m) = (system.state_dim(), system.control_dim());
    if x.len() != n || barrier.state_dim() != n {
        return Err(InputError::shape("x", n, x.len()));
    }
    if u.len() != m {
        return Err(InputError::shape("u", m, u.len()));
    }
    let rows = n * (1 + m);
    let mut fbuf = vec![0.0; rows];
    let mut xdot = vec![0.0; n];
    system.xdot(x, u, &mut fbuf, &mut xdot);
    let gains = barrier.gains();
    let mut grad = vec![0.0; n];
    match barrier.relative_degree() {
        1 => {
            let h = barrier.gradient(x, &mut grad, &mut vec![Dual64::from(0.0); n]);
            Ok(dot(&grad, &xdot) + gains[0] * h)
        }
        2 => {
            let mut hess = vec![0.0; n * n];
            let h = barrier.hessian(
                x,
                &mut grad,
                &mut hess,
                &mut vec![HyperDual64::from(0.0); n],
            );
            // J_F column-major (rows × n); f is the first n rows
            let mut jac = vec![0.0; rows * n];
            system.jacobian_into(
                x,
                &mut jac,
                &mut vec![Dual64::from(0.0); n],
                &mut vec![Dual64::from(0.0); rows],
            );
            let f = &fbuf[..n];
            let lf = dot(&grad, f);
            // ∇(L_f h)ᵀ ẋ = ẋᵀ ∇²h f + ∇hᵀ J_f ẋ
            let mut d = 0.0;
            for a in 0..n {
                for b in 0..n {
                    d += xdot[a] * hess[a * n + b] * f[b] + grad[a] * jac[a + rows * b] * xdot[b];
                }
            }
            Ok(d + gains[0] * h + gains[1] * lf)
        }
        r => Err(InputError::invalid(
            "relative_degree",
            r as f64,
            "the true condition is computed for relative degree 1 and 2",
        )),
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::barrier::{CircleHeading, PendulumSector};
    use crate::systems::{Ackermann, Pendulum};

    /// The derivative along the true flow, by central differences of `h`
    /// along a short exact trajectory: `d/dt h` (relative degree 1) and
    /// `d/dt (L_f h)` (relative degree 2) at constant control.
    fn flow_derivative(
        sys: &dyn DynSystem,
        g: &dyn Fn(&[f64]) -> f64,
        x: &[f64],
        u: &[f64],
    ) -> f64 {
        let n = x.len();
        let mut fb = vec![0.0; n * (1 + u.len())];
        let mut xd = vec![0.0; n];
        sys.xdot(x, u, &mut fb, &mut xd);
        let eps = 1e-5;
        let xp: Vec<f64> = (0..n).map(|i| x[i] + eps * xd[i]).collect();
        let xm: Vec<f64> = (0..n).map(|i| x[i] - eps * xd[i]).collect();
        (g(&xp) - g(&xm)) / (2.0 * eps)
    }

    #[test]
    fn relative_degree_one_and_two_match_finite_differences() {
        let car = Ackermann { wheelbase: 2.0 };
        let b = CircleHeading::new([-1.0, 0.5], 0.6, 0.7, 0.3, 1, vec![5.0]).unwrap();
        for (x, u) in [
            ([0.3, -0.2, 0.4], [0.8, -0.3]),
            ([-2.0, 1.0, -2.5], [-0.5, 1.2]),
        ] {
            let want = flow_derivative(&car, &|y| b.value(y), &x, &u) + 5.0 * b.value(&x);
            let got = true_condition(&car, &b, &x, &u).unwrap();
            assert!(
                (got - want).abs() < 1e-7 * (1.0 + want.abs()),
                "{got} {want}"
            );
        }
        let pend = Pendulum::default();
        let s = PendulumSector::new(0.785, 0.39, 2, vec![1.0, 3.0]).unwrap();
        let lf = |y: &[f64]| {
            let mut fb = [0.0; 4];
            pend.eval_f64(y, &mut fb);
            let mut g = [0.0; 2];
            s.gradient(y, &mut g, &mut [Dual64::from(0.0); 2]);
            g[0] * fb[0] + g[1] * fb[1]
        };
        for (x, u) in [([1.2, -0.4], [0.7]), ([-2.5, 3.0], [-4.0])] {
            let want = flow_derivative(&pend, &lf, &x, &u) + s.value(&x) + 3.0 * lf(&x);
            let got = true_condition(&pend, &s, &x, &u).unwrap();
            assert!(
                (got - want).abs() < 1e-6 * (1.0 + want.abs()),
                "{got} {want}"
            );
        }
        assert!(true_condition(&pend, &s, &[0.0], &[0.0]).is_err());
    }
}
