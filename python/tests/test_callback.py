"""Barriers written in Python give the built-ins' moments and controls."""

from __future__ import annotations

import numpy as np
import pytest

import bayes_cbf as bc
from conftest import DELTA, THETA_C, assert_same_controls, gains, sector


def sector_callbacks(theta_c: float, delta: float):
    """h = cos(delta) - cos(theta - theta_c), written by hand."""
    def h(x):
        return np.cos(delta) - np.cos(x[0] - theta_c)

    def grad(x):
        return np.array([np.sin(x[0] - theta_c), 0.0])

    def hess(x):
        return np.array([[np.cos(x[0] - theta_c), 0.0], [0.0, 0.0]])

    return h, grad, hess


@pytest.mark.parametrize("degree", [1, 2])
def test_callback_moments_equal_the_builtin(model, degree):
    builtin = sector(degree)
    h, g, H = sector_callbacks(THETA_C, DELTA)
    cb = bc.Barrier.callback(h, g, H, state_dim=2, relative_degree=degree, **gains(degree))
    rng = np.random.default_rng(0)
    for _ in range(5):
        x, u = rng.uniform(-3, 3, 2), rng.uniform(-5, 5, 1)
        m1, v1 = bc.moments(model, builtin, x, u)
        m2, v2 = bc.moments(model, cb, x, u)
        assert abs(m1 - m2) <= 1e-10 * max(1, abs(m1))
        assert abs(v1 - v2) <= 1e-10 * max(1, abs(v1))
        np.testing.assert_allclose(cb.gradient(x), builtin.gradient(x), atol=1e-12)
        np.testing.assert_allclose(cb.hessian(x), builtin.hessian(x), atol=1e-12)


def test_callback_controls_equal_the_builtin(model):
    builtin = sector(2)
    h, g, H = sector_callbacks(THETA_C, DELTA)
    cb = bc.Barrier.callback(h, g, H, state_dim=2, relative_degree=2, **gains(2))
    assert_same_controls(model, builtin, cb, atol=1e-8)


def test_check_derivatives_accepts_right_and_rejects_wrong():
    h, g, H = sector_callbacks(0.3, 0.2)
    assert bc.check_derivatives(h, g, H, state_dim=2)["ok"]
    wrong = bc.check_derivatives(h, lambda x: 2 * g(x), H, state_dim=2)
    assert not wrong["ok"] and wrong["grad_error"] > 1e-3
    wrong_h = bc.check_derivatives(h, g, lambda x: H(x).T * 0.5, state_dim=2)
    assert not wrong_h["ok"] and wrong_h["hess_error"] > 1e-3


def test_check_derivatives_allows_for_the_rounding_of_a_large_h():
    """h = c + |x|²: the central differences of a value near c round to
    about eps c / step, which no fixed atol covers at every c; a wrong
    gradient is still found when its error exceeds that rounding."""
    for c in (1e6, 1e9, 1e12):
        h = lambda x, c=c: c * (1.0 + x @ x)
        g = lambda x, c=c: 2.0 * c * x
        H = lambda x, c=c: 2.0 * c * np.eye(2)
        assert bc.check_derivatives(h, g, H, state_dim=2)["ok"], c
        assert not bc.check_derivatives(h, lambda x, g=g: 1.01 * g(x), state_dim=2)["ok"], c
    # an offset far above the gradient's scale: at the default step the
    # round-off (0.09) hides the gradient (about 1) at some points, and the
    # check says so rather than pass a wrong one; a larger step resolves it
    # (the error was 5e-3 > atol, a right gradient failed)
    offset = lambda x: 1e9 + x @ x
    at_default = bc.check_derivatives(offset, lambda x: 2.0 * x, state_dim=2)
    assert at_default["unresolved"] > 0 and not at_default["ok"]
    assert bc.check_derivatives(offset, lambda x: 2.0 * x, state_dim=2, step=1e-2)["ok"]
    # a gradient of zeros under an offset of 1e11 (round-off 8.9) is not passed
    wrong = bc.check_derivatives(lambda x: 1e11 + x @ x, lambda x: np.zeros(2), state_dim=2)
    assert not wrong["ok"]
    # a linear h's zero Hessian is resolved, with atol = 0 too
    linear = bc.check_derivatives(lambda x: 3.0 * x[0] - x[1], lambda x: np.array([3.0, -1.0]),
                                  lambda x: np.zeros((2, 2)), state_dim=2, atol=0.0)
    assert linear["ok"] and linear["unresolved"] == 0, linear


