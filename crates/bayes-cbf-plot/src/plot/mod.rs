//! Declarative figures rendered headless to PNG and GIF with plotters.
//!
//! A [`Figure`] is a grid of [`Panel`]s; each panel has axis labels (with
//! units), optional fixed or logarithmic axes, a legend and a stack of
//! [`Layer`]s (lines, scatter, error bars, bands, reference lines, heat maps
//! with a colour bar and a zero contour, circles and vehicle markers).
//! Everything is drawn with the DejaVu Sans font embedded in the binary
//! (`assets/DejaVuSans.ttf`, licence in `assets/DejaVuSans-LICENSE.txt`), so
//! no system fonts are needed.
//!
//! Bad data never panics: non-finite points are skipped (a line is broken at
//! them), empty series draw nothing, and mismatched lengths are truncated to
//! the shorter series. Files are written completely or not at all (rendered
//! to a temporary file in the same directory, then renamed).
//!
//! ```no_run
//! # fn main() -> bayes_cbf_plot::Result<()> {
//! use bayes_cbf_plot::plot::{render_png, Figure, Layer, Panel};
//! let mut panel = Panel::new("decay", "time t (s)", "x (m)");
//! panel.layers.push(Layer::line("x(t)", vec![0.0, 1.0, 2.0], vec![1.0, 0.5, 0.25], 0));
//! let fig = Figure::single(800, 500, panel);
//! render_png(&fig, std::path::Path::new("decay.png"))?;
//! # Ok(()) }
//! ```

mod clip;
mod colormap;
mod draw;
mod layers;
#[cfg(test)]
mod tests;

use crate::{bail, err, Context, Result};
use bayes_cbf_scenario::io::write_via_temp;
use plotters::prelude::*;
use std::path::Path;
use std::sync::OnceLock;

pub use colormap::finite_min_max as finite_range;

/// The embedded font family name used by every text element.
pub(crate) const FONT: &str = "sans-serif";

/// Palette index of black.
pub const BLACK: usize = 10;
/// Palette index of grey.
pub const GREY: usize = 11;
/// Palette index of red (the paper's training-point colour).
pub const RED: usize = 3;

/// The palette as `0xRRGGBB`: Tableau-10 colours, then black and grey.
/// Indices wrap.
const PALETTE: [u32; 12] = [
    0x1f77b4, 0xff7f0e, 0x2ca02c, 0xd62728, 0x9467bd, 0x8c564b, 0xe377c2, 0x7f7f7f, 0xbcbd22,
    0x17becf, 0x000000, 0x6e6e6e,
];

/// Colour of palette index `i` (wrapping).
pub fn palette(i: usize) -> RGBColor {
    let c = PALETTE[i % PALETTE.len()];
    RGBColor((c >> 16) as u8, (c >> 8) as u8, c as u8)
}

/// Marker shape of a [`Layer::Scatter`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PointShape {
    /// Filled circle.
    #[default]
    Circle,
    /// A `+` sign (the paper marks training points with red `+`).
    Plus,
    /// An `×` sign.
    Cross,
}

/// Corner of a panel where its legend goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LegendPos {
    /// Upper left.
    UpperLeft,
    /// Upper right.
    #[default]
    UpperRight,
    /// Lower left.
    #[allow(dead_code)] // declarative API: no caller in the binary yet
    LowerLeft,
    /// Lower right.
    LowerRight,
}

