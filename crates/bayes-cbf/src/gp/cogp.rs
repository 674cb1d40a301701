//! Coregionalization Gaussian process (CoGP) regression of `F(x)`: the
//! baseline the paper compares the MVGP against (paper, Appendix
//! "Coregionalization Gaussian Process", Lemma and Eq. `coregionalization-posterior`;
//! Sec. VII-A).
//!
//! ## Model
//! `vec F(x) ~ GP(vec M0(x), Σ k0(x, x'))`, `Σ ∈ R^{n(1+m) × n(1+m)}` SPD, with
//! `vec` column-major (entry `(i, c)` of `F` at `i + n c`, as for the MVGP).
//! Observations `ẋ_j = F(x_j) u̲_j + w_j = (u̲_jᵀ ⊗ I_n) vec F(x_j) + w_j`,
//! `w_j ~ N(0, S)`, `S ∈ R^{n×n}` SPD.
//!
//! ## Relation to the MVGP
//! With `Σ = B ⊗ A` and `S = σ² A` the CoGP **is** the MVGP of Prop. 1: same
//! prior, same likelihood, hence the same posterior `B_k(x, x') ⊗ A` and the
//! same marginal likelihood. The CoGP pays for its generality with a
//! `kn × kn` Gram matrix (`O((kn)³)` to factor, `O((kn)² n(1+m))` per
//! posterior covariance) instead of the MVGP's `k × k`.
//!
//! ## Likelihood and gradient
//! `r = vec(Ẋ − 𝓜U̲) ~ N(0, 𝐆)`, `𝐆 = [P_i Σ P_jᵀ k0_ij]_{ij} + I_k ⊗ S`,
//! `P_j = u̲_jᵀ ⊗ I_n`:
//! `log p = −½ [rᵀ 𝐆⁻¹ r + log|𝐆| + kn log 2π]`.
//!
//! With `α = 𝐆⁻¹ r` and `Ḡ = ∂ log p/∂𝐆 = ½ (α αᵀ − 𝐆⁻¹)` (blocks `Ḡ_ij`, `n × n`):
//! - `∂ log p/∂Σ = Σ_ij k0_ij P_iᵀ Ḡ_ij P_j = Σ_ij k0_ij (u̲_i u̲_jᵀ) ⊗ Ḡ_ij`,
//! - `∂ log p/∂S = Σ_i Ḡ_ii`,
//! - `∂ log p/∂ log θ = Σ_ij ⟨Ḡ_ij, P_i Σ P_jᵀ⟩ ∂k0_ij/∂ log θ`.

use super::data::{check_batch, check_state, TrainingData};
use super::factor::{CholFactor, Jitter};
use super::input_map::InputMap;
use super::kernel::{Kernel, Rbf};
use super::mvgp::check_spd;
use super::prior::PriorMean;
use super::simd::with_faer;
use crate::error::{Error, GpError, InputError};
use faer::Mat;
use nalgebra::DMatrix;
use std::sync::OnceLock;

/// The CoGP's number of outputs `n(1 + m)`, the side of its dense `Σ`,
/// checked against [`MAX_DIMENSION`](super::MAX_DIMENSION).
pub fn cogp_outputs(n: usize, m: usize) -> Result<usize, InputError> {
    super::check_dims(n, m)?;
    let outputs = n * (m + 1);
    if outputs > super::MAX_DIMENSION {
        return Err(InputError::invalid_shown(
            "state_dim·(1 + control_dim)",
            outputs,
            &format!(
                "too large: the CoGP's output covariance Σ is dense, of side at most {}",
                super::MAX_DIMENSION
            ),
        ));
    }
    Ok(outputs)
}

/// Hyperparameters of a CoGP: `vec F ~ GP(vec M0, Σ k0)`, noise `w ~ N(0, S)`.
#[derive(Debug, Clone, PartialEq)]
#[allow(non_snake_case)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct CogpHyper<K: Kernel = Rbf> {
    /// Scalar kernel `k0`.
    pub kernel: K,
    /// Output covariance `Σ ∈ R^{n(1+m) × n(1+m)}` of `vec F` (SPD).
    pub Sigma: DMatrix<f64>,
    /// Observation-noise covariance `S ∈ R^{n×n}` (SPD).
    pub S: DMatrix<f64>,
}

