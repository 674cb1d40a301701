//! Scenario files: everything a closed-loop run needs, in TOML.
//!
//! A scenario names the true system, the GP model (prior mean, kernel, input
//! map, initial `A`, `B`, `σ`), the online-learning schedule, the barriers,
//! an optional CLF, the safety controller, the reference (planner, ε-greedy
//! or constant), start, goal, `dt`, steps and seed. The built-in scenarios
//! are TOML files compiled into the binary (`bayes-cbf list`;
//! `bayes-cbf run NAME --print-config` prints one as a starting point).
//! `--set key=value` overrides any field (`controller.probability=0.9`,
//! `barriers.0.radius=0.5`); unknown keys are errors.

mod build;
mod run;

pub use build::{build, Built};
pub use run::{
    run_scenario, run_scenario_until, trajectory_csv, Column, Percentiles, RunOutput, RunSummary,
    RunWarning, Stats, TraceCov, Trajectory, TriggerSummary,
};

use crate::barrier_file::BarrierSpec;
use crate::error::{Context, Result};
use crate::input_map_spec::FeatureSpec;
use crate::params::Params;
use crate::prior_spec::PriorSpec;
use crate::{bail, err};
use bayes_cbf::control::RecalibrationSettings;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The built-in scenarios: (name, TOML text).
pub const BUILTIN: &[(&str, &str)] = &[
    ("pendulum-safe", include_str!("builtin/pendulum-safe.toml")),
    (
        "ackermann-mean-cbf",
        include_str!("builtin/ackermann-mean-cbf.toml"),
    ),
    (
        "ackermann-bayes-cbf",
        include_str!("builtin/ackermann-bayes-cbf.toml"),
    ),
    (
        "ackermann-no-learning",
        include_str!("builtin/ackermann-no-learning.toml"),
    ),
    (
        "ackermann-learning",
        include_str!("builtin/ackermann-learning.toml"),
    ),
    (
        "ackermann-self-triggered",
        include_str!("builtin/ackermann-self-triggered.toml"),
    ),
    (
        "double-integrator",
        include_str!("builtin/double-integrator.toml"),
    ),
    (
        "unicycle-obstacles",
        include_str!("builtin/unicycle-obstacles.toml"),
    ),
    (
        "cartpole-track",
        include_str!("builtin/cartpole-track.toml"),
    ),
    (
        "quadrotor-floor",
        include_str!("builtin/quadrotor-floor.toml"),
    ),
];

/// A closed-loop scenario. Only `[system]` is required; the defaults are
/// [`DEFAULT_DT`], [`DEFAULT_STEPS`], the origin as the start, the model
/// of [`GpSpec::default`], learning at every step
/// ([`LearningSpec::default`]), the controller of
/// [`ControllerSpec::default`] and a zero reference control (README, "Your
/// own robot").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    /// Name, used for the default output directory; [`load`] names a file
    /// without one by its stem.
    #[serde(default)]
    pub name: String,
    /// One line for `bayes-cbf list`.
    #[serde(default)]
    pub description: String,
    /// Seed of everything random in the run (random A, B, exploration, noise).
    #[serde(default)]
    pub seed: u64,
    /// Control period τ (s).
    #[serde(default = "default_dt")]
    pub dt: f64,
    /// Control steps.
    #[serde(default = "default_steps")]
    pub steps: usize,
    /// Initial state (default: the origin).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start: Option<Vec<f64>>,
    /// Half-widths of a uniform spread of the initial state, drawn from
    /// the seed: the run starts at `start + U[−spread, spread]` (seed
    /// sweeps then vary the start, not only the noise).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_spread: Option<Vec<f64>>,
    /// Goal state (vehicle scenarios).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub goal: Option<Vec<f64>>,
    /// The true system.
    pub system: PriorSpec,
    /// The GP model.
    #[serde(default)]
    pub gp: GpSpec,
    /// Online learning schedule.
    #[serde(default)]
    pub learning: LearningSpec,
    /// Barriers (same fields as barrier files).
    #[serde(default)]
    pub barriers: Vec<BarrierSpec>,
    /// Discs in the plane of the first two states that the barriers keep
    /// the robot out of, for the report (`min_obstacle_distance`,
    /// `collided`) and the figures. `disc` barriers on states 0 and 1 and
    /// `circle_heading` barriers add theirs; list here the obstacles of
    /// barriers written as expressions.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub obstacles: Vec<ObstacleSpec>,
    /// Optional control Lyapunov function.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clf: Option<ClfSpec>,
    /// The safety controller.
    #[serde(default)]
    pub controller: ControllerSpec,
    /// The reference (default: the zero control).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reference: Option<ReferenceSpec>,
    /// Integration.
    #[serde(default)]
    pub sim: SimSpec,
    /// Which outputs to write.
    #[serde(default)]
    pub outputs: OutputSpec,
    /// Self-triggered control (paper, Sec. V-B, VI-C).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub trigger: Option<TriggerSpec>,
}

/// Control period of a scenario that gives none (s).
pub const DEFAULT_DT: f64 = 0.01;
/// Control steps of a scenario that gives none (5 s at [`DEFAULT_DT`]).
pub const DEFAULT_STEPS: usize = 500;

fn default_dt() -> f64 {
    DEFAULT_DT
}
fn default_steps() -> usize {
    DEFAULT_STEPS
}

/// A disc in the plane of the first two states.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObstacleSpec {
    /// Centre.
    pub center: [f64; 2],
    /// Radius (> 0).
    pub radius: f64,
}

/// Self-triggering: Lipschitz bound of the learned dynamics on a cuboid
/// around the state (Lemma 3) and the hold `τ_k` (Props. 3 and 5).
///
/// Relative-degree-1 barriers use the controller's margin `controller.zeta`
/// as ζ (it must be > 0); barriers of relative degree ≥ 2 are shifted to
/// `h − zeta_b` in the SOCP. The SOCP probability becomes
/// `p + 2 delta_l` so that the interval guarantee is `controller.probability`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TriggerSpec {
    /// Side lengths of the cuboid around `x_k`, one per state coordinate.
    pub cuboid: Vec<f64>,
    /// δ_L: the Lipschitz bound holds with probability 1 − δ_L.
    #[serde(default = "default_delta_l")]
    pub delta_l: f64,
    /// Grid nodes per side (analytic mean term, numerical estimate, L_h).
    #[serde(default = "default_grid")]
    pub grid: usize,
    /// Sampled Jacobians per node for the numerical estimate (0: none).
    #[serde(default = "default_grid")]
    pub samples: usize,
    /// Shift ζ_b of barriers of relative degree ≥ 2.
    #[serde(default = "default_zeta_b")]
    pub zeta_b: f64,
    /// Shortest hold (s).
    #[serde(default = "default_tau_min")]
    pub tau_min: f64,
    /// Longest hold (s).
    #[serde(default = "default_tau_max")]
    pub tau_max: f64,
    /// `analytic` or `numerical`: the estimate that sets the hold.
    #[serde(default = "default_tau_from")]
    pub tau_from: String,
    /// Hold each control for τ_k (true), or keep the fixed period `dt` and
    /// only evaluate τ_k (false).
    #[serde(default = "yes")]
    pub self_triggered: bool,
    /// Solve a step whose τ_k falls below `tau_min` again with the margin
    /// that holds for `tau_min`
    /// ([`TriggerSettings::margin_for_tau_min`](bayes_cbf::control::TriggerSettings::margin_for_tau_min));
    /// false keeps `controller.zeta` at every step, as the paper does.
    #[serde(default = "yes")]
    pub margin_for_tau_min: bool,
}

