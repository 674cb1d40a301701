#![allow(clippy::too_many_arguments, clippy::approx_constant)]
//! Barrier-condition moments against Monte Carlo over joint posterior
//! samples, and the joint posterior of `F` and its Jacobian against finite
//! differences of the (brute-force-validated) posterior.

mod common;

use bayes_cbf::barrier::{
    add_observation_noise, cbc_moments, clc_moments, AckermannClf, Barrier, ConditionMoments,
    DynBarrier, DynLyapunov, Lyapunov, MomentWorkspace, PendulumSector,
};
use bayes_cbf::gp::{InputMap, Kernel, Mvgp, MvgpHyper, PriorMean, Rbf};
use bayes_cbf::systems::{Ackermann, DynSystem, Pendulum};
use common::{random_spd, Quadratic2};
use nalgebra::{DMatrix, DVector};
use num_dual::DualNum;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use std::sync::Arc;

/// `h(x) = xᵀQx + bᵀx + c`.
struct Quadratic {
    q: DMatrix<f64>,
    b: Vec<f64>,
    c: f64,
    r: usize,
    gains: Vec<f64>,
}

impl Barrier for Quadratic {
    fn state_dim(&self) -> usize {
        self.b.len()
    }
    fn h<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D]) -> D {
        let n = self.b.len();
        let mut s = D::from(self.c);
        for i in 0..n {
            s += x[i] * self.b[i];
            for j in 0..n {
                s += x[i] * x[j] * self.q[(i, j)];
            }
        }
        s
    }
    fn relative_degree(&self) -> usize {
        self.r
    }
    fn gains(&self) -> &[f64] {
        &self.gains
    }
}

/// `∇f(x)` by central differences of step `h`.
fn central_gradient(f: impl Fn(&[f64]) -> f64, x: &[f64], h: f64) -> Vec<f64> {
    (0..x.len())
        .map(|i| {
            let (mut a, mut b) = (x.to_vec(), x.to_vec());
            a[i] += h;
            b[i] -= h;
            (f(&a) - f(&b)) / (2.0 * h)
        })
        .collect()
}

fn model(n: usize, m: usize, prior: PriorMean, k: usize, seed: u64) -> Mvgp {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![1.2; n], 1.0).unwrap(),
        A: random_spd(n, &mut rng) * 0.5,
        B: random_spd(m + 1, &mut rng),
        sigma: 0.3,
    };
    let mut model = Mvgp::new(n, m, hyper, prior, InputMap::Identity).unwrap();
    let xs: Vec<f64> = (0..k * n).map(|_| rng.random_range(-1.5..1.5)).collect();
    let us: Vec<f64> = (0..k * m).map(|_| rng.random_range(-1.0..1.0)).collect();
    let xd: Vec<f64> = (0..k * n).map(|_| rng.random_range(-1.0..1.0)).collect();
    model.set_data(&xs, &us, &xd).unwrap();
    model
}

/// Samples `vec 𝔽 ~ N(vec 𝕄, Ĉ ⊗ A)`; calls `f(𝔽)` per sample and
/// returns the sample mean, variance and the standard errors of both.
fn monte_carlo(
    model: &Mvgp,
    x: &[f64],
    samples: usize,
    seed: u64,
    mut f: impl FnMut(&DMatrix<f64>) -> f64,
) -> (f64, f64, f64, f64) {
    let joint = model.joint_posterior(x).unwrap();
    let n = model.state_dim();
    let pp = joint.c.ncols();
    let cov = joint.c.kronecker(&model.hyper().A);
    let dim = cov.nrows();
    let l = (cov + DMatrix::identity(dim, dim) * 1e-12)
        .cholesky()
        .expect("joint covariance PSD")
        .l();
    let mu = DVector::from_column_slice(joint.mean.as_slice());
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let vals: Vec<f64> = (0..samples)
        .map(|_| {
            let z = DVector::from_fn(dim, |_, _| StandardNormal.sample(&mut rng));
            let v = &mu + &l * z;
            f(&DMatrix::from_column_slice(n, pp, v.as_slice()))
        })
        .collect();
    let nn = samples as f64;
    let mean = vals.iter().sum::<f64>() / nn;
    let var = vals.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (nn - 1.0);
    let m4 = vals.iter().map(|v| (v - mean).powi(4)).sum::<f64>() / nn;
    (
        mean,
        var,
        (var / nn).sqrt(),
        ((m4 - var * var).max(0.0) / nn).sqrt(),
    )
}

