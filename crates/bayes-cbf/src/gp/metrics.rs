//! Accuracy of a learned model of `F(x)` on held-out points against the true
//! system: the variance-weighted error of the paper (Sec. VII-A, Eq. 33) and
//! plain root-mean-square errors.
//!
//! All functions take any [`DynamicsModel`] (MVGP or CoGP), so both are
//! scored identically; score models *after* fitting them.

use super::factor::JITTER_LEVELS;
use super::model::DynamicsModel;
use crate::error::{check_finite, Error, GpError, InputError};
use crate::systems::DynSystem;
use nalgebra::{DMatrix, DVector};

/// All held-out errors of [`held_out_errors`] from one pass over the points.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeldOutErrors {
    /// Variance-weighted error, Eq. 33 (see [`variance_weighted_error`]).
    pub variance_weighted: f64,
    /// RMSE of the entries of `M_k(x)` (see [`rmse_f`]).
    pub rmse_f: f64,
    /// RMSE of the entries of `M_k(x) u̲` (see [`rmse_fu`]).
    pub rmse_fu: f64,
    /// `‖M_k u̲ − F u̲‖ / ‖F u̲‖` over all points (see [`relative_rmse_fu`]).
    pub relative_rmse_fu: f64,
    /// Number of held-out points `|𝒯|`.
    pub points: usize,
}

/// `‖L⁻¹ e‖² = eᵀ K⁻¹ e` for an SPD `K = L Lᵀ`, which equals
/// `‖K^{-1/2} e‖²` for the symmetric square root. If `K` is numerically
/// singular, jitter `level × mean(diag K)` escalates through
/// [`JITTER_LEVELS`] (logged); beyond that a [`GpError::IllConditioned`].
#[track_caller]
pub fn mahalanobis_sq(cov: &DMatrix<f64>, e: &[f64]) -> Result<f64, GpError> {
    let dim = cov.nrows();
    assert_eq!(cov.ncols(), dim, "covariance must be square");
    assert_eq!(e.len(), dim, "error vector length");
    let mean_diag = (cov.trace() / dim.max(1) as f64)
        .abs()
        .max(f64::MIN_POSITIVE);
    for &level in JITTER_LEVELS.iter() {
        let jit = level * mean_diag;
        let mut c = cov.clone();
        for i in 0..dim {
            c[(i, i)] += jit;
        }
        if let Some(ch) = c.cholesky() {
            if level > 0.0 {
                log::warn!(
                    "posterior covariance needed jitter {jit:.3e} in the variance-weighted error"
                );
            }
            let mut v = DVector::from_column_slice(e);
            ch.l_dirty().solve_lower_triangular_mut(&mut v);
            return Ok(v.norm_squared());
        }
    }
    Err(GpError::IllConditioned {
        size: dim,
        max_jitter: *JITTER_LEVELS.last().unwrap_or(&0.0),
    })
}

/// Checks the held-out inputs against the model and the truth and returns
/// the number of points `|𝒯|`.
fn check_inputs(
    model: &dyn DynamicsModel,
    xs: &[f64],
    us: Option<&[f64]>,
    truth: &dyn DynSystem,
) -> Result<usize, InputError> {
    let (n, m) = (model.state_dim(), model.control_dim());
    if (truth.state_dim(), truth.control_dim()) != (n, m) {
        return Err(InputError::shape(
            "truth",
            format!("system with n = {n}, m = {m}"),
            format!("n = {}, m = {}", truth.state_dim(), truth.control_dim()),
        ));
    }
    let t = check_rows("xs", xs, n, None)?;
    if let Some(us) = us {
        check_rows("us", us, m, Some(t))?;
    }
    Ok(t)
}

/// Checks that `values` holds `rows` rows (with `None`, at least one) of
/// `width` finite values, and returns the number of rows.
fn check_rows(
    field: &str,
    values: &[f64],
    width: usize,
    rows: Option<usize>,
) -> Result<usize, InputError> {
    let t = rows.unwrap_or(values.len() / width.max(1));
    if t == 0 || values.len() != t * width {
        let expected = match rows {
            Some(t) => format!("{t} × {width} values"),
            None => format!("|T| × {width} values with |T| ≥ 1"),
        };
        return Err(InputError::shape(
            field,
            expected,
            format!("{} values", values.len()),
        ));
    }
    for j in 0..t {
        check_finite(
            &format!("{field}[{j}]"),
            &values[j * width..(j + 1) * width],
        )?;
    }
    Ok(t)
}

/// Sums over the held-out points: (Σ e ᵀK⁻¹e, Σ‖vec(M−F)‖², Σ‖(M−F)u̲‖², Σ‖Fu̲‖²).
fn sums(
    model: &dyn DynamicsModel,
    xs: &[f64],
    us: Option<&[f64]>,
    truth: &dyn DynSystem,
    weighted: bool,
) -> Result<(usize, [f64; 4]), Error> {
    let t = check_inputs(model, xs, us, truth)?;
    let (n, m) = (model.state_dim(), model.control_dim());
    let np = n * (m + 1);
    let mut f = vec![0.0; np];
    let mut e = vec![0.0; np];
    let mut acc = [0.0; 4];
    for j in 0..t {
        let x = &xs[j * n..(j + 1) * n];
        truth.eval_f64(x, &mut f);
        let mean = if weighted {
            let (mean, cov) = model.posterior_vec(x)?;
            for a in 0..np {
                e[a] = mean[a] - f[a];
            }
            acc[0] += mahalanobis_sq(&cov, &e)?;
            mean
        } else {
            model.posterior_mean(x)?
        };
        for a in 0..np {
            e[a] = mean[a] - f[a];
            acc[1] += e[a] * e[a];
        }
        if let Some(us) = us {
            let u = &us[j * m..(j + 1) * m];
            for i in 0..n {
                let (mut eu, mut fu) = (e[i], f[i]);
                for c in 0..m {
                    eu += e[i + n * (c + 1)] * u[c];
                    fu += f[i + n * (c + 1)] * u[c];
                }
                acc[2] += eu * eu;
                acc[3] += fu * fu;
            }
        }
    }
    Ok((t, acc))
}

