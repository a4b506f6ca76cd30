"""The MILP benchmark in a reduced mode, so that it cannot rot (no timing asserted)."""

import csv
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).parent.parent


def test_milp_benchmark_reduced_mode(tmp_path):
    subprocess.run(
        [
            sys.executable,
            str(ROOT / "bench" / "milp_scaling.py"),
            "--sizes",
            "5",
            "--paper-sizes",
            "5,7",
            "--paper-solve-sizes",
            "",
            "--budgets",
            "0..1",
            "--out",
            str(tmp_path),
        ],
        check=True,
        capture_output=True,
    )
    rows = list(csv.DictReader((tmp_path / "milp_scaling.csv").open()))
    compact = [r for r in rows if r["formulation"] == "compact"]
    # SPEC §3, budgets 0 and 1
    assert [float(r["probability"]) for r in compact] == pytest.approx(
        [0.084957, 0.719924], abs=5e-7
    )
    paper = {int(r["n"]): r for r in rows if r["formulation"] == "paper"}
    for n in (5, 7):  # closed form of misdirect.milp.paper, E = 4n² - 9
        edges = 4 * n * n - 9
        assert int(paper[n]["variables"]) == 64 + 24 * n * n + 192 * edges
        assert int(paper[n]["rows"]) == 10 + 24 * n * n + 4 * 192 * edges
    assert (tmp_path / "milp_scaling.png").stat().st_size > 10_000
    assert (tmp_path / "milp_scaling.json").exists()
    assert "| 5 | compact | 68 | 21 | 99 |" in (tmp_path / "milp_scaling.md").read_text()
