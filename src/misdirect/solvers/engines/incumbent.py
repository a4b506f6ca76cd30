"""The incumbent of a branch-and-bound search and what its pruning has proven, written once.

Both searches (the per-state depth-first one of branch-and-bound and the best-first segment
search) keep the best complete assignment found, value assignments exactly (each once), prune
subtrees whose bound cannot beat it by more than a tie, and report as their proven bound the
largest bound of anything pruned or still open. Values within
:data:`~misdirect.core.tolerance.PRUNE` (relative) count as tied: the cheaper assignment wins, so an
answer never spends more of the budget than it needs.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable

import numpy as np

from misdirect.core import tolerance
from misdirect.solvers.engines.alarm import Verdict
from misdirect.solvers.engines.per_state import PerStateRelaxation

Picks = tuple[int, ...]  # one candidate per observation of ``PerStateRelaxation.order``


class Incumbent:
    """The best picks found so far; thread-safe when given the search's ``lock``.

    ``order_ties``: among tied, equally cheap assignments the smallest picks win, so that a
    search with several workers returns the same answer whichever worker finds it first.
    """

    def __init__(
        self,
        relax: PerStateRelaxation,
        picks: Picks,
        budget: float,
        *,
        order_ties: bool = False,
        lock: threading.RLock | threading.Condition | None = None,
        accept: Callable[[Picks], Verdict] | None = None,
        values: dict[Picks, float] | None = None,
    ):
        """``values``: exact values of complete assignments already computed, shared with the
        searches of the other budgets of a curve (the same relaxation, so the same picks):
        the rounded policies of their nodes come back."""
        self.relax = relax
        self.budget = budget  # offers over it are refused: searches may reach them by rounding
        self.order_ties = order_ties
        self._lock = lock if lock is not None else contextlib.nullcontext()
        self.picks: Picks = picks
        self.value = -1.0  # below every value: the first offer is taken
        self.cost = 0.0
        self.improved = True  # the incumbent changed (by more than a tie) since last asked
        self.pruned = 0
        self.pruned_bound = -np.inf  # largest bound of any pruned subtree
        # a value attained elsewhere (another worker's incumbent): pruning is against the
        # larger of it and ours, so that it stays global when a search is split up
        self.floor = -np.inf
        self._values: dict[Picks, float] = {} if values is None else values
        # max_alarm: only alterations proven feasible are kept; the best value of one whose
        # verdict is undecided stays in the proven bound
        self.accept = accept
        self.undecided = -np.inf

    def value_of(self, picks: Picks) -> float:
        """Exact value of a complete assignment (the chain of its groups, least fixed point),
        computed once per assignment."""
        if picks not in self._values:
            self._values[picks] = self.relax.value_of(picks)
        return self._values[picks]

    def offer(self, picks: Picks, value: float) -> None:
        """Keep ``picks`` if clearly better, or tied within the tolerance and cheaper (and
        only if it fits the budget exactly: a search's float sums may admit a few more)."""
        cost = self.relax.cost(picks)
        scale = self.relax.space.scale
        if not scale.fits_terms(cost, lambda: self.relax.terms(picks), self.budget):
            return
        with self._lock:
            room = tolerance.slack(value, self.value, rel=tolerance.PRUNE)
            better = value > self.value + room
            tied = value >= self.value - room
            cheaper = scale.cheaper(cost, self.cost)
            same_cost = scale.same(cost, self.cost)
            ordered = self.order_ties and same_cost and picks < self.picks
            if (better or (tied and (cheaper or ordered))) and self._feasible(picks, value):
                self.picks, self.value, self.cost = picks, value, cost
                self.improved = self.improved or better

    def _feasible(self, picks: Picks, value: float) -> bool:
        """Under ``max_alarm``: whether ``picks`` is proven feasible (an undecided one's value
        is kept for the bound)."""
        if self.accept is None:
            return True
        verdict = self.accept(picks)
        if verdict == Verdict.UNDECIDED:
            self.undecided = max(self.undecided, value)
        return verdict == Verdict.FEASIBLE

    def offer_exact(self, picks: Picks) -> None:
        self.offer(picks, self.value_of(picks))

    def prune(self, bound: float) -> bool:
        """Whether a subtree of ``bound`` cannot beat the incumbent (then counted as pruned)."""
        with self._lock:
            best = max(self.value, self.floor)
            if bound <= best + tolerance.slack(bound, best, rel=tolerance.PRUNE):
                self.pruned += 1
                self.pruned_bound = max(self.pruned_bound, bound)
                return True
            return False

    def settle(self, best: float) -> None:
        """A subtree solved to the end (enumerated) whose best is worth ``best``: its best is
        kept only if it beats the incumbent by more than a tie, but the optimum may be that
        tie above the incumbent, so the proven bound keeps it."""
        with self._lock:
            self.pruned_bound = max(self.pruned_bound, best)

    def proven_bound(self, open_bound: float) -> float:
        """The search's bound on the optimum: the incumbent, anything pruned, and the largest
        bound still open; never above the objective's largest value."""
        ceiling = self.relax.problem.objective.max_value
        return float(min(max(self.value, self.pruned_bound, open_bound, self.undecided), ceiling))


class IncumbentSearch:
    """A search read through its incumbent: ``best_picks`` and ``best_value``."""

    incumbent: Incumbent

    @property
    def best_picks(self) -> Picks:
        return self.incumbent.picks

    @property
    def best_value(self) -> float:
        return self.incumbent.value
