//! `MVGP` and `CoGP`: thin wrappers over [`Mvgp`] and [`Cogp`], the model
//! file (`model.json`) of the scenario crate, and the fits.

use crate::args;
use crate::convert::{
    borrow_mut, core_err, extend_rows, input_err, json_of, json_of_error, matrix, matrix_to_numpy,
    rows, scenario_err, square, to_numpy, vector, with_matrix, NdArray, NumericalError,
};
use bayes_cbf::gp::{
    fit_cogp_until, fit_until, Cogp, CogpFitSettings, CogpHyper, FitReport, FitSettings, Mvgp,
    Posterior, PosteriorWorkspace, Rank, Rbf,
};
use bayes_cbf_scenario::input_map_spec::{to_input_map, FeatureSpec};
use bayes_cbf_scenario::io::write_atomic;
use bayes_cbf_scenario::model_file::ModelFile;
use bayes_cbf_scenario::prior_spec::PriorSpec;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyTuple};
use std::path::PathBuf;

/// Two numpy arrays (the posterior means and covariances of `predict`).
type ArrayPair<'py> = (NdArray<'py>, NdArray<'py>);

/// The prior mean from `None` or a dict in the model file's format.
fn prior_of(obj: Option<&Bound<'_, PyAny>>) -> PyResult<PriorSpec> {
    match obj {
        None => Ok(PriorSpec::default()),
        Some(o) if o.is_none() => Ok(PriorSpec::default()),
        Some(o) => serde_json::from_str(&json_of(o, "prior_mean")?)
            .map_err(|e| input_err(format!("prior_mean: {}", json_of_error(&e)))),
    }
}

/// The input map from `None` or a list in the model file's format.
fn input_map_of(obj: Option<&Bound<'_, PyAny>>) -> PyResult<Option<Vec<FeatureSpec>>> {
    match obj {
        None => Ok(None),
        Some(o) if o.is_none() => Ok(None),
        Some(o) => serde_json::from_str(&json_of(o, "input_map")?)
            .map(Some)
            .map_err(|e| input_err(format!("input_map: {}", json_of_error(&e)))),
    }
}

/// Training data `(X, U, Xdot)` as row-major arrays, shapes checked.
fn data_of(
    x: &Bound<'_, PyAny>,
    u: &Bound<'_, PyAny>,
    xdot: &Bound<'_, PyAny>,
    n: usize,
    m: usize,
) -> PyResult<(Vec<f64>, Vec<f64>, Vec<f64>)> {
    let (xs, k, _) = matrix(x, "X", None, Some(n))?;
    let (us, _, _) = matrix(u, "U", Some(k), Some(m))?;
    let (xd, _, _) = matrix(xdot, "Xdot", Some(k), Some(n))?;
    Ok((xs, us, xd))
}

fn report_dict<'py>(py: Python<'py>, r: &FitReport) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("initial_log_likelihood", r.initial_log_likelihood)?;
    d.set_item("log_likelihood", r.log_likelihood)?;
    d.set_item("evaluations", r.evaluations)?;
    d.set_item("starts", r.starts)?;
    Ok(d)
}

/// The posterior at every row of `Xq (q, n)`, the GIL released: `each(x,
/// means, covs)` appends the mean (`n × p`) and the covariance (`c × c`) at
/// `x`; returned as arrays `(q, n, p)` and `(q, c, c)`.
#[allow(non_snake_case)]
fn predict_rows<'py>(
    Xq: &Bound<'py, PyAny>,
    (n, p, c): (usize, usize, usize),
    mut each: impl FnMut(&[f64], &mut Vec<f64>, &mut Vec<f64>) -> Result<(), bayes_cbf::InputError>
        + Send,
) -> PyResult<ArrayPair<'py>> {
    let py = Xq.py();
    let (q, means, covs) = with_matrix(Xq, "Xq", None, Some(n), |xs, q, _| {
        py.detach(|| -> Result<_, bayes_cbf::InputError> {
            let mut means = Vec::with_capacity(q * n * p);
            let mut covs = Vec::with_capacity(q * c * c);
            for x in xs.chunks(n.max(1)).take(q) {
                each(x, &mut means, &mut covs)?;
            }
            Ok((q, means, covs))
        })
    })?
    .map_err(core_err)?;
    // an overflow of the hyperparameters (variance · B) or data shows here
    if let Some(i) = means.iter().chain(&covs).position(|v| !v.is_finite()) {
        let point = if i < means.len() {
            i / (n * p)
        } else {
            (i - means.len()) / (c * c)
        };
        return Err(NumericalError::new_err(format!(
            "the posterior at Xq[{point}] is not finite: the hyperparameters (variance, A, B) \
             or the data overflow the model's arithmetic"
        )));
    }
    Ok((
        to_numpy(py, means, &[q, n, p])?,
        to_numpy(py, covs, &[q, c, c])?,
    ))
}

