//! Matrix-variate Gaussian process regression of `F(x) = [f(x) g(x)]`
//! (paper, Sec. IV, Prop. 1).

use super::data::{check_batch, check_point, check_state, TrainingData};
use super::factor::{CholFactor, Pivot};
use super::input_map::InputMap;
use super::kernel::{Kernel, Rbf};
use super::prior::PriorMean;
use super::simd::with_faer;
use crate::error::{check_positive, Error, GpError, InputError};
use faer::Mat;
use nalgebra::DMatrix;
use std::sync::OnceLock;

mod budget;

/// How far the data stray from a known row of `F`
/// ([`Mvgp::known_row_misfit`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KnownRowMisfit {
    /// The known row `i`.
    pub row: usize,
    /// Root mean square over the observations of the misfit
    /// `e_j = ẋ_j[i] − (M0(x_j) u̲_j)[i]`.
    pub rms_misfit: f64,
    /// Root mean square of the labels `ẋ_j[i]`.
    pub rms_label: f64,
    /// The largest `|e_j|` on the row.
    pub max_misfit: f64,
    /// Its observation `j` (0 = oldest).
    pub observation: usize,
    /// How much of the misfit is a function of the inputs rather than
    /// noise: `Σ_j e_j e_{ν(j)} / Σ_j e_j²`, with `ν(j)` the observation
    /// nearest to `j` in the kernel's inputs and the controls (each
    /// coordinate scaled by its spread over the data). Near 1 when the
    /// prior is wrong (neighbours share the error), near 0 or below for
    /// label noise, which neighbours do not share.
    pub smooth_share: f64,
}

/// Fewest observations on which [`Mvgp::known_row_misfit`] judges a known
/// row.
pub const KNOWN_ROW_MIN_OBSERVATIONS: usize = 10;

impl KnownRowMisfit {
    /// Whether the prior mean, not noise or the labels' own error, is off
    /// on the row: the misfit varies smoothly with the inputs
    /// (`smooth_share > 0.5`) and is more than half the labels (a finite
    /// difference's O(dt) error on a right row is far less; the warning is
    /// for a row the prior does not give at all).
    pub fn is_large(&self) -> bool {
        self.smooth_share > 0.5 && self.rms_misfit > 0.5 * self.rms_label
    }

    /// A one-line explanation for a warning.
    pub fn describe(&self) -> String {
        let percent = 100.0 * self.rms_misfit / self.rms_label.max(f64::MIN_POSITIVE);
        // labels of (nearly) zero size make the share astronomical: no
        // hundreds of digits
        let percent = if percent < 1e6 {
            format!("{percent:.0}")
        } else {
            format!("{percent:.1e}")
        };
        format!(
            "row {} of F is declared known, but the data differ from the prior mean's \
             value on it by {:.3e} (root mean square; {percent} % of the labels', at most \
             {:.3e} at observation {}), in a way that follows the state and control \
             rather than noise: the prior mean does not give this row, and the model \
             ignores what the data say about it",
            self.row, self.rms_misfit, self.max_misfit, self.observation
        )
    }
}

/// Hyperparameters of an MVGP with `B0(x, x') = B k0(x, x')`:
/// `vec F ~ GP(vec M0, B k0 ⊗ A)`, noise `w ~ N(0, σ² A)`.
#[derive(Debug, Clone, PartialEq)]
#[allow(non_snake_case)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct MvgpHyper<K: Kernel = Rbf> {
    /// Scalar kernel `k0`.
    pub kernel: K,
    /// Row covariance `A ∈ R^{n×n}` (symmetric positive definite).
    pub A: DMatrix<f64>,
    /// Column covariance `B ∈ R^{(1+m)×(1+m)}` (symmetric positive definite).
    pub B: DMatrix<f64>,
    /// Noise scale `σ > 0`: `Cov(w) = σ² A`.
    pub sigma: f64,
}

/// Checks that `m` is square of size `dim`, finite, symmetric and positive
/// definite, naming it `field` in the error.
pub fn check_spd(field: &str, m: &DMatrix<f64>, dim: usize) -> Result<(), InputError> {
    if m.nrows() != dim || m.ncols() != dim {
        return Err(InputError::shape(
            field,
            format!("{dim}×{dim}"),
            format!("{}×{}", m.nrows(), m.ncols()),
        ));
    }
    for i in 0..dim {
        for j in 0..dim {
            let v = m[(i, j)];
            if !v.is_finite() {
                return Err(InputError::invalid(
                    &format!("{field}[{i}][{j}]"),
                    v,
                    "must be finite",
                ));
            }
            let w = m[(j, i)];
            if (v - w).abs() > 1e-9 * (1.0 + v.abs().max(w.abs())) {
                return Err(InputError::NotPositiveDefinite {
                    field: field.into(),
                    reason: format!("not symmetric: [{i}][{j}] = {v} but [{j}][{i}] = {w}"),
                });
            }
        }
    }
    if m.clone().cholesky().is_none() {
        let ev = m.clone().symmetric_eigenvalues();
        let min = ev.iter().cloned().fold(f64::INFINITY, f64::min);
        return Err(InputError::NotPositiveDefinite {
            field: field.into(),
            reason: format!("smallest eigenvalue {min:.3e} ≤ 0"),
        });
    }
    Ok(())
}

impl<K: Kernel> MvgpHyper<K> {
    /// Lower Cholesky factors `(L_A, L_B)` of `A` and `B`, for sampling
    /// `vec F ~ N(·, B ⊗ A)` as `L_A Z L_Bᵀ`.
    pub fn cholesky_factors(&self) -> Result<(DMatrix<f64>, DMatrix<f64>), InputError> {
        let chol = |field: &str, m: &DMatrix<f64>| {
            m.clone()
                .cholesky()
                .map(|c| c.l())
                .ok_or_else(|| InputError::NotPositiveDefinite {
                    field: field.into(),
                    reason: "Cholesky failed".into(),
                })
        };
        Ok((chol("A", &self.A)?, chol("B", &self.B)?))
    }

