"""Bayes CBF on gymnasium's Pendulum-v1, whose dynamics bayes_cbf never sees.

Pendulum-v1: theta = 0 upright, dt = 0.05 s, torque |u| <= 2, observation
(cos theta, sin theta, theta_dot). The model's state is x = (phi, phi_dot)
with phi = theta - pi (0 hanging, the convention of bayes_cbf's pendulum).
True dynamics: phi_ddot = -15 sin(phi) + 3 u. The model starts from a wrong
prior, the pendulum prior with m = l = 1, g = 10 (phi_ddot = -10 sin(phi) + u:
two thirds of the gravity term, a third of the input gain) whose kinematic
row phi' = phi_dot is known exactly (known_rows=[0]), or from a zero prior,
and learns F(x) = [f(x) g(x)] online from the observed transitions.
Pendulum-v1 integrates the velocity with forward Euler, so the transitions
are labelled at their start (label_at="start"), where the velocity row's
label is exact.

The barrier is an energy cap, written in Python:

    E(x) = phi_dot^2 / 2 - 15 cos(phi),    h(x) = E_max - E(x),

with 15 = 3 g / (2 l) for Pendulum-v1's g = 10, l = 1 (the designer knows the
pendulum's size, not its dynamics model). Along the true dynamics
dE/dt = 3 u phi_dot, so u = 0 keeps h constant: the safe set {h >= 0} is
invariant under any torque bound, and +-2 N m can always keep it. h >= 0
implies -15 cos(phi) <= E_max, i.e. the pendulum never swings higher than
arccos(-E_max / 15) from hanging (120 degrees for E_max = 7.5): think of a
cable or a wall it must not reach.

The barrier condition is continuous-time, but Pendulum-v1 integrates with
semi-implicit Euler, which by itself lifts the unforced pendulum's energy by
up to ~1.9 at dt = 0.05 from rest at the cap. The filters therefore demand
the margin zeta = alpha * (that rise), computed from the environment at start.

The policy is an energy-pumping swing-up controller (u = 2 sign(theta_dot),
plus noise) that wants to go over the top, or a uniformly random policy.
Each episode starts hanging (theta = pi +- 0.5, theta_dot in [-1, 1]) with a
fresh, untrained model. Compared: the unfiltered policy, the mean CBF (the
filter on the posterior mean, p = 0.5) and the Bayes CBF (p = 0.99), both
from the wrong prior, and the Bayes CBF from a zero prior.

    python examples/gym_pendulum.py --episodes 100 --seed 1000 --out docs/gym_pendulum.json

--u-max U bounds the filters' torque to [-U, U] (the environment's is 2),
and --fallback NAME sets their fallback on infeasible steps (the library's
default is max_margin): with bounds tighter than the policy's torque, the
fallback decides (docs/python.md, "Input bounds and the fallback").
"""

from __future__ import annotations

import argparse
import json
import time

import gymnasium as gym
import numpy as np

import bayes_cbf as bc
from bayes_cbf.gym import SafetyFilterWrapper

E_MAX = 7.5
GRAVITY_TERM = 15.0  # 3 g / (2 l), Pendulum-v1
ALPHA = 2.0


def energy(x) -> float:
    return 0.5 * x[1] ** 2 - GRAVITY_TERM * np.cos(x[0])


def integrator_energy_rise(steps: int = 2000) -> float:
    """How far Pendulum-v1's integrator lifts the energy of the unforced
    pendulum above its start, from rest at the energy cap (semi-implicit
    Euler does not conserve E; at dt = 0.05 the rise is about 1.9)."""
    env = gym.make("Pendulum-v1")
    env.reset(seed=0)
    phi0 = np.arccos(-E_MAX / GRAVITY_TERM)
    env.unwrapped.state = np.array([phi0 + np.pi, 0.0])
    e0, top = E_MAX, E_MAX
    for _ in range(steps):
        obs, *_ = env.step(np.zeros(1, dtype=np.float32))
        top = max(top, energy(state_from_obs(obs)))
    return float(top - e0)


def energy_barrier() -> bc.Barrier:
    def h(x):
        return E_MAX - energy(x)

    def grad(x):
        return np.array([-GRAVITY_TERM * np.sin(x[0]), -x[1]])

    def hess(x):
        return np.array([[-GRAVITY_TERM * np.cos(x[0]), 0.0], [0.0, -1.0]])

    return bc.Barrier.callback(h, grad, hess, state_dim=2, relative_degree=1, alpha=ALPHA,
                               name="energy")


def state_from_obs(obs) -> np.ndarray:
    """(phi, phi_dot) with phi = theta - pi, from (cos theta, sin theta, theta_dot)."""
    return np.array([np.arctan2(-obs[1], -obs[0]), obs[2]])


class HangingStart(gym.Wrapper):
    """Starts every episode near the bottom, inside the safe set."""

    def reset(self, *, seed=None, options=None):
        _, info = self.env.reset(seed=seed, options=options)
        rng = self.env.unwrapped.np_random
        self.env.unwrapped.state = np.array([np.pi + rng.uniform(-0.5, 0.5), rng.uniform(-1, 1)])
        return self.env.unwrapped._get_obs(), info


WRONG_PRIOR = {"type": "pendulum", "mass": 1.0, "length": 1.0, "gravity": 10.0}


def new_model(prior) -> bc.MVGP:
    # hyperparameters chosen for a pendulum-sized system (accelerations of
    # order 10), not fitted to this one; the kernel sees (cos phi, sin phi, phi_dot)
    return bc.MVGP(2, 1, lengthscales=[1.0, 1.0, 3.0], A=np.diag([0.01, 25.0]), B=np.eye(2),
                   noise_sigma=0.05, prior_mean=prior, input_map=[{"cos": 0}, {"sin": 0}, 1],
                   known_rows=[0] if prior is not None else None)


