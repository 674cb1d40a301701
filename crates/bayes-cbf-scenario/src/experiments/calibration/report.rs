//! Aggregation of the calibration episodes: rates with confidence
//! intervals per (system, truth, controller), the paired comparison of the
//! mean and Bayes CBFs, the calibration plot, the per-episode CSV and the
//! summary.

use super::episode::{
    ControllerKind, EpisodeStats, System, TruthKind, ZStats, ACTIVE_SLACK, CONTROLLERS, DT,
    FEATURES, INTERNAL_STEP, NOISE, NORMAL_QUANTILES, PROCESS_NOISE_MIS, PROCESS_NOISE_WELL,
};
use super::stats::{cluster_interval, pooled, proportion, sign_test_p, wilson};
use super::stats::{Pooled, Proportion};
use super::{Plan, Task};
use crate::experiments::Table;
use crate::experiments::{quantile, ExperimentArgs};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt::Write as _;

/// Everything counted for one (system, truth, controller).
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Row {
    pub system: System,
    pub truth: TruthKind,
    pub controller: ControllerKind,
    pub errors: usize,
    /// Per episode (in episode order; `None` when the run failed):
    /// `min h < 0`.
    pub violating: Vec<Option<bool>>,
    /// Per episode: `(steps with h < 0 on the fine grid, steps)`.
    pub h_steps: Vec<(usize, usize)>,
    /// Per episode: `(violated true conditions, solved steps)`.
    pub cbc: Vec<(usize, usize)>,
    /// Per episode: the same over active steps.
    pub active: Vec<(usize, usize)>,
    /// Per episode: the same over active steps from step `BURN_IN` (100) on.
    pub active_late: Vec<(usize, usize)>,
    /// Per episode: `(violated realised conditions, active steps)`.
    pub realised: Vec<(usize, usize)>,
    /// Per episode: `(infeasible steps, steps)`.
    pub infeasible: Vec<(usize, usize)>,
    pub min_h: Vec<f64>,
    pub min_distance: Vec<f64>,
    pub goal: Vec<bool>,
    pub non_finite: usize,
    /// Standardised true conditions (solved, active steps).
    pub z: [ZStats; 2],
}

