"""PAYNT as it comes: controllers synthesized here by the installed PAYNT, loaded unedited.

The models in tests/data are our own, in the style of PAYNT's benchmarks. Each controller is
synthesized in the test through PAYNT's own API (no misdirect code involved) and written as
PAYNT writes it; misdirect then loads it as ``controller: {paynt: FILE}``. The expected values
come from Storm: the PRISM program with a controller module added, built by Storm with the
property's target terminal (as PAYNT builds), where each state reads PAYNT's observation of
it, taken from PAYNT's own model. They are also compared with the value PAYNT reports.
"""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from misdirect import decoy_probability, load_problem, solve
from misdirect.cli import app
from result_schema import checked

stormpy = pytest.importorskip("stormpy")
try:
    import paynt.api
    import paynt.parser.sketch
    import paynt.utils.timer
except ImportError:  # pragma: no cover - CI installs it with the test extra
    pytest.skip("paynt is not installed (pip install 'misdirect[paynt]')", allow_module_level=True)

from prism_product import prism_product  # noqa: E402

DATA = Path(__file__).parent / "data"
runner = CliRunner()
PAYNT_TOLERANCE = 1e-4  # PAYNT model checks to a precision of 1e-4

# model, constants, PAYNT's property, memory
CASES = {
    "maze": ("maze", None, 'Pmax=? [F "goal"]', 2),
    "geo": ("geo", None, 'Pmax=? [F "goal"]', 2),
    "grid": ("grid_avoid", "N=3", 'Pmax=? [F "goal"]', 2),
}


def _split_observables(text: str) -> str:
    """PAYNT reads ``observables`` only with the keyword and ``endobservables`` on lines of
    their own; our maze and geo write it on one line."""
    return re.sub(
        r"(?m)^observables\s+(.*?)\s+endobservables", r"observables\n\1\nendobservables", text
    )


def _constants(text: str, constants: str | None) -> str:
    for part in (constants or "").split(","):
        if part:
            name, value = part.split("=")
            text = re.sub(rf"const int {name};", f"const int {name} = {value};", text)
    return text


def _run_paynt(tmp_path: Path, case: str):
    """PAYNT's own API: its JSON of the controller (unedited), its value, its POMDP."""
    result, factory, _ = _synthesize(tmp_path, case)
    return json.loads(str(result.fsc)), float(result.value), factory.pomdp


def _synthesize(tmp_path: Path, case: str):
    """PAYNT's result, sketch factory and synthesizer; the controller written as PAYNT
    writes it to robot.fsc.json."""
    model, constants, prop, memory = CASES[case]
    sketch = tmp_path / f"{model}-sketch.prism"
    text = (DATA / f"{model}.prism").read_text()
    sketch.write_text(_constants(_split_observables(text), constants))
    props = tmp_path / "sketch.props"
    props.write_text(prop + "\n")
    paynt.utils.timer.GlobalTimer.start(20)
    factory, task = paynt.parser.sketch.Sketch.load_sketch(
        str(sketch), str(props), task_kwargs={"memory_size": memory}
    )
    synthesizer = paynt.api.get_synthesizer(factory, task, "ar", fsc_synthesis=True)
    synthesizer.synthesize(synthesizer.colored_mdp.parameter_space, print_stats=False)
    result = synthesizer.build_result()
    assert result.fsc is not None
    (tmp_path / "robot.fsc.json").write_text(str(result.fsc))  # PAYNT's own __str__: its JSON
    return result, factory, synthesizer


