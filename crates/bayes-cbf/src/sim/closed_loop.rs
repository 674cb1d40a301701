//! The closed loop: observe, reference, safety SOCP, zero-order hold on the
//! true system, record the observation, update the model on schedule.

use super::background_refit::BackgroundRefit;
use super::reference::{Reference, ReferenceOut};
use super::{SimSettings, Simulator};
use crate::barrier::DynBarrier;
use crate::control::{
    evaluate_trigger, ControlOutput, ControlStatus, SafetyController, TriggerReport,
    TriggerSettings,
};
use crate::error::{Error, InputError};
use crate::gp::{fit, FitSettings, Mvgp};
use crate::systems::{wrap_angle, DynSystem};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use std::sync::Arc;
use std::time::Instant;

/// Schedule and simulation settings of a closed-loop run.
#[derive(Debug, Clone, PartialEq)]
pub struct LoopSettings {
    /// Control period τ (s).
    pub dt: f64,
    /// Number of control steps.
    pub steps: usize,
    /// Integrator settings (fine grid, process noise).
    pub sim: SimSettings,
    /// Add the buffered observations to the model every this many steps
    /// (0: never learn online; 1: every step). Each observation is added
    /// with the O(k²) factor growth.
    pub update_every: usize,
    /// Refit the hyperparameters every this many steps (0: never).
    pub refit_every: usize,
    /// Also refit when the data size first reaches 4, 8, 16, … (below
    /// `refit_every`): early refits calibrate the model while data is scarce,
    /// at an amortised O(k³) total cost.
    pub refit_geometric: bool,
    /// Sliding window: keep at most this many observations.
    pub window: Option<usize>,
    /// Budget: keep at most this many observations, the most informative
    /// ones. At the budget each new observation either replaces the stored
    /// point of smallest leave-one-out predictive variance or is discarded
    /// ([`Mvgp::remove_least_informative`]: the kept set has the largest
    /// `log det(K + σ²I)`), O(k²) per observation. Exclusive with `window`.
    pub budget: Option<usize>,
    /// Refit on a background thread: `Some(d)` launches each scheduled refit
    /// on a copy of the model (same data, hyperparameters and fit seed as the
    /// synchronous refit, hence the same result) and swaps it in after step
    /// `k + d` (`d ≥ 1`), the loop meanwhile going on with the previous
    /// hyperparameters; the data changes since the launch are replayed on
    /// the refitted model (O(k²) each). Deterministic: the swap happens at
    /// that step whatever the thread timing (the loop waits for an
    /// unfinished fit). A refit due while another runs is skipped; one still
    /// running at the end is discarded. `None`: refits run synchronously
    /// inside the step.
    pub refit_background: Option<usize>,
    /// Hyperparameter-fit settings of the refits.
    pub fit: FitSettings,
    /// Standard deviation of the noise on the measured `ẋ` (finite
    /// differences of the observed states are used as the measurement).
    pub xdot_noise: f64,
    /// Seed of the run (reference exploration, process and measurement noise).
    pub seed: u64,
    /// Self-triggering (paper, Sec. V-B): evaluate `τ_k` at every trigger and,
    /// if [`TriggerSettings::hold`], hold each control for `τ_k` until the
    /// horizon `steps · dt` (so `steps` counts fixed-step triggers only).
    pub trigger: Option<TriggerSettings>,
}

impl Default for LoopSettings {
    /// `dt = 0.01`, 100 steps, default integrator, learning every step,
    /// no refits, no window or budget, no measurement noise, seed 0.
    fn default() -> Self {
        Self {
            dt: 0.01,
            steps: 100,
            sim: SimSettings::default(),
            update_every: 1,
            refit_every: 0,
            refit_geometric: false,
            window: None,
            budget: None,
            refit_background: None,
            fit: FitSettings::default(),
            xdot_noise: 0.0,
            seed: 0,
            trigger: None,
        }
    }
}

