//! Timings of the real workloads (`bayes-cbf bench`), each next to the
//! memory-bound floor of an exact posterior (one triangular solve with the
//! `k × k` factor) measured in the same run: the control step, online
//! updates, prediction, fits, bounded streams and their quality.

use crate::bail;
use crate::error::{Context, Result};
use crate::stats::quantile;
use crate::workloads::{
    ackermann_control, ackermann_control_written, ackermann_data, ackermann_heading_sweep,
    pendulum_control, pendulum_control_written, pendulum_data, ControlWorkload, Written,
};
use bayes_cbf::control::ControlOutput;
use bayes_cbf::gp::{
    fit, fit_cogp, held_out_errors, Cogp, CogpFitSettings, CogpHyper, FitSettings, InputMap, Mvgp,
    MvgpHyper, MvgpLikelihood, PriorMean, Rbf,
};
use bayes_cbf::systems::Ackermann;
use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// The result of [`run_bench`]: one row per measurement.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Bench {
    /// Threads of the dense linear algebra.
    pub threads: usize,
    /// Reduced sizes and repetitions.
    pub quick: bool,
    /// The measurements.
    pub rows: Vec<BenchRow>,
}

/// One measurement of [`run_bench`], tagged by `case`. Times are medians
/// (`p50`) and 99th percentiles (`p99`) in microseconds (`_us`) or
/// milliseconds (`_ms`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "case", rename_all = "snake_case")]
pub enum BenchRow {
    /// One control step (posterior, moments, SOCP) of a workload.
    ControlStep {
        /// The workload (`ackermann`, `pendulum`, or either with
        /// `-expression`: written in the expression language).
        system: String,
        /// The barriers' relative degree.
        relative_degree: usize,
        /// Observations in the model.
        k: usize,
        /// Median.
        p50_us: f64,
        /// 99th percentile.
        p99_us: f64,
        /// Steps whose SOCP was infeasible (timed with the fallback and
        /// `p*`), of the built-in workloads.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        infeasible_steps: Option<usize>,
        /// An expression workload: the built-in step's median in the same run.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        builtin_p50_us: Option<f64>,
        /// An expression workload: its median over the built-in's.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        over_builtin: Option<f64>,
    },
    /// One observation added to a model of `k` points.
    AddObservation(Timing),
    /// The oldest observation removed from a model of `k + 1` points.
    RemoveOldest(Timing),
    /// The posterior at one state.
    Predict(Timing),
    /// One triangular solve with the `k × k` factor: the memory-bound cost
    /// of any exact posterior variance.
    Floor {
        /// Observations.
        k: usize,
        /// Median.
        p50_us: f64,
    },
    /// A hyperparameter fit of the MVGP or the CoGP.
    Fit {
        /// `mvgp` or `cogp`.
        model: String,
        /// The data's system.
        system: String,
        /// Observations.
        k: usize,
        /// L-BFGS iterations.
        max_iters: u64,
        /// Median over the repetitions.
        p50_ms: f64,
        /// Objective evaluations of the fit.
        evaluations: usize,
        /// The CoGP's median over the MVGP's.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        ratio_to_mvgp: Option<f64>,
    },
    /// A fit with active bounds against the same fit without them.
    FitBound {
        /// The data's system.
        system: String,
        /// Observations.
        k: usize,
        /// L-BFGS iterations.
        max_iters: u64,
        /// Which bounds.
        bound: String,
        /// Evaluations without the bounds.
        evaluations_free: usize,
        /// Evaluations with them.
        evaluations_bound: usize,
        /// Their ratio.
        evaluations_ratio: f64,
        /// Time without the bounds.
        free_ms: f64,
        /// Time with them.
        bound_ms: f64,
    },
    /// One likelihood-and-gradient evaluation of a fit against its floor.
    FitEvaluation {
        /// The data's system.
        system: String,
        /// Observations.
        k: usize,
        /// Median of an evaluation.
        p50_ms: f64,
        /// Median of one Cholesky factorisation and one inverse of the
        /// same matrix in the same buffers.
        floor_p50_ms: f64,
        /// Their ratio.
        over_floor: f64,
    },
    /// A stream of control steps and bounded online updates.
    Stream {
        /// The workload.
        system: String,
        /// Steps.
        steps: usize,
        /// Step (control and update): median.
        p50_us: f64,
        /// Step: 99th percentile.
        p99_us: f64,
        /// Step: largest.
        max_us: f64,
        /// Step median over the first tenth of the stream.
        p50_us_first_tenth: f64,
        /// Step median over the last tenth.
        p50_us_last_tenth: f64,
        /// Control step: median.
        control_p50_us: f64,
        /// Control step: 99th percentile.
        control_p99_us: f64,
        /// Update: median.
        update_p50_us: f64,
        /// Update: 99th percentile.
        update_p99_us: f64,
        /// Steps whose SOCP was infeasible.
        infeasible_steps: usize,
        /// Step: 99th percentile of the feasible steps.
        p99_us_feasible_steps: f64,
        /// Control step median of the feasible steps.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        control_p50_us_feasible: Option<f64>,
        /// Control step median of the infeasible steps.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        control_p50_us_infeasible: Option<f64>,
        /// Their ratio.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        infeasible_over_feasible: Option<f64>,
        /// How the model's data are bounded.
        #[serde(flatten)]
        bound: BoundKey,
    },
    /// The prediction quality of a bounded model against the full data.
    StreamQuality {
        /// The workload.
        system: String,
        /// Observations streamed.
        steps: usize,
        /// Observations kept at the end.
        k_end: usize,
        /// Update: median.
        update_p50_us: f64,
        /// Update: 99th percentile.
        update_p99_us: f64,
        /// Root mean square error of `F(x)u̲` on held-out data.
        rmse_fu: f64,
        /// Variance-weighted error (Eq. 33) on held-out data.
        variance_weighted: f64,
        /// The largest heading interval without a kept point (rad).
        largest_heading_gap_rad: f64,
        /// How the model's data are bounded.
        #[serde(flatten)]
        bound: BoundKey,
    },
}

