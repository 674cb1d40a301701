//! Expression-defined systems, barriers and Lyapunov functions against the
//! built-ins they restate: values, Jacobians, gradients and Hessians agree
//! to 1e-12; evaluation failures are typed errors naming the entry.

use bayes_cbf::barrier::{
    cbc_moments, clc_moments, AckermannClf, CircleHeading, ConditionMoments, DynBarrier,
    DynLyapunov, ExpressionBarrier, ExpressionClf, MomentWorkspace, PendulumSector,
};
use bayes_cbf::control::{ControlOutput, SafetyController, SafetySettings};
use bayes_cbf::gp::{InputMap, Mvgp, MvgpHyper, PriorMean, Rbf};
use bayes_cbf::systems::{Ackermann, DynSystem, ExpressionSystem, Pendulum};
use num_dual::{Dual64, HyperDual64};
use std::sync::Arc;

/// Deterministic points in `[lo, hi]^n`.
fn points(n: usize, count: usize, lo: f64, hi: f64) -> Vec<Vec<f64>> {
    let mut s = 0x2545_F491_4F6C_DD1Du64;
    (0..count)
        .map(|_| {
            (0..n)
                .map(|_| {
                    s ^= s << 13;
                    s ^= s >> 7;
                    s ^= s << 17;
                    lo + (hi - lo) * (s >> 11) as f64 / (1u64 << 53) as f64
                })
                .collect()
        })
        .collect()
}

fn close(a: &[f64], b: &[f64], tol: f64, what: &str) {
    assert_eq!(a.len(), b.len(), "{what}");
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!(
            (x - y).abs() <= tol * y.abs().max(1.0),
            "{what}[{i}]: {x} vs {y}"
        );
    }
}

fn expression_pendulum(m: f64, l: f64, g: f64) -> ExpressionSystem {
    ExpressionSystem::new(
        &["theta", "omega"],
        &["u"],
        &[("m", m), ("l", l), ("g", g)],
        &["omega", "-g/l*sin(theta)"],
        &[vec!["0"], vec!["1/(m*l)"]],
        &["theta"],
    )
    .unwrap()
}

fn expression_ackermann(wheelbase: f64) -> ExpressionSystem {
    ExpressionSystem::new(
        &["x", "y", "theta"],
        &["v", "z"],
        &[("L", wheelbase)],
        &["0", "0", "0"],
        &[
            vec!["cos(theta)", "0"],
            vec!["sin(theta)", "0"],
            vec!["0", "1/L"],
        ],
        &["theta"],
    )
    .unwrap()
}

fn same_system(a: &dyn DynSystem, b: &dyn DynSystem, lo: f64, hi: f64) {
    let (n, m) = (a.state_dim(), a.control_dim());
    assert_eq!((n, m), (b.state_dim(), b.control_dim()));
    assert_eq!(a.angle_indices(), b.angle_indices());
    let rows = n * (1 + m);
    let (mut fa, mut fb) = (vec![0.0; rows], vec![0.0; rows]);
    let (mut ja, mut jb) = (vec![0.0; rows * n], vec![0.0; rows * n]);
    let mut sx = vec![Dual64::from(0.0); n];
    let mut so = vec![Dual64::from(0.0); rows];
    for x in points(n, 200, lo, hi) {
        a.eval_f64(&x, &mut fa);
        b.eval_f64(&x, &mut fb);
        close(&fa, &fb, 1e-12, "vec F");
        a.jacobian_into(&x, &mut ja, &mut sx, &mut so);
        b.jacobian_into(&x, &mut jb, &mut sx, &mut so);
        close(&ja, &jb, 1e-12, "∂ vec F/∂x");
    }
    assert!(a.take_error().is_none() && b.take_error().is_none());
}

#[test]
fn expression_systems_equal_the_built_ins() {
    same_system(
        &expression_pendulum(1.0, 1.0, 10.0),
        &Pendulum::default(),
        -4.0,
        4.0,
    );
    same_system(
        &expression_pendulum(2.0, 0.5, 9.81),
        &Pendulum {
            mass: 2.0,
            length: 0.5,
            gravity: 9.81,
        },
        -4.0,
        4.0,
    );
    same_system(
        &expression_ackermann(12.0),
        &Ackermann { wheelbase: 12.0 },
        -3.0,
        3.0,
    );
}

