//! `bayes-cbf bench`: timings of the real workloads as JSON
//! ([`bayes_cbf_scenario::bench`]).

use anyhow::Result;
use bayes_cbf_scenario::bench::run_bench as measure;
use clap::Args;
use std::path::PathBuf;

/// Arguments of `bayes-cbf bench`.
#[derive(Debug, Args)]
pub struct BenchArgs {
    /// Reduced sizes and repetitions (seconds instead of minutes).
    #[arg(long)]
    pub quick: bool,
    /// Write the JSON here instead of stdout (`-`: stdout).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Threads for faer's dense linear algebra (default 1: single core).
    #[arg(long, allow_negative_numbers = true, default_value_t = 1)]
    pub threads: usize,
}

/// Runs `bayes-cbf bench`.
pub fn run_bench(a: &BenchArgs) -> Result<()> {
    let result = measure(a.quick, a.threads, &|stage| note!("bench: {stage}"))?;
    crate::output::emit(&result, &a.out, true)
}
