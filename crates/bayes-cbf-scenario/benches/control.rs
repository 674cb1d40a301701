//! Real workloads: one control step (posterior, moments, SOCP), one
//! prediction, one online update, and hyperparameter fits, as k grows.

use bayes_cbf::control::ControlOutput;
use bayes_cbf::gp::{fit, FitSettings};
use bayes_cbf_scenario::workloads::{ackermann_control, pendulum_control};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use std::hint::black_box;

fn control_step(c: &mut Criterion) {
    bayes_cbf::gp::set_linear_algebra_threads(1);
    let mut g = c.benchmark_group("control_step");
    for k in [200, 1000] {
        let mut w = ackermann_control(k, 0).unwrap();
        let mut out = ControlOutput::new(2, 2);
        g.bench_with_input(BenchmarkId::new("ackermann_rd1", k), &k, |b, _| {
            b.iter(|| {
                let r = w
                    .reference
                    .as_ref()
                    .map(|(a, b)| (a.as_slice(), b.as_slice()));
                w.controller
                    .step(&w.model, black_box(&w.x), &w.u_ref, r, &mut out)
                    .unwrap();
            })
        });
        let mut w = pendulum_control(k, 0).unwrap();
        let mut out = ControlOutput::new(1, 1);
        g.bench_with_input(BenchmarkId::new("pendulum_rd2", k), &k, |b, _| {
            b.iter(|| {
                w.controller
                    .step(&w.model, black_box(&w.x), &w.u_ref, None, &mut out)
                    .unwrap()
            })
        });
    }
    g.finish();
}

fn gp_ops(c: &mut Criterion) {
    bayes_cbf::gp::set_linear_algebra_threads(1);
    let mut g = c.benchmark_group("gp");
    let w = pendulum_control(1000, 0).unwrap();
    let mut ws = w.model.workspace();
    let mut post = w.model.posterior(&w.x).unwrap();
    g.bench_function("predict/pendulum/1000", |b| {
        b.iter(|| {
            w.model
                .posterior_into(black_box(&w.x), &mut ws, &mut post)
                .unwrap()
        })
    });
    let model = w.model.clone();
    let e = w.extra.clone();
    g.bench_function("add_observation/pendulum/1000", |b| {
        b.iter_batched(
            || model.clone(),
            |mut m| {
                m.add_observation(&e.xs[0..2], &e.us[0..1], &e.xdot[0..2])
                    .unwrap();
                m
            },
            criterion::BatchSize::LargeInput,
        )
    });
    // one budgeted update at k = 200: drop the least informative of the
    // 201 points, the new one included (diag(G⁻¹) already tracked)
    let mut w = ackermann_control(200, 0).unwrap();
    let plain = w.model.clone();
    w.model.gram_inverse_diagonal();
    let e = w.extra.clone();
    g.bench_function("budget_update/ackermann/200", |b| {
        b.iter_batched(
            || w.model.clone(),
            |mut m| {
                m.add_observation_within_budget(&e.xs[0..3], &e.us[0..2], &e.xdot[0..3], 200)
                    .unwrap();
                m
            },
            criterion::BatchSize::LargeInput,
        )
    });
    g.bench_function("window_update/ackermann/200", |b| {
        b.iter_batched(
            || plain.clone(),
            |mut m| {
                m.add_observation(&e.xs[0..3], &e.us[0..2], &e.xdot[0..3])
                    .unwrap();
                m.remove_oldest();
                m
            },
            criterion::BatchSize::LargeInput,
        )
    });
    g.sample_size(10);
    let w = ackermann_control(500, 0).unwrap();
    g.bench_function("fit/mvgp/ackermann/500", |b| {
        b.iter_batched(
            || w.model.clone(),
            |mut m| {
                fit(
                    &mut m,
                    &FitSettings {
                        max_iters: 30,
                        ..Default::default()
                    },
                )
                .unwrap()
            },
            criterion::BatchSize::LargeInput,
        )
    });
    g.finish();
}

criterion_group!(benches, control_step, gp_ops);
criterion_main!(benches);
