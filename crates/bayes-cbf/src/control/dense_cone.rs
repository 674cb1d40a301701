//! A dense interior-point method for the small conic programs of the safety
//! filter: Clarabel's homogeneous embedding (Goulart & Chen, *Clarabel: an
//! interior-point solver for conic programs with quadratic objectives*,
//! 2024) with Nesterov–Todd scaling and Mehrotra's predictor–corrector,
//! written for programs of a few variables and a few dozen constraint rows.
//!
//! ```text
//! min  ½ xᵀPx + qᵀx   s.t.  Ax + s = b,  s ∈ K = K₁ × … × K_c
//! ```
//!
//! with each `K_i` a nonnegative orthant or a second-order cone
//! `{(t, v) : t ≥ ‖v‖}`. The iterate is `(x, s, z, τ, κ)` with the central
//! path of the embedding
//!
//! ```text
//! Px + Aᵀz + qτ = 0,   Ax + s − bτ = 0,   qᵀx + bᵀz + κ + xᵀPx/τ = 0,
//! s ∘ z = μe,   τκ = μ,
//! ```
//!
//! a solution at `τ > 0, κ = 0` (divide by τ), and a certificate of
//! infeasibility at `τ = 0, κ > 0` (`bᵀz < 0` with `Aᵀz ≈ 0`: the primal is
//! infeasible). Each Newton step solves the quasi-definite system
//! `[P Aᵀ; A −H] [Δx; Δz] = [r_x; r_z]` twice (once for the constant
//! right-hand side `[−q; b]` that carries `Δτ`), where `H = WᵀW` is the NT
//! scaling, block diagonal over the cones. `Δz` is eliminated:
//! `(P + AᵀH⁻¹A) Δx = r_x + AᵀH⁻¹r_z` is an `n × n` Cholesky solve and
//! `Δz = H⁻¹(AΔx − r_z)`. Once `μ` is below 10⁻⁶ of its start, where `H`
//! grows ill-conditioned, each solve is followed by up to three steps of
//! iterative refinement against the full system.
//!
//! Why not Clarabel here: on the control step's programs (3 variables, 16
//! rows) Clarabel spends most of its time in sparse bookkeeping, its
//! timers and hashing, 60 % of a budgeted 200-point stream step. The
//! iteration here is the same (same start, centring `σ = (1 − α)³`, step
//! fraction 0.99, tolerances and status tests), so it needs about as many
//! iterations, each a few microseconds cheaper.
//! [`ConeProgram`](super::socp::ConeProgram) falls back to Clarabel
//! whenever this solver neither converges to full accuracy nor certifies
//! infeasibility.

/// One cone of the product `K`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Cone {
    /// `{s : s ≥ 0}` of this dimension.
    NonNegative(usize),
    /// `{(t, v) : t ≥ ‖v‖}` of this dimension (`1 + dim v`).
    SecondOrder(usize),
}

impl Cone {
    fn dim(self) -> usize {
        match self {
            Self::NonNegative(d) | Self::SecondOrder(d) => d,
        }
    }
    /// Degree of the cone's barrier (`d` for the orthant, 1 for a SOC).
    fn degree(self) -> usize {
        match self {
            Self::NonNegative(d) => d,
            Self::SecondOrder(_) => 1,
        }
    }
}

/// Outcome of a solve.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum DenseStatus {
    /// Converged to the full tolerances.
    Solved,
    /// A certificate of primal infeasibility (`z` holds it).
    PrimalInfeasible,
    /// A certificate of dual infeasibility (`x` holds it).
    DualInfeasible,
    /// No convergence: iteration limit, slow progress or a numerical fault.
    Failed,
}

/// Tolerances (Clarabel's defaults).
const TOL_GAP_ABS: f64 = 1e-8;
const TOL_GAP_REL: f64 = 1e-8;
const TOL_FEAS: f64 = 1e-8;
const TOL_INFEAS_ABS: f64 = 1e-8;
const TOL_INFEAS_REL: f64 = 1e-8;
const TOL_KTRATIO: f64 = 1e-6;
const MAX_STEP_FRACTION: f64 = 0.99;
const MIN_TERMINATE_STEP: f64 = 1e-4;
const MAX_ITER: usize = 100;
const REFINE_STEPS: usize = 3;
/// Refinement starts once `μ` has fallen below this fraction of its
/// initial value: the elimination of `z` loses accuracy only as `H` becomes
/// ill-conditioned near the solution.
const REFINE_BELOW_MU: f64 = 1e-6;
const REFINE_REL_TOL: f64 = 1e-13;
const REFINE_ABS_TOL: f64 = 1e-12;

/// The iterate `(x, s, z, τ, κ)` (also used for steps and right-hand sides).
#[derive(Debug, Clone)]
struct Point {
    x: Vec<f64>,
    s: Vec<f64>,
    z: Vec<f64>,
    tau: f64,
    kappa: f64,
}

impl Point {
    fn new(n: usize, m: usize) -> Self {
        Self {
            x: vec![0.0; n],
            s: vec![0.0; m],
            z: vec![0.0; m],
            tau: 1.0,
            kappa: 1.0,
        }
    }
}

/// Residuals and the measures of convergence of one iterate.
#[derive(Debug, Clone, Default)]
struct Measures {
    dot_qx: f64,
    dot_bz: f64,
    dot_sz: f64,
    dot_xpx: f64,
    /// `r_τ = qᵀx + bᵀz + κ + xᵀPx/τ`.
    rtau: f64,
    res_primal: f64,
    res_dual: f64,
    res_primal_inf: f64,
    res_dual_inf: f64,
    gap_abs: f64,
    gap_rel: f64,
    ktratio: f64,
}

/// A dense conic solver of fixed dimensions; every buffer is allocated at
/// construction, so a solve allocates nothing.
#[derive(Debug, Clone)]
pub(crate) struct DenseConeSolver {
    n: usize,
    m: usize,
    /// The cones and their scaling.
    sc: Scaling,
    degree: usize,
    /// `A`, row-major `m × n`.
    pub(crate) a: Vec<f64>,
    /// `P`, row-major `n × n`, both triangles.
    pub(crate) p: Vec<f64>,
    pub(crate) q: Vec<f64>,
    pub(crate) b: Vec<f64>,
    v: Point,
    step: Point,
    rhs: Point,
    /// `r_x`, `r_z`, `Px`, `−Aᵀz`, `Ax + s`.
    rx: Vec<f64>,
    rz: Vec<f64>,
    px: Vec<f64>,
    rx_inf: Vec<f64>,
    rz_inf: Vec<f64>,
    meas: Measures,
    prev_meas: Measures,
    /// `λ = Wz`.
    lambda: Vec<f64>,
    /// `Aᵀ` (row-major `n × m`, refreshed at each solve).
    at: Vec<f64>,
    /// `Gᵀ = (H⁻¹A)ᵀ` (row-major `n × m`) and the Cholesky factor of
    /// `P + AᵀG` (lower triangle of a row-major `n × n`).
    gt: Vec<f64>,
    chol: Vec<f64>,
    x1: Vec<f64>,
    z1: Vec<f64>,
    x2: Vec<f64>,
    z2: Vec<f64>,
    /// Scratch of length `n + m` (right-hand side, solution, residual,
    /// correction) and `m`.
    rhs_full: Vec<f64>,
    sol_full: Vec<f64>,
    res_full: Vec<f64>,
    cor_full: Vec<f64>,
    ds_const: Vec<f64>,
    work_m: Vec<f64>,
    work_m2: Vec<f64>,
    work_n: Vec<f64>,
    /// Refinement steps allowed in the current iteration.
    refine: usize,
    /// Interior-point iterations of the last solve.
    pub(crate) iterations: usize,
}

impl DenseConeSolver {
    /// A solver for `n` variables and the cones `cones` (rows in order).
    pub(crate) fn new(n: usize, cones: &[Cone]) -> Self {
        let mut offset = 0;
        let mut list = Vec::with_capacity(cones.len());
        for &c in cones {
            list.push((c, offset));
            offset += c.dim();
        }
        let m = offset;
        let nm = n + m;
        Self {
            n,
            m,
            degree: cones.iter().map(|c| c.degree()).sum(),
            sc: Scaling {
                cones: list,
                eta: vec![0.0; cones.len()],
                wbar: vec![0.0; m],
            },
            a: vec![0.0; m * n],
            p: vec![0.0; n * n],
            q: vec![0.0; n],
            b: vec![0.0; m],
            v: Point::new(n, m),
            step: Point::new(n, m),
            rhs: Point::new(n, m),
            rx: vec![0.0; n],
            rz: vec![0.0; m],
            px: vec![0.0; n],
            rx_inf: vec![0.0; n],
            rz_inf: vec![0.0; m],
            meas: Measures::default(),
            prev_meas: Measures::default(),
            lambda: vec![0.0; m],
            at: vec![0.0; n * m],
            gt: vec![0.0; n * m],
            chol: vec![0.0; n * n],
            x1: vec![0.0; n],
            z1: vec![0.0; m],
            x2: vec![0.0; n],
            z2: vec![0.0; m],
            rhs_full: vec![0.0; nm],
            sol_full: vec![0.0; nm],
            res_full: vec![0.0; nm],
            cor_full: vec![0.0; nm],
            ds_const: vec![0.0; m],
            work_m: vec![0.0; m],
            work_m2: vec![0.0; m],
            work_n: vec![0.0; n],
            refine: 0,
            iterations: 0,
        }
    }

    /// The primal solution `x` (or the certificate of dual infeasibility).
    pub(crate) fn x(&self) -> &[f64] {
        &self.v.x
    }
    /// The slack `s`.
    pub(crate) fn s(&self) -> &[f64] {
        &self.v.s
    }
    /// The dual `z` (or the certificate of primal infeasibility).
    pub(crate) fn z(&self) -> &[f64] {
        &self.v.z
    }

    /// Solves with the current `P, q, A, b`.
    pub(crate) fn solve(&mut self) -> DenseStatus {
        self.iterations = 0;
        let (n, m) = (self.n, self.m);
        for r in 0..m {
            for j in 0..n {
                self.at[j * m + r] = self.a[r * n + j];
            }
        }
        if !self.initial_point() {
            return DenseStatus::Failed;
        }
        let mut status = None;
        let mut alpha;
        let mut iter = 0;
        let mut mu0 = f64::NAN;
        loop {
            self.update_residuals();
            let mu = (self.meas.dot_sz + self.v.tau * self.v.kappa) / (self.degree + 1) as f64;
            if iter == 0 {
                mu0 = mu;
            }
            self.refine = if mu < REFINE_BELOW_MU * mu0 {
                REFINE_STEPS
            } else {
                0
            };
            self.update_measures();
            if let Some(s) = self.check_termination(iter) {
                status = Some(s);
                break;
            }
            if !mu.is_finite() || !self.update_scaling() {
                break;
            }
            iter += 1;
            if !self.factor_kkt() {
                break;
            }
            // constant right-hand side [−q; b] carries Δτ
            if !self.solve_constant() {
                break;
            }
            // affine (predictor) direction
            self.affine_rhs();
            if !self.solve_step(false) {
                break;
            }
            alpha = self.step_length(false);
            let sigma = (1.0 - alpha).powi(3);
            let scale = if iter > 1 { 1.0 } else { alpha };
            // combined (corrector and centring) direction
            self.combined_rhs(sigma, mu, scale);
            if !self.solve_step(true) {
                break;
            }
            alpha = self.step_length(true);
            if alpha <= MIN_TERMINATE_STEP {
                break;
            }
            self.prev_meas = self.meas.clone();
            self.add_step(alpha);
        }
        self.iterations = iter;
        match status {
            Some(DenseStatus::Solved) => {
                let inv = 1.0 / self.v.tau;
                self.scale_point(inv);
                DenseStatus::Solved
            }
            Some(s @ (DenseStatus::PrimalInfeasible | DenseStatus::DualInfeasible)) => {
                let inv = 1.0 / self.v.kappa;
                self.scale_point(inv);
                s
            }
            _ => DenseStatus::Failed,
        }
    }

