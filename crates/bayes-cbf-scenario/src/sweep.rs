//! Monte Carlo sweeps: one scenario over a range of seeds, split into shards
//! that any scheduler can run, and merged back into exactly the result of
//! the unsharded sweep.
//!
//! A sweep runs [`run_scenario`](crate::scenario::run_scenario) once per seed (in parallel on rayon; each
//! run depends only on its seed, so the rows do not depend on the thread
//! count) and keeps one [`SweepRow`] per seed. Shard `I/N` runs the seeds
//! at positions `I, I + N, I + 2N, …` of the range. [`merge_sweeps`] checks
//! that the shards describe the same sweep and cover it exactly once, sorts
//! the rows by seed and recomputes the summary from them, so that sharded
//! and unsharded sweeps give the same counts and statistics to the bit
//! (timings aside).
//!
//! A seed whose run stops with an error (a numerical failure such as
//! `ControlError::Unresolved`, or a true system that leaves its domain) is
//! an outcome of the sweep, not the end of it: its row keeps the error,
//! the summary counts it as failing every outcome, and lists it. Only a
//! sweep in which every seed stopped is an error.
//!
//! Rows travel as CSV (`sweep.csv`): Rust prints the shortest decimal that
//! parses back to the same `f64`, and parses correctly rounded, so the
//! round trip is exact.

use crate::error::{Context, Error, Result};
use crate::scenario::{self, run_scenario_until};
use crate::stats::wilson;
use crate::{bail, err};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::str::FromStr;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Instant;

/// A range of seeds: `A..B` (B excluded) or `A..=B` (B included).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct SeedRange {
    /// First seed.
    pub start: u64,
    /// One past the last seed.
    pub end: u64,
}

impl FromStr for SeedRange {
    type Err = crate::Error;
    fn from_str(s: &str) -> Result<Self> {
        let bad = || err!("seeds '{s}': expected A..B (B excluded) or A..=B, e.g. 0..100");
        let (a, b, inclusive) = if let Some((a, b)) = s.split_once("..=") {
            (a, b, true)
        } else if let Some((a, b)) = s.split_once("..") {
            (a, b, false)
        } else {
            return Err(bad());
        };
        let too_large = || err!("seeds '{s}': seeds are at most {} (2^63 − 1)", i64::MAX);
        let seed = |v: &str| -> Result<u64> {
            let v = v.trim();
            match v.parse::<u64>() {
                Ok(n) => Ok(n),
                Err(_) if !v.is_empty() && v.bytes().all(|c| c.is_ascii_digit()) => {
                    Err(too_large())
                }
                Err(_) => Err(bad()),
            }
        };
        let (a, b) = (seed(a)?, seed(b)?);
        let end = if inclusive {
            b.checked_add(1).ok_or_else(too_large)?
        } else {
            b
        };
        if end <= a {
            bail!("seeds '{s}': the range is empty");
        }
        // a seed is a scenario's `seed`, a TOML integer
        if end - 1 > i64::MAX as u64 {
            bail!("seeds '{s}': seeds are at most {} (2^63 − 1)", i64::MAX);
        }
        Ok(SeedRange { start: a, end })
    }
}

impl SeedRange {
    /// The seeds, in order.
    pub fn seeds(&self) -> Vec<u64> {
        (self.start..self.end).collect()
    }
    /// Number of seeds.
    pub fn len(&self) -> usize {
        self.end.saturating_sub(self.start) as usize
    }
    /// True if the range holds no seed.
    pub fn is_empty(&self) -> bool {
        self.end <= self.start
    }
}

/// Shard `index` of `count` (`--shard I/N`, `0 ≤ I < N`): the items at
/// positions `I, I + N, I + 2N, …`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Shard {
    /// This shard, from 0.
    pub index: usize,
    /// Number of shards.
    pub count: usize,
}

impl Shard {
    /// The whole run as one shard.
    pub const WHOLE: Shard = Shard { index: 0, count: 1 };

    /// Whether the item at `position` belongs to this shard (never, for an
    /// invalid shard).
    pub fn owns(&self, position: usize) -> bool {
        self.count > 0 && position % self.count == self.index
    }

    /// Checks `1 ≤ count` and `index < count` (a shard read from a file may
    /// violate them).
    pub fn validate(&self) -> Result<()> {
        if self.count == 0 || self.index >= self.count {
            bail!(
                "shard {}/{}: expected I/N with 0 ≤ I < N",
                self.index,
                self.count
            );
        }
        Ok(())
    }
}

impl FromStr for Shard {
    type Err = crate::Error;
    fn from_str(s: &str) -> Result<Self> {
        let bad = |why: &str| err!("shard '{s}': {why}");
        let (i, n) = s
            .split_once('/')
            .ok_or_else(|| bad("expected I/N, e.g. 0/4 for the first of four shards"))?;
        let index: usize = i.trim().parse().map_err(|_| bad("I is not a number"))?;
        let count: usize = n.trim().parse().map_err(|_| bad("N is not a number"))?;
        if count == 0 {
            return Err(bad("N must be ≥ 1"));
        }
        if index >= count {
            return Err(bad("I must be < N (shards are numbered from 0)"));
        }
        Ok(Shard { index, count })
    }
}

