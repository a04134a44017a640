r"""The tracking study: many runs of K cycles, chunked, sharded, resumable
([`jaxloc.run_track_study`][]), and its per-cycle statistics ([`jaxloc.summarize_track`][]).

As [`jaxloc.run_study`][]: run `i` of a study seeded `s` uses the key
`jax.random.fold_in(key(s), i)`, so its numbers do not depend on the chunk size or the
devices; a chunk is one compiled call whose runs are sharded over every local device, each
device walking its share in `lax.map` steps of `MICRO_BATCH` runs; on disk a study is a
folder of verified chunk files (`jaxloc._study.chunks`) and resumes after an
interruption. Its manifest's scenario is the tracking scenario's file form with the
number of cycles and the smoother's window.
"""

from collections import Counter
from collections.abc import Callable

import numpy as np

from .._core.programs import Program
from .._core.results import status_names
from .._cycle.layout import CAMERAS
from .._study.chunks import check_seed, open_study, study_manifest
from .._study.engine import chunk_inputs, chunk_program, stream_chunks
from .._study.stats import describe
from .scenario import track_scenario_to_dict, TrackScenario
from .tracker import DEFAULT_WINDOW
from .trial import run_track_trial, TRACK_METHODS, TrackErrors


#: The arrays of a chunk (the fields of [`jaxloc.TrackErrors`][]) besides `index`.
TRACK_FIELDS = tuple(TrackErrors.__dataclass_fields__)


def _track_program(track: TrackScenario, chunk_size: int, cycles: int, window: int) -> Program:
    trial = lambda tr, key: run_track_trial(tr, key, cycles, window)  # noqa: E731
    static = repr((int(cycles), int(window)))
    return chunk_program("track_chunk", trial, track, chunk_size, static, TRACK_FIELDS)


def run_track_chunk(
    track: TrackScenario,
    seed: int,
    chunk_index: int,
    chunk_size: int,
    cycles: int,
    window: int = DEFAULT_WINDOW,
) -> dict[str, np.ndarray]:
    """Runs `chunk_index * chunk_size + [0, chunk_size)` of a tracking study: the fields
    of [`jaxloc.TrackErrors`][] with a leading run axis, and `"index"`. Deterministic (a
    cluster engine's retried task gets the same numbers)."""
    start = chunk_index * chunk_size
    program = _track_program(track, chunk_size, cycles, window)
    errors = program(chunk_inputs(track, seed, start))
    out = {name: np.asarray(errors[name])[:chunk_size] for name in TRACK_FIELDS}
    out["index"] = np.arange(start, start + chunk_size, dtype=np.int64)
    return out


def precompile_track(track: TrackScenario, chunk_size: int, cycles: int, window: int) -> None:
    """Compile a tracking study's chunk program now (later chunks reuse it)."""
    _track_program(track, chunk_size, cycles, window).compile()


def track_chunk_fields(track: TrackScenario, chunk_size: int, cycles: int):
    """`name -> (shape, dtype)` of every array of a tracking study's chunk file."""
    f = np.dtype(track.scenario.base.dtype)
    i32, b = np.dtype(np.int32), np.dtype(bool)
    n, K, M = chunk_size, cycles, len(TRACK_METHODS)
    shapes = {
        "status": ((n, K, M), i32), "position": ((n, K, M, 4), f),
        "rotation": ((n, K, M, 4), f), "position_vector": ((n, K, M, 4, 3), f),
        "bound_position_var": ((n, K, M, 4), f), "bound_rotation_var": ((n, K, M, 4), f),
        "nees": ((n, K, M, 4), f), "root_correct": ((n, K), b), "root_count": ((n, K), i32),
        "truth_position": ((n, K, 4, 3), f), "covariance_xy": ((n, K, M, 4, 3), f),
    }  # fmt: skip
    assert set(shapes) == set(TRACK_FIELDS)
    shapes["index"] = ((n,), np.dtype(np.int64))
    return shapes


def track_manifest(track, seed, chunk_size, cycles, window):
    """The study manifest of a tracking study (`jaxloc._study.chunks.study_manifest`)."""
    body = {"kind": "track", "track_scenario": track_scenario_to_dict(track),
            "cycles": int(cycles), "window": int(window)}  # fmt: skip
    return study_manifest(body, seed, chunk_size, TRACK_METHODS)


def _check_args(n_runs, cycles, chunk_size, window, seed):
    for name, v in (("n_runs", n_runs), ("cycles", cycles), ("chunk_size", chunk_size),
                    ("window", window)):  # fmt: skip
        if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
            raise ValueError(f"`{name}` must be a positive integer; got {v!r}.")
    check_seed(seed)


