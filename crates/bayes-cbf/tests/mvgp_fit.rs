//! Hyperparameter learning: the fitted likelihood beats the true
//! hyperparameters' on data drawn from a known MVGP, and fits of simulated
//! pendulum and Ackermann data predict held-out `F(x)u̲` within 5 %.

mod common;

use bayes_cbf::gp::{fit, FitSettings, InputMap, Kernel, Mvgp, MvgpHyper, PriorMean, Rank, Rbf};
use bayes_cbf::sim::sample_uniform;
use bayes_cbf::systems::{Ackermann, DynSystem, Pendulum};
use nalgebra::{DMatrix, DVector};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

fn default_hyper(d: usize, n: usize, m: usize) -> MvgpHyper {
    MvgpHyper {
        kernel: Rbf::new(vec![1.0; d], 1.0).unwrap(),
        A: DMatrix::identity(n, n),
        B: DMatrix::identity(m + 1, m + 1),
        sigma: 0.1,
    }
}

/// A zero-mean MVGP (unit start) on rows `xs`, `us`, `xdot`.
fn zero_mean_model(n: usize, m: usize, xs: &[f64], us: &[f64], xdot: &[f64]) -> Mvgp {
    let hyper = default_hyper(n, n, m);
    let mut model = Mvgp::new(n, m, hyper, PriorMean::Zero, InputMap::Identity).unwrap();
    model.set_data(xs, us, xdot).unwrap();
    model
}

/// The pendulum MVGP (zero prior mean, unit start) on `data`.
fn pendulum_mvgp(data: &bayes_cbf::sim::Dataset) -> Mvgp {
    zero_mean_model(2, 1, &data.xs, &data.us, &data.xdot)
}

#[test]
#[allow(non_snake_case)]
fn fit_beats_true_hyperparameters_on_mvgp_samples() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let (n, m, k) = (2, 1, 80);
    let p = m + 1;
    let kernel = Rbf::new(vec![0.6, 0.9], 1.0).unwrap();
    let A = DMatrix::from_row_slice(2, 2, &[1.0, 0.3, 0.3, 0.5]);
    let B = DMatrix::from_row_slice(2, 2, &[2.0, 0.5, 0.5, 1.0]);
    let sigma = 0.1;
    let xs: Vec<f64> = (0..k * n).map(|_| rng.random_range(-2.0..2.0)).collect();
    let us: Vec<f64> = (0..k * m).map(|_| rng.random_range(-2.0..2.0)).collect();
    // draw vec Ẋ ~ N(0, (K + σ²I) ⊗ A)
    let mut g = DMatrix::zeros(k, k);
    for i in 0..k {
        for j in 0..k {
            let ui = DVector::from_vec(vec![1.0, us[i]]);
            let uj = DVector::from_vec(vec![1.0, us[j]]);
            g[(i, j)] = (ui.transpose() * &B * uj)[(0, 0)]
                * kernel.value(&xs[i * n..i * n + n], &xs[j * n..j * n + n]);
        }
        g[(i, i)] += sigma * sigma;
    }
    let cov = g.kronecker(&A);
    let l = cov.cholesky().unwrap().l();
    let e = DVector::from_fn(k * n, |_, _| StandardNormal.sample(&mut rng));
    let y = l * e; // vec of n × k, column-major: ẋ_j = y[j n .. j n + n]
    let xdot: Vec<f64> = y.iter().cloned().collect();

    let truth = MvgpHyper {
        kernel,
        A,
        B,
        sigma,
    };
    let mut true_model = Mvgp::new(n, m, truth, PriorMean::Zero, InputMap::Identity).unwrap();
    true_model.set_data(&xs, &us, &xdot).unwrap();
    let ll_true = true_model.log_marginal_likelihood();

    for (ra, rb) in [(Rank::Full, Rank::Full), (Rank::Low(1), Rank::Full)] {
        let mut model = zero_mean_model(n, m, &xs, &us, &xdot);
        let rep = fit(
            &mut model,
            &FitSettings {
                rank_a: ra,
                rank_b: rb,
                max_iters: 200,
                restarts: 2,
                ..Default::default()
            },
        )
        .unwrap();
        assert!(
            rep.log_likelihood >= ll_true - 1e-6,
            "fitted {} < true {ll_true}",
            rep.log_likelihood
        );
        assert!(rep.log_likelihood > rep.initial_log_likelihood);
        assert!(
            (model.hyper().A.trace() - n as f64).abs() < 1e-9,
            "A normalised to tr A = n"
        );
        assert_eq!(model.hyper().B.nrows(), p);
    }
}