/// One seed of a sweep.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SweepRow {
    /// The seed.
    pub seed: u64,
    /// Every barrier stayed ≥ 0 on the fine grid.
    pub safe: bool,
    /// Entered an obstacle (scenarios with obstacles) or a barrier went
    /// negative.
    pub collided: bool,
    /// Smallest barrier value over the run (all barriers).
    pub min_barrier: f64,
    /// Steps whose SOCP was infeasible.
    pub infeasible_steps: usize,
    /// Distance to the goal at the end (NaN without a goal; an empty cell
    /// in `sweep.csv`).
    pub goal_distance: f64,
    /// Median control step (µs).
    pub control_step_us: f64,
    /// Wall time of the run (s), up to its error if it stopped.
    pub wall_time_s: f64,
    /// Why the run stopped before its horizon, if it did, with the step it
    /// stopped at. Such a row's flags are `false`, its counts 0 and its
    /// other numbers NaN (empty cells in `sweep.csv`): the run has no
    /// outcome, and the summary counts it as failing each one.
    #[serde(default)]
    pub error: Option<String>,
    /// The kinds of warning the run issued ([`scenario::RunWarning::kind`]),
    /// in order; none for a run that stopped.
    #[serde(default)]
    pub warnings: Vec<String>,
}

impl SweepRow {
    /// The row of a run that stopped with `error` after `wall_time_s`;
    /// line breaks in the error become spaces, as in `sweep.csv`, so that
    /// sharded and unsharded sweeps summarise it alike.
    pub fn stopped(seed: u64, error: String, wall_time_s: f64) -> Self {
        let error = error.replace(['\n', '\r'], " ");
        SweepRow {
            seed,
            safe: false,
            collided: false,
            min_barrier: f64::NAN,
            infeasible_steps: 0,
            goal_distance: f64::NAN,
            control_step_us: f64::NAN,
            wall_time_s,
            error: Some(error),
            warnings: Vec::new(),
        }
    }

    /// The run reached its horizon.
    pub fn completed(&self) -> bool {
        self.error.is_none()
    }
}

/// The columns before `warnings` and `error`, with which `sweep.csv` files
/// written before those existed end.
macro_rules! outcome_columns {
    () => {
        "seed,safe,collided,min_barrier,infeasible_steps,goal_distance,control_step_us,wall_time_s"
    };
}
const HEADER_OUTCOMES: &str = outcome_columns!();
/// The header of files written before the `warnings` column existed.
const HEADER_ERROR: &str = concat!(outcome_columns!(), ",error");
const HEADER: &str = concat!(outcome_columns!(), ",warnings,error");

/// The `warnings` cell: the kinds, separated by `;`.
fn warnings_cell(kinds: &[String]) -> String {
    kinds.join(";")
}

/// The kinds of a `warnings` cell (`None`: not kinds, which are lower-case
/// words joined by `_`).
fn parse_warnings(cell: &str) -> Option<Vec<String>> {
    if cell.is_empty() {
        return Some(Vec::new());
    }
    let word = |k: &str| {
        !k.is_empty()
            && k.bytes()
                .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_')
    };
    let kinds: Vec<String> = cell.split(';').map(str::to_string).collect();
    kinds.iter().all(|k| word(k)).then_some(kinds)
}

/// An error message as one CSV cell: quoted, quotes doubled, line breaks
/// as spaces.
fn quote(message: &str) -> String {
    format!(
        "\"{}\"",
        message.replace(['\n', '\r'], " ").replace('"', "\"\"")
    )
}

/// The message of a cell written by [`quote`] (`None` for an empty cell).
fn unquote(cell: &str) -> Option<Option<String>> {
    if cell.is_empty() {
        return Some(None);
    }
    let inner = cell.strip_prefix('"')?.strip_suffix('"')?;
    if inner.replace("\"\"", "").contains('"') {
        return None;
    }
    Some(Some(inner.replace("\"\"", "\"")))
}

/// `sweep.csv`: a header and one line per row; a scenario without a goal
/// leaves `goal_distance` empty, as `trajectory.csv` leaves a missing value.
/// A run that stopped has only its seed, wall time and quoted error.
/// `warnings` lists the kinds of warning a run issued, separated by `;`.
pub fn rows_csv(rows: &[SweepRow]) -> String {
    let mut s = String::from(HEADER);
    s.push('\n');
    for r in rows {
        if let Some(e) = &r.error {
            s += &format!("{},,,,,,,{},,{}\n", r.seed, r.wall_time_s, quote(e));
            continue;
        }
        let goal = if r.goal_distance.is_nan() {
            String::new()
        } else {
            r.goal_distance.to_string()
        };
        s += &format!(
            "{},{},{},{},{},{},{},{},{},\n",
            r.seed,
            u8::from(r.safe),
            u8::from(r.collided),
            r.min_barrier,
            r.infeasible_steps,
            goal,
            r.control_step_us,
            r.wall_time_s,
            warnings_cell(&r.warnings)
        );
    }
    s
}

