//! Lipschitz constant of a posterior sample `f_k(x) = F(x)u̲` over a cuboid
//! (paper, Lemma 3), analytic and numerical.
//!
//! Under the MVGP posterior, `f = μ + e` with `μ(x) = M_k(x)u̲` and
//! `e ~ GP(0, A κ_B(x, x'))`, `κ_B(x, x') = u̲ᵀ B_k(x, x') u̲`. Each Jacobian
//! entry `∂_j e_i` is a zero-mean GP with kernel `A_ii κ^{∂j}(x, x')`,
//! `κ^{∂j} = ∂²κ_B/∂x_j∂x'_j`. Lederer et al. (2019, Thm 3.2 / Lemma B.2)
//! bound its supremum over a compact `X` of diameter `r` with probability
//! `1 − δ_L/n²`:
//!
//! `sup_X |∂_j e_i| ≤ √(2 ln(2n²/δ_L)) σ_ij + 12 √(6n) max{σ_ij, √(r A_ii L^{∂j})}`,
//!
//! `σ_ij = sup_X √(A_ii κ^{∂j}(x, x))`, `L^{∂j}` a Lipschitz constant of
//! `κ^{∂j}` on `X × X`. A union bound over the `n²` entries and the mean
//! value theorem on the convex `X` give, with probability `1 − δ_L`,
//!
//! `‖f(x) − f(x')‖ ≤ L_f ‖x − x'‖`, `L_f = √(Σ_ij L_ij²)`,
//! `L_ij = sup_X |∂_j μ_i| + (the bound above)`.
//!
//! Two corrections to the paper's statement of Lemma 3: (i) the posterior
//! mean's Jacobian is part of the sample's Jacobian and is added (the lemma
//! as printed bounds a zero-mean process); (ii) the paper's factor `1/n²`
//! under the root does not follow from its proof (summing
//! `|f_i(x') − f_i(x)| ≤ L_ij |x'_j − x_j|` over `j` gives
//! `|f_i(x') − f_i(x)| ≤ Σ_j L_ij |x'_j − x_j|`, not `n` times the left side),
//! so `L_f` here is the Frobenius norm of the entry bounds.
//!
//! ## The kernel constants
//!
//! For the RBF kernel on an input map whose features each read one state
//! coordinate, `k0(x, x') = s Π_c ψ_c(x_c, x'_c)` with
//! `ψ_c(a, b) = exp(−½ Σ_{f ∈ c} (φ_f(a) − φ_f(b))²/ℓ_f²)`, `|ψ_c| ≤ 1`.
//! With `M1_c ≥ sup|∂_aψ_c|`, `M11_c ≥ sup|∂_a∂_bψ_c|`,
//! `M21_c ≥ sup|∂_a²∂_bψ_c|` (closed form for a single coordinate feature —
//! the Gaussian `ψ(Δ) = exp(−Δ²/2ℓ²)`: `e^{−1/2}/ℓ`, `1/ℓ²`,
//! `√6 t e^{−t²/2}/ℓ³` with `t² = 3 − √6`; Cauchy's estimate on a complex
//! polydisc for periodic features) and the diagonal values
//! `D11_c = sup_a Σ_f φ_f'(a)²/ℓ_f²`, `D22_c = sup_a Σ_f φ_f''(a)²/ℓ_f² + 3 D11_c²`
//! (`sin² + cos² = 1`: a `(cos, sin)` pair contributes its larger `1/ℓ²`)
//! (`∂_a∂_bψ` and `∂_a²∂_b²ψ` at `a = b`):
//!
//! * prior part: `sup ‖∇_x κ^{∂j}_0(x, x')‖ ≤ β s √(M21_j² + Σ_{l≠j} M11_j² M1_l²)`,
//!   `β = u̲ᵀ B u̲`;
//! * posterior correction: `κ^{∂j}_0 − κ^{∂j} = Cov(∂_j e(x), y) Σ_y⁻¹ Cov(y, ∂_j e(x'))`
//!   for the training observations `y`; by Cauchy–Schwarz in the `Σ_y⁻¹`
//!   inner product, and because explained variance never exceeds prior
//!   variance, its `x_l`-derivative is at most
//!   `√(Var₀ ∂_l∂_j e(x)) √(Var₀ ∂_j e(x'))`, so
//!   `‖∇_x(correction)‖ ≤ β s √(D11_j Σ_l V_lj)`, `V_jj = D22_j`,
//!   `V_lj = D11_l D11_j` — a bound that holds for any data.
//!
//! `L^{∂j}` is √2 times the sum of both (Lipschitz on `X × X` jointly; the
//! one-argument constant is enough for the metric bound
//! `d(x, x')² ≤ 2 L ‖x − x'‖` but the factor covers either reading of the
//! lemma). `σ_ij² ≤ A_ii min(β s D11_j, max_grid κ^{∂j}(x,x) + 2 L₁ h)` where
//! `h` is the largest distance from a point of `X` to the nearest grid node
//! and `L₁` the one-argument constant (`κ^{∂j}(x, x)` is `2L₁`-Lipschitz).
//!
//! `sup_X |∂_j μ_i|` is the grid maximum plus `h` times the largest
//! finite-difference slope of `∂_j μ_i` between neighbouring nodes: the mean
//! is deterministic and smooth; this term is an estimate, not a proof.
//!
//! ## Numerical estimate
//!
//! At every grid node the Jacobian `J = ∂f/∂x` of a posterior sample is
//! Gaussian, `J = ∂μ + L_A Z L_Hᵀ` with `Cov(J_ic, J_jd) = A_ij H_cd`,
//! `H = ∇_x∇_{x'}κ_B(x, x)`; `L_ij` is the largest `|J_ij|` over nodes and
//! samples, and `L_f = √(Σ_ij L_ij²)` as above (paper, Sec. VII-B).
//!
//! Cost: kernel quantities depend only on the coordinates the input map
//! reads, so the posterior is evaluated on the grid over those coordinates
//! (`N^{|C|}` nodes, one `k × n` triangular solve each); the prior mean's
//! Jacobian on the full `N^n` grid.

