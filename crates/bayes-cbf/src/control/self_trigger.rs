//! Self-triggered control: how long a control may be held (paper, Sec. V-B
//! and VI-C), with the hold of Prop. 3 corrected.
//!
//! Over a hold the control `u̲_k` is constant and `ẋ = f_k(x) = F(x)u̲_k`.
//! With `L_f` a Lipschitz constant of `f_k` on the cuboid `X_k` around `x_k`
//! (Lemma 3, [`Mvgp::lipschitz`]) and `X ≥ ‖ẋ_k‖`, Grönwall's inequality
//! (Lemma 5) keeps the state within
//! `r(s) = X (e^{s L_f} − 1)/L_f` of `x_k` and its velocity within
//! `‖ẋ(s) − ẋ_k‖ ≤ L_f r(s)`, for as long as the state stays in `X_k`.
//!
//! ## Relative degree 1 (Prop. 3, corrected)
//!
//! `CBC(x) = ∇h(x)ᵀ f_k(x) + α h(x)`. Splitting
//! `∇h(x)ᵀf_k(x) − ∇h(x_k)ᵀf_k(x_k) = ∇h(x)ᵀ(f_k(x) − f_k(x_k)) +
//! (∇h(x) − ∇h(x_k))ᵀ f_k(x_k)`,
//!
//! `|CBC(x) − CBC(x_k)| ≤ (L_h (L_f + L_α) + L_∇h X) ‖x − x_k‖`,
//!
//! with `L_h ≥ sup ‖∇h‖`, `L_∇h ≥ sup ‖∇²h‖` on `X_k` and `L_α = α` (the
//! barrier's gain). If `CBC(x_k) ≥ ζ_k`, then `CBC ≥ 0` for
//! `r(s) ≤ ζ_k / (L_h (L_f + L_α) + L_∇h X)`, that is for
//!
//! `τ_k = ln(1 + L_f ζ_k / ((L_h (L_f + L_α) + L_∇h X) X)) / L_f`.
//!
//! The paper's Prop. 3 prints this without `L_∇h X`: it bounds the change of
//! `∇hᵀ f_k` as if `∇h` were constant, which is unsafe for a curved barrier
//! (see `tests/self_trigger_holds.rs` for the counterexample
//! `h = 0.01 x − x²`, `ẋ = 1`, `ζ = 0.01`, where the printed hold is
//! `0.0476 s` and `h < 0` from `0.01 s`).
//!
//! The margin `ζ_k`: the SOCP's chance constraint
//! `E[CBC] − c(p̃) √Var[CBC] ≥ ζ` makes `CBC(x_k) ≥ E[CBC] − c(p̃) √Var[CBC]`
//! with probability `p̃` (the condition is Gaussian for relative degree 1),
//! so the hold uses that certified value at the applied control when the
//! step's [`ConstraintReport`]s are given (it is `≥ ζ`, and larger when the
//! constraint is inactive), and the paper's `ζ` otherwise.
//!
//! ## Relative degree `r` (Prop. 5)
//!
//! `|h(x) − h(x_k)| ≤ L_h ‖x − x_k‖`, so `h ≥ 0` over the hold while
//! `r(s) ≤ h(x_k)/L_h`. Prop. 5 takes the margin `ζ_b`, assuming
//! `h(x_k) ≥ ζ_b` (the SOCP enforces the condition on `h_b = h − ζ_b`,
//! [`ShiftedBarrier`]), which the sampled-data loop does not ensure; the
//! hold here uses the margin `h(x_k)` itself, which is what the bound needs:
//!
//! `τ_k = ln(1 + L_f h(x_k) / (L_h X)) / L_f` (0 when `h(x_k) ≤ 0`).
//!
//! ## Staying in the cuboid
//!
//! The constants hold on `X_k` only. Coordinate `i` moves at most
//! `d_i(s) = b_i s + X ((e^{s L_f} − 1)/L_f − s)` with `b_i ≥ |ẋ_{k,i}|`
//! (integrate `|ẋ_i(s)| ≤ |ẋ_{k,i}| + L_f r(s)`); the hold is shortened to
//! the largest `s` with `d_i(s) ≤ side_i / 2` for every `i`.
//!
//! ## `‖ẋ_k‖` with high probability
//!
//! `v = F(x_k)u̲_k ~ N(μ, s A)` with `μ = M_k(x_k)u̲_k`,
//! `s = u̲_kᵀ B_k(x_k, x_k) u̲_k` and `A` the row covariance. By Gaussian
//! concentration of the 1-Lipschitz map `z ↦ ‖Σ^{1/2} z‖`,
//! `‖v − μ‖ ≤ ρ = √s (√tr A + √(2 λ_max(A) ln(1/δ_L)))` with probability
//! `1 − δ_L`; then `X = ‖μ‖ + ρ` and `b_i = |μ_i| + ρ`.
//!
//! ## Probability
//!
//! The hold's guarantee needs three events: the SOCP's condition at `x_k`
//! (probability `p̃`), the Lipschitz bound (`1 − δ_L`) and the velocity bound
//! (`1 − δ_L`). They concern the same random `F`, so they are not
//! independent; by the union bound all three hold with probability at least
//! `p` when the SOCP uses `p̃ = p + 2δ_L` ([`TriggerSettings::tilde_p`]). The
//! paper's `p̃ = p/(1 − δ_L)` multiplies probabilities as if the events were
//! independent.
//!
//! The applied hold is `τ_k` clamped to `[τ_min, τ_max]`; a clamp from below
//! is reported, since the guarantee then no longer covers the whole hold.
//!
//! ## Holds shorter than `τ_min`
//!
//! A controller cannot trigger sooner than `τ_min`, so a `τ_k < τ_min`
//! leaves the end of the hold unguaranteed. Where the margins of
//! relative-degree-1 barriers are what keeps `τ_k` short, a larger margin
//! fixes it: the corrected Prop. 3 hold is `τ_min` at
//! `ζ = (e^{L_f τ_min} − 1)/L_f · (L_h (L_f + L_α) + L_∇h X) X`
//! ([`zeta_for_tau`]). With [`TriggerSettings::margin_for_tau_min`] the
//! closed loop solves such a step again with that margin (the largest over
//! the barriers), evaluates the trigger at the new control (its `L_f` and
//! `X` depend on the control) and repeats a few times while the hold is
//! still short. A program infeasible at the raised margin keeps the step's
//! first solution, and its clamped hold. The margin cannot help where the
//! state may leave the cuboid before `τ_min` or a relative-degree-≥2
//! barrier's `h(x_k)` is too small ([`TriggerReport::margin_for_hold`]).
//! `L_h` and `L_∇h` are grid estimates (the grid maximum plus the covering
//! radius times the largest slope between neighbouring nodes), like the
//! mean term of Lemma 3.

