"""Exact means exact: every value carries a proven error bound, checked against rational solves.

The chains here are absorbed only after about 4·10^9 steps (every state of a 5-state cycle
leaks to the decoy or the goal with probability 10^-11 to 10^-10), like the published maze
whose direct solve was 1.6e-7 off. The reference is Gaussian elimination in exact rational
arithmetic (``fractions``) on the very doubles of the chain, written out here independently
of the program; where stormpy is installed, Storm's exact engine agrees with it.
"""

from __future__ import annotations

import json
from decimal import Decimal
from fractions import Fraction

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import splu
from typer.testing import CliRunner

from misdirect import evaluate, load_problem, solve
from misdirect.cli import app
from misdirect.core import reachability, residual, tolerance
from misdirect.core.reachability import occupation, reach_probability_bounded
from misdirect.solvers.certification import decide
from misdirect.solvers.status import Status
from rational import gauss_jordan

UNIT = Decimal("3e-11")  # the leaks are multiples of this
CYCLE = 5
# In-cycle moves of state i (the entry left as None takes what the leaks leave), shared by
# both actions; the actions differ only in their leaks (to decoy, to goal) in units of UNIT.
MOVES = {
    0: {1: "0.6", 3: None},
    1: {2: "0.3", 0: "0.5", 4: None},
    2: {3: "0.7", 2: "0.1", 0: None},
    3: {4: "0.45", 1: None},
    4: {0: "0.8", 2: None},
}
LEAKS = {
    "a": {0: (3, 4), 1: (1, 8), 2: (6, 2), 3: (2, 2), 4: (5, 5)},
    "b": {0: (9, 1), 1: (8, 3), 2: (1, 7), 3: (7, 4), 4: (2, 9)},
}
NAMES = [f"c{i}" for i in range(CYCLE)] + ["decoy", "goal"]
DECOY = NAMES.index("decoy")


def _row(state: int, action: str) -> dict[int, Decimal]:
    """State ``state``'s row under ``action``: decimals that sum to exactly 1."""
    to_decoy, to_goal = LEAKS[action][state]
    row = {DECOY: to_decoy * UNIT, DECOY + 1: to_goal * UNIT}
    given = {j: Decimal(p) for j, p in MOVES[state].items() if p is not None}
    rest = 1 - sum(row.values()) - sum(given.values())
    row.update(given)
    row.update({j: rest for j, p in MOVES[state].items() if p is None})
    return row


def _matrix(actions: str) -> np.ndarray:
    """The chain when state ``i`` plays ``actions[i]``, as the doubles a reader makes of it."""
    p = np.zeros((len(NAMES), len(NAMES)))
    for i, action in enumerate(actions):
        for j, q in _row(i, action).items():
            p[i, j] = float(q)
    p[DECOY, DECOY] = p[DECOY + 1, DECOY + 1] = 1.0
    return p


def _exact(p: np.ndarray, rhs: np.ndarray) -> list[Fraction]:
    """``(I - Q) x = rhs`` on the cycle, Q and rhs taken as exact rationals (Gauss-Jordan)."""
    n = CYCLE
    a = [[Fraction(int(i == j)) - Fraction(float(p[i, j])) for j in range(n)] for i in range(n)]
    return gauss_jordan(a, [Fraction(rhs[i]) for i in range(n)])


def _exact_decoy(p: np.ndarray) -> list[Fraction]:
    return _exact(p, [Fraction(float(p[i, DECOY])) for i in range(CYCLE)])


def _off(value: float, exact: Fraction) -> float:
    return abs(float(Fraction(value) - exact))


