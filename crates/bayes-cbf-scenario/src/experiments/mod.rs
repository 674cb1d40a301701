//! Built-in experiments: `pendulum-learning` (Fig. 4, MVGP vs CoGP fit of
//! the pendulum), `speed-test` (Fig. 5, time and variance-weighted error of
//! MVGP and CoGP, full and diagonal, as the data grow), `covariance-shapes`
//! (Fig. 1), `ackermann-triggering` (Fig. 2), `calibration` (violation rates
//! against `1 − p`) and `soak` (a long online-learning run).
//!
//! Each experiment is seeded and deterministic in its numbers (timings
//! aside) and returns an [`ExperimentResult`]: its `summary.json` (with at
//! least `scenario` and `seed`), its CSV tables and the data of its figures
//! (drawn by the `bayes-cbf-plot` crate). Nothing here prints, plots or
//! writes files. Models are always *fitted* (marginal-likelihood
//! hyperparameters) before they are scored, and MVGP and CoGP always share
//! the kernel family (RBF), the prior mean (zero), the input map and the data.

pub mod ackermann_triggering;
pub mod calibration;
pub mod covariance_shapes;
pub mod learning_demo;
pub mod pendulum_learning;
pub mod soak;
pub mod speed_test;

use crate::bail;
use crate::error::Result;
use crate::scenario::{Column, Trajectory};
pub(crate) use crate::stats::quantile;
use bayes_cbf::gp::{
    metrics, Cogp, CogpHyper, DynamicsModel, InputMap, ModelFitSettings, Mvgp, MvgpHyper,
    PriorMean, Rbf,
};
use bayes_cbf::sim::{simulate_trajectory, Dataset, SimSettings};
use bayes_cbf::systems::{wrap_angle, DynSystem, Pendulum};
use nalgebra::DMatrix;
use rand::seq::SliceRandom;
use rand::{Rng, RngExt};
use rand_distr::{Distribution, StandardNormal};
use std::f64::consts::PI;

/// Options shared by every experiment.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ExperimentArgs {
    /// Seed of every random choice.
    pub seed: u64,
    /// Reduced version that finishes in seconds (for tests and smoke runs);
    /// `pendulum-learning` is already small and ignores it.
    pub quick: bool,
}

/// Progress of a long experiment: `update(done, total)` after each unit of
/// work (episode, case, block of steps), possibly from worker threads.
pub trait Progress: Sync {
    /// `done` of `total` units are finished.
    fn update(&self, done: usize, total: usize);
}

impl<F: Fn(usize, usize) + Sync> Progress for F {
    fn update(&self, done: usize, total: usize) {
        self(done, total)
    }
}

/// A CSV table an experiment produced, with the file name it is written to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Table {
    /// File name (`grid.csv`).
    pub file: String,
    /// The CSV text, header first.
    pub csv: String,
}

