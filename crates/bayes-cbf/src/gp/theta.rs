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

/// Data-driven start of the log hyperparameters `kh`: the first `d` (the
/// lengthscales of the RBF layout) are the logs of the standard deviations
/// of the kernel inputs `zs` (`k × d`, row-major; at least `10⁻³`), and
/// the output scale at `scale_idx` is 1.
pub(crate) fn start_from_inputs(
    kh: &mut [f64],
    zs: &[f64],
    k: usize,
    d: usize,
    scale_idx: Option<usize>,
) {
    for j in 0..d.min(kh.len()) {
        let mean = (0..k).map(|i| zs[i * d + j]).sum::<f64>() / k as f64;
        let var = (0..k).map(|i| (zs[i * d + j] - mean).powi(2)).sum::<f64>() / k as f64;
        kh[j] = var.sqrt().max(1e-3).ln();
    }
    if let Some(si) = scale_idx {
        kh[si] = 0.0;
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
