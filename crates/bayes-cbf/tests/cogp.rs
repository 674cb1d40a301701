//! The coregionalization GP (paper, Appendix): posterior against a
//! brute-force construction of the full joint Gaussian of
//! `[vec Ẋ; vec F(x*); vec F(x**)]` conditioned directly; equality with the
//! MVGP when `Σ = B ⊗ A`, `S = σ² A`; the analytic likelihood gradient
//! against finite differences; and learning on simulated pendulum data.

mod common;

use bayes_cbf::gp::{
    fit_cogp, Cogp, CogpFitSettings, CogpHyper, DynamicsModel, InputMap, Kernel, ModelFitSettings,
    Mvgp, MvgpHyper, PriorMean, Rank, Rbf,
};
use bayes_cbf::sim::sample_uniform;
use bayes_cbf::systems::{DynSystem, Pendulum};
use bayes_cbf::{Error, InputError};
use common::{
    condition, joint_prior, observation_map, point_block, random_rbf, random_spd, rel_diff,
    RandomSystem,
};
use nalgebra::{DMatrix, DVector};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::sync::Arc;

struct Problem {
    xs: Vec<f64>,
    us: Vec<f64>,
    xdot: Vec<f64>,
    kernel: Rbf,
}

fn random_problem(n: usize, m: usize, k: usize, d: usize, rng: &mut ChaCha8Rng) -> Problem {
    Problem {
        kernel: random_rbf(d, 0.5..1.5, rng),
        xs: (0..k * n).map(|_| rng.random_range(-1.5..1.5)).collect(),
        us: (0..k * m).map(|_| rng.random_range(-2.0..2.0)).collect(),
        xdot: (0..k * n).map(|_| rng.random_range(-2.0..2.0)).collect(),
    }
}

#[allow(non_snake_case)]
fn check_case(n: usize, m: usize, k: usize, prior: PriorMean, input_map: InputMap, seed: u64) {
    let (p, np) = (m + 1, n * (m + 1));
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let d = input_map.output_dim(n);
    let pr = random_problem(n, m, k, d, &mut rng);
    let (Sigma, S) = (random_spd(np, &mut rng), random_spd(n, &mut rng) * 0.2);
    let tests: Vec<Vec<f64>> = (0..2)
        .map(|_| (0..n).map(|_| rng.random_range(-1.5..1.5)).collect())
        .collect();
    let hyper = CogpHyper {
        kernel: pr.kernel.clone(),
        Sigma: Sigma.clone(),
        S: S.clone(),
    };
    let mut model = Cogp::new(n, m, hyper, prior.clone(), input_map.clone()).unwrap();
    model.set_data(&pr.xs, &pr.us, &pr.xdot).unwrap();
    assert_eq!(model.len(), k);

    // brute force over all k + 2 points
    let pts: Vec<Vec<f64>> = (0..k)
        .map(|j| pr.xs[j * n..(j + 1) * n].to_vec())
        .chain(tests.iter().cloned())
        .collect();
    let z = |x: &[f64]| {
        let mut zz = vec![0.0; d];
        input_map.apply(x, &mut zz);
        zz
    };
    let joint = joint_prior(&pts, &Sigma, |a, b| pr.kernel.value(&z(a), &z(b)), &prior);
    let h = observation_map(&pr.us, m, n, k + 2);
    let y = DVector::from_column_slice(&pr.xdot);
    let (post_mean, post_cov, ll_bf) = condition((&joint.0, &joint.1), &h, &S, &y);

    for (t, x) in tests.iter().enumerate() {
        let post = model.posterior(x).unwrap();
        let (mean_bf, cov_bf) = point_block(&post_mean, &post_cov, k + t, n, p);
        let tag = format!("n={n} m={m} {prior:?}");
        assert!(rel_diff(&post.mean, &mean_bf) < 1e-9, "mean {tag}");
        assert!(rel_diff(&post.cov, &cov_bf) < 1e-9, "cov {tag}");
        let mean_only = model.posterior_mean(x).unwrap();
        assert!(
            rel_diff(&mean_only, &mean_bf) < 1e-9,
            "posterior_mean {tag}"
        );
    }
    let cross = model.posterior_cov(&tests[0], &tests[1]).unwrap();
    let cross_bf = post_cov.view((k * np, (k + 1) * np), (np, np)).into_owned();
    assert!(rel_diff(&cross, &cross_bf) < 1e-9, "cross cov n={n} m={m}");
    let ll = model.log_marginal_likelihood();
    assert!(
        (ll - ll_bf).abs() < 1e-9 * (1.0 + ll_bf.abs()),
        "log likelihood {ll} vs {ll_bf}"
    );
}

