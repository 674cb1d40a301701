//! Figures of a closed-loop run (paper, Figs. 6–8) and the vehicle animation.

use crate::plot::{render_gif, render_png, Figure, Layer, LegendPos, Panel, PointShape};
use crate::Result;
use bayes_cbf::barrier::{cbc_moments, quantile_factor, ConditionMoments, MomentWorkspace};
use bayes_cbf::sim::StepStatus;
use bayes_cbf_scenario::prior_spec::PriorSpec;
use bayes_cbf_scenario::scenario::RunOutput;
use std::path::{Path, PathBuf};

/// Writes the figures (and the animation for vehicles) of a run into `dir`;
/// returns the files written.
pub fn write_figures(out: &RunOutput, dir: &Path) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    if !out.scenario.outputs.plots {
        return Ok(files);
    }
    // the paper's robots get the paper's figures; a system written as
    // expressions gets its named states, controls and barriers over time
    // (and the map of a planar robot: x, y, heading and two controls)
    let expression = matches!(out.scenario.system, PriorSpec::Expression(_));
    match (out.built.truth.state_dim(), out.built.truth.control_dim()) {
        (2, 1) if !expression => files.push(pendulum(out, dir)?),
        (3, 2) => {
            files.push(vehicle_map(out, dir)?);
            files.push(if expression {
                generic_series(out, dir)?
            } else {
                vehicle_series(out, dir)?
            });
            if out.scenario.outputs.animation {
                files.push(animation(out, dir)?);
            }
        }
        _ if expression => files.push(generic_series(out, dir)?),
        _ => {}
    }
    Ok(files)
}

/// States, controls (applied and reference, infeasible steps marked),
/// barrier values and the model's uncertainty over time, labelled with the
/// system's own names.
fn generic_series(out: &RunOutput, dir: &Path) -> Result<PathBuf> {
    let t = times(out);
    let rec = &out.result.records;
    let (states, controls) = out.scenario.system.names().unwrap_or_default();
    let mut xs = Panel::new("state", "t (s)", "x");
    for i in 0..out.built.truth.state_dim() {
        let ys = rec.iter().map(|r| r.x[i]).collect();
        xs.layers.push(Layer::line(
            &name(&states, i, &format!("x{i}")),
            t.clone(),
            ys,
            i,
        ));
    }
    let mut us = Panel::new("control", "t (s)", "u");
    for j in 0..out.built.truth.control_dim() {
        let c = name(&controls, j, &format!("u{j}"));
        us.layers.push(Layer::Scatter {
            name: Some(format!("{c} reference")),
            xs: t.clone(),
            ys: rec.iter().map(|r| r.u_ref[j]).collect(),
            color: 7,
            size: 1,
            shape: PointShape::Circle,
        });
        us.layers.push(Layer::line(
            &c,
            t.clone(),
            rec.iter().map(|r| r.u[j]).collect(),
            j,
        ));
    }
    let inf: Vec<(f64, f64)> = rec
        .iter()
        .filter(|r| r.status == StepStatus::Infeasible)
        .map(|r| (r.t, r.u[0]))
        .collect();
    if !inf.is_empty() {
        us.layers.push(Layer::Scatter {
            name: Some("infeasible (fallback)".into()),
            xs: inf.iter().map(|p| p.0).collect(),
            ys: inf.iter().map(|p| p.1).collect(),
            color: 3,
            size: 3,
            shape: PointShape::Cross,
        });
    }
    let mut hs = Panel::new("barriers (h ≥ 0 is safe)", "t (s)", "h");
    hs.layers.push(Layer::HLine {
        y: 0.0,
        color: 3,
        dashed: true,
        name: Some("h = 0".into()),
    });
    for i in 0..out.built.barriers.len() {
        let ys = rec.iter().map(|r| r.h_fine_min[i]).collect();
        hs.layers
            .push(Layer::line(&format!("h{i}"), t.clone(), ys, i));
    }
    let trace = trace_panel(out);
    timeseries(out, dir, (1000, 1100), vec![xs, us, hs, trace])
}

/// `names[i]`, or `fallback` when the system has no such name.
fn name(names: &[String], i: usize, fallback: &str) -> String {
    names
        .get(i)
        .cloned()
        .unwrap_or_else(|| fallback.to_string())
}

fn times(out: &RunOutput) -> Vec<f64> {
    out.result.records.iter().map(|r| r.t).collect()
}

