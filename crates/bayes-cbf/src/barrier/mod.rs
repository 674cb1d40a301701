//! Control barrier functions `h(x)` and control Lyapunov functions `V(x)`,
//! and the moments of their conditions under the GP posterior
//! (paper, Sec. V–VI).
//!
//! Users write `h` (or `V`) once, generic over dual numbers; gradients and
//! Hessians come from forward-mode automatic differentiation (num-dual):
//! `n` passes of [`Dual64`] for `∇h`, `n(n+1)/2` passes of [`HyperDual64`]
//! for `∇²h`.

/// The [`Barrier`] methods (of the built-in and expression barriers) that return the stored relative degree and gains.
macro_rules! order_and_gains {
    () => {
        fn relative_degree(&self) -> usize {
            self.relative_degree
        }
        fn gains(&self) -> &[f64] {
            &self.gains
        }
    };
}

mod builtins;
mod callback;
mod clf;
mod condition;
mod expression;
mod moments;
mod monte_carlo;

pub use builtins::{
    CircleHeading, Disc, HalfSpace, PendulumSector, PendulumSectorEdge, SectorEdge,
};
pub use callback::{ArrayFn, CallbackBarrier, ValueFn};
pub use clf::{AckermannClf, DynLyapunov, Lyapunov};
pub use condition::{fastest_pole, realised_condition, start_margin, true_condition};
pub use expression::{ExpressionBarrier, ExpressionClf};
pub use moments::{
    add_observation_noise, cbc_moments, clc_moments, factor_probability, quantile_factor,
    unmodelled_lgh_std, ConditionMoments, MomentWorkspace,
};
pub use monte_carlo::{mc_cbc_moments, McMoments, McSettings};

use crate::error::InputError;
use num_dual::{Dual64, DualNum, HyperDual64};

/// A control barrier function: the safe set is `{x : h(x) ≥ 0}`.
///
/// ## Reference
/// Paper, Def. 2 (relative degree 1, `CBC = ∇hᵀ F u̲ + α h`) and Def. 4
/// (relative degree `r`, `CBC⁽ʳ⁾ = ∇(L_f^{r−1}h)ᵀ F u̲ + k_αᵀ η(x)`).
pub trait Barrier: Send + Sync {
    /// State dimension the barrier expects.
    fn state_dim(&self) -> usize;
    /// `h(x)`.
    fn h<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D]) -> D;
    /// Declared relative degree `r` (1 or 2 have exact moments).
    fn relative_degree(&self) -> usize;
    /// Class-K gains: `[α]` for `r = 1`; `[k_α0, …, k_α(r−1)]` for `r ≥ 2`,
    /// multiplying `[h, L_f h, …, L_f^{r−1} h]`.
    fn gains(&self) -> &[f64];
    /// Short name for reports.
    fn name(&self) -> &str {
        "barrier"
    }
    /// The first failed evaluation on this thread since its last call, for
    /// barriers whose evaluation can fail ([`ExpressionBarrier`]); `None`
    /// for barriers written in Rust.
    fn take_error(&self) -> Option<String> {
        None
    }
}

/// Object-safe view of a [`Barrier`], implemented for all of them.
pub trait DynBarrier: Send + Sync {
    /// State dimension.
    fn state_dim(&self) -> usize;
    /// `h(x)`.
    fn value(&self, x: &[f64]) -> f64;
    /// `h` on dual numbers.
    fn value_dual(&self, x: &[Dual64]) -> Dual64;
    /// `h` on hyper-dual numbers.
    fn value_hyper(&self, x: &[HyperDual64]) -> HyperDual64;
    /// Relative degree.
    fn relative_degree(&self) -> usize;
    /// Class-K gains.
    fn gains(&self) -> &[f64];
    /// Name.
    fn name(&self) -> &str;

    /// `∇h(x)` into `grad` (length n); returns `h(x)`. `scratch` length `n`.
    ///
    /// # Panics
    /// If `grad` or `scratch` is shorter than `x` (a caller's buffer, not
    /// user input: [`crate::control::SafetyFilter`] sizes its own).
    fn gradient(&self, x: &[f64], grad: &mut [f64], scratch: &mut [Dual64]) -> f64 {
        let n = x.len();
        check_buffers(n, grad.len(), n, scratch.len());
        let mut h = 0.0;
        for j in 0..n {
            crate::autodiff::seed_dual(x, j, &mut scratch[..n]);
            let v = self.value_dual(&scratch[..n]);
            grad[j] = v.eps;
            h = v.re;
        }
        if n == 0 {
            h = self.value(x);
        }
        h
    }

