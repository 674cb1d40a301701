//! Training data for learning `F(x)`: samples of `(x, u, ẋ)`.

use super::{SimSettings, Simulator};
use crate::error::{check_nonnegative, check_positive, InputError};
use crate::systems::DynSystem;
use rand::{Rng, RngExt};
use rand_distr::{Distribution, StandardNormal};

/// Observations `(x_j, u_j, ẋ_j)`, each row-major (`k × n`, `k × m`, `k × n`).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Dataset {
    /// State dimension `n`.
    pub n: usize,
    /// Control dimension `m`.
    pub m: usize,
    /// States, `k × n`.
    pub xs: Vec<f64>,
    /// Controls, `k × m`.
    pub us: Vec<f64>,
    /// State derivatives, `k × n`.
    pub xdot: Vec<f64>,
}

impl Dataset {
    /// Number of observations.
    pub fn len(&self) -> usize {
        self.xs.len().checked_div(self.n).unwrap_or(0)
    }
    /// No observations.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Rows `range` as a new dataset.
    pub fn slice(&self, range: std::ops::Range<usize>) -> Dataset {
        let (n, m) = (self.n, self.m);
        Dataset {
            n,
            m,
            xs: self.xs[range.start * n..range.end * n].to_vec(),
            us: self.us[range.start * m..range.end * m].to_vec(),
            xdot: self.xdot[range.start * n..range.end * n].to_vec(),
        }
    }
}

/// Samples `k` states uniformly in the box `[x_lo, x_hi]` and controls
/// uniformly in `[u_lo, u_hi]`, with `ẋ = F(x)u̲ + ε`, `ε ~ N(0, noise² I)`.
#[allow(clippy::too_many_arguments)]
pub fn sample_uniform<R: Rng + ?Sized>(
    system: &dyn DynSystem,
    x_lo: &[f64],
    x_hi: &[f64],
    u_lo: &[f64],
    u_hi: &[f64],
    k: usize,
    noise: f64,
    rng: &mut R,
) -> Result<Dataset, InputError> {
    let (n, m) = (system.state_dim(), system.control_dim());
    for (name, v, d) in [
        ("x_lo", x_lo, n),
        ("x_hi", x_hi, n),
        ("u_lo", u_lo, m),
        ("u_hi", u_hi, m),
    ] {
        if v.len() != d {
            return Err(InputError::shape(name, d, v.len()));
        }
        crate::error::check_finite(name, v)?;
    }
    for (name, lo, hi, reason) in [
        ("x_lo", x_lo, x_hi, "must be ≤ x_hi"),
        ("u_lo", u_lo, u_hi, "must be ≤ u_hi"),
    ] {
        if let Some(i) = (0..lo.len()).find(|&i| lo[i] > hi[i]) {
            return Err(InputError::invalid(&format!("{name}[{i}]"), lo[i], reason));
        }
    }
    check_nonnegative("noise", noise)?;
    let mut ds = Dataset {
        n,
        m,
        ..Default::default()
    };
    let mut fbuf = vec![0.0; n * (1 + m)];
    let mut x = vec![0.0; n];
    let mut u = vec![0.0; m];
    let mut xd = vec![0.0; n];
    let uni = |rng: &mut R, lo: f64, hi: f64| {
        if hi > lo {
            rng.random_range(lo..hi)
        } else {
            lo
        }
    };
    for _ in 0..k {
        for i in 0..n {
            x[i] = uni(rng, x_lo[i], x_hi[i]);
        }
        for i in 0..m {
            u[i] = uni(rng, u_lo[i], u_hi[i]);
        }
        system.xdot(&x, &u, &mut fbuf, &mut xd);
        for v in xd.iter_mut() {
            let e: f64 = StandardNormal.sample(rng);
            *v += noise * e;
        }
        ds.xs.extend_from_slice(&x);
        ds.us.extend_from_slice(&u);
        ds.xdot.extend_from_slice(&xd);
    }
    Ok(ds)
}

/// Simulates `k` zero-order-hold steps of length `dt` from `x0` with
/// `u_j = policy(x_j, rng)`, and returns the visited states with `ẋ`
/// estimated by wrap-aware finite differences (paper, footnote 1).
pub fn simulate_trajectory<R: Rng + ?Sized>(
    system: &dyn DynSystem,
    x0: &[f64],
    mut policy: impl FnMut(&[f64], &mut R) -> Vec<f64>,
    dt: f64,
    k: usize,
    settings: SimSettings,
    rng: &mut R,
) -> Result<Dataset, InputError> {
    let (n, m) = (system.state_dim(), system.control_dim());
    if x0.len() != n {
        return Err(InputError::shape("x0", n, x0.len()));
    }
    check_positive("dt", dt)?;
    if k < 2 {
        return Err(InputError::invalid_shown("k", k, "need at least 2 samples"));
    }
    let mut sim = Simulator::new(system, settings);
    let mut ds = Dataset {
        n,
        m,
        ..Default::default()
    };
    let mut x = x0.to_vec();
    for _ in 0..k {
        let u = policy(&x, rng);
        if u.len() != m {
            return Err(InputError::shape("policy output", m, u.len()));
        }
        ds.xs.extend_from_slice(&x);
        ds.us.extend_from_slice(&u);
        sim.step(&mut x, &u, dt, rng)?;
    }
    // forward differences (x_{j+1} − x_j)/dt, wrapped for angles: the held
    // control u_j acts over exactly that interval
    let angles = system.angle_indices();
    let mut xd = Vec::with_capacity(k * n);
    for j in 0..k {
        let next = if j + 1 < k {
            &ds.xs[(j + 1) * n..(j + 2) * n]
        } else {
            &x[..]
        };
        for i in 0..n {
            let dx = next[i] - ds.xs[j * n + i];
            let dx = if angles.contains(&i) {
                crate::systems::wrap_angle(dx)
            } else {
                dx
            };
            xd.push(dx / dt);
        }
    }
    ds.xdot = xd;
    Ok(ds)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::systems::Pendulum;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn bad_boxes_and_noise_are_errors_naming_the_field() {
        let sys = Pendulum::default();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mut draw = |xl: [f64; 2], ul: f64, noise: f64| {
            sample_uniform(&sys, &xl, &[1.0, 1.0], &[ul], &[1.0], 5, noise, &mut rng)
        };
        assert!(draw([-1.0, -1.0], -1.0, 0.0).is_ok());
        let want = |f: &str, v: f64, r: &str| Err(InputError::invalid(f, v, r));
        assert_eq!(
            draw([-1.0, 2.0], -1.0, 0.1),
            want("x_lo[1]", 2.0, "must be ≤ x_hi")
        );
        assert_eq!(
            draw([-1.0, 0.0], 3.0, 0.1),
            want("u_lo[0]", 3.0, "must be ≤ u_hi")
        );
        assert_eq!(
            draw([-1.0, 0.0], 0.0, -0.1),
            want("noise", -0.1, "must be finite and ≥ 0")
        );
    }
}
