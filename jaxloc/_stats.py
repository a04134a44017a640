"""Summary statistics of a Monte Carlo study, skipping (and counting) failed trials."""

from collections import Counter

import numpy as np

from ._results import status_names
from ._trial import CAMERAS


def describe(x: np.ndarray) -> dict[str, float]:
    """Mean, median, RMSE, 90th and 99th percentiles of a sample (NaN if empty)."""
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return {k: float("nan") for k in ("mean", "median", "rmse", "p90", "p99")}
    return {
        "mean": float(np.mean(x)),
        "median": float(np.median(x)),
        "rmse": float(np.sqrt(np.mean(x**2))),
        "p90": float(np.percentile(x, 90)),
        "p99": float(np.percentile(x, 99)),
    }


def summarize(study: dict[str, np.ndarray], methods: tuple[str, ...]) -> dict:
    """Per method and camera: error statistics over the successful trials.

    **Arguments:**

    - `study`: the arrays returned by [`jaxloc.run_study`][].
    - `methods`: the methods of the study, in order.

    **Returns:** a JSON-ready dict: `{"n_trials": n, "methods": {method: {"n_ok": ...,
    "failures": {status_name: count}, "cameras": {camera: {"position_m": stats,
    "rotation_rad": stats, "ypr_mean_abs_rad": stats}}}}}`, where `stats` is
    [`describe`][]'s dict and `ypr_mean_abs` is the mean of the absolute yaw, pitch and
    roll errors of a trial (the paper's Table I metric). Failed trials are skipped and
    counted by status name.
    """
    names = status_names()
    status = study["status"]
    out = {"n_trials": int(status.shape[0]), "methods": {}}
    for mi, method in enumerate(methods):
        ok = status[:, mi] == 0
        failures = Counter(names.get(int(c), str(int(c))) for c in status[~ok, mi])
        cameras = {}
        for ci, cam in enumerate(CAMERAS):
            cameras[cam] = {
                "position_m": describe(study["position"][ok, mi, ci]),
                "rotation_rad": describe(study["rotation"][ok, mi, ci]),
                "ypr_mean_abs_rad": describe(np.mean(np.abs(study["ypr"][ok, mi, ci]), axis=-1)),
            }
        out["methods"][method] = {
            "n_ok": int(ok.sum()),
            "failures": dict(sorted(failures.items())),
            "cameras": cameras,
        }
    return out
