//! `calibration`: does the promised safety probability hold? Closed-loop
//! Monte Carlo of the Bayes CBF at `p ∈ {0.9, 0.99, 0.999}` and the mean
//! CBF (`c(p) = 0`), on truths for which the model is exactly right and on
//! the paper's parametric mismatch (SPEC, capability 9).
//!
//! ## Episodes
//! Each episode draws (from its own seed) a truth, an initial state and the
//! noise; every controller runs the *same* episode (paired comparison): the
//! Bayes CBF with the posterior as it is, recalibrated, and recalibrated
//! with the predictive condition, each at three `p`, and the mean CBF.
//! The model learns online at every step (O(k²) growth, no refits, no
//! window). States are observed exactly and `ẋ` is measured by the
//! difference quotient of each step; the noise is process noise, so that the data follow the
//! MVGP's own observation model (see `PROCESS_NOISE_WELL` in `episode.rs`).
//!
//! - **Ackermann vehicle** (relative degree 1, Gaussian factor): obstacle
//!   disc of radius 0.6 m at the origin with the paper's heading barrier
//!   `h = 0.7 (‖p − o‖² − r²) + 0.3 cos(θ − bearing)`, `α = 5`; start
//!   uniform in `[−2.3, −1.9] × [−0.5, 0.5] × [−0.3, 0.3]`; the reference is
//!   a pure pursuit at 1.2 m/s of a waypoint `(0, ±0.65)` on the start's side
//!   (the straight line to it cuts through the disc), then of the goal
//!   `(2.5, 0)` behind the obstacle; bounds `|v| ≤ 1.5`, `|z| ≤ 3`; 450
//!   steps. Model: prior mean the vehicle with wheelbase 1, kernel on
//!   `(cos θ, sin θ)` (translation invariance), lengthscales 1,
//!   `A = 0.01 I`, `B = I`, `σ² A = 0.02² I`.
//! - **Pendulum** (relative degree 2, Cantelli factor): the unsafe sector
//!   `45° ± 22.5°` of `pendulum-safe`, with `k_α = (4, 4)` (a double root
//!   at −2, so that `h` may approach zero within the episode); start uniform
//!   in `θ ∈ [−0.6, 0]`, `ω ∈ [−0.5, 0.5]`; the reference is a PD controller
//!   into the centre of the sector; `|u| ≤ 20`; 250 steps. Model: prior
//!   mean the pendulum `m = l = 1`, kernel on `(cos θ, sin θ, ω)`,
//!   lengthscales `(1, 1, 3)`, `A = 0.04 I`, `B = I`, `σ² A = 0.02² I`.
//!
//! Truths:
//! - **well specified**: a draw of the model's own prior
//!   [`GpSample`](bayes_cbf::systems::GpSample) (128 random Fourier
//!   features per entry) around the model's prior mean, with the model's
//!   kernel, `A` and `B`, and process noise `q = 0.002` (`ẋ` noise
//!   `q/√τ = 0.02`, what the model assumes). For the pendulum, `A = 0.04 I`
//!   also randomises the kinematic row (`θ̇ = ω + δ(x) + δ'(x) u`), so a
//!   truth drawn from this prior does not have relative degree 2 with
//!   respect to the sector barrier: the condition the controller enforces
//!   (which assumes `L_g h = 0`) then no longer implies `h ≥ 0`, and the
//!   pendulum can enter the sector while every step's condition holds;
//! - **mis-specified**: the vehicle with wheelbase 12 (model 1; paper,
//!   Fig. 7), the pendulum with `m = 2`, `l = 0.5` (model 1, 1); process
//!   noise `q = 0.01` (`ẋ` noise 0.1, five times the model's).
//!
//! ## What is counted (per controller)
//! Episodes with `h < 0` anywhere on the fine RK4 grid (1 ms), steps with
//! such a violation, the true barrier condition at every solved step (see
//! `episode.rs`): violated steps among all solved steps and among steps
//! whose chance constraint is active, with the number the model expected
//! (`Σ Φ(−E/√Var)`) and the standardised values
//! `z = (C_true − E[C])/√Var[C]`; on active steps also the condition as
//! realised over the step (`barrier::realised_condition` at the observed
//! rate, what the predictive controllers promise); infeasible steps (the
//! fallback was applied: `relax` unless `--fallback` says otherwise) and
//! episodes using it, collisions and goal reached
//! (vehicle). Rates come with 95 % Wilson score intervals; pooled step rates
//! also with a cluster-robust interval, since steps of one episode are not
//! independent. The paired sign test compares episode violations of the
//! mean CBF and each Bayes CBF.
//!
//! Deterministic given `--seed` for any thread count: every episode's seed
//! is a hash of `(seed, system, truth, episode)`, and results are collected
//! in task order.