fn same_barrier(a: &dyn DynBarrier, b: &dyn DynBarrier, pts: &[Vec<f64>]) {
    let n = a.state_dim();
    assert_eq!(n, b.state_dim());
    assert_eq!(a.relative_degree(), b.relative_degree());
    assert_eq!(a.gains(), b.gains());
    let (mut ga, mut gb) = (vec![0.0; n], vec![0.0; n]);
    let (mut ha, mut hb) = (vec![0.0; n * n], vec![0.0; n * n]);
    let mut d = vec![Dual64::from(0.0); n];
    let mut hd = vec![HyperDual64::from(0.0); n];
    for x in pts {
        close(&[a.value(x)], &[b.value(x)], 1e-12, "h");
        let va = a.gradient(x, &mut ga, &mut d);
        let vb = b.gradient(x, &mut gb, &mut d);
        close(&[va], &[vb], 1e-12, "h");
        close(&ga, &gb, 1e-12, "∇h");
        a.hessian(x, &mut ga, &mut ha, &mut hd);
        b.hessian(x, &mut gb, &mut hb, &mut hd);
        close(&ga, &gb, 1e-12, "∇h");
        close(&ha, &hb, 1e-12, "∇²h");
    }
    assert!(a.take_error().is_none());
}

#[test]
fn expression_barriers_equal_the_built_ins() {
    let (tc, delta) = (std::f64::consts::FRAC_PI_4, std::f64::consts::PI / 8.0);
    let sector = ExpressionBarrier::new(
        &["theta", "omega"],
        &[("theta_c", tc), ("delta", delta)],
        "cos(delta) - cos(theta - theta_c)",
        2,
        vec![1.0, 3.0],
    )
    .unwrap();
    let builtin = PendulumSector::new(tc, delta, 2, vec![1.0, 3.0]).unwrap();
    same_barrier(&sector, &builtin, &points(2, 200, -4.0, 4.0));

    let (c, r, q1, q2) = ([-1.1667, -1.5], 0.7906, 0.7, 0.3);
    let heading = ExpressionBarrier::new(
        &["x", "y", "theta"],
        &[("cx", c[0]), ("cy", c[1]), ("r", r), ("q1", q1), ("q2", q2)],
        "q1*((x - cx)^2 + (y - cy)^2 - r^2) + q2*cos(theta - atan2(y - cy, x - cx))",
        1,
        vec![5.0],
    )
    .unwrap();
    let builtin = CircleHeading::new(c, r, q1, q2, 1, vec![5.0]).unwrap();
    // every quadrant around the obstacle, and the axes through its centre
    let mut pts = points(3, 200, -4.0, 2.0);
    pts.push(vec![c[0], 0.5, 0.2]);
    pts.push(vec![0.3, c[1], -1.0]);
    pts.push(vec![-3.0, c[1], 2.0]);
    same_barrier(&heading, &builtin, &pts);
}

#[test]
fn expression_clf_equals_the_ackermann_clf() {
    let (w1, w2, gamma) = (1.5, 0.8, 2.0);
    let expr = ExpressionClf::new(
        &["x", "y", "theta"],
        &[("w1", w1), ("w2", w2)],
        "w1/2*((x_d - x)^2 + (y_d - y)^2) + w2*(1 - cos(theta - atan2(y_d - y, x_d - x)))",
        gamma,
    )
    .unwrap();
    let builtin = AckermannClf::new(w1, w2, gamma).unwrap();
    assert_eq!(DynLyapunov::gamma(&expr), 2.0);
    let (mut ga, mut gb) = (vec![0.0; 3], vec![0.0; 3]);
    let mut scratch = vec![Dual64::from(0.0); 6];
    for p in points(9, 200, -3.0, 3.0) {
        let (x, xd, xdd) = (&p[0..3], &p[3..6], &p[6..9]);
        let (va, da) = expr.gradient(x, xd, xdd, &mut ga, &mut scratch);
        let (vb, db) = builtin.gradient(x, xd, xdd, &mut gb, &mut scratch);
        close(&[va, da], &[vb, db], 1e-12, "V, ∇_{x_d}V ẋ_d");
        close(&ga, &gb, 1e-12, "∇V");
    }
    let err = ExpressionClf::new(&["x"], &[], "(x - x_ref)^2", 1.0).unwrap_err();
    assert!(
        err.to_string()
            .contains("unknown name 'x_ref' (known: x, x_d"),
        "{err}"
    );
}

/// `θ̇ = ω`, `ω̇ = log θ + u`: not finite for `θ ≤ 0`.
fn log_theta_system() -> ExpressionSystem {
    ExpressionSystem::new(
        &["theta", "omega"],
        &["u"],
        &[],
        &["omega", "log(theta)"],
        &[vec!["0"], vec!["1"]],
        &[],
    )
    .unwrap()
}

