"""Writing a problem's world out for other tools: Storm's DRN and the PRISM language.

Both writers produce the explicit POMDP (every action of every state, absorbing states as
self-loops) with the decoy states as the label ``decoy``; ``misdirect convert`` uses them, and
the tests read the files back through Storm and compare evaluated probabilities.
"""

from __future__ import annotations

import numpy as np

from misdirect.core.model import Problem
from misdirect.io.files import one_line


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


def _drn_action(name: str, fallback: str) -> str:
    """DRN reads an action name up to the end of its line, and splits it at white space."""
    ok = name and name.isprintable() and not any(c.isspace() or c in "[]{}" for c in name)
    return name if ok else fallback


def export_notes(problem: Problem, to: str) -> list[str]:
    """What the PRISM or DRN text cannot keep as it is, one line each: names that are not
    PRISM identifiers (PRISM) or not single words (DRN) become ``a<k>``, and names with
    control characters appear escaped in the comments."""
    pomdp = problem.pomdp
    rename = _identifier if to == "prism" else _drn_action
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
    actions = [_drn_action(name, f"a{k}") for k, name in enumerate(pomdp.actions)]
    lines = [
        "// Exported by misdirect",
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
    lines = [
        "// Exported by misdirect",
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
