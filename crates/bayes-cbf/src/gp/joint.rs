//! Joint posterior of `F(x)` and its Jacobian at one point.
//!
//! Derivatives of a GP are jointly Gaussian with it. Stack
//! `𝔽(x) = [F(x) ∂_1F(x) … ∂_nF(x)] ∈ R^{n × P}`, `P = (1+m)(1+n)`. Under the
//! MVGP posterior `vec 𝔽 ~ N(vec 𝕄, Ĉ ⊗ A)` — the Kronecker structure
//! survives differentiation because `A` does not depend on `x` — with
//! `𝕄 = [M_k ∂_1M_k … ∂_nM_k]` and, for blocks `a, b ∈ {0, 1, …, n}`
//! (0 = `F`, `i` = `∂_iF`),
//!
//! `Ĉ_ab = B ∂_a∂'_b k0(x, x') − Ω_aᵀ G⁻¹ Ω_b` at `x' = x`,
//!
//! where `Ω_0 = W = (𝓑(x)U̲)ᵀ` (rows `k0(x,x_j)(Bu̲_j)ᵀ`), `Ω_i = ∂W/∂x_i`,
//! `∂_0` is the identity and `∂'_b` differentiates the second argument.
//! This is what the relative-degree-2 moments (paper, Sec. VI, Lemma 5) and
//! the Lipschitz bound (Lemma 3) need.

use super::kernel::Kernel;
use super::mvgp::{add_data_part, Mvgp};
use crate::error::InputError;
use faer::Mat;
use nalgebra::DMatrix;
use num_dual::Dual64;

/// `vec 𝔽(x) ~ N(vec mean, c ⊗ A)` with `𝔽 = [F ∂_1F … ∂_nF]`.
#[derive(Debug, Clone, PartialEq)]
pub struct JointPosterior {
    /// `𝕄`, `n × (1+m)(1+n)`; column `a(1+m) + c` is column `c` of block `a`.
    pub mean: DMatrix<f64>,
    /// `Ĉ`, `(1+m)(1+n)` square.
    pub c: DMatrix<f64>,
}

impl JointPosterior {
    /// Empty shell for dimensions `n`, `m`.
    pub fn zeros(n: usize, m: usize) -> Self {
        let pp = (1 + m) * (1 + n);
        Self {
            mean: DMatrix::zeros(n, pp),
            c: DMatrix::zeros(pp, pp),
        }
    }
}

/// Which columns of `𝔽` a joint posterior keeps.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Columns {
    /// All `(1+m)(1+n)`: column `a(1+m) + c` is column `c` of block `a`.
    All,
    /// `F` and the drift column of each `∂_iF` (`1 + m + n`), all that the
    /// relative-degree-2 moments read: column `c ≤ m` of `F`, then `∂_i f`
    /// at `1 + m + (i − 1)` for block `i ≥ 1`. Each entry equals the full
    /// posterior's at that pair of columns, and the data part solves for
    /// `1 + m + n` columns instead of `(1+m)(1+n)`.
    Drift,
}

impl Columns {
    /// How many columns of block `a` are kept (the first ones).
    fn in_block(self, a: usize, p: usize) -> usize {
        match (self, a) {
            (Self::All, _) | (Self::Drift, 0) => p,
            (Self::Drift, _) => 1,
        }
    }
    /// The output index of column `c` of block `a`.
    fn index(self, a: usize, c: usize, p: usize) -> usize {
        match (self, a) {
            (Self::All, _) => a * p + c,
            (Self::Drift, 0) => c,
            (Self::Drift, _) => p + a - 1,
        }
    }
    /// How many columns are kept in all.
    fn width(self, n: usize, p: usize) -> usize {
        match self {
            Self::All => p * (1 + n),
            Self::Drift => p + n,
        }
    }
}

/// Buffers for [`Mvgp::joint_posterior_into`]; the default is empty, sized
/// at its first use.
#[derive(Debug, Clone)]
pub struct JointWorkspace {
    z: Vec<f64>,
    dz: Vec<f64>,
    gk: Vec<f64>,
    hk: Vec<f64>,
    gx: Vec<f64>,
    omega: Mat<f64>,
    m0: Vec<f64>,
    jac0: Vec<f64>,
    sx: Vec<Dual64>,
    so: Vec<Dual64>,
}