#[test]
fn non_finite_evaluations_are_errors_naming_the_entry() {
    let sys = log_theta_system();
    let mut f = [0.0; 4];
    sys.eval_f64(&[0.5, 0.0], &mut f);
    assert!(sys.take_error().is_none());
    sys.eval_f64(&[-0.5, 0.0], &mut f);
    let msg = sys.take_error().unwrap();
    assert!(
        msg.contains("f[1] = NaN at state [-0.5, 0.0]") && msg.contains("log(theta)"),
        "{msg}"
    );
    assert!(sys.take_error().is_none(), "taken once");

    // through the model: a prior mean that fails is an error of the step
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![1.0, 1.0], 1.0).unwrap(),
        A: nalgebra::DMatrix::identity(2, 2),
        B: nalgebra::DMatrix::identity(2, 2),
        sigma: 0.1,
    };
    let model = Mvgp::new(
        2,
        1,
        hyper,
        PriorMean::System(Arc::new(sys)),
        InputMap::Identity,
    )
    .unwrap();
    let barrier = ExpressionBarrier::new(&["a", "b"], &[], "sqrt(a) - b", 1, vec![1.0]).unwrap();
    let mut ws = MomentWorkspace::new(&model);
    let err = ws.update(&model, &[-0.5, 0.0], 1).unwrap_err().to_string();
    assert!(err.contains("prior mean: f[1] = NaN"), "{err}");
    ws.update(&model, &[0.5, 0.0], 1).unwrap();
    let mut out = ConditionMoments::zeros(1);
    cbc_moments(&mut ws, &barrier, &mut out).unwrap();
    ws.update(&model, &[1.0, 0.0], 1).unwrap();
    let bad = ExpressionBarrier::new(&["a", "b"], &[], "sqrt(a - 2) - b", 1, vec![1.0])
        .unwrap()
        .with_name("root");
    let err = cbc_moments(&mut ws, &bad, &mut out)
        .unwrap_err()
        .to_string();
    assert!(err.contains("h of barrier 'root' = NaN"), "{err}");
}

/// A zero-mean model on two states and one control, without data.
fn prior_model() -> Mvgp {
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![1.0, 1.0], 1.0).unwrap(),
        A: nalgebra::DMatrix::identity(2, 2),
        B: nalgebra::DMatrix::identity(2, 2),
        sigma: 0.1,
    };
    Mvgp::new(2, 1, hyper, PriorMean::Zero, InputMap::Identity).unwrap()
}

/// Where `h` is finite but its gradient is not, the message names the
/// gradient; a failing barrier among several is named by its index, since
/// barriers that share a formula differ only in their parameters; a CLF
/// that is not differentiable at its reference names `V` and the reference.
#[test]
fn failures_name_the_barrier_the_derivative_and_the_clf() {
    let model = prior_model();
    let mut ws = MomentWorkspace::new(&model);
    let mut out = ConditionMoments::zeros(1);
    ws.update(&model, &[1.0, 0.0], 1).unwrap();
    // (a − 1)^1.5: gradient 0 at a = 1, fine for relative degree 1
    let smooth =
        ExpressionBarrier::new(&["a", "b"], &[], "(a - 1)^1.5 + 1 - b", 1, vec![1.0]).unwrap();
    cbc_moments(&mut ws, &smooth, &mut out).unwrap();
    assert_eq!((out.value, out.e[0]), (1.0, 1.0));
    // (a − 1)^0.5: value 1, infinite gradient, which is named as such
    let kink =
        ExpressionBarrier::new(&["a", "b"], &[], "(a - 1)^0.5 + 1 - b", 1, vec![1.0]).unwrap();
    let err = cbc_moments(&mut ws, &kink, &mut out)
        .unwrap_err()
        .to_string();
    assert!(
        err.starts_with("∇h of barrier") && err.contains("is inf at x = [1.0, 0.0]"),
        "{err}"
    );
    // two discs of one formula: the second fails, and is named
    let disc = |c: f64| -> Arc<dyn DynBarrier> {
        Arc::new(
            ExpressionBarrier::new(
                &["a", "b"],
                &[("c", c)],
                "a^2 + b^2 - 0.25 + 0*log(a + c)",
                1,
                vec![1.0],
            )
            .unwrap(),
        )
    };
    let mut ctrl = SafetyController::new(
        2,
        1,
        vec![disc(0.0), disc(-2.0)],
        None,
        SafetySettings::new(1),
    )
    .unwrap();
    let mut co = ControlOutput::new(1, 2);
    let err = ctrl
        .step(&model, &[1.0, 0.0], &[0.0], None, &mut co)
        .unwrap_err()
        .to_string();
    assert!(
        err.starts_with("barriers[1]: ") && err.contains("= NaN"),
        "{err}"
    );
    // V = ‖x − x_d‖ at x = x_d
    let clf = ExpressionClf::new(&["a", "b"], &[], "sqrt((a - a_d)^2 + (b - b_d)^2)", 1.0).unwrap();
    let err = clc_moments(&mut ws, &clf, &[1.0, 0.0], &[0.0, 0.0], &mut out)
        .unwrap_err()
        .to_string();
    assert!(
        err.starts_with("clf: ∇ₓV is NaN") && err.contains("x_d = [1.0, 0.0]"),
        "{err}"
    );
    // a state named like another state's reference
    let err = ExpressionClf::new(&["x", "x_d"], &[], "(x - x_d)^2", 1.0)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("clashes with the reference of state 'x'"),
        "{err}"
    );
}

