#![allow(clippy::needless_range_loop)]
//! Lemma 3 (Lipschitz bound of a posterior sample, with the corrections
//! documented in `gp/lipschitz.rs`) recomputed entry by entry from its
//! formulas on a small model, with a posterior written out independently of
//! the library (Gram matrix, residuals and kernel derivatives by hand); the
//! bound against brute-force slopes of joint posterior samples, from below
//! and from above; and the kernel constants against the exact supremum.

mod common;

use bayes_cbf::gp::{
    factor_bounds, kernel_constants, InputMap, LipschitzEstimate, LipschitzSettings, Mvgp,
    MvgpHyper, PriorMean, Rbf,
};
use common::{random_spd, RandomSystem};
use nalgebra::DMatrix;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use std::sync::Arc;

const N: usize = 2;
const P: usize = 2; // 1 + m, m = 1

/// The model's parameters, from which both the library model and the
/// independent reference are built.
struct Setup {
    ls: [f64; N],
    s: f64,
    a: DMatrix<f64>,
    b: DMatrix<f64>,
    sigma: f64,
    sys: RandomSystem,
    xs: Vec<[f64; N]>,
    us: Vec<f64>,
    xdot: Vec<[f64; N]>,
}

impl Setup {
    /// `k` observations scattered over `[−0.4, 0.4]²` (around the cuboids
    /// used below), a random prior mean `F_ic = a sin(wᵀx + b)`.
    fn new(seed: u64, k: usize) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let ls = [rng.random_range(0.5..0.8), rng.random_range(0.5..0.8)];
        let s = rng.random_range(0.8..1.5);
        let a = random_spd(N, &mut rng);
        let b = random_spd(P, &mut rng);
        let xs = (0..k)
            .map(|_| [rng.random_range(-0.4..0.4), rng.random_range(-0.4..0.4)])
            .collect();
        let us = (0..k).map(|_| rng.random_range(-1.0..1.0)).collect();
        let xdot = (0..k)
            .map(|_| [rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0)])
            .collect();
        Self {
            ls,
            s,
            a,
            b,
            sigma: 0.05,
            sys: RandomSystem::new(N, P - 1, seed + 100),
            xs,
            us,
            xdot,
        }
    }

    fn model(&self) -> Mvgp {
        let hyper = MvgpHyper {
            kernel: Rbf::new(self.ls.to_vec(), self.s).unwrap(),
            A: self.a.clone(),
            B: self.b.clone(),
            sigma: self.sigma,
        };
        let prior = PriorMean::System(Arc::new(self.sys.clone()));
        let mut gp = Mvgp::new(N, P - 1, hyper, prior, InputMap::Identity).unwrap();
        if !self.xs.is_empty() {
            let xs: Vec<f64> = self.xs.iter().flatten().copied().collect();
            let xdot: Vec<f64> = self.xdot.iter().flatten().copied().collect();
            gp.set_data(&xs, &self.us, &xdot).unwrap();
        }
        gp
    }

    /// `k0(x, y) = s exp(−½ Σ (x_c − y_c)²/ℓ_c²)`.
    fn k0(&self, x: &[f64], y: &[f64]) -> f64 {
        let q: f64 = (0..N).map(|c| ((x[c] - y[c]) / self.ls[c]).powi(2)).sum();
        self.s * (-0.5 * q).exp()
    }

    /// `∂k0(x, y)/∂x_j = −k0 (x_j − y_j)/ℓ_j²`.
    fn dk0(&self, x: &[f64], y: &[f64], j: usize) -> f64 {
        -self.k0(x, y) * (x[j] - y[j]) / (self.ls[j] * self.ls[j])
    }

    /// `M0(x)` entry `(i, c)` of the prior `F_ic = a_r sin(w_rᵀx + b_r)`,
    /// `r = i + n c` (column-major `vec F`).
    fn m0(&self, x: &[f64], i: usize, c: usize) -> f64 {
        let r = i + N * c;
        let arg: f64 = self.sys.b[r] + (0..N).map(|j| self.sys.w[r * N + j] * x[j]).sum::<f64>();
        self.sys.a[r] * arg.sin()
    }

    /// `∂M0_ic/∂x_j`.
    fn dm0(&self, x: &[f64], i: usize, c: usize, j: usize) -> f64 {
        let r = i + N * c;
        let arg: f64 = self.sys.b[r] + (0..N).map(|j| self.sys.w[r * N + j] * x[j]).sum::<f64>();
        self.sys.a[r] * arg.cos() * self.sys.w[r * N + j]
    }
}

