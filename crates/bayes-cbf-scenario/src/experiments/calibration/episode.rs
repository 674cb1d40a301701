//! One calibration episode: the truth, model, barrier, controller, reference
//! and initial state of `(system, truth kind, episode)`, the closed-loop run,
//! and what it says about safety.
//!
//! ## The true stochastic condition
//! At every step with a solved SOCP the controller promised
//! `P(CBC(x_k, u_k) ≥ 0) ≥ p` under its posterior (paper, Prop. 2 for
//! relative degree 1, Gaussian, `c(p) = √2 erf⁻¹(2p − 1)`; Prop. 4 for
//! relative degree 2, Cantelli, `c(p) = √(p/(1 − p))`). Here the condition
//! is evaluated with the *true* dynamics at the applied control:
//! - relative degree 1: `CBC = ∇h(x)ᵀ F(x) u̲ + α h(x)`;
//! - relative degree 2: `CBC⁽²⁾ = ∇(L_f h)(x)ᵀ F(x) u̲ + k₀ h(x) + k₁ L_f h(x)`
//!   with `L_f h = ∇hᵀ f`.
//!
//! The condition is [`true_condition`]: the barrier's gradient and Hessian
//! by automatic differentiation, the truth's `F` and its Jacobian exactly.
//!
//! A negative value is a violation of the promise. When the model is exactly
//! right, the fraction of violated steps is at most `1 − p` in expectation,
//! and equal to it on the steps where the constraint is *active* (slack 0)
//! for the Gaussian factor (Cantelli's is a bound for any distribution).

use super::Task;
use bayes_cbf::barrier::{
    cbc_moments, realised_condition, true_condition, CircleHeading, ConditionMoments, DynBarrier,
    MomentWorkspace, PendulumSector,
};
use bayes_cbf::control::{Fallback, SafetyController, SafetySettings};
use bayes_cbf::gp::{Feature, InputMap, Mvgp, MvgpHyper, PriorMean, Rbf};
use bayes_cbf::sim::{
    ClosedLoop, LoopResult, LoopSettings, Monitor, Reference, ReferenceOut, SimSettings, StepStatus,
};
use bayes_cbf::systems::{wrap_angle, Ackermann, DynSystem, GpSample, Pendulum};
use nalgebra::DMatrix;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::f64::consts::PI;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use crate::error::{Context, Result};
use crate::stats::normal_cdf;

/// Rows of the pendulum's `F` known exactly: `θ̇ = ω`.
const KNOWN_ROWS: [usize; 1] = [0];
/// Random Fourier features per entry of a GP-prior truth.
pub(crate) const FEATURES: usize = 128;
/// Control period τ (s), as in the paper's experiments.
pub(crate) const DT: f64 = 0.01;
/// Fine RK4 grid on which `h ≥ 0` is checked (s).
pub(crate) const INTERNAL_STEP: f64 = 1e-3;
/// Standard deviation `q/√τ` of the forward difference `(x_{k+1} − x_k)/τ`
/// caused by the process noise of the well-specified truths; the model's
/// noise `σ² A` equals `NOISE² I`.
pub(crate) const NOISE: f64 = 0.02;
/// Process noise intensity `q` of the well-specified truths (Euler–Maruyama
/// increments `q √h ξ` on the fine grid): with the states observed exactly,
/// `ẋ` measured as `(x_{k+1} − x_k)/τ = F(x_k) u̲_k + w_k + O(τ)` with
/// `w_k ~ N(0, q²/τ)` — the MVGP's own observation model with `σ² A = q²/τ I`.
///
/// Noise added to the measured `ẋ` instead (the closed loop's `xdot_noise`)
/// is *not* that model: the next state reveals each noise value exactly, so
/// the controller's noise-driven model errors also decide where its
/// constraint becomes active. Measured during development with
/// `xdot_noise = 0.02` (40 episodes, vehicle): mean-CBF violations on active
/// steps 59 %, while the same steps replayed with independent noise gave
/// 50.0 %.
pub(crate) const PROCESS_NOISE_WELL: f64 = NOISE * 0.1; // q = NOISE √τ, τ = 0.01
/// Process noise intensity of the mis-specified truths: `ẋ` noise
/// `q/√τ = 0.1`, five times what the model assumes.
pub(crate) const PROCESS_NOISE_MIS: f64 = 0.01;
/// A step's chance constraint counts as active when its slack
/// `E − c·std` is below this (the SOCP's accuracy is ~1e-8).
pub(crate) const ACTIVE_SLACK: f64 = 1e-5;

