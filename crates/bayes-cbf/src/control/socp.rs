//! The safety SOCP (paper, Prop. 2 and Prop. 4), built once and updated in
//! place each step; solved by the dense interior-point method of
//! [`dense_cone`](super::dense_cone), with Clarabel as the fallback.
//!
//! Variables `x = [u; δ]` (δ only with a CLF). With `u̲ = [1; u]`:
//!
//! ```text
//! min  ‖R(u − û)‖² + λ δ²
//! s.t. ‖c_i V_i u̲‖ ≤ e_iᵀu̲ − ζ             for every barrier i   (SCBC_i ≥ 0)
//!      ‖c_V P u̲‖ ≤ δ − qᵀu̲                  (CLF, optional)        (SCLC ≤ δ)
//!      u_min ≤ u ≤ u_max                    (optional)
//! ```
//!
//! Prop. 2 writes the objective through an epigraph variable,
//! `min y s.t. ‖[R(u − û); √λ δ]‖ ≤ y`; the quadratic objective used here has
//! the same minimiser and is handled natively by both solvers.

use super::dense_cone::{Cone, DenseConeSolver, DenseStatus};
use crate::barrier::ConditionMoments;
use clarabel::algebra::CscMatrix;
use clarabel::solver::{DefaultSettings, DefaultSolver, IPSolver, SolverStatus, SupportedConeT};

/// Shape of a safety SOCP.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SocpShape {
    /// Control dimension `m`.
    pub m: usize,
    /// Number of barrier constraints.
    pub barriers: usize,
    /// Whether a CLF constraint (with slack δ) is present.
    pub clf: bool,
    /// Whether box bounds are present.
    pub bounds: bool,
}

/// What the solver reported.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SolveStatus {
    /// Solved to full accuracy.
    Optimal,
    /// Solved to reduced accuracy.
    AlmostOptimal,
    /// Certified (or nearly certified) infeasible.
    Infeasible,
    /// Unbounded or dual infeasible (cannot happen with a PD objective).
    Unbounded,
    /// Iteration/time limit, numerical error or lack of progress.
    Failed,
}

impl SolveStatus {
    fn from_clarabel(s: SolverStatus) -> Self {
        match s {
            SolverStatus::Solved => Self::Optimal,
            SolverStatus::AlmostSolved => Self::AlmostOptimal,
            SolverStatus::PrimalInfeasible | SolverStatus::AlmostPrimalInfeasible => {
                Self::Infeasible
            }
            SolverStatus::DualInfeasible | SolverStatus::AlmostDualInfeasible => Self::Unbounded,
            _ => Self::Failed,
        }
    }
    /// A usable primal solution.
    pub fn is_solved(self) -> bool {
        matches!(self, Self::Optimal | Self::AlmostOptimal)
    }
}

/// The solver whose solution [`ConeProgram::x`] returns.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Answer {
    Dense,
    /// Clarabel without (0) or with (1) iterative refinement.
    Clarabel(usize),
    /// The reference `û` itself, feasible ([`ConeProgram::reference_feasible`]).
    Reference,
}

/// A conic program of fixed sparsity whose values are updated in place.
pub(crate) struct ConeProgram {
    shape: SocpShape,
    /// Extra variable: δ (CLF) in the control problem, t in the max-margin problem.
    extra: bool,
    /// The max-margin variant (min −t, t in every barrier row 0).
    max_margin: bool,
    pub(crate) a_nz: Vec<f64>,
    pub(crate) b: Vec<f64>,
    pub(crate) q: Vec<f64>,
    pub(crate) p_nz: Vec<f64>,
    per_col: usize,
    /// `[fast, refined]`: without and with iterative refinement
    /// ([`settings`](Self::settings)).
    solvers: [Option<DefaultSolver<f64>>; 2],
    /// The dense solver tried first ([`solve`](Self::solve)), built on first
    /// use.
    dense: Option<DenseConeSolver>,
    /// Which solver produced the last answer.
    last: Answer,
    a_pattern: (Vec<usize>, Vec<usize>),
    p_pattern: (Vec<usize>, Vec<usize>),
    cones: Vec<SupportedConeT<f64>>,
    /// Scratch for one row of `A` (capacity `m`, reused).
    g_buf: Vec<f64>,
    /// The reference `û` (length `m`).
    u_ref: Vec<f64>,
    /// Scratch for `b − Ax` (one entry per row).
    s_buf: Vec<f64>,
    /// The data as set, kept while [`rescue`](Self::rescue) rescales them
    /// (`b`, `q`, `P`; allocated at construction).
    saved: (Vec<f64>, Vec<f64>, Vec<f64>),
    /// How the last answer's program differs from the one set:
    /// the factor its objective was divided by and whether a bound was
    /// capped, and the cap (see [`rescue`](Self::rescue)); `(1, None)` if
    /// not rescued.
    rescued: (f64, Option<f64>),
}