    /// `∇²h(x)` into `hess` (row-major `n × n`) and `∇h` into `grad`;
    /// returns `h(x)`. `scratch` length `n`.
    ///
    /// # Panics
    /// If `grad` or `scratch` is shorter than `x`, or `hess` shorter than
    /// `n²`.
    fn hessian(
        &self,
        x: &[f64],
        grad: &mut [f64],
        hess: &mut [f64],
        scratch: &mut [HyperDual64],
    ) -> f64 {
        let n = x.len();
        check_buffers(n, grad.len(), n, scratch.len());
        check_hessian_buffer(n, hess.len());
        let mut h = self.value(x);
        for a in 0..n {
            for b in a..n {
                crate::autodiff::seed_hyper(x, a, b, &mut scratch[..n]);
                let v = self.value_hyper(&scratch[..n]);
                hess[a * n + b] = v.eps1eps2;
                hess[b * n + a] = v.eps1eps2;
                if a == b {
                    grad[a] = v.eps1;
                }
                h = v.re;
            }
        }
        h
    }

    /// The first failure of an evaluation on this thread since its last
    /// call, for barriers whose evaluation can fail (callbacks:
    /// [`CallbackBarrier`]); `None` for barriers written in Rust.
    fn take_error(&self) -> Option<String> {
        None
    }
}

/// The buffer-length contract of [`DynBarrier::gradient`] and
/// [`DynBarrier::hessian`] (and the CLF's gradient), as a clear panic.
pub(crate) fn check_buffers(n: usize, grad: usize, scratch_needed: usize, scratch: usize) {
    assert!(
        grad >= n,
        "grad has {grad} entries, the gradient of {n} states needs {n}"
    );
    assert!(
        scratch >= scratch_needed,
        "scratch has {scratch} entries, {scratch_needed} are needed for {n} states"
    );
}

/// `hess` holds the `n × n` Hessian, as a clear panic.
pub(crate) fn check_hessian_buffer(n: usize, hess: usize) {
    assert!(
        hess >= n * n,
        "hess has {hess} entries, the Hessian of {n} states needs {}",
        n * n
    );
}

impl<T: Barrier> DynBarrier for T {
    fn state_dim(&self) -> usize {
        Barrier::state_dim(self)
    }
    fn value(&self, x: &[f64]) -> f64 {
        self.h(x)
    }
    fn value_dual(&self, x: &[Dual64]) -> Dual64 {
        self.h(x)
    }
    fn value_hyper(&self, x: &[HyperDual64]) -> HyperDual64 {
        self.h(x)
    }
    fn relative_degree(&self) -> usize {
        Barrier::relative_degree(self)
    }
    fn gains(&self) -> &[f64] {
        Barrier::gains(self)
    }
    fn name(&self) -> &str {
        Barrier::name(self)
    }
    fn take_error(&self) -> Option<String> {
        Barrier::take_error(self)
    }
}

/// `atan2(y, x)` on dual numbers with derivatives that stay finite when
/// `x = 0` (num-dual differentiates `atan(y/x)`, which divides by zero on
/// the y axis): `atan(y/x)` for `x > 0`, `±π/2 − atan(x/y)` for `y ≠ 0`,
/// `atan(y/x) ± π` on the negative x axis. The derivative
/// `(x dy − y dx)/(x² + y²)` is undefined only at the origin.
pub fn atan2<D: DualNum<Primitive = f64> + Copy>(y: D, x: D) -> D {
    use std::f64::consts::{FRAC_PI_2, PI};
    let (yr, xr) = (y.re(), x.re());
    if xr > 0.0 {
        (y / x).atan()
    } else if yr > 0.0 {
        D::from(FRAC_PI_2) - (x / y).atan()
    } else if yr < 0.0 {
        D::from(-FRAC_PI_2) - (x / y).atan()
    } else if xr < 0.0 {
        // on the negative x axis: the branch cut of atan2 (±π)
        let base = (y / x).atan();
        if yr.is_sign_negative() {
            base - PI
        } else {
            base + PI
        }
    } else {
        y.atan2(x)
    }
}

