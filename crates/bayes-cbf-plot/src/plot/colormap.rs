//! Colour maps, the zero level set of a gridded field (marching squares),
//! tick-label formatting and axis-range helpers.

use plotters::style::colors::colormaps::{ColorMap, DerivedColorMap, ViridisRGB};
use plotters::style::RGBColor;
use std::sync::LazyLock;

/// A blue–white–red diverging map on `[0, 1]` through these control points
/// (the sequential map is plotters' viridis).
static DIVERGING: LazyLock<DerivedColorMap<RGBColor>> =
    LazyLock::new(|| DerivedColorMap::new(&DIVERGING_POINTS));
const DIVERGING_POINTS: [RGBColor; 7] = [
    RGBColor(33, 102, 172),
    RGBColor(103, 169, 207),
    RGBColor(209, 229, 240),
    RGBColor(247, 247, 247),
    RGBColor(253, 219, 199),
    RGBColor(239, 138, 98),
    RGBColor(178, 24, 43),
];

/// A colour scale mapping values in `[lo, hi]` to colours.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct ColorScale {
    pub lo: f64,
    pub hi: f64,
    pub diverging: bool,
}

impl ColorScale {
    /// The scale of finite `values` (or the fixed `range`); a diverging
    /// scale is made symmetric about zero. Never degenerate.
    pub fn new(values: &[f64], range: Option<(f64, f64)>, diverging: bool) -> Self {
        let (mut lo, mut hi) = match range {
            Some((a, b)) if a.is_finite() && b.is_finite() => (a.min(b), a.max(b)),
            _ => finite_min_max(values).unwrap_or((0.0, 1.0)),
        };
        if diverging {
            let m = lo.abs().max(hi.abs());
            (lo, hi) = (-m, m);
        }
        if hi - lo <= 1e-12 * lo.abs().max(hi.abs()).max(1e-300) {
            let pad = (0.05 * lo.abs()).max(1e-9);
            (lo, hi) = (lo - pad, hi + pad);
        }
        ColorScale { lo, hi, diverging }
    }

    /// Colour of value `v` (clamped to the scale; the middle colour for a
    /// value that is not finite).
    pub fn color(&self, v: f64) -> RGBColor {
        let t = (v - self.lo) / (self.hi - self.lo);
        let t = if t.is_finite() {
            t.clamp(0.0, 1.0)
        } else {
            0.5
        };
        if self.diverging {
            DIVERGING.get_color(t)
        } else {
            ViridisRGB.get_color(t)
        }
    }
}

/// Smallest and largest finite value, if any.
pub fn finite_min_max(values: &[f64]) -> Option<(f64, f64)> {
    values
        .iter()
        .filter(|v| v.is_finite())
        .fold(None, |acc, &v| match acc {
            None => Some((v, v)),
            Some((a, b)) => Some((a.min(v), b.max(v))),
        })
}

/// A line segment `((x0, y0), (x1, y1))` in data coordinates.
pub(crate) type Segment = ((f64, f64), (f64, f64));