/// The rescue's first cap on the box bounds ([`ConeProgram::rescue`]);
/// a bound beyond it times `max(1, ‖û‖∞)` sends a program to the rescue.
const RESCUE_CAP: f64 = 1e3;
/// The factor between successive caps: a cap far above the minimiser
/// (10⁹ for one at 10⁷) is already beyond the solvers' range.
const RESCUE_CAP_STEP: f64 = 10.0;
/// Caps tried before the bounds as set: 10³, 10⁴, …, 10¹².
const RESCUE_CAPS: usize = 10;
/// Objective entries above this go to the rescue (see
/// [`ConeProgram::badly_scaled`]).
const RESCALE_ABOVE: f64 = 1e4;

impl ConeProgram {
    pub(crate) fn new(shape: SocpShape, max_margin: bool) -> Self {
        let (m, p) = (shape.m, shape.m + 1);
        let blocks = shape.barriers + usize::from(shape.clf && !max_margin);
        let extra = if max_margin { true } else { shape.clf };
        let nv = m + usize::from(extra);
        let per_col = blocks * (1 + p) + if shape.bounds { 2 } else { 0 };
        let rows = blocks * (1 + p) + if shape.bounds { 2 * m } else { 0 };
        // A pattern
        let mut colptr = vec![0usize];
        let mut rowval = Vec::new();
        for j in 0..m {
            for r in 0..blocks * (1 + p) {
                rowval.push(r);
            }
            if shape.bounds {
                rowval.push(blocks * (1 + p) + 2 * j);
                rowval.push(blocks * (1 + p) + 2 * j + 1);
            }
            colptr.push(rowval.len());
        }
        if extra {
            if max_margin {
                for k in 0..shape.barriers {
                    rowval.push(k * (1 + p));
                }
            } else {
                rowval.push(shape.barriers * (1 + p));
            }
            colptr.push(rowval.len());
        }
        let a_nz = vec![0.0; rowval.len()];
        // P pattern: upper triangle of the u block, plus the δ diagonal
        let mut pcol = vec![0usize];
        let mut prow = Vec::new();
        for j in 0..m {
            for i in 0..=j {
                prow.push(i);
            }
            pcol.push(prow.len());
        }
        if extra {
            if !max_margin {
                prow.push(m);
            }
            pcol.push(prow.len());
        }
        let mut cones = Vec::new();
        for _ in 0..blocks {
            cones.push(SupportedConeT::SecondOrderConeT(1 + p));
        }
        if shape.bounds {
            cones.push(SupportedConeT::NonnegativeConeT(2 * m));
        }
        let p_len = prow.len();
        let mut prog = Self {
            shape,
            extra,
            max_margin,
            a_nz,
            b: vec![0.0; rows],
            q: vec![0.0; nv],
            p_nz: vec![0.0; prow.len()],
            per_col,
            solvers: [None, None],
            dense: None,
            last: Answer::Clarabel(0),
            a_pattern: (colptr, rowval),
            p_pattern: (pcol, prow),
            cones,
            g_buf: Vec::with_capacity(m),
            u_ref: vec![0.0; m],
            s_buf: vec![0.0; rows],
            saved: (vec![0.0; rows], vec![0.0; nv], vec![0.0; p_len]),
            rescued: (1.0, None),
        };
        // constant entries
        if shape.bounds {
            for j in 0..m {
                let base = j * per_col + blocks * (1 + p);
                prog.a_nz[base] = 1.0;
                prog.a_nz[base + 1] = -1.0;
            }
        }
        if extra {
            let base = m * per_col;
            if max_margin {
                for k in 0..shape.barriers {
                    prog.a_nz[base + k] = 1.0;
                }
                prog.q[m] = -1.0;
            } else {
                prog.a_nz[base] = -1.0;
            }
        }
        prog
    }

    /// Writes the SOC block `k`: `s0 = b0 + offset + g·u (+ …)`, `s_t = c(V u̲)_t`.
    /// For a barrier `g = e_u`, `b0 = e_0 − ζ`; for the CLF `g = −q_u`, `b0 = −q_0`.
    fn set_block(&mut self, k: usize, g: &[f64], b0: f64, c: f64, v: &nalgebra::DMatrix<f64>) {
        let (m, p) = (self.shape.m, self.shape.m + 1);
        let row0 = k * (1 + p);
        for j in 0..m {
            let base = j * self.per_col + row0;
            self.a_nz[base] = -g[j];
            for t in 0..p {
                self.a_nz[base + 1 + t] = -c * v[(t, j + 1)];
            }
        }
        self.b[row0] = b0;
        for t in 0..p {
            self.b[row0 + 1 + t] = c * v[(t, 0)];
        }
    }

