//! Shards of seed sweeps and of `calibration`, and their merge: the
//! scenario crate's functions, for `bayes_cbf.sweep` to run as Ray tasks.
//! Shards travel as text (JSON and CSV) so that any executor can move them.

use crate::args;
use crate::convert::{core_err, input_err, scenario_err};
use bayes_cbf::control::Fallback;
use bayes_cbf_scenario::experiments::calibration::{self, CalibrationPart};
use bayes_cbf_scenario::experiments::ExperimentArgs;
use bayes_cbf_scenario::sweep::{
    merge_sweeps, parse_rows_csv, rows_csv, run_seeds_until, summarise, SeedRange, Shard, SweepMeta,
};
use pyo3::prelude::*;

fn shard(index: usize, count: usize) -> PyResult<Shard> {
    format!("{index}/{count}").parse().map_err(scenario_err)
}

/// The description (JSON) of shard `index/count` of a sweep of `scenario`
/// over seeds `start..end` with `sets` (`key=value` overrides).
#[pyfunction]
#[pyo3(signature = (scenario, start, end, sets, index=0, count=1, goal_tolerance=1.0))]
pub fn sweep_meta(
    #[pyo3(from_py_with = args::scenario)] scenario: String,
    #[pyo3(from_py_with = args::start)] start: u64,
    #[pyo3(from_py_with = args::end)] end: u64,
    sets: Vec<String>,
    index: usize,
    count: usize,
    goal_tolerance: f64,
) -> PyResult<String> {
    let seeds: SeedRange = format!("{start}..{end}").parse().map_err(scenario_err)?;
    let meta = SweepMeta::new(
        &scenario,
        &sets,
        seeds,
        shard(index, count)?,
        goal_tolerance,
    )
    .map_err(scenario_err)?;
    serde_json::to_string(&meta).map_err(|e| input_err(e.to_string()))
}

fn parse_meta(text: &str) -> PyResult<SweepMeta> {
    serde_json::from_str(text).map_err(|e| input_err(format!("sweep shard description: {e}")))
}

/// Loads and validates scenario `name` with `sets` (`key=value`) at the
/// seed they give (`scenario::check`), raising `InputError` if it, an
/// override or a setting is bad.
#[pyfunction]
pub fn check_scenario(py: Python<'_>, name: &str, sets: Vec<String>) -> PyResult<()> {
    let checked = bayes_cbf_scenario::scenario::check(name, &sets);
    crate::warnings::after(py, checked.map_err(scenario_err))
}

/// Runs the shard described by `meta` (JSON) and returns its rows as CSV
/// (`sweep.csv`).
#[pyfunction]
pub fn sweep_shard(py: Python<'_>, meta: &str) -> PyResult<String> {
    let meta = parse_meta(meta)?;
    // Ctrl-C ends the runs under way and starts no others
    let (rows, signal) =
        crate::interrupt::interruptible(py, |stop| run_seeds_until(&meta, &|_, _| {}, stop));
    Ok(rows_csv(
        &crate::warnings::after(py, signal.map(|()| rows))?.map_err(scenario_err)?,
    ))
}

/// Merges shards `(meta JSON, rows CSV)` into the whole sweep: returns the
/// summary (`sweep_summary.json`) and the rows (`sweep.csv`).
#[pyfunction]
pub fn sweep_merge(parts: Vec<(String, String)>) -> PyResult<(String, String)> {
    let mut ps = Vec::new();
    for (i, (m, csv)) in parts.iter().enumerate() {
        let rows = parse_rows_csv(csv, &format!("shard {i}")).map_err(scenario_err)?;
        ps.push((parse_meta(m)?, rows));
    }
    let (meta, rows) = merge_sweeps(ps).map_err(scenario_err)?;
    let summary = summarise(&meta, &rows);
    let json = serde_json::to_string(&summary).map_err(|e| input_err(e.to_string()))?;
    Ok((json, rows_csv(&rows)))
}

/// The experiment's arguments and options, checked (the fallback's name,
/// the number of episodes).
fn calibration_options(
    seed: u64,
    quick: bool,
    episodes: Option<usize>,
    fallback: Option<&str>,
) -> PyResult<(ExperimentArgs, calibration::Options)> {
    let fallback = fallback
        .map(Fallback::parse)
        .transpose()
        .map_err(core_err)?;
    let options = calibration::Options { episodes, fallback };
    options.check(quick).map_err(scenario_err)?;
    Ok((ExperimentArgs { seed, quick }, options))
}

/// Checks the arguments of `calibration` (raising `InputError`), so that
/// `bayes_cbf.sweep.calibration` fails before any task runs.
#[pyfunction]
#[pyo3(signature = (seed=0, quick=false, episodes=None, fallback=None))]
pub fn calibration_check(
    #[pyo3(from_py_with = args::seed)] seed: u64,
    #[pyo3(from_py_with = args::quick)] quick: bool,
    #[pyo3(from_py_with = args::episodes)] episodes: Option<usize>,
    #[pyo3(from_py_with = args::fallback)] fallback: Option<&str>,
) -> PyResult<()> {
    calibration_options(seed, quick, episodes, fallback).map(|_| ())
}

/// Runs shard `index/count` of `calibration` and returns it (`part.json`);
/// `fallback` names every controller's fallback (default `relax`, the
/// experiment's).
#[pyfunction]
#[pyo3(signature = (seed=0, quick=false, episodes=None, index=0, count=1, fallback=None))]
pub fn calibration_shard(
    py: Python<'_>,
    #[pyo3(from_py_with = args::seed)] seed: u64,
    #[pyo3(from_py_with = args::quick)] quick: bool,
    #[pyo3(from_py_with = args::episodes)] episodes: Option<usize>,
    index: usize,
    count: usize,
    #[pyo3(from_py_with = args::fallback)] fallback: Option<&str>,
) -> PyResult<String> {
    let s = shard(index, count)?;
    let (args, options) = calibration_options(seed, quick, episodes, fallback)?;
    // Ctrl-C ends the episodes under way and starts no others
    let (part, signal) = crate::interrupt::interruptible(py, |stop| {
        calibration::run_shard_until(&args, &options, s, &|_: usize, _: usize| {}, stop)
    });
    let part = crate::warnings::after(py, signal.map(|()| part))?.map_err(scenario_err)?;
    serde_json::to_string(&part).map_err(|e| input_err(e.to_string()))
}

/// Merges calibration shards (`part.json` texts) and returns the summary
/// (`summary.json`) and the episode table (`episodes.csv`).
#[pyfunction]
pub fn calibration_merge(py: Python<'_>, parts: Vec<String>) -> PyResult<(String, String)> {
    let mut ps = Vec::new();
    for (i, p) in parts.iter().enumerate() {
        let part: CalibrationPart = serde_json::from_str(p)
            .map_err(|e| input_err(format!("calibration shard {i}: {e}")))?;
        ps.push(part);
    }
    let merged = py.detach(|| calibration::merge(ps)).map_err(scenario_err)?;
    let csv = merged
        .tables
        .first()
        .map(|t| t.csv.clone())
        .unwrap_or_default();
    let json = serde_json::to_string(&merged.summary).map_err(|e| input_err(e.to_string()))?;
    Ok((json, csv))
}