/// Parses `sweep.csv` (`name` labels errors); also reads the files written
/// before the `warnings` or `error` column existed.
pub fn parse_rows_csv(text: &str, name: &str) -> Result<Vec<SweepRow>> {
    let mut lines = text.lines();
    // fields, and the columns of warnings and error
    let (fields, warnings_at, error_at) = match lines.next().map(str::trim) {
        Some(HEADER) => (10, Some(8), Some(9)),
        Some(HEADER_ERROR) => (9, None, Some(8)),
        Some(HEADER_OUTCOMES) => (8, None, None),
        _ => bail!("{name}: expected the header '{HEADER}'"),
    };
    let column: Vec<&str> = HEADER.split(',').collect();
    let mut rows = Vec::new();
    for (i, line) in lines.enumerate() {
        let at = || format!("{name} line {}", i + 2);
        // the error, last, may hold commas
        let f: Vec<&str> = line.splitn(fields, ',').collect();
        if f.len() != fields || (fields == 8 && f[7].contains(',')) {
            bail!(
                "{}: expected {fields} fields, got {}",
                at(),
                line.split(',').count()
            );
        }
        let error = match error_at {
            None => None,
            Some(j) => unquote(f[j]).ok_or_else(|| {
                err!(
                    "{}: field {} (error) is not a quoted message: {}",
                    at(),
                    j + 1,
                    f[j]
                )
            })?,
        };
        let warnings = match warnings_at {
            None => Vec::new(),
            Some(j) => parse_warnings(f[j]).ok_or_else(|| {
                err!(
                    "{}: field {} (warnings) = '{}' is not kinds of warning separated by ';'",
                    at(),
                    j + 1,
                    f[j]
                )
            })?,
        };
        let num = |j: usize| -> Result<f64> {
            match f[j].parse::<f64>() {
                Ok(v) if !v.is_nan() => Ok(v),
                _ => Err(err!(
                    "{}: field {} ({}) = '{}' is not a number",
                    at(),
                    j + 1,
                    column[j],
                    f[j]
                )),
            }
        };
        let int = |j: usize| -> Result<u64> {
            f[j].parse::<u64>().map_err(|_| {
                err!(
                    "{}: field {} ({}) = '{}' is not an integer",
                    at(),
                    j + 1,
                    column[j],
                    f[j]
                )
            })
        };
        if let Some(error) = error {
            let filled = (1..7).chain(warnings_at).find(|&j| !f[j].is_empty());
            if let Some(j) = filled {
                bail!(
                    "{}: field {} = '{}': a run that stopped with an error has only its seed, wall time and error",
                    at(),
                    j + 1,
                    f[j]
                );
            }
            rows.push(SweepRow::stopped(int(0)?, error, num(7)?));
            continue;
        }
        let flag = |j: usize| -> Result<bool> {
            match f[j] {
                "0" => Ok(false),
                "1" => Ok(true),
                _ => Err(err!("{}: field {} = '{}' is not 0 or 1", at(), j + 1, f[j])),
            }
        };
        let (safe, min_barrier) = (flag(1)?, num(3)?);
        // a run is safe exactly when its smallest h is ≥ 0 (+inf: no barrier)
        if safe != (min_barrier >= 0.0) {
            bail!(
                "{}: field 2 (safe) = {} disagrees with field 4 (min_barrier) = {}",
                at(),
                f[1],
                f[3]
            );
        }
        rows.push(SweepRow {
            seed: int(0)?,
            safe,
            collided: flag(2)?,
            min_barrier,
            infeasible_steps: int(4)? as usize,
            goal_distance: if f[5].is_empty() { f64::NAN } else { num(5)? },
            control_step_us: num(6)?,
            wall_time_s: num(7)?,
            error: None,
            warnings,
        });
    }
    Ok(rows)
}

/// What a sweep is: the scenario with its overrides and the seed range,
/// and which shard of it a file holds (`shard.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SweepMeta {
    /// Scenario name or path.
    pub scenario: String,
    /// `--set` overrides, in order.
    pub sets: Vec<String>,
    /// The whole sweep's seeds.
    pub seeds: SeedRange,
    /// The shard this file holds.
    pub shard: Shard,
    /// Goal tolerance of the `goal_reached` count (m).
    pub goal_tolerance: f64,
    /// [`scenario::digest`] of the scenario with its overrides when the
    /// sweep was described: each shard checks that it runs that scenario,
    /// and [`merge_sweeps`] that the shards ran the same one (files
    /// written before it existed: `None`, and the path is compared).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scenario_digest: Option<String>,
}

