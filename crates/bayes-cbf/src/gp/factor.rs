//! A Cholesky factor `L Lᵀ = G` of a Gram matrix that grows by one row per
//! observation (O(k²)) and drops its oldest row (O(k²) rank-one update).
//!
//! The factor is stored as a faer matrix; the public methods take and return
//! nalgebra matrices or slices, the faer-typed ones are crate-private.

use super::simd::with_faer;
use crate::error::GpError;
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::triangular_solve::{
    solve_lower_triangular_in_place, solve_upper_triangular_in_place,
};
use faer::{Mat, MatMut, MatRef, Par};
use nalgebra::DMatrix;

/// Relative jitter levels tried, in order, when a factorisation fails: the
/// jitter added to the diagonal is `level × mean(diag G)`.
pub const JITTER_LEVELS: [f64; 6] = [0.0, 1e-12, 1e-10, 1e-8, 1e-7, 1e-6];

/// Smallest accepted squared pivot `L_jj²`, relative to its own diagonal
/// entry `G_jj` (plus jitter): a pivot below it counts as a failed
/// factorisation and escalates the jitter.
///
/// The computed factor satisfies `L Lᵀ = G + ΔG` with a backward error
/// `|ΔG| ≲ k ε |G|` (ε = 2.2e-16), up to ~1e-13 relative at k = 1000. A
/// pivot within that error of zero (near-duplicate points with tiny noise)
/// makes `L Lᵀ` a factor of a possibly indefinite matrix, and the posterior
/// `B k0 − Vᵀ V`, `V = L⁻¹ W`, amplifies the error by `1/L_jj²`. Measured
/// (`tests/numerical_faults.rs`, a pendulum at rest observed 300 times with
/// model noise σ = 1e-9): with the former floor of 1e-14, `tr B_k` reached
/// −6·10⁴ times its prior value; with 1e-10 it stays ≥ 0.
const MIN_PIVOT: f64 = 1e-10;

/// Lower-triangular Cholesky factor with spare capacity for online growth.
#[derive(Debug, Clone)]
pub struct CholFactor {
    l: Mat<f64>,
    k: usize,
    /// Jitter added to each diagonal entry (absolute).
    jitter: Vec<f64>,
}

impl Default for CholFactor {
    fn default() -> Self {
        Self {
            l: Mat::zeros(0, 0),
            k: 0,
            jitter: Vec::new(),
        }
    }
}

/// The new diagonal entry of an append: `L_kk² = G_kk + jitter − ‖L⁻¹g‖²`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Pivot {
    /// `L_kk²`.
    pub(crate) square: f64,
    /// The jitter added to `G_kk`.
    pub(crate) jitter: f64,
}

impl CholFactor {
    /// Factorises `G` (only the lower triangle is read), escalating jitter
    /// through [`JITTER_LEVELS`] while the factorisation fails or leaves a
    /// pivot `L_jj² ≤ 1e-10 (G_jj + jitter)` (within roundoff of singular);
    /// fails with [`GpError::IllConditioned`].
    pub(crate) fn factor(g: MatRef<'_, f64>, capacity: usize) -> Result<Self, GpError> {
        Self::factor_with(g, capacity, Jitter::Escalate)
    }

    /// [`factor`](Self::factor) with the given jitter policy.
    pub(crate) fn factor_with(
        g: MatRef<'_, f64>,
        capacity: usize,
        jitter: Jitter,
    ) -> Result<Self, GpError> {
        let k = g.nrows();
        let cap = capacity.max(k).max(1);
        let mut l = Mat::<f64>::zeros(cap, cap);
        let mut scratch = DenseScratch::new(k);
        let jit = factor_in_place(
            l.as_mut().submatrix_mut(0, 0, k, k),
            &mut scratch,
            jitter,
            |mut a| {
                for j in 0..k {
                    for i in j..k {
                        a[(i, j)] = g[(i, j)];
                    }
                }
            },
        )?;
        if jit > 0.0 {
            log::warn!("Gram matrix (k = {k}) needed jitter {jit:.3e} to factorise");
        }
        // clear the strict upper triangle
        for j in 0..k {
            for i in 0..j {
                l[(i, j)] = 0.0;
            }
        }
        Ok(Self {
            l,
            k,
            jitter: vec![jit; k],
        })
    }

    /// Number of rows `k`.
    pub fn len(&self) -> usize {
        self.k
    }

    /// `k == 0`.
    pub fn is_empty(&self) -> bool {
        self.k == 0
    }

