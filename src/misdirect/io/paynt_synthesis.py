"""The robot's controller from PAYNT (``misdirect[paynt]``), through PAYNT's Python API.

PAYNT 0.5 reads a PRISM program (or a DRN file) and a properties file from disk
(``paynt.parser.sketch.Sketch.load_sketch``) and synthesizes a finite-state controller with
a given number of memory nodes (``paynt.pomdp.PomdpSynthesizer``, abstraction refinement).
We run it for one memory size, within a time limit, and keep PAYNT's own JSON of the
controller (``FscFactored.to_json``) unedited, so that ``controller: {paynt: FILE}`` reads
exactly what PAYNT writes.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import math
import multiprocessing
import os
import re
import signal
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from misdirect.core.model import Controller, Problem
from misdirect.errors import MisdirectError, ProblemError
from misdirect.io.files import check_input_file, read_text_file
from misdirect.io.paynt_model import paynt_prism_text
from misdirect.io.storm_expressions import strip_comments
from misdirect.io.storm_guard import check_drn_text, check_nesting, run_isolated

NEEDS_PAYNT = "needs paynt: pip install 'misdirect[paynt]'"
_CONSTANT = re.compile(
    r"^\s*([A-Za-z_]\w*)\s*=\s*(-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?|true|false)\s*$"
)


@dataclass(frozen=True)
class Synthesis:
    """PAYNT's controller and what PAYNT reports about it."""

    document: dict[str, Any]  # PAYNT's JSON of the controller, as it writes it
    value: float | None  # PAYNT's value of the property under this controller
    property: str
    memory: int
    seconds: float


def _paynt():
    try:
        import paynt.api
        import paynt.parser.sketch
        import paynt.utils.timer
    except ImportError:
        raise ProblemError(NEEDS_PAYNT) from None
    return paynt


def _with_constants(text: str, constants: str | None) -> str:
    """PAYNT has no option for undefined constants: write ``N=5`` into ``const int N;``."""
    if not constants:
        return text
    for part in constants.split(","):
        match = _CONSTANT.match(part)
        if match is None:
            raise ProblemError(
                f"cannot read {part.strip()!r}: expected NAME=VALUE (a number, true or false)",
                field="constants",
            )
        name, value = match[1], match[2]
        declaration = re.compile(
            r"(?m)^(\s*const\s+(?:(?:int|double|bool)\s+)?" + re.escape(name) + r")\s*;"
        )
        text, count = declaration.subn(rf"\g<1> = {value};", text)
        if count != 1:
            raise ProblemError(
                f"the program has no undefined constant {name!r} (const ... {name};)",
                field="constants",
            )
    return text


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """PAYNT logs through ``logging`` and prints, and Storm's parsers write to the process's
    file descriptors (PAYNT tries several on a DRN file): none of it may reach our output
    (``--json`` prints one object, an error is one line)."""
    logger = logging.getLogger("paynt")
    level = logger.level
    logger.setLevel(logging.ERROR)
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    sink = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(sink, 1)
        os.dup2(sink, 2)
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            yield
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        for fd, copy in zip((1, 2), saved, strict=True):
            os.dup2(copy, fd)
            os.close(copy)
        os.close(sink)
        logger.setLevel(level)


