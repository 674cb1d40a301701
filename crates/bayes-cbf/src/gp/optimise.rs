//! The optimiser shared by the hyperparameter fits of the MVGP
//! ([`fit`](super::fit)) and the CoGP ([`fit_cogp`](super::fit_cogp)): both
//! minimise `−log p(θ)` over a box `l ≤ θ ≤ u` with a projected L-BFGS, from
//! one or more starts.
//!
//! ## Projected L-BFGS
//! At `θ` with gradient `g`, a coordinate at a bound whose gradient points
//! out of the box is *active* and held; the others are free. With `P` the
//! projection onto the free coordinates and `H` the L-BFGS inverse-Hessian
//! approximation (two-loop recursion, 10 pairs, initial scaling
//! `sᵀy/yᵀy`), the direction is `d = −P H P g`, a descent direction since
//! `gᵀd = −(Pg)ᵀ H (Pg) < 0`; a free coordinate at its bound that `d` would
//! push out of the box joins the active set and `d` is recomputed. The
//! line search looks for the strong Wolfe conditions on `θ + α d`,
//! `0 < α ≤ α_max`, where `α_max` is the longest step inside the box
//! (sufficient decrease alone at `α_max`, where a coordinate reaches its
//! bound and becomes active at the next iteration); it starts from
//! `α = 1` (`1/‖d‖` without memory). A pair `(s, y)` enters the memory only
//! if `sᵀy > 10⁻¹⁰ yᵀy`, which keeps `H` positive definite. This is the
//! active-set scheme of Bertsekas, *Projected Newton methods for
//! optimization problems with simple constraints*, SIAM J. Control Optim.
//! 20 (1982), with the limited-memory matrix and the bounded line search of
//! Byrd, Lu, Nocedal and Zhu's L-BFGS-B (SIAM J. Sci. Comput. 16, 1995),
//! without its Cauchy-point search.
//!
//! A parameter at its bound therefore costs nothing: it stops moving, where
//! an unconstrained optimiser on a transformed parameter (`σ = σ_min +
//! e^θ`) walks towards `θ → −∞` with vanishing gradients.
//!
//! A run stops when the projected gradient `‖Π(θ − g) − θ‖_∞` (`Π` the
//! projection onto the box) falls below `10⁻⁵`, when an iteration lowers
//! `f` by less than [`RunSettings::relative_cost_tolerance`] `× max(|f|,
//! 1)`, when the line search fails, or after [`RunSettings::max_iters`]
//! iterations.
//!
//! ## Failed evaluations
//! Some `θ` cannot be evaluated: the Gram matrix does not factorise (the
//! fits factorise exactly, without jitter), the likelihood is not finite,
//! or the hyperparameters are rejected. An [`Objective`] then returns an
//! [`EvalFailure`], and the line search takes the trial point as one with
//! `f = +∞`: the next trial is a tenth of the way from the best point to
//! it. A failure never becomes a point: only successful evaluations are
//! candidates for the best point, and a fit in which none succeeded is a
//! typed error.
//!
//! ## Resumption after a stall
//! A line search that fails for numerical reasons (near the optimum, or on
//! a curved valley where the memory misleads) ends a run. With
//! [`RunSettings::stall_resumes`] `> 0` the start resumes, with fresh
//! memory, from its best point while that still improves and iterations
//! remain.
//!
//! ## Stopping
//! A harness given a stop flag ([`Harness::with_stop`]) checks it before
//! every evaluation and iteration: once it is set, evaluations fail at once
//! and the start ends with [`Error::Interrupted`], within one likelihood
//! evaluation of the flag being set.
//!
//! ## Starts and pre-fits
//! [`multi_start`] runs the starts of a fit and keeps the best point over all
//! of them. Each start is described by a [`StartPlan`]: the point L-BFGS
//! begins at and further candidate points. A pre-fit is a start whose point
//! comes from fitting a restricted objective first (the CoGP fits diagonal
//! covariances and lifts that optimum into the full parameterisation); the
//! lifted optimum itself is then one of the plan's candidates, so the full
//! fit is never worse than the restricted one.

use crate::error::{Error, GpError, InputError};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use std::collections::VecDeque;
use std::fmt;
use std::sync::atomic::{AtomicBool, Ordering};

