//! Partially known dynamics (`Mvgp::with_known_rows`) against a brute-force
//! joint Gaussian in which the known rows of `F` have zero prior variance and
//! only the learned rows are observed.

mod common;

use bayes_cbf::gp::{fit, FitSettings, InputMap, Kernel, Mvgp, MvgpHyper, PriorMean, Rbf};
use bayes_cbf::systems::DynSystem;
use common::{condition, joint_prior, point_block, random_spd, rel_diff};
use nalgebra::{DMatrix, DVector};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::sync::Arc;

struct Setup {
    model: Mvgp,
    kernel: Rbf,
    a: DMatrix<f64>,
    b: DMatrix<f64>,
    sigma: f64,
    prior: PriorMean,
    xs: Vec<f64>,
    us: Vec<f64>,
    xdot: Vec<f64>,
}

const N: usize = 3;
const M: usize = 1;
const K: usize = 7;

fn prior() -> PriorMean {
    // a 3-state prior: the pendulum's two rows and a third row f = 0, g = 0
    #[derive(Debug)]
    struct Three;
    impl bayes_cbf::systems::ControlAffine for Three {
        fn state_dim(&self) -> usize {
            N
        }
        fn control_dim(&self) -> usize {
            M
        }
        fn dynamics<D: num_dual::DualNum<Primitive = f64> + Copy>(&self, x: &[D], out: &mut [D]) {
            out[0] = x[1];
            out[1] = x[0].sin() * (-10.0);
            out[2] = x[2] * 0.5;
            out[3] = D::from(0.0);
            out[4] = D::from(1.0);
            out[5] = D::from(0.2);
        }
    }
    PriorMean::System(Arc::new(Three) as Arc<dyn DynSystem>)
}

fn setup(seed: u64, known: &[usize]) -> Setup {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let kernel = Rbf::new(vec![0.9, 1.2, 1.0], 1.1).unwrap();
    let (a, b) = (random_spd(N, &mut rng), random_spd(M + 1, &mut rng));
    let sigma = 0.2;
    let xs: Vec<f64> = (0..K * N).map(|_| rng.random_range(-1.5..1.5)).collect();
    let us: Vec<f64> = (0..K * M).map(|_| rng.random_range(-2.0..2.0)).collect();
    let xdot: Vec<f64> = (0..K * N).map(|_| rng.random_range(-2.0..2.0)).collect();
    let hyper = MvgpHyper {
        kernel: kernel.clone(),
        A: a.clone(),
        B: b.clone(),
        sigma,
    };
    let mut model = Mvgp::new(N, M, hyper, prior(), InputMap::Identity)
        .unwrap()
        .with_known_rows(known)
        .unwrap();
    model.set_data(&xs, &us, &xdot).unwrap();
    Setup {
        model,
        kernel,
        a,
        b,
        sigma,
        prior: prior(),
        xs,
        us,
        xdot,
    }
}

/// Dense conditioning of `[y_L; vec F(x*)]`: `A_eff` zero on known rows,
/// only learned rows observed. Returns the posterior mean and covariance of
/// `vec F(x*)` and the log density of the observations.
fn brute_force(s: &Setup, known: &[usize], xq: &[f64]) -> (DMatrix<f64>, DMatrix<f64>, f64) {
    let p = M + 1;
    let np = N * p;
    let learned: Vec<usize> = (0..N).filter(|i| !known.contains(i)).collect();
    let r = learned.len();
    let mut a_eff = s.a.clone();
    for &i in known {
        a_eff.row_mut(i).fill(0.0);
        a_eff.column_mut(i).fill(0.0);
    }
    let ba = s.b.kronecker(&a_eff);
    let pts: Vec<Vec<f64>> = (0..K)
        .map(|j| s.xs[j * N..(j + 1) * N].to_vec())
        .chain(std::iter::once(xq.to_vec()))
        .collect();
    let tot = K + 1;
    let prior = joint_prior(&pts, &ba, |a, b| s.kernel.value(a, b), &s.prior);
    // y_j = rows L of F(x_j) u̲_j + w_j, w_j ~ N(0, σ² A_LL)
    let mut h = DMatrix::zeros(K * r, tot * np);
    for j in 0..K {
        let ub = [1.0, s.us[j]];
        for (a, &i) in learned.iter().enumerate() {
            for c in 0..p {
                h[(j * r + a, j * np + i + N * c)] = ub[c];
            }
        }
    }
    let a_ll = DMatrix::from_fn(r, r, |i, j| s.a[(learned[i], learned[j])]);
    let y = DVector::from_iterator(
        K * r,
        (0..K).flat_map(|j| learned.iter().map(move |&i| s.xdot[j * N + i])),
    );
    let noise = &a_ll * (s.sigma * s.sigma);
    let (post_mean, post_cov, ll) = condition((&prior.0, &prior.1), &h, &noise, &y);
    let (mean, cov) = point_block(&post_mean, &post_cov, K, N, p);
    (mean, cov, ll)
}

