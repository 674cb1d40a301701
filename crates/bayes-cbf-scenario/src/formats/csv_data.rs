//! Reading training data from CSV files with a header row: either
//! `x1..xN,u1..uM,xdot1..xdotN` or, as a time series, `t,x1..xN,u1..uM`
//! (`ẋ` then estimated by finite differences, paper footnote 1).

use crate::error::{Context, Result};
use crate::{bail, err};
use bayes_cbf::sim::{finite_difference_xdot, Dataset};
use std::path::Path;

/// Column layout of a data file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Layout {
    /// `x1..xN,u1..uM,xdot1..xdotN`.
    Derivatives,
    /// `t,x1..xN,u1..uM`.
    TimeSeries,
}

/// Expected header names for state dimension `n` and control dimension `m`.
pub fn expected_header(layout: Layout, n: usize, m: usize) -> Result<Vec<String>> {
    let width = match layout {
        Layout::Derivatives => n.checked_mul(2).and_then(|v| v.checked_add(m)),
        Layout::TimeSeries => n.checked_add(m).and_then(|v| v.checked_add(1)),
    };
    match width {
        Some(w) if w <= 100_000 => {}
        _ => bail!("--state-dim {n} / --control-dim {m} are too large"),
    }
    let mut h = Vec::new();
    if layout == Layout::TimeSeries {
        h.push("t".to_string());
    }
    h.extend((1..=n).map(|i| format!("x{i}")));
    h.extend((1..=m).map(|i| format!("u{i}")));
    if layout == Layout::Derivatives {
        h.extend((1..=n).map(|i| format!("xdot{i}")));
    }
    Ok(h)
}

fn show_header(h: &[String]) -> String {
    if h.len() <= 24 {
        h.join(",")
    } else {
        format!("{},…,{}", h[..3].join(","), h[h.len() - 3..].join(","))
    }
}

/// Parses CSV text into rows of numbers after checking the header; `name`
/// labels errors. Blank lines are skipped; line numbers are 1-based.
pub fn parse_table(text: &str, name: &str, header: &[String]) -> Result<Vec<Vec<f64>>> {
    let text = crate::parse::strip_bom(text);
    if text.contains('\r') && !text.contains('\n') {
        bail!(
            "{name}: its lines end in a carriage return alone (CR, old Mac OS line endings); \
             convert them to LF or CRLF"
        );
    }
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty());
    let (_, first) = lines.next().ok_or_else(|| {
        err!(
            "{name} is empty: expected a header row {}",
            show_header(header)
        )
    })?;
    let got: Vec<String> = first
        .split(',')
        .map(|c| c.trim().trim_matches('"').trim().to_string())
        .collect();
    if got.len() != header.len() {
        bail!(
            "{name} line 1: header has {} columns but the dimensions given need {}: {}",
            got.len(),
            header.len(),
            show_header(header)
        );
    }
    if let Some(j) = (0..header.len()).find(|&j| !got[j].eq_ignore_ascii_case(&header[j])) {
        bail!(
            "{name} line 1: header column {} is \"{}\", expected \"{}\" (header must be {})",
            j + 1,
            got[j],
            header[j],
            show_header(header)
        );
    }
    let mut rows = Vec::new();
    for (i, line) in lines {
        let lineno = i + 1;
        let cells: Vec<&str> = line.split(',').collect();
        if cells.len() != header.len() {
            bail!(
                "{name} line {lineno}: expected {} columns, got {}",
                header.len(),
                cells.len()
            );
        }
        let mut row = Vec::with_capacity(cells.len());
        for (j, c) in cells.iter().enumerate() {
            let c = c.trim().trim_matches('"').trim();
            let v: f64 = c.parse().map_err(|_| {
                err!(
                    "{name} line {lineno}, column {}: \"{c}\" is not a number",
                    header[j]
                )
            })?;
            if !v.is_finite() {
                bail!(
                    "{name} line {lineno}, column {}: value {c} is not finite",
                    header[j]
                );
            }
            row.push(v);
        }
        rows.push(row);
    }
    if rows.is_empty() {
        bail!("{name} has a header but no data rows");
    }
    Ok(rows)
}