mod episode;
mod report;
mod stats;

use super::{ExperimentArgs, Progress, Table};
use crate::bail;
use crate::error::Result;
use crate::sweep::{check_shard_set, Shard};
use bayes_cbf::control::Fallback;
use episode::{run_episode, EpisodeStats, System, TruthKind, CONTROLLERS};
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Instant;

pub use report::{
    CalibrationSummary, Cell, ConditionViolations, ControllerInfo, EpisodeError, Files, MinH,
    PairedComparison, ProcessNoise, RowSummary, Series, SolvedActive, ZSummary, FLOOR,
};
pub use stats::{Pooled, Proportion};

/// The result of `calibration`.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    /// The plotted rates, one cell per (system, truth).
    pub cells: Vec<Cell>,
    /// The table printed at the end of a run: one line per (system, truth,
    /// controller).
    pub console_table: String,
    /// `summary.json`.
    pub summary: CalibrationSummary,
    /// `episodes.csv`: one line per episode and controller.
    pub tables: Vec<Table>,
}

/// What `--episodes` and `--fallback` choose; `None` takes the default.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Options {
    /// Episodes per (system, truth) (default 200; 12 with `--quick`).
    pub episodes: Option<usize>,
    /// Every controller's fallback on an infeasible step (default
    /// [`DEFAULT_FALLBACK`]).
    pub fallback: Option<Fallback>,
}

/// Largest `--episodes`: its task list and episode table stay in memory.
pub const MAX_EPISODES: usize = 1_000_000;

impl Options {
    /// Checks the options as a run would (`--episodes` ≥ 1 and bounded),
    /// without running anything.
    pub fn check(&self, quick: bool) -> Result<()> {
        Plan::new(quick, self.episodes, self.fallback).map(|_| ())
    }
}

/// Default number of episodes per (system, truth).
pub(crate) const DEFAULT_EPISODES: usize = 200;
/// The controllers' fallback unless `--fallback` says otherwise: `relax`,
/// the control SOCP at the largest feasible probability `p*`. On both
/// systems of the experiment it keeps every Bayes CBF at least as safe
/// as the library's default, max-margin, which brakes the pendulum too
/// little where its input gain is uncertain (docs/calibration.md, "Which
/// fallback").
pub const DEFAULT_FALLBACK: Fallback = Fallback::Relax;
/// Episodes of `--quick`.
const QUICK_EPISODES: usize = 12;

/// The experiment's size.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Plan {
    pub episodes: usize,
    /// `(system, control steps per episode)`.
    pub systems: Vec<(System, usize)>,
    /// Every controller's fallback on an infeasible step.
    pub fallback: Fallback,
}

