//! Figures of `ackermann-triggering` (paper, Fig. 2): `lipschitz.png`
//! (`L_f` and `τ_k`, analytic and numerical, over the self-triggered and
//! the fixed-step run) and `tau-vs-zeta.png`; each run's own figures go to
//! its subdirectory.

use crate::plot::{render_png, Figure, Layer, Panel, PointShape};
use crate::Result;
use bayes_cbf_scenario::experiments::ackermann_triggering::{AckermannTriggering, ZetaRun};
use bayes_cbf_scenario::scenario::RunOutput;
use std::path::{Path, PathBuf};

/// Writes `lipschitz.png`, `tau-vs-zeta.png` and every run's figures (in
/// its subdirectory) into `dir`; returns the files written.
pub fn figures(r: &AckermannTriggering, dir: &Path) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    for (sub, o) in &r.runs {
        files.extend(crate::scenario::write_figures(o, &dir.join(sub))?);
    }
    let (Some(fixed), Some(selft)) = (r.run("fixed-step"), r.run("self-triggered")) else {
        return Ok(files);
    };
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
            ("self-triggered", selft, false, 2),
            ("fixed step", fixed, true, 1),
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
    let mut tp = Panel::new(
        "Inter-trigger time (Prop. 3, corrected)",
        "t (s)",
        "τ_k (s)",
    );
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
    let fig = Figure::grid(
        (1300, 550),
        (1, 2),
        format!(
            "Ackermann vehicle learning online, δ_L = 1e-4, ζ = {}, cuboid (0.2, 0.2, π/50)",
            selft.scenario.controller.zeta
        ),
        vec![lp, tp],
    );
    let path = dir.join("lipschitz.png");
    render_png(&fig, &path)?;
    files.push(path);

    let curve = &r.summary.tau_vs_zeta_on_self_triggered_data;
    let dense: Vec<f64> = curve.iter().map(|c| c.zeta).collect();
    let curve_a: Vec<f64> = curve.iter().map(|c| c.tau_analytic_median_s).collect();
    let curve_n: Vec<f64> = curve.iter().map(|c| c.tau_numerical_median_s).collect();
    let sweep = &r.summary.zeta_sweep;
    let zs: Vec<f64> = sweep.iter().map(|s| s.zeta).collect();
    let col = |f: fn(&ZetaRun) -> f64| -> Vec<f64> { sweep.iter().map(f).collect() };
    let at_each = |what: &str, ys: Vec<f64>, color: usize| Layer::Scatter {
        name: Some(format!("{what}, run at each ζ")),
        xs: zs.clone(),
        ys,
        color,
        size: 5,
        shape: PointShape::Circle,
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
        at_each("analytic", col(|s| s.tau_analytic_median_s), 0),
        at_each("numerical", col(|s| s.tau_numerical_median_s), 1),
    ];
    let mut gp = Panel::new("Runs at each ζ (fixed step, learning)", "ζ", "distance (m)");
    gp.log_x = true;
    gp.layers = vec![
        Layer::line(
            "final distance to goal",
            zs.clone(),
            col(|s| s.final_goal_distance.unwrap_or(f64::NAN)),
            2,
        ),
        Layer::line(
            "closest obstacle distance",
            zs,
            col(|s| s.min_obstacle_distance.unwrap_or(f64::NAN)),
            3,
        ),
    ];
    let fig = Figure::grid((1200, 500), (1, 2), "Margin ζ against hold τ_k: τ_k grows about linearly in ζ; the margin constrains the controller", vec![zp, gp]);
    let path = dir.join("tau-vs-zeta.png");
    render_png(&fig, &path)?;
    files.push(path);
    Ok(files)
}
