"""The online attacker: one who sees the true state and the controller's memory and may alter
every reading differently, as it goes.

It is a stronger threat model than the offline alteration the solvers optimise (one function
of the observation, fixed in advance), so its value is an upper bound on theirs; with a budget
paid per altered reading it is a different threat again. Both are MDP optima over the
attacker's choice product, computed with :mod:`misdirect.defence.mdp`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable

import numpy as np

from misdirect.core import tolerance
from misdirect.core.attack import prepare
from misdirect.core.checkpoint import interruptible
from misdirect.core.choice_product import ChoiceProduct
from misdirect.core.model import Problem
from misdirect.defence.mdp import budgeted_mdp, max_reach_bounded
from misdirect.defence.results import OnlineAttack
from misdirect.errors import ProblemError
from misdirect.solvers.deadline import Deadline

MAX_BUDGET_LEVELS = 100_000  # budgeted online MDP: at most this many remaining-budget levels
MAX_BUDGETED_STATES = 20_000_000


def cost_unit(costs: Iterable[float]) -> float | None:
    """The largest unit every cost is a whole multiple of, or None: the step of the costs as
    written (0.1 and 0.25: 0.05; 1e-10: 1e-10, at any scale), else of their float values (a
    power of two); None where neither adds exactly (:class:`misdirect.core.tolerance.CostScale`).
    """
    scale = tolerance.CostScale.of(costs, terms=1)
    return None if scale.kind == "rounded" else float(scale.step)


def online_attack_value(
    problem: Problem, budget: float | None = None, *, deadline: Deadline | None = None
) -> OnlineAttack:
    """Value of the online attacker (docs/defence.md); ``budget``: costs paid per altered
    reading along the run, against ``budget``; None: every allowed target at any cost.
    ``deadline``: checked between the choice product's stages and before every policy
    round; once it has passed, :class:`~misdirect.solvers.deadline.DeadlineExpiredError`
    (a value cut short proves nothing, so there is no partial one).

    The unlimited value bounds the offline optimum at every budget from above (an
    alteration is one of the online attacker's strategies). The budgeted value is a different
    threat (it pays for every altered reading, the offline attacker once per sensor), not a
    bound of the offline optimum either way.
    """
    started = time.perf_counter()
    if budget is not None and not (math.isfinite(budget) and budget >= 0):
        raise ProblemError(f"must be a non-negative number, got {budget}", field="budget")
    check = None if deadline is None else deadline.check
    with interruptible(check):
        chain = prepare(problem, math.inf).chain
    unlimited, unlimited_bound, evaluations = max_reach_bounded(
        chain.group_state,
        chain.transitions,
        chain.target,
        chain.initial,
        blocks=chain.node,
        value=chain.target_value,
        deadline=deadline,
    )
    budgeted = budgeted_bound = unit = None
    mdp_states = chain.n_states
    if budget is not None:
        budgeted, budgeted_bound, unit, b_evaluations, mdp_states = _budgeted_value(
            chain, budget, deadline
        )
        evaluations += b_evaluations
    return OnlineAttack(
        probability=unlimited if budgeted is None else budgeted,
        unlimited_probability=unlimited,
        unlimited_bound=unlimited_bound,
        budget=None if budget is None else float(budget),
        budgeted_probability=budgeted,
        budgeted_bound=budgeted_bound,
        cost_unit=unit,
        product_states=chain.n_states,
        mdp_states=mdp_states,
        policy_evaluations=evaluations,
        time_s=time.perf_counter() - started,
    )


def _budgeted_value(
    chain: ChoiceProduct, budget: float, deadline: Deadline | None = None
) -> tuple[float, float, float, int, int]:
    """The online attacker paying per altered reading within ``budget``: the optimum of the
    MDP whose states carry the remaining budget in whole cost units. Returns ``(value, its
    proven upper bound, unit, policy evaluations, MDP states)``."""
    unit = cost_unit(chain.options.cost)
    if unit is None:
        raise ProblemError(
            "the budgeted online value needs alteration costs that are whole multiples "
            "of a common unit (e.g. 0.5); these are not, so it is not computed",
            field="budget",
        )
    levels = tolerance.whole_units(budget, unit) + 1
    if levels > MAX_BUDGET_LEVELS or levels * chain.n_states > MAX_BUDGETED_STATES:
        raise ProblemError(
            f"budget {budget:g} is {budget / unit:,.6g} cost units of {unit:g}: too many budget "
            f"levels for the budgeted online MDP ({chain.n_states:,} product states each)",
            field="budget",
        )
    owner, matrix, target, initial = budgeted_mdp(chain, _group_units(chain, unit), levels)
    value, bound, evaluations = max_reach_bounded(
        owner,
        matrix,
        target,
        initial,
        value=np.tile(chain.target_value, levels),
        deadline=deadline,
    )
    return value, bound, unit, evaluations, target.size


def _group_units(chain: ChoiceProduct, unit: float) -> np.ndarray:
    """Per group of the choice product, the cost units a state pays to take it."""
    units = np.rint(chain.options.cost / unit).astype(np.int64)
    # cheapest way to make a state take each group: min over the options selecting it
    # (option 0 of every observation, "unaltered", costs 0; groups without options too)
    membership = chain.group_options.tocoo()
    group_units = np.zeros(chain.n_groups, dtype=np.int64)
    has_option = np.zeros(chain.n_groups, dtype=bool)
    has_option[membership.row] = True
    group_units[has_option] = np.iinfo(np.int64).max
    np.minimum.at(group_units, membership.row, units[membership.col])
    return group_units
