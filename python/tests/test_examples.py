"""The examples run end to end (short)."""

from __future__ import annotations

import importlib.util
import json
import pathlib
import runpy
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]


def test_fit_predict_filter_runs(capsys):
    runpy.run_path(str(ROOT / "examples" / "fit_predict_filter.py"), run_name="__main__")
    out = capsys.readouterr().out
    assert "derivatives: True" in out and "FilterResult" in out


def test_gym_pendulum_runs(tmp_path):
    out = tmp_path / "gym.json"
    subprocess.run([sys.executable, str(ROOT / "examples" / "gym_pendulum.py"), "--episodes", "2",
                    "--policy", "swing-up", "--seed", "7", "--out", str(out)], check=True,
                   capture_output=True)
    result = json.loads(out.read_text())
    rows = {r["controller"]: r for r in result["rows"]}
    assert set(rows) == {"unfiltered", "mean-cbf", "bayes-cbf", "bayes-cbf-zero-prior"}
    assert rows["unfiltered"]["episodes_with_h_below_0"] == 2
    assert 1.0 < result["integrator_energy_rise"] < 3.0


def test_gym_pendulum_asks_for_matplotlib_before_it_runs(tmp_path):
    if importlib.util.find_spec("matplotlib") is not None:
        pytest.skip("matplotlib is installed: the figure can be drawn")
    out = tmp_path / "gym.json"
    r = subprocess.run([sys.executable, str(ROOT / "examples" / "gym_pendulum.py"), "--episodes",
                        "100", "--figure", str(tmp_path / "f.png"), "--out", str(out)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--figure needs matplotlib" in r.stderr, r.stderr
    assert not out.exists()


def test_gym_mountaincar_runs(tmp_path):
    out = tmp_path / "mc.json"
    subprocess.run([sys.executable, str(ROOT / "examples" / "gym_mountaincar.py"), "--episodes",
                    "2", "--seed", "11", "--out", str(out)], check=True, capture_output=True)
    rows = {r["controller"]: r for r in json.loads(out.read_text())["rows"]}
    assert set(rows) == {"unfiltered", "bayes-cbf-learn-all", "bayes-cbf-skip-clips"}
    assert rows["unfiltered"]["episodes_with_h_below_0"] == 2
    skip = rows["bayes-cbf-skip-clips"]
    assert skip["unlearned_steps"] > 0 and rows["bayes-cbf-learn-all"]["unlearned_steps"] == 0
