//! Running a scenario: the closed loop, its typed [`RunSummary`] and the
//! trajectory table (`trajectory.csv`).

use super::build::{build, Built};
use super::Scenario;
use crate::error::{Context, Result};
use crate::stats::quantile;
use bayes_cbf::control::{TriggerReport, TriggerSettings};
use bayes_cbf::sim::{ClosedLoop, LoopResult, Monitor, StepRecord, StepStatus};
use serde::{Deserialize, Serialize};
use std::sync::atomic::AtomicBool;
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

/// `tr(B_k(x, x) ⊗ A_row)` at the first and the last step (`A_row`: the
/// model's row covariance, `A` with the known rows zero).
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
    /// Distance to the goal at the end (of the position only, in scenarios
    /// with obstacles).
    pub final_goal_distance: Option<f64>,
    /// Steps whose SOCP was infeasible.
    pub infeasible_steps: usize,
    /// The fallback of infeasible steps: the declared one, or the default
    /// ([`super::ControllerSpec::fallback_name`]).
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
    /// The model was the true system (`gp.oracle`): a check of the
    /// scenario's design, not of learning.
    #[serde(default)]
    pub oracle: bool,
    /// Posterior uncertainty at the first and last step.
    pub trace_cov: TraceCov,
    /// Wall time of the run (s).
    pub wall_time_s: f64,
    /// The warnings the run issued, the first of each kind, in order
    /// (shown once per run or sweep; recorded for each run): those of the
    /// run's own thread ([`bayes_cbf::warnings::Record`]), not of a refit
    /// in the background.
    #[serde(default)]
    pub warnings: Vec<RunWarning>,
}

/// A warning a run issued.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RunWarning {
    /// Its kind: the name of the place that issues it
    /// ([`bayes_cbf::warnings::WarnOnce::name`]), as `clamped_holds`.
    pub kind: String,
    /// The warning.
    pub message: String,
}

impl RunWarning {
    /// The warnings of `record`.
    pub fn of(record: bayes_cbf::warnings::Record) -> Vec<RunWarning> {
        record
            .finish()
            .into_iter()
            .map(|i| RunWarning {
                kind: i.site.to_string(),
                message: i.message,
            })
            .collect()
    }
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
    /// Time the state provably stays in the cuboid (s).
    pub tau_cuboid_s: Option<Stats>,
    /// High-probability bound on `‖ẋ_k‖`.
    pub xdot_norm: Option<Stats>,
    /// Posterior mean `‖M_k(x_k)u̲_k‖`.
    pub xdot_mean_norm: Option<Stats>,
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
    /// Solve the steps whose `τ_k` fell below `tau_min` again with a raised
    /// margin.
    pub margin_for_tau_min: bool,
    /// Steps solved with a raised margin (their hold reached `tau_min`, or
    /// came closer to it).
    pub raised_margins: usize,
}

/// Runs `scenario`; `progress(k, steps)` is called after each step.
pub fn run_scenario(scenario: &Scenario, progress: impl FnMut(usize, usize)) -> Result<RunOutput> {
    run_scenario_until(scenario, progress, Arc::new(AtomicBool::new(false)))
}