fn default_delta_l() -> f64 {
    1e-4
}
fn default_grid() -> usize {
    10
}
fn default_zeta_b() -> f64 {
    1e-2
}
fn default_tau_min() -> f64 {
    1e-3
}
fn default_tau_max() -> f64 {
    0.1
}
fn default_tau_from() -> String {
    "analytic".into()
}
fn yes() -> bool {
    true
}

/// A covariance matrix given by structure.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum MatrixSpec {
    /// `scale · I`.
    Identity {
        /// Scale > 0.
        scale: f64,
    },
    /// `scale · (C Cᵀ / dim + I)` with `C` standard normal, drawn from the
    /// scenario seed: the paper's "randomly generated" A and B, kept well
    /// conditioned. (A nearly singular random `C Cᵀ` encodes a spurious,
    /// almost deterministic relation between `f` and `g` in the prior, and
    /// the pendulum then trusts a wrong-signed `g` before its first refit.)
    Random {
        /// Scale > 0.
        scale: f64,
    },
    /// Explicit rows.
    Rows {
        /// The matrix, an array of rows.
        rows: Vec<Vec<f64>>,
    },
}

/// A [`MatrixSpec`] given as a table (`{ type = "identity", scale = 1.0 }`,
/// …) or, for [`MatrixSpec::Rows`], as the matrix itself (`[[1.0, 0.0],
/// [0.0, 2.0]]`).
fn matrix_spec<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> std::result::Result<MatrixSpec, D::Error> {
    use serde::de::value::{MapAccessDeserializer, SeqAccessDeserializer};
    use serde::de::{MapAccess, SeqAccess, Visitor};
    struct Form;
    impl<'de> Visitor<'de> for Form {
        type Value = MatrixSpec;
        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            f.write_str(
                "a matrix (an array of rows, e.g. [[1.0, 0.0], [0.0, 1.0]]) or a table \
                 { type = \"identity\", scale = … }, { type = \"random\", scale = … } or \
                 { type = \"rows\", rows = [[…], …] }",
            )
        }
        fn visit_seq<A: SeqAccess<'de>>(self, seq: A) -> std::result::Result<MatrixSpec, A::Error> {
            let rows = Vec::<Vec<f64>>::deserialize(SeqAccessDeserializer::new(seq))?;
            Ok(MatrixSpec::Rows { rows })
        }
        fn visit_map<A: MapAccess<'de>>(self, map: A) -> std::result::Result<MatrixSpec, A::Error> {
            MatrixSpec::deserialize(MapAccessDeserializer::new(map))
        }
    }
    d.deserialize_any(Form)
}

/// The GP model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GpSpec {
    /// Prior mean (`"zero"` or a parametric model).
    #[serde(default)]
    pub prior_mean: PriorSpec,
    /// What the kernel sees (default: the whole state).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub input_map: Option<Vec<FeatureSpec>>,
    /// RBF lengthscales, one per kernel input (default: 1 each).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lengthscales: Option<Vec<f64>>,
    /// RBF variance.
    #[serde(default = "one")]
    pub kernel_variance: f64,
    /// Row covariance `A` (n × n): a table, or the matrix itself
    /// (default: the identity).
    #[serde(rename = "A", deserialize_with = "matrix_spec", default = "identity")]
    pub a: MatrixSpec,
    /// Column covariance `B` ((1+m) × (1+m)): a table, or the matrix
    /// itself (default: the identity).
    #[serde(rename = "B", deserialize_with = "matrix_spec", default = "identity")]
    pub b: MatrixSpec,
    /// Noise scale σ (noise covariance σ²A; default
    /// [`DEFAULT_NOISE_SIGMA`]).
    #[serde(default = "default_noise_sigma")]
    pub noise_sigma: f64,
    /// Rows of `F` known exactly from the prior mean (e.g. `[0]` for a
    /// pendulum's `θ̇ = ω`); only the others are learned.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub known_rows: Vec<usize>,
    /// Replace the model by the true system, a check of the scenario's
    /// design apart from learning: the prior mean is `[system]`, `B` is
    /// [`ORACLE_VARIANCE`]` · I` (next to no uncertainty) and nothing is
    /// learned (the `learning` schedule is ignored; the scenario's own
    /// prior mean, `B` and learning settings are still checked). An
    /// infeasible step of such a run is one where the barriers, gains and
    /// bounds conflict for the true system, and the fallback decides it;
    /// an unsafe run is a design that fails given the true dynamics, which
    /// a learning run survives only by the margin its model's spread adds.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub oracle: bool,
}

impl Default for GpSpec {
    /// A zero prior mean, the RBF kernel on the whole state with unit
    /// lengthscales and variance, `A = I`, `B = I`, `σ =`
    /// [`DEFAULT_NOISE_SIGMA`], no known rows.
    fn default() -> Self {
        Self {
            prior_mean: PriorSpec::default(),
            input_map: None,
            lengthscales: None,
            kernel_variance: 1.0,
            a: identity(),
            b: identity(),
            noise_sigma: DEFAULT_NOISE_SIGMA,
            known_rows: Vec::new(),
            oracle: false,
        }
    }
}

/// The model's noise scale `σ` when a scenario gives none: with `A = I`, a
/// standard deviation of 0.1 on each learned row of `ẋ`.
pub const DEFAULT_NOISE_SIGMA: f64 = 0.1;

fn default_noise_sigma() -> f64 {
    DEFAULT_NOISE_SIGMA
}
fn identity() -> MatrixSpec {
    MatrixSpec::Identity { scale: 1.0 }
}

/// `B` of the oracle model ([`GpSpec::oracle`]) as a multiple of the
/// identity: the conditions' spread is ~1e-6 of their scale.
pub const ORACLE_VARIANCE: f64 = 1e-12;

fn one() -> f64 {
    1.0
}

