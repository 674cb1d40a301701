"""Arguments of the wrong type or out of range raise `InputError` (a
`ValueError`) whose message names the argument: never a bare `TypeError`,
an `OverflowError` or a message about the library's internal types."""

from __future__ import annotations

import numpy as np
import pytest

import bayes_cbf as bc
from conftest import pendulum_data

I2 = np.eye(2)
X, U, XD = pendulum_data(10, seed=4)


def mvgp(**kw):
    args = dict(state_dim=2, control_dim=1, lengthscales=[0.7, 1.3], A=I2, B=I2, noise_sigma=0.1)
    args.update(kw)
    return bc.MVGP(**args)


def half_space():
    return bc.Barrier.half_space([1.0, 0.0], 0.0)


def raises_naming(field, thunk, *also):
    """`thunk()` raises `InputError` whose message contains `field` and
    each of `also`."""
    with pytest.raises(bc.InputError) as e:
        thunk()
    msg = str(e.value)
    assert field in msg, msg
    for text in also:
        assert text in msg, msg
    return msg


OUT_OF_RANGE = [
    ("state_dim", lambda: mvgp(state_dim=-1), "state_dim = -1: must be ≥ 1"),
    # zero is named as the dimension at fault, not as A's or B's shape
    ("state_dim", lambda: mvgp(state_dim=0), "state_dim = 0: must be ≥ 1"),
    ("control_dim", lambda: mvgp(control_dim=0), "control_dim = 0: must be ≥ 1"),
    ("max_iters", lambda: mvgp().fit(X, U, XD, max_iters=0), "max_iters = 0: must be ≥ 1"),
    ("max_iters", lambda: mvgp().fit(X, U, XD, max_iters=-1), "max_iters = -1"),
    ("seed", lambda: mvgp().fit(X, U, XD, seed=-1), "seed = -1"),
    ("relative_degree", lambda: bc.Barrier.pendulum_sector(0.7, 0.3, relative_degree=-1), "= -1"),
    ("samples", lambda: bc.moments(mvgp(), half_space(), [0.0, 0.0], [0.0], samples=-5), "= -5"),
    ("budget", lambda: mvgp().add_observation_within_budget([0.1, 0.2], [0.5], [0.2, -0.4], -1),
     "= -1"),
    ("known_rows", lambda: mvgp(known_rows=[-1]), "known_rows[0] = -1"),
    ("known_rows", lambda: mvgp(known_rows=[0, 2]), "known_rows[1] = 2"),
    ("seed", lambda: bc.run_scenario("double-integrator", seed=-1), "seed = -1"),
    ("seed", lambda: mvgp().fit(X, U, XD, seed=2**64),
     "seed = 18446744073709551616: too large (at most 2^64 − 1)"),
    ("state_dim", lambda: bc.MVGP(2**70, 1, [1.0], I2, I2, 0.1), "too large"),
]


@pytest.mark.parametrize("field,thunk,text", OUT_OF_RANGE,
                         ids=[f"{c[0]}-{i}" for i, c in enumerate(OUT_OF_RANGE)])
def test_integers_out_of_range_name_the_argument(field, thunk, text):
    raises_naming(field, thunk, text)