/// Checks the iteration budget and the number of restarts of a fit's
/// settings: `max_iters ≥ 1`, `restarts ≤ 1000`.
pub(crate) fn check_run_settings(max_iters: u64, restarts: usize) -> Result<(), InputError> {
    if max_iters == 0 {
        return Err(InputError::invalid("max_iters", 0.0, "must be ≥ 1"));
    }
    if restarts > 1000 {
        return Err(InputError::invalid_shown(
            "restarts",
            restarts,
            "must be ≤ 1000",
        ));
    }
    Ok(())
}

/// Why an objective could not be evaluated at `θ`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum EvalFailure {
    /// `θ` is not finite.
    OutOfRange,
    /// The hyperparameters decoded from `θ` were rejected (kernel).
    InvalidHyper,
    /// The Gram matrix (or `A`) is not positive definite.
    NotPositiveDefinite,
    /// The log likelihood is not finite.
    NonFinite,
    /// The fit's stop flag is set.
    Stopped,
}

impl fmt::Display for EvalFailure {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            EvalFailure::OutOfRange => "parameters not finite",
            EvalFailure::InvalidHyper => "invalid kernel hyperparameters",
            EvalFailure::NotPositiveDefinite => "Gram matrix not positive definite",
            EvalFailure::NonFinite => "log likelihood not finite",
            EvalFailure::Stopped => "stopped",
        })
    }
}

impl std::error::Error for EvalFailure {}

/// A function to minimise over a box: `−log p(θ)` and its gradient.
pub(crate) trait Objective {
    /// `−log p(θ)`, with `−∇θ log p(θ)` written into `grad` (of the length
    /// of `θ`), or why `θ` cannot be evaluated.
    fn eval(&mut self, theta: &[f64], grad: &mut [f64]) -> Result<f64, EvalFailure>;

    /// Lower and upper bounds of `θ` (infinite where unbounded).
    fn bounds(&self) -> (&[f64], &[f64]);
}

/// A point and its objective value `−log p(θ)`.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Point {
    pub theta: Vec<f64>,
    pub value: f64,
}

/// Settings of one start.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct RunSettings {
    /// Iterations of the start, over all its runs.
    pub max_iters: u64,
    /// Resumptions from the best point (fresh memory) after a run whose
    /// line search fails, while the best point improves.
    pub stall_resumes: usize,
    /// End a run when an iteration lowers `f` by less than this fraction of
    /// `max(|f|, 1)`.
    pub relative_cost_tolerance: f64,
}

/// L-BFGS history length.
const MEMORY: usize = 10;
/// Trial steps of one line search.
const MAX_TRIALS: usize = 30;
/// Projected-gradient tolerance (`‖Π(θ − g) − θ‖_∞`).
const PG_TOLERANCE: f64 = 1e-5;

/// Why a run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stop {
    /// Projected gradient or relative decrease below tolerance.
    Converged,
    /// The line search found no acceptable step.
    LineSearch,
    /// Iterations used up.
    Iterations,
    /// The stop flag is set.
    Stopped,
}

/// One curvature pair of the L-BFGS memory.
#[derive(Debug, Clone)]
struct Pair {
    s: Vec<f64>,
    y: Vec<f64>,
    rho: f64,
}

/// An objective with its counters, minimised by projected L-BFGS.
pub(crate) struct Harness<'s, O: Objective> {
    objective: O,
    /// Ends the fit once set (module docs).
    stop: Option<&'s AtomicBool>,
    /// Objective evaluations, failed ones included.
    evaluations: usize,
    /// Failed evaluations.
    failures: usize,
    /// The most recent failure, for the error when nothing succeeded.
    last_failure: Option<EvalFailure>,
    /// Best successful evaluation of the current start.
    best: Option<Point>,
}

impl<'s, O: Objective> Harness<'s, O> {
    pub fn new(objective: O) -> Self {
        Self {
            objective,
            stop: None,
            evaluations: 0,
            failures: 0,
            last_failure: None,
            best: None,
        }
    }

    /// The harness, stopping once `stop` is set (module docs).
    pub fn with_stop(mut self, stop: &'s AtomicBool) -> Self {
        self.stop = Some(stop);
        self
    }

    /// Whether the stop flag is set.
    pub fn stopped(&self) -> bool {
        self.stop.is_some_and(|s| s.load(Ordering::Relaxed))
    }

    /// The objective.
    pub fn objective(&self) -> &O {
        &self.objective
    }

    /// The objective, mutably.
    pub fn objective_mut(&mut self) -> &mut O {
        &mut self.objective
    }

    /// Objective evaluations so far (failed ones included).
    pub fn evaluations(&self) -> usize {
        self.evaluations
    }