/// Online learning schedule.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LearningSpec {
    /// Add buffered observations every this many steps (0: never; default 1).
    pub update_every: usize,
    /// Refit hyperparameters every this many steps (0: never).
    pub refit_every: usize,
    /// Also refit at 4, 8, 16, … observations below `refit_every`.
    pub refit_geometric: bool,
    /// Run refits on a background thread, swapping the new hyperparameters
    /// in this many steps after each refit is due (0: synchronous refits).
    pub refit_background: usize,
    /// Sliding window (0: unbounded).
    pub window: usize,
    /// Budget of the most informative observations (0: unbounded); exclusive
    /// with `window`.
    pub budget: usize,
    /// Noise floor of the refits: `σ·√A₀₀ ≥ sigma_min`
    /// ([`bayes_cbf::gp::FitSettings::sigma_min`]).
    pub sigma_min: f64,
    /// L-BFGS iterations per refit.
    pub max_iters: u64,
    /// Structure of A in refits: full, diag or an integer rank.
    pub rank_a: String,
    /// Structure of B in refits.
    pub rank_b: String,
    /// Noise on the measured ẋ.
    pub xdot_noise: f64,
    /// Recalibrate the barrier conditions' variances online after every
    /// model update (`bayes_cbf::control::Recalibrator`); on by default.
    pub recalibrate: bool,
    /// Step size `η` of the recalibration's `log κ`.
    pub recalibration_rate: f64,
}

impl Default for LearningSpec {
    /// Learning from every step (an observation each), no refits, all data
    /// kept, recalibration on.
    fn default() -> Self {
        Self {
            update_every: 1,
            refit_every: 0,
            refit_geometric: false,
            refit_background: 0,
            window: 0,
            budget: 0,
            sigma_min: 0.0,
            max_iters: 50,
            rank_a: "full".into(),
            rank_b: "full".into(),
            xdot_noise: 0.0,
            recalibrate: true,
            recalibration_rate: RecalibrationSettings::default().rate,
        }
    }
}

/// A control Lyapunov function.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum ClfSpec {
    /// `V = w1/2 ρ² + w2 (1 − cos α)` (paper, Sec. VII-B).
    Ackermann {
        /// Distance weight.
        w1: f64,
        /// Heading weight.
        w2: f64,
        /// Decay rate γ_V.
        gamma: f64,
    },
    /// `V` written as an expression over the state names and the
    /// reference names `<state>_d`.
    Expression {
        /// `V(x, x_d)`.
        #[serde(rename = "V")]
        v: String,
        /// Named constants.
        #[serde(default, skip_serializing_if = "Params::is_empty")]
        params: Params,
        /// Decay rate γ_V (default 1).
        #[serde(default = "one")]
        gamma: f64,
    },
}

impl ClfSpec {
    /// Builds the library CLF for a system whose states are named `state`,
    /// validating every field.
    pub fn build(
        &self,
        state: &[String],
    ) -> Result<std::sync::Arc<dyn bayes_cbf::barrier::DynLyapunov>> {
        let n = state.len();
        match self {
            ClfSpec::Expression { v, params, gamma } => {
                let params = params.pairs();
                Ok(std::sync::Arc::new(
                    bayes_cbf::barrier::ExpressionClf::new(state, &params, v, *gamma)
                        .map_err(|e| err!("clf: {e}"))?,
                ))
            }
            ClfSpec::Ackermann { w1, w2, gamma } => {
                if n != 3 {
                    bail!("clf: the ackermann CLF needs a 3-state system");
                }
                Ok(std::sync::Arc::new(
                    bayes_cbf::barrier::AckermannClf::new(*w1, *w2, *gamma)
                        .map_err(|e| err!("clf: {e}"))?,
                ))
            }
        }
    }
}

/// The safety controller.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControllerSpec {
    /// Required probability p of each stochastic condition (default
    /// [`DEFAULT_PROBABILITY`]).
    #[serde(default = "default_probability")]
    pub probability: f64,
    /// Margin ζ.
    #[serde(default)]
    pub zeta: f64,
    /// CLF slack weight λ.
    #[serde(default = "one")]
    pub lambda: f64,
    /// Diagonal of the objective weight R (default identity).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub r: Option<Vec<f64>>,
    /// Lower control bounds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub u_min: Option<Vec<f64>>,
    /// Upper control bounds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub u_max: Option<Vec<f64>>,
    /// relax, max_margin, brake or hold; [`fallback_name`](Self::fallback_name)
    /// when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fallback: Option<String>,
    /// Promise each barrier condition as realised over the step,
    /// the model's observation noise included
    /// ([`bayes_cbf::control::SafetySettings::predictive`]); on by default,
    /// `false` for the paper's condition on the latent `F`.
    #[serde(default = "yes", skip_serializing_if = "is_true")]
    pub predictive: bool,
}

/// The probability `p` of a scenario that gives none.
pub const DEFAULT_PROBABILITY: f64 = 0.99;

fn default_probability() -> f64 {
    DEFAULT_PROBABILITY
}

impl Default for ControllerSpec {
    /// `p =` [`DEFAULT_PROBABILITY`], `ζ = 0`, `λ = 1`, `R = I`, no
    /// bounds, the fallback of [`fallback_name`](Self::fallback_name), the
    /// predictive condition.
    fn default() -> Self {
        Self {
            probability: DEFAULT_PROBABILITY,
            zeta: 0.0,
            lambda: 1.0,
            r: None,
            u_min: None,
            u_max: None,
            fallback: None,
            predictive: true,
        }
    }
}

impl ControllerSpec {
    /// The fallback: the one given, else `relax` (the largest feasible
    /// probability, which brakes where max-margin trades the mean for the
    /// spread of an uncertain input gain; docs/robots.md) with input bounds
    /// and `max_margin` without (where relax's `p*` can be reached only by
    /// an unbounded control).
    pub fn fallback_name(&self) -> &str {
        match &self.fallback {
            Some(f) => f,
            None if self.u_min.is_some() && self.u_max.is_some() => "relax",
            None => "max_margin",
        }
    }
}

fn is_true(b: &bool) -> bool {
    *b
}

/// The reference.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum ReferenceSpec {
    /// Straight line from start to goal in `duration` seconds, û = 0.
    Planner {
        /// Duration (s).
        duration: f64,
    },
    /// `û ~ (1 − ε_k) δ_0 + ε_k U[lo, hi]`, `ε_k = 10^(−k/decay)`.
    EpsilonGreedy {
        /// Lower end.
        lo: Vec<f64>,
        /// Upper end.
        hi: Vec<f64>,
        /// Steps per decade.
        decay: f64,
    },
    /// A constant reference control.
    Constant {
        /// The control.
        u: Vec<f64>,
    },
    /// Linear state feedback `û = u0 + K (target − x)` (the system's angles
    /// differenced on the circle): a nominal PD-type controller.
    Feedback {
        /// Feed-forward control `u0`.
        u0: Vec<f64>,
        /// Gain `K`, one row per control of one entry per state.
        gain: Vec<Vec<f64>>,
        /// Target state.
        target: Vec<f64>,
    },
}

