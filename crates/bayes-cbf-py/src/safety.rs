//! `Barrier`, `CLF`, `moments` and `SafetyFilter`: wrappers over the
//! barrier files of the scenario crate, [`CallbackBarrier`] and the
//! library's [`SafetyController`].

use crate::args;
use crate::convert::{
    borrow, borrow_mut, copy_into, core_err, input_err, scenario_err, square, to_numpy, vector,
    NdArray,
};
use crate::models::PyMvgp;
use bayes_cbf::barrier::{ArrayFn, CallbackBarrier, DynBarrier, DynLyapunov, McSettings, ValueFn};
use bayes_cbf::control::{ControlOutput, Fallback, SafetyController, SafetySettings};
use bayes_cbf_scenario::barrier_file::{BarrierSpec, EdgeSpec};
use bayes_cbf_scenario::queries::{check_barrier, condition_moments, status_parts};
use bayes_cbf_scenario::scenario::ClfSpec;
use numpy::{PyArray1, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyTuple};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

/// A control barrier function: the safe set is `{x : h(x) ≥ 0}`.
///
/// Built from a barrier file (`Barrier.from_json`, `Barrier.load`, the
/// built-in constructors) or from Python callbacks (`Barrier.callback`).
#[pyclass(name = "Barrier", module = "bayes_cbf", frozen)]
pub struct PyBarrier {
    pub(crate) barrier: Arc<dyn DynBarrier>,
    /// The barrier-file description, for barriers built from one.
    spec: Option<BarrierSpec>,
    /// The arguments of `Barrier.callback` that built a callback barrier
    /// (what pickling rebuilds it from).
    callback_args: Option<Py<PyTuple>>,
    /// Name in reports.
    #[pyo3(get, name = "name")]
    pub(crate) label: String,
    /// State dimension `n`.
    #[pyo3(get)]
    state_dim: usize,
    /// Relative degree `r`.
    #[pyo3(get)]
    relative_degree: usize,
    /// Class-K gains (`[α]` or `k_α`).
    #[pyo3(get)]
    gains: Vec<f64>,
}

/// `alpha`, or 1 for a relative-degree-1 barrier given no gain (the
/// default of every barrier constructor, as of `Barrier.callback`).
fn default_alpha(
    relative_degree: usize,
    alpha: Option<f64>,
    k_alpha: &Option<Vec<f64>>,
) -> Option<f64> {
    match (relative_degree, alpha, k_alpha) {
        (1, None, None) => Some(1.0),
        _ => alpha,
    }
}

/// Calls `f(x)` in Python with `x` as a numpy array. A raised exception
/// becomes the message the library carries, and is kept
/// ([`crate::convert::keep_callback_error`]) to be raised again, as the
/// cause of the library's error or as itself, when the error reaches Python.
/// The message quotes the exception's first 300 characters
/// ([`bayes_cbf::error::shortened`]: a callback that calls itself would nest
/// every level's message); the cause is whole. Callbacks nest at most
/// [`MAX_NESTING`] deep on one thread: one that calls the barrier it serves
/// fails there, rather than recursing through Rust to Python's recursion
/// limit.
fn call_py<'py>(py: Python<'py>, f: &Py<PyAny>, x: &[f64]) -> Result<Bound<'py, PyAny>, String> {
    let _nested = Nested::enter()?;
    f.bind(py)
        .call1((PyArray1::from_slice(py, x),))
        .map_err(|e| {
            let text = bayes_cbf::error::shortened(e.to_string());
            crate::convert::keep_callback_error(text.clone(), e);
            text
        })
}

/// How deep Python callbacks may nest on one thread ([`call_py`]).
const MAX_NESTING: usize = 32;

thread_local! {
    /// The Python callbacks under way on this thread, outermost first.
    static NESTING: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
}

/// One callback under way on this thread, counted in [`NESTING`] until
/// dropped (on return, error or panic).
struct Nested;

impl Nested {
    fn enter() -> Result<Self, String> {
        let depth = NESTING.with(std::cell::Cell::get);
        if depth >= MAX_NESTING {
            return Err(format!(
                "callbacks nest {MAX_NESTING} deep on this thread: a callback calls the \
                 barrier or filter it serves, without end"
            ));
        }
        NESTING.with(|d| d.set(depth + 1));
        Ok(Self)
    }
}

impl Drop for Nested {
    fn drop(&mut self) {
        NESTING.with(|d| d.set(d.get() - 1));
    }
}

#[pymethods]
impl PyBarrier {
    /// A barrier from barrier-file JSON text (interfaces.md).
    #[staticmethod]
    fn from_json(#[pyo3(from_py_with = args::text)] text: &str) -> PyResult<Self> {
        Self::of_spec(BarrierSpec::parse(text, "barrier").map_err(scenario_err)?)
    }

    /// Reads a barrier file.
    #[staticmethod]
    fn load(#[pyo3(from_py_with = args::path)] path: PathBuf) -> PyResult<Self> {
        let (spec, barrier) = BarrierSpec::load(&path).map_err(scenario_err)?;
        Ok(Self::new(barrier, Some(spec), path.display().to_string()))
    }

