//! The safety filter around a reference control `û`.

use super::recalibration::{RecalibrationSettings, Recalibrator};
use super::socp::{ConeProgram, SocpShape, SolveStatus};
use crate::barrier::{
    add_observation_noise, cbc_moments, clc_moments, factor_probability, mc_cbc_moments,
    quantile_factor, ConditionMoments, DynBarrier, DynLyapunov, McSettings, MomentWorkspace,
};
use crate::error::{
    check_finite, check_nonnegative, check_positive, ControlError, Error, InputError,
};
use crate::gp::{Kernel, Mvgp};
use nalgebra::DMatrix;
use std::sync::Arc;

/// What to apply when the SOCP is infeasible (paper, Remark 2). Its
/// serialised form is its [`name`](Fallback::name).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(rename_all = "snake_case"))]
pub enum Fallback {
    /// Maximise the worst stochastic CBC `E[C] − ζ − c(p)·std[C]` at the
    /// requested `p` within the bounds (itself an SOCP). With a large
    /// `c(p)` it favours controls of small variance, which keeps inputs the
    /// conditions do not constrain small, but may brake too little where
    /// the input gain is uncertain (docs/calibration.md, "Which fallback").
    #[default]
    MaxMargin,
    /// Apply `u = 0` (clamped into the bounds).
    Brake,
    /// Hold the previous control, clamped into the bounds (before any
    /// control was applied, brake).
    Hold,
    /// Solve the same SOCP at the largest feasible probability `p*`
    /// (graceful degradation; the maximal-margin control if no `p*` exists).
    /// It maximises the conditions' probability, and may take inputs they
    /// do not constrain to their bounds. Without bounds `p*` may be reached
    /// only as the control grows without limit (a condition whose mean
    /// grows with `u` faster than `c·std`): the control is then as large as
    /// `p*`'s tolerance (`p_star_tol`) requires, and bounds keep it finite.
    Relax,
}

impl Fallback {
    /// Name used in files and reports.
    pub fn name(self) -> &'static str {
        match self {
            Fallback::MaxMargin => "max_margin",
            Fallback::Brake => "brake",
            Fallback::Hold => "hold",
            Fallback::Relax => "relax",
        }
    }
    /// Parses [`name`](Self::name).
    pub fn parse(s: &str) -> Result<Self, InputError> {
        match s {
            "max_margin" => Ok(Fallback::MaxMargin),
            "brake" => Ok(Fallback::Brake),
            "hold" => Ok(Fallback::Hold),
            "relax" => Ok(Fallback::Relax),
            _ => Err(InputError::Invalid {
                field: "fallback".into(),
                value: s.into(),
                reason: "expected max_margin, brake, hold or relax".into(),
            }),
        }
    }
}

/// [`SafetySettings::predictive`] unless set: on.
fn predictive_default() -> bool {
    true
}

/// Settings of the safety SOCP, validated by [`SafetySettings::validate`].
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct SafetySettings {
    /// Required probability `p̃` of each stochastic condition.
    pub probability: f64,
    /// Margin `ζ ≥ 0` on every barrier condition.
    pub zeta: f64,
    /// Weight `λ > 0` of the CLF slack.
    pub lambda: f64,
    /// Objective weight `R` (`m × m`, invertible); identity by default.
    /// Its weights may be up to 10³ apart (the square root of the
    /// condition number of `RᵀR`); a filter warns beyond 100, where the
    /// solver's 10⁻⁸ relative accuracy resolves the minimiser along the
    /// lightly weighted controls only roughly. `(cR, c²λ)` give the control
    /// of `(R, λ)` for any `c`: the objective is normalised by the largest
    /// diagonal entry of `RᵀR`.
    pub r: DMatrix<f64>,
    /// Lower control bounds.
    pub u_min: Option<Vec<f64>>,
    /// Upper control bounds.
    pub u_max: Option<Vec<f64>>,
    /// Fallback on infeasibility.
    pub fallback: Fallback,
    /// Absolute tolerance of `p*`: its iteration stops when a step gains less.
    pub p_star_tol: f64,
    /// Promise each barrier condition (relative degree 1 and 2) as realised
    /// over the step, observation noise included ([`add_observation_noise`]):
    /// the model's noise `σ² A` widens the condition's variance
    /// (`σ² ∇hᵀA∇h` at relative degree 1), so that process noise that
    /// moves the state during the hold is covered too. On by default: under
    /// process noise a condition promised on `F` alone holds at the sample
    /// and fails over the step about half the time at an active constraint
    /// (docs/calibration.md). `false` is the paper's condition (Props. 2
    /// and 4): the posterior of `F` alone. Barriers of relative degree > 2
    /// (Monte Carlo moments) keep the posterior's.
    #[cfg_attr(feature = "serde", serde(default = "predictive_default"))]
    pub predictive: bool,
}

impl SafetySettings {
    /// Defaults for control dimension `m`: `p = 0.99`, `ζ = 0`, `λ = 1`,
    /// `R = I`, no bounds, max-margin fallback, predictive conditions.
    pub fn new(m: usize) -> Self {
        Self {
            probability: 0.99,
            zeta: 0.0,
            lambda: 1.0,
            r: DMatrix::identity(m, m),
            u_min: None,
            u_max: None,
            fallback: Fallback::MaxMargin,
            p_star_tol: 1e-5,
            predictive: predictive_default(),
        }
    }

    /// The paper's settings: [`new`](Self::new) with the conditions on the
    /// latent `F` alone (`predictive = false`).
    pub fn paper(m: usize) -> Self {
        Self {
            predictive: false,
            ..Self::new(m)
        }
    }

    /// Checks ranges and shapes for control dimension `m`.
    pub fn validate(&self, m: usize) -> Result<(), InputError> {
        quantile_factor(self.probability, 1)?;
        check_nonnegative("zeta", self.zeta)?;
        check_positive("lambda", self.lambda)?;
        if self.r.shape() != (m, m) {
            return Err(InputError::shape(
                "R",
                format!("{m}×{m}"),
                format!("{}×{}", self.r.nrows(), self.r.ncols()),
            ));
        }
        check_finite("R", self.r.as_slice())?;
        // RᵀR positive definite with every pivot above roundoff: a
        // singular R passes a plain Cholesky on a rounding error
        match weight_spread(&self.r) {
            None => {
                return Err(InputError::invalid_shown(
                    "R",
                    "singular",
                    "R must be invertible (RᵀR positive definite)",
                ))
            }
            Some(spread) if spread > MAX_WEIGHT_SPREAD => {
                return Err(InputError::invalid_shown(
                    "R",
                    format!("weights {spread:.1e} apart"),
                    &format!(
                        "R is singular to rounding, or its weights are more than \
                         {MAX_WEIGHT_SPREAD:.0e} apart (the square root of RᵀR's largest \
                         diagonal entry over its smallest squared Cholesky pivot), where the \
                         solver no longer resolves the minimiser along the lightly weighted \
                         controls (a control 38% further from u_ref than the closest safe one \
                         at 3e3 apart); express the controls in units whose weights are closer"
                    ),
                ))
            }
            Some(_) => {}
        }
        // the objective is divided by w = max diag RᵀR: λ/w must stay finite
        let w = (0..m).fold(0.0_f64, |a, i| a.max(self.r.column(i).norm_squared()));
        if !(w.is_normal() && (self.lambda / w).is_finite()) {
            return Err(InputError::invalid(
                "R",
                self.r.amax(),
                "its scale against lambda is beyond the range of f64 (the objective is \
                 divided by the largest diagonal entry of RᵀR, which must be a normal number, \
                 with lambda / it finite): scale R and lambda together",
            ));
        }
        if self.u_min.is_some() != self.u_max.is_some() {
            let given = if self.u_min.is_some() {
                "u_min"
            } else {
                "u_max"
            };
            return Err(InputError::invalid_shown(
                "u_min/u_max",
                format!("only {given}"),
                "give both bounds or neither",
            ));
        }
        if let (Some(lo), Some(hi)) = (&self.u_min, &self.u_max) {
            if lo.len() != m {
                return Err(InputError::shape("u_min", m, lo.len()));
            }
            if hi.len() != m {
                return Err(InputError::shape("u_max", m, hi.len()));
            }
            for (field, bound) in [("u_min", lo), ("u_max", hi)] {
                if let Some(j) = bound.iter().position(|b| !b.is_finite()) {
                    return Err(InputError::invalid(
                        &format!("{field}[{j}]"),
                        bound[j],
                        "must be finite: bounds are given for every control, and a control \
                         free on one side takes a finite bound there, such as its actuator's \
                         limit (an inactive bound leaves the control as it is)",
                    ));
                }
            }
            for j in 0..m {
                if lo[j] > hi[j] {
                    return Err(InputError::invalid(
                        &format!("u_min[{j}]"),
                        lo[j],
                        &format!("must be ≤ u_max[{j}] = {}", hi[j]),
                    ));
                }
            }
        }
        if !(self.p_star_tol > 0.0 && self.p_star_tol < 0.1) {
            return Err(InputError::invalid(
                "p_star_tol",
                self.p_star_tol,
                "must be in (0, 0.1)",
            ));
        }
        Ok(())
    }
}

