//! The compiled module `bayes_cbf._core` of the Python package `bayes_cbf`.
//!
//! A thin wrapper: numpy arrays in and out, arguments converted by name
//! (a wrong type or value is an `InputError` naming the argument), the
//! library's errors as typed exceptions (`InputError`, a `ValueError` naming
//! the field, and `NumericalError`), the GIL released during fits, runs and
//! filter steps. Every computation is the core or scenario crate's.

mod args;
mod convert;
mod interrupt;
mod models;
mod safety;
mod scenarios;
mod sweeps;
mod warnings;

use pyo3::prelude::*;

/// `bayes_cbf._core`: see the package `bayes_cbf`.
#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    warnings::install();
    m.add("InputError", py.get_type::<convert::InputError>())?;
    m.add("NumericalError", py.get_type::<convert::NumericalError>())?;
    m.add_class::<models::PyMvgp>()?;
    m.add_class::<models::PyCogp>()?;
    m.add_class::<safety::PyBarrier>()?;
    m.add_class::<safety::PyClf>()?;
    m.add_class::<safety::PyFilterResult>()?;
    m.add_class::<safety::PySafetyFilter>()?;
    m.add_function(wrap_pyfunction!(safety::moments, m)?)?;
    m.add_function(wrap_pyfunction!(scenarios::run_scenario, m)?)?;
    m.add_function(wrap_pyfunction!(scenarios::list_scenarios, m)?)?;
    for f in [
        wrap_pyfunction!(sweeps::check_scenario, m)?,
        wrap_pyfunction!(scenarios::override_sets, m)?,
        wrap_pyfunction!(sweeps::sweep_meta, m)?,
        wrap_pyfunction!(sweeps::sweep_shard, m)?,
        wrap_pyfunction!(sweeps::sweep_merge, m)?,
        wrap_pyfunction!(sweeps::calibration_shard, m)?,
        wrap_pyfunction!(sweeps::calibration_check, m)?,
        wrap_pyfunction!(sweeps::calibration_merge, m)?,
    ] {
        m.add_function(f)?;
    }
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