/// Median and 99th percentile of an operation on a model of `k` points.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Timing {
    /// The data's system.
    pub system: String,
    /// Observations.
    pub k: usize,
    /// Median.
    pub p50_us: f64,
    /// 99th percentile.
    pub p99_us: f64,
}

/// How a stream bounds the model's data: one of the three fields.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct BoundKey {
    /// A sliding window of this many points.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub window: Option<usize>,
    /// A budget of this many points.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub budget: Option<usize>,
    /// All the data.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub full: Option<bool>,
}

fn round(x: f64) -> f64 {
    (x * 100.0).round() / 100.0
}

/// Microseconds of `f` over `reps` calls: (p50, p99).
fn time_us(reps: usize, mut f: impl FnMut(usize)) -> (f64, f64) {
    let mut t = Vec::with_capacity(reps);
    for i in 0..reps {
        let s = Instant::now();
        f(i);
        t.push(s.elapsed().as_secs_f64() * 1e6);
    }
    (round(quantile(&t, 0.5)), round(quantile(&t, 0.99)))
}

fn control_row(
    system: &str,
    rd: usize,
    k: usize,
    reps: usize,
    w: &mut ControlWorkload,
) -> Result<BenchRow> {
    let m = w.model.control_dim();
    let mut out = ControlOutput::new(m, 2);
    let r = w.reference.clone();
    let mut x = w.x.clone();
    let (mut err, mut infeasible) = (None, 0);
    let (p50, p99) = time_us(reps, |i| {
        x[0] = w.x[0] + 1e-4 * (i % 50) as f64;
        let reference = r.as_ref().map(|(a, b)| (a.as_slice(), b.as_slice()));
        if let Err(e) = w
            .controller
            .step(&w.model, &x, &w.u_ref, reference, &mut out)
        {
            err = Some(e);
        }
        infeasible += usize::from(out.is_infeasible());
    });
    if let Some(e) = err {
        bail!("control step ({system}, k = {k}): {e}");
    }
    Ok(BenchRow::ControlStep {
        system: system.into(),
        relative_degree: rd,
        k,
        p50_us: p50,
        p99_us: p99,
        infeasible_steps: Some(infeasible),
        builtin_p50_us: None,
        over_builtin: None,
    })
}

