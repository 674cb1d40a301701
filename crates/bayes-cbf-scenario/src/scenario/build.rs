//! From a parsed [`Scenario`] to the library's objects, validating every
//! field with errors that name it.

use super::{LearningSpec, MatrixSpec, ReferenceSpec, Scenario};
use crate::bail;
use crate::barrier_file::BarrierSpec;
use crate::error::{check_vector, Context, Result};
use crate::input_map_spec::to_input_map;
use crate::parse::parse_rank;
use crate::prior_spec::{PriorSpec, SystemNames};
use crate::warn_once;
use bayes_cbf::barrier::{
    add_observation_noise, cbc_moments, fastest_pole, quantile_factor, start_margin,
    ConditionMoments, DynBarrier, MomentWorkspace,
};
use bayes_cbf::control::{
    ControlOutput, ControlStatus, Fallback, RecalibrationSettings, SafetyController,
    SafetySettings, SelfTriggered, TauSource, TriggerSettings,
};
use bayes_cbf::gp::{FitSettings, LipschitzSettings, Mvgp, MvgpHyper, PriorMean, Rbf};
use bayes_cbf::sim::{
    ConstantReference, DataPolicy, EpsilonGreedy, LinearFeedback, LoopSettings, Reference,
    SimSettings, StepRecord, StepStatus, StraightLinePlanner,
};
use bayes_cbf::systems::DynSystem;
use bayes_cbf::warnings::WarnOnce;
use nalgebra::DMatrix;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use std::sync::Arc;

/// Everything a run needs.
pub struct Built {
    /// The initial state (`start`, spread by the seed if `start_spread`).
    pub start: Vec<f64>,
    /// The true system.
    pub truth: Arc<dyn DynSystem>,
    /// The initial model.
    pub model: Mvgp,
    /// The barriers (also checked on the fine grid).
    pub barriers: Vec<Arc<dyn DynBarrier>>,
    /// Obstacle discs `(centre, radius)` for the signed distance.
    pub obstacles: Vec<([f64; 2], f64)>,
    /// The controller.
    pub controller: SafetyController,
    /// The reference.
    pub reference: Box<dyn Reference>,
    /// Loop settings.
    pub loop_settings: LoopSettings,
}

fn matrix(
    field: &str,
    spec: &MatrixSpec,
    dim: usize,
    rng: &mut ChaCha8Rng,
) -> Result<DMatrix<f64>> {
    let positive = |s: f64| -> Result<()> {
        if !(s.is_finite() && s > 0.0) {
            bail!("gp.{field}.scale = {s}: must be finite and > 0");
        }
        Ok(())
    };
    Ok(match spec {
        MatrixSpec::Identity { scale } => {
            positive(*scale)?;
            DMatrix::identity(dim, dim) * *scale
        }
        MatrixSpec::Random { scale } => {
            positive(*scale)?;
            let c = DMatrix::<f64>::from_fn(dim, dim, |_, _| StandardNormal.sample(rng));
            (&c * c.transpose() / dim as f64 + DMatrix::identity(dim, dim)) * *scale
        }
        MatrixSpec::Rows { rows } => {
            if rows.len() != dim || rows.iter().any(|r| r.len() != dim) {
                let lengths: Vec<usize> = rows.iter().map(Vec::len).collect();
                bail!(
                    "gp.{field} must be {dim}×{dim}: got {} row(s) of length(s) {lengths:?}",
                    rows.len()
                );
            }
            DMatrix::from_fn(dim, dim, |i, j| rows[i][j])
        }
    })
}

/// The true system and its state and control names.
fn truth(spec: &PriorSpec) -> Result<(Arc<dyn DynSystem>, SystemNames)> {
    let system = spec.to_system(None).context("system")?.ok_or_else(|| {
        crate::err!(
            "system: a true system is required (type = \"pendulum\", \"ackermann\" or \"expression\")"
        )
    })?;
    let names = spec.names().unwrap_or_else(|| {
        (
            (0..system.state_dim()).map(|i| format!("x{i}")).collect(),
            Vec::new(),
        )
    });
    Ok((system, names))
}

