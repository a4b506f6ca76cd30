"""The segment search split over a :class:`~misdirect.solvers.pool.TaskPool` (Dask workers).

The coordinator runs the search here until it has a frontier of open subtrees (a few per
worker), then hands each to a task with the incumbent so far. A task searches its subtree
for a slice of time with the same :class:`SegmentSearch`, pruning against a shared best
value (:class:`~misdirect.solvers.pool.SharedBest`, raised by every task, so pruning stays
global), and returns its best alteration, the largest bound it pruned, and the nodes it
left open; the coordinator queues those again, largest bound first.

Why the certificate is the local one: every node is either pruned (its bound, at most the
incumbent of some task, is kept), enumerated or branched, or still open; the proven bound is
the largest of the incumbent, every pruned bound and every open bound, exactly as in one
process, and the answer is re-evaluated exactly by the front door. Only the order of nodes
differs, so the value is the same optimum (within the search's tie tolerance) and the status
``optimal`` exactly when every subtree was finished.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from misdirect.core.attack import prepare
from misdirect.core.model import Problem
from misdirect.solvers.deadline import Deadline
from misdirect.solvers.engines.incumbent import IncumbentSearch, Picks
from misdirect.solvers.engines.per_state import PerStateRelaxation
from misdirect.solvers.engines.segment_relaxation import SegmentRelaxation
from misdirect.solvers.engines.segment_search import SegmentSearch, Subtree
from misdirect.solvers.pool import SharedBest, TaskPool
from misdirect.solvers.status import Status

FRONTIER_PER_WORKER = 4  # open subtrees per worker before the coordinator hands them out
EXPAND_STEP = 8  # nodes the coordinator bounds between looks at its frontier
TASK_SECONDS = 2.0  # a task's slice: what it leaves open comes back to the queue
BATCH = 8  # subtrees a task takes at most
CACHED = 2  # relaxations a worker keeps (one per problem being solved)

_cache: dict[str, SegmentRelaxation] = {}
_cache_lock = threading.Lock()


@dataclass(frozen=True)
class SubtreeResult:
    """What one task hands back: small (picks and numbers), whatever the problem's size."""

    picks: Picks
    value: float
    pruned_bound: float
    open: list[Subtree]
    nodes: int
    enumerated: int
    enumerated_alterations: int
    seconds: float
    where: dict[str, Any]


def _relaxation(problem: Problem, key: str, max_budget: float) -> SegmentRelaxation:
    """The segment relaxation of ``problem``, built once per worker (``key``: the solve)."""
    with _cache_lock:
        if key in _cache:
            return _cache[key]
    instance = prepare(problem, max_budget)
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    seg = SegmentRelaxation(instance, relax, threads=1)
    with _cache_lock:
        while len(_cache) >= CACHED:
            _cache.pop(next(iter(_cache)))
        _cache[key] = seg
    return seg


def search_subtrees(
    problem: Problem,
    key: str,
    max_budget: float,
    budget: float,
    roots: Sequence[Subtree],
    seed: Picks,
    shared: SharedBest,
    seconds: float,
    enumerate_at: int,
) -> SubtreeResult:
    """A task: the segment search of ``roots`` for ``seconds``, from the incumbent ``seed``."""
    import os
    import socket

    began = time.perf_counter()
    seg = _relaxation(problem, key, max_budget)
    search = SegmentSearch(
        seg, budget, seeds=[seed], enumerate_at=enumerate_at, roots=roots, shared=shared
    )
    search.incumbent.floor = shared.get()
    search.run(Deadline(seconds), workers=1)
    return SubtreeResult(
        picks=search.best_picks,
        value=search.best_value,
        pruned_bound=float(search.incumbent.pruned_bound),
        open=search.open_nodes(),
        nodes=search.nodes,
        enumerated=search.enumerated,
        enumerated_alterations=search.enumerated_alterations,
        seconds=time.perf_counter() - began,
        where={"host": socket.gethostname(), "pid": os.getpid()},
    )


