//! The control step (posterior, moments, SOCP) allocates nothing once its
//! workspaces are warm: counted with a global allocator.

use bayes_cbf::control::ControlOutput;
use bayes_cbf::gp::{FitSettings, InputMap, Mvgp, MvgpHyper, MvgpLikelihood, PriorMean, Rbf};
use bayes_cbf_scenario::workloads::{ackermann_control, pendulum_control, pendulum_data};
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

/// Allocations of 50 Ackermann control steps after warm-up (each followed
/// by a recalibration against the same model when `recalibrate`).
fn ackermann_step_allocations(k: usize, recalibrate: bool) -> usize {
    let mut w = ackermann_control(k, 3).unwrap();
    if recalibrate {
        w.controller
            .set_recalibration(Some(Default::default()))
            .unwrap();
    }
    let mut out = ControlOutput::new(2, 2);
    let r = w.reference.clone().unwrap();
    let mut x = w.x.clone();
    for i in 0..5 {
        x[0] = -3.0 + 0.013 * i as f64;
        w.controller
            .step(&w.model, &x, &w.u_ref, Some((&r.0, &r.1)), &mut out)
            .unwrap();
        w.controller.recalibrate(&w.model).unwrap();
    }
    count(|| {
        for i in 0..50 {
            x[0] = -3.0 + 0.013 * i as f64;
            w.controller
                .step(&w.model, &x, &w.u_ref, Some((&r.0, &r.1)), &mut out)
                .unwrap();
            w.controller.recalibrate(&w.model).unwrap();
        }
    })
}

/// The posterior and the moments of every condition allocate nothing; the
/// whole step allocates only inside Clarabel, whose solve re-creates its
/// nested timer maps: a small constant per step, independent of `k`.
#[test]
fn control_steps_do_not_allocate() {
    faer::set_global_parallelism(faer::Par::Seq);
    let small = ackermann_step_allocations(150, false);
    let large = ackermann_step_allocations(600, false);
    assert_eq!(small, large, "allocations depend on k: {small} vs {large}");
    // the recalibration (moments once more after the update) adds none
    let recalibrated = ackermann_step_allocations(600, true);
    assert_eq!(recalibrated, large, "recalibration allocates");
    assert!(small <= 50 * 8, "{small} allocations in 50 steps");
    eprintln!(
        "control step: {} allocations per step, all in the SOCP solver's timers",
        small / 50
    );
}

#[test]
fn posterior_and_moments_do_not_allocate() {
    use bayes_cbf::barrier::{
        cbc_moments, clc_moments, AckermannClf, CircleHeading, ConditionMoments, MomentWorkspace,
        PendulumSector,
    };
    faer::set_global_parallelism(faer::Par::Seq);
    let w = ackermann_control(150, 3).unwrap();
    let mut ws = MomentWorkspace::new(&w.model);
    let mut mom = ConditionMoments::zeros(2);
    let b = CircleHeading::new([-1.1667, -1.5], 0.7906, 0.7, 0.3, 1, vec![5.0]).unwrap();
    let clf = AckermannClf::new(0.9, 1.5, 10.0).unwrap();
    let r = w.reference.clone().unwrap();
    let mut x = w.x.clone();
    let mut run = |x: &[f64]| {
        ws.update(&w.model, x, 1).unwrap();
        cbc_moments(&mut ws, &b, &mut mom).unwrap();
        clc_moments(&mut ws, &clf, &r.0, &r.1, &mut mom).unwrap();
    };
    run(&x);
    let n = count(|| {
        for i in 0..50 {
            x[1] = -1.0 + 0.01 * i as f64;
            run(&x);
        }
    });
    assert_eq!(n, 0, "relative degree 1: {n} allocations");
    let w = pendulum_control(150, 3).unwrap();
    let mut ws = MomentWorkspace::new(&w.model);
    let mut mom = ConditionMoments::zeros(1);
    let b = PendulumSector::new(
        std::f64::consts::FRAC_PI_4,
        std::f64::consts::FRAC_PI_8,
        2,
        vec![1.0, 3.0],
    )
    .unwrap();
    let mut x = w.x.clone();
    ws.update(&w.model, &x, 2).unwrap();
    cbc_moments(&mut ws, &b, &mut mom).unwrap();
    let n = count(|| {
        for i in 0..50 {
            x[1] = -0.01 + 0.01 * i as f64;
            ws.update(&w.model, &x, 2).unwrap();
            cbc_moments(&mut ws, &b, &mut mom).unwrap();
        }
    });
    assert_eq!(n, 0, "relative degree 2: {n} allocations");
}