/// Builds and validates a scenario.
pub fn build(s: &Scenario) -> Result<Built> {
    let (truth, names) = truth(&s.system)?;
    let (n, m) = (truth.state_dim(), truth.control_dim());
    let mut start = match &s.start {
        Some(x) => {
            check_vector("start", x, n, "the state dimension")?;
            x.clone()
        }
        None => vec![0.0; n],
    };
    if let Some(spread) = &s.start_spread {
        check_vector("start_spread", spread, n, "the state dimension")?;
        if let Some(i) = spread.iter().position(|v| *v < 0.0) {
            bail!("start_spread[{i}] = {}: must be ≥ 0", spread[i]);
        }
        // the interval [−w, w] must have a finite width, and the start
        // must stay finite wherever in it the draw lands
        if let Some(i) = (0..n).find(|&i| !(2.0 * spread[i] + start[i].abs()).is_finite()) {
            bail!(
                "start_spread[{i}] = {}: too large (start[{i}] ± start_spread[{i}] overflows)",
                bayes_cbf::error::number(spread[i])
            );
        }
        let mut rng = ChaCha8Rng::seed_from_u64(s.seed ^ 0x57A7_5EED);
        for (x, w) in start.iter_mut().zip(spread) {
            if *w > 0.0 {
                *x += rng.random_range(-*w..=*w);
            }
        }
    }
    if let Some(g) = &s.goal {
        check_vector("goal", g, n, "the state dimension")?;
    }
    if !(s.dt.is_finite() && s.dt > 0.0) {
        bail!(
            "dt = {}: must be finite and > 0",
            bayes_cbf::error::number(s.dt)
        );
    }
    if s.steps == 0 {
        bail!("steps = 0: must be ≥ 1");
    }
    // model
    let mut rng = ChaCha8Rng::seed_from_u64(s.seed ^ 0x5EED_0FAB);
    let a = matrix("A", &s.gp.a, n, &mut rng)?;
    let mut b = matrix("B", &s.gp.b, m + 1, &mut rng)?;
    if s.gp.oracle {
        // the scenario's B is checked all the same
        b = DMatrix::identity(m + 1, m + 1) * super::ORACLE_VARIANCE;
    }
    let input_map = to_input_map(s.gp.input_map.as_deref());
    let inputs = input_map.output_dim(n);
    let lengthscales = match &s.gp.lengthscales {
        Some(l) if l.len() != inputs => bail!(
            "gp.lengthscales has {} entries, expected {inputs}, one per kernel input ({})",
            l.len(),
            if s.gp.input_map.is_some() {
                "the entries of gp.input_map"
            } else {
                "the states"
            }
        ),
        Some(l) => l.clone(),
        None => vec![1.0; inputs],
    };
    let kernel =
        Rbf::new(lengthscales, s.gp.kernel_variance).map_err(|e| crate::err!("gp: {e}"))?;
    let hyper = MvgpHyper {
        kernel,
        A: a,
        B: b,
        sigma: s.gp.noise_sigma,
    };
    // the scenario's prior mean is checked all the same
    let mut prior = s.gp.prior_mean.to_prior_in(Some(&names)).context("gp")?;
    if let PriorMean::System(p) = &prior {
        if (p.state_dim(), p.control_dim()) != (n, m) {
            bail!(
                "gp.prior_mean has {} states and {} controls, the system {n} and {m}",
                p.state_dim(),
                p.control_dim()
            );
        }
    }
    let zero_prior = matches!(prior, PriorMean::Zero);
    if s.gp.oracle {
        prior = PriorMean::System(truth.clone());
    }
    let mut model = Mvgp::new(n, m, hyper, prior, input_map).map_err(|e| crate::err!("gp: {e}"))?;
    if !s.gp.known_rows.is_empty() {
        model = model
            .with_known_rows(&s.gp.known_rows)
            .map_err(|e| crate::err!("gp: {e}"))?;
    }
    // barriers and obstacles
    let mut barriers = Vec::new();
    let mut obstacles = Vec::new();
    for (i, spec) in s.barriers.iter().enumerate() {
        let b = spec
            .build_in(Some(&names.0))
            .with_context(|| format!("barriers[{i}]"))?;
        if b.state_dim() != n {
            bail!(
                "barriers[{i}] is for state dimension {}, the system has {n}",
                b.state_dim()
            );
        }
        match spec {
            BarrierSpec::CircleHeading { center, radius, .. } => obstacles.push((*center, *radius)),
            BarrierSpec::Disc {
                indices,
                center,
                radius,
                ..
            } if *indices == [0, 1] => obstacles.push((*center, *radius)),
            _ => {}
        }
        barriers.push(b);
    }
    if !s.obstacles.is_empty() && n < 2 {
        bail!("obstacles: discs in the plane of states 0 and 1 need at least two states");
    }
    for (i, o) in s.obstacles.iter().enumerate() {
        check_vector(
            &format!("obstacles[{i}].center"),
            &o.center,
            2,
            "a point in the plane",
        )?;
        if !(o.radius.is_finite() && o.radius > 0.0) {
            bail!(
                "obstacles[{i}].radius = {}: must be finite and > 0",
                bayes_cbf::error::number(o.radius)
            );
        }
        obstacles.push((o.center, o.radius));
    }
    let clf = s.clf.as_ref().map(|c| c.build(&names.0)).transpose()?;
    // self-triggering
    let trigger = match &s.trigger {
        None => None,
        Some(t) => {
            check_vector("trigger.cuboid", &t.cuboid, n, "the state dimension")?;
            Some(TriggerSettings {
                lipschitz: LipschitzSettings {
                    delta_l: t.delta_l,
                    sides: t.cuboid.clone(),
                    grid: t.grid,
                    samples: t.samples,
                },
                zeta: s.controller.zeta,
                zeta_b: t.zeta_b,
                tau_min: t.tau_min,
                tau_max: t.tau_max,
                tau_from: TauSource::parse(&t.tau_from)?,
                hold: t.self_triggered,
                margin_for_tau_min: t.margin_for_tau_min,
            })
        }
    };
    // controller
    let c = &s.controller;
    let mut settings = SafetySettings::new(m);
    settings.probability = c.probability;
    settings.zeta = c.zeta;
    settings.lambda = c.lambda;
    settings.predictive = c.predictive;
    if let Some(r) = &c.r {
        check_vector("controller.r", r, m, "the control dimension")?;
        settings.r = DMatrix::from_diagonal(&nalgebra::DVector::from_column_slice(r));
    }
    if let Some(v) = &c.u_min {
        check_vector("controller.u_min", v, m, "the control dimension")?;
    }
    if let Some(v) = &c.u_max {
        check_vector("controller.u_max", v, m, "the control dimension")?;
    }
    settings.u_min = c.u_min.clone();
    settings.u_max = c.u_max.clone();
    settings.fallback =
        Fallback::parse(c.fallback_name()).map_err(|e| crate::err!("controller: {e}"))?;
    // Props. 3 and 5: one ζ, shifted barriers of relative degree ≥ 2, p̃
    let (controller, trigger) = match trigger {
        Some(ts) => {
            let st = SelfTriggered::new(n, m, &barriers, clf, settings, ts)?;
            (st.controller, Some(st.trigger))
        }
        None => (
            SafetyController::new(n, m, barriers.clone(), clf, settings)
                .map_err(|e| crate::err!("controller: {e}"))?,
            None,
        ),
    };
    // reference: only the planner gives a CLF its reference state x_d;
    // the others hold x_d = x, where the CLF asks nothing
    if s.clf.is_some() && !matches!(s.reference, Some(ReferenceSpec::Planner { .. })) {
        warn_once(
            &CLF_WITHOUT_PLANNER,
            "clf: the reference is not a planner, so the CLF's reference state x_d is the \
             state itself and the CLF pulls nowhere; use reference.type = \"planner\" \
             (with a goal) to steer towards the goal"
                .to_string(),
        );
    }
    let reference: Box<dyn Reference> = match &s.reference {
        None => Box::new(ConstantReference(vec![0.0; m])),
        Some(ReferenceSpec::Planner { duration }) => {
            let goal = s
                .goal
                .clone()
                .context("reference: the planner needs a goal")?;
            Box::new(
                StraightLinePlanner::new(start.clone(), goal, *duration)
                    .map_err(|e| crate::err!("reference: {e}"))?,
            )
        }
        Some(ReferenceSpec::EpsilonGreedy { lo, hi, decay }) => {
            check_vector("reference.lo", lo, m, "the control dimension")?;
            check_vector("reference.hi", hi, m, "the control dimension")?;
            Box::new(
                EpsilonGreedy::new(lo.clone(), hi.clone(), *decay)
                    .map_err(|e| crate::err!("reference: {e}"))?,
            )
        }
        Some(ReferenceSpec::Constant { u }) => {
            check_vector("reference.u", u, m, "the control dimension")?;
            Box::new(ConstantReference(u.clone()))
        }
        Some(ReferenceSpec::Feedback { u0, gain, target }) => {
            check_vector("reference.u0", u0, m, "the control dimension")?;
            check_vector("reference.target", target, n, "the state dimension")?;
            Box::new(
                LinearFeedback::new(
                    u0.clone(),
                    gain,
                    target.clone(),
                    truth.angle_indices().to_vec(),
                )
                .map_err(|e| crate::err!("reference: {e}"))?,
            )
        }
    };
    // loop
    let oracle_learning;
    let l = if s.gp.oracle {
        oracle_learning = LearningSpec {
            update_every: 0,
            refit_every: 0,
            refit_geometric: false,
            ..s.learning.clone()
        };
        &oracle_learning
    } else {
        &s.learning
    };
    let fit = FitSettings {
        rank_a: parse_rank("learning.rank_a", &l.rank_a)?,
        rank_b: parse_rank("learning.rank_b", &l.rank_b)?,
        max_iters: l.max_iters,
        seed: s.seed,
        sigma_min: l.sigma_min,
        ..FitSettings::default()
    };
    let sim = SimSettings::new(s.sim.internal_step, s.sim.process_noise)
        .map_err(|e| crate::err!("sim: {e}"))?;
    let loop_settings = LoopSettings {
        dt: s.dt,
        steps: s.steps,
        sim,
        update_every: l.update_every,
        refit_every: l.refit_every,
        refit_geometric: l.refit_geometric,
        refit_background: (l.refit_background > 0).then_some(l.refit_background),
        data: match (l.window, l.budget) {
            (0, 0) => DataPolicy::All,
            (w, 0) => DataPolicy::Window(w),
            (0, b) => DataPolicy::Budget(b),
            (w, b) => bail!(
                "learning.window = {w} and learning.budget = {b}: give either a window or a budget, not both"
            ),
        },
        fit,
        xdot_noise: l.xdot_noise,
        seed: s.seed,
        trigger,
        recalibration: (l.recalibrate && l.update_every > 0).then_some(RecalibrationSettings {
            rate: l.recalibration_rate,
            ..RecalibrationSettings::default()
        }),
    };
    loop_settings.validate().map_err(|e| {
        // the library's names of the learning settings, as the file has them
        let mut msg = e.to_string();
        for key in ["window", "budget", "refit_background", "xdot_noise"] {
            if msg.starts_with(&format!("invalid {key} = ")) {
                msg = msg.replacen(key, &format!("learning.{key}"), 1);
            }
        }
        crate::err!("run settings: {msg}")
    })?;
    warn_start_margin(&barriers, truth.as_ref(), &start, s.seed);
    if !s.gp.oracle {
        warn_known_rows_at_start(&model, &s.gp.known_rows, truth.as_ref(), &start);
        if zero_prior {
            warn_zero_prior(&barriers, l.update_every);
        }
    }
    // controls held for dt (a trigger that only evaluates τ_k holds them
    // for dt too)
    if !loop_settings.trigger.as_ref().is_some_and(|t| t.hold) {
        warn_fast_gains(&barriers, loop_settings.dt);
    }
    // self-triggered labels are differences over their holds: checked on
    // the run's holds ([`warn_noise_below_held_labels`])
    let holding = loop_settings.trigger.as_ref().is_some_and(|t| t.hold);
    if !s.gp.oracle && l.update_every > 0 && !holding {
        warn_noise_below_labels(&model, s.sim.process_noise, s.dt, "dt");
    }
    Ok(Built {
        start,
        truth,
        model,
        barriers,
        obstacles,
        controller,
        reference,
        loop_settings,
    })
}

