"""PRISM encoding of (POMDP, controller, alteration) for Storm to build the product itself.

Two modules synchronise on action labels: ``world`` owns the state ``s`` and moves it with
``P(s, a, ·)``; ``controller`` owns the node ``n`` and, reading the observation the altered
sensor shows in ``s``, enables exactly one action label and updates ``n``. Storm's parallel
composition is therefore an independent construction of the product chain. A randomized
controller takes two steps per world step: an internal command draws the entry ``e`` of its
move (a distribution over (action, next node)) with the move's probabilities, then the
synchronised command ``[act<a>] e=k`` plays that entry's action and sets the node; the
intermediate states add steps, not probability, so Pr(F decoy) is unchanged. Probabilities are
written as exact fractions where they are ratios of small integers, so Storm can check the
model in exact rational arithmetic.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np

from misdirect.core.model import Problem


def _any(var: str, values) -> str:
    return "(" + " | ".join(f"{var}={int(v)}" for v in values) + ")"


def _exact(p: float) -> str:
    fraction = Fraction(p).limit_denominator(10_000)
    return str(fraction) if abs(float(fraction) - p) < 1e-15 else repr(float(p))


def world_module(pomdp) -> list[str]:
    """The POMDP's world as a PRISM module: one command per state and action, labelled act<a>
    so that a controller module synchronises on it; absorbing states loop."""
    lines = ["module world", f"  s : [0..{pomdp.n_states - 1}] init {pomdp.initial_state};"]
    for s in range(pomdp.n_states):
        for a in range(pomdp.n_actions):
            if pomdp.absorbing[s]:
                lines.append(f"  [act{a}] s={s} -> 1:(s'={s});")
                continue
            row = pomdp.transition_matrix(a)[s]
            branches = " + ".join(
                f"{_exact(p)}:(s'={t})" for t, p in zip(row.indices, row.data, strict=True)
            )
            lines.append(f"  [act{a}] s={s} -> {branches};")
    return [*lines, "endmodule"]


def prism_product(problem: Problem, alteration: np.ndarray) -> str:
    pomdp, ctrl = problem.pomdp, problem.controller
    received = alteration[pomdp.observation_of]  # observation the robot gets in each state
    lines = ["dtmc", *world_module(pomdp)]
    lines += [
        "module controller",
        f"  n : [0..{ctrl.n_nodes - 1}] init {ctrl.initial_node};",
    ]
    # Every label must be in the controller's alphabet, or the world would fire it on its own.
    lines += [f"  [act{a}] false -> true;" for a in range(pomdp.n_actions)]
    if not ctrl.is_deterministic:
        return _randomized(problem, received, lines)
    for n in range(ctrl.n_nodes):
        behaviour = np.stack([ctrl.action[n, received], ctrl.update[n, received]], axis=1)
        for a, nxt in np.unique(behaviour, axis=0):
            states = np.flatnonzero((behaviour[:, 0] == a) & (behaviour[:, 1] == nxt))
            lines.append(f"  [act{a}] n={n} & {_any('s', states)} -> 1:(n'={nxt});")
    lines.append("endmodule")
    lines.append(f'label "decoy" = {_any("s", np.flatnonzero(problem.decoy))};')
    return "\n".join(lines) + "\n"


def _randomized(problem: Problem, received: np.ndarray, lines: list[str]) -> str:
    """The controller module of a randomized controller: draw an entry, then play it."""
    ctrl = problem.controller
    entries = ctrl.move_action.size
    lines.insert(lines.index("module controller") + 2, f"  e : [-1..{entries - 1}] init -1;")
    for n in range(ctrl.n_nodes):
        moves = ctrl.move[n, received]  # the move played in each world state
        for m in np.unique(moves):
            states = np.flatnonzero(moves == m)
            first, last = ctrl.move_ptr[m], ctrl.move_ptr[m + 1]
            branches = " + ".join(
                f"{_exact(ctrl.move_probability[k])}:(e'={k})" for k in range(first, last)
            )
            lines.append(f"  [] e=-1 & n={n} & {_any('s', states)} -> {branches};")
    for k in range(entries):
        a, nxt = ctrl.move_action[k], ctrl.move_next[k]
        lines.append(f"  [act{a}] e={k} -> 1:(n'={nxt}) & (e'=-1);")
    lines.append("endmodule")
    lines.append(f'label "decoy" = {_any("s", np.flatnonzero(problem.decoy))};')
    return "\n".join(lines) + "\n"


def storm_probability(tmp_path, problem: Problem, alteration: np.ndarray) -> float:
    """Storm's exact (rational arithmetic) Pr(F decoy) for the PRISM product encoding."""
    import stormpy

    path = tmp_path / "product.prism"
    path.write_text(prism_product(problem, alteration))
    program = stormpy.parse_prism_program(str(path))
    formula = stormpy.parse_properties('P=? [F "decoy"]', program)
    model = stormpy.build_model[stormpy.Rational](program, formula)
    result = stormpy.model_checking(model, formula[0], environment=stormpy.environments.exact())
    return float(result.get_value(model.initial_states[0]))


def random_allowed_alteration(problem: Problem, rng: np.random.Generator) -> np.ndarray:
    """A random alteration that respects the problem (initial observation, forbidden pairs)."""
    alpha = problem.identity()
    for o in range(problem.pomdp.n_observations):
        if o != problem.pomdp.initial_observation:
            alpha[o] = rng.choice(np.flatnonzero(np.isfinite(problem.cost.row(o))))
    return alpha
