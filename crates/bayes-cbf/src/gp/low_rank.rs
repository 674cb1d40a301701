//! Covariance matrices parameterised as `C Cᵀ + diag(exp(logv))` (full, low
//! rank or diagonal), shared by the MVGP and CoGP fits.

use nalgebra::DMatrix;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

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

/// Starting `C`, `log v` for `M ≈ C Cᵀ + diag(v)`, `C` row-major `dim × r`.
/// With `exact` and full rank (warm starts): `v = ½ λ_min(M)`,
/// `C = chol(M − diag(v))`. Otherwise `C` small random (`0.1 √M_ii` times a
/// standard normal, drawn row by row) and `v` the rest of the diagonal
/// (floored): the scale then sits in `log v`, where the optimiser can shrink
/// it to zero, rather than in `C`, whose gradient vanishes as `C → 0`.
pub(crate) fn init_low_rank(
    m: &DMatrix<f64>,
    r: usize,
    exact: bool,
    rng: &mut ChaCha8Rng,
    c: &mut [f64],
    logv: &mut [f64],
) {
    let dim = m.nrows();
    if exact && r == dim {
        let lmin = m.clone().symmetric_eigenvalues().min();
        if lmin > 0.0 {
            let v = 0.5 * lmin;
            let shifted = m - DMatrix::identity(dim, dim) * v;
            if let Some(ch) = shifted.cholesky() {
                let lo = ch.l();
                for i in 0..dim {
                    for q in 0..dim {
                        c[i * r + q] = lo[(i, q)];
                    }
                    logv[i] = v.ln();
                }
                return;
            }
        }
    }
    for i in 0..dim {
        let scale = 0.1 * m[(i, i)].abs().sqrt();
        for q in 0..r {
            let z: f64 = StandardNormal.sample(rng);
            c[i * r + q] = scale * z;
        }
        let cc: f64 = (0..r).map(|q| c[i * r + q].powi(2)).sum();
        logv[i] = (m[(i, i)] - cc).max(1e-3 * m[(i, i)].abs()).max(1e-12).ln();
    }
}
