//! Seeding dual numbers for forward-mode derivatives of user functions
//! (systems, barriers, Lyapunov functions): `x + ε e_j` for a gradient or a
//! Jacobian column, `x + ε₁ e_a + ε₂ e_b` for a Hessian entry.

use num_dual::{Dual64, HyperDual64};

/// Writes `x + ε e_j` into `out` (`out[i] = x[i] + δ_ij ε`): one forward
/// pass then gives `∂/∂x_j` of every output.
#[track_caller]
pub fn seed_dual(x: &[f64], j: usize, out: &mut [Dual64]) {
    assert_eq!(x.len(), out.len(), "dual seed length");
    for (i, (o, &xi)) in out.iter_mut().zip(x).enumerate() {
        *o = Dual64::new(xi, if i == j { 1.0 } else { 0.0 });
    }
}

/// Writes `x + ε₁ e_a + ε₂ e_b` into `out`: one pass gives `∂_a`, `∂_b` and
/// `∂²/∂x_a∂x_b` of a scalar function.
#[track_caller]
pub fn seed_hyper(x: &[f64], a: usize, b: usize, out: &mut [HyperDual64]) {
    assert_eq!(x.len(), out.len(), "hyper-dual seed length");
    for (i, (o, &xi)) in out.iter_mut().zip(x).enumerate() {
        *o = HyperDual64::new(
            xi,
            if i == a { 1.0 } else { 0.0 },
            if i == b { 1.0 } else { 0.0 },
            0.0,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seeds_give_partial_derivatives() {
        let f = |v: &[HyperDual64]| v[0] * v[0] * v[1];
        let x = [2.0, 3.0];
        let mut h = [HyperDual64::from(0.0); 2];
        seed_hyper(&x, 0, 1, &mut h);
        let r = f(&h);
        assert_eq!((r.re, r.eps1, r.eps2, r.eps1eps2), (12.0, 12.0, 4.0, 4.0));
        let mut d = [Dual64::from(0.0); 2];
        seed_dual(&x, 1, &mut d);
        assert_eq!((d[0].eps, d[1].eps, d[1].re), (0.0, 1.0, 3.0));
    }
}
