//! `bayes-cbf run` and `bayes-cbf list`.

use crate::logger::hold_warnings;
use crate::output::print_stdout;
use anyhow::Result;
use bayes_cbf::control::Fallback;
use bayes_cbf_plot::{comparison_figure, experiment_figures, write_figures};
use bayes_cbf_scenario::experiments::{self, calibration, ExperimentArgs, ExperimentResult, Sizes};
use bayes_cbf_scenario::io::{write_atomic, write_json, StagedDir};
use bayes_cbf_scenario::scenario::{self, trajectory_csv, RunOutput, BUILTIN};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};

/// Arguments of `bayes-cbf run`.
#[derive(Debug, Args)]
pub struct RunArgs {
    /// A built-in scenario or experiment (see `bayes-cbf list`) or a scenario TOML file.
    pub scenario: String,
    /// Output directory (default `runs/<scenario>`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Seed (overrides the scenario's), 0 to 2^63 − 1.
    #[arg(long, allow_negative_numbers = true,
          value_parser = clap::value_parser!(u64).range(..=i64::MAX as u64))]
    pub seed: Option<u64>,
    /// Override a field: `--set controller.probability=0.9` (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub sets: Vec<String>,
    /// Print the scenario (with overrides) as TOML and exit.
    #[arg(long)]
    pub print_config: bool,
    /// Reduced version of an experiment (speed-test, calibration, soak) for quick checks.
    #[arg(long)]
    pub quick: bool,
    /// Episodes per system and truth of `calibration` (default 200).
    #[arg(long, allow_hyphen_values = true)]
    pub episodes: Option<usize>,
    /// The controllers' fallback on an infeasible step in `calibration`:
    /// relax (default), max_margin (the library's `SafetySettings` default,
    /// and a scenario's without input bounds), brake or hold.
    /// (Scenarios set theirs with `--set controller.fallback=NAME`.)
    #[arg(long, value_name = "NAME", value_parser = parse_fallback)]
    pub fallback: Option<Fallback>,
    /// Control steps of `soak` (default 100000).
    #[arg(long, allow_hyphen_values = true)]
    pub steps: Option<usize>,
    /// Sliding window (observations kept) of `soak` (default 500).
    #[arg(long, allow_hyphen_values = true)]
    pub window: Option<usize>,
    /// Run the scenario once per seed, A..B (B excluded) or A..=B, in
    /// parallel: writes sweep.csv (one row per seed),
    /// sweep_summary.json (outcome counts with Wilson intervals) and
    /// shard.json (what was run).
    #[arg(long, value_name = "A..B", allow_hyphen_values = true)]
    pub seeds: Option<String>,
    /// Run only shard I of N (from 0) of a seed sweep or of calibration;
    /// combine the shards' directories with `bayes-cbf merge`.
    #[arg(long, value_name = "I/N", allow_hyphen_values = true)]
    pub shard: Option<String>,
}

/// `--fallback NAME`.
fn parse_fallback(s: &str) -> Result<Fallback, String> {
    Fallback::parse(s).map_err(|e| e.to_string())
}

/// A progress bar on stderr when it is a terminal outside CI, else hidden.
pub fn progress_bar(what: &str, unit: &str) -> ProgressBar {
    if std::io::stderr().is_terminal() && std::env::var_os("CI").is_none() {
        let style = ProgressStyle::with_template(&format!(
            "{what} {{elapsed_precise}} [{{bar:40}}] {{pos}}/{{len}} {unit}, ETA {{eta}}"
        ))
        .unwrap_or_else(|_| ProgressStyle::default_bar());
        ProgressBar::new(0).with_style(style)
    } else {
        ProgressBar::hidden()
    }
}

