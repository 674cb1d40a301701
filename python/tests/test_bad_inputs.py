"""Bad input raises a typed exception naming the field; the interpreter
survives. Constructors are fuzzed with hypothesis."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import bayes_cbf as bc
from conftest import pendulum_data

I2 = np.eye(2)


def mvgp(**kw):
    args = dict(state_dim=2, control_dim=1, lengthscales=[1.0, 1.0], A=I2, B=I2, noise_sigma=0.1)
    args.update(kw)
    return bc.MVGP(**args)


@pytest.fixture(scope="module")
def model():
    X, U, Xdot = pendulum_data(30, seed=3)
    return mvgp().fit(X, U, Xdot, max_iters=10)


@pytest.fixture(scope="module")
def barrier():
    return bc.Barrier.half_space([0.0, 1.0], -2.0, alpha=1.0)


X, U, XD = pendulum_data(10, seed=4)
NAN2 = np.array([np.nan, 0.0])

# (label, thunk, field named in the message)
CONSTRUCTOR_CASES = [
    ("A wrong shape", lambda: mvgp(A=np.eye(3)), "A"),
    ("B wrong shape", lambda: mvgp(B=np.eye(3)), "B"),
    ("A not PD", lambda: mvgp(A=np.array([[1.0, 2.0], [2.0, 1.0]])), "A"),
    ("B not PD", lambda: mvgp(B=-I2), "B"),
    ("A with NaN", lambda: mvgp(A=np.array([[np.nan, 0], [0, 1.0]])), "A"),
    ("A strings", lambda: mvgp(A=[["a", "b"], ["c", "d"]]), "A"),
    ("A 1-D", lambda: mvgp(A=np.ones(4)), "A"),
    ("lengthscales count", lambda: mvgp(lengthscales=[1.0]), "lengthscales"),
    ("lengthscale negative", lambda: mvgp(lengthscales=[1.0, -1.0]), "lengthscale"),
    ("noise_sigma zero", lambda: mvgp(noise_sigma=0.0), "noise_sigma"),
    ("noise_sigma NaN", lambda: mvgp(noise_sigma=float("nan")), "noise_sigma"),
    ("state_dim zero", lambda: mvgp(state_dim=0, A=np.zeros((0, 0)), lengthscales=[]), "state_dim"),
    ("theta_c NaN", lambda: bc.Barrier.pendulum_sector(float("nan"), 0.3, k_alpha=[1, 3]),
     "theta_c = NaN"),
    ("prior unknown type", lambda: mvgp(prior_mean={"type": "rocket"}), "prior_mean"),
    ("prior unknown key", lambda: mvgp(prior_mean={"type": "pendulum", "mass": 1, "length": 1,
                                                    "gravity": 10, "colour": 3}), "colour"),
    ("input map bad index", lambda: mvgp(input_map=[5], lengthscales=[1.0]), "input_map"),
    ("CoGP Sigma shape", lambda: bc.CoGP(2, 1, [1.0, 1.0], Sigma=np.eye(3)), "Sigma"),
    ("CoGP S not PD", lambda: bc.CoGP(2, 1, [1.0, 1.0], S=-I2), "S"),
    ("model json unknown key", lambda: bc.MVGP.from_json(json.dumps({"state_dim": 1, "junk": 1})), "junk"),
    ("model json malformed", lambda: bc.MVGP.from_json("{not json"), "model"),
    ("barrier unknown type", lambda: bc.Barrier.from_json('{"type": "torus"}'), "torus"),
    ("barrier unknown key", lambda: bc.Barrier.from_json(
        '{"type": "half_space", "normal": [1], "offset": 0, "relative_degree": 1, "alpha": 1, "beta": 2}'), "beta"),
    ("barrier missing gains", lambda: bc.Barrier.pendulum_sector(0.0, 0.3, relative_degree=2), "k_alpha"),
    ("barrier negative gain", lambda: bc.Barrier.half_space([1.0], 0.0, alpha=-1.0), "alpha"),
    ("sector edge unknown", lambda: bc.Barrier.pendulum_sector_edge(0.0, 0.3, "middle", k_alpha=[1.0, 3.0]), "edge"),
    ("callback not callable", lambda: bc.Barrier.callback(3, lambda x: x), "h"),
    ("callback rd2 without hess", lambda: bc.Barrier.callback(
        lambda x: 1.0, lambda x: x, state_dim=2, relative_degree=2, k_alpha=[1.0, 2.0]), "hess"),
    ("clf unknown type", lambda: bc.CLF.from_json('{"type": "quadratic"}'), "clf"),
    ("clf ackermann NaN", lambda: bc.CLF.ackermann(float("nan"), 1.0, 1.0), "w1"),
    ("clf ackermann gamma", lambda: bc.CLF.ackermann(1.0, 1.0, -1.0), "gamma"),
    ("disc centre length", lambda: bc.Barrier.disc(3, [0, 1], [0.0], 1.0), "center"),
    ("disc indices length", lambda: bc.Barrier.disc(3, [0], [0.0, 0.0], 1.0), "indices"),
    ("known rows repeated", lambda: mvgp(known_rows=[0, 0]), "[0, 0]"),
    ("model json key twice", lambda: bc.MVGP.from_json(
        '{"state_dim": 1, "state_dim": 1}'), "given twice"),
]


def model_cases(model, barrier):
    return [
        ("fit X wrong width", lambda: mvgp().fit(X[:, :1], U, XD), "X"),
        ("fit U wrong rows", lambda: mvgp().fit(X, U[:5], XD), "U"),
        ("fit Xdot NaN", lambda: mvgp().fit(X, U, np.where(XD > 0, np.nan, XD)), "Xdot"),
        ("fit rank", lambda: mvgp().fit(X, U, XD, rank_a="half"), "rank_a"),
        ("fit rank negative", lambda: mvgp().fit(X, U, XD, rank_b=-1), "rank_b"),
        ("fit rank above n", lambda: mvgp().fit(X, U, XD, rank_a=5), "rank_a"),
        ("fit no data", lambda: mvgp().fit(np.zeros((0, 2)), np.zeros((0, 1)), np.zeros((0, 2))), "data"),
        ("observation overflows", lambda: mvgp().add_observation([0.1, 0.2], [0.5], [1e300, 0.0]), "xdot"),
        ("fit X object dtype", lambda: mvgp().fit(np.array([[object()] * 2] * 10), U, XD), "X"),
        ("predict wrong width", lambda: model.predict(np.zeros((3, 3))), "Xq"),
        ("predict 1-D", lambda: model.predict(np.zeros(2)), "Xq"),
        ("predict NaN", lambda: model.predict(np.array([[np.nan, 0.0]])), "Xq"),
        ("add_observation x length", lambda: model.add_observation(np.zeros(3), [0.0], np.zeros(2)), "x"),
        ("add_observation NaN u", lambda: model.add_observation(np.zeros(2), [np.nan], np.zeros(2)), "u"),
        ("remove from empty", lambda: mvgp().remove_oldest(), "remove_oldest"),
        ("moments x length", lambda: bc.moments(model, barrier, np.zeros(3), [0.0]), "x"),
        ("moments u NaN", lambda: bc.moments(model, barrier, np.zeros(2), [np.inf]), "u"),
        ("moments barrier dim", lambda: bc.moments(
            model, bc.Barrier.half_space([1.0, 0.0, 0.0], 0.0, alpha=1.0), np.zeros(2), [0.0]), "state dimension"),
        ("filter p = 1", lambda: bc.SafetyFilter(model, [barrier], probability=1.0), "probability"),
        ("filter p = 0", lambda: bc.SafetyFilter(model, [barrier], probability=0.0), "probability"),
        ("filter p < 0.5 rd1", lambda: bc.SafetyFilter(model, [barrier], probability=0.3), "probability"),
        ("filter zeta negative", lambda: bc.SafetyFilter(model, [barrier], zeta=-1.0), "zeta"),
        ("filter R shape", lambda: bc.SafetyFilter(model, [barrier], R=np.eye(2)), "R"),
        ("filter R singular", lambda: bc.SafetyFilter(model, [barrier], R=np.zeros((1, 1))), "R"),
        ("filter one bound", lambda: bc.SafetyFilter(model, [barrier], u_min=[-1.0]), "u_min"),
        ("filter bound length", lambda: bc.SafetyFilter(model, [barrier], u_min=[-1.0, 0], u_max=[1.0]), "u_min"),
        ("filter fallback", lambda: bc.SafetyFilter(model, [barrier], fallback="pray"), "fallback"),
        ("filter x_d without CLF", lambda: bc.SafetyFilter(model, [barrier]).filter(
            np.zeros(2), [0.0], x_d=np.zeros(2)), "x_d"),
        ("moments samples", lambda: bc.moments(model, barrier, np.zeros(2), [0.0], samples=0), "samples"),
        ("moments step", lambda: bc.moments(model, barrier, np.zeros(2), [0.0], step=float("nan")), "step"),
        ("filter clf dims", lambda: bc.SafetyFilter(model, [barrier], clf=bc.CLF.ackermann(1, 1, 1)), "clf"),
        ("filter x NaN", lambda: bc.SafetyFilter(model, [barrier]).filter(NAN2, [0.0]), "x"),
        ("filter u_ref length", lambda: bc.SafetyFilter(model, [barrier]).filter(np.zeros(2), [0.0, 1.0]), "u_ref"),
        ("filter x strings", lambda: bc.SafetyFilter(model, [barrier]).filter(["a", "b"], [0.0]), "x"),
        ("barrier value length", lambda: barrier.value(np.zeros(5)), "x"),
        ("check_derivatives no points", lambda: bc.check_derivatives(lambda x: 0.0, lambda x: x), "state_dim"),
        # a timing of 2**62 runs panicked (capacity overflow), 10**11 aborted
        ("step timing repeats", lambda: bc.SafetyFilter(model, [barrier]).rust_step_time_us(
            np.zeros(2), [0.0], repeats=2**62), "repeats"),
        ("predict timing repeats", lambda: model.rust_predict_time_s(np.zeros((1, 2)), repeats=10**11), "repeats"),
        ("no timing repeats", lambda: model.rust_predict_time_s(np.zeros((1, 2)), repeats=0), "repeats = 0"),
    ]


@pytest.mark.parametrize("label,thunk,field", CONSTRUCTOR_CASES, ids=[c[0] for c in CONSTRUCTOR_CASES])
def test_constructor_bad_input(label, thunk, field):
    with pytest.raises(bc.InputError) as e:
        thunk()
    assert field in str(e.value), f"{label}: {e.value}"
    assert isinstance(e.value, ValueError)


def test_method_bad_inputs(model, barrier):
    cases = model_cases(model, barrier)
    assert len(CONSTRUCTOR_CASES) + len(cases) >= 30
    for label, thunk, field in cases:
        with pytest.raises(bc.InputError) as e:
            thunk()
        assert field in str(e.value), f"{label}: {e.value}"
    # the model is unchanged and usable after all that
    assert len(model) == 30
    assert np.isfinite(model.log_marginal_likelihood())


def test_non_contiguous_arrays_are_read_correctly(model):
    xs = np.asfortranarray(np.array([[0.1, 0.2], [0.3, -0.4], [1.0, 2.0]]))
    strided = np.zeros((3, 4))
    strided[:, ::2] = xs
    view = strided[:, ::2]
    assert not view.flags["C_CONTIGUOUS"]
    for a, b in zip(model.predict(np.ascontiguousarray(xs)), model.predict(view)):
        np.testing.assert_array_equal(a, b)
    a, b = model.predict(xs)
    np.testing.assert_array_equal(a, model.predict(np.ascontiguousarray(xs))[0])
    np.testing.assert_array_equal(b, model.predict(np.ascontiguousarray(xs))[1])


def test_integer_and_list_inputs_are_converted(model):
    m1 = model.predict(np.array([[0, 1]]))
    m2 = model.predict([[0.0, 1.0]])
    np.testing.assert_array_equal(m1[0], m2[0])


def test_infeasible_is_a_status_not_an_exception(model):
    # keep x2 ≥ 5 while x2 = 0 and |u| ≤ 1e-3: impossible
    b = bc.Barrier.half_space([0.0, 1.0], 5.0, alpha=10.0)
    res = bc.SafetyFilter(model, [b], probability=0.9, u_min=[-1e-3], u_max=[1e-3]).filter(
        np.zeros(2), [0.0])
    assert res.status == "infeasible"
    assert res.fallback == "max_margin"
    assert np.all(np.abs(res.u) <= 1e-3 + 1e-9)


finite = st.floats(-1e3, 1e3, allow_nan=False)
anything = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-5, 5),
                     st.text(max_size=3), st.none(), st.lists(finite, max_size=4))


@settings(max_examples=150, deadline=None)
@given(n=st.integers(0, 3), m=st.integers(0, 2), ls=st.lists(anything, max_size=4),
       a=anything, b=anything, sigma=anything)
def test_fuzz_mvgp_constructor(n, m, ls, a, b, sigma):
    try:
        model = bc.MVGP(n, m, ls, a, b, sigma)
    except bc.InputError:
        return
    assert model.state_dim == n and model.control_dim == m


@settings(max_examples=150, deadline=None)
@given(text=st.one_of(st.text(max_size=40), st.dictionaries(
    st.sampled_from(["type", "normal", "offset", "relative_degree", "alpha", "k_alpha", "theta_c",
                     "delta", "junk"]),
    st.one_of(finite, st.integers(-2, 3), st.sampled_from(["half_space", "pendulum_sector", "disc"]),
              st.lists(finite, max_size=3)), max_size=6).map(json.dumps)))
def test_fuzz_barrier_json(text):
    try:
        b = bc.Barrier.from_json(text)
    except bc.InputError:
        return
    assert b.relative_degree >= 1


@settings(max_examples=100, deadline=None)
@given(p=anything, zeta=anything, lo=anything, hi=anything, fallback=st.text(max_size=12))
def test_fuzz_filter_constructor(model, barrier, p, zeta, lo, hi, fallback):
    try:
        f = bc.SafetyFilter(model, [barrier], probability=p, zeta=zeta, u_min=lo, u_max=hi,
                            fallback=fallback)
    except bc.InputError:
        return
    res = f.filter(np.zeros(2), [0.0])
    assert res.status in ("optimal", "infeasible")


def test_a_model_being_fitted_serves_filters_and_moments():
    """`fit` releases the GIL and works on a copy: filter steps and moments
    queries from another thread meanwhile succeed (never a Rust panic, which
    is no `Exception`), and a change to the model raises RuntimeError."""
    import threading

    X, U, Xdot = pendulum_data(150, seed=5)
    m = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1).fit(X, U, Xdot, max_iters=2)
    b = bc.Barrier.pendulum_sector(0.785, 0.393, k_alpha=[1.0, 3.0])
    f = bc.SafetyFilter(m, [b])
    served, refused = 0, 0
    t = threading.Thread(target=lambda: m.fit(X, U, Xdot, max_iters=40, restarts=1))
    t.start()
    while t.is_alive():
        assert f.filter([0.2, 1.5], [1.0]).u.shape == (1,)
        assert np.isfinite(bc.moments(m, b, [0.2, 1.5], [1.0])).all()
        served += 1
        try:
            m.add_observation([0.0, 0.0], [0.0], [0.0, 0.0])
        except RuntimeError as e:
            assert "being fitted by another thread's call" in str(e), e
            refused += 1
    t.join()
    assert served > 0 and refused > 0, (served, refused)


def test_long_expressions_evaluate():
    """A sum of 200 000 terms: the parser accepts chains of any length, and
    the evaluation does not recurse (it used to overflow the stack)."""
    b = bc.Barrier.expression("+".join(["x"] * 200_000), ["x"], alpha=1.0)
    assert b.value([1.5]) == pytest.approx(300_000.0)


def test_results_read_as_python():
    """Reprs and values are Python's: no Rust `Some(...)` or struct dumps;
    a relative-degree-1 built-in barrier given no gain has alpha = 1, as an
    expression barrier; a scenario's status column is a numpy array."""
    X, U, Xdot = pendulum_data(30, seed=3)
    m = mvgp().fit(X, U, Xdot, max_iters=5)
    b = bc.Barrier.half_space([0.0, 1.0], -2.0)
    assert b.gains == [1.0] == bc.Barrier.expression("y + 2", ["x", "y"]).gains
    f = bc.SafetyFilter(m, [b], u_min=[-0.1], u_max=[0.1])
    assert repr(f) == (
        'SafetyFilter(state_dim=2, control_dim=1, barriers=["half_space"], clf=None, '
        "probability=0.99, zeta=0.0, predictive=False)"
    ), repr(f)
    r = f.filter([0.0, -2.5], [0.0])
    assert "Some(" not in repr(r) and "p_star=" in repr(r), repr(r)
    # a CoGP's kernel reads back as an MVGP's
    cogp = bc.CoGP(2, 1, [0.5, 2.0], variance=3.0)
    assert cogp.lengthscales.tolist() == [0.5, 2.0] and cogp.variance == 3.0
    with pytest.raises(ValueError, match="read-only"):
        r.u[0] = 42.0  # a frozen result, its control too
    clf = bc.CLF.ackermann(0.9, 1.5, 10.0)
    assert repr(clf).startswith('CLF({"type":"ackermann"'), repr(clf)
    # an expression CLF's JSON keeps its state names, and reads back
    e = bc.CLF.expression("(x - x_d)^2 + (y - y_d)^2", ["x", "y"])
    back = bc.CLF.from_json(e.to_json())
    assert repr(back) == repr(e) and '"state":["x","y"]' in e.to_json(), e.to_json()
    bc.SafetyFilter(mvgp(), [], clf=back).filter([0.5, 0.0], [0.0], x_d=[0.0, 0.0])
    out = bc.run_scenario("double-integrator", overrides={"steps": 5})
    status = out["trajectory"]["status"]
    assert isinstance(status, np.ndarray) and status.shape == (5,), status