use super::{ConstraintReport, SafetyController, SafetySettings};
use crate::barrier::{DynBarrier, DynLyapunov};
use crate::error::{check_positive, Error, InputError};
use crate::gp::lipschitz::{grid_nodes, grid_sup_estimate};
use crate::gp::{LipschitzEstimate, LipschitzSettings, Mvgp};
use num_dual::{Dual64, HyperDual64};
use rand::Rng;
use std::sync::Arc;

/// Which Lipschitz estimate sets the hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub enum TauSource {
    /// The analytic bound of Lemma 3 (holds with probability `1 − δ_L`).
    #[default]
    Analytic,
    /// The numerical estimate from sampled Jacobians (no guarantee).
    Numerical,
}

impl TauSource {
    /// Name used in files.
    pub fn name(self) -> &'static str {
        match self {
            TauSource::Analytic => "analytic",
            TauSource::Numerical => "numerical",
        }
    }
    /// Parses [`name`](Self::name).
    pub fn parse(s: &str) -> Result<Self, InputError> {
        match s {
            "analytic" => Ok(TauSource::Analytic),
            "numerical" => Ok(TauSource::Numerical),
            _ => Err(InputError::Invalid {
                field: "trigger.tau_from".into(),
                value: s.into(),
                reason: "expected analytic or numerical".into(),
            }),
        }
    }
}

/// Settings of the self-triggering computation.
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct TriggerSettings {
    /// Lipschitz settings (`δ_L`, cuboid, grid, samples). Every side of the
    /// cuboid must be > 0: the hold keeps the state inside it.
    pub lipschitz: LipschitzSettings,
    /// Margin `ζ > 0` of relative-degree-1 barriers (Prop. 3); must equal the
    /// SOCP's margin.
    pub zeta: f64,
    /// Shift `ζ_b > 0` of barriers of relative degree ≥ 2 (Prop. 5).
    pub zeta_b: f64,
    /// Shortest hold (s).
    pub tau_min: f64,
    /// Longest hold (s).
    pub tau_max: f64,
    /// Estimate that sets the hold.
    pub tau_from: TauSource,
    /// Hold the control for `τ_k` (self-triggered). When false the run is
    /// time-triggered and `τ_k` is only evaluated and recorded.
    pub hold: bool,
    /// At a feasible step whose `τ_k` falls below `τ_min` because of the
    /// margins of relative-degree-1 barriers, solve the step again with
    /// the SOCP's margin raised to the one whose corrected Prop. 3 hold is
    /// `τ_min` ([`TriggerReport::margin_for_hold`]), so that the guarantee
    /// covers the whole hold; kept only when that program is feasible
    /// (module docs, "Holds shorter than τ_min"). Settings written before
    /// the field existed read as `true`.
    #[cfg_attr(feature = "serde", serde(default = "raise_margins"))]
    pub margin_for_tau_min: bool,
}

/// The default of [`TriggerSettings::margin_for_tau_min`] when read.
#[cfg(feature = "serde")]
fn raise_margins() -> bool {
    true
}

impl TriggerSettings {
    /// The paper's evaluation (Sec. VII-B) for the cuboid `sides`:
    /// `δ_L = 1e-4`, `ζ = ζ_b = 1e-2`, 10 nodes per side, holds in
    /// `[1 ms, 0.1 s]`, self-triggered, analytic; and, beyond the paper,
    /// the margin raised where a hold would fall short of `τ_min`
    /// ([`margin_for_tau_min`](Self::margin_for_tau_min); `false` keeps
    /// the paper's `ζ` at every step).
    pub fn new(sides: Vec<f64>) -> Self {
        Self {
            lipschitz: LipschitzSettings::new(sides),
            zeta: 1e-2,
            zeta_b: 1e-2,
            tau_min: 1e-3,
            tau_max: 0.1,
            tau_from: TauSource::Analytic,
            hold: true,
            margin_for_tau_min: true,
        }
    }

