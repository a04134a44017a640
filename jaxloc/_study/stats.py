"""Summary statistics of a Monte Carlo study, skipping (and counting) failed trials.

[`jaxloc.summarize`][] works on a study held in memory (exact order statistics);
[`jaxloc.StreamingSummary`][] folds in one chunk at a time and keeps only fixed-size
accumulators, for studies too large to hold (10^7 trials and more).
"""

from collections import Counter

import numpy as np

from .._core.results import status_names
from .._cycle.layout import CAMERAS


def _rms(x: np.ndarray) -> float:
    """Root mean of `x` (a mean of variances), NaN for no values (without a warning)."""
    return float(np.sqrt(np.mean(x))) if np.size(x) else float("nan")


def _nees_entry(total: float, n: int) -> dict:
    """Mean NEES of `n` values summing to `total`, with the 95% interval of that mean for a
    consistent estimator (chi-square with 3 degrees of freedom, normal approximation)."""
    half = 1.96 * np.sqrt(2 * 3 / max(n, 1))
    return {
        "mean": float(total / n) if n else float("nan"),
        "expected": 3.0,
        "interval95": [3.0 - half, 3.0 + half],
        "n": int(n),
    }


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
    [`jaxloc.describe`][]'s dict and `ypr_mean_abs` is the mean of the absolute yaw, pitch and
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
            "gates": gate_counts(study, mi, ok),
            "cameras": cameras,
        }
    if "crlb_position_var" in study:
        out["crlb"] = crlb_summary(study, methods)
    if "refined" in methods and "nees" in study:
        out["nees"] = nees_summary(study, methods)
    return out


def gate_counts(study: dict[str, np.ndarray], mi: int, ok: np.ndarray) -> dict[str, int]:
    """Of the trials a method's solver estimated (`ok`), how many its gates flag, by the
    status they give (`inconsistent_fit`, `unobservable`, `ambiguous`)."""
    if "gated" not in study:
        return {}
    names = status_names()
    flagged = study["gated"][ok, mi]
    return dict(sorted(Counter(names[int(c)] for c in flagged[flagged != 0]).items()))


def crlb_summary(study: dict[str, np.ndarray], methods: tuple[str, ...]) -> dict:
    """Cramér–Rao predicted RMSE per camera: `sqrt(mean over trials of trace(bound))`.

    Averaged over the trials in which every method succeeded (the same trials the
    errors are computed on when nothing fails); NaN if there is none.
    """
    ok = np.all(study["status"] == 0, axis=1)
    out = {}
    for ci, cam in enumerate(CAMERAS):
        out[cam] = {
            "position_rmse_m": _rms(study["crlb_position_var"][ok, ci]),
            "rotation_rmse_rad": _rms(study["crlb_rotation_var"][ok, ci]),
        }
        if "crlb_position_sample" in study:
            out[cam]["position_m"] = describe(study["crlb_position_sample"][ok, ci])
            out[cam]["rotation_rad"] = describe(study["crlb_rotation_sample"][ok, ci])
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
        out[cam] = _nees_entry(float(np.sum(x)), x.size)
    return out


#: Error histograms of [`jaxloc.StreamingSummary`][]: log-spaced bins from 1e-12 to 1e3 (m or
#: rad), this many per decade; a percentile is read to within one bin, a relative error
#: below 10**(1/200) - 1 = 1.2% (about 0.6% typical, from interpolation inside the bin).
BINS_PER_DECADE = 200
_LOG_LO, _LOG_HI = -12, 3


class _ColumnStats:
    """Exact sums and log-spaced histograms of nonnegative values in `columns` columns."""

    def __init__(self, columns: int):
        self.edges = np.logspace(_LOG_LO, _LOG_HI, (_LOG_HI - _LOG_LO) * BINS_PER_DECADE + 1)
        self.hist = np.zeros((columns, self.edges.size + 1), np.int64)  # [0, lo) .. [hi, inf)
        self.sum = np.zeros(columns)
        self.sumsq = np.zeros(columns)
        self.n = np.zeros(columns, np.int64)

    def update(self, column: int, x: np.ndarray) -> None:
        x = np.asarray(x, np.float64)
        self.sum[column] += x.sum()
        self.sumsq[column] += (x * x).sum()
        self.n[column] += x.size
        bins = np.searchsorted(self.edges, x, side="right")
        self.hist[column] += np.bincount(bins, minlength=self.hist.shape[1])

    def _quantile(self, column: int, q: float) -> float:
        # The rank np.percentile interpolates at, read off the histogram with a log-linear
        # interpolation inside the bin that holds the order statistic at its floor.
        hist = self.hist[column]
        rank = q * (self.n[column] - 1)
        cum = np.cumsum(hist)
        b = int(np.searchsorted(cum, rank, side="right"))
        if b == 0:
            return 0.0
        if b >= hist.size - 1:
            return float(self.edges[-1])
        lo, hi = np.log(self.edges[b - 1]), np.log(self.edges[b])
        frac = (rank - cum[b - 1]) / hist[b]
        return float(np.exp(lo + min(max(frac, 0.0), 1.0) * (hi - lo)))

    def describe(self, column: int) -> dict[str, float]:
        n = int(self.n[column])
        if n == 0:
            return {key: float("nan") for key in ("mean", "median", "rmse", "p90", "p99")}
        return {
            "mean": float(self.sum[column] / n),
            "median": self._quantile(column, 0.5),
            "rmse": float(np.sqrt(self.sumsq[column] / n)),
            "p90": self._quantile(column, 0.9),
            "p99": self._quantile(column, 0.99),
        }


