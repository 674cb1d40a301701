//! `bayes-cbf fit` and `bayes-cbf predict` (formats in `interfaces.md`).

use crate::logger::hold_warnings;
use anyhow::{bail, Context, Result};
use bayes_cbf::gp::{fit, FitReport, InputMap};
use bayes_cbf_scenario::csv_data::{read_dataset, Layout};
use bayes_cbf_scenario::fitting::{fit_settings, initial_model};
use bayes_cbf_scenario::input_map_spec::{parse_input_map, to_input_map};
use bayes_cbf_scenario::model_file::ModelFile;
use bayes_cbf_scenario::parse::{parse_indices, parse_vector, rank_name};
use bayes_cbf_scenario::prior_spec::PriorSpec;
use clap::Args;
use nalgebra::DMatrix;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Options of `bayes-cbf fit`.
#[derive(Debug, Args)]
pub struct FitArgs {
    /// CSV with header x1..xN,u1..uM,xdot1..xdotN (or t,x1..xN,u1..uM with --time-series).
    #[arg(long, value_name = "DATA.csv")]
    pub data: PathBuf,
    /// State dimension n.
    #[arg(long, allow_negative_numbers = true, value_name = "N")]
    pub state_dim: usize,
    /// Control dimension m.
    #[arg(long, allow_negative_numbers = true, value_name = "M")]
    pub control_dim: usize,
    /// Prior mean: "zero", a JSON object such as
    /// '{"type":"pendulum","mass":1,"length":1,"gravity":10}' or
    /// '{"type":"ackermann","wheelbase":1}', an expression prior
    /// '{"type":"expression","state":[..],"control":[..],"f":[..],"g":[[..]]}'
    /// (docs/formats.md), or a file holding that JSON. Keys left out take
    /// the values shown (also for the bare names pendulum and ackermann).
    #[arg(long, value_name = "JSON", default_value = "zero")]
    pub prior_mean: String,
    /// Output model file (written completely or not at all; `-`: stdout).
    #[arg(long, value_name = "MODEL.json")]
    pub out: PathBuf,
    /// Columns are t,x1..xN,u1..uM; ẋ is estimated by finite differences.
    #[arg(long)]
    pub time_series: bool,
    /// Angle components (comma-separated state indices, or "none") whose
    /// differences are wrapped to [-π, π) with --time-series. Default: the
    /// angles of the prior mean's system (pendulum 0, ackermann 2).
    #[arg(long, value_name = "I,J", allow_hyphen_values = true)]
    pub angle_index: Option<String>,
    /// Structure of A: full, diag or an integer rank.
    #[arg(
        long,
        value_name = "RANK",
        default_value = "full",
        allow_hyphen_values = true
    )]
    pub rank_a: String,
    /// Structure of B: full, diag or an integer rank.
    #[arg(
        long,
        value_name = "RANK",
        default_value = "full",
        allow_hyphen_values = true
    )]
    pub rank_b: String,
    /// Random restarts of the optimiser besides the data-driven start.
    #[arg(long, allow_negative_numbers = true, default_value_t = 0)]
    pub restarts: usize,
    /// Seed of the random initialisation.
    #[arg(long, allow_negative_numbers = true, default_value_t = 0)]
    pub seed: u64,
    /// L-BFGS iterations per start.
    #[arg(long, allow_negative_numbers = true, default_value_t = 100)]
    pub max_iters: u64,
    /// Floor of the noise standard deviation of state component 0, σ·√A₀₀
    /// (keeps the Gram matrix well conditioned on nearly noise-free data).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub sigma_min: f64,
    /// What the kernel sees, comma-separated: state indices i, or cos:i and
    /// sin:i for a periodic angle embedding; e.g. 2 for a translation-
    /// invariant Ackermann model, cos:0,sin:0,1 for the pendulum. Default:
    /// the whole state.
    #[arg(long, value_name = "I,J", allow_hyphen_values = true)]
    pub input_map: Option<String>,
    /// Rows of F known exactly from the prior mean (comma-separated, e.g. 0
    /// for the pendulum's θ̇ = ω); only the others are learned.
    #[arg(long, value_name = "I,J")]
    pub known_rows: Option<String>,
}

/// Options of `bayes-cbf predict`.
#[derive(Debug, Args)]
pub struct PredictArgs {
    /// Model file written by `bayes-cbf fit`.
    #[arg(long, value_name = "MODEL.json")]
    pub model: PathBuf,
    /// Query state, comma-separated (repeat for several states).
    #[arg(
        long = "x",
        value_name = "X",
        required = true,
        allow_hyphen_values = true
    )]
    pub xs: Vec<String>,
    /// Write the JSON here instead of stdout (`-`: stdout).
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
}