/// A posterior workspace of `model` and a posterior to write into.
fn posterior_buffers(model: &Mvgp) -> (PosteriorWorkspace, Posterior) {
    let (n, p) = (model.state_dim(), model.control_dim() + 1);
    let post = Posterior {
        mean: nalgebra::DMatrix::zeros(n, p),
        B: nalgebra::DMatrix::zeros(p, p),
    };
    (model.workspace(), post)
}

/// What a fit warns of: a row declared known that the data contradict
/// ([`Mvgp::known_row_misfit`]).
trait FitWarning {
    fn fit_warning(&self) -> Option<String>;
}

impl FitWarning for Mvgp {
    fn fit_warning(&self) -> Option<String> {
        self.known_row_misfit()
            .filter(|m| m.is_large())
            .map(|m| format!("known_rows: {}", m.describe()))
    }
}

impl FitWarning for Cogp {
    fn fit_warning(&self) -> Option<String> {
        None
    }
}

/// A model's state of fitting ([`IDLE`], [`FITTING`], [`INSTALLING`]),
/// which [`idle`] and [`read`] check.
type FitFlag = std::sync::Arc<std::sync::atomic::AtomicU8>;
/// No fit runs.
const IDLE: u8 = 0;
/// A fit runs on a copy of the model.
const FITTING: u8 = 1;
/// A fit waits to put its result in place: readers wait ([`read`]).
const INSTALLING: u8 = 2;

/// A fit in progress: its model's flag set from [`start`](Self::start)
/// until the fitted copy is back in the object (or the fit is dropped, by
/// an error or a signal).
struct Fitting(FitFlag);

impl Fitting {
    fn start(flag: &FitFlag) -> Self {
        flag.store(FITTING, std::sync::atomic::Ordering::Release);
        Self(flag.clone())
    }

    /// Borrows `obj` mutably to put the fitted copy back, waiting (the GIL
    /// released) while another thread's call reads it; new reads wait
    /// meanwhile ([`read`]), so that a loop of filter steps on another
    /// thread cannot hold the fit off. Ctrl-C while waiting drops the fit.
    fn finish<'py, T: pyo3::PyClass<Frozen = pyo3::pyclass::boolean_struct::False>>(
        self,
        obj: &Bound<'py, T>,
    ) -> PyResult<PyRefMut<'py, T>> {
        self.0
            .store(INSTALLING, std::sync::atomic::Ordering::Release);
        loop {
            if let Ok(slf) = obj.try_borrow_mut() {
                return Ok(slf);
            }
            pause(obj.py())?;
        }
    }
}

/// Releases the GIL for a millisecond, after checking for signals.
fn pause(py: Python<'_>) -> PyResult<()> {
    py.check_signals()?;
    py.detach(|| std::thread::sleep(std::time::Duration::from_millis(1)));
    Ok(())
}

impl Drop for Fitting {
    fn drop(&mut self) {
        self.0.store(IDLE, std::sync::atomic::Ordering::Release);
    }
}

/// Borrows a model to read it (a prediction, a filter step, moments),
/// waiting while a fit puts its result in place.
pub(crate) fn read<'py, T: Fitted>(obj: &Bound<'py, T>, what: &str) -> PyResult<PyRef<'py, T>> {
    loop {
        let slf = crate::convert::borrow(obj, what)?;
        if slf.fit_flag().load(std::sync::atomic::Ordering::Acquire) != INSTALLING {
            return Ok(slf);
        }
        drop(slf);
        pause(obj.py())?;
    }
}

/// A model of `MVGP` or `CoGP`, with its flag of a fit in progress.
pub(crate) trait Fitted:
    pyo3::PyClass<Frozen = pyo3::pyclass::boolean_struct::False>
{
    fn fit_flag(&self) -> &FitFlag;
}

/// Raises `RuntimeError` when another thread's `fit` of `model` has not
/// returned: its result would replace a change made meanwhile.
fn idle<T: Fitted>(model: &T, what: &str) -> PyResult<()> {
    if model.fit_flag().load(std::sync::atomic::Ordering::Acquire) != IDLE {
        return Err(pyo3::exceptions::PyRuntimeError::new_err(format!(
            "{what} is being fitted by another thread's call, whose result would replace \
             this change; change it after that fit returns"
        )));
    }
    Ok(())
}

/// Borrows a model mutably to add or drop an observation, or raises
/// `RuntimeError` when a call holds it or a fit of it runs ([`idle`]).
fn borrow_idle<'py, T: Fitted>(obj: &Bound<'py, T>, what: &str) -> PyResult<PyRefMut<'py, T>> {
    let slf = borrow_mut(obj, what)?;
    idle(&*slf, what)?;
    Ok(slf)
}

