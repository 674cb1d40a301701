//! The default job: a small but real pendulum learning run (paper,
//! Sec. VII-A, Fig. 4). Simulates the pendulum (`m = l = 1`, `g = 10`) for
//! 200 steps of `dt = 0.01` under the random torques
//! `u = m g sin θ · U(0.6, 1.4)`, fits an MVGP with zero prior mean by
//! maximising the marginal likelihood, and compares the learned `f` and `g`
//! (posterior mean columns) with the truth on a 20 × 20 grid of
//! `[-π, π) × [-6, 6]`, and `F(x)u̲` on held-out samples.
//!
//! The 200 steps are split into trajectories of 20 steps, each from a fresh
//! random initial state: one 200-step trajectory (2 s) sweeps too little of
//! the grid (relative error of `f` ≈ 0.4 with seed 0, against ≈ 0.016).
//! `--trajectory-len 200` reproduces the single trajectory.

use crate::commands::initial_model;
use crate::logger::hold_warnings;
use anyhow::{bail, Context, Result};
use bayes_cbf::gp::{fit, FitSettings, InputMap, Mvgp};
use bayes_cbf::sim::{simulate_trajectory, Dataset, SimSettings};
use bayes_cbf::systems::{DynSystem, Pendulum};
use bayes_cbf_scenario::csv_data::to_csv;
use bayes_cbf_scenario::io::write_atomic;
use bayes_cbf_scenario::model_file::ModelFile;
use bayes_cbf_scenario::prior_spec::PriorSpec;
use clap::{Args, ValueEnum};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::json;
use std::f64::consts::PI;
use std::io::Write;
use std::path::PathBuf;
use std::time::Instant;

/// How the demo collects its training data.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Sampling {
    /// Several trajectories of `dt`-spaced steps from random initial
    /// states; `ẋ` by finite differences.
    Trajectory,
    /// States drawn uniformly on the evaluation box with exact `ẋ`.
    Uniform,
}

/// Options of `bayes-cbf demo`.
#[derive(Debug, Clone, PartialEq, Args)]
pub struct DemoArgs {
    /// Output directory.
    #[arg(long, default_value = "runs/learning-demo")]
    pub out: PathBuf,
    /// Seed of every random choice (initial states, torques, splits, fit).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Number of training samples k.
    #[arg(long, default_value_t = 200)]
    pub steps: usize,
    /// Number of held-out samples for the error of F(x)u̲.
    #[arg(long, default_value_t = 100)]
    pub heldout: usize,
    /// Evaluation grid size per axis (θ and ω).
    #[arg(long, default_value_t = 20)]
    pub grid: usize,
    /// Time step dt of the simulation (s).
    #[arg(long, default_value_t = 0.01)]
    pub dt: f64,
    /// Steps per trajectory with --sampling trajectory (a fresh random
    /// initial state in [-π, π) × [-6, 6] starts each trajectory).
    #[arg(long, default_value_t = 20)]
    pub trajectory_len: usize,
    /// Random restarts of the hyperparameter optimiser.
    #[arg(long, default_value_t = 0)]
    pub restarts: usize,
    /// Floor of the learned noise scale σ.
    #[arg(long, default_value_t = 0.0)]
    pub sigma_min: f64,
    /// Process-noise intensity of the simulation (Euler–Maruyama, per √s).
    #[arg(long, default_value_t = 0.0)]
    pub process_noise: f64,
    /// Kernel sees θ through (cos θ, sin θ), continuous across ±π.
    #[arg(long)]
    pub periodic: bool,
    /// Training-data design.
    #[arg(long, value_enum, default_value_t = Sampling::Trajectory)]
    pub sampling: Sampling,
}

impl Default for DemoArgs {
    fn default() -> Self {
        Self {
            out: PathBuf::from("runs/learning-demo"),
            seed: 0,
            steps: 200,
            heldout: 100,
            grid: 20,
            dt: 0.01,
            trajectory_len: 20,
            restarts: 0,
            sigma_min: 0.0,
            process_noise: 0.0,
            periodic: false,
            sampling: Sampling::Trajectory,
        }
    }
}

const OMEGA_MAX: f64 = 6.0;

/// Random torque of the paper's experiment: `u = m g sin θ · U(0.6, 1.4)`.
fn random_torque(p: &Pendulum, x: &[f64], rng: &mut ChaCha8Rng) -> Vec<f64> {
    vec![p.mass * p.gravity * x[0].sin() * rng.random_range(0.6..1.4)]
}

fn random_state(rng: &mut ChaCha8Rng) -> [f64; 2] {
    [
        rng.random_range(-PI..PI),
        rng.random_range(-OMEGA_MAX..OMEGA_MAX),
    ]
}

