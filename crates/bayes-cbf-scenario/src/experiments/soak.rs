//! `soak`: a long online-learning run with a sliding window, checking that
//! nothing degrades: no non-finite value, no growth of memory, no growth of
//! the control-step time (SPEC, "Speed and scale" and "Reliability").
//!
//! ## Setup
//! The pendulum (`m = l = 1`, `g = 10`, Eq. 31) learned from a parametric
//! prior mean with the wrong mass and length (`m = 1.5`, `l = 0.8`; its
//! row `θ̇ = ω` declared known, only `ω̇` learned),
//! kernel on `(cos θ, sin θ, ω)`, lengthscales `(1, 1, 3)`, `A = 0.04 I`,
//! `B = I`, `σ = 0.1` (`σ² A = 0.02² I`, the measurement noise on `ẋ`).
//! The relative-degree-2 Bayes CBF (`p = 0.99`, Cantelli, `k_α = (4, 4)`)
//! keeps it out of the sector `45° ± 22.5°` while the reference drives it
//! into the sector with a PD controller plus a uniformly random torque in
//! `[−10, 10]` N·m at every step; `|u| ≤ 20`. Every observation
//! is added to the model (O(k²) factor growth) and the oldest is dropped
//! beyond the window (O(k²) rank-one downdate), so the model holds `W`
//! observations after warm-up. The hyperparameters are refitted (warm
//! started, 30 L-BFGS iterations, noise floor 1e-3) at the end of every
//! tenth of the run.
//!
//! The run steps one [`ClosedLoop`] to the end, keeping only running
//! statistics of the step records (nothing grows with the run). After each
//! tenth of the run the report takes the peak resident set
//! size (`VmHWM` of `/proc/self/status`, Linux only), the current one
//! (`VmRSS`), the 50 % and 99 % quantiles of the control-step time
//! (posterior, moments, SOCP) and the mean wall time per loop step
//! (control, simulation, online update, refit). With glibc's default
//! allocator settings the resident size creeps up by a few MB over a run
//! without anything being kept (see `memory_kb.note` in `summary.json`).

use super::{quantile, ExperimentArgs, Progress};
use crate::bail;
use crate::error::{Context, Result};
use bayes_cbf::barrier::{DynBarrier, PendulumSector};
use bayes_cbf::control::{Fallback, SafetyController, SafetySettings};
use bayes_cbf::gp::{FitSettings, InputMap, Mvgp, MvgpHyper, PriorMean, Rbf};
use bayes_cbf::sim::{
    ClosedLoop, DataPolicy, LoopSettings, Reference, ReferenceOut, SimSettings, StepStatus,
};
use bayes_cbf::systems::{wrap_angle, Pendulum};
use nalgebra::DMatrix;
use rand::RngExt;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::f64::consts::PI;
use std::sync::Arc;
use std::time::Instant;

/// How to read the memory figures (copied into `summary.json`).
const ALLOCATOR_NOTE: &str = "glibc raises its mmap threshold to the size of the largest \
block freed so far (up to 32 MB), after which large temporaries (the refits' k x k Gram \
matrices) come from the heap, which fragments and is not returned: \
with the default allocator settings the peak and current RSS creep up by a few MB over a run \
even though nothing is kept. \
Measured on the default 100 000 steps: with \
MALLOC_MMAP_THRESHOLD_=65536 (a fixed threshold) the current RSS was flat at 13.1 MB and the \
peak at 25.4 MB from 30 % of the run to its end.";

/// The result of `soak`.
pub struct Soak {
    /// Steps with a non-finite state, control, barrier value or posterior
    /// (and 1 if the final model answers with a non-finite value).
    pub non_finite: usize,
    /// `summary.json`.
    pub summary: Summary,
}

/// Median and 99th percentile (µs).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct P50P99 {
    /// Median.
    pub p50: f64,
    /// 99th percentile.
    pub p99: f64,
}

