"""The Dask side of a :class:`~misdirect.solvers.pool.TaskPool`, and connecting to a cluster.

Dask is imported inside the functions only: ``import misdirect`` (and the CLI) never pays for
it, and a machine without the ``cluster`` extra runs everything locally as before.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import threading
import uuid
from collections.abc import Callable, Hashable, Iterator
from typing import Any

from misdirect.errors import OptionError, ProblemError
from misdirect.solvers.pool import LocalPool, SharedBest, TaskPool

INSTALL = "needs the cluster extra: pip install 'misdirect[cluster]'"


class DaskBest:
    """A :class:`~misdirect.solvers.pool.SharedBest` held by the scheduler (a Dask
    ``Variable``): tasks read it and raise it. Two raises at once may leave the smaller; that
    only weakens pruning, never soundness, since every value offered was attained."""

    def __init__(self, name: str):
        self.name = name

    def _variable(self) -> Any:
        from distributed import Variable

        return Variable(self.name)

    def get(self) -> float:
        return float(self._variable().get(timeout=10))

    def offer(self, value: float) -> None:
        variable = self._variable()
        if value > float(variable.get(timeout=10)):
            variable.set(float(value))


class DaskPool:
    """Tasks on the workers of a Dask ``Client``; results as they complete."""

    def __init__(self, client: Any):
        from distributed import as_completed

        self.client = client
        self._completed = as_completed([], with_results=False)

    @property
    def size(self) -> int:
        return max(1, sum(self.client.nthreads().values()))

    def share(self, value: Any) -> Any:
        return self.client.scatter(value, broadcast=True, hash=False)

    def submit(self, fn: Callable[..., Any], *args: Any) -> Hashable:
        future = self.client.submit(fn, *args, pure=False)
        self._completed.add(future)
        return str(future.key)

    def next_done(self) -> tuple[Hashable, Any, BaseException | None]:
        future = next(self._completed)
        try:
            return str(future.key), future.result(), None
        except Exception as error:  # the task's, or the cluster's (a worker lost for good)
            return str(future.key), None, error

    def pending(self) -> int:
        return int(self._completed.count())

    def shared_best(self, initial: float) -> SharedBest:
        from distributed import Variable

        best = DaskBest(f"misdirect-best-{uuid.uuid4().hex}")
        Variable(best.name, client=self.client).set(float(initial))
        return best


@contextlib.contextmanager
def connect(
    cluster: str | None = None, workers: int | None = None, *, processes: bool = True
) -> Iterator[TaskPool | None]:
    """A pool on the Dask scheduler at ``cluster``, or on a LocalCluster of ``workers``
    processes (one thread each); None when neither is given (the caller runs locally)."""
    if cluster is None and workers is None:
        yield None
        return
    field = "cluster" if cluster is not None else "workers"
    if cluster is not None and workers is not None:
        raise OptionError("give cluster or workers, not both", parameter=field)
    if workers is not None and workers < 1:
        raise OptionError(f"must be at least 1, got {workers}", parameter="workers")
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ProblemError(INSTALL, field=field) from None
    logging.getLogger("distributed").setLevel(logging.ERROR)
    with contextlib.ExitStack() as stack:
        if cluster is not None:
            client = stack.enter_context(_reach(Client, scheduler_address(cluster)))
        else:
            local = stack.enter_context(
                LocalCluster(
                    n_workers=workers,
                    threads_per_worker=1,
                    processes=processes,
                    dashboard_address=":0",
                )
            )
            client = stack.enter_context(Client(local))
        yield DaskPool(client)


CONNECT_TIMEOUT_S = 10.0  # a scheduler that does not answer within this is refused
SCHEMES = ("tcp",)  # tls:// needs certificates, ucx:// a UCX build: neither is configured here


def scheduler_address(address: str) -> str:
    """``address`` as Dask's client takes it (``tcp://host:port``), checked first: a scheme
    misdirect cannot speak or a port outside 1..65535 is refused at once, naming it."""
    scheme, sep, rest = address.partition("://")
    if not sep:
        scheme, rest = "tcp", address
    if scheme not in SCHEMES:
        raise ProblemError(
            f"{address!r}: misdirect connects to Dask schedulers over tcp:// only "
            f"({scheme}:// would need a security or UCX configuration it does not take)",
            field="cluster",
        )
    host, colon, port = rest.rpartition(":")
    if not colon or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ProblemError(
            f"{address!r}: expected tcp://HOST:PORT with a port from 1 to 65535",
            field="cluster",
        )
    return f"tcp://{host}:{int(port)}"


@contextlib.contextmanager
def _reach(client_class: Any, address: str) -> Iterator[Any]:
    """A client of the scheduler at ``address``, or a one-line error within
    :data:`CONNECT_TIMEOUT_S`: Dask's own timeout does not cover a server that accepts and
    never answers (its handshake waits forever), and one that is no scheduler (an HTTP
    server) fails in ways of its own, a frame of some gigabytes among them. The client is
    made in a thread of its own so that the wait can be cut."""
    made: list[Any] = []
    failed: list[BaseException] = []

    def make() -> None:
        try:
            made.append(client_class(address, timeout=f"{CONNECT_TIMEOUT_S:g}s"))
        except BaseException as error:  # anything: reported below as the address's fault
            failed.append(error)

    worker = threading.Thread(target=make, name="misdirect-connect", daemon=True)
    worker.start()
    worker.join(CONNECT_TIMEOUT_S + 2.0)
    if worker.is_alive():
        raise ProblemError(
            f"{address}: no Dask scheduler answered within {CONNECT_TIMEOUT_S:g} s",
            field="cluster",
        )
    if failed or not made:
        error = failed[0] if failed else RuntimeError("no client")
        reason = str(error) or type(error).__name__
        if isinstance(error, MemoryError):
            reason = "it sent something that is not Dask's protocol"
        raise ProblemError(
            f"{address}: cannot reach a Dask scheduler there ({reason})", field="cluster"
        )
    client = made[0]
    try:
        yield client
    finally:
        client.close()


def pool_or_local(pool: TaskPool | None) -> TaskPool:
    return pool if pool is not None else LocalPool()


def where_am_i() -> dict[str, Any]:
    """Where a task runs: host name, process id and, on a Dask worker, its address."""
    address = "local"
    try:
        from distributed import get_worker

        address = str(get_worker().address)
    except (ImportError, ValueError):
        pass
    return {"host": socket.gethostname(), "worker": address, "pid": os.getpid()}