    /// Validates shapes and positivity for state dim `n`, control dim `m`,
    /// kernel input dim `d`.
    pub fn validate(&self, n: usize, m: usize, d: usize) -> Result<(), InputError> {
        super::check_dims(n, m)?;
        if self.kernel.input_dim() != d {
            return Err(InputError::shape(
                "kernel.lengthscales",
                d,
                self.kernel.input_dim(),
            ));
        }
        check_spd("A", &self.A, n)?;
        check_spd("B", &self.B, m + 1)?;
        check_positive("noise_sigma", self.sigma)?;
        // the noise covariance σ²A must be finite
        if !(self.sigma * self.sigma * self.A.amax()).is_finite() {
            return Err(InputError::invalid(
                "noise_sigma",
                self.sigma,
                "too large: σ² or the noise covariance σ²A overflows",
            ));
        }
        Ok(())
    }
}

/// Posterior of `vec F(x)` at one point: `N(vec M_k(x), B_k(x, x) ⊗ A)`.
#[derive(Debug, Clone, PartialEq)]
#[allow(non_snake_case)]
pub struct Posterior {
    /// `M_k(x)`, `n × (1+m)`.
    pub mean: DMatrix<f64>,
    /// `B_k(x, x)`, `(1+m) × (1+m)`.
    pub B: DMatrix<f64>,
}

/// Reusable buffers for posterior queries, so that repeated queries allocate
/// nothing once warmed up. Create with [`Mvgp::workspace`].
#[derive(Debug, Clone)]
pub struct PosteriorWorkspace {
    pub(crate) z: Vec<f64>,
    pub(crate) kvec: Vec<f64>,
    /// `W = (𝓑(x)U̲)ᵀ`, then `V = L⁻¹ W` in place: `k × (1+m)`.
    pub(crate) w: Mat<f64>,
    pub(crate) m0: Vec<f64>,
}

/// An MVGP model of `F(x)` with its training data and factorised Gram matrix.
///
/// Observations are `ẋ_j = F(x_j) u̲_j + w_j`, `w_j ~ N(0, σ² A)`. The Gram
/// matrix is `G = K + σ² I` with `K_ij = u̲_iᵀ B u̲_j k0(x_i, x_j)`
/// (the correct form of Prop. 1: σ² belongs in the Gram matrix).
///
/// ## Reference
/// Paper, Prop. 1, Eq. (12):
/// `M_k(x) = M0(x) + (Ẋ − 𝓜U̲) G⁻¹ (𝓑(x)U̲)ᵀ`,
/// `B_k(x,x') = B0(x,x') − 𝓑(x)U̲ G⁻¹ (𝓑(x')U̲)ᵀ`,
/// `𝓑(x)U̲ = [B0(x,x_1)u̲_1 … B0(x,x_k)u̲_k]`.
#[derive(Debug, Clone)]
pub struct Mvgp<K: Kernel = Rbf> {
    n: usize,
    m: usize,
    hyper: MvgpHyper<K>,
    prior: PriorMean,
    input_map: InputMap,
    data: TrainingData,
    /// `B u̲_j`, row-major `k × (1+m)`.
    bu: Vec<f64>,
    factor: CholFactor,
    /// `β = L⁻¹ Rᵀ`, `k × n` (rows beyond `k` are capacity).
    beta: Mat<f64>,
    /// `α = G⁻¹ Rᵀ = L⁻ᵀ β`, computed on demand.
    alpha: OnceLock<Mat<f64>>,
    scratch: Vec<f64>,
    /// `diag(G⁻¹)` for the budget policy, maintained once requested.
    info: budget::InfoTracker,
    /// Rows of `F` known exactly from the prior mean (not learned).
    known: Vec<usize>,
    /// `A` with the known rows and columns zeroed: the row covariance of
    /// the model (`Cov(vec F(x)) = B_k(x, x) ⊗ row_cov`).
    row_cov: DMatrix<f64>,
}

impl<K: Kernel> Mvgp<K> {
    /// A model with no data (the prior), validated.
    pub fn new(
        n: usize,
        m: usize,
        hyper: MvgpHyper<K>,
        prior: PriorMean,
        input_map: InputMap,
    ) -> Result<Self, InputError> {
        super::prior::check_model_dims(n, m, &input_map, &prior)?;
        hyper.validate(n, m, input_map.output_dim(n))?;
        let row_cov = hyper.A.clone();
        Ok(Self {
            n,
            m,
            hyper,
            prior,
            input_map,
            data: TrainingData::default(),
            bu: Vec::new(),
            factor: CholFactor::default(),
            beta: Mat::zeros(0, n),
            alpha: OnceLock::new(),
            scratch: Vec::new(),
            info: budget::InfoTracker::default(),
            known: Vec::new(),
            row_cov,
        })
    }

