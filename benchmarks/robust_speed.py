"""Speed of the robust joint refinement on the cycles of `benchmarks/robust_refine.py`.

    python benchmarks/robust_speed.py [--batch 500] [--calls 3] [--loss huber]

The first `--batch` cycles of the 5%-of-sightings study (sequential paper scenario, seed
0, every sighting an outlier with probability 5%), their closed forms computed before the
clock starts; then `jax.jit(jax.vmap(refine_cycle(..., loss=...)))` on the batch: the
first call's seconds (trace and compile, no persistent cache) and the best of `--calls`
later calls, as cycles/s. Compare commits in alternating back-to-back runs on a quiet
machine (the speed of a shared machine drifts).
"""

import argparse
import time

import jax


jax.config.update("jax_enable_x64", True)
jax.config.update("jax_enable_compilation_cache", False)

import jax.numpy as jnp  # noqa: E402
import jax.random as jr  # noqa: E402
import jaxloc  # noqa: E402
from robust_refine import _outlier_masks  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--batch", type=int, default=500)
    parser.add_argument("--calls", type=int, default=3)
    parser.add_argument("--loss", default="huber", choices=("huber", "cauchy"))
    args = parser.parse_args()
    sc = jaxloc.Scenario.paper("sequential")
    rig = sc.rig

    @jax.jit
    @jax.vmap
    def inputs(key):
        k_sim, k_mask, k_out = jr.split(key, 3)
        _, obs, _ = jaxloc.simulate_cycle(sc, k_sim)
        m, o = _outlier_masks("5%-of-sightings", obs, k_mask)
        bad = jaxloc.add_outliers(obs, rig, m, o, key=k_out)
        return bad, jaxloc.localize_cycle(bad, rig, throw=False)

    # The study's keys (`robust_refine.py`: cycle i of its second study).
    keys = jax.vmap(lambda i: jr.fold_in(jr.key(0), i))(jnp.arange(args.batch) + 10**9)
    bad, est = jax.block_until_ready(inputs(keys))
    refine = jax.jit(jax.vmap(
        lambda o, e: jaxloc.refine_cycle(o, rig, e, loss=args.loss, throw=False)
    ))  # fmt: skip
    t0 = time.perf_counter()
    jax.block_until_ready(refine(bad, est))
    first = time.perf_counter() - t0
    times = []
    for _ in range(args.calls):
        t0 = time.perf_counter()
        jax.block_until_ready(refine(bad, est))
        times.append(time.perf_counter() - t0)
    print(f"robust refinement ({args.loss}), {args.batch} cycles: first call {first:.1f} s; "
          f"best of {args.calls} later calls {min(times):.2f} s = "
          f"{args.batch / min(times):.0f} cycles/s")  # fmt: skip


if __name__ == "__main__":
    main()
