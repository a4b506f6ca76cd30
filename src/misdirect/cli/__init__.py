"""Command-line interface: a thin layer that parses options, calls the library, formats results.

Every command takes ``--json`` and then prints exactly one JSON object on stdout. Bad input of
any kind exits with code 2 and one line naming the file (or option), the field and the reason.

The commands live by topic (``solving``: evaluate, solve, simulate, show; ``models``: scenario *,
controller synthesize, convert, export-fsc, export-milp, schema; ``exports``: decode,
export-chain; ``defence``: audit, harden;
``reproduce``); ``common`` holds what they share (errors, JSON, signals, progress) and
``options`` the shared options, declared once (:func:`~misdirect.cli.options.problem_input`).
This module builds the typer app from them and is the console entry point (:func:`main`).
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Callable
from typing import Annotated, Any

import typer
from rich.markup import escape

from misdirect import __version__, startup
from misdirect.cli import cluster, defence, exports, models, reproduce, solving
from misdirect.cli.common import (
    INPUT_ERROR,
    INTERRUPTED,
    TERMINATED,
    Terminated,
    check_range,
    err,
    handle_errors,
    out,
    print_json,
)
from misdirect.cli.helptext import Command, Group, literal_help
from misdirect.cli.options import (
    MAX_GRID_SIZE,
    MAX_RANDOM,
    MAX_RUNS,
    MAX_SAMPLES,
    MAX_SEED,
    MAX_STEPS,
    Scenario,
    parse_budgets,
)
from misdirect.core.memory import MEMORY_LIMIT_ENV, parse_memory_size
from misdirect.errors import ProblemError, WriteError
from misdirect.io.files import one_line
from misdirect.report import json_output

__all__ = [
    "INPUT_ERROR",
    "INTERRUPTED",
    "MAX_GRID_SIZE",
    "MAX_RANDOM",
    "MAX_RUNS",
    "MAX_SAMPLES",
    "MAX_SEED",
    "MAX_STEPS",
    "TERMINATED",
    "Scenario",
    "Terminated",
    "app",
    "check_range",
    "main",
    "parse_budgets",
]

app = typer.Typer(
    name="misdirect",
    help="Optimal sensor deception: which sensor readings to alter, within a budget, so that a "
    "robot driven by a finite-state controller ends up in a decoy state.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    cls=Group,
)
scenario_app = typer.Typer(help="Write a generated problem file.", no_args_is_help=True, cls=Group)
app.add_typer(scenario_app, name="scenario")
controller_app = typer.Typer(
    help="The robot's controller: synthesize it with PAYNT, or a robust one.",
    no_args_is_help=True,
    cls=Group,
)
app.add_typer(controller_app, name="controller")


def _add(group: typer.Typer, command: Callable[..., None], name: str | None = None) -> None:
    """Register ``command``, its errors turned into one line and an exit code."""
    typed = name or command.__name__
    if group is scenario_app:
        typed = f"scenario {typed}"
    elif group is controller_app:
        typed = f"controller {typed}"
    group.command(name, cls=Command, help=literal_help(command))(handle_errors(command, typed))


# in the order of misdirect --help
_add(app, solving.evaluate)
_add(app, solving.solve)
_add(app, solving.simulate)
_add(app, solving.show)
_add(app, reproduce.reproduce)
_add(app, models.convert)
_add(app, models.export_fsc, "export-fsc")
_add(app, models.export_milp, "export-milp")
_add(app, exports.decode)
_add(app, exports.export_chain, "export-chain")
_add(app, models.schema)
_add(app, defence.audit)
_add(app, defence.harden)
_add(app, cluster.sweep)
_add(scenario_app, models.scenario_paper_grid, "paper-grid")
_add(scenario_app, models.scenario_knapsack, "knapsack")
_add(scenario_app, models.scenario_sensor_grid, "sensor-grid")
_add(scenario_app, models.scenario_drone, "drone")
_add(scenario_app, models.scenario_random, "random")
_add(controller_app, models.controller_synthesize, "synthesize")
_add(controller_app, defence.controller_robust, "robust")


def _version(value: bool) -> None:
    if value:
        out.print(f"misdirect {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    context: typer.Context,
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Show version.")
    ] = False,
    memory_limit: Annotated[
        str | None,
        typer.Option(
            "--memory-limit",
            help="Refuse work estimated to need more memory than this (e.g. 8G, 512M; default: "
            f"the memory available, or ${MEMORY_LIMIT_ENV}).",
        ),
    ] = None,
) -> None:
    """misdirect: optimal sensor deception for POMDP robots with finite-state controllers."""
    if memory_limit is not None:
        try:
            parse_memory_size(memory_limit, field="--memory-limit")
        except ProblemError as error:
            raise typer.BadParameter(error.reason, param_hint="'--memory-limit'") from None
        previous = os.environ.get(MEMORY_LIMIT_ENV)
        os.environ[MEMORY_LIMIT_ENV] = memory_limit  # read by every memory check
        context.call_on_close(lambda: _restore(MEMORY_LIMIT_ENV, previous))


def _restore(name: str, value: str | None) -> None:
    """An environment variable as it was (a command run in-process must not leak its option)."""
    if value is None:
        os.environ.pop(name, None)
    else:
        os.environ[name] = value


def main() -> None:
    """The console entry point: usage errors (an option that does not parse, an unknown
    command) become one line and exit code 2, like every other input error."""
    # typer may vendor click: take its classes from typer's own exceptions, by name
    # (found at run time, so its type is not known here)
    usage_error: Any = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "UsageError")
    startup.release()  # imported: Ctrl-C is a KeyboardInterrupt again, handled per command
    try:
        code = app(standalone_mode=False)
    except usage_error as error:
        if type(error).__name__ == "NoArgsIsHelpError":  # help, asked for by omission
            print(error.ctx.get_help())
            sys.exit(0)
        where = f"{error.ctx.command_path}: " if error.ctx is not None else ""
        message = one_line(where + error.format_message())
        if "--json" in sys.argv[1:]:  # the one JSON object, as for every other error
            document = json_output.error_document(
                _typed_command(error.ctx), message, field=_usage_field(error)
            )
            with contextlib.suppress(WriteError):
                print_json(document)
        err.print(f"error: {escape(message)}", highlight=False, soft_wrap=True)
        sys.exit(INPUT_ERROR)
    except typer.Abort:
        err.print("interrupted", highlight=False)
        sys.exit(INTERRUPTED)
    sys.exit(code if isinstance(code, int) else 0)


def _typed_command(context: Any) -> str | None:
    """The command of a usage error as typed (``solve``, ``scenario knapsack``); None when
    the command itself is what did not parse."""
    names = []
    while context is not None and context.parent is not None:
        names.append(context.info_name)
        context = context.parent
    return " ".join(reversed(names)) or None


def _usage_field(error: Any) -> str | None:
    """The option a usage error is about: the unknown one (``--bogus``), or the one whose
    value does not parse (its first name); None for an extra argument."""
    if getattr(error, "option_name", None):
        return str(error.option_name)
    param = getattr(error, "param", None)
    if param is not None:
        opts = getattr(param, "opts", None) or [param.name]
        return str(max(opts, key=len)) if opts else None
    return None
