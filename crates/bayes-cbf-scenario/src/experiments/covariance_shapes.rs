//! `covariance-shapes` (paper, Fig. 1): the posterior covariances of the
//! columns of `F(x) = [f g_1 g_2]` of the Ackermann vehicle, learned by an
//! MVGP and by a CoGP from the same data.
//!
//! Under the MVGP, `Cov(vec F(x)) = B_k(x, x) ⊗ A`, so the covariance of
//! column `c` is `B_k[c, c] · A`: every column has the shape of `A`, up to
//! scale. The CoGP's `Σ k0` leaves the `n × n` diagonal blocks free. The
//! figure draws the 3σ ellipses of each column's covariance, normalised to
//! unit trace so that only the shapes are compared, projected on each pair
//! of state coordinates; `summary.json` holds the raw blocks and the
//! largest Frobenius distance between two normalised blocks (zero for the
//! MVGP by construction).

use super::{fit_settings, new_model, ExperimentArgs, ModelKind, Table};
use crate::error::Result;
use crate::workloads::ackermann_data;
use bayes_cbf::gp::{DynamicsModel, InputMap};
use nalgebra::DMatrix;
use serde::Serialize;
use std::time::Instant;

/// Names of the columns of `F` for the Ackermann vehicle (`u = (v, ω)`).
pub const COLUMNS: [&str; 3] = ["f", "g_1 (v)", "g_2 (ω)"];
/// Names of the state coordinates.
pub const STATES: [&str; 3] = ["x", "y", "θ"];

/// The covariance blocks of one model.
#[derive(Debug, Clone)]
pub struct ModelShapes {
    /// Which model.
    pub kind: ModelKind,
    /// The `n × n` covariance of each column of `F` at [`CovarianceShapes::x`].
    pub blocks: Vec<DMatrix<f64>>,
    /// Largest Frobenius distance between two unit-trace blocks.
    pub spread: f64,
    /// Fit time (s).
    pub fit_s: f64,
}

/// One column's covariance block in the summary.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ColumnCovariance {
    /// Column name (`f`, `g_1 (v)`, `g_2 (ω)`).
    pub column: &'static str,
    /// Its trace.
    pub trace: f64,
    /// The `n × n` block, rows.
    pub rows: Vec<Vec<f64>>,
}

/// One model's part of the summary.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ModelSummary {
    /// `MVGP` or `CoGP`.
    pub model: &'static str,
    /// Fit time (s).
    pub fit_s: f64,
    /// Log marginal likelihood of the fitted model.
    pub log_marginal_likelihood: f64,
    /// The covariance of each column of `F`.
    pub column_covariances: Vec<ColumnCovariance>,
    /// Largest Frobenius distance between two unit-trace blocks.
    pub shape_spread: f64,
}

/// `summary.json` of `covariance-shapes`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Summary {
    /// `covariance-shapes`.
    pub scenario: &'static str,
    /// Seed.
    pub seed: u64,
    /// Reduced run.
    pub quick: bool,
    /// Training points.
    pub k: usize,
    /// Where the covariances are taken.
    pub x: [f64; 3],
    /// What the kernel sees.
    pub input_map: &'static str,
    /// MVGP, then CoGP.
    pub models: Vec<ModelSummary>,
}

/// The result of `covariance-shapes`.
#[derive(Debug, Clone)]
pub struct CovarianceShapes {
    /// Training points.
    pub k: usize,
    /// The state where the covariances are taken.
    pub x: [f64; 3],
    /// MVGP, then CoGP.
    pub models: Vec<ModelShapes>,
    /// `summary.json`.
    pub summary: Summary,
    /// `trajectory.csv`: the Ackermann samples both models are fitted to.
    pub tables: Vec<Table>,
}

/// The `n × n` covariance block of column `c` in `Cov(vec F)` (column-major
/// `vec`, entry `i + n c`).
fn block(cov: &DMatrix<f64>, n: usize, c: usize) -> DMatrix<f64> {
    cov.view((c * n, c * n), (n, n)).into_owned()
}

/// Largest Frobenius distance between two unit-trace blocks.
fn shape_spread(blocks: &[DMatrix<f64>]) -> f64 {
    let unit: Vec<DMatrix<f64>> = blocks.iter().map(|b| b / b.trace()).collect();
    let mut worst = 0.0f64;
    for a in 0..unit.len() {
        for b in a + 1..unit.len() {
            worst = worst.max((&unit[a] - &unit[b]).norm());
        }
    }
    worst
}

/// Runs the experiment.
pub fn run(args: &ExperimentArgs) -> Result<CovarianceShapes> {
    let k = if args.quick { 60 } else { 200 };
    let iters = if args.quick { 15 } else { 50 };
    let data = ackermann_data(k, 1.0, args.seed)?;
    // the dynamics do not depend on the position: the kernel sees θ only
    let map = InputMap::Select(vec![2]);
    let x_star = [0.0, 0.0, std::f64::consts::FRAC_PI_4];
    let n = data.n;
    let mut models = Vec::new();
    let mut shapes = Vec::new();
    for kind in [ModelKind::Mvgp, ModelKind::Cogp] {
        let mut model: Box<dyn DynamicsModel> = new_model(kind, &map, &data)?;
        let started = Instant::now();
        model.fit(&fit_settings(false, iters, args.seed))?;
        let fit_s = started.elapsed().as_secs_f64();
        let (_, cov) = model.posterior_vec(&x_star)?;
        let blocks: Vec<DMatrix<f64>> = (0..COLUMNS.len()).map(|c| block(&cov, n, c)).collect();
        let spread = shape_spread(&blocks);
        models.push(ModelSummary {
            model: kind.name(),
            fit_s,
            log_marginal_likelihood: model.log_marginal_likelihood(),
            column_covariances: blocks
                .iter()
                .zip(COLUMNS)
                .map(|(b, column)| ColumnCovariance {
                    column,
                    trace: b.trace(),
                    rows: (0..n)
                        .map(|i| (0..n).map(|j| b[(i, j)]).collect())
                        .collect(),
                })
                .collect(),
            shape_spread: spread,
        });
        shapes.push(ModelShapes {
            kind,
            blocks,
            spread,
            fit_s,
        });
    }
    let summary = Summary {
        scenario: "covariance-shapes",
        seed: args.seed,
        quick: args.quick,
        k,
        x: x_star,
        input_map: "theta only",
        models,
    };
    Ok(CovarianceShapes {
        k,
        x: x_star,
        models: shapes,
        summary,
        tables: vec![super::samples_table(&[("ackermann", &data)])],
    })
}
