//! Hyperparameter learning for the CoGP by maximising the exact marginal
//! likelihood with an analytic gradient (L-BFGS, argmin), mirroring
//! [`fit`](super::fit) for the MVGP.
//!
//! The likelihood and its gradient are [`Cogp::log_marginal_likelihood_gradient`].
//!
//! ## Parameterisation
//! `Σ = C_Σ C_Σᵀ + diag(v_Σ)`, `S = C_S C_Sᵀ + diag(v_S)` with ranks from
//! [`Rank`]. The kernel's output scale is held fixed (it is redundant with
//! `Σ`); there is no other redundancy, since `S` is the only noise term.
//! `θ = [log ℓ (kernel, without scale), vec C_Σ, log v_Σ, vec C_S, log v_S]`.

use super::cogp::{lml_grad, Cogp, CogpData, CogpHyper};
use super::kernel::Kernel;
use super::low_rank::{chain_low_rank, init_low_rank, low_rank_plus_diag};
use super::optimise::{
    multi_start, perturb, prefit, EvalFailure, Evaluation, Harness, Objective, RunSettings,
    StartPlan,
};
use super::theta::{kernel_from_free, pack_free, start_from_inputs};
use super::training::{FitReport, Rank};
use crate::error::{Error, GpError, InputError};
use nalgebra::DMatrix;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Settings of [`fit_cogp`], validated by [`CogpFitSettings::validate`].
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct CogpFitSettings {
    /// Structure of `Σ` (`Rank::Diagonal` is the paper's "diag" CoGP).
    pub rank_sigma: Rank,
    /// Structure of the noise covariance `S`.
    pub rank_s: Rank,
    /// L-BFGS iterations per start.
    pub max_iters: u64,
    /// Extra random restarts besides the data-driven start.
    pub restarts: usize,
    /// Seed of the random initialisation of the factors and of the restarts.
    pub seed: u64,
    /// Initialise from the model's current hyperparameters instead of the
    /// data-driven heuristic.
    pub warm_start: bool,
    /// For full or low-rank `Σ`/`S` without warm start: fit the diagonal
    /// model first and start from its optimum (see [`fit_cogp`]).
    pub prefit_diagonal: bool,
}

impl Default for CogpFitSettings {
    fn default() -> Self {
        Self {
            rank_sigma: Rank::Full,
            rank_s: Rank::Full,
            max_iters: 100,
            restarts: 0,
            seed: 0,
            warm_start: false,
            prefit_diagonal: true,
        }
    }
}

impl CogpFitSettings {
    /// Checks the settings.
    pub fn validate(&self) -> Result<(), InputError> {
        if self.max_iters == 0 {
            return Err(InputError::invalid("max_iters", 0.0, "must be ≥ 1"));
        }
        if self.restarts > 1000 {
            return Err(InputError::invalid(
                "restarts",
                self.restarts as f64,
                "must be ≤ 1000",
            ));
        }
        Ok(())
    }
}

/// Layout of θ.
#[derive(Debug, Clone)]
struct Layout {
    n: usize,
    np: usize,
    n_kern: usize,
    scale_idx: Option<usize>,
    rs: usize,
    rn: usize,
}

impl Layout {
    fn off_cs(&self) -> usize {
        self.n_kern - usize::from(self.scale_idx.is_some())
    }
    fn off_vs(&self) -> usize {
        self.off_cs() + self.np * self.rs
    }
    fn off_cn(&self) -> usize {
        self.off_vs() + self.np
    }
    fn off_vn(&self) -> usize {
        self.off_cn() + self.n * self.rn
    }
    fn len(&self) -> usize {
        self.off_vn() + self.n
    }
}

/// `−log p(θ)` of the CoGP (module docs) on fixed data.
struct Likelihood<'a, K: Kernel> {
    layout: Layout,
    kernel: K,
    data: CogpData<'a>,
}

