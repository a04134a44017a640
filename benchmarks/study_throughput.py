"""Throughput, compile time and peak memory of Monte Carlo studies (issue 4 / 5 figures).

    python benchmarks/study_throughput.py [--trials N] [--chunk-size C] [--out results.json]

For each strategy, method set and dtype: the first chunk's wall time (compile + run), then
the steady-state trials/s over `--trials` trials, streamed to a temporary folder on disk as
a real study would be, and the process's peak RSS. Memory is bounded by the chunk size,
not by the number of trials: compare the peak RSS of runs with different `--trials`.
"""

import argparse
import json
import platform
import resource
import tempfile
import time

import jax
import jax.numpy as jnp
import jaxloc


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def measure(strategy: str, methods: tuple[str, ...], dtype, trials: int, chunk: int) -> dict:
    scenario = jaxloc.Scenario.paper(strategy=strategy)
    if dtype == jnp.float32:
        scenario = jaxloc.astype(scenario, jnp.float32)
    t0 = time.perf_counter()
    jaxloc.run_study(scenario, chunk, seed=123, chunk_size=chunk, methods=methods, progress=False)
    first = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        study = jaxloc.run_study(
            scenario,
            trials,
            seed=0,
            chunk_size=chunk,
            methods=methods,
            out_dir=out,
            progress=False,
        )
        elapsed = time.perf_counter() - t0
    ok = float((study["status"] == 0).mean())
    return {
        "strategy": strategy,
        "methods": list(methods),
        "dtype": jnp.dtype(dtype).name,
        "trials": trials,
        "chunk_size": chunk,
        "first_chunk_seconds": round(first, 2),
        "trials_per_second": round(trials / elapsed, 1),
        "fraction_ok": round(ok, 4),
        "peak_rss_mb": round(peak_rss_mb(), 1),
    }


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--trials", type=int, default=20_000)
    parser.add_argument("--chunk-size", type=int, default=4096)
    parser.add_argument("--out", default=None)
    parser.add_argument("--refined", action="store_true", help="also time the ML refinement")
    args = parser.parse_args()
    rows = []
    configs = [
        (("paper", "robust"), jnp.float64),
        (("robust",), jnp.float64),
        (("robust",), jnp.float32),
    ]
    if args.refined:
        configs.append((("paper", "robust", "refined"), jnp.float64))
    for strategy in ("sequential", "concurrent"):
        for methods, dtype in configs:
            row = measure(strategy, methods, dtype, args.trials, args.chunk_size)
            print(json.dumps(row), flush=True)
            rows.append(row)
    report = {
        "command": "python benchmarks/study_throughput.py "
        + f"--trials {args.trials} --chunk-size {args.chunk_size}"
        + (" --refined" if args.refined else ""),
        "machine": {
            "cpu_count": jax.local_device_count(),
            "platform": platform.platform(),
            "jax": jax.__version__,
            "python": platform.python_version(),
        },
        "rows": rows,
    }
    if args.out:
        with open(args.out, "w") as f:
            json.dump(report, f, indent=2)


if __name__ == "__main__":
    main()