    /// Declares the rows of `F` in `rows` known exactly from the prior mean
    /// (partially known dynamics, e.g. a kinematic row `θ̇ = ω`): their
    /// posterior is the prior mean with zero variance, and only the other
    /// rows are learned.
    ///
    /// Since the posterior mean `M_k = M0 + R G⁻¹ 𝓑U̲ᵀ` does not involve `A`
    /// and the covariance is `B_k ⊗ A`, this is the MVGP whose `A` has
    /// zero rows and columns at the known rows: their residuals are set to
    /// zero (the label is the prior's value), their variance is zero, and
    /// the likelihood is that of the learned rows alone (`A` restricted to
    /// them). `A`'s entries on known rows are kept but unused.
    ///
    /// Refactorises the data, if any (O(k³)).
    pub fn with_known_rows(mut self, rows: &[usize]) -> Result<Self, Error> {
        let mut known = rows.to_vec();
        known.sort_unstable();
        known.dedup();
        if known.len() != rows.len() {
            return Err(InputError::invalid_shown(
                "known_rows",
                format!("{rows:?}"),
                "rows must be distinct",
            )
            .into());
        }
        if let Some(j) = rows.iter().position(|&r| r >= self.n) {
            return Err(InputError::invalid_shown(
                &format!("known_rows[{j}]"),
                rows[j],
                &format!("is not a row of F (state_dim = {})", self.n),
            )
            .into());
        }
        if known.len() == self.n {
            return Err(InputError::Invalid {
                field: "known_rows".into(),
                value: format!("{known:?}"),
                reason: "every row is known: nothing is left to learn".into(),
            }
            .into());
        }
        self.known = known;
        self.update_row_cov();
        if !self.is_empty() {
            let (xs, xdot) = (self.data.xs.clone(), self.data.xdot.clone());
            let us = self.controls();
            self.set_data(&xs, &us, &xdot)?;
        }
        Ok(self)
    }

    /// Rows of `F` known exactly (sorted).
    pub fn known_rows(&self) -> &[usize] {
        &self.known
    }

    /// How far the data stray from the known rows: for each known row `i`
    /// the misfits `e_j = ẋ_j[i] − (M0(x_j) u̲_j)[i]` over the observations
    /// `j`, summarised ([`KnownRowMisfit`]) for the row whose misfit is the
    /// largest share of its labels; `None` without known rows or with fewer
    /// than [`KNOWN_ROW_MIN_OBSERVATIONS`] observations (the first steps of
    /// a run, whose finite-difference labels near rest are all error, tell
    /// no trend). The posterior replaces these labels by the
    /// prior's value, so a large misfit ([`KnownRowMisfit::is_large`]) says
    /// that the prior mean does not give the row (a kinematic row `θ̇ = ω`
    /// declared known under a zero prior mean, for one). O(k²) for the
    /// nearest neighbours, O(k) prior evaluations.
    pub fn known_row_misfit(&self) -> Option<KnownRowMisfit> {
        let (n, p, k) = (self.n, self.m + 1, self.len());
        if self.known.is_empty() || k < KNOWN_ROW_MIN_OBSERVATIONS {
            return None;
        }
        let nearest = self.nearest_observations();
        let r = self.known.len();
        // misfits, row-major k × r
        let mut e = vec![0.0; k * r];
        let mut m0 = vec![0.0; n * p];
        for j in 0..k {
            let x = &self.data.xs[j * n..(j + 1) * n];
            let u = &self.data.us[j * p..(j + 1) * p];
            self.prior.eval(x, &mut m0);
            for (q, &i) in self.known.iter().enumerate() {
                let mean: f64 = (0..p).map(|c| m0[c * n + i] * u[c]).sum();
                e[j * r + q] = self.data.xdot[j * n + i] - mean;
            }
        }
        let summary = |q: usize| {
            let i = self.known[q];
            let (mut sq, mut labels, mut shared, mut max, mut at) = (0.0, 0.0, 0.0, 0.0, 0);
            for j in 0..k {
                let ej = e[j * r + q];
                let label = self.data.xdot[j * n + i];
                sq += ej * ej;
                labels += label * label;
                shared += ej * e[nearest[j] * r + q];
                if ej.abs() > max {
                    (max, at) = (ej.abs(), j);
                }
            }
            KnownRowMisfit {
                row: i,
                rms_misfit: (sq / k as f64).sqrt(),
                rms_label: (labels / k as f64).sqrt(),
                max_misfit: max,
                observation: at,
                smooth_share: if sq > 0.0 { shared / sq } else { 0.0 },
            }
        };
        let share = |m: &KnownRowMisfit| m.rms_misfit / m.rms_label.max(f64::MIN_POSITIVE);
        (0..r)
            .map(summary)
            .fold(None, |best: Option<KnownRowMisfit>, m| match best {
                Some(b) if share(&b) >= share(&m) => Some(b),
                _ => Some(m),
            })
    }

    /// For each observation, the nearest other one in the kernel's inputs
    /// `z = φ(x)` and the controls, each coordinate scaled by its standard
    /// deviation over the data (a constant coordinate is left out). O(k²).
    fn nearest_observations(&self) -> Vec<usize> {
        let (k, p) = (self.len(), self.m + 1);
        let d = self.data.zs.len() / k;
        let coords = |j: usize| {
            self.data.zs[j * d..(j + 1) * d]
                .iter()
                .chain(&self.data.us[j * p + 1..(j + 1) * p])
                .copied()
        };
        let dim = d + p - 1;
        let (mut mean, mut sq) = (vec![0.0; dim], vec![0.0; dim]);
        for j in 0..k {
            for (c, v) in coords(j).enumerate() {
                mean[c] += v / k as f64;
                sq[c] += v * v / k as f64;
            }
        }
        let scale: Vec<f64> = mean
            .iter()
            .zip(&sq)
            .map(|(m, s)| {
                let var = (s - m * m).max(0.0);
                if var > 0.0 {
                    1.0 / var.sqrt()
                } else {
                    0.0
                }
            })
            .collect();
        (0..k)
            .map(|j| {
                let mut best = (f64::INFINITY, if j == 0 { 1 } else { 0 });
                for l in (0..k).filter(|&l| l != j) {
                    let dist: f64 = coords(j)
                        .zip(coords(l))
                        .zip(&scale)
                        .map(|((a, b), w)| ((a - b) * w).powi(2))
                        .sum();
                    if dist < best.0 {
                        best = (dist, l);
                    }
                }
                best.1
            })
            .collect()
    }

