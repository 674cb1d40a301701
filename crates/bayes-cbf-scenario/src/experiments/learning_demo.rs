//! The learning demo of `bayes-cbf demo`: a small but real pendulum
//! learning run (paper, Sec. VII-A, Fig. 4) with one model and its files.
//!
//! ## Setup
//! Pendulum `m = l = 1`, `g = 10` (Eq. 31). Training and held-out samples
//! come from [`super::pendulum_samples`] (trajectories of 20 steps of
//! `dt = 0.01` s from random states in `[-π, π) × [-6, 6]` under
//! `u = m g sin θ · U(0.6, 1.4)`, `ẋ` by finite differences at the step
//! midpoints plus `N(0, 0.01²)` noise), or with [`Sampling::Uniform`] from
//! [`crate::workloads::pendulum_data`] (uniform states on the same box,
//! `u ~ U(−20, 20)`, exact `ẋ` plus the same noise). Short trajectories
//! matter: one 200-step trajectory (2 s) sweeps too little of the grid.
//!
//! One MVGP with zero prior mean (and an RBF kernel on `(θ, ω)`, or on
//! `(cos θ, sin θ, ω)` with `periodic`) is fitted by maximising the marginal
//! likelihood ([`bayes_cbf::gp::fit`]) and scored against the true `F(x)`:
//! the relative RMSE of the posterior mean columns `f` and `g` on the
//! `g × g` grid `θ_i = −π + 2π i/g`, `ω_j = −6 + 12 j/g`, and of `F(x)u̲` on
//! the held-out samples ([`metrics::relative_rmse_fu`]).

use super::{pendulum_samples, Table, OMEGA_MAX, PENDULUM_DT, TRAJECTORY_LEN};
use crate::bail;
use crate::csv_data::to_csv;
use crate::error::{Context, Result};
use crate::experiments::pendulum_learning::SystemInfo;
use crate::fitting::initial_model;
use crate::model_file::ModelFile;
use crate::prior_spec::PriorSpec;
use crate::workloads::pendulum_data;
use bayes_cbf::gp::{fit, metrics, DynamicsModel, FitSettings, InputMap, Mvgp};
use bayes_cbf::sim::Dataset;
use bayes_cbf::systems::{DynSystem, Pendulum};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::f64::consts::PI;
use std::time::Instant;

/// How the demo collects its data.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Sampling {
    /// Short trajectories from random initial states ([`pendulum_samples`]).
    #[default]
    Trajectory,
    /// States uniform on the box ([`pendulum_data`]).
    Uniform,
}

/// Options of the demo.
#[derive(Debug, Clone, PartialEq)]
pub struct Settings {
    /// Seed of every random choice (data and fit).
    pub seed: u64,
    /// Training samples `k`, 2 to 20 000.
    pub steps: usize,
    /// Held-out samples for the error of `F(x)u̲`, at most 100 000.
    pub heldout: usize,
    /// Grid points per axis, 2 to 500.
    pub grid: usize,
    /// Random restarts of the hyperparameter optimiser.
    pub restarts: usize,
    /// Floor of the learned noise standard deviation of state component 0,
    /// `σ·√A₀₀` ([`bayes_cbf::gp::FitSettings::sigma_min`]).
    pub sigma_min: f64,
    /// Kernel on `(cos θ, sin θ, ω)`, continuous across `±π`.
    pub periodic: bool,
    /// Data design.
    pub sampling: Sampling,
}

impl Default for Settings {
    fn default() -> Self {
        Self {
            seed: 0,
            steps: 200,
            heldout: 100,
            grid: 20,
            restarts: 0,
            sigma_min: 0.0,
            periodic: false,
            sampling: Sampling::Trajectory,
        }
    }
}