    /// Scales `x, s, z` by `f` (`1/τ` for a solution, `1/κ` for a
    /// certificate); `τ, κ` are not read after a solve.
    fn scale_point(&mut self, f: f64) {
        self.v.x.iter_mut().for_each(|x| *x *= f);
        self.v.s.iter_mut().for_each(|x| *x *= f);
        self.v.z.iter_mut().for_each(|x| *x *= f);
    }

    /// Clarabel's start for symmetric cones: with `H = I`, solve
    /// `[P Aᵀ; A −I][x; z] = [−q; b]`, `s = −z` (for `P = 0`:
    /// `[x; −s]` from `[0; b]` and `z` from `[−q; 0]`), then shift `s` and
    /// `z` into the interior.
    fn initial_point(&mut self) -> bool {
        let (n, m) = (self.n, self.m);
        self.set_identity_scaling();
        if !self.factor_kkt() {
            return false;
        }
        if self.p.iter().all(|&v| v == 0.0) {
            self.rhs_full[..n].fill(0.0);
            self.rhs_full[n..].copy_from_slice(&self.b);
            if !self.solve_kkt() {
                return false;
            }
            self.v.x.copy_from_slice(&self.sol_full[..n]);
            for i in 0..m {
                self.v.s[i] = -self.sol_full[n + i];
            }
            for i in 0..n {
                self.rhs_full[i] = -self.q[i];
            }
            self.rhs_full[n..].fill(0.0);
            if !self.solve_kkt() {
                return false;
            }
            self.v.z.copy_from_slice(&self.sol_full[n..]);
        } else {
            for i in 0..n {
                self.rhs_full[i] = -self.q[i];
            }
            self.rhs_full[n..].copy_from_slice(&self.b);
            if !self.solve_kkt() {
                return false;
            }
            self.v.x.copy_from_slice(&self.sol_full[..n]);
            self.v.z.copy_from_slice(&self.sol_full[n..]);
            for i in 0..m {
                self.v.s[i] = -self.v.z[i];
            }
        }
        let mut s = std::mem::take(&mut self.v.s);
        let mut z = std::mem::take(&mut self.v.z);
        self.shift_to_interior(&mut s);
        self.shift_to_interior(&mut z);
        self.v.s = s;
        self.v.z = z;
        self.v.tau = 1.0;
        self.v.kappa = 1.0;
        true
    }

    /// Adds `α e` to every cone so that the smallest margin becomes
    /// `max(1, 0.1 · (sum of the positive margins) / degree)`.
    fn shift_to_interior(&self, v: &mut [f64]) {
        let mut min_margin = f64::INFINITY;
        let mut pos = 0.0;
        for &(c, o) in &self.sc.cones {
            match c {
                Cone::NonNegative(d) => {
                    for &x in &v[o..o + d] {
                        min_margin = min_margin.min(x);
                        pos += x.max(0.0);
                    }
                }
                Cone::SecondOrder(d) => {
                    let margin = v[o] - norm(&v[o + 1..o + d]);
                    min_margin = min_margin.min(margin);
                    pos += margin.max(0.0);
                }
            }
        }
        let target = (0.1 * pos / self.degree.max(1) as f64).max(1.0);
        let shift = if min_margin < target {
            target - min_margin
        } else {
            0.0
        };
        for &(c, o) in &self.sc.cones {
            match c {
                Cone::NonNegative(d) => v[o..o + d].iter_mut().for_each(|x| *x += shift),
                Cone::SecondOrder(_) => v[o] += shift,
            }
        }
    }

    fn set_identity_scaling(&mut self) {
        for (k, &(c, o)) in self.sc.cones.iter().enumerate() {
            self.sc.eta[k] = 1.0;
            match c {
                Cone::NonNegative(d) => self.sc.wbar[o..o + d].fill(1.0),
                Cone::SecondOrder(d) => {
                    self.sc.wbar[o..o + d].fill(0.0);
                    self.sc.wbar[o] = 1.0;
                }
            }
        }
    }

    /// `r_x = −Px − Aᵀz − qτ`, `r_z = Ax + s − bτ`,
    /// `r_τ = qᵀx + bᵀz + κ + xᵀPx/τ`.
    fn update_residuals(&mut self) {
        let (n, m) = (self.n, self.m);
        let v = &self.v;
        for i in 0..n {
            self.px[i] = dot(&self.p[i * n..(i + 1) * n], &v.x);
            self.rx_inf[i] = -dot(&self.at[i * m..(i + 1) * m], &v.z);
        }
        for r in 0..m {
            self.rz_inf[r] = dot(&self.a[r * n..(r + 1) * n], &v.x) + v.s[r];
        }
        for i in 0..n {
            self.rx[i] = -self.px[i] - v.tau * self.q[i] + self.rx_inf[i];
        }
        for r in 0..m {
            self.rz[r] = self.rz_inf[r] - v.tau * self.b[r];
        }
        self.meas.dot_qx = dot(&self.q, &v.x);
        self.meas.dot_bz = dot(&self.b, &v.z);
        self.meas.dot_sz = dot(&v.s, &v.z);
        self.meas.dot_xpx = dot(&v.x, &self.px);
        self.meas.rtau = self.meas.dot_qx + self.meas.dot_bz + v.kappa + self.meas.dot_xpx / v.tau;
    }

    /// Clarabel's measures of convergence (no equilibration).
    fn update_measures(&mut self) {
        let v = &self.v;
        let tau_inv = 1.0 / v.tau;
        let mm = &mut self.meas;
        let half_xpx = mm.dot_xpx * tau_inv * tau_inv / 2.0;
        let cost_primal = mm.dot_qx * tau_inv + half_xpx;
        let cost_dual = -mm.dot_bz * tau_inv - half_xpx;
        let (nx, nz, ns) = (norm(&v.x), norm(&v.z), norm(&v.s));
        mm.res_primal_inf = norm(&self.rx_inf) / nz.max(1.0);
        mm.res_dual_inf =
            (norm(&self.px) / nx.max(1.0)).max(norm(&self.rz_inf) / (nx + ns).max(1.0));
        let (nx, nz, ns) = (nx * tau_inv, nz * tau_inv, ns * tau_inv);
        mm.res_primal = norm(&self.rz) * tau_inv / (norm(&self.b) + nx + ns).max(1.0);
        mm.res_dual = norm(&self.rx) * tau_inv / (norm(&self.q) + nx + nz).max(1.0);
        mm.gap_abs = (cost_primal - cost_dual).abs();
        mm.gap_rel = mm.gap_abs / cost_primal.abs().min(cost_dual.abs()).max(1.0);
        mm.ktratio = v.kappa * tau_inv;
    }

    fn check_termination(&self, iter: usize) -> Option<DenseStatus> {
        let mm = &self.meas;
        let finite = [mm.res_primal, mm.res_dual, mm.gap_abs, mm.ktratio]
            .iter()
            .all(|x| x.is_finite());
        if !finite {
            return Some(DenseStatus::Failed);
        }
        if mm.ktratio <= 1.0
            && (mm.gap_abs < TOL_GAP_ABS || mm.gap_rel < TOL_GAP_REL)
            && mm.res_primal < TOL_FEAS
            && mm.res_dual < TOL_FEAS
        {
            return Some(DenseStatus::Solved);
        }
        if mm.ktratio > 1000.0 / TOL_KTRATIO {
            if mm.dot_bz < -TOL_INFEAS_ABS && mm.res_primal_inf < -TOL_INFEAS_REL * mm.dot_bz {
                return Some(DenseStatus::PrimalInfeasible);
            }
            if mm.dot_qx < -TOL_INFEAS_ABS && mm.res_dual_inf < -TOL_INFEAS_REL * mm.dot_qx {
                return Some(DenseStatus::DualInfeasible);
            }
        }
        let p = &self.prev_meas;
        if iter > 1 && (mm.res_dual > p.res_dual || mm.res_primal > p.res_primal) {
            let stalled = mm.ktratio < 100.0 * f64::EPSILON
                && (p.gap_abs < TOL_GAP_ABS || p.gap_rel < TOL_GAP_REL);
            let diverging = mm.ktratio < 1.0
                && ((mm.res_dual > 100.0 * TOL_FEAS && mm.res_dual > 100.0 * p.res_dual)
                    || (mm.res_primal > 100.0 * TOL_FEAS && mm.res_primal > 100.0 * p.res_primal));
            if stalled || diverging {
                return Some(DenseStatus::Failed);
            }
        }
        if iter >= MAX_ITER {
            return Some(DenseStatus::Failed);
        }
        None
    }

    /// Nesterov–Todd scaling of every cone at `(s, z)`; false if either is
    /// not interior.
    fn update_scaling(&mut self) -> bool {
        for (k, &(c, o)) in self.sc.cones.iter().enumerate() {
            let s = &self.v.s[o..o + c.dim()];
            let z = &self.v.z[o..o + c.dim()];
            match c {
                Cone::NonNegative(d) => {
                    for i in 0..d {
                        if !(s[i] > 0.0 && z[i] > 0.0) {
                            return false;
                        }
                        self.sc.wbar[o + i] = (s[i] / z[i]).sqrt();
                        self.lambda[o + i] = (s[i] * z[i]).sqrt();
                    }
                    self.sc.eta[k] = 1.0;
                }
                Cone::SecondOrder(d) => {
                    let ss = soc_residual(s);
                    let zz = soc_residual(z);
                    if !(ss > 0.0 && zz > 0.0 && s[0] > 0.0 && z[0] > 0.0) {
                        return false;
                    }
                    let (sn, zn) = (ss.sqrt(), zz.sqrt());
                    // γ² = (1 + s̄ᵀz̄)/2 with s̄ = s/‖s‖_J, z̄ = z/‖z‖_J
                    let sz = dot(s, z) / (sn * zn);
                    let gamma = ((1.0 + sz) / 2.0).sqrt();
                    let w = &mut self.sc.wbar[o..o + d];
                    w[0] = (s[0] / sn + z[0] / zn) / (2.0 * gamma);
                    for i in 1..d {
                        w[i] = (s[i] / sn - z[i] / zn) / (2.0 * gamma);
                    }
                    self.sc.eta[k] = (sn / zn).sqrt();
                    // λ = W z
                    let mut lam = std::mem::take(&mut self.lambda);
                    soc_w_mul(
                        self.sc.eta[k],
                        &self.sc.wbar[o..o + d],
                        z,
                        &mut lam[o..o + d],
                        false,
                    );
                    self.lambda = lam;
                }
            }
        }
        true
    }

