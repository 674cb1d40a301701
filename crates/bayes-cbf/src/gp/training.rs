//! Hyperparameter learning for the MVGP by maximising the exact marginal
//! likelihood with an analytic gradient (projected L-BFGS, [`optimise`](super::optimise)).
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
//! carried by `B`), and `A`'s first Cholesky pivot is held at 1 (`A_00 = 1`;
//! for a diagonal or low-rank `A`, `v_0 = 1`). `A` and `B` are
//! parameterised by their Cholesky factors with logarithmic diagonals (or a
//! lower-trapezoidal low-rank factor plus a diagonal), a bijection with no
//! flat directions (`psd` module). After fitting, the equivalent model with
//! `tr A = n` is reported.
//!
//! `θ = [log ℓ (kernel, without scale), log σ, θ_B, θ_A]`
//! ([`MvgpLikelihood`]).
//!
//! ## Bounds
//! The optimiser works on a box, and a parameter that reaches its bound
//! stops there at no cost:
//! - `ℓ_i ∈ [s_i/10³, 10³ s_i]`, `s_i` the standard deviation of kernel
//!   input `i` (at least `10⁻³`);
//! - `σ ∈ [max(σ_min, 10⁻⁶ ρ), 10³ ρ]`, `ρ` the root mean square of the
//!   residuals `R`; the noise variance in `G` is `σ² + ε·mean_j K_jj`
//!   with `ε = 10⁻¹⁰`, which keeps `G` at a condition number that a
//!   Cholesky factorisation resolves (above the pivot floor of the factor)
//!   however small `σ` gets;
//! - the logarithmic diagonal entries of the factors of `A` and `B` within
//!   `10⁶` of their start's scale (standard deviations; `psd` module),
//!   which keeps both numerically positive definite; their off-diagonal
//!   entries are free.
//!
//! ## Cost of one evaluation
//! One Cholesky factorisation of `G` (`k³/3` flops), the inverse `S`
//! (`⅔k³`), triangular solves for `α` (`2k²n`) and one pass over the lower
//! triangle for all gradient terms (`O(k²(d + 1 + m))`), in a workspace
//! allocated once per fit: an evaluation allocates nothing that grows
//! with `k`.

use super::factor::{factor_in_place, inverse_in_place, DenseScratch, Jitter};
use super::kernel::{sum_by_4, Kernel, Rbf};
use super::mvgp::{Mvgp, MvgpHyper};
use super::optimise::{
    multi_start_ranked, perturb, EvalFailure, Harness, Objective, RunSettings, StartPlan,
};
use super::psd::{PsdParam, SCALE_RANGE};
use super::simd::with_faer;
use super::theta::{input_spreads, kernel_bounds, kernel_from_free, pack_free, start_from_inputs};
use crate::error::{check_nonnegative, Error, GpError, InputError};
use faer::linalg::triangular_solve::{
    solve_lower_triangular_in_place, solve_upper_triangular_in_place,
};
use faer::{MatMut, MatRef, Par};
use nalgebra::DMatrix;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::sync::atomic::AtomicBool;

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
    /// Checks that a low rank is at most `dim`, the size of the matrix it
    /// parameterises (named `field`, of dimension `what`).
    pub fn check(self, field: &str, dim: usize, what: &str) -> Result<(), InputError> {
        match self {
            Rank::Low(r) if r == 0 || r > dim => Err(InputError::invalid_shown(
                field,
                r,
                &format!("a low rank must be between 1 and {what} = {dim}"),
            )),
            _ => Ok(()),
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
    /// Extra random restarts besides the first start (the data-driven one,
    /// or the model's own hyperparameters where they are better: [`fit`]).
    pub restarts: usize,
    /// Seed of the random initialisation of the off-diagonal factors and of
    /// the restarts.
    pub seed: u64,
    /// Learn `A` (otherwise it is held at its current value).
    pub learn_a: bool,
    /// Initialise from the model's current hyperparameters instead of the
    /// data-driven heuristic.
    pub warm_start: bool,
    /// With `warm_start`: how far, as a factor either way, the fit may move
    /// each scale from its current value (the lengthscales, `σ`, and the
    /// standard deviations `√A_ii`, `√B_ii` through the diagonals of their
    /// factors). An online refit on a short stretch of closed-loop data
    /// then adapts the hyperparameters instead of replacing them: on such
    /// data the likelihood is often unbounded (a trajectory at a nearly
    /// constant heading makes `A` tend to singular), and the fit would
    /// otherwise stop wherever the wide bounds of a cold start are.
    /// `f64::INFINITY` keeps the cold-start bounds.
    pub warm_range: f64,
    /// Floor of the noise: the noise standard deviation of state component
    /// 0, `σ √A₀₀ ≥ σ_min`. The fit's parameterisation fixes `A₀₀ = 1`,
    /// where this is a bound of the optimiser (besides the floor `10⁻⁶ ×`
    /// the residuals' root mean square that every fit has; module docs).
    /// The fitted model scales `A` to trace `n`, so its `σ` itself is below
    /// `σ_min` when `A₀₀ > 1`. A floor keeps the Gram matrix well
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
            warm_range: 10.0,
            sigma_min: 0.0,
        }
    }
}

