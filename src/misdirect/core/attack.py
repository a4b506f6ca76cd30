"""One problem as the attacker sees it, prepared once and shared by every solver.

The attacker's real choices (:mod:`misdirect.core.alterations`), the MDP they span over the
product states (:mod:`misdirect.core.choice_product`), which product states can still reach
a decoy, how many of those each observation owns, and where the chain could cycle: auto
measures these to pick a method, then the method it picks needs them again, and a curve's
fallback stages once more. :func:`prepare` builds them once per problem and budget range
within a :func:`shared_preparation` block (one per ``solve`` call, one per audit); every
solver asks it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from contextvars import ContextVar
from dataclasses import dataclass
from functools import cached_property
from typing import cast

import numpy as np

from misdirect.core.alterations import AlterationSpace, alteration_space, options_bound
from misdirect.core.choice_product import (
    ChoiceProduct,
    build_choice_product,
    check_choice_product_fits,
    distinct_options,
    end_component_states,
)
from misdirect.core.model import Problem
from misdirect.core.tolerance import TIE


@dataclass(eq=False)
class AttackInstance:
    """Everything about ``problem`` that does not depend on one alteration, for budgets up to
    ``budget`` (a larger budget's instance serves every smaller one: solvers filter options by
    the budget they solve for)."""

    problem: Problem
    budget: float
    candidates: AlterationSpace  # the cheapest target of every behaviour class

    @cached_property
    def _distinct(self) -> tuple[AlterationSpace, ChoiceProduct | None, np.ndarray | None]:
        """The space without options that change nothing the value sees
        (:func:`~misdirect.core.choice_product.distinct_options`), and the candidates' MDP and
        live states when they are that space's too."""
        chain = build_choice_product(self.problem, self.candidates)
        live = _live(chain)
        space = distinct_options(chain, self.candidates, live)
        if space is self.candidates:
            return space, chain, live
        return space, None, None

    @property
    def space(self) -> AlterationSpace:
        """The attacker's real choices: per observation, one option per distinct way the
        robot can then move (an option that moves it as another, cheaper one does is left
        out: no alteration taking it is worth more)."""
        return self._distinct[0]

    @property
    def left_out(self) -> int:
        """How many candidate options :attr:`space` leaves out."""
        return _options(self.candidates) - _options(self.space)

    @cached_property
    def chain(self) -> ChoiceProduct:
        """The attacker's MDP over the product states reachable under some alteration."""
        space, chain, _ = self._distinct
        return chain if chain is not None else build_choice_product(self.problem, space)

    @cached_property
    def live(self) -> np.ndarray:
        """Product states outside the decoy from which some alteration can still reach it: the
        only ones whose value is unknown (elsewhere it is the decoy's weight, or 0)."""
        live = self._distinct[2]
        return live if live is not None else _live(self.chain)

    @cached_property
    def live_states_per_observation(self) -> np.ndarray:
        """How many live product states emit each observation: altering it changes their rows,
        and only theirs."""
        emitted = self.problem.pomdp.observation_of[self.chain.world_state[self.live]]
        return np.bincount(emitted, minlength=self.problem.pomdp.n_observations)

    @cached_property
    def cycling(self) -> np.ndarray:
        """Live states in some end component: where an alteration can make the chain cycle
        forever without reaching the decoy (the MILP's witness rows, incremental's refusal)."""
        chain = self.chain
        return end_component_states(chain.group_state, chain.transitions, self.live)


def _options(space: AlterationSpace) -> int:
    return sum(choice.size - 1 for choice in space.choices)


def _live(chain: ChoiceProduct) -> np.ndarray:
    return cast(np.ndarray, chain.can_reach_target() & ~chain.target)


# per problem (by id; the entry keeps the problem alive, so the id stays its own): the
# instances built within the current shared_preparation block, by budget
_Prepared = dict[int, tuple[Problem, dict[float, AttackInstance]]]
_shared: ContextVar[_Prepared | None] = ContextVar("misdirect_prepared_attacks", default=None)


@contextlib.contextmanager
def shared_preparation() -> Iterator[None]:
    """Within this block (of this thread or task), :func:`prepare` builds each problem's
    instance once and every stage reuses it; outside, nothing is kept. Nested blocks share
    the outermost one's instances."""
    if _shared.get() is not None:
        yield
        return
    token = _shared.set({})
    try:
        yield
    finally:
        _shared.reset(token)


def prepare(problem: Problem, budget: float) -> AttackInstance:
    """The prepared instance of ``problem`` for budgets up to ``budget``: one already built
    within this :func:`shared_preparation` block for this or a larger budget, else a new one."""
    shared = _shared.get()
    prepared = {} if shared is None else shared.setdefault(id(problem), (problem, {}))[1]
    fitting = [b for b in prepared if b >= budget - TIE]
    if fitting:
        return prepared[min(fitting)]
    at_budget = problem.with_budget(budget)
    # the choice product grows with the space: refuse what cannot fit before building either
    check_choice_product_fits(at_budget, options_bound(at_budget))
    instance = AttackInstance(problem, float(budget), alteration_space(at_budget))
    prepared[float(budget)] = instance
    return instance
