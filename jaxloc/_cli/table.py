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
    "robust-refined": "jaxloc refined (Huber, outliers out)",
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


def _header(methods: tuple[str, ...], with_crlb: bool, paper_run: bool) -> tuple[str, str]:
    head, sub = f"{'Camera':<10}", f"{'':<10}"
    if paper_run:
        head += f"{'paper run':>10} |"
        sub += f"{'(1 trial)':>10} |"
    else:
        head, sub = head + " |", sub + " |"
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


def _row_group(strategy: str, summary: dict, methods, row: tuple, paper_run: bool) -> list[str]:
    title, key, scale, paper_key, crlb_key = row
    crlb = summary.get("crlb")
    labels = {cam: cam for cam in CAMERAS}
    if strategy == "concurrent":
        labels["C1"] = "C1 (ref)"
    lines = ["", title, *_header(methods, crlb is not None, paper_run)]
    for ci, cam in enumerate(CAMERAS):
        line = f"{labels[cam]:<10}"
        if paper_run:
            paper = PAPER_TABLE1[strategy][paper_key][ci] if paper_key else float("nan")
            line += f"{_fmt(paper, 10)} |"
        else:
            line += " |"
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


def format_table(
    strategy: str, summary: dict, methods: tuple[str, ...], *, paper_run: bool = True
) -> str:
    """The paper's Table I layout for one strategy, with jaxloc's distributions beside it.

    **Arguments:** `strategy`; `summary`, [`jaxloc.summarize`][]'s (or a
    [`jaxloc.StreamingSummary`][]'s) dict; `methods`, the study's methods in order;
    `paper_run`, whether to show the paper's single simulated run (only meaningful for
    the paper's own scenario). Failed trials are skipped and counted in the title;
    statistics of an empty set of trials print as `n/a`."""
    lines = [_title(strategy, summary, methods)]
    for row in _ROWS:
        lines += _row_group(strategy, summary, methods, row, paper_run)
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


# How each estimator's curve is drawn: distinct line styles and markers, so that two
# methods that coincide (paper and robust do for C1-C3: they share the ground robots'
# closed form) both stay visible, one dashed over the other.
_STYLES = {
    "paper": dict(color="tab:orange", linestyle="-", linewidth=2.6, alpha=0.75),
    "robust": dict(color="tab:blue", linestyle=(0, (5, 3)), linewidth=1.6, marker="o",
                   markersize=3.5, markevery=0.1),
    "refined": dict(color="tab:green", linestyle="-.", linewidth=1.6, marker="s",
                    markersize=3.5, markevery=(0.05, 0.1)),
    "robust-refined": dict(color="tab:red", linestyle=":", linewidth=1.6, marker="^",
                           markersize=3.5, markevery=(0.02, 0.1)),
}
_BOUND_STYLE = dict(color="black", linestyle=":", linewidth=2.0)
# Panel rows of a strategy: title, study key of the methods' errors, of the bound's draws,
# scale to the printed unit, axis label.
_PANELS = (
    ("position", "position", "crlb_position_sample", 100.0, "position error (cm)"),
    ("orientation", "rotation", "crlb_rotation_sample", 180.0 / np.pi,
     "orientation error (deg, geodesic)"),
)  # fmt: skip


def _ecdf(ax, x: np.ndarray, n_total: int, label: str, style: dict) -> None:
    """Empirical CDF of `x` (the errors of the successful trials) as a fraction of all
    `n_total` trials: a method with failures ends below 1."""
    x = np.sort(x[np.isfinite(x)])
    if not x.size:
        return
    y = np.arange(1, x.size + 1) / n_total
    ax.step(x, y, where="post", label=label, **style)


def _cdf_panel(ax, study: dict, methods, ci: int, panel: tuple) -> bool:
    """The CDFs of one camera's errors, each method's and the Cramér-Rao bound's; False
    if there is nothing to show (the reference robot: zero error by definition)."""
    _, key, bound_key, scale, _ = panel
    n = study["status"].shape[0]
    curves = []
    for mi, m in enumerate(methods):
        ok = study["status"][:, mi] == 0
        curves.append((scale * study[key][ok, mi, ci], _label(m), _STYLES.get(m, {})))
    if bound_key in study:
        every_ok = np.all(study["status"] == 0, axis=1)
        curves.append((scale * study[bound_key][every_ok, ci], "Cramér–Rao bound",
                       _BOUND_STYLE))  # fmt: skip
    # The reference robot's errors are zero up to round-off (1e-16 deg): nothing to plot.
    positive = [x[x > 1e-9] for x, _, _ in curves]
    if not any(p.size for p in positive):
        return False
    for x, label, style in curves:
        _ecdf(ax, x, n, label, style)
    lo = min(np.percentile(p, 0.5) for p in positive if p.size)
    hi = max(np.percentile(p, 99.5) for p in positive if p.size)
    ax.set_xscale("log")
    ax.set_xlim(lo, hi)
    ax.set_ylim(0.0, 1.0)
    ax.grid(True, which="both", alpha=0.25)
    return True


def plot_studies(studies: dict, methods, path: str) -> None:
    """Error CDFs per strategy and camera, saved to `path`: for each strategy a row of
    position errors and a row of orientation errors (geodesic angle), one column per
    camera, every method's curve beside the Cramér–Rao bound's (one draw from
    N(0, bound) per trial: an estimator exactly at the bound)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [(strategy, panel) for strategy in studies for panel in _PANELS]
    fig, axes = plt.subplots(len(rows), 4, figsize=(17, 3.4 * len(rows)), squeeze=False)
    for r, (strategy, panel) in enumerate(rows):
        study = studies[strategy]
        for ci, cam in enumerate(CAMERAS):
            ax = axes[r, ci]
            if not _cdf_panel(ax, study, methods, ci, panel):
                ok = np.any(study["status"] == 0)
                text = "reference robot:\nexact by definition" if ok else "no successful trial"
                ax.text(0.5, 0.5, f"{strategy}: {cam}\n{text}", ha="center", va="center",
                        transform=ax.transAxes)  # fmt: skip
                ax.set_axis_off()
                continue
            ax.set_title(f"{strategy}: {cam}, {panel[0]}")
            ax.set_xlabel(f"{panel[4]}, log scale")
            if ci == 0 or not axes[r, 0].axison:
                ax.set_ylabel("fraction of trials ≤ x")
            ax.legend(fontsize=7, loc="lower right")
    counts = ", ".join(f"{s} {study['status'].shape[0]}" for s, study in studies.items())
    fig.suptitle(f"Error CDFs over {counts} trials (a method's failed trials keep its curve "
                 "below 1)", fontsize=11)  # fmt: skip
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