/// Mean, standard deviation, safety factor and slack of one condition at the
/// returned control: `slack = mean − ζ − c·std` (≥ 0 when met) for barriers,
/// `δ − mean − c·std` for the CLF.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ConstraintReport {
    /// `E[C]`.
    pub mean: f64,
    /// `√Var[C]`.
    pub std: f64,
    /// Safety factor `c(p)`.
    pub c: f64,
    /// Constraint slack.
    pub slack: f64,
}

/// Details of an infeasible step (paper, Remark 2).
#[derive(Debug, Clone, PartialEq)]
pub struct InfeasibleInfo {
    /// Barriers whose stochastic condition is violated at the fallback control.
    pub violated: Vec<usize>,
    /// Largest probability for which the barrier constraints are jointly
    /// feasible within the bounds (in `[0.5, p)` when a
    /// relative-degree-1 barrier is present, else `(0, p]`); `None` if not
    /// feasible even at the lower end.
    pub p_star: Option<f64>,
    /// The fallback that produced `u`: the declared one, or the one it
    /// falls back to itself (`relax` where no control attains `p*` gives
    /// the max-margin control; `max_margin` whose program fails brakes).
    pub fallback: Fallback,
    /// Raw solver status of the control SOCP.
    pub solver: SolveStatus,
}

/// Outcome of one control step.
#[derive(Debug, Clone, PartialEq)]
pub enum ControlStatus {
    /// The SOCP was solved.
    Optimal,
    /// Solved to reduced accuracy.
    AlmostOptimal,
    /// No control meets every constraint; `u` is the declared fallback.
    Infeasible(InfeasibleInfo),
}

/// The control and a report of every constraint; reused across steps.
#[derive(Debug, Clone, PartialEq)]
pub struct ControlOutput {
    /// Applied control.
    pub u: Vec<f64>,
    /// Outcome.
    pub status: ControlStatus,
    /// CLF slack δ (0 without a CLF).
    pub delta: f64,
    /// One report per barrier.
    pub constraints: Vec<ConstraintReport>,
    /// The CLF report, if any.
    pub clf: Option<ConstraintReport>,
}

impl ControlOutput {
    /// Empty output for `m` controls and `nb` barriers.
    pub fn new(m: usize, nb: usize) -> Self {
        Self {
            u: vec![0.0; m],
            status: ControlStatus::Optimal,
            delta: 0.0,
            constraints: vec![ConstraintReport::default(); nb],
            clf: None,
        }
    }
    /// True if the step was infeasible.
    pub fn is_infeasible(&self) -> bool {
        matches!(self.status, ControlStatus::Infeasible(_))
    }
}

/// Prefixes `barriers[i]: ` to a failed evaluation of barrier `i`, which
/// barriers that share a formula (discs with other parameters) would not
/// tell apart.
fn naming_barrier(i: usize) -> impl Fn(Error) -> Error {
    move |e| match e {
        Error::Input(InputError::Evaluation(m)) => {
            InputError::Evaluation(format!("barriers[{i}]: {m}")).into()
        }
        e => e,
    }
}

/// The report of one barrier condition at `u`.
fn report(mom: &ConditionMoments, c: f64, u: &[f64], zeta: f64) -> ConstraintReport {
    let mean = mom.mean(u);
    let std = mom.variance(u).sqrt();
    ConstraintReport {
        mean,
        std,
        c,
        slack: mean - zeta - c * std,
    }
}

/// Checks that a solved program's control meets every barrier condition,
/// recomputed from the covariance, up to a tolerance well above the
/// solver's (relative `1e-6` against its `1e-8`; `1e-2` at reduced
/// accuracy): a solver working at the rounding level of a huge covariance
/// can report a solution that misses by far more.
fn check_solution(
    cbcs: &[ConditionMoments],
    reports: &[ConstraintReport],
    status: SolveStatus,
) -> Result<(), ControlError> {
    let rel = if status == SolveStatus::Optimal {
        1e-6
    } else {
        1e-2
    };
    for (k, (mom, r)) in cbcs.iter().zip(reports).enumerate() {
        let tol = rel * (1.0 + r.mean.abs() + r.c.abs() * r.std);
        // a non-finite slack (a control too far out for its covariance) is
        // no solution either
        if !r.slack.is_finite() || r.slack < -tol {
            return Err(ControlError::Unresolved {
                barrier: k,
                slack: r.slack,
                mean: r.mean,
                std: r.std,
                scale: mom.cov.amax(),
            });
        }
    }
    Ok(())
}

/// The max-margin program's outcome at one probability.
enum Margin {
    /// Its maximum (the maximiser is written out).
    Max(f64),
    /// No maximum: the margin grows without limit (no input bounds), so
    /// the conditions are feasible at that probability.
    Unbounded,
    /// The solver failed: nothing is known.
    Failed,
}

/// The one check of the probability against the conditions: with a
/// relative-degree-1 condition (a barrier of relative degree 1 or a CLF)
/// `p ≥ 0.5` is required, since `c(p) < 0` would make the cone constraint
/// non-convex (Prop. 2).
fn check_probability(p: f64, relative_degree_one: bool) -> Result<(), InputError> {
    if p < 0.5 && relative_degree_one {
        return Err(InputError::invalid(
            "controller.probability",
            p,
            "must be ≥ 0.5 with relative-degree-1 conditions (c(p) < 0 would make the constraint non-convex)",
        ));
    }
    Ok(())
}

/// The SOCP safety filter given condition moments (no GP inside): useful on
/// its own, and the engine of [`SafetyController`].
pub struct SafetyFilter {
    shape: SocpShape,
    settings: SafetySettings,
    program: ConeProgram,
    margin: Option<ConeProgram>,
    last_u: Vec<f64>,
    /// Buffers of the infeasible path (the max-margin control, the `p*`
    /// iterate, the violated barriers), so that it allocates nothing.
    u_mm: Vec<f64>,
    u_p: Vec<f64>,
    violated: Vec<usize>,
    /// The margins added to the barriers' `ζ` in a second solve (see
    /// [`solve`](Self::solve)).
    backoff: Vec<f64>,
}

impl std::fmt::Debug for SafetyFilter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SafetyFilter")
            .field("shape", &self.shape)
            .field("settings", &self.settings)
            .finish()
    }
}

/// [`weight_spread`] beyond which `R` is refused: singular to rounding, or
/// weights beyond what the solver resolves.
const MAX_WEIGHT_SPREAD: f64 = 1e3;

/// [`weight_spread`] beyond which a filter warns: weights 100 apart, where
/// the minimiser along the light one is off by 10⁻⁴ of the distance (0.55%
/// at 10³ apart, 38% at 3×10³, on random programs).
const WARN_WEIGHT_SPREAD: f64 = 100.0;

/// How far apart the weights of `R` are: the square root of the largest
/// diagonal entry of `RᵀR` over its smallest squared Cholesky pivot (`s`
/// for `R = diag(1, s)`), an estimate of the condition number of `R`.
/// `None` if `RᵀR` has no Cholesky factor.
fn weight_spread(r: &DMatrix<f64>) -> Option<f64> {
    let rtr = r.transpose() * r;
    let largest = rtr.diagonal().max();
    let chol = rtr.cholesky()?;
    let smallest = chol
        .l()
        .diagonal()
        .iter()
        .fold(f64::INFINITY, |a, d| a.min(d * d));
    (largest > 0.0 && smallest > 0.0).then(|| (largest / smallest).sqrt())
}