impl Row {
    fn episodes(&self) -> usize {
        self.violating.iter().flatten().count()
    }
    fn episodes_violating(&self) -> usize {
        self.violating.iter().flatten().filter(|v| **v).count()
    }
    fn sum(v: &[(usize, usize)]) -> (usize, usize) {
        v.iter().fold((0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
    }
    /// The rate the controller promises not to exceed per solved step:
    /// `1 − p`, none for the mean CBF.
    fn requested(&self) -> Option<f64> {
        (!self.controller.mean).then_some(1.0 - self.controller.p)
    }
    /// Where the row sits on the plot's x axis: `1 − p` (0.5 for the mean CBF).
    fn plot_x(&self) -> f64 {
        1.0 - self.controller.p
    }
    fn label(&self) -> String {
        format!(
            "{} / {} / {}",
            self.system.name(),
            self.truth.name(),
            self.controller.name
        )
    }
}

/// One row per (system, truth, controller), in plan order.
pub(super) fn tables(plan: &Plan, results: &[(Task, EpisodeStats)]) -> Vec<Row> {
    let mut rows = Vec::new();
    for &(system, _) in &plan.systems {
        for truth in [TruthKind::WellSpecified, TruthKind::MisSpecified] {
            for (ci, kind) in CONTROLLERS.iter().enumerate() {
                let mut row = Row {
                    system,
                    truth,
                    controller: *kind,
                    errors: 0,
                    violating: vec![None; plan.episodes],
                    h_steps: Vec::new(),
                    cbc: Vec::new(),
                    active: Vec::new(),
                    active_late: Vec::new(),
                    realised: Vec::new(),
                    infeasible: Vec::new(),
                    min_h: Vec::new(),
                    min_distance: Vec::new(),
                    goal: Vec::new(),
                    non_finite: 0,
                    z: Default::default(),
                };
                for (t, s) in results {
                    if (t.system, t.truth, t.controller) != (system, truth, ci) {
                        continue;
                    }
                    if s.error.is_some() {
                        row.errors += 1;
                        continue;
                    }
                    row.violating[t.episode] = Some(s.min_h < 0.0);
                    row.h_steps.push((s.steps_h_violated, s.steps));
                    row.cbc.push((s.cbc_violations, s.solved_steps));
                    row.active.push((s.active_violations, s.active_steps));
                    row.active_late
                        .push((s.active_violations_late, s.active_steps_late));
                    if s.realised_active_steps > 0 {
                        row.realised
                            .push((s.realised_active_violations, s.realised_active_steps));
                    }
                    row.infeasible.push((s.infeasible_steps, s.steps));
                    row.min_h.push(s.min_h);
                    row.non_finite += s.non_finite;
                    if let Some(d) = s.min_distance {
                        row.min_distance.push(d);
                    }
                    if let Some(g) = s.goal_reached {
                        row.goal.push(g);
                    }
                    row.z[0].merge(&s.z[0]);
                    row.z[1].merge(&s.z[1]);
                }
                rows.push(row);
            }
        }
    }
    rows
}

/// The summary of one (system, truth, controller).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RowSummary {
    /// `vehicle` or `pendulum`.
    pub system: String,
    /// `well_specified` or `mis_specified`.
    pub truth: String,
    /// The controller's name.
    pub controller: String,
    /// Its probability `p`.
    pub p: f64,
    /// Whether it is the mean CBF (`c(p) = 0`).
    pub mean_cbf: bool,
    /// `1 − p`, the rate the controller promises not to exceed per solved
    /// step; none for the mean CBF.
    pub requested_violation_rate: Option<f64>,
    /// Episodes run to the end.
    pub episodes: usize,
    /// Episodes that failed.
    pub errors: usize,
    /// Step records with a value that is not finite.
    pub non_finite_records: usize,
    /// Episodes with `h < 0` on the fine grid.
    pub episodes_violating_h: Proportion,
    /// Steps with `h < 0` on the fine grid.
    pub steps_violating_h: Pooled,
    /// Steps whose true condition was violated.
    pub true_condition_violated: ConditionViolations,
    /// Active steps whose condition as realised over the step (the true
    /// condition with `F(x_k)u̲_k` replaced by `(x_{k+1} − x_k)/τ`: true
    /// dynamics and process noise) was negative: what the predictive
    /// condition promises.
    pub realised_condition_violated: Option<Pooled>,
    /// Standardised true conditions `z = (C_true − E[C]) / √Var[C]`.
    pub standardised_condition: SolvedActive<Option<ZSummary>>,
    /// Steps whose SOCP was infeasible.
    pub infeasible_steps: Pooled,
    /// Episodes in which the fallback was used.
    pub episodes_with_fallback: Proportion,
    /// Episodes that entered an obstacle (vehicle).
    pub collisions: Option<Proportion>,
    /// Episodes that reached the goal (vehicle).
    pub goal_reached: Option<Proportion>,
    /// The episodes' smallest `h`.
    pub min_h: MinH,
}

/// A pair of values over solved steps and over active steps.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SolvedActive<T> {
    /// Over the steps whose SOCP was solved.
    pub solved_steps: T,
    /// Over the solved steps whose chance constraint was active.
    pub active_steps: T,
}

/// Violated true conditions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ConditionViolations {
    /// Over solved steps.
    pub solved_steps: Pooled,
    /// Over active steps.
    pub active_steps: Pooled,
    /// Over active steps from step 100 of each episode on.
    pub active_steps_after_burn_in: Pooled,
    /// The violations the model expected, `Σ Φ(−E/√Var)`.
    pub expected_by_the_model: SolvedActive<f64>,
}

/// Distribution of the standardised conditions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ZSummary {
    /// Steps.
    pub steps: usize,
    /// Mean of `z`.
    pub mean: f64,
    /// Standard deviation of `z`.
    pub sd: f64,
    /// Fractions of `z` below the normal quantiles of these probabilities.
    pub fraction_below_normal_quantile: BTreeMap<String, Proportion>,
    /// The violations the model expected.
    pub expected_violations: f64,
}