/// The zero level set of `values` (row-major `ys.len() × xs.len()`) on the
/// grid `xs × ys` by marching squares with linear interpolation along cell
/// edges; saddle cells are resolved by the sign of the cell mean. Cells
/// with a non-finite corner are skipped; mismatched sizes give no segments.
///
/// Not the `contour` crate: its port of d3-contour builds closed rings,
/// closing each level set along the border of the grid, and compares a
/// value that is not finite as below every threshold, so it would draw
/// lines along the edge of the plot and around the cells where a barrier
/// is not defined.
pub(crate) fn marching_squares_zero(xs: &[f64], ys: &[f64], values: &[f64]) -> Vec<Segment> {
    let (nx, ny) = (xs.len(), ys.len());
    let mut out = Vec::new();
    if nx < 2 || ny < 2 || values.len() != nx * ny {
        return out;
    }
    let at = |i: usize, j: usize| values[j * nx + i];
    let cross = |p: (f64, f64), q: (f64, f64), a: f64, b: f64| {
        let t = if a == b { 0.5 } else { a / (a - b) };
        (p.0 + t * (q.0 - p.0), p.1 + t * (q.1 - p.1))
    };
    for j in 0..ny - 1 {
        for i in 0..nx - 1 {
            let (v00, v10, v01, v11) = (at(i, j), at(i + 1, j), at(i, j + 1), at(i + 1, j + 1));
            let corners = [xs[i], xs[i + 1], ys[j], ys[j + 1], v00, v10, v01, v11];
            if corners.iter().any(|v| !v.is_finite()) {
                continue;
            }
            let (p00, p10, p01, p11) = (
                (xs[i], ys[j]),
                (xs[i + 1], ys[j]),
                (xs[i], ys[j + 1]),
                (xs[i + 1], ys[j + 1]),
            );
            let pos = |v: f64| v >= 0.0;
            // edges: bottom, right, top, left
            let edges = [
                (p00, p10, v00, v10),
                (p10, p11, v10, v11),
                (p01, p11, v01, v11),
                (p00, p01, v00, v01),
            ];
            let hits: Vec<Option<(f64, f64)>> = edges
                .iter()
                .map(|&(p, q, a, b)| (pos(a) != pos(b)).then(|| cross(p, q, a, b)))
                .collect();
            let found: Vec<(f64, f64)> = hits.iter().flatten().copied().collect();
            match found.len() {
                2 => out.push((found[0], found[1])),
                4 => {
                    let centre = 0.25 * (v00 + v10 + v01 + v11);
                    let h = |e: usize| hits[e].unwrap_or_default();
                    if pos(centre) == pos(v00) {
                        out.push((h(0), h(1)));
                        out.push((h(2), h(3)));
                    } else {
                        out.push((h(0), h(3)));
                        out.push((h(2), h(1)));
                    }
                }
                _ => {}
            }
        }
    }
    out
}

/// A short tick label: about three significant digits, scientific notation
/// for very large or small magnitudes, no trailing zeros.
pub(crate) fn fmt_tick(v: f64) -> String {
    if !v.is_finite() {
        return String::new();
    }
    let a = v.abs();
    if a < 1e-12 {
        return "0".into();
    }
    if !(1e-3..1e5).contains(&a) {
        let s = format!("{v:.1e}");
        return s.replace(".0e", "e");
    }
    let decimals = (2 - a.log10().floor() as i32).clamp(0, 4) as usize;
    let s = format!("{v:.decimals$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// A usable axis range from optional fixed bounds and finite data values:
/// data range padded by 5 %; log axes use positive values only and pad by a
/// factor. Never empty or inverted.
pub(crate) fn axis_range(fixed: Option<(f64, f64)>, data: &[f64], log: bool) -> (f64, f64) {
    if let Some((a, b)) = fixed {
        let ok = a.is_finite() && b.is_finite() && a != b && (!log || (a > 0.0 && b > 0.0));
        if ok {
            return (a.min(b), a.max(b));
        }
    }
    if log {
        let pos: Vec<f64> = data
            .iter()
            .copied()
            .filter(|v| v.is_finite() && *v > 0.0)
            .collect();
        return match finite_min_max(&pos) {
            Some((lo, hi)) if hi > lo => (lo / 1.12, hi * 1.12),
            Some((lo, _)) => (lo / 2.0, lo * 2.0),
            None => (1.0, 10.0),
        };
    }
    match finite_min_max(data) {
        Some((lo, hi)) if hi > lo => {
            let pad = 0.05 * (hi - lo);
            (lo - pad, hi + pad)
        }
        Some((lo, _)) => {
            let pad = (0.1 * lo.abs()).max(0.5);
            (lo - pad, lo + pad)
        }
        None => (0.0, 1.0),
    }
}
