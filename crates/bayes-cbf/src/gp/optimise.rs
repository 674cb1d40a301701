//! The L-BFGS harness shared by the hyperparameter fits of the MVGP
//! ([`fit`](super::fit)) and the CoGP ([`fit_cogp`](super::fit_cogp)): both
//! minimise `−log p(θ)` over an unconstrained parameter vector `θ` with
//! argmin's L-BFGS and a More–Thuente line search, from one or more starts.
//!
//! ## Failed evaluations
//! Some `θ` cannot be evaluated: the Gram matrix does not factorise even with
//! jitter, `A` is not positive definite, the likelihood is not finite, or `θ`
//! left the box where the parameterisation is trusted. An [`Objective`] then
//! returns an [`EvalFailure`], and the argmin adapter passes it on as an
//! `Err` from `CostFunction::cost`.
//!
//! argmin 0.11 does not treat an `Err` as a rejected trial step: More–Thuente
//! (and Hager–Zhang alike) propagates it with `?`, and L-BFGS turns the
//! failed line search into `TerminationReason::SolverExit`, ending the whole
//! run. Two layers keep the fit going:
//!
//! 1. L-BFGS runs with a line search that rejects failed steps
//!    ([`RejectingLineSearch`], More–Thuente wrapped). The error of a failed
//!    trial step carries `θ_f = θ₀ + α_f d`; the wrapper catches it and
//!    restarts More–Thuente from the same `θ₀` and direction `d` with its
//!    steps bounded by half the smallest failed step, `α ≤ ½ min α_f`, and a
//!    cautious first trial at `10⁻³` of that bound, from which More–Thuente
//!    extrapolates until the strong Wolfe conditions hold or the bound is
//!    reached (the failed region lies beyond `α_f` along the line, as with
//!    too long a step out of `|θ| ≤ 50` or into an indefinite Gram matrix).
//!    This repeats, up to 30 halvings of the bound, while trial steps fail.
//!    L-BFGS never sees a handled failure and keeps its memory.
//! 2. If a line search still gives up (the bound fell below More–Thuente's
//!    smallest step, `√ε`), the error reaches L-BFGS and ends the run;
//!    [`Harness::run_start`] sees the failed last evaluation and resumes,
//!    with fresh memory, from the best point found, provided the run improved
//!    on the point it started from.
//!
//! A failure never becomes a point: only successful evaluations are
//! candidates for the best point, and a fit in which none succeeded is a
//! typed error.
//!
//! ## Resumption after a stall
//! A line search that fails for numerical reasons (normal near the optimum,
//! and on the curved valleys of `C Cᵀ + diag(v)`) also ends a run. With
//! [`RunSettings::stall_resumes`] `> 0` the start resumes, with fresh L-BFGS
//! memory, from its best point while that still improves and iterations
//! remain.
//!
//! ## Starts and pre-fits
//! [`multi_start`] runs the starts of a fit and keeps the best point over all
//! of them. Each start is described by a [`StartPlan`]: the point L-BFGS
//! begins at and further candidate points. A pre-fit is a start whose point
//! comes from fitting a restricted objective first (the CoGP fits diagonal
//! covariances and lifts that optimum into the full parameterisation); the
//! lifted optimum itself is then one of the plan's candidates, so the full
//! fit is never worse than the restricted one.

use crate::error::GpError;
use argmin::core::{
    CostFunction, Executor, Gradient, IterState, Problem, Solver, State, TerminationStatus, KV,
};
use argmin::solver::linesearch::{LineSearch, MoreThuenteLineSearch};
use argmin::solver::quasinewton::LBFGS;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use std::cell::RefCell;
use std::fmt;

/// Why an objective could not be evaluated at `θ`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum EvalFailure {
    /// `θ` is not finite, or a log-scale entry left `|θ_i| ≤ 50`.
    OutOfRange,
    /// The hyperparameters decoded from `θ` were rejected (kernel).
    InvalidHyper,
    /// The Gram matrix (or `A`) is not positive definite.
    NotPositiveDefinite,
    /// The log likelihood is not finite.
    NonFinite,
}

impl fmt::Display for EvalFailure {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            EvalFailure::OutOfRange => "parameters out of range",
            EvalFailure::InvalidHyper => "invalid kernel hyperparameters",
            EvalFailure::NotPositiveDefinite => "Gram matrix not positive definite",
            EvalFailure::NonFinite => "log likelihood not finite",
        })
    }
}