def _problem(tmp_path: Path, case: str, decoy: str = "bad", name: str = "p.yaml") -> Path:
    model, constants, prop, _ = CASES[case]
    pomdp = {"prism": str(DATA / f"{model}.prism"), "terminal_from": prop}
    if constants:
        pomdp["constants"] = constants
    document = {
        "format": "misdirect/v1",
        "pomdp": pomdp,
        "controller": {"paynt": "robot.fsc.json"},
        "deception": {"decoy": {"label": decoy}, "budget": 1},
    }
    path = tmp_path / name
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def _storm_values(tmp_path: Path, case: str, fsc: dict, pomdp) -> dict[str, float]:
    """Pr(F "bad") and Pr(F "goal") of the PRISM program composed with PAYNT's controller.

    Each state reads PAYNT's observation of it: the guard of observation k lists the states
    of PAYNT's own POMDP in it, by valuation. Unlabelled commands get PAYNT's names
    (module_cmd_k, k the command's position in its module)."""
    model, constants, prop, _ = CASES[case]
    source = _constants((DATA / f"{model}.prism").read_text(), constants)
    source = re.sub(r"(?ms)^observables\b.*?endobservables", "", source)
    source = re.sub(r'(?m)^observable\s+"[^"]*"\s*=[^;]*;', "", source).replace("pomdp", "mdp", 1)

    def name_commands(match: re.Match) -> str:
        module, body, count = match[1], match[2], iter(range(10**6))

        def label(command: re.Match) -> str:
            k = next(count)  # position among all commands of the module
            return f"{command[1]}[{command[2] or f'{module}_cmd_{k}'}]"

        named = re.sub(r"(?m)^(\s*)\[(\w*)\]", label, body)
        return f"module {module}{named}endmodule"

    source = re.sub(r"(?ms)^module (\w+)(.*?)endmodule", name_commands, source)
    guards: dict[int, list[str]] = {}
    for s in range(pomdp.nr_states):
        valuation = json.loads(str(pomdp.state_valuations.to_json(s)))
        items = [
            (k if v else f"!{k}") if isinstance(v, bool) else f"{k}={v}"
            for k, v in valuation.items()
        ]
        guards.setdefault(int(pomdp.observations[s]), []).append(" & ".join(items))
    labels = [str(label) for label in fsc["action_labels"]]
    lines = ["module controller", f"  node : [0..{fsc['num_nodes'] - 1}] init 0;"]
    for n in range(fsc["num_nodes"]):
        for k in range(fsc["num_observations"]):
            a, m = fsc["action_function"][n][k], fsc["update_function"][n][k]
            if a is None or k not in guards or labels[a] == "__no_label__":
                continue
            guard = " | ".join(f"({g})" for g in guards[k])
            lines.append(f"  [{labels[a]}] node = {n} & ({guard}) -> (node' = {m});")
    lines += [f"  [{label}] false -> true;" for label in labels if label != "__no_label__"]
    lines.append("endmodule")
    composed = tmp_path / "composed.prism"
    composed.write_text(source + "\n" + "\n".join(lines) + "\n")
    program = stormpy.parse_prism_program(str(composed))
    options = stormpy.BuilderOptions([stormpy.parse_properties(prop, program)[0].get_raw_formula()])
    options.set_build_all_labels()
    mdp = stormpy.build_model[stormpy.Rational](program, options=options)
    values = {}
    for label in ("bad", "goal"):
        both = []
        for direction in ("max", "min"):
            formula = stormpy.parse_properties(f'P{direction}=? [F "{label}"]', program)[0]
            result = stormpy.model_checking(mdp, formula, environment=stormpy.environments.exact())
            both.append(float(result.get_value(mdp.initial_states[0])))
        assert both[0] == pytest.approx(both[1], abs=1e-12)  # the controller is deterministic
        values[label] = both[0]
    return values


@pytest.mark.parametrize("case", list(CASES))
def test_paynt_controller_loads_unedited_and_agrees_with_storm(tmp_path, case):
    fsc, paynt_value, pomdp = _run_paynt(tmp_path, case)
    # as PAYNT writes it: its names for unlabelled commands, Storm's (wrong) observation text
    assert "__comment_action_function" in fsc
    assert any(re.fullmatch(r"\w+_cmd_\d+", label) for label in fsc["action_labels"])
    storm = _storm_values(tmp_path, case, fsc, pomdp)
    problem = load_problem(_problem(tmp_path, case))
    assert decoy_probability(problem, problem.identity()) == pytest.approx(storm["bad"], abs=1e-9)
    goal = load_problem(_problem(tmp_path, case, decoy="goal", name="goal.yaml"))
    reach_goal = decoy_probability(goal, goal.identity())
    assert reach_goal == pytest.approx(storm["goal"], abs=1e-9)
    assert reach_goal == pytest.approx(paynt_value, abs=PAYNT_TOLERANCE)


