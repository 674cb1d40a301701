//! `ackermann-triggering` (paper, Sec. VII-B "Evaluating triggering time",
//! Fig. 2): the Lipschitz constant of the learned vehicle dynamics and the
//! inter-trigger time τ_k, analytic (Lemma 3, Prop. 3) and numerical, over a
//! run; the self-triggered loop against fixed-step control over the same
//! horizon; and τ_k against the margin ζ.
//!
//! Runs (each a closed loop of the built-in scenario
//! `ackermann-self-triggered` with the paper's margin ζ at every step,
//! `trigger.margin_for_tau_min = false`; outputs in a subdirectory):
//!
//! * `fixed-step/`: time-triggered at `dt`, τ_k evaluated at every step;
//! * `self-triggered/`: each control held for the analytic τ_k (clamped to
//!   `[τ_min, τ_max]`);
//! * `self-triggered-numerical/`: held for the numerical τ_k;
//! * `zeta-*/`: fixed-step runs with τ_k evaluated for a range of ζ.
//!
//! Top level: `summary.json` (the runs' outcomes, trigger counts, τ and L_f
//! statistics, the ζ sweep), `lipschitz.png` (L_f and τ_k over the
//! fixed-step run, Fig. 2), `tau-vs-zeta.png`.

use super::{ExperimentArgs, Table};
use crate::error::Result;
use crate::scenario::{self, RunOutput, RunSummary};
use crate::stats;
use bayes_cbf::control::TriggerReport;
use serde::Serialize;

/// A fixed-step run at one margin ζ, τ_k evaluated.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ZetaRun {
    /// The margin.
    pub zeta: f64,
    /// Median analytic `τ_k` over the run (s).
    pub tau_analytic_median_s: f64,
    /// Median numerical `τ_k` over the run (s).
    pub tau_numerical_median_s: f64,
    /// Closest obstacle distance.
    pub min_obstacle_distance: Option<f64>,
    /// Distance to the goal at the end.
    pub final_goal_distance: Option<f64>,
    /// Entered an obstacle.
    pub collided: bool,
}

/// Median `τ_k` at one ζ on the self-triggered run's data.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TauAtZeta {
    /// The margin.
    pub zeta: f64,
    /// Median analytic `τ_k` (s).
    pub tau_analytic_median_s: f64,
    /// Median numerical `τ_k` (s).
    pub tau_numerical_median_s: f64,
}

/// `summary.json` of `ackermann-triggering`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Summary {
    /// `ackermann-triggering`.
    pub scenario: &'static str,
    /// Seed.
    pub seed: u64,
    /// Reduced run.
    pub quick: bool,
    /// Horizon of every run (s).
    pub horizon_s: f64,
    /// Time-triggered at `dt`, `τ_k` evaluated: the run's summary.
    pub fixed_step: RunSummary,
    /// Held for the analytic `τ_k`.
    pub self_triggered: RunSummary,
    /// Held for the numerical `τ_k`.
    pub self_triggered_numerical: RunSummary,
    /// Fixed-step runs at each ζ.
    pub zeta_sweep: Vec<ZetaRun>,
    /// `τ_k` against ζ on the self-triggered run's data.
    pub tau_vs_zeta_on_self_triggered_data: Vec<TauAtZeta>,
}

/// The result of `ackermann-triggering`.
pub struct AckermannTriggering {
    /// The closed-loop runs, each with the subdirectory its files go to:
    /// `fixed-step`, `self-triggered`, `self-triggered-numerical`, then
    /// one `zeta-*` run per swept ζ.
    pub runs: Vec<(String, RunOutput)>,
    /// `summary.json`: the runs' outcomes, the ζ sweep and the τ–ζ curve.
    pub summary: Summary,
    /// `trajectory.csv`: the self-triggered run's (the run of Fig. 2;
    /// every run's is in its subdirectory too).
    pub tables: Vec<Table>,
}

impl AckermannTriggering {
    /// The run written to subdirectory `dir`.
    pub fn run(&self, dir: &str) -> Option<&RunOutput> {
        self.runs.iter().find(|(d, _)| d == dir).map(|(_, o)| o)
    }
}

/// ζ values of the trade-off sweep.
const ZETAS: &[f64] = &[0.003, 0.01, 0.03, 0.1, 0.3];

fn run_one(args: &ExperimentArgs, sets: &[String]) -> Result<RunOutput> {
    // the paper's evaluation: ζ at every step, short holds clamped
    let mut all = vec![
        format!("seed={}", args.seed),
        "trigger.margin_for_tau_min=false".into(),
    ];
    if args.quick {
        all.extend(
            [
                "steps=100",
                "trigger.grid=5",
                "trigger.samples=4",
                "outputs.animation=false",
            ]
            .map(String::from),
        );
    }
    all.extend_from_slice(sets);
    let (sc, _) = scenario::load("ackermann-self-triggered", &all)?;
    scenario::run_scenario(&sc, |_, _| {})
}

