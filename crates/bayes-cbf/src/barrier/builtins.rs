//! Built-in barrier functions.

use super::{validate_gains, Barrier};
use crate::error::{check_finite, check_finite_scalar, check_index, check_positive, InputError};
use num_dual::DualNum;

/// Checks an obstacle radius: finite and positive.
fn check_radius(radius: f64) -> Result<(), InputError> {
    check_positive("radius", radius)?;
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
        check_finite_scalar("theta_c", theta_c)?;
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

/// Which edge of a pendulum's unsafe sector a [`PendulumSectorEdge`] keeps.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SectorEdge {
    /// The edge `θ_c + Δ`, reached by turning clockwise (decreasing `θ`).
    Upper,
    /// The edge `θ_c − Δ`, reached by turning counter-clockwise.
    Lower,
}

/// One edge of a pendulum's unsafe sector as a linear barrier in the angle
/// measured from the sector's centre:
/// `φ(θ) = (θ − θ_c) mod 2π ∈ [0, 2π)`, `h = φ − Δ` for the upper edge and
/// `h = 2π − Δ − φ` for the lower edge. The two together keep `θ` in the
/// arc the sector leaves free; `φ` jumps only at `θ = θ_c`, inside the
/// sector, so `h` is smooth (and `∇²h = 0`) on the whole safe arc, whether
/// or not the simulation wraps `θ`.
///
/// Unlike [`PendulumSector`], whose `∂h/∂θ = sin(θ − θ_c)` vanishes at the
/// far side `θ_c + π` (there `ḧ = cos(θ − θ_c) ω² = −ω²` whatever the
/// torque, so the relative-degree-2 condition `ḧ + k₁ḣ + k₀h ≥ 0` has no
/// solution once `ω² > k₀ (1 + cos Δ)`), the gradient here is constant:
/// `ḧ = ±ω̇`, and the relative-degree-2 safe set
/// `{h ≥ 0, ḣ + λ h ≥ 0}` (`λ` the slower root of `s² + k₁ s + k₀`) is
/// control-invariant when the torque bound affords `|ω̇| ≥ λ² (2π − 2Δ)`.
#[derive(Debug, Clone, PartialEq)]
pub struct PendulumSectorEdge {
    /// Sector centre `θ_c` (rad).
    pub theta_c: f64,
    /// Half-width `Δ` (rad).
    pub delta: f64,
    /// The edge this barrier keeps.
    pub edge: SectorEdge,
    relative_degree: usize,
    gains: Vec<f64>,
}

impl PendulumSectorEdge {
    /// Validated constructor; `gains` = `[α]` (r = 1) or `k_α` (r = 2).
    pub fn new(
        theta_c: f64,
        delta: f64,
        edge: SectorEdge,
        relative_degree: usize,
        gains: Vec<f64>,
    ) -> Result<Self, InputError> {
        // the same checks as the sector's
        let s = PendulumSector::new(theta_c, delta, relative_degree, gains)?;
        Ok(Self {
            theta_c: s.theta_c,
            delta: s.delta,
            edge,
            relative_degree: s.relative_degree,
            gains: s.gains,
        })
    }
}

impl Barrier for PendulumSectorEdge {
    fn state_dim(&self) -> usize {
        2
    }
    fn h<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D]) -> D {
        let tau = std::f64::consts::TAU;
        let d = x[0] - self.theta_c;
        // the whole turns are a constant: φ has the derivatives of θ
        let phi = d - (d.re() / tau).floor() * tau;
        match self.edge {
            SectorEdge::Upper => phi - self.delta,
            SectorEdge::Lower => -phi + (tau - self.delta),
        }
    }
    order_and_gains!();
    fn name(&self) -> &str {
        "pendulum_sector_edge"
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
        super::check_state_dim("state_dim", n)?;
        for (j, &i) in indices.iter().enumerate() {
            check_index(&format!("indices[{j}]"), i, n)?;
        }
        if indices[0] == indices[1] {
            return Err(InputError::invalid_shown(
                "indices[1]",
                indices[1],
                "must differ from indices[0] (the disc lies in the plane of two state coordinates)",
            ));
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
        super::check_state_dim("normal", normal.len())?;
        check_finite("normal", &normal)?;
        if normal.iter().all(|v| *v == 0.0) {
            return Err(InputError::invalid("normal", 0.0, "must not be zero"));
        }
        check_finite_scalar("offset", offset)?;
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

#[cfg(test)]
mod tests {
    use super::super::DynBarrier;
    use super::*;
    use num_dual::HyperDual64;
    use std::f64::consts::{PI, TAU};

    #[test]
    fn disc_names_an_index_beyond_the_state() {
        let e = Disc::new(3, [0, 3], [0.0, 0.0], 1.0, 1, vec![1.0])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("indices[1]") && e.contains("state dimension 3"),
            "{e}"
        );
        assert!(Disc::new(3, [0, 2], [0.0, 0.0], 1.0, 1, vec![1.0]).is_ok());
        let e = Disc::new(3, [1, 1], [0.0, 0.0], 1.0, 1, vec![1.0])
            .unwrap_err()
            .to_string();
        assert!(e.contains("indices[1]") && e.contains("must differ"), "{e}");
    }

    #[test]
    fn sector_edges_are_linear_in_the_angle_from_the_centre_on_the_free_arc() {
        let (tc, d) = (PI / 4.0, PI / 8.0);
        let up = PendulumSectorEdge::new(tc, d, SectorEdge::Upper, 2, vec![1.0, 3.0]).unwrap();
        let lo = PendulumSectorEdge::new(tc, d, SectorEdge::Lower, 2, vec![1.0, 3.0]).unwrap();
        let (mut g, mut hs, mut hd) = (vec![0.0; 2], vec![0.0; 4], vec![HyperDual64::from(0.0); 2]);
        for i in 0..=200 {
            // the free arc, in unwrapped and in wrapped coordinates
            let s = d + (TAU - 2.0 * d) * i as f64 / 200.0;
            for turns in [-2.0, -1.0, 0.0, 1.0] {
                let x = [tc + s + turns * TAU, 0.3];
                let hu = up.hessian(&x, &mut g, &mut hs, &mut hd);
                assert!((hu - (s - d)).abs() < 1e-12, "{x:?}: {hu}");
                assert_eq!((g[0], g[1]), (1.0, 0.0));
                assert!(hs.iter().all(|v| *v == 0.0));
                let hl = lo.hessian(&x, &mut g, &mut hs, &mut hd);
                assert!((hl - (TAU - d - s)).abs() < 1e-12, "{x:?}: {hl}");
                assert_eq!((g[0], g[1]), (-1.0, 0.0));
            }
        }
        // inside the sector one edge is negative: the centre itself, and
        // points either side of it
        for s in [-0.3, 0.0, 0.3] {
            let x = [tc + s, 0.0];
            assert!(up.value(&x).min(lo.value(&x)) < 0.0, "{s}");
        }
        assert!(PendulumSectorEdge::new(tc, 0.0, SectorEdge::Upper, 1, vec![1.0]).is_err());
        assert!(PendulumSectorEdge::new(tc, d, SectorEdge::Upper, 2, vec![1.0]).is_err());
    }
}
