//! numpy arrays in and out, and the library's errors as typed Python
//! exceptions. No maths here: shapes, dtypes and names only.

use nalgebra::DMatrix;
use numpy::ndarray::{ArrayD, IxDyn};
use numpy::{IntoPyArray, PyArrayDyn, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::exceptions::{PyFileNotFoundError, PyOSError, PyPermissionError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

/// A numpy array of float64 (any shape), as returned to Python.
pub type NdArray<'py> = Bound<'py, PyArrayDyn<f64>>;

pyo3::create_exception!(
    bayes_cbf,
    InputError,
    PyValueError,
    "Bad input: a wrong shape, dtype or value, a malformed file or an unknown key. The message names the field."
);
pyo3::create_exception!(
    bayes_cbf,
    NumericalError,
    pyo3::exceptions::PyRuntimeError,
    "A numerical failure: a Gram matrix that cannot be factorised, an optimiser that fails."
);

/// Borrows `obj`, or raises `RuntimeError` ([`in_use`]) when a call that
/// has not returned holds it mutably.
pub fn borrow<'py, T: pyo3::PyClass>(obj: &Bound<'py, T>, what: &str) -> PyResult<PyRef<'py, T>> {
    obj.try_borrow().map_err(|_| in_use(what))
}

/// Borrows `obj` mutably (the methods that change a model or step a
/// filter), or raises `RuntimeError` ([`in_use`]) when a call that has not
/// returned holds it; pyo3's own message would be "Already borrowed".
pub fn borrow_mut<'py, T: pyo3::PyClass<Frozen = pyo3::pyclass::boolean_struct::False>>(
    obj: &Bound<'py, T>,
    what: &str,
) -> PyResult<PyRefMut<'py, T>> {
    obj.try_borrow_mut().map_err(|_| in_use(what))
}

/// The `RuntimeError` of an object in use: by another thread's call (a
/// call releases the GIL while it computes), or by the call whose callback
/// made this one.
fn in_use(what: &str) -> PyErr {
    pyo3::exceptions::PyRuntimeError::new_err(format!(
        "{what} is in use by a call that has not returned: another thread's, or the \
         call whose callback (a barrier's h, grad or hess) made this one; call this \
         after that call returns (a callback must not change or step the model or \
         filter it serves)"
    ))
}

/// An [`InputError`] with `msg` (caused by the callback exception it
/// quotes, if any).
pub fn input_err(msg: impl Into<String>) -> PyErr {
    let msg = msg.into();
    with_callback_cause(InputError::new_err(msg.clone()), &msg)
}

thread_local! {
    /// The last exception a Python callback raised on this thread, with
    /// the text the library's error quotes.
    static CALLBACK_ERROR: std::cell::RefCell<Option<(String, PyErr)>> =
        const { std::cell::RefCell::new(None) };
}

/// Keeps the exception `err` (quoted as `text`) that a callback raised.
pub fn keep_callback_error(text: String, err: PyErr) {
    CALLBACK_ERROR.with(|slot| *slot.borrow_mut() = Some((text, err)));
}

/// `new`, the exception of a library error with message `msg`, linked to
/// the callback exception that `msg` quotes: that exception itself when it
/// is not an `Exception` (`KeyboardInterrupt`, `SystemExit` pass through),
/// else `new` with it as `__cause__`.
fn with_callback_cause(new: PyErr, msg: &str) -> PyErr {
    let Some((text, orig)) = CALLBACK_ERROR.with(|slot| slot.borrow_mut().take()) else {
        return new;
    };
    if !msg.contains(&text) {
        return new;
    }
    Python::attach(|py| {
        if !orig.is_instance_of::<pyo3::exceptions::PyException>(py) {
            return orig;
        }
        new.set_cause(py, Some(orig));
        new
    })
}

/// The Python exception of a scenario-layer error: bad input of any kind is
/// [`InputError`], I/O is `OSError` (`FileNotFoundError`, `PermissionError`
/// where it is one of these), numerical failures [`NumericalError`].
pub fn scenario_err(e: bayes_cbf_scenario::Error) -> PyErr {
    use bayes_cbf_scenario::Error as E;
    let msg = e.to_string();
    let new = match e.root() {
        E::Io(io) => match io.kind() {
            std::io::ErrorKind::NotFound => PyFileNotFoundError::new_err(msg.clone()),
            std::io::ErrorKind::PermissionDenied => PyPermissionError::new_err(msg.clone()),
            _ => PyOSError::new_err(msg.clone()),
        },
        E::Core(bayes_cbf::Error::Input(_)) => InputError::new_err(msg.clone()),
        E::Core(_) => NumericalError::new_err(msg.clone()),
        _ => InputError::new_err(msg.clone()),
    };
    with_callback_cause(new, &msg)
}

/// The Python exception of a core-library error.
pub fn core_err(e: impl Into<bayes_cbf::Error>) -> PyErr {
    let e: bayes_cbf::Error = e.into();
    let msg = e.to_string();
    let new = match e {
        bayes_cbf::Error::Input(_) => InputError::new_err(msg.clone()),
        _ => NumericalError::new_err(msg.clone()),
    };
    with_callback_cause(new, &msg)
}

