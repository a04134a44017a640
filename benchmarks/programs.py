"""What jaxloc compiles: trace, compile, fused kernels and run time of every public entry
point and of each study program (issue 19, item 1).

    python benchmarks/programs.py [--only NAME,...] [--batches 1,32,1024] [--out FILE]

For each program: the seconds to trace and lower it (Python), the CPU seconds XLA takes to
compile it, the number of fused kernels in the compiled program (XLA:CPU compiles each
with LLVM; compile time grows with their number), and the run time per problem under
`jit(vmap)` at each batch size (best of 3 calls; the study programs: per trial of one
chunk, sharded over the host devices as `jaxloc table1` runs them). Every program is
compiled in a fresh cache (the persistent compilation cache is off). Writes JSON with the
machine, the versions, the command and every figure.
"""

import argparse
import os
import re
import resource
import sys
import time


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _fusions(compiled) -> int:
    return len(re.findall(r" fusion\(", compiled.as_text()))


def measure(name, fn, args, batches=(), batched_args=None):
    """Trace, compile and run `jax.jit(fn)(*args)`; then per-problem time of
    `jit(vmap(fn))` at each batch size (`batched_args(n)` builds the inputs)."""
    import jax

    t0 = time.perf_counter()
    lowered = jax.jit(fn).lower(*args)
    t1, c0 = time.perf_counter(), _cpu()
    compiled = lowered.compile()
    c1, t2 = _cpu(), time.perf_counter()
    row = {
        "name": name,
        "trace_s": t1 - t0,
        "compile_cpu_s": c1 - c0,
        "compile_wall_s": t2 - t1,
        "fusions": _fusions(compiled),
    }
    jax.block_until_ready(compiled(*args))
    latency = []
    for _ in range(20):
        s = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        latency.append(time.perf_counter() - s)
    row["latency_us"] = 1e6 * sorted(latency)[len(latency) // 2]
    for n in batches:
        f = jax.jit(jax.vmap(fn))
        xs = batched_args(n)
        jax.block_until_ready(f(*xs))
        best = min(_timed(f, xs) for _ in range(3))
        row[f"per_problem_us_batch_{n}"] = 1e6 * best / n
    print(_format(row), flush=True)
    return row


def _timed(f, xs):
    import jax

    s = time.perf_counter()
    jax.block_until_ready(f(*xs))
    return time.perf_counter() - s


def _format(row):
    parts = [
        f"{row['name']:<32} trace {row['trace_s']:6.2f} s",
        f"compile {row['compile_cpu_s']:6.2f} CPU-s",
        f"{row['fusions']:5d} fusions",
        f"latency {row.get('latency_us', 0):8.0f} us",
    ]
    for k, v in row.items():
        if k.startswith("per_problem_us_batch_"):
            parts.append(f"b{k.rsplit('_', 1)[1]} {v:.1f} us")
    return "  ".join(parts)


def entry_points(batches):
    import jax
    import jax.numpy as jnp
    import jax.random as jr
    import jaxloc

    rows = []
    for strategy in ("sequential", "concurrent"):
        sc = jaxloc.Scenario.paper(strategy)
        rig = sc.rig

        def sim(k, sc=sc):
            return jaxloc.simulate_cycle(sc, k)

        def keys(n):
            return (jr.split(jr.key(1), n),)

        rows.append(measure(f"simulate_cycle[{strategy}]", sim, (jr.key(0),), batches, keys))
        _, obs, _ = jax.jit(sim)(jr.key(0))
        batch_obs = jax.jit(jax.vmap(sim))(jr.split(jr.key(1), max(batches)))[1]

        def obs_batch(n, b=batch_obs):
            return (jax.tree.map(lambda x: x[:n], b),)

        def localize(o, rig=rig):
            return jaxloc.localize_cycle(o, rig, throw=False)

        rows.append(measure(f"localize_cycle[{strategy}]", localize, (obs,), batches, obs_batch))
        est = jax.jit(localize)(obs)
        batch_est = jax.jit(jax.vmap(localize))(batch_obs)

        def refine(o, e, rig=rig):
            return jaxloc.refine_cycle(o, rig, e, throw=False)

        def refine_batch(n, b=batch_obs, e=batch_est):
            return jax.tree.map(lambda x: x[:n], (b, e))

        rows.append(measure(f"refine_cycle[{strategy}]", refine, (obs, est), batches, refine_batch))
        truth = jax.jit(sim)(jr.key(0))[0]

        def crlb(t, rig=rig, sc=sc):
            return jaxloc.cycle_crlb(rig, t.poses, odometry_sigma_rel=sc.odometry_sigma_rel)

        rows.append(measure(f"cycle_crlb[{strategy}]", crlb, (truth,)))
    X = jnp.array([[0.0, 0, 0], [1, 0.2, 0], [0.1, 1, 0.05], [1.1, 1.2, 0.1], [0.5, -0.4, 0.02],
                   [-0.6, 0.4, 0.03]])  # fmt: skip
    cam = jaxloc.paper_overhead_camera()
    T = jaxlie_pose()
    q = jax.vmap(T.apply)(X)
    b = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    uv = cam.project(q)

    def overhead(X, b):
        return jaxloc.solve_overhead_pose(X, b, throw=False).pose.wxyz_xyz

    def tile(n, *a):
        return tuple(jnp.broadcast_to(x, (n,) + x.shape) for x in a)

    rows.append(measure("solve_overhead_pose", overhead, (X, b), batches, lambda n: tile(n, X, b)))

    def refine_pose(X, uv):
        return jaxloc.refine_overhead_pose(T, cam, X, uv, sigma=1.0, throw=False).pose.wxyz_xyz

    rows.append(measure("refine_overhead_pose", refine_pose, (X, uv), batches,
                        lambda n: tile(n, X, uv)))  # fmt: skip

    def p3p(X, b):
        return jaxloc.p3p(X[:3], b[:3]).poses.wxyz_xyz

    rows.append(measure("p3p", p3p, (X, b), batches, lambda n: tile(n, X, b)))
    return rows


def jaxlie_pose():
    import jax.numpy as jnp
    import jaxlie

    R = jnp.array([[0.0, -1, 0], [-1, 0, 0], [0, 0, -1]])
    return jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.from_matrix(R), jnp.array([0.3, -0.2, 3.5])
    ).inverse()


