"""The model as written, in rational arithmetic (``--exact``): Storm builds a PRISM or DRN
world with exact probabilities, and Storm's exact engine values an alteration on it.

misdirect solves the chain as loaded, in doubles, and proves each value it prints to within
1e-9 of *that* chain's (docs/exactness.md). A probability such as 1/3 or 0.1 is not a double,
so the chain as loaded is the model rounded once, and on a chain absorbed only after some 10^9
steps that rounding alone can move the answer in its seventh digit. This module says what an
answer is worth on the model as written: the world's probabilities as Storm builds them in
rationals, the controller's probabilities and the decoy weights as the shortest decimals of
their doubles (what a file writes). Optimality stays a statement about the chain as loaded.

Storm is native code that a malformed file can crash, so both Storm steps run in a child
process (:func:`~misdirect.io.storm_guard.run_isolated`), as the loader's do.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from misdirect.core import tolerance
from misdirect.core.evaluate import decoy_value
from misdirect.core.model import Problem, reachable_from
from misdirect.core.product import full_product_matrix
from misdirect.errors import ProblemError
from misdirect.io.model_problem import built_from
from misdirect.io.problem_file import StormPomdpSpec, read_spec
from misdirect.io.storm import build_storm_model, load_stormpy
from misdirect.io.storm_guard import run_isolated
from misdirect.io.storm_names import NO_LABEL

FIELD = "exact"
# a double and Storm's rational of the same entry may differ by the rounding of the
# expression that computed the double (Storm evaluates PRISM expressions in doubles)
AGREEMENT = tolerance.TIE


@dataclass(frozen=True)
class ExactValue:
    """One alteration's value on the model as written, beside its value on the chain as
    loaded (what the solvers print)."""

    value: Fraction
    loaded: float
    product_states: int  # of the exact chain Storm checked (decoy states not expanded)

    @property
    def difference(self) -> float:
        """Exact value minus the chain-as-loaded value (the input's rounding, in effect)."""
        return float(self.value - Fraction(self.loaded))

    def to_dict(self) -> dict[str, Any]:
        return {
            "value": f"{self.value.numerator}/{self.value.denominator}",
            "approx": float(self.value),
            "difference": self.difference,
        }


class ExactModel:
    """The world's probabilities as rationals, one per entry of ``problem.pomdp.transitions``
    (the same CSR structure), and the exact value of any alteration on it."""

    def __init__(self, problem: Problem, transitions: np.ndarray, name: str) -> None:
        self.problem = problem
        self.transitions = transitions  # (nnz,) object array of Fraction
        self.name = name  # the model file, for messages

    def value(self, alteration: Any) -> ExactValue:
        """Storm's exact value of ``alteration`` on the model as written."""
        problem = self.problem
        alteration = problem.as_alteration(alteration, source=FIELD)
        loaded = decoy_value(problem, alteration).value
        text, weights, states = self._product_drn(alteration)
        found = run_isolated(
            _check_exactly,
            text,
            [f"decoy{i}" for i in range(len(weights))],
            name=f"the exact product chain of {self.name}",
            field=FIELD,
        )
        value = sum((w * Fraction(p) for w, p in zip(weights, found, strict=True)), Fraction(0))
        return ExactValue(value=value, loaded=loaded, product_states=states)

    def _product_drn(self, alteration: np.ndarray) -> tuple[str, list[Fraction], int]:
        """The product chain under ``alteration`` as an exact DRN text (states reachable from
        the start; a decoy state stops the run), with the weight of each decoy label (one per
        weight among the decoy states it reaches), and its number of states."""
        problem = self.problem
        pomdp, ctrl = problem.pomdp, problem.controller
        n, m = pomdp.n_states, ctrl.n_nodes
        objective = problem.objective
        stop = np.repeat(objective.target, m)  # product index s * m + node
        graph = full_product_matrix(problem, alteration)
        graph = sp.diags((~stop).astype(np.float64)) @ graph  # decoys are not expanded
        start = pomdp.initial_state * m + ctrl.initial_node
        keep = np.flatnonzero(reachable_from(graph.tocsr(), np.array([start])))
        expand = keep[~stop[keep]]
        world, node = expand // m, expand % m
        received = alteration[pomdp.observation_of]
        owner, action, next_node, probability = ctrl.entries(node, received[world])
        move_p = [_decimal(p) for p in probability.tolist()]
        _check_moves(owner, move_p, ctrl, node, received[world], problem)
        matrix = pomdp.transitions
        rows = action * n + world[owner]
        counts = np.diff(matrix.indptr)[rows]
        offsets = np.cumsum(counts) - counts
        at = np.repeat(matrix.indptr[rows] - offsets, counts) + np.arange(int(counts.sum()))
        entry = np.repeat(np.arange(owner.size), counts)  # controller entry of each branch
        source = np.searchsorted(keep, expand[owner[entry]])
        target = np.searchsorted(keep, matrix.indices[at].astype(np.int64) * m + next_node[entry])
        exact = self.transitions
        branch = [exact[i] * move_p[e] for i, e in zip(at.tolist(), entry.tolist(), strict=True)]
        stops = np.flatnonzero(stop[keep])
        weight_of = {k: _decimal(float(objective.value[keep[k] // m])) for k in stops.tolist()}
        weights = sorted(set(weight_of.values()))  # those of decoy states the run may reach
        label_of = {w: f"decoy{i}" for i, w in enumerate(weights)}
        label = dict.fromkeys(range(keep.size), "")
        for k, w in weight_of.items():
            label[k] = " " + label_of[w]
        rows_out: dict[int, dict[int, Fraction]] = {k: {} for k in range(keep.size)}
        for s, t, p in zip(source.tolist(), target.tolist(), branch, strict=True):
            row = rows_out[s]
            row[t] = row.get(t, Fraction(0)) + p
        for k in stops.tolist():
            rows_out[k] = {k: Fraction(1)}
        initial = int(np.searchsorted(keep, start))
        lines = ["@type: DTMC", "@parameters", "", "@reward_models", "", "@nr_states"]
        lines += [str(keep.size), "@nr_choices", str(keep.size), "@model"]
        for k in range(keep.size):
            lines.append(f"state {k}" + (" init" if k == initial else "") + label[k])
            lines.append("\taction 0")
            for t, p in sorted(rows_out[k].items()):
                lines.append(f"\t\t{t} : {p.numerator}/{p.denominator}")
        return "\n".join(lines) + "\n", weights, int(keep.size)


def exact_model(problem: Problem) -> ExactModel:
    """The world of ``problem`` rebuilt by Storm in rational arithmetic, from the PRISM or DRN
    model its problem file names. Refused, naming the reason, for any other world.

    Examples
    --------
    >>> problem = misdirect.load_problem("lingering.yaml")  # doctest: +SKIP
    >>> misdirect.exact_model(problem).value(problem.identity()).value  # doctest: +SKIP
    Fraction(1, 3)
    """
    if problem.source is None or not Path(problem.source).is_file():
        raise ProblemError(
            "exact values need the problem file that names a PRISM or DRN model "
            "(this problem was not read from a file)"
        )
    path = Path(problem.source)
    settings = built_from(problem)
    if settings is not None:  # built from a model and its settings, not a problem file
        world, path = settings, Path(problem.source).absolute().parent / "settings"
    else:
        spec = read_spec(path)
        if not isinstance(spec.pomdp, StormPomdpSpec) or spec.grid is not None:
            raise ProblemError(
                "exact values need a world that Storm builds (pomdp: {prism: FILE} or "
                "{drn: FILE}); this problem's world is "
                + ("a grid map" if spec.grid is not None else "an explicit model"),
                field="pomdp",
                source=str(path),
            )
        world = spec.pomdp
    kind = "prism" if world.prism is not None else "drn"
    model = path.parent / str(world.prism or world.drn)
    transitions = run_isolated(
        _exact_transitions,
        problem,
        model,
        kind,
        world.constants,
        world.terminal,
        world.terminal_from,
        name=model.name,
        field=f"pomdp.{kind}",
    )
    return ExactModel(problem, transitions, model.name)


def _exact_transitions(
    problem: Problem,
    path: Path,
    kind: str,
    constants: str | None,
    terminal: str | None,
    terminal_from: str | None,
) -> np.ndarray:
    """Storm's rational probability of every entry of ``problem.pomdp.transitions``; the rows
    misdirect adds itself (disabled actions, absorbing states: stay with probability 1) are 1."""
    stormpy = load_stormpy(f"pomdp.{kind}")
    model, _ = build_storm_model(
        stormpy,
        path,
        kind,
        f"pomdp.{kind}",
        constants=constants,
        terminal=terminal,
        terminal_from=terminal_from,
        exact=True,
    )
    pomdp = problem.pomdp
    n = pomdp.n_states
    if model.nr_states != n:
        raise ProblemError(
            f"Storm's exact build of {path.name} has {model.nr_states:,} states, its double "
            f"build {n:,}",
            field=FIELD,
        )
    action_index = {name: i for i, name in enumerate(pomdp.actions)}
    labelling = model.choice_labeling if model.has_choice_labeling() else None
    groups = model.nondeterministic_choice_indices
    rows: list[int] = []
    cols: list[int] = []
    values: list[Fraction] = []
    parsed: dict[str, Fraction] = {}  # models repeat a few probabilities: parse each once
    matrix = model.transition_matrix
    for s in np.flatnonzero(~pomdp.absorbing).tolist():
        for choice in range(groups[s], groups[s + 1]):
            labels = sorted(labelling.get_labels_of_choice(choice)) if labelling else []
            a = action_index.get("+".join(labels) or NO_LABEL)
            if a is None:
                raise ProblemError(
                    f"Storm's exact build of {path.name} has action {'+'.join(labels)!r} in "
                    f"state {pomdp.states[s]!r}, which its double build has not",
                    field=FIELD,
                )
            total = Fraction(0)
            for branch in matrix.get_row(choice):
                text = str(branch.value)
                p = parsed.get(text) or parsed.setdefault(text, Fraction(text))
                total += p
                if p:
                    rows.append(a * n + s)
                    cols.append(int(branch.column))
                    values.append(p)
            if total != 1:
                raise ProblemError(
                    f"in {path.name}, the probabilities of state {pomdp.states[s]!r} under "
                    f"action {pomdp.actions[a]!r} add up to {total} in exact arithmetic, not 1",
                    field=FIELD,
                )
    return _aligned(pomdp.transitions, n, rows, cols, values, path.name)


def _aligned(
    matrix: sp.csr_matrix, n: int, rows: list[int], cols: list[int], values: list[Fraction], name
) -> np.ndarray:
    """``values`` placed at their entries of ``matrix``; every entry checked against the
    double misdirect loaded, and every entry Storm did not give checked to be a stay of 1."""
    entry_row = np.repeat(np.arange(matrix.shape[0]), np.diff(matrix.indptr))
    keys = entry_row * n + matrix.indices.astype(np.int64)
    order = np.argsort(keys, kind="stable")
    theirs = np.asarray(rows, dtype=np.int64) * n + np.asarray(cols, dtype=np.int64)
    where = np.searchsorted(keys[order], theirs)
    where = np.minimum(where, max(keys.size - 1, 0))
    missing = keys.size == 0 or not np.array_equal(keys[order][where], theirs)
    if missing:
        raise ProblemError(
            f"Storm's exact build of {name} has transitions its double build has not",
            field=FIELD,
        )
    at = order[where]
    exact = np.full(matrix.nnz, Fraction(1), dtype=object)
    exact[at] = values
    approx = np.array([float(v) for v in values])
    if not np.allclose(approx, matrix.data[at], rtol=AGREEMENT, atol=0.0):
        raise ProblemError(
            f"Storm's exact build of {name} does not match its double build",
            field=FIELD,
        )
    given = np.zeros(matrix.nnz, dtype=bool)
    given[at] = True
    stays = entry_row[~given] % n == matrix.indices[~given]
    if not (stays.all() and (matrix.data[~given] == 1.0).all()):
        raise ProblemError(
            f"the double build of {name} has transitions Storm's exact build has not",
            field=FIELD,
        )
    return exact


def _decimal(x: float) -> Fraction:
    """The shortest decimal that reads back as ``x``: what a file wrote (``0.1`` is 1/10)."""
    return Fraction(repr(float(x)))


def _check_moves(owner, move_p, ctrl, node, received, problem: Problem) -> None:
    """Each move of a randomized controller must sum to 1 as decimals, or it is no
    distribution on the model as written."""
    if ctrl.is_deterministic:
        return
    sums: dict[int, Fraction] = {}
    for o, p in zip(owner.tolist(), move_p, strict=True):
        sums[o] = sums.get(o, Fraction(0)) + p
    for o, total in sums.items():
        if total != 1:
            raise ProblemError(
                f"the controller's move in node {ctrl.nodes[node[o]]!r} reading "
                f"{problem.pomdp.observations[received[o]]!r} has probabilities whose decimals "
                f"add up to {float(total)!r}, not 1: no exact distribution to check",
                field=FIELD,
            )


def _check_exactly(text: str, labels: list[str]) -> list[str]:
    """Storm's exact Pr(F label) from the initial state, one per label (child process)."""
    stormpy = load_stormpy(FIELD)
    with tempfile.TemporaryDirectory(prefix="misdirect-exact-") as folder:
        path = Path(folder) / "product.drn"
        path.write_text(text, encoding="utf-8")
        model = stormpy.build_model_from_drn[stormpy.Rational](str(path))
    environment = stormpy.environments.exact()
    found = []
    for label in labels:
        formula = stormpy.parse_properties(f'P=? [F "{label}"]')[0]
        result = stormpy.model_checking(model, formula, environment=environment)
        found.append(str(result.get_value(model.initial_states[0])))
    return found