/// The two systems.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize, serde::Deserialize,
)]
pub(crate) enum System {
    /// Ackermann vehicle (Eq. 32), relative-degree-1 obstacle barrier.
    Vehicle,
    /// Pendulum (Eq. 31), relative-degree-2 sector barrier.
    Pendulum,
}

impl System {
    pub fn name(self) -> &'static str {
        match self {
            System::Vehicle => "ackermann",
            System::Pendulum => "pendulum",
        }
    }
}

/// Well-specified or mis-specified truth.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize, serde::Deserialize,
)]
pub(crate) enum TruthKind {
    /// A draw of the model's own GP prior; no process noise.
    WellSpecified,
    /// The paper's parametric mismatch, with process noise.
    MisSpecified,
}

impl TruthKind {
    pub fn name(self) -> &'static str {
        match self {
            TruthKind::WellSpecified => "well_specified",
            TruthKind::MisSpecified => "mis_specified",
        }
    }
}

/// One of the compared controllers.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct ControllerKind {
    /// Report name.
    pub name: &'static str,
    /// Requested probability `p` (the mean CBF has `c(p) = 0`).
    pub p: f64,
    /// The mean CBF: `c = 0` (p = 0.5 at relative degree 1).
    pub mean: bool,
    /// Online recalibration of the condition's variance
    /// ([`bayes_cbf::control::Recalibrator`], default settings).
    pub recalibrate: bool,
    /// The condition as realised over the step, the model's observation
    /// noise included ([`SafetySettings::predictive`]).
    pub predictive: bool,
}

/// Bayes CBF at p ∈ {0.9, 0.99, 0.999} with the posterior as it is, with
/// online recalibration, and recalibrated with the predictive condition;
/// and the mean CBF.
pub(crate) const CONTROLLERS: [ControllerKind; 10] = [
    bayes("bayes-cbf p=0.9", 0.9, false, false),
    bayes("bayes-cbf p=0.99", 0.99, false, false),
    bayes("bayes-cbf p=0.999", 0.999, false, false),
    bayes("bayes-cbf p=0.9 recalibrated", 0.9, true, false),
    bayes("bayes-cbf p=0.99 recalibrated", 0.99, true, false),
    bayes("bayes-cbf p=0.999 recalibrated", 0.999, true, false),
    bayes("bayes-cbf p=0.9 recalibrated predictive", 0.9, true, true),
    bayes("bayes-cbf p=0.99 recalibrated predictive", 0.99, true, true),
    bayes(
        "bayes-cbf p=0.999 recalibrated predictive",
        0.999,
        true,
        true,
    ),
    ControllerKind {
        name: "mean-cbf",
        p: 0.5,
        mean: true,
        recalibrate: false,
        predictive: false,
    },
];

const fn bayes(name: &'static str, p: f64, recalibrate: bool, predictive: bool) -> ControllerKind {
    ControllerKind {
        name,
        p,
        mean: false,
        recalibrate,
        predictive,
    }
}

impl ControllerKind {
    /// The probability given to the SOCP: `p`, or for the mean CBF the one
    /// with `c(p) = 0` — 0.5 for the Gaussian factor (relative degree 1),
    /// ~0 for Cantelli's (relative degree 2: `p = 1e-9`, `c = 3e-5`).
    pub fn socp_probability(self, system: System) -> f64 {
        match (self.mean, system) {
            (true, System::Pendulum) => 1e-9,
            (true, System::Vehicle) => 0.5,
            (false, _) => self.p,
        }
    }
}

// ------------------------------------------------------------------ vehicle

