"""The package's own imports keep its layers honest (docs/architecture.md, "Dependency rules").

Read from the source with ``ast`` (function-level imports included: an import hidden in a
function is still a dependency), so the rules hold for every module, imported or not.
"""

from __future__ import annotations

import ast
import re
import tokenize
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "misdirect"

# what each layer may never import (by module prefix)
FORBIDDEN = {
    "misdirect.core": (
        "misdirect.io",
        "misdirect.solvers",
        "misdirect.report",
        "misdirect.defence",
        "misdirect.cli",
        "misdirect.scenarios",
        "misdirect.distributed",
    ),
    "misdirect.io": (
        "misdirect.report",
        "misdirect.defence",
        "misdirect.cli",
        "misdirect.distributed",
    ),
    "misdirect.solvers": (
        "misdirect.report",
        "misdirect.defence",
        "misdirect.cli",
        "misdirect.distributed",
    ),
    "misdirect.solvers.engines": (
        "misdirect.solvers.auto",
        "misdirect.solvers.exhaustive",
        "misdirect.solvers.incremental",
        "misdirect.solvers.branch_and_bound",
        "misdirect.solvers.milp",
        "misdirect.solvers.run",
    ),
    # the defence takes a pool (solvers.pool), never Dask's
    "misdirect.defence": ("misdirect.report", "misdirect.cli", "misdirect.distributed"),
    "misdirect.distributed": ("misdirect.report", "misdirect.cli"),
    "misdirect.report": ("misdirect.cli",),
    "misdirect.scenarios": ("misdirect.solvers", "misdirect.report", "misdirect.cli"),
}
# the methods stand on the engines; auto, the portfolio, is the one module that composes them
METHODS = (
    "misdirect.solvers.exhaustive",
    "misdirect.solvers.incremental",
    "misdirect.solvers.branch_and_bound",
    "misdirect.solvers.milp",
)


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _imports(name: str) -> list[tuple[str, str | None, int]]:
    """(module imported, name taken from it or None, line) of every import in ``name``."""
    path = MODULES[name]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, None, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{anchor}.{base}" if base else anchor
            for alias in node.names:
                submodule = f"{base}.{alias.name}"
                if submodule in MODULES:
                    found.append((submodule, None, node.lineno))
                else:
                    found.append((base, alias.name, node.lineno))
    return [item for item in found if item[0].startswith("misdirect")]