impl FitSettings {
    /// Checks the settings.
    pub fn validate(&self) -> Result<(), InputError> {
        super::optimise::check_run_settings(self.max_iters, self.restarts)?;
        check_nonnegative("sigma_min", self.sigma_min)?;
        if self.sigma_min > super::MAX_DATA_MAGNITUDE {
            return Err(InputError::invalid(
                "sigma_min",
                self.sigma_min,
                "must be at most 1e150 (the noise variance σ² it floors must be finite)",
            ));
        }
        if self.warm_range.is_nan() || self.warm_range < 1.0 {
            return Err(InputError::invalid(
                "warm_range",
                self.warm_range,
                "must be ≥ 1",
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

/// Layout of θ: `[log ℓ (free kernel hyperparameters), log σ, θ_B, θ_A]`.
#[derive(Debug, Clone)]
struct Layout {
    /// Free kernel hyperparameters (all but the output scale).
    kern_free: usize,
    scale_idx: Option<usize>,
    b: PsdParam,
    /// `None` when `A` is held fixed.
    a: Option<PsdParam>,
}

impl Layout {
    fn off_sigma(&self) -> usize {
        self.kern_free
    }
    fn off_b(&self) -> usize {
        self.kern_free + 1
    }
    fn off_a(&self) -> usize {
        self.off_b() + self.b.len()
    }
    fn len(&self) -> usize {
        self.off_a() + self.a.as_ref().map_or(0, PsdParam::len)
    }
}

/// Buffers of one evaluation at a fixed `k` (module docs: no allocation
/// that grows with `k`). `k × k` matrices are column-major slices.
struct Workspace {
    k: usize,
    /// Factor of the pivot floor of the exact factorisation
    /// ([`Jitter::Exact`]): 1 while fitting, more for the final check.
    pivot_margin: f64,
    /// `G`, then its Cholesky factor `L` (lower triangle).
    gram: Vec<f64>,
    /// `k0(x_i, x_j)` (lower triangle).
    k0: Vec<f64>,
    /// `S = G⁻¹`, then `Ḡ = ∂ log p/∂G` (lower triangle).
    inv: Vec<f64>,
    /// `L⁻¹ Rᵀ`, then `α = G⁻¹ Rᵀ` (`k × n`).
    alpha: Vec<f64>,
    /// `α A⁻¹` (`k × n`, row-major).
    gamma: Vec<f64>,
    /// `B u̲_j` (`k × (1+m)`, row-major).
    bu: Vec<f64>,
    /// `σ²` of the last evaluation.
    noise: f64,
    /// `Ḡ_ij` and the kernel weights of the current column `j` (`k`).
    gcol: Vec<f64>,
    wcol: Vec<f64>,
    /// Kernel gradient accumulator and scratch.
    kern_acc: Vec<f64>,
    kern_scratch: Vec<f64>,
    dense: DenseScratch,
}

impl Workspace {
    /// Factorises `G = (u̲_iᵀ B u̲_j) k0_ij + σ² δ_ij` (from `k0`, `B u̲` and
    /// `σ²` in the workspace) in place in `gram`, without jitter. With
    /// `fresh = (kernel, zs, d)`, each column of `k0` is first computed from
    /// the kernel inputs `zs` (`k × d`) in the same pass.
    fn factor_gram<K: Kernel>(
        &mut self,
        u_cols: &[f64],
        p: usize,
        fresh: Option<(&K, &[f64], usize)>,
    ) -> Result<f64, GpError> {
        let k = self.k;
        let (k0, bu, s2, q) = (&mut self.k0, &self.bu, self.noise, &mut self.wcol);
        let gram = MatMut::from_column_major_slice_mut(&mut self.gram, k, k);
        factor_in_place(
            gram,
            &mut self.dense,
            Jitter::Exact(self.pivot_margin),
            |mut g| {
                for j in 0..k {
                    let (buj, k0j) = (&bu[j * p..(j + 1) * p], &mut k0[j * k + j..(j + 1) * k]);
                    if let Some((kern, zs, d)) = fresh {
                        let zj = &zs[j * d..(j + 1) * d];
                        for (o, zi) in k0j.iter_mut().zip(zs[j * d..].chunks_exact(d)) {
                            *o = kern.value(zi, zj);
                        }
                    }
                    // q_i = u̲_iᵀ B u̲_j
                    let q = &mut q[..k - j];
                    q.fill(0.0);
                    for (c, bc) in buj.iter().enumerate() {
                        for (qi, ui) in q.iter_mut().zip(&u_cols[c * k + j..(c + 1) * k]) {
                            *qi += bc * ui;
                        }
                    }
                    let gj = g
                        .as_mut()
                        .col_mut(j)
                        .try_as_col_major_mut()
                        .expect("the Gram buffer is column-major")
                        .as_slice_mut();
                    for ((o, kv), qi) in gj[j..].iter_mut().zip(k0j.iter()).zip(q.iter()) {
                        *o = qi * kv;
                    }
                    gj[j] += s2;
                }
            },
        )
    }
}

/// The negative log marginal likelihood `−log p(θ)` of an MVGP's data and
/// its gradient, over the parameter vector `θ` of the fit (module docs):
/// the objective [`fit`] minimises, for use with any other optimiser.
///
/// `θ = [log ℓ (the kernel's log hyperparameters without its output
/// scale), log σ, θ_B, θ_A]`, where `θ_B` and `θ_A` are the Cholesky factors
/// of `B` and `A` with logarithmic diagonals, row by row (`[log L_00, L_10,
/// log L_11, …]`; `A`'s `log L_00` is held at 0 and left out), or for a
/// low-rank or diagonal [`Rank`] the lower-trapezoidal factor `C` row by
/// row followed by `log v`. Only the learned rows of `A` enter
/// ([`Mvgp::with_known_rows`]); with `learn_a` off, `θ_A` is empty.
///
/// ## Reference
/// Paper, Sec. IV (marginal likelihood of Eq. 11).
pub struct MvgpLikelihood<'a, K: Kernel = Rbf> {
    layout: Layout,
    /// The kernel with the output scale held fixed.
    kernel: K,
    /// `A` on the learned rows when it is not learned.
    fixed_a: DMatrix<f64>,
    zs: &'a [f64],
    us: &'a [f64],
    /// `U̲` column by column (`(1+m) × k`).
    u_cols: Vec<f64>,
    /// Residuals on the learned rows (`k × n`, row-major).
    resid: Vec<f64>,
    k: usize,
    /// Learned rows.
    n: usize,
    p: usize,
    d: usize,
    lower: Vec<f64>,
    upper: Vec<f64>,
    start: Vec<f64>,
    /// Standard deviations of the kernel inputs ([`input_spreads`]).
    spreads: Vec<f64>,
    /// The model's `A` (all rows) and its learned rows, for [`hyper`](Self::hyper).
    full_a: DMatrix<f64>,
    rows: Vec<usize>,
    work: Workspace,
}

impl<'a, K: Kernel> MvgpLikelihood<'a, K> {
    /// The likelihood of `model`'s data over the parameterisation that
    /// `settings` describes (ranks of `A` and `B`, whether `A` is learned,
    /// the noise floor), with the start point of [`fit`]: the model's own
    /// hyperparameters with `warm_start`, else the data-driven heuristic
    /// (lengthscales at the inputs' spreads, `B = (E r²/E‖u̲‖²) I`, `A = I`,
    /// `σ² = 0.01 E r²`), low-rank factors drawn from `settings.seed`.
    #[allow(non_snake_case)]
    pub fn new(model: &'a Mvgp<K>, settings: &FitSettings) -> Result<Self, Error> {
        settings.validate()?;
        let k = model.len();
        if k == 0 {
            return Err(InputError::shape("data", "at least one observation to fit", 0).into());
        }
        let n_state = model.state_dim();
        let p = model.control_dim() + 1;
        let d = model.input_map().output_dim(n_state);
        let rows = model.learned_rows();
        let n = rows.len();
        settings.rank_b.check("rank_b", p, "1 + control_dim")?;
        settings
            .rank_a
            .check("rank_a", n, "the number of learned rows")?;
        let a_learned = DMatrix::from_fn(n, n, |i, j| model.hyper().A[(rows[i], rows[j])]);
        let kernel = model.hyper().kernel.clone();
        let scale_idx = kernel.scale_index();
        let layout = Layout {
            kern_free: kernel.n_hyper() - usize::from(scale_idx.is_some()),
            scale_idx,
            b: PsdParam::new(p, settings.rank_b),
            a: (settings.learn_a && n > 0).then(|| PsdParam::fixed_first(n, settings.rank_a)),
        };
        let all_resid = model.residuals();
        let resid: Vec<f64> = (0..k)
            .flat_map(|j| rows.iter().map(move |&i| all_resid[j * n_state + i]))
            .collect();
        let (zs, us) = (model.mapped_inputs(), model.augmented_controls());
        let mean_r2 =
            (resid.iter().map(|r| r * r).sum::<f64>() / resid.len().max(1) as f64).max(1e-24);
        let mean_u2 = us
            .chunks(p)
            .map(|u| u.iter().map(|v| v * v).sum::<f64>())
            .sum::<f64>()
            / k as f64;
        // bounds (module docs); a warm start narrows them around the
        // current values (FitSettings::warm_range)
        let len = layout.len();
        let (mut lower, mut upper) = (vec![f64::NEG_INFINITY; len], vec![f64::INFINITY; len]);
        let warm = settings.warm_start && n > 0;
        let spreads = input_spreads(zs, k, d);
        kernel_bounds(
            kernel.n_hyper(),
            scale_idx,
            &spreads,
            &mut lower,
            &mut upper,
        );
        let rms = mean_r2.sqrt();
        let sigma_lo = settings.sigma_min.max(SIGMA_FLOOR * rms);
        lower[layout.off_sigma()] = sigma_lo.ln();
        upper[layout.off_sigma()] = (SIGMA_CEILING * rms).max(10.0 * sigma_lo).ln();
        // start point
        let mut rng = ChaCha8Rng::seed_from_u64(settings.seed);
        let mut start = vec![0.0; len];
        let mut kh = kernel.log_hyper();
        if !settings.warm_start {
            start_from_inputs(&mut kh, zs, k, d, scale_idx);
        }
        pack_free(&kh, scale_idx, &mut start);
        let mut kernel_start = kernel.clone();
        kernel_start.set_log_hyper(&kh)?;
        let (a0, b0, sigma0) = if settings.warm_start && n > 0 {
            // the equivalent model with A_00 = 1
            let h = model.hyper();
            let c = a_learned[(0, 0)];
            (&a_learned / c, &h.B * c, h.sigma * c.sqrt())
        } else {
            (
                DMatrix::identity(n, n),
                DMatrix::identity(p, p) * (mean_r2 / mean_u2.max(1e-12)),
                (0.01 * mean_r2).sqrt(),
            )
        };
        start[layout.off_sigma()] = sigma0.max(1e-300).ln();
        let range = if warm {
            settings.warm_range
        } else {
            SCALE_RANGE
        };
        let (ob, oa) = (layout.off_b(), layout.off_a());
        layout.b.init(&b0, &mut rng, &mut start[ob..oa]);
        layout
            .b
            .bounds(&b0, range, &mut lower[ob..oa], &mut upper[ob..oa]);
        if let Some(a) = &layout.a {
            a.init(&a0, &mut rng, &mut start[oa..]);
            a.bounds(&a0, range, &mut lower[oa..], &mut upper[oa..]);
        }
        if warm {
            // the kernel's free parameters and σ_f within the range of their
            // current values (and inside the cold-start bounds where the
            // current value is)
            let r = settings.warm_range.ln();
            for i in (0..layout.kern_free).chain([layout.off_sigma()]) {
                let (lo, hi) = (start[i] - r, start[i] + r);
                lower[i] = if start[i] >= lower[i] {
                    lower[i].max(lo)
                } else {
                    lo
                };
                upper[i] = if start[i] <= upper[i] {
                    upper[i].min(hi)
                } else {
                    hi
                };
            }
            lower[layout.off_sigma()] = lower[layout.off_sigma()].max(sigma_lo.ln());
            upper[layout.off_sigma()] = upper[layout.off_sigma()].max(lower[layout.off_sigma()]);
        }
        for ((t, l), u) in start.iter_mut().zip(&lower).zip(&upper) {
            *t = t.clamp(*l, *u);
        }
        let work = Workspace {
            k,
            pivot_margin: 1.0,
            gram: vec![0.0; k * k],
            k0: vec![0.0; k * k],
            inv: vec![0.0; k * k],
            alpha: vec![0.0; k * n],
            gamma: vec![0.0; k * n],
            bu: vec![0.0; k * p],
            noise: f64::NAN,
            gcol: vec![0.0; k],
            wcol: vec![0.0; k],
            kern_acc: vec![0.0; kernel.n_hyper()],
            kern_scratch: vec![0.0; kernel.n_hyper()],
            dense: DenseScratch::new(k),
        };
        let u_cols = (0..p)
            .flat_map(|c| us.chunks_exact(p).map(move |u| u[c]))
            .collect();
        Ok(Self {
            layout,
            kernel: kernel_start,
            fixed_a: a_learned,
            zs,
            us,
            u_cols,
            resid,
            k,
            n,
            p,
            d,
            lower,
            upper,
            start,
            spreads,
            full_a: model.hyper().A.clone(),
            rows,
            work,
        })
    }

    /// Length of `θ`.
    pub fn dim(&self) -> usize {
        self.start.len()
    }

    /// `hyper` (a model's own hyperparameters) as a point `θ` of this
    /// parameterisation, clamped into the bounds: the equivalent model with
    /// the kernel's output scale of the parameterisation (`B` absorbs the
    /// rest), `A_00 = 1` when `A` is learned, and `σ_f² = σ² − ε·signal`.
    /// Exact, inside the bounds, for full and diagonal ranks; a low-rank
    /// factor starts small and random (`seed`), as at [`start`](Self::start).
    #[allow(non_snake_case)]
    pub fn point_of(&self, hyper: &MvgpHyper<K>, seed: u64) -> Result<Vec<f64>, Error> {
        let l = &self.layout;
        let mut th = vec![0.0; self.dim()];
        let kh = hyper.kernel.log_hyper();
        pack_free(&kh, l.scale_idx, &mut th);
        let scale = l
            .scale_idx
            .map_or(1.0, |i| (kh[i] - self.kernel.log_hyper()[i]).exp());
        let rows = &self.rows;
        let A = DMatrix::from_fn(self.n, self.n, |i, j| hyper.A[(rows[i], rows[j])]);
        let c = if l.a.is_some() { A[(0, 0)] } else { 1.0 };
        let B = &hyper.B * (scale * c);
        let kernel = kernel_from_free(&self.kernel, &th, l.scale_idx)?;
        let signal = self.mean_signal(&kernel, &B);
        let sigma2 = hyper.sigma * hyper.sigma * c;
        th[l.off_sigma()] = 0.5 * (sigma2 - NOISE_TO_SIGNAL * signal).max(1e-300).ln();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (ob, oa) = (l.off_b(), l.off_a());
        l.b.init(&B, &mut rng, &mut th[ob..oa]);
        if let Some(a) = &l.a {
            a.init(&(A / c), &mut rng, &mut th[oa..]);
        }
        for ((t, lo), hi) in th.iter_mut().zip(&self.lower).zip(&self.upper) {
            *t = t.clamp(*lo, *hi);
        }
        Ok(th)
    }

    /// The start point of [`fit`] (inside the bounds).
    pub fn start(&self) -> &[f64] {
        &self.start
    }

    /// Lower and upper bounds of `θ` (module docs; infinite where free).
    pub fn bounds(&self) -> (&[f64], &[f64]) {
        (&self.lower, &self.upper)
    }

    /// `−log p(θ)`, with `−∇θ log p(θ)` written into `grad` (length
    /// [`dim`](Self::dim)). Fails with [`GpError::NotEvaluable`] where the
    /// likelihood is not defined (e.g. `G` does not factorise).
    #[track_caller]
    pub fn evaluate(&mut self, theta: &[f64], grad: &mut [f64]) -> Result<f64, Error> {
        assert!(
            theta.len() == self.dim() && grad.len() == self.dim(),
            "θ and its gradient must have length {}",
            self.dim()
        );
        self.eval(theta, grad)
            .map_err(|e| GpError::NotEvaluable(e.to_string()).into())
    }

    /// The floor of an evaluation's cost, for benchmarks: factorises the
    /// Gram matrix of the last [`evaluate`](Self::evaluate) again (one
    /// Cholesky factorisation) and inverts it, in the same buffers and with
    /// the same calls as an evaluation, without the rest (kernel values,
    /// solves and gradient terms). Fails if nothing was evaluated yet.
    pub fn floor(&mut self) -> Result<(), Error> {
        if self.work.noise.is_nan() {
            return Err(GpError::NotEvaluable("no evaluation yet".into()).into());
        }
        let k = self.k;
        self.work.factor_gram::<K>(&self.u_cols, self.p, None)?;
        let l = MatRef::from_column_major_slice(&self.work.gram, k, k);
        inverse_in_place(
            MatMut::from_column_major_slice_mut(&mut self.work.inv, k, k),
            l,
            &mut self.work.dense,
        );
        Ok(())
    }

    /// The kernel, `A` (learned rows), `B` and `σ` at `θ`.
    #[allow(non_snake_case)]
    fn unpack(&self, th: &[f64]) -> Result<(K, DMatrix<f64>, DMatrix<f64>, f64), InputError> {
        let l = &self.layout;
        let kern = kernel_from_free(&self.kernel, th, l.scale_idx)?;
        let sigma = th[l.off_sigma()].exp();
        let B = l.b.matrix(&th[l.off_b()..l.off_a()]);
        let A = match &l.a {
            Some(a) => a.matrix(&th[l.off_a()..]),
            None => self.fixed_a.clone(),
        };
        Ok((kern, A, B, sigma))
    }

    /// The mean signal variance `(1/k) Σ_j u̲_jᵀ B u̲_j k0(z_j, z_j)` of the
    /// data under `kernel` and `B`, which scales the noise floor `ε`.
    #[allow(non_snake_case)]
    fn mean_signal(&self, kernel: &K, B: &DMatrix<f64>) -> f64 {
        let (p, d) = (self.p, self.d);
        (0..self.k)
            .map(|j| {
                let (u, z) = (&self.us[j * p..(j + 1) * p], &self.zs[j * d..(j + 1) * d]);
                quad(u, B) * kernel.value(z, z)
            })
            .sum::<f64>()
            / self.k as f64
    }

    /// The hyperparameters at `θ`, as the equivalent model with `tr A = n`
    /// over the learned rows (known rows keep a zero coupling).
    #[allow(non_snake_case)]
    pub fn hyper(&self, theta: &[f64]) -> Result<MvgpHyper<K>, Error> {
        let (kernel, A, B, sigma_f) = self.unpack(theta)?;
        let signal = self.mean_signal(&kernel, &B);
        let sigma = (sigma_f * sigma_f + NOISE_TO_SIGNAL * signal).sqrt();
        let n = self.n;
        let c = if n > 0 { A.trace() / n as f64 } else { 1.0 };
        let mut full_a = self.full_a.clone();
        for (i, &ri) in self.rows.iter().enumerate() {
            for j in 0..full_a.ncols() {
                if !self.rows.contains(&j) {
                    full_a[(ri, j)] = 0.0;
                    full_a[(j, ri)] = 0.0;
                }
            }
            for (j, &rj) in self.rows.iter().enumerate() {
                full_a[(ri, rj)] = A[(i, j)] / c;
            }
        }
        Ok(MvgpHyper {
            kernel,
            A: symmetrise(&full_a),
            B: symmetrise(&(B * c)),
            sigma: sigma * c.sqrt(),
        })
    }
}

/// Factor of the pivot floor the fit's result must meet (fit).
const FINAL_PIVOT_MARGIN: f64 = 4.0;

/// Floor of the free noise scale `σ_f` relative to the residuals' root mean
/// square (module docs).
const SIGMA_FLOOR: f64 = 1e-6;
/// `ε`: the noise variance is at least `ε` times the mean signal variance
/// `s̄ = mean_j K_jj` (module docs).
const NOISE_TO_SIGNAL: f64 = 1e-10;
/// Ceiling of `σ` relative to the residuals' root mean square.
const SIGMA_CEILING: f64 = 1e3;

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// `uᵀ M u`.
fn quad(u: &[f64], m: &DMatrix<f64>) -> f64 {
    (0..u.len())
        .map(|a| u[a] * (0..u.len()).map(|b| m[(a, b)] * u[b]).sum::<f64>())
        .sum()
}

/// Column `j` of a column-major `k × k` buffer.
#[inline]
fn col(buf: &[f64], k: usize, j: usize) -> &[f64] {
    &buf[j * k..(j + 1) * k]
}

impl<K: Kernel> Objective for MvgpLikelihood<'_, K> {
    fn bounds(&self) -> (&[f64], &[f64]) {
        (&self.lower, &self.upper)
    }

    /// `(−log p, −∇θ log p)` (module docs).
    #[allow(non_snake_case)]
    fn eval(&mut self, th: &[f64], grad: &mut [f64]) -> Result<f64, EvalFailure> {
        let (kern, A, B, sigma) = self.unpack(th).map_err(|_| EvalFailure::InvalidHyper)?;
        let (n, p, k, d) = (self.n, self.p, self.k, self.d);
        let (zs, us) = (self.zs, self.us);
        let z = |i: usize| &zs[i * d..(i + 1) * d];
        let u = |i: usize| &us[i * p..(i + 1) * p];
        let w = &mut self.work;
        // B u̲_j; σ² = σ_f² + ε s̄ (module docs), s̄ the mean of K's diagonal
        let mut signal = 0.0;
        for j in 0..k {
            let uj = u(j);
            for a in 0..p {
                w.bu[j * p + a] = (0..p).map(|c| B[(a, c)] * uj[c]).sum();
            }
            signal += dot(uj, &w.bu[j * p..(j + 1) * p]) * kern.value(z(j), z(j));
        }
        let s2 = sigma * sigma + NOISE_TO_SIGNAL * signal / k as f64;
        w.noise = s2;
        w.factor_gram(&self.u_cols, p, Some((&kern, zs, d)))
            .map_err(|_| EvalFailure::NotPositiveDefinite)?;
        let l = MatRef::from_column_major_slice(&w.gram, k, k);
        let log_det_g = 2.0 * (0..k).map(|i| w.gram[i * k + i].ln()).sum::<f64>();
        // β = L⁻¹ Rᵀ, Q = βᵀβ, α = L⁻ᵀ β
        for j in 0..k {
            for i in 0..n {
                w.alpha[i * k + j] = self.resid[j * n + i];
            }
        }
        let mut alpha = MatMut::from_column_major_slice_mut(&mut w.alpha, k, n);
        with_faer(|| solve_lower_triangular_in_place(l, alpha.as_mut(), Par::Seq));
        let Q = DMatrix::from_fn(n, n, |a, b| {
            col(&w.alpha, k, a)
                .iter()
                .zip(col(&w.alpha, k, b))
                .map(|(x, y)| x * y)
                .sum::<f64>()
        });
        let mut alpha = MatMut::from_column_major_slice_mut(&mut w.alpha, k, n);
        with_faer(|| solve_upper_triangular_in_place(l.transpose(), alpha.as_mut(), Par::Seq));
        inverse_in_place(
            MatMut::from_column_major_slice_mut(&mut w.inv, k, k),
            l,
            &mut w.dense,
        );
        let chol_a = A
            .clone()
            .cholesky()
            .ok_or(EvalFailure::NotPositiveDefinite)?;
        let Ainv = chol_a.inverse();
        let logdet_a = 2.0 * chol_a.l().diagonal().iter().map(|v| v.ln()).sum::<f64>();
        let ll = -0.5
            * (n as f64 * log_det_g
                + k as f64 * logdet_a
                + (&Ainv * &Q).trace()
                + (n * k) as f64 * (2.0 * std::f64::consts::PI).ln());
        if !ll.is_finite() {
            return Err(EvalFailure::NonFinite);
        }
        // γ = α A⁻¹ (row-major)
        for j in 0..k {
            for b in 0..n {
                w.gamma[j * n + b] = (0..n).map(|a| w.alpha[a * k + j] * Ainv[(a, b)]).sum();
            }
        }
        // Ḡ_ij = −½ (n S_ij − γ_i·α_j); through the floor ε s̄ every K_jj
        // also moves G's diagonal by ε/k: Ḡ_jj gains ε tr(Ḡ)/k
        let nf = n as f64;
        let tr_gbar: f64 = (0..k)
            .map(|j| {
                let ga: f64 = (0..n)
                    .map(|a| w.alpha[a * k + j] * w.gamma[j * n + a])
                    .sum();
                -0.5 * (nf * w.inv[j * k + j] - ga)
            })
            .sum();
        let diag_shift = NOISE_TO_SIGNAL * tr_gbar / k as f64;
        // one pass over the lower triangle, column by column, for every
        // gradient term (∂G_ij/∂h = u̲_iᵀBu̲_j ∂k0_ij/∂h, ∂G/∂B_ab =
        // k0_ij u_ia u_jb); an off-diagonal entry stands for (i, j) and
        // (j, i), the diagonal one for itself (weight ½ of the pair's)
        w.kern_acc.fill(0.0);
        let mut bbar = DMatrix::<f64>::zeros(p, p);
        let ucols = &self.u_cols;
        for j in 0..k {
            let (zj, uj, buj) = (z(j), u(j), &w.bu[j * p..(j + 1) * p]);
            let m = k - j;
            let (k0j, sj) = (&col(&w.k0, k, j)[j..], &col(&w.inv, k, j)[j..]);
            // Ḡ_ij for i ≥ j
            let gcol = &mut w.gcol[..m];
            for (g, sij) in gcol.iter_mut().zip(sj) {
                *g = -0.5 * nf * sij;
            }
            for a in 0..n {
                let ga = 0.5 * w.gamma[j * n + a];
                for (g, x) in gcol.iter_mut().zip(&w.alpha[a * k + j..(a + 1) * k]) {
                    *g += ga * x;
                }
            }
            gcol[0] += diag_shift;
            gcol[0] *= 0.5;
            // kernel weights 2 Ḡ_ij u̲_iᵀBu̲_j, and T += (Σ_i Ḡ_ij k0_ij u̲_i) u̲_jᵀ
            let wk = &mut w.wcol[..m];
            wk.fill(0.0);
            for c in 0..p {
                let uc = &ucols[c * k + j..(c + 1) * k];
                let bc = 2.0 * buj[c];
                for ((o, g), ui) in wk.iter_mut().zip(gcol.iter()).zip(uc) {
                    *o += bc * g * ui;
                }
                let t = sum_by_4(m, |i| gcol[i] * k0j[i] * uc[i]);
                for (b, ujb) in uj.iter().enumerate() {
                    bbar[(c, b)] += t * ujb;
                    bbar[(b, c)] += t * ujb;
                }
            }
            kern.add_grad_log_hyper_rows(
                &zs[j * d..],
                zj,
                k0j,
                wk,
                &mut w.kern_acc,
                &mut w.kern_scratch,
            );
        }
        let l = &self.layout;
        pack_free(&w.kern_acc, l.scale_idx, grad);
        // σ_f = e^θ: ∂G/∂θ = 2σ_f² I
        grad[l.off_sigma()] = 2.0 * sigma * sigma * tr_gbar;
        l.b.chain(
            &bbar,
            &th[l.off_b()..l.off_a()],
            &mut grad[l.off_b()..l.off_a()],
        );
        if let Some(a) = &l.a {
            let abar = -0.5 * (k as f64 * &Ainv - &Ainv * &Q * &Ainv);
            a.chain(&abar, &th[l.off_a()..], &mut grad[l.off_a()..]);
        }
        for gi in grad.iter_mut() {
            *gi = -*gi;
        }
        Ok(-ll)
    }
}

/// Learns the kernel lengthscales, `A`, `B` and `σ` of `model` from its data
/// by maximising the exact marginal likelihood ([`MvgpLikelihood`], module
/// docs) with projected L-BFGS over the bounds, and refactorises the model.
///
/// A cold fit (not `warm_start`) starts from the data-driven point or, when
/// its likelihood is higher, from the model's own hyperparameters
/// ([`MvgpLikelihood::point_of`]): a fit then never ends below the model it
/// was given, where the parameterisation holds that model exactly (full or
/// diagonal ranks, inside the bounds). Restarts perturb that start.
///
/// Deterministic for a given `settings.seed`.
///
/// ## Reference
/// Paper, Sec. IV (marginal likelihood of Eq. 11), Prop. 1.
pub fn fit<K: Kernel>(model: &mut Mvgp<K>, settings: &FitSettings) -> Result<FitReport, Error> {
    fit_until(model, settings, &AtomicBool::new(false))
}

/// [`fit`], stopped once `stop` is set (by another thread: a Ctrl-C
/// handler, a deadline), within one likelihood evaluation: it then returns
/// [`Error::Interrupted`] and leaves the
/// model's hyperparameters as they were.
pub fn fit_until<K: Kernel>(
    model: &mut Mvgp<K>,
    settings: &FitSettings,
    stop: &AtomicBool,
) -> Result<FitReport, Error> {
    let initial_ll = model.log_marginal_likelihood();
    let likelihood = MvgpLikelihood::new(model, settings)?;
    let spreads = likelihood.spreads.clone();
    let th0 = likelihood.start.clone();
    // a cold fit starts from the model's own hyperparameters when they are
    // the better point: it then never ends below the model it was given
    // (where the parameterisation holds that model exactly)
    let own = (!settings.warm_start)
        .then(|| likelihood.point_of(model.hyper(), settings.seed))
        .transpose()?;
    let off_sigma = likelihood.layout.off_sigma();
    let sigma_max = likelihood.upper[off_sigma];
    let mut harness = Harness::new(likelihood).with_stop(stop);
    let (mut th0, mut at_start) = harness.better_start(th0, own);
    // a start whose Gram matrix does not factorise without jitter (the
    // fit evaluates exactly; e.g. the model's own σ on redundant online
    // data) starts again with ten times the noise, up to σ's bound
    while at_start.is_none() && th0[off_sigma] < sigma_max {
        th0[off_sigma] = (th0[off_sigma] + std::f64::consts::LN_10).min(sigma_max);
        at_start = harness.point(th0.clone()).map(|p| p.value);
    }
    // one run per start, ending when an iteration improves −log p by less
    // than 1e-9 relative, or at a stall. The CoGP fit resumes after stalls
    // and pre-fits a diagonal model (same harness, `fit_cogp`): its Σ has
    // (n(1+m))² entries and its landscape many flat valleys. The MVGP's
    // few parameters do not need it: with four resumptions and 1e-12 the
    // pendulum fit at k = 500 and the scalar one at k = 1000 reach the same
    // likelihood (to 2·10⁻⁵ relative) with 4-24 % more evaluations.
    let run = RunSettings {
        max_iters: settings.max_iters,
        stall_resumes: 0,
        relative_cost_tolerance: 1e-9,
    };
    let starts = 1 + settings.restarts;
    let mut rng = ChaCha8Rng::seed_from_u64(settings.seed);
    let ranked = multi_start_ranked(&mut harness, starts, &run, |_, s| {
        let mut th = th0.clone();
        if s > 0 {
            perturb(&mut th, &mut rng);
        }
        Ok::<_, Error>(StartPlan::at(th))
    })?;
    // the model refactorises the result with its own roundoff: a pivot at
    // the floor could then need jitter, so the result must factorise with
    // a margin, and σ_f grows by steps of 10 % until it does (twice σ
    // lifts the floor of every pivot four times). Each start's result is
    // so adjusted, and the one whose model has the largest likelihood
    // wins: an adjustment can cost a start its lead, so more starts never
    // give a worse model.
    harness.objective_mut().work.pivot_margin = FINAL_PIVOT_MARGIN;
    let mut hypers = Vec::with_capacity(ranked.len());
    for p in ranked {
        let mut theta = p.theta;
        for _ in 0..30 {
            if harness.point(theta.clone()).is_some() || theta[off_sigma] >= sigma_max {
                break;
            }
            theta[off_sigma] = (theta[off_sigma] + 0.1).min(sigma_max);
        }
        hypers.push(harness.objective().hyper(&theta));
    }
    if harness.stopped() {
        return Err(Error::Interrupted);
    }
    let evaluations = harness.evaluations();
    drop(harness);
    if hypers.len() == 1 {
        // one start: no comparison, no copy of the model
        model.set_hyper(hypers.swap_remove(0)?)?;
        warn_collapsed_lengthscales(model, &spreads);
        return Ok(FitReport {
            initial_log_likelihood: initial_ll,
            log_likelihood: model.log_marginal_likelihood(),
            evaluations,
            starts,
        });
    }
    let mut best: Option<(f64, Mvgp<K>)> = None;
    let mut failure = None;
    for hyper in hypers {
        let mut trial = model.clone();
        match hyper.and_then(|h| trial.set_hyper(h)) {
            Ok(()) => {
                let ll = trial.log_marginal_likelihood();
                if best.as_ref().is_none_or(|(b, _)| ll > *b) {
                    best = Some((ll, trial));
                }
            }
            Err(e) => failure = Some(e),
        }
    }
    let (log_likelihood, fitted) = match (best, failure) {
        (Some(b), _) => b,
        (None, Some(e)) => return Err(e),
        (None, None) => {
            return Err(GpError::Optimisation("no start gave hyperparameters".into()).into())
        }
    };
    *model = fitted;
    warn_collapsed_lengthscales(model, &spreads);
    Ok(FitReport {
        initial_log_likelihood: initial_ll,
        log_likelihood,
        evaluations,
        starts,
    })
}

static LENGTHSCALE_UNFIT: crate::warnings::WarnOnce =
    crate::warnings::WarnOnce::new("lengthscale_unfit");

/// Warns, once per scope, when the fit could not set a lengthscale from the
/// data: its input takes one value in every row (the likelihood does not
/// depend on that lengthscale, which keeps its start), or the lengthscale ended at
/// the floor of its range (a thousandth of the input's spread,
/// [`kernel_bounds`]: the kernel treats the input as white noise). Either
/// way the posterior away from the training inputs falls back to the prior
/// mean.
fn warn_collapsed_lengthscales<K: Kernel>(model: &Mvgp<K>, spreads: &[f64]) {
    let kernel = &model.hyper().kernel;
    let scale_idx = kernel.scale_index();
    let all = kernel.log_hyper();
    let mut free = vec![0.0; all.len() - usize::from(scale_idx.is_some())];
    pack_free(&all, scale_idx, &mut free);
    let floor = |s: f64| (s / super::theta::LENGTHSCALE_RANGE).ln();
    let (zs, k, d) = (model.mapped_inputs(), model.len(), spreads.len());
    // an input with one value in every row (its spread floored, and no
    // variation at all)
    let constant = |j: usize| (1..k).all(|i| zs[i * d + j] == zs[j]);
    let why = free
        .iter()
        .zip(spreads)
        .enumerate()
        .find_map(|(i, (&t, &s))| {
            let l = t.exp();
            if constant(i) {
                Some((
                    i,
                    format!(
                        "takes one value in every row: the fit cannot learn its lengthscale \
                         ({l:.3e})"
                    ),
                ))
            } else if t <= floor(s) + 0.01 {
                Some((
                    i,
                    format!(
                        "has its lengthscale at the floor of its range ({l:.3e}, a thousandth \
                         of the input's spread {s:.3e}): the kernel treats the input as noise"
                    ),
                ))
            } else {
                None
            }
        });
    if let Some((i, why)) = why {
        LENGTHSCALE_UNFIT.issue(|| {
            format!(
                "fit: kernel input {i} {why}; the model's prediction away from the {k} training \
             inputs falls back to the prior mean (a constant input, repeated rows or too few \
             rows)"
            )
        });
    }
}

fn symmetrise(m: &DMatrix<f64>) -> DMatrix<f64> {
    0.5 * (m + m.transpose())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gp::theta::random_training_rows;
    use crate::gp::Rbf;
    use rand::RngExt;

    fn model(n: usize, m: usize, k: usize, rng: &mut ChaCha8Rng) -> Mvgp {
        let (zs, us, resid) = random_training_rows(rng, k, n, m);
        let p = m + 1;
        let mut model = crate::gp::plain_model(n, m, 0.8, 1.3, 0.3);
        let u_only: Vec<f64> = us.chunks(p).flat_map(|u| u[1..].to_vec()).collect();
        model.set_data(&zs, &u_only, &resid).unwrap();
        model
    }

    /// Default settings with these ranks of `A` and `B`, `A` learned or not.
    fn shaped(rank_a: Rank, rank_b: Rank, learn_a: bool) -> FitSettings {
        FitSettings {
            rank_a,
            rank_b,
            learn_a,
            ..FitSettings::default()
        }
    }

    /// The analytic gradient of −log p against central finite differences,
    /// and the value against the model's own likelihood at the decoded
    /// hyperparameters (an independent computation through its factor).
    #[test]
    fn likelihood_gradient_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for (n, m, ra, rb, learn_a, known) in [
            (2, 1, Rank::Full, Rank::Full, true, vec![]),
            (3, 2, Rank::Low(1), Rank::Diagonal, true, vec![]),
            (3, 1, Rank::Full, Rank::Low(2), true, vec![0]),
            (1, 1, Rank::Diagonal, Rank::Full, true, vec![]),
            (2, 2, Rank::Full, Rank::Full, false, vec![]),
        ] {
            let mut model = model(n, m, 15, &mut rng);
            if !known.is_empty() {
                model = model.with_known_rows(&known).unwrap();
            }
            let settings = shaped(ra, rb, learn_a);
            let mut lik = MvgpLikelihood::new(&model, &settings).unwrap();
            let th: Vec<f64> = (0..lik.dim())
                .map(|_| rng.random_range(-0.5..0.5))
                .collect();
            let mut g = vec![0.0; th.len()];
            let f0 = lik.evaluate(&th, &mut g).unwrap();
            let mut scratch = vec![0.0; th.len()];
            let h = 1e-6;
            for i in 0..th.len() {
                let (mut tp, mut tm) = (th.clone(), th.clone());
                tp[i] += h;
                tm[i] -= h;
                let fd = (lik.evaluate(&tp, &mut scratch).unwrap()
                    - lik.evaluate(&tm, &mut scratch).unwrap())
                    / (2.0 * h);
                assert!(
                    (fd - g[i]).abs() < 1e-5 * (1.0 + fd.abs()),
                    "n={n} m={m} param {i}: fd {fd} analytic {}",
                    g[i]
                );
            }
            let hyper = lik.hyper(&th).unwrap();
            drop(lik);
            let mut check = model.clone();
            check.set_hyper(hyper).unwrap();
            assert!(
                (check.log_marginal_likelihood() + f0).abs() < 1e-8 * (1.0 + f0.abs()),
                "{} against {}",
                check.log_marginal_likelihood(),
                -f0
            );
        }
    }

    /// Evaluations reuse the workspace: the same θ gives the same value and
    /// gradient after other evaluations, bit for bit.
    #[test]
    fn evaluations_do_not_depend_on_earlier_ones() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let model = model(2, 1, 20, &mut rng);
        let mut lik = MvgpLikelihood::new(&model, &FitSettings::default()).unwrap();
        let th = lik.start().to_vec();
        let (mut g1, mut g2) = (vec![0.0; th.len()], vec![0.0; th.len()]);
        let f1 = lik.evaluate(&th, &mut g1).unwrap();
        let other: Vec<f64> = th.iter().map(|v| v + 0.3).collect();
        lik.evaluate(&other, &mut g2).unwrap();
        let f2 = lik.evaluate(&th, &mut g2).unwrap();
        assert_eq!(f1, f2);
        assert_eq!(g1, g2);
    }

    /// A model's own hyperparameters, as a point of the parameterisation,
    /// give the model's own likelihood: with a kernel scale, `A_00` and `σ`
    /// far from the parameterisation's, for full and diagonal ranks, known
    /// rows, and `A` held.
    #[test]
    fn a_models_own_hyperparameters_are_a_point_of_the_fit() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for (n, m, ra, rb, learn_a, known) in [
            (2, 1, Rank::Full, Rank::Full, true, vec![]),
            (3, 2, Rank::Diagonal, Rank::Full, true, vec![]),
            (3, 1, Rank::Full, Rank::Diagonal, true, vec![0]),
            (2, 2, Rank::Full, Rank::Full, false, vec![]),
        ] {
            let mut model = model(n, m, 25, &mut rng);
            if !known.is_empty() {
                model = model.with_known_rows(&known).unwrap();
            }
            let spd = |d: usize, diag: bool, rng: &mut ChaCha8Rng| {
                let c = DMatrix::from_fn(d, d, |i, j| {
                    if diag && i != j {
                        0.0
                    } else {
                        rng.random_range(-1.0..1.0) + if i == j { 1.5 } else { 0.0 }
                    }
                });
                &c * c.transpose()
            };
            let hyper = MvgpHyper {
                kernel: Rbf::new((0..n).map(|i| 0.5 + 0.3 * i as f64).collect(), 2.7).unwrap(),
                A: spd(n, ra == Rank::Diagonal, &mut rng),
                B: spd(m + 1, rb == Rank::Diagonal, &mut rng),
                sigma: 0.45,
            };
            model.set_hyper(hyper).unwrap();
            let settings = shaped(ra, rb, learn_a);
            let mut lik = MvgpLikelihood::new(&model, &settings).unwrap();
            let th = lik.point_of(model.hyper(), 0).unwrap();
            let mut g = vec![0.0; th.len()];
            let f = lik.evaluate(&th, &mut g).unwrap();
            let want = model.log_marginal_likelihood();
            assert!(
                (f + want).abs() < 1e-9 * want.abs().max(1.0),
                "n={n} m={m} {ra:?} {rb:?} learn_a={learn_a}: {} against {want}",
                -f
            );
        }
    }