#[test]
fn posterior_matches_brute_force_joint_gaussian() {
    common::for_each_posterior_case(|n, m, prior, seed| {
        check_case(n, m, 7, prior, InputMap::Identity, seed)
    });
}

#[test]
fn posterior_with_input_map_matches_brute_force() {
    let sys: Arc<dyn DynSystem> = Arc::new(bayes_cbf::systems::Ackermann { wheelbase: 2.0 });
    check_case(
        3,
        2,
        6,
        PriorMean::System(sys),
        InputMap::Select(vec![2]),
        42,
    );
    check_case(3, 1, 5, PriorMean::Zero, InputMap::Select(vec![0, 2]), 43);
}

/// With `Σ = B ⊗ A` and `S = σ² A` the CoGP is the MVGP.
#[test]
#[allow(non_snake_case)]
fn kronecker_cogp_equals_mvgp() {
    let mut seed = 200;
    for (n, m) in [(1, 1), (2, 1), (2, 2), (3, 2)] {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        seed += 1;
        let pr = random_problem(n, m, 9, n, &mut rng);
        let (A, B) = (random_spd(n, &mut rng), random_spd(m + 1, &mut rng));
        let sigma = rng.random_range(0.1..0.5);
        let prior = PriorMean::System(Arc::new(RandomSystem::new(n, m, seed)));
        let mut mvgp = Mvgp::new(
            n,
            m,
            MvgpHyper {
                kernel: pr.kernel.clone(),
                A: A.clone(),
                B: B.clone(),
                sigma,
            },
            prior.clone(),
            InputMap::Identity,
        )
        .unwrap();
        let mut cogp = Cogp::new(
            n,
            m,
            CogpHyper {
                kernel: pr.kernel.clone(),
                Sigma: B.kronecker(&A),
                S: &A * (sigma * sigma),
            },
            prior,
            InputMap::Identity,
        )
        .unwrap();
        mvgp.set_data(&pr.xs, &pr.us, &pr.xdot).unwrap();
        cogp.set_data(&pr.xs, &pr.us, &pr.xdot).unwrap();
        for _ in 0..3 {
            let x: Vec<f64> = (0..n).map(|_| rng.random_range(-2.0..2.0)).collect();
            let x2: Vec<f64> = (0..n).map(|_| rng.random_range(-2.0..2.0)).collect();
            let (mm, mc) = DynamicsModel::posterior_vec(&mvgp, &x).unwrap();
            let (cm, cc) = DynamicsModel::posterior_vec(&cogp, &x).unwrap();
            assert!(rel_diff(&cm, &mm) < 1e-9, "mean n={n} m={m}");
            assert!(rel_diff(&cc, &mc) < 1e-9, "cov n={n} m={m}");
            let cross_m = mvgp.posterior_cov(&x, &x2).unwrap().kronecker(&A);
            let cross_c = cogp.posterior_cov(&x, &x2).unwrap();
            assert!(rel_diff(&cross_c, &cross_m) < 1e-9, "cross n={n} m={m}");
        }
        let (lm, lc) = (
            mvgp.log_marginal_likelihood(),
            cogp.log_marginal_likelihood(),
        );
        assert!((lm - lc).abs() < 1e-9 * (1.0 + lm.abs()), "{lm} vs {lc}");
    }
}

