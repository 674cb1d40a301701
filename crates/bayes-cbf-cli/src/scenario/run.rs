//! Running a scenario and writing its outputs.

use super::build::{build, Built};
use super::Scenario;
use crate::util::write_atomic;
use anyhow::{Context, Result};
use bayes_cbf::control::{TriggerReport, TriggerSettings};
use bayes_cbf::sim::{run_closed_loop, LoopResult, Monitor};
use serde_json::json;
use std::io::IsTerminal;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

/// Options of a run.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// Output directory.
    pub out: PathBuf,
    /// Progress on stderr (only shown on a terminal).
    pub progress: bool,
}

/// What a run produced, for callers that post-process it (figures).
pub struct RunOutput {
    /// The scenario as run.
    pub scenario: Scenario,
    /// The built objects (after the run: the controller and reference state).
    pub built: Built,
    /// The loop's result.
    pub result: LoopResult,
    /// The summary written to summary.json.
    pub summary: serde_json::Value,
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() - 1) as f64 * q).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

/// Runs `scenario` and writes `summary.json` and `trajectory.csv` into
/// `opts.out`.
pub fn run_scenario(scenario: &Scenario, opts: &RunOptions) -> Result<RunOutput> {
    let mut built = build(scenario)?;
    let monitors: Vec<Monitor> = built
        .obstacles
        .iter()
        .map(|&(c, r)| {
            Arc::new(move |x: &[f64]| ((x[0] - c[0]).powi(2) + (x[1] - c[1]).powi(2)).sqrt() - r)
                as Monitor
        })
        .collect();
    std::fs::create_dir_all(&opts.out)
        .with_context(|| format!("cannot create output directory '{}'", opts.out.display()))?;
    let show = opts.progress && std::io::stderr().is_terminal();
    let steps = scenario.steps;
    let started = Instant::now();
    let result = run_closed_loop(
        built.truth.as_ref(),
        built.model.clone(),
        &mut built.controller,
        &built.barriers,
        &monitors,
        built.reference.as_mut(),
        &scenario.start,
        &built.loop_settings,
        |k| {
            if show && (k % 10 == 0 || k + 1 == steps) {
                eprint!("\r{}: step {}/{steps}", scenario.name, k + 1);
                if k + 1 == steps {
                    eprintln!();
                }
            }
        },
    )
    .with_context(|| format!("scenario '{}'", scenario.name))?;
    let wall = started.elapsed().as_secs_f64();
    let summary = summarise(scenario, &built, &result, wall);
    write_atomic(
        &opts.out.join("summary.json"),
        (serde_json::to_string_pretty(&summary)? + "\n").as_bytes(),
    )?;
    write_atomic(
        &opts.out.join("trajectory.csv"),
        trajectory_csv(&built, &result).as_bytes(),
    )?;
    Ok(RunOutput {
        scenario: scenario.clone(),
        built,
        result,
        summary,
    })
}

fn summarise(s: &Scenario, built: &Built, r: &LoopResult, wall: f64) -> serde_json::Value {
    let mut us: Vec<f64> = r.records.iter().map(|x| x.control_us).collect();
    us.sort_by(|a, b| a.total_cmp(b));
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
    let refits = r.records.iter().filter(|x| x.refit).count();
    let fallback_steps = r
        .records
        .iter()
        .filter(|x| x.status == "infeasible")
        .count();
    let trace_start = r.records.first().map(|x| x.trace_cov);
    let trigger = built
        .loop_settings
        .trigger
        .as_ref()
        .map(|ts| trigger_summary(ts, r));
    let trace_end = r.records.last().map(|x| x.trace_cov);
    json!({
        "scenario": s.name,
        "description": s.description,
        "seed": s.seed,
        "steps": s.steps,
        "dt": s.dt,
        "collided": collided,
        "safe": safe,
        "min_barrier": r.min_barrier,
        "min_obstacle_distance": min_obstacle,
        "final_state": r.final_state,
        "final_goal_distance": goal_distance,
        "infeasible_steps": r.infeasible_steps,
        "fallback": s.controller.fallback,
        "fallback_steps": fallback_steps,
        "triggers": r.records.len(),
        "self_triggered": built.loop_settings.trigger.as_ref().is_some_and(|t| t.hold),
        "trigger": trigger,
        "control_step_us": {"p50": percentile(&us, 0.5), "p99": percentile(&us, 0.99), "max": us.last().copied().unwrap_or(f64::NAN)},
        "probability": s.controller.probability,
        "refits": refits,
        "data_size": r.model.len(),
        "trace_cov": {"start": trace_start, "end": trace_end},
        "wall_time_s": wall,
    })
}

/// Median, mean, minimum and maximum of `v` (NaN-free), as JSON.
fn stats(mut v: Vec<f64>) -> serde_json::Value {
    v.retain(|x| x.is_finite());
    if v.is_empty() {
        return serde_json::Value::Null;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    json!({
        "median": percentile(&v, 0.5),
        "mean": v.iter().sum::<f64>() / v.len() as f64,
        "min": v[0],
        "max": v[v.len() - 1],
    })
}

/// The self-triggering part of the summary: holds, `τ_k` and `L_f`, both
/// estimates, and how often the hold was clamped.
fn trigger_summary(ts: &TriggerSettings, r: &LoopResult) -> serde_json::Value {
    let reps: Vec<_> = r
        .records
        .iter()
        .filter_map(|x| x.trigger.as_ref())
        .collect();
    let field = |f: &dyn Fn(&TriggerReport) -> Option<f64>| -> Vec<f64> {
        reps.iter().filter_map(|t| f(t)).collect()
    };
    let la = field(&|t| Some(t.lipschitz.analytic));
    let ln = field(&|t| t.lipschitz.numerical);
    let ratio: Vec<f64> = reps
        .iter()
        .filter_map(|t| t.lipschitz.numerical.map(|n| t.lipschitz.analytic / n))
        .collect();
    let numerical_exceeds = reps
        .iter()
        .filter(|t| {
            t.lipschitz
                .numerical
                .is_some_and(|n| n > t.lipschitz.analytic)
        })
        .count();
    json!({
        "delta_l": ts.lipschitz.delta_l,
        "cuboid": ts.lipschitz.sides,
        "grid": ts.lipschitz.grid,
        "samples": ts.lipschitz.samples,
        "zeta": ts.zeta,
        "zeta_b": ts.zeta_b,
        "l_alpha": ts.l_alpha,
        "tau_min": ts.tau_min,
        "tau_max": ts.tau_max,
        "tau_from": ts.tau_from.name(),
        "hold_s": stats(r.records.iter().map(|x| x.hold).collect()),
        "tau_analytic_s": stats(field(&|t| Some(t.tau_analytic))),
        "tau_numerical_s": stats(field(&|t| t.tau_numerical)),
        "lipschitz_analytic": stats(la),
        "lipschitz_numerical": stats(ln),
        "lipschitz_ratio_analytic_over_numerical": stats(ratio),
        "numerical_above_analytic": numerical_exceeds,
        "evaluation_us": stats(field(&|t| Some(t.eval_us))),
        "clamped_to_tau_min": reps.iter().filter(|t| t.clamped_low).count(),
        "clamped_to_tau_max": reps.iter().filter(|t| !t.clamped_low && t.hold >= ts.tau_max).count(),
    })
}

fn trajectory_csv(built: &Built, r: &LoopResult) -> String {
    let n = built.truth.n();
    let m = built.truth.m();
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
        row.push(rec.status.to_string());
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
