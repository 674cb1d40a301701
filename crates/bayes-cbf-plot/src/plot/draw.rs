//! Drawing a [`Figure`] onto any plotters backend: panel layout, axes
//! (linear or logarithmic), layers clipped to the axis box, legend and
//! colour bar.

use super::clip::{ticks, Axes};
use super::colormap::{axis_range, fmt_tick, ColorScale};
use super::layers::draw_layer;
use super::{Figure, Layer, LegendPos, Panel, FONT};
use crate::{err, Result};
use plotters::coord::ranged1d::{DefaultFormatting, KeyPointHint};
use plotters::coord::Shift;
use plotters::prelude::*;

/// Converts any plotters error into this crate's error.
pub(super) fn de<E: std::fmt::Debug>(e: E) -> crate::Error {
    err!("drawing failed: {e:?}")
}

/// Width (pixels) of the colour-bar strip of a panel with a heat map.
const BAR_WIDTH: u32 = 105;
const X_LABEL_AREA: u32 = 48;
const Y_LABEL_AREA: u32 = 72;
const CAPTION_PX: u32 = 20;

/// Draws `fig` onto `root` (cleared to white first).
pub(super) fn draw_figure<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    fig: &Figure,
) -> Result<()> {
    root.fill(&WHITE).map_err(de)?;
    let area = match &fig.title {
        Some(t) => root.titled(t, (FONT, 26)).map_err(de)?,
        None => root.clone(),
    };
    let cells = area.split_evenly((fig.rows, fig.cols));
    for (panel, cell) in fig.panels.iter().zip(cells.iter()) {
        draw_panel(cell, panel)?;
    }
    Ok(())
}

/// All x and y values a panel's layers want visible (for automatic ranges).
fn extents(panel: &Panel) -> (Vec<f64>, Vec<f64>) {
    let (mut xs, mut ys) = (Vec::new(), Vec::new());
    for layer in &panel.layers {
        match layer {
            Layer::Line { xs: a, ys: b, .. } | Layer::Scatter { xs: a, ys: b, .. } => {
                xs.extend(a);
                ys.extend(b);
            }
            Layer::ErrorBars {
                xs: a, mid, lo, hi, ..
            } => {
                xs.extend(a);
                ys.extend(mid.iter().chain(lo).chain(hi));
            }
            Layer::Band { xs: a, lo, hi, .. } => {
                xs.extend(a);
                ys.extend(lo.iter().chain(hi));
            }
            Layer::HLine { y, .. } => ys.push(*y),
            Layer::VLine { x, .. } => xs.push(*x),
            Layer::HBand { .. } => {}
            Layer::Heatmap { xs: a, ys: b, .. } => {
                xs.extend(cell_edges(a));
                ys.extend(cell_edges(b));
            }
            Layer::Circle { cx, cy, r, .. } => {
                xs.extend([cx - r, cx + r]);
                ys.extend([cy - r, cy + r]);
            }
            Layer::Marker { x, y, .. } => {
                xs.push(*x);
                ys.push(*y);
            }
        }
    }
    (xs, ys)
}

/// Cell edges of a grid of centres: midpoints, extended by half a step.
pub(super) fn cell_edges(c: &[f64]) -> Vec<f64> {
    match c.len() {
        0 => Vec::new(),
        1 => vec![c[0] - 0.5, c[0] + 0.5],
        n => {
            let mut e = Vec::with_capacity(n + 1);
            e.push(c[0] - 0.5 * (c[1] - c[0]));
            e.extend(c.windows(2).map(|w| 0.5 * (w[0] + w[1])));
            e.push(c[n - 1] + 0.5 * (c[n - 1] - c[n - 2]));
            e
        }
    }
}

/// Widens one range so both axes have the same data units per pixel.
fn equalise(xr: &mut (f64, f64), yr: &mut (f64, f64), w_px: f64, h_px: f64) {
    let (sx, sy) = ((xr.1 - xr.0) / w_px.max(1.0), (yr.1 - yr.0) / h_px.max(1.0));
    if sx > sy {
        let (c, half) = (0.5 * (yr.0 + yr.1), 0.5 * sx * h_px);
        *yr = (c - half, c + half);
    } else {
        let (c, half) = (0.5 * (xr.0 + xr.1), 0.5 * sy * w_px);
        *xr = (c - half, c + half);
    }
}

fn draw_panel<DB: DrawingBackend>(cell: &DrawingArea<DB, Shift>, panel: &Panel) -> Result<()> {
    let heat = panel.layers.iter().find_map(|l| match l {
        Layer::Heatmap {
            values,
            range,
            diverging,
            label,
            ..
        } => Some((ColorScale::new(values, *range, *diverging), label.clone())),
        _ => None,
    });
    let (w, h) = cell.dim_in_pixel();
    let (area, bar) = if heat.is_some() && w > 2 * BAR_WIDTH {
        let (a, b) = cell.split_horizontally(w - BAR_WIDTH);
        (a, Some(b))
    } else {
        (cell.clone(), None)
    };
    let (xd, yd) = extents(panel);
    let mut xr = axis_range(panel.x_range, &xd, panel.log_x);
    let mut yr = axis_range(panel.y_range, &yd, panel.log_y);
    if panel.equal_aspect && !panel.log_x && !panel.log_y {
        let (aw, _) = area.dim_in_pixel();
        let pw = aw as f64 - Y_LABEL_AREA as f64 - 20.0;
        let ph = h as f64 - X_LABEL_AREA as f64 - CAPTION_PX as f64 - 30.0;
        equalise(&mut xr, &mut yr, pw, ph);
    }
    let axes = Axes {
        x: xr,
        y: yr,
        log_x: panel.log_x,
        log_y: panel.log_y,
    };
    chart(&area, panel, &axes)?;
    if let (Some(bar), Some((scale, label))) = (bar, heat) {
        color_bar(&bar, &scale, &label)?;
    }
    Ok(())
}