impl std::error::Error for EvalFailure {}

/// Outcome of one evaluation: `(−log p(θ), −∇θ log p(θ))`, or why `θ`
/// cannot be evaluated.
pub(crate) type Evaluation = Result<(f64, Vec<f64>), EvalFailure>;

/// A function to minimise: `−log p(θ)` and its gradient.
pub(crate) trait Objective {
    /// `(−log p(θ), −∇θ log p(θ))`, or why `θ` cannot be evaluated.
    fn eval(&self, theta: &[f64]) -> Evaluation;
}

/// A point and its objective value `−log p(θ)`.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Point {
    pub theta: Vec<f64>,
    pub value: f64,
}

/// What the harness remembers between calls from argmin.
#[derive(Debug, Default)]
struct EvalCache {
    /// `θ` and outcome of the last evaluation: argmin asks for the cost and
    /// then for the gradient at the same `θ`.
    last: Option<(Vec<f64>, Evaluation)>,
    /// Best successful evaluation of the current start.
    best: Option<Point>,
    /// The most recent failure, for the error when nothing succeeded.
    last_failure: Option<EvalFailure>,
    /// Objective evaluations (cache misses), failed ones included.
    evaluations: usize,
    /// Failed evaluations.
    failures: usize,
}

/// Settings of one start.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct RunSettings {
    /// L-BFGS iterations of the start, over all its runs.
    pub max_iters: u64,
    /// Resumptions from the best point (fresh memory) after a run that ends
    /// early without a failed evaluation, while the best point improves.
    pub stall_resumes: usize,
    /// End a run when an iteration improves `−log p` by less than this
    /// fraction of `max(|−log p(θ₀)|, 1)` at the start point `θ₀`.
    pub relative_cost_tolerance: Option<f64>,
}

/// L-BFGS history length.
const MEMORY: usize = 10;
/// Halvings of the step bound within one line search before it gives up.
const MAX_HALVINGS: usize = 30;
/// First trial step of a restarted line search, relative to its bound.
const RESTART_STEP: f64 = 1e-3;

type MoreThuente = MoreThuenteLineSearch<Vec<f64>, Vec<f64>, f64>;
type Lbfgs = LBFGS<RejectingLineSearch, Vec<f64>, Vec<f64>, f64>;

/// An objective with its evaluation cache, driven by argmin's L-BFGS.
pub(crate) struct Harness<O: Objective> {
    objective: O,
    cache: RefCell<EvalCache>,
}

impl<O: Objective> Harness<O> {
    pub fn new(objective: O) -> Self {
        Self {
            objective,
            cache: RefCell::new(EvalCache::default()),
        }
    }

    /// The objective.
    pub fn objective(&self) -> &O {
        &self.objective
    }

    /// Objective evaluations so far (cache misses, failed ones included).
    pub fn evaluations(&self) -> usize {
        self.cache.borrow().evaluations
    }

    /// Failed evaluations so far.
    pub fn failures(&self) -> usize {
        self.cache.borrow().failures
    }

    /// The most recent failure, if any.
    pub fn last_failure(&self) -> Option<EvalFailure> {
        self.cache.borrow().last_failure
    }

    /// `(−log p, −∇ log p)` at `θ`, through the cache; records the best
    /// successful point of the current start and counts failures.
    fn evaluate(&self, theta: &[f64]) -> Evaluation {
        let mut c = self.cache.borrow_mut();
        if let Some((t, r)) = &c.last {
            if t.as_slice() == theta {
                return r.clone();
            }
        }
        let r = self.objective.eval(theta);
        c.evaluations += 1;
        match &r {
            Ok((f, _)) => {
                if c.best.as_ref().is_none_or(|b| *f < b.value) {
                    c.best = Some(Point {
                        theta: theta.to_vec(),
                        value: *f,
                    });
                }
            }
            Err(e) => {
                c.failures += 1;
                c.last_failure = Some(*e);
            }
        }
        c.last = Some((theta.to_vec(), r.clone()));
        r
    }

    /// `θ` with its value, if it evaluates (counted, through the cache).
    pub fn point(&self, theta: Vec<f64>) -> Option<Point> {
        let (value, _) = self.evaluate(&theta).ok()?;
        Some(Point { theta, value })
    }

