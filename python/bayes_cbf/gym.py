"""A safety filter for any continuous-action gymnasium environment.

:class:`SafetyFilterWrapper` passes every action of the wrapped policy
through a :class:`bayes_cbf.SafetyFilter`, learns the dynamics online from
the observed transitions (the filter's MVGP gains one observation per step,
in O(k^2)), and records barrier values, violations and infeasible steps.

The learning labels: a transition ``x_k -> x_{k+1}`` over ``dt`` under the
held control ``u_k`` gives the derivative estimate ``(x_{k+1} - x_k) / dt``
(angles wrapped). For a continuous-time system sampled with a zero-order
hold, label it at the midpoint ``(x_k + x_{k+1}) / 2`` (``label_at=
"midpoint"``, the default): the central difference is exact to O(dt^2)
there, where a label at ``x_k`` is biased by O(dt). For an environment that
integrates with forward Euler (``x_{k+1} = x_k + dt F(x_k) u_k``), the label
at the start (``label_at="start"``) is exact.
"""

from __future__ import annotations

import numbers
import warnings
from typing import Any, Callable, Optional, Sequence

import numpy as np

try:
    import gymnasium as gym
except ImportError as e:  # pragma: no cover - exercised only without gymnasium
    raise ImportError(
        "bayes_cbf.gym needs gymnasium: pip install 'bayes_cbf[gym]'"
    ) from e

from ._checks import count
from ._core import Barrier, InputError, SafetyFilter