fn pendulum(out: &RunOutput, dir: &Path) -> Result<PathBuf> {
    let t = times(out);
    let rec = &out.result.records;
    let deg = |v: f64| v.to_degrees();
    let mut theta = Panel::new("pendulum angle", "t (s)", "θ (°)");
    // the sectors of the sector barriers and of their edges, once each
    let mut sectors: Vec<(f64, f64)> = Vec::new();
    for spec in &out.scenario.barriers {
        use bayes_cbf_scenario::barrier_file::BarrierSpec;
        if let BarrierSpec::PendulumSector { theta_c, delta, .. }
        | BarrierSpec::PendulumSectorEdge { theta_c, delta, .. } = spec
        {
            if !sectors.contains(&(*theta_c, *delta)) {
                sectors.push((*theta_c, *delta));
            }
        }
    }
    for (theta_c, delta) in sectors {
        theta.layers.push(Layer::HBand {
            lo: deg(theta_c - delta),
            hi: deg(theta_c + delta),
            color: 3,
            name: Some("unsafe sector".into()),
        });
    }
    let th: Vec<f64> = rec.iter().map(|r| deg(r.x[0])).collect();
    // keep the sector in view
    let (mut lo, mut hi) = th
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(*v), b.max(*v))
        });
    for l in &theta.layers {
        if let Layer::HBand { lo: a, hi: b, .. } = l {
            lo = lo.min(*a);
            hi = hi.max(*b);
        }
    }
    if lo.is_finite() && hi.is_finite() {
        theta.y_range = Some((lo - 5.0, hi + 5.0));
    }
    theta.layers.push(Layer::line("θ", t.clone(), th, 0));
    let mut omega = Panel::new("angular velocity", "t (s)", "ω (rad/s)");
    omega.layers.push(Layer::line(
        "ω",
        t.clone(),
        rec.iter().map(|r| r.x[1]).collect(),
        0,
    ));
    let mut u = Panel::new("torque", "t (s)", "u (N·m)");
    u.layers.push(Layer::Scatter {
        name: Some("reference û (ε-greedy)".into()),
        xs: t.clone(),
        ys: rec.iter().map(|r| r.u_ref[0]).collect(),
        color: 7,
        size: 2,
        shape: PointShape::Circle,
    });
    u.layers.push(Layer::line(
        "applied u",
        t.clone(),
        rec.iter().map(|r| r.u[0]).collect(),
        1,
    ));
    let inf: Vec<f64> = rec
        .iter()
        .filter(|r| r.status == StepStatus::Infeasible)
        .map(|r| r.t)
        .collect();
    if !inf.is_empty() {
        let y0 = out
            .scenario
            .controller
            .u_min
            .as_ref()
            .map(|v| v[0])
            .unwrap_or(0.0);
        u.layers.push(Layer::Scatter {
            name: Some("infeasible (fallback)".into()),
            ys: vec![y0; inf.len()],
            xs: inf,
            color: 3,
            size: 3,
            shape: PointShape::Cross,
        });
    }
    timeseries(out, dir, (1100, 900), vec![theta, omega, u])
}

/// Heat map of [`scbc_grid`] on `cells × cells` points of the region the
/// run covers ([`arena`]) with its zero contour; the colour range is
/// `range`, or symmetric about zero and at most ±10 when `None`.
fn scbc_heatmap(
    out: &RunOutput,
    theta: f64,
    u: &[f64],
    cells: usize,
    range: Option<(f64, f64)>,
) -> Layer {
    let axis = |(lo, hi): (f64, f64)| -> Vec<f64> {
        (0..cells)
            .map(|i| lo + (hi - lo) * i as f64 / (cells - 1) as f64)
            .collect()
    };
    let (x_range, y_range) = arena(out);
    let (xs, ys) = (axis(x_range), axis(y_range));
    let values = scbc_grid(out, theta, u, &xs, &ys);
    let range = range.unwrap_or_else(|| {
        let lim = values
            .iter()
            .filter(|v| v.is_finite())
            .fold(0.0f64, |a, v| a.max(v.abs()))
            .min(10.0);
        (-lim, lim)
    });
    Layer::Heatmap {
        xs,
        ys,
        values,
        zero_contour: true,
        label: "min SCBC".into(),
        diverging: true,
        range: Some(range),
    }
}

/// The square region of the plane of states 0 and 1 around the start, the
/// goal, the obstacles and the trajectory, with a margin of 0.5 m.
fn arena(out: &RunOutput) -> ((f64, f64), (f64, f64)) {
    let mut lo = [out.built.start[0], out.built.start[1]];
    let mut hi = lo;
    let mut cover = |x: f64, y: f64, r: f64| {
        if x.is_finite() && y.is_finite() {
            lo = [lo[0].min(x - r), lo[1].min(y - r)];
            hi = [hi[0].max(x + r), hi[1].max(y + r)];
        }
    };
    for r in &out.result.records {
        cover(r.x[0], r.x[1], 0.0);
    }
    if let Some(g) = &out.scenario.goal {
        cover(g[0], g[1], 0.0);
    }
    for (c, r) in &out.built.obstacles {
        cover(c[0], c[1], *r);
    }
    let side = (hi[0] - lo[0]).max(hi[1] - lo[1]) + 1.0;
    let centre = [0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])];
    let span = |c: f64| (c - 0.5 * side, c + 0.5 * side);
    (span(centre[0]), span(centre[1]))
}

