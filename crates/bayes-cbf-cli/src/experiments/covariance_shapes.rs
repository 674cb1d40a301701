//! `covariance-shapes` (paper, Fig. 1): the posterior covariances of the
//! columns of `F(x) = [f g_1 g_2]` of the Ackermann vehicle, learned by an
//! MVGP and by a CoGP from the same data.
//!
//! Under the MVGP, `Cov(vec F(x)) = B_k(x, x) ⊗ A`, so the covariance of
//! column `c` is `B_k[c, c] · A`: every column has the shape of `A`, up to
//! scale. The CoGP's `Σ k0` leaves the `n × n` diagonal blocks free. The
//! figure draws the 3σ ellipses of each column's covariance, normalised to
//! unit trace so that only the shapes are compared, projected on each pair
//! of state coordinates; `summary.json` holds the raw blocks and the
//! largest Frobenius distance between two normalised blocks (zero for the
//! MVGP by construction).

use super::{fit_settings, new_model, ExperimentArgs, ModelKind};
use crate::plot::{render_png, Figure, Layer, Panel};
use crate::util::write_atomic;
use anyhow::Result;
use bayes_cbf::gp::{DynamicsModel, InputMap};
use bayes_cbf::workloads::ackermann_data;
use nalgebra::{DMatrix, SymmetricEigen};
use serde_json::json;
use std::time::Instant;

/// Names of the columns of `F` for the Ackermann vehicle (`u = (v, ω)`).
const COLUMNS: [&str; 3] = ["f", "g_1 (v)", "g_2 (ω)"];
/// Names of the state coordinates.
const STATES: [&str; 3] = ["x", "y", "θ"];

/// The `n × n` covariance block of column `c` in `Cov(vec F)` (column-major
/// `vec`, entry `i + n c`).
fn block(cov: &DMatrix<f64>, n: usize, c: usize) -> DMatrix<f64> {
    cov.view((c * n, c * n), (n, n)).into_owned()
}

/// Points of the 3σ ellipse of the 2 × 2 covariance `s`.
fn ellipse(s: &DMatrix<f64>) -> (Vec<f64>, Vec<f64>) {
    let sym = (s + s.transpose()) * 0.5;
    let e = SymmetricEigen::new(sym);
    let (mut xs, mut ys) = (Vec::new(), Vec::new());
    for i in 0..=120 {
        let a = 2.0 * std::f64::consts::PI * i as f64 / 120.0;
        let (c, sn) = (a.cos(), a.sin());
        let r0 = 3.0 * e.eigenvalues[0].max(0.0).sqrt();
        let r1 = 3.0 * e.eigenvalues[1].max(0.0).sqrt();
        xs.push(e.eigenvectors[(0, 0)] * r0 * c + e.eigenvectors[(0, 1)] * r1 * sn);
        ys.push(e.eigenvectors[(1, 0)] * r0 * c + e.eigenvectors[(1, 1)] * r1 * sn);
    }
    (xs, ys)
}

/// Largest Frobenius distance between two unit-trace blocks.
fn shape_spread(blocks: &[DMatrix<f64>]) -> f64 {
    let unit: Vec<DMatrix<f64>> = blocks.iter().map(|b| b / b.trace()).collect();
    let mut worst = 0.0f64;
    for a in 0..unit.len() {
        for b in a + 1..unit.len() {
            worst = worst.max((&unit[a] - &unit[b]).norm());
        }
    }
    worst
}

/// Runs the experiment.
pub fn run(args: &ExperimentArgs) -> Result<()> {
    std::fs::create_dir_all(&args.out)?;
    let k = if args.quick { 60 } else { 200 };
    let iters = if args.quick { 15 } else { 50 };
    let data = ackermann_data(k, 1.0, args.seed)?;
    // the dynamics do not depend on the position: the kernel sees θ only
    let map = InputMap::Select(vec![2]);
    let x_star = [0.0, 0.0, std::f64::consts::FRAC_PI_4];
    let n = data.n;
    let mut models = Vec::new();
    let mut panels = Vec::new();
    for kind in [ModelKind::Mvgp, ModelKind::Cogp] {
        let mut model: Box<dyn DynamicsModel> = new_model(kind, &map, &data)?;
        let started = Instant::now();
        model.fit(&fit_settings(false, iters, args.seed))?;
        let fit_s = started.elapsed().as_secs_f64();
        let (_, cov) = model.posterior_vec(&x_star)?;
        let blocks: Vec<DMatrix<f64>> = (0..COLUMNS.len()).map(|c| block(&cov, n, c)).collect();
        let spread = shape_spread(&blocks);
        eprintln!(
            "  {:<5} fitted in {fit_s:.2} s; largest distance between column shapes {spread:.3e}",
            kind.name()
        );
        for (a, b) in [(0usize, 1usize), (0, 2), (1, 2)] {
            let mut p = Panel::new(
                &format!("{}: ({}, {})", kind.name(), STATES[a], STATES[b]),
                &format!("{} (normalised)", STATES[a]),
                &format!("{} (normalised)", STATES[b]),
            );
            p.equal_aspect = true;
            for (c, bl) in blocks.iter().enumerate() {
                let unit = bl / bl.trace();
                let s2 = DMatrix::from_fn(2, 2, |i, j| unit[([a, b][i], [a, b][j])]);
                let (xs, ys) = ellipse(&s2);
                // decreasing widths: coinciding ellipses stay visible
                p.layers.push(Layer::Line {
                    name: Some(COLUMNS[c].into()),
                    xs,
                    ys,
                    color: c,
                    width: 6 - 2 * c as u32,
                    dashed: false,
                });
            }
            panels.push(p);
        }
        models.push(json!({
            "model": kind.name(),
            "fit_s": fit_s,
            "log_marginal_likelihood": model.log_marginal_likelihood(),
            "column_covariances": blocks
                .iter()
                .zip(COLUMNS)
                .map(|(b, name)| json!({
                    "column": name,
                    "trace": b.trace(),
                    "rows": (0..n).map(|i| (0..n).map(|j| b[(i, j)]).collect::<Vec<_>>()).collect::<Vec<_>>(),
                }))
                .collect::<Vec<_>>(),
            "shape_spread": spread,
        }));
    }
    let fig = Figure {
        width: 1350,
        height: 900,
        rows: 2,
        cols: 3,
        title: Some(format!(
            "3σ ellipses of the unit-trace covariance of each column of F at x = (0, 0, π/4), Ackermann, k = {k}"
        )),
        panels,
    };
    render_png(&fig, &args.out.join("covariance-shapes.png"))?;
    let summary = json!({
        "scenario": "covariance-shapes",
        "seed": args.seed,
        "quick": args.quick,
        "k": k,
        "x": x_star,
        "input_map": "theta only",
        "models": models,
    });
    write_atomic(
        &args.out.join("summary.json"),
        (serde_json::to_string_pretty(&summary)? + "\n").as_bytes(),
    )?;
    eprintln!(
        "wrote {}: summary.json, covariance-shapes.png",
        args.out.display()
    );
    Ok(())
}