/// One control step of `builtin` and of `expr` (the same workload written
/// as expressions), alternating, `reps` each: the expression step's
/// percentiles and its median over the built-in's.
fn expression_row(
    system: &str,
    rd: usize,
    k: usize,
    reps: usize,
    builtin: &mut ControlWorkload,
    expr: &mut ControlWorkload,
) -> Result<BenchRow> {
    let m = builtin.model.control_dim();
    let mut out = ControlOutput::new(m, 2);
    let (mut tb, mut te) = (Vec::with_capacity(reps), Vec::with_capacity(reps));
    let mut x = builtin.x.clone();
    for i in 0..2 * reps {
        let w = if i % 2 == 0 {
            &mut *builtin
        } else {
            &mut *expr
        };
        x[0] = w.x[0] + 1e-4 * ((i / 2) % 50) as f64;
        let r = w.reference.clone();
        let reference = r.as_ref().map(|(a, b)| (a.as_slice(), b.as_slice()));
        let s = Instant::now();
        w.controller
            .step(&w.model, &x, &w.u_ref, reference, &mut out)
            .with_context(|| format!("control step ({system}, k = {k})"))?;
        let us = s.elapsed().as_secs_f64() * 1e6;
        if i % 2 == 0 {
            tb.push(us)
        } else {
            te.push(us)
        }
    }
    let (b50, e50, e99) = (quantile(&tb, 0.5), quantile(&te, 0.5), quantile(&te, 0.99));
    Ok(BenchRow::ControlStep {
        system: format!("{system}-expression"),
        relative_degree: rd,
        k,
        p50_us: round(e50),
        p99_us: round(e99),
        infeasible_steps: None,
        builtin_p50_us: Some(round(b50)),
        over_builtin: Some(round(e50 / b50)),
    })
}

fn floor_row(model: &Mvgp, k: usize, reps: usize) -> BenchRow {
    let mut rhs = nalgebra::DMatrix::<f64>::zeros(k, 1);
    let (p50, _) = time_us(reps, |i| {
        for j in 0..k {
            rhs[(j, 0)] = ((i + j) % 7) as f64;
        }
        model.factor().solve_l_in_place(&mut rhs);
    });
    BenchRow::Floor { k, p50_us: p50 }
}

/// Runs `f` once: its value and its wall time (ms).
fn timed_ms<T>(f: impl FnOnce() -> Result<T>) -> Result<(T, f64)> {
    let s = Instant::now();
    let v = f()?;
    Ok((v, s.elapsed().as_secs_f64() * 1e3))
}