    /// Checks the settings for state dimension `n`.
    pub fn validate(&self, n: usize) -> Result<(), InputError> {
        self.lipschitz
            .validate(n)
            .map_err(|e| e.within("trigger."))?;
        if let Some((i, &w)) = self
            .lipschitz
            .sides
            .iter()
            .enumerate()
            .find(|(_, &w)| w <= 0.0)
        {
            return Err(InputError::invalid(
                &format!("trigger.cuboid[{i}]"),
                w,
                "must be > 0: the hold keeps the state inside the cuboid",
            ));
        }
        for (name, v) in [("zeta", self.zeta), ("trigger.zeta_b", self.zeta_b)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(InputError::invalid(name, v, "must be finite and ≥ 0"));
            }
        }
        check_positive("trigger.tau_min", self.tau_min)?;
        if !(self.tau_max.is_finite() && self.tau_max >= self.tau_min) {
            return Err(InputError::invalid(
                "trigger.tau_max",
                self.tau_max,
                "must be finite and ≥ tau_min",
            ));
        }
        if self.tau_from == TauSource::Numerical && self.lipschitz.samples == 0 {
            return Err(InputError::invalid(
                "trigger.samples",
                0.0,
                "must be ≥ 1 when tau_from = numerical",
            ));
        }
        Ok(())
    }

    /// `p̃ = p + 2δ_L`: the SOCP probability that makes the guarantee over
    /// each hold `p` (union bound over the SOCP's condition, the Lipschitz
    /// bound and the velocity bound; see the module docs). Errors when
    /// `p̃ ≥ 1`.
    pub fn tilde_p(&self, p: f64) -> Result<f64, InputError> {
        let pt = p + 2.0 * self.lipschitz.delta_l;
        if !(pt > 0.0 && pt < 1.0) {
            return Err(InputError::invalid(
                "controller.probability",
                p,
                &format!(
                    "p + 2δ_L = {pt} must be < 1 (δ_L = {})",
                    self.lipschitz.delta_l
                ),
            ));
        }
        Ok(pt)
    }
}

/// `ln(1 + L a)/L`, continuous at `L = 0` (limit `a`) and `+∞` for `a = ∞`.
fn log1p_over(l: f64, a: f64) -> f64 {
    if a.is_infinite() {
        return f64::INFINITY;
    }
    if l * a < 1e-12 {
        a
    } else {
        (l * a).ln_1p() / l
    }
}

/// Prop. 3, corrected:
/// `τ = ln(1 + L_f ζ / ((L_h (L_f + L_α) + L_∇h X) X)) / L_f`
/// (`+∞` when the denominator is 0 and `ζ > 0`; `0` when `ζ ≤ 0`). With
/// `l_grad_h = 0` this is the paper's printed formula, which is unsafe for
/// curved barriers.
pub fn tau_relative_degree_one(
    l_f: f64,
    zeta: f64,
    l_alpha: f64,
    l_h: f64,
    l_grad_h: f64,
    xdot: f64,
) -> f64 {
    if zeta <= 0.0 {
        return 0.0;
    }
    let den = (l_h * (l_f + l_alpha) + l_grad_h * xdot) * xdot;
    let a = if den > 0.0 { zeta / den } else { f64::INFINITY };
    log1p_over(l_f, a)
}

/// The margin at which [`tau_relative_degree_one`] is `tau`, its inverse in
/// `ζ`: `ζ = (e^{L_f τ} − 1)/L_f · (L_h (L_f + L_α) + L_∇h X) X` (the limit
/// `τ (…) X` at `L_f = 0`).
pub fn zeta_for_tau(l_f: f64, tau: f64, l_alpha: f64, l_h: f64, l_grad_h: f64, xdot: f64) -> f64 {
    let den = (l_h * (l_f + l_alpha) + l_grad_h * xdot) * xdot;
    let growth = if l_f * tau < 1e-12 {
        tau
    } else {
        (l_f * tau).exp_m1() / l_f
    };
    growth * den
}

/// Prop. 5 with margin `m`: `τ = ln(1 + L_f m / (L_h X)) / L_f` (`+∞` when
/// `L_h X = 0` and `m > 0`; `0` when `m ≤ 0`). The hold uses `m = h(x_k)`.
pub fn tau_relative_degree_r(l_f: f64, margin: f64, l_h: f64, xdot: f64) -> f64 {
    if margin <= 0.0 {
        return 0.0;
    }
    let den = l_h * xdot;
    let a = if den > 0.0 {
        margin / den
    } else {
        f64::INFINITY
    };
    log1p_over(l_f, a)
}

/// `(e^{L s} − 1)/L − s`, the growth of the distance bound beyond the
/// straight line (continuous at `L = 0`, where it is 0).
fn excess(l: f64, s: f64) -> f64 {
    let ls = l * s;
    if ls < 1e-4 {
        l * s * s / 2.0 * (1.0 + ls / 3.0 + ls * ls / 12.0)
    } else {
        (ls.exp_m1() - ls) / l
    }
}

/// The longest `s ≤ upper` for which the state provably stays in the
/// cuboid: `b_i s + X ((e^{s L_f} − 1)/L_f − s) ≤ half_sides[i]` for every
/// coordinate `i` (module docs). `b[i] ≥ |ẋ_{k,i}|`, `xdot ≥ ‖ẋ_k‖`.
pub fn tau_in_cuboid(l_f: f64, half_sides: &[f64], b: &[f64], xdot: f64, upper: f64) -> f64 {
    let worst = |s: f64| -> f64 {
        half_sides
            .iter()
            .zip(b)
            .map(|(&w, &bi)| (bi * s + xdot * excess(l_f, s)) / w)
            .fold(0.0, f64::max)
    };
    if !upper.is_finite() {
        // the bound grows without limit unless the state is at rest
        if xdot == 0.0 {
            return f64::INFINITY;
        }
        let mut hi = 1.0;
        while worst(hi) <= 1.0 && hi < 1e12 {
            hi *= 2.0;
        }
        return tau_in_cuboid(l_f, half_sides, b, xdot, hi);
    }
    if worst(upper) <= 1.0 {
        return upper;
    }
    let (mut lo, mut hi) = (0.0, upper);
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        if worst(mid) <= 1.0 {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo <= 1e-15 * hi.max(1e-300) {
            break;
        }
    }
    lo
}

