//! The closed loop as an engine: observe, reference, safety SOCP,
//! zero-order hold on the true system, record the observation, update the
//! model on schedule; one [`ClosedLoop::step`] at a time or
//! [`ClosedLoop::run`] to the horizon with an [`Observer`].

use super::background_refit::{BackgroundRefit, REFIT_FAILED};
use super::reference::{Reference, ReferenceOut};
use super::{SimSettings, Simulator};
use crate::barrier::DynBarrier;
use crate::control::{
    evaluate_trigger, ControlOutput, ControlStatus, RecalibrationSettings, SafetyController,
    TriggerReport, TriggerSettings,
};
use crate::error::{check_len, check_nonnegative, check_positive, Error, InputError};
use crate::gp::{fit_until, FitSettings, Mvgp};
use crate::systems::{wrap_angle, DynSystem};
use crate::warnings::WarnOnce;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

/// Which observations the model keeps as data arrive.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub enum DataPolicy {
    /// Every observation (the cost of a step grows with the data).
    #[default]
    All,
    /// Sliding window: the last `k` observations (O(k²) per removal). For
    /// dynamics that drift. It forgets: where the input saturates, the last
    /// `k` observations can hold one control, and the input gain is then
    /// told from the drift by the prior alone; [`Budget`](Self::Budget)
    /// keeps the observations that told them apart (docs/robots.md).
    Window(usize),
    /// Budget: at most `k` observations, the most informative ones. At the
    /// budget each new observation either replaces the stored point of
    /// smallest leave-one-out predictive variance or is discarded
    /// ([`Mvgp::remove_least_informative`]: the kept set has the largest
    /// `log det(K + σ²I)`), O(k²) per observation.
    Budget(usize),
}

/// Outcome of a step's safety SOCP.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub enum StepStatus {
    /// Solved to tolerance.
    Optimal,
    /// Solved to the reduced tolerance.
    AlmostOptimal,
    /// Infeasible: the declared fallback was applied.
    Infeasible,
}

impl StepStatus {
    /// `optimal`, `almost_optimal` or `infeasible`.
    pub fn name(self) -> &'static str {
        match self {
            StepStatus::Optimal => "optimal",
            StepStatus::AlmostOptimal => "almost_optimal",
            StepStatus::Infeasible => "infeasible",
        }
    }
}

/// Schedule and simulation settings of a closed-loop run.
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
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
    /// Which observations the model keeps.
    pub data: DataPolicy,
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
    /// Online recalibration of the barrier conditions' variances after
    /// every model update ([`crate::control::Recalibrator`]); `None` keeps
    /// the posterior variances as they are.
    pub recalibration: Option<RecalibrationSettings>,
}

impl Default for LoopSettings {
    /// `dt = 0.01`, 100 steps, default integrator, learning every step,
    /// no refits, all data kept, no measurement noise, seed 0.
    fn default() -> Self {
        Self {
            dt: 0.01,
            steps: 100,
            sim: SimSettings::default(),
            update_every: 1,
            refit_every: 0,
            refit_geometric: false,
            data: DataPolicy::All,
            refit_background: None,
            fit: FitSettings::default(),
            xdot_noise: 0.0,
            seed: 0,
            trigger: None,
            recalibration: Some(RecalibrationSettings::default()),
        }
    }
}