impl SafetyFilter {
    /// Builds the filter for `barriers` barrier constraints and an optional CLF.
    pub fn new(
        m: usize,
        barriers: usize,
        clf: bool,
        settings: SafetySettings,
    ) -> Result<Self, InputError> {
        if m == 0 {
            return Err(InputError::invalid("control_dim", 0.0, "must be ≥ 1"));
        }
        settings.validate(m)?;
        if settings.fallback == Fallback::Relax && settings.u_min.is_none() {
            static UNBOUNDED_RELAX: crate::warnings::WarnOnce =
                crate::warnings::WarnOnce::new("relax_without_bounds");
            UNBOUNDED_RELAX.issue(|| {
                "fallback relax without input bounds (u_min, u_max): where the conditions \
                 are met only as the control grows, the largest feasible probability p* \
                 is approached only by ever larger controls: relax applies a very large \
                 one, or the max-margin control where none attains p* (reported as \
                 fallback max_margin; docs/calibration.md, \"Which fallback\"); give \
                 u_min and u_max, or use max_margin (shown once per run or filter)"
                    .to_string()
            });
        }
        if let Some(spread) = weight_spread(&settings.r).filter(|s| *s > WARN_WEIGHT_SPREAD) {
            static SPREAD_WEIGHTS: crate::warnings::WarnOnce =
                crate::warnings::WarnOnce::new("spread_weights");
            SPREAD_WEIGHTS.issue(|| {
                format!(
                    "R: its weights are {spread:.1e} apart (the square root of RᵀR's largest \
                     diagonal entry over its smallest squared Cholesky pivot): the solver's \
                     1e-8 relative accuracy resolves the minimiser along the lightly weighted \
                     controls only roughly, and the control can lie further from u_ref than \
                     the closest safe one (it still meets every condition; on random programs \
                     0.55% of the distance at weights 1 and 1e3, 38% at 1 and 3e3); scale the \
                     controls so that their weights are within 100 of each other (shown once \
                     per run or filter)"
                )
            });
        }
        let shape = SocpShape {
            m,
            barriers,
            clf,
            bounds: settings.u_min.is_some(),
        };
        let mut program = ConeProgram::new(shape, false);
        if let (Some(lo), Some(hi)) = (&settings.u_min, &settings.u_max) {
            program.set_bounds(lo, hi);
        }
        Ok(Self {
            shape,
            settings,
            program,
            margin: None,
            last_u: vec![0.0; m],
            u_mm: vec![0.0; m],
            u_p: vec![0.0; m],
            violated: Vec::with_capacity(barriers),
            backoff: vec![0.0; barriers],
        })
    }

    /// The settings.
    pub fn settings(&self) -> &SafetySettings {
        &self.settings
    }

    /// Changes the required probability (validated).
    pub fn set_probability(&mut self, p: f64) -> Result<(), InputError> {
        quantile_factor(p, 1)?;
        self.settings.probability = p;
        Ok(())
    }

    /// Changes the margin `ζ` of the barrier conditions (finite, `≥ 0`).
    pub fn set_zeta(&mut self, zeta: f64) -> Result<(), InputError> {
        check_nonnegative("zeta", zeta)?;
        self.settings.zeta = zeta;
        Ok(())
    }

    /// Solves the SOCP for reference `u_ref` and writes the outcome.
    ///
    /// `cbcs` has one entry per barrier (each with its relative degree),
    /// `clc` is required iff the filter was built with a CLF. On an error
    /// `out` holds no outcome: after a solution rejected by its check
    /// ([`ControlError::Unresolved`]) its `u` and `delta` are NaN.
    pub fn solve(
        &mut self,
        cbcs: &[ConditionMoments],
        clc: Option<&ConditionMoments>,
        u_ref: &[f64],
        out: &mut ControlOutput,
    ) -> Result<(), Error> {
        let m = self.shape.m;
        if cbcs.len() != self.shape.barriers {
            return Err(
                InputError::shape("barrier moments", self.shape.barriers, cbcs.len()).into(),
            );
        }
        if clc.is_some() != self.shape.clf {
            let given = if clc.is_some() { "given" } else { "missing" };
            return Err(InputError::invalid_shown(
                "clf",
                format!("moments {given}"),
                "CLF moments must be given iff the filter has a CLF",
            )
            .into());
        }
        if u_ref.len() != m {
            return Err(InputError::shape("u_ref", m, u_ref.len()).into());
        }
        check_finite("u_ref", u_ref)?;
        // the objective ‖R(u − u_ref)‖² multiplies u_ref by R twice and by
        // the iterates, as large as u_ref unless bounds keep them smaller:
        // beyond ~1e308 that overflows, and an overflowing program reads
        // as infeasible
        let largest = |v: &mut dyn Iterator<Item = &f64>| v.fold(0.0f64, |a, x| a.max(x.abs()));
        let (r_max, u_max) = (
            largest(&mut self.settings.r.iter()),
            largest(&mut u_ref.iter()),
        );
        let iterates = match (&self.settings.u_min, &self.settings.u_max) {
            (Some(lo), Some(hi)) => u_max.min(largest(&mut lo.iter().chain(hi))),
            _ => u_max,
        };
        let (reach, control) = (r_max * u_max, r_max * iterates.max(1.0));
        if reach * control > 1e300 {
            return Err(InputError::invalid(
                "u_ref",
                largest(&mut u_ref.iter()),
                "too large for the objective ‖R(u − u_ref)‖², which would overflow: \
                 |R|·|u_ref| must stay below 1e150 without input bounds, and \
                 |R|²·|u_ref|·max(min(|u_ref|, |u_min|, |u_max|), 1) below 1e300 with them",
            )
            .into());
        }
        for (i, mom) in cbcs.iter().chain(clc).enumerate() {
            if mom.e.len() != m + 1 {
                return Err(
                    InputError::shape(&format!("moments[{i}].e"), m + 1, mom.e.len()).into(),
                );
            }
            // field names are formatted only on failure (no allocation per step)
            if mom.e.iter().any(|v| !v.is_finite()) {
                check_finite(&format!("moments[{i}].e"), &mom.e)?;
            }
            if mom.cov.iter().any(|v| !v.is_finite()) {
                check_finite(&format!("moments[{i}].cov"), mom.cov.as_slice())?;
            }
        }
        if out.u.len() != m || out.constraints.len() != cbcs.len() {
            *out = ControlOutput::new(m, cbcs.len());
        }
        let p = self.settings.probability;
        let zeta = self.settings.zeta;
        check_probability(
            p,
            clc.is_some() || cbcs.iter().any(|c| c.relative_degree <= 1),
        )?;
        let c1 = quantile_factor(p, 1)?;
        if let Some(mom) = clc {
            self.program.set_clf(mom, c1);
        }
        self.program
            .set_objective(&self.settings.r, u_ref, self.settings.lambda);
        // one solve, and one more where the control misses a condition by
        // the solver's own accuracy (a tolerance relative to the whole
        // program's data, such as a CLF term far larger than the barrier
        // conditions): that barrier's margin is raised by twice the miss.
        // The second can be infeasible (the condition held only to that
        // accuracy), which is then the step's outcome
        self.backoff.fill(0.0);
        for attempt in 0..2 {
            for (k, mom) in cbcs.iter().enumerate() {
                let c = quantile_factor(p, mom.relative_degree)?;
                self.program.set_barrier(k, mom, c, zeta + self.backoff[k]);
            }
            let status = self.program.solve();
            if status.is_solved() {
                let x = self.program.x();
                out.u.copy_from_slice(&x[..m]);
                self.clamp_to_bounds(&mut out.u);
                out.delta = if self.shape.clf { x[m] } else { 0.0 };
                let solved = if status == SolveStatus::Optimal {
                    ControlStatus::Optimal
                } else {
                    ControlStatus::AlmostOptimal
                };
                // an earlier infeasible step's list is kept for the next one
                if let ControlStatus::Infeasible(info) = std::mem::replace(&mut out.status, solved)
                {
                    self.violated = info.violated;
                }
            } else {
                out.delta = 0.0;
                let info = self.infeasible(cbcs, clc, status, out)?;
                out.status = ControlStatus::Infeasible(info);
            }
            for (k, mom) in cbcs.iter().enumerate() {
                let c = quantile_factor(p, mom.relative_degree)?;
                out.constraints[k] = report(mom, c, &out.u, zeta);
            }
            if out.is_infeasible() {
                break;
            }
            match check_solution(cbcs, &out.constraints, status) {
                Ok(()) => break,
                // not where the covariance itself is beyond double
                // precision at this control: no margin makes that exact
                Err(_)
                    if attempt == 0
                        && cbcs.iter().all(|mom| mom.variance_resolved(&out.u).is_ok()) =>
                {
                    for (b, r) in self.backoff.iter_mut().zip(&out.constraints) {
                        if r.slack < 0.0 && r.slack.is_finite() {
                            *b = -2.0 * r.slack;
                        }
                    }
                }
                Err(e) => {
                    // no control to apply: a caller that ignores the error
                    // gets NaN, not the rejected control
                    out.u.fill(f64::NAN);
                    out.delta = f64::NAN;
                    return Err(e.into());
                }
            }
        }
        let (u, delta) = (&out.u, out.delta);
        out.clf = clc.map(|mom| {
            let mean = mom.mean(u);
            let std = mom.variance(u).sqrt();
            ConstraintReport {
                mean,
                std,
                c: c1,
                slack: delta - mean - c1 * std,
            }
        });
        self.last_u.copy_from_slice(&out.u);
        Ok(())
    }