impl SweepMeta {
    /// The sweep of `scenario` with overrides `sets` over `seeds`, shard
    /// `shard`, with the scenario's digest ([`scenario::digest`]).
    pub fn new(
        scenario: &str,
        sets: &[String],
        seeds: SeedRange,
        shard: Shard,
        goal_tolerance: f64,
    ) -> Result<Self> {
        Ok(SweepMeta {
            scenario: scenario.into(),
            sets: sets.to_vec(),
            seeds,
            shard,
            goal_tolerance,
            scenario_digest: Some(scenario::digest(scenario, sets)?),
        })
    }

    /// Whether `self` and `other` describe one sweep, whatever their
    /// shards: the same overrides, seeds and tolerance, and the same
    /// scenario (by digest where both have one, else by path).
    fn same_sweep(&self, other: &SweepMeta) -> bool {
        let same_scenario = match (&self.scenario_digest, &other.scenario_digest) {
            (Some(a), Some(b)) => a == b,
            _ => self.scenario == other.scenario,
        };
        same_scenario
            && (&self.sets, &self.seeds, self.goal_tolerance)
                == (&other.sets, &other.seeds, other.goal_tolerance)
    }
}

/// Runs the seeds of `meta.shard` (in parallel) and returns their rows in
/// seed order; `progress(done, total)` after each run. A run that stops
/// with an error gives a row with that error ([`SweepRow::stopped`]); the
/// whole sweep (not a shard, which [`merge_sweeps`] checks) is an error if
/// every run stopped ([`check_ran`]).
pub fn run_seeds(
    meta: &SweepMeta,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<Vec<SweepRow>> {
    run_seeds_until(meta, progress, &Arc::new(AtomicBool::new(false)))
}

/// [`run_seeds`], stopped once `stop` is set (by another thread: a Ctrl-C
/// handler, a deadline): the runs under way end before their next step,
/// the others do not start, and the sweep is
/// [`bayes_cbf::Error::Interrupted`], not rows.
pub fn run_seeds_until(
    meta: &SweepMeta,
    progress: &(dyn Fn(usize, usize) + Sync),
    stop: &Arc<AtomicBool>,
) -> Result<Vec<SweepRow>> {
    let _warnings = bayes_cbf::warnings::Scope::enter();
    meta.shard.validate()?;
    if meta.seeds.is_empty() {
        bail!(
            "seeds {}..{}: the range is empty",
            meta.seeds.start,
            meta.seeds.end
        );
    }
    // the shard's seeds: positions index, index + count, … of the range
    let (index, count) = (meta.shard.index, meta.shard.count);
    let owned = meta.seeds.len().saturating_sub(index).div_ceil(count);
    let seed_of = |j: usize| meta.seeds.start + (index + j * count) as u64;
    // one row per seed is kept: a sweep whose rows cannot be held is
    // refused here, not when the memory runs out (nor is a list of its
    // seeds made)
    drop(bayes_cbf::error::reserve::<SweepRow>("seeds", owned)?);
    // the scenario the sweep was described with (another machine may have
    // another copy of the file)
    if let Some(want) = &meta.scenario_digest {
        let now = scenario::digest(&meta.scenario, &meta.sets)?;
        if &now != want {
            bail!(
                "scenario '{}' is not the one the sweep was described with (digest {now}, \
                 expected {want}): the file changed since, or this machine has another copy",
                meta.scenario
            );
        }
    }
    // check the scenario once before fanning out, at the first seed
    let mut sets = meta.sets.clone();
    let first = if owned > 0 {
        seed_of(0)
    } else {
        meta.seeds.start
    };
    sets.push(format!("seed={first}"));
    scenario::check(&meta.scenario, &sets)?;
    let done = AtomicUsize::new(0);
    let total = owned;
    (0..owned)
        .into_par_iter()
        .map(|j| {
            let seed = seed_of(j);
            if stop.load(Ordering::Relaxed) {
                return Err(bayes_cbf::Error::Interrupted.into());
            }
            let mut sets = meta.sets.clone();
            sets.push(format!("seed={seed}"));
            // the seed's warnings: those of loading it and of its run
            let record = bayes_cbf::warnings::Record::start();
            let (sc, _) =
                scenario::load(&meta.scenario, &sets).with_context(|| format!("seed {seed}"))?;
            let started = Instant::now();
            // steps completed: the observer sees step k once it is done
            let mut completed = 0;
            let row = match run_scenario_until(&sc, |k, _| completed = k + 1, Arc::clone(stop)) {
                Ok(out) => {
                    let s = &out.summary;
                    let mut warnings: Vec<String> = scenario::RunWarning::of(record)
                        .into_iter()
                        .chain(s.warnings.iter().cloned())
                        .map(|w| w.kind)
                        .collect();
                    // a kind once, where it first came
                    let mut seen = std::collections::BTreeSet::new();
                    warnings.retain(|k| seen.insert(k.clone()));
                    SweepRow {
                        seed,
                        safe: s.safe,
                        collided: s.collided,
                        min_barrier: s.min_barrier.iter().cloned().fold(f64::INFINITY, f64::min),
                        infeasible_steps: s.infeasible_steps,
                        goal_distance: s.final_goal_distance.unwrap_or(f64::NAN),
                        control_step_us: s.control_step_us.p50,
                        wall_time_s: s.wall_time_s,
                        error: None,
                        warnings,
                    }
                }
                Err(e) if matches!(e.root(), Error::Core(bayes_cbf::Error::Interrupted)) => {
                    return Err(e)
                }
                Err(e) => SweepRow::stopped(
                    seed,
                    format!("stopped at step {completed}: {e}"),
                    started.elapsed().as_secs_f64(),
                ),
            };
            progress(done.fetch_add(1, Ordering::Relaxed) + 1, total);
            Ok(row)
        })
        .collect::<Result<Vec<SweepRow>>>()
        .and_then(|rows| {
            if meta.shard == Shard::WHOLE {
                check_ran(&rows)?;
            }
            Ok(rows)
        })
}

/// An error if every one of `rows` stopped with an error: then the
/// scenario, not a seed, is at fault, and the first error says why.
pub fn check_ran(rows: &[SweepRow]) -> Result<()> {
    match rows.first() {
        Some(first) if !rows.iter().any(SweepRow::completed) => bail!(
            "every one of the {} seeds stopped with an error; seed {}: {}",
            rows.len(),
            first.seed,
            first.error.as_deref().unwrap_or_default()
        ),
        _ => Ok(()),
    }
}

/// A count of episodes with an outcome, its rate and the 95 % Wilson
/// score interval of the rate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Count {
    /// Episodes with the outcome.
    pub count: usize,
    /// Episodes.
    pub of: usize,
    /// `count / of`.
    pub rate: f64,
    /// 95 % Wilson score interval of the rate.
    pub wilson_95: [f64; 2],
}

