"""Traced programs kept on disk, so that a command's later runs skip Python tracing.

JAX's persistent compilation cache saves XLA's work, but each run still traces and
lowers its programs in Python to compute the cache key: for a study's chunk program that
is 9-14 s per strategy, most of a warm `jaxloc table1`. A [`Program`][] exports its
function once (`jax.export`: the traced and lowered StableHLO), keeps the export next to
the compilation cache, and in later processes deserializes it (milliseconds) instead of
tracing; its compilation then hits the compilation cache as before. The numbers are the
same bit for bit: the same StableHLO is compiled.

An export is reused only by a process that would trace the same program: its file name
is a digest of the program's name and static description, the shapes and dtypes of its
arguments, jaxloc's own source files, the versions of the libraries that write the
trace, the JAX settings that change it (`PROGRAM_CONFIG`) and the devices. Anything else
that shapes the trace must be in the static description the caller gives.

Programs are exported only when a persistent compilation cache is configured (the
`jaxloc` command does so by default; `jax_compilation_cache_dir`) and `flatbuffers`
(JAX's serialization format) is installed; otherwise a `Program` traces as a plain
`jax.jit` would, once per process.
"""

import functools as ft
import hashlib
import importlib.metadata
import os
import threading
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec, SingleDeviceSharding

from .files import atomic_write


#: JAX settings that change what a trace produces (dtypes, random bits, dot precision).
PROGRAM_CONFIG = (
    "jax_enable_x64",
    "jax_default_prng_impl",
    "jax_threefry_partitionable",
    "jax_default_matmul_precision",
    "jax_numpy_dtype_promotion",
)
#: Libraries whose code is traced into jaxloc's programs.
TRACED_LIBRARIES = ("jax", "jaxlib", "equinox", "optimistix", "lineax", "jaxlie", "numpy")
#: Subfolder of the compilation cache holding the exported programs.
FOLDER = "jaxloc-programs"