    /// Worst barrier margin `max_u min_i SCBC_i(u)` at probability `p`,
    /// and the maximiser written into `u`. `None` when there is none
    /// (unbounded without input bounds, or the solver failed).
    fn max_margin(
        &mut self,
        cbcs: &[ConditionMoments],
        p: f64,
        u: &mut [f64],
    ) -> Result<Option<f64>, Error> {
        Ok(match self.margin_at(cbcs, p, u)? {
            Margin::Max(t) => Some(t),
            Margin::Unbounded | Margin::Failed => None,
        })
    }

    /// [`max_margin`](Self::max_margin), telling an unbounded margin
    /// (feasible at `p`) from a failed solve (nothing known).
    fn margin_at(
        &mut self,
        cbcs: &[ConditionMoments],
        p: f64,
        u: &mut [f64],
    ) -> Result<Margin, Error> {
        let shape = self.shape;
        let prog = self.margin.get_or_insert_with(|| {
            let mut pr = ConeProgram::new(shape, true);
            if let (Some(lo), Some(hi)) = (&self.settings.u_min, &self.settings.u_max) {
                pr.set_bounds(lo, hi);
            }
            pr
        });
        for (k, mom) in cbcs.iter().enumerate() {
            let c = quantile_factor(p, mom.relative_degree)?;
            prog.set_barrier(k, mom, c, self.settings.zeta);
        }
        let st = prog.solve();
        Ok(if st.is_solved() {
            let x = prog.x();
            u.copy_from_slice(&x[..shape.m]);
            Margin::Max(x[shape.m])
        } else if st == SolveStatus::Unbounded {
            Margin::Unbounded
        } else {
            Margin::Failed
        })
    }

    /// The largest probability at which `u` meets every barrier
    /// constraint: for each barrier the factor `c_i = (E[C_i] − ζ)/√Var[C_i]`
    /// that `u` affords, turned into its probability
    /// ([`factor_probability`]), and the smallest of these. `1` when no
    /// constraint has variance.
    fn afforded_probability(&self, cbcs: &[ConditionMoments], u: &[f64]) -> f64 {
        cbcs.iter()
            .map(|mom| {
                let gap = mom.mean(u) - self.settings.zeta;
                let std = mom.variance(u).sqrt();
                let c = if std > 0.0 {
                    gap / std
                } else if gap >= 0.0 {
                    f64::INFINITY
                } else {
                    f64::NEG_INFINITY
                };
                factor_probability(c, mom.relative_degree)
            })
            .fold(1.0, f64::min)
    }

    /// `p*` (Remark 2): the largest probability at which the barrier
    /// constraints are jointly feasible within the bounds, below the
    /// requested `p`, at which they are not; `u_p`, if computed, is the
    /// max-margin control at `p`, where the iteration starts (else at the
    /// lowest admissible probability).
    ///
    /// A Dinkelbach iteration for the generalised fractional program
    /// `max_u min_i prob_i(u)`: from a control `u_k`, `p_{k+1}` is the
    /// probability `u_k` affords ([`Self::afforded_probability`]), feasible
    /// by construction; `u_{k+1}` is the max-margin control at `p_{k+1}`,
    /// whose margin is ≥ 0, so it affords at least `p_{k+1}`. The sequence
    /// increases to `p*` (for one barrier it is Newton's method on the
    /// convex, decreasing margin as a function of `c`, which converges
    /// superlinearly); it stops when a step gains less than `p_star_tol` or
    /// the margin reaches 0. Each step is one SOCP, against the ~17 of a
    /// bisection to the same tolerance. `None` when not even the lowest
    /// admissible probability (0.5 with a relative-degree-1 barrier, where
    /// `c(p) ≥ 0` keeps the cone convex) is feasible.
    fn p_star(
        &mut self,
        cbcs: &[ConditionMoments],
        p: f64,
        u_p: Option<&[f64]>,
    ) -> Result<Option<f64>, Error> {
        let tol = self.settings.p_star_tol;
        let lo = if cbcs.iter().any(|c| c.relative_degree <= 1) {
            0.5
        } else {
            1e-9
        };
        // each barrier alone, at c = 0: if the box holds no u with
        // E[C_i](u) ≥ ζ (a linear condition, maximised coordinate-wise),
        // no probability is feasible, without a solve
        if let (Some(lo_u), Some(hi_u)) = (&self.settings.u_min, &self.settings.u_max) {
            let zeta = self.settings.zeta;
            let hopeless = cbcs.iter().any(|mom| {
                let best: f64 = mom.e[0]
                    + (0..self.shape.m)
                        .map(|j| (mom.e[j + 1] * lo_u[j]).max(mom.e[j + 1] * hi_u[j]))
                        .sum::<f64>();
                best - zeta < -1e-9
            });
            if hopeless {
                return Ok(None);
            }
        }
        let mut u = std::mem::take(&mut self.u_p);
        u.resize(self.shape.m, 0.0);
        let q = self.p_star_from(cbcs, p, lo, tol, u_p, &mut u);
        self.u_p = u;
        q
    }

    /// [`p_star`](Self::p_star)'s iteration from `u_p` (or the max-margin
    /// control at `lo`), with `u` as its iterate.
    fn p_star_from(
        &mut self,
        cbcs: &[ConditionMoments],
        p: f64,
        lo: f64,
        tol: f64,
        u_p: Option<&[f64]>,
        u: &mut [f64],
    ) -> Result<Option<f64>, Error> {
        let mut q = match u_p {
            Some(up) => {
                u.copy_from_slice(up);
                self.afforded_probability(cbcs, u).min(p)
            }
            None => f64::NEG_INFINITY,
        };
        if q < lo {
            // no start, or u_p affords too little: start from the lowest
            // admissible p
            q = match self.margin_at(cbcs, lo, u)? {
                Margin::Max(t) if t < -1e-9 => return Ok(None),
                Margin::Max(_) => self.afforded_probability(cbcs, u).clamp(lo, p),
                Margin::Unbounded => match self.past_unbounded(cbcs, lo, p, tol, u)? {
                    (level, true) => self.afforded_probability(cbcs, u).clamp(level, p),
                    (level, false) => return Ok(Some(level)),
                },
                // nothing known beyond the lowest admissible level
                Margin::Failed => return Ok(Some(lo)),
            };
        }
        for _ in 0..50 {
            let level = match self.margin_at(cbcs, q, u)? {
                Margin::Max(t) if t > 1e-12 => q,
                Margin::Max(_) | Margin::Failed => break,
                Margin::Unbounded => match self.past_unbounded(cbcs, q, p, tol, u)? {
                    (level, true) => level,
                    (level, false) => {
                        q = level;
                        break;
                    }
                },
            };
            let next = self.afforded_probability(cbcs, u).min(p);
            if next <= level + tol {
                q = level.max(next);
                break;
            }
            q = next;
        }
        Ok(Some(q))
    }