/// Obstacle centre and radius (m).
const OBSTACLE: ([f64; 2], f64) = ([0.0, 0.0], 0.6);
/// Goal behind the obstacle.
const GOAL: [f64; 2] = [2.5, 0.0];
/// Lateral offset of the pursuit's first waypoint `(0, ±0.65)`, 5 cm
/// outside the obstacle: the straight line to it from the start cuts
/// through the disc, so the reference drives into the obstacle, but off its
/// centre, so that about half of the filtered paths slide around it and
/// reach the goal instead of stopping in front of it (the deadlock of CBF
/// filters; with the waypoint on the obstacle's centre line almost every
/// episode stopped there).
const WAYPOINT_OFFSET: f64 = 0.65;
/// The model's wheelbase (prior mean) and the mis-specified truth's
/// (paper, Fig. 7: true 12, model 1).
const WHEELBASE_MODEL: f64 = 1.0;
const WHEELBASE_TRUE: f64 = 12.0;
/// Reference speed (m/s) and heading gain (1/s) of the pursuit.
const V_REF: f64 = 1.2;
const HEADING_GAIN: f64 = 2.0;
/// Control bounds `[v, z]`.
const U_MAX_VEHICLE: [f64; 2] = [1.5, 3.0];
/// The goal counts as reached within this distance (m).
const GOAL_TOL: f64 = 0.3;

/// Pure pursuit `û = [v_ref, L k wrap(bearing − θ)]` (clamped) of the
/// waypoint `(0, ±0.35)` on the start's side while `x < 0`, then of the goal.
#[derive(Debug, Clone)]
struct Pursuit {
    side: f64,
}

impl Reference for Pursuit {
    fn at(&mut self, _k: usize, _t: f64, x: &[f64], _rng: &mut ChaCha8Rng, out: &mut ReferenceOut) {
        let target = if x[0] < OBSTACLE.0[0] {
            [OBSTACLE.0[0], OBSTACLE.0[1] + self.side * WAYPOINT_OFFSET]
        } else {
            GOAL
        };
        let bearing = (target[1] - x[1]).atan2(target[0] - x[0]);
        let z = WHEELBASE_MODEL * HEADING_GAIN * wrap_angle(bearing - x[2]);
        out.u_ref[0] = V_REF;
        out.u_ref[1] = z.clamp(-U_MAX_VEHICLE[1], U_MAX_VEHICLE[1]);
        out.xd.copy_from_slice(x);
        out.xd_dot.fill(0.0);
    }
}

// ----------------------------------------------------------------- pendulum

/// Unsafe sector `θ_c ± Δ` (as `pendulum-safe`).
const SECTOR: (f64, f64) = (PI / 4.0, PI / 8.0);
/// Gains `k_α` of the relative-degree-2 barrier.
/// `s² + 4s + 4` has a double root at −2: the condition lets `h` approach
/// zero within about a second, so the episodes reach the boundary (with
/// `pendulum-safe`'s `(1, 3)` the slow root −0.38 keeps `h > 0.1` for the
/// whole episode and nothing is tested).
const K_ALPHA: [f64; 2] = [4.0, 4.0];
/// Mis-specified truth: mass and length (the model assumes 1 and 1).
const PENDULUM_TRUE: Pendulum = Pendulum {
    mass: 2.0,
    length: 0.5,
    gravity: 10.0,
};
/// Torque bound.
const TORQUE_MAX: f64 = 20.0;
/// PD gains of the reference that drives the pendulum to the sector centre.
const KP: f64 = 12.0;
const KD: f64 = 3.0;

/// `û = m g l sin θ + K_p (θ_c − θ) − K_d ω` with the model's `m = l = 1`:
/// a PD controller toward the centre of the unsafe sector.
#[derive(Debug, Clone)]
struct IntoSector;

impl Reference for IntoSector {
    fn at(&mut self, _k: usize, _t: f64, x: &[f64], _rng: &mut ChaCha8Rng, out: &mut ReferenceOut) {
        let u = 10.0 * x[0].sin() + KP * wrap_angle(SECTOR.0 - x[0]) - KD * x[1];
        out.u_ref[0] = u.clamp(-TORQUE_MAX, TORQUE_MAX);
        out.xd.copy_from_slice(x);
        out.xd_dot.fill(0.0);
    }
}

// ----------------------------------------------------------------- episodes

/// Everything one episode needs (shared by the four controllers).
pub(crate) struct Setup {
    pub truth: Arc<dyn DynSystem>,
    pub model: Mvgp,
    pub barrier: Arc<dyn DynBarrier>,
    pub x0: Vec<f64>,
    pub loop_settings: LoopSettings,
    pub monitors: Vec<Monitor>,
}

#[allow(non_snake_case)]
fn vehicle_hyper() -> Result<(MvgpHyper, InputMap)> {
    // the kernel sees the heading only, periodically (shift invariance)
    let map = InputMap::Features(vec![Feature::Cos(2), Feature::Sin(2)]);
    let A = DMatrix::identity(3, 3) * 0.01;
    let sigma = NOISE / 0.1; // σ² A = NOISE² I
    Ok((
        MvgpHyper {
            kernel: Rbf::new(vec![1.0, 1.0], 1.0)?,
            A,
            B: DMatrix::identity(3, 3),
            sigma,
        },
        map,
    ))
}