/// One tenth of the run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Tenth {
    /// 1 to 10.
    pub tenth: usize,
    /// Steps done at its end.
    pub steps_done: usize,
    /// Observations in the model at its end.
    pub model_observations: usize,
    /// Control-step time over the tenth (µs).
    pub control_step_us: P50P99,
    /// Mean wall time per loop step (µs): control, simulation, update, refit.
    pub loop_step_mean_us: f64,
    /// Peak resident set size (kB), where available.
    pub peak_rss_kb: Option<u64>,
    /// Current resident set size (kB), where available.
    pub rss_kb: Option<u64>,
}

/// Peak and current resident set size (kB).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Memory {
    /// `VmHWM`.
    pub peak: Option<u64>,
    /// `VmRSS`.
    pub rss: Option<u64>,
}

/// Memory over the run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MemoryReport {
    /// Before the first step.
    pub start: Memory,
    /// After the first tenth.
    pub at_10_percent: Memory,
    /// At half the run.
    pub at_50_percent: Memory,
    /// At the end.
    pub at_100_percent: Memory,
    /// Peak at the end minus peak after the first tenth (kB).
    pub growth_after_first_tenth: Option<i64>,
    /// Where the figures come from.
    pub source: &'static str,
    /// How to read them.
    pub note: &'static str,
}

/// `summary.json` of `soak`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Summary {
    /// `soak`.
    pub scenario: &'static str,
    /// Seed.
    pub seed: u64,
    /// Reduced run.
    pub quick: bool,
    /// Control steps.
    pub steps: usize,
    /// Sliding window.
    pub window: usize,
    /// The setup.
    pub system: &'static str,
    /// The learning schedule.
    pub learning: &'static str,
    /// Non-finite records (and the final model).
    pub non_finite: usize,
    /// Observations in the final model.
    pub final_model_observations: usize,
    /// Hyperparameter refits.
    pub refits: usize,
    /// Steps where some `h < 0` on the fine grid.
    pub steps_with_h_violation: usize,
    /// Smallest `h` over the run.
    pub min_h: f64,
    /// Steps whose SOCP was infeasible.
    pub infeasible_steps: usize,
    /// Memory.
    pub memory_kb: MemoryReport,
    /// Median control step in the last tenth over the first.
    pub control_step_us_p50_ratio_last_to_first_tenth: f64,
    /// Per tenth.
    pub tenths: Vec<Tenth>,
    /// Wall time (s).
    pub wall_seconds: f64,
}

/// Default number of control steps.
pub(crate) const DEFAULT_STEPS: usize = 100_000;
/// Default sliding window.
pub(crate) const DEFAULT_WINDOW: usize = 500;
/// Steps of `--quick`.
const QUICK_STEPS: usize = 5_000;

/// The soak's reference: a PD controller toward the centre of the unsafe
/// sector, `û = 10 sin θ + 12 wrap(θ_c − θ) − 3 ω`, plus a uniformly random
/// torque in `[−10, 10]` N·m at every step (from the loop's seeded stream),
/// so that the safety filter is exercised and the data keep changing.
struct Excite;

impl Reference for Excite {
    fn at(&mut self, _k: usize, _t: f64, x: &[f64], rng: &mut ChaCha8Rng, out: &mut ReferenceOut) {
        let pd = 10.0 * x[0].sin() + 12.0 * wrap_angle(PI / 4.0 - x[0]) - 3.0 * x[1];
        out.u_ref[0] = (pd + rng.random_range(-10.0..10.0)).clamp(-20.0, 20.0);
        out.xd.copy_from_slice(x);
        out.xd_dot.fill(0.0);
    }
}

/// `(peak, current)` resident set size in kB from `/proc/self/status`.
pub(crate) fn memory_kb() -> (Option<u64>, Option<u64>) {
    let text = match std::fs::read_to_string("/proc/self/status") {
        Ok(t) => t,
        Err(_) => return (None, None),
    };
    let field = |name: &str| {
        text.lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse().ok())
    };
    (field("VmHWM:"), field("VmRSS:"))
}

