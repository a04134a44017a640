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
    if "crlb_position_var" in study:
        out["crlb"] = crlb_summary(study, methods)
    if "refined" in methods and "nees" in study:
        out["nees"] = nees_summary(study, methods)
    return out


def crlb_summary(study: dict[str, np.ndarray], methods: tuple[str, ...]) -> dict:
    """Cramér–Rao predicted RMSE per camera: `sqrt(mean over trials of trace(bound))`.

    Averaged over the trials in which every method succeeded (the same trials the
    errors are computed on when nothing fails).
    """
    ok = np.all(study["status"] == 0, axis=1)
    out = {}
    for ci, cam in enumerate(CAMERAS):
        out[cam] = {
            "position_rmse_m": float(np.sqrt(np.mean(study["crlb_position_var"][ok, ci]))),
            "rotation_rmse_rad": float(np.sqrt(np.mean(study["crlb_rotation_var"][ok, ci]))),
        }
    return out


def nees_summary(study: dict[str, np.ndarray], methods: tuple[str, ...]) -> dict:
    """Mean normalized estimation error squared of each camera's final position under the
    refined estimate's covariance, with the 95% interval of that mean for a consistent
    estimator (chi-square with 3 degrees of freedom, normal approximation)."""
    ok = study["status"][:, methods.index("refined")] == 0
    out = {}
    for ci, cam in enumerate(CAMERAS):
        x = study["nees"][ok, ci]
        x = x[np.isfinite(x)]
        half = 1.96 * np.sqrt(2 * 3 / max(x.size, 1))
        out[cam] = {
            "mean": float(np.mean(x)) if x.size else float("nan"),
            "expected": 3.0,
            "interval95": [3.0 - half, 3.0 + half],
            "n": int(x.size),
        }
    return out
