"""Writing a problem's world out for other tools: Storm's DRN and the PRISM language.

Both writers produce the explicit POMDP (every action of every state, absorbing states as
self-loops) with the decoy states as the label ``decoy``; ``misdirect convert`` uses them, and
the tests read the files back through Storm and compare evaluated probabilities.
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from misdirect.core.model import Pomdp, Problem
from misdirect.io.files import one_line

# DRN has no names for states or observations (Storm numbers them): a DRN file misdirect writes
# keeps them in this comment, one JSON line, so a controller or alteration written against the
# original names reads back against the DRN file
NAMES_COMMENT = "// misdirect-names: "
_MAX_HEADER_LINES = 64


def _rows(problem: Problem):
    """(state, action, [(target, probability)]) for every state and action, in order."""
    pomdp = problem.pomdp
    matrix = pomdp.transitions.tocsr()
    matrix.sort_indices()
    for s in range(pomdp.n_states):
        for a in range(pomdp.n_actions):
            row = a * pomdp.n_states + s
            start, end = matrix.indptr[row], matrix.indptr[row + 1]
            yield (
                s,
                a,
                list(
                    zip(
                        matrix.indices[start:end].tolist(),
                        matrix.data[start:end].tolist(),
                        strict=True,
                    )
                ),
            )


def drn_action(name: str, fallback: str) -> str:
    """DRN reads an action name up to the end of its line, and splits it at white space."""
    ok = name and name.isprintable() and not any(c.isspace() or c in "[]{}" for c in name)
    return name if ok else fallback


def export_notes(problem: Problem, to: str) -> list[str]:
    """What the PRISM or DRN text cannot keep as it is, one line each: names that are not
    PRISM identifiers (PRISM) or not single words (DRN) become ``a<k>``, and names with
    control characters appear escaped in the comments."""
    pomdp = problem.pomdp
    rename = _identifier if to == "prism" else drn_action
    renamed = [
        f"{name!r} -> {label}"
        for k, name in enumerate(pomdp.actions)
        if (label := rename(name, f"a{k}")) != name
    ]
    notes = []
    if renamed:
        shown = ", ".join(renamed[:5]) + (
            f", … ({len(renamed)} in all)" if len(renamed) > 5 else ""
        )
        notes.append(f"{to.upper()} cannot express these action names, renamed: {shown}")
    names = (problem.name, *pomdp.states, *pomdp.observations, *pomdp.actions)
    if to == "prism" and any(one_line(name) != name for name in names):
        notes.append("names with control characters are escaped in the PRISM comments")
    return notes


def drn_text(problem: Problem) -> str:
    """Storm's explicit DRN format (``@type: POMDP``); observation ids follow ours. An action
    name DRN cannot hold (white space, brackets, control characters) is written ``a<k>``."""
    pomdp = problem.pomdp
    actions = [drn_action(name, f"a{k}") for k, name in enumerate(pomdp.actions)]
    names = {"states": list(pomdp.states), "observations": list(pomdp.observations)}
    lines = [
        "// Exported by misdirect",
        # ASCII JSON escapes every line break, so the names stay on this comment line
        NAMES_COMMENT + json.dumps(names, ensure_ascii=True, separators=(",", ":")),
        "@type: POMDP",
        "@parameters",
        "",
        "@reward_models",
        "",
        "@nr_states",
        str(pomdp.n_states),
        "@nr_choices",
        str(pomdp.n_states * pomdp.n_actions),
        "@model",
    ]
    current = -1
    for s, a, entries in _rows(problem):
        if s != current:
            labels = []
            if s == pomdp.initial_state:
                labels.append("init")
            if problem.decoy[s]:
                labels.append("decoy")
            lines.append(
                f"state {s} {{{int(pomdp.observation_of[s])}}} {' '.join(labels)}".rstrip()
            )
            current = s
        lines.append(f"\taction {actions[a]}")
        lines += [f"\t\t{t} : {p!r}" for t, p in entries]
    return "\n".join(lines) + "\n"


def prism_text(problem: Problem) -> str:
    """A PRISM POMDP: state variable ``s``, observable ``o`` updated with it, label ``decoy``.

    Action names become PRISM action labels, so they must be PRISM identifiers; others are
    replaced by ``a<k>`` and listed in a comment.
    """
    pomdp = problem.pomdp
    labels = [_identifier(name, f"a{k}") for k, name in enumerate(pomdp.actions)]
    o_of = pomdp.observation_of
    # names appear only in comments, which end at a line break: escape what could break one
    names = {"states": list(pomdp.states), "observations": list(pomdp.observations)}
    lines = [
        "// Exported by misdirect",
        NAMES_COMMENT + json.dumps(names, ensure_ascii=True, separators=(",", ":")),
        f"// problem: {one_line(problem.name)}",
        "// states (value of s): "
        + ", ".join(f"{i}={one_line(n)}" for i, n in enumerate(pomdp.states)),
        "// observations (value of o): "
        + ", ".join(f"{i}={one_line(n)}" for i, n in enumerate(pomdp.observations)),
        "// actions: "
        + ", ".join(f"{lab}={one_line(n)}" for lab, n in zip(labels, pomdp.actions, strict=True)),
        "",
        "pomdp",
        "",
        "observables",
        "\to",
        "endobservables",
        "",
        "module world",
        f"\ts : [0..{pomdp.n_states - 1}] init {pomdp.initial_state};",
        f"\to : [0..{pomdp.n_observations - 1}] init {int(o_of[pomdp.initial_state])};",
    ]
    for s, a, entries in _rows(problem):
        update = " + ".join(f"{p!r} : (s'={t}) & (o'={int(o_of[t])})" for t, p in entries)
        lines.append(f"\t[{labels[a]}] s={s} -> {update};")
    lines += ["endmodule", ""]
    decoys = np.flatnonzero(problem.decoy)
    lines.append('label "decoy" = ' + (" | ".join(f"s={s}" for s in decoys) or "false") + ";")
    return "\n".join(lines) + "\n"


def _identifier(name: str, fallback: str) -> str:
    ok = name.replace("_", "a").isalnum() and not name[0].isdigit() and name.isascii()
    return name if ok else fallback


def drn_names(path: Path) -> dict[str, list[str]] | None:
    """The names a DRN (or PRISM) file misdirect wrote keeps in its header comment (see
    :data:`NAMES_COMMENT`), or None: no such comment, or one that does not hold two lists of
    distinct, non-empty names."""
    try:
        with open(path, encoding="utf-8", errors="replace") as stream:
            for _ in range(_MAX_HEADER_LINES):
                line = stream.readline()
                if not line.startswith("//"):
                    return None
                if line.startswith(NAMES_COMMENT):
                    document = json.loads(line[len(NAMES_COMMENT) :])
                    break
            else:
                return None
    except (OSError, ValueError, RecursionError):
        return None
    if not isinstance(document, dict):
        return None
    names = {key: document.get(key) for key in ("states", "observations")}
    for value in names.values():
        if not _distinct_names(value):
            return None
    return names  # type: ignore[return-value]


def _distinct_names(value: Any) -> bool:
    return (
        isinstance(value, list)
        and all(isinstance(name, str) and name for name in value)
        and len(set(value)) == len(value)
    )


# how Storm names what our files number: DRN observations obs<k>; PRISM ones by the value of
# the observable o, PRISM states by s (and o)
_NUMBERED = {
    "drn": (re.compile(r"obs(\d+)"), None),
    "prism": (re.compile(r"o=(\d+)"), re.compile(r"s=(\d+),o=\d+")),
}


def with_exported_names(pomdp: Pomdp, path: Path, kind: str) -> Pomdp:
    """``pomdp``, read by Storm from a PRISM or DRN file ``path``, with the names the file's
    header keeps (files misdirect wrote): observation k (as the file numbers it) gets the k-th
    name, and state k the k-th; observations the header names but no state emits are added.
    Unchanged without such a header, or where the numbers Storm shows do not fit the names."""
    names = drn_names(path)
    if names is None:
        return pomdp
    observation_pattern, state_pattern = _NUMBERED[kind]
    observations = _renamed(pomdp.observations, observation_pattern, names["observations"])
    if observations != pomdp.observations:
        # observations no state emits (declared for the controller) are in no Storm model:
        # still alteration targets, so they come back after the emitted ones
        emitted = set(observations)
        observations += tuple(name for name in names["observations"] if name not in emitted)
    if state_pattern is None:  # DRN keeps the file's state numbers
        same = len(names["states"]) == pomdp.n_states
        states = tuple(names["states"]) if same else pomdp.states
    else:
        states = _renamed(pomdp.states, state_pattern, names["states"])
    return dataclasses.replace(pomdp, states=states, observations=observations)


def _renamed(shown: tuple[str, ...], pattern: re.Pattern[str], names: list[str]) -> tuple[str, ...]:
    """Each ``shown`` name, numbered as ``pattern`` reads it, as ``names`` names that number;
    ``shown`` itself unless every name is numbered, within range and distinct."""
    found = [pattern.fullmatch(name) for name in shown]
    numbers = [int(match[1]) for match in found if match]
    if len(numbers) != len(shown) or len(set(numbers)) != len(numbers):
        return shown
    if any(k >= len(names) for k in numbers):
        return shown
    return tuple(names[k] for k in numbers)


# -- the attacked product chain -----------------------------------------------------------------


def chain_labels(problem: Problem, world_state: np.ndarray, initial: int) -> dict[str, np.ndarray]:
    """The product states each label holds: ``init`` (the start), ``decoy`` (a decoy world
    state), ``absorbing`` (an absorbing world state: the run has ended) and, for a monitored
    problem, ``alarm`` (the monitor raised the alarm: the run has ended outside the decoy)."""
    init = np.zeros(world_state.size, dtype=bool)
    init[initial] = True
    labels = {
        "init": init,
        "decoy": np.asarray(problem.decoy, dtype=bool)[world_state],
        "absorbing": problem.pomdp.absorbing[world_state],
    }
    if problem.alarm_state is not None:  # a monitored problem: where its alarm ends a run
        labels["alarm"] = world_state == problem.alarm_state
    return labels


def chain_state_names(problem: Problem, world_state: np.ndarray, node: np.ndarray) -> list[str]:
    """``(world state, node)`` of each product state, by name."""
    states = np.array(problem.pomdp.states, dtype=object)[world_state]
    nodes = np.array(problem.controller.nodes, dtype=object)[node]
    return [f"({s}, {n})" for s, n in zip(states.tolist(), nodes.tolist(), strict=True)]


def chain_drn_text(
    problem: Problem, matrix, world_state: np.ndarray, node: np.ndarray, initial: int
) -> str:
    """The product chain as a Storm DRN ``DTMC``: labels ``init``, ``decoy``, ``absorbing``;
    the names of its states ``(world state, node)`` in the header comment."""
    matrix = matrix.tocsr()
    matrix.sort_indices()
    labels = chain_labels(problem, world_state, initial)
    names = {"states": chain_state_names(problem, world_state, node)}
    n = int(world_state.size)
    lines = [
        "// Exported by misdirect: the product chain of the robot and its controller under "
        "one alteration",
        NAMES_COMMENT + json.dumps(names, ensure_ascii=True, separators=(",", ":")),
        "@type: DTMC",
        "@parameters",
        "",
        "@reward_models",
        "",
        "@nr_states",
        str(n),
        "@nr_choices",
        str(n),
        "@model",
    ]
    tags = np.full(n, "", dtype=object)
    for label, mask in labels.items():
        tags[mask] = tags[mask] + " " + label
    indptr, indices, data = matrix.indptr, matrix.indices.tolist(), matrix.data.tolist()
    for q in range(n):
        lines.append(f"state {q}{tags[q]}")
        lines.append("\taction 0")
        lines += [
            f"\t\t{t} : {p!r}"
            for t, p in zip(
                indices[indptr[q] : indptr[q + 1]], data[indptr[q] : indptr[q + 1]], strict=True
            )
        ]
    return "\n".join(lines) + "\n"


def chain_prism_explicit(
    problem: Problem, matrix, world_state: np.ndarray, initial: int
) -> tuple[str, str]:
    """The product chain in PRISM's explicit format: the ``.tra`` text (``states
    transitions``, then ``i j p`` rows) and the ``.lab`` text (label ``init``, ``decoy``,
    ``absorbing``)."""
    coo = matrix.tocsr()
    coo.sort_indices()
    coo = coo.tocoo()
    n = int(world_state.size)
    tra = [f"{n} {coo.nnz}"] + [
        f"{i} {j} {p!r}"
        for i, j, p in zip(coo.row.tolist(), coo.col.tolist(), coo.data.tolist(), strict=True)
    ]
    labels = chain_labels(problem, world_state, initial)
    names = list(labels)
    header = " ".join(f'{k}="{name}"' for k, name in enumerate(names))
    member = np.stack([labels[name] for name in names], axis=1)
    lab = [header] + [
        f"{q}: " + " ".join(str(k) for k in np.flatnonzero(member[q]))
        for q in np.flatnonzero(member.any(axis=1)).tolist()
    ]
    return "\n".join(tra) + "\n", "\n".join(lab) + "\n"