/// An observation whose prior mean fails to evaluate is rejected and
/// leaves the model as it was: the same data, factor and posterior, and the
/// next observation is learned as by a model that never saw the bad one.
#[test]
fn a_rejected_observation_leaves_the_model_unchanged() {
    let prior = || PriorMean::System(Arc::new(log_theta_system()));
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![1.0, 1.0], 1.0).unwrap(),
        A: nalgebra::DMatrix::identity(2, 2),
        B: nalgebra::DMatrix::identity(2, 2),
        sigma: 0.1,
    };
    let new = || Mvgp::new(2, 1, hyper.clone(), prior(), InputMap::Identity).unwrap();
    let (mut model, mut clean) = (new(), new());
    for m in [&mut model, &mut clean] {
        m.add_observation(&[0.5, 0.1], &[0.3], &[0.1, -0.2])
            .unwrap();
        m.add_observation(&[1.5, 0.4], &[-0.6], &[0.2, 0.3])
            .unwrap();
    }
    let err = model
        .add_observation(&[-0.5, 0.0], &[0.2], &[0.0, 0.1])
        .unwrap_err()
        .to_string();
    assert!(err.contains("NaN"), "{err}");
    assert_eq!(model.len(), 2);
    assert_eq!(
        (model.xs(), model.xdot(), model.controls()),
        (clean.xs(), clean.xdot(), clean.controls())
    );
    for m in [&mut model, &mut clean] {
        m.add_observation(&[0.8, -0.3], &[0.1], &[-0.3, 0.4])
            .unwrap();
    }
    let (a, b) = (
        model.posterior(&[0.7, 0.0]).unwrap(),
        clean.posterior(&[0.7, 0.0]).unwrap(),
    );
    assert_eq!((a.mean, a.B), (b.mean, b.B));
}

#[test]
fn bad_expressions_are_typed_errors() {
    let cases: Vec<(Result<(), bayes_cbf::InputError>, &str)> = vec![
        (
            ExpressionSystem::new(&["x"], &["u"], &[], &["u*x"], &[vec!["1"]], &[]).map(|_| ()),
            "f[0], column 1: 'u' cannot be used here",
        ),
        (
            ExpressionSystem::new(&["x"], &["u"], &[], &["x", "x"], &[vec!["1"]], &[]).map(|_| ()),
            "wrong shape of f",
        ),
        (
            ExpressionSystem::new(&["x"], &["u"], &[], &["x"], &[vec!["1", "2"]], &[]).map(|_| ()),
            "wrong shape of g[0]",
        ),
        (
            ExpressionSystem::new(&["x"], &["u"], &[], &["x"], &[vec!["1 +"]], &[]).map(|_| ()),
            "g[0][0], column 4",
        ),
        (
            ExpressionSystem::new(&["x"], &["u"], &[], &["x"], &[vec!["1"]], &["y"]).map(|_| ()),
            "invalid angles = y",
        ),
        (
            ExpressionBarrier::new(&["x"], &[], "x", 2, vec![0.0, 3.0]).map(|_| ()),
            "Hurwitz",
        ),
        (
            ExpressionBarrier::new(&["x", "x"], &[], "x", 1, vec![1.0]).map(|_| ()),
            "given twice",
        ),
    ];
    for (r, want) in cases {
        let msg = r.unwrap_err().to_string();
        assert!(msg.contains(want), "{msg} should contain {want}");
    }
}

#[test]
fn no_state_or_no_control_is_an_error_naming_it() {
    let none: [&str; 0] = [];
    let state_err = bayes_cbf::InputError::invalid("state", 0.0, "at least one state is needed");
    let e = ExpressionBarrier::new(&none, &[], "1", 1, vec![1.0]).unwrap_err();
    assert_eq!(e, state_err);
    let e = ExpressionSystem::new(&none, &["u"], &[], &none, &[], &none).unwrap_err();
    assert_eq!(e, state_err);
    let e = ExpressionSystem::new(&["x"], &none, &[], &["x"], &[vec![]], &none).unwrap_err();
    assert_eq!(
        e,
        bayes_cbf::InputError::invalid("control", 0.0, "at least one control is needed")
    );
}