fn grad_hess(b: &dyn DynBarrier, x: &[f64]) -> (f64, Vec<f64>, DMatrix<f64>) {
    let n = x.len();
    let mut g = vec![0.0; n];
    let mut h = vec![0.0; n * n];
    let mut s = vec![num_dual::HyperDual64::from(0.0); n];
    let v = b.hessian(x, &mut g, &mut h, &mut s);
    (v, g, DMatrix::from_row_slice(n, n, &h))
}

/// CBC of relative degree `r` evaluated directly from one sample of 𝔽.
fn cbc_direct(
    big_f: &DMatrix<f64>,
    n: usize,
    p: usize,
    h: f64,
    g: &[f64],
    hess: &DMatrix<f64>,
    gains: &[f64],
    r: usize,
    u: &[f64],
) -> f64 {
    let ub: Vec<f64> = std::iter::once(1.0).chain(u.iter().cloned()).collect();
    let fu: Vec<f64> = (0..n)
        .map(|i| (0..p).map(|c| big_f[(i, c)] * ub[c]).sum())
        .collect();
    let gv = DVector::from_column_slice(g);
    if r == 1 {
        return gv.dot(&DVector::from_vec(fu)) + gains[0] * h;
    }
    let f = DVector::from_fn(n, |i, _| big_f[(i, 0)]);
    let jf = DMatrix::from_fn(n, n, |l, i| big_f[(l, (i + 1) * p)]); // ∂f_l/∂x_i
    let grad_lfh = hess * &f + jf.transpose() * &gv;
    grad_lfh.dot(&DVector::from_vec(fu)) + gains[0] * h + gains[1] * gv.dot(&f)
}

fn check_against_mc(model: &Mvgp, barrier: &dyn DynBarrier, x: &[f64], u: &[f64], seed: u64) {
    let (n, p) = (model.state_dim(), model.control_dim() + 1);
    let r = barrier.relative_degree();
    let mut ws = MomentWorkspace::new(model);
    ws.update(model, x, r).unwrap();
    let mut out = ConditionMoments::zeros(model.control_dim());
    cbc_moments(&mut ws, barrier, &mut out).unwrap();
    let (h, g, hess) = grad_hess(barrier, x);
    assert!((out.value - h).abs() < 1e-12);
    let gains = barrier.gains().to_vec();
    let (mc_mean, mc_var, se_mean, se_var) = monte_carlo(model, x, 100_000, seed, |bf| {
        cbc_direct(bf, n, p, h, &g, &hess, &gains, r, u)
    });
    let (em, ev) = (out.mean(u), out.variance(u));
    assert!(
        (em - mc_mean).abs() < 4.0 * se_mean,
        "r={r} mean exact {em} MC {mc_mean} ± {se_mean}"
    );
    assert!(
        (ev - mc_var).abs() < 4.0 * se_var,
        "r={r} variance exact {ev} MC {mc_var} ± {se_var}"
    );
    // the factor reproduces the covariance
    let vtv = out.v.transpose() * &out.v;
    assert!((vtv - &out.cov).abs().max() < 1e-9 * out.cov.abs().max().max(1.0));
}

#[test]
fn pendulum_sector_moments_match_monte_carlo() {
    let truth: Arc<dyn DynSystem> = Arc::new(Pendulum {
        mass: 1.3,
        length: 0.9,
        gravity: 10.0,
    });
    for (i, prior) in [PriorMean::Zero, PriorMean::System(truth)]
        .into_iter()
        .enumerate()
    {
        let m = model(2, 1, prior, 12, 10 + i as u64);
        let rd2 = PendulumSector::new(0.7854, 0.3927, 2, vec![1.0, 3.0]).unwrap();
        let rd1 = PendulumSector::new(0.7854, 0.3927, 1, vec![2.0]).unwrap();
        for (j, x) in [[1.2, -0.4], [0.1, 0.8]].iter().enumerate() {
            check_against_mc(&m, &rd2, x, &[0.7], 100 + j as u64);
            check_against_mc(&m, &rd1, x, &[-1.1], 200 + j as u64);
        }
    }
}

