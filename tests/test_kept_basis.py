"""Relaxations on a kept basis (issue 50): the same proven bounds as the per-state relaxation
solved on the whole chain, for free sets of random problems whose controllers loop and of a
turn-back grid, at nodes with decided sensors; and the proof's offset on the kept basis lets
a bound through only where the rigorous check holds."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from misdirect.core.attack import prepare
from misdirect.core.blas import one_blas_thread
from misdirect.scenarios import random_problem
from misdirect.scenarios.sensor_grid import sensor_grid
from misdirect.solvers.engines.covering import _relaxation
from misdirect.solvers.engines.kept_basis import KeptBasis
from misdirect.solvers.engines.per_state import PerStateRelaxation


def _agree(relax, fixed, undecided, frees, cap) -> int:
    """Asserts each free set's bound on the kept basis equals the whole chain's (both proven;
    two proofs of one optimum differ by their offsets only); returns how many the kept basis
    solved itself (not handed back to the whole chain)."""
    with one_blas_thread():
        basis = KeptBasis(relax, fixed, undecided)
        for free in frees:
            kept = basis.bound(free, cap)
            whole = _relaxation(relax, free, cap, fixed, None)
            assert kept == pytest.approx(whole, rel=1e-7, abs=1e-12), (free, kept, whole)
    return basis.reduced


@pytest.mark.parametrize("seed", range(12))
def test_random_problems_with_loops(seed):
    rng = np.random.default_rng(seed)
    for attempt in range(100):
        problem = random_problem(
            300 * seed + attempt, states=10, actions=3, observations=6, nodes=3, budget=3.0
        )
        instance = prepare(problem, 2.0)
        if len(instance.space.choices) >= 3:
            break
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    n = len(instance.space.choices)
    cap = instance.space.scale.cap(2.0)
    frees = [sorted(rng.choice(n, int(rng.integers(1, n + 1)), replace=False)) for _ in range(4)]
    _agree(relax, {}, range(n), [list(map(int, f)) for f in frees], cap)
    # a node: choice 0 decided (its first alteration), the others undecided
    if instance.space.choices[0].size > 1:
        rest = [list(map(int, f)) for f in frees if 0 not in f] or [[1]]
        _agree(relax, {0: 1}, range(1, n), rest, cap)


def test_a_turn_back_grid_with_decided_sensors():
    """The 12x12 grid with 16 sensors (end components: the robot turns back): free sets of 4
    and 8 sensors, at the root and with two sensors decided (one altered, one not)."""
    problem = sensor_grid(12, 16, goal="inside")
    instance = prepare(problem, 3.0)
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    cap = instance.space.scale.cap(3.0)
    rng = np.random.default_rng(5)
    frees = [list(map(int, rng.choice(16, size, replace=False))) for size in (4, 8, 4, 8)]
    assert _agree(relax, {}, range(16), frees, cap) == 4  # none handed back
    fixed = {0: 1, 1: 0}
    frees = [[i for i in free if i not in fixed] for free in frees]
    assert _agree(relax, fixed, range(2, 16), frees, instance.space.scale.cap(2.0)) == 4


def test_an_offset_only_proposes():
    """The proof only takes an offset the check accepts, and never one below the cost it was
    asked for: an offset solver that proposes negative sums leaves the same bound."""
    problem = sensor_grid(10, 12, goal="inside")
    instance = prepare(problem, 2.0)
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    cap = instance.space.scale.cap(2.0)
    allowed = relax.allowed_groups(relax.allowed_options((), cap))
    penalty = np.where(allowed, 0.0, -np.inf)
    values, policy = relax.mdp.optimise(relax.best_groups(penalty)[0], penalty)
    start = relax.chain.initial
    honest = relax.mdp.proven_bound(values, policy, start, penalty)
    lazy = relax.mdp.proven_bound(
        values, policy, start, penalty, offset=lambda cost: np.full_like(cost, -1.0)
    )
    assert lazy == pytest.approx(honest, rel=1e-9)
    assert lazy >= values[start]


def _union_sets(n_sensors: int, n_groups: int, budget: int) -> list[list[int]]:
    """Every union of ``budget`` of the ``n_groups`` round-robin groups of the sensors."""
    groups = [list(range(j, n_sensors, n_groups)) for j in range(n_groups)]
    return [
        sorted(i for g in chosen for i in groups[g])
        for chosen in itertools.combinations(range(n_groups), budget)
    ]


def test_solve_chain_matches_a_direct_solve():
    """The proof's solves on the kept basis (states of E and O held at 0, the policy off the
    base chain in O) against a sparse LU of ``I - P[F, F]`` on the whole chain."""
    problem = sensor_grid(12, 16, goal="inside")
    instance = prepare(problem, 3.0)
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    cap = instance.space.scale.cap(3.0)
    rng = np.random.default_rng(11)
    transitions = relax.chain.transitions.tocsr()
    checked = 0
    with one_blas_thread():
        for fixed, undecided in (({}, range(16)), ({0: 1, 1: 0}, range(2, 16))):
            basis = KeptBasis(relax, fixed, undecided)
            for free_set in _union_sets(16, 8, 3)[:6]:
                free_set = [i for i in free_set if i not in fixed]
                allowed = relax.allowed_groups(relax.free_options(free_set, cap, fixed))
                penalty = np.where(allowed, 0.0, -np.inf)
                values, policy = relax.mdp.optimise(relax.best_groups(penalty)[0], penalty)
                positive = basis.in_kept & (values > 0) & (values < 1)
                for held_share in (0.0, 0.05, 0.3):
                    free = positive & (rng.random(positive.size) >= held_share)
                    rhs = np.where(free, rng.random(free.size), 0.0)
                    x = basis.solve_chain(policy, free, rhs)
                    assert x is not None
                    inner = np.flatnonzero(free)
                    block = transitions[policy[inner]][:, inner]
                    system = (sp.identity(inner.size) - block).tocsc()
                    expected = spla.spsolve(system, rhs[inner])
                    assert x[inner] == pytest.approx(expected, rel=1e-8, abs=1e-10)
                    assert (x[~free] == 0).all()
                    checked += 1
    assert checked == 36


def test_later_attempts_on_the_kept_basis():
    """Unions of a turn-back grid whose proof's first offset fails (ties: the later attempts
    and the double-double refinement run): proven on the kept basis, the same bound as the
    proof that solves those attempts on the whole chain, and as the relaxation solved on the
    whole chain; and the kept basis took those solves (no whole-chain LU)."""
    problem = sensor_grid(12, 16, goal="inside")
    instance = prepare(problem, 3.0)
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    cap = instance.space.scale.cap(3.0)
    held_solves = []
    later = 0
    with one_blas_thread():
        basis = KeptBasis(relax, {}, range(16))
        kept_solve = basis.solve_chain

        def counted(policy, free, rhs):
            found = kept_solve(policy, free, rhs)
            held_solves.append(found is not None)
            return found

        basis.solve_chain = counted  # type: ignore[method-assign]
        for free in _union_sets(16, 8, 3)[:12]:
            before = len(held_solves)
            kept = basis.bound(free, cap)
            if len(held_solves) > before:
                later += 1
            basis.solve_chain = lambda *args: None  # type: ignore[method-assign]
            on_whole = basis.bound(free, cap)  # the later attempts on the whole chain
            basis.solve_chain = counted  # type: ignore[method-assign]
            whole = _relaxation(relax, free, cap, {}, None)
            assert kept == pytest.approx(on_whole, rel=1e-7), free
            assert kept == pytest.approx(whole, rel=1e-7), free
            assert kept < 1.0
    assert later >= 3  # the later attempts ran ...
    assert all(held_solves)  # ... each solve on the kept basis


def test_a_basis_too_large_to_keep_is_not_built(monkeypatch):
    """The basis keeps dense arrays over the states of O: the base inverse (O x O), the rows
    of O's groups on O and their products with it (groups x O, twice), H (E x O). Counting
    only H let a monitored drone (73,224 states in O) try to allocate 677 GiB. On the 12x12
    grid (O 228 states, E 340, 912 groups: 545,376 numbers, H alone 77,520) a limit between
    the two refuses the basis, and the covering bound then solves without it."""
    from misdirect.solvers.engines import kept_basis

    problem = sensor_grid(12, 16, goal="inside")
    instance = prepare(problem, 2.0)
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    basis = KeptBasis(relax, {}, range(16))
    o, e, g = basis.o_states.size, basis.e_states.size, basis.groups.size
    kept = o * (e + 2 * g + o)
    assert basis.usable and e * o < kept
    monkeypatch.setattr(kept_basis, "MAX_KEPT_ENTRIES", (e * o + kept) // 2)
    assert not KeptBasis(relax, {}, range(16)).usable
    monkeypatch.setattr(kept_basis, "MAX_KEPT_ENTRIES", kept)
    assert KeptBasis(relax, {}, range(16)).usable
