"""Commands that write models: generated problem files (scenario *), the robot's controller
(controller synthesize), other formats (convert, export-fsc, export-milp) and the schema."""

from __future__ import annotations

import json
import math
import os
from enum import StrEnum
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from misdirect.cli.common import (
    check_budget,
    check_range,
    note,
    out,
    print_json,
    write_text,
    wrote,
)
from misdirect.cli.exports import column_map_path, column_map_text
from misdirect.cli.options import (
    MAX_GRID_SIZE,
    MAX_RANDOM,
    MAX_SEED,
    FormulationOption,
    JsonOption,
    ProblemSource,
    numbers,
    problem_input,
)
from misdirect.core.model import Problem
from misdirect.errors import ProblemError
from misdirect.io.files import check_output_path, read_text_file, write_output
from misdirect.io.problem_file import json_schema, model_kind, write_problem
from misdirect.report import json_output
from misdirect.scenarios import drone, knapsack, paper_grid, random_problem, sensor_grid
from misdirect.solvers.milp.backends import write_model
from misdirect.solvers.milp.model import column_map
from misdirect.solvers.milp.solver import scaled_formulation

OutputOption = Annotated[Path, typer.Option("--output", "-o", help="File to write (.yaml/.json).")]
ScenarioBudgetOption = Annotated[float, typer.Option(help="Budget written into the file.")]
RandomSeedOption = Annotated[int, typer.Option(help="Random seed.")]

# -- scenario * ---------------------------------------------------------------------------------


def _write_scenario(problem: Problem, output: Path, as_json: bool, command: str) -> None:
    write_problem(problem, output)  # atomic: nothing is reported unless the file is in place
    if as_json:
        print_json(
            json_output.written_files(
                command, [output], problem=problem.name, states=problem.pomdp.n_states
            )
        )
    else:
        wrote(f"wrote {output} ({problem.name}, {problem.pomdp.n_states:,} states)")


def scenario_paper_grid(
    output: OutputOption,
    size: Annotated[int, typer.Option(help="Grid size n ≥ 5.")] = 5,
    budget: ScenarioBudgetOption = 4,
    as_json: JsonOption = False,
) -> None:
    """The paper's n x n grid world (its Sec. VII-B case study, scaled)."""
    check_output_path(output)
    check_range("--size", size, 5, MAX_GRID_SIZE)
    if not (math.isfinite(budget) and budget >= 0):
        raise ProblemError(f"must be a non-negative number, got {budget}", field="--budget")
    _write_scenario(paper_grid(size, budget=budget), output, as_json, "scenario paper-grid")


def scenario_knapsack(
    output: OutputOption,
    weights: Annotated[str, typer.Option(help="Item weights, e.g. 1,2,3,4,5.")],
    values: Annotated[str, typer.Option(help="Item values, e.g. 20,30,40,50,60.")],
    capacity: Annotated[float, typer.Option(help="Knapsack capacity (the budget).")],
    as_json: JsonOption = False,
) -> None:
    """The knapsack reduction of the NP-hardness proof (paper Sec. V)."""
    check_output_path(output)
    problem = knapsack(numbers(weights, "--weights"), numbers(values, "--values"), capacity)
    _write_scenario(problem, output, as_json, "scenario knapsack")


