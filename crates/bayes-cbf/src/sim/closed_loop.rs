//! The closed loop: observe, reference, safety SOCP, zero-order hold on the
//! true system, record the observation, update the model on schedule.

use super::reference::{Reference, ReferenceOut};
use super::{SimSettings, Simulator};
use crate::barrier::DynBarrier;
use crate::control::{ControlOutput, ControlStatus, SafetyController};
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
    /// Hyperparameter-fit settings of the refits.
    pub fit: FitSettings,
    /// Standard deviation of the noise on the measured `ẋ` (finite
    /// differences of the observed states are used as the measurement).
    pub xdot_noise: f64,
    /// Seed of the run (reference exploration, process and measurement noise).
    pub seed: u64,
}

impl Default for LoopSettings {
    /// `dt = 0.01`, 100 steps, default integrator, learning every step,
    /// no refits, no window, no measurement noise, seed 0.
    fn default() -> Self {
        Self {
            dt: 0.01,
            steps: 100,
            sim: SimSettings::default(),
            update_every: 1,
            refit_every: 0,
            refit_geometric: false,
            window: None,
            fit: FitSettings::default(),
            xdot_noise: 0.0,
            seed: 0,
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
        SimSettings::new(self.sim.internal_step, self.sim.process_noise)?;
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
    for k in 0..settings.steps {
        let t = k as f64 * settings.dt;
        reference.at(k, t, &x, &mut rng, &mut r);
        let start = Instant::now();
        controller.step(&model, &x, &r.u_ref, Some((&r.xd, &r.xd_dot)), &mut out)?;
        let control_us = start.elapsed().as_secs_f64() * 1e6;
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
        sim.step_with(&mut x, &out.u, settings.dt, &mut rng, |_, xs| {
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
                d / settings.dt + settings.xdot_noise * e
            })
            .collect();
        buffer.push((x_prev.clone(), out.u.clone(), xdot));
        if settings.update_every > 0 && (k + 1) % settings.update_every == 0 {
            for (xo, uo, xd) in buffer.drain(..) {
                // an observation the factor cannot absorb even with bounded
                // jitter duplicates information already in the model
                if let Err(e) = model.add_observation(&xo, &uo, &xd) {
                    log::warn!("step {k}: observation skipped ({e})");
                    continue;
                }
                if let Some(w) = settings.window {
                    while model.len() > w {
                        model.remove_oldest();
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
        let refit = settings.refit_every > 0
            && ((k + 1) % settings.refit_every == 0 || geometric)
            && !model.is_empty();
        if refit {
            last_refit_len = len;
            let fs = FitSettings {
                warm_start: true,
                seed: settings.fit.seed.wrapping_add(k as u64),
                ..settings.fit.clone()
            };
            if let Err(e) = fit(&mut model, &fs) {
                log::warn!("refit at step {k} failed ({e}); keeping the previous hyperparameters");
            }
        }
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
        });
        progress(k);
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