#[test]
fn fit_is_deterministic_given_seed() {
    let sys = Pendulum::default();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let ds = sample_uniform(
        &sys,
        &[-3.0, -5.0],
        &[3.0, 5.0],
        &[-10.0],
        &[10.0],
        60,
        0.01,
        &mut rng,
    )
    .unwrap();
    let run = || {
        let mut model = pendulum_mvgp(&ds);
        fit(
            &mut model,
            &FitSettings {
                restarts: 1,
                seed: 9,
                ..Default::default()
            },
        )
        .unwrap();
        model.hyper().clone()
    };
    assert_eq!(run(), run());
}

/// Relative RMSE of the posterior mean of `F(x)u̲` on held-out samples.
fn held_out_relative_rmse(
    model: &Mvgp,
    sys: &dyn DynSystem,
    test: &bayes_cbf::sim::Dataset,
) -> f64 {
    let (n, m) = (sys.state_dim(), sys.control_dim());
    let (mut num, mut den) = (0.0, 0.0);
    let mut fbuf = vec![0.0; n * (1 + m)];
    let mut truth = vec![0.0; n];
    for j in 0..test.len() {
        let x = &test.xs[j * n..(j + 1) * n];
        let u = &test.us[j * m..(j + 1) * m];
        sys.xdot(x, u, &mut fbuf, &mut truth);
        let mean = model.posterior_mean(x).unwrap();
        for i in 0..n {
            let mut pred = mean[(i, 0)];
            for c in 0..m {
                pred += mean[(i, c + 1)] * u[c];
            }
            num += (pred - truth[i]).powi(2);
            den += truth[i].powi(2);
        }
    }
    (num / den).sqrt()
}

#[test]
fn pendulum_fit_predicts_held_out_within_five_percent() {
    let sys = Pendulum::default();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let (lo, hi) = ([-std::f64::consts::PI, -6.0], [std::f64::consts::PI, 6.0]);
    let [train, test] = [0.01, 0.0].map(|noise| {
        sample_uniform(&sys, &lo, &hi, &[-15.0], &[15.0], 200, noise, &mut rng).unwrap()
    });
    let mut model = pendulum_mvgp(&train);
    fit(&mut model, &FitSettings::default()).unwrap();
    let e = held_out_relative_rmse(&model, &sys, &test);
    eprintln!("pendulum held-out relative RMSE: {e:.4}");
    assert!(e <= 0.05, "relative RMSE {e}");
}

#[test]
fn ackermann_fit_predicts_held_out_within_five_percent() {
    let sys = Ackermann { wheelbase: 1.0 };
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let (lo, hi) = (
        [-3.0, -3.0, -std::f64::consts::PI],
        [3.0, 3.0, std::f64::consts::PI],
    );
    let [train, test] = [0.01, 0.0].map(|noise| {
        sample_uniform(&sys, &lo, &hi, &[-1.0; 2], &[1.0; 2], 200, noise, &mut rng).unwrap()
    });
    let mut model = Mvgp::new(
        3,
        2,
        default_hyper(1, 3, 2),
        PriorMean::Zero,
        InputMap::Select(vec![2]),
    )
    .unwrap();
    model.set_data(&train.xs, &train.us, &train.xdot).unwrap();
    fit(&mut model, &FitSettings::default()).unwrap();
    let e = held_out_relative_rmse(&model, &sys, &test);
    eprintln!("ackermann held-out relative RMSE: {e:.4}");
    assert!(e <= 0.05, "relative RMSE {e}");
}

/// A pendulum model of `k` observations and the default start.
fn pendulum_model(k: usize, seed: u64) -> Mvgp {
    let sys = Pendulum::default();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (lo, hi) = ([-std::f64::consts::PI, -6.0], [std::f64::consts::PI, 6.0]);
    pendulum_mvgp(&sample_uniform(&sys, &lo, &hi, &[-20.0], &[20.0], k, 0.01, &mut rng).unwrap())
}

/// `σ` in the fit's own scale (`A_00 = 1`).
fn fitted_sigma(model: &Mvgp) -> f64 {
    let h = model.hyper();
    h.sigma * h.A[(0, 0)].sqrt()
}

