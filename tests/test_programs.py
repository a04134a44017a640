"""Traced programs kept on disk (`jaxloc._core.programs`): exported once, loaded by the
next process instead of traced, the same numbers; the file name changes with everything
that changes the trace."""

import logging
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxloc._core.programs import describe, program_key


SCRIPT = textwrap.dedent(
    """
    import sys
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_compilation_cache_dir", sys.argv[1])
    from jaxloc._core.programs import cached_program, program_key

    def make_fn():
        def fn(args):
            x, k = args
            return {"y": jnp.sin(x) * k, "s": jnp.sum(x)}
        return fn

    args = (jnp.linspace(0.0, 1.0, 5), jnp.asarray(3.0))
    program = cached_program("toy", make_fn, "toy v1", args)
    again = cached_program("toy", make_fn, "toy v1", args)
    out = program((jnp.arange(5.0), jnp.asarray(2.0)))
    print("loaded" if program.loaded else "traced", again is program)
    print(repr(np.asarray(out["y"]).tolist()), float(out["s"]))
    """
)


def _run(cache):
    run = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(cache)], capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 0, run.stderr
    return run.stdout.split("\n")


def test_a_program_is_traced_once_and_loaded_by_the_next_process(tmp_path):
    first = _run(tmp_path)
    second = _run(tmp_path)
    assert first[0] == "traced True" and second[0] == "loaded True"
    assert first[1] == second[1]  # the same numbers, to the last digit
    y = np.sin(np.arange(5.0)) * 2.0
    assert first[1] == f"{y.tolist()!r} 10.0"
    (name,) = os.listdir(tmp_path / "jaxloc-programs")
    assert name.startswith("toy-") and name.endswith(".jaxexport")


def test_a_damaged_export_is_traced_anew(tmp_path):
    _run(tmp_path)
    (name,) = os.listdir(tmp_path / "jaxloc-programs")
    with open(tmp_path / "jaxloc-programs" / name, "r+b") as f:
        f.truncate(100)
    assert _run(tmp_path)[0] == "traced True"
    assert _run(tmp_path)[0] == "loaded True"


def test_the_key_names_what_changes_the_trace():
    args = (jnp.zeros(5), jnp.asarray(3.0))
    key = program_key("toy", "v1", args)
    assert key == program_key("toy", "v1", (jnp.ones(5), jnp.asarray(-1.0)))  # values: no
    structs = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), args)
    assert key == program_key("toy", "v1", structs)
    assert key != program_key("toy", "v2", args)
    assert key != program_key("other", "v1", args)
    assert key != program_key("toy", "v1", (jnp.zeros(6), jnp.asarray(3.0)))
    assert key != program_key("toy", "v1", (jnp.zeros(5, jnp.float32), jnp.asarray(3.0)))
    assert key != program_key("toy", "v1", [jnp.zeros(5), jnp.asarray(3.0)])
    with jax.enable_x64(False):
        assert key != program_key("toy", "v1", args)


def test_a_static_description_holds_every_value():
    import jaxloc

    assert describe(jaxloc.Limits()) == describe(jaxloc.Limits())
    assert describe(jaxloc.Limits()) != describe(jaxloc.Limits(separation=0.2))
    assert describe((np.zeros(2), "a")) != describe((np.ones(2), "a"))  # arrays by value
    assert describe((1.0, None)) != describe((1.0,))  # structure


def test_compiler_options_apply_at_the_top_level_only():
    """`jaxloc._core.compiler.jit`: the CPU options on an eager call (JAX rejects options
    on a nested jit), none inside a caller's `jit` or `vmap`; the same numbers."""
    import jaxloc
    from jaxloc._core import compiler

    assert jaxloc.compiler_options() == (
        compiler.CPU_OPTIONS if jax.default_backend() == "cpu" else {}
    )
    f = compiler.jit(lambda x: jnp.sin(x) * 2.0)
    x = jnp.linspace(0.0, 1.0, 4)
    eager = f(x)
    assert list(f._jitted) == [True]
    nested = jax.jit(f)(x)
    mapped = jax.vmap(f)(x)
    inlined = jax.jit(compiler.jit(inline=True)(lambda x: jnp.sin(x) * 2.0))(x)
    assert sorted(f._jitted) == [False, True]
    for y in (nested, mapped, inlined):
        np.testing.assert_allclose(y, eager, rtol=1e-15)
    lowered = f.lower(x)
    np.testing.assert_allclose(lowered.compile()(x), eager, rtol=1e-15)


def test_compiled_ahead_compiles_chained_calls_without_running_them():
    """`jaxloc.compiled_ahead`: inside the block an eager jaxloc call returns zeros of its
    outputs' shapes (so a second call can take them as inputs) and runs nothing; after
    it, the same calls run the programs compiled there, traced once, with the numbers of
    plain calls."""
    import jaxloc
    from jaxloc._core import compiler

    traces = []

    def first(x):
        traces.append("first")
        return {"y": jnp.sin(x) * 2.0, "n": jnp.sum(x > 0.5)}

    def second(out, scale):
        traces.append("second")
        return out["y"] * scale + out["n"]

    f, g = compiler.jit(first), compiler.jit(second)
    x = jnp.linspace(0.0, 1.0, 5)
    with jaxloc.compiled_ahead():
        out = f(x)
        assert isinstance(out["y"], np.ndarray) and out["y"].shape == (5,)
        assert out["n"].dtype == jnp.sum(x > 0.5).dtype and not np.any(out["y"])
        z = g(out, jnp.asarray(3.0))
        assert isinstance(z, np.ndarray) and not np.any(z)
    assert traces == ["first", "second"]
    compiled = []

    class Compilations(logging.Handler):
        def emit(self, record):
            if "Finished XLA compilation" in record.getMessage():
                compiled.append(record.getMessage())

    handler, logger = Compilations(), logging.getLogger("jax")
    logger.addHandler(handler)
    try:
        with jax.log_compiles():
            np.testing.assert_allclose(g(f(x), jnp.asarray(3.0)), np.sin(x) * 6.0 + 2, rtol=1e-6)
    finally:
        logger.removeHandler(handler)
    assert traces == ["first", "second"]  # the calls reused the programs: no new trace
    assert not [m for m in compiled if "first" in m or "second" in m], compiled  # nor compile
    with pytest.raises(RuntimeError, match="do not nest"):
        with jaxloc.compiled_ahead():
            with jaxloc.compiled_ahead():
                pass
    y = f(x)  # a failed block leaves eager calls eager
    assert not isinstance(y["y"], np.ndarray)
