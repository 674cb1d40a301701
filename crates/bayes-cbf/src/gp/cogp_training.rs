//! Hyperparameter learning for the CoGP by maximising the exact marginal
//! likelihood with an analytic gradient (projected L-BFGS, as
//! [`fit`](super::fit) for the MVGP).
//!
//! The likelihood and its gradient are [`Cogp::log_marginal_likelihood_gradient`].
//!
//! ## Parameterisation
//! `Σ` and `S` by their Cholesky factors with logarithmic diagonals, or a
//! low-rank or diagonal form ([`Rank`]; the `psd` module). The kernel's
//! output scale is held fixed (it is redundant with `Σ`); there is no other
//! redundancy, since `S` is the only noise term.
//! `θ = [log ℓ (kernel, without scale), θ_Σ, θ_S]`, bounded as the MVGP's:
//! lengthscales within `10³` of their input's spread either way,
//! logarithmic diagonal entries within `10⁶` of their start's scale.

use super::cogp::{lml_grad, Cogp, CogpData, CogpHyper};
use super::factor::Jitter;
use super::kernel::Kernel;
use super::optimise::{
    multi_start, perturb, EvalFailure, Harness, Objective, RunSettings, StartPlan,
};
use super::psd::{PsdParam, SCALE_RANGE};
use super::theta::{input_spreads, kernel_bounds, kernel_from_free, pack_free, start_from_inputs};
use super::training::{FitReport, Rank};
use crate::error::{Error, InputError};
use nalgebra::DMatrix;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::sync::atomic::AtomicBool;

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
    /// Extra random restarts besides the first start ([`fit_cogp`]).
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
        super::optimise::check_run_settings(self.max_iters, self.restarts)
    }
}

/// Layout of θ: `[log ℓ (free kernel hyperparameters), θ_Σ, θ_S]`.
#[derive(Debug, Clone)]
struct Layout {
    kern_free: usize,
    scale_idx: Option<usize>,
    sigma: PsdParam,
    s: PsdParam,
}

impl Layout {
    fn new(kernel: &impl Kernel, np: usize, n: usize, rank_sigma: Rank, rank_s: Rank) -> Self {
        let scale_idx = kernel.scale_index();
        Self {
            kern_free: kernel.n_hyper() - usize::from(scale_idx.is_some()),
            scale_idx,
            sigma: PsdParam::new(np, rank_sigma),
            s: PsdParam::new(n, rank_s),
        }
    }
    fn off_sigma(&self) -> usize {
        self.kern_free
    }
    fn off_s(&self) -> usize {
        self.kern_free + self.sigma.len()
    }
    fn len(&self) -> usize {
        self.off_s() + self.s.len()
    }
}

/// `−log p(θ)` of the CoGP (module docs) on fixed data.
struct Likelihood<'a, K: Kernel> {
    layout: Layout,
    kernel: K,
    data: CogpData<'a>,
    lower: Vec<f64>,
    upper: Vec<f64>,
}

impl<'a, K: Kernel> Likelihood<'a, K> {
    /// The likelihood, with the covariances' logarithmic entries bounded
    /// around the scales of `scale_sigma` and `scale_s` (the start).
    fn new(
        layout: Layout,
        kernel: K,
        data: CogpData<'a>,
        scale_sigma: &DMatrix<f64>,
        scale_s: &DMatrix<f64>,
    ) -> Self {
        let len = layout.len();
        let (mut lower, mut upper) = (vec![f64::NEG_INFINITY; len], vec![f64::INFINITY; len]);
        let spreads = input_spreads(data.zs, data.k, data.d);
        kernel_bounds(
            kernel.n_hyper(),
            layout.scale_idx,
            &spreads,
            &mut lower,
            &mut upper,
        );
        let (os, on) = (layout.off_sigma(), layout.off_s());
        let r = SCALE_RANGE;
        layout
            .sigma
            .bounds(scale_sigma, r, &mut lower[os..on], &mut upper[os..on]);
        layout
            .s
            .bounds(scale_s, r, &mut lower[on..], &mut upper[on..]);
        Self {
            layout,
            kernel,
            data,
            lower,
            upper,
        }
    }