    /// A barrier written as an expression over the named states `state`
    /// and parameters `params` (interfaces.md, "Expressions"), e.g.
    /// `Barrier.expression("(x - 1)^2 + (y + 1)^2 - r^2", ["x", "y", "theta"],
    /// {"r": 0.5}, alpha=5.0)`. Gradients and Hessians are exact (dual
    /// numbers) and evaluated in Rust, with no Python call per step.
    #[staticmethod]
    #[pyo3(signature = (h, state, params=None, relative_degree=1, alpha=None, k_alpha=None))]
    fn expression(
        #[pyo3(from_py_with = args::h)] h: String,
        #[pyo3(from_py_with = args::state)] state: Vec<String>,
        #[pyo3(from_py_with = args::params)] params: Option<BTreeMap<String, f64>>,
        #[pyo3(from_py_with = args::relative_degree)] relative_degree: usize,
        #[pyo3(from_py_with = args::alpha)] alpha: Option<f64>,
        #[pyo3(from_py_with = args::k_alpha)] k_alpha: Option<Vec<f64>>,
    ) -> PyResult<Self> {
        let alpha = default_alpha(relative_degree, alpha, &k_alpha);
        Self::of_spec(BarrierSpec::Expression {
            state: Some(state),
            params: params.unwrap_or_default().into(),
            h,
            relative_degree,
            alpha,
            k_alpha,
        })
    }

    /// A barrier written in Python: `h(x) -> float`, `grad(x) -> (n,)` and,
    /// for relative degree 2 (or self-triggering), `hess(x) -> (n, n)`.
    /// Dual numbers follow from them by the chain rule, so the moments are
    /// those of a built-in barrier with the same derivatives. `alpha` is the
    /// class-K gain for relative degree 1 (1 by default), `k_alpha` the gains
    /// for relative degree ≥ 2 (one or the other, as for the built-ins).
    /// Check the derivatives with `bayes_cbf.check_derivatives`. A callback
    /// may call other barriers; callbacks nest at most 32 deep on a thread,
    /// so one that calls the barrier it serves fails with `InputError`.
    #[staticmethod]
    #[pyo3(signature = (h, grad, hess=None, state_dim=2, relative_degree=1, alpha=None, k_alpha=None, name="callback"))]
    #[allow(clippy::too_many_arguments)]
    fn callback(
        h: Py<PyAny>,
        grad: Py<PyAny>,
        hess: Option<Py<PyAny>>,
        #[pyo3(from_py_with = args::state_dim)] state_dim: usize,
        #[pyo3(from_py_with = args::relative_degree)] relative_degree: usize,
        #[pyo3(from_py_with = args::alpha)] alpha: Option<f64>,
        #[pyo3(from_py_with = args::k_alpha)] k_alpha: Option<Vec<f64>>,
        #[pyo3(from_py_with = args::name)] name: &str,
    ) -> PyResult<Self> {
        let args = Python::attach(|py| -> PyResult<Py<PyTuple>> {
            for (field, f) in [
                ("h", Some(&h)),
                ("grad", Some(&grad)),
                ("hess", hess.as_ref()),
            ] {
                if let Some(f) = f {
                    if !f.bind(py).is_callable() {
                        return Err(input_err(format!("{field}: expected a callable")));
                    }
                }
            }
            let hess = hess.as_ref().map(|f| f.clone_ref(py));
            let given = (
                &h,
                &grad,
                hess,
                state_dim,
                relative_degree,
                alpha,
                &k_alpha,
                name,
            );
            Ok(given.into_pyobject(py)?.unbind())
        })?;
        let alpha = default_alpha(relative_degree, alpha, &k_alpha);
        let gains = bayes_cbf_scenario::barrier_file::gains(relative_degree, &alpha, &k_alpha)
            .map_err(scenario_err)?;
        let n = state_dim;
        let hf: ValueFn = Box::new(move |x: &[f64]| {
            Python::attach(|py| {
                let v = call_py(py, &h, x)?;
                // Python's bool, and numpy's (x[0] < 1 gives one)
                let numpy_bool = v
                    .getattr("dtype")
                    .and_then(|d| d.getattr("kind"))
                    .is_ok_and(|k| k.to_string() == "b");
                if v.is_instance_of::<pyo3::types::PyBool>() || numpy_bool {
                    return Err("h must return a float, not a bool".to_string());
                }
                v.extract::<f64>()
                    .map_err(|e| format!("h must return a float ({e})"))
            })
        });
        let array_fn = |f: Py<PyAny>, what: &'static str, len: usize| -> ArrayFn {
            Box::new(move |x: &[f64], out: &mut [f64]| {
                Python::attach(|py| {
                    let r = call_py(py, &f, x)?;
                    let v = crate::convert::array(&r, what, if what == "hess" { 2 } else { 1 })
                        .map_err(|e| e.to_string())?;
                    if what == "hess" && v.shape() != [n, n] {
                        return Err(format!(
                            "hess returned shape {:?}, expected ({n}, {n})",
                            v.shape()
                        ));
                    }
                    let flat = crate::convert::row_major(&v);
                    if flat.len() != len {
                        return Err(format!(
                            "{what} returned {} entries, expected {len}",
                            flat.len()
                        ));
                    }
                    out.copy_from_slice(&flat);
                    Ok(())
                })
            })
        };
        let gf = array_fn(grad, "grad", n);
        let hsf = hess.map(|f| array_fn(f, "hess", n * n));
        let b =
            CallbackBarrier::new(name, n, relative_degree, gains, hf, gf, hsf).map_err(core_err)?;
        let mut barrier = Self::new(Arc::new(b), None, name.to_string());
        barrier.callback_args = Some(args);
        Ok(barrier)
    }

    /// Pickling (`pickle`, `copy.deepcopy`, Ray tasks): a barrier-file
    /// barrier as its JSON and name, a callback barrier as its callbacks
    /// and arguments (callbacks that `pickle` cannot write, such as
    /// lambdas, need `cloudpickle`, which Ray uses).
    fn __reduce__<'py>(
        slf: &Bound<'py, Self>,
    ) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyTuple>)> {
        let (py, this) = (slf.py(), slf.get());
        let cls = slf.get_type();
        match (&this.callback_args, this.to_json()?) {
            (Some(args), _) => Ok((cls.getattr("callback")?, args.bind(py).clone())),
            (None, Some(text)) => Ok((
                cls.getattr("_restore")?,
                (text, &this.label).into_pyobject(py)?,
            )),
            (None, None) => Err(input_err("this barrier has no description to pickle")),
        }
    }

    /// The barrier of barrier-file JSON `text` named `name` (unpickling).
    #[staticmethod]
    fn _restore(text: &str, name: String) -> PyResult<Self> {
        let mut barrier = Self::from_json(text)?;
        barrier.label = name;
        Ok(barrier)
    }

    /// `h(x)`.
    fn value(&self, py: Python<'_>, x: &Bound<'_, PyAny>) -> PyResult<f64> {
        let x = vector(x, "x", Some(self.state_dim))?;
        let b = &self.barrier;
        let v = py.detach(|| b.value(&x));
        self.check(v)
    }

    /// `∇h(x)` by automatic differentiation (or the callback).
    fn gradient<'py>(&self, x: &Bound<'py, PyAny>) -> PyResult<NdArray<'py>> {
        let n = self.state_dim;
        self.derivative(x, &[n], |b, x, g| {
            let mut scratch = vec![num_dual::Dual64::from(0.0); n];
            b.gradient(x, g, &mut scratch)
        })
    }

    /// `∇²h(x)` by automatic differentiation (or the callback).
    fn hessian<'py>(&self, x: &Bound<'py, PyAny>) -> PyResult<NdArray<'py>> {
        let n = self.state_dim;
        self.derivative(x, &[n, n], |b, x, hs| {
            let (mut g, mut scratch) = (vec![0.0; n], vec![num_dual::HyperDual64::from(0.0); n]);
            b.hessian(x, &mut g, hs, &mut scratch)
        })
    }

    /// The barrier-file JSON, or `None` for a callback barrier.
    fn to_json(&self) -> PyResult<Option<String>> {
        self.spec
            .as_ref()
            .map(|s| serde_json::to_string(s).map_err(|e| input_err(e.to_string())))
            .transpose()
    }
    fn __repr__(&self) -> String {
        format!(
            "Barrier('{}', state_dim={}, relative_degree={})",
            self.label, self.state_dim, self.relative_degree
        )
    }
}

