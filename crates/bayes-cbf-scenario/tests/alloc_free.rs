//! The control step (posterior, moments, SOCP) allocates nothing once its
//! workspaces are warm: counted with a global allocator.

use bayes_cbf::barrier::{
    cbc_moments, clc_moments, ConditionMoments, DynLyapunov, ExpressionClf, MomentWorkspace,
};
use bayes_cbf::control::{ControlOutput, SafetyController, SafetySettings};
use bayes_cbf::gp::{FitSettings, InputMap, Mvgp, MvgpHyper, MvgpLikelihood, PriorMean, Rbf};
use bayes_cbf_scenario::workloads::{
    ackermann_control, ackermann_control_written, pendulum_control_written, pendulum_data,
    ControlWorkload, Written,
};
use nalgebra::DMatrix;
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

struct Counting;

thread_local! {
    // per test thread: tests run in parallel
    static COUNTING: Cell<bool> = const { Cell::new(false) };
    static ALLOCS: Cell<usize> = const { Cell::new(0) };
    static BYTES: Cell<usize> = const { Cell::new(0) };
}

fn note(bytes: usize) {
    if COUNTING.with(Cell::get) {
        ALLOCS.with(|a| a.set(a.get() + 1));
        BYTES.with(|b| b.set(b.get() + bytes));
    }
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note(new_size);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn count<F: FnMut()>(f: F) -> usize {
    count_bytes(f).0
}

/// Allocations and the bytes they asked for.
fn count_bytes<F: FnMut()>(mut f: F) -> (usize, usize) {
    ALLOCS.with(|a| a.set(0));
    BYTES.with(|b| b.set(0));
    COUNTING.with(|c| c.set(true));
    f();
    COUNTING.with(|c| c.set(false));
    (ALLOCS.with(Cell::get), BYTES.with(Cell::get))
}

/// The workload's controller with the conditions as realised
/// (`predictive`) or on the latent `F`.
fn with_predictive(w: &mut ControlWorkload, predictive: bool) {
    let c = &w.controller;
    let settings = SafetySettings {
        predictive,
        ..c.settings().clone()
    };
    let (n, m) = (w.model.state_dim(), w.model.control_dim());
    w.controller =
        SafetyController::new(n, m, c.barriers().to_vec(), c.clf().cloned(), settings).unwrap();
}

/// Allocations of 50 Ackermann control steps after warm-up (each followed
/// by a recalibration against the same model when `recalibrate`), the
/// conditions predictive or latent.
fn ackermann_step_allocations(k: usize, recalibrate: bool, predictive: bool) -> usize {
    let mut w = ackermann_control(k, 3).unwrap();
    with_predictive(&mut w, predictive);
    if recalibrate {
        w.controller
            .set_recalibration(Some(Default::default()))
            .unwrap();
    }
    let mut out = ControlOutput::new(2, 2);
    let r = w.reference.clone().unwrap();
    let mut x = w.x.clone();
    let mut steps = |count: usize| {
        for i in 0..count {
            x[0] = -3.0 + 0.013 * i as f64;
            w.controller
                .step(&w.model, &x, &w.u_ref, Some((&r.0, &r.1)), &mut out)
                .unwrap();
            w.controller.recalibrate(&w.model).unwrap();
        }
    };
    steps(5);
    count(|| steps(50))
}

/// The whole step allocates nothing: the posterior, the moments of every
/// condition (latent or predictive), the dense SOCP solver and the
/// infeasible path work in buffers sized at the first step. (A program
/// that falls back to Clarabel would allocate inside its timers; none of
/// these does.)
#[test]
fn control_steps_do_not_allocate() {
    bayes_cbf::gp::set_linear_algebra_threads(1);
    let small = ackermann_step_allocations(150, false, false);
    let large = ackermann_step_allocations(600, false, false);
    assert_eq!(small, large, "allocations depend on k: {small} vs {large}");
    // the recalibration (moments once more after the update) adds none
    let recalibrated = ackermann_step_allocations(600, true, false);
    assert_eq!(recalibrated, large, "recalibration allocates");
    assert_eq!(small, 0, "{small} allocations in 50 steps");
    // nor does the predictive condition (the default), at relative degree
    // 1 here and 2 on the pendulum
    assert_eq!(ackermann_step_allocations(300, true, true), 0);
    // the pendulum at its start, infeasible there: the infeasible path
    // (max-margin program, p*, the list of violated barriers) too
    let mut w = pendulum_control_written(300, 3, Written::BuiltIn).unwrap();
    let mut out = ControlOutput::new(1, 1);
    for predictive in [false, true] {
        with_predictive(&mut w, predictive);
        let mut x = w.x.clone();
        let mut steps = |w: &mut ControlWorkload, count: usize| {
            for i in 0..count {
                x[1] = -0.5 + 0.02 * i as f64;
                w.controller
                    .step(&w.model, &x, &w.u_ref, None, &mut out)
                    .unwrap();
            }
        };
        steps(&mut w, 5);
        assert_eq!(count(|| steps(&mut w, 50)), 0, "predictive {predictive}");
        assert!(out.is_infeasible(), "{:?}", out.status);
    }
}

/// Allocations of the posterior and the moments of every condition of a
/// workload (its barriers, and `clf` or else its own CLF) at 50 states
/// after warm-up; `vary` moves the state.
fn moment_allocations(
    w: &ControlWorkload,
    clf: Option<&dyn DynLyapunov>,
    vary: fn(&mut [f64], usize),
) -> usize {
    let degree = w
        .controller
        .barriers()
        .iter()
        .map(|b| b.relative_degree())
        .max()
        .unwrap_or(1);
    let mut ws = MomentWorkspace::new(&w.model);
    let mut mom = ConditionMoments::zeros(w.u_ref.len());
    let zero = vec![0.0; w.x.len()];
    let (xd, xd_dot) = w.reference.as_ref().map_or((&zero, &zero), |(a, b)| (a, b));
    let mut x = w.x.clone();
    let mut run = |x: &[f64]| {
        ws.update(&w.model, x, degree).unwrap();
        for b in w.controller.barriers() {
            cbc_moments(&mut ws, b.as_ref(), &mut mom).unwrap();
        }
        if let Some(clf) = clf.or(w.controller.clf().map(|c| c.as_ref())) {
            clc_moments(&mut ws, clf, xd, xd_dot, &mut mom).unwrap();
        }
    };
    run(&x);
    count(|| {
        for i in 0..50 {
            vary(&mut x, i);
            run(&x);
        }
    })
}

/// The posterior and the moments allocate nothing, for the built-in
/// barriers and CLF and for the same scenarios written as expressions, with
/// the vehicle's CLF as an expression too (relative degree 1: the
/// vehicle's heading barriers and CLF; relative degree 2: the pendulum's
/// sector).
#[test]
fn posterior_and_moments_do_not_allocate() {
    bayes_cbf::gp::set_linear_algebra_threads(1);
    let clf = ExpressionClf::new(
        &["x", "y", "theta"],
        &[("w1", 0.9), ("w2", 1.5)],
        "w1/2*((x_d - x)^2 + (y_d - y)^2) + w2*(1 - cos(theta - atan2(y_d - y, x_d - x)))",
        10.0,
    )
    .unwrap();
    for (written, clf) in [
        (Written::BuiltIn, None),
        (Written::Expressions, Some(&clf as &dyn DynLyapunov)),
    ] {
        let w = ackermann_control_written(150, 3, written).unwrap();
        let n = moment_allocations(&w, clf, |x, i| x[1] = -1.0 + 0.01 * i as f64);
        assert_eq!(n, 0, "{written:?}, relative degree 1: {n} allocations");
        let w = pendulum_control_written(150, 3, written).unwrap();
        let n = moment_allocations(&w, None, |x, i| x[1] = -0.01 + 0.01 * i as f64);
        assert_eq!(n, 0, "{written:?}, relative degree 2: {n} allocations");
    }
}

/// One likelihood-and-gradient evaluation of a fit allocates nothing that
/// grows with `k` (its `k`-sized buffers are the fit's workspace): the same
/// few `n × n` and `(1+m) × (1+m)` matrices at k = 100 and k = 400.
#[test]
fn fit_evaluations_allocate_nothing_that_grows_with_k() {
    let per_evaluation = |k: usize| {
        let data = pendulum_data(k, 11).unwrap();
        let hyper = MvgpHyper {
            kernel: Rbf::new(vec![1.0; 2], 1.0).unwrap(),
            A: DMatrix::identity(2, 2),
            B: DMatrix::identity(2, 2),
            sigma: 0.1,
        };
        let mut model = Mvgp::new(2, 1, hyper, PriorMean::Zero, InputMap::Identity).unwrap();
        model.set_data(&data.xs, &data.us, &data.xdot).unwrap();
        let mut lik = MvgpLikelihood::new(&model, &FitSettings::default()).unwrap();
        let theta = lik.start().to_vec();
        let mut grad = vec![0.0; theta.len()];
        lik.evaluate(&theta, &mut grad).unwrap();
        count_bytes(|| {
            lik.evaluate(&theta, &mut grad).unwrap();
        })
    };
    let (small, large) = (per_evaluation(100), per_evaluation(400));
    eprintln!("allocations, bytes per evaluation: {small:?} at k = 100, {large:?} at k = 400");
    assert_eq!(small, large);
    assert!(small.1 < 4096, "{} bytes", small.1);
}
