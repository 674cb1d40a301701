"""Sweeps on a local Ray (num_cpus=2) equal the CLI's unsharded runs."""

from __future__ import annotations

import json

import numpy as np
import pytest

import bayes_cbf as bc

ray = pytest.importorskip("ray")
from bayes_cbf import sweep  # noqa: E402
from conftest import run_cli  # noqa: E402


@pytest.fixture(scope="module", autouse=True)
def local_ray():
    ray.init(num_cpus=2, ignore_reinit_error=True, log_to_driver=False)
    yield
    ray.shutdown()


def drop(d: dict, *keys: str) -> dict:
    return {k: v for k, v in d.items() if k not in keys}


def test_seed_sweep_on_ray_equals_the_cli(cli, tmp_path):
    run_cli(cli, "run", "pendulum-safe", "--seeds", "2..7", "--set", "steps=40",
            "--out", str(tmp_path))
    theirs = json.loads((tmp_path / "sweep_summary.json").read_text())
    ours = sweep.seeds("pendulum-safe", range(2, 7), overrides={"steps": 40}, shards=3, rows=True)
    assert drop(ours, "timing", "rows") == drop(theirs, "timing")
    assert ours["episodes"] == 5
    csv_ours = [line.split(",")[:6] for line in ours["rows"].splitlines()]
    csv_theirs = [line.split(",")[:6] for line in (tmp_path / "sweep.csv").read_text().splitlines()]
    assert csv_ours == csv_theirs


def test_seeds_that_stop_are_rows_on_ray_as_in_the_cli(cli, tmp_path):
    # the double integrator's barrier with a term 0·sqrt(e) is NaN, an
    # error, where e < 0: at e = 0.5 - p on the seeds whose cart passes
    # p = 0.5 within 3 s, not on the others; at e = -p on every seed
    text = run_cli(cli, "run", "double-integrator", "--print-config")
    assert 'h = "p_max - p"' in text

    def edged(edge: str):
        path = tmp_path / f"cart{len(edge)}.toml"
        path.write_text(text.replace('h = "p_max - p"', f'h = "p_max - p + 0*sqrt({edge})"'))
        return path

    overrides = {"steps": 300}
    run_cli(cli, "run", str(edged("0.5 - p")), "--seeds", "73000..73010", "--set", "steps=300",
            "--out", str(tmp_path / "out"))
    theirs = json.loads((tmp_path / "out" / "sweep_summary.json").read_text())
    ours = sweep.seeds(edged("0.5 - p"), range(73000, 73010), overrides=overrides, shards=2)
    assert drop(ours, "timing") == drop(theirs, "timing")
    assert 0 < ours["stopped"]["count"] < 10
    assert ours["safe"]["count"] + len(ours["unsafe_seeds"]) + ours["stopped"]["count"] == 10
    for s in ours["stopped_seeds"]:
        assert s["error"].startswith("stopped at step") and "NaN at state" in s["error"]
    # every seed stopped: the scenario is at fault
    with pytest.raises(bc.InputError, match="every one of the 4 seeds stopped"):
        sweep.seeds(edged("-p"), range(73000, 73004), overrides=overrides, shards=2)


def test_calibration_on_ray_equals_the_cli(cli, tmp_path):
    run_cli(cli, "run", "calibration", "--quick", "--episodes", "1", "--seed", "3",
            "--fallback", "max_margin", "--out", str(tmp_path))
    theirs = json.loads((tmp_path / "summary.json").read_text())
    ours = sweep.calibration(episodes=1, seed=3, quick=True, shards=2, fallback="max_margin")
    assert ours["fallback"] == "max_margin"
    assert drop(ours, "wall_seconds", "threads", "episodes_csv") == drop(
        theirs, "wall_seconds", "threads")
    assert ours["episodes_csv"] == (tmp_path / "episodes.csv").read_text()


