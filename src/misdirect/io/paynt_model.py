"""The model as PAYNT 0.5 builds it, matched to ours.

A PAYNT controller (``.fsc.json``, read by :mod:`misdirect.io.paynt`) speaks of PAYNT's model,
not ours: its observations are numbered as PAYNT's builder numbers them and its actions carry
the names PAYNT gives unlabelled commands. This module rebuilds that model the way PAYNT does
(:func:`build_paynt_view`) and matches it to ours by state, and writes a PRISM program in the
form PAYNT can read (:func:`paynt_prism_text`, used when misdirect runs PAYNT).
"""

from __future__ import annotations

import re
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from misdirect.core.model import Pomdp
from misdirect.errors import ProblemError
from misdirect.io.storm_expressions import (
    instantiate_constants,
    prism_property,
    prism_target,
    storm_message,
)
from misdirect.io.storm_names import NO_LABEL, read_variables, valuation_names

PAYNT_NO_LABEL = "__no_label__"  # PAYNT's label for a choice without one (ours: __NOLABEL__)
_ONE_LINE_OBSERVABLES = re.compile(
    r"(?m)^[ \t]*observables\b[ \t]*(?P<items>[^\n]*?)[ \t]*\bendobservables\b"
    r"[ \t]*(?P<rest>[^\n]*)$"
)


@dataclass(frozen=True)
class PayntView:
    """The model as PAYNT 0.5 builds it, matched to ours.

    PAYNT's ``.fsc.json`` has one column per observation of *its* model, in its order; its
    ``observation_labels`` are only Storm's text of them (stormpy 2.0 prints most of them
    wrongly, and several observations alike), and its action labels include names it made up
    for unlabelled PRISM commands (``maze_cmd_8``). So the columns are matched by position
    against a rebuild of PAYNT's model, not by label.
    """

    labels: tuple[str, ...]  # what PAYNT writes as observation_labels[k]
    # (columns,) our observation for PAYNT's observation k; -1: no state of ours, -2: several
    observation: np.ndarray
    actions: dict[str, str]  # PAYNT's action label -> our action name
    available: tuple[frozenset[str], ...]  # PAYNT's action labels enabled at its observation k
    kind: str = "prism"  # the file PAYNT built it from: prism or drn (which has no constants)


def paynt_prism_text(text: str) -> str:
    """The PRISM program as PAYNT 0.5 can read it.

    PAYNT reads ``observables`` line by line: the keyword must start a line and
    ``endobservables`` must start a later one (``observables x, y endobservables`` on one line
    makes it give up on the file). Such a block is split over three lines; nothing else
    changes, so Storm builds the same model from either text.
    """

    def split(match: re.Match) -> str:
        rest = f"\n{match['rest']}" if match["rest"].strip() else ""
        return f"observables\n{match['items']}\nendobservables{rest}"

    text = _ONE_LINE_OBSERVABLES.sub(split, text)
    return re.sub(r"(?m)^[ \t]+(?=(?:end)?observables\b)", "", text)


def _paynt_rewrite(text: str) -> str:
    """PAYNT's own rewriting of an ``observables`` block (paynt/parser/prism_parser.py,
    ``load_sketch_prism``): each listed variable ``x`` becomes ``observable "x" = x;``. Storm
    then numbers and prints the observations as PAYNT sees them."""
    out: list[str] = []
    inside = False
    for line in text.splitlines(keepends=True):
        if line.startswith("observables"):
            inside = True
            line = line.split("//")[0].strip()
            if len(line) <= len("observables"):
                continue
            line = line[len("observables") :].strip()
        if inside:
            if line.startswith("endobservables"):
                inside = False
                continue
            line = line.split("//")[0].strip()
            out += [f'observable "{o.strip()}" = {o.strip()};\n' for o in line.split(",")]
            continue
        out.append(line)
    return "".join(out)


def build_paynt_view(
    stormpy,
    path: Path,
    kind: str,
    pomdp: Pomdp,
    state_variables: tuple[str, ...],
    *,
    constants: str | None,
    terminal: str | None,
    terminal_from: str | None,
) -> PayntView:
    """Build the model the way PAYNT 0.5 does and match it to ``pomdp``, our build of the same
    file (its states named by ``state_variables``, empty when it has no valuations)."""
    model, renamed = _build_as_paynt(
        stormpy, path, kind, constants=constants, terminal=terminal, terminal_from=terminal_from
    )
    n_obs = model.nr_observations
    paynt_obs = np.asarray(model.observations, dtype=np.int64)  # PAYNT's observation of a state
    observation = _match_observations(model, paynt_obs, pomdp, state_variables)
    if model.has_observation_valuations():
        valuations = model.observation_valuations
        labels = tuple(valuations.to_string(o) for o in range(n_obs))
    else:
        labels = tuple(str(o) for o in range(n_obs))
    available = _available_labels(model, paynt_obs)
    actions: dict[str, str] = {}
    for label in set().union(*available) if available else set():
        if label in pomdp.actions:
            actions[label] = label
        elif (label in renamed or label == PAYNT_NO_LABEL) and NO_LABEL in pomdp.actions:
            actions[label] = NO_LABEL
    return PayntView(
        labels=labels,
        observation=observation,
        actions=actions,
        available=tuple(available),
        kind=kind,
    )


