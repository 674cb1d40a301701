"""Bayes CBF on gymnasium's MountainCarContinuous-v0: a wall the car must not pass.

MountainCarContinuous-v0: state (p, v) (the observation itself), one step
per control (dt = 1, the environment has no dt of its own), force
|a| <= 1. Its update is v += 0.0015 a - 0.0025 cos(3p), v clipped to
[-0.07, 0.07], then p += v, p clipped to [-1.2, 0.6]; at the left end a
negative velocity is set to 0. The velocity row is forward Euler, so the
transitions are labelled at their start (label_at="start").

The barrier is a wall at p = 0.2, short of the goal at 0.45:
h = 0.2 - p, relative degree 2, with real poles 0.05 and 0.1 per step
(k_alpha = [0.005, 0.15]). The policy pumps energy (a = sign(v) plus noise)
and, unfiltered, drives through the wall to the goal. The model starts from
a wrong prior (no gravity term, an input gain of 0.001 where the car's is
0.0015) with the kinematic row p' = v known, and learns online.

The left-end reset is not the car's dynamics: a transition into it has a
velocity label of up to 0.07 per step, ten times anything the force and
the slope give (at most 0.004), and a model that learns it gets the drift
and the input gain wrong. The Bayes CBF is run twice: learning every transition, and with
learn_if skipping the transitions that end at a clip (the left end, the
speed limit).

    python examples/gym_mountaincar.py --episodes 100 --seed 2000 --out mountaincar.json
"""

from __future__ import annotations

import argparse
import json
import time

import gymnasium as gym
import numpy as np

import bayes_cbf as bc
from bayes_cbf.gym import SafetyFilterWrapper

P_WALL = 0.2
POLES = (0.05, 0.1)
MIN_POSITION, MAX_SPEED = -1.2, 0.07
VARIANTS = ["unfiltered", "bayes-cbf-learn-all", "bayes-cbf-skip-clips"]

# wrong: no gravity term, input gain 0.001 (the car's: 0.0015)
WRONG_PRIOR = {"type": "expression", "state": ["p", "v"], "control": ["a"],
               "params": {"gain": 0.001}, "f": ["v", "0"], "g": [["0"], ["gain"]]}


def wall() -> bc.Barrier:
    p1, p2 = POLES
    return bc.Barrier.expression("p_wall - p", ["p", "v"], {"p_wall": P_WALL},
                                 relative_degree=2, k_alpha=[p1 * p2, p1 + p2])


def not_a_clip(x, u, x_next, info) -> bool:
    """Learn a transition unless it ends at one of the environment's clips."""
    at_left_end = x_next[0] <= MIN_POSITION + 1e-6
    at_speed_limit = abs(x_next[1]) >= MAX_SPEED - 1e-6
    return not (at_left_end or at_speed_limit)


def pump(rng: np.random.Generator, obs) -> np.ndarray:
    direction = np.sign(obs[1]) if abs(obs[1]) > 1e-4 else 1.0
    return np.array([np.clip(direction + 0.1 * rng.standard_normal(), -1.0, 1.0)])


def episode(variant: str, seed: int) -> dict:
    env = gym.make("MountainCarContinuous-v0")
    rng = np.random.default_rng(seed)
    barrier = wall()
    stats = {"return": 0.0, "violation_steps": 0, "infeasible_steps": 0, "unlearned_steps": 0,
             "reached_goal": False}
    if variant == "unfiltered":
        obs, _ = env.reset(seed=seed)
        stats["min_barrier"] = barrier.value(np.asarray(obs, dtype=float))
        done = False
        while not done:
            obs, r, term, trunc, _ = env.step(pump(rng, obs).astype(np.float32))
            h = barrier.value(np.asarray(obs, dtype=float))
            stats["return"] += float(r)
            stats["violation_steps"] += h < 0
            stats["min_barrier"] = min(stats["min_barrier"], h)
            stats["reached_goal"] |= term
            done = term or trunc
        return stats
    model = bc.MVGP(2, 1, lengthscales=[0.3, 0.03], A=np.diag([1e-6, 1e-6]), B=np.eye(2),
                    noise_sigma=0.05, prior_mean=WRONG_PRIOR, known_rows=[0])
    filt = bc.SafetyFilter(model, [barrier], probability=0.99, u_min=[-1.0], u_max=[1.0],
                           predictive=True)
    learn_if = not_a_clip if variant == "bayes-cbf-skip-clips" else None
    wrapped = SafetyFilterWrapper(env, filt, lambda obs: np.asarray(obs, dtype=float), dt=1.0,
                                  max_data=200, label_at="start", barriers_for_log=[barrier],
                                  learn_if=learn_if)
    obs, _ = wrapped.reset(seed=seed)
    done = False
    while not done:
        obs, _, term, trunc, _ = wrapped.step(pump(rng, obs))
        stats["reached_goal"] |= term
        done = term or trunc
    return {**stats, **wrapped.episode_stats}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0, help="first episode seed")
    ap.add_argument("--controllers", choices=VARIANTS, nargs="+", default=VARIANTS)
    ap.add_argument("--out", help="write the table as JSON here")
    a = ap.parse_args()
    table = []
    for variant in a.controllers:
        t0 = time.perf_counter()
        eps = [episode(variant, a.seed + i) for i in range(a.episodes)]
        row = {
            "controller": variant,
            "episodes": a.episodes,
            "episodes_with_h_below_0": int(sum(e["violation_steps"] > 0 for e in eps)),
            "violation_steps": int(sum(e["violation_steps"] for e in eps)),
            "infeasible_steps": int(sum(e["infeasible_steps"] for e in eps)),
            "unlearned_steps": int(sum(e["unlearned_steps"] for e in eps)),
            "episodes_at_goal": int(sum(e["reached_goal"] for e in eps)),
            "min_barrier": float(min(e["min_barrier"] for e in eps)),
            "seconds": round(time.perf_counter() - t0, 2),
        }
        table.append(row)
        print(json.dumps(row))
    if a.out:
        with open(a.out, "w") as f:
            json.dump({"rows": table}, f, indent=1)


if __name__ == "__main__":
    main()
