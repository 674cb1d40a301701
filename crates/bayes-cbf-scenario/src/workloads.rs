//! Standard workloads for benchmarks and examples: the model and safety
//! controller of a built-in scenario (the one source of every built-in
//! setup) with `k` observations: the Ackermann vehicle (two obstacle
//! barriers and the CLF, relative degree 1) or the pendulum (sector
//! barrier, relative degree 2), as in the paper's Sec. VII.

use crate::barrier_file::BarrierSpec;
use crate::error::Result;
use crate::prior_spec::PriorSpec;
use crate::scenario::{self, Scenario};
use bayes_cbf::control::SafetyController;
use bayes_cbf::gp::Mvgp;
use bayes_cbf::sim::{sample_uniform, Dataset};
use bayes_cbf::systems::{Ackermann, Pendulum};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::f64::consts::PI;

/// A model, a controller and a state to run one control step at.
pub struct ControlWorkload {
    /// The learned model (`k` observations).
    pub model: Mvgp,
    /// The safety controller.
    pub controller: SafetyController,
    /// Query state.
    pub x: Vec<f64>,
    /// Reference control.
    pub u_ref: Vec<f64>,
    /// CLF reference `(x_d, ẋ_d)`, if any.
    pub reference: Option<(Vec<f64>, Vec<f64>)>,
    /// Further observations for online-update benchmarks.
    pub extra: Dataset,
}

/// Uniform training data of the Ackermann vehicle (true wheelbase `L`).
pub fn ackermann_data(k: usize, wheelbase: f64, seed: u64) -> Result<Dataset> {
    let sys = Ackermann { wheelbase };
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    Ok(sample_uniform(
        &sys,
        &[-3.0, -3.0, -PI],
        &[3.0, 3.0, PI],
        &[-1.0, -1.0],
        &[1.0, 1.0],
        k,
        0.01,
        &mut rng,
    )?)
}

/// A stream of Ackermann observations (true wheelbase `L`) whose heading
/// sweeps once through `[−π, π)` in order: observation `j` has
/// `θ_j ~ U[−π + 2πj/k, −π + 2π(j+1)/k)`, position uniform in `[−3, 3]²`,
/// control uniform in `[−1, 1]²`, `ẋ = F(x)u̲ + N(0, 0.01² I)`. With the
/// kernel on θ only, a sliding window of `w ≪ k` points sees only the
/// last `2πw/k` radians of heading: the workload that separates a window
/// from a budget (docs/performance.md).
pub fn ackermann_heading_sweep(k: usize, wheelbase: f64, seed: u64) -> Result<Dataset> {
    let sys = Ackermann { wheelbase };
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut out = Dataset {
        n: 3,
        m: 2,
        ..Dataset::default()
    };
    let width = 2.0 * PI / k.max(1) as f64;
    for j in 0..k {
        let lo = -PI + width * j as f64;
        let one = sample_uniform(
            &sys,
            &[-3.0, -3.0, lo],
            &[3.0, 3.0, lo + width],
            &[-1.0, -1.0],
            &[1.0, 1.0],
            1,
            0.01,
            &mut rng,
        )?;
        out.xs.extend_from_slice(&one.xs);
        out.us.extend_from_slice(&one.us);
        out.xdot.extend_from_slice(&one.xdot);
    }
    Ok(out)
}

/// Uniform training data of the pendulum (`m = l = 1`, `g = 10`).
pub fn pendulum_data(k: usize, seed: u64) -> Result<Dataset> {
    let sys = Pendulum::default();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    Ok(sample_uniform(
        &sys,
        &[-PI, -6.0],
        &[PI, 6.0],
        &[-20.0],
        &[20.0],
        k,
        0.01,
        &mut rng,
    )?)
}

/// How a workload's scenario is written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Written {
    /// As built in (Rust systems and barriers).
    BuiltIn,
    /// System, prior mean and barriers in the expression language
    /// ([`scenario::as_expressions`]).
    Expressions,
}

/// A built-in scenario's model (with `k` observations of `data`, the rest
/// kept for online updates), controller and start state.
fn from_builtin(
    name: &str,
    adjust: fn(&mut Scenario),
    k: usize,
    data: Dataset,
    written: Written,
) -> Result<ControlWorkload> {
    let (mut sc, _) = scenario::load(name, &[])?;
    adjust(&mut sc);
    if written == Written::Expressions {
        sc = scenario::as_expressions(&sc)?;
    }
    let built = scenario::build(&sc)?;
    let mut model = built.model;
    let train = data.slice(0..k);
    model.set_data(&train.xs, &train.us, &train.xdot)?;
    Ok(ControlWorkload {
        model,
        controller: built.controller,
        x: built.start.clone(),
        u_ref: vec![0.0; built.truth.control_dim()],
        reference: None,
        extra: data.slice(k..data.len()),
    })
}

/// Ackermann workload: the built-in scenario `ackermann-bayes-cbf` (prior
/// mean `L = 1`, kernel on θ only, `A = 0.01 I`, `B = I`, two
/// `circle_heading` barriers and the CLF of Sec. VII-B, `p = 0.99`) with
/// `k` observations of the true vehicle (`L = 12`) at its start state,
/// reference control `(0.5, 0)` and a CLF reference just ahead.
pub fn ackermann_control(k: usize, seed: u64) -> Result<ControlWorkload> {
    ackermann_control_written(k, seed, Written::BuiltIn)
}

/// [`ackermann_control`] with the scenario written as `written`.
pub fn ackermann_control_written(k: usize, seed: u64, written: Written) -> Result<ControlWorkload> {
    let mut w = from_builtin(
        "ackermann-bayes-cbf",
        |_| {},
        k,
        ackermann_data(k + 200, 12.0, seed)?,
        written,
    )?;
    w.u_ref = vec![0.5, 0.0];
    w.reference = Some((vec![-2.9, -0.97, PI / 4.0], vec![0.3, 0.1, 0.0]));
    Ok(w)
}

/// Pendulum workload: the paper's Fig. 6 (Sec. VII-A), the built-in
/// scenario `pendulum-safe` as the paper wrote it (zero prior mean, the
/// sector barrier `cos Δ − cos(θ − θ_c)` with `θ_c = 45°`, `Δ = 22.5°`,
/// relative degree 2 with `k_α = [1, 3]`, the max-margin fallback;
/// `p = 0.99`, `|u| ≤ 20`) with `k` observations, at its start `θ = 75°`,
/// `ω = −0.01`.
pub fn pendulum_control(k: usize, seed: u64) -> Result<ControlWorkload> {
    pendulum_control_written(k, seed, Written::BuiltIn)
}

/// [`pendulum_control`] with the scenario written as `written`.
pub fn pendulum_control_written(k: usize, seed: u64, written: Written) -> Result<ControlWorkload> {
    from_builtin(
        "pendulum-safe",
        as_in_the_paper,
        k,
        pendulum_data(k + 200, seed)?,
        written,
    )
}

/// `pendulum-safe` as the paper wrote it: zero prior mean (no known row),
/// one sector barrier, the max-margin fallback.
fn as_in_the_paper(sc: &mut Scenario) {
    sc.gp.prior_mean = PriorSpec::Zero;
    sc.gp.known_rows.clear();
    sc.barriers = vec![BarrierSpec::PendulumSector {
        theta_c: std::f64::consts::FRAC_PI_4,
        delta: std::f64::consts::FRAC_PI_8,
        relative_degree: 2,
        alpha: None,
        k_alpha: Some(vec![1.0, 3.0]),
    }];
    sc.controller.fallback = Some("max_margin".into());
}