/// The episodes' smallest barrier values.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MinH {
    /// Median.
    pub median: f64,
    /// 10 % quantile.
    pub q10: f64,
    /// Smallest.
    pub min: f64,
}

fn row_summary(r: &Row) -> RowSummary {
    let episodes = r.episodes();
    let with_fallback = r.infeasible.iter().filter(|(k, _)| *k > 0).count();
    let collisions = r.min_distance.iter().filter(|d| **d < 0.0).count();
    let goal = r.goal.iter().filter(|g| **g).count();
    RowSummary {
        system: r.system.name().into(),
        truth: r.truth.name().into(),
        controller: r.controller.name.into(),
        p: r.controller.p,
        mean_cbf: r.controller.mean,
        requested_violation_rate: r.requested(),
        episodes,
        errors: r.errors,
        non_finite_records: r.non_finite,
        episodes_violating_h: proportion(r.episodes_violating(), episodes),
        steps_violating_h: pooled(&r.h_steps),
        true_condition_violated: ConditionViolations {
            solved_steps: pooled(&r.cbc),
            active_steps: pooled(&r.active),
            active_steps_after_burn_in: pooled(&r.active_late),
            expected_by_the_model: SolvedActive {
                solved_steps: r.z[0].expected,
                active_steps: r.z[1].expected,
            },
        },
        realised_condition_violated: (!r.realised.is_empty()).then(|| pooled(&r.realised)),
        standardised_condition: SolvedActive {
            solved_steps: z_summary(&r.z[0]),
            active_steps: z_summary(&r.z[1]),
        },
        infeasible_steps: pooled(&r.infeasible),
        episodes_with_fallback: proportion(with_fallback, episodes),
        collisions: (!r.min_distance.is_empty())
            .then(|| proportion(collisions, r.min_distance.len())),
        goal_reached: (!r.goal.is_empty()).then(|| proportion(goal, r.goal.len())),
        min_h: MinH {
            median: quantile(&r.min_h, 0.5),
            q10: quantile(&r.min_h, 0.1),
            min: r.min_h.iter().cloned().fold(f64::INFINITY, f64::min),
        },
    }
}

/// Mean, standard deviation and lower-tail fractions of standardised
/// conditions, and the violations the model expected.
fn z_summary(z: &ZStats) -> Option<ZSummary> {
    if z.n == 0 {
        return None;
    }
    let (mean, sd) = z.mean_sd();
    Some(ZSummary {
        steps: z.n,
        mean,
        sd,
        fraction_below_normal_quantile: NORMAL_QUANTILES
            .iter()
            .zip(z.below)
            .map(|((q, _), k)| (format!("{q}"), proportion(k, z.n)))
            .collect(),
        expected_violations: z.expected,
    })
}

/// The paired episode comparison of the mean CBF with one Bayes CBF.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PairedComparison {
    /// `vehicle` or `pendulum`.
    pub system: String,
    /// `well_specified` or `mis_specified`.
    pub truth: String,
    /// The Bayes CBF's name.
    pub bayes: String,
    /// Episodes where only the mean CBF reached `h < 0`.
    pub only_mean_cbf_violates: usize,
    /// Episodes where only the Bayes CBF did.
    pub only_bayes_cbf_violates: usize,
    /// Episodes where both did.
    pub both_violate: usize,
    /// One-sided exact sign test that the mean CBF violates more often.
    pub p_value_mean_violates_more: f64,
}

/// Paired episode comparison of the mean CBF with each Bayes CBF of the
/// same (system, truth): discordant episodes and the one-sided exact sign
/// test that the mean CBF violates more often.
fn paired(rows: &[Row]) -> Vec<PairedComparison> {
    let mut out = Vec::new();
    for mean in rows.iter().filter(|r| r.controller.mean) {
        for bayes in rows
            .iter()
            .filter(|r| !r.controller.mean && (r.system, r.truth) == (mean.system, mean.truth))
        {
            let (mut only_mean, mut only_bayes, mut both) = (0, 0, 0);
            for (a, b) in mean.violating.iter().zip(&bayes.violating) {
                match (a, b) {
                    (Some(true), Some(false)) => only_mean += 1,
                    (Some(false), Some(true)) => only_bayes += 1,
                    (Some(true), Some(true)) => both += 1,
                    _ => {}
                }
            }
            out.push(PairedComparison {
                system: mean.system.name().into(),
                truth: mean.truth.name().into(),
                bayes: bayes.controller.name.into(),
                only_mean_cbf_violates: only_mean,
                only_bayes_cbf_violates: only_bayes,
                both_violate: both,
                p_value_mean_violates_more: sign_test_p(only_mean, only_mean + only_bayes),
            });
        }
    }
    out
}

