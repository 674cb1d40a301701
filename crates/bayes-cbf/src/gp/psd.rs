//! Symmetric positive-definite matrices as parameter vectors, shared by the
//! MVGP and CoGP fits.
//!
//! | [`Rank`] | matrix | parameters |
//! |---|---|---|
//! | `Full` | `M = L Lᵀ`, `L` lower triangular with `L_ii > 0` | `log L_ii` and `L_ij` (`i > j`), row by row: `[log L_00, L_10, log L_11, L_20, L_21, log L_22, …]` |
//! | `Low(r)` | `M = C Cᵀ + diag(v)`, `C` lower trapezoidal `dim × r` (`C_iq = 0` for `q > i`) | `C_iq` row by row, then `log v` |
//! | `Diagonal` | `M = diag(v)` | `log v` |
//!
//! The full parameterisation is the Cholesky factor with a logarithmic
//! diagonal: a bijection between `R^{dim(dim+1)/2}` and the positive-definite
//! matrices, so the likelihood has no flat directions from it (a square
//! `C Cᵀ + diag(v)` has `dim(dim−1)/2 + dim` of them: rotations of `C`, and
//! the split of the diagonal between `C Cᵀ` and `v`). The low-rank factor
//! is lower trapezoidal, which removes the rotations of `C`.
//!
//! With [`PsdParam::fixed_first`] the first logarithmic diagonal entry
//! (`log L_00`, or `log v_0`) is held at 0 and is not a parameter: that
//! fixes the scale of `M` (`M_00 = 1` for the full and diagonal forms), which
//! the MVGP needs because `B k0 ⊗ A` is invariant under `(A, B) → (A/c, c B)`.
//!
//! Entries on a logarithmic scale are the ones the fits bound
//! ([`PsdParam::bounds`]): within a factor [`SCALE_RANGE`] of the start's
//! scale in standard-deviation terms, and no smaller than [`CONDITION`]
//! times the start's largest standard deviation. A likelihood that prefers
//! a variance of zero (a column of `F` that is identically zero, such as the
//! Ackermann vehicle's drift) then stops at the floor: a factor `L` with
//! `L_00 = e^{−50}` next to entries of order 1 gives an `M` whose own
//! Cholesky factorisation fails in floating point, and a covariance with a
//! condition number much beyond `10⁸` gives posterior covariances whose
//! Mahalanobis distances are rounding error (relative error ≈ cond · ε).

use super::training::Rank;
use nalgebra::DMatrix;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

/// How far a logarithmic diagonal entry may go from its start, in
/// standard-deviation terms, either way (module docs).
pub(crate) const SCALE_RANGE: f64 = 1e6;

/// Smallest standard deviation of a logarithmic diagonal entry relative to
/// the largest of the start (module docs): variances within `10⁸`.
pub(crate) const CONDITION: f64 = 1e-4;

/// One parameter of a [`PsdParam`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Entry {
    /// `log F_ii` of the factor's diagonal (full form).
    LogFactorDiag(usize),
    /// `F_iq` of the factor.
    Factor(usize, usize),
    /// `log v_i` of the diagonal term.
    LogDiag(usize),
}

/// The parameterisation of a `dim × dim` positive-definite matrix (module
/// docs).
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct PsdParam {
    dim: usize,
    /// Columns of the factor `F` (`L` or `C`).
    cols: usize,
    /// Whether a diagonal term `diag(v)` is present.
    has_diag: bool,
    fixed_first: bool,
    entries: Vec<Entry>,
}

impl PsdParam {
    /// The parameterisation of rank `rank` (module docs).
    pub fn new(dim: usize, rank: Rank) -> Self {
        Self::build(dim, rank, false)
    }

    /// As [`new`](Self::new), with the first logarithmic diagonal entry held
    /// at 0 (module docs).
    pub fn fixed_first(dim: usize, rank: Rank) -> Self {
        Self::build(dim, rank, true)
    }

    fn build(dim: usize, rank: Rank, fixed_first: bool) -> Self {
        let mut entries = Vec::new();
        let (cols, has_diag) = match rank {
            Rank::Full => {
                for i in 0..dim {
                    entries.extend((0..i).map(|q| Entry::Factor(i, q)));
                    if !(fixed_first && i == 0) {
                        entries.push(Entry::LogFactorDiag(i));
                    }
                }
                (dim, false)
            }
            Rank::Low(r) => {
                let r = r.min(dim);
                for i in 0..dim {
                    entries.extend((0..r.min(i + 1)).map(|q| Entry::Factor(i, q)));
                }
                (r, true)
            }
            Rank::Diagonal => (0, true),
        };
        if has_diag {
            let first = usize::from(fixed_first);
            entries.extend((first..dim).map(Entry::LogDiag));
        }
        Self {
            dim,
            cols,
            has_diag,
            fixed_first,
            entries,
        }
    }