/// The posterior of `f = F(x)u̲` written out from Prop. 1:
/// `G_ll' = u̲_lᵀBu̲_l' k0(x_l, x_l') + σ²δ_ll'`, residuals
/// `R_l = ẋ_l − M0(x_l)u̲_l`, `α = G⁻¹R`; with `w_l(x) = k0(x, x_l) u̲_lᵀBu̲`,
/// `μ(x) = M0(x)u̲ + Σ_l α_l w_l(x)` and
/// `κ_B(x, y) = β k0(x, y) − w(x)ᵀG⁻¹w(y)`, `β = u̲ᵀBu̲`.
struct Reference<'a> {
    st: &'a Setup,
    ubar: [f64; P],
    beta: f64,
    /// `u̲_lᵀ B u̲` per observation.
    coef: Vec<f64>,
    ginv: DMatrix<f64>,
    /// `α`, `k × n`.
    alpha: DMatrix<f64>,
}

impl<'a> Reference<'a> {
    fn new(st: &'a Setup, u: f64) -> Self {
        let ubar = [1.0, u];
        let ubl = |l: usize| [1.0, st.us[l]];
        let quad = |x: &[f64; P], y: &[f64; P]| -> f64 {
            (0..P)
                .map(|a| (0..P).map(|c| x[a] * st.b[(a, c)] * y[c]).sum::<f64>())
                .sum()
        };
        let k = st.xs.len();
        let g = DMatrix::from_fn(k, k, |l, m| {
            quad(&ubl(l), &ubl(m)) * st.k0(&st.xs[l], &st.xs[m])
                + if l == m { st.sigma * st.sigma } else { 0.0 }
        });
        let ginv = if k > 0 {
            g.clone().cholesky().unwrap().inverse()
        } else {
            g
        };
        let resid = DMatrix::from_fn(k, N, |l, i| {
            st.xdot[l][i]
                - (0..P)
                    .map(|c| st.m0(&st.xs[l], i, c) * ubl(l)[c])
                    .sum::<f64>()
        });
        let alpha = &ginv * resid;
        Self {
            st,
            ubar,
            beta: quad(&ubar, &ubar),
            coef: (0..k).map(|l| quad(&ubl(l), &ubar)).collect(),
            ginv,
            alpha,
        }
    }

    fn k(&self) -> usize {
        self.coef.len()
    }

    fn mean(&self, x: &[f64]) -> [f64; N] {
        let st = self.st;
        let mut f = [0.0; N];
        for (i, fi) in f.iter_mut().enumerate() {
            *fi = (0..P).map(|c| st.m0(x, i, c) * self.ubar[c]).sum::<f64>();
            for l in 0..self.k() {
                *fi += self.alpha[(l, i)] * st.k0(x, &st.xs[l]) * self.coef[l];
            }
        }
        f
    }

    /// `∂μ_i/∂x_j` (the posterior mean's Jacobian, correction (i)).
    fn mean_jacobian(&self, x: &[f64]) -> [[f64; N]; N] {
        let st = self.st;
        let mut jac = [[0.0; N]; N];
        for (i, row) in jac.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v = (0..P)
                    .map(|c| st.dm0(x, i, c, j) * self.ubar[c])
                    .sum::<f64>();
                for l in 0..self.k() {
                    *v += self.alpha[(l, i)] * st.dk0(x, &st.xs[l], j) * self.coef[l];
                }
            }
        }
        jac
    }

    fn kappa(&self, x: &[f64], y: &[f64]) -> f64 {
        let st = self.st;
        let k = self.k();
        let wx: Vec<f64> = (0..k).map(|l| st.k0(x, &st.xs[l]) * self.coef[l]).collect();
        let wy: Vec<f64> = (0..k).map(|l| st.k0(y, &st.xs[l]) * self.coef[l]).collect();
        let mut v = self.beta * st.k0(x, y);
        for l in 0..k {
            for m in 0..k {
                v -= wx[l] * self.ginv[(l, m)] * wy[m];
            }
        }
        v
    }

    /// `∂²κ_B(x, y)/∂x_j∂y_j` at `y = x`: the posterior variance of `∂_j e_i`
    /// per unit `A_ii`, `β s/ℓ_j² − ∂_jw(x)ᵀG⁻¹∂_jw(x)`.
    fn derivative_variance(&self, x: &[f64], j: usize) -> f64 {
        let st = self.st;
        let k = self.k();
        let dw: Vec<f64> = (0..k)
            .map(|l| st.dk0(x, &st.xs[l], j) * self.coef[l])
            .collect();
        let mut v = self.beta * st.s / (st.ls[j] * st.ls[j]);
        for l in 0..k {
            for m in 0..k {
                v -= dw[l] * self.ginv[(l, m)] * dw[m];
            }
        }
        v
    }
}

