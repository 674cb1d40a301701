//! Aggregation, plots and files of the speed test: medians and deciles per
//! `(system, k, model, variant)`, CoGP/MVGP time ratios, the Fig. 5 plots
//! and the per-fit CSV.

use super::{variant, Outcome, System, MAX_ITERS};
use crate::experiments::{num, quantile, ModelKind};
use crate::plot::{render_png, Figure, Layer, LegendPos, Panel, BLACK, GREY};
use crate::util::write_atomic;
use anyhow::Result;
use serde_json::{json, Value};
use std::path::Path;

/// Why [`MAX_ITERS`] is what it is (copied into `summary.json`).
pub(super) const ITERATION_NOTE: &str = "L-BFGS is capped at max_iters iterations per \
start (the CoGP full fit runs its diagonal pre-fit with the same cap). Uncapped (100), a CoGP \
full fit of 200 pendulum samples took 1000-1350 objective evaluations; at k = 1024 one costs \
about 0.35 s, so those 30 fits alone would take hours. With the cap of 15 the full run \
(1200 fits) took 1209 s on one core of a 2-vCPU Intel Xeon; CoGP full fits use 46-50 \
evaluations, the other models 21-28, and the capped fits are near-calibrated \
(variance-weighted error close to sqrt(n(1+m))).";

/// Why timings depend on the thread count (copied into `summary.json`).
pub(super) const TIMING_NOTE: &str = "Fits run in parallel on `threads` rayon threads \
(RAYON_NUM_THREADS). Concurrent fits slow each other down (about 2x per fit with 2 threads \
on a 2-vCPU machine, unevenly), so compare timings from RAYON_NUM_THREADS=1 runs; the \
errors do not depend on the thread count.";

/// Median and 2nd/9th deciles of a sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Stats {
    pub median: f64,
    pub d2: f64,
    pub d9: f64,
}

impl Stats {
    fn of(v: &[f64]) -> Self {
        Stats {
            median: quantile(v, 0.5),
            d2: quantile(v, 0.2),
            d9: quantile(v, 0.9),
        }
    }
    fn to_json(self) -> Value {
        json!({"median": num(self.median), "d2": num(self.d2), "d9": num(self.d9)})
    }
}

/// One row of the table.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Row {
    pub system: System,
    pub k: usize,
    pub kind: ModelKind,
    pub diag: bool,
    pub ok: usize,
    pub failed: usize,
    /// Held-out points (over all repetitions) that needed extended jitter.
    pub extended_jitter: usize,
    pub fit: Stats,
    pub per_eval: Stats,
    pub evaluations: Stats,
    pub predict: Stats,
    pub vwe: Stats,
    pub rmse: Stats,
}

impl Row {
    /// The row as it appears in `summary.json`.
    pub fn to_json(&self) -> Value {
        json!({
            "system": self.system.name(), "k": self.k, "model": self.kind.name(),
            "variant": variant(self.diag), "repetitions_ok": self.ok, "failures": self.failed,
            "extended_jitter_points": self.extended_jitter,
            "fit_seconds": self.fit.to_json(), "seconds_per_evaluation": self.per_eval.to_json(),
            "evaluations": self.evaluations.to_json(), "predict_seconds": self.predict.to_json(),
            "variance_weighted_error": self.vwe.to_json(), "rmse_F": self.rmse.to_json(),
        })
    }
}