fn fit_rows(system: &str, k: usize, reps: usize, iters: u64) -> Result<Vec<BenchRow>> {
    let (n, m, d, data, map, prior) = match system {
        "ackermann" => (
            3,
            2,
            1,
            ackermann_data(k, 1.0, 11)?,
            InputMap::Select(vec![2]),
            PriorMean::Zero,
        ),
        _ => (
            2,
            1,
            2,
            pendulum_data(k, 11)?,
            InputMap::Identity,
            PriorMean::Zero,
        ),
    };
    let (mut mv, mut co) = (Vec::new(), Vec::new());
    let (mut mv_evals, mut co_evals) = (0, 0);
    for _ in 0..reps {
        let hyper = MvgpHyper {
            kernel: Rbf::new(vec![1.0; d], 1.0)?,
            A: DMatrix::identity(n, n),
            B: DMatrix::identity(m + 1, m + 1),
            sigma: 0.1,
        };
        let mut model = Mvgp::new(n, m, hyper, prior.clone(), map.clone())?;
        model.set_data(&data.xs, &data.us, &data.xdot)?;
        let settings = FitSettings {
            max_iters: iters,
            ..FitSettings::default()
        };
        let (evals, ms) = timed_ms(|| Ok(fit(&mut model, &settings)?.evaluations))?;
        mv_evals = evals;
        mv.push(ms);
        let np = n * (m + 1);
        let ch = CogpHyper {
            kernel: Rbf::new(vec![1.0; d], 1.0)?,
            Sigma: DMatrix::identity(np, np),
            S: DMatrix::identity(n, n) * 0.01,
        };
        let mut cogp = Cogp::new(n, m, ch, prior.clone(), map.clone())?;
        cogp.set_data(&data.xs, &data.us, &data.xdot)?;
        let settings = CogpFitSettings {
            max_iters: iters,
            prefit_diagonal: false,
            ..CogpFitSettings::default()
        };
        let (evals, ms) = timed_ms(|| Ok(fit_cogp(&mut cogp, &settings)?.evaluations))?;
        co_evals = evals;
        co.push(ms);
    }
    let (m50, c50) = (round(quantile(&mv, 0.5)), round(quantile(&co, 0.5)));
    let row = |model: &str, p50_ms, evaluations, ratio_to_mvgp| BenchRow::Fit {
        model: model.into(),
        system: system.into(),
        k,
        max_iters: iters,
        p50_ms,
        evaluations,
        ratio_to_mvgp,
    };
    Ok(vec![
        row("mvgp", m50, mv_evals, None),
        row("cogp", c50, co_evals, Some(round(c50 / m50))),
    ])
}

/// The pendulum MVGP of the fit rows (zero prior mean, unit start) on `k`
/// uniform observations.
fn pendulum_fit_model(k: usize) -> Result<Mvgp> {
    let data = pendulum_data(k, 11)?;
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![1.0; 2], 1.0)?,
        A: DMatrix::identity(2, 2),
        B: DMatrix::identity(2, 2),
        sigma: 0.1,
    };
    let mut model = Mvgp::new(2, 1, hyper, PriorMean::Zero, InputMap::Identity)?;
    model.set_data(&data.xs, &data.us, &data.xdot)?;
    Ok(model)
}

/// One evaluation of the likelihood and its gradient (the unit of a fit)
/// against its floor, one Cholesky factorisation and one inverse of the
/// same `k × k` Gram matrix in the same buffers, interleaved in one run.
fn fit_evaluation_row(k: usize, reps: usize) -> Result<BenchRow> {
    let model = pendulum_fit_model(k)?;
    let mut lik = MvgpLikelihood::new(&model, &FitSettings::default())?;
    let theta = lik.start().to_vec();
    let mut grad = vec![0.0; theta.len()];
    let (mut te, mut tf) = (Vec::with_capacity(reps), Vec::with_capacity(reps));
    lik.evaluate(&theta, &mut grad)?;
    for _ in 0..reps {
        let s = Instant::now();
        lik.evaluate(&theta, &mut grad)?;
        te.push(s.elapsed().as_secs_f64() * 1e3);
        let s = Instant::now();
        lik.floor()?;
        tf.push(s.elapsed().as_secs_f64() * 1e3);
    }
    let (e50, f50) = (quantile(&te, 0.5), quantile(&tf, 0.5));
    Ok(BenchRow::FitEvaluation {
        system: "pendulum".into(),
        k,
        p50_ms: round(e50),
        floor_p50_ms: round(f50),
        over_floor: round(e50 / f50),
    })
}