/// `k` samples from the chosen design.
fn collect(p: &Pendulum, a: &DemoArgs, k: usize, rng: &mut ChaCha8Rng) -> Result<Dataset> {
    let mut ds = Dataset {
        n: 2,
        m: 1,
        ..Default::default()
    };
    match a.sampling {
        Sampling::Trajectory => {
            let len = a.trajectory_len.max(2);
            while ds.len() < k {
                let x0 = random_state(rng);
                let t = simulate_trajectory(
                    p,
                    &x0,
                    |x, r| random_torque(p, x, r),
                    a.dt,
                    len,
                    SimSettings::new(1e-3, a.process_noise)?,
                    rng,
                )?;
                let take = (k - ds.len()).min(t.len());
                let part = t.slice(0..take);
                ds.xs.extend(part.xs);
                ds.us.extend(part.us);
                ds.xdot.extend(part.xdot);
            }
        }
        Sampling::Uniform => {
            let mut fbuf = [0.0; 4];
            let mut xd = [0.0; 2];
            for _ in 0..k {
                let x = random_state(rng);
                let u = random_torque(p, &x, rng);
                p.xdot(&x, &u, &mut fbuf, &mut xd);
                ds.xs.extend_from_slice(&x);
                ds.us.extend_from_slice(&u);
                ds.xdot.extend_from_slice(&xd);
            }
        }
    }
    Ok(ds)
}

/// Errors and grid rows of a fitted model against the true pendulum.
struct Evaluation {
    f_rel_rmse: f64,
    g_rel_rmse: f64,
    fu_rel_rmse: f64,
    grid_rows: Vec<Vec<f64>>,
}

fn evaluate(model: &Mvgp, p: &Pendulum, heldout: &Dataset, g: usize) -> Result<Evaluation> {
    let a = &model.hyper().A;
    let (mut ef, mut nf, mut eg, mut ng) = (0.0, 0.0, 0.0, 0.0);
    let mut truth = [0.0; 4];
    let mut rows = Vec::with_capacity(g * g);
    for i in 0..g {
        for j in 0..g {
            let x = [
                -PI + 2.0 * PI * i as f64 / g as f64,
                -OMEGA_MAX + 2.0 * OMEGA_MAX * j as f64 / g as f64,
            ];
            p.eval_f64(&x, &mut truth);
            let post = model.posterior(&x)?;
            // column-major vec F: truth[r + 2c]
            let mean = [
                post.mean[(0, 0)],
                post.mean[(1, 0)],
                post.mean[(0, 1)],
                post.mean[(1, 1)],
            ];
            let std: Vec<f64> = (0..4)
                .map(|e| (post.B[(e / 2, e / 2)] * a[(e % 2, e % 2)]).max(0.0).sqrt())
                .collect();
            for e in 0..2 {
                ef += (mean[e] - truth[e]).powi(2);
                nf += truth[e].powi(2);
                eg += (mean[2 + e] - truth[2 + e]).powi(2);
                ng += truth[2 + e].powi(2);
            }
            let mut row = vec![x[0], x[1]];
            row.extend_from_slice(&truth);
            row.extend_from_slice(&mean);
            row.extend_from_slice(&std);
            rows.push(row);
        }
    }
    // held-out error against the exact F(x)u̲ (not the finite differences)
    let (mut efu, mut nfu) = (0.0, 0.0);
    let mut exact = [0.0; 2];
    for j in 0..heldout.len() {
        let x = &heldout.xs[2 * j..2 * j + 2];
        let u = heldout.us[j];
        p.xdot(x, &[u], &mut truth, &mut exact);
        let post = model.posterior(x)?;
        for (r, ex) in exact.iter().enumerate() {
            let pred = post.mean[(r, 0)] + post.mean[(r, 1)] * u;
            efu += (pred - ex).powi(2);
            nfu += ex.powi(2);
        }
    }
    let rel = |e: f64, n: f64| (e / n.max(1e-300)).sqrt();
    Ok(Evaluation {
        f_rel_rmse: rel(ef, nf),
        g_rel_rmse: rel(eg, ng),
        fu_rel_rmse: rel(efu, nfu),
        grid_rows: rows,
    })
}

