//! Reference controls `û` and time-varying CLF references `x_d(t)`.

use crate::error::InputError;
use rand::RngExt;
use rand_chacha::ChaCha8Rng;

/// What the controller is asked to track at one step.
#[derive(Debug, Clone, PartialEq)]
pub struct ReferenceOut {
    /// Reference control `û`.
    pub u_ref: Vec<f64>,
    /// Desired state `x_d(t)` (for a CLF).
    pub xd: Vec<f64>,
    /// Its time derivative `ẋ_d(t)`.
    pub xd_dot: Vec<f64>,
}

/// A source of references, called once per control step.
pub trait Reference: Send {
    /// Fills `out` for step `k` at time `t` and state `x`.
    fn at(&mut self, k: usize, t: f64, x: &[f64], rng: &mut ChaCha8Rng, out: &mut ReferenceOut);
}

/// A constant reference control and no CLF reference.
#[derive(Debug, Clone, PartialEq)]
pub struct ConstantReference(pub Vec<f64>);

impl Reference for ConstantReference {
    fn at(&mut self, _k: usize, _t: f64, x: &[f64], _rng: &mut ChaCha8Rng, out: &mut ReferenceOut) {
        out.u_ref.copy_from_slice(&self.0);
        out.xd.copy_from_slice(x);
        out.xd_dot.fill(0.0);
    }
}

/// The ε-greedy reference of the pendulum experiment (paper, Sec. VII-A):
/// `û_k ~ (1 − ε_k) δ_0 + ε_k U[lo, hi]` with `ε_k = 10^(−k/decay)`.
#[derive(Debug, Clone, PartialEq)]
pub struct EpsilonGreedy {
    /// Lower end of the uniform exploration.
    pub lo: Vec<f64>,
    /// Upper end.
    pub hi: Vec<f64>,
    /// Steps per decade of ε (50 in the paper).
    pub decay: f64,
}

impl EpsilonGreedy {
    /// Validated constructor.
    pub fn new(lo: Vec<f64>, hi: Vec<f64>, decay: f64) -> Result<Self, InputError> {
        if lo.len() != hi.len() {
            return Err(InputError::shape("epsilon_greedy.hi", lo.len(), hi.len()));
        }
        for j in 0..lo.len() {
            if !(lo[j].is_finite() && hi[j].is_finite() && lo[j] <= hi[j]) {
                return Err(InputError::invalid(
                    &format!("epsilon_greedy.lo[{j}]"),
                    lo[j],
                    "must be finite and ≤ hi",
                ));
            }
        }
        if !(decay.is_finite() && decay > 0.0) {
            return Err(InputError::invalid(
                "epsilon_greedy.decay",
                decay,
                "must be finite and > 0",
            ));
        }
        Ok(Self { lo, hi, decay })
    }
}

impl Reference for EpsilonGreedy {
    fn at(&mut self, k: usize, _t: f64, x: &[f64], rng: &mut ChaCha8Rng, out: &mut ReferenceOut) {
        let eps = 10f64.powf(-(k as f64) / self.decay);
        let explore = rng.random_range(0.0..1.0) < eps;
        for j in 0..out.u_ref.len() {
            // draw always, so the random stream does not depend on the branch
            let v = if self.hi[j] > self.lo[j] {
                rng.random_range(self.lo[j]..self.hi[j])
            } else {
                self.lo[j]
            };
            out.u_ref[j] = if explore { v } else { 0.0 };
        }
        out.xd.copy_from_slice(x);
        out.xd_dot.fill(0.0);
    }
}

/// The time-parameterised straight line from `start` to `goal` of the
/// vehicle experiments (paper, Sec. VII-B): `x_d(t) = start + s(t)(goal −
/// start)`, `s(t) = min(t/T, 1)`, `ẋ_d = (goal − start)/T` while `t < T`.
/// The reference control is zero: the CLF does the tracking.
#[derive(Debug, Clone, PartialEq)]
pub struct StraightLinePlanner {
    /// Start state.
    pub start: Vec<f64>,
    /// Goal state.
    pub goal: Vec<f64>,
    /// Duration `T` (s).
    pub duration: f64,
}

impl StraightLinePlanner {
    /// Validated constructor.
    pub fn new(start: Vec<f64>, goal: Vec<f64>, duration: f64) -> Result<Self, InputError> {
        if start.len() != goal.len() {
            return Err(InputError::shape("goal", start.len(), goal.len()));
        }
        crate::error::check_finite("start", &start)?;
        crate::error::check_finite("goal", &goal)?;
        if !(duration.is_finite() && duration > 0.0) {
            return Err(InputError::invalid(
                "planner.duration",
                duration,
                "must be finite and > 0",
            ));
        }
        Ok(Self {
            start,
            goal,
            duration,
        })
    }
}

impl Reference for StraightLinePlanner {
    fn at(&mut self, _k: usize, t: f64, _x: &[f64], _rng: &mut ChaCha8Rng, out: &mut ReferenceOut) {
        let s = (t / self.duration).min(1.0);
        let moving = t < self.duration;
        for i in 0..self.start.len() {
            let d = self.goal[i] - self.start[i];
            out.xd[i] = self.start[i] + s * d;
            out.xd_dot[i] = if moving { d / self.duration } else { 0.0 };
        }
        out.u_ref.fill(0.0);
    }
}