@pytest.mark.parametrize(
    "name,thunk",
    [
        ("state_dim", lambda: mvgp(state_dim=-1)),
        ("known_rows", lambda: mvgp(known_rows=[-1])),
        ("max_iters", lambda: mvgp().fit(X, U, XD, max_iters=-1)),
        ("seed", lambda: mvgp().fit(X, U, XD, seed=-1)),
        ("restarts", lambda: mvgp().fit(X, U, XD, restarts=-1)),
        ("budget", lambda: mvgp().add_observation_within_budget([0.1, 0.2], [0.5], [0.2, -0.4], budget=-1)),
        ("relative_degree", lambda: bc.Barrier.expression("x", ["x"], relative_degree=-1)),
        ("state_dim", lambda: bc.Barrier.disc(-3, [0, 1], [0.0, 0.0], 1.0)),
        ("samples", lambda: bc.moments(mvgp(), bc.Barrier.half_space([1.0, 0.0], 0.0), [0.0, 0.0], [0.0], samples=-1)),
        ("seed", lambda: bc.run_scenario("double-integrator", seed=-1)),
    ],
)
def test_negative_integers_are_input_errors_naming_the_argument(name, thunk):
    with pytest.raises(bc.InputError) as e:
        thunk()
    # the dimensions and max_iters are at least 1, the other counts at least 0
    least = 1 if name in ("state_dim", "max_iters") else 0
    assert name in str(e.value) and f"must be ≥ {least}" in str(e.value), str(e.value)