impl Settings {
    /// Checks the sizes (errors name the field).
    pub fn validate(&self) -> Result<()> {
        if !(2..=20_000).contains(&self.steps) {
            bail!("steps = {} must be between 2 and 20000", self.steps);
        }
        if self.heldout > 100_000 {
            bail!("heldout = {} must be at most 100000", self.heldout);
        }
        if !(2..=500).contains(&self.grid) {
            bail!("grid = {} must be between 2 and 500", self.grid);
        }
        Ok(())
    }
}

/// Relative RMSEs of the fitted model.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RelRmse {
    /// `√(Σ‖f̂ − f‖² / Σ‖f‖²)` over the grid.
    pub f_grid: f64,
    /// The same for `g`.
    pub g_grid: f64,
    /// `‖(M_k − F) u̲‖ / ‖F u̲‖` over the held-out samples (NaN without any).
    #[serde(rename = "Fu_heldout")]
    pub fu_heldout: f64,
}

/// `summary.json` of the demo (the command adds the paths it wrote).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Summary {
    /// `pendulum-learning`.
    pub demo: &'static str,
    /// Seed.
    pub seed: u64,
    /// The true system.
    pub system: SystemInfo,
    /// Data design.
    pub sampling: Sampling,
    /// Step of the trajectories (s).
    pub dt: f64,
    /// Steps per trajectory (trajectory sampling only).
    pub trajectory_len: Option<usize>,
    /// Process-noise intensity of the simulation.
    pub process_noise: f64,
    /// How `ẋ` was measured.
    pub xdot: &'static str,
    /// Training samples.
    pub training_samples: usize,
    /// Held-out samples.
    pub heldout_samples: usize,
    /// Grid points per axis.
    pub grid: usize,
    /// Fit time (s).
    pub fit_seconds: f64,
    /// Log marginal likelihood at the fit's start.
    pub log_likelihood_initial: f64,
    /// Log marginal likelihood fitted.
    pub log_likelihood: f64,
    /// The errors.
    pub rel_rmse: RelRmse,
    /// Fitted kernel lengthscales.
    pub lengthscales: Vec<f64>,
    /// Fitted noise scale `σ`.
    pub noise_sigma: f64,
    /// Largest jitter the Gram factor needed.
    pub gram_jitter: f64,
    /// What the kernel sees.
    pub input_map: &'static str,
}

/// The result of the demo.
#[derive(Debug, Clone)]
pub struct LearningDemo {
    /// The fitted model (zero prior mean).
    pub model: Mvgp,
    /// `summary.json`.
    pub summary: Summary,
    /// `grid.csv`: per grid point `θ, ω`, the true `f, g`, posterior means
    /// and standard deviations.
    pub grid: Table,
}

impl LearningDemo {
    /// The fitted model as a model file.
    pub fn model_file(&self) -> ModelFile {
        ModelFile::from_model(&self.model, &PriorSpec::Zero)
    }
}

/// Training and held-out data of `s.sampling`.
fn data(pend: &Pendulum, s: &Settings) -> Result<(Dataset, Dataset)> {
    Ok(match s.sampling {
        Sampling::Trajectory => {
            let mut rng = ChaCha8Rng::seed_from_u64(s.seed);
            let train = pendulum_samples(pend, s.steps, &mut rng)?;
            (train, pendulum_samples(pend, s.heldout, &mut rng)?)
        }
        Sampling::Uniform => {
            let all = pendulum_data(s.steps + s.heldout, s.seed)?;
            (all.slice(0..s.steps), all.slice(s.steps..all.len()))
        }
    })
}