/// The built-in barriers of barrier files as static constructors of
/// `Barrier`: `name(fields..., relative_degree=r, alpha=None,
/// k_alpha=None)` describes the barrier-file variant `Variant` with those
/// fields, and the library builds and validates it ([`BarrierSpec::build`]).
/// A relative-degree-1 barrier given neither gain has `alpha = 1`.
macro_rules! builtin_barriers {
    ($(
        $(#[doc = $doc:tt])*
        $name:ident($($field:ident: $ty:ty),*) = $variant:ident, relative_degree = $rd:tt;
    )*) => {
        #[pymethods]
        impl PyBarrier {$(
            $(#[doc = $doc])*
            #[staticmethod]
            #[pyo3(signature = ($($field,)* relative_degree=$rd, alpha=None, k_alpha=None))]
            #[allow(clippy::too_many_arguments)]
            fn $name(
                $(#[pyo3(from_py_with = args::$field)] $field: $ty,)*
                #[pyo3(from_py_with = args::relative_degree)] relative_degree: usize,
                #[pyo3(from_py_with = args::alpha)] alpha: Option<f64>,
                #[pyo3(from_py_with = args::k_alpha)] k_alpha: Option<Vec<f64>>,
            ) -> PyResult<Self> {
                let alpha = default_alpha(relative_degree, alpha, &k_alpha);
                Self::of_spec(BarrierSpec::$variant {
                    $($field,)*
                    relative_degree,
                    alpha,
                    k_alpha,
                })
            }
        )*}
    };
}

builtin_barriers! {
    /// `h = cos(δ) − cos(θ − θ_c)`: keeps the pendulum angle out of the
    /// sector of half-width `delta` around `theta_c` (paper, Sec. VII-A).
    pendulum_sector(theta_c: f64, delta: f64) = PendulumSector, relative_degree = 2;

    /// One edge of the sector `theta_c ± delta`, linear in
    /// `φ = (θ − θ_c) mod 2π`: `h = φ − δ` (`edge="upper"`) or
    /// `h = 2π − δ − φ` (`edge="lower"`); the two edges together keep the
    /// pendulum in the free arc with a control-invariant safe set.
    pendulum_sector_edge(theta_c: f64, delta: f64, edge: EdgeSpec) = PendulumSectorEdge,
        relative_degree = 2;

    /// The Ackermann obstacle barrier with heading term (paper, Sec. VII-B).
    circle_heading(center: [f64; 2], radius: f64, q1: f64, q2: f64) = CircleHeading,
        relative_degree = 1;

    /// `h = ‖x[indices] − center‖² − radius²`: stay out of a disc.
    disc(state_dim: usize, indices: [usize; 2], center: [f64; 2], radius: f64) = Disc,
        relative_degree = 1;

    /// `h = normalᵀx − offset`: stay in a half-space.
    half_space(normal: Vec<f64>, offset: f64) = HalfSpace, relative_degree = 1;
}

impl PyBarrier {
    /// The wrapper of `barrier`, described by `spec` (barrier files) and
    /// named `label` in reports.
    fn new(barrier: Arc<dyn DynBarrier>, spec: Option<BarrierSpec>, label: String) -> Self {
        Self {
            state_dim: barrier.state_dim(),
            relative_degree: barrier.relative_degree(),
            gains: barrier.gains().to_vec(),
            barrier,
            spec,
            callback_args: None,
            label,
        }
    }

    /// The barrier a barrier-file description builds (fields validated).
    /// Its warnings (a kink in `h`) are issued here.
    fn of_spec(spec: BarrierSpec) -> PyResult<Self> {
        Python::attach(|py| {
            crate::warnings::after(
                py,
                spec.build().map_err(scenario_err).map(|barrier| {
                    let label = barrier.name().to_string();
                    Self::new(barrier, Some(spec), label)
                }),
            )
        })
    }

    /// A derivative of `h` at `x`, of `shape`: `eval(barrier, x, out)`
    /// writes it into `out` and returns `h(x)`, the GIL released.
    fn derivative<'py>(
        &self,
        x: &Bound<'py, PyAny>,
        shape: &[usize],
        eval: impl FnOnce(&dyn DynBarrier, &[f64], &mut [f64]) -> f64 + Send,
    ) -> PyResult<NdArray<'py>> {
        let py = x.py();
        let x = vector(x, "x", Some(self.state_dim))?;
        let b = self.barrier.as_ref();
        let (h, out) = py.detach(|| {
            let mut out = vec![0.0; shape.iter().product()];
            (eval(b, &x, &mut out), out)
        });
        self.check(h)?;
        if let Some(i) = out.iter().position(|v| !v.is_finite()) {
            let what = if shape.len() == 1 {
                "gradient"
            } else {
                "Hessian"
            };
            return Err(input_err(format!(
                "barrier '{}': the {what} is not finite at x = {x:?} (entry {i} = {})",
                self.label, out[i]
            )));
        }
        to_numpy(py, out, shape)
    }

    /// Turns a callback's recorded failure or a non-finite value into an
    /// [`crate::convert::InputError`].
    fn check(&self, v: f64) -> PyResult<f64> {
        if let Some(e) = self.barrier.take_error() {
            // an expression's message names its barrier already
            let named = e.contains(&format!("barrier '{}'", self.label));
            return Err(input_err(if named {
                e
            } else {
                format!("barrier '{}': {e}", self.label)
            }));
        }
        if !v.is_finite() {
            return Err(input_err(format!(
                "barrier '{}': h = {v} is not finite",
                self.label
            )));
        }
        Ok(v)
    }
}

/// A control Lyapunov function for the filter's CLF constraint (paper,
/// Eq. 21), from its JSON description (`{"type": "ackermann", "w1": ...,
/// "w2": ..., "gamma": ...}`, the scenario file's `[clf]`).
#[pyclass(name = "CLF", module = "bayes_cbf", frozen)]
pub struct PyClf {
    spec: ClfSpec,
    /// State names of an expression CLF.
    state: Option<Vec<String>>,
}

#[pymethods]
impl PyClf {
    /// A CLF from JSON text.
    #[staticmethod]
    fn from_json(#[pyo3(from_py_with = args::text)] text: &str) -> PyResult<Self> {
        let mut v: serde_json::Value =
            serde_json::from_str(text).map_err(|e| input_err(format!("clf: {e}")))?;
        let state = match v.as_object_mut().and_then(|o| o.remove("state")) {
            None => None,
            Some(s) => Some(
                serde_json::from_value::<Vec<String>>(s)
                    .map_err(|e| input_err(format!("clf.state: {e}")))?,
            ),
        };
        let spec: ClfSpec =
            serde_json::from_value(v).map_err(|e| input_err(format!("clf: {e}")))?;
        Ok(Self { spec, state })
    }
    /// `V(x, x_d)` written as an expression over the state names `state`,
    /// the reference names `<state>_d` and the parameters `params`, decay
    /// rate `gamma`: `CLF.expression("(x - x_d)^2 + (y - y_d)^2", ["x", "y", "theta"])`.
    #[staticmethod]
    #[pyo3(signature = (V, state, params=None, gamma=1.0))]
    #[allow(non_snake_case)]
    fn expression(
        #[pyo3(from_py_with = args::V)] V: String,
        #[pyo3(from_py_with = args::state)] state: Vec<String>,
        #[pyo3(from_py_with = args::params)] params: Option<BTreeMap<String, f64>>,
        #[pyo3(from_py_with = args::gamma)] gamma: f64,
    ) -> PyResult<Self> {
        let spec = ClfSpec::Expression {
            v: V,
            params: params.unwrap_or_default().into(),
            gamma,
        };
        // parse now, so a bad expression fails here
        spec.build(&state).map_err(scenario_err)?;
        Ok(Self {
            spec,
            state: Some(state),
        })
    }
    /// `V = w1/2 ρ² + w2 (1 − cos α)` for the Ackermann vehicle (paper,
    /// Sec. VII-B), decay rate `gamma`.
    #[staticmethod]
    fn ackermann(
        #[pyo3(from_py_with = args::w1)] w1: f64,
        #[pyo3(from_py_with = args::w2)] w2: f64,
        #[pyo3(from_py_with = args::gamma)] gamma: f64,
    ) -> PyResult<Self> {
        // checked now, not when a filter is built
        bayes_cbf::barrier::AckermannClf::new(w1, w2, gamma).map_err(core_err)?;
        Ok(Self {
            spec: ClfSpec::Ackermann { w1, w2, gamma },
            state: None,
        })
    }
    /// The JSON text `CLF.from_json` reads back (with `state` for an
    /// expression CLF).
    fn to_json(&self) -> PyResult<String> {
        let unwritable = |e: serde_json::Error| input_err(format!("clf: not JSON: {e}"));
        let spec = serde_json::to_string(&self.spec).map_err(unwritable)?;
        match (&self.state, spec.strip_suffix('}')) {
            // the spec's fields in their order, then the state names
            (Some(state), Some(open)) => {
                let state = serde_json::to_string(state).map_err(unwritable)?;
                Ok(format!("{open},\"state\":{state}}}"))
            }
            _ => Ok(spec),
        }
    }
    fn __repr__(&self) -> String {
        format!("CLF({})", self.to_json().unwrap_or_else(|_| "?".into()))
    }
    /// Pickling (`pickle`, `copy.deepcopy`, Ray tasks): its JSON.
    fn __reduce__<'py>(slf: &Bound<'py, Self>) -> PyResult<(Bound<'py, PyAny>, (String,))> {
        Ok((
            slf.get_type().getattr("from_json")?,
            (slf.get().to_json()?,),
        ))
    }
}