impl Count {
    /// `count` of `of` with its Wilson interval.
    pub fn new(count: usize, of: usize) -> Self {
        let (lo, hi) = wilson(count, of);
        Count {
            count,
            of,
            rate: count as f64 / of.max(1) as f64,
            wilson_95: [lo, hi],
        }
    }
}

/// The outcome counts of a sweep (`sweep_summary.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SweepSummary {
    /// Scenario name or path.
    pub scenario: String,
    /// `--set` overrides.
    pub sets: Vec<String>,
    /// Seeds run.
    pub seeds: SeedRange,
    /// Episodes.
    pub episodes: usize,
    /// Episodes that reached their horizon and whose barriers stayed ≥ 0.
    pub safe: Count,
    /// Episodes that reached their horizon and entered no obstacle.
    pub collision_free: Count,
    /// Episodes that reached their horizon without an infeasible step.
    pub no_infeasible_step: Count,
    /// Episodes that ended within `goal_tolerance` of the goal (scenarios
    /// with a goal).
    pub goal_reached: Option<Count>,
    /// The tolerance of `goal_reached` (m).
    pub goal_tolerance: f64,
    /// Smallest barrier value over the episodes that reached their horizon.
    pub min_barrier: f64,
    /// Seeds whose barriers went negative.
    pub unsafe_seeds: Vec<u64>,
    /// Infeasible steps over the episodes that reached their horizon.
    pub infeasible_steps: usize,
    /// Episodes that stopped with an error before their horizon: each
    /// fails every outcome above, and is not among `unsafe_seeds`.
    pub stopped: Count,
    /// Their seeds and errors.
    pub stopped_seeds: Vec<StoppedSeed>,
    /// Each kind of warning the runs issued, with the seeds that issued it
    /// (a sweep shows each kind once, for the first seed to issue it).
    #[serde(default)]
    pub warnings: BTreeMap<String, Vec<u64>>,
    /// Timing (not part of the bit-for-bit comparison of merged shards).
    pub timing: SweepTiming,
}

/// A seed whose run stopped with an error.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StoppedSeed {
    /// The seed.
    pub seed: u64,
    /// The error, with the step the run stopped at.
    pub error: String,
}

/// Timing of a sweep.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SweepTiming {
    /// Sum of the episodes' wall times (s): the CPU time of the sweep.
    pub episode_seconds: f64,
    /// Episodes per second per core (`episodes / episode_seconds`).
    pub episodes_per_core_second: f64,
    /// Median of the episodes' median control steps (µs).
    pub control_step_us_median: f64,
}

/// Each kind of warning that `rows` issued, with the seeds of the rows
/// that issued it, in the rows' order.
pub fn warned_seeds(rows: &[SweepRow]) -> BTreeMap<String, Vec<u64>> {
    let mut by_kind = BTreeMap::new();
    for r in rows {
        for k in &r.warnings {
            by_kind
                .entry(k.clone())
                .or_insert_with(Vec::new)
                .push(r.seed);
        }
    }
    by_kind
}

