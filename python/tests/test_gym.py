"""The gymnasium wrapper on a short seeded run of Pendulum-v1."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import bayes_cbf as bc
from bayes_cbf.gym import SafetyFilterWrapper


def make(learn=True, seed=0):
    model = bc.MVGP(2, 1, [1.0, 1.0, 3.0], np.diag([0.01, 25.0]), np.eye(2), 0.05,
                    prior_mean={"type": "pendulum", "mass": 1.0, "length": 1.0, "gravity": 10.0},
                    input_map=[{"cos": 0}, {"sin": 0}, 1])
    b = bc.Barrier.half_space([0.0, -1.0], -6.0, alpha=2.0)  # phi_dot <= 6
    filt = bc.SafetyFilter(model, [b], probability=0.9, u_min=[-2.0], u_max=[2.0])
    env = gym.make("Pendulum-v1")
    w = SafetyFilterWrapper(
        env, filt, lambda o: np.array([np.arctan2(-o[1], -o[0]), o[2]]), learn=learn,
        angle_indices=[0], max_data=50, barriers_for_log=[b])
    return w, model


def run(w, seed, steps=60):
    rng = np.random.default_rng(seed)
    obs, _ = w.reset(seed=seed)
    infos = []
    for _ in range(steps):
        obs, r, term, trunc, info = w.step(rng.uniform(-2, 2, 1))
        infos.append(info)
    return infos


def test_wrapper_learns_filters_and_records():
    w, model = make()
    infos = run(w, seed=1)
    assert len(model) == 50  # the window
    st = w.episode_stats
    assert st["steps"] == 60 and np.isfinite(st["return"]) and np.isfinite(st["min_barrier"])
    for info in infos:
        assert info["filter_status"] in ("optimal", "infeasible")
        assert np.all(np.abs(info["u_applied"]) <= 2.0)
        assert len(info["barrier_values"]) == 1
    assert st["violation_steps"] == sum(i["violation"] for i in infos)
    # the learned model predicts the true acceleration's input gain (3) well
    mean, _ = model.predict(np.array([[0.3, 0.0]]))
    assert abs(mean[0, 1, 1] - 3.0) < 1.0


def test_wrapper_is_deterministic_given_seeds():
    a = [i["u_applied"][0] for i in run(make()[0], seed=5, steps=30)]
    b = [i["u_applied"][0] for i in run(make()[0], seed=5, steps=30)]
    assert a == b


def test_without_learning_the_model_is_untouched():
    w, model = make(learn=False)
    run(w, seed=2, steps=20)
    assert len(model) == 0


def test_without_learning_the_wrapper_passes_check_env():
    from gymnasium.utils.env_checker import check_env

    w, _ = make(learn=False)
    check_env(w, skip_render_check=True)


def test_wrapper_rejects_bad_setups():
    three = bc.Barrier.half_space([1.0, 0.0, 0.0], 0.0)
    for field, value, pattern in [
        ("max_data", 0, "max_data"), ("max_data", 2.5, "max_data"),
        ("refit_every", -1, "refit_every"), ("refit_every", "3", "refit_every"),
        ("max_data", True, "max_data"), ("angle_indices", [0.5], "angle_indices"),
        ("angle_indices", [-1], "angle_indices"), ("angle_indices", [2], "angle_indices"),
        ("learn", "no", "learn"),
        ("barriers_for_log", [1.0], r"barriers_for_log\[0\]: float"),
        ("barriers_for_log", [three], r"barriers_for_log\[0\]: a barrier on 3 states"),
        ("barriers_for_log", 5, "barriers_for_log: int, expected a sequence"),
        ("keep", "oldest", "keep: 'oldest', expected 'latest' or 'informative'"),
        ("keep", 5, "keep: 5"),
    ]:
        model = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1)
        filt = bc.SafetyFilter(model, [bc.Barrier.half_space([1.0, 0.0], 0.0, alpha=1.0)])
        with pytest.raises(bc.InputError, match=pattern):
            SafetyFilterWrapper(gym.make("Pendulum-v1"), filt, lambda o: o[:2], **{field: value})
    # a period given and wrong is named as given
    for dt in [0.0, -1.0, float("nan"), "0.1"]:
        model = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1)
        filt = bc.SafetyFilter(model, [bc.Barrier.half_space([1.0, 0.0], 0.0, alpha=1.0)])
        with pytest.raises(bc.InputError, match="must be a finite number > 0"):
            SafetyFilterWrapper(gym.make("Pendulum-v1"), filt, lambda o: o[:2], dt=dt)
    with pytest.raises(bc.InputError, match="filter: NoneType, expected"):
        SafetyFilterWrapper(gym.make("Pendulum-v1"), None, lambda o: o[:2])
    w, _ = make()
    with pytest.raises(bc.InputError, match="reset"):
        w.step(np.zeros(1))
    w.reset(seed=0)
    for action in [np.array([True]), "1", np.array(["1.0"])]:
        with pytest.raises(bc.InputError, match="action"):
            w.step(action)
    with pytest.raises(bc.InputError, match="action: 2 values, the model has 1 controls"):
        w.step(np.zeros(2))
    # None logs no barrier
    model = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1)
    filt = bc.SafetyFilter(model, [bc.Barrier.half_space([1.0, 0.0], 0.0, alpha=1.0)])
    assert SafetyFilterWrapper(gym.make("Pendulum-v1"), filt, lambda o: o[:2],
                               barriers_for_log=None).barriers_for_log == []
    # a 0-d array is a number, as elsewhere in the package
    model = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1)
    filt = bc.SafetyFilter(model, [bc.Barrier.half_space([1.0, 0.0], 0.0, alpha=1.0)])
    assert SafetyFilterWrapper(gym.make("Pendulum-v1"), filt, lambda o: o[:2],
                               dt=np.array(0.05)).dt == 0.05
    # so is the environment's own; a string there is named, not a numpy error
    for env_dt, want in [(np.array(0.04), 0.04), ("0.1", "the environment's dt is '0.1'")]:
        env = gym.make("Pendulum-v1")
        env.unwrapped.dt = env_dt
        if isinstance(want, float):
            assert SafetyFilterWrapper(env, filt, lambda o: o[:2]).dt == want
        else:
            with pytest.raises(bc.InputError, match=want):
                SafetyFilterWrapper(env, filt, lambda o: o[:2])
    model = bc.MVGP(2, 2, [1.0, 1.0], np.eye(2), np.eye(3), 0.1)
    filt = bc.SafetyFilter(model, [bc.Barrier.half_space([1.0, 0.0], 0.0, alpha=1.0)])
    with pytest.raises(bc.InputError, match="action shape"):
        SafetyFilterWrapper(gym.make("Pendulum-v1"), filt, lambda o: o[:2])
    w2, _ = make()
    w2.state_from_obs = lambda o: np.array([np.nan, 0.0])
    with pytest.raises(bc.InputError, match="state_from_obs"):
        w2.reset(seed=0)


def test_an_unsafe_start_is_warned_of_and_a_failing_state_map_is_typed():
    """A reset outside the safe set warns (its steps count as violations);
    an exception of state_from_obs is an InputError with it as the cause."""
    w, _ = make(learn=False)
    w.barriers_for_log = [bc.Barrier.half_space([0.0, -1.0], 100.0, alpha=2.0)]  # never safe
    with pytest.warns(UserWarning, match="starts outside the safe set"):
        w.reset(seed=0)
    w2, _ = make(learn=False)
    w2.state_from_obs = lambda o: 1 / 0
    with pytest.raises(bc.InputError, match="state_from_obs: raised ZeroDivisionError") as e:
        w2.reset(seed=0)
    assert isinstance(e.value.__cause__, ZeroDivisionError)


def test_a_step_that_fails_after_the_environment_moved_needs_a_reset():
    """A state map that fails in a step (the environment has moved) leaves
    no state to the filter: the next step asks for a reset instead of
    learning the two steps' motion as one; a reset goes on learning from
    single steps. A map that returns no numbers, and angle indices that
    are not a sequence, are InputErrors."""
    w, model = make()
    w.reset(seed=0)
    w.step(np.array([0.5]))
    good = w.state_from_obs
    w.state_from_obs = lambda o: 1 / 0
    with pytest.raises(bc.InputError, match="state_from_obs"):
        w.step(np.array([0.5]))
    w.state_from_obs = good
    k = len(model)
    with pytest.raises(bc.InputError, match="the last step failed after the environment moved"):
        w.step(np.array([0.5]))
    assert len(model) == k, "nothing learned from the step over the failure"
    w.reset(seed=1)
    w.step(np.array([0.5]))
    assert len(model) == k + 1
    # a reset that fails is named as such, not as a failed step
    w.state_from_obs = lambda o: 1 / 0
    with pytest.raises(bc.InputError, match="state_from_obs"):
        w.reset(seed=2)
    w.state_from_obs = good
    with pytest.raises(bc.InputError, match="the last reset failed"):
        w.step(np.array([0.5]))
    for bad in ["ab", {"a": 1.0}]:
        w.state_from_obs = lambda o, bad=bad: bad
        with pytest.raises(bc.InputError, match="state_from_obs: returned"):
            w.reset(seed=0)
    model2 = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1)
    filt = bc.SafetyFilter(model2, [bc.Barrier.half_space([1.0, 0.0], 0.0, alpha=1.0)])
    with pytest.raises(bc.InputError, match="angle_indices: 0, expected a sequence"):
        SafetyFilterWrapper(gym.make("Pendulum-v1"), filt, lambda o: o[:2], angle_indices=0)


def test_learn_if_skips_the_transitions_it_refuses():
    """learn_if sees (x, u, x_next, info) of each transition; one it refuses
    is not learned, is marked in info and counted in episode_stats; a
    learn_if that is not a function, or that raises, is an InputError."""
    w, model = make()
    seen = []

    def every_other(x, u, x_next, info):
        seen.append((x.shape, u.shape, x_next.shape, isinstance(info, dict)))
        return len(seen) % 2 == 0

    w.learn_if = every_other
    infos = run(w, seed=3, steps=20)
    assert len(model) == 10
    assert [i["learned"] for i in infos] == [k % 2 == 1 for k in range(20)]
    assert w.episode_stats["unlearned_steps"] == 10
    assert set(seen) == {((2,), (1,), (2,), True)}
    w2, _ = make(learn=False)
    assert all(not i["learned"] for i in run(w2, seed=3, steps=3))
    assert w2.episode_stats["unlearned_steps"] == 0, "nothing is refused without learning"
    w3, model3 = make()
    w3.learn_if = lambda *a: 1 / 0
    w3.reset(seed=0)
    with pytest.raises(bc.InputError, match="learn_if: raised ZeroDivisionError") as e:
        w3.step(np.array([0.5]))
    assert isinstance(e.value.__cause__, ZeroDivisionError) and len(model3) == 0
    w3.learn_if = None
    # the failed step's outcome never reached the caller: a reset follows
    with pytest.raises(bc.InputError, match="learn_if failed after the environment moved"):
        w3.step(np.array([0.5]))
    w3.reset(seed=1)
    w3.step(np.array([0.5]))
    assert len(model3) == 1
    filt = bc.SafetyFilter(bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1),
                           [bc.Barrier.half_space([1.0, 0.0], 0.0, alpha=1.0)])
    with pytest.raises(bc.InputError, match="learn_if: bool, expected a function"):
        SafetyFilterWrapper(gym.make("Pendulum-v1"), filt, lambda o: o[:2], learn_if=True)


def test_keep_chooses_the_latest_or_the_most_informative_observations():
    """keep="latest" holds the last max_data transitions; keep="informative"
    holds max_data of them chosen by the budget, earlier ones among them
    where they tell more (the model's add_observation_within_budget)."""
    kept = {}
    for keep in ["latest", "informative"]:
        w, model = make()
        w.max_data, w.keep, w.label_at = 10, keep, "start"
        states = []
        w.learn_if = lambda x, u, x_next, info: states.append(x.copy()) or True
        run(w, seed=4, steps=60)
        assert len(model) == 10 and len(states) == 60
        rows = {tuple(x) for x in model.X}
        assert rows <= {tuple(x) for x in states}
        kept[keep] = (rows, {tuple(x) for x in states[-10:]})
    latest, last = kept["latest"]
    assert latest == last
    informative, last = kept["informative"]
    assert informative != last, "the budget kept some earlier transitions"
    model = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1)
    filt = bc.SafetyFilter(model, [bc.Barrier.half_space([1.0, 0.0], 0.0, alpha=1.0)])
    with pytest.raises(bc.InputError, match="max_data: 1 with keep='informative'"):
        SafetyFilterWrapper(gym.make("Pendulum-v1"), filt, lambda o: o[:2], max_data=1,
                            keep="informative")


