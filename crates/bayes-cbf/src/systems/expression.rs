//! Systems written as expressions (interfaces.md, "Expressions").

use super::ControlAffine;
use crate::error::InputError;
use crate::expr::{real_parts, Expr, Failure, Names};
use num_dual::DualNum;

/// A control-affine system `ẋ = f(x) + g(x)u` whose `f` and `g` are
/// expressions over named states and parameters ([`crate::expr`]).
///
/// Jacobians come from the same dual-number passes as for systems written
/// in Rust, so they are exact. An evaluation that is not finite is kept and
/// reported by [`ControlAffine::take_error`], naming the entry (`f[1]`) and
/// the state.
///
/// ```
/// use bayes_cbf::systems::{ControlAffine, ExpressionSystem, DynSystem};
/// let pendulum = ExpressionSystem::new(
///     &["theta", "omega"], &["u"], &[("m", 1.0), ("l", 1.0), ("g", 10.0)],
///     &["omega", "-g/l*sin(theta)"], &[vec!["0"], vec!["1/(m*l^2)"]], &["theta"],
/// ).unwrap();
/// let mut f = [0.0; 4]; // vec F = [f; g], column-major n × (1+m)
/// pendulum.eval_f64(&[0.5, 0.0], &mut f);
/// assert!((f[1] + 10.0 * 0.5f64.sin()).abs() < 1e-15 && f[3] == 1.0);
/// ```
#[derive(Debug)]
pub struct ExpressionSystem {
    state: Vec<String>,
    control: Vec<String>,
    /// `vec F` entries, column-major `n × (1+m)`: `f` then each column of `g`.
    entries: Vec<Expr>,
    angles: Vec<usize>,
    failure: Failure,
}

impl Clone for ExpressionSystem {
    fn clone(&self) -> Self {
        Self {
            state: self.state.clone(),
            control: self.control.clone(),
            entries: self.entries.clone(),
            angles: self.angles.clone(),
            failure: Failure::default(),
        }
    }
}

impl ExpressionSystem {
    /// Parses `f` (`n` expressions) and `g` (`n` rows of `m` expressions)
    /// over the states `state` and the parameters `params`; `angles` names
    /// the states wrapped to `[-π, π)`. Control names may not appear in `f`
    /// or `g` (the system is control-affine: `g`'s columns multiply them).
    pub fn new<S: AsRef<str>>(
        state: &[S],
        control: &[S],
        params: &[(S, f64)],
        f: &[S],
        g: &[Vec<S>],
        angles: &[S],
    ) -> Result<Self, InputError> {
        let (n, m) = (state.len(), control.len());
        let mut names = Names::states(state)?;
        if m == 0 {
            return Err(InputError::invalid(
                "control",
                0.0,
                "at least one control is needed",
            ));
        }
        for c in control {
            names.reserve(
                c.as_ref(),
                "f and g are functions of the state; the controls enter as ẋ = f + g u",
            )?;
        }
        for (p, v) in params {
            names.add_param(p.as_ref(), *v)?;
        }
        if f.len() != n {
            return Err(InputError::shape(
                "f",
                format!("{n} expressions (one per state)"),
                f.len(),
            ));
        }
        if g.len() != n {
            return Err(InputError::shape(
                "g",
                format!("{n} rows (one per state)"),
                g.len(),
            ));
        }
        let mut entries = Vec::with_capacity(n * (1 + m));
        for (i, e) in f.iter().enumerate() {
            entries.push(Expr::parse(&format!("f[{i}]"), e.as_ref(), &names)?);
        }
        for (i, row) in g.iter().enumerate() {
            if row.len() != m {
                return Err(InputError::shape(
                    &format!("g[{i}]"),
                    format!("{m} expressions (one per control)"),
                    row.len(),
                ));
            }
        }
        for c in 0..m {
            for (i, row) in g.iter().enumerate() {
                entries.push(Expr::parse(
                    &format!("g[{i}][{c}]"),
                    row[c].as_ref(),
                    &names,
                )?);
            }
        }
        names.check_params_used()?;
        let mut idx = Vec::new();
        for a in angles {
            let i = state
                .iter()
                .position(|s| s.as_ref() == a.as_ref())
                .ok_or_else(|| InputError::Invalid {
                    field: "angles".into(),
                    value: a.as_ref().to_string(),
                    reason: "not a state name".into(),
                })?;
            if !idx.contains(&i) {
                idx.push(i);
            }
        }
        idx.sort_unstable();
        Ok(Self {
            state: state.iter().map(|s| s.as_ref().to_string()).collect(),
            control: control.iter().map(|s| s.as_ref().to_string()).collect(),
            entries,
            angles: idx,
            failure: Failure::default(),
        })
    }

    /// State names.
    pub fn state_names(&self) -> &[String] {
        &self.state
    }

    /// Control names.
    pub fn control_names(&self) -> &[String] {
        &self.control
    }
}

impl ControlAffine for ExpressionSystem {
    fn state_dim(&self) -> usize {
        self.state.len()
    }
    fn control_dim(&self) -> usize {
        self.control.len()
    }
    fn dynamics<D: DualNum<Primitive = f64> + Copy>(&self, x: &[D], out: &mut [D]) {
        let n = self.state.len();
        for (r, (e, o)) in self.entries.iter().zip(out.iter_mut()).enumerate() {
            *o = e.eval(x);
            if !o.re().is_finite() {
                let v = o.re();
                self.failure.record(|| {
                    let (i, c) = (r % n, r / n);
                    let entry = if c == 0 {
                        format!("f[{i}]")
                    } else {
                        format!("g[{i}][{}]", c - 1)
                    };
                    format!(
                        "{entry} = {v} at state {:?} ({entry} = \"{}\")",
                        real_parts(x),
                        e.text()
                    )
                });
            }
        }
    }
    fn angle_indices(&self) -> &[usize] {
        &self.angles
    }
    fn take_error(&self) -> Option<String> {
        self.failure.take()
    }
}