/// Moments of the barrier condition `CBC(x, u)` under the model's
/// posterior: `(mean, variance)`. Exact for relative degree 1 and 2 (paper,
/// Lemma 2 and Thm. 2), Monte Carlo (`samples`, `step`, `seed`) beyond.
#[pyfunction]
#[pyo3(signature = (model, barrier, x, u, samples=20_000, step=1e-2, seed=0))]
#[allow(clippy::too_many_arguments)]
pub fn moments<'py>(
    py: Python<'py>,
    #[pyo3(from_py_with = args::model)] model: Bound<'py, PyMvgp>,
    #[pyo3(from_py_with = args::barrier)] barrier: Bound<'py, PyBarrier>,
    x: &Bound<'py, PyAny>,
    u: &Bound<'py, PyAny>,
    #[pyo3(from_py_with = args::samples)] samples: usize,
    #[pyo3(from_py_with = args::step)] step: f64,
    #[pyo3(from_py_with = args::seed)] seed: u64,
) -> PyResult<(f64, f64)> {
    let model = crate::models::read(&model, "the model")?;
    let b = barrier.get();
    let x = vector(x, "x", Some(model.model.state_dim()))?;
    let u = vector(u, "u", Some(model.model.control_dim()))?;
    let mc = McSettings {
        samples,
        step,
        seed,
    };
    let m = &model.model;
    let r = py.detach(|| {
        condition_moments(
            m,
            b.barrier.as_ref(),
            &format!("barrier '{}'", b.label),
            &x,
            &u,
            &mc,
        )
    });
    crate::warnings::emit(py)?;
    let r = r.map_err(scenario_err)?;
    Ok((r.mean, r.variance))
}

