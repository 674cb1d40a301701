"""Hyperparameter fits against the peers, measured in one run on one thread.

bayes-cbf (`MVGP.fit`, the library's fit through the Python package),
scikit-learn's `GaussianProcessRegressor` and, when it is installed,
GPyTorch's exact GP on the CPU fit the same data:

- a scalar GP: state_dim 1, control_dim 1 and u = 0, so that the MVGP is an
  ordinary GP with kernel B_00 k0(x, x') and noise variance sigma^2;
- x ~ U(-3, 3), xdot = sin(3x) + x/2 + N(0, 0.1^2), k points from a seed.

Every library fits a squared-exponential kernel with an output scale and a
noise level by maximising the log marginal likelihood, from the same start
(lengthscale = std x, output scale = E xdot^2, noise variance =
0.01 E xdot^2), with one start and one thread: sklearn with scipy's L-BFGS-B
(its default optimiser), GPyTorch with torch's L-BFGS and a strong Wolfe line
search in float64, Cholesky solves throughout (max_cholesky_size raised
above k). Reported per k: the median wall time over --repeats fits, the log
marginal likelihood at the result (each library's own value), and the
objective evaluations.

    python benchmarks/fit_peers.py [--sizes 1000 3000] [--repeats 3] [--out docs/fit-peers.json]

scripts/python-env provides bayes_cbf; scikit-learn (and gpytorch) are
installed on demand with --install.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "RAYON_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse
import json
import platform
import subprocess
import sys
import time

import numpy as np


def data(k: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = rng.uniform(-3.0, 3.0, k)
    y = np.sin(3.0 * x) + 0.5 * x + 0.1 * rng.standard_normal(k)
    return x, y


def start(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """Lengthscale, output scale and noise variance of the common start."""
    r2 = float(np.mean(y**2))
    return float(np.std(x)), r2, 0.01 * r2


def fit_bayes_cbf(x: np.ndarray, y: np.ndarray) -> dict:
    import bayes_cbf as bc

    ell, scale, noise = start(x, y)
    k = len(x)
    model = bc.MVGP(1, 1, [ell], np.eye(1), np.eye(2) * scale, np.sqrt(noise))
    t = time.perf_counter()
    model.fit(x.reshape(k, 1), np.zeros((k, 1)), y.reshape(k, 1))
    elapsed = time.perf_counter() - t
    report = model.fit_report
    return {
        "seconds": elapsed,
        "log_likelihood": float(model.log_marginal_likelihood()),
        "evaluations": int(report["evaluations"]),
    }


def fit_sklearn(x: np.ndarray, y: np.ndarray) -> dict:
    import scipy.optimize
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel
    from threadpoolctl import threadpool_limits

    ell, scale, noise = start(x, y)
    evaluations = [0]

    def optimizer(objective, theta0, bounds):
        def counted(theta):
            evaluations[0] += 1
            return objective(theta)

        r = scipy.optimize.minimize(counted, theta0, method="L-BFGS-B", jac=True, bounds=bounds)
        return r.x, r.fun

    kernel = ConstantKernel(scale, (1e-5, 1e5)) * RBF(ell, (1e-5, 1e5)) + WhiteKernel(noise, (1e-10, 1e5))
    gp = GaussianProcessRegressor(kernel, optimizer=optimizer)
    with threadpool_limits(1):
        t = time.perf_counter()
        gp.fit(x.reshape(-1, 1), y)
        elapsed = time.perf_counter() - t
    return {
        "seconds": elapsed,
        "log_likelihood": float(gp.log_marginal_likelihood_value_),
        "evaluations": evaluations[0],
    }


def fit_gpytorch(x: np.ndarray, y: np.ndarray) -> dict:
    import gpytorch
    import torch

    torch.set_num_threads(1)
    ell, scale, noise = start(x, y)
    tx = torch.tensor(x, dtype=torch.float64).reshape(-1, 1)
    ty = torch.tensor(y, dtype=torch.float64)

    class Exact(gpytorch.models.ExactGP):
        def __init__(self, likelihood):
            super().__init__(tx, ty, likelihood)
            self.mean_module = gpytorch.means.ZeroMean()
            self.covar_module = gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel())

        def forward(self, z):
            return gpytorch.distributions.MultivariateNormal(self.mean_module(z), self.covar_module(z))

    likelihood = gpytorch.likelihoods.GaussianLikelihood().double()
    model = Exact(likelihood).double()
    model.covar_module.base_kernel.lengthscale = ell
    model.covar_module.outputscale = scale
    likelihood.noise = noise
    model.train()
    likelihood.train()
    mll = gpytorch.mlls.ExactMarginalLogLikelihood(likelihood, model)
    opt = torch.optim.LBFGS(model.parameters(), lr=1.0, max_iter=100, line_search_fn="strong_wolfe",
                            tolerance_change=1e-9, tolerance_grad=1e-5)
    evaluations = [0]
    k = len(x)
    with gpytorch.settings.max_cholesky_size(10 * k), gpytorch.settings.fast_computations(False, False, False):

        def closure():
            evaluations[0] += 1
            opt.zero_grad()
            loss = -mll(model(tx), ty)
            loss.backward()
            return loss

        t = time.perf_counter()
        opt.step(closure)
        elapsed = time.perf_counter() - t
        with torch.no_grad():
            value = float(mll(model(tx), ty)) * k
    return {"seconds": elapsed, "log_likelihood": value, "evaluations": evaluations[0]}


def available(module: str) -> bool:
    try:
        __import__(module)
        return True
    except Exception:  # a broken install counts as missing
        return False


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 3000])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--install", action="store_true", help="pip install scikit-learn and gpytorch first")
    ap.add_argument("--out")
    a = ap.parse_args()
    if a.install:
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", "scikit-learn", "threadpoolctl"], check=True)
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", "gpytorch"], check=False)
    fitters = {"bayes-cbf": fit_bayes_cbf, "scikit-learn": fit_sklearn}
    if available("gpytorch"):
        fitters["gpytorch"] = fit_gpytorch
    rows = []
    for k in a.sizes:
        x, y = data(k, a.seed + k)
        results: dict[str, list[dict]] = {name: [] for name in fitters}
        # interleaved repeats: a slow phase of a shared machine hits every library
        for _ in range(a.repeats):
            for name, fitter in fitters.items():
                results[name].append(fitter(x, y))
        base = float(np.median([r["seconds"] for r in results["bayes-cbf"]]))
        for name, rs in results.items():
            seconds = float(np.median([r["seconds"] for r in rs]))
            row = {
                "library": name,
                "k": k,
                "seconds_p50": round(seconds, 4),
                "log_likelihood": round(rs[0]["log_likelihood"], 4),
                "evaluations": rs[0]["evaluations"],
                "over_bayes_cbf": round(seconds / base, 2),
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
    out = {
        "threads": 1,
        "repeats": a.repeats,
        "python": platform.python_version(),
        "missing": [] if "gpytorch" in fitters else ["gpytorch"],
        "rows": rows,
    }
    text = json.dumps(out, indent=1)
    if a.out:
        with open(a.out, "w") as f:
            f.write(text + "\n")
    else:
        print(text)


if __name__ == "__main__":
    main()