    /// Failed evaluations so far.
    pub fn failures(&self) -> usize {
        self.failures
    }

    /// The most recent failure, if any.
    pub fn last_failure(&self) -> Option<EvalFailure> {
        self.last_failure
    }

    /// `−log p(θ)` with its gradient; counts the evaluation and records the
    /// best successful point of the current start.
    fn evaluate(&mut self, theta: &[f64], grad: &mut [f64]) -> Result<f64, EvalFailure> {
        if self.stopped() {
            return Err(EvalFailure::Stopped);
        }
        self.evaluations += 1;
        let r = if theta.iter().all(|v| v.is_finite()) {
            self.objective.eval(theta, grad)
        } else {
            Err(EvalFailure::OutOfRange)
        };
        match r {
            Ok(f) if f.is_finite() && grad.iter().all(|g| g.is_finite()) => {
                if self.best.as_ref().is_none_or(|b| f < b.value) {
                    self.best = Some(Point {
                        theta: theta.to_vec(),
                        value: f,
                    });
                }
                Ok(f)
            }
            Ok(_) => self.fail(EvalFailure::NonFinite),
            Err(e) => self.fail(e),
        }
    }

    fn fail(&mut self, e: EvalFailure) -> Result<f64, EvalFailure> {
        self.failures += 1;
        self.last_failure = Some(e);
        Err(e)
    }

    /// `θ` projected into the box.
    fn project(&self, theta: &mut [f64]) {
        let (lo, hi) = self.objective.bounds();
        for ((t, l), h) in theta.iter_mut().zip(lo).zip(hi) {
            *t = t.clamp(*l, *h);
        }
    }

    /// `θ` (projected into the box) with its value, if it evaluates.
    pub fn point(&mut self, mut theta: Vec<f64>) -> Option<Point> {
        self.project(&mut theta);
        let mut g = vec![0.0; theta.len()];
        let value = self.evaluate(&theta, &mut g).ok()?;
        Some(Point { theta, value })
    }

    /// The better of `start` and `own` (a model's own hyperparameters, when
    /// the fit is not warm-started) to start from, with its value: a fit
    /// that starts from the model it was given when that is the better
    /// point never ends below it. `None` when neither evaluates. An `own`
    /// within 10⁻⁶ of `start` (a model made at the data-driven
    /// start) costs no evaluation.
    pub fn better_start(
        &mut self,
        start: Vec<f64>,
        own: Option<Vec<f64>>,
    ) -> (Vec<f64>, Option<f64>) {
        let at_start = self.point(start.clone()).map(|p| p.value);
        let same = |own: &Vec<f64>| {
            own.iter()
                .zip(&start)
                .all(|(a, b)| (a - b).abs() <= 1e-6 * (1.0 + b.abs()))
        };
        match own.filter(|own| !same(own)).and_then(|own| self.point(own)) {
            Some(p) if at_start.is_none_or(|v| p.value < v) => (p.theta, Some(p.value)),
            _ => (start, at_start),
        }
    }

    /// One start of projected L-BFGS from `theta` (projected into the box;
    /// module docs). Returns the best point of this start, `None` if no
    /// evaluation succeeded (e.g. the start point itself fails).
    pub fn run_start(
        &mut self,
        mut theta: Vec<f64>,
        settings: &RunSettings,
    ) -> Result<Option<Point>, Error> {
        self.best = None;
        self.project(&mut theta);
        let mut grad = vec![0.0; theta.len()];
        let mut value = match self.evaluate(&theta, &mut grad) {
            Ok(v) => v,
            Err(EvalFailure::Stopped) => return Err(Error::Interrupted),
            Err(_) => return Ok(None),
        };
        let (mut remaining, mut resumes) = (settings.max_iters, 0);
        loop {
            let run_value = value;
            let (used, stop) =
                self.minimise(&mut theta, &mut value, &mut grad, remaining, settings);
            if stop == Stop::Stopped {
                return Err(Error::Interrupted);
            }
            remaining = remaining.saturating_sub(used.max(1));
            // a run whose line search failed resumes, with fresh memory, from
            // its last (best accepted) point if it improved on its start
            let improved = value < run_value;
            if stop != Stop::LineSearch
                || remaining == 0
                || resumes >= settings.stall_resumes
                || !improved
            {
                break;
            }
            resumes += 1;
        }
        Ok(self.best.clone())
    }

