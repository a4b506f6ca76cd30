"""A problem from a PRISM or DRN model and a few settings, without a problem file.

``misdirect evaluate model.prism --controller c.fsc.json --decoy bad`` builds the same
problem as the problem file

.. code-block:: yaml

    format: misdirect/v1
    pomdp: {prism: model.prism}
    controller: {paynt: c.fsc.json}
    deception: {decoy: {label: bad}}

and it is built that way: :func:`model_document` writes that document (what ``misdirect
convert`` writes), and :func:`problem_from_model` validates and compiles it exactly as
:func:`~misdirect.io.problem_file.load_problem` does a file. Errors name the setting they
come from (``decoy``, ``constants``, ``goal``, ``terminal_from``, ``controller``) as their
source, not a place in a file that was never written.

:func:`controller_document` reads a controller file (PAYNT's ``.fsc.json``, or a YAML/JSON
mapping of rules, or the controller of another problem file) as the ``controller:`` entry of
a document; :func:`with_controller` puts it in place of any problem's own controller.
"""

from __future__ import annotations

import dataclasses
import re
import weakref
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from misdirect.core.alterations import max_alteration_cost
from misdirect.core.model import Pomdp, Problem
from misdirect.errors import ProblemError, ProblemsError
from misdirect.io.files import check_input_file
from misdirect.io.paynt import forbid_targets, read_paynt_controller, unmet_rule_warning
from misdirect.io.problem_file import (
    FORMAT,
    ControllerSpec,
    StormPomdpSpec,
    compile_controller,
    compile_problem,
    controller_document,
    controller_error,
    error_field,
    error_reason,
    model_kind,
    parse_spec,
    relative_path,
)

__all__ = [
    "built_from",
    "controller_document",
    "decoy_document",
    "model_document",
    "model_kind",
    "problem_from_model",
    "with_controller",
]

# a decoy given as one name is a state label; anything else is a state expression
_LABEL = re.compile(r'^\s*(?:"([A-Za-z_][\w]*)"|([A-Za-z_][\w]*))\s*$')


def decoy_document(decoy: str) -> dict[str, str]:
    """``--decoy``'s text as the file's ``deception.decoy``: a label when it is one name
    (``bad`` or ``"bad"``), else a state expression (``x = 3 & y > 2``, ``"bad" | "trap"``)."""
    match = _LABEL.match(decoy)
    if match:
        return {"label": match[1] or match[2]}
    return {"expression": decoy}


def model_document(
    model: str | Path,
    *,
    controller: str | Path,
    decoy: str | None = None,
    goal: str | None = None,
    constants: str | None = None,
    terminal_from: str | None = None,
    budget: float | None = None,
    property: str | None = None,
    kind: str | None = None,
    relative_to: Path | None = None,
) -> dict[str, Any]:
    """The ``misdirect/v1`` document of a PRISM or DRN model with these settings.

    File names are written relative to ``relative_to`` (the folder the document is written
    to), or absolute. ``goal`` is the file's ``pomdp.terminal``; a setting not given is left
    out, so the file's defaults apply (budget 0, every alteration costing 1). ``property``
    (the file's ``deception.property``) names the decoy when ``decoy`` is not given."""
    kind = kind or model_kind(model) or "prism"
    pomdp: dict[str, Any] = {kind: relative_path(model, relative_to)}
    if constants is not None:
        pomdp["constants"] = constants
    if goal is not None:
        pomdp["terminal"] = goal
    if terminal_from is not None:
        pomdp["terminal_from"] = terminal_from
    deception: dict[str, Any] = {}
    if decoy is not None:
        deception["decoy"] = decoy_document(decoy)
    if property is not None:
        deception["property"] = property
    if budget is not None:
        deception["budget"] = budget
    return {
        "format": FORMAT,
        "pomdp": pomdp,
        "controller": controller_document(controller, relative_to=relative_to),
        "deception": deception,
    }


# where a problem's field comes from, when the document was built from settings: the longest
# matching prefix wins (pomdp.terminal_from before pomdp.terminal)
_SOURCES = (
    ("pomdp.constants", "constants"),
    ("pomdp.terminal_from", "terminal_from"),
    ("pomdp.terminal", "goal"),
    ("deception.decoy", "decoy"),
    ("deception.property", "property"),
    ("deception.budget", "budget"),
)


def _attributed(error: ProblemError, model: str, controller: str) -> ProblemError:
    """``error`` of the built document attributed to the setting it comes from."""
    if isinstance(error, ProblemsError):
        problems = [_attributed(problem, model, controller) for problem in error.problems]
        return ProblemsError.of(problems, error.total)
    if error.source is not None:  # already names its file (a PAYNT file, say)
        return error
    field = error.field or ""
    for prefix, name in _SOURCES:
        if field == prefix or field.startswith(prefix + ".") or field.startswith(prefix + "["):
            # the flag's own text is the place: deception.decoy.label says no more than it
            inside = (
                None if name in ("decoy", "property") else field[len(prefix) :].lstrip(".") or None
            )
            return ProblemError(error.reason, source=name, field=inside)
    if field.startswith("controller"):  # a rules controller: its own file
        return controller_error(error, controller)
    if field.startswith("pomdp") or not field:
        return ProblemError(error.reason, source=model, field=None)
    return ProblemError(error.reason, source=model, field=field)