def synthesize(
    model: Path,
    prop: str,
    *,
    constants: str | None = None,
    memory: int = 1,
    timeout: float = 60.0,
    constraints: tuple[str, ...] = (),
) -> Synthesis:
    """Run PAYNT on a POMDP (a PRISM program or a DRN file, as PAYNT reads both) for one
    property and ``memory`` nodes per observation.

    ``constraints`` are bounded properties (``P>=0.9 [F "goal"]``) every controller PAYNT
    returns must satisfy besides optimizing ``prop`` (PAYNT's specification: constraints, then
    one optimizing property).

    ``timeout`` bounds the whole call, not PAYNT's search alone: building the model (which
    neither Storm nor PAYNT can interrupt, and which PAYNT's timer does not stop) runs with
    the search in a worker process that is stopped at the limit, and the search gets what the
    build leaves, less a margin for writing its answer back.
    """
    started = time.monotonic()
    _paynt()
    import stormpy

    check_input_file(model, field="MODEL")
    text = read_text_file(model, field="MODEL")
    drn = is_drn(text)
    if drn and constants:
        raise ProblemError("a DRN model has no constants to set", field="constants")
    if not drn:
        text = _with_constants(paynt_prism_text(text), constants)
    # what Storm would crash, hang or allocate without bound on is refused before it reads
    if drn:
        check_drn_text(text, name=str(model), field="MODEL")
    else:
        check_nesting(strip_comments(text), field="MODEL", what=str(model))
    check_nesting(prop, field="prop", what="the property")
    for constraint in constraints:
        check_nesting(constraint, field="constraints", what="the constraint")
    stormpy.developer.set_log_level(stormpy.developer.LogLevel.OFF)
    with tempfile.TemporaryDirectory(prefix="misdirect-paynt-") as folder:
        sketch, props = Path(folder) / model.name, Path(folder) / "sketch.props"
        sketch.write_text(text, encoding="utf-8")
        lines = [c.strip() for c in constraints] + [prop.strip()]
        props.write_text("\n".join(lines) + "\n", encoding="utf-8")
        # Storm's parser may still crash on the file: it reads it in a child process
        run_isolated(
            _check_sketch,
            str(sketch),
            drn,
            prop,
            str(model),
            constraints,
            name=str(model),
            field="MODEL",
        )
        job = _Job(str(sketch), str(props), memory, drn, deadline=started + timeout)
        kind, payload = _run_bounded(job)
    if kind == "problem":
        raise ProblemError(payload, source=str(model))
    if kind == "failed":
        raise MisdirectError(f"PAYNT failed on {model}: {payload}")
    if kind in ("building", "searching"):
        where = "was still building the model" if kind == "building" else "was stopped"
        raise MisdirectError(
            f"PAYNT found no controller with {memory} memory node(s) within {timeout:g} s "
            f"(it {where} at the time limit, which counts building the model)"
        )
    document, value, timed_out = payload
    if document is None and timed_out:
        raise MisdirectError(
            f"PAYNT found no controller with {memory} memory node(s) within {timeout:g} s"
        )
    if document is None:
        raise MisdirectError(
            f"PAYNT found no controller with {memory} memory node(s) under which "
            f"{prop.strip()} has a finite value (it finished its search; more memory nodes "
            "may help)"
        )
    return Synthesis(document, value, prop.strip(), memory, time.monotonic() - started)


@dataclass(frozen=True)
class ProblemSynthesis:
    """PAYNT's controller of a problem's world, read back as ours."""

    controller: Controller
    synthesis: Synthesis
    undefined: int  # (node, reading) entries PAYNT left null, filled with a placeholder


def synthesize_problem(
    problem: Problem,
    goal: np.ndarray,
    *,
    memory: int = 1,
    timeout: float = 60.0,
    prop: str = 'Pmax=? [F "goal"]',
    labels: Mapping[str, np.ndarray] | None = None,
    constraints: tuple[str, ...] = (),
) -> ProblemSynthesis:
    """PAYNT's controller with ``memory`` nodes maximising Pr(reach ``goal``) on ``problem``'s
    world (or optimizing ``prop`` subject to ``constraints``), for any problem: the world is
    written as DRN (observation ids are ours) with the label ``goal`` on the states of ``goal``
    (``decoy`` on the decoys, and each of ``labels`` on its states), and PAYNT's columns and
    action labels are renamed to ours before the controller is read back by the project's
    PAYNT reader. An observation no state emits has no column in PAYNT's controller: it is
    read back as never met (null), so the reader fills it with its placeholder."""
    from misdirect.io.export import drn_action, drn_text
    from misdirect.io.paynt import read_paynt_controller

    pomdp = problem.pomdp
    marks = {"goal": np.asarray(goal, dtype=bool)}
    marks.update({name: np.asarray(mask, dtype=bool) for name, mask in (labels or {}).items()})
    lines = []
    for line in drn_text(problem).splitlines():
        if line.startswith("state "):
            state = int(line.split()[1])
            line += "".join(f" {name}" for name, mask in marks.items() if mask[state])
        lines.append(line)
    drn_names = {drn_action(name, f"a{k}"): name for k, name in enumerate(pomdp.actions)}
    with tempfile.TemporaryDirectory(prefix="misdirect-paynt-") as folder:
        model = Path(folder) / "world.drn"
        model.write_text("\n".join(lines) + "\n", encoding="utf-8")
        found = synthesize(
            model, prop, memory=memory, timeout=timeout, constraints=tuple(constraints)
        )
        document = _with_every_observation(dict(found.document), pomdp.n_observations)
        document["observation_labels"] = [
            pomdp.observations[int(label)] for label in document["observation_labels"]
        ]
        document["action_labels"] = [
            drn_names.get(str(label), str(label)) for label in document["action_labels"]
        ]
        written = Path(folder) / "paynt.fsc.json"
        written.write_text(json.dumps(document), encoding="utf-8")
        read = read_paynt_controller(written, pomdp)
    return ProblemSynthesis(read.controller, found, int(np.count_nonzero(read.undefined)))