/// Validates `--steps` and `--window`.
fn sizes(quick: bool, steps: Option<usize>, window: Option<usize>) -> Result<(usize, usize)> {
    let steps = steps.unwrap_or(if quick { QUICK_STEPS } else { DEFAULT_STEPS });
    if steps < 10 {
        bail!("steps = {steps}: must be ≥ 10 (the report is per tenth of the run)");
    }
    if steps.checked_mul(10).is_none() {
        bail!("steps = {steps}: too large");
    }
    let window = window.unwrap_or(DEFAULT_WINDOW);
    if window < 2 {
        bail!("window = {window}: must be ≥ 2 observations");
    }
    Ok((steps, window))
}

/// Runs the soak (see the module docs), reporting the steps done.
#[allow(non_snake_case)]
pub fn run(
    args: &ExperimentArgs,
    steps: Option<usize>,
    window: Option<usize>,
    progress: &dyn Progress,
) -> Result<Soak> {
    let (steps, window) = sizes(args.quick, steps, window)?;
    bayes_cbf::gp::set_linear_algebra_threads(1);
    let truth = Pendulum::default();
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![1.0, 1.0, 3.0], 1.0)?,
        A: DMatrix::identity(2, 2) * 0.04,
        B: DMatrix::identity(2, 2),
        sigma: 0.1,
    };
    let prior = PriorMean::System(Arc::new(Pendulum {
        mass: 1.5,
        length: 0.8,
        gravity: 10.0,
    }));
    // θ̇ = ω is known from the prior whatever its mass and length: only ω̇
    // is learned, and the relative-degree-2 condition's L_g h is 0
    let model =
        Mvgp::new(2, 1, hyper, prior, InputMap::periodic(2, &[0]))?.with_known_rows(&[0])?;
    let barrier: Arc<dyn DynBarrier> =
        Arc::new(PendulumSector::new(PI / 4.0, PI / 8.0, 2, vec![4.0, 4.0])?);
    // the paper's controller (conditions on the latent F)
    let mut settings = SafetySettings::paper(1);
    settings.probability = 0.99;
    settings.u_min = Some(vec![-20.0]);
    settings.u_max = Some(vec![20.0]);
    settings.fallback = Fallback::MaxMargin;
    let mut ctrl = SafetyController::new(2, 1, vec![barrier.clone()], None, settings)?;
    let mut reference = Excite;
    let barriers = [barrier];
    let x0 = [-0.3, 0.0];

    let ls = LoopSettings {
        dt: 0.01,
        steps,
        sim: SimSettings::new(1e-3, 0.0)?,
        update_every: 1,
        // a refit after every tenth of the run
        refit_every: (steps / 10).max(1),
        data: DataPolicy::Window(window),
        fit: FitSettings {
            max_iters: 30,
            sigma_min: 1e-3,
            ..FitSettings::default()
        },
        xdot_noise: 0.02,
        seed: args.seed,
        ..LoopSettings::default()
    };
    let mut run = ClosedLoop::new(
        &truth,
        model,
        &mut ctrl,
        &barriers,
        &mut reference,
        &x0,
        &ls,
    )?;
    let (hwm_start, rss_start) = memory_kb();
    let started = Instant::now();
    let mut tenths = Vec::new();
    let mut times = bayes_cbf::error::reserve::<f64>("steps", steps / 10 + 1).map_err(|_| {
        crate::err!(
            "steps = {steps}: too large (the memory for a tenth of the run's \
             control-step times cannot be reserved)"
        )
    })?;
    let mut done = 0usize;
    let (mut non_finite, mut h_violations, mut infeasible, mut refits) = (0usize, 0, 0, 0);
    let mut min_h = f64::INFINITY;
    for tenth in 0..10 {
        let end = steps * (tenth + 1) / 10;
        times.clear();
        let tenth_start = Instant::now();
        let tenth_steps = end - done;
        while done < end {
            let rec = run.step().with_context(|| format!("soak: step {done}"))?;
            times.push(rec.control_us);
            non_finite += usize::from(!rec.is_finite());
            h_violations += usize::from(rec.h_fine_min.iter().any(|&h| h < 0.0));
            infeasible += usize::from(rec.status == StepStatus::Infeasible);
            refits += usize::from(rec.refit);
            min_h = rec.h_fine_min.iter().cloned().fold(min_h, f64::min);
            done += 1;
            if done.is_multiple_of(100) || done == steps {
                progress.update(done, steps);
            }
        }
        let wall = tenth_start.elapsed().as_secs_f64();
        let (hwm, rss) = memory_kb();
        tenths.push(Tenth {
            tenth: tenth + 1,
            steps_done: done,
            model_observations: run.model().len(),
            control_step_us: P50P99 {
                p50: quantile(&times, 0.5),
                p99: quantile(&times, 0.99),
            },
            loop_step_mean_us: 1e6 * wall / tenth_steps.max(1) as f64,
            peak_rss_kb: hwm,
            rss_kb: rss,
        });
    }
    let wall = started.elapsed().as_secs_f64();
    // the final model must still answer with finite values
    let post = run.model().posterior(run.state())?;
    let final_finite = post.mean.iter().chain(post.B.iter()).all(|v| v.is_finite());
    non_finite += usize::from(!final_finite);
    let mem = |t: usize| Memory {
        peak: tenths[t - 1].peak_rss_kb,
        rss: tenths[t - 1].rss_kb,
    };
    let p50 = |t: usize| tenths[t - 1].control_step_us.p50;
    let summary = Summary {
        scenario: "soak",
        seed: args.seed,
        quick: args.quick,
        steps,
        window,
        system: "pendulum m = l = 1, prior mean m = 1.5, l = 0.8, relative-degree-2 Bayes CBF p = 0.99, reference: PD into the unsafe sector plus uniform random torques in [-10, 10]",
        learning: "every step (O(k^2) growth), sliding window, refit at the end of every tenth",
        non_finite,
        final_model_observations: run.model().len(),
        refits,
        steps_with_h_violation: h_violations,
        min_h,
        infeasible_steps: infeasible,
        memory_kb: MemoryReport {
            start: Memory {
                peak: hwm_start,
                rss: rss_start,
            },
            at_10_percent: mem(1),
            at_50_percent: mem(5),
            at_100_percent: mem(10),
            growth_after_first_tenth: match (mem(1).peak, mem(10).peak) {
                (Some(a), Some(b)) => Some(b as i64 - a as i64),
                _ => None,
            },
            source: "VmHWM (peak) and VmRSS of /proc/self/status; null where unavailable",
            note: ALLOCATOR_NOTE,
        },
        control_step_us_p50_ratio_last_to_first_tenth: p50(10) / p50(1),
        tenths,
        wall_seconds: wall,
    };
    Ok(Soak {
        non_finite,
        summary,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_are_validated_naming_the_option() {
        assert_eq!(
            sizes(false, None, None).unwrap(),
            (DEFAULT_STEPS, DEFAULT_WINDOW)
        );
        assert_eq!(sizes(true, None, Some(50)).unwrap(), (QUICK_STEPS, 50));
        let e = sizes(false, Some(5), None).unwrap_err().to_string();
        assert!(e.contains("steps = "), "{e}");
        let e = sizes(false, None, Some(1)).unwrap_err().to_string();
        assert!(e.contains("window = "), "{e}");
    }

    #[test]
    fn memory_is_read_on_linux() {
        let (hwm, rss) = memory_kb();
        if cfg!(target_os = "linux") {
            assert!(hwm.unwrap() >= rss.unwrap() && rss.unwrap() > 0);
        }
    }
}
