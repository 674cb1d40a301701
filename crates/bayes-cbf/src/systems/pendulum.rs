use super::ControlAffine;
use num_dual::DualNum;

/// Torque-controlled pendulum (paper, Sec. VII-A, Eq. 31).
///
/// State `x = [θ, ω]`, control `u` (torque):
/// `θ̇ = ω`, `ω̇ = −(g/l) sin θ + u / (m l)`, so
/// `f(x) = [ω, −(g/l) sin θ]`, `g(x) = [0, 1/(m l)]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pendulum {
    /// Mass `m` (kg).
    pub mass: f64,
    /// Length `l` (m).
    pub length: f64,
    /// Gravity `g` (m/s²).
    pub gravity: f64,
}

impl Default for Pendulum {
    /// The paper's pendulum: `m = l = 1`, `g = 10`.
    fn default() -> Self {
        Self {
            mass: 1.0,
            length: 1.0,
            gravity: 10.0,
        }
    }
}

impl ControlAffine for Pendulum {
    fn state_dim(&self) -> usize {
        2
    }
    fn control_dim(&self) -> usize {
        1
    }
    fn dynamics<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D], out: &mut [D]) {
        let theta = x[0];
        let omega = x[1];
        out[0] = omega;
        out[1] = theta.sin() * (-self.gravity / self.length);
        out[2] = D::from(0.0);
        out[3] = D::from(1.0 / (self.mass * self.length));
    }
    fn angle_indices(&self) -> &[usize] {
        &[0]
    }
}