impl LoopSettings {
    /// Checks the settings.
    pub fn validate(&self) -> Result<(), InputError> {
        check_positive("dt", self.dt)?;
        if self.steps == 0 {
            return Err(InputError::invalid("steps", 0.0, "must be ≥ 1"));
        }
        check_nonnegative("xdot_noise", self.xdot_noise)?;
        match self.data {
            DataPolicy::Window(w) if w < 2 => {
                return Err(InputError::invalid_shown("window", w, "must be ≥ 2"));
            }
            DataPolicy::Budget(b) if b < 2 => {
                return Err(InputError::invalid_shown("budget", b, "must be ≥ 2"));
            }
            _ => {}
        }
        if self.refit_background == Some(0) {
            return Err(InputError::invalid(
                "refit_background",
                0.0,
                "must be ≥ 1 step (or absent: synchronous refits)",
            ));
        }
        SimSettings::new(self.sim.internal_step, self.sim.process_noise)?;
        if let Some(t) = self.trigger.as_ref().filter(|t| t.hold) {
            // the run ends at steps·dt, each hold at least τ_min long
            let triggers = self.steps as f64 * self.dt / t.tau_min;
            if triggers > super::MAX_TRIGGERS as f64 {
                return Err(InputError::invalid_shown(
                    "steps",
                    self.steps,
                    &format!(
                        "steps · dt / trigger.tau_min = {} possible triggers, more than {}",
                        crate::error::number(triggers),
                        super::MAX_TRIGGERS
                    ),
                ));
            }
        }
        let longest = match &self.trigger {
            Some(t) if t.hold => ("trigger.tau_max", t.tau_max),
            _ => ("dt", self.dt),
        };
        let substeps = longest.1 / self.sim.internal_step;
        if substeps > super::MAX_SUBSTEPS as f64 {
            return Err(InputError::invalid(
                longest.0,
                longest.1,
                &format!(
                    "{} / sim.internal_step = {} RK4 sub-steps per hold, more than {} \
                     (raise sim.internal_step or shorten the hold)",
                    longest.0,
                    crate::error::number(substeps),
                    super::MAX_SUBSTEPS
                ),
            ));
        }
        if let Some(r) = &self.recalibration {
            r.validate()?;
        }
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
    /// `tr(B_k(x, x) ⊗ A_row) = tr B_k · tr A_row`, `A_row` the model's row
    /// covariance ([`Mvgp::row_cov`]: `A` with the known rows zero).
    pub trace_cov: f64,
    /// Solver outcome.
    pub status: StepStatus,
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
    /// The variance inflation `κ_i` of each of the controller's barrier
    /// conditions at this step (empty when the recalibration is off).
    pub inflation: Vec<f64>,
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

impl LoopResult {
    /// The self-triggering evaluations of the run's steps, in order (none
    /// without [`LoopSettings::trigger`]).
    pub fn trigger_reports(&self) -> impl Iterator<Item = &TriggerReport> {
        self.records.iter().filter_map(|r| r.trigger.as_ref())
    }
}

/// A scalar function of the state whose minimum over the fine grid is
/// recorded (e.g. the signed distance to an obstacle).
pub type Monitor = Arc<dyn Fn(&[f64]) -> f64 + Send + Sync>;

/// Something that watches a run step by step (progress, logging,
/// statistics), as argmin's observers watch an optimiser.
pub trait Observer {
    /// Called after step `k` with its record.
    fn observe(&mut self, k: usize, record: &StepRecord);
}

impl<F: FnMut(usize, &StepRecord)> Observer for F {
    fn observe(&mut self, k: usize, record: &StepRecord) {
        self(k, record)
    }
}

/// Skipped observations warned of, one by one, in a run.
const SKIPS_SHOWN: usize = 3;
/// Solves of a step again with a raised margin, at most
/// ([`TriggerSettings::margin_for_tau_min`]).
const MARGIN_ROUNDS: usize = 4;
/// The raised margin over the one the last evaluation asks for.
const MARGIN_ABOVE_NEED: f64 = 1.01;
/// A run skipped an observation: recorded once, shown as [`SKIPS_SHOWN`]
/// says.
static OBSERVATION_SKIPPED: WarnOnce = WarnOnce::new("observation_skipped");

/// The closed loop of a true system, a learned model and a safety
/// controller, stepped one control period (or one self-triggered hold) at a
/// time.
///
/// Each [`step`](Self::step): the reference at the current state, the
/// controller's SOCP on the current model (posterior, moments), the
/// self-trigger evaluation when configured, the zero-order hold of the
/// control on the true system (RK4 on the fine grid, where every barrier
/// and monitor is checked), the observation `ẋ ≈ (x⁺ − x)/τ` buffered,
/// and, on schedule, the online update (O(k²) per observation, with the
/// [`DataPolicy`]) and the hyperparameter refit (in the loop or on a
/// background thread). Deterministic given [`LoopSettings::seed`].
pub struct ClosedLoop<'a> {
    truth: &'a dyn DynSystem,
    model: Mvgp,
    controller: &'a mut SafetyController,
    barriers: &'a [Arc<dyn DynBarrier>],
    monitors: &'a [Monitor],
    reference: &'a mut dyn Reference,
    settings: LoopSettings,
    /// The integrator, its RK4 buffers reused at every step.
    sim: Simulator<'a>,
    rng: ChaCha8Rng,
    trigger_rng: ChaCha8Rng,
    x: Vec<f64>,
    out: ControlOutput,
    r: ReferenceOut,
    buffer: Vec<(Vec<f64>, Vec<f64>, Vec<f64>)>,
    min_barrier: Vec<f64>,
    min_monitor: Vec<f64>,
    infeasible_steps: usize,
    /// Observations the model could not absorb (warned of up to
    /// [`SKIPS_SHOWN`]).
    skipped: usize,
    last_refit_len: usize,
    background: Option<BackgroundRefit>,
    t_now: f64,
    k: usize,
    last: Option<StepRecord>,
    /// Ends [`run`](Self::run) and the refits once set
    /// ([`with_stop`](Self::with_stop)).
    stop: Arc<AtomicBool>,
}

impl<'a> ClosedLoop<'a> {
    /// A loop from state `x0`. `barriers` are checked on the fine grid (the
    /// controller's own may be shifted versions of them); `model` is the
    /// initial model, owned and updated by the loop.
    pub fn new(
        truth: &'a dyn DynSystem,
        model: Mvgp,
        controller: &'a mut SafetyController,
        barriers: &'a [Arc<dyn DynBarrier>],
        reference: &'a mut dyn Reference,
        x0: &[f64],
        settings: &LoopSettings,
    ) -> Result<Self, Error> {
        settings.validate()?;
        let (n, m) = (truth.state_dim(), truth.control_dim());
        if x0.len() != n {
            return Err(InputError::shape("start", n, x0.len()).into());
        }
        crate::error::check_finite("start", x0)?;
        if model.state_dim() != n || model.control_dim() != m {
            return Err(InputError::shape(
                "model dimensions",
                format!("n = {n}, m = {m}"),
                format!("n = {}, m = {}", model.state_dim(), model.control_dim()),
            )
            .into());
        }
        for (i, b) in barriers.iter().enumerate() {
            if b.state_dim() != n {
                // the field is formatted only on failure
                check_len(&format!("barriers[{i}] state dimension"), n, b.state_dim())?;
            }
        }
        reference.check_dims(n, m)?;
        if let Some(ts) = &settings.trigger {
            let nb = controller.barrier_moments().len();
            if nb != barriers.len() {
                return Err(InputError::shape(
                    "barriers (one per controller barrier, for the trigger)",
                    nb,
                    barriers.len(),
                )
                .into());
            }
            if ts.lipschitz.sides.len() != n {
                return Err(
                    InputError::shape("trigger.cuboid", n, ts.lipschitz.sides.len()).into(),
                );
            }
        }
        controller.set_recalibration(settings.recalibration)?;
        Ok(Self {
            truth,
            model,
            controller,
            barriers,
            monitors: &[],
            reference,
            settings: settings.clone(),
            sim: Simulator::new(truth, settings.sim),
            rng: ChaCha8Rng::seed_from_u64(settings.seed),
            // a separate stream, so that evaluating τ_k leaves the run unchanged
            trigger_rng: ChaCha8Rng::seed_from_u64(settings.seed ^ 0x5e1f_7419_c0de_0001),
            x: x0.to_vec(),
            out: ControlOutput::new(m, barriers.len()),
            r: ReferenceOut {
                u_ref: vec![0.0; m],
                xd: vec![0.0; n],
                xd_dot: vec![0.0; n],
            },
            buffer: Vec::new(),
            min_barrier: barriers.iter().map(|b| b.value(x0)).collect(),
            min_monitor: Vec::new(),
            infeasible_steps: 0,
            skipped: 0,
            last_refit_len: 0,
            background: None,
            t_now: 0.0,
            k: 0,
            last: None,
            stop: Arc::new(AtomicBool::new(false)),
        })
    }