    /// Factorises the KKT matrix `K = [P Aᵀ; A −H]` by eliminating `z`
    /// (`H` is block diagonal and positive definite at interior points):
    /// `M = P + AᵀH⁻¹A = LLᵀ`, with `G = H⁻¹A` kept. False if `M` is not
    /// numerically positive definite.
    fn factor_kkt(&mut self) -> bool {
        let (n, m) = (self.n, self.m);
        // Gᵀ = (H⁻¹A)ᵀ, column of A by column, cone by cone
        for j in 0..n {
            let col = &self.at[j * m..(j + 1) * m];
            let gcol = &mut self.gt[j * m..(j + 1) * m];
            self.sc.apply(hinv_mul, col, gcol);
        }
        let l = &mut self.chol;
        for i in 0..n {
            for j in 0..=i {
                l[i * n + j] = self.p[i * n + j]
                    + dot(&self.at[i * m..(i + 1) * m], &self.gt[j * m..(j + 1) * m]);
            }
        }
        let maxdiag = (0..n).map(|i| l[i * n + i].abs()).fold(0.0, f64::max);
        let eps = f64::EPSILON * maxdiag;
        // in-place Cholesky on the lower triangle
        for j in 0..n {
            let mut d = l[j * n + j] + eps;
            for t in 0..j {
                d -= l[j * n + t] * l[j * n + t];
            }
            if !(d > 0.0 && d.is_finite()) {
                return false;
            }
            let d = d.sqrt();
            l[j * n + j] = d;
            for i in j + 1..n {
                let mut v = l[i * n + j];
                for t in 0..j {
                    v -= l[i * n + t] * l[j * n + t];
                }
                l[i * n + j] = v / d;
            }
        }
        true
    }

    /// `[x; z] = K⁻¹ [r₁; r₂]` for `rhs_full = [r₁; r₂]` into `sol_full`:
    /// `x = M⁻¹(r₁ + Aᵀ H⁻¹ r₂)`, `z = H⁻¹(Ax − r₂)`, then iterative
    /// refinement against `K` (it corrects the rounding of the elimination
    /// when `H` is ill-conditioned near the solution).
    fn solve_kkt(&mut self) -> bool {
        let (n, m) = (self.n, self.m);
        let rhs_norm = if self.refine > 0 {
            self.rhs_full.iter().fold(0.0f64, |a, &x| a.max(x.abs()))
        } else {
            0.0
        };
        self.res_full.copy_from_slice(&self.rhs_full);
        self.sol_full.fill(0.0);
        for step in 0..=self.refine {
            if step > 0 {
                // residual e = rhs − K sol
                let mut err = 0.0f64;
                for i in 0..n {
                    let v = dot(&self.p[i * n..(i + 1) * n], &self.sol_full[..n])
                        + dot(&self.at[i * m..(i + 1) * m], &self.sol_full[n..]);
                    self.res_full[i] = self.rhs_full[i] - v;
                    err = err.max(self.res_full[i].abs());
                }
                self.sc.apply(h_mul, &self.sol_full[n..], &mut self.work_m);
                for r in 0..m {
                    let v = dot(&self.a[r * n..(r + 1) * n], &self.sol_full[..n]) - self.work_m[r];
                    self.res_full[n + r] = self.rhs_full[n + r] - v;
                    err = err.max(self.res_full[n + r].abs());
                }
                if err <= REFINE_ABS_TOL + REFINE_REL_TOL * rhs_norm {
                    break;
                }
            }
            // correction from the residual
            self.sc
                .apply(hinv_mul, &self.res_full[n..], &mut self.work_m);
            for i in 0..n {
                self.cor_full[i] =
                    self.res_full[i] + dot(&self.at[i * m..(i + 1) * m], &self.work_m);
            }
            chol_solve(&self.chol, n, &mut self.cor_full[..n]);
            for r in 0..m {
                self.work_m2[r] =
                    dot(&self.a[r * n..(r + 1) * n], &self.cor_full[..n]) - self.res_full[n + r];
            }
            self.sc
                .apply(hinv_mul, &self.work_m2, &mut self.cor_full[n..]);
            for i in 0..n + m {
                self.sol_full[i] += self.cor_full[i];
            }
        }
        self.sol_full.iter().all(|x| x.is_finite())
    }

    fn solve_constant(&mut self) -> bool {
        let n = self.n;
        for i in 0..n {
            self.rhs_full[i] = -self.q[i];
        }
        self.rhs_full[n..].copy_from_slice(&self.b);
        if !self.solve_kkt() {
            return false;
        }
        self.x2.copy_from_slice(&self.sol_full[..n]);
        self.z2.copy_from_slice(&self.sol_full[n..]);
        true
    }

    /// Predictor right-hand side: the residuals, `λ∘λ` and `τκ`.
    fn affine_rhs(&mut self) {
        self.rhs.x.copy_from_slice(&self.rx);
        self.rhs.z.copy_from_slice(&self.rz);
        for &(c, o) in &self.sc.cones {
            let lam = &self.lambda[o..o + c.dim()];
            circ(c, lam, lam, &mut self.rhs.s[o..o + c.dim()]);
        }
        self.rhs.tau = self.meas.rtau;
        self.rhs.kappa = self.v.tau * self.v.kappa;
    }

    /// Corrector right-hand side: `(1 − σ)` of the residuals,
    /// `λ∘λ + (W⁻ᵀΔs_a)∘(WΔz_a) − σμe` and `τκ + Δτ_aΔκ_a − σμ`, with the
    /// affine step scaled by `scale` in the products. `rhs.s` still holds
    /// the predictor's `λ∘λ`, to which the shift is added.
    fn combined_rhs(&mut self, sigma: f64, mu: f64, scale: f64) {
        let sm = sigma * mu;
        for i in 0..self.n {
            self.rhs.x[i] = (1.0 - sigma) * self.rx[i];
        }
        self.rhs.tau = (1.0 - sigma) * self.meas.rtau;
        self.rhs.kappa = -sm + scale * self.step.tau * self.step.kappa + self.v.tau * self.v.kappa;
        if scale != 1.0 {
            self.step.z.iter_mut().for_each(|x| *x *= scale);
        }
        // work_m = WΔz, work_m2 = W⁻ᵀΔs (W symmetric)
        self.sc.apply(w_mul, &self.step.z, &mut self.work_m);
        self.sc.apply(winv_mul, &self.step.s, &mut self.work_m2);
        for &(c, o) in &self.sc.cones {
            let r = o..o + c.dim();
            let shift = &mut self.ds_const[r.clone()];
            circ(c, &self.work_m2[r.clone()], &self.work_m[r.clone()], shift);
            match c {
                Cone::NonNegative(_) => shift.iter_mut().for_each(|x| *x -= sm),
                Cone::SecondOrder(_) => shift[0] -= sm,
            }
            for (t, sh) in self.rhs.s[r].iter_mut().zip(shift.iter()) {
                *t += sh;
            }
        }
        for i in 0..self.m {
            self.rhs.z[i] = (1.0 - sigma) * self.rz[i];
        }
    }

    /// Solves the Newton system for `rhs` into `step` (Clarabel's
    /// `DefaultKKTSystem::solve`): `[Δx₁; Δz₁]` from `[r_x; Δs₀ − r_z]`,
    /// then `Δτ` from the third row, `Δx = Δx₁ + Δτ x₂`, `Δz = Δz₁ + Δτ z₂`,
    /// `Δs = −(HΔz + Δs₀)`, `Δκ = −(r_κ + κΔτ)/τ`; `Δs₀ = s` for the
    /// predictor and `Wᵀ(λ \ r_s)` for the corrector.
    fn solve_step(&mut self, combined: bool) -> bool {
        let (n, m) = (self.n, self.m);
        if combined {
            for &(c, o) in &self.sc.cones {
                let r = o..o + c.dim();
                inv_circ(
                    c,
                    &self.lambda[r.clone()],
                    &self.rhs.s[r.clone()],
                    &mut self.work_m[r],
                );
            }
            self.sc.apply(w_mul, &self.work_m, &mut self.ds_const);
        } else {
            self.ds_const.copy_from_slice(&self.v.s);
        }
        self.rhs_full[..n].copy_from_slice(&self.rhs.x);
        for i in 0..m {
            self.rhs_full[n + i] = self.ds_const[i] - self.rhs.z[i];
        }
        if !self.solve_kkt() {
            return false;
        }
        self.x1.copy_from_slice(&self.sol_full[..n]);
        self.z1.copy_from_slice(&self.sol_full[n..]);
        let v = &self.v;
        // ξ = x/τ
        for i in 0..n {
            self.work_n[i] = v.x[i] / v.tau;
        }
        let p_xi_x1 = quad(&self.p, n, &self.work_n, &self.x1);
        let num = self.rhs.tau - self.rhs.kappa / v.tau
            + dot(&self.q, &self.x1)
            + dot(&self.b, &self.z1)
            + 2.0 * p_xi_x1;
        let p_xi_xi = quad(&self.p, n, &self.work_n, &self.work_n);
        let p_xi_x2 = quad(&self.p, n, &self.work_n, &self.x2);
        let den = v.kappa / v.tau - dot(&self.q, &self.x2) - dot(&self.b, &self.z2) + p_xi_xi
            - 2.0 * p_xi_x2;
        let dtau = num / den;
        if !dtau.is_finite() {
            return false;
        }
        self.step.tau = dtau;
        for i in 0..n {
            self.step.x[i] = self.x1[i] + dtau * self.x2[i];
        }
        for i in 0..m {
            self.step.z[i] = self.z1[i] + dtau * self.z2[i];
        }
        // Δs = −(HΔz + Δs₀)
        self.sc.apply(h_mul, &self.step.z, &mut self.step.s);
        for i in 0..m {
            self.step.s[i] = -(self.step.s[i] + self.ds_const[i]);
        }
        self.step.kappa = -(self.rhs.kappa + v.kappa * dtau) / v.tau;
        true
    }

    /// Largest step in `(0, 1]` keeping `τ, κ ≥ 0` and `s, z` in the cones
    /// (times 0.99 for the corrector).
    fn step_length(&self, combined: bool) -> f64 {
        let (v, d) = (&self.v, &self.step);
        let mut alpha: f64 = 1.0;
        if d.tau < 0.0 {
            alpha = alpha.min(-v.tau / d.tau);
        }
        if d.kappa < 0.0 {
            alpha = alpha.min(-v.kappa / d.kappa);
        }
        for &(c, o) in &self.sc.cones {
            let r = o..o + c.dim();
            alpha = cone_step(c, &v.z[r.clone()], &d.z[r.clone()], alpha);
            alpha = cone_step(c, &v.s[r.clone()], &d.s[r], alpha);
        }
        if combined {
            alpha * MAX_STEP_FRACTION
        } else {
            alpha
        }
    }

    fn add_step(&mut self, alpha: f64) {
        let (v, d) = (&mut self.v, &self.step);
        axpy(alpha, &d.x, &mut v.x);
        axpy(alpha, &d.s, &mut v.s);
        axpy(alpha, &d.z, &mut v.z);
        v.tau += alpha * d.tau;
        v.kappa += alpha * d.kappa;
    }
}

#[inline]
fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

#[inline]
fn norm(a: &[f64]) -> f64 {
    dot(a, a).sqrt()
}

#[inline]
fn axpy(alpha: f64, x: &[f64], y: &mut [f64]) {
    for (y, x) in y.iter_mut().zip(x) {
        *y += alpha * x;
    }
}

/// `aᵀ P b` for a row-major `n × n` matrix.
#[inline]
fn quad(p: &[f64], n: usize, a: &[f64], b: &[f64]) -> f64 {
    (0..n).map(|i| a[i] * dot(&p[i * n..(i + 1) * n], b)).sum()
}

/// `x₀² − ‖x₁‖²`.
#[inline]
fn soc_residual(x: &[f64]) -> f64 {
    x[0] * x[0] - dot(&x[1..], &x[1..])
}