    /// Number of parameters.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Bounds of the parameters around a start matrix `m` (module docs):
    /// `log L_ii ∈ [l_i, max(ln √m_ii + ln R, l_i)]` with
    /// `l_i = max(ln √m_ii − ln R, ln √max_j m_jj + ln C)`, `R = range`
    /// ([`SCALE_RANGE`] for a cold start) and `C` = [`CONDITION`]; `log v_i`
    /// in twice that interval; factor entries are free. An entry further
    /// below the largest than `C R` may rise to the floor: the interval is
    /// never empty.
    pub fn bounds(&self, m: &DMatrix<f64>, range: f64, lo: &mut [f64], hi: &mut [f64]) {
        let r = range.ln();
        let log_var = |i: usize| {
            let v = m[(i, i)];
            if v.is_finite() && v > 0.0 {
                v.ln()
            } else {
                0.0
            }
        };
        let top = (0..self.dim).map(log_var).fold(f64::NEG_INFINITY, f64::max);
        let floor = 0.5 * top + CONDITION.ln();
        for ((e, l), h) in self.entries.iter().zip(lo.iter_mut()).zip(hi.iter_mut()) {
            (*l, *h) = match *e {
                Entry::LogFactorDiag(i) => {
                    let c = 0.5 * log_var(i);
                    let l = (c - r).max(floor);
                    (l, (c + r).max(l))
                }
                Entry::Factor(..) => (f64::NEG_INFINITY, f64::INFINITY),
                Entry::LogDiag(i) => {
                    let c = log_var(i);
                    let l = (c - 2.0 * r).max(2.0 * floor);
                    (l, (c + 2.0 * r).max(l))
                }
            };
        }
    }

    /// The factor `F` (`dim × cols`) and the diagonal `v` at `th`.
    fn parts(&self, th: &[f64]) -> (DMatrix<f64>, Vec<f64>) {
        debug_assert_eq!(th.len(), self.len());
        let mut f = DMatrix::zeros(self.dim, self.cols);
        let mut v = vec![0.0; if self.has_diag { self.dim } else { 0 }];
        if self.fixed_first {
            if self.has_diag {
                v[0] = 1.0;
            } else {
                f[(0, 0)] = 1.0;
            }
        }
        for (e, t) in self.entries.iter().zip(th) {
            match *e {
                Entry::LogFactorDiag(i) => f[(i, i)] = t.exp(),
                Entry::Factor(i, q) => f[(i, q)] = *t,
                Entry::LogDiag(i) => v[i] = t.exp(),
            }
        }
        (f, v)
    }

    /// `M(θ)`.
    pub fn matrix(&self, th: &[f64]) -> DMatrix<f64> {
        let (f, v) = self.parts(th);
        let mut m = &f * f.transpose();
        for (i, vi) in v.iter().enumerate() {
            m[(i, i)] += vi;
        }
        m
    }

    /// Chain rule through `M(θ)`: `out_i = Σ_ab M̄_ab ∂M_ab/∂θ_i` for a
    /// symmetric `M̄` (the gradient of a function of `M` with respect to
    /// `M`'s entries).
    ///
    /// `∂/∂F = 2 M̄ F`; a logarithmic entry multiplies by its exponential.
    pub fn chain(&self, mbar: &DMatrix<f64>, th: &[f64], out: &mut [f64]) {
        let (f, v) = self.parts(th);
        let gf = 2.0 * mbar * &f;
        for (e, o) in self.entries.iter().zip(out.iter_mut()) {
            *o = match *e {
                Entry::LogFactorDiag(i) => gf[(i, i)] * f[(i, i)],
                Entry::Factor(i, q) => gf[(i, q)],
                Entry::LogDiag(i) => mbar[(i, i)] * v[i],
            };
        }
    }

    /// Parameters of `diag(m_00, …)`, exactly, with a zero factor off the
    /// diagonal (for the low-rank form a saddle point of `C`: a candidate
    /// to compare, not a start).
    pub fn diagonal_point(&self, m: &DMatrix<f64>, out: &mut [f64]) {
        for (e, o) in self.entries.iter().zip(out.iter_mut()) {
            *o = match *e {
                Entry::LogFactorDiag(i) => 0.5 * m[(i, i)].max(1e-300).ln(),
                Entry::Factor(..) => 0.0,
                Entry::LogDiag(i) => m[(i, i)].max(1e-300).ln(),
            };
        }
    }

