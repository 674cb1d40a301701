//! `calibration.png`: per (system, truth), the empirical violation rates
//! with 95 % intervals against the requested `1 − p`, log–log, with the
//! line `y = x`.

use crate::plot::{render_png, Figure, Layer, LegendPos, Panel, PointShape, BLACK};
use crate::Result;
use bayes_cbf_scenario::experiments::calibration::{Calibration, FLOOR};
use std::path::{Path, PathBuf};

/// Writes `calibration.png` into `dir`; returns the files written.
pub fn figures(r: &Calibration, dir: &Path) -> Result<Vec<PathBuf>> {
    let mut panels = Vec::new();
    for (pi, cell) in r.cells.iter().enumerate() {
        let mut p = Panel::new(
            &format!("{}, {}", cell.system, cell.truth.replace('_', " ")),
            "requested violation rate 1 − p (mean CBF at 0.5)",
            "empirical violation rate",
        );
        (p.log_x, p.log_y, p.legend_pos) = (true, true, LegendPos::UpperLeft);
        p.x_range = Some((5e-4, 1.0));
        p.y_range = Some((FLOOR, 1.0));
        p.legend = pi == 0;
        p.layers.push(Layer::Line {
            name: Some("y = x".into()),
            xs: vec![5e-4, 1.0],
            ys: vec![5e-4, 1.0],
            color: BLACK,
            width: 1,
            dashed: true,
        });
        for s in &cell.series {
            p.layers.push(Layer::Scatter {
                name: None,
                xs: s.xs.clone(),
                ys: s.mid.clone(),
                color: s.color,
                size: 4,
                shape: PointShape::Circle,
            });
            p.layers.push(Layer::ErrorBars {
                name: Some(s.name.into()),
                xs: s.xs.clone(),
                mid: s.mid.clone(),
                lo: s.lo.clone(),
                hi: s.hi.clone(),
                color: s.color,
            });
        }
        panels.push(p);
    }
    let cols = 2;
    let rows_n = r.cells.len().div_ceil(cols).max(1);
    let fig = Figure::grid(
        (1400, 560 * rows_n as u32),
        (rows_n, cols),
        "Safety calibration: violation rates, 95 % intervals (zero counts drawn at 1e-5)",
        panels,
    );
    let path = dir.join("calibration.png");
    render_png(&fig, &path)?;
    Ok(vec![path])
}
