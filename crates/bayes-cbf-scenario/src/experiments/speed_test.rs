//! `speed-test`: time and accuracy of MVGP vs CoGP, with full and diagonal
//! covariances, as the number of observations `k` grows (paper, Sec. VII-A
//! and VII-B, Fig. 5).
//!
//! ## What is measured
//! For each system, `k` and repetition, fresh data are drawn (seeded), split
//! at random into `k` training and 100 held-out samples, and the four models
//! (MVGP full/diag, CoGP full/diag) are built on the same data with the same
//! kernel family (RBF), prior mean (zero) and input map, then
//! 1. **fitted** by maximising the marginal likelihood (the authors' code
//!    scored unfitted models): wall time of the fit (L-BFGS, at most
//!    [`MAX_ITERS`] iterations per start; the CoGP's full fit includes its
//!    diagonal pre-fit), and objective evaluations, so the per-evaluation
//!    cost is reported too;
//! 2. timed predicting the posterior mean and covariance of `vec F(x)` on a
//!    400-point test grid;
//! 3. scored by the variance-weighted error (Eq. 33) and the RMSE of `F` on
//!    the held-out samples against the true `F(x)`.
//!
//! Pendulum (`n = 2`, `m = 1`): data as in `pendulum-learning` (20-step
//! trajectories, `u = m g sin θ · U(0.6, 1.4)`, `ẋ` noise 0.01), kernel on
//! `(θ, ω)` (see `pendulum_learning` for why not `(cos θ, sin θ, ω)`), `k ∈ {256, 320, 384, 512, 1024}`, grid 20 × 20 of
//! `θ × ω`. Ackermann (`n = 3`, `m = 2`, `L = 1`): uniform states in
//! `[-3, 3]² × [-π, π]`, controls in `[-1, 1]²`, `ẋ` with noise 0.01;
//! translation invariant, so the kernel sees θ only (as in the paper,
//! `F(x) = F([0, 0, θ])`);
//! `k ∈ {64, 80, 96, 128, 256}`, grid of 20 positions × 20 headings.
//!
//! Medians and the 2nd–9th deciles (20 % and 90 % quantiles) over 30
//! repetitions are reported per `(system, k, model, variant)`, with the
//! CoGP/MVGP ratios of the median fit, per-evaluation and predict times
//! (theory: `n³` for the factorisation).
//!
//! ## Threads and timing quality
//! Fits run in parallel with rayon (one task per fit; faer sequential inside
//! each task), on all cores unless `RAYON_NUM_THREADS` says otherwise. On the
//! 2-vCPU development machine two concurrent fits each ran about 2× slower
//! than one alone (5.4 vs 11.5 ms per evaluation for the pendulum MVGP at
//! k = 384), and unevenly so depending on which fits were paired, which
//! scrambled the CoGP/MVGP ratios (one came out at 0.9); the two-thread run
//! saved only 8 % of the wall time (1107 s vs 1209 s). The reference table
//! was therefore measured with `RAYON_NUM_THREADS=1`: clean single-core
//! timings. The errors do not depend on the thread count.
//!
//! ## Cost and the iteration cap
//! The full run caps L-BFGS at [`MAX_ITERS`] = 15 iterations per start.
//! Uncapped (the library's default 100), the CoGP full fit of 200 pendulum
//! samples took 1000–1350 objective evaluations; at k = 1024 one evaluation
//! costs 0.35 s, so each of those 30 fits alone would take 6–8 minutes and
//! the experiment several hours. With the cap, CoGP full fits use 46–50
//! evaluations (the cap applies to its diagonal pre-fit too), the other
//! models 21–28, and the whole experiment (1200 fits) took 1209 s on one
//! core of the development machine (Intel Xeon, 2 vCPUs). The capped fits
//! are near-calibrated: the median variance-weighted errors are 1.9–2.2
//! (pendulum) and 2.9–3.2 (Ackermann), against `√(n(1+m))` = 2 and 3 for a
//! calibrated model. `--quick` runs 3 repetitions of the two smallest `k`
//! per system with at most 10 iterations, for tests and smoke runs.