@pytest.mark.parametrize("actions", ["aaaab", "aaaaa", "bbbbb"])
def test_the_chain_is_ill_conditioned_and_double_precision_loses_digits(actions):
    """The premise: absorbed after more than 10^9 steps, and both direct double solves (the
    dense LU of small chains, SuperLU of larger ones) are off by more than 1e-9."""
    p = _matrix(actions)
    steps = _exact(p, [Fraction(1)] * CYCLE)
    assert min(steps) > 1e9
    exact = _exact_decoy(p)
    system, b = np.eye(CYCLE) - p[:CYCLE, :CYCLE], p[:CYCLE, DECOY]
    dense = np.linalg.solve(system, b)
    sparse = splu(sp.csc_matrix(system)).solve(b)
    assert max(_off(dense[i], exact[i]) for i in range(CYCLE)) > 1e-9
    assert max(_off(sparse[i], exact[i]) for i in range(CYCLE)) > 1e-9


def _ladder(rungs: int) -> tuple[sp.csr_matrix, np.ndarray]:
    """``rungs`` copies of the cycle in a row: the leaks of copy ``k`` to the goal enter copy
    ``k + 1`` instead (the last one's reach the goal), so each copy is its own small strongly
    connected component, as the component-wise routes need."""
    size = rungs * CYCLE + 2
    decoy, goal = size - 2, size - 1
    p = np.zeros((size, size))
    for k in range(rungs):
        block = _matrix("ab"[k % 2] * CYCLE)
        base = k * CYCLE
        p[base : base + CYCLE, base : base + CYCLE] = block[:CYCLE, :CYCLE]
        p[base : base + CYCLE, decoy] = block[:CYCLE, DECOY]
        p[base : base + CYCLE, goal if k == rungs - 1 else base + CYCLE] = block[:CYCLE, DECOY + 1]
    p[decoy, decoy] = p[goal, goal] = 1.0
    target = np.zeros(size, dtype=bool)
    target[decoy] = True
    return sp.csr_matrix(p), target


def _exact_ladder(matrix: sp.csr_matrix, rungs: int, goal: bool = False) -> Fraction:
    """Pr(decoy) (or Pr(goal)) from state 0 of the ladder: the last copy first, then back to
    the first. The rows' doubles need not sum to 1 exactly, so neither is 1 minus the other."""
    p = matrix.toarray()
    decoy = rungs * CYCLE + goal
    after: list[Fraction] = [Fraction(0)] * CYCLE  # values of the next copy's states
    for k in reversed(range(rungs)):
        base = k * CYCLE
        block = p[base : base + CYCLE, base : base + CYCLE + CYCLE]
        rhs = [
            Fraction(float(p[base + i, decoy]))
            + (
                sum(
                    (Fraction(float(block[i, CYCLE + j])) * after[j] for j in range(CYCLE)),
                    Fraction(0),
                )
                if k < rungs - 1
                else Fraction(0)
            )
            for i in range(CYCLE)
        ]
        after = _exact(np.pad(block[:, :CYCLE], ((0, 2), (0, 2))), rhs)
    return after[0]


@pytest.mark.parametrize("route", ["dense", "lu", "components"])
def test_refined_value_is_within_its_proven_bound(route, monkeypatch):
    """Each direct route proves its answer within EXACT_TOL (<= 1e-9) of the rational value."""
    rungs = 3
    matrix, target = _ladder(rungs)
    if route != "dense":
        monkeypatch.setattr(reachability, "DENSE_MAX_STATES", 0)
    if route == "components":
        monkeypatch.setattr(reachability, "DIRECT_MAX_STATES", 0)
        called = []
        solve_topological = reachability.solve_topological
        monkeypatch.setattr(
            reachability,
            "solve_topological",
            lambda *args: called.append(1) or solve_topological(*args),
        )
    found = reach_probability_bounded(matrix, target, 0)
    exact = _exact_ladder(matrix, rungs)
    assert found.error <= reachability.EXACT_TOL <= tolerance.CERTIFY
    assert _off(found.value, exact) <= found.error
    if route == "components":
        assert called  # the component-wise route answered, and refined
    # without refinement the bound is honest about what double precision gives
    monkeypatch.setattr(reachability, "EXACT_ROUNDS", 0)
    rough = reach_probability_bounded(matrix, target, 0)
    assert rough.error > tolerance.CERTIFY
    assert _off(rough.value, exact) <= rough.error


