//! The Kronecker-structured MVGP posterior (Prop. 1) against a brute-force
//! construction of the full joint Gaussian of `[vec Ẋ; vec F(x*); vec F(x**)]`,
//! conditioned directly.

mod common;

use bayes_cbf::gp::{InputMap, Kernel, Mvgp, MvgpHyper, PriorMean, Rbf};
use bayes_cbf::systems::DynSystem;
use common::{
    condition, joint_prior, observation_map, point_block, random_rbf, random_spd, rel_diff,
};
use nalgebra::DVector;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::sync::Arc;

struct Case {
    n: usize,
    m: usize,
    k: usize,
    prior: PriorMean,
    input_map: InputMap,
}

fn check_case(case: Case, seed: u64) {
    let Case {
        n,
        m,
        k,
        prior,
        input_map,
    } = case;
    let p = m + 1;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let d = input_map.output_dim(n);
    let kernel = random_rbf(d, 0.5..1.5, &mut rng);
    #[allow(non_snake_case)]
    let (A, B) = (random_spd(n, &mut rng), random_spd(p, &mut rng));
    let sigma = rng.random_range(0.05..0.5);
    let xs: Vec<f64> = (0..k * n).map(|_| rng.random_range(-1.5..1.5)).collect();
    let us: Vec<f64> = (0..k * m).map(|_| rng.random_range(-2.0..2.0)).collect();
    let xdot: Vec<f64> = (0..k * n).map(|_| rng.random_range(-2.0..2.0)).collect();
    let tests: Vec<Vec<f64>> = (0..2)
        .map(|_| (0..n).map(|_| rng.random_range(-1.5..1.5)).collect())
        .collect();

    let hyper = MvgpHyper {
        kernel: kernel.clone(),
        A: A.clone(),
        B: B.clone(),
        sigma,
    };
    let mut model = Mvgp::new(n, m, hyper, prior.clone(), input_map.clone()).unwrap();
    model.set_data(&xs, &us, &xdot).unwrap();

    // brute force: all k + 2 points
    let pts: Vec<Vec<f64>> = (0..k)
        .map(|j| xs[j * n..(j + 1) * n].to_vec())
        .chain(tests.iter().cloned())
        .collect();
    let z = |x: &[f64]| {
        let mut zz = vec![0.0; d];
        input_map.apply(x, &mut zz);
        zz
    };
    let np = n * p;
    let ba = B.kronecker(&A);
    let joint = joint_prior(&pts, &ba, |a, b| kernel.value(&z(a), &z(b)), &prior);
    // observation map: y = H vec F(all) + w, only the first k points observed
    let h = observation_map(&us, m, n, k + 2);
    let y = DVector::from_column_slice(&xdot);
    let noise = &A * (sigma * sigma);
    let (post_mean, post_cov, _) = condition((&joint.0, &joint.1), &h, &noise, &y);

    for (t, x) in tests.iter().enumerate() {
        let post = model.posterior(x).unwrap();
        let (mean_bf, cov_bf) = point_block(&post_mean, &post_cov, k + t, n, p);
        let cov_mvgp = post.B.kronecker(&A);
        assert!(
            rel_diff(&post.mean, &mean_bf) < 1e-9,
            "mean: n={n} m={m} {:?}",
            prior
        );
        assert!(rel_diff(&cov_mvgp, &cov_bf) < 1e-9, "cov: n={n} m={m}");
        let mean_only = model.posterior_mean(x).unwrap();
        assert!(rel_diff(&mean_only, &mean_bf) < 1e-9, "posterior_mean");
    }
    // cross-covariance B_k(x*, x**) ⊗ A
    let cross = model
        .posterior_cov(&tests[0], &tests[1])
        .unwrap()
        .kronecker(&A);
    let cross_bf = post_cov.view((k * np, (k + 1) * np), (np, np)).into_owned();
    assert!(rel_diff(&cross, &cross_bf) < 1e-9, "cross cov n={n} m={m}");
}

#[test]
fn posterior_matches_brute_force_joint_gaussian() {
    common::for_each_posterior_case(|n, m, prior, seed| {
        let input_map = InputMap::Identity;
        check_case(
            Case {
                n,
                m,
                k: 7,
                prior,
                input_map,
            },
            seed,
        )
    });
}

#[test]
fn posterior_with_input_map_matches_brute_force() {
    let sys: Arc<dyn DynSystem> = Arc::new(bayes_cbf::systems::Ackermann { wheelbase: 2.0 });
    check_case(
        Case {
            n: 3,
            m: 2,
            k: 9,
            prior: PriorMean::System(sys),
            input_map: InputMap::Select(vec![2]),
        },
        42,
    );
    check_case(
        Case {
            n: 3,
            m: 1,
            k: 6,
            prior: PriorMean::Zero,
            input_map: InputMap::Select(vec![0, 2]),
        },
        43,
    );
}

#[test]
fn posterior_variance_is_positive_semidefinite() {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let (n, m, k) = (2, 1, 40);
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![0.3, 0.3], 1.0).unwrap(),
        A: random_spd(n, &mut rng),
        B: random_spd(m + 1, &mut rng),
        sigma: 1e-3,
    };
    let mut model = Mvgp::new(n, m, hyper, PriorMean::Zero, InputMap::Identity).unwrap();
    let xs: Vec<f64> = (0..k * n).map(|_| rng.random_range(-1.0..1.0)).collect();
    let us: Vec<f64> = (0..k * m).map(|_| rng.random_range(-1.0..1.0)).collect();
    let xd: Vec<f64> = (0..k * n).map(|_| rng.random_range(-1.0..1.0)).collect();
    model.set_data(&xs, &us, &xd).unwrap();
    for j in 0..k + 20 {
        let x: Vec<f64> = if j < k {
            xs[j * n..(j + 1) * n].to_vec()
        } else {
            (0..n).map(|_| rng.random_range(-3.0..3.0)).collect()
        };
        let b = model.posterior(&x).unwrap().B;
        let ev = b.symmetric_eigenvalues();
        assert!(ev.iter().all(|&e| e > -1e-9), "eigenvalues {ev:?}");
    }
}