#[allow(non_snake_case)]
fn pendulum_hyper() -> Result<(MvgpHyper, InputMap)> {
    let map = InputMap::periodic(2, &[0]);
    let A = DMatrix::identity(2, 2) * 0.04;
    let sigma = NOISE / 0.2; // σ² A = NOISE² I
    Ok((
        MvgpHyper {
            kernel: Rbf::new(vec![1.0, 1.0, 3.0], 1.0)?,
            A,
            B: DMatrix::identity(2, 2),
            sigma,
        },
        map,
    ))
}

/// The setup of `(system, truth, seed)`: the truth draw, initial state and
/// noise all come from `seed`, so the four controllers see the same episode.
pub(crate) fn setup(system: System, truth: TruthKind, seed: u64, steps: usize) -> Result<Setup> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let process_noise = match truth {
        TruthKind::WellSpecified => PROCESS_NOISE_WELL,
        TruthKind::MisSpecified => PROCESS_NOISE_MIS,
    };
    let loop_settings = LoopSettings {
        dt: DT,
        steps,
        sim: SimSettings::new(INTERNAL_STEP, process_noise)?,
        update_every: 1,
        refit_every: 0,
        xdot_noise: 0.0,
        seed: rng.random(),
        recalibration: None,
        ..LoopSettings::default()
    };
    let truth_seed: u64 = rng.random();
    let (truth, model, barrier, x0, monitors): (_, _, Arc<dyn DynBarrier>, _, _) = match system {
        System::Vehicle => {
            let (hyper, map) = vehicle_hyper()?;
            let prior = Ackermann {
                wheelbase: WHEELBASE_MODEL,
            };
            let truth_sys: Arc<dyn DynSystem> = match truth {
                TruthKind::WellSpecified => Arc::new(GpSample::draw(
                    3,
                    2,
                    Some(prior),
                    &hyper,
                    &map,
                    FEATURES,
                    truth_seed,
                )?),
                TruthKind::MisSpecified => Arc::new(Ackermann {
                    wheelbase: WHEELBASE_TRUE,
                }),
            };
            let model = Mvgp::new(3, 2, hyper, PriorMean::System(Arc::new(prior)), map)?;
            let barrier = Arc::new(CircleHeading::new(
                OBSTACLE.0,
                OBSTACLE.1,
                0.7,
                0.3,
                1,
                vec![5.0],
            )?);
            let x0 = vec![
                rng.random_range(-2.3..-1.9),
                rng.random_range(-0.5..0.5),
                rng.random_range(-0.3..0.3),
            ];
            let (c, r) = OBSTACLE;
            let monitor: Monitor = Arc::new(move |x: &[f64]| (x[0] - c[0]).hypot(x[1] - c[1]) - r);
            (truth_sys, model, barrier, x0, vec![monitor])
        }
        System::Pendulum => {
            let (hyper, map) = pendulum_hyper()?;
            let prior = Pendulum::default();
            let truth_sys: Arc<dyn DynSystem> = match truth {
                // the structured prior: θ̇ = ω exactly, only ω̇ drawn
                TruthKind::WellSpecified => Arc::new(
                    GpSample::draw(2, 1, Some(prior), &hyper, &map, FEATURES, truth_seed)?
                        .with_known_rows(&KNOWN_ROWS)?,
                ),
                TruthKind::MisSpecified => Arc::new(PENDULUM_TRUE),
            };
            // the model knows the kinematic row too (interfaces.md, known_rows)
            let model = Mvgp::new(2, 1, hyper, PriorMean::System(Arc::new(prior)), map)?
                .with_known_rows(&KNOWN_ROWS)?;
            let barrier = Arc::new(PendulumSector::new(
                SECTOR.0,
                SECTOR.1,
                2,
                K_ALPHA.to_vec(),
            )?);
            let x0 = vec![rng.random_range(-0.6..0.0), rng.random_range(-0.5..0.5)];
            (truth_sys, model, barrier, x0, Vec::new())
        }
    };
    Ok(Setup {
        truth,
        model,
        barrier,
        x0,
        loop_settings,
        monitors,
    })
}

