//! A true system drawn from the MVGP prior itself, by random Fourier
//! features of the RBF kernel: the "well specified" truth of the safety
//! calibration, for which the model is exactly right.

use super::ControlAffine;
use crate::error::{check_index, InputError};
use crate::gp::{Feature, InputMap, MvgpHyper, Rbf};
use nalgebra::DMatrix;
use num_dual::DualNum;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

/// One draw `F` of the matrix-variate GP prior
/// `vec F ~ GP(vec M0, B k0 ⊗ A)` (paper, Sec. IV), as a control-affine
/// system `ẋ = F(x) u̲`.
///
/// With `z = φ(x)` the kernel input ([`InputMap`]), `L_A L_Aᵀ = A` and
/// `L_B L_Bᵀ = B` (Cholesky), the draw is
///
/// `F(x) = M0(x) + L_A W(z) L_Bᵀ`, where the `n × (1+m)` entries of `W` are
/// independent scalar GPs with the RBF kernel
/// `k0(z, z') = s exp(−½ Σ_i (z_i − z'_i)²/ℓ_i²)`, each approximated by `D`
/// random Fourier features (Rahimi and Recht, 2007):
///
/// `W_ab(z) = √(s/D) Σ_j [ξ_jab cos(ω_jᵀz) + η_jab sin(ω_jᵀz)]`,
/// `ω_j ~ N(0, diag(ℓ)⁻²)`, `ξ, η ~ N(0, 1)` independent.
///
/// Then `E[W_ab(z) W_ab(z')] = s E_ω[cos(ωᵀ(z − z'))] = k0(z, z')` (Bochner),
/// so `Cov(F_ic(x), F_jd(x')) = A_ij B_cd k0(z, z')`: exactly the prior's
/// `B k0 ⊗ A` over draws, for any `D`; a larger `D` makes each draw closer
/// to Gaussian (the sum of `D` independent features). The draw is smooth
/// and, when the input map embeds angles as `(cos θ, sin θ)`, periodic in
/// them. It is deterministic given the seed.
///
/// The prior mean `M0` is a parametric model `P` (or zero). Implements
/// [`ControlAffine`] for every dual number type, hence also
/// [`DynSystem`](super::DynSystem).
///
/// ```
/// use bayes_cbf::gp::{InputMap, MvgpHyper, Rbf};
/// use bayes_cbf::systems::{DynSystem, GpSample, Pendulum};
/// use nalgebra::DMatrix;
/// let hyper = MvgpHyper {
///     kernel: Rbf::new(vec![1.0; 3], 1.0).unwrap(),
///     A: DMatrix::identity(2, 2) * 0.01,
///     B: DMatrix::identity(2, 2),
///     sigma: 0.1,
/// };
/// let map = InputMap::periodic(2, &[0]);
/// let truth = GpSample::draw(2, 1, Some(Pendulum::default()), &hyper, &map, 256, 7).unwrap();
/// let mut f = [0.0; 4];
/// truth.eval_f64(&[0.3, -0.2], &mut f);
/// assert!(f.iter().all(|v| v.is_finite()));
/// ```
#[derive(Debug, Clone, PartialEq)]
pub struct GpSample<P: ControlAffine> {
    n: usize,
    m: usize,
    mean: Option<P>,
    input_map: InputMap,
    angles: Vec<usize>,
    /// `D`.
    features: usize,
    /// Kernel input dimension `d`.
    d: usize,
    /// Frequencies `ω_j`, row-major `D × d`.
    omega: Vec<f64>,
    /// `vec(√(s/D) L_A Ξ_j L_Bᵀ)`, row-major `D × n(1+m)`.
    cos_coef: Vec<f64>,
    /// `vec(√(s/D) L_A H_j L_Bᵀ)`, row-major `D × n(1+m)`.
    sin_coef: Vec<f64>,
}