#[test]
fn posterior_and_likelihood_match_the_brute_force_gaussian() {
    for (seed, known) in [(1, vec![0]), (2, vec![0, 2]), (3, vec![1]), (4, vec![])] {
        let s = setup(seed, &known);
        let xq = [0.3, -0.4, 0.8];
        let (mean_bf, cov_bf, ll_bf) = brute_force(&s, &known, &xq);
        let post = s.model.posterior(&xq).unwrap();
        let cov = post.B.kronecker(s.model.row_cov());
        assert!(
            rel_diff(&post.mean, &mean_bf) < 1e-9,
            "mean, known {known:?}"
        );
        assert!(rel_diff(&cov, &cov_bf) < 1e-9, "cov, known {known:?}");
        let ll = s.model.log_marginal_likelihood();
        assert!(
            (ll - ll_bf).abs() < 1e-9 * ll_bf.abs().max(1.0),
            "{ll} vs {ll_bf}"
        );
        // known rows: the prior mean, exactly, with zero variance
        let mut m0 = vec![0.0; N * (M + 1)];
        s.prior.eval(&xq, &mut m0);
        for &i in &known {
            for c in 0..=M {
                assert_eq!(post.mean[(i, c)], m0[i + N * c]);
            }
            assert!(s.model.row_cov().row(i).iter().all(|v| *v == 0.0));
        }
    }
}

#[test]
fn known_row_labels_are_ignored_by_posterior_and_fit() {
    let known = [0];
    let s = setup(5, &known);
    let mut other = s.xdot.clone();
    for j in 0..K {
        other[j * N] += 100.0 * (j as f64 + 1.0);
    }
    let mut m2 = s.model.clone();
    m2.set_data(&s.xs, &s.us, &other).unwrap();
    let xq = [0.1, 0.2, -0.3];
    assert_eq!(s.model.posterior(&xq).unwrap(), m2.posterior(&xq).unwrap());
    let settings = FitSettings {
        max_iters: 30,
        ..FitSettings::default()
    };
    let (mut f1, mut f2) = (s.model.clone(), m2);
    let r1 = fit(&mut f1, &settings).unwrap();
    let r2 = fit(&mut f2, &settings).unwrap();
    assert_eq!(r1.log_likelihood, r2.log_likelihood);
    assert!(r1.log_likelihood >= r1.initial_log_likelihood);
    // the fitted A does not couple the known row to the others
    let a = &f1.hyper().A;
    assert!(a[(0, 1)] == 0.0 && a[(0, 2)] == 0.0 && a[(1, 0)] == 0.0);
    // the fitted model's likelihood is the learned rows' (brute force again)
    let s2 = Setup {
        model: f1.clone(),
        kernel: f1.hyper().kernel.clone(),
        a: f1.hyper().A.clone(),
        b: f1.hyper().B.clone(),
        sigma: f1.hyper().sigma,
        prior: prior(),
        xs: s.xs.clone(),
        us: s.us.clone(),
        xdot: s.xdot.clone(),
    };
    let (_, _, ll_bf) = brute_force(&s2, &known, &xq);
    assert!((f1.log_marginal_likelihood() - ll_bf).abs() < 1e-8 * ll_bf.abs().max(1.0));
}

#[test]
fn declaring_known_rows_after_the_data_refactorises() {
    let s = setup(6, &[]);
    let later = s.model.clone().with_known_rows(&[2]).unwrap();
    let first = setup(6, &[2]).model;
    let xq = [0.5, 0.5, 0.5];
    let (a, b) = (later.posterior(&xq).unwrap(), first.posterior(&xq).unwrap());
    assert!(rel_diff(&a.mean, &b.mean) < 1e-12 && rel_diff(&a.B, &b.B) < 1e-12);
    assert_eq!(later.learned_rows(), vec![0, 1]);
    // online updates keep the known rows exact
    let mut online = first.clone();
    online
        .add_observation(&[0.2, 0.1, 0.0], &[1.0], &[5.0, 5.0, 5.0])
        .unwrap();
    online.remove_oldest();
    let post = online.posterior(&xq).unwrap();
    let mut m0 = vec![0.0; N * (M + 1)];
    prior().eval(&xq, &mut m0);
    assert_eq!(post.mean[(2, 0)], m0[2]);
    assert_eq!(post.mean[(2, 1)], m0[2 + N]);
}

#[test]
fn bad_known_rows_are_errors_naming_the_field() {
    let s = setup(7, &[]);
    for rows in [vec![3], vec![0, 0], vec![0, 1, 2]] {
        let e = s.model.clone().with_known_rows(&rows).unwrap_err();
        assert!(e.to_string().contains("known_rows"), "{e}");
    }
}