/// The safety controller `kind` for `system`, with the input bounds and
/// `fallback`.
pub(crate) fn controller(
    system: System,
    kind: ControllerKind,
    fallback: Fallback,
    barrier: &Arc<dyn DynBarrier>,
) -> Result<SafetyController> {
    let (n, m, lo, hi) = match system {
        System::Vehicle => (
            3,
            2,
            vec![-U_MAX_VEHICLE[0], -U_MAX_VEHICLE[1]],
            U_MAX_VEHICLE.to_vec(),
        ),
        System::Pendulum => (2, 1, vec![-TORQUE_MAX], vec![TORQUE_MAX]),
    };
    let mut s = SafetySettings::new(m);
    s.probability = kind.socp_probability(system);
    s.zeta = 0.0;
    s.u_min = Some(lo);
    s.u_max = Some(hi);
    s.fallback = fallback;
    s.predictive = kind.predictive;
    Ok(SafetyController::new(n, m, vec![barrier.clone()], None, s)?)
}

/// What one episode of one controller showed.
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub(crate) struct EpisodeStats {
    /// Control steps run.
    pub steps: usize,
    /// `min h` over the fine grid of the whole episode.
    #[serde(with = "crate::exact")]
    pub min_h: f64,
    /// Steps whose fine grid has `h < 0`.
    pub steps_h_violated: usize,
    /// Steps with a solved SOCP (the promise applies).
    pub solved_steps: usize,
    /// Solved steps whose true condition is negative.
    pub cbc_violations: usize,
    /// Solved steps with an active chance constraint.
    pub active_steps: usize,
    /// Active steps whose true condition is negative.
    pub active_violations: usize,
    /// Active steps from step [`BURN_IN`] on.
    #[serde(default)]
    pub active_steps_late: usize,
    /// Active steps from step [`BURN_IN`] on whose true condition is
    /// negative.
    #[serde(default)]
    pub active_violations_late: usize,
    /// Active steps whose realised condition was evaluated.
    #[serde(default)]
    pub realised_active_steps: usize,
    /// Those whose condition as realised over the step, [`realised`], is
    /// negative.
    #[serde(default)]
    pub realised_active_violations: usize,
    /// Steps with an infeasible SOCP (the fallback was applied).
    pub infeasible_steps: usize,
    /// Standardised true conditions `z = (C_true − E[C]) / √Var[C]` of the
    /// solved steps (`[0]`) and of the active steps (`[1]`), under the model
    /// that chose the control (steps with zero predicted variance are left
    /// out).
    pub z: [ZStats; 2],
    /// Closest distance to the obstacle (vehicle).
    #[serde(with = "crate::exact::option")]
    pub min_distance: Option<f64>,
    /// Goal reached (vehicle: within [`GOAL_TOL`] at some step).
    pub goal_reached: Option<bool>,
    /// Non-finite values in the records (must stay 0).
    pub non_finite: usize,
    /// The run failed with this error (counted separately).
    pub error: Option<String>,
}