impl<P: ControlAffine> GpSample<P> {
    /// Draws `F` from the prior with hyperparameters `hyper` (kernel, `A`,
    /// `B`; the noise `σ` is not used), prior mean `mean` (`None`: zero),
    /// input map `input_map`, `features` random Fourier features per entry,
    /// seeded by `seed`. Angle components are those of `mean` (see
    /// [`with_angles`](Self::with_angles)).
    ///
    /// Errors name the field: dimensions of `mean`, `A`, `B`, the kernel's
    /// input dimension against the input map, `features ≥ 1`.
    pub fn draw(
        n: usize,
        m: usize,
        mean: Option<P>,
        hyper: &MvgpHyper<Rbf>,
        input_map: &InputMap,
        features: usize,
        seed: u64,
    ) -> Result<Self, InputError> {
        if n == 0 {
            return Err(InputError::invalid("state_dim", 0.0, "must be ≥ 1"));
        }
        if m == 0 {
            return Err(InputError::invalid("control_dim", 0.0, "must be ≥ 1"));
        }
        if let Some(p) = &mean {
            if (p.state_dim(), p.control_dim()) != (n, m) {
                return Err(InputError::shape(
                    "prior_mean",
                    format!("system with n = {n}, m = {m}"),
                    format!("n = {}, m = {}", p.state_dim(), p.control_dim()),
                ));
            }
        }
        if features == 0 {
            return Err(InputError::invalid("features", 0.0, "must be ≥ 1"));
        }
        input_map.validate(n)?;
        let d = input_map.output_dim(n);
        hyper.validate(n, m, d)?;
        // validated positive definite above, so both factorisations succeed
        let (la, lb) = hyper.cholesky_factors()?;
        let p = m + 1;
        let np = n * p;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let ls = hyper.kernel.lengthscales();
        let amp = (hyper.kernel.variance() / features as f64).sqrt();
        let mut omega = Vec::with_capacity(features * d);
        let mut cos_coef = Vec::with_capacity(features * np);
        let mut sin_coef = Vec::with_capacity(features * np);
        for _ in 0..features {
            for l in ls {
                let xi: f64 = StandardNormal.sample(&mut rng);
                omega.push(xi / l);
            }
            for coef in [&mut cos_coef, &mut sin_coef] {
                let w = DMatrix::<f64>::from_fn(n, p, |_, _| StandardNormal.sample(&mut rng));
                let c = &la * w * lb.transpose() * amp;
                // column-major storage of nalgebra is vec C
                coef.extend_from_slice(c.as_slice());
            }
        }
        let angles = mean
            .as_ref()
            .map(|p| p.angle_indices().to_vec())
            .unwrap_or_default();
        Ok(Self {
            n,
            m,
            mean,
            input_map: input_map.clone(),
            angles,
            features,
            d,
            omega,
            cos_coef,
            sin_coef,
        })
    }

    /// Makes the rows of `F` in `rows` the prior mean's exactly: a draw of
    /// the structured prior of [`crate::gp::Mvgp::with_known_rows`], whose
    /// `A` has zero rows and columns there. The other rows keep their
    /// distribution (their coefficients `L_A[L,:] Ξ L_Bᵀ` have covariance
    /// `A_LL`).
    pub fn with_known_rows(mut self, rows: &[usize]) -> Result<Self, InputError> {
        if let Some(&i) = rows.iter().find(|&&i| i >= self.n) {
            return Err(InputError::invalid_shown(
                "known_rows",
                i,
                &format!("is not a row of F (state_dim = {})", self.n),
            ));
        }
        let np = self.n * (self.m + 1);
        for coef in [&mut self.cos_coef, &mut self.sin_coef] {
            for feature in coef.chunks_mut(np) {
                for c in 0..=self.m {
                    for &i in rows {
                        feature[i + self.n * c] = 0.0;
                    }
                }
            }
        }
        Ok(self)
    }

    /// Sets the angle components (wrapped by the simulator), e.g. for a
    /// zero prior mean.
    pub fn with_angles(mut self, angles: Vec<usize>) -> Result<Self, InputError> {
        for (j, &i) in angles.iter().enumerate() {
            check_index(&format!("angles[{j}]"), i, self.n)?;
        }
        self.angles = angles;
        Ok(self)
    }

    /// Number of random Fourier features `D` per entry.
    pub fn features(&self) -> usize {
        self.features
    }

    /// The prior mean `M0`, if not zero.
    pub fn mean(&self) -> Option<&P> {
        self.mean.as_ref()
    }

    /// The input map `φ` the kernel sees.
    pub fn input_map(&self) -> &InputMap {
        &self.input_map
    }
}

/// `z_j = φ(x)_j` on dual numbers.
#[inline]
fn feature<D: DualNum<Primitive = f64> + Copy>(map: &InputMap, j: usize, x: &[D]) -> D {
    match map {
        InputMap::Identity => x[j],
        InputMap::Select(idx) => x[idx[j]],
        InputMap::Features(f) => match f[j] {
            Feature::Coord(i) => x[i],
            Feature::Cos(i) => x[i].cos(),
            Feature::Sin(i) => x[i].sin(),
        },
    }
}