/// One thing drawn in a panel, in data coordinates. `color` is a palette
/// index (see [`palette`]); `name`s appear in the panel's legend.
#[derive(Debug, Clone, PartialEq)]
pub enum Layer {
    /// Polyline through `(xs[i], ys[i])`, broken at non-finite points.
    Line {
        /// Legend entry (none: not in the legend).
        name: Option<String>,
        /// x coordinates.
        xs: Vec<f64>,
        /// y coordinates.
        ys: Vec<f64>,
        /// Palette index.
        color: usize,
        /// Line width (px).
        width: u32,
        /// Dashed line.
        dashed: bool,
    },
    /// Markers of `size` pixels.
    Scatter {
        /// Legend entry (none: not in the legend).
        name: Option<String>,
        /// x coordinates.
        xs: Vec<f64>,
        /// y coordinates.
        ys: Vec<f64>,
        /// Palette index.
        color: usize,
        /// Marker size (px).
        size: u32,
        /// Marker shape.
        shape: PointShape,
    },
    /// Vertical error bars from `lo[i]` to `hi[i]` with a dot at `mid[i]`.
    ErrorBars {
        /// Legend entry (none: not in the legend).
        name: Option<String>,
        /// x coordinates.
        xs: Vec<f64>,
        /// Central values.
        mid: Vec<f64>,
        /// Lower ends.
        lo: Vec<f64>,
        /// Upper ends.
        hi: Vec<f64>,
        /// Palette index.
        color: usize,
    },
    /// Shaded region between `lo` and `hi` over `xs` (e.g. ±2σ).
    #[allow(dead_code)] // declarative API: no caller in the binary yet
    Band {
        /// x coordinates.
        xs: Vec<f64>,
        /// Lower ends.
        lo: Vec<f64>,
        /// Upper ends.
        hi: Vec<f64>,
        /// Palette index.
        color: usize,
    },
    /// Horizontal line at `y` across the panel.
    HLine {
        /// The height.
        y: f64,
        /// Palette index.
        color: usize,
        /// Dashed line.
        dashed: bool,
        /// Legend entry (none: not in the legend).
        name: Option<String>,
    },
    /// Vertical line at `x` across the panel.
    VLine {
        /// The position.
        x: f64,
        /// Palette index.
        color: usize,
        /// Dashed line.
        dashed: bool,
        /// Legend entry (none: not in the legend).
        name: Option<String>,
    },
    /// Shaded horizontal stripe `lo ≤ y ≤ hi` across the panel (e.g. an
    /// unsafe sector of the pendulum angle).
    HBand {
        /// Lower ends.
        lo: f64,
        /// Upper ends.
        hi: f64,
        /// Palette index.
        color: usize,
        /// Legend entry (none: not in the legend).
        name: Option<String>,
    },
    /// Heat map of `values` (row-major `ys.len() × xs.len()`, row `j` at
    /// `y = ys[j]`) on the grid of cell centres `xs × ys`, with a colour bar
    /// titled `label` beside the panel. `diverging` uses a blue–white–red
    /// map symmetric about zero; otherwise viridis. `range` fixes the colour
    /// scale (to compare panels); `zero_contour` draws the zero level set.
    Heatmap {
        /// x coordinates.
        xs: Vec<f64>,
        /// y coordinates.
        ys: Vec<f64>,
        /// Values, row-major over `ys × xs`.
        values: Vec<f64>,
        /// Draw the zero level set.
        zero_contour: bool,
        /// Colour-bar label.
        label: String,
        /// Diverging colour map (centred at zero).
        diverging: bool,
        /// Colour range (default: the data's).
        range: Option<(f64, f64)>,
    },
    /// Circle of radius `r` (data units) around `(cx, cy)`, lightly filled.
    Circle {
        /// Cx.
        cx: f64,
        /// Cy.
        cy: f64,
        /// R.
        r: f64,
        /// Palette index.
        color: usize,
        /// Legend entry (none: not in the legend).
        name: Option<String>,
    },
    /// A pose marker of `size` pixels at `(x, y)`: a triangle pointing along
    /// `heading` (radians from the x axis), or a dot without a heading.
    Marker {
        /// The position.
        x: f64,
        /// The height.
        y: f64,
        /// Heading.
        heading: Option<f64>,
        /// Palette index.
        color: usize,
        /// Marker size (px).
        size: u32,
    },
}

impl Layer {
    /// A solid named line of width 2.
    pub fn line(name: &str, xs: Vec<f64>, ys: Vec<f64>, color: usize) -> Self {
        Layer::Line {
            name: Some(name.to_string()),
            xs,
            ys,
            color,
            width: 2,
            dashed: false,
        }
    }
}

/// One chart: title, axis labels (put units in them, e.g. `"θ (rad)"`),
/// optional fixed ranges, log axes, equal aspect ratio, legend, layers.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Panel {
    /// Title above the chart.
    pub title: String,
    /// x-axis label with unit.
    pub x_label: String,
    /// y-axis label with unit.
    pub y_label: String,
    /// Fixed x range; automatic (finite data + 5 %) when `None`.
    pub x_range: Option<(f64, f64)>,
    /// Fixed y range; automatic when `None`.
    pub y_range: Option<(f64, f64)>,
    /// Logarithmic x axis (non-positive values are skipped).
    pub log_x: bool,
    /// Logarithmic y axis (non-positive values are skipped).
    pub log_y: bool,
    /// Same data units per pixel on both axes (ranges are widened to fit).
    pub equal_aspect: bool,
    /// Draw a legend of the named layers.
    pub legend: bool,
    /// Legend corner.
    pub legend_pos: LegendPos,
    /// Layers, drawn in order.
    pub layers: Vec<Layer>,
}

impl Panel {
    /// An empty panel with a title and axis labels, legend on.
    pub fn new(title: &str, x_label: &str, y_label: &str) -> Self {
        Panel {
            title: title.to_string(),
            x_label: x_label.to_string(),
            y_label: y_label.to_string(),
            legend: true,
            ..Panel::default()
        }
    }
}