impl Default for JointWorkspace {
    fn default() -> Self {
        Self {
            z: Vec::new(),
            dz: Vec::new(),
            gk: Vec::new(),
            hk: Vec::new(),
            gx: Vec::new(),
            omega: Mat::zeros(0, 0),
            m0: Vec::new(),
            jac0: Vec::new(),
            sx: Vec::new(),
            so: Vec::new(),
        }
    }
}

impl<K: Kernel> Mvgp<K> {
    /// A workspace for [`joint_posterior_into`](Self::joint_posterior_into).
    pub fn joint_workspace(&self) -> JointWorkspace {
        self.joint_workspace_for(Columns::All)
    }

    /// A workspace for the columns `cols` (its `Ω` has their width only).
    pub(crate) fn joint_workspace_for(&self, cols: Columns) -> JointWorkspace {
        let [z, dz, gk, hk, gx, _, m0, jac0, sx, so] = self.joint_sizes(cols);
        let (n, p) = (self.state_dim(), self.control_dim() + 1);
        JointWorkspace {
            z: vec![0.0; z],
            dz: vec![0.0; dz],
            gk: vec![0.0; gk],
            hk: vec![0.0; hk],
            gx: vec![0.0; gx],
            omega: Mat::zeros(self.capacity(), cols.width(n, p)),
            m0: vec![0.0; m0],
            jac0: vec![0.0; jac0],
            sx: vec![Dual64::from(0.0); sx],
            so: vec![Dual64::from(0.0); so],
        }
    }

    /// The entries of each buffer of a workspace for `cols`
    /// ([`joint_workspace_for`](Self::joint_workspace_for)): `z`, `dz`, `gk`, `hk`, `gx`,
    /// `Ω` (capacity × width), `m0`, `jac0`, `sx` and `so`. Saturating, so
    /// that a caller can check their memory before it asks for them.
    fn joint_sizes(&self, cols: Columns) -> [usize; 10] {
        let (n, p) = (self.state_dim(), self.control_dim() + 1);
        let d = self.input_map().output_dim(n);
        let np = n.saturating_mul(p);
        [
            d,
            d,
            d,
            d.saturating_mul(d),
            n,
            self.capacity().saturating_mul(cols.width(n, p)),
            np,
            np.saturating_mul(n),
            n,
            np,
        ]
    }

    /// How many `f64`-sized entries a workspace for `cols` holds (a dual
    /// number is two): what a caller checks before it asks for one.
    pub(crate) fn joint_workspace_len(&self, cols: Columns) -> usize {
        let sizes = self.joint_sizes(cols);
        // sx and so hold duals
        sizes
            .into_iter()
            .chain([sizes[8], sizes[9]])
            .fold(0usize, usize::saturating_add)
    }

    /// Joint posterior of `F(x)` and `∂F/∂x_i` (module docs), written into
    /// `out`; no allocation once `ws` is sized for the data.
    pub fn joint_posterior_into(
        &self,
        x: &[f64],
        ws: &mut JointWorkspace,
        out: &mut JointPosterior,
    ) -> Result<(), InputError> {
        self.joint_columns_into(x, Columns::All, ws, out)
    }