/// Checks a relative degree and its gains: `r ≥ 1`, `r` gains for `r ≥ 2`
/// (one for `r = 1`), all finite and `≥ 0`; for `r ≥ 2`, the gains must
/// make `sʳ + k_α(r−1) sʳ⁻¹ + … + k_α1 s + k_α0` Hurwitz (every root in the
/// open left half-plane), else `h^(r) = −Σ k_αi h^(i)`, the boundary of the
/// condition, does not bring `h` back and `CBC⁽ʳ⁾ ≥ 0` does not keep
/// `h ≥ 0` (paper, Def. 4; exponential CBFs). `k_α0 = 0` is the first
/// failure: `s = 0` is a root.
///
/// The roots must also be real (poles `−p_i`, `p_i > 0`: Nguyen & Sreenath,
/// Thm. 2, which Def. 4 rests on). With complex roots the boundary of the
/// condition is a damped oscillation about `h = 0`: where the condition
/// binds, `h` crosses zero although every step meets it (`k_α = [4, 1]`
/// from rest at `h = 1` reaches `h = −0.44`).
pub fn validate_gains(r: usize, gains: &[f64]) -> Result<(), InputError> {
    if r == 0 {
        return Err(InputError::invalid("relative_degree", 0.0, "must be ≥ 1"));
    }
    if r > MAX_RELATIVE_DEGREE {
        return Err(InputError::invalid_shown(
            "relative_degree",
            r,
            &format!(
                "must be at most {MAX_RELATIVE_DEGREE} (the gains' real poles are told from \
                 complex ones only that far in floating point)"
            ),
        ));
    }
    let want = r.max(1);
    if gains.len() != want {
        let field = if r == 1 { "alpha" } else { "k_alpha" };
        return Err(InputError::shape(field, want, gains.len()));
    }
    for (i, g) in gains.iter().enumerate() {
        let field = || {
            if r == 1 {
                "alpha".to_string()
            } else {
                format!("k_alpha[{i}]")
            }
        };
        if !(g.is_finite() && *g >= 0.0) {
            return Err(InputError::invalid(&field(), *g, "must be finite and ≥ 0"));
        }
        if !(g * g).is_finite() {
            return Err(InputError::invalid(
                &field(),
                *g,
                "must be below about 1.3e154: the condition's variance carries its square, which overflows",
            ));
        }
    }
    if r >= 2 && !is_hurwitz(gains) {
        return Err(InputError::Invalid {
            field: "k_alpha".into(),
            value: format!("{gains:?}"),
            reason: format!(
                "the polynomial s^{r} + Σ k_alpha[i] s^i is not Hurwitz, so CBC ≥ 0 does not keep h ≥ 0 (every k_alpha[i] must be > 0{})",
                if r >= 3 { ", and the Routh–Hurwitz conditions hold" } else { "" }
            ),
        });
    }
    if r >= 2 && !has_real_roots(gains) {
        let example = match r {
            2 => "with poles −p₁, −p₂ (p_i > 0) k_alpha = [p₁p₂, p₁ + p₂], e.g. [1, 2], [2, 3] or [16, 8]",
            3 => "with poles −p₁, −p₂, −p₃ (p_i > 0) k_alpha = [p₁p₂p₃, p₁p₂ + p₁p₃ + p₂p₃, p₁ + p₂ + p₃], e.g. [1, 3, 3]",
            _ => "the coefficients of Π (s + p_i) with every p_i > 0",
        };
        return Err(InputError::Invalid {
            field: "k_alpha".into(),
            value: format!("{gains:?}"),
            reason: format!(
                "the roots of s^{r} + Σ k_alpha[i] s^i are not all real: where the condition binds, h follows a damped oscillation about 0 and crosses it, so CBC ≥ 0 does not keep h ≥ 0; choose real poles: {example}"
            ),
        });
    }
    Ok(())
}

/// Checks a barrier's state dimension `n` given as `field`: `1 ≤ n ≤`
/// [`MAX_DIMENSION`](crate::gp::MAX_DIMENSION), the models' bound (its
/// Hessian holds `n²` entries).
pub(crate) fn check_state_dim(field: &str, n: usize) -> Result<(), InputError> {
    if n == 0 {
        return Err(InputError::invalid(
            field,
            0.0,
            "at least one state is needed",
        ));
    }
    if n > crate::gp::MAX_DIMENSION {
        return Err(InputError::invalid_shown(
            field,
            format!("{n} states"),
            &format!(
                "too large: a barrier's state dimension is at most {} (the models' bound)",
                crate::gp::MAX_DIMENSION
            ),
        ));
    }
    Ok(())
}