def policy(kind: str, rng: np.random.Generator, obs) -> np.ndarray:
    if kind == "random":
        return rng.uniform(-2, 2, 1)
    thdot = obs[2]
    return np.array([np.clip(2.0 * np.sign(thdot) + 0.3 * rng.standard_normal(), -2, 2)])


VARIANTS = ["unfiltered", "mean-cbf", "bayes-cbf", "bayes-cbf-zero-prior"]


def episode(variant: str, kind: str, seed: int, zeta: float, trace: list | None = None,
            u_max: float = 2.0, fallback: str | None = None) -> dict:
    env = HangingStart(gym.make("Pendulum-v1"))
    rng = np.random.default_rng(seed)
    barrier = energy_barrier()
    if variant == "unfiltered":
        obs, _ = env.reset(seed=seed)
        stats = {"return": 0.0, "infeasible_steps": 0, "violation_steps": 0,
                 "min_barrier": barrier.value(state_from_obs(obs))}
        done = False
        while not done:
            obs, r, term, trunc, _ = env.step(policy(kind, rng, obs).astype(np.float32))
            h = barrier.value(state_from_obs(obs))
            if trace is not None:
                trace.append(h)
            stats["return"] += float(r)
            stats["violation_steps"] += h < 0
            stats["min_barrier"] = min(stats["min_barrier"], h)
            done = term or trunc
        return stats
    p = {"mean-cbf": 0.5, "bayes-cbf": 0.99, "bayes-cbf-zero-prior": 0.99}[variant]
    prior = None if variant.endswith("zero-prior") else WRONG_PRIOR
    options = {} if fallback is None else {"fallback": fallback}
    filt = bc.SafetyFilter(new_model(prior), [barrier], probability=p, zeta=zeta,
                           u_min=[-u_max], u_max=[u_max], predictive=True, **options)
    wrapped = SafetyFilterWrapper(env, filt, state_from_obs, learn=True, angle_indices=[0],
                                  max_data=200, label_at="start", barriers_for_log=[barrier])
    obs, _ = wrapped.reset(seed=seed)
    done = False
    while not done:
        obs, _, term, trunc, info = wrapped.step(policy(kind, rng, obs))
        if trace is not None:
            trace.append(info["barrier_values"][0])
        done = term or trunc
    return dict(wrapped.episode_stats)


def plot(path: str, seed: int, zeta: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.6))
    colours = ["tab:gray", "tab:orange", "tab:blue", "tab:purple"]
    for variant, colour in zip(VARIANTS, colours):
        trace: list = []
        episode(variant, "swing-up", seed, zeta, trace)
        t = 0.05 * np.arange(1, len(trace) + 1)
        ax.plot(t, trace, label=variant, color=colour, lw=1.2)
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set_ylim(-6, 25)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("h = E_max - E")
    ax.set_title(f"Pendulum-v1, swing-up policy, episode seed {seed}")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0, help="first episode seed")
    ap.add_argument("--policy", choices=["swing-up", "random"], nargs="+",
                    default=["swing-up", "random"])
    ap.add_argument("--out", help="write the table as JSON here")
    ap.add_argument("--figure", help="plot h(t) of one swing-up episode per controller here "
                    "(PNG; needs matplotlib)")
    ap.add_argument("--controllers", choices=VARIANTS, nargs="+", default=VARIANTS)
    ap.add_argument("--u-max", type=float, default=2.0,
                    help="the filters' torque bound (the environment's is 2)")
    ap.add_argument("--fallback", choices=["max_margin", "relax", "brake", "hold"],
                    help="the filters' fallback (default: the library's, max_margin)")
    a = ap.parse_args()
    if not 0.0 < a.u_max <= 2.0:
        ap.error(f"--u-max {a.u_max}: must be in (0, 2], within the environment's bound")
    if a.figure:
        # before the episodes run, not after them
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            ap.error("--figure needs matplotlib (pip install matplotlib)")
    # the CBF condition is continuous-time; the environment's integrator
    # lifts the energy by up to `rise` on its own, so the filters demand the
    # margin zeta = alpha * rise (a state where the condition binds then
    # has h >= rise)
    rise = integrator_energy_rise()
    zeta = ALPHA * rise
    print(json.dumps({"integrator_energy_rise": rise, "zeta": zeta}))
    table = []
    for kind in a.policy:
        for variant in a.controllers:
            t0 = time.perf_counter()
            eps = [episode(variant, kind, a.seed + i, zeta, u_max=a.u_max, fallback=a.fallback)
                   for i in range(a.episodes)]
            row = {
                "policy": kind,
                "controller": variant,
                # the filters' bound and fallback (the unfiltered policy has neither)
                "u_max": None if variant == "unfiltered" else a.u_max,
                "fallback": None if variant == "unfiltered" else a.fallback or "max_margin",
                "episodes": a.episodes,
                "episodes_with_h_below_0": int(sum(e["violation_steps"] > 0 for e in eps)),
                "violation_steps": int(sum(e["violation_steps"] for e in eps)),
                "infeasible_steps": int(sum(e["infeasible_steps"] for e in eps)),
                "mean_return": float(np.mean([e["return"] for e in eps])),
                "min_barrier": float(min(e["min_barrier"] for e in eps)),
                "seconds": round(time.perf_counter() - t0, 2),
            }
            table.append(row)
            print(json.dumps(row))
    if a.figure:
        plot(a.figure, a.seed, zeta)
    if a.out:
        with open(a.out, "w") as f:
            json.dump({"integrator_energy_rise": rise, "zeta": zeta, "rows": table}, f, indent=1)


if __name__ == "__main__":
    main()
