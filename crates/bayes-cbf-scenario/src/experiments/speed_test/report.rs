//! Aggregation and tables of the speed test: medians and deciles per
//! `(system, k, model, variant)`, CoGP/MVGP time ratios and the per-fit
//! CSV.

use super::{variant, Outcome, System, MAX_ITERS};
use crate::experiments::{quantile, ModelKind, Table};
use serde::Serialize;

/// Why [`MAX_ITERS`] is what it is (copied into `summary.json`).
pub(super) const ITERATION_NOTE: &str = "L-BFGS is capped at max_iters iterations per \
start (the CoGP full fit runs its diagonal pre-fit with the same cap). Uncapped (100), a CoGP \
full fit of 200 pendulum samples took 1000-1350 objective evaluations; at k = 1024 one costs \
about 0.35 s, so those 30 fits alone would take hours. With the cap of 15 the full run \
(1200 fits) took 1209 s on one core of a 2-vCPU Intel Xeon; CoGP full fits use 46-50 \
evaluations, the other models 21-28, and the capped fits are near-calibrated \
(variance-weighted error close to sqrt(n(1+m))).";

/// Why timings depend on the thread count (copied into `summary.json`).
pub(super) const TIMING_NOTE: &str = "Fits run in parallel on `threads` rayon threads \
(RAYON_NUM_THREADS). Concurrent fits slow each other down (about 2x per fit with 2 threads \
on a 2-vCPU machine, unevenly), so compare timings from RAYON_NUM_THREADS=1 runs; the \
errors do not depend on the thread count.";

/// Median and 2nd/9th deciles of a sample.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Stats {
    /// Median.
    pub median: f64,
    /// 2nd decile (0.2 quantile).
    pub d2: f64,
    /// 9th decile (0.9 quantile).
    pub d9: f64,
}

impl Stats {
    fn of(v: &[f64]) -> Self {
        Stats {
            median: quantile(v, 0.5),
            d2: quantile(v, 0.2),
            d9: quantile(v, 0.9),
        }
    }
}

/// One row of the table.
#[derive(Debug, Clone, PartialEq)]
pub struct Row {
    /// System.
    pub system: System,
    /// Training points.
    pub k: usize,
    /// Model.
    pub kind: ModelKind,
    /// Diagonal covariances.
    pub diag: bool,
    /// Repetitions that succeeded.
    pub ok: usize,
    /// Repetitions that failed.
    pub failed: usize,
    /// Held-out points (over all repetitions) that needed extended jitter.
    pub extended_jitter: usize,
    /// Fit time (s).
    pub fit: Stats,
    /// Fit time per likelihood evaluation (s).
    pub per_eval: Stats,
    /// Likelihood evaluations per fit.
    pub evaluations: Stats,
    /// Time to predict on the 400-point grid (s).
    pub predict: Stats,
    /// Variance-weighted error (Eq. 33), held out.
    pub vwe: Stats,
    /// RMSE of `F`, held out.
    pub rmse: Stats,
}

/// A row as it appears in `summary.json`.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[allow(non_snake_case)]
pub struct RowSummary {
    /// System.
    pub system: &'static str,
    /// Training points.
    pub k: usize,
    /// Model.
    pub model: &'static str,
    /// `full` or `diag`.
    pub variant: &'static str,
    /// Repetitions that succeeded.
    pub repetitions_ok: usize,
    /// Repetitions that failed.
    pub failures: usize,
    /// Held-out points that needed extended jitter.
    pub extended_jitter_points: usize,
    /// Fit time (s).
    pub fit_seconds: Stats,
    /// Fit time per likelihood evaluation (s).
    pub seconds_per_evaluation: Stats,
    /// Likelihood evaluations per fit.
    pub evaluations: Stats,
    /// Time to predict on the grid (s).
    pub predict_seconds: Stats,
    /// Variance-weighted error (Eq. 33), held out.
    pub variance_weighted_error: Stats,
    /// RMSE of `F`, held out.
    pub rmse_F: Stats,
}

impl Row {
    /// The row as it appears in `summary.json`.
    pub fn summary(&self) -> RowSummary {
        RowSummary {
            system: self.system.name(),
            k: self.k,
            model: self.kind.name(),
            variant: variant(self.diag),
            repetitions_ok: self.ok,
            failures: self.failed,
            extended_jitter_points: self.extended_jitter,
            fit_seconds: self.fit,
            seconds_per_evaluation: self.per_eval,
            evaluations: self.evaluations,
            predict_seconds: self.predict,
            variance_weighted_error: self.vwe,
            rmse_F: self.rmse,
        }
    }
}