/// Fits with active bounds against the same fits without them
/// (evaluations and time): the pendulum fit with the noise floor at 5× the
/// free optimum's `σ` (the bounded optimum sits on the floor), and a warm
/// start a factor 3 away from the free optimum whose every scale may move
/// only 1.5× either way (`warm_range`) against the same warm start without
/// that box.
fn fit_bound_rows(k: usize, iters: u64) -> Result<Vec<BenchRow>> {
    let run = |model: &mut Mvgp, settings: FitSettings| -> Result<(usize, f64)> {
        let settings = FitSettings {
            max_iters: iters,
            ..settings
        };
        timed_ms(|| Ok(fit(model, &settings)?.evaluations))
    };
    let row = |bound: &str, free: (usize, f64), bounded: (usize, f64)| BenchRow::FitBound {
        system: "pendulum".into(),
        k,
        max_iters: iters,
        bound: bound.into(),
        evaluations_free: free.0,
        evaluations_bound: bounded.0,
        evaluations_ratio: round(bounded.0 as f64 / free.0 as f64),
        free_ms: round(free.1),
        bound_ms: round(bounded.1),
    };
    let mut free_model = pendulum_fit_model(k)?;
    let free = run(&mut free_model, FitSettings::default())?;
    // σ in the fit's own scale, A_00 = 1
    let h = free_model.hyper().clone();
    let sigma = h.sigma * h.A[(0, 0)].sqrt();
    let floored = run(
        &mut pendulum_fit_model(k)?,
        FitSettings {
            sigma_min: 5.0 * sigma,
            ..FitSettings::default()
        },
    )?;
    let warm = |range: f64| -> Result<(usize, f64)> {
        let mut model = pendulum_fit_model(k)?;
        let mut start = h.clone();
        let l = start.kernel.lengthscales().to_vec();
        start.kernel = Rbf::new(vec![3.0 * l[0], l[1] / 3.0], 1.0)?;
        start.sigma *= 3.0;
        start.B /= 3.0;
        model.set_hyper(start)?;
        run(
            &mut model,
            FitSettings {
                warm_start: true,
                warm_range: range,
                ..FitSettings::default()
            },
        )
    };
    let (wide, boxed) = (warm(f64::INFINITY)?, warm(1.5)?);
    Ok(vec![
        row("noise floor at 5 × the free optimum's sigma", free, floored),
        row("warm start, every scale within 1.5 × of it", wide, boxed),
    ])
}

/// How a stream bounds the model's data.
#[derive(Debug, Clone, Copy)]
enum Bound {
    /// Drop the oldest point.
    Window(usize),
    /// Drop the least informative point (which may be the new one).
    Budget(usize),
    /// Keep everything.
    Full,
}

impl Bound {
    /// Adds one observation and applies the bound.
    fn add(self, model: &mut Mvgp, x: &[f64], u: &[f64], xdot: &[f64]) -> Result<()> {
        match self {
            Bound::Window(w) => {
                model.add_observation(x, u, xdot)?;
                while model.len() > w {
                    model.remove_oldest();
                }
            }
            Bound::Budget(b) => {
                model.add_observation_within_budget(x, u, xdot, b)?;
            }
            Bound::Full => model.add_observation(x, u, xdot)?,
        }
        Ok(())
    }
    fn key(self) -> BoundKey {
        match self {
            Bound::Window(w) => BoundKey {
                window: Some(w),
                ..BoundKey::default()
            },
            Bound::Budget(b) => BoundKey {
                budget: Some(b),
                ..BoundKey::default()
            },
            Bound::Full => BoundKey {
                full: Some(true),
                ..BoundKey::default()
            },
        }
    }
}

/// One stream's timings (µs) and its infeasible steps.
struct StreamStats {
    /// Step p50, p99, max, p50 of the first and of the last tenth; control
    /// p50, p99; update p50, p99; p99 of the feasible steps.
    times: [f64; 10],
    /// Control-step medians of the feasible and the infeasible steps.
    split: Option<(f64, f64)>,
    infeasible: usize,
}

