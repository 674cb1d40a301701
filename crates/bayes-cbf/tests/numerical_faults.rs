//! Numerical faults: near-singular Gram matrices (duplicate and
//! near-duplicate training points, nearly noise-free data), extreme
//! hyperparameters (lengthscales 1e-6 and 1e6, σ = 1e-10) and states far
//! outside the data.
//!
//! What must hold (SPEC "Reliability"):
//! - the posterior covariance `B_k(x, x') ⊗ A` stays positive semi-definite:
//!   the smallest eigenvalue of the stacked `[B_k(x_a, x_b)]_ab` over a few
//!   points (and of the joint covariance `Ĉ` of `F` and its Jacobian) is
//!   `≥ −1e-9 ×` its largest (roundoff only; `A` is positive definite, so
//!   the Kronecker product is PSD iff the stacked `B_k` is);
//! - the jitter added to the Gram matrix is bounded by the last level of
//!   [`JITTER_LEVELS`] (1e-6 × the mean diagonal) and reported: the factor
//!   records it ([`CholFactor::jitter`]) and a `log::warn!` says so;
//! - the safety controller returns a typed outcome: `Ok` with a status and a
//!   finite control within the bounds, or a typed `Err` — never a panic,
//!   never a NaN control.

use bayes_cbf::barrier::{DynBarrier, HalfSpace, PendulumSector};
use bayes_cbf::control::{ControlOutput, ControlStatus, SafetyController, SafetySettings};
use bayes_cbf::gp::{
    fit, FitSettings, InputMap, Kernel, Mvgp, MvgpHyper, PriorMean, Rbf, JITTER_LEVELS,
};
use bayes_cbf::sim::{ClosedLoop, ConstantReference, DataPolicy, LoopSettings};
use bayes_cbf::systems::{DynSystem, Pendulum};
use bayes_cbf::Error;
use nalgebra::DMatrix;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::cell::RefCell;
use std::sync::{Arc, Once};

// ---------------------------------------------------------------- logging

thread_local! {
    /// Warnings logged on this thread (each test runs on its own thread).
    static WARNINGS: RefCell<Vec<String>> = const { RefCell::new(Vec::new()) };
}

struct CaptureLogger;

impl log::Log for CaptureLogger {
    fn enabled(&self, m: &log::Metadata<'_>) -> bool {
        m.level() <= log::Level::Warn
    }
    fn log(&self, r: &log::Record<'_>) {
        if self.enabled(r.metadata()) {
            WARNINGS.with(|w| w.borrow_mut().push(r.args().to_string()));
        }
    }
    fn flush(&self) {}
}

static LOGGER: CaptureLogger = CaptureLogger;

/// Installs the capturing logger (once) and clears this thread's warnings.
fn capture_warnings() {
    static INIT: Once = Once::new();
    INIT.call_once(|| {
        let _ = log::set_logger(&LOGGER);
        log::set_max_level(log::LevelFilter::Warn);
    });
    WARNINGS.with(|w| w.borrow_mut().clear());
}

fn warnings() -> Vec<String> {
    WARNINGS.with(|w| w.borrow().clone())
}

/// Held by the tests that update a model online: the online-jitter warning
/// is issued once per scope ([`bayes_cbf::warnings`]), which a test opens
/// for itself while no other can take the warning first.
static ONLINE: std::sync::Mutex<()> = std::sync::Mutex::new(());

// ---------------------------------------------------------------- models

const TRUTH: Pendulum = Pendulum {
    mass: 1.0,
    length: 1.0,
    gravity: 10.0,
};

/// A pendulum model: prior mean with the wrong mass and length, kernel on
/// `(cos θ, sin θ, ω)` with lengthscale `ell`, noise `sigma`.
#[allow(non_snake_case)]
fn model(ell: f64, sigma: f64) -> Mvgp {
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![ell; 3], 1.0).unwrap(),
        A: DMatrix::from_row_slice(2, 2, &[1.0, 0.2, 0.2, 0.5]),
        B: DMatrix::from_row_slice(2, 2, &[1.0, 0.3, 0.3, 2.0]),
        sigma,
    };
    let prior = PriorMean::System(Arc::new(Pendulum {
        mass: 2.0,
        length: 0.5,
        gravity: 10.0,
    }));
    Mvgp::new(2, 1, hyper, prior, InputMap::periodic(2, &[0])).unwrap()
}

