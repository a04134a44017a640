"""Studies on a Ray cluster: each chunk of a study one Ray task (DESIGN §5, scale-out).

A chunk is [`jaxloc.run_chunk`][]: deterministic, trial `i` keyed by
`fold_in(key(seed), i)`, so a task that fails and is retried (Ray's `max_retries`: a
worker process that dies, a node that is lost) returns the same numbers, and the study
does not depend on which machine ran which chunk. The driver (this process) submits the
chunks, keeps a bounded number in flight, and hands them to the engine in order
([`jaxloc._study.engine.study_chunks`][]): the same resumable `out_dir` folder (chunk
files written and verified by the driver) and the same summaries as a local study.

Every worker runs JAX with the driver's float64 setting, as many CPU devices as its task
reserves CPUs (`cpus_per_task`, default 1) and, when the driver has one, the same
persistent compilation cache folder: a worker compiles the chunk program once (or loads
it from the cache) and reuses it for every chunk it runs. The numbers equal a local
study's on the same number of JAX devices to the last bit; on another device count they
agree to round-off, as local studies on different device counts do.

The same pieces run any other list of independent, deterministic tasks ([`map_on_ray`][]),
e.g. the groups of starts of a formation design (`jaxloc._design.cluster`).

Ray is optional (`pip install "jaxloc[cluster]"`); it is imported only here.
"""

from collections.abc import Callable, Iterator, Sequence
from typing import Any

import jax
import numpy as np

from .._sim.scenario import Scenario
from .engine import (
    ChunkRunner,
    concatenate_chunks,
    run_chunk,
    study_chunks,
    summarize_chunks,
)
from .trial import METHODS


#: Retries of a failed chunk task (worker process died, node lost) before the study fails.
MAX_RETRIES = 3


class ClusterError(RuntimeError):
    """A task (a study's chunk, a design's group of starts) failed on the cluster after
    its retries, or the cluster could not be reached."""


def _ray():
    try:
        import ray
    except ImportError:
        raise ClusterError(
            "Ray is not installed: `pip install \"jaxloc[cluster]\"` (or `pip install ray`)."
        ) from None
    return ray


def connect(address: str | None = None) -> bool:
    """Connect this process to a Ray cluster: the one at `address` (e.g.
    `"ray://head:10001"` or `"head:6379"`; `"auto"`: the cluster this machine belongs to),
    or, with `address=None`, a new local cluster with one worker per core. Does nothing if
    Ray is already initialized. Returns whether this call started Ray (then
    [`disconnect`][] stops it)."""
    ray = _ray()
    if ray.is_initialized():
        return False
    import logging
    import warnings

    # Ray's start-up notes (e.g. that a command's worker thread cannot take SIGTERM) are
    # not the user's business; its errors are, as exceptions.
    kwargs: dict[str, Any] = dict(log_to_driver=False, logging_level=logging.ERROR)
    try:
        with warnings.catch_warnings():
            # Ray starts its processes with fork + exec (subprocess), which JAX's fork
            # warning cannot tell from a bare fork.
            warnings.filterwarnings("ignore", "os.fork", RuntimeWarning)
            if address is None:
                ray.init(include_dashboard=False, **kwargs)
            else:
                ray.init(address=address, **kwargs)
    except (ConnectionError, RuntimeError, ValueError) as e:
        where = "a local Ray cluster" if address is None else f"the Ray cluster at `{address}`"
        raise ClusterError(f"cannot start or reach {where}: {' '.join(str(e).split())}") from None
    return True


def disconnect() -> None:
    """Disconnect from Ray (stopping a local cluster this process started)."""
    ray = _ray()
    if ray.is_initialized():
        ray.shutdown()


def describe_cluster() -> str:
    """One line: the cluster's CPUs and nodes, e.g. `Ray cluster: 2 CPUs on 1 node`."""
    ray = _ray()
    cpus = int(ray.cluster_resources().get("CPU", 0))
    nodes = sum(1 for n in ray.nodes() if n.get("Alive"))
    return f"Ray cluster: {cpus} CPUs on {nodes} node{'s' if nodes != 1 else ''}"


def cluster_cpus() -> int:
    """The CPUs of the connected Ray cluster (at least 1)."""
    return max(1, int(_connected_ray().cluster_resources().get("CPU", 1)))


def _connected_ray():
    """The `ray` module, once this process is connected to a cluster."""
    ray = _ray()
    if not ray.is_initialized():
        raise ClusterError("Ray is not initialized: call `connect()` first.")
    return ray


