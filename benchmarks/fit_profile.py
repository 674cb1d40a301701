"""Where one likelihood-and-gradient evaluation of a fit spends its time.

Runs `bayes-cbf fit` under callgrind (instruction counts: repeatable on a
shared machine) on two data sets and splits the instructions of the
evaluations into their parts:

- pendulum, k = 500: x = (theta, omega) uniform on [-pi, pi] x [-6, 6],
  u uniform on [-20, 20], xdot of the pendulum (g/l = 10, unit input gain)
  plus N(0, 0.01^2); `--state-dim 2 --control-dim 1`;
- scalar, k = 1000: x uniform on [-3, 3], u = 0, xdot = sin 3x + x/2 +
  N(0, 0.1^2) (an ordinary GP); `--state-dim 1 --control-dim 1`.

Each fit runs 20 L-BFGS iterations from the data-driven start.

    python3 benchmarks/fit_profile.py [--binary target/release/bayes-cbf] [--out docs/fit-profile.json]

Needs valgrind; uses only the standard library.
"""

from __future__ import annotations

import argparse
import json
import math
import random
import re
import subprocess
import sys
import tempfile
from pathlib import Path

# the parts of an evaluation: inclusive costs of these functions (full
# names; callgrind_annotate lists a function once per source file of its
# inlined lines, and the largest of those entries is the whole function)
PARTS = {
    "evaluation": "<bayes_cbf::gp::training::MvgpLikelihood<K> as bayes_cbf::gp::optimise::Objective>::eval",
    "factor": "bayes_cbf::gp::factor::factor_in_place",
    "gram": "bayes_cbf::gp::training::Workspace::factor_gram::{{closure}}",
    "inverse": "bayes_cbf::gp::factor::inverse_in_place",
    "gradient_pass": "<bayes_cbf::gp::kernel::Rbf as bayes_cbf::gp::kernel::Kernel>::add_grad_log_hyper_rows",
}


def inclusive(annotated: str) -> dict[str, int]:
    """Inclusive instructions per function (the largest of its entries)."""
    total: dict[str, int] = {}
    for line in annotated.splitlines():
        m = re.match(r"\s*([\d,]+) \(\s*[\d.]+%\)\s+[^:]*:(.*?)(?: \[.*\])?$", line)
        if m:
            total[m.group(2)] = max(total.get(m.group(2), 0), int(m.group(1).replace(",", "")))
    return total


def pendulum(path: Path, k: int) -> None:
    rng = random.Random(11)
    with path.open("w") as f:
        f.write("x1,x2,u1,xdot1,xdot2\n")
        for _ in range(k):
            th, om, u = rng.uniform(-math.pi, math.pi), rng.uniform(-6, 6), rng.uniform(-20, 20)
            d0 = om + rng.gauss(0, 0.01)
            d1 = -10 * math.sin(th) + u + rng.gauss(0, 0.01)
            f.write(f"{th!r},{om!r},{u!r},{d0!r},{d1!r}\n")


def scalar(path: Path, k: int) -> None:
    rng = random.Random(1000)
    with path.open("w") as f:
        f.write("x1,u1,xdot1\n")
        for _ in range(k):
            x = rng.uniform(-3, 3)
            f.write(f"{x!r},0.0,{math.sin(3 * x) + 0.5 * x + rng.gauss(0, 0.1)!r}\n")


def profile(binary: str, data: Path, n: int, work: Path) -> dict:
    out = work / (data.stem + ".cg")
    run = subprocess.run(
        ["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", binary, "fit",
         "--data", str(data), "--state-dim", str(n), "--control-dim", "1",
         "--max-iters", "20", "--out", str(work / (data.stem + ".json"))],
        capture_output=True, text=True, check=True)
    evaluations = int(re.search(r"(\d+) evaluations", run.stderr).group(1))
    annotated = subprocess.run(["callgrind_annotate", "--inclusive=yes", "--threshold=100", str(out)],
                               capture_output=True, text=True, check=True, cwd=work).stdout
    by_function = inclusive(annotated)
    cost = {name: by_function.get(function, 0) for name, function in PARTS.items()}
    per = {name: value / evaluations for name, value in cost.items()}
    ev = per["evaluation"]
    parts = {
        "gram matrix (kernel values, u^T B u)": per["gram"],
        "Cholesky factorisation": per["factor"] - per["gram"],
        "inverse of the factor": per["inverse"],
        "gradient pass (kernel, B)": per["gradient_pass"],
        "rest (solves for alpha, A, traces)": ev - per["factor"] - per["inverse"] - per["gradient_pass"],
    }
    return {
        "data": data.stem,
        "evaluations": evaluations,
        "instructions_per_evaluation": round(ev),
        "floor_per_evaluation": round(per["factor"] - per["gram"] + per["inverse"]),
        "over_floor": round(ev / (per["factor"] - per["gram"] + per["inverse"]), 3),
        "parts": {name: {"instructions": round(v), "share": round(v / ev, 3)} for name, v in parts.items()},
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--binary", default="target/release/bayes-cbf")
    ap.add_argument("--out")
    a = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        pendulum(work / "pendulum500.csv", 500)
        scalar(work / "scalar1000.csv", 1000)
        for data, n in ((work / "pendulum500.csv", 2), (work / "scalar1000.csv", 1)):
            row = profile(a.binary, data, n, work)
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    text = json.dumps({"tool": "callgrind", "rows": rows}, indent=1)
    if a.out:
        Path(a.out).write_text(text + "\n")
    else:
        print(text)


if __name__ == "__main__":
    main()