class StreamingSummary:
    """[`jaxloc.summarize`][]'s statistics accumulated chunk by chunk in bounded memory.

    Means, RMSEs, failure counts, the Cramér–Rao means and the NEES means are exact (sums
    in float64). Medians and percentiles come from log-spaced histograms
    (`BINS_PER_DECADE` bins per decade between 1e-12 and 1e3; smaller values, such as the
    reference robot's exact zero, count as 0): each is within 1.2% (relative) of the
    order statistic at the floor of `np.percentile`'s rank. Memory: a few MB whatever
    the number of trials.

    Usage: `acc = StreamingSummary(methods)`, then `acc.update(chunk_arrays)` for each
    chunk (the dict [`jaxloc.run_chunk`][] returns), then `acc.result()`.
    """

    _METRICS = ("position_m", "rotation_rad", "ypr_mean_abs_rad")

    def __init__(self, methods: tuple[str, ...]):
        self.methods = tuple(methods)
        n_cam = len(CAMERAS)
        self._errors = _ColumnStats(len(self._METRICS) * len(self.methods) * n_cam)
        self._bound = _ColumnStats(2 * n_cam)  # crlb_{position,rotation}_sample
        self._n = 0
        self._n_ok = np.zeros(len(self.methods), np.int64)
        self._failures = [Counter() for _ in self.methods]
        self._gates = [Counter() for _ in self.methods]
        self._crlb = np.zeros((2, n_cam))
        self._crlb_n = 0
        self._nees_sum = np.zeros(n_cam)
        self._nees_n = np.zeros(n_cam, np.int64)

    def _column(self, k: int, mi: int, ci: int) -> int:
        return (k * len(self.methods) + mi) * len(CAMERAS) + ci

    def update(self, arrays: dict[str, np.ndarray]) -> None:
        """Fold in one chunk of trials (arrays with a leading trial axis)."""
        names = status_names()
        status = arrays["status"]
        self._n += status.shape[0]
        values = (
            arrays["position"],
            arrays["rotation"],
            np.mean(np.abs(arrays["ypr"]), axis=-1),
        )
        for mi in range(len(self.methods)):
            ok = status[:, mi] == 0
            self._n_ok[mi] += ok.sum()
            self._failures[mi].update(names.get(int(c), str(int(c))) for c in status[~ok, mi])
            if "gated" in arrays:
                flagged = arrays["gated"][ok, mi]
                self._gates[mi].update(names[int(c)] for c in flagged[flagged != 0])
            for k, v in enumerate(values):
                for ci in range(len(CAMERAS)):
                    self._errors.update(self._column(k, mi, ci), v[ok, mi, ci])
        if "crlb_position_var" in arrays:
            all_ok = np.all(status == 0, axis=1)
            self._crlb[0] += arrays["crlb_position_var"][all_ok].sum(axis=0)
            self._crlb[1] += arrays["crlb_rotation_var"][all_ok].sum(axis=0)
            self._crlb_n += int(all_ok.sum())
            if "crlb_position_sample" in arrays:
                n_cam = len(CAMERAS)
                for ci in range(n_cam):
                    self._bound.update(ci, arrays["crlb_position_sample"][all_ok, ci])
                    self._bound.update(n_cam + ci, arrays["crlb_rotation_sample"][all_ok, ci])
        if "refined" in self.methods and "nees" in arrays:
            ok = status[:, self.methods.index("refined")] == 0
            x = arrays["nees"][ok]
            finite = np.isfinite(x)
            self._nees_sum += np.where(finite, x, 0.0).sum(axis=0)
            self._nees_n += finite.sum(axis=0)

    def result(self) -> dict:
        """The dict [`jaxloc.summarize`][] returns, for every trial folded in so far."""
        out = {"n_trials": self._n, "methods": {}, "percentiles": "histogram"}
        for mi, method in enumerate(self.methods):
            cameras = {
                cam: {
                    metric: self._errors.describe(self._column(k, mi, ci))
                    for k, metric in enumerate(self._METRICS)
                }
                for ci, cam in enumerate(CAMERAS)
            }
            out["methods"][method] = {
                "n_ok": int(self._n_ok[mi]),
                "failures": dict(sorted(self._failures[mi].items())),
                "gates": dict(sorted(self._gates[mi].items())),
                "cameras": cameras,
            }
        if self._crlb_n:
            n = self._crlb_n
            out["crlb"] = {}
            for ci, cam in enumerate(CAMERAS):
                out["crlb"][cam] = {
                    "position_rmse_m": float(np.sqrt(self._crlb[0, ci] / n)),
                    "rotation_rmse_rad": float(np.sqrt(self._crlb[1, ci] / n)),
                }
                if self._bound.n.any():
                    out["crlb"][cam]["position_m"] = self._bound.describe(ci)
                    out["crlb"][cam]["rotation_rad"] = self._bound.describe(len(CAMERAS) + ci)
        if "refined" in self.methods and self._nees_n.any():
            out["nees"] = {}
            for ci, cam in enumerate(CAMERAS):
                out["nees"][cam] = _nees_entry(self._nees_sum[ci], int(self._nees_n[ci]))
        return out