/// [`run_scenario`], stopped once `stop` is set (by another thread: a
/// Ctrl-C handler, a deadline) with [`bayes_cbf::Error::Interrupted`]
/// before the next step ([`ClosedLoop::with_stop`]).
pub fn run_scenario_until(
    scenario: &Scenario,
    mut progress: impl FnMut(usize, usize),
    stop: Arc<AtomicBool>,
) -> Result<RunOutput> {
    let _warnings = bayes_cbf::warnings::Scope::enter();
    let record = bayes_cbf::warnings::Record::start();
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
        &built.start,
        &built.loop_settings,
    )
    .map(|l| l.with_monitors(&monitors).with_stop(stop))
    .and_then(|l| l.run(&mut |k, _: &_| progress(k, steps)))
    .with_context(|| format!("scenario '{}'", scenario.name))?;
    let wall = started.elapsed().as_secs_f64();
    // labels over dt (self-triggered: over the holds), each with the noise
    // σ_w/√τ of the process noise
    let holding = built.loop_settings.trigger.as_ref().is_some_and(|t| t.hold);
    let dt = (!holding).then_some(scenario.dt);
    let hold = dt.or_else(|| super::build::median_hold(&result.records));
    let label_noise = scenario.sim.process_noise / hold.unwrap_or(scenario.dt).sqrt();
    super::build::warn_known_row_misfit(
        &result.model,
        &built.barriers,
        (dt, label_noise),
        scenario.seed,
    );
    super::build::warn_crossing_outside(
        &built.barriers,
        built.truth.as_ref(),
        &result.records,
        scenario.seed,
    );
    let predictive = built.controller.settings().predictive;
    super::build::warn_mostly_infeasible(
        &result.records,
        scenario.controller.fallback_name(),
        scenario.seed,
        || {
            predictive
                .then(|| {
                    super::build::noise_above_labels(
                        &built.controller,
                        &result.model,
                        &result.records,
                        label_noise,
                    )
                })
                .flatten()
        },
    );
    super::build::warn_crossing_in_infeasible_step(
        built.barriers.len(),
        &result.records,
        (
            scenario.controller.fallback_name(),
            built.controller.settings().u_min.is_some(),
            built.loop_settings.data,
        ),
        scenario.seed,
    );
    super::build::warn_crossing_in_met_step(
        &built.barriers,
        built.truth.as_ref(),
        &result.records,
        (predictive, scenario.sim.process_noise),
        scenario.seed,
    );
    if predictive && !scenario.gp.oracle {
        super::build::warn_predictive_standoff(
            &built.barriers,
            &result.model,
            &result.records,
            (built.controller.settings().probability, label_noise),
            scenario.seed,
        );
    }
    if let Some(t) = built.loop_settings.trigger.as_ref().filter(|t| t.hold) {
        super::build::warn_clamped_holds(&result.records, t, scenario.seed);
        if !scenario.gp.oracle && scenario.learning.update_every > 0 {
            super::build::warn_noise_below_held_labels(
                &built.model,
                scenario.sim.process_noise,
                &result.records,
            );
        }
    }
    let mut summary = summarise(scenario, &built, &result, wall);
    summary.warnings = RunWarning::of(record);
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
        fallback: s.controller.fallback_name().to_string(),
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
        oracle: s.gp.oracle,
        trace_cov: TraceCov {
            start: r.records.first().map(|x| x.trace_cov),
            end: r.records.last().map(|x| x.trace_cov),
        },
        wall_time_s: wall,
        warnings: Vec::new(),
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
    let reps: Vec<&TriggerReport> = r.trigger_reports().collect();
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
        tau_min: ts.tau_min,
        tau_max: ts.tau_max,
        tau_from: ts.tau_from.name().to_string(),
        hold_s: stats(r.records.iter().map(|x| x.hold).collect()),
        tau_analytic_s: stats(field(&|t| Some(t.tau_analytic))),
        tau_numerical_s: stats(field(&|t| t.tau_numerical)),
        tau_cuboid_s: stats(field(&|t| Some(t.tau_cuboid).filter(|v| v.is_finite()))),
        xdot_norm: stats(field(&|t| Some(t.xdot_norm))),
        xdot_mean_norm: stats(field(&|t| Some(t.xdot_mean_norm))),
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
        margin_for_tau_min: ts.margin_for_tau_min,
        raised_margins: reps.iter().filter(|t| t.raised_zeta.is_some()).count(),
    }
}

/// One column of the trajectory table.
#[derive(Debug, Clone, PartialEq)]
pub enum Column {
    /// Numbers; NaN where the value is absent (written as an empty field).
    Numbers(Vec<f64>),
    /// Words (the solver status).
    Words(Vec<&'static str>),
}

/// The trajectory of a run as named columns, one row per step: time,
/// state, control, reference, each barrier's value, fine-grid minimum and
/// stochastic condition, the CLF slack, the posterior trace, solver status,
/// `p*`, timing, data size, refits and hold, and the trigger's parts when
/// self-triggering is evaluated (`trajectory.csv`, interfaces.md).
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    /// `(name, column)` in file order.
    pub columns: Vec<(String, Column)>,
}

impl Trajectory {
    /// The table of `out`.
    pub fn of(out: &RunOutput) -> Self {
        trajectory_columns(&out.built, &out.result)
    }

    /// CSV text: a header and one line per step; non-finite numbers are
    /// written as empty fields.
    pub fn to_csv(&self) -> String {
        let rows = self
            .columns
            .first()
            .map(|(_, c)| match c {
                Column::Numbers(v) => v.len(),
                Column::Words(v) => v.len(),
            })
            .unwrap_or(0);
        let head: Vec<&str> = self.columns.iter().map(|(n, _)| n.as_str()).collect();
        let mut out = head.join(",") + "\n";
        for r in 0..rows {
            for (i, (_, c)) in self.columns.iter().enumerate() {
                if i > 0 {
                    out.push(',');
                }
                match c {
                    Column::Numbers(v) if v[r].is_finite() => out += &format!("{}", v[r]),
                    Column::Numbers(_) => {}
                    Column::Words(v) => out += v[r],
                }
            }
            out.push('\n');
        }
        out
    }
}