    pub(crate) fn set_barrier(&mut self, k: usize, mom: &ConditionMoments, c: f64, zeta: f64) {
        let mut g = std::mem::take(&mut self.g_buf);
        g.clear();
        g.extend_from_slice(&mom.e[1..]);
        self.set_block(k, &g, mom.e[0] - zeta, c, &mom.v);
        self.g_buf = g;
    }

    pub(crate) fn set_clf(&mut self, mom: &ConditionMoments, c: f64) {
        let k = self.shape.barriers;
        let mut g = std::mem::take(&mut self.g_buf);
        g.clear();
        g.extend(mom.e[1..].iter().map(|v| -v));
        self.set_block(k, &g, -mom.e[0], c, &mom.v);
        self.g_buf = g;
    }

    pub(crate) fn set_bounds(&mut self, lo: &[f64], hi: &[f64]) {
        let m = self.shape.m;
        let blocks = self.shape.barriers + usize::from(self.shape.clf && !self.max_margin);
        let base = blocks * (1 + m + 1);
        for j in 0..m {
            self.b[base + 2 * j] = hi[j];
            self.b[base + 2 * j + 1] = -lo[j];
        }
    }

    /// Objective `‖R(u − û)‖² + λδ²` as `½xᵀPx + qᵀx`, divided by the
    /// largest diagonal entry `w` of `RᵀR`, which leaves the minimiser
    /// unchanged and gives the solvers' gap tolerances a control term of
    /// unit order whatever the scale of `R` (`R = 10⁻⁵ I` objective values
    /// of 10⁻¹⁰ met the absolute gap tolerance at the first iterate). For
    /// `R = I` the data are as written.
    pub(crate) fn set_objective(&mut self, r: &nalgebra::DMatrix<f64>, u_ref: &[f64], lambda: f64) {
        let m = self.shape.m;
        let rtr =
            |i: usize, j: usize| -> f64 { (0..r.nrows()).map(|k| r[(k, i)] * r[(k, j)]).sum() };
        let w = (0..m).fold(0.0_f64, |a, i| a.max(rtr(i, i)));
        let mut t = 0;
        for j in 0..m {
            for i in 0..=j {
                self.p_nz[t] = 2.0 * (rtr(i, j) / w);
                t += 1;
            }
        }
        if self.extra && !self.max_margin {
            self.p_nz[t] = 2.0 * (lambda / w);
        }
        for i in 0..m {
            let mut s = 0.0;
            for j in 0..m {
                s += (rtr(i, j) / w) * u_ref[j];
            }
            self.q[i] = -2.0 * s;
        }
        self.u_ref.copy_from_slice(u_ref);
    }

    /// Clarabel settings of the safety SOCPs: the defaults (gap and
    /// feasibility tolerances 10⁻⁸) except **no equilibration**, and
    /// iterative refinement of the KKT solves only in the `refine` solver.
    ///
    /// Clarabel computes its Ruiz equilibration once, from the data of the
    /// first solve, and reapplies that scaling to every in-place update, so
    /// with it the answer at a step depends on the first state the filter saw.
    /// Without it each step solves exactly its own data (the data are of unit
    /// order already: `|e|`, `c‖V‖` and the bounds are O(1–10²)). Measured on
    /// the Ackermann workload at k = 200 this also halves the interior-point
    /// iterations at the benchmark state (14 → 7; 13.0 → 12.5 on average over
    /// 400 states), and on 3 000 random strictly feasible programs it solves
    /// all to full accuracy (2 `AlmostSolved` with equilibration).
    ///
    /// Iterative refinement is a quarter of the solver's time at k = 200.
    /// On the controller's programs it changes nothing measurable (400 of 400
    /// Ackermann steps `Solved` either way, the controls as close to a
    /// 10⁻¹² reference solve), but without it one random program in six ends
    /// `AlmostSolved` (13 %) or falsely infeasible (3 %). Hence [`solve`](Self::solve) tries the fast solver first
    /// and re-solves with refinement whenever the fast one does not report
    /// `Solved`; the termination test is on the true residuals, so a fast
    /// `Solved` meets the same tolerances.
    fn settings(refine: bool) -> DefaultSettings<f64> {
        DefaultSettings {
            verbose: false,
            presolve_enable: false,
            input_sparse_dropzeros: false,
            max_threads: 1,
            max_iter: 100,
            equilibrate_enable: false,
            iterative_refinement_enable: refine,
            ..DefaultSettings::default()
        }
    }

