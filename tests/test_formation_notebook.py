"""Runs notebooks/formation_design.ipynb at small size (issue 8)."""

import os

import nbformat
import pytest
from nbclient import NotebookClient


NOTEBOOK = os.path.join(os.path.dirname(__file__), "..", "notebooks", "formation_design.ipynb")


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_formation_notebook_runs_at_small_size(monkeypatch):
    monkeypatch.setenv("JAXLOC_NOTEBOOK_SIZE", "small")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    with open(NOTEBOOK) as f:
        nb = nbformat.read(f, as_version=4)
    NotebookClient(nb, timeout=1100, kernel_name="python3").execute()
    outputs = [o for cell in nb.cells if cell.cell_type == "code" for o in cell.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