/// Groups `outcomes` (sorted by system, k, model, variant) into rows.
pub(super) fn table(outcomes: &[Outcome]) -> Vec<Row> {
    let mut rows: Vec<Row> = Vec::new();
    for group in outcomes.chunk_by(|a, b| {
        let (x, y) = (a.case, b.case);
        (x.system, x.k, x.kind, x.diag) == (y.system, y.k, y.kind, y.diag)
    }) {
        let c = group[0].case;
        let good: Vec<&Outcome> = group.iter().filter(|o| o.error.is_none()).collect();
        let col = |f: &dyn Fn(&Outcome) -> f64| {
            Stats::of(&good.iter().map(|o| f(o)).collect::<Vec<f64>>())
        };
        rows.push(Row {
            system: c.system,
            k: c.k,
            kind: c.kind,
            diag: c.diag,
            ok: good.len(),
            failed: group.len() - good.len(),
            extended_jitter: good.iter().map(|o| o.extended_jitter).sum(),
            fit: col(&|o| o.fit_seconds),
            per_eval: col(&|o| o.fit_seconds / o.evaluations.max(1) as f64),
            evaluations: col(&|o| o.evaluations as f64),
            predict: col(&|o| o.predict_seconds),
            vwe: col(&|o| o.vwe),
            rmse: col(&|o| o.rmse_f),
        });
    }
    rows
}

fn find(table: &[Row], s: System, k: usize, kind: ModelKind, diag: bool) -> Option<&Row> {
    table
        .iter()
        .find(|r| (r.system, r.k, r.kind, r.diag) == (s, k, kind, diag))
}

/// CoGP/MVGP ratios of the median fit, per-evaluation and predict times
/// per `(system, k, variant)`, with the factorisation-cost theory `n³`.
pub(super) fn ratios(table: &[Row]) -> Vec<Value> {
    let mut out = Vec::new();
    for r in table.iter().filter(|r| r.kind == ModelKind::Mvgp) {
        if let Some(c) = find(table, r.system, r.k, ModelKind::Cogp, r.diag) {
            let n = super::System::n(r.system) as f64;
            out.push(json!({
                "system": r.system.name(), "k": r.k, "variant": variant(r.diag),
                "fit": num(c.fit.median / r.fit.median),
                "per_evaluation": num(c.per_eval.median / r.per_eval.median),
                "predict": num(c.predict.median / r.predict.median),
                "theory_n3": n * n * n,
            }));
        }
    }
    out
}

/// Palette index and dash of each model/variant, and its legend name.
fn style(kind: ModelKind, diag: bool) -> (usize, bool, String) {
    let color = match (kind, diag) {
        (ModelKind::Mvgp, false) => 0,
        (ModelKind::Mvgp, true) => 9,
        (ModelKind::Cogp, false) => 1,
        (ModelKind::Cogp, true) => 3,
    };
    (color, diag, format!("{} {}", kind.name(), variant(diag)))
}