/// The summary of `rows` (sorted by seed).
pub fn summarise(meta: &SweepMeta, rows: &[SweepRow]) -> SweepSummary {
    let n = rows.len();
    let count = |f: &dyn Fn(&SweepRow) -> bool| Count::new(rows.iter().filter(|r| f(r)).count(), n);
    // an outcome of a run that reached its horizon
    let outcome = |f: &dyn Fn(&SweepRow) -> bool| count(&|r| r.completed() && f(r));
    let has_goal = rows.iter().any(|r| !r.goal_distance.is_nan());
    let secs: f64 = rows.iter().map(|r| r.wall_time_s).sum();
    let mut steps: Vec<f64> = rows
        .iter()
        .filter(|r| r.completed())
        .map(|r| r.control_step_us)
        .collect();
    steps.sort_by(f64::total_cmp);
    SweepSummary {
        scenario: meta.scenario.clone(),
        sets: meta.sets.clone(),
        seeds: meta.seeds,
        episodes: n,
        safe: outcome(&|r| r.safe),
        collision_free: outcome(&|r| !r.collided),
        no_infeasible_step: outcome(&|r| r.infeasible_steps == 0),
        goal_reached: has_goal.then(|| outcome(&|r| r.goal_distance <= meta.goal_tolerance)),
        goal_tolerance: meta.goal_tolerance,
        min_barrier: rows
            .iter()
            .filter(|r| r.completed())
            .map(|r| r.min_barrier)
            .fold(f64::INFINITY, f64::min),
        unsafe_seeds: rows
            .iter()
            .filter(|r| r.completed() && !r.safe)
            .map(|r| r.seed)
            .collect(),
        infeasible_steps: rows.iter().map(|r| r.infeasible_steps).sum(),
        stopped: count(&|r| !r.completed()),
        stopped_seeds: rows
            .iter()
            .filter_map(|r| {
                r.error.as_ref().map(|e| StoppedSeed {
                    seed: r.seed,
                    error: e.clone(),
                })
            })
            .collect(),
        warnings: warned_seeds(rows),
        timing: SweepTiming {
            episode_seconds: secs,
            episodes_per_core_second: n as f64 / secs.max(f64::MIN_POSITIVE),
            control_step_us_median: steps.get(steps.len() / 2).copied().unwrap_or(f64::NAN),
        },
    }
}

/// Checks that `shards` split one run into the same number of shards and
/// hold each shard exactly once; returns that number.
pub fn check_shard_set(shards: impl IntoIterator<Item = Shard>) -> Result<usize> {
    let shards: Vec<Shard> = shards.into_iter().collect();
    let Some(count) = shards.first().map(|s| s.count) else {
        bail!("merge: no shards given");
    };
    let mut seen = vec![false; count];
    for s in &shards {
        s.validate()?;
        if s.count != count {
            bail!(
                "merge: shard {}/{} does not belong to a split into {count}",
                s.index,
                s.count
            );
        }
        if std::mem::replace(&mut seen[s.index], true) {
            bail!("merge: shard {}/{count} is given twice", s.index);
        }
    }
    let missing: Vec<String> = (0..count)
        .filter(|&i| !seen[i])
        .map(|i| format!("{i}/{count}"))
        .collect();
    if !missing.is_empty() {
        bail!("merge: missing shard(s) {}", missing.join(", "));
    }
    Ok(count)
}

/// Checks that shards `parts` (each: its meta and rows) are the shards of
/// one sweep, each present once, and that some seed ran to its horizon
/// ([`check_ran`]); returns the whole sweep's meta and its rows sorted by
/// seed.
pub fn merge_sweeps(parts: Vec<(SweepMeta, Vec<SweepRow>)>) -> Result<(SweepMeta, Vec<SweepRow>)> {
    let Some((first, _)) = parts.first() else {
        bail!("merge: no shards given");
    };
    let whole = SweepMeta {
        shard: Shard::WHOLE,
        ..first.clone()
    };
    for (m, _) in &parts {
        if !m.same_sweep(first) {
            let digest = |m: &SweepMeta| {
                m.scenario_digest
                    .as_ref()
                    .map(|d| format!(" digest {d}"))
                    .unwrap_or_default()
            };
            bail!(
                "merge: shard {}/{} is of another sweep ({}{} {:?} seeds {}..{}) than shard {}/{} ({}{} {:?} seeds {}..{})",
                m.shard.index, m.shard.count, m.scenario, digest(m), m.sets, m.seeds.start, m.seeds.end,
                first.shard.index, first.shard.count, first.scenario, digest(first), first.sets, first.seeds.start, first.seeds.end
            );
        }
    }
    check_shard_set(parts.iter().map(|(m, _)| m.shard))?;
    if whole.seeds.is_empty() {
        bail!(
            "merge: the shards' seed range {}..{} is empty",
            whole.seeds.start,
            whole.seeds.end
        );
    }
    let mut rows: Vec<SweepRow> = bayes_cbf::error::reserve("seeds", whole.seeds.len())?;
    for (m, r) in parts {
        check_shard_seeds(&m, &r)?;
        rows.extend(r);
    }
    rows.sort_by_key(|r| r.seed);
    if rows.len() != whole.seeds.len() || rows.windows(2).any(|w| w[0].seed == w[1].seed) {
        bail!(
            "merge: the shards hold {} rows for {} seeds (a shard is incomplete or duplicated)",
            rows.len(),
            whole.seeds.len()
        );
    }
    check_ran(&rows)?;
    Ok((whole, rows))
}