def problem_from_model(
    model: str | Path,
    *,
    controller: str | Path,
    decoy: str | None = None,
    goal: str | None = None,
    constants: str | None = None,
    terminal_from: str | None = None,
    budget: float | None = None,
    property: str | None = None,
) -> Problem:
    """The problem of a PRISM or DRN model, a controller and a decoy, as the problem file of
    :func:`model_document` gives it (needs ``misdirect[storm]``).

    Parameters
    ----------
    model : str or Path
        A PRISM POMDP (``.prism``, ``.nm``, ``.pm``) or a DRN file (``.drn``).
    controller : str or Path
        PAYNT's ``.fsc.json`` (or a YAML file of rules).
    decoy : str, optional
        A state label (``bad``), or a state expression (``x = 3 & y > 2``); needed unless
        ``property`` names the decoy.
    goal : str, optional
        States that end the run (``pomdp.terminal``): Storm builds them terminal, as PAYNT
        builds its model with its property's target.
    constants : str, optional
        The PRISM program's undefined constants, ``"N=4,p=0.1"``.
    terminal_from : str, optional
        PAYNT's property (``P=? [F "goal"]``): its target states are built terminal.
    budget : float, optional
        The attacker's budget (default the file format's, 0).
    property : str, optional
        The objective as a PRISM property, whose target is the decoy: ``P=? [F "decoy"]``,
        ``P=? [!"avoid" U "decoy"]``, ``P=? [F<=k "decoy"]``, ``P=? [a U<=k b]``
        (:mod:`misdirect.core.objective_property`).

    Raises
    ------
    ProblemError
        Naming the setting at fault as its source (``decoy: no state label 'x' ...``).
    """
    model_path = Path(model)
    kind = model_kind(model_path) or "prism"
    document = model_document(
        model_path,
        controller=controller,
        decoy=decoy,
        goal=goal,
        constants=constants,
        terminal_from=terminal_from,
        budget=budget,
        property=property,
        kind=kind,
    )
    try:
        spec = parse_spec(document)
        # the model's own name is the source: results are titled by it
        problem = compile_problem(spec, source=str(model_path))
    except ProblemError as error:
        raise _attributed(error, str(model_path), str(controller)) from None
    assert isinstance(spec.pomdp, StormPomdpSpec)  # model_document names a model
    _BUILT[problem.pomdp] = spec.pomdp
    return problem


# the settings each world built from a model was built with (its file names absolute), for
# what builds it again (exact_model: Storm in rational arithmetic); held while the world is
_BUILT: weakref.WeakKeyDictionary[Pomdp, StormPomdpSpec] = weakref.WeakKeyDictionary()


def built_from(problem: Problem) -> StormPomdpSpec | None:
    """The ``pomdp:`` settings :func:`problem_from_model` built ``problem``'s world with (the
    model named by its absolute path), or None for a problem read from a file."""
    return _BUILT.get(problem.pomdp)


def with_controller(problem: Problem, controller: str | Path) -> Problem:
    """``problem`` with the controller in the file ``controller`` instead of its own: PAYNT's
    ``.fsc.json`` matched to the model by name, or rules (:func:`controller_document`).

    For a problem read from a file, load it with ``load_problem(path, controller=...)``
    instead: a PRISM or DRN model is then matched to PAYNT's columns as PAYNT built it."""
    document = controller_document(controller)
    try:
        if "paynt" in document:
            path = Path(document["paynt"])
            if path.exists():
                check_input_file(path, source="controller")
            paynt = read_paynt_controller(path, problem.pomdp)
            cost = forbid_targets(problem.cost, paynt.never_read)
            replaced = dataclasses.replace(
                problem, controller=paynt.controller, cost=cost, warnings=()
            )
            warning = unmet_rule_warning(
                replaced, paynt.undefined, path, terminal_given=False, labels={}
            )
            if warning is not None:
                replaced = dataclasses.replace(replaced, warnings=(warning,))
        else:
            try:
                spec = ControllerSpec.model_validate(document)
            except ValidationError as error:
                found = [
                    ProblemError(
                        error_reason(item), field=error_field(("controller", *item["loc"]))
                    )
                    for item in error.errors()
                ]
                raise ProblemsError.of(found) from None
            replaced = dataclasses.replace(
                problem, controller=compile_controller(spec, problem.pomdp), warnings=()
            )
        max_alteration_cost(replaced)
    except ProblemError as error:
        raise controller_error(error, str(controller)) from None
    return replaced