use super::{
    fit_settings, new_model, pendulum_samples, random_split, variance_weighted, ExperimentArgs,
    ModelKind, Progress, Table, OMEGA_MAX,
};
use crate::error::Result;
use crate::workloads::ackermann_data;
use bayes_cbf::gp::{metrics, InputMap};
use bayes_cbf::sim::Dataset;
use bayes_cbf::systems::{Ackermann, DynSystem, Pendulum};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::Serialize;
use std::f64::consts::PI;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

mod report;

pub use report::{Machine, Ratio, Row, RowSummary, Stats};

/// A fit that failed.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Failure {
    /// System.
    pub system: &'static str,
    /// Training points.
    pub k: usize,
    /// Repetition.
    pub rep: usize,
    /// Model.
    pub model: &'static str,
    /// `full` or `diag`.
    pub variant: &'static str,
    /// The error.
    pub error: String,
}

/// Fit settings in the summary.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FitInfo {
    /// L-BFGS iterations per start.
    pub max_iters: u64,
    /// Restarts.
    pub restarts: usize,
    /// Why the cap is what it is.
    pub iteration_cap_note: &'static str,
}

/// What the kernel sees, per system.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct InputMaps {
    /// Pendulum.
    pub pendulum: &'static str,
    /// Ackermann vehicle.
    pub ackermann: &'static str,
}

/// The files written.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Files {
    /// The figures.
    pub plots: [&'static str; 2],
    /// Every fit.
    pub runs: &'static str,
    /// The training samples of the first repetition at the largest k of
    /// each system.
    pub samples: &'static str,
}

/// `summary.json` of `speed-test`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Summary {
    /// `speed-test`.
    pub scenario: &'static str,
    /// Seed.
    pub seed: u64,
    /// Reduced run.
    pub quick: bool,
    /// Repetitions per `(system, k)`.
    pub repetitions: usize,
    /// Data sizes per system.
    pub ks: std::collections::BTreeMap<&'static str, Vec<usize>>,
    /// The four models.
    pub models: [&'static str; 4],
    /// Kernel family.
    pub kernel: &'static str,
    /// Prior mean.
    pub prior_mean: &'static str,
    /// What the kernel sees.
    pub input_map: InputMaps,
    /// Held-out samples per repetition.
    pub test_points: usize,
    /// Prediction grid points.
    pub grid_points: usize,
    /// Fit settings.
    pub fit_settings: FitInfo,
    /// The machine.
    pub machine: Machine,
    /// Rayon threads.
    pub threads: usize,
    /// How to read the timings.
    pub timing_note: &'static str,
    /// Wall time (s).
    pub wall_seconds: f64,
    /// What the quantiles are.
    pub quantiles: &'static str,
    /// Medians and deciles per `(system, k, model, variant)`.
    pub table: Vec<RowSummary>,
    /// CoGP/MVGP time ratios.
    pub time_ratio_cogp_over_mvgp: Vec<Ratio>,
    /// Fits that failed.
    pub failures: Vec<Failure>,
    /// The files written.
    pub files: Files,
}

/// The result of `speed-test`.
pub struct SpeedTest {
    /// Medians and deciles per `(system, k, model, variant)`.
    pub table: Vec<Row>,
    /// `summary.json`.
    pub summary: Summary,
    /// `runs.csv`: every fit.
    pub tables: Vec<Table>,
}

impl SpeedTest {
    /// The row of `(system, k, model, variant)`.
    pub fn find(&self, s: System, k: usize, kind: ModelKind, diag: bool) -> Option<&Row> {
        report::find(&self.table, s, k, kind, diag)
    }
}

/// L-BFGS iterations per start in the full run, chosen so that the full
/// experiment (1200 fits) finishes in about 20 minutes on this machine
/// (measured: 1209 s single-threaded); see the module docs and
/// `fit_settings.iteration_cap_note` in `summary.json`.
pub const MAX_ITERS: u64 = 15;
/// Iteration cap of `--quick`.
const QUICK_ITERS: u64 = 10;
/// Held-out samples per repetition.
const TEST_POINTS: usize = 100;
/// Grid points per axis of the prediction-time grid (20 × 20).
const GRID: usize = 20;