/// Runs `bayes-cbf run`.
pub fn run(a: &RunArgs) -> Result<()> {
    if let Some((name, _)) = experiments::EXPERIMENTS
        .iter()
        .find(|(n, _)| *n == a.scenario)
    {
        if !a.sets.is_empty() || a.print_config {
            anyhow::bail!("--set and --print-config apply to closed-loop scenarios, not to the experiment '{name}'");
        }
        let out = a
            .out
            .clone()
            .unwrap_or_else(|| PathBuf::from("runs").join(name));
        if a.seeds.is_some() {
            anyhow::bail!(
                "--seeds applies to closed-loop scenarios, not to the experiment '{name}'"
            );
        }
        let args = ExperimentArgs {
            seed: a.seed.unwrap_or(0),
            quick: a.quick,
        };
        let options = calibration::Options {
            episodes: a.episodes,
            fallback: a.fallback,
        };
        if let Some(shard) = &a.shard {
            if *name != "calibration" {
                anyhow::bail!(
                    "--shard applies to calibration and to seed sweeps (--seeds), not to '{name}'"
                );
            }
            return crate::sweep_cmd::run_calibration_shard(&args, &options, shard, &out);
        }
        return run_experiment(
            name,
            &out,
            &args,
            &Sizes {
                calibration: options,
                steps: a.steps,
                window: a.window,
            },
        );
    }
    if a.episodes.is_some() || a.fallback.is_some() || a.steps.is_some() || a.window.is_some() {
        anyhow::bail!(
            "--episodes, --fallback, --steps and --window apply to the experiments calibration and soak, not to the scenario '{}' (its fallback: --set controller.fallback=NAME)",
            a.scenario
        );
    }
    if a.quick {
        anyhow::bail!(
            "--quick applies to the experiments, not to the scenario '{}' (its length: --set steps=N)",
            a.scenario
        );
    }
    if let Some(seeds) = &a.seeds {
        if a.seed.is_some() || a.print_config {
            anyhow::bail!("--seeds runs many seeds: drop --seed and --print-config");
        }
        let (sc, _) = scenario::load(&a.scenario, &a.sets)?;
        let out = a
            .out
            .clone()
            .map_or_else(|| scenario::default_out_dir(&sc.name, "-seeds"), Ok)?;
        return crate::sweep_cmd::run_sweep(&a.scenario, &a.sets, seeds, a.shard.as_deref(), &out);
    }
    if a.shard.is_some() {
        anyhow::bail!("--shard applies to seed sweeps (--seeds) and calibration");
    }
    let mut sets = a.sets.clone();
    if let Some(seed) = a.seed {
        sets.push(format!("seed={seed}"));
    }
    let (sc, merged) = scenario::load(&a.scenario, &sets)?;
    if a.print_config {
        // what is printed is a scenario that runs (or fails at its seed only)
        scenario::check(&a.scenario, &sets)?;
        return print_stdout(&merged);
    }
    let out = a
        .out
        .clone()
        .map_or_else(|| scenario::default_out_dir(&sc.name, ""), Ok)?;
    // a signal from here on stops the run and removes what it staged
    crate::interrupt::stop_flag();
    let staged = StagedDir::new(&out)?;
    let (output, figures) = run_and_plot(&sc, staged.path(), true)?;
    crate::interrupt::check()?;
    staged.publish()?;
    let s = &output.summary;
    let opt = |v: Option<f64>| v.map_or("null".to_string(), |d| d.to_string());
    note!(
        "{}{}: collided {}, min barrier {:?}, min obstacle distance {}, final goal distance {}, infeasible steps {}, control step p50 {:.0} µs",
        sc.name, if s.oracle { " (oracle: the true dynamics as the model)" } else { "" }, s.collided, s.min_barrier, opt(s.min_obstacle_distance), opt(s.final_goal_distance), s.infeasible_steps, s.control_step_us.p50
    );
    note!(
        "wrote {}: summary.json, trajectory.csv{}",
        out.display(),
        figures
            .iter()
            .filter_map(|p| p.file_name())
            .map(|n| format!(", {}", n.to_string_lossy()))
            .collect::<String>()
    );
    Ok(())
}

/// Writes a run's `trajectory.csv` and `summary.json` into `dir`, the
/// summary last.
fn write_run(output: &RunOutput, dir: &Path) -> Result<()> {
    write_atomic(
        &dir.join("trajectory.csv"),
        trajectory_csv(output).as_bytes(),
    )?;
    write_json(&dir.join("summary.json"), &output.summary)?;
    Ok(())
}

/// Runs a scenario into `out`, writes its files and figures; returns the
/// run and the figure files.
fn run_and_plot(
    sc: &scenario::Scenario,
    out: &Path,
    progress: bool,
) -> Result<(RunOutput, Vec<PathBuf>)> {
    let show = progress && std::io::stderr().is_terminal();
    let name = sc.name.clone();
    let output = scenario::run_scenario_until(
        sc,
        |k, steps| {
            if show && (k % 10 == 0 || k + 1 == steps) {
                note_part!("\r{name}: step {}/{steps}", k + 1);
                if k + 1 == steps {
                    note!();
                }
            }
        },
        crate::interrupt::stop_flag(),
    )
    .inspect_err(|_| {
        if show {
            note!();
        }
    })?;
    // the summary last: a directory with a summary.json holds a complete run
    write_atomic(
        &out.join("trajectory.csv"),
        trajectory_csv(&output).as_bytes(),
    )?;
    let figures = write_figures(&output, out)?;
    write_json(&out.join("summary.json"), &output.summary)?;
    Ok((output, figures))
}