/// Minimum over barriers of the stochastic CBC `E − ζ − c·std` on an
/// `(x, y)` grid at fixed heading and control, with the final model.
fn scbc_grid(out: &RunOutput, theta: f64, u: &[f64], xs: &[f64], ys: &[f64]) -> Vec<f64> {
    let model = &out.result.model;
    let p = out.scenario.controller.probability;
    let zeta = out.scenario.controller.zeta;
    let mut ws = MomentWorkspace::new(model);
    let mut mom = ConditionMoments::zeros(model.control_dim());
    let mut vals = Vec::with_capacity(xs.len() * ys.len());
    for &y in ys {
        for &x in xs {
            let state = [x, y, theta];
            let mut best = f64::INFINITY;
            if ws.update(model, &state, 2).is_ok() {
                for b in &out.built.barriers {
                    if cbc_moments(&mut ws, b.as_ref(), &mut mom).is_ok() {
                        let c = quantile_factor(p.max(0.5), b.relative_degree()).unwrap_or(0.0);
                        best = best.min(mom.mean(u) - zeta - c * mom.variance(u).sqrt());
                    }
                }
            }
            vals.push(if best.is_finite() { best } else { f64::NAN });
        }
    }
    vals
}

fn map_panel(out: &RunOutput, upto: usize, title: &str) -> Panel {
    let rec = &out.result.records;
    let mut panel = Panel::new(title, "x (m)", "y (m)");
    panel.equal_aspect = true;
    panel.legend_pos = LegendPos::LowerRight;
    for (i, (c, r)) in out.built.obstacles.iter().enumerate() {
        panel.layers.push(Layer::Circle {
            cx: c[0],
            cy: c[1],
            r: *r,
            color: 3,
            name: if i == 0 {
                Some("obstacles".into())
            } else {
                None
            },
        });
    }
    if let Some(g) = &out.scenario.goal {
        let s = &out.built.start;
        panel.layers.push(Layer::Line {
            name: Some("planned path".into()),
            xs: vec![s[0], g[0]],
            ys: vec![s[1], g[1]],
            color: 7,
            width: 1,
            dashed: true,
        });
        panel.layers.push(Layer::Scatter {
            name: Some("goal".into()),
            xs: vec![g[0]],
            ys: vec![g[1]],
            color: 2,
            size: 8,
            shape: PointShape::Plus,
        });
    }
    let upto = upto.min(rec.len());
    panel.layers.push(Layer::Line {
        name: Some("trajectory".into()),
        xs: rec[..upto].iter().map(|r| r.x[0]).collect(),
        ys: rec[..upto].iter().map(|r| r.x[1]).collect(),
        color: 0,
        width: 2,
        dashed: true,
    });
    panel
}

fn vehicle_map(out: &RunOutput, dir: &Path) -> Result<PathBuf> {
    let rec = &out.result.records;
    // heading and control where the vehicle came closest to an obstacle
    let k = rec
        .iter()
        .enumerate()
        .min_by(|a, b| {
            a.1.monitors
                .iter()
                .cloned()
                .fold(f64::INFINITY, f64::min)
                .total_cmp(&b.1.monitors.iter().cloned().fold(f64::INFINITY, f64::min))
        })
        .map(|(i, _)| i)
        .unwrap_or(0);
    let (theta, u) = (rec[k].x[2], rec[k].u.clone());
    // the system's own names (the vehicle's: x, y, theta; v, z)
    let (states, controls) = out.scenario.system.names().unwrap_or_default();
    let mut panel = map_panel(
        out,
        rec.len(),
        &format!(
            "trajectory over min stochastic CBC ({} = {:.2} rad, {} = {:.2}, {} = {:.2})",
            name(&states, 2, "θ"),
            theta,
            name(&controls, 0, "v"),
            u[0],
            name(&controls, 1, "z"),
            u[1]
        ),
    );
    panel
        .layers
        .insert(0, scbc_heatmap(out, theta, &u, 50, None));
    panel.layers.push(Layer::Marker {
        x: rec[k].x[0],
        y: rec[k].x[1],
        heading: Some(theta),
        color: 9,
        size: 10,
    });
    let fig = Figure::single(900, 760, panel);
    let path = dir.join("trajectory.png");
    render_png(&fig, &path)?;
    Ok(path)
}

