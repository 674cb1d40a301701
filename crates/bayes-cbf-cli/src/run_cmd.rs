//! `bayes-cbf run` and `bayes-cbf list`.

use crate::experiments;
use crate::scenario::{self, RunOptions, BUILTIN};
use anyhow::Result;
use clap::Args;
use std::path::PathBuf;

/// Arguments of `bayes-cbf run`.
#[derive(Debug, Args)]
pub struct RunArgs {
    /// A built-in scenario or experiment (see `bayes-cbf list`) or a scenario TOML file.
    pub scenario: String,
    /// Output directory (default `runs/<scenario>`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Seed (overrides the scenario's).
    #[arg(long)]
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
    /// Control steps of `soak` (default 100000).
    #[arg(long, allow_hyphen_values = true)]
    pub steps: Option<usize>,
    /// Sliding window (observations kept) of `soak` (default 500).
    #[arg(long, allow_hyphen_values = true)]
    pub window: Option<usize>,
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
        return experiments::run_sized(
            name,
            &experiments::ExperimentArgs {
                out,
                seed: a.seed.unwrap_or(0),
                quick: a.quick,
            },
            &experiments::Sizes {
                episodes: a.episodes,
                steps: a.steps,
                window: a.window,
            },
        );
    }
    if a.episodes.is_some() || a.steps.is_some() || a.window.is_some() {
        anyhow::bail!(
            "--episodes, --steps and --window apply to the experiments calibration and soak, not to the scenario '{}'",
            a.scenario
        );
    }
    let mut sets = a.sets.clone();
    if let Some(seed) = a.seed {
        sets.push(format!("seed={seed}"));
    }
    let (sc, merged) = scenario::load(&a.scenario, &sets)?;
    if a.print_config {
        print!("{merged}");
        return Ok(());
    }
    let out = a
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("runs").join(&sc.name));
    let (output, figures) = run_and_plot(&sc, &out)?;
    let s = &output.summary;
    eprintln!(
        "{}: collided {}, min barrier {}, min obstacle distance {}, final goal distance {}, infeasible steps {}, control step p50 {:.0} µs",
        sc.name, s["collided"], s["min_barrier"], s["min_obstacle_distance"], s["final_goal_distance"], s["infeasible_steps"], s["control_step_us"]["p50"].as_f64().unwrap_or(f64::NAN)
    );
    eprintln!(
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

/// Runs a scenario into `out` and writes its figures; returns the run and
/// the figure files.
fn run_and_plot(
    sc: &scenario::Scenario,
    out: &std::path::Path,
) -> Result<(scenario::RunOutput, Vec<PathBuf>)> {
    let output = scenario::run_scenario(
        sc,
        &RunOptions {
            out: out.to_path_buf(),
            progress: true,
        },
    )?;
    let figures = scenario::write_figures(&output, out)?;
    Ok((output, figures))
}

/// Runs `bayes-cbf list`.
pub fn list() -> Result<()> {
    for (name, text) in BUILTIN {
        let desc = toml::from_str::<scenario::Scenario>(text)
            .map(|s| s.description)
            .unwrap_or_default();
        println!("{name:<24} {desc}");
    }
    for (name, desc) in experiments::EXPERIMENTS {
        println!("{name:<24} {desc}");
    }
    Ok(())
}

/// The default job (`bayes-cbf` without a subcommand): the mean CBF against
/// the Bayes CBF on the Ackermann vehicle whose true wheelbase (12) differs
/// from the model's (1), side by side (paper, Fig. 7).
pub fn default_job() -> Result<()> {
    let root = PathBuf::from("runs/demo");
    let mut outputs = Vec::new();
    for (name, dir) in [
        ("ackermann-mean-cbf", "mean-cbf"),
        ("ackermann-bayes-cbf", "bayes-cbf"),
    ] {
        let (sc, _) = scenario::load(name, &[])?;
        let out = root.join(dir);
        outputs.push(run_and_plot(&sc, &out)?.0);
    }
    let comparison = root.join("comparison.png");
    scenario::comparison_figure(&outputs[0], &outputs[1], &comparison)?;
    eprintln!("Ackermann vehicle, true wheelbase 12, model wheelbase 1 (paper, Fig. 7):");
    for o in &outputs {
        let s = &o.summary;
        eprintln!(
            "  {:<22} p = {:<4}  collided: {:<5}  closest obstacle distance {:>7.3} m  final distance to goal {:.2} m",
            o.scenario.name,
            o.scenario.controller.probability,
            s["collided"],
            s["min_obstacle_distance"].as_f64().unwrap_or(f64::NAN),
            s["final_goal_distance"].as_f64().unwrap_or(f64::NAN)
        );
    }
    eprintln!("wrote {} (side by side), and runs/demo/mean-cbf/, runs/demo/bayes-cbf/ (summary.json, trajectory.csv, trajectory.png, timeseries.png, animation.gif)", comparison.display());
    eprintln!(
        "more: `bayes-cbf list` shows every built-in scenario; `bayes-cbf run NAME` runs one"
    );
    Ok(())
}