/// The two systems of the speed test.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum System {
    /// Pendulum, Eq. 31.
    Pendulum,
    /// Ackermann vehicle, Eq. 32.
    Ackermann,
}

impl System {
    /// Report name.
    pub fn name(self) -> &'static str {
        match self {
            System::Pendulum => "pendulum",
            System::Ackermann => "ackermann",
        }
    }
    /// State dimension.
    pub fn state_dim(self) -> usize {
        match self {
            System::Pendulum => 2,
            System::Ackermann => 3,
        }
    }
    fn truth(self) -> Box<dyn DynSystem> {
        match self {
            System::Pendulum => Box::new(Pendulum::default()),
            System::Ackermann => Box::new(Ackermann { wheelbase: 1.0 }),
        }
    }
    fn input_map(self) -> InputMap {
        match self {
            System::Pendulum => InputMap::Identity,
            System::Ackermann => InputMap::Select(vec![2]),
        }
    }
    /// `total` fresh samples, seeded.
    fn data(self, total: usize, seed: u64) -> Result<Dataset> {
        match self {
            System::Pendulum => pendulum_samples(
                &Pendulum::default(),
                total,
                &mut ChaCha8Rng::seed_from_u64(seed),
            ),
            System::Ackermann => Ok(ackermann_data(total, 1.0, seed)?),
        }
    }
    /// The 400-point prediction grid, row-major states.
    fn grid(self) -> Vec<f64> {
        let lin = |a: f64, b: f64, i: usize| a + (b - a) * i as f64 / (GRID - 1) as f64;
        let mut xs = Vec::new();
        for i in 0..GRID {
            for j in 0..GRID {
                match self {
                    System::Pendulum => xs.extend([lin(-PI, PI, j), lin(-OMEGA_MAX, OMEGA_MAX, i)]),
                    System::Ackermann => xs.extend([lin(-3.0, 3.0, i), 0.0, lin(-PI, PI, j)]),
                }
            }
        }
        xs
    }
}

/// The experiment's size.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Plan {
    pub reps: usize,
    pub ks: Vec<(System, Vec<usize>)>,
    pub max_iters: u64,
}

impl Plan {
    pub fn new(quick: bool) -> Self {
        if quick {
            Plan {
                reps: 3,
                ks: vec![
                    (System::Pendulum, vec![256, 320]),
                    (System::Ackermann, vec![64, 80]),
                ],
                max_iters: QUICK_ITERS,
            }
        } else {
            Plan {
                reps: 30,
                ks: vec![
                    (System::Pendulum, vec![256, 320, 384, 512, 1024]),
                    (System::Ackermann, vec![64, 80, 96, 128, 256]),
                ],
                max_iters: MAX_ITERS,
            }
        }
    }
}

/// One fit to run: system, `k`, repetition, model, diagonal variant.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Case {
    pub system: System,
    pub k: usize,
    pub rep: usize,
    pub kind: ModelKind,
    pub diag: bool,
}

/// Measurements of one [`Case`]; `error` is set (and the numbers NaN) when
/// the fit or the scoring failed.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Outcome {
    pub case: Case,
    pub fit_seconds: f64,
    pub evaluations: usize,
    pub predict_seconds: f64,
    pub vwe: f64,
    pub rmse_f: f64,
    /// Held-out points whose covariance needed the extended jitter ladder.
    pub extended_jitter: usize,
    pub log_likelihood: f64,
    pub error: Option<String>,
}

/// SplitMix64 finaliser: decorrelated seeds from structured inputs.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Data seed of `(system, k, rep)`: the same for the four models.
fn data_seed(seed: u64, c: &Case) -> u64 {
    mix(mix(mix(seed) ^ c.system as u64) ^ ((c.k as u64) << 20 | c.rep as u64))
}