    /// Rows of `F` that are learned (sorted).
    pub fn learned_rows(&self) -> Vec<usize> {
        (0..self.n).filter(|i| !self.known.contains(i)).collect()
    }

    /// The row covariance of the model: `A` with known rows and columns
    /// zeroed, so that `Cov(vec F(x)) = B_k(x, x) ⊗ row_cov()`.
    pub fn row_cov(&self) -> &DMatrix<f64> {
        &self.row_cov
    }

    /// A factor `L` with `L Lᵀ = row_cov()`: the Cholesky factor of `A`
    /// restricted to the learned rows, zero on the known rows (for drawing
    /// `F`).
    pub fn row_cov_factor(&self) -> Result<DMatrix<f64>, InputError> {
        let rows = self.learned_rows();
        let r = rows.len();
        let a = DMatrix::from_fn(r, r, |i, j| self.hyper.A[(rows[i], rows[j])]);
        let l = a
            .cholesky()
            .ok_or_else(|| InputError::NotPositiveDefinite {
                field: "A".into(),
                reason: "the learned rows' block has no Cholesky factor".into(),
            })?
            .l();
        let mut full = DMatrix::zeros(self.n, self.n);
        for (i, &ri) in rows.iter().enumerate() {
            for (j, &rj) in rows.iter().enumerate() {
                full[(ri, rj)] = l[(i, j)];
            }
        }
        Ok(full)
    }

    fn update_row_cov(&mut self) {
        self.row_cov.copy_from(&self.hyper.A);
        for &r in &self.known {
            self.row_cov.row_mut(r).fill(0.0);
            self.row_cov.column_mut(r).fill(0.0);
        }
    }

    shared_model_accessors!(MvgpHyper<K>);
    /// Number of observations `k`.
    pub fn len(&self) -> usize {
        self.factor.len()
    }
    /// Cholesky factor of `K + σ²I`.
    pub fn factor(&self) -> &CholFactor {
        &self.factor
    }
    fn push_point(&mut self, x: &[f64], u: &[f64], xdot: &[f64]) {
        let (n, p) = (self.n, self.m + 1);
        let uoff = self.data.us.len();
        self.data.push(x, u, xdot, &self.input_map);
        let us = &self.data.us;
        let mut m0 = vec![0.0; n * p];
        self.prior.eval(x, &mut m0);
        for i in 0..n {
            let mut r = xdot[i];
            for c in 0..p {
                r -= m0[i + n * c] * us[uoff + c];
            }
            // known rows: the label is the prior's value
            if self.known.contains(&i) {
                r = 0.0;
            }
            self.data.resid.push(r);
        }
        for a in 0..p {
            let mut s = 0.0;
            for c in 0..p {
                s += self.hyper.B[(a, c)] * us[uoff + c];
            }
            self.bu.push(s);
        }
    }

    /// `G_ij = u̲_iᵀ B u̲_j k0(z_i, z_j) + σ² δ_ij`.
    #[inline]
    fn gram_entry(&self, i: usize, j: usize) -> f64 {
        let p = self.m + 1;
        let d = self.input_map.output_dim(self.n);
        let kv = self.hyper.kernel.value(
            &self.data.zs[i * d..(i + 1) * d],
            &self.data.zs[j * d..(j + 1) * d],
        );
        let ubu: f64 = (0..p)
            .map(|c| self.data.us[i * p + c] * self.bu[j * p + c])
            .sum();
        let mut g = ubu * kv;
        if i == j {
            g += self.hyper.sigma * self.hyper.sigma;
        }
        g
    }

    /// Replaces the training data and factorises `K + σ²I` from scratch.
    ///
    /// `xs` is `k × n`, `us` is `k × m`, `xdot` is `k × n`, all row-major.
    pub fn set_data(&mut self, xs: &[f64], us: &[f64], xdot: &[f64]) -> Result<(), Error> {
        let (n, m) = (self.n, self.m);
        let k = check_batch(n, m, xs, us, xdot)?;
        self.clear();
        for j in 0..k {
            self.push_point(
                &xs[j * n..(j + 1) * n],
                &us[j * m..(j + 1) * m],
                &xdot[j * n..(j + 1) * n],
            );
        }
        if let Err(e) = self.prior.check() {
            self.clear();
            return Err(e.into());
        }
        self.refactor()?;
        Ok(())
    }

    fn clear(&mut self) {
        self.data.clear();
        self.bu.clear();
        self.factor = CholFactor::default();
        self.beta = Mat::zeros(0, self.n);
        self.alpha = OnceLock::new();
        self.info.reset();
    }

    /// Recomputes the factor and `β` from the stored data (O(k³)).
    pub fn refactor(&mut self) -> Result<(), GpError> {
        let k = self.data.xs.len() / self.n;
        let mut g = Mat::<f64>::zeros(k, k);
        for j in 0..k {
            for i in j..k {
                g[(i, j)] = self.gram_entry(i, j);
            }
        }
        let cap = k + k / 2 + 8;
        self.factor = CholFactor::factor(g.as_ref(), cap)?;
        self.beta = Mat::zeros(cap, self.n);
        for j in 0..k {
            for i in 0..self.n {
                self.beta[(j, i)] = self.data.resid[j * self.n + i];
            }
        }
        self.factor
            .solve_l(self.beta.as_mut().submatrix_mut(0, 0, k, self.n));
        self.alpha = OnceLock::new();
        self.scratch.resize(4 * cap + 1, 0.0);
        self.info.reset();
        Ok(())
    }

