//! Standard workloads for benchmarks and examples: an MVGP with `k`
//! observations of the Ackermann vehicle (two obstacle barriers and the CLF,
//! relative degree 1) or the pendulum (sector barrier, relative degree 2),
//! and the safety controller around it, as in the paper's Sec. VII.

use crate::barrier::{AckermannClf, CircleHeading, DynBarrier, DynLyapunov, PendulumSector};
use crate::control::{SafetyController, SafetySettings};
use crate::error::Error;
use crate::gp::{InputMap, Mvgp, MvgpHyper, PriorMean, Rbf};
use crate::sim::{sample_uniform, Dataset};
use crate::systems::{Ackermann, DynSystem, Pendulum};
use nalgebra::DMatrix;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::f64::consts::PI;
use std::sync::Arc;

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
pub fn ackermann_data(k: usize, wheelbase: f64, seed: u64) -> Result<Dataset, Error> {
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
/// from a budget (README, "Performance").
pub fn ackermann_heading_sweep(k: usize, wheelbase: f64, seed: u64) -> Result<Dataset, Error> {
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
pub fn pendulum_data(k: usize, seed: u64) -> Result<Dataset, Error> {
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

/// Ackermann workload: prior mean `L = 1`, truth `L = 12`, kernel on θ only,
/// `A = 0.01 I`, `B = I`; two `circle_heading` barriers (Sec. VII-B) and the
/// CLF; `p = 0.99`, bounds `|v| ≤ 2`, `|z| ≤ 2`.
pub fn ackermann_control(k: usize, seed: u64) -> Result<ControlWorkload, Error> {
    let data = ackermann_data(k + 200, 12.0, seed)?;
    let prior: Arc<dyn DynSystem> = Arc::new(Ackermann { wheelbase: 1.0 });
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![1.0], 1.0)?,
        A: DMatrix::identity(3, 3) * 0.01,
        B: DMatrix::identity(3, 3),
        sigma: 0.1,
    };
    let mut model = Mvgp::new(
        3,
        2,
        hyper,
        PriorMean::System(prior),
        InputMap::Select(vec![2]),
    )?;
    let train = data.slice(0..k);
    model.set_data(&train.xs, &train.us, &train.xdot)?;
    let barriers: Vec<Arc<dyn DynBarrier>> = vec![
        Arc::new(CircleHeading::new(
            [-1.1667, -1.5],
            0.7906,
            0.7,
            0.3,
            1,
            vec![5.0],
        )?),
        Arc::new(CircleHeading::new(
            [-1.8333, 0.5],
            0.7906,
            0.7,
            0.3,
            1,
            vec![5.0],
        )?),
    ];
    let clf: Arc<dyn DynLyapunov> = Arc::new(AckermannClf::new(0.9, 1.5, 10.0)?);
    let mut settings = SafetySettings::new(2);
    settings.u_min = Some(vec![-2.0, -2.0]);
    settings.u_max = Some(vec![2.0, 2.0]);
    let controller = SafetyController::new(3, 2, barriers, Some(clf), settings)?;
    Ok(ControlWorkload {
        model,
        controller,
        x: vec![-3.0, -1.0, -PI / 4.0],
        u_ref: vec![0.5, 0.0],
        reference: Some((vec![-2.9, -0.97, PI / 4.0], vec![0.3, 0.1, 0.0])),
        extra: data.slice(k..k + 200),
    })
}

/// Pendulum workload: zero prior mean, the unsafe sector `θ_c = 45°`,
/// `Δ = 22.5°`, relative degree 2 with `k_α = [1, 3]`, `p = 0.99`,
/// `|u| ≤ 20`, at `θ = 75°`, `ω = −0.01` (Sec. VII-A).
pub fn pendulum_control(k: usize, seed: u64) -> Result<ControlWorkload, Error> {
    let data = pendulum_data(k + 200, seed)?;
    let hyper = MvgpHyper {
        kernel: Rbf::new(vec![1.0, 3.0], 1.0)?,
        A: DMatrix::identity(2, 2),
        B: DMatrix::identity(2, 2),
        sigma: 0.1,
    };
    let mut model = Mvgp::new(2, 1, hyper, PriorMean::Zero, InputMap::Identity)?;
    let train = data.slice(0..k);
    model.set_data(&train.xs, &train.us, &train.xdot)?;
    let barriers: Vec<Arc<dyn DynBarrier>> = vec![Arc::new(PendulumSector::new(
        PI / 4.0,
        PI / 8.0,
        2,
        vec![1.0, 3.0],
    )?)];
    let mut settings = SafetySettings::new(1);
    settings.u_min = Some(vec![-20.0]);
    settings.u_max = Some(vec![20.0]);
    let controller = SafetyController::new(2, 1, barriers, None, settings)?;
    Ok(ControlWorkload {
        model,
        controller,
        x: vec![75f64.to_radians(), -0.01],
        u_ref: vec![0.0],
        reference: None,
        extra: data.slice(k..k + 200),
    })
}