impl<P: ControlAffine> ControlAffine for GpSample<P> {
    fn state_dim(&self) -> usize {
        self.n
    }
    fn control_dim(&self) -> usize {
        self.m
    }
    fn dynamics<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D], out: &mut [D]) {
        match &self.mean {
            Some(p) => p.dynamics(x, out),
            None => out.fill(D::from(0.0)),
        }
        let np = self.n * (self.m + 1);
        let d = self.d;
        // the kernel input, at most a few entries: keep it on the stack
        let mut zbuf = [D::from(0.0); 16];
        let mut zvec = Vec::new();
        let z: &mut [D] = if d <= 16 {
            &mut zbuf[..d]
        } else {
            zvec.resize(d, D::from(0.0));
            &mut zvec
        };
        for (j, zj) in z.iter_mut().enumerate() {
            *zj = feature(&self.input_map, j, x);
        }
        for f in 0..self.features {
            let w = &self.omega[f * d..(f + 1) * d];
            let mut phase = D::from(0.0);
            for (zi, wi) in z.iter().zip(w) {
                phase += *zi * *wi;
            }
            let (s, c) = phase.sin_cos();
            let cc = &self.cos_coef[f * np..(f + 1) * np];
            let sc = &self.sin_coef[f * np..(f + 1) * np];
            for r in 0..np {
                out[r] += c * cc[r] + s * sc[r];
            }
        }
    }
    fn angle_indices(&self) -> &[usize] {
        &self.angles
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::systems::{Ackermann, DynSystem, Pendulum};

    fn hyper(n: usize, m: usize, d: usize) -> MvgpHyper<Rbf> {
        MvgpHyper {
            kernel: Rbf::new(vec![0.8; d], 1.5).unwrap(),
            A: DMatrix::identity(n, n) * 0.2,
            B: DMatrix::identity(m + 1, m + 1),
            sigma: 0.1,
        }
    }

    #[test]
    fn draws_are_deterministic_and_seed_dependent() {
        let map = InputMap::periodic(2, &[0]);
        let h = hyper(2, 1, 3);
        let a = GpSample::draw(2, 1, Some(Pendulum::default()), &h, &map, 64, 3).unwrap();
        let b = GpSample::draw(2, 1, Some(Pendulum::default()), &h, &map, 64, 3).unwrap();
        let c = GpSample::draw(2, 1, Some(Pendulum::default()), &h, &map, 64, 4).unwrap();
        assert_eq!(a, b);
        let (mut fa, mut fc) = ([0.0; 4], [0.0; 4]);
        a.eval_f64(&[0.4, 1.0], &mut fa);
        c.eval_f64(&[0.4, 1.0], &mut fc);
        assert_ne!(fa, fc);
        assert_eq!(ControlAffine::angle_indices(&a), &[0]);
    }

    #[test]
    fn periodic_map_gives_a_periodic_draw() {
        let map = InputMap::periodic(3, &[2]);
        let h = hyper(3, 2, 4);
        let s = GpSample::draw(3, 2, Some(Ackermann::default()), &h, &map, 128, 1).unwrap();
        let (mut f1, mut f2) = ([0.0; 9], [0.0; 9]);
        s.eval_f64(&[0.3, -0.1, 3.1], &mut f1);
        s.eval_f64(&[0.3, -0.1, 3.1 - 2.0 * std::f64::consts::PI], &mut f2);
        for (a, b) in f1.iter().zip(&f2) {
            assert!((a - b).abs() < 1e-9, "{a} {b}");
        }
    }

    #[test]
    fn jacobian_by_dual_numbers_matches_finite_differences() {
        let map = InputMap::periodic(2, &[0]);
        let h = hyper(2, 1, 3);
        let s = GpSample::draw(2, 1, Some(Pendulum::default()), &h, &map, 64, 9).unwrap();
        let x = [0.7, -0.4];
        let mut jac = [0.0; 8];
        let mut sx = [num_dual::Dual64::from(0.0); 2];
        let mut so = [num_dual::Dual64::from(0.0); 4];
        s.jacobian_into(&x, &mut jac, &mut sx, &mut so);
        let eps = 1e-6;
        for j in 0..2 {
            let (mut xp, mut xm) = (x, x);
            xp[j] += eps;
            xm[j] -= eps;
            let (mut fp, mut fm) = ([0.0; 4], [0.0; 4]);
            s.eval_f64(&xp, &mut fp);
            s.eval_f64(&xm, &mut fm);
            for r in 0..4 {
                let fd = (fp[r] - fm[r]) / (2.0 * eps);
                assert!((fd - jac[r + 4 * j]).abs() < 1e-6, "{r} {j}");
            }
        }
    }

    #[test]
    fn bad_input_is_an_error_naming_the_field() {
        let map = InputMap::periodic(2, &[0]);
        let h = hyper(2, 1, 3);
        let e = GpSample::draw(2, 1, Some(Pendulum::default()), &h, &map, 0, 0).unwrap_err();
        assert!(e.to_string().contains("features"), "{e}");
        let e = GpSample::draw(3, 2, Some(Pendulum::default()), &h, &map, 8, 0).unwrap_err();
        assert!(e.to_string().contains("prior_mean"), "{e}");
        let e = GpSample::draw(
            2,
            1,
            Some(Pendulum::default()),
            &h,
            &InputMap::Identity,
            8,
            0,
        )
        .unwrap_err();
        assert!(e.to_string().contains("lengthscales"), "{e}");
        let s = GpSample::draw(2, 1, None::<Pendulum>, &h, &map, 8, 0).unwrap();
        let e = s.clone().with_angles(vec![0, 2]).unwrap_err().to_string();
        assert!(
            e.contains("angles[1]") && e.contains("state dimension 2"),
            "{e}"
        );
        assert_eq!(
            ControlAffine::angle_indices(&s.with_angles(vec![0]).unwrap()),
            &[0]
        );
    }
}
