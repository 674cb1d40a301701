//! Pieces of the parameter vector `θ` shared by the MVGP fit
//! ([`fit`](super::fit)) and the CoGP fit ([`fit_cogp`](super::fit_cogp)):
//! both put the kernel's free log hyperparameters first, that is every one
//! but the output scale (held fixed, see the fits' module docs), and both
//! start the lengthscales from the spread of the kernel inputs.

use super::kernel::Kernel;
use crate::error::InputError;

/// Copies the log hyperparameters `all` (in `Kernel::log_hyper` order)
/// without the one at `scale_idx` into `free`, in order.
pub(crate) fn pack_free(all: &[f64], scale_idx: Option<usize>, free: &mut [f64]) {
    let mut t = 0;
    for (i, a) in all.iter().enumerate() {
        if Some(i) != scale_idx {
            free[t] = *a;
            t += 1;
        }
    }
}

/// `kernel` with its free log hyperparameters read from the start of `th`
/// (the inverse of [`pack_free`]); the one at `scale_idx` keeps its value.
pub(crate) fn kernel_from_free<K: Kernel>(
    kernel: &K,
    th: &[f64],
    scale_idx: Option<usize>,
) -> Result<K, InputError> {
    let mut kern = kernel.clone();
    let mut kh = kern.log_hyper();
    let mut t = 0;
    for (i, h) in kh.iter_mut().enumerate() {
        if Some(i) != scale_idx {
            *h = th[t];
            t += 1;
        }
    }
    kern.set_log_hyper(&kh)?;
    Ok(kern)
}

/// Standard deviations of the kernel inputs `zs` (`k × d`, row-major), each
/// at least `10⁻³`: the scale of each lengthscale.
pub(crate) fn input_spreads(zs: &[f64], k: usize, d: usize) -> Vec<f64> {
    (0..d)
        .map(|j| {
            let mean = (0..k).map(|i| zs[i * d + j]).sum::<f64>() / k as f64;
            let var = (0..k).map(|i| (zs[i * d + j] - mean).powi(2)).sum::<f64>() / k as f64;
            var.sqrt().max(1e-3)
        })
        .collect()
}

/// Data-driven start of the log hyperparameters `kh`: the first `d` (the
/// lengthscales of the RBF layout) are the logs of the
/// [`input_spreads`], and the output scale at `scale_idx` is 1.
pub(crate) fn start_from_inputs(
    kh: &mut [f64],
    zs: &[f64],
    k: usize,
    d: usize,
    scale_idx: Option<usize>,
) {
    for (h, s) in kh.iter_mut().zip(input_spreads(zs, k, d)) {
        *h = s.ln();
    }
    if let Some(si) = scale_idx {
        kh[si] = 0.0;
    }
}

/// Bounds of a log-scale parameter with no scale of its own (log-diagonal
/// entries of covariance factors, kernel hyperparameters other than the
/// lengthscales): `|θ| ≤ 50`.
pub(crate) const LOG_BOUND: f64 = 50.0;

/// How far a lengthscale may go from the spread of its input, either way:
/// `ℓ_i ∈ [s_i/10³, 10³ s_i]`. Beyond the upper end the kernel is constant
/// along input `i` to within `5·10⁻⁷` over one spread; below the lower end
/// it is white noise.
pub(crate) const LENGTHSCALE_RANGE: f64 = 1e3;

/// Bounds `[lo, hi]` of the kernel's free log hyperparameters (in the order
/// of [`pack_free`]): lengthscales within [`LENGTHSCALE_RANGE`] of their
/// input's spread, any other hyperparameter within [`LOG_BOUND`].
pub(crate) fn kernel_bounds(
    n_hyper: usize,
    scale_idx: Option<usize>,
    spreads: &[f64],
    lo: &mut [f64],
    hi: &mut [f64],
) {
    let mut t = 0;
    for i in 0..n_hyper {
        if Some(i) == scale_idx {
            continue;
        }
        (lo[t], hi[t]) = match spreads.get(i) {
            Some(s) => ((s / LENGTHSCALE_RANGE).ln(), (s * LENGTHSCALE_RANGE).ln()),
            None => (-LOG_BOUND, LOG_BOUND),
        };
        t += 1;
    }
}

/// Random training rows for gradient tests: mapped inputs `zs` (`k × n`,
/// uniform on `[−1, 1)`), augmented controls `[1, u_j]` (`k × (1+m)`) and
/// residuals (`k × n`), drawn in that order.
#[cfg(test)]
pub(crate) fn random_training_rows(
    rng: &mut rand_chacha::ChaCha8Rng,
    k: usize,
    n: usize,
    m: usize,
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    use rand::RngExt;
    let zs: Vec<f64> = (0..k * n).map(|_| rng.random_range(-1.0..1.0)).collect();
    let us: Vec<f64> = (0..k)
        .flat_map(|_| {
            let mut v = vec![1.0];
            v.extend((0..m).map(|_| rng.random_range(-1.0..1.0)));
            v
        })
        .collect();
    let resid: Vec<f64> = (0..k * n).map(|_| rng.random_range(-1.0..1.0)).collect();
    (zs, us, resid)
}