impl Plan {
    /// The plan for `episodes` (default [`DEFAULT_EPISODES`]) and
    /// `fallback` (default [`DEFAULT_FALLBACK`]); `--quick` runs fewer and shorter
    /// episodes.
    pub fn new(quick: bool, episodes: Option<usize>, fallback: Option<Fallback>) -> Result<Self> {
        match episodes {
            Some(0) => bail!("episodes = 0: must be ≥ 1"),
            Some(e) if e > MAX_EPISODES => bail!(
                "episodes = {e}: too large (at most {MAX_EPISODES} per system and truth; \
                 each is one closed-loop run per controller)"
            ),
            _ => {}
        }
        let (default, steps) = if quick {
            (
                QUICK_EPISODES,
                [(System::Vehicle, 250), (System::Pendulum, 150)],
            )
        } else {
            (
                DEFAULT_EPISODES,
                [(System::Vehicle, 450), (System::Pendulum, 250)],
            )
        };
        Ok(Plan {
            episodes: episodes.unwrap_or(default),
            systems: steps.to_vec(),
            fallback: fallback.unwrap_or(DEFAULT_FALLBACK),
        })
    }
}

/// One closed-loop run.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub(crate) struct Task {
    pub system: System,
    pub steps: usize,
    pub truth: TruthKind,
    pub episode: usize,
    pub controller: usize,
}

/// SplitMix64 finaliser.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Seed of an episode: the same for the four controllers.
pub(crate) fn episode_seed(seed: u64, t: &Task) -> u64 {
    mix(mix(mix(seed) ^ t.system as u64) ^ ((t.truth as u64) << 32 | t.episode as u64))
}

fn tasks(plan: &Plan) -> Vec<Task> {
    let mut v = Vec::new();
    for &(system, steps) in &plan.systems {
        for truth in [TruthKind::WellSpecified, TruthKind::MisSpecified] {
            for episode in 0..plan.episodes {
                for controller in 0..CONTROLLERS.len() {
                    v.push(Task {
                        system,
                        steps,
                        truth,
                        episode,
                        controller,
                    });
                }
            }
        }
    }
    v
}

/// Runs every task of `plan` (in parallel) and returns the results in task
/// order.
#[cfg(test)]
pub(crate) fn run_tasks(
    plan: &Plan,
    seed: u64,
    progress: &dyn Progress,
) -> Vec<(Task, EpisodeStats)> {
    let never = Arc::new(AtomicBool::new(false));
    run_shard_tasks(plan, seed, Shard::WHOLE, progress, &never)
}

/// Runs the tasks of `plan` that belong to `shard` (by position in task
/// order), in parallel, and returns them in task order. Once `stop` is set
/// the episodes under way end before their next step and no other starts
/// (what they return is then of no use: the caller checks `stop`).
fn run_shard_tasks(
    plan: &Plan,
    seed: u64,
    shard: Shard,
    progress: &dyn Progress,
    stop: &Arc<AtomicBool>,
) -> Vec<(Task, EpisodeStats)> {
    let all: Vec<Task> = tasks(plan)
        .into_iter()
        .enumerate()
        .filter(|(i, _)| shard.owns(*i))
        .map(|(_, t)| t)
        .collect();
    let done = AtomicUsize::new(0);
    all.par_iter()
        .map(|t| {
            if stop.load(Ordering::Relaxed) {
                return (*t, EpisodeStats::default());
            }
            let s = run_episode(t, plan.fallback, episode_seed(seed, t), stop);
            progress.update(done.fetch_add(1, Ordering::Relaxed) + 1, all.len());
            (*t, s)
        })
        .collect()
}

/// The results of one shard of a calibration run (`part.json`): merged
/// with the other shards by [`merge`], they give exactly the unsharded run.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationPart {
    /// `--seed`.
    pub seed: u64,
    /// `--quick`.
    pub quick: bool,
    /// Episodes per (system, truth).
    pub episodes: usize,
    /// `--fallback` (shards written before it existed: max-margin).
    #[serde(default)]
    pub fallback: Fallback,
    /// This shard.
    pub shard: Shard,
    /// Wall time of this shard (s).
    pub wall_time_s: f64,
    results: Vec<(Task, EpisodeStats)>,
}