def test_prior_mean_dicts_take_numpy_numbers_and_refuse_nan():
    prior = {"type": "pendulum", "mass": np.float32(1.0), "length": np.float64(1.0), "gravity": 10}
    assert mvgp(prior_mean=prior).state_dim == 2
    with pytest.raises(bc.InputError, match="prior_mean.*not JSON-serialisable.*finite numbers"):
        mvgp(prior_mean={"type": "pendulum", "mass": float("nan"), "length": 1.0, "gravity": 10.0})


def test_overflows_are_errors_not_non_finite_results():
    """Dimensions that overflowed, lengthscales whose 1/ℓ² overflows, a
    variance·B that overflows, and NaN derivatives are errors."""
    for thunk, field in [
        (lambda: bc.CoGP(2**32, 1, [1.0]), "state_dim"),
        (lambda: bc.CoGP(1, 10**5, [1.0]), "control_dim"),
        (lambda: bc.CoGP(200, 99, [1.0] * 200), "state_dim·(1 + control_dim)"),
        (lambda: bc.MVGP(1, 2**64 - 1, [1.0], [[1.0]], np.zeros((0, 0)), 0.1), "control_dim"),
        (lambda: mvgp(lengthscales=[1e-300, 1.0]), "lengthscales[0]"),
        (lambda: bc.Barrier.expression("sqrt(x)", ["x", "y"]).gradient([0.0, 0.0]), "gradient"),
    ]:
        with pytest.raises(bc.InputError, match=re.escape(field)):
            thunk()
    big = bc.MVGP(1, 1, [1.0], [[1.0]], [[10.0, 0], [0, 10.0]], 0.1, variance=1e308)
    with pytest.raises(bc.NumericalError, match="not finite"):
        big.predict([[0.0]])
    tiny = bc.MVGP(1, 1, [1.0], np.eye(1) * 1e-320, np.eye(2), 0.1)
    tiny.add_observation([0.0], [1.0], [1.0])
    with pytest.raises(bc.NumericalError):
        tiny.log_marginal_likelihood()


