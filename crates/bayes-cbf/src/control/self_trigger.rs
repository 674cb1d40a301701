//! Self-triggered control: how long a control may be held (paper, Sec. V-B
//! and VI-C).
//!
//! With `L_f` a Lipschitz constant of `f_k = F(x)u̲_k` on a set `X_k` around
//! `x_k` (Lemma 3, [`Mvgp::lipschitz`]), the state stays within
//! `r̄(s) = ‖ẋ_k‖ (e^{s L_f} − 1)/L_f` of `x_k` (Lemma 5). Then
//!
//! * relative degree 1 (Prop. 3): if the SOCP enforced `CBC ≥ ζ` at `t_k`,
//!   `CBC ≥ 0` on `[t_k, t_k + τ_k)` for
//!   `τ_k = ln(1 + L_f ζ / ((L_f + L_α) L_h ‖ẋ_k‖)) / L_f`;
//! * relative degree `r` (Prop. 5): with the barrier shifted to
//!   `h_b = h − ζ_b` (see [`ShiftedBarrier`]) and `ζ = 0`,
//!   `h ≥ 0` on the interval for `τ_k = ln(1 + L_f ζ_b / (L_h ‖ẋ_k‖)) / L_f`,
//!
//! where `L_h ≥ sup_{X_k} ‖∇h‖` and `L_α` is the Lipschitz constant of the
//! class-K function. Both hold with probability `p = p̃ (1 − δ_L)` when the
//! SOCP uses `p̃ = p / (1 − δ_L)` ([`TriggerSettings::tilde_p`]).
//!
//! `‖ẋ_k‖` is the posterior mean `‖M_k(x_k)u̲_k‖`. The applied hold is `τ_k`
//! clamped to `[τ_min, τ_max]`; a clamp from below is reported, since the
//! guarantee then no longer covers the whole hold.

use super::{SafetyController, SafetySettings};
use crate::barrier::{DynBarrier, DynLyapunov};
use crate::error::{Error, InputError};
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
    /// Lipschitz settings (`δ_L`, cuboid, grid, samples).
    pub lipschitz: LipschitzSettings,
    /// Margin `ζ > 0` of relative-degree-1 barriers (Prop. 3); must equal the
    /// SOCP's margin.
    pub zeta: f64,
    /// Shift `ζ_b > 0` of barriers of relative degree ≥ 2 (Prop. 5).
    pub zeta_b: f64,
    /// Lipschitz constant `L_α` of the class-K function.
    pub l_alpha: f64,
    /// Shortest hold (s).
    pub tau_min: f64,
    /// Longest hold (s).
    pub tau_max: f64,
    /// Estimate that sets the hold.
    pub tau_from: TauSource,
    /// Hold the control for `τ_k` (self-triggered). When false the run is
    /// time-triggered and `τ_k` is only evaluated and recorded.
    pub hold: bool,
}

impl TriggerSettings {
    /// The paper's evaluation (Sec. VII-B) for the cuboid `sides`:
    /// `δ_L = 1e-4`, `ζ = ζ_b = 1e-2`, `L_α = 1`, 10 nodes per side, holds in
    /// `[1 ms, 0.1 s]`, self-triggered, analytic.
    pub fn new(sides: Vec<f64>) -> Self {
        Self {
            lipschitz: LipschitzSettings::new(sides),
            zeta: 1e-2,
            zeta_b: 1e-2,
            l_alpha: 1.0,
            tau_min: 1e-3,
            tau_max: 0.1,
            tau_from: TauSource::Analytic,
            hold: true,
        }
    }

    /// Checks the settings for state dimension `n`.
    pub fn validate(&self, n: usize) -> Result<(), InputError> {
        self.lipschitz.validate(n)?;
        for (name, v) in [
            ("zeta", self.zeta),
            ("trigger.zeta_b", self.zeta_b),
            ("trigger.l_alpha", self.l_alpha),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(InputError::invalid(name, v, "must be finite and ≥ 0"));
            }
        }
        if !(self.tau_min.is_finite() && self.tau_min > 0.0) {
            return Err(InputError::invalid(
                "trigger.tau_min",
                self.tau_min,
                "must be finite and > 0",
            ));
        }
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