def test_geo_values_by_hand(tmp_path):
    """geo: the target's end is a fair coin the robot cannot see, and the goal ends the run.
    A controller that surely reaches the goal visits one end first, which is the bad one
    with probability 1/2: Pr(goal) = 1 and Pr(bad) = 1/2."""
    _, paynt_value, _ = _run_paynt(tmp_path, "geo")
    goal = load_problem(_problem(tmp_path, "geo", decoy="goal"))
    bad = load_problem(_problem(tmp_path, "geo", name="bad.yaml"))
    assert paynt_value == pytest.approx(1.0, abs=PAYNT_TOLERANCE)
    assert decoy_probability(goal, goal.identity()) == pytest.approx(1.0, abs=1e-9)
    assert decoy_probability(bad, bad.identity()) == pytest.approx(0.5, abs=1e-9)


@pytest.mark.parametrize("case", ["maze", "grid"])
def test_solve_on_paynt_controller_re_evaluates_exactly(tmp_path, case):
    _run_paynt(tmp_path, case)
    problem = load_problem(_problem(tmp_path, case))
    result = solve(problem, budgets=[1])
    alteration = problem.alteration(result.alteration)
    assert result.probability == pytest.approx(decoy_probability(problem, alteration), abs=1e-12)
    # Storm builds the product of the attacked robot itself, in exact arithmetic
    path = tmp_path / "product.prism"
    path.write_text(prism_product(problem, alteration))
    program = stormpy.parse_prism_program(str(path))
    formula = stormpy.parse_properties('P=? [F "decoy"]', program)
    model = stormpy.build_model[stormpy.Rational](program, formula)
    exact = stormpy.model_checking(model, formula[0], environment=stormpy.environments.exact())
    assert result.probability == pytest.approx(
        float(exact.get_value(model.initial_states[0])), abs=1e-9
    )


def test_cli_synthesize_writes_what_paynt_writes(tmp_path):
    output = tmp_path / "robot.fsc.json"
    result = runner.invoke(
        app,
        [
            "controller",
            "synthesize",
            str(DATA / "grid_avoid.prism"),
            "--props",
            'Pmax=? [F "goal"]',
            "--constants",
            "N=3",
            "--memory",
            "2",
            "--timeout",
            "20",
            "-o",
            str(output),
            "--json",
        ],
    )
    assert result.exit_code == 0, result.output
    report = checked(result.stdout)  # the result schema (misdirect-result/1)
    assert report["written"] == [str(output)]
    fsc = json.loads(output.read_text())
    assert "grid_cmd_0" in fsc["action_labels"] and "__no_label__" in fsc["action_labels"]
    problem = load_problem(_problem(tmp_path, "grid", decoy="goal"))
    value = decoy_probability(problem, problem.identity())
    assert report["value"] == pytest.approx(value, abs=PAYNT_TOLERANCE)
    assert report["nodes"] == fsc["num_nodes"] == problem.controller.n_nodes


def test_cli_synthesize_errors(tmp_path):
    model = str(DATA / "grid_avoid.prism")
    cases = [
        (["--props", 'P=? [F "goal"]', "--constants", "N=3"], "--props", "optimizing"),
        (["--props", 'Pmax=? [F "nowhere"]', "--constants", "N=3"], "PAYNT", "'nowhere'"),
        (["--props", 'Pmax=? [F "goal"]', "--constants", "M=3"], "--constants", "'M'"),
    ]
    for extra, field, words in cases:
        result = runner.invoke(
            app, ["controller", "synthesize", model, "-o", str(tmp_path / "x.json"), *extra]
        )
        assert result.exit_code == 2, result.output
        assert result.stderr.count("\n") == 1 and field in result.stderr and words in result.stderr


def _write_fsc(tmp_path: Path, fsc: dict) -> Path:
    (tmp_path / "robot.fsc.json").write_text(json.dumps(fsc))
    return _problem(tmp_path, "grid")


