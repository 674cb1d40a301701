//! Arguments from Python values. Every error is an [`InputError`] whose
//! message names the argument: a value of the wrong type (`noise_sigma:
//! expected a number, got str`) as much as a value out of range (`seed =
//! -1: must be ≥ 0`).
//!
//! [`FromArg`] converts by type; the functions at the end, one per
//! argument name, are the `#[pyo3(from_py_with = ...)]` of the arguments
//! so named.
//!
//! [`InputError`]: crate::convert::InputError

use crate::convert::{input_err, scenario_err, type_name, vector};
use bayes_cbf::gp::Rank;
use bayes_cbf_scenario::barrier_file::EdgeSpec;
use bayes_cbf_scenario::parse::parse_rank;
use pyo3::exceptions::PyOverflowError;
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::{PyBool, PyComplex, PyDict, PyFloat, PyString, PyTuple};
use pyo3::PyTypeInfo;
use std::collections::BTreeMap;
use std::path::PathBuf;

/// A Rust value of an argument, from the Python value `obj` of the
/// argument `field`.
pub trait FromArg<'a, 'py>: Sized {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self>;
}

/// The error of an argument `field` given `obj` where `what` was expected.
fn expected(obj: &Bound<'_, PyAny>, field: &str, what: &str) -> PyErr {
    input_err(format!("{field}: expected {what}, got {}", type_name(obj)))
}

/// Whether `obj` is a bool or a complex number (Python's or numpy's),
/// values that Python converts to numbers but a numeric argument refuses:
/// a bool is almost always a mistake, and a complex number would lose its
/// imaginary part.
fn not_real(obj: &Bound<'_, PyAny>) -> PyResult<bool> {
    static TYPES: PyOnceLock<Py<PyTuple>> = PyOnceLock::new();
    let py = obj.py();
    let types = TYPES.get_or_try_init(py, || -> PyResult<_> {
        let np = py.import("numpy")?;
        let types = [
            py.get_type::<PyBool>().into_any(),
            np.getattr("bool_")?,
            py.get_type::<PyComplex>().into_any(),
            np.getattr("complexfloating")?,
        ];
        Ok(PyTuple::new(py, types)?.unbind())
    })?;
    obj.is_instance(types.bind(py))
}

/// A number (a Python or numpy float or integer).
fn number(obj: &Bound<'_, PyAny>, field: &str) -> PyResult<f64> {
    if let Ok(f) = obj.cast::<PyFloat>() {
        return Ok(f.value());
    }
    if not_real(obj)? {
        return Err(expected(obj, field, "a number"));
    }
    obj.extract::<f64>().map_err(|e| {
        if e.is_instance_of::<PyOverflowError>(obj.py()) {
            input_err(format!(
                "{field}: too large for a float ({})",
                e.value(obj.py())
            ))
        } else {
            expected(obj, field, "a number")
        }
    })
}

/// The value of an integer (a Python or numpy integer, not a bool), an
/// integer beyond `i128` as `i128::MIN` or `i128::MAX`; `None` for any
/// other value.
fn integer(obj: &Bound<'_, PyAny>) -> PyResult<Option<i128>> {
    if not_real(obj)? {
        return Ok(None);
    }
    match obj.extract::<i128>() {
        Ok(v) => Ok(Some(v)),
        Err(e) if e.is_instance_of::<PyOverflowError>(obj.py()) => {
            let negative = obj.lt(0)?;
            Ok(Some(if negative { i128::MIN } else { i128::MAX }))
        }
        Err(_) => Ok(None),
    }
}

/// An integer type of counts, indices and seeds, from 0 to `MAX` (`i64`:
/// a seed a scenario file holds, an integer of TOML).
pub trait Count: TryFrom<i128> {
    const MAX: u128;
}

macro_rules! counts {
    ($($t:ty),*) => {$(
        impl Count for $t {
            const MAX: u128 = <$t>::MAX as u128;
        }
        impl<'a, 'py> FromArg<'a, 'py> for $t {
            fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
                count(obj, field)
            }
        }
    )*};
}
counts!(u64, usize, i64);