/// The grid of `g × g` nodes over the cuboid with centre `xc` and sides
/// `sides`, as `[a][b]` (coordinate 0 by `a`, 1 by `b`).
fn grid(xc: &[f64; N], sides: &[f64; N], g: usize) -> Vec<Vec<[f64; N]>> {
    let t = |c: usize, i: usize| xc[c] - sides[c] / 2.0 + sides[c] * i as f64 / (g - 1) as f64;
    (0..g)
        .map(|a| (0..g).map(|b| [t(0, a), t(1, b)]).collect())
        .collect()
}

/// Every quantity of the corrected Lemma 3, recomputed.
struct Expected {
    mean: [[f64; N]; N],
    sigma: [[f64; N]; N],
    kernel_lipschitz: [f64; N],
    entries: [[f64; N]; N],
    /// Whether `σ_ij` came from the grid (not the prior variance).
    grid_branch: [bool; N],
}

/// The Gaussian factor `ψ(Δ) = exp(−Δ²/2ℓ²)` of one coordinate: suprema of
/// `|ψ'| = e^{−1/2}/ℓ` (at `Δ = ℓ`), `|ψ''|` = `1/ℓ²` (at 0),
/// `|ψ'''| = |3t − t³| e^{−t²/2}/ℓ³` with `t = Δ/ℓ`, largest where
/// `t⁴ − 6t² + 3 = 0`, `t² = 3 − √6`, i.e. `√6 t e^{−t²/2}/ℓ³`; the
/// diagonal values `∂_a∂_bψ(a, a) = 1/ℓ²`, `∂_a²∂_b²ψ(a, a) = 3/ℓ⁴`.
fn gaussian_factor(l: f64) -> (f64, f64, f64, f64, f64) {
    let t = (3.0 - 6f64.sqrt()).sqrt();
    (
        (-0.5f64).exp() / l,
        1.0 / (l * l),
        6f64.sqrt() * t * (-t * t / 2.0).exp() / l.powi(3),
        1.0 / (l * l),
        3.0 / l.powi(4),
    )
}

fn expected(
    st: &Setup,
    refp: &Reference,
    xc: &[f64; N],
    sides: &[f64; N],
    g: usize,
    delta_l: f64,
) -> Expected {
    let nodes = grid(xc, sides, g);
    let steps = [sides[0] / (g - 1) as f64, sides[1] / (g - 1) as f64];
    // covering radius: the largest distance from a point of the cuboid to
    // the nearest node, half the diagonal of a grid cell
    let h = 0.5 * (steps[0].powi(2) + steps[1].powi(2)).sqrt();
    let jac: Vec<Vec<[[f64; N]; N]>> = nodes
        .iter()
        .map(|row| row.iter().map(|x| refp.mean_jacobian(x)).collect())
        .collect();
    // sup_X |∂_j μ_i|: the grid maximum plus h times the largest slope
    // between neighbouring nodes
    let mut mean = [[0.0; N]; N];
    for i in 0..N {
        for j in 0..N {
            let (mut sup, mut slope) = (0.0f64, 0.0f64);
            for a in 0..g {
                for b in 0..g {
                    let v = jac[a][b][i][j];
                    sup = sup.max(v.abs());
                    if a + 1 < g {
                        slope = slope.max((jac[a + 1][b][i][j] - v).abs() / steps[0]);
                    }
                    if b + 1 < g {
                        slope = slope.max((jac[a][b + 1][i][j] - v).abs() / steps[1]);
                    }
                }
            }
            mean[i][j] = sup + h * slope;
        }
    }
    let fb = [gaussian_factor(st.ls[0]), gaussian_factor(st.ls[1])];
    let with_data = refp.k() > 0;
    let r = (sides[0].powi(2) + sides[1].powi(2)).sqrt();
    let log_term = (2.0 * (2.0 * (N * N) as f64 / delta_l).ln()).sqrt();
    let dudley = 12.0 * (6.0 * N as f64).sqrt();
    let mut out = Expected {
        mean,
        sigma: [[0.0; N]; N],
        kernel_lipschitz: [0.0; N],
        entries: [[0.0; N]; N],
        grid_branch: [false; N],
    };
    for j in 0..N {
        let l = 1 - j;
        let (_, m11j, m21j, d11j, d22j) = fb[j];
        let (m1l, _, _, d11l, _) = fb[l];
        // one-argument Lipschitz constant of κ^{∂j}: the prior part
        // β s √(M21_j² + M11_j² M1_l²) and, with data, the correction
        // β s √(D11_j (D22_j + D11_l D11_j))
        let prior = st.s * (m21j * m21j + (m11j * m1l).powi(2)).sqrt();
        let corr = if with_data {
            st.s * (d11j * (d22j + d11l * d11j)).sqrt()
        } else {
            0.0
        };
        let l1 = refp.beta * (prior + corr);
        let lj = std::f64::consts::SQRT_2 * l1;
        out.kernel_lipschitz[j] = lj;
        // σ_ij² / A_ii: the prior variance β s D11_j, or the grid maximum
        // of the posterior variance plus 2 L₁ h (κ^{∂j}(x, x) is
        // 2L₁-Lipschitz), whichever is smaller
        let grid_var = nodes
            .iter()
            .flatten()
            .map(|x| refp.derivative_variance(x, j))
            .fold(0.0, f64::max);
        let var = (refp.beta * st.s * d11j)
            .min(grid_var + 2.0 * l1 * h)
            .max(0.0);
        out.grid_branch[j] = grid_var + 2.0 * l1 * h < refp.beta * st.s * d11j;
        for i in 0..N {
            let aii = st.a[(i, i)];
            let sig = (aii * var).sqrt();
            out.sigma[i][j] = sig;
            out.entries[i][j] =
                out.mean[i][j] + log_term * sig + dudley * sig.max((r * aii * lj).sqrt());
        }
    }
    out
}

