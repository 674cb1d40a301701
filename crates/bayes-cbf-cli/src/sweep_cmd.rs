//! Seed sweeps (`run NAME --seeds A..B`), shards (`--shard I/N`) and
//! `bayes-cbf merge`.

use crate::run_cmd::{progress_bar, write_experiment};
use anyhow::{bail, Context, Result};
use bayes_cbf_scenario::experiments::calibration::{self, CalibrationPart};
use bayes_cbf_scenario::experiments::{ExperimentArgs, ExperimentResult};
use bayes_cbf_scenario::io::{write_atomic, write_json, StagedDir};
use bayes_cbf_scenario::sweep::{
    merge_sweeps, parse_rows_csv, rows_csv, run_seeds_until, summarise, SeedRange, Shard,
    SweepMeta, SweepRow,
};
use clap::Args;
use std::path::{Path, PathBuf};

/// Distance to the goal that counts as reached in a sweep's summary (m).
pub const GOAL_TOLERANCE: f64 = 1.0;

/// Arguments of `bayes-cbf merge`.
#[derive(Debug, Args)]
pub struct MergeArgs {
    /// Output directories of the shards (each written by `--shard I/N`).
    #[arg(required = true)]
    pub dirs: Vec<PathBuf>,
    /// Where to write the merged result (default: the first directory's
    /// parent, `merged`).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// Runs a seed sweep of `scenario` into `out`.
pub fn run_sweep(
    scenario: &str,
    sets: &[String],
    seeds: &str,
    shard: Option<&str>,
    out: &Path,
) -> Result<()> {
    let shard = shard
        .map(str::parse::<Shard>)
        .transpose()?
        .unwrap_or(Shard::WHOLE);
    let meta = SweepMeta::new(
        scenario,
        sets,
        seeds.parse::<SeedRange>()?,
        shard,
        GOAL_TOLERANCE,
    )?;
    // a signal from here on stops the sweep and removes what it staged
    let stop = crate::interrupt::stop_flag();
    let staged = StagedDir::new(out)?;
    let bar = progress_bar(&format!("{scenario} seeds"), "runs");
    let rows = run_seeds_until(
        &meta,
        &|done, total| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        },
        &stop,
    )
    .inspect_err(|_| bar.abandon())?;
    bar.finish_and_clear();
    let stage = staged.path();
    write_atomic(&stage.join("sweep.csv"), rows_csv(&rows).as_bytes())?;
    write_json(&stage.join("shard.json"), &meta)?;
    let mut files = "sweep.csv, shard.json".to_string();
    let summary = (meta.shard == Shard::WHOLE).then(|| summarise(&meta, &rows));
    if let Some(summary) = &summary {
        write_json(&stage.join("sweep_summary.json"), summary)?;
        files += ", sweep_summary.json";
    }
    crate::interrupt::check()?;
    staged.publish()?;
    if let Some(summary) = &summary {
        note!(
            "{scenario}: {} seeds, safe {}/{}, no infeasible step {}/{}{}",
            summary.episodes,
            summary.safe.count,
            summary.episodes,
            summary.no_infeasible_step.count,
            summary.episodes,
            summary
                .goal_reached
                .as_ref()
                .map(|g| format!(", goal reached {}/{}", g.count, g.of))
                .unwrap_or_default()
        );
    }
    note_stopped(&rows);
    note_warnings(&rows);
    note!("wrote {}: {files}", out.display());
    Ok(())
}

/// Counts the seeds that issued each kind of warning: the sweep showed
/// each kind once, for the first seed to issue it.
fn note_warnings(rows: &[SweepRow]) {
    let by_kind = bayes_cbf_scenario::sweep::warned_seeds(rows);
    if by_kind.is_empty() {
        return;
    }
    let kinds: Vec<String> = by_kind
        .iter()
        .map(|(kind, seeds)| {
            let listed: Vec<String> = seeds.iter().take(5).map(u64::to_string).collect();
            let more = if seeds.len() > 5 { ", …" } else { "" };
            format!(
                "{kind} on {} of {} ({}{more})",
                seeds.len(),
                rows.len(),
                listed.join(", ")
            )
        })
        .collect();
    note!(
        "warnings by seed: {}; each kind was shown once, above, for the first seed to issue it; \
         sweep.csv lists each seed's",
        kinds.join("; ")
    );
}

/// Warns of the seeds whose runs stopped with an error, naming the first.
fn note_stopped(rows: &[SweepRow]) {
    let mut stopped = rows.iter().filter(|r| !r.completed());
    if let Some(first) = stopped.next() {
        note!(
            "warning: {} of {} seeds stopped with an error (counted as failing every outcome; each in sweep.csv): seed {}: {}",
            stopped.count() + 1,
            rows.len(),
            first.seed,
            first.error.as_deref().unwrap_or_default()
        );
    }
}

