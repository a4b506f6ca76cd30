"""Outcomes, expected visits and the certified iterative route against independent solves.

Expected values come from dense linear algebra (``numpy.linalg``) or from SciPy's own sparse
solver on a system the test builds itself, never from misdirect's solvers.
"""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

import misdirect.core.reachability as reachability
from misdirect import evaluate
from misdirect.core.evaluate import decoy_probability
from misdirect.core.product import build_product
from misdirect.core.reachability import (
    lu_would_fill,
    occupation,
    reach_probabilities,
    reach_probability,
    solve_certified,
    solve_chain,
)
from misdirect.scenarios import random_problem
from misdirect.scenarios.drone import drone

ROOT = Path(__file__).parent.parent


def _can_reach(p: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Dense backward closure: states with a path (of length >= 0) into ``target``."""
    reach = target.copy()
    edges = p > 0
    while True:
        grown = reach | (edges & reach[None, :]).any(axis=1)
        if (grown == reach).all():
            return reach
        reach = grown


def _dense_reference(p: np.ndarray, terminal: np.ndarray, initial: int):
    """Visits and first-entry probabilities by one dense inverse (least fixed point)."""
    transient = _can_reach(p, terminal) & ~terminal
    visits, entered = np.zeros(len(p)), np.zeros(len(p))
    if not transient[initial]:
        entered[initial] = 1.0
        return visits, entered, transient
    inner = np.flatnonzero(transient)
    green = np.linalg.inv(np.eye(inner.size) - p[np.ix_(inner, inner)])
    visits[inner] = green[np.searchsorted(inner, initial)]
    entered = visits[inner] @ p[inner]
    entered[inner] = 0.0
    return visits, entered, transient


def _random_chain(seed: int, n: int = 40):
    """A random chain with every case: decoys (absorbing or not), absorbing non-decoys, closed
    cycles that never reach either, self-loops, and states nothing reaches."""
    rng = np.random.default_rng(seed)
    p = np.zeros((n, n))
    for s in range(n):
        targets = rng.choice(n, size=rng.integers(1, 5), replace=False)
        p[s, targets] = rng.integers(1, 10, size=targets.size)
    kinds = rng.permutation(n)
    absorbing, trap, decoy_moving = kinds[:3], kinds[3:6], kinds[6]
    p[absorbing] = 0.0
    p[absorbing, absorbing] = 1.0
    p[trap] = 0.0  # a closed cycle: trap[0] -> trap[1] -> trap[2] -> trap[0]
    p[trap, np.roll(trap, -1)] = 1.0
    p /= p.sum(axis=1, keepdims=True)
    terminal = np.zeros(n, dtype=bool)
    terminal[absorbing] = True
    terminal[decoy_moving] = True  # a decoy the chain can leave: runs end there all the same
    decoy = np.zeros(n, dtype=bool)
    decoy[[absorbing[0], decoy_moving]] = True
    return p, terminal, decoy, int(kinds[7])


@pytest.mark.parametrize("seed", range(25))
def test_occupation_equals_a_dense_solve(seed):
    p, terminal, decoy, initial = _random_chain(seed)
    visits, entered, transient = _dense_reference(p, terminal, initial)
    occ = occupation(sp.csr_matrix(p), terminal, initial)
    assert np.abs(occ.visits - visits).max() < 1e-10
    assert np.abs(occ.entered - entered).max() < 1e-12
    assert (occ.transient == transient).all()
    # The probability of reaching the decoy is the mass that first enters a decoy state.
    value = reach_probability(sp.csr_matrix(p), decoy, initial)
    assert value == pytest.approx(entered[decoy].sum(), abs=1e-12)
    # Every run is absorbed somewhere or trapped: the entries sum to one.
    assert entered.sum() == pytest.approx(1.0, abs=1e-12)
    assert occ.entered[occ.trapped].sum() == pytest.approx(entered[~transient & ~terminal].sum())


@pytest.mark.parametrize("seed", range(8))
def test_certified_route_equals_a_dense_solve_within_its_bound(seed, monkeypatch):
    """The iterative route, forced on small chains, and its proven bounds."""
    p, terminal, decoy, initial = _random_chain(seed, n=60)
    visits, entered, transient = _dense_reference(p, terminal, initial)
    if not transient[initial]:
        return
    inner = np.flatnonzero(transient)
    q = sp.csr_matrix(p[np.ix_(inner, inner)])
    rng = np.random.default_rng(seed)
    b = rng.random(inner.size)
    exact = np.linalg.solve(np.eye(inner.size) - q.toarray(), b)
    forward = solve_certified(q, b)
    assert forward is not None
    assert (np.abs(forward.x - exact) <= forward.state_error() + 1e-15).all()
    assert forward.state_error().max() < 1e-9
    start = np.zeros(inner.size)
    start[np.searchsorted(inner, initial)] = 1.0
    backward = solve_certified(q, start, transpose=True)
    assert backward is not None
    assert (np.abs(backward.x - visits[inner]) <= backward.state_error() + 1e-15).all()

    monkeypatch.setattr(reachability, "DIRECT_MAX_STATES", 0)
    monkeypatch.setattr(reachability, "DENSE_MAX_STATES", 0)
    monkeypatch.setattr(reachability, "ITERATIVE_MIN_STATES", 0)
    monkeypatch.setattr(reachability, "WIDE_LEVEL", 0)
    monkeypatch.setattr(reachability, "_structured", lambda *args: None)
    occ = occupation(sp.csr_matrix(p), terminal, initial)
    assert occ.error_bound is not None and occ.error_bound < 1e-10
    assert np.abs(occ.entered - entered).max() <= occ.error_bound
    assert np.abs(occ.visits - visits).max() < 1e-9
    value = reach_probability(sp.csr_matrix(p), decoy, initial)
    assert value == pytest.approx(entered[decoy].sum(), abs=1e-10)


def test_evaluate_random_models_against_dense(monkeypatch):
    """Outcomes per world state, never absorbed and visits, on random POMDPs with traps."""
    checked = 0
    for seed in range(30):
        problem = random_problem(seed, states=10, nodes=2)
        chain = build_product(problem, problem.identity())
        pomdp = problem.pomdp
        terminal = (problem.decoy | pomdp.absorbing)[chain.world_state]
        visits, entered, transient = _dense_reference(
            chain.matrix.toarray(), terminal, chain.initial
        )
        report = evaluate(problem)
        per_state = np.bincount(
            chain.world_state, weights=np.where(terminal, entered, 0), minlength=pomdp.n_states
        )
        expected = {pomdp.states[s]: per_state[s] for s in np.flatnonzero(per_state > 1e-15)}
        assert report.outcomes == pytest.approx(expected, abs=1e-12)
        assert all(v > 0 for v in report.outcomes.values())  # zeros are left out ...
        every = report.all_outcomes  # ... but kept where asked for
        assert set(every) == {
            pomdp.states[s] for s in np.flatnonzero(problem.decoy | pomdp.absorbing)
        }

        def listed(document: dict) -> dict:
            return {o["state"]: o["probability"] for o in document["outcomes"] if o["state"]}

        assert listed(report.to_dict(all_outcomes=True)) == every
        assert listed(report.to_dict()) == report.outcomes
        trapped = ~transient & ~terminal
        assert report.never_absorbed == pytest.approx(entered[trapped].sum(), abs=1e-12)
        assert report.probability == pytest.approx(
            entered[problem.decoy[chain.world_state]].sum(), abs=1e-12
        )
        cells = np.bincount(chain.world_state, weights=visits, minlength=pomdp.n_states)
        assert np.abs(report.expected_visits - cells).max() < 1e-9
        checked += report.never_absorbed > 0
    assert checked >= 3  # trapped runs really occurred


def _reference_by_scipy(problem):
    """Occupation measure of the product by SciPy's spsolve on a system built here."""
    chain = build_product(problem, problem.identity())
    terminal = (problem.decoy | problem.pomdp.absorbing)[chain.world_state]
    graph = chain.matrix.T.tocsr()
    reach = terminal.copy()
    frontier = np.flatnonzero(terminal)
    while frontier.size:
        nxt = np.unique(graph[frontier].indices)
        nxt = nxt[~reach[nxt]]
        reach[nxt] = True
        frontier = nxt
    inner = np.flatnonzero(reach & ~terminal)
    rows = chain.matrix[inner]
    system = (sp.identity(inner.size) - rows[:, inner]).T.tocsc()
    start = np.zeros(inner.size)
    start[np.searchsorted(inner, chain.initial)] = 1.0
    x = spsolve(system, start)
    entered = np.asarray(rows.T @ x).ravel()
    entered[inner] = 0.0
    visits = np.zeros(chain.n_states)
    visits[inner] = x
    return chain, entered, visits


def test_mid_size_drone_chain_iterative_against_scipy_lu(monkeypatch):
    """About 10^4 product states, one wide component: the certified route (forced at this size)
    against SciPy's sparse LU of the transposed system, the route evaluation used before."""
    problem = drone(6, agents=2, rows=3)
    chain, entered, visits = _reference_by_scipy(problem)
    assert chain.n_states > 10_000
    monkeypatch.setattr(reachability, "ITERATIVE_MIN_STATES", 5_000)
    monkeypatch.setattr(reachability, "WIDE_LEVEL", 200)
    assert lu_would_fill(chain.matrix)
    report = evaluate(problem)
    assert report.error_bound is not None and report.error_bound < 1e-10
    decoy = problem.decoy[chain.world_state]
    assert abs(report.probability - entered[decoy].sum()) <= report.error_bound
    per_state = np.bincount(chain.world_state, weights=entered, minlength=problem.pomdp.n_states)
    for name, value in report.all_outcomes.items():
        assert abs(value - per_state[problem.pomdp.states.index(name)]) <= report.error_bound
    cells = np.bincount(chain.world_state, weights=visits, minlength=problem.pomdp.n_states)
    assert np.abs(report.expected_visits - cells).max() < 1e-9 * max(1.0, cells.max())
    assert decoy_probability(problem, problem.identity()) == pytest.approx(
        entered[decoy].sum(), abs=1e-10
    )
    # Values at every state (what the solvers' policy evaluations use): the forward route.
    lu_calls = []
    real_solve = reachability._solve
    monkeypatch.setattr(
        reachability, "_solve", lambda *args, **kw: lu_calls.append(1) or real_solve(*args, **kw)
    )
    values = reach_probabilities(chain.matrix, decoy, blocks=chain.node)
    assert not lu_calls  # the certified route answered
    assert values[chain.initial] == pytest.approx(entered[decoy].sum(), abs=1e-10)
    assert 0.0 < report.probability < 1.0 and len(report.outcomes) > 3


def test_the_drone_chain_is_wide_and_a_grid_is_not():
    problem = drone(8)
    chain = build_product(problem, problem.identity())
    assert chain.n_states > 20_000 and lu_would_fill(chain.matrix)
    side = 200  # a 2-D random walk: narrow levels, a cheap LU
    walk = sp.diags([np.full(side * side - 1, 0.24), np.full(side * side - side, 0.24)], [1, side])
    assert not lu_would_fill((walk + walk.T).tocsr())


def test_slow_chain_falls_back_to_lu(monkeypatch):
    """A long corridor with a tiny leak: Krylov would need thousands of steps, so the certified
    route gives up early and the LU answers, still equal to a dense solve."""
    n = 400
    q = sp.diags([np.full(n - 1, 0.5), np.full(n - 1, 0.4999)], [1, -1], format="csr")
    b = np.zeros(n)
    b[-1] = 0.5
    monkeypatch.setattr(reachability, "KRYLOV_MAX_ITER", 50)
    assert solve_certified(q, b) is None
    monkeypatch.setattr(reachability, "DIRECT_MAX_STATES", 0)
    monkeypatch.setattr(reachability, "DENSE_MAX_STATES", 0)
    monkeypatch.setattr(reachability, "ITERATIVE_MIN_STATES", 0)
    monkeypatch.setattr(reachability, "WIDE_LEVEL", 0)
    exact = np.linalg.solve(np.eye(n) - q.toarray(), b)
    assert np.abs(solve_chain(q, b) - exact).max() < 1e-12


def test_real_chains_benchmark_quick(tmp_path):
    subprocess.run(
        [
            sys.executable,
            str(ROOT / "bench" / "real_chains.py"),
            "--quick",
            "--repeats",
            "1",
            "--out",
            str(tmp_path),
        ],
        check=True,
        capture_output=True,
    )
    text = (tmp_path / "real_chains.md").read_text()
    assert "drone" in text
    assert (tmp_path / "real_chains.csv").exists() and (tmp_path / "real_chains.json").exists()