impl<K: Kernel> Likelihood<'_, K> {
    #[allow(non_snake_case)]
    fn unpack(&self, th: &[f64]) -> Result<(K, DMatrix<f64>, DMatrix<f64>), InputError> {
        let l = &self.layout;
        let kern = kernel_from_free(&self.kernel, th, l.scale_idx)?;
        let Sigma = low_rank_plus_diag(
            &th[l.off_cs()..l.off_vs()],
            &th[l.off_vs()..l.off_cn()],
            l.np,
            l.rs,
        );
        let S = low_rank_plus_diag(
            &th[l.off_cn()..l.off_vn()],
            &th[l.off_vn()..l.len()],
            l.n,
            l.rn,
        );
        Ok((kern, Sigma, S))
    }

    /// θ for the given kernel (its scale is ignored), `Σ` and `S`.
    #[allow(non_snake_case)]
    fn theta(
        &self,
        kern: &K,
        Sigma: &DMatrix<f64>,
        S: &DMatrix<f64>,
        exact: bool,
        rng: &mut ChaCha8Rng,
    ) -> Vec<f64> {
        let l = &self.layout;
        let mut th = vec![0.0; l.len()];
        pack_free(&kern.log_hyper(), l.scale_idx, &mut th);
        let (cs, rest) = th[l.off_cs()..].split_at_mut(l.np * l.rs);
        let (vs, rest) = rest.split_at_mut(l.np);
        let (cn, vn) = rest.split_at_mut(l.n * l.rn);
        init_low_rank(Sigma, l.rs, exact, rng, cs, vs);
        init_low_rank(S, l.rn, exact, rng, cn, vn);
        th
    }
}

impl<K: Kernel> Objective for Likelihood<'_, K> {
    /// `(−log p, −∇θ log p)`.
    fn eval(&self, th: &[f64]) -> Evaluation {
        let l = &self.layout;
        // log-scale parameters are bounded to |θ| ≤ 50; the factors C are
        // on the scale of √Σ and only need to be finite
        let is_log =
            |i: usize| i < l.off_cs() || (l.off_vs()..l.off_cn()).contains(&i) || i >= l.off_vn();
        let bad = |(i, v): (usize, &f64)| !v.is_finite() || (is_log(i) && v.abs() > 50.0);
        if th.iter().enumerate().any(bad) {
            return Err(EvalFailure::OutOfRange);
        }
        let (kern, sigma, s) = self.unpack(th).map_err(|_| EvalFailure::InvalidHyper)?;
        let g = lml_grad(&self.data, &kern, &sigma, &s)
            .map_err(|_| EvalFailure::NotPositiveDefinite)?;
        if !g.log_likelihood.is_finite() {
            return Err(EvalFailure::NonFinite);
        }
        let mut grad = vec![0.0; th.len()];
        pack_free(&g.kernel_log_hyper, l.scale_idx, &mut grad);
        chain_low_rank(
            &g.Sigma,
            &th[l.off_cs()..l.off_vs()],
            &th[l.off_vs()..l.off_cn()],
            l.rs,
            &mut grad[l.off_cs()..l.off_cn()],
        );
        chain_low_rank(
            &g.S,
            &th[l.off_cn()..l.off_vn()],
            &th[l.off_vn()..l.len()],
            l.rn,
            &mut grad[l.off_cn()..l.len()],
        );
        for gi in grad.iter_mut() {
            *gi = -*gi;
        }
        Ok((-g.log_likelihood, grad))
    }
}

