"""``--method auto``: the fastest exact method for the model's shape, within one deadline.

1. ``incremental`` (one base solve per outer choice, a tiny Woodbury solve per alteration)
   when the chain cannot cycle without reaching the decoy and at most 200,000 alterations
   fit, or up to ``INCREMENTAL_LIMIT`` (12 million) when half the time left covers them at
   ``UPDATE_SECONDS`` each, or with no time limit when that is at most ``UNLIMITED_FIRST``
   (on 2 threads: sensor_grid(40, 64) at budgets 0..3, 1.2 million, in 3.4 s and 0.6 GiB;
   sensor_grid(40, 128) at 0..3, 9.5 million, in 30 s and 2.2 GiB). When they would take
   longer (but under ``ENUMERATION_RESERVE`` of the time left), branch-and-bound (4.) goes
   first, with the time the enumeration leaves (at least ``SEARCH_FIRST`` of it; with no
   limit: ``UNLIMITED_SEARCH`` of the enumeration's time), and the enumeration takes the
   budgets it did not certify. A curve whose top budget is too large has its small budgets
   enumerated first, and the rest searched from their best answer;
2. ``exhaustive`` (one exact evaluation per alteration) when at most ``ENUMERATION_LIMIT``
   (300) fit, or when enumerating them all would take at most ``ENUMERATION_SECONDS`` at the
   measured cost of one evaluation (tiny chains: a few hundred product states evaluate in well
   under a millisecond, so thousands of alterations are quicker to enumerate than to search):
   below that, enumeration beats branch-and-bound's several evaluations per node (measured on
   trap grids n = 9 and 21: 31 alterations 0.09 s against 0.17 s, 436 alterations 2.2 s
   against 1.2 s);
3. the MILP when every relevant observation owns at most ``KNAPSACK_STATES`` live product
   states (knapsack-like): the per-state relaxation then only drops the budget, its bound is
   weak and branch-and-bound degenerates to enumeration, while the MILP's LP handles the budget
   row (20-item knapsack: 3,126 nodes and 13 s against 0.06 s); a budget the MILP cannot
   certify to 1e-9 goes to branch-and-bound, started from the MILP's answer;
4. ``branch-and-bound`` otherwise (its relaxation is tight where few observations own many
   states, where the MILP's is weak), with the MILP as fallback for any budget on which it hits
   its node limit; on a tiny chain (under ``TINY_CHAIN`` product states) it has no node limit,
   since a node costs microseconds there and the MILP has hung on such chains (88 states).

Every stage runs against what is left of the one deadline (``--time-limit``), so no hand-over
starts without time, and every hand-over is reported to the progress callback. All stages are
exact; every answer records which method certified it and why.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from misdirect.core.attack import AttackInstance, prepare
from misdirect.core.evaluate import decoy_probability
from misdirect.core.model import Problem
from misdirect.solvers.base import (
    CERTIFY_TOLERANCE,
    Deadline,
    ProgressCallback,
    Solution,
    Status,
    check_time_limit,
    report,
)
from misdirect.solvers.branch_and_bound import BranchAndBoundSolver
from misdirect.solvers.exhaustive import ExhaustiveSolver
from misdirect.solvers.incremental import (
    MAX_ALTERATIONS,
    IncrementalSolver,
    NotApplicableError,
)
from misdirect.solvers.milp.solver import MilpSolver

ENUMERATION_LIMIT = 300  # alterations within the budget for plain enumeration
ENUMERATION_SECONDS = 2.0  # ... or as many as one-by-one evaluation gets through in this time
INCREMENTAL_SURE = 200_000  # ... and for enumeration with low-rank updates, always
INCREMENTAL_LIMIT = MAX_ALTERATIONS  # ... and up to this many when the time left allows it:
UPDATE_SECONDS = 5e-6  # at about this much each (sensor networks, 2 threads: 2.8-3.1 us)
ENUMERATION_FIRST = 0.5  # enumerate first when this share of the time left covers it; else
ENUMERATION_RESERVE = 0.9  # search first, keeping this share for enumerating what is left
SEARCH_FIRST = 0.25  # ... but giving the search at least this share (H2 at --time-limit 60:
# its segment search certifies budget 3 in 8 s, the enumeration needs 30 s)
UNLIMITED_FIRST = 10.0  # with no time limit: enumerate first what takes at most this long,
UNLIMITED_SEARCH = 0.2  # else search first for this share of the enumeration's time
KNAPSACK_STATES = 2  # observations owning at most this many live states: knapsack-like
NODE_LIMIT = 5_000  # branch-and-bound nodes per budget before the MILP takes over
TINY_CHAIN = 1_000  # product states below which branch-and-bound keeps going (no MILP)


class AutoSolver:
    name = "auto"
    curve_is_free = False

    def __init__(
        self,
        enumeration_limit: int = ENUMERATION_LIMIT,
        node_limit: int = NODE_LIMIT,
        time_limit: float | None = None,
        **milp_options: Any,
    ):
        check_time_limit(time_limit)
        self.enumeration_limit = enumeration_limit
        self.time_limit = time_limit
        self.milp = MilpSolver(**milp_options)  # validates the options up front
        self.threads = milp_options.get("threads")  # the enumerations honour --threads too
        self.branch_and_bound = BranchAndBoundSolver(max_nodes=node_limit, threads=self.threads)

    def solve(
        self,
        problem: Problem,
        budgets: Sequence[float],
        *,
        progress: ProgressCallback | None = None,
        deadline: Deadline | None = None,
        seeds: Sequence | None = None,
    ) -> list[Solution]:
        """``seeds`` (one alteration per budget, optional) start branch-and-bound."""
        deadline = deadline or Deadline(self.time_limit)
        top = max(budgets)
        instance = prepare(problem, top)
        space = instance.space
        count = space.count_within(top, INCREMENTAL_LIMIT)
        reason = (
            f"{count:,} alterations fit the budget"
            if count <= INCREMENTAL_LIMIT
            else f"more than {INCREMENTAL_LIMIT:,} alterations fit the budget"
        )

        def enumerable(n: int) -> bool:
            left = deadline.remaining()
            first = UNLIMITED_FIRST if left is None else ENUMERATION_FIRST * left
            return n <= INCREMENTAL_SURE or (n <= INCREMENTAL_LIMIT and n * UPDATE_SECONDS <= first)

        if not enumerable(count) and len(budgets) > 1:
            # the smaller budgets of a curve may still be enumerable: prove those first, and
            # start the search for the larger ones from their best answer
            ordered = sorted(budgets)
            small = [b for b in ordered if enumerable(space.count_within(b, INCREMENTAL_LIMIT))]
            if small:
                first = self._enumerated(problem, small, progress, deadline)
                if first is not None:
                    note = f"auto: budgets up to {small[-1]:g} enumerated, the rest searched"
                    report(progress, 0, 0, note=note)
                    rest = [b for b in ordered if b not in small]
                    later = self.solve(
                        problem,
                        rest,
                        progress=progress,
                        deadline=deadline,
                        seeds=[first[-1].alteration] * len(rest),
                    )
                    found = dict(zip(small, _label(first, "incremental", reason), strict=True))
                    found.update(zip(rest, later, strict=True))
                    return [found[b] for b in budgets]
        if enumerable(count):
            solutions = self._enumerated(problem, budgets, progress, deadline)
            if solutions is not None:
                return _label(solutions, "incremental", reason)
            reason += "; no low-rank updates: the chain can cycle without reaching the decoy"
        if count <= self.enumeration_limit or (
            count <= INCREMENTAL_LIMIT and count * _evaluation_time(problem) <= ENUMERATION_SECONDS
        ):
            if count > self.enumeration_limit:
                reason += (
                    f"; one evaluation is quick enough to try all within {ENUMERATION_SECONDS:g} s"
                )
            solutions = ExhaustiveSolver().solve(
                problem, budgets, progress=progress, deadline=deadline
            )
            return _label(solutions, "exhaustive", reason)
        largest, product_states = _largest_observation(instance)
        if largest <= KNAPSACK_STATES:
            reason += (
                f"; knapsack-like (each observation owns at most {largest} live product "
                "states), so the MILP"
            )
            report(progress, 0, len(budgets), stage="milp", note=f"auto: {reason}")
            solutions = _label(
                self.milp.solve(problem, budgets, progress=progress, deadline=deadline),
                "milp",
                reason,
            )
            return self._finish_with(
                self._branch_and_bound_after,
                problem,
                budgets,
                solutions,
                progress,
                deadline,
                why=f"{reason}; the MILP did not certify it, so branch-and-bound from its answer",
            )
        reason += f"; the largest observation owns {largest:,} live product states"
        search = self.branch_and_bound
        if product_states < TINY_CHAIN:
            # a node costs microseconds here, while the MILP's start-up alone costs more
            reason += f"; a tiny chain ({product_states:,} product states): no node limit"
            search = BranchAndBoundSolver(max_nodes=10**9, threads=self.threads)
        search_deadline, search_s = deadline, _search_before_enumerating(count, deadline)
        if search_s is not None and not instance.cycling.any():
            # the enumeration would likely finish, but not soon: the search goes first (it
            # often certifies in seconds) and the enumeration takes what it did not certify
            search_deadline = Deadline(search_s)
            reason += f"; {count:,} alterations kept for enumeration after the search"
        report(progress, 0, len(budgets), stage="branch-and-bound", note=f"auto: {reason}")
        solutions = _label(
            search.solve(
                problem, budgets, progress=progress, deadline=search_deadline, seeds=seeds
            ),
            "branch-and-bound",
            reason,
        )
        if search_deadline is not deadline:
            solutions = self._finish_with(
                self._incremental_after,
                problem,
                budgets,
                solutions,
                progress,
                deadline,
                why=f"{reason}; branch-and-bound did not certify it, so enumeration",
            )
        return self._finish_with(
            self._milp_after,
            problem,
            budgets,
            solutions,
            progress,
            deadline,
            why=f"{reason}; branch-and-bound hit its node limit, so the MILP",
        )

    def _finish_with(self, stage, problem, budgets, solutions, progress, deadline, *, why):
        """Hand every budget that is not certified to ``stage``, if time is left; keep the
        better answer and the tighter bound of the two."""
        unfinished = [j for j, s in enumerate(solutions) if s.status != Status.OPTIMAL]
        if not unfinished:
            return solutions
        if deadline.expired():
            report(progress, 0, 0, note=f"auto: no time left to hand over ({why})")
            return solutions
        report(
            progress,
            0,
            len(unfinished),
            note=f"auto: budgets {', '.join(f'{budgets[j]:g}' for j in unfinished)}: {why}",
        )
        fallback = stage(
            problem,
            [budgets[j] for j in unfinished],
            [solutions[j] for j in unfinished],
            progress,
            deadline,
        )
        for j, second in zip(unfinished, fallback, strict=True):
            solutions[j] = _better(problem, solutions[j], second, why)
        return solutions

    def _enumerated(self, problem, budgets, progress, deadline) -> list[Solution] | None:
        """The enumeration's answers, or None where it does not apply (the chain can cycle)."""
        try:
            return IncrementalSolver(threads=self.threads).solve(
                problem, budgets, progress=progress, deadline=deadline
            )
        except NotApplicableError:
            return None

    def _incremental_after(self, problem, budgets, earlier, progress, deadline):
        solutions = self._enumerated(problem, budgets, progress, deadline)
        return earlier if solutions is None else _label(solutions, "incremental", "")

    def _milp_after(self, problem, budgets, earlier, progress, deadline):
        del earlier  # the MILP warm-starts from its own previous budget
        return _label(
            self.milp.solve(problem, budgets, progress=progress, deadline=deadline), "milp", ""
        )

    def _branch_and_bound_after(self, problem, budgets, earlier, progress, deadline):
        # the deadline is the only limit now
        solver = BranchAndBoundSolver(max_nodes=10**9, threads=self.threads)
        seeds = [s.alteration for s in earlier]
        return _label(
            solver.solve(problem, budgets, progress=progress, deadline=deadline, seeds=seeds),
            "branch-and-bound",
            "",
        )