def test_a_control_outside_the_action_space_is_warned_of_once():
    """A filter without bounds passes an action beyond the environment's
    through: the wrapper clips it, reports both controls and warns once;
    a control at its bound to the solver's tolerance is not warned of."""
    model = bc.MVGP(2, 1, [1.0, 1.0], np.eye(2), np.eye(2), 0.1, prior_mean="pendulum")
    b = bc.Barrier.half_space([0.0, -1.0], -1e6, alpha=1.0)  # never binds
    w = SafetyFilterWrapper(gym.make("Pendulum-v1"), bc.SafetyFilter(model, [b]),
                            lambda o: np.array([np.arctan2(-o[1], -o[0]), o[2]]), learn=False)
    w.reset(seed=0)
    with pytest.warns(UserWarning, match=r"the filter's control \[5.0\] lies outside the action"):
        _, _, _, _, info = w.step(np.array([5.0]))
    assert info["u_filtered"][0] == pytest.approx(5.0) and info["u_applied"][0] == 2.0
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        w.step(np.array([7.0]))  # shown once per wrapper
        w2, _ = make(learn=False)
        infos = run(w2, seed=4, steps=30)  # a bounded filter within the action space
    assert all(np.all(np.abs(i["u_applied"] - i["u_filtered"]) <= 1e-5) for i in infos)