/// One trigger's evaluation.
#[derive(Debug, Clone, PartialEq)]
pub struct TriggerReport {
    /// The Lipschitz constants of `f_k` on the cuboid.
    pub lipschitz: LipschitzEstimate,
    /// `L_h ≥ sup ‖∇h‖` of each barrier on the cuboid.
    pub l_h: Vec<f64>,
    /// `L_∇h ≥ sup ‖∇²h‖` (Frobenius) of each relative-degree-1 barrier on
    /// the cuboid; 0 for barriers of higher relative degree (Prop. 5 does
    /// not use it).
    pub l_grad_h: Vec<f64>,
    /// The margin of each barrier's hold: for relative degree 1 the
    /// certified condition `E[CBC] − c(p̃)√Var[CBC]` at the applied control
    /// (or `ζ` without the step's reports); `h(x_k)` for relative degree ≥ 2.
    pub margin: Vec<f64>,
    /// `‖M_k(x_k)u̲_k‖`, the posterior mean of `‖ẋ_k‖`.
    pub xdot_mean_norm: f64,
    /// `X`: the bound on `‖ẋ_k‖` that holds with probability `1 − δ_L`.
    pub xdot_norm: f64,
    /// `b_i ≥ |ẋ_{k,i}|` per coordinate, under the same event as `X`.
    pub xdot_bound: Vec<f64>,
    /// `τ_k` from the analytic `L_f`: the minimum over barriers and the time
    /// the state provably stays in the cuboid (unclamped).
    pub tau_analytic: f64,
    /// `τ_k` from the numerical `L_f`, if estimated.
    pub tau_numerical: Option<f64>,
    /// The time the state provably stays in the cuboid, with the `L_f` that
    /// sets the hold, computed up to the longer of `τ_max` and the
    /// barriers' `τ_k` (it is that bound when the state cannot leave before).
    pub tau_cuboid: f64,
    /// The hold applied: the chosen `τ_k` clamped to `[τ_min, τ_max]`.
    pub hold: f64,
    /// The chosen `τ_k` was below `τ_min` (the guarantee does not cover the
    /// whole hold).
    pub clamped_low: bool,
    /// The SOCP margin the step was solved with when it was raised for the
    /// hold ([`TriggerSettings::margin_for_tau_min`]); `None` when the step
    /// used `ζ`.
    pub raised_zeta: Option<f64>,
    /// Wall time of this evaluation (µs).
    pub eval_us: f64,
}

impl TriggerReport {
    /// `τ_k` from `L_f` with `margins` (one per barrier, as
    /// [`margin`](Self::margin)) on this report's `L_h`, `L_∇h` and velocity
    /// bounds: the smallest over `barriers` of the corrected Prop. 3 or
    /// Prop. 5 hold and the time the state provably stays in the cuboid of
    /// `half_sides`; and that cuboid time, computed up to the longer of
    /// `tau_max` and the barriers' `τ_k`.
    pub fn tau_with(
        &self,
        l_f: f64,
        margins: &[f64],
        barriers: &[Arc<dyn DynBarrier>],
        half_sides: &[f64],
        tau_max: f64,
    ) -> (f64, f64) {
        let x = self.xdot_norm;
        let by_barriers = barriers
            .iter()
            .enumerate()
            .map(|(i, b)| {
                if b.relative_degree() == 1 {
                    let l_alpha = b.gains().first().map_or(0.0, |a| a.abs());
                    let (l_h, l_gh) = (self.l_h[i], self.l_grad_h[i]);
                    tau_relative_degree_one(l_f, margins[i], l_alpha, l_h, l_gh, x)
                } else {
                    tau_relative_degree_r(l_f, margins[i], self.l_h[i], x)
                }
            })
            .fold(f64::INFINITY, f64::min);
        let upper = by_barriers.max(tau_max);
        let cube = tau_in_cuboid(l_f, half_sides, &self.xdot_bound, x, upper);
        (by_barriers.min(cube), cube)
    }

    /// The `L_f` that set this report's hold: the numerical estimate when
    /// `source` asks for it and it was estimated, the analytic bound
    /// otherwise.
    pub fn l_f(&self, source: TauSource) -> f64 {
        match (source, self.lipschitz.numerical) {
            (TauSource::Numerical, Some(l)) => l,
            _ => self.lipschitz.analytic,
        }
    }

    /// The smallest margin of the relative-degree-1 conditions at which the
    /// hold would be `tau` with this report's `L_f` (`source`), `L_h`,
    /// `L_∇h` and velocity bound: the largest [`zeta_for_tau`] over those
    /// barriers. `None` when a margin cannot give that hold: the state may
    /// leave the cuboid before `tau`, or a barrier of relative degree ≥ 2
    /// (whose margin is `h(x_k)`) holds for less; or no barrier has
    /// relative degree 1.
    pub fn margin_for_hold(
        &self,
        source: TauSource,
        barriers: &[Arc<dyn DynBarrier>],
        tau: f64,
    ) -> Option<f64> {
        let (l_f, x) = (self.l_f(source), self.xdot_norm);
        if self.tau_cuboid < tau {
            return None;
        }
        let mut need: Option<f64> = None;
        for (i, b) in barriers.iter().enumerate() {
            if b.relative_degree() == 1 {
                let l_alpha = b.gains().first().map_or(0.0, |a| a.abs());
                let z = zeta_for_tau(l_f, tau, l_alpha, self.l_h[i], self.l_grad_h[i], x);
                need = Some(need.map_or(z, |n| n.max(z)));
            } else if tau_relative_degree_r(l_f, self.margin[i], self.l_h[i], x) < tau {
                return None;
            }
        }
        need
    }
}

