//! Drawing the layers of a panel: every [`Layer`] kind, clipped to the axis
//! box in axis space, with its legend entry.

use super::clip::{clip_polygon, clip_segment, Axes};
use super::colormap::{marching_squares_zero, ColorScale};
use super::draw::{cell_edges, de, Chart};
use super::{palette, Layer, PointShape};
use crate::Result;
use plotters::chart::SeriesAnno;
use plotters::element::DashedPathElement;
use plotters::prelude::*;

/// Attaches a legend entry when `name` is set; `kind` picks the sample:
/// 0 line, 1 dot, 2 filled box, 3 plus, 4 cross, 5 dashed line.
fn legend<'a, DB: DrawingBackend + 'a>(
    anno: &mut SeriesAnno<'a, DB>,
    name: &Option<String>,
    style: ShapeStyle,
    kind: u8,
) -> bool {
    let Some(n) = name else { return false };
    let anno = anno.label(n.as_str());
    match kind {
        0 => anno.legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 22, y)], style)),
        5 => anno.legend(move |(x, y)| {
            EmptyElement::at((x, y))
                + PathElement::new(vec![(0, 0), (8, 0)], style)
                + PathElement::new(vec![(14, 0), (22, 0)], style)
        }),
        1 => anno.legend(move |(x, y)| Circle::new((x + 11, y), 4, style)),
        3 => anno.legend(move |(x, y)| {
            EmptyElement::at((x + 11, y))
                + PathElement::new(vec![(-5, 0), (5, 0)], style)
                + PathElement::new(vec![(0, -5), (0, 5)], style)
        }),
        4 => anno.legend(move |(x, y)| {
            EmptyElement::at((x + 11, y))
                + PathElement::new(vec![(-4, -4), (4, 4)], style)
                + PathElement::new(vec![(-4, 4), (4, -4)], style)
        }),
        _ => anno.legend(move |(x, y)| Rectangle::new([(x, y - 6), (x + 22, y + 6)], style)),
    };
    true
}

/// Draws polylines, solid or dashed, as one series.
fn draw_lines<'a, 'b, DB>(
    ch: &'b mut Chart<'a, DB>,
    segs: Vec<Vec<(f64, f64)>>,
    style: ShapeStyle,
    dashed: bool,
) -> Result<&'b mut SeriesAnno<'a, DB>>
where
    DB: DrawingBackend + 'a,
{
    if dashed {
        ch.draw_series(
            segs.into_iter()
                .map(|s| DashedPathElement::new(s, 8, 5, style)),
        )
        .map_err(de)
    } else {
        ch.draw_series(segs.into_iter().map(|s| PathElement::new(s, style)))
            .map_err(de)
    }
}

/// Fills the polygon `pts` clipped to the axis box (nothing where less
/// than a triangle is left), as one series.
fn fill_clipped<'a, 'b, DB>(
    ch: &'b mut Chart<'a, DB>,
    ax: &Axes,
    pts: &[(f64, f64)],
    style: ShapeStyle,
) -> Result<&'b mut SeriesAnno<'a, DB>>
where
    DB: DrawingBackend + 'a,
{
    let poly = clip_polygon(ax, pts);
    ch.draw_series((poly.len() >= 3).then(|| Polygon::new(poly, style)))
        .map_err(de)
}

/// Draws polylines, solid or dashed, with a legend entry of the same line
/// when `name` is set; returns whether it added one.
fn draw_named_lines<'a, DB>(
    ch: &mut Chart<'a, DB>,
    segs: Vec<Vec<(f64, f64)>>,
    style: ShapeStyle,
    dashed: bool,
    name: &Option<String>,
) -> Result<bool>
where
    DB: DrawingBackend + 'a,
{
    let anno = draw_lines(ch, segs, style, dashed)?;
    Ok(legend(anno, name, style, if dashed { 5 } else { 0 }))
}