/// Active bounds cost no more than twice the evaluations of the same fit
/// without them: the noise floor above the free optimum's `σ` (the bounded
/// optimum sits on the floor), and a warm start whose every scale may move
/// only 1.5× either way (most scales end on their bounds) against the same
/// warm start without that box.
#[test]
fn active_bounds_cost_at_most_twice_the_evaluations() {
    for seed in [3, 4] {
        let mut free = pendulum_model(200, seed);
        let r_free = fit(&mut free, &FitSettings::default()).unwrap();
        let sigma = fitted_sigma(&free);
        for factor in [2.0, 5.0, 20.0] {
            let mut floored = pendulum_model(200, seed);
            let settings = FitSettings {
                sigma_min: factor * sigma,
                ..FitSettings::default()
            };
            let r = fit(&mut floored, &settings).unwrap();
            // the result sits on the floor (within the final factorisation's
            // 10 % steps), below the free optimum's likelihood
            let s = fitted_sigma(&floored);
            assert!(
                s >= factor * sigma * (1.0 - 1e-9) && s <= 1.25 * factor * sigma,
                "seed {seed}, floor {factor}×: σ {s} against the floor {}",
                factor * sigma
            );
            assert!(r.log_likelihood < r_free.log_likelihood);
            assert!(
                r.evaluations <= 2 * r_free.evaluations,
                "seed {seed}, floor {factor}×: {} evaluations against {} free",
                r.evaluations,
                r_free.evaluations
            );
        }
        // warm starts from a point away from the optimum: lengthscales,
        // σ and B off by factors of 3
        let start = |model: &mut Mvgp| {
            let mut h = free.hyper().clone();
            let l = h.kernel.lengthscales().to_vec();
            h.kernel = Rbf::new(vec![3.0 * l[0], 0.3 * l[1]], 1.0).unwrap();
            h.sigma *= 3.0;
            h.B *= 0.3;
            model.set_hyper(h).unwrap();
        };
        let mut wide = pendulum_model(200, seed);
        start(&mut wide);
        let r_wide = fit(
            &mut wide,
            &FitSettings {
                warm_start: true,
                warm_range: f64::INFINITY,
                ..FitSettings::default()
            },
        )
        .unwrap();
        let mut boxed = pendulum_model(200, seed);
        start(&mut boxed);
        let r_box = fit(
            &mut boxed,
            &FitSettings {
                warm_start: true,
                warm_range: 1.5,
                ..FitSettings::default()
            },
        )
        .unwrap();
        // the box binds: its optimum is worse than the free one's
        assert!(r_box.log_likelihood < r_wide.log_likelihood - 1.0);
        assert!(
            r_box.evaluations <= 2 * r_wide.evaluations,
            "seed {seed}: {} evaluations in the box against {} without",
            r_box.evaluations,
            r_wide.evaluations
        );
        eprintln!(
            "seed {seed}: free {} evaluations; warm start {} without the box, {} in it",
            r_free.evaluations, r_wide.evaluations, r_box.evaluations
        );
    }
}

/// Each check of `FitSettings::validate` at its boundary: `warm_range ≥ 1`
/// (1 itself allowed, NaN rejected), `0 ≤ σ_min ≤ 1e150`.
#[test]
fn fit_settings_boundaries() {
    let ok = |warm_range: f64, sigma_min: f64| {
        FitSettings {
            warm_range,
            sigma_min,
            ..FitSettings::default()
        }
        .validate()
        .is_ok()
    };
    assert!(ok(1.0, 0.0) && ok(f64::INFINITY, 0.5));
    assert!(!ok(1.0 - 1e-12, 0.0) && !ok(f64::NAN, 0.0) && !ok(0.0, 0.0));
    assert!(!ok(2.0, -1e-300) && !ok(2.0, f64::NAN));
    assert!(ok(2.0, 1e150) && !ok(2.0, 1e151) && !ok(2.0, f64::INFINITY));
    let e = FitSettings {
        warm_range: 0.5,
        ..FitSettings::default()
    }
    .validate()
    .unwrap_err();
    assert!(e.to_string().contains("warm_range"), "{e}");
}