#[test]
fn random_quadratic_barrier_moments_match_monte_carlo() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    for (n, m) in [(2, 1), (3, 2)] {
        for nonzero in [false, true] {
            let prior = if nonzero {
                PriorMean::System(Arc::new(common::RandomSystem::new(n, m, 7)) as Arc<dyn DynSystem>)
            } else {
                PriorMean::Zero
            };
            let model = model(n, m, prior, 10, 20 + n as u64);
            let qa = DMatrix::from_fn(n, n, |_, _| rng.random_range(-1.0..1.0));
            let b = Quadratic {
                q: &qa + qa.transpose(),
                b: (0..n).map(|_| rng.random_range(-1.0..1.0)).collect(),
                c: 0.3,
                r: 2,
                gains: vec![0.5, 1.5],
            };
            let x: Vec<f64> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
            let u: Vec<f64> = (0..m).map(|_| rng.random_range(-1.0..1.0)).collect();
            check_against_mc(&model, &b, &x, &u, 300 + n as u64);
            let b1 = Quadratic {
                r: 1,
                gains: vec![2.0],
                ..b
            };
            check_against_mc(&model, &b1, &x, &u, 400 + n as u64);
        }
    }
}

#[test]
fn joint_posterior_matches_finite_differences_of_posterior() {
    let prior: Arc<dyn DynSystem> = Arc::new(common::RandomSystem::new(3, 2, 3));
    for map in [
        InputMap::Identity,
        InputMap::Select(vec![2, 0]),
        InputMap::periodic(3, &[2]),
    ] {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let kernel = Rbf::new(vec![1.1; map.output_dim(3)], 1.4).unwrap();
        check_joint_against_finite_differences(kernel, map.clone(), prior.clone(), &mut rng);
        let kernel = Quadratic2(map.output_dim(3));
        check_joint_against_finite_differences(kernel, map, prior.clone(), &mut rng);
    }
}

/// The joint posterior of `F` and `∂F/∂x` at one point against central
/// differences of the posterior mean and cross-covariance, 30 observations.
fn check_joint_against_finite_differences<K: Kernel>(
    kernel: K,
    map: InputMap,
    prior: Arc<dyn DynSystem>,
    rng: &mut ChaCha8Rng,
) {
    let hyper = MvgpHyper {
        kernel,
        A: random_spd(3, rng),
        B: random_spd(3, rng),
        sigma: 0.2,
    };
    let mut model = Mvgp::new(3, 2, hyper, PriorMean::System(prior), map).unwrap();
    let xs: Vec<f64> = (0..30).map(|_| rng.random_range(-1.0..1.0)).collect();
    let us: Vec<f64> = (0..20).map(|_| rng.random_range(-1.0..1.0)).collect();
    let xd: Vec<f64> = (0..30).map(|_| rng.random_range(-1.0..1.0)).collect();
    model.set_data(&xs, &us, &xd).unwrap();
    let x = [0.2, -0.3, 0.5];
    let joint = model.joint_posterior(&x).unwrap();
    let p = 3;
    let h = 1e-4;
    let shift = |i: usize, s: f64| {
        let mut y = x;
        if i > 0 {
            y[i - 1] += s;
        }
        y
    };
    for a in 0..=3 {
        // mean blocks: ∂_a M_k
        let mean_fd = if a == 0 {
            model.posterior_mean(&x).unwrap()
        } else {
            (model.posterior_mean(&shift(a, h)).unwrap()
                - model.posterior_mean(&shift(a, -h)).unwrap())
                / (2.0 * h)
        };
        let blk = joint.mean.columns(a * p, p).into_owned();
        assert!(
            (&blk - &mean_fd).abs().max() < 1e-6,
            "mean block {a}: {blk} vs {mean_fd}"
        );
        for b in 0..=3 {
            let cov = |sa: f64, sb: f64| model.posterior_cov(&shift(a, sa), &shift(b, sb)).unwrap();
            let fd = match (a, b) {
                (0, 0) => cov(0.0, 0.0),
                (_, 0) => (cov(h, 0.0) - cov(-h, 0.0)) / (2.0 * h),
                (0, _) => (cov(0.0, h) - cov(0.0, -h)) / (2.0 * h),
                _ => (cov(h, h) - cov(h, -h) - cov(-h, h) + cov(-h, -h)) / (4.0 * h * h),
            };
            let blk = joint.c.view((a * p, b * p), (p, p)).into_owned();
            let tol = 1e-5 * (1.0 + fd.abs().max());
            assert!(
                (&blk - &fd).abs().max() < tol,
                "cov block ({a},{b}): {blk} vs {fd}"
            );
        }
    }
}