    /// Where the worst margin stops being unbounded (without input bounds
    /// it grows without limit along some direction of `u` while the
    /// factors are small): bisection on the probability between `lo`, whose
    /// margin is unbounded (so feasible), and the infeasible `hi`. Returns
    /// the first level found whose margin has a maximiser and is ≥ 0, with
    /// that maximiser in `u` (`true`), or, when the bracket narrows to
    /// `tol` (or to neighbouring numbers, or a solve fails) first, its
    /// feasible end (`false`; `u` holds nothing).
    fn past_unbounded(
        &mut self,
        cbcs: &[ConditionMoments],
        mut lo: f64,
        mut hi: f64,
        tol: f64,
        u: &mut [f64],
    ) -> Result<(f64, bool), Error> {
        // 64 halvings narrow any bracket within [0, 1] to below 1e-19
        for _ in 0..64 {
            let mid = 0.5 * (lo + hi);
            if hi - lo <= tol || mid <= lo || mid >= hi {
                break;
            }
            match self.margin_at(cbcs, mid, u)? {
                Margin::Unbounded => lo = mid,
                Margin::Max(t) if t >= -1e-12 => return Ok((mid, true)),
                Margin::Max(_) => hi = mid,
                Margin::Failed => break,
            }
        }
        Ok((lo, false))
    }

    fn infeasible(
        &mut self,
        cbcs: &[ConditionMoments],
        clc: Option<&ConditionMoments>,
        status: SolveStatus,
        out: &mut ControlOutput,
    ) -> Result<InfeasibleInfo, Error> {
        // the max-margin control at p: the MaxMargin fallback, and Relax's
        // when p* or the relaxed program fails (not needed otherwise)
        let mut u_mm = std::mem::take(&mut self.u_mm);
        u_mm.resize(self.shape.m, 0.0);
        let info = self.fall_back(cbcs, clc, status, out, &mut u_mm);
        self.u_mm = u_mm;
        info
    }

    /// [`infeasible`](Self::infeasible) with `u_mm` for the max-margin
    /// control.
    fn fall_back(
        &mut self,
        cbcs: &[ConditionMoments],
        clc: Option<&ConditionMoments>,
        status: SolveStatus,
        out: &mut ControlOutput,
        u_mm: &mut [f64],
    ) -> Result<InfeasibleInfo, Error> {
        let m = self.shape.m;
        let p = self.settings.probability;
        let fallback = self.settings.fallback;
        let margin = match fallback {
            Fallback::MaxMargin | Fallback::Relax => self.max_margin(cbcs, p, u_mm)?,
            Fallback::Brake | Fallback::Hold => None,
        };
        // p*: the largest p with a non-negative worst margin
        let p_star = if status == SolveStatus::Infeasible {
            self.p_star(cbcs, p, margin.map(|_| &u_mm[..]))?
        } else {
            None
        };
        let mut relaxed = false;
        if let (Fallback::Relax, Some(ps)) = (fallback, p_star) {
            // the constraints at p* are feasible: re-solve the control SOCP there
            for (k, mom) in cbcs.iter().enumerate() {
                let c = quantile_factor(ps, mom.relative_degree)?;
                self.program.set_barrier(k, mom, c, self.settings.zeta);
            }
            if let Some(mom) = clc {
                self.program.set_clf(mom, quantile_factor(ps.max(0.5), 1)?);
            }
            if self.program.solve().is_solved() {
                let x = self.program.x();
                out.u.copy_from_slice(&x[..m]);
                out.delta = if self.shape.clf { x[m] } else { 0.0 };
                relaxed = true;
            } else if self.afforded_probability(cbcs, &self.u_p) >= ps - self.settings.p_star_tol {
                // at p* the conditions just hold, and their feasible set
                // can be one point the solver does not resolve: the p*
                // iteration's own control affords p*
                out.u.copy_from_slice(&self.u_p);
                out.delta = 0.0;
                relaxed = true;
            }
        }
        // the fallback that acts: relax where no control attains p* (it is
        // then approached only as the control grows) is the max-margin
        // control, and max_margin without a margin (its program unsolved)
        // brakes
        let applied = match fallback {
            _ if relaxed => Fallback::Relax,
            Fallback::MaxMargin | Fallback::Relax if margin.is_some() => Fallback::MaxMargin,
            Fallback::Hold => Fallback::Hold,
            _ => Fallback::Brake,
        };
        match applied {
            Fallback::Relax => {}
            Fallback::MaxMargin => out.u.copy_from_slice(u_mm),
            // brake: zero, within the bounds; hold: the last control, within
            // the bounds (zero before the first step, which holds nothing)
            Fallback::Brake | Fallback::Hold => {
                for j in 0..m {
                    let (lo, hi) = match (&self.settings.u_min, &self.settings.u_max) {
                        (Some(l), Some(h)) => (l[j], h[j]),
                        _ => (f64::NEG_INFINITY, f64::INFINITY),
                    };
                    let held = if applied == Fallback::Hold {
                        self.last_u[j]
                    } else {
                        0.0
                    };
                    out.u[j] = held.clamp(lo, hi);
                }
            }
        }
        self.clamp_to_bounds(&mut out.u);
        // the list of the last infeasible step, refilled
        let mut violated = match &mut out.status {
            ControlStatus::Infeasible(info) => std::mem::take(&mut info.violated),
            _ => std::mem::take(&mut self.violated),
        };
        violated.clear();
        violated.extend(
            cbcs.iter()
                .enumerate()
                .filter(|(_, mom)| {
                    let c = quantile_factor(p, mom.relative_degree).unwrap_or(0.0);
                    mom.mean(&out.u) - self.settings.zeta - c * mom.variance(&out.u).sqrt() < 0.0
                })
                .map(|(i, _)| i),
        );
        Ok(InfeasibleInfo {
            violated,
            p_star,
            fallback: applied,
            solver: status,
        })
    }

    /// Clamps `u` into the bounds, if any. The solvers meet a bound to their
    /// tolerance (a few 1e-9 beyond it); the control applied lies within the
    /// bounds as set.
    fn clamp_to_bounds(&self, u: &mut [f64]) {
        if let (Some(lo), Some(hi)) = (&self.settings.u_min, &self.settings.u_max) {
            for ((u, lo), hi) in u.iter_mut().zip(lo).zip(hi) {
                *u = u.clamp(*lo, *hi);
            }
        }
    }

    /// The last control SOCP with its solution, for verifying the KKT
    /// conditions (see [`KktData`]).
    pub fn kkt_data(&self) -> KktData {
        let (a, b, p, q) = self.program.dense();
        let (s, z) = self.program.duals();
        KktData {
            a,
            b,
            p,
            q,
            cones: self.program.cones().to_vec(),
            x: self.program.x().to_vec(),
            s,
            z,
        }
    }
}

/// A solved cone program in Clarabel's standard form,
/// `min ½ xᵀPx + qᵀx` subject to `Ax + s = b`, `s ∈ K`, with its primal
/// solution `x`, slack `s` and dual `z`. At an optimum the KKT conditions
/// read `s = b − Ax ∈ K`, `z ∈ K*`, `Px + q + Aᵀz = 0` and `sᵀz = 0`.
///
/// Returned by [`SafetyFilter::kkt_data`] for the last control SOCP: `x` is
/// `[u; δ]` (`δ` only with a CLF), the rows of `A` follow `cones`.
#[derive(Debug, Clone, PartialEq)]
pub struct KktData {
    /// Constraint matrix `A` (dense).
    pub a: DMatrix<f64>,
    /// Constraint offset `b`.
    pub b: Vec<f64>,
    /// Quadratic cost `P` (dense, symmetric): of the objective
    /// `‖R(u − û)‖² + λδ²` divided by the largest diagonal entry of `RᵀR`,
    /// as solved.
    pub p: DMatrix<f64>,
    /// Linear cost `q`, of the same objective.
    pub q: Vec<f64>,
    /// The cones `K`, in the row order of `A`.
    pub cones: Vec<clarabel::solver::SupportedConeT<f64>>,
    /// Primal solution `x`, as solved: a bounded control can lie beyond
    /// its bound by the solver's tolerance, where the applied `u` is
    /// clamped.
    pub x: Vec<f64>,
    /// Primal slack `s = b − Ax`.
    pub s: Vec<f64>,
    /// Dual solution `z`.
    pub z: Vec<f64>,
}

/// Joint posterior draws per step for the moments of a barrier of relative
/// degree > 2 in the closed loop.
const MC_SAMPLES: usize = 2_000;
/// A barrier of relative degree above 2: its moments are sampled.
static MONTE_CARLO_MOMENTS: crate::warnings::WarnOnce =
    crate::warnings::WarnOnce::new("monte_carlo_moments");