/// The `#[pymethods]` that `MVGP` and `CoGP` share: `fit` (named rank
/// settings, then `max_iters`, `seed`, `restarts` and the model's extra
/// settings, with their defaults), `fit_report`, `log_marginal_likelihood`,
/// `state_dim`, `control_dim` and `len`. `$fit` is the library's stoppable fit of the
/// model and `$settings` its settings.
macro_rules! gp_methods {
    (
        $(#[doc = $doc:tt])*
        $class:ident: fit = $fit:ident($settings:ident {
            $rank_1:ident, $rank_2:ident $(, $extra:ident: $ty:ty = $default:tt)*
        }), text_signature = $text:literal
    ) => {
        #[pymethods]
        impl $class {
            $(#[doc = $doc])*
            #[pyo3(text_signature = $text)]
            #[pyo3(signature = (
                X, U, Xdot, $rank_1=Rank::Full, $rank_2=Rank::Full, max_iters=100,
                seed=0, restarts=0 $(, $extra=$default)*
            ))]
            #[allow(non_snake_case, clippy::too_many_arguments)]
            fn fit<'py>(
                obj: &Bound<'py, Self>,
                X: &Bound<'py, PyAny>,
                U: &Bound<'py, PyAny>,
                Xdot: &Bound<'py, PyAny>,
                #[pyo3(from_py_with = args::$rank_1)] $rank_1: Rank,
                #[pyo3(from_py_with = args::$rank_2)] $rank_2: Rank,
                #[pyo3(from_py_with = args::max_iters)] max_iters: u64,
                #[pyo3(from_py_with = args::seed)] seed: u64,
                #[pyo3(from_py_with = args::restarts)] restarts: usize,
                $(#[pyo3(from_py_with = args::$extra)] $extra: $ty,)*
            ) -> PyResult<Bound<'py, Self>> {
                let py = X.py();
                // a copy needs the model read only: a fit starts while
                // another thread's filter step reads it
                let slf = crate::convert::borrow(obj, "this model")?;
                idle(&*slf, "this model")?;
                let fitting = Fitting::start(&slf.fitting);
                let (n, m) = (slf.model.state_dim(), slf.model.control_dim());
                let (xs, us, xd) = data_of(X, U, Xdot, n, m)?;
                let settings = $settings {
                    $rank_1,
                    $rank_2,
                    max_iters,
                    restarts,
                    seed,
                    $($extra,)*
                    ..$settings::default()
                };
                settings.validate().map_err(core_err)?;
                // the fit runs on a copy, the GIL released and the object
                // not borrowed: other threads read (predict, filter) the
                // model as it was, and changes wait for the fit (Fitting)
                let mut model = slf.model.clone();
                drop(slf);
                // Ctrl-C stops the fit (KeyboardInterrupt): the model then
                // holds the new data with its hyperparameters as before
                let (report, signal) = crate::interrupt::interruptible(py, |stop| {
                    model.set_data(&xs, &us, &xd)?;
                    $fit(&mut model, &settings, stop)
                });
                let mut slf = fitting.finish(obj)?;
                slf.model = model;
                // a fit that finished as the signal came keeps its result:
                // the report says so
                if let Ok(r) = &report {
                    slf.last_fit = Some(r.clone());
                }
                let report =
                    crate::warnings::after(py, signal.map(|()| report))?.map_err(core_err)?;
                slf.last_fit = Some(report);
                if let Some(w) = FitWarning::fit_warning(&slf.model) {
                    let msg = std::ffi::CString::new(w).unwrap_or_default();
                    let category = py.get_type::<pyo3::exceptions::PyUserWarning>();
                    PyErr::warn(py, &category, &msg, 1)?;
                }
                Ok(obj.clone())
            }

            /// Report of the last `fit` (`initial_log_likelihood`,
            /// `log_likelihood`, `evaluations`, `starts`), or `None`.
            #[getter]
            fn fit_report<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
                self.last_fit.as_ref().map(|r| report_dict(py, r)).transpose()
            }

            /// `log p(Ẋ | X, U)` under the current hyperparameters.
            fn log_marginal_likelihood(&self, py: Python<'_>) -> PyResult<f64> {
                let v = self.model.log_marginal_likelihood();
                crate::warnings::emit(py)?;
                if !v.is_finite() {
                    return Err(NumericalError::new_err(format!(
                        "the log marginal likelihood is {v}: the data or the \
                         hyperparameters (a covariance that is singular in floating \
                         point, or one that overflows) are outside the model's arithmetic"
                    )));
                }
                Ok(v)
            }

            /// State dimension `n`.
            #[getter]
            fn state_dim(&self) -> usize {
                self.model.state_dim()
            }

            /// Control dimension `m`.
            #[getter]
            fn control_dim(&self) -> usize {
                self.model.control_dim()
            }

            /// The number of observations `k`.
            fn __len__(&self) -> usize {
                self.model.len()
            }

            /// The training states `(k, n)`.
            #[getter(X)]
            fn x<'py>(&self, py: Python<'py>) -> PyResult<NdArray<'py>> {
                let (k, n) = (self.model.len(), self.model.state_dim());
                to_numpy(py, self.model.xs().to_vec(), &[k, n])
            }
            /// The training controls `(k, m)`.
            #[getter(U)]
            fn u<'py>(&self, py: Python<'py>) -> PyResult<NdArray<'py>> {
                let (k, m) = (self.model.len(), self.model.control_dim());
                to_numpy(py, self.model.controls(), &[k, m])
            }
            /// The training derivatives `(k, n)`.
            #[getter(Xdot)]
            fn xdot<'py>(&self, py: Python<'py>) -> PyResult<NdArray<'py>> {
                let (k, n) = (self.model.len(), self.model.state_dim());
                to_numpy(py, self.model.xdot().to_vec(), &[k, n])
            }

            /// Restores what a pickled model carries besides its
            /// constructor's arguments (`__reduce__`): the last fit's
            /// report and, for a CoGP, its data.
            fn __setstate__(&mut self, state: &Bound<'_, PyDict>) -> PyResult<()> {
                self.restore_data(state)?;
                self.last_fit = match state.get_item("fit_report")? {
                    Some(d) if !d.is_none() => Some(report_of(d.cast::<PyDict>()?)?),
                    _ => None,
                };
                Ok(())
            }
        }
    };
}

