"""The per-state relaxation's bound is proven: a pre-fixed point of the Bellman operator.

Policy iteration's values are rounded solutions of linear systems and may lie below the
relaxation's optimum; the bound the searches prune with may not. Expected values come from
exact rational arithmetic by hand, from the exhaustive solver, or from policy iteration's own
values where the test is that the bound is no looser than they are.
"""

from fractions import Fraction

import numpy as np
import scipy.sparse as sp

from misdirect import problem_from_dict, solve
from misdirect.core.attack import prepare
from misdirect.scenarios import paper_grid, sensor_grid
from misdirect.solvers.engines.per_state import PerStateRelaxation, relaxation_bound
from misdirect.solvers.engines.policy_iteration import MaxReachability

# A random six-state model whose probabilities go down to 1e-10 (a stress search found it):
# policy iteration's relaxation value lay 2.9e-10 below the optimum 1.0 that exhaustive
# search proves at budgets 1 and 2, so a search pruned the optimum away.
STRESS_MOVES = [
    ("s0", "a", "s1", 6.015807389239922e-10),
    ("s0", "a", "s5", 0.9999999993984192),
    ("s0", "b", "s1", 0.10169217851064488),
    ("s0", "b", "s2", 0.8983078214893552),
    ("s1", "a", "s3", 0.9999999999381447),
    ("s1", "a", "s0", 6.185529866087336e-11),
    ("s1", "b", "goal", 1.0072599045684278e-08),
    ("s1", "b", "s5", 0.37741468300420833),
    ("s1", "b", "s1", 0.6225853069231926),
    ("s2", "a", "s2", 0.6934812352602299),
    ("s2", "a", "s0", 0.30651876473977013),
    ("s2", "b", "s0", 1.7889964493759526e-10),
    ("s2", "b", "trap", 0.9999999998211003),
    ("s3", "a", "trap", 0.8256968397954115),
    ("s3", "a", "s2", 0.17430316020458847),
    ("s3", "b", "s3", 0.9999994235289009),
    ("s3", "b", "s5", 5.76471099078546e-07),
    ("s4", "a", "goal", 6.12940941896056e-10),
    ("s4", "a", "s1", 0.9999999993870591),
    ("s4", "b", "s3", 0.9999999594838004),
    ("s4", "b", "s4", 4.0516199617535165e-08),
    ("s5", "a", "s0", 0.9999997948438777),
    ("s5", "a", "trap", 2.0515612231264413e-07),
    ("s5", "b", "s2", 4.374644582459842e-09),
    ("s5", "b", "s0", 0.9999999956253555),
]
STRESS_RULES = [
    ("n0", "o0", "a", "n0"),
    ("n0", "o1", "a", "n1"),
    ("n0", "o2", "b", "n0"),
    ("n0", "o3", "b", "n1"),
    ("n1", "o0", "a", "n1"),
    ("n1", "o1", "a", "n0"),
    ("n1", "o2", "a", "n0"),
    ("n1", "o3", "a", "n0"),
    ("*", "*", "a", "n0"),
]
STRESS_OBSERVE = {
    "s0": "o0",
    "s1": "o3",
    "s2": "o3",
    "s3": "o3",
    "s4": "o1",
    "s5": "o2",
    "trap": "g",
    "goal": "g",
}


def stress_problem():
    states = [f"s{i}" for i in range(6)]
    return problem_from_dict(
        {
            "format": "misdirect/v1",
            "name": "stress",
            "pomdp": {
                "states": [*states, "trap", "goal"],
                "actions": ["a", "b"],
                "initial": "s0",
                "observe": {**STRESS_OBSERVE, "trap": "g", "goal": "g"},
                "transitions": [list(move) for move in STRESS_MOVES],
                "absorbing": ["trap", "goal"],
            },
            "controller": {
                "nodes": ["n0", "n1"],
                "initial": "n0",
                "rules": [
                    {"node": n, "obs": o, "action": a, "next": x} for n, o, a, x in STRESS_RULES
                ],
            },
            "deception": {"decoy": ["trap"], "budget": 2.0, "cost": {"default": 1.0}},
        }
    )


def mdp(rows, n_states, target, value=None):
    """An MDP from ``rows``: (owner, {successor: probability})."""
    owner = np.array([o for o, _ in rows])
    data = [(g, j, p) for g, (_, row) in enumerate(rows) for j, p in row.items()]
    g, j, p = (np.array(x) for x in zip(*data, strict=True))
    matrix = sp.csr_matrix((p.astype(float), (g, j)), shape=(len(rows), n_states))
    mask = np.zeros(n_states, dtype=bool)
    mask[target] = True
    return MaxReachability(owner, matrix, mask, value=value)


def test_stress_bound_is_above_the_exhaustive_optimum():
    problem = stress_problem()
    exact = solve(problem, method="exhaustive", budgets=[0, 1, 2])
    for point in exact.curve:
        assert point.status.value == "optimal"
        bound = relaxation_bound(problem, point.budget)
        assert bound >= point.probability
        # and no looser than certification needs (the chain is absorbed after 4e8 steps)
        assert bound - point.probability <= 1e-12
    assert exact.curve[-1].probability == 1.0  # what the old bound fell short of