impl CalibrationPart {
    /// Checks each episode's counts against each other (solved and
    /// infeasible steps add up to the steps, violations are among the steps
    /// they count, the sums are finite): a shard that another program wrote
    /// or edited is refused, naming the task and the field, rather than
    /// merged into rates above 1. [`merge`] checks every part.
    pub fn check(&self) -> Result<()> {
        for (t, s) in &self.results {
            s.check().map_err(|e| {
                crate::err!(
                    "shard {}/{}, episode {t:?}: {e}; the file is not a shard this program wrote",
                    self.shard.index,
                    self.shard.count
                )
            })?;
        }
        Ok(())
    }
}

/// Runs shard `shard` of the experiment (every task whose position in the
/// task order belongs to it).
pub fn run_shard(
    args: &ExperimentArgs,
    options: &Options,
    shard: Shard,
    progress: &dyn Progress,
) -> Result<CalibrationPart> {
    run_shard_until(
        args,
        options,
        shard,
        progress,
        &Arc::new(AtomicBool::new(false)),
    )
}

/// [`run_shard`], stopped once `stop` is set (by another thread: a Ctrl-C
/// handler, a deadline): the episodes under way end before their next
/// step, the others do not start, and the shard is
/// [`bayes_cbf::Error::Interrupted`], not a part.
pub fn run_shard_until(
    args: &ExperimentArgs,
    options: &Options,
    shard: Shard,
    progress: &dyn Progress,
    stop: &Arc<AtomicBool>,
) -> Result<CalibrationPart> {
    shard.validate()?;
    let plan = Plan::new(args.quick, options.episodes, options.fallback)?;
    bayes_cbf::gp::set_linear_algebra_threads(1);
    let start = Instant::now();
    let results = run_shard_tasks(&plan, args.seed, shard, progress, stop);
    if stop.load(Ordering::Relaxed) {
        return Err(bayes_cbf::Error::Interrupted.into());
    }
    Ok(CalibrationPart {
        seed: args.seed,
        quick: args.quick,
        episodes: plan.episodes,
        fallback: plan.fallback,
        shard,
        wall_time_s: start.elapsed().as_secs_f64(),
        results,
    })
}

/// Merges the shards of one calibration run into its result: checks that
/// they share seed, size and split and are each present once, restores
/// the task order and computes the tables and summary from all tasks (the
/// wall time is the sum of the shards').
pub fn merge(parts: Vec<CalibrationPart>) -> Result<Calibration> {
    let Some(first) = parts.first() else {
        bail!("merge: no shards given");
    };
    let (seed, quick, episodes, fallback) =
        (first.seed, first.quick, first.episodes, first.fallback);
    for p in &parts {
        if (p.seed, p.quick, p.episodes, p.fallback) != (seed, quick, episodes, fallback) {
            bail!(
                "merge: shard {}/{} is of another run (seed {}, quick {}, episodes {}, fallback {}) than shard {}/{} (seed {seed}, quick {quick}, episodes {episodes}, fallback {})",
                p.shard.index, p.shard.count, p.seed, p.quick, p.episodes, p.fallback.name(), first.shard.index, first.shard.count, fallback.name()
            );
        }
    }
    let count = check_shard_set(parts.iter().map(|p| p.shard))?;
    for p in &parts {
        p.check().map_err(|e| crate::err!("merge: {e}"))?;
    }
    let plan = Plan::new(quick, Some(episodes), Some(fallback))?;
    let order = tasks(&plan);
    let mut slots: Vec<Option<EpisodeStats>> = vec![None; order.len()];
    let mut wall = 0.0;
    for p in parts {
        wall += p.wall_time_s;
        let mut mine = (0..order.len()).filter(|i| p.shard.owns(*i));
        for (t, s) in p.results {
            match mine.next() {
                Some(i) if order[i] == t => slots[i] = Some(s),
                _ => bail!(
                    "merge: shard {}/{count} holds a task out of its order ({t:?}); the file is not a shard of this run",
                    p.shard.index
                ),
            }
        }
        if mine.next().is_some() {
            bail!("merge: shard {}/{count} is incomplete", p.shard.index);
        }
    }
    let results: Vec<(Task, EpisodeStats)> = order
        .into_iter()
        .zip(slots)
        .map(|(t, s)| s.map(|s| (t, s)))
        .collect::<Option<_>>()
        .ok_or_else(|| crate::err!("merge: a task has no result"))?;
    let args = ExperimentArgs { seed, quick };
    let rows = report::tables(&plan, &results);
    Ok(Calibration {
        cells: report::plot_cells(&rows),
        console_table: report::console_table(&rows),
        summary: report::summary(&args, &plan, &rows, &results, wall),
        tables: vec![report::episodes_csv(&results)],
    })
}

