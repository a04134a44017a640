"""The tables and plots of `jaxloc table1` and `jaxloc simulate`: the paper's Table I
layout with jaxloc's error distributions beside it, and error histograms."""

import numpy as np

from .._cycle.layout import CAMERAS


# The paper's Table I (one simulated run): position errors in cm, orientation errors in
# degrees (mean of yaw, pitch, roll errors), per camera C, C1, C2, C3.
PAPER_TABLE1 = {
    "concurrent": {
        "position_cm": [2.85, 0.0, 3.77, 1.84],
        "orientation_deg": [1.31, 0.0, 2.58, 0.97],
    },
    "sequential": {
        "position_cm": [1.77, 0.37, 0.92, 1.46],
        "orientation_deg": [0.83, 0.56, 0.86, 1.05],
    },
}
METHOD_LABELS = {
    "paper": "paper Eq. 6",
    "robust": "jaxloc robust",
    "refined": "jaxloc refined (ML)",
}
# Row groups of the table: title, summary key, scale to the printed unit, the paper's key
# and the Cramér–Rao key (None: no such column).
_ROWS = (
    ("Position error (cm, Euclidean)", "position_m", 100.0, "position_cm", "position_rmse_m"),
    (
        "Orientation error (deg, mean of |yaw|, |pitch|, |roll| errors)",
        "ypr_mean_abs_rad",
        180.0 / np.pi,
        "orientation_deg",
        None,
    ),
    (
        "Orientation error (deg, geodesic angle)",
        "rotation_rad",
        180.0 / np.pi,
        None,
        "rotation_rmse_rad",
    ),
)


def _label(method: str) -> str:
    return METHOD_LABELS.get(method, method)


def _fmt(x: float, width: int = 7) -> str:
    if not np.isfinite(x):
        return "n/a".rjust(width)
    if abs(x) >= 1000:
        return f"{x:{width}.0f}"
    return f"{x:{width}.2f}"


def _title(strategy: str, summary: dict, methods: tuple[str, ...]) -> str:
    fails = []
    for m in methods:
        f = summary["methods"][m]["failures"]
        text = ", ".join(f"{k} {v}" for k, v in f.items()) or "none"
        fails.append(f"{_label(m)}: {text}")
    n = summary["n_trials"]
    return f"{strategy.capitalize()} strategy — {n} trials; failures skipped ({'; '.join(fails)})"


def _header(methods: tuple[str, ...], with_crlb: bool) -> tuple[str, str]:
    head = f"{'Camera':<10}{'paper run':>10} |"
    sub = f"{'':<10}{'(1 trial)':>10} |"
    for m in methods:
        head += f" {_label(m):^23} |"
        sub += f" {'median':>7}{'RMSE':>8}{'p90':>8} |"
    if with_crlb:
        head += f" {'Cramér–Rao bound':^23} | {'effic.':>6}"
        sub += f" {'median':>7}{'RMSE':>8}{'p90':>8} | {'':>6}"
    return head, sub


def _crlb_cells(summary: dict, methods, cam: str, key: str, scale: float, crlb_key: str) -> str:
    """The bound's median, RMSE and p90 and the efficiency of the last (most refined)
    method, for one camera."""
    crlb = summary["crlb"][cam]
    bound = crlb[crlb_key] * scale
    sampled = crlb.get(key, {})
    med, p90 = (sampled.get(k, float("nan")) * scale for k in ("median", "p90"))
    mc = summary["methods"][methods[-1]]["cameras"][cam][key]["rmse"] * scale
    eff = bound / mc if mc > 0 and bound > 0 else float("nan")
    return f" {_fmt(med)}{_fmt(bound, 8)}{_fmt(p90, 8)} | {_fmt(eff, 6)}"