/// The trajectory table of a run (`trajectory.csv`).
pub fn trajectory_csv(out: &RunOutput) -> String {
    Trajectory::of(out).to_csv()
}

fn trajectory_columns(built: &Built, r: &LoopResult) -> Trajectory {
    let n = built.truth.state_dim();
    let m = built.truth.control_dim();
    let nb = built.barriers.len();
    let recs = &r.records;
    let col = |f: &dyn Fn(&StepRecord) -> f64| Column::Numbers(recs.iter().map(f).collect());
    let absent = f64::NAN;
    let mut columns: Vec<(String, Column)> = vec![("t".into(), col(&|rec| rec.t))];
    for i in 0..n {
        columns.push((format!("x{}", i + 1), col(&|rec| rec.x[i])));
    }
    for i in 0..m {
        columns.push((format!("u{}", i + 1), col(&|rec| rec.u[i])));
    }
    for i in 0..m {
        columns.push((format!("u_ref{}", i + 1), col(&|rec| rec.u_ref[i])));
    }
    for i in 0..nb {
        columns.push((format!("h{i}"), col(&|rec| rec.h[i])));
        columns.push((format!("h{i}_fine_min"), col(&|rec| rec.h_fine_min[i])));
        columns.push((format!("scbc{i}"), col(&|rec| rec.scbc[i])));
    }
    // the recalibration's variance inflation of each barrier's condition
    if built.loop_settings.recalibration.is_some() {
        for i in 0..nb {
            columns.push((
                format!("kappa{i}"),
                col(&|rec| rec.inflation.get(i).copied().unwrap_or(absent)),
            ));
        }
    }
    let status = Column::Words(recs.iter().map(|rec| rec.status.name()).collect());
    let mut rest: Vec<(&str, Column)> = vec![
        ("sclc", col(&|rec| rec.sclc.unwrap_or(absent))),
        ("trace_cov", col(&|rec| rec.trace_cov)),
        ("status", status),
        ("p_star", col(&|rec| rec.p_star.unwrap_or(absent))),
        ("control_us", col(&|rec| rec.control_us)),
        ("data_size", col(&|rec| rec.data_size as f64)),
        ("refit", col(&|rec| f64::from(u8::from(rec.refit)))),
        ("hold", col(&|rec| rec.hold)),
    ];
    if built.loop_settings.trigger.is_some() {
        rest.extend([
            (
                "lipschitz_analytic",
                col(&|rec| {
                    rec.trigger
                        .as_ref()
                        .map(|t| &t.lipschitz)
                        .map_or(absent, |l| l.analytic)
                }),
            ),
            (
                "lipschitz_numerical",
                col(&|rec| {
                    rec.trigger
                        .as_ref()
                        .map(|t| &t.lipschitz)
                        .and_then(|l| l.numerical)
                        .unwrap_or(absent)
                }),
            ),
            (
                "tau_analytic",
                col(&|rec| rec.trigger.as_ref().map_or(absent, |t| t.tau_analytic)),
            ),
            (
                "tau_numerical",
                col(&|rec| {
                    rec.trigger
                        .as_ref()
                        .and_then(|t| t.tau_numerical)
                        .unwrap_or(absent)
                }),
            ),
            (
                "tau_cuboid",
                col(&|rec| rec.trigger.as_ref().map_or(absent, |t| t.tau_cuboid)),
            ),
            (
                "xdot_norm",
                col(&|rec| rec.trigger.as_ref().map_or(absent, |t| t.xdot_norm)),
            ),
            (
                "xdot_mean_norm",
                col(&|rec| rec.trigger.as_ref().map_or(absent, |t| t.xdot_mean_norm)),
            ),
            (
                "clamped",
                col(&|rec| {
                    rec.trigger
                        .as_ref()
                        .map_or(absent, |t| f64::from(u8::from(t.clamped_low)))
                }),
            ),
            (
                "raised_zeta",
                col(&|rec| {
                    rec.trigger
                        .as_ref()
                        .and_then(|t| t.raised_zeta)
                        .unwrap_or(absent)
                }),
            ),
        ]);
    }
    columns.extend(rest.into_iter().map(|(n, c)| (n.to_string(), c)));
    if built.loop_settings.trigger.is_some() {
        let part =
            |f: &dyn Fn(&TriggerReport) -> f64| col(&|rec| rec.trigger.as_ref().map_or(absent, f));
        for i in 0..nb {
            columns.push((format!("l_h{i}"), part(&|t| t.l_h[i])));
            columns.push((format!("l_grad_h{i}"), part(&|t| t.l_grad_h[i])));
            columns.push((format!("margin{i}"), part(&|t| t.margin[i])));
        }
    }
    Trajectory { columns }
}
