"""Barriers, CLFs and prior means written as expressions equal the built-ins
and the Python callbacks; bad expressions raise InputError naming the field."""

from __future__ import annotations

import json

import numpy as np
import pytest

import bayes_cbf as bc
from conftest import DELTA, THETA_C, assert_same_controls, gains, pendulum_data, sector

SECTOR = "cos(delta) - cos(theta - theta_c)"
PARAMS = {"theta_c": THETA_C, "delta": DELTA}


@pytest.mark.parametrize("degree", [1, 2])
def test_expression_barrier_equals_the_builtin(model, degree):
    builtin = sector(degree)
    expr = bc.Barrier.expression(SECTOR, ["theta", "omega"], PARAMS, relative_degree=degree,
                                 **gains(degree))
    assert expr.state_dim == 2 and expr.relative_degree == degree
    rng = np.random.default_rng(1)
    for _ in range(10):
        x, u = rng.uniform(-3, 3, 2), rng.uniform(-5, 5, 1)
        assert abs(expr.value(x) - builtin.value(x)) <= 1e-12
        np.testing.assert_allclose(expr.gradient(x), builtin.gradient(x), atol=1e-12)
        np.testing.assert_allclose(expr.hessian(x), builtin.hessian(x), atol=1e-12)
        m1, v1 = bc.moments(model, builtin, x, u)
        m2, v2 = bc.moments(model, expr, x, u)
        assert abs(m1 - m2) <= 1e-10 * max(1, abs(m1))
        assert abs(v1 - v2) <= 1e-10 * max(1, abs(v1))
    # the barrier file round trip
    again = bc.Barrier.from_json(expr.to_json())
    assert again.value([0.3, 0.1]) == expr.value([0.3, 0.1])


def test_expression_filter_equals_the_builtin(model):
    builtin = sector(2)
    expr = bc.Barrier.expression(SECTOR, ["theta", "omega"], PARAMS, relative_degree=2,
                                 k_alpha=[1.0, 3.0])
    assert_same_controls(model, builtin, expr, atol=1e-9)


def test_expression_prior_mean_equals_the_pendulum_prior():
    X, U, Xdot = pendulum_data(30, seed=4)
    expr_prior = {"type": "expression", "state": ["theta", "omega"], "control": ["u"],
                  "params": {"g": 10.0, "l": 1.0, "m": 1.0},
                  "f": ["omega", "-g/l*sin(theta)"], "g": [["0"], ["1/(m*l)"]],
                  "angles": ["theta"]}
    a = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1, prior_mean={"type": "pendulum"})
    b = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1, prior_mean=expr_prior)
    a.fit(X, U, Xdot, max_iters=20)
    b.fit(X, U, Xdot, max_iters=20)
    Xq = np.random.default_rng(5).uniform(-2, 2, (6, 2))
    ma, Ba = a.predict(Xq)
    mb, Bb = b.predict(Xq)
    np.testing.assert_allclose(ma, mb, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(Ba, Bb, rtol=1e-9, atol=1e-9)


def test_expression_clf_in_the_filter(model):
    clf = bc.CLF.expression("(theta - theta_d)^2 + 0.1*omega^2", ["theta", "omega"], gamma=2.0)
    expr = bc.Barrier.expression(SECTOR, ["theta", "omega"], PARAMS, relative_degree=2,
                                 k_alpha=[1.0, 3.0])
    filt = bc.SafetyFilter(model, [expr], clf=clf, probability=0.9, u_min=[-10.0], u_max=[10.0])
    res = filt.filter(np.array([-0.5, 0.0]), [0.0])
    assert res.status in ("optimal", "infeasible") and np.all(np.isfinite(res.u))


@pytest.mark.parametrize("call, field", [
    (lambda: bc.Barrier.expression("cos(theta - ", ["theta", "omega"]), "h, column 13"),
    (lambda: bc.Barrier.expression("cos(phi)", ["theta", "omega"]), "unknown name 'phi'"),
    (lambda: bc.Barrier.expression("theta", ["theta", "theta"]), "given twice"),
    (lambda: bc.Barrier.expression("theta", ["theta"], relative_degree=2, k_alpha=[0.0, 1.0]),
     "Hurwitz"),
    (lambda: bc.Barrier.expression("theta", ["theta"], {"k": float("nan")}), "params.k"),
    (lambda: bc.CLF.expression("(x - y_d)^2", ["x"]), "unknown name 'y_d'"),
    (lambda: bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1,
                     prior_mean={"type": "expression", "state": ["a", "b"], "control": ["u"],
                                 "f": ["b", "a +"], "g": [["0"], ["1"]]}), "f[1], column 4"),
])
def test_bad_expressions_raise_input_error(call, field):
    with pytest.raises(bc.InputError, match=None) as e:
        call()
    assert field in str(e.value), str(e.value)


def test_non_finite_evaluation_raises(model):
    b = bc.Barrier.expression("log(theta)", ["theta", "omega"])
    with pytest.raises(bc.InputError) as e:
        bc.moments(model, b, np.array([-0.5, 0.0]), np.array([0.0]))
    assert "h of barrier" in str(e.value) and "NaN" in str(e.value)
    assert json.loads(b.to_json())["type"] == "expression"