/// A complete safety controller: posterior at `x`, moments of every barrier
/// (and the CLF), and the SOCP.
pub struct SafetyController {
    barriers: Vec<Arc<dyn DynBarrier>>,
    clf: Option<Arc<dyn DynLyapunov>>,
    /// `n` zeros: the CLF reference `(x_d, ẋ_d)` when none is given.
    zero_reference: Vec<f64>,
    filter: SafetyFilter,
    ws: Option<MomentWorkspace>,
    cbcs: Vec<ConditionMoments>,
    /// The observation-noise variance each condition received this step
    /// ([`SafetySettings::predictive`]; zeros otherwise).
    noise: Vec<f64>,
    clc: ConditionMoments,
    max_degree: usize,
    mc: McSettings,
    steps: u64,
    recal: Option<Recalibration>,
    /// The moments in place are a whole step's ([`resolve`](Self::resolve)).
    solved: bool,
}

/// The recalibration state: the inflations, and the last step's state,
/// control and uninflated latent condition moments `(E, Var)` at that
/// control (without the observation noise of
/// [`SafetySettings::predictive`]).
#[derive(Debug, Clone)]
struct Recalibration {
    inflation: Recalibrator,
    x: Vec<f64>,
    u: Vec<f64>,
    predicted: Vec<Option<(f64, f64)>>,
    post: ConditionMoments,
}

impl std::fmt::Debug for SafetyController {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SafetyController")
            .field("barriers", &self.barriers.len())
            .field("clf", &self.clf.is_some())
            .field("filter", &self.filter)
            .finish()
    }
}

impl SafetyController {
    /// A controller for state dim `n`, control dim `m`.
    pub fn new(
        n: usize,
        m: usize,
        barriers: Vec<Arc<dyn DynBarrier>>,
        clf: Option<Arc<dyn DynLyapunov>>,
        settings: SafetySettings,
    ) -> Result<Self, InputError> {
        for (i, b) in barriers.iter().enumerate() {
            if b.state_dim() != n {
                return Err(InputError::shape(
                    &format!("barrier[{i}] state dimension"),
                    n,
                    b.state_dim(),
                ));
            }
            super::super::barrier::validate_gains(b.relative_degree(), b.gains())?;
            if b.relative_degree() > 2 {
                MONTE_CARLO_MOMENTS.issue(|| {
                    format!(
                        "barrier[{i}] '{}' has relative degree {}: exact moments exist for \
                         relative degree 1 and 2, so its condition's moments are estimated from \
                         {MC_SAMPLES} joint posterior draws at every step (seconds per step)",
                        b.name(),
                        b.relative_degree()
                    )
                });
            }
        }
        if let Some(c) = &clf {
            if c.state_dim() != n {
                return Err(InputError::shape("clf state dimension", n, c.state_dim()));
            }
        }
        check_probability(
            settings.probability,
            clf.is_some() || barriers.iter().any(|b| b.relative_degree() <= 1),
        )?;
        let max_degree = barriers
            .iter()
            .map(|b| b.relative_degree())
            .max()
            .unwrap_or(1)
            .min(2);
        let filter = SafetyFilter::new(m, barriers.len(), clf.is_some(), settings)?;
        let nb = barriers.len();
        Ok(Self {
            barriers,
            clf,
            zero_reference: vec![0.0; n],
            filter,
            ws: None,
            cbcs: vec![ConditionMoments::zeros(m); nb],
            noise: vec![0.0; nb],
            clc: ConditionMoments::zeros(m),
            max_degree,
            mc: McSettings {
                samples: MC_SAMPLES,
                ..McSettings::default()
            },
            steps: 0,
            recal: None,
            solved: false,
        })
    }

    /// The barriers, in the order of their conditions.
    pub fn barriers(&self) -> &[Arc<dyn DynBarrier>] {
        &self.barriers
    }

    /// The control Lyapunov function, if any.
    pub fn clf(&self) -> Option<&Arc<dyn DynLyapunov>> {
        self.clf.as_ref()
    }

    /// The settings of its SOCP.
    pub fn settings(&self) -> &SafetySettings {
        self.filter.settings()
    }

    /// Turns the online recalibration of the barrier conditions' variances
    /// on (`Some`) or off (see [`super::Recalibrator`]); on, every step's
    /// condition variances are inflated by `κ_i²` and
    /// [`SafetyController::recalibrate`] adapts `κ_i` after each model
    /// update. Turning it on again restarts from `κ = 1`.
    pub fn set_recalibration(
        &mut self,
        settings: Option<RecalibrationSettings>,
    ) -> Result<(), InputError> {
        self.recal = match settings {
            None => None,
            Some(s) => Some(Recalibration {
                inflation: Recalibrator::new(self.barriers.len(), s)?,
                x: Vec::new(),
                u: Vec::new(),
                predicted: vec![None; self.barriers.len()],
                post: ConditionMoments::zeros(self.filter.shape.m),
            }),
        };
        Ok(())
    }

    /// The recalibration's inflations, if it is on.
    pub fn recalibrator(&self) -> Option<&Recalibrator> {
        self.recal.as_ref().map(|r| &r.inflation)
    }

    /// Adapts the inflations to the model `model` that has learned the last
    /// step's observation: each barrier's condition at the last step's state
    /// and control, before and after, is one update of its `κ_i`
    /// ([`Recalibrator::update`]). Does nothing when the recalibration is
    /// off or no step was taken; barriers of relative degree > 2 (Monte
    /// Carlo moments) are not recalibrated.
    pub fn recalibrate<K: Kernel>(&mut self, model: &Mvgp<K>) -> Result<(), Error> {
        let (Some(rc), Some(ws)) = (self.recal.as_mut(), self.ws.as_mut()) else {
            return Ok(());
        };
        if rc.x.is_empty() {
            return Ok(());
        }
        ws.update(model, &rc.x, self.max_degree)?;
        let p = self.filter.settings.probability;
        for (i, b) in self.barriers.iter().enumerate() {
            let Some(before) = rc.predicted[i].take() else {
                continue;
            };
            cbc_moments(ws, b.as_ref(), &mut rc.post)?;
            let after = (rc.post.mean(&rc.u), rc.post.variance(&rc.u));
            let c = quantile_factor(p, b.relative_degree())?;
            rc.inflation.update(i, before, after, c, 1.0 - p);
        }
        Ok(())
    }

    /// Monte Carlo settings used for barriers of relative degree > 2
    /// (default 2 000 draws, step 10⁻², seed 0; the seed advances by one
    /// each step).
    pub fn set_monte_carlo(&mut self, mc: McSettings) {
        self.mc = mc;
    }

    /// The filter (settings, probability).
    pub fn filter_mut(&mut self) -> &mut SafetyFilter {
        &mut self.filter
    }

    /// Moments of the last step, one per barrier (their covariances
    /// inflated by `κ_i²` when the recalibration is on).
    pub fn barrier_moments(&self) -> &[ConditionMoments] {
        &self.cbcs
    }

    /// The moment workspace of the last step (posterior at `x`).
    pub fn workspace(&self) -> Option<&MomentWorkspace> {
        self.ws.as_ref()
    }

