//! # bayes-cbf-scenario
//!
//! Everything around the core library [`bayes_cbf`] that a user needs
//! without the command line: the file formats (model, barrier, prior mean,
//! input map, CSV data), scenario files in TOML with `key=value` overrides,
//! the built-in scenarios, closed-loop runs returning a typed
//! [`scenario::RunSummary`], and the paper's experiments returning typed
//! results. Nothing here prints or plots; the `bayes-cbf` binary, the
//! figures crate and the Python package build on it.
//!
//! ## Error policy
//! Every failure caused by input (a file, a field, a value) or by the
//! numerics is an [`Error`] whose message is one line naming the field;
//! nothing here panics on user input.

#![warn(missing_docs)]
// Index loops mirror the subscripts of the maths in the docs.
#![allow(clippy::needless_range_loop)]

pub mod bench;
pub mod error;
pub mod exact;
pub mod experiments;
pub mod fitting;
pub mod formats;
pub mod io;
pub mod queries;
pub mod scenario;
pub mod stats;
pub mod sweep;
pub mod workloads;

#[cfg(test)]
mod fuzz_tests;

pub use error::{Context, Error, Result};

/// Issues `message` at `flag` ([`bayes_cbf::warnings`]): shown the first
/// time `flag` is seen in the current scope (a run, a sweep, an
/// experiment; a sweep builds its scenario once per seed), and kept in the
/// run's record.
pub(crate) fn warn_once(flag: &bayes_cbf::warnings::WarnOnce, message: String) {
    flag.issue(|| message);
}
pub use formats::{barrier_file, csv_data, input_map_spec, model_file, params, parse, prior_spec};

/// The README's Rust examples, compiled and run as doctests.
#[cfg(doctest)]
#[doc = include_str!("../../../README.md")]
pub struct ReadmeDoctests;