class DistributedSegmentSearch(IncumbentSearch):
    """The segment search of one budget over ``pool``; ``run`` it, then read ``best_picks``,
    ``best_value`` and ``open_bound()`` as for :class:`SegmentSearch`."""

    def __init__(
        self,
        seg: SegmentRelaxation,
        budget: float,
        pool: TaskPool,
        *,
        problem: Any,
        key: str | None = None,
        max_budget: float,
        seeds: Sequence[Picks | None] = (),
        enumerate_at: int = 0,
        frontier: int | None = None,
    ):
        """``problem``: the problem (or the pool's handle of it) the tasks rebuild ``seg``
        from, at ``max_budget`` (as ``seg`` was built); ``key`` names that build;
        ``frontier``: open subtrees to reach before handing them out (default: a few per
        worker)."""
        self.frontier = frontier
        self.local = SegmentSearch(seg, budget, seeds, enumerate_at)
        self.incumbent = self.local.incumbent
        self.pool, self.problem, self.budget = pool, problem, budget
        self.key = key or uuid.uuid4().hex
        self.max_budget, self.enumerate_at = max_budget, enumerate_at
        self.queue: list[Subtree] = []
        self._in_flight: dict[Any, float] = {}
        self.tasks: list[SubtreeResult] = []
        self.extra_nodes = self.extra_enumerated = self.extra_alterations = 0

    @property
    def nodes(self) -> int:
        return self.local.nodes + self.extra_nodes

    @property
    def enumerated(self) -> int:
        return self.local.enumerated + self.extra_enumerated

    @property
    def enumerated_alterations(self) -> int:
        return self.local.enumerated_alterations + self.extra_alterations

    @property
    def root_bound(self) -> float | None:
        return self.local.root_bound

    def open_bound(self) -> float:
        bounds = [node[2] for node in self.queue] + list(self._in_flight.values())
        # the coordinator's own heap: open until the frontier is handed out
        local = self.local.open_bound()
        return max(local, self.incumbent.proven_bound(max(bounds, default=-np.inf)))

    def run(
        self,
        deadline: Deadline | None = None,
        tick: Callable[[], None] | None = None,
        max_nodes: int | None = None,
        workers: int = 1,
    ) -> Status:
        """As :meth:`SegmentSearch.run`; ``workers`` is the pool's business here."""
        deadline = deadline or Deadline()
        target = self.frontier or FRONTIER_PER_WORKER * self.pool.size
        while len(self.local.heap) < target:
            limit = self.local.nodes + EXPAND_STEP
            if max_nodes is not None:
                limit = min(limit, max_nodes)
            status = self.local.run(deadline, tick, max_nodes=limit, workers=1)
            if status != Status.FEASIBLE or (max_nodes is not None and limit >= max_nodes):
                return status  # finished (or stopped) before there was anything to hand out
        self.queue = self.local.open_nodes()
        self.local.heap.clear()
        return self._distribute(deadline, tick, max_nodes)

    def _distribute(
        self, deadline: Deadline, tick: Callable[[], None] | None, max_nodes: int | None
    ) -> Status:
        pool, incumbent = self.pool, self.incumbent
        shared = pool.shared_best(incumbent.value)
        status = Status.OPTIMAL
        while self.queue or self._in_flight:
            stop = deadline.expired() or (max_nodes is not None and self.nodes >= max_nodes)
            if stop and status == Status.OPTIMAL:
                status = Status.TIME_LIMIT if deadline.expired() else Status.FEASIBLE
            self.queue.sort(key=lambda node: node[2])  # the largest bound last: popped first
            while not stop and self.queue and len(self._in_flight) < 2 * pool.size:
                batch = self._batch(2 * pool.size - len(self._in_flight))
                if not batch:
                    continue
                left = deadline.remaining()
                seconds = TASK_SECONDS if left is None else max(min(TASK_SECONDS, left), 0.05)
                ticket = pool.submit(
                    search_subtrees,
                    self.problem,
                    self.key,
                    self.max_budget,
                    self.budget,
                    batch,
                    incumbent.picks,
                    shared,
                    seconds,
                    self.enumerate_at,
                )
                self._in_flight[ticket] = batch[0][2]  # the largest bound of the batch
            if not self._in_flight:
                if stop:
                    break
                continue
            ticket, result, error = pool.next_done()
            self._in_flight.pop(ticket)
            if error is not None:
                raise error
            self._take(result, shared)
            if tick is not None:
                tick()
        return status

    def _batch(self, slots: int) -> list[Subtree]:
        """The next task's subtrees, largest bound first (pruned ones are dropped): the
        queue shared out over the ``slots`` free, at most :data:`BATCH` each. A subtree is
        often pruned within a few nodes, and a task costs a round trip and a search's set-up,
        so one subtree a task left each worker idle for much of its time."""
        size = min(BATCH, max(1, -(-len(self.queue) // max(slots, 1))))
        batch: list[Subtree] = []
        while self.queue and len(batch) < size:
            node = self.queue.pop()
            if not self.incumbent.prune(node[2]):
                batch.append(node)
        return batch

    def _take(self, result: SubtreeResult, shared: SharedBest) -> None:
        incumbent = self.incumbent
        self.tasks.append(result)
        incumbent.offer(result.picks, result.value)
        shared.offer(incumbent.value)
        incumbent.pruned_bound = max(incumbent.pruned_bound, result.pruned_bound)
        self.queue.extend(result.open)
        self.extra_nodes += result.nodes
        self.extra_enumerated += result.enumerated
        self.extra_alterations += result.enumerated_alterations