    /// A fit never ends below the likelihood of the model it was given: a
    /// refit of a well-fitted model with one iteration or the defaults,
    /// and a fit of the hyperparameters that made the data.
    #[test]
    fn a_fit_never_ends_below_the_model_it_was_given() {
        for seed in 0..6 {
            let mut rng = ChaCha8Rng::seed_from_u64(100 + seed);
            let mut model = model(2, 1, 40, &mut rng);
            let good = FitSettings {
                restarts: 4,
                seed,
                ..FitSettings::default()
            };
            fit(&mut model, &good).unwrap();
            for max_iters in [1, 3, 100] {
                let mut refit = model.clone();
                let report = fit(
                    &mut refit,
                    &FitSettings {
                        max_iters,
                        seed: seed + 7,
                        ..FitSettings::default()
                    },
                )
                .unwrap();
                let before = model.log_marginal_likelihood();
                assert_eq!(report.initial_log_likelihood, before);
                assert!(
                    report.log_likelihood >= before - 1e-9 * before.abs().max(1.0),
                    "seed {seed}, max_iters {max_iters}: {} after {before}",
                    report.log_likelihood
                );
            }
        }
    }

    #[test]
    fn start_is_inside_the_bounds_and_sigma_respects_its_floor() {
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        let model = model(2, 1, 30, &mut rng);
        let settings = FitSettings {
            sigma_min: 0.5,
            ..FitSettings::default()
        };
        let lik = MvgpLikelihood::new(&model, &settings).unwrap();
        let (lo, hi) = lik.bounds();
        for ((t, l), h) in lik.start().iter().zip(lo).zip(hi) {
            assert!(l <= t && t <= h);
        }
        // θ_σ = log σ, bounded below by log σ_min (above the relative floor)
        let off = lik.layout.off_sigma();
        assert!((lo[off] - 0.5f64.ln()).abs() < 1e-15);
        assert!(lik.start()[off] >= 0.5f64.ln());
    }
}