use super::input_map::{Feature, InputMap};
use super::kernel::{Kernel, Rbf};
use super::mvgp::Mvgp;
use crate::error::{check_finite, check_nonnegative, Error, InputError};
use faer::Mat;
use nalgebra::{DMatrix, SymmetricEigen};
use num_dual::Dual64;
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};

/// Settings of the Lipschitz computation.
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct LipschitzSettings {
    /// `δ_L ∈ (0, 1)`: the analytic bound holds with probability `1 − δ_L`.
    pub delta_l: f64,
    /// Side lengths of the cuboid `X_k` centred at `x_k` (one per state
    /// coordinate, ≥ 0).
    pub sides: Vec<f64>,
    /// Grid nodes per coordinate (≥ 2; a side of length 0 uses one node).
    pub grid: usize,
    /// Posterior Jacobian samples per node for the numerical estimate
    /// (0: no numerical estimate).
    pub samples: usize,
}

impl LipschitzSettings {
    /// The paper's evaluation (Sec. VII-B) for a state of dimension `n`:
    /// `δ_L = 1e-4`, a 10-node grid, 10 samples per node, sides `sides`.
    pub fn new(sides: Vec<f64>) -> Self {
        Self {
            delta_l: 1e-4,
            sides,
            grid: 10,
            samples: 10,
        }
    }