    /// The loop, stopped by `stop`: once it is set (by another thread: a
    /// Ctrl-C handler, a deadline), [`run`](Self::run) returns
    /// [`Error::Interrupted`] before its next step, and a refit running,
    /// in the loop or on the background thread, ends within one likelihood
    /// evaluation, keeping the previous hyperparameters.
    pub fn with_stop(mut self, stop: Arc<AtomicBool>) -> Self {
        self.stop = stop;
        self
    }

    /// Also records the minimum of each monitor (e.g. the signed distance
    /// to an obstacle) over the fine grid.
    pub fn with_monitors(mut self, monitors: &'a [Monitor]) -> Self {
        self.min_monitor = monitors.iter().map(|f| f(&self.x)).collect();
        self.monitors = monitors;
        self
    }

    fn self_triggered(&self) -> bool {
        self.settings.trigger.as_ref().is_some_and(|t| t.hold)
    }

    fn horizon(&self) -> f64 {
        self.settings.steps as f64 * self.settings.dt
    }

    /// The time at the start of the next step.
    pub fn time(&self) -> f64 {
        if self.self_triggered() {
            self.t_now
        } else {
            self.k as f64 * self.settings.dt
        }
    }

    /// Whether the horizon is reached: `steps` fixed steps, or `steps · dt`
    /// seconds of self-triggered holds.
    pub fn is_finished(&self) -> bool {
        if self.self_triggered() {
            self.t_now >= self.horizon() - 1e-9
        } else {
            self.k >= self.settings.steps
        }
    }

