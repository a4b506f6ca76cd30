"""Issue 53, item 5: progress that shows the phase (loading, product, bounds, enumeration
with a count and a rate, search), the facts from the library and the words from the CLI."""

from __future__ import annotations

import io

from rich.console import Console

from misdirect import solve
from misdirect.cli import common
from misdirect.scenarios import paper_grid
from misdirect.solvers.base import report


def test_an_enumeration_reports_its_count_and_rate_after_the_product_phase():
    calls = []

    def watch(done, total, *, stage=None, detail=None, note=None, rate=None):
        calls.append((stage, done, total, rate))

    result = solve(paper_grid(5), budgets=range(5), method="incremental", progress=watch)
    stages = [stage for stage, *_ in calls if stage is not None]
    assert stages[0] == "product"  # before any method's stage
    enumerated = [call for call in calls if call[0] == "enumeration"]
    assert enumerated, stages
    last = enumerated[-1]
    assert last[1] == result.curve[-1].stats.evaluations > 0  # done: alterations valued
    assert 0 < last[1] <= last[2]  # of those within the budget
    assert last[3] is not None and last[3] > 0  # alterations a second


def test_a_callback_without_rate_still_works():
    """``rate`` goes only to callbacks that take it: one written before it keeps working."""
    calls = []

    def old(done, total, *, stage=None, detail=None, note=None):
        calls.append(stage)

    report(old, 1, 2, stage="enumeration", rate=10.0)
    report(lambda done, total, **info: calls.append(info.get("rate")), 1, 2, rate=10.0)
    assert calls == ["enumeration", 10.0]


def test_the_bars_show_the_phase_then_the_rate_and_the_time_left(monkeypatch):
    console = Console(file=io.StringIO(), record=True, force_terminal=True, width=160)
    monkeypatch.setattr(common, "err", console)
    with common.ProgressBars(enabled=True) as bars:
        assert bars is not None and bars.bar is not None
        progress = bars.task("solving")
        progress(0, 0, stage="product")
        task = bars.bar.tasks[0]
        assert task.total is None and "building the product chain" in task.description
        progress(0, 1000, stage="enumeration")
        progress(400, 1000, stage="enumeration", rate=100.0)
        task = bars.bar.tasks[0]
        assert "enumerating alterations" in task.description
        assert task.fields["detail"] == "100/s, about 6 s left"
        progress(0, 0, stage="bounds")
        assert bars.bar.tasks[0].fields["detail"] == ""  # the last phase's detail is gone
        bars.bar.refresh()
    text = console.export_text()
    assert "building the product chain" in text or "bounds" in text


def test_time_left_reads_as_an_estimate():
    assert common.eta(0.2) == "about 1 s"
    assert common.eta(150) == "about 2 min"
    assert common.eta(5400) == "about 1.5 h"


def test_no_bars_without_a_terminal(monkeypatch):
    monkeypatch.setattr(common, "err", Console(file=io.StringIO(), force_terminal=False))
    with common.ProgressBars(enabled=True) as bars:
        assert bars is None