/// The fit report of a pickled model, from [`report_dict`]'s dict.
fn report_of(d: &Bound<'_, PyDict>) -> PyResult<FitReport> {
    let item = |key: &str| {
        d.get_item(key)?
            .ok_or_else(|| input_err(format!("fit_report.{key}: missing")))
    };
    Ok(FitReport {
        initial_log_likelihood: item("initial_log_likelihood")?.extract()?,
        log_likelihood: item("log_likelihood")?.extract()?,
        evaluations: item("evaluations")?.extract()?,
        starts: item("starts")?.extract()?,
    })
}

/// The state a pickled model carries: the last fit's report, and `extra`.
fn pickled_state<'py>(
    py: Python<'py>,
    report: &Option<FitReport>,
    extra: &[(&str, Bound<'py, PyAny>)],
) -> PyResult<Bound<'py, PyDict>> {
    let state = PyDict::new(py);
    state.set_item(
        "fit_report",
        report.as_ref().map(|r| report_dict(py, r)).transpose()?,
    )?;
    for (k, v) in extra {
        state.set_item(*k, v)?;
    }
    Ok(state)
}

/// Matrix-variate GP model of `F(x) = [f(x) g(x)]` (paper, Sec. IV):
/// `vec F(x) ~ GP(vec M0(x), B k0(x, x') ⊗ A)`, noise `σ² A`.
///
/// `MVGP(state_dim, control_dim, lengthscales, A, B, noise_sigma,
/// prior_mean=None, input_map=None, variance=1.0, known_rows=None)`;
/// `prior_mean` and `input_map` take the values of the model file
/// (`model.json`); `known_rows` lists rows of `F` known exactly from the
/// prior mean (only the others are learned).
#[pyclass(name = "MVGP", module = "bayes_cbf")]
pub struct PyMvgp {
    pub(crate) model: Mvgp,
    prior: PriorSpec,
    /// Report of the last fit.
    last_fit: Option<FitReport>,
    /// Set while a `fit` runs on a copy of `model`.
    fitting: FitFlag,
}

impl Fitted for PyMvgp {
    fn fit_flag(&self) -> &FitFlag {
        &self.fitting
    }
}

impl PyMvgp {
    /// An MVGP's data is in its model file.
    fn restore_data(&mut self, _state: &Bound<'_, PyDict>) -> PyResult<()> {
        Ok(())
    }

    fn from_file(file: &ModelFile) -> PyResult<Self> {
        let model = file.to_model().map_err(scenario_err)?;
        Ok(Self {
            model,
            prior: file.prior_mean.clone(),
            last_fit: None,
            fitting: FitFlag::default(),
        })
    }

    fn file(&self) -> ModelFile {
        ModelFile::from_model(&self.model, &self.prior)
    }
}