/// A model with rows 0 and 2 known and `k` observations whose known rows'
/// labels are the prior's values plus `off(x, u, rng)` on row 0.
fn labelled(k: usize, off: impl Fn(&[f64], f64, &mut ChaCha8Rng) -> f64) -> (Mvgp, Vec<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![0.9, 1.2, 1.0], 1.1).unwrap(),
        A: random_spd(N, &mut rng),
        B: random_spd(M + 1, &mut rng),
        sigma: 0.2,
    };
    let xs: Vec<f64> = (0..k * N).map(|_| rng.random_range(-1.5..1.5)).collect();
    let us: Vec<f64> = (0..k * M).map(|_| rng.random_range(-2.0..2.0)).collect();
    let mut xdot = vec![0.0; k * N];
    for j in 0..k {
        let (x, u) = (&xs[j * N..(j + 1) * N], us[j]);
        xdot[j * N] = x[1] + off(x, u, &mut rng);
        xdot[j * N + 1] = rng.random_range(-2.0..2.0);
        xdot[j * N + 2] = 0.5 * x[2] + 0.2 * u;
    }
    let mut model = Mvgp::new(N, M, hyper, prior(), InputMap::Identity)
        .unwrap()
        .with_known_rows(&[0, 2])
        .unwrap();
    model.set_data(&xs, &us, &xdot).unwrap();
    (model, xdot)
}

/// `known_row_misfit` summarises how far the labels of the known rows
/// stray from the prior mean (root mean squares of the misfit and of the
/// labels, the largest misfit and its observation) and how much of it
/// neighbouring observations share: a wrong prior's misfit follows the
/// state, label noise does not. Only a shared misfit above half the labels
/// is large.
#[test]
fn known_row_misfit_tells_a_wrong_prior_from_noise() {
    use rand_distr::{Distribution, StandardNormal};
    let normal = |rng: &mut ChaCha8Rng| -> f64 { StandardNormal.sample(rng) };
    // labels as the prior says: no misfit
    let (clean, _) = labelled(300, |_, _, _| 0.0);
    let m = clean.known_row_misfit().unwrap();
    assert!(m.rms_misfit < 1e-12 && m.max_misfit < 1e-12, "{m:?}");
    assert!(!m.is_large());
    // a prior that misses a term of the state (θ̇ = ω + x₂ in the data)
    let (wrong, xdot) = labelled(300, |x, _, _| x[2]);
    let m = wrong.known_row_misfit().unwrap();
    let (rms, labels) = (0..300).fold((0.0, 0.0), |(a, b), j| {
        let e = xdot[j * N] - wrong.xs()[j * N + 1];
        (a + e * e / 300.0, b + xdot[j * N].powi(2) / 300.0)
    });
    assert_eq!(m.row, 0);
    assert!((m.rms_misfit - rms.sqrt()).abs() < 1e-12, "{m:?}");
    assert!((m.rms_label - labels.sqrt()).abs() < 1e-12, "{m:?}");
    assert!(m.smooth_share > 0.8, "{m:?}");
    assert!(m.is_large(), "{m:?}");
    assert!(m.describe().contains("row 0"), "{}", m.describe());
    // labels of nearly no size: the share is written short, not in 300
    // digits
    let tiny = bayes_cbf::gp::KnownRowMisfit {
        rms_label: 1e-300,
        ..m
    };
    let text = tiny.describe();
    assert!(text.contains("e301 % of the labels'"), "{text}");
    assert!(text.len() < 500, "{text}");
    // label noise as large as the labels: a right prior, not flagged
    let (noisy, _) = labelled(300, |_, _, rng| normal(rng));
    let m = noisy.known_row_misfit().unwrap();
    assert!(m.rms_misfit > 0.5 && m.smooth_share.abs() < 0.3, "{m:?}");
    assert!(!m.is_large(), "{m:?}");
    // the wrong prior under that noise is still found
    let (both, _) = labelled(300, |x, _, rng| 2.0 * x[2] + normal(rng));
    let m = both.known_row_misfit().unwrap();
    assert!(m.is_large(), "{m:?}");
    // a fifth off everywhere (far more than a finite difference's bias):
    // not large
    let (biased, _) = labelled(300, |x, _, _| 0.2 * x[1]);
    let m = biased.known_row_misfit().unwrap();
    assert!(m.smooth_share > 0.8 && !m.is_large(), "{m:?}");
    // no known rows: nothing to report
    let free = setup(8, &[]);
    assert_eq!(free.model.known_row_misfit(), None);
    // too few observations to tell a trend: not judged
    use bayes_cbf::gp::KNOWN_ROW_MIN_OBSERVATIONS as MIN;
    let (few, _) = labelled(MIN - 1, |x, _, _| x[2]);
    assert_eq!(few.known_row_misfit(), None);
    let (enough, _) = labelled(MIN, |x, _, _| x[2]);
    assert!(enough.known_row_misfit().is_some());
}