/// `x ← (LLᵀ)⁻¹ x` with the lower Cholesky factor of a row-major `n × n`.
#[inline]
fn chol_solve(l: &[f64], n: usize, x: &mut [f64]) {
    for i in 0..n {
        let mut v = x[i];
        for t in 0..i {
            v -= l[i * n + t] * x[t];
        }
        x[i] = v / l[i * n + i];
    }
    for i in (0..n).rev() {
        let mut v = x[i];
        for t in i + 1..n {
            v -= l[t * n + i] * x[t];
        }
        x[i] = v / l[i * n + i];
    }
}

/// The cones of `K` (each with the offset of its first row) and the NT
/// scaling at the current iterate: `w̄` of each SOC (`w = √(s/z)` for the
/// orthant) and `η` per cone.
#[derive(Debug, Clone)]
struct Scaling {
    cones: Vec<(Cone, usize)>,
    eta: Vec<f64>,
    wbar: Vec<f64>,
}

impl Scaling {
    /// Applies `op(cone, η, w̄, v, out)`, one cone's block of a scaling
    /// operator, cone by cone: `out_i = op(v_i)` on each cone's rows.
    #[inline]
    fn apply<F: Fn(Cone, f64, &[f64], &[f64], &mut [f64])>(
        &self,
        op: F,
        v: &[f64],
        out: &mut [f64],
    ) {
        for (k, &(c, o)) in self.cones.iter().enumerate() {
            let r = o..o + c.dim();
            op(
                c,
                self.eta[k],
                &self.wbar[r.clone()],
                &v[r.clone()],
                &mut out[r],
            );
        }
    }
}

/// `out = W v` of one cone: for a SOC
/// `W = η [w̄₀, w̄₁ᵀ; w̄₁, I + w̄₁w̄₁ᵀ/(1 + w̄₀)]`, for the orthant
/// `W = diag(w)`.
#[inline]
fn w_mul(c: Cone, eta: f64, w: &[f64], v: &[f64], out: &mut [f64]) {
    match c {
        Cone::NonNegative(_) => {
            for i in 0..v.len() {
                out[i] = v[i] * w[i];
            }
        }
        Cone::SecondOrder(_) => soc_w_mul(eta, w, v, out, false),
    }
}

/// `out = W⁻¹ v` of one cone: `W` with `−w̄₁` and `1/η` for a SOC.
#[inline]
fn winv_mul(c: Cone, eta: f64, w: &[f64], v: &[f64], out: &mut [f64]) {
    match c {
        Cone::NonNegative(_) => {
            for i in 0..v.len() {
                out[i] = v[i] / w[i];
            }
        }
        Cone::SecondOrder(_) => soc_w_mul(eta, w, v, out, true),
    }
}

#[inline]
fn soc_w_mul(eta: f64, w: &[f64], v: &[f64], out: &mut [f64], inverse: bool) {
    let sign = if inverse { -1.0 } else { 1.0 };
    let f = if inverse { 1.0 / eta } else { eta };
    let w1v1 = dot(&w[1..], &v[1..]);
    out[0] = f * (w[0] * v[0] + sign * w1v1);
    let c = sign * v[0] + w1v1 / (1.0 + w[0]);
    for i in 1..v.len() {
        out[i] = f * (v[i] + c * w[i]);
    }
}

/// `out = H v` with `H = WᵀW`: `η²(2w̄(w̄ᵀv) − Jv)` for a SOC, `w² v` for
/// the orthant.
#[inline]
fn h_mul(c: Cone, eta: f64, w: &[f64], v: &[f64], out: &mut [f64]) {
    match c {
        Cone::NonNegative(_) => {
            for i in 0..v.len() {
                out[i] = w[i] * w[i] * v[i];
            }
        }
        Cone::SecondOrder(_) => {
            let e2 = eta * eta;
            let wv = 2.0 * dot(w, v);
            out[0] = e2 * (wv * w[0] - v[0]);
            for i in 1..v.len() {
                out[i] = e2 * (wv * w[i] + v[i]);
            }
        }
    }
}

/// `out = H⁻¹ v`: `η⁻²(2(Jw̄)((Jw̄)ᵀv) − Jv)` for a SOC (`w̄ᵀJw̄ = 1`),
/// `v / w²` for the orthant.
#[inline]
fn hinv_mul(c: Cone, eta: f64, w: &[f64], v: &[f64], out: &mut [f64]) {
    match c {
        Cone::NonNegative(_) => {
            for i in 0..v.len() {
                out[i] = v[i] / (w[i] * w[i]);
            }
        }
        Cone::SecondOrder(_) => {
            let e2 = 1.0 / (eta * eta);
            // Jw̄ = (w̄₀, −w̄₁)
            let jwv = 2.0 * (w[0] * v[0] - dot(&w[1..], &v[1..]));
            out[0] = e2 * (jwv * w[0] - v[0]);
            for i in 1..v.len() {
                out[i] = e2 * (-jwv * w[i] + v[i]);
            }
        }
    }
}

/// Jordan product `u ∘ v`: `(uᵀv, u₀v₁ + v₀u₁)` for a SOC, elementwise for
/// the orthant.
#[inline]
fn circ(c: Cone, u: &[f64], v: &[f64], out: &mut [f64]) {
    match c {
        Cone::NonNegative(_) => {
            for i in 0..u.len() {
                out[i] = u[i] * v[i];
            }
        }
        Cone::SecondOrder(_) => {
            out[0] = dot(u, v);
            for i in 1..u.len() {
                out[i] = u[0] * v[i] + v[0] * u[i];
            }
        }
    }
}

/// `out = λ \ r`, the `v` with `λ ∘ v = r`.
#[inline]
fn inv_circ(c: Cone, lam: &[f64], r: &[f64], out: &mut [f64]) {
    match c {
        Cone::NonNegative(_) => {
            for i in 0..r.len() {
                out[i] = r[i] / lam[i];
            }
        }
        Cone::SecondOrder(_) => {
            let det = soc_residual(lam);
            let v0 = (lam[0] * r[0] - dot(&lam[1..], &r[1..])) / det;
            out[0] = v0;
            for i in 1..r.len() {
                out[i] = (r[i] - v0 * lam[i]) / lam[0];
            }
        }
    }
}

/// The largest `α ≤ alpha` with `x + α d` in the cone (`x` interior).
#[inline]
fn cone_step(c: Cone, x: &[f64], d: &[f64], alpha: f64) -> f64 {
    let mut alpha = alpha;
    match c {
        Cone::NonNegative(_) => {
            for (xi, di) in x.iter().zip(d) {
                if *di < 0.0 {
                    alpha = alpha.min(-xi / di);
                }
            }
            alpha
        }
        Cone::SecondOrder(_) => {
            if x[0] >= 0.0 && d[0] < 0.0 {
                alpha = alpha.min(-x[0] / d[0]);
            }
            // smallest positive root of a α² + b α + c (c ≥ 0)
            let a = soc_residual(d);
            let b = 2.0 * (x[0] * d[0] - dot(&x[1..], &d[1..]));
            let c = soc_residual(x).max(0.0);
            if a == 0.0 {
                // d on the boundary of ±K: the residual c + bα is linear
                // and reaches 0 at −c/b if it falls (Clarabel's rule
                // returns the cap here, and so leaves the cone)
                return if b < 0.0 { alpha.min(-c / b) } else { alpha };
            }
            let disc = b * b - 4.0 * a * c;
            if (a > 0.0 && b > 0.0) || disc < 0.0 {
                return alpha;
            }
            if c == 0.0 {
                return if a >= 0.0 { alpha } else { 0.0 };
            }
            let t = if b >= 0.0 {
                -b - disc.sqrt()
            } else {
                -b + disc.sqrt()
            };
            let r1 = 2.0 * c / t;
            let r2 = t / (2.0 * a);
            let r1 = if r1 < 0.0 { f64::INFINITY } else { r1 };
            let r2 = if r2 < 0.0 { f64::INFINITY } else { r2 };
            alpha.min(r1).min(r2)
        }
    }
}