def test_occupation_outcomes_are_within_their_proven_bound(monkeypatch):
    """The transposed solve (first-entry probabilities) is refined and proven the same way."""
    monkeypatch.setattr(reachability, "DENSE_MAX_STATES", 0)
    matrix, target = _ladder(2)
    terminal = target.copy()
    terminal[-1] = True
    occ = occupation(matrix, terminal, 0)
    exact = _exact_ladder(matrix, 2)
    assert occ.error_bound <= tolerance.CERTIFY
    assert _off(float(occ.entered[target].sum()), exact) <= occ.error_bound
    assert _off(float(occ.entered[-1]), _exact_ladder(matrix, 2, goal=True)) <= occ.error_bound
    # visits: the expected steps from state 0 exceed 10^9, as the chain promises
    assert occ.visits.sum() > 1e9


def _problem_file(tmp_path) -> str:
    """The cycle as a misdirect/v1 problem: state ``c_i`` shows sensor ``o_i``; the controller
    plays ``a`` on o0..o3 and ``b`` on o4, so fooling a sensor switches a state's leaks."""
    transitions = [
        f"    - [c{i}, {action}, {NAMES[j]}, {format(q, 'f')}]"
        for action in "ab"
        for i in range(CYCLE)
        for j, q in _row(i, action).items()
    ]
    observe = ", ".join(f"c{i}: o{i}" for i in range(CYCLE))
    text = "\n".join(
        [
            "format: misdirect/v1",
            "name: a cycle left after 4e9 steps",
            "pomdp:",
            f"  states: [{', '.join(NAMES)}]",
            "  actions: [a, b]",
            "  initial: c0",
            f"  observe: {{{observe}, decoy: g, goal: g}}",
            "  transitions:",
            *transitions,
            "  absorbing: [decoy, goal]",
            "controller:",
            "  nodes: [m]",
            "  initial: m",
            "  rules:",
            '    - {node: "*", obs: o4, action: b, next: m}',
            '    - {node: "*", obs: "*", action: a, next: m}',
            "deception:",
            "  decoy: [decoy]",
            "  budget: 1",
        ]
    )
    path = tmp_path / "cycle.yaml"
    path.write_text(text + "\n")
    return str(path)


def _exact_of(problem, alteration) -> Fraction:
    """Exact value of an alteration, from the table above: which action each state plays."""
    shown = [
        problem.pomdp.observations[alteration[problem.pomdp.observation_of[i]]]
        for i in range(CYCLE)
    ]
    return _exact_decoy(_matrix("".join("b" if o == "o4" else "a" for o in shown)))[0]


def test_evaluate_reports_a_proven_bound(tmp_path):
    path = _problem_file(tmp_path)
    problem = load_problem(path)
    report = evaluate(problem)
    exact = _exact_of(problem, problem.identity())
    assert report.error_bound is not None and report.error_bound <= tolerance.CERTIFY
    assert _off(report.probability, exact) <= report.error_bound
    assert _off(report.outcomes["decoy"], exact) <= report.error_bound
    # the command line shows it
    result = CliRunner().invoke(app, ["evaluate", path, "--json"])
    assert result.exit_code == 0, result.output
    payload = json.loads(result.output)
    assert 0 < payload["error_bound"] <= tolerance.CERTIFY
    assert _off(payload["value"], exact) <= payload["error_bound"]


