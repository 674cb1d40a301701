//! Mean and variance of barrier and Lyapunov conditions under the MVGP
//! posterior, in the form the SOCP needs: `E = eᵀu̲`, `Var = ‖V u̲‖²`.
//!
//! ## Relative degree 1 (paper, Lemma 2)
//! `CBC = ∇hᵀ F u̲ + α h`, `F u̲ ~ N(M_k u̲, (u̲ᵀB_k u̲) A)`:
//! `e = M_kᵀ∇h + [αh; 0]`, `Cov = (∇hᵀA∇h) B_k`.
//!
//! ## Relative degree 2 (paper, Sec. VI, Alg. 1)
//! `CBC⁽²⁾ = ∇(L_f h)ᵀ F u̲ + k₀ h + k₁ L_f h` with `L_f h = ∇hᵀ f` and
//! `∇(L_f h) = ∇²h f + J_fᵀ ∇h`. Write `a = ∇²h f + J_fᵀ∇h`,
//! `y_c = F e_c`; then `CBC⁽²⁾ = Σ_c u̲_c z_c` with
//! `z_c = aᵀ y_c + δ_{c0} (k₁ ∇hᵀ f + k₀ h)`. All of `a`, `y_c`, `f` are
//! linear in `vec 𝔽 = vec[F ∂_1F … ∂_nF]`, which is Gaussian
//! ([`crate::gp::JointPosterior`]), so `E[z]` and `Cov(z)` follow exactly
//! from Isserlis' theorem. For jointly Gaussian vectors `a`, `y`, `y'`:
//!
//! `Cov(aᵀy, aᵀy') = Σ_ij [S(a_i,a_j) S(y_i,y'_j) + S(a_i,y'_j) S(y_i,a_j)
//!   + ā_i ā_j S(y_i,y'_j) + ā_i ȳ'_j S(y_i,a_j) + ȳ_i ā_j S(a_i,y'_j)
//!   + ȳ_i ȳ'_j S(a_i,a_j)]`, `S = Cov`.
//!
//! With `y = y'` this is `tr(Σaa Σyy) + tr(Σay Σay) + ȳᵀΣaaȳ + āᵀΣyyā +
//! 2ȳᵀΣay ā`. The paper's Lemma 4 prints `½ tr((Σay + Σya)²)`, which is
//! `tr(Σay Σay) + tr(Σay Σya)`: it has `tr(Σay Σya)` where `tr(Σaa Σyy)`
//! belongs. The exact expression here is validated against Monte Carlo in
//! the tests, and so is that swap.

use super::{DynBarrier, DynLyapunov};
use crate::error::{ControlError, Error, InputError};
use crate::gp::joint::Columns;
use crate::gp::{JointPosterior, JointWorkspace, Kernel, Mvgp, Posterior, PosteriorWorkspace};
use nalgebra::DMatrix;
use num_dual::{Dual64, HyperDual64};

/// Moments of a condition `C(x, u) = zᵀu̲` with random `z ∈ R^{1+m}`:
/// `E[C] = eᵀu̲`, `Var[C] = u̲ᵀ cov u̲ = ‖v u̲‖²`.
#[derive(Debug, Clone, PartialEq)]
pub struct ConditionMoments {
    /// `e = E[z]`.
    pub e: Vec<f64>,
    /// `Cov(z)`.
    pub cov: DMatrix<f64>,
    /// Factor with `vᵀ v = cov` (upper triangular).
    pub v: DMatrix<f64>,
    /// `h(x)` or `V(x)`.
    pub value: f64,
    /// Relative degree used.
    pub relative_degree: usize,
}

impl ConditionMoments {
    /// Zeros for control dimension `m`.
    pub fn zeros(m: usize) -> Self {
        let p = m + 1;
        Self {
            e: vec![0.0; p],
            cov: DMatrix::zeros(p, p),
            v: DMatrix::zeros(p, p),
            value: 0.0,
            relative_degree: 1,
        }
    }
    /// Moments from `e` and a symmetric positive-semidefinite `cov`
    /// (validated), e.g. computed elsewhere.
    pub fn from_parts(
        e: Vec<f64>,
        cov: DMatrix<f64>,
        relative_degree: usize,
    ) -> Result<Self, InputError> {
        let p = e.len();
        if p < 2 {
            return Err(InputError::shape("e", "≥ 2 entries (1 + m)", p));
        }
        if cov.shape() != (p, p) {
            return Err(InputError::shape(
                "cov",
                format!("{p}×{p}"),
                format!("{}×{}", cov.nrows(), cov.ncols()),
            ));
        }
        crate::error::check_finite("e", &e)?;
        crate::error::check_finite("cov", cov.as_slice())?;
        let ev = cov.clone().symmetric_eigenvalues();
        let scale = ev.iter().fold(0.0f64, |a, b| a.max(b.abs()));
        if ev.iter().any(|&l| l < -1e-9 * scale.max(1e-300))
            || (&cov - cov.transpose()).abs().max() > 1e-9 * scale.max(1.0)
        {
            return Err(InputError::NotPositiveDefinite {
                field: "cov".into(),
                reason: "must be symmetric positive semidefinite".into(),
            });
        }
        if relative_degree == 0 {
            return Err(InputError::invalid("relative_degree", 0.0, "must be ≥ 1"));
        }
        let mut v = DMatrix::zeros(p, p);
        psd_factor(&cov, &mut v);
        Ok(Self {
            e,
            cov,
            v,
            value: 0.0,
            relative_degree,
        })
    }