def scenario_sensor_grid(
    output: OutputOption,
    size: Annotated[int, typer.Option(help="Grid size n (5..1000).")] = 20,
    sensors: Annotated[
        int, typer.Option(help="Number of sensors k, each covering 1-6 cells.")
    ] = 16,
    seed: RandomSeedOption = 0,
    memory: Annotated[
        int | None,
        typer.Option(
            help="Controller memory nodes (default 3, the paper's; 4, one per heading, with "
            "--goal inside).",
            show_default=False,
        ),
    ] = None,
    costs: Annotated[
        str, typer.Option(help="uniform (every alteration 1) or random (1..3 per sensor).")
    ] = "uniform",
    budget: ScenarioBudgetOption = 3,
    goal: Annotated[
        str,
        typer.Option(
            help="corner (the paper's: East/North to (n-1, n-1)) or inside (the centre; "
            "sensors point N/E/S/W, the robot can turn back)."
        ),
    ] = "corner",
    as_json: JsonOption = False,
) -> None:
    """A sensor network on the paper's slippery grid (docs/sensor-grid.md)."""
    check_output_path(output)  # before building: a big grid takes minutes
    if not (math.isfinite(budget) and budget >= 0):
        raise ProblemError(f"must be a non-negative number, got {budget}", field="--budget")
    problem = sensor_grid(
        size, sensors, seed=seed, memory=memory, costs=costs, budget=budget, goal=goal
    )
    _write_scenario(problem, output, as_json, "scenario sensor-grid")


def scenario_drone(
    output: OutputOption,
    size: Annotated[int, typer.Option(help="Grid size n (4..40).")] = 8,
    agents: Annotated[int, typer.Option(help="Patrolling agents (1..3).")] = 2,
    rows: Annotated[int, typer.Option(help="Rows each agent patrols.")] = 3,
    radius: Annotated[int, typer.Option(help="How far the drone sees agents (cells).")] = 2,
    slip: Annotated[float, typer.Option(help="Probability that a step drifts sideways.")] = 0.2,
    budget: ScenarioBudgetOption = 2,
    as_json: JsonOption = False,
) -> None:
    """A drone among patrolling agents, shaped like PAYNT's drone benchmarks (cycles, hundreds
    of observations; docs/sensor-grid.md)."""
    check_output_path(output)
    problem = drone(size, agents=agents, rows=rows, radius=radius, slip=slip, budget=budget)
    _write_scenario(problem, output, as_json, "scenario drone")


def scenario_random(
    output: OutputOption,
    seed: RandomSeedOption = 0,
    states: Annotated[int, typer.Option(help="Number of non-absorbing states.")] = 6,
    actions: Annotated[int, typer.Option(help="Number of actions.")] = 2,
    observations: Annotated[int, typer.Option(help="Number of observations.")] = 4,
    nodes: Annotated[int, typer.Option(help="Controller memory nodes.")] = 2,
    as_json: JsonOption = False,
) -> None:
    """A seeded random model with traps, absorbing non-decoy states and forbidden pairs."""
    check_output_path(output)
    check_range("--seed", seed, 0, MAX_SEED)
    for option, value in (
        ("--states", states),
        ("--actions", actions),
        ("--observations", observations),
        ("--nodes", nodes),
    ):
        if value < 1:
            raise ProblemError(f"must be at least 1, got {value}", field=option)
        check_range(option, value, 1, MAX_RANDOM[option])
    problem = random_problem(
        seed, states=states, actions=actions, observations=observations, nodes=nodes
    )
    _write_scenario(problem, output, as_json, "scenario random")


# -- controller synthesize ----------------------------------------------------------------------


