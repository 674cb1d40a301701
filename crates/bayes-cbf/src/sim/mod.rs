//! Simulation of control-affine systems (paper, Sec. III) and derivative
//! estimation from sampled trajectories (paper, footnote 1).

mod background_refit;
mod closed_loop;
mod dataset;
mod derivative;
mod reference;

pub use closed_loop::{
    ClosedLoop, DataPolicy, LoopResult, LoopSettings, Monitor, Observer, StepRecord, StepStatus,
};
pub use dataset::{sample_uniform, simulate_trajectory, Dataset};
pub use derivative::finite_difference_xdot;
pub use reference::{
    ConstantReference, EpsilonGreedy, LinearFeedback, Reference, ReferenceOut, StraightLinePlanner,
};

use crate::error::{check_finite_scalar, check_len, check_nonnegative, check_positive, InputError};
use crate::systems::{wrap_angle, DynSystem};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};

/// Most RK4 sub-steps one control hold may take ([`LoopSettings::validate`]
/// refuses a `dt`, or a longest self-triggered hold, that needs more).
pub const MAX_SUBSTEPS: usize = 1_000_000;

/// Most triggers a self-triggered run may need: `steps · dt / τ_min`
/// (each hold is at least `τ_min` long).
pub const MAX_TRIGGERS: usize = 10_000_000;

/// Settings of the zero-order-hold integrator.
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct SimSettings {
    /// Internal RK4 step (s). The hold interval is split into
    /// `ceil(interval / internal_step)` equal sub-steps.
    pub internal_step: f64,
    /// Standard deviation of additive process noise on `ẋ`, per unit √time
    /// (Euler–Maruyama increment `σ_w √h ξ` added after each sub-step).
    /// Zero gives deterministic integration.
    pub process_noise: f64,
    /// Wrap angle components (see [`crate::systems::ControlAffine::angle_indices`]).
    pub wrap_angles: bool,
}

impl Default for SimSettings {
    fn default() -> Self {
        Self {
            internal_step: 1e-3,
            process_noise: 0.0,
            wrap_angles: true,
        }
    }
}

impl SimSettings {
    /// Validated constructor.
    pub fn new(internal_step: f64, process_noise: f64) -> Result<Self, InputError> {
        check_positive("internal_step", internal_step)?;
        check_nonnegative("process_noise", process_noise)?;
        Ok(Self {
            internal_step,
            process_noise,
            wrap_angles: true,
        })
    }
}

/// Reusable buffers for [`Simulator`]: no allocation per step.
pub struct Simulator<'a> {
    system: &'a dyn DynSystem,
    settings: SimSettings,
    fbuf: Vec<f64>,
    k: [Vec<f64>; 4],
    tmp: Vec<f64>,
}