    /// [`joint_posterior_into`](Self::joint_posterior_into) for the columns
    /// `cols` of `𝔽` only: `out.mean` is `n × w`, `out.c` `w × w`.
    pub(crate) fn joint_columns_into(
        &self,
        x: &[f64],
        cols: Columns,
        ws: &mut JointWorkspace,
        out: &mut JointPosterior,
    ) -> Result<(), InputError> {
        let (n, m) = (self.state_dim(), self.control_dim());
        let p = m + 1;
        let width = cols.width(n, p);
        self.check_x(x)?;
        if out.mean.shape() != (n, width) || out.c.shape() != (width, width) {
            out.mean = DMatrix::zeros(n, width);
            out.c = DMatrix::zeros(width, width);
        }
        let k = self.len();
        // a workspace of a model of another shape, or one too narrow for
        // `cols`, is remade
        let d = self.input_map().output_dim(n);
        if ws.omega.nrows() < k
            || ws.omega.ncols() < width
            || ws.z.len() != d
            || ws.gx.len() != n
            || ws.m0.len() != n * p
        {
            *ws = self.joint_workspace();
        }
        let map = self.input_map();
        let kern = &self.hyper().kernel;
        let b = &self.hyper().B;
        map.apply(x, &mut ws.z);
        // prior part: K̂_ab ⊗ B
        kern.grad_x(&ws.z, &ws.z, &mut ws.gk);
        let k00 = kern.hess_xy(&ws.z, &ws.z, &mut ws.hk);
        // ∂z_j/∂x_i = [i = src(j)] dz_j (the map acts coordinate-wise)
        for j in 0..d {
            ws.dz[j] = map.derivative(j, x);
        }
        let kk = |a: usize, bb: usize, ws: &JointWorkspace| -> f64 {
            // ∂_a ∂'_b k0(φ(x), φ(x')) at x' = x, in state coordinates. By
            // the kernel's symmetry ∂'k0(z, z) = ∂k0(z, z): both first-order
            // blocks are the gradient at the diagonal (zero for a stationary
            // kernel such as the RBF, not for others)
            match (a, bb) {
                (0, 0) => k00,
                (i, 0) | (0, i) => (0..d)
                    .filter(|&j| map.source(j) == i - 1)
                    .map(|j| ws.gk[j] * ws.dz[j])
                    .sum(),
                (i, l) => {
                    let mut s = 0.0;
                    for r in 0..d {
                        if map.source(r) != i - 1 {
                            continue;
                        }
                        for c in 0..d {
                            if map.source(c) == l - 1 {
                                s += ws.hk[r * d + c] * ws.dz[r] * ws.dz[c];
                            }
                        }
                    }
                    s
                }
            }
        };
        for a in 0..=n {
            for bb in 0..=n {
                let kab = kk(a, bb, ws);
                for c in 0..cols.in_block(a, p) {
                    for c2 in 0..cols.in_block(bb, p) {
                        out.c[(cols.index(a, c, p), cols.index(bb, c2, p))] = kab * b[(c, c2)];
                    }
                }
            }
        }
        // prior mean and its Jacobian
        self.prior().eval(x, &mut ws.m0);
        self.prior()
            .jacobian(x, &mut ws.jac0, &mut ws.sx, &mut ws.so);
        self.prior().check()?;
        let rows = n * p;
        for c in 0..p {
            for i in 0..n {
                out.mean[(i, c)] = ws.m0[i + n * c];
                for a in (1..=n).filter(|&a| c < cols.in_block(a, p)) {
                    out.mean[(i, cols.index(a, c, p))] = ws.jac0[(i + n * c) + rows * (a - 1)];
                }
            }
        }
        if k == 0 {
            return Ok(());
        }
        // Ω = [W ∂_1W … ∂_nW]
        let zs = self.mapped_inputs();
        let bu = self.bu();
        for j in 0..k {
            let kv = kern.grad_x(&ws.z, &zs[j * d..(j + 1) * d], &mut ws.gk);
            ws.gx.fill(0.0);
            for (r, g) in ws.gk.iter().enumerate() {
                ws.gx[map.source(r)] += g * ws.dz[r];
            }
            for c in 0..p {
                let buc = bu[j * p + c];
                ws.omega[(j, c)] = kv * buc;
                for i in (0..n).filter(|&i| c < cols.in_block(i + 1, p)) {
                    ws.omega[(j, cols.index(i + 1, c, p))] = ws.gx[i] * buc;
                }
            }
        }
        let mut v = ws.omega.as_mut().submatrix_mut(0, 0, k, width);
        self.factor().solve_l(v.as_mut());
        add_data_part(v.as_ref(), self.beta_mat(), &mut out.mean, &mut out.c);
        Ok(())
    }

