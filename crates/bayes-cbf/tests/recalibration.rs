//! The controller's online recalibration: an observation that moves the
//! condition's mean down by more than the certified bound widens the
//! condition's variance by exactly `κ²` in the SOCP, and one that does not
//! narrows it by `e^{−η(1−p)}`. (Closed loops under a wrong prior:
//! `bayes-cbf-scenario`'s quick calibration test.)

use bayes_cbf::barrier::{DynBarrier, PendulumSector};
use bayes_cbf::control::{ControlOutput, RecalibrationSettings, SafetyController, SafetySettings};
use bayes_cbf::gp::{InputMap, Mvgp, MvgpHyper, PriorMean, Rbf};
use bayes_cbf::systems::Pendulum;
use nalgebra::DMatrix;
use std::sync::Arc;

fn model(mass: f64, gravity: f64) -> Mvgp {
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![1.0; 3], 1.0).unwrap(),
        A: DMatrix::identity(2, 2) * 0.01,
        B: DMatrix::identity(2, 2),
        sigma: 0.02,
    };
    let prior = PriorMean::System(Arc::new(Pendulum {
        mass,
        length: 1.0,
        gravity,
    }));
    Mvgp::new(2, 1, hyper, prior, InputMap::periodic(2, &[0])).unwrap()
}

/// The sector barrier of relative degree 1 (`ḣ = sin(θ − θ_c) θ̇`).
fn controller() -> (SafetyController, Arc<dyn DynBarrier>) {
    let sector: Arc<dyn DynBarrier> =
        Arc::new(PendulumSector::new(0.785, 0.39, 1, vec![2.0]).unwrap());
    let mut s = SafetySettings::new(1);
    s.probability = 0.99;
    s.u_min = Some(vec![-20.0]);
    s.u_max = Some(vec![20.0]);
    (
        SafetyController::new(2, 1, vec![sector.clone()], None, s).unwrap(),
        sector,
    )
}

/// The controller keeps what it was built from, and says so.
#[test]
fn the_controller_reports_its_parts() {
    let (ctrl, sector) = controller();
    assert_eq!(ctrl.barriers().len(), 1);
    assert!(std::ptr::addr_eq(
        Arc::as_ptr(&ctrl.barriers()[0]),
        Arc::as_ptr(&sector)
    ));
    assert!(ctrl.clf().is_none());
    assert_eq!(ctrl.settings().probability, 0.99);
    let shown = format!("{ctrl:?}");
    assert!(
        shown.starts_with("SafetyController") && shown.contains("barriers: 1"),
        "{shown}"
    );
    let clf: Arc<dyn bayes_cbf::barrier::DynLyapunov> =
        Arc::new(bayes_cbf::barrier::AckermannClf::new(1.0, 1.0, 1.0).unwrap());
    let with_clf =
        SafetyController::new(3, 2, vec![], Some(clf.clone()), SafetySettings::new(2)).unwrap();
    assert!(std::ptr::addr_eq(
        Arc::as_ptr(with_clf.clf().unwrap()),
        Arc::as_ptr(&clf)
    ));
}

#[test]
fn a_miss_widens_the_conditions_variance_by_kappa_squared() {
    let (mut ctrl, _) = controller();
    ctrl.set_recalibration(Some(RecalibrationSettings::default()))
        .unwrap();
    let m = model(1.0, 10.0);
    let x = [1.6, -0.5];
    let mut out = ControlOutput::new(1, 1);
    // nothing learned: no update, κ = 1
    ctrl.step(&m, &x, &[0.0], None, &mut out).unwrap();
    ctrl.recalibrate(&m).unwrap();
    assert_eq!(ctrl.recalibrator().unwrap().counts(0), (0, 0));
    ctrl.step(&m, &x, &[0.0], None, &mut out).unwrap();
    let raw = ctrl.barrier_moments()[0].cov.clone();
    let u = out.u.clone();
    // an observation at x saying θ turns towards the sector much faster
    // than the model thinks (ḣ = sin(θ − θ_c) θ̇, sin > 0 here): the
    // condition's mean drops
    let mut learned = m.clone();
    learned.add_observation(&x, &u, &[-30.0, -10.0]).unwrap();
    ctrl.recalibrate(&learned).unwrap();
    let r = ctrl.recalibrator().unwrap();
    assert_eq!(r.counts(0), (1, 1));
    let kappa = r.inflation(0);
    assert!((kappa - (0.3f64 * 0.99).exp()).abs() < 1e-12, "{kappa}");
    // the next step with the same model sees κ² times the variance
    ctrl.step(&m, &x, &[0.0], None, &mut out).unwrap();
    let inflated = &ctrl.barrier_moments()[0].cov;
    for (a, b) in inflated.iter().zip(raw.iter()) {
        assert!(
            (a - kappa * kappa * b).abs() <= 1e-12 * b.abs().max(1e-300),
            "{a} {b}"
        );
    }
    // and so does the cone the SOCP is built from: vᵀv = Cov
    let v = &ctrl.barrier_moments()[0].v;
    let gap = (v.transpose() * v - inflated).amax();
    assert!(gap <= 1e-10 * inflated.amax(), "vᵀv − Cov: {gap}");
    // and a hit lowers κ by e^{−η(1−p)}
    let mut learned = m.clone();
    learned.add_observation(&x, &out.u, &[30.0, 0.0]).unwrap();
    ctrl.recalibrate(&learned).unwrap();
    let r = ctrl.recalibrator().unwrap();
    assert_eq!(r.counts(0), (1, 2));
    assert!((r.inflation(0) - kappa * (-0.3f64 * 0.01).exp()).abs() < 1e-12);
}