def test_a_raising_callback_is_an_input_error_naming_it(model):
    cb = bc.Barrier.callback(lambda x: 1.0 / 0.0, lambda x: np.zeros(2), state_dim=2)
    with pytest.raises(bc.InputError, match="h failed.*ZeroDivisionError"):
        bc.moments(model, cb, np.zeros(2), np.zeros(1))
    nan = bc.Barrier.callback(lambda x: 1.0, lambda x: np.array([np.nan, 0.0]), state_dim=2)
    with pytest.raises(bc.InputError, match="grad returned NaN"):
        bc.moments(model, nan, np.zeros(2), np.zeros(1))
    filt = bc.SafetyFilter(model, [nan], probability=0.9)
    with pytest.raises(bc.InputError, match="grad"):
        filt.filter(np.zeros(2), np.zeros(1))
    # the barrier recovers once its callbacks behave
    assert bc.moments(model, bc.Barrier.callback(
        lambda x: 1.0, lambda x: np.zeros(2), state_dim=2), np.zeros(2), np.zeros(1))[0] > 0


def test_callback_outputs_and_gains_are_checked(model):
    """A Hessian of n² entries in another shape, a bool for h and strings
    for the gradient are refused; alpha and k_alpha together are too, as
    for the built-ins, and relative degree 0 is named."""
    h, g = (lambda x: 1.0 - x @ x), (lambda x: -2 * x)
    flat = bc.Barrier.callback(h, g, lambda x: (-2 * np.eye(2)).reshape(4, 1),
                               relative_degree=2, k_alpha=[1.0, 2.0])
    with pytest.raises(bc.InputError, match=r"hess returned shape \[4, 1\], expected \(2, 2\)"):
        flat.hessian([0.1, 0.2])
    for boolean in (lambda x: True, lambda x: x[0] < 1):  # Python's and numpy's
        with pytest.raises(bc.InputError, match="not a bool"):
            bc.Barrier.callback(boolean, g).value([0.1, 0.2])
    with pytest.raises(bc.InputError, match="strings are not numbers"):
        bc.Barrier.callback(h, lambda x: np.array(["1", "2"])).gradient([0.1, 0.2])
    with pytest.raises(bc.InputError, match="give either alpha or"):
        bc.Barrier.callback(h, g, alpha=2.0, k_alpha=[3.0])
    with pytest.raises(bc.InputError, match="alpha is for relative_degree 1"):
        bc.Barrier.callback(h, g, relative_degree=2, alpha=2.0)
    with pytest.raises(bc.InputError, match="relative_degree = 0: must be ≥ 1"):
        bc.Barrier.callback(h, g, relative_degree=0)
    assert bc.Barrier.callback(h, g).gains == [1.0]
    assert bc.Barrier.callback(h, g, alpha=2.5).gains == [2.5]
    assert bc.Barrier.callback(h, g, k_alpha=[3.0]).gains == [3.0]


def test_sector_edges_are_linear_in_the_angle_from_the_centre():
    tc, d = THETA_C, DELTA
    up = bc.Barrier.pendulum_sector_edge(tc, d, "upper", k_alpha=[1.0, 3.0])
    lo = bc.Barrier.pendulum_sector_edge(tc, d, "lower", k_alpha=[1.0, 3.0])
    for s in np.linspace(d, 2 * np.pi - d, 9):
        for turns in (-1, 0, 1):
            x = np.array([tc + s + 2 * np.pi * turns, 0.4])
            assert abs(up.value(x) - (s - d)) < 1e-12
            assert abs(lo.value(x) - (2 * np.pi - d - s)) < 1e-12
            np.testing.assert_array_equal(up.gradient(x), [1.0, 0.0])
            np.testing.assert_array_equal(lo.gradient(x), [-1.0, 0.0])