def _within(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def _graph() -> dict[str, set[str]]:
    graph = {name: set() for name in MODULES}
    for name in MODULES:
        for target, _, _ in _imports(name):
            # importing a.b.c runs a and a.b too, but those are the packages' own business:
            # the edge that matters is to the module named
            if target in MODULES and target != name:
                graph[name].add(target)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return found


def test_the_rules_see_the_whole_package():
    assert "misdirect.solvers.engines.segment_search" in MODULES
    assert "misdirect.solvers.engines.per_state" in {
        target for target, _, _ in _imports("misdirect.solvers.branch_and_bound")
    }


def test_no_import_circles():
    assert _cycles(_graph()) == []


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


@pytest.mark.parametrize("layer", sorted(FORBIDDEN))
def test_no_upward_imports(layer):
    wrong = [
        f"{name}:{line} imports {target}"
        for name in MODULES
        if _within(name, layer)
        for target, _, line in _imports(name)
        for forbidden in FORBIDDEN[layer]
        if _within(target, forbidden) and not _within(name, forbidden)
    ]
    assert wrong == []


def test_no_method_imports_another_method():
    wrong = [
        f"{name}:{line} imports {target}"
        for name in MODULES
        for method in METHODS
        if _within(name, method)
        for target, _, line in _imports(name)
        for other in METHODS
        if other != method and _within(target, other)
    ]
    assert wrong == []


def test_no_private_name_is_imported_from_another_module():
    wrong = [
        f"{name}:{line} imports {target}.{taken}"
        for name in MODULES
        for target, taken, line in _imports(name)
        if taken is not None and taken.startswith("_") and not taken.startswith("__")
    ]
    assert wrong == []


def test_a_private_module_is_imported_by_its_own_package_only():
    """``misdirect._x`` is the package's own business: only ``misdirect`` may import it (the
    rule above sees names, and a module imported by ``from misdirect import _x`` is one)."""
    wrong = [
        f"{name}:{line} imports {target}"
        for name in MODULES
        for target, _, line in _imports(name)
        if target.rpartition(".")[2].startswith("_")
        and not target.rpartition(".")[2].startswith("__")
        and name != target.rpartition(".")[0]
    ]
    assert wrong == []


# -- only the CLI names flags; only core/tolerance.py writes a tolerance ----------------------

FLAG = re.compile(r"(?<![\w-])--[a-z]")

# library strings that name a flag on purpose (module, text), each with why
NAMES_A_FLAG = {
    # the limit's one library handle is the environment variable, which --memory-limit sets:
    # the message names both, so either kind of user knows what to change
    ("misdirect.core.memory", "--memory-limit"),
    # a command that writes the file PAYNT needs, not a parameter of any call
    ("misdirect.io.paynt", "misdirect convert --to drn"),
    # a cell of the report of `misdirect reproduce`, which says how to get the row it lacks
    ("misdirect.report.reproduce", "--full only"),
}


def _docstrings(tree: ast.AST) -> set[int]:
    """The ids of the docstring nodes of ``tree`` (a module's, a class's, a function's)."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            first = node.body[0] if node.body else None
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                found.add(id(first.value))
    return found


def test_only_the_cli_names_flags():
    """A library error names the parameter (``method="milp"``, ``field="path"``); the CLI
    shows it as its flag (misdirect.cli.common: ``flag``, ``field_flag``)."""
    wrong = []
    for name, path in MODULES.items():
        if _within(name, "misdirect.cli"):
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        docstrings = _docstrings(tree)
        for node in ast.walk(tree):
            if not (isinstance(node, ast.Constant) and isinstance(node.value, str)):
                continue
            text = node.value
            if id(node) in docstrings or not (FLAG.search(text) or text == "-o"):
                continue
            if not any(name == module and part in text for module, part in NAMES_A_FLAG):
                wrong.append(f"{name}:{node.lineno}: {text!r}")
    assert wrong == []


def test_the_cli_shows_library_parameters_as_flags():
    from misdirect.cli.common import as_flags, assignments_as_flags, shown_lines
    from misdirect.errors import OptionError, ProblemError

    assert shown_lines(ProblemError("cannot write x", field="path")) == ["-o: cannot write x"]
    assert shown_lines(ProblemError("bad", field="prop")) == ["--props: bad"]
    assert shown_lines(ProblemError("bad", field="pomdp.states")) == ["pomdp.states: bad"]
    both = OptionError("give cluster or workers, not both", parameter="cluster")
    assert shown_lines(both) == ["--cluster: give --cluster or --workers, not both"]
    suggested = assignments_as_flags('too long (try method="milp"); or solver="scip"')
    assert suggested == "too long (try --method milp); or --solver scip"
    assert as_flags('threads: at most 4; try solver="highs"') == (
        "--threads: at most 4; try --solver highs"
    )


EXPONENT = re.compile(r"[eE]([+-]?\d+)$")
TOLERANCES = "misdirect.core.tolerance"

# small numbers that are not tolerances, named in their module (module, name), each with why
NOT_TOLERANCES = {
    # a scenario's definition: the decoys it generates (a new number changes every seed's problem)
    ("misdirect.scenarios.sensor_grid", "MIN_DECOY_PROBABILITY"),
    # Gurobi's own threshold for a coefficient it reads as 0 (its documentation), not ours
    ("misdirect.solvers.milp.backends", "GUROBI_TINY"),
    # seconds (the enumeration's time per alteration), a time policy's estimate
    ("misdirect.solvers.schedule", "UPDATE_SECONDS"),
    # how a report prints a value (six decimals, or three figures below this)
    ("misdirect.report.reproduce", "SHOWN_FIXED"),
}


def _small_literals(path: Path) -> list[tuple[int, str, str | None]]:
    """(line, literal, name or None) of each float literal in code (not in comments or
    strings) whose exponent is -6 or less; the name when the line is a module's constant
    ``NAME = literal`` alone."""
    found = []
    with path.open("rb") as handle:
        for token in tokenize.tokenize(handle.readline):
            if token.type != tokenize.NUMBER:
                continue
            exponent = EXPONENT.search(token.string.rstrip("jJ"))
            if token.string.lower().startswith("0x") or not exponent:
                continue
            if int(exponent[1]) <= -6:
                # a module's constant: ``NAME = literal`` (with a comment, perhaps), nothing more
                whole = rf"(\w+)\s*(?::[^=]*)?=\s*{re.escape(token.string)}\s*(?:#.*)?"
                assigned = re.fullmatch(whole, token.line.rstrip("\n"))
                found.append((token.start[0], token.string, assigned and assigned[1]))
    return found


def test_no_literal_tolerance_outside_the_policy():
    """Every tolerance is named, with its why, in core/tolerance.py (docs/architecture.md)."""
    wrong, used = [], set()
    for name, path in MODULES.items():
        if name == TOLERANCES:
            continue
        for line, literal, assigned in _small_literals(path):
            if (name, assigned) in NOT_TOLERANCES:
                used.add((name, assigned))
            else:
                wrong.append(f"{name}:{line}: {literal}")
    assert wrong == []
    assert used == NOT_TOLERANCES, "a named exception no longer needed: drop it"


def test_the_literal_finder_sees_code_not_comments(tmp_path):
    sample = tmp_path / "sample.py"
    sample.write_text(
        '"""1e-9 in a docstring."""\nLIMIT = 2.5e-10  # 1e-12 in a comment\nx = 1e-5 + 1E-7\n'
    )
    found = [(literal, assigned) for _, literal, assigned in _small_literals(sample)]
    assert found == [("2.5e-10", "LIMIT"), ("1E-7", None)]


def test_a_call_deadline_is_built_from_a_time_limit_in_one_place():
    """``Deadline`` carries a call's time: only ``deadline.call_deadline`` builds one from a
    ``time_limit`` (a method takes the front door's, :func:`misdirect.solvers.base.
    method_deadline`), so no method starts a clock of its own beside the call's."""
    builds = []
    for name, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.Call) and ast.unparse(node.func).endswith("Deadline")):
                continue
            if "time_limit" in ast.unparse(node):
                builds.append(f"{name}:{node.lineno}")
    assert builds and {b.split(":")[0] for b in builds} == {"misdirect.solvers.deadline"}, builds
