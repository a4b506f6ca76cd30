"""The segment relaxation's bounds are proven, not policy iteration's rounded values.

Before, a node's bound was the value policy iteration computed in doubles: on models whose
probabilities go down to 1e-12 the root bound lay below the exhaustive optimum (stress seed
31: 1.0978081889e-05 against 1.0978083622e-05; seed 85: 2.8e-5 of it below), so a search
could prune the optimum away and call the rest optimal. Expected values come from the
exhaustive enumeration (each alteration evaluated with a proven error), from exact rational
arithmetic, or from a certified evaluation of a policy of the same MDP.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
import scipy.sparse as sp

from misdirect import solve
from misdirect.core.reachability import reach_probability_bounded
from misdirect.scenarios import sensor_grid
from misdirect.solvers.engines.segment_relaxation import SegmentMdp, segment_relaxation
from misdirect.solvers.engines.transient import STEP_MARGIN, TransientPolicyIteration
from stress_model import stress_model


@pytest.mark.parametrize("seed", [31, 85])
def test_root_bounds_lie_above_the_exhaustive_optimum_where_doubles_round(seed):
    problem = stress_model(seed)
    budgets = [0.0, 1.0, 2.0]
    exact = solve(problem, method="exhaustive", budgets=budgets)
    seg = segment_relaxation(problem, 2.0)
    cap = seg.space.scale.cap
    plain = [seg.node({}, cap(b), -np.inf)[0].bound for b in budgets]
    seg.compute_entries(cap(2.0))
    charged = [seg.node({}, cap(b), -np.inf)[0].bound for b in budgets]
    for point, p, c in zip(exact.curve, plain, charged, strict=True):
        floor = Fraction(point.probability) - Fraction(point.error_bound)
        assert Fraction(p) >= floor, (point.budget, p, point.probability)
        assert Fraction(c) >= floor, (point.budget, c, point.probability)


def _transient(rows, n_states):
    """A transient MDP from ``rows``: (state, reward, {successor: probability})."""
    owner = np.array([s for s, _, _ in rows])
    reward = np.array([r for _, r, _ in rows], dtype=float)
    data = [(g, j, p) for g, (_, _, row) in enumerate(rows) for j, p in row.items()]
    g, j, p = (np.array(x) for x in zip(*data, strict=True))
    matrix = sp.csr_matrix((p.astype(float), (g, j)), shape=(len(rows), n_states))
    return TransientPolicyIteration(owner, matrix, n_states), reward


# State 0: take 0.3 and move to 1 with 0.7 (the rest leaves), or pay 0.1 and stay with 0.9.
# State 1: take 0.3 and come back to 0 with 0.6, or take 0.45 and leave. By hand: staying in
# 0 is worth (-0.1 + 0.9 v0), below v0 for v0 >= 0; leaving 1 at once is worth 0.45, against
# 0.3 + 0.6 v0 with v0 = 0.3 + 0.7 v1: v1 = (0.3 + 0.18) / (1 - 0.42) = 0.48 / 0.58 > 0.45.
ROWS = [
    (0, 0.3, {1: 0.7}),
    (0, -0.1, {0: 0.9}),
    (1, 0.3, {0: 0.6}),
    (1, 0.45, {}),
]
V1 = Fraction(0.3) + Fraction(0.6) * Fraction(0.3)
V1 = V1 / (1 - Fraction(0.6) * Fraction(0.7))  # the rounded constants, exactly
V0 = Fraction(0.3) + Fraction(0.7) * V1


def _potential(mdp):
    potential = mdp.proven_potential()
    assert potential is not None
    # checked in rational arithmetic: W(x) >= STEP_MARGIN + P_a W for every row
    matrix = mdp.matrix.tocsr()
    for g in range(matrix.shape[0]):
        lo, hi = matrix.indptr[g], matrix.indptr[g + 1]
        step = sum(
            (
                Fraction(float(p)) * Fraction(float(potential[j]))
                for p, j in zip(matrix.data[lo:hi], matrix.indices[lo:hi], strict=True)
            ),
            Fraction(0),
        )
        assert Fraction(float(potential[mdp.row_state[g]])) >= Fraction(STEP_MARGIN) + step
    return potential


def test_the_potential_falls_by_a_step_along_every_row():
    mdp, _ = _transient(ROWS, 2)
    potential = _potential(mdp)
    # the longest stay, by hand: in 0, staying (0.9) gives N0 = 1 / (1 - 0.9) = 10, moving
    # to 1 gives N0 = 1.7 / 0.58 < 3; then N1 = 1 + 0.6 N0 = 7. The potential lies above
    # these (a proof) and only a margin of about 2^-30 over them
    assert potential[0] >= 10.0 and potential[1] >= 7.0
    assert potential[0] <= 10.0 * (1 + 1e-6) and potential[1] <= 7.0 * (1 + 1e-6)


def test_the_bound_lies_above_the_optimum_from_values_below_it():
    mdp, reward = _transient(ROWS, 2)
    potential = _potential(mdp)
    values, policy, _, optimal = mdp.optimise(reward)
    assert optimal and policy.tolist() == [0, 2]
    bound = mdp.proven_bound(reward, values, 0, potential)
    assert Fraction(bound) >= V0
    assert bound - float(V0) <= 1e-14
    # values a little low (a rounded solve of an ill-conditioned chain): still above
    low = values - 1e-6
    bound = mdp.proven_bound(reward, low, 0, potential)
    assert Fraction(bound) >= V0
    assert bound <= float(V0) + 1e-3  # raised by its defect along the potential, not more


def test_a_turn_back_grid_root_bound_lies_above_its_own_policy_certified():
    # with end components nothing is charged: the proof is one of reachability
    problem = sensor_grid(8, 4, goal="inside")
    seg = segment_relaxation(problem, 1.0)
    cap = seg.space.scale.cap(1.0)
    layers = seg.layers_of({}, cap)
    mdp = SegmentMdp(
        seg.bound,
        seg.relax.policy_of(seg.complete({})),
        [(seg.space.choices[i].observation, g) for i, _, g in layers],
        [0.0] * len(layers),
    )
    assert mdp.potential is None  # the choice product has end components
    _, policy, _, _ = mdp.solver.optimise(mdp.reward_const)
    reach = mdp._reachability()
    chain = reach.transitions[np.concatenate([policy, mdp.matrix.shape[0] + np.arange(2)])]
    certified = reach_probability_bounded(chain, reach.target, mdp.start, value=reach.value)
    bound = seg.node({}, cap, -np.inf)[0].bound
    assert Fraction(bound) >= Fraction(certified.value) - Fraction(certified.error)
    assert bound <= certified.value + 1e-9


def test_the_potential_is_computed_within_the_deadline():
    """The first node of a search computes the potential (a policy iteration over the whole
    choice product): past its deadline it stops, and the next node computes it again."""
    from misdirect.solvers.deadline import Deadline, DeadlineExpiredError

    seg = segment_relaxation(sensor_grid(12, 6), 2.0)
    with pytest.raises(DeadlineExpiredError):
        seg.bound.potential(Deadline(0.0))
    assert seg.bound.potential() is not None  # not kept as "none": computed again
    cap = seg.space.scale.cap(2.0)
    assert seg.node({}, cap, -np.inf)[0].bound < 1.0


def _slow_start() -> tuple[TransientPolicyIteration, np.ndarray, np.ndarray, Fraction]:
    """Start A (value 1e-4) moves to B (value about 1) with 1e-7 a step, and stays 999 steps
    in 1000: (MDP, reward, potential, A's exact value). By hand: v(B) = 0.0007 / (1 -
    0.9993), v(A) = 1e-7 v(B) / (1 - 0.999)."""
    rows = [
        (0, 0.0, {0: 0.999, 1: 1e-7}),
        (0, 0.0, {0: 0.5}),
        (1, 0.0007, {1: 0.9993}),
        (1, 0.0, {0: 0.3}),
    ]
    mdp, reward = _transient(rows, 2)
    v_b = Fraction(0.0007) / (1 - Fraction(0.9993))
    return mdp, reward, _potential(mdp), Fraction(1e-7) * v_b / (1 - Fraction(0.999))


def test_defects_are_charged_where_runs_meet_them():
    """B's one-ulp defect charged at each of A's thousand steps is 2.6e-13 of A's value;
    collected where runs meet it (A's runs reach B one time in 10^4), much less."""
    mdp, reward, potential, v_a = _slow_start()
    values, policy, lu, optimal = mdp.optimise(reward)
    assert optimal and policy.tolist() == [0, 2]
    charged_everywhere = mdp.proven_bound(reward, values, 0, potential)
    where_met = mdp.proven_bound(reward, values, 0, potential, policy, lu)
    assert Fraction(charged_everywhere) >= v_a
    assert Fraction(where_met) >= v_a
    assert (where_met - float(v_a)) / float(v_a) <= 1e-14
    assert where_met < charged_everywhere


def test_collecting_defects_is_spared_where_it_cannot_decide_a_prune():
    """The collected bound costs a policy iteration; a search only needs it where it could
    prune the node: the first bound above the threshold, the values at or below it."""
    mdp, reward, potential, v_a = _slow_start()
    values, policy, lu, _ = mdp.optimise(reward)
    first = mdp.proven_bound(reward, values, 0, potential)
    collected = mdp.proven_bound(reward, values, 0, potential, policy, lu)
    assert collected < first
    between = (float(values[0]) + collected) / 2  # above the values, below both bounds
    assert values[0] < between < collected
    for prune_at, expected in [
        (float(values[0]) / 2, first),  # the values lie above it: the node stays open
        (np.nextafter(first, np.inf), first),  # pruned with the first bound already
        (collected, collected),  # only the collected bound prunes it
        (between, collected),
    ]:
        bound = mdp.proven_bound(reward, values, 0, potential, policy, lu, prune_at)
        assert bound == expected
        assert Fraction(bound) >= v_a