def study_programs():
    import jax
    import jaxloc
    import jaxloc._study.engine as engine

    rows = []
    chunk = engine.balanced_chunk_size(10_000)
    for strategy in ("sequential", "concurrent"):
        scenario = jaxloc.Scenario.paper(strategy)
        inputs = engine._chunk_inputs(scenario, 0, 0, chunk, jaxloc.METHODS)
        t0 = time.perf_counter()
        lowered = engine._run_chunk.lower(*inputs)
        t1, c0 = time.perf_counter(), _cpu()
        compiled = lowered.compile()
        c1 = _cpu()
        row = {"name": f"study chunk[{strategy}]", "trace_s": t1 - t0, "compile_cpu_s": c1 - c0,
               "fusions": _fusions(compiled.compiled), "chunk": chunk,
               "devices": jax.device_count()}  # fmt: skip
        print(_format(row), flush=True)
        times = []
        for c in range(2):
            s = time.perf_counter()
            inputs = engine._chunk_inputs(scenario, 0, c * chunk, chunk, jaxloc.METHODS)
            jax.block_until_ready(compiled(*inputs))
            times.append(time.perf_counter() - s)
        row["per_trial_us"] = 1e6 * min(times) / chunk
        row["trials_per_s"] = chunk / min(times)
        print(_format(row), f"  {row['trials_per_s']:.0f} trials/s", flush=True)
        rows.append(row)
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--only", default="entry,study", help="entry,study")
    parser.add_argument("--batches", default="1,32,1024")
    parser.add_argument("--devices", type=int, default=2)
    parser.add_argument("--out", default="benchmarks/results/programs.json")
    args = parser.parse_args(argv)
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={args.devices}"
    )
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_compilation_cache_dir", None)
    sys.path.insert(0, os.path.dirname(__file__))
    from run import machine_info

    batches = tuple(int(b) for b in args.batches.split(","))
    only = set(args.only.split(","))
    report = {"command": " ".join(["python", "benchmarks/programs.py", *sys.argv[1:]]),
              "machine": machine_info(), "rows": []}  # fmt: skip
    if "entry" in only:
        report["rows"] += entry_points(batches)
    if "study" in only:
        report["rows"] += study_programs()
    from jaxloc._core.files import atomic_write_json

    atomic_write_json(args.out, report)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
