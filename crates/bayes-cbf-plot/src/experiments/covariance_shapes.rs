//! `covariance-shapes.png` (paper, Fig. 1): 3σ ellipses of the unit-trace
//! covariance of each column of `F`, MVGP against CoGP.

use crate::plot::{render_png, Figure, Layer, Panel};
use crate::Result;
use bayes_cbf_scenario::experiments::covariance_shapes::{CovarianceShapes, COLUMNS, STATES};
use nalgebra::{DMatrix, SymmetricEigen};
use std::path::{Path, PathBuf};

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

/// Writes `covariance-shapes.png` into `dir`; returns the files written.
pub fn figures(r: &CovarianceShapes, dir: &Path) -> Result<Vec<PathBuf>> {
    let mut panels = Vec::new();
    for m in &r.models {
        for (a, b) in [(0usize, 1usize), (0, 2), (1, 2)] {
            let mut p = Panel::new(
                &format!("{}: ({}, {})", m.kind.name(), STATES[a], STATES[b]),
                &format!("{} (normalised)", STATES[a]),
                &format!("{} (normalised)", STATES[b]),
            );
            p.equal_aspect = true;
            for (c, bl) in m.blocks.iter().enumerate() {
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
    }
    let fig = Figure::grid((1350, 900), (2, 3), format!(
            "3σ ellipses of the unit-trace covariance of each column of F at x = (0, 0, π/4), Ackermann, k = {}",
            r.k
        ), panels);
    let path = dir.join("covariance-shapes.png");
    render_png(&fig, &path)?;
    Ok(vec![path])
}