/// `trajectory.csv` of the samples an experiment fits its models to, one
/// row per sample: `x1..xn`, `u1..um`, `xdot1..xdotn`, after a `system`
/// column when there are several sets; a system with fewer states or
/// controls than the widest leaves those cells empty.
pub(crate) fn samples_table(sets: &[(&'static str, &Dataset)]) -> Table {
    let n = sets.iter().map(|(_, d)| d.n).max().unwrap_or(0);
    let m = sets.iter().map(|(_, d)| d.m).max().unwrap_or(0);
    let mut columns: Vec<(String, Column)> = Vec::new();
    if sets.len() > 1 {
        let names = sets
            .iter()
            .flat_map(|(name, d)| std::iter::repeat_n(*name, d.len()))
            .collect();
        columns.push(("system".into(), Column::Words(names)));
    }
    // entry `i` of every sample's block of `width(d)` values in `values(d)`;
    // NaN (an empty cell) where a set's block is narrower
    type Block = fn(&Dataset) -> (&[f64], usize);
    let blocks: [(&str, usize, Block); 3] = [
        ("x", n, |d| (&d.xs, d.n)),
        ("u", m, |d| (&d.us, d.m)),
        ("xdot", n, |d| (&d.xdot, d.n)),
    ];
    for (prefix, width, block) in blocks {
        for i in 0..width {
            let values = sets
                .iter()
                .flat_map(|(_, d)| {
                    let (v, w) = block(d);
                    (0..d.len()).map(move |j| if i < w { v[j * w + i] } else { f64::NAN })
                })
                .collect();
            columns.push((format!("{prefix}{}", i + 1), Column::Numbers(values)));
        }
    }
    Table::new("trajectory.csv", Trajectory { columns }.to_csv())
}

impl Table {
    /// A table for `file`.
    pub fn new(file: &str, csv: String) -> Self {
        Self {
            file: file.to_string(),
            csv,
        }
    }
}

/// The built-in experiments: `(name, one-line description)`.
pub const EXPERIMENTS: &[(&str, &str)] = &[
    (
        "pendulum-learning",
        "MVGP vs CoGP fit of the pendulum on 200 samples: true and learned f, g on a 20x20 grid (Fig. 4)",
    ),
    (
        "speed-test",
        "MVGP vs CoGP, full and diag: fit/predict time and variance-weighted error vs k, pendulum and Ackermann (Fig. 5)",
    ),
    (
        "covariance-shapes",
        "MVGP vs CoGP on Ackermann data: 3-sigma ellipses of the covariance of each column of F (Fig. 1)",
    ),
    (
        "ackermann-triggering",
        "Lipschitz bound and inter-trigger time, analytic and numerical; self-triggered vs fixed-step; tau vs zeta (Fig. 2)",
    ),
    (
        "calibration",
        "Monte Carlo of Bayes CBF (p = 0.9, 0.99, 0.999) and mean CBF on GP-prior and mis-specified truths: violation rate vs 1 - p",
    ),
    (
        "soak",
        "long online-learning run with a sliding window: NaN count, peak memory and control-step time over 100 000 steps",
    ),
];

/// Sizes and options of the Monte Carlo experiments; `None` takes the
/// experiment's default.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Sizes {
    /// Episodes and fallback of `calibration`.
    pub calibration: calibration::Options,
    /// Control steps of `soak`.
    pub steps: Option<usize>,
    /// Sliding window of `soak`.
    pub window: Option<usize>,
}

/// What an experiment produced: its summary, tables and the data of its
/// figures.
pub enum ExperimentResult {
    /// `pendulum-learning`.
    PendulumLearning(pendulum_learning::PendulumLearning),
    /// `speed-test`.
    SpeedTest(speed_test::SpeedTest),
    /// `covariance-shapes`.
    CovarianceShapes(covariance_shapes::CovarianceShapes),
    /// `ackermann-triggering`.
    AckermannTriggering(Box<ackermann_triggering::AckermannTriggering>),
    /// `calibration`.
    Calibration(calibration::Calibration),
    /// `soak`.
    Soak(soak::Soak),
}

impl ExperimentResult {
    /// `summary.json`: at least `scenario` (the experiment's name) and `seed`.
    pub fn summary(&self) -> serde_json::Value {
        match self {
            ExperimentResult::PendulumLearning(r) => json_of(&r.summary),
            ExperimentResult::SpeedTest(r) => json_of(&r.summary),
            ExperimentResult::CovarianceShapes(r) => json_of(&r.summary),
            ExperimentResult::AckermannTriggering(r) => json_of(&r.summary),
            ExperimentResult::Calibration(r) => json_of(&r.summary),
            ExperimentResult::Soak(r) => json_of(&r.summary),
        }
    }

    /// The CSV tables to write beside the summary.
    pub fn tables(&self) -> &[Table] {
        match self {
            ExperimentResult::PendulumLearning(r) => &r.tables,
            ExperimentResult::SpeedTest(r) => &r.tables,
            ExperimentResult::Calibration(r) => &r.tables,
            ExperimentResult::CovarianceShapes(r) => &r.tables,
            ExperimentResult::AckermannTriggering(r) => &r.tables,
            ExperimentResult::Soak(_) => &[],
        }
    }
}

/// A typed summary as JSON (non-finite numbers become `null`).
fn json_of<T: serde::Serialize>(summary: &T) -> serde_json::Value {
    serde_json::to_value(summary).unwrap_or(serde_json::Value::Null)
}

/// Runs experiment `name` with `args` and default sizes.
pub fn run(name: &str, args: &ExperimentArgs) -> Result<ExperimentResult> {
    run_sized(name, args, &Sizes::default(), &|_, _| {})
}

/// Runs experiment `name` with `args` and `sizes`, reporting progress; a
/// size given to an experiment that has no such option is an error naming
/// the option.
pub fn run_sized(
    name: &str,
    args: &ExperimentArgs,
    sizes: &Sizes,
    progress: &dyn Progress,
) -> Result<ExperimentResult> {
    let _warnings = bayes_cbf::warnings::Scope::enter();
    let takes = |option: &str, given: bool, accepted: &[&str]| -> Result<()> {
        if given && !accepted.contains(&name) {
            bail!(
                "{option} applies to the experiment(s) {}, not to '{name}'",
                accepted.join(", ")
            );
        }
        Ok(())
    };
    takes(
        "episodes",
        sizes.calibration.episodes.is_some(),
        &["calibration"],
    )?;
    takes(
        "fallback",
        sizes.calibration.fallback.is_some(),
        &["calibration"],
    )?;
    takes("steps", sizes.steps.is_some(), &["soak"])?;
    takes("window", sizes.window.is_some(), &["soak"])?;
    Ok(match name {
        "pendulum-learning" => ExperimentResult::PendulumLearning(pendulum_learning::run(args)?),
        "speed-test" => ExperimentResult::SpeedTest(speed_test::run(args, progress)?),
        "ackermann-triggering" => {
            ExperimentResult::AckermannTriggering(Box::new(ackermann_triggering::run(args)?))
        }
        "covariance-shapes" => ExperimentResult::CovarianceShapes(covariance_shapes::run(args)?),
        "calibration" => {
            ExperimentResult::Calibration(calibration::run(args, &sizes.calibration, progress)?)
        }
        "soak" => ExperimentResult::Soak(soak::run(args, sizes.steps, sizes.window, progress)?),
        _ => {
            let names: Vec<&str> = EXPERIMENTS.iter().map(|(n, _)| *n).collect();
            bail!(
                "unknown experiment '{name}'; built-in experiments: {}",
                names.join(", ")
            )
        }
    })
}

/// The two GP models of `F(x)` compared by the experiments.
#[derive(serde::Serialize, Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum ModelKind {
    /// Matrix-variate GP (Prop. 1): `B k0 ⊗ A`, a `k × k` Gram matrix.
    Mvgp,
    /// Coregionalization GP (Appendix): `Σ k0`, a `kn × kn` Gram matrix.
    Cogp,
}