    /// Adds one observation `(x, u, ẋ)`, growing the Cholesky factor by one
    /// row (one triangular solve, O(k²); no refactorisation).
    pub fn add_observation(&mut self, x: &[f64], u: &[f64], xdot: &[f64]) -> Result<(), Error> {
        let pivot = self.stage_observation(x, u, xdot)?;
        self.commit_observation(pivot);
        Ok(())
    }

    /// Stores the point and finds its factor row: `scratch[..k] = L⁻¹ g`
    /// with `g_i = G[k, i]`, and the pivot (one triangular solve). The
    /// model is unchanged but for the stored point until
    /// [`commit_observation`](Self::commit_observation), or
    /// [`pop_last_point`](Self::pop_last_point) to drop it; on error the
    /// point is dropped.
    fn stage_observation(&mut self, x: &[f64], u: &[f64], xdot: &[f64]) -> Result<Pivot, Error> {
        let k = self.len();
        check_point(self.n, self.m, x, u, xdot, k)?;
        self.push_point(x, u, xdot);
        if let Err(e) = self.prior.check() {
            self.pop_last_point();
            return Err(e.into());
        }
        let mut gcol = std::mem::take(&mut self.scratch);
        gcol.resize((2 * (k + 1)).max(gcol.len()), 0.0);
        let (g_new, row) = gcol.split_at_mut(k + 1);
        for (i, gi) in g_new.iter_mut().enumerate().take(k) {
            *gi = self.gram_entry(k, i);
        }
        let diag = self.gram_entry(k, k);
        let res = self.factor.pivot(&g_new[..k], diag, row);
        // the row moves to the front of the scratch
        gcol.copy_within(k + 1..2 * k + 1, 0);
        self.scratch = gcol;
        res.map_err(|e| {
            self.pop_last_point();
            e.into()
        })
    }

    /// Appends the staged row `scratch[..k]`: the factor, `β` and
    /// `diag(G⁻¹)`.
    fn commit_observation(&mut self, pivot: Pivot) {
        self.commit_row(pivot);
        self.info_after_append();
    }

    /// [`commit_observation`](Self::commit_observation) without the update
    /// of `diag(G⁻¹)`: the factor and `β`.
    fn commit_row(&mut self, pivot: Pivot) {
        let k = self.factor.len();
        let n = self.n;
        self.factor.push_row(&self.scratch[..k], pivot);
        // β grows by one row: β_k = (r_k − Σ_j L_kj β_j) / L_kk
        if self.beta.nrows() < k + 1 {
            let cap = (2 * self.beta.nrows()).max(k + 1).max(16);
            let mut nb = Mat::<f64>::zeros(cap, n);
            with_faer(|| {
                nb.as_mut()
                    .submatrix_mut(0, 0, k, n)
                    .copy_from(self.beta.as_ref().submatrix(0, 0, k, n))
            });
            self.beta = nb;
        }
        let l = self.factor.l_ref();
        for i in 0..n {
            let mut s = self.data.resid[k * n + i];
            for j in 0..k {
                s -= l[(k, j)] * self.beta[(j, i)];
            }
            self.beta[(k, i)] = s / l[(k, k)];
        }
        self.alpha = OnceLock::new();
    }

    fn pop_last_point(&mut self) {
        let (n, p) = (self.n, self.m + 1);
        let d = self.input_map.output_dim(n);
        self.data.pop(n, p, d);
        self.bu.truncate(self.bu.len() - p);
    }

    /// Drops the oldest observation (sliding window): a rank-one update of
    /// the factor and the same rotations applied to `β`, O(k²)
    /// ([`remove_observation`](Self::remove_observation)`(0)`).
    pub fn remove_oldest(&mut self) {
        if !self.is_empty() {
            self.remove_observation(0);
        }
    }

    /// A copy of `α = G⁻¹ (Ẋ − 𝓜U̲)ᵀ`, `k × n`.
    pub fn alpha(&self) -> DMatrix<f64> {
        let a = self.alpha_mat();
        DMatrix::from_fn(self.len(), self.n, |j, i| a[(j, i)])
    }

    /// `α = G⁻¹ (Ẋ − 𝓜U̲)ᵀ`, `k × n`, cached until the data change.
    pub(crate) fn alpha_mat(&self) -> &Mat<f64> {
        self.alpha.get_or_init(|| {
            let k = self.len();
            let mut a = with_faer(|| self.beta.as_ref().submatrix(0, 0, k, self.n).to_owned());
            self.factor.solve_lt(a.as_mut());
            a
        })
    }

    /// A workspace for allocation-free posterior queries.
    pub fn workspace(&self) -> PosteriorWorkspace {
        let cap = self.beta.nrows().max(self.len());
        PosteriorWorkspace {
            z: vec![0.0; self.input_map.output_dim(self.n)],
            kvec: vec![0.0; cap],
            w: Mat::zeros(cap, self.m + 1),
            m0: vec![0.0; self.n * (self.m + 1)],
        }
    }

    /// Whether `ws` was made for a model of this shape (state, control and
    /// kernel-input dimensions) and holds its data; a workspace of another
    /// model is remade, not indexed out of its bounds.
    fn fits(&self, ws: &PosteriorWorkspace) -> bool {
        let (k, p) = (self.len(), self.m + 1);
        ws.z.len() == self.input_map.output_dim(self.n)
            && ws.m0.len() == self.n * p
            && ws.w.ncols() == p
            && ws.kvec.len() >= k
            && ws.w.nrows() >= k
    }

    pub(crate) fn check_x(&self, x: &[f64]) -> Result<(), InputError> {
        check_state("x", self.n, x)
    }

