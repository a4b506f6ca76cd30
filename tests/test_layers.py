"""The package's own imports keep its layers honest (docs/architecture.md, "Dependency rules").

Read from the source with ``ast`` (function-level imports included: an import hidden in a
function is still a dependency), so the rules hold for every module, imported or not.
"""

from __future__ import annotations

import ast
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
