"""Monte Carlo engine: many trials of a scenario, chunked, sharded, streamed to disk.

Trial `i` of a study with seed `s` always uses the key `jax.random.fold_in(key(s), i)`, so
the numbers do not depend on the chunk size, on the number of devices, or on which
machine ran which chunk. Each chunk is one `jit(vmap(run_trial))` call whose trials are
sharded over every local device; memory stays bounded by the chunk size whatever the
number of trials.

On disk a study is a folder: `study.json` (what was run: scenario, seed, chunk size,
methods) and one `chunk_NNNNNN.npz` per chunk, each written atomically
(`jaxloc._study.chunks`). Running the same study again resumes: finished chunks are read
back and verified (trial indices, seed, study hash, shapes and dtypes), missing or damaged
ones are computed; no trial is lost or duplicated.
"""

import os
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jax.sharding import Mesh, PartitionSpec
from jaxtyping import Array

from .._core.compiler import compiler_options, jit
from .._core.programs import cached_program, describe, Program
from .._sim.scenario import Scenario
from .._sim.scenario_file import scenario_to_dict
from .chunks import (
    check_seed,
    chunk_path,
    open_study,
    read_chunk,
    study_manifest,
    write_chunk,
)
from .stats import StreamingSummary
from .trial import ALL_METHODS, METHODS, run_trial


FIELDS = (
    "status", "gated", "position", "rotation", "ypr", "position_vector",
    "crlb_position_var", "crlb_rotation_var", "crlb_position_sample",
    "crlb_rotation_sample", "nees",
)


def trial_key(seed: int, index):
    """Key of trial `index` of a study seeded with `seed` (the same on any machine)."""
    return jr.fold_in(jr.key(seed), index)


def _mesh() -> Mesh:
    return Mesh(np.array(jax.devices()), ("trials",))


MICRO_BATCH = 32
"""Trials per vectorized step inside a chunk. Each device walks its share of a chunk in
`lax.map` steps of this many `vmap`-ed trials: the working set of a step stays in cache,
and an iterative solver's batch waits only for the slowest of these trials, not of the
whole chunk (DESIGN §8). Chunks of ~3400 paper-scenario trials on 2 CPU devices ran in
3.2 / 3.3 / 3.6 s (concurrent) and 1.4 / 1.4 / 1.7 s (sequential) with steps of 16 /
32 / 64: smaller steps wait for fewer stragglers of the refinement, larger ones
vectorize better. A CPU setting: an accelerator wants the whole chunk in one step."""


def map_trials(trial: Callable[[Array], Any], start, chunk_size: int) -> Any:
    """`trial(i)` for every `i` in `start + [0, chunk_size)` (`chunk_size` a multiple of
    the device count), stacked: the trials sharded over every local device, each device
    walking its share in `lax.map` steps of `MICRO_BATCH` trials. For use inside a jitted
    chunk program (this module's, `jaxloc._track.study`'s)."""
    mesh = _mesh()
    indices = start + jnp.arange(chunk_size)

    def local(indices):
        return jax.lax.map(trial, indices, batch_size=min(MICRO_BATCH, indices.shape[0]))

    spec = PartitionSpec("trials")
    # check_vma=False: the trial code is written per trial, unaware of the device axis.
    return jax.shard_map(local, mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False)(
        indices
    )


def _chunk_trials(scenario: Scenario, seed, start, chunk_size: int, methods: tuple[str, ...]):
    return map_trials(
        lambda i: run_trial(scenario, jr.fold_in(jr.key(seed), i), methods), start, chunk_size
    )


#: The chunk program as a plain jitted function (benchmarks lower it directly).
_run_chunk = jit(_chunk_trials)