/// A float64 array of `obj` (numpy arrays of float64 as they are; lists and
/// other real dtypes converted by `numpy.asarray`), with `ndim`
/// dimensions. Errors name `field`; complex values are one (numpy would
/// drop their imaginary parts), and so are booleans, strings and dates
/// (which numpy would read as numbers).
pub fn array<'py>(
    obj: &Bound<'py, PyAny>,
    field: &str,
    ndim: usize,
) -> PyResult<PyReadonlyArrayDyn<'py, f64>> {
    let arr: PyReadonlyArrayDyn<'py, f64> = match obj.extract() {
        Ok(a) => a,
        Err(_) => {
            let py = obj.py();
            let np = py.import("numpy")?;
            let not_numbers = |e: PyErr| {
                input_err(format!(
                    "{field}: expected an array of numbers (float64), got {} ({e})",
                    type_name(obj)
                ))
            };
            let any = np.call_method1("asarray", (obj,)).map_err(not_numbers)?;
            let kind = any.getattr("dtype")?.getattr("kind")?.extract::<String>()?;
            // as a scalar argument refuses True: a bool array is not numbers
            // numpy would read strings of digits and dates as numbers too
            // in an object array, the entries' own types
            let texts = kind == "O"
                && any.call_method0("ravel")?.try_iter()?.any(|e| {
                    e.is_ok_and(|e| {
                        e.is_instance_of::<pyo3::types::PyString>()
                            || e.is_instance_of::<pyo3::types::PyBytes>()
                    })
                });
            let refused = match kind.as_str() {
                _ if texts => Some("strings are not numbers"),
                "f" | "i" | "u" | "O" => None,
                "c" => Some("complex values are not accepted"),
                "b" => Some("booleans are not numbers"),
                "U" | "S" => Some("strings are not numbers"),
                "M" | "m" => Some("dates and durations are not numbers"),
                _ => Some("expected an array of numbers"),
            };
            if let Some(why) = refused {
                return Err(input_err(format!(
                    "{field}: {why} (got dtype {})",
                    any.getattr("dtype")?
                )));
            }
            let kw = PyDict::new(py);
            kw.set_item("dtype", "float64")?;
            let conv = np
                .call_method("asarray", (&any,), Some(&kw))
                .map_err(not_numbers)?;
            conv.extract().map_err(|_| {
                input_err(format!(
                    "{field}: expected an array of numbers (float64), got {}",
                    type_name(obj)
                ))
            })?
        }
    };
    if arr.ndim() != ndim {
        return Err(input_err(format!(
            "{field}: expected a {ndim}-D array, got shape {:?}",
            arr.shape()
        )));
    }
    Ok(arr)
}

/// The name of `obj`'s type (`float`, `str`, `ndarray`).
pub fn type_name(obj: &Bound<'_, PyAny>) -> String {
    obj.get_type()
        .name()
        .map(|n| n.to_string())
        .unwrap_or_else(|_| "an object".into())
}

/// The entries of `arr` in row-major (C) order: borrowed when the array is
/// C-contiguous, copied otherwise.
/// (`as_slice` alone would also accept Fortran-ordered arrays, whose memory
/// order is column-major.)
pub fn row_major<'a>(arr: &'a PyReadonlyArrayDyn<'_, f64>) -> std::borrow::Cow<'a, [f64]> {
    match arr.as_slice() {
        Ok(s) if arr.is_c_contiguous() => std::borrow::Cow::Borrowed(s),
        _ => std::borrow::Cow::Owned(arr.as_array().iter().copied().collect()),
    }
}

/// Calls `f` with the entries of a vector of exactly `len` finite entries
/// (`len = None`: any length), borrowed from numpy when C-contiguous.
fn with_vector<R>(
    obj: &Bound<'_, PyAny>,
    field: &str,
    len: Option<usize>,
    f: impl FnOnce(&[f64]) -> R,
) -> PyResult<R> {
    let arr = array(obj, field, 1)?;
    let v = row_major(&arr);
    if let Some(len) = len.filter(|&len| len != v.len()) {
        return Err(input_err(format!(
            "{field}: expected {len} entries, got {}",
            v.len()
        )));
    }
    check_finite(field, &v, None)?;
    Ok(f(&v))
}

/// A vector of exactly `len` finite entries (`len = None`: any length).
pub fn vector(obj: &Bound<'_, PyAny>, field: &str, len: Option<usize>) -> PyResult<Vec<f64>> {
    with_vector(obj, field, len, <[f64]>::to_vec)
}

/// Copies a vector of exactly `out.len()` finite entries into `out`,
/// without allocating when the array is C-contiguous.
pub fn copy_into(obj: &Bound<'_, PyAny>, field: &str, out: &mut [f64]) -> PyResult<()> {
    with_vector(obj, field, Some(out.len()), |v| out.copy_from_slice(v))
}