    /// `p̃ = p / (1 − δ_L)`: the SOCP probability that makes the interval
    /// guarantee `p`. Errors when `p̃ ≥ 1`.
    pub fn tilde_p(&self, p: f64) -> Result<f64, InputError> {
        let pt = p / (1.0 - self.lipschitz.delta_l);
        if !(pt > 0.0 && pt < 1.0) {
            return Err(InputError::invalid(
                "controller.probability",
                p,
                &format!(
                    "p / (1 − δ_L) = {pt} must be < 1 (δ_L = {})",
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

/// Prop. 3: `τ = ln(1 + L_f ζ / ((L_f + L_α) L_h ‖ẋ‖)) / L_f`
/// (`+∞` when `L_h ‖ẋ‖ = 0`).
pub fn tau_relative_degree_one(l_f: f64, zeta: f64, l_alpha: f64, l_h: f64, xdot: f64) -> f64 {
    let den = (l_f + l_alpha) * l_h * xdot;
    let a = if den > 0.0 { zeta / den } else { f64::INFINITY };
    log1p_over(l_f, a)
}

/// Prop. 5: `τ = ln(1 + L_f ζ_b / (L_h ‖ẋ‖)) / L_f` (`+∞` when `L_h ‖ẋ‖ = 0`).
pub fn tau_relative_degree_r(l_f: f64, zeta_b: f64, l_h: f64, xdot: f64) -> f64 {
    let den = l_h * xdot;
    let a = if den > 0.0 {
        zeta_b / den
    } else {
        f64::INFINITY
    };
    log1p_over(l_f, a)
}

/// One trigger's evaluation.
#[derive(Debug, Clone, PartialEq)]
pub struct TriggerReport {
    /// The Lipschitz constants of `f_k` on the cuboid.
    pub lipschitz: LipschitzEstimate,
    /// `L_h` of each barrier on the cuboid.
    pub l_h: Vec<f64>,
    /// `‖ẋ_k‖` (posterior mean).
    pub xdot_norm: f64,
    /// `τ_k` from the analytic `L_f` (minimum over barriers, unclamped).
    pub tau_analytic: f64,
    /// `τ_k` from the numerical `L_f`, if estimated.
    pub tau_numerical: Option<f64>,
    /// The hold applied: the chosen `τ_k` clamped to `[τ_min, τ_max]`.
    pub hold: f64,
    /// The chosen `τ_k` was below `τ_min` (the guarantee does not cover the
    /// whole hold).
    pub clamped_low: bool,
    /// Wall time of this evaluation (µs).
    pub eval_us: f64,
}

/// `τ_k` for each barrier from `L_f`, minimum over barriers.
fn tau_for(
    l_f: f64,
    barriers: &[Arc<dyn DynBarrier>],
    l_h: &[f64],
    xdot: f64,
    s: &TriggerSettings,
) -> f64 {
    barriers
        .iter()
        .zip(l_h)
        .map(|(b, &lh)| {
            if b.relative_degree() == 1 {
                tau_relative_degree_one(l_f, s.zeta, s.l_alpha, lh, xdot)
            } else {
                tau_relative_degree_r(l_f, s.zeta_b, lh, xdot)
            }
        })
        .fold(f64::INFINITY, f64::min)
}

/// `sup ‖∇h‖` on the cuboid: the maximum over the grid plus the covering
/// radius times the largest finite-difference slope of `‖∇h‖` between
/// neighbouring nodes.
pub fn barrier_gradient_bound(b: &dyn DynBarrier, x: &[f64], s: &LipschitzSettings) -> f64 {
    let n = x.len();
    let all: Vec<usize> = (0..n).collect();
    let mut grad = vec![0.0; n];
    let mut scratch = vec![Dual64::from(0.0); n];
    let norms: Vec<Vec<f64>> = grid_nodes(x, &s.sides, s.grid, &all)
        .iter()
        .map(|node| {
            b.gradient(node, &mut grad, &mut scratch);
            vec![grad.iter().map(|v| v * v).sum::<f64>().sqrt()]
        })
        .collect();
    grid_sup_estimate(&norms, &s.sides, s.grid)[0]
}

/// Evaluates the trigger at `(x_k, u_k)`: Lipschitz constants, `L_h`,
/// `‖ẋ_k‖`, both `τ_k` and the hold.
pub fn evaluate_trigger<R: Rng>(
    model: &Mvgp,
    x: &[f64],
    u: &[f64],
    barriers: &[Arc<dyn DynBarrier>],
    settings: &TriggerSettings,
    rng: &mut R,
) -> Result<TriggerReport, Error> {
    let started = std::time::Instant::now();
    settings.validate(model.state_dim())?;
    let lipschitz = model.lipschitz(x, u, &settings.lipschitz, rng)?;
    let mean = model.posterior_mean(x)?;
    let xdot_norm = (0..model.state_dim())
        .map(|i| {
            let v = mean[(i, 0)] + (0..u.len()).map(|a| mean[(i, a + 1)] * u[a]).sum::<f64>();
            v * v
        })
        .sum::<f64>()
        .sqrt();
    let l_h: Vec<f64> = barriers
        .iter()
        .map(|b| barrier_gradient_bound(b.as_ref(), x, &settings.lipschitz))
        .collect();
    let tau_analytic = tau_for(lipschitz.analytic, barriers, &l_h, xdot_norm, settings);
    let tau_numerical = lipschitz
        .numerical
        .map(|l| tau_for(l, barriers, &l_h, xdot_norm, settings));
    let chosen = match settings.tau_from {
        TauSource::Analytic => tau_analytic,
        TauSource::Numerical => tau_numerical.unwrap_or(tau_analytic),
    };
    let hold = chosen.clamp(settings.tau_min, settings.tau_max);
    Ok(TriggerReport {
        lipschitz,
        l_h,
        xdot_norm,
        tau_analytic,
        tau_numerical,
        hold,
        clamped_low: chosen < settings.tau_min,
        eval_us: started.elapsed().as_secs_f64() * 1e6,
    })
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
/// - the SOCP probability is `p̃ = p/(1 − δ_L)`
///   ([`TriggerSettings::tilde_p`]), so that the guarantee over each hold is
///   the requested `p` (the bound of Lemma 3 holds with probability
///   `1 − δ_L`).
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