static CLF_WITHOUT_PLANNER: WarnOnce = WarnOnce::new("clf_without_planner");
static START_OUTSIDE: WarnOnce = WarnOnce::new("start_outside");
static START_UNSAFE: WarnOnce = WarnOnce::new("start_unsafe");
static FAST_GAINS: WarnOnce = WarnOnce::new("fast_gains");

/// Warns, once per scope, when a barrier's fastest pole `λ` exceeds
/// `1/dt`: the condition holds at each step, but the control is held over
/// `dt`, in which `h` moves by about `−λ h dt`, past zero when `λ dt > 1`.
fn warn_fast_gains(barriers: &[Arc<dyn DynBarrier>], dt: f64) {
    for (i, b) in barriers.iter().enumerate() {
        if let Some(pole) = fastest_pole(b.as_ref()).filter(|p| p * dt > 1.0) {
            let gains = if b.relative_degree() == 1 {
                "alpha"
            } else {
                "k_alpha"
            };
            warn_once(
                &FAST_GAINS,
                format!(
                    "barriers[{i}]: its gains ask for a pole of {} /s, beyond 1/dt = {} /s: \
                     the control is held over dt, in which h moves by about −λ·h·dt and \
                     crosses zero although each step meets its condition; lower {gains} \
                     below 1/dt or shorten dt (docs/robots.md, \"Noise and starts\")",
                    short(pole),
                    short(1.0 / dt)
                ),
            );
        }
    }
}
static KNOWN_ROW_MISFIT: WarnOnce = WarnOnce::new("known_row_misfit");

/// Warns, once per scope, when a run's data contradict a row declared
/// known (`gp.known_rows`): a misfit that follows the state and exceeds
/// half the labels ([`Mvgp::known_row_misfit`]). Under gains with a pole
/// beyond `1/dt` ([`warn_fast_gains`]) the labels, differences of the
/// states over `dt`, miss motion faster than the step, which alone can
/// make such a misfit: the warning then says so (`dt`: `None` when the
/// labels are differences over self-triggered holds). A misfit within
/// twice `label_noise`, the noise that process noise puts on every label
/// (`σ_w/√τ`, known rows included), is that noise: no warning.
pub(crate) fn warn_known_row_misfit(
    model: &Mvgp,
    barriers: &[Arc<dyn DynBarrier>],
    (dt, label_noise): (Option<f64>, f64),
    seed: u64,
) {
    let misfit = model
        .known_row_misfit()
        .filter(|m| m.is_large() && m.rms_misfit > 2.0 * label_noise);
    if let Some(m) = misfit {
        let fast = barriers
            .iter()
            .filter_map(|b| fastest_pole(b.as_ref()))
            .fold(0.0f64, f64::max);
        let labels = if let Some(dt) = dt.filter(|dt| fast * dt > 1.0) {
            format!(
                "; unless the labels are what is off: they are differences of the \
                 states over dt = {} s, and the barriers' gains (a pole of {} /s, beyond \
                 1/dt) move the state faster than that",
                short(dt),
                short(fast)
            )
        } else {
            String::new()
        };
        warn_once(
            &KNOWN_ROW_MISFIT,
            format!("gp.known_rows (seed {seed}): {}{labels}", m.describe()),
        );
    }
}

static LEFT_INVARIANT: WarnOnce = WarnOnce::new("left_invariant");

