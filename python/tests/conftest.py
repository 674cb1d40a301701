"""Shared fixtures: the CLI binary (for equality checks) and pendulum data."""

from __future__ import annotations

import os
import pathlib
import subprocess

import numpy as np
import pytest

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
