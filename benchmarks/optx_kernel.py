"""jaxloc's least-squares kernel called directly or as an optimistix solver.

    python benchmarks/optx_kernel.py [--cycles 1024] [--seed 5] [--repeats 3] [--out FILE]

The joint refinement of one cycle (paper scenario, both strategies, default noise), one
start (the robust closed form's poses, its alternatives dropped, so that every solver
runs the same single-start problem), three ways: `refine_cycle(solver="lm")` (the
kernel's own `while_loop`), `"optx-kernel"` (the same kernel as
`jaxloc._core.least_squares.KernelLevenbergMarquardt`, driven by
`optx.least_squares`: optimistix's loop, adjoint and `RESULTS`) and `"optx-lm"`
(`optx.LevenbergMarquardt`). For each: seconds to trace and compile `jit(vmap)` of the
batch, per-cycle time at the batch (best of `--repeats`), batch-1 latency of a jitted
call (median of 200), the Levenberg--Marquardt steps, and the largest difference of the
overhead camera's position from `"lm"`'s among the cycles both call successful.
"""

import argparse
import json
import os
import platform
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np


SOLVERS = ("lm", "optx-kernel", "optx-lm")


def _problem(strategy: str, cycles: int, seed: int):
    import equinox as eqx
    import jaxloc

    scenario = jaxloc.Scenario.paper(strategy)
    rig = scenario.rig

    def start(key):
        _, obs, _ = jaxloc.simulate_cycle(scenario, key)
        closed = jaxloc.localize_cycle(obs, rig, throw=False)
        return obs, eqx.tree_at(lambda e: e.alternatives, closed, None, is_leaf=lambda x: x is None)

    obs, closed = jax.jit(jax.vmap(start))(jr.split(jr.key(seed), cycles))
    return rig, obs, closed


def _refine(rig, solver):
    import jaxloc

    def one(obs, closed):
        out = jaxloc.refine_cycle(obs, rig, closed, solver=solver, throw=False)
        return (out.poses.T_world_overhead.translation(), out.result._value,
                out.stats["num_steps"])  # fmt: skip

    return one


def _best(fn, args, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return best


def measure(strategy: str, cycles: int, seed: int, repeats: int) -> dict:
    rig, obs, closed = _problem(strategy, cycles, seed)
    rows, ref = {}, None
    for solver in SOLVERS:
        batched = jax.jit(jax.vmap(_refine(rig, solver)))
        t0 = time.perf_counter()
        compiled = batched.lower(obs, closed).compile()
        compile_s = time.perf_counter() - t0
        per_cycle = _best(compiled, (obs, closed), repeats) / cycles
        c, result, steps = (np.asarray(a) for a in compiled(obs, closed))
        single = jax.jit(_refine(rig, solver))
        first = jax.tree.map(lambda a: a[0], (obs, closed))
        jax.block_until_ready(single(*first))
        lat = []
        for _ in range(200):
            t0 = time.perf_counter()
            jax.block_until_ready(single(*first))
            lat.append(time.perf_counter() - t0)
        ok = result == 0
        if ref is None:
            ref = (c, ok)
        both = ok & ref[1]
        rows[solver] = {
            "compile_s": round(compile_s, 2),
            "us_per_cycle_batched": round(1e6 * per_cycle, 1),
            "latency_us_batch1": round(1e6 * float(np.median(lat)), 1),
            "successful": int(ok.sum()),
            "steps_median": float(np.median(steps[ok])),
            "steps_max": int(steps[ok].max()),
            "max_diff_from_lm_m": float(np.max(np.abs(c[both] - ref[0][both]))),
        }
        print(f"{strategy:<10} {solver:<12} compile {compile_s:6.2f} s  "
              f"{1e6 * per_cycle:8.1f} us/cycle (batch {cycles})  "
              f"latency {rows[solver]['latency_us_batch1']:8.1f} us  "
              f"ok {ok.sum()}/{cycles}  steps median {rows[solver]['steps_median']:.0f} "
              f"max {rows[solver]['steps_max']}  "
              f"|dC| vs lm {rows[solver]['max_diff_from_lm_m']:.2e} m", flush=True)  # fmt: skip
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cycles", type=int, default=1024)
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=None, metavar="FILE", help="write the figures as JSON")
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_compilation_cache_dir", None)
    results = {s: measure(s, args.cycles, args.seed, args.repeats)
               for s in ("sequential", "concurrent")}  # fmt: skip
    if args.out:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True).stdout.strip()  # fmt: skip
        meta = {"command": " ".join(sys.argv), "commit": commit, "jax": jax.__version__,
                "machine": platform.machine(), "cpus": os.cpu_count(),
                "load_average": os.getloadavg(), "dtype": str(jnp.zeros(()).dtype)}  # fmt: skip
        with open(args.out, "w", encoding="utf-8") as f:
            json.dump({"meta": meta, "results": results}, f, indent=1)


if __name__ == "__main__":
    main()