    /// Fills `ws.z`, `ws.kvec[..k]` and `ws.w[..k]` with `W = (𝓑(x)U̲)ᵀ`,
    /// row `j` = `k0(x, x_j) (B u̲_j)ᵀ`.
    fn fill_w(&self, x: &[f64], ws: &mut PosteriorWorkspace) {
        let k = self.len();
        let p = self.m + 1;
        if !self.fits(ws) {
            *ws = self.workspace();
        }
        let d = ws.z.len();
        self.input_map.apply(x, &mut ws.z);
        for j in 0..k {
            let kv = self
                .hyper
                .kernel
                .value(&ws.z, &self.data.zs[j * d..(j + 1) * d]);
            ws.kvec[j] = kv;
            for c in 0..p {
                ws.w[(j, c)] = kv * self.bu[j * p + c];
            }
        }
    }

    /// Posterior mean `M_k(x)` only (O(k) with the cached `α`).
    pub fn posterior_mean(&self, x: &[f64]) -> Result<DMatrix<f64>, InputError> {
        self.check_x(x)?;
        let mut ws = self.workspace();
        let (n, p) = (self.n, self.m + 1);
        let mut out = DMatrix::zeros(n, p);
        self.prior.eval(x, &mut ws.m0);
        self.prior.check()?;
        for c in 0..p {
            for i in 0..n {
                out[(i, c)] = ws.m0[i + n * c];
            }
        }
        if self.is_empty() {
            return Ok(out);
        }
        self.fill_w(x, &mut ws);
        let alpha = self.alpha_mat();
        for j in 0..self.len() {
            for c in 0..p {
                let w = ws.w[(j, c)];
                for i in 0..n {
                    out[(i, c)] += alpha[(j, i)] * w;
                }
            }
        }
        Ok(out)
    }

    /// Full posterior at `x`: `M_k(x)` and `B_k(x, x)` (Prop. 1), written
    /// into `out` using `ws`; allocation-free once `ws` and `out` are sized.
    ///
    /// With `V = L⁻¹ W`: `M_k = M0 + βᵀ V`, `B_k = B k0(x,x) − Vᵀ V`.
    pub fn posterior_into(
        &self,
        x: &[f64],
        ws: &mut PosteriorWorkspace,
        out: &mut Posterior,
    ) -> Result<(), InputError> {
        self.check_x(x)?;
        if !self.fits(ws) {
            *ws = self.workspace();
        }
        let (n, p, k) = (self.n, self.m + 1, self.len());
        if out.mean.shape() != (n, p) {
            out.mean = DMatrix::zeros(n, p);
        }
        if out.B.shape() != (p, p) {
            out.B = DMatrix::zeros(p, p);
        }
        self.prior.eval(x, &mut ws.m0);
        self.prior.check()?;
        for c in 0..p {
            for i in 0..n {
                out.mean[(i, c)] = ws.m0[i + n * c];
            }
        }
        self.input_map.apply(x, &mut ws.z);
        let kxx = self.hyper.kernel.value(&ws.z, &ws.z);
        for a in 0..p {
            for b in 0..p {
                out.B[(a, b)] = self.hyper.B[(a, b)] * kxx;
            }
        }
        if k == 0 {
            return Ok(());
        }
        self.fill_w(x, ws);
        let mut v = ws.w.as_mut().submatrix_mut(0, 0, k, p);
        self.factor.solve_l(v.as_mut());
        add_data_part(v.as_ref(), self.beta.as_ref(), &mut out.mean, &mut out.B);
        Ok(())
    }

    /// Full posterior at `x` (allocating convenience wrapper).
    pub fn posterior(&self, x: &[f64]) -> Result<Posterior, InputError> {
        let mut ws = self.workspace();
        let mut out = Posterior {
            mean: DMatrix::zeros(self.n, self.m + 1),
            B: DMatrix::zeros(self.m + 1, self.m + 1),
        };
        self.posterior_into(x, &mut ws, &mut out)?;
        Ok(out)
    }

    /// Posterior cross-covariance factor `B_k(x, x')`.
    #[allow(non_snake_case)]
    pub fn posterior_cov(&self, x: &[f64], x2: &[f64]) -> Result<DMatrix<f64>, InputError> {
        self.check_x(x)?;
        self.check_x(x2)?;
        let (k, p) = (self.len(), self.m + 1);
        let mut ws1 = self.workspace();
        let mut ws2 = self.workspace();
        self.input_map.apply(x, &mut ws1.z);
        self.input_map.apply(x2, &mut ws2.z);
        let k12 = self.hyper.kernel.value(&ws1.z, &ws2.z);
        let mut out = &self.hyper.B * k12;
        if k == 0 {
            return Ok(out);
        }
        self.fill_w(x, &mut ws1);
        self.fill_w(x2, &mut ws2);
        let mut v1 = ws1.w.as_mut().submatrix_mut(0, 0, k, p);
        self.factor.solve_l(v1.as_mut());
        let mut v2 = ws2.w.as_mut().submatrix_mut(0, 0, k, p);
        self.factor.solve_l(v2.as_mut());
        with_faer(|| {
            for a in 0..p {
                for b in 0..p {
                    out[(a, b)] -= v1.as_ref().col(a).transpose() * v2.as_ref().col(b);
                }
            }
        });
        Ok(out)
    }

