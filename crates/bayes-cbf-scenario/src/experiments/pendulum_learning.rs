//! `pendulum-learning`: MVGP vs CoGP fit of the pendulum dynamics (paper,
//! Sec. VII-A, Fig. 4).
//!
//! ## Setup
//! Pendulum `m = l = 1`, `g = 10` (Eq. 31). 300 samples from trajectories of
//! 20 steps of `dt = 0.01` s, each from a uniform random state in
//! `[-π, π) × [-6, 6]`, under `u = m g sin θ · U(0.6, 1.4)`, with `ẋ` by
//! finite differences (attributed to step midpoints, plus `N(0, 0.01²)`
//! noise, see [`super::pendulum_samples`]); a random split gives 200 training and 100 held-out
//! samples. Both models have zero prior mean and an RBF kernel, are fitted by
//! maximising the marginal likelihood (full `A`, `B` for the MVGP; full `Σ`,
//! `S` for the CoGP) and are scored against the true `F(x)` on the 20 × 20
//! grid of `[-π, π] × [-6, 6]` and on the held-out samples: the
//! variance-weighted error (Eq. 33) and RMSEs.
//!
//! ## Input map
//! Both models see `x = (θ, ω)` directly (identity map). The periodic map
//! `(cos θ, sin θ, ω)` looks more natural, but the pendulum's `F` is
//! *linear* in those features (`f = [ω, −10 sin θ]`, `g` constant), so the
//! marginal likelihood is maximised at infinite lengthscales and signal
//! variance (the RBF tends to a polynomial kernel): with seed 0 the fits
//! ran to lengthscales ~1e9 and `B`, `Σ` ~1e9, where the posterior
//! covariance `Σ k0 − 𝐊 𝐆⁻¹ 𝐊ᵀ` loses all precision to cancellation and the
//! variance-weighted error cannot be computed. With the identity map the
//! hyperparameters stay finite (θ lengthscale ≈ 4) and both models are
//! near-calibrated. The grid is `[-π, π]`, so its edge columns are
//! extrapolated from one side only; that is visible in the plots.
//!
//! ## Outputs
//! `summary.json`, `trajectory.csv` (the 300 samples with their split),
//! `grid.csv` (truth, posterior means and standard deviations),
//! `pendulum_f.png`, `pendulum_g.png` (true and learned components with the
//! training points as red `+`, one colour scale per column) and
//! `pendulum_std.png` (posterior standard deviations).

use super::{fit_settings, ExperimentArgs, TRAJECTORY_LEN};
use super::{
    linspace, new_model, pendulum_samples, random_split, variance_weighted, ModelKind, Table,
    OMEGA_MAX, PENDULUM_DT,
};
use crate::csv_data::to_csv;
use crate::error::{Context, Result};
use bayes_cbf::gp::{metrics, InputMap};
use bayes_cbf::sim::Dataset;
use bayes_cbf::systems::{DynSystem, Pendulum};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::f64::consts::PI;
use std::time::Instant;

/// Training points.
pub const TRAIN: usize = 200;
const HELDOUT: usize = 100;
/// Grid points per side.
pub const GRID: usize = 20;
const MAX_ITERS: u64 = 100;

/// Names, units and true-`F` entry (`vec F` index `i + n c`) of the four
/// components `f₁, f₂, g₁, g₂`.
pub const COMPONENTS: [(&str, &str); 4] = [
    ("f₁", "rad/s"),
    ("f₂", "rad/s²"),
    ("g₁", "rad/s per N·m"),
    ("g₂", "rad/s² per N·m"),
];

/// Scores on the 20 × 20 grid.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[allow(non_snake_case)]
pub struct GridScores {
    /// Variance-weighted error (Eq. 33).
    pub variance_weighted_error: f64,
    /// Points whose covariance needed the extended jitter ladder.
    pub extended_jitter_points: usize,
    /// RMSE of `vec F`.
    pub rmse_F: f64,
    /// RMSE of `f`.
    pub rmse_f: f64,
    /// RMSE of `g`.
    pub rmse_g: f64,
}

/// Scores on the held-out samples.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[allow(non_snake_case)]
pub struct HeldoutScores {
    /// Variance-weighted error (Eq. 33).
    pub variance_weighted_error: f64,
    /// Points whose covariance needed the extended jitter ladder.
    pub extended_jitter_points: usize,
    /// RMSE of `vec F`.
    pub rmse_F: f64,
    /// RMSE of `F(x)u̲`.
    pub rmse_Fu: f64,
    /// RMSE of `F(x)u̲` relative to its scale.
    pub relative_rmse_Fu: f64,
    /// Held-out samples.
    pub points: usize,
}