/// The benchmark floor of an evaluation needs an evaluation first, and
/// leaves the next evaluation's value and gradient as they were.
#[test]
fn likelihood_floor_needs_an_evaluation_and_changes_nothing() {
    use bayes_cbf::gp::MvgpLikelihood;
    let model = pendulum_model(40, 3);
    let mut lik = MvgpLikelihood::new(&model, &FitSettings::default()).unwrap();
    assert!(lik.floor().is_err());
    let theta = lik.start().to_vec();
    let mut g1 = vec![0.0; lik.dim()];
    let v1 = lik.evaluate(&theta, &mut g1).unwrap();
    lik.floor().unwrap();
    let mut g2 = vec![0.0; lik.dim()];
    let v2 = lik.evaluate(&theta, &mut g2).unwrap();
    assert_eq!(v1, v2);
    assert_eq!(g1, g2);
}

/// The likelihood's start with `log σ_f` (the one coordinate that moves
/// `σ` alone) at −300: `σ_f` is zero and the noise is the floor.
fn without_free_noise<K: Kernel + PartialEq>(
    lik: &bayes_cbf::gp::MvgpLikelihood<'_, K>,
) -> Vec<f64> {
    let start = lik.start().to_vec();
    let base = lik.hyper(&start).unwrap();
    let i = (0..lik.dim())
        .find(|&i| {
            let mut th = start.clone();
            th[i] += 0.5;
            let h = lik.hyper(&th).unwrap();
            h.sigma != base.sigma && h.A == base.A && h.B == base.B && h.kernel == base.kernel
        })
        .expect("a coordinate for σ_f");
    let mut th = start;
    th[i] = -300.0;
    th
}

/// Sets the model's kernel variance to `s` and returns fit settings that
/// keep it: a warm start (a cold one starts the kernel from variance 1,
/// where `s̄`'s factor `k(z, z)` could be dropped or inverted unseen).
fn kernel_variance(model: &mut Mvgp, s: f64) -> FitSettings {
    let mut h = model.hyper().clone();
    h.kernel = Rbf::new(h.kernel.lengthscales().to_vec(), s).unwrap();
    model.set_hyper(h).unwrap();
    FitSettings {
        warm_start: true,
        ..FitSettings::default()
    }
}

/// The noise floor `σ² = σ_f² + ε s̄` (`ε = 10⁻¹⁰`, `s̄` the mean of the
/// Gram matrix's signal diagonal `u̲_jᵀ B u̲_j k(z_j, z_j)`): with `σ_f`
/// driven to zero, the hyperparameters at `θ` have exactly
/// `σ² = ε · mean_j u̲_jᵀ B u̲_j k₀(z_j, z_j)` (in the returned
/// normalisation, where `B` and `σ²` scale together).
#[test]
fn the_noise_floor_is_a_fraction_of_the_mean_signal() {
    let mut model = pendulum_model(30, 4);
    let warm = kernel_variance(&mut model, 2.5);
    check_noise_floor(&model, &warm);
    // a kernel that is not stationary: k(z_j, z_j) = (1 + |z_j|²)² differs
    // from point to point
    let h = model.hyper();
    let mut quad = Mvgp::new(
        2,
        1,
        MvgpHyper {
            kernel: common::Quadratic2(2),
            A: h.A.clone(),
            B: h.B.clone(),
            sigma: h.sigma,
        },
        PriorMean::Zero,
        InputMap::Identity,
    )
    .unwrap();
    quad.set_data(model.xs(), &model.controls(), model.xdot())
        .unwrap();
    check_noise_floor(&quad, &FitSettings::default());
}

/// `σ` of the hyperparameters at `σ_f → 0` against `√(ε s̄)` recomputed
/// from the returned `B`, the kernel and the data.
fn check_noise_floor<K: Kernel + PartialEq>(model: &Mvgp<K>, settings: &FitSettings) {
    use bayes_cbf::gp::MvgpLikelihood;
    let lik = MvgpLikelihood::new(model, settings).unwrap();
    let th = without_free_noise(&lik);
    let h = lik.hyper(&th).unwrap();
    let (xs, us, m) = (model.xs(), &model.controls(), model.control_dim());
    let mean_signal = (0..model.len())
        .map(|j| {
            let ub: Vec<f64> = std::iter::once(1.0)
                .chain(us[j * m..(j + 1) * m].iter().copied())
                .collect();
            let x = &xs[j * 2..j * 2 + 2];
            let bu = &h.B * DVector::from_column_slice(&ub);
            DVector::from_column_slice(&ub).dot(&bu) * h.kernel.value(x, x)
        })
        .sum::<f64>()
        / model.len() as f64;
    let want = (1e-10 * mean_signal).sqrt();
    assert!(
        (h.sigma - want).abs() <= 1e-9 * want,
        "σ = {} against √(ε s̄) = {want}",
        h.sigma
    );
}

