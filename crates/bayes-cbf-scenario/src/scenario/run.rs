//! Running a scenario: the closed loop, its typed [`RunSummary`] and the
//! trajectory table (`trajectory.csv`).

use super::build::{build, Built};
use super::Scenario;
use crate::error::{Context, Result};
use crate::stats::quantile;
use bayes_cbf::control::{TriggerReport, TriggerSettings};
use bayes_cbf::sim::{ClosedLoop, LoopResult, Monitor, StepStatus};
use serde::{Deserialize, Serialize};
use std::sync::Arc;
use std::time::Instant;

/// What a run produced, for callers that post-process it (figures, files).
pub struct RunOutput {
    /// The scenario as run.
    pub scenario: Scenario,
    /// The built objects (after the run: the controller and reference state).
    pub built: Built,
    /// The loop's result.
    pub result: LoopResult,
    /// The summary (`summary.json`).
    pub summary: RunSummary,
}

/// Median, 99th percentile and maximum (µs).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Percentiles {
    /// Median.
    pub p50: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Maximum.
    pub max: f64,
}

/// Median, mean, minimum and maximum of the finite values of a series.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    /// Median.
    pub median: f64,
    /// Mean.
    pub mean: f64,
    /// Minimum.
    pub min: f64,
    /// Maximum.
    pub max: f64,
}

/// `tr(B_k(x, x) ⊗ A)` at the first and the last step.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TraceCov {
    /// At the first step.
    pub start: Option<f64>,
    /// At the last step.
    pub end: Option<f64>,
}

/// The outcome of a closed-loop run (`summary.json`; `interfaces.md`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunSummary {
    /// Scenario name.
    pub scenario: String,
    /// Its one-line description.
    pub description: String,
    /// Seed of the run.
    pub seed: u64,
    /// Control steps (fixed-step triggers).
    pub steps: usize,
    /// Control period (s).
    pub dt: f64,
    /// Entered an obstacle disc (scenarios with obstacles), or a barrier
    /// went negative on the fine grid (others).
    pub collided: bool,
    /// Every barrier stayed ≥ 0 on the fine grid.
    pub safe: bool,
    /// Minimum of each barrier `h` over the fine grid.
    pub min_barrier: Vec<f64>,
    /// Smallest signed distance to an obstacle disc (negative: inside).
    pub min_obstacle_distance: Option<f64>,
    /// State after the last step.
    pub final_state: Vec<f64>,
    /// Distance to the goal at the end (position only for vehicles).
    pub final_goal_distance: Option<f64>,
    /// Steps whose SOCP was infeasible.
    pub infeasible_steps: usize,
    /// The declared fallback.
    pub fallback: String,
    /// Steps that applied the fallback.
    pub fallback_steps: usize,
    /// Control computations (steps, or triggers when self-triggered).
    pub triggers: usize,
    /// Each control was held for `τ_k`.
    pub self_triggered: bool,
    /// Self-triggering statistics, when evaluated.
    pub trigger: Option<TriggerSummary>,
    /// Time of the control step (µs).
    pub control_step_us: Percentiles,
    /// Required probability `p`.
    pub probability: f64,
    /// Hyperparameter refits.
    pub refits: usize,
    /// Observations in the final model.
    pub data_size: usize,
    /// Posterior uncertainty at the first and last step.
    pub trace_cov: TraceCov,
    /// Wall time of the run (s).
    pub wall_time_s: f64,
}

/// Holds, `τ_k` and `L_f` (both estimates) over a run, and how often the
/// hold was clamped.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TriggerSummary {
    /// δ_L.
    pub delta_l: f64,
    /// Cuboid side lengths.
    pub cuboid: Vec<f64>,
    /// Grid nodes per side.
    pub grid: usize,
    /// Sampled Jacobians per node.
    pub samples: usize,
    /// Margin ζ of relative-degree-1 barriers.
    pub zeta: f64,
    /// Shift ζ_b of barriers of relative degree ≥ 2.
    pub zeta_b: f64,
    /// Lipschitz constant of the class-K function.
    pub l_alpha: f64,
    /// Shortest hold (s).
    pub tau_min: f64,
    /// Longest hold (s).
    pub tau_max: f64,
    /// The estimate that sets the hold.
    pub tau_from: String,
    /// Holds (s).
    pub hold_s: Option<Stats>,
    /// `τ_k` from the analytic bound (s).
    pub tau_analytic_s: Option<Stats>,
    /// `τ_k` from the numerical estimate (s).
    pub tau_numerical_s: Option<Stats>,
    /// Analytic `L_f` (Lemma 3).
    pub lipschitz_analytic: Option<Stats>,
    /// Numerical `L_f`.
    pub lipschitz_numerical: Option<Stats>,
    /// Ratio analytic / numerical.
    pub lipschitz_ratio_analytic_over_numerical: Option<Stats>,
    /// Evaluations whose numerical estimate exceeded the analytic bound.
    pub numerical_above_analytic: usize,
    /// Time of one trigger evaluation (µs).
    pub evaluation_us: Option<Stats>,
    /// Holds clamped to `tau_min`.
    pub clamped_to_tau_min: usize,
    /// Holds clamped to `tau_max`.
    pub clamped_to_tau_max: usize,
}