/// CoGP/MVGP ratio of median times at one `(system, k, variant)`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Ratio {
    /// System.
    pub system: &'static str,
    /// Training points.
    pub k: usize,
    /// `full` or `diag`.
    pub variant: &'static str,
    /// Fit time ratio.
    pub fit: f64,
    /// Time per likelihood evaluation ratio.
    pub per_evaluation: f64,
    /// Prediction time ratio.
    pub predict: f64,
    /// The factorisation-cost theory `n³`.
    pub theory_n3: f64,
}

/// The machine, for the record.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Machine {
    /// CPU model.
    pub cpu: String,
    /// Cores available.
    pub cores: usize,
    /// Operating system.
    pub os: &'static str,
    /// L-BFGS cap of the full run.
    pub max_iters_full_run: u64,
}

/// Groups `outcomes` (sorted by system, k, model, variant) into rows.
pub(super) fn table(outcomes: &[Outcome]) -> Vec<Row> {
    let mut rows: Vec<Row> = Vec::new();
    for group in outcomes.chunk_by(|a, b| {
        let (x, y) = (a.case, b.case);
        (x.system, x.k, x.kind, x.diag) == (y.system, y.k, y.kind, y.diag)
    }) {
        let c = group[0].case;
        let good: Vec<&Outcome> = group.iter().filter(|o| o.error.is_none()).collect();
        let col = |f: &dyn Fn(&Outcome) -> f64| {
            Stats::of(&good.iter().map(|o| f(o)).collect::<Vec<f64>>())
        };
        rows.push(Row {
            system: c.system,
            k: c.k,
            kind: c.kind,
            diag: c.diag,
            ok: good.len(),
            failed: group.len() - good.len(),
            extended_jitter: good.iter().map(|o| o.extended_jitter).sum(),
            fit: col(&|o| o.fit_seconds),
            per_eval: col(&|o| o.fit_seconds / o.evaluations.max(1) as f64),
            evaluations: col(&|o| o.evaluations as f64),
            predict: col(&|o| o.predict_seconds),
            vwe: col(&|o| o.vwe),
            rmse: col(&|o| o.rmse_f),
        });
    }
    rows
}

pub(super) fn find(
    table: &[Row],
    s: System,
    k: usize,
    kind: ModelKind,
    diag: bool,
) -> Option<&Row> {
    table
        .iter()
        .find(|r| (r.system, r.k, r.kind, r.diag) == (s, k, kind, diag))
}

/// CoGP/MVGP ratios of the median fit, per-evaluation and predict times
/// per `(system, k, variant)`, with the factorisation-cost theory `n³`.
pub(super) fn ratios(table: &[Row]) -> Vec<Ratio> {
    let mut out = Vec::new();
    for r in table.iter().filter(|r| r.kind == ModelKind::Mvgp) {
        if let Some(c) = find(table, r.system, r.k, ModelKind::Cogp, r.diag) {
            let n = super::System::state_dim(r.system) as f64;
            out.push(Ratio {
                system: r.system.name(),
                k: r.k,
                variant: variant(r.diag),
                fit: c.fit.median / r.fit.median,
                per_evaluation: c.per_eval.median / r.per_eval.median,
                predict: c.predict.median / r.predict.median,
                theory_n3: n * n * n,
            });
        }
    }
    out
}

/// Every fit as one CSV row (NaN for failed fits).
pub(super) fn runs_csv(outcomes: &[Outcome]) -> Table {
    let mut s = String::from("system,k,rep,model,variant,fit_seconds,evaluations,predict_seconds,variance_weighted_error,extended_jitter_points,rmse_F,log_likelihood,error\n");
    for o in outcomes {
        let c = o.case;
        let err = o
            .error
            .as_deref()
            .unwrap_or("")
            .replace([',', '\n', '"'], " ");
        s.push_str(&format!(
            "{},{},{},{},{},{},{},{},{},{},{},{},{}\n",
            c.system.name(),
            c.k,
            c.rep,
            c.kind.name(),
            variant(c.diag),
            o.fit_seconds,
            o.evaluations,
            o.predict_seconds,
            o.vwe,
            o.extended_jitter,
            o.rmse_f,
            o.log_likelihood,
            err
        ));
    }
    Table::new("runs.csv", s)
}

/// CPU model and core count, for the record.
pub(super) fn machine() -> Machine {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|t| {
            t.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| "unknown".into());
    let cores = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);
    Machine {
        cpu,
        cores,
        os: std::env::consts::OS,
        max_iters_full_run: MAX_ITERS,
    }
}