    /// Projected L-BFGS from `(θ, f, g)` for at most `max_iters` iterations;
    /// leaves the last accepted point in `(θ, f, g)`. Returns the iterations
    /// used and why it stopped.
    fn minimise(
        &mut self,
        theta: &mut [f64],
        f: &mut f64,
        g: &mut [f64],
        max_iters: u64,
        settings: &RunSettings,
    ) -> (u64, Stop) {
        let dim = theta.len();
        let mut memory: VecDeque<Pair> = VecDeque::with_capacity(MEMORY);
        let mut d = vec![0.0; dim];
        let mut free = vec![true; dim];
        let mut search = LineSearch::new(dim);
        for it in 0..max_iters {
            if self.stopped() {
                return (it, Stop::Stopped);
            }
            let (lo, hi) = self.objective.bounds();
            // convergence on the projected gradient; the active set
            let mut pg = 0.0f64;
            for i in 0..dim {
                let step = (theta[i] - g[i]).clamp(lo[i], hi[i]) - theta[i];
                pg = pg.max(step.abs());
                free[i] = !((theta[i] <= lo[i] && g[i] > 0.0) || (theta[i] >= hi[i] && g[i] < 0.0));
            }
            if pg <= PG_TOLERANCE {
                return (it, Stop::Converged);
            }
            // d = −P H P g; a free coordinate at its bound that d would push
            // out of the box joins the active set, and d is recomputed
            let slope = loop {
                direction(&memory, g, &free, &mut d);
                let mut slope = dot(g, &d);
                if slope.is_nan() || slope >= 0.0 {
                    memory.clear();
                    direction(&memory, g, &free, &mut d);
                    slope = dot(g, &d);
                }
                let blocked: Vec<usize> = (0..dim)
                    .filter(|&i| {
                        free[i]
                            && ((theta[i] <= lo[i] && d[i] < 0.0)
                                || (theta[i] >= hi[i] && d[i] > 0.0))
                    })
                    .collect();
                if blocked.is_empty() {
                    break slope;
                }
                for i in blocked {
                    free[i] = false;
                }
            };
            if slope.is_nan() || slope >= 0.0 {
                return (it, Stop::Converged);
            }
            // the longest step inside the box
            let mut alpha_max = f64::INFINITY;
            for i in 0..dim {
                if d[i] < 0.0 {
                    alpha_max = alpha_max.min((lo[i] - theta[i]) / d[i]);
                } else if d[i] > 0.0 {
                    alpha_max = alpha_max.min((hi[i] - theta[i]) / d[i]);
                }
            }
            let alpha0 = if memory.is_empty() {
                1.0 / norm(&d).max(1.0)
            } else {
                1.0
            };
            let Some(ft) = search.run(self, theta, *f, slope, &d, alpha0.min(alpha_max), alpha_max)
            else {
                let why = if self.stopped() {
                    Stop::Stopped
                } else {
                    Stop::LineSearch
                };
                return (it, why);
            };
            // curvature pair
            let s: Vec<f64> = (0..dim).map(|i| search.point[i] - theta[i]).collect();
            let y: Vec<f64> = (0..dim).map(|i| search.grad[i] - g[i]).collect();
            let (sy, yy) = (dot(&s, &y), dot(&y, &y));
            if sy > 1e-10 * yy {
                if memory.len() == MEMORY {
                    memory.pop_front();
                }
                memory.push_back(Pair {
                    s,
                    y,
                    rho: 1.0 / sy,
                });
            }
            let converged = *f - ft <= settings.relative_cost_tolerance * f.abs().max(1.0);
            theta.copy_from_slice(&search.point);
            g.copy_from_slice(&search.grad);
            *f = ft;
            if converged {
                return (it + 1, Stop::Converged);
            }
        }
        (max_iters, Stop::Iterations)
    }
}

/// `d = −P H P g` by the two-loop recursion (module docs), `P` the
/// projection onto the `free` coordinates.
fn direction(memory: &VecDeque<Pair>, g: &[f64], free: &[bool], d: &mut [f64]) {
    let mut alphas = [0.0; MEMORY];
    for i in 0..d.len() {
        d[i] = if free[i] { g[i] } else { 0.0 };
    }
    for (a, p) in alphas.iter_mut().zip(memory.iter().rev()) {
        *a = p.rho * dot(&p.s, d);
        axpy(-*a, &p.y, d);
    }
    if let Some(p) = memory.back() {
        let gamma = 1.0 / (p.rho * dot(&p.y, &p.y));
        d.iter_mut().for_each(|v| *v *= gamma);
    }
    for (a, p) in alphas.iter().zip(memory.iter().rev()).rev() {
        let b = p.rho * dot(&p.y, d);
        axpy(a - b, &p.s, d);
    }
    for i in 0..d.len() {
        d[i] = if free[i] { -d[i] } else { 0.0 };
    }
}