/// [`model`] conditioned on `data`.
fn model_on(ell: f64, sigma: f64, (xs, us, xdot): &(Vec<f64>, Vec<f64>, Vec<f64>)) -> Mvgp {
    let mut m = model(ell, sigma);
    m.set_data(xs, us, xdot).unwrap();
    m
}

/// `k` noise-free observations of the true pendulum at random states.
fn data(k: usize, seed: u64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (mut xs, mut us, mut xdot) = (Vec::new(), Vec::new(), Vec::new());
    let mut f = [0.0; 4];
    for _ in 0..k {
        let x = [rng.random_range(-3.0..3.0), rng.random_range(-4.0..4.0)];
        let u = rng.random_range(-5.0..5.0);
        TRUTH.eval_f64(&x, &mut f);
        xs.extend(x);
        us.push(u);
        xdot.extend([f[0] + f[2] * u, f[1] + f[3] * u]);
    }
    (xs, us, xdot)
}

/// `data` with every point repeated `copies` times, the copies displaced
/// by `offset` in θ (0: exact duplicates).
fn duplicated(k: usize, copies: usize, offset: f64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let (xs, us, xdot) = data(k, 1);
    let (mut x2, mut u2, mut d2) = (Vec::new(), Vec::new(), Vec::new());
    for j in 0..k {
        for c in 0..copies {
            x2.extend([xs[2 * j] + c as f64 * offset, xs[2 * j + 1]]);
            u2.push(us[j]);
            d2.extend(&xdot[2 * j..2 * j + 2]);
        }
    }
    (x2, u2, d2)
}

/// States where the posterior is probed: on the data, between, and far
/// outside it (ω far beyond the data's ±4 rad/s; θ = 1e6 is just an angle).
fn probes() -> Vec<[f64; 2]> {
    let (xs, _, _) = data(3, 1);
    vec![
        [xs[0], xs[1]],
        [xs[2] + 1e-7, xs[3]],
        [0.1, 0.2],
        [2.5, -3.9],
        [0.3, 60.0],
        [1e6, -1e3],
        [-0.7, 1e150],
    ]
}

// ---------------------------------------------------------------- checks

/// Smallest eigenvalue over largest magnitude of a symmetric matrix.
fn min_eig_ratio(c: &DMatrix<f64>) -> f64 {
    let sym = (c + c.transpose()) * 0.5;
    let ev = sym.symmetric_eigenvalues();
    let max = ev.iter().fold(0.0f64, |a, b| a.max(b.abs()));
    let min = ev.iter().cloned().fold(f64::INFINITY, f64::min);
    if max == 0.0 {
        0.0
    } else {
        min / max
    }
}

/// The posterior is finite and PSD at every probe and jointly over them.
fn assert_posterior_psd(model: &Mvgp, label: &str) {
    let pts = probes();
    let p = model.control_dim() + 1;
    let np = pts.len() * p;
    let mut stacked = DMatrix::zeros(np, np);
    for (a, xa) in pts.iter().enumerate() {
        let post = model.posterior(xa).unwrap();
        assert!(
            post.mean.iter().chain(post.B.iter()).all(|v| v.is_finite()),
            "{label}: non-finite posterior at {xa:?}: {post:?}"
        );
        let r = min_eig_ratio(&post.B);
        assert!(
            r >= -1e-9,
            "{label}: B_k({xa:?}) has eigenvalue ratio {r:e}"
        );
        for (b, xb) in pts.iter().enumerate() {
            let c = model.posterior_cov(xa, xb).unwrap();
            for i in 0..p {
                for j in 0..p {
                    stacked[(a * p + i, b * p + j)] = c[(i, j)];
                }
            }
        }
        // F and its Jacobian jointly (relative degree 2 uses it)
        let mut ws = model.joint_workspace();
        let mut joint =
            bayes_cbf::gp::JointPosterior::zeros(model.state_dim(), model.control_dim());
        model.joint_posterior_into(xa, &mut ws, &mut joint).unwrap();
        assert!(
            joint
                .c
                .iter()
                .chain(joint.mean.iter())
                .all(|v| v.is_finite()),
            "{label}: non-finite joint posterior at {xa:?}"
        );
        let r = min_eig_ratio(&joint.c);
        assert!(
            r >= -1e-9,
            "{label}: joint Ĉ at {xa:?} has eigenvalue ratio {r:e}"
        );
    }
    let r = min_eig_ratio(&stacked);
    assert!(
        r >= -1e-9,
        "{label}: stacked B_k over the probes: eigenvalue ratio {r:e}"
    );
    // the posterior variance never exceeds the prior's (data only inform)
    for x in &pts {
        let post = model.posterior(x).unwrap();
        let mut z = vec![0.0; model.input_map().output_dim(2)];
        model.input_map().apply(x, &mut z);
        let k0 = model.hyper().kernel.value(&z, &z);
        for c in 0..p {
            assert!(
                post.B[(c, c)] <= model.hyper().B[(c, c)] * k0 * (1.0 + 1e-9),
                "{label}: posterior variance above the prior at {x:?}"
            );
        }
    }
}

