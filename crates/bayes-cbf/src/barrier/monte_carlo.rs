//! Monte Carlo moments of `CBC⁽ʳ⁾` for any relative degree (paper, Sec. VI:
//! "for r > 2, Monte Carlo sampling can be used").
//!
//! `CBC⁽ʳ⁾ = ∇(L_f^{r−1}h)ᵀ F u̲ + Σ_j k_j L_f^j h = zᵀu̲`, with
//! `z_c = ∇(L_f^{r−1}h)ᵀ F e_c + δ_{c0} Σ_j k_j L_f^j h` (Lemma 3 of
//! Sec. VI: mean affine, variance quadratic in `u̲`). Each sample is a joint
//! posterior draw of `F` on the lattice `x + s·{−(r−1), …, r−1}ⁿ`; the Lie
//! derivatives `L_f^j h = ∇(L_f^{j−1}h)·f` of that draw are taken by central
//! differences of step `s`, so the estimate carries an `O(s²)` bias besides
//! the sampling error, which is reported as standard errors.
//!
//! Draws use the Kronecker structure: on lattice points `p_1 … p_P`,
//! `Cov(vec[F(p_1) … F(p_P)]) = Ĉ ⊗ A` with `Ĉ_ab = B_k(p_a, p_b)`, so a draw
//! is `𝕄 + L_A Ξ Ĉ^{½}` with `Ξ` standard normal (`Ĉ^{½}` from a
//! symmetric eigendecomposition, robust to the near-singularity of closely
//! spaced points).

use super::moments::ConditionMoments;
use super::DynBarrier;
use crate::error::{check_positive, Error, InputError};
use crate::gp::{Kernel, Mvgp};
use nalgebra::DMatrix;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

/// Settings of the Monte Carlo moment estimate.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct McSettings {
    /// Number of posterior draws.
    pub samples: usize,
    /// Finite-difference step `s` (state units).
    pub step: f64,
    /// Seed of the draws.
    pub seed: u64,
}

impl Default for McSettings {
    fn default() -> Self {
        Self {
            samples: 20_000,
            step: 1e-2,
            seed: 0,
        }
    }
}

impl McSettings {
    /// Checks `samples ≥ 2` and a finite `step > 0`.
    pub fn validate(&self) -> Result<(), InputError> {
        if self.samples < 2 {
            return Err(InputError::invalid(
                "samples",
                self.samples as f64,
                "must be ≥ 2",
            ));
        }
        check_positive("step", self.step)
    }
}

/// Monte Carlo moments with their standard errors.
#[derive(Debug, Clone, PartialEq)]
pub struct McMoments {
    /// The estimate, ready for the SOCP.
    pub moments: ConditionMoments,
    /// Draws used.
    pub samples: usize,
    /// Standard error of each entry of `e`.
    pub e_se: Vec<f64>,
    /// Standard error of each entry of `Cov(z)` (row-major `(1+m)²`).
    pub cov_se: Vec<f64>,
}

impl McMoments {
    /// Standard errors of `E[CBC]` and `Var[CBC]` at control `u`: the
    /// spread of `zᵀu̲` over the draws is re-estimated from the stored
    /// per-entry errors assuming independence (a conservative bound).
    pub fn standard_errors(&self, u: &[f64]) -> (f64, f64) {
        let p = self.e_se.len();
        let ub = |i: usize| if i == 0 { 1.0 } else { u[i - 1] };
        let se_mean = (0..p)
            .map(|i| (ub(i) * self.e_se[i]).powi(2))
            .sum::<f64>()
            .sqrt();
        let mut v = 0.0;
        for i in 0..p {
            for j in 0..p {
                v += (ub(i) * ub(j) * self.cov_se[i * p + j]).powi(2);
            }
        }
        (se_mean, v.sqrt())
    }
}

/// Largest joint posterior (lattice points × `(1 + m)`) the estimate
/// draws from: a 5000 × 5000 covariance (200 MB) and its eigendecomposition.
const MAX_JOINT: usize = 5000;

