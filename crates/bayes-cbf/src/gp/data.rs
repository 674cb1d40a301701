//! Training data `(x_j, u_j, ẋ_j)` of a GP model of `F(x)`, stored row-major
//! with the derived rows every model needs: mapped inputs `z_j = φ(x_j)`,
//! augmented controls `u̲_j = [1, u_j]` and residuals `ẋ_j − M0(x_j) u̲_j`.
//! Shared by the MVGP and the CoGP.

use super::input_map::InputMap;
use crate::error::{check_finite, check_len, InputError};

/// Stored observations of a model with state dim `n`, control dim `m` and
/// mapped-input dim `d` (`p = 1 + m`).
#[derive(Debug, Clone, Default)]
pub(crate) struct TrainingData {
    /// Inputs `x_j`, row-major `k × n`.
    pub xs: Vec<f64>,
    /// Mapped inputs `z_j = φ(x_j)`, row-major `k × d`.
    pub zs: Vec<f64>,
    /// `u̲_j = [1, u_j]`, row-major `k × (1+m)`.
    pub us: Vec<f64>,
    /// `ẋ_j`, row-major `k × n`.
    pub xdot: Vec<f64>,
    /// Residuals `r_j = ẋ_j − M0(x_j) u̲_j`, row-major `k × n`; the model
    /// computes them (see [`push`](Self::push)).
    pub resid: Vec<f64>,
}

/// Checks a batch `xs` (`k × n`), `us` (`k × m`), `xdot` (`k × n`), all
/// row-major: shapes, then finiteness row by row (errors name the row).
/// Returns `k`.
pub(crate) fn check_batch(
    n: usize,
    m: usize,
    xs: &[f64],
    us: &[f64],
    xdot: &[f64],
) -> Result<usize, InputError> {
    let k = xs.len() / n;
    if xs.len() != k * n || us.len() != k * m || xdot.len() != k * n {
        return Err(InputError::shape(
            "data",
            format!("x: k×{n}, u: k×{m}, xdot: k×{n}"),
            format!("{} x, {} u, {} xdot values", xs.len(), us.len(), xdot.len()),
        ));
    }
    for j in 0..k {
        check_point(
            n,
            m,
            &xs[j * n..(j + 1) * n],
            &us[j * m..(j + 1) * m],
            &xdot[j * n..(j + 1) * n],
            j,
        )?;
    }
    Ok(k)
}

/// Checks one observation `(x, u, ẋ)`, numbered `j` in the errors.
pub(crate) fn check_point(
    n: usize,
    m: usize,
    x: &[f64],
    u: &[f64],
    xdot: &[f64],
    j: usize,
) -> Result<(), InputError> {
    if x.len() != n {
        return Err(InputError::shape(&format!("x[{j}]"), n, x.len()));
    }
    if u.len() != m {
        return Err(InputError::shape(&format!("u[{j}]"), m, u.len()));
    }
    if xdot.len() != n {
        return Err(InputError::shape(&format!("xdot[{j}]"), n, xdot.len()));
    }
    check_values("x", j, x)?;
    check_values("u", j, u)?;
    check_values("xdot", j, xdot)
}

/// Largest magnitude of an observed value: squares of the values (kernel
/// distances, the Gram matrix's `u̲ᵀ B u̲`, the likelihood's residuals)
/// appear throughout the regression and must stay finite.
pub const MAX_DATA_MAGNITUDE: f64 = 1e150;

/// Checks that every entry of `v` is finite and at most
/// [`MAX_DATA_MAGNITUDE`] in magnitude, naming `name[j][i]`; nothing is
/// allocated unless an entry is bad.
fn check_values(name: &str, j: usize, v: &[f64]) -> Result<(), InputError> {
    match v
        .iter()
        .position(|a| a.is_nan() || a.abs() > MAX_DATA_MAGNITUDE)
    {
        None => Ok(()),
        Some(i) => Err(InputError::invalid(
            &format!("{name}[{j}][{i}]"),
            v[i],
            if v[i].is_finite() {
                "too large: observed values must be at most 1e150 in magnitude, \
                 whose squares are finite (rescale the data)"
            } else {
                "must be finite"
            },
        )),
    }
}

/// Checks a query state `x` of dimension `n`, named `field` in the errors.
pub(crate) fn check_state(field: &str, n: usize, x: &[f64]) -> Result<(), InputError> {
    check_len(field, n, x.len())?;
    check_finite(field, x)
}

impl TrainingData {
    /// Appends `x`, `z = φ(x)`, `u̲ = [1, u]` and `ẋ` (not the residual,
    /// which the model appends to `resid`).
    pub fn push(&mut self, x: &[f64], u: &[f64], xdot: &[f64], input_map: &InputMap) {
        let d = input_map.output_dim(x.len());
        self.xs.extend_from_slice(x);
        let zoff = self.zs.len();
        self.zs.resize(zoff + d, 0.0);
        input_map.apply(x, &mut self.zs[zoff..]);
        self.us.push(1.0);
        self.us.extend_from_slice(u);
        self.xdot.extend_from_slice(xdot);
    }

    /// Drops the last observation (`n`, `p = 1 + m`, `d` as above).
    pub fn pop(&mut self, n: usize, p: usize, d: usize) {
        self.xs.truncate(self.xs.len() - n);
        self.zs.truncate(self.zs.len() - d);
        self.us.truncate(self.us.len() - p);
        self.xdot.truncate(self.xdot.len() - n);
        self.resid.truncate(self.resid.len() - n);
    }

    /// Drops observation `j` (`n`, `p = 1 + m`, `d` as above).
    pub fn remove(&mut self, j: usize, n: usize, p: usize, d: usize) {
        self.xs.drain(j * n..(j + 1) * n);
        self.zs.drain(j * d..(j + 1) * d);
        self.us.drain(j * p..(j + 1) * p);
        self.xdot.drain(j * n..(j + 1) * n);
        self.resid.drain(j * n..(j + 1) * n);
    }

    /// Drops every observation, keeping the buffers.
    pub fn clear(&mut self) {
        self.xs.clear();
        self.zs.clear();
        self.us.clear();
        self.xdot.clear();
        self.resid.clear();
    }
}