/// Counts that must be at least 1 (the library's own checks say so too).
const AT_LEAST_ONE: [&str; 4] = ["state_dim", "control_dim", "max_iters", "episodes"];

/// A non-negative integer (a count, an index, a seed) that fits `T`; at
/// least 1 for the fields of [`AT_LEAST_ONE`].
fn count<T: Count>(obj: &Bound<'_, PyAny>, field: &str) -> PyResult<T> {
    let v = integer(obj)?.ok_or_else(|| expected(obj, field, "an integer"))?;
    let least = i128::from(AT_LEAST_ONE.contains(&field));
    if v < least {
        return Err(input_err(format!("{field} = {obj}: must be ≥ {least}")));
    }
    T::try_from(v).map_err(|_| {
        let max = match T::MAX.checked_add(1) {
            Some(p) if p.is_power_of_two() => format!("2^{} − 1", p.trailing_zeros()),
            _ => T::MAX.to_string(),
        };
        input_err(format!("{field} = {obj}: too large (at most {max})"))
    })
}

impl<'a, 'py> FromArg<'a, 'py> for f64 {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
        number(obj, field)
    }
}

/// `True` or `False` (also numpy's).
impl<'a, 'py> FromArg<'a, 'py> for bool {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
        obj.extract()
            .map_err(|_| expected(obj, field, "True or False"))
    }
}

impl<'a, 'py> FromArg<'a, 'py> for &'a str {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
        obj.cast::<PyString>()
            .map_err(|_| expected(obj, field, "a string"))?
            .to_str()
    }
}

impl<'a, 'py> FromArg<'a, 'py> for String {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
        <&str>::from_arg(obj, field).map(str::to_owned)
    }
}

/// A file path: a string or an `os.PathLike`.
impl<'a, 'py> FromArg<'a, 'py> for PathBuf {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
        obj.extract()
            .map_err(|_| expected(obj, field, "a path (str or os.PathLike)"))
    }
}

/// A scenario: a built-in name (a `str`) or a TOML file (a `str` or an
/// `os.PathLike`).
pub struct ScenarioRef(pub String);

impl<'a, 'py> FromArg<'a, 'py> for ScenarioRef {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
        let path: PathBuf = obj
            .extract()
            .map_err(|_| expected(obj, field, "a built-in name or a path (str or os.PathLike)"))?;
        path.to_str()
            .map(|s| ScenarioRef(s.to_owned()))
            .ok_or_else(|| input_err(format!("{field}: the path {path:?} is not valid UTF-8")))
    }
}

/// An instance of the Python class `T` (`MVGP`, `dict`).
impl<'a, 'py, T: PyTypeInfo> FromArg<'a, 'py> for Bound<'py, T> {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
        obj.cast::<T>().cloned().map_err(|_| {
            let name = T::type_object(obj.py()).name();
            expected(obj, field, &name.map_or("?".into(), |n| n.to_string()))
        })
    }
}

/// `None`, or the value.
impl<'a, 'py, T: FromArg<'a, 'py>> FromArg<'a, 'py> for Option<T> {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
        if obj.is_none() {
            Ok(None)
        } else {
            T::from_arg(obj, field).map(Some)
        }
    }
}

/// Finite numbers, as an array or a sequence ([`vector`]).
impl<'a, 'py> FromArg<'a, 'py> for Vec<f64> {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
        vector(obj, field, None)
    }
}

/// Exactly `N` finite numbers ([`vector`]).
impl<'a, 'py, const N: usize> FromArg<'a, 'py> for [f64; N] {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
        let v = vector(obj, field, Some(N))?;
        Ok(std::array::from_fn(|i| v[i]))
    }
}

/// The items of a sequence (not a string), each named `field[i]`.
fn items<'py, T: for<'b> FromArg<'b, 'py>>(
    obj: &Bound<'py, PyAny>,
    field: &str,
) -> PyResult<Vec<T>> {
    let iter = match obj.try_iter() {
        Ok(it) if !obj.is_instance_of::<PyString>() => it,
        _ => return Err(expected(obj, field, "a sequence")),
    };
    iter.enumerate()
        .map(|(i, item)| T::from_arg(&item?, &format!("{field}[{i}]")))
        .collect()
}