def chunk_program(
    name: str,
    trial: Callable[[Any, Array], Any],
    scenario: eqx.Module,
    chunk_size: int,
    static: str,
    fields: Sequence[str],
) -> Program:
    """The chunk program of a study: `trial(scenario, key)` of trials `start + [0, n)`,
    `n` the chunk size rounded up to a multiple of the device count, each keyed
    `fold_in(key(seed), i)` and sharded by [`map_trials`][]. Traced once per scenario
    structure, chunk size and `static` (the text naming the rest of what `trial` closes
    over) and kept beside the compilation cache (`jaxloc._core.programs`), so that a later
    process loads it instead of tracing it again.

    `program(chunk_inputs(scenario, seed, start))` returns a dict of the record's `fields`,
    each with a leading axis of `n`."""
    n_dev = jax.device_count()
    padded = -(-chunk_size // n_dev) * n_dev
    dynamic, rest = eqx.partition(scenario, eqx.is_array)
    arrays, tree = jax.tree.flatten(dynamic)

    def make_fn():
        def chunk(args):
            arrays, seed, start = args
            sc = eqx.combine(jax.tree.unflatten(tree, arrays), rest)
            record = map_trials(lambda i: trial(sc, jr.fold_in(jr.key(seed), i)), start, padded)
            return {f: getattr(record, f) for f in fields}

        return chunk

    description = repr((describe(rest), str(tree), padded, static, tuple(fields)))
    args = (arrays, jax.ShapeDtypeStruct((), jnp.uint32), jax.ShapeDtypeStruct((), jnp.int32))
    return cached_program(
        name, make_fn, description, args, compiler_options=compiler_options()
    )


def chunk_inputs(scenario: eqx.Module, seed: int, start: int):
    """The arguments of a [`chunk_program`][] call: the scenario's arrays, the seed and
    the first trial index."""
    arrays = jax.tree.leaves(eqx.filter(scenario, eqx.is_array))
    return arrays, jnp.asarray(seed, jnp.uint32), jnp.asarray(start, jnp.int32)


def _study_program(scenario: Scenario, chunk_size: int, methods) -> Program:
    methods = tuple(methods)
    trial = lambda sc, key: run_trial(sc, key, methods)  # noqa: E731
    return chunk_program("study_chunk", trial, scenario, chunk_size, repr(methods), FIELDS)


def balanced_chunk_size(n_trials: int, max_chunk_size: int = 4096) -> int:
    """Chunk size that covers `n_trials` in the fewest chunks of about `max_chunk_size`
    trials or fewer, with the least padding: a study always computes whole chunks, so
    10,000 trials in chunks of 4096 would compute 12,288. Rounded up to a multiple of
    `MICRO_BATCH` times the device count (each device's `lax.map` then has no remainder
    step, which would compile the trial a second time); e.g. 10,000 trials on 2 devices:
    3 chunks of 3392."""
    if n_trials <= 0 or max_chunk_size <= 0:
        raise ValueError(
            f"`n_trials` and `max_chunk_size` must be positive; got {n_trials!r}, "
            f"{max_chunk_size!r}."
        )
    quantum = MICRO_BATCH * jax.device_count()
    if max_chunk_size < quantum:
        return max_chunk_size
    n_chunks = -(-n_trials // max_chunk_size)
    per_chunk = -(-n_trials // n_chunks)
    return -(-per_chunk // quantum) * quantum


def _chunk_inputs(scenario: Scenario, seed: int, start: int, chunk_size: int, methods):
    n_dev = jax.device_count()
    padded = -(-chunk_size // n_dev) * n_dev
    # seed and start are passed as arrays so that every chunk reuses one compilation.
    return (
        scenario, jnp.asarray(seed, jnp.uint32), jnp.asarray(start, jnp.int32), padded,
        tuple(methods),
    )


def precompile(
    scenarios: Sequence[Scenario],
    chunk_size: int = 4096,
    methods: tuple[str, ...] = METHODS,
) -> None:
    """Compile the chunk programs of several studies at once, before running them.

    Tracing and lowering are Python and run one study after the other; XLA's compilations
    release the GIL and run in parallel threads, one per study. On a machine with as many
    cores as studies, all compile in about the time of the slowest one. Later
    [`jaxloc.run_study`][] / [`jaxloc.run_chunk`][] calls with the same scenario, chunk
    size and methods reuse the compiled programs (they do not depend on seed or chunk).
    """
    for compiling in compile_in_background(scenarios, chunk_size, methods):
        compiling.join()


def compile_in_background(
    scenarios: Sequence[Scenario],
    chunk_size: int = 4096,
    methods: tuple[str, ...] = METHODS,
) -> list[threading.Thread]:
    """Start compiling the chunk programs of several studies; return at once.

    Traces the studies one after the other, in the given order, and hands each program to
    its own thread as soon as it is traced: the first one compiles while the next ones
    are traced. Returns the threads, in the same order; `join` a study's thread before
    running it, and the run reuses its program (as after [`jaxloc.precompile`][]). A
    study can then run while the others are still compiling: put the one that compiles
    fastest first.
    """
    threads = []
    for scenario in scenarios:
        program = _study_program(scenario, chunk_size, methods)
        thread = threading.Thread(target=program.compile, daemon=True)
        thread.start()
        threads.append(thread)
    return threads


def run_chunk(
    scenario: Scenario,
    seed: int,
    chunk_index: int,
    chunk_size: int,
    methods: tuple[str, ...] = METHODS,
) -> dict[str, np.ndarray]:
    """Run one chunk of a study: trials `chunk_index * chunk_size + [0, chunk_size)`.

    This is the unit of work to hand to a cluster engine (one task per chunk; see the
    README's "Studies larger than one machine"). Deterministic: a retried task returns
    the same numbers. `chunk_size` is rounded up to a multiple of the device count
    internally and the padding trials are dropped.

    **Returns:** a dict of numpy arrays, the fields of [`jaxloc.TrialErrors`][] with a
    leading trial axis, plus `"index"` (the trial indices).
    """
    start = chunk_index * chunk_size
    errors = _study_program(scenario, chunk_size, methods)(chunk_inputs(scenario, seed, start))
    out = {name: np.asarray(errors[name])[:chunk_size] for name in FIELDS}
    out["index"] = np.arange(start, start + chunk_size, dtype=np.int64)
    return out


def chunk_fields(
    scenario: Scenario, chunk_size: int, methods: tuple[str, ...]
) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """Shape and dtype of every array [`jaxloc.run_chunk`][] returns for this study, as
    `name -> (shape, dtype)`: what a chunk file must hold. From the chunk program (traced
    or loaded once: a later compilation reuses it)."""
    out = _study_program(scenario, chunk_size, methods).out_avals
    fields = {n: ((chunk_size, *out[n].shape[1:]), np.dtype(out[n].dtype)) for n in FIELDS}
    fields["index"] = ((chunk_size,), np.dtype(np.int64))
    return fields


def _check_study_args(n_trials, chunk_size, methods, seed) -> tuple[str, ...]:
    if not isinstance(n_trials, int) or n_trials <= 0:
        raise ValueError(f"`n_trials` must be a positive integer; got {n_trials!r}.")
    if not isinstance(chunk_size, int) or chunk_size <= 0:
        raise ValueError(f"`chunk_size` must be a positive integer; got {chunk_size!r}.")
    unknown = [m for m in methods if m not in ALL_METHODS]
    if unknown or not methods:
        raise ValueError(
            f"`methods` must be a non-empty subset of {ALL_METHODS}; got {methods!r}."
        )
    check_seed(seed)
    return tuple(methods)


ChunkRunner = Callable[[Sequence[int], Callable[[], None]], Iterator[dict[str, np.ndarray]]]
"""Computes a study's chunks: called with the indices of the chunks to compute (in
order) and `on_done`, it returns an iterator over their arrays (as
[`jaxloc.run_chunk`][] returns them) in that order, and calls `on_done()` whenever a
chunk finishes, in whatever order they finish. [`local_runner`][] computes them here, one
after the other; `jaxloc._study.cluster` as Ray tasks."""


def local_runner(scenario: Scenario, seed: int, chunk_size: int, methods) -> ChunkRunner:
    """The [`ChunkRunner`][] that computes each chunk in this process, when asked for."""

    def run(chunks: Sequence[int], on_done: Callable[[], None]):
        for c in chunks:
            arrays = run_chunk(scenario, seed, c, chunk_size, methods)
            on_done()
            yield arrays

    return run


def stream_chunks(
    n_trials: int,
    chunk_size: int,
    runner: ChunkRunner,
    out_dir: str | None,
    manifest: dict | None,
    expected: Callable[[], dict[str, tuple[tuple[int, ...], np.dtype]]],
    progress: bool,
) -> Iterator[dict[str, np.ndarray]]:
    """Yield a chunked study's chunks' arrays in order (the last one cut to `n_trials`):
    read back from `out_dir` (a study opened with `manifest`) when a previous run wrote
    them and they pass the checks of `jaxloc._study.chunks` against `expected()` (`name ->
    (shape, dtype)`), else computed by `runner` and written there. Any study with chunk
    files uses it ([`study_chunks`][], `jaxloc._track.study`)."""
    n_chunks = -(-n_trials // chunk_size)
    paths = [None if out_dir is None else chunk_path(out_dir, c) for c in range(n_chunks)]
    todo = [c for c in range(n_chunks) if paths[c] is None or not os.path.exists(paths[c])]
    to_compute = set(todo)
    bar = ProgressBar(progress, n_trials, n_chunks)
    on_done = bar.chunk_done if bar is not None else (lambda: None)
    computed = runner(todo, on_done)
    fields = None
    done = 0
    t0 = time.perf_counter()
    for c in range(n_chunks):
        size = min(chunk_size, n_trials - c * chunk_size)
        if c in to_compute:
            arrays = next(computed)
        else:
            fields = fields or expected()
            arrays = read_chunk(paths[c], fields, c * chunk_size, manifest)
            if arrays is not None:
                on_done()
            else:  # damaged: recomputed (whole, so a resumed, longer study gets the same trials)
                arrays = next(iter(runner([c], on_done)))
                write_chunk(paths[c], arrays, manifest)
        if c in to_compute and paths[c] is not None:
            write_chunk(paths[c], arrays, manifest)
        arrays = {k: v[:size] for k, v in arrays.items()}
        done += size
        if bar is not None:
            bar.advance(size, done / max(time.perf_counter() - t0, 1e-9))
        yield arrays
    if bar is not None:
        bar.close()


def study_chunks(
    scenario: Scenario,
    n_trials: int,
    seed: int,
    chunk_size: int,
    methods: tuple[str, ...],
    out_dir: str | None,
    progress: bool,
    runner: ChunkRunner | None = None,
) -> Iterator[dict[str, np.ndarray]]:
    """Validate a study's settings, then yield its chunks' arrays in order: read back
    from `out_dir` when a previous run wrote them and they pass the checks of
    `jaxloc._study.chunks`, else computed by `runner` (default: [`local_runner`][]) and
    written to `out_dir`."""
    methods = _check_study_args(n_trials, chunk_size, methods, seed)
    runner = runner or local_runner(scenario, seed, chunk_size, methods)
    manifest = None
    if out_dir is not None:  # only a study on disk needs the scenario's file form
        manifest = study_manifest(scenario_to_dict(scenario), seed, chunk_size, methods)
        open_study(out_dir, manifest)
    yield from stream_chunks(
        n_trials, chunk_size, runner, out_dir, manifest,
        lambda: chunk_fields(scenario, chunk_size, methods), progress,
    )  # fmt: skip


def run_study(
    scenario: Scenario,
    n_trials: int,
    *,
    seed: int = 0,
    chunk_size: int = 4096,
    methods: tuple[str, ...] = METHODS,
    out_dir: str | None = None,
    progress: bool = True,
    on_chunk: Callable[[int, dict], None] | None = None,
) -> dict[str, np.ndarray]:
    """Run `n_trials` trials of `scenario` and return their errors.

    **Arguments:**

    - `scenario`: a [`jaxloc.Scenario`][].
    - `n_trials`: number of trials (any positive int; the last chunk is partial).
    - `seed`: the study's seed, an integer in `[0, 2**32 - 1]`; trial `i` uses
      `fold_in(key(seed), i)`.
    - `chunk_size`: trials per compiled call; bounds the working memory. Results do not
      depend on it.
    - `methods`: estimators to compare on the same observations (see `jaxloc.METHODS`).
    - `out_dir`: if given, every chunk is written there as it finishes, and a study
      already present there is resumed (it must have the same scenario, seed, chunk size
      and methods, or a `ValueError` says which differs); a damaged chunk file is
      recomputed with a one-line warning.
    - `progress`: show a progress bar with trials/s.
    - `on_chunk`: optional callback `(chunk_index, arrays)` after each chunk.

    **Returns:** dict of numpy arrays with a leading axis of `n_trials` (about 360 bytes
    per trial with the three default methods; for studies too large to hold, use
    [`jaxloc.stream_study`][]): `"status"` `(n, methods)`, `"position"`, `"rotation"`
    `(n, methods, 4)`, `"ypr"`, `"position_vector"` `(n, methods, 4, 3)`, `"index"` `(n,)`.
    """
    chunks = study_chunks(scenario, n_trials, seed, chunk_size, methods, out_dir, progress)
    return concatenate_chunks(chunks, on_chunk)


def stream_study(
    scenario: Scenario,
    n_trials: int,
    *,
    seed: int = 0,
    chunk_size: int = 4096,
    methods: tuple[str, ...] = METHODS,
    out_dir: str | None = None,
    progress: bool = True,
) -> dict:
    """Run a study of any size in bounded memory and return its summary.

    The same trials, chunks, resumption and `out_dir` files as [`jaxloc.run_study`][]
    (same arguments), but no chunk is kept in memory: each is folded into a
    [`jaxloc.StreamingSummary`][] (exact means, RMSEs, failure counts, Cramér–Rao and
    NEES means; percentiles from histograms, within 1.2%) and dropped. Memory is that of
    one chunk's computation, whatever `n_trials`; with `out_dir`, every trial's errors
    are also on disk.

    **Returns:** [`jaxloc.summarize`][]'s dict, plus `"percentiles": "histogram"`.
    """
    chunks = study_chunks(scenario, n_trials, seed, chunk_size, methods, out_dir, progress)
    return summarize_chunks(chunks, methods)


def concatenate_chunks(
    chunks: Iterator[dict[str, np.ndarray]], on_chunk: Callable[[int, dict], None] | None = None
) -> dict[str, np.ndarray]:
    """A study's chunks (from [`study_chunks`][]) joined along the trial axis, calling
    `on_chunk(chunk_index, arrays)` after each: [`jaxloc.run_study`][]'s result."""
    gathered = []
    for c, arrays in enumerate(chunks):
        gathered.append(arrays)
        if on_chunk is not None:
            on_chunk(c, arrays)
    return {k: np.concatenate([ch[k] for ch in gathered]) for k in gathered[0]}


def summarize_chunks(chunks: Iterator[dict[str, np.ndarray]], methods) -> dict:
    """A study's chunks folded one by one into a [`jaxloc.StreamingSummary`][]:
    [`jaxloc.stream_study`][]'s result."""
    summary = StreamingSummary(tuple(methods))
    for arrays in chunks:
        summary.update(arrays)
    return summary.result()


class ProgressBar:
    """A rich progress bar showing trials, trials/s and chunks finished (or nothing if
    disabled). Chunks may finish out of order (on a cluster): the bar counts trials as
    they reach the study in order, and chunks as they finish anywhere."""

    def __new__(cls, enabled: bool, total: int, n_chunks: int):
        if not enabled:
            return None
        return super().__new__(cls)

    def __init__(self, enabled: bool, total: int, n_chunks: int):
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

        self._p = Progress(
            TextColumn("trials"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[rate]}"),
            TextColumn("{task.fields[chunks]}"),
            transient=True,
        )
        self._p.start()
        self._n_chunks, self._chunks_done = n_chunks, 0
        self._task = self._p.add_task("trials", total=total, rate="", chunks=self._chunks_text())

    def _chunks_text(self) -> str:
        return f"chunks done {self._chunks_done}/{self._n_chunks}"

    def chunk_done(self):
        self._chunks_done += 1
        self._p.update(self._task, chunks=self._chunks_text())

    def advance(self, n: int, rate: float):
        self._p.update(self._task, advance=n, rate=f"{rate:,.0f} trials/s")

    def close(self):
        self._p.stop()