    /// Loads the current data into solver `i`, building it on first use
    /// (both solvers are built together, so that later steps allocate
    /// nothing). False if Clarabel rejects the problem.
    fn load(&mut self, i: usize) -> bool {
        let nv = self.q.len();
        let rows = self.b.len();
        let updated = match self.solvers[i].as_mut() {
            None => false,
            Some(s) => {
                s.update_A(&self.a_nz).is_ok()
                    && s.update_b(&self.b).is_ok()
                    && s.update_q(&self.q).is_ok()
                    && s.update_P(&self.p_nz).is_ok()
            }
        };
        if updated {
            return true;
        }
        let csc = |nrows, (colptr, rowval): &(Vec<usize>, Vec<usize>), nz: &Vec<f64>| {
            CscMatrix::new(nrows, nv, colptr.clone(), rowval.clone(), nz.clone())
        };
        let a = csc(rows, &self.a_pattern, &self.a_nz);
        let p = csc(nv, &self.p_pattern, &self.p_nz);
        for (j, slot) in self.solvers.iter_mut().enumerate() {
            if j == i || slot.is_none() {
                let settings = Self::settings(j == 1);
                match DefaultSolver::new(&p, &self.q, &a, &self.b, &self.cones, settings) {
                    Ok(s) => *slot = Some(s),
                    Err(e) => {
                        log::warn!("SOCP setup failed: {e}");
                        *slot = None;
                        return false;
                    }
                }
            }
        }
        true
    }

    /// Solves with the current data: the dense solver first
    /// ([`DenseConeSolver`]: the same homogeneous-embedding iteration and
    /// tolerances as Clarabel, without the sparse machinery), which answers
    /// when it converges to full accuracy or certifies infeasibility; else
    /// Clarabel's fast solver, then its refined one if the fast one does not
    /// report `Solved` (see [`settings`](Self::settings)). The first call
    /// builds the solvers, later calls update them in place.
    ///
    /// A program whose objective is positive definite cannot be unbounded:
    /// an `Unbounded` or `Failed` answer is the solvers' trouble with the
    /// data's scale (a reference or bounds far beyond the conditions' unit
    /// order), and [`rescue`](Self::rescue) solves an equivalent program.
    pub(crate) fn solve(&mut self) -> SolveStatus {
        self.rescued = (1.0, None);
        if self.badly_scaled() {
            return self.rescue(None);
        }
        match self.solve_once() {
            first @ (SolveStatus::Unbounded | SolveStatus::Failed) => self.rescue(Some(first)),
            status => status,
        }
    }

    /// Data beyond the solvers' unit order: an objective entry above
    /// [`RESCALE_ABOVE`] (a reference of ~10⁴), or a box bound beyond the
    /// rescue's first cap. Such programs go to [`rescue`](Self::rescue)
    /// directly: the solvers misread them as unbounded or infeasible.
    fn badly_scaled(&self) -> bool {
        let cap = RESCUE_CAP * self.u_ref.iter().fold(1.0_f64, |a, v| a.max(v.abs()));
        self.q
            .iter()
            .chain(&self.p_nz)
            .any(|v| v.abs() > RESCALE_ABOVE)
            || self.box_rows().any(|r| self.b[r] > cap)
    }

    /// One attempt: dense, then Clarabel.
    fn solve_once(&mut self) -> SolveStatus {
        match self.solve_dense() {
            DenseStatus::Solved => {
                self.last = Answer::Dense;
                return SolveStatus::Optimal;
            }
            DenseStatus::PrimalInfeasible => {
                self.last = Answer::Dense;
                return SolveStatus::Infeasible;
            }
            DenseStatus::DualInfeasible | DenseStatus::Failed => {}
        }
        self.solve_clarabel()
    }