impl<'a, 'py> FromArg<'a, 'py> for Vec<usize> {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
        items(obj, field)
    }
}

impl<'a, 'py> FromArg<'a, 'py> for Vec<String> {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
        items(obj, field)
    }
}

impl<'a, 'py, T: PyTypeInfo> FromArg<'a, 'py> for Vec<Bound<'py, T>> {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
        items(obj, field)
    }
}

/// Exactly `N` indices.
impl<'a, 'py, const N: usize> FromArg<'a, 'py> for [usize; N] {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
        let v: Vec<usize> = items(obj, field)?;
        let n = v.len();
        v.try_into()
            .map_err(|_| input_err(format!("{field}: expected {N} entries, got {n}")))
    }
}

/// A dict of numbers by name, each named `field['name']`.
impl<'a, 'py> FromArg<'a, 'py> for BTreeMap<String, f64> {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
        let dict = obj
            .cast::<PyDict>()
            .map_err(|_| expected(obj, field, "a dict"))?;
        dict.iter()
            .map(|(k, v)| {
                let key = String::from_arg(&k, &format!("{field} (a key)"))?;
                let value = number(&v, &format!("{field}['{key}']"))?;
                Ok((key, value))
            })
            .collect()
    }
}

/// A rank: `"full"`, `"diag"` or an integer ([`parse_rank`]).
impl<'a, 'py> FromArg<'a, 'py> for Rank {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
        let text = if let Ok(s) = obj.cast::<PyString>() {
            s.to_str()?.to_owned()
        } else if integer(obj)?.is_some() {
            obj.str()?.to_string()
        } else {
            return Err(expected(obj, field, "'full', 'diag' or an integer"));
        };
        parse_rank(field, &text).map_err(scenario_err)
    }
}

/// The edge of a sector, `"upper"` or `"lower"` (as in barrier files).
impl<'a, 'py> FromArg<'a, 'py> for EdgeSpec {
    fn from_arg(obj: &'a Bound<'py, PyAny>, field: &str) -> PyResult<Self> {
        <&str>::from_arg(obj, field)?.parse().map_err(scenario_err)
    }
}

/// One `from_py_with` function per argument name: `name(obj)` is
/// [`FromArg::from_arg`]`(obj, "name")`, of the argument's type.
macro_rules! named {
    ($($name:ident)*) => {$(
        #[allow(non_snake_case)]
        pub fn $name<'a, 'py, T: FromArg<'a, 'py>>(obj: &'a Bound<'py, PyAny>) -> PyResult<T> {
            T::from_arg(obj, stringify!($name))
        }
    )*};
}

named! {
    alpha barrier barriers budget center clf clf_weight control_dim delta edge end episodes
    fallback gamma h quick scenario start
    indices k_alpha known_rows max_iters model name noise_sigma normal offset overrides params
    path predictive probability q1 q2 radius rank_a rank_b rank_s rank_sigma relative_degree
    repeats restarts samples seed sigma_min state state_dim step text theta_c variance w1 w2 zeta
    V
}

/// The most runs a timing helper takes (`repeats`): its times are kept
/// for the median.
pub const MAX_REPEATS: usize = 10_000_000;

/// Checks a timing helper's `repeats` (at most [`MAX_REPEATS`]).
pub fn check_repeats(repeats: usize) -> PyResult<usize> {
    if repeats > MAX_REPEATS {
        return Err(crate::convert::core_err(
            bayes_cbf::InputError::invalid_shown(
                "repeats",
                repeats,
                &format!("must be at most {MAX_REPEATS}: each run's time is kept for the median"),
            ),
        ));
    }
    if repeats == 0 {
        return Err(crate::convert::core_err(
            bayes_cbf::InputError::invalid_shown("repeats", 0, "must be ≥ 1"),
        ));
    }
    Ok(repeats)
}
