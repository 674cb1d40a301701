"""Overhead of the Python binding against the library, measured in one run.

- SafetyFilter.filter against the Rust step (SafetyFilter.rust_step_time_us)
  at k = 200 and 1000 observations: overhead = Python median - Rust median;
- MVGP.predict on 1000 query points against the Rust loop over the same
  points (MVGP.rust_predict_time_s).

    python benchmarks/overhead.py [--out docs/python_overhead.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np

import bayes_cbf as bc


def pendulum_model(k: int, seed: int = 0) -> bc.MVGP:
    rng = np.random.default_rng(seed)
    model = bc.MVGP(2, 1, [0.8, 0.8, 2.0], np.diag([0.01, 4.0]), np.eye(2), 0.05,
                    prior_mean={"type": "pendulum", "mass": 1.0, "length": 1.0, "gravity": 10.0},
                    input_map=[{"cos": 0}, {"sin": 0}, 1])
    for _ in range(k):
        x = np.array([rng.uniform(-np.pi, np.pi), rng.uniform(-4, 4)])
        u = rng.uniform(-5, 5, 1)
        xdot = np.array([x[1], -15 * np.sin(x[0]) + 3 * u[0]]) + 0.01 * rng.standard_normal(2)
        model.add_observation(x, u, xdot)
    return model


def median_us(f, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        f()
        times.append((time.perf_counter() - t) * 1e6)
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=2000)
    ap.add_argument("--out")
    a = ap.parse_args()
    rows = []
    barrier = bc.Barrier.pendulum_sector(np.pi / 4, np.pi / 8, relative_degree=2, k_alpha=[1.0, 3.0])
    x, u_ref = np.array([0.2, 0.5]), np.array([1.0])
    for k in (200, 1000):
        model = pendulum_model(k)
        filt = bc.SafetyFilter(model, [barrier], probability=0.99, u_min=[-20.0], u_max=[20.0])
        for _ in range(50):
            filt.filter(x, u_ref)
        # interleave to share the machine's state
        py, rust = [], []
        for _ in range(5):
            py.append(median_us(lambda: filt.filter(x, u_ref), a.repeats // 5))
            rust.append(filt.rust_step_time_us(x, u_ref, a.repeats // 5))
        py_us, rust_us = float(np.median(py)), float(np.median(rust))
        rows.append({"what": "filter", "k": k, "python_us": py_us, "rust_us": rust_us,
                     "overhead_us": py_us - rust_us})
        xq = np.random.default_rng(1).uniform(-3, 3, (1000, 2))
        py_s = median_us(lambda: model.predict(xq), 7) / 1e6
        rust_s = model.rust_predict_time_s(xq, 7)
        rows.append({"what": "predict_1000", "k": k, "python_s": py_s, "rust_s": rust_s,
                     "ratio": py_s / rust_s})
    result = {"machine": platform.platform(), "rows": rows}
    print(json.dumps(result, indent=1))
    if a.out:
        with open(a.out, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