    fn best(&self) -> Option<Point> {
        self.cache.borrow().best.clone()
    }

    /// One start of L-BFGS from `theta` (module docs: failed evaluations
    /// and stalls). Returns the best point of this start, `None` if no
    /// evaluation succeeded (e.g. the start point itself fails).
    pub fn run_start(
        &self,
        theta: Vec<f64>,
        settings: &RunSettings,
    ) -> Result<Option<Point>, GpError> {
        self.cache.borrow_mut().best = None;
        let Ok((f0, _)) = self.evaluate(&theta) else {
            return Ok(None);
        };
        let tolerance = settings
            .relative_cost_tolerance
            .map(|r| r * f0.abs().max(1.0));
        let fresh = || -> Result<Lbfgs, GpError> {
            let solver = LBFGS::new(RejectingLineSearch::default(), MEMORY);
            match tolerance {
                Some(t) => solver
                    .with_tolerance_cost(t)
                    .map_err(|e| GpError::Optimisation(e.to_string())),
                None => Ok(solver),
            }
        };
        let (mut theta, mut remaining) = (theta, settings.max_iters);
        let (mut stalls, mut last, mut run_value) = (0, f64::INFINITY, f0);
        loop {
            let used = Executor::new(ArgminView(self), fresh()?)
                .configure(|st| st.param(theta).max_iters(remaining))
                .run()
                .map_or(remaining, |r| r.state.iter);
            let Some(best) = self.best() else {
                return Ok(None);
            };
            remaining = remaining.saturating_sub(used.max(1));
            if remaining == 0 {
                break;
            }
            // a line search that gives up on a failed step leaves it as the
            // last evaluation
            let failed = matches!(self.cache.borrow().last, Some((_, Err(_))));
            if failed {
                // a line search ended in a failed evaluation (layer 2)
                if best.value >= run_value {
                    break;
                }
            } else {
                let improved = best.value < last - 1e-8 * (1.0 + best.value.abs());
                if stalls >= settings.stall_resumes || !improved {
                    break;
                }
                stalls += 1;
                last = best.value;
            }
            run_value = best.value;
            theta = best.theta;
        }
        Ok(self.best())
    }
}

/// The argmin view of a harness.
struct ArgminView<'h, O: Objective>(&'h Harness<O>);

impl<O: Objective> CostFunction for ArgminView<'_, O> {
    type Param = Vec<f64>;
    type Output = f64;
    fn cost(&self, p: &Self::Param) -> Result<f64, argmin::core::Error> {
        self.0
            .evaluate(p)
            .map(|(f, _)| f)
            .map_err(|reason| FailedStep::error(p, reason))
    }
}

impl<O: Objective> Gradient for ArgminView<'_, O> {
    type Param = Vec<f64>;
    type Gradient = Vec<f64>;
    fn gradient(&self, p: &Self::Param) -> Result<Vec<f64>, argmin::core::Error> {
        self.0
            .evaluate(p)
            .map(|(_, g)| g)
            .map_err(|reason| FailedStep::error(p, reason))
    }
}

/// The error an evaluation failure becomes inside argmin: it carries `θ`, so
/// that [`RejectingLineSearch`] can tell which step failed.
#[derive(Debug)]
struct FailedStep {
    theta: Vec<f64>,
    reason: EvalFailure,
}

impl FailedStep {
    fn error(theta: &[f64], reason: EvalFailure) -> argmin::core::Error {
        argmin::core::Error::new(FailedStep {
            theta: theta.to_vec(),
            reason,
        })
    }
}

impl fmt::Display for FailedStep {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "objective failed at a trial point: {}", self.reason)
    }
}

impl std::error::Error for FailedStep {}

type LineState = IterState<Vec<f64>, Vec<f64>, (), (), (), f64>;

/// More–Thuente that rejects a trial step whose evaluation fails and
/// restarts from the same point and direction with its steps bounded by
/// half the smallest failed step (module docs, layer 1).
#[derive(Clone, Default)]
struct RejectingLineSearch {
    inner: MoreThuente,
    /// `θ₀`, `−log p(θ₀)` and its gradient at the start of the search.
    origin: Option<(Vec<f64>, f64, Vec<f64>)>,
    direction: Vec<f64>,
    /// Smallest failed step of this search.
    failed_step: f64,
    halvings: usize,
}