/// A trial step of the line search: `α`, `φ(α) = f(θ + αd)` and
/// `φ'(α) = ∇f(θ + αd)ᵀd` (`φ = +∞` where the evaluation failed).
#[derive(Debug, Clone, Copy)]
struct Trial {
    alpha: f64,
    value: f64,
    slope: f64,
}

/// Line search for the strong Wolfe conditions
/// `φ(α) ≤ φ(0) + c₁ α φ'(0)` and `|φ'(α)| ≤ c₂ |φ'(0)|` (`c₁ = 10⁻⁴`,
/// `c₂ = 0.9`) on `0 < α ≤ α_max`, by bracketing and zooming with
/// safeguarded cubic interpolation (Nocedal & Wright, *Numerical
/// Optimization*, 2nd ed., Algorithms 3.5 and 3.6). A failed evaluation
/// counts as `φ = +∞`. At `α_max` (a bound reached) sufficient decrease
/// alone is accepted.
struct LineSearch {
    /// The accepted point and its gradient.
    point: Vec<f64>,
    grad: Vec<f64>,
    /// The trial point and its gradient.
    trial: Vec<f64>,
    trial_grad: Vec<f64>,
}

impl LineSearch {
    fn new(dim: usize) -> Self {
        Self {
            point: vec![0.0; dim],
            grad: vec![0.0; dim],
            trial: vec![0.0; dim],
            trial_grad: vec![0.0; dim],
        }
    }

    /// Evaluates `θ + αd` (clamped into the box) into `trial`.
    fn probe<O: Objective>(
        &mut self,
        h: &mut Harness<O>,
        theta: &[f64],
        d: &[f64],
        alpha: f64,
    ) -> Trial {
        let (lo, hi) = h.objective.bounds();
        for i in 0..theta.len() {
            self.trial[i] = (theta[i] + alpha * d[i]).clamp(lo[i], hi[i]);
        }
        match h.evaluate(&self.trial, &mut self.trial_grad) {
            Ok(value) => Trial {
                alpha,
                value,
                slope: dot(&self.trial_grad, d),
            },
            Err(_) => Trial {
                alpha,
                value: f64::INFINITY,
                slope: f64::NAN,
            },
        }
    }

    /// Keeps the trial as the accepted point.
    fn keep(&mut self) {
        self.point.copy_from_slice(&self.trial);
        self.grad.copy_from_slice(&self.trial_grad);
    }

    /// Searches from `θ` (value `f0`, slope `φ'(0) = s0 < 0`) along `d`;
    /// returns the accepted value (point and gradient in `point`, `grad`),
    /// or `None` if no step lowered `f`.
    #[allow(clippy::too_many_arguments)]
    fn run<O: Objective>(
        &mut self,
        h: &mut Harness<O>,
        theta: &[f64],
        f0: f64,
        s0: f64,
        d: &[f64],
        alpha0: f64,
        alpha_max: f64,
    ) -> Option<f64> {
        const C1: f64 = 1e-4;
        const C2: f64 = 0.9;
        let armijo = |t: &Trial| t.value <= f0 + C1 * t.alpha * s0 && t.value < f0;
        let wolfe = |t: &Trial| t.slope.abs() <= -C2 * s0;
        let mut prev = Trial {
            alpha: 0.0,
            value: f0,
            slope: s0,
        };
        // the best point with sufficient decrease seen so far
        let mut best: Option<f64> = None;
        let d_max = d.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let mut alpha = alpha0;
        let mut trials = 0;
        let (lo, hi) = loop {
            if trials == MAX_TRIALS || alpha.is_nan() || alpha <= 0.0 {
                return best;
            }
            trials += 1;
            let t = self.probe(h, theta, d, alpha);
            if !armijo(&t) || (trials > 1 && t.value >= prev.value) {
                break (prev, t);
            }
            self.keep();
            best = Some(t.value);
            if wolfe(&t) || alpha >= alpha_max {
                return best;
            }
            if t.slope >= 0.0 {
                break (t, prev);
            }
            prev = t;
            alpha = (4.0 * alpha).min(alpha_max);
        };
        // zoom: `lo` satisfies sufficient decrease and has the lower value,
        // the minimiser lies between `lo` and `hi`
        let (mut lo, mut hi) = (lo, hi);
        while trials < MAX_TRIALS {
            trials += 1;
            let (a_lo, a_hi) = (lo.alpha.min(hi.alpha), lo.alpha.max(hi.alpha));
            let width = a_hi - a_lo;
            let alpha = match cubic_minimiser(&lo, &hi) {
                Some(a) if hi.value.is_finite() => a.clamp(a_lo + 0.1 * width, a_hi - 0.1 * width),
                // a failed evaluation at `hi`: a tenth of the way there
                _ => lo.alpha + 0.1 * (hi.alpha - lo.alpha),
            };
            // steps that move θ by less than 10⁻⁹ resolve only roundoff
            // (the likelihood of a nearly singular Gram matrix is noisy at
            // a relative 10⁻⁶)
            if (alpha - lo.alpha).abs() * d_max < 1e-9 {
                break;
            }
            let t = self.probe(h, theta, d, alpha);
            if !armijo(&t) || t.value >= lo.value {
                hi = t;
                continue;
            }
            self.keep();
            best = Some(t.value);
            if wolfe(&t) {
                break;
            }
            if t.slope * (hi.alpha - lo.alpha) >= 0.0 {
                hi = lo;
            }
            lo = t;
        }
        best
    }
}