def run_track_study(
    track: TrackScenario,
    n_runs: int,
    cycles: int,
    *,
    seed: int = 0,
    chunk_size: int = 1024,
    window: int = DEFAULT_WINDOW,
    out_dir: str | None = None,
    progress: bool = True,
    on_chunk: Callable[[int, dict], None] | None = None,
) -> dict[str, np.ndarray]:
    """Run `n_runs` runs of `cycles` cycles of `track` and return their errors.

    **Arguments:** the scenario, the number of runs and of cycles per run; keyword only:
    the study's `seed` (`[0, 2**32 - 1]`), `chunk_size` (runs per compiled call), the
    smoother's `window` (cycles), `out_dir` (write every chunk there as it finishes; a
    study already there with the same settings is resumed, its chunks verified),
    `progress`, `on_chunk(chunk_index, arrays)`.

    **Returns:** the fields of [`jaxloc.TrackErrors`][] with a leading axis of `n_runs`,
    and `"index"`. Summarize with [`jaxloc.summarize_track`][].
    """
    _check_args(n_runs, cycles, chunk_size, window, seed)
    manifest = None
    if out_dir is not None:
        manifest = track_manifest(track, seed, chunk_size, cycles, window)
        open_study(out_dir, manifest)

    def runner(todo, on_done):
        for c in todo:
            arrays = run_track_chunk(track, seed, c, chunk_size, cycles, window)
            on_done()
            yield arrays

    chunks = []
    stream = stream_chunks(
        n_runs, chunk_size, runner, out_dir, manifest,
        lambda: track_chunk_fields(track, chunk_size, cycles), progress,
    )  # fmt: skip
    for c, arrays in enumerate(stream):
        chunks.append(arrays)
        if on_chunk is not None:
            on_chunk(c, arrays)
    return {k: np.concatenate([ch[k] for ch in chunks]) for k in chunks[0]}


def _bound_rmse(var: np.ndarray) -> float:
    return float(np.sqrt(np.mean(var))) if var.size else float("nan")


def summarize_track(study: dict[str, np.ndarray]) -> dict:
    """Per cycle, method and robot: position and rotation error statistics over the runs
    that method tracked successfully up to that cycle, beside the method's bound (root
    mean of its variance over the same runs) and their ratio; failures by status name;
    NEES means; the one-step root statistics.

    **Returns:** a JSON-ready dict: `{"n_runs", "cycles", "methods": {method: [per cycle
    {"n_ok", "failures", "robots": {robot: {"position_m": stats, "bound_position_rmse_m",
    "ratio", "efficiency", "rotation_rad": stats, "bound_rotation_rmse_rad", "nees"}}}]},
    "one_step": {...}}` (`stats`: [`jaxloc.describe`][]'s)."""
    names = status_names()
    status = study["status"]
    n, K, M = status.shape
    out = {"n_runs": int(n), "cycles": int(K), "methods": {}}
    for m, method in enumerate(TRACK_METHODS):
        per_cycle = []
        for k in range(K):
            ok = status[:, k, m] == 0
            failures = Counter(names.get(int(c), str(int(c))) for c in status[~ok, k, m])
            robots = {}
            for r, cam in enumerate(CAMERAS):
                pos = study["position"][ok, k, m, r]
                bound = _bound_rmse(study["bound_position_var"][ok, k, m, r])
                stats = describe(pos)
                nees = study["nees"][ok, k, m, r]
                nees = nees[np.isfinite(nees)]
                robots[cam] = {
                    "position_m": stats,
                    "bound_position_rmse_m": bound,
                    "ratio": stats["rmse"] / bound if bound > 0 else float("nan"),
                    "efficiency": bound / stats["rmse"] if stats["rmse"] > 0 else float("nan"),
                    "rotation_rad": describe(study["rotation"][ok, k, m, r]),
                    "bound_rotation_rmse_rad": _bound_rmse(
                        study["bound_rotation_var"][ok, k, m, r]
                    ),
                    "nees": float(np.mean(nees)) if nees.size else float("nan"),
                }
            per_cycle.append({"n_ok": int(ok.sum()), "failures": dict(sorted(failures.items())),
                              "robots": robots})  # fmt: skip
        out["methods"][method] = per_cycle
    one = TRACK_METHODS.index("one_step")
    ran = status[:, :, one] == 0
    ambiguous = status[:, :, one] == _code("ambiguous")
    has_roots = study["root_count"] > 0
    out["one_step"] = {
        "root_correct": float(np.mean(study["root_correct"][has_roots])) if has_roots.any()
        else float("nan"),
        "root_correct_successful": float(np.mean(study["root_correct"][ran]))
        if ran.any() else float("nan"),
        "ambiguous": float(np.mean(ambiguous[has_roots])) if has_roots.any() else float("nan"),
        "wrong_root_successful": int(np.sum(ran & ~study["root_correct"])),
    }  # fmt: skip
    return out


def _code(name: str) -> int:
    return {v: k for k, v in status_names().items()}[name]