/// Calls `f` with the row-major entries and the shape of a `rows × cols`
/// matrix (either may be `None`: any) of finite entries, borrowed from
/// numpy when C-contiguous.
pub fn with_matrix<R>(
    obj: &Bound<'_, PyAny>,
    field: &str,
    rows: Option<usize>,
    cols: Option<usize>,
    f: impl FnOnce(&[f64], usize, usize) -> R,
) -> PyResult<R> {
    let arr = array(obj, field, 2)?;
    let (r, c) = (arr.shape()[0], arr.shape()[1]);
    if rows.is_some_and(|x| x != r) || cols.is_some_and(|x| x != c) {
        let want = |d: Option<usize>| d.map_or("any".to_string(), |d| d.to_string());
        return Err(input_err(format!(
            "{field}: expected shape ({}, {}), got ({r}, {c})",
            want(rows),
            want(cols)
        )));
    }
    let v = row_major(&arr);
    check_finite(field, &v, Some(c))?;
    Ok(f(&v, r, c))
}

/// A `rows × cols` matrix (either may be `None`: any) as rows, entries
/// finite. Returns the row-major entries and the shape.
pub fn matrix(
    obj: &Bound<'_, PyAny>,
    field: &str,
    rows: Option<usize>,
    cols: Option<usize>,
) -> PyResult<(Vec<f64>, usize, usize)> {
    with_matrix(obj, field, rows, cols, |v, r, c| (v.to_vec(), r, c))
}

/// A square `d × d` matrix of finite entries.
pub fn square(obj: &Bound<'_, PyAny>, field: &str, d: usize) -> PyResult<DMatrix<f64>> {
    with_matrix(obj, field, Some(d), Some(d), |v, _, _| {
        DMatrix::from_row_slice(d, d, v)
    })
}

/// Rejects NaN and infinities, naming the entry: `field[i][j]` for a
/// matrix of `cols` columns (one column included), `field[i]` for a vector.
pub fn check_finite(field: &str, v: &[f64], cols: Option<usize>) -> PyResult<()> {
    if let Some(i) = v.iter().position(|x| !x.is_finite()) {
        let at = match cols {
            Some(c) => format!("[{}][{}]", i / c.max(1), i % c.max(1)),
            None => format!("[{i}]"),
        };
        return Err(input_err(format!("{field}{at} = {} is not finite", v[i])));
    }
    Ok(())
}

/// Rows of a row-major matrix, for JSON.
pub fn rows(v: &[f64], cols: usize) -> Vec<Vec<f64>> {
    v.chunks(cols.max(1)).map(<[f64]>::to_vec).collect()
}

/// A numpy array of `shape` owning `data` (row-major), without a copy.
pub fn to_numpy<'py>(py: Python<'py>, data: Vec<f64>, shape: &[usize]) -> PyResult<NdArray<'py>> {
    let a = ArrayD::from_shape_vec(IxDyn(shape), data)
        .map_err(|e| NumericalError::new_err(format!("internal shape error: {e}")))?;
    Ok(a.into_pyarray(py))
}

/// Appends the rows of `m` to `out` (row-major order).
pub fn extend_rows(out: &mut Vec<f64>, m: &DMatrix<f64>) {
    for row in m.row_iter() {
        out.extend(row.iter());
    }
}

/// A numpy array of a nalgebra matrix, row-major.
pub fn matrix_to_numpy<'py>(py: Python<'py>, m: &DMatrix<f64>) -> PyResult<NdArray<'py>> {
    let mut v = Vec::with_capacity(m.len());
    extend_rows(&mut v, m);
    to_numpy(py, v, &[m.nrows(), m.ncols()])
}

/// The message of an error in reading [`json_of`]'s text: without the
/// position in that text, which the caller never saw, and with Rust's
/// type names in words.
pub fn json_of_error(e: &serde_json::Error) -> String {
    let mut msg = e.to_string();
    let at = format!(" at line {} column {}", e.line(), e.column());
    if let Some(cut) = msg.strip_suffix(&at).map(str::len) {
        msg.truncate(cut);
    }
    bayes_cbf_scenario::parse::in_words(&msg)
}

/// Python JSON text of `obj` (a dict or list), for fields whose format is
/// the model file's.
pub fn json_of(obj: &Bound<'_, PyAny>, field: &str) -> PyResult<String> {
    let py = obj.py();
    let json = py.import("json")?;
    let kwargs = PyDict::new(py);
    // numpy scalars and arrays as their Python values; NaN and infinities
    // refused (JSON has none)
    kwargs.set_item("default", py.eval(c"lambda o: o.tolist()", None, None)?)?;
    kwargs.set_item("allow_nan", false)?;
    json.call_method("dumps", (obj,), Some(&kwargs))
        .and_then(|s| s.extract::<String>())
        .map_err(|e| {
            input_err(format!(
                "{field}: not JSON-serialisable ({e}); values are finite numbers, \
                 strings, lists and dicts"
            ))
        })
}