/// Data-driven start: lengthscales equal to the standard deviations of the
/// kernel inputs, kernel scale 1, `Σ = I_{1+m} ⊗ diag(E r_i² / E‖u̲‖²)`,
/// `S = 0.01 diag(E r_i²)` (`r` the residuals of the prior mean).
#[allow(non_snake_case)]
fn data_driven_start<K: Kernel>(
    model: &Cogp<K>,
) -> Result<(K, DMatrix<f64>, DMatrix<f64>), InputError> {
    let (n, np, k) = (
        model.state_dim(),
        model.state_dim() * (model.control_dim() + 1),
        model.len(),
    );
    let d = model.input_map().output_dim(n);
    let (zs, us, resid) = (
        model.mapped_inputs(),
        model.augmented_controls(),
        model.residuals(),
    );
    let mut kern = model.hyper().kernel.clone();
    let mut kh = kern.log_hyper();
    start_from_inputs(&mut kh, zs, k, d, kern.scale_index());
    kern.set_log_hyper(&kh)?;
    let mean_u2 = (us.iter().map(|v| v * v).sum::<f64>() / k as f64).max(1e-12);
    let r2: Vec<f64> = (0..n)
        .map(|i| ((0..k).map(|j| resid[j * n + i].powi(2)).sum::<f64>() / k as f64).max(1e-12))
        .collect();
    let Sigma = DMatrix::from_fn(
        np,
        np,
        |a, b| {
            if a == b {
                r2[a % n] / mean_u2
            } else {
                0.0
            }
        },
    );
    let S = DMatrix::from_fn(n, n, |a, b| if a == b { 0.01 * r2[a] } else { 0.0 });
    Ok((kern, Sigma, S))
}