impl ModelKind {
    /// Report name.
    pub fn name(self) -> &'static str {
        match self {
            ModelKind::Mvgp => "MVGP",
            ModelKind::Cogp => "CoGP",
        }
    }
}

/// An unfitted model with zero prior mean, an RBF kernel on `map(x)` and
/// neutral starting hyperparameters (the fit starts from a data-driven point
/// anyway), holding `data`.
pub(crate) fn new_model(
    kind: ModelKind,
    map: &InputMap,
    data: &Dataset,
) -> Result<Box<dyn DynamicsModel>> {
    let (n, m) = (data.n, data.m);
    let d = map.output_dim(n);
    let kernel = Rbf::new(vec![1.0; d], 1.0)?;
    let mut model: Box<dyn DynamicsModel> = match kind {
        ModelKind::Mvgp => {
            let hyper = MvgpHyper {
                kernel,
                A: DMatrix::identity(n, n),
                B: DMatrix::identity(m + 1, m + 1),
                sigma: 0.1,
            };
            Box::new(Mvgp::new(n, m, hyper, PriorMean::Zero, map.clone())?)
        }
        ModelKind::Cogp => {
            let hyper = CogpHyper {
                kernel,
                Sigma: DMatrix::identity(n * (m + 1), n * (m + 1)),
                S: DMatrix::identity(n, n) * 0.01,
            };
            Box::new(Cogp::new(n, m, hyper, PriorMean::Zero, map.clone())?)
        }
    };
    model.set_data(&data.xs, &data.us, &data.xdot)?;
    Ok(model)
}

/// Fit settings of a variant: `diag` makes both covariances diagonal.
pub(crate) fn fit_settings(diag: bool, max_iters: u64, seed: u64) -> ModelFitSettings {
    let base = if diag {
        ModelFitSettings::diagonal()
    } else {
        ModelFitSettings::default()
    };
    ModelFitSettings {
        max_iters,
        seed,
        ..base
    }
}