def _worker_env(cpus_per_task: int) -> dict[str, str]:
    """Environment of the worker processes: JAX configured like this process (float64
    mode, compilation cache) with `cpus_per_task` CPU devices. Set before the worker
    imports JAX, so that the scenario's arrays arrive in the driver's dtype."""
    env = {
        "JAX_ENABLE_X64": "1" if jax.config.jax_enable_x64 else "0",
        "JAX_NUM_CPU_DEVICES": str(cpus_per_task),
    }
    cache = jax.config.jax_compilation_cache_dir
    if cache:
        env["JAX_COMPILATION_CACHE_DIR"] = str(cache)
    return env


def _remote(fn: Callable, cpus_per_task: int, max_retries: int):
    """`fn` as a Ray remote function: `cpus_per_task` CPUs per task, JAX in the worker
    configured like this process ([`_worker_env`][]), a task whose worker dies retried
    `max_retries` times."""
    if cpus_per_task < 1:
        raise ValueError(f"`cpus_per_task` must be a positive integer; got {cpus_per_task!r}.")
    return _connected_ray().remote(fn).options(
        num_cpus=cpus_per_task,
        max_retries=max_retries,
        retry_exceptions=False,  # a Python error is a bug, the same on every attempt
        runtime_env={"env_vars": _worker_env(cpus_per_task)},
    )


