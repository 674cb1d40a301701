//! Shared helpers of the integration tests.
#![allow(dead_code, clippy::needless_range_loop)]

use bayes_cbf::systems::ControlAffine;
use nalgebra::DMatrix;
use num_dual::DualNum;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A smooth random control-affine system: `F_ic(x) = a_ic sin(w_icᵀ x + b_ic)`.
#[derive(Debug, Clone)]
pub struct RandomSystem {
    pub n: usize,
    pub m: usize,
    pub a: Vec<f64>,
    pub w: Vec<f64>,
    pub b: Vec<f64>,
}

impl RandomSystem {
    pub fn new(n: usize, m: usize, seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let cnt = n * (1 + m);
        Self {
            n,
            m,
            a: (0..cnt).map(|_| rng.random_range(-1.0..1.0)).collect(),
            w: (0..cnt * n).map(|_| rng.random_range(-1.0..1.0)).collect(),
            b: (0..cnt).map(|_| rng.random_range(-1.0..1.0)).collect(),
        }
    }
}

impl ControlAffine for RandomSystem {
    fn state_dim(&self) -> usize {
        self.n
    }
    fn control_dim(&self) -> usize {
        self.m
    }
    fn dynamics<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D], out: &mut [D]) {
        for (r, o) in out.iter_mut().enumerate() {
            let mut s = D::from(self.b[r]);
            for j in 0..self.n {
                s += x[j] * self.w[r * self.n + j];
            }
            *o = s.sin() * self.a[r];
        }
    }
}

/// The cases of the brute-force posterior checks: `n ∈ 1..=3`,
/// `m ∈ 1..=2`, a zero prior mean and a [`RandomSystem`] one, each with its
/// own seed.
pub fn for_each_posterior_case(mut check: impl FnMut(usize, usize, bayes_cbf::gp::PriorMean, u64)) {
    use bayes_cbf::gp::PriorMean;
    let mut seed = 0;
    for n in 1..=3 {
        for m in 1..=2 {
            for nonzero_prior in [false, true] {
                let prior = if nonzero_prior {
                    PriorMean::System(std::sync::Arc::new(RandomSystem::new(n, m, seed + 100)))
                } else {
                    PriorMean::Zero
                };
                check(n, m, prior, seed);
                seed += 1;
            }
        }
    }
}

/// Selection matrix `P = u̲ᵀ ⊗ I_n` so that `F(x) u̲ = P vec F(x)`.
pub fn selection(u: &[f64], n: usize) -> DMatrix<f64> {
    let p = u.len();
    let mut s = DMatrix::zeros(n, n * p);
    for c in 0..p {
        for i in 0..n {
            s[(i, i + n * c)] = u[c];
        }
    }
    s
}

/// A random symmetric positive-definite matrix.
pub fn random_spd(dim: usize, rng: &mut ChaCha8Rng) -> DMatrix<f64> {
    let c = DMatrix::from_fn(dim, dim, |_, _| rng.random_range(-1.0..1.0));
    &c * c.transpose() + DMatrix::identity(dim, dim) * 0.3
}

/// An RBF kernel on `d` inputs with lengthscales drawn from `scales` and
/// then a variance from `[0.5, 2)`.
pub fn random_rbf(
    d: usize,
    scales: std::ops::Range<f64>,
    rng: &mut ChaCha8Rng,
) -> bayes_cbf::gp::Rbf {
    let ls = (0..d).map(|_| rng.random_range(scales.clone())).collect();
    bayes_cbf::gp::Rbf::new(ls, rng.random_range(0.5..2.0)).unwrap()
}

/// Max relative difference `|a − b| / max(1, |b|)`, entrywise, scaled by the
/// largest magnitude of `b`.
pub fn rel_diff(a: &DMatrix<f64>, b: &DMatrix<f64>) -> f64 {
    assert_eq!(a.shape(), b.shape());
    let scale = b.iter().fold(1e-300f64, |s, v| s.max(v.abs()));
    a.iter()
        .zip(b.iter())
        .fold(0.0f64, |m, (x, y)| m.max((x - y).abs() / scale))
}

/// A 2-state, 1-input MVGP with a pendulum prior mean (m = 2, l = 1, g = 9),
/// RBF lengthscales (0.8, 1.1), variance 1.3, random `A`, `B`, σ = 0.05.
pub fn pendulum_model(seed: u64) -> bayes_cbf::gp::Mvgp {
    use bayes_cbf::gp::{InputMap, Mvgp, MvgpHyper, PriorMean, Rbf};
    use bayes_cbf::systems::{DynSystem, Pendulum};
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![0.8, 1.1], 1.3).unwrap(),
        A: random_spd(2, &mut rng),
        B: random_spd(2, &mut rng),
        sigma: 0.05,
    };
    let prior: std::sync::Arc<dyn DynSystem> = std::sync::Arc::new(Pendulum {
        mass: 2.0,
        length: 1.0,
        gravity: 9.0,
    });
    Mvgp::new(2, 1, hyper, PriorMean::System(prior), InputMap::Identity).unwrap()
}