/// Runs shard `shard` of `calibration` into `out` (`part.json`).
pub fn run_calibration_shard(
    args: &ExperimentArgs,
    options: &calibration::Options,
    shard: &str,
    out: &Path,
) -> Result<()> {
    let shard: Shard = shard.parse()?;
    let staged = StagedDir::new(out)?;
    let bar = progress_bar("calibration shard", "episodes");
    let part = calibration::run_shard(args, options, shard, &|done: usize, total: usize| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })?;
    bar.finish_and_clear();
    write_json(&staged.path().join("part.json"), &part)?;
    staged.publish()?;
    note!(
        "calibration shard {}/{}: wrote {}: part.json (merge the shards with `bayes-cbf merge`)",
        shard.index,
        shard.count,
        out.display()
    );
    Ok(())
}

fn read(path: &Path) -> Result<String> {
    bayes_cbf_scenario::io::read_input_text(path)
        .with_context(|| format!("cannot read '{}'", path.display()))
}

/// Runs `bayes-cbf merge`.
pub fn run_merge(a: &MergeArgs) -> Result<()> {
    let out = a
        .out
        .clone()
        .unwrap_or_else(|| a.dirs[0].parent().unwrap_or(Path::new(".")).join("merged"));
    if let Some(d) = a.dirs.iter().find(|d| !d.is_dir()) {
        bail!("merge: '{}' is not a directory", d.display());
    }
    if let Ok(o) = out.canonicalize() {
        if let Some(d) = a
            .dirs
            .iter()
            .find(|d| d.canonicalize().is_ok_and(|d| d == o))
        {
            bail!(
                "merge: --out '{}' is the shard '{}': the merged result would overwrite it",
                out.display(),
                d.display()
            );
        }
    }
    let staged = StagedDir::new(&out).context("merge: --out")?;
    let calib = a
        .dirs
        .iter()
        .filter(|d| d.join("part.json").is_file())
        .count();
    let sweeps = a
        .dirs
        .iter()
        .filter(|d| d.join("shard.json").is_file())
        .count();
    if calib == a.dirs.len() {
        let mut parts = Vec::new();
        for d in &a.dirs {
            let p = d.join("part.json");
            let part: CalibrationPart = serde_json::from_str(&read(&p)?)
                .with_context(|| format!("'{}' is not a calibration shard", p.display()))?;
            part.check()
                .with_context(|| format!("merge: '{}'", p.display()))?;
            parts.push(part);
        }
        let result = ExperimentResult::Calibration(calibration::merge(parts)?);
        write_experiment("calibration", &result, staged)
    } else if sweeps == a.dirs.len() {
        let mut parts = Vec::new();
        for d in &a.dirs {
            let m = d.join("shard.json");
            let meta: SweepMeta = serde_json::from_str(&read(&m)?)
                .with_context(|| format!("'{}' is not a sweep shard", m.display()))?;
            meta.shard
                .validate()
                .with_context(|| format!("merge: '{}'", m.display()))?;
            let csv = d.join("sweep.csv");
            let rows = parse_rows_csv(&read(&csv)?, &csv.display().to_string())?;
            parts.push((meta, rows));
        }
        let (meta, rows) = merge_sweeps(parts)?;
        let summary = summarise(&meta, &rows);
        let stage = staged.path();
        write_atomic(&stage.join("sweep.csv"), rows_csv(&rows).as_bytes())?;
        write_json(&stage.join("shard.json"), &meta)?;
        write_json(&stage.join("sweep_summary.json"), &summary)?;
        staged.publish()?;
        note!(
            "merged {} shards of {} ({} seeds): wrote {}: sweep.csv, shard.json, sweep_summary.json",
            a.dirs.len(),
            meta.scenario,
            rows.len(),
            out.display()
        );
        note_stopped(&rows);
        Ok(())
    } else {
        let neither: Vec<String> = a
            .dirs
            .iter()
            .filter(|d| !d.join("part.json").is_file() && !d.join("shard.json").is_file())
            .map(|d| format!("'{}'", d.display()))
            .collect();
        let neither = if neither.is_empty() {
            String::new()
        } else {
            format!("; neither: {}", neither.join(", "))
        };
        bail!(
            "merge: every directory must hold a calibration shard (part.json) or every one a sweep shard (shard.json and sweep.csv); got {calib} and {sweeps} of {}{neither}",
            a.dirs.len(),
        )
    }
}
