//! Hyperparameter learning for the MVGP by maximising the exact marginal
//! likelihood with an analytic gradient (L-BFGS, argmin).
//!
//! ## Likelihood
//! `vec Ẋ ~ N(vec(𝓜U̲), G ⊗ A)`, `G = K + σ²I`, `K_ij = u̲_iᵀ B u̲_j k0(x_i,x_j)`:
//!
//! `log p = −½ [n log|G| + k log|A| + tr(A⁻¹ R G⁻¹ Rᵀ) + nk log 2π]`, `R = Ẋ − 𝓜U̲`.
//!
//! With `S = G⁻¹`, `α = S Rᵀ`, `Q = R S Rᵀ`:
//! `∂ log p/∂G = −½ (n S − α A⁻¹ αᵀ)`, `∂ log p/∂A = −½ (k A⁻¹ − A⁻¹ Q A⁻¹)`.
//!
//! ## Parameterisation and the scale redundancy
//! `B k0 ⊗ A` with noise `σ²A` is invariant under `(A, B, s, σ²) →
//! (A/c, c B/t, t s, c σ²)` for the kernel variance `s`. We remove both
//! redundancies: the kernel's output scale is held fixed (its scale is
//! carried by `B`), and `A = C_A C_Aᵀ + diag(v)` has `v_1 = 1` fixed, which is
//! a bijective normalisation of the family up to scale. After fitting the
//! equivalent model with `tr A = n` is reported.
//!
//! `θ = [log ℓ (kernel, without scale), log σ, vec C_B, log v_B, vec C_A, log v_A[2..n]]`.