    /// Steps taken so far.
    pub fn steps_taken(&self) -> usize {
        self.k
    }

    /// The current state.
    pub fn state(&self) -> &[f64] {
        &self.x
    }

    /// The current model.
    pub fn model(&self) -> &Mvgp {
        &self.model
    }

    /// Minimum of each barrier over the fine grid so far.
    pub fn min_barrier(&self) -> &[f64] {
        &self.min_barrier
    }

    /// Minimum of each monitor over the fine grid so far.
    pub fn min_monitor(&self) -> &[f64] {
        &self.min_monitor
    }

    /// Steps whose SOCP was infeasible so far.
    pub fn infeasible_steps(&self) -> usize {
        self.infeasible_steps
    }

    /// The record of the last step, if any.
    pub fn last_record(&self) -> Option<&StepRecord> {
        self.last.as_ref()
    }

    /// Takes one step; an error if the horizon is already reached, or if
    /// the controller or the trigger evaluation fails.
    pub fn step(&mut self) -> Result<&StepRecord, Error> {
        if self.is_finished() {
            return Err(InputError::invalid_shown(
                "steps",
                self.settings.steps,
                "the run has reached its horizon",
            )
            .into());
        }
        let rec = self.advance()?;
        Ok(self.last.insert(rec))
    }

    /// Steps to the horizon, calling `observer` after each step, and
    /// returns every step's record with the final state and model.
    pub fn run(mut self, observer: &mut dyn Observer) -> Result<LoopResult, Error> {
        let mut records = crate::error::reserve("steps", self.settings.steps)?;
        while !self.is_finished() {
            if self.stop.load(Ordering::Relaxed) {
                // a background refit sees the flag too and ends within one
                // evaluation: joined, so that no thread outlives the run
                if let Some(bg) = self.background.take() {
                    bg.abandon();
                }
                return Err(Error::Interrupted);
            }
            let rec = self.advance()?;
            observer.observe(self.k - 1, &rec);
            records.push(rec);
        }
        Ok(self.finish(records))
    }

    /// Ends the run (a background refit still running is joined and
    /// dropped) and returns its result with `records`.
    pub fn finish(mut self, records: Vec<StepRecord>) -> LoopResult {
        if let Some(bg) = self.background.take() {
            bg.abandon();
        }
        LoopResult {
            records,
            final_state: self.x,
            min_barrier: self.min_barrier,
            min_monitor: self.min_monitor,
            infeasible_steps: self.infeasible_steps,
            model: self.model,
        }
    }

