"""The package gives what the CLI gives on the same files (interfaces.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import bayes_cbf as bc
from conftest import pendulum_data, run_cli

SECTOR = {"type": "pendulum_sector", "theta_c": 0.7854, "delta": 0.3927,
          "relative_degree": 2, "k_alpha": [1.0, 3.0]}
HALF = {"type": "half_space", "normal": [0.0, 1.0], "offset": -2.0,
        "relative_degree": 1, "alpha": 2.0}


def vec(v) -> str:
    return ",".join(repr(float(a)) for a in np.ravel(v))


@pytest.fixture(scope="module")
def fitted(cli, tmp_path_factory):
    """A model fitted by the CLI on pendulum data, and the same data."""
    d = tmp_path_factory.mktemp("fit")
    X, U, Xdot = pendulum_data(60, seed=1)
    csv = d / "data.csv"
    np.savetxt(csv, np.c_[X, U, Xdot], delimiter=",", fmt="%.17g",
               header="x1,x2,u1,xdot1,xdot2", comments="")
    model = d / "model.json"
    run_cli(cli, "fit", "--data", str(csv), "--state-dim", "2", "--control-dim", "1",
            "--max-iters", "40", "--out", str(model))
    for name, spec in [("sector", SECTOR), ("half", HALF)]:
        (d / f"{name}.json").write_text(json.dumps(spec))
    return d, (X, U, Xdot)


def test_fit_reaches_the_cli_log_likelihood(fitted):
    d, (X, U, Xdot) = fitted
    cli_model = bc.MVGP.load(d / "model.json")
    ours = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1).fit(X, U, Xdot, max_iters=40)
    assert ours.log_marginal_likelihood() >= cli_model.log_marginal_likelihood() - 1e-6
    assert ours.fit_report["log_likelihood"] == pytest.approx(
        ours.log_marginal_likelihood(), abs=1e-9)
    assert len(ours) == 60


def test_predict_equals_the_cli(cli, fitted):
    d, _ = fitted
    model = bc.MVGP.load(d / "model.json")
    xs = np.array([[0.3, -0.2], [2.5, 1.0], [-3.0, 0.0]])
    out = json.loads(run_cli(cli, "predict", "--model", str(d / "model.json"),
                             *sum((["--x", vec(x)] for x in xs), [])))
    mean, B = model.predict(xs)
    assert mean.shape == (3, 2, 2) and B.shape == (3, 2, 2)
    for i, p in enumerate(out["predictions"]):
        np.testing.assert_allclose(mean[i], p["mean"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(B[i], p["B"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(model.A, p["A"], rtol=0, atol=1e-12)


@pytest.mark.parametrize("barrier", ["sector", "half"])
def test_moments_equal_the_cli(cli, fitted, barrier):
    d, _ = fitted
    model = bc.MVGP.load(d / "model.json")
    b = bc.Barrier.load(d / f"{barrier}.json")
    for x, u in [([0.4, 0.1], [1.5]), ([2.0, -1.0], [-3.0])]:
        out = json.loads(run_cli(cli, "moments", "--model", str(d / "model.json"),
                                 "--barrier", str(d / f"{barrier}.json"),
                                 "--x", vec(x), "--u", vec(u)))
        mean, var = bc.moments(model, b, np.array(x), np.array(u))
        assert abs(mean - out["mean"]) <= 1e-12 * max(1, abs(mean))
        assert abs(var - out["variance"]) <= 1e-12 * max(1, abs(var))


def test_control_equals_the_cli(cli, fitted):
    d, _ = fitted
    model = bc.MVGP.load(d / "model.json")
    bs = [bc.Barrier.load(d / "sector.json"), bc.Barrier.load(d / "half.json")]
    filt = bc.SafetyFilter(model, bs, probability=0.9, u_min=[-3.0], u_max=[3.0])
    for x, u_ref in [([0.4, 0.1], [1.5]), ([1.0, -1.9], [-2.0]), ([0.79, 2.5], [3.0])]:
        out = json.loads(run_cli(cli, "control", "--model", str(d / "model.json"),
                                 "--barrier", str(d / "sector.json"),
                                 "--barrier", str(d / "half.json"),
                                 "--x", vec(x), "--probability", "0.9",
                                 "--u-ref", vec(u_ref), "--u-min", "-3", "--u-max", "3"))
        res = filt.filter(np.array(x), np.array(u_ref))
        assert res.status == out["status"]
        np.testing.assert_allclose(res.u, out["u"], rtol=0, atol=1e-12)
        assert res.p_star == out.get("p_star")
        assert res.fallback == out.get("fallback")
        for c, o in zip(res.constraints, out["constraints"]):
            for key in ("mean", "std", "c", "slack"):
                assert abs(c[key] - o[key]) <= 1e-12 * max(1, abs(o[key]))


def test_save_load_round_trip(fitted, tmp_path):
    d, _ = fitted
    model = bc.MVGP.load(d / "model.json")
    model.save(tmp_path / "again.json")
    back = bc.MVGP.load(tmp_path / "again.json")
    assert back.to_json() == model.to_json() == (d / "model.json").read_text()
    assert len(back) == 60
    xs = np.array([[0.3, 0.3], [-1.0, 2.0]])
    for a, b in zip(model.predict(xs), back.predict(xs)):
        np.testing.assert_array_equal(a, b)
    assert back.log_marginal_likelihood() == model.log_marginal_likelihood()


def test_online_updates_match_a_refactorisation(fitted):
    """add_observation / remove_oldest equal building the model on the data."""
    d, _ = fitted
    model = bc.MVGP.load(d / "model.json")
    X, U, Xd = model.X, model.U, model.Xdot
    model.add_observation(np.array([0.5, 0.5]), np.array([1.0]), np.array([0.5, -3.8]))
    model.remove_oldest()
    spec = json.loads(model.to_json())
    direct = bc.MVGP.from_json(json.dumps(spec))
    np.testing.assert_allclose(model.X[:-1], X[1:])
    xs = np.array([[0.0, 0.0], [1.0, -1.0]])
    for a, b in zip(model.predict(xs), direct.predict(xs)):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)


def test_a_budget_keeps_the_most_informative_points(fitted):
    """add_observation_within_budget drops the point with the largest
    [G⁻¹]_jj among the stored ones and the new one."""
    d, _ = fitted
    model = bc.MVGP.load(d / "model.json")
    k = len(model)
    assert model.add_observation_within_budget([0.5, 0.5], [1.0], [0.5, -3.8], k + 1) is None
    assert len(model) == k + 1
    rng = np.random.default_rng(3)
    outcomes = set()
    for _ in range(40):
        x, u = rng.uniform(-3, 3, 2), rng.uniform(-2, 2, 1)
        before = model.X.copy()
        j = model.add_observation_within_budget(x, u, [x[1], -10 * np.sin(x[0]) + u[0]], k + 1)
        assert len(model) == k + 1
        if j == k + 1:
            np.testing.assert_array_equal(model.X, before)
        else:
            np.testing.assert_array_equal(model.X[:-1], np.delete(before, j, axis=0))
            np.testing.assert_array_equal(model.X[-1], x)
        outcomes.add(j == k + 1)
    assert outcomes == {True, False}
    with pytest.raises(bc.InputError, match="budget"):
        model.add_observation_within_budget([0.5, 0.5], [1.0], [0.5, -3.8], 0)


def test_known_rows_fit_equals_the_cli_and_round_trips(cli, fitted, tmp_path):
    d, (X, U, Xdot) = fitted
    prior = {"type": "pendulum", "mass": 1.0, "length": 1.0, "gravity": 10.0}
    run_cli(cli, "fit", "--data", str(d / "data.csv"), "--state-dim", "2", "--control-dim", "1",
            "--max-iters", "30", "--prior-mean", json.dumps(prior), "--known-rows", "0",
            "--out", str(tmp_path / "known.json"))
    theirs = bc.MVGP.load(tmp_path / "known.json")
    ours = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1, prior_mean=prior,
                   known_rows=[0]).fit(X, U, Xdot, max_iters=30)
    assert theirs.known_rows == ours.known_rows == [0]
    assert ours.log_marginal_likelihood() >= theirs.log_marginal_likelihood() - 1e-6
    xs = np.array([[0.4, -1.3], [2.0, 0.5]])
    mean, B = ours.predict(xs)
    # the known row is the prior's, exactly, with zero variance
    np.testing.assert_array_equal(mean[:, 0, 0], xs[:, 1])
    np.testing.assert_array_equal(mean[:, 0, 1], 0.0)
    assert np.all(ours.row_cov[0] == 0) and np.all(ours.row_cov[:, 0] == 0)
    ours.save(tmp_path / "again.json")
    back = bc.MVGP.load(tmp_path / "again.json")
    assert back.known_rows == [0]
    np.testing.assert_array_equal(back.predict(xs)[0], mean)


def test_a_known_row_that_the_data_contradict_warns(fitted):
    """Under a zero prior mean a known row says θ̇ = 0, which the pendulum's
    data contradict: fit warns. The pendulum prior gives the row: no warning."""
    import warnings

    _, (X, U, Xdot) = fitted
    with pytest.warns(UserWarning, match="row 0 of F is declared known"):
        bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1,
                known_rows=[0]).fit(X, U, Xdot, max_iters=5)
    prior = {"type": "pendulum", "mass": 1.0, "length": 1.0, "gravity": 10.0}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1, prior_mean=prior,
                known_rows=[0]).fit(X, U, Xdot, max_iters=5)
