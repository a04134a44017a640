import gc
import os
import random

import jax
import jax.random as jr
import pytest
from jaxloc._core.programs import clear_programs


jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
# JAX's persistent compilation cache, shared by every test process (the slow-test run,
# notebook and command-line subprocesses reuse what the default run compiled): most of
# the suite's time is XLA compilation of the same programs.
_XLA_CACHE = os.path.abspath(
    os.path.join(os.path.dirname(__file__), "..", ".pytest_cache", "xla")
)
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", _XLA_CACHE)
os.environ.setdefault("JAXLOC_COMPILE_CACHE", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
# The test processes (pytest-xdist's workers, the command-line and notebook subprocesses)
# share that cache at once. A size limit turns on JAX's file lock around every read and
# write of an entry, so no process reads an entry another is still writing. The limit
# itself (64 GiB) is never reached.
os.environ.setdefault("JAX_COMPILATION_CACHE_MAX_SIZE", str(64 * 2**30))
_MAX_SIZE = int(os.environ["JAX_COMPILATION_CACHE_MAX_SIZE"])
jax.config.update("jax_compilation_cache_max_size", _MAX_SIZE)



@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop every compiled program after each test module. Each executable keeps its
    machine code in memory mappings (thousands per study-sized program); one process
    running the whole suite would pass the kernel's limit (`vm.max_map_count`, 65530)
    and XLA would crash in `mmap`. Later modules reload what they share from the
    persistent compilation cache."""
    yield
    jax.clear_caches()
    clear_programs()
    gc.collect()


SHARED = os.path.join(os.path.dirname(__file__), "..", "..", "shared")


@pytest.fixture
def getkey():
    seed = random.randint(0, 2**31 - 1)
    print(f"getkey seed: {seed}")
    keys = iter(jr.split(jr.key(seed), 1000))
    return lambda: next(keys)
