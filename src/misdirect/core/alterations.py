"""The attacker's real choices: per relevant observation, one candidate per behaviour class.

Two targets on which the controller acts identically (same γ and δ on every node) lead to the
same product chain, so only the cheapest one of each class is worth paying for. This turns the
``|Ω|^|Ω|`` alteration functions into a product of a few choices per observation, and it is the
shared search space of the exhaustive solver and the MILP.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple, cast

import numpy as np

from misdirect.core import tolerance
from misdirect.core.checkpoint import checkpoint
from misdirect.core.memory import check_memory
from misdirect.core.model import Problem
from misdirect.errors import ProblemError

GROW_CHUNK = 8_000_000  # candidate extensions listed at once by altered_within (64 MB each)
READBACK_CHUNK = 1_000_000  # alterations it reads back at once (a check of the deadline each)


@dataclass(frozen=True)
class ObservationChoices:
    """Candidates for one observation; index 0 is always "leave it unaltered" (cost 0)."""

    observation: int
    targets: np.ndarray  # candidate received observations, one per behaviour class
    costs: np.ndarray

    @property
    def size(self) -> int:
        return int(self.targets.size)


class AlteredEntries(NamedTuple):
    """Alterations as lists of altered entries: entry ``e`` of alteration ``alteration[e]``
    takes option ``option[e]`` (≥ 1) of choice ``choice[e]`` (a position in the ``indices``
    enumerated); entries are grouped by alteration, which are numbered from 0 (the unaltered
    one, with no entries) and cost ``costs``. ``parent[a]``: the alteration ``a`` is without
    its last entry (-1 for the unaltered one); the children of a parent are consecutive."""

    alteration: np.ndarray
    choice: np.ndarray
    option: np.ndarray
    costs: np.ndarray
    parent: np.ndarray

    def picks(self, index: int, n_choices: int) -> np.ndarray:
        """The dense choice vector of alteration ``index`` (0: unaltered)."""
        lo, hi = np.searchsorted(self.alteration, [index, index + 1])
        picked = np.zeros(n_choices, dtype=np.int64)
        picked[self.choice[lo:hi]] = self.option[lo:hi]
        return picked

    def picks_of(self, indices: np.ndarray, n_choices: int) -> np.ndarray:
        """The dense choice vectors of the alterations ``indices`` (ascending), one row each."""
        mask = np.isin(self.alteration, indices)
        picked = np.zeros((indices.size, n_choices), dtype=np.int64)
        rows = np.searchsorted(indices, self.alteration[mask])
        picked[rows, self.choice[mask]] = self.option[mask]
        return picked

    def restricted(self, keep: np.ndarray) -> AlteredEntries:
        """The alterations ``keep`` selects, renumbered; each one's parent must be kept too
        (the low-rank updates build every alteration from its parent)."""
        number = np.cumsum(keep) - 1
        entries = keep[self.alteration]
        parent = self.parent[keep]
        return AlteredEntries(
            alteration=number[self.alteration[entries]],
            choice=self.choice[entries],
            option=self.option[entries],
            costs=self.costs[keep],
            parent=np.where(parent >= 0, number[np.maximum(parent, 0)], -1),
        )


def _chunks(counts: np.ndarray, size: int) -> Iterator[slice]:
    """Consecutive slices of ``counts`` whose sums are about ``size`` (at least one item)."""
    ends = np.searchsorted(np.cumsum(counts), np.arange(size, int(counts.sum()) + size, size))
    begin = 0
    for end in np.unique(np.minimum(ends + 1, counts.size)):
        if end > begin:
            yield slice(begin, int(end))
            begin = int(end)


def rank_in_group(counts: np.ndarray) -> np.ndarray:
    """0, 1, …, counts[0]-1, 0, 1, …, counts[1]-1, …: each expanded item's place in its group."""
    return cast(np.ndarray, np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts))


