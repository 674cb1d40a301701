"""What one call leaves behind for the next: a CLF reference not given is
zero at that call, warnings are issued by the call that raised them, and a
callback's failure is reported to the thread whose call met it."""

from __future__ import annotations

import threading
import warnings

import numpy as np
import pytest

import bayes_cbf as bc

PENDULUM = {"type": "pendulum", "mass": 1.0, "length": 1.0, "gravity": 10.0}


def clf_filter():
    model = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1, prior_mean=PENDULUM)
    clf = bc.CLF.expression("(x - x_d)^2 + (y - y_d)^2", ["x", "y"], gamma=1.0)
    return lambda: bc.SafetyFilter(model, [], clf=clf)


def test_an_absent_reference_is_zero_whatever_an_earlier_call_gave():
    fresh = clf_filter()
    x, u_ref, zero = [0.3, 0.2], [0.0], [0.0, 0.0]
    want = fresh().filter(x, u_ref, x_d=zero, xdot_d=zero).u
    assert not np.allclose(want, fresh().filter(x, u_ref, x_d=[2.0, -1.0]).u)
    f = fresh()
    f.filter(x, u_ref, x_d=[2.0, -1.0])
    np.testing.assert_array_equal(f.filter(x, u_ref, xdot_d=zero).u, want)
    f.filter(x, u_ref, xdot_d=[5.0, 5.0])
    np.testing.assert_array_equal(f.filter(x, u_ref, x_d=zero).u, want)
    f.filter(x, u_ref, x_d=[2.0, -1.0], xdot_d=[5.0, 5.0])
    np.testing.assert_array_equal(f.filter(x, u_ref).u, want)


def test_warnings_are_issued_by_the_call_that_raised_them():
    """The online-jitter warning is issued once per warning scope, which
    each filter built opens: it comes from the update that raised it, not
    from the next call."""
    model = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 1e-6)
    other = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1, prior_mean=PENDULUM)
    disc = bc.Barrier.disc(2, [0, 1], [0.0, 0.0], 1.0)

    def new_scope():
        bc.SafetyFilter(other, [disc])

    new_scope()
    with pytest.warns(UserWarning, match="jitter"):
        for _ in range(3):
            model.add_observation([0.0, 0.0], [0.0], [1.0, 1.0])
    new_scope()
    with pytest.warns(UserWarning, match="jitter"):
        model.add_observation([0.0, 0.0], [0.0], [1.0, 1.0])  # in this call, not the next
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bc.moments(other, disc, [2.0, 1.0], [0.0])
        new_scope()
        with pytest.raises(UserWarning, match="jitter"):
            model.add_observation([0.0, 0.0], [0.0], [1.0, 1.0])


def test_a_callback_failure_is_reported_to_its_own_thread():
    in_h, b_done = threading.Event(), threading.Event()

    def grad(x):
        if x[0] > 5:
            raise ValueError("bad region")
        return 2 * x

    def h(x):
        if x[0] > 5:  # grad has failed on this thread: let the other call now
            in_h.set()
            b_done.wait(5)
        return x[0] ** 2 + x[1] ** 2 - 1.0

    b = bc.Barrier.callback(h, grad, state_dim=2)
    out = {}

    def failing():
        with pytest.raises(bc.InputError, match="bad region") as e:
            b.gradient([6.0, 0.5])
        out["failing"] = str(e.value)

    def healthy():
        in_h.wait(5)
        try:
            out["healthy"] = b.value([1.5, 0.5])
        finally:
            b_done.set()

    threads = [threading.Thread(target=failing), threading.Thread(target=healthy)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert out["healthy"] == pytest.approx(1.5)
    assert "6.0" in out["failing"]


def test_ctrl_c_stops_a_fit_and_leaves_the_hyperparameters():
    """SIGINT during a long fit raises KeyboardInterrupt within a moment,
    not when the fit ends; the model keeps its hyperparameters."""
    import os
    import signal
    import time

    rng = np.random.default_rng(0)
    k = 1500
    X = rng.uniform(-3, 3, (k, 2))
    U = rng.uniform(-2, 2, (k, 1))
    Xd = np.c_[X[:, 1], -10 * np.sin(X[:, 0]) + U[:, 0]] + 0.05 * rng.normal(size=(k, 2))
    m = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1)
    before = (m.lengthscales.copy(), m.A.copy(), m.B.copy(), m.noise_sigma)
    timer = threading.Timer(0.5, lambda: os.kill(os.getpid(), signal.SIGINT))
    started = time.monotonic()
    timer.start()
    # 20 restarts of a 1500-point fit take a minute; one evaluation, 0.1 s
    with pytest.raises(KeyboardInterrupt):
        m.fit(X, U, Xd, max_iters=40, restarts=20)
    elapsed = time.monotonic() - started
    timer.join()
    assert elapsed < 5.0, elapsed
    after = (m.lengthscales, m.A, m.B, m.noise_sigma)
    for a, b in zip(before, after):
        np.testing.assert_array_equal(a, b)
    assert len(m) == k


