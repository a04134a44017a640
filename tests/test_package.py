"""The package's shape (issue 18): no hidden global state, seams through public names,
data flowing one way between the role subpackages, short functions."""

import ast
import pathlib
import subprocess
import sys
import textwrap

import pytest


PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "jaxloc"
#: The role subpackages in data-flow order (DESIGN §6): a subpackage may import those
#: before it, never one after it. `_cli` is last: nothing imports it.
LAYERS = (
    "_core", "_cameras", "_cycle", "_model", "_solvers", "_refine", "_sim", "_study",
    "_design", "_vision", "_track", "_cli",
)  # fmt: skip


def _modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        yield path, ast.parse(path.read_text())


def _subpackage(path: pathlib.Path) -> str | None:
    parts = path.relative_to(PACKAGE).parts
    return parts[0] if len(parts) > 1 else None


def _imported_subpackages(path: pathlib.Path, tree: ast.AST):
    """`(subpackage, imported name)` of every relative import of `path`."""
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            base = path.relative_to(PACKAGE).parts[:-1]
            base = base[: len(base) - (node.level - 1)]
            target = (*base, *(node.module.split(".") if node.module else ()))
            for alias in node.names:
                yield (target[0] if target else alias.name), alias.name


def test_no_private_name_imported_across_modules():
    bad = [
        f"{path.relative_to(PACKAGE)}: {name}"
        for path, tree in _modules()
        for _, name in _imported_subpackages(path, tree)
        if name.startswith("_") and not name.startswith("__")
    ]
    assert not bad, bad


def test_subpackages_import_only_earlier_layers():
    bad = []
    for path, tree in _modules():
        own = _subpackage(path)
        if own not in LAYERS:
            continue
        for target, name in _imported_subpackages(path, tree):
            if target in LAYERS and LAYERS.index(target) > LAYERS.index(own):
                bad.append(f"{path.relative_to(PACKAGE)} imports {target} ({name})")
    assert not bad, bad


def test_every_subpackage_says_its_role():
    for sub in PACKAGE.iterdir():
        if sub.is_dir() and (sub / "__init__.py").exists():
            doc = ast.get_docstring(ast.parse((sub / "__init__.py").read_text()))
            assert doc and "import" in doc.lower(), sub.name


def _run(code: str) -> str:
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
        timeout=600,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def test_import_leaves_jax_configuration_alone():
    out = _run("""
        import jax
        import jaxloc
        import jaxloc._cli.main as cli
        cli.main(["cameras"])
        print(jax.config.jax_enable_x64, jax.config.jax_num_cpu_devices)
    """)
    assert out.strip().splitlines()[-1] == "False -1"


@pytest.mark.slow
def test_a_cycle_in_float32_without_x64():
    """With JAX's default 32-bit mode, everything jaxloc builds is float32 and a cycle is
    localized and refined (no float64 requested anywhere)."""
    out = _run("""
        import warnings
        warnings.simplefilter("error")
        import jax, jax.numpy as jnp, jaxloc
        sc = jaxloc.Scenario.paper("sequential")
        truth, obs, ok = jax.jit(jaxloc.simulate_cycle)(sc, jax.random.key(3))
        est = jax.jit(lambda o, r: jaxloc.localize_cycle(o, r, throw=False))(obs, sc.rig)
        ref = jax.jit(lambda o, r, e: jaxloc.refine_cycle(o, r, e, throw=False))(obs, sc.rig, est)
        print(sc.base.dtype, obs.mutual.dtype, ref.poses.T_world_body.wxyz_xyz.dtype,
              jaxloc.status_names()[int(jaxloc.status_code(ref.result))])
    """)
    assert out.split() == ["float32", "float32", "float32", "successful"]