impl EpisodeStats {
    /// Checks the counts against each other as [`run_episode`] writes them
    /// (each a subset of the one it is counted among, the sums finite), so
    /// that a shard edited or written by another program is refused rather
    /// than merged into rates above 1. Returns the first field that breaks
    /// a relation.
    pub(crate) fn check(&self) -> std::result::Result<(), String> {
        let at_most = |field: &str, v: usize, bound: &str, b: usize| {
            if v > b {
                Err(format!("{field} = {v} exceeds {bound} = {b}"))
            } else {
                Ok(())
            }
        };
        let solved_or_not = self.solved_steps.checked_add(self.infeasible_steps);
        if solved_or_not != Some(self.steps) {
            return Err(format!(
                "solved_steps + infeasible_steps = {} + {} is not steps = {}",
                self.solved_steps, self.infeasible_steps, self.steps
            ));
        }
        at_most(
            "steps_h_violated",
            self.steps_h_violated,
            "steps",
            self.steps,
        )?;
        at_most("non_finite", self.non_finite, "steps", self.steps)?;
        at_most(
            "cbc_violations",
            self.cbc_violations,
            "solved_steps",
            self.solved_steps,
        )?;
        at_most(
            "active_steps",
            self.active_steps,
            "solved_steps",
            self.solved_steps,
        )?;
        at_most(
            "active_violations",
            self.active_violations,
            "active_steps",
            self.active_steps,
        )?;
        at_most(
            "active_violations",
            self.active_violations,
            "cbc_violations",
            self.cbc_violations,
        )?;
        at_most(
            "active_steps_late",
            self.active_steps_late,
            "active_steps",
            self.active_steps,
        )?;
        at_most(
            "active_violations_late",
            self.active_violations_late,
            "active_violations",
            self.active_violations,
        )?;
        at_most(
            "active_violations_late",
            self.active_violations_late,
            "active_steps_late",
            self.active_steps_late,
        )?;
        at_most(
            "realised_active_steps",
            self.realised_active_steps,
            "active_steps",
            self.active_steps,
        )?;
        at_most(
            "realised_active_violations",
            self.realised_active_violations,
            "realised_active_steps",
            self.realised_active_steps,
        )?;
        at_most("z[0].n", self.z[0].n, "solved_steps", self.solved_steps)?;
        at_most("z[1].n", self.z[1].n, "active_steps", self.active_steps)?;
        for (i, z) in self.z.iter().enumerate() {
            for (j, b) in z.below.iter().enumerate() {
                at_most(&format!("z[{i}].below[{j}]"), *b, &format!("z[{i}].n"), z.n)?;
            }
            let expected_ok = (0.0..=z.n as f64).contains(&z.expected);
            if !(z.sum.is_finite() && z.sum2.is_finite() && z.sum2 >= 0.0 && expected_ok) {
                return Err(format!(
                    "z[{i}]: sum = {}, sum2 = {}, expected = {}: the sums must be finite, sum2 ≥ 0 \
                     and expected between 0 and n = {}",
                    z.sum, z.sum2, z.expected, z.n
                ));
            }
        }
        if self.error.is_some() && self.steps > 0 {
            return Err(format!(
                "steps = {}: an episode that failed has no steps",
                self.steps
            ));
        }
        if self.steps > 0 && self.min_h.is_nan() {
            return Err("min_h is not a number in an episode that ran".into());
        }
        if self.steps_h_violated > 0 && (self.min_h.is_nan() || self.min_h >= 0.0) {
            return Err(format!(
                "steps_h_violated = {} with min_h = {} ≥ 0",
                self.steps_h_violated, self.min_h
            ));
        }
        if let Some(d) = self.min_distance.filter(|d| d.is_nan()) {
            return Err(format!("min_distance = {d}"));
        }
        Ok(())
    }
}

/// The condition as realised over the step from `x` to `x_next`
/// ([`realised_condition`] at the rate `(x_next − x)/τ`, angle differences
/// wrapped): what the predictive condition promises
/// ([`SafetySettings::predictive`]).
pub(crate) fn realised(
    truth: &dyn DynSystem,
    b: &dyn DynBarrier,
    x: &[f64],
    x_next: &[f64],
) -> Result<f64> {
    let angles = truth.angle_indices();
    let rate: Vec<f64> = (0..x.len())
        .map(|i| {
            let d = x_next[i] - x[i];
            let d = if angles.contains(&i) {
                wrap_angle(d)
            } else {
                d
            };
            d / DT
        })
        .collect();
    Ok(realised_condition(truth, b, x, &rate)?)
}

/// The true barrier condition at `(x, u)`: [`true_condition`] by automatic
/// differentiation of `h` and the true dynamics.
pub(crate) fn condition(
    truth: &dyn DynSystem,
    b: &dyn DynBarrier,
    x: &[f64],
    u: &[f64],
) -> Result<f64> {
    Ok(true_condition(truth, b, x, u)?)
}

/// Runs the episode of `task` (its system, truth, controller and length)
/// from `seed`, with `fallback`, and summarises it; the episode ends
/// before its next step once `stop` is set.
pub(crate) fn run_episode(
    task: &Task,
    fallback: Fallback,
    seed: u64,
    stop: &Arc<AtomicBool>,
) -> EpisodeStats {
    match run_inner(task, fallback, seed, stop) {
        Ok(s) => s,
        Err(e) => EpisodeStats {
            error: Some(format!("{e:#}")),
            min_h: f64::NAN,
            ..EpisodeStats::default()
        },
    }
}