    /// Allocating wrapper of [`joint_posterior_into`](Self::joint_posterior_into).
    pub fn joint_posterior(&self, x: &[f64]) -> Result<JointPosterior, InputError> {
        let mut ws = self.joint_workspace();
        let mut out = JointPosterior::zeros(self.state_dim(), self.control_dim());
        self.joint_posterior_into(x, &mut ws, &mut out)?;
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Fitting buffers are used in place (no reallocation), also when the
    /// data fill the capacity exactly (32 observations); a workspace made
    /// before the model grew is regrown; an output with either matrix of
    /// the wrong shape is resized. Every case gives the fresh posterior.
    #[test]
    fn buffers_are_kept_when_they_fit_and_regrown_when_not() {
        let mut model = crate::gp::plain_model(2, 1, 1.0, 1.0, 0.1);
        let mut stale = model.joint_workspace();
        for j in 0..32 {
            let t = 0.2 * j as f64 - 3.0;
            model
                .add_observation(&[t, t.cos()], &[0.5 * t], &[t.sin(), 0.3 * t])
                .unwrap();
        }
        let x = [0.4, -0.2];
        let want = model.joint_posterior(&x).unwrap();
        let mut out = JointPosterior::zeros(2, 1);
        model
            .joint_posterior_into(&x, &mut stale, &mut out)
            .unwrap();
        assert_eq!(out, want);
        let mut ws = model.joint_workspace();
        assert_eq!(ws.omega.nrows(), model.len());
        let ptrs = |ws: &JointWorkspace, out: &JointPosterior| {
            (ws.omega.as_ptr(), out.mean.as_ptr(), out.c.as_ptr())
        };
        let before = ptrs(&ws, &out);
        model.joint_posterior_into(&x, &mut ws, &mut out).unwrap();
        assert_eq!(ptrs(&ws, &out), before);
        assert_eq!(out, want);
        for (mean, c) in [((2, 6), (5, 5)), ((1, 6), (6, 6)), ((0, 0), (0, 0))] {
            let mut bad = JointPosterior {
                mean: DMatrix::zeros(mean.0, mean.1),
                c: DMatrix::zeros(c.0, c.1),
            };
            model.joint_posterior_into(&x, &mut ws, &mut bad).unwrap();
            assert_eq!(bad, want, "mean {mean:?}, c {c:?}");
        }
    }
}

#[cfg(test)]
mod drift_tests {
    use super::*;
    use crate::gp::input_map::Feature;
    use crate::gp::{InputMap, MvgpHyper, PriorMean, Rbf};
    use crate::systems::Pendulum;
    use std::sync::Arc;

    /// The drift joint posterior is the full one's block at the columns of
    /// `F` and of each `∂_i f`, entry for entry (a prior mean with a
    /// Jacobian, a trigonometric input map, data), and keeps its buffers.
    #[test]
    fn drift_columns_are_the_full_posteriors_block() {
        let hyper = MvgpHyper {
            kernel: Rbf::new(vec![0.9, 1.3, 1.1], 1.2).unwrap(),
            A: DMatrix::from_row_slice(2, 2, &[1.0, 0.3, 0.3, 0.7]),
            B: DMatrix::from_row_slice(2, 2, &[1.1, -0.2, -0.2, 0.8]),
            sigma: 0.2,
        };
        let map = InputMap::Features(vec![Feature::Cos(0), Feature::Sin(0), Feature::Coord(1)]);
        let prior = PriorMean::System(Arc::new(Pendulum::default()));
        let mut model = Mvgp::new(2, 1, hyper, prior, map).unwrap();
        for j in 0..12 {
            let t = 0.37 * j as f64 - 2.0;
            model
                .add_observation(&[t, 0.5 * t.sin()], &[0.3 * t], &[t.cos(), -0.4 * t])
                .unwrap();
        }
        let (n, p) = (2, 2);
        let x = [0.4, -0.7];
        let full = model.joint_posterior(&x).unwrap();
        // the drift workspace holds their `p + n` columns of Ω, not all
        let mut ws = model.joint_workspace_for(Columns::Drift);
        assert_eq!(ws.omega.ncols(), p + n);
        assert_eq!(
            model.joint_workspace_len(Columns::All) - model.joint_workspace_len(Columns::Drift),
            model.capacity() * (p * (1 + n) - (p + n))
        );
        let mut drift = JointPosterior::zeros(0, 0);
        model
            .joint_columns_into(&x, Columns::Drift, &mut ws, &mut drift)
            .unwrap();
        assert_eq!(drift.mean.shape(), (n, p + n));
        // reduced column → full column
        let col = |j: usize| if j < p { j } else { (j - p + 1) * p };
        for a in 0..p + n {
            for i in 0..n {
                assert_eq!(
                    drift.mean[(i, a)],
                    full.mean[(i, col(a))],
                    "mean ({i}, {a})"
                );
            }
            for b in 0..p + n {
                let (got, want) = (drift.c[(a, b)], full.c[(col(a), col(b))]);
                assert!(
                    (got - want).abs() <= 1e-14 * want.abs().max(1.0),
                    "c ({a}, {b})"
                );
            }
        }
        let ptrs = (drift.mean.as_ptr(), drift.c.as_ptr(), ws.omega.as_ptr());
        model
            .joint_columns_into(&[0.1, 0.2], Columns::Drift, &mut ws, &mut drift)
            .unwrap();
        assert_eq!(
            (drift.mean.as_ptr(), drift.c.as_ptr(), ws.omega.as_ptr()),
            ptrs
        );
    }
}