/// Grid estimates of `sup` over the cuboid of each component of
/// `value(node)` (the grid maximum plus the covering radius times the
/// largest slope between neighbouring nodes).
fn sup_on_cuboid(
    x: &[f64],
    s: &LipschitzSettings,
    value: &mut dyn FnMut(&[f64]) -> Vec<f64>,
) -> Vec<f64> {
    let all: Vec<usize> = (0..x.len()).collect();
    let values: Vec<Vec<f64>> = grid_nodes(x, &s.sides, s.grid, &all)
        .iter()
        .map(|node| value(node))
        .collect();
    grid_sup_estimate(&values, &s.sides, s.grid)
}

/// `sup ‖∇h‖` on the cuboid (grid estimate: the grid maximum plus the
/// covering radius times the largest slope between neighbouring nodes).
pub fn barrier_gradient_bound(b: &dyn DynBarrier, x: &[f64], s: &LipschitzSettings) -> f64 {
    let n = x.len();
    let mut grad = vec![0.0; n];
    let mut scratch = vec![Dual64::from(0.0); n];
    sup_on_cuboid(x, s, &mut |node| {
        b.gradient(node, &mut grad, &mut scratch);
        vec![grad.iter().map(|v| v * v).sum::<f64>().sqrt()]
    })[0]
}

/// `(sup ‖∇h‖, sup ‖∇²h‖_F)` on the cuboid from one pass of Hessians over
/// the grid (grid estimates as [`barrier_gradient_bound`]; the Frobenius
/// norm bounds the spectral norm).
pub fn barrier_gradient_and_hessian_bounds(
    b: &dyn DynBarrier,
    x: &[f64],
    s: &LipschitzSettings,
) -> (f64, f64) {
    let n = x.len();
    let mut grad = vec![0.0; n];
    let mut hess = vec![0.0; n * n];
    let mut scratch = vec![HyperDual64::from(0.0); n];
    let sup = sup_on_cuboid(x, s, &mut |node| {
        b.hessian(node, &mut grad, &mut hess, &mut scratch);
        let norm = |v: &[f64]| v.iter().map(|e| e * e).sum::<f64>().sqrt();
        vec![norm(&grad), norm(&hess)]
    });
    (sup[0], sup[1])
}

/// The mean `μ = M_k(x)u̲` of `ẋ = F(x)u̲` and the radius `ρ` with
/// `P(‖F(x)u̲ − μ‖ ≤ ρ) ≥ 1 − δ` (module docs).
pub fn velocity_bound(
    model: &Mvgp,
    x: &[f64],
    u: &[f64],
    delta: f64,
) -> Result<(Vec<f64>, f64), Error> {
    let post = model.posterior(x)?;
    let (n, p) = (model.state_dim(), u.len() + 1);
    if post.mean.ncols() != p {
        return Err(InputError::shape("u", post.mean.ncols() - 1, u.len()).into());
    }
    let ubar = |c: usize| if c == 0 { 1.0 } else { u[c - 1] };
    let mu: Vec<f64> = (0..n)
        .map(|i| (0..p).map(|c| post.mean[(i, c)] * ubar(c)).sum())
        .collect();
    let s: f64 = (0..p)
        .map(|a| {
            (0..p)
                .map(|c| ubar(a) * post.B[(a, c)] * ubar(c))
                .sum::<f64>()
        })
        .sum::<f64>()
        .max(0.0);
    let a = model.row_cov();
    let trace = a.trace().max(0.0);
    let lambda_max = a
        .clone()
        .symmetric_eigenvalues()
        .iter()
        .copied()
        .fold(0.0, f64::max);
    let rho = s.sqrt() * (trace.sqrt() + (2.0 * lambda_max * (1.0 / delta).ln()).sqrt());
    Ok((mu, rho))
}

/// Evaluates the trigger at `(x_k, u_k)`: Lipschitz constants, `L_h`,
/// `L_∇h`, the high-probability `‖ẋ_k‖`, both `τ_k`, the cuboid time and
/// the hold. `barriers` are the unshifted barriers; `conditions`, if given,
/// are the step's reports of the same barriers
/// ([`ControlOutput::constraints`](super::ControlOutput::constraints)),
/// whose certified values set the margins of relative-degree-1 barriers
/// (module docs).
pub fn evaluate_trigger<R: Rng>(
    model: &Mvgp,
    x: &[f64],
    u: &[f64],
    barriers: &[Arc<dyn DynBarrier>],
    conditions: Option<&[ConstraintReport]>,
    settings: &TriggerSettings,
    rng: &mut R,
) -> Result<TriggerReport, Error> {
    let started = std::time::Instant::now();
    settings.validate(model.state_dim())?;
    if let Some(c) = conditions {
        if c.len() != barriers.len() {
            return Err(InputError::shape("conditions", barriers.len(), c.len()).into());
        }
    }
    let lipschitz = model.lipschitz(x, u, &settings.lipschitz, rng)?;
    let (mu, rho) = velocity_bound(model, x, u, settings.lipschitz.delta_l)?;
    let xdot_mean_norm = mu.iter().map(|v| v * v).sum::<f64>().sqrt();
    let xdot_norm = xdot_mean_norm + rho;
    let b: Vec<f64> = mu.iter().map(|v| v.abs() + rho).collect();
    let half_sides: Vec<f64> = settings.lipschitz.sides.iter().map(|w| w / 2.0).collect();
    let ls = &settings.lipschitz;
    // L_∇h only for relative degree 1 (Prop. 5 does not use it)
    let (l_h, l_grad_h): (Vec<f64>, Vec<f64>) = barriers
        .iter()
        .map(|b| {
            if b.relative_degree() == 1 {
                barrier_gradient_and_hessian_bounds(b.as_ref(), x, ls)
            } else {
                (barrier_gradient_bound(b.as_ref(), x, ls), 0.0)
            }
        })
        .unzip();
    let margin: Vec<f64> = barriers
        .iter()
        .enumerate()
        .map(|(i, b)| {
            if b.relative_degree() >= 2 {
                b.value(x)
            } else {
                conditions.map_or(settings.zeta, |c| c[i].mean - c[i].c * c[i].std)
            }
        })
        .collect();
    let mut report = TriggerReport {
        lipschitz,
        l_h,
        l_grad_h,
        margin,
        xdot_mean_norm,
        xdot_norm,
        xdot_bound: b,
        tau_analytic: f64::NAN,
        tau_numerical: None,
        tau_cuboid: f64::NAN,
        hold: f64::NAN,
        clamped_low: false,
        raised_zeta: None,
        eval_us: 0.0,
    };
    let tau =
        |l_f: f64| report.tau_with(l_f, &report.margin, barriers, &half_sides, settings.tau_max);
    let (tau_analytic, cube_analytic) = tau(report.lipschitz.analytic);
    let numerical = report.lipschitz.numerical.map(tau);
    let (chosen, tau_cuboid) = match (settings.tau_from, numerical) {
        (TauSource::Numerical, Some(t)) => t,
        _ => (tau_analytic, cube_analytic),
    };
    report.tau_analytic = tau_analytic;
    report.tau_numerical = numerical.map(|t| t.0);
    report.tau_cuboid = tau_cuboid;
    report.hold = chosen.clamp(settings.tau_min, settings.tau_max);
    report.clamped_low = chosen < settings.tau_min;
    report.eval_us = started.elapsed().as_secs_f64() * 1e6;
    Ok(report)
}

