"""Pieces of one computation in forked copies of the process (solvers/engines/forked.py), and
a cover's unions shared among them: the same answers as in one process."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from misdirect.core.attack import prepare
from misdirect.scenarios.sensor_grid import sensor_grid
from misdirect.solvers.deadline import Deadline, DeadlineExpiredError
from misdirect.solvers.engines import covering, forked
from misdirect.solvers.engines.covering import covering_bound, stratified_groups
from misdirect.solvers.engines.forked import Claims, can_fork, forked_call, forked_map
from misdirect.solvers.engines.per_state import PerStateRelaxation

needs_fork = pytest.mark.skipif(not can_fork(), reason="no fork on this platform")


@needs_fork
def test_pieces_run_in_other_processes_and_come_back_in_order():
    touched: list[int] = []

    def work(k: int) -> tuple[int, int]:
        touched.append(k)
        return k * k, os.getpid()

    answers = forked_map(work, 3)
    assert [a for a, _ in answers] == [0, 1, 4]
    pids = [pid for _, pid in answers]
    assert pids[0] == os.getpid() and len(set(pids)) == 3
    assert touched == [0]  # a child's changes to this process's objects do not come back


def test_without_fork_every_piece_runs_here_in_order(monkeypatch):
    monkeypatch.setenv(forked.FORK_ENV, "0")
    touched: list[int] = []
    assert forked_map(lambda k: touched.append(k) or os.getpid(), 3) == [os.getpid()] * 3
    assert touched == [0, 1, 2]


@needs_fork
def test_no_fork_where_the_copies_would_not_fit_the_memory(monkeypatch):
    monkeypatch.setattr(forked, "memory_limit", lambda: (1, "available"))  # one byte
    assert forked_map(lambda k: os.getpid(), 2) == [os.getpid()] * 2
    monkeypatch.setattr(forked, "memory_limit", lambda: (None, "available"))  # unknown
    assert len(set(forked_map(lambda k: os.getpid(), 2))) == 2


@needs_fork
def test_a_childs_exception_is_raised_here_as_itself():
    def work(k: int) -> int:
        if k == 1:
            raise ValueError("piece one is bad")
        return k

    with pytest.raises(ValueError, match="piece one is bad") as caught:
        forked_map(work, 2)
    assert any("forked worker" in note for note in caught.value.__notes__)


@needs_fork
def test_a_child_past_the_deadline_is_killed_and_the_deadline_raised():
    def work(k: int) -> int:
        if k == 1:
            time.sleep(30)
        return k

    began = time.perf_counter()
    with pytest.raises(DeadlineExpiredError):
        forked_map(work, 2, Deadline(0.3))
    assert time.perf_counter() - began < 10  # not the child's 30 s


@needs_fork
def test_one_call_in_a_child_comes_back_or_is_killed_at_the_deadline():
    """forked_call runs a call that cannot watch a deadline (a sparse LU) in a child when
    there is a limit, here when there is none; past the limit the child is killed."""
    assert forked_call(os.getpid, Deadline(30)) != os.getpid()
    assert forked_call(os.getpid, None) == os.getpid()
    assert forked_call(os.getpid, Deadline(None)) == os.getpid()
    began = time.perf_counter()
    with pytest.raises(DeadlineExpiredError):
        forked_call(lambda: time.sleep(30), Deadline(0.3))
    assert time.perf_counter() - began < 10  # not the call's 30 s


@needs_fork
def test_a_cancelled_deadline_stops_the_wait_at_once():
    deadline = Deadline(None)

    def work(k: int) -> int:
        if k == 0:
            deadline.cancel.cancel()  # in this process: the child's copy never hears of it
        else:
            time.sleep(30)
        return k

    with pytest.raises(DeadlineExpiredError):
        forked_map(work, 2, deadline)


@pytest.mark.parametrize("fork", ["1", "0"])
def test_claims_hand_out_every_index_once_across_workers(monkeypatch, fork):
    monkeypatch.setenv(forked.FORK_ENV, fork)
    claims = Claims(200, workers=3)
    taken = forked_map(lambda _: list(claims), 3)
    flat = sorted(i for part in taken for i in part)
    assert flat == list(range(200))


def test_stopped_claims_hand_out_nothing_more():
    claims = Claims(10, workers=1)
    first = []
    for index in claims:
        first.append(index)
        if index == 3:
            claims.stop()
    assert first == [0, 1, 2, 3] and list(claims) == []


@needs_fork
@pytest.mark.parametrize("budget", [1.0, 2.0])
def test_a_cover_shared_among_processes_is_the_cover_in_one(monkeypatch, budget):
    """Same unions, the same bounds (to a rounding) and the same counts of proofs, with the
    unions shared among two forked workers as in one process (a turn-back grid: end
    components, failed proofs)."""
    monkeypatch.setattr(covering, "FORK_FROM", 1)
    problem = sensor_grid(8, 8, goal="inside")
    instance = prepare(problem, budget)
    relax = PerStateRelaxation(problem, instance.space, instance.chain, instance.cycling)
    choices = range(len(instance.space.choices))
    groups = stratified_groups(choices, 6, np.random.default_rng(0).random(len(choices)))
    cap = instance.space.scale.cap(budget)
    found = {}
    proofs = {}
    for workers in (1, 2):
        before = relax.mdp.proofs
        found[workers] = covering_bound(relax, groups, cap, workers=workers)
        proofs[workers] = relax.mdp.proofs - before
    one, two = found[1], found[2]
    assert one is not None and two is not None
    assert len(one.unions) > 1
    # each union proven in either process; a kept basis's cache, filled in another order,
    # may move a proven bound by a rounding
    assert sorted(u for u, _ in two.unions) == sorted(u for u, _ in one.unions)
    alone = dict(one.unions)
    assert all(b == pytest.approx(alone[u], rel=1e-12) for u, b in two.unions)
    assert two.bound == pytest.approx(one.bound, rel=1e-12)
    assert (two.solved, two.refined, two.enumerated) == (one.solved, one.refined, one.enumerated)
    assert proofs[2] == proofs[1] == one.solved


@needs_fork
def test_a_worker_dies_with_its_parent(tmp_path):
    """A parent killed outright (SIGKILL: no cleanup runs) takes its forked workers with it."""
    import signal
    import subprocess
    import sys

    pid_file = tmp_path / "worker.pid"
    script = f"""
import os, time
from misdirect.solvers.engines.forked import forked_map
def work(k):
    if k == 1:
        open({str(pid_file)!r}, "w").write(str(os.getpid()))
    time.sleep(60)
    return k
forked_map(work, 2)
"""
    parent = subprocess.Popen([sys.executable, "-c", script])
    try:
        for _ in range(200):  # the worker has started once it wrote its pid
            if pid_file.exists() and pid_file.read_text():
                break
            time.sleep(0.05)
        worker = int(pid_file.read_text())
        os.kill(worker, 0)  # alive
    finally:
        parent.send_signal(signal.SIGKILL)
        parent.wait()
    for _ in range(100):
        try:
            os.kill(worker, 0)
        except ProcessLookupError:
            return
        try:
            with open(f"/proc/{worker}/stat") as stat:  # a zombie (not reaped yet): gone
                if stat.read().split()[2] == "Z":
                    return
        except FileNotFoundError:
            return
        time.sleep(0.05)
    raise AssertionError(f"worker {worker} outlived its parent")