/// With the predictive condition the misses are still decided on the
/// latent condition: the innovation of a model update is in the posterior
/// of `F`, and at relative degree 2 the observation noise's share of the
/// variance, `σ² E[aᵀAa]`, shrinks with an update too. Over a sweep of
/// observations across the miss threshold, the controller's decisions equal
/// the rule applied to the latent moments computed here, both at `κ = 1`
/// and at `κ > 1` (after one miss), where the step's inflated variance must
/// be divided by `κ²` and the bound widened by `κ`.
#[test]
fn predictive_misses_are_decided_on_the_latent_condition() {
    use bayes_cbf::barrier::{cbc_moments, quantile_factor, ConditionMoments, MomentWorkspace};
    let sector: Arc<dyn DynBarrier> =
        Arc::new(PendulumSector::new(0.785, 0.39, 2, vec![1.0, 3.0]).unwrap());
    let mut s = SafetySettings::new(1);
    s.probability = 0.9;
    s.u_min = Some(vec![-20.0]);
    s.u_max = Some(vec![20.0]);
    s.predictive = true;
    let mut m = model(1.0, 10.0);
    let mut hyper = m.hyper().clone();
    hyper.sigma = 10.0; // noise of the order of the posterior's spread
    m.set_hyper(hyper).unwrap();
    let x = [1.2, 0.4];
    let c = quantile_factor(0.9, 2).unwrap();
    let latent = |model: &Mvgp, u: &[f64]| {
        let mut ws = MomentWorkspace::new(model);
        ws.update(model, &x, 2).unwrap();
        let mut mom = ConditionMoments::zeros(1);
        cbc_moments(&mut ws, sector.as_ref(), &mut mom).unwrap();
        (mom.mean(u), mom.variance(u))
    };
    let mut decisions = [[0usize; 2]; 2];
    let mut noise: f64 = 0.0;
    // from κ = 1, and from κ > 1 after one large miss: the decision divides
    // the inflation out of the variance
    for (i, inflated) in (0..81).flat_map(|i| [(i, false), (i, true)]) {
        let mut ctrl = SafetyController::new(2, 1, vec![sector.clone()], None, s.clone()).unwrap();
        ctrl.set_recalibration(Some(RecalibrationSettings::default()))
            .unwrap();
        let mut out = ControlOutput::new(1, 1);
        if inflated {
            ctrl.step(&m, &x, &[0.0], None, &mut out).unwrap();
            // the low end of the sweep below: a miss
            let mut far = m.clone();
            let wdot = -10.0 * x[0].sin() + out.u[0] - 12.0;
            far.add_observation(&x, &out.u, &[0.4, wdot]).unwrap();
            ctrl.recalibrate(&far).unwrap();
            let kappa = ctrl.recalibrator().unwrap().inflation(0);
            assert!(kappa > 1.2, "{kappa}");
        }
        ctrl.step(&m, &x, &[0.0], None, &mut out).unwrap();
        let u = out.u.clone();
        let mut learned = m.clone();
        // around the prior's prediction ω̇ = −(g/l) sin θ + u/(m l²)
        // (further down from κ > 1, whose bound is wider)
        let offset = if inflated {
            -20.0 + 0.3 * i as f64
        } else {
            -12.0 + 0.2 * i as f64
        };
        let wdot = -10.0 * x[0].sin() + u[0] + offset;
        learned.add_observation(&x, &u, &[0.4, wdot]).unwrap();
        let kappa = ctrl.recalibrator().unwrap().inflation(0);
        ctrl.recalibrate(&learned).unwrap();
        let (e, v) = latent(&m, &u);
        let (e1, v1) = latent(&learned, &u);
        let (misses, updates) = ctrl.recalibrator().unwrap().counts(0);
        let (misses, updates) = (
            misses - usize::from(inflated),
            updates - usize::from(inflated),
        );
        if !inflated {
            noise = noise.max(ctrl.barrier_moments()[0].variance(&u) - v);
        }
        if v <= v1 {
            // the update explained no variance of the condition (its mean
            // moved, and the variance of a quadratic form with it): no
            // decision
            assert_eq!(updates, 0, "ω̇ = {wdot}");
            continue;
        }
        // a miss falls below the bound widened by the current κ
        let want = e1 - e < -c * kappa * (v - v1).sqrt();
        assert_eq!(updates, 1, "ω̇ = {wdot}");
        assert_eq!(
            misses == 1,
            want,
            "ω̇ = {wdot}, κ = {kappa}: innovation {} vs {}",
            e1 - e,
            c * kappa * (v - v1).sqrt()
        );
        decisions[usize::from(inflated)][usize::from(want)] += 1;
    }
    // the sweep crosses the threshold, and the noise is a large share
    assert!(decisions.iter().flatten().all(|&d| d > 0), "{decisions:?}");
    assert!(noise > 0.2, "{noise}");
}
