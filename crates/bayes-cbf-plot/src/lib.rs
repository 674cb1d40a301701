//! # bayes-cbf-plot
//!
//! Figures of closed-loop runs (paper, Figs. 6–8, the vehicle animation and
//! the mean-against-Bayes comparison) and of the experiments (Figs. 1, 2, 4,
//! 5 and the calibration plot), rendered headless to PNG and GIF with
//! plotters from the typed results of [`bayes_cbf_scenario`]. Nothing here
//! computes a result: it draws them.

#![warn(missing_docs)]

pub mod experiments;
pub mod plot;
pub mod scenario;

pub use bayes_cbf_scenario::error::{Context, Error, Result};
pub use bayes_cbf_scenario::{bail, err};
pub use experiments::experiment_figures;
pub use scenario::{comparison_figure, write_figures};
