"""Shared fixtures: the CLI binary (for equality checks), pendulum data, a
fitted pendulum model and the paper's sector barrier."""

from __future__ import annotations

import os
import pathlib
import subprocess

import numpy as np
import pytest

import bayes_cbf as bc

ROOT = pathlib.Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def cli() -> pathlib.Path:
    """The `bayes-cbf` binary of this checkout (built if missing)."""
    target = pathlib.Path(os.environ.get("CARGO_TARGET_DIR", ROOT / "target"))
    exe = target / "release" / "bayes-cbf"
    if not exe.exists():
        subprocess.run(
            ["cargo", "build", "--release", "-p", "bayes-cbf-cli"], cwd=ROOT, check=True
        )
    return exe


def run_cli(cli: pathlib.Path, *args: str) -> str:
    r = subprocess.run([str(cli), *args], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return r.stdout


def pendulum_data(k: int, seed: int = 0):
    """`(X, U, Xdot)` of the paper's pendulum (m = l = 1, g = 10), noisy."""
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-np.pi, np.pi, k), rng.uniform(-3, 3, k)]
    U = rng.uniform(-5, 5, (k, 1))
    Xdot = np.c_[X[:, 1], -10.0 * np.sin(X[:, 0]) + U[:, 0]]
    Xdot += 0.01 * rng.standard_normal(Xdot.shape)
    return X, U, Xdot


@pytest.fixture
def data():
    return pendulum_data(40)


@pytest.fixture(scope="module")
def model() -> bc.MVGP:
    """An MVGP fitted to 40 noisy pendulum observations."""
    X, U, Xdot = pendulum_data(40, seed=2)
    return bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1).fit(X, U, Xdot, max_iters=30)


# The paper's pendulum sector (Sec. VII-A): centre and half-width (rad).
THETA_C, DELTA = 0.7854, 0.3927


def gains(degree: int) -> dict:
    """Class-K gains as keyword arguments: `alpha` for relative degree 1,
    `k_alpha` for 2."""
    return {"alpha": 2.0} if degree == 1 else {"k_alpha": [1.0, 3.0]}


def sector(degree: int) -> bc.Barrier:
    """The built-in sector barrier `cos(DELTA) - cos(theta - THETA_C)` with
    the gains of `gains(degree)`."""
    return bc.Barrier.pendulum_sector(THETA_C, DELTA, relative_degree=degree, **gains(degree))


def assert_same_controls(model: bc.MVGP, a: bc.Barrier, b: bc.Barrier, atol: float) -> None:
    """Safety filters with barrier `a` and with barrier `b` give the same
    status and control at a few pendulum states."""
    f1 = bc.SafetyFilter(model, [a], probability=0.95, u_min=[-10.0], u_max=[10.0])
    f2 = bc.SafetyFilter(model, [b], probability=0.95, u_min=[-10.0], u_max=[10.0])
    for x in ([0.2, 1.0], [1.3, -2.0], [0.5, 0.5]):
        r1, r2 = f1.filter(np.array(x), [5.0]), f2.filter(np.array(x), [5.0])
        assert r1.status == r2.status
        np.testing.assert_allclose(r1.u, r2.u, atol=atol)
