"""A formation design's starts as Ray tasks (DESIGN §5, scale-out; issue 22).

[`ray_starts`][] is a [`StartRunner`][jaxloc._design.search.StartRunner] for
[`jaxloc.design_formation`][]: the starts are split into consecutive groups, one per task
the cluster runs at once, and each group is one Ray task running the design's own search
([`jaxloc._design.search.search_starts`][]) on the same draws (common random numbers: the
same keys in every task). The results come back in start order, and the design picks the
best start by its usual rule. Tasks run as a study's chunks do
([`jaxloc._study.cluster.map_on_ray`][]): JAX in each worker configured like the driver, a
task whose worker dies retried, a task that still fails a
[`ClusterError`][jaxloc._study.cluster.ClusterError].

Ray itself is imported only in `jaxloc._study.cluster`.
"""

from .._study.cluster import cluster_cpus, map_on_ray, MAX_RETRIES
from .search import num_starts, split_starts, StartRunner


def ray_starts(
    *, groups: int | None = None, cpus_per_task: int = 1, max_retries: int = MAX_RETRIES
) -> StartRunner:
    """A start runner that runs each group of starts as one Ray task on the connected
    cluster (`jaxloc._study.cluster.connect`).

    **Arguments:**

    - `groups`: how many groups (tasks) the starts are split into; default: as many as
      the cluster runs at once (its CPUs divided by `cpus_per_task`), so that every
      worker gets work. Never more than the starts. Keyword only (as the rest).
    - `cpus_per_task`: CPUs each task reserves, and JAX CPU devices its worker exposes.
    - `max_retries`: retries of a task whose worker died (Ray's `max_retries`).

    **Returns:** a `StartRunner`, for `design_formation(..., runner=ray_starts())`.
    """
    if groups is not None and groups < 1:
        raise ValueError(f"`groups` must be a positive integer; got {groups!r}.")

    def run(search, starts) -> list:
        n = num_starts(starts)
        wanted = groups if groups is not None else cluster_cpus() // cpus_per_task
        parts = split_starts(starts, max(1, min(wanted, n)))
        return map_on_ray(search, parts, cpus_per_task=cpus_per_task, max_retries=max_retries)

    return run