#[test]
fn expression_posterior_and_moments_do_not_allocate() {
    // the Ackermann workload with its prior mean and barriers written as
    // expressions, and an expression CLF; the pendulum's sector barrier of
    // relative degree 2 as an expression
    use bayes_cbf::barrier::{
        cbc_moments, clc_moments, ConditionMoments, ExpressionBarrier, ExpressionClf,
        MomentWorkspace,
    };
    use bayes_cbf_scenario::workloads::{
        ackermann_control_written, pendulum_control_written, Written,
    };
    faer::set_global_parallelism(faer::Par::Seq);
    let w = ackermann_control_written(150, 3, Written::Expressions).unwrap();
    let mut ws = MomentWorkspace::new(&w.model);
    let mut mom = ConditionMoments::zeros(2);
    let clf = ExpressionClf::new(
        &["x", "y", "theta"],
        &[("w1", 0.9), ("w2", 1.5)],
        "w1/2*((x_d - x)^2 + (y_d - y)^2) + w2*(1 - cos(theta - atan2(y_d - y, x_d - x)))",
        10.0,
    )
    .unwrap();
    let b = ExpressionBarrier::new(
        &["x", "y", "theta"],
        &[
            ("cx", -1.1667),
            ("cy", -1.5),
            ("r", 0.7906),
            ("q1", 0.7),
            ("q2", 0.3),
        ],
        "q1*((x - cx)^2 + (y - cy)^2 - r^2) + q2*cos(theta - atan2(y - cy, x - cx))",
        1,
        vec![5.0],
    )
    .unwrap();
    let r = w.reference.clone().unwrap();
    let mut x = w.x.clone();
    let mut run = |x: &[f64]| {
        ws.update(&w.model, x, 1).unwrap();
        cbc_moments(&mut ws, &b, &mut mom).unwrap();
        clc_moments(&mut ws, &clf, &r.0, &r.1, &mut mom).unwrap();
    };
    run(&x);
    let n = count(|| {
        for i in 0..50 {
            x[1] = -1.0 + 0.01 * i as f64;
            run(&x);
        }
    });
    assert_eq!(n, 0, "expressions, relative degree 1: {n} allocations");
    let w = pendulum_control_written(150, 3, Written::Expressions).unwrap();
    let b = ExpressionBarrier::new(
        &["theta", "omega"],
        &[
            ("tc", std::f64::consts::FRAC_PI_4),
            ("d", std::f64::consts::FRAC_PI_8),
        ],
        "cos(d) - cos(theta - tc)",
        2,
        vec![1.0, 3.0],
    )
    .unwrap();
    let mut ws = MomentWorkspace::new(&w.model);
    let mut mom = ConditionMoments::zeros(1);
    let mut x = w.x.clone();
    ws.update(&w.model, &x, 2).unwrap();
    cbc_moments(&mut ws, &b, &mut mom).unwrap();
    let n = count(|| {
        for i in 0..50 {
            x[1] = -0.01 + 0.01 * i as f64;
            ws.update(&w.model, &x, 2).unwrap();
            cbc_moments(&mut ws, &b, &mut mom).unwrap();
        }
    });
    assert_eq!(n, 0, "expressions, relative degree 2: {n} allocations");
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