    /// One step: control, hold, observation, learning; the step's record.
    fn advance(&mut self) -> Result<StepRecord, Error> {
        let (n, k, t) = (self.truth.state_dim(), self.k, self.time());
        let self_triggered = self.self_triggered();
        let horizon = self.horizon();
        self.reference.at(k, t, &self.x, &mut self.rng, &mut self.r);
        // a reference may have replaced the vectors
        let m = self.truth.control_dim();
        check_len("reference control", m, self.r.u_ref.len())?;
        check_len("reference x_d", n, self.r.xd.len())?;
        check_len("reference ẋ_d", n, self.r.xd_dot.len())?;
        let start = Instant::now();
        self.controller.step(
            &self.model,
            &self.x,
            &self.r.u_ref,
            Some((&self.r.xd, &self.r.xd_dot)),
            &mut self.out,
        )?;
        let control_us = start.elapsed().as_secs_f64() * 1e6;
        let inflation: Vec<f64> = self
            .controller
            .recalibrator()
            .map(|r| (0..r.barriers()).map(|i| r.inflation(i)).collect())
            .unwrap_or_default();
        let trigger = self.evaluate_trigger()?;
        // an infeasible step did not enforce the condition the hold's
        // guarantee starts from: hold for the shortest time only
        let infeasible = matches!(self.out.status, ControlStatus::Infeasible(_));
        let hold = match (&trigger, &self.settings.trigger) {
            (Some(_), Some(ts)) if self_triggered && infeasible => ts.tau_min.min(horizon - t),
            (Some(tr), _) if self_triggered => tr.hold.min(horizon - t),
            _ => self.settings.dt,
        };
        let data_size = self.model.len();
        let (status, p_star) = match &self.out.status {
            ControlStatus::Optimal => (StepStatus::Optimal, None),
            ControlStatus::AlmostOptimal => (StepStatus::AlmostOptimal, None),
            ControlStatus::Infeasible(info) => {
                self.infeasible_steps += 1;
                (StepStatus::Infeasible, info.p_star)
            }
        };
        let trace_cov = self
            .controller
            .workspace()
            .map(|ws| ws.posterior().B.trace() * self.model.row_cov().trace())
            .unwrap_or(f64::NAN);
        let h: Vec<f64> = self.barriers.iter().map(|b| b.value(&self.x)).collect();
        let mut h_fine_min = h.clone();
        let mut mon_min: Vec<f64> = self.monitors.iter().map(|f| f(&self.x)).collect();
        let x_prev = self.x.clone();
        let (barriers, monitors) = (self.barriers, self.monitors);
        self.sim
            .step_with(&mut self.x, &self.out.u, hold, &mut self.rng, |_, xs| {
                for (b, hm) in barriers.iter().zip(h_fine_min.iter_mut()) {
                    *hm = hm.min(b.value(xs));
                }
                for (f, mm) in monitors.iter().zip(mon_min.iter_mut()) {
                    *mm = mm.min(f(xs));
                }
            })?;
        if let Some(msg) = self.truth.take_error() {
            return Err(InputError::Evaluation(format!("true system at step {k}: {msg}")).into());
        }
        if let Some(i) = self.x.iter().position(|v| !v.is_finite()) {
            return Err(InputError::Evaluation(format!(
                "the state x[{i}] became {} at step {k} (t = {t}) from x = {x_prev:?}, u = {:?}",
                self.x[i], self.out.u
            ))
            .into());
        }
        for (a, b) in self.min_barrier.iter_mut().zip(&h_fine_min) {
            *a = a.min(*b);
        }
        for (a, b) in self.min_monitor.iter_mut().zip(&mon_min) {
            *a = a.min(*b);
        }
        // the measurement: the difference quotient of the observed states
        // over the hold, labelled at the midpoint of the step, where it is
        // the derivative up to O(τ²) (at x_prev it is biased by τ/2 · ẍ)
        let mut mid = x_prev.clone();
        let xdot: Vec<f64> = (0..n)
            .map(|i| {
                let d = self.x[i] - x_prev[i];
                let d = if self.truth.angle_indices().contains(&i) {
                    wrap_angle(d)
                } else {
                    d
                };
                mid[i] += 0.5 * d;
                let e: f64 = StandardNormal.sample(&mut self.rng);
                d / hold + self.settings.xdot_noise * e
            })
            .collect();
        self.buffer.push((mid, self.out.u.clone(), xdot));
        if self.learn(k) {
            self.controller.recalibrate(&self.model)?;
            self.forget();
        }
        let refit = self.refit(k);
        let rec = StepRecord {
            t,
            x: x_prev,
            u: self.out.u.clone(),
            u_ref: self.r.u_ref.clone(),
            h,
            h_fine_min,
            scbc: self.out.constraints.iter().map(|c| c.slack).collect(),
            sclc: self.out.clf.map(|c| c.slack),
            trace_cov,
            status,
            p_star,
            control_us,
            data_size,
            refit,
            monitors: mon_min,
            hold,
            trigger,
            inflation,
        };
        self.k += 1;
        self.t_now += hold;
        Ok(rec)
    }

