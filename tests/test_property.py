"""PRISM properties as the objective (issue 53, item 2): ``P=? [F b]``, ``P=? [a U b]``,
``P=? [F<=k b]``, ``P=? [a U<=k b]``.

The reference is Storm's own model check of the induced chain of the *unchanged* problem
(decoy ``"decoy"``, no property): the chain misdirect exports (labels ``init``, ``decoy``),
with the model's other labels added here by the world state's name (``x=1,y=1``), checked
with the property itself. misdirect's value comes from its own reduction (absorbing states
for ``U``, a step counter for ``<=k``), so the two routes share only the product chain's
construction, which tests/test_storm_agreement.py checks on its own. The model and the
controller are our own (tests/data/patrol.prism, tests/data/patrol.rules.yaml).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from misdirect import evaluate
from misdirect.cli import app
from misdirect.core.product import build_product
from misdirect.errors import ProblemError
from misdirect.io.export import chain_drn_text
from misdirect.io.model_problem import problem_from_model

stormpy = pytest.importorskip("stormpy")

DATA = Path(__file__).resolve().parent / "data"
MODEL = DATA / "patrol.prism"
RULES = DATA / "patrol.rules.yaml"
GOAL = '"goal"'
FLAGS = ["--controller", str(RULES), "--goal", GOAL]
runner = CliRunner()

# the model's labels, by the state's variables (tests/data/patrol.prism)
LABELS = {
    "avoid": lambda x, y: x == 1 and y == 1,
    "top": lambda x, y: y == 1,
    "left": lambda x, y: x == 0,
}

PROPERTIES = [
    'P=? [F "decoy"]',
    'P=? [!"avoid" U "decoy"]',
    'P=? [F<=0 "decoy"]',
    'P=? [F<=1 "decoy"]',
    'P=? [F<=3 "decoy"]',
    'P=? [F<=4 "decoy"]',
    'P=? [!"avoid" U<=3 "decoy"]',
    'P=? [!"avoid" U<=5 "decoy"]',
]
# the same properties over the target y = 1 (reached in one step), so F<=1 is not 0
TOP_PROPERTIES = ["P=? [F<=0 (y=1)]", "P=? [F<=1 (y=1)]", "P=? [(x=0) U<=3 (y=1)]"]


def _base(budget: float = 1):
    return problem_from_model(MODEL, controller=RULES, decoy="decoy", goal=GOAL, budget=budget)


def _with(prop: str, budget: float = 1):
    return problem_from_model(MODEL, controller=RULES, goal=GOAL, property=prop, budget=budget)


def _labelled_chain(problem, alpha, path: Path) -> Path:
    """The exported chain of ``problem`` under ``alpha`` with the model's labels added (by
    the world state's variables)."""
    chain = build_product(problem, alpha)
    text = chain_drn_text(problem, chain.matrix, chain.world_state, chain.node, chain.initial)
    names = [problem.pomdp.states[int(s)] for s in chain.world_state]
    lines = text.splitlines()
    for i, line in enumerate(lines):
        match = re.match(r"^state (\d+)", line)
        if match is None or "=" not in names[int(match[1])]:
            continue  # not a state line, or the alarm sink
        values = dict(item.split("=") for item in names[int(match[1])].split(","))
        x, y = int(values["x"]), int(values["y"])
        extra = [name for name, holds in LABELS.items() if holds(x, y)]
        lines[i] = " ".join([line, *extra])
    path.write_text("\n".join(lines) + "\n")
    return path


def _storm(path: Path, prop: str) -> float:
    model = stormpy.build_model_from_drn(str(path))
    text = prop.replace("(y=1)", '"top"').replace("(x=0)", '"left"')
    formula = stormpy.parse_properties(text)[0]
    result = stormpy.model_checking(model, formula)
    return float(result.get_value(model.initial_states[0]))


def _tolerance(prop: str) -> float:
    """Storm's default engine iterates an unbounded property to a relative 1e-6; a bounded
    one is k exact matrix-vector steps."""
    return 1e-9 if "<=" in prop else 1e-6


def _alterations(problem, budget: float):
    """Every alteration of cost at most ``budget`` changing at most one observation."""
    found = [problem.identity()]
    pomdp = problem.pomdp
    for o in range(pomdp.n_observations):
        for t in range(pomdp.n_observations):
            if t == o or o == pomdp.initial_observation:  # never altered
                continue
            alpha = problem.identity()
            alpha[o] = t
            if problem.cost.fits(alpha, budget):
                found.append(alpha)
    return found


@pytest.fixture(scope="module")
def base():
    return _base()


@pytest.fixture(scope="module")
def alterations(base):
    found = _alterations(base, 1)
    assert len(found) == 1 + 4 * 4  # the identity, and each of four observations read as another
    return found


@pytest.mark.parametrize("prop", PROPERTIES)
def test_every_budget_one_alteration_against_storm(tmp_path, base, alterations, prop):
    """misdirect's value of the property under each alteration (unaltered included) is
    Storm's check of the property on the unchanged problem's chain."""
    problem = _with(prop)
    assert np.array_equal(problem.decoy[: base.pomdp.n_states], base.decoy)
    for k, alpha in enumerate(alterations):
        ours = evaluate(problem, alpha).probability
        storm = _storm(_labelled_chain(base, alpha, tmp_path / f"c{k}.drn"), prop)
        assert ours == pytest.approx(storm, abs=_tolerance(prop)), (
            prop,
            base.changed_observations(alpha),
        )


