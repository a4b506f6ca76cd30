"""The small model of the scale tests (tests/test_scale.py, tests/test_exports.py): from s0
the robot reaches s1 with probability ``p``, where the controller plays a or b by what it
reads; a plays into the decoy with 0.8, b with 0.2. Altering o1 to o0 makes s1 play a: the
decoy's probability goes from 0.2 p to 0.8 p (by hand)."""

from __future__ import annotations

import textwrap


def yaml_float(x: float) -> str:
    """``x`` as YAML reads a float back (``1e-10`` is a string to it; ``1.0e-10`` is not)."""
    text = repr(float(x))
    mantissa, _, exponent = text.partition("e")
    if exponent and "." not in mantissa:
        mantissa += ".0"
    return mantissa + ("e" + ("+" if exponent[0].isdigit() else "") + exponent if exponent else "")


def scale_model_text(
    *, p: float = 0.5, weight: float | None = None, cost: float = 1.0, budget: float = 1.0
) -> str:
    """The problem file (misdirect/v1) of the model, its decoy weighted by ``weight`` if given."""
    decoy = "decoy: [trap]" if weight is None else f"decoy: {{trap: {yaml_float(weight)}}}"
    p_text, q_text = yaml_float(p), yaml_float(1 - p)
    return textwrap.dedent(
        f"""\
        format: misdirect/v1
        name: scale
        pomdp:
          states: [s0, s1, s2, trap, goal]
          actions: [a, b]
          initial: s0
          observe: {{s0: o0, s1: o1, s2: o2, trap: g, goal: g}}
          transitions:
            - [s0, a, s1, {p_text}]
            - [s0, a, s2, {q_text}]
            - [s0, b, s1, {p_text}]
            - [s0, b, s2, {q_text}]
            - [s1, a, trap, 0.8]
            - [s1, a, goal, 0.2]
            - [s1, b, trap, 0.2]
            - [s1, b, goal, 0.8]
            - [s2, a, goal, 1.0]
            - [s2, b, goal, 1.0]
          absorbing: [trap, goal]
        controller:
          nodes: [n]
          initial: n
          rules:
            - {{node: "*", obs: o0, action: a, next: n}}
            - {{node: "*", obs: "*", action: b, next: n}}
        deception:
          {decoy}
          budget: {yaml_float(budget)}
          cost: {{default: {yaml_float(cost)}}}
        """
    )
