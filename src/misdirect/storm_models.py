"""POMDPs from Storm: PRISM programs and DRN files, read through stormpy (``misdirect[storm]``).

Storm lets each state enable only some actions, and an altered observation can make the
controller pick one that is not enabled. The problem file decides what then happens:
``disabled_action: stay`` (the robot stays where it is; default) or ``forbid`` (alterations
that can make the controller pick a disabled action are not allowed at all).

Names: states are named by their variable valuation (``s=2,o=3``) where Storm has one, else
``s<k>``; observations by their valuation (``o=3``) or ``obs<k>``; actions by their choice
label, ``__NOLABEL__`` for an unlabelled choice (as Storm's own DRN export writes it).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from misdirect.errors import ProblemError
from misdirect.model import Pomdp

NO_LABEL = "__NOLABEL__"


@dataclass(frozen=True)
class StormPomdp:
    pomdp: Pomdp
    labels: dict[str, np.ndarray]  # label -> state mask
    enabled: np.ndarray  # (|S|, |A|) bool: Storm enables this action here


def _stormpy(field: str):
    try:
        import stormpy
    except ImportError:
        raise ProblemError(
            "reading PRISM or DRN models needs stormpy: pip install 'misdirect[storm]'",
            field=field,
        ) from None
    return stormpy


def load_storm_pomdp(
    path: Path, *, kind: str, constants: str | None = None, base: Path | None = None
) -> StormPomdp:
    """Build the model with Storm and translate it; ``kind`` is ``prism`` or ``drn``."""
    field = f"pomdp.{kind}"
    stormpy = _stormpy(field)
    # Storm logs parse errors to stderr itself; we report them once, in our own words
    stormpy.developer.set_log_level(stormpy.developer.LogLevel.OFF)
    path = (base / path) if base is not None and not Path(path).is_absolute() else Path(path)
    if not path.exists():
        raise ProblemError(f"file not found: {path}", field=field)
    try:
        if kind == "prism":
            program = stormpy.parse_prism_program(str(path))
            if constants:
                program = _instantiate(stormpy, program, constants)
            if program.has_undefined_constants:
                missing = ", ".join(c.name for c in program.constants if not c.defined)
                raise ProblemError(
                    f'constants without a value: {missing} (give them as constants: "N=5")',
                    field="pomdp.constants",
                )
            options = stormpy.BuilderOptions()
            options.set_build_state_valuations()
            options.set_build_choice_labels()
            options.set_build_observation_valuations()
            options.set_build_all_labels()
            model = stormpy.build_model(program, options=options)
        else:
            options = stormpy.developer.DirectEncodingParserOptions()
            options.build_choice_labeling = True
            model = stormpy.build_model_from_drn(str(path), options=options)
    except ProblemError:
        raise
    except Exception as error:  # Storm reports parse errors as RuntimeError/StormError
        message = " ".join(str(error).split())
        where = re.search(r"at (\d+):(\d+)", message)
        located = f"{field}, line {where[1]}, column {where[2]}" if where else field
        raise ProblemError(f"Storm cannot read {path.name}: {message}", field=located) from None
    if not model.is_partially_observable:
        raise ProblemError(f"{path.name} is a {model.model_type.name}, not a POMDP", field=field)
    return _translate(model, field)


def _instantiate(stormpy, program, constants: str):
    """Set ``constants`` ("N=5,p=0.1"); a bad definition is an error in ``pomdp.constants``."""
    try:
        program, _ = stormpy.instantiate_constants(program, constants)
    except Exception as error:  # Storm raises RuntimeError (WrongFormatException) here
        message = " ".join(str(error).split())
        message = re.sub(
            r"^(\w+Exception: )?Illegal constant definition string[^:]*: ", "", message
        )
        message = re.sub(r"^\w+Exception: ", "", message).rstrip(".")
        undefined = [c.name for c in program.constants if not c.defined]
        known = ", ".join(undefined) if undefined else "none: the program defines all of them"
        raise ProblemError(
            f"cannot set {constants!r}: {message} (constants to set: {known})",
            field="pomdp.constants",
        ) from None
    return program


def valuation_name(valuation: object) -> str:
    """Storm's valuation text as a name: ``[s=2\\t& o=3]`` -> ``s=2,o=3``.

    The one place this normalisation lives: observation names of Storm models and the
    observation labels of PAYNT controllers (which PAYNT writes in Storm's form) both go
    through it, so they match.
    """
    return re.sub(r"\s*&\s*", ",", str(valuation).strip().strip("[]").strip())


def _translate(model, field: str) -> StormPomdp:
    n_states = model.nr_states
    initial = list(model.initial_states)
    if len(initial) != 1:
        raise ProblemError(
            f"the model has {len(initial)} initial states; misdirect needs exactly one",
            field=field,
        )
    if model.has_state_valuations():
        names = [valuation_name(model.state_valuations.to_string(s)) for s in range(n_states)]
        if len(set(names)) != n_states:
            names = [f"s{s}" for s in range(n_states)]
    else:
        names = [f"s{s}" for s in range(n_states)]
    n_obs = model.nr_observations
    if model.has_observation_valuations():
        valuations = model.observation_valuations
        observations = [valuation_name(valuations.to_string(o)) for o in range(n_obs)]
        if len(set(observations)) != n_obs:
            observations = [f"obs{o}" for o in range(n_obs)]
    else:
        observations = [f"obs{o}" for o in range(n_obs)]

    matrix = model.transition_matrix
    groups = list(model.nondeterministic_choice_indices)
    labelling = model.choice_labeling if model.has_choice_labeling() else None
    action_index: dict[str, int] = {}
    act, src, dst, prob = [], [], [], []
    for s in range(n_states):
        seen: set[str] = set()
        for choice in range(groups[s], groups[s + 1]):
            labels = sorted(labelling.get_labels_of_choice(choice)) if labelling else []
            label = "+".join(labels) if labels else NO_LABEL
            if label in seen:
                raise ProblemError(
                    f"state {names[s]!r} has two choices labelled {label!r}; misdirect needs "
                    "one distribution per (state, action)",
                    field=field,
                )
            seen.add(label)
            a = action_index.setdefault(label, len(action_index))
            for entry in matrix.get_row(choice):
                act.append(a)
                src.append(s)
                dst.append(entry.column)
                prob.append(float(entry.value))
    act_a, src_a = np.array(act, dtype=np.int64), np.array(src, dtype=np.int64)
    dst_a = np.array(dst, dtype=np.int64)
    n_actions = len(action_index)
    enabled = np.zeros((n_states, n_actions), dtype=bool)
    enabled[src_a, act_a] = True
    # a state whose every enabled choice stays put is absorbing (as under `stay`, its disabled
    # actions do too): runs end there, and outcomes and simulation report it as such
    leaves = np.bincount(src_a[dst_a != src_a], minlength=n_states) > 0
    absorbing = ~leaves
    # a disabled (state, action) is a self-loop in the matrix; `forbid` is enforced on costs
    loops_s, loops_a = np.nonzero(~enabled)
    pomdp = Pomdp.from_triplets(
        states=tuple(names),
        actions=tuple(action_index),
        observations=tuple(observations),
        initial_state=int(initial[0]),
        observation_of=np.array(list(model.observations), dtype=np.int64),
        action=np.concatenate([act_a, loops_a]),
        source=np.concatenate([src_a, loops_s]),
        target=np.concatenate([dst_a, loops_s]),
        probability=np.concatenate([np.array(prob), np.ones(loops_s.size)]),
        absorbing=absorbing,
    )
    labels = {}
    for label in model.labeling.get_labels():
        mask = np.zeros(n_states, dtype=bool)
        mask[np.fromiter(model.labeling.get_states(label), dtype=np.int64)] = True
        labels[label] = mask
    return StormPomdp(pomdp=pomdp, labels=labels, enabled=enabled)