WRONG_TYPES = [
    ("noise_sigma", lambda: mvgp(noise_sigma="0.1"), "expected a number, got str"),
    ("noise_sigma", lambda: mvgp(noise_sigma=None), "expected a number, got NoneType"),
    ("noise_sigma", lambda: mvgp(noise_sigma=True), "got bool"),
    ("noise_sigma", lambda: mvgp(noise_sigma=0.1 + 0j), "got complex"),
    ("variance", lambda: mvgp(variance=[1.0]), "expected a number"),
    ("state_dim", lambda: mvgp(state_dim=2.0), "expected an integer, got float"),
    ("state_dim", lambda: mvgp(state_dim=True), "got bool"),
    ("control_dim", lambda: mvgp(control_dim="1"), "expected an integer"),
    ("known_rows", lambda: mvgp(known_rows=[0.0]), "known_rows[0]"),
    ("probability", lambda: bc.SafetyFilter(mvgp(), [half_space()], probability=None), "number"),
    ("zeta", lambda: bc.SafetyFilter(mvgp(), [half_space()], zeta="0"), "number"),
    ("fallback", lambda: bc.SafetyFilter(mvgp(), [half_space()], fallback=3), "string"),
    ("predictive", lambda: bc.SafetyFilter(mvgp(), [half_space()], predictive=1), "True or False"),
    ("model", lambda: bc.SafetyFilter(None, [half_space()]), "MVGP"),
    ("barriers", lambda: bc.SafetyFilter(mvgp(), half_space()), "sequence"),
    ("barriers[0]", lambda: bc.SafetyFilter(mvgp(), [None]), "Barrier"),
    ("params['a']", lambda: bc.Barrier.expression("x", ["x", "y"], params={"a": "s"}), "number"),
    ("state", lambda: bc.Barrier.expression("x", "xy"), "sequence"),
    ("h", lambda: bc.Barrier.expression(None, ["x"]), "string"),
    ("alpha", lambda: bc.Barrier.half_space([1.0], 0.0, alpha="1"), "number"),
    ("k_alpha", lambda: bc.Barrier.pendulum_sector(0.7, 0.3, k_alpha=1.0), "k_alpha"),
    ("theta_c", lambda: bc.Barrier.pendulum_sector(None, 0.3, k_alpha=[1.0, 3.0]), "number"),
    ("edge", lambda: bc.Barrier.pendulum_sector_edge(0.7, 0.3, 1, k_alpha=[1.0, 3.0]), "string"),
    ("indices[1]", lambda: bc.Barrier.disc(2, [0, 1.0], [0.0, 0.0], 1.0), "integer"),
    ("name", lambda: bc.Barrier.callback(lambda x: 0.0, lambda x: x, name=3), "string"),
    ("gamma", lambda: bc.CLF.ackermann(1.0, 1.0, "fast"), "number"),
    ("text", lambda: bc.Barrier.from_json(None), "string"),
    ("path", lambda: bc.MVGP.load(None), "path"),
    ("step", lambda: bc.moments(mvgp(), half_space(), [0.0, 0.0], [0.0], step="a"), "number"),
    ("model", lambda: bc.moments(half_space(), half_space(), [0.0, 0.0], [0.0]), "MVGP"),
    ("seed", lambda: bc.run_scenario("double-integrator", seed=1.5), "expected an integer"),
    ("overrides", lambda: bc.run_scenario("double-integrator", overrides=[("steps", 5)]), "dict"),
    ("rank_b", lambda: mvgp().fit(X, U, XD, rank_b=1.5), "'full', 'diag' or an integer"),
    ("rank_a", lambda: mvgp().fit(X, U, XD, rank_a=None), "'full', 'diag' or an integer"),
]


@pytest.mark.parametrize("field,thunk,text", WRONG_TYPES,
                         ids=[f"{c[0]}-{i}" for i, c in enumerate(WRONG_TYPES)])
def test_wrong_types_are_input_errors_naming_the_argument(field, thunk, text):
    msg = raises_naming(field, thunk, text)
    assert "RankArg" not in msg and "failed to extract" not in msg, msg


def test_numpy_scalars_and_ints_are_accepted():
    m = bc.MVGP(np.int64(2), np.int32(1), [0.7, 1.3], I2, I2, np.float32(0.5), variance=2)
    assert (m.state_dim, m.control_dim, m.variance) == (2, 1, 2.0)
    assert m.noise_sigma == pytest.approx(0.5)
    m.fit(X, U, XD, rank_a=np.int64(1), seed=np.uint64(2**64 - 1), max_iters=np.int16(2))
    b = bc.Barrier.expression("x + a", ("x", "y"), params={"a": np.float64(1.0)}, alpha=np.int8(2))
    assert b.value([1.0, 0.0]) == 2.0
    f = bc.SafetyFilter(m, [b], probability=np.float64(0.9), predictive=np.True_,
                        fallback=np.str_("brake"))
    assert f.filter([0.0, 0.0], [0.0]).status in ("optimal", "infeasible")
    assert bc.Barrier.disc(np.int64(2), np.array([0, 1]), np.zeros(2), 1.0).state_dim == 2


@pytest.mark.parametrize("key,value", [("controller.probability", float("nan")),
                                       ("dt", float("inf")), ("dt", np.float32("-inf"))])
def test_non_finite_overrides_name_the_key(key, value):
    msg = raises_naming(f"overrides['{key}']", lambda: bc.run_scenario(
        "double-integrator", overrides={key: value}), "must be a finite number")
    assert "string" not in msg, msg


