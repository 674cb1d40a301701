"""Models, barriers, CLFs and filters pickle (pickle, copy.deepcopy, Ray
tasks): the copy predicts and filters as the original, to rounding, and is
independent of it."""

from __future__ import annotations

import copy
import pickle

import numpy as np
import pytest

import bayes_cbf as bc

PENDULUM = {"type": "pendulum", "mass": 1.0, "length": 1.0, "gravity": 10.0}


def data(k: int = 40, seed: int = 3):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-2, 2, (k, 2))
    U = rng.uniform(-1, 1, (k, 1))
    Xd = np.c_[X[:, 1], -10 * np.sin(X[:, 0]) + U[:, 0]] + 0.01 * rng.normal(size=(k, 2))
    return X, U, Xd


def h(x):
    return 1.0 - x[0] ** 2


def grad_h(x):
    return np.array([-2.0 * x[0], 0.0])


def speed_limit(x):
    return 4.0 - x[1] ** 2


def grad_speed_limit(x):
    return np.array([0.0, -2.0 * x[1]])


def test_an_mvgp_pickles_with_its_data_prior_map_and_fit_report():
    X, U, Xd = data()
    m = bc.MVGP(2, 1, [1.0, 1.0, 1.0], np.eye(2), np.eye(2), 0.1, prior_mean=PENDULUM,
                input_map=[{"cos": 0}, {"sin": 0}, 1], known_rows=[0], variance=1.7)
    m.fit(X, U, Xd, max_iters=5)
    m.add_observation([0.1, 0.2], [0.3], [0.2, -1.0])
    for copied in (pickle.loads(pickle.dumps(m)), copy.deepcopy(m)):
        assert type(copied) is bc.MVGP and len(copied) == len(m)
        assert copied.fit_report == m.fit_report
        assert copied.known_rows == m.known_rows and copied.to_json() == m.to_json()
        for a, b in zip(copied.predict(X[:4]), m.predict(X[:4])):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)
        copied.add_observation([0.0, 0.0], [0.0], [0.0, 0.0])
        assert len(copied) == len(m) + 1
    assert pickle.loads(pickle.dumps(bc.MVGP(1, 1, [1.0], np.eye(1), np.eye(2), 0.1))).fit_report is None


def test_a_cogp_pickles_with_its_data_and_fit_report():
    X, U, Xd = data(20)
    c = bc.CoGP(2, 1, [1.0, 1.0], prior_mean=PENDULUM, variance=2.0).fit(X, U, Xd, max_iters=3)
    c2 = pickle.loads(pickle.dumps(c))
    assert c2.fit_report == c.fit_report and len(c2) == len(c)
    for name in ("X", "U", "Xdot", "Sigma", "S", "lengthscales"):
        np.testing.assert_array_equal(getattr(c2, name), getattr(c, name))
    assert c2.variance == c.variance
    for a, b in zip(c2.predict(X[:3]), c.predict(X[:3])):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)


def test_barriers_and_clfs_pickle_as_they_were_made():
    built = [
        bc.Barrier.pendulum_sector(theta_c=0.785, delta=0.393, relative_degree=2, k_alpha=[1, 3]),
        bc.Barrier.expression(
            "x^2 + y^2 - 1", ["x", "y"], relative_degree=1, alpha=2.0),
        bc.Barrier.callback(h, grad_h, name="mine", alpha=3.0),
    ]
    x = np.array([0.4, -0.3])
    for b in built:
        b2 = pickle.loads(pickle.dumps(b))
        assert (b2.name, b2.state_dim, b2.relative_degree, b2.gains) == (
            b.name, b.state_dim, b.relative_degree, b.gains)
        assert b2.value(x) == b.value(x)
        np.testing.assert_array_equal(b2.gradient(x), b.gradient(x))
        assert b2.to_json() == b.to_json()
    clf = bc.CLF.expression("(x - x_d)^2 + (y - y_d)^2", ["x", "y"], gamma=2.0)
    assert pickle.loads(pickle.dumps(clf)).to_json() == clf.to_json()
    # a lambda is beyond pickle (Ray's cloudpickle writes it)
    with pytest.raises((pickle.PicklingError, AttributeError, TypeError)):
        pickle.dumps(bc.Barrier.callback(lambda x: 1.0, grad_h))


def test_a_filter_pickles_with_its_model_and_settings():
    X, U, Xd = data()
    m = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1, prior_mean=PENDULUM, known_rows=[0])
    m.fit(X, U, Xd, max_iters=5)
    sector = bc.Barrier.pendulum_sector(theta_c=0.785, delta=0.393, relative_degree=2,
                                        k_alpha=[1, 3])
    clf = bc.CLF.expression("(theta - theta_d)^2", ["theta", "omega"])
    limit = bc.Barrier.callback(speed_limit, grad_speed_limit)
    f = bc.SafetyFilter(m, [sector, limit], clf=clf, probability=0.95,
                        zeta=0.01, u_min=[-5.0], u_max=[5.0], R=[[2.0]], fallback="relax",
                        clf_weight=0.5, predictive=True)
    x, u_ref = [0.2, 0.4], [4.0]
    want = f.filter(x, u_ref)
    m2, f2 = pickle.loads(pickle.dumps((m, f)))
    assert f2.model is m2 and f2.barrier_names == f.barrier_names
    got = f2.filter(x, u_ref)
    assert got.status == want.status and got.fallback == want.fallback
    np.testing.assert_allclose(got.u, want.u, rtol=1e-9, atol=1e-12)
    # the copy learns on its own
    m2.add_observation(x, got.u, [0.4, 0.0])
    assert len(m2) == len(m) + 1
