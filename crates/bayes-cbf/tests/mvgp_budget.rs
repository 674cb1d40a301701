//! Budgeted learning: removing any observation equals a model built without
//! it, the maintained `diag(G⁻¹)` equals the exact one, and the budget
//! policy removes the point whose removal keeps the largest `log det G`.

mod common;

use bayes_cbf::gp::Mvgp;
use common::rel_diff;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn data(k: usize, seed: u64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (
        (0..2 * k).map(|_| rng.random_range(-2.0..2.0)).collect(),
        (0..k).map(|_| rng.random_range(-2.0..2.0)).collect(),
        (0..2 * k).map(|_| rng.random_range(-2.0..2.0)).collect(),
    )
}

fn model(seed: u64) -> Mvgp {
    common::pendulum_model(seed)
}

/// The same model rebuilt from scratch on `m`'s stored data.
fn rebuilt(m: &Mvgp, seed: u64) -> Mvgp {
    let mut fresh = model(seed);
    fresh.set_data(m.xs(), &m.controls(), m.xdot()).unwrap();
    fresh
}

fn assert_same(a: &Mvgp, b: &Mvgp, tol: f64) {
    assert_eq!(a.len(), b.len());
    let mut rng = ChaCha8Rng::seed_from_u64(77);
    for _ in 0..10 {
        let x: Vec<f64> = (0..2).map(|_| rng.random_range(-2.0..2.0)).collect();
        let (pa, pb) = (a.posterior(&x).unwrap(), b.posterior(&x).unwrap());
        assert!(
            rel_diff(&pa.mean, &pb.mean) < tol,
            "mean {} vs {}",
            pa.mean,
            pb.mean
        );
        assert!(rel_diff(&pa.B, &pb.B) < tol, "B {} vs {}", pa.B, pb.B);
        assert!(rel_diff(&a.posterior_mean(&x).unwrap(), &pb.mean) < tol);
    }
    let (la, lb) = (a.factor().l(), b.factor().l());
    for j in 0..la.ncols() {
        for i in 0..la.nrows() {
            assert!((la[(i, j)] - lb[(i, j)]).abs() < tol, "L[{i},{j}]");
        }
    }
    let (ba, bb) = (a.beta(), b.beta());
    for c in 0..2 {
        for i in 0..a.len() {
            assert!((ba[(i, c)] - bb[(i, c)]).abs() < tol, "beta[{i},{c}]");
        }
    }
    let (x, y) = (a.log_marginal_likelihood(), b.log_marginal_likelihood());
    assert!((x - y).abs() < tol * y.abs().max(1.0), "LML {x} vs {y}");
}

/// `diag(G⁻¹)` from the dense inverse of a fresh factorisation.
fn exact_diag(m: &Mvgp) -> Vec<f64> {
    let inv = m.factor().inverse();
    (0..m.len()).map(|j| inv[(j, j)]).collect()
}

fn assert_diag(tracked: &[f64], exact: &[f64], tol: f64) {
    assert_eq!(tracked.len(), exact.len());
    for (j, (a, b)) in tracked.iter().zip(exact).enumerate() {
        assert!((a - b).abs() < tol * b.abs(), "[G⁻¹]_{j}{j}: {a} vs {b}");
    }
}

#[test]
fn removing_any_observation_equals_a_model_without_it() {
    let (xs, us, xd) = data(60, 1);
    for j in [0, 1, 17, 30, 58, 59] {
        let mut online = model(5);
        online.set_data(&xs, &us, &xd).unwrap();
        online.remove_observation(j);
        let keep: Vec<usize> = (0..60).filter(|&i| i != j).collect();
        let pick = |v: &[f64], d: usize| -> Vec<f64> {
            keep.iter()
                .flat_map(|&i| v[i * d..(i + 1) * d].to_vec())
                .collect()
        };
        let mut fresh = model(5);
        fresh
            .set_data(&pick(&xs, 2), &pick(&us, 1), &pick(&xd, 2))
            .unwrap();
        assert_same(&online, &fresh, 1e-10);
    }
}