/// The barrier `h_b = h − ζ_b` of Prop. 5: enforcing it at the triggering
/// times keeps `h ≥ ζ_b` there.
pub struct ShiftedBarrier {
    inner: Arc<dyn DynBarrier>,
    shift: f64,
}

impl ShiftedBarrier {
    /// `h − shift`.
    pub fn new(inner: Arc<dyn DynBarrier>, shift: f64) -> Self {
        Self { inner, shift }
    }
}

impl DynBarrier for ShiftedBarrier {
    fn state_dim(&self) -> usize {
        self.inner.state_dim()
    }
    fn value(&self, x: &[f64]) -> f64 {
        self.inner.value(x) - self.shift
    }
    fn value_dual(&self, x: &[Dual64]) -> Dual64 {
        self.inner.value_dual(x) - self.shift
    }
    fn value_hyper(&self, x: &[HyperDual64]) -> HyperDual64 {
        self.inner.value_hyper(x) - self.shift
    }
    fn relative_degree(&self) -> usize {
        self.inner.relative_degree()
    }
    fn gains(&self) -> &[f64] {
        self.inner.gains()
    }
    fn name(&self) -> &str {
        self.inner.name()
    }
}

/// A safety controller set up for self-triggered control, with the trigger
/// settings it goes with: the rules of Props. 3 and 5 in one place.
///
/// - One margin ζ: the SOCP's [`SafetySettings::zeta`] is the ζ of Prop. 3
///   (it must be > 0 when a barrier has relative degree 1);
/// - barriers of relative degree ≥ 2 enter the SOCP shifted to
///   `h_b = h − ζ_b` ([`ShiftedBarrier`], Prop. 5; `ζ_b` > 0 required);
/// - the SOCP probability is `p̃ = p + 2δ_L`
///   ([`TriggerSettings::tilde_p`]), so that the guarantee over each hold is
///   the requested `p` (the bound of Lemma 3 and the velocity bound each
///   hold with probability `1 − δ_L`; union bound).
///
/// `barriers` are the unshifted barriers (check `h` against them);
/// [`SafetyController::new`] checks the rest (`p ≥ 0.5` with
/// relative-degree-1 conditions, dimensions, bounds).
pub struct SelfTriggered {
    /// The controller: shifted barriers, `p̃`, margin ζ.
    pub controller: SafetyController,
    /// The trigger settings, with `zeta` equal to the controller's.
    pub trigger: TriggerSettings,
}

impl SelfTriggered {
    /// Builds the controller for `n` states and `m` controls from the
    /// requested `settings` (probability `p`, margin ζ) and `trigger`
    /// (whose `zeta` is replaced by `settings.zeta`).
    pub fn new(
        n: usize,
        m: usize,
        barriers: &[Arc<dyn DynBarrier>],
        clf: Option<Arc<dyn DynLyapunov>>,
        mut settings: SafetySettings,
        mut trigger: TriggerSettings,
    ) -> Result<Self, Error> {
        trigger.zeta = settings.zeta;
        trigger.validate(n)?;
        if barriers.iter().any(|b| b.relative_degree() == 1) && settings.zeta <= 0.0 {
            return Err(InputError::invalid(
                "controller.zeta",
                settings.zeta,
                "self-triggering needs a margin ζ > 0 on relative-degree-1 barriers (Prop. 3)",
            )
            .into());
        }
        if barriers.iter().any(|b| b.relative_degree() >= 2) && trigger.zeta_b <= 0.0 {
            return Err(InputError::invalid(
                "trigger.zeta_b",
                trigger.zeta_b,
                "self-triggering needs ζ_b > 0 on barriers of relative degree ≥ 2 (Prop. 5)",
            )
            .into());
        }
        settings.probability = trigger.tilde_p(settings.probability)?;
        let shifted = barriers
            .iter()
            .map(|b| {
                if b.relative_degree() >= 2 {
                    Arc::new(ShiftedBarrier::new(b.clone(), trigger.zeta_b)) as Arc<dyn DynBarrier>
                } else {
                    b.clone()
                }
            })
            .collect();
        let controller = SafetyController::new(n, m, shifted, clf, settings)?;
        Ok(Self {
            controller,
            trigger,
        })
    }
}

