//! Error types, one enum per layer, joined into [`Error`](enum@Error) with `#[from]`.

use thiserror::Error;

/// Bad input from a user: wrong shapes, non-finite values, out-of-range
/// settings. Every variant names the offending field.
#[derive(Debug, Clone, Error, PartialEq)]
#[non_exhaustive]
pub enum InputError {
    /// A value outside its allowed range.
    #[error("invalid {field} = {value}: {reason}")]
    Invalid {
        /// Field name, e.g. `noise_sigma` or `x[3][1]`.
        field: String,
        /// The offending value, formatted.
        value: String,
        /// What was expected.
        reason: String,
    },
    /// A vector or matrix of the wrong size.
    #[error("wrong shape of {field}: expected {expected}, got {got}")]
    Shape {
        /// Field name.
        field: String,
        /// Expected shape.
        expected: String,
        /// Actual shape.
        got: String,
    },
    /// A user function (a callback barrier's `h`, `∇h` or `∇²h`) failed or
    /// returned a non-finite value; the message names the function.
    #[error("{0}")]
    Evaluation(String),
    /// An expression that does not parse or names what it may not
    /// ([`crate::expr`]); a syntax error gives its 1-based column.
    #[error("{field}{}: {message}", column.map(|c| format!(", column {c}")).unwrap_or_default())]
    Expression {
        /// The field holding the expression (`f[1]`, `barriers[0].h`).
        field: String,
        /// Column of a syntax error.
        column: Option<usize>,
        /// What is wrong.
        message: String,
    },
    /// A matrix that must be symmetric positive definite is not.
    #[error("{field} is not symmetric positive definite: {reason}")]
    NotPositiveDefinite {
        /// Field name (`A`, `B`, ...).
        field: String,
        /// Details.
        reason: String,
    },
}

impl InputError {
    /// `Invalid` with a numeric value.
    pub fn invalid(field: &str, value: f64, reason: &str) -> Self {
        Self::invalid_shown(field, number(value), reason)
    }

    /// `Invalid` with a value shown as `value` (a list, a pair of settings);
    /// a value longer than 300 characters is cut there, with its length.
    pub fn invalid_shown(field: &str, value: impl std::fmt::Display, reason: &str) -> Self {
        Self::Invalid {
            field: field.to_string(),
            value: shortened(value.to_string()),
            reason: reason.to_string(),
        }
    }

    /// The same error with its field read inside `prefix` (`trigger.` makes
    /// `grid` `trigger.grid`): settings checked on their own and as part
    /// of larger ones name the field as the user wrote it.
    pub fn within(mut self, prefix: &str) -> Self {
        match &mut self {
            Self::Invalid { field, .. }
            | Self::Shape { field, .. }
            | Self::Expression { field, .. }
            | Self::NotPositiveDefinite { field, .. } => field.insert_str(0, prefix),
            Self::Evaluation(_) => {}
        }
        self
    }

    /// `Shape` error.
    pub fn shape(field: &str, expected: impl ToString, got: impl ToString) -> Self {
        Self::Shape {
            field: field.to_string(),
            expected: expected.to_string(),
            got: got.to_string(),
        }
    }
}

/// How many characters of a value or a quoted message an error shows.
pub const SHOWN_CHARS: usize = 300;

/// `text` as an error shows it: whole up to [`SHOWN_CHARS`] characters,
/// else cut there and followed by its length (a relative degree of 10⁶
/// would otherwise be a message of megabytes).
pub fn shortened(mut text: String) -> String {
    if let Some((cut, _)) = text.char_indices().nth(SHOWN_CHARS) {
        let total = text.chars().count();
        text.truncate(cut);
        text.push_str(&format!(" … ({total} characters)"));
    }
    text
}

/// `value` as a message shows it: plain decimals for everyday magnitudes,
/// scientific notation for the others (`1e-300`, not 300 digits).
pub fn number(value: f64) -> String {
    let a = value.abs();
    if a == 0.0 || !a.is_finite() || (1e-4..1e16).contains(&a) {
        format!("{value}")
    } else {
        format!("{value:e}")
    }
}

/// An empty vector with room for `n` entries, or an error naming `field`
/// when that memory cannot be had: a count too large to run (`steps`,
/// `samples`, `seeds`) is refused instead of aborting the process.
pub fn reserve<T>(field: &str, n: usize) -> Result<Vec<T>, InputError> {
    let mut v = Vec::new();
    v.try_reserve_exact(n).map_err(|_| {
        InputError::invalid_shown(
            field,
            n,
            "too large: the memory for one entry each cannot be reserved",
        )
    })?;
    Ok(v)
}

