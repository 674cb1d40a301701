//! The error of this crate: bad files, fields and values, failures of the
//! core library, and I/O, each with the context that locates it.
//!
//! Every message is one line naming the field or value at fault;
//! [`Error::Context`] prefixes the place (`scenario 'x.toml': ...`), so
//! `to_string()` reads like a path to the problem.

use std::fmt::Display;

/// An error of the scenario layer.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// Bad input: a file, field or value; the message names it.
    #[error("{0}")]
    Input(String),
    /// The core library rejected an input or failed numerically.
    #[error(transparent)]
    Core(#[from] bayes_cbf::Error),
    /// Reading or writing a file failed.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// An error with the place where it happened (the message includes the
    /// inner error, so it is not reported again as a source).
    #[error("{context}: {inner}")]
    Context {
        /// Where: a file, a field, a run.
        context: String,
        /// What went wrong there.
        inner: Box<Error>,
    },
}

impl Error {
    /// Adds `context` in front of this error.
    pub fn context(self, context: impl Display) -> Self {
        Error::Context {
            context: context.to_string(),
            inner: Box::new(self),
        }
    }

    /// The innermost error, below every [`Error::Context`].
    pub fn root(&self) -> &Error {
        match self {
            Error::Context { inner, .. } => inner.root(),
            e => e,
        }
    }
}

impl From<bayes_cbf::InputError> for Error {
    fn from(e: bayes_cbf::InputError) -> Self {
        Error::Core(e.into())
    }
}

impl From<bayes_cbf::GpError> for Error {
    fn from(e: bayes_cbf::GpError) -> Self {
        Error::Core(e.into())
    }
}

impl From<serde_json::Error> for Error {
    fn from(e: serde_json::Error) -> Self {
        Error::Input(e.to_string().replace('\n', " "))
    }
}

impl From<toml::ser::Error> for Error {
    fn from(e: toml::ser::Error) -> Self {
        Error::Input(e.to_string().replace('\n', " "))
    }
}

/// `Result` with this crate's [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Context for results and options: `.context("reading 'x.csv'")`.
pub trait Context<T> {
    /// Prefixes the error with `context`.
    fn context<C: Display>(self, context: C) -> Result<T>;
    /// Prefixes the error with the context `f` builds (only on failure).
    fn with_context<C: Display, F: FnOnce() -> C>(self, f: F) -> Result<T>;
}

impl<T, E: Into<Error>> Context<T> for std::result::Result<T, E> {
    fn context<C: Display>(self, context: C) -> Result<T> {
        self.map_err(|e| e.into().context(context))
    }
    fn with_context<C: Display, F: FnOnce() -> C>(self, f: F) -> Result<T> {
        self.map_err(|e| e.into().context(f()))
    }
}

impl<T> Context<T> for Option<T> {
    fn context<C: Display>(self, context: C) -> Result<T> {
        self.ok_or_else(|| Error::Input(context.to_string()))
    }
    fn with_context<C: Display, F: FnOnce() -> C>(self, f: F) -> Result<T> {
        self.ok_or_else(|| Error::Input(f().to_string()))
    }
}

/// An [`Error::Input`] from a format string.
#[macro_export]
macro_rules! err {
    ($($t:tt)*) => { $crate::error::Error::Input(format!($($t)*)) };
}

/// Returns early with an [`Error::Input`] from a format string.
#[macro_export]
macro_rules! bail {
    ($($t:tt)*) => { return Err($crate::err!($($t)*).into()) };
}

/// Checks that `v` has `len` entries, all finite, naming `field` and what
/// `len` is (`"the state dimension"`, `"the model's control_dim"`, ...).
pub fn check_vector(field: &str, v: &[f64], len: usize, what: &str) -> Result<()> {
    if v.len() != len {
        bail!("{field} has {} entries, expected {len} ({what})", v.len());
    }
    if let Some(i) = v.iter().position(|x| !x.is_finite()) {
        bail!("{field}[{i}] = {} is not finite", v[i]);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vectors_are_checked_for_length_then_finiteness() {
        let short = check_vector("start", &[0.0], 2, "the state dimension").unwrap_err();
        assert_eq!(
            short.to_string(),
            "start has 1 entries, expected 2 (the state dimension)"
        );
        let nan = check_vector("x", &[0.0, f64::NAN], 2, "state_dim").unwrap_err();
        assert_eq!(nan.to_string(), "x[1] = NaN is not finite");
        assert!(check_vector("x", &[0.0, 1.0], 2, "state_dim").is_ok());
    }

    #[test]
    fn context_reads_as_a_path() {
        let e: Result<()> = Err(err!("x[1] = nan is not finite"));
        let e = e.context("data 'a.csv'").unwrap_err().context("fit");
        assert_eq!(e.to_string(), "fit: data 'a.csv': x[1] = nan is not finite");
        assert!(matches!(e.root(), Error::Input(_)));
        let none: Option<u8> = None;
        assert_eq!(none.context("missing").unwrap_err().to_string(), "missing");
    }
}