/// Where each relative-degree-2 barrier's `h` first crossed zero in a step
/// that met its condition, from a state outside the set its gains keep safe
/// (`ψ₁ < 0`, [`start_margin`] with the true dynamics): the barrier's
/// index, the step's time, `ψ₁` there and the infeasible steps of the
/// stretch with `ψ₁ < 0` that led to it and of the step that left the set,
/// one entry per barrier that did. An infeasible stretch left that set, and
/// the condition alone does not bring the state back before `h` crosses.
pub(crate) fn crossings_outside(
    barriers: &[Arc<dyn DynBarrier>],
    truth: &dyn DynSystem,
    records: &[StepRecord],
) -> Vec<(usize, f64, f64, usize)> {
    let barriers = barriers.iter().enumerate();
    barriers
        .filter_map(|(i, b)| {
            records.iter().enumerate().find_map(|(k, r)| {
                let crossed =
                    r.status != StepStatus::Infeasible && r.h[i] >= 0.0 && r.h_fine_min[i] < 0.0;
                if !crossed {
                    return None;
                }
                let psi_at = |x: &[f64]| start_margin(truth, b.as_ref(), x).ok().flatten();
                let psi = psi_at(&r.x)?;
                // the infeasible steps of the stretch outside the set that led
                // here and of the step that left it, not those of the whole run
                let outside = records[..k]
                    .iter()
                    .rev()
                    .take_while(|r| psi_at(&r.x).is_some_and(|p| p < 0.0))
                    .count();
                let infeasible = records[k.saturating_sub(outside + 1)..k]
                    .iter()
                    .filter(|r| r.status == StepStatus::Infeasible)
                    .count();
                (psi < 0.0).then_some((i, r.t, psi, infeasible))
            })
        })
        .collect()
}

/// Warns, once per scope, of the [`crossings_outside`]: one warning naming
/// each barrier's.
pub(crate) fn warn_crossing_outside(
    barriers: &[Arc<dyn DynBarrier>],
    truth: &dyn DynSystem,
    records: &[StepRecord],
    seed: u64,
) {
    let mut found = Vec::new();
    for (i, t, psi, infeasible) in crossings_outside(barriers, truth, records) {
        let how = if infeasible > 0 {
            format!(
                "the stretch outside it held {infeasible} infeasible step(s) \
                 (docs/robots.md, \"Infeasible stretches\")"
            )
        } else {
            "steps that met their conditions led there, with no infeasible step: the hold, \
             noise or model error beyond p (docs/robots.md, \"Noise and starts\")"
                .to_string()
        };
        found.push(format!(
            "barriers[{i}] (seed {seed}): h crossed zero at t = {t:.3} in a step that met its \
             condition, from a state outside the set its gains keep safe (ψ₁ = ḣ + λh = {} < \
             0); {how}",
            short(psi)
        ));
    }
    if !found.is_empty() {
        warn_once(&LEFT_INVARIANT, found.join("; and "));
    }
}

static KNOWN_ROW_NOT_TRUE: WarnOnce = WarnOnce::new("known_row_not_true");

/// Warns, once per scope, when a row of `F` declared known differs from
/// the system's at the start state or a unit step from it along a
/// coordinate: a known row is the prior mean's and is never learned (a
/// zero prior mean makes every known row zero).
///
/// The unit steps are states the run may never visit: an evaluation that
/// fails there (an expression not finite off the start) is discarded, so
/// that the run does not stop on it.
fn warn_known_rows_at_start(model: &Mvgp, known: &[usize], truth: &dyn DynSystem, start: &[f64]) {
    if known.is_empty() {
        return;
    }
    let n = truth.state_dim();
    let mut points = vec![start.to_vec()];
    for j in 0..n {
        for step in [1.0, -1.0] {
            let mut x = start.to_vec();
            x[j] += step;
            points.push(x);
        }
    }
    // stops at the first state that warns
    let _ = points
        .iter()
        .all(|x| known_rows_agree(model, known, truth, x));
    let _ = (truth.take_error(), model.prior().take_error());
}

/// [`warn_known_rows_at_start`] at one state `x`: whether every known row
/// agrees there (after warning of the first that does not).
fn known_rows_agree(model: &Mvgp, known: &[usize], truth: &dyn DynSystem, x: &[f64]) -> bool {
    let (n, p) = (truth.state_dim(), truth.control_dim() + 1);
    let Ok(prior) = model.posterior_mean(x) else {
        return true;
    };
    let mut f = vec![0.0; n * p];
    truth.eval_f64(x, &mut f);
    for &i in known.iter().filter(|&&i| i < n) {
        let true_row: Vec<f64> = (0..p).map(|c| f[i + n * c]).collect();
        let prior_row: Vec<f64> = (0..p).map(|c| prior[(i, c)]).collect();
        let scale = true_row.iter().fold(1.0f64, |a, v| a.max(v.abs()));
        let off = true_row
            .iter()
            .zip(&prior_row)
            .any(|(a, b)| (a - b).abs() > 1e-6 * scale);
        if off {
            let show = |row: &[f64]| row.iter().map(|v| short(*v)).collect::<Vec<_>>().join(", ");
            warn_once(
                &KNOWN_ROW_NOT_TRUE,
                format!(
                    "gp.known_rows: row {i} of F is taken from gp.prior_mean, which gives \
                     [{}] at x = [{}] where the system has [{}]: a known row is never \
                     learned, so the model keeps it wrong (a zero prior mean makes every \
                     known row zero); give gp.prior_mean that row exactly",
                    show(&prior_row),
                    show(x),
                    show(&true_row)
                ),
            );
            return false;
        }
    }
    true
}

static ZERO_PRIOR: WarnOnce = WarnOnce::new("zero_prior");

/// Warns, once per scope, of a zero prior mean where it defeats the
/// conditions: under a barrier of relative degree ≥ 2 (the model knows
/// neither the rows that tie `h`'s derivatives to the state nor how the
/// input acts), or without learning (it never learns how the input acts).
fn warn_zero_prior(barriers: &[Arc<dyn DynBarrier>], update_every: usize) {
    if barriers.is_empty() {
        // no condition to meet: nothing is infeasible
        return;
    }
    let high = barriers
        .iter()
        .enumerate()
        .find(|(_, b)| b.relative_degree() >= 2);
    let why = match high {
        Some((i, b)) => format!(
            "barriers[{i}] has relative degree {}: the model knows neither the rows that \
             tie h's derivatives to the state (as p' = v) nor how the input acts, and a \
             robot that must learn them can cross (docs/robots.md, \"A zero prior mean\")",
            b.relative_degree()
        ),
        None if update_every == 0 => "learning.update_every = 0: the model never learns how \
            the input acts, so its steps can be infeasible throughout"
            .to_string(),
        None => return,
    };
    warn_once(
        &ZERO_PRIOR,
        format!(
            "gp.prior_mean is zero and {why}; give gp.prior_mean the rows you know (the \
             kinematic ones, with gp.known_rows) and the input's sign and rough gain \
             (README, \"Your own robot\")"
        ),
    );
}

