//! Axis space and clipping. Charts are drawn in *axis space*: data
//! coordinates, with `log10` applied on logarithmic axes. Segments and
//! polygons are clipped to the axis box there, so nothing is drawn over the
//! labels, and non-finite or non-positive (on log axes) points are dropped.

/// The visible axis box of a panel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Axes {
    /// x range (data units).
    pub x: (f64, f64),
    /// y range (data units).
    pub y: (f64, f64),
    /// Logarithmic x axis.
    pub log_x: bool,
    /// Logarithmic y axis.
    pub log_y: bool,
}

fn fwd(v: f64, log: bool) -> Option<f64> {
    match (v.is_finite(), log) {
        (false, _) => None,
        (true, true) if v <= 0.0 => None,
        (true, true) => Some(v.log10()),
        (true, false) => Some(v),
    }
}

impl Axes {
    /// The box in axis space: `(x_lo, x_hi, y_lo, y_hi)`.
    pub fn bounds(&self) -> Option<(f64, f64, f64, f64)> {
        let (a, b) = (fwd(self.x.0, self.log_x)?, fwd(self.x.1, self.log_x)?);
        let (c, d) = (fwd(self.y.0, self.log_y)?, fwd(self.y.1, self.log_y)?);
        Some((a.min(b), a.max(b), c.min(d), c.max(d)))
    }

    /// `p` in axis space, if it can be drawn on these axes at all.
    pub fn axis_coords(self, p: (f64, f64)) -> Option<(f64, f64)> {
        Some((fwd(p.0, self.log_x)?, fwd(p.1, self.log_y)?))
    }

    /// `p` in axis space if it is drawable and inside the box.
    pub fn point(&self, p: (f64, f64)) -> Option<(f64, f64)> {
        self.contains(p).then(|| self.axis_coords(p)).flatten()
    }

    /// Whether `p` is finite, drawable on the axes and inside the box.
    pub fn contains(&self, p: (f64, f64)) -> bool {
        match (self.bounds(), self.axis_coords(p)) {
            (Some((x0, x1, y0, y1)), Some((x, y))) => x >= x0 && x <= x1 && y >= y0 && y <= y1,
            _ => false,
        }
    }
}

/// The part of segment `a`–`b` (data coordinates) inside the box, in axis
/// space (Liang–Barsky), if any.
pub(crate) fn clip_segment(
    ax: &Axes,
    a: (f64, f64),
    b: (f64, f64),
) -> Option<((f64, f64), (f64, f64))> {
    let (x0, x1, y0, y1) = ax.bounds()?;
    let (p, q) = (ax.axis_coords(a)?, ax.axis_coords(b)?);
    let (dx, dy) = (q.0 - p.0, q.1 - p.1);
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (den, num) in [
        (-dx, p.0 - x0),
        (dx, x1 - p.0),
        (-dy, p.1 - y0),
        (dy, y1 - p.1),
    ] {
        if den == 0.0 {
            if num < 0.0 {
                return None;
            }
        } else {
            let t = num / den;
            if den < 0.0 {
                t0 = t0.max(t);
            } else {
                t1 = t1.min(t);
            }
        }
    }
    if t0 > t1 {
        return None;
    }
    let at = |t: f64| (p.0 + t * dx, p.1 + t * dy);
    Some((at(t0), at(t1)))
}

/// The part of polygon `poly` (data coordinates) inside the box, in axis
/// space (Sutherland–Hodgman). Points that cannot be drawn on the axes are
/// dropped first.
pub(crate) fn clip_polygon(ax: &Axes, poly: &[(f64, f64)]) -> Vec<(f64, f64)> {
    let Some((x0, x1, y0, y1)) = ax.bounds() else {
        return Vec::new();
    };
    let mut pts: Vec<(f64, f64)> = poly.iter().filter_map(|&p| ax.axis_coords(p)).collect();
    // (axis, bound, keep-if-greater)
    let planes = [(0, x0, true), (0, x1, false), (1, y0, true), (1, y1, false)];
    for (axis, bound, greater) in planes {
        if pts.len() < 3 {
            return Vec::new();
        }
        let coord = |p: (f64, f64)| if axis == 0 { p.0 } else { p.1 };
        let inside = |p: (f64, f64)| {
            if greater {
                coord(p) >= bound
            } else {
                coord(p) <= bound
            }
        };
        let mut out = Vec::with_capacity(pts.len() + 4);
        for i in 0..pts.len() {
            let (cur, prev) = (pts[i], pts[(i + pts.len() - 1) % pts.len()]);
            let cross = || {
                let t = (bound - coord(prev)) / (coord(cur) - coord(prev));
                (prev.0 + t * (cur.0 - prev.0), prev.1 + t * (cur.1 - prev.1))
            };
            match (inside(cur), inside(prev)) {
                (true, true) => out.push(cur),
                (true, false) => {
                    out.push(cross());
                    out.push(cur);
                }
                (false, true) => out.push(cross()),
                (false, false) => {}
            }
        }
        pts = out;
    }
    pts
}

/// "Nice" tick positions in axis space for the axis range `(lo, hi)` (data
/// units): multiples of 1, 2 or 5 × 10ᵉ on linear axes; on log axes powers
/// of ten, or 1-2-5 multiples, or linear-nice values for narrow ranges.
pub(crate) fn ticks(lo: f64, hi: f64, log: bool) -> Vec<f64> {
    let linear = |lo: f64, hi: f64, target: f64| -> Vec<f64> {
        let raw = (hi - lo) / target;
        if !(raw.is_finite() && raw > 0.0) {
            return vec![lo];
        }
        let e = 10f64.powf(raw.log10().floor());
        let step = [1.0, 2.0, 2.5, 5.0, 10.0]
            .iter()
            .map(|m| m * e)
            .find(|s| *s >= raw)
            .unwrap_or(10.0 * e);
        let first = (lo / step).ceil() as i64;
        let last = (hi / step).floor() as i64;
        (first..=last).take(50).map(|i| i as f64 * step).collect()
    };
    if !log {
        return linear(lo, hi, 8.0);
    }
    let (a, b) = (lo.log10(), hi.log10());
    let decades = b - a;
    let mults: &[f64] = if decades > 5.0 {
        &[1.0]
    } else if decades > 0.9 {
        &[1.0, 2.0, 5.0]
    } else {
        &[]
    };
    let mut out = Vec::new();
    if !mults.is_empty() {
        for e in (a.floor() as i64)..=(b.ceil() as i64) {
            for m in mults {
                let v = m * 10f64.powi(e as i32);
                if v >= lo && v <= hi {
                    out.push(v.log10());
                }
            }
        }
        if decades > 10.0 {
            let keep = (decades / 8.0).ceil() as usize;
            out = out.into_iter().step_by(keep).collect();
        }
    }
    if out.len() < 3 {
        out = linear(lo, hi, 7.0)
            .into_iter()
            .filter(|v| *v > 0.0)
            .map(f64::log10)
            .collect();
    }
    out
}
