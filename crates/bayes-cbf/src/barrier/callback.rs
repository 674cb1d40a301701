//! Barriers given by callbacks for `h`, `∇h` and (optionally) `∇²h`, such
//! as a barrier written in Python.
//!
//! The library evaluates barriers on dual numbers (module docs of
//! [`crate::barrier`]). A callback barrier is not generic over them, so its
//! dual values follow from the value, gradient and Hessian by the chain rule:
//! for `x = x₀ + ε₁a + ε₂b + ε₁ε₂c` (hyper-dual, `ε₁² = ε₂² = 0`),
//!
//! `h(x) = h(x₀) + ε₁ ∇hᵀa + ε₂ ∇hᵀb + ε₁ε₂ (aᵀ∇²h b + ∇hᵀc)`,
//!
//! and for `x = x₀ + εv` (dual), `h(x) = h(x₀) + ε ∇hᵀv`. These are the
//! first and second-order Taylor expansions, exact on (hyper-)dual numbers.
//!
//! These evaluations allocate a few vectors of length `n` and `n²`; a
//! callback (into Python, say) costs far more.
//!
//! Callbacks may fail (a Python exception) or return non-finite values.
//! [`DynBarrier`] methods are infallible, so the first failure is kept, for
//! the thread that met it, and reported to that thread by
//! [`DynBarrier::take_error`]; [`super::cbc_moments`] checks it
//! after every evaluation and returns it as an [`crate::InputError`].

use super::DynBarrier;
use crate::expr::Failure;
use num_dual::{Dual64, HyperDual64};

/// `h(x)`, or a message saying why it could not be evaluated.
pub type ValueFn = Box<dyn Fn(&[f64]) -> Result<f64, String> + Send + Sync>;
/// Writes `∇h(x)` (length `n`) or `∇²h(x)` (row-major `n × n`) into the
/// slice, or returns a message saying why it could not.
pub type ArrayFn = Box<dyn Fn(&[f64], &mut [f64]) -> Result<(), String> + Send + Sync>;

/// A barrier from callbacks for `h`, `∇h` and optionally `∇²h`.
///
/// Relative degree 2 needs `∇²h` (the condition contains
/// `∇(L_f h) = ∇²h f + J_fᵀ ∇h`); without it, an evaluation that needs it
/// fails with a message naming `hess`.
pub struct CallbackBarrier {
    n: usize,
    relative_degree: usize,
    gains: Vec<f64>,
    name: String,
    h: ValueFn,
    grad: ArrayFn,
    hess: Option<ArrayFn>,
    failure: Failure,
}

impl std::fmt::Debug for CallbackBarrier {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CallbackBarrier")
            .field("name", &self.name)
            .field("state_dim", &self.n)
            .field("relative_degree", &self.relative_degree)
            .field("gains", &self.gains)
            .field("hess", &self.hess.is_some())
            .finish()
    }
}

impl CallbackBarrier {
    /// A barrier on `state_dim` states with the given relative degree and
    /// class-K gains (`[α]` for relative degree 1, `k_α` otherwise; checked
    /// by [`super::validate_gains`]).
    pub fn new(
        name: &str,
        state_dim: usize,
        relative_degree: usize,
        gains: Vec<f64>,
        h: ValueFn,
        grad: ArrayFn,
        hess: Option<ArrayFn>,
    ) -> Result<Self, crate::InputError> {
        super::check_state_dim("state_dim", state_dim)?;
        super::validate_gains(relative_degree, &gains)?;
        if relative_degree >= 2 && hess.is_none() {
            return Err(crate::InputError::Invalid {
                field: "hess".into(),
                value: "None".into(),
                reason: format!(
                    "relative degree {relative_degree} needs the Hessian of h (the condition contains ∇²h f)"
                ),
            });
        }
        Ok(Self {
            n: state_dim,
            relative_degree,
            gains,
            name: name.to_string(),
            h,
            grad,
            hess,
            failure: Failure::default(),
        })
    }

    fn fail(&self, msg: String) {
        self.failure.record(|| msg);
    }