#[cfg(test)]
mod tests {
    //! The private helpers of the hold against independent references, and
    //! the checks of the settings field by field.
    use super::*;

    /// `Σ_{j ≥ 2} (ls)^j / j! / l`, the series of `(e^{ls} − 1 − ls)/l`,
    /// summed to convergence.
    fn excess_series(l: f64, s: f64) -> f64 {
        let x = l * s;
        let (mut term, mut sum) = (x * x / 2.0, 0.0f64);
        let mut j = 2.0;
        while term.abs() > 1e-18 * sum.abs() || sum == 0.0 {
            sum += term;
            j += 1.0;
            term *= x / j;
            if j > 200.0 {
                break;
            }
        }
        sum / l
    }

    fn field_of(e: InputError) -> String {
        match e {
            InputError::Invalid { field, .. } => field,
            other => panic!("expected Invalid, got {other:?}"),
        }
    }

    #[test]
    fn excess_matches_its_series_on_both_branches() {
        for l in [0.5, 3.0, 40.0] {
            for x in [1e-9, 1e-6, 3e-5, 9.9e-5, 1e-4, 1.01e-4, 1e-3, 0.1, 1.0, 5.0] {
                let s = x / l;
                let (got, want) = (excess(l, s), excess_series(l, s));
                assert!(
                    (got - want).abs() <= 1e-11 * want,
                    "l = {l}, ls = {x}: {got} against {want}"
                );
            }
        }
        assert_eq!(excess(0.0, 0.3), 0.0);
    }

    #[test]
    fn log1p_over_matches_its_definition_and_limit() {
        for (l, a) in [
            (2.0, 0.1),
            (0.5, 3.0),
            (1e-3, 1e-2),
            (10.0, 1e-6),
            (1e-6, 1e7),
        ] {
            let want = (1.0f64 + l * a).ln() / l;
            let got = log1p_over(l, a);
            assert!(
                (got - want).abs() <= 1e-9 * want,
                "{l}, {a}: {got} against {want}"
            );
        }
        // below l·a = 1e-12 the limit a (error of order l a² / 2)
        assert_eq!(log1p_over(0.0, 0.25), 0.25);
        assert_eq!(log1p_over(1e-14, 0.25), 0.25);
        assert_eq!(log1p_over(3.0, f64::INFINITY), f64::INFINITY);
    }

    /// `zeta_for_tau` inverts `tau_relative_degree_one`, on both branches
    /// of its `L_f → 0` limit.
    #[test]
    fn the_margin_for_a_hold_gives_that_hold() {
        for (l_f, tau) in [
            (2.0, 1e-3),
            (41.0, 1e-3),
            (0.5, 0.1),
            (1e-14, 1e-3),
            (0.0, 0.02),
        ] {
            for (l_alpha, l_h, l_gh, x) in [(1.0, 0.5, 0.3, 0.2), (3.0, 2.9, 2.1, 6.3)] {
                let z = zeta_for_tau(l_f, tau, l_alpha, l_h, l_gh, x);
                let back = tau_relative_degree_one(l_f, z, l_alpha, l_h, l_gh, x);
                assert!((back - tau).abs() <= 1e-9 * tau, "{l_f} {tau}: {back}");
            }
        }
    }

    #[test]
    fn tau_formulas_at_literal_values() {
        // ln(1 + 2·0.01/((0.5·(2 + 1) + 0.3·0.2)·0.2))/2
        let want = (1.0f64 + 2.0 * 0.01 / ((0.5 * 3.0 + 0.3 * 0.2) * 0.2)).ln() / 2.0;
        let got = tau_relative_degree_one(2.0, 0.01, 1.0, 0.5, 0.3, 0.2);
        assert!((got - want).abs() < 1e-15);
        assert_eq!(tau_relative_degree_one(2.0, 0.0, 1.0, 0.5, 0.3, 0.2), 0.0);
        assert_eq!(
            tau_relative_degree_one(2.0, 0.01, 1.0, 0.5, 0.3, 0.0),
            f64::INFINITY
        );
        let want = (1.0f64 + 2.0 * 0.05 / (0.5 * 0.2)).ln() / 2.0;
        assert!((tau_relative_degree_r(2.0, 0.05, 0.5, 0.2) - want).abs() < 1e-15);
        assert_eq!(tau_relative_degree_r(2.0, -0.1, 0.5, 0.2), 0.0);
        assert_eq!(tau_relative_degree_r(2.0, 0.05, 0.0, 0.2), f64::INFINITY);
    }