    /// A copy of the factor `L` (`k × k`, lower triangular).
    pub fn l(&self) -> DMatrix<f64> {
        let l = self.l_ref();
        DMatrix::from_fn(self.k, self.k, |i, j| l[(i, j)])
    }

    /// The factor `L` (`k × k`), borrowed.
    pub(crate) fn l_ref(&self) -> MatRef<'_, f64> {
        self.l.as_ref().submatrix(0, 0, self.k, self.k)
    }

    /// Absolute jitter added to each diagonal entry of `G`.
    pub fn jitter(&self) -> &[f64] {
        &self.jitter
    }

    /// Largest absolute jitter in use.
    pub fn max_jitter(&self) -> f64 {
        self.jitter.iter().cloned().fold(0.0, f64::max)
    }

    /// Solves `L X = B` in place; `B` must have `k` rows.
    #[track_caller]
    pub fn solve_l_in_place(&self, rhs: &mut DMatrix<f64>) {
        let (r, c) = rhs.shape();
        self.solve_l(MatMut::from_column_major_slice_mut(
            rhs.as_mut_slice(),
            r,
            c,
        ));
    }

    /// Solves `Lᵀ X = B` in place; `B` must have `k` rows.
    #[track_caller]
    pub fn solve_lt_in_place(&self, rhs: &mut DMatrix<f64>) {
        let (r, c) = rhs.shape();
        self.solve_lt(MatMut::from_column_major_slice_mut(
            rhs.as_mut_slice(),
            r,
            c,
        ));
    }

    /// Solves `L X = B` in place (`B` has `k` rows).
    #[track_caller]
    pub(crate) fn solve_l(&self, rhs: MatMut<'_, f64>) {
        assert_eq!(rhs.nrows(), self.k, "right-hand side rows");
        with_faer(|| solve_lower_triangular_in_place(self.l_ref(), rhs, Par::Seq));
    }

    /// Solves `Lᵀ X = B` in place (`B` has `k` rows).
    #[track_caller]
    pub(crate) fn solve_lt(&self, rhs: MatMut<'_, f64>) {
        assert_eq!(rhs.nrows(), self.k, "right-hand side rows");
        with_faer(|| solve_upper_triangular_in_place(self.l_ref().transpose(), rhs, Par::Seq));
    }

    /// Solves `L_pᵀ X = B` in place with the leading `p × p` block `L_p`
    /// of the factor (the factor before its last `k − p` appends).
    #[track_caller]
    pub(crate) fn solve_leading_lt(&self, p: usize, rhs: MatMut<'_, f64>) {
        assert!(p <= self.k, "leading block {p} larger than k = {}", self.k);
        assert_eq!(rhs.nrows(), p, "right-hand side rows");
        let lp = self.l.as_ref().submatrix(0, 0, p, p);
        with_faer(|| solve_upper_triangular_in_place(lp.transpose(), rhs, Par::Seq));
    }

    /// Column `j` of `G⁻¹` into `out[..k]`: `y = L⁻¹ e_j` (zero above `j`,
    /// so only the trailing `(k − j)²/2` block is solved), then `Lᵀ c = y`.
    /// O(k²).
    #[track_caller]
    pub fn inverse_column_into(&self, j: usize, out: &mut [f64]) {
        let k = self.k;
        assert!(
            j < k && out.len() >= k,
            "inverse_column_into: j = {j}, k = {k}"
        );
        let out = &mut out[..k];
        out[..j].fill(0.0);
        self.unit_solve_trailing(j, &mut out[j..]);
        self.solve_lt(MatMut::from_column_major_slice_mut(out, k, 1));
    }

    /// `y = (L⁻¹ e_j)[j..]`, written into `y` (length `k − j`).
    fn unit_solve_trailing(&self, j: usize, y: &mut [f64]) {
        let k = self.k;
        let t = k - 1 - j;
        let yj = 1.0 / self.l[(j, j)];
        y[0] = yj;
        for i in 0..t {
            y[1 + i] = -self.l[(j + 1 + i, j)] * yj;
        }
        let l33 = self.l.as_ref().submatrix(j + 1, j + 1, t, t);
        let rhs = MatMut::from_column_major_slice_mut(&mut y[1..], t, 1);
        with_faer(|| solve_lower_triangular_in_place(l33, rhs, Par::Seq));
    }

    /// The diagonal of `G⁻¹`, `[G⁻¹]_jj = ‖L⁻¹ e_j‖²`, into `out` (cleared
    /// first), using `work` (≥ k entries). `Σ_j (k − j)²/2 ≈ k³/6` flops,
    /// no allocation once `out` has capacity `k`.
    pub fn inverse_diagonal_into(&self, out: &mut Vec<f64>, work: &mut [f64]) {
        let k = self.k;
        out.clear();
        for j in 0..k {
            let y = &mut work[..k - j];
            self.unit_solve_trailing(j, y);
            out.push(y.iter().map(|v| v * v).sum());
        }
    }

    /// `G⁻¹` (full symmetric `k × k`) by faer's blocked inverse of the
    /// factor (≈ ⅔k³ flops).
    pub fn inverse(&self) -> DMatrix<f64> {
        let inv = self.inverse_mat();
        DMatrix::from_fn(self.k, self.k, |i, j| inv[(i, j)])
    }

    /// [`inverse`](Self::inverse) as a faer matrix.
    pub(crate) fn inverse_mat(&self) -> Mat<f64> {
        let k = self.k;
        let mut out = Mat::<f64>::zeros(k, k);
        inverse_in_place(out.as_mut(), self.l_ref(), &mut DenseScratch::new(k));
        // only the lower triangle is written
        for j in 0..k {
            for i in 0..j {
                out[(i, j)] = out[(j, i)];
            }
        }
        out
    }

    /// `log det G = 2 Σ log L_ii`.
    pub fn log_det(&self) -> f64 {
        2.0 * (0..self.k).map(|i| self.l[(i, i)].ln()).sum::<f64>()
    }

    fn ensure_capacity(&mut self, k: usize) {
        if self.l.nrows() >= k {
            return;
        }
        let cap = (2 * self.l.nrows()).max(k).max(16);
        let mut l = Mat::<f64>::zeros(cap, cap);
        with_faer(|| {
            l.as_mut()
                .submatrix_mut(0, 0, self.k, self.k)
                .copy_from(self.l_ref())
        });
        self.l = l;
    }

    /// Appends one row: `g_new[i] = G[k, i]` for the existing `i < k`, and the
    /// new diagonal `G[k, k]`. Cost: one triangular solve, O(k²).
    ///
    /// If the new pivot is not positive, or `L_kk² ≤ 1e-10 (diag + jitter)`
    /// (e.g. a duplicate point with tiny noise), jitter escalates through
    /// [`JITTER_LEVELS`] relative to `diag` for this entry only.
    pub fn append(&mut self, g_new: &[f64], diag: f64, scratch: &mut [f64]) -> Result<(), GpError> {
        let pivot = self.pivot(g_new, diag, scratch)?;
        self.push_row(&scratch[..self.k], pivot);
        Ok(())
    }

    /// The row an [`append`](Self::append) would add, without adding it:
    /// `scratch[..k] = L⁻¹ g_new` and the new pivot `L_kk²` with the jitter
    /// it needed (one triangular solve). [`push_row`](Self::push_row)
    /// completes the append.
    pub(crate) fn pivot(
        &self,
        g_new: &[f64],
        diag: f64,
        scratch: &mut [f64],
    ) -> Result<Pivot, GpError> {
        let k = self.k;
        assert_eq!(g_new.len(), k, "g_new length");
        if !diag.is_finite() {
            return Err(GpError::Overflow {
                size: k + 1,
                diagonal: diag,
            });
        }
        let row = &mut scratch[..k];
        row.copy_from_slice(g_new);
        self.solve_l(MatMut::from_column_major_slice_mut(row, k, 1));
        let sq: f64 = row.iter().map(|v| v * v).sum();
        for &level in JITTER_LEVELS.iter() {
            let jitter = level * diag.abs().max(f64::MIN_POSITIVE);
            let square = diag + jitter - sq;
            if square > 0.0 && square.is_finite() && square > MIN_PIVOT * (diag + jitter).abs() {
                // once per scope ([`crate::warnings`]): a run would repeat it
                // at every update
                static JITTER: crate::warnings::WarnOnce =
                    crate::warnings::WarnOnce::new("online_update_jitter");
                if level > 0.0 {
                    JITTER.issue(|| {
                        format!(
                            "online update (k = {}) needed jitter {jitter:.3e} on the new \
                             diagonal entry (later online updates that need jitter are not \
                             shown)",
                            k + 1
                        )
                    });
                }
                return Ok(Pivot { square, jitter });
            }
        }
        Err(GpError::IllConditioned {
            size: k + 1,
            max_jitter: *JITTER_LEVELS.last().unwrap_or(&0.0),
        })
    }

    /// Appends the row `[row, √pivot.square]` found by
    /// [`pivot`](Self::pivot).
    pub(crate) fn push_row(&mut self, row: &[f64], pivot: Pivot) {
        let k = self.k;
        self.ensure_capacity(k + 1);
        for (j, v) in row.iter().enumerate() {
            self.l[(k, j)] = *v;
        }
        self.l[(k, k)] = pivot.square.sqrt();
        for i in 0..k {
            self.l[(i, k)] = 0.0;
        }
        self.jitter.push(pivot.jitter);
        self.k += 1;
    }

    /// Removes the first row and column of `G` (sliding window); see
    /// [`remove`](Self::remove). `scratch` needs `4k − 3` entries.
    pub fn remove_first(&mut self, scratch: &mut [f64]) {
        if self.k > 0 {
            self.remove(0, scratch);
        }
    }

    /// Removes row and column `j` of `G`, O(k²).
    ///
    /// With `L = [L11 0 0; l21ᵀ l22 0; L31 l32 L33]` (block row `j` in the
    /// middle), the factor of `G` without `j` is `[L11 0; L31 L33']` with
    /// `L33' L33'ᵀ = L33 L33ᵀ + l32 l32ᵀ`: the rows below `j` move up, the
    /// columns after `j` move left, and the trailing block takes a rank-one
    /// update by `t = k − 1 − j` Givens rotations, `O(t²)`.
    ///
    /// Rotation `c` acts on column `c` of the trailing block and the vector
    /// `v = l32`: `(L_c, v) ← (cos L_c + sin v, −sin L_c + cos v)`. They are
    /// written to `scratch[t + 2c]` (cos) and `scratch[t + 2c + 1]` (sin) so
    /// that a caller can apply the same orthogonal transformation to a
    /// right-hand side `β = L⁻¹ R`: rows `(β3_c, β_j)` rotate the same way
    /// and the first `t` results are the new `β3'`. `scratch` needs `4t + 1`
    /// entries.
    ///
    /// Each trailing column is read once and written once (shift and
    /// rotation fused, contiguous column slices), so the cost is one pass
    /// over the `(k − j)²/2` trailing entries plus a `memmove` of the rows
    /// below `j` in the first `j` columns.
    #[track_caller]
    pub fn remove(&mut self, j: usize, scratch: &mut [f64]) {
        let k = self.k;
        assert!(j < k, "remove: index {j} out of range (k = {k})");
        let t = k - 1 - j;
        assert!(scratch.len() > 4 * t, "remove: scratch too short");
        let (v, rest) = scratch.split_at_mut(t);
        let (rot, col) = rest.split_at_mut(2 * t);
        v.copy_from_slice(&self.l.col_as_slice(j)[j + 1..k]);
        // rows below j move up in the columns before j
        for c in 0..j {
            self.l.col_as_slice_mut(c).copy_within(j + 1..k, j);
        }
        // trailing block: new column j + c is old column j + c + 1 moved up
        // one row, rotated against v (rank-one update L33 L33ᵀ + v vᵀ)
        for c in 0..t {
            let cc = j + c;
            let len = t - c;
            col[..len].copy_from_slice(&self.l.col_as_slice(cc + 1)[cc + 1..k]);
            let dst = &mut self.l.col_as_slice_mut(cc)[cc..cc + len];
            let lcc = col[0];
            let r = (lcc * lcc + v[c] * v[c]).sqrt();
            let (cs, sn) = (lcc / r, v[c] / r);
            dst[0] = r;
            for ((d, &lic), vi) in dst[1..].iter_mut().zip(&col[1..len]).zip(&mut v[c + 1..]) {
                *d = cs * lic + sn * *vi;
                *vi = cs * *vi - sn * lic;
            }
            rot[2 * c] = cs;
            rot[2 * c + 1] = sn;
        }
        let k1 = k - 1;
        for i in 0..k {
            self.l[(k1, i)] = 0.0;
            self.l[(i, k1)] = 0.0;
        }
        self.jitter.remove(j);
        self.k = k1;
    }
}

