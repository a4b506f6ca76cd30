"""Cancellation is per solve: a token stops the solves that hold it, and no other.

Two solves in two threads of one process (a notebook, a server): cancelling one leaves the
other's answer exactly as it is alone. A cancellation that arrives before its solve starts is
not lost. The expected values come from the same solve run alone, not from constants.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from misdirect import solve
from misdirect.core.model import reachable_from
from misdirect.scenarios import paper_grid, sensor_grid
from misdirect.solvers.deadline import CancelToken, Deadline

SLOW = (paper_grid(9), [0.0, 1.0, 2.0, 3.0])  # exhaustive: thousands of exact evaluations
OTHER = (paper_grid(7), [0.0, 1.0, 2.0])


def _curve(result):
    return [(p.status, p.probability, p.alteration, p.upper_bound) for p in result.curve]


def test_cancelling_one_solve_leaves_another_in_the_next_thread_alone():
    """The first solve cancels its own token from its progress callback, once the second is
    under way (so the two overlap whatever the machine's speed); the second goes on."""
    alone = solve(OTHER[0], method="exhaustive", budgets=OTHER[1])
    assert all(p.status == "optimal" for p in alone.curve)
    slow_token, other_token = CancelToken(), CancelToken()
    other_started = threading.Event()
    results: dict[str, object] = {}

    def slow_progress(done, total, **_):
        if not slow_token.cancelled and other_started.wait(timeout=60):
            slow_token.cancel()

    def other_progress(done, total, **_):
        other_started.set()

    def run(name, problem, budgets, token, progress):
        results[name] = solve(
            problem, method="exhaustive", budgets=budgets, cancel=token, progress=progress
        )

    threads = [
        threading.Thread(target=run, args=("slow", *SLOW, slow_token, slow_progress)),
        threading.Thread(target=run, args=("other", *OTHER, other_token, other_progress)),
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=300)
    assert not any(thread.is_alive() for thread in threads)
    slow, other = results["slow"], results["other"]
    assert slow.interrupted and not other.interrupted
    assert "interrupted" in {p.status for p in slow.curve}
    assert _curve(other) == _curve(alone)
    assert not other_token.cancelled


def test_a_cancellation_before_the_solve_starts_is_kept():
    token = CancelToken()
    token.cancel()
    began = time.perf_counter()
    result = solve(SLOW[0], method="exhaustive", budgets=SLOW[1], cancel=token)
    assert time.perf_counter() - began < 5.0  # it did not search: one evaluation per budget
    assert result.interrupted
    assert result.curve[0].status == "optimal"  # budget 0: "alter nothing" is all there is
    assert {p.status for p in result.curve[1:]} == {"interrupted"}
    assert all(p.upper_bound >= p.probability for p in result.curve)


def test_a_shared_deadline_bounds_a_solve_and_cancels_with_its_token():
    token = CancelToken()
    shared = Deadline(60.0, cancel=token)
    piece = shared.within(10.0)
    assert piece.cancel is token and piece.end <= shared.end
    assert shared.within(None).end == shared.end
    token.cancel()
    assert piece.expired() and piece.remaining() == 0.0
    result = solve(SLOW[0], method="exhaustive", budgets=SLOW[1], deadline=shared)
    assert result.interrupted


def test_options_are_checked_and_named_by_parameter():
    from misdirect.errors import OptionError

    with pytest.raises(OptionError, match="positive number of seconds") as caught:
        solve(OTHER[0], time_limit=-1)
    assert caught.value.parameter == "time_limit" and "--" not in str(caught.value)
    with pytest.raises(OptionError, match="does not apply") as caught:
        solve(OTHER[0], method="exhaustive", mip_gap=0.1)
    assert caught.value.parameter == "mip_gap"
    with pytest.raises(TypeError, match="time_limt"):
        solve(OTHER[0], time_limt=5)  # type: ignore[call-arg]


def test_prepared_instances_are_shared_only_within_a_block():
    """Nothing is cached on a Problem: two prepares outside a block build two instances; inside
    ``shared_preparation`` (as within one solve) they share one, and a larger budget's serves
    a smaller one."""
    from misdirect import shared_preparation
    from misdirect.core.attack import prepare

    problem = OTHER[0]
    assert prepare(problem, 2.0) is not prepare(problem, 2.0)
    with shared_preparation():
        first = prepare(problem, 2.0)
        assert prepare(problem, 1.0) is first and prepare(problem, 2.0) is first
        assert prepare(problem, 3.0) is not first
    assert prepare(problem, 2.0) is not first


def test_a_cancellation_stops_every_loop_on_a_grid_whose_robot_turns_back():
    """Issue 27: on a grid whose robot can turn back (end components), a solve with no time
    limit ran on in policy iteration after Ctrl-C. Cancelled mid-solve from its own progress
    callback (so the cancel lands inside the search, whatever the machine's speed), it returns
    with the open budgets interrupted and every bound above the exhaustive optimum."""
    problem = sensor_grid(12, 12, seed=1, goal="inside")
    budgets = [0.0, 1.0, 2.0, 3.0]
    token = CancelToken()
    calls = []

    def progress(done, total, **info):
        calls.append(info.get("stage"))
        if len(calls) >= 3:
            token.cancel()

    results = {}
    thread = threading.Thread(
        target=lambda: results.setdefault(
            "cut",
            solve(
                problem, method="branch-and-bound", budgets=budgets, cancel=token, progress=progress
            ),
        )
    )
    thread.start()
    thread.join(timeout=300)
    assert not thread.is_alive()
    cut = results["cut"]
    oracle = solve(problem, method="incremental", budgets=budgets)
    assert all(p.status == "optimal" for p in oracle.curve)
    for mine, best in zip(cut.curve, oracle.curve, strict=True):
        assert mine.probability <= best.probability + 1e-9
        assert mine.upper_bound is None or mine.upper_bound >= best.probability - 1e-9
    assert cut.interrupted and "interrupted" in {p.status for p in cut.curve}


def test_policy_iterations_raise_once_their_deadline_has_passed():
    """Both kinds check the deadline before every round (one linear solve each)."""
    import numpy as np
    import scipy.sparse as sp

    from misdirect.solvers.deadline import DeadlineExpiredError
    from misdirect.solvers.engines.policy_iteration import MaxReachability
    from misdirect.solvers.engines.transient import TransientPolicyIteration

    cancelled = Deadline()
    cancelled.cancel.cancel()
    # two states, each with a choice to loop and one to reach the target (state 2)
    owner = np.array([0, 0, 1, 1, 2])
    moves = sp.csr_matrix(
        ([1.0, 1.0, 1.0, 1.0, 1.0], ([0, 1, 2, 3, 4], [0, 2, 1, 2, 2])), shape=(5, 3)
    )
    mdp = MaxReachability(owner, moves, np.array([False, False, True]))
    with pytest.raises(DeadlineExpiredError):
        mdp.optimise(mdp.first_choices(), deadline=cancelled)
    values, _ = mdp.optimise(mdp.first_choices(), deadline=Deadline())
    assert values.tolist() == [1.0, 1.0, 1.0]  # by hand: both reach the target surely
    transient = TransientPolicyIteration(
        np.array([0, 1]), sp.csr_matrix(np.array([[0.0, 0.5], [0.0, 0.0]])), 2
    )
    with pytest.raises(DeadlineExpiredError):
        transient.optimise(np.array([1.0, 2.0]), deadline=cancelled)


def test_bounds_proven_after_the_deadline_share_one_grace():
    """A curve cut short proves a bound per budget once its time is up; all of them end one
    grace after the deadline (not one grace each), and a cancellation still ends them."""
    from misdirect.solvers.schedule import CLOSING_BOUND_SECONDS, closing_bound

    deadline = Deadline(0.0)
    first = closing_bound(deadline)
    time.sleep(0.05)
    second = closing_bound(deadline)
    assert first.end == second.end == deadline.end + CLOSING_BOUND_SECONDS
    unlimited = closing_bound(Deadline(None))
    assert unlimited.end is not None and unlimited.end <= time.perf_counter() + 1.01 * (
        CLOSING_BOUND_SECONDS
    )
    deadline.cancel.cancel()
    assert closing_bound(deadline).expired()


def test_a_portfolio_hands_over_only_with_time_to_answer():
    """auto starts a later stage only with HANDOVER_MIN_SECONDS left (one started with half a
    second overran the limit), always without a limit, never once stopped."""
    from misdirect.solvers.schedule import HANDOVER_MIN_SECONDS, can_hand_over

    assert can_hand_over(Deadline(None))
    assert can_hand_over(Deadline(HANDOVER_MIN_SECONDS + 5.0))
    assert not can_hand_over(Deadline(HANDOVER_MIN_SECONDS / 2))
    stopped = Deadline(None)
    stopped.cancel.cancel()
    assert not can_hand_over(stopped)


def test_policy_iteration_settles_on_a_grid_whose_robot_turns_back():
    """On the 8x8 turn-back grid, policy iteration for the per-state relaxation used to cycle:
    a switch gaining 1e-9 of rounding closed a class of 95 states (value 0 as the least fixed
    point), the next round opened it, and the bound was 1.0 at the deadline. From a policy
    under which every live state reaches the target, with such switches refused, it settles
    in a few rounds (a round limit raises otherwise), above the brute-force optimum."""
    from misdirect.core.attack import prepare
    from misdirect.solvers.engines.per_state import PerStateRelaxation, relaxation_bound

    problem = sensor_grid(8, 6, seed=1, goal="inside")
    instance = prepare(problem, 2.0)
    assert instance.cycling.any()
    relax = PerStateRelaxation(problem, instance.space, instance.chain)
    mdp = relax.mdp
    start = mdp.first_choices()  # improper: some live states cannot reach the decoy
    assert (mdp.live & ~_reaching(mdp, start)).any()
    values, policy = mdp.optimise(start, max_rounds=50)
    assert not (mdp.live & ~_reaching(mdp, policy)).any()
    best = solve(problem, method="exhaustive", budgets=[2]).curve[0].probability
    bound = relaxation_bound(problem, 2.0, Deadline(600))
    assert best - 1e-12 <= bound < 1.0
    assert values[instance.chain.initial] == pytest.approx(bound, abs=1e-6)


def _reaching(mdp, policy):
    """States that reach the MDP's target under ``policy``."""
    moves = mdp.transitions[policy]
    return reachable_from(moves.T.tocsr(), np.flatnonzero(mdp.target))


def test_a_start_policy_is_made_proper_only_where_end_components_can_form():
    """Without end components every policy leaves the live states, so no round can close a
    cycle and the start is kept as given; with them, the states that cannot reach the decoy
    under it are the ones switched."""
    from misdirect.core.attack import prepare
    from misdirect.solvers.engines.per_state import PerStateRelaxation

    for goal, cycles in (("corner", False), ("inside", True)):
        problem = sensor_grid(8, 6, seed=1, goal=goal)
        instance = prepare(problem, 2.0)
        assert instance.cycling.any() == cycles
        mdp = PerStateRelaxation(problem, instance.space, instance.chain).mdp
        start = mdp.first_choices()
        stranded = mdp.live & ~_reaching(mdp, start)
        made = mdp.proper(start)
        if not cycles:
            assert made is start
            continue
        assert stranded.any()
        assert not (mdp.live & ~_reaching(mdp, made)).any()
        assert (made != start).any() and not (made != start)[~stranded].any()