/// Integration settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimSpec {
    /// RK4 step of the fine grid (s).
    pub internal_step: f64,
    /// Process noise intensity.
    pub process_noise: f64,
}

impl Default for SimSpec {
    fn default() -> Self {
        Self {
            internal_step: 1e-3,
            process_noise: 0.0,
        }
    }
}

/// Outputs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OutputSpec {
    /// Write PNG figures.
    pub plots: bool,
    /// Write animation.gif (vehicle scenarios).
    pub animation: bool,
}

impl Default for OutputSpec {
    fn default() -> Self {
        Self {
            plots: true,
            animation: true,
        }
    }
}

/// The scenario with its system, prior mean and barriers restated in the
/// expression language ([`PriorSpec::to_expression`],
/// [`BarrierSpec::to_expression`]); the CLF, controller and everything
/// else unchanged. The run is the same up to rounding (tests/expressions.rs).
pub fn as_expressions(s: &Scenario) -> Result<Scenario> {
    let mut out = s.clone();
    let names = s
        .system
        .names()
        .ok_or_else(|| err!("system: a true system is required"))?;
    if let Some(e) = s.system.to_expression() {
        out.system = PriorSpec::Expression(e);
    }
    if let Some(mut e) = s.gp.prior_mean.to_expression() {
        // inside a scenario the prior takes the system's names
        e.state = None;
        e.control = None;
        out.gp.prior_mean = PriorSpec::Expression(e);
    }
    out.barriers = s
        .barriers
        .iter()
        .enumerate()
        .map(|(i, b)| {
            b.to_expression(&names.0)
                .with_context(|| format!("barriers[{i}]"))
        })
        .collect::<Result<_>>()?;
    Ok(out)
}

/// Validates a scenario completely (everything a run would check before
/// starting).
pub fn validate(s: &Scenario) -> Result<()> {
    build::build(s).map(|_| ())
}

/// Checks scenario `name` with overrides `sets` as a sweep does before its
/// runs: it [`load`]s and [`validate`]s at the seed the overrides give,
/// so that a bad setting (`dt = -1`, a probability of 2, a start of the
/// wrong length) is one error, not every seed's. A failure that belongs to
/// that seed (an expression not finite at its start, a numerical failure)
/// passes: it is the outcome of that seed's run, and other seeds may run.
pub fn check(name: &str, sets: &[String]) -> Result<()> {
    let _warnings = bayes_cbf::warnings::Scope::enter();
    let (s, _) = load(name, sets)?;
    match validate(&s) {
        Err(e) if !seed_specific(&e) => Err(e),
        _ => Ok(()),
    }
}

/// An error that a run can meet at one seed and not at another: a user
/// function that fails at a state, or a numerical failure.
fn seed_specific(e: &crate::Error) -> bool {
    use crate::Error;
    use bayes_cbf::{Error as Core, InputError};
    matches!(
        e.root(),
        Error::Core(Core::Input(InputError::Evaluation(_)) | Core::Gp(_) | Core::Control(_))
    )
}

/// Applies `key=value` to a TOML table; `key` is a dotted path whose numeric
/// segments index arrays; `value` is a TOML literal (strings may be bare)
/// or a JSON object (as Python's `json.dumps` writes a dict).
/// A key the file leaves out (a field with a default, an optional section)
/// is added, and the typed parse judges it: an unknown one is refused there,
/// with the list of the known ones.
pub fn apply_set(table: &mut toml::Table, assignment: &str) -> Result<()> {
    let (key, value) = assignment
        .split_once('=')
        .ok_or_else(|| err!("override '{assignment}': expected key=value"))?;
    let key = key.trim();
    if key.is_empty() {
        bail!("override '{assignment}': empty key");
    }
    let text = value.trim();
    let value: toml::Value = match format!("v = {text}").parse::<toml::Table>() {
        Ok(mut t) => t.remove("v").unwrap_or(toml::Value::String(text.into())),
        Err(_) if is_integer(text) && text.parse::<i64>().is_ok() => {
            bail!("override '{key}': {text}: an integer is written without leading zeros (TOML)")
        }
        Err(_) if is_integer(text) => bail!(
            "override '{key}': {text} is outside the range of integers \
             (-9223372036854775808 to 9223372036854775807)"
        ),
        // a number TOML spells otherwise (.5, 5., 1E3, +.5)
        Err(_) if text.parse::<f64>().is_ok_and(f64::is_finite) => {
            toml::Value::Float(text.parse::<f64>().unwrap_or_default())
        }
        // a JSON array (Python's json.dumps of a list of dicts), else a
        // malformed list
        Err(e) if text.starts_with('[') => match serde_json::from_str::<serde_json::Value>(text) {
            Ok(json) => toml::Value::try_from(json).map_err(|_| {
                err!("override '{key}': {text}: a null (Python's None) has no value here")
            })?,
            Err(_) => bail!(
                "override '{key}': {text} is not a TOML array: {} (lists are written \
                 [1.0, 2.0], strings in them quoted)",
                e.message().trim_end()
            ),
        },
        Err(_) if text.starts_with('{') => match serde_json::from_str::<serde_json::Value>(text) {
            Ok(json) => {
                toml::Value::try_from(json).map_err(|e| err!("override '{key}': {text}: {e}"))?
            }
            Err(_) => toml::Value::String(text.to_string()),
        },
        Err(_) => toml::Value::String(text.to_string()),
    };
    let parts: Vec<&str> = key.split('.').collect();
    let mut cur = table
        .entry(parts[0])
        .or_insert_with(|| toml::Value::Table(toml::Table::new()));
    if parts.len() == 1 {
        *cur = value;
        return Ok(());
    }
    for (i, part) in parts.iter().enumerate().skip(1) {
        let path = parts[..i].join(".");
        cur = match cur {
            toml::Value::Table(t) => {
                if !t.contains_key(*part) && i + 1 == parts.len() {
                    // a new leaf: accepted here, judged by the typed parse
                    t.insert((*part).to_string(), value.clone());
                    return Ok(());
                }
                // a table the file leaves out (a defaulted `gp.A`): added,
                // and judged by the typed parse
                t.entry(*part)
                    .or_insert_with(|| toml::Value::Table(toml::Table::new()))
            }
            toml::Value::Array(a) => {
                let idx: usize = part.parse().map_err(|_| {
                    err!("override '{key}': '{path}' is an array; '{part}' is not an index")
                })?;
                let len = a.len();
                a.get_mut(idx).ok_or_else(|| {
                    err!("override '{key}': index {idx} out of range ('{path}' has {len} entries)")
                })?
            }
            _ => bail!("override '{key}': '{path}' is a value, not a table"),
        };
    }
    *cur = value;
    Ok(())
}

/// An optional sign and decimal digits only.
fn is_integer(text: &str) -> bool {
    let digits = text.strip_prefix(['-', '+']).unwrap_or(text);
    !digits.is_empty() && digits.bytes().all(|b| b.is_ascii_digit())
}