impl LoopSettings {
    /// Checks the settings.
    pub fn validate(&self) -> Result<(), InputError> {
        if !(self.dt.is_finite() && self.dt > 0.0) {
            return Err(InputError::invalid("dt", self.dt, "must be finite and > 0"));
        }
        if self.steps == 0 {
            return Err(InputError::invalid("steps", 0.0, "must be ≥ 1"));
        }
        if !(self.xdot_noise.is_finite() && self.xdot_noise >= 0.0) {
            return Err(InputError::invalid(
                "xdot_noise",
                self.xdot_noise,
                "must be finite and ≥ 0",
            ));
        }
        if let Some(w) = self.window {
            if w < 2 {
                return Err(InputError::invalid("window", w as f64, "must be ≥ 2"));
            }
        }
        if let Some(b) = self.budget {
            if b < 2 {
                return Err(InputError::invalid("budget", b as f64, "must be ≥ 2"));
            }
            if self.window.is_some() {
                return Err(InputError::invalid(
                    "budget",
                    b as f64,
                    "give either a window or a budget, not both",
                ));
            }
        }
        if self.refit_background == Some(0) {
            return Err(InputError::invalid(
                "refit_background",
                0.0,
                "must be ≥ 1 step (or absent: synchronous refits)",
            ));
        }
        SimSettings::new(self.sim.internal_step, self.sim.process_noise)?;
        if let Some(t) = &self.trigger {
            // the cuboid's dimension is checked against the system in the loop
            t.validate(t.lipschitz.sides.len())?;
        }
        self.fit.validate()
    }
}

/// One control step of a run.
#[derive(Debug, Clone, PartialEq)]
pub struct StepRecord {
    /// Time at the start of the step.
    pub t: f64,
    /// State at the start of the step.
    pub x: Vec<f64>,
    /// Applied control.
    pub u: Vec<f64>,
    /// Reference control.
    pub u_ref: Vec<f64>,
    /// Each barrier's `h(x)`.
    pub h: Vec<f64>,
    /// Each barrier's minimum `h` over the fine integration grid of the step.
    pub h_fine_min: Vec<f64>,
    /// Each barrier's stochastic CBC `E − ζ − c·std` at the applied control.
    pub scbc: Vec<f64>,
    /// Stochastic CLC slack `δ − E − c·std`, if a CLF is used.
    pub sclc: Option<f64>,
    /// `tr(B_k(x, x) ⊗ A) = tr B_k · tr A`.
    pub trace_cov: f64,
    /// Solver outcome: `optimal`, `almost_optimal` or `infeasible`.
    pub status: &'static str,
    /// `p*` of an infeasible step.
    pub p_star: Option<f64>,
    /// Time of the control step (posterior, moments, SOCP), µs.
    pub control_us: f64,
    /// Observations in the model that computed this step's control.
    pub data_size: usize,
    /// A hyperparameter refit happened after this step.
    pub refit: bool,
    /// Each monitor's minimum over the fine grid of the step.
    pub monitors: Vec<f64>,
    /// How long the control was held (s): `dt`, or `τ_k` clamped when
    /// self-triggered.
    pub hold: f64,
    /// The trigger evaluation, when [`LoopSettings::trigger`] is set.
    pub trigger: Option<TriggerReport>,
}

impl StepRecord {
    /// Every recorded number of the step (state, control, barrier values and
    /// conditions, posterior trace) is finite.
    pub fn is_finite(&self) -> bool {
        self.x
            .iter()
            .chain(&self.u)
            .chain(&self.h)
            .chain(&self.h_fine_min)
            .chain(&self.scbc)
            .all(|v| v.is_finite())
            && self.trace_cov.is_finite()
    }
}

/// Result of a run.
#[derive(Debug, Clone)]
pub struct LoopResult {
    /// Per-step records.
    pub records: Vec<StepRecord>,
    /// State after the last step.
    pub final_state: Vec<f64>,
    /// Minimum of each barrier over the whole fine grid.
    pub min_barrier: Vec<f64>,
    /// Minimum of each monitor over the whole fine grid.
    pub min_monitor: Vec<f64>,
    /// Steps whose SOCP was infeasible.
    pub infeasible_steps: usize,
    /// The model at the end.
    pub model: Mvgp,
}

/// A scalar function of the state whose minimum over the fine grid is
/// recorded (e.g. the signed distance to an obstacle).
pub type Monitor = Arc<dyn Fn(&[f64]) -> f64 + Send + Sync>;