/// Workspace of the dense factorisation and inverse at a fixed size `k`
/// ([`factor_in_place`], [`inverse_in_place`]): reused, it keeps repeated
/// factorisations (the likelihood evaluations of a fit) free of allocation.
pub(crate) struct DenseScratch {
    mem: MemBuffer,
    diag: Vec<f64>,
}

impl DenseScratch {
    /// Scratch for `k × k` matrices.
    pub(crate) fn new(k: usize) -> Self {
        use faer::linalg::cholesky::llt::{factor, inverse};
        let req = factor::cholesky_in_place_scratch::<f64>(k, Par::Seq, Default::default())
            .or(inverse::inverse_scratch::<f64>(k, Par::Seq));
        Self {
            mem: MemBuffer::new(req),
            diag: vec![0.0; k],
        }
    }
}

/// How [`factor_in_place`] treats a matrix that does not factorise.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Jitter {
    /// Escalate jitter through [`JITTER_LEVELS`] while the factorisation
    /// fails or leaves a pivot within roundoff of singular (a model's
    /// factor: its posterior variances need the pivot floor).
    Escalate,
    /// Factorise `G` as it is and fail if it is not positive definite or a
    /// pivot is below the floor times the given factor (a likelihood
    /// evaluation inside an optimiser: jitter would make the objective jump
    /// where it switches on, and the pivot floor keeps the optimum where
    /// the model's own factor needs no jitter; a factor above 1 leaves a
    /// margin for the model's factor, computed with other roundoff).
    Exact(f64),
}