/// Learns the kernel lengthscales, `Σ` and `S` of `model` from its data by
/// maximising the exact marginal likelihood (L-BFGS with the analytic
/// gradient of [`Cogp::log_marginal_likelihood_gradient`]), and refactorises the model.
///
/// The kernel output scale is held fixed (redundant with `Σ`). Without
/// `warm_start` each start begins at the data-driven point (lengthscales =
/// standard deviations of the kernel inputs, `Σ = I_{1+m} ⊗ diag(E r_i² /
/// E‖u̲‖²)`, `S = 0.01 diag(E r_i²)`), perturbed for restarts. With
/// `prefit_diagonal` a full or low-rank fit first fits diagonal `Σ`, `S`
/// and starts from that optimum: the diagonal family is well conditioned
/// and lets entries of `F` with (near) zero variance, such as the constant
/// `g` of the pendulum, shrink to zero on a log scale, which the `C Cᵀ`
/// factor alone reaches only slowly. The best point seen over all starts
/// is kept, since line-search failures near the optimum are normal.
/// Deterministic for a given `settings.seed`.
///
/// ## Reference
/// Paper, Appendix (Coregionalization GP) and Sec. VII-A.
#[allow(non_snake_case)]
pub fn fit_cogp<K: Kernel>(
    model: &mut Cogp<K>,
    settings: &CogpFitSettings,
) -> Result<FitReport, Error> {
    settings.validate()?;
    let k = model.len();
    if k == 0 {
        return Err(GpError::NoData.into());
    }
    let (n, p) = (model.state_dim(), model.control_dim() + 1);
    let np = n * p;
    let initial_ll = model.log_marginal_likelihood();
    let (kernel0, Sigma0, S0) = if settings.warm_start {
        let h = model.hyper();
        (h.kernel.clone(), h.Sigma.clone(), h.S.clone())
    } else {
        data_driven_start(model)?
    };
    let data = CogpData {
        n,
        p,
        d: model.input_map().output_dim(n),
        k,
        zs: model.mapped_inputs(),
        us: model.augmented_controls(),
        resid: model.residuals(),
    };
    let layout = Layout {
        n,
        np,
        n_kern: kernel0.n_hyper(),
        scale_idx: kernel0.scale_index(),
        rs: settings.rank_sigma.cols(np),
        rn: settings.rank_s.cols(n),
    };
    let use_prefit = settings.prefit_diagonal && !settings.warm_start && layout.rs + layout.rn > 0;
    let diag = Harness::new(Likelihood {
        layout: Layout {
            rs: 0,
            rn: 0,
            ..layout.clone()
        },
        kernel: kernel0.clone(),
        data,
    });
    let full = Harness::new(Likelihood {
        layout,
        kernel: kernel0.clone(),
        data,
    });
    // a run that stops early (line-search failure) resumes from the best
    // point with fresh memory, up to 4 times, while it improves
    let run = RunSettings {
        max_iters: settings.max_iters,
        stall_resumes: 4,
        relative_cost_tolerance: None,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(settings.seed);
    let (obj, dg) = (full.objective(), diag.objective());
    let starts = 1 + settings.restarts;
    let best = multi_start(&full, starts, &run, |s| {
        if !use_prefit {
            let exact = settings.warm_start && s == 0;
            let mut th = obj.theta(&kernel0, &Sigma0, &S0, exact, &mut rng);
            if s > 0 {
                perturb(&mut th, &mut rng);
            }
            return Ok::<_, Error>(StartPlan::at(th));
        }
        let mut th = dg.theta(&kernel0, &Sigma0, &S0, false, &mut rng);
        if s > 0 {
            perturb(&mut th, &mut rng);
        }
        prefit(&diag, &full, th, &run, |optimum| {
            let Some(opt) = optimum else {
                // no diagonal model could be evaluated: start the full fit cold
                return Ok((obj.theta(&kernel0, &Sigma0, &S0, false, &mut rng), None));
            };
            let (kd, sd, nd) = dg.unpack(opt)?;
            let th = obj.theta(&kd, &sd, &nd, false, &mut rng);
            // the diagonal optimum itself (C = 0) stays a candidate
            let mut th_diag = th.clone();
            let l = &obj.layout;
            th_diag[l.off_cs()..l.off_vs()].fill(0.0);
            th_diag[l.off_cn()..l.off_vn()].fill(0.0);
            Ok((th, Some(th_diag)))
        })
    })?;
    let evaluations = full.evaluations() + diag.evaluations();
    let (kern, Sigma, S) = obj.unpack(&best.theta)?;
    drop((full, diag));
    model.set_hyper(CogpHyper {
        kernel: kern,
        Sigma: 0.5 * (&Sigma + Sigma.transpose()),
        S: 0.5 * (&S + S.transpose()),
    })?;
    Ok(FitReport {
        initial_log_likelihood: initial_ll,
        log_likelihood: model.log_marginal_likelihood(),
        evaluations,
        starts,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gp::theta::random_training_rows;
    use crate::gp::Rbf;
    use rand::RngExt;

    /// The θ-level gradient (through `C Cᵀ + diag(v)`) against central
    /// finite differences.
    #[test]
    fn theta_gradient_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        for (n, m, rs, rn) in [
            (2, 1, Rank::Full, Rank::Full),
            (3, 1, Rank::Low(2), Rank::Diagonal),
            (1, 2, Rank::Diagonal, Rank::Full),
        ] {
            let (k, p) = (8, m + 1);
            let (zs, us, resid) = random_training_rows(&mut rng, k, n, m);
            let kernel = Rbf::new(vec![0.8; n], 1.3).unwrap();
            let layout = Layout {
                n,
                np: n * p,
                n_kern: n + 1,
                scale_idx: Some(n),
                rs: rs.cols(n * p),
                rn: rn.cols(n),
            };
            let th: Vec<f64> = (0..layout.len())
                .map(|_| rng.random_range(-0.5..0.5))
                .collect();
            let obj = Likelihood {
                layout,
                kernel,
                data: CogpData {
                    n,
                    p,
                    d: n,
                    k,
                    zs: &zs,
                    us: &us,
                    resid: &resid,
                },
            };
            let f = |th: &[f64]| obj.eval(th).unwrap();
            let (_, g) = f(&th);
            let h = 1e-6;
            for i in 0..th.len() {
                let (mut tp, mut tm) = (th.clone(), th.clone());
                tp[i] += h;
                tm[i] -= h;
                let fd = (f(&tp).0 - f(&tm).0) / (2.0 * h);
                assert!(
                    (fd - g[i]).abs() < 1e-5 * (1.0 + fd.abs()),
                    "n={n} m={m} param {i}: fd {fd} analytic {}",
                    g[i]
                );
            }
        }
    }
}