/// A `rows × cols` grid of panels (row-major; missing panels stay blank)
/// on a `width × height` pixel canvas with an optional overall title.
#[derive(Debug, Clone, PartialEq)]
pub struct Figure {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Rows of panels.
    pub rows: usize,
    /// Columns of panels.
    pub cols: usize,
    /// Overall title.
    pub title: Option<String>,
    /// Panels, row-major.
    pub panels: Vec<Panel>,
}

impl Figure {
    /// `panels` (row-major) on a `grid = (rows, cols)` under `title`, at
    /// `size = (width, height)` pixels.
    pub fn grid(
        size: (u32, u32),
        grid: (usize, usize),
        title: impl Into<String>,
        panels: Vec<Panel>,
    ) -> Self {
        Figure {
            width: size.0,
            height: size.1,
            rows: grid.0,
            cols: grid.1,
            title: Some(title.into()),
            panels,
        }
    }

    /// A figure holding one panel.
    pub fn single(width: u32, height: u32, panel: Panel) -> Self {
        Figure {
            width,
            height,
            rows: 1,
            cols: 1,
            title: None,
            panels: vec![panel],
        }
    }

    fn check(&self) -> Result<()> {
        if !(16..=16_384).contains(&self.width) || !(16..=16_384).contains(&self.height) {
            bail!(
                "figure size {}×{} must be within 16..=16384 pixels",
                self.width,
                self.height
            );
        }
        if self.rows == 0 || self.cols == 0 || self.rows * self.cols > 256 {
            bail!(
                "figure grid {}×{} must have 1..=256 cells",
                self.rows,
                self.cols
            );
        }
        if self.panels.len() > self.rows * self.cols {
            bail!(
                "figure has {} panels but only {}×{} cells",
                self.panels.len(),
                self.rows,
                self.cols
            );
        }
        Ok(())
    }
}

/// Registers the embedded DejaVu Sans once for every style plotters asks for.
pub(crate) fn ensure_font() -> Result<()> {
    static FONT_OK: OnceLock<bool> = OnceLock::new();
    static BYTES: &[u8] = include_bytes!("../../assets/DejaVuSans.ttf");
    let ok = *FONT_OK.get_or_init(|| {
        [
            FontStyle::Normal,
            FontStyle::Bold,
            FontStyle::Italic,
            FontStyle::Oblique,
        ]
        .into_iter()
        .all(|s| plotters::style::register_font(FONT, s, BYTES).is_ok())
    });
    if ok {
        Ok(())
    } else {
        Err(err!("the embedded font DejaVuSans.ttf could not be loaded"))
    }
}

/// Checks that `path` ends in `.{ext}`, from which the encoder picks the
/// image format.
fn check_extension(path: &Path, ext: &str) -> Result<()> {
    match path.extension() {
        Some(e) if e.eq_ignore_ascii_case(ext) => Ok(()),
        _ => Err(err!(
            "output file '{}' must end in .{ext} (the image format)",
            path.display()
        )),
    }
}

/// Renders `fig` to the PNG file `path` (written completely or not at all).
pub fn render_png(fig: &Figure, path: &Path) -> Result<()> {
    check_extension(path, "png")?;
    fig.check()?;
    ensure_font()?;
    write_via_temp(path, |tmp| {
        let root = BitMapBackend::new(tmp, (fig.width, fig.height)).into_drawing_area();
        draw::draw_figure(&root, fig)?;
        root.present()
            .map_err(|e| err!("cannot encode the PNG: {e}"))?;
        Ok(())
    })
    .with_context(|| format!("rendering '{}'", path.display()))
}

/// Renders `frames` as an animated GIF at `path`, `frame_delay_ms` per frame
/// (written completely or not at all). All frames take the first frame's size.
pub fn render_gif(frames: &[Figure], frame_delay_ms: u32, path: &Path) -> Result<()> {
    check_extension(path, "gif")?;
    let first = frames
        .first()
        .ok_or_else(|| err!("an animation needs at least one frame"))?;
    for (i, f) in frames.iter().enumerate() {
        f.check().with_context(|| format!("frame {i}"))?;
        if (f.width, f.height) != (first.width, first.height) {
            bail!(
                "frame {i} is {}×{} but frame 0 is {}×{}",
                f.width,
                f.height,
                first.width,
                first.height
            );
        }
    }
    ensure_font()?;
    write_via_temp(path, |tmp| {
        let root = BitMapBackend::gif(tmp, (first.width, first.height), frame_delay_ms)
            .map_err(|e| err!("cannot start the GIF: {e}"))?
            .into_drawing_area();
        for fig in frames {
            draw::draw_figure(&root, fig)?;
            root.present()
                .map_err(|e| err!("cannot encode a GIF frame: {e}"))?;
        }
        Ok(())
    })
    .with_context(|| format!("rendering '{}'", path.display()))
}
