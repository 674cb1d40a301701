//! Online updates: growing the factor row by row equals a fresh
//! factorisation, and a sliding window equals a model built on the window.

mod common;

use bayes_cbf::gp::{InputMap, Mvgp, MvgpHyper, PriorMean, Rbf};
use common::rel_diff;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn data(k: usize, n: usize, m: usize, seed: u64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (
        (0..k * n).map(|_| rng.random_range(-2.0..2.0)).collect(),
        (0..k * m).map(|_| rng.random_range(-2.0..2.0)).collect(),
        (0..k * n).map(|_| rng.random_range(-2.0..2.0)).collect(),
    )
}

fn model(seed: u64) -> Mvgp {
    common::pendulum_model(seed)
}

fn assert_same(a: &Mvgp, b: &Mvgp, tol: f64) {
    let mut rng = ChaCha8Rng::seed_from_u64(77);
    for _ in 0..10 {
        let x: Vec<f64> = (0..2).map(|_| rng.random_range(-2.0..2.0)).collect();
        let pa = a.posterior(&x).unwrap();
        let pb = b.posterior(&x).unwrap();
        assert!(
            rel_diff(&pa.mean, &pb.mean) < tol,
            "mean {} vs {}",
            pa.mean,
            pb.mean
        );
        assert!(rel_diff(&pa.B, &pb.B) < tol, "B");
        assert!(rel_diff(&a.posterior_mean(&x).unwrap(), &pb.mean) < tol);
    }
    assert!(
        (a.log_marginal_likelihood() - b.log_marginal_likelihood()).abs()
            < tol * b.log_marginal_likelihood().abs().max(1.0)
    );
    let (la, lb) = (a.factor().l(), b.factor().l());
    for j in 0..la.ncols() {
        for i in 0..la.nrows() {
            assert!((la[(i, j)] - lb[(i, j)]).abs() < tol, "L[{i},{j}]");
        }
    }
}

#[test]
fn online_growth_equals_refactorisation() {
    let (xs, us, xd) = data(120, 2, 1, 1);
    let mut online = model(5);
    online.set_data(&xs[..20], &us[..10], &xd[..20]).unwrap();
    for j in 10..120 {
        online
            .add_observation(&xs[2 * j..2 * j + 2], &us[j..j + 1], &xd[2 * j..2 * j + 2])
            .unwrap();
    }
    let mut fresh = model(5);
    fresh.set_data(&xs, &us, &xd).unwrap();
    assert_eq!(online.len(), 120);
    assert_same(&online, &fresh, 1e-10);
    // starting from an empty model works too
    let mut empty = model(5);
    for j in 0..120 {
        empty
            .add_observation(&xs[2 * j..2 * j + 2], &us[j..j + 1], &xd[2 * j..2 * j + 2])
            .unwrap();
    }
    assert_same(&empty, &fresh, 1e-10);
}

#[test]
fn sliding_window_equals_model_on_window() {
    let (xs, us, xd) = data(150, 2, 1, 2);
    let w = 50;
    let mut online = model(6);
    online
        .set_data(&xs[..2 * w], &us[..w], &xd[..2 * w])
        .unwrap();
    for j in w..150 {
        online
            .add_observation(&xs[2 * j..2 * j + 2], &us[j..j + 1], &xd[2 * j..2 * j + 2])
            .unwrap();
        online.remove_oldest();
        assert_eq!(online.len(), w);
    }
    let start = 150 - w;
    let mut fresh = model(6);
    fresh
        .set_data(&xs[2 * start..], &us[start..], &xd[2 * start..])
        .unwrap();
    assert_same(&online, &fresh, 1e-10);
}

#[test]
fn bad_observations_are_rejected_and_leave_the_model_intact() {
    let (xs, us, xd) = data(10, 2, 1, 3);
    let mut m = model(7);
    m.set_data(&xs, &us, &xd).unwrap();
    let before = m.posterior(&[0.1, 0.2]).unwrap();
    let err = m
        .add_observation(&[f64::NAN, 0.0], &[0.0], &[0.0, 0.0])
        .unwrap_err();
    assert!(err.to_string().contains("x[10]"), "{err}");
    let err = m
        .add_observation(&[0.0, 0.0], &[0.0, 1.0], &[0.0, 0.0])
        .unwrap_err();
    assert!(err.to_string().contains("u[10]"), "{err}");
    assert!(m.set_data(&xs[..3], &us, &xd).is_err());
    assert_eq!(m.len(), 10);
    assert_eq!(m.posterior(&[0.1, 0.2]).unwrap(), before);
}

#[test]
fn duplicate_points_with_tiny_noise_use_bounded_jitter() {
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![1.0, 1.0], 1.0).unwrap(),
        A: nalgebra::DMatrix::identity(2, 2),
        B: nalgebra::DMatrix::identity(2, 2),
        sigma: 1e-9,
    };
    let mut m = Mvgp::new(2, 1, hyper, PriorMean::Zero, InputMap::Identity).unwrap();
    let x = [0.3, 0.4];
    for _ in 0..5 {
        m.add_observation(&x, &[1.0], &[0.1, 0.2]).unwrap();
    }
    assert!(m.factor().max_jitter() > 0.0);
    assert!(m.factor().max_jitter() < 1e-5);
    let p = m.posterior(&x).unwrap();
    assert!(p.mean.iter().all(|v| v.is_finite()));
    assert!(p.B.symmetric_eigenvalues().iter().all(|&e| e > -1e-8));
}

#[test]
fn more_data_never_increases_posterior_variance() {
    let (xs, us, xd) = data(60, 2, 1, 9);
    let mut m = model(8);
    let mut rng = ChaCha8Rng::seed_from_u64(10);
    let probes: Vec<Vec<f64>> = (0..20)
        .map(|_| (0..2).map(|_| rng.random_range(-2.5..2.5)).collect())
        .collect();
    let mut prev: Vec<nalgebra::DMatrix<f64>> =
        probes.iter().map(|x| m.posterior(x).unwrap().B).collect();
    for j in 0..60 {
        m.add_observation(&xs[2 * j..2 * j + 2], &us[j..j + 1], &xd[2 * j..2 * j + 2])
            .unwrap();
        for (x, p) in probes.iter().zip(prev.iter_mut()) {
            let b = m.posterior(x).unwrap().B;
            // B_prev − B_new is positive semidefinite
            let ev = (&*p - &b).symmetric_eigenvalues();
            assert!(
                ev.iter().all(|&e| e > -1e-9),
                "variance grew at {x:?}: {ev}"
            );
            *p = b;
        }
    }
}
