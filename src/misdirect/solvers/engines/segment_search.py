"""The segment search: best-first branch-and-bound for one budget, bounded by the segment
relaxation, with the subtrees small enough enumerated exactly and two workers on one heap.

A node fixes some observations to one candidate each (``picks``, by choice index); the rest
are free within the ``remaining`` budget. It branches on the free observation whose layers the
bound's optimal scheduler enters most, and its incumbent rounds that scheduler (per
observation the layer entered most, most-entered first, within the budget).

With ``enumerate_at``, a node with at most that many completions is not bounded but
enumerated exactly (the low-rank enumeration, with a base kept per outer pick). The bound
cannot see the budget, but it does see which sensors are left: on sensor networks a few
sensors carry the value, so a node that leaves a strong sensor out is pruned, and one that
alters it has a budget one smaller, soon small enough to enumerate. A node that would need a
new base solve is bounded first (it may be pruned). Where the bound cannot see the budget
(chains with end components), a larger node is enumerated whole when branching it would only
make tiny enumerations, each paying a subtree's fixed cost; an enumeration cut short by the
deadline still offers the best alteration it valued (the node stays open).

Each node's policy iteration starts from its parent's entry choices (mostly one factorisation
instead of several from scratch). Whenever the incumbent improves, a local search enumerates
its neighbourhoods (:meth:`SegmentSearch.local_search`): good incumbents early make the
search, since the optimum at one budget is often the previous budget's plus one sensor.
"""

from __future__ import annotations

import heapq
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from misdirect.core import tolerance
from misdirect.core.blas import one_blas_thread
from misdirect.solvers.deadline import Deadline, DeadlineExpiredError
from misdirect.solvers.engines.incumbent import Incumbent, IncumbentSearch, Picks
from misdirect.solvers.engines.segment_relaxation import Layer, SegmentRelaxation
from misdirect.solvers.pool import SharedBest
from misdirect.solvers.status import Status

NEIGHBOURHOOD = 50_000  # the local search enumerates a neighbourhood of at most this many
BIG_REGION = 0.25  # an observation owning this share of the live states is branched on first
# where the bounds cannot see the budget, a node with up to this many times enumerate_at
# completions is enumerated when its altered children would have at most this share of it
# each: branching it would enumerate them all, each paying a subtree's fixed cost
BLIND_ENUMERATE = 8
SMALL_SUBTREE = 1 / 16
SHARE_EVERY_S = 0.2  # a search with a shared incumbent reads and raises it at most this often

# an open node handed between processes: picks, remaining budget, bound, bounded (its own),
# its parent's entry choices (where its policy iteration starts: without them a task would
# branch on other observations than one process does, and its tree grows)
Subtree = tuple[dict[int, int], float, float, bool, dict[int, np.ndarray] | None]


@dataclass(order=True)
class _Open:
    """A node on the heap: the largest bound first, then the oldest."""

    priority: float  # minus the node's bound
    token: int
    picks: dict[int, int] = field(compare=False)
    remaining: float = field(compare=False)
    bounded: bool = field(compare=False)  # the bound is the node's own, not its parent's
    # the parent's entry choices
    warm: dict[int, np.ndarray] | None = field(compare=False, default=None)
    completions: int = field(compare=False, default=0)  # counted when taken off the heap
    enumerable: bool = field(compare=False, default=False)  # decided then too

    @property
    def bound(self) -> float:
        return -self.priority


class _SearchOverError(Exception):
    """The search is over; ``status`` says why."""