    /// The trigger at the state and the step's control, if the run has one
    /// ([`LoopSettings::trigger`]); with
    /// [`TriggerSettings::margin_for_tau_min`], a feasible step whose hold
    /// falls short of `τ_min` is solved again with the margin that gives
    /// `τ_min` ([`crate::control::self_trigger`], "Holds shorter than
    /// τ_min"), up to [`MARGIN_ROUNDS`] times while it is still short; a
    /// program infeasible at the raised margin keeps the first solution.
    fn evaluate_trigger(&mut self) -> Result<Option<TriggerReport>, Error> {
        let Some(ts) = &self.settings.trigger else {
            return Ok(None);
        };
        let (model, x, barriers) = (&self.model, &self.x, self.barriers);
        let at = |out: &ControlOutput, rng: &mut ChaCha8Rng| {
            evaluate_trigger(model, x, &out.u, barriers, Some(&out.constraints), ts, rng)
        };
        let mut report = at(&self.out, &mut self.trigger_rng)?;
        if !(ts.hold && ts.margin_for_tau_min) || self.out.is_infeasible() || !report.clamped_low {
            return Ok(Some(report));
        }
        let zeta = self.controller.settings().zeta;
        let first = report.clone();
        let mut raised = zeta;
        // the margin of the last feasible round, whose solution is in out
        let mut kept = None;
        let mut resolved = false;
        let mut failure = None;
        for _ in 0..MARGIN_ROUNDS {
            let Some(need) = report.margin_for_hold(ts.tau_from, self.barriers, ts.tau_min) else {
                break;
            };
            // 1 % above the need: the new control's L_f and velocity bound
            // are larger where a margin asks more of the input, and the
            // solver meets the margin to its accuracy
            raised = raised.max(need * MARGIN_ABOVE_NEED);
            if !raised.is_finite() {
                break;
            }
            if let Err(e) = self.controller.filter_mut().set_zeta(raised) {
                failure = Some(e.into());
                break;
            }
            resolved = true;
            if let Err(e) = self.controller.resolve(&self.r.u_ref, &mut self.out) {
                failure = Some(e);
                break;
            }
            if self.out.is_infeasible() {
                kept = None;
                break;
            }
            match at(&self.out, &mut self.trigger_rng) {
                Ok(r) => report = r,
                Err(e) => {
                    failure = Some(e);
                    break;
                }
            }
            report.raised_zeta = Some(raised);
            kept = Some(raised);
            if !report.clamped_low {
                break;
            }
        }
        self.controller.filter_mut().set_zeta(zeta)?;
        if let Some(e) = failure {
            return Err(e);
        }
        match kept {
            Some(raised) => {
                // the record's conditions are E − ζ − c·std with the run's ζ
                for c in &mut self.out.constraints {
                    c.slack += raised - zeta;
                }
            }
            None => {
                // the first solution again, solved at ζ as it was (the
                // solver's result does not depend on earlier solves), so
                // that the controller's state (the control a hold falls
                // back to, the recalibration's record) is the applied one
                if resolved {
                    self.controller.resolve(&self.r.u_ref, &mut self.out)?;
                }
                report = first;
            }
        }
        Ok(Some(report))
    }