impl<K: Kernel> CogpHyper<K> {
    /// Validates shapes and positivity for state dim `n`, control dim `m`,
    /// kernel input dim `d`; errors name the field (`Sigma`, `S`, ...).
    pub fn validate(&self, n: usize, m: usize, d: usize) -> Result<(), InputError> {
        cogp_outputs(n, m)?;
        if self.kernel.input_dim() != d {
            return Err(InputError::shape(
                "kernel.lengthscales",
                d,
                self.kernel.input_dim(),
            ));
        }
        check_spd("Sigma", &self.Sigma, n * (m + 1))?;
        check_spd("S", &self.S, n)?;
        Ok(())
    }
}

/// Posterior of `vec F(x)` at one point: `N(vec M_k(x), K_k(x, x))`.
#[derive(Debug, Clone, PartialEq)]
pub struct CogpPosterior {
    /// `M_k(x)`, `n × (1+m)`.
    pub mean: DMatrix<f64>,
    /// `K_k(x, x) = Cov(vec F(x))`, `n(1+m)` square.
    pub cov: DMatrix<f64>,
}

/// A CoGP model of `F(x)` with its data and factorised `kn × kn` Gram matrix.
///
/// ## Reference
/// Paper, Appendix (Coregionalization GP), Eq. `coregionalization-posterior`:
/// with `P_j = u̲_jᵀ ⊗ I_n`,
/// `𝐆 = [P_i Σ P_jᵀ k0(x_i, x_j)]_{ij} + I_k ⊗ S` (`kn × kn`),
/// `𝐊(x) = [Σ P_1ᵀ k0(x, x_1) … Σ P_kᵀ k0(x, x_k)]` (`n(1+m) × kn`),
/// `vec M_k(x) = vec M0(x) + 𝐊(x) 𝐆⁻¹ vec(Ẋ − 𝓜U̲)`,
/// `K_k(x, x') = Σ k0(x, x') − 𝐊(x) 𝐆⁻¹ 𝐊(x')ᵀ`.
///
/// ## Example
/// ```
/// use bayes_cbf::gp::{Cogp, CogpHyper, InputMap, PriorMean, Rbf};
/// use nalgebra::DMatrix;
/// let hyper = CogpHyper {
///     kernel: Rbf::new(vec![1.0, 1.0], 1.0)?,
///     Sigma: DMatrix::identity(4, 4),
///     S: DMatrix::identity(2, 2) * 0.01,
/// };
/// let mut gp = Cogp::new(2, 1, hyper, PriorMean::Zero, InputMap::Identity)?;
/// // two observations (x, u, ẋ), row-major
/// gp.set_data(&[0.1, 0.2, -0.3, 0.5], &[1.0, -1.0], &[0.2, 0.9, 0.5, -2.0])?;
/// let post = gp.posterior(&[0.0, 0.3])?;
/// assert_eq!((post.mean.shape(), post.cov.shape()), ((2, 2), (4, 4)));
/// # Ok::<(), bayes_cbf::Error>(())
/// ```
#[derive(Debug, Clone)]
pub struct Cogp<K: Kernel = Rbf> {
    n: usize,
    m: usize,
    hyper: CogpHyper<K>,
    prior: PriorMean,
    input_map: InputMap,
    /// Training data; its residuals are `vec(Ẋ − 𝓜U̲)`: entry `j n + i` is
    /// `ẋ_ji − (M0(x_j) u̲_j)_i`.
    data: TrainingData,
    /// `Σ P_jᵀ` (`n(1+m) × n`) per point: entry `(a, i)` at `j n²(1+m) + i n(1+m) + a`.
    su: Vec<f64>,
    factor: CholFactor,
    /// `β = L⁻¹ vec(Ẋ − 𝓜U̲)`, `kn × 1`.
    beta: Mat<f64>,
    /// `α = 𝐆⁻¹ vec(Ẋ − 𝓜U̲)`, computed on demand.
    alpha: OnceLock<Vec<f64>>,
}

impl<K: Kernel> Cogp<K> {
    /// A model with no data (the prior), validated.
    pub fn new(
        n: usize,
        m: usize,
        hyper: CogpHyper<K>,
        prior: PriorMean,
        input_map: InputMap,
    ) -> Result<Self, InputError> {
        super::prior::check_model_dims(n, m, &input_map, &prior)?;
        cogp_outputs(n, m)?;
        hyper.validate(n, m, input_map.output_dim(n))?;
        Ok(Self {
            n,
            m,
            hyper,
            prior,
            input_map,
            data: TrainingData::default(),
            su: Vec::new(),
            factor: CholFactor::default(),
            beta: Mat::zeros(0, 1),
            alpha: OnceLock::new(),
        })
    }