/// The largest relative degree a barrier may declare: up to it,
/// [`has_real_roots`] tells a multiple real root from a complex pair whose
/// overshoot matters.
pub const MAX_RELATIVE_DEGREE: usize = 10;

/// Whether every root of `sʳ + k[r−1] sʳ⁻¹ + … + k[0]` (monic, `r =
/// k.len()`) is real, a multiple root included: for `r ≤ 3` by the
/// discriminant (`≥ 0` to a relative `1e-9` of its terms); above, from the
/// eigenvalues of the companion matrix of the polynomial scaled to roots of
/// unit geometric mean (`s = k[0]^(1/r) t`), whose imaginary parts must be
/// within `max(1 %, 4 (rε)^(1/r))` of their modulus: the eigenvalues of an
/// `r`-fold root spread by about `(rε)^(1/r)` (3.4 % at `r = 10`). A pair
/// that near the real axis (within 1 %: damping ratio above 0.99995;
/// within 14 % at `r = 10`: above 0.99) overshoots by
/// `e^(−πζ/√(1−ζ²))`, below `e^(−300)` and `e^(−22)`.
pub fn has_real_roots(k: &[f64]) -> bool {
    match *k {
        [] | [_] => true,
        // s² + b s + c
        [c, b] => b * b >= 4.0 * c * (1.0 - 1e-9),
        // s³ + a s² + b s + c: discriminant ≥ 0
        [c, b, a] => {
            let terms = [
                18.0 * a * b * c,
                -4.0 * a.powi(3) * c,
                a * a * b * b,
                -4.0 * b.powi(3),
                -27.0 * c * c,
            ];
            let disc: f64 = terms.iter().sum();
            let scale: f64 = terms.iter().map(|t| t.abs()).sum();
            disc >= -1e-9 * scale
        }
        _ => {
            let r = k.len();
            // roots scaled by 1/ρ: coefficient k[i] by ρ^(i − r)
            let rho = match k[0].abs().powf(1.0 / r as f64) {
                v if v.is_normal() => v,
                _ => 1.0,
            };
            let companion = nalgebra::DMatrix::from_fn(r, r, |i, j| {
                if i == 0 {
                    -k[r - 1 - j] / rho.powi(j as i32 + 1)
                } else if j + 1 == i {
                    1.0
                } else {
                    0.0
                }
            });
            let tol = (4.0 * (r as f64 * f64::EPSILON).powf(1.0 / r as f64)).max(1e-2);
            companion
                .complex_eigenvalues()
                .iter()
                .all(|z| z.im.abs() <= tol * z.norm())
        }
    }
}

