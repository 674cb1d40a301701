//! Rendering tests: every layer kind, log axes, bad data, GIFs, and the
//! geometry helpers (clipping, ticks, zero contour).

use super::clip::{clip_polygon, clip_segment, ticks, Axes};
use super::colormap::{axis_range, fmt_tick, marching_squares_zero, ColorScale};
use super::*;
use std::path::PathBuf;

/// A fresh scratch directory for one test.
fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("bayes-cbf-plot-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Copies `path` into `$BAYES_CBF_KEEP_PLOTS`, if set, to look at it.
fn keep(path: &Path) {
    if let Some(dir) = std::env::var_os("BAYES_CBF_KEEP_PLOTS") {
        let _ = std::fs::create_dir_all(&dir);
        let _ = std::fs::copy(
            path,
            Path::new(&dir).join(path.file_name().unwrap_or_default()),
        );
    }
}

/// Width and height from a PNG's IHDR chunk.
fn png_size(path: &Path) -> (u32, u32) {
    let b = std::fs::read(path).unwrap();
    assert_eq!(&b[1..4], b"PNG", "not a PNG");
    let be = |i: usize| u32::from_be_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
    (be(16), be(20))
}

/// Width, height and number of image descriptors (frames) of a GIF.
fn gif_info(path: &Path) -> (u32, u32, usize) {
    let b = std::fs::read(path).unwrap();
    assert_eq!(&b[0..3], b"GIF", "not a GIF");
    let le = |i: usize| u16::from_le_bytes([b[i], b[i + 1]]) as u32;
    // graphic control extensions: one per frame
    let frames = b.windows(2).filter(|w| w == &[0x21, 0xF9]).count();
    (le(6), le(8), frames)
}

fn grid_layer(diverging: bool, zero: bool) -> Layer {
    let xs: Vec<f64> = (0..15).map(|i| -1.0 + 2.0 * i as f64 / 14.0).collect();
    let ys = xs.clone();
    let values = ys
        .iter()
        .flat_map(|y| xs.iter().map(move |x| x * x + y * y - 0.5))
        .collect();
    Layer::Heatmap {
        xs,
        ys,
        values,
        zero_contour: zero,
        label: "h(x) (m²)".into(),
        diverging,
        range: None,
    }
}

/// One panel of every layer kind.
fn all_layers_figure() -> Figure {
    let xs: Vec<f64> = (0..30).map(|i| 0.1 + i as f64 * 0.2).collect();
    let ys: Vec<f64> = xs.iter().map(|x| x.sin()).collect();
    let mut lines = Panel::new("lines, scatter, band", "time t (s)", "θ (rad)");
    lines.layers = vec![
        Layer::Band {
            xs: xs.clone(),
            lo: ys.iter().map(|y| y - 0.3).collect(),
            hi: ys.iter().map(|y| y + 0.3).collect(),
            color: 0,
        },
        Layer::line("sin t", xs.clone(), ys.clone(), 0),
        Layer::Line {
            name: Some("dashed".into()),
            xs: xs.clone(),
            ys: ys.iter().map(|y| 0.5 * y).collect(),
            color: 1,
            width: 3,
            dashed: true,
        },
        Layer::Scatter {
            name: Some("samples".into()),
            xs: xs.clone(),
            ys: ys.iter().map(|y| y + 0.1).collect(),
            color: 2,
            size: 4,
            shape: PointShape::Circle,
        },
        Layer::Scatter {
            name: Some("plus".into()),
            xs: vec![1.0, 2.0],
            ys: vec![0.0, 0.2],
            color: RED,
            size: 5,
            shape: PointShape::Plus,
        },
        Layer::Scatter {
            name: None,
            xs: vec![3.0],
            ys: vec![-0.2],
            color: 4,
            size: 5,
            shape: PointShape::Cross,
        },
        Layer::HLine {
            y: 0.8,
            color: BLACK,
            dashed: true,
            name: Some("limit".into()),
        },
        Layer::VLine {
            x: 3.0,
            color: GREY,
            dashed: false,
            name: Some("event".into()),
        },
        Layer::HBand {
            lo: -1.2,
            hi: -0.9,
            color: RED,
            name: Some("unsafe".into()),
        },
    ];
    let mut bars = Panel::new("error bars, log axes", "k", "time (s)");
    (bars.log_x, bars.log_y, bars.legend_pos) = (true, true, LegendPos::UpperLeft);
    let ks = vec![64.0, 128.0, 256.0, 512.0];
    bars.layers = vec![
        Layer::line("median", ks.clone(), vec![0.01, 0.05, 0.3, 2.0], 0),
        Layer::ErrorBars {
            name: Some("deciles".into()),
            xs: ks,
            mid: vec![0.01, 0.05, 0.3, 2.0],
            lo: vec![0.008, 0.04, 0.2, 1.5],
            hi: vec![0.02, 0.07, 0.4, 3.0],
            color: 0,
        },
    ];
    let mut heat = Panel::new("heat map + zero level", "x (m)", "y (m)");
    heat.layers = vec![grid_layer(true, true)];
    let mut seq = Panel::new("sequential heat map", "x (m)", "y (m)");
    seq.layers = vec![grid_layer(false, false)];
    let mut world = Panel::new("vehicle", "x (m)", "y (m)");
    world.equal_aspect = true;
    world.layers = vec![
        Layer::Circle {
            cx: -1.1667,
            cy: -1.5,
            r: 0.7906,
            color: RED,
            name: Some("obstacle".into()),
        },
        Layer::Circle {
            cx: -1.8333,
            cy: 0.5,
            r: 0.7906,
            color: RED,
            name: None,
        },
        Layer::line(
            "path",
            vec![-3.0, -2.0, -1.0, 0.0],
            vec![-1.0, -0.8, -0.3, 0.0],
            0,
        ),
        Layer::Marker {
            x: -2.0,
            y: -0.8,
            heading: Some(0.4),
            color: 0,
            size: 14,
        },
        Layer::Marker {
            x: 0.0,
            y: 0.0,
            heading: None,
            color: 2,
            size: 10,
        },
    ];
    let mut fixed = Panel::new("fixed ranges, clipped", "x (m)", "y (m)");
    fixed.x_range = Some((0.0, 1.0));
    fixed.y_range = Some((0.0, 1.0));
    fixed.layers = vec![
        Layer::line("long", vec![-5.0, 5.0], vec![-5.0, 5.0], 1),
        Layer::Circle {
            cx: 1.0,
            cy: 1.0,
            r: 0.5,
            color: 2,
            name: None,
        },
    ];
    Figure {
        width: 1200,
        height: 800,
        rows: 2,
        cols: 3,
        title: Some("every layer kind".into()),
        panels: vec![lines, bars, heat, seq, world, fixed],
    }
}

#[test]
fn renders_every_layer_kind() {
    let dir = scratch("all");
    let path = dir.join("all.png");
    render_png(&all_layers_figure(), &path).unwrap();
    assert_eq!(png_size(&path), (1200, 800));
    keep(&path);
    // nothing but the PNG is left in the directory
    assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn bad_data_does_not_panic() {
    let (nan, inf) = (f64::NAN, f64::INFINITY);
    let mut p = Panel::new("bad data", "x", "y");
    p.layers = vec![
        Layer::Line {
            name: Some("nan".into()),
            xs: vec![nan, 1.0, 2.0, inf, 4.0],
            ys: vec![0.0, nan, 2.0, 3.0, -inf],
            color: 0,
            width: 2,
            dashed: false,
        },
        Layer::Line {
            name: None,
            xs: vec![],
            ys: vec![],
            color: 1,
            width: 0,
            dashed: true,
        },
        Layer::Line {
            name: None,
            xs: vec![1.0, 2.0, 3.0],
            ys: vec![1.0],
            color: 1,
            width: 1,
            dashed: false,
        },
        Layer::Scatter {
            name: Some("empty".into()),
            xs: vec![],
            ys: vec![],
            color: 2,
            size: 0,
            shape: PointShape::Circle,
        },
        Layer::ErrorBars {
            name: None,
            xs: vec![1.0, 2.0],
            mid: vec![nan, 1.0],
            lo: vec![0.0, -inf],
            hi: vec![1.0, 2.0],
            color: 3,
        },
        Layer::Band {
            xs: vec![nan, 1.0],
            lo: vec![0.0, 0.0],
            hi: vec![1.0, inf],
            color: 4,
        },
        Layer::HLine {
            y: nan,
            color: 5,
            dashed: false,
            name: None,
        },
        Layer::VLine {
            x: inf,
            color: 5,
            dashed: true,
            name: None,
        },
        Layer::HBand {
            lo: nan,
            hi: 1.0,
            color: 6,
            name: None,
        },
        Layer::Heatmap {
            xs: vec![0.0, 1.0],
            ys: vec![0.0, 1.0],
            values: vec![nan, inf, 1.0],
            zero_contour: true,
            label: "bad".into(),
            diverging: true,
            range: Some((nan, 1.0)),
        },
        Layer::Circle {
            cx: 0.0,
            cy: 0.0,
            r: nan,
            color: 7,
            name: None,
        },
        Layer::Marker {
            x: nan,
            y: 0.0,
            heading: Some(inf),
            color: 8,
            size: 0,
        },
    ];
    let mut logp = Panel::new("log of non-positive data", "x", "y");
    (logp.log_x, logp.log_y) = (true, true);
    logp.x_range = Some((-1.0, 10.0));
    logp.layers = vec![Layer::line(
        "neg",
        vec![-1.0, 0.0, 1.0, 10.0],
        vec![-5.0, 0.0, 1.0, 100.0],
        0,
    )];
    let mut empty = Panel::new("empty", "x", "y");
    empty.log_y = true;
    let mut heat = Panel::new("all-NaN heat map", "x", "y");
    heat.layers = vec![Layer::Heatmap {
        xs: vec![0.0],
        ys: vec![0.0],
        values: vec![nan],
        zero_contour: true,
        label: "nothing".into(),
        diverging: false,
        range: None,
    }];
    let fig = Figure {
        width: 900,
        height: 600,
        rows: 2,
        cols: 2,
        title: None,
        panels: vec![p, logp, empty, heat],
    };
    let dir = scratch("bad");
    let path = dir.join("bad.png");
    render_png(&fig, &path).unwrap();
    assert_eq!(png_size(&path), (900, 600));
    keep(&path);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn invalid_figures_are_errors_and_leave_no_file() {
    let dir = scratch("invalid");
    let path = dir.join("x.png");
    let mut fig = Figure::single(400, 300, Panel::new("a", "x", "y"));
    fig.panels.push(Panel::new("b", "x", "y"));
    assert!(render_png(&fig, &path)
        .unwrap_err()
        .to_string()
        .contains("panels"));
    let tiny = Figure::single(2, 300, Panel::default());
    assert!(render_png(&tiny, &path).is_err());
    assert!(render_gif(&[], 100, &dir.join("x.gif")).is_err());
    let frames = [
        Figure::single(400, 300, Panel::default()),
        Figure::single(300, 300, Panel::default()),
    ];
    assert!(render_gif(&frames, 100, &dir.join("x.gif"))
        .unwrap_err()
        .to_string()
        .contains("frame 1"));
    let plain = Figure::single(400, 300, Panel::default());
    assert!(render_png(&plain, &dir.join("x.gif"))
        .unwrap_err()
        .to_string()
        .contains("must end in .png"));
    assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 0);
    render_png(&plain, &dir.join("upper.PNG")).unwrap();
    assert_eq!(png_size(&dir.join("upper.PNG")), (400, 300));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn renders_an_animated_gif() {
    let frames: Vec<Figure> = (0..3)
        .map(|i| {
            let mut p = Panel::new(&format!("frame {i}"), "x (m)", "y (m)");
            (p.x_range, p.y_range, p.equal_aspect) = (Some((-2.0, 2.0)), Some((-2.0, 2.0)), true);
            p.layers = vec![
                Layer::Circle {
                    cx: 0.0,
                    cy: 0.0,
                    r: 0.5,
                    color: RED,
                    name: Some("obstacle".into()),
                },
                Layer::Marker {
                    x: -1.5 + i as f64,
                    y: -1.0,
                    heading: Some(0.3 * i as f64),
                    color: 0,
                    size: 12,
                },
            ];
            Figure::single(320, 240, p)
        })
        .collect();
    let dir = scratch("gif");
    let path = dir.join("anim.gif");
    render_gif(&frames, 50, &path).unwrap();
    keep(&path);
    let (w, h, n) = gif_info(&path);
    assert_eq!((w, h), (320, 240));
    assert!(n >= 3, "{n} frames");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn zero_contour_of_a_plane_and_a_saddle() {
    let xs = [-1.0, 0.0, 1.0];
    let ys = [-1.0, 0.0, 1.0];
    // v = x + 0.5: zero line at x = -0.5
    let v: Vec<f64> = ys.iter().flat_map(|_| xs.iter().map(|x| x + 0.5)).collect();
    let segs = marching_squares_zero(&xs, &ys, &v);
    assert_eq!(segs.len(), 2);
    for ((x0, _), (x1, _)) in segs {
        assert!((x0 + 0.5).abs() < 1e-12 && (x1 + 0.5).abs() < 1e-12);
    }
    // one saddle cell: two segments; bad sizes and NaN give none
    let saddle = marching_squares_zero(&[0.0, 1.0], &[0.0, 1.0], &[1.0, -1.0, -1.0, 1.0]);
    assert_eq!(saddle.len(), 2);
    assert!(marching_squares_zero(&xs, &ys, &v[..5]).is_empty());
    assert!(
        marching_squares_zero(&[0.0, 1.0], &[0.0, 1.0], &[1.0, f64::NAN, -1.0, 1.0]).is_empty()
    );
}

#[test]
fn clipping_ticks_and_labels() {
    let ax = Axes {
        x: (0.0, 1.0),
        y: (0.0, 1.0),
        log_x: false,
        log_y: false,
    };
    let (a, b) = clip_segment(&ax, (-1.0, 0.5), (2.0, 0.5)).unwrap();
    assert_eq!((a, b), ((0.0, 0.5), (1.0, 0.5)));
    assert!(clip_segment(&ax, (2.0, 2.0), (3.0, 3.0)).is_none());
    assert!(clip_segment(&ax, (f64::NAN, 0.0), (0.5, 0.5)).is_none());
    let sq = clip_polygon(&ax, &[(-1.0, -1.0), (0.5, -1.0), (0.5, 0.5), (-1.0, 0.5)]);
    assert!(
        sq.iter()
            .all(|p| p.0 >= 0.0 && p.1 >= 0.0 && p.0 <= 0.5 && p.1 <= 0.5)
            && sq.len() >= 4
    );
    let logax = Axes {
        x: (1.0, 1000.0),
        y: (1.0, 10.0),
        log_x: true,
        log_y: true,
    };
    assert!(clip_segment(&logax, (-1.0, 2.0), (10.0, 2.0)).is_none());
    let decade: Vec<f64> = ticks(1.0, 1000.0, true)
        .iter()
        .map(|t| 10f64.powf(*t))
        .collect();
    let want = [1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0];
    assert!(
        decade.len() == want.len()
            && decade
                .iter()
                .zip(want)
                .all(|(a, b)| (a - b).abs() < 1e-9 * b)
    );
    assert!(ticks(250.0, 350.0, true).len() >= 3);
    assert_eq!(
        ticks(0.0, 1.0, false),
        vec![0.0, 0.2, 0.4, 0.6000000000000001, 0.8, 1.0]
    );
    assert_eq!(fmt_tick(0.25), "0.25");
    assert_eq!(fmt_tick(1024.0), "1024");
    assert_eq!(fmt_tick(1.23456), "1.23");
    assert_eq!(fmt_tick(2e-5), "2e-5");
    assert_eq!(fmt_tick(f64::NAN), "");
    assert_eq!(axis_range(None, &[], false), (0.0, 1.0));
    assert_eq!(
        axis_range(Some((1.0, f64::NAN)), &[2.0, 4.0], false),
        (1.9, 4.1)
    );
    let s = ColorScale::new(&[1.0, 1.0], None, false);
    assert!(s.hi > s.lo);
    let d = ColorScale::new(&[-1.0, 3.0], None, true);
    assert_eq!((d.lo, d.hi), (-3.0, 3.0));
}