@pytest.mark.parametrize("key", ["steps=7 #", "steps 7", "dt#", "barriers..alpha", ""])
def test_override_keys_must_be_dotted_names(key):
    """A key is pasted before '=' in a `key=value` line: "steps=7 #" would
    have set steps to 7 and hidden its value behind a comment."""
    raises_naming(f"overrides['{key}']", lambda: bc.run_scenario(
        "double-integrator", overrides={key: 1}), "not a key")


def test_sweep_overrides_are_converted_as_run_scenarios():
    from bayes_cbf import sweep

    assert sweep._sets({"steps": 5, "gp.prior_mean": {"type": "zero"}}) == [
        "steps=5", 'gp.prior_mean={"type": "zero"}']
    raises_naming("overrides['dt']", lambda: sweep._sets({"dt": float("nan")}), "finite")


def test_scenario_seeds_above_2_63_are_refused_naming_seed():
    raises_naming("seed", lambda: bc.run_scenario("double-integrator", seed=2**63),
                  "seed = 9223372036854775808", "2^63 − 1")
    out = bc.run_scenario("double-integrator", seed=2**63 - 1, overrides={"steps": 2})
    assert len(out["trajectory"]["status"]) == 2


COMPLEX = [
    ("A", lambda: mvgp(A=I2.astype(complex) + 1j)),
    ("B", lambda: mvgp(B=I2.astype(np.complex64))),
    ("lengthscales", lambda: mvgp(lengthscales=[0.7, 1j])),
    ("x", lambda: half_space().value(np.array([1.0, 0.0], dtype=complex))),
    ("grad", lambda: bc.Barrier.callback(
        lambda x: 1.0, lambda x: x.astype(complex)).gradient([1.0, 0.0])),
]


@pytest.mark.parametrize("field,thunk", COMPLEX, ids=[c[0] for c in COMPLEX])
def test_complex_arrays_are_refused(field, thunk):
    raises_naming(field, thunk, "complex values are not accepted")


BOOLEAN = [
    ("A", lambda: mvgp(A=np.eye(2, dtype=bool))),
    ("x", lambda: half_space().value(np.array([True, False]))),
    ("Xq", lambda: mvgp().predict(np.array([[True, False]]))),
]


@pytest.mark.parametrize("field,thunk", BOOLEAN, ids=[c[0] for c in BOOLEAN])
def test_boolean_arrays_are_refused(field, thunk):
    """As a scalar argument refuses True, an array of booleans is not one of
    numbers (a mixed list such as [True, 1.5] is numbers to numpy)."""
    raises_naming(field, thunk, "booleans are not numbers")


TEXT_AND_DATES = [
    ("lengthscales", lambda: mvgp(lengthscales=["1.0", "2.0"]), "strings are not numbers"),
    ("Xq", lambda: mvgp().predict([["0.5", "0.1"]]), "strings are not numbers"),
    ("x", lambda: half_space().value(np.array([0.5, "0.4"], dtype=object)), "strings are not numbers"),
    ("x", lambda: half_space().value(np.array(["2020-01-01", "2020-01-02"], dtype="datetime64[D]")),
     "dates and durations are not numbers"),
    ("u_ref", lambda: bc.SafetyFilter(mvgp(), [half_space()]).filter(
        [0.0, 0.0], np.array([5], dtype="timedelta64[s]")), "dates and durations are not numbers"),
]


@pytest.mark.parametrize("field,thunk,why", TEXT_AND_DATES, ids=[c[0] for c in TEXT_AND_DATES])
def test_string_and_date_arrays_are_refused(field, thunk, why):
    """As a scalar argument refuses "0.1", numpy's reading of strings of
    digits (and of dates, as days since 1970) as numbers is refused."""
    raises_naming(field, thunk, why)


def test_a_kinked_barrier_is_warned_of_by_its_constructor():
    """The warning of a kink in h is issued by Barrier.expression itself,
    not by whichever call comes next."""
    import subprocess
    import sys
    code = (
        "import warnings, bayes_cbf as bc\n"
        "with warnings.catch_warnings(record=True) as w:\n"
        "    warnings.simplefilter('always')\n"
        "    bc.Barrier.expression('min(1 - x, 1 - y)', ['x', 'y'])\n"
        "print(sum('uses min' in str(x.message) for x in w))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "1", out.stdout + out.stderr
