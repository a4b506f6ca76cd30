"""``--exact``: an answer valued on the model as written, in rational arithmetic by Storm.

The model is a robot that lingers: in ``x=1``, going on leaves only once in 10^10 steps, to
the decoy with probability 1/(3·10^10) and to the goal with 2/(3·10^10); waiting leaves at
once, to the decoy with probability 1/7. By hand, going is worth (1/(3·10^10)) / 10^-10 = 1/3
and waiting 1/7. In doubles ``1 - 1/10^10`` is rounded, and the leak it leaves is off by
about 10^-7 of itself, so the chain as loaded is worth 0.33333331 (proven to 1e-15 on that
chain): the premise of every test here, checked in the first.
"""

from __future__ import annotations

import json
from fractions import Fraction
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from misdirect import decoy_probability, load_problem
from misdirect.cli import app
from misdirect.errors import ProblemError
from misdirect.scenarios import paper_grid
from prism_product import storm_probability
from result_schema import checked

stormpy = pytest.importorskip("stormpy")
from misdirect.io.exact_model import exact_model  # noqa: E402  (needs stormpy)

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
DATA = Path(__file__).resolve().parent / "data"
runner = CliRunner()

LINGERING_PRISM = """\
pomdp
observables o endobservables
module robot
  x : [0..3] init 0;
  o : [0..2] init 0;
  [go]   x=0 -> 1:(x'=1)&(o'=1);
  [wait] x=0 -> 1:(x'=1)&(o'=1);
  [go]   x=1 -> (1-1/10000000000):(x'=1) + 1/30000000000:(x'=2)&(o'=2)
                + 2/30000000000:(x'=3)&(o'=2);
  [wait] x=1 -> 1/7:(x'=2)&(o'=2) + 6/7:(x'=3)&(o'=2);
  [go]   x>=2 -> true;
  [wait] x>=2 -> true;
endmodule
label "decoy" = x=2;
label "home" = x=3;
"""

LINGERING_DRN = """\
@type: POMDP
@parameters

@reward_models

@nr_states
4
@nr_choices
6
@model
state 0 {0} init
\taction go
\t\t1 : 1
\taction wait
\t\t1 : 1
state 1 {1}
\taction go
\t\t1 : 9999999999/10000000000
\t\t2 : 1/30000000000
\t\t3 : 2/30000000000
\taction wait
\t\t2 : 1/7
\t\t3 : 6/7
state 2 {2} decoy
\taction go
\t\t2 : 1
state 3 {2} home
\taction go
\t\t3 : 1
"""

THIRD, SEVENTH = Fraction(1, 3), Fraction(1, 7)


def _controller(second: str, arrived: str, lingering: object = "go") -> dict:
    """Wait on the arrival reading; ``lingering`` (an action or a distribution) elsewhere."""
    return {
        "nodes": ["m"],
        "initial": "m",
        "rules": [
            {"node": "*", "obs": arrived, "action": "wait", "next": "m"},
            {"node": "*", "obs": second, "action": lingering, "next": "m"},
            {"node": "*", "obs": "*", "action": "go", "next": "m"},
        ],
    }


def _lingering(tmp_path: Path, kind: str = "prism", lingering: object = "go", decoy=None):
    model = tmp_path / f"lingering.{kind}"
    model.write_text(LINGERING_PRISM if kind == "prism" else LINGERING_DRN)
    names = ("o=1", "o=2") if kind == "prism" else ("obs1", "obs2")
    document = {
        "format": "misdirect/v1",
        "pomdp": {kind: model.name},
        "controller": _controller(*names, lingering=lingering),
        "deception": {"decoy": decoy or {"label": "decoy"}, "budget": 1},
    }
    path = tmp_path / f"lingering-{kind}.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return load_problem(path), names


@pytest.mark.parametrize("kind", ["prism", "drn"])
def test_the_model_as_written_is_worth_a_third_where_its_doubles_are_not(tmp_path, kind):
    problem, (second, arrived) = _lingering(tmp_path, kind)
    loaded = decoy_probability(problem, problem.identity())
    assert abs(loaded - 1 / 3) > 1e-8  # the premise: the input's rounding moves the 8th digit
    model = exact_model(problem)
    going = model.value(problem.identity())
    assert going.value == THIRD
    assert going.loaded == loaded
    assert going.difference == pytest.approx(float(THIRD - Fraction(loaded)), rel=1e-12)
    waiting = model.value(problem.alteration({second: arrived}))
    assert waiting.value == SEVENTH
    assert abs(waiting.difference) < 1e-15  # no lingering: the doubles are as good


