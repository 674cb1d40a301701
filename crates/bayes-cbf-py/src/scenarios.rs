//! `run_scenario` and `list_scenarios`: the scenario crate's closed-loop
//! runs, the same as `bayes-cbf run`.

use crate::args;
use crate::convert::{input_err, json_of, scenario_err, to_numpy};
use bayes_cbf_scenario::scenario::{self, run_scenario_until, Column, Trajectory, BUILTIN};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

/// The `--set key=value` texts of the overrides dict `overrides` (dotted
/// keys to values; values finite numbers, strings, lists and dicts).
fn override_texts(overrides: Option<&Bound<'_, PyDict>>) -> PyResult<Vec<String>> {
    let Some(o) = overrides else {
        return Ok(Vec::new());
    };
    o.iter()
        .map(|(k, v)| {
            let key: String = k.extract().map_err(|_| {
                input_err("overrides: keys must be strings such as 'controller.probability'")
            })?;
            let field = format!("overrides['{key}']");
            let segment = |p: &str| {
                !p.is_empty()
                    && p.bytes()
                        .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
            };
            if !key.split('.').all(segment) {
                return Err(input_err(format!(
                    "{field}: not a key: dotted names and indices (letters, digits, '_', '-') \
                     such as 'controller.probability' or 'barriers.0.alpha'"
                )));
            }
            if v.is_none() {
                return Err(input_err(format!("{field}: None is not a value")));
            }
            if v.extract::<f64>().is_ok_and(|x| !x.is_finite()) {
                return Err(input_err(format!("{field} = {v}: must be a finite number")));
            }
            Ok(format!("{key}={}", json_of(&v, &field)?))
        })
        .collect()
}

/// The overrides dict `overrides` as `key=value` texts (`--set`), for
/// `bayes_cbf.sweep`.
#[pyfunction]
#[pyo3(signature = (overrides))]
pub fn override_sets(
    #[pyo3(from_py_with = args::overrides)] overrides: Option<Bound<'_, PyDict>>,
) -> PyResult<Vec<String>> {
    override_texts(overrides.as_ref())
}

/// Runs a scenario (a built-in name or a TOML file) and returns its
/// summary as a dict (the keys of `summary.json`) plus `"trajectory"`: a
/// dict of the columns of `trajectory.csv` (numpy arrays; NaN where the CSV
/// is empty; `status` an array of strings). `overrides` maps dotted keys to
/// values, as `--set key=value`. `seed` is from 0 to 2^63 − 1 (a scenario
/// file's integer).
#[pyfunction]
#[pyo3(signature = (name, seed=None, overrides=None))]
pub fn run_scenario<'py>(
    py: Python<'py>,
    #[pyo3(from_py_with = args::name)] name: args::ScenarioRef,
    #[pyo3(from_py_with = args::seed)] seed: Option<i64>,
    #[pyo3(from_py_with = args::overrides)] overrides: Option<Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyDict>> {
    let mut sets = override_texts(overrides.as_ref())?;
    if let Some(s) = seed {
        sets.push(format!("seed={s}"));
    }
    // Ctrl-C ends the run before its next step (KeyboardInterrupt)
    let (result, signal) =
        crate::interrupt::interruptible(py, |stop| -> bayes_cbf_scenario::Result<_> {
            let (sc, _) = scenario::load(&name.0, &sets)?;
            let out = run_scenario_until(&sc, |_, _| {}, stop.clone())?;
            let json = serde_json::to_string(&out.summary)?;
            Ok((Trajectory::of(&out), json))
        });
    let (output, summary_json) =
        crate::warnings::after(py, signal.map(|()| result))?.map_err(scenario_err)?;
    let summary = py
        .import("json")?
        .call_method1("loads", (summary_json,))?
        .cast_into::<PyDict>()?;
    let traj = PyDict::new(py);
    let numpy = py.import("numpy")?;
    for (name, col) in output.columns {
        match col {
            Column::Numbers(v) => {
                let len = v.len();
                traj.set_item(name, to_numpy(py, v, &[len])?)?
            }
            Column::Words(v) => {
                let words = numpy.call_method1("array", (PyList::new(py, v)?,))?;
                traj.set_item(name, words)?
            }
        }
    }
    summary.set_item("trajectory", traj)?;
    Ok(summary)
}

/// The built-in scenarios' names.
#[pyfunction]
pub fn list_scenarios() -> Vec<&'static str> {
    BUILTIN.iter().map(|(n, _)| *n).collect()
}