    /// Checks that `h(x)`, `e` and `Cov(z)` are finite. The error names the
    /// condition (`label`), the state `x` and the first non-finite entry;
    /// nothing is allocated when all is finite.
    pub fn check_finite(&self, label: &str, x: &[f64]) -> Result<(), InputError> {
        let p = self.e.len();
        let bad = if !self.value.is_finite() {
            Some(format!("h(x) = {}", self.value))
        } else if let Some(i) = self.e.iter().position(|v| !v.is_finite()) {
            Some(format!("e[{i}] = {}", self.e[i]))
        } else {
            self.cov
                .iter()
                .position(|v| !v.is_finite())
                .map(|i| format!("cov[{}][{}] = {}", i % p, i / p, self.cov.as_slice()[i]))
        };
        match bad {
            None => Ok(()),
            Some(entry) => Err(InputError::Evaluation(format!(
                "{label}: the condition's moments are not finite at x = {} ({entry}): \
                 the model, the function or their derivatives overflow at this state",
                crate::error::Brief(x)
            ))),
        }
    }

    /// `E[C]` at control `u` (without the leading 1).
    pub fn mean(&self, u: &[f64]) -> f64 {
        self.e[0] + u.iter().zip(&self.e[1..]).map(|(a, b)| a * b).sum::<f64>()
    }
    /// `Var[C]` at control `u`, or [`ControlError::VarianceUnresolved`]
    /// when the rounding of the sum it comes from could be a tenth of it or
    /// more, and that rounding matters: `u̲ᵀ C u̲` sums `(1+m)²` terms
    /// `u̲_i C_ij u̲_j`, each rounded, so its error is up to about `r =
    /// 2 (1+m)² ε Σ |u̲_i C_ij u̲_j|` (ε the machine epsilon, doubled for
    /// the rounding of `C` itself), and it matters when `√r`, the standard
    /// deviation it could hide, exceeds `10⁻⁶ max(1, |E[C]|)`. For a report
    /// of the variance (`bayes-cbf moments`, Python's `moments`), where
    /// [`variance`](Self::variance) would give the rounding, clamped at 0.
    pub fn variance_resolved(&self, u: &[f64]) -> Result<f64, ControlError> {
        let (s, size) = self.quadratic_form(u);
        let p = self.e.len();
        let rounding = 2.0 * (p * p) as f64 * f64::EPSILON * size;
        let matters = rounding.sqrt() > 1e-6 * self.mean(u).abs().max(1.0);
        if rounding > 0.1 * s.max(0.0) && matters {
            return Err(ControlError::VarianceUnresolved {
                variance: s,
                rounding,
                scale: self.cov.amax(),
            });
        }
        Ok(s.max(0.0))
    }

    /// `Var[C]` at control `u`.
    pub fn variance(&self, u: &[f64]) -> f64 {
        self.quadratic_form(u).0.max(0.0)
    }

    /// `u̲ᵀ C u̲` and the sum of its terms' magnitudes `Σ |u̲_i C_ij u̲_j|`.
    fn quadratic_form(&self, u: &[f64]) -> (f64, f64) {
        let p = self.e.len();
        let ub = |i: usize| if i == 0 { 1.0 } else { u[i - 1] };
        let (mut s, mut size) = (0.0, 0.0f64);
        for i in 0..p {
            for j in 0..p {
                let t = ub(i) * self.cov[(i, j)] * ub(j);
                s += t;
                size += t.abs();
            }
        }
        (s, size)
    }
}

/// Safety factor `c(p)`: `√2 erf⁻¹(2p − 1)` (Gaussian quantile, exact for
/// relative degree 1, Prop. 2) or `√(p/(1−p))` (Cantelli, any distribution,
/// relative degree ≥ 2, Prop. 4). `c = 0` at `p = 0.5` for `r = 1` gives the
/// mean-CBF QP.
pub fn quantile_factor(p: f64, relative_degree: usize) -> Result<f64, InputError> {
    if !(p.is_finite() && p > 0.0 && p < 1.0) {
        return Err(InputError::invalid("probability", p, "must be in (0, 1)"));
    }
    Ok(if relative_degree <= 1 {
        std::f64::consts::SQRT_2 * statrs::function::erf::erf_inv(2.0 * p - 1.0)
    } else {
        (p / (1.0 - p)).sqrt()
    })
}

/// The probability whose safety factor is `c`: the inverse of
/// [`quantile_factor`], `Φ(c)` for relative degree 1 and `c²/(1 + c²)`
/// (`c ≥ 0`) for relative degree ≥ 2; `0` for a negative Cantelli factor,
/// which no probability reaches.
pub fn factor_probability(c: f64, relative_degree: usize) -> f64 {
    if relative_degree <= 1 {
        0.5 * statrs::function::erf::erfc(-c / std::f64::consts::SQRT_2)
    } else if c.is_infinite() && c > 0.0 {
        1.0
    } else if c >= 0.0 {
        c * c / (1.0 + c * c)
    } else {
        0.0
    }
}