use super::factor::CholFactor;
use super::kernel::Kernel;
use super::low_rank::{chain_low_rank, init_low_rank, low_rank_plus_diag};
use super::mvgp::{Mvgp, MvgpHyper};
use super::optimise::{
    multi_start, perturb, EvalFailure, Evaluation, Harness, Objective, RunSettings, StartPlan,
};
use super::simd::with_faer;
use super::theta::{kernel_from_free, pack_free, start_from_inputs};
use crate::error::{Error, GpError, InputError};
use faer::Mat;
use nalgebra::DMatrix;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Structure of a learned covariance matrix `C Cᵀ + diag(v)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub enum Rank {
    /// `C` square: any positive-definite matrix.
    #[default]
    Full,
    /// `C = 0`: diagonal.
    Diagonal,
    /// `C` with `r` columns.
    Low(usize),
}

impl Rank {
    /// Columns of `C` for a `dim × dim` matrix.
    pub(crate) fn cols(self, dim: usize) -> usize {
        match self {
            Rank::Full => dim,
            Rank::Diagonal => 0,
            Rank::Low(r) => r.min(dim),
        }
    }
}

/// Settings of [`fit`], validated by [`FitSettings::validate`].
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct FitSettings {
    /// Structure of `A`.
    pub rank_a: Rank,
    /// Structure of `B`.
    pub rank_b: Rank,
    /// L-BFGS iterations per start.
    pub max_iters: u64,
    /// Extra random restarts besides the data-driven start.
    pub restarts: usize,
    /// Seed of the random initialisation of the off-diagonal factors and of
    /// the restarts.
    pub seed: u64,
    /// Learn `A` (otherwise it is held at its current value).
    pub learn_a: bool,
    /// Initialise from the model's current hyperparameters instead of the
    /// data-driven heuristic.
    pub warm_start: bool,
    /// Floor of the noise scale: `σ = σ_min + exp(θ_σ)`. Zero gives the
    /// plain maximum-likelihood σ; a floor keeps the Gram matrix well
    /// conditioned on near-duplicate, nearly noise-free data.
    pub sigma_min: f64,
}

impl Default for FitSettings {
    fn default() -> Self {
        Self {
            rank_a: Rank::Full,
            rank_b: Rank::Full,
            max_iters: 100,
            restarts: 0,
            seed: 0,
            learn_a: true,
            warm_start: false,
            sigma_min: 0.0,
        }
    }
}

impl FitSettings {
    /// Checks the settings.
    pub fn validate(&self) -> Result<(), InputError> {
        if self.max_iters == 0 {
            return Err(InputError::invalid("max_iters", 0.0, "must be ≥ 1"));
        }
        if !(self.sigma_min.is_finite() && self.sigma_min >= 0.0) {
            return Err(InputError::invalid(
                "sigma_min",
                self.sigma_min,
                "must be finite and ≥ 0",
            ));
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

/// Outcome of [`fit`].
#[derive(Debug, Clone, PartialEq)]
pub struct FitReport {
    /// Log marginal likelihood before fitting (at the initial hyperparameters).
    pub initial_log_likelihood: f64,
    /// Log marginal likelihood at the returned hyperparameters.
    pub log_likelihood: f64,
    /// Objective evaluations over all starts.
    pub evaluations: usize,
    /// Starts run.
    pub starts: usize,
}

/// Layout of θ.
#[derive(Debug, Clone)]
struct Layout {
    n: usize,
    p: usize,
    n_kern: usize,
    scale_idx: Option<usize>,
    rb: usize,
    ra: usize,
    learn_a: bool,
    sigma_min: f64,
}

impl Layout {
    fn kern_free(&self) -> usize {
        self.n_kern - usize::from(self.scale_idx.is_some())
    }
    fn off_sigma(&self) -> usize {
        self.kern_free()
    }
    fn off_cb(&self) -> usize {
        self.off_sigma() + 1
    }
    fn off_vb(&self) -> usize {
        self.off_cb() + self.p * self.rb
    }
    fn off_ca(&self) -> usize {
        self.off_vb() + self.p
    }
    fn off_va(&self) -> usize {
        self.off_ca() + if self.learn_a { self.n * self.ra } else { 0 }
    }
    fn len(&self) -> usize {
        self.off_va() + if self.learn_a { self.n - 1 } else { 0 }
    }
}

/// `−log p(θ)` of the MVGP (module docs) on fixed data.
struct Likelihood<'a, K: Kernel> {
    layout: Layout,
    kernel: K,
    fixed_a: DMatrix<f64>,
    zs: &'a [f64],
    us: &'a [f64],
    resid: &'a [f64],
    k: usize,
    d: usize,
}

impl<K: Kernel> Likelihood<'_, K> {
    #[allow(non_snake_case)]
    fn unpack(&self, th: &[f64]) -> Result<(K, DMatrix<f64>, DMatrix<f64>, f64), InputError> {
        let l = &self.layout;
        let kern = kernel_from_free(&self.kernel, th, l.scale_idx)?;
        let sigma = l.sigma_min + th[l.off_sigma()].exp();
        let B = low_rank_plus_diag(
            &th[l.off_cb()..l.off_vb()],
            &th[l.off_vb()..l.off_vb() + l.p],
            l.p,
            l.rb,
        );
        let A = if l.learn_a {
            let mut logv = vec![0.0; l.n];
            logv[1..].copy_from_slice(&th[l.off_va()..l.off_va() + l.n - 1]);
            low_rank_plus_diag(&th[l.off_ca()..l.off_va()], &logv, l.n, l.ra)
        } else {
            self.fixed_a.clone()
        };
        Ok((kern, A, B, sigma))
    }
}

impl<K: Kernel> Objective for Likelihood<'_, K> {
    /// `(−log p, −∇θ log p)`.
    #[allow(non_snake_case)]
    fn eval(&self, th: &[f64]) -> Evaluation {
        let l = &self.layout;
        let (n, p, k, d) = (l.n, l.p, self.k, self.d);
        if th.iter().any(|v| !v.is_finite() || v.abs() > 50.0) {
            return Err(EvalFailure::OutOfRange);
        }
        let (kern, A, B, sigma) = self.unpack(th).map_err(|_| EvalFailure::InvalidHyper)?;
        // Gram matrix
        let z = |i: usize| &self.zs[i * d..(i + 1) * d];
        let u = |i: usize| &self.us[i * p..(i + 1) * p];
        let mut bu = vec![0.0; k * p];
        for j in 0..k {
            for a in 0..p {
                bu[j * p + a] = (0..p).map(|c| B[(a, c)] * u(j)[c]).sum::<f64>();
            }
        }
        let mut k0 = Mat::<f64>::zeros(k, k);
        let mut ubu = Mat::<f64>::zeros(k, k);
        let mut g = Mat::<f64>::zeros(k, k);
        for j in 0..k {
            for i in j..k {
                let kv = kern.value(z(i), z(j));
                let q: f64 = (0..p).map(|c| u(i)[c] * bu[j * p + c]).sum();
                k0[(i, j)] = kv;
                k0[(j, i)] = kv;
                ubu[(i, j)] = q;
                ubu[(j, i)] = q;
                g[(i, j)] = q * kv;
            }
            g[(j, j)] += sigma * sigma;
        }
        let factor = CholFactor::factor_quiet(g.as_ref(), k)
            .map_err(|_| EvalFailure::NotPositiveDefinite)?;
        // α = G⁻¹ Rᵀ, S = G⁻¹
        let mut alpha = Mat::<f64>::from_fn(k, n, |j, i| self.resid[j * n + i]);
        factor.solve_l(alpha.as_mut());
        let beta = with_faer(|| alpha.clone());
        factor.solve_lt(alpha.as_mut());
        let s = factor.inverse_mat();
        let qf = with_faer(|| beta.transpose() * &beta);
        let Q = DMatrix::from_fn(n, n, |i, j| qf[(i, j)]);
        let chol_a = A
            .clone()
            .cholesky()
            .ok_or(EvalFailure::NotPositiveDefinite)?;
        let Ainv = chol_a.inverse();
        let logdet_a = 2.0 * chol_a.l().diagonal().iter().map(|v| v.ln()).sum::<f64>();
        let ll = -0.5
            * (n as f64 * factor.log_det()
                + k as f64 * logdet_a
                + (&Ainv * &Q).trace()
                + (n * k) as f64 * (2.0 * std::f64::consts::PI).ln());
        if !ll.is_finite() {
            return Err(EvalFailure::NonFinite);
        }
        // Ḡ = −½ (n S − α A⁻¹ αᵀ)
        let ainv_f = Mat::<f64>::from_fn(n, n, |i, j| Ainv[(i, j)]);
        let mut gbar = with_faer(|| &(&alpha * &ainv_f) * alpha.transpose());
        for j in 0..k {
            for i in 0..k {
                gbar[(i, j)] = -0.5 * (n as f64 * s[(i, j)] - gbar[(i, j)]);
            }
        }
        let mut grad = vec![0.0; th.len()];
        // kernel hyperparameters: ∂K_ij = ubu_ij ∂k0_ij
        let nk = kern.n_hyper();
        let mut gh = vec![0.0; nk];
        let mut acc = vec![0.0; nk];
        for j in 0..k {
            for i in 0..k {
                let w = gbar[(i, j)] * ubu[(i, j)];
                if w != 0.0 {
                    kern.grad_log_hyper(z(i), z(j), &mut gh);
                    for (a, g) in acc.iter_mut().zip(&gh) {
                        *a += w * g;
                    }
                }
            }
        }
        pack_free(&acc, l.scale_idx, &mut grad);
        // σ = σ_min + e^θ: ∂G/∂θ = 2σ (σ − σ_min) I
        let tr_gbar: f64 = (0..k).map(|i| gbar[(i, i)]).sum();
        grad[l.off_sigma()] = 2.0 * sigma * (sigma - l.sigma_min) * tr_gbar;
        // B̄ = U̲ᵀ (Ḡ ∘ K0) U̲
        let mut bbar = DMatrix::<f64>::zeros(p, p);
        let mut tmp = vec![0.0; p];
        for i in 0..k {
            tmp.fill(0.0);
            for j in 0..k {
                let w = gbar[(i, j)] * k0[(i, j)];
                for c in 0..p {
                    tmp[c] += w * u(j)[c];
                }
            }
            for a in 0..p {
                for c in 0..p {
                    bbar[(a, c)] += u(i)[a] * tmp[c];
                }
            }
        }
        let bbar = 0.5 * (&bbar + bbar.transpose());
        chain_low_rank(
            &bbar,
            &th[l.off_cb()..l.off_vb()],
            &th[l.off_vb()..l.off_vb() + p],
            l.rb,
            &mut grad[l.off_cb()..l.off_vb() + p],
        );
        if l.learn_a {
            let abar = -0.5 * (k as f64 * &Ainv - &Ainv * &Q * &Ainv);
            let mut logv = vec![0.0; n];
            logv[1..].copy_from_slice(&th[l.off_va()..l.off_va() + n - 1]);
            let mut ga = vec![0.0; n * l.ra + n];
            chain_low_rank(&abar, &th[l.off_ca()..l.off_va()], &logv, l.ra, &mut ga);
            grad[l.off_ca()..l.off_va()].copy_from_slice(&ga[..n * l.ra]);
            grad[l.off_va()..l.off_va() + n - 1].copy_from_slice(&ga[n * l.ra + 1..]);
        }
        for gi in grad.iter_mut() {
            *gi = -*gi;
        }
        Ok((-ll, grad))
    }
}

/// Learns the kernel lengthscales, `A`, `B` and `σ` of `model` from its data
/// by maximising the exact marginal likelihood, and refactorises the model.
///
/// Deterministic for a given `settings.seed`.
///
/// ## Reference
/// Paper, Sec. IV (marginal likelihood of Eq. 11), Prop. 1.
#[allow(non_snake_case)]
pub fn fit<K: Kernel>(model: &mut Mvgp<K>, settings: &FitSettings) -> Result<FitReport, Error> {
    settings.validate()?;
    let k = model.len();
    if k == 0 {
        return Err(GpError::NoData.into());
    }
    let n_state = model.state_dim();
    let p = model.control_dim() + 1;
    let d = model.input_map().output_dim(n_state);
    // with known rows, only the learned rows enter the likelihood (their
    // residuals and A's block on them; Mvgp::with_known_rows)
    let rows = model.learned_rows();
    let n = rows.len();
    let a_learned = DMatrix::from_fn(n, n, |i, j| model.hyper().A[(rows[i], rows[j])]);
    let initial_ll = model.log_marginal_likelihood();
    let kernel = model.hyper().kernel.clone();
    let layout = Layout {
        n,
        p,
        n_kern: kernel.n_hyper(),
        scale_idx: kernel.scale_index(),
        rb: settings.rank_b.cols(p),
        ra: settings.rank_a.cols(n),
        learn_a: settings.learn_a && n > 0,
        sigma_min: settings.sigma_min,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(settings.seed);
    // data-driven initial point
    let all_resid = model.residuals();
    let resid: Vec<f64> = if n == n_state {
        all_resid.to_vec()
    } else {
        (0..k)
            .flat_map(|j| rows.iter().map(move |&i| all_resid[j * n_state + i]))
            .collect()
    };
    let resid = resid.as_slice();
    let us = model.augmented_controls();
    let zs = model.mapped_inputs();
    let mean_r2 = (resid.iter().map(|r| r * r).sum::<f64>() / resid.len() as f64).max(1e-12);
    let mean_u2 = us
        .chunks(p)
        .map(|u| u.iter().map(|v| v * v).sum::<f64>())
        .sum::<f64>()
        / k as f64;
    let mut th0 = vec![0.0; layout.len()];
    let mut kh = kernel.log_hyper();
    if !settings.warm_start {
        start_from_inputs(&mut kh, zs, k, d, layout.scale_idx);
    }
    pack_free(&kh, layout.scale_idx, &mut th0);
    let kernel_start = {
        let mut kk = kernel.clone();
        kk.set_log_hyper(&kh)?;
        kk
    };
    let (a0, b0, sigma0) = if settings.warm_start {
        let h = model.hyper();
        let s = kernel_start
            .scale_index()
            .map(|i| kh[i].exp())
            .unwrap_or(1.0);
        let c = a_learned[(0, 0)];
        (
            a_learned.clone() / c,
            &h.B * (c * s / s.max(1e-300)),
            h.sigma * c.sqrt(),
        )
    } else {
        let b_scale = mean_r2 / mean_u2.max(1e-12);
        (
            DMatrix::identity(n, n),
            DMatrix::identity(p, p) * b_scale,
            (0.01 * mean_r2).sqrt(),
        )
    };
    th0[layout.off_sigma()] = (sigma0 - settings.sigma_min)
        .max(1e-3 * sigma0.max(1e-12))
        .ln();
    {
        let (cb, rest) = th0[layout.off_cb()..].split_at_mut(p * layout.rb);
        init_low_rank(&b0, layout.rb, false, &mut rng, cb, &mut rest[..p]);
    }
    if layout.learn_a {
        let mut logv = vec![0.0; n];
        let mut ca = vec![0.0; n * layout.ra];
        init_low_rank(&a0, layout.ra, false, &mut rng, &mut ca, &mut logv);
        th0[layout.off_ca()..layout.off_va()].copy_from_slice(&ca);
        for i in 1..n {
            th0[layout.off_va() + i - 1] = logv[i] - logv[0];
        }
    }
    let harness = Harness::new(Likelihood {
        layout: layout.clone(),
        kernel: kernel_start,
        fixed_a: a_learned.clone(),
        zs,
        us,
        resid,
        k,
        d,
    });
    // one run per start, ending when an iteration improves −log p by less
    // than 1e-9 relative; a line-search failure near the optimum ends it too
    let run = RunSettings {
        max_iters: settings.max_iters,
        stall_resumes: 0,
        relative_cost_tolerance: Some(1e-9),
    };
    let starts = 1 + settings.restarts;
    let best = multi_start(&harness, starts, &run, |s| {
        let mut th = th0.clone();
        if s > 0 {
            perturb(&mut th, &mut rng);
        }
        Ok::<_, Error>(StartPlan::at(th))
    })?;
    let evaluations = harness.evaluations();
    let (kern, A, B, sigma) = harness.objective().unpack(&best.theta)?;
    drop(harness);
    // report the equivalent model with tr A = n (over the learned rows)
    let c = A.trace() / n as f64;
    let mut full_a = model.hyper().A.clone();
    for (i, &ri) in rows.iter().enumerate() {
        for j in 0..n_state {
            if !rows.contains(&j) {
                full_a[(ri, j)] = 0.0;
                full_a[(j, ri)] = 0.0;
            }
        }
        for (j, &rj) in rows.iter().enumerate() {
            full_a[(ri, rj)] = A[(i, j)] / c;
        }
    }
    let hyper = MvgpHyper {
        kernel: kern,
        A: symmetrise(&full_a),
        B: symmetrise(&(B * c)),
        sigma: sigma * c.sqrt(),
    };
    model.set_hyper(hyper)?;
    Ok(FitReport {
        initial_log_likelihood: initial_ll,
        log_likelihood: model.log_marginal_likelihood(),
        evaluations,
        starts,
    })
}

fn symmetrise(m: &DMatrix<f64>) -> DMatrix<f64> {
    0.5 * (m + m.transpose())
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::gp::theta::random_training_rows;
    use crate::gp::{InputMap, PriorMean, Rbf};

    /// The analytic gradient of −log p against central finite differences.
    #[test]
    fn likelihood_gradient_matches_finite_differences() {
        use rand::RngExt;
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for (n, m, ra, rb) in [
            (2, 1, Rank::Full, Rank::Full),
            (3, 2, Rank::Low(1), Rank::Diagonal),
            (1, 1, Rank::Diagonal, Rank::Full),
        ] {
            let k = 15;
            let p = m + 1;
            let (zs, us, resid) = random_training_rows(&mut rng, k, n, m);
            let kernel = Rbf::new(vec![0.8; n], 1.0).unwrap();
            let layout = Layout {
                n,
                p,
                n_kern: n + 1,
                scale_idx: Some(n),
                rb: rb.cols(p),
                ra: ra.cols(n),
                learn_a: true,
                // exercise the noise floor's chain rule in one case
                sigma_min: if n == 2 { 0.05 } else { 0.0 },
            };
            let obj = Likelihood {
                layout: layout.clone(),
                kernel,
                fixed_a: DMatrix::identity(n, n),
                zs: &zs,
                us: &us,
                resid: &resid,
                k,
                d: n,
            };
            let f = |th: &[f64]| obj.eval(th).unwrap();
            let th: Vec<f64> = (0..layout.len())
                .map(|_| rng.random_range(-0.5..0.5))
                .collect();
            let (_, g) = f(&th);
            let h = 1e-6;
            for i in 0..th.len() {
                let mut tp = th.clone();
                let mut tm = th.clone();
                tp[i] += h;
                tm[i] -= h;
                let fd = (f(&tp).0 - f(&tm).0) / (2.0 * h);
                assert!(
                    (fd - g[i]).abs() < 1e-5 * (1.0 + fd.abs()),
                    "n={n} m={m} param {i}: fd {fd} analytic {}",
                    g[i]
                );
            }
            // and the value agrees with the model's own likelihood
            let (kern, a, b, sigma) = obj.unpack(&th).unwrap();
            let mut model = Mvgp::new(
                n,
                m,
                MvgpHyper {
                    kernel: kern,
                    A: a,
                    B: b,
                    sigma,
                },
                PriorMean::Zero,
                InputMap::Identity,
            )
            .unwrap();
            let u_only: Vec<f64> = us.chunks(p).flat_map(|u| u[1..].to_vec()).collect();
            model.set_data(&zs, &u_only, &resid).unwrap();
            assert!((model.log_marginal_likelihood() + f(&th).0).abs() < 1e-8);
        }
    }
}