    shared_model_accessors!(CogpHyper<K>);
    /// Number of observations `k` (the Gram matrix is `kn × kn`).
    pub fn len(&self) -> usize {
        self.data.xs.len() / self.n
    }
    /// Cholesky factor of the `kn × kn` Gram matrix `𝐆`.
    pub fn factor(&self) -> &CholFactor {
        &self.factor
    }
    /// Mapped training inputs (row-major `k × d`).
    pub fn mapped_inputs(&self) -> &[f64] {
        &self.data.zs
    }
    /// `u̲_j` rows (row-major `k × (1+m)`), with the leading 1.
    pub fn augmented_controls(&self) -> &[f64] {
        &self.data.us
    }
    /// `vec(Ẋ − 𝓜U̲)` (entry `j n + i`), i.e. row-major `k × n` residuals.
    pub fn residuals(&self) -> &[f64] {
        &self.data.resid
    }

    /// Replaces the training data and factorises `𝐆` from scratch
    /// (`O((kn)³)`). `xs` is `k × n`, `us` is `k × m`, `xdot` is `k × n`, all
    /// row-major; bad shapes or non-finite values name the offending row. On
    /// any error the previous data and factor stay in place.
    pub fn set_data(&mut self, xs: &[f64], us: &[f64], xdot: &[f64]) -> Result<(), Error> {
        let (n, m) = (self.n, self.m);
        let k = check_batch(n, m, xs, us, xdot)?;
        let p = m + 1;
        let mut data = TrainingData::default();
        let mut m0 = vec![0.0; n * p];
        for j in 0..k {
            let x = &xs[j * n..(j + 1) * n];
            data.push(
                x,
                &us[j * m..(j + 1) * m],
                &xdot[j * n..(j + 1) * n],
                &self.input_map,
            );
            self.prior.eval(x, &mut m0);
            for i in 0..n {
                let pred: f64 = (0..p).map(|c| m0[i + n * c] * data.us[j * p + c]).sum();
                data.resid.push(xdot[j * n + i] - pred);
            }
        }
        let old = std::mem::replace(&mut self.data, data);
        if let Err(e) = self.refactor() {
            // keep the previous data, whose factor is still in place
            self.data = old;
            return Err(e.into());
        }
        Ok(())
    }

    /// Recomputes `Σ P_jᵀ`, the factor of `𝐆` and `β` from the stored data
    /// (`O((kn)³)`). On failure ([`GpError::IllConditioned`]) the previous
    /// factorisation is kept unchanged.
    pub fn refactor(&mut self) -> Result<(), GpError> {
        let (n, p, k) = (self.n, self.m + 1, self.len());
        let d = self.input_map.output_dim(n);
        let su = sigma_u(&self.hyper.Sigma, &self.data.us, n, p, k);
        let g = gram(
            &self.hyper.kernel,
            &self.hyper.S,
            &su,
            &self.data.zs,
            &self.data.us,
            (n, p, d, k),
        );
        let factor = CholFactor::factor(g.as_ref(), k * n)?;
        let mut beta = Mat::<f64>::from_fn(k * n, 1, |r, _| self.data.resid[r]);
        factor.solve_l(beta.as_mut());
        (self.su, self.factor, self.beta) = (su, factor, beta);
        self.alpha = OnceLock::new();
        Ok(())
    }

    /// Replaces the hyperparameters (validated) and refactorises; on a
    /// numerical failure the previous hyperparameters stay in place.
    pub fn set_hyper(&mut self, hyper: CogpHyper<K>) -> Result<(), Error> {
        hyper.validate(self.n, self.m, self.input_map.output_dim(self.n))?;
        let old = std::mem::replace(&mut self.hyper, hyper);
        if let Err(e) = self.refactor() {
            self.hyper = old;
            return Err(e.into());
        }
        Ok(())
    }

    /// `α = 𝐆⁻¹ vec(Ẋ − 𝓜U̲)`, cached until the data change.
    pub fn alpha(&self) -> &[f64] {
        self.alpha.get_or_init(|| {
            let mut a = with_faer(|| self.beta.clone());
            self.factor.solve_lt(a.as_mut());
            (0..a.nrows()).map(|r| a[(r, 0)]).collect()
        })
    }

    fn check_x(&self, field: &str, x: &[f64]) -> Result<(), InputError> {
        check_state(field, self.n, x)
    }

    fn mapped(&self, x: &[f64]) -> Vec<f64> {
        let mut z = vec![0.0; self.input_map.output_dim(self.n)];
        self.input_map.apply(x, &mut z);
        z
    }