#[cfg(test)]
mod tests {
    //! The solver against Clarabel (an independent implementation of the
    //! same problem class) on random programs, the KKT conditions and
    //! infeasibility certificates of its answers, a closed-form projection,
    //! and the identities of the NT scaling.
    use super::*;
    use clarabel::algebra::CscMatrix;
    use clarabel::solver::{
        DefaultSettings, DefaultSolver, IPSolver, SolverStatus, SupportedConeT,
    };
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, StandardNormal};

    fn normal(rng: &mut ChaCha8Rng) -> f64 {
        StandardNormal.sample(rng)
    }

    /// A random point of the interior of `K` (or of its boundary region:
    /// margins down to 10⁻³).
    fn interior(rng: &mut ChaCha8Rng, cones: &[Cone]) -> Vec<f64> {
        let mut v = Vec::new();
        for &c in cones {
            match c {
                Cone::NonNegative(d) => {
                    v.extend((0..d).map(|_| 10f64.powf(rng.random_range(-3.0..1.0))))
                }
                Cone::SecondOrder(d) => {
                    let tail: Vec<f64> = (0..d - 1).map(|_| normal(rng)).collect();
                    v.push(norm(&tail) + 10f64.powf(rng.random_range(-3.0..1.0)));
                    v.extend(tail);
                }
            }
        }
        v
    }

    fn random_cones(rng: &mut ChaCha8Rng, n: usize) -> Vec<Cone> {
        let mut cones: Vec<Cone> = (0..rng.random_range(1..4))
            .map(|_| Cone::SecondOrder(rng.random_range(2..5)))
            .collect();
        if rng.random_bool(0.5) {
            cones.push(Cone::NonNegative(2 * n));
        }
        cones
    }

    /// `n < n_end` variables, random cones and a random program on them.
    fn random_case(rng: &mut ChaCha8Rng, n_end: usize) -> (usize, Vec<Cone>, DenseConeSolver) {
        let n = rng.random_range(1..n_end);
        let cones = random_cones(rng, n);
        let s = random_program(rng, n, &cones);
        (n, cones, s)
    }

    /// A program with `P ≻ 0` (or `P = 0` on the last variable with
    /// `q_last = −1`, the max-margin shape) and random `A`.
    fn random_program(rng: &mut ChaCha8Rng, n: usize, cones: &[Cone]) -> DenseConeSolver {
        let mut s = DenseConeSolver::new(n, cones);
        let max_margin = rng.random_bool(0.25);
        let b: Vec<f64> = (0..n * n).map(|_| normal(rng)).collect();
        for i in 0..n {
            for j in 0..n {
                let mut v: f64 = (0..n).map(|k| b[k * n + i] * b[k * n + j]).sum();
                if i == j {
                    v += 0.1;
                }
                s.p[i * n + j] = v;
            }
        }
        if max_margin {
            for i in 0..n {
                s.p[i * n + n - 1] = 0.0;
                s.p[(n - 1) * n + i] = 0.0;
            }
        }
        for v in s.q.iter_mut() {
            *v = normal(rng);
        }
        if max_margin {
            s.q[n - 1] = -1.0;
        }
        for v in s.a.iter_mut() {
            *v = normal(rng);
        }
        s
    }

    /// Clarabel's answer to the same program (its default settings, with
    /// equilibration), `AlmostSolved` read as `Solved`.
    fn clarabel(s: &DenseConeSolver, cones: &[Cone]) -> (SolverStatus, Vec<f64>, f64) {
        let (status, x, obj, _) = clarabel_with(s, cones, true);
        (status, x, obj)
    }

    /// [`clarabel`] with or without equilibration, and its iterations.
    fn clarabel_with(
        s: &DenseConeSolver,
        cones: &[Cone],
        equilibrate: bool,
    ) -> (SolverStatus, Vec<f64>, f64, u32) {
        let (n, m) = (s.n, s.m);
        let dense_to_csc = |rows: usize, vals: &[f64], upper: bool| {
            let mut colptr = vec![0];
            let mut rowval = Vec::new();
            let mut nz = Vec::new();
            for j in 0..n {
                for i in 0..rows {
                    if (!upper || i <= j) && vals[i * n + j] != 0.0 {
                        rowval.push(i);
                        nz.push(vals[i * n + j]);
                    }
                }
                colptr.push(rowval.len());
            }
            CscMatrix::new(rows, n, colptr, rowval, nz)
        };
        let p = dense_to_csc(n, &s.p, true);
        let a = dense_to_csc(m, &s.a, false);
        let kinds: Vec<SupportedConeT<f64>> = cones
            .iter()
            .map(|c| match *c {
                Cone::NonNegative(d) => SupportedConeT::NonnegativeConeT(d),
                Cone::SecondOrder(d) => SupportedConeT::SecondOrderConeT(d),
            })
            .collect();
        let settings = DefaultSettings {
            verbose: false,
            equilibrate_enable: equilibrate,
            ..DefaultSettings::default()
        };
        let mut solver = DefaultSolver::new(&p, &s.q, &a, &s.b, &kinds, settings).unwrap();
        solver.solve();
        let sol = &solver.solution;
        let status = match sol.status {
            SolverStatus::AlmostSolved => SolverStatus::Solved,
            SolverStatus::AlmostPrimalInfeasible => SolverStatus::PrimalInfeasible,
            SolverStatus::AlmostDualInfeasible => SolverStatus::DualInfeasible,
            other => other,
        };
        (status, sol.x.clone(), sol.obj_val, sol.iterations)
    }

    fn objective(s: &DenseConeSolver) -> f64 {
        let x = s.x();
        0.5 * quad(&s.p, s.n, x, x) + dot(&s.q, x)
    }

    /// The smallest cone margin of `v` (negative: outside `K`; `K` is
    /// self-dual, so this also tests `K*`).
    fn margin(cones: &[Cone], v: &[f64]) -> f64 {
        let mut o = 0;
        let mut worst = f64::INFINITY;
        for &c in cones {
            let w = &v[o..o + c.dim()];
            worst = worst.min(match c {
                Cone::NonNegative(_) => w.iter().cloned().fold(f64::INFINITY, f64::min),
                Cone::SecondOrder(_) => w[0] - norm(&w[1..]),
            });
            o += c.dim();
        }
        worst
    }

    /// Stationarity, primal feasibility, cone membership and
    /// complementarity of a `Solved` answer.
    fn assert_kkt(s: &DenseConeSolver, cones: &[Cone]) {
        let (n, m) = (s.n, s.m);
        let (x, sl, z) = (s.x(), s.s(), s.z());
        let scale = 1.0 + norm(x) + norm(z) + norm(&s.q) + norm(&s.b);
        for i in 0..n {
            let g = dot(&s.p[i * n..(i + 1) * n], x)
                + s.q[i]
                + (0..m).map(|r| s.a[r * n + i] * z[r]).sum::<f64>();
            assert!(g.abs() < 1e-6 * scale, "stationarity {g}");
        }
        for r in 0..m {
            let e = dot(&s.a[r * n..(r + 1) * n], x) + sl[r] - s.b[r];
            assert!(e.abs() < 1e-6 * scale, "primal residual {e}");
        }
        assert!(margin(cones, sl) > -1e-9 * scale && margin(cones, z) > -1e-9 * scale);
        assert!(
            dot(sl, z).abs() < 1e-6 * scale,
            "complementarity {}",
            dot(sl, z)
        );
    }

    /// Clarabel's termination rules, case by case on both sides of each
    /// threshold: solved (`κ/τ ≤ 1`, either gap, both residuals), the
    /// infeasibility certificates (`κ/τ > 10⁹`, the sign and size of
    /// `bᵀz` or `qᵀx`), a stalled or diverging iteration (after the first,
    /// a residual worse than the last), non-finite measures and the
    /// iteration cap.
    #[test]
    fn termination_follows_clarabels_rules() {
        let mut d = DenseConeSolver::new(2, &[Cone::NonNegative(2)]);
        let converged = Measures {
            ktratio: 0.5,
            gap_abs: 1e-9,
            gap_rel: 1e-9,
            res_primal: 1e-9,
            res_dual: 1e-9,
            ..Measures::default()
        };
        type Edit = fn(&mut Measures, &mut Measures);
        /// A residual worse than the last at `κ/τ` near zero, the last
        /// gaps closed (`converged`'s): a stall, unless a case changes it.
        fn stalling(m: &mut Measures, p: &mut Measures) {
            (m.ktratio, m.res_primal, p.res_primal) = (1e-15, 1e-7, 1e-8);
        }
        let cases: [(&str, usize, Edit, Option<DenseStatus>); 43] = [
            // solved, and Clarabel's strict inequalities at equality
            ("converged", 3, |_, _| {}, Some(DenseStatus::Solved)),
            (
                "κ/τ = 1",
                3,
                |m, _| m.ktratio = 1.0,
                Some(DenseStatus::Solved),
            ),
            ("κ/τ > 1", 3, |m, _| m.ktratio = 1.5, None),
            (
                "absolute gap only",
                3,
                |m, _| m.gap_rel = 1e-7,
                Some(DenseStatus::Solved),
            ),
            (
                "relative gap only",
                3,
                |m, _| m.gap_abs = 1e-7,
                Some(DenseStatus::Solved),
            ),
            (
                "neither gap",
                3,
                |m, _| (m.gap_abs, m.gap_rel) = (1e-7, 1e-7),
                None,
            ),
            (
                "gaps at their tolerance",
                1,
                |m, _| (m.gap_abs, m.gap_rel) = (TOL_GAP_ABS, TOL_GAP_REL),
                None,
            ),
            ("primal residual", 1, |m, _| m.res_primal = 1e-7, None),
            (
                "primal residual at its tolerance",
                1,
                |m, _| m.res_primal = TOL_FEAS,
                None,
            ),
            ("dual residual", 1, |m, _| m.res_dual = 1e-7, None),
            (
                "dual residual at its tolerance",
                1,
                |m, _| m.res_dual = TOL_FEAS,
                None,
            ),
            (
                "non-finite",
                1,
                |m, _| m.res_dual = f64::NAN,
                Some(DenseStatus::Failed),
            ),
            // infeasibility certificates
            (
                "primal certificate",
                3,
                |m, _| (m.ktratio, m.dot_bz, m.res_primal_inf) = (2e9, -1.0, 1e-9),
                Some(DenseStatus::PrimalInfeasible),
            ),
            (
                "primal certificate, κ/τ too small",
                3,
                |m, _| (m.ktratio, m.dot_bz, m.res_primal_inf) = (5e8, -1.0, 1e-9),
                None,
            ),
            (
                "κ/τ at the certificate threshold",
                3,
                |m, _| (m.ktratio, m.dot_bz, m.res_primal_inf) = (1000.0 / TOL_KTRATIO, -1.0, 1e-9),
                None,
            ),
            (
                "primal certificate, bᵀz too small",
                3,
                |m, _| (m.ktratio, m.dot_bz, m.res_primal_inf) = (2e9, -5e-9, 1e-20),
                None,
            ),
            (
                "bᵀz at its tolerance",
                3,
                |m, _| (m.ktratio, m.dot_bz, m.res_primal_inf) = (2e9, -TOL_INFEAS_ABS, 0.0),
                None,
            ),
            (
                "primal certificate, residual too large",
                3,
                |m, _| (m.ktratio, m.dot_bz, m.res_primal_inf) = (2e9, -2.0, 3e-8),
                None,
            ),
            (
                "primal certificate residual at its tolerance",
                3,
                |m, _| (m.ktratio, m.dot_bz, m.res_primal_inf) = (2e9, -1.0, TOL_INFEAS_REL),
                None,
            ),
            (
                "dual certificate",
                3,
                |m, _| (m.ktratio, m.dot_qx, m.res_dual_inf) = (2e9, -1.0, 1e-9),
                Some(DenseStatus::DualInfeasible),
            ),
            (
                "dual certificate, qᵀx too small",
                3,
                |m, _| (m.ktratio, m.dot_qx, m.res_dual_inf) = (2e9, -5e-9, 1e-20),
                None,
            ),
            (
                "qᵀx at its tolerance",
                3,
                |m, _| (m.ktratio, m.dot_qx, m.res_dual_inf) = (2e9, -TOL_INFEAS_ABS, 0.0),
                None,
            ),
            (
                "dual certificate, residual too large",
                3,
                |m, _| (m.ktratio, m.dot_qx, m.res_dual_inf) = (2e9, -2.0, 3e-8),
                None,
            ),
            (
                "dual certificate residual at its tolerance",
                3,
                |m, _| (m.ktratio, m.dot_qx, m.res_dual_inf) = (2e9, -1.0, TOL_INFEAS_REL),
                None,
            ),
            // a stalled iteration (from `stalling`)
            (
                "stalled",
                3,
                |m, p| stalling(m, p),
                Some(DenseStatus::Failed),
            ),
            (
                "stalled at the first iteration",
                1,
                |m, p| stalling(m, p),
                None,
            ),
            (
                "stalled, residuals improving",
                3,
                |m, p| {
                    stalling(m, p);
                    p.res_primal = 1e-6;
                },
                None,
            ),
            (
                "small κ/τ, residuals unchanged",
                3,
                |m, p| {
                    stalling(m, p);
                    p.res_primal = 1e-7;
                },
                None,
            ),
            (
                "small κ/τ, last gap open",
                3,
                |m, p| {
                    stalling(m, p);
                    (p.gap_abs, p.gap_rel) = (1e-7, 1e-7);
                },
                None,
            ),
            (
                "stalled, last relative gap closed",
                3,
                |m, p| {
                    stalling(m, p);
                    p.gap_abs = 1e-7;
                },
                Some(DenseStatus::Failed),
            ),
            (
                "stalled, last absolute gap closed",
                3,
                |m, p| {
                    stalling(m, p);
                    p.gap_rel = 1e-7;
                },
                Some(DenseStatus::Failed),
            ),
            (
                "κ/τ at the stall threshold",
                3,
                |m, p| {
                    stalling(m, p);
                    m.ktratio = 100.0 * f64::EPSILON;
                },
                None,
            ),
            (
                "last absolute gap at its tolerance",
                3,
                |m, p| {
                    stalling(m, p);
                    (p.gap_abs, p.gap_rel) = (TOL_GAP_ABS, 1e-7);
                },
                None,
            ),
            (
                "last relative gap at its tolerance",
                3,
                |m, p| {
                    stalling(m, p);
                    (p.gap_abs, p.gap_rel) = (1e-7, TOL_GAP_REL);
                },
                None,
            ),
            // a diverging iteration
            (
                "dual residual diverging",
                3,
                |m, p| (m.res_dual, p.res_dual) = (1e-3, 1e-6),
                Some(DenseStatus::Failed),
            ),
            (
                "dual residual growing less than 100×",
                3,
                |m, p| (m.res_dual, p.res_dual) = (1e-3, 1e-4),
                None,
            ),
            (
                "dual residual grown exactly 100×",
                3,
                |m, p| (m.res_dual, p.res_dual) = (100.0 * 1e-5, 1e-5),
                None,
            ),
            (
                "dual residual at the divergence floor",
                3,
                |m, p| (m.res_dual, p.res_dual) = (100.0 * TOL_FEAS, 1e-9),
                None,
            ),
            (
                "diverging at κ/τ = 1",
                3,
                |m, p| (m.ktratio, m.res_dual, p.res_dual) = (1.0, 1e-3, 1e-6),
                None,
            ),
            (
                "primal residual diverging",
                3,
                |m, p| (m.res_primal, p.res_primal) = (1e-3, 1e-6),
                Some(DenseStatus::Failed),
            ),
            (
                "primal residual grown exactly 100×",
                3,
                |m, p| (m.res_primal, p.res_primal) = (100.0 * 1e-5, 1e-5),
                None,
            ),
            (
                "primal residual at the divergence floor",
                3,
                |m, p| (m.res_primal, p.res_primal) = (100.0 * TOL_FEAS, 1e-9),
                None,
            ),
            // the iteration cap
            (
                "the iteration cap",
                MAX_ITER,
                |m, _| m.res_primal = 1e-7,
                Some(DenseStatus::Failed),
            ),
        ];
        for (name, iter, edit, want) in cases {
            let (mut m, mut p) = (converged.clone(), converged.clone());
            edit(&mut m, &mut p);
            (d.meas, d.prev_meas) = (m, p);
            assert_eq!(d.check_termination(iter), want, "{name}");
        }
        // below the cap, with nothing decided
        d.meas = Measures {
            res_primal: 1e-7,
            ..converged.clone()
        };
        d.prev_meas = converged;
        assert_eq!(d.check_termination(MAX_ITER - 1), None);
    }

    /// The scaling is computed only at interior points: every entry of a
    /// nonnegative cone and the head and `J`-norm of a second-order cone
    /// strictly positive in both `s` and `z`; on the boundary or outside
    /// it refuses, for either vector.
    #[test]
    fn scaling_refuses_points_not_interior() {
        let mut d = DenseConeSolver::new(1, &[Cone::NonNegative(2), Cone::SecondOrder(3)]);
        let inside = [1.0, 2.0, 10.0, 3.0, 4.0];
        let outside: [(usize, f64); 7] = [
            (0, 0.0),   // a nonnegative entry on the boundary
            (1, -1.0),  // and outside
            (2, 0.0),   // the SOC head at zero
            (2, -10.0), // a negative head, positive J-norm
            (2, 5.0),   // ‖tail‖ = head: J-norm zero
            (3, 11.0),  // the tail out of the cone
            (4, -10.0), // and on its other side
        ];
        d.v.s = inside.to_vec();
        d.v.z = inside.to_vec();
        assert!(d.update_scaling());
        for (i, v) in outside {
            for in_z in [false, true] {
                d.v.s = inside.to_vec();
                d.v.z = inside.to_vec();
                if in_z {
                    d.v.z[i] = v;
                } else {
                    d.v.s[i] = v;
                }
                assert!(
                    !d.update_scaling(),
                    "entry {i} = {v} in {}",
                    if in_z { "z" } else { "s" }
                );
            }
        }
    }

    /// A vector of `len` normal entries times `scale`.
    fn scaled(rng: &mut ChaCha8Rng, len: usize, scale: f64) -> Vec<f64> {
        (0..len).map(|_| scale * normal(rng)).collect()
    }

    /// The measures of convergence are Clarabel's (`DefaultInfo::update`
    /// without equilibration, written out here from its definitions) at
    /// random iterates with `τ` from 0.1 to 10 and norms on both sides of
    /// the `max(1, ·)` guards: every norm, `τ` scaling and guard.
    #[test]
    fn measures_follow_clarabels_definitions() {
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let cones = [Cone::NonNegative(2), Cone::SecondOrder(3)];
        let (n, m) = (3, 5);
        let mut d = DenseConeSolver::new(n, &cones);
        for trial in 0..300 {
            let scale = 10f64.powf(rng.random_range(-2.0..2.0));
            d.v.x = scaled(&mut rng, n, scale);
            d.v.s = scaled(&mut rng, m, scale);
            d.v.z = scaled(&mut rng, m, scale);
            d.v.tau = 10f64.powf(rng.random_range(-1.0..1.0));
            d.v.kappa = rng.random_range(0.0..3.0);
            d.rx = scaled(&mut rng, n, scale);
            d.rz = scaled(&mut rng, m, scale);
            d.px = scaled(&mut rng, n, scale);
            d.rx_inf = scaled(&mut rng, n, scale);
            d.rz_inf = scaled(&mut rng, m, scale);
            d.b = scaled(&mut rng, m, scale);
            d.q = scaled(&mut rng, n, scale);
            d.meas.dot_qx = scale * normal(&mut rng);
            d.meas.dot_bz = scale * normal(&mut rng);
            d.meas.dot_xpx = scale * normal(&mut rng).abs();
            d.update_measures();

            let t = 1.0 / d.v.tau;
            let half = d.meas.dot_xpx * t * t / 2.0;
            let primal = d.meas.dot_qx * t + half;
            let dual = -d.meas.dot_bz * t - half;
            let (nx, nz, ns) = (norm(&d.v.x), norm(&d.v.z), norm(&d.v.s));
            let gap = (primal - dual).abs();
            let want = [
                ("res_primal_inf", norm(&d.rx_inf) / nz.max(1.0)),
                (
                    "res_dual_inf",
                    (norm(&d.px) / nx.max(1.0)).max(norm(&d.rz_inf) / (nx + ns).max(1.0)),
                ),
                (
                    "res_primal",
                    norm(&d.rz) * t / (norm(&d.b) + (nx + ns) * t).max(1.0),
                ),
                (
                    "res_dual",
                    norm(&d.rx) * t / (norm(&d.q) + (nx + nz) * t).max(1.0),
                ),
                ("gap_abs", gap),
                ("gap_rel", gap / primal.abs().min(dual.abs()).max(1.0)),
                ("ktratio", d.v.kappa * t),
            ];
            let mm = &d.meas;
            let got = [
                mm.res_primal_inf,
                mm.res_dual_inf,
                mm.res_primal,
                mm.res_dual,
                mm.gap_abs,
                mm.gap_rel,
                mm.ktratio,
            ];
            for ((name, w), g) in want.iter().zip(got) {
                assert!(
                    (w - g).abs() <= 1e-12 * w.abs().max(1e-300),
                    "trial {trial}: {name} {g} against {w}"
                );
            }
        }
    }

    #[test]
    fn strictly_feasible_programs_match_clarabel_and_meet_kkt() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for trial in 0..400 {
            let (n, cones, mut s) = random_case(&mut rng, 5);
            // b = A x₀ + s₀ with s₀ interior: strictly feasible
            let x0: Vec<f64> = (0..n).map(|_| normal(&mut rng)).collect();
            let s0 = interior(&mut rng, &cones);
            for r in 0..s.m {
                s.b[r] = dot(&s.a[r * n..(r + 1) * n], &x0) + s0[r];
            }
            let (cs, cx, cobj) = clarabel(&s, &cones);
            let st = s.solve();
            if cs == SolverStatus::DualInfeasible {
                // the max-margin shape can be unbounded
                assert_ne!(st, DenseStatus::Solved, "trial {trial}");
                continue;
            }
            assert_eq!(cs, SolverStatus::Solved, "trial {trial}");
            assert_eq!(st, DenseStatus::Solved, "trial {trial}");
            assert_kkt(&s, &cones);
            let obj = objective(&s);
            assert!(
                (obj - cobj).abs() <= 1e-6 * (1.0 + cobj.abs()),
                "trial {trial}: objective {obj} against Clarabel's {cobj}"
            );
            let scale = 1.0 + norm(&cx);
            for (a, b) in s.x().iter().zip(&cx) {
                assert!(
                    (a - b).abs() < 1e-4 * scale,
                    "trial {trial}: x {a} against {b}"
                );
            }
        }
    }

    /// The same iteration as Clarabel's (start, centring, corrector, step
    /// fraction, termination): on strictly feasible programs at scales from
    /// 10⁻² to 10³, without equilibration, both take the same number of
    /// iterations, up to the rounding of their different linear algebra.
    #[test]
    fn iterations_follow_clarabels() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (mut same, mut total, mut worst) = (0, 0, 0i64);
        for _ in 0..300 {
            let (n, cones, mut s) = random_case(&mut rng, 5);
            if s.p[n * n - 1] == 0.0 {
                continue; // the max-margin shape can be unbounded
            }
            let x0: Vec<f64> = (0..n).map(|_| normal(&mut rng)).collect();
            let s0 = interior(&mut rng, &cones);
            for r in 0..s.m {
                s.b[r] = dot(&s.a[r * n..(r + 1) * n], &x0) + s0[r];
            }
            // data from 10⁻² to 10³: the start's shift into the cones
            // scales with the data's margins
            let f = 10f64.powf(rng.random_range(-2.0..3.0));
            s.b.iter_mut().for_each(|v| *v *= f);
            s.q.iter_mut().for_each(|v| *v *= f);
            let (cs, _, _, ci) = clarabel_with(&s, &cones, false);
            if cs != SolverStatus::Solved {
                continue;
            }
            assert_eq!(s.solve(), DenseStatus::Solved);
            let d = s.iterations as i64 - ci as i64;
            total += 1;
            same += usize::from(d == 0);
            worst = worst.max(d.abs());
        }
        assert!(total >= 200 && same * 10 >= total * 9, "{same} of {total}");
        assert!(worst <= 2, "{worst}");
    }

    #[test]
    fn infeasible_programs_end_with_a_certificate() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        for trial in 0..300 {
            let (n, cones, mut s) = random_case(&mut rng, 4);
            let m = s.m;
            // z₀ interior with Aᵀz₀ = 0 and bᵀz₀ < 0: no x, s ∈ K with Ax + s = b
            let z0 = interior(&mut rng, &cones);
            let zz = dot(&z0, &z0);
            for j in 0..n {
                let proj = (0..m).map(|r| s.a[r * n + j] * z0[r]).sum::<f64>() / zz;
                for r in 0..m {
                    s.a[r * n + j] -= proj * z0[r];
                }
            }
            for v in s.b.iter_mut() {
                *v = normal(&mut rng);
            }
            let bz = dot(&s.b, &z0);
            let shift = (bz + 1.0) / zz;
            for r in 0..m {
                s.b[r] -= shift * z0[r];
            }
            assert!(dot(&s.b, &z0) < 0.0);
            assert_eq!(s.solve(), DenseStatus::PrimalInfeasible, "trial {trial}");
            let z = s.z();
            assert!(dot(&s.b, z) < 0.0);
            let atz: f64 = (0..n)
                .map(|j| (0..m).map(|r| s.a[r * n + j] * z[r]).sum::<f64>().powi(2))
                .sum::<f64>()
                .sqrt();
            assert!(atz < 1e-6 * -dot(&s.b, z), "trial {trial}: ‖Aᵀz‖ = {atz}");
            assert!(margin(&cones, z) > -1e-9 * norm(z), "trial {trial}: z ∉ K*");
        }
    }

    #[test]
    fn random_programs_never_contradict_clarabel() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let (mut agree, mut fell_back, mut total) = (0, 0, 0);
        for trial in 0..1000 {
            let (_, cones, mut s) = random_case(&mut rng, 5);
            for v in s.b.iter_mut() {
                *v = normal(&mut rng);
            }
            let (cs, _, cobj) = clarabel(&s, &cones);
            let st = s.solve();
            total += 1;
            match (cs, st) {
                (SolverStatus::Solved, DenseStatus::Solved) => {
                    assert_kkt(&s, &cones);
                    let obj = objective(&s);
                    assert!(
                        (obj - cobj).abs() <= 1e-6 * (1.0 + cobj.abs()),
                        "trial {trial}"
                    );
                    agree += 1;
                }
                (SolverStatus::PrimalInfeasible, DenseStatus::PrimalInfeasible)
                | (SolverStatus::DualInfeasible, DenseStatus::DualInfeasible) => agree += 1,
                (_, DenseStatus::Failed) => fell_back += 1,
                (c, d) => panic!("trial {trial}: Clarabel {c:?}, dense {d:?}"),
            }
        }
        // Failed hands the program to Clarabel: allowed, but rare
        assert!(fell_back * 100 <= total, "{fell_back} of {total} fell back");
        assert_eq!(agree + fell_back, total);
    }

    /// A non-finite entry anywhere makes the first KKT factorisation or
    /// solve non-finite: the solver stops before iterating.
    #[test]
    fn non_finite_data_fail_before_the_first_iteration() {
        let mut s = DenseConeSolver::new(2, &[Cone::SecondOrder(3)]);
        s.p[0] = 1.0;
        s.p[3] = 1.0;
        s.a[0] = -1.0;
        s.a[3] = -1.0;
        s.b[0] = 1.0;
        assert_eq!(s.solve(), DenseStatus::Solved);
        for poison in [f64::NAN, f64::INFINITY] {
            for field in 0..4 {
                let mut t = s.clone();
                match field {
                    0 => t.b[1] = poison,
                    1 => t.q[0] = poison,
                    2 => t.a[2] = poison,
                    _ => t.p[1] = poison,
                }
                assert_eq!(t.solve(), DenseStatus::Failed, "{field} {poison}");
                assert_eq!(t.iterations, 0);
            }
        }
    }

    #[test]
    fn projection_onto_a_second_order_cone_has_its_closed_form() {
        // min ½‖x − a‖² s.t. x ∈ SOC: x = a inside, 0 in the polar cone,
        // ((a₀ + ‖a₁‖)/2)(1, a₁/‖a₁‖) otherwise
        for a in [
            [2.0, 1.0, -0.5],
            [-3.0, 1.0, 1.0],
            [0.5, 2.0, -1.0],
            [0.0, 0.3, 0.4],
        ] {
            let mut s = DenseConeSolver::new(3, &[Cone::SecondOrder(3)]);
            for i in 0..3 {
                s.p[i * 3 + i] = 1.0;
                s.q[i] = -a[i];
                s.a[i * 3 + i] = -1.0;
            }
            assert_eq!(s.solve(), DenseStatus::Solved);
            let t = norm(&a[1..]);
            let expected = if t <= a[0] {
                a.to_vec()
            } else if t <= -a[0] {
                vec![0.0; 3]
            } else {
                let f = (a[0] + t) / 2.0;
                vec![f, f * a[1] / t, f * a[2] / t]
            };
            for (x, e) in s.x().iter().zip(&expected) {
                assert!((x - e).abs() < 1e-7, "{a:?}: {x} against {e}");
            }
        }
    }

    #[test]
    fn nesterov_todd_scaling_identities() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let cones = [
            Cone::SecondOrder(4),
            Cone::NonNegative(3),
            Cone::SecondOrder(2),
        ];
        let mut s = DenseConeSolver::new(1, &cones);
        for _ in 0..200 {
            s.v.s = interior(&mut rng, &cones);
            s.v.z = interior(&mut rng, &cones);
            assert!(s.update_scaling());
            let r: Vec<f64> = (0..s.m).map(|_| normal(&mut rng)).collect();
            for (k, &(c, o)) in s.sc.cones.iter().enumerate() {
                let d = c.dim();
                let (w, eta) = (&s.sc.wbar[o..o + d], s.sc.eta[k]);
                let (sv, zv, lam) = (&s.v.s[o..o + d], &s.v.z[o..o + d], &s.lambda[o..o + d]);
                let close = |a: &[f64], b: &[f64]| {
                    a.iter()
                        .zip(b)
                        .all(|(x, y)| (x - y).abs() < 1e-9 * (1.0 + y.abs()))
                };
                // W z = W⁻ᵀ s = λ
                let mut t = vec![0.0; d];
                winv_mul(c, eta, w, sv, &mut t);
                assert!(close(&t, lam));
                w_mul(c, eta, w, zv, &mut t);
                assert!(close(&t, lam));
                // H z = s, H⁻¹ H r = r, W⁻¹ W r = r
                h_mul(c, eta, w, zv, &mut t);
                assert!(close(&t, sv));
                let mut u = vec![0.0; d];
                h_mul(c, eta, w, &r[o..o + d], &mut t);
                hinv_mul(c, eta, w, &t, &mut u);
                assert!(close(&u, &r[o..o + d]));
                w_mul(c, eta, w, &r[o..o + d], &mut t);
                winv_mul(c, eta, w, &t, &mut u);
                assert!(close(&u, &r[o..o + d]));
                // λ ∘ (λ \ r) = r
                inv_circ(c, lam, &r[o..o + d], &mut t);
                circ(c, lam, &t, &mut u);
                assert!(close(&u, &r[o..o + d]));
            }
        }
    }

    /// The largest `t ∈ [0, cap]` with `x + t d` in the cone `c`, by
    /// bisection on membership (the `t` with `x + t d ∈ K` form an interval
    /// from 0: `K` is convex and `x ∈ K`).
    fn max_step(c: Cone, x: &[f64], d: &[f64], cap: f64) -> f64 {
        let inside = |t: f64| {
            let y: Vec<f64> = x.iter().zip(d).map(|(a, b)| a + t * b).collect();
            match c {
                Cone::NonNegative(_) => y.iter().all(|&v| v >= 0.0),
                Cone::SecondOrder(_) => y[0] >= norm(&y[1..]),
            }
        };
        if inside(cap) {
            return cap;
        }
        let (mut lo, mut hi) = (0.0, cap);
        for _ in 0..200 {
            let mid = 0.5 * (lo + hi);
            if inside(mid) {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        lo
    }

    /// The step to one cone's boundary (`cone_step`) is the largest
    /// `t ≤ cap` with `x + t d` in the cone: against bisection on membership
    /// at random interior points and directions (some with a zero entry),
    /// and at the cases Clarabel's `_step_length_soc_component` treats
    /// apart where its rule gives that step: the head reaching zero first,
    /// a zero head of `d`, a point on the boundary, a direction along it,
    /// and a tiny `x₀² − ‖x₁‖²`, whose root the cancellation-free formula
    /// keeps accurate; and a direction on the boundary of `±K` (`a = 0`),
    /// where the residual is linear and the exit is `−c/b` if `b < 0`
    /// (Clarabel's rule returns the cap there).
    #[test]
    fn cone_step_reaches_the_boundary() {
        let close = |got: f64, want: f64| (got - want).abs() <= 1e-9 * want.max(1e-6);
        let mut rng = ChaCha8Rng::seed_from_u64(22);
        for trial in 0..3000 {
            let c = if trial % 2 == 0 {
                Cone::NonNegative(rng.random_range(1..5))
            } else {
                Cone::SecondOrder(rng.random_range(2..5))
            };
            let x = interior(&mut rng, &[c]);
            let scale = 10f64.powf(rng.random_range(-2.0..2.0));
            let mut d = scaled(&mut rng, c.dim(), scale);
            if trial % 5 == 1 {
                let i = rng.random_range(0..c.dim());
                d[i] = 0.0;
            }
            let cap = if rng.random_bool(0.5) {
                1.0
            } else {
                rng.random_range(0.1..5.0)
            };
            let (got, want) = (cone_step(c, &x, &d, cap), max_step(c, &x, &d, cap));
            assert!(
                close(got, want),
                "trial {trial}: {c:?} x {x:?} d {d:?} cap {cap}: {got} against {want}"
            );
        }
        let soc = Cone::SecondOrder(3);
        // name, x, d, cap and the step
        type Case = (&'static str, [f64; 3], [f64; 3], f64, f64);
        let cases: [Case; 11] = [
            // x + t d = (1 − t) x: the head and the J-norm reach 0 at t = 1
            (
                "along −x, x on the boundary",
                [1.0, 1.0, 0.0],
                [-1.0, -1.0, 0.0],
                2.0,
                1.0,
            ),
            (
                "along −x, x interior",
                [2.0, 1.0, 0.0],
                [-2.0, -1.0, 0.0],
                3.0,
                1.0,
            ),
            // (2, t, 0) leaves at t = 2
            ("d₀ = 0", [2.0, 0.0, 0.0], [0.0, 1.0, 0.0], 5.0, 2.0),
            // (1, 1 + t, 0) leaves at once
            (
                "x on the boundary, leaving",
                [1.0, 1.0, 0.0],
                [0.0, 1.0, 0.0],
                1.0,
                0.0,
            ),
            // (1, 1, t) leaves at once (x₀² − ‖x₁‖² = 0 and a zero
            // discriminant)
            (
                "x on the boundary, across it",
                [1.0, 1.0, 0.0],
                [0.0, 0.0, 1.0],
                1.0,
                0.0,
            ),
            // (2 + t, t, 0) never leaves
            (
                "d on the boundary",
                [2.0, 0.0, 0.0],
                [1.0, 1.0, 0.0],
                3.0,
                3.0,
            ),
            // (1 − t, t, 0): d on the boundary of −K, leaving at t = 1/2
            // (x₀² − ‖x₁‖² = 1 − 2t)
            (
                "d on the boundary of −K, leaving",
                [1.0, 0.0, 0.0],
                [-1.0, 1.0, 0.0],
                1.0,
                0.5,
            ),
            // (2 + t, 1 − t, 0): d on the boundary of K, x₀² − ‖x₁‖² = 3 + 6t
            // grows
            (
                "d on the boundary of K, entering",
                [2.0, 1.0, 0.0],
                [1.0, -1.0, 0.0],
                4.0,
                4.0,
            ),
            // no direction: a = b = 0, x stays
            ("d = 0", [2.0, 1.0, 0.0], [0.0, 0.0, 0.0], 3.0, 3.0),
            // (x₀ + t, 1 − 1.5t, 0) leaves at t = 2(x₀ + 1)
            (
                "x₀² − ‖x₁‖² ≈ 2·10⁻¹³",
                [1.0 + 1e-13, 1.0, 0.0],
                [1.0, -1.5, 0.0],
                10.0,
                2.0 * (2.0 + 1e-13),
            ),
            // (1 − t, 0.99 + (1 + 10⁻⁸)t, 0) leaves at t = 0.01/(2 + 10⁻⁸), the
            // small root of a quadratic with |4ac| ≪ b²
            (
                "|4ac| ≪ b², b < 0",
                [1.0, 0.99, 0.0],
                [-1.0, 1.0 + 1e-8, 0.0],
                1.0,
                (1.0 - 0.99) / (2.0 + 1e-8),
            ),
        ];
        for (name, x, d, cap, want) in cases {
            let got = cone_step(soc, &x, &d, cap);
            assert!(close(got, want), "{name}: {got} against {want}");
            // bisection resolves the tangential exit only to √ε
            let reference = max_step(soc, &x, &d, cap);
            assert!(
                (reference - want).abs() < 1e-7,
                "{name}: reference {reference}"
            );
        }
    }

    /// The step length (`step_length`) is the largest `α ≤ 1` that keeps
    /// `τ, κ ≥ 0` and each cone's `s` and `z` in the cone, times 0.99 for
    /// the corrector: against bisection on membership at random iterates
    /// and steps of three cones, with `Δτ` or `Δκ` zero (no limit) in some.
    #[test]
    fn step_length_keeps_the_iterate_in_the_cones() {
        let mut rng = ChaCha8Rng::seed_from_u64(23);
        let cones = [
            Cone::SecondOrder(3),
            Cone::NonNegative(2),
            Cone::SecondOrder(2),
        ];
        let mut d = DenseConeSolver::new(1, &cones);
        for trial in 0..500 {
            let scale = 10f64.powf(rng.random_range(-1.0..1.5));
            d.v.s = interior(&mut rng, &cones);
            d.v.z = interior(&mut rng, &cones);
            d.v.tau = 10f64.powf(rng.random_range(-1.0..1.0));
            d.v.kappa = 10f64.powf(rng.random_range(-3.0..1.0));
            d.step.s = scaled(&mut rng, d.m, scale);
            d.step.z = scaled(&mut rng, d.m, scale);
            d.step.tau = if trial % 4 == 1 {
                0.0
            } else {
                scale * normal(&mut rng)
            };
            d.step.kappa = if trial % 4 == 2 {
                0.0
            } else {
                scale * normal(&mut rng)
            };
            let mut want = 1.0f64;
            for (v, dv) in [(d.v.tau, d.step.tau), (d.v.kappa, d.step.kappa)] {
                want = want.min(max_step(Cone::NonNegative(1), &[v], &[dv], 1.0));
            }
            for &(c, o) in &d.sc.cones {
                let r = o..o + c.dim();
                want = want.min(max_step(c, &d.v.s[r.clone()], &d.step.s[r.clone()], 1.0));
                want = want.min(max_step(c, &d.v.z[r.clone()], &d.step.z[r], 1.0));
            }
            for (combined, f) in [(false, 1.0), (true, 0.99)] {
                let got = d.step_length(combined);
                assert!(
                    (got - f * want).abs() <= 1e-9 * want.max(1e-6),
                    "trial {trial}, combined {combined}: {got} against {}",
                    f * want
                );
            }
        }
    }

    /// `K = [P Aᵀ; A −H]` written out, with `H = WᵀW` from its definition
    /// for each cone: `η²(2w̄w̄ᵀ − J)` for a SOC, `diag(w²)` for the orthant.
    fn kkt_matrix(s: &DenseConeSolver) -> Vec<Vec<f64>> {
        let (n, m) = (s.n, s.m);
        let mut k = vec![vec![0.0; n + m]; n + m];
        for i in 0..n {
            for j in 0..n {
                k[i][j] = s.p[i * n + j];
            }
            for r in 0..m {
                k[i][n + r] = s.a[r * n + i];
                k[n + r][i] = s.a[r * n + i];
            }
        }
        for (idx, &(c, o)) in s.sc.cones.iter().enumerate() {
            let (w, eta) = (&s.sc.wbar[o..o + c.dim()], s.sc.eta[idx]);
            for i in 0..c.dim() {
                for j in 0..c.dim() {
                    let h = match c {
                        Cone::NonNegative(_) => {
                            if i == j {
                                w[i] * w[i]
                            } else {
                                0.0
                            }
                        }
                        Cone::SecondOrder(_) => {
                            let jij = match (i, j) {
                                (0, 0) => 1.0,
                                _ if i == j => -1.0,
                                _ => 0.0,
                            };
                            eta * eta * (2.0 * w[i] * w[j] - jij)
                        }
                    };
                    k[n + o + i][n + o + j] = -h;
                }
            }
        }
        k
    }

    /// The largest entry of `r − K x`, relative to `‖K‖∞‖x‖∞ + ‖r‖∞`.
    fn kkt_backward_error(k: &[Vec<f64>], x: &[f64], r: &[f64]) -> f64 {
        let inf = |v: &[f64]| v.iter().fold(0.0f64, |a, &b| a.max(b.abs()));
        let knorm = k
            .iter()
            .map(|row| row.iter().map(|v| v.abs()).sum::<f64>())
            .fold(0.0, f64::max);
        let res = k
            .iter()
            .zip(r)
            .map(|(row, ri)| (ri - dot(row, x)).abs())
            .fold(0.0, f64::max);
        res / (knorm * inf(x) + inf(r))
    }

    /// A KKT solve with iterative refinement (`solve_kkt` with `refine`
    /// steps) solves `K [x; z] = r` to its tolerance: a backward error
    /// `‖r − K[x; z]‖∞ / (‖K‖∞‖[x; z]‖∞ + ‖r‖∞)` of at most 10⁻¹³, with `K`
    /// written out from its definition, at the scaling where 200 random
    /// programs stopped (there `H` is ill-conditioned and the elimination
    /// of `z` alone loses digits), for right-hand sides of norm 1 and 10³.
    /// A right-hand side of norm 10⁻¹³, below the absolute tolerance
    /// 10⁻¹², stops the refinement at once: only the elimination's accuracy
    /// (10⁻⁶) is asked of it.
    #[test]
    fn refined_kkt_solves_are_backward_stable() {
        let mut rng = ChaCha8Rng::seed_from_u64(24);
        let (mut worst_unrefined, mut solved) = (0.0f64, 0);
        for trial in 0..200 {
            let (n, cones, mut s) = random_case(&mut rng, 5);
            let x0: Vec<f64> = (0..n).map(|_| normal(&mut rng)).collect();
            let s0 = interior(&mut rng, &cones);
            for r in 0..s.m {
                s.b[r] = dot(&s.a[r * n..(r + 1) * n], &x0) + s0[r];
            }
            if s.solve() != DenseStatus::Solved {
                continue;
            }
            solved += 1;
            assert!(s.factor_kkt(), "trial {trial}");
            let k = kkt_matrix(&s);
            for scale in [1e-13, 1.0, 1e3] {
                let r = scaled(&mut rng, s.n + s.m, scale);
                for refine in [0, REFINE_STEPS] {
                    s.refine = refine;
                    s.rhs_full.copy_from_slice(&r);
                    assert!(s.solve_kkt(), "trial {trial}");
                    let e = kkt_backward_error(&k, &s.sol_full, &r);
                    if refine == 0 {
                        worst_unrefined = worst_unrefined.max(e);
                    } else {
                        let bound = if scale < 1e-12 { 1e-6 } else { 1e-13 };
                        assert!(e <= bound, "trial {trial}, scale {scale}: {e}");
                    }
                }
            }
        }
        assert!(solved >= 150, "{solved}");
        // the programs include systems that need the refinement
        assert!(worst_unrefined > 1e-12, "{worst_unrefined}");
    }

    /// `W⁻¹` of the current scaling as an `m × m` matrix, block by block
    /// from its definition: `(1/η)[w̄₀, −w̄₁ᵀ; −w̄₁, I + w̄₁w̄₁ᵀ/(1 + w̄₀)]` for
    /// a SOC, `diag(1/w)` for the orthant.
    fn scaling_inverse(s: &DenseConeSolver) -> Vec<Vec<f64>> {
        let m = s.m;
        let mut winv = vec![vec![0.0; m]; m];
        for (k, &(c, o)) in s.sc.cones.iter().enumerate() {
            let (wb, eta) = (&s.sc.wbar[o..o + c.dim()], s.sc.eta[k]);
            for i in 0..c.dim() {
                for j in 0..c.dim() {
                    winv[o + i][o + j] = match c {
                        Cone::NonNegative(_) if i == j => 1.0 / wb[i],
                        Cone::NonNegative(_) => 0.0,
                        Cone::SecondOrder(_) => match (i, j) {
                            (0, 0) => wb[0] / eta,
                            (0, _) => -wb[j] / eta,
                            (_, 0) => -wb[i] / eta,
                            _ => {
                                let id = if i == j { 1.0 } else { 0.0 };
                                (id + wb[i] * wb[j] / (1.0 + wb[0])) / eta
                            }
                        },
                    };
                }
            }
        }
        winv
    }

    /// The factor of the KKT system (`factor_kkt`) is the Cholesky factor
    /// of `M + εI`, `M = P + AᵀH⁻¹A` with `H⁻¹ = W⁻¹W⁻¹` written out from
    /// its definition and `ε = ϵ·max|M_ii|` (the static regularisation):
    /// `LLᵀ` against `M` at random interior points of random programs, and
    /// `L` itself where `M` is exactly singular (a variable in no
    /// constraint and without cost), where only `ε` makes the pivot
    /// positive.
    #[test]
    fn kkt_factor_is_the_cholesky_factor_of_the_reduced_matrix() {
        let mut rng = ChaCha8Rng::seed_from_u64(26);
        for trial in 0..200 {
            let (n, cones, mut d) = random_case(&mut rng, 5);
            let m = d.m;
            for r in 0..m {
                for j in 0..n {
                    d.at[j * m + r] = d.a[r * n + j];
                }
            }
            d.v.s = interior(&mut rng, &cones);
            d.v.z = interior(&mut rng, &cones);
            assert!(d.update_scaling() && d.factor_kkt(), "trial {trial}");
            let winv = scaling_inverse(&d);
            // W⁻¹A, column by column
            let wa: Vec<Vec<f64>> = (0..n)
                .map(|j| {
                    let col: Vec<f64> = (0..m).map(|r| d.a[r * n + j]).collect();
                    winv.iter().map(|row| dot(row, &col)).collect::<Vec<f64>>()
                })
                .collect();
            let l = &d.chol;
            let eps = f64::EPSILON
                * (0..n)
                    .map(|i| (d.p[i * n + i] + dot(&wa[i], &wa[i])).abs())
                    .fold(0.0, f64::max);
            for i in 0..n {
                for j in 0..=i {
                    let shift = if i == j { eps } else { 0.0 };
                    let want = d.p[i * n + j] + dot(&wa[i], &wa[j]) + shift;
                    let got: f64 = (0..=j).map(|t| l[i * n + t] * l[j * n + t]).sum();
                    let size = d.p[i * n + j].abs() + norm(&wa[i]) * norm(&wa[j]);
                    assert!(
                        (got - want).abs() <= 1e-12 * size,
                        "trial {trial}: (LLᵀ)_{i}{j} = {got} against {want}"
                    );
                }
            }
        }
        // P = 0, A = [0 1; 0 2], s = z = 1 (H = I): M = diag(0, 5)
        let mut d = DenseConeSolver::new(2, &[Cone::NonNegative(2)]);
        d.a = vec![0.0, 1.0, 0.0, 2.0];
        d.at = vec![0.0, 0.0, 1.0, 2.0];
        d.v.s = vec![1.0; 2];
        d.v.z = vec![1.0; 2];
        assert!(d.update_scaling() && d.factor_kkt());
        let eps = f64::EPSILON * 5.0;
        for (got, want) in [
            (d.chol[0], eps.sqrt()),
            (d.chol[2], 0.0),
            (d.chol[3], (5.0 + eps).sqrt()),
        ] {
            assert!((got - want).abs() <= 1e-14 * want, "{got} against {want}");
        }
        // not positive definite: a pivot that overflows (P₀₀ = f64::MAX,
        // P₁₁ = 1), and M = 0 of one variable (a zero pivot even with ε)
        d.a.fill(0.0);
        d.at.fill(0.0);
        d.p = vec![f64::MAX, 0.0, 0.0, 1.0];
        assert!(!d.factor_kkt());
        let mut d = DenseConeSolver::new(1, &[Cone::NonNegative(1)]);
        d.v.s = vec![1.0];
        d.v.z = vec![1.0];
        assert!(d.update_scaling() && !d.factor_kkt());
    }
}