/// Relative errors of `f` and `g` on the `g × g` grid, and its rows.
fn grid_scores(model: &Mvgp, pend: &Pendulum, g: usize) -> Result<(f64, f64, Vec<Vec<f64>>)> {
    let (mut ef, mut nf, mut eg, mut ng) = (0.0, 0.0, 0.0, 0.0);
    let mut truth = [0.0; 4];
    let mut rows = Vec::with_capacity(g * g);
    for i in 0..g {
        for j in 0..g {
            let x = [
                -PI + 2.0 * PI * i as f64 / g as f64,
                -OMEGA_MAX + 2.0 * OMEGA_MAX * j as f64 / g as f64,
            ];
            pend.eval_f64(&x, &mut truth);
            // vec F, column-major: entry r + 2c; Cov(vec F) = B ⊗ A
            let (m, cov) = model.posterior_vec(&x)?;
            let mean = [m[(0, 0)], m[(1, 0)], m[(0, 1)], m[(1, 1)]];
            for e in 0..2 {
                ef += (mean[e] - truth[e]).powi(2);
                nf += truth[e].powi(2);
                eg += (mean[2 + e] - truth[2 + e]).powi(2);
                ng += truth[2 + e].powi(2);
            }
            let mut row = vec![x[0], x[1]];
            row.extend(truth);
            row.extend(mean);
            row.extend((0..4).map(|e| cov[(e, e)].max(0.0).sqrt()));
            rows.push(row);
        }
    }
    let rel = |e: f64, n: f64| (e / n.max(1e-300)).sqrt();
    Ok((rel(ef, nf), rel(eg, ng), rows))
}

/// Runs the demo (see the module docs).
pub fn run(s: &Settings) -> Result<LearningDemo> {
    s.validate()?;
    let pend = Pendulum::default();
    let (train, heldout) = data(&pend, s).context("simulating the pendulum")?;
    let map = if s.periodic {
        InputMap::periodic(2, &[0])
    } else {
        InputMap::Identity
    };
    let mut model = initial_model(2, 1, &PriorSpec::Zero, map)?;
    model.set_data(&train.xs, &train.us, &train.xdot)?;
    let settings = FitSettings {
        restarts: s.restarts,
        sigma_min: s.sigma_min,
        seed: s.seed,
        ..FitSettings::default()
    };
    let start = Instant::now();
    let report = fit(&mut model, &settings).context("fitting the MVGP")?;
    let fit_seconds = start.elapsed().as_secs_f64();
    let (f_grid, g_grid, rows) = grid_scores(&model, &pend, s.grid)?;
    let fu_heldout = if heldout.is_empty() {
        f64::NAN
    } else {
        metrics::relative_rmse_fu(&model, &heldout.xs, &heldout.us, &pend)?
    };
    let header = [
        "theta", "omega", "f1_true", "f2_true", "g1_true", "g2_true", "f1_mean", "f2_mean",
        "g1_mean", "g2_mean", "f1_std", "f2_std", "g1_std", "g2_std",
    ];
    let trajectory = s.sampling == Sampling::Trajectory;
    let h = model.hyper();
    let summary = Summary {
        demo: "pendulum-learning",
        seed: s.seed,
        system: SystemInfo {
            kind: "pendulum",
            mass: pend.mass,
            length: pend.length,
            gravity: pend.gravity,
        },
        sampling: s.sampling,
        dt: PENDULUM_DT,
        trajectory_len: trajectory.then_some(TRAJECTORY_LEN),
        process_noise: 0.0,
        xdot: if trajectory {
            "finite differences at step midpoints + N(0, 0.01^2) noise"
        } else {
            "exact + N(0, 0.01^2) noise"
        },
        training_samples: model.len(),
        heldout_samples: heldout.len(),
        grid: s.grid,
        fit_seconds,
        log_likelihood_initial: report.initial_log_likelihood,
        log_likelihood: report.log_likelihood,
        rel_rmse: RelRmse {
            f_grid,
            g_grid,
            fu_heldout,
        },
        lengthscales: h.kernel.lengthscales().to_vec(),
        noise_sigma: h.sigma,
        gram_jitter: model.factor().max_jitter(),
        input_map: if s.periodic {
            "cos:0,sin:0,1"
        } else {
            "identity"
        },
    };
    Ok(LearningDemo {
        grid: Table::new("grid.csv", to_csv(&header, &rows)),
        model,
        summary,
    })
}