/// The TOML text of a built-in scenario, or of the file at `name`.
pub fn scenario_text(name: &str) -> Result<(String, String)> {
    if let Some((n, t)) = BUILTIN.iter().find(|(n, _)| *n == name) {
        return Ok((n.to_string(), t.to_string()));
    }
    let path = Path::new(name);
    if path.is_file() {
        let text = crate::io::read_input_text(path)
            .with_context(|| format!("cannot read scenario file '{name}'"))?;
        return Ok((name.to_string(), crate::parse::strip_bom(&text).to_string()));
    }
    if path.is_dir() {
        bail!("scenario '{name}' is a directory, not a scenario file");
    }
    if crate::experiments::EXPERIMENTS
        .iter()
        .any(|(n, _)| *n == name)
    {
        bail!("'{name}' is an experiment, not a closed-loop scenario");
    }
    let names: Vec<&str> = BUILTIN.iter().map(|(n, _)| *n).collect();
    let experiments: Vec<&str> = crate::experiments::EXPERIMENTS
        .iter()
        .map(|(n, _)| *n)
        .collect();
    bail!(
        "unknown scenario '{name}': not a built-in ({}), an experiment ({}) nor an existing file",
        names.join(", "),
        experiments.join(", ")
    )
}

/// The message of a TOML parse error on one line, with the Rust types that
/// serde names in it (`expected usize`) in words.
fn message(e: &toml::de::Error) -> String {
    crate::parse::in_words(&e.message().replace('\n', " "))
}

/// One-line rendering of a TOML parse error, with the line it points at.
fn toml_error(source: &str, text: &str, e: &toml::de::Error) -> crate::error::Error {
    let msg = message(e);
    match e.span() {
        // a field missing at the top level: the span is the whole file
        Some(span) if span.start == 0 && msg.starts_with("missing field") => {
            err!("scenario '{source}': {msg} at the top level")
        }
        Some(span) => {
            let line_no = text[..span.start.min(text.len())].matches('\n').count() + 1;
            let line = text.lines().nth(line_no - 1).unwrap_or("").trim();
            // a long line (a generated expression) is quoted by its start
            let quoted: String = if line.chars().count() > 120 {
                line.chars().take(117).chain("...".chars()).collect()
            } else {
                line.to_string()
            };
            err!("scenario '{source}' line {line_no} (`{quoted}`): {msg}")
        }
        None => err!("scenario '{source}': {msg}"),
    }
}

/// Loads a scenario by built-in name or path, applies the overrides, and
/// parses it strictly. Returns the scenario and its merged TOML text.
pub fn load(name: &str, sets: &[String]) -> Result<(Scenario, String)> {
    let (source, text, table) = table_with(name, sets)?;
    let merged = if sets.is_empty() {
        text.clone()
    } else {
        toml::to_string(&table).context("cannot render the scenario")?
    };
    let mut scenario: Scenario = match toml::from_str(&merged) {
        Ok(s) => s,
        Err(e) if sets.is_empty() => return Err(toml_error(&source, &text, &e)),
        Err(e) => return Err(blame(&source, &text, sets, &e)),
    };
    if scenario.name.is_empty() {
        // a file that names no scenario: its stem
        scenario.name = Path::new(&source)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
    }
    Ok((scenario, merged))
}

/// The text of scenario `name` (built-in or file), its source and its
/// TOML table with the overrides `sets` applied.
fn table_with(name: &str, sets: &[String]) -> Result<(String, String, toml::Table)> {
    let (source, text) = scenario_text(name)?;
    if text.trim().is_empty() {
        bail!("scenario '{source}' is empty");
    }
    let mut table: toml::Table = text
        .parse()
        .map_err(|e: toml::de::Error| toml_error(&source, &text, &e))?;
    for s in sets {
        apply_set(&mut table, s)?;
    }
    Ok((source, text, table))
}

/// A digest of what scenario `name` with overrides `sets` says: 64-bit
/// FNV-1a of its table rendered as TOML (comments, layout and the order of
/// keys left out), in hex. Two spellings of one file's path give the same
/// digest; a file edited in a field gives another. A sweep records it so
/// that its shards are known to have run the same scenario
/// ([`crate::sweep::SweepMeta`]).
pub fn digest(name: &str, sets: &[String]) -> Result<String> {
    let (_, _, table) = table_with(name, sets)?;
    let text = toml::to_string(&table).context("cannot render the scenario")?;
    let hash = text.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    });
    Ok(format!("{hash:016x}"))
}

/// The default output directory of a scenario named `name`:
/// `runs/<name><suffix>`. The name must be one plain path component (no
/// `/`, not empty, `.` or `..`), so that the outputs stay below `runs/`.
pub fn default_out_dir(name: &str, suffix: &str) -> Result<std::path::PathBuf> {
    use std::path::Component;
    let mut parts = Path::new(name).components();
    match (parts.next(), parts.next()) {
        (Some(Component::Normal(n)), None) if n == name => {
            Ok(Path::new("runs").join(format!("{name}{suffix}")))
        }
        _ => bail!(
            "name = {name:?} cannot name the output directory runs/<name> (it must be one \
             path component, without '/'): give --out, or rename the scenario"
        ),
    }
}

