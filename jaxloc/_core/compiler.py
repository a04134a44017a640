"""XLA options for jaxloc's programs, and the jit of its eager entry points.

XLA:CPU spends most of a jaxloc program's compile time in LLVM, one fused kernel at a
time (~15 ms each). Its classic emitters, LLVM at -O1 and no YNNPACK fusions compile a
cycle's programs in about 60 % of the time and run them as fast (a first jitted
`localize_cycle` 16.1 s -> 10.7 s, `benchmarks/first_calls.py`); see [`CPU_OPTIONS`][]. The
options apply on the CPU backend only: [`compiler_options`][] gives none elsewhere.
"""

import contextlib
import functools as ft
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import equinox as eqx
import jax
import numpy as np


#: XLA options of jaxloc's programs on the CPU backend. XLA:CPU's newer fusion emitters
#: take ~25% longer to compile a cycle trial (measured on the paper's scenario, chunk of
#: 4096: 49 s -> 37 s concurrent, 34 s -> 30 s sequential) and run it no faster (6.3 s
#: -> 5.2 s, 4.3 s -> 4.3 s per chunk), so the classic emitters compile it. Most of the
#: rest is LLVM (~12 of 17 s for the sequential chunk), and LLVM's -O1 instead of the
#: default -O3 compiles the concurrent chunk (3456 trials) ~4 s faster and runs it as
#: fast (5.4-5.6 s vs 6.0 s), the sequential one ~4 s faster and 0.3 s slower per chunk
#: (2.7 s vs 2.4 s). XLA:CPU also hands some element-wise and reduction fusions to the
#: YNNPACK library by default; on a trial's small arrays the library's per-call overhead
#: outweighs its kernels: with `xla_cpu_experimental_ynn_fusion_type` empty (every fusion
#: compiled by XLA), chunks of 3392 paper-scenario trials on 2 CPU devices ran in 2.63 s
#: instead of 3.46 s (concurrent) and 1.20 s instead of 1.44 s (sequential), and compile
#: no slower (`benchmarks/study_programs.py --ab-ynn`). The last bits of the errors
#: differ (another summation order); `jaxloc table1` prints the same table. On
#: `jit(vmap(localize_cycle))` (sequential, batch 1024) they take lowering and compiling
#: from 32.0 to 19.2 CPU-s (20.8 to 14.7 s wall; 985 to 877 kernels), and the run from 767
#: to 763 us per cycle (`benchmarks/localize_kernels.py` without and with `--options`,
#: idle, at c8e4f73).
CPU_OPTIONS: dict[str, Any] = {
    "xla_cpu_use_fusion_emitters": False,
    "xla_backend_optimization_level": 1,
    "xla_cpu_experimental_ynn_fusion_type": "",
}


def compiler_options() -> dict[str, Any]:
    """XLA options for compiling jaxloc's programs on the default backend: [`CPU_OPTIONS`][]
    on the CPU, none elsewhere. Pass them to your own `jax.jit(...,
    compiler_options=jaxloc.compiler_options())` around jaxloc's functions."""
    return dict(CPU_OPTIONS) if jax.default_backend() == "cpu" else {}


try:  # JAX's own test for "not inside a transformation" (private; absent: no options)
    from jax._src.core import trace_state_clean as _top_level
except ImportError:  # pragma: no cover
    def _top_level() -> bool:
        return False


class _Jitted:
    """`eqx.filter_jit(fn, **kwargs)`, with `compiler_options=compiler_options()` when
    called outside any transformation (JAX accepts options on a top-level jit only),
    built at the first call (the backend is known then, not at import)."""

    def __init__(self, fn: Callable, kwargs: dict):
        self._fn, self._kwargs = fn, kwargs
        self._jitted: dict[bool, Any] = {}
        self._lock = threading.Lock()
        ft.update_wrapper(self, fn)

    def _get(self, top_level: bool):
        with self._lock:
            if top_level not in self._jitted:
                options = compiler_options() if top_level else {}
                self._jitted[top_level] = eqx.filter_jit(
                    self._fn, **self._kwargs, **({"compiler_options": options} if options else {})
                )
            return self._jitted[top_level]

    def __call__(self, *args, **kwargs):
        top_level = _top_level()
        ahead = getattr(_AHEAD, "pool", None)
        if top_level and ahead is not None:
            return _compile_in(ahead, self._get(True).lower(*args, **kwargs))
        return self._get(top_level)(*args, **kwargs)

    def lower(self, *args, **kwargs):
        return self._get(True).lower(*args, **kwargs)


_AHEAD = threading.local()


def _compile_in(ahead: tuple[ThreadPoolExecutor, list[Future]], lowered) -> Any:
    """Start compiling `lowered` (an `eqx` lowered program) in the pool; zeros of its
    outputs' shapes stand in for what it would return."""
    pool, pending = ahead
    pending.append(pool.submit(lowered.compile))
    zeros = jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), lowered.lowered.out_info)
    return lowered.postprocess(zeros)


@contextlib.contextmanager
def compiled_ahead(workers: int = 2) -> Iterator[None]:
    """Compile the programs of several eager calls side by side, without running them.

    Inside the block, a call of a [`jit`][] function outside any transformation (an eager
    entry point such as `localize_cycle` or `refine_cycle`, in this thread) traces and
    lowers its program, starts compiling it in one of `workers` threads and returns zeros
    of its outputs' shapes and dtypes instead of running it, so a call that takes an
    earlier call's outputs is lowered before the earlier program is compiled. Leaving the
    block waits for every compilation (and raises the first error); an exception inside
    it is raised at once. The same calls made afterwards with arguments of the same
    shapes and static values run the compiled programs (JAX keeps them per process, and
    in its persistent compilation cache when one is set). XLA compiles outside Python's
    lock, so two programs compile in about the time of the larger one:

    ```python
    with jaxloc.compiled_ahead():
        placeholder = jaxloc.localize_cycle(obs, rig, throw=False)  # zeros
        jaxloc.refine_cycle(obs, rig, placeholder, throw=False)
    estimate = jaxloc.localize_cycle(obs, rig, throw=False)  # runs, compiled
    refined = jaxloc.refine_cycle(obs, rig, estimate, throw=False)
    ```

    Only jaxloc's `jit` functions are deferred: any other JAX operation inside the block
    runs eagerly on the zeros, so keep only the calls to compile inside it.
    """
    if getattr(_AHEAD, "pool", None) is not None:
        raise RuntimeError("`compiled_ahead` blocks do not nest.")
    pending: list[Future] = []
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="jaxloc-compile")
    _AHEAD.pool = (pool, pending)
    try:
        yield
    except BaseException:  # e.g. Ctrl-C: raised at once, not after the compilations
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    finally:
        _AHEAD.pool = None
    pool.shutdown(wait=True)
    for future in pending:
        future.result()


def jit(fn: Callable | None = None, **kwargs) -> Any:
    """`eqx.filter_jit` with jaxloc's [`compiler_options`][], for the functions behind
    eager entry points (`localize_cycle`, `refine_cycle`, ...) and jaxloc's own large
    programs; inside a caller's `jax.jit` or `vmap` the caller's options apply.
    `jit(inline=True)` also inlines the function into a caller's trace. Usable as `@jit`
    or `@jit(inline=True)`."""
    if fn is None:
        return lambda f: _Jitted(f, kwargs)
    return _Jitted(fn, kwargs)