#[test]
fn clf_moments_match_monte_carlo_and_time_derivative() {
    let prior: Arc<dyn DynSystem> = Arc::new(Ackermann { wheelbase: 1.0 });
    let model = model(3, 2, PriorMean::System(prior), 8, 31);
    let clf = AckermannClf::new(0.9, 1.5, 10.0).unwrap();
    let (x, xd, xd_dot) = ([-1.0, -0.5, 0.3], [0.0, 0.2, 0.7], [0.4, -0.2, 0.0]);
    let mut ws = MomentWorkspace::new(&model);
    ws.update(&model, &x, 1).unwrap();
    let mut out = ConditionMoments::zeros(2);
    clc_moments(&mut ws, &clf, &xd, &xd_dot, &mut out).unwrap();
    // V and its derivatives by finite differences
    let v = |x: &[f64], xd: &[f64]| clf.v(x, xd);
    let hh = 1e-6;
    let g = central_gradient(|y| v(y, &xd), &x, hh);
    let xdp: Vec<f64> = (0..3).map(|i| xd[i] + hh * xd_dot[i]).collect();
    let xdm: Vec<f64> = (0..3).map(|i| xd[i] - hh * xd_dot[i]).collect();
    let dvdt = (v(&x, &xdp) - v(&x, &xdm)) / (2.0 * hh);
    let u = [0.5, -0.3];
    let (mc_mean, mc_var, se_m, se_v) = monte_carlo(&model, &x, 100_000, 5, |bf| {
        let fu: Vec<f64> = (0..3)
            .map(|i| bf[(i, 0)] + bf[(i, 1)] * u[0] + bf[(i, 2)] * u[1])
            .collect();
        (0..3).map(|i| g[i] * fu[i]).sum::<f64>() + dvdt + 10.0 * v(&x, &xd)
    });
    assert!(
        (out.mean(&u) - mc_mean).abs() < 4.0 * se_m + 1e-6,
        "{} vs {mc_mean}",
        out.mean(&u)
    );
    assert!(
        (out.variance(&u) - mc_var).abs() < 4.0 * se_v,
        "{} vs {mc_var}",
        out.variance(&u)
    );
}

#[test]
fn autodiff_derivatives_match_finite_differences() {
    let b = bayes_cbf::barrier::CircleHeading::new([-1.1667, -1.5], 0.7906, 0.7, 0.3, 1, vec![5.0])
        .unwrap();
    let x = [-2.4, -0.7, 0.4];
    let (h, g, hess) = grad_hess(&b, &x);
    let f = |y: &[f64]| DynBarrier::value(&b, y);
    assert!((h - f(&x)).abs() < 1e-14);
    let e = 1e-5;
    for i in 0..3 {
        let (mut a, mut c) = (x, x);
        a[i] += e;
        c[i] -= e;
        assert!(
            ((f(&a) - f(&c)) / (2.0 * e) - g[i]).abs() < 1e-7,
            "grad {i}"
        );
        for j in 0..3 {
            let fd = {
                let mut pp = x;
                pp[i] += e;
                pp[j] += e;
                let mut pm = x;
                pm[i] += e;
                pm[j] -= e;
                let mut mp = x;
                mp[i] -= e;
                mp[j] += e;
                let mut mm = x;
                mm[i] -= e;
                mm[j] -= e;
                (f(&pp) - f(&pm) - f(&mp) + f(&mm)) / (4.0 * e * e)
            };
            assert!(
                (fd - hess[(i, j)]).abs() < 1e-4,
                "hess {i}{j}: {fd} vs {}",
                hess[(i, j)]
            );
        }
    }
    // Lyapunov gradient
    let clf = AckermannClf::new(0.9, 1.5, 10.0).unwrap();
    let xd = [0.0, 0.0, 0.7];
    let mut gv = [0.0; 3];
    let mut scratch = vec![num_dual::Dual64::from(0.0); 6];
    clf.gradient(&x, &xd, &[0.0; 3], &mut gv, &mut scratch);
    for i in 0..3 {
        let (mut a, mut c) = (x, x);
        a[i] += e;
        c[i] -= e;
        assert!(((clf.v(&a, &xd) - clf.v(&c, &xd)) / (2.0 * e) - gv[i]).abs() < 1e-7);
    }
}

