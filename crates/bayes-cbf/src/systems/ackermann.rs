use super::ControlAffine;
use num_dual::DualNum;

/// Kinematic Ackermann-drive vehicle (paper, Sec. VII-B, Eq. 32).
///
/// State `x = [x, y, θ]`, control `u = [v, z]` with `z = v tan φ` (φ the
/// steering angle): `ẋ = v cos θ`, `ẏ = v sin θ`, `θ̇ = z / L`, so `f(x) = 0`
/// and `g(x) = [[cos θ, 0], [sin θ, 0], [0, 1/L]]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ackermann {
    /// Wheelbase `L` (m).
    pub wheelbase: f64,
}

impl Default for Ackermann {
    fn default() -> Self {
        Self { wheelbase: 1.0 }
    }
}

impl ControlAffine for Ackermann {
    fn state_dim(&self) -> usize {
        3
    }
    fn control_dim(&self) -> usize {
        2
    }
    fn dynamics<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D], out: &mut [D]) {
        let theta = x[2];
        let zero = D::from(0.0);
        // column 0: f
        out[0] = zero;
        out[1] = zero;
        out[2] = zero;
        // column 1: g_v
        out[3] = theta.cos();
        out[4] = theta.sin();
        out[5] = zero;
        // column 2: g_z
        out[6] = zero;
        out[7] = zero;
        out[8] = D::from(1.0 / self.wheelbase);
    }
    fn angle_indices(&self) -> &[usize] {
        &[2]
    }
}