/// Runs one case: fresh data, fit, predict on the grid, score held out.
pub(crate) fn run_case(c: Case, seed: u64, max_iters: u64) -> Outcome {
    let mut out = Outcome {
        case: c,
        fit_seconds: f64::NAN,
        evaluations: 0,
        predict_seconds: f64::NAN,
        vwe: f64::NAN,
        rmse_f: f64::NAN,
        extended_jitter: 0,
        log_likelihood: f64::NAN,
        error: None,
    };
    if let Err(e) = measure(c, seed, max_iters, &mut out) {
        out.error = Some(format!("{e:#}"));
    }
    out
}

/// The training and test samples of case `c`.
fn case_data(c: &Case, seed: u64) -> Result<(Dataset, Dataset)> {
    let s = data_seed(seed, c);
    let data = c.system.data(c.k + TEST_POINTS, s)?;
    Ok(random_split(
        &data,
        c.k,
        &mut ChaCha8Rng::seed_from_u64(mix(s)),
    ))
}

fn measure(c: Case, seed: u64, max_iters: u64, out: &mut Outcome) -> Result<()> {
    let s = data_seed(seed, &c);
    let (train, test) = case_data(&c, seed)?;
    let mut model = new_model(c.kind, &c.system.input_map(), &train)?;
    let start = Instant::now();
    let report = model.fit(&fit_settings(c.diag, max_iters, s))?;
    out.fit_seconds = start.elapsed().as_secs_f64();
    out.evaluations = report.evaluations;
    out.log_likelihood = model.log_marginal_likelihood();
    let grid = c.system.grid();
    let n = c.system.state_dim();
    let start = Instant::now();
    let mut checksum = 0.0;
    for x in grid.chunks(n) {
        let (m, cov) = model.posterior_vec(x)?;
        checksum += m[(0, 0)] + cov[(0, 0)];
    }
    out.predict_seconds = start.elapsed().as_secs_f64();
    std::hint::black_box(checksum);
    let truth = c.system.truth();
    let (vwe, extended) = variance_weighted(model.as_ref(), &test.xs, truth.as_ref())?;
    out.vwe = vwe;
    out.extended_jitter = extended;
    out.rmse_f = metrics::rmse_f(model.as_ref(), &test.xs, truth.as_ref())?;
    Ok(())
}

/// All cases of `plan`, the most expensive first (better load balance).
fn cases(plan: &Plan) -> Vec<Case> {
    let mut v = Vec::new();
    for (system, ks) in &plan.ks {
        for &k in ks {
            for rep in 0..plan.reps {
                for kind in [ModelKind::Mvgp, ModelKind::Cogp] {
                    for diag in [false, true] {
                        v.push(Case {
                            system: *system,
                            k,
                            rep,
                            kind,
                            diag,
                        });
                    }
                }
            }
        }
    }
    let cost = |c: &Case| {
        let size = (c.k
            * if c.kind == ModelKind::Cogp {
                c.system.state_dim()
            } else {
                1
            }) as f64;
        size.powi(3) * if c.diag { 1.0 } else { 2.0 }
    };
    v.sort_by(|a, b| cost(b).total_cmp(&cost(a)));
    v
}

