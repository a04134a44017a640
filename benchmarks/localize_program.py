"""Size and speed of `jit(vmap(localize_cycle))`, runnable on any commit of jaxloc.

    python benchmarks/localize_program.py [--batch 256] [--strategy sequential]

Compiles `jax.jit(jax.vmap(localize_cycle))` over a batch of simulated paper-scenario
cycles (compilation cache off) and prints the trace and compile seconds, the fused
kernels and while loops of the compiled program, and the best of 5 calls per cycle. It
calls `localize_cycle(obs, rig)` or, on commits before the Rig (e.g. 5ebd322),
`localize_cycle(obs)`, so that one script compares two checkouts back to back:
`PYTHONPATH=OTHER_CHECKOUT python benchmarks/localize_program.py`.
"""

import argparse
import re
import time

import jax
import jax.random as jr


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--strategy", default=None, help="default: both")
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_compilation_cache_dir", None)
    import jaxloc

    for strategy in [args.strategy] if args.strategy else ["sequential", "concurrent"]:
        sc = jaxloc.Scenario.paper(strategy)
        keys = jr.split(jr.key(0), args.batch)
        obs = jax.jit(jax.vmap(lambda k, sc=sc: jaxloc.simulate_cycle(sc, k)[1]))(keys)
        if hasattr(sc, "rig"):
            def fn(o, sc=sc):
                return jaxloc.localize_cycle(o, sc.rig, throw=False)
        else:  # before the Rig
            def fn(o):
                return jaxloc.localize_cycle(o, throw=False)
        t0 = time.perf_counter()
        lowered = jax.jit(jax.vmap(fn)).lower(obs)
        t1 = time.perf_counter()
        compiled = lowered.compile()
        t2 = time.perf_counter()
        text = compiled.as_text()
        best = float("inf")
        for _ in range(5):
            t = time.perf_counter()
            jax.block_until_ready(compiled(obs))
            best = min(best, time.perf_counter() - t)
        print(f"{strategy}: trace {t1 - t0:.1f} s, compile {t2 - t1:.1f} s, "
              f"{len(re.findall(r' fusion[(]', text))} fused kernels, "
              f"{len(re.findall(r' while[(]', text))} while loops, "
              f"{1e6 * best / args.batch:.1f} us per cycle at batch {args.batch}")  # fmt: skip


if __name__ == "__main__":
    main()
