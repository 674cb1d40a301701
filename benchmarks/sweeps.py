"""Throughput of Monte Carlo sweeps: rayon (the CLI) against Ray tasks on
this machine, and a projection of a 10^6-episode calibration on N nodes.

    python benchmarks/sweeps.py [--episodes 6] [--out docs/sweeps.json]

Measured in one run: `bayes-cbf run calibration --episodes E` (rayon, all
cores) and `bayes_cbf.sweep.calibration(episodes=E)` on a local Ray with the
same cores, each repeated and the medians compared.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import subprocess
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]


def cli() -> pathlib.Path:
    target = pathlib.Path(os.environ.get("CARGO_TARGET_DIR", ROOT / "target"))
    exe = target / "release" / "bayes-cbf"
    if not exe.exists():
        subprocess.run(["cargo", "build", "--release", "-p", "bayes-cbf-cli"], cwd=ROOT, check=True)
    return exe


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--episodes", type=int, default=6, help="per (system, truth)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out")
    a = ap.parse_args()
    import ray

    from bayes_cbf import sweep

    cores = os.cpu_count() or 1
    runs = 0  # episode runs: one line of episodes.csv each (controllers x episodes)
    rayon_s, ray_s = [], []
    ray.init(num_cpus=cores, log_to_driver=False)
    sweep.calibration(episodes=1, quick=True)  # warm the workers
    for _ in range(a.repeats):
        with tempfile.TemporaryDirectory() as d:
            t = time.perf_counter()
            subprocess.run([str(cli()), "run", "calibration", "--episodes", str(a.episodes),
                            "--out", d], check=True, capture_output=True)
            rayon_s.append(time.perf_counter() - t)
            with open(pathlib.Path(d) / "episodes.csv") as f:
                runs = sum(1 for _ in f) - 1
        t = time.perf_counter()
        sweep.calibration(episodes=a.episodes, shards=cores)
        ray_s.append(time.perf_counter() - t)
    ray.shutdown()
    r, y = float(np.median(rayon_s)), float(np.median(ray_s))
    per_core = runs / (r * cores)
    # projection: 10^6 episode-runs on N nodes of C cores at the measured
    # per-core rate, with Ray's measured relative overhead
    overhead = y / r
    proj = {
        str(n): {"cores_per_node": 32, "hours": 1e6 / (per_core * 32 * n) * overhead / 3600}
        for n in (1, 10, 100)
    }
    result = {
        "machine": platform.platform(),
        "cores": cores,
        "episode_runs": runs,
        "rayon_s_median": r,
        "ray_s_median": y,
        "episode_runs_per_core_second": per_core,
        "ray_over_rayon": overhead,
        "projection_1e6_runs": proj,
        "rayon_s": rayon_s,
        "ray_s": ray_s,
    }
    print(json.dumps(result, indent=1))
    if a.out:
        pathlib.Path(a.out).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
