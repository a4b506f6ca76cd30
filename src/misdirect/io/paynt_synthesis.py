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
import logging
import math
import os
import re
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from misdirect.errors import MisdirectError, ProblemError
from misdirect.io.files import check_input_file, read_text_file
from misdirect.io.paynt_model import paynt_prism_text

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
                field="--constants",
            )
        name, value = match[1], match[2]
        declaration = re.compile(
            r"(?m)^(\s*const\s+(?:(?:int|double|bool)\s+)?" + re.escape(name) + r")\s*;"
        )
        text, count = declaration.subn(rf"\g<1> = {value};", text)
        if count != 1:
            raise ProblemError(
                f"the program has no undefined constant {name!r} (const ... {name};)",
                field="--constants",
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
) -> Synthesis:
    """Run PAYNT on a POMDP (a PRISM program or a DRN file, as PAYNT reads both) for one
    property and ``memory`` nodes per observation."""
    paynt = _paynt()
    import stormpy

    check_input_file(model, field="MODEL")
    text = read_text_file(model, field="MODEL")
    drn = is_drn(text)
    if drn and constants:
        raise ProblemError("a DRN model has no constants to set", field="--constants")
    if not drn:
        text = _with_constants(paynt_prism_text(text), constants)
    stormpy.developer.set_log_level(stormpy.developer.LogLevel.OFF)
    with tempfile.TemporaryDirectory(prefix="misdirect-paynt-") as folder:
        sketch, props = Path(folder) / model.name, Path(folder) / "sketch.props"
        sketch.write_text(text, encoding="utf-8")
        props.write_text(prop.strip() + "\n", encoding="utf-8")
        program = None
        if not drn:
            try:
                program = stormpy.parse_prism_program(str(sketch), prism_compatibility=True)
            except Exception as error:
                raise ProblemError(
                    f"Storm cannot read it: {' '.join(str(error).split())}", source=str(model)
                ) from None
        _check_property(stormpy, program, prop)
        started = time.monotonic()
        try:
            with _quiet():
                paynt.utils.timer.GlobalTimer.start(timeout)
                factory, task = paynt.parser.sketch.Sketch.load_sketch(
                    str(sketch), str(props), task_kwargs={"memory_size": memory}
                )
                synthesizer = paynt.api.get_synthesizer(factory, task, "ar", fsc_synthesis=True)
                synthesizer.synthesize(synthesizer.colored_mdp.parameter_space, print_stats=False)
                result = synthesizer.build_result()
        except (AssertionError, ValueError, RuntimeError, SyntaxError) as error:
            if drn:  # PAYNT only says it knows no such format: Storm says what is wrong
                with _quiet():
                    _check_drn(stormpy, sketch, model)
            reason = " ".join(str(error).split()) or type(error).__name__
            raise ProblemError(
                f"PAYNT cannot synthesize for it: {reason}", source=str(model)
            ) from None
    seconds = time.monotonic() - started
    if result.fsc is None:
        raise MisdirectError(
            f"PAYNT found no controller with {memory} memory node(s) within {timeout:g} s"
        )
    value = None if result.value is None else float(result.value)
    if value is not None and not math.isfinite(value):
        value = None
    return Synthesis(result.fsc.to_json(), value, prop.strip(), memory, seconds)


def is_drn(text: str) -> bool:
    """Whether a model file is Storm's explicit DRN format (its header has ``@type:``; Storm's
    export starts with ``//`` comments) rather than a PRISM program."""
    for line in text.splitlines():
        if line.strip() and not line.lstrip().startswith("//"):
            return line.lstrip().startswith("@type:")
    return False


def _check_drn(stormpy, sketch: Path, model: Path) -> None:
    """Storm's reason a DRN file cannot be read, if it cannot."""
    try:
        stormpy.build_model_from_drn(str(sketch))
    except Exception as error:
        raise ProblemError(
            f"Storm cannot read it: {' '.join(str(error).split())}", source=str(model)
        ) from None


def _check_property(stormpy, program, prop: str) -> None:
    """One optimizing property (``Pmax=? [F "goal"]``), as PAYNT needs for a controller's value."""
    try:
        # a DRN model has no program: its labels are checked when PAYNT reads the model
        properties = stormpy.parse_properties(prop, program)
    except Exception as error:
        message = re.sub(r"^\w+Exception: ", "", " ".join(str(error).split()))
        raise ProblemError(f"Storm cannot parse it: {message}", field="--props") from None
    if len(properties) != 1:
        raise ProblemError(f"expected one property, got {len(properties)}", field="--props")
    formula = properties[0].get_raw_formula()
    if not getattr(formula, "has_optimality_type", False) or formula.has_bound:
        raise ProblemError(
            'expected an optimizing property without a bound, e.g. Pmax=? [F "goal"]',
            field="--props",
        )
