//! `bayes-cbf moments` and `bayes-cbf control` (interfaces.md).

use anyhow::{bail, Context, Result};
use bayes_cbf::barrier::McSettings;
use bayes_cbf::control::{Fallback, SafetySettings};
use bayes_cbf_scenario::barrier_file::BarrierSpec;
use bayes_cbf_scenario::model_file::ModelFile;
use bayes_cbf_scenario::parse::parse_vector;
use bayes_cbf_scenario::queries::{check_barrier, condition_moments, control_step};
use clap::Args;
use serde::Serialize;
use std::path::PathBuf;

/// The Monte Carlo moments of barriers of relative degree > 2 (no closed
/// form exists), in `moments` and `control` alike.
#[derive(Debug, Args)]
pub struct McArgs {
    /// Monte Carlo draws for relative degree > 2.
    #[arg(long, allow_negative_numbers = true, default_value_t = 20_000)]
    pub samples: usize,
    /// Finite-difference step of the Monte Carlo Lie derivatives.
    #[arg(long, default_value_t = 1e-2, allow_hyphen_values = true)]
    pub step: f64,
    /// Seed of the Monte Carlo draws.
    #[arg(long, allow_negative_numbers = true, default_value_t = 0)]
    pub seed: u64,
}

impl McArgs {
    fn settings(&self) -> McSettings {
        McSettings {
            samples: self.samples,
            step: self.step,
            seed: self.seed,
        }
    }
}