def _search_before_enumerating(count: int, deadline: Deadline) -> float | None:
    """Seconds for the search before enumerating ``count`` alterations, or None if they are
    not to be enumerated: within a limit, what the enumeration leaves of the time (if it
    needs under ``ENUMERATION_RESERVE`` of it), at least ``SEARCH_FIRST`` of it; without one,
    ``UNLIMITED_SEARCH`` of the enumeration's time, so a search that certifies at once saves
    it, at worst costing that."""
    if count > INCREMENTAL_LIMIT:
        return None
    needed = count * UPDATE_SECONDS
    left = deadline.remaining()
    if left is None:
        return UNLIMITED_SEARCH * needed
    if needed > ENUMERATION_RESERVE * left:
        return None
    return max(left - needed / ENUMERATION_RESERVE, SEARCH_FIRST * left)


def _better(problem: Problem, first: Solution, second: Solution, why: str) -> Solution:
    """The better answer of two stages for one budget, with the tighter of their bounds."""
    values = [
        decoy_probability(problem, np.asarray(s.alteration, dtype=np.int64))
        for s in (first, second)
    ]
    pick = second if values[1] > values[0] + 1e-12 else first
    value = max(values)
    bounds = [s.upper_bound for s in (first, second) if s.upper_bound is not None]
    bound = max(min(bounds), value) if bounds else None
    proven = bound is not None and bound - value <= CERTIFY_TOLERANCE
    if proven:
        status = Status.OPTIMAL
    elif Status.TIME_LIMIT in (first.status, second.status):  # the proof ran out of time
        status = Status.TIME_LIMIT
    else:
        status = pick.status
    stats = {**pick.stats, "auto_reason": why, "stages": [first.stats, second.stats]}
    # the stage whose bound closed the gap certified it; otherwise the one whose answer it is
    closer = second if second.upper_bound is not None and second.upper_bound == bound else pick
    return Solution(
        budget=pick.budget,
        alteration=pick.alteration,
        solver_probability=value,
        status=status,
        upper_bound=bound,
        stats=stats,
        certified_by=(closer if proven else pick).certified_by or "auto",
    )


def _evaluation_time(problem: Problem) -> float:
    """Seconds for one exact evaluation (of the unaltered chain, once)."""
    began = time.perf_counter()
    decoy_probability(problem, problem.identity())
    return time.perf_counter() - began


def _largest_observation(instance: AttackInstance) -> tuple[int, int]:
    """Live product states owned by the relevant observation that owns the most, and the
    number of states of the choice product."""
    observations = np.array([c.observation for c in instance.space.choices], dtype=np.int64)
    counts = instance.live_states_per_observation
    return int(counts[observations].max(initial=0)), int(instance.chain.n_states)


def _label(solutions: list[Solution], method: str, reason: str) -> list[Solution]:
    return [
        replace(s, stats={**s.stats, "auto_reason": reason}, certified_by=method) for s in solutions
    ]