fn assert_rel(got: f64, want: f64, what: &str) {
    assert!(
        (got - want).abs() <= 1e-9 * want.abs().max(1e-12),
        "{what}: {got} vs {want} (rel {:e})",
        (got - want).abs() / want.abs()
    );
}

fn check_entries(est: &LipschitzEstimate, exp: &Expected, label: &str) {
    for i in 0..N {
        for j in 0..N {
            let e = i * N + j;
            assert_rel(
                est.mean_entries[e],
                exp.mean[i][j],
                &format!("{label} sup|∂_{j}μ_{i}|"),
            );
            assert_rel(
                est.sigma_entries[e],
                exp.sigma[i][j],
                &format!("{label} σ_{i}{j}"),
            );
            assert_rel(
                est.analytic_entries[e],
                exp.entries[i][j],
                &format!("{label} L_{i}{j}"),
            );
        }
        assert_rel(
            est.kernel_lipschitz[i],
            exp.kernel_lipschitz[i],
            &format!("{label} L^∂{i}"),
        );
    }
    let frob = exp
        .entries
        .iter()
        .flatten()
        .map(|v| v * v)
        .sum::<f64>()
        .sqrt();
    assert_rel(est.analytic, frob, &format!("{label} L_f"));
}

/// Largest slope `‖f(x) − f(x')‖/‖x − x'‖` between neighbouring nodes
/// (horizontal, vertical, both diagonals) of a `g × g` grid over the cuboid,
/// over `draws` joint posterior samples of `f` on the grid:
/// `vec f ~ N(μ, K_B ⊗ A)`, `K_B[a, b] = κ_B(x_a, x_b)`.
fn brute_force_slope(
    refp: &Reference,
    xc: &[f64; N],
    sides: &[f64; N],
    g: usize,
    draws: usize,
    seed: u64,
) -> f64 {
    let pts: Vec<[f64; N]> = grid(xc, sides, g).into_iter().flatten().collect();
    let np = pts.len();
    let mut kb = DMatrix::from_fn(np, np, |a, b| refp.kappa(&pts[a], &pts[b]));
    let jitter = 1e-10 * kb.diagonal().max();
    for a in 0..np {
        kb[(a, a)] += jitter;
    }
    let lk = kb.cholesky().expect("posterior covariance").l();
    let la = refp.st.a.clone().cholesky().unwrap().l();
    let mu: Vec<[f64; N]> = pts.iter().map(|x| refp.mean(x)).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut max_slope = 0.0f64;
    for _ in 0..draws {
        let z = DMatrix::from_fn(np, N, |_, _| StandardNormal.sample(&mut rng));
        let e = &lk * z * la.transpose();
        let f = |q: usize, i: usize| mu[q][i] + e[(q, i)];
        for a in 0..g {
            for b in 0..g {
                let q = a * g + b;
                for (da, db) in [(1i64, 0i64), (0, 1), (1, 1), (1, -1)] {
                    let (a2, b2) = (a as i64 + da, b as i64 + db);
                    if a2 >= g as i64 || b2 < 0 || b2 >= g as i64 {
                        continue;
                    }
                    let r = a2 as usize * g + b2 as usize;
                    let df = ((f(r, 0) - f(q, 0)).powi(2) + (f(r, 1) - f(q, 1)).powi(2)).sqrt();
                    let dx =
                        ((pts[r][0] - pts[q][0]).powi(2) + (pts[r][1] - pts[q][1]).powi(2)).sqrt();
                    max_slope = max_slope.max(df / dx);
                }
            }
        }
    }
    max_slope
}