/// The jitter in use is bounded by the last level × the Gram matrix's mean
/// diagonal (each entry's own diagonal for online growth).
fn assert_jitter_bounded(model: &Mvgp, label: &str) -> f64 {
    let f = model.factor();
    let max_level = *JITTER_LEVELS.last().unwrap();
    // the diagonal of G: u̲ᵀ B u̲ k0(x, x) + σ²
    let (p, s) = (model.control_dim() + 1, model.hyper().sigma);
    let us = model.augmented_controls();
    let bu = model.bu();
    let kxx = model.hyper().kernel.value(&[0.0; 3], &[0.0; 3]);
    let max_diag = (0..model.len())
        .map(|j| (0..p).map(|c| us[j * p + c] * bu[j * p + c]).sum::<f64>() * kxx + s * s)
        .fold(0.0f64, f64::max);
    assert!(
        f.max_jitter() <= max_level * max_diag * (1.0 + 1e-12),
        "{label}: jitter {} above {max_level:e} × {max_diag}",
        f.max_jitter()
    );
    assert_eq!(f.jitter().len(), model.len());
    f.max_jitter()
}

/// The controller's outcome is typed: `Ok` with a finite control within the
/// bounds and a status, or an `Err`; returns the status name.
fn control_outcome(
    ctrl: &mut SafetyController,
    model: &Mvgp,
    x: &[f64],
    bounds: (f64, f64),
) -> &'static str {
    let mut out = ControlOutput::new(1, 1);
    match ctrl.step(model, x, &[15.0], None, &mut out) {
        Ok(()) => {
            let u = out.u[0];
            assert!(u.is_finite(), "NaN control at {x:?}: {out:?}");
            assert!(
                u >= bounds.0 - 1e-6 && u <= bounds.1 + 1e-6,
                "control {u} outside the bounds at {x:?}"
            );
            match out.status {
                ControlStatus::Optimal => "optimal",
                ControlStatus::AlmostOptimal => "almost_optimal",
                ControlStatus::Infeasible(ref info) => {
                    if let Some(p) = info.p_star {
                        assert!(p > 0.0 && p < 1.0, "p* = {p}");
                    }
                    "infeasible"
                }
            }
        }
        Err(Error::Input(_)) => "input_error",
        Err(Error::Gp(_)) => "gp_error",
        Err(e) => panic!("unexpected error kind: {e}"),
    }
}