def controller_synthesize(
    model: Annotated[Path, typer.Argument(help="PRISM or DRN POMDP (the robot's world).")],
    output: Annotated[
        Path, typer.Option("--output", "-o", help="PAYNT .fsc.json to write (PAYNT's own JSON).")
    ],
    props: Annotated[
        str | None,
        typer.Option(
            "--props",
            help="Properties file, as PAYNT's --props takes it: one optimizing property, e.g. "
            'Pmax=? [F "goal"] (// comments, a closing ; and empty lines allowed). A property '
            "written out here is read as --property.",
            show_default=False,
        ),
    ] = None,
    property_text: Annotated[
        str | None,
        typer.Option(
            "--property",
            help='The optimizing property itself, e.g. Pmax=? [F "goal"].',
            show_default=False,
        ),
    ] = None,
    constants: Annotated[
        str | None, typer.Option(help='Undefined PRISM constants, e.g. "N=5,p=0.1".')
    ] = None,
    memory_nodes: Annotated[
        int,
        typer.Option(
            "--memory-nodes", "--memory", help="Memory nodes per observation (PAYNT's memory)."
        ),
    ] = 1,
    time_limit: Annotated[
        float,
        typer.Option(
            "--time-limit",
            "--timeout",
            help="Seconds for the whole command, model build included.",
        ),
    ] = 60.0,
    as_json: JsonOption = False,
) -> None:
    """Synthesize the robot's controller with PAYNT and write PAYNT's JSON of it
    (controller: {paynt: FILE} reads it; give the property as pomdp.terminal_from)."""
    from misdirect.io.paynt_synthesis import synthesize

    check_output_path(output)
    check_range("--memory-nodes", memory_nodes, 1, 100)
    check_range("--time-limit", time_limit, 1, 10**6)
    prop, where = synthesis_property(props, property_text)
    try:
        result = synthesize(
            model, prop, constants=constants, memory=memory_nodes, timeout=time_limit
        )
    except ProblemError as error:  # the property's fault: name where it was written
        if error.field != "prop" or error.source is not None:
            raise
        raise ProblemError(error.reason, **where) from None
    write_output(output, json.dumps(result.document, indent=4) + "\n")
    nodes = result.document.get("num_nodes")
    if as_json:
        print_json(
            json_output.written_files(
                "controller synthesize",
                [output],
                value=result.value,
                property=result.property,
                nodes=nodes,
                memory=result.memory,
                time_s=result.seconds,
            )
        )
        return
    value = "not reported" if result.value is None else f"{result.value:.6g}"
    out.print(
        f"PAYNT's controller: {escape(result.property)} = {value} ({nodes} nodes, "
        f"{result.seconds:.1f} s)",
        highlight=False,
        soft_wrap=True,
    )
    wrote(f"wrote {output}")


# what --props holds when it is a property written out, not a file (the spelling of earlier
# versions): a formula's brackets or query
_WRITTEN_PROPERTY = ("[", "=?")


def synthesis_property(
    props: str | None, property_text: str | None
) -> tuple[str, dict[str, str | None]]:
    """The property of ``controller synthesize`` and where an error in it is to be named
    (``source`` and ``field`` of the error): ``--property STRING``, or ``--props FILE`` read
    as PAYNT reads a properties file (one property per line, ``//`` comments, a closing
    ``;``), which must hold exactly one. A ``--props`` value that is a property itself (as
    ``--props`` took before) is read as ``--property``."""
    if props is not None and property_text is not None:
        raise ProblemError("give --props FILE or --property STRING, not both", field="--property")
    if props is None and property_text is None:
        raise ProblemError(
            'give the property: --props FILE or --property STRING (e.g. Pmax=? [F "goal"])',
            field="--props",
        )
    if property_text is not None:
        return property_text, {"field": "--property", "source": None}
    assert props is not None
    path = Path(props)
    if not path.exists() and any(mark in props for mark in _WRITTEN_PROPERTY):
        return props, {"field": "--props", "source": None}
    text = read_text_file(path, field="--props")
    found = []
    for number, line in enumerate(text.splitlines(), start=1):
        formula = line.split("//", 1)[0].strip().removesuffix(";").strip()
        if formula:
            found.append((number, formula))
    if len(found) != 1:
        lines = ", ".join(str(number) for number, _ in found)
        held = "no property" if not found else f"{len(found)} properties (lines {lines})"
        raise ProblemError(
            f"holds {held}; controller synthesize takes one optimizing property, e.g. "
            'Pmax=? [F "goal"]',
            source=str(path),
        )
    number, formula = found[0]
    return formula, {"field": f"line {number}", "source": str(path)}


# -- convert, export-fsc, export-milp, schema ---------------------------------------------------