    /// Checks the settings against state dimension `n`.
    pub fn validate(&self, n: usize) -> Result<(), InputError> {
        if !(self.delta_l > 0.0 && self.delta_l < 1.0) {
            return Err(InputError::invalid(
                "delta_l",
                self.delta_l,
                "must be in (0, 1)",
            ));
        }
        if self.sides.len() != n {
            return Err(InputError::shape("cuboid", n, self.sides.len()));
        }
        for (i, &s) in self.sides.iter().enumerate() {
            check_nonnegative(&format!("cuboid[{i}]"), s)?;
        }
        if self.grid < 2 {
            return Err(InputError::invalid_shown("grid", self.grid, "must be ≥ 2"));
        }
        let nodes = self.grid.checked_pow(n as u32);
        if nodes.is_none_or(|g| g > 1_000_000) {
            return Err(InputError::invalid_shown(
                "grid",
                self.grid,
                "grid^n must be ≤ 1e6 nodes",
            ));
        }
        if nodes
            .and_then(|g| g.checked_mul(self.samples))
            .is_none_or(|d| d > 10_000_000)
        {
            return Err(InputError::invalid_shown(
                "samples",
                self.samples,
                "samples · grid^n must be ≤ 1e7 Jacobian draws per evaluation",
            ));
        }
        Ok(())
    }
}

/// Lipschitz constants of `f_k = F(x)u̲` on the cuboid.
#[derive(Debug, Clone, PartialEq)]
pub struct LipschitzEstimate {
    /// Analytic `L_f` (Lemma 3, corrected): holds with probability `1 − δ_L`.
    pub analytic: f64,
    /// Numerical `L_f` from sampled Jacobians, if samples were drawn.
    pub numerical: Option<f64>,
    /// Analytic entry bounds `L_ij` (row-major `n × n`).
    pub analytic_entries: Vec<f64>,
    /// Numerical entry maxima (row-major `n × n`, empty without samples).
    pub numerical_entries: Vec<f64>,
    /// `sup_X |∂_j μ_i|` (row-major `n × n`).
    pub mean_entries: Vec<f64>,
    /// `σ_ij`: bound on the posterior standard deviation of `∂_j e_i` on `X`.
    pub sigma_entries: Vec<f64>,
    /// `L^{∂j}` without `A` (per coordinate `j`).
    pub kernel_lipschitz: Vec<f64>,
    /// Diameter `r` of the cuboid.
    pub extension: f64,
}

/// Bounds on the derivatives of one coordinate's kernel factor `ψ_c(a, b)`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FactorBounds {
    /// `sup |∂_a ψ|`.
    pub m1: f64,
    /// `sup |∂_a ∂_b ψ|`.
    pub m11: f64,
    /// `sup |∂_a² ∂_b ψ|`.
    pub m21: f64,
    /// `sup_a ∂_a∂_b ψ(a, a)`.
    pub d11: f64,
    /// `sup_a ∂_a²∂_b² ψ(a, a)`.
    pub d22: f64,
}

/// The Gaussian factor `exp(−Δ²/2ℓ²)`: exact suprema.
fn gaussian_bounds(l: f64) -> FactorBounds {
    let t2 = 3.0 - 6f64.sqrt();
    FactorBounds {
        m1: (-0.5f64).exp() / l,
        m11: 1.0 / (l * l),
        m21: 6f64.sqrt() * t2.sqrt() * (-t2 / 2.0).exp() / (l * l * l),
        d11: 1.0 / (l * l),
        d22: 3.0 / (l * l * l * l),
    }
}