/// One fitted model's part of the summary.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ModelScores {
    /// Fit time (s).
    pub fit_seconds: f64,
    /// Time to predict on the grid (s).
    pub predict_grid_seconds: f64,
    /// Log marginal likelihood at the fit's start.
    pub log_likelihood_initial: f64,
    /// Log marginal likelihood fitted.
    pub log_likelihood: f64,
    /// Likelihood evaluations.
    pub evaluations: usize,
    /// On the grid.
    pub grid: GridScores,
    /// Held out.
    pub heldout: HeldoutScores,
}

/// The true system in the summary.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SystemInfo {
    /// `pendulum`.
    #[serde(rename = "type")]
    pub kind: &'static str,
    /// Mass.
    pub mass: f64,
    /// Length.
    pub length: f64,
    /// Gravity.
    pub gravity: f64,
}

/// The grid's box.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GridBox {
    /// Angle range.
    pub theta: [f64; 2],
    /// Angular velocity range.
    pub omega: [f64; 2],
}

/// The files written.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Files {
    /// The figures.
    pub plots: [&'static str; 3],
    /// The samples.
    pub trajectory: &'static str,
    /// The grid.
    pub grid: &'static str,
}

/// `summary.json` of `pendulum-learning`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Summary {
    /// `pendulum-learning`.
    pub scenario: &'static str,
    /// Seed.
    pub seed: u64,
    /// The true system.
    pub system: SystemInfo,
    /// Step of the sampled trajectories (s).
    pub dt: f64,
    /// How the inputs were drawn.
    pub inputs: &'static str,
    /// Steps per trajectory.
    pub trajectory_len: usize,
    /// Training samples.
    pub training_points: usize,
    /// Held-out samples.
    pub heldout_points: usize,
    /// Grid size.
    pub grid: [usize; 2],
    /// Grid box.
    pub grid_box: GridBox,
    /// Kernel family.
    pub kernel: &'static str,
    /// Prior mean.
    pub prior_mean: &'static str,
    /// What the kernel sees.
    pub input_map: &'static str,
    /// How `ẋ` was measured.
    pub xdot: &'static str,
    /// Structure of the covariances.
    pub covariances: &'static str,
    /// L-BFGS iterations.
    pub max_iters: u64,
    /// `MVGP` and `CoGP`.
    pub models: std::collections::BTreeMap<&'static str, ModelScores>,
    /// The files written.
    pub files: Files,
}

/// One fitted model's posterior on the grid and its scores.
#[derive(Debug, Clone)]
pub struct Fitted {
    /// Which model.
    pub kind: ModelKind,
    /// Posterior means of `vec F` (4 per grid point, grid row-major).
    pub mean: Vec<[f64; 4]>,
    /// Posterior standard deviations of `vec F`.
    pub std: Vec<[f64; 4]>,
    /// This model's part of the summary.
    pub summary: ModelScores,
}

/// The result of `pendulum-learning`.
#[derive(Debug, Clone)]
pub struct PendulumLearning {
    /// Grid angles (columns of the grid).
    pub thetas: Vec<f64>,
    /// Grid angular velocities (rows of the grid).
    pub omegas: Vec<f64>,
    /// Training states, row-major `(θ, ω)`.
    pub train_xs: Vec<f64>,
    /// True `vec F` on the grid.
    pub truth: Vec<[f64; 4]>,
    /// MVGP, then CoGP.
    pub fitted: Vec<Fitted>,
    /// `summary.json`.
    pub summary: Summary,
    /// `trajectory.csv` and `grid.csv`.
    pub tables: Vec<Table>,
}

/// Grid states, row `j` at `ω_j`, column `i` at `θ_i` (row-major `ω × θ`).
fn grid() -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let thetas = linspace(-PI, PI, GRID);
    let omegas = linspace(-OMEGA_MAX, OMEGA_MAX, GRID);
    let mut xs = Vec::with_capacity(2 * GRID * GRID);
    for &w in &omegas {
        for &t in &thetas {
            xs.extend([t, w]);
        }
    }
    (thetas, omegas, xs)
}

