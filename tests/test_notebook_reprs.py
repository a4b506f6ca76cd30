"""What a notebook shows: ``_repr_html_`` and ``_repr_markdown_`` of the public objects.

Expected values: the trap example by hand (from ``start`` 0.4 reaches ``exit``, whose ``stay``
ends in the decoy with 0.25: 0.1 unaltered; reading the loop's sensor as ``o0`` sends the 0.6
in the loop on, half into the decoy: 0.1 + 0.3 = 0.4), with its names made hostile to HTML
and Markdown: the loop's sensor is ``<o&1>``, the decoy state ``de|coy*``.
"""

from __future__ import annotations

from html.parser import HTMLParser
from pathlib import Path

import pytest
import yaml

import misdirect
from misdirect.core import notebook as nb

ROOT = Path(__file__).resolve().parents[1]
SENSOR = "<o&1>"
DECOY = "de|coy*"


def _hostile_trap() -> misdirect.Problem:
    text = (ROOT / "examples" / "trap.yaml").read_text(encoding="utf-8")
    document = yaml.safe_load(text)
    document["name"] = "trap <script>"
    pomdp = document["pomdp"]
    pomdp["observe"]["loop"] = SENSOR
    pomdp["states"] = [DECOY if s == "decoy" else s for s in pomdp["states"]]
    pomdp["observe"][DECOY] = pomdp["observe"].pop("decoy")
    pomdp["transitions"] = [[DECOY if x == "decoy" else x for x in t] for t in pomdp["transitions"]]
    pomdp["absorbing"] = ["goal", DECOY]
    document["deception"]["decoy"] = [DECOY]
    return misdirect.problem_from_dict(document, source="trap.yaml")


class _Text(HTMLParser):
    """The text a browser shows, and whether the markup parsed into balanced elements."""

    def __init__(self) -> None:
        super().__init__()
        self.parts: list[str] = []
        self.open: list[str] = []

    def handle_starttag(self, tag: str, attrs: object) -> None:
        self.open.append(tag)

    def handle_endtag(self, tag: str) -> None:
        assert self.open and self.open.pop() == tag, f"</{tag}> closes nothing open"

    def handle_data(self, data: str) -> None:
        self.parts.append(data)


def _shown(markup: str) -> str:
    parser = _Text()
    parser.feed(markup)
    parser.close()
    assert parser.open == [], f"left open: {parser.open}"
    return " ".join(parser.parts)


def _check_escaped(markup: str, markdown: str, *, titled: bool = True) -> str:
    """Raw names never reach the markup; the browser shows them as they are (and the
    problem's name in the title, when the object has one)."""
    for raw in (SENSOR, "<script>"):
        assert raw not in markup and raw not in markdown
    shown = _shown(markup)
    assert SENSOR in shown and ("trap <script>" in shown or not titled)
    assert "&lt;o&amp;1&gt;" in markdown
    return shown


@pytest.fixture(scope="module")
def trap() -> misdirect.Problem:
    return _hostile_trap()


def test_the_problem_shows_its_sizes_and_names(trap: misdirect.Problem):
    markup, markdown = trap._repr_html_(), trap._repr_markdown_()
    shown = _check_escaped(markup, markdown)
    pomdp = trap.pomdp
    assert f"states {pomdp.n_states} ({int(pomdp.absorbing.sum())} absorbing)" in shown
    assert f"observations ({pomdp.n_observations})" in shown
    assert f"memory nodes {trap.controller.n_nodes} " in shown
    for name in pomdp.observations:
        assert name in shown
    assert DECOY in shown and "de\\|coy\\*" in markdown  # a pipe would split the table
    assert f"- states: {pomdp.n_states} (2 absorbing)" in markdown
    assert f"- observations ({pomdp.n_observations}):" in markdown


def test_the_solve_result_shows_every_budget(trap: misdirect.Problem):
    result = misdirect.solve(trap, budgets=[0, 1])
    assert result.probability == pytest.approx(0.4, abs=1e-12)
    markup, markdown = result._repr_html_(), result._repr_markdown_()
    shown = _check_escaped(markup, markdown)
    assert "budget status value proven bound gap cost alteration" in shown
    for point in result.curve:
        assert f"{point.probability:.6f}" in shown and point.status.value in shown
    assert "0.100000" in shown and "0.400000" in shown  # by hand: unaltered, then o1 → o0
    assert f"{SENSOR} → o0" in shown
    assert "| 1 | optimal | 0.400000 | 0.400000 |" in markdown
    assert "&lt;o&amp;1&gt; → o0" in markdown
    # one change never breaks across lines; the list wraps between changes
    assert '<span style="white-space: nowrap;">&lt;o&amp;1&gt; → o0</span>' in markup
    assert f"max-width: {nb.MAX_WIDTH}" in markup


def test_a_point_shows_status_value_bound_gap_and_alteration(trap: misdirect.Problem):
    point = misdirect.solve(trap, budgets=[1]).final
    shown = _check_escaped(point._repr_html_(), point._repr_markdown_(), titled=False)
    assert "status optimal" in shown and "value 0.400000" in shown
    assert "proven bound 0.400000" in shown and f"{SENSOR} → o0" in shown
    assert point.gap is not None and "gap " in shown
    assert "Budget 1" in point._repr_markdown_()


def test_the_evaluation_shows_where_runs_end(trap: misdirect.Problem):
    report = misdirect.evaluate(trap, trap.alteration({SENSOR: "o0"}))
    shown = _check_escaped(report._repr_html_(), report._repr_markdown_())
    assert "Pr(reach decoy) 0.400000" in shown
    assert f"decoy {DECOY} 0.400000" in shown and "goal goal 0.600000" in shown


def test_audit_and_harden_show_their_tables(trap: misdirect.Problem):
    audit = misdirect.audit(trap, budget=1)
    shown = _check_escaped(audit._repr_html_(), audit._repr_markdown_())
    assert f"optimum at budget 1 {audit.probability:.6f}" in shown
    for row in audit.sensors:
        assert f"{row.observation} {row.criticality:.6f}" in shown
    assert "the attacker's optimum per budget" in shown and "0.400000" in shown

    plan = misdirect.harden(trap, budget=1, protect_budget=1)
    shown = _check_escaped(plan._repr_html_(), plan._repr_markdown_())
    assert f"protect {' '.join(plan.protection) or 'nothing'}" in shown
    assert f"before {plan.value_before:.6f}" in shown and f"after {plan.value_after:.6f}" in shown
    for point in plan.curve:
        assert f"{point.probability:.6f}" in shown


def test_a_long_list_says_how_many_it_leaves_out():
    names = [f"s{i}" for i in range(nb.LISTED + 7)]
    cell = nb.names(names, where="problem.pomdp.observations")
    assert cell.parts is not None and len(cell.parts) == nb.LISTED + 1
    assert cell.parts[-1] == "… and 7 more (problem.pomdp.observations)"
    assert nb.names([]).text == "none" and nb.changes({}).text == "none"


def test_markdown_escapes_its_own_characters():
    assert nb.escape_markdown("a|b*c_d`e<f>&g") == "a\\|b\\*c\\_d\\`e&lt;f&gt;&amp;g"
    view = nb.View("t", (), [nb.Table(("x",), [(nb.text("| <b>"),)])])
    assert "| \\| &lt;b&gt; |" in view.markdown()