@pytest.mark.parametrize("method", ["exhaustive", "auto"])
def test_solve_is_optimal_only_when_its_value_is_proven(tmp_path, method, monkeypatch):
    problem = load_problem(_problem_file(tmp_path))
    # every single-sensor alteration, valued exactly: the optimum at budget 1
    candidates = [problem.identity()]
    for o in range(CYCLE):
        for to in range(problem.pomdp.n_observations):
            alpha = problem.identity()
            if to != o and np.isfinite(problem.cost.row(o)[to]):
                alpha[o] = to
                candidates.append(alpha)
    best = max(_exact_of(problem, alpha) for alpha in candidates)
    assert best > _exact_of(problem, problem.identity()) + 0.01  # budget 1 gains something

    result = solve(problem, method=method, budgets=[0, 1])
    final = result.curve[-1]
    assert final.status == Status.OPTIMAL
    assert final.error_bound is not None and final.error_bound <= tolerance.CERTIFY
    assert _off(final.probability, best) <= final.error_bound + 1e-15
    assert final.gap is not None and final.gap >= final.error_bound
    assert result.to_dict()["error_bound"] == final.error_bound

    # without refinement the values cannot be proven that close: never called optimal
    monkeypatch.setattr(reachability, "EXACT_ROUNDS", 0)
    rough = solve(problem, method=method, budgets=[0, 1])
    for point in rough.curve:
        assert point.error_bound is not None and point.error_bound > tolerance.CERTIFY
        assert point.status != Status.OPTIMAL
        assert point.gap is not None and point.gap >= point.error_bound
    assert "ill-conditioned" in rough.curve[-1].notes["not_certified"]


def test_decide_charges_the_value_error():
    assert decide(Status.OPTIMAL, 0.5, 0.5, 5e-10) == Status.OPTIMAL
    assert decide(Status.OPTIMAL, 0.5, 0.5, 2e-9) == Status.FEASIBLE
    assert decide(Status.OPTIMAL, 0.5, 0.5 + 6e-10, 6e-10) == Status.FEASIBLE
    assert decide(Status.OPTIMAL, 0.5, 0.5, float("inf")) == Status.FEASIBLE
    assert decide(Status.TIME_LIMIT, 0.5, 0.5, 2e-9) == Status.TIME_LIMIT


def test_storm_exact_engine_agrees_with_the_rational_reference(tmp_path):
    """Storm, in rational arithmetic on the same doubles (written as exact fractions)."""
    stormpy = pytest.importorskip("stormpy")
    p = _matrix("aaaab")
    lines = ["@type: DTMC", "@parameters", "", "@reward_models", "", "@nr_states"]
    lines += [str(len(NAMES)), "@nr_choices", str(len(NAMES)), "@model"]
    for s in range(len(NAMES)):
        lines += [f"state {s}" + (" init" if s == 0 else "") + (" decoy" if s == DECOY else "")]
        lines += ["\taction 0"]
        for t in np.flatnonzero(p[s]):
            q = Fraction(float(p[s, t]))
            lines.append(f"\t\t{t} : {q.numerator}/{q.denominator}")
    path = tmp_path / "cycle.drn"
    path.write_text("\n".join(lines) + "\n")
    model = stormpy.build_model_from_drn[stormpy.Rational](str(path))
    formula = stormpy.parse_properties('P=? [F "decoy"]')[0]
    result = stormpy.model_checking(model, formula, environment=stormpy.environments.exact())
    storm = Fraction(str(result.get_value(model.initial_states[0])))
    assert storm == _exact_decoy(p)[0]
    target = np.zeros(len(NAMES), dtype=bool)
    target[DECOY] = True
    found = reach_probability_bounded(sp.csr_matrix(p), target, 0)
    assert _off(found.value, storm) <= found.error <= tolerance.CERTIFY


