"""The documentation site covers the public API (issue 22): every public name of `jaxloc`
has a docstring, as the site's generator (griffe) reads it, and an entry on an API page;
every entry names a real object; every notebook the site renders has stored outputs."""

import json
import os
import re
import types

import griffe
import jaxloc
import pytest


ROOT = os.path.join(os.path.dirname(__file__), "..")
API = os.path.join(ROOT, "docs", "api")
ENTRY = re.compile(r"^::: (jaxloc\.[A-Za-z0-9_.]+)\s*$", re.MULTILINE)


def public_names() -> set[str]:
    """`jaxloc`'s public API: its `__all__` if it has one, else every name of `dir(jaxloc)`
    without a leading underscore that is not a submodule."""
    names = getattr(jaxloc, "__all__", None) or dir(jaxloc)
    return {
        n for n in names
        if not n.startswith("_") and not isinstance(getattr(jaxloc, n), types.ModuleType)
    }  # fmt: skip


def api_entries() -> dict[str, str]:
    """`::: jaxloc.NAME` entries of the API pages, as `{path: page}`."""
    entries = {}
    for page in sorted(os.listdir(API)):
        with open(os.path.join(API, page)) as f:
            for path in ENTRY.findall(f.read()):
                assert path not in entries, f"{path} is on {entries[path]} and {page}"
                entries[path] = page
    return entries


@pytest.fixture(scope="module")
def package():
    return griffe.load("jaxloc", search_paths=[ROOT], resolve_aliases=True,
                       resolve_external=False)  # fmt: skip


def test_the_public_api_is_more_than_a_handful_of_names():
    assert len(public_names()) > 100
    assert {"Rig", "localize_cycle", "run_study", "run_study_on_ray"} <= public_names()


def test_every_public_name_has_a_docstring(package):
    missing = []
    for name in sorted(public_names()):
        docstring = package[name].docstring  # what mkdocstrings renders
        if docstring is None or len(docstring.value.strip()) < 10:
            missing.append(name)
    assert not missing, f"public names without a docstring: {missing}"


def test_every_public_name_has_an_entry_on_an_api_page():
    entries = api_entries()
    on_pages = {path.removeprefix("jaxloc.") for path in entries if path.count(".") == 1}
    missing = sorted(public_names() - on_pages)
    assert not missing, f"public names on no page of docs/api/: {missing}"
    unknown = sorted(on_pages - public_names())
    assert not unknown, f"docs/api/ documents names that jaxloc does not export: {unknown}"


def test_every_api_entry_exists(package):
    for path, page in api_entries().items():
        try:
            package[path.removeprefix("jaxloc.")]
        except KeyError:
            raise AssertionError(f"{page}: `::: {path}` names no object") from None


def test_the_rendered_notebooks_have_stored_outputs():
    # The site renders the notebooks as stored (mkdocs-jupyter, execute: false), so each
    # must hold its outputs (`python notebooks/render.py` refreshes them).
    folder = os.path.join(ROOT, "notebooks")
    for name in sorted(n for n in os.listdir(folder) if n.endswith(".ipynb")):
        with open(os.path.join(folder, name)) as f:
            cells = [c for c in json.load(f)["cells"] if c["cell_type"] == "code"]
        outputs = [o for c in cells for o in c.get("outputs", [])]
        assert outputs, f"{name} has no stored outputs"
        assert not [o for o in outputs if o["output_type"] == "error"], name