def test_other_threads_read_a_model_while_it_is_fitted():
    """A fit runs on a copy: meanwhile another thread predicts and filters
    with the model as it was, and a change (add_observation) is refused
    with a message saying why, not pyo3's "Already mutably borrowed". The
    long fit runs on the main thread, so that the reader can end it with
    SIGINT when it is done."""
    import os
    import signal
    import time

    rng = np.random.default_rng(7)
    k = 1500
    X = rng.uniform(-3, 3, (k, 2))
    U = rng.uniform(-2, 2, (k, 1))
    Xd = np.c_[X[:, 1], -10 * np.sin(X[:, 0]) + U[:, 0]] + 0.05 * rng.normal(size=(k, 2))
    m = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1, prior_mean=PENDULUM,
                known_rows=[0])
    m.add_observation([0.1, 0.2], [0.3], [0.2, -1.0])
    b = bc.Barrier.from_json('{"type": "pendulum_sector", "theta_c": 0.7854, '
                             '"delta": 0.3927, "relative_degree": 2, "k_alpha": [1.0, 3.0]}')
    f = bc.SafetyFilter(m, [b])
    xq, x, u_ref = np.array([[0.3, -0.2]]), [0.0, 0.1], [2.0]
    want_mean, want_b = m.predict(xq)
    want_u = f.filter(x, u_ref).u
    seen: dict = {}

    def reader():
        try:
            time.sleep(0.5)
            seen["mean"], seen["B"] = m.predict(xq)
            seen["u"] = f.filter(x, u_ref).u
            seen["len"], seen["A"] = len(m), m.A
            for change in (lambda: m.add_observation([0.0, 0.0], [0.0], [0.0, 0.0]),
                           lambda: m.fit(X[:5], U[:5], Xd[:5])):
                try:
                    change()
                except RuntimeError as e:
                    seen.setdefault("refused", []).append(str(e))
        finally:
            os.kill(os.getpid(), signal.SIGINT)

    t = threading.Thread(target=reader)
    t.start()
    with pytest.raises(KeyboardInterrupt):
        m.fit(X, U, Xd, max_iters=40, restarts=20)
    t.join()
    np.testing.assert_array_equal(seen["mean"], want_mean)
    np.testing.assert_array_equal(seen["B"], want_b)
    np.testing.assert_array_equal(seen["u"], want_u)
    np.testing.assert_array_equal(seen["A"], np.eye(2))
    assert not np.array_equal(want_u, u_ref)
    assert seen["len"] == 1
    assert len(seen["refused"]) == 2, seen["refused"]
    assert "this MVGP is being fitted by another thread's call" in seen["refused"][0]
    assert "this model is being fitted by another thread's call" in seen["refused"][1]
    # the interrupted fit left its data, and the model takes changes again
    assert len(m) == k
    m.add_observation([0.0, 0.0], [0.0], [0.0, 0.0])
    assert len(m) == k + 1


def test_ctrl_c_stops_a_run():
    """SIGINT during a long run raises KeyboardInterrupt before its next
    step, not when the run ends."""
    import os
    import signal
    import time

    timer = threading.Timer(0.5, lambda: os.kill(os.getpid(), signal.SIGINT))
    started = time.monotonic()
    timer.start()
    # 200 000 steps of the pendulum take minutes
    with pytest.raises(KeyboardInterrupt):
        bc.run_scenario("pendulum-safe", seed=1, overrides={"steps": 200000})
    timer.join()
    assert time.monotonic() - started < 5.0


def test_ctrl_c_stops_a_calibration_shard():
    """SIGINT during a calibration shard raises KeyboardInterrupt once the
    episodes under way have stopped, not when the shard ends."""
    import os
    import signal
    import time

    from bayes_cbf import _core

    timer = threading.Timer(0.5, lambda: os.kill(os.getpid(), signal.SIGINT))
    started = time.monotonic()
    timer.start()
    # the full calibration takes minutes
    with pytest.raises(KeyboardInterrupt):
        _core.calibration_shard(seed=2)
    timer.join()
    assert time.monotonic() - started < 10.0


def test_a_monte_carlo_condition_reports_its_own_failure():
    """Relative degree 3 (moments from posterior draws on a lattice around
    x): h undefined on the lattice is this step's error, naming the
    barrier, and not a later call's."""
    model = bc.MVGP(3, 1, [1.0] * 3, np.eye(3), np.eye(2), 0.1)
    b = bc.Barrier.expression("log(x) + 5", ["x", "y", "z"], relative_degree=3,
                              k_alpha=[1.0, 3.0, 3.0])
    f = bc.SafetyFilter(model, [b])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the Monte Carlo estimate's cost
        with pytest.raises(bc.InputError, match=r"barriers\[0\]: h of barrier 'log\(x\) \+ 5'"):
            f.filter([0.0005, 0.0, 0.0], [0.0])
    assert b.value([1.0, 0.0, 0.0]) == 5.0


