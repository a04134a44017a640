"""A workaround for a crash of XLA:CPU in the jaxlib releases that have it."""

import importlib.metadata
import os


#: jaxlib releases whose XLA:CPU YNN fusions crash (SIGSEGV on an Eigen worker thread,
#: reported wherever the main thread happens to be) on some reductions:
#: https://github.com/jax-ml/jax/issues/39257 and /40412.
AFFECTED_JAXLIB = ("0.10.2", "0.11.0")
YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type="


def avoid_ynn_crash() -> bool:
    """Turn XLA:CPU's YNN fusions off through `XLA_FLAGS` when the installed jaxlib is
    affected and `XLA_FLAGS` does not choose already. Takes effect only if JAX's backend
    has not started yet. Returns whether the flag was added."""
    try:
        version = importlib.metadata.version("jaxlib")
    except importlib.metadata.PackageNotFoundError:
        return False
    flags = os.environ.get("XLA_FLAGS", "")
    if version not in AFFECTED_JAXLIB or "ynn_fusion_type" in flags:
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {YNN_FLAG}".strip()
    return True