    /// One control step at state `x` around reference `u_ref`. `reference`
    /// gives `(x_d, ẋ_d)` for a time-varying CLF (zeros if absent).
    pub fn step<K: Kernel>(
        &mut self,
        model: &Mvgp<K>,
        x: &[f64],
        u_ref: &[f64],
        reference: Option<(&[f64], &[f64])>,
        out: &mut ControlOutput,
    ) -> Result<(), Error> {
        if model.control_dim() != self.filter.shape.m {
            return Err(InputError::shape(
                "model control dimension",
                self.filter.shape.m,
                model.control_dim(),
            )
            .into());
        }
        self.solved = false;
        let ws = self.ws.get_or_insert_with(|| MomentWorkspace::new(model));
        ws.update(model, x, self.max_degree)?;
        let cbcs = self.cbcs.iter_mut().zip(self.noise.iter_mut());
        for (i, (b, (mom, noise))) in self.barriers.iter().zip(cbcs).enumerate() {
            *noise = 0.0;
            if b.relative_degree() <= 2 {
                cbc_moments(ws, b.as_ref(), mom).map_err(naming_barrier(i))?;
                if self.filter.settings.predictive {
                    let latent = mom.cov[(0, 0)];
                    add_observation_noise(ws, mom)?;
                    *noise = mom.cov[(0, 0)] - latent;
                }
            } else {
                // no closed form: Monte Carlo over joint posterior draws,
                // a fresh deterministic seed each step
                let mc = McSettings {
                    seed: self.mc.seed.wrapping_add(self.steps),
                    ..self.mc
                };
                *mom = mc_cbc_moments(model, b.as_ref(), x, &mc)
                    .map_err(naming_barrier(i))?
                    .moments;
            }
        }
        self.steps += 1;
        if let Some(rc) = &self.recal {
            for (i, mom) in self.cbcs.iter_mut().enumerate() {
                let k = rc.inflation.inflation(i);
                if k != 1.0 {
                    mom.cov *= k * k;
                    mom.v *= k;
                }
            }
        }
        if let Some(c) = &self.clf {
            let zeros = self.zero_reference.as_slice();
            let (xd, xdd) = reference.unwrap_or((zeros, zeros));
            clc_moments(ws, c.as_ref(), xd, xdd, &mut self.clc)?;
            self.clc.check_finite("clf", x)?;
        }
        for (i, mom) in self.cbcs.iter().enumerate() {
            if mom.check_finite("", x).is_err() {
                mom.check_finite(&format!("barriers[{i}]"), x)?;
            }
        }
        self.solve(Some(x), u_ref, out)?;
        self.solved = true;
        Ok(())
    }

    /// Solves the last [`step`](Self::step)'s program again, from the same
    /// moments, with the filter's settings as they are now (after
    /// [`SafetyFilter::set_zeta`] or [`SafetyFilter::set_probability`]
    /// through [`filter_mut`](Self::filter_mut)): the state and reference
    /// are the step's, `u_ref` its reference control. An error before the
    /// first step and after a step that failed.
    pub fn resolve(&mut self, u_ref: &[f64], out: &mut ControlOutput) -> Result<(), Error> {
        if !self.solved {
            return Err(InputError::invalid_shown(
                "resolve",
                "without a solved step",
                "solves the last step's program again: call step first (a step that failed leaves none)",
            )
            .into());
        }
        self.solve(None, u_ref, out)
    }

