"""Cost of the exact relative-degree-2 moments as the robot grows.

One call of `bayes_cbf.moments` (joint posterior of F and its Jacobian at
the state, then the exact mean and variance of the condition, Sec. VI) for
a half-space barrier of relative degree 2 on a model of n states and m
controls with 30 observations; medians over repeated calls.

    python benchmarks/moments_scaling.py [--out moments-scaling.json]
"""

from __future__ import annotations

import argparse
import json
import time
import warnings

import numpy as np

import bayes_cbf as bc

SIZES = [(2, 1), (4, 1), (6, 3), (8, 4), (12, 4), (12, 6), (18, 17)]


def measure(n: int, m: int, repeats: int) -> dict:
    rng = np.random.default_rng(0)
    model = bc.MVGP(n, m, np.ones(n), np.eye(n), np.eye(m + 1), 0.1)
    for _ in range(30):
        model.add_observation(rng.normal(size=n), rng.normal(size=m), rng.normal(size=n))
    normal = np.zeros(n)
    normal[0] = 1.0
    barrier = bc.Barrier.half_space(normal, 5.0, relative_degree=2, k_alpha=[1.0, 2.0])
    x, u = rng.normal(size=n) * 0.1, np.zeros(m)
    mean, var = bc.moments(model, barrier, x, u)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        bc.moments(model, barrier, x, u)
        times.append(time.perf_counter() - t)
    return {"n": n, "m": m, "median_us": 1e6 * float(np.median(times)),
            "repeats": repeats, "mean": mean, "variance": var}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", help="write the rows as JSON here")
    args = ap.parse_args()
    # the model leaves L_g h uncertain: its warning is not what is timed
    warnings.simplefilter("ignore")
    rows = []
    for n, m in SIZES:
        row = measure(n, m, repeats=21 if n * (m + 1) > 100 else 201)
        rows.append(row)
        print(f"n = {n:2d}, m = {m:2d}: {row['median_us']:10.1f} µs")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