/// A state shown in a message: whole up to 8 entries, else its first 6,
/// its last and its length (a state of a thousand coordinates would fill
/// the message).
pub struct Brief<'a>(pub &'a [f64]);

impl std::fmt::Display for Brief<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.0 {
            x if x.len() <= 8 => write!(f, "{x:?}"),
            x => {
                let head: Vec<String> = x[..6].iter().map(|v| format!("{v:?}")).collect();
                let last = x[x.len() - 1];
                write!(
                    f,
                    "[{}, …, {last:?}] ({} entries)",
                    head.join(", "),
                    x.len()
                )
            }
        }
    }
}

/// Checks that every entry of `v` is finite, naming the first bad entry.
pub fn check_finite(field: &str, v: &[f64]) -> Result<(), InputError> {
    match v.iter().position(|x| !x.is_finite()) {
        None => Ok(()),
        Some(i) => Err(InputError::invalid(
            &format!("{field}[{i}]"),
            v[i],
            "must be finite",
        )),
    }
}

/// Checks that `field` has `len` entries where `expected` are needed.
pub fn check_len(field: &str, expected: usize, len: usize) -> Result<(), InputError> {
    if len == expected {
        Ok(())
    } else {
        Err(InputError::shape(field, expected, len))
    }
}

/// Checks that the scalar `v` is finite, naming `field`.
pub fn check_finite_scalar(field: &str, v: f64) -> Result<(), InputError> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(InputError::invalid(field, v, "must be finite"))
    }
}

/// Checks that the state index `i` is below the state dimension `n`,
/// naming `field`.
pub fn check_index(field: &str, i: usize, n: usize) -> Result<(), InputError> {
    if i < n {
        Ok(())
    } else {
        Err(InputError::invalid_shown(
            field,
            i,
            &format!("index must be < state dimension {n}"),
        ))
    }
}

/// Checks that `v` is finite and `> 0`, naming `field`.
pub fn check_positive(field: &str, v: f64) -> Result<(), InputError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(InputError::invalid(field, v, "must be finite and > 0"))
    }
}

/// Checks that `v` is finite and `≥ 0`, naming `field`.
pub fn check_nonnegative(field: &str, v: f64) -> Result<(), InputError> {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(InputError::invalid(field, v, "must be finite and ≥ 0"))
    }
}

/// Numerical failures of Gaussian-process computations.
#[derive(Debug, Clone, Error, PartialEq)]
#[non_exhaustive]
pub enum GpError {
    /// The Gram matrix `K + σ²I` could not be factorised even after the
    /// bounded jitter escalation.
    #[error("Gram matrix (k = {size}) is not positive definite even with jitter {max_jitter:e} (relative to its mean diagonal); data may contain duplicate points with zero noise")]
    IllConditioned {
        /// Size `k` of the Gram matrix.
        size: usize,
        /// Largest relative jitter tried.
        max_jitter: f64,
    },
    /// The Gram matrix has entries beyond f64's range: its scale (kernel
    /// variance times `u̲ᵀBu̲`, plus the noise) overflows.
    #[error("Gram matrix (k = {size}) has a diagonal entry of {diagonal:e}: its scale (the kernel variance times u̲ᵀBu̲ of the controls, plus σ²) is beyond the range of f64; scale the kernel variance, B or the controls down")]
    Overflow {
        /// Size `k` of the Gram matrix.
        size: usize,
        /// The first non-finite diagonal entry.
        diagonal: f64,
    },
    /// Hyperparameter optimisation failed to produce a finite likelihood.
    #[error("hyperparameter optimisation failed: {0}")]
    Optimisation(String),
    /// The marginal likelihood cannot be evaluated at the given parameter
    /// vector (the Gram matrix does not factorise, the value is not finite,
    /// or the decoded hyperparameters are rejected).
    #[error("the likelihood cannot be evaluated at these parameters: {0}")]
    NotEvaluable(String),
    /// An operation that needs data was called on an empty model.
    #[error("the model has no training data")]
    NoData,
}

