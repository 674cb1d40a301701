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
//!
//! The step is checked both ways, and a step the estimate cannot trust is
//! an [`InputError`] naming `step`:
//! - too large: the lattice spans more than the kernel's shortest
//!   lengthscale, or the truncation (estimated from the condition at the
//!   posterior mean at twice or half the step) exceeds 1 % of the
//!   condition's spread;
//! - too small: the rounding of `h` and of the posterior mean, amplified by
//!   `s^{−r}`, moves the condition by over 1 % of its spread; or the modes
//!   of `Ĉ` at its round-off floor (at or below its largest negative
//!   eigenvalue, and at least `dim · ε · λ_max`) widen the margin `3·std`
//!   of the first draws' condition by over 1 % of its spread. On a model without data
//!   (lengthscale 1, relative degree 3) that floor binds below a step of
//!   about 3e-4.

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
            return Err(InputError::invalid_shown(
                "samples",
                self.samples,
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
/// draws from: a 5000 × 5000 covariance (200 MB), its eigendecomposition
/// and two square-root factors of the same size.
const MAX_JOINT: usize = 5000;

/// Draws also taken without the modes of `Ĉ` at its round-off floor.
const FLOOR_PROBES: usize = 32;

/// The largest share of the spread of each entry of `z` (standard
/// deviation plus `|mean|`) by which the modes at the round-off floor may
/// widen its margin `c·std` (`c = 3`). Moving `z` by `d` (root mean square
/// over the probes) independently of the rest widens its standard deviation
/// `σ` by `d²/(2σ)`, so the margin by `1.5 d²/σ`.
const MAX_UNRESOLVED: f64 = 0.01;

/// The larger of two shares of the spread, a NaN share counting as
/// infinite (a fold's step).
fn worst(a: f64, v: f64) -> f64 {
    if v.is_nan() {
        f64::INFINITY
    } else {
        a.max(v)
    }
}

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

/// The lattices of one estimate: `h` on `x + s·{−r, …, r}ⁿ`, `F` on
/// `x + s·{−(r−1), …, r−1}ⁿ`.
struct Lattice {
    n: usize,
    r: usize,
    h_points: Vec<Vec<i64>>,
    f_points: Vec<Vec<i64>>,
    centre_h: usize,
    centre_f: usize,
}

/// What the round-off probe of [`Lattice::round_off`] perturbs: the
/// posterior mean of `F` on its lattice and the values of `h`, each by its
/// relative rounding and by the absolute rounding of the lattice points
/// (`h_abs`, `mean_abs`).
struct RoundOff<'a> {
    mean: &'a DMatrix<f64>,
    h_vals: &'a [f64],
    h_abs: f64,
    mean_abs: f64,
    seed: u64,
}

impl Lattice {
    fn new(n: usize, r: usize) -> Self {
        let h_points = lattice(n, r);
        let f_points = lattice(n, r - 1);
        let centre = |pts: &[Vec<i64>]| pts.iter().position(|o| o.iter().all(|&d| d == 0));
        Self {
            n,
            r,
            centre_h: centre(&h_points).unwrap_or(0),
            centre_f: centre(&f_points).unwrap_or(0),
            h_points,
            f_points,
        }
    }

    /// Index of offset `off` on the lattice of radius `radius`, if on it.
    fn index(&self, off: &[i64], radius: usize) -> Option<usize> {
        let side = 2 * radius + 1;
        let mut idx = 0usize;
        for i in (0..self.n).rev() {
            let d = off[i] + radius as i64;
            if d < 0 || d >= side as i64 {
                return None;
            }
            idx = idx * side + d as usize;
        }
        Some(idx)
    }

    /// Central-difference gradient of `phi` (on the `h` lattice) at `off`.
    fn gradient(&self, phi: &[f64], off: &[i64], s: f64, i: usize) -> f64 {
        let mut a = off.to_vec();
        let mut b = off.to_vec();
        a[i] += 1;
        b[i] -= 1;
        let at = |o: &[i64]| self.index(o, self.r).map_or(f64::NAN, |k| phi[k]);
        (at(&a) - at(&b)) / (2.0 * s)
    }

    /// `z` of one draw of `F` (`n × P(1+m)`, the `F` lattice): the Lie
    /// derivatives `φ_j = ∇φ_{j−1}·f` on the `h` lattice where defined
    /// (radius `r − j`), then `z_c = ∇φ_{r−1}·F e_c + δ_{c0} Σ_j k_j φ_j`.
    fn condition(
        &self,
        draw: &DMatrix<f64>,
        h_vals: &[f64],
        gains: &[f64],
        s: f64,
        (phi, next): &mut (Vec<f64>, Vec<f64>),
        z: &mut [f64],
    ) {
        let (n, r, p) = (self.n, self.r, z.len());
        phi.copy_from_slice(h_vals);
        let centre = vec![0; n];
        let mut lie = 0.0; // Σ_j k_j φ_j at x
        for (j, k) in gains.iter().enumerate().take(r) {
            if j > 0 {
                let radius = (r - j) as i64;
                next.fill(f64::NAN);
                for o in self
                    .h_points
                    .iter()
                    .filter(|o| o.iter().all(|d| d.abs() <= radius))
                {
                    let a = self.index(o, r - 1).unwrap_or(self.centre_f);
                    next[self.index(o, r).unwrap_or(self.centre_h)] = (0..n)
                        .map(|i| self.gradient(phi, o, s, i) * draw[(i, a * p)])
                        .sum();
                }
                std::mem::swap(phi, next);
            }
            lie += k * phi[self.centre_h];
        }
        for (c, zc) in z.iter_mut().enumerate() {
            *zc = (0..n)
                .map(|i| self.gradient(phi, &centre, s, i) * draw[(i, self.centre_f * p + c)])
                .sum::<f64>();
            if c == 0 {
                *zc += lie;
            }
        }
    }

    /// How far round-off moves `z` against its spread (`spread[c]`, the
    /// standard deviation plus `|E z_c|`), if beyond 1 % in any entry. The
    /// nested differences amplify the rounding of `h` and of the posterior
    /// mean of `F` by `s^{−r}`: a bias, the same in every draw, which the
    /// standard errors do not show. That rounding is relative (`ε`) and
    /// absolute, from the lattice points `x + s·k`, rounded to
    /// `ε·(|x| + r s)`, which moves a value by that times its gradient.
    /// Sixteen probes of `h(1 + εξ) + h_abs ξ'` and likewise of `M` are
    /// compared with the exact values.
    /// (The draws' own round-off, from the near-singular `Ĉ` of closely
    /// spaced points, is checked apart: [`mc_cbc_moments`] takes the first
    /// draws again without the modes of `Ĉ` at its round-off floor.)
    fn round_off(&self, probe: &RoundOff, gains: &[f64], s: f64, spread: &[f64]) -> Option<f64> {
        let p = spread.len();
        let eps = f64::EPSILON;
        let mut scratch = (probe.h_vals.to_vec(), vec![0.0; probe.h_vals.len()]);
        let mut reference = vec![0.0; p];
        self.condition(
            probe.mean,
            probe.h_vals,
            gains,
            s,
            &mut scratch,
            &mut reference,
        );
        let mut rng = ChaCha8Rng::seed_from_u64(probe.seed ^ 0x9e37_79b9_7f4a_7c15);
        let mut dev = vec![0.0; p];
        let mut z = vec![0.0; p];
        let mut h = probe.h_vals.to_vec();
        let mut draw = probe.mean.clone();
        const PROBES: usize = 16;
        for _ in 0..PROBES {
            let mut noise = || -> (f64, f64) {
                (
                    StandardNormal.sample(&mut rng),
                    StandardNormal.sample(&mut rng),
                )
            };
            for (hv, h0) in h.iter_mut().zip(probe.h_vals) {
                let (g, g2) = noise();
                *hv = h0 * (1.0 + eps * g) + probe.h_abs * g2;
            }
            for (v, m0) in draw.iter_mut().zip(probe.mean.iter()) {
                let (g, g2) = noise();
                *v = m0 * (1.0 + eps * g) + probe.mean_abs * g2;
            }
            self.condition(&draw, &h, gains, s, &mut scratch, &mut z);
            for c in 0..p {
                dev[c] += (z[c] - reference[c]).powi(2) / PROBES as f64;
            }
        }
        let floor = 1e-12 * spread.iter().fold(0.0f64, |a, v| a.max(*v));
        (0..p)
            .map(|c| dev[c].sqrt() / (spread[c] + floor))
            .filter(|ratio| !ratio.is_finite() || *ratio > 1e-2)
            .fold(None, |a: Option<f64>, v| Some(a.map_or(v, |a| a.max(v))))
    }
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
        return Err(InputError::invalid_shown(
            "relative_degree",
            r,
            &format!(
                "too high for Monte Carlo moments on {n} states: the lattice of \
                 {}^{n} points times {p} columns exceeds {MAX_JOINT} jointly Gaussian entries",
                2 * rf + 1
            ),
        )
        .into());
    }
    // the lattice of h spans r·s about x; the kernel's inputs move by at
    // most the states' steps (coordinates, cos and sin): beyond one
    // lengthscale the differences of F alias, and no truncation estimate
    // below can tell
    let scale = model.hyper().kernel.shortest_scale();
    if r as f64 * s > scale {
        return Err(InputError::invalid(
            "step",
            s,
            &format!(
                "too large for relative degree {r}: the lattice of the nested differences \
                 spans {r}·step = {}, more than the kernel's shortest lengthscale {} \
                 (decrease step; the default is 1e-2)",
                crate::error::number(r as f64 * s),
                crate::error::number(scale)
            ),
        )
        .into());
    }
    let lat = Lattice::new(n, r);
    let np = lat.f_points.len();
    // the lattice point `x + step·off`
    let point_at = |step: f64, off: &[i64]| -> Vec<f64> {
        (0..n).map(|i| x[i] + step * off[i] as f64).collect()
    };
    let point = |off: &[i64]| point_at(s, off);
    // h on its lattice and the posterior mean of F on F's, at step `step`
    let lattice_means = |step: f64| -> Result<(Vec<f64>, DMatrix<f64>), Error> {
        let at = |off: &[i64]| point_at(step, off);
        let h_vals: Vec<f64> = lat.h_points.iter().map(|o| barrier.value(&at(o))).collect();
        let mut mean = DMatrix::<f64>::zeros(n, np * p);
        for (a, o) in lat.f_points.iter().enumerate() {
            let mk = model.posterior_mean(&at(o))?;
            mean.view_mut((0, a * p), (n, p)).copy_from(&mk);
        }
        Ok((h_vals, mean))
    };
    let (h_vals, mean) = lattice_means(s)?;
    super::moments::check_evaluation(barrier, x, &h_vals, &[], &[])?;
    // joint posterior on the F lattice: Ĉ
    let mut chat = DMatrix::<f64>::zeros(np * p, np * p);
    for a in 0..np {
        for b in a..np {
            let blk = model.posterior_cov(&point(&lat.f_points[a]), &point(&lat.f_points[b]))?;
            chat.view_mut((a * p, b * p), (p, p)).copy_from(&blk);
            chat.view_mut((b * p, a * p), (p, p))
                .copy_from(&blk.transpose());
        }
    }
    let eig = nalgebra::SymmetricEigen::new(chat);
    // Ĉ = S Sᵀ, S = V Λ^{½}; the draws use Sᵀ
    let eigenvalues = &eig.eigenvalues;
    let factor_t = |keep: &dyn Fn(f64) -> f64| -> DMatrix<f64> {
        (&eig.eigenvectors * DMatrix::from_diagonal(&eigenvalues.map(keep))).transpose()
    };
    let sqrt_t = factor_t(&|l| l.max(0.0).sqrt());
    // the round-off floor of Ĉ's eigenvalues: the largest negative one
    // (rounding, not the posterior, made it negative), and at least the
    // rounding of a matrix of that size and norm. The modes at or below it
    // are rounding, yet the nested differences amplify them by s^{1−r}:
    // the first draws are also taken without them, and their share of z
    // is checked below
    let floor = (-eigenvalues.min())
        .max(eigenvalues.len() as f64 * f64::EPSILON * eigenvalues.max())
        .max(0.0);
    let resolved_t = factor_t(&|l| if l > floor { l.sqrt() } else { 0.0 });
    let floor_probes = settings.samples.min(FLOOR_PROBES);
    let mut floor_dev = vec![0.0; p];
    let mut z_resolved = vec![0.0; p];
    let la = model.row_cov_factor()?;
    let mut rng = ChaCha8Rng::seed_from_u64(settings.seed);
    let mut zs = crate::error::reserve("samples", settings.samples.saturating_mul(p))
        .map_err(|_| InputError::invalid_shown("samples", settings.samples, "too large"))?;
    zs.resize(settings.samples * p, 0.0);
    let mut scratch = (h_vals.clone(), vec![0.0; h_vals.len()]);
    let mut xi = DMatrix::<f64>::zeros(n, np * p);
    for t in 0..settings.samples {
        for v in xi.iter_mut() {
            *v = StandardNormal.sample(&mut rng);
        }
        let draw = &mean + &la * &xi * &sqrt_t;
        let z = &mut zs[t * p..(t + 1) * p];
        lat.condition(&draw, &h_vals, gains, s, &mut scratch, z);
        if t < floor_probes {
            let resolved = &mean + &la * &xi * &resolved_t;
            lat.condition(&resolved, &h_vals, gains, s, &mut scratch, &mut z_resolved);
            for c in 0..p {
                floor_dev[c] += (z[c] - z_resolved[c]).powi(2) / floor_probes as f64;
            }
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
    let spread: Vec<f64> = (0..p).map(|c| cov[(c, c)].sqrt() + e[c].abs()).collect();
    // the absolute rounding of the lattice points, times the largest
    // central difference of h (on its lattice) and of M (on F's)
    let coordinate = x.iter().fold(0.0f64, |a, v| a.max(v.abs())) + r as f64 * s;
    let slope = |values: &dyn Fn(usize) -> f64, radius: usize| -> f64 {
        let mut largest = 0.0f64;
        for i in 0..n {
            let mut off = vec![0i64; n];
            off[i] = 1;
            let up = lat.index(&off, radius);
            off[i] = -1;
            if let (Some(a), Some(b)) = (up, lat.index(&off, radius)) {
                largest = largest.max(((values(a) - values(b)) / (2.0 * s)).abs());
            }
        }
        largest
    };
    let h_slope = slope(&|k| h_vals[k], r);
    let mean_slope = (0..n * p)
        .map(|e| slope(&|a| mean[(e % n, a * p + e / n)], r - 1))
        .fold(0.0f64, f64::max);
    let probe = RoundOff {
        mean: &mean,
        h_vals: &h_vals,
        h_abs: f64::EPSILON * coordinate * h_slope,
        mean_abs: f64::EPSILON * coordinate * mean_slope,
        seed: settings.seed,
    };
    let share = |ratio: f64| {
        if ratio.is_finite() {
            format!("{:.0}% of the condition's spread", 100.0 * ratio)
        } else {
            "a spread that is not finite".to_string()
        }
    };
    if let Some(ratio) = lat.round_off(&probe, gains, s, &spread) {
        return Err(InputError::invalid(
            "step",
            s,
            &format!(
                "too small for relative degree {r}: its {r} nested differences amplify the \
                 round-off of h and of the mean of F to {}, which would bias the moments \
                 (increase step; the default is 1e-2)",
                share(ratio)
            ),
        )
        .into());
    }
    // the margin the draws' modes at the round-off floor add, as a share of
    // the spread (an entry that no draw moves is not refused for the
    // rounding of zero)
    let unresolved = (0..p)
        .map(|c| match floor_dev[c] {
            0.0 => 0.0,
            d2 => 1.5 * d2 / (cov[(c, c)].sqrt() * spread[c]),
        })
        .fold(0.0, worst);
    if unresolved > MAX_UNRESOLVED {
        return Err(InputError::invalid(
            "step",
            s,
            &format!(
                "too small for relative degree {r}: its {r} nested differences amplify the \
                 round-off of the posterior draws of F, which can widen the margin 3·std by \
                 {} (increase step; the default is 1e-2)",
                share(unresolved)
            ),
        )
        .into());
    }
    // the truncation of the differences, O(s²): the condition at the
    // posterior mean at steps s and 2s differ by about 3× the error at s
    // (at 2s rather than s/2, where the round-off is 2ʳ times larger).
    // Where h or the mean is not finite on the doubled lattice (h's domain
    // ends within 2·r·s of x, where h curves hardest), from s/2 instead,
    // whose lattice lies within the one at s: about 4/3 × the difference.
    // A failed evaluation out there is not this call's error
    let mut z1 = vec![0.0; p];
    lat.condition(&mean, &h_vals, gains, s, &mut scratch, &mut z1);
    let mut compare = |step: f64, z: &mut [f64]| -> bool {
        let at = lattice_means(step).ok();
        let _ = barrier.take_error();
        match at {
            Some((h, m)) => {
                lat.condition(&m, &h, gains, step, &mut scratch, z);
                z.iter().all(|v| v.is_finite())
            }
            None => false,
        }
    };
    let mut z2 = vec![0.0; p];
    let (factor, from) = if compare(2.0 * s, &mut z2) {
        (1.0 / 3.0, "the step doubled")
    } else if compare(0.5 * s, &mut z2) {
        (4.0 / 3.0, "half the step (h is not finite at twice it)")
    } else {
        return Err(InputError::invalid(
            "step",
            s,
            &format!(
                "h or the posterior mean is not finite on the lattices at twice and at half \
                 the step around x, so the truncation of the {r} nested differences cannot \
                 be estimated (decrease step)"
            ),
        )
        .into());
    };
    let truncation = (0..p)
        .map(|c| match (z2[c] - z1[c]).abs() * factor {
            0.0 => 0.0,
            d => d / spread[c],
        })
        .fold(0.0, worst);
    if truncation > 1e-2 {
        return Err(InputError::invalid(
            "step",
            s,
            &format!(
                "too large for relative degree {r}: the truncation of its {r} nested \
                 differences, estimated from {from}, is {} (decrease step; the default is \
                 1e-2)",
                share(truncation)
            ),
        )
        .into());
    }
    let cov = 0.5 * (&cov + cov.transpose());
    let mut moments = ConditionMoments::from_parts(e, cov, r.max(1))?;
    moments.value = h_vals[lat.centre_h];
    Ok(McMoments {
        moments,
        samples: settings.samples,
        e_se,
        cov_se,
    })
}
