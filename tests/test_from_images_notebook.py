"""Executes notebooks/from_images.ipynb at small size (issue 7)."""

import os

import nbformat
import pytest
from nbclient import NotebookClient


NOTEBOOKS = os.path.join(os.path.dirname(__file__), "..", "notebooks")


@pytest.mark.slow  # ~25 s on an idle machine (a fresh kernel compiles everything)
@pytest.mark.timeout(1200)
def test_from_images_notebook_runs_at_small_size(monkeypatch):
    monkeypatch.setenv("JAXLOC_NOTEBOOK_TRIALS", "8")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    with open(os.path.join(NOTEBOOKS, "from_images.ipynb")) as f:
        nb = nbformat.read(f, as_version=4)
    NotebookClient(nb, timeout=1100, kernel_name="python3").execute()
    outputs = [o for cell in nb.cells if cell.cell_type == "code" for o in cell.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    text = "".join(o.get("text", "") for o in outputs if o.get("output_type") == "stream")
    assert "detections: error vs the projected marker centre" in text