/// Whether `sʳ + k[r−1] sʳ⁻¹ + … + k[0]` (monic, `r = k.len()`) has every
/// root in the open left half-plane: the first column of its Routh array
/// is positive.
pub fn is_hurwitz(k: &[f64]) -> bool {
    let r = k.len();
    let pos = |v: f64| v.is_finite() && v > 0.0;
    // closed forms for the common degrees, without allocation (the control
    // loop checks the gains at every step)
    match *k {
        [k0] => return pos(k0),
        [k0, k1] => return pos(k0) && pos(k1),
        [k0, k1, k2] => return pos(k0) && pos(k1) && pos(k2) && k2 * k1 > k0,
        _ => {}
    }
    // coefficients from the highest power: 1, k[r−1], …, k[0]
    let c: Vec<f64> = std::iter::once(1.0)
        .chain(k.iter().rev().copied())
        .collect();
    if c.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
        return false;
    }
    let width = r / 2 + 1;
    let row = |start: usize| -> Vec<f64> {
        (0..width)
            .map(|j| c.get(start + 2 * j).copied().unwrap_or(0.0))
            .collect()
    };
    let (mut a, mut b) = (row(0), row(1));
    for _ in 0..r {
        if b[0].is_nan() || b[0] <= 0.0 {
            return false;
        }
        let next: Vec<f64> = (0..width)
            .map(|j| {
                let a1 = a.get(j + 1).copied().unwrap_or(0.0);
                let b1 = b.get(j + 1).copied().unwrap_or(0.0);
                (b[0] * a1 - a[0] * b1) / b[0]
            })
            .collect();
        // a zero row before row r (roots symmetric about the origin) fails
        // the check of the next round
        a = std::mem::replace(&mut b, next);
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    #[should_panic(expected = "scratch has 1 entries, 3 are needed for 3 states")]
    fn a_short_scratch_buffer_is_named() {
        let disc = Disc::new(3, [0, 1], [0.0, 0.0], 1.0, 1, vec![1.0]).unwrap();
        let mut grad = [0.0; 3];
        let mut scratch = [Dual64::from(0.0); 1];
        disc.gradient(&[0.5, 0.5, 0.0], &mut grad, &mut scratch);
    }

    #[test]
    #[should_panic(expected = "hess has 4 entries, the Hessian of 3 states needs 9")]
    fn a_short_hessian_buffer_is_named() {
        let disc = Disc::new(3, [0, 1], [0.0, 0.0], 1.0, 1, vec![1.0]).unwrap();
        let (mut grad, mut hess) = ([0.0; 3], [0.0; 4]);
        let mut scratch = [HyperDual64::from(0.0); 3];
        disc.hessian(&[0.5, 0.5, 0.0], &mut grad, &mut hess, &mut scratch);
    }

    #[test]
    fn hurwitz_test_matches_the_roots() {
        // (s + 1)(s + 2) = s² + 3s + 2; (s + 1)³ = s³ + 3s² + 3s + 1
        assert!(is_hurwitz(&[2.0, 3.0]));
        assert!(is_hurwitz(&[1.0, 3.0, 3.0]));
        // s² + 0 s + 1: roots ±i; s²: double root 0; s² − s + 1 is excluded by sign
        assert!(!is_hurwitz(&[1.0, 0.0]));
        assert!(!is_hurwitz(&[0.0, 3.0]));
        // s³ + s² + s + 2: Routh 1·1 < 2, two roots in the right half-plane
        assert!(!is_hurwitz(&[2.0, 1.0, 1.0]));
        // s³ + 2s² + 2s + 2: 2·2 > 2, Hurwitz (roots −1.54, −0.23 ± 1.12i)
        assert!(is_hurwitz(&[2.0, 2.0, 2.0]));
        // (s + 1)⁴ = s⁴ + 4s³ + 6s² + 4s + 1, and (s² + 1)(s + 1)² loses it
        assert!(is_hurwitz(&[1.0, 4.0, 6.0, 4.0]));
        assert!(!is_hurwitz(&[1.0, 2.0, 2.0, 2.0]));
        assert!(is_hurwitz(&[5.0]));
        // against the roots of random cubics by brute force
        let mut seed = 7u64;
        let mut next = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64 * 4.0
        };
        for _ in 0..2000 {
            let k = [next(), next(), next()];
            let m = nalgebra::Matrix3::new(-k[2], -k[1], -k[0], 1.0, 0.0, 0.0, 0.0, 1.0, 0.0);
            let stable = m.complex_eigenvalues().iter().all(|z| z.re < -1e-9);
            let marginal = m.complex_eigenvalues().iter().any(|z| z.re.abs() <= 1e-9);
            if !marginal {
                assert_eq!(is_hurwitz(&k), stable, "{k:?}");
            }
        }
        assert!(validate_gains(2, &[0.0, 3.0])
            .unwrap_err()
            .to_string()
            .contains("Hurwitz"));
        assert!(validate_gains(2, &[1.0, 3.0]).is_ok());
        assert!(validate_gains(1, &[0.0]).is_ok());
    }

    /// Gains with complex roots are refused, multiple real roots are not;
    /// against the roots of random polynomials of degree 2 to 5 (from
    /// their real poles, and perturbed).
    #[test]
    fn gains_must_have_real_roots() {
        // s² + s + 4: −0.5 ± 1.94i; s² + 2s + 1 = (s + 1)²; s² + 8s + 16
        assert!(!has_real_roots(&[4.0, 1.0]));
        assert!(has_real_roots(&[1.0, 2.0]));
        assert!(has_real_roots(&[16.0, 8.0]));
        // (s + 1)³, (s + 1)(s² + s + 1), (s + 1)⁴, (s + 1)²(s² + 2s + 2)
        assert!(has_real_roots(&[1.0, 3.0, 3.0]));
        assert!(!has_real_roots(&[1.0, 2.0, 2.0]));
        assert!(has_real_roots(&[1.0, 4.0, 6.0, 4.0]));
        assert!(!has_real_roots(&[2.0, 6.0, 7.0, 4.0]));
        let e = validate_gains(2, &[4.0, 1.0]).unwrap_err().to_string();
        assert!(e.contains("k_alpha") && e.contains("not all real"), "{e}");
        assert!(validate_gains(3, &[1.0, 2.0, 2.0]).is_err());
        assert!(validate_gains(3, &[6.0, 11.0, 6.0]).is_ok());
        // random real poles, and the same polynomials with a complex pair
        let mut seed = 11u64;
        let mut next = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            0.1 + (seed >> 11) as f64 / (1u64 << 53) as f64 * 5.0
        };
        // coefficients k[0..r] of Π (s + p_i) · (s² + 2as + a² + b²)^pair
        let monic = |roots: &[f64], pair: Option<(f64, f64)>| -> Vec<f64> {
            let mut c = vec![1.0]; // highest power first
            let mut mul = |f: &[f64]| {
                let mut out = vec![0.0; c.len() + f.len() - 1];
                for (i, a) in c.iter().enumerate() {
                    for (j, b) in f.iter().enumerate() {
                        out[i + j] += a * b;
                    }
                }
                c = out;
            };
            for p in roots {
                mul(&[1.0, *p]);
            }
            if let Some((a, b)) = pair {
                mul(&[1.0, 2.0 * a, a * a + b * b]);
            }
            c.iter().skip(1).rev().copied().collect()
        };
        for r in 2..=5 {
            for _ in 0..300 {
                let roots: Vec<f64> = (0..r).map(|_| next()).collect();
                assert!(has_real_roots(&monic(&roots, None)), "{roots:?}");
                let (a, b) = (next(), 0.2 + next());
                let k = monic(&roots[..r - 2], Some((a, b)));
                assert!(!has_real_roots(&k), "{roots:?} ± {b}i: {k:?}");
            }
        }
        // r-fold roots up to the largest relative degree, at every scale;
        // a pair of damping ratio 0.9 beside r − 2 of them is refused
        for r in 2..=MAX_RELATIVE_DEGREE {
            for p in [0.05, 1.0, 20.0] {
                let k = monic(&vec![p; r], None);
                assert!(has_real_roots(&k), "(s + {p})^{r}: {k:?}");
                assert!(validate_gains(r, &k).is_ok(), "(s + {p})^{r}");
                let k = monic(&vec![p; r - 2], Some((0.9 * p, 0.436 * p)));
                assert!(
                    !has_real_roots(&k),
                    "(s + {p})^{} with a pair: {k:?}",
                    r - 2
                );
            }
        }
        let e = validate_gains(11, &[1.0; 11]).unwrap_err().to_string();
        assert!(
            e.contains("relative_degree") && e.contains("at most 10"),
            "{e}"
        );
    }

    /// Gains whose square overflows name the gain (a run with
    /// `k_alpha = [1e200, 1e200]` failed later, on non-finite moments).
    #[test]
    fn gains_whose_square_overflows_are_named() {
        let e = validate_gains(2, &[1e200, 1e200]).unwrap_err().to_string();
        assert!(e.contains("k_alpha[0]") && e.contains("1.3e154"), "{e}");
        let e = validate_gains(1, &[2e154]).unwrap_err().to_string();
        assert!(e.contains("alpha") && e.contains("overflows"), "{e}");
        assert!(validate_gains(2, &[1e150, 3e75]).is_ok());
    }

    #[test]
    fn atan2_values_and_derivatives_everywhere_but_the_origin() {
        for &(y, x) in &[
            (0.3, 0.0),
            (-0.3, 0.0),
            (0.0, 0.7),
            (0.0, -0.7),
            (-0.0, -0.7),
            (0.4, -0.2),
            (-0.4, -0.2),
            (1.0, 2.0),
        ] {
            let v: f64 = atan2(y, x);
            assert!((v - f64::atan2(y, x)).abs() < 1e-15, "({y}, {x}): {v}");
            let dy = atan2(Dual64::new(y, 1.0), Dual64::from(x)).eps;
            let dx = atan2(Dual64::from(y), Dual64::new(x, 1.0)).eps;
            let r2 = x * x + y * y;
            assert!(
                (dy - x / r2).abs() < 1e-12 && (dx + y / r2).abs() < 1e-12,
                "({y}, {x}): {dy} {dx}"
            );
        }
    }
}
