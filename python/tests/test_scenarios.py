"""`run_scenario` equals `bayes-cbf run`."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

import bayes_cbf as bc
from conftest import run_cli

TIMING = {"wall_time_s", "control_step_us"}


def strip(summary: dict) -> dict:
    return {k: v for k, v in summary.items() if k not in TIMING and k != "trajectory"}


def test_list_scenarios_has_the_builtins():
    names = bc.list_scenarios()
    assert "pendulum-safe" in names and "ackermann-bayes-cbf" in names


def test_run_scenario_equals_the_cli(cli, tmp_path):
    ours = bc.run_scenario("pendulum-safe", seed=3,
                           overrides={"controller.probability": 0.9, "steps": 150})
    run_cli(cli, "run", "pendulum-safe", "--seed", "3", "--set", "controller.probability=0.9",
            "--set", "steps=150", "--out", str(tmp_path))
    theirs = json.loads((tmp_path / "summary.json").read_text())
    assert strip(ours) == strip(theirs)
    with open(tmp_path / "trajectory.csv") as f:
        rows = list(csv.DictReader(f))
    traj = ours["trajectory"]
    assert list(traj) == list(rows[0])
    assert len(traj["t"]) == len(rows) == 150
    for name, col in traj.items():
        if name == "control_us":
            continue
        if name == "status":
            assert col.tolist() == [r[name] for r in rows]
            continue
        want = np.array([float(r[name]) if r[name] else np.nan for r in rows])
        np.testing.assert_array_equal(col, want, err_msg=name)


def test_run_scenario_rejects_bad_overrides():
    with pytest.raises(bc.InputError, match="nosuchkey"):
        bc.run_scenario("pendulum-safe", overrides={"nosuchkey": 1})
    with pytest.raises(bc.InputError, match="unknown scenario"):
        bc.run_scenario("no-such-scenario")


def test_the_librarys_warnings_reach_python():
    """A warning the run logs (here: a row declared known that a zero prior
    mean gets wrong) is a UserWarning in Python, not lost."""
    with pytest.warns(UserWarning, match="row 0 of F is declared known"):
        bc.run_scenario("pendulum-safe", seed=1,
                        overrides={"steps": 60, "gp.prior_mean": {"type": "zero"}})


def test_a_run_records_its_warnings_in_its_summary():
    """The summary lists each kind of warning the run issued, with the text
    the UserWarning showed; a run that issued none lists none."""
    over = {"steps": 60, "gp.prior_mean": {"type": "zero"}}
    with pytest.warns(UserWarning, match="row 0 of F is declared known") as shown:
        first = bc.run_scenario("pendulum-safe", seed=1, overrides=over)
    kinds = [w["kind"] for w in first["warnings"]]
    assert "known_row_not_true" in kinds, kinds
    text = next(w["message"] for w in first["warnings"] if w["kind"] == "known_row_not_true")
    assert any(text == str(w.message) for w in shown), text
    quiet = bc.run_scenario("pendulum-safe", seed=1, overrides={"steps": 60})
    assert quiet["warnings"] == []


def test_an_oracle_run_learns_nothing_and_starts_where_the_learning_run_does():
    """`gp.oracle`: the true dynamics in place of the model (docs/robots.md,
    "Check the design with the true dynamics")."""
    learning = bc.run_scenario("double-integrator", seed=4, overrides={"steps": 40})
    oracle = bc.run_scenario("double-integrator", seed=4,
                             overrides={"steps": 40, "gp.oracle": True})
    assert oracle["oracle"] and not learning["oracle"]
    assert oracle["data_size"] == 0 and learning["data_size"] > 0
    np.testing.assert_array_equal(oracle["trajectory"]["x1"][:1], learning["trajectory"]["x1"][:1])
    assert oracle["trajectory"]["trace_cov"][0] < 1e-9 < learning["trajectory"]["trace_cov"][0]


def test_a_scenario_file_is_a_str_or_a_path():
    """run_scenario takes a TOML file as a str or an os.PathLike, and names
    the argument for anything else."""
    import pathlib

    drone = pathlib.Path(__file__).resolve().parents[2] / "examples" / "drone.toml"
    overrides = {"steps": 5}
    a = bc.run_scenario(drone, seed=1, overrides=overrides)
    b = bc.run_scenario(str(drone), seed=1, overrides=overrides)
    assert a["min_barrier"] == b["min_barrier"] and a["steps"] == 5
    with pytest.raises(bc.InputError, match="name: expected a built-in name or a path"):
        bc.run_scenario(3)
