//! The barrier condition with known dynamics: what the stochastic
//! condition of Secs. V–VI estimates under the GP posterior.

use super::DynBarrier;
use crate::error::{check_finite, InputError};
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
    check_point(barrier, n, x, ("u", u, m))?;
    let mut fbuf = vec![0.0; n * (1 + m)];
    let mut xdot = vec![0.0; n];
    system.xdot(x, u, &mut fbuf, &mut xdot);
    along(system, barrier, x, &fbuf[..n], &xdot)
}

/// The barrier condition of `barrier` at `x` as realised over a step in
/// which the state moved at the observed rate `xdot` (e.g. `(x_{k+1} −
/// x_k)/τ`): the condition of [`true_condition`] with `F(x)u̲` replaced by
/// `xdot`, the drift `f` of `system` where the condition needs it:
///
/// - relative degree 1: `∇h(x)ᵀ ẋ + α h(x)`;
/// - relative degree 2: `∇(L_f h)(x)ᵀ ẋ + k₀ h(x) + k₁ L_f h(x)`.
///
/// What the predictive condition
/// ([`SafetySettings::predictive`](crate::control::SafetySettings::predictive))
/// promises: the true dynamics and the disturbance of the step both act on
/// it.
pub fn realised_condition(
    system: &dyn DynSystem,
    barrier: &dyn DynBarrier,
    x: &[f64],
    xdot: &[f64],
) -> Result<f64, InputError> {
    let (n, m) = (system.state_dim(), system.control_dim());
    check_point(barrier, n, x, ("xdot", xdot, n))?;
    check_finite("x", x)?;
    check_finite("xdot", xdot)?;
    let mut fbuf = vec![0.0; n * (1 + m)];
    let mut f = vec![0.0; n];
    system.xdot(x, &vec![0.0; m], &mut fbuf, &mut f);
    along(system, barrier, x, &f, xdot)
}

/// Checks that `x` and the barrier have the state dimension `n`, and that
/// `v` (named `field`) has `len` entries.
fn check_point(
    barrier: &dyn DynBarrier,
    n: usize,
    x: &[f64],
    (field, v, len): (&str, &[f64], usize),
) -> Result<(), InputError> {
    if x.len() != n || barrier.state_dim() != n {
        return Err(InputError::shape("x", n, x.len()));
    }
    if v.len() != len {
        return Err(InputError::shape(field, len, v.len()));
    }
    Ok(())
}

/// The fastest pole `λ` of a barrier's condition: `α` at relative degree
/// 1; at 2 the larger root magnitude of `s² + k₁ s + k₀` (gains `[k₀, k₁]`),
/// with a double root's discriminant rounded below zero taken as zero, as
/// [`has_real_roots`](super::has_real_roots) takes it; `None` above, or for
/// complex roots.
pub fn fastest_pole(barrier: &dyn DynBarrier) -> Option<f64> {
    match (barrier.relative_degree(), barrier.gains()) {
        (1, &[alpha]) => Some(alpha),
        (2, &[k0, k1]) => super::has_real_roots(&[k0, k1])
            .then(|| 0.5 * (k1 + (k1 * k1 - 4.0 * k0).max(0.0).sqrt())),
        _ => None,
    }
}