/// Notes copied into `summary.json`.
const CI_NOTE: &str = "95 % Wilson score intervals (binomial). Step rates pool the steps of \
all episodes; their Wilson interval treats steps as independent, which they are not, so \
ci95_clustered gives a cluster-robust (ratio-estimator, by episode) normal interval as well.";
const CONDITION_NOTE: &str = "true_condition_violated: at every step whose SOCP was solved, \
the barrier condition (relative degree 1: dh/dt + alpha h; relative degree 2: \
d2h/dt2 + k1 dh/dt + k0 h) evaluated with the true dynamics at the applied control is \
negative. The controller promises P(condition >= 0) >= p under its posterior at each \
step, so with an exactly right model the expected rate over solved steps is at most 1 - p, \
and on active steps (slack <= 1e-5) it is 1 - p for the Gaussian factor (relative degree 1) \
and at most 1 - p for Cantelli's (relative degree 2, distribution free).";

/// `summary.json` of `calibration` (see the module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CalibrationSummary {
    /// `calibration`.
    pub scenario: String,
    /// The seed.
    pub seed: u64,
    /// Quick mode.
    pub quick: bool,
    /// Episodes per (system, truth).
    pub episodes: usize,
    /// Every controller's fallback on an infeasible step (`--fallback`).
    pub fallback: String,
    /// Control steps per episode, by system.
    pub steps_per_episode: BTreeMap<String, usize>,
    /// Control period (s).
    pub dt: f64,
    /// RK4 step of the simulation (s).
    pub internal_step: f64,
    /// The model's noise `σ`.
    pub model_noise: f64,
    /// Process noise of the truths.
    pub process_noise: ProcessNoise,
    /// Noise on the measured `ẋ` (none: process noise only).
    pub xdot_measurement_noise: f64,
    /// Random Fourier features of a well-specified truth.
    pub random_fourier_features: usize,
    /// Slack below which a constraint counts as active.
    pub active_slack: f64,
    /// The controllers compared.
    pub controllers: Vec<ControllerInfo>,
    /// How the mean CBF is run.
    pub mean_cbf_note: String,
    /// The intervals.
    pub ci_method: String,
    /// What a violated true condition is.
    pub true_condition_note: String,
    /// One row per (system, truth, controller).
    pub rows: Vec<RowSummary>,
    /// The mean CBF against each Bayes CBF.
    pub paired_mean_vs_bayes: Vec<PairedComparison>,
    /// Episodes that failed.
    pub errors: Vec<EpisodeError>,
    /// Worker threads.
    pub threads: usize,
    /// Wall time of the experiment (s).
    pub wall_seconds: f64,
    /// The files written beside the summary.
    pub files: Files,
}

/// Process noise of the truths.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProcessNoise {
    /// Well specified.
    pub well_specified: f64,
    /// Mis-specified.
    pub mis_specified: f64,
}

/// A compared controller.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ControllerInfo {
    /// Its name.
    pub name: String,
    /// Its `p`.
    pub p: f64,
    /// Whether it is the mean CBF.
    pub mean_cbf: bool,
}

/// An episode that failed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeError {
    /// `vehicle` or `pendulum`.
    pub system: String,
    /// `well_specified` or `mis_specified`.
    pub truth: String,
    /// Episode index.
    pub episode: usize,
    /// The controller's name.
    pub controller: String,
    /// What failed.
    pub error: String,
}

/// The files written beside the summary.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Files {
    /// The calibration plot.
    pub plot: String,
    /// One line per episode and controller.
    pub episodes: String,
}