def _row_group(strategy: str, summary: dict, methods, row: tuple) -> list[str]:
    title, key, scale, paper_key, crlb_key = row
    crlb = summary.get("crlb")
    labels = {cam: cam for cam in CAMERAS}
    if strategy == "concurrent":
        labels["C1"] = "C1 (ref)"
    lines = ["", title, *_header(methods, crlb is not None)]
    for ci, cam in enumerate(CAMERAS):
        paper = PAPER_TABLE1[strategy][paper_key][ci] if paper_key else float("nan")
        line = f"{labels[cam]:<10}{_fmt(paper, 10)} |"
        for m in methods:
            s = summary["methods"][m]["cameras"][cam][key]
            med, rmse, p90 = (s[k] * scale for k in ("median", "rmse", "p90"))
            line += f" {_fmt(med)}{_fmt(rmse, 8)}{_fmt(p90, 8)} |"
        if crlb is not None and crlb_key is not None and cam in crlb:
            line += _crlb_cells(summary, methods, cam, key, scale, crlb_key)
        lines.append(line)
    return lines


def _nees_line(nees: dict) -> str:
    """The covariance-consistency line: mean NEES per camera with refined trials, and the
    95% interval of the mean for a consistent estimator."""
    counted = {cam: d for cam, d in nees.items() if d["n"]}
    if not counted:
        return "Covariance consistency (refined): no successful refined trial with a NEES."
    parts = [f"{cam} {d['mean']:.2f}" for cam, d in counted.items()]
    lo, hi = list(counted.values())[-1]["interval95"]
    return (
        "Covariance consistency (refined): mean NEES of final positions "
        + ", ".join(parts)
        + f"; expected 3, 95% interval of the mean [{lo:.2f}, {hi:.2f}]."
    )


def format_table(strategy: str, summary: dict, methods: tuple[str, ...]) -> str:
    """The paper's Table I layout for one strategy, with jaxloc's distributions beside it.

    **Arguments:** `strategy`; `summary`, [`jaxloc.summarize`][]'s (or a
    [`jaxloc.StreamingSummary`][]'s) dict; `methods`, the study's methods in order.
    Failed trials are skipped and counted in the title; statistics of an empty set of
    trials print as `n/a`."""
    lines = [_title(strategy, summary, methods)]
    for row in _ROWS:
        lines += _row_group(strategy, summary, methods, row)
    if summary.get("crlb") is not None:
        lines.append("")
        lines.append(
            "Cramér–Rao bound: RMSE = sqrt of the mean bound over the trials' true "
            "geometries; median and p90 of one draw from N(0, bound) per trial (an estimator "
            "exactly at the bound, tails included); efficiency = bound RMSE / "
            f"{_label(methods[-1])} RMSE (1 = at the bound)."
        )
    if summary.get("nees") is not None:
        lines.append(_nees_line(summary["nees"]))
    return "\n".join(lines)


def _histograms(ax, study: dict, methods, ci: int) -> bool:
    """Position-error histograms of each method's successful trials for camera `ci`;
    False if no method has a nonzero error to show."""
    errs = {}
    for mi, m in enumerate(methods):
        ok = study["status"][:, mi] == 0
        err = 100 * study["position"][ok, mi, ci]
        errs[m] = err[err > 0]
    positive = [e for e in errs.values() if e.size]
    if not positive:
        return False
    lo = min(np.percentile(e, 0.5) for e in positive)
    hi = max(np.percentile(e, 99.5) for e in positive)
    bins = np.logspace(np.log10(lo), np.log10(hi), 60)
    for m, err in errs.items():
        ax.hist(err, bins=bins, alpha=0.5, label=_label(m))
    return True


def plot_studies(studies: dict, methods, path: str) -> None:
    """Error histograms per strategy (rows) and camera (columns), saved to `path`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(studies), 4, figsize=(16, 3.6 * len(studies)), squeeze=False)
    for row, (strategy, study) in enumerate(studies.items()):
        for ci, cam in enumerate(CAMERAS):
            ax = axes[row, ci]
            if not _histograms(ax, study, methods, ci):
                ok = np.any(study["status"] == 0)
                text = "reference robot:\nexact by definition" if ok else "no successful trial"
                ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes)
                ax.set_axis_off()
                continue
            ax.set_xscale("log")
            ax.set_title(f"{strategy}: {cam}")
            ax.set_xlabel("position error (cm, log scale)")
            ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