def test_bad_sweeps_are_input_errors():
    with pytest.raises(bc.InputError, match="shards"):
        sweep.seeds("pendulum-safe", range(0, 3), shards=0)
    with pytest.raises(bc.InputError, match="seeds"):
        sweep.seeds("pendulum-safe", [0, 2, 5])
    with pytest.raises(bc.InputError, match="unknown scenario"):
        sweep.seeds("no-such-scenario", range(0, 3))
    with pytest.raises(bc.InputError, match="nosuchkey"):
        sweep.seeds("pendulum-safe", range(0, 3), overrides={"nosuchkey": 1})
    with pytest.raises(bc.InputError, match="episodes"):
        sweep.calibration(episodes=0)
    with pytest.raises(bc.InputError, match="max_margin, brake, hold or relax"):
        bc._core.calibration_shard(0, True, 1, 0, 1, "slow")
    # every argument is checked, naming it, before Ray starts
    for call, field in [
        (lambda: sweep.calibration(seed=-1), "seed = -1"),
        (lambda: sweep.calibration(seed=2**64), "seed"),
        (lambda: sweep.calibration(episodes=1.5), "episodes"),
        (lambda: sweep.calibration(episodes=10**7), "too large"),
        (lambda: sweep.calibration(quick="yes"), "quick"),
        (lambda: sweep.calibration(fallback="slow"), "max_margin, brake, hold or relax"),
        (lambda: sweep.seeds("pendulum-safe", range(-3, 2)), "start = -3"),
        (lambda: sweep.calibration(episodes=-1), "must be ≥ 1"),
        # neither a list of the span nor range's own len() (an OverflowError)
        (lambda: sweep.seeds("pendulum-safe", [0, 10**10]), "consecutive"),
        (lambda: sweep.seeds("pendulum-safe", range(0, 2**70)), "at most 9223372036854775807"),
        (lambda: sweep.seeds("pendulum-safe", range(0, 3), num_cpus=-1), "num_cpus"),
    ]:
        with pytest.raises(bc.InputError, match=field):
            call()
    # seeds are integers: 0.5 and 1.7 were read as seeds 0 and 1
    for bad in ([0.5, 1.7], [True, 2], ["0", "1"]):
        with pytest.raises(bc.InputError, match="not an integer seed"):
            sweep.seeds("pendulum-safe", bad)
    assert sweep._seed_range(np.arange(3, 6)) == (3, 6)


def test_a_filter_and_its_model_go_to_ray_tasks():
    """A fitted model and a filter with a barrier written as lambdas are
    arguments of Ray tasks (cloudpickle): each task filters as the driver."""
    rng = np.random.default_rng(5)
    X = rng.uniform(-2, 2, (30, 2))
    U = rng.uniform(-1, 1, (30, 1))
    Xd = np.c_[X[:, 1], -10 * np.sin(X[:, 0]) + U[:, 0]]
    prior = {"type": "pendulum", "mass": 1.0, "length": 1.0, "gravity": 10.0}
    m = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1, prior_mean=prior,
                known_rows=[0]).fit(X, U, Xd, max_iters=5)
    limit = bc.Barrier.callback(lambda x: 4.0 - x[1] ** 2, lambda x: np.array([0.0, -2.0 * x[1]]))
    f = bc.SafetyFilter(m, [limit], u_min=[-5.0], u_max=[5.0], fallback="relax")
    xs = [[0.1, 1.9], [0.5, -1.95], [-0.3, 0.2]]

    @ray.remote
    def step(filt, x):
        return filt.filter(x, [5.0]).u

    got = ray.get([step.remote(f, x) for x in xs])
    for x, u in zip(xs, got):
        np.testing.assert_allclose(u, f.filter(x, [5.0]).u, rtol=1e-9, atol=1e-12)


def test_unreachable_addresses_are_refused_at_once():
    """An address where nothing listens is a ConnectionError naming it within
    the connect timeout (Ray retries it for minutes); one that listens, and
    Ray's own 'auto', pass."""
    import socket
    import time

    with socket.socket() as closed:
        closed.bind(("127.0.0.1", 0))
        free = closed.getsockname()[1]
    t0 = time.monotonic()
    for address in (f"127.0.0.1:{free}", f"ray://127.0.0.1:{free}", "nowhere.invalid:6379"):
        with pytest.raises(ConnectionError, match="address: no Ray cluster answers at"):
            sweep._reachable(address)
    assert time.monotonic() - t0 < 3 * sweep._CONNECT_TIMEOUT_S
    with socket.socket() as listening:
        listening.bind(("127.0.0.1", 0))
        listening.listen()
        sweep._reachable(f"127.0.0.1:{listening.getsockname()[1]}")
    sweep._reachable("auto")
    for bad, field in [("HEAD:http", "port number"), ("HEAD:0", "port number"),
                       (6379, "must be a string")]:
        with pytest.raises(bc.InputError, match=field):
            sweep._init(bad, None) if not isinstance(bad, str) else sweep._reachable(bad)


def test_numpy_integers_are_shard_counts():
    """A shard count from numpy is an integer, as a seed is."""
    class Cluster:
        @staticmethod
        def cluster_resources():
            return {"CPU": 2}
    assert sweep._shard_count(Cluster, np.int64(4), 10) == 4
    assert sweep._shard_count(Cluster, None, 10) == 2
    with pytest.raises(bc.InputError, match="shards"):
        sweep._shard_count(Cluster, np.float64(4.0), 10)