    /// Exact log marginal likelihood of the stored data:
    /// `vec Ẋ ~ N(vec(𝓜U̲), (K + σ²I) ⊗ A)`,
    /// `log p = −½ [n log|G| + k log|A| + tr(A⁻¹ R G⁻¹ Rᵀ) + nk log 2π]`;
    /// with known rows, `n`, `A` and `R` are those of the learned rows.
    pub fn log_marginal_likelihood(&self) -> f64 {
        let (n, k) = (self.n, self.len());
        if k == 0 {
            return 0.0;
        }
        // R G^{-1} R^T = βᵀ β, on the learned rows (module docs of
        // with_known_rows)
        let rows = self.learned_rows();
        let r = rows.len();
        let b = self.beta.as_ref().submatrix(0, 0, k, n);
        let q = with_faer(|| b.transpose() * b);
        let qn = DMatrix::from_fn(r, r, |i, j| q[(rows[i], rows[j])]);
        let a = DMatrix::from_fn(r, r, |i, j| self.hyper.A[(rows[i], rows[j])]);
        let chol_a = match a.cholesky() {
            Some(c) => c,
            None => return f64::NEG_INFINITY,
        };
        let logdet_a = 2.0 * chol_a.l().diagonal().iter().map(|v| v.ln()).sum::<f64>();
        let tr = (chol_a.inverse() * qn).trace();
        -0.5 * (r as f64 * self.factor.log_det()
            + k as f64 * logdet_a
            + tr
            + (r * k) as f64 * (2.0 * std::f64::consts::PI).ln())
    }

    /// Replaces the hyperparameters (validated) and refactorises; on error
    /// the model keeps its previous hyperparameters and factor.
    pub fn set_hyper(&mut self, hyper: MvgpHyper<K>) -> Result<(), Error> {
        hyper.validate(self.n, self.m, self.input_map.output_dim(self.n))?;
        let old = std::mem::replace(&mut self.hyper, hyper);
        self.update_bu();
        if let Err(e) = self.refactor() {
            // the factor and β are untouched on failure: restore the rest
            self.hyper = old;
            self.update_bu();
            return Err(e.into());
        }
        self.update_row_cov();
        Ok(())
    }

    fn update_bu(&mut self) {
        let p = self.m + 1;
        for j in 0..self.len() {
            for a in 0..p {
                self.bu[j * p + a] = (0..p)
                    .map(|c| self.hyper.B[(a, c)] * self.data.us[j * p + c])
                    .sum();
            }
        }
    }

    /// Rows reserved in the factor and `β` (grows geometrically).
    pub fn capacity(&self) -> usize {
        self.beta.nrows().max(self.len())
    }
    /// `B u̲_j` rows (row-major `k × (1+m)`).
    pub fn bu(&self) -> &[f64] {
        &self.bu
    }
    /// A copy of `β = L⁻¹ Rᵀ`, `k × n`.
    pub fn beta(&self) -> DMatrix<f64> {
        let b = self.beta.as_ref();
        DMatrix::from_fn(self.len(), self.n, |j, i| b[(j, i)])
    }

    /// `β = L⁻¹ Rᵀ`, borrowed (rows beyond [`len`](Self::len) are spare
    /// capacity).
    pub(crate) fn beta_mat(&self) -> faer::MatRef<'_, f64> {
        self.beta.as_ref()
    }
    /// Mapped training inputs (row-major `k × d`).
    pub fn mapped_inputs(&self) -> &[f64] {
        &self.data.zs
    }
    /// `u̲_j` rows (row-major `k × (1+m)`), with the leading 1.
    pub fn augmented_controls(&self) -> &[f64] {
        &self.data.us
    }
    /// Residuals `ẋ_j − M0(x_j) u̲_j` (row-major `k × n`).
    pub fn residuals(&self) -> &[f64] {
        &self.data.resid
    }
}

/// The data part of the posterior (Prop. 1) from `V = L⁻¹ W` (`k × q`,
/// one column per column of the stacked mean) and `β = L⁻¹ Rᵀ` (rows
/// `0..k` used): `mean += βᵀ V` (`n × q`) and `cov −= Vᵀ V` (`q × q`,
/// both triangles).
pub(crate) fn add_data_part(
    v: faer::MatRef<'_, f64>,
    beta: faer::MatRef<'_, f64>,
    mean: &mut DMatrix<f64>,
    cov: &mut DMatrix<f64>,
) {
    let (k, q, n) = (v.nrows(), v.ncols(), mean.nrows());
    with_faer(|| {
        for c in 0..q {
            let vc = v.col(c);
            for i in 0..n {
                mean[(i, c)] += beta.col(i).subrows(0, k).transpose() * vc;
            }
            for a in 0..=c {
                let s = v.col(a).transpose() * vc;
                cov[(a, c)] -= s;
                if a != c {
                    cov[(c, a)] -= s;
                }
            }
        }
    });
}