    #[allow(non_snake_case)]
    fn unpack(&self, th: &[f64]) -> Result<(K, DMatrix<f64>, DMatrix<f64>), InputError> {
        let l = &self.layout;
        let kern = kernel_from_free(&self.kernel, th, l.scale_idx)?;
        let Sigma = l.sigma.matrix(&th[l.off_sigma()..l.off_s()]);
        let S = l.s.matrix(&th[l.off_s()..]);
        Ok((kern, Sigma, S))
    }

    /// θ for the given kernel (its scale is ignored), `Σ` and `S`: exact for
    /// full and diagonal forms, with random low-rank factors.
    #[allow(non_snake_case)]
    fn theta(
        &self,
        kern: &K,
        Sigma: &DMatrix<f64>,
        S: &DMatrix<f64>,
        rng: &mut ChaCha8Rng,
    ) -> Vec<f64> {
        let l = &self.layout;
        let mut th = vec![0.0; l.len()];
        pack_free(&kern.log_hyper(), l.scale_idx, &mut th);
        let (ts, tn) = th[l.off_sigma()..].split_at_mut(l.sigma.len());
        l.sigma.init(Sigma, rng, ts);
        l.s.init(S, rng, tn);
        th
    }

    /// θ of the diagonal parts of `Σ` and `S` with zero factors off the
    /// diagonal, keeping the kernel entries of `th`.
    #[allow(non_snake_case)]
    fn diagonal_theta(&self, th: &[f64], Sigma: &DMatrix<f64>, S: &DMatrix<f64>) -> Vec<f64> {
        let l = &self.layout;
        let mut out = th.to_vec();
        let (ts, tn) = out[l.off_sigma()..].split_at_mut(l.sigma.len());
        l.sigma.diagonal_point(Sigma, ts);
        l.s.diagonal_point(S, tn);
        out
    }
}