/// Draws one layer; returns whether it added a legend entry.
pub(super) fn draw_layer<'a, DB>(ch: &mut Chart<'a, DB>, layer: &Layer, ax: &Axes) -> Result<bool>
where
    DB: DrawingBackend + 'a,
{
    let (x0, x1, y0, y1) = (ax.x.0, ax.x.1, ax.y.0, ax.y.1);
    let solid = |c: usize, w: u32| palette(c).stroke_width(w);
    let segments = |pts: Vec<(f64, f64)>| -> Vec<Vec<(f64, f64)>> {
        let mut out: Vec<Vec<(f64, f64)>> = Vec::new();
        for w in pts.windows(2) {
            if let Some((a, b)) = clip_segment(ax, w[0], w[1]) {
                match out.last_mut() {
                    Some(last) if last.last() == Some(&a) => last.push(b),
                    _ => out.push(vec![a, b]),
                }
            } else {
                out.push(Vec::new());
            }
        }
        out.retain(|s| s.len() >= 2);
        out
    };
    Ok(match layer {
        Layer::Line {
            name,
            xs,
            ys,
            color,
            width,
            dashed,
        } => {
            let pts: Vec<(f64, f64)> = xs.iter().copied().zip(ys.iter().copied()).collect();
            let style = solid(*color, (*width).max(1));
            draw_named_lines(ch, segments(pts), style, *dashed, name)?
        }
        Layer::Scatter {
            name,
            xs,
            ys,
            color,
            size,
            shape,
        } => {
            let pts: Vec<(f64, f64)> = xs
                .iter()
                .copied()
                .zip(ys.iter().copied())
                .filter_map(|p| ax.point(p))
                .collect();
            let s = (*size).max(1) as i32;
            let style = solid(*color, 2);
            let anno = match shape {
                PointShape::Circle => ch
                    .draw_series(
                        pts.into_iter()
                            .map(|p| Circle::new(p, s, palette(*color).filled())),
                    )
                    .map_err(de)?,
                PointShape::Plus | PointShape::Cross => {
                    let (a, b) = if *shape == PointShape::Plus {
                        (((-s, 0), (s, 0)), ((0, -s), (0, s)))
                    } else {
                        (((-s, -s), (s, s)), ((-s, s), (s, -s)))
                    };
                    ch.draw_series(pts.into_iter().map(|p| {
                        EmptyElement::at(p)
                            + PathElement::new(vec![a.0, a.1], style)
                            + PathElement::new(vec![b.0, b.1], style)
                    }))
                    .map_err(de)?
                }
            };
            let marker = if *shape == PointShape::Circle {
                palette(*color).filled()
            } else {
                style
            };
            let kind = match shape {
                PointShape::Circle => 1,
                PointShape::Plus => 3,
                PointShape::Cross => 4,
            };
            legend(anno, name, marker, kind)
        }
        Layer::ErrorBars {
            name,
            xs,
            mid,
            lo,
            hi,
            color,
        } => {
            let style = solid(*color, 2);
            let n = xs.len().min(mid.len()).min(lo.len()).min(hi.len());
            let bars: Vec<(f64, f64, f64, f64)> = (0..n)
                .filter_map(|i| {
                    let (x, l, m, h) = (xs[i], lo[i].min(hi[i]), mid[i], lo[i].max(hi[i]));
                    let (px, pl) = ax.point((x, l))?;
                    Some((px, pl, ax.point((x, m))?.1, ax.point((x, h))?.1))
                })
                .collect();
            let anno = ch
                .draw_series(
                    bars.iter()
                        .map(|&(x, l, m, h)| ErrorBar::new_vertical(x, l, m, h, style, 10)),
                )
                .map_err(de)?;
            legend(anno, name, style, 0)
        }
        Layer::Band { xs, lo, hi, color } => {
            let n = xs.len().min(lo.len()).min(hi.len());
            let idx: Vec<usize> = (0..n)
                .filter(|&i| xs[i].is_finite() && lo[i].is_finite() && hi[i].is_finite())
                .collect();
            let mut poly: Vec<(f64, f64)> = idx.iter().map(|&i| (xs[i], hi[i])).collect();
            poly.extend(idx.iter().rev().map(|&i| (xs[i], lo[i])));
            fill_clipped(ch, ax, &poly, palette(*color).mix(0.2).filled())?;
            false
        }
        Layer::HLine {
            y: at,
            color,
            dashed,
            name,
        }
        | Layer::VLine {
            x: at,
            color,
            dashed,
            name,
        } => {
            let style = solid(*color, 2);
            let ends = if matches!(layer, Layer::HLine { .. }) {
                vec![(x0, *at), (x1, *at)]
            } else {
                vec![(*at, y0), (*at, y1)]
            };
            draw_named_lines(ch, segments(ends), style, *dashed, name)?
        }
        Layer::HBand {
            lo,
            hi,
            color,
            name,
        } => {
            let style = palette(*color).mix(0.25).filled();
            let corners = [(x0, *lo), (x1, *lo), (x1, *hi), (x0, *hi)];
            let anno = fill_clipped(ch, ax, &corners, style)?;
            legend(anno, name, style, 2)
        }
        Layer::Heatmap {
            xs,
            ys,
            values,
            zero_contour,
            range,
            diverging,
            ..
        } => {
            let scale = ColorScale::new(values, *range, *diverging);
            let (ex, ey) = (cell_edges(xs), cell_edges(ys));
            let mut cells = Vec::new();
            if values.len() == xs.len() * ys.len() {
                for j in 0..ys.len() {
                    for i in 0..xs.len() {
                        let v = values[j * xs.len() + i];
                        let rect = [
                            (ex[i], ey[j]),
                            (ex[i + 1], ey[j]),
                            (ex[i + 1], ey[j + 1]),
                            (ex[i], ey[j + 1]),
                        ];
                        let poly = clip_polygon(ax, &rect);
                        if v.is_finite() && poly.len() >= 3 {
                            cells.push(Polygon::new(poly, scale.color(v).filled()));
                        }
                    }
                }
            }
            ch.draw_series(cells).map_err(de)?;
            if *zero_contour {
                let style = BLACK.stroke_width(2);
                let segs: Vec<Vec<(f64, f64)>> = marching_squares_zero(xs, ys, values)
                    .into_iter()
                    .filter_map(|(a, b)| clip_segment(ax, a, b).map(|(a, b)| vec![a, b]))
                    .collect();
                draw_named_lines(ch, segs, style, false, &Some("zero level".into()))?
            } else {
                false
            }
        }
        Layer::Circle {
            cx,
            cy,
            r,
            color,
            name,
        } => {
            if !(cx.is_finite() && cy.is_finite() && r.is_finite() && *r > 0.0) {
                return Ok(false);
            }
            let ring: Vec<(f64, f64)> = (0..=96)
                .map(|i| {
                    let t = std::f64::consts::TAU * i as f64 / 96.0;
                    (cx + r * t.cos(), cy + r * t.sin())
                })
                .collect();
            fill_clipped(ch, ax, &ring, palette(*color).mix(0.25).filled())?;
            let style = solid(*color, 2);
            let anno = draw_lines(ch, segments(ring), style, false)?;
            legend(anno, name, palette(*color).mix(0.5).filled(), 2)
        }
        Layer::Marker {
            x,
            y,
            heading,
            color,
            size,
        } => {
            let Some(at) = ax.point((*x, *y)) else {
                return Ok(false);
            };
            let s = (*size).max(2) as f64;
            let fill = palette(*color).filled();
            match heading.filter(|h| h.is_finite()) {
                Some(h) => {
                    // pixel y grows downwards
                    let pt = |a: f64, r: f64| {
                        (
                            (r * (h + a).cos()).round() as i32,
                            (-r * (h + a).sin()).round() as i32,
                        )
                    };
                    let tri = vec![pt(0.0, s), pt(2.5, 0.8 * s), pt(-2.5, 0.8 * s)];
                    let mut outline = tri.clone();
                    outline.push(tri[0]);
                    ch.draw_series(std::iter::once(
                        EmptyElement::at(at)
                            + Polygon::new(tri, fill)
                            + PathElement::new(outline, BLACK.stroke_width(1)),
                    ))
                    .map_err(de)?;
                }
                None => {
                    ch.draw_series(std::iter::once(Circle::new(at, (s / 2.0) as i32, fill)))
                        .map_err(de)?;
                }
            }
            false
        }
    })
}