class ConvertTarget(StrEnum):
    prism = "prism"
    drn = "drn"
    json = "json"
    yaml = "yaml"


_SUFFIX_TARGETS = {
    ".prism": "prism",
    ".drn": "drn",
    ".json": "json",
    ".yaml": "yaml",
    ".yml": "yaml",
}


@problem_input
def convert(
    to: Annotated[
        ConvertTarget | None,
        typer.Option("--to", help="Format to write (default: by the suffix of -o)."),
    ] = None,
    output: Annotated[
        Path | None,
        typer.Option("--output", "-o", help="File to write (default: standard output)."),
    ] = None,
    budget: Annotated[
        float | None,
        typer.Option(help="Budget written into the file (default: the problem's)."),
    ] = None,
    explicit: Annotated[
        bool,
        typer.Option(
            "--explicit",
            help="With a PRISM/DRN model and --to yaml/json: write the model's states and "
            "transitions, not a problem file that names the model and the flags.",
        ),
    ] = False,
    *,
    source: ProblemSource,
    as_json: JsonOption = False,
) -> None:
    """Write the explicit model: PRISM or DRN for Storm (decoy as label "decoy"), or v1.
    Given a PRISM or DRN model with --controller and --decoy, --to yaml/json writes the
    problem file those flags stand for (the model and the controller named in it)."""
    if output is not None:
        check_output_path(output)
    if to is None:
        target = None if output is None else _SUFFIX_TARGETS.get(output.suffix.lower())
        if target is None:
            raise ProblemError(
                "give the format to write (prism, drn, json or yaml), or -o with one of the "
                "suffixes .prism, .drn, .json, .yaml",
                field="--to",
            )
        to = ConvertTarget(target)
    check_budget(budget, "--budget")
    if output is not None and to in (ConvertTarget.json, ConvertTarget.yaml):
        wanted = (".json",) if to is ConvertTarget.json else (".yaml", ".yml")
        if output.suffix.lower() not in wanted:
            raise ProblemError(f"--to {to.value} writes a {wanted[0]} file", field="-o")
    kind = model_kind(source.file) if source.file is not None else None
    if kind is not None and not explicit and to in (ConvertTarget.json, ConvertTarget.yaml):
        text, name, states = _problem_file_of_flags(source, kind, to, output, budget)
    else:
        problem = source.load()
        if budget is not None:
            problem = problem.with_budget(budget)
        text, name, states = _converted(problem, to), problem.name, problem.pomdp.n_states
    write_text("convert", text, output, as_json, problem=name, format=to.value)
    if output is not None and not as_json:
        size = "" if states is None else f", {states:,} states"
        wrote(f"wrote {output} ({to.value}{size})")


def _problem_file_of_flags(
    source: ProblemSource,
    kind: str,
    to: ConvertTarget,
    output: Path | None,
    budget: float | None,
) -> tuple[str, str, int | None]:
    """The problem file a PRISM or DRN model and its flags stand for: checked by loading it
    (as the flags' own route does), written with file names relative to ``output``."""
    from misdirect.io.model_problem import model_document
    from misdirect.io.problem_file import problem_document_text

    problem = source.load()  # every mistake is reported against its flag, before writing
    assert source.file is not None and source.controller is not None  # and a decoy or property
    document = model_document(
        source.file,
        controller=source.controller,
        decoy=source.decoy,
        **{name: value for name, value in source.model_flags().items() if name != "decoy"},
        budget=budget,
        kind=kind,
        relative_to=(output or Path("x")).absolute().parent,
    )
    text = problem_document_text(document, as_json=to is ConvertTarget.json)
    return text, problem.name, problem.pomdp.n_states