@dataclass(frozen=True)
class AlterationSpace:
    choices: tuple[ObservationChoices, ...]
    # how its costs add up and fit a budget (default: from the choices' own costs)
    given_scale: tolerance.CostScale | None = None

    @cached_property
    def scale(self) -> tolerance.CostScale:
        if self.given_scale is not None:
            return self.given_scale
        costs = [float(c) for choice in self.choices for c in np.asarray(choice.costs).tolist()]
        return tolerance.CostScale.of(costs, len(self.choices))

    @property
    def size(self) -> int:
        """Number of alterations (before the budget) the space contains."""
        return int(np.prod([c.size for c in self.choices], dtype=float))

    def within(
        self,
        budget: float,
        indices: Sequence[int] | None = None,
        limit: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Every choice vector with total cost ≤ ``budget``: (candidate index table, costs).

        Over the choices at ``indices`` (default: all). Grown one observation at a time,
        dropping partial vectors already over the budget; since candidate 0 is free, a
        partial vector always completes, so ``None`` (more than ``limit``) is known early.
        """
        cap = self.scale.cap(budget)
        costs = np.zeros(1)
        steps = []  # per choice: (row of the previous step each vector extends, its option)
        for i in range(len(self.choices)) if indices is None else indices:
            grown = costs[:, None] + np.asarray(self.choices[i].costs, dtype=np.float64)
            keep_row, keep_option = np.nonzero(grown <= cap)
            if limit is not None and keep_row.size > limit:
                return None
            steps.append((keep_row, keep_option))
            costs = grown[keep_row, keep_option]
        # the table is read back from the last step to the first: growing it column by column
        # would copy the whole table once per choice
        table = np.zeros((costs.size, len(steps)), dtype=np.int64)
        row = np.arange(costs.size)
        for j in range(len(steps) - 1, -1, -1):
            keep_row, keep_option = steps[j]
            table[:, j] = keep_option[row]
            row = keep_row[row]
        return table, costs

    def altered_within(
        self,
        budget: float,
        indices: Sequence[int] | None = None,
        limit: int | None = None,
        usable: np.ndarray | None = None,
    ) -> AlteredEntries | None:
        """Every choice vector with total cost ≤ ``budget``, listed by its altered entries only.

        The sparse twin of :meth:`within`: a sensor network's alterations alter a few of
        hundreds of observations, so the dense table is almost all zeros (9.6 million x 128
        int64, 9.8 GB, for three of 128 sensors). ``usable[j, k]`` (optional) drops option
        ``k ≥ 1`` of the ``j``-th choice, e.g. one that changes nothing. Alterations come by
        number of altered entries (0 first), then in lexicographic order; grown one altered
        entry at a time, so ``None`` (more than ``limit``) is known before listing them.
        """
        positions = list(range(len(self.choices))) if indices is None else list(indices)
        cap = self.scale.cap(budget)
        choice, option, cost = [], [], []
        for j, i in enumerate(positions):
            costs = np.asarray(self.choices[i].costs, dtype=np.float64)
            keep = np.flatnonzero(costs[1:] <= cap) + 1
            if usable is not None:
                keep = keep[usable[j, keep]] if usable.shape[1] else keep[:0]
            choice.append(np.full(keep.size, j, dtype=np.int64))
            option.append(keep)
            cost.append(costs[keep])
        cand_choice = np.concatenate([np.zeros(0, dtype=np.int64), *choice])
        cand_option = np.concatenate([np.zeros(0, dtype=np.int64), *option])
        cand_cost = np.concatenate([np.zeros(0), *cost])
        # candidates are sorted by choice: those after the choice of candidate c start here
        after = np.append(np.searchsorted(cand_choice, cand_choice, side="right"), 0)
        cheapest_from = np.append(np.minimum.accumulate(cand_cost[::-1])[::-1], np.inf)
        levels = [(np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64))]  # (parent, cand)
        last, level_cost, costs_out, total = np.full(1, -1), np.zeros(1), [np.zeros(1)], 1
        while last.size:
            first = after[last]  # last = -1 (nothing altered yet): from the first candidate
            # only vectors that can still afford a later candidate grow
            growing = np.flatnonzero(level_cost + cheapest_from[first] <= cap)
            counts = cand_cost.size - first[growing]
            parents, cands = [], []
            for chunk in _chunks(counts, GROW_CHUNK):  # candidates listed a chunk at a time
                checkpoint()  # millions of alterations take seconds: the caller's deadline
                parent = np.repeat(growing[chunk], counts[chunk])
                cand = np.repeat(first[growing[chunk]], counts[chunk]) + rank_in_group(
                    counts[chunk]
                )
                fits = level_cost[parent] + cand_cost[cand] <= cap
                parents.append(parent[fits])
                cands.append(cand[fits])
                total += int(fits.sum())
                if limit is not None and total > limit:
                    return None
            parent = np.concatenate([np.zeros(0, dtype=np.int64), *parents])
            cand = np.concatenate([np.zeros(0, dtype=np.int64), *cands])
            if not cand.size:
                break
            levels.append((parent, cand))
            last, level_cost = cand, level_cost[parent] + cand_cost[cand]
            costs_out.append(level_cost)
        # read back along the parents, into arrays allocated once (ten million alterations
        # are hundreds of MB per copy), a chunk of rows at a time between the caller's checks
        sizes = np.array([level[1].size for level in levels[1:]], dtype=np.int64)
        depths = np.arange(1, len(levels), dtype=np.int64)
        n_entries = int((sizes * depths).sum())
        alteration = np.empty(n_entries, dtype=np.int64)
        entry_choice = np.empty(n_entries, dtype=np.int64)
        entry_option = np.empty(n_entries, dtype=np.int64)
        parents = [np.full(1, -1)]
        offset, parent_offset, position = 1, 0, 0
        for depth in range(1, len(levels)):
            n = levels[depth][1].size
            parents.append(levels[depth][0] + parent_offset)
            parent_offset = offset
            for lo in range(0, n, READBACK_CHUNK):
                checkpoint()
                hi = min(n, lo + READBACK_CHUNK)
                entries = np.empty((hi - lo, depth), dtype=np.int64)
                row = np.arange(lo, hi)
                for d in range(depth, 0, -1):
                    parent, cand = levels[d]
                    entries[:, d - 1] = cand[row]
                    row = parent[row]
                end = position + entries.size
                alteration[position:end] = np.repeat(np.arange(offset + lo, offset + hi), depth)
                entry_choice[position:end] = cand_choice[entries.ravel()]
                entry_option[position:end] = cand_option[entries.ravel()]
                position = end
            offset += n
        return AlteredEntries(
            alteration=alteration,
            choice=entry_choice,
            option=entry_option,
            costs=np.concatenate(costs_out),
            parent=np.concatenate(parents),
        )

    def cheapest(self) -> float:
        """The cost of the cheapest alteration (inf where no choice has one)."""
        costs = [float(np.min(c.costs[1:])) for c in self.choices if len(c.costs) > 1]
        return min(costs, default=float("inf"))

    def count_within(self, budget: float, limit: int) -> int:
        """How many choice vectors cost at most ``budget`` (``limit + 1`` once it is more than
        ``limit``), without listing them: a count per distinct total cost, the polynomial of
        each group of alike choices raised to its size by squaring (a search counts every node
        it takes, under its lock, so it must be cheap). Counts are capped at
        ``limit + 1``: ``min(a·b, cap)`` and ``min(a + b, cap)`` only need capped terms."""
        cap = limit + 1
        scale = self.scale
        top = scale.units_cap(budget)  # costs in units that add up exactly

        def times(a: dict[float, int], b: dict[float, int]) -> dict[float, int]:
            product: dict[float, int] = {}
            for cost_a, count_a in a.items():
                for cost_b, count_b in b.items():
                    key = cost_a + cost_b
                    if key <= top:
                        product[key] = min(product.get(key, 0) + count_a * count_b, cap)
            return product

        alike: dict[tuple[float, ...], int] = {}
        for choice in self.choices:
            costs = tuple(sorted(scale.units(c) for c in np.asarray(choice.costs).tolist()))
            alike[costs] = alike.get(costs, 0) + 1
        total = {0.0: 1}
        for costs, size in alike.items():
            one: dict[float, int] = {}  # one choice of the group: options per cost
            for c in costs:
                if c <= top:
                    one[c] = min(one.get(c, 0) + 1, cap)
            power = {0.0: 1}
            while size:
                if size & 1:
                    power = times(power, one)
                size >>= 1
                if size:
                    one = times(one, one)
            total = times(total, power)
            if not total:
                return 0
        return min(sum(total.values()), cap)

    def alteration(
        self,
        problem: Problem,
        picked: Sequence[int] | np.ndarray,
        indices: Sequence[int] | np.ndarray | None = None,
    ) -> np.ndarray:
        """The alteration that takes candidate ``picked[j]`` for the ``j``-th choice."""
        alpha = problem.identity()
        for i, k in zip(
            range(len(self.choices)) if indices is None else indices, picked, strict=True
        ):
            choice = self.choices[i]
            alpha[choice.observation] = choice.targets[k]
        return alpha


def options_bound(problem: Problem) -> np.ndarray:
    """Per observation, at most how many candidates (itself included) the alteration space
    gives it, read off the cost model without building anything: one per behaviour class
    among the targets its budget may afford (every target when the default cost fits, else
    its affordable overrides), 0 for observations that cannot matter or are protected. Exact
    when the default fits and no override forbids a class's last target."""
    cost, n = problem.cost, problem.pomdp.n_observations
    n_classes = int(problem.controller.behaviour_class.max(initial=-1)) + 1
    bound = np.zeros(n, dtype=np.int64)
    cap = cost.scale.cap(problem.budget)  # one cost fits the budget exactly when <= cap
    default_fits = math.isfinite(cost.default) and cost.default <= cap
    overrides = cost.pairs_by_source
    for o in problem.relevant_observations.tolist():
        if o in cost.protected:
            continue
        if default_fits:
            targets = n
        else:
            _, values = overrides.get(o, (None, np.zeros(0)))
            fits = np.isfinite(values) & (values <= cap)
            targets = 1 + int(np.count_nonzero(fits))
        bound[o] = min(targets, n_classes)
    return bound


# bytes per candidate of the alteration space (targets, costs, and the options' flat copy)
BYTES_PER_OPTION = 40


def alteration_space(problem: Problem) -> AlterationSpace:
    """Cheapest target per behaviour class for every observation that can matter."""
    options = int(options_bound(problem).sum())
    check_memory(
        options * BYTES_PER_OPTION,
        f"the alteration space (up to {options:,} candidate targets: "
        f"{problem.relevant_observations.size:,} observations, one per behaviour class)",
        field="alterations",
    )
    classes = problem.controller.behaviour_class
    choices = []
    for o in problem.relevant_observations:
        o = int(o)
        costs = problem.cost.row(o)
        allowed = np.flatnonzero(
            np.isfinite(costs) & (costs <= problem.cost.scale.cap(problem.budget))
        )
        # cheapest per class; ties go to the lowest index, and o itself (cost 0) wins its class
        order = allowed[np.lexsort((allowed, allowed != o, costs[allowed]))]
        _, first = np.unique(classes[order], return_index=True)
        picked = order[np.sort(first)]
        picked = np.concatenate([[o], picked[picked != o]])
        if picked.size > 1:
            choices.append(ObservationChoices(o, picked, costs[picked]))
    return AlterationSpace(tuple(choices), problem.cost.scale)


def max_alteration_cost(problem: Problem) -> float:
    """Cost of the most expensive complete alteration: for every relevant observation, its
    most expensive finite alteration. Any budget at least this large affords every alteration,
    so it is "no limit" and solvers never need to look beyond it (budgets are clamped to it).

    Read off the cost model's default and overrides, without a dense ``|Ω|`` row per
    observation. A sum past the largest float is refused (:class:`ProblemError`): no budget
    could be compared with it."""
    cost = problem.cost
    n = cost.n_observations
    overrides = cost.pairs_by_source
    mosts = []
    for o in problem.relevant_observations.tolist():
        if o in cost.protected:
            continue
        targets, values = overrides.get(o, (np.zeros(0, dtype=np.int64), np.zeros(0)))
        listed = values[(targets != o)]
        finite = listed[np.isfinite(listed)]
        most = float(finite.max()) if finite.size else 0.0
        uncovered = n - 1 - np.unique(targets[targets != o]).size  # targets at the default
        if uncovered > 0 and math.isfinite(cost.default):
            most = max(most, float(cost.default))
        mosts.append(most)
    try:
        return float(cost.scale.exact(mosts))  # the exact sum: a float sum may fall short of it
    except OverflowError:
        raise ProblemError(
            "the costs of a complete alteration sum to more than the largest number "
            f"({np.finfo(float).max:.3g}); scale them down",
            field="deception.cost",
        ) from None