static MOSTLY_INFEASIBLE: WarnOnce = WarnOnce::new("mostly_infeasible");

/// Warns, once per scope, when the infeasible steps of a run held more
/// than half its time: the fallback acted on most of it, safe or not (a
/// robot kept still by it is safe, and goes nowhere). Time, not steps:
/// self-triggered holds of infeasible steps are short.
///
/// `noise` gives [`noise_above_labels`] of a predictive controller (its
/// conditions carry the model's noise, which then exceeds what the labels
/// carry), which the warning names among the causes; it is called only
/// when the warning is due.
pub(crate) fn warn_mostly_infeasible(
    records: &[StepRecord],
    fallback: &str,
    seed: u64,
    noise: impl FnOnce() -> Option<String>,
) {
    let infeasible = records
        .iter()
        .filter(|r| r.status == StepStatus::Infeasible)
        .count();
    let total: f64 = records.iter().map(|r| r.hold).sum();
    let fallen: f64 = records
        .iter()
        .filter(|r| r.status == StepStatus::Infeasible)
        .map(|r| r.hold)
        .sum();
    // the probes of `noise` cost solves: none once the warning was given
    if 2.0 * fallen > total && MOSTLY_INFEASIBLE.pending() {
        let noise = noise();
        warn_once(
            &MOSTLY_INFEASIBLE,
            format!(
                "seed {seed}: {infeasible} of {} steps were infeasible, {:.0}% of the run's \
                 time, so the fallback ({fallback}) acted on most of the run and no \
                 condition was promised there: \
                 a model too uncertain of the input's effect for controller.probability (a \
                 zero prior mean, a wide B), {}bounds and gains in conflict{} (docs/robots.md, \
                 \"Infeasible steps\")",
                records.len(),
                100.0 * fallen / total,
                if noise.is_some() { "" } else { "or " },
                noise.map_or_else(String::new, |n| format!(", or {n}"))
            ),
        );
    }
}

static CROSSED_IN_INFEASIBLE_STEP: WarnOnce = WarnOnce::new("crossed_in_infeasible_step");

/// The first step in which a barrier's `h` crossed zero (from `h ≥ 0` at
/// the step's start) while its SOCP was infeasible: the barrier's index
/// and the step.
pub(crate) fn crossing_in_infeasible_step(
    barriers: usize,
    records: &[StepRecord],
) -> Option<(usize, &StepRecord)> {
    records.iter().find_map(|r| {
        (0..barriers)
            .find(|&i| r.status == StepStatus::Infeasible && r.h[i] >= 0.0 && r.h_fine_min[i] < 0.0)
            .map(|i| (i, r))
    })
}

/// Warns, once per scope, of a [`crossing_in_infeasible_step`]: no
/// control met the conditions at `p` there, and the fallback did not keep
/// `h ≥ 0`. Without such a warning a run whose steps were all infeasible
/// crossed in silence.
///
/// Under max-margin with input bounds, the warning adds that relax would
/// have met the conditions at `p*` (without bounds relax is no better: its
/// `p*` can take an unbounded control); with a data window, that the
/// window may have dropped what the model knew ([`window_forgot`]).
pub(crate) fn warn_crossing_in_infeasible_step(
    barriers: usize,
    records: &[StepRecord],
    (fallback, bounded, data): (&str, bool, DataPolicy),
    seed: u64,
) {
    if let Some((i, r)) = crossing_in_infeasible_step(barriers, records) {
        let window = window_forgot(data, records, r);
        let budget_section = if window.is_some() {
            ", \"For a robot whose dynamics do not change\""
        } else {
            ""
        };
        let window = window.unwrap_or_default();
        let infeasible = records
            .iter()
            .filter(|r| r.status == StepStatus::Infeasible)
            .count();
        let p_star = r
            .p_star
            .map_or_else(|| "none, no probability was feasible".to_string(), short);
        // max-margin at c(p) favours the control of least variance, which
        // can brake too little where relax would have met the conditions
        // at p*
        let max_margin = if fallback == Fallback::MaxMargin.name() && bounded && r.p_star.is_some()
        {
            "; max_margin, at the c(p) of controller.probability, applies the control of \
                 least spread, which can brake too little: relax would have met the conditions \
                 at p* (docs/calibration.md, \"Which fallback\"; docs/robots.md, "
        } else {
            " (docs/robots.md, "
        };
        warn_once(
            &CROSSED_IN_INFEASIBLE_STEP,
            format!(
                "barriers[{i}] (seed {seed}): h crossed zero at t = {:.3} in an infeasible step \
                 (p* = {p_star}; fallback {fallback}), {infeasible} of {} steps were \
                 infeasible: the model's spread at controller.probability, the input bounds \
                 or the gains left no control that meets the conditions{window}{max_margin}\
                 \"Infeasible steps\"{budget_section})",
                r.t,
                records.len()
            ),
        );
    }
}

/// How many times its smallest over the [`SPREAD_RISE_STEPS`] steps before
/// the model's spread `tr Σ` at a step must be for [`window_forgot`].
const SPREAD_RISE: f64 = 3.0;

/// The steps over which [`window_forgot`] looks for a rise of the spread.
const SPREAD_RISE_STEPS: usize = 10;

/// The clause of [`warn_crossing_in_infeasible_step`] for a run with a data
/// window (`data = Window(k)`) in which, between the window's filling and
/// the crossing step `r`, the model's spread `tr Σ` rose more than
/// [`SPREAD_RISE`]-fold within [`SPREAD_RISE_STEPS`] steps. The window drops
/// its oldest observations, which can be the only ones at other controls
/// (where the input saturates) and the only ones that told the input gain
/// from the drift; a budget keeps the most informative. A sudden rise is
/// what such a drop does; a state moving into new regions raises the spread
/// too, but gradually (the double integrator's max-margin crossings under a
/// quarter or half of its bound, which a budget does not prevent, rose at most 2.4-fold
/// within 10 steps; the window's own crossings 7.6–9.5-fold).
pub(crate) fn window_forgot(
    data: DataPolicy,
    records: &[StepRecord],
    r: &StepRecord,
) -> Option<String> {
    let DataPolicy::Window(k) = data else {
        return None;
    };
    let end = records.iter().position(|q| std::ptr::eq(q, r))?;
    let full = records[..=end].iter().position(|q| q.data_size >= k)?;
    let (rise, from, to) = (full.max(1)..=end)
        .filter_map(|t| {
            let before = &records[t.saturating_sub(SPREAD_RISE_STEPS)..t];
            let least = before
                .iter()
                .map(|q| q.trace_cov)
                .fold(f64::INFINITY, f64::min);
            let now = records[t].trace_cov;
            (least > 0.0 && now.is_finite()).then(|| (now / least, least, now))
        })
        .max_by(|a, b| a.0.total_cmp(&b.0))?;
    (rise > SPREAD_RISE).then(|| {
        format!(
            "; the data window was full (learning.window = {k}) and the model's spread rose \
             from tr Σ = {} to {} within {SPREAD_RISE_STEPS} steps: a window drops its oldest \
             observations, which can be the only ones at other controls, and \
             learning.budget = {k} keeps the most informative instead",
            short(from),
            short(to)
        )
    })
}