def _converted(problem: Problem, to: ConvertTarget) -> str:
    """The text of ``problem`` in format ``to`` (with a note on stderr for each thing a PRISM
    or DRN file cannot say)."""
    from misdirect.io.export import drn_text, export_notes, prism_text
    from misdirect.io.problem_file import problem_text

    if to in (ConvertTarget.prism, ConvertTarget.drn):
        for text in export_notes(problem, to.value):
            note(f"note: {text}")
    if to is ConvertTarget.prism:
        return prism_text(problem)
    if to is ConvertTarget.drn:
        return drn_text(problem)
    return problem_text(problem, as_json=to is ConvertTarget.json)


@problem_input
def export_fsc(
    output: Annotated[
        Path | None,
        typer.Option("--output", "-o", help="PAYNT .fsc.json to write (default: standard output)."),
    ] = None,
    *,
    source: ProblemSource,
    as_json: JsonOption = False,
) -> None:
    """Write the controller in PAYNT's JSON format (controller: {paynt: FILE} reads it)."""
    from misdirect.io.paynt import controller_to_paynt

    if output is not None:
        check_output_path(output)
    problem = source.load()
    text = json.dumps(controller_to_paynt(problem.controller, problem.pomdp), indent=1) + "\n"
    write_text("export-fsc", text, output, as_json, problem=problem.name, format="paynt")
    if output is not None and not as_json:
        wrote(f"wrote {output} ({problem.controller.n_nodes} nodes)")


@problem_input
def export_milp(
    output: Annotated[
        Path, typer.Option("--output", "-o", help="Model file to write (.mps or .lp).")
    ],
    source: ProblemSource,
    formulation: FormulationOption = "compact",
    budget: Annotated[
        float | None, typer.Option(help="Budget in the budget row (default: the file's).")
    ] = None,
    as_json: JsonOption = False,
) -> None:
    """Write the MILP as MPS or LP for any other solver (columns c0, c1, …; maximise), and
    beside it M.columns.json: which columns choose which alteration (misdirect decode)."""
    check_output_path(output)
    if output.suffix.lower() not in (".mps", ".lp"):
        raise ProblemError(
            f"cannot write {output.suffix or 'a file without suffix'}: use .mps or .lp",
            field="-o",
        )
    problem = source.load()
    if budget is not None and (not math.isfinite(budget) or budget < 0):
        raise ProblemError("must be a non-negative number", field="--budget")
    model = scaled_formulation(problem, formulation, budget)  # as the solve scales it
    mapping = column_map(model, problem, problem.budget if budget is None else budget)
    mapping["problem_file"] = str(source.file.resolve()) if source.file is not None else None
    map_path = column_map_path(output)
    check_output_path(map_path)
    # both files or neither: the model is staged beside its place, the map written, and only
    # then the model put in place (a map that cannot be written leaves the old pair as it was)
    staged = output.with_name(f".{output.stem}.partial{output.suffix}")
    try:
        write_model(model, staged)
        write_output(map_path, column_map_text(mapping))
        os.replace(staged, output)
    finally:
        staged.unlink(missing_ok=True)
    if as_json:
        print_json(
            json_output.written_files(
                "export-milp", [output, map_path], problem=problem.name, **model.stats()
            )
        )
    else:
        wrote(
            f"wrote {output}: {formulation} MILP, {model.n_columns:,} variables "
            f"({int(model.integer.sum()):,} binary), {model.n_rows:,} rows, "
            f"{model.matrix.nnz:,} non-zeros"
        )
        wrote(f"wrote {map_path}: which column chooses which alteration (misdirect decode)")


def schema(
    output: Annotated[Path | None, typer.Option("--output", "-o", help="Write to a file.")] = None,
    result: Annotated[
        bool,
        typer.Option(
            "--result", help="The schema of the --json output (misdirect-result/1) instead."
        ),
    ] = False,
    as_json: JsonOption = False,
) -> None:
    """Print the JSON Schema of the problem file format (or, with --result, of --json)."""
    document = json_output.result_schema() if result else json_schema()
    text = json.dumps(document, indent=2) + "\n"
    if output is not None:
        check_output_path(output)
    write_text("schema", text, output, as_json)