/// `ψ₁(x) = L_f h(x) + λ h(x)` of a relative-degree-2 barrier at a start
/// `x` of `system`, `λ` the larger root of `s² + k₁ s + k₀` (gains
/// `[k₀, k₁]`, [`fastest_pole`]); `None` for another relative degree (or
/// complex roots, which [`validate_gains`](super::validate_gains) refuses).
///
/// For real roots `−λ₁`, `−λ₂` the condition `ḧ + k₁ ḣ + k₀ h ≥ 0` is
/// `ψ̇₁ + λ₂ ψ₁ ≥ 0` with `ψ₁ = ḣ + λ₁ h`, so `ψ₁(t) ≥ ψ₁(0) e^{−λ₂ t}`, and
/// `ψ₁ ≥ 0` gives `h(t) ≥ h(0) e^{−λ₁ t}`: a start with `h ≥ 0` and
/// `ψ₁ ≥ 0` (for either root; the larger one asks less) stays safe while
/// the condition holds. A start with `ψ₁ < 0` lies outside the set the
/// gains keep invariant: `h` can cross zero although every step meets its
/// condition (a fast approach with small gains). `ḣ = L_f h` because
/// `L_g h = 0` at relative degree 2.
pub fn start_margin(
    system: &dyn DynSystem,
    barrier: &dyn DynBarrier,
    x: &[f64],
) -> Result<Option<f64>, InputError> {
    let (n, m) = (system.state_dim(), system.control_dim());
    check_point(barrier, n, x, ("x", x, n))?;
    check_finite("x", x)?;
    let lambda = match fastest_pole(barrier) {
        Some(l) if barrier.relative_degree() == 2 => l,
        _ => return Ok(None),
    };
    let mut fbuf = vec![0.0; n * (1 + m)];
    let mut f = vec![0.0; n];
    system.xdot(x, &vec![0.0; m], &mut fbuf, &mut f);
    let mut grad = vec![0.0; n];
    let h = barrier.gradient(x, &mut grad, &mut vec![Dual64::from(0.0); n]);
    Ok(Some(dot(&grad, &f) + lambda * h))
}

