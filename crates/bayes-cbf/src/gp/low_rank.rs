//! Covariance matrices parameterised as `C Cᵀ + diag(exp(logv))` (full, low
//! rank or diagonal), shared by the MVGP and CoGP fits.

use nalgebra::DMatrix;

/// `C Cᵀ + diag(exp(logv))` with `C` row-major `dim × r`.
pub(crate) fn low_rank_plus_diag(c: &[f64], logv: &[f64], dim: usize, r: usize) -> DMatrix<f64> {
    DMatrix::from_fn(dim, dim, |i, j| {
        let s: f64 = (0..r).map(|q| c[i * r + q] * c[j * r + q]).sum();
        if i == j {
            s + logv[i].exp()
        } else {
            s
        }
    })
}

/// Chain rule through `M = C Cᵀ + diag(exp(logv))` for symmetric `M̄`:
/// writes `[vec C̄ (row-major), M̄_ii v_i]` into `out`, `C̄ = 2 M̄ C`.
pub(crate) fn chain_low_rank(
    mbar: &DMatrix<f64>,
    c: &[f64],
    logv: &[f64],
    r: usize,
    out: &mut [f64],
) {
    let dim = mbar.nrows();
    for i in 0..dim {
        for q in 0..r {
            out[i * r + q] = 2.0 * (0..dim).map(|j| mbar[(i, j)] * c[j * r + q]).sum::<f64>();
        }
        out[dim * r + i] = mbar[(i, i)] * logv[i].exp();
    }
}
