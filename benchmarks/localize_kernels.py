"""Where `jit(vmap(localize_cycle))`'s fused kernels come from, and what it costs (issue 19).

    python benchmarks/localize_kernels.py [--strategy sequential] [--batch 1024] [--top 30]
                                          [--options] [--map-batch N]

Compiles `jax.jit(jax.vmap(lambda o: jaxloc.localize_cycle(o, rig, throw=False)))` on
`--batch` simulated cycles of the paper's scenario (`split(key(0), batch)`) in a fresh
cache (with `--options`, under `compiler_options=jaxloc.compiler_options()`, the XLA
options jaxloc's own entry points and studies compile with; with `--map-batch N`, as
`jax.lax.map(..., batch_size=N)` instead of one `vmap`), then prints: the fused
kernels of the compiled program, the CPU and wall seconds of lowering and compiling, the
run time per problem (best of 3 calls), the share of `successful` cycles and C's mean
position (to compare two versions of the code: run it with `PYTHONPATH` pointing at a
`git worktree` of the other commit). Then the kernels counted by the JAX path in their
`op_name` metadata (the transformations and nested `jit`s down to the op, the op itself
dropped): jaxlie's rotation code shows as `jit(as_matrix)`, `jit(exp)`, `jit(log)`,
loops as `while/body`. (Their `stack_frame_id` chains stop at loop bodies, so the Python
source is not a reliable key; `benchmarks/kernel_sources.py` keys a study program's
kernels by source line.)"""

import argparse
import collections
import re
import resource
import time

import jax


jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir", None)

import jax.numpy as jnp  # noqa: E402
import jax.random as jr  # noqa: E402
import jaxloc  # noqa: E402
import numpy as np  # noqa: E402


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--strategy", default="sequential")
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--top", type=int, default=30)
    parser.add_argument("--options", action="store_true")
    parser.add_argument("--map-batch", type=int, default=0, metavar="N",
                        help="walk the batch in jax.lax.map steps of N vmapped cycles")  # fmt: skip
    args = parser.parse_args()
    scenario = jaxloc.Scenario.paper(args.strategy)
    keys = jr.split(jr.key(0), args.batch)
    obs = jax.jit(jax.vmap(lambda k: jaxloc.simulate_cycle(scenario, k)[1]))(keys)
    one = lambda o: jaxloc.localize_cycle(o, scenario.rig, throw=False)  # noqa: E731
    if args.map_batch:
        fn = lambda o: jax.lax.map(one, o, batch_size=args.map_batch)  # noqa: E731
    else:
        fn = jax.vmap(one)
    c0, t0 = _cpu(), time.perf_counter()
    options = jaxloc.compiler_options() if args.options else None
    compiled = jax.jit(fn, compiler_options=options).lower(obs).compile()
    cpu, wall = _cpu() - c0, time.perf_counter() - t0
    best = np.inf
    for _ in range(3):
        t = time.perf_counter()
        out = jax.block_until_ready(compiled(obs))
        best = min(best, time.perf_counter() - t)
    fusions = [line for line in compiled.as_text().splitlines()
               if line.startswith("  %") and " fusion(" in line]  # fmt: skip
    ok = np.asarray(out.result._value) == 0
    mean_c = float(jnp.mean(out.poses.T_world_overhead.wxyz_xyz[:, 4:]))
    layout = f"lax.map steps of {args.map_batch}" if args.map_batch else "vmap"
    print(f"{args.strategy}, batch {args.batch} ({layout}), options {options}: "
          f"{len(fusions)} fused kernels; lower+compile "
          f"{cpu:.1f} CPU-s ({wall:.1f} s wall); {best / args.batch * 1e6:.0f} us per problem; "
          f"successful {ok.mean():.4f}; mean of C's coordinates {mean_c:.9f}")  # fmt: skip
    paths = collections.Counter()
    for line in fusions:
        name = re.search(r'op_name="([^"]*)"', line)
        paths["/".join(name.group(1).split("/")[:-1]) if name else "(no metadata)"] += 1
    print(f"\nkernels by JAX path (top {args.top}):")
    for path, count in paths.most_common(args.top):
        print(f"{count:6d}  {path or '(top level)'}")


if __name__ == "__main__":
    main()