@ft.cache
def source_digest() -> str:
    """SHA-256 of every `.py` file of the installed jaxloc package (paths and contents)."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    h = hashlib.sha256()
    for folder, dirs, files in sorted(os.walk(root)):
        dirs.sort()
        for name in sorted(files):
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                h.update(os.path.relpath(path, root).encode())
                with open(path, "rb") as f:
                    h.update(hashlib.sha256(f.read()).digest())
    return h.hexdigest()


def _versions() -> str:
    out = []
    for lib in TRACED_LIBRARIES:
        try:
            out.append(f"{lib}={importlib.metadata.version(lib)}")
        except importlib.metadata.PackageNotFoundError:
            out.append(f"{lib}=?")
    return ",".join(out)


def describe(static: Any) -> str:
    """A deterministic text of a pytree of static values (structure, and every leaf's
    value; arrays by their values), for the `static` of [`program_key`][]."""
    leaves, tree = jax.tree.flatten(static)
    values = [np.asarray(x).tolist() if eqx.is_array(x) else x for x in leaves]
    return repr((str(tree), values))


def program_key(name: str, static: str, args: Any, devices=None) -> str:
    """Digest naming the export of program `name` with static description `static` (a
    deterministic text naming everything the function closes over that changes its
    trace, e.g. a scenario's static fields and a chunk size) called on `args` (arrays or
    shape-dtype structs) in this process's configuration, on `devices` (default: every
    local device)."""
    leaves, tree = jax.tree.flatten(args)
    avals = [(tuple(x.shape), str(x.dtype)) for x in leaves]
    config = [(c, str(getattr(jax.config, c))) for c in PROGRAM_CONFIG]
    devices = [(d.platform, d.device_kind) for d in (devices or jax.devices())]
    text = repr((name, static, str(tree), avals, config, devices, _versions(), source_digest()))
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def _store() -> str | None:
    """Folder of the exported programs, or `None` when exports are not kept."""
    cache = jax.config.jax_compilation_cache_dir
    if not cache:
        return None
    try:
        import flatbuffers  # noqa: F401  (JAX's serialization of exports needs it)
    except ImportError:
        return None
    return os.path.join(str(cache), FOLDER)


def _structs(args):
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), args)


def _load(path: str):
    try:
        with open(path, "rb") as f:
            return jax.export.deserialize(bytearray(f.read()))
    except Exception:  # noqa: BLE001  a missing, partial or foreign file: trace anew
        return None


def _save(path: str, exported) -> None:
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        atomic_write(path, bytes(exported.serialize()))
    except OSError:  # a read-only or remote cache: the next process traces again
        pass


class Program:
    """A jitted function of a pytree of arrays, exported once and reused across processes.

    **Arguments:**

    - `name`: the program's name (part of its file name).
    - `fn(args) -> outputs`: a pure function of one pytree of arrays (lists, tuples,
      dicts) returning a pytree of the same kinds; its static configuration is closed
      over, and described in `key`.
    - `key`: the [`program_key`][jaxloc._core.programs.program_key] of the program, its
      static description and `args`.
    - `args`: example arguments (arrays or `jax.ShapeDtypeStruct`), fixing the shapes.
    - `compiler_options`: XLA options for its compilation.
    - `replicated`: every argument replicated over all local devices (the program shards
      its work itself, e.g. with `shard_map`); `False`: the program runs on the default
      device alone.
 Call [`compile`][jaxloc._core.programs.Program.compile]
    ahead (e.g. in a thread) or let the first call compile it.
    """

    def __init__(
        self,
        name: str,
        fn: Callable,
        key: str,
        args: Any,
        *,
        compiler_options=None,
        replicated: bool = True,
    ):
        self.name = name
        if replicated:
            mesh = jax.sharding.Mesh(np.array(jax.devices()), ("devices",))
            self._sharding = NamedSharding(mesh, PartitionSpec())
        else:
            self._sharding = SingleDeviceSharding(jax.devices()[0])
        store = _store()
        path = None if store is None else os.path.join(store, f"{name}-{key}.jaxexport")
        self._example = self._replicated(_structs(args))
        exported = None if path is None or not os.path.exists(path) else _load(path)
        self.loaded = exported is not None
        if exported is None:
            exported = jax.export.export(jax.jit(fn))(self._example)
            if path is not None:
                _save(path, exported)
        self.exported = exported
        self._jitted = jax.jit(exported.call, compiler_options=compiler_options)
        self._compiled = None
        self._lock = threading.Lock()

    def _replicated(self, args):
        def put(x):
            if isinstance(x, jax.ShapeDtypeStruct):
                return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=self._sharding)
            return jax.device_put(x, self._sharding)

        return jax.tree.map(put, args)

    @property
    def out_avals(self):
        """Shapes and dtypes of the outputs (a pytree of `jax.core.ShapedArray`)."""
        return jax.tree.unflatten(self.exported.out_tree, self.exported.out_avals)

    def compile(self):
        """Compile the program (from the compilation cache when it holds it), once: e.g.
        in a thread while other work goes on. Returns the compiled program."""
        with self._lock:  # a second thread waits for the first one's compilation
            if self._compiled is None:
                self._compiled = self._jitted.lower(self._example).compile()
            return self._compiled

    def __call__(self, args):
        return self.compile()(self._replicated(args))


_PROGRAMS: dict[str, Program] = {}
_PROGRAMS_LOCK = threading.Lock()


def cached_program(
    name: str,
    make_fn: Callable[[], Callable],
    static: str,
    args: Any,
    *,
    compiler_options=None,
    replicated: bool = True,
) -> Program:
    """The [`Program`][jaxloc._core.programs.Program] `name` for `static` and the shapes
    of `args`, made once per process (`make_fn()` builds its function only then)."""
    devices = None if replicated else jax.devices()[:1]
    key = program_key(name, repr((static, replicated)), args, devices)
    with _PROGRAMS_LOCK:
        if key not in _PROGRAMS:
            _PROGRAMS[key] = Program(
                name, make_fn(), key, args, compiler_options=compiler_options,
                replicated=replicated,
            )  # fmt: skip
        return _PROGRAMS[key]


def clear_programs() -> None:
    """Forget this process's programs and their compiled code (as `jax.clear_caches()`
    does for JAX's own caches; they load again from disk when next used)."""
    with _PROGRAMS_LOCK:
        _PROGRAMS.clear()