    /// Adds the buffered observations when an update is due after step `k`
    /// (the data may then exceed the [`DataPolicy`] until
    /// [`forget`](Self::forget)); whether it was due.
    fn learn(&mut self, k: usize) -> bool {
        let every = self.settings.update_every;
        if every == 0 || !(k + 1).is_multiple_of(every) {
            return false;
        }
        for (xo, uo, xd) in self.buffer.drain(..) {
            // an observation the factor cannot absorb even with bounded
            // jitter duplicates information already in the model
            if let Err(e) = self.model.add_observation(&xo, &uo, &xd) {
                self.skipped += 1;
                OBSERVATION_SKIPPED.keep(|| format!("step {k}: observation skipped ({e})"));
                match self.skipped {
                    ..SKIPS_SHOWN => log::warn!("step {k}: observation skipped ({e})"),
                    SKIPS_SHOWN => log::warn!(
                        "step {k}: observation skipped ({e}); later skipped observations of this run are not shown"
                    ),
                    _ => {}
                }
                continue;
            }
            // a refit running in the background replays these changes
            if let Some(bg) = self.background.as_mut() {
                bg.record_add(xo, uo, xd);
            }
        }
        true
    }

    /// Brings the data back within the [`DataPolicy`]: a window drops the
    /// oldest observations, a budget the least informative ones (the same
    /// choice as [`Mvgp::add_observation_within_budget`], which may be a
    /// new point). Called after the recalibration, which compares the
    /// condition before and after the new observations only: removing data
    /// moves the posterior by more than the new data explain, and counted
    /// as misses it ratcheted the inflation up while a robot stood still.
    fn forget(&mut self) {
        let (limit, oldest) = match self.settings.data {
            DataPolicy::All => return,
            DataPolicy::Window(w) => (w, true),
            DataPolicy::Budget(b) => (b, false),
        };
        while self.model.len() > limit {
            let j = if oldest {
                self.model.remove_oldest();
                0
            } else {
                match self.model.remove_least_informative() {
                    Some(j) => j,
                    None => break,
                }
            };
            if let Some(bg) = self.background.as_mut() {
                bg.record_remove(j);
            }
        }
    }

    /// Swaps in a background refit that is due and runs or launches a
    /// scheduled refit after step `k`; whether the model's hyperparameters
    /// changed at this step.
    fn refit(&mut self, k: usize) -> bool {
        let s = &self.settings;
        let len = self.model.len();
        let geometric = s.refit_geometric
            && len >= 16
            && len.is_power_of_two()
            && len < s.refit_every
            && len != self.last_refit_len;
        let due = s.refit_every > 0
            && ((k + 1).is_multiple_of(s.refit_every) || geometric)
            && !self.model.is_empty();
        // a background refit launched d steps ago is swapped in first
        let swapped = match self.background.take() {
            Some(bg) if bg.due(k) => {
                bg.finish(&mut self.model);
                true
            }
            other => {
                self.background = other;
                false
            }
        };
        if due {
            self.last_refit_len = len;
            let fs = FitSettings {
                warm_start: true,
                seed: s.fit.seed.wrapping_add(k as u64),
                ..s.fit.clone()
            };
            match s.refit_background {
                None => {
                    match fit_until(&mut self.model, &fs, &self.stop) {
                        // an interrupted refit ends the run at the next step
                        Ok(_) | Err(Error::Interrupted) => {}
                        Err(e) => REFIT_FAILED.issue(|| {
                            format!("refit at step {k} failed ({e}); keeping the previous hyperparameters")
                        }),
                    }
                }
                Some(_) if self.background.is_some() => {
                    log::info!("refit due at step {k} skipped: the previous one is still running");
                }
                Some(d) => {
                    let stop = Arc::clone(&self.stop);
                    self.background = Some(BackgroundRefit::launch(&self.model, fs, k, d, stop));
                }
            }
        }
        swapped || (due && s.refit_background.is_none())
    }
}