/// Fits `kind` to `train` and scores it on the grid and the held-out set.
fn fit_and_score(
    kind: ModelKind,
    map: &InputMap,
    train: &Dataset,
    test: &Dataset,
    grid_xs: &[f64],
    seed: u64,
) -> Result<Fitted> {
    let truth = Pendulum::default();
    let mut model = new_model(kind, map, train)?;
    let start = Instant::now();
    let report = model
        .fit(&fit_settings(false, MAX_ITERS, seed))
        .with_context(|| format!("fitting the {}", kind.name()))?;
    let fit_seconds = start.elapsed().as_secs_f64();
    let start = Instant::now();
    let (mut mean, mut std) = (Vec::new(), Vec::new());
    for x in grid_xs.chunks(2) {
        let (m, cov) = model.posterior_vec(x)?;
        mean.push([m[(0, 0)], m[(1, 0)], m[(0, 1)], m[(1, 1)]]);
        std.push([0, 1, 2, 3].map(|e| cov[(e, e)].max(0.0).sqrt()));
    }
    let predict_seconds = start.elapsed().as_secs_f64();
    let mut f = [0.0; 4];
    let (mut ef, mut eg) = (0.0, 0.0);
    for (x, m) in grid_xs.chunks(2).zip(&mean) {
        truth.eval_f64(x, &mut f);
        ef += (m[0] - f[0]).powi(2) + (m[1] - f[1]).powi(2);
        eg += (m[2] - f[2]).powi(2) + (m[3] - f[3]).powi(2);
    }
    let pts = mean.len() as f64;
    let (vwe_grid, jit_grid) = variance_weighted(model.as_ref(), grid_xs, &truth)?;
    let rmse_grid = metrics::rmse_f(model.as_ref(), grid_xs, &truth)?;
    let (vwe_held, jit_held) = variance_weighted(model.as_ref(), &test.xs, &truth)?;
    let rmse_held = metrics::rmse_f(model.as_ref(), &test.xs, &truth)?;
    let rmse_fu = metrics::rmse_fu(model.as_ref(), &test.xs, &test.us, &truth)?;
    let rel_fu = metrics::relative_rmse_fu(model.as_ref(), &test.xs, &test.us, &truth)?;
    let summary = ModelScores {
        fit_seconds,
        predict_grid_seconds: predict_seconds,
        log_likelihood_initial: report.initial_log_likelihood,
        log_likelihood: model.log_marginal_likelihood(),
        evaluations: report.evaluations,
        grid: GridScores {
            variance_weighted_error: vwe_grid,
            extended_jitter_points: jit_grid,
            rmse_F: rmse_grid,
            rmse_f: (ef / (2.0 * pts)).sqrt(),
            rmse_g: (eg / (2.0 * pts)).sqrt(),
        },
        heldout: HeldoutScores {
            variance_weighted_error: vwe_held,
            extended_jitter_points: jit_held,
            rmse_F: rmse_held,
            rmse_Fu: rmse_fu,
            relative_rmse_Fu: rel_fu,
            points: test.len(),
        },
    };
    Ok(Fitted {
        kind,
        mean,
        std,
        summary,
    })
}

/// Runs the experiment (see the module docs).
pub fn run(args: &ExperimentArgs) -> Result<PendulumLearning> {
    let pend = Pendulum::default();
    let mut rng = ChaCha8Rng::seed_from_u64(args.seed);
    let data =
        pendulum_samples(&pend, TRAIN + HELDOUT, &mut rng).context("simulating the pendulum")?;
    let (train, test) = random_split(&data, TRAIN, &mut rng);
    let map = InputMap::Identity;
    let (thetas, omegas, grid_xs) = grid();
    let fitted = [ModelKind::Mvgp, ModelKind::Cogp]
        .into_iter()
        .map(|k| fit_and_score(k, &map, &train, &test, &grid_xs, args.seed))
        .collect::<Result<Vec<_>>>()?;
    let mut truth = Vec::with_capacity(GRID * GRID);
    let mut f = [0.0; 4];
    for x in grid_xs.chunks(2) {
        pend.eval_f64(x, &mut f);
        truth.push(f);
    }
    let plots = ["pendulum_f.png", "pendulum_g.png", "pendulum_std.png"];
    let tables = tables(&data, &train, &grid_xs, &truth, &fitted);
    let models = fitted
        .iter()
        .map(|m| (m.kind.name(), m.summary.clone()))
        .collect();
    let summary = Summary {
        scenario: "pendulum-learning",
        seed: args.seed,
        system: SystemInfo {
            kind: "pendulum",
            mass: pend.mass,
            length: pend.length,
            gravity: pend.gravity,
        },
        dt: PENDULUM_DT,
        inputs: "u = m g sin(theta) * U(0.6, 1.4)",
        trajectory_len: TRAJECTORY_LEN,
        training_points: train.len(),
        heldout_points: test.len(),
        grid: [GRID, GRID],
        grid_box: GridBox {
            theta: [-PI, PI],
            omega: [-OMEGA_MAX, OMEGA_MAX],
        },
        kernel: "rbf",
        prior_mean: "zero",
        input_map: "identity: (theta, omega)",
        xdot: "finite differences at step midpoints + N(0, 0.01^2) noise",
        covariances: "full (MVGP: A, B; CoGP: Sigma, S)",
        max_iters: MAX_ITERS,
        models,
        files: Files {
            plots,
            trajectory: "trajectory.csv",
            grid: "grid.csv",
        },
    };
    Ok(PendulumLearning {
        thetas,
        omegas,
        train_xs: train.xs,
        truth,
        fitted,
        summary,
        tables,
    })
}

