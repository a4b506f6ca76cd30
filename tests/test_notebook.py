"""``examples/quickstart.ipynb`` runs from top to bottom in a Jupyter kernel, and shows tables.

The kernel is started by nbclient (``pip install nbclient ipykernel``, in the ``test``
extra) with this checkout's ``src`` first on its ``PYTHONPATH``, so it imports the code under
test. Expected value: the paper's budget-1 optimum on its grid, 0.719924 (Section VII, as in
tests/test_paper_values.py).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK = ROOT / "examples" / "quickstart.ipynb"
PAPER_BUDGET_1 = "0.719924"


def _outputs(notebook: object, cell_id: str) -> list[dict]:
    (cell,) = [c for c in notebook.cells if c.get("id") == cell_id]  # type: ignore[attr-defined]
    return cell.outputs


def _data(outputs: list[dict], kind: str) -> str:
    shown = [o["data"][kind] for o in outputs if kind in o.get("data", {})]
    assert shown, f"no {kind} output in {outputs}"
    return shown[-1]


@pytest.fixture(scope="module")
def executed() -> object:
    notebook = nbformat.read(NOTEBOOK, as_version=4)
    path = os.pathsep.join(filter(None, [str(ROOT / "src"), os.environ.get("PYTHONPATH")]))
    before = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = path  # the kernel process inherits it
    try:
        client = nbclient.NotebookClient(
            notebook,
            timeout=120,
            kernel_name="python3",
            resources={"metadata": {"path": str(NOTEBOOK.parent)}},
        )
        client.execute()
    finally:
        if before is None:
            del os.environ["PYTHONPATH"]
        else:
            os.environ["PYTHONPATH"] = before
    return notebook


def test_the_notebook_is_stored_without_outputs():
    notebook = nbformat.read(NOTEBOOK, as_version=4)
    nbformat.validate(notebook)
    code = [c for c in notebook.cells if c.cell_type == "code"]
    assert code and all(not c.outputs and c.execution_count is None for c in code)


def test_the_notebook_runs_and_prints_the_papers_value(executed: object):
    printed = "".join(o.get("text", "") for o in _outputs(executed, "budget-1"))
    assert printed.startswith(f"budget 1: {PAPER_BUDGET_1}, "), printed


def test_the_notebook_shows_tables(executed: object):
    problem = _data(_outputs(executed, "problem"), "text/html")
    assert "observations (8)" in problem and "<table" in problem
    assert "misdirect-view" in problem  # this checkout's code ran in the kernel
    curve = _data(_outputs(executed, "solve"), "text/html")
    assert PAPER_BUDGET_1 in curve and "optimal" in curve and "proven bound" in curve
    assert "o1 → o2" in curve or "o1 → o3" in curve
    assert PAPER_BUDGET_1 in _data(_outputs(executed, "solve"), "text/markdown")
    assert "0.719924" in _data(_outputs(executed, "evaluate"), "text/html")
    audit = _data(_outputs(executed, "audit"), "text/html")
    assert "criticality" in audit and "0.860130" in audit  # the paper's budget-2 optimum