/// The summary (see the module docs of `calibration`).
pub(super) fn summary(
    args: &ExperimentArgs,
    plan: &Plan,
    rows: &[Row],
    results: &[(Task, EpisodeStats)],
    wall: f64,
) -> CalibrationSummary {
    let errors = results
        .iter()
        .filter_map(|(t, s)| {
            s.error.as_ref().map(|e| EpisodeError {
                system: t.system.name().into(),
                truth: t.truth.name().into(),
                episode: t.episode,
                controller: CONTROLLERS[t.controller].name.into(),
                error: e.clone(),
            })
        })
        .collect();
    CalibrationSummary {
        scenario: "calibration".into(),
        seed: args.seed,
        quick: args.quick,
        episodes: plan.episodes,
        fallback: plan.fallback.name().into(),
        steps_per_episode: plan
            .systems
            .iter()
            .map(|(s, n)| (s.name().to_string(), *n))
            .collect(),
        dt: DT,
        internal_step: INTERNAL_STEP,
        model_noise: NOISE,
        process_noise: ProcessNoise {
            well_specified: PROCESS_NOISE_WELL,
            mis_specified: PROCESS_NOISE_MIS,
        },
        xdot_measurement_noise: 0.0,
        random_fourier_features: FEATURES,
        active_slack: ACTIVE_SLACK,
        controllers: CONTROLLERS
            .iter()
            .map(|c| ControllerInfo {
                name: c.name.into(),
                p: c.p,
                mean_cbf: c.mean,
            })
            .collect(),
        mean_cbf_note: "the mean CBF has c(p) = 0: the SOCP gets p = 0.5 at relative degree 1 \
            (Gaussian factor) and p = 1e-9 (Cantelli c = 3e-5) at relative degree 2"
            .into(),
        ci_method: CI_NOTE.into(),
        true_condition_note: CONDITION_NOTE.into(),
        rows: rows.iter().map(row_summary).collect(),
        paired_mean_vs_bayes: paired(rows),
        errors,
        threads: rayon::current_num_threads(),
        wall_seconds: wall,
        files: Files {
            plot: "calibration.png".into(),
            episodes: "episodes.csv".into(),
        },
    }
}

/// A fixed-width table of the main rates for the terminal.
pub(super) fn console_table(rows: &[Row]) -> String {
    let mut s = String::new();
    let pct = |k: usize, n: usize| {
        if n == 0 {
            "-".to_string()
        } else {
            let (lo, hi) = wilson(k, n);
            format!(
                "{:.2}% [{:.2}, {:.2}]",
                100.0 * k as f64 / n as f64,
                100.0 * lo,
                100.0 * hi
            )
        }
    };
    let _ = writeln!(
        s,
        "{:<58} {:>6} {:>24} {:>24} {:>24} {:>24} {:>24} {:>24} {:>12}",
        "system / truth / controller",
        "1-p",
        "episodes h<0",
        "true cond.<0 (solved)",
        "true cond.<0 (active)",
        "(active, k >= 100)",
        "realised cond.<0 (active)",
        "infeasible steps",
        "z mean/sd"
    );
    for r in rows {
        let (cv, cn) = Row::sum(&r.cbc);
        let (av, an) = Row::sum(&r.active);
        let (lv, ln) = Row::sum(&r.active_late);
        let (rv, rn) = Row::sum(&r.realised);
        let (iv, inn) = Row::sum(&r.infeasible);
        let req = r
            .requested()
            .map(|q| format!("{q:.3}"))
            .unwrap_or_else(|| "mean".into());
        let (zm, zsd) = r.z[0].mean_sd();
        let _ = writeln!(
            s,
            "{:<58} {:>6} {:>24} {:>24} {:>24} {:>24} {:>24} {:>24} {:>12}",
            r.label(),
            req,
            pct(r.episodes_violating(), r.episodes()),
            pct(cv, cn),
            pct(av, an),
            pct(lv, ln),
            pct(rv, rn),
            pct(iv, inn),
            format!("{zm:.2}/{zsd:.2}")
        );
    }
    s
}

/// Smallest rate shown on the log axis; zero counts sit here with their
/// upper confidence limit.
pub const FLOOR: f64 = 1e-5;