/// Variance-weighted error of the posterior mean of `F(x)` on the held-out
/// states `xs` (row-major `|𝒯| × n`), paper Sec. VII-A, Eq. 33:
///
/// `err(𝒯) = √( Σ_{x ∈ 𝒯} ‖K_k^{-1/2}(x, x) vec(M_k(x) − F(x))‖² / |𝒯| )`,
///
/// where `M_k(x)` and `K_k(x, x) = Cov(vec F(x))` are the model's posterior
/// and `F(x)` the true system's. The squared norm is the Mahalanobis distance
/// `eᵀ K_k⁻¹ e`, computed with a Cholesky factor (see [`mahalanobis_sq`]).
/// For a calibrated model `E[err²] = n(1+m)`.
pub fn variance_weighted_error(
    model: &dyn DynamicsModel,
    xs: &[f64],
    truth: &dyn DynSystem,
) -> Result<f64, Error> {
    let (t, acc) = sums(model, xs, None, truth, true)?;
    Ok((acc[0] / t as f64).sqrt())
}

/// RMSE of the entries of the posterior mean of `F(x)`:
/// `√( Σ_{x ∈ 𝒯} ‖vec(M_k(x) − F(x))‖² / (|𝒯| n(1+m)) )`.
pub fn rmse_f(model: &dyn DynamicsModel, xs: &[f64], truth: &dyn DynSystem) -> Result<f64, Error> {
    let (t, acc) = sums(model, xs, None, truth, false)?;
    Ok((acc[1] / (t * model.state_dim() * (model.control_dim() + 1)) as f64).sqrt())
}

/// RMSE of the predicted state derivative, entrywise:
/// `√( Σ_j ‖M_k(x_j) u̲_j − F(x_j) u̲_j‖² / (|𝒯| n) )`, `u̲_j = [1; u_j]`,
/// with held-out controls `us` (row-major `|𝒯| × m`).
pub fn rmse_fu(
    model: &dyn DynamicsModel,
    xs: &[f64],
    us: &[f64],
    truth: &dyn DynSystem,
) -> Result<f64, Error> {
    let (t, acc) = sums(model, xs, Some(us), truth, false)?;
    Ok((acc[2] / (t * model.state_dim()) as f64).sqrt())
}

/// Relative error of the predicted state derivative:
/// `√( Σ_j ‖(M_k(x_j) − F(x_j)) u̲_j‖² / Σ_j ‖F(x_j) u̲_j‖² )`.
/// Infinite if every `F(x_j) u̲_j` is zero and the error is not.
pub fn relative_rmse_fu(
    model: &dyn DynamicsModel,
    xs: &[f64],
    us: &[f64],
    truth: &dyn DynSystem,
) -> Result<f64, Error> {
    let (_, acc) = sums(model, xs, Some(us), truth, false)?;
    Ok(ratio(acc[2], acc[3]))
}

fn ratio(num: f64, den: f64) -> f64 {
    if num == 0.0 {
        0.0
    } else {
        (num / den).sqrt()
    }
}

/// All of [`variance_weighted_error`], [`rmse_f`], [`rmse_fu`] and
/// [`relative_rmse_fu`] from one posterior evaluation per point.
///
/// ## Example
/// ```
/// use bayes_cbf::gp::{held_out_errors, InputMap, Mvgp, MvgpHyper, PriorMean, Rbf};
/// use bayes_cbf::systems::Pendulum;
/// use nalgebra::DMatrix;
/// let hyper = MvgpHyper {
///     kernel: Rbf::new(vec![1.0, 1.0], 1.0)?,
///     A: DMatrix::identity(2, 2),
///     B: DMatrix::identity(2, 2),
///     sigma: 0.1,
/// };
/// let model = Mvgp::new(2, 1, hyper, PriorMean::Zero, InputMap::Identity)?;
/// // held-out states (|T| × n) and controls (|T| × m)
/// let errs = held_out_errors(&model, &[0.5, 1.0, -1.0, 2.0], &[0.3, -0.2], &Pendulum::default())?;
/// assert_eq!(errs.points, 2);
/// assert!(errs.variance_weighted > 0.0);
/// # Ok::<(), bayes_cbf::Error>(())
/// ```
pub fn held_out_errors(
    model: &dyn DynamicsModel,
    xs: &[f64],
    us: &[f64],
    truth: &dyn DynSystem,
) -> Result<HeldOutErrors, Error> {
    let (t, acc) = sums(model, xs, Some(us), truth, true)?;
    let (n, np) = (
        model.state_dim(),
        model.state_dim() * (model.control_dim() + 1),
    );
    Ok(HeldOutErrors {
        variance_weighted: (acc[0] / t as f64).sqrt(),
        rmse_f: (acc[1] / (t * np) as f64).sqrt(),
        rmse_fu: (acc[2] / (t * n) as f64).sqrt(),
        relative_rmse_fu: ratio(acc[2], acc[3]),
        points: t,
    })
}
