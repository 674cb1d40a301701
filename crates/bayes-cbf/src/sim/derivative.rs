use crate::error::InputError;
use crate::systems::wrap_angle;

/// Estimates `ẋ` at each sample of a time series by finite differences
/// (paper, footnote 1): central differences inside, one-sided at the ends.
///
/// Differences of the components listed in `angle_indices` are wrapped to
/// `[-π, π)` first, so a trajectory crossing `±π` does not produce a `2π/Δt`
/// spike. `xs` is `k × n` row-major; times must be strictly increasing.
pub fn finite_difference_xdot(
    t: &[f64],
    xs: &[f64],
    n: usize,
    angle_indices: &[usize],
) -> Result<Vec<f64>, InputError> {
    let k = t.len();
    if n == 0 || xs.len() != k * n {
        return Err(InputError::Shape {
            field: "x".into(),
            expected: format!("{k} rows of {n}"),
            got: xs.len().to_string(),
        });
    }
    if k < 2 {
        return Err(InputError::invalid_shown(
            "t",
            format!("{k} sample(s)"),
            "a time series needs at least 2 samples",
        ));
    }
    for i in 1..k {
        if t[i].partial_cmp(&t[i - 1]) != Some(std::cmp::Ordering::Greater) {
            return Err(InputError::invalid(
                &format!("t[{i}]"),
                t[i],
                "times must be strictly increasing",
            ));
        }
    }
    let diff = |a: usize, b: usize, j: usize| -> f64 {
        let d = xs[b * n + j] - xs[a * n + j];
        if angle_indices.contains(&j) {
            wrap_angle(d)
        } else {
            d
        }
    };
    let mut out = vec![0.0; k * n];
    for i in 0..k {
        for j in 0..n {
            out[i * n + j] = if i == 0 {
                diff(0, 1, j) / (t[1] - t[0])
            } else if i == k - 1 {
                diff(k - 2, k - 1, j) / (t[k - 1] - t[k - 2])
            } else {
                // second-order accurate on non-uniform grids
                let (h1, h2) = (t[i] - t[i - 1], t[i + 1] - t[i]);
                let (d1, d2) = (diff(i - 1, i, j) / h1, diff(i, i + 1, j) / h2);
                (h2 * d1 + h1 * d2) / (h1 + h2)
            };
        }
    }
    // a quotient beyond what the model takes, of states within it, comes
    // from samples too close in time for the change of the state: named by
    // its times (a state beyond it is the data check's to name)
    let limit = crate::gp::MAX_DATA_MAGNITUDE;
    let states_in_range = xs.iter().all(|v| v.abs() <= limit);
    let beyond = out.iter().position(|v| v.is_nan() || v.abs() > limit);
    if let (Some(p), true) = (beyond, states_in_range) {
        let (i, j) = (p / n, p % n);
        let (a, b) = (i.saturating_sub(1), (i + 1).min(k - 1));
        return Err(InputError::invalid_shown(
            &format!("t[{a}..={b}]"),
            format!("{:e} to {:e}", t[a], t[b]),
            &format!(
                "the difference quotient of x[{j}] at sample {i} is {:e}, beyond the \
                 {limit:e} the model takes: samples too close in time for the change of \
                 the state (check the units of t)",
                out[p]
            ),
        ));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn derivative_across_wrap() {
        // θ(t) = π - 0.5 + t, crosses π at t = 0.5, ω = 1
        let t: Vec<f64> = (0..100).map(|i| i as f64 * 0.01).collect();
        let xs: Vec<f64> = t
            .iter()
            .flat_map(|&ti| [wrap_angle(std::f64::consts::PI - 0.5 + ti), ti * ti])
            .collect();
        let d = finite_difference_xdot(&t, &xs, 2, &[0]).unwrap();
        for i in 0..100 {
            assert!((d[2 * i] - 1.0).abs() < 1e-9, "i={i} d={}", d[2 * i]);
            let exact = 2.0 * t[i];
            let tol = if i == 0 || i == 99 { 0.011 } else { 1e-9 };
            assert!((d[2 * i + 1] - exact).abs() < tol);
        }
    }

    #[test]
    fn a_quotient_beyond_the_data_limit_names_the_times() {
        let e = finite_difference_xdot(&[0.0, 5e-302, 1e-301], &[0.2, -0.9, 0.6], 1, &[])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("t[0..=1]") && e.contains("difference quotient of x[0] at sample 0"),
            "{e}"
        );
        // a state beyond the limit is not blamed on the times
        assert!(finite_difference_xdot(&[0.0, 1.0], &[0.0, 1e200], 1, &[]).is_ok());
    }

    #[test]
    fn rejects_non_increasing_time() {
        assert!(finite_difference_xdot(&[0.0, 0.0], &[1.0, 2.0], 1, &[]).is_err());
    }
}
