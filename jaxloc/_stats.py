"""Summary statistics of a Monte Carlo study, skipping (and counting) failed trials.

[`jaxloc.summarize`][] works on a study held in memory (exact order statistics);
[`jaxloc.StreamingSummary`][] folds in one chunk at a time and keeps only fixed-size
accumulators, for studies too large to hold (10^7 trials and more).
"""

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


#: Error histograms of [`StreamingSummary`][]: log-spaced bins from 1e-12 to 1e3 (m or
#: rad), this many per decade; a percentile is read to within one bin, a relative error
#: below 10**(1/200) - 1 = 1.2% (about 0.6% typical, from interpolation inside the bin).
BINS_PER_DECADE = 200
_LOG_LO, _LOG_HI = -12, 3


class StreamingSummary:
    """[`jaxloc.summarize`][]'s statistics accumulated chunk by chunk in bounded memory.

    Means, RMSEs, failure counts, the Cramér–Rao means and the NEES means are exact (sums
    in float64). Medians and percentiles come from log-spaced histograms
    (`BINS_PER_DECADE` bins per decade between 1e-12 and 1e3; smaller values, such as the
    reference robot's exact zero, count as 0): each is within 1.2% (relative) of the exact
    order statistic. Memory: about 1 MB whatever the number of trials.

    Usage: `acc = StreamingSummary(methods)`, then `acc.update(chunk_arrays)` for each
    chunk (the dict [`jaxloc.run_chunk`][] returns), then `acc.result()`.
    """

    def __init__(self, methods: tuple[str, ...]):
        self.methods = tuple(methods)
        m, c = len(self.methods), len(CAMERAS)
        self._edges = np.logspace(_LOG_LO, _LOG_HI, (_LOG_HI - _LOG_LO) * BINS_PER_DECADE + 1)
        nb = self._edges.size + 1  # [0, lo), the bins, [hi, inf)
        self._metrics = ("position_m", "rotation_rad", "ypr_mean_abs_rad")
        self._hist = np.zeros((len(self._metrics), m, c, nb), np.int64)
        self._sum = np.zeros((len(self._metrics), m, c))
        self._sumsq = np.zeros((len(self._metrics), m, c))
        self._n_ok = np.zeros(m, np.int64)
        self._failures = [Counter() for _ in range(m)]
        self._n = 0
        self._crlb = np.zeros((2, c))
        self._crlb_n = 0
        self._nees_sum = np.zeros(c)
        self._nees_n = np.zeros(c, np.int64)

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
            for k, v in enumerate(values):
                x = v[ok, mi].astype(np.float64)  # (n_ok, cameras)
                self._sum[k, mi] += x.sum(axis=0)
                self._sumsq[k, mi] += (x * x).sum(axis=0)
                nb = self._hist.shape[-1]
                bins = np.searchsorted(self._edges, x, side="right") + nb * np.arange(x.shape[1])
                counts = np.bincount(bins.ravel(), minlength=nb * x.shape[1])
                self._hist[k, mi] += counts.reshape(x.shape[1], nb)
        if "crlb_position_var" in arrays:
            all_ok = np.all(status == 0, axis=1)
            self._crlb[0] += arrays["crlb_position_var"][all_ok].sum(axis=0)
            self._crlb[1] += arrays["crlb_rotation_var"][all_ok].sum(axis=0)
            self._crlb_n += int(all_ok.sum())
        if "refined" in self.methods and "nees" in arrays:
            ok = status[:, self.methods.index("refined")] == 0
            x = arrays["nees"][ok]
            finite = np.isfinite(x)
            self._nees_sum += np.where(finite, x, 0.0).sum(axis=0)
            self._nees_n += finite.sum(axis=0)

    def _quantile(self, hist: np.ndarray, n: int, q: float) -> float:
        # Rank of np.percentile's linear interpolation, read off the histogram with a
        # log-linear interpolation inside the bin that holds it.
        rank = q * (n - 1)
        cum = np.cumsum(hist)
        b = int(np.searchsorted(cum, rank, side="right"))
        if b == 0:
            return 0.0
        if b >= hist.size - 1:
            return float(self._edges[-1])
        lo, hi = np.log(self._edges[b - 1]), np.log(self._edges[b])
        frac = (rank - cum[b - 1]) / hist[b]
        return float(np.exp(lo + min(max(frac, 0.0), 1.0) * (hi - lo)))

    def _describe(self, k: int, mi: int, ci: int) -> dict[str, float]:
        n = int(self._n_ok[mi])
        if n == 0:
            return {key: float("nan") for key in ("mean", "median", "rmse", "p90", "p99")}
        h = self._hist[k, mi, ci]
        return {
            "mean": float(self._sum[k, mi, ci] / n),
            "median": self._quantile(h, n, 0.5),
            "rmse": float(np.sqrt(self._sumsq[k, mi, ci] / n)),
            "p90": self._quantile(h, n, 0.9),
            "p99": self._quantile(h, n, 0.99),
        }

    def result(self) -> dict:
        """The dict [`jaxloc.summarize`][] returns, for every trial folded in so far."""
        out = {"n_trials": self._n, "methods": {}, "percentiles": "histogram"}
        for mi, method in enumerate(self.methods):
            cameras = {
                cam: {
                    metric: self._describe(k, mi, ci)
                    for k, metric in enumerate(self._metrics)
                }
                for ci, cam in enumerate(CAMERAS)
            }
            out["methods"][method] = {
                "n_ok": int(self._n_ok[mi]),
                "failures": dict(sorted(self._failures[mi].items())),
                "cameras": cameras,
            }
        if self._crlb_n:
            n = self._crlb_n
            out["crlb"] = {
                cam: {
                    "position_rmse_m": float(np.sqrt(self._crlb[0, ci] / n)),
                    "rotation_rmse_rad": float(np.sqrt(self._crlb[1, ci] / n)),
                }
                for ci, cam in enumerate(CAMERAS)
            }
        if "refined" in self.methods and self._nees_n.any():
            out["nees"] = {}
            for ci, cam in enumerate(CAMERAS):
                n = int(self._nees_n[ci])
                half = 1.96 * np.sqrt(2 * 3 / max(n, 1))
                out["nees"][cam] = {
                    "mean": float(self._nees_sum[ci] / n) if n else float("nan"),
                    "expected": 3.0,
                    "interval95": [3.0 - half, 3.0 + half],
                    "n": n,
                }
        return out