/// Runs `bayes-cbf fit`.
pub fn run_fit(a: &FitArgs) -> Result<()> {
    let (n, m) = (a.state_dim, a.control_dim);
    if n == 0 {
        bail!("--state-dim must be ≥ 1");
    }
    if m == 0 {
        bail!("--control-dim must be ≥ 1");
    }
    let prior_file = Path::new(&a.prior_mean);
    let mut inputs = vec![("--data", a.data.as_path())];
    if prior_file.is_file() {
        inputs.push(("--prior-mean", prior_file));
    }
    crate::output::refuse_input_as_output(&a.out, &inputs)?;
    let prior = PriorSpec::from_arg(&a.prior_mean)?;
    let input_map = match &a.input_map {
        None => InputMap::Identity,
        Some(s) => {
            let spec = parse_input_map(s, n)?;
            to_input_map(Some(&spec))
        }
    };
    let settings = fit_settings(
        [("--rank-a", &a.rank_a), ("--rank-b", &a.rank_b)],
        a.max_iters,
        a.restarts,
        a.seed,
        a.sigma_min,
    )?;
    let (layout, angles) = if a.time_series {
        let angles = match &a.angle_index {
            Some(s) => parse_indices("--angle-index", s, n)?,
            None => prior
                .angle_indices()
                .into_iter()
                .filter(|&i| i < n)
                .collect(),
        };
        (Layout::TimeSeries, angles)
    } else {
        if a.angle_index.is_some() {
            bail!("--angle-index only applies with --time-series");
        }
        (Layout::Derivatives, Vec::new())
    };
    let ds = read_dataset(&a.data, layout, n, m, &angles)?;
    let mut model = initial_model(n, m, &prior, input_map)?;
    if let Some(rows) = &a.known_rows {
        let rows = parse_indices("--known-rows", rows, n)?;
        model = model.with_known_rows(&rows).context("--known-rows")?;
    }
    model
        .set_data(&ds.xs, &ds.us, &ds.xdot)
        .context("training data")?;
    let start = Instant::now();
    let report: FitReport = hold_warnings("hyperparameter fitting", || fit(&mut model, &settings))
        .context("fitting hyperparameters")?;
    let secs = start.elapsed().as_secs_f64();
    if let Some(m) = model.known_row_misfit().filter(|m| m.is_large()) {
        log::warn!("--known-rows: {}", m.describe());
    }
    let file = ModelFile::from_model(&model, &prior);
    crate::output::write_out(&a.out, file.to_json()?.as_bytes())?;
    note!(
        "fit: k = {}, log-likelihood {:.3} -> {:.3}, {} start(s), {} evaluations, rank A {} / B {}, {:.2} s, wrote {}",
        model.len(),
        report.initial_log_likelihood,
        report.log_likelihood,
        report.starts,
        report.evaluations,
        rank_name(settings.rank_a),
        rank_name(settings.rank_b),
        secs,
        a.out.display()
    );
    Ok(())
}

/// One prediction: `M_k(x)` and `B_k(x, x)`, with `Cov(vec F(x)) = B ⊗ A`
/// (`A` with the known rows and columns zeroed, `Mvgp::row_cov`).
#[derive(Debug, Serialize)]
#[allow(non_snake_case)]
struct Prediction {
    x: Vec<f64>,
    mean: Vec<Vec<f64>>,
    B: Vec<Vec<f64>>,
    A: Vec<Vec<f64>>,
}

#[derive(Debug, Serialize)]
struct Predictions {
    predictions: Vec<Prediction>,
}

fn rows(m: &DMatrix<f64>) -> Vec<Vec<f64>> {
    (0..m.nrows())
        .map(|i| m.row(i).iter().copied().collect())
        .collect()
}

/// Runs `bayes-cbf predict`.
pub fn run_predict(a: &PredictArgs) -> Result<()> {
    if let Some(out) = &a.out {
        crate::output::refuse_input_as_output(out, &[("--model", &a.model)])?;
    }
    let file = ModelFile::load(&a.model)?;
    let model = file
        .to_model()
        .with_context(|| format!("model file '{}'", a.model.display()))?;
    let n = model.state_dim();
    let mut predictions = Vec::with_capacity(a.xs.len());
    for (q, s) in a.xs.iter().enumerate() {
        let name = if a.xs.len() == 1 {
            "--x".to_string()
        } else {
            format!("--x (#{})", q + 1)
        };
        let x = parse_vector(&name, s)?;
        if x.len() != n {
            bail!(
                "{name} '{s}' has {} values, but the model's state_dim is {n}",
                x.len()
            );
        }
        let post = model.posterior(&x).with_context(|| name.clone())?;
        if post
            .mean
            .iter()
            .chain(post.B.iter())
            .any(|v| !v.is_finite())
        {
            bail!(
                "{name}: the posterior is not finite: the hyperparameters (variance, A, B) \
                 or the data overflow the model's arithmetic"
            );
        }
        predictions.push(Prediction {
            x,
            mean: rows(&post.mean),
            B: rows(&post.B),
            A: rows(model.row_cov()),
        });
    }
    crate::output::emit(&Predictions { predictions }, &a.out, false)
}