/// A stream of `steps` Ackermann states (uniform): one control step and one
/// bounded online update per state, timed together (`p50_us`, `p99_us`,
/// `max_us`) and apart (`control_*`, `update_*`); `infeasible_steps` counts
/// the steps whose SOCP was infeasible (they also solve the max-margin
/// program and iterate for `p*`), `p99_us_feasible_steps` leaves them out,
/// `infeasible_over_feasible` is the ratio of the median control steps.
/// The stream runs `repeats` times from the same model; each figure is the
/// median over the repeats (a shared machine's preemptions land in the
/// tail of one run, not of all).
fn stream_row(steps: usize, bound: Bound, size: usize, repeats: usize) -> Result<BenchRow> {
    let runs = (0..repeats.max(1))
        .map(|_| stream_once(steps, bound, size))
        .collect::<Result<Vec<_>>>()?;
    let med = |f: &dyn Fn(&StreamStats) -> f64| {
        let v: Vec<f64> = runs.iter().map(f).collect();
        round(quantile(&v, 0.5))
    };
    let t = |i: usize| med(&|r: &StreamStats| r.times[i]);
    let split = runs[0].split.map(|_| {
        let fe = med(&|r: &StreamStats| r.split.map_or(f64::NAN, |s| s.0));
        let inf = med(&|r: &StreamStats| r.split.map_or(f64::NAN, |s| s.1));
        (fe, inf)
    });
    Ok(BenchRow::Stream {
        system: "ackermann".into(),
        steps,
        p50_us: t(0),
        p99_us: t(1),
        max_us: t(2),
        p50_us_first_tenth: t(3),
        p50_us_last_tenth: t(4),
        control_p50_us: t(5),
        control_p99_us: t(6),
        update_p50_us: t(7),
        update_p99_us: t(8),
        infeasible_steps: runs[0].infeasible,
        p99_us_feasible_steps: t(9),
        control_p50_us_feasible: split.map(|s| s.0),
        control_p50_us_infeasible: split.map(|s| s.1),
        infeasible_over_feasible: split.map(|(fe, inf)| round(inf / fe)),
        bound: bound.key(),
    })
}

/// One run of the stream of [`stream_row`].
fn stream_once(steps: usize, bound: Bound, size: usize) -> Result<StreamStats> {
    let mut w = ackermann_control(size, 5)?;
    let extra = ackermann_data(steps, 12.0, 6)?;
    let mut out = ControlOutput::new(2, 2);
    let r = w.reference.clone().context("reference")?;
    let mut times = Vec::with_capacity(steps);
    let mut control = Vec::with_capacity(steps);
    let mut update = Vec::with_capacity(steps);
    let mut infeasible = 0;
    let mut feasible = Vec::with_capacity(steps);
    let mut control_feasible = Vec::with_capacity(steps);
    let mut control_infeasible = Vec::new();
    for j in 0..steps {
        let x = &extra.xs[3 * j..3 * j + 3];
        let s = Instant::now();
        w.controller
            .step(&w.model, x, &w.u_ref, Some((&r.0, &r.1)), &mut out)?;
        let c = s.elapsed().as_secs_f64() * 1e6;
        bound.add(
            &mut w.model,
            x,
            &extra.us[2 * j..2 * j + 2],
            &extra.xdot[3 * j..3 * j + 3],
        )?;
        let t = s.elapsed().as_secs_f64() * 1e6;
        if out.is_infeasible() {
            infeasible += 1;
            control_infeasible.push(c);
        } else {
            feasible.push(t);
            control_feasible.push(c);
        }
        times.push(t);
        control.push(c);
        update.push(t - c);
    }
    let (f, l) = (&times[..steps / 10], &times[steps - steps / 10..]);
    let max = times.iter().cloned().fold(0.0, f64::max);
    // the cost of an infeasible step (max-margin program, p*, fallback)
    // against a feasible one, control step only
    let split = (!control_infeasible.is_empty()).then(|| {
        (
            quantile(&control_feasible, 0.5),
            quantile(&control_infeasible, 0.5),
        )
    });
    Ok(StreamStats {
        times: [
            quantile(&times, 0.5),
            quantile(&times, 0.99),
            max,
            quantile(f, 0.5),
            quantile(l, 0.5),
            quantile(&control, 0.5),
            quantile(&control, 0.99),
            quantile(&update, 0.5),
            quantile(&update, 0.99),
            quantile(&feasible, 0.99),
        ],
        split,
        infeasible,
    })
}

