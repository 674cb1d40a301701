//! Figures of `speed-test` (paper, Fig. 5): `speed_test.png` (time to fit,
//! time to predict and error against `k`, one row per system) and
//! `speed_ratio.png` (CoGP/MVGP time ratios).

use crate::plot::{render_png, Figure, Layer, LegendPos, Panel, BLACK, GREY};
use crate::Result;
use bayes_cbf_scenario::experiments::speed_test::{variant, Ratio, Row, SpeedTest, Stats, System};
use bayes_cbf_scenario::experiments::ModelKind;
use std::path::{Path, PathBuf};

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
pub fn figures(r: &SpeedTest, out: &Path) -> Result<Vec<PathBuf>> {
    let table = &r.table;
    let ratios = &r.summary.time_ratio_cogp_over_mvgp;
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
    let fig = Figure::grid(
        (1650, 1000),
        (2, 3),
        "MVGP vs CoGP (fitted models): median and 2nd–9th decile over repetitions",
        panels,
    );
    render_png(&fig, &out.join("speed_test.png"))?;
    let mut panels = Vec::new();
    for s in systems {
        let n = System::state_dim(s) as f64;
        let mut p = Panel::new(
            &format!("{}: CoGP / MVGP median time", s.name()),
            "observations k",
            "time ratio CoGP / MVGP",
        );
        (p.log_x, p.log_y, p.legend_pos) = (true, true, LegendPos::LowerRight);
        type Pick = fn(&Ratio) -> f64;
        let series: [(bool, &str, Pick, usize); 4] = [
            (false, "fit", |r| r.fit, 0),
            (true, "fit", |r| r.fit, 9),
            (false, "per_evaluation", |r| r.per_evaluation, 2),
            (false, "predict", |r| r.predict, 4),
        ];
        for (diag, key, pick, color) in series {
            let pts: Vec<(f64, f64)> = ratios
                .iter()
                .filter(|r| r.system == s.name() && r.variant == variant(diag))
                .map(|r| (r.k as f64, pick(r)))
                .filter(|p| p.1.is_finite())
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
    render_png(&fig, &out.join("speed_ratio.png"))?;
    Ok(vec![
        out.join("speed_test.png"),
        out.join("speed_ratio.png"),
    ])
}
