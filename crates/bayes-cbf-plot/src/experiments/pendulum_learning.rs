//! Figures of `pendulum-learning` (paper, Fig. 4): `pendulum_f.png`,
//! `pendulum_g.png` (true and learned components with the training points
//! as red `+`, one colour scale per column) and `pendulum_std.png`
//! (posterior standard deviations).

use crate::plot::{finite_range, render_png, Figure, Layer, Panel, PointShape, RED};
use crate::Result;
use bayes_cbf_scenario::experiments::pendulum_learning::{
    PendulumLearning, COMPONENTS, GRID, TRAIN,
};
use bayes_cbf_scenario::experiments::OMEGA_MAX;
use std::f64::consts::PI;
use std::path::{Path, PathBuf};

/// Writes the three figures into `dir`; returns the files written.
pub fn figures(r: &PendulumLearning, dir: &Path) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    let plots = ["pendulum_f.png", "pendulum_g.png", "pendulum_std.png"];
    let view = |c: usize, rows: &[[f64; 4]]| rows.iter().map(|r| r[c]).collect::<Vec<f64>>();
    for (file, comps) in plots[..2].iter().zip([[0usize, 1], [2, 3]]) {
        let mut panels = Vec::new();
        let mut rows = vec![("true", view(comps[0], &r.truth), view(comps[1], &r.truth))];
        for m in &r.fitted {
            rows.push((
                m.kind.name(),
                view(comps[0], &m.mean),
                view(comps[1], &m.mean),
            ));
        }
        // one colour scale per column, over truth and both models
        let range = |c: usize| {
            let all: Vec<f64> = rows
                .iter()
                .flat_map(|r| if c == 0 { r.1.clone() } else { r.2.clone() })
                .collect();
            finite_range(&all)
        };
        let ranges = [range(0), range(1)];
        for (who, a, b) in &rows {
            for (col, vals) in [a, b].into_iter().enumerate() {
                let (name, unit) = COMPONENTS[comps[col]];
                let title = if *who == "true" {
                    format!("true {name}")
                } else {
                    format!("{who} posterior mean of {name}")
                };
                panels.push(heat_panel(
                    &title,
                    &r.thetas,
                    &r.omegas,
                    vals.clone(),
                    &format!("{name} ({unit})"),
                    ranges[col],
                    comps[0] == 0,
                    &r.train_xs,
                ));
            }
        }
        let fig = Figure { width: 1200, height: 1250, rows: 3, cols: 2, title: Some(format!("Pendulum: true vs learned {} on the {GRID}×{GRID} grid ({TRAIN} training points, red +)", if comps[0] == 0 { "f(x)" } else { "g(x)" })), panels };
        let path = dir.join(file);
        render_png(&fig, &path)?;
        files.push(path);
    }
    let mut panels = Vec::new();
    for m in &r.fitted {
        for c in [1usize, 3] {
            let (name, unit) = COMPONENTS[c];
            panels.push(heat_panel(
                &format!("{} posterior std of {name}", m.kind.name()),
                &r.thetas,
                &r.omegas,
                view(c, &m.std),
                &format!("std {name} ({unit})"),
                None,
                false,
                &r.train_xs,
            ));
        }
    }
    let fig = Figure::grid(
        (1200, 850),
        (2, 2),
        "Posterior standard deviation (training points red +)",
        panels,
    );
    let path = dir.join(plots[2]);
    render_png(&fig, &path)?;
    files.push(path);
    Ok(files)
}

/// A heat-map panel on the `θ × ω` grid with the training points as red `+`.
#[allow(clippy::too_many_arguments)]
fn heat_panel(
    title: &str,
    thetas: &[f64],
    omegas: &[f64],
    values: Vec<f64>,
    label: &str,
    range: Option<(f64, f64)>,
    zero: bool,
    train_xs: &[f64],
) -> Panel {
    let mut p = Panel::new(title, "θ (rad)", "ω (rad/s)");
    p.x_range = Some((-PI - 0.17, PI + 0.17));
    p.y_range = Some((-OMEGA_MAX - 0.32, OMEGA_MAX + 0.32));
    p.legend = false;
    let diverging = range.is_some_and(|(lo, hi)| lo < 0.0 && hi > 0.0);
    p.layers.push(Layer::Heatmap {
        xs: thetas.to_vec(),
        ys: omegas.to_vec(),
        values,
        zero_contour: zero,
        label: label.to_string(),
        diverging,
        range,
    });
    let (tx, ty): (Vec<f64>, Vec<f64>) = train_xs.chunks(2).map(|x| (x[0], x[1])).unzip();
    p.layers.push(Layer::Scatter {
        name: Some("training points".into()),
        xs: tx,
        ys: ty,
        color: RED,
        size: 4,
        shape: PointShape::Plus,
    });
    p
}