def _with_every_observation(document: dict[str, Any], n_observations: int) -> dict[str, Any]:
    """PAYNT's controller with a column for every observation id (one no state of the DRN
    model emits gets null entries: PAYNT never meets it; an alteration may make the robot),
    and an action wherever PAYNT gave a next node but left the action out."""
    actions, updates = document.get("action_function"), document.get("update_function")
    if isinstance(actions, list) and isinstance(updates, list):
        # PAYNT leaves the action of a (node, reading) out where no action changes its value
        # (and may keep the node update there): any action then does, the first is played
        for row_a, row_u in zip(actions, updates, strict=False):
            for k in range(min(len(row_a), len(row_u))):
                if row_a[k] is None and row_u[k] is not None:
                    row_a[k] = 0
    present = {int(label) for label in document.get("observation_labels", [])}
    missing = [o for o in range(n_observations) if o not in present]
    if not missing:
        return document
    document["observation_labels"] = [*document["observation_labels"], *map(str, missing)]
    for key in ("action_function", "update_function", "transitions"):
        if isinstance(document.get(key), list):
            document[key] = [[*row, *([None] * len(missing))] for row in document[key]]
    if "num_observations" in document:
        document["num_observations"] = len(document["observation_labels"])
    return document


SEARCH_SHARE = 0.9  # of the time left after the build, PAYNT's search gets this much
STOP_POLL_S = 0.1  # how often the parent looks for the worker's answer and for Ctrl-C


@dataclass(frozen=True)
class _Job:
    sketch: str
    props: str
    memory: int
    drn: bool
    deadline: float  # time.monotonic() by which the whole synthesis must end


def _search(job: _Job, built: Callable[[], None]) -> tuple[str, Any]:
    """PAYNT's synthesis (quietly): ``("done", (document or None, value, timed out))`` or
    ``("problem", reason)``; ``built()`` is called once the model is built."""
    paynt = _paynt()
    import stormpy

    with _quiet():
        try:
            # PAYNT's timer starts now, so it counts the build; the search ends by SEARCH_SHARE
            # of the time left, leaving the rest for building and sending the answer
            left = job.deadline - time.monotonic()
            paynt.utils.timer.GlobalTimer.start(max(left * SEARCH_SHARE, 0.0))
            factory, task = paynt.parser.sketch.Sketch.load_sketch(
                job.sketch, job.props, task_kwargs={"memory_size": job.memory}
            )
            synthesizer = paynt.api.get_synthesizer(factory, task, "ar", fsc_synthesis=True)
            built()
            synthesizer.synthesize(synthesizer.colored_mdp.parameter_space, print_stats=False)
            result = synthesizer.build_result()
        except (AssertionError, ValueError, RuntimeError, SyntaxError) as error:
            if job.drn:  # PAYNT only says it knows no such format: Storm says what is wrong
                try:
                    stormpy.build_model_from_drn(job.sketch)
                except Exception as storm_error:
                    return "problem", f"Storm cannot read it: {' '.join(str(storm_error).split())}"
            reason = " ".join(str(error).split()) or type(error).__name__
            return "problem", f"PAYNT cannot synthesize for it: {reason}"
        timed_out = paynt.utils.timer.GlobalTimer.time_limit_reached()
        value = None if result.value is None else float(result.value)
        if value is not None and not math.isfinite(value):
            value = None
        document = None if result.fsc is None else result.fsc.to_json()
        return "done", (document, value, timed_out)