    fn prior_mean(&self, x: &[f64]) -> DMatrix<f64> {
        let mut m0 = vec![0.0; self.n * (self.m + 1)];
        self.prior.eval(x, &mut m0);
        DMatrix::from_column_slice(self.n, self.m + 1, &m0)
    }

    /// `V = L⁻¹ 𝐊(x)ᵀ` (`kn × n(1+m)`): row `j n + i`, column `a` of
    /// `𝐊(x)ᵀ` is `k0(x, x_j) (Σ P_jᵀ)_{a i}`.
    fn v_matrix(&self, z: &[f64]) -> Mat<f64> {
        let (n, np, k) = (self.n, self.n * (self.m + 1), self.len());
        let d = z.len();
        let mut w = Mat::<f64>::zeros(k * n, np);
        for j in 0..k {
            let kv = self
                .hyper
                .kernel
                .value(z, &self.data.zs[j * d..(j + 1) * d]);
            let blk = &self.su[j * n * np..(j + 1) * n * np];
            for i in 0..n {
                for a in 0..np {
                    w[(j * n + i, a)] = kv * blk[i * np + a];
                }
            }
        }
        self.factor.solve_l(w.as_mut());
        w
    }

    /// Posterior mean `M_k(x)` only (`O(k n² (1+m))` with the cached `α`).
    pub fn posterior_mean(&self, x: &[f64]) -> Result<DMatrix<f64>, InputError> {
        self.check_x("x", x)?;
        let (n, np) = (self.n, self.n * (self.m + 1));
        let mut mean = self.prior_mean(x);
        if self.is_empty() {
            return Ok(mean);
        }
        let z = self.mapped(x);
        let d = z.len();
        let alpha = self.alpha();
        for j in 0..self.len() {
            let kv = self
                .hyper
                .kernel
                .value(&z, &self.data.zs[j * d..(j + 1) * d]);
            let blk = &self.su[j * n * np..(j + 1) * n * np];
            for i in 0..n {
                let w = kv * alpha[j * n + i];
                for a in 0..np {
                    mean[a] += w * blk[i * np + a];
                }
            }
        }
        Ok(mean)
    }

    /// Full posterior at `x`: `M_k(x)` and `K_k(x, x) = Cov(vec F(x))`.
    ///
    /// With `V = L⁻¹ 𝐊(x)ᵀ`, `β = L⁻¹ vec(Ẋ − 𝓜U̲)`:
    /// `vec M_k = vec M0 + Vᵀ β`, `K_k = Σ k0(x, x) − Vᵀ V`.
    pub fn posterior(&self, x: &[f64]) -> Result<CogpPosterior, InputError> {
        self.check_x("x", x)?;
        let (k, np) = (self.len(), self.n * (self.m + 1));
        let z = self.mapped(x);
        let mut mean = self.prior_mean(x);
        let mut cov = &self.hyper.Sigma * self.hyper.kernel.value(&z, &z);
        if k == 0 {
            return Ok(CogpPosterior { mean, cov });
        }
        let v = self.v_matrix(&z);
        let (vb, vtv) = with_faer(|| (v.transpose() * &self.beta, v.transpose() * &v));
        for a in 0..np {
            mean[a] += vb[(a, 0)];
            for b in 0..np {
                cov[(a, b)] -= 0.5 * (vtv[(a, b)] + vtv[(b, a)]);
            }
        }
        Ok(CogpPosterior { mean, cov })
    }

    /// Posterior cross-covariance `K_k(x, x') = Cov(vec F(x), vec F(x'))`.
    pub fn posterior_cov(&self, x: &[f64], x2: &[f64]) -> Result<DMatrix<f64>, InputError> {
        self.check_x("x", x)?;
        self.check_x("x2", x2)?;
        let np = self.n * (self.m + 1);
        let (z1, z2) = (self.mapped(x), self.mapped(x2));
        let mut out = &self.hyper.Sigma * self.hyper.kernel.value(&z1, &z2);
        if self.is_empty() {
            return Ok(out);
        }
        let (v1, v2) = (self.v_matrix(&z1), self.v_matrix(&z2));
        let c = with_faer(|| v1.transpose() * &v2);
        for a in 0..np {
            for b in 0..np {
                out[(a, b)] -= c[(a, b)];
            }
        }
        Ok(out)
    }