/// `∂ log p/∂Σ`, `∂ log p/∂S` and `∂ log p/∂ log θ` against central finite
/// differences (symmetric perturbations of `Σ` and `S`).
#[test]
#[allow(non_snake_case)]
fn likelihood_gradient_matches_finite_differences() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    for (n, m) in [(1, 1), (2, 1), (2, 2)] {
        let np = n * (m + 1);
        let pr = random_problem(n, m, 8, n, &mut rng);
        let prior = PriorMean::System(Arc::new(RandomSystem::new(n, m, 3)));
        let hyper = CogpHyper {
            kernel: pr.kernel.clone(),
            Sigma: random_spd(np, &mut rng),
            S: random_spd(n, &mut rng) * 0.3,
        };
        let ll_at = |h: CogpHyper| {
            let mut c = Cogp::new(n, m, h, prior.clone(), InputMap::Identity).unwrap();
            c.set_data(&pr.xs, &pr.us, &pr.xdot).unwrap();
            c.log_marginal_likelihood()
        };
        let mut model = Cogp::new(n, m, hyper.clone(), prior.clone(), InputMap::Identity).unwrap();
        model.set_data(&pr.xs, &pr.us, &pr.xdot).unwrap();
        let g = model.log_marginal_likelihood_gradient().unwrap();
        assert!((g.log_likelihood - model.log_marginal_likelihood()).abs() < 1e-9);
        let eps = 1e-6;
        let close = |fd: f64, an: f64, what: &str| {
            assert!(
                (fd - an).abs() < 1e-6 * (1.0 + fd.abs()),
                "n={n} m={m} {what}: fd {fd} analytic {an}"
            );
        };
        let sym_fd = |mat: &DMatrix<f64>, a: usize, b: usize, is_sigma: bool| {
            let mut e = DMatrix::zeros(mat.nrows(), mat.ncols());
            e[(a, b)] = eps;
            e[(b, a)] = eps;
            let with = |mm: DMatrix<f64>| {
                let mut h = hyper.clone();
                if is_sigma {
                    h.Sigma = mm;
                } else {
                    h.S = mm;
                }
                ll_at(h)
            };
            (with(mat + &e) - with(mat - &e)) / (2.0 * eps)
        };
        // the gradient in a symmetric entry pair (a, b) moves both entries
        for (name, mat, grad, is_sigma) in [
            ("Sigma", &hyper.Sigma, &g.Sigma, true),
            ("S", &hyper.S, &g.S, false),
        ] {
            for a in 0..mat.nrows() {
                for b in 0..=a {
                    let an = if a == b {
                        grad[(a, a)]
                    } else {
                        2.0 * grad[(a, b)]
                    };
                    close(
                        sym_fd(mat, a, b, is_sigma),
                        an,
                        &format!("{name}[{a}][{b}]"),
                    );
                }
            }
        }
        let th = hyper.kernel.log_hyper();
        for i in 0..th.len() {
            let mut kp = hyper.kernel.clone();
            let mut km = hyper.kernel.clone();
            let (mut tp, mut tm) = (th.clone(), th.clone());
            tp[i] += eps;
            tm[i] -= eps;
            kp.set_log_hyper(&tp).unwrap();
            km.set_log_hyper(&tm).unwrap();
            let fd = (ll_at(CogpHyper {
                kernel: kp,
                ..hyper.clone()
            }) - ll_at(CogpHyper {
                kernel: km,
                ..hyper.clone()
            })) / (2.0 * eps);
            close(fd, g.kernel_log_hyper[i], &format!("kernel[{i}]"));
        }
    }
}

#[test]
fn invalid_input_is_rejected_with_field_names() {
    let kernel = Rbf::new(vec![1.0, 1.0], 1.0).unwrap();
    let good = CogpHyper {
        kernel: kernel.clone(),
        Sigma: DMatrix::identity(4, 4),
        S: DMatrix::identity(2, 2),
    };
    let field_of = |e: InputError| match e {
        InputError::Shape { field, .. }
        | InputError::Invalid { field, .. }
        | InputError::NotPositiveDefinite { field, .. } => field,
        _ => String::new(),
    };
    let mk = |h: CogpHyper| Cogp::new(2, 1, h, PriorMean::Zero, InputMap::Identity);
    let mut bad = good.clone();
    bad.Sigma[(0, 0)] = -1.0;
    assert_eq!(field_of(mk(bad).unwrap_err()), "Sigma");
    let mut bad = good.clone();
    bad.S = DMatrix::identity(3, 3);
    assert_eq!(field_of(mk(bad).unwrap_err()), "S");
    let mut bad = good.clone();
    bad.S[(0, 1)] = 0.5;
    assert_eq!(field_of(mk(bad).unwrap_err()), "S");
    let mut model = mk(good).unwrap();
    let err = model
        .set_data(&[0.0, 0.0, 1.0, f64::NAN], &[0.0, 1.0], &[0.0; 4])
        .unwrap_err();
    assert!(
        matches!(err, Error::Input(InputError::Invalid { ref field, .. }) if field == "x[1][1]")
    );
    assert!(model.set_data(&[0.0, 0.0], &[0.0, 1.0], &[0.0; 2]).is_err());
    assert!(model.posterior(&[0.0]).is_err());
    assert!(model.log_marginal_likelihood_gradient().is_err());
    assert!(fit_cogp(&mut model, &CogpFitSettings::default()).is_err());
}