/// Numerical failures of the safety filter.
#[derive(Debug, Clone, Error, PartialEq)]
#[non_exhaustive]
pub enum ControlError {
    /// The SOCP reported a solution that misses a barrier's condition by
    /// well beyond the solver's tolerance, also when solved again with that
    /// barrier's margin raised by twice the miss: the condition's covariance
    /// is too large for double precision to resolve its standard deviation
    /// at the control. A kernel variance far above the data's spread does
    /// this: 10¹⁶ for one step of `bayes-cbf control`; 10¹² stops 2 of 10
    /// seeds of the double integrator's learning run, whose Gram matrix it
    /// also ill-conditions (the others' steps end infeasible).
    #[error("barrier {barrier}: the solver's control misses the condition by {slack:.3e} (mean {mean:.3e}, std {std:.3e}), also when solved again with a margin; the condition's covariance (largest entry {scale:.1e}) is beyond what double precision resolves: check the model's kernel variance and noise")]
    Unresolved {
        /// Index of the barrier.
        barrier: usize,
        /// `E[C] − ζ − c·std` at the control.
        slack: f64,
        /// `E[C]` at the control.
        mean: f64,
        /// Standard deviation at the control.
        std: f64,
        /// Largest absolute entry of the condition's covariance.
        scale: f64,
    },
    /// A condition's variance at a control is not resolved: the rounding
    /// of the terms it is summed from (`u̲ᵀ Cov u̲` with entries far larger
    /// than the result) could be a tenth of it or more, so the value, at
    /// worst clamped to 0, says little. A kernel variance far above the
    /// data's spread does this (10¹³ and more for the model of the
    /// command-line tests, where the variance is 0.004).
    #[error("the condition's variance at u ({variance:.3e}) is not resolved: the rounding of the covariance's terms could be {rounding:.1e} (largest entry {scale:.1e}), a tenth of it or more; check the model's kernel variance and noise")]
    VarianceUnresolved {
        /// The computed `u̲ᵀ Cov u̲` (before clamping at 0).
        variance: f64,
        /// Bound on its rounding error.
        rounding: f64,
        /// Largest absolute entry of the covariance.
        scale: f64,
    },
}

/// Any error of this library.
#[derive(Debug, Clone, Error, PartialEq)]
#[non_exhaustive]
pub enum Error {
    /// Bad user input.
    #[error(transparent)]
    Input(#[from] InputError),
    /// Numerical failure in the GP layer.
    #[error(transparent)]
    Gp(#[from] GpError),
    /// Numerical failure in the safety filter.
    #[error(transparent)]
    Control(#[from] ControlError),
    /// A stop flag was set before the work finished: a fit
    /// ([`crate::gp::fit_until`]), which then leaves the model's
    /// hyperparameters as they were, or a closed-loop run
    /// ([`crate::sim::ClosedLoop::with_stop`]).
    #[error("interrupted: stopped before it finished")]
    Interrupted,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A short state is shown as Rust shows a slice; a long one by its
    /// first six entries, its last and its length.
    #[test]
    fn long_states_are_shown_briefly() {
        assert_eq!(Brief(&[0.5, -1.0]).to_string(), "[0.5, -1.0]");
        let x: Vec<f64> = (0..1000).map(f64::from).collect();
        assert_eq!(
            Brief(&x).to_string(),
            "[0.0, 1.0, 2.0, 3.0, 4.0, 5.0, …, 999.0] (1000 entries)"
        );
    }

    /// A value of a million characters is shown cut to 300, with its
    /// length; a short one whole; a cut never splits a character.
    #[test]
    fn long_values_are_cut_in_messages() {
        let long = "é".repeat(1_000_000);
        let text = InputError::invalid_shown("k", &long, "why").to_string();
        assert!(text.len() < 1000, "{} bytes", text.len());
        assert!(text.contains(&"é".repeat(300)) && text.contains("(1000000 characters)"));
        let short = InputError::invalid_shown("k", "[1, 2]", "why").to_string();
        assert!(
            short.contains("[1, 2]") && !short.contains("characters"),
            "{short}"
        );
    }

    #[test]
    fn scalar_checks_name_the_field_and_reject_nan_infinity_and_the_boundary() {
        for v in [1e-300, 1.0, 1e300] {
            assert_eq!(check_positive("a", v), Ok(()));
            assert_eq!(check_nonnegative("a", v), Ok(()));
        }
        assert_eq!(check_nonnegative("a", 0.0), Ok(()));
        for v in [0.0, -1.0, f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            let e = check_positive("p.q", v).unwrap_err();
            assert_eq!(e, InputError::invalid("p.q", v, "must be finite and > 0"));
        }
        for v in [-1e-300, f64::NAN, f64::INFINITY] {
            let e = check_nonnegative("r", v).unwrap_err();
            assert_eq!(e, InputError::invalid("r", v, "must be finite and ≥ 0"));
            assert!(e.to_string().contains('r'));
        }
    }
}
