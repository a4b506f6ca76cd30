"""Commands that cross to other tools and back: ``decode`` (another MILP solver's solution of
the model ``export-milp`` wrote, as an alteration, verified exactly) and ``export-chain`` (the
attacked product chain, for Storm)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Any

import typer
from pydantic import BaseModel, ConfigDict, ValidationError, field_validator
from rich.markup import escape

from misdirect.cli.common import fmt_alteration, note, out, print_json, wrote
from misdirect.cli.options import (
    AlterationFileOption,
    AlterOption,
    AtBudgetOption,
    FormulationOption,
    JsonOption,
    ProblemSource,
    alteration,
    problem_input,
)
from misdirect.core import tolerance
from misdirect.core.evaluate import evaluate as evaluate_alteration
from misdirect.core.model import Problem
from misdirect.errors import ProblemError
from misdirect.io.files import check_output_path, parse_json, read_text_file, write_output
from misdirect.io.problem_file import error_field, error_reason, load_problem
from misdirect.report import json_output

MAP_SUFFIX = ".columns.json"


def column_map_path(model: Path) -> Path:
    """Where ``export-milp`` writes the column map of ``model``: beside it, ``M.columns.json``
    for ``M.mps`` or ``M.lp``."""
    return model.with_suffix(MAP_SUFFIX)


# -- decode -------------------------------------------------------------------------------------


def decode(
    model: Annotated[
        Path,
        typer.Argument(
            help="The model export-milp wrote (.mps/.lp: its column map is read from beside "
            "it), the column map itself (.columns.json), or the problem file (the model is "
            "built again, as export-milp builds it).",
            show_default=False,
        ),
    ],
    solution: Annotated[
        Path,
        typer.Argument(
            help="The other solver's solution: HiGHS, Gurobi or SCIP .sol ('name value' lines).",
            show_default=False,
        ),
    ],
    problem_file: Annotated[
        Path | None,
        typer.Option(
            "--problem",
            help="The problem file (default: the one export-milp read, named in the map).",
            show_default=False,
        ),
    ] = None,
    formulation: FormulationOption = "compact",
    budget: Annotated[
        float | None,
        typer.Option(
            help="Budget the alteration must fit (default: the map's, else the file's).",
            show_default=False,
        ),
    ] = None,
    as_json: JsonOption = False,
) -> None:
    """Turn another solver's solution of the exported MILP into an alteration, verified
    exactly: re-evaluated on the chain, its cost checked against the budget (exit 1 if over)."""
    from misdirect.io.solution import read_solution
    from misdirect.solvers.milp.model import decode_columns

    if budget is not None and (not math.isfinite(budget) or budget < 0):
        raise ProblemError("must be a non-negative number", field="--budget")
    problem, mapping = _problem_and_map(model, problem_file, formulation, budget)
    found = read_solution(solution)
    try:
        alpha = decode_columns(problem, mapping["alteration_columns"], found.values)
    except ProblemError as error:
        raise error.located(str(solution)) from None
    problem.check_alteration(alpha, source=str(solution))
    limit = budget if budget is not None else mapping.get("budget", problem.budget)
    limit = problem.budget if limit is None else float(limit)
    result = evaluate_alteration(problem.with_budget(limit), alpha)
    fits = problem.cost.fits(alpha, limit)
    warnings = []
    if found.objective is not None:
        claimed = found.objective
        if tolerance.mismatch(
            result.probability, claimed, scale=float(problem.objective.max_value)
        ):
            warnings.append(
                f"the solution file claims objective {claimed:.9g}; the exact value of its "
                f"alteration is {result.probability:.9g}"
            )
    if not fits:
        warnings.append(f"the alteration costs {result.cost:g}, over the budget {limit:g}")
    status = "verified" if fits else "over_budget"
    if as_json:
        print_json(
            json_output.document(
                "decode",
                problem=problem.name,
                within_budget=fits,
                value=result.probability,
                alteration=result.alteration,
                cost=result.cost,
                budget=limit,
                claimed=found.objective,
                warnings=warnings,
            )
        )
    else:
        out.print(
            f"alteration {fmt_alteration(result.alteration)} · cost {result.cost:g} "
            f"(budget {limit:g}) · {escape(problem.objective.label)} "
            f"[bold]{result.probability:.6f}[/] (exact) · {status.replace('_', ' ')}",
            highlight=False,
            soft_wrap=True,
        )
        for text in warnings:
            note(f"warning: {text}")
    if not fits:
        raise typer.Exit(1)


class _MapEntry(BaseModel):
    """One alteration column of a column map: the fields decode reads, strictly typed."""

    model_config = ConfigDict(strict=True, extra="allow")
    column: str
    observation: str
    target: str


class _ColumnMap(BaseModel):
    model_config = ConfigDict(strict=True, extra="allow")
    alteration_columns: list[_MapEntry]
    budget: float | None = None
    problem_file: str | None = None

    @field_validator("budget")
    @classmethod
    def _budget(cls, budget: float | None) -> float | None:
        if budget is not None and not (math.isfinite(budget) and budget >= 0):
            raise ValueError(f"a budget must be a non-negative number, got {budget}")
        return budget


def _checked_map(document: Any, source: str) -> dict[str, Any]:
    """A column map as export-milp writes it, or one line naming the file and the field."""
    if not isinstance(document, dict):
        raise ProblemError("not a column map of misdirect export-milp", source=source)
    try:
        _ColumnMap.model_validate(document)
    except ValidationError as error:
        first = error.errors()[0]
        raise ProblemError(
            f"not a column map of misdirect export-milp: {error_reason(first)}",
            source=source,
            field=error_field(first["loc"]),
        ) from None
    return document


def _problem_and_map(
    model: Path, problem_file: Path | None, formulation: str, budget: float | None
) -> tuple[Problem, dict[str, Any]]:
    """The problem and the column map ``decode`` reads the solution through."""
    from misdirect.solvers.milp.model import column_map
    from misdirect.solvers.milp.solver import scaled_formulation

    suffix = model.suffix.lower()
    if suffix in (".mps", ".lp") or model.name.endswith(MAP_SUFFIX):
        map_path = model if model.name.endswith(MAP_SUFFIX) else column_map_path(model)
        if not map_path.exists():
            raise ProblemError(
                f"no column map {map_path.name} beside the model: write the model with "
                "misdirect export-milp, or give the problem file instead",
                field="MODEL",
            )
        mapping = _checked_map(
            parse_json(read_text_file(map_path), source=str(map_path)), str(map_path)
        )
        named = mapping.get("problem_file")
        if problem_file is None and not named:
            raise ProblemError(
                "the map names no problem file (the model came from a scenario): give --problem",
                source=str(map_path),
            )
        problem = load_problem(problem_file if problem_file is not None else Path(str(named)))
        return problem, mapping
    problem = load_problem(problem_file or model)
    built = scaled_formulation(problem, formulation, budget)
    limit = problem.budget if budget is None else budget
    return problem, column_map(built, problem, limit)


# -- export-chain -------------------------------------------------------------------------------


@problem_input
def export_chain(
    output: Annotated[
        Path,
        typer.Option(
            "--output",
            "-o",
            help="File to write: .drn (Storm's DRN, a DTMC) or .tra (PRISM's explicit format, "
            "labels in .lab beside it: prism -importtrans F.tra -importlabels F.lab -dtmc).",
        ),
    ],
    source: ProblemSource,
    alter: AlterOption = None,
    alteration_file: AlterationFileOption = None,
    at_budget: AtBudgetOption = None,
    as_json: JsonOption = False,
) -> None:
    """Write the product chain under an alteration (--alter; none by default), labels init,
    decoy and absorbing, for Storm or PRISM: P=? [F "decoy"] gives the value evaluate prints."""
    from misdirect.core.product import build_product
    from misdirect.io.export import chain_drn_text, chain_prism_explicit

    check_output_path(output)
    suffix = output.suffix.lower()
    if suffix not in (".drn", ".tra"):
        raise ProblemError(
            f"cannot write {suffix or 'a file without suffix'}: use .drn or .tra", field="-o"
        )
    problem = source.load()
    alpha = alteration(problem, alter, alteration_file, at_budget)
    chain = build_product(problem, alpha)
    # what Storm's P=? [F "decoy"] computes: the probability of any decoy, unweighted
    result = evaluate_alteration(problem.unweighted(), alpha)
    written = [output]
    if suffix == ".drn":
        write_output(
            output,
            chain_drn_text(problem, chain.matrix, chain.world_state, chain.node, chain.initial),
        )
    else:
        tra, lab = chain_prism_explicit(problem, chain.matrix, chain.world_state, chain.initial)
        labels = output.with_suffix(".lab")
        check_output_path(labels)
        write_output(output, tra)
        write_output(labels, lab)
        written.append(labels)
    warnings = []
    if problem.decoy_sets:
        warnings.append(
            'the chain labels every decoy state "decoy": Storm\'s P=? [F "decoy"] is the '
            "probability of any decoy, not the weighted value"
        )
    if as_json:
        print_json(
            json_output.document(
                "export-chain",
                problem=problem.name,
                value=result.probability,
                alteration=result.alteration,
                states=chain.n_states,
                transitions=chain.n_transitions,
                written=written,
                warnings=warnings,
            )
        )
        return
    for path in written:
        wrote(f"wrote {path}")
    note(
        f"{chain.n_states:,} states, {chain.n_transitions:,} transitions; "
        f'Storm\'s P=? [F "decoy"] should give {result.probability:.12g}'
    )
    for text in warnings:
        note(f"warning: {text}")


def column_map_text(mapping: dict[str, Any]) -> str:
    """The column map as ``export-milp`` writes it."""
    return json.dumps(mapping, indent=1) + "\n"