@pytest.mark.parametrize("seed", range(4))
def test_residual_bound_holds_and_is_tight(seed):
    """``residual.residual`` against the same residual in rational arithmetic: the bound holds,
    and exceeds the truth by no more than second-order rounding (rows of 0 to 40 entries)."""
    rng = np.random.default_rng(seed)
    n = 60
    lengths = rng.integers(0, 41, size=n)
    lengths[:3] = [0, 1, 40]
    cols = [rng.choice(n, size=k, replace=False) for k in lengths]
    data = [rng.random(k) * rng.choice([1.0, 1e-9, -1.0], size=k) for k in lengths]
    indptr = np.concatenate(([0], np.cumsum(lengths)))
    rows = sp.csr_matrix((np.concatenate(data), np.concatenate(cols), indptr), shape=(n, n))
    z_hi = rng.random(n) * 10.0 ** rng.integers(-3, 10, size=n)
    z_lo = z_hi * rng.random(n) * 2.0**-53
    own = rng.permutation(n)
    const = rng.random(n)
    r, bound = residual.residual(rows, z_hi, z_lo, own, const)
    for i in range(n):
        z = [Fraction(float(z_hi[j])) + Fraction(float(z_lo[j])) for j in range(n)]
        exact = Fraction(float(const[i])) - z[own[i]]
        for k in range(indptr[i], indptr[i + 1]):
            exact += Fraction(float(rows.data[k])) * z[rows.indices[k]]
        scale = float(abs(Fraction(float(const[i]))) + abs(z[own[i]]))
        scale += sum(
            abs(float(rows.data[k]) * float(z_hi[rows.indices[k]]))
            for k in range(indptr[i], indptr[i + 1])
        )
        assert abs(exact) <= Fraction(float(bound[i]))
        # the bound's own slack: a few units of rounding relative to r, second order to the rest
        slack = 1e-28 * scale + 8 * 2.0**-53 * float(abs(exact)) + 1e-300
        assert float(bound[i]) - float(abs(exact)) <= slack
        assert abs(float(Fraction(float(r[i])) - exact)) <= slack


def _best_within(problem, budget: float) -> Fraction:
    """The exact optimum within ``budget``, by brute force over every alteration of the cycle's
    observations (each state's shown observation decides its action: the table above)."""
    from itertools import product

    n_obs = problem.pomdp.n_observations
    shown_first = problem.pomdp.initial_observation  # never altered
    options = []
    for o in range(CYCLE):
        row = problem.cost.row(o)
        targets = [o] if o == shown_first else range(n_obs)
        options.append([(to, 0.0 if to == o else float(row[to])) for to in targets])
    best = Fraction(0)
    for picks in product(*options):
        if sum(cost for _, cost in picks) <= budget + 1e-12:
            alpha = problem.identity()
            alpha[:CYCLE] = [to for to, _ in picks]
            best = max(best, _exact_of(problem, alpha))
    return best


def test_low_rank_enumeration_on_an_ill_conditioned_chain_claims_exact_values(tmp_path):
    """Low-rank updates on a base chain left after 4e9 steps are 2e-8 off; the enumeration
    values every alteration that may be the best exactly, so the value it claims for its
    answer and the bound it proves are the rational optimum's (within 1e-12 relative)."""
    from misdirect.solvers.incremental import IncrementalSolver

    problem = load_problem(_problem_file(tmp_path))
    budgets = [1.0, 2.0]
    solutions = IncrementalSolver().solve(problem, budgets)
    for budget, solution in zip(budgets, solutions, strict=True):
        best = _best_within(problem, budget)
        assert _off(solution.solver_probability, best) <= 1e-12
        assert solution.upper_bound is not None
        assert solution.upper_bound >= float(best) * (1 - 1e-12)  # a bound, not below it
        assert _off(float(_exact_of(problem, solution.alteration)), best) <= 1e-12


def test_steps_bound_is_proven_and_tight():
    """A state that stays with probability 0.9 leaves after 10 steps on average; with one
    before it (0.5 stay, 0.4 on to it), by hand: t1 = 10 and t0 = (1 + 0.4 t1) / 0.5 = 10.
    A rough solution still proves a bound (above the truth, and looser); a chain that never
    leaves proves none."""
    one = sp.csr_matrix([[0.9]])
    assert 10 <= reachability.steps_bound(one, np.array([10.0])) <= 10 * (1 + 1e-8)
    two = sp.csr_matrix([[0.5, 0.4], [0.0, 0.9]])
    assert 10 <= reachability.steps_bound(two, np.array([10.0, 10.0])) <= 10 * (1 + 1e-8)
    rough = reachability.steps_bound(two, np.array([9.5, 9.9]))  # (I - Q) t >= 0.79
    assert rough == pytest.approx(9.9 / 0.79, rel=1e-6)
    assert reachability.steps_bound(sp.csr_matrix([[1.0]]), np.array([5.0])) == np.inf