fn speed_panel(out: &RunOutput) -> Panel {
    let mut speed = Panel::new("speed", "t (s)", "|v| (m/s)");
    speed.layers.push(Layer::line(
        "|v|",
        times(out),
        out.result.records.iter().map(|r| r.u[0].abs()).collect(),
        0,
    ));
    speed
}

fn scbc_panel(out: &RunOutput) -> Panel {
    let mut scbc = Panel::new(
        "minimum stochastic CBC over the barriers",
        "t (s)",
        "min SCBC",
    );
    scbc.layers.push(Layer::HLine {
        y: 0.0,
        color: 3,
        dashed: true,
        name: Some("constraint".into()),
    });
    let min_scbc = out
        .result
        .records
        .iter()
        .map(|r| r.scbc.iter().cloned().fold(f64::INFINITY, f64::min))
        .collect();
    scbc.layers
        .push(Layer::line("min SCBC", times(out), min_scbc, 0));
    scbc
}

/// `tr(B_k(x, x) ⊗ A)` over time, on a log scale.
fn trace_panel(out: &RunOutput) -> Panel {
    let mut trace = Panel::new("model uncertainty", "t (s)", "tr(B_k(x,x) ⊗ A)");
    trace.log_y = true;
    let ys = out.result.records.iter().map(|r| r.trace_cov).collect();
    trace
        .layers
        .push(Layer::line("tr(B_k ⊗ A)", times(out), ys, 1));
    trace
}

fn vehicle_series(out: &RunOutput, dir: &Path) -> Result<PathBuf> {
    let rec = &out.result.records;
    let (speed, scbc) = (speed_panel(out), scbc_panel(out));
    let mut trace = trace_panel(out);
    let mut first = true;
    for w in rec.windows(2) {
        if w[0].data_size != w[1].data_size {
            trace.layers.push(Layer::VLine {
                x: w[1].t,
                color: 7,
                dashed: true,
                name: if first {
                    Some("model update".into())
                } else {
                    None
                },
            });
            first = false;
        }
    }
    timeseries(out, dir, (1000, 900), vec![speed, scbc, trace])
}

/// `timeseries.png`: `panels` one above the other, titled with the
/// scenario and its seed, at `size` pixels.
fn timeseries(
    out: &RunOutput,
    dir: &Path,
    size: (u32, u32),
    panels: Vec<Panel>,
) -> Result<PathBuf> {
    let fig = Figure::grid(
        (size.0, size.1),
        (panels.len(), 1),
        format!("{} (seed {})", out.scenario.name, out.scenario.seed),
        panels,
    );
    let path = dir.join("timeseries.png");
    render_png(&fig, &path)?;
    Ok(path)
}

fn animation(out: &RunOutput, dir: &Path) -> Result<PathBuf> {
    let rec = &out.result.records;
    let frames = 60usize.min(rec.len()).max(1);
    let figs: Vec<Figure> = (1..=frames)
        .map(|f| {
            let upto = (rec.len() * f / frames).max(1);
            let r = &rec[upto - 1];
            let mut panel = map_panel(
                out,
                upto,
                &format!("{}: t = {:.2} s", out.scenario.name, r.t),
            );
            panel.x_range = Some((-4.0, 1.0));
            panel.y_range = Some((-3.0, 2.0));
            panel.layers.push(Layer::Marker {
                x: r.x[0],
                y: r.x[1],
                heading: Some(r.x[2]),
                color: 0,
                size: 12,
            });
            Figure::single(480, 440, panel)
        })
        .collect();
    let path = dir.join("animation.gif");
    render_gif(&figs, 80, &path)?;
    Ok(path)
}

/// Two vehicle runs side by side: trajectories over their minimum
/// stochastic-CBC maps, speed and minimum SCBC over time.
pub fn comparison_figure(a: &RunOutput, b: &RunOutput, path: &Path) -> Result<()> {
    let mut panels = Vec::new();
    for o in [a, b] {
        let rec = &o.result.records;
        let k = rec.len() / 2;
        let (theta, u) = (rec[k].x[2], rec[k].u.clone());
        let mut p = map_panel(
            o,
            rec.len(),
            &format!(
                "{} (p = {})",
                o.scenario.name, o.scenario.controller.probability
            ),
        );
        p.layers
            .insert(0, scbc_heatmap(o, theta, &u, 40, Some((-10.0, 10.0))));
        panels.push(p);
    }
    panels.extend([a, b].map(speed_panel));
    panels.extend([a, b].map(scbc_panel));
    let fig = Figure::grid(
        (1500, 1400),
        (3, 2),
        "mean CBF (left) against Bayes CBF (right): true wheelbase 12, model wheelbase 1",
        panels,
    );
    render_png(&fig, path)
}