def test_point_distributions_and_joint_form_load(tmp_path):
    fsc, _, _ = _run_paynt(tmp_path, "grid")
    reference = load_problem(_problem(tmp_path, "grid"))
    factored = dict(fsc)
    factored["action_function"] = [
        [None if a is None else {str(a): 1.0} for a in row] for row in fsc["action_function"]
    ]
    factored["update_function"] = [
        [None if m is None else {str(m): 1.0} for m in row] for row in fsc["update_function"]
    ]
    joint = {k: v for k, v in fsc.items() if k not in ("action_function", "update_function")}
    joint["transitions"] = [
        [None if a is None else {f"({a}, {m})": 1.0} for a, m in zip(ra, rm, strict=True)]
        for ra, rm in zip(fsc["action_function"], fsc["update_function"], strict=True)
    ]
    for variant in (factored, joint):
        problem = load_problem(_write_fsc(tmp_path, variant))
        assert np.array_equal(problem.controller.action, reference.controller.action)
        assert np.array_equal(problem.controller.update, reference.controller.update)


@pytest.mark.parametrize("case", list(CASES))
def test_randomized_paynt_controllers_agree_with_paynt(tmp_path, case):
    """PAYNT 0.5's AR synthesis gives deterministic FSCs (its randomized ones come from SAYNT,
    Storm's belief exploration), so the randomized FSC is built with PAYNT's own FscFactored
    from the synthesized one: in node 0 the actions enabled at each observation are mixed
    (weights 3:1:...) and the next node is drawn uniformly; node 1 keeps PAYNT's choice.
    It is written by PAYNT's own to_json and loaded unedited. The oracle is PAYNT's own
    induced chain of a randomized FscFactored (paynt.pomdp._utils.get_induced_dtmc_from_fsc,
    action and update drawn independently), checked by Storm."""
    import paynt.pomdp._utils as paynt_utils
    from paynt.pomdp.fsc import FscFactored

    result, _, synthesizer = _synthesize(tmp_path, case)
    info = synthesizer.colored_mdp.feature_info
    fsc = result.fsc
    randomized = FscFactored(fsc.num_nodes, fsc.num_observations, is_deterministic=False)
    randomized.action_labels, randomized.observation_labels = (
        fsc.action_labels,
        fsc.observation_labels,
    )
    index = {label: i for i, label in enumerate(fsc.action_labels)}
    mixed = 0
    for n in range(fsc.num_nodes):
        for z in range(fsc.num_observations):
            if fsc.action_function[n][z] is None:
                randomized.action_function[n][z] = randomized.update_function[n][z] = None
                continue
            enabled = [index[label] for label in info.action_labels_at_observation[z]]
            if n == 0 and len(enabled) > 1:
                weights = [3.0] + [1.0] * (len(enabled) - 1)
                randomized.action_function[n][z] = {
                    a: w / sum(weights) for a, w in zip(enabled, weights, strict=True)
                }
                mixed += 1
            else:
                randomized.action_function[n][z] = {fsc.action_function[n][z]: 1.0}
            randomized.update_function[n][z] = (
                {m: 1.0 / fsc.num_nodes for m in range(fsc.num_nodes)}
                if n == 0
                else {fsc.update_function[n][z]: 1.0}
            )
    assert mixed > 0
    (tmp_path / "robot.fsc.json").write_text(str(randomized))  # PAYNT's own to_json
    dtmc = paynt_utils.get_induced_dtmc_from_fsc(info, randomized)
    for label in ("bad", "goal"):
        formula = stormpy.parse_properties(f'P=? [F "{label}"]')[0]
        expected = stormpy.model_checking(dtmc, formula).get_value(dtmc.initial_states[0])
        problem = load_problem(_problem(tmp_path, case, decoy=label, name=f"{label}.yaml"))
        assert not problem.controller.is_deterministic
        ours = decoy_probability(problem, problem.identity())
        assert ours == pytest.approx(expected, abs=1e-6), label  # Storm's default precision
    # and the attacked robot: misdirect's optimum re-checked by Storm's own product
    problem = load_problem(_problem(tmp_path, case))
    best = solve(problem, budgets=[1])
    alteration = problem.alteration(best.alteration)
    path = tmp_path / "product.prism"
    path.write_text(prism_product(problem, alteration))
    program = stormpy.parse_prism_program(str(path))
    formula = stormpy.parse_properties('P=? [F "decoy"]', program)
    model = stormpy.build_model(program, formula)
    exact = stormpy.model_checking(model, formula[0]).get_value(model.initial_states[0])
    assert best.probability == pytest.approx(exact, abs=1e-6)