@pytest.mark.parametrize("prop", TOP_PROPERTIES)
def test_expressions_and_k_zero_and_one_against_storm(tmp_path, alterations, prop):
    base = problem_from_model(MODEL, controller=RULES, decoy="y=1", goal=GOAL, budget=1)
    problem = _with(prop)
    values = []
    for k, alpha in enumerate(alterations):
        ours = evaluate(problem, alpha).probability
        storm = _storm(_labelled_chain(base, alpha, tmp_path / f"c{k}.drn"), prop)
        assert ours == pytest.approx(storm, abs=1e-9), (prop, k)
        values.append(ours)
    if "F<=0" in prop:
        assert max(values) == 0  # the start is not in the top row
    else:
        assert min(values) > 0


def test_the_bounds_are_the_steps_of_storm(tmp_path, base):
    """F<=k grows with k to F, and differs at every k from 2 to 4 (the decoy is two steps
    away at the least): an off-by-one would show."""
    alpha = base.alteration({"y=0,!wall,!home": "y=1,!wall,!home"})
    values = [evaluate(_with(f'P=? [F<={k} "decoy"]'), alpha).probability for k in range(7)]
    chain = _labelled_chain(base, alpha, tmp_path / "c.drn")
    storm = [_storm(chain, f'P=? [F<={k} "decoy"]') for k in range(7)]
    assert values == pytest.approx(storm, abs=1e-12)
    assert values[0] == values[1] == 0 < values[2] < values[3] < values[4]
    unbounded = evaluate(_with('P=? [F "decoy"]'), alpha).probability
    assert values[-1] <= unbounded + 1e-12


@pytest.mark.parametrize("prop", [PROPERTIES[1], PROPERTIES[4], PROPERTIES[6]])
def test_solve_certifies_the_brute_force_optimum(tmp_path, base, alterations, prop):
    """solve's certified optimum at budget 1 is the best of Storm's values over every
    budget-1 alteration; on the command line, with --property and no --decoy."""
    best = max(
        _storm(_labelled_chain(base, alpha, tmp_path / f"c{k}.drn"), prop)
        for k, alpha in enumerate(alterations)
    )
    result = runner.invoke(
        app,
        ["solve", str(MODEL), *FLAGS, "--property", prop, "--budget", "1", "--json"],
    )
    assert result.exit_code == 0, result.output
    payload = json.loads(result.stdout)
    assert payload["status"] == "optimal"
    assert payload["value"] == pytest.approx(best, abs=_tolerance(prop))
    assert best > evaluate(_with(prop), base.identity()).probability  # the attack matters


@pytest.mark.parametrize("method", ["exhaustive", "incremental", "branch-and-bound", "milp"])
def test_every_method_agrees(method):
    from misdirect import solve

    problem = _with(PROPERTIES[6])
    reference = solve(problem, method="exhaustive").curve[-1].probability
    assert solve(problem, method=method).curve[-1].probability == pytest.approx(
        reference, abs=1e-12
    )


def test_export_chain_of_the_property_problem_agrees_with_storm(tmp_path):
    """export-chain with --property writes the reduced chain: Storm's F "decoy" on it is the
    value, and Storm's bounded property on the plain chain too."""
    alter = ["--alter", "y=0,!wall,!home=y=1,!wall,!home"]
    flags = ["--controller", str(RULES), "--goal", GOAL, *alter]
    chain = tmp_path / "reduced.drn"
    prop = PROPERTIES[6]
    result = runner.invoke(
        app,
        ["export-chain", str(MODEL), *flags, "--property", prop, "-o", str(chain), "--json"],
    )
    assert result.exit_code == 0, result.output
    value = json.loads(result.stdout)["value"]
    evaluated = runner.invoke(app, ["evaluate", str(MODEL), *flags, "--property", prop, "--json"])
    assert json.loads(evaluated.stdout)["value"] == pytest.approx(value, abs=1e-12)
    assert _storm(chain, 'P=? [F "decoy"]') == pytest.approx(value, abs=1e-6)
    plain = tmp_path / "plain.drn"
    result = runner.invoke(
        app, ["export-chain", str(MODEL), *flags, "--decoy", "decoy", "-o", str(plain)]
    )
    assert result.exit_code == 0, result.output
    base = _base()
    labelled = _labelled_chain(base, base.alteration({"y=0,!wall,!home": "y=1,!wall,!home"}), plain)
    assert _storm(labelled, prop) == pytest.approx(value, abs=1e-9)