/// Buffers for moment computation at one state; no allocation after the
/// first use with a given model size.
#[derive(Debug, Clone)]
pub struct MomentWorkspace {
    pub(crate) post: Posterior,
    pub(crate) post_ws: PosteriorWorkspace,
    pub(crate) joint: JointPosterior,
    pub(crate) joint_ws: JointWorkspace,
    /// Which posterior is current: 0 none, 1 plain, 2 joint.
    level: usize,
    x: Vec<f64>,
    grad: Vec<f64>,
    hess: Vec<f64>,
    sd: Vec<Dual64>,
    sh: Vec<HyperDual64>,
    /// `A ∇²h` (column `i` is `A H_i`) and `∇²h A ∇²h` (rd2's `AH`, `HAH`).
    ah: DMatrix<f64>,
    hah: DMatrix<f64>,
    /// `A ∇h` and `∇²h A ∇h` (rd2's `Ag`, `HAg`).
    ag: Vec<f64>,
    hag: Vec<f64>,
    /// Covariance (R × R) and means of the linear functionals.
    s: DMatrix<f64>,
    mu: Vec<f64>,
    a_mat: DMatrix<f64>,
    /// The model's noise scale `σ²` (observation noise `σ² A`).
    noise: f64,
}

impl MomentWorkspace {
    /// A workspace for `model`. The buffers of relative degree 2 (the joint
    /// posterior of `F` and its Jacobian, and the functionals' covariance,
    /// `O(n²(1+m)²)` entries) are made at the first
    /// [`update`](Self::update) that needs them.
    pub fn new<K: Kernel>(model: &Mvgp<K>) -> Self {
        let (n, m) = (model.state_dim(), model.control_dim());
        let p = m + 1;
        Self {
            post: Posterior {
                mean: DMatrix::zeros(n, p),
                B: DMatrix::zeros(p, p),
            },
            post_ws: model.workspace(),
            joint: JointPosterior::zeros(0, 0),
            joint_ws: JointWorkspace::default(),
            level: 0,
            x: vec![0.0; n],
            grad: vec![0.0; n],
            hess: Vec::new(),
            sd: vec![Dual64::from(0.0); 2 * n],
            sh: Vec::new(),
            ah: DMatrix::zeros(0, 0),
            hah: DMatrix::zeros(0, 0),
            ag: Vec::new(),
            hag: Vec::new(),
            s: DMatrix::zeros(0, 0),
            mu: Vec::new(),
            a_mat: DMatrix::zeros(n, n),
            noise: 0.0,
        }
    }

    /// Computes the posterior at `x`: plain (`max_degree ≤ 1`) or joint with
    /// the Jacobian (`max_degree = 2`).
    pub fn update<K: Kernel>(
        &mut self,
        model: &Mvgp<K>,
        x: &[f64],
        max_degree: usize,
    ) -> Result<(), InputError> {
        let (n, p) = (model.state_dim(), model.control_dim() + 1);
        if self.x.len() != n || self.post.B.nrows() != p {
            // made for a model of another shape
            *self = Self::new(model);
        }
        if max_degree >= 2 {
            if self.s.nrows() != n * (1 + p) + 1 {
                self.make_second_order(model)?;
            }
            model.joint_columns_into(x, Columns::Drift, &mut self.joint_ws, &mut self.joint)?;
            for c in 0..p {
                for i in 0..n {
                    self.post.mean[(i, c)] = self.joint.mean[(i, c)];
                }
                for c2 in 0..p {
                    self.post.B[(c, c2)] = self.joint.c[(c, c2)];
                }
            }
            self.level = 2;
        } else {
            model.posterior_into(x, &mut self.post_ws, &mut self.post)?;
            self.level = 1;
        }
        self.x.copy_from_slice(x);
        self.a_mat.copy_from(model.row_cov());
        self.noise = model.hyper().sigma * model.hyper().sigma;
        Ok(())
    }

    /// Sizes the buffers of relative degree 2 for `model`, or says that
    /// they cannot be allocated (a model of thousands of states), rather
    /// than abort the process.
    fn make_second_order<K: Kernel>(&mut self, model: &Mvgp<K>) -> Result<(), InputError> {
        let (n, p) = (model.state_dim(), model.control_dim() + 1);
        let r = n * (1 + p) + 1;
        // joint posterior (p + n columns), its workspace, ∇²h and its duals
        // (4 each), AH, HAH, Ag, HAg, S and μ
        let entries = [
            n * (p + n) + (p + n) * (p + n),
            model.joint_workspace_len(Columns::Drift),
            n * n + 4 * n,
            2 * n * n + 2 * n,
            r * r + r,
        ]
        .into_iter()
        .fold(0usize, usize::saturating_add);
        let bytes = entries.saturating_mul(std::mem::size_of::<f64>());
        if Vec::<u8>::new().try_reserve_exact(bytes).is_err() {
            return Err(InputError::invalid_shown(
                "state_dim",
                n,
                &format!(
                    "relative-degree-2 moments at {n} states and {} controls need {:.1} GB of \
                     buffers (the joint posterior of F and its Jacobian, and the covariance of \
                     {r} linear functionals), more than can be allocated",
                    p - 1,
                    bytes as f64 / 1e9
                ),
            ));
        }
        self.joint = JointPosterior {
            mean: DMatrix::zeros(n, p + n),
            c: DMatrix::zeros(p + n, p + n),
        };
        self.joint_ws = model.joint_workspace_for(Columns::Drift);
        self.hess = vec![0.0; n * n];
        self.sh = vec![HyperDual64::from(0.0); n];
        self.ah = DMatrix::zeros(n, n);
        self.hah = DMatrix::zeros(n, n);
        self.ag = vec![0.0; n];
        self.hag = vec![0.0; n];
        self.s = DMatrix::zeros(r, r);
        self.mu = vec![0.0; r];
        Ok(())
    }