impl<K: Kernel> Objective for Likelihood<'_, K> {
    fn bounds(&self) -> (&[f64], &[f64]) {
        (&self.lower, &self.upper)
    }

    /// `(−log p, −∇θ log p)`.
    fn eval(&mut self, th: &[f64], grad: &mut [f64]) -> Result<f64, EvalFailure> {
        let l = &self.layout;
        let (kern, sigma, s) = self.unpack(th).map_err(|_| EvalFailure::InvalidHyper)?;
        // exactly, without jitter (as the MVGP's fit; factor::Jitter)
        let g = lml_grad(&self.data, &kern, &sigma, &s, Jitter::Exact(1.0))
            .map_err(|_| EvalFailure::NotPositiveDefinite)?;
        if !g.log_likelihood.is_finite() {
            return Err(EvalFailure::NonFinite);
        }
        pack_free(&g.kernel_log_hyper, l.scale_idx, grad);
        let (gs, gn) = grad[l.off_sigma()..].split_at_mut(l.sigma.len());
        l.sigma.chain(&g.Sigma, &th[l.off_sigma()..l.off_s()], gs);
        l.s.chain(&g.S, &th[l.off_s()..], gn);
        for gi in grad.iter_mut() {
            *gi = -*gi;
        }
        Ok(-g.log_likelihood)
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
/// E‖u̲‖²)`, `S = 0.01 diag(E r_i²)`), perturbed for restarts; the first
/// begins at the model's own hyperparameters instead where their
/// likelihood is higher, so that a fit never ends below the model it was
/// given (where the parameterisation holds it exactly). With
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
pub fn fit_cogp<K: Kernel>(
    model: &mut Cogp<K>,
    settings: &CogpFitSettings,
) -> Result<FitReport, Error> {
    fit_cogp_until(model, settings, &AtomicBool::new(false))
}

/// [`fit_cogp`], stopped once `stop` is set (by another thread), within one
/// likelihood evaluation: it then returns [`Error::Interrupted`] and
/// leaves the model's hyperparameters as they were.
#[allow(non_snake_case)]
pub fn fit_cogp_until<K: Kernel>(
    model: &mut Cogp<K>,
    settings: &CogpFitSettings,
    stop: &AtomicBool,
) -> Result<FitReport, Error> {
    settings.validate()?;
    let k = model.len();
    if k == 0 {
        return Err(InputError::shape("data", "at least one observation to fit", 0).into());
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
    settings
        .rank_sigma
        .check("rank_sigma", np, "n (1 + control_dim)")?;
    settings.rank_s.check("rank_s", n, "state_dim")?;
    let layout = Layout::new(&kernel0, np, n, settings.rank_sigma, settings.rank_s);
    let full_rank = settings.rank_sigma != Rank::Diagonal || settings.rank_s != Rank::Diagonal;
    let use_prefit = settings.prefit_diagonal && !settings.warm_start && full_rank;
    let diag_layout = Layout::new(&kernel0, np, n, Rank::Diagonal, Rank::Diagonal);
    let mut diag = Harness::new(Likelihood::new(
        diag_layout,
        kernel0.clone(),
        data,
        &Sigma0,
        &S0,
    ))
    .with_stop(stop);
    let mut full =
        Harness::new(Likelihood::new(layout, kernel0.clone(), data, &Sigma0, &S0)).with_stop(stop);
    // a run that stops early (line-search failure) resumes from its last
    // point with fresh memory, up to 4 times, while it improves
    let run = RunSettings {
        max_iters: settings.max_iters,
        stall_resumes: 4,
        relative_cost_tolerance: 1e-12,
    };
    // a cold fit's first start is the model's own hyperparameters when
    // they are the better point (as the MVGP fit's): the equivalent model
    // at the kernel scale of the parameterisation, which `Σ` absorbs
    let mut own = (!settings.warm_start).then(|| {
        let h = model.hyper();
        let scale = kernel0.scale_index().map_or(1.0, |i| {
            (h.kernel.log_hyper()[i] - kernel0.log_hyper()[i]).exp()
        });
        let mut rng = ChaCha8Rng::seed_from_u64(settings.seed);
        full.objective()
            .theta(&h.kernel, &(&h.Sigma * scale), &h.S, &mut rng)
    });
    let mut rng = ChaCha8Rng::seed_from_u64(settings.seed);
    let starts = 1 + settings.restarts;
    // the start of run s: the data-driven point (perturbed after the
    // first), or the diagonal pre-fit's optimum lifted into the full
    // parameterisation
    let mut planned_start = |full: &mut Harness<Likelihood<'_, K>>, s: usize| {
        if !use_prefit {
            let mut th = full.objective().theta(&kernel0, &Sigma0, &S0, &mut rng);
            if s > 0 {
                perturb(&mut th, &mut rng);
            }
            return Ok::<_, Error>(StartPlan::at(th));
        }
        let mut th = diag.objective().theta(&kernel0, &Sigma0, &S0, &mut rng);
        if s > 0 {
            perturb(&mut th, &mut rng);
        }
        // pre-fit: the diagonal model's optimum, lifted into the full
        // parameterisation, is the start; itself it stays a candidate
        let (start, candidate) = match diag.run_start(th, &run)? {
            // no diagonal model could be evaluated: start the full fit cold
            None => (
                full.objective().theta(&kernel0, &Sigma0, &S0, &mut rng),
                None,
            ),
            Some(opt) => {
                let (kd, sd, nd) = diag.objective().unpack(&opt.theta)?;
                let th = full.objective().theta(&kd, &sd, &nd, &mut rng);
                let th_diag = full.objective().diagonal_theta(&th, &sd, &nd);
                (th, Some(th_diag))
            }
        };
        Ok(StartPlan {
            theta: start,
            candidates: candidate.and_then(|t| full.point(t)).into_iter().collect(),
        })
    };
    let best = multi_start(&mut full, starts, &run, |full, s| {
        let mut plan = planned_start(full, s)?;
        if let Some(own) = own.take() {
            plan.theta = full.better_start(plan.theta, Some(own)).0;
        }
        Ok::<_, Error>(plan)
    })?;
    if full.stopped() {
        return Err(Error::Interrupted);
    }
    let evaluations = full.evaluations() + diag.evaluations();
    let (kern, Sigma, S) = full.objective().unpack(&best.theta)?;
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

    /// The θ-level gradient (through the parameterisations of `Σ` and `S`)
    /// against central finite differences.
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
            let layout = Layout::new(&kernel, n * p, n, rs, rn);
            let th: Vec<f64> = (0..layout.len())
                .map(|_| rng.random_range(-0.5..0.5))
                .collect();
            let data = CogpData {
                n,
                p,
                d: n,
                k,
                zs: &zs,
                us: &us,
                resid: &resid,
            };
            let (sigma0, s0) = (DMatrix::identity(n * p, n * p), DMatrix::identity(n, n));
            let mut obj = Likelihood::new(layout, kernel, data, &sigma0, &s0);
            let mut f = |th: &[f64]| {
                let mut g = vec![0.0; th.len()];
                let v = obj.eval(th, &mut g).unwrap();
                (v, g)
            };
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

    /// As the MVGP fit: a fit never ends below the likelihood of the model
    /// it was given (a refit of a well-fitted model with one, three or the
    /// default iterations, pre-fit and not, at a kernel scale the
    /// parameterisation does not hold).
    #[test]
    fn a_fit_never_ends_below_the_model_it_was_given() {
        use crate::gp::{Cogp, InputMap, PriorMean};
        for seed in 0..4 {
            let mut rng = ChaCha8Rng::seed_from_u64(200 + seed);
            let (n, m, k) = (2, 1, 25);
            let (zs, us, resid) = random_training_rows(&mut rng, k, n, m);
            let hyper = CogpHyper {
                kernel: Rbf::new(vec![0.8; n], 1.3).unwrap(),
                Sigma: DMatrix::identity(n * (m + 1), n * (m + 1)),
                S: DMatrix::identity(n, n) * 0.1,
            };
            let mut model = Cogp::new(n, m, hyper, PriorMean::Zero, InputMap::Identity).unwrap();
            let u_only: Vec<f64> = us.chunks(m + 1).flat_map(|u| u[1..].to_vec()).collect();
            model.set_data(&zs, &u_only, &resid).unwrap();
            let good = CogpFitSettings {
                restarts: 2,
                seed,
                ..CogpFitSettings::default()
            };
            fit_cogp(&mut model, &good).unwrap();
            // the same model at another kernel scale
            let mut h = model.hyper().clone();
            h.kernel = Rbf::new(h.kernel.lengthscales().to_vec(), 3.0).unwrap();
            h.Sigma *= h.kernel.variance().recip() * model.hyper().kernel.variance();
            let before = model.log_marginal_likelihood();
            model.set_hyper(h).unwrap();
            assert!((model.log_marginal_likelihood() - before).abs() < 1e-9 * before.abs());
            for (max_iters, prefit_diagonal) in [(1, true), (3, false), (100, true)] {
                let mut refit = model.clone();
                let settings = CogpFitSettings {
                    max_iters,
                    prefit_diagonal,
                    seed: seed + 7,
                    ..CogpFitSettings::default()
                };
                let report = fit_cogp(&mut refit, &settings).unwrap();
                assert!(
                    report.log_likelihood >= before - 1e-9 * before.abs().max(1.0),
                    "seed {seed}, max_iters {max_iters}: {} after {before}",
                    report.log_likelihood
                );
            }
        }
    }
}