gp_methods! {
    /// Learns the hyperparameters by maximising the log marginal likelihood
    /// (L-BFGS) on the data `X (k, n)`, `U (k, m)`, `Xdot (k, n)`, which
    /// replace the model's data. Returns `self`. `sigma_min` floors the noise
    /// standard deviation of state component 0, `noise_sigma·√A[0, 0]`.
    PyMvgp: fit = fit_until(FitSettings { rank_a, rank_b, sigma_min: f64 = 0.0 }),
    text_signature = "($self, X, U, Xdot, rank_a='full', rank_b='full', max_iters=100, seed=0, restarts=0, sigma_min=0.0)"
}

#[pymethods]
impl PyMvgp {
    #[new]
    #[pyo3(signature = (state_dim, control_dim, lengthscales, A, B, noise_sigma, prior_mean=None, input_map=None, variance=1.0, known_rows=None))]
    #[allow(non_snake_case, clippy::too_many_arguments)]
    fn new(
        #[pyo3(from_py_with = args::state_dim)] state_dim: usize,
        #[pyo3(from_py_with = args::control_dim)] control_dim: usize,
        lengthscales: &Bound<'_, PyAny>,
        A: &Bound<'_, PyAny>,
        B: &Bound<'_, PyAny>,
        #[pyo3(from_py_with = args::noise_sigma)] noise_sigma: f64,
        prior_mean: Option<&Bound<'_, PyAny>>,
        input_map: Option<&Bound<'_, PyAny>>,
        #[pyo3(from_py_with = args::variance)] variance: f64,
        #[pyo3(from_py_with = args::known_rows)] known_rows: Option<Vec<usize>>,
    ) -> PyResult<Self> {
        let (n, m) = (state_dim, control_dim);
        bayes_cbf::gp::check_dims(n, m).map_err(core_err)?;
        let ls = vector(lengthscales, "lengthscales", None)?;
        let (a, _, _) = matrix(A, "A", Some(n), Some(n))?;
        let (b, _, _) = matrix(B, "B", Some(m + 1), Some(m + 1))?;
        let file = ModelFile {
            state_dim: n,
            control_dim: m,
            kernel: bayes_cbf_scenario::model_file::KernelSpec::Rbf {
                lengthscales: ls,
                variance,
            },
            A: rows(&a, n),
            B: rows(&b, m + 1),
            noise_sigma,
            prior_mean: prior_of(prior_mean)?,
            input_map: input_map_of(input_map)?,
            known_rows: known_rows.unwrap_or_default(),
            data: Default::default(),
        };
        crate::warnings::after(A.py(), Self::from_file(&file))
    }

    /// Posterior at the rows of `Xq (q, n)`: the means `M_k(x)` as
    /// `(q, n, 1+m)` and `B_k(x, x)` as `(q, 1+m, 1+m)`, with
    /// `Cov(vec F(x)) = B_k(x, x) ⊗ row_cov` (paper, Prop. 1; `row_cov` is
    /// `A` with the known rows' rows and columns zero).
    #[allow(non_snake_case)]
    fn predict<'py>(slf: &Bound<'py, Self>, Xq: &Bound<'py, PyAny>) -> PyResult<ArrayPair<'py>> {
        let this = read(slf, "this MVGP")?;
        let model = &this.model;
        let p = model.control_dim() + 1;
        let (mut ws, mut post) = posterior_buffers(model);
        let rows = predict_rows(Xq, (model.state_dim(), p, p), |x, means, bs| {
            model.posterior_into(x, &mut ws, &mut post)?;
            extend_rows(means, &post.mean);
            extend_rows(bs, &post.B);
            Ok(())
        });
        crate::warnings::after(Xq.py(), rows)
    }

    /// Median wall time (s) of the library computing the posterior at every
    /// row of `Xq` into reused buffers, timed in Rust over `repeats` runs:
    /// the reference for `predict`'s overhead (`benchmarks/overhead.py`).
    #[pyo3(signature = (Xq, repeats=5))]
    #[allow(non_snake_case)]
    fn rust_predict_time_s(
        &self,
        py: Python<'_>,
        Xq: &Bound<'_, PyAny>,
        #[pyo3(from_py_with = args::repeats)] repeats: usize,
    ) -> PyResult<f64> {
        let model = &self.model;
        let n = model.state_dim();
        let (xs, _, _) = matrix(Xq, "Xq", None, Some(n))?;
        let repeats = args::check_repeats(repeats)?;
        py.detach(|| -> Result<f64, bayes_cbf::InputError> {
            let (mut ws, mut post) = posterior_buffers(model);
            let mut times = Vec::with_capacity(repeats);
            for _ in 0..repeats {
                let t = std::time::Instant::now();
                for x in xs.chunks(n) {
                    model.posterior_into(x, &mut ws, &mut post)?;
                }
                std::hint::black_box(&post);
                times.push(t.elapsed().as_secs_f64());
            }
            times.sort_by(f64::total_cmp);
            Ok(times[times.len() / 2])
        })
        .map_err(core_err)
    }

