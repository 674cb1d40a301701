//! Figures of the built-in experiments.

pub mod ackermann_triggering;
pub mod calibration;
pub mod covariance_shapes;
pub mod pendulum_learning;
pub mod speed_test;

use crate::Result;
use bayes_cbf_scenario::experiments::ExperimentResult;
use std::path::{Path, PathBuf};

/// Writes the figures of an experiment's result into `dir`; returns the
/// files written (`soak` has none).
pub fn experiment_figures(r: &ExperimentResult, dir: &Path) -> Result<Vec<PathBuf>> {
    match r {
        ExperimentResult::PendulumLearning(r) => pendulum_learning::figures(r, dir),
        ExperimentResult::SpeedTest(r) => speed_test::figures(r, dir),
        ExperimentResult::CovarianceShapes(r) => covariance_shapes::figures(r, dir),
        ExperimentResult::AckermannTriggering(r) => ackermann_triggering::figures(r, dir),
        ExperimentResult::Calibration(r) => calibration::figures(r, dir),
        ExperimentResult::Soak(_) => Ok(Vec::new()),
    }
}