/// Runs the closed loop from `x0`.
///
/// `barriers` are those of the controller, used for the fine-grid check;
/// `progress(k)` is called after each step.
#[allow(clippy::too_many_arguments)]
pub fn run_closed_loop(
    truth: &dyn DynSystem,
    mut model: Mvgp,
    controller: &mut SafetyController,
    barriers: &[Arc<dyn DynBarrier>],
    monitors: &[Monitor],
    reference: &mut dyn Reference,
    x0: &[f64],
    settings: &LoopSettings,
    mut progress: impl FnMut(usize),
) -> Result<LoopResult, Error> {
    settings.validate()?;
    let (n, m) = (truth.n(), truth.m());
    if x0.len() != n {
        return Err(InputError::shape("start", n, x0.len()).into());
    }
    crate::error::check_finite("start", x0)?;
    if model.n() != n || model.m() != m {
        return Err(InputError::shape(
            "model dimensions",
            format!("n = {n}, m = {m}"),
            format!("n = {}, m = {}", model.n(), model.m()),
        )
        .into());
    }
    let mut rng = ChaCha8Rng::seed_from_u64(settings.seed);
    let mut sim = Simulator::new(truth, settings.sim);
    let mut x = x0.to_vec();
    let mut out = ControlOutput::new(m, barriers.len());
    let mut r = ReferenceOut {
        u_ref: vec![0.0; m],
        xd: vec![0.0; n],
        xd_dot: vec![0.0; n],
    };
    let mut records = Vec::with_capacity(settings.steps);
    let mut min_barrier = barriers.iter().map(|b| b.value(&x)).collect::<Vec<_>>();
    let mut min_monitor = monitors.iter().map(|f| f(&x)).collect::<Vec<_>>();
    let mut buffer: Vec<(Vec<f64>, Vec<f64>, Vec<f64>)> = Vec::new();
    let mut infeasible_steps = 0;
    let mut last_refit_len = 0;
    let mut background: Option<BackgroundRefit> = None;
    if let Some(ts) = &settings.trigger {
        if ts.lipschitz.sides.len() != n {
            return Err(InputError::shape("trigger.cuboid", n, ts.lipschitz.sides.len()).into());
        }
    }
    // a separate stream, so that evaluating τ_k leaves the run unchanged
    let mut trigger_rng = ChaCha8Rng::seed_from_u64(settings.seed ^ 0x5e1f_7419_c0de_0001);
    let self_triggered = settings.trigger.as_ref().is_some_and(|t| t.hold);
    let horizon = settings.steps as f64 * settings.dt;
    let mut t_now = 0.0;
    let mut k = 0usize;
    loop {
        let t = if self_triggered {
            t_now
        } else {
            k as f64 * settings.dt
        };
        if (self_triggered && t >= horizon - 1e-9) || (!self_triggered && k >= settings.steps) {
            break;
        }
        reference.at(k, t, &x, &mut rng, &mut r);
        let start = Instant::now();
        controller.step(&model, &x, &r.u_ref, Some((&r.xd, &r.xd_dot)), &mut out)?;
        let control_us = start.elapsed().as_secs_f64() * 1e6;
        let trigger = match &settings.trigger {
            Some(ts) => Some(evaluate_trigger(
                &model,
                &x,
                &out.u,
                barriers,
                ts,
                &mut trigger_rng,
            )?),
            None => None,
        };
        let hold = match &trigger {
            Some(tr) if self_triggered => tr.hold.min(horizon - t),
            _ => settings.dt,
        };
        let data_size = model.len();
        let (status, p_star) = match &out.status {
            ControlStatus::Optimal => ("optimal", None),
            ControlStatus::AlmostOptimal => ("almost_optimal", None),
            ControlStatus::Infeasible(info) => {
                infeasible_steps += 1;
                ("infeasible", info.p_star)
            }
        };
        let trace_cov = controller
            .workspace()
            .map(|ws| ws.posterior().B.trace() * model.hyper().A.trace())
            .unwrap_or(f64::NAN);
        let h: Vec<f64> = barriers.iter().map(|b| b.value(&x)).collect();
        let mut h_fine_min = h.clone();
        let mut mon_min: Vec<f64> = monitors.iter().map(|f| f(&x)).collect();
        let x_prev = x.clone();
        sim.step_with(&mut x, &out.u, hold, &mut rng, |_, xs| {
            for (b, hm) in barriers.iter().zip(h_fine_min.iter_mut()) {
                *hm = hm.min(b.value(xs));
            }
            for (f, mm) in monitors.iter().zip(mon_min.iter_mut()) {
                *mm = mm.min(f(xs));
            }
        });
        for (a, b) in min_barrier.iter_mut().zip(&h_fine_min) {
            *a = a.min(*b);
        }
        for (a, b) in min_monitor.iter_mut().zip(&mon_min) {
            *a = a.min(*b);
        }
        // the measurement: forward difference of the observed states
        let xdot: Vec<f64> = (0..n)
            .map(|i| {
                let d = x[i] - x_prev[i];
                let d = if truth.angles().contains(&i) {
                    wrap_angle(d)
                } else {
                    d
                };
                let e: f64 = StandardNormal.sample(&mut rng);
                d / hold + settings.xdot_noise * e
            })
            .collect();
        buffer.push((x_prev.clone(), out.u.clone(), xdot));
        if settings.update_every > 0 && (k + 1).is_multiple_of(settings.update_every) {
            for (xo, uo, xd) in buffer.drain(..) {
                // an observation the factor cannot absorb even with bounded
                // jitter duplicates information already in the model
                if let Err(e) = model.add_observation(&xo, &uo, &xd) {
                    log::warn!("step {k}: observation skipped ({e})");
                    continue;
                }
                // a refit running in the background replays these changes
                if let Some(bg) = background.as_mut() {
                    bg.record_add(xo, uo, xd);
                }
                if let Some(w) = settings.window {
                    while model.len() > w {
                        model.remove_oldest();
                        if let Some(bg) = background.as_mut() {
                            bg.record_remove(0);
                        }
                    }
                }
                if let Some(b) = settings.budget {
                    while model.len() > b {
                        let j = model.remove_least_informative();
                        if let (Some(j), Some(bg)) = (j, background.as_mut()) {
                            bg.record_remove(j);
                        }
                    }
                }
            }
        }
        let len = model.len();
        let geometric = settings.refit_geometric
            && len >= 16
            && len.is_power_of_two()
            && len < settings.refit_every
            && len != last_refit_len;
        let due = settings.refit_every > 0
            && ((k + 1).is_multiple_of(settings.refit_every) || geometric)
            && !model.is_empty();
        // a background refit launched d steps ago is swapped in first
        let swapped = match background.take() {
            Some(bg) if bg.due(k) => {
                bg.finish(&mut model);
                true
            }
            other => {
                background = other;
                false
            }
        };
        if due {
            last_refit_len = len;
            let fs = FitSettings {
                warm_start: true,
                seed: settings.fit.seed.wrapping_add(k as u64),
                ..settings.fit.clone()
            };
            match settings.refit_background {
                None => {
                    if let Err(e) = fit(&mut model, &fs) {
                        log::warn!(
                            "refit at step {k} failed ({e}); keeping the previous hyperparameters"
                        );
                    }
                }
                Some(_) if background.is_some() => {
                    log::info!("refit due at step {k} skipped: the previous one is still running");
                }
                Some(d) => background = Some(BackgroundRefit::launch(&model, fs, k, d)),
            }
        }
        let refit = swapped || (due && settings.refit_background.is_none());
        let scbc = out.constraints.iter().map(|c| c.slack).collect();
        records.push(StepRecord {
            t,
            x: x_prev,
            u: out.u.clone(),
            u_ref: r.u_ref.clone(),
            h,
            h_fine_min,
            scbc,
            sclc: out.clf.map(|c| c.slack),
            trace_cov,
            status,
            p_star,
            control_us,
            data_size,
            refit,
            monitors: mon_min,
            hold,
            trigger,
        });
        progress(k);
        k += 1;
        t_now += hold;
    }
    if let Some(bg) = background {
        bg.abandon();
    }
    Ok(LoopResult {
        records,
        final_state: x,
        min_barrier,
        min_monitor,
        infeasible_steps,
        model,
    })
}