    /// The plain posterior at the last [`update`](Self::update) point.
    pub fn posterior(&self) -> &Posterior {
        &self.post
    }
}

/// Writes an upper-triangular `v` with `vᵀv = cov` (pivot-free Cholesky that
/// treats non-positive pivots of a PSD matrix as zero).
fn psd_factor(cov: &DMatrix<f64>, v: &mut DMatrix<f64>) {
    let p = cov.nrows();
    v.fill(0.0);
    let scale = (0..p)
        .map(|i| cov[(i, i)].abs())
        .fold(0.0, f64::max)
        .max(f64::MIN_POSITIVE);
    for j in 0..p {
        let mut d = cov[(j, j)];
        for k in 0..j {
            d -= v[(k, j)] * v[(k, j)];
        }
        if d <= 1e-13 * scale {
            continue;
        }
        let dj = d.sqrt();
        v[(j, j)] = dj;
        for i in j + 1..p {
            let mut s = cov[(j, i)];
            for k in 0..j {
                s -= v[(k, j)] * v[(k, i)];
            }
            v[(j, i)] = s / dj;
        }
    }
}

fn check_dims(ws: &MomentWorkspace, dim: usize, needs: usize) -> Result<(), Error> {
    if dim != ws.x.len() {
        return Err(InputError::shape("barrier state dimension", ws.x.len(), dim).into());
    }
    if ws.level < needs {
        return Err(InputError::invalid_shown("relative_degree", needs, "posterior not prepared for this degree (call MomentWorkspace::update with max_degree ≥ r)").into());
    }
    Ok(())
}

/// Standard deviation, per unit of control, of `L_g h · u = ∇hᵀ g(x) u`
/// under the posterior at the last update point: `√(∇hᵀ A ∇h · max_c
/// B_k,cc)` over the control columns `c ≥ 1` (`A` the model's row
/// covariance). A relative-degree-2 condition assumes `L_g h = 0`; when the
/// model leaves `g`'s rows that `∇h` sees uncertain (e.g. a kinematic row
/// that is not declared known), this term is random and ignored. Call after
/// [`cbc_moments`] (which sets `∇h`).
pub fn unmodelled_lgh_std(ws: &MomentWorkspace) -> f64 {
    let n = ws.x.len();
    let mut q = 0.0;
    for i in 0..n {
        for j in 0..n {
            q += ws.grad[i] * ws.a_mat[(i, j)] * ws.grad[j];
        }
    }
    let p = ws.post.B.nrows();
    let b = (1..p).map(|c| ws.post.B[(c, c)]).fold(0.0, f64::max);
    (q.max(0.0) * b.max(0.0)).sqrt()
}

/// Warns once per scope ([`crate::warnings`]) when a relative-degree-2 barrier sees an
/// `L_g h · u` whose spread is more than a tenth of the condition's own
/// (per unit control): the guarantee of the condition does not cover it.
fn warn_unmodelled_lgh(ws: &MomentWorkspace, barrier: &dyn DynBarrier, out: &ConditionMoments) {
    static WARNED: crate::warnings::WarnOnce = crate::warnings::WarnOnce::new("unmodelled_lgh");
    if !WARNED.pending() {
        return;
    }
    let s = unmodelled_lgh_std(ws);
    let p = out.cov.nrows();
    let own = (0..p).map(|c| out.cov[(c, c)]).fold(0.0, f64::max).sqrt();
    if s > 0.1 * own.max(1e-12) {
        WARNED.issue(|| format!(
            "barrier '{}' has relative degree 2, but the model leaves L_g h · u uncertain (std {s:.3e} per unit u, where the condition's own std is {own:.3e}): the condition assumes L_g h = 0 and does not cover it; declare the rows of F that ∇h weighs known (gp.known_rows), with a prior mean that has them exactly (a known row is the prior mean's), or use relative degree 1",
            barrier.name()
        ));
    }
}