def test_callback_exceptions_are_the_cause_and_interrupts_pass_through():
    """A callback's own exception is the `__cause__` of the InputError; a
    KeyboardInterrupt or SystemExit raised in a callback reaches the caller
    as itself (Ctrl-C stops a filter step)."""

    class Mine(RuntimeError):
        pass

    def failing(exc):
        def h(x):
            raise exc

        return bc.Barrier.callback(h, lambda x: np.zeros(2))

    with pytest.raises(bc.InputError) as e:
        failing(Mine("broken")).value([0.0, 0.0])
    assert isinstance(e.value.__cause__, Mine), repr(e.value.__cause__)
    assert "broken" in str(e.value)
    for exc in (KeyboardInterrupt, SystemExit):
        with pytest.raises(exc):
            failing(exc()).value([0.0, 0.0])
    # through a filter step too
    model = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1)
    f = bc.SafetyFilter(model, [failing(KeyboardInterrupt())])
    with pytest.raises(KeyboardInterrupt):
        f.filter([0.1, 0.2], [0.0])
    f = bc.SafetyFilter(model, [failing(Mine("in the loop"))])
    with pytest.raises(bc.InputError) as e:
        f.filter([0.1, 0.2], [0.0])
    assert isinstance(e.value.__cause__, Mine)


def test_check_derivatives_reports_failures_and_refuses_bad_settings():
    h = lambda x: float(x @ x)
    g = lambda x: 2 * x
    good = bc.check_derivatives(h, g, hess=lambda x: 2 * np.eye(2), state_dim=2)
    assert good["ok"] and good["grad_error"] < 1e-6 and good["hess_error"] < 1e-4
    nan = bc.check_derivatives(h, lambda x: np.array([np.nan, 0.0]), state_dim=2)
    assert not nan["ok"] and nan["grad_error"] == np.inf and nan["worst_point"] is not None
    for kw, field in [
        ({"state_dim": 2, "step": 0.0}, "step"),
        ({"state_dim": 0}, "state_dim"),
        ({"points": np.zeros((0, 2))}, "points"),
        ({"points": np.zeros((3, 2)), "state_dim": 3}, "points"),
        ({"state_dim": 2.7}, "state_dim: 2.7 is not an integer"),
        ({"state_dim": "2"}, "state_dim"),
        ({"state_dim": 2, "step": "a"}, "step: 'a' is not a real number"),
        ({"state_dim": 2, "rtol": True}, "rtol"),
    ]:
        with pytest.raises(bc.InputError, match=field):
            bc.check_derivatives(h, g, **kw)
    # numbers of numpy, 0-d arrays and a seed of None are numbers and a seed
    ok = bc.check_derivatives(h, g, state_dim=np.int64(2), step=np.array(1e-5),
                              atol=np.float32(1e-6), seed=None)
    assert ok["ok"]
    # h as Barrier.callback reads it: a float, not an array of one
    with pytest.raises(bc.InputError, match="expected a float"):
        bc.check_derivatives(lambda x: np.array([x @ x]), g, state_dim=2)
    with pytest.raises(bc.InputError, match="h must return a float"):
        bc.Barrier.callback(lambda x: np.array([x @ x]), g).value([1.0, 0.0])


def test_check_derivatives_wraps_a_callbacks_exception():
    h = lambda x: float(x @ x)
    g = lambda x: 2 * x
    for args, name in [((lambda x: 1 / 0, g), "h"), ((h, lambda x: 1 / 0), "grad"),
                       ((h, g, lambda x: 1 / 0), "hess")]:
        with pytest.raises(bc.InputError, match=f"{name} failed at x = ") as e:
            bc.check_derivatives(*args, state_dim=2)
        assert isinstance(e.value.__cause__, ZeroDivisionError)

    def interrupt(x):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        bc.check_derivatives(interrupt, g, state_dim=2)