/// Checks that shard `m`'s rows `r` are its seeds, each once: names a seed
/// that is not its own, one given twice, and the first one missing.
fn check_shard_seeds(m: &SweepMeta, r: &[SweepRow]) -> Result<()> {
    let (index, count) = (m.shard.index, m.shard.count);
    for row in r {
        let pos = row.seed.checked_sub(m.seeds.start).map(|p| p as usize);
        if row.seed >= m.seeds.end || !pos.is_some_and(|p| m.shard.owns(p)) {
            bail!(
                "merge: shard {index}/{count} holds seed {}, which is not one of its seeds",
                row.seed
            );
        }
    }
    let mut seeds: Vec<u64> = r.iter().map(|row| row.seed).collect();
    seeds.sort_unstable();
    if let Some(w) = seeds.windows(2).find(|w| w[0] == w[1]) {
        bail!("merge: shard {index}/{count} holds seed {} twice", w[0]);
    }
    // its own seeds, in order: the first that the sorted rows skip
    let positions = (index..m.seeds.len()).step_by(count.max(1));
    let owned = positions.len();
    let mut held = seeds.iter().peekable();
    for seed in positions.map(|p| m.seeds.start + p as u64) {
        if held.next_if_eq(&&seed).is_none() {
            bail!(
                "merge: shard {index}/{count} holds {} of its {} seeds: seed {seed} is missing \
                 (its run was interrupted, or its sweep.csv cut short)",
                seeds.len(),
                owned
            );
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A sweep whose rows cannot be held is refused by name before it
    /// runs (no list of its seeds is made); a shard beyond the seeds owns
    /// none and runs none.
    #[test]
    fn sweeps_too_large_to_hold_are_refused_before_they_run() {
        let seeds = SeedRange {
            start: 0,
            end: 100_000_000_000_000_000,
        };
        let meta = SweepMeta::new("double-integrator", &[], seeds, Shard::WHOLE, 0.5).unwrap();
        let e = run_seeds(&meta, &|_, _| {}).unwrap_err().to_string();
        assert!(e.contains("seeds") && e.contains("too large"), "{e}");
        let few = SweepMeta {
            seeds: SeedRange { start: 5, end: 7 },
            shard: Shard { index: 3, count: 4 },
            ..meta
        };
        assert!(run_seeds(&few, &|_, _| {}).unwrap().is_empty());
    }

    #[test]
    fn seed_ranges_and_shards_parse_or_name_the_option() {
        assert_eq!(
            "3..7".parse::<SeedRange>().unwrap().seeds(),
            vec![3, 4, 5, 6]
        );
        assert_eq!("3..=7".parse::<SeedRange>().unwrap().len(), 5);
        let last = "9223372036854775807..=9223372036854775807".parse::<SeedRange>();
        assert_eq!(last.unwrap().len(), 1);
        for big in [
            "0..=9223372036854775808",
            "18446744073709551615..=18446744073709551615",
            "0..99999999999999999999",
        ] {
            let e = big.parse::<SeedRange>().unwrap_err().to_string();
            assert!(e.contains("seeds are at most"), "{big}: {e}");
        }
        for bad in ["7..3", "3..3", "a..4", "5", "", "0..=9223372036854775808"] {
            let e = bad.parse::<SeedRange>().unwrap_err().to_string();
            assert!(e.contains("seeds '"), "{bad}: {e}");
        }
        assert_eq!(
            "1/3".parse::<Shard>().unwrap(),
            Shard { index: 1, count: 3 }
        );
        for bad in ["0/0", "3/2", "2/2", "1", "x/2", "-1/2"] {
            let e = bad.parse::<Shard>().unwrap_err().to_string();
            assert!(e.contains("shard '"), "{bad}: {e}");
        }
        // shards read from files are validated where they are used
        assert!(check_shard_set([Shard { index: 0, count: 0 }]).is_err());
        assert!(check_shard_set([Shard { index: 2, count: 2 }]).is_err());
        assert!(!Shard { index: 0, count: 0 }.owns(0));
        let mut bad = SweepMeta {
            scenario: "pendulum-safe".into(),
            sets: vec![],
            seeds: "0..2".parse().unwrap(),
            shard: Shard { index: 3, count: 2 },
            goal_tolerance: 1.0,
            scenario_digest: None,
        };
        assert!(run_seeds(&bad, &|_, _| {}).is_err());
        bad.shard = Shard::WHOLE;
        bad.seeds = SeedRange { start: 4, end: 4 };
        assert!(run_seeds(&bad, &|_, _| {}).is_err());
    }

    #[test]
    fn csv_round_trip_is_exact() {
        let rows = vec![
            SweepRow {
                seed: 4,
                safe: true,
                collided: false,
                min_barrier: 0.1 + 0.2,
                infeasible_steps: 3,
                goal_distance: f64::NAN,
                control_step_us: 1.0 / 3.0,
                wall_time_s: 1e-300,
                error: None,
                warnings: vec!["clamped_holds".into(), "mostly_infeasible".into()],
            },
            SweepRow {
                seed: 9,
                safe: false,
                collided: true,
                min_barrier: -f64::INFINITY,
                infeasible_steps: 0,
                goal_distance: 2.5e17,
                control_step_us: 7.0,
                wall_time_s: 0.0,
                error: None,
                warnings: Vec::new(),
            },
            SweepRow::stopped(12, "stopped at step 3: barrier 0: \"x\", y\nz".into(), 0.25),
        ];
        let text = rows_csv(&rows);
        // no literal NaN: a missing goal distance is an empty cell
        assert!(!text.contains("NaN"), "{text}");
        assert_eq!(text.lines().nth(1).unwrap().split(',').nth(5), Some(""));
        let back = parse_rows_csv(&text, "x").unwrap();
        assert_eq!(back.len(), 3);
        for (a, b) in rows.iter().zip(&back) {
            assert_eq!(a.min_barrier.to_bits(), b.min_barrier.to_bits());
            assert_eq!(a.goal_distance.is_nan(), b.goal_distance.is_nan());
            assert_eq!(a.control_step_us.to_bits(), b.control_step_us.to_bits());
            assert_eq!(a.wall_time_s.to_bits(), b.wall_time_s.to_bits());
            assert_eq!((a.seed, a.safe, a.collided), (b.seed, b.safe, b.collided));
            assert_eq!(a.warnings, b.warnings);
        }
        assert_eq!(
            text.lines().nth(1).unwrap().split(',').nth(8),
            Some("clamped_holds;mostly_infeasible")
        );
        // the error keeps its commas and quotes; its line break became a
        // space in the row already, so the rows are equal through the file
        assert_eq!(
            back[2].error.as_deref(),
            Some("stopped at step 3: barrier 0: \"x\", y z")
        );
        assert_eq!(back[2].error, rows[2].error);
        assert_eq!(text.lines().count(), 4);
        assert!(parse_rows_csv("seed\n", "x").is_err());
        // files written before the warnings column read as runs that
        // warned of nothing, and with it the same otherwise
        let drop_column = |l: &str, j: usize| {
            let mut f: Vec<&str> = l.splitn(10, ',').collect();
            f.remove(j);
            f.join(",") + "\n"
        };
        let before_warnings: String = text.lines().map(|l| drop_column(l, 8)).collect();
        assert!(before_warnings.starts_with(&format!("{HEADER_ERROR}\n")));
        let old = parse_rows_csv(&before_warnings, "x").unwrap();
        assert_eq!(old.len(), 3);
        assert!(old.iter().all(|r| r.warnings.is_empty()));
        assert_eq!(old[2].error, rows[2].error);
        assert_eq!(old[0].min_barrier.to_bits(), rows[0].min_barrier.to_bits());
        // files written before the error column read as runs that completed
        let legacy: String = before_warnings
            .lines()
            .take(3)
            .map(|l| drop_column(l, 8))
            .collect();
        assert!(legacy.starts_with(HEADER_OUTCOMES));
        let old = parse_rows_csv(&legacy, "x").unwrap();
        assert_eq!(old.len(), 2);
        assert!(old.iter().all(SweepRow::completed));
        assert_eq!(old[0].min_barrier.to_bits(), rows[0].min_barrier.to_bits());
        // a stopped row has no outcome; an error is a quoted message
        let stopped = text.lines().nth(3).unwrap();
        for (tampered, msg) in [
            (stopped.replacen(",,", ",1,", 1), "field 2 = '1'"),
            (
                stopped.replace("\"stopped", "stopped"),
                "not a quoted message",
            ),
            (format!("{},,,,,,,1.0,,\"a\"b\"", 3), "not a quoted message"),
            (
                format!("{},,,,,,,1.0,clamped_holds,\"a\"", 3),
                "field 9 = 'clamped_holds'",
            ),
        ] {
            let e = parse_rows_csv(&format!("{HEADER}\n{tampered}\n"), "x")
                .unwrap_err()
                .to_string();
            assert!(e.contains("x line 2") && e.contains(msg), "{e}");
        }
        // a tampered row: NaN is no number, 2 no flag
        let line1 = text.lines().nth(1).unwrap();
        let mut f: Vec<&str> = line1.split(',').collect();
        for (j, bad, msg) in [
            (3, "NaN", "field 4 (min_barrier) = 'NaN'"),
            (1, "2", "not 0 or 1"),
            (8, "Clamped holds", "field 9 (warnings) = 'Clamped holds'"),
            (8, "a;;b", "field 9 (warnings) = 'a;;b'"),
        ] {
            let keep = f[j];
            f[j] = bad;
            let tampered = format!("{HEADER}\n{}\n", f.join(","));
            let e = parse_rows_csv(&tampered, "x").unwrap_err().to_string();
            assert!(e.contains("x line 2") && e.contains(msg), "{e}");
            f[j] = keep;
        }
    }
}
