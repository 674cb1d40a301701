//! A Cholesky factor `L Lᵀ = G` of a Gram matrix that grows by one row per
//! observation (O(k²)) and drops its oldest row (O(k²) rank-one update).

use crate::error::GpError;
use faer::linalg::triangular_solve::{
    solve_lower_triangular_in_place, solve_upper_triangular_in_place,
};
use faer::{Mat, MatMut, MatRef, Par};

/// Clears the upper halves of the AVX registers (`vzeroupper`).
///
/// faer's SIMD kernels return with the upper register state dirty; on many
/// x86 CPUs every later legacy-SSE instruction (libm's `exp` entry point,
/// scalar code compiled for the x86-64 baseline) then pays a transition
/// penalty. Measured here: a 200 × 200 RBF Gram matrix took 3.3 ms after a
/// faer call and 0.30 ms after this. Called after every faer operation on
/// hot paths.
#[inline]
pub fn clear_simd_state() {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx") {
            // SAFETY: the `avx` feature was detected at run time.
            unsafe { std::arch::x86_64::_mm256_zeroupper() }
        }
    }
}

/// Relative jitter levels tried, in order, when a factorisation fails: the
/// jitter added to the diagonal is `level × mean(diag G)`.
pub const JITTER_LEVELS: [f64; 6] = [0.0, 1e-12, 1e-10, 1e-8, 1e-7, 1e-6];

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

impl CholFactor {
    /// Factorises `G` (only the lower triangle is read), escalating jitter
    /// through [`JITTER_LEVELS`]; fails with [`GpError::IllConditioned`].
    pub fn factor(g: MatRef<'_, f64>, capacity: usize) -> Result<Self, GpError> {
        Self::factor_impl(g, capacity, true)
    }

    /// [`factor`](Self::factor) without logging the jitter (used inside
    /// optimisers, which evaluate many nearby matrices).
    pub fn factor_quiet(g: MatRef<'_, f64>, capacity: usize) -> Result<Self, GpError> {
        Self::factor_impl(g, capacity, false)
    }