/// The condition along the rate `xdot`, with drift `f` (relative degree 2).
fn along(
    system: &dyn DynSystem,
    barrier: &dyn DynBarrier,
    x: &[f64],
    f: &[f64],
    xdot: &[f64],
) -> Result<f64, InputError> {
    let n = x.len();
    let rows = n * (1 + system.control_dim());
    let gains = barrier.gains();
    let mut grad = vec![0.0; n];
    match barrier.relative_degree() {
        1 => {
            let h = barrier.gradient(x, &mut grad, &mut vec![Dual64::from(0.0); n]);
            Ok(dot(&grad, xdot) + gains[0] * h)
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
        r => Err(InputError::invalid_shown(
            "relative_degree",
            r,
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
    use crate::barrier::{CircleHeading, HalfSpace, PendulumSector};
    use crate::systems::{Ackermann, ExpressionSystem, Pendulum};

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

    /// Along the true rate `F(x)u̲` the realised condition is the true
    /// one; it is linear in the rate, and bad rates are errors naming them.
    #[test]
    fn realised_condition_along_the_true_rate_is_the_true_condition() {
        let pend = Pendulum::default();
        let car = Ackermann { wheelbase: 2.0 };
        let sector = PendulumSector::new(0.8, 0.3, 2, vec![1.0, 3.0]).unwrap();
        let disc = CircleHeading::new([-1.0, 0.5], 0.6, 0.7, 0.3, 1, vec![5.0]).unwrap();
        type Case<'a> = (&'a dyn DynSystem, &'a dyn DynBarrier, Vec<f64>, Vec<f64>);
        let cases: [Case; 2] = [
            (&pend, &sector, vec![1.2, -0.4], vec![0.7]),
            (&car, &disc, vec![0.3, -0.2, 0.4], vec![0.8, -0.3]),
        ];
        for (sys, b, x, u) in cases {
            let n = x.len();
            let (mut fb, mut xd) = (vec![0.0; n * (1 + u.len())], vec![0.0; n]);
            sys.xdot(&x, &u, &mut fb, &mut xd);
            let want = true_condition(sys, b, &x, &u).unwrap();
            let got = realised_condition(sys, b, &x, &xd).unwrap();
            assert!(
                (got - want).abs() < 1e-12 * (1.0 + want.abs()),
                "{got} {want}"
            );
            // affine in the rate: a disturbance d adds its directional part
            let d: Vec<f64> = (0..n).map(|i| 0.1 * (i as f64 + 1.0)).collect();
            let plus: Vec<f64> = xd.iter().zip(&d).map(|(a, b)| a + b).collect();
            let minus: Vec<f64> = xd.iter().zip(&d).map(|(a, b)| a - b).collect();
            let (p, m) = (
                realised_condition(sys, b, &x, &plus).unwrap(),
                realised_condition(sys, b, &x, &minus).unwrap(),
            );
            assert!(((p + m) / 2.0 - want).abs() < 1e-12 * (1.0 + want.abs()));
            assert!((p - m).abs() > 1e-6, "the disturbance must act");
            let short = realised_condition(sys, b, &x, &xd[..n - 1]).unwrap_err();
            assert_eq!(short, InputError::shape("xdot", n, n - 1));
            let mut bad = xd.clone();
            bad[0] = f64::NAN;
            let e = realised_condition(sys, b, &x, &bad).unwrap_err();
            assert!(e.to_string().contains("xdot[0]"), "{e}");
        }
    }

    /// A cart with friction, `ṗ = v`, `v̇ = −c v + u`, and the wall
    /// `h = 1 − p`: under the least the condition allows,
    /// `ḧ + k₁ḣ + k₀h = 0`, the barrier crosses zero exactly from the
    /// starts with `ψ₁ < 0` (integrated by RK4 from `h₀ = 1 − p`,
    /// `ḣ₀ = −v`).
    #[test]
    fn start_margin_decides_whether_the_least_allowed_motion_crosses() {
        let c = 0.4;
        let cart = ExpressionSystem::new(
            &["p", "v"],
            &["u"],
            &[("c", c)],
            &["v", "-c*v"],
            &[vec!["0"], vec!["1"]],
            &[],
        )
        .unwrap();
        for gains in [[2.0, 3.0], [4.0, 4.0], [0.5, 5.0]] {
            let wall = HalfSpace::new(vec![-1.0, 0.0], -1.0, 2, gains.to_vec()).unwrap();
            let (mut crossed, mut kept) = (0, 0);
            for p in [-1.0, 0.0, 0.5, 0.9] {
                for v in [-1.0, 0.0, 0.5, 1.0, 2.0, 4.0, 8.0] {
                    let psi = start_margin(&cart, &wall, &[p, v]).unwrap().unwrap();
                    // the least-allowed motion of h, by RK4
                    let rate = |s: [f64; 2]| [s[1], -gains[1] * s[1] - gains[0] * s[0]];
                    let (mut s, dt) = ([1.0 - p, -v], 1e-3);
                    let mut lowest = s[0];
                    for _ in 0..60_000 {
                        let k1 = rate(s);
                        let k2 = rate([s[0] + 0.5 * dt * k1[0], s[1] + 0.5 * dt * k1[1]]);
                        let k3 = rate([s[0] + 0.5 * dt * k2[0], s[1] + 0.5 * dt * k2[1]]);
                        let k4 = rate([s[0] + dt * k3[0], s[1] + dt * k3[1]]);
                        for i in 0..2 {
                            s[i] += dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
                        }
                        lowest = lowest.min(s[0]);
                    }
                    if psi.abs() < 1e-6 {
                        continue;
                    }
                    assert_eq!(
                        lowest < 0.0,
                        psi < 0.0,
                        "gains {gains:?}, start ({p}, {v}): ψ₁ {psi}, lowest h {lowest}"
                    );
                    if psi < 0.0 {
                        crossed += 1
                    } else {
                        kept += 1
                    }
                }
            }
            assert!(
                crossed >= 3 && kept >= 3,
                "{gains:?}: {crossed} crossed, {kept} kept"
            );
        }
        // gains with complex roots are refused; relative degree 1 has no
        // such margin
        assert!(HalfSpace::new(vec![-1.0, 0.0], -1.0, 2, vec![4.0, 1.0]).is_err());
        let rd1 = HalfSpace::new(vec![-1.0, 0.0], -1.0, 1, vec![1.0]).unwrap();
        assert_eq!(start_margin(&cart, &rd1, &[0.0, 1.0]).unwrap(), None);
    }
}