    /// Solves programs with the minimiser of the one set, scaled to the
    /// solvers' unit order, after [`solve`](Self::solve) failed on it:
    ///
    /// - the objective divided by `s = max(1, ‖q‖∞, ‖P‖∞)`, which leaves
    ///   the minimiser unchanged (a reference `û` of 10⁶ makes `q` 10⁶);
    /// - each box bound beyond a cap `M` lowered to `M`, for `M = 10³, 10⁴,
    ///   …, 10¹²`, then the bounds as set. A minimiser with every
    ///   lowered bound inactive is the minimiser of the program as set (the
    ///   programs agree near it, and both are convex); one that meets a
    ///   lowered bound, or a program infeasible within the caps, goes on to
    ///   the next cap;
    /// - before these, a reference that meets every constraint is the
    ///   minimiser ([`reference_feasible`](Self::reference_feasible)).
    ///
    /// The data as set are restored afterwards; `rescued` records the
    /// difference, for [`duals`](Self::duals). The failed first answer
    /// stands if no program differs from it.
    fn rescue(&mut self, first: Option<SolveStatus>) -> SolveStatus {
        if self.reference_feasible() {
            return SolveStatus::Optimal;
        }
        let scale = self
            .q
            .iter()
            .chain(&self.p_nz)
            .fold(1.0_f64, |a, v| a.max(v.abs()));
        self.saved.0.copy_from_slice(&self.b);
        self.saved.1.copy_from_slice(&self.q);
        self.saved.2.copy_from_slice(&self.p_nz);
        for v in self.q.iter_mut().chain(self.p_nz.iter_mut()) {
            *v /= scale;
        }
        let rows = self.box_rows();
        let mut result = first.unwrap_or(SolveStatus::Failed);
        // the last capped program was infeasible
        let mut capped_infeasible = false;
        let mut cap = RESCUE_CAP;
        for tier in 0..=RESCUE_CAPS {
            let capping = tier < RESCUE_CAPS;
            let mut capped = false;
            for r in rows.clone() {
                let set = self.saved.0[r];
                capped |= capping && set > cap;
                self.b[r] = if capping { set.min(cap) } else { set };
            }
            if capping && !capped {
                continue; // no bound beyond this cap, nor beyond the larger ones
            }
            if let Some(first) = first.filter(|_| !capped && scale == 1.0) {
                // the program as set, which failed (infeasible if every
                // capped program was)
                self.rescued = (1.0, None);
                result = if capped_infeasible {
                    SolveStatus::Infeasible
                } else {
                    first
                };
                break;
            }
            result = self.solve_once();
            self.rescued = (scale, capped.then_some(cap));
            if result.is_solved() && !self.within_box(rows.clone()) {
                // beyond the solvers' range: a bound missed by more than
                // their tolerance
                result = SolveStatus::Failed;
            }
            if !capping && capped_infeasible && !result.is_solved() {
                // infeasible within every cap: any feasible control lies
                // beyond the largest, past the solvers' range
                result = SolveStatus::Infeasible;
                break;
            }
            let failed = matches!(result, SolveStatus::Unbounded | SolveStatus::Failed);
            let cap_met = capped
                && result.is_solved()
                && rows.clone().any(|r| {
                    self.b[r] < self.saved.0[r]
                        && self.box_row_value(r) >= self.b[r] - 1e-6 * self.b[r].abs()
                });
            let infeasible_within_caps = capped && result == SolveStatus::Infeasible;
            capped_infeasible = infeasible_within_caps;
            if !(failed || cap_met || infeasible_within_caps) {
                break;
            }
            if !capping {
                break;
            }
            cap *= RESCUE_CAP_STEP;
        }
        self.b.copy_from_slice(&self.saved.0);
        self.q.copy_from_slice(&self.saved.1);
        self.p_nz.copy_from_slice(&self.saved.2);
        result
    }

    /// Whether the reference `û` meets every constraint, in a program
    /// whose only variable is `u` (no CLF): then it is the minimiser (the
    /// objective `‖R(u − û)‖²` is 0 there), and [`x`](Self::x) returns it.
    fn reference_feasible(&mut self) -> bool {
        if self.extra {
            return false;
        }
        self.slack_at_reference();
        let s = &self.s_buf;
        let mut row = 0;
        if s.iter().any(|v| !v.is_finite()) {
            return false;
        }
        for cone in &self.cones {
            let (ok, d) = match *cone {
                SupportedConeT::SecondOrderConeT(d) => {
                    // ‖tail‖ by hypot: squares of a far reference overflow
                    let tail = s[row + 1..row + d].iter().fold(0.0_f64, |a, v| a.hypot(*v));
                    (tail.is_finite() && s[row] >= tail, d)
                }
                SupportedConeT::NonnegativeConeT(d) => {
                    (s[row..row + d].iter().all(|&v| v >= 0.0), d)
                }
                _ => (false, 0),
            };
            if !ok {
                return false;
            }
            row += d;
        }
        self.last = Answer::Reference;
        true
    }

    /// `s_buf = b − A û`.
    fn slack_at_reference(&mut self) {
        self.s_buf.copy_from_slice(&self.b);
        for (j, &u) in self.u_ref.iter().enumerate() {
            for t in self.a_pattern.0[j]..self.a_pattern.0[j + 1] {
                self.s_buf[self.a_pattern.1[t]] -= self.a_nz[t] * u;
            }
        }
    }

    /// Whether the last solution meets the box rows `rows` (as now set) up
    /// to the solvers' tolerance, relative to the bound.
    fn within_box(&self, mut rows: std::ops::Range<usize>) -> bool {
        rows.all(|r| self.box_row_value(r) <= self.b[r] + 1e-6 * (1.0 + self.b[r].abs()))
    }

    /// `(Ax)_r` of box row `r` at the last solution: `u_j` for the row
    /// `start + 2j` (`u_j ≤ b`), `−u_j` for `start + 2j + 1` (`−u_j ≤ b`).
    fn box_row_value(&self, r: usize) -> f64 {
        let k = r - self.box_rows().start;
        let u = self.x()[k / 2];
        if k.is_multiple_of(2) {
            u
        } else {
            -u
        }
    }