/// The result of one filter step.
#[pyclass(name = "FilterResult", module = "bayes_cbf", frozen)]
pub struct PyFilterResult {
    u: Py<PyArray1<f64>>,
    status: &'static str,
    p_star: Option<f64>,
    fallback: Option<&'static str>,
    violated: Option<Vec<usize>>,
    /// Per barrier: name, relative degree and the library's report.
    reports: Vec<(String, usize, bayes_cbf::control::ConstraintReport)>,
    solve_time_us: f64,
}

#[pymethods]
impl PyFilterResult {
    /// The control to apply.
    #[getter]
    fn u(&self, py: Python<'_>) -> Py<PyArray1<f64>> {
        self.u.clone_ref(py)
    }
    /// `"optimal"` or `"infeasible"`.
    #[getter]
    fn status(&self) -> &'static str {
        self.status
    }
    /// Largest probability at which the barrier constraints are feasible
    /// (infeasible steps), else `None`.
    #[getter]
    fn p_star(&self) -> Option<f64> {
        self.p_star
    }
    /// The fallback that produced `u` (infeasible steps), else `None`.
    #[getter]
    fn fallback(&self) -> Option<&'static str> {
        self.fallback
    }
    /// Barriers violated at the fallback control (infeasible steps).
    #[getter]
    fn violated(&self) -> Option<Vec<usize>> {
        self.violated.clone()
    }
    /// One dict per barrier: `barrier`, `relative_degree`, `mean`, `std`,
    /// `c` and `slack` (`mean − ζ − c·std`, ≥ 0 when met).
    #[getter]
    fn constraints<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, pyo3::types::PyList>> {
        let list = pyo3::types::PyList::empty(py);
        for (name, r, c) in &self.reports {
            let d = PyDict::new(py);
            d.set_item("barrier", name)?;
            d.set_item("relative_degree", r)?;
            d.set_item("mean", c.mean)?;
            d.set_item("std", c.std)?;
            d.set_item("c", c.c)?;
            d.set_item("slack", c.slack)?;
            list.append(d)?;
        }
        Ok(list)
    }
    /// Wall time of the whole call in µs (conversions included).
    #[getter]
    fn solve_time_us(&self) -> f64 {
        self.solve_time_us
    }
    fn __repr__(&self, py: Python<'_>) -> String {
        format!(
            "FilterResult(status='{}', u={}, p_star={})",
            self.status,
            self.u.bind(py),
            self.p_star.map_or("None".to_string(), |p| p.to_string())
        )
    }
}