/// Rejects a failed or non-finite evaluation of `h` (at `x`, or on a
/// lattice around it), `∇h` or `∇²h`, naming the barrier (a callback's own
/// message first): the evaluation's failure is this call's error, not a
/// later call's.
pub(super) fn check_evaluation(
    barrier: &dyn DynBarrier,
    x: &[f64],
    h: &[f64],
    grad: &[f64],
    hess: &[f64],
) -> Result<(), Error> {
    if let Some(msg) = barrier.take_error() {
        return Err(InputError::Evaluation(msg).into());
    }
    for (what, v) in [("h", h), ("∇h", grad), ("∇²h", hess)] {
        if let Some(bad) = v.iter().find(|v| !v.is_finite()) {
            return Err(InputError::Evaluation(format!(
                "{what} of barrier '{}' is {bad} at x = {}",
                barrier.name(),
                crate::error::Brief(x)
            ))
            .into());
        }
    }
    Ok(())
}

/// Moments of the barrier condition at the point of the last
/// [`MomentWorkspace::update`]. Exact for relative degree 1 and 2.
pub fn cbc_moments(
    ws: &mut MomentWorkspace,
    barrier: &dyn DynBarrier,
    out: &mut ConditionMoments,
) -> Result<(), Error> {
    let r = barrier.relative_degree();
    let gains = barrier.gains();
    super::validate_gains(r, gains)?;
    match r {
        1 => {
            check_dims(ws, barrier.state_dim(), 1)?;
            let h = barrier.gradient(&ws.x, &mut ws.grad, &mut ws.sd);
            check_evaluation(barrier, &ws.x, &[h], &ws.grad, &[])?;
            rd1(ws, h, gains[0], out);
            out.value = h;
            out.relative_degree = 1;
        }
        2 => {
            check_dims(ws, barrier.state_dim(), 2)?;
            let h = barrier.hessian(&ws.x, &mut ws.grad, &mut ws.hess, &mut ws.sh);
            check_evaluation(barrier, &ws.x, &[h], &ws.grad, &ws.hess)?;
            rd2(ws, h, gains[0], gains[1], out);
            warn_unmodelled_lgh(ws, barrier, out);
            out.value = h;
            out.relative_degree = 2;
        }
        _ => {
            return Err(InputError::invalid_shown(
                "relative_degree",
                r,
                "exact moments exist for relative degree 1 and 2",
            )
            .into());
        }
    }
    // once per scope: a run would repeat it at every step
    static NO_INPUT_WARNED: crate::warnings::WarnOnce =
        crate::warnings::WarnOnce::new("no_input_effect");
    let nrm: f64 = out.e[1..].iter().map(|v| v * v).sum::<f64>().sqrt();
    let scale = out.e[0].abs().max(1.0);
    if nrm < 1e-9 * scale {
        NO_INPUT_WARNED.issue(|| format!("barrier '{}': the model's mean of L_g L_f^(r-1) h is ≈ 0 at x = {} (|e_u| = {nrm:.2e}): the input has no mean effect on the condition there, because the prior mean gives it none (a zero prior mean, before data) or because relative degree {r} is wrong (shown once per run or filter)", barrier.name(), crate::error::Brief(&ws.x)));
    }
    Ok(())
}

/// Turns the moments of a barrier condition that [`cbc_moments`] just
/// wrote with `ws` (the same barrier, no other moment computed since) into
/// those of the condition *as realised over the step*: the rate `F u̲` is
/// replaced by `ẋ_obs = F u̲ + ε`, `ε ~ N(0, σ² A)` independent of `F`,
/// the model's own observation noise, which for process noise is the
/// disturbance that moves the state over the hold
/// ([`realised_condition`](super::realised_condition) with the true `F`).
///
/// - Relative degree 1: `∇hᵀ ẋ_obs + α h` has, since `u̲₀ = 1`,
///   `Var = (u̲ᵀ B_k u̲ + σ²) ∇hᵀA∇h`: `σ² ∇hᵀA∇h` more.
/// - Relative degree 2: `∇(L_f h)ᵀ ẋ_obs + k₀ h + k₁ L_f h = C⁽²⁾ + aᵀε`
///   with `a = ∇(L_f h)` (module docs); `aᵀε` has mean 0, no covariance
///   with `C⁽²⁾` (`ε` is independent of `𝔽` and centred) and variance
///   `E[aᵀ σ²A a] = σ² (āᵀAā + tr(A Σ_aa))`.
///
/// Either way the term does not depend on `u`: it is added to `cov₀₀`
/// and the factor recomputed; the mean is unchanged. An error for other
/// relative degrees.
pub fn add_observation_noise(
    ws: &MomentWorkspace,
    out: &mut ConditionMoments,
) -> Result<(), Error> {
    let a = &ws.a_mat;
    let n = ws.x.len();
    let mut added = 0.0;
    match out.relative_degree {
        1 => {
            let g = &ws.grad;
            for i in 0..n {
                for j in 0..n {
                    added += g[i] * a[(i, j)] * g[j];
                }
            }
        }
        // the functionals a_i are the first n of `rd2` (ia(i) = i)
        2 => {
            for i in 0..n {
                for j in 0..n {
                    added += a[(i, j)] * (ws.mu[i] * ws.mu[j] + ws.s[(i, j)]);
                }
            }
        }
        r => {
            return Err(InputError::invalid_shown(
                "relative_degree",
                r,
                "the observation noise is added to conditions of relative degree 1 and 2",
            )
            .into());
        }
    }
    out.cov[(0, 0)] += ws.noise * added;
    psd_factor(&out.cov, &mut out.v);
    Ok(())
}