fn pendulum_data(k: usize, seed: u64) -> (bayes_cbf::sim::Dataset, bayes_cbf::sim::Dataset) {
    let sys = Pendulum::default();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (lo, hi) = ([-std::f64::consts::PI, -6.0], [std::f64::consts::PI, 6.0]);
    let train = sample_uniform(&sys, &lo, &hi, &[-15.0], &[15.0], k, 0.01, &mut rng).unwrap();
    let test = sample_uniform(&sys, &lo, &hi, &[-15.0], &[15.0], 200, 0.0, &mut rng).unwrap();
    (train, test)
}

fn unit_cogp(n: usize, m: usize) -> Cogp {
    Cogp::new(
        n,
        m,
        CogpHyper {
            kernel: Rbf::new(vec![1.0; n], 1.0).unwrap(),
            Sigma: DMatrix::identity(n * (m + 1), n * (m + 1)),
            S: DMatrix::identity(n, n) * 0.01,
        },
        PriorMean::Zero,
        InputMap::Identity,
    )
    .unwrap()
}

#[test]
fn pendulum_fit_increases_likelihood_and_predicts_held_out() {
    let sys = Pendulum::default();
    let (train, test) = pendulum_data(150, 1);
    let mut lls = Vec::new();
    for (rs, rn) in [(Rank::Full, Rank::Full), (Rank::Diagonal, Rank::Diagonal)] {
        let mut model = unit_cogp(2, 1);
        model.set_data(&train.xs, &train.us, &train.xdot).unwrap();
        let rep = fit_cogp(
            &mut model,
            &CogpFitSettings {
                rank_sigma: rs,
                rank_s: rn,
                ..Default::default()
            },
        )
        .unwrap();
        assert!(rep.log_likelihood > rep.initial_log_likelihood);
        assert!((rep.log_likelihood - model.log_marginal_likelihood()).abs() < 1e-9);
        let e = bayes_cbf::gp::metrics::relative_rmse_fu(&model, &test.xs, &test.us, &sys).unwrap();
        eprintln!(
            "CoGP {rs:?}/{rn:?}: log p {:.2} -> {:.2}, {} evaluations, held-out relative RMSE {e:.4}",
            rep.initial_log_likelihood, rep.log_likelihood, rep.evaluations
        );
        assert!(e <= 0.05, "{rs:?}: relative RMSE {e}");
        lls.push(rep.log_likelihood);
    }
    // the diagonal family is contained in the full one (diagonal prefit)
    assert!(
        lls[0] >= lls[1] - 1e-6,
        "full {} < diagonal {}",
        lls[0],
        lls[1]
    );
}

#[test]
fn fit_is_deterministic_and_works_through_the_trait() {
    let (train, _) = pendulum_data(50, 5);
    let settings = ModelFitSettings {
        restarts: 1,
        seed: 9,
        max_iters: 30,
        ..Default::default()
    };
    let run = || {
        let mut model: Box<dyn DynamicsModel> = Box::new(unit_cogp(2, 1));
        model.set_data(&train.xs, &train.us, &train.xdot).unwrap();
        let rep = model.fit(&settings).unwrap();
        assert_eq!(model.name(), "CoGP");
        assert_eq!(rep.starts, 2);
        model.posterior_vec(&[0.3, -1.0]).unwrap()
    };
    assert_eq!(run(), run());
    // the MVGP through the same trait, with the same settings
    let mut mvgp: Box<dyn DynamicsModel> = Box::new(
        Mvgp::new(
            2,
            1,
            MvgpHyper {
                kernel: Rbf::new(vec![1.0; 2], 1.0).unwrap(),
                A: DMatrix::identity(2, 2),
                B: DMatrix::identity(2, 2),
                sigma: 0.1,
            },
            PriorMean::Zero,
            InputMap::Identity,
        )
        .unwrap(),
    );
    mvgp.set_data(&train.xs, &train.us, &train.xdot).unwrap();
    let rep = mvgp.fit(&settings).unwrap();
    assert!(rep.log_likelihood > rep.initial_log_likelihood);
    assert_eq!((mvgp.name(), mvgp.len()), ("MVGP", 50));
    let (mean, cov) = mvgp.posterior_vec(&[0.3, -1.0]).unwrap();
    assert_eq!((mean.shape(), cov.shape()), ((2, 2), (4, 4)));
}
