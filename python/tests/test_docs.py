"""The calibration report's table is the stored summary's: every row of
docs/calibration.md's table is what scripts/calibration-table makes of
docs/calibration-summary.json, in the same order."""

from __future__ import annotations

import subprocess
import sys

from conftest import ROOT


def test_calibration_table_is_the_stored_summarys():
    made = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "calibration-table"),
         str(ROOT / "docs" / "calibration-summary.json")],
        capture_output=True, text=True, check=True,
    ).stdout.splitlines()
    page = (ROOT / "docs" / "calibration.md").read_text().splitlines()
    table = [line for line in page if line.startswith(("| vehicle,", "| pendulum,"))]
    # the page's first table is the summary's; tables below it quote other runs
    assert len(made) == 40
    assert table[: len(made)] == made


def test_the_readmes_python_runs_as_written():
    """Every ```python block of the README runs on its own, in order."""
    text = (ROOT / "README.md").read_text()
    blocks = text.split("```python\n")[1:]
    assert len(blocks) >= 2
    for block in blocks:
        code = block.split("```", 1)[0]
        exec(compile(code, "README.md", "exec"), {})