/// `Φ(c)` of the standard normal, by composite Simpson's rule on the density
/// over `[0, |c|]` (4 000 panels: error below 10⁻¹³ for `|c| ≤ 6`). An
/// implementation independent of the library's `erf⁻¹`.
pub fn normal_cdf(c: f64) -> f64 {
    let phi = |t: f64| (-0.5 * t * t).exp() / (2.0 * std::f64::consts::PI).sqrt();
    let (a, panels) = (c.abs(), 4000);
    let h = a / panels as f64;
    let mut s = phi(0.0) + phi(a);
    for k in 1..panels {
        s += phi(k as f64 * h) * if k % 2 == 1 { 4.0 } else { 2.0 };
    }
    let half = s * h / 3.0;
    if c >= 0.0 {
        0.5 + half
    } else {
        0.5 - half
    }
}

/// `Φ⁻¹(p)` by Newton's method on [`normal_cdf`] (Φ is convex for `c < 0`
/// and concave for `c > 0`, so Newton from 0 converges monotonically).
pub fn normal_quantile(p: f64) -> f64 {
    let mut c: f64 = 0.0;
    for _ in 0..100 {
        let density = (-0.5 * c * c).exp() / (2.0 * std::f64::consts::PI).sqrt();
        let step = (normal_cdf(c) - p) / density;
        c -= step;
        if step.abs() < 1e-14 {
            break;
        }
    }
    c
}

/// Independent `c(p)`: the Gaussian quantile `Φ⁻¹(p)` at relative degree 1
/// (paper, Prop. 2), Cantelli's `√(p/(1−p))` at relative degree ≥ 2
/// (Prop. 4).
pub fn c_reference(p: f64, relative_degree: usize) -> f64 {
    if relative_degree <= 1 {
        normal_quantile(p)
    } else {
        (p / (1.0 - p)).sqrt()
    }
}

/// The largest `q ∈ [lo, hi]` with `best_margin(q) ≥ 0`, by bisection to
/// 1e-7, for a margin that decreases in `q`: the independent reference for
/// `p*` of an infeasible step (with `best_margin` computed on a grid).
pub fn bisect_p_star(best_margin: impl Fn(f64) -> f64, lo: f64, hi: f64) -> f64 {
    let (mut a, mut b) = (lo, hi);
    while b - a > 1e-7 {
        let mid = 0.5 * (a + b);
        if best_margin(mid) >= 0.0 {
            a = mid;
        } else {
            b = mid;
        }
    }
    a
}

/// `k(z, z') = (1 + z·z')²`, a kernel that is not stationary: its gradient
/// at `z' = z` is not zero, so the prior covariance of `F` and `∂F/∂x` is
/// not either (for the RBF it is).
#[derive(Debug, Clone, PartialEq)]
pub struct Quadratic2(pub usize);

impl bayes_cbf::gp::Kernel for Quadratic2 {
    fn input_dim(&self) -> usize {
        self.0
    }
    /// A polynomial: its differences of order 3 and above vanish at any step.
    fn shortest_scale(&self) -> f64 {
        f64::INFINITY
    }
    fn value(&self, x: &[f64], y: &[f64]) -> f64 {
        let s = 1.0 + x.iter().zip(y).map(|(a, b)| a * b).sum::<f64>();
        s * s
    }
    fn grad_x(&self, x: &[f64], y: &[f64], out: &mut [f64]) -> f64 {
        let s = 1.0 + x.iter().zip(y).map(|(a, b)| a * b).sum::<f64>();
        for (o, b) in out.iter_mut().zip(y) {
            *o = 2.0 * s * b;
        }
        s * s
    }
    fn hess_xy(&self, x: &[f64], y: &[f64], out: &mut [f64]) -> f64 {
        let d = self.0;
        let s = 1.0 + x.iter().zip(y).map(|(a, b)| a * b).sum::<f64>();
        for i in 0..d {
            for j in 0..d {
                out[i * d + j] = 2.0 * (x[j] * y[i] + if i == j { s } else { 0.0 });
            }
        }
        s * s
    }
    fn hess_xx(&self, x: &[f64], y: &[f64], out: &mut [f64]) -> f64 {
        let d = self.0;
        for i in 0..d {
            for j in 0..d {
                out[i * d + j] = 2.0 * y[i] * y[j];
            }
        }
        self.value(x, y)
    }
    fn n_hyper(&self) -> usize {
        0
    }
    fn log_hyper(&self) -> Vec<f64> {
        Vec::new()
    }
    fn set_log_hyper(&mut self, _theta: &[f64]) -> Result<(), bayes_cbf::error::InputError> {
        Ok(())
    }
    fn grad_log_hyper(&self, x: &[f64], y: &[f64], _out: &mut [f64]) -> f64 {
        self.value(x, y)
    }
}