def test_controller_of_another_model_is_one_clear_error(tmp_path):
    """PAYNT's file for N=3 against the model built with N=4: PAYNT's labels of its
    observations differ, so nothing is matched silently."""
    _run_paynt(tmp_path, "grid")
    path = _problem(tmp_path, "grid")
    document = yaml.safe_load(path.read_text())
    document["pomdp"]["constants"] = "N=4"
    path.write_text(yaml.safe_dump(document))
    result = runner.invoke(app, ["evaluate", str(path)])
    assert result.exit_code == 2, result.output
    assert result.stderr.count("\n") == 1 and "robot.fsc.json" in result.stderr


# A DRN POMDP whose observation ids have gaps (1, 4, 5, 7: no 0), as hallway's do. From s0
# (obs 1), `right` goes to s2, `left` to s1 or s2 (1/2 each); s1 and s2 both read obs 4, from
# which `left`/`right` reach goal (s3, obs 5) or bad (s4, obs 7).
GAPPED_DRN = """@type: POMDP
@parameters

@reward_models

@nr_states
5
@nr_choices
8
@model
state 0 {1} init
\taction left
\t\t1 : 0.5
\t\t2 : 0.5
\taction right
\t\t2 : 1
state 1 {4}
\taction left
\t\t3 : 0.8
\t\t4 : 0.2
\taction right
\t\t3 : 0.3
\t\t4 : 0.7
state 2 {4}
\taction left
\t\t3 : 0.4
\t\t4 : 0.6
\taction right
\t\t3 : 0.9
\t\t4 : 0.1
state 3 {5} goal
\taction left
\t\t3 : 1
state 4 {7} bad
\taction left
\t\t4 : 1
"""


def test_drn_with_gaps_in_its_observation_ids(tmp_path):
    """PAYNT's controller of a DRN model numbered 1, 4, 5, 7 has a column per id 0..7 (null
    where no state reads it) and loads as written. By hand, with one memory node the only
    controller reaching the goal with 0.9 plays `right` at obs 1 and at obs 4 (`left` at
    obs 1 gives 1/2 (0.8 or 0.3) + 1/2 (0.4 or 0.9) = 0.6 at most): Pr(bad) = 0.1. With one
    sensor altered: obs4 -> obs5 (or obs7), where the controller plays `left`: s2 reaches bad
    with 0.6; obs1 -> obs5: 1/2 0.7 + 1/2 0.1 = 0.4; so the budget-1 optimum is 0.6."""
    (tmp_path / "gap.drn").write_text(GAPPED_DRN)
    (tmp_path / "sketch.props").write_text('Pmax=? [F "goal"]\n')
    paynt.utils.timer.GlobalTimer.start(20)
    factory, task = paynt.parser.sketch.Sketch.load_sketch(
        str(tmp_path / "gap.drn"), str(tmp_path / "sketch.props"), task_kwargs={"memory_size": 1}
    )
    synthesizer = paynt.api.get_synthesizer(factory, task, "ar", fsc_synthesis=True)
    synthesizer.synthesize(synthesizer.colored_mdp.parameter_space, print_stats=False)
    result = synthesizer.build_result()
    assert float(result.value) == pytest.approx(0.9, abs=PAYNT_TOLERANCE)
    (tmp_path / "robot.fsc.json").write_text(str(result.fsc))  # as PAYNT writes it
    fsc = json.loads((tmp_path / "robot.fsc.json").read_text())
    assert fsc["num_observations"] == 8 and fsc["action_function"][0][0] is None
    document = {
        "format": "misdirect/v1",
        "pomdp": {"drn": "gap.drn"},
        "controller": {"paynt": "robot.fsc.json"},
        "deception": {"decoy": {"label": "bad"}, "budget": 1},
    }
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(document))
    problem = load_problem(tmp_path / "p.yaml")
    # an id no state emits is no observation of the model
    assert problem.pomdp.observations == ("obs1", "obs4", "obs5", "obs7")
    assert decoy_probability(problem, problem.identity()) == pytest.approx(0.1, abs=1e-12)
    best = solve(problem, budgets=[0, 1])
    assert [p.probability for p in best.curve] == pytest.approx([0.1, 0.6], abs=1e-12)


