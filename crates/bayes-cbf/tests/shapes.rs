//! Pieces made for systems of different shapes meet as errors naming the
//! piece, never as a panic: references, checked barriers, controllers and
//! workspaces reused with another model, and the simulator.

use bayes_cbf::barrier::{DynBarrier, HalfSpace, MomentWorkspace};
use bayes_cbf::control::{ControlOutput, SafetyController, SafetySettings};
use bayes_cbf::gp::{InputMap, Mvgp, MvgpHyper, Posterior, PriorMean, Rbf};
use bayes_cbf::sim::{
    ClosedLoop, ConstantReference, EpsilonGreedy, LinearFeedback, LoopSettings, Reference,
    ReferenceOut, StraightLinePlanner,
};
use bayes_cbf::systems::{Ackermann, Pendulum};
use nalgebra::DMatrix;
use rand_chacha::ChaCha8Rng;
use std::sync::Arc;

/// A zero-mean model with `n` states and `m` controls, `k` observations.
fn model(n: usize, m: usize, k: usize) -> Mvgp {
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![1.0; n], 1.0).unwrap(),
        A: DMatrix::identity(n, n),
        B: DMatrix::identity(m + 1, m + 1),
        sigma: 0.1,
    };
    let mut g = Mvgp::new(n, m, hyper, PriorMean::Zero, InputMap::Identity).unwrap();
    for j in 0..k {
        let x: Vec<f64> = (0..n).map(|i| 0.1 * (i + j) as f64).collect();
        let u: Vec<f64> = (0..m).map(|i| 0.2 * (i + 2 * j) as f64 - 0.3).collect();
        let xdot: Vec<f64> = (0..n).map(|i| (x[i] + 1.0).sin()).collect();
        g.add_observation(&x, &u, &xdot).unwrap();
    }
    g
}

fn half_space(n: usize) -> Arc<dyn DynBarrier> {
    let mut normal = vec![0.0; n];
    normal[0] = -1.0;
    Arc::new(HalfSpace::new(normal, 2.0, 1, vec![1.0]).unwrap())
}

/// A closed loop of the pendulum (n = 2, m = 1) with `reference` and the
/// checked `barriers`: the error of building it and taking one step.
fn pendulum_loop(
    reference: &mut dyn Reference,
    barriers: &[Arc<dyn DynBarrier>],
) -> Result<(), bayes_cbf::Error> {
    let truth = Pendulum::default();
    let mut ctrl =
        SafetyController::new(2, 1, vec![half_space(2)], None, SafetySettings::new(1)).unwrap();
    let settings = LoopSettings {
        steps: 2,
        ..LoopSettings::default()
    };
    let mut lp = ClosedLoop::new(
        &truth,
        model(2, 1, 3),
        &mut ctrl,
        barriers,
        reference,
        &[0.1, 0.0],
        &settings,
    )?;
    lp.step().map(|_| ())
}

fn message(r: Result<(), bayes_cbf::Error>) -> String {
    r.expect_err("an error, not a run").to_string()
}