    /// Adds one observation `(x, u, ẋ)`: a rank-one extension of the factor,
    /// O(k²).
    fn add_observation(
        slf: &Bound<'_, Self>,
        x: &Bound<'_, PyAny>,
        u: &Bound<'_, PyAny>,
        xdot: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let mut this = borrow_idle(slf, "this MVGP")?;
        let (n, m) = (this.model.state_dim(), this.model.control_dim());
        let x = vector(x, "x", Some(n))?;
        let u = vector(u, "u", Some(m))?;
        let xd = vector(xdot, "xdot", Some(n))?;
        let added = this.model.add_observation(&x, &u, &xd).map_err(core_err);
        crate::warnings::after(xdot.py(), added)
    }

    /// Adds `(x, u, ẋ)` to a model kept at `budget` observations: the
    /// least informative of the stored points and the new one (smallest
    /// leave-one-out predictive variance) is dropped, O(k²). Returns the
    /// index dropped among the `k + 1` (`k`: the new point was not
    /// stored), `None` below the budget.
    fn add_observation_within_budget(
        slf: &Bound<'_, Self>,
        x: &Bound<'_, PyAny>,
        u: &Bound<'_, PyAny>,
        xdot: &Bound<'_, PyAny>,
        #[pyo3(from_py_with = args::budget)] budget: usize,
    ) -> PyResult<Option<usize>> {
        let mut this = borrow_idle(slf, "this MVGP")?;
        let (n, m) = (this.model.state_dim(), this.model.control_dim());
        let x = vector(x, "x", Some(n))?;
        let u = vector(u, "u", Some(m))?;
        let xd = vector(xdot, "xdot", Some(n))?;
        let added = this
            .model
            .add_observation_within_budget(&x, &u, &xd, budget)
            .map_err(core_err);
        crate::warnings::after(xdot.py(), added)
    }

    /// Drops the oldest observation (sliding window), O(k²).
    fn remove_oldest(slf: &Bound<'_, Self>) -> PyResult<()> {
        let mut this = borrow_idle(slf, "this MVGP")?;
        if this.model.is_empty() {
            return Err(input_err("remove_oldest: the model has no observations"));
        }
        this.model.remove_oldest();
        crate::warnings::after(slf.py(), Ok(()))
    }

    /// Writes the model file (`model.json`, the CLI's format) completely or
    /// not at all, creating its directory if it is missing (as the CLI's
    /// `--out` does).
    fn save(
        &self,
        py: Python<'_>,
        #[pyo3(from_py_with = args::path)] path: PathBuf,
    ) -> PyResult<()> {
        let text = self.file().to_json().map_err(scenario_err)?;
        py.detach(|| write_atomic(&path, text.as_bytes()))
            .map_err(scenario_err)
    }

    /// Reads a model file (`model.json`).
    #[staticmethod]
    fn load(py: Python<'_>, #[pyo3(from_py_with = args::path)] path: PathBuf) -> PyResult<Self> {
        let file = py.detach(|| ModelFile::load(&path)).map_err(scenario_err)?;
        crate::warnings::after(py, Self::from_file(&file))
    }

    /// The model from model-file text.
    #[staticmethod]
    fn from_json(py: Python<'_>, #[pyo3(from_py_with = args::text)] text: &str) -> PyResult<Self> {
        let file = ModelFile::parse(text, "model").map_err(scenario_err)?;
        crate::warnings::after(py, Self::from_file(&file))
    }

    /// The model-file text (hyperparameters and data).
    fn to_json(&self) -> PyResult<String> {
        self.file().to_json().map_err(scenario_err)
    }