/// State box of the pendulum experiments: `θ ∈ [-π, π)`, `ω ∈ [-6, 6]` rad/s.
pub const OMEGA_MAX: f64 = 6.0;
/// Time step of the pendulum data (s).
pub const PENDULUM_DT: f64 = 0.01;
/// Standard deviation of the measurement noise added to the pendulum's `ẋ`
/// estimates (the library's Ackermann workload uses the same 0.01).
pub const XDOT_NOISE: f64 = 0.01;
/// Steps per pendulum trajectory (each from a fresh random state).
pub const TRAJECTORY_LEN: usize = 20;

/// `k` pendulum samples (paper, Sec. VII-A): trajectories of
/// [`TRAJECTORY_LEN`] zero-order-hold steps of `dt = 0.01` s from uniform
/// random states in `[-π, π) × [-6, 6]`, under the random torques
/// `u = m g sin θ · U(0.6, 1.4)`, with `ẋ` by finite differences
/// (footnote 1) plus `N(0, 0.01²)` measurement noise ([`XDOT_NOISE`]).
/// Each difference quotient `(x_{j+1} − x_j)/dt` is paired
/// with the midpoint `x_j + ½ dt ẋ_j` of its step, where it matches
/// `F(x)u̲_j` to `O(dt²)` (at `x_j` only to `O(dt)`). Measured with seed 0
/// on noise-free data and the `(cos θ, sin θ, ω)` kernel input, this cut the
/// grid RMSE of the fitted MVGP from 0.068 to 0.001 and its
/// variance-weighted error from 1.4e4 to 5.2: the forward-difference bias is
/// systematic, so the nearly noise-free fit was badly overconfident.
/// The noise keeps the fits well posed: on exactly smooth data the
/// likelihood drives the signal variance up and the posterior covariance
/// down to where roundoff makes it indefinite (with the identity kernel
/// input and seed 0, the CoGP's variance-weighted error on the grid then
/// needed the extended jitter of [`variance_weighted`] and came out at 57
/// vs the MVGP's 5.8; with the noise, 1.2 and 1.6, near the calibrated
/// value √(n(1+m)) = 2).
pub fn pendulum_samples<R: Rng>(pend: &Pendulum, k: usize, rng: &mut R) -> Result<Dataset> {
    let mut ds = Dataset {
        n: 2,
        m: 1,
        ..Default::default()
    };
    while ds.len() < k {
        let x0 = [
            rng.random_range(-PI..PI),
            rng.random_range(-OMEGA_MAX..OMEGA_MAX),
        ];
        let torque = |x: &[f64], r: &mut R| {
            vec![pend.mass * pend.gravity * x[0].sin() * r.random_range(0.6..1.4)]
        };
        let t = simulate_trajectory(
            pend,
            &x0,
            torque,
            PENDULUM_DT,
            TRAJECTORY_LEN,
            SimSettings::default(),
            rng,
        )?;
        let mut part = t.slice(0..(k - ds.len()).min(t.len()));
        // (x_{j+1} − x_j)/dt equals F(x)u̲_j to O(dt²) at the midpoint of the
        // step but only to O(dt) at x_j: attribute it to the midpoint
        for (x, xd) in part.xs.chunks_mut(2).zip(part.xdot.chunks_mut(2)) {
            x[0] = wrap_angle(x[0] + 0.5 * PENDULUM_DT * xd[0]);
            x[1] += 0.5 * PENDULUM_DT * xd[1];
            for v in xd.iter_mut() {
                let e: f64 = StandardNormal.sample(rng);
                *v += XDOT_NOISE * e;
            }
        }
        ds.xs.extend(part.xs);
        ds.us.extend(part.us);
        ds.xdot.extend(part.xdot);
    }
    Ok(ds)
}

/// Randomly splits `data` into `k` training and the remaining test samples
/// (the paper's random train/test split).
pub(crate) fn random_split<R: Rng>(data: &Dataset, k: usize, rng: &mut R) -> (Dataset, Dataset) {
    let mut idx: Vec<usize> = (0..data.len()).collect();
    idx.shuffle(rng);
    let pick = |ids: &[usize]| {
        let mut d = Dataset {
            n: data.n,
            m: data.m,
            ..Default::default()
        };
        for &j in ids {
            let s = data.slice(j..j + 1);
            d.xs.extend(s.xs);
            d.us.extend(s.us);
            d.xdot.extend(s.xdot);
        }
        d
    };
    let k = k.min(idx.len());
    (pick(&idx[..k]), pick(&idx[k..]))
}