fn run_inner(
    task: &Task,
    fallback: Fallback,
    seed: u64,
    stop: &Arc<AtomicBool>,
) -> Result<EpisodeStats> {
    let (system, steps) = (task.system, task.steps);
    let kind = CONTROLLERS[task.controller];
    let mut s = setup(system, task.truth, seed, steps)?;
    s.loop_settings.recalibration = kind
        .recalibrate
        .then(bayes_cbf::control::RecalibrationSettings::default);
    let mut ctrl = controller(system, kind, fallback, &s.barrier)?;
    let mut reference: Box<dyn Reference> = match system {
        System::Vehicle => Box::new(Pursuit {
            side: if s.x0[1] >= 0.0 { 1.0 } else { -1.0 },
        }),
        System::Pendulum => Box::new(IntoSector),
    };
    let barriers = [s.barrier.clone()];
    let mut lp = ClosedLoop::new(
        s.truth.as_ref(),
        s.model.clone(),
        &mut ctrl,
        &barriers,
        reference.as_mut(),
        &s.x0,
        &s.loop_settings,
    )
    .context("closed loop")?
    .with_monitors(&s.monitors)
    .with_stop(Arc::clone(stop));
    // the condition's moments under the model that chooses each step's
    // control (hyperparameters refitted or not), at the applied control
    let b = s.barrier.as_ref();
    let degree = b.relative_degree().min(2);
    let mut ws = MomentWorkspace::new(lp.model());
    let mut mom = ConditionMoments::zeros(lp.model().control_dim());
    let mut moments = Vec::with_capacity(steps);
    let mut records = Vec::with_capacity(steps);
    while !lp.is_finished() {
        // this loop steps the engine itself: `run` would check the flag
        if stop.load(std::sync::atomic::Ordering::Relaxed) {
            return Err(bayes_cbf::Error::Interrupted.into());
        }
        ws.update(lp.model(), lp.state(), degree)
            .context("the model's moments")?;
        cbc_moments(&mut ws, b, &mut mom).context("the model's moments")?;
        let rec = lp.step().context("closed loop")?;
        moments.push((mom.mean(&rec.u), mom.variance(&rec.u).sqrt()));
        records.push(rec.clone());
    }
    let r = lp.finish(records);
    Ok(summarise(system, &s, &r, &moments))
}

/// Steps of an episode before its active-step rate is counted again
/// separately (the recalibration's burn-in).
pub(crate) const BURN_IN: usize = 100;

/// Standard normal quantiles `Φ⁻¹(q)` for `q` = 0.5, 0.1, 0.01, 0.001.
pub(crate) const NORMAL_QUANTILES: [(f64, f64); 4] = [
    (0.5, 0.0),
    (0.1, -1.281_551_565_544_600_5),
    (0.01, -2.326_347_874_040_840_8),
    (0.001, -3.090_232_306_167_813_5),
];

/// Summary of standardised conditions `z = (C_true − E[C]) / √Var[C]`: a
/// calibrated Gaussian predictive distribution gives mean 0, variance 1 and
/// `P(z < Φ⁻¹(q)) = q`.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub(crate) struct ZStats {
    pub n: usize,
    #[serde(with = "crate::exact")]
    pub sum: f64,
    #[serde(with = "crate::exact")]
    pub sum2: f64,
    /// Counts below each of [`NORMAL_QUANTILES`].
    pub below: [usize; 4],
    /// `Σ Φ(−E[C]/√Var[C])`: the violations the model expects.
    #[serde(with = "crate::exact")]
    pub expected: f64,
}

impl ZStats {
    fn push(&mut self, z: f64, predicted: f64) {
        self.n += 1;
        self.sum += z;
        self.sum2 += z * z;
        for (b, (_, zq)) in self.below.iter_mut().zip(NORMAL_QUANTILES) {
            *b += usize::from(z < zq);
        }
        self.expected += predicted;
    }
    /// Adds `o` into `self`.
    pub fn merge(&mut self, o: &ZStats) {
        self.n += o.n;
        self.sum += o.sum;
        self.sum2 += o.sum2;
        for (a, b) in self.below.iter_mut().zip(o.below) {
            *a += b;
        }
        self.expected += o.expected;
    }
    /// Mean and standard deviation.
    pub fn mean_sd(&self) -> (f64, f64) {
        if self.n == 0 {
            return (f64::NAN, f64::NAN);
        }
        let nf = self.n as f64;
        let mean = self.sum / nf;
        (mean, (self.sum2 / nf - mean * mean).max(0.0).sqrt())
    }
}