    /// `h(x)`, recording a failure and returning NaN.
    fn eval_h(&self, x: &[f64]) -> f64 {
        match (self.h)(x) {
            Ok(v) if v.is_finite() => v,
            Ok(v) => {
                self.fail(format!("h returned {v} at x = {}", crate::error::Brief(x)));
                f64::NAN
            }
            Err(e) => {
                self.fail(format!("h failed at x = {}: {e}", crate::error::Brief(x)));
                f64::NAN
            }
        }
    }

    /// Fills `out` by `f` (named `what`), recording a failure (NaN-filled).
    fn eval_array(&self, what: &str, f: &ArrayFn, x: &[f64], out: &mut [f64]) -> bool {
        let r = f(x, out);
        let x = crate::error::Brief(x);
        let msg = match r {
            Err(e) => Some(format!("{what} failed at x = {x}: {e}")),
            Ok(()) => out
                .iter()
                .position(|v| !v.is_finite())
                .map(|i| format!("{what} returned {} in entry {i} at x = {x}", out[i])),
        };
        match msg {
            Some(m) => {
                self.fail(m);
                out.fill(f64::NAN);
                false
            }
            None => true,
        }
    }

    /// Records a failure (and NaN-fills `hess`) when the `n × n` Hessian
    /// is not symmetric to `1e-8` of its largest entry: a Hessian of a
    /// smooth `h` is, and the moments read only one triangle of it.
    fn check_symmetric(&self, x: &[f64], hess: &mut [f64]) {
        let n = self.n;
        let scale = hess.iter().fold(0.0f64, |a, v| a.max(v.abs()));
        let bad = (0..n)
            .flat_map(|i| (0..i).map(move |j| (i, j)))
            .find(|&(i, j)| (hess[i * n + j] - hess[j * n + i]).abs() > 1e-8 * scale.max(1e-300));
        if let Some((i, j)) = bad {
            self.fail(format!(
                "hess returned a non-symmetric matrix at x = {}: entry ({i}, {j}) = {}, ({j}, {i}) = {}",
                crate::error::Brief(x),
                hess[i * n + j],
                hess[j * n + i]
            ));
            hess.fill(f64::NAN);
        }
    }

    fn eval_grad(&self, x: &[f64], out: &mut [f64]) {
        self.eval_array("grad", &self.grad, x, out);
    }

    fn eval_hess(&self, x: &[f64], out: &mut [f64]) {
        match &self.hess {
            Some(f) => {
                if self.eval_array("hess", f, x, out) {
                    self.check_symmetric(x, out);
                }
            }
            None => {
                self.fail(
                    "hess is required here (second derivatives of h), but none was given".into(),
                );
                out.fill(f64::NAN);
            }
        }
    }
}