def test_cli_synthesize_reads_drn(tmp_path):
    """`controller synthesize` on a DRN model, as PAYNT reads it: the gapped model above, whose
    best one-node controller reaches the goal with 0.9 (by hand, see above)."""
    (tmp_path / "gap.drn").write_text(GAPPED_DRN)
    output = tmp_path / "robot.fsc.json"
    args = ["controller", "synthesize", str(tmp_path / "gap.drn"), "-o", str(output)]
    result = runner.invoke(app, [*args, "--props", 'Pmax=? [F "goal"]', "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["value"] == pytest.approx(0.9, abs=PAYNT_TOLERANCE)
    document = {
        "format": "misdirect/v1",
        "pomdp": {"drn": "gap.drn"},
        "controller": {"paynt": "robot.fsc.json"},
        "deception": {"decoy": {"label": "goal"}, "budget": 1},
    }
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(document))
    problem = load_problem(tmp_path / "p.yaml")
    assert decoy_probability(problem, problem.identity()) == pytest.approx(0.9, abs=1e-12)
    # what is wrong with a DRN model or its property: one line
    (tmp_path / "bad.drn").write_text("@type: POMDP\n@nr_states\nx\n")
    for model, extra, words in [
        ("bad.drn", ["--props", 'Pmax=? [F "goal"]'], "Storm cannot read it"),
        ("gap.drn", ["--props", 'Pmax=? [F "nowhere"]'], "'nowhere'"),
        ("gap.drn", ["--props", 'Pmax=? [F "goal"]', "--constants", "N=2"], "--constants"),
    ]:
        args = ["controller", "synthesize", str(tmp_path / model), "-o", str(output), *extra]
        result = runner.invoke(app, args)
        assert result.exit_code == 2, result.output
        assert result.stderr.count("\n") == 1 and words in result.stderr, result.stderr


def test_cli_synthesize_says_why_no_controller(tmp_path, monkeypatch):
    """Two different failures, two messages. The goal of this model is unreachable, so every
    controller collects the step reward forever: PAYNT finishes its search with no controller
    of finite value (not "within the time limit"). And a build that outlives --timeout (a
    stand-in that never ends, as Storm's build of a large model) is stopped at the limit."""
    (tmp_path / "loop.drn").write_text(
        "@type: POMDP\n@parameters\n\n@reward_models\nsteps\n@nr_states\n3\n@nr_choices\n4\n"
        "@model\nstate 0 {0} init\n\taction a [1]\n\t\t1 : 1\n\taction b [1]\n\t\t0 : 0.5\n"
        "\t\t1 : 0.5\nstate 1 {1}\n\taction a [1]\n\t\t1 : 1\nstate 2 {2} goal\n"
        "\taction a [0]\n\t\t2 : 1\n"
    )
    args = ["controller", "synthesize", str(tmp_path / "loop.drn"), "-o", str(tmp_path / "x")]
    result = runner.invoke(app, [*args, "--props", 'R{"steps"}min=? [F "goal"]'])
    assert result.exit_code == 1, result.output
    assert "finite value" in result.stderr and "within" not in result.stderr, result.stderr

    import misdirect.io.paynt_synthesis as synthesis

    def endless_build(job, built):
        time.sleep(3600)

    def endless_search(job, built):
        built()
        time.sleep(3600)

    for stand_in, words in [
        (endless_build, "still building the model"),
        (endless_search, "was stopped at the time limit"),
    ]:
        monkeypatch.setattr(synthesis, "_search", stand_in)
        result = runner.invoke(app, [*args, "--props", 'Pmax=? [F "goal"]', "--timeout", "1"])
        assert result.exit_code == 1, result.output
        assert "no controller with 1 memory node(s) within 1 s" in result.stderr
        assert words in result.stderr, result.stderr