/// Lemma 4 as printed against the exact variance of `xᵀy` for jointly
/// Gaussian `x`, `y`: the printed `½ tr((Σxy + Σyx)²)` equals
/// `tr(Σxy Σxy) + tr(Σxy Σyx)`, where the exact variance has
/// `tr(Σxy Σxy) + tr(Σxx Σyy)`. Monte Carlo agrees with the exact
/// expression, and the printed one is off by exactly
/// `tr(Σxy Σyx) − tr(Σxx Σyy)`, many standard errors away.
#[test]
#[allow(non_snake_case)]
fn lemma_4_as_printed_swaps_one_trace() {
    let d = 3;
    let mut rng = ChaCha8Rng::seed_from_u64(41);
    let S = random_spd(2 * d, &mut rng);
    let mean: Vec<f64> = (0..2 * d).map(|_| rng.random_range(-1.0..1.0)).collect();
    let block = |r: usize, c: usize| S.view((r * d, c * d), (d, d)).into_owned();
    let (sxx, sxy, syx, syy) = (block(0, 0), block(0, 1), block(1, 0), block(1, 1));
    let xb = DVector::from_column_slice(&mean[..d]);
    let yb = DVector::from_column_slice(&mean[d..]);
    let tr = |a: &DMatrix<f64>, b: &DMatrix<f64>| (a * b).trace();
    let mean_terms = (yb.transpose() * &sxx * &yb)[(0, 0)]
        + (xb.transpose() * &syy * &xb)[(0, 0)]
        + (yb.transpose() * &sxy * &xb)[(0, 0)]
        + (xb.transpose() * &syx * &yb)[(0, 0)];
    let exact = tr(&sxx, &syy) + tr(&sxy, &sxy) + mean_terms;
    let sum = &sxy + &syx;
    let printed = 0.5 * tr(&sum, &sum) + mean_terms;
    let swap = tr(&sxy, &syx) - tr(&sxx, &syy);
    assert!((printed - exact - swap).abs() < 1e-12 * exact.abs());

    let chol = S.clone().cholesky().unwrap();
    let draws = 200_000;
    let products: Vec<f64> = (0..draws)
        .map(|_| {
            let z = DVector::from_fn(2 * d, |_, _| StandardNormal.sample(&mut rng));
            let v = chol.l() * z;
            (0..d)
                .map(|i| (mean[i] + v[i]) * (mean[d + i] + v[d + i]))
                .sum()
        })
        .collect();
    let nf = draws as f64;
    let m = products.iter().sum::<f64>() / nf;
    let var = products.iter().map(|p| (p - m).powi(2)).sum::<f64>() / nf;
    let m4 = products.iter().map(|p| (p - m).powi(4)).sum::<f64>() / nf;
    // standard error of the sample variance: √((μ₄ − σ⁴)/N)
    let se = ((m4 - var * var) / nf).sqrt();
    assert!(
        (var - exact).abs() < 4.0 * se,
        "MC {var} exact {exact} ± {se}"
    );
    assert!(
        (var - printed).abs() > 10.0 * se,
        "MC {var} printed {printed} ± {se}: the swap {swap} is not visible"
    );
}