/// 30 pendulum observations with the first one repeated (without noise the
/// Gram matrix is singular, so the floor decides its smallest eigenvalue)
/// and a kernel variance of 2.5, with the warm fit settings that keep it.
fn floor_model() -> (Mvgp, FitSettings) {
    let mut model = pendulum_model(30, 4);
    let (x0, u0, xd0) = (
        model.xs()[..2].to_vec(),
        model.controls()[..1].to_vec(),
        model.xdot()[..2].to_vec(),
    );
    model.add_observation(&x0, &u0, &xd0).unwrap();
    let warm = kernel_variance(&mut model, 2.5);
    (model, warm)
}

/// The gradient through the floor: with `σ_f` driven to zero and one
/// observation repeated, the floor `ε s̄` is the Gram matrix's smallest
/// eigenvalue and `∂s̄/∂θ` (through `B` and the kernel) carries an O(1)
/// share of `−∇ log p`, which central differences check.
#[test]
fn the_gradient_follows_the_floor() {
    use bayes_cbf::gp::MvgpLikelihood;
    let (model, warm) = floor_model();
    let mut lik = MvgpLikelihood::new(&model, &warm).unwrap();
    let th = without_free_noise(&lik);
    let mut g = vec![0.0; lik.dim()];
    lik.evaluate(&th, &mut g).unwrap();
    let mut scratch = g.clone();
    // the near-singular Gram matrix puts rounding noise of ~10⁻⁶ on −log p:
    // a wide step, whose O(h²) error is ~10⁻⁵ relative here
    let h = 1e-3;
    let mut checked = 0;
    for i in 0..th.len() {
        if th[i] == -300.0 {
            continue;
        }
        let (mut tp, mut tm) = (th.clone(), th.clone());
        tp[i] += h;
        tm[i] -= h;
        let fd = (lik.evaluate(&tp, &mut scratch).unwrap()
            - lik.evaluate(&tm, &mut scratch).unwrap())
            / (2.0 * h);
        assert!(
            (fd - g[i]).abs() <= 1e-4 * (1.0 + fd.abs()),
            "parameter {i}: finite differences {fd}, analytic {}",
            g[i]
        );
        checked += 1;
    }
    assert_eq!(checked, th.len() - 1);
}

/// The evaluation applies the same floor: at `θ` with `σ_f` driven to
/// zero, `−log p(θ)` equals the negative log marginal likelihood of the
/// model with the hyperparameters `hyper(θ)` (whose `σ` is the floor). One
/// observation is repeated, so that the Gram matrix without noise is
/// singular and the floor decides its smallest eigenvalue.
#[test]
fn the_evaluation_and_the_hyperparameters_share_the_floor() {
    use bayes_cbf::gp::MvgpLikelihood;
    let (model, warm) = floor_model();
    let mut lik = MvgpLikelihood::new(&model, &warm).unwrap();
    let th = without_free_noise(&lik);
    let mut g = vec![0.0; lik.dim()];
    let neg = lik.evaluate(&th, &mut g).unwrap();
    let mut refit = model.clone();
    refit.set_hyper(lik.hyper(&th).unwrap()).unwrap();
    let want = -refit.log_marginal_likelihood();
    assert!(
        (neg - want).abs() <= 1e-6 * want.abs().max(1.0),
        "{neg} against {want}"
    );
}

/// The fit descends from the likelihood's documented start: one iteration
/// ends at or below `−log p` there (a start moved elsewhere, to the noise's
/// upper bound or by a perturbation, ends above it), and a fit with
/// restarts keeps the best of its starts, so it ends no higher either.
#[test]
fn the_fit_descends_from_the_documented_start() {
    use bayes_cbf::gp::MvgpLikelihood;
    for restarts in [0, 2] {
        let mut model = pendulum_model(40, 6);
        let settings = FitSettings {
            max_iters: 1,
            restarts,
            ..FitSettings::default()
        };
        let mut lik = MvgpLikelihood::new(&model, &settings).unwrap();
        let start = lik.start().to_vec();
        let mut g = vec![0.0; start.len()];
        let at_start = lik.evaluate(&start, &mut g).unwrap();
        drop(lik);
        fit(&mut model, &settings).unwrap();
        let end = -model.log_marginal_likelihood();
        assert!(
            end <= at_start + 1e-9 * at_start.abs(),
            "restarts {restarts}: −log p {end} after one iteration, {at_start} at the start"
        );
    }
}

