//! `bayes-cbf`: learn control-affine dynamics `ẋ = F(x)u̲` with a
//! matrix-variate Gaussian process and query the learned model.
//!
//! Without a subcommand it runs the default job: the mean CBF against the
//! Bayes CBF on the Ackermann vehicle (paper, Fig. 7). Every error exits
//! non-zero with a one-line `error: ...` message on stderr naming the bad
//! field or value; JSON results go to stdout unless `--out` is given.

/// `eprintln!` that ignores a failed write: a full or closed stderr does
/// not end a run, nor change its exit status.
macro_rules! note {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stderr(), $($t)*);
    }};
}

/// `eprint!` that ignores a failed write (see `note!`).
macro_rules! note_part {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let _ = write!(std::io::stderr(), $($t)*);
    }};
}

mod bench;
mod commands;
mod demo;
mod interrupt;
mod logger;
mod output;
mod run_cmd;
mod safety_cmds;
mod sweep_cmd;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

/// Matrix-variate Gaussian-process learning of control-affine dynamics with
/// probabilistic control barrier functions (Dhiman et al., IEEE TAC 2021).
///
/// Without a subcommand, runs the default job: the mean CBF against the
/// Bayes CBF on the Ackermann vehicle, outputs in runs/demo/.
#[derive(Debug, Parser)]
#[command(name = "bayes-cbf", version, about, long_about = None)]
struct Cli {
    /// More diagnostics on stderr (-v info, -vv debug).
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Learn kernel lengthscales, A, B and noise_sigma from data by
    /// maximising the marginal likelihood, and write a model file.
    Fit(commands::FitArgs),
    /// Posterior mean M_k(x) and column covariance B_k(x, x) of F(x) at states.
    Predict(commands::PredictArgs),
    /// Exact mean and variance of a barrier condition under the posterior.
    Moments(safety_cmds::MomentsArgs),
    /// Safe control: the chance-constrained SOCP for one state.
    Control(safety_cmds::ControlArgs),
    /// Run a built-in scenario or experiment, or a scenario TOML file.
    Run(run_cmd::RunArgs),
    /// Combine the shards of a seed sweep or of calibration (directories
    /// written with --shard I/N) into the unsharded result.
    Merge(sweep_cmd::MergeArgs),
    /// List the built-in scenarios and experiments.
    List,
    /// Time the real workloads (control step, update, prediction, fits, streams) as JSON.
    Bench(bench::BenchArgs),
    /// Pendulum learning demo: simulate, fit, evaluate on a grid.
    Demo(demo::DemoArgs),
}

/// Collapses clap's multi-line message into one line, without the usage part.
fn one_line_clap_error(e: &clap::Error) -> String {
    let rendered = e.render().to_string();
    let mut parts: Vec<&str> = Vec::new();
    for line in rendered.lines() {
        let t = line.trim();
        if t.is_empty() {
            if !parts.is_empty() {
                break;
            }
            continue;
        }
        parts.push(t);
    }
    let msg = parts.join(" ");
    let msg = msg.strip_prefix("error: ").unwrap_or(&msg).to_string();
    format!("error: {msg} (see --help)")
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(c) => c,
        Err(e) => {
            use clap::error::ErrorKind;
            return match e.kind() {
                ErrorKind::DisplayHelp | ErrorKind::DisplayVersion => {
                    let _ = e.print();
                    ExitCode::SUCCESS
                }
                _ => {
                    note!("{}", one_line_clap_error(&e));
                    ExitCode::from(2)
                }
            };
        }
    };
    logger::init_logger(cli.verbose);
    let result = match &cli.command {
        Some(Command::Fit(a)) => commands::run_fit(a),
        Some(Command::Predict(a)) => commands::run_predict(a),
        Some(Command::Demo(a)) => demo::run_demo(a),
        Some(Command::Moments(a)) => safety_cmds::run_moments(a),
        Some(Command::Run(a)) => run_cmd::run(a),
        Some(Command::List) => run_cmd::list(),
        Some(Command::Merge(a)) => sweep_cmd::run_merge(a),
        Some(Command::Bench(a)) => bench::run_bench(a),
        Some(Command::Control(a)) => safety_cmds::run_control(a),
        None => run_cmd::default_job(),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) if interrupt::is_interrupted(&e) => {
            note!("interrupted: nothing was written");
            ExitCode::from(interrupt::INTERRUPTED)
        }
        Err(e) => {
            // `{:#}` joins the context chain with ": " on one line.
            let msg = format!("{e:#}").replace('\n', " ");
            note!("error: {msg}");
            ExitCode::FAILURE
        }
    }
}
