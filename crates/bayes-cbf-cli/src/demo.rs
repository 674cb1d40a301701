//! `bayes-cbf demo`: the pendulum learning demo
//! ([`bayes_cbf_scenario::experiments::learning_demo`]), its files and its
//! report.

use crate::logger::hold_warnings;
use crate::output::print_stdout;
use anyhow::{Context, Result};
use bayes_cbf_scenario::experiments::learning_demo::{self, Settings};
use bayes_cbf_scenario::io::{write_atomic, write_json, StagedDir};
use clap::{Args, ValueEnum};
use serde_json::json;
use std::path::PathBuf;

/// How the demo collects its training data.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Sampling {
    /// Trajectories of 20 steps of dt = 0.01 s from random initial states;
    /// ẋ by finite differences at the step midpoints.
    Trajectory,
    /// States drawn uniformly on the evaluation box, torques on [-20, 20].
    Uniform,
}

/// Options of `bayes-cbf demo`.
#[derive(Debug, Clone, PartialEq, Args)]
pub struct DemoArgs {
    /// Output directory.
    #[arg(long, default_value = "runs/learning-demo")]
    pub out: PathBuf,
    /// Seed of every random choice (initial states, torques, fit).
    #[arg(long, allow_negative_numbers = true, default_value_t = Settings::default().seed)]
    pub seed: u64,
    /// Number of training samples k.
    #[arg(long, allow_negative_numbers = true, default_value_t = Settings::default().steps)]
    pub steps: usize,
    /// Number of held-out samples for the error of F(x)u̲.
    #[arg(long, allow_negative_numbers = true, default_value_t = Settings::default().heldout)]
    pub heldout: usize,
    /// Evaluation grid size per axis (θ and ω).
    #[arg(long, allow_negative_numbers = true, default_value_t = Settings::default().grid)]
    pub grid: usize,
    /// Random restarts of the hyperparameter optimiser.
    #[arg(long, allow_negative_numbers = true, default_value_t = Settings::default().restarts)]
    pub restarts: usize,
    /// Floor of the learned noise standard deviation of state component 0, σ·√A₀₀.
    #[arg(long, allow_negative_numbers = true, default_value_t = Settings::default().sigma_min)]
    pub sigma_min: f64,
    /// Kernel sees θ through (cos θ, sin θ), continuous across ±π.
    #[arg(long)]
    pub periodic: bool,
    /// Training-data design.
    #[arg(long, value_enum, default_value_t = Sampling::Trajectory)]
    pub sampling: Sampling,
}

/// Runs the demo and prints where its outputs went.
pub fn run_demo(a: &DemoArgs) -> Result<()> {
    let settings = Settings {
        seed: a.seed,
        steps: a.steps,
        heldout: a.heldout,
        grid: a.grid,
        restarts: a.restarts,
        sigma_min: a.sigma_min,
        periodic: a.periodic,
        sampling: match a.sampling {
            Sampling::Trajectory => learning_demo::Sampling::Trajectory,
            Sampling::Uniform => learning_demo::Sampling::Uniform,
        },
    };
    let staged = StagedDir::new(&a.out)?;
    let demo = hold_warnings("hyperparameter fitting", || learning_demo::run(&settings))?;
    let s = &demo.summary;
    let model_path = a.out.join("model.json");
    let grid_path = a.out.join(&demo.grid.file);
    let summary_path = a.out.join("summary.json");
    let stage = staged.path();
    write_atomic(
        &stage.join("model.json"),
        demo.model_file().to_json()?.as_bytes(),
    )?;
    write_atomic(&stage.join(&demo.grid.file), demo.grid.csv.as_bytes())?;
    let mut summary = serde_json::to_value(s).context("cannot serialise the summary")?;
    summary["files"] = json!({"model": model_path, "grid": grid_path, "summary": summary_path});
    write_json(&stage.join("summary.json"), &summary)?;
    staged.publish()?;

    let (g, r) = (a.grid, &s.rel_rmse);
    let report_text = format!(
        "pendulum learning demo (m = l = 1, g = 10, seed {seed}, {sampling:?} sampling)\n\
         \x20 trained MVGP (zero prior mean) on k = {k} samples (dt = {dt}), fit {fit_secs:.2} s, \
         log-likelihood {ll0:.1} -> {ll1:.1}\n\
         \x20 relative RMSE on the {g}x{g} grid of [-pi, pi) x [-6, 6]: f {ef:.3e}, g {eg:.3e}\n\
         \x20 relative RMSE of F(x)u on {nh} held-out samples: {efu:.3e}\n\
         \x20 wrote {mp}\n  wrote {gp}\n  wrote {sp}\n",
        seed = a.seed,
        sampling = a.sampling,
        k = s.training_samples,
        dt = s.dt,
        fit_secs = s.fit_seconds,
        ll0 = s.log_likelihood_initial,
        ll1 = s.log_likelihood,
        ef = r.f_grid,
        eg = r.g_grid,
        nh = s.heldout_samples,
        efu = r.fu_heldout,
        mp = model_path.display(),
        gp = grid_path.display(),
        sp = summary_path.display(),
    );
    print_stdout(&report_text)
}