/// Factorises `G = L Lᵀ` in place in the lower triangle of `a` (`k × k`),
/// where `fill(a)` writes `G`'s lower triangle (the strict upper triangle
/// is neither read nor written). With [`Jitter::Escalate`], escalates
/// jitter through [`JITTER_LEVELS`] (relative to the mean diagonal,
/// refilling `a` for each level) while the factorisation fails or leaves a
/// pivot `L_jj² ≤ 1e-10 (G_jj + jitter)` (within roundoff of singular);
/// with [`Jitter::Exact`], either fails at once. Returns the absolute jitter added to the diagonal, or fails with
/// [`GpError::IllConditioned`].
pub(crate) fn factor_in_place(
    mut a: MatMut<'_, f64>,
    scratch: &mut DenseScratch,
    jitter: Jitter,
    mut fill: impl FnMut(MatMut<'_, f64>),
) -> Result<f64, GpError> {
    use faer::linalg::cholesky::llt::factor;
    let k = a.nrows();
    assert!(
        a.ncols() == k && scratch.diag.len() >= k,
        "factor_in_place: size"
    );
    fill(a.as_mut());
    let diag = &mut scratch.diag[..k];
    for (j, d) in diag.iter_mut().enumerate() {
        *d = a[(j, j)];
    }
    if let Some(&d) = diag.iter().find(|d| !d.is_finite()) {
        return Err(GpError::Overflow {
            size: k,
            diagonal: d,
        });
    }
    let mean_diag = if k == 0 {
        1.0
    } else {
        diag.iter().sum::<f64>() / k as f64
    };
    let (levels, min_pivot) = match jitter {
        Jitter::Escalate => (&JITTER_LEVELS[..], MIN_PIVOT),
        Jitter::Exact(margin) => (&JITTER_LEVELS[..1], margin * MIN_PIVOT),
    };
    for (li, &level) in levels.iter().enumerate() {
        let jit = level * mean_diag.abs().max(f64::MIN_POSITIVE);
        if li > 0 {
            fill(a.as_mut());
        }
        for j in 0..k {
            a[(j, j)] = diag[j] + jit;
        }
        let ok = with_faer(|| {
            factor::cholesky_in_place(
                a.as_mut(),
                Default::default(),
                Par::Seq,
                MemStack::new(&mut scratch.mem),
                Default::default(),
            )
            .is_ok()
        }) && (0..k).all(|j| {
            let p = a[(j, j)];
            p * p > min_pivot * (diag[j] + jit).abs()
        });
        if ok {
            return Ok(jit);
        }
    }
    Err(GpError::IllConditioned {
        size: k,
        max_jitter: *JITTER_LEVELS.last().unwrap_or(&0.0),
    })
}

/// Writes the lower triangle of `G⁻¹ = L⁻ᵀ L⁻¹` into `out` from the factor
/// in the lower triangle of `l` (faer's blocked inverse, ≈ ⅔k³ flops; the
/// strict upper triangles are neither read nor written).
pub(crate) fn inverse_in_place(
    out: MatMut<'_, f64>,
    l: MatRef<'_, f64>,
    scratch: &mut DenseScratch,
) {
    use faer::linalg::cholesky::llt::inverse;
    with_faer(|| inverse::inverse(out, l, Par::Seq, MemStack::new(&mut scratch.mem)));
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_spd(k: usize, seed: u64) -> Mat<f64> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let x = Mat::<f64>::from_fn(k, k + 3, |_, _| rng.random_range(-1.0..1.0));
        let mut g = &x * x.transpose();
        for i in 0..k {
            g[(i, i)] += 0.1;
        }
        g
    }

    fn assert_close(a: MatRef<'_, f64>, b: MatRef<'_, f64>, tol: f64) {
        assert_eq!(a.nrows(), b.nrows());
        for j in 0..a.ncols() {
            for i in 0..a.nrows() {
                assert!(
                    (a[(i, j)] - b[(i, j)]).abs() < tol,
                    "({i},{j}) {} vs {}",
                    a[(i, j)],
                    b[(i, j)]
                );
            }
        }
    }

    #[test]
    fn append_matches_refactorisation() {
        let k = 40;
        let g = random_spd(k, 1);
        let mut f = CholFactor::factor(g.as_ref().submatrix(0, 0, 10, 10), 4).unwrap();
        let mut scratch = vec![0.0; k];
        for j in 10..k {
            let col: Vec<f64> = (0..j).map(|i| g[(j, i)]).collect();
            f.append(&col, g[(j, j)], &mut scratch).unwrap();
        }
        let fresh = CholFactor::factor(g.as_ref(), k).unwrap();
        assert_close(f.l_ref(), fresh.l_ref(), 1e-10);
    }

    #[test]
    fn remove_first_matches_refactorisation() {
        let k = 30;
        let g = random_spd(k, 2);
        let mut f = CholFactor::factor(g.as_ref(), k).unwrap();
        let mut scratch = vec![0.0; 4 * k];
        for r in 1..5 {
            f.remove_first(&mut scratch);
            let fresh = CholFactor::factor(g.as_ref().submatrix(r, r, k - r, k - r), k).unwrap();
            assert_close(f.l_ref(), fresh.l_ref(), 1e-10);
        }
        assert!(
            (f.log_det()
                - CholFactor::factor(g.as_ref().submatrix(4, 4, k - 4, k - 4), 0)
                    .unwrap()
                    .log_det())
            .abs()
                < 1e-9
        );
    }

    #[test]
    fn remove_any_row_matches_refactorisation() {
        let k = 25;
        let g = random_spd(k, 3);
        let mut scratch = vec![0.0; 4 * k];
        for j in [0, 1, 7, 12, 23, 24] {
            let mut f = CholFactor::factor(g.as_ref(), k).unwrap();
            // β = L⁻¹ R for two right-hand sides, rotated along with the factor
            let r = Mat::<f64>::from_fn(k, 2, |i, c| (i as f64 * 0.37 + c as f64).sin());
            let mut beta = r.clone();
            f.solve_l(beta.as_mut());
            f.remove(j, &mut scratch);
            let t = k - 1 - j;
            for c in 0..2 {
                let mut w = beta[(j, c)];
                for q in 0..t {
                    let (cs, sn) = (scratch[t + 2 * q], scratch[t + 2 * q + 1]);
                    let b = beta[(j + 1 + q, c)];
                    beta[(j + q, c)] = cs * b + sn * w;
                    w = -sn * b + cs * w;
                }
            }
            let keep: Vec<usize> = (0..k).filter(|&i| i != j).collect();
            let gj = Mat::<f64>::from_fn(k - 1, k - 1, |a, b| g[(keep[a], keep[b])]);
            let fresh = CholFactor::factor(gj.as_ref(), k).unwrap();
            assert_close(f.l_ref(), fresh.l_ref(), 1e-10);
            assert_eq!(f.jitter().len(), k - 1);
            let mut bf = Mat::<f64>::from_fn(k - 1, 2, |a, c| r[(keep[a], c)]);
            fresh.solve_l(bf.as_mut());
            assert_close(beta.as_ref().submatrix(0, 0, k - 1, 2), bf.as_ref(), 1e-10);
        }
    }

    #[test]
    fn inverse_matches_solves() {
        let g = random_spd(37, 5);
        let f = CholFactor::factor(g.as_ref(), 37).unwrap();
        let inv = f.inverse_mat();
        let prod = &g * &inv;
        assert_close(prod.as_ref(), Mat::<f64>::identity(37, 37).as_ref(), 1e-9);
    }

    /// The in-place factorisation and inverse read and write only lower
    /// triangles (the MVGP likelihood relies on it): NaN in the strict upper
    /// triangles stays put and does not reach the results, which match the
    /// factor and inverse of a clean copy.
    #[test]
    fn in_place_operations_leave_the_upper_triangle_alone() {
        let k = 70;
        let g = random_spd(k, 9);
        let mut a = Mat::<f64>::from_fn(k, k, |i, j| if i >= j { 0.0 } else { f64::NAN });
        let mut scratch = DenseScratch::new(k);
        let jit = factor_in_place(a.as_mut(), &mut scratch, Jitter::Escalate, |mut a| {
            for j in 0..k {
                for i in j..k {
                    a[(i, j)] = g[(i, j)];
                }
            }
        })
        .unwrap();
        assert_eq!(jit, 0.0);
        let mut inv = Mat::<f64>::from_fn(k, k, |i, j| if i >= j { 0.0 } else { f64::NAN });
        inverse_in_place(inv.as_mut(), a.as_ref(), &mut scratch);
        let clean = CholFactor::factor(g.as_ref(), k).unwrap();
        let reference = clean.inverse_mat();
        for j in 0..k {
            for i in 0..k {
                if i >= j {
                    assert!((a[(i, j)] - clean.l[(i, j)]).abs() < 1e-12);
                    assert!(
                        (inv[(i, j)] - reference[(i, j)]).abs()
                            < 1e-9 * reference[(i, j)].abs().max(1.0)
                    );
                } else {
                    assert!(a[(i, j)].is_nan() && inv[(i, j)].is_nan());
                }
            }
        }
        // and the inverse times G is the identity
        let prod = &reference * &g;
        for j in 0..k {
            for i in 0..k {
                let e = if i == j { 1.0 } else { 0.0 };
                assert!((prod[(i, j)] - e).abs() < 1e-8);
            }
        }
    }

    #[test]
    fn jitter_escalation_is_bounded() {
        // rank-one matrix: needs jitter
        let v = Mat::<f64>::from_fn(5, 1, |i, _| 1.0 + i as f64);
        let g = &v * v.transpose();
        let f = CholFactor::factor(g.as_ref(), 5).unwrap();
        assert!(f.max_jitter() > 0.0);
        // indefinite matrix: typed error
        let mut h = Mat::<f64>::identity(3, 3);
        h[(2, 2)] = -1.0;
        assert!(matches!(
            CholFactor::factor(h.as_ref(), 3),
            Err(GpError::IllConditioned { .. })
        ));
        // an overflowing scale is told as such, not as ill-conditioning,
        // in a factorisation and in an append
        let mut big = Mat::<f64>::identity(3, 3);
        big[(1, 1)] = f64::INFINITY;
        let e = CholFactor::factor(big.as_ref(), 3).unwrap_err();
        assert_eq!(
            e,
            GpError::Overflow {
                size: 3,
                diagonal: f64::INFINITY
            }
        );
        assert!(e.to_string().contains("beyond the range of f64"), "{e}");
        let mut f = CholFactor::factor(Mat::<f64>::identity(2, 2).as_ref(), 4).unwrap();
        let e = f
            .append(&[0.0, 0.0], f64::INFINITY, &mut [0.0; 4])
            .unwrap_err();
        assert!(matches!(e, GpError::Overflow { size: 3, .. }), "{e:?}");
    }

    /// `L Lᵀ` equals `G` plus the recorded jitter on the diagonal.
    fn assert_reproduces(f: &CholFactor, g: MatRef<'_, f64>, tol: f64) {
        let l = f.l();
        let llt = &l * l.transpose();
        for j in 0..f.len() {
            for i in 0..f.len() {
                let want = g[(i, j)] + if i == j { f.jitter()[i] } else { 0.0 };
                assert!((llt[(i, j)] - want).abs() < tol, "({i},{j})");
            }
        }
    }

    /// The escalation takes the first level of [`JITTER_LEVELS`], relative to
    /// the *mean* diagonal, at which every pivot clears `L_jj² > 10⁻¹⁰
    /// (G_jj + jitter)`. `[[2, 2], [2, 2]] ⊕ [8]` (mean diagonal 4) has a
    /// zero pivot: a jitter `j` gives `L_11² = 2j − j²/(2+j)·…≈ 2j`, below
    /// the floor `10⁻¹⁰ (2 + j)` at level 10⁻¹² (`j = 4·10⁻¹²`) and above it
    /// at 10⁻¹⁰ (`j = 4·10⁻¹⁰`).
    #[test]
    fn jitter_is_the_first_level_that_clears_the_pivot_floor() {
        let mut g = Mat::<f64>::zeros(3, 3);
        for (i, j) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
            g[(i, j)] = 2.0;
        }
        g[(2, 2)] = 8.0;
        let f = CholFactor::factor(g.as_ref(), 3).unwrap();
        assert_eq!(f.jitter(), &[4e-10; 3]);
        assert_eq!(f.max_jitter(), 4e-10);
        assert_reproduces(&f, g.as_ref(), 1e-14);
        // a pivot just above the floor needs none, one just below it does:
        // s [[1, 1 − δ], [1 − δ, 1]] has L_11² = s (2δ − δ²), against the
        // floor 10⁻¹⁰ s, whatever the scale s
        for s in [1.0, 1e4] {
            for (delta, jitter) in [(1e-9, 0.0), (2e-11, 1e-10 * s)] {
                let h =
                    Mat::<f64>::from_fn(2, 2, |i, j| s * if i == j { 1.0 } else { 1.0 - delta });
                let f = CholFactor::factor(h.as_ref(), 2).unwrap();
                assert_eq!(f.max_jitter(), jitter, "δ = {delta}, s = {s}");
                assert_reproduces(&f, h.as_ref(), 1e-14 * s);
            }
        }
        // without escalation the same matrix is an error
        assert!(CholFactor::factor_with(g.as_ref(), 3, Jitter::Exact(1.0)).is_err());
    }

    /// A near-duplicate appended online (`G_kk = d(1 − 10⁻⁹)` below the
    /// `sq = d` that the existing row explains): its pivot `G_kk + j − sq ≈
    /// d(level − 10⁻⁹)` is negative at the levels 10⁻¹² and 10⁻¹⁰ and first
    /// clears the floor `10⁻¹⁰ (G_kk + j)` at 10⁻⁸, relative to the new
    /// diagonal entry itself.
    #[test]
    fn an_appended_near_duplicate_gets_the_jitter_of_its_own_diagonal() {
        for d in [0.25, 4.0] {
            let diag = d * (1.0 - 1e-9);
            let g = Mat::<f64>::from_fn(2, 2, |i, j| if i == 1 && j == 1 { diag } else { d });
            let mut f = CholFactor::factor(g.as_ref().submatrix(0, 0, 1, 1), 1).unwrap();
            let mut scratch = vec![0.0; 4];
            f.append(&[d], diag, &mut scratch).unwrap();
            assert_eq!(f.len(), 2);
            assert_eq!(f.jitter(), &[0.0, 1e-8 * diag]);
            assert_reproduces(&f, g.as_ref(), 1e-12 * d);
        }
        // the floor scales with the new diagonal entry: a pivot of 10⁻¹² d
        // clears 10⁻¹⁰ d only with the jitter 10⁻¹⁰ d (d = 10⁴)
        let d = 1e4;
        let diag = d * (1.0 + 1e-12);
        let g = Mat::<f64>::from_fn(2, 2, |i, j| if i == 1 && j == 1 { diag } else { d });
        let mut f = CholFactor::factor(g.as_ref().submatrix(0, 0, 1, 1), 1).unwrap();
        let mut scratch = vec![0.0; 4];
        f.append(&[d], diag, &mut scratch).unwrap();
        assert_eq!(f.jitter(), &[0.0, 1e-10 * diag]);
        assert_reproduces(&f, g.as_ref(), 1e-12 * d);
        // an appended entry that no jitter can make positive is an error
        let mut f = CholFactor::factor(Mat::<f64>::identity(1, 1).as_ref(), 1).unwrap();
        let mut scratch = vec![0.0; 4];
        assert!(matches!(
            f.append(&[2.0], 1.0, &mut scratch),
            Err(GpError::IllConditioned { size: 2, .. })
        ));
        assert_eq!(f.len(), 1);
    }

    /// The small API: emptiness, triangular solves against dense ones, and
    /// removing the only row.
    #[test]
    fn solves_lengths_and_removal() {
        let g = random_spd(6, 9);
        let mut f = CholFactor::factor(g.as_ref(), 6).unwrap();
        assert!(!f.is_empty() && CholFactor::default().is_empty());
        let l = f.l();
        let b = DMatrix::from_fn(6, 2, |i, c| (i as f64 + 0.5 * c as f64).cos());
        let mut x = b.clone();
        f.solve_l_in_place(&mut x);
        assert!((&l * &x - &b).abs().max() < 1e-12);
        let mut y = b.clone();
        f.solve_lt_in_place(&mut y);
        assert!((l.transpose() * &y - &b).abs().max() < 1e-12);
        let mut scratch = vec![0.0; 24];
        let mut one = CholFactor::factor(g.as_ref().submatrix(0, 0, 1, 1), 1).unwrap();
        one.remove_first(&mut scratch);
        assert!(one.is_empty());
        one.remove_first(&mut scratch);
        assert_eq!(one.len(), 0);
        f.remove_first(&mut scratch);
        assert_eq!(f.len(), 5);
    }
}