    /// Pickling (`pickle`, `copy.deepcopy`, Ray tasks): the model file
    /// (hyperparameters, prior, input map, known rows, data) and the last
    /// fit's report. The copy's posterior equals this one's to rounding.
    #[allow(clippy::type_complexity)]
    fn __reduce__<'py>(
        slf: &Bound<'py, Self>,
    ) -> PyResult<(Bound<'py, PyAny>, (String,), Bound<'py, PyDict>)> {
        let this = crate::convert::borrow(slf, "this MVGP")?;
        let state = pickled_state(slf.py(), &this.last_fit, &[])?;
        Ok((
            slf.get_type().getattr("from_json")?,
            (this.to_json()?,),
            state,
        ))
    }

    /// Row covariance `A` (`n × n`).
    #[getter(A)]
    fn a<'py>(&self, py: Python<'py>) -> PyResult<NdArray<'py>> {
        matrix_to_numpy(py, &self.model.hyper().A)
    }
    /// The row covariance of the posterior, `A` with the known rows and
    /// columns zeroed: `Cov(vec F(x)) = B_k(x, x) ⊗ row_cov`.
    #[getter]
    fn row_cov<'py>(&self, py: Python<'py>) -> PyResult<NdArray<'py>> {
        matrix_to_numpy(py, self.model.row_cov())
    }
    /// Column covariance `B` (`(1+m) × (1+m)`).
    #[getter(B)]
    fn b<'py>(&self, py: Python<'py>) -> PyResult<NdArray<'py>> {
        matrix_to_numpy(py, &self.model.hyper().B)
    }
    /// Kernel lengthscales.
    #[getter]
    fn lengthscales<'py>(&self, py: Python<'py>) -> PyResult<NdArray<'py>> {
        let ls = self.model.hyper().kernel.lengthscales().to_vec();
        let d = ls.len();
        to_numpy(py, ls, &[d])
    }
    /// Rows of `F` known exactly from the prior mean.
    #[getter]
    fn known_rows(&self) -> Vec<usize> {
        self.model.known_rows().to_vec()
    }
    /// Kernel output scale.
    #[getter]
    fn variance(&self) -> f64 {
        self.model.hyper().kernel.variance()
    }
    /// Noise scale `σ`.
    #[getter]
    fn noise_sigma(&self) -> f64 {
        self.model.hyper().sigma
    }
    fn __repr__(&self) -> String {
        format!(
            "MVGP(state_dim={}, control_dim={}, k={}, noise_sigma={:.4e})",
            self.model.state_dim(),
            self.model.control_dim(),
            self.model.len(),
            self.model.hyper().sigma
        )
    }
}

/// Coregionalisation GP baseline (paper, Appendix): `vec F(x) ~ GP(vec
/// M0(x), k0(x, x') Σ)` with noise covariance `S`; fit and predict only
/// (no online updates).
///
/// `CoGP(state_dim, control_dim, lengthscales, Sigma=None, S=None,
/// prior_mean=None, input_map=None, variance=1.0)`; `Sigma` defaults to the
/// identity of size `n(1+m)`, `S` to `0.01 I_n`.
#[pyclass(name = "CoGP", module = "bayes_cbf")]
pub struct PyCogp {
    model: Cogp,
    /// The prior mean and the input map as given (for pickling).
    prior: PriorSpec,
    input_map: Option<Vec<FeatureSpec>>,
    last_fit: Option<FitReport>,
    fitting: FitFlag,
}

impl PyCogp {
    /// Sets the data `X`, `U`, `Xdot` of a pickled CoGP's state.
    fn restore_data(&mut self, state: &Bound<'_, PyDict>) -> PyResult<()> {
        let item = |key: &str| {
            state
                .get_item(key)?
                .ok_or_else(|| input_err(format!("state.{key}: missing")))
        };
        let (n, m) = (self.model.state_dim(), self.model.control_dim());
        let (xs, us, xd) = data_of(&item("X")?, &item("U")?, &item("Xdot")?, n, m)?;
        self.model.set_data(&xs, &us, &xd).map_err(core_err)
    }
}

impl Fitted for PyCogp {
    fn fit_flag(&self) -> &FitFlag {
        &self.fitting
    }
}

gp_methods! {
    /// Learns `Σ`, `S` and the kernel on `X (k, n)`, `U (k, m)`,
    /// `Xdot (k, n)`, which replace the model's data. Returns `self`.
    PyCogp: fit = fit_cogp_until(CogpFitSettings { rank_sigma, rank_s }),
    text_signature = "($self, X, U, Xdot, rank_sigma='full', rank_s='full', max_iters=100, seed=0, restarts=0)"
}