    /// The rows of the box bounds: `u_j ≤ u_max,j` at `start + 2j`,
    /// `−u_j ≤ −u_min,j` at `start + 2j + 1` (empty without bounds).
    fn box_rows(&self) -> std::ops::Range<usize> {
        let rows = self.b.len();
        if self.shape.bounds {
            rows - 2 * self.shape.m..rows
        } else {
            rows..rows
        }
    }

    /// Copies the data into the dense solver (built on first use) and
    /// solves.
    fn solve_dense(&mut self) -> DenseStatus {
        let nv = self.q.len();
        let dense = self.dense.get_or_insert_with(|| {
            let cones: Vec<Cone> = self
                .cones
                .iter()
                .map(|c| match c {
                    SupportedConeT::SecondOrderConeT(d) => Cone::SecondOrder(*d),
                    SupportedConeT::NonnegativeConeT(d) => Cone::NonNegative(*d),
                    other => unreachable!("the safety SOCPs have no {other:?} cone"),
                })
                .collect();
            DenseConeSolver::new(nv, &cones)
        });
        dense.a.fill(0.0);
        for j in 0..nv {
            for t in self.a_pattern.0[j]..self.a_pattern.0[j + 1] {
                dense.a[self.a_pattern.1[t] * nv + j] = self.a_nz[t];
            }
        }
        dense.p.fill(0.0);
        for j in 0..nv {
            for t in self.p_pattern.0[j]..self.p_pattern.0[j + 1] {
                let i = self.p_pattern.1[t];
                dense.p[i * nv + j] = self.p_nz[t];
                dense.p[j * nv + i] = self.p_nz[t];
            }
        }
        dense.q.copy_from_slice(&self.q);
        dense.b.copy_from_slice(&self.b);
        dense.solve()
    }

    /// Clarabel: the fast solver, then the refined one.
    fn solve_clarabel(&mut self) -> SolveStatus {
        let mut fast = SolveStatus::Failed;
        if self.load(0) {
            if let Some(s) = self.solvers[0].as_mut() {
                s.solve();
                self.last = Answer::Clarabel(0);
                if s.solution.status == SolverStatus::Solved {
                    return SolveStatus::Optimal;
                }
                fast = SolveStatus::from_clarabel(s.solution.status);
            }
        }
        if !self.load(1) {
            return fast;
        }
        let Some(s) = self.solvers[1].as_mut() else {
            return fast;
        };
        s.solve();
        let refined = SolveStatus::from_clarabel(s.solution.status);
        if refined.is_solved() || !fast.is_solved() {
            self.last = Answer::Clarabel(1);
            refined
        } else {
            fast
        }
    }

    pub(crate) fn x(&self) -> &[f64] {
        match self.last {
            Answer::Reference => &self.u_ref,
            Answer::Dense => self.dense.as_ref().map(|d| d.x()).unwrap_or(&[]),
            Answer::Clarabel(i) => self.solvers[i]
                .as_ref()
                .map(|s| s.solution.x.as_slice())
                .unwrap_or(&[]),
        }
    }

    /// Primal slack `s` and dual `z` of the last solve (for KKT checks),
    /// of the program as set: after a [`rescue`](Self::rescue), `z` times
    /// the objective's scale, and `s = b − Ax` where a bound was capped;
    /// for the feasible reference, `s = b − Aû` and `z = 0`.
    pub(crate) fn duals(&self) -> (Vec<f64>, Vec<f64>) {
        let (s, z): (&[f64], &[f64]) = match self.last {
            Answer::Dense => match self.dense.as_ref() {
                Some(d) => (d.s(), d.z()),
                None => (&[], &[]),
            },
            Answer::Clarabel(i) => match self.solvers[i].as_ref() {
                Some(s) => (s.solution.s.as_slice(), s.solution.z.as_slice()),
                None => (&[], &[]),
            },
            Answer::Reference => (&self.s_buf, &[]),
        };
        let (scale, cap) = self.rescued;
        let mut s = s.to_vec();
        let mut z: Vec<f64> = z.iter().map(|v| v * scale).collect();
        if self.last == Answer::Reference {
            z = vec![0.0; s.len()];
        } else if let Some(cap) = cap {
            let (a, b, _, _) = self.dense();
            let ax = &a * nalgebra::DVector::from_column_slice(self.x());
            for (i, si) in s.iter_mut().enumerate() {
                *si = b[i] - ax[i];
            }
            // a lowered bound is inactive at an accepted answer: its
            // multiplier in the program as set is 0
            for r in self.box_rows() {
                if b[r] > cap {
                    z[r] = 0.0;
                }
            }
        }
        (s, z)
    }

