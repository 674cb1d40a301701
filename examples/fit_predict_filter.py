"""Fit, predict and filter with bayes_cbf, step by step (notebook style).

    python examples/fit_predict_filter.py
"""

from __future__ import annotations

import numpy as np

import bayes_cbf as bc

# %% Data from the paper's pendulum (m = l = 1, g = 10): theta' = omega,
# omega' = -10 sin(theta) + u, observed with noise
rng = np.random.default_rng(0)
k = 80
X = np.c_[rng.uniform(-np.pi, np.pi, k), rng.uniform(-3, 3, k)]
U = rng.uniform(-5, 5, (k, 1))
Xdot = np.c_[X[:, 1], -10 * np.sin(X[:, 0]) + U[:, 0]] + 0.02 * rng.standard_normal((k, 2))

# %% An MVGP with a wrong prior (g = 7) whose kinematic row is known exactly;
# the kernel sees (cos theta, sin theta, omega)
model = bc.MVGP(
    2, 1, lengthscales=[1.0, 1.0, 1.0], A=np.eye(2), B=np.eye(2), noise_sigma=0.1,
    prior_mean={"type": "pendulum", "mass": 1.0, "length": 1.0, "gravity": 7.0},
    input_map=[{"cos": 0}, {"sin": 0}, 1], known_rows=[0],
).fit(X, U, Xdot, max_iters=60)
print(model, model.fit_report)

# %% Posterior of F(x) = [f(x) g(x)] at a few states
Xq = np.array([[0.5, 0.0], [2.0, 1.0]])
mean, B = model.predict(Xq)
for x, M, Bx in zip(Xq, mean, B):
    truth = np.array([[x[1], 0.0], [-10 * np.sin(x[0]), 1.0]])
    sd = np.sqrt(np.outer(np.diag(model.row_cov), np.diag(Bx)))  # std of each entry of F
    print(f"x = {x}: |M - F| = {np.abs(M - truth).max():.3f}, max std = {sd.max():.3f}")

# %% A barrier: keep theta out of the sector around pi/4 (relative degree 2),
# and the same barrier written in Python
sector = bc.Barrier.pendulum_sector(theta_c=np.pi / 4, delta=np.pi / 8, relative_degree=2,
                                    k_alpha=[1.0, 3.0])
c, d = np.pi / 4, np.pi / 8
mine = bc.Barrier.callback(
    lambda x: np.cos(d) - np.cos(x[0] - c),
    lambda x: np.array([np.sin(x[0] - c), 0.0]),
    lambda x: np.array([[np.cos(x[0] - c), 0.0], [0.0, 0.0]]),
    state_dim=2, relative_degree=2, k_alpha=[1.0, 3.0], name="my sector",
)
print("derivatives:", bc.check_derivatives(
    lambda x: np.cos(d) - np.cos(x[0] - c),
    lambda x: np.array([np.sin(x[0] - c), 0.0]),
    lambda x: np.array([[np.cos(x[0] - c), 0.0], [0.0, 0.0]]), state_dim=2)["ok"])
x, u = np.array([0.2, 1.5]), np.array([3.0])
print("moments (built-in):", bc.moments(model, sector, x, u))
print("moments (callback):", bc.moments(model, mine, x, u))

# %% The safety filter: the reference control would drive theta into the
# sector; the filter returns the closest control whose condition holds with
# probability 0.99 (an infeasible step, with these bounds, takes the control
# of the largest feasible probability: fallback "relax")
filt = bc.SafetyFilter(model, [sector], probability=0.99, u_min=[-20.0], u_max=[20.0],
                       fallback="relax")
res = filt.filter(x, u_ref=[15.0])
print(res, res.constraints)

# %% Online: one more observation, O(k^2); the filter reads the model each step
model.add_observation(x, res.u, np.array([x[1], -10 * np.sin(x[0]) + res.u[0]]))
print(len(model), filt.filter(x, u_ref=[15.0]).u)