/// Cauchy's estimate for `sup |∂_a^p ∂_b^q ψ|` over real `(a, b)`:
/// `ψ` is entire and on the polydisc of radius `ρ`,
/// `|ψ| ≤ exp(Σ_f 2 m_f(ρ)²/ℓ_f²)` with `m_f(ρ) = ρ` for a coordinate and
/// `sinh ρ` for `cos`/`sin` (`|Im cos(a + iy)| ≤ sinh |y|`), since
/// `Re w² ≥ −(Im w)²`. The bound `p! q! sup|ψ| / ρ^{p+q}` is minimised over
/// a grid of radii (each radius gives a valid bound).
fn cauchy_bound(features: &[(Feature, f64)], p: u32, q: u32) -> f64 {
    let fact = |k: u32| (1..=k).map(f64::from).product::<f64>();
    let mut best = f64::INFINITY;
    for i in 0..400 {
        let rho = 1e-3 * 1e4f64.powf(i as f64 / 399.0);
        let e: f64 = features
            .iter()
            .map(|&(f, l)| {
                let m = match f {
                    Feature::Coord(_) => rho,
                    Feature::Cos(_) | Feature::Sin(_) => rho.sinh(),
                };
                2.0 * m * m / (l * l)
            })
            .sum();
        let b = fact(p) * fact(q) * e.exp() / rho.powi((p + q) as i32);
        if b.is_finite() {
            best = best.min(b);
        }
    }
    best
}

/// Per-coordinate factor bounds of the RBF kernel `kernel` seen through
/// `map`, for a state of dimension `n`.
pub fn factor_bounds(kernel: &Rbf, map: &InputMap, n: usize) -> Vec<FactorBounds> {
    let ls = kernel.lengthscales();
    let d = map.output_dim(n);
    (0..n)
        .map(|c| {
            let feats: Vec<(Feature, f64)> = (0..d)
                .filter(|&j| map.source(j) == c)
                .map(|j| {
                    let f = match map {
                        InputMap::Features(f) => f[j],
                        _ => Feature::Coord(c),
                    };
                    (f, ls[j])
                })
                .collect();
            match feats.as_slice() {
                [] => FactorBounds::default(),
                [(Feature::Coord(_), l)] => gaussian_bounds(*l),
                _ => {
                    // φ' and φ'' of cos and sin are (−sin, cos) and (−cos, −sin):
                    // Σ over the pair is at most the larger 1/ℓ²
                    let inv = |want: fn(&Feature) -> bool| {
                        feats
                            .iter()
                            .filter(|(f, _)| want(f))
                            .map(|(_, l)| 1.0 / (l * l))
                            .fold(0.0, f64::max)
                    };
                    let coord = inv(|f| matches!(f, Feature::Coord(_)));
                    let trig = inv(|f| !matches!(f, Feature::Coord(_)));
                    let (s, t) = (coord + trig, trig);
                    FactorBounds {
                        m1: cauchy_bound(&feats, 1, 0),
                        m11: cauchy_bound(&feats, 1, 1),
                        m21: cauchy_bound(&feats, 2, 1),
                        d11: s,
                        d22: t + 3.0 * s * s,
                    }
                }
            }
        })
        .collect()
}

/// Kernel-derivative constants (without `β = u̲ᵀBu̲` and `A`) for each `j`:
/// `(L₁ prior + L₁ correction, prior variance of ∂_j)`, where `L₁` is the
/// one-argument Lipschitz constant of `κ^{∂j}` and the variance is
/// `s D11_j`.
pub fn kernel_constants(bounds: &[FactorBounds], s: f64, with_data: bool) -> Vec<(f64, f64)> {
    let n = bounds.len();
    (0..n)
        .map(|j| {
            let bj = bounds[j];
            let mut q = bj.m21 * bj.m21;
            for (l, bl) in bounds.iter().enumerate() {
                if l != j {
                    q += (bj.m11 * bl.m1).powi(2);
                }
            }
            let prior = s * q.sqrt();
            let corr = if with_data {
                let v: f64 = bounds
                    .iter()
                    .enumerate()
                    .map(|(l, bl)| if l == j { bj.d22 } else { bl.d11 * bj.d11 })
                    .sum();
                s * (bj.d11 * v).sqrt()
            } else {
                0.0
            };
            (prior + corr, s * bj.d11)
        })
        .collect()
}