    /// `(A, b, P, q)` in dense form (tests and diagnostics).
    pub(crate) fn dense(
        &self,
    ) -> (
        nalgebra::DMatrix<f64>,
        Vec<f64>,
        nalgebra::DMatrix<f64>,
        Vec<f64>,
    ) {
        let nv = self.q.len();
        let mut a = nalgebra::DMatrix::zeros(self.b.len(), nv);
        for j in 0..nv {
            for t in self.a_pattern.0[j]..self.a_pattern.0[j + 1] {
                a[(self.a_pattern.1[t], j)] = self.a_nz[t];
            }
        }
        let mut p = nalgebra::DMatrix::zeros(nv, nv);
        for j in 0..nv {
            for t in self.p_pattern.0[j]..self.p_pattern.0[j + 1] {
                let i = self.p_pattern.1[t];
                p[(i, j)] = self.p_nz[t];
                p[(j, i)] = self.p_nz[t];
            }
        }
        (a, self.b.clone(), p, self.q.clone())
    }

    pub(crate) fn cones(&self) -> &[SupportedConeT<f64>] {
        &self.cones
    }
}

#[cfg(test)]
mod tests {
    //! The two solvers of [`ConeProgram`] on the same sequence of programs:
    //! the dense one and the Clarabel fallback must agree, whatever the
    //! programs solved before.
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Random data in the program's pattern: `P = 2RᵀR + I`-like, `A`
    /// random, `b = Ax₀ + s₀` with `s₀` interior (strictly feasible).
    fn randomise(p: &mut ConeProgram, rng: &mut ChaCha8Rng) {
        for v in p.a_nz.iter_mut() {
            *v = rng.random_range(-1.0..1.0);
        }
        let nv = p.q.len();
        for j in 0..nv {
            for t in p.p_pattern.0[j]..p.p_pattern.0[j + 1] {
                let i = p.p_pattern.1[t];
                p.p_nz[t] = if i == j {
                    if p.max_margin && j == nv - 1 {
                        0.0
                    } else {
                        rng.random_range(1.0..3.0)
                    }
                } else {
                    rng.random_range(-0.3..0.3)
                };
            }
        }
        for (i, v) in p.q.iter_mut().enumerate() {
            *v = if p.max_margin && i == nv - 1 {
                -1.0
            } else {
                rng.random_range(-2.0..2.0)
            };
        }
        let (a, _, _, _) = p.dense();
        let x0: Vec<f64> = (0..nv).map(|_| rng.random_range(-0.5..0.5)).collect();
        let mut row = 0;
        for c in p.cones.clone() {
            let d = match c {
                SupportedConeT::SecondOrderConeT(d) | SupportedConeT::NonnegativeConeT(d) => d,
                _ => unreachable!(),
            };
            // s₀: (‖tail‖ + margin, tail) for a SOC, positive entries else
            let tail: Vec<f64> = (1..d).map(|_| rng.random_range(-1.0..1.0)).collect();
            for k in 0..d {
                let s0 = match c {
                    SupportedConeT::SecondOrderConeT(_) if k == 0 => {
                        tail.iter().map(|t| t * t).sum::<f64>().sqrt() + rng.random_range(0.01..1.0)
                    }
                    SupportedConeT::SecondOrderConeT(_) => tail[k - 1],
                    _ => rng.random_range(0.01..1.0),
                };
                let ax: f64 = (0..nv).map(|j| a[(row + k, j)] * x0[j]).sum();
                p.b[row + k] = ax + s0;
            }
            row += d;
        }
    }

    fn objective(p: &ConeProgram, x: &[f64]) -> f64 {
        let (_, _, pm, q) = p.dense();
        let n = x.len();
        let mut v = 0.0;
        for i in 0..n {
            v += q[i] * x[i];
            for j in 0..n {
                v += 0.5 * x[i] * pm[(i, j)] * x[j];
            }
        }
        v
    }

    /// Every Clarabel status has its meaning here: solved, almost solved,
    /// infeasible (also almost), unbounded (also almost), else failed.
    #[test]
    fn clarabel_statuses_map_to_ours() {
        use SolverStatus as C;
        for (c, ours) in [
            (C::Solved, SolveStatus::Optimal),
            (C::AlmostSolved, SolveStatus::AlmostOptimal),
            (C::PrimalInfeasible, SolveStatus::Infeasible),
            (C::AlmostPrimalInfeasible, SolveStatus::Infeasible),
            (C::DualInfeasible, SolveStatus::Unbounded),
            (C::AlmostDualInfeasible, SolveStatus::Unbounded),
            (C::MaxIterations, SolveStatus::Failed),
            (C::NumericalError, SolveStatus::Failed),
            (C::InsufficientProgress, SolveStatus::Failed),
        ] {
            assert_eq!(SolveStatus::from_clarabel(c), ours, "{c:?}");
        }
    }