/// Arguments of `bayes-cbf moments`.
#[derive(Debug, Args)]
pub struct MomentsArgs {
    /// Model file (see `bayes-cbf fit`).
    #[arg(long)]
    pub model: PathBuf,
    /// Barrier file.
    #[arg(long)]
    pub barrier: PathBuf,
    /// State, comma separated.
    #[arg(long, allow_hyphen_values = true)]
    pub x: String,
    /// Control, comma separated.
    #[arg(long, allow_hyphen_values = true)]
    pub u: String,
    #[command(flatten)]
    pub mc: McArgs,
    /// Write the JSON here instead of stdout (`-`: stdout).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// Arguments of `bayes-cbf control`.
#[derive(Debug, Args)]
pub struct ControlArgs {
    /// Model file (see `bayes-cbf fit`).
    #[arg(long)]
    pub model: PathBuf,
    /// Barrier file; repeat for several barriers.
    #[arg(long = "barrier", required = true)]
    pub barriers: Vec<PathBuf>,
    /// State, comma separated.
    #[arg(long, allow_hyphen_values = true)]
    pub x: String,
    /// Required probability of each barrier condition, in (0, 1).
    #[arg(long, allow_hyphen_values = true)]
    pub probability: f64,
    /// Margin ζ ≥ 0 on every barrier condition.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub zeta: f64,
    /// Reference control (default 0).
    #[arg(long = "u-ref", allow_hyphen_values = true)]
    pub u_ref: Option<String>,
    /// Lower control bounds.
    #[arg(long = "u-min", allow_hyphen_values = true)]
    pub u_min: Option<String>,
    /// Upper control bounds.
    #[arg(long = "u-max", allow_hyphen_values = true)]
    pub u_max: Option<String>,
    /// Action when infeasible: max_margin, relax (the SOCP at the largest
    /// feasible probability p*), brake or hold.
    #[arg(long, default_value = "max_margin")]
    pub fallback: String,
    /// Promise each barrier condition as realised over the step: the
    /// model's observation noise σ²A joins its variance. Without it, the
    /// condition is the paper's, on the latent F, with the mean and
    /// variance `bayes-cbf moments` prints.
    #[arg(long, conflicts_with = "latent")]
    pub predictive: bool,
    /// The condition on the latent F (the default; kept for scripts that
    /// name it).
    #[arg(long)]
    pub latent: bool,
    #[command(flatten)]
    pub mc: McArgs,
    /// Write the JSON here instead of stdout (`-`: stdout).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

fn emit<T: Serialize>(value: &T, out: &Option<PathBuf>) -> Result<()> {
    crate::output::emit(value, out, false)
}

fn vector_of_len(name: &str, s: &str, len: usize, what: &str) -> Result<Vec<f64>> {
    let v = parse_vector(name, s)?;
    if v.len() != len {
        bail!(
            "{name} '{s}' has {} values, but the model's {what} is {len}",
            v.len()
        );
    }
    Ok(v)
}

/// Runs `bayes-cbf moments`.
pub fn run_moments(a: &MomentsArgs) -> Result<()> {
    let model = ModelFile::load(&a.model)?
        .to_model()
        .with_context(|| format!("model file '{}'", a.model.display()))?;
    let (_, barrier) = BarrierSpec::load(&a.barrier)?;
    let label = format!("barrier '{}'", a.barrier.display());
    check_barrier(&model, barrier.as_ref(), &label)?;
    let x = vector_of_len("--x", &a.x, model.state_dim(), "state_dim")?;
    let u = vector_of_len("--u", &a.u, model.control_dim(), "control_dim")?;
    let mc = a.mc.settings();
    let report = condition_moments(&model, barrier.as_ref(), &label, &x, &u, &mc).map_err(|e| {
        anyhow::anyhow!(
            "{}",
            e.to_string()
                .replace("invalid samples", "invalid --samples")
                .replace("invalid step", "invalid --step")
        )
    })?;
    emit(&report, &a.out)
}

/// Runs `bayes-cbf control`.
pub fn run_control(a: &ControlArgs) -> Result<()> {
    let model = ModelFile::load(&a.model)?
        .to_model()
        .with_context(|| format!("model file '{}'", a.model.display()))?;
    let (n, m) = (model.state_dim(), model.control_dim());
    let mut barriers = Vec::new();
    for path in &a.barriers {
        let (_, b) = BarrierSpec::load(path)?;
        let label = path.display().to_string();
        check_barrier(&model, b.as_ref(), &format!("barrier '{label}'"))?;
        barriers.push((label, b));
    }
    let x = vector_of_len("--x", &a.x, n, "state_dim")?;
    let u_ref = match &a.u_ref {
        Some(s) => vector_of_len("--u-ref", s, m, "control_dim")?,
        None => vec![0.0; m],
    };
    let mut settings = SafetySettings::new(m);
    settings.probability = a.probability;
    settings.zeta = a.zeta;
    settings.predictive = a.predictive;
    settings.u_min = a
        .u_min
        .as_deref()
        .map(|s| vector_of_len("--u-min", s, m, "control_dim"))
        .transpose()?;
    settings.u_max = a
        .u_max
        .as_deref()
        .map(|s| vector_of_len("--u-max", s, m, "control_dim"))
        .transpose()?;
    settings.fallback = Fallback::parse(&a.fallback).context("--fallback")?;
    let mc = a.mc.settings();
    let report = control_step(&model, barriers, settings, &mc, &x, &u_ref)
        .map_err(anyhow::Error::from)
        .map_err(|e| fix_field(e, "--"))?;
    emit(&report, &a.out)
}

/// Library field names (`probability`, `zeta`, `u_min[0]`) → CLI flags.
fn fix_field(e: anyhow::Error, prefix: &str) -> anyhow::Error {
    let msg = format!("{e:#}");
    let fixed = msg
        .replace(
            "invalid probability",
            &format!("invalid {prefix}probability"),
        )
        .replace(
            "invalid controller.probability",
            &format!("invalid {prefix}probability"),
        )
        .replace("invalid zeta", &format!("invalid {prefix}zeta"))
        .replace("u_min[", &format!("{prefix}u-min["))
        .replace("invalid fallback", &format!("invalid {prefix}fallback"))
        .replace("invalid samples", &format!("invalid {prefix}samples"))
        .replace("invalid step", &format!("invalid {prefix}step"));
    anyhow::anyhow!(fixed)
}
