//! Built-in barrier functions.

use super::{validate_gains, Barrier};
use crate::error::{check_finite, InputError};
use num_dual::DualNum;

/// Checks an obstacle radius: finite and positive.
fn check_radius(radius: f64) -> Result<(), InputError> {
    if !(radius.is_finite() && radius > 0.0) {
        return Err(InputError::invalid(
            "radius",
            radius,
            "must be finite and > 0",
        ));
    }
    Ok(())
}

/// Unsafe angular sector of a pendulum (paper, Sec. VII-A):
/// `h(x) = cos Δ − cos(θ − θ_c)` with `θ = x[0]`; unsafe when `|θ − θ_c| < Δ`.
#[derive(Debug, Clone, PartialEq)]
pub struct PendulumSector {
    /// Sector centre `θ_c` (rad).
    pub theta_c: f64,
    /// Half-width `Δ` (rad).
    pub delta: f64,
    relative_degree: usize,
    gains: Vec<f64>,
}

impl PendulumSector {
    /// Validated constructor; `gains` = `[α]` (r = 1) or `k_α` (r = 2).
    pub fn new(
        theta_c: f64,
        delta: f64,
        relative_degree: usize,
        gains: Vec<f64>,
    ) -> Result<Self, InputError> {
        check_finite("theta_c", &[theta_c])?;
        if !(delta.is_finite() && delta > 0.0 && delta < std::f64::consts::PI) {
            return Err(InputError::invalid("delta", delta, "must be in (0, π)"));
        }
        validate_gains(relative_degree, &gains)?;
        Ok(Self {
            theta_c,
            delta,
            relative_degree,
            gains,
        })
    }
}

impl Barrier for PendulumSector {
    fn state_dim(&self) -> usize {
        2
    }
    fn h<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D]) -> D {
        D::from(self.delta.cos()) - (x[0] - self.theta_c).cos()
    }
    order_and_gains!();
    fn name(&self) -> &str {
        "pendulum_sector"
    }
}

/// Obstacle barrier of the Ackermann vehicle with a heading term
/// (paper, Sec. VII-B):
/// `h(x) = q1 (‖x[0:2] − o‖² − r²) + q2 cos(θ − atan2(y − o_y, x − o_x))`.
#[derive(Debug, Clone, PartialEq)]
pub struct CircleHeading {
    /// Obstacle centre `o`.
    pub center: [f64; 2],
    /// Obstacle radius `r`.
    pub radius: f64,
    /// Weight of the distance term.
    pub q1: f64,
    /// Weight of the heading term.
    pub q2: f64,
    relative_degree: usize,
    gains: Vec<f64>,
}

impl CircleHeading {
    /// Validated constructor.
    pub fn new(
        center: [f64; 2],
        radius: f64,
        q1: f64,
        q2: f64,
        relative_degree: usize,
        gains: Vec<f64>,
    ) -> Result<Self, InputError> {
        check_finite("center", &center)?;
        check_radius(radius)?;
        check_finite("q1", &[q1])?;
        check_finite("q2", &[q2])?;
        validate_gains(relative_degree, &gains)?;
        Ok(Self {
            center,
            radius,
            q1,
            q2,
            relative_degree,
            gains,
        })
    }

    /// Signed distance of the point `(x, y)` to the obstacle disc
    /// (negative inside).
    pub fn signed_distance(&self, x: &[f64]) -> f64 {
        ((x[0] - self.center[0]).powi(2) + (x[1] - self.center[1]).powi(2)).sqrt() - self.radius
    }
}

impl Barrier for CircleHeading {
    fn state_dim(&self) -> usize {
        3
    }
    fn h<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D]) -> D {
        let dx = x[0] - self.center[0];
        let dy = x[1] - self.center[1];
        let dist = (dx * dx + dy * dy - self.radius * self.radius) * self.q1;
        let phi = super::atan2(dy, dx);
        dist + (x[2] - phi).cos() * self.q2
    }
    order_and_gains!();
    fn name(&self) -> &str {
        "circle_heading"
    }
}

/// Keep-out disc on two chosen coordinates: `h(x) = ‖x[I] − o‖² − r²`.
#[derive(Debug, Clone, PartialEq)]
pub struct Disc {
    /// State dimension.
    pub n: usize,
    /// The two coordinates of the plane.
    pub indices: [usize; 2],
    /// Centre.
    pub center: [f64; 2],
    /// Radius.
    pub radius: f64,
    relative_degree: usize,
    gains: Vec<f64>,
}

impl Disc {
    /// Validated constructor.
    pub fn new(
        n: usize,
        indices: [usize; 2],
        center: [f64; 2],
        radius: f64,
        relative_degree: usize,
        gains: Vec<f64>,
    ) -> Result<Self, InputError> {
        for (j, &i) in indices.iter().enumerate() {
            if i >= n {
                return Err(InputError::invalid(
                    &format!("indices[{j}]"),
                    i as f64,
                    &format!("must be < state dimension {n}"),
                ));
            }
        }
        check_finite("center", &center)?;
        check_radius(radius)?;
        validate_gains(relative_degree, &gains)?;
        Ok(Self {
            n,
            indices,
            center,
            radius,
            relative_degree,
            gains,
        })
    }
}

impl Barrier for Disc {
    fn state_dim(&self) -> usize {
        self.n
    }
    fn h<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D]) -> D {
        let dx = x[self.indices[0]] - self.center[0];
        let dy = x[self.indices[1]] - self.center[1];
        dx * dx + dy * dy - self.radius * self.radius
    }
    order_and_gains!();
    fn name(&self) -> &str {
        "disc"
    }
}

/// Half-space `h(x) = aᵀx − b ≥ 0`.
#[derive(Debug, Clone, PartialEq)]
pub struct HalfSpace {
    /// Normal `a`.
    pub normal: Vec<f64>,
    /// Offset `b`.
    pub offset: f64,
    relative_degree: usize,
    gains: Vec<f64>,
}

impl HalfSpace {
    /// Validated constructor.
    pub fn new(
        normal: Vec<f64>,
        offset: f64,
        relative_degree: usize,
        gains: Vec<f64>,
    ) -> Result<Self, InputError> {
        if normal.is_empty() {
            return Err(InputError::shape("normal", "≥ 1 entry", 0));
        }
        check_finite("normal", &normal)?;
        if normal.iter().all(|v| *v == 0.0) {
            return Err(InputError::invalid("normal", 0.0, "must not be zero"));
        }
        check_finite("offset", &[offset])?;
        validate_gains(relative_degree, &gains)?;
        Ok(Self {
            normal,
            offset,
            relative_degree,
            gains,
        })
    }
}

impl Barrier for HalfSpace {
    fn state_dim(&self) -> usize {
        self.normal.len()
    }
    fn h<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D]) -> D {
        let mut s = D::from(-self.offset);
        for (xi, ai) in x.iter().zip(&self.normal) {
            s += *xi * *ai;
        }
        s
    }
    order_and_gains!();
    fn name(&self) -> &str {
        "half_space"
    }
}