class SafetyFilterWrapper(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Filters every action of ``env`` through ``filter``.

    Parameters
    ----------
    env:
        A gymnasium environment with a ``Box`` action space of the filter
        model's control dimension.
    filter:
        The :class:`bayes_cbf.SafetyFilter`; its model (``filter.model``)
        is the one that learns.
    state_from_obs:
        Maps an observation to the state ``x`` of the model, ``(n,)``.
    learn:
        Add one observation per step to the model.
    dt:
        Control period in seconds; default ``env.unwrapped.dt``.
    angle_indices:
        State indices that are angles: their differences are wrapped to
        ``[-pi, pi)`` when estimating derivatives.
    max_data:
        Keep at most this many observations.
    keep:
        Which ``max_data`` observations: ``"latest"`` (a sliding window,
        oldest dropped first) or ``"informative"`` (a budget: each new
        observation replaces the stored one of least leave-one-out variance,
        or is dropped; ``MVGP.add_observation_within_budget``). A window
        suits dynamics that drift; where the input saturates, it drops the
        few observations at other controls that told the input gain from the
        drift, which a budget keeps (docs/robots.md, "For a robot whose
        dynamics do not change").
    refit_every:
        Refit the hyperparameters on the model's data every this many steps
        (0: never).
    label_at:
        ``"midpoint"`` or ``"start"``: where the derivative estimate of a
        transition is labelled (module docs).
    barriers_for_log:
        Barriers whose values are logged; default (or ``None``): none (``info`` then has
        only the filter's outcome). Pass the filter's barriers to record
        violations.
    learn_if:
        ``learn_if(x, u, x_next, info) -> bool``, called before each
        transition is learned (with ``learn=True``): a false value skips
        it. For transitions the dynamics ``F(x)u`` do not make: a clip of
        the state at a limit, a contact, a reset inside the environment
        (MountainCarContinuous-v0 sets the velocity to 0 at its left end: a
        label ten times anything its dynamics give, which leaves a model
        that learns it with the wrong drift and input gain). ``info`` is the
        environment's.

    ``info`` of each step gains:

    - ``filter_status``: ``"optimal"`` or ``"infeasible"``;
    - ``p_star``: on an infeasible step, the largest probability at which
      the conditions could be met, or ``None`` if none could (the mean
      conditions cannot be met within the bounds) or the solver found none;
      ``None`` on an optimal step;
    - ``u_ref``: the policy's action; ``u_filtered``: the filter's control;
      ``u_applied``: the control sent to the environment, ``u_filtered``
      clipped to the action space (a filter whose bounds are wider than the
      action space is warned of once, at the first step where the clip
      changes its control);
    - ``learned``: whether the transition was added to the model;
    - ``barrier_values``: the logged barriers at the new state (empty
      without ``barriers_for_log``), and ``violation``: a logged barrier
      below 0 (``False`` without any).

    :attr:`episode_stats` sums them over the episode (``steps``,
    ``return``, ``infeasible_steps``, ``violation_steps``,
    ``unlearned_steps``, ``min_barrier``).

    With ``learn=True`` the model keeps what it learned across ``reset``:
    that is the point of learning online, and it makes the wrapped
    environment non-stationary, so the same seed and actions give slightly
    different filtered actions in a later episode (gymnasium's ``check_env``
    reports this). With ``learn=False`` the wrapper passes ``check_env``.
    """

    def __init__(
        self,
        env: gym.Env,
        filter: SafetyFilter,
        state_from_obs: Callable[[Any], np.ndarray],
        learn: bool = True,
        dt: Optional[float] = None,
        angle_indices: Sequence[int] = (),
        max_data: int = 500,
        keep: str = "latest",
        refit_every: int = 0,
        label_at: str = "midpoint",
        barriers_for_log: Optional[Sequence[Any]] = (),
        learn_if: Optional[Callable[..., Any]] = None,
    ):
        # the arguments after env, recorded for env.spec; not copied: a
        # wrapper made again from the spec shares this filter and its model
        recorded = {k: v for k, v in locals().items() if k not in ("self", "env", "__class__")}
        gym.utils.RecordConstructorArgs.__init__(self, _disable_deepcopy=True, **recorded)
        super().__init__(env)
        if not isinstance(filter, SafetyFilter):
            raise InputError(
                f"filter: {type(filter).__name__}, expected a bayes_cbf.SafetyFilter"
            )
        if not isinstance(env.action_space, gym.spaces.Box):
            raise InputError("env: the action space must be a gymnasium.spaces.Box")
        self.filter = filter
        self.model = filter.model
        if env.action_space.shape != (self.model.control_dim,):
            raise InputError(
                f"env: action shape {env.action_space.shape} != (control_dim,) = "
                f"({self.model.control_dim},)"
            )
        self.state_from_obs = state_from_obs
        if not isinstance(learn, (bool, np.bool_)):
            raise InputError(f"learn = {learn!r}: expected True or False")
        self.learn = bool(learn)
        if dt is not None:
            if isinstance(dt, np.ndarray) and dt.shape == ():
                dt = dt.item()
            real = isinstance(dt, numbers.Real) and not isinstance(dt, bool)
            if not real or not np.isfinite(dt) or dt <= 0:
                raise InputError(f"dt = {dt!r}: the control period must be a finite number > 0")
        else:
            dt = getattr(env.unwrapped, "dt", None)
            if isinstance(dt, np.ndarray) and dt.shape == ():
                dt = dt.item()
            real = isinstance(dt, numbers.Real) and not isinstance(dt, bool)
            if not real or not np.isfinite(dt) or dt <= 0:
                raise InputError(
                    f"dt: give the control period (the environment's dt is {dt!r}, "
                    "not a positive number)"
                )
        self.dt = float(dt)
        n = self.model.state_dim
        if isinstance(angle_indices, (str, bytes)) or not hasattr(angle_indices, "__iter__"):
            raise InputError(
                f"angle_indices: {angle_indices!r}, expected a sequence of state indices"
            )
        self.angle_indices = [count("angle_indices", i, 0) for i in angle_indices]
        for i in self.angle_indices:
            if i >= n:
                raise InputError(f"angle_indices: {i} is not a state index (state_dim = {n})")
        self.max_data = count("max_data", max_data, 1)
        if keep not in ("latest", "informative"):
            raise InputError(f"keep: {keep!r}, expected 'latest' or 'informative'")
        if keep == "informative" and self.max_data < 2:
            raise InputError("max_data: 1 with keep='informative', expected at least 2")
        self.keep = keep
        self.refit_every = count("refit_every", refit_every, 0)
        if label_at not in ("midpoint", "start"):
            raise InputError(f"label_at: {label_at!r}, expected 'midpoint' or 'start'")
        self.label_at = label_at
        if barriers_for_log is None:
            barriers_for_log = ()
        if isinstance(barriers_for_log, (str, bytes)) or not hasattr(barriers_for_log, "__iter__"):
            raise InputError(
                f"barriers_for_log: {type(barriers_for_log).__name__}, expected a sequence "
                "of bayes_cbf.Barrier"
            )
        self.barriers_for_log = list(barriers_for_log)
        for i, b in enumerate(self.barriers_for_log):
            if not isinstance(b, Barrier):
                raise InputError(
                    f"barriers_for_log[{i}]: {type(b).__name__}, expected a bayes_cbf.Barrier"
                )
            if b.state_dim != n:
                raise InputError(
                    f"barriers_for_log[{i}]: a barrier on {b.state_dim} states, the model has {n}"
                )
        if learn_if is not None and not callable(learn_if):
            raise InputError(
                f"learn_if: {type(learn_if).__name__}, expected a function "
                f"(x, u, x_next, info) -> bool"
            )
        self.learn_if = learn_if
        self._clip_warned = False
        self._low = np.asarray(env.action_space.low, dtype=np.float64)
        self._high = np.asarray(env.action_space.high, dtype=np.float64)
        self._x: Optional[np.ndarray] = None
        # why step needs a reset: never reset, or a step failed after the
        # environment moved (its state is then unknown to the filter)
        self._needs_reset = "call reset() first"
        self._steps = 0
        self.episode_stats: dict = {}

    def _state(self, obs) -> np.ndarray:
        try:
            raw = self.state_from_obs(obs)
        except Exception as e:  # KeyboardInterrupt and SystemExit pass through
            raise InputError(f"state_from_obs: raised {type(e).__name__}: {e}") from e
        try:
            x = np.asarray(raw, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError) as e:
            raise InputError(
                f"state_from_obs: returned {raw!r}, expected {self.model.state_dim} finite values"
            ) from e
        if x.shape != (self.model.state_dim,) or not np.all(np.isfinite(x)):
            raise InputError(
                f"state_from_obs: returned {x!r}, expected {self.model.state_dim} finite values"
            )
        return x

    def reset(self, **kwargs):
        self._x = None
        self._needs_reset = "the last reset failed; call reset() again"
        obs, info = self.env.reset(**kwargs)
        self._x = self._state(obs)
        self.episode_stats = {
            "steps": 0,
            "return": 0.0,
            "infeasible_steps": 0,
            "violation_steps": 0,
            "unlearned_steps": 0,
            "min_barrier": float("inf"),
        }
        values = self._log_barriers(self._x)
        if values and min(values) < 0:
            warnings.warn(
                f"reset: the episode starts outside the safe set (barrier values "
                f"{[round(v, 4) for v in values]}): no filter keeps a state safe that "
                f"starts unsafe; its steps count as violations while h < 0",
                UserWarning,
                stacklevel=2,
            )
        return obs, info

    def _log_barriers(self, x: np.ndarray) -> list:
        values = [b.value(x) for b in self.barriers_for_log]
        if values:
            self.episode_stats["min_barrier"] = min(self.episode_stats["min_barrier"], min(values))
        return values

    def step(self, action):
        if self._x is None:
            raise InputError(f"step: {self._needs_reset}")
        kind = np.asarray(action).dtype.kind
        if kind not in "fiu":
            raise InputError(f"action: {action!r}, expected numbers (got dtype kind {kind!r})")
        u_ref = np.asarray(action, dtype=np.float64).reshape(-1)
        if u_ref.size != self.model.control_dim:
            raise InputError(
                f"action: {u_ref.size} values, the model has {self.model.control_dim} controls"
            )
        res = self.filter.filter(self._x, u_ref)
        u = np.clip(res.u, self._low, self._high)
        self._warn_clip(res.u, u)
        # from here the environment may move: until its new state is known,
        # no state is the filter's (a transition over two steps would be
        # learned as one)
        x, self._x = self._x, None
        self._needs_reset = (
            "the last step failed after the environment moved; call reset() first"
        )
        obs, reward, terminated, truncated, info = self.env.step(u.astype(self.action_space.dtype))
        x_new = self._state(obs)
        self._x = x_new
        self._needs_reset = "call reset() first"
        if self.learn:
            # a learn_if that raises leaves the step unreported to the
            # caller: as after a failed state_from_obs, a reset follows
            self._x = None
            self._needs_reset = "learn_if failed after the environment moved; call reset() first"
            learned = self._wanted(x, u, x_new, info)
            self._x = x_new
            self._needs_reset = "call reset() first"
        else:
            learned = False
        if learned:
            self._observe(x, u, x_new)
        values = self._log_barriers(x_new)
        st = self.episode_stats
        st["steps"] += 1
        try:
            st["return"] += float(reward)
        except (TypeError, ValueError) as e:
            raise InputError(f"the environment's reward {reward!r} is not a number") from e
        st["infeasible_steps"] += res.status == "infeasible"
        st["unlearned_steps"] += self.learn and not learned
        violated = bool(values) and min(values) < 0
        st["violation_steps"] += violated
        info = dict(info)
        info.update(
            filter_status=res.status,
            p_star=res.p_star,
            u_ref=u_ref,
            u_filtered=np.asarray(res.u, dtype=np.float64),
            u_applied=u,
            learned=learned,
            barrier_values=values,
            violation=violated,
        )
        return obs, reward, terminated, truncated, info

    def _wanted(self, x: np.ndarray, u: np.ndarray, x_new: np.ndarray, info: dict) -> bool:
        if self.learn_if is None:
            return True
        try:
            return bool(self.learn_if(x.copy(), u.copy(), x_new.copy(), info))
        except Exception as e:  # KeyboardInterrupt and SystemExit pass through
            raise InputError(f"learn_if: raised {type(e).__name__}: {e}") from e

    def _warn_clip(self, u_filtered: np.ndarray, u: np.ndarray) -> None:
        # the solver meets a bound to its tolerance, not to the last bit
        scale = 1.0 + np.maximum(np.abs(self._low), np.abs(self._high))
        if self._clip_warned or np.all(np.abs(u_filtered - u) <= 1e-6 * scale):
            return
        self._clip_warned = True
        warnings.warn(
            f"step: the filter's control {np.round(u_filtered, 6).tolist()} lies outside the "
            f"action space [{self._low.tolist()}, {self._high.tolist()}] and was clipped to "
            f"{np.round(u, 6).tolist()}, which its conditions did not account for: give the "
            f"SafetyFilter u_min and u_max within the action space (shown once per wrapper)",
            UserWarning,
            stacklevel=3,
        )

    def _observe(self, x: np.ndarray, u: np.ndarray, x_new: np.ndarray) -> None:
        dx = x_new - x
        for i in self.angle_indices:
            dx[i] = (dx[i] + np.pi) % (2 * np.pi) - np.pi
        at = x + 0.5 * dx if self.label_at == "midpoint" else x
        if self.keep == "informative":
            self.model.add_observation_within_budget(at, u, dx / self.dt, self.max_data)
        else:
            self.model.add_observation(at, u, dx / self.dt)
            while len(self.model) > self.max_data:
                self.model.remove_oldest()
        self._steps += 1
        if self.refit_every and self._steps % self.refit_every == 0 and len(self.model) >= 10:
            self.model.fit(self.model.X, self.model.U, self.model.Xdot, max_iters=30)