impl LineSearch<Vec<f64>, f64> for RejectingLineSearch {
    fn search_direction(&mut self, direction: Vec<f64>) {
        self.direction.clone_from(&direction);
        self.inner.search_direction(direction);
    }

    fn initial_step_length(&mut self, step_length: f64) -> Result<(), argmin::core::Error> {
        self.inner.initial_step_length(step_length)
    }
}

impl<P> Solver<P, LineState> for RejectingLineSearch
where
    MoreThuente: Solver<P, LineState>,
{
    fn name(&self) -> &str {
        "More-Thuente line search rejecting failed steps"
    }

    fn init(
        &mut self,
        problem: &mut Problem<P>,
        state: LineState,
    ) -> Result<(LineState, Option<KV>), argmin::core::Error> {
        self.origin = match (state.get_param(), state.get_gradient()) {
            (Some(t), Some(g)) if state.get_cost().is_finite() => {
                Some((t.clone(), state.get_cost(), g.clone()))
            }
            _ => None,
        };
        self.failed_step = f64::INFINITY;
        self.halvings = 0;
        self.inner.init(problem, state)
    }

    fn next_iter(
        &mut self,
        problem: &mut Problem<P>,
        state: LineState,
    ) -> Result<(LineState, Option<KV>), argmin::core::Error> {
        // after `init` the state holds no vectors: a cheap copy
        let backup = state.clone();
        let err = match self.inner.next_iter(problem, state) {
            Ok(r) => return Ok(r),
            Err(e) => e,
        };
        let failed_theta = match err.downcast_ref::<FailedStep>() {
            Some(f) => f.theta.clone(),
            None => return Err(err),
        };
        let Some((t0, f0, g0)) = self.origin.clone() else {
            return Err(err);
        };
        // the failed step along the direction: θ_f = θ₀ + α_f d
        let dd: f64 = self.direction.iter().map(|d| d * d).sum();
        let step = failed_theta
            .iter()
            .zip(&t0)
            .zip(&self.direction)
            .map(|((f, t), d)| (f - t) * d)
            .sum::<f64>()
            / dd;
        self.failed_step = self.failed_step.min(step);
        let bound = 0.5 * self.failed_step;
        let min_step = f64::EPSILON.sqrt();
        if bound.is_nan() || bound <= min_step || self.halvings >= MAX_HALVINGS {
            return Err(err);
        }
        self.halvings += 1;
        let mut inner = MoreThuente::new().with_bounds(min_step, bound)?;
        inner.initial_step_length((RESTART_STEP * bound).max(2.0 * min_step))?;
        inner.search_direction(self.direction.clone());
        self.inner = inner;
        let state = backup.param(t0).gradient(g0).cost(f0);
        self.inner.init(problem, state)
    }

    fn terminate(&mut self, state: &LineState) -> TerminationStatus {
        self.inner.terminate(state)
    }
}

/// Where one start begins, and points already known to it.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct StartPlan {
    /// Start point of L-BFGS.
    pub theta: Vec<f64>,
    /// Further candidates for the best point (e.g. a pre-fit's optimum,
    /// lifted into the full parameterisation), with their values.
    pub candidates: Vec<Point>,
}

impl StartPlan {
    /// A plain start at `theta`.
    pub fn at(theta: Vec<f64>) -> Self {
        Self {
            theta,
            candidates: Vec::new(),
        }
    }
}

/// Plans a start by a pre-fit (module docs): L-BFGS on `restricted` from
/// `theta`; then `lift(optimum)` returns the start point of the full fit and
/// the restricted optimum embedded in the full parameterisation, which
/// becomes a candidate if it evaluates. `lift(None)` (no restricted
/// evaluation succeeded) returns a cold start.
pub(crate) fn prefit<R: Objective, F: Objective, E: From<GpError>>(
    restricted: &Harness<R>,
    full: &Harness<F>,
    theta: Vec<f64>,
    settings: &RunSettings,
    lift: impl FnOnce(Option<&[f64]>) -> Result<(Vec<f64>, Option<Vec<f64>>), E>,
) -> Result<StartPlan, E> {
    let optimum = restricted.run_start(theta, settings)?;
    let (start, embedded) = lift(optimum.as_ref().map(|p| p.theta.as_slice()))?;
    Ok(StartPlan {
        theta: start,
        candidates: embedded.and_then(|t| full.point(t)).into_iter().collect(),
    })
}