fn summarise(system: System, s: &Setup, r: &LoopResult, moments: &[(f64, f64)]) -> EpisodeStats {
    let b = s.barrier.as_ref();
    let mut st = EpisodeStats {
        steps: r.records.len(),
        min_h: r.min_barrier.first().copied().unwrap_or(f64::NAN),
        ..EpisodeStats::default()
    };
    for (k, rec) in r.records.iter().enumerate() {
        let finite = rec.is_finite();
        if !finite {
            st.non_finite += 1;
        }
        if rec.h_fine_min.iter().any(|&h| h < 0.0) {
            st.steps_h_violated += 1;
        }
        if rec.status == StepStatus::Infeasible {
            st.infeasible_steps += 1;
            continue;
        }
        st.solved_steps += 1;
        let Ok(c) = condition(s.truth.as_ref(), b, &rec.x, &rec.u) else {
            continue;
        };
        let violated = c < 0.0;
        st.cbc_violations += violated as usize;
        let active = rec.scbc.first().is_some_and(|&sl| sl <= ACTIVE_SLACK);
        if active {
            let next = r.records.get(k + 1).map_or(&r.final_state, |n| &n.x);
            if let Ok(c) = realised(s.truth.as_ref(), b, &rec.x, next) {
                st.realised_active_steps += 1;
                st.realised_active_violations += usize::from(c < 0.0);
            }
            st.active_steps += 1;
            st.active_violations += violated as usize;
            if k >= BURN_IN {
                st.active_steps_late += 1;
                st.active_violations_late += violated as usize;
            }
        }
        // the standard deviation the controller used
        let (mean, std) = moments[k];
        let std = std * rec.inflation.first().copied().unwrap_or(1.0);
        if std > 0.0 {
            let (z, q) = ((c - mean) / std, normal_cdf(-mean / std));
            st.z[0].push(z, q);
            if active {
                st.z[1].push(z, q);
            }
        }
    }
    if system == System::Vehicle {
        st.min_distance = r.min_monitor.first().copied();
        let reached = r
            .records
            .iter()
            .map(|rec| &rec.x)
            .chain(std::iter::once(&r.final_state))
            .any(|x| (x[0] - GOAL[0]).hypot(x[1] - GOAL[1]) < GOAL_TOL);
        st.goal_reached = Some(reached);
    }
    st
}

#[cfg(test)]
mod tests {
    use super::*;

    /// With the truth as the prior mean, no data and a negligible prior
    /// covariance (`A` = 1e-14 I; at relative degree 2 the mean of the
    /// condition includes `tr Cov(∇L_f h, F u̲)`), the model's mean of the
    /// condition is the true condition: the library's exact moments against
    /// [`true_condition`].
    #[test]
    fn true_condition_matches_the_moments_of_an_exact_model() {
        for system in [System::Vehicle, System::Pendulum] {
            let s = setup(system, TruthKind::MisSpecified, 3, 10).unwrap();
            let truth = s.truth.clone();
            let mut hyper = s.model.hyper().clone();
            hyper.A *= 1e-12;
            let model = Mvgp::new(
                s.model.state_dim(),
                s.model.control_dim(),
                hyper,
                PriorMean::System(truth.clone()),
                s.model.input_map().clone(),
            )
            .unwrap();
            let mut ws = MomentWorkspace::new(&model);
            let mut mom = ConditionMoments::zeros(model.control_dim());
            let cases: Vec<(Vec<f64>, Vec<f64>)> = match system {
                System::Vehicle => vec![
                    (vec![-1.0, 0.3, 0.2], vec![1.0, 0.5]),
                    (vec![0.4, -0.9, 2.0], vec![-0.7, 2.0]),
                ],
                System::Pendulum => {
                    vec![(vec![0.1, 0.8], vec![3.0]), (vec![-0.5, -1.5], vec![-7.0])]
                }
            };
            for (x, u) in cases {
                ws.update(&model, &x, s.barrier.relative_degree()).unwrap();
                cbc_moments(&mut ws, s.barrier.as_ref(), &mut mom).unwrap();
                let want = mom.mean(&u);
                let got = condition(truth.as_ref(), s.barrier.as_ref(), &x, &u).unwrap();
                assert!(
                    (got - want).abs() < 1e-5 * (1.0 + want.abs()),
                    "{system:?} at {x:?}, {u:?}: {got} vs {want}"
                );
            }
        }
    }
}