/// A model whose Gram matrix does not factorise at its own noise: every
/// observation twice and `σ = 10⁻⁹`.
fn repeated_with_tiny_noise() -> Mvgp {
    let mut model = pendulum_model(20, 7);
    let mut h = model.hyper().clone();
    h.sigma = 1e-9;
    model.set_hyper(h).unwrap();
    repeat_every_observation(&mut model);
    model
}

/// Adds every observation of the model once more.
fn repeat_every_observation(model: &mut Mvgp) {
    let (xs, us, xd) = (
        model.xs().to_vec(),
        model.controls().to_vec(),
        model.xdot().to_vec(),
    );
    for j in 0..model.len() {
        model
            .add_observation(&xs[2 * j..2 * j + 2], &us[j..j + 1], &xd[2 * j..2 * j + 2])
            .unwrap();
    }
}

/// A warm start whose Gram matrix does not factorise starts again with ten
/// times the noise until it does, within the noise's bounds: with a warm
/// range of six decades the fit goes on from a start that factorises;
/// with one decade no noise level factorises and the fit says so (an
/// error, not a loop without end).
#[test]
fn a_start_that_does_not_factorise_gets_more_noise_within_its_bounds() {
    for (range, ok) in [(1e6, true), (10.0, false)] {
        let mut model = repeated_with_tiny_noise();
        let settings = FitSettings {
            max_iters: 1,
            warm_start: true,
            warm_range: range,
            learn_a: false,
            ..FitSettings::default()
        };
        let before = model.hyper().sigma;
        let r = fit(&mut model, &settings);
        assert_eq!(r.is_ok(), ok, "warm range {range}: {r:?}");
        if ok {
            assert!(model.hyper().sigma > 1e3 * before);
            // and the result factorises with its margin: no jitter
            assert_eq!(model.factor().max_jitter(), 0.0);
        } else {
            let e = r.unwrap_err().to_string();
            assert!(e.contains("finite likelihood"), "{e}");
        }
    }
}

/// The seed drives only the perturbed restarts: without restarts two seeds
/// give the same fit, bit for bit; with restarts (one iteration each, so
/// that where each start lies shows) they differ.
#[test]
fn the_seed_moves_the_restarts_only() {
    let run = |restarts: usize, seed: u64| {
        let mut model = pendulum_model(40, 6);
        let settings = FitSettings {
            max_iters: 1,
            restarts,
            seed,
            ..FitSettings::default()
        };
        fit(&mut model, &settings).unwrap();
        model.hyper().clone()
    };
    assert_eq!(run(0, 1), run(0, 2));
    assert_ne!(run(3, 1), run(3, 2));
}

/// The fit's result factorises with a margin: on exact repeats, where the
/// likelihood drives the noise to its floor, every pivot of the refitted
/// model keeps `L_jj² ≥ 4·10⁻¹⁰ G_jj` (four times the floor of an exact
/// factorisation), so the model's own roundoff needs no jitter.
#[test]
fn the_fitted_noise_leaves_the_pivots_a_margin() {
    let mut model = pendulum_model(20, 7);
    repeat_every_observation(&mut model);
    fit(&mut model, &FitSettings::default()).unwrap();
    let l = model.factor().l();
    let worst = (0..l.nrows())
        .map(|j| {
            let g: f64 = (0..=j).map(|i| l[(j, i)].powi(2)).sum();
            l[(j, j)].powi(2) / g
        })
        .fold(f64::INFINITY, f64::min);
    assert!(worst >= 3.9e-10, "smallest relative pivot {worst:e}");
    assert_eq!(model.factor().max_jitter(), 0.0);
}