/// The chance-constrained safety filter (paper, Eq. 21 / Sec. V): at each
/// call, the control closest to `u_ref` (in `R`) whose barrier conditions
/// hold with probability `probability` under the model's posterior.
///
/// The filter reads the model at every call, so observations added to it
/// (`MVGP.add_observation`) take effect at the next step. Each condition
/// is the paper's, on the latent `F`, with the variance `moments` gives
/// (as `bayes-cbf control`); `predictive=True` promises it as realised
/// over the step instead, the model's noise `σ²A` in its variance.
#[pyclass(name = "SafetyFilter", module = "bayes_cbf")]
pub struct PySafetyFilter {
    model: Py<PyMvgp>,
    /// The constructor's arguments, validated (what pickling rebuilds the
    /// filter from).
    args: Py<PyTuple>,
    ctrl: SafetyController,
    out: ControlOutput,
    labels: Vec<String>,
    degrees: Vec<usize>,
    x: Vec<f64>,
    u_ref: Vec<f64>,
    xd: Vec<f64>,
    xd_dot: Vec<f64>,
}

#[pymethods]
impl PySafetyFilter {
    #[new]
    #[pyo3(signature = (model, barriers, clf=None, probability=0.99, zeta=0.0, u_min=None, u_max=None, R=None, fallback="max_margin", clf_weight=1.0, predictive=false))]
    #[allow(non_snake_case, clippy::too_many_arguments)]
    fn new(
        #[pyo3(from_py_with = args::model)] model: Bound<'_, PyMvgp>,
        #[pyo3(from_py_with = args::barriers)] barriers: Vec<Bound<'_, PyBarrier>>,
        #[pyo3(from_py_with = args::clf)] clf: Option<Bound<'_, PyClf>>,
        #[pyo3(from_py_with = args::probability)] probability: f64,
        #[pyo3(from_py_with = args::zeta)] zeta: f64,
        u_min: Option<&Bound<'_, PyAny>>,
        u_max: Option<&Bound<'_, PyAny>>,
        R: Option<&Bound<'_, PyAny>>,
        #[pyo3(from_py_with = args::fallback)] fallback: &str,
        #[pyo3(from_py_with = args::clf_weight)] clf_weight: f64,
        #[pyo3(from_py_with = args::predictive)] predictive: bool,
    ) -> PyResult<Self> {
        // a new filter warns anew of what an earlier one was warned of, and
        // its constructor issues what it warns of
        let _warnings = bayes_cbf::warnings::Scope::enter();
        let py = model.py();
        let built = move || -> PyResult<Self> {
            let (n, m) = {
                let mm = crate::models::read(&model, "the model")?;
                (mm.model.state_dim(), mm.model.control_dim())
            };
            let mut bs: Vec<Arc<dyn DynBarrier>> = Vec::new();
            let mut labels = Vec::new();
            {
                let mm = crate::models::read(&model, "the model")?;
                for (i, b) in barriers.iter().enumerate() {
                    let b = b.get();
                    check_barrier(
                        &mm.model,
                        b.barrier.as_ref(),
                        &format!("barriers[{i}] ('{}')", b.label),
                    )
                    .map_err(scenario_err)?;
                    bs.push(b.barrier.clone());
                    labels.push(b.label.clone());
                }
            }
            let clf_arg = clf.clone();
            let clf: Option<Arc<dyn DynLyapunov>> = match clf {
                None => None,
                Some(c) => {
                    let c = c.get();
                    let names = c
                        .state
                        .clone()
                        .unwrap_or_else(|| (0..n).map(|i| format!("x{i}")).collect());
                    if names.len() != n {
                        return Err(input_err(format!(
                            "clf: {} state names, the model has {n} states",
                            names.len()
                        )));
                    }
                    Some(c.spec.build(&names).map_err(scenario_err)?)
                }
            };
            let mut settings = SafetySettings::new(m);
            settings.probability = probability;
            settings.zeta = zeta;
            settings.lambda = clf_weight;
            settings.predictive = predictive;
            settings.u_min = u_min.map(|v| vector(v, "u_min", Some(m))).transpose()?;
            settings.u_max = u_max.map(|v| vector(v, "u_max", Some(m))).transpose()?;
            if let Some(r) = R {
                settings.r = square(r, "R", m)?;
            }
            settings.fallback = Fallback::parse(fallback).map_err(core_err)?;
            let args = (
                &model,
                pyo3::types::PyList::new(py, &barriers)?,
                clf_arg,
                probability,
                zeta,
                settings.u_min.clone(),
                settings.u_max.clone(),
                R,
                fallback,
                clf_weight,
                predictive,
            )
                .into_pyobject(py)?
                .unbind();
            let degrees = bs.iter().map(|b| b.relative_degree()).collect();
            let nb = bs.len();
            let ctrl = SafetyController::new(n, m, bs, clf, settings)
                .map_err(|e| core_err(argument_names(e)))?;
            Ok(Self {
                model: model.unbind(),
                args,
                ctrl,
                out: ControlOutput::new(m, nb),
                labels,
                degrees,
                x: vec![0.0; n],
                u_ref: vec![0.0; m],
                xd: vec![0.0; n],
                xd_dot: vec![0.0; n],
            })
        };
        crate::warnings::after(py, built())
    }

