//! `ackermann-triggering` (paper, Sec. VII-B "Evaluating triggering time",
//! Fig. 2): the Lipschitz constant of the learned vehicle dynamics and the
//! inter-trigger time τ_k, analytic (Lemma 3, Prop. 3) and numerical, over a
//! run; the self-triggered loop against fixed-step control over the same
//! horizon; and τ_k against the margin ζ.
//!
//! Runs (each a closed loop of the built-in scenario
//! `ackermann-self-triggered`, outputs in a subdirectory):
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

use super::ExperimentArgs;
use crate::plot::{render_png, Figure, Layer, Panel, PointShape};
use crate::scenario::{self, RunOptions, RunOutput};
use crate::util::write_atomic;
use anyhow::Result;
use bayes_cbf::control::{tau_relative_degree_one, tau_relative_degree_r};
use serde_json::json;

/// ζ values of the trade-off sweep.
const ZETAS: &[f64] = &[0.003, 0.01, 0.03, 0.1, 0.3];

fn median(mut v: Vec<f64>) -> f64 {
    v.retain(|x| x.is_finite());
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

fn run_one(args: &ExperimentArgs, dir: &str, sets: &[String]) -> Result<RunOutput> {
    let mut all = vec![format!("seed={}", args.seed)];
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
    let out = args.out.join(dir);
    let output = scenario::run_scenario(
        &sc,
        &RunOptions {
            out: out.clone(),
            progress: false,
        },
    )?;
    scenario::write_figures(&output, &out)?;
    eprintln!(
        "  {dir:<26} triggers {:>5}  collided {:<5}  min obstacle distance {:>6.3} m  goal distance {:.2} m",
        output.result.records.len(),
        output.summary["collided"],
        output.summary["min_obstacle_distance"]
            .as_f64()
            .unwrap_or(f64::NAN),
        output.summary["final_goal_distance"]
            .as_f64()
            .unwrap_or(f64::NAN),
    );
    Ok(output)
}

/// One run's part of the summary.
fn run_summary(o: &RunOutput) -> serde_json::Value {
    let s = &o.summary;
    json!({
        "triggers": s["triggers"],
        "self_triggered": s["self_triggered"],
        "collided": s["collided"],
        "safe": s["safe"],
        "min_barrier": s["min_barrier"],
        "min_obstacle_distance": s["min_obstacle_distance"],
        "final_goal_distance": s["final_goal_distance"],
        "infeasible_steps": s["infeasible_steps"],
        "trigger": s["trigger"],
    })
}

/// Runs the experiment.
pub fn run(args: &ExperimentArgs) -> Result<()> {
    std::fs::create_dir_all(&args.out)?;
    eprintln!("ackermann-triggering: Lipschitz bounds and inter-trigger times (Fig. 2)");
    // fixed steps of 10 ms: refit every 40 steps (0.4 s, as the self-triggered run)
    let fixed_sets = [
        "trigger.self_triggered=false".to_string(),
        "learning.refit_every=40".into(),
    ];
    let fixed = run_one(args, "fixed-step", &fixed_sets)?;
    let selft = run_one(args, "self-triggered", &[])?;
    let selfn = run_one(
        args,
        "self-triggered-numerical",
        &["trigger.tau_from=\"numerical\"".into()],
    )?;
    let zetas: &[f64] = if args.quick { &ZETAS[1..3] } else { ZETAS };
    let mut sweep = Vec::new();
    for &z in zetas {
        let o = run_one(
            args,
            &format!("zeta-{z}"),
            &[
                fixed_sets[0].clone(),
                fixed_sets[1].clone(),
                format!("controller.zeta={z}"),
                "outputs.plots=false".into(),
            ],
        )?;
        let reps: Vec<_> = o
            .result
            .records
            .iter()
            .filter_map(|r| r.trigger.as_ref())
            .collect();
        sweep.push(json!({
            "zeta": z,
            "tau_analytic_median_s": median(reps.iter().map(|t| t.tau_analytic).collect()),
            "tau_numerical_median_s": median(reps.iter().filter_map(|t| t.tau_numerical).collect()),
            "min_obstacle_distance": o.summary["min_obstacle_distance"],
            "final_goal_distance": o.summary["final_goal_distance"],
            "collided": o.summary["collided"],
        }));
    }

    // Fig. 2: L_f and τ_k over the self-triggered run (solid) and the
    // fixed-step run (dashed)
    type Pick<'a> = &'a dyn Fn(&bayes_cbf::control::TriggerReport) -> Option<f64>;
    let series = |o: &RunOutput, f: Pick| -> (Vec<f64>, Vec<f64>) {
        let recs = &o.result.records;
        (
            recs.iter().map(|r| r.t).collect(),
            recs.iter()
                .map(|r| r.trigger.as_ref().and_then(f).unwrap_or(f64::NAN))
                .collect(),
        )
    };
    let layers = |what: [(&str, Pick); 2]| -> Vec<Layer> {
        let mut v = Vec::new();
        for (run, o, dashed, width) in [
            ("self-triggered", &selft, false, 2),
            ("fixed step", &fixed, true, 1),
        ] {
            for (color, (name, f)) in what.iter().enumerate() {
                let (xs, ys) = series(o, *f);
                v.push(Layer::Line {
                    name: Some(format!("{name}, {run}")),
                    xs,
                    ys,
                    color,
                    width,
                    dashed,
                });
            }
        }
        v
    };
    let mut lp = Panel::new("Lipschitz constant of f_k on the cuboid", "t (s)", "L_f");
    lp.log_y = true;
    lp.layers = layers([
        ("analytic (Lemma 3)", &|r| Some(r.lipschitz.analytic)),
        ("numerical", &|r| r.lipschitz.numerical),
    ]);
    let mut tp = Panel::new("Inter-trigger time (Prop. 3)", "t (s)", "τ_k (s)");
    tp.log_y = true;
    tp.layers = layers([
        ("analytic", &|r| Some(r.tau_analytic)),
        ("numerical", &|r| r.tau_numerical),
    ]);
    tp.layers.push(Layer::HLine {
        y: selft
            .built
            .loop_settings
            .trigger
            .as_ref()
            .map_or(f64::NAN, |s| s.tau_min),
        color: 7,
        dashed: true,
        name: Some("τ_min".into()),
    });
    let fig = Figure {
        width: 1300,
        height: 550,
        rows: 1,
        cols: 2,
        title: Some(format!(
            "Ackermann vehicle learning online, δ_L = 1e-4, ζ = {}, cuboid (0.2, 0.2, π/50)",
            selft.scenario.controller.zeta
        )),
        panels: vec![lp, tp],
    };
    render_png(&fig, &args.out.join("lipschitz.png"))?;

    // τ against ζ on the self-triggered run's own L_f, L_h and ‖ẋ‖
    // (Prop. 3/5 at each trigger, median over the run): the effect of ζ alone
    let degrees: Vec<usize> = selft.built.barriers.iter().map(|b| b.degree()).collect();
    let ts = selft.built.loop_settings.trigger.clone();
    let tau_at = |z: f64, l: f64, r: &bayes_cbf::control::TriggerReport| -> f64 {
        // the sweep varies ζ of Prop. 3 and ζ_b of Prop. 5 together
        let (la, zb) = (ts.as_ref().map_or(1.0, |t| t.l_alpha), z);
        degrees
            .iter()
            .zip(&r.l_h)
            .map(|(&d, &lh)| {
                if d == 1 {
                    tau_relative_degree_one(l, z, la, lh, r.xdot_norm)
                } else {
                    tau_relative_degree_r(l, zb, lh, r.xdot_norm)
                }
            })
            .fold(f64::INFINITY, f64::min)
    };
    let dense: Vec<f64> = (0..=12)
        .map(|i| 1e-3 * 10f64.powf(i as f64 / 4.0))
        .collect();
    let reps: Vec<_> = selft
        .result
        .records
        .iter()
        .filter_map(|r| r.trigger.as_ref())
        .collect();
    let curve = |numerical: bool| -> Vec<f64> {
        dense
            .iter()
            .map(|&z| {
                median(
                    reps.iter()
                        .filter_map(|r| {
                            let l = if numerical {
                                r.lipschitz.numerical?
                            } else {
                                r.lipschitz.analytic
                            };
                            Some(tau_at(z, l, r))
                        })
                        .collect(),
                )
            })
            .collect()
    };
    let (curve_a, curve_n) = (curve(false), curve(true));
    let zs: Vec<f64> = sweep
        .iter()
        .map(|s| s["zeta"].as_f64().unwrap_or(f64::NAN))
        .collect();
    let col = |k: &str| -> Vec<f64> {
        sweep
            .iter()
            .map(|s| s[k].as_f64().unwrap_or(f64::NAN))
            .collect()
    };
    let mut zp = Panel::new(
        "Inter-trigger time against the margin ζ",
        "ζ",
        "median τ_k (s)",
    );
    zp.log_x = true;
    zp.log_y = true;
    zp.layers = vec![
        Layer::line(
            "analytic, self-triggered run (ζ = 0.01) data",
            dense.clone(),
            curve_a.clone(),
            0,
        ),
        Layer::line("numerical, same data", dense.clone(), curve_n.clone(), 1),
        Layer::Scatter {
            name: Some("analytic, run at each ζ".into()),
            xs: zs.clone(),
            ys: col("tau_analytic_median_s"),
            color: 0,
            size: 5,
            shape: PointShape::Circle,
        },
        Layer::Scatter {
            name: Some("numerical, run at each ζ".into()),
            xs: zs.clone(),
            ys: col("tau_numerical_median_s"),
            color: 1,
            size: 5,
            shape: PointShape::Circle,
        },
    ];
    let mut gp = Panel::new("Runs at each ζ (fixed step, learning)", "ζ", "distance (m)");
    gp.log_x = true;
    gp.layers = vec![
        Layer::line(
            "final distance to goal",
            zs.clone(),
            col("final_goal_distance"),
            2,
        ),
        Layer::line(
            "closest obstacle distance",
            zs,
            col("min_obstacle_distance"),
            3,
        ),
    ];
    let fig = Figure {
        width: 1200,
        height: 500,
        rows: 1,
        cols: 2,
        title: Some("Margin ζ against hold τ_k: τ_k grows about linearly in ζ; the margin constrains the controller".into()),
        panels: vec![zp, gp],
    };
    render_png(&fig, &args.out.join("tau-vs-zeta.png"))?;

    let summary = json!({
        "scenario": "ackermann-triggering",
        "seed": args.seed,
        "quick": args.quick,
        "horizon_s": fixed.scenario.dt * fixed.scenario.steps as f64,
        "fixed_step": run_summary(&fixed),
        "self_triggered": run_summary(&selft),
        "self_triggered_numerical": run_summary(&selfn),
        "zeta_sweep": sweep,
        "tau_vs_zeta_on_self_triggered_data": dense
            .iter()
            .zip(curve_a.iter().zip(&curve_n))
            .map(|(z, (a, n))| json!({"zeta": z, "tau_analytic_median_s": a, "tau_numerical_median_s": n}))
            .collect::<Vec<_>>(),
    });
    write_atomic(
        &args.out.join("summary.json"),
        (serde_json::to_string_pretty(&summary)? + "\n").as_bytes(),
    )?;
    eprintln!(
        "wrote {}: summary.json, lipschitz.png, tau-vs-zeta.png, fixed-step/, self-triggered/, self-triggered-numerical/, zeta-*/",
        args.out.display()
    );
    Ok(())
}