/// Runs the experiment.
pub fn run(args: &ExperimentArgs) -> Result<AckermannTriggering> {
    // fixed steps of 10 ms: refit every 40 steps (0.4 s, as the self-triggered run)
    let fixed_sets = [
        "trigger.self_triggered=false".to_string(),
        "learning.refit_every=40".into(),
    ];
    // each run's summary says which variant of the scenario it is
    let fixed = run_one(
        args,
        &[
            fixed_sets[0].clone(),
            fixed_sets[1].clone(),
            "description=\"ackermann-self-triggered at fixed 10 ms steps, refitting every \
             40 steps: the τ_k of Prop. 3 evaluated, not applied\""
                .into(),
        ],
    )?;
    let selft = run_one(args, &[])?;
    let selfn = run_one(
        args,
        &[
            "trigger.tau_from=\"numerical\"".into(),
            "description=\"ackermann-self-triggered, each control held for the numerical \
             estimate of τ_k\""
                .into(),
        ],
    )?;
    let zetas: &[f64] = if args.quick { &ZETAS[1..3] } else { ZETAS };
    let mut sweep = Vec::new();
    let mut zeta_runs = Vec::new();
    for &z in zetas {
        let o = run_one(
            args,
            &[
                fixed_sets[0].clone(),
                fixed_sets[1].clone(),
                format!("controller.zeta={z}"),
                "outputs.plots=false".into(),
            ],
        )?;
        let reps: Vec<_> = o.result.trigger_reports().collect();
        let tau_a = stats::median(&reps.iter().map(|t| t.tau_analytic).collect::<Vec<_>>());
        let tau_n = stats::median(
            &reps
                .iter()
                .filter_map(|t| t.tau_numerical)
                .collect::<Vec<_>>(),
        );
        let s = &o.summary;
        sweep.push(ZetaRun {
            zeta: z,
            tau_analytic_median_s: tau_a,
            tau_numerical_median_s: tau_n,
            min_obstacle_distance: s.min_obstacle_distance,
            final_goal_distance: s.final_goal_distance,
            collided: s.collided,
        });
        zeta_runs.push((format!("zeta-{z}"), o));
    }

    // τ against ζ on the self-triggered run's own L_f, L_h, L_∇h and ‖ẋ‖
    // (the corrected Prop. 3 with margin ζ, the worst case of an active
    // constraint, and the cuboid time at each trigger; median over the run):
    // the effect of ζ alone. Barriers of relative degree ≥ 2 keep their
    // margin h(x_k).
    let barriers = &selft.built.barriers;
    let (half_sides, tau_max): (Vec<f64>, f64) = selft
        .built
        .loop_settings
        .trigger
        .as_ref()
        .map(|t| {
            (
                t.lipschitz.sides.iter().map(|w| w / 2.0).collect(),
                t.tau_max,
            )
        })
        .unwrap_or_default();
    let tau_at = |z: f64, l: f64, r: &TriggerReport| -> f64 {
        let margins: Vec<f64> = barriers
            .iter()
            .zip(&r.margin)
            .map(|(b, &m)| if b.relative_degree() == 1 { z } else { m })
            .collect();
        r.tau_with(l, &margins, barriers, &half_sides, tau_max).0
    };
    let dense: Vec<f64> = (0..=12)
        .map(|i| 1e-3 * 10f64.powf(i as f64 / 4.0))
        .collect();
    let reps: Vec<_> = selft.result.trigger_reports().collect();
    let curve = |numerical: bool| -> Vec<f64> {
        dense
            .iter()
            .map(|&z| {
                stats::median(
                    &reps
                        .iter()
                        .filter_map(|r| {
                            let l = if numerical {
                                r.lipschitz.numerical?
                            } else {
                                r.lipschitz.analytic
                            };
                            Some(tau_at(z, l, r))
                        })
                        .collect::<Vec<_>>(),
                )
            })
            .collect()
    };
    let (curve_a, curve_n) = (curve(false), curve(true));
    let summary = Summary {
        scenario: "ackermann-triggering",
        seed: args.seed,
        quick: args.quick,
        horizon_s: fixed.scenario.dt * fixed.scenario.steps as f64,
        fixed_step: fixed.summary.clone(),
        self_triggered: selft.summary.clone(),
        self_triggered_numerical: selfn.summary.clone(),
        zeta_sweep: sweep,
        tau_vs_zeta_on_self_triggered_data: dense
            .iter()
            .zip(curve_a.iter().zip(&curve_n))
            .map(|(&zeta, (&a, &n))| TauAtZeta {
                zeta,
                tau_analytic_median_s: a,
                tau_numerical_median_s: n,
            })
            .collect(),
    };
    let mut runs = vec![
        ("fixed-step".to_string(), fixed),
        ("self-triggered".to_string(), selft),
        ("self-triggered-numerical".to_string(), selfn),
    ];
    runs.extend(zeta_runs);
    let tables = runs
        .iter()
        .filter(|(dir, _)| dir == "self-triggered")
        .map(|(_, o)| Table::new("trajectory.csv", scenario::trajectory_csv(o)))
        .collect();
    Ok(AckermannTriggering {
        runs,
        summary,
        tables,
    })
}