/// Moments of the Lyapunov condition
/// `CLC = ∇ₓVᵀ F u̲ + ∇_{x_d}Vᵀẋ_d + γV` at the last update point.
pub fn clc_moments(
    ws: &mut MomentWorkspace,
    clf: &dyn DynLyapunov,
    xd: &[f64],
    xd_dot: &[f64],
    out: &mut ConditionMoments,
) -> Result<(), Error> {
    check_dims(ws, clf.state_dim(), 1)?;
    let n = ws.x.len();
    if xd.len() != n || xd_dot.len() != n {
        return Err(InputError::shape("reference", n, xd.len().min(xd_dot.len())).into());
    }
    let (v, dvdt) = clf.gradient(&ws.x, xd, xd_dot, &mut ws.grad, &mut ws.sd);
    let at = |what: &str, bad: f64| {
        let (x, xd) = (crate::error::Brief(&ws.x), crate::error::Brief(xd));
        Err(InputError::Evaluation(format!(
            "clf: {what} is {bad} at x = {x}, x_d = {xd} (V is not defined or not differentiable there)"
        ))
        .into())
    };
    if !v.is_finite() {
        return at("V", v);
    }
    if let Some(&bad) = ws.grad[..n].iter().find(|g| !g.is_finite()) {
        return at("∇ₓV", bad);
    }
    if !dvdt.is_finite() {
        return at("∇_{x_d}V · ẋ_d", dvdt);
    }
    rd1(ws, v, clf.gamma(), out);
    out.e[0] += dvdt;
    out.value = v;
    out.relative_degree = 1;
    Ok(())
}

/// `e = M_kᵀ g + [γ·value; 0]`, `cov = (gᵀAg) B_k` with `g = ws.grad`.
fn rd1(ws: &MomentWorkspace, value: f64, gain: f64, out: &mut ConditionMoments) {
    let (n, p) = (ws.post.mean.nrows(), ws.post.mean.ncols());
    let g = &ws.grad;
    for c in 0..p {
        out.e[c] = (0..n).map(|i| ws.post.mean[(i, c)] * g[i]).sum();
    }
    out.e[0] += gain * value;
    let mut gag = 0.0;
    for i in 0..n {
        for j in 0..n {
            gag += g[i] * ws.a_mat[(i, j)] * g[j];
        }
    }
    for a in 0..p {
        for b in 0..p {
            out.cov[(a, b)] = gag * ws.post.B[(a, b)];
        }
    }
    psd_factor(&out.cov, &mut out.v);
}