    /// The box rows `u_j ≤ hi_j`, `−u_j ≤ −lo_j` of each control follow the
    /// cone blocks, two per control, and nothing else is written.
    #[test]
    fn bounds_fill_their_own_rows() {
        for (clf, max_margin) in [(true, false), (false, false), (true, true)] {
            let shape = SocpShape {
                m: 3,
                barriers: 2,
                clf,
                bounds: true,
            };
            let mut p = ConeProgram::new(shape, max_margin);
            p.b.fill(f64::NAN);
            p.set_bounds(&[-1.0, -2.0, -3.0], &[4.0, 5.0, 6.0]);
            let blocks = 2 + usize::from(clf && !max_margin);
            let base = blocks * (1 + 3 + 1);
            assert!(p.b[..base].iter().all(|v| v.is_nan()));
            assert_eq!(&p.b[base..base + 6], &[4.0, 1.0, 5.0, 2.0, 6.0, 3.0]);
        }
    }

    /// When Clarabel's fast solver stops short (here capped at one
    /// iteration), the refined one answers: with the solution of a feasible
    /// program and with the certificate of an infeasible one.
    #[test]
    fn refined_solver_answers_when_the_fast_one_stops_short() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let shape = SocpShape {
            m: 2,
            barriers: 2,
            clf: true,
            bounds: true,
        };
        let mut p = ConeProgram::new(shape, false);
        randomise(&mut p, &mut rng);
        assert_eq!(p.solve_clarabel(), SolveStatus::Optimal);
        assert_eq!(p.last, Answer::Clarabel(0));
        let reference = p.x().to_vec();
        let capped = DefaultSettings {
            max_iter: 1,
            ..ConeProgram::settings(false)
        };
        p.solvers[0]
            .as_mut()
            .expect("built by the first solve")
            .update_settings(capped)
            .expect("max_iter can be updated");
        assert_eq!(p.solve_clarabel(), SolveStatus::Optimal);
        assert_eq!(p.last, Answer::Clarabel(1));
        for (a, b) in p.x().iter().zip(&reference) {
            assert!((a - b).abs() < 1e-6, "{a} against {b}");
        }
        // u ≥ 1 and u ≤ −1: the capped fast solver fails, the refined one
        // certifies infeasibility, and that is the answer
        p.set_bounds(&[1.0, 1.0], &[-1.0, -1.0]);
        assert_eq!(p.solve_clarabel(), SolveStatus::Infeasible);
        assert_eq!(p.last, Answer::Clarabel(1));
    }

    #[test]
    fn dense_solver_and_clarabel_fallback_agree_along_a_sequence() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for (max_margin, bounds) in [(false, true), (false, false), (true, true)] {
            let shape = SocpShape {
                m: 2,
                barriers: 2,
                clf: true,
                bounds,
            };
            let mut p = ConeProgram::new(shape, max_margin);
            let mut compared = 0;
            for trial in 0..150 {
                randomise(&mut p, &mut rng);
                let dense = p.solve_dense();
                let xd = p.dense.as_ref().unwrap().x().to_vec();
                let clarabel = p.solve_clarabel();
                if dense == DenseStatus::DualInfeasible {
                    // an unbounded max-margin program
                    assert_eq!(clarabel, SolveStatus::Unbounded, "trial {trial}");
                    continue;
                }
                assert_eq!(dense, DenseStatus::Solved, "trial {trial}");
                assert_eq!(clarabel, SolveStatus::Optimal, "trial {trial}");
                let xc = p.x().to_vec();
                // both stop at a relative gap of 1e-8: x agrees to about
                // its square root, the objective to the gap
                let scale = 1.0 + xc.iter().map(|v| v * v).sum::<f64>().sqrt();
                for (a, b) in xd.iter().zip(&xc) {
                    assert!(
                        (a - b).abs() < 1e-4 * scale,
                        "{max_margin} {bounds} trial {trial}: {a} against {b}"
                    );
                }
                // Clarabel answers from the current data alone: a solver
                // built for this program gives the same x
                let mut fresh = ConeProgram::new(shape, max_margin);
                fresh.a_nz.copy_from_slice(&p.a_nz);
                fresh.b.copy_from_slice(&p.b);
                fresh.q.copy_from_slice(&p.q);
                fresh.p_nz.copy_from_slice(&p.p_nz);
                assert_eq!(fresh.solve_clarabel(), SolveStatus::Optimal);
                for (a, b) in fresh.x().iter().zip(&xc) {
                    assert!(
                        (a - b).abs() <= 1e-12 * scale,
                        "trial {trial}: {a} against {b}"
                    );
                }
                let (od, oc) = (objective(&p, &xd), objective(&p, &xc));
                assert!(
                    (od - oc).abs() < 1e-7 * (1.0 + oc.abs()),
                    "{max_margin} {bounds} trial {trial}: objective {od} against {oc}"
                );
                compared += 1;
            }
            assert!(compared >= 100, "{compared} programs compared");
        }
    }
}