/// Relative jitter levels tried after the library's own ladder (which stops
/// at 1e-6) when a posterior covariance is numerically singular.
pub const EXTRA_JITTER: [f64; 3] = [1e-5, 1e-4, 1e-3];

/// Variance-weighted error (paper, Eq. 33) of `model` on the states `xs`
/// (row-major) against `truth`, with the library's
/// [`metrics::mahalanobis_sq`] per point, exactly as
/// [`bayes_cbf::gp::variance_weighted_error`] computes it, except that when
/// the library's jitter ladder (up to 1e-6 × mean diagonal) fails, the
/// ladder continues with [`EXTRA_JITTER`]. Nearly noise-free data make
/// `K_k(x, x)` so small that the roundoff of `Σ k0 − 𝐊 𝐆⁻¹ 𝐊ᵀ` leaves it
/// indefinite at the 1e-6 level for the CoGP. Returns the error and the
/// number of points that needed the extended ladder.
pub fn variance_weighted(
    model: &dyn DynamicsModel,
    xs: &[f64],
    truth: &dyn DynSystem,
) -> Result<(f64, usize)> {
    let (n, np) = (
        model.state_dim(),
        model.state_dim() * (model.control_dim() + 1),
    );
    let mut f = vec![0.0; np];
    let (mut sum, mut extended, mut points) = (0.0, 0, 0usize);
    for x in xs.chunks(n) {
        let (mean, cov) = model.posterior_vec(x)?;
        truth.eval_f64(x, &mut f);
        let e: Vec<f64> = (0..np).map(|a| mean[a] - f[a]).collect();
        let d = match metrics::mahalanobis_sq(&cov, &e) {
            Ok(d) => d,
            Err(first) => {
                extended += 1;
                let scale = (cov.trace() / np as f64).abs().max(f64::MIN_POSITIVE);
                EXTRA_JITTER
                    .iter()
                    .find_map(|&lvl| {
                        let mut c = cov.clone();
                        for i in 0..np {
                            c[(i, i)] += lvl * scale;
                        }
                        metrics::mahalanobis_sq(&c, &e).ok()
                    })
                    .ok_or(first)?
            }
        };
        sum += d;
        points += 1;
    }
    if points == 0 {
        bail!("no points to score");
    }
    Ok(((sum / points as f64).sqrt(), extended))
}

/// `n` evenly spaced points from `a` to `b` inclusive.
pub(crate) fn linspace(a: f64, b: f64, n: usize) -> Vec<f64> {
    match n {
        0 => Vec::new(),
        1 => vec![a],
        _ => (0..n)
            .map(|i| a + (b - a) * i as f64 / (n - 1) as f64)
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn helpers() {
        assert_eq!(linspace(0.0, 1.0, 3), vec![0.0, 0.5, 1.0]);
        assert_eq!(json_of(&f64::INFINITY), serde_json::Value::Null);
        let err = run(
            "nope",
            &ExperimentArgs {
                seed: 0,
                quick: true,
            },
        )
        .err()
        .unwrap();
        assert!(err.to_string().contains("speed-test"));
    }

    #[test]
    fn pendulum_data_and_split() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let ds = pendulum_samples(&Pendulum::default(), 45, &mut rng).unwrap();
        assert_eq!((ds.len(), ds.xs.len(), ds.us.len()), (45, 90, 45));
        // u = m g sin θ_j · c with c in [0.6, 1.4], where the stored state is
        // the step midpoint θ_j + ½ dt ω_j (|½ dt ω| < 0.04 rad here)
        for j in 0..45 {
            let (theta, u) = (ds.xs[2 * j], ds.us[j]);
            assert!(
                u.abs() <= 14.0 * (theta.sin().abs() + 0.04),
                "{u} at {theta}"
            );
            assert!(
                u * theta.sin() >= 0.0 || theta.sin().abs() < 0.04,
                "{u} at {theta}"
            );
        }
        // the difference quotients match F(x)u̲ at the midpoints to about the noise
        let mut f = [0.0; 4];
        for j in 0..45 {
            Pendulum::default().eval_f64(&ds.xs[2 * j..2 * j + 2], &mut f);
            let wdot = f[1] + f[3] * ds.us[j];
            assert!((ds.xdot[2 * j + 1] - wdot).abs() < 0.06, "{j}");
        }
        let (tr, te) = random_split(&ds, 30, &mut rng);
        assert_eq!((tr.len(), te.len()), (30, 15));
    }
}
