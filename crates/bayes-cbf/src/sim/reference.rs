//! Reference controls `û` and time-varying CLF references `x_d(t)`.

use crate::error::{check_len, check_positive, InputError};
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
    /// Fills `out` for step `k` at time `t` and state `x`; its vectors
    /// have the lengths `m`, `n` and `n` of the system.
    fn at(&mut self, k: usize, t: f64, x: &[f64], rng: &mut ChaCha8Rng, out: &mut ReferenceOut);

    /// Checks that the reference is made for a system with `n` states and
    /// `m` controls (a closed loop calls it before its first step); the
    /// default accepts any.
    fn check_dims(&self, n: usize, m: usize) -> Result<(), InputError> {
        let _ = (n, m);
        Ok(())
    }
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

    fn check_dims(&self, _n: usize, m: usize) -> Result<(), InputError> {
        check_len("reference control", m, self.0.len())
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
        check_positive("epsilon_greedy.decay", decay)?;
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

    fn check_dims(&self, _n: usize, m: usize) -> Result<(), InputError> {
        check_len("epsilon_greedy.lo", m, self.lo.len())?;
        check_len("epsilon_greedy.hi", m, self.hi.len())
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
        check_positive("planner.duration", duration)?;
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

    fn check_dims(&self, n: usize, _m: usize) -> Result<(), InputError> {
        check_len("planner.start", n, self.start.len())?;
        check_len("planner.goal", n, self.goal.len())
    }
}

/// Linear state feedback towards a target: `û = u₀ + K (x* − x)`, with `K`
/// of size `m × n` (row-major) and the components listed in `angles`
/// differenced on the circle (wrapped to `[−π, π)`). The nominal
/// controller of a robot without a CLF (a PD law on positions and
/// velocities); the safety filter keeps it safe. No CLF reference.
#[derive(Debug, Clone, PartialEq)]
pub struct LinearFeedback {
    u0: Vec<f64>,
    gain: Vec<f64>,
    target: Vec<f64>,
    angles: Vec<usize>,
}

impl LinearFeedback {
    /// Validated constructor: `u0` of length `m`, `gain` of `m` rows of
    /// length `n = target.len()`, all finite; `angles` below `n`.
    pub fn new(
        u0: Vec<f64>,
        gain: &[Vec<f64>],
        target: Vec<f64>,
        angles: Vec<usize>,
    ) -> Result<Self, InputError> {
        let (m, n) = (u0.len(), target.len());
        crate::error::check_finite("feedback.u0", &u0)?;
        crate::error::check_finite("feedback.target", &target)?;
        if gain.len() != m {
            return Err(InputError::shape(
                "feedback.gain",
                format!("{m} rows (one per control)"),
                format!("{} rows", gain.len()),
            ));
        }
        let mut flat = Vec::with_capacity(m * n);
        for (j, row) in gain.iter().enumerate() {
            let field = format!("feedback.gain[{j}]");
            if row.len() != n {
                return Err(InputError::shape(
                    &field,
                    format!("{n} entries (one per state)"),
                    row.len(),
                ));
            }
            crate::error::check_finite(&field, row)?;
            flat.extend_from_slice(row);
        }
        if let Some(&i) = angles.iter().find(|&&i| i >= n) {
            return Err(InputError::invalid_shown(
                "feedback.angles",
                i,
                "must index a state",
            ));
        }
        Ok(Self {
            u0,
            gain: flat,
            target,
            angles,
        })
    }
}

impl Reference for LinearFeedback {
    fn at(&mut self, _k: usize, _t: f64, x: &[f64], _rng: &mut ChaCha8Rng, out: &mut ReferenceOut) {
        let n = self.target.len();
        for (j, u) in out.u_ref.iter_mut().enumerate() {
            let mut v = self.u0[j];
            for i in 0..n {
                let mut e = self.target[i] - x[i];
                if self.angles.contains(&i) {
                    e = crate::systems::wrap_angle(e);
                }
                v += self.gain[j * n + i] * e;
            }
            *u = v;
        }
        out.xd.copy_from_slice(x);
        out.xd_dot.fill(0.0);
    }

    fn check_dims(&self, n: usize, m: usize) -> Result<(), InputError> {
        check_len("feedback.u0", m, self.u0.len())?;
        check_len("feedback.target", n, self.target.len())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn linear_feedback_is_u0_plus_k_times_the_error() {
        let mut r = LinearFeedback::new(
            vec![1.0, -2.0],
            &[vec![2.0, 0.5, 0.0], vec![0.0, 1.0, 3.0]],
            vec![1.0, 0.0, 3.0],
            vec![2],
        )
        .unwrap();
        let mut out = ReferenceOut {
            u_ref: vec![0.0; 2],
            xd: vec![0.0; 3],
            xd_dot: vec![9.0; 3],
        };
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let x = [0.5, 0.2, -3.0];
        r.at(0, 0.0, &x, &mut rng, &mut out);
        // the angle error 3 − (−3) = 6 wraps to 6 − 2π
        let e2 = 6.0 - 2.0 * std::f64::consts::PI;
        assert!((out.u_ref[0] - (1.0 + 2.0 * 0.5 + 0.5 * -0.2)).abs() < 1e-15);
        assert!((out.u_ref[1] - (-2.0 - 0.2 + 3.0 * e2)).abs() < 1e-12);
        assert_eq!(
            (out.xd.as_slice(), out.xd_dot.as_slice()),
            (&x[..], &[0.0; 3][..])
        );
        for (gain, target, want) in [
            (vec![vec![1.0]], vec![0.0, 0.0], "feedback.gain[0]"),
            (
                vec![vec![1.0, f64::NAN]],
                vec![0.0, 0.0],
                "feedback.gain[0][1]",
            ),
            (vec![], vec![0.0, 0.0], "feedback.gain"),
        ] {
            let e = LinearFeedback::new(vec![0.0], &gain, target, vec![]).unwrap_err();
            assert!(e.to_string().contains(want), "{e}");
        }
    }
}