class SegmentSearch(IncumbentSearch):
    """The search of one budget; ``run`` it, then read ``best_picks``, ``best_value`` and
    ``open_bound()``."""

    def __init__(
        self,
        seg: SegmentRelaxation,
        budget: float,
        seeds: Sequence[Picks | None] = (),
        enumerate_at: int = 0,
        *,
        roots: Sequence[Subtree] | None = None,
        shared: SharedBest | None = None,
    ):
        """``roots``: search these subtrees only (default: the whole tree); ``shared``: the
        best value of every search of this budget, read and raised as this one runs."""
        self.seg, self.budget = seg, budget
        self.shared = shared
        self._shared_at = -np.inf  # when it was last read
        # a node's ``remaining`` is this cap less what it spent: ``cost <= remaining`` is exact
        self.cap = seg.space.scale.cap(budget)
        # a node with at most this many completions is enumerated instead of bounded
        self.enumerate_at = enumerate_at if seg.space.choices else 0
        self.enumerated = 0  # nodes
        self.enumerated_alterations = 0
        self._lock = threading.Condition(threading.RLock())  # the heap and the incumbent
        self.incumbent = Incumbent(
            seg.relax, seg.complete({}), budget, order_ties=True, lock=self._lock
        )
        self._error: BaseException | None = None
        self._in_flight: dict[int, float] = {}  # bound of every node a worker holds
        self._status: Status | None = None  # set when the search is over: why
        self._local_running = False
        self._last_node_s = 0.0  # a node is not started with less time left than the last one
        # neighbourhoods the local search has enumerated
        self.searched: set[tuple[tuple[int, int], ...]] = set()
        self.incumbent.offer_exact(self.incumbent.picks)
        for picks in seeds:
            if picks is not None and seg.relax.cost(picks) <= self.cap:
                self.incumbent.offer_exact(picks)
        self.heap: list[_Open] = []
        self.counter = 0
        self.nodes = 0
        # the bound over the whole tree (or the subtrees given) once each of its first
        # nodes has been bounded: the largest of theirs (a first node split off a large
        # region is one of several)
        self.root_bound: float | None = None
        self._root_bounds: dict[int, float] = {}
        first = self.counter + 1
        if roots is None:
            self._push_roots()
        for fixed, remaining, bound, bounded, warm in roots or ():
            self._push(dict(fixed), remaining, bound, bounded, warm)
        self._root_tokens = set(range(first, self.counter + 1))

    def _push_roots(self) -> None:
        seg, cap = self.seg, self.cap
        big = [i for i in seg.order if seg.region_size[i] >= BIG_REGION * seg.live_total]
        if big:  # branch on the largest region at once: the root with it free is costly, loose
            i = max(big, key=lambda i: seg.region_size[i])
            costs = seg.space.choices[i].costs
            for k in np.flatnonzero(costs <= cap)[::-1].tolist():
                self._push({i: int(k)}, cap - float(costs[k]), np.inf)
        else:
            self._push({}, cap, np.inf)

    def _push(
        self,
        picks: dict[int, int],
        remaining: float,
        bound: float,
        bounded: bool = False,
        warm: dict[int, np.ndarray] | None = None,
    ) -> None:
        """``bounded``: ``bound`` is the node's own (not its parent's); ``warm``: the entry
        choices of its parent's bound, where its policy iteration starts."""
        self.counter += 1
        heapq.heappush(self.heap, _Open(-bound, self.counter, picks, remaining, bounded, warm))

    def local_search(self, deadline: Deadline) -> None:
        """Enumerate the incumbent's neighbourhoods: its altered sensors fixed (what one more
        sensor adds), and all of them but one (swap one); again from a better one."""
        seg = self.seg
        if not self.enumerate_at:
            return
        while True:
            with self._lock:
                if not self.incumbent.improved or self._status is not None:
                    return
                self.incumbent.improved = False
                picks = dict(zip(seg.order, self.best_picks, strict=True))
            outer = {i: picks.get(i, 0) for i in seg.outer}  # one block each
            altered = {i: k for i, k in picks.items() if k and i not in outer}
            for drop in [None, *altered]:
                fixed = {**outer, **{i: k for i, k in altered.items() if i != drop}}
                key = tuple(sorted(fixed.items()))
                remaining = self.cap - seg.relax.cost(seg.complete(fixed))
                if key in self.searched or remaining < 0:
                    continue
                self.searched.add(key)
                if seg.completions(fixed, remaining, NEIGHBOURHOOD) > NEIGHBOURHOOD:
                    continue
                found = seg.enumerate(fixed, self.budget, deadline, self._floor())
                if found is not None and tolerance.better(
                    found[0], self.best_value, rel=tolerance.PRUNE
                ):
                    self.incumbent.offer_exact(found[1])
                if found is None or not found[2] or self._status is not None:
                    return  # out of time, or the search is over

    def _floor(self) -> float | None:
        """What an enumeration must beat to matter: the best value reached within the budget,
        here or by another worker (an enumeration then leaves out what cannot reach it)."""
        with self._lock:
            best = max(self.incumbent.value, self.incumbent.floor)
        return best if best >= 0 else None

    def open_nodes(self) -> list[Subtree]:
        """The nodes still open (none is held by a worker once ``run`` returns)."""
        with self._lock:
            return [(e.picks, e.remaining, e.bound, e.bounded, e.warm) for e in self.heap]

    def _share(self) -> None:
        """Raise the shared best to ours, and prune against it (at most every
        ``SHARE_EVERY_S``: each is a round trip to the scheduler on a cluster)."""
        now = time.monotonic()
        if self.shared is None or now - self._shared_at < SHARE_EVERY_S:
            return
        self._shared_at = now
        self.shared.offer(self.incumbent.value)
        self.incumbent.floor = max(self.incumbent.floor, self.shared.get())

    def open_bound(self) -> float:
        """The proven bound on this budget's optimum so far."""
        with self._lock:
            top = self.heap[0].bound if self.heap else -np.inf
            top = max([top, *self._in_flight.values()])
            return self.incumbent.proven_bound(top)

    def run(
        self,
        deadline: Deadline | None = None,
        tick: Callable[[], None] | None = None,
        max_nodes: int | None = None,
        workers: int = 1,
    ) -> Status:
        """Search until every node is pruned or enumerated (``optimal``: finished), the
        deadline passes (``time_limit``) or ``max_nodes`` were bounded (``feasible``).
        ``workers`` threads take nodes from the one heap: the bounds' factorisations and the
        enumeration's compiled loop release the GIL, so two workers use both cores."""
        deadline = deadline or Deadline()
        self._status = None
        if workers <= 1:
            self._work(deadline, tick, max_nodes)
        else:
            threads = [
                threading.Thread(target=self._work, args=(deadline, tick, max_nodes))
                for _ in range(workers)
            ]
            # one BLAS thread per worker: OpenBLAS's own threads would spin on the cores the
            # workers need
            with one_blas_thread():
                for thread in threads:
                    thread.start()
                for thread in threads:
                    thread.join()
        if self._error is not None:
            raise self._error
        return self._status or Status.OPTIMAL

    def _work(
        self, deadline: Deadline, tick: Callable[[], None] | None, max_nodes: int | None
    ) -> None:
        """One worker: take a task, do it outside the lock, apply its result under it."""
        try:
            while (task := self._next_task(deadline, tick, max_nodes)) is not None:
                kind, entry = task
                try:
                    if kind == "local":
                        self.local_search(deadline)
                    elif kind == "enumerate":
                        assert entry is not None  # only a local search comes without a node
                        self._do_enumerate(entry, deadline)
                    else:
                        assert entry is not None
                        self._do_node(entry, deadline)
                finally:
                    with self._lock:
                        self._in_flight.pop(entry.token if entry else -1, None)
                        if kind == "local":
                            self._local_running = False
                        self._lock.notify_all()
        except BaseException as error:  # re-raised by run, in the caller's thread
            with self._lock:
                self._error = error
                self._status = self._status or Status.UNVERIFIED
                self._lock.notify_all()

    def _next_task(
        self, deadline: Deadline, tick: Callable[[], None] | None, max_nodes: int | None
    ) -> tuple[str, _Open | None] | None:
        """Under the lock: the next node to bound or enumerate (pruned ones are dropped), a
        local search, or None when the search is over (``_status`` then says why)."""
        with self._lock:
            try:
                while True:
                    self._check_over(deadline, max_nodes)
                    self._share()
                    if self.incumbent.improved and self.enumerate_at and not self._local_running:
                        self._local_running = True
                        return "local", None
                    if self.heap:
                        task = self._take(heapq.heappop(self.heap), tick)
                        if task is not None:
                            return task
                        continue
                    if not self._in_flight and not self._local_running:
                        self._over(Status.OPTIMAL)
                    self._lock.wait(0.05)  # another worker's node may branch
            except _SearchOverError:
                return None

    def _check_over(self, deadline: Deadline, max_nodes: int | None) -> None:
        if self._status is not None:
            raise _SearchOverError
        left = deadline.remaining()
        if deadline.expired() or (left is not None and left < self._last_node_s):
            self._over(Status.TIME_LIMIT)
        if max_nodes is not None and self.nodes >= max_nodes:
            self._over(Status.FEASIBLE)

    def _over(self, status: Status) -> None:
        self._status = status
        self._lock.notify_all()
        raise _SearchOverError

    def _take(self, entry: _Open, tick: Callable[[], None] | None) -> tuple[str, _Open] | None:
        """What to do with a node taken off the heap: nothing (pruned), bound or enumerate."""
        if self.incumbent.prune(entry.bound):
            return None
        kind = "node"
        if self.enumerate_at:
            entry.enumerable = self._enumerable(entry)
            # a node needing a new base solve is bounded first (it may be pruned)
            ready = entry.bounded or self.seg.basis_ready(entry.picks)
            if entry.enumerable and ready:
                kind = "enumerate"
        if kind == "node":
            self.nodes += 1
            if tick is not None and self.nodes % 16 == 0:
                tick()
        self._in_flight[entry.token] = entry.bound
        return kind, entry

    def _enumerable(self, entry: _Open) -> bool:
        """Whether to enumerate the node rather than branch: it has at most ``enumerate_at``
        completions, or, where the bounds cannot see the budget (:attr:`SegmentRelaxation.
        budget_blind`: its children would all be enumerated anyway), up to
        ``BLIND_ENUMERATE`` times as many and its altered children would be small
        enumerations, each paying a subtree's fixed cost (its basis updated) for few
        alterations. Sets ``entry.completions``."""
        seg, remaining = self.seg, entry.remaining
        wide = self.enumerate_at * BLIND_ENUMERATE if seg.budget_blind else self.enumerate_at
        free = seg.free_space(entry.picks)
        entry.completions = free.count_within(remaining, wide)
        if entry.completions <= self.enumerate_at:
            return True
        if entry.completions > wide:
            return False
        small = int(self.enumerate_at * SMALL_SUBTREE)
        return free.count_within(remaining - free.cheapest(), small) <= small

    def _do_enumerate(self, entry: _Open, deadline: Deadline) -> None:
        found = self.seg.enumerate(entry.picks, self.budget, deadline, self._floor())
        exact = None
        if found is not None and tolerance.better(found[0], self.best_value, rel=tolerance.PRUNE):
            exact = self.incumbent.value_of(found[1])  # re-evaluated exactly, outside the lock
        with self._lock:
            if found is not None and exact is not None:
                self.incumbent.offer(found[1], exact)  # even the best of a run cut short
            if found is None or not found[2]:  # cut by the deadline: the node stays open
                self._push(entry.picks, entry.remaining, entry.bound, bounded=True)
                self._status = self._status or Status.TIME_LIMIT
                return
            # a best tied with the incumbent is not taken, but it bounds the optimum
            self.incumbent.settle(found[3] if exact is None else max(found[3], exact))
            self.enumerated += 1
            self.enumerated_alterations += entry.completions

    def _do_node(self, entry: _Open, deadline: Deadline) -> None:
        seg = self.seg
        began = time.perf_counter()
        try:
            result, usage, layers, entry_choices = seg.node(
                entry.picks,
                entry.remaining,
                self.best_value + tolerance.slack(self.best_value, rel=tolerance.PRUNE),
                entry.warm,
                known_bound=entry.bound,
                deadline=deadline,
            )
        except DeadlineExpiredError:  # cut inside its bound: open, with its parent's
            with self._lock:
                self._push(entry.picks, entry.remaining, entry.bound, entry.bounded, entry.warm)
                self._status = self._status or Status.TIME_LIMIT
            return
        # both proven: the node's own and the one it was pushed with (its parent's)
        bound = min(float(result.bound), entry.bound, seg.problem.objective.max_value)
        rounded = self._round(entry, usage, layers)
        value = self.incumbent.value_of(rounded)
        with self._lock:
            self._last_node_s = time.perf_counter() - began
            if entry.token in self._root_tokens:
                self._root_bounds[entry.token] = bound
                if len(self._root_bounds) == len(self._root_tokens):
                    self.root_bound = max(self._root_bounds.values())
            self.incumbent.offer(rounded, value)
            if not layers or self.incumbent.prune(bound):
                return
            if entry.enumerable:  # bounded, not pruned: enumerated next
                self._push(entry.picks, entry.remaining, bound, bounded=True)
                return
            self._branch(entry, bound, usage, layers, entry_choices)

    def _round(self, entry: _Open, usage: np.ndarray, layers: list[Layer]) -> Picks:
        """The node's scheduler rounded to an alteration within the budget: per observation
        the layer entered most, most-entered first."""
        if not layers:  # nothing affordable changes anything: the node is one alteration
            return self.seg.complete(entry.picks)
        choices = self.seg.space.choices
        chosen, left = dict(entry.picks), entry.remaining
        for j in np.argsort(-usage, kind="stable"):
            if usage[j] <= 0:
                break
            i, k, _ = layers[j]
            if i in chosen or not choices[i].costs[k] <= left:
                continue
            chosen[i] = k
            left -= float(choices[i].costs[k])
        return self.seg.complete(chosen)

    def _branch(
        self,
        entry: _Open,
        bound: float,
        usage: np.ndarray,
        layers: list[Layer],
        entry_choices: dict[int, np.ndarray] | None,
    ) -> None:
        """Push the children of a node: one per affordable option of the observation to
        branch on, the options its scheduler enters most first."""
        seg, choices = self.seg, self.seg.space.choices
        per_obs: dict[int, float] = {}
        for (i, _, _), u in zip(layers, usage, strict=True):
            per_obs[i] = per_obs.get(i, 0.0) + float(u)
        big = [i for i in per_obs if seg.region_size[i] >= BIG_REGION * seg.live_total]
        # a region covering much of the map (the blank reading) first: its layers make the
        # MDP large and the bound loose; then the observation the scheduler enters most
        branch = max(
            big or per_obs,
            key=lambda i: (seg.region_size[i], per_obs[i]) if big else per_obs[i],
        )
        entered: dict[int, float] = {}
        for (i, k, _), u in zip(layers, usage, strict=True):
            if i == branch:
                entered[k] = entered.get(k, 0.0) + float(u)
        costs = choices[branch].costs
        affordable = [k for k in range(choices[branch].size) if costs[k] <= entry.remaining]
        for k in sorted(affordable, key=lambda k: -entered.get(k, 0.0)):
            child = dict(entry.picks)
            child[branch] = int(k)
            self._push(child, entry.remaining - float(costs[k]), bound, warm=entry_choices)
