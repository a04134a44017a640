import os

import nbformat
import pytest
from nbclient import NotebookClient


NOTEBOOKS = os.path.join(os.path.dirname(__file__), "..", "notebooks")


# Slow (XLA compilation of four small studies, ~2 min): run by CI's second step.
@pytest.mark.slow
@pytest.mark.timeout(1200)
@pytest.mark.parametrize("name", ["noise_study.ipynb", "tracking.ipynb"])
def test_notebook_runs_at_small_size(name, monkeypatch):
    monkeypatch.setenv("JAXLOC_NOTEBOOK_TRIALS", "32")
    monkeypatch.setenv("JAXLOC_NOTEBOOK_RUNS", "4")
    monkeypatch.setenv("JAXLOC_NOTEBOOK_CYCLES", "3")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    with open(os.path.join(NOTEBOOKS, name)) as f:
        nb = nbformat.read(f, as_version=4)
    NotebookClient(nb, timeout=1100, kernel_name="python3").execute()
    outputs = [o for cell in nb.cells if cell.cell_type == "code" for o in cell.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