#[test]
fn references_of_another_shape_are_errors() {
    let fine = [half_space(2)];
    // the pendulum has one control and two states
    let cases: Vec<(Box<dyn Reference>, &str)> = vec![
        (
            Box::new(ConstantReference(vec![0.0; 3])),
            "reference control",
        ),
        (
            Box::new(EpsilonGreedy::new(vec![-1.0; 2], vec![1.0; 2], 50.0).unwrap()),
            "epsilon_greedy.lo",
        ),
        (
            Box::new(StraightLinePlanner::new(vec![0.0; 3], vec![1.0; 3], 1.0).unwrap()),
            "planner.start",
        ),
        // public fields: struct literals whose second vector is short
        (
            Box::new(EpsilonGreedy {
                lo: vec![-1.0],
                hi: vec![],
                decay: 50.0,
            }),
            "epsilon_greedy.hi",
        ),
        (
            Box::new(StraightLinePlanner {
                start: vec![0.0; 2],
                goal: vec![1.0],
                duration: 1.0,
            }),
            "planner.goal",
        ),
        (
            Box::new(
                LinearFeedback::new(
                    vec![0.0; 2],
                    &[vec![1.0; 2], vec![1.0; 2]],
                    vec![0.0; 2],
                    vec![],
                )
                .unwrap(),
            ),
            "feedback.u0",
        ),
        (
            Box::new(
                LinearFeedback::new(vec![0.0], &[vec![1.0; 4]], vec![0.0; 4], vec![]).unwrap(),
            ),
            "feedback.target",
        ),
    ];
    for (mut r, field) in cases {
        let e = message(pendulum_loop(r.as_mut(), &fine));
        assert!(e.contains(field), "{field}: {e}");
    }
    // a reference that replaces its vectors is caught at the step
    struct Replacing;
    impl Reference for Replacing {
        fn at(&mut self, _: usize, _: f64, _: &[f64], _: &mut ChaCha8Rng, out: &mut ReferenceOut) {
            out.xd = vec![0.0; 5];
        }
    }
    let e = message(pendulum_loop(&mut Replacing, &fine));
    assert!(e.contains("reference x_d"), "{e}");
    // and the right shapes run
    pendulum_loop(&mut ConstantReference(vec![0.0]), &fine).unwrap();
}

#[test]
fn checked_barriers_of_another_state_dimension_are_errors() {
    for n in [1, 3, 5] {
        let barriers = [half_space(2), half_space(n)];
        let e = message(pendulum_loop(&mut ConstantReference(vec![0.0]), &barriers));
        assert!(e.contains("barriers[1] state dimension"), "{n}: {e}");
    }
}

/// A controller and a moment workspace that served one model serve a
/// model of another shape as a fresh one would: an error where the
/// barriers do not fit it, the same numbers where they do.
#[test]
fn workspaces_follow_the_model_they_are_given() {
    let mut ctrl =
        SafetyController::new(4, 2, vec![half_space(4)], None, SafetySettings::new(2)).unwrap();
    let mut out = ControlOutput::new(2, 1);
    ctrl.step(&model(4, 2, 5), &[0.1; 4], &[0.0; 2], None, &mut out)
        .unwrap();
    let e = ctrl
        .step(&model(3, 2, 5), &[0.1; 3], &[0.0; 2], None, &mut out)
        .unwrap_err()
        .to_string();
    let fresh = SafetyController::new(4, 2, vec![half_space(4)], None, SafetySettings::new(2))
        .unwrap()
        .step(&model(3, 2, 5), &[0.1; 3], &[0.0; 2], None, &mut out)
        .unwrap_err()
        .to_string();
    assert_eq!(e, fresh);

    // a posterior workspace of a 4-state model, used for 2 and 3 states
    let big = model(4, 2, 6);
    let mut ws = big.workspace();
    let mut post = Posterior {
        mean: DMatrix::zeros(1, 1),
        B: DMatrix::zeros(1, 1),
    };
    big.posterior_into(&[0.3; 4], &mut ws, &mut post).unwrap();
    for (n, m) in [(2, 1), (3, 3)] {
        let g = model(n, m, 4);
        let x = vec![0.25; n];
        g.posterior_into(&x, &mut ws, &mut post).unwrap();
        assert_eq!(post, g.posterior(&x).unwrap(), "n = {n}, m = {m}");
        let mut mws = MomentWorkspace::new(&big);
        mws.update(&g, &x, 2).unwrap();
        let mut fresh = MomentWorkspace::new(&g);
        fresh.update(&g, &x, 2).unwrap();
        assert_eq!(mws.posterior(), fresh.posterior(), "n = {n}, m = {m}");
    }
}

#[test]
fn the_simulator_refuses_a_control_of_another_length() {
    let truth = Ackermann { wheelbase: 1.0 };
    let mut sim = bayes_cbf::sim::Simulator::new(&truth, Default::default());
    let mut rng = <ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
    let mut x = [0.0; 3];
    let e = sim.step(&mut x, &[1.0], 0.1, &mut rng).unwrap_err();
    assert!(e.to_string().contains("shape of u:"), "{e}");
}