    /// Exact log marginal likelihood
    /// `log p(Ẋ) = −½ [rᵀ 𝐆⁻¹ r + log|𝐆| + kn log 2π]`, `r = vec(Ẋ − 𝓜U̲)`
    /// (0 without data).
    pub fn log_marginal_likelihood(&self) -> f64 {
        let kn = self.len() * self.n;
        if kn == 0 {
            return 0.0;
        }
        let quad: f64 = (0..kn).map(|r| self.beta[(r, 0)].powi(2)).sum();
        -0.5 * (quad + self.factor.log_det() + kn as f64 * (2.0 * std::f64::consts::PI).ln())
    }
}

/// Value and gradient of the CoGP log marginal likelihood with respect to
/// the matrices themselves (entries treated as independent, so a symmetric
/// perturbation `dΣ` changes `log p` by `⟨Σ̄, dΣ⟩`).
#[derive(Debug, Clone, PartialEq)]
#[allow(non_snake_case)]
pub struct CogpGradient {
    /// `log p(Ẋ)`.
    pub log_likelihood: f64,
    /// `∂ log p/∂ log θ` for every kernel hyperparameter (`Kernel::log_hyper` order).
    pub kernel_log_hyper: Vec<f64>,
    /// `∂ log p/∂Σ`, `n(1+m)` square, symmetric.
    pub Sigma: DMatrix<f64>,
    /// `∂ log p/∂S`, `n × n`, symmetric.
    pub S: DMatrix<f64>,
}

/// Training data of a CoGP as seen by the likelihood: mapped inputs
/// (`k × d`), augmented controls (`k × p`), residuals `vec(Ẋ − 𝓜U̲)`.
#[derive(Clone, Copy)]
pub(crate) struct CogpData<'a> {
    pub n: usize,
    pub p: usize,
    pub d: usize,
    pub k: usize,
    pub zs: &'a [f64],
    pub us: &'a [f64],
    pub resid: &'a [f64],
}

/// Log marginal likelihood and its gradient (module docs).
#[allow(non_snake_case)]
pub(crate) fn lml_grad<K: Kernel>(
    data: &CogpData<'_>,
    kernel: &K,
    Sigma: &DMatrix<f64>,
    S: &DMatrix<f64>,
    jitter: Jitter,
) -> Result<CogpGradient, GpError> {
    let CogpData {
        n,
        p,
        d,
        k,
        zs,
        us,
        resid,
    } = *data;
    let (np, kn) = (n * p, k * n);
    let su = sigma_u(Sigma, us, n, p, k);
    let g = gram(kernel, S, &su, zs, us, (n, p, d, k));
    let factor = CholFactor::factor_with(g.as_ref(), kn, jitter)?;
    drop(g);
    let mut alpha = Mat::<f64>::from_fn(kn, 1, |r, _| resid[r]);
    factor.solve_l(alpha.as_mut());
    let quad: f64 = (0..kn).map(|r| alpha[(r, 0)].powi(2)).sum();
    factor.solve_lt(alpha.as_mut());
    let ll = -0.5 * (quad + factor.log_det() + kn as f64 * (2.0 * std::f64::consts::PI).ln());
    // Ḡ = ½ (α αᵀ − 𝐆⁻¹), with 𝐆⁻¹ = L⁻ᵀ L⁻¹
    let mut gbar = factor.inverse_mat();
    for c in 0..kn {
        for r in c..kn {
            let v = 0.5 * (alpha[(r, 0)] * alpha[(c, 0)] - gbar[(r, c)]);
            gbar[(r, c)] = v;
            gbar[(c, r)] = v;
        }
    }
    let nh = kernel.n_hyper();
    let mut g_kern = vec![0.0; nh];
    let mut gh = vec![0.0; nh];
    let mut sbar = DMatrix::<f64>::zeros(n, n);
    let mut sigbar = DMatrix::<f64>::zeros(np, np);
    let mut blk = vec![0.0; n * n];
    for j in 0..k {
        let (zj, uj) = (&zs[j * d..(j + 1) * d], &us[j * p..(j + 1) * p]);
        let su_j = &su[j * n * np..(j + 1) * n * np];
        for i in 0..k {
            let (zi, ui) = (&zs[i * d..(i + 1) * d], &us[i * p..(i + 1) * p]);
            let kv = kernel.grad_log_hyper(zi, zj, &mut gh);
            block_psp(ui, su_j, n, &mut blk);
            let mut inner = 0.0;
            for r in 0..n {
                for s in 0..n {
                    let gb = gbar[(i * n + r, j * n + s)];
                    inner += gb * blk[r * n + s];
                    // Σ̄ block (c, c') += k0_ij u_ic u_jc' Ḡ_ij
                    for (c, uic) in ui.iter().enumerate() {
                        let w = kv * uic * gb;
                        for (c2, ujc) in uj.iter().enumerate() {
                            sigbar[(r + n * c, s + n * c2)] += w * ujc;
                        }
                    }
                    if i == j {
                        sbar[(r, s)] += gb;
                    }
                }
            }
            for (a, g) in g_kern.iter_mut().zip(&gh) {
                *a += inner * g;
            }
        }
    }
    Ok(CogpGradient {
        log_likelihood: ll,
        kernel_log_hyper: g_kern,
        Sigma: 0.5 * (&sigbar + sigbar.transpose()),
        S: 0.5 * (&sbar + sbar.transpose()),
    })
}