/// Offsets of the cube lattice `{−R, …, R}ⁿ`, row-major `P × n`.
fn lattice(n: usize, radius: usize) -> Vec<Vec<i64>> {
    let side = 2 * radius + 1;
    let total = side.pow(n as u32);
    (0..total)
        .map(|mut idx| {
            (0..n)
                .map(|_| {
                    let d = (idx % side) as i64 - radius as i64;
                    idx /= side;
                    d
                })
                .collect()
        })
        .collect()
}

/// Estimates the moments of `CBC⁽ʳ⁾` at `x` by Monte Carlo (module docs).
pub fn mc_cbc_moments<K: Kernel>(
    model: &Mvgp<K>,
    barrier: &dyn DynBarrier,
    x: &[f64],
    settings: &McSettings,
) -> Result<McMoments, Error> {
    let (n, m) = (model.state_dim(), model.control_dim());
    let p = m + 1;
    let r = barrier.relative_degree();
    let gains = barrier.gains();
    super::validate_gains(r, gains)?;
    if barrier.state_dim() != n {
        return Err(InputError::shape("barrier state dimension", n, barrier.state_dim()).into());
    }
    if x.len() != n {
        return Err(InputError::shape("x", n, x.len()).into());
    }
    crate::error::check_finite("x", x)?;
    settings.validate()?;
    let s = settings.step;
    let rf = r - 1; // radius of the lattice where F is drawn
                    // the joint posterior of F on the lattice is a dense (P·(m+1))² matrix
                    // with an eigendecomposition: bound its size
    let joint = (2 * rf + 1)
        .checked_pow(n as u32)
        .and_then(|np| np.checked_mul(p))
        .filter(|&d| d <= MAX_JOINT);
    if joint.is_none() {
        return Err(InputError::invalid(
            "relative_degree",
            r as f64,
            &format!(
                "too high for Monte Carlo moments on {n} states: the lattice of \
                 {}^{n} points times {p} columns exceeds {MAX_JOINT} jointly Gaussian entries",
                2 * rf + 1
            ),
        )
        .into());
    }
    let rh = r; // radius where h is evaluated
    let pts_h = lattice(n, rh);
    let side_h = 2 * rh + 1;
    let index_h = |off: &[i64]| -> usize {
        let mut idx = 0usize;
        for i in (0..n).rev() {
            idx = idx * side_h + (off[i] + rh as i64) as usize;
        }
        idx
    };
    let point = |off: &[i64]| -> Vec<f64> { (0..n).map(|i| x[i] + s * off[i] as f64).collect() };
    let h_vals: Vec<f64> = pts_h.iter().map(|o| barrier.value(&point(o))).collect();
    super::moments::check_evaluation(barrier, x, &h_vals, &[], &[])?;
    let pts_f: Vec<Vec<i64>> = lattice(n, rf);
    let np = pts_f.len();
    // joint posterior on the F lattice: means and Ĉ
    let mut mean = DMatrix::<f64>::zeros(n, np * p);
    for (a, o) in pts_f.iter().enumerate() {
        let mk = model.posterior_mean(&point(o))?;
        mean.view_mut((0, a * p), (n, p)).copy_from(&mk);
    }
    let mut chat = DMatrix::<f64>::zeros(np * p, np * p);
    for a in 0..np {
        for b in a..np {
            let blk = model.posterior_cov(&point(&pts_f[a]), &point(&pts_f[b]))?;
            chat.view_mut((a * p, b * p), (p, p)).copy_from(&blk);
            chat.view_mut((b * p, a * p), (p, p))
                .copy_from(&blk.transpose());
        }
    }
    let eig = nalgebra::SymmetricEigen::new(chat);
    let sqrt_c =
        &eig.eigenvectors * DMatrix::from_diagonal(&eig.eigenvalues.map(|l| l.max(0.0).sqrt())); // Ĉ = S Sᵀ
    let la = model.row_cov_factor()?;
    let centre_f = pts_f
        .iter()
        .position(|o| o.iter().all(|&d| d == 0))
        .unwrap_or(0);
    let index_f = |off: &[i64]| -> Option<usize> {
        let side = 2 * rf + 1;
        let mut idx = 0usize;
        for i in (0..n).rev() {
            let d = off[i] + rf as i64;
            if d < 0 || d >= side as i64 {
                return None;
            }
            idx = idx * side + d as usize;
        }
        Some(idx)
    };
    let mut rng = ChaCha8Rng::seed_from_u64(settings.seed);
    let mut zs = crate::error::reserve("samples", settings.samples.saturating_mul(p))
        .map_err(|_| InputError::invalid("samples", settings.samples as f64, "too large"))?;
    zs.resize(settings.samples * p, 0.0);
    let mut phi = h_vals.clone();
    let mut next = vec![0.0; h_vals.len()];
    let mut xi = DMatrix::<f64>::zeros(n, np * p);
    for t in 0..settings.samples {
        for v in xi.iter_mut() {
            *v = StandardNormal.sample(&mut rng);
        }
        let draw = &mean + &la * &xi * sqrt_c.transpose();
        // Lie derivatives: φ_j on the h lattice where defined (radius r − j)
        phi.copy_from_slice(&h_vals);
        let mut eta = vec![phi[index_h(&vec![0; n])]];
        let grad_at = |phi: &[f64], off: &[i64]| -> Vec<f64> {
            (0..n)
                .map(|i| {
                    let mut a = off.to_vec();
                    let mut b = off.to_vec();
                    a[i] += 1;
                    b[i] -= 1;
                    (phi[index_h(&a)] - phi[index_h(&b)]) / (2.0 * s)
                })
                .collect()
        };
        for j in 1..r {
            let radius = (r - j) as i64;
            next.fill(f64::NAN);
            for o in pts_h.iter().filter(|o| o.iter().all(|d| d.abs() <= radius)) {
                let g = grad_at(&phi, o);
                let a = index_f(o).unwrap_or(centre_f);
                next[index_h(o)] = (0..n).map(|i| g[i] * draw[(i, a * p)]).sum();
            }
            std::mem::swap(&mut phi, &mut next);
            eta.push(phi[index_h(&vec![0; n])]);
        }
        let g = grad_at(&phi, &vec![0; n]);
        for c in 0..p {
            let mut z = (0..n)
                .map(|i| g[i] * draw[(i, centre_f * p + c)])
                .sum::<f64>();
            if c == 0 {
                z += gains.iter().zip(&eta).map(|(k, e)| k * e).sum::<f64>();
            }
            zs[t * p + c] = z;
        }
    }
    // moments and standard errors
    let nn = settings.samples as f64;
    let e: Vec<f64> = (0..p)
        .map(|c| (0..settings.samples).map(|t| zs[t * p + c]).sum::<f64>() / nn)
        .collect();
    let mut cov = DMatrix::<f64>::zeros(p, p);
    let mut cov_se = vec![0.0; p * p];
    for a in 0..p {
        for b in 0..p {
            let prods: Vec<f64> = (0..settings.samples)
                .map(|t| (zs[t * p + a] - e[a]) * (zs[t * p + b] - e[b]))
                .collect();
            let c = prods.iter().sum::<f64>() / (nn - 1.0);
            cov[(a, b)] = c;
            let var_p = prods.iter().map(|v| (v - c).powi(2)).sum::<f64>() / (nn - 1.0);
            cov_se[a * p + b] = (var_p / nn).sqrt();
        }
    }
    let e_se: Vec<f64> = (0..p).map(|c| (cov[(c, c)] / nn).sqrt()).collect();
    let cov = 0.5 * (&cov + cov.transpose());
    let mut moments = ConditionMoments::from_parts(e, cov, r.max(1))?;
    moments.value = h_vals[index_h(&vec![0; n])];
    Ok(McMoments {
        moments,
        samples: settings.samples,
        e_se,
        cov_se,
    })
}