def _run_bounded(job: _Job) -> tuple[str, Any]:
    """:func:`_search` in a forked worker, stopped at ``job.deadline``: ``("building", None)``
    or ``("searching", None)`` when it was, or what the search returned (``("failed", why)``
    when the worker died). Ctrl-C stops the worker at once. Where no worker can be started (a
    daemonic process, no ``fork``), the search runs here, bounded by PAYNT's timer only."""
    if "fork" not in multiprocessing.get_all_start_methods() or (
        multiprocessing.current_process().daemon
    ):
        return _search(job, lambda: None)
    context = multiprocessing.get_context("fork")
    conn, child = context.Pipe(duplex=False)
    worker = context.Process(target=_worker, args=(child, job), daemon=True)
    worker.start()
    child.close()
    phase = "building"
    try:
        while True:
            left = job.deadline - time.monotonic()
            if left <= 0:
                return phase, None
            if not conn.poll(min(left, STOP_POLL_S)):
                continue
            try:
                kind, payload = conn.recv()
            except (EOFError, OSError):
                worker.join(timeout=1)
                return "failed", f"its worker stopped (exit code {worker.exitcode})"
            if kind == "built":
                phase = "searching"
                continue
            return kind, payload
    finally:
        if worker.is_alive():
            worker.kill()
        worker.join(timeout=1)
        conn.close()


def _worker(conn: Any, job: _Job) -> None:
    """The forked worker: one search, its answer sent back over ``conn``."""
    # Ctrl-C reaches the whole process group: the parent handles it and kills this worker
    # (which must not run the parent's SIGTERM handler, inherited through fork)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        answer = _search(job, lambda: conn.send(("built", None)))
    except Exception as error:  # anything else PAYNT raises: one line in the parent
        answer = ("failed", " ".join(f"{type(error).__name__}: {error}".split()))
    conn.send(answer)
    conn.close()


def is_drn(text: str) -> bool:
    """Whether a model file is Storm's explicit DRN format (its header has ``@type:``; Storm's
    export starts with ``//`` comments) rather than a PRISM program."""
    for line in text.splitlines():
        if line.strip() and not line.lstrip().startswith("//"):
            return line.lstrip().startswith("@type:")
    return False


def _check_sketch(
    sketch: str, drn: bool, prop: str, model: str, constraints: tuple[str, ...] = ()
) -> None:
    """Storm reads the program (not a DRN model: PAYNT does) and the properties against it."""
    import stormpy

    stormpy.developer.set_log_level(stormpy.developer.LogLevel.OFF)
    program = None
    if not drn:
        try:
            program = stormpy.parse_prism_program(sketch, prism_compatibility=True)
        except Exception as error:
            raise ProblemError(
                f"Storm cannot read it: {' '.join(str(error).split())}", source=model
            ) from None
    _check_property(stormpy, program, prop)
    for constraint in constraints:
        _check_constraint(stormpy, program, constraint)


def _parsed(stormpy, text: str, program, field: str) -> list:
    """Storm's properties of ``text``, or a ProblemError in ``field`` with Storm's message
    (its exception's name left out)."""
    try:
        return list(stormpy.parse_properties(text, program))
    except Exception as error:
        message = re.sub(r"^\w+Exception: ", "", " ".join(str(error).split()))
        raise ProblemError(f"Storm cannot parse it: {message}", field=field) from None


def _check_constraint(stormpy, program, constraint: str) -> None:
    """One bounded property (``P>=0.9 [F "goal"]``): a constraint of PAYNT's specification."""
    properties = _parsed(stormpy, constraint, program, "constraints")
    if len(properties) != 1 or not properties[0].get_raw_formula().has_bound:
        raise ProblemError(
            f'expected one property with a bound, e.g. P>=0.9 [F "goal"], got {constraint!r}',
            field="constraints",
        )


def _check_property(stormpy, program, prop: str) -> None:
    """One optimizing property (``Pmax=? [F "goal"]``), as PAYNT needs for a controller's value."""
    # a DRN model has no program: its labels are checked when PAYNT reads the model
    properties = _parsed(stormpy, prop, program, "prop")
    if len(properties) != 1:
        raise ProblemError(f"expected one property, got {len(properties)}", field="prop")
    formula = properties[0].get_raw_formula()
    if not getattr(formula, "has_optimality_type", False) or formula.has_bound:
        raise ProblemError(
            'expected an optimizing property without a bound, e.g. Pmax=? [F "goal"]',
            field="prop",
        )