/// Runs the experiment with `episodes` per (system, truth) (see the module
/// docs), reporting each finished episode: the one-shard run, merged.
pub fn run(
    args: &ExperimentArgs,
    options: &Options,
    progress: &dyn Progress,
) -> Result<Calibration> {
    merge(vec![run_shard(args, options, Shard::WHOLE, progress)?])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `--episodes` is checked before anything is allocated.
    #[test]
    fn episodes_are_bounded() {
        for (e, msg) in [
            (0, "episodes = 0: must be ≥ 1"),
            (usize::MAX, "too large (at most 1000000"),
            (MAX_EPISODES + 1, "too large"),
        ] {
            let err = Plan::new(true, Some(e), None).unwrap_err().to_string();
            assert!(err.contains(msg), "{err}");
        }
        assert_eq!(
            Plan::new(true, Some(MAX_EPISODES), None).unwrap().episodes,
            MAX_EPISODES
        );
    }

    /// `--fallback` reaches every controller of both systems, and the
    /// default is `relax`.
    #[test]
    fn the_fallback_reaches_every_controller() {
        assert_eq!(
            Plan::new(false, None, None).unwrap().fallback,
            Fallback::Relax
        );
        for system in [System::Vehicle, System::Pendulum] {
            let s = episode::setup(system, TruthKind::MisSpecified, 3, 10).unwrap();
            for kind in CONTROLLERS {
                for fallback in [Fallback::Relax, Fallback::Brake, Fallback::MaxMargin] {
                    let c = episode::controller(system, kind, fallback, &s.barrier).unwrap();
                    assert_eq!(c.settings().fallback, fallback, "{}", kind.name);
                }
            }
        }
    }

    #[test]
    fn results_do_not_depend_on_the_thread_count() {
        let plan = Plan {
            episodes: 2,
            systems: vec![(System::Vehicle, 60), (System::Pendulum, 40)],
            fallback: Fallback::MaxMargin,
        };
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap()
            .install(|| run_tasks(&plan, 5, &|_, _| {}));
        let two = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap()
            .install(|| run_tasks(&plan, 5, &|_, _| {}));
        let c = CONTROLLERS.len();
        assert_eq!(one.len(), 2 * 2 * 2 * c);
        assert_eq!(one, two);
        for (t, s) in &one {
            assert!(s.error.is_none(), "{t:?}: {:?}", s.error);
            assert_eq!(s.steps, t.steps);
            assert_eq!(s.non_finite, 0);
        }
        // the controllers share each episode: the same start, so the
        // same first h
        let seeds: Vec<u64> = one.iter().map(|(t, _)| episode_seed(5, t)).collect();
        assert_eq!(seeds[0], seeds[c - 1]);
        assert_ne!(seeds[0], seeds[c]);
    }

    #[test]
    fn zero_episodes_is_an_error_naming_the_option() {
        let e = Plan::new(false, Some(0), None).unwrap_err().to_string();
        assert!(e.contains("episodes = "), "{e}");
        assert_eq!(
            Plan::new(true, None, None).unwrap().episodes,
            QUICK_EPISODES
        );
        assert_eq!(Plan::new(false, Some(7), None).unwrap().episodes, 7);
    }
}