/// One case: the library's estimate against the recomputed formulas, and
/// the ratio of the bound to brute-force sample slopes, which must be at
/// least 1 (a bound) and at most twice the `measured` ratio. Returns the
/// recomputed quantities.
fn lemma_three_case(label: &str, seed: u64, k: usize, measured: f64) -> Expected {
    let st = Setup::new(seed, k);
    let gp = st.model();
    let (xc, u) = ([0.1, -0.05], 0.6);
    let refp = Reference::new(&st, u);
    // the reference posterior is the library's
    for x in [[0.0, 0.0], [0.2, -0.3], [-0.25, 0.15]] {
        let mm = gp.posterior_mean(&x).unwrap();
        let f = refp.mean(&x);
        for (i, fi) in f.iter().enumerate() {
            let lib = mm[(i, 0)] + mm[(i, 1)] * u;
            assert!(
                (lib - fi).abs() < 1e-9 * (1.0 + fi.abs()),
                "{label}: μ {lib} vs {fi}"
            );
        }
        let b = gp.posterior_cov(&x, &[0.1, 0.1]).unwrap();
        let kap: f64 = (0..P)
            .map(|a| {
                (0..P)
                    .map(|c| refp.ubar[a] * b[(a, c)] * refp.ubar[c])
                    .sum::<f64>()
            })
            .sum();
        let want = refp.kappa(&x, &[0.1, 0.1]);
        assert!(
            (kap - want).abs() < 1e-9 * (1.0 + want.abs()),
            "{label}: κ {kap} vs {want}"
        );
    }
    let sides = [0.5, 0.4];
    let (g, delta_l) = (10, 1e-2);
    let settings = LipschitzSettings {
        delta_l,
        sides: sides.to_vec(),
        grid: g,
        samples: 0,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let est = gp.lipschitz(&xc, &[u], &settings, &mut rng).unwrap();
    let exp = expected(&st, &refp, &xc, &sides, g, delta_l);
    check_entries(&est, &exp, label);
    assert_rel(
        est.extension,
        (sides[0].powi(2) + sides[1].powi(2)).sqrt(),
        label,
    );
    let slope = brute_force_slope(&refp, &xc, &sides, 25, 200, seed + 1);
    let ratio = est.analytic / slope;
    eprintln!(
        "{label}: L_f = {:.4}, brute-force slope {slope:.4}, ratio {ratio:.3}; entries {:?}",
        est.analytic, est.analytic_entries
    );
    assert!(
        ratio >= 1.0,
        "{label}: bound below a sample slope: ratio {ratio}"
    );
    assert!(
        ratio <= 2.0 * measured,
        "{label}: bound looser than measured: ratio {ratio}"
    );
    exp
}

/// The prior alone (no data): `σ_ij² = A_ii β s/ℓ_j²` exactly, and the mean
/// Jacobian is the prior mean's.
///
/// The bound exceeds the sample slopes by a factor set mostly by the
/// Dudley constant `12√(6n) ≈ 41.6` of the entropy term; measured 25.1 here.
#[test]
fn lemma_three_entries_without_data() {
    let exp = lemma_three_case("no data", 31, 0, 25.1);
    assert_eq!(exp.grid_branch, [false; N]);
}

/// Twelve observations around the cuboid: the posterior mean's Jacobian has
/// a data part, the derivative variance on the grid is so far below the
/// prior's that `σ_i0` comes from the grid maximum plus its covering term
/// `2L₁h` (`σ_i1` from the prior variance), and the kernel constant carries
/// the posterior correction. Measured ratio of the bound to the sample
/// slopes: 14.8.
#[test]
fn lemma_three_entries_with_data() {
    let exp = lemma_three_case("with data", 32, 12, 14.8);
    assert_eq!(exp.grid_branch, [true, false], "which σ come from the grid");
}

/// The one-argument Lipschitz constant of the prior derivative kernel
/// `κ^{∂j}_0(x, y) = β s ∂_j∂'_j k0`, `β = 1`, against its exact suprema:
/// with `t = Δ_j/ℓ_j`, `ρ = Δ_l/ℓ_l` (`Δ = x − y`),
/// `κ^{∂j}_0 = (s/ℓ_j²)(1 − t²) e^{−(t² + ρ²)/2}` and
/// `∇_x κ^{∂j}_0 = (s/ℓ_j²) e^{−(t²+ρ²)/2} ((t³ − 3t)/ℓ_j, −(1 − t²) ρ/ℓ_l)`,
/// maximised on a dense `(t, ρ)` grid. The constant
/// `s √(M21_j² + M11_j² M1_l²)` is the root-sum-square of the two
/// components' suprema, which are attained at different points: it equals
/// that root-sum-square (to the grid's accuracy), and it lies between the
/// supremum of the gradient's norm and `√2` times it.
#[test]
fn prior_kernel_constant_is_tight() {
    for (ls, s) in [([0.6, 0.6], 1.0), ([0.5, 1.3], 1.7), ([1.4, 0.45], 0.6)] {
        let kern = Rbf::new(ls.to_vec(), s).unwrap();
        let bounds = factor_bounds(&kern, &InputMap::Identity, N);
        let consts = kernel_constants(&bounds, s, false);
        for j in 0..N {
            let l = 1 - j;
            let (lj, ll) = (ls[j], ls[l]);
            let (mut sup, mut sup_j, mut sup_l) = (0.0f64, 0.0f64, 0.0f64);
            let steps = 1601;
            for a in 0..steps {
                let t = -4.0 + 8.0 * a as f64 / (steps - 1) as f64;
                for b in 0..steps {
                    let rho = -4.0 + 8.0 * b as f64 / (steps - 1) as f64;
                    let e = (s / (lj * lj)) * (-(t * t + rho * rho) / 2.0).exp();
                    let gj = e * (t * t * t - 3.0 * t) / lj;
                    let gl = -e * (1.0 - t * t) * rho / ll;
                    sup = sup.max((gj * gj + gl * gl).sqrt());
                    sup_j = sup_j.max(gj.abs());
                    sup_l = sup_l.max(gl.abs());
                }
            }
            let bound = consts[j].0;
            let rss = (sup_j * sup_j + sup_l * sup_l).sqrt();
            assert!(
                (bound - rss).abs() <= 1e-4 * rss,
                "{ls:?} j = {j}: constant {bound} vs root-sum-square of suprema {rss}"
            );
            assert!(
                sup <= bound * (1.0 + 1e-9) && bound <= std::f64::consts::SQRT_2 * sup,
                "{ls:?} j = {j}: constant {bound} vs supremum {sup}"
            );
            // the prior variance of ∂_j: s/ℓ_j² exactly
            assert_rel(consts[j].1, s / (lj * lj), "prior variance of ∂_j");
        }
    }
}

/// `min_ρ p! q! exp(Σ_f 2 m_f(ρ)²/ℓ_f²) / ρ^{p+q}` (`m_f = ρ` for a
/// coordinate, `sinh ρ` for cos and sin) by golden-section search on
/// `log ρ` (the objective is convex in `log ρ`): the Cauchy estimate of a
/// periodic factor's derivative suprema, computed independently.
fn cauchy_minimum(feats: &[(bool, f64)], p: i32, q: i32) -> f64 {
    let fact = |k: i32| (1..=k).map(f64::from).product::<f64>();
    let log_bound = |t: f64| {
        let rho = t.exp();
        let e: f64 = feats
            .iter()
            .map(|&(trig, l)| {
                let m = if trig { rho.sinh() } else { rho };
                2.0 * m * m / (l * l)
            })
            .sum();
        e - f64::from(p + q) * t
    };
    let (mut a, mut b) = ((1e-3f64).ln(), 10f64.ln());
    let g = (5f64.sqrt() - 1.0) / 2.0;
    for _ in 0..200 {
        let (c, d) = (b - g * (b - a), a + g * (b - a));
        if log_bound(c) < log_bound(d) {
            b = d;
        } else {
            a = c;
        }
    }
    fact(p) * fact(q) * log_bound(0.5 * (a + b)).exp()
}

/// The suprema of a periodic coordinate's kernel factor (features cos and
/// sin, or a coordinate beside them) are the Cauchy estimates minimised
/// over the radius: never below the true minimum (each radius gives a valid
/// bound) and within 0.1 % of it (the library searches a grid of radii).
#[test]
fn periodic_factor_bounds_are_the_minimised_cauchy_estimates() {
    use bayes_cbf::gp::Feature;
    for (feats, ls) in [
        (vec![Feature::Cos(0), Feature::Sin(0)], vec![0.7, 1.3]),
        (vec![Feature::Cos(0), Feature::Sin(0)], vec![2.5, 2.5]),
        (vec![Feature::Coord(0), Feature::Cos(0)], vec![0.9, 0.4]),
    ] {
        let kind: Vec<(bool, f64)> = feats
            .iter()
            .zip(&ls)
            .map(|(f, &l)| (!matches!(f, Feature::Coord(_)), l))
            .collect();
        let kern = Rbf::new(ls.clone(), 1.0).unwrap();
        let b = factor_bounds(&kern, &InputMap::Features(feats.clone()), 1)[0];
        for (got, p, q) in [(b.m1, 1, 0), (b.m11, 1, 1), (b.m21, 2, 1)] {
            let want = cauchy_minimum(&kind, p, q);
            assert!(
                got >= want * (1.0 - 1e-12) && got <= want * 1.001,
                "{feats:?} {ls:?} (p, q) = ({p}, {q}): {got} against {want}"
            );
        }
    }
}

/// A coordinate the kernel does not see (no feature of the input map reads
/// it) has a constant factor: every derivative bound is zero.
#[test]
fn a_coordinate_the_kernel_ignores_has_zero_factor_bounds() {
    use bayes_cbf::gp::Feature;
    let kern = Rbf::new(vec![0.8, 1.1], 1.0).unwrap();
    let map = InputMap::Features(vec![Feature::Cos(0), Feature::Sin(0)]);
    let b = factor_bounds(&kern, &map, 2);
    assert_eq!(b.len(), 2);
    assert!(b[0].m1 > 0.0);
    assert_eq!(b[1], Default::default());
}

/// A model with `hyper`, the prior mean of a random system (`prior_seed`)
/// and `k` observations: states uniform in `[−w, w]ⁿ`, controls and
/// derivatives in `[−1, 1]`.
fn random_model(
    hyper: MvgpHyper,
    (n, m, k): (usize, usize, usize),
    w: f64,
    prior_seed: u64,
    rng: &mut ChaCha8Rng,
) -> Mvgp {
    let prior = PriorMean::System(Arc::new(RandomSystem::new(n, m, prior_seed)));
    let mut gp = Mvgp::new(n, m, hyper, prior, InputMap::Identity).unwrap();
    let xs: Vec<f64> = (0..k * n).map(|_| rng.random_range(-w..w)).collect();
    let us: Vec<f64> = (0..k * m).map(|_| rng.random_range(-1.0..1.0)).collect();
    let xd: Vec<f64> = (0..k * n).map(|_| rng.random_range(-1.0..1.0)).collect();
    gp.set_data(&xs, &us, &xd).unwrap();
    gp
}

/// The Euclidean norm.
fn euclidean(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

/// The numerical estimate on a one-node cuboid (every side 0) is the
/// largest `|J_ic|` over posterior draws `J = ∂μ + L_A Z L_Hᵀ` of the
/// Jacobian, whose entry `(i, c)` has mean `∂μ_ic` and standard deviation
/// `√(A_ii H_cc)` ([`Mvgp::jacobian_posterior`]). Over 20 000 draws the
/// excess `(entry − |∂μ_ic|)/√(A_ii H_cc)` of each entry is the largest of
/// 20 000 standard normals (folded when `∂μ_ic ≈ 0`): between 2.5 and 5.5
/// (it is outside with probability below 10⁻³ per entry). A wrong square
/// root of `H`, a draw combined wrongly or an entry written to another
/// place moves it out.
#[test]
fn numerical_estimate_is_the_largest_posterior_draw_of_each_entry() {
    let mut rng = ChaCha8Rng::seed_from_u64(31);
    let (n, m, k) = (2, 1, 12);
    let a = random_spd(n, &mut rng) * 0.3 + DMatrix::from_diagonal(&nalgebra::dvector![2.0, 0.05]);
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![0.7, 1.9], 1.3).unwrap(),
        A: a,
        B: random_spd(m + 1, &mut rng),
        sigma: 0.2,
    };
    let gp = random_model(hyper, (n, m, k), 1.5, 5, &mut rng);
    let (x, u) = ([0.3, -0.4], [0.6]);
    let settings = LipschitzSettings {
        delta_l: 1e-2,
        sides: vec![0.0; n],
        grid: 2,
        samples: 20_000,
    };
    let est = gp.lipschitz(&x, &u, &settings, &mut rng).unwrap();
    let (mean, h) = gp.jacobian_posterior(&x, &u).unwrap();
    let a = gp.row_cov();
    let mut stds = Vec::new();
    for i in 0..n {
        for c in 0..n {
            let sd = (a[(i, i)] * h[(c, c)]).sqrt();
            stds.push(sd);
            let excess = (est.numerical_entries[i * n + c] - mean[(i, c)].abs()) / sd;
            assert!(
                (2.5..5.5).contains(&excess),
                "entry ({i}, {c}): {} against |mean| {} and sd {sd}: excess {excess}",
                est.numerical_entries[i * n + c],
                mean[(i, c)].abs()
            );
        }
    }
    // the entries' spreads differ enough for a swap of entries to show
    let (lo, hi) = stds
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(l, h), s| (l.min(*s), h.max(*s)));
    assert!(hi > 3.0 * lo, "{stds:?}");
    let norm = euclidean(&est.numerical_entries);
    assert!((est.numerical.unwrap() - norm).abs() <= 1e-12 * norm);
}

