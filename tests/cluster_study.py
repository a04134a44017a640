"""The Ray study of `tests/test_cluster.py`, run as its own process: Ray's driver state
(threads, signal handlers) then never outlives the test inside the pytest process.

    python tests/cluster_study.py TMP_DIR

Starts a local two-worker Ray cluster, runs a small study whose chunk `CRASHING_CHUNK`
kills its worker process on the first attempt, and checks that the study is the local
one, bit for bit. Exits 0 when every check passes.
"""

import json
import math
import os
import sys
import time

import jax


jax.config.update("jax_enable_x64", True)  # as tests/conftest.py

import jaxloc  # noqa: E402
import numpy as np  # noqa: E402
import ray  # noqa: E402
from jaxloc._cli.main import main  # noqa: E402
from jaxloc._core.files import dumps_json  # noqa: E402
from jaxloc._study import cluster  # noqa: E402


N = 96
CHUNK = 32
SEED = 11
METHODS = ("robust",)
CRASHING_CHUNK = 1


def crash_once(marker_dir: str):
    """A chunk task whose worker process exits, without a word, the first time it runs
    chunk `CRASHING_CHUNK` (as a machine lost mid-study would): Ray must retry it."""

    def task(scenario, seed, chunk_index, chunk_size, methods):
        marker = os.path.join(marker_dir, f"crashed_{chunk_index}")
        if chunk_index == CRASHING_CHUNK and not os.path.exists(marker):
            with open(marker, "w") as f:
                f.write(str(os.getpid()))
            os._exit(1)
        return jaxloc.run_chunk(scenario, seed, chunk_index, chunk_size, methods)

    return task


def bits(x):
    """`x` with every float replaced by its exact hex form (NaN included), to compare
    summaries bit for bit."""
    if isinstance(x, dict):
        return {k: bits(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [bits(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return "nan" if math.isnan(x) else float(x).hex()
    if isinstance(x, np.ndarray):
        return bits(x.tolist())
    return x


def check(tmp: str) -> None:
    t0 = time.perf_counter()
    scenario = jaxloc.Scenario.paper(strategy="sequential")
    kwargs = dict(seed=SEED, chunk_size=CHUNK, methods=METHODS, progress=False)
    local = jaxloc.run_study(scenario, N, **kwargs)
    local_summary = jaxloc.stream_study(scenario, N, **kwargs)
    print(f"local study: {time.perf_counter() - t0:.1f} s", flush=True)

    t0 = time.perf_counter()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    print(f"ray.init (two workers): {time.perf_counter() - t0:.1f} s", flush=True)
    try:
        t0 = time.perf_counter()
        out = os.path.join(tmp, "study")
        streamed = cluster.stream_study_on_ray(
            scenario, N, out_dir=out, task=crash_once(tmp), **kwargs
        )
        assert os.path.exists(os.path.join(tmp, f"crashed_{CRASHING_CHUNK}")), "no crash"
        assert bits(streamed) == bits(local_summary), "streamed summary differs"
        print(f"on Ray, a worker lost and retried: {time.perf_counter() - t0:.1f} s", flush=True)

        # The chunks the cluster computed are the study's files: a local run resumes from
        # them (verified, nothing recomputed) and gets the same trials.
        on_disk = sorted(f for f in os.listdir(out) if f.startswith("chunk_"))
        assert len(on_disk) == N // CHUNK, on_disk
        resumed = jaxloc.run_study(scenario, N, out_dir=out, **kwargs)
        for k in local:
            np.testing.assert_array_equal(resumed[k], local[k], err_msg=k)

        # run_study on the cluster returns every trial, bit for bit.
        on_ray = jaxloc.run_study_on_ray(scenario, N, **kwargs)
        for k in local:
            np.testing.assert_array_equal(on_ray[k], local[k], err_msg=k)

        # The command line: `jaxloc simulate --ray --stream` (Ray already running here, so
        # --ray uses this cluster) writes the local summary, bit for bit.
        path, report = os.path.join(tmp, "scenario.yaml"), os.path.join(tmp, "report.json")
        jaxloc.save_scenario(scenario, path)
        args = ["simulate", "--scenario", path, "--trials", str(N), "--seed", str(SEED),
                "--chunk-size", str(CHUNK), "--methods", ",".join(METHODS), "--quiet"]  # fmt: skip
        assert main(args + ["--ray", "--stream", "--json", report]) == 0
        with open(report) as f:
            got = json.load(f)
        assert got["ray"].startswith("Ray cluster: 2 CPUs"), got["ray"]
        summary = got["strategies"]["sequential"]
        del summary["seconds"]
        assert bits(summary) == bits(json.loads(dumps_json(local_summary))), "CLI differs"
    finally:
        ray.shutdown()
    print("all checks passed", flush=True)


if __name__ == "__main__":
    check(sys.argv[1])
