"""Studies on a Ray cluster (`jaxloc._study.cluster`, issue 22): every chunk one Ray task,
a task whose worker dies is retried, and the study is the local one, bit for bit.

Ray is a test dependency (the `tests` extra installs `jaxloc[cluster]`): this test runs in
CI and is never skipped.
"""

import json
import math
import os
import sys

import jaxloc
import numpy as np
import pytest
import ray
from jaxloc._cli.main import main
from jaxloc._core.files import dumps_json
from jaxloc._study import cluster


N = 96
CHUNK = 32
SEED = 11
METHODS = ("robust",)
CRASHING_CHUNK = 1


def _crash_once(marker_dir: str):
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


def _bits(x):
    """`x` with every float replaced by its exact hex form (NaN included), to compare
    summaries bit for bit."""
    if isinstance(x, dict):
        return {k: _bits(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_bits(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return "nan" if math.isnan(x) else float(x).hex()
    if isinstance(x, np.ndarray):
        return _bits(x.tolist())
    return x


@pytest.fixture(scope="module")
def two_workers():
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # ship _crash_once's task
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        yield
    finally:
        ray.shutdown()


@pytest.mark.timeout(600)
def test_a_study_on_two_ray_workers_survives_a_lost_task(two_workers, tmp_path):
    scenario = jaxloc.Scenario.paper(strategy="sequential")
    kwargs = dict(seed=SEED, chunk_size=CHUNK, methods=METHODS, progress=False)
    local = jaxloc.run_study(scenario, N, **kwargs)
    local_summary = jaxloc.stream_study(scenario, N, **kwargs)

    out = str(tmp_path / "study")
    task = _crash_once(str(tmp_path))
    streamed = cluster.stream_study_on_ray(scenario, N, out_dir=out, task=task, **kwargs)
    assert os.path.exists(tmp_path / f"crashed_{CRASHING_CHUNK}")  # the worker did die
    assert _bits(streamed) == _bits(local_summary)

    # The chunks the cluster computed are the study's files: a local run resumes from
    # them (verified, nothing recomputed) and gets the same trials.
    on_disk = sorted(f for f in os.listdir(out) if f.startswith("chunk_"))
    assert len(on_disk) == N // CHUNK
    resumed = jaxloc.run_study(scenario, N, out_dir=out, **kwargs)
    for k in local:
        np.testing.assert_array_equal(resumed[k], local[k], err_msg=k)

    # And run_study on the cluster returns every trial, bit for bit.
    on_ray = jaxloc.run_study_on_ray(scenario, N, **kwargs)
    for k in local:
        np.testing.assert_array_equal(on_ray[k], local[k], err_msg=k)

    # The command line: `jaxloc simulate --ray --stream` (Ray already running here, so
    # --ray uses this cluster) prints and writes the local summary, bit for bit.
    path, report = str(tmp_path / "scenario.yaml"), str(tmp_path / "report.json")
    jaxloc.save_scenario(scenario, path)
    args = ["simulate", "--scenario", path, "--trials", str(N), "--seed", str(SEED),
            "--chunk-size", str(CHUNK), "--methods", ",".join(METHODS), "--quiet"]  # fmt: skip
    assert main(args + ["--ray", "--stream", "--json", report]) == 0
    with open(report) as f:
        got = json.load(f)
    assert got["ray"].startswith("Ray cluster: 2 CPUs")
    summary = got["strategies"]["sequential"]
    del summary["seconds"]
    assert _bits(summary) == _bits(json.loads(dumps_json(local_summary)))