/// Exact relative-degree-2 moments (module docs).
///
/// The functionals are `a_i` (`i < n`), `y_{c,l}` (`c ≤ m`, `l < n`) and
/// `b = ∇hᵀf`; each is a sum of terms `vᵀ 𝕄 e_q` (a vector `v` against one
/// column `q` of `𝕄 = [F ∂_1F … ∂_nF]`): `a_i = H_iᵀ 𝕄 e_0 + gᵀ 𝕄 e_{q_i}`
/// with `H_i` the `i`-th row of `∇²h`, `g = ∇h`, `q_i` the drift column of
/// `∂_iF` (column `1 + m + i` of the workspace's joint posterior, which
/// keeps only `F` and the drift columns, `Columns::Drift`);
/// `y_{c,l} = e_lᵀ 𝕄 e_c`;
/// `b = gᵀ 𝕄 e_0`. Under
/// `Cov(vec 𝕄) = Ĉ ⊗ A` two such terms covary by `(vᵀAw) Ĉ_{qq'}`, so
/// every entry of `S` follows from `AH`, `HAH`, `Ag`, `HAg` and `gᵀAg`:
/// `O(n³ + n²(1+m)²)` in all, where forming `Wᵀ(Ĉ ⊗ A)W` for the
/// coefficient matrix `W` of the functionals costs `O(n⁵(1+m)³)` (the
/// brute-force construction the tests check this against).
fn rd2(ws: &mut MomentWorkspace, h: f64, k0: f64, k1: f64, out: &mut ConditionMoments) {
    let n = ws.x.len();
    let p = out.e.len();
    // functionals: r = 0..n → a_i; n + c n + l → y_{c,l}; n + np → b = ∇hᵀ f
    let ia = |i: usize| i;
    let iy = |c: usize, l: usize| n + c * n + l;
    let ib = n + n * p;
    let qd = |i: usize| p + i;
    let (g, hess, a, cm, mean) = (&ws.grad, &ws.hess, &ws.a_mat, &ws.joint.c, &ws.joint.mean);
    // AH (column i = A H_i), Ag, HAH, HAg, gᵀAg
    for i in 0..n {
        let mut sg = 0.0;
        for l in 0..n {
            let mut s = 0.0;
            for j in 0..n {
                s += a[(l, j)] * hess[i * n + j];
            }
            ws.ah[(l, i)] = s;
            sg += a[(i, l)] * g[l];
        }
        ws.ag[i] = sg;
    }
    let mut gag = 0.0;
    for i in 0..n {
        gag += g[i] * ws.ag[i];
        let mut s = 0.0;
        for l in 0..n {
            s += hess[i * n + l] * ws.ag[l];
        }
        ws.hag[i] = s;
        for j in 0..=i {
            let mut s = 0.0;
            for l in 0..n {
                s += hess[i * n + l] * ws.ah[(l, j)];
            }
            ws.hah[(i, j)] = s;
            ws.hah[(j, i)] = s;
        }
    }
    // means μ_r = w_rᵀ vec 𝕄
    for i in 0..n {
        let mut s = 0.0;
        for l in 0..n {
            s += hess[i * n + l] * mean[(l, 0)] + g[l] * mean[(l, qd(i))];
        }
        ws.mu[ia(i)] = s;
    }
    for c in 0..p {
        for l in 0..n {
            ws.mu[iy(c, l)] = mean[(l, c)];
        }
    }
    ws.mu[ib] = (0..n).map(|l| g[l] * mean[(l, 0)]).sum();
    // S = Cov of the functionals, entry by entry
    let sm = &mut ws.s;
    for i in 0..n {
        for j in 0..=i {
            let v = ws.hah[(i, j)] * cm[(0, 0)]
                + ws.hag[i] * cm[(0, qd(j))]
                + ws.hag[j] * cm[(qd(i), 0)]
                + gag * cm[(qd(i), qd(j))];
            sm[(ia(i), ia(j))] = v;
            sm[(ia(j), ia(i))] = v;
        }
        for c in 0..p {
            for l in 0..n {
                let v = ws.ah[(l, i)] * cm[(0, c)] + ws.ag[l] * cm[(qd(i), c)];
                sm[(ia(i), iy(c, l))] = v;
                sm[(iy(c, l), ia(i))] = v;
            }
        }
        let v = ws.hag[i] * cm[(0, 0)] + gag * cm[(qd(i), 0)];
        sm[(ia(i), ib)] = v;
        sm[(ib, ia(i))] = v;
    }
    for c in 0..p {
        for l in 0..n {
            for d in 0..p {
                for j in 0..n {
                    sm[(iy(c, l), iy(d, j))] = a[(l, j)] * cm[(c, d)];
                }
            }
            let v = ws.ag[l] * cm[(c, 0)];
            sm[(iy(c, l), ib)] = v;
            sm[(ib, iy(c, l))] = v;
        }
    }
    sm[(ib, ib)] = gag * cm[(0, 0)];
    let s = &ws.s;
    let mu = &ws.mu;
    for c in 0..p {
        let mut e = 0.0;
        for i in 0..n {
            e += mu[ia(i)] * mu[iy(c, i)] + s[(ia(i), iy(c, i))];
        }
        if c == 0 {
            e += k1 * mu[ib] + k0 * h;
        }
        out.e[c] = e;
    }
    for c in 0..p {
        for d in 0..=c {
            let mut v = 0.0;
            for i in 0..n {
                let (ai, yci) = (ia(i), iy(c, i));
                for j in 0..n {
                    let (aj, ydj) = (ia(j), iy(d, j));
                    v += s[(ai, aj)] * s[(yci, ydj)]
                        + s[(ai, ydj)] * s[(yci, aj)]
                        + mu[ai] * mu[aj] * s[(yci, ydj)]
                        + mu[ai] * mu[ydj] * s[(yci, aj)]
                        + mu[yci] * mu[aj] * s[(ai, ydj)]
                        + mu[yci] * mu[ydj] * s[(ai, aj)];
                }
            }
            // linear term k1 b in z_0
            if d == 0 {
                for i in 0..n {
                    v += k1 * (mu[iy(c, i)] * s[(ia(i), ib)] + mu[ia(i)] * s[(iy(c, i), ib)]);
                }
            }
            if c == 0 {
                for j in 0..n {
                    v += k1 * (mu[iy(d, j)] * s[(ia(j), ib)] + mu[ia(j)] * s[(iy(d, j), ib)]);
                }
            }
            if c == 0 && d == 0 {
                v += k1 * k1 * s[(ib, ib)];
            }
            out.cov[(c, d)] = v;
            out.cov[(d, c)] = v;
        }
    }
    psd_factor(&out.cov, &mut out.v);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gp::{InputMap, MvgpHyper, PriorMean, Rbf};
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// `h(x) = xᵀQx + bᵀx + 1` over states `x0, x1, …` as an expression,
    /// relative degree 2 with gains `[1, 2]`: a full Hessian.
    fn quadratic(q: &DMatrix<f64>, b: &[f64]) -> crate::barrier::ExpressionBarrier {
        let n = b.len();
        let names: Vec<String> = (0..n).map(|i| format!("x{i}")).collect();
        let mut h = "1".to_string();
        for i in 0..n {
            h += &format!(" + ({}) * x{i}", b[i]);
            for j in 0..n {
                h += &format!(" + ({}) * x{i} * x{j}", q[(i, j)]);
            }
        }
        crate::barrier::ExpressionBarrier::new(&names, &[], &h, 2, vec![1.0, 2.0]).unwrap()
    }

    fn random_matrix(r: usize, c: usize, rng: &mut ChaCha8Rng) -> DMatrix<f64> {
        DMatrix::from_fn(r, c, |_, _| rng.random_range(-1.0..1.0))
    }

    /// The functionals' means and covariance the brute-force way: the
    /// coefficient matrix `W` (`n(1+m)(1+n) × R`) written column by column
    /// from the definitions of `a_i`, `y_{c,l}` and `b`, then
    /// `μ = Wᵀ vec 𝕄` and `S = Wᵀ (Ĉ ⊗ A) W` with the Kronecker product
    /// built in full, from the full joint posterior of `F` and its Jacobian.
    fn brute_force(
        ws: &MomentWorkspace,
        joint: &JointPosterior,
        p: usize,
    ) -> (Vec<f64>, DMatrix<f64>) {
        let n = ws.x.len();
        let pp = p * (1 + n);
        let rr = n + n * p + 1;
        let idx = |l: usize, q: usize| l + n * q;
        let mut w = DMatrix::zeros(n * pp, rr);
        for i in 0..n {
            for l in 0..n {
                w[(idx(l, 0), i)] += ws.hess[i * n + l];
                w[(idx(l, (i + 1) * p), i)] += ws.grad[l];
            }
        }
        for c in 0..p {
            for l in 0..n {
                w[(idx(l, c), n + c * n + l)] = 1.0;
            }
        }
        for l in 0..n {
            w[(idx(l, 0), n + n * p)] = ws.grad[l];
        }
        let vec_m = DMatrix::from_column_slice(n * pp, 1, joint.mean.as_slice());
        let mu = (w.transpose() * vec_m).as_slice().to_vec();
        let s = w.transpose() * joint.c.kronecker(&ws.a_mat) * &w;
        (mu, s)
    }

    #[test]
    fn rd2_functionals_equal_the_full_kronecker_construction() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for (n, m) in [(1, 1), (2, 1), (3, 2), (4, 3), (5, 1), (2, 4)] {
            let g = random_matrix(n, n, &mut rng);
            let gb = random_matrix(m + 1, m + 1, &mut rng);
            let hyper = MvgpHyper {
                kernel: Rbf::new(vec![1.1; n], 0.8).unwrap(),
                A: &g * g.transpose() + DMatrix::identity(n, n) * 0.1,
                B: &gb * gb.transpose() + DMatrix::identity(m + 1, m + 1) * 0.1,
                sigma: 0.2,
            };
            let mut model = Mvgp::new(n, m, hyper, PriorMean::Zero, InputMap::Identity).unwrap();
            let k = 9;
            let xs: Vec<f64> = (0..k * n).map(|_| rng.random_range(-1.5..1.5)).collect();
            let us: Vec<f64> = (0..k * m).map(|_| rng.random_range(-1.0..1.0)).collect();
            let xd: Vec<f64> = (0..k * n).map(|_| rng.random_range(-1.0..1.0)).collect();
            model.set_data(&xs, &us, &xd).unwrap();
            let q = random_matrix(n, n, &mut rng);
            let b: Vec<f64> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
            let barrier = quadratic(&(&q + q.transpose()), &b);
            let x: Vec<f64> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
            let mut ws = MomentWorkspace::new(&model);
            ws.update(&model, &x, 2).unwrap();
            let mut out = ConditionMoments::zeros(m);
            cbc_moments(&mut ws, &barrier, &mut out).unwrap();
            let (mu, s) = brute_force(&ws, &model.joint_posterior(&x).unwrap(), m + 1);
            let scale = s.amax().max(1.0);
            for (r, (a, b)) in ws.mu.iter().zip(&mu).enumerate() {
                assert!(
                    (a - b).abs() <= 1e-12 * scale,
                    "n={n} m={m} μ[{r}]: {a} vs {b}"
                );
            }
            assert_eq!(ws.s.shape(), s.shape());
            for ((r, c), a) in s
                .iter()
                .enumerate()
                .map(|(t, a)| ((t % s.nrows(), t / s.nrows()), a))
            {
                let b = ws.s[(r, c)];
                assert!(
                    (a - b).abs() <= 1e-12 * scale,
                    "n={n} m={m} S[{r},{c}]: {b} vs {a}"
                );
            }
        }
    }
}

#[cfg(test)]
mod size_tests {
    use super::*;

    /// A model of 2200 states and 2199 controls (allowed) asks the
    /// relative-degree-2 buffers for about 1.9·10¹⁴ bytes: an error naming
    /// `state_dim`, not an abort; relative degree 1 needs none of them.
    #[test]
    fn second_order_buffers_too_large_are_an_error() {
        // beyond the 2⁴⁷-byte address space of x86-64 and AArch64 (1.4·10¹⁴
        // bytes): refused whatever the kernel's overcommit setting
        let (n, m) = (2200, 2199);
        let model = crate::gp::plain_model(n, m, 1.0, 1.0, 0.1);
        let x = vec![0.0; n];
        let mut ws = MomentWorkspace::new(&model);
        ws.update(&model, &x, 1).unwrap();
        assert_eq!(ws.s.nrows(), 0);
        let err = ws.update(&model, &x, 2).unwrap_err().to_string();
        assert!(
            err.contains(
                "invalid state_dim = 2200: relative-degree-2 moments at 2200 states and \
                 2199 controls need"
            ) && err.contains("GB of buffers (the joint posterior"),
            "{err}"
        );
    }
}