/// Writes `speed_test.png` (time to fit, time to predict and error vs `k`,
/// one row per system) and `speed_ratio.png` (CoGP/MVGP time ratios).
pub(super) fn plots(table: &[Row], ratios: &[Value], out: &Path) -> Result<()> {
    let systems = [System::Pendulum, System::Ackermann];
    type Metric = (&'static str, &'static str, fn(&Row) -> Stats);
    let metrics: [Metric; 3] = [
        ("time to fit", "fit time (s)", |r| r.fit),
        (
            "time to predict the posterior on 400 grid points",
            "predict time (s)",
            |r| r.predict,
        ),
        (
            "variance-weighted error (Eq. 33), held out",
            "error (Eq. 33)",
            |r| r.vwe,
        ),
    ];
    let variants = [
        (ModelKind::Mvgp, false),
        (ModelKind::Mvgp, true),
        (ModelKind::Cogp, false),
        (ModelKind::Cogp, true),
    ];
    let mut panels = Vec::new();
    for s in systems {
        for (mi, (title, ylabel, get)) in metrics.iter().enumerate() {
            let mut p = Panel::new(&format!("{}: {title}", s.name()), "observations k", ylabel);
            (p.log_x, p.log_y, p.legend_pos) = (true, true, LegendPos::UpperLeft);
            p.legend = mi == 0;
            for (vi, &(kind, diag)) in variants.iter().enumerate() {
                let rows: Vec<&Row> = table
                    .iter()
                    .filter(|r| (r.system, r.kind, r.diag) == (s, kind, diag))
                    .collect();
                // spread the variants a little along k so their bars do not overlap
                let xs: Vec<f64> = rows
                    .iter()
                    .map(|r| r.k as f64 * (1.0 + 0.015 * (vi as f64 - 1.5)))
                    .collect();
                let st: Vec<Stats> = rows.iter().map(|r| get(r)).collect();
                let (color, dashed, name) = style(kind, diag);
                p.layers.push(Layer::Line {
                    name: Some(name),
                    xs: xs.clone(),
                    ys: st.iter().map(|s| s.median).collect(),
                    color,
                    width: 2,
                    dashed,
                });
                p.layers.push(Layer::ErrorBars {
                    name: None,
                    xs,
                    mid: st.iter().map(|s| s.median).collect(),
                    lo: st.iter().map(|s| s.d2).collect(),
                    hi: st.iter().map(|s| s.d9).collect(),
                    color,
                });
            }
            panels.push(p);
        }
    }
    let fig = Figure {
        width: 1650,
        height: 1000,
        rows: 2,
        cols: 3,
        title: Some(
            "MVGP vs CoGP (fitted models): median and 2nd–9th decile over repetitions".into(),
        ),
        panels,
    };
    render_png(&fig, &out.join("speed_test.png"))?;
    let mut panels = Vec::new();
    for s in systems {
        let n = super::System::n(s) as f64;
        let mut p = Panel::new(
            &format!("{}: CoGP / MVGP median time", s.name()),
            "observations k",
            "time ratio CoGP / MVGP",
        );
        (p.log_x, p.log_y, p.legend_pos) = (true, true, LegendPos::LowerRight);
        for (diag, key, color) in [
            (false, "fit", 0),
            (true, "fit", 9),
            (false, "per_evaluation", 2),
            (false, "predict", 4),
        ] {
            let pts: Vec<(f64, f64)> = ratios
                .iter()
                .filter(|r| r["system"] == s.name() && r["variant"] == variant(diag))
                .filter_map(|r| Some((r["k"].as_f64()?, r[key].as_f64()?)))
                .collect();
            let name = format!("{} ({})", key.replace('_', " "), variant(diag));
            p.layers.push(Layer::Line {
                name: Some(name),
                xs: pts.iter().map(|p| p.0).collect(),
                ys: pts.iter().map(|p| p.1).collect(),
                color,
                width: 2,
                dashed: diag,
            });
        }
        p.layers.push(Layer::HLine {
            y: n * n * n,
            color: BLACK,
            dashed: true,
            name: Some(format!("n³ = {}", n * n * n)),
        });
        p.layers.push(Layer::HLine {
            y: 1.0,
            color: GREY,
            dashed: false,
            name: None,
        });
        panels.push(p);
    }
    let fig = Figure {
        width: 1300,
        height: 560,
        rows: 1,
        cols: 2,
        title: None,
        panels,
    };
    render_png(&fig, &out.join("speed_ratio.png"))
}

/// Every fit as one CSV row (NaN for failed fits).
pub(super) fn write_runs_csv(outcomes: &[Outcome], path: &Path) -> Result<()> {
    let mut s = String::from("system,k,rep,model,variant,fit_seconds,evaluations,predict_seconds,variance_weighted_error,extended_jitter_points,rmse_F,log_likelihood,error\n");
    for o in outcomes {
        let c = o.case;
        let err = o
            .error
            .as_deref()
            .unwrap_or("")
            .replace([',', '\n', '"'], " ");
        s.push_str(&format!(
            "{},{},{},{},{},{},{},{},{},{},{},{},{}\n",
            c.system.name(),
            c.k,
            c.rep,
            c.kind.name(),
            variant(c.diag),
            o.fit_seconds,
            o.evaluations,
            o.predict_seconds,
            o.vwe,
            o.extended_jitter,
            o.rmse_f,
            o.log_likelihood,
            err
        ));
    }
    write_atomic(path, s.as_bytes())
}

/// CPU model and core count, for the record.
pub(super) fn machine() -> Value {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|t| {
            t.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| "unknown".into());
    let cores = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);
    json!({"cpu": cpu, "cores": cores, "os": std::env::consts::OS, "max_iters_full_run": MAX_ITERS})
}