def test_a_randomized_controller_and_weighted_decoys_by_hand(tmp_path):
    """Going or waiting with probability 1/2 each step in x=1: per step the robot leaves to
    the decoy with 1/14 + 1/(6·10^10) and at all with 1/2 + 1/(2·10^10)."""
    problem, _ = _lingering(tmp_path, lingering={"go": 0.5, "wait": 0.5})
    leave_decoy = Fraction(1, 14) + Fraction(1, 6 * 10**10)
    leave = Fraction(1, 2) + Fraction(1, 2 * 10**10)
    assert exact_model(problem).value(problem.identity()).value == leave_decoy / leave
    weighted, _ = _lingering(
        tmp_path,
        decoy={
            "trap": {"weight": 0.5, "label": "decoy"},
            "home": {"weight": 0.25, "label": "home"},
        },
    )
    # a third of the runs score 1/2, two thirds 1/4
    assert exact_model(weighted).value(weighted.identity()).value == THIRD


def test_a_controller_whose_decimals_are_no_distribution_is_refused(tmp_path):
    # 1/3 and 2/3 written to 16 digits: as decimals they add up to 0.9999999999999999
    problem, _ = _lingering(
        tmp_path, lingering={"go": 0.3333333333333333, "wait": 0.6666666666666666}
    )
    with pytest.raises(ProblemError, match="decimals add up to"):
        exact_model(problem).value(problem.identity())


def test_storms_own_product_agrees_on_the_maze(tmp_path):
    """The maze example (PRISM, built terminal as PAYNT builds it, PAYNT's controller) has
    decimal probabilities 0.6 and 0.4: Storm composing the product itself from the chain's
    fractions (tests/prism_product.py) must give the same rational."""
    for name in ("maze.prism", "maze.yaml"):
        (tmp_path / name).write_text((EXAMPLES / name).read_text())
    (tmp_path / "maze.fsc.json").write_text((DATA / "maze.fsc.json").read_text())
    problem = load_problem(tmp_path / "maze.yaml")
    model = exact_model(problem)
    changes = [{}, {problem.pomdp.observations[1]: problem.pomdp.observations[2]}]
    for change in changes:
        altered = problem.alteration(change)
        assert float(model.value(altered).value) == pytest.approx(
            storm_probability(tmp_path, problem, altered), abs=1e-15
        )


def test_only_worlds_that_storm_builds_have_an_exact_value():
    with pytest.raises(ProblemError, match="not read from a file"):
        exact_model(paper_grid(5))
    with pytest.raises(ProblemError, match="explicit model") as error:
        exact_model(load_problem(EXAMPLES / "tiny.yaml"))
    assert error.value.field == "pomdp"


def test_evaluate_and_solve_print_the_value_as_written(tmp_path):
    _lingering(tmp_path)
    path = str(tmp_path / "lingering-prism.yaml")
    result = runner.invoke(app, ["evaluate", path, "--exact", "--json"])
    assert result.exit_code == 0, result.output
    document = checked(result.stdout)
    assert Fraction(document["exact"]["value"]) == THIRD
    assert any("model as written" in n for n in document["notes"])
    result = runner.invoke(app, ["solve", path, "--budget", "0..1", "--exact", "--json"])
    assert result.exit_code == 0, result.output
    document = checked(result.stdout)
    assert [Fraction(p["exact"]["value"]) for p in document["curve"]] == [THIRD, THIRD]
    assert Fraction(document["exact"]["value"]) == THIRD
    # without --exact nothing changes shape
    plain = json.loads(runner.invoke(app, ["solve", path, "--budget", "0..1", "--json"]).stdout)
    assert "exact" not in plain and all("exact" not in p for p in plain["curve"])
    text = runner.invoke(app, ["evaluate", path, "--exact"])
    assert "on the model as written" in text.output and "0.333333333333" in text.output
    refused = runner.invoke(app, ["solve", "--scenario", "paper-grid", "--exact"])
    assert refused.exit_code == 2 and "not read from a file" in refused.output