/// In any dimension each analytic entry is Lemma 3's sum of its reported
/// parts: `L_ij = M_ij + √(2 ln(2n²/δ_L)) σ_ij + 12 √(6n) max(σ_ij,
/// √(r A_ii L_j))` with `r` the cuboid's diagonal (its extension) and `L_j`
/// the kernel's Lipschitz constant (checked here at n = 1 and 3, where
/// `n²`, `2n` and `n + n` differ).
#[test]
fn analytic_entries_are_the_sum_of_their_parts_in_any_dimension() {
    for n in [1usize, 3] {
        let mut rng = ChaCha8Rng::seed_from_u64(40 + n as u64);
        let m = 1;
        let hyper = MvgpHyper {
            kernel: Rbf::new(vec![0.9; n], 1.1).unwrap(),
            A: random_spd(n, &mut rng),
            B: random_spd(m + 1, &mut rng),
            sigma: 0.2,
        };
        let gp = random_model(hyper, (n, m, 8), 1.0, 9, &mut rng);
        let delta_l = 0.01;
        let settings = LipschitzSettings {
            delta_l,
            sides: vec![0.3; n],
            grid: 3,
            samples: 0,
        };
        let x = vec![0.1; n];
        let est = gp.lipschitz(&x, &[0.4], &settings, &mut rng).unwrap();
        let log_term = (2.0 * (2.0 * (n * n) as f64 / delta_l).ln()).sqrt();
        let dudley = 12.0 * (6.0 * n as f64).sqrt();
        let a = gp.row_cov();
        for i in 0..n {
            for j in 0..n {
                let e = i * n + j;
                let sig = est.sigma_entries[e];
                let want = est.mean_entries[e]
                    + log_term * sig
                    + dudley
                        * sig.max((est.extension * a[(i, i)] * est.kernel_lipschitz[j]).sqrt());
                let got = est.analytic_entries[e];
                assert!(
                    (got - want).abs() <= 1e-12 * want,
                    "n = {n} ({i}, {j}): {got} {want}"
                );
            }
        }
        let norm = euclidean(&est.analytic_entries);
        assert!((est.analytic - norm).abs() <= 1e-12 * norm);
        // the extension is the diagonal of the cuboid
        let r = (n as f64 * 0.09).sqrt();
        assert!((est.extension - r).abs() < 1e-15);
    }
}

/// The settings' boundaries: `δ_L` in the open interval, at least two grid
/// nodes, at most 10⁶ grid nodes in all.
#[test]
fn settings_boundaries() {
    let ok = |delta_l: f64, grid: usize, n: usize| {
        LipschitzSettings {
            delta_l,
            sides: vec![0.1; n],
            grid,
            samples: 0,
        }
        .validate(n)
        .is_ok()
    };
    assert!(ok(0.5, 2, 2));
    assert!(!ok(1.0, 10, 2) && !ok(0.0, 10, 2) && ok(1.0 - 1e-12, 10, 2));
    assert!(!ok(0.5, 1, 2));
    assert!(ok(0.5, 1000, 2) && !ok(0.5, 1001, 2));
    assert!(ok(0.5, 100, 3) && !ok(0.5, 101, 3));
}