/// The grid of `grid` nodes per coordinate over the cuboid `sides` centred
/// at `x`, restricted to the coordinates `coords` (others fixed at `x`).
pub(crate) fn grid_nodes(x: &[f64], sides: &[f64], grid: usize, coords: &[usize]) -> Vec<Vec<f64>> {
    let axis = |c: usize| -> Vec<f64> {
        if sides[c] == 0.0 {
            vec![x[c]]
        } else {
            (0..grid)
                .map(|i| x[c] - sides[c] / 2.0 + sides[c] * i as f64 / (grid - 1) as f64)
                .collect()
        }
    };
    let mut nodes = vec![x.to_vec()];
    for &c in coords {
        let ax = axis(c);
        nodes = nodes
            .into_iter()
            .flat_map(|p| {
                ax.iter().map(move |&v| {
                    let mut q = p.clone();
                    q[c] = v;
                    q
                })
            })
            .collect();
    }
    nodes
}

/// Estimates `sup |v_e|` over the cuboid of each component `e` of a smooth
/// function sampled at the nodes of [`grid_nodes`] over all coordinates
/// (`values[node][e]`): the grid maximum plus the covering radius times the
/// largest finite-difference slope between neighbouring nodes.
pub(crate) fn grid_sup_estimate(values: &[Vec<f64>], sides: &[f64], grid: usize) -> Vec<f64> {
    let n = sides.len();
    let dim = values.first().map_or(0, Vec::len);
    let counts: Vec<usize> = sides
        .iter()
        .map(|&w| if w == 0.0 { 1 } else { grid })
        .collect();
    let mut sup = vec![0.0f64; dim];
    let mut slope = vec![0.0f64; dim];
    for (idx, v) in values.iter().enumerate() {
        for e in 0..dim {
            sup[e] = sup[e].max(v[e].abs());
        }
        let mut stride = 1;
        let mut rem = idx;
        for c in (0..n).rev() {
            let ic = rem % counts[c];
            rem /= counts[c];
            if ic + 1 < counts[c] {
                let other = &values[idx + stride];
                let step = sides[c] / (grid - 1) as f64;
                for e in 0..dim {
                    slope[e] = slope[e].max((other[e] - v[e]).abs() / step);
                }
            }
            stride *= counts[c];
        }
    }
    let all: Vec<usize> = (0..n).collect();
    let h = covering_radius(sides, grid, &all);
    sup.iter().zip(&slope).map(|(s, d)| s + h * d).collect()
}