    /// Parameters of (or near) `m`, written into `out`.
    ///
    /// Full form: the Cholesky factor of `m`, exact (with `fixed_first`,
    /// `m_00` must be 1; a matrix that is not positive definite starts from
    /// its diagonal). Diagonal form: `log m_ii`, exact. Low-rank form: `C`
    /// small and random (`0.1 √m_ii` times a standard normal, drawn row by
    /// row) and `v` the rest of the diagonal (floored), since the gradient
    /// with respect to `C` vanishes at `C = 0`.
    pub fn init(&self, m: &DMatrix<f64>, rng: &mut ChaCha8Rng, out: &mut [f64]) {
        let dim = self.dim;
        let mut f = DMatrix::<f64>::zeros(dim, self.cols);
        let mut v = vec![0.0; dim];
        if self.has_diag {
            for i in 0..dim {
                let scale = 0.1 * m[(i, i)].abs().sqrt();
                for q in 0..self.cols.min(i + 1) {
                    let z: f64 = StandardNormal.sample(rng);
                    f[(i, q)] = scale * z;
                }
                let ff: f64 = (0..self.cols).map(|q| f[(i, q)].powi(2)).sum();
                v[i] = (m[(i, i)] - ff).max(1e-3 * m[(i, i)].abs()).max(1e-300);
            }
        } else {
            let diag = || DMatrix::from_fn(dim, dim, |i, j| if i == j { m[(i, i)] } else { 0.0 });
            let l = m
                .clone()
                .cholesky()
                .or_else(|| diag().cholesky())
                .map(|c| c.l());
            match l {
                Some(l) => f.copy_from(&l),
                None => f.fill_with_identity(),
            }
        }
        for (e, o) in self.entries.iter().zip(out.iter_mut()) {
            *o = match *e {
                Entry::LogFactorDiag(i) => f[(i, i)].max(1e-300).ln(),
                Entry::Factor(i, q) => f[(i, q)],
                Entry::LogDiag(i) => v[i].ln(),
            };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    fn forms() -> Vec<PsdParam> {
        let mut v = Vec::new();
        for dim in 1..=4 {
            for rank in [Rank::Full, Rank::Diagonal, Rank::Low(1), Rank::Low(2)] {
                v.push(PsdParam::new(dim, rank));
                v.push(PsdParam::fixed_first(dim, rank));
            }
        }
        v
    }

    #[test]
    fn parameter_counts() {
        // full: dim(dim+1)/2, one fewer with the first entry fixed
        assert_eq!(PsdParam::new(3, Rank::Full).len(), 6);
        assert_eq!(PsdParam::fixed_first(3, Rank::Full).len(), 5);
        // low rank 2 on 4: trapezoidal factor 1 + 2 + 2 + 2, diagonal 4
        assert_eq!(PsdParam::new(4, Rank::Low(2)).len(), 11);
        assert_eq!(PsdParam::fixed_first(4, Rank::Diagonal).len(), 3);
    }

    #[test]
    fn matrices_are_positive_definite_and_fixed_first_pins_the_scale() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for p in forms() {
            let th: Vec<f64> = (0..p.len()).map(|_| rng.random_range(-1.0..1.0)).collect();
            let m = p.matrix(&th);
            assert!(m.clone().cholesky().is_some(), "{p:?}");
            assert!((&m - m.transpose()).amax() < 1e-15);
            // low rank: v_0 = 1 and M_00 = 1 + |C_0|²
            let low_rank = p.has_diag && p.cols > 0;
            if p.fixed_first && !low_rank {
                assert!((m[(0, 0)] - 1.0).abs() < 1e-15, "{p:?}");
            }
        }
    }

    /// The chain rule against central finite differences of `tr(M̄ M(θ))`.
    #[test]
    fn chain_rule_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        for p in forms() {
            let th: Vec<f64> = (0..p.len()).map(|_| rng.random_range(-1.0..1.0)).collect();
            let a = DMatrix::<f64>::from_fn(p.dim, p.dim, |_, _| rng.random_range(-1.0..1.0));
            let mbar = &a + a.transpose();
            let f = |t: &[f64]| (&mbar.transpose() * p.matrix(t)).trace();
            let mut g = vec![0.0; p.len()];
            p.chain(&mbar, &th, &mut g);
            for i in 0..p.len() {
                let (mut tp, mut tm) = (th.clone(), th.clone());
                tp[i] += 1e-6;
                tm[i] -= 1e-6;
                let fd = (f(&tp) - f(&tm)) / 2e-6;
                assert!(
                    (fd - g[i]).abs() < 1e-7 * (1.0 + fd.abs()),
                    "{p:?} {i}: {fd} {}",
                    g[i]
                );
            }
        }
    }

