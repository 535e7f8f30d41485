"""The docs/ notebooks execute from top to bottom (slow: a few minutes each on the coarse mesh).

They run from the repository root with EYEFEM_RESULTS pointing at the session's temporary
results folder, never at the repository's results/; the compare_cases notebook reuses the
session's coarse comparison of cases 1-6 (conftest.coarse_comparison)."""

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "docs").glob("*.ipynb"))

pytestmark = pytest.mark.slow


def test_there_are_notebooks():
    assert {p.stem for p in NOTEBOOKS} >= {"compare_cases", "sensitivity", "planning"}


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_executes(path, request, results_root, monkeypatch):
    nbformat = pytest.importorskip("nbformat", reason="nbformat is in the [test] extra")
    nbclient = pytest.importorskip("nbclient", reason="nbclient is in the [test] extra")
    if path.stem == "compare_cases":
        request.getfixturevalue("coarse_comparison")
    monkeypatch.setenv("EYEFEM_RESULTS", str(results_root))
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=1800, kernel_name="python3",
                                     resources={"metadata": {"path": str(ROOT)}})
    client.execute()  # raises CellExecutionError with the failing cell's traceback
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if o.get("output_type") == "error"]
    assert not errors