/// Prediction quality of a bounded model against the full data: the
/// Ackermann heading sweep ([`ackermann_heading_sweep`]) streamed into a
/// model of `size` points (window, budget) or all of them (full); errors of
/// the final model on 1 000 uniform held-out states and controls over the
/// whole heading range, and the time of each online update (add + bound).
fn quality_rows(steps: usize, size: usize) -> Result<Vec<BenchRow>> {
    let data = ackermann_heading_sweep(steps, 12.0, 21)?;
    let test = ackermann_data(1000, 12.0, 22)?;
    let truth = Ackermann { wheelbase: 12.0 };
    let mut rows = Vec::new();
    for bound in [Bound::Window(size), Bound::Budget(size), Bound::Full] {
        let mut model = ackermann_control(0, 0)?.model;
        model.set_data(
            &data.xs[..3 * size],
            &data.us[..2 * size],
            &data.xdot[..3 * size],
        )?;
        let mut times = Vec::with_capacity(steps - size);
        for j in size..steps {
            let s = Instant::now();
            bound.add(
                &mut model,
                &data.xs[3 * j..3 * j + 3],
                &data.us[2 * j..2 * j + 2],
                &data.xdot[3 * j..3 * j + 3],
            )?;
            times.push(s.elapsed().as_secs_f64() * 1e6);
        }
        let errs = held_out_errors(&model, &test.xs, &test.us, &truth)?;
        // heading range covered by the kept points
        let mut thetas: Vec<f64> = model.xs().chunks(3).map(|x| x[2]).collect();
        thetas.sort_by(f64::total_cmp);
        let gap = thetas
            .windows(2)
            .map(|w| w[1] - w[0])
            .chain([thetas[0] + 2.0 * std::f64::consts::PI - thetas[thetas.len() - 1]])
            .fold(0.0, f64::max);
        let row = BenchRow::StreamQuality {
            system: "ackermann".into(),
            steps,
            k_end: model.len(),
            update_p50_us: round(quantile(&times, 0.5)),
            update_p99_us: round(quantile(&times, 0.99)),
            rmse_fu: (errs.rmse_fu * 1e4).round() / 1e4,
            variance_weighted: (errs.variance_weighted * 1e3).round() / 1e3,
            largest_heading_gap_rad: (gap * 1e3).round() / 1e3,
            bound: bound.key(),
        };
        rows.push(row);
    }
    Ok(rows)
}