#[pymethods]
impl PyCogp {
    #[new]
    #[pyo3(signature = (state_dim, control_dim, lengthscales, Sigma=None, S=None, prior_mean=None, input_map=None, variance=1.0))]
    #[allow(non_snake_case, clippy::too_many_arguments)]
    fn new(
        #[pyo3(from_py_with = args::state_dim)] state_dim: usize,
        #[pyo3(from_py_with = args::control_dim)] control_dim: usize,
        lengthscales: &Bound<'_, PyAny>,
        Sigma: Option<&Bound<'_, PyAny>>,
        S: Option<&Bound<'_, PyAny>>,
        prior_mean: Option<&Bound<'_, PyAny>>,
        input_map: Option<&Bound<'_, PyAny>>,
        #[pyo3(from_py_with = args::variance)] variance: f64,
    ) -> PyResult<Self> {
        let (n, m) = (state_dim, control_dim);
        if n == 0 || m == 0 {
            return Err(input_err(format!(
                "state_dim = {n}, control_dim = {m}: both must be ≥ 1"
            )));
        }
        let big = bayes_cbf::gp::cogp_outputs(n, m).map_err(core_err)?;
        let sq = |obj: Option<&Bound<'_, PyAny>>, field: &str, d: usize, default: f64| {
            obj.filter(|o| !o.is_none())
                .map(|o| square(o, field, d))
                .unwrap_or_else(|| Ok(nalgebra::DMatrix::identity(d, d) * default))
        };
        let hyper = CogpHyper {
            kernel: Rbf::new(vector(lengthscales, "lengthscales", None)?, variance)
                .map_err(core_err)?,
            Sigma: sq(Sigma, "Sigma", big, 1.0)?,
            S: sq(S, "S", n, 0.01)?,
        };
        let input_map = input_map_of(input_map)?;
        let map = to_input_map(input_map.as_deref());
        let prior = prior_of(prior_mean)?;
        let model =
            Cogp::new(n, m, hyper, prior.to_prior().map_err(scenario_err)?, map).map_err(core_err);
        crate::warnings::after(
            lengthscales.py(),
            model.map(|model| Self {
                model,
                prior,
                input_map,
                last_fit: None,
                fitting: FitFlag::default(),
            }),
        )
    }

    /// Pickling (`pickle`, `copy.deepcopy`, Ray tasks): the constructor's
    /// arguments at the current hyperparameters, then the data and the
    /// last fit's report. The copy's posterior equals this one's to
    /// rounding.
    #[allow(clippy::type_complexity)]
    fn __reduce__<'py>(
        slf: &Bound<'py, Self>,
    ) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyTuple>, Bound<'py, PyDict>)> {
        let py = slf.py();
        let this = crate::convert::borrow(slf, "this CoGP")?;
        let json = |v: Result<String, serde_json::Error>| -> PyResult<Bound<'py, PyAny>> {
            let text = v.map_err(|e| input_err(format!("not JSON: {e}")))?;
            py.import("json")?.call_method1("loads", (text,))
        };
        let args = (
            this.model.state_dim(),
            this.model.control_dim(),
            this.lengthscales(py)?,
            this.sigma(py)?,
            this.s(py)?,
            json(serde_json::to_string(&this.prior))?,
            json(serde_json::to_string(&this.input_map))?,
            this.variance(),
        )
            .into_pyobject(py)?;
        let data = [
            ("X", this.x(py)?),
            ("U", this.u(py)?),
            ("Xdot", this.xdot(py)?),
        ];
        let data = data.map(|(k, v)| (k, v.into_any()));
        let state = pickled_state(py, &this.last_fit, &data)?;
        Ok((slf.get_type().into_any(), args, state))
    }

    /// Posterior at the rows of `Xq (q, n)`: the means `(q, n, 1+m)` and the
    /// full covariances of `vec F(x)` (column-major vec), `(q, n(1+m), n(1+m))`.
    #[allow(non_snake_case)]
    fn predict<'py>(slf: &Bound<'py, Self>, Xq: &Bound<'py, PyAny>) -> PyResult<ArrayPair<'py>> {
        let this = read(slf, "this CoGP")?;
        let model = &this.model;
        let (n, p) = (model.state_dim(), model.control_dim() + 1);
        let rows = predict_rows(Xq, (n, p, n * p), |x, means, covs| {
            let post = model.posterior(x)?;
            extend_rows(means, &post.mean);
            extend_rows(covs, &post.cov);
            Ok(())
        });
        crate::warnings::after(Xq.py(), rows)
    }

    /// Output covariance `Σ` (`n(1+m)` square).
    #[getter(Sigma)]
    fn sigma<'py>(&self, py: Python<'py>) -> PyResult<NdArray<'py>> {
        matrix_to_numpy(py, &self.model.hyper().Sigma)
    }
    /// Noise covariance `S` (`n × n`).
    #[getter(S)]
    fn s<'py>(&self, py: Python<'py>) -> PyResult<NdArray<'py>> {
        matrix_to_numpy(py, &self.model.hyper().S)
    }
    /// Kernel lengthscales.
    #[getter]
    fn lengthscales<'py>(&self, py: Python<'py>) -> PyResult<NdArray<'py>> {
        let ls = self.model.hyper().kernel.lengthscales();
        to_numpy(py, ls.to_vec(), &[ls.len()])
    }
    /// Kernel output scale.
    #[getter]
    fn variance(&self) -> f64 {
        self.model.hyper().kernel.variance()
    }
    fn __repr__(&self) -> String {
        format!(
            "CoGP(state_dim={}, control_dim={}, k={})",
            self.model.state_dim(),
            self.model.control_dim(),
            self.model.len()
        )
    }
}