/// Largest distance from a point of the cuboid to its nearest grid node,
/// over the coordinates `coords`.
fn covering_radius(sides: &[f64], grid: usize, coords: &[usize]) -> f64 {
    0.5 * coords
        .iter()
        .map(|&c| (sides[c] / (grid - 1) as f64).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// Posterior derivative quantities of the GP part at one node.
struct NodeMoments {
    /// `∂_c μ_i` of the data part (row-major `n × n`, `i` rows).
    jac_gp: Vec<f64>,
    /// `H = ∇∇'κ_B(x, x)` (row-major `n × n`).
    h: Vec<f64>,
}

impl Mvgp<Rbf> {
    /// Lipschitz constants of `f_k = F(x)u̲` on the cuboid around `x` for the
    /// control `u` (module docs). `rng` draws the numerical samples.
    pub fn lipschitz<R: Rng>(
        &self,
        x: &[f64],
        u: &[f64],
        settings: &LipschitzSettings,
        rng: &mut R,
    ) -> Result<LipschitzEstimate, Error> {
        let n = self.state_dim();
        settings.validate(n)?;
        let ubar = self.augmented(x, u)?;
        let p = ubar.len();
        let hyper = self.hyper();
        let beta = self.beta_u(&ubar);
        let s = hyper.kernel.variance();
        let map = self.input_map();
        let d = map.output_dim(n);
        let mut coords: Vec<usize> = (0..d).map(|j| map.source(j)).collect();
        coords.sort_unstable();
        coords.dedup();
        let all: Vec<usize> = (0..n).collect();
        let sides = &settings.sides;
        let g = settings.grid;

        // posterior derivative moments on the kernel-coordinate grid
        let gp_nodes = grid_nodes(x, sides, g, &coords);
        let moments = self.node_moments(&gp_nodes, &ubar, beta);
        // full grid: prior-mean Jacobian plus the GP part of its projection
        let full = grid_nodes(x, sides, g, &all);
        let strides: Vec<usize> = {
            // index of a full node's projection in gp_nodes
            let mut st = vec![0; n];
            let mut acc = 1;
            for &c in coords.iter().rev() {
                st[c] = acc;
                acc *= if sides[c] == 0.0 { 1 } else { g };
            }
            st
        };
        let counts: Vec<usize> = (0..n)
            .map(|c| if sides[c] == 0.0 { 1 } else { g })
            .collect();
        let mut pj = PriorJacobian::new(n, p);
        let mut jmu: Vec<Vec<f64>> = Vec::with_capacity(full.len());
        let mut proj: Vec<usize> = Vec::with_capacity(full.len());
        for (idx, node) in full.iter().enumerate() {
            // multi-index of the node (last coordinate fastest)
            let mut rem = idx;
            let mut gi = 0;
            for c in (0..n).rev() {
                let ic = rem % counts[c];
                rem /= counts[c];
                gi += ic * strides[c];
            }
            jmu.push(pj.add_prior(self, node, &ubar, moments[gi].jac_gp.clone()));
            proj.push(gi);
        }
        if jmu.iter().flatten().any(|v| !v.is_finite()) {
            return Err(InputError::invalid_shown(
                "posterior mean Jacobian",
                "non-finite entries",
                "must be finite on the cuboid",
            )
            .into());
        }

        let mean_entries = grid_sup_estimate(&jmu, sides, g);

        // analytic bound
        let bounds = factor_bounds(&hyper.kernel, map, n);
        let consts = kernel_constants(&bounds, s, !self.is_empty());
        let h_gp = covering_radius(sides, g, &coords);
        let r = sides.iter().map(|w| w * w).sum::<f64>().sqrt();
        let log_term = (2.0 * (2.0 * (n * n) as f64 / settings.delta_l).ln()).sqrt();
        let dudley = 12.0 * (6.0 * n as f64).sqrt();
        let a = self.row_cov();
        let mut kernel_lipschitz = vec![0.0; n];
        let mut sigma_entries = vec![0.0; n * n];
        let mut analytic_entries = vec![0.0; n * n];
        for j in 0..n {
            let (l1, var0) = consts[j];
            let l1 = beta * l1;
            let lj = std::f64::consts::SQRT_2 * l1;
            kernel_lipschitz[j] = lj;
            let grid_var = moments.iter().map(|nm| nm.h[j * n + j]).fold(0.0, f64::max);
            let var = (beta * var0).min(grid_var + 2.0 * l1 * h_gp).max(0.0);
            for i in 0..n {
                let aii = a[(i, i)];
                let sig = (aii * var).sqrt();
                sigma_entries[i * n + j] = sig;
                analytic_entries[i * n + j] = mean_entries[i * n + j]
                    + log_term * sig
                    + dudley * sig.max((r * aii * lj).sqrt());
            }
        }
        let analytic = analytic_entries.iter().map(|v| v * v).sum::<f64>().sqrt();

        // numerical estimate
        let (numerical, numerical_entries) = if settings.samples == 0 {
            (None, Vec::new())
        } else {
            let la = self.row_cov_factor()?;
            let lh: Vec<DMatrix<f64>> = moments
                .iter()
                .map(|nm| psd_sqrt(&DMatrix::from_row_slice(n, n, &nm.h)))
                .collect();
            let mut maxima = vec![0.0f64; n * n];
            let mut z = DMatrix::zeros(n, n);
            for (jm, &gi) in jmu.iter().zip(&proj) {
                for _ in 0..settings.samples {
                    for v in z.iter_mut() {
                        *v = StandardNormal.sample(rng);
                    }
                    let e = &la * &z * lh[gi].transpose();
                    for i in 0..n {
                        for c in 0..n {
                            let v = (jm[i * n + c] + e[(i, c)]).abs();
                            maxima[i * n + c] = maxima[i * n + c].max(v);
                        }
                    }
                }
            }
            let l = maxima.iter().map(|v| v * v).sum::<f64>().sqrt();
            (Some(l), maxima)
        };
        Ok(LipschitzEstimate {
            analytic,
            numerical,
            analytic_entries,
            numerical_entries,
            mean_entries,
            sigma_entries,
            kernel_lipschitz,
            extension: r,
        })
    }

    /// Posterior of the Jacobian `J = ∂f/∂x` of `f = F(x)u̲` at `x`: its mean
    /// `∂μ` (`n × n`, `J_ic = ∂f_i/∂x_c`) and `H = ∇_x∇_{x'}κ_B(x, x)`, so that
    /// `Cov(J_ic, J_jd) = A_ij H_cd`.
    pub fn jacobian_posterior(
        &self,
        x: &[f64],
        u: &[f64],
    ) -> Result<(DMatrix<f64>, DMatrix<f64>), Error> {
        let n = self.state_dim();
        let ubar = self.augmented(x, u)?;
        let beta = self.beta_u(&ubar);
        let nm = self.node_moments(&[x.to_vec()], &ubar, beta).remove(0);
        let mut ws = PriorJacobian::new(n, ubar.len());
        let mean = ws.add_prior(self, x, &ubar, nm.jac_gp);
        Ok((
            DMatrix::from_row_slice(n, n, &mean),
            DMatrix::from_row_slice(n, n, &nm.h),
        ))
    }

    /// Checks `x` and `u` and returns `u̲ = [1, u]`.
    fn augmented(&self, x: &[f64], u: &[f64]) -> Result<Vec<f64>, Error> {
        let (n, m) = (self.state_dim(), self.control_dim());
        if x.len() != n {
            return Err(InputError::shape("x", n, x.len()).into());
        }
        if u.len() != m {
            return Err(InputError::shape("u", m, u.len()).into());
        }
        check_finite("x", x)?;
        check_finite("u", u)?;
        let mut ubar = vec![1.0; m + 1];
        ubar[1..].copy_from_slice(u);
        Ok(ubar)
    }

    /// `β = u̲ᵀ B u̲`.
    fn beta_u(&self, ubar: &[f64]) -> f64 {
        let b = &self.hyper().B;
        (0..ubar.len())
            .map(|a| {
                (0..ubar.len())
                    .map(|c| ubar[a] * b[(a, c)] * ubar[c])
                    .sum::<f64>()
            })
            .sum()
    }

    /// Data part of the mean Jacobian and the derivative covariance
    /// `H = ∇∇'κ_B(x, x)` at each node: with `w_l(x) = k0(x, x_l) u̲ᵀBu̲_l`,
    /// `∂_c μ_i = Σ_l α_li ∂_c w_l` and
    /// `H_cd = β ∂_c∂'_d k0(x, x) − (L⁻¹∂_c w)ᵀ(L⁻¹∂_d w)`.
    fn node_moments(&self, nodes: &[Vec<f64>], ubar: &[f64], beta: f64) -> Vec<NodeMoments> {
        let (n, p, k) = (self.state_dim(), ubar.len(), self.len());
        let map = self.input_map();
        let kern = &self.hyper().kernel;
        let d = map.output_dim(n);
        let zs = self.mapped_inputs();
        let bu = self.bu();
        let ub: Vec<f64> = (0..k)
            .map(|l| (0..p).map(|a| ubar[a] * bu[l * p + a]).sum())
            .collect();
        let mut z = vec![0.0; d];
        let mut grad = vec![0.0; d];
        let mut hess = vec![0.0; d * d];
        let mut out = Vec::with_capacity(nodes.len());
        // nodes in chunks so the right-hand side stays small
        for chunk in nodes.chunks(64) {
            let mut dw = Mat::<f64>::zeros(k, n * chunk.len());
            let mut prior_h = Vec::with_capacity(chunk.len());
            for (q, x) in chunk.iter().enumerate() {
                map.apply(x, &mut z);
                let dz: Vec<f64> = (0..d).map(|a| map.derivative(a, x)).collect();
                for l in 0..k {
                    kern.grad_x(&z, &zs[l * d..(l + 1) * d], &mut grad);
                    for a in 0..d {
                        dw[(l, q * n + map.source(a))] += grad[a] * dz[a] * ub[l];
                    }
                }
                kern.hess_xy(&z, &z, &mut hess);
                let mut h0 = vec![0.0; n * n];
                for a in 0..d {
                    for b in 0..d {
                        h0[map.source(a) * n + map.source(b)] +=
                            beta * dz[a] * hess[a * d + b] * dz[b];
                    }
                }
                prior_h.push(h0);
            }
            let mut jac_gp = vec![vec![0.0; n * n]; chunk.len()];
            if k > 0 {
                let alpha = self.alpha_mat();
                for (q, jg) in jac_gp.iter_mut().enumerate() {
                    for i in 0..n {
                        for c in 0..n {
                            jg[i * n + c] =
                                (0..k).map(|l| alpha[(l, i)] * dw[(l, q * n + c)]).sum();
                        }
                    }
                }
                self.factor().solve_l(dw.as_mut());
            }
            for (q, (mut h, jg)) in prior_h.into_iter().zip(jac_gp).enumerate() {
                if k > 0 {
                    for c in 0..n {
                        for e in 0..n {
                            let v: f64 = (0..k)
                                .map(|l| dw[(l, q * n + c)] * dw[(l, q * n + e)])
                                .sum();
                            h[c * n + e] -= v;
                        }
                    }
                }
                out.push(NodeMoments { jac_gp: jg, h });
            }
        }
        out
    }
}

/// Buffers for the prior mean's contribution `∂(M0(x)u̲)/∂x` to the mean
/// Jacobian.
struct PriorJacobian {
    n: usize,
    p: usize,
    jac0: Vec<f64>,
    sx: Vec<Dual64>,
    so: Vec<Dual64>,
}

impl PriorJacobian {
    fn new(n: usize, p: usize) -> Self {
        Self {
            n,
            p,
            jac0: vec![0.0; n * p * n],
            sx: vec![Dual64::from(0.0); n],
            so: vec![Dual64::from(0.0); n * p],
        }
    }

    /// `jac_gp + ∂(M0(x)u̲)/∂x` (row-major `n × n`).
    fn add_prior(
        &mut self,
        gp: &Mvgp<Rbf>,
        x: &[f64],
        ubar: &[f64],
        mut jac_gp: Vec<f64>,
    ) -> Vec<f64> {
        let (n, p) = (self.n, self.p);
        gp.prior()
            .jacobian(x, &mut self.jac0, &mut self.sx, &mut self.so);
        for i in 0..n {
            for c in 0..n {
                jac_gp[i * n + c] += (0..p)
                    .map(|a| self.jac0[(i + n * a) + n * p * c] * ubar[a])
                    .sum::<f64>();
            }
        }
        jac_gp
    }
}

/// Symmetric square root factor `S` with `S Sᵀ = M` (negative eigenvalues of
/// rounding clipped to zero).
fn psd_sqrt(mtx: &DMatrix<f64>) -> DMatrix<f64> {
    let sym = (mtx + mtx.transpose()) * 0.5;
    let e = SymmetricEigen::new(sym);
    let mut s = e.eigenvectors.clone();
    for (j, &lam) in e.eigenvalues.iter().enumerate() {
        let r = lam.max(0.0).sqrt();
        for i in 0..s.nrows() {
            s[(i, j)] *= r;
        }
    }
    s
}