/// Runs `starts` starts, start `s` planned by `plan(s)`, and returns the best
/// point over every start and candidate (the first on ties).
///
/// Fails with [`GpError::Optimisation`] if no evaluation succeeded.
pub(crate) fn multi_start<O: Objective, E: From<GpError>>(
    harness: &Harness<O>,
    starts: usize,
    settings: &RunSettings,
    mut plan: impl FnMut(usize) -> Result<StartPlan, E>,
) -> Result<Point, E> {
    let mut best: Option<Point> = None;
    for s in 0..starts {
        let StartPlan { theta, candidates } = plan(s)?;
        let found = harness.run_start(theta, settings)?;
        for p in candidates.into_iter().chain(found) {
            if best.as_ref().is_none_or(|b| p.value < b.value) {
                best = Some(p);
            }
        }
    }
    if harness.failures() > 0 {
        log::debug!(
            "hyperparameter fit: {} of {} evaluations failed",
            harness.failures(),
            harness.evaluations()
        );
    }
    best.ok_or_else(|| {
        let why = harness
            .last_failure()
            .map_or("no evaluation".to_string(), |f| f.to_string());
        GpError::Optimisation(format!(
            "no hyperparameters gave a finite likelihood (last failure: {why})"
        ))
        .into()
    })
}

/// Adds `N(0, 0.5²)` noise to every entry (random restarts).
pub(crate) fn perturb(theta: &mut [f64], rng: &mut ChaCha8Rng) {
    for v in theta.iter_mut() {
        let z: f64 = StandardNormal.sample(rng);
        *v += 0.5 * z;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `(3/2) Σ (θ_i − 1)²`, failing outside `|θ_i| < limit`.
    struct Bowl {
        limit: f64,
    }

    impl Objective for Bowl {
        fn eval(&self, th: &[f64]) -> Evaluation {
            if th.iter().any(|v| v.abs() >= self.limit) {
                return Err(EvalFailure::OutOfRange);
            }
            let f = th.iter().map(|v| 1.5 * (v - 1.0).powi(2)).sum();
            Ok((f, th.iter().map(|v| 3.0 * (v - 1.0)).collect()))
        }
    }

    fn settings() -> RunSettings {
        RunSettings {
            max_iters: 50,
            stall_resumes: 0,
            relative_cost_tolerance: None,
        }
    }

    #[test]
    fn failed_steps_are_rejected_and_the_run_goes_on() {
        // the first steepest-descent step goes from (25, −20) to (−47, 43),
        // outside the box: the line search rejects it and tries shorter ones
        let h = Harness::new(Bowl { limit: 30.0 });
        let p = h
            .run_start(vec![25.0, -20.0], &settings())
            .unwrap()
            .unwrap();
        assert!(h.failures() > 0);
        assert!(p.value < 1e-12, "{p:?}");
        for v in &p.theta {
            assert!((v - 1.0).abs() < 1e-6, "{p:?}");
        }
    }

    #[test]
    fn a_failing_start_point_gives_no_point_and_a_typed_error() {
        let h = Harness::new(Bowl { limit: 1.0 });
        assert_eq!(h.run_start(vec![5.0], &settings()).unwrap(), None);
        let e = multi_start(&h, 2, &settings(), |_| {
            Ok::<_, GpError>(StartPlan::at(vec![5.0]))
        })
        .unwrap_err();
        assert!(matches!(e, GpError::Optimisation(_)), "{e}");
        assert_eq!(h.last_failure(), Some(EvalFailure::OutOfRange));
    }

    #[test]
    fn candidates_compete_with_the_runs() {
        let h = Harness::new(Bowl { limit: 100.0 });
        let exact = Point {
            theta: vec![1.0],
            value: 0.0,
        };
        let p = multi_start(&h, 1, &settings(), |_| {
            Ok::<_, GpError>(StartPlan {
                theta: vec![3.0],
                candidates: vec![exact.clone()],
            })
        })
        .unwrap();
        assert_eq!(p, exact);
    }
}
