//! `bayes-cbf moments` and `bayes-cbf control` (interfaces.md).

use anyhow::{bail, Context, Result};
use bayes_cbf::barrier::{
    cbc_moments, mc_cbc_moments, ConditionMoments, McSettings, MomentWorkspace,
};
use bayes_cbf::control::{
    ControlOutput, ControlStatus, Fallback, SafetyController, SafetySettings,
};
use bayes_cbf_scenario::barrier_file::BarrierSpec;
use bayes_cbf_scenario::model_file::ModelFile;
use bayes_cbf_scenario::parse::parse_vector;
use clap::Args;
use serde::Serialize;
use std::path::PathBuf;

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
    /// Monte Carlo draws for relative degree > 2 (no closed form exists).
    #[arg(long, default_value_t = 20_000)]
    pub samples: usize,
    /// Finite-difference step of the Monte Carlo Lie derivatives.
    #[arg(long, default_value_t = 1e-2)]
    pub step: f64,
    /// Seed of the Monte Carlo draws.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Write the JSON here instead of stdout.
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
    #[arg(long)]
    pub probability: f64,
    /// Margin ζ ≥ 0 on every barrier condition.
    #[arg(long, default_value_t = 0.0)]
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
    /// Action when infeasible: max_margin, brake or hold.
    #[arg(long, default_value = "max_margin")]
    pub fallback: String,
    /// Write the JSON here instead of stdout.
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

#[derive(Serialize)]
struct MomentsOut {
    relative_degree: usize,
    mean: f64,
    variance: f64,
    h: f64,
    e: Vec<f64>,
    cov: Vec<Vec<f64>>,
    /// "exact" (relative degree 1 and 2) or "monte_carlo".
    method: &'static str,
    #[serde(skip_serializing_if = "Option::is_none")]
    samples: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    mean_se: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    variance_se: Option<f64>,
}

/// Runs `bayes-cbf moments`.
pub fn run_moments(a: &MomentsArgs) -> Result<()> {
    let model = ModelFile::load(&a.model)?
        .to_model()
        .with_context(|| format!("model file '{}'", a.model.display()))?;
    let (_, barrier) = BarrierSpec::load(&a.barrier)?;
    let (n, m) = (model.state_dim(), model.control_dim());
    if barrier.state_dim() != n {
        bail!(
            "barrier '{}' is for state dimension {}, but the model's state_dim is {n}",
            a.barrier.display(),
            barrier.state_dim()
        );
    }
    let x = vector_of_len("--x", &a.x, n, "state_dim")?;
    let u = vector_of_len("--u", &a.u, m, "control_dim")?;
    let label = format!("barrier '{}'", a.barrier.display());
    let (mom, method, samples, mean_se, variance_se) = if barrier.relative_degree() <= 2 {
        let mut ws = MomentWorkspace::new(&model);
        ws.update(&model, &x, barrier.relative_degree())
            .context("--x")?;
        let mut mom = ConditionMoments::zeros(m);
        cbc_moments(&mut ws, barrier.as_ref(), &mut mom).with_context(|| label.clone())?;
        (mom, "exact", None, None, None)
    } else {
        let settings = McSettings {
            samples: a.samples,
            step: a.step,
            seed: a.seed,
        };
        let mc = mc_cbc_moments(&model, barrier.as_ref(), &x, &settings)
            .map_err(|e| {
                anyhow::anyhow!(
                    "{}",
                    e.to_string()
                        .replace("invalid samples", "invalid --samples")
                        .replace("invalid step", "invalid --step")
                )
            })
            .with_context(|| label.clone())?;
        let (se_m, se_v) = mc.standard_errors(&u);
        (
            mc.moments,
            "monte_carlo",
            Some(mc.samples),
            Some(se_m),
            Some(se_v),
        )
    };
    let cov = (0..m + 1)
        .map(|i| mom.cov.row(i).iter().copied().collect())
        .collect();
    emit(
        &MomentsOut {
            relative_degree: mom.relative_degree,
            mean: mom.mean(&u),
            variance: mom.variance(&u),
            h: mom.value,
            e: mom.e.clone(),
            cov,
            method,
            samples,
            mean_se,
            variance_se,
        },
        &a.out,
    )
}

#[derive(Serialize)]
struct ConstraintOut {
    barrier: String,
    relative_degree: usize,
    mean: f64,
    std: f64,
    c: f64,
    slack: f64,
}

#[derive(Serialize)]
struct ControlOut {
    status: &'static str,
    u: Vec<f64>,
    constraints: Vec<ConstraintOut>,
    #[serde(skip_serializing_if = "Option::is_none")]
    fallback: Option<&'static str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    p_star: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    violated: Option<Vec<usize>>,
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
        if b.state_dim() != n {
            bail!(
                "barrier '{}' is for state dimension {}, but the model's state_dim is {n}",
                path.display(),
                b.state_dim()
            );
        }
        barriers.push(b);
    }
    let x = vector_of_len("--x", &a.x, n, "state_dim")?;
    let u_ref = match &a.u_ref {
        Some(s) => vector_of_len("--u-ref", s, m, "control_dim")?,
        None => vec![0.0; m],
    };
    let mut settings = SafetySettings::new(m);
    settings.probability = a.probability;
    settings.zeta = a.zeta;
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
    if a.probability < 0.5 && barriers.iter().any(|b| b.relative_degree() == 1) {
        bail!(
            "--probability = {}: must be ≥ 0.5 with relative-degree-1 barriers",
            a.probability
        );
    }
    let labels: Vec<String> = a.barriers.iter().map(|p| p.display().to_string()).collect();
    let degrees: Vec<usize> = barriers.iter().map(|b| b.relative_degree()).collect();
    let mut ctrl = SafetyController::new(n, m, barriers, None, settings)
        .map_err(anyhow::Error::from)
        .map_err(|e| fix_field(e, "--"))?;
    let mut out = ControlOutput::new(m, labels.len());
    ctrl.step(&model, &x, &u_ref, None, &mut out)?;
    let constraints = out
        .constraints
        .iter()
        .zip(labels.iter().zip(&degrees))
        .map(|(c, (l, r))| ConstraintOut {
            barrier: l.clone(),
            relative_degree: *r,
            mean: c.mean,
            std: c.std,
            c: c.c,
            slack: c.slack,
        })
        .collect();
    let (status, fallback, p_star, violated) = match &out.status {
        ControlStatus::Optimal | ControlStatus::AlmostOptimal => ("optimal", None, None, None),
        ControlStatus::Infeasible(info) => (
            "infeasible",
            Some(info.fallback.name()),
            info.p_star,
            Some(info.violated.clone()),
        ),
    };
    emit(
        &ControlOut {
            status,
            u: out.u.clone(),
            constraints,
            fallback,
            p_star,
            violated,
        },
        &a.out,
    )
}

/// Library field names (`probability`, `zeta`, `u_min[0]`) → CLI flags.
fn fix_field(e: anyhow::Error, prefix: &str) -> anyhow::Error {
    let msg = format!("{e:#}");
    let fixed = msg
        .replace(
            "invalid probability",
            &format!("invalid {prefix}probability"),
        )
        .replace("invalid zeta", &format!("invalid {prefix}zeta"))
        .replace("u_min[", &format!("{prefix}u-min["))
        .replace("invalid fallback", &format!("invalid {prefix}fallback"));
    anyhow::anyhow!(fixed)
}