impl<'a> Simulator<'a> {
    /// A simulator for `system`.
    pub fn new(system: &'a dyn DynSystem, settings: SimSettings) -> Self {
        let n = system.state_dim();
        let m = system.control_dim();
        Self {
            system,
            settings,
            fbuf: vec![0.0; n * (1 + m)],
            k: [vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n]],
            tmp: vec![0.0; n],
        }
    }

    /// The settings in use.
    pub fn settings(&self) -> &SimSettings {
        &self.settings
    }

    /// Holds `u` constant over `[t, t + interval]` and integrates `x` in place
    /// with RK4 sub-steps. `observer(t_rel, x)` is called after every sub-step
    /// (for checking a barrier on the fine grid); pass `|_, _| {}` if unused.
    /// A state or control of the wrong length, or an interval that is not
    /// finite, is an error (`x` unchanged); an interval ≤ 0 does nothing.
    pub fn step_with<R: Rng + ?Sized>(
        &mut self,
        x: &mut [f64],
        u: &[f64],
        interval: f64,
        rng: &mut R,
        mut observer: impl FnMut(f64, &[f64]),
    ) -> Result<(), InputError> {
        let n = self.system.state_dim();
        check_len("x", n, x.len())?;
        check_len("u", self.system.control_dim(), u.len())?;
        check_finite_scalar("interval", interval)?;
        if interval <= 0.0 {
            return Ok(());
        }
        let steps = (interval / self.settings.internal_step).ceil().max(1.0) as usize;
        let h = interval / steps as f64;
        for s in 0..steps {
            self.rk4(x, u, h);
            if self.settings.process_noise > 0.0 {
                let scale = self.settings.process_noise * h.sqrt();
                for xi in x.iter_mut() {
                    let xi_noise: f64 = StandardNormal.sample(rng);
                    *xi += scale * xi_noise;
                }
            }
            if self.settings.wrap_angles {
                for &a in self.system.angle_indices() {
                    x[a] = wrap_angle(x[a]);
                }
            }
            observer((s + 1) as f64 * h, x);
        }
        Ok(())
    }

    /// [`step_with`](Self::step_with) without an observer.
    pub fn step<R: Rng + ?Sized>(
        &mut self,
        x: &mut [f64],
        u: &[f64],
        interval: f64,
        rng: &mut R,
    ) -> Result<(), InputError> {
        self.step_with(x, u, interval, rng, |_, _| {})
    }

    fn rk4(&mut self, x: &mut [f64], u: &[f64], h: f64) {
        let n = x.len();
        let sys = self.system;
        let [k1, k2, k3, k4] = &mut self.k;
        sys.xdot(x, u, &mut self.fbuf, k1);
        for i in 0..n {
            self.tmp[i] = x[i] + 0.5 * h * k1[i];
        }
        sys.xdot(&self.tmp, u, &mut self.fbuf, k2);
        for i in 0..n {
            self.tmp[i] = x[i] + 0.5 * h * k2[i];
        }
        sys.xdot(&self.tmp, u, &mut self.fbuf, k3);
        for i in 0..n {
            self.tmp[i] = x[i] + h * k3[i];
        }
        sys.xdot(&self.tmp, u, &mut self.fbuf, k4);
        for i in 0..n {
            x[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::systems::{Ackermann, Pendulum};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn ackermann_straight_and_circle() {
        let sys = Ackermann { wheelbase: 2.0 };
        let mut sim = Simulator::new(&sys, SimSettings::default());
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mut x = [0.0, 0.0, 0.0];
        sim.step(&mut x, &[1.0, 0.0], 1.0, &mut rng).unwrap();
        assert!((x[0] - 1.0).abs() < 1e-12 && x[1].abs() < 1e-12);
        // constant turn rate z/L = 0.5 rad/s with v = 1: circle of radius 2
        let mut x = [0.0, 0.0, 0.0];
        sim.step(&mut x, &[1.0, 1.0], 1.0, &mut rng).unwrap();
        let (ex, ey) = (2.0 * (0.5f64).sin(), 2.0 * (1.0 - (0.5f64).cos()));
        assert!(
            (x[0] - ex).abs() < 1e-10 && (x[1] - ey).abs() < 1e-10,
            "{x:?}"
        );
        assert!((x[2] - 0.5).abs() < 1e-12);
    }

    #[test]
    fn pendulum_energy_conserved_without_input() {
        let sys = Pendulum::default();
        let mut sim = Simulator::new(&sys, SimSettings::default());
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let energy = |x: &[f64]| 0.5 * x[1] * x[1] - 10.0 * x[0].cos();
        let mut x = [1.0, 0.0];
        let e0 = energy(&x);
        for _ in 0..100 {
            sim.step(&mut x, &[0.0], 0.05, &mut rng).unwrap();
        }
        assert!((energy(&x) - e0).abs() < 1e-8);
    }

    #[test]
    fn angles_wrap_and_wrong_lengths_are_errors() {
        let sys = Pendulum::default();
        let mut sim = Simulator::new(&sys, SimSettings::default());
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mut x = [3.1, 5.0];
        sim.step(&mut x, &[0.0], 0.1, &mut rng).unwrap();
        assert!(x[0] < 0.0 && x[0] >= -std::f64::consts::PI);
        // a state or control of the wrong length and a non-finite interval
        // are errors naming them, and leave the state as it was
        let mut x = [0.1, 0.0];
        let e = sim.step(&mut x, &[0.0, 1.0], 0.1, &mut rng).unwrap_err();
        assert!(e.to_string().contains("shape of u:"), "{e}");
        let e = sim.step(&mut [0.1], &[0.0], 0.1, &mut rng).unwrap_err();
        assert!(e.to_string().contains("shape of x:"), "{e}");
        let e = sim.step(&mut x, &[0.0], f64::NAN, &mut rng).unwrap_err();
        assert!(e.to_string().contains("interval = NaN"), "{e}");
        assert_eq!(x, [0.1, 0.0]);
    }
}