/// The minimiser of the cubic through two trials' values and slopes, if it
/// exists (Nocedal & Wright, Eq. 3.59).
fn cubic_minimiser(a: &Trial, b: &Trial) -> Option<f64> {
    let d1 = a.slope + b.slope - 3.0 * (a.value - b.value) / (a.alpha - b.alpha);
    let disc = d1 * d1 - a.slope * b.slope;
    if disc.is_nan() || disc < 0.0 {
        return None;
    }
    let d2 = (b.alpha - a.alpha).signum() * disc.sqrt();
    let x = b.alpha - (b.alpha - a.alpha) * (b.slope + d2 - d1) / (b.slope - a.slope + 2.0 * d2);
    x.is_finite().then_some(x)
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn norm(a: &[f64]) -> f64 {
    dot(a, a).sqrt()
}

fn axpy(a: f64, x: &[f64], y: &mut [f64]) {
    for (yi, xi) in y.iter_mut().zip(x) {
        *yi += a * xi;
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

/// Runs `starts` starts, start `s` planned by `plan(harness, s)`, and
/// returns the best point over every start and candidate (the first on
/// ties).
///
/// Fails with [`GpError::Optimisation`] if no evaluation succeeded, with
/// [`Error::Interrupted`] once the harness's stop flag is set.
pub(crate) fn multi_start<O: Objective>(
    harness: &mut Harness<O>,
    starts: usize,
    settings: &RunSettings,
    plan: impl FnMut(&mut Harness<O>, usize) -> Result<StartPlan, Error>,
) -> Result<Point, Error> {
    let mut ranked = multi_start_ranked(harness, starts, settings, plan)?;
    Ok(ranked.swap_remove(0))
}

/// [`multi_start`], returning the best point of each start (its run or
/// its candidates), best first (earlier starts first on ties): for a fit
/// whose result is adjusted afterwards, which may change the order.
pub(crate) fn multi_start_ranked<O: Objective>(
    harness: &mut Harness<O>,
    starts: usize,
    settings: &RunSettings,
    mut plan: impl FnMut(&mut Harness<O>, usize) -> Result<StartPlan, Error>,
) -> Result<Vec<Point>, Error> {
    let mut ranked: Vec<Point> = Vec::with_capacity(starts);
    for s in 0..starts {
        let StartPlan { theta, candidates } = plan(harness, s)?;
        let found = harness.run_start(theta, settings)?;
        let mut best: Option<Point> = None;
        for p in candidates.into_iter().chain(found) {
            if best.as_ref().is_none_or(|b| p.value < b.value) {
                best = Some(p);
            }
        }
        ranked.extend(best);
    }
    // stable: the first of equal values stays first
    ranked.sort_by(|a, b| a.value.total_cmp(&b.value));
    if harness.failures() > 0 {
        log::debug!(
            "hyperparameter fit: {} of {} evaluations failed",
            harness.failures(),
            harness.evaluations()
        );
    }
    if ranked.is_empty() {
        let why = harness
            .last_failure()
            .map_or("no evaluation".to_string(), |f| f.to_string());
        return Err(GpError::Optimisation(format!(
            "no hyperparameters gave a finite likelihood (last failure: {why})"
        ))
        .into());
    }
    Ok(ranked)
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

    /// `Σ c_i (θ_i − 1)²` on the box `[lo, hi]`, failing outside
    /// `|θ_i| < limit`; counts evaluations.
    struct Bowl {
        c: Vec<f64>,
        limit: f64,
        lo: Vec<f64>,
        hi: Vec<f64>,
    }

    impl Bowl {
        fn unbounded(c: Vec<f64>, limit: f64) -> Self {
            let n = c.len();
            Self {
                c,
                limit,
                lo: vec![f64::NEG_INFINITY; n],
                hi: vec![f64::INFINITY; n],
            }
        }
    }

    impl Objective for Bowl {
        fn eval(&mut self, th: &[f64], g: &mut [f64]) -> Result<f64, EvalFailure> {
            if th.iter().any(|v| v.abs() >= self.limit) {
                return Err(EvalFailure::OutOfRange);
            }
            for i in 0..th.len() {
                g[i] = 2.0 * self.c[i] * (th[i] - 1.0);
            }
            Ok(th
                .iter()
                .zip(&self.c)
                .map(|(v, c)| c * (v - 1.0).powi(2))
                .sum())
        }
        fn bounds(&self) -> (&[f64], &[f64]) {
            (&self.lo, &self.hi)
        }
    }

    /// The Rosenbrock function `(1 − a)² + 100 (b − a²)²`.
    struct Rosenbrock {
        lo: Vec<f64>,
        hi: Vec<f64>,
    }

    impl Objective for Rosenbrock {
        fn eval(&mut self, th: &[f64], g: &mut [f64]) -> Result<f64, EvalFailure> {
            let (a, b) = (th[0], th[1]);
            g[0] = -2.0 * (1.0 - a) - 400.0 * a * (b - a * a);
            g[1] = 200.0 * (b - a * a);
            Ok((1.0 - a).powi(2) + 100.0 * (b - a * a).powi(2))
        }
        fn bounds(&self) -> (&[f64], &[f64]) {
            (&self.lo, &self.hi)
        }
    }

    fn settings() -> RunSettings {
        RunSettings {
            max_iters: 200,
            stall_resumes: 0,
            relative_cost_tolerance: 0.0,
        }
    }

    #[test]
    fn failed_steps_are_shortened_and_the_run_goes_on() {
        // the first step from (25, −20) leaves |θ| < 30 for the ill-scaled
        // bowl: the line search shortens it
        let mut h = Harness::new(Bowl::unbounded(vec![1.5, 40.0], 30.0));
        let p = h
            .run_start(vec![25.0, -20.0], &settings())
            .unwrap()
            .unwrap();
        assert!(p.value < 1e-10, "{p:?}");
        for v in &p.theta {
            assert!((v - 1.0).abs() < 1e-5, "{p:?}");
        }
    }

    #[test]
    fn minimises_rosenbrock() {
        let mut h = Harness::new(Rosenbrock {
            lo: vec![f64::NEG_INFINITY; 2],
            hi: vec![f64::INFINITY; 2],
        });
        let p = h.run_start(vec![-1.2, 1.0], &settings()).unwrap().unwrap();
        assert!(
            (p.theta[0] - 1.0).abs() < 1e-4 && (p.theta[1] - 1.0).abs() < 1e-4,
            "{p:?}"
        );
        // L-BFGS takes some 35–60 evaluations here
        assert!(h.evaluations() < 120, "{}", h.evaluations());
    }

    /// Rosenbrock that sets `stop` at its `after`-th evaluation (as another
    /// thread would between two evaluations).
    struct StoppingRosenbrock<'a> {
        inner: Rosenbrock,
        stop: &'a AtomicBool,
        after: usize,
        evaluations: usize,
    }

    impl Objective for StoppingRosenbrock<'_> {
        fn eval(&mut self, th: &[f64], g: &mut [f64]) -> Result<f64, EvalFailure> {
            self.evaluations += 1;
            if self.evaluations == self.after {
                self.stop.store(true, Ordering::Relaxed);
            }
            self.inner.eval(th, g)
        }
        fn bounds(&self) -> (&[f64], &[f64]) {
            self.inner.bounds()
        }
    }

    /// A set stop flag ends the start with `Interrupted` before the next
    /// evaluation, wherever the optimiser is (start point, iteration, line
    /// search), and a harness stopped before it starts evaluates nothing.
    #[test]
    fn a_set_stop_flag_ends_the_start_at_the_next_evaluation() {
        for after in [1, 2, 7, 20] {
            let stop = AtomicBool::new(false);
            let objective = StoppingRosenbrock {
                inner: Rosenbrock {
                    lo: vec![f64::NEG_INFINITY; 2],
                    hi: vec![f64::INFINITY; 2],
                },
                stop: &stop,
                after,
                evaluations: 0,
            };
            let mut h = Harness::new(objective).with_stop(&stop);
            let r = h.run_start(vec![-1.2, 1.0], &settings());
            assert_eq!(r, Err(Error::Interrupted), "after {after}");
            assert_eq!(h.objective().evaluations, after);
        }
        let stop = AtomicBool::new(true);
        let mut h = Harness::new(Rosenbrock {
            lo: vec![f64::NEG_INFINITY; 2],
            hi: vec![f64::INFINITY; 2],
        })
        .with_stop(&stop);
        assert_eq!(
            h.run_start(vec![0.0, 0.0], &settings()),
            Err(Error::Interrupted)
        );
        assert_eq!(h.evaluations(), 0);
    }

    /// With the optimum outside the box, the answer is the KKT point on the
    /// boundary, reached in about as many evaluations as the unbounded fit.
    #[test]
    fn bounds_hold_without_extra_evaluations() {
        // unbounded minimum at (1, 1, 1); box θ_0 ≤ −2, θ_2 ≥ 3
        let c = vec![1.0, 3.0, 0.5];
        let mut free = Harness::new(Bowl::unbounded(c.clone(), 1e9));
        free.run_start(vec![-3.0, 0.0, 4.0], &settings())
            .unwrap()
            .unwrap();
        let mut boxed = Harness::new(Bowl {
            c,
            limit: 1e9,
            lo: vec![f64::NEG_INFINITY, f64::NEG_INFINITY, 3.0],
            hi: vec![-2.0, f64::INFINITY, f64::INFINITY],
        });
        let p = boxed
            .run_start(vec![-3.0, 0.0, 4.0], &settings())
            .unwrap()
            .unwrap();
        assert_eq!(p.theta[0], -2.0);
        assert_eq!(p.theta[2], 3.0);
        assert!((p.theta[1] - 1.0).abs() < 1e-6, "{p:?}");
        assert!(
            boxed.evaluations() <= 2 * free.evaluations(),
            "{} against {}",
            boxed.evaluations(),
            free.evaluations()
        );
        // a bounded Rosenbrock: minimum on b ≤ 0.5 is the KKT point where
        // ∂f/∂a = 0 with b = 0.5 (a ≈ 0.7057), and ∂f/∂b < 0 there
        let mut h = Harness::new(Rosenbrock {
            lo: vec![f64::NEG_INFINITY; 2],
            hi: vec![f64::INFINITY, 0.5],
        });
        let p = h.run_start(vec![-1.2, 0.3], &settings()).unwrap().unwrap();
        let mut g = [0.0; 2];
        Rosenbrock {
            lo: vec![],
            hi: vec![],
        }
        .eval(&p.theta, &mut g)
        .unwrap();
        assert_eq!(p.theta[1], 0.5);
        assert!(g[0].abs() < 1e-5 && g[1] < 0.0, "{p:?} {g:?}");
    }

    #[test]
    fn a_failing_start_point_gives_no_point_and_a_typed_error() {
        let mut h = Harness::new(Bowl::unbounded(vec![1.0], 1.0));
        assert_eq!(h.run_start(vec![5.0], &settings()).unwrap(), None);
        let e =
            multi_start(&mut h, 2, &settings(), |_, _| Ok(StartPlan::at(vec![5.0]))).unwrap_err();
        assert!(matches!(e, Error::Gp(GpError::Optimisation(_))), "{e}");
        assert_eq!(h.last_failure(), Some(EvalFailure::OutOfRange));
    }

    #[test]
    fn candidates_compete_with_the_runs() {
        let mut h = Harness::new(Bowl::unbounded(vec![1.5], 100.0));
        let exact = Point {
            theta: vec![1.0],
            value: 0.0,
        };
        let p = multi_start(&mut h, 1, &settings(), |_, _| {
            Ok(StartPlan {
                theta: vec![3.0],
                candidates: vec![exact.clone()],
            })
        })
        .unwrap();
        assert_eq!(p, exact);
    }
}