/// A fit whose stop flag another thread sets ends with `Interrupted` soon
/// after, the model keeping its hyperparameters and data; a fit whose flag
/// stays clear is `fit` to the bit; a CoGP fit stopped before it starts
/// changes nothing either.
#[test]
fn a_stopped_fit_is_interrupted_and_changes_nothing() {
    use bayes_cbf::gp::{fit_cogp_until, fit_until, Cogp, CogpFitSettings, CogpHyper};
    use bayes_cbf::Error;
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::time::{Duration, Instant};

    let sys = Ackermann { wheelbase: 1.0 };
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (lo, hi) = ([-3.0, -3.0, -3.0], [3.0, 3.0, 3.0]);
    let data = sample_uniform(&sys, &lo, &hi, &[-1.0; 2], &[1.0; 2], 300, 0.01, &mut rng).unwrap();
    let fresh = || {
        let mut m = Mvgp::new(
            3,
            2,
            default_hyper(3, 3, 2),
            PriorMean::Zero,
            InputMap::Identity,
        )
        .unwrap();
        m.set_data(&data.xs, &data.us, &data.xdot).unwrap();
        m
    };
    let settings = FitSettings {
        restarts: 50,
        ..FitSettings::default()
    };
    let mut model = fresh();
    let before = model.hyper().clone();
    let stop = AtomicBool::new(false);
    let started = Instant::now();
    let (result, stopped_at) = std::thread::scope(|s| {
        s.spawn(|| {
            std::thread::sleep(Duration::from_millis(100));
            stop.store(true, Ordering::Relaxed);
        });
        let r = fit_until(&mut model, &settings, &stop);
        (r, started.elapsed())
    });
    assert_eq!(result.unwrap_err(), Error::Interrupted);
    // 51 starts of a 300-point fit take seconds; one evaluation, milliseconds
    assert!(stopped_at < Duration::from_secs(2), "{stopped_at:?}");
    assert_eq!(model.hyper(), &before);
    assert_eq!(model.len(), 300);

    let quick = FitSettings {
        max_iters: 5,
        ..FitSettings::default()
    };
    let (mut a, mut b) = (fresh(), fresh());
    let ra = fit(&mut a, &quick).unwrap();
    let rb = fit_until(&mut b, &quick, &AtomicBool::new(false)).unwrap();
    assert_eq!((ra, a.hyper()), (rb, b.hyper()));

    let hyper = CogpHyper {
        kernel: Rbf::new(vec![1.0; 3], 1.0).unwrap(),
        Sigma: DMatrix::identity(9, 9),
        S: DMatrix::identity(3, 3) * 0.01,
    };
    let mut cogp = Cogp::new(3, 2, hyper.clone(), PriorMean::Zero, InputMap::Identity).unwrap();
    cogp.set_data(&data.xs[..60], &data.us[..40], &data.xdot[..60])
        .unwrap();
    let r = fit_cogp_until(
        &mut cogp,
        &CogpFitSettings::default(),
        &AtomicBool::new(true),
    );
    assert_eq!(r.unwrap_err(), Error::Interrupted);
    assert_eq!(cogp.hyper(), &hyper);
}

/// More starts never give a worse model: each start's result is adjusted
/// to factorise with a margin (σ raised), which can cost it its lead, so
/// the fit compares the adjusted models. Noise-free linear data with three
/// controls, where the adjustment matters (seed 2: when the best start was
/// adjusted alone, three restarts gave 561.7 where one start gave 600.9).
#[test]
fn more_restarts_never_give_a_worse_model() {
    for seed in [1u64, 2, 3] {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let k = 50;
        let (mut xs, mut us, mut xdot) = (Vec::new(), Vec::new(), Vec::new());
        for _ in 0..k {
            let x: [f64; 2] = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
            let u: [f64; 3] = [
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            ];
            xs.extend_from_slice(&x);
            us.extend_from_slice(&u);
            xdot.extend_from_slice(&[x[1] + u[0] - u[2], -x[0] + u[1] + 0.5 * u[2]]);
        }
        let mut last = f64::NEG_INFINITY;
        for restarts in 0..6 {
            let mut model = zero_mean_model(2, 3, &xs, &us, &xdot);
            let report = fit(
                &mut model,
                &FitSettings {
                    restarts,
                    seed: 58311,
                    ..Default::default()
                },
            )
            .unwrap();
            assert_eq!(report.log_likelihood, model.log_marginal_likelihood());
            assert!(
                report.log_likelihood >= last,
                "seed {seed}: {restarts} restarts give {} < {last}",
                report.log_likelihood
            );
            last = report.log_likelihood;
        }
    }
}