/// The joint Gaussian of `vec F` at the points `pts`, built entry by entry:
/// the brute-force reference for the Kronecker shortcuts. Mean: the prior
/// means `vec M0(x_i)` stacked; covariance: `block · k(x_i, x_j)`, with
/// `block` the covariance of one point's `vec F` (`B ⊗ A` for the MVGP,
/// `Σ` for the CoGP) and `k` the kernel on the points as given.
pub fn joint_prior(
    pts: &[Vec<f64>],
    block: &DMatrix<f64>,
    k: impl Fn(&[f64], &[f64]) -> f64,
    prior: &bayes_cbf::gp::PriorMean,
) -> (nalgebra::DVector<f64>, DMatrix<f64>) {
    let (tot, np) = (pts.len(), block.nrows());
    let mut cov = DMatrix::zeros(tot * np, tot * np);
    let mut mean = nalgebra::DVector::zeros(tot * np);
    let mut m0 = vec![0.0; np];
    for i in 0..tot {
        for j in 0..tot {
            cov.view_mut((i * np, j * np), (np, np))
                .copy_from(&(block * k(&pts[i], &pts[j])));
        }
        prior.eval(&pts[i], &mut m0);
        mean.rows_mut(i * np, np).copy_from_slice(&m0);
    }
    (mean, cov)
}

/// `(mean, cov)` of a Gaussian conditioned on `y = H x + w`, `w ~ N(0,
/// noise)` (each observation's block `noise` on the diagonal, `H` with
/// `noise.nrows()` rows per observation), by a dense Cholesky factor:
/// the posterior mean, the posterior covariance and `log p(y)`.
pub fn condition(
    (mean, cov): (&nalgebra::DVector<f64>, &DMatrix<f64>),
    h: &DMatrix<f64>,
    noise: &DMatrix<f64>,
    y: &nalgebra::DVector<f64>,
) -> (nalgebra::DVector<f64>, DMatrix<f64>, f64) {
    let r = noise.nrows();
    let mut cov_y = h * cov * h.transpose();
    for j in 0..h.nrows() / r {
        let mut blk = cov_y.view_mut((j * r, j * r), (r, r));
        blk += noise;
    }
    let cov_xy = cov * h.transpose();
    let resid = y - h * mean;
    let chol = cov_y.cholesky().expect("joint covariance is PD");
    let post_mean = mean + &cov_xy * chol.solve(&resid);
    let post_cov = cov - &cov_xy * chol.solve(&cov_xy.transpose());
    let logdet = 2.0 * chol.l().diagonal().iter().map(|v| v.ln()).sum::<f64>();
    let ll = -0.5
        * (resid.dot(&chol.solve(&resid))
            + logdet
            + h.nrows() as f64 * (2.0 * std::f64::consts::PI).ln());
    (post_mean, post_cov, ll)
}

/// The map `H` from `vec F` at `tot` points to the `n`-vectors
/// `F(x_j) u̲_j` of the first `us.len() / m` of them (`u̲_j = [1, u_j]`,
/// `u_j` the `m` controls of row `j` of `us`), so that `y = H vec F + w`.
pub fn observation_map(us: &[f64], m: usize, n: usize, tot: usize) -> DMatrix<f64> {
    let (k, np) = (us.len() / m, n * (m + 1));
    let mut h = DMatrix::zeros(k * n, tot * np);
    for j in 0..k {
        let mut ub = vec![1.0];
        ub.extend_from_slice(&us[j * m..(j + 1) * m]);
        h.view_mut((j * n, j * np), (n, np))
            .copy_from(&selection(&ub, n));
    }
    h
}

/// Point `i`'s posterior from [`condition`]'s mean and covariance over all
/// the points: the mean as the `n × p` matrix `M` and the `np × np`
/// covariance of `vec F(x_i)`.
pub fn point_block(
    mean: &nalgebra::DVector<f64>,
    cov: &DMatrix<f64>,
    i: usize,
    n: usize,
    p: usize,
) -> (DMatrix<f64>, DMatrix<f64>) {
    let np = n * p;
    let off = i * np;
    (
        DMatrix::from_column_slice(n, p, mean.rows(off, np).as_slice()),
        cov.view((off, off), (np, np)).into_owned(),
    )
}