/// Runs the experiment (see the module docs), reporting each finished fit.
pub fn run(args: &ExperimentArgs, progress: &dyn Progress) -> Result<SpeedTest> {
    bayes_cbf::gp::set_linear_algebra_threads(1);
    let plan = Plan::new(args.quick);
    let todo = cases(&plan);
    let done = AtomicUsize::new(0);
    let start = Instant::now();
    let mut outcomes: Vec<Outcome> = todo
        .par_iter()
        .map(|c| {
            let o = run_case(*c, args.seed, plan.max_iters);
            progress.update(done.fetch_add(1, Ordering::Relaxed) + 1, todo.len());
            o
        })
        .collect();
    let wall = start.elapsed().as_secs_f64();
    outcomes.sort_by_key(|o| {
        (
            o.case.system,
            o.case.k,
            o.case.kind,
            o.case.diag,
            o.case.rep,
        )
    });
    let table = report::table(&outcomes);
    let ratios = report::ratios(&table);
    let failures = outcomes
        .iter()
        .filter_map(|o| {
            o.error.as_ref().map(|e| Failure {
                system: o.case.system.name(),
                k: o.case.k,
                rep: o.case.rep,
                model: o.case.kind.name(),
                variant: variant(o.case.diag),
                error: e.clone(),
            })
        })
        .collect();
    let summary = Summary {
        scenario: "speed-test",
        seed: args.seed,
        quick: args.quick,
        repetitions: plan.reps,
        ks: plan.ks.iter().map(|(s, k)| (s.name(), k.clone())).collect(),
        models: ["MVGP full", "MVGP diag", "CoGP full", "CoGP diag"],
        kernel: "rbf",
        prior_mean: "zero",
        input_map: InputMaps {
            pendulum: "identity (theta, omega)",
            ackermann: "theta only",
        },
        test_points: TEST_POINTS,
        grid_points: GRID * GRID,
        fit_settings: FitInfo {
            max_iters: plan.max_iters,
            restarts: 0,
            iteration_cap_note: report::ITERATION_NOTE,
        },
        machine: report::machine(),
        threads: rayon::current_num_threads(),
        timing_note: report::TIMING_NOTE,
        wall_seconds: wall,
        quantiles: "median and 2nd-9th deciles (0.2 and 0.9 quantiles) over the repetitions",
        table: table.iter().map(Row::summary).collect(),
        time_ratio_cogp_over_mvgp: ratios,
        failures,
        files: Files {
            plots: ["speed_test.png", "speed_ratio.png"],
            runs: "runs.csv",
            samples: "trajectory.csv",
        },
    };
    // trajectory.csv: the training samples of the first repetition at the
    // largest k of each system
    let mut largest = Vec::new();
    for (system, ks) in &plan.ks {
        let k = ks.iter().copied().max().unwrap_or(0);
        let case = Case {
            system: *system,
            k,
            rep: 0,
            kind: ModelKind::Mvgp,
            diag: false,
        };
        largest.push((system.name(), case_data(&case, args.seed)?.0));
    }
    let sets: Vec<(&str, &Dataset)> = largest.iter().map(|(s, d)| (*s, d)).collect();
    Ok(SpeedTest {
        table,
        summary,
        tables: vec![report::runs_csv(&outcomes), super::samples_table(&sets)],
    })
}

/// `"diag"` or `"full"`.
pub fn variant(diag: bool) -> &'static str {
    if diag {
        "diag"
    } else {
        "full"
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quick_speed_test_table() {
        let r = run(
            &ExperimentArgs {
                seed: 2,
                quick: true,
            },
            &|_, _| {},
        )
        .unwrap();
        let s = serde_json::to_value(&r.summary).unwrap();
        assert_eq!(s["scenario"], "speed-test");
        let table = s["table"].as_array().unwrap();
        // 2 systems × 2 k × 2 models × 2 variants
        assert_eq!(table.len(), 16);
        for row in table {
            assert_eq!(row["repetitions_ok"], 3, "{row}");
            for key in ["fit_seconds", "predict_seconds", "seconds_per_evaluation"] {
                for q in ["median", "d2", "d9"] {
                    assert!(row[key][q].as_f64().unwrap() > 0.0, "{key} {q} {row}");
                }
            }
            let e = row["variance_weighted_error"]["median"].as_f64().unwrap();
            assert!(e.is_finite() && e > 0.0);
        }
        assert_eq!(s["time_ratio_cogp_over_mvgp"].as_array().unwrap().len(), 8);
        assert_eq!(r.tables[0].csv.lines().count(), 1 + 16 * 3);
    }

    #[test]
    fn cases_cover_the_plan_and_seeds_pair_models() {
        let plan = Plan::new(false);
        let all = cases(&plan);
        assert_eq!(all.len(), 2 * 5 * 30 * 4);
        let a = Case {
            system: System::Pendulum,
            k: 256,
            rep: 3,
            kind: ModelKind::Mvgp,
            diag: false,
        };
        let b = Case {
            kind: ModelKind::Cogp,
            diag: true,
            ..a
        };
        assert_eq!(data_seed(0, &a), data_seed(0, &b));
        assert_ne!(data_seed(0, &a), data_seed(0, &Case { rep: 4, ..a }));
        assert_eq!(System::Ackermann.grid().len(), 3 * 400);
    }
}