impl<K: Kernel> Cogp<K> {
    /// The log marginal likelihood and its analytic gradient with respect to
    /// the kernel's log hyperparameters, `Σ` and `S` (see [`CogpGradient`]).
    ///
    /// Costs `O((kn)³)`: it forms `𝐆⁻¹` explicitly.
    pub fn log_marginal_likelihood_gradient(&self) -> Result<CogpGradient, Error> {
        let (n, p) = (self.state_dim(), self.control_dim() + 1);
        let k = self.len();
        if k == 0 {
            return Err(GpError::NoData.into());
        }
        let data = CogpData {
            n,
            p,
            d: self.input_map().output_dim(n),
            k,
            zs: self.mapped_inputs(),
            us: self.augmented_controls(),
            resid: self.residuals(),
        };
        let h = self.hyper();
        Ok(lml_grad(
            &data,
            &h.kernel,
            &h.Sigma,
            &h.S,
            Jitter::Escalate,
        )?)
    }
}

/// `Σ P_jᵀ = Σ (u̲_j ⊗ I_n)` for every point: `n(1+m) × n` blocks, entry
/// `(a, i)` of block `j` at `j n²(1+m) + i n(1+m) + a`.
pub(crate) fn sigma_u(sigma: &DMatrix<f64>, us: &[f64], n: usize, p: usize, k: usize) -> Vec<f64> {
    let np = n * p;
    let mut su = vec![0.0; k * n * np];
    for j in 0..k {
        let u = &us[j * p..(j + 1) * p];
        let blk = &mut su[j * n * np..(j + 1) * n * np];
        for i in 0..n {
            for a in 0..np {
                blk[i * np + a] = (0..p).map(|c| sigma[(a, i + n * c)] * u[c]).sum();
            }
        }
    }
    su
}

/// Block `P_i Σ P_jᵀ` (`n × n`, row-major) of the noise-free Gram matrix
/// before the kernel factor: entry `(r, s) = Σ_c u_ic (Σ P_jᵀ)_{r + nc, s}`.
#[inline]
pub(crate) fn block_psp(ui: &[f64], su_j: &[f64], n: usize, out: &mut [f64]) {
    let np = n * ui.len();
    for r in 0..n {
        for s in 0..n {
            out[r * n + s] = ui
                .iter()
                .enumerate()
                .map(|(c, uc)| uc * su_j[s * np + r + n * c])
                .sum();
        }
    }
}

/// The `kn × kn` Gram matrix `𝐆 = [P_i Σ P_jᵀ k0(z_i, z_j)]_{ij} + I_k ⊗ S`
/// (lower triangle and diagonal blocks filled). `dims = (n, p, d, k)`.
pub(crate) fn gram<K: Kernel>(
    kernel: &K,
    s: &DMatrix<f64>,
    su: &[f64],
    zs: &[f64],
    us: &[f64],
    dims: (usize, usize, usize, usize),
) -> Mat<f64> {
    let (n, p, d, k) = dims;
    let np = n * p;
    let mut g = Mat::<f64>::zeros(k * n, k * n);
    let mut blk = vec![0.0; n * n];
    for j in 0..k {
        let su_j = &su[j * n * np..(j + 1) * n * np];
        for i in j..k {
            let kv = kernel.value(&zs[i * d..(i + 1) * d], &zs[j * d..(j + 1) * d]);
            block_psp(&us[i * p..(i + 1) * p], su_j, n, &mut blk);
            for r in 0..n {
                for c in 0..n {
                    let mut v = kv * blk[r * n + c];
                    if i == j {
                        v += s[(r, c)];
                    }
                    g[(i * n + r, j * n + c)] = v;
                }
            }
        }
    }
    g
}