#[test]
fn tracked_inverse_diagonal_equals_the_exact_one() {
    let (xs, us, xd) = data(200, 2);
    let mut online = model(6);
    online.set_data(&xs[..40], &us[..20], &xd[..40]).unwrap();
    let exact = exact_diag(&online);
    assert_diag(online.gram_inverse_diagonal(), &exact, 1e-10);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    // mixed appends and removals anywhere, fewer than the refresh period
    for j in 20..120 {
        online
            .add_observation(&xs[2 * j..2 * j + 2], &us[j..j + 1], &xd[2 * j..2 * j + 2])
            .unwrap();
        if j % 3 == 0 {
            let r = rng.random_range(0..online.len());
            online.remove_observation(r);
        }
    }
    let fresh = rebuilt(&online, 6);
    assert_same(&online, &fresh, 1e-9);
    let tracked = online.gram_inverse_diagonal().to_vec();
    assert_diag(&tracked, &exact_diag(&fresh), 1e-9);
}

#[test]
fn policy_keeps_the_subset_of_largest_log_det() {
    let (xs, us, xd) = data(31, 4);
    let mut m = model(8);
    m.set_data(&xs, &us, &xd).unwrap();
    let logdet = m.factor().log_det();
    // brute force: log det G₋ⱼ for every j from a fresh factorisation
    let drop_logdet = |j: usize| {
        let mut c = m.clone();
        c.remove_observation(j);
        rebuilt(&c, 8).factor().log_det()
    };
    let all: Vec<f64> = (0..31).map(drop_logdet).collect();
    let diag = m.gram_inverse_diagonal().to_vec();
    for j in 0..31 {
        // log det G₋ⱼ = log det G + log [G⁻¹]_jj
        assert!((all[j] - (logdet + diag[j].ln())).abs() < 1e-8, "j = {j}");
    }
    let best = (0..31).fold(0, |b, j| if all[j] > all[b] { j } else { b });
    let removed = m.remove_least_informative().unwrap();
    assert_eq!(removed, best);
    assert_eq!(m.len(), 30);
}

/// A budget over a long stream (3 920 incremental updates of `diag(G⁻¹)`,
/// one exact recomputation): the model stays the exact GP of the points it
/// kept, the tracked diagonal stays exact, and a repeated point is the one
/// discarded.
#[test]
fn budget_stream_stays_exact_and_discards_duplicates() {
    let budget = 40;
    let (xs, us, xd) = data(2000, 5);
    let mut m = model(9);
    m.set_data(&xs[..2 * budget], &us[..budget], &xd[..2 * budget])
        .unwrap();
    let mut discarded = 0;
    for j in budget..2000 {
        m.add_observation(&xs[2 * j..2 * j + 2], &us[j..j + 1], &xd[2 * j..2 * j + 2])
            .unwrap();
        if m.remove_least_informative() == Some(budget) {
            discarded += 1;
        }
        assert_eq!(m.len(), budget);
    }
    assert!(discarded > 0 && discarded < 1960, "discarded {discarded}");
    let fresh = rebuilt(&m, 9);
    assert_same(&m, &fresh, 1e-8);
    let tracked = m.gram_inverse_diagonal().to_vec();
    assert_diag(&tracked, &exact_diag(&fresh), 1e-10);
    // a copy of a stored point carries almost no new information: discarded
    let x0 = m.xs()[..2].to_vec();
    let u0 = m.controls()[..1].to_vec();
    let d0 = m.xdot()[..2].to_vec();
    m.add_observation(&x0, &u0, &d0).unwrap();
    let r = m.remove_least_informative().unwrap();
    assert!(r == 0 || r == budget, "removed {r}");
}

#[test]
#[should_panic(expected = "remove_observation")]
fn removing_past_the_end_is_a_bug() {
    let (xs, us, xd) = data(5, 6);
    let mut m = model(1);
    m.set_data(&xs, &us, &xd).unwrap();
    m.remove_observation(5);
}
