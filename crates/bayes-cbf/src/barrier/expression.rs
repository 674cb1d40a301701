//! Barriers and Lyapunov functions written as expressions
//! (interfaces.md, "Expressions").

use super::{validate_gains, Barrier, Lyapunov};
use crate::error::{check_nonnegative, InputError};
use crate::expr::{real_parts, Expr, Failure, Names};
use num_dual::DualNum;

/// Variables `state` and parameters `params` of an expression.
fn names<S: AsRef<str>>(state: &[S], params: &[(S, f64)]) -> Result<Names, InputError> {
    let mut names = Names::states(state)?;
    for (p, v) in params {
        names.add_param(p.as_ref(), *v)?;
    }
    Ok(names)
}

/// A barrier `h(x)` written as an expression over named states and
/// parameters; `∇h` and `∇²h` are exact (dual numbers).
///
/// ```
/// use bayes_cbf::barrier::{DynBarrier, ExpressionBarrier};
/// let disc = ExpressionBarrier::new(
///     &["x", "y", "theta"], &[("r", 0.5)], "(x - 1)^2 + (y + 1)^2 - r^2", 1, vec![5.0],
/// ).unwrap();
/// let mut grad = [0.0; 3];
/// let mut scratch = [num_dual::Dual64::from(0.0); 3];
/// let h = disc.gradient(&[0.0, 0.0, 0.3], &mut grad, &mut scratch);
/// assert_eq!((h, grad), (1.75, [-2.0, 2.0, 0.0]));
/// ```
#[derive(Debug)]
pub struct ExpressionBarrier {
    state: Vec<String>,
    h: Expr,
    relative_degree: usize,
    gains: Vec<f64>,
    name: String,
    failure: Failure,
}

impl Clone for ExpressionBarrier {
    fn clone(&self) -> Self {
        Self {
            state: self.state.clone(),
            h: self.h.clone(),
            relative_degree: self.relative_degree,
            gains: self.gains.clone(),
            name: self.name.clone(),
            failure: Failure::default(),
        }
    }
}

impl ExpressionBarrier {
    /// Parses `h` over `state` and `params`; `gains` are `[α]` for relative
    /// degree 1 and `k_α` (real negative roots) for relative degree ≥ 2
    /// ([`validate_gains`]).
    pub fn new<S: AsRef<str>>(
        state: &[S],
        params: &[(S, f64)],
        h: &str,
        relative_degree: usize,
        gains: Vec<f64>,
    ) -> Result<Self, InputError> {
        super::check_state_dim("state", state.len())?;
        let names = names(state, params)?;
        let text = h.trim().to_string();
        let h = Expr::parse("h", h, &names)?;
        names.check_params_used()?;
        validate_gains(relative_degree, &gains)?;
        Ok(Self {
            state: names.vars().to_vec(),
            h,
            relative_degree,
            gains,
            // reports and warnings tell expression barriers apart by their h
            name: text,
            failure: Failure::default(),
        })
    }

    /// The same barrier reported under `name`.
    pub fn with_name(mut self, name: &str) -> Self {
        self.name = name.to_string();
        self
    }

    /// State names.
    pub fn state_names(&self) -> &[String] {
        &self.state
    }

    /// The expression of `h`.
    pub fn expression(&self) -> &str {
        self.h.text()
    }

    /// The functions with kinks `h` applies to the state (`abs`, `min`,
    /// `max`). A barrier must be differentiable (`C¹` at relative degree
    /// 1, `Cʳ` at `r`): where one of these switches, the condition
    /// constrains the gradient of one side only, and the other side can
    /// cross zero although every step meets the condition (`min(1 − x,
    /// 1 − y)` escapes its corner). Write each side as its own barrier.
    pub fn kinks(&self) -> Vec<&'static str> {
        self.h.kinks()
    }
}

impl Barrier for ExpressionBarrier {
    fn state_dim(&self) -> usize {
        self.state.len()
    }
    fn h<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D]) -> D {
        let v = self.h.eval(x);
        if !v.re().is_finite() {
            self.failure.record(|| {
                let text = self.h.text();
                let shown = if self.name == text.trim() {
                    String::new()
                } else {
                    format!(" (h = \"{text}\")")
                };
                format!(
                    "h of barrier '{}' = {} at state {:?}{shown}",
                    self.name,
                    v.re(),
                    real_parts(x)
                )
            });
        }
        v
    }
    order_and_gains!();
    fn name(&self) -> &str {
        &self.name
    }
    fn take_error(&self) -> Option<String> {
        self.failure.take()
    }
}

/// A control Lyapunov function `V(x, x_d)` written as an expression over
/// the state names and the reference names `<state>_d`
/// (`V = "(x - x_d)^2 + (y - y_d)^2"`).
#[derive(Debug, Clone)]
pub struct ExpressionClf {
    n: usize,
    v: Expr,
    gamma: f64,
}

impl ExpressionClf {
    /// Parses `v` over `state`, the references `<state>_d` and `params`;
    /// `gamma` is the decay rate `γ ≥ 0`.
    pub fn new<S: AsRef<str>>(
        state: &[S],
        params: &[(S, f64)],
        v: &str,
        gamma: f64,
    ) -> Result<Self, InputError> {
        let reference: Vec<String> = state.iter().map(|s| format!("{}_d", s.as_ref())).collect();
        let mut names = names(state, &[])?;
        for (r, s) in reference.iter().zip(state) {
            if state.iter().any(|t| t.as_ref() == r) {
                return Err(InputError::Invalid {
                    field: "state".into(),
                    value: r.clone(),
                    reason: format!(
                        "a state named '{r}' clashes with the reference of state '{}' in V (the reference names are the state names with _d): rename one of them",
                        s.as_ref()
                    ),
                });
            }
            names.add_var(r)?;
        }
        for (p, value) in params {
            names.add_param(p.as_ref(), *value)?;
        }
        check_nonnegative("gamma", gamma)?;
        let v = Expr::parse("V", v, &names)?;
        names.check_params_used()?;
        Ok(Self {
            n: state.len(),
            v,
            gamma,
        })
    }
}

impl Lyapunov for ExpressionClf {
    fn state_dim(&self) -> usize {
        self.n
    }
    fn v<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D], xd: &[D]) -> D {
        self.v.eval2(x, xd)
    }
    fn gamma(&self) -> f64 {
        self.gamma
    }
}
