"""Studies on a Ray cluster (`jaxloc._study.cluster`, issue 22): every chunk one Ray task,
a task whose worker dies is retried, and the study is the local one, bit for bit.

Ray is a test dependency (the `tests` extra installs `jaxloc[cluster]`): this test runs in
CI and is never skipped. The study runs in a process of its own (`cluster_study.py`), so
that Ray's driver (its threads and signal handlers) stays out of the pytest process.
"""

import os
import subprocess
import sys

import pytest


HERE = os.path.dirname(os.path.abspath(__file__))


def _run_cluster_script(script: str, tmp_path, timeout: float) -> None:
    """Run `tests/<script>` in a process of its own; it must pass every check and have
    seen a worker process die (and its task retried)."""
    run = subprocess.run(
        [sys.executable, os.path.join(HERE, script), str(tmp_path)],
        capture_output=True, text=True, timeout=timeout,
        env={**os.environ, "RAY_ENABLE_AUTO_CONNECT": "0"},
    )  # fmt: skip
    assert run.returncode == 0, f"{run.stdout}\n{run.stderr}"
    assert "all checks passed" in run.stdout
    assert os.path.exists(tmp_path / "crashed_1")  # the worker process did die
    print(run.stdout)


@pytest.mark.timeout(900)
def test_a_study_on_two_ray_workers_survives_a_lost_task(tmp_path):
    _run_cluster_script("cluster_study.py", tmp_path, timeout=840)


@pytest.mark.slow  # 149 s with its programs not yet compiled (idle): the slow run of CI
@pytest.mark.timeout(1800)
def test_a_design_on_two_ray_workers_is_the_local_design(tmp_path):
    # Issue 22: `design_formation(..., runner=ray_starts())` and `jaxloc design --ray` run
    # the starts in two tasks of two and pick the local run's start and formation. Three
    # programs compile (the local search, and the two-start search in both workers at
    # once): beside a busy test run on 2 cores that took more than 840 s.
    _run_cluster_script("cluster_design.py", tmp_path, timeout=1740)