/// `ConditionMoments::from_parts` validates what it is given: `e` with at
/// least two entries, a square `cov` of the same size, finite, symmetric
/// within `10⁻⁹ max(s, 1)` and with no eigenvalue below `−10⁻⁹ s` (`s`
/// the largest absolute eigenvalue, so the tolerances scale with `cov`),
/// and a relative degree of at least 1; the factor satisfies `vᵀv = cov`.
#[test]
fn condition_moments_from_parts_validates_its_parts() {
    let m = |s: f64, rows: &[f64]| DMatrix::from_row_slice(3, 3, rows) * s;
    let e = vec![0.5, 1.0, -2.0];
    let field = |r: Result<ConditionMoments, bayes_cbf::InputError>| r.unwrap_err().to_string();
    // a rank-one covariance (zero eigenvalues) and one at scale 10⁴ with an
    // eigenvalue of −10⁻⁸, inside −10⁻⁹ · 10⁴: accepted
    let c = DVector::from_vec(vec![1.0, -0.5, 2.0]);
    let near_psd = m(1e4, &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1e-12]);
    for cov in [&c * c.transpose(), near_psd] {
        let mom = ConditionMoments::from_parts(e.clone(), cov.clone(), 2).unwrap();
        assert!((mom.v.transpose() * &mom.v - &cov).abs().max() < 1e-9 * cov.abs().max());
        assert_eq!((mom.e, mom.relative_degree), (e.clone(), 2));
    }
    // an eigenvalue of −10⁻⁶ at scale 1, and an asymmetry beyond the
    // tolerance at scale 10⁴: rejected
    let indefinite = m(1.0, &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1e-6]);
    let asymmetric = m(1e4, &[1.0, 2e-9, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
    for cov in [indefinite, asymmetric] {
        let err = field(ConditionMoments::from_parts(e.clone(), cov, 1));
        assert!(err.contains("cov") && err.contains("semidefinite"), "{err}");
    }
    // within the symmetry tolerance: accepted
    let nearly = m(1e4, &[1.0, 5e-14, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
    assert!(ConditionMoments::from_parts(e.clone(), nearly, 1).is_ok());
    let id = || DMatrix::identity(3, 3);
    assert!(field(ConditionMoments::from_parts(
        vec![1.0],
        DMatrix::identity(1, 1),
        1
    ))
    .contains('e'));
    assert!(ConditionMoments::from_parts(vec![1.0, 2.0], DMatrix::identity(2, 2), 1).is_ok());
    assert!(field(ConditionMoments::from_parts(
        e.clone(),
        DMatrix::identity(2, 2),
        1
    ))
    .contains("cov"));
    assert!(field(ConditionMoments::from_parts(
        vec![f64::NAN, 0.0, 0.0],
        id(),
        1
    ))
    .contains('e'));
    assert!(field(ConditionMoments::from_parts(e.clone(), id(), 0)).contains("relative_degree"));
}

/// Misuse of the moment functions is an error naming what is wrong: a
/// barrier of another state dimension, a relative-degree-2 barrier on a
/// workspace prepared for degree 1, a CLF reference of the wrong length
/// (either of `x_d` and `ẋ_d`).
#[test]
fn moment_functions_reject_misuse() {
    let m2 = model(2, 1, PriorMean::Zero, 6, 41);
    let mut ws = MomentWorkspace::new(&m2);
    ws.update(&m2, &[0.3, -0.2], 1).unwrap();
    let mut out = ConditionMoments::zeros(1);
    let rd2 = PendulumSector::new(0.7854, 0.3927, 2, vec![1.0, 3.0]).unwrap();
    let err = cbc_moments(&mut ws, &rd2, &mut out)
        .unwrap_err()
        .to_string();
    assert!(err.contains("relative_degree"), "{err}");
    let rd1 = PendulumSector::new(0.7854, 0.3927, 1, vec![2.0]).unwrap();
    assert!(cbc_moments(&mut ws, &rd1, &mut out).is_ok());
    let wide = bayes_cbf::barrier::HalfSpace::new(vec![1.0, 0.0, 0.0], 0.5, 1, vec![1.0]).unwrap();
    let err = cbc_moments(&mut ws, &wide, &mut out)
        .unwrap_err()
        .to_string();
    assert!(err.contains("barrier state dimension"), "{err}");

    let m3 = model(3, 2, PriorMean::Zero, 6, 42);
    let mut ws = MomentWorkspace::new(&m3);
    ws.update(&m3, &[-1.0, -0.5, 0.3], 1).unwrap();
    let clf = AckermannClf::new(0.9, 1.5, 10.0).unwrap();
    let mut out = ConditionMoments::zeros(2);
    let (good, short) = ([0.0, 0.2, 0.7], [0.0, 0.2]);
    assert!(clc_moments(&mut ws, &clf, &good, &good, &mut out).is_ok());
    for (xd, xd_dot) in [(&good[..], &short[..]), (&short[..], &good[..])] {
        let err = clc_moments(&mut ws, &clf, xd, xd_dot, &mut out)
            .unwrap_err()
            .to_string();
        assert!(err.contains("reference"), "{err}");
    }
}

/// `c(p)` is defined on the open interval `0 < p < 1`: both ends and
/// anything outside are errors naming the probability.
#[test]
fn quantile_factor_needs_a_probability_strictly_between_0_and_1() {
    use bayes_cbf::barrier::quantile_factor;
    for r in [1, 2] {
        for p in [0.0, 1.0, -0.1, 1.1, f64::NAN, f64::INFINITY] {
            let err = quantile_factor(p, r).unwrap_err().to_string();
            assert!(err.contains("probability"), "p = {p}: {err}");
        }
    }
    assert_eq!(quantile_factor(0.5, 1).unwrap(), 0.0);
    assert_eq!(quantile_factor(0.5, 2).unwrap(), 1.0);
}

/// `unmodelled_lgh_std` is `√(∇hᵀ A ∇h · max_{c ≥ 1} B_k,cc)`, recomputed
/// here from central differences of `h`, the model's `A` and the
/// posterior's `B_k` at the same state.
#[test]
fn unmodelled_lgh_std_matches_its_formula() {
    let model = model(2, 1, PriorMean::Zero, 6, 43);
    let x = [0.9, -0.4];
    let mut ws = MomentWorkspace::new(&model);
    ws.update(&model, &x, 2).unwrap();
    let rd2 = PendulumSector::new(0.7854, 0.3927, 2, vec![1.0, 3.0]).unwrap();
    cbc_moments(&mut ws, &rd2, &mut ConditionMoments::zeros(1)).unwrap();
    let h = 1e-6;
    let g = DVector::from_vec(central_gradient(|y| DynBarrier::value(&rd2, y), &x, h));
    let q = (g.transpose() * &model.hyper().A * &g)[(0, 0)];
    let b = model.posterior(&x).unwrap().B[(1, 1)];
    let want = (q * b).sqrt();
    let got = bayes_cbf::barrier::unmodelled_lgh_std(&ws);
    assert!(want > 1e-3, "{want}");
    assert!((got - want).abs() < 1e-6 * want, "{got} vs {want}");
}

/// The predictive moments against Monte Carlo of the realised condition,
/// `F u̲` replaced by `F u̲ + ε` with `F` (and its Jacobian) drawn from the
/// joint posterior and `ε ~ N(0, σ² A)` drawn independently: at relative
/// degree 1 `∇hᵀ(F u̲ + ε) + α h`, at relative degree 2
/// `∇(L_f h)ᵀ(F u̲ + ε) + k₀ h + k₁ L_f h`; and the error for relative
/// degree 3.
#[test]
fn predictive_moments_match_monte_carlo_of_the_realised_condition() {
    for (seed, (n, m)) in [(2usize, 1usize), (3, 2)].into_iter().enumerate() {
        let model = model(n, m, PriorMean::Zero, 9, 40 + seed as u64);
        let mut rng = ChaCha8Rng::seed_from_u64(50 + seed as u64);
        let qa = DMatrix::from_fn(n, n, |_, _| rng.random_range(-1.0..1.0));
        let x: Vec<f64> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
        let u: Vec<f64> = (0..m).map(|_| rng.random_range(-1.0..1.0)).collect();
        let hyper = model.hyper();
        let noise = (&hyper.A * hyper.sigma.powi(2)).cholesky().unwrap().l();
        for (r, gains) in [(1usize, vec![2.0]), (2, vec![0.5, 1.5])] {
            let b = Quadratic {
                q: &qa + qa.transpose(),
                b: (0..n).map(|_| rng.random_range(-1.0..1.0)).collect(),
                c: 0.3,
                r,
                gains: gains.clone(),
            };
            let mut ws = MomentWorkspace::new(&model);
            ws.update(&model, &x, r).unwrap();
            let mut latent = ConditionMoments::zeros(m);
            cbc_moments(&mut ws, &b, &mut latent).unwrap();
            let mut out = latent.clone();
            add_observation_noise(&ws, &mut out).unwrap();
            // a constant added to the variance, the mean unchanged
            let added = out.variance(&u) - latent.variance(&u);
            assert!(added > 1e-3, "{added}");
            assert_eq!(out.mean(&u), latent.mean(&u));
            let v0: Vec<f64> = (0..m).map(|i| i as f64 - 0.5).collect();
            let added0 = out.variance(&v0) - latent.variance(&v0);
            assert!((added0 - added).abs() < 1e-10 * added, "{added0} {added}");
            if r == 1 {
                let (_, g, _) = grad_hess(&b, &x);
                let gv = DVector::from_column_slice(&g);
                let want = hyper.sigma.powi(2) * gv.dot(&(&hyper.A * &gv));
                assert!((added - want).abs() < 1e-10 * want, "{added} {want}");
            }
            let vtv = out.v.transpose() * &out.v;
            assert!((vtv - &out.cov).abs().max() < 1e-9 * out.cov.abs().max());
            // Monte Carlo of the realised condition
            let (h, g, hess) = grad_hess(&b, &x);
            let gv = DVector::from_column_slice(&g);
            let p = m + 1;
            let mut nrng = ChaCha8Rng::seed_from_u64(60 + seed as u64);
            let (mc_mean, mc_var, se_mean, se_var) = monte_carlo(&model, &x, 100_000, 70, |bf| {
                let eps = &noise * DVector::from_fn(n, |_, _| StandardNormal.sample(&mut nrng));
                let latent_c = cbc_direct(bf, n, p, h, &g, &hess, &gains, r, &u);
                // the rate that ε disturbs: ∇h, or ∇(L_f h) = ∇²h f + J_fᵀ∇h
                let a = if r == 1 {
                    gv.clone()
                } else {
                    let f = DVector::from_fn(n, |i, _| bf[(i, 0)]);
                    let jf = DMatrix::from_fn(n, n, |l, i| bf[(l, (i + 1) * p)]);
                    &hess * &f + jf.transpose() * &gv
                };
                latent_c + a.dot(&eps)
            });
            assert!(
                (out.mean(&u) - mc_mean).abs() < 4.0 * se_mean,
                "r = {r}: {mc_mean}"
            );
            assert!(
                (out.variance(&u) - mc_var).abs() < 4.0 * se_var,
                "r = {r}: {} against {mc_var} ± {se_var}",
                out.variance(&u)
            );
        }
    }
    let model = model(2, 1, PriorMean::Zero, 5, 80);
    let mut ws = MomentWorkspace::new(&model);
    ws.update(&model, &[0.3, 0.1], 2).unwrap();
    let mut out = ConditionMoments::zeros(1);
    out.relative_degree = 3;
    let e = add_observation_noise(&ws, &mut out).unwrap_err();
    assert!(e.to_string().contains("relative_degree"), "{e}");
}

/// `Cov = a v vᵀ + diag(0.004, 0)` with `v = (1, −2)` orthogonal to
/// `u̲ = (1, 0.5)`: the variance at `u = 0.5` is 0.004 whatever `a`. At
/// `a = 1` it is resolved (to 1e-12); at `a = 10¹³` the terms of `u̲ᵀ Cov
/// u̲` are 10¹³ and their rounding could be 10⁻³, a fourth of the
/// result: `variance_resolved` says so instead of giving a number. At
/// `a = 10¹⁵`, where 0.004 is below an ulp of the terms, `variance` gives
/// 0.
#[test]
fn a_variance_below_the_rounding_of_its_terms_is_unresolved() {
    use bayes_cbf::ControlError;
    let at = |a: f64| {
        let cov = DMatrix::from_row_slice(2, 2, &[a + 0.004, -2.0 * a, -2.0 * a, 4.0 * a]);
        ConditionMoments::from_parts(vec![0.17, -0.11], cov, 1).unwrap()
    };
    let v = at(1.0).variance_resolved(&[0.5]).unwrap();
    assert!((v - 0.004).abs() < 1e-12, "{v}");
    for a in [1e13, 1e15] {
        let mom = at(a);
        let e = mom.variance_resolved(&[0.5]).unwrap_err();
        assert!(matches!(e, ControlError::VarianceUnresolved { .. }), "{e}");
        assert!(e.to_string().contains("not resolved"), "{e}");
    }
    // what the unchecked sum gives where 0.004 is below an ulp of 10¹⁵
    assert_eq!(at(1e15).variance(&[0.5]), 0.0);
    // where the rounding cannot hide a standard deviation that matters,
    // a variance of 0 is 0 (a deterministic condition)
    let exact = ConditionMoments::from_parts(vec![0.17, -0.11], DMatrix::zeros(2, 2), 1).unwrap();
    assert_eq!(exact.variance_resolved(&[0.5]).unwrap(), 0.0);
}
