"""The proof on the MDP with its maximal end components collapsed (issue 50): sound, and tight
where policy iteration converged.

The oracle is the definition: maximal reachability is attained by a memoryless deterministic
policy, so the optimum is the best of all of them, each valued as the least fixed point by a
dense solve on the states that reach the target under it (the others are 0).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.sparse as sp

from misdirect.solvers.engines.end_components import collapsed_bound, maximal_end_components
from misdirect.solvers.engines.policy_iteration import MaxReachability


def random_mdp(seed: int, n: int = 7, choices: int = 2):
    """States 0..n-1, then a target (n) and a sink (n+1), both absorbing; every state has
    ``choices`` choices, some of them self-loops or cycles among a few states (end
    components), some leaving to the target or the sink."""
    rng = np.random.default_rng(seed)
    owner, rows = [], []
    for s in range(n):
        for _ in range(choices):
            row = np.zeros(n + 2)
            kind = rng.random()
            if kind < 0.3:  # stay among a few nearby states: an end component, or part of one
                for t in rng.choice(n, size=2, replace=False):
                    row[t] += rng.integers(1, 4)
            else:
                for t in rng.choice(n + 2, size=3, replace=False):
                    row[t] += rng.integers(1, 4)
            owner.append(s)
            rows.append(row / row.sum())
    for s in (n, n + 1):  # absorbing
        row = np.zeros(n + 2)
        row[s] = 1.0
        owner.append(s)
        rows.append(row)
    target = np.zeros(n + 2, dtype=bool)
    target[n] = True
    return np.array(owner), sp.csr_matrix(np.array(rows)), target


def optimum(owner, matrix, target) -> np.ndarray:
    """The best value per state over every memoryless deterministic policy."""
    dense = matrix.toarray()
    n = target.size
    per_state = [np.flatnonzero(owner == s) for s in range(n)]
    best = np.zeros(n)
    for policy in itertools.product(*per_state):
        p = dense[list(policy)]
        reach = target.copy()  # states that reach the target under the policy
        while True:
            more = reach | (p[:, reach].sum(axis=1) > 0)
            if (more == reach).all():
                break
            reach = more
        inner = np.flatnonzero(reach & ~target)
        values = target.astype(float)
        if inner.size:
            a = np.eye(inner.size) - p[np.ix_(inner, inner)]
            b = p[np.ix_(inner, np.flatnonzero(target))].sum(axis=1)
            values[inner] = np.linalg.solve(a, b)
        best = np.maximum(best, values)
    return best


@pytest.mark.parametrize("seed", range(30))
def test_collapsed_bound_is_sound_and_tight(seed):
    owner, matrix, target = random_mdp(seed)
    truth = optimum(owner, matrix, target)
    allowed = np.ones(owner.size, dtype=bool)
    fixed = target.astype(float)
    mdp = MaxReachability(owner, matrix, target)
    start = mdp.first_choices()
    _, policy = mdp.optimise(start)
    for state in range(target.size - 2):
        proof = collapsed_bound(owner, matrix, target, fixed, allowed, state, policy)
        bound = proof.bound
        assert bound is not None, (seed, state, proof.why)
        assert bound >= truth[state] - 1e-15, (seed, state, bound, truth[state])
        assert bound <= truth[state] * (1 + 1e-6) + 1e-15, (seed, state, bound, truth[state])


def test_a_cycle_the_direct_check_cannot_prove_is_proven_collapsed():
    """By hand: states a and b each either pass the run to the other (an end component) or
    leave, a to the target with 1/2 (else the sink), b to the target with 1/4. The optimum is
    1/2 at both (walk to a, then leave); every vector constant 1/2 + e on {a, b} is a fixed
    point inside the cycle, so only the collapsed MDP (one state {a, b}, choices 1/2 and 1/4)
    pins it down."""
    # states: a=0, b=1, target=2, sink=3
    owner = np.array([0, 0, 1, 1, 2, 3])
    rows = np.array(
        [
            [0, 1, 0, 0],  # a -> b
            [0, 0, 0.5, 0.5],  # a leaves
            [1, 0, 0, 0],  # b -> a
            [0, 0, 0.25, 0.75],  # b leaves
            [0, 0, 1, 0],
            [0, 0, 0, 1],
        ]
    )
    target = np.array([False, False, True, False])
    matrix = sp.csr_matrix(rows)
    labels, internal = maximal_end_components(
        owner, matrix, np.ones(6, dtype=bool), np.array([True, True, False, False])
    )
    assert labels[0] == labels[1] and labels[2] == -1
    assert internal.tolist() == [True, False, True, False, False, False]
    for state in (0, 1):
        bound = collapsed_bound(
            owner, matrix, target, target.astype(float), internal | True, state
        ).bound
        assert bound == pytest.approx(0.5, rel=1e-12) and bound >= 0.5
    # with a's way out forbidden, the best is b's: 1/4
    allowed = np.array([True, False, True, True, True, True])
    bound = collapsed_bound(owner, matrix, target, target.astype(float), allowed, 0).bound
    assert bound == pytest.approx(0.25, rel=1e-12) and bound >= 0.25


def test_a_collapsed_proof_whose_policy_iteration_does_not_settle_falls_back(monkeypatch):
    """With no improvement allowed on the collapsed MDP (as where its policy iteration cycles
    on rounding-level gains), the proof stops instead of running on: no bound, and the
    reason, which :class:`MaxReachability` reports in ``last_unproven`` (its bound then stays
    above the optimum: the fallback is sound). Without the limit the same proofs hold."""
    from misdirect.solvers.engines import end_components

    monkeypatch.setattr(end_components, "COLLAPSED_ROUNDS", 0)
    stopped = 0
    for seed in range(30):
        owner, matrix, target = random_mdp(seed)
        truth = optimum(owner, matrix, target)
        allowed = np.ones(owner.size, dtype=bool)
        fixed = target.astype(float)
        for state in range(target.size - 2):
            proof = collapsed_bound(owner, matrix, target, fixed, allowed, state)
            if proof.bound is None:
                stopped += 1
                assert "did not settle" in proof.why
            else:
                assert proof.bound >= truth[state] - 1e-15
    assert stopped > 0  # the first rows were not optimal everywhere: some proofs stopped
    # through the MDP's proof, forced past its direct checks into the collapsed proof, warm
    # started from a policy that is not optimal (each MDP's first choices)
    monkeypatch.setattr(MaxReachability, "_proven_double", lambda self, *a, **k: None)
    monkeypatch.setattr(MaxReachability, "_proven_extended", lambda self, *a, **k: None)
    reported = 0
    for seed in range(30):
        owner, matrix, target = random_mdp(seed)
        mdp = MaxReachability(owner, matrix, target)
        values, _ = mdp.optimise(mdp.first_choices())
        bound = mdp.proven_bound(values, mdp.first_choices(), 0)
        assert bound >= min(optimum(owner, matrix, target)[0], 1.0) - 1e-15
        if values[0] < 1 - 1e-6 and bound >= 1.0:
            assert "did not settle" in mdp.last_unproven
            reported += 1
    assert reported > 0