fn controllers() -> Vec<(&'static str, SafetyController)> {
    let mut settings = SafetySettings::new(1);
    settings.u_min = Some(vec![-20.0]);
    settings.u_max = Some(vec![20.0]);
    let sector: Arc<dyn DynBarrier> =
        Arc::new(PendulumSector::new(0.785, 0.39, 2, vec![1.0, 3.0]).unwrap());
    // h = 2 − ω: relative degree 1 in ω
    let half: Arc<dyn DynBarrier> =
        Arc::new(HalfSpace::new(vec![0.0, -1.0], -2.0, 1, vec![1.0]).unwrap());
    vec![
        (
            "sector r=2 p=0.99",
            SafetyController::new(2, 1, vec![sector.clone()], None, settings.clone()).unwrap(),
        ),
        (
            "half-space r=1 p=0.999",
            SafetyController::new(
                2,
                1,
                vec![half],
                None,
                SafetySettings {
                    probability: 0.999,
                    ..settings.clone()
                },
            )
            .unwrap(),
        ),
        (
            "sector r=2 p=0.5 brake",
            SafetyController::new(
                2,
                1,
                vec![sector],
                None,
                SafetySettings {
                    probability: 0.5,
                    fallback: bayes_cbf::control::Fallback::Brake,
                    ..settings
                },
            )
            .unwrap(),
        ),
    ]
}

/// Posterior PSD, jitter bounded, and typed control outcomes at every probe.
fn check_all(model: &Mvgp, label: &str) -> Vec<&'static str> {
    assert_posterior_psd(model, label);
    assert_jitter_bounded(model, label);
    let mut statuses = Vec::new();
    for (name, mut ctrl) in controllers() {
        for x in probes() {
            let s = control_outcome(&mut ctrl, model, &x, (-20.0, 20.0));
            assert_ne!(s, "gp_error", "{label} / {name} at {x:?}");
            statuses.push(s);
        }
    }
    statuses
}

// ---------------------------------------------------------------- tests

#[test]
fn exact_duplicates_with_tiny_noise_need_bounded_reported_jitter() {
    capture_warnings();
    let data = duplicated(40, 5, 0.0);
    let m = model_on(1.0, 1e-10, &data);
    let (xs, us, xdot) = data;
    assert_eq!(m.len(), 200);
    let jit = assert_jitter_bounded(&m, "duplicates");
    assert!(
        jit > 0.0,
        "a rank-deficient Gram matrix with σ = 1e-10 needs jitter"
    );
    let w = warnings();
    assert!(
        w.iter().any(|s| s.contains("needed jitter")),
        "jitter not reported: {w:?}"
    );
    check_all(&m, "exact duplicates, σ = 1e-10");
    // the posterior still interpolates the (consistent) duplicated data
    let post = m.posterior(&[xs[0], xs[1]]).unwrap();
    let pred = post.mean[(1, 0)] + post.mean[(1, 1)] * us[0];
    assert!((pred - xdot[1]).abs() < 1e-3, "{pred} vs {}", xdot[1]);
}

#[test]
fn near_duplicates_online_and_batch_agree_and_stay_psd() {
    let _online = ONLINE.lock().unwrap_or_else(|e| e.into_inner());
    bayes_cbf::warnings::new_scope();
    capture_warnings();
    let (xs, us, xdot) = duplicated(30, 4, 1e-9);
    let mut batch = model(0.7, 1e-8);
    batch.set_data(&xs, &us, &xdot).unwrap();
    check_all(&batch, "near duplicates (1e-9 apart), batch");
    // the same data one observation at a time (O(k²) growth)
    let mut online = model(0.7, 1e-8);
    let mut skipped = 0;
    for j in 0..us.len() {
        match online.add_observation(
            &xs[2 * j..2 * j + 2],
            &us[j..j + 1],
            &xdot[2 * j..2 * j + 2],
        ) {
            Ok(()) => {}
            Err(Error::Gp(_)) => skipped += 1,
            Err(e) => panic!("{e}"),
        }
    }
    assert_eq!(online.len() + skipped, us.len());
    check_all(&online, "near duplicates (1e-9 apart), online");
    assert!(
        warnings().iter().any(|s| s.contains("online update")),
        "online jitter not reported"
    );
    // both give the same prediction away from the data to well within the
    // prior scale (jitter differs: batch adds it uniformly, online per entry)
    let (pb, po) = (
        batch.posterior(&[0.1, 0.2]).unwrap(),
        online.posterior(&[0.1, 0.2]).unwrap(),
    );
    assert!((&pb.mean - &po.mean).abs().max() < 1e-2, "{pb:?} {po:?}");
    // sliding window down to a few points keeps the factor consistent
    for _ in 0..online.len() - 3 {
        online.remove_oldest();
    }
    check_all(&online, "near duplicates, window of 3");
}