/// The model's noise on each learned row `i`, `σ·√A_ii`.
fn row_noise(model: &Mvgp) -> impl Iterator<Item = (usize, f64)> + '_ {
    let (sigma, a) = (model.hyper().sigma, &model.hyper().A);
    model
        .learned_rows()
        .into_iter()
        .map(move |i| (i, sigma * a[(i, i)].sqrt()))
}

/// Infeasible steps re-solved by [`noise_above_labels`], at most.
const NOISE_PROBES: usize = 20;

/// The clause of [`warn_mostly_infeasible`] for a predictive controller
/// whose model's noise on a learned row, `σ·√A_ii`, is more than twice the
/// noise of the labels, `label_noise` (`σ_w/√τ`; 0 without process noise),
/// and blocks the steps: each predictive condition carries `c·σ·√A_ii`
/// times the gradient's weight on that row, a spread no amount of data
/// removes. Up to [`NOISE_PROBES`] infeasible steps, spread over the run,
/// are solved again with the run's final `model` (its data and noise),
/// with and without the noise in the conditions (no CLF: it is soft); the
/// clause is given when more than half of them are infeasible with it and
/// feasible without. Not for barriers of relative degree above 2, whose
/// moments are Monte Carlo estimates.
pub(crate) fn noise_above_labels(
    controller: &SafetyController,
    model: &Mvgp,
    records: &[StepRecord],
    label_noise: f64,
) -> Option<String> {
    let (i, noise) = row_noise(model).find(|(_, noise)| *noise > 2.0 * label_noise)?;
    let barriers = controller.barriers().to_vec();
    if barriers.iter().any(|b| b.relative_degree() > 2) {
        return None;
    }
    let infeasible: Vec<&StepRecord> = records
        .iter()
        .filter(|r| r.status == StepStatus::Infeasible)
        .collect();
    let probes: Vec<&StepRecord> = (0..NOISE_PROBES.min(infeasible.len()))
        .map(|j| infeasible[j * infeasible.len() / NOISE_PROBES.min(infeasible.len())])
        .collect();
    let (n, m, nb) = (model.state_dim(), model.control_dim(), barriers.len());
    let solver = |predictive: bool| {
        let mut settings = controller.settings().clone();
        settings.predictive = predictive;
        SafetyController::new(n, m, barriers.clone(), None, settings).ok()
    };
    let (mut with, mut without) = (solver(true)?, solver(false)?);
    let mut out = ControlOutput::new(m, nb);
    let mut feasible = |c: &mut SafetyController, r: &StepRecord| {
        c.step(model, &r.x, &r.u_ref, None, &mut out).is_ok()
            && !matches!(out.status, ControlStatus::Infeasible(_))
    };
    let blocked = probes
        .iter()
        .filter(|r| !feasible(&mut with, r) && feasible(&mut without, r))
        .count();
    if 2 * blocked <= probes.len() {
        return None;
    }
    let labels = labels_noise(label_noise);
    Some(format!(
        "gp.noise_sigma too large for controller.predictive, whose conditions carry the \
         model's noise: σ·√A_ii = {} on row {i}, where {labels}; with the run's final model, \
         {blocked} of {} infeasible steps are feasible without it (lower gp.noise_sigma \
         towards the labels' noise, or let refits learn it)",
        short(noise),
        probes.len()
    ))
}

static PREDICTIVE_STANDOFF: WarnOnce = WarnOnce::new("predictive_standoff");

/// A condition's slack `|scbc|` at most this is active: it set the control.
const ACTIVE_SCBC: f64 = 1e-5;

/// [`warn_predictive_standoff`] names a standoff above this share of `h`
/// at the start: one that takes a good part of the robot's room.
const STANDOFF_SHARE: f64 = 0.25;

/// Warns, once per scope, when a predictive controller's barrier condition
/// held the control back from the reference on more than half of the
/// run's steps, the model's noise on a learned row, `σ·√A_ii`, is more
/// than twice the labels' own (`label_noise`, `σ_w/√τ`; 0 without process
/// noise), and the standoff that noise makes is more than a quarter of `h`
/// at the start. The predictive condition carries the noise: at rest it
/// reads `k₀h ≥ c(p)·σ_c`, `σ_c` the noise's std in the condition, so the
/// robot stops about `c(p)·σ_c/k₀` from its limit (docs/robots.md, "The
/// predictive condition keeps a standoff"), a standoff here made by a noise
/// the labels do not have. The standoff is evaluated with the final model
/// at the last state whose control the condition held back.
pub(crate) fn warn_predictive_standoff(
    barriers: &[Arc<dyn DynBarrier>],
    model: &Mvgp,
    records: &[StepRecord],
    (probability, label_noise): (f64, f64),
    seed: u64,
) {
    if !PREDICTIVE_STANDOFF.pending() {
        return;
    }
    let Some((row, noise)) = row_noise(model).find(|(_, n)| *n > 2.0 * label_noise) else {
        return;
    };
    for (i, b) in barriers.iter().enumerate() {
        let r = b.relative_degree();
        let k0 = b.gains().first().copied().unwrap_or(0.0);
        if r > 2 || k0 <= 0.0 {
            continue;
        }
        // steps whose control this condition moved off the reference
        let held = |rec: &&StepRecord| {
            let off: f64 = rec
                .u
                .iter()
                .zip(&rec.u_ref)
                .map(|(u, v)| (u - v).powi(2))
                .sum();
            let scale: f64 = rec.u_ref.iter().map(|v| v * v).sum();
            rec.status != StepStatus::Infeasible
                && rec.scbc.get(i).is_some_and(|s| s.abs() <= ACTIVE_SCBC)
                && off.sqrt() > 1e-6 * (1.0 + scale.sqrt())
        };
        let held: Vec<&StepRecord> = records.iter().filter(held).collect();
        let Some(last) = held.last().filter(|_| 2 * held.len() > records.len()) else {
            continue;
        };
        let start = records[0].h[i];
        let Some(standoff) = standoff(b.as_ref(), model, &last.x, probability)
            .filter(|s| *s > STANDOFF_SHARE * start)
        else {
            continue;
        };
        let labels = labels_noise(label_noise);
        warn_once(
            &PREDICTIVE_STANDOFF,
            format!(
                "barriers[{i}] (seed {seed}): its condition held the control back from the \
                 reference on {} of {} steps, and controller.predictive puts the model's noise \
                 in it, σ·√A_ii = {} on row {row}, where {labels}: at rest the condition keeps \
                 h ≥ c(p)·σ_c/k₀ = {} (c({probability}) = {}, k₀ = {}, σ_c the noise's std \
                 in the condition; h = {} at the start), a standoff the labels do not call \
                 for; lower gp.noise_sigma towards the labels' noise (or let refits learn \
                 it), or set controller.predictive = false for the paper's condition on the \
                 latent dynamics (docs/robots.md, \"The predictive condition keeps a \
                 standoff\")",
                held.len(),
                records.len(),
                short(noise),
                short(standoff),
                short(quantile_factor(probability, r).unwrap_or(f64::NAN)),
                short(k0),
                short(start)
            ),
        );
        return;
    }
}