    #[test]
    fn bounds_keep_the_matrix_positive_definite() {
        // every logarithmic entry at its lower bound and the factor's other
        // entries at the scale of their row: the matrix still factorises
        let m = DMatrix::from_diagonal(&nalgebra::DVector::from_vec(vec![4.0, 0.01, 9.0]));
        for p in [
            PsdParam::new(3, Rank::Full),
            PsdParam::new(3, Rank::Low(2)),
            PsdParam::fixed_first(3, Rank::Full),
        ] {
            let (mut lo, mut hi) = (vec![0.0; p.len()], vec![0.0; p.len()]);
            p.bounds(&m, SCALE_RANGE, &mut lo, &mut hi);
            let th: Vec<f64> = p
                .entries
                .iter()
                .zip(&lo)
                .map(|(e, l)| match *e {
                    Entry::Factor(i, _) => m[(i, i)].sqrt(),
                    _ => *l,
                })
                .collect();
            assert!(p.matrix(&th).cholesky().is_some(), "{p:?}");
            for (l, h) in lo.iter().zip(&hi) {
                assert!(l < h);
            }
        }
    }

    #[test]
    fn a_narrow_range_below_the_floor_rises_to_it() {
        // √m_11 = 1e-6 of √m_00: with range 10 its interval [1e-7, 1e-5]
        // (relative) lies wholly below the floor C = 1e-4, which wins
        let m = DMatrix::from_diagonal(&nalgebra::DVector::from_vec(vec![1.0, 1e-12]));
        let floor = CONDITION.ln();
        for p in [
            PsdParam::new(2, Rank::Full),
            PsdParam::new(2, Rank::Diagonal),
        ] {
            let (mut lo, mut hi) = (vec![0.0; p.len()], vec![0.0; p.len()]);
            p.bounds(&m, 10.0, &mut lo, &mut hi);
            for (e, (l, h)) in p.entries.iter().zip(lo.iter().zip(&hi)) {
                match *e {
                    Entry::LogFactorDiag(1) => assert_eq!((*l, *h), (floor, floor)),
                    Entry::LogDiag(1) => assert_eq!((*l, *h), (2.0 * floor, 2.0 * floor)),
                    Entry::LogFactorDiag(0) => {
                        assert_eq!((*l, *h), (-(10f64.ln()), 10f64.ln()))
                    }
                    Entry::LogDiag(0) => {
                        assert_eq!((*l, *h), (-2.0 * 10f64.ln(), 2.0 * 10f64.ln()))
                    }
                    _ => assert!(l <= h),
                }
            }
        }
    }

    #[test]
    fn full_and_diagonal_starts_are_exact() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let a = DMatrix::<f64>::from_fn(3, 3, |_, _| rng.random_range(-1.0..1.0));
        let mut m = &a * a.transpose() + DMatrix::identity(3, 3) * 0.5;
        m /= m[(0, 0)];
        for p in [
            PsdParam::new(3, Rank::Full),
            PsdParam::fixed_first(3, Rank::Full),
        ] {
            let mut th = vec![0.0; p.len()];
            p.init(&m, &mut rng, &mut th);
            assert!((p.matrix(&th) - &m).amax() < 1e-12, "{p:?}");
        }
        let d = DMatrix::from_diagonal(&m.diagonal());
        for p in [
            PsdParam::new(3, Rank::Diagonal),
            PsdParam::fixed_first(3, Rank::Diagonal),
        ] {
            let mut th = vec![0.0; p.len()];
            p.init(&d, &mut rng, &mut th);
            assert!((p.matrix(&th) - &d).amax() < 1e-12, "{p:?}");
        }
        for p in [
            PsdParam::new(3, Rank::Full),
            PsdParam::new(3, Rank::Low(2)),
            PsdParam::new(3, Rank::Diagonal),
        ] {
            let mut th = vec![0.0; p.len()];
            p.diagonal_point(&d, &mut th);
            assert!((p.matrix(&th) - &d).amax() < 1e-12, "{p:?}");
        }
        // the low-rank start keeps the diagonal
        let p = PsdParam::new(3, Rank::Low(1));
        let mut th = vec![0.0; p.len()];
        p.init(&m, &mut rng, &mut th);
        let s = p.matrix(&th);
        for i in 0..3 {
            assert!((s[(i, i)] - m[(i, i)]).abs() < 1e-12);
        }
    }
}