/// Reads a data file and returns the dataset. For [`Layout::TimeSeries`],
/// `ẋ` is estimated with [`finite_difference_xdot`], wrapping the
/// differences of the state components in `angle_indices`.
pub fn read_dataset(
    path: &Path,
    layout: Layout,
    n: usize,
    m: usize,
    angle_indices: &[usize],
) -> Result<Dataset> {
    let header = expected_header(layout, n, m)?;
    let name = path.display().to_string();
    let bytes =
        crate::io::read_input(path).with_context(|| format!("cannot read data file '{name}'"))?;
    let text =
        String::from_utf8(bytes).map_err(|e| err!("data file '{name}' is not UTF-8 text: {e}"))?;
    let rows = parse_table(&text, &name, &header)?;
    let mut ds = Dataset {
        n,
        m,
        ..Default::default()
    };
    match layout {
        Layout::Derivatives => {
            for r in &rows {
                ds.xs.extend_from_slice(&r[..n]);
                ds.us.extend_from_slice(&r[n..n + m]);
                ds.xdot.extend_from_slice(&r[n + m..]);
            }
        }
        Layout::TimeSeries => {
            let t: Vec<f64> = rows.iter().map(|r| r[0]).collect();
            for r in &rows {
                ds.xs.extend_from_slice(&r[1..1 + n]);
                ds.us.extend_from_slice(&r[1 + n..]);
            }
            ds.xdot = finite_difference_xdot(&t, &ds.xs, n, angle_indices)
                .map_err(|e| err!("{name} (time series, column t): {e}"))?;
        }
    }
    Ok(ds)
}

/// Formats rows of numbers as CSV with the given header.
pub fn to_csv(header: &[&str], rows: &[Vec<f64>]) -> String {
    let mut s = header.join(",");
    s.push('\n');
    for r in rows {
        let cells: Vec<String> = r.iter().map(|v| format!("{v}")).collect();
        s.push_str(&cells.join(","));
        s.push('\n');
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_and_rows() {
        let h = expected_header(Layout::Derivatives, 2, 1).unwrap();
        assert_eq!(h.join(","), "x1,x2,u1,xdot1,xdot2");
        let rows = parse_table(
            "x1,x2,u1,xdot1,xdot2\r\n1,2,3,4,5\n\n6,7,8,9,10\n",
            "d.csv",
            &h,
        )
        .unwrap();
        assert_eq!(
            rows,
            vec![
                vec![1.0, 2.0, 3.0, 4.0, 5.0],
                vec![6.0, 7.0, 8.0, 9.0, 10.0]
            ]
        );
        for (text, message) in [
            // CR alone ends no line for `lines`: said so, not a header of 13 columns
            (
                "x1,x2,u1,xdot1,xdot2\r1,2,3,4,5\r",
                "d.csv: its lines end in a carriage return alone",
            ),
            (
                "x1,x2,u1,xdot1,xdot2\n1,2,3,4\n",
                "line 2: expected 5 columns, got 4",
            ),
            (
                "x1,x2,u1,xdot1,xdot2\n1,2,3,nan,5\n",
                "column xdot1: value nan is not finite",
            ),
            (
                "x1,x2,u,xdot1,xdot2\n",
                "column 3 is \"u\", expected \"u1\"",
            ),
        ] {
            let e = parse_table(text, "d.csv", &h).unwrap_err().to_string();
            assert!(e.contains(message), "{e}");
        }
        assert!(parse_table("", "d.csv", &h)
            .unwrap_err()
            .to_string()
            .contains("empty"));
        assert!(parse_table("x1,x2,u1,xdot1,xdot2\n", "d.csv", &h).is_err());
        let ts = expected_header(Layout::TimeSeries, 3, 2).unwrap();
        assert_eq!(ts.join(","), "t,x1,x2,x3,u1,u2");
        assert!(expected_header(Layout::Derivatives, usize::MAX, 1).is_err());
    }
}
