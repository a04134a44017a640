"""Execute the notebooks in place, storing their outputs, which the documentation site
renders as they are (mkdocs-jupyter with `execute: false`: building the site runs nothing).

    python notebooks/render.py                      # every notebook, at full size
    python notebooks/render.py noise_study.ipynb    # one

Run it after a change that alters what a notebook shows, and commit the notebooks. The
slow tests execute the same notebooks at small size (without storing anything).
"""

import os
import sys
import time

import nbformat
from nbclient import NotebookClient


NOTEBOOKS = os.path.join(os.path.dirname(os.path.abspath(__file__)), ".")


def render(name: str) -> float:
    path = os.path.join(NOTEBOOKS, name)
    with open(path) as f:
        nb = nbformat.read(f, as_version=4)
    t0 = time.perf_counter()
    NotebookClient(nb, timeout=3600, kernel_name="python3",
                   resources={"metadata": {"path": NOTEBOOKS}}).execute()  # fmt: skip
    for cell in nb.cells:  # no execution counts or timings: smaller diffs
        cell.get("metadata", {}).pop("execution", None)
    with open(path, "w") as f:
        nbformat.write(nb, f)
    return time.perf_counter() - t0


if __name__ == "__main__":
    os.environ.setdefault("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    names = sys.argv[1:] or sorted(n for n in os.listdir(NOTEBOOKS) if n.endswith(".ipynb"))
    for name in names:
        print(f"{name}: {render(name):.0f} s", flush=True)