def test_an_unresolvable_covariance_is_a_numerical_error():
    """A kernel variance of 1e16 leaves the condition's standard deviation
    below the rounding of its covariance: the filter raises NumericalError
    rather than report an optimum that misses the condition."""
    A = np.array([[1.0, 0.1], [0.1, 0.8]])
    B = np.array([[1.0, 0.2], [0.2, 0.5]])
    m = bc.MVGP(2, 1, [0.7, 1.3], A, B, 0.1, variance=1e16)
    m.add_observation([0.1, 0.2], [0.5], [0.2, -0.4])
    sector = bc.Barrier.pendulum_sector(0.7854, 0.3927, relative_degree=1, alpha=1.0)
    f = bc.SafetyFilter(m, [sector], probability=0.9, u_min=[-5.0], u_max=[5.0])
    with pytest.raises(bc.NumericalError, match="double precision"):
        f.filter([0.1, 0.2], [0.0])


def test_an_unresolved_variance_is_a_numerical_error():
    """At a kernel variance of 1e14 the condition's variance at u = 0.5 is
    below the rounding of its terms: moments raises NumericalError where it
    returned 0."""
    A = np.array([[1.0, 0.1], [0.1, 0.8]])
    B = np.array([[1.0, 0.2], [0.2, 0.5]])
    sector = bc.Barrier.pendulum_sector(0.7854, 0.3927, relative_degree=1, alpha=2.0)
    for variance, resolved in [(1.5, True), (1e14, False)]:
        m = bc.MVGP(2, 1, [0.7, 1.3], A, B, 0.1, variance=variance)
        m.add_observation([0.1, 0.2], [0.5], [0.2, -0.4])
        if resolved:
            assert bc.moments(m, sector, [0.1, 0.2], [0.5])[1] > 0.0
        else:
            with pytest.raises(bc.NumericalError, match="not resolved"):
                bc.moments(m, sector, [0.1, 0.2], [0.5])


def test_a_missing_model_file_is_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere.json"):
        bc.MVGP.load(str(tmp_path / "nowhere.json"))