/// One plotted series of a calibration cell: empirical rates with 95 %
/// intervals against the requested `1 − p` (the mean CBF at 0.5, shifted
/// per series so that the bars do not overlap); zero rates at [`FLOOR`].
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Legend name.
    pub name: &'static str,
    /// Palette index.
    pub color: usize,
    /// Requested rates (shifted).
    pub xs: Vec<f64>,
    /// Empirical rates.
    pub mid: Vec<f64>,
    /// Lower ends of the intervals.
    pub lo: Vec<f64>,
    /// Upper ends of the intervals.
    pub hi: Vec<f64>,
}

/// The data of one panel of the calibration plot: a (system, truth) cell.
#[derive(Debug, Clone, PartialEq)]
pub struct Cell {
    /// `vehicle` or `pendulum`.
    pub system: &'static str,
    /// `well_specified` or `mis_specified`.
    pub truth: &'static str,
    /// Active-step, solved-step and episode rates.
    pub series: Vec<Series>,
}

/// Per (system, truth), empirical rates with 95 % intervals (step rates
/// cluster-robust by episode, Wilson's upper end where the count is zero;
/// episode rates Wilson) against the requested `1 − p`.
pub(super) fn plot_cells(rows: &[Row]) -> Vec<Cell> {
    let mut cells: Vec<(System, TruthKind)> = Vec::new();
    for r in rows {
        if !cells.contains(&(r.system, r.truth)) {
            cells.push((r.system, r.truth));
        }
    }
    let mut out = Vec::new();
    for &(system, truth) in &cells {
        let sel: Vec<&Row> = rows
            .iter()
            .filter(|r| (r.system, r.truth) == (system, truth))
            .collect();
        type Get = fn(&Row) -> Vec<(usize, usize)>;
        let series: [(&str, usize, f64, bool, Get); 3] = [
            ("true condition < 0, active steps", 0, 0.85, true, |r| {
                r.active.clone()
            }),
            ("true condition < 0, solved steps", 2, 1.0, true, |r| {
                r.cbc.clone()
            }),
            ("episodes with h < 0", 3, 1.18, false, |r| {
                vec![(r.episodes_violating(), r.episodes())]
            }),
        ];
        let mut cell = Cell {
            system: system.name(),
            truth: truth.name(),
            series: Vec::new(),
        };
        for (name, color, shift, clustered, get) in series {
            let (mut xs, mut mid, mut lo, mut hi) =
                (Vec::new(), Vec::new(), Vec::new(), Vec::new());
            for r in &sel {
                let counts = get(r);
                let (k, n) = Row::sum(&counts);
                if n == 0 {
                    continue;
                }
                let (l, h) = match (clustered && k > 0, cluster_interval(&counts)) {
                    (true, Some(ci)) => ci,
                    _ => wilson(k, n),
                };
                xs.push(r.plot_x() * shift);
                mid.push((k as f64 / n as f64).max(FLOOR));
                lo.push(l.max(FLOOR));
                hi.push(h.max(FLOOR));
            }
            cell.series.push(Series {
                name,
                color,
                xs,
                mid,
                lo,
                hi,
            });
        }
        out.push(cell);
    }
    out
}

/// One line per (task): the per-episode counts.
pub(super) fn episodes_csv(results: &[(Task, EpisodeStats)]) -> Table {
    let mut s = String::from(
        "system,truth,episode,controller,steps,min_h,steps_h_violated,solved_steps,cbc_violations,active_steps,active_violations,realised_active_steps,realised_active_violations,infeasible_steps,min_distance,goal_reached,error\n",
    );
    let opt = |v: Option<f64>| v.map(|x| format!("{x}")).unwrap_or_default();
    for (t, e) in results {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            t.system.name(),
            t.truth.name(),
            t.episode,
            CONTROLLERS[t.controller].name,
            e.steps,
            e.min_h,
            e.steps_h_violated,
            e.solved_steps,
            e.cbc_violations,
            e.active_steps,
            e.active_violations,
            e.realised_active_steps,
            e.realised_active_violations,
            e.infeasible_steps,
            opt(e.min_distance),
            e.goal_reached.map(|g| g.to_string()).unwrap_or_default(),
            e.error.as_deref().unwrap_or("").replace([',', '\n'], ";"),
        );
    }
    Table::new("episodes.csv", s)
}