/// The error of a scenario that its overrides make invalid, told against
/// what the user wrote: the file's own error with its line, or the `--set`
/// after which the scenario stopped parsing and no later one repaired it
/// (the merged text's lines are in no file).
fn blame(
    source: &str,
    text: &str,
    sets: &[String],
    merged: &toml::de::Error,
) -> crate::error::Error {
    if let Err(e) = toml::from_str::<Scenario>(text) {
        return toml_error(source, text, &e);
    }
    let Ok(mut table) = text.parse::<toml::Table>() else {
        return err!("scenario '{source}': {}", message(merged));
    };
    let mut culprit: Option<(&String, toml::de::Error)> = None;
    for s in sets {
        if apply_set(&mut table, s).is_err() {
            break;
        }
        let rendered = toml::to_string(&table).unwrap_or_default();
        match toml::from_str::<Scenario>(&rendered) {
            Err(e) if culprit.is_none() => culprit = Some((s, e)),
            Err(_) => {}
            Ok(_) => culprit = None,
        }
    }
    match culprit {
        Some((s, e)) => err!("scenario '{source}', override `{s}`: {}", message(&e)),
        None => err!("scenario '{source}': {}", message(merged)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The error of loading `scenario` with the one override `set`.
    fn refusal(scenario: &str, set: &str) -> String {
        format!("{:#}", load(scenario, &[set.into()]).unwrap_err())
    }

    #[test]
    fn builtins_parse_and_round_trip() {
        for (name, _) in BUILTIN {
            let (s, _) = load(name, &[]).unwrap();
            assert_eq!(&s.name, name);
            let again: Scenario = toml::from_str(&toml::to_string(&s).unwrap()).unwrap();
            assert_eq!(again, s);
        }
    }

    /// A scenario that does not say promises the conditions as realised
    /// (predictive); the built-ins keep the paper's latent condition, and
    /// the setting survives a round trip and reaches the controller.
    #[test]
    fn conditions_are_predictive_unless_a_scenario_says_otherwise() {
        for (name, _) in BUILTIN {
            let (s, _) = load(name, &[]).unwrap();
            assert!(!s.controller.predictive, "{name}");
        }
        let text = scenario_text("pendulum-safe").unwrap().1;
        let unsaid = text.replace("predictive = false\n", "");
        assert_ne!(unsaid, text);
        let s: Scenario = toml::from_str(&unsaid).unwrap();
        assert!(s.controller.predictive);
        let shown = toml::to_string(&s).unwrap();
        assert!(!shown.contains("predictive"), "the default is not written");
        assert_eq!(toml::from_str::<Scenario>(&shown).unwrap(), s);
        let (latent, _) = load("pendulum-safe", &[]).unwrap();
        for (sc, want) in [(&s, true), (&latent, false)] {
            let built = build::build(sc).unwrap();
            assert_eq!(built.controller.settings().predictive, want);
        }
    }

    /// A crossing in a feasible step is reported when its state lies
    /// outside the set the gains keep (`ψ₁ < 0`), with the infeasible steps
    /// of its way out of that set, and not when the state was inside it (a crossing by
    /// chance, or by noise).
    #[test]
    fn a_feasible_crossing_from_outside_the_kept_set_is_found() {
        use bayes_cbf::sim::{DataPolicy, StepRecord, StepStatus};
        let (sc, _) = load("double-integrator", &[]).unwrap();
        let built = build::build(&sc).unwrap();
        // h = 1 − p, gains [1, 2]: λ = 1, ψ₁ = −v + (1 − p) for the true drift
        let step = |t: f64, x: [f64; 2], h_fine_min: f64, status: StepStatus| StepRecord {
            t,
            x: x.to_vec(),
            u: vec![0.0],
            u_ref: vec![0.0],
            h: vec![1.0 - x[0]],
            h_fine_min: vec![h_fine_min],
            scbc: vec![0.0],
            sclc: None,
            trace_cov: 0.0,
            status,
            p_star: None,
            control_us: 0.0,
            data_size: 0,
            refit: false,
            monitors: vec![],
            hold: 0.01,
            trigger: None,
            inflation: vec![],
        };
        let find = |records: &[StepRecord]| {
            build::crossings_outside(&built.barriers, built.truth.as_ref(), records)
                .into_iter()
                .next()
        };
        let infeasible = step(0.0, [0.0, 0.5], 0.9, StepStatus::Infeasible);
        // fast towards the wall, 1 mm short of it: ψ₁ = −2 + 0.001 < 0
        let fast = step(0.01, [0.999, 2.0], -0.01, StepStatus::Optimal);
        let (i, t, psi, before) = find(&[infeasible.clone(), fast.clone()]).unwrap();
        assert_eq!((i, t, before), (0, 0.01, 1));
        assert!((psi - (-2.0 + 0.001)).abs() < 1e-12, "{psi}");
        // at rest by the wall: ψ₁ > 0, a crossing the report leaves alone
        let slow = step(0.01, [0.999, 0.0], -0.0001, StepStatus::Optimal);
        assert_eq!(find(&[infeasible.clone(), slow.clone()]), None);
        // ... but not one that comes after it, whose count is that of its
        // own way out of the set (the step that left it), not the run's
        let later = StepRecord {
            t: 0.02,
            ..fast.clone()
        };
        let found = find(&[
            infeasible.clone(),
            slow.clone(),
            infeasible.clone(),
            later.clone(),
        ]);
        assert_eq!(found.map(|f| (f.1, f.3)), Some((0.02, 1)));
        let found = find(&[infeasible.clone(), slow, later]);
        assert_eq!(found.map(|f| (f.1, f.3)), Some((0.02, 0)));
        // the same fast crossing in an infeasible step is the fallback's,
        // and is found as such
        let fallback = step(0.01, [0.999, 2.0], -0.01, StepStatus::Infeasible);
        assert_eq!(find(&[infeasible.clone(), fallback.clone()]), None);
        let in_infeasible = |records: &[StepRecord]| {
            build::crossing_in_infeasible_step(1, records).map(|(i, r)| (i, r.t))
        };
        assert_eq!(
            in_infeasible(&[infeasible.clone(), fallback]),
            Some((0, 0.01))
        );
        assert_eq!(in_infeasible(&[infeasible.clone(), fast.clone()]), None);
        // an infeasible step that starts below zero did not cross
        let below = step(0.01, [1.1, 0.0], -0.2, StepStatus::Infeasible);
        assert_eq!(in_infeasible(&[infeasible.clone(), below]), None);
        // two barriers that both crossed from outside: both are found
        let twice = |r: &StepRecord| StepRecord {
            h: vec![r.h[0]; 2],
            h_fine_min: vec![r.h_fine_min[0]; 2],
            scbc: vec![0.0; 2],
            ..r.clone()
        };
        let barriers = [built.barriers[0].clone(), built.barriers[0].clone()];
        let records = [twice(&infeasible), twice(&fast)];
        let found = build::crossings_outside(&barriers, built.truth.as_ref(), &records);
        let which: Vec<(usize, f64)> = found.iter().map(|f| (f.0, f.1)).collect();
        assert_eq!(which, [(0, 0.01), (1, 0.01)]);
        // a crossing in an infeasible step after the data window filled,
        // with the model's spread risen threefold within 10 steps, names the
        // window; with a budget, a window not yet full, a spread as low as
        // before or one that rose as gradually as a moving state's does not
        let crossing = step(0.01, [0.999, 2.0], -0.01, StepStatus::Infeasible);
        let at = |data_size: usize, trace_cov: f64, r: &StepRecord| StepRecord {
            data_size,
            trace_cov,
            ..r.clone()
        };
        let forgot = |data, records: &[StepRecord]| {
            build::window_forgot(data, records, &records[records.len() - 1])
        };
        let window = DataPolicy::Window(300);
        let grown = [at(299, 0.05, &infeasible), at(300, 0.5, &crossing)];
        let clause = forgot(window, &grown).unwrap();
        assert!(
            clause.contains("(learning.window = 300)")
                && clause.contains("tr Σ = 0.050 to 0.500")
                && clause.contains("learning.budget = 300"),
            "{clause}"
        );
        assert_eq!(forgot(DataPolicy::Budget(300), &grown), None);
        assert_eq!(forgot(DataPolicy::All, &grown), None);
        let filling = [at(298, 0.05, &infeasible), at(299, 0.5, &crossing)];
        assert_eq!(forgot(window, &filling), None);
        let steady = [at(299, 0.05, &infeasible), at(300, 0.1, &crossing)];
        assert_eq!(forgot(window, &steady), None);
        // 10 % a step for 30 steps: 17-fold in all, 2.6-fold over any 10
        let mut gradual: Vec<StepRecord> = (0..30)
            .map(|i| at(300, 0.05 * 1.1f64.powi(i), &infeasible))
            .collect();
        gradual.push(at(300, 0.05 * 1.1f64.powi(30), &crossing));
        assert_eq!(forgot(window, &gradual), None);
        // the same with one step's jump in it is found, with that jump
        gradual[20].trace_cov = 0.05 * 1.1f64.powi(11) * 4.0;
        let clause = forgot(window, &gradual).unwrap();
        assert!(clause.contains("within 10 steps"), "{clause}");
    }

    /// Only `[system]` is required: the name is the file's stem, and the
    /// step, horizon, start, model, controller and reference take the
    /// documented defaults; the scenario of `interfaces.md` runs as
    /// written there.
    #[test]
    fn a_scenario_of_a_system_alone_takes_the_defaults() {
        let dir = std::env::temp_dir().join(format!("bcbf-defaults-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("just-a-pendulum.toml");
        std::fs::write(
            &file,
            "[system]\ntype = \"pendulum\"\nmass = 1.0\nlength = 1.0\ngravity = 10.0\n",
        )
        .unwrap();
        let (s, _) = load(file.to_str().unwrap(), &[]).unwrap();
        assert_eq!(s.name, "just-a-pendulum");
        assert_eq!((s.dt, s.steps), (DEFAULT_DT, DEFAULT_STEPS));
        assert_eq!(s.gp, GpSpec::default());
        assert_eq!(s.controller, ControllerSpec::default());
        // a robot that learns, and relaxes p where nothing is feasible when
        // its inputs are bounded
        assert_eq!(s.learning.update_every, 1);
        assert_eq!(s.controller.fallback_name(), "max_margin");
        let (bounded, _) = load(
            file.to_str().unwrap(),
            &[
                "controller.u_min=[-1.0]".into(),
                "controller.u_max=[1.0]".into(),
            ],
        )
        .unwrap();
        assert_eq!(bounded.controller.fallback_name(), "relax");
        let built = build::build(&s).unwrap();
        assert_eq!(built.start, vec![0.0, 0.0]);
        let hyper = built.model.hyper();
        assert_eq!(hyper.kernel.lengthscales(), &[1.0, 1.0]);
        assert_eq!(hyper.sigma, DEFAULT_NOISE_SIGMA);
        assert_eq!(hyper.A, nalgebra::DMatrix::identity(2, 2));
        assert_eq!(hyper.B, nalgebra::DMatrix::identity(2, 2));
        assert_eq!(built.controller.settings().probability, DEFAULT_PROBABILITY);
        // the lengthscales default to the kernel's inputs, not the state's
        let (s, _) = load(
            file.to_str().unwrap(),
            &["gp.input_map=[{ cos = 0 }, { sin = 0 }, 1]".into()],
        )
        .unwrap();
        let built = build::build(&s).unwrap();
        assert_eq!(built.model.hyper().kernel.lengthscales(), &[1.0; 3]);
        // the zero reference control, at every state
        let (s, _) = load(file.to_str().unwrap(), &["steps=3".into()]).unwrap();
        let out = run::run_scenario(&s, |_, _| {}).unwrap();
        assert!(out.result.records.iter().all(|r| r.u_ref == [0.0]));
        // interfaces.md's [system], [gp] and [[barriers]], as written there
        let spec = "[system]\ntype = \"expression\"\nstate = [\"theta\", \"omega\"]\n\
            control = [\"u\"]\nparams = { m = 1.0, l = 1.0, g = 10.0 }\n\
            f = [\"omega\", \"-g/l*sin(theta)\"]\ng = [[\"0\"], [\"1/(m*l^2)\"]]\n\
            angles = [\"theta\"]\n\n[gp]\nprior_mean = { type = \"expression\", params = \
            { l = 2.0 }, f = [\"omega\", \"-10/l*sin(theta)\"], g = [[\"0\"], [\"1/l^2\"]] }\n\
            known_rows = [0]\n\n[[barriers]]\ntype = \"expression\"\n\
            h = \"cos(0.3927) - cos(theta - 0.7854)\"\nrelative_degree = 2\nk_alpha = [1.0, 3.0]\n";
        let file = dir.join("spec.toml");
        std::fs::write(&file, spec).unwrap();
        let (s, _) = load(file.to_str().unwrap(), &["steps=3".into()]).unwrap();
        assert_eq!(
            run::run_scenario(&s, |_, _| {})
                .unwrap()
                .result
                .records
                .len(),
            3
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn unknown_names_list_the_scenarios_and_experiments() {
        let e = load("no-such", &[]).unwrap_err().to_string();
        assert!(
            e.contains("double-integrator") && e.contains("calibration"),
            "{e}"
        );
        let e = load("calibration", &[]).unwrap_err().to_string();
        assert!(e.contains("is an experiment"), "{e}");
        let dir = std::env::temp_dir();
        let e = load(dir.to_str().unwrap(), &[]).unwrap_err().to_string();
        assert!(e.contains("is a directory"), "{e}");
    }

    #[test]
    fn names_stay_inside_the_output_directory() {
        for bad in ["../escape", "/tmp/abs", "", "a/b", ".", ".."] {
            let e = default_out_dir(bad, "").unwrap_err().to_string();
            assert!(e.contains("cannot name the output directory"), "{bad}: {e}");
        }
        for good in ["my-cart_2.v1", "Pendel Test", "pendule-é", ".hidden"] {
            assert_eq!(
                default_out_dir(good, "-seeds").unwrap(),
                Path::new("runs").join(format!("{good}-seeds"))
            );
        }
        // any name loads: it matters only for the default directory
        let (s, _) = load("double-integrator", &["name=\"a/b\"".into()]).unwrap();
        assert_eq!(s.name, "a/b");
    }

    #[test]
    fn covariances_are_tables_or_matrices() {
        let rows = load(
            "double-integrator",
            &["gp.B=[[2.0, 0.0], [0.0, 3.0]]".into()],
        )
        .unwrap()
        .0;
        assert_eq!(
            rows.gp.b,
            MatrixSpec::Rows {
                rows: vec![vec![2.0, 0.0], vec![0.0, 3.0]]
            }
        );
        let table = load(
            "double-integrator",
            &["gp.B={type = \"rows\", rows = [[2.0, 0.0], [0.0, 3.0]]}".into()],
        )
        .unwrap()
        .0;
        assert_eq!(rows.gp.b, table.gp.b);
        let err = format!(
            "{:#}",
            build(
                &load("double-integrator", &["gp.B=[[1.0, 0.0, 0.0]]".into()])
                    .unwrap()
                    .0
            )
            .err()
            .unwrap()
        );
        assert!(
            err.contains("gp.B must be 2×2: got 1 row(s) of length(s) [3]"),
            "{err}"
        );
        for (set, want) in [
            ("gp.A=\"eye\"", "expected a matrix (an array of rows"),
            (
                "gp.A={type = \"wishart\"}",
                "expected one of `identity`, `random`, `rows`",
            ),
            ("gp.A=[[1.0, \"a\"]]", "expected a number"),
        ] {
            let err = refusal("double-integrator", set);
            assert!(err.contains(want), "{set}: {err}");
        }
    }

    #[test]
    fn a_field_missing_at_the_top_level_is_not_put_on_a_line() {
        let dir = std::env::temp_dir().join(format!("bayes-cbf-noname-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("noname.toml");
        std::fs::write(&path, "# a comment\n\nsteps = 10\n").unwrap();
        let err = format!("{:#}", load(path.to_str().unwrap(), &[]).unwrap_err());
        assert!(
            err.contains("missing field `system` at the top level") && !err.contains("line"),
            "{err}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn overrides_apply_and_unknown_keys_fail() {
        // a nested key of a table an earlier override gave, and of a table
        // the file leaves out: created, and judged whole by the typed parse
        let (s, _) = load(
            "double-integrator",
            &[
                "gp.B={type=\"identity\", scale=1.0}".into(),
                "gp.B.scale=3.0".into(),
            ],
        )
        .unwrap();
        assert_eq!(s.gp.b, MatrixSpec::Identity { scale: 3.0 });
        let file = std::env::temp_dir().join(format!("bcbf-nested-{}.toml", std::process::id()));
        std::fs::write(
            &file,
            "[system]\ntype = \"pendulum\"\nmass = 1.0\nlength = 1.0\ngravity = 10.0\n",
        )
        .unwrap();
        let path = file.to_str().unwrap();
        let sets = ["gp.A.type=identity".to_string(), "gp.A.scale=2.0".into()];
        assert_eq!(
            load(path, &sets).unwrap().0.gp.a,
            MatrixSpec::Identity { scale: 2.0 }
        );
        let err = format!("{:#}", load(path, &sets[1..]).unwrap_err());
        assert!(
            err.contains("gp.A.scale=2.0") && err.contains("missing field `type`"),
            "{err}"
        );
        let err = format!("{:#}", load(path, &["gp.Aa.scale=2".into()]).unwrap_err());
        assert!(err.contains("unknown field `Aa`"), "{err}");
        // a number TOML spells otherwise is read; a leading zero and a
        // malformed list are named as such, not as strings
        let (s, _) = load("double-integrator", &["dt=.05".into()]).unwrap();
        assert_eq!(s.dt, 0.05);
        // a JSON list of tables, as Python's json.dumps writes one
        let set = r#"gp.input_map=[{"cos": 0}, {"sin": 0}, 1]"#;
        assert!(load("pendulum-safe", &[set.into()]).is_ok());
        for (set, want) in [
            ("steps=05", "written without leading zeros"),
            ("start=[1, 0", "is not a TOML array"),
            (
                "start=[null, 0]",
                "a null (Python's None) has no value here",
            ),
            ("controller=5", "expected a table"),
        ] {
            let err = refusal("double-integrator", set);
            assert!(err.contains(want) && !err.contains("Spec"), "{set}: {err}");
        }
        // a negative count and a string for a number are told in words
        for (set, want) in [
            ("trigger.samples=-5", "expected a non-negative whole number"),
            ("dt='fast'", "expected a number"),
        ] {
            let err = refusal("ackermann-self-triggered", set);
            assert!(
                err.contains(want) && !err.contains("usize") && !err.contains("f64"),
                "{set}: {err}"
            );
        }
        // settings checked when the run is built name the file's keys
        for (set, want) in [
            (
                "gp.lengthscales=[1.0, 2.0]",
                "gp.lengthscales has 2 entries, expected 1, one per kernel input (the entries of gp.input_map)",
            ),
            ("learning.budget=1", "invalid learning.budget = 1: must be ≥ 2"),
            (
                "learning.window=300",
                "learning.window = 300 and learning.budget = 300: give either a window or a budget",
            ),
        ] {
            let (s, _) = load("double-integrator", &[set.into()]).unwrap();
            let err = format!("{:#}", validate(&s).unwrap_err());
            assert!(err.contains(want), "{set}: {err}");
        }
        std::fs::remove_file(&file).unwrap();
        let (s, _) = load(
            "ackermann-bayes-cbf",
            &[
                "controller.probability=0.9".into(),
                "barriers.1.radius=0.5".into(),
                "seed=7".into(),
            ],
        )
        .unwrap();
        assert_eq!(s.controller.probability, 0.9);
        assert_eq!(s.seed, 7);
        match &s.barriers[1] {
            BarrierSpec::CircleHeading { radius, .. } => assert_eq!(*radius, 0.5),
            b => panic!("{b:?}"),
        }
        for (set, want) in [
            ("controller.probabilty=0.9", "probabilty"),
            ("bogus=1", "bogus"),
            ("barriers.5.radius=1", "out of range"),
            ("controller.probability=high", "probability"),
            ("noequals", "key=value"),
        ] {
            let err = refusal("ackermann-bayes-cbf", set);
            assert!(err.contains(want), "{set}: {err}");
            assert!(!err.contains('\n'), "{err}");
        }
        // the override that breaks the scenario is named, not a line of
        // the merged text, which is in no file
        let err = format!(
            "{:#}",
            load(
                "ackermann-bayes-cbf",
                &["seed=3".into(), "controller.probabilty=0.9".into()]
            )
            .unwrap_err()
        );
        assert!(
            err.contains("override `controller.probabilty=0.9`"),
            "{err}"
        );
        assert!(!err.contains("line"), "{err}");
        // a JSON object (a Python dict) is the TOML inline table
        let as_json = load(
            "double-integrator",
            &[
                r#"gp.prior_mean={"type": "pendulum", "mass": 2, "length": 0.5, "gravity": 9.0}"#
                    .into(),
            ],
        )
        .unwrap()
        .0;
        let as_toml = load(
            "double-integrator",
            &[
                r#"gp.prior_mean={type = "pendulum", mass = 2, length = 0.5, gravity = 9.0}"#
                    .into(),
            ],
        )
        .unwrap()
        .0;
        assert_eq!(as_json, as_toml);
        // one that a later override repairs is not blamed
        let err = format!(
            "{:#}",
            load(
                "double-integrator",
                &[
                    "gp.prior_mean.type=zero".into(),
                    "gp.prior_mean={type=\"zero\"}".into(),
                    "controller.probabilty=0.9".into()
                ]
            )
            .unwrap_err()
        );
        assert!(
            err.contains("override `controller.probabilty=0.9`"),
            "{err}"
        );
        assert!(format!("{:#}", load("no-such-scenario", &[]).unwrap_err())
            .contains("unknown scenario"));
    }
}