/// Runs experiment `name` and writes its summary, tables and figures into
/// `out`.
fn run_experiment(name: &str, out: &Path, args: &ExperimentArgs, sizes: &Sizes) -> Result<()> {
    let unit = match name {
        "calibration" => "episodes",
        "soak" => "steps",
        _ => "fits",
    };
    let staged = StagedDir::new(out)?;
    let bar = progress_bar(name, unit);
    let progress = |done: usize, total: usize| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    };
    let result = hold_warnings(&format!("the {name} run"), || {
        experiments::run_sized(name, args, sizes, &progress)
    })?;
    bar.finish_and_clear();
    write_experiment(name, &result, staged)
}

/// Writes an experiment's tables, figures and summary into the output
/// directory `staged` stands for, all of them or none.
pub fn write_experiment(name: &str, result: &ExperimentResult, staged: StagedDir) -> Result<()> {
    let stage = staged.path();
    for t in result.tables() {
        write_atomic(&stage.join(&t.file), t.csv.as_bytes())?;
    }
    if let ExperimentResult::AckermannTriggering(r) = result {
        for (dir, o) in &r.runs {
            write_run(o, &stage.join(dir))?;
        }
    }
    let figures = experiment_figures(result, stage)?;
    write_json(&stage.join("summary.json"), &result.summary())?;
    let in_top = |p: &&PathBuf| p.parent() == Some(stage);
    let figures: Vec<String> = figures
        .iter()
        .filter(in_top)
        .filter_map(|p| p.file_name())
        .map(|n| n.to_string_lossy().into_owned())
        .collect();
    let out = staged.out().to_path_buf();
    staged.publish()?;
    match result {
        ExperimentResult::Calibration(r) => note_part!("{}", r.console_table),
        ExperimentResult::Soak(r) if r.non_finite > 0 => anyhow::bail!(
            "soak: {} step(s) produced non-finite values (see {})",
            r.non_finite,
            out.join("summary.json").display()
        ),
        _ => {}
    }
    let files: Vec<String> = std::iter::once("summary.json".to_string())
        .chain(result.tables().iter().map(|t| t.file.clone()))
        .chain(figures)
        .collect();
    note!("{name}: wrote {}: {}", out.display(), files.join(", "));
    Ok(())
}

/// Runs `bayes-cbf list`.
pub fn list() -> Result<()> {
    let mut text = String::new();
    for (name, _) in BUILTIN {
        let desc = scenario::load(name, &[])
            .map(|(s, _)| s.description)
            .unwrap_or_default();
        text += &format!("{name:<24} {desc}\n");
    }
    for (name, desc) in experiments::EXPERIMENTS {
        text += &format!("{name:<24} {desc}\n");
    }
    print_stdout(&text)
}

/// The default job (`bayes-cbf` without a subcommand): the mean CBF against
/// the Bayes CBF on the Ackermann vehicle whose true wheelbase (12) differs
/// from the model's (1), side by side (paper, Fig. 7).
pub fn default_job() -> Result<()> {
    let root = PathBuf::from("runs/demo");
    // a signal from here on stops the runs and removes what they staged
    crate::interrupt::stop_flag();
    let staged = StagedDir::new(&root)?;
    let mut outputs = Vec::new();
    for (name, dir) in [
        ("ackermann-mean-cbf", "mean-cbf"),
        ("ackermann-bayes-cbf", "bayes-cbf"),
    ] {
        let (sc, _) = scenario::load(name, &[])?;
        outputs.push(run_and_plot(&sc, &staged.path().join(dir), true)?.0);
    }
    comparison_figure(
        &outputs[0],
        &outputs[1],
        &staged.path().join("comparison.png"),
    )?;
    crate::interrupt::check()?;
    staged.publish()?;
    let comparison = root.join("comparison.png");
    note!("Ackermann vehicle, true wheelbase 12, model wheelbase 1 (paper, Fig. 7):");
    for o in &outputs {
        let s = &o.summary;
        note!(
            "  {:<22} p = {:<4}  collided: {:<5}  closest obstacle distance {:>7.3} m  final distance to goal {:.2} m",
            o.scenario.name,
            o.scenario.controller.probability,
            s.collided,
            s.min_obstacle_distance.unwrap_or(f64::NAN),
            s.final_goal_distance.unwrap_or(f64::NAN)
        );
    }
    note!("wrote {} (side by side), and runs/demo/mean-cbf/, runs/demo/bayes-cbf/ (summary.json, trajectory.csv, trajectory.png, timeseries.png, animation.gif)", comparison.display());
    note!("more: `bayes-cbf list` shows every built-in scenario; `bayes-cbf run NAME` runs one");
    Ok(())
}