/// Runs the demo and prints where its outputs went.
pub fn run_demo(a: &DemoArgs) -> Result<()> {
    if !(2..=20_000).contains(&a.steps) {
        bail!("--steps = {} must be between 2 and 20000", a.steps);
    }
    if a.heldout > 100_000 {
        bail!("--heldout = {} must be at most 100000", a.heldout);
    }
    if !(2..=500).contains(&a.grid) {
        bail!("--grid = {} must be between 2 and 500", a.grid);
    }
    if !(a.dt.is_finite() && a.dt > 0.0 && a.dt <= 1.0) {
        bail!("--dt = {} must be in (0, 1]", a.dt);
    }
    let pend = Pendulum::default();
    let mut rng = ChaCha8Rng::seed_from_u64(a.seed);
    let train = collect(&pend, a, a.steps, &mut rng).context("simulating training data")?;
    let heldout = collect(&pend, a, a.heldout, &mut rng).context("simulating held-out data")?;
    let prior = PriorSpec::Zero;
    let mut model = initial_model(
        2,
        1,
        &prior,
        if a.periodic {
            InputMap::periodic(2, &[0])
        } else {
            InputMap::Identity
        },
    )?;
    model.set_data(&train.xs, &train.us, &train.xdot)?;
    let settings = FitSettings {
        restarts: a.restarts,
        sigma_min: a.sigma_min,
        seed: a.seed,
        ..FitSettings::default()
    };
    let start = Instant::now();
    let report = hold_warnings("hyperparameter fitting", || fit(&mut model, &settings))
        .context("fitting the MVGP")?;
    let fit_secs = start.elapsed().as_secs_f64();
    let ev = evaluate(&model, &pend, &heldout, a.grid)?;

    let model_path = a.out.join("model.json");
    let grid_path = a.out.join("grid.csv");
    let summary_path = a.out.join("summary.json");
    write_atomic(
        &model_path,
        ModelFile::from_model(&model, &prior).to_json()?.as_bytes(),
    )?;
    let header = [
        "theta", "omega", "f1_true", "f2_true", "g1_true", "g2_true", "f1_mean", "f2_mean",
        "g1_mean", "g2_mean", "f1_std", "f2_std", "g1_std", "g2_std",
    ];
    write_atomic(&grid_path, to_csv(&header, &ev.grid_rows).as_bytes())?;
    let h = model.hyper();
    let summary = json!({
        "demo": "pendulum-learning",
        "seed": a.seed,
        "system": {"type": "pendulum", "mass": pend.mass, "length": pend.length, "gravity": pend.gravity},
        "sampling": format!("{:?}", a.sampling).to_lowercase(),
        "dt": a.dt,
        "trajectory_len": if a.sampling == Sampling::Trajectory { Some(a.trajectory_len) } else { None },
        "process_noise": a.process_noise,
        "training_samples": model.len(),
        "heldout_samples": a.heldout,
        "grid": a.grid,
        "fit_seconds": fit_secs,
        "log_likelihood_initial": report.initial_log_likelihood,
        "log_likelihood": report.log_likelihood,
        "rel_rmse": {"f_grid": ev.f_rel_rmse, "g_grid": ev.g_rel_rmse, "Fu_heldout": ev.fu_rel_rmse},
        "lengthscales": h.kernel.lengthscales(),
        "noise_sigma": h.sigma,
        "gram_jitter": model.factor().max_jitter(),
        "input_map": if a.periodic { "cos:0,sin:0,1" } else { "identity" },
        "files": {"model": model_path, "grid": grid_path, "summary": summary_path},
    });
    let mut text =
        serde_json::to_string_pretty(&summary).context("cannot serialise the summary")?;
    text.push('\n');
    write_atomic(&summary_path, text.as_bytes())?;

    let g = a.grid;
    let report_text = format!(
        "pendulum learning demo (m = l = 1, g = 10, seed {seed}, {sampling:?} sampling)\n\
         \x20 trained MVGP (zero prior mean) on k = {k} samples (dt = {dt}), fit {fit_secs:.2} s, \
         log-likelihood {ll0:.1} -> {ll1:.1}\n\
         \x20 relative RMSE on the {g}x{g} grid of [-pi, pi) x [-6, 6]: f {ef:.3e}, g {eg:.3e}\n\
         \x20 relative RMSE of F(x)u on {nh} held-out samples: {efu:.3e}\n\
         \x20 wrote {mp}\n  wrote {gp}\n  wrote {sp}\n",
        seed = a.seed,
        sampling = a.sampling,
        k = model.len(),
        dt = a.dt,
        ll0 = report.initial_log_likelihood,
        ll1 = report.log_likelihood,
        ef = ev.f_rel_rmse,
        eg = ev.g_rel_rmse,
        nh = a.heldout,
        efu = ev.fu_rel_rmse,
        mp = model_path.display(),
        gp = grid_path.display(),
        sp = summary_path.display(),
    );
    let mut out = std::io::stdout().lock();
    out.write_all(report_text.as_bytes())
        .and_then(|()| out.flush())
        .context("cannot write to stdout")?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::{FromArgMatches, Subcommand};

    #[derive(Debug, clap::Subcommand)]
    enum Wrapper {
        Demo(DemoArgs),
    }

    #[test]
    fn default_matches_command_line_defaults() {
        let cmd = Wrapper::augment_subcommands(clap::Command::new("t"));
        let matches = cmd.try_get_matches_from(["t", "demo"]).unwrap();
        let Wrapper::Demo(parsed) = Wrapper::from_arg_matches(&matches).unwrap();
        assert_eq!(parsed, DemoArgs::default());
    }
}