def _build_as_paynt(
    stormpy,
    path: Path,
    kind: str,
    *,
    constants: str | None,
    terminal: str | None,
    terminal_from: str | None,
):
    """PAYNT's model of the file (``Sketch.load_sketch``) and the action names PAYNT made up.

    PRISM: PAYNT's rewriting of ``observables``, Storm's parser in PRISM compatibility mode,
    ``label_unlabelled_commands`` (an unlabelled command of module ``m`` becomes the action
    ``m_cmd_<k>``, k its position in the module), Storm's builder with PAYNT's options and the
    property's target terminal, then ``make_canonic``. DRN: Storm's DRN reader, then
    ``make_canonic``; unlabelled choices are PAYNT's ``__no_label__``. The terminal states are
    those of the problem file (``terminal``/``terminal_from``): PAYNT's are its property's.
    """
    field = "controller.paynt"
    renamed: set[str] = set()
    try:
        if kind == "prism":
            text = _paynt_rewrite(paynt_prism_text(path.read_text(encoding="utf-8")))
            with tempfile.TemporaryDirectory(prefix="misdirect-") as folder:
                copy = Path(folder) / path.name
                copy.write_text(text, encoding="utf-8")
                program = stormpy.parse_prism_program(str(copy), prism_compatibility=True)
            if constants:
                program = instantiate_constants(stormpy, program, constants)
            labelled = program.label_unlabelled_commands({})

            def commands(p) -> set[str]:
                return {c.action_name for m in p.modules for c in m.commands}

            renamed = commands(labelled) - commands(program)
            formulas = []
            if terminal is not None:
                formulas = [prism_target(stormpy, labelled, terminal, "pomdp.terminal")]
            elif terminal_from is not None:
                formulas = [prism_property(stormpy, labelled, terminal_from)]
            options = stormpy.BuilderOptions(formulas) if formulas else stormpy.BuilderOptions()
            options.set_build_state_valuations(True)
            options.set_build_choice_origins(True)
            options.set_build_all_labels(True)
            options.set_build_choice_labels(True)
            options.set_add_overlapping_guards_label(True)
            options.set_build_observation_valuations(True)
            model = stormpy.build_model(labelled, options=options)
        else:
            options = stormpy.developer.DirectEncodingParserOptions()
            options.build_choice_labeling = True
            model = stormpy.build_model_from_drn(str(path), options=options)
        model = stormpy.pomdp.make_canonic(model)
    except ProblemError:
        raise
    except Exception as error:  # Storm's parser or builder (RuntimeError, SyntaxError)
        raise ProblemError(
            f"cannot build {path.name} the way PAYNT does: {storm_message(error)}", field=field
        ) from None
    return model, renamed


def _match_observations(
    model, paynt_obs: np.ndarray, pomdp: Pomdp, state_variables: tuple[str, ...]
) -> np.ndarray:
    """Our observation for each of PAYNT's: -1 where none of its states is ours, -2 where its
    states read several of ours. States are matched by name (valuation), or, for a model
    without valuations (DRN), by number when both have as many."""
    n_states = model.nr_states
    ours = np.full(n_states, -1, dtype=np.int64)  # our state of each of PAYNT's states
    if state_variables and model.has_state_valuations():
        values = read_variables(model.state_valuations, state_variables)
        names = valuation_names(values) or []
        index = {name: s for s, name in enumerate(pomdp.states)}
        ours = np.array([index.get(name, -1) for name in names], dtype=np.int64)
    elif n_states == pomdp.n_states:  # no valuations (DRN): the same file, the same states
        ours = np.arange(n_states)
    found = ours >= 0
    pairs = np.unique(
        np.stack([paynt_obs[found], pomdp.observation_of[ours[found]]], axis=1), axis=0
    )
    observation = np.full(model.nr_observations, -1, dtype=np.int64)
    column, counts = np.unique(pairs[:, 0], return_counts=True)
    observation[column[counts > 1]] = -2
    single = np.isin(pairs[:, 0], column[counts == 1])
    observation[pairs[single, 0]] = pairs[single, 1]
    return observation


def _available_labels(model, paynt_obs: np.ndarray) -> list[frozenset[str]]:
    """PAYNT's action labels enabled at each of its observations (read at its first state;
    none at an observation no state emits, as a DRN file's gaps in its ids)."""
    emitted, first_state = np.unique(paynt_obs, return_index=True)
    first = np.full(model.nr_observations, -1, dtype=np.int64)
    first[emitted] = first_state
    labelling = model.choice_labeling if model.has_choice_labeling() else None
    available: list[frozenset[str]] = []
    for o in range(model.nr_observations):
        names_here: set[str] = set()
        if first[o] >= 0:
            state = int(first[o])
            for offset in range(model.get_nr_available_actions(state)):
                choice = model.get_choice_index(state, offset)
                got = labelling.get_labels_of_choice(choice) if labelling else set()
                names_here.add(next(iter(got)) if len(got) == 1 else PAYNT_NO_LABEL)
        available.append(frozenset(names_here))
    return available