/// Runs `scenario`; `progress(k, steps)` is called after each step.
pub fn run_scenario(
    scenario: &Scenario,
    mut progress: impl FnMut(usize, usize),
) -> Result<RunOutput> {
    let mut built = build(scenario)?;
    let monitors: Vec<Monitor> = built
        .obstacles
        .iter()
        .map(|&(c, r)| {
            Arc::new(move |x: &[f64]| ((x[0] - c[0]).powi(2) + (x[1] - c[1]).powi(2)).sqrt() - r)
                as Monitor
        })
        .collect();
    let steps = scenario.steps;
    let started = Instant::now();
    let result = ClosedLoop::new(
        built.truth.as_ref(),
        built.model.clone(),
        &mut built.controller,
        &built.barriers,
        built.reference.as_mut(),
        &scenario.start,
        &built.loop_settings,
    )
    .map(|l| l.with_monitors(&monitors))
    .and_then(|l| l.run(&mut |k, _: &_| progress(k, steps)))
    .with_context(|| format!("scenario '{}'", scenario.name))?;
    let wall = started.elapsed().as_secs_f64();
    let summary = summarise(scenario, &built, &result, wall);
    Ok(RunOutput {
        scenario: scenario.clone(),
        built,
        result,
        summary,
    })
}

fn summarise(s: &Scenario, built: &Built, r: &LoopResult, wall: f64) -> RunSummary {
    let us: Vec<f64> = r.records.iter().map(|x| x.control_us).collect();
    let min_obstacle = r.min_monitor.iter().cloned().fold(f64::INFINITY, f64::min);
    let min_obstacle = if built.obstacles.is_empty() {
        None
    } else {
        Some(min_obstacle)
    };
    let safe = r.min_barrier.iter().all(|&h| h >= 0.0);
    let collided = match min_obstacle {
        Some(d) => d < 0.0,
        None => !safe,
    };
    let goal_distance = s.goal.as_ref().map(|g| {
        let k = if built.obstacles.is_empty() {
            g.len()
        } else {
            2
        };
        (0..k)
            .map(|i| (r.final_state[i] - g[i]).powi(2))
            .sum::<f64>()
            .sqrt()
    });
    let fallback_steps = r
        .records
        .iter()
        .filter(|x| x.status == StepStatus::Infeasible)
        .count();
    RunSummary {
        scenario: s.name.clone(),
        description: s.description.clone(),
        seed: s.seed,
        steps: s.steps,
        dt: s.dt,
        collided,
        safe,
        min_barrier: r.min_barrier.clone(),
        min_obstacle_distance: min_obstacle,
        final_state: r.final_state.clone(),
        final_goal_distance: goal_distance,
        infeasible_steps: r.infeasible_steps,
        fallback: s.controller.fallback.clone(),
        fallback_steps,
        triggers: r.records.len(),
        self_triggered: built.loop_settings.trigger.as_ref().is_some_and(|t| t.hold),
        trigger: built
            .loop_settings
            .trigger
            .as_ref()
            .map(|ts| trigger_summary(ts, r)),
        control_step_us: Percentiles {
            p50: quantile(&us, 0.5),
            p99: quantile(&us, 0.99),
            max: us.iter().copied().fold(f64::NAN, f64::max),
        },
        probability: s.controller.probability,
        refits: r.records.iter().filter(|x| x.refit).count(),
        data_size: r.model.len(),
        trace_cov: TraceCov {
            start: r.records.first().map(|x| x.trace_cov),
            end: r.records.last().map(|x| x.trace_cov),
        },
        wall_time_s: wall,
    }
}

/// Median, mean, minimum and maximum of the finite values of `v`; `None`
/// when there are none.
fn stats(mut v: Vec<f64>) -> Option<Stats> {
    v.retain(|x| x.is_finite());
    if v.is_empty() {
        return None;
    }
    Some(Stats {
        median: quantile(&v, 0.5),
        mean: v.iter().sum::<f64>() / v.len() as f64,
        min: v.iter().copied().fold(f64::INFINITY, f64::min),
        max: v.iter().copied().fold(f64::NEG_INFINITY, f64::max),
    })
}