/// Times every workload on `threads` threads of dense linear algebra
/// (`quick`: reduced sizes and repetitions, seconds instead of minutes);
/// `stage` is told what is being measured.
pub fn run_bench(quick: bool, threads: usize, stage: &dyn Fn(&str)) -> Result<Bench> {
    if threads == 0 || threads > 256 {
        bail!("threads = {threads}: must be in 1..=256");
    }
    bayes_cbf::gp::set_linear_algebra_threads(threads);

    let ks: &[usize] = if quick {
        &[100, 200]
    } else {
        &[100, 200, 300, 1000, 3000]
    };
    let reps = |k: usize| {
        if quick || k >= 3000 {
            200
        } else {
            1000
        }
    };
    let mut rows = Vec::new();
    for &k in ks {
        stage(&format!("k = {k}"));
        let mut w = ackermann_control(k, 0)?;
        rows.push(control_row("ackermann", 1, k, reps(k), &mut w)?);
        let mut p = pendulum_control(k, 0)?;
        rows.push(control_row("pendulum", 2, k, reps(k), &mut p)?);
        // the same workloads with the system, prior mean and barriers
        // written as expressions, interleaved step by step with the
        // built-ins so that both see the same machine
        let mut we = ackermann_control_written(k, 0, Written::Expressions)?;
        rows.push(expression_row("ackermann", 1, k, reps(k), &mut w, &mut we)?);
        let mut pe = pendulum_control_written(k, 0, Written::Expressions)?;
        rows.push(expression_row("pendulum", 2, k, reps(k), &mut p, &mut pe)?);
        let e = p.extra.clone();
        // one observation added to a model of size k (a fresh copy each time, not timed)
        let adds = if k >= 3000 {
            20
        } else if k >= 1000 {
            60
        } else {
            200
        };
        let mut t_add = Vec::with_capacity(adds);
        let mut t_remove = Vec::with_capacity(adds);
        for i in 0..adds {
            let j = i % e.len();
            let mut model = p.model.clone();
            let s = Instant::now();
            model.add_observation(
                &e.xs[2 * j..2 * j + 2],
                &e.us[j..j + 1],
                &e.xdot[2 * j..2 * j + 2],
            )?;
            t_add.push(s.elapsed().as_secs_f64() * 1e6);
            let s = Instant::now();
            model.remove_oldest();
            t_remove.push(s.elapsed().as_secs_f64() * 1e6);
        }
        let timing = |t: &[f64]| Timing {
            system: "pendulum".into(),
            k,
            p50_us: round(quantile(t, 0.5)),
            p99_us: round(quantile(t, 0.99)),
        };
        rows.push(BenchRow::AddObservation(timing(&t_add)));
        rows.push(BenchRow::RemoveOldest(timing(&t_remove)));
        let mut ws = p.model.workspace();
        let mut post = p.model.posterior(&p.x)?;
        let mut x = p.x.clone();
        let (p50, p99) = time_us(reps(k), |i| {
            x[1] = -0.01 + 1e-3 * (i % 100) as f64;
            let _ = p.model.posterior_into(&x, &mut ws, &mut post);
        });
        rows.push(BenchRow::Predict(Timing {
            system: "pendulum".into(),
            k,
            p50_us: p50,
            p99_us: p99,
        }));
        rows.push(floor_row(&p.model, k, reps(k)));
    }
    let (fit_k, fit_reps, iters) = if quick { (100, 1, 10) } else { (500, 3, 30) };
    stage(&format!("fits at k = {fit_k}"));
    rows.extend(fit_rows("ackermann", fit_k, fit_reps, iters)?);
    rows.extend(fit_rows("pendulum", fit_k, fit_reps, iters)?);
    rows.extend(fit_bound_rows(fit_k, 100)?);
    let evaluation_ks: &[(usize, usize)] = if quick {
        &[(100, 5), (300, 5)]
    } else {
        &[(500, 15), (1000, 9), (3000, 5)]
    };
    for &(k, reps) in evaluation_ks {
        stage(&format!("fit evaluation at k = {k}"));
        rows.push(fit_evaluation_row(k, reps)?);
    }
    stage("streams");
    let (steps, repeats, bounds): (usize, usize, &[(Bound, usize)]) = if quick {
        (
            2_000,
            1,
            &[(Bound::Window(200), 200), (Bound::Budget(200), 200)],
        )
    } else {
        (
            20_000,
            3,
            &[
                (Bound::Window(1_000), 1_000),
                (Bound::Window(200), 200),
                (Bound::Budget(200), 200),
            ],
        )
    };
    for &(bound, size) in bounds {
        rows.push(stream_row(steps, bound, size, repeats)?);
    }
    stage("stream quality");
    rows.extend(if quick {
        quality_rows(600, 60)?
    } else {
        quality_rows(4_000, 200)?
    });
    Ok(Bench {
        threads,
        quick,
        rows,
    })
}