# A (0) and B (1) form an end component: A moves to B, or stays half the time; B moves back
# to A, or leaves: to the target T (2) with 0.3, to the sink Z (3) with 0.7. C (4) and D (5)
# form one with no way out. By hand: the optimum is 0.3 (the double) at A and B, 0 at C, D.
END_COMPONENTS = [
    (0, {1: 1.0}),
    (0, {0: 0.5, 1: 0.5}),
    (1, {0: 1.0}),
    (1, {2: 0.3, 3: 0.7}),
    (2, {2: 1.0}),
    (3, {3: 1.0}),
    (4, {5: 1.0}),
    (5, {4: 1.0}),
    (5, {4: 0.5, 5: 0.5}),
]


def test_bound_verifies_on_end_components():
    model = mdp(END_COMPONENTS, 6, [2])
    values, policy = model.optimise(model.first_choices())
    for state in (0, 1):
        bound = model.proven_bound(values, policy, state)
        assert Fraction(bound) >= Fraction(0.3)
        assert bound - 0.3 <= 1e-13  # proven well below the trivial bound, 1
    assert model.proven_bound(values, policy, 4) == 0.0
    assert model.proven_bound(values, policy, 5) == 0.0


def test_bound_with_weights_stays_below_the_largest_weight():
    value = np.array([0, 0, 0.25, 0, 0, 0], dtype=float)
    model = mdp(END_COMPONENTS, 6, [2], value=value)
    values, policy = model.optimise(model.first_choices())
    bound = model.proven_bound(values, policy, 0)
    assert Fraction(bound) >= Fraction(0.3) * Fraction(0.25)
    assert bound - 0.075 <= 1e-13


def test_forbidden_choices_are_left_out():
    # with B's way out forbidden, A and B can only cycle: the optimum is 0
    model = mdp(END_COMPONENTS, 6, [2])
    penalty = np.zeros(len(END_COMPONENTS))
    penalty[3] = -np.inf
    values, policy = model.optimise(model.first_choices(), penalty)
    assert model.proven_bound(values, policy, 0, penalty) == 0.0
    assert model.proven_bound(values, policy, 0) >= 0.3  # allowed again: no proof of 0


# s0 (0) moves to s1 (1) or the sink (3) half and half; s1 to the target (2) or back to s0.
# By hand: v1 = 1/2 + v0/2, v0 = v1/2, so v0 = 1/3 and v1 = 2/3.
HALVES = [(0, {1: 0.5, 3: 0.5}), (1, {2: 0.5, 0: 0.5}), (2, {2: 1.0}), (3, {3: 1.0})]


def test_check_rejects_values_below_the_optimum():
    model = mdp(HALVES, 4, [2])
    optimum = np.array([1 / 3, 2 / 3, 1.0, 0.0])
    above = optimum + np.array([1e-12, 1e-12, 0.0, 0.0])
    assert model.pre_fixed(above)
    for state in (0, 1):
        below = above.copy()
        below[state] = optimum[state] - 1e-15
        assert not model.pre_fixed(below)
    assert not model.pre_fixed(np.array([0.0, 0.0, 1.0, 0.0]))  # the values of a bad policy


def test_bound_from_values_perturbed_downwards():
    model = mdp(HALVES, 4, [2])
    policy = np.arange(4)
    perturbed = np.array([1 / 3 - 1e-6, 2 / 3 - 1e-6, 1.0, 0.0])
    bound = model.proven_bound(perturbed, policy, 0)
    assert Fraction(bound) >= Fraction(1, 3)
    assert bound <= 1 / 3 + 1e-4  # the offset covers the defect it measured, not more


def test_ill_conditioned_chain_bound_is_above_the_optimum():
    # absorbed after about 10^9 steps: policy iteration's value may be off far beyond 1e-16
    stay, win, lose = 1 - 1e-9, 6e-10, 4e-10
    model = mdp([(0, {0: stay, 1: win, 2: lose}), (1, {1: 1.0}), (2, {2: 1.0})], 3, [1])
    values, policy = model.optimise(model.first_choices())
    optimum = Fraction(win) / (1 - Fraction(stay))  # the least fixed point, exactly
    bound = model.proven_bound(values, policy, 0)
    assert Fraction(bound) >= optimum
    assert bound - float(optimum) <= 1e-12  # in double-double: not 1e9 steps of rounding


def _root(problem):
    instance = prepare(problem, problem.budget)
    relax = PerStateRelaxation(problem, instance.space, instance.chain)
    cap = instance.space.scale.cap(problem.budget)
    allowed = relax.allowed_groups(relax.allowed_options((), cap))
    start = relax.best_groups(relax.live_groups.astype(np.float64))[0]
    bound, values, _ = relax.optimise(allowed, start)
    return bound, float(values[instance.chain.initial])


def test_bound_is_as_tight_as_policy_iteration_on_grids():
    inside = sensor_grid(12, 8, goal="inside", budget=2)  # turns back: end components
    for problem in (paper_grid(5), sensor_grid(16, 12, budget=2), inside):
        bound, value = _root(problem)
        # the proof is of the model, whose rows sum to 1; policy iteration solves the rows as
        # doubles, which on the turn-back grid sum to 1 + 2^-54 inside its end components
        # (0.8 + 0.2), and a run lingering there some 300 steps adds that up to about 2e-14
        # (solved in long double: 0.99973190821938133 where the double-double proof gives
        # 0.99973190821936410, every row it checks holding within its rounding)
        assert bound >= value * (1 - 1e-13)
        assert bound - value <= 1e-9 * value, problem.name