    /// Pickling (`pickle`, `copy.deepcopy`, Ray tasks): the constructor's
    /// arguments, the model and the barriers among them. The copy starts
    /// as a new filter (no warm start, warnings anew).
    fn __reduce__<'py>(
        slf: &Bound<'py, Self>,
    ) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyTuple>)> {
        let this = borrow(slf, "this SafetyFilter")?;
        Ok((slf.get_type().into_any(), this.args.bind(slf.py()).clone()))
    }

    /// One filter step at state `x` around the reference control `u_ref`;
    /// `x_d`, `xdot_d` are the CLF's reference state and its derivative
    /// (zeros if absent). Infeasibility is a status, never an exception.
    #[pyo3(signature = (x, u_ref, x_d=None, xdot_d=None))]
    fn filter(
        slf: &Bound<'_, Self>,
        x: &Bound<'_, PyAny>,
        u_ref: &Bound<'_, PyAny>,
        x_d: Option<&Bound<'_, PyAny>>,
        xdot_d: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<PyFilterResult> {
        borrow_mut(slf, "this SafetyFilter")?.filter_step(slf.py(), x, u_ref, x_d, xdot_d)
    }

    /// Median wall time (µs) of the library's filter step at `(x, u_ref)`,
    /// timed in Rust over `repeats` steps without crossing into Python: the
    /// reference for the binding's overhead (`benchmarks/overhead.py`).
    #[pyo3(signature = (x, u_ref, repeats=1000))]
    fn rust_step_time_us(
        slf: &Bound<'_, Self>,
        x: &Bound<'_, PyAny>,
        u_ref: &Bound<'_, PyAny>,
        #[pyo3(from_py_with = args::repeats)] repeats: usize,
    ) -> PyResult<f64> {
        borrow_mut(slf, "this SafetyFilter")?.time_steps(x, u_ref, repeats)
    }

    /// The model the filter reads at every step.
    #[getter]
    fn model(&self, py: Python<'_>) -> Py<PyMvgp> {
        self.model.clone_ref(py)
    }

    /// The barriers' names, in constraint order.
    #[getter]
    fn barrier_names(&self) -> Vec<String> {
        self.labels.clone()
    }

    fn __repr__(&self) -> String {
        let s = self.ctrl.settings();
        format!(
            "SafetyFilter(state_dim={}, control_dim={}, barriers={:?}, clf={}, \
             probability={:?}, zeta={:?}, predictive={})",
            self.x.len(),
            self.u_ref.len(),
            self.labels,
            if self.ctrl.clf().is_some() {
                "True"
            } else {
                "None"
            },
            s.probability,
            s.zeta,
            if s.predictive { "True" } else { "False" }
        )
    }
}