def _default_in_flight(cpus_per_task: int) -> int:
    """Twice the tasks the cluster runs at once, at least 2."""
    return max(2, 2 * cluster_cpus() // cpus_per_task)


def ray_runner(
    scenario: Scenario,
    seed: int,
    chunk_size: int,
    methods: Sequence[str],
    *,
    cpus_per_task: int = 1,
    max_retries: int = MAX_RETRIES,
    max_in_flight: int | None = None,
    task: Callable[..., dict[str, np.ndarray]] | None = None,
) -> ChunkRunner:
    """A [`ChunkRunner`][jaxloc._study.engine.ChunkRunner] that runs each chunk as one
    Ray task on the connected cluster ([`connect`][]).

    **Arguments:**

    - `scenario`, `seed`, `chunk_size`, `methods`: the study's, as for
      [`jaxloc.run_chunk`][]. The scenario is put in Ray's object store once.
    - `cpus_per_task`: CPUs each task reserves, and JAX CPU devices its worker exposes.
    - `max_retries`: retries of a task whose worker died (Ray's `max_retries`).
    - `max_in_flight`: most chunks submitted and not yet handed to the study (bounds the
      driver's and the object store's memory); default twice the cluster's CPUs divided
      by `cpus_per_task`, at least 2.
    - `task`: the function a task runs, with [`jaxloc.run_chunk`][]'s arguments (default:
      `run_chunk`); e.g. a wrapper that logs, or one that fails on purpose in a test.
    """
    ray = _connected_ray()
    remote = _remote(task or run_chunk, cpus_per_task, max_retries)
    if max_in_flight is None:
        max_in_flight = _default_in_flight(cpus_per_task)
    scenario_ref = ray.put(scenario)
    methods = tuple(methods)

    def submit(c: int):
        return remote.remote(scenario_ref, seed, c, chunk_size, methods)

    def run(chunks: Sequence[int], on_done: Callable[[], None]) -> Iterator[dict]:
        queue = list(chunks)
        refs = _submit_first(queue, submit, max_in_flight)  # at once, before iteration
        return _in_order(ray, chunks, queue, refs, submit, on_done, max_retries)

    return run


def _call(fn: Callable[[Any], Any], item: Any) -> Any:
    """A task of [`map_on_ray`][]: `fn(item)` (Ray hands `fn` over from its object store)."""
    return fn(item)


def map_on_ray(
    fn: Callable[[Any], Any],
    items: Sequence[Any],
    *,
    cpus_per_task: int = 1,
    max_retries: int = MAX_RETRIES,
    max_in_flight: int | None = None,
) -> list:
    """`[fn(item) for item in items]`, each call one Ray task on the connected cluster
    ([`connect`][]), results in the order of `items`.

    `fn` must be deterministic and picklable (a module-level function, or a
    `functools.partial` of one: it is put in Ray's object store once, with what it holds,
    e.g. a scenario). Tasks run as the study's chunks do ([`ray_runner`][]): JAX in each
    worker configured like this process, `cpus_per_task` CPUs (and JAX devices) per task,
    a task whose worker dies retried `max_retries` times, at most `max_in_flight` tasks
    submitted and not yet collected (default: twice the cluster's CPUs divided by
    `cpus_per_task`). A task that still fails raises [`ClusterError`][].
    """
    ray = _connected_ray()
    remote = _remote(_call, cpus_per_task, max_retries)
    if max_in_flight is None:
        max_in_flight = _default_in_flight(cpus_per_task)
    fn_ref = ray.put(fn)

    def submit(i: int):
        return remote.remote(fn_ref, items[i])

    order = range(len(items))
    queue = list(order)
    refs = _submit_first(queue, submit, max_in_flight)
    return list(_in_order(ray, order, queue, refs, submit, lambda: None, max_retries))


def _submit_first(queue: list, submit: Callable, max_in_flight: int) -> dict:
    """Submit the first `max_in_flight` tasks of `queue` (removed from it). Returns
    `{index: task}`, the submitted tasks not yet handed over."""
    refs = {}
    while queue and len(refs) < max_in_flight:
        i = queue.pop(0)
        refs[i] = submit(i)
    return refs


def _in_order(ray, chunks, queue, refs, submit, on_done, max_retries) -> Iterator[dict]:
    """Hand over the chunk tasks' results in the order of `chunks`, calling `on_done` as
    each task finishes (in any order) and submitting the next of `queue` as each result
    is handed over. `refs` maps each submitted chunk to its task (updated in place).
    A task's failure cancels the others and raises `ClusterError`."""
    finished: set[int] = set()
    try:
        for want in chunks:
            while want not in finished:
                if not ray.is_initialized():  # else Ray's next call would start a
                    # new local cluster (its auto-init)
                    raise ClusterError("disconnected from the Ray cluster.")
                waiting = [r for c, r in refs.items() if c not in finished]
                ready, _ = ray.wait(waiting, num_returns=1, timeout=1.0)
                for c, r in refs.items():
                    if r in ready:
                        finished.add(c)
                        on_done()
            arrays = ray.get(refs.pop(want))
            finished.discard(want)
            if queue:
                c = queue.pop(0)
                refs[c] = submit(c)
            yield arrays
    except ray.exceptions.RayError as e:
        if ray.is_initialized():
            for r in refs.values():
                ray.cancel(r, force=True)
        raise ClusterError(
            f"a task failed on the Ray cluster (a lost worker is retried "
            f"{max_retries} times, a Python error is not): "
            f"{' '.join(str(e).split())[:300]}"
        ) from None


def run_study_on_ray(
    scenario: Scenario,
    n_trials: int,
    *,
    seed: int = 0,
    chunk_size: int = 4096,
    methods: tuple[str, ...] = METHODS,
    out_dir: str | None = None,
    progress: bool = True,
    on_chunk: Callable[[int, dict], None] | None = None,
    cpus_per_task: int = 1,
    max_retries: int = MAX_RETRIES,
    task: Callable[..., dict[str, np.ndarray]] | None = None,
) -> dict[str, np.ndarray]:
    """[`jaxloc.run_study`][] with every chunk a task on the connected Ray cluster.

    Same arguments, same result, same `out_dir` folder (resumable: a study started
    locally can finish on the cluster and the other way round); connect first with
    `jaxloc._study.cluster.connect(address)` (or `ray.init`). The progress bar counts
    the chunks finished anywhere on the cluster. `cpus_per_task`, `max_retries` and
    `task`: see `jaxloc._study.cluster.ray_runner`. A task that still fails after its
    retries raises `jaxloc._study.cluster.ClusterError`; the chunks finished until then
    are in `out_dir`.
    """
    runner = ray_runner(scenario, seed, chunk_size, methods, cpus_per_task=cpus_per_task,
                        max_retries=max_retries, task=task)  # fmt: skip
    chunks = study_chunks(
        scenario, n_trials, seed, chunk_size, methods, out_dir, progress, runner=runner
    )
    return concatenate_chunks(chunks, on_chunk)


def stream_study_on_ray(
    scenario: Scenario,
    n_trials: int,
    *,
    seed: int = 0,
    chunk_size: int = 4096,
    methods: tuple[str, ...] = METHODS,
    out_dir: str | None = None,
    progress: bool = True,
    cpus_per_task: int = 1,
    max_retries: int = MAX_RETRIES,
    task: Callable[..., dict[str, np.ndarray]] | None = None,
) -> dict:
    """[`jaxloc.stream_study`][] with every chunk a task on the connected Ray cluster:
    the same summary, in bounded memory (at most a few chunks per cluster CPU are held
    at once). Arguments as [`jaxloc.run_study_on_ray`][]."""
    runner = ray_runner(scenario, seed, chunk_size, methods, cpus_per_task=cpus_per_task,
                        max_retries=max_retries, task=task)  # fmt: skip
    chunks = study_chunks(
        scenario, n_trials, seed, chunk_size, methods, out_dir, progress, runner=runner
    )
    return summarize_chunks(chunks, methods)