/// What process noise puts on the labels, `label_noise`, as a warning
/// says it.
fn labels_noise(label_noise: f64) -> String {
    if label_noise > 0.0 {
        format!(
            "sim.process_noise puts {} on the labels",
            short(label_noise)
        )
    } else {
        "the labels carry no process noise".to_string()
    }
}

/// `c(p)·σ_c/k₀` of barrier `b` at `x` under `model`: the value of `h` a
/// predictive condition keeps at rest, `σ_c` the model's noise in the
/// condition ([`add_observation_noise`]); `None` where it cannot be
/// evaluated. A probe after the run: what its moments warn of is not the
/// run's, and stays out of the run's record.
fn standoff(b: &dyn DynBarrier, model: &Mvgp, x: &[f64], probability: f64) -> Option<f64> {
    let _probe = bayes_cbf::warnings::Record::start();
    let r = b.relative_degree();
    let mut ws = MomentWorkspace::new(model);
    ws.update(model, x, r).ok()?;
    let mut mom = ConditionMoments::zeros(model.control_dim());
    cbc_moments(&mut ws, b, &mut mom).ok()?;
    let latent = mom.cov[(0, 0)];
    add_observation_noise(&ws, &mut mom).ok()?;
    let sd = (mom.cov[(0, 0)] - latent).max(0.0).sqrt();
    let c = quantile_factor(probability, r).ok()?;
    Some(c * sd / b.gains()[0]).filter(|s| s.is_finite())
}

static NOISE_BELOW_LABELS: WarnOnce = WarnOnce::new("noise_below_labels");

/// Warns, once per scope, when the model's noise on a learned row,
/// `σ·√A_ii`, is below the noise that process noise `σ_w` puts on the
/// learning labels, `σ_w/√τ` (finite differences over the hold `τ`, named
/// `tau`: `dt`, or the median hold of a self-triggered run): the
/// conditions then take the labels for more exact than they are.
fn warn_noise_below_labels(model: &Mvgp, process_noise: f64, hold: f64, tau: &str) {
    let label = process_noise / hold.sqrt();
    let low = row_noise(model).find(|(_, noise)| *noise < label);
    if let Some((i, noise)) = low {
        warn_once(
            &NOISE_BELOW_LABELS,
            format!(
                "gp.noise_sigma: the model's noise on row {i}, σ·√A_ii = {}, is below the \
                 noise sim.process_noise puts on the learning labels, σ_w/√τ = {} with τ = \
                 {tau} = {} s: the conditions take the labels for more exact than they are, \
                 and can cross; raise noise_sigma (docs/robots.md, \"Tell the model the \
                 noise it will see\")",
                short(noise),
                short(label),
                short(hold)
            ),
        );
    }
}

/// [`warn_noise_below_labels`] for a self-triggered run: its labels are
/// differences over the holds, `σ_w/√τ_k`; the warning takes the median
/// hold (half the labels are at least that noisy).
pub(crate) fn warn_noise_below_held_labels(
    model: &Mvgp,
    process_noise: f64,
    records: &[StepRecord],
) {
    if let Some(median) = median_hold(records) {
        warn_noise_below_labels(model, process_noise, median, "the median hold");
    }
}

/// The median of the run's positive holds (`None` without any).
pub(crate) fn median_hold(records: &[StepRecord]) -> Option<f64> {
    let mut holds: Vec<f64> = records
        .iter()
        .map(|r| r.hold)
        .filter(|h| *h > 0.0)
        .collect();
    holds.sort_by(f64::total_cmp);
    holds.get(holds.len() / 2).copied()
}

static CLAMPED_HOLDS: WarnOnce = WarnOnce::new("clamped_holds");

/// Warns, once per scope, when self-triggered holds were clamped up to
/// `tau_min`: there the hold that keeps the conditions (Props. 3, 5) was
/// shorter than the one applied, which lies outside the guarantee. The
/// warning says what would lengthen them: a larger cuboid where the state
/// may leave it before `tau_min`, else the margin raised for the hold
/// (`trigger.margin_for_tau_min`), or, where that was infeasible, a lower
/// `tau_min` or probability.
pub(crate) fn warn_clamped_holds(records: &[StepRecord], ts: &TriggerSettings, seed: u64) {
    // an infeasible step has no margin (τ_k = 0) and holds its fallback:
    // not a hold the guarantee sized
    let reports: Vec<_> = records
        .iter()
        .filter(|r| r.status != StepStatus::Infeasible)
        .filter_map(|r| r.trigger.as_ref())
        .collect();
    let clamped: Vec<_> = reports.iter().filter(|t| t.clamped_low).collect();
    if clamped.is_empty() {
        return;
    }
    let tau_min = ts.tau_min;
    let shortest = clamped
        .iter()
        .map(|t| t.tau_analytic)
        .fold(f64::INFINITY, f64::min);
    let leaving = clamped.iter().filter(|t| t.tau_cuboid < tau_min).count();
    let mut why = Vec::new();
    if leaving > 0 {
        why.push(format!(
            "on {leaving} the state could leave trigger.cuboid before tau_min (enlarge it)"
        ));
    }
    let by_margin = clamped.len() - leaving;
    if by_margin > 0 {
        why.push(if ts.margin_for_tau_min {
            format!(
                "on {by_margin} the margin that holds for tau_min was infeasible or out of \
                 reach (lower trigger.tau_min or controller.probability)"
            )
        } else {
            format!(
                "on {by_margin} the margins were too small (set trigger.margin_for_tau_min = \
                 true to raise them, or lower trigger.tau_min)"
            )
        });
    }
    warn_once(
        &CLAMPED_HOLDS,
        format!(
            "trigger (seed {seed}): {} of {} holds of steps that met their conditions were \
             clamped up to tau_min = {} s, where the hold that keeps the conditions was \
             shorter (analytic τ_k down to {} s): those holds lie outside the guarantee; {} \
             (docs/robots.md, \"Holds clamped to tau_min\")",
            clamped.len(),
            reports.len(),
            short(tau_min),
            short(shortest),
            why.join("; ")
        ),
    );
}