/// `trajectory.csv` (all samples with their split) and `grid.csv`.
fn tables(
    data: &Dataset,
    train: &Dataset,
    grid_xs: &[f64],
    truth: &[[f64; 4]],
    fitted: &[Fitted],
) -> Vec<Table> {
    let rows: Vec<Vec<f64>> = (0..data.len())
        .map(|j| {
            let (x, xd) = (&data.xs[2 * j..2 * j + 2], &data.xdot[2 * j..2 * j + 2]);
            let in_train = train.xs.chunks(2).any(|t| t == x);
            vec![
                x[0],
                x[1],
                data.us[j],
                xd[0],
                xd[1],
                if in_train { 1.0 } else { 0.0 },
            ]
        })
        .collect();
    let header = ["theta", "omega", "u", "theta_dot", "omega_dot", "train"];
    let trajectory = Table::new("trajectory.csv", to_csv(&header, &rows));
    let mut header: Vec<String> = vec!["theta".into(), "omega".into()];
    let comps = ["f1", "f2", "g1", "g2"];
    header.extend(comps.iter().map(|c| format!("{c}_true")));
    for m in fitted {
        let n = m.kind.name().to_lowercase();
        header.extend(comps.iter().map(|c| format!("{c}_{n}_mean")));
        header.extend(comps.iter().map(|c| format!("{c}_{n}_std")));
    }
    let rows: Vec<Vec<f64>> = grid_xs
        .chunks(2)
        .enumerate()
        .map(|(j, x)| {
            let mut r = x.to_vec();
            r.extend(truth[j]);
            for m in fitted {
                r.extend(m.mean[j]);
                r.extend(m.std[j]);
            }
            r
        })
        .collect();
    let header: Vec<&str> = header.iter().map(String::as_str).collect();
    vec![trajectory, Table::new("grid.csv", to_csv(&header, &rows))]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pendulum_learning_summary_and_tables() {
        let r = run(&ExperimentArgs {
            seed: 1,
            quick: true,
        })
        .unwrap();
        let s = serde_json::to_value(&r.summary).unwrap();
        assert_eq!(s["scenario"], "pendulum-learning");
        assert_eq!(s["seed"], 1);
        assert_eq!(
            (s["training_points"].as_u64(), s["heldout_points"].as_u64()),
            (Some(200), Some(100))
        );
        for m in ["MVGP", "CoGP"] {
            let r = &s["models"][m];
            for key in ["grid", "heldout"] {
                let vwe = r[key]["variance_weighted_error"].as_f64().unwrap();
                let rmse = r[key]["rmse_F"].as_f64().unwrap();
                // The score is √(mean of the squared Mahalanobis errors of
                // vec F): a calibrated model has E[d²] = n(1+m) = 4, a score
                // near 2. Measured with seed 1: MVGP 2.06 (grid) and 1.73
                // (held out). The bounds allow a factor 1.5 either way
                // (mean d² in [1.8, 9]): standard deviations overstated by a
                // factor 2 (score halved) fail the lower bound for both
                // scores, understated by 2 (score doubled) the upper bound.
                //
                // The CoGP fitted to its optimum is overconfident: 17.2
                // (grid) and 11.7 (held out), 8.2/5.8 and 4.4/5.2 at seeds 2
                // and 3. Its free Σ learns cross-covariances between f and g
                // of correlation near ±1, which the torques u ∝ sin θ of the
                // data cannot refute, and its posterior is sharp along them;
                // the MVGP's B k0 ⊗ A has no such freedom. It keeps the
                // lower bound, and the paper's comparison (Sec. VII-A): the
                // MVGP is the better calibrated of the two.
                assert!(vwe.is_finite() && vwe > 2.0 / 1.5, "{m} {key} vwe {vwe}");
                if m == "MVGP" {
                    assert!(vwe < 2.0 * 1.5, "{m} {key} vwe {vwe}");
                    let cogp = s["models"]["CoGP"][key]["variance_weighted_error"]
                        .as_f64()
                        .unwrap();
                    assert!(vwe < cogp, "{key}: MVGP {vwe}, CoGP {cogp}");
                }
                // measured 0.032 and 0.098 on the grid, 0.006 and 0.004 held out
                assert!(rmse.is_finite() && rmse < 0.25, "{m} {key} rmse {rmse}");
            }
            assert!(r["fit_seconds"].as_f64().unwrap() > 0.0);
            assert!(
                r["log_likelihood"].as_f64().unwrap()
                    > r["log_likelihood_initial"].as_f64().unwrap()
            );
        }
        let files: Vec<&str> = r.tables.iter().map(|t| t.file.as_str()).collect();
        assert_eq!(files, ["trajectory.csv", "grid.csv"]);
        assert_eq!(r.tables[1].csv.lines().count(), 1 + GRID * GRID);
        assert_eq!(r.fitted.len(), 2);
    }
}