#[test]
fn extreme_lengthscales_and_noise() {
    let (xs, us, xdot) = data(150, 2);
    for (ell, sigma) in [
        (1e-6, 1e-10),
        (1e6, 1e-10),
        (1e6, 1e-3),
        (1e-6, 1.0),
        (1.0, 1e-10),
    ] {
        capture_warnings();
        let mut m = model(ell, sigma);
        let label = format!("ℓ = {ell:e}, σ = {sigma:e}");
        match m.set_data(&xs, &us, &xdot) {
            Ok(()) => {}
            Err(e) => panic!("{label}: factorisation failed ({e}) where bounded jitter suffices"),
        }
        let statuses = check_all(&m, &label);
        if ell >= 1e6 && sigma < 1e-6 {
            // the kernel is constant: K has rank 1 + m = 2 at k = 150
            assert!(m.factor().max_jitter() > 0.0, "{label}");
            assert!(
                warnings().iter().any(|s| s.contains("needed jitter")),
                "{label}"
            );
        }
        if ell <= 1e-6 {
            // every point is uncorrelated with every other: the posterior
            // away from the data is the prior
            let p = m.posterior(&[0.1, 0.2]).unwrap();
            let mut m0 = [0.0; 4];
            m.prior().eval(&[0.1, 0.2], &mut m0);
            for c in 0..2 {
                for i in 0..2 {
                    assert!((p.mean[(i, c)] - m0[i + 2 * c]).abs() < 1e-12, "{label}");
                }
            }
            assert!((&p.B - &m.hyper().B).abs().max() < 1e-12, "{label}");
        }
        eprintln!("{label}: statuses {statuses:?}");
    }
}

#[test]
fn states_far_outside_the_data_revert_to_the_prior() {
    let m = model_on(1.0, 1e-3, &data(100, 3));
    for x in [[0.3, 60.0], [-0.7, 1e150], [0.0, -1e300]] {
        let p = m.posterior(&x).unwrap();
        let mut m0 = [0.0; 4];
        m.prior().eval(&x, &mut m0);
        for c in 0..2 {
            for i in 0..2 {
                assert!((p.mean[(i, c)] - m0[i + 2 * c]).abs() < 1e-9, "{x:?}");
            }
        }
        assert!((&p.B - &m.hyper().B).abs().max() < 1e-9, "{x:?}: {}", p.B);
    }
    // non-finite states are typed input errors, for the model and controller
    assert!(m.posterior(&[f64::NAN, 0.0]).is_err());
    assert!(m.posterior(&[0.0, f64::INFINITY]).is_err());
    for (name, mut ctrl) in controllers() {
        let s = control_outcome(&mut ctrl, &m, &[f64::NAN, 0.0], (-20.0, 20.0));
        assert_eq!(s, "input_error", "{name}");
        let s = control_outcome(&mut ctrl, &m, &[0.2, f64::NEG_INFINITY], (-20.0, 20.0));
        assert_eq!(s, "input_error", "{name}");
    }
}

/// A fit that cannot set a lengthscale from the data warns: an input that
/// is the same in every row (ω held at 0.7) keeps its lengthscale's start,
/// and the model reverts to the prior away from that value. A fit on data
/// that vary in every input says nothing.
#[test]
fn a_fit_that_cannot_learn_a_lengthscale_warns() {
    let settings = FitSettings {
        max_iters: 30,
        ..FitSettings::default()
    };
    let fitted = |(xs, us, xdot): (Vec<f64>, Vec<f64>, Vec<f64>)| {
        capture_warnings();
        bayes_cbf::warnings::new_scope();
        let mut m = model_on(1.0, 0.1, &(xs, us, xdot));
        fit(&mut m, &settings).unwrap();
        warnings()
            .into_iter()
            .filter(|w| w.contains("kernel input"))
            .collect::<Vec<_>>()
    };
    assert!(fitted(data(40, 3)).is_empty());
    let (mut xs, us, mut xdot) = data(40, 3);
    for j in 0..40 {
        xs[2 * j + 1] = 0.7;
        let mut f = [0.0; 4];
        TRUTH.eval_f64(&xs[2 * j..2 * j + 2], &mut f);
        xdot[2 * j..2 * j + 2].copy_from_slice(&[f[0] + f[2] * us[j], f[1] + f[3] * us[j]]);
    }
    let w = fitted((xs, us, xdot));
    // the kernel sees (cos θ, sin θ, ω): ω is input 2
    assert!(
        w.len() == 1 && w[0].contains("kernel input 2 takes one value in every row"),
        "{w:?}"
    );
}