impl DynBarrier for CallbackBarrier {
    fn state_dim(&self) -> usize {
        self.n
    }
    fn value(&self, x: &[f64]) -> f64 {
        self.eval_h(x)
    }
    fn value_dual(&self, x: &[Dual64]) -> Dual64 {
        let x0: Vec<f64> = x.iter().map(|v| v.re).collect();
        let h = self.eval_h(&x0);
        let mut g = vec![0.0; self.n];
        self.eval_grad(&x0, &mut g);
        let d: f64 = g.iter().zip(x).map(|(g, xi)| g * xi.eps).sum();
        Dual64::new(h, d)
    }
    fn value_hyper(&self, x: &[HyperDual64]) -> HyperDual64 {
        let n = self.n;
        let x0: Vec<f64> = x.iter().map(|v| v.re).collect();
        let h = self.eval_h(&x0);
        let (mut g, mut hs) = (vec![0.0; n], vec![0.0; n * n]);
        self.eval_grad(&x0, &mut g);
        self.eval_hess(&x0, &mut hs);
        let (mut d1, mut d2, mut d12) = (0.0, 0.0, 0.0);
        for i in 0..n {
            d1 += g[i] * x[i].eps1;
            d2 += g[i] * x[i].eps2;
            d12 += g[i] * x[i].eps1eps2;
            for j in 0..n {
                d12 += x[i].eps1 * hs[i * n + j] * x[j].eps2;
            }
        }
        HyperDual64::new(h, d1, d2, d12)
    }
    fn relative_degree(&self) -> usize {
        self.relative_degree
    }
    fn gains(&self) -> &[f64] {
        &self.gains
    }
    fn name(&self) -> &str {
        &self.name
    }
    /// One call each of `h` and `∇h` (instead of `n` dual passes).
    fn gradient(&self, x: &[f64], grad: &mut [f64], _scratch: &mut [Dual64]) -> f64 {
        super::check_buffers(self.n, grad.len(), 0, 0);
        self.eval_grad(x, &mut grad[..self.n]);
        self.eval_h(x)
    }
    /// One call each of `h`, `∇h` and `∇²h`.
    fn hessian(
        &self,
        x: &[f64],
        grad: &mut [f64],
        hess: &mut [f64],
        _scratch: &mut [HyperDual64],
    ) -> f64 {
        let n = self.n;
        super::check_buffers(n, grad.len(), 0, 0);
        super::check_hessian_buffer(n, hess.len());
        self.eval_grad(x, &mut grad[..n]);
        self.eval_hess(x, &mut hess[..n * n]);
        self.eval_h(x)
    }
    fn take_error(&self) -> Option<String> {
        self.failure.take()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::barrier::Disc;

    /// `h = ‖x[0:2] − c‖² − r²` on 3 states with hand-written derivatives.
    fn disc_callback(c: [f64; 2], r: f64, hess: bool) -> CallbackBarrier {
        let h: ValueFn =
            Box::new(move |x| Ok((x[0] - c[0]).powi(2) + (x[1] - c[1]).powi(2) - r * r));
        let g: ArrayFn = Box::new(move |x, out| {
            out.copy_from_slice(&[2.0 * (x[0] - c[0]), 2.0 * (x[1] - c[1]), 0.0]);
            Ok(())
        });
        let hs: ArrayFn = Box::new(|_, out| {
            out.fill(0.0);
            out[0] = 2.0;
            out[4] = 2.0;
            Ok(())
        });
        CallbackBarrier::new("disc", 3, 2, vec![1.0, 2.0], h, g, hess.then_some(hs)).unwrap()
    }

    #[test]
    fn chain_rule_matches_automatic_differentiation() {
        let (c, r) = ([0.3, -0.7], 0.5);
        let cb = disc_callback(c, r, true);
        let ad = Disc::new(3, [0, 1], c, r, 2, vec![1.0, 2.0]).unwrap();
        let x = [1.1, 0.4, -2.0];
        // arbitrary (non-unit) dual directions
        let (a, b, cc) = ([0.3, -1.2, 0.7], [2.0, 0.1, -0.4], [0.5, 0.25, -1.0]);
        let xd: Vec<Dual64> = (0..3).map(|i| Dual64::new(x[i], a[i])).collect();
        let (v1, v2) = (cb.value_dual(&xd), DynBarrier::value_dual(&ad, &xd));
        assert!((v1.re - v2.re).abs() < 1e-14 && (v1.eps - v2.eps).abs() < 1e-13);
        let xh: Vec<HyperDual64> = (0..3)
            .map(|i| HyperDual64::new(x[i], a[i], b[i], cc[i]))
            .collect();
        let (w1, w2) = (cb.value_hyper(&xh), DynBarrier::value_hyper(&ad, &xh));
        for (p, q) in [
            (w1.re, w2.re),
            (w1.eps1, w2.eps1),
            (w1.eps2, w2.eps2),
            (w1.eps1eps2, w2.eps1eps2),
        ] {
            assert!((p - q).abs() < 1e-13, "{w1:?} vs {w2:?}");
        }
        assert!(cb.take_error().is_none());
        assert_eq!(w1.re, cb.value(&x));
    }

    /// `h = x₀x₁` with the gradient right and the Hessian `hess`.
    fn product_barrier(hess: [f64; 4]) -> CallbackBarrier {
        let h: ValueFn = Box::new(|x| Ok(x[0] * x[1]));
        let g: ArrayFn = Box::new(|x, out| {
            out.copy_from_slice(&[x[1], x[0]]);
            Ok(())
        });
        let hs: ArrayFn = Box::new(move |_, out| {
            out.copy_from_slice(&hess);
            Ok(())
        });
        CallbackBarrier::new("xy", 2, 2, vec![1.0, 2.0], h, g, Some(hs)).unwrap()
    }

    #[test]
    fn a_non_symmetric_hessian_is_a_failure() {
        let (mut grad, mut hess) = ([0.0; 2], [0.0; 4]);
        let skew = product_barrier([0.0, 1.0, 0.9, 0.0]);
        skew.hessian(&[0.5, 0.2], &mut grad, &mut hess, &mut []);
        let e = skew.take_error().unwrap();
        assert!(
            e.contains("non-symmetric") && e.contains("(1, 0) = 0.9"),
            "{e}"
        );
        assert!(hess.iter().all(|v| v.is_nan()));
        // the symmetric one passes
        let right = product_barrier([0.0, 1.0, 1.0, 0.0]);
        right.hessian(&[0.5, 0.2], &mut grad, &mut hess, &mut []);
        assert!(right.take_error().is_none());
        assert_eq!(hess, [0.0, 1.0, 1.0, 0.0]);
    }

    /// `h` failing with `message` where `x₀ > limit`, `below(x₀)` elsewhere.
    fn failing_above(limit: f64, message: &'static str, below: fn(f64) -> f64) -> ValueFn {
        Box::new(move |x| {
            if x[0] > limit {
                Err(message.into())
            } else {
                Ok(below(x[0]))
            }
        })
    }

    /// A gradient or Hessian of constant entries `v`.
    fn filled(v: f64) -> ArrayFn {
        Box::new(move |_, out| {
            out.fill(v);
            Ok(())
        })
    }

    #[test]
    fn failures_are_recorded_once_and_taken() {
        let h = failing_above(0.0, "boom", |_| f64::INFINITY);
        let g = filled(0.0);
        let cb = CallbackBarrier::new("bad", 1, 1, vec![1.0], h, g, None).unwrap();
        assert!(cb.value(&[1.0]).is_nan());
        assert!(cb.value(&[-1.0]).is_nan());
        let e = cb.take_error().unwrap();
        assert!(e.starts_with("h failed") && e.contains("boom"), "{e}");
        assert!(cb.value(&[-1.0]).is_nan());
        assert!(cb.take_error().unwrap().contains("h returned inf"));
        assert!(cb.take_error().is_none());
        // no Hessian: a second-order evaluation fails naming hess
        let _ = cb.value_hyper(&[HyperDual64::new(-1.0, 1.0, 1.0, 0.0)]);
        let _ = cb.take_error();
        let mut grad = [0.0];
        let mut hess = [0.0];
        cb.hessian(&[-1.0], &mut grad, &mut hess, &mut []);
        // the first failure wins: the missing Hessian comes before h
        assert!(cb.take_error().unwrap().contains("hess is required"));
        let ok_h: ValueFn = Box::new(|_| Ok(1.0));
        let no_hess = CallbackBarrier::new("c", 1, 1, vec![1.0], ok_h, filled(0.0), None).unwrap();
        no_hess.hessian(&[0.0], &mut grad, &mut hess, &mut []);
        assert!(no_hess.take_error().unwrap().contains("hess is required"));
    }

    /// A barrier shared by threads reports to each thread its own failure:
    /// a thread that evaluates where `h` is fine is not handed another
    /// thread's failure, and the failing thread gets its own message.
    #[test]
    fn failures_are_reported_to_the_thread_that_met_them() {
        let h = failing_above(5.0, "bad region", |x| x);
        let cb = CallbackBarrier::new("shared", 1, 1, vec![1.0], h, filled(1.0), None).unwrap();
        let failed = std::sync::Barrier::new(2);
        let taken = std::sync::Barrier::new(2);
        std::thread::scope(|s| {
            s.spawn(|| {
                assert!(cb.value(&[6.0]).is_nan());
                failed.wait();
                taken.wait();
                let e = cb.take_error().unwrap();
                assert!(e.contains("bad region") && e.contains("6.0"), "{e}");
                assert!(cb.take_error().is_none());
            });
            s.spawn(|| {
                failed.wait();
                assert_eq!(cb.value(&[1.5]), 1.5);
                assert_eq!(cb.take_error(), None);
                taken.wait();
            });
        });
        assert_eq!(cb.take_error(), None);
    }

    #[test]
    fn relative_degree_two_needs_a_hessian() {
        let h: ValueFn = Box::new(|_| Ok(0.0));
        let g: ArrayFn = Box::new(|_, _| Ok(()));
        let e = CallbackBarrier::new("c", 2, 2, vec![1.0, 2.0], h, g, None).unwrap_err();
        assert!(e.to_string().contains("hess"), "{e}");
    }
}