/// The self-triggering part of the summary.
fn trigger_summary(ts: &TriggerSettings, r: &LoopResult) -> TriggerSummary {
    let reps: Vec<&TriggerReport> = r
        .records
        .iter()
        .filter_map(|x| x.trigger.as_ref())
        .collect();
    let field = |f: &dyn Fn(&TriggerReport) -> Option<f64>| -> Vec<f64> {
        reps.iter().filter_map(|t| f(t)).collect()
    };
    let ratio: Vec<f64> = reps
        .iter()
        .filter_map(|t| t.lipschitz.numerical.map(|n| t.lipschitz.analytic / n))
        .collect();
    TriggerSummary {
        delta_l: ts.lipschitz.delta_l,
        cuboid: ts.lipschitz.sides.clone(),
        grid: ts.lipschitz.grid,
        samples: ts.lipschitz.samples,
        zeta: ts.zeta,
        zeta_b: ts.zeta_b,
        l_alpha: ts.l_alpha,
        tau_min: ts.tau_min,
        tau_max: ts.tau_max,
        tau_from: ts.tau_from.name().to_string(),
        hold_s: stats(r.records.iter().map(|x| x.hold).collect()),
        tau_analytic_s: stats(field(&|t| Some(t.tau_analytic))),
        tau_numerical_s: stats(field(&|t| t.tau_numerical)),
        lipschitz_analytic: stats(field(&|t| Some(t.lipschitz.analytic))),
        lipschitz_numerical: stats(field(&|t| t.lipschitz.numerical)),
        lipschitz_ratio_analytic_over_numerical: stats(ratio),
        numerical_above_analytic: reps
            .iter()
            .filter(|t| {
                t.lipschitz
                    .numerical
                    .is_some_and(|n| n > t.lipschitz.analytic)
            })
            .count(),
        evaluation_us: stats(field(&|t| Some(t.eval_us))),
        clamped_to_tau_min: reps.iter().filter(|t| t.clamped_low).count(),
        clamped_to_tau_max: reps
            .iter()
            .filter(|t| !t.clamped_low && t.hold >= ts.tau_max)
            .count(),
    }
}

/// The trajectory table of a run (`trajectory.csv`): one row per step with
/// time, state, control, reference, each barrier's value, fine-grid
/// minimum and stochastic condition, the CLF slack, the posterior trace,
/// solver status, `p*`, timing, data size, refits and hold, and the
/// trigger's parts when self-triggering is evaluated.
pub fn trajectory_csv(out: &RunOutput) -> String {
    trajectory_table(&out.built, &out.result)
}

fn trajectory_table(built: &Built, r: &LoopResult) -> String {
    let n = built.truth.state_dim();
    let m = built.truth.control_dim();
    let nb = built.barriers.len();
    let mut head: Vec<String> = vec!["t".into()];
    head.extend((1..=n).map(|i| format!("x{i}")));
    head.extend((1..=m).map(|i| format!("u{i}")));
    head.extend((1..=m).map(|i| format!("u_ref{i}")));
    for i in 0..nb {
        head.push(format!("h{i}"));
        head.push(format!("h{i}_fine_min"));
        head.push(format!("scbc{i}"));
    }
    head.extend(
        [
            "sclc",
            "trace_cov",
            "status",
            "p_star",
            "control_us",
            "data_size",
            "refit",
            "hold",
        ]
        .iter()
        .map(|s| s.to_string()),
    );
    let with_trigger = built.loop_settings.trigger.is_some();
    if with_trigger {
        head.extend(
            [
                "lipschitz_analytic",
                "lipschitz_numerical",
                "tau_analytic",
                "tau_numerical",
                "l_h",
                "xdot_norm",
                "clamped",
            ]
            .iter()
            .map(|s| s.to_string()),
        );
    }
    let mut out = head.join(",") + "\n";
    let f = |v: f64| {
        if v.is_finite() {
            format!("{v}")
        } else {
            String::new()
        }
    };
    for rec in &r.records {
        let mut row: Vec<String> = vec![f(rec.t)];
        row.extend(rec.x.iter().map(|v| f(*v)));
        row.extend(rec.u.iter().map(|v| f(*v)));
        row.extend(rec.u_ref.iter().map(|v| f(*v)));
        for i in 0..nb {
            row.push(f(rec.h[i]));
            row.push(f(rec.h_fine_min[i]));
            row.push(f(rec.scbc[i]));
        }
        row.push(rec.sclc.map(f).unwrap_or_default());
        row.push(f(rec.trace_cov));
        row.push(rec.status.name().to_string());
        row.push(rec.p_star.map(f).unwrap_or_default());
        row.push(f(rec.control_us));
        row.push(rec.data_size.to_string());
        row.push(u8::from(rec.refit).to_string());
        row.push(f(rec.hold));
        if with_trigger {
            let (l, t) = match &rec.trigger {
                Some(t) => (Some(&t.lipschitz), Some(t)),
                None => (None, None),
            };
            row.push(l.map(|l| f(l.analytic)).unwrap_or_default());
            row.push(l.and_then(|l| l.numerical).map(f).unwrap_or_default());
            row.push(t.map(|t| f(t.tau_analytic)).unwrap_or_default());
            row.push(t.and_then(|t| t.tau_numerical).map(f).unwrap_or_default());
            row.push(
                t.map(|t| f(t.l_h.iter().cloned().fold(0.0, f64::max)))
                    .unwrap_or_default(),
            );
            row.push(t.map(|t| f(t.xdot_norm)).unwrap_or_default());
            row.push(
                t.map(|t| u8::from(t.clamped_low).to_string())
                    .unwrap_or_default(),
            );
        }
        out += &(row.join(",") + "\n");
    }
    out
}