#[test]
fn fitting_duplicated_noise_free_data_is_typed_and_leaves_a_usable_model() {
    capture_warnings();
    let mut m = model_on(1.0, 1e-6, &duplicated(25, 4, 0.0));
    let before = m.hyper().clone();
    let settings = FitSettings {
        max_iters: 30,
        sigma_min: 0.0,
        ..FitSettings::default()
    };
    match fit(&mut m, &settings) {
        Ok(report) => {
            assert!(report.log_likelihood.is_finite(), "{report:?}");
        }
        Err(e) => {
            // a typed error keeps the previous hyperparameters
            assert!(matches!(e, Error::Gp(_)), "{e}");
            assert_eq!(m.hyper(), &before);
        }
    }
    check_all(&m, "fitted on duplicated noise-free data");
}

#[test]
fn closed_loop_at_rest_piles_up_duplicates_without_nan() {
    // the pendulum hangs near rest with u ≈ 0: the observations are
    // near-duplicates (x ≈ 0, u ≈ 0, ẋ ≈ 0) and the model noise is 1e-9.
    // Regression: with a pivot floor of 1e-14 the online factor absorbed
    // pivots within roundoff of zero and tr(B_k ⊗ A) reached −6·10⁴ × the
    // prior's (see `MIN_PIVOT` in gp/factor.rs)
    let _online = ONLINE.lock().unwrap_or_else(|e| e.into_inner());
    capture_warnings();
    let truth = TRUTH;
    let sector: Arc<dyn DynBarrier> =
        Arc::new(PendulumSector::new(0.785, 0.39, 2, vec![1.0, 3.0]).unwrap());
    let mut settings = SafetySettings::new(1);
    settings.u_min = Some(vec![-20.0]);
    settings.u_max = Some(vec![20.0]);
    let mut ctrl = SafetyController::new(2, 1, vec![sector.clone()], None, settings).unwrap();
    let ls = LoopSettings {
        steps: 300,
        update_every: 1,
        data: DataPolicy::Window(200),
        ..LoopSettings::default()
    };
    let barriers = [sector];
    let mut reference = ConstantReference(vec![0.0]);
    let r = ClosedLoop::new(
        &truth,
        model(1.0, 1e-9),
        &mut ctrl,
        &barriers,
        &mut reference,
        &[0.0, 0.0],
        &ls,
    )
    .unwrap()
    .run(&mut |_, _: &_| {})
    .unwrap();
    let prior_trace = 3.0 * 1.5;
    let worst = r
        .records
        .iter()
        .map(|rec| rec.trace_cov / prior_trace)
        .fold(f64::INFINITY, f64::min);
    eprintln!("smallest tr(B_k ⊗ A) / prior: {worst:e}");
    for rec in &r.records {
        assert!(
            rec.u.iter().all(|u| u.is_finite()),
            "step at t = {}: {rec:?}",
            rec.t
        );
        assert!(
            rec.trace_cov.is_finite() && rec.trace_cov >= -1e-9 * prior_trace,
            "{rec:?}"
        );
        assert!(
            rec.h.iter().chain(&rec.scbc).all(|v| v.is_finite()),
            "{rec:?}"
        );
    }
    assert!(r.model.len() <= 200);
    // the prior's first steps are infeasible (max-margin fallback, small
    // torques); afterwards the pendulum stays near rest
    assert!(
        r.final_state.iter().all(|v| v.abs() < 0.05),
        "{:?}",
        r.final_state
    );
    assert_jitter_bounded(&r.model, "closed loop at rest");
    assert!(r.model.factor().max_jitter() > 0.0);
    assert_posterior_psd(&r.model, "closed loop at rest");
}