    /// The root of `b s + X((e^{Ls} − 1)/L − s) = w` by bisection on the
    /// plain formula (`L > 0`, the root in `(0, 10)`).
    fn reach_root(l: f64, w: f64, b: f64, xdot: f64) -> f64 {
        let f = |s: f64| b * s + xdot * ((l * s).exp() - 1.0 - l * s) / l - w;
        let (mut lo, mut hi) = (0.0, 10.0);
        for _ in 0..200 {
            let mid = 0.5 * (lo + hi);
            if f(mid) <= 0.0 {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        lo
    }

    #[test]
    fn tau_in_cuboid_solves_its_equation_with_and_without_an_upper_bound() {
        // L = 0: the straight line, s = min w_i / b_i
        let t = tau_in_cuboid(0.0, &[0.1, 0.3], &[0.5, 0.5], 0.7, f64::INFINITY);
        assert!((t - 0.2).abs() < 1e-12, "{t}");
        assert!((tau_in_cuboid(0.0, &[0.1, 0.3], &[0.5, 0.5], 0.7, 5.0) - 0.2).abs() < 1e-12);
        // L > 0: the binding coordinate's root
        let (l, xdot) = (3.0, 0.9);
        let want = reach_root(l, 0.1, 0.6, xdot).min(reach_root(l, 0.25, 0.8, xdot));
        for upper in [1.0, 7.5, f64::INFINITY] {
            let got = tau_in_cuboid(l, &[0.1, 0.25], &[0.6, 0.8], xdot, upper);
            assert!(
                (got - want).abs() < 1e-12 * want,
                "{upper}: {got} against {want}"
            );
        }
        // an upper bound below the root is the answer
        assert_eq!(
            tau_in_cuboid(l, &[0.1, 0.25], &[0.6, 0.8], xdot, 0.5 * want),
            0.5 * want
        );
        // a root beyond the first guess of 1 s: the bracket is widened
        let t = tau_in_cuboid(0.0, &[0.1], &[0.01], 0.01, f64::INFINITY);
        assert!((t - 10.0).abs() < 1e-11, "{t}");
        // at rest the state never leaves
        assert_eq!(
            tau_in_cuboid(l, &[0.1], &[0.0], 0.0, f64::INFINITY),
            f64::INFINITY
        );
    }

    #[test]
    fn tau_source_names_round_trip() {
        for t in [TauSource::Analytic, TauSource::Numerical] {
            assert_eq!(TauSource::parse(t.name()), Ok(t));
        }
        assert_ne!(TauSource::Analytic.name(), TauSource::Numerical.name());
        assert_eq!(
            field_of(TauSource::parse("both").unwrap_err()),
            "trigger.tau_from"
        );
    }

    #[test]
    fn tilde_p_adds_twice_delta_l_inside_the_unit_interval() {
        let mut t = TriggerSettings::new(vec![0.1, 0.1]);
        t.lipschitz.delta_l = 0.01;
        assert!((t.tilde_p(0.9).unwrap() - 0.92).abs() < 1e-15);
        for p in [0.98, 0.99, -0.02, -0.5] {
            assert_eq!(
                field_of(t.tilde_p(p).unwrap_err()),
                "controller.probability"
            );
        }
    }

    #[test]
    fn the_shifted_barrier_is_h_minus_zeta_b_and_forwards_the_rest() {
        use crate::barrier::{PendulumSectorEdge, SectorEdge};
        let inner: Arc<dyn DynBarrier> = Arc::new(
            PendulumSectorEdge::new(0.8, 0.4, SectorEdge::Upper, 2, vec![2.0, 3.0]).unwrap(),
        );
        let b = ShiftedBarrier::new(inner.clone(), 0.05);
        for x in [[0.3, -0.2], [1.4, 0.7]] {
            assert_eq!(b.value(&x), inner.value(&x) - 0.05);
            let d = |v: f64, e: f64| Dual64::new(v, e);
            let xd = [d(x[0], 1.0), d(x[1], 0.0)];
            let (got, want) = (b.value_dual(&xd), inner.value_dual(&xd));
            assert_eq!((got.re, got.eps), (want.re - 0.05, want.eps));
            let h = |v: f64, e1: f64, e2: f64| HyperDual64::new(v, e1, e2, 0.0);
            let xh = [h(x[0], 1.0, 1.0), h(x[1], 0.0, 0.0)];
            let (got, want) = (b.value_hyper(&xh), inner.value_hyper(&xh));
            assert_eq!(
                (got.re, got.eps1, got.eps2, got.eps1eps2),
                (want.re - 0.05, want.eps1, want.eps2, want.eps1eps2)
            );
        }
        assert_eq!(b.state_dim(), 2);
        assert_eq!(b.relative_degree(), 2);
        assert_eq!(b.gains(), &[2.0, 3.0]);
        assert_eq!(b.name(), inner.name());
    }

    #[test]
    fn settings_reject_each_bad_field_by_name() {
        let good = TriggerSettings::new(vec![0.2, 0.1]);
        assert!(good.validate(2).is_ok());
        let mut zero_zeta = good.clone();
        zero_zeta.zeta = 0.0;
        zero_zeta.zeta_b = 0.0;
        assert!(zero_zeta.validate(2).is_ok());
        let mut equal = good.clone();
        equal.tau_max = equal.tau_min;
        assert!(equal.validate(2).is_ok());
        type Edit = fn(&mut TriggerSettings);
        let cases: [(Edit, &str); 11] = [
            (|t| t.lipschitz.sides[1] = 0.0, "trigger.cuboid[1]"),
            (|t| t.zeta = -1e-3, "zeta"),
            (|t| t.zeta = f64::NAN, "zeta"),
            (|t| t.zeta_b = -1e-3, "trigger.zeta_b"),
            (|t| t.zeta_b = f64::INFINITY, "trigger.zeta_b"),
            (|t| t.tau_min = 0.0, "trigger.tau_min"),
            (|t| t.tau_min = f64::INFINITY, "trigger.tau_min"),
            (|t| t.tau_max = 0.5 * t.tau_min, "trigger.tau_max"),
            (|t| t.tau_max = f64::INFINITY, "trigger.tau_max"),
            (
                |t| {
                    t.tau_from = TauSource::Numerical;
                    t.lipschitz.samples = 0;
                },
                "trigger.samples",
            ),
            (|t| t.lipschitz.delta_l = 0.0, "trigger.delta_l"),
        ];
        for (edit, field) in cases {
            let mut t = good.clone();
            edit(&mut t);
            assert_eq!(field_of(t.validate(2).unwrap_err()), field);
        }
        let mut numerical = good.clone();
        numerical.tau_from = TauSource::Numerical;
        numerical.lipschitz.samples = 1;
        assert!(numerical.validate(2).is_ok());
    }
}