def test_the_problem_file_field_is_the_flag(tmp_path):
    prop = PROPERTIES[6]
    document = {
        "format": "misdirect/v1",
        "pomdp": {"prism": str(MODEL), "terminal": GOAL},
        "controller": yaml.safe_load(RULES.read_text()),
        "deception": {"property": prop, "budget": 1},
    }
    path = tmp_path / "patrol.yaml"
    path.write_text(yaml.safe_dump(document))
    by_file = runner.invoke(app, ["solve", str(path), "--json"])
    by_flags = runner.invoke(
        app,
        ["solve", str(MODEL), *FLAGS, "--property", prop, "--budget", "1", "--json"],
    )
    assert by_file.exit_code == 0, by_file.output
    assert json.loads(by_file.stdout)["value"] == json.loads(by_flags.stdout)["value"]
    # the decoy given too must name the property's target
    document["deception"]["decoy"] = {"label": "decoy"}
    path.write_text(yaml.safe_dump(document))
    assert runner.invoke(app, ["evaluate", str(path)]).exit_code == 0
    document["deception"]["decoy"] = {"label": "avoid"}
    path.write_text(yaml.safe_dump(document))
    result = runner.invoke(app, ["evaluate", str(path), "--json"])
    assert result.exit_code != 0
    assert "deception.property" in result.stdout and "target is not the decoy" in result.stdout


def test_convert_writes_the_property(tmp_path):
    prop = PROPERTIES[6]
    out = tmp_path / "patrol.yaml"
    result = runner.invoke(
        app, ["convert", str(MODEL), *FLAGS, "--property", prop, "--budget", "1", "-o", str(out)]
    )
    assert result.exit_code == 0, result.output
    assert yaml.safe_load(out.read_text())["deception"]["property"] == prop
    by_file = runner.invoke(app, ["solve", str(out), "--json"])
    by_flags = runner.invoke(
        app, ["solve", str(MODEL), *FLAGS, "--property", prop, "--budget", "1", "--json"]
    )
    assert json.loads(by_file.stdout)["value"] == json.loads(by_flags.stdout)["value"]


def test_a_bounded_property_and_a_monitor_end_at_the_first_alarm(tmp_path):
    """A step bound and a monitor together: the run ends at the first of the two alarms.
    Against the chain of the problem with the monitor alone, checked by Storm with the bound
    (the alarm label marks the monitor's sink, which nothing leaves)."""
    from misdirect.core.monitor import Monitor, Transition, with_monitor
    from misdirect.core.objective_property import within_steps

    base = _base()
    watch = Monitor.from_transitions(
        states=["ok", "caught"],
        initial="ok",
        alarm=["caught"],
        transitions=[
            Transition("ok", "y=1,wall,!home", "caught"),
            Transition("ok", "*", "ok"),
        ],
        observations=base.pomdp.observations,
        actions=base.pomdp.actions,
    )
    watched = with_monitor(base, watch)
    alpha = base.alteration({"y=1,!wall,!home": "y=1,wall,!home"})
    chain = _labelled_chain(watched, alpha, tmp_path / "w.drn")
    for k in (0, 1, 3, 5):
        both = within_steps(watched, k)
        other_order = with_monitor(within_steps(base, k), watch)
        storm = _storm(chain, f'P=? [!"alarm" U<={k} "decoy"]')
        assert evaluate(both, alpha).probability == pytest.approx(storm, abs=1e-9)
        assert evaluate(other_order, alpha).probability == pytest.approx(storm, abs=1e-9)
    assert storm < evaluate(within_steps(base, 5), alpha).probability  # the monitor bites


@pytest.mark.parametrize(
    ("prop", "says"),
    [
        ('R=? [F "decoy"]', "a reward property"),
        ('Pmin=? [F "decoy"]', "Pmin"),
        ('P>0.5 [F "decoy"]', "a probability bound"),
        ('P=? [G "decoy"]', "G (globally)"),
        ('P=? [X "decoy"]', "X (next)"),
        ('P=? [F ("decoy" & F "goal")]', "a nested property"),
        ('P=? [F>=2 "decoy"]', "a lower step bound"),
        ('multi(P=? [F "decoy"], P=? [F "goal"])', "multi-objective"),
        ('P=? [F "nowhere"]', "no label 'nowhere'"),
        ("P=? [F", "Storm cannot parse it"),
    ],
)
def test_unsupported_properties_are_named(prop, says):
    with pytest.raises(ProblemError, match=re.escape(says)) as caught:
        _with(prop)
    assert caught.value.source == "property"
    result = runner.invoke(
        app,
        ["evaluate", str(MODEL), "--controller", str(RULES), "--property", prop, "--json"],
    )
    assert result.exit_code != 0
    error = json.loads(result.stdout)["error"]
    assert error["source"] == "--property"
    assert says in error["message"]


def test_a_property_needs_a_storm_model(tmp_path):
    tiny = Path(__file__).resolve().parents[1] / "examples" / "tiny.yaml"
    document = yaml.safe_load(tiny.read_text())
    document["deception"]["property"] = 'P=? [F "trap"]'
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(document))
    result = runner.invoke(app, ["evaluate", str(path), "--json"])
    assert result.exit_code != 0
    assert "needs a PRISM or DRN model" in result.stdout
    # --property describes a PRISM or DRN model: refused with a problem file
    result = runner.invoke(app, ["evaluate", str(tiny), "--property", 'P=? [F "trap"]'])
    assert result.exit_code != 0