static CROSSED_IN_MET_STEP: WarnOnce = WarnOnce::new("crossed_in_met_step");

/// Warns, once per scope, when a barrier's `h` crossed zero within a held
/// step that met its condition: one warning naming each barrier's first
/// such crossing.
///
/// Relative degree 1: the condition bounds `ḣ` at the step; over the hold
/// `τ`, `h` also moves by `½τ²ẋᵀ∇²h ẋ` (its curvature along the motion, at
/// the step's state and control under the true dynamics). The warning
/// blames that term where `h + τḣ ≥ 0` and `h + τḣ + ½τ²ẋᵀ∇²h ẋ < 0`;
/// otherwise noise, model error beyond `p` or a kink. Relative degree ≥ 2,
/// from within the set the gains keep (outside it, [`warn_crossing_outside`]
/// speaks): noise or model error beyond `p`. The noise is named only where
/// the run has process noise, and a latent condition (the paper's, or Monte
/// Carlo's at relative degree ≥ 3), which leaves it out, is named as such.
pub(crate) fn warn_crossing_in_met_step(
    barriers: &[Arc<dyn DynBarrier>],
    truth: &dyn DynSystem,
    records: &[StepRecord],
    (predictive, process_noise): (bool, f64),
    seed: u64,
) {
    let n = truth.state_dim();
    let cause = |r_degree: usize| -> &'static str {
        match (process_noise > 0.0, predictive, r_degree) {
            (false, _, _) => "model error beyond p",
            (true, _, 3..) => {
                "the process noise, which the Monte Carlo condition of relative degree ≥ 3 \
                 leaves out, or model error beyond p"
            }
            (true, false, _) => {
                "the process noise, which the latent condition (controller.predictive = false) \
                 leaves out, or model error beyond p (use controller.predictive = true)"
            }
            (true, true, _) => "process noise or model error beyond p",
        }
    };
    // each barrier's first such crossing, in one warning
    let mut crossings = Vec::new();
    for (i, b) in barriers.iter().enumerate() {
        let found = records
            .iter()
            .find(|r| r.status != StepStatus::Infeasible && r.h[i] >= 0.0 && r.h_fine_min[i] < 0.0);
        let Some(r) = found else { continue };
        let r_degree = b.relative_degree();
        let noise = cause(r_degree);
        if r_degree >= 2 {
            let outside = start_margin(truth, b.as_ref(), &r.x)
                .ok()
                .flatten()
                .is_some_and(|psi| psi < 0.0);
            if outside {
                continue;
            }
            crossings.push(format!(
                "barriers[{i}] (seed {seed}): h crossed zero at t = {:.3} within a hold of {} s \
                 that met its condition (relative degree {r_degree}): {noise} did",
                r.t,
                short(r.hold),
            ));
            continue;
        }
        let mut fbuf = vec![0.0; n * (1 + truth.control_dim())];
        let mut xdot = vec![0.0; n];
        truth.xdot(&r.x, &r.u, &mut fbuf, &mut xdot);
        let (mut grad, mut hess) = (vec![0.0; n], vec![0.0; n * n]);
        let mut scratch = vec![bayes_cbf::num_dual::HyperDual64::from(0.0); n];
        b.hessian(&r.x, &mut grad, &mut hess, &mut scratch);
        let curvature: f64 = (0..n)
            .flat_map(|a| (0..n).map(move |c| (a, c)))
            .map(|(a, c)| xdot[a] * hess[a * n + c] * xdot[c])
            .sum();
        let drop = 0.5 * r.hold * r.hold * curvature;
        // the curvature is the cause where the first-order motion over the
        // hold keeps h ≥ 0 and the curvature term takes it below
        let hdot: f64 = grad.iter().zip(&xdot).map(|(g, v)| g * v).sum();
        let first_order = r.h[i] + r.hold * hdot;
        let cause = if first_order >= 0.0 && first_order + drop < 0.0 {
            format!(
                "over the hold h also moves by ½·τ²·ẋᵀ∇²h·ẋ = {} there (its curvature \
                 along the motion, which the condition at the step does not bound); add a \
                 margin controller.zeta ≥ ½·τ·|ẋᵀ∇²h·ẋ| = {}, shorten dt, or self-trigger",
                short(drop),
                short(-drop / r.hold)
            )
        } else {
            format!(
                "its curvature along the motion does not explain it: {noise}, or a kink of h, did"
            )
        };
        crossings.push(format!(
            "barriers[{i}] (seed {seed}): h crossed zero at t = {:.3} within a hold of {} s \
             that met its condition: {cause} (docs/robots.md, \"Curved barriers over the \
             hold\")",
            r.t,
            short(r.hold),
        ));
    }
    if !crossings.is_empty() {
        warn_once(&CROSSED_IN_MET_STEP, crossings.join("; and "));
    }
}

/// `v` in three decimals, or in scientific notation where those would be
/// too many digits or none.
fn short(v: f64) -> String {
    if v != 0.0 && !(1e-3..1e6).contains(&v.abs()) {
        format!("{v:.3e}")
    } else {
        format!("{v:.3}")
    }
}

/// Warns, once per scope, when the start lies outside the set that a
/// relative-degree-2 barrier's gains keep safe ([`start_margin`]).
fn warn_start_margin(
    barriers: &[Arc<dyn DynBarrier>],
    truth: &dyn DynSystem,
    x: &[f64],
    seed: u64,
) {
    for (i, b) in barriers.iter().enumerate() {
        let h = b.value(x);
        if h < 0.0 {
            warn_once(
                &START_UNSAFE,
                format!(
                    "barriers[{i}]: the start {x:?} (seed {seed}) is outside the safe set \
                     (h = {} < 0): the run is unsafe from its first state",
                    short(h)
                ),
            );
            continue;
        }
        if let Ok(Some(psi)) = start_margin(truth, b.as_ref(), x) {
            if psi < 0.0 {
                warn_once(
                    &START_OUTSIDE,
                    format!(
                        "barriers[{i}]: the start {x:?} (seed {seed}) is outside the set its \
                         gains keep safe: ψ₁ = ḣ + λh = {} < 0 (λ the larger root of \
                         s² + k₁s + k₀); h can cross zero although every step meets its \
                         condition: raise k_alpha or start slower (docs/robots.md, \
                         \"Noise and starts\")",
                        short(psi)
                    ),
                );
            }
        }
    }
}