def test_each_call_is_warned_of_its_own_mistakes():
    """A warning is issued once per run, sweep or filter, not once per
    process: a second filter, or a second run, with the same mistake is
    warned of too."""
    import warnings

    prior = {"type": "expression", "state": ["p", "v"], "control": ["F"],
             "f": ["v", "0"], "g": [["0"], ["1"]]}
    model = bc.MVGP(2, 1, [2.0], np.eye(2), np.diag([0.5, 0.01]), 0.1,
                    prior_mean=prior, input_map=[1], known_rows=[0])

    # a wall in p declared relative degree 1: the input has no mean effect
    # on ḣ
    wall = bc.Barrier.expression("2 - p", ["p", "v"], relative_degree=1, alpha=1.0)

    def filter_warnings():
        f = bc.SafetyFilter(model, [wall], u_min=[-3], u_max=[3])
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            f.filter(np.array([1.5, 1.0]), [3.0])
        return [str(x.message) for x in w if "no mean effect" in str(x.message)]

    assert filter_warnings(), "the first filter is warned"
    assert filter_warnings(), "the second filter is warned too"

    def run_warnings():
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            bc.run_scenario("ackermann-no-learning", seed=0, overrides={"steps": 30})
        return [str(x.message) for x in w if "infeasible" in str(x.message)]

    assert run_warnings(), "the first run is warned"
    assert run_warnings(), "the second run is warned too"


def test_a_filter_constructor_issues_its_own_warnings():
    """What building a filter warns of (relax without input bounds) is
    issued by the constructor, not by the next call into the library."""
    model = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1, prior_mean=PENDULUM)
    wall = bc.Barrier.expression("1.2 - q", ["q", "w"], relative_degree=2, k_alpha=[1.0, 2.0])
    with warnings.catch_warnings(record=True) as built:
        warnings.simplefilter("always")
        f = bc.SafetyFilter(model, [wall], fallback="relax")
    assert any("relax without input bounds" in str(w.message) for w in built), built
    with warnings.catch_warnings(record=True) as stepped:
        warnings.simplefilter("always")
        f.filter([0.0, 0.0], [1.0])
    assert not any("relax without input bounds" in str(w.message) for w in stepped)


def test_a_callback_that_changes_the_model_it_serves_is_told_so():
    """A barrier callback that adds data to the model its filter is
    stepping gets an error saying the model is in use, not pyo3's bare
    "Already borrowed"; a callback that calls itself is stopped 32 calls
    deep with a message of bounded length, the whole exception as its
    cause."""
    model = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1, prior_mean=PENDULUM)

    def h(x):
        model.add_observation(x, [0.0], [0.0, 0.0])
        return 1.0 - x[0] ** 2

    b = bc.Barrier.callback(h, lambda x: np.array([-2 * x[0], 0.0]))
    f = bc.SafetyFilter(model, [b])
    with pytest.raises(bc.InputError, match="this MVGP is in use by a call that has not returned") as e:
        f.filter([0.3, 0.0], [0.0])
    assert isinstance(e.value.__cause__, RuntimeError)
    assert len(model) == 0

    holder = {}
    selfish = bc.Barrier.callback(lambda x: holder["b"].value(x), lambda x: np.zeros(2))
    holder["b"] = selfish
    with pytest.raises(bc.InputError) as e:
        selfish.value([0.3, 0.0])
    assert len(str(e.value)) < 1000, len(str(e.value))
    # it stops 32 callbacks deep (the 33rd call's refusal is the last
    # cause), not at Python's recursion limit
    chain = [e.value]
    while chain[-1].__cause__ is not None:
        chain.append(chain[-1].__cause__)
    assert len(chain) == 33, len(chain)
    assert "callbacks nest 32 deep on this thread" in str(chain[-1])
    # the count unwinds: the barrier serves again at depth one
    holder["b"] = bc.Barrier.callback(lambda x: 0.5, lambda x: np.zeros(2))
    assert selfish.value([0.3, 0.0]) == 0.5


def test_known_rows_under_a_zero_prior_mean_are_warned_of():
    """Known rows come from the prior mean: with none given they are
    declared exactly zero, which the constructor says; with a prior mean
    that has them it says nothing."""
    with pytest.warns(UserWarning, match=r"rows \[0\] of F are taken from prior_mean, which is zero"):
        bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1, known_rows=[0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1, prior_mean=PENDULUM, known_rows=[0])