    fn factor_impl(g: MatRef<'_, f64>, capacity: usize, log_jitter: bool) -> Result<Self, GpError> {
        let k = g.nrows();
        let cap = capacity.max(k).max(1);
        let mean_diag = if k == 0 {
            1.0
        } else {
            (0..k).map(|i| g[(i, i)]).sum::<f64>() / k as f64
        };
        let mut l = Mat::<f64>::zeros(cap, cap);
        for &level in JITTER_LEVELS.iter() {
            let jit = level * mean_diag.abs().max(f64::MIN_POSITIVE);
            {
                let mut sub = l.as_mut().submatrix_mut(0, 0, k, k);
                for j in 0..k {
                    for i in j..k {
                        sub[(i, j)] = g[(i, j)];
                    }
                    sub[(j, j)] += jit;
                }
            }
            let ok = cholesky_in_place(l.as_mut().submatrix_mut(0, 0, k, k));
            clear_simd_state();
            if ok {
                if level > 0.0 && log_jitter {
                    log::warn!("Gram matrix (k = {k}) needed jitter {jit:.3e} ({level:e} × mean diagonal) to factorise");
                }
                // clear the strict upper triangle
                for j in 0..k {
                    for i in 0..j {
                        l[(i, j)] = 0.0;
                    }
                }
                return Ok(Self {
                    l,
                    k,
                    jitter: vec![jit; k],
                });
            }
        }
        Err(GpError::IllConditioned {
            size: k,
            max_jitter: *JITTER_LEVELS.last().unwrap_or(&0.0),
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

    /// The factor `L` (`k × k`).
    pub fn l(&self) -> MatRef<'_, f64> {
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

    /// Solves `L X = B` in place (`B` has `k` rows).
    #[track_caller]
    pub fn solve_l_in_place(&self, rhs: MatMut<'_, f64>) {
        solve_lower_triangular_in_place(self.l(), rhs, Par::Seq);
        clear_simd_state();
    }

    /// Solves `Lᵀ X = B` in place.
    #[track_caller]
    pub fn solve_lt_in_place(&self, rhs: MatMut<'_, f64>) {
        solve_upper_triangular_in_place(self.l().transpose(), rhs, Par::Seq);
        clear_simd_state();
    }

    /// `G⁻¹` (full symmetric `k × k`) by faer's blocked inverse of the
    /// factor (≈ ⅔k³ flops).
    pub fn inverse(&self) -> Mat<f64> {
        use faer::dyn_stack::{MemBuffer, MemStack};
        use faer::linalg::cholesky::llt::inverse;
        let k = self.k;
        let mut out = Mat::<f64>::zeros(k, k);
        let mut mem = MemBuffer::new(inverse::inverse_scratch::<f64>(k, Par::Seq));
        inverse::inverse(out.as_mut(), self.l(), Par::Seq, MemStack::new(&mut mem));
        clear_simd_state();
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
        l.as_mut()
            .submatrix_mut(0, 0, self.k, self.k)
            .copy_from(self.l());
        self.l = l;
    }

    /// Appends one row: `g_new[i] = G[k, i]` for the existing `i < k`, and the
    /// new diagonal `G[k, k]`. Cost: one triangular solve, O(k²).
    ///
    /// If the new pivot is not positive (e.g. a duplicate point with tiny
    /// noise), jitter escalates through [`JITTER_LEVELS`] relative to
    /// `diag` for this entry only.
    pub fn append(&mut self, g_new: &[f64], diag: f64, scratch: &mut [f64]) -> Result<(), GpError> {
        let k = self.k;
        assert_eq!(g_new.len(), k, "g_new length");
        self.ensure_capacity(k + 1);
        let row = &mut scratch[..k];
        row.copy_from_slice(g_new);
        {
            let rhs = faer::MatMut::from_column_major_slice_mut(row, k, 1);
            solve_lower_triangular_in_place(self.l(), rhs, Par::Seq);
        }
        clear_simd_state();
        let sq: f64 = row.iter().map(|v| v * v).sum();
        for &level in JITTER_LEVELS.iter() {
            let jit = level * diag.abs().max(f64::MIN_POSITIVE);
            let d2 = diag + jit - sq;
            if d2 > 0.0 && d2.is_finite() && d2 > 1e-14 * (diag + jit).abs() {
                if level > 0.0 {
                    log::warn!(
                        "online update (k = {}) needed jitter {jit:.3e} on the new diagonal entry",
                        k + 1
                    );
                }
                for (j, v) in row.iter().enumerate() {
                    self.l[(k, j)] = *v;
                }
                self.l[(k, k)] = d2.sqrt();
                for i in 0..k {
                    self.l[(i, k)] = 0.0;
                }
                self.jitter.push(jit);
                self.k += 1;
                return Ok(());
            }
        }
        Err(GpError::IllConditioned {
            size: k + 1,
            max_jitter: *JITTER_LEVELS.last().unwrap_or(&0.0),
        })
    }

    /// Removes the first row and column of `G`: with
    /// `L = [l11 0; l21 L22]`, the new factor is `chol(L22 L22ᵀ + l21 l21ᵀ)`,
    /// a rank-one update of `L22`, O(k²).
    pub fn remove_first(&mut self, scratch: &mut [f64]) {
        let k = self.k;
        if k == 0 {
            return;
        }
        let v = &mut scratch[..k - 1];
        for i in 1..k {
            v[i - 1] = self.l[(i, 0)];
        }
        // shift L22 to the top-left corner, column by column (column-major)
        for j in 1..k {
            for i in j..k {
                self.l[(i - 1, j - 1)] = self.l[(i, j)];
            }
        }
        let k1 = k - 1;
        for i in 0..k {
            self.l[(k1, i)] = 0.0;
            self.l[(i, k1)] = 0.0;
        }
        // rank-one update L L^T + v v^T
        for c in 0..k1 {
            let lcc = self.l[(c, c)];
            let r = (lcc * lcc + v[c] * v[c]).sqrt();
            let cs = r / lcc;
            let sn = v[c] / lcc;
            self.l[(c, c)] = r;
            for i in c + 1..k1 {
                let lic = (self.l[(i, c)] + sn * v[i]) / cs;
                self.l[(i, c)] = lic;
                v[i] = cs * v[i] - sn * lic;
            }
        }
        self.jitter.remove(0);
        self.k = k1;
    }
}

/// Unblocked-by-column Cholesky in place (lower triangle); false if not PD.
/// Delegates to faer's blocked LLᵀ.
fn cholesky_in_place(a: MatMut<'_, f64>) -> bool {
    use faer::dyn_stack::{MemBuffer, MemStack};
    use faer::linalg::cholesky::llt::factor;
    let n = a.nrows();
    let req = factor::cholesky_in_place_scratch::<f64>(n, Par::Seq, Default::default());
    let mut mem = MemBuffer::new(req);
    let stack = MemStack::new(&mut mem);
    factor::cholesky_in_place(a, Default::default(), Par::Seq, stack, Default::default()).is_ok()
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
        assert_close(f.l(), fresh.l(), 1e-10);
    }

    #[test]
    fn remove_first_matches_refactorisation() {
        let k = 30;
        let g = random_spd(k, 2);
        let mut f = CholFactor::factor(g.as_ref(), k).unwrap();
        let mut scratch = vec![0.0; k];
        for r in 1..5 {
            f.remove_first(&mut scratch);
            let fresh = CholFactor::factor(g.as_ref().submatrix(r, r, k - r, k - r), k).unwrap();
            assert_close(f.l(), fresh.l(), 1e-10);
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
    fn inverse_matches_solves() {
        let g = random_spd(37, 5);
        let f = CholFactor::factor(g.as_ref(), 37).unwrap();
        let inv = f.inverse();
        let prod = &g * &inv;
        assert_close(prod.as_ref(), Mat::<f64>::identity(37, 37).as_ref(), 1e-9);
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
    }
}