/// An `n`-state, `m`-control model with no data, a zero prior mean, the
/// identity input map, `A = I`, `B = I`, noise scale `sigma` and an RBF
/// kernel of lengthscale `lengthscale` in every input and output scale
/// `variance`: the plain model of unit tests.
#[cfg(test)]
pub(crate) fn plain_model(n: usize, m: usize, lengthscale: f64, variance: f64, sigma: f64) -> Mvgp {
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![lengthscale; n], variance).unwrap(),
        A: DMatrix::identity(n, n),
        B: DMatrix::identity(m + 1, m + 1),
        sigma,
    };
    Mvgp::new(n, m, hyper, PriorMean::Zero, InputMap::Identity).unwrap()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hyper(sigma: f64) -> MvgpHyper {
        MvgpHyper {
            kernel: Rbf::new(vec![1.0], 1.0).unwrap(),
            A: DMatrix::identity(1, 1),
            B: DMatrix::identity(2, 2),
            sigma,
        }
    }

    /// `check_spd`: both dimensions checked; symmetry within `10⁻⁹ (1 +
    /// max(|a_ij|, |a_ji|))`, a tolerance that is absolute below 1 and
    /// relative above; positive definiteness.
    #[test]
    fn spd_check_boundaries() {
        let m = |a: f64, b: f64, c: f64, d: f64| DMatrix::from_row_slice(2, 2, &[a, b, c, d]);
        for (r, c) in [(2, 3), (3, 2), (1, 1)] {
            let e = check_spd("B", &DMatrix::identity(r, c), 2).unwrap_err();
            assert!(matches!(e, InputError::Shape { .. }), "{r}×{c}: {e}");
        }
        // within the tolerance: accepted
        assert!(check_spd("B", &m(1.0, 0.01, 0.01 + 5e-10, 1.0), 2).is_ok());
        assert!(check_spd("B", &m(100.0, 50.0, 50.0 + 5e-8, 100.0), 2).is_ok());
        // beyond it: not symmetric
        for bad in [
            m(1.0, 0.01, 0.01 + 3e-9, 1.0),
            m(100.0, 50.0, 50.0 + 2e-7, 100.0),
        ] {
            let e = check_spd("B", &bad, 2).unwrap_err().to_string();
            assert!(e.contains("not symmetric"), "{e}");
        }
        // symmetric but indefinite, and not finite
        let e = check_spd("A", &m(1.0, 2.0, 2.0, 1.0), 2)
            .unwrap_err()
            .to_string();
        assert!(e.contains("A") && e.contains("eigenvalue"), "{e}");
        assert!(check_spd("A", &m(1.0, f64::NAN, f64::NAN, 1.0), 2).is_err());
    }

    /// The noise scale must be finite and positive, and small enough that
    /// `σ²A` is finite.
    #[test]
    fn noise_scale_must_be_finite_and_positive() {
        assert!(hyper(0.1).validate(1, 1, 1).is_ok());
        assert!(hyper(1e150).validate(1, 1, 1).is_ok());
        for sigma in [0.0, -0.1, f64::INFINITY, f64::NAN, 1e155, 1e308] {
            let e = hyper(sigma).validate(1, 1, 1).unwrap_err().to_string();
            assert!(e.contains("noise_sigma"), "σ = {sigma}: {e}");
        }
        let e = hyper(1e308).validate(1, 1, 1).unwrap_err().to_string();
        assert!(e.contains("too large"), "{e}");
    }

    /// A workspace sized for the model is used as it is (no reallocation),
    /// with spare capacity (20 points in 32) and when the data fill it
    /// exactly (32 observations: the capacity doubles 16 → 32); one made
    /// before the model grew past it is regrown on use and gives the
    /// posterior of a fresh one. An output of the right shape is written in
    /// place too, one of the wrong shape resized.
    #[test]
    fn a_stale_workspace_is_regrown_and_a_fitting_one_kept() {
        let mut model = Mvgp::new(1, 1, hyper(0.1), PriorMean::Zero, InputMap::Identity).unwrap();
        let mut stale = model.workspace();
        let mut out = Posterior {
            mean: DMatrix::zeros(1, 2),
            B: DMatrix::zeros(2, 2),
        };
        for j in 0..32 {
            let x = 0.1 * j as f64 - 2.0;
            model
                .add_observation(&[x], &[(0.7 * x).cos()], &[x.sin() + 0.5 * x])
                .unwrap();
            if j == 19 {
                // 20 points in a capacity of 32
                let mut ws = model.workspace();
                assert_eq!(ws.kvec.len(), 32);
                let (kvec, w) = (ws.kvec.as_ptr(), ws.w.as_ptr());
                model.posterior_into(&[0.1], &mut ws, &mut out).unwrap();
                assert_eq!((ws.kvec.as_ptr(), ws.w.as_ptr()), (kvec, w));
            }
        }
        let x = [0.33];
        let want = model.posterior(&x).unwrap();
        model.posterior_into(&x, &mut stale, &mut out).unwrap();
        assert_eq!(out.mean, want.mean);
        assert_eq!(out.B, want.B);
        // the regrown workspace fits: used in place from now on
        let (kvec, w) = (stale.kvec.as_ptr(), stale.w.as_ptr());
        model.posterior_into(&[-1.2], &mut stale, &mut out).unwrap();
        assert_eq!((stale.kvec.as_ptr(), stale.w.as_ptr()), (kvec, w));
        let mut fitting = model.workspace();
        assert_eq!(fitting.kvec.len(), model.len());
        let (kvec, w) = (fitting.kvec.as_ptr(), fitting.w.as_ptr());
        let (mean, b) = (out.mean.as_ptr(), out.B.as_ptr());
        model.posterior_into(&x, &mut fitting, &mut out).unwrap();
        assert_eq!((fitting.kvec.as_ptr(), fitting.w.as_ptr()), (kvec, w));
        assert_eq!((out.mean.as_ptr(), out.B.as_ptr()), (mean, b));
        assert_eq!(out.mean, want.mean);
        // an output of the wrong shape is resized
        let mut empty = Posterior {
            mean: DMatrix::zeros(0, 0),
            B: DMatrix::zeros(0, 0),
        };
        model.posterior_into(&x, &mut fitting, &mut empty).unwrap();
        assert_eq!((empty.mean, empty.B), (want.mean, want.B));
    }

    /// The rows known exactly are reported in order, and none by default.
    #[test]
    fn known_rows_are_reported() {
        let model = Mvgp::new(
            2,
            1,
            {
                let mut h = hyper(0.1);
                h.kernel = Rbf::new(vec![1.0, 1.0], 1.0).unwrap();
                h.A = DMatrix::identity(2, 2);
                h
            },
            PriorMean::Zero,
            InputMap::Identity,
        )
        .unwrap();
        assert!(model.known_rows().is_empty());
        let model = model.with_known_rows(&[1]).unwrap();
        assert_eq!(model.known_rows(), &[1]);
    }
}