/// Builds the chart in axis space (see [`super::clip`]) with nice ticks
/// and draws every layer.
fn chart<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    panel: &Panel,
    axes: &Axes,
) -> Result<()> {
    let Some((x0, x1, y0, y1)) = axes.bounds() else {
        return Ok(());
    };
    let xs = TickAxis {
        lo: x0,
        hi: x1,
        ticks: ticks(axes.x.0, axes.x.1, axes.log_x),
    };
    let ys = TickAxis {
        lo: y0,
        hi: y1,
        ticks: ticks(axes.y.0, axes.y.1, axes.log_y),
    };
    let mut ch = ChartBuilder::on(area)
        .caption(&panel.title, (FONT, CAPTION_PX))
        .margin(10)
        .x_label_area_size(X_LABEL_AREA)
        .y_label_area_size(Y_LABEL_AREA)
        .build_cartesian_2d(xs, ys)
        .map_err(de)?;
    let (lx, ly) = (axes.log_x, axes.log_y);
    let fmt_x = move |v: &f64| fmt_tick(if lx { 10f64.powf(*v) } else { *v });
    let fmt_y = move |v: &f64| fmt_tick(if ly { 10f64.powf(*v) } else { *v });
    ch.configure_mesh()
        .x_desc(panel.x_label.as_str())
        .y_desc(panel.y_label.as_str())
        .label_style((FONT, 14))
        .axis_desc_style((FONT, 16))
        .x_label_formatter(&fmt_x)
        .y_label_formatter(&fmt_y)
        .bold_line_style(RGBColor(210, 210, 210))
        .light_line_style(RGBColor(238, 238, 238))
        .draw()
        .map_err(de)?;
    let mut named = false;
    for layer in &panel.layers {
        named |= draw_layer(&mut ch, layer, axes)?;
    }
    if panel.legend && named {
        let pos = match panel.legend_pos {
            LegendPos::UpperLeft => SeriesLabelPosition::UpperLeft,
            LegendPos::UpperRight => SeriesLabelPosition::UpperRight,
            LegendPos::LowerLeft => SeriesLabelPosition::LowerLeft,
            LegendPos::LowerRight => SeriesLabelPosition::LowerRight,
        };
        ch.configure_series_labels()
            .position(pos)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font((FONT, 14))
            .draw()
            .map_err(de)?;
    }
    Ok(())
}

/// A linear axis in axis space with explicit tick positions.
#[derive(Debug, Clone)]
pub(super) struct TickAxis {
    lo: f64,
    hi: f64,
    ticks: Vec<f64>,
}

impl Ranged for TickAxis {
    type FormatOption = DefaultFormatting;
    type ValueType = f64;

    fn map(&self, v: &f64, limit: (i32, i32)) -> i32 {
        let t = (v - self.lo) / (self.hi - self.lo);
        let px = limit.0 as f64 + t * (limit.1 - limit.0) as f64;
        px.clamp(-1e6, 1e6).round() as i32
    }

    fn key_points<H: KeyPointHint>(&self, hint: H) -> Vec<f64> {
        // labelled ticks and bold grid lines only; no light grid lines
        if hint.weight().allow_light_points() {
            Vec::new()
        } else {
            self.ticks.clone()
        }
    }

    fn range(&self) -> std::ops::Range<f64> {
        self.lo..self.hi
    }
}

pub(super) type Chart<'a, DB> = ChartContext<'a, DB, Cartesian2d<TickAxis, TickAxis>>;

/// A vertical colour bar for `scale`, ticks on the right, titled `label`.
fn color_bar<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    scale: &ColorScale,
    label: &str,
) -> Result<()> {
    let (lo, hi) = (scale.lo, scale.hi);
    let mut ch = ChartBuilder::on(area)
        .margin_top(10 + CAPTION_PX + 12)
        .margin_bottom(10)
        .margin_left(14)
        .margin_right(4)
        .set_label_area_size(LabelAreaPosition::Right, 62)
        .set_label_area_size(LabelAreaPosition::Bottom, X_LABEL_AREA)
        .build_cartesian_2d(0.0..1.0, lo..hi)
        .map_err(de)?;
    let steps = 128;
    ch.draw_series((0..steps).map(|i| {
        let a = lo + (hi - lo) * i as f64 / steps as f64;
        let b = lo + (hi - lo) * (i + 1) as f64 / steps as f64;
        Rectangle::new([(0.0, a), (1.0, b)], scale.color(0.5 * (a + b)).filled())
    }))
    .map_err(de)?;
    let fmt = |v: &f64| fmt_tick(*v);
    ch.configure_mesh()
        .disable_mesh()
        .disable_x_axis()
        .y_desc(label)
        .y_labels(7)
        .y_label_formatter(&fmt)
        .label_style((FONT, 13))
        .axis_desc_style((FONT, 14))
        .draw()
        .map_err(de)?;
    Ok(())
}
