"""Batching a single-problem function over the host devices, in cache-sized `vmap` steps."""

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np


def map_problems(fn: Callable, *, batch_size: int = 128, devices=None) -> Callable:
    r"""Batch a single-problem function the fast way on CPU: shard the problems over the
    host devices and walk each device's share in `lax.map` steps of `batch_size` problems
    `vmap`-ed together.

    `jax.jit(jax.vmap(fn))` runs every problem on one core, and an iterative solver's whole
    batch waits for its slowest problem; small `vmap`-ed steps keep the working set in
    cache and let each step stop with its own slowest problem (DESIGN §8: ~2x for
    element-wise kernels), and `shard_map` over the devices uses every core that XLA
    exposes (set `XLA_FLAGS=--xla_force_host_platform_device_count=N` before JAX starts
    for N CPU devices).

    **Arguments:**

    - `fn`: a function of one problem, `fn(*args) -> pytree of arrays` (e.g. a wrapper
        around [`jaxloc.solve_overhead_pose`][] and [`jaxloc.refine_overhead_pose`][]
        with `throw=False`). It must not call LAPACK (`jnp.linalg`): such programs were
        seen to hang when run from two devices at once (DESIGN §8).
    - `batch_size`: problems per `vmap`-ed step. Keyword only.
    - `devices`: the devices to shard over; default all of `jax.devices()`. Keyword only.

    **Returns:** a jitted function of the batched arguments (leading axis = problems, any
    size: padded internally to a multiple of the device count) returning `fn`'s outputs
    with the same leading axis. Results do not depend on `batch_size` or the devices.
    """
    if not isinstance(batch_size, int) or batch_size < 1:
        raise ValueError(f"`batch_size` must be a positive int; got {batch_size!r}.")
    devs = np.array(jax.devices() if devices is None else list(devices))
    mesh = jax.sharding.Mesh(devs, ("problems",))
    spec = jax.sharding.PartitionSpec("problems")
    nd = devs.size

    def local(*args):
        m = jax.tree.leaves(args)[0].shape[0]
        return jax.lax.map(lambda a: fn(*a), args, batch_size=min(batch_size, m))

    sharded = jax.shard_map(local, mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False)

    @jax.jit
    def run(*args):
        leaves = jax.tree.leaves(args)
        if not leaves:
            raise ValueError("`map_problems`: the batched function needs array arguments.")
        n = leaves[0].shape[0]
        pad = (-n) % nd
        if pad:
            args = jax.tree.map(
                lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]), args
            )
        out = sharded(*args)
        return jax.tree.map(lambda o: o[:n], out) if pad else out

    return run