    /// Solves the program of the moments in place and keeps the
    /// recalibration's record of the state `x` (`None`: the step's, kept)
    /// and the control.
    fn solve(
        &mut self,
        x: Option<&[f64]>,
        u_ref: &[f64],
        out: &mut ControlOutput,
    ) -> Result<(), Error> {
        let clc = self.clf.is_some().then_some(&self.clc);
        self.filter.solve(&self.cbcs, clc, u_ref, out)?;
        if let Some(rc) = self.recal.as_mut() {
            if let Some(x) = x {
                rc.x.clear();
                rc.x.extend_from_slice(x);
            }
            rc.u.clear();
            rc.u.extend_from_slice(&out.u);
            // the latent condition's moments: the innovation of a model
            // update is in the posterior of F, not in the noise
            for (i, (b, mom)) in self.barriers.iter().zip(&self.cbcs).enumerate() {
                let k = rc.inflation.inflation(i);
                rc.predicted[i] = (b.relative_degree() <= 2).then(|| {
                    let var = mom.variance(&out.u) / (k * k) - self.noise[i];
                    (mom.mean(&out.u), var)
                });
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    //! Private paths: the fallback where the max-margin program has no
    //! maximiser (no public program reaches it: an unbounded margin makes
    //! the control program feasible), and the check of a solved program.
    use super::*;

    /// A program whose CLF term is four orders of magnitude above its
    /// barrier conditions (a unicycle step, moments as recorded) is solved
    /// to an accuracy relative to the CLF's scale: its control missed
    /// barrier 0 by 1.2e-6, beyond the check's 1e-6 on that condition's
    /// scale, and stopped the run. The second solve, with that barrier's
    /// margin raised by twice the miss, finds the step infeasible: p* is
    /// 2·10⁻⁵ below the requested 0.99. At 0.98 the conditions hold.
    #[test]
    fn a_miss_at_the_solvers_accuracy_is_solved_again_with_a_margin() {
        let mom = |e: [f64; 3], cov: [f64; 9]| {
            ConditionMoments::from_parts(e.to_vec(), DMatrix::from_row_slice(3, 3, &cov), 1)
                .unwrap()
        };
        let cbcs = [
            mom(
                [
                    0.002607354483486818,
                    -1.3920448574085187,
                    -0.033023995910753584,
                ],
                [
                    1.3277135439070477e-6,
                    -7.705506190750196e-6,
                    6.679965950504242e-5,
                    -7.705506190750196e-6,
                    0.09819244019667119,
                    0.0001597668036168877,
                    6.679965950504242e-5,
                    0.0001597668036168877,
                    0.09687767252667533,
                ],
            ),
            mom(
                [10.444908477488362, -4.549721636146223, 0.29138521971150677],
                [
                    1.5487620932816424e-5,
                    -8.988381531955224e-5,
                    0.0007792101011569811,
                    -8.988381531955224e-5,
                    1.145403162612279,
                    0.0018636608050142118,
                    0.0007792101011569811,
                    0.0018636608050142118,
                    1.1300665537623782,
                ],
            ),
            mom(
                [26.411116504826065, -7.365585566350277, -0.14427073676880475],
                [
                    3.7006213243399295e-5,
                    -0.0002147689210159917,
                    0.0018618492336500015,
                    -0.0002147689210159917,
                    2.7368331049141883,
                    0.004453042172383507,
                    0.0018618492336500015,
                    0.004453042172383507,
                    2.7001877208366722,
                ],
            ),
        ];
        let clc = mom(
            [56.962613838451, -4.617417186254453, -0.009076178544572207],
            [
                1.4408291619389588e-5,
                -8.36198295790777e-5,
                0.0007249070996085,
                -8.36198295790777e-5,
                1.06558023729263,
                0.0017337826432318325,
                0.0007249070996085,
                0.0017337826432318325,
                1.0513124337532456,
            ],
        );
        let mut settings = SafetySettings::new(2);
        settings.u_min = Some(vec![0.0, -2.0]);
        settings.u_max = Some(vec![1.0, 2.0]);
        settings.lambda = 100.0;
        for (probability, feasible) in [(0.99, false), (0.98, true)] {
            settings.probability = probability;
            let mut filter = SafetyFilter::new(2, 3, true, settings.clone()).unwrap();
            let mut out = ControlOutput::new(2, 3);
            filter
                .solve(&cbcs, Some(&clc), &[0.0, 0.0], &mut out)
                .unwrap();
            if feasible {
                assert_eq!(out.status, ControlStatus::Optimal);
                for (k, r) in out.constraints.iter().enumerate() {
                    let tol = 1e-6 * (1.0 + r.mean.abs() + r.c * r.std);
                    assert!(r.slack >= -tol, "barrier {k}: slack {}", r.slack);
                }
                continue;
            }
            // p = 0.99 held to the solver's accuracy only: p* is 2·10⁻⁵
            // below it, and the step falls back, naming barrier 0
            let ControlStatus::Infeasible(info) = &out.status else {
                panic!("{out:?}");
            };
            assert_eq!(info.violated, [0]);
            let p_star = info.p_star.unwrap();
            assert!((0.9899..0.99).contains(&p_star), "p* {p_star}");
        }
    }

    /// A solved program's control passes within the check's tolerance of
    /// its status and fails beyond it, naming the barrier.
    #[test]
    fn solved_controls_are_checked_against_their_conditions() {
        let mom = ConditionMoments::from_parts(vec![1.0, 0.0], DMatrix::zeros(2, 2), 1).unwrap();
        let report = |slack: f64| ConstraintReport {
            mean: 1.0,
            std: 0.0,
            c: 1.0,
            slack,
        };
        let check = |slack: f64, status| {
            check_solution(
                &[mom.clone(), mom.clone()],
                &[report(0.0), report(slack)],
                status,
            )
        };
        // the tolerance is relative to 1 + |mean| + c·std = 2
        assert!(check(-1.9e-6, SolveStatus::Optimal).is_ok());
        assert!(check(-1.9e-2, SolveStatus::AlmostOptimal).is_ok());
        for (slack, status) in [
            (-2.1e-6, SolveStatus::Optimal),
            (-2.1e-2, SolveStatus::AlmostOptimal),
        ] {
            match check(slack, status) {
                Err(ControlError::Unresolved { barrier: 1, .. }) => {}
                other => panic!("{slack} {status:?}: {other:?}"),
            }
        }
    }

    /// A solution the check rejects leaves no control in `out`: its `u`
    /// is NaN, not the rejected control a caller ignoring the error would
    /// apply. The covariance `s·[1 −1; −1 1]` at `s = 10¹⁶` rounds its
    /// quadratic form by ~1 near `u = 1`, where the condition binds.
    #[test]
    fn a_rejected_solution_leaves_no_control() {
        let mut settings = SafetySettings::new(1);
        settings.u_min = Some(vec![-5.0]);
        settings.u_max = Some(vec![5.0]);
        settings.probability = 0.9;
        let solve = |s: f64, out: &mut ControlOutput| {
            let mut filter = SafetyFilter::new(1, 1, false, settings.clone()).unwrap();
            let a = 0.1;
            let cov = DMatrix::from_row_slice(2, 2, &[s * a * a, -s * a, -s * a, s]);
            let mom = ConditionMoments::from_parts(vec![-a, 1.0], cov, 1).unwrap();
            filter.solve(&[mom], None, &[0.0], out)
        };
        let mut out = ControlOutput::new(1, 1);
        // resolved at s = 10¹²: the condition binds at u = 0.1
        solve(1e12, &mut out).unwrap();
        assert!((out.u[0] - 0.1).abs() < 1e-9, "{out:?}");
        match solve(1e16, &mut out) {
            Err(Error::Control(ControlError::Unresolved { barrier: 0, .. })) => {}
            other => panic!("{other:?}"),
        }
        assert!(out.u[0].is_nan() && out.delta.is_nan(), "{out:?}");
    }

    /// A reference whose objective would overflow is an error naming
    /// `u_ref` (`1e308` read as infeasible, `1e160` without bounds as a
    /// numerical failure of the model); below the limit the program is
    /// solved: the condition `u ≥ 0.1` (certain) binds for any reference
    /// under it, and a reference above it is the control (within bounds).
    #[test]
    fn an_extreme_reference_is_named_or_solved() {
        for bounded in [false, true] {
            let mut settings = SafetySettings::new(1);
            if bounded {
                settings.u_min = Some(vec![-10.0]);
                settings.u_max = Some(vec![10.0]);
            }
            let mut filter = SafetyFilter::new(1, 1, false, settings).unwrap();
            let mom =
                ConditionMoments::from_parts(vec![-0.1, 1.0], DMatrix::zeros(2, 2), 1).unwrap();
            let mut out = ControlOutput::new(1, 1);
            let refused: &[f64] = if bounded {
                &[-1e308, 1e308, 2e299]
            } else {
                &[-1e308, 1e308, -1e160, 1e151]
            };
            for &u_ref in refused {
                let err = filter.solve(std::slice::from_ref(&mom), None, &[u_ref], &mut out);
                let text = err.unwrap_err().to_string();
                assert!(
                    text.contains("u_ref") && text.contains("overflow"),
                    "{text}"
                );
            }
            let solved = if bounded {
                vec![(-1e298, 0.1), (-1e160, 0.1), (1e160, 10.0), (5.0, 5.0)]
            } else {
                vec![(-1e149, 0.1), (-1e6, 0.1), (5.0, 5.0), (1e149, 1e149)]
            };
            for (u_ref, want) in solved {
                filter
                    .solve(std::slice::from_ref(&mom), None, &[u_ref], &mut out)
                    .unwrap();
                assert_eq!(out.status, ControlStatus::Optimal, "{u_ref}: {out:?}");
                assert!(
                    (out.u[0] - want).abs() <= 1e-6 * want.abs().max(1.0),
                    "{u_ref}: {out:?}"
                );
            }
        }
    }

    /// Without input bounds the worst margin is unbounded at low
    /// probabilities, and `p*` lies beyond them. Two conditions with a
    /// closed-form `p*`, `Var[C](u) = 1 + u²`:
    /// - `E[C] = 2 + u`: `max_u 2 + u − c√(1 + u²) = 2 − √(c² − 1)` for
    ///   `c ≥ 1` (unbounded below 1), zero at `c = √5`;
    /// - `E[C] = −1 + u`: unbounded for `c < 1`, negative from 1 on (the
    ///   supremum, −1, is never reached), so `p*` is the level of `c = 1`.
    ///
    /// `p*` is that factor's probability (Gaussian for relative degree 1,
    /// Cantelli for 2) and `relax` solves there, meeting the condition;
    /// also at a tolerance below the spacing of numbers near `p*`, where
    /// the bisection stops at neighbouring numbers.
    #[test]
    fn p_star_lies_beyond_an_unbounded_margin() {
        let mut fell_back = 0;
        for (e0, c_star) in [(2.0, 5f64.sqrt()), (-1.0, 1.0)] {
            for (degree, tol) in [(1, 1e-5), (2, 1e-5), (1, 1e-17), (2, 1e-17)] {
                let p_star = factor_probability(c_star, degree);
                let mut settings = SafetySettings::new(1);
                settings.fallback = Fallback::Relax;
                settings.p_star_tol = tol;
                settings.probability = 0.5 + 0.5 * p_star.max(0.6);
                let mut filter = SafetyFilter::new(1, 1, false, settings).unwrap();
                let mom =
                    ConditionMoments::from_parts(vec![e0, 1.0], DMatrix::identity(2, 2), degree)
                        .unwrap();
                let mut out = ControlOutput::new(1, 1);
                filter
                    .solve(std::slice::from_ref(&mom), None, &[0.0], &mut out)
                    .unwrap();
                let ControlStatus::Infeasible(info) = &out.status else {
                    panic!("{e0} {degree}: {out:?}");
                };
                let got = info.p_star.expect("p* exists");
                assert!(
                    (got - p_star).abs() < 1e-4,
                    "{e0} {degree}: p* {got} ≠ {p_star}"
                );
                assert!(got <= p_star + 1e-9, "{e0} {degree}: p* {got} > {p_star}");
                match info.fallback {
                    Fallback::Relax => {}
                    // p* that near the asymptote can ask for a control
                    // near 1/tol, beyond the solver: relax then falls back
                    // to the max-margin control, and says so
                    Fallback::MaxMargin if tol < 1e-9 => {
                        fell_back += 1;
                        continue;
                    }
                    other => panic!("{e0} {degree} {tol}: fallback {other:?}"),
                }
                // relax meets the condition at p* (its own factor)
                let c = quantile_factor(got, degree).unwrap();
                let slack = mom.mean(&out.u) - c * mom.variance(&out.u).sqrt();
                assert!(
                    slack > -1e-6,
                    "{e0} {degree}: slack {slack} at u {:?}",
                    out.u
                );
            }
        }
        assert!(fell_back > 0, "no case fell back to the max-margin control");
    }

    /// With no maximiser (here an unbounded margin: no bounds and a
    /// condition `E[C](u) = 1 + u₀` without variance) the max-margin and
    /// relax fallbacks brake, whatever the max-margin buffer held.
    #[test]
    fn max_margin_fallback_without_a_maximiser_brakes() {
        let mut filter = SafetyFilter::new(2, 1, false, SafetySettings::new(2)).unwrap();
        let mut mom = ConditionMoments::zeros(2);
        mom.e = vec![1.0, 1.0, 0.0];
        let cbcs = [mom];
        let mut out = ControlOutput::new(2, 1);
        for fallback in [Fallback::MaxMargin, Fallback::Relax] {
            filter.settings.fallback = fallback;
            let mut u_mm = [7.0, -7.0];
            out.u.copy_from_slice(&[3.0, 3.0]);
            assert_eq!(filter.max_margin(&cbcs, 0.9, &mut u_mm).unwrap(), None);
            assert_eq!(u_mm, [7.0, -7.0], "no maximiser is written");
            let info = filter
                .fall_back(&cbcs, None, SolveStatus::Failed, &mut out, &mut u_mm)
                .unwrap();
            assert_eq!(out.u, [0.0, 0.0], "{fallback:?}");
            assert_eq!(info.fallback, Fallback::Brake, "{fallback:?}");
            assert_eq!(info.p_star, None);
            assert_eq!(info.violated, Vec::<usize>::new());
        }
    }
}