/// The library's settings error under the name of the constructor's
/// argument: `probability` (the library says `controller.probability`, as
/// in a scenario file) and `clf_weight` (the settings' `lambda`).
fn argument_names(e: bayes_cbf::InputError) -> bayes_cbf::InputError {
    match e {
        bayes_cbf::InputError::Invalid {
            field,
            value,
            reason,
        } => {
            let field = match field.as_str() {
                "controller.probability" => "probability".to_string(),
                "lambda" => "clf_weight".to_string(),
                _ => field,
            };
            bayes_cbf::InputError::Invalid {
                field,
                value,
                reason,
            }
        }
        e => e,
    }
}

/// One step of the library's controller on the filter's buffers.
type Step<'a> = dyn FnMut() -> Result<(), bayes_cbf::Error> + 'a;

/// The inputs of a filter step: `x`, `u_ref` and, when given, the CLF
/// reference `x_d` and `xdot_d`.
type StepInputs<'a, 'py> = (
    &'a Bound<'py, PyAny>,
    &'a Bound<'py, PyAny>,
    Option<&'a Bound<'py, PyAny>>,
    Option<&'a Bound<'py, PyAny>>,
);

impl PySafetyFilter {
    /// [`filter`](Self::filter) on the borrowed filter.
    fn filter_step(
        &mut self,
        py: Python<'_>,
        x: &Bound<'_, PyAny>,
        u_ref: &Bound<'_, PyAny>,
        x_d: Option<&Bound<'_, PyAny>>,
        xdot_d: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<PyFilterResult> {
        let started = Instant::now();
        if self.ctrl.clf().is_none() && (x_d.is_some() || xdot_d.is_some()) {
            let given = if x_d.is_some() { "x_d" } else { "xdot_d" };
            return Err(input_err(format!(
                "{given}: a reference for a CLF, but this filter has none (give clf=...)"
            )));
        }
        let stepped = self.with_step((x, u_ref, x_d, xdot_d), |step| step());
        crate::warnings::emit(py)?;
        stepped?;
        let (status, fallback, p_star, violated) = status_parts(&self.out);
        let reports = self
            .labels
            .iter()
            .zip(&self.degrees)
            .zip(&self.out.constraints)
            .map(|((l, r), c)| (l.clone(), *r, *c))
            .collect();
        let u = PyArray1::from_slice(py, &self.out.u);
        // the result is frozen: its control too
        let kw = PyDict::new(py);
        kw.set_item("write", false)?;
        u.call_method("setflags", (), Some(&kw))?;
        let u = u.unbind();
        Ok(PyFilterResult {
            u,
            status,
            p_star,
            fallback,
            violated,
            reports,
            solve_time_us: started.elapsed().as_secs_f64() * 1e6,
        })
    }

    /// [`rust_step_time_us`](Self::rust_step_time_us) on the borrowed filter.
    fn time_steps(
        &mut self,
        x: &Bound<'_, PyAny>,
        u_ref: &Bound<'_, PyAny>,
        repeats: usize,
    ) -> PyResult<f64> {
        let repeats = args::check_repeats(repeats)?;
        self.with_step((x, u_ref, None, None), |step| {
            let mut times = Vec::with_capacity(repeats);
            for _ in 0..repeats {
                let t = Instant::now();
                step()?;
                times.push(t.elapsed().as_secs_f64() * 1e6);
            }
            times.sort_by(f64::total_cmp);
            Ok(times[times.len() / 2])
        })
    }

    /// Copies `x`, `u_ref` and the CLF reference `x_d`, `xdot_d` (zeros
    /// when not given) into the filter's buffers, then calls `run(step)` with the GIL
    /// released, where `step()` is one step of the controller on them into
    /// `self.out`.
    fn with_step<R: Send>(
        &mut self,
        (x, u_ref, x_d, xdot_d): StepInputs<'_, '_>,
        run: impl FnOnce(&mut Step<'_>) -> Result<R, bayes_cbf::Error> + Send,
    ) -> PyResult<R> {
        let py = x.py();
        copy_into(x, "x", &mut self.x)?;
        copy_into(u_ref, "u_ref", &mut self.u_ref)?;
        let with_ref = x_d.is_some() || xdot_d.is_some();
        // an absent reference is zero at this step, whatever an earlier
        // step was given
        for (given, name, buf) in [
            (x_d, "x_d", &mut self.xd),
            (xdot_d, "xdot_d", &mut self.xd_dot),
        ] {
            match given {
                Some(v) => copy_into(v, name, buf)?,
                None => buf.fill(0.0),
            }
        }
        let model = crate::models::read(self.model.bind(py), "the filter's model")?;
        let m = &model.model;
        let Self {
            ctrl,
            out,
            x,
            u_ref,
            xd,
            xd_dot,
            ..
        } = self;
        let reference = with_ref.then_some((xd.as_slice(), xd_dot.as_slice()));
        py.detach(|| run(&mut || ctrl.step(m, x, u_ref, reference, out)))
            .map_err(core_err)
    }
}
