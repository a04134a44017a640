"""`jaxloc track`: the team tracked over many cycles, as a Monte Carlo study (issue 21).

Wire with `register(sub)` on the `jaxloc` sub-parsers.
"""

import argparse
import math
import os
import sys
import time

import numpy as np

from .common import (
    chatter,
    check_outputs,
    check_seed_arg,
    EXIT_CODES_HELP,
    EXIT_NO_RESULT,
    EXIT_OK,
    HelpFormatter,
    quiet_option,
    write_report,
)


_LABELS = {"chain": "chaining", "smoother": "smoother", "one_step": "one-step"}
_BOUNDS = {"chain": "chained", "smoother": "window", "one_step": "own"}


def register(sub: argparse._SubParsersAction, parents=None) -> None:
    """Add the `track` subcommand to `jaxloc`'s sub-parsers (with the options of the
    `parents` parsers; default: `--quiet`)."""
    parents = [quiet_option()] if parents is None else list(parents)
    p = sub.add_parser(
        "track", parents=parents, epilog=EXIT_CODES_HELP, formatter_class=HelpFormatter,
        help="track the team over many cycles: chaining, fixed-lag smoother, one-step",
        description=(
            "Monte Carlo study of K consecutive cycles of a scenario (its `tracking` "
            "section: the climbing robot's motion and odometry between cycles). Prints, per "
            "cycle and robot, the position error (median / RMSE / p90) of each cycle chained "
            "into the first cycle's frame, of the fixed-lag smoother, and of one-step "
            "localization of the climbing robot (in each cycle's own frame), each beside its "
            "bound; writes --json and a --plot (top view of one run with uncertainty "
            "ellipses, and error against cycle)."
        ),
    )
    p.add_argument("--scenario", required=True, metavar="FILE",
                   help="scenario file (YAML/JSON), with an optional `tracking` section")
    p.add_argument("--cycles", type=int, required=True, metavar="K", help="cycles per run")
    p.add_argument("--runs", type=int, default=1000, help="Monte Carlo runs (default 1000)")
    p.add_argument("--window", type=int, default=None, metavar="W",
                   help="the smoother's window in cycles (default 2)")
    p.add_argument("--seed", type=int, default=0,
                   help="the study's seed, an integer in [0, 4294967295] (2**32 - 1)")
    p.add_argument("--chunk-size", type=int, default=None,
                   help="runs per compiled call (default: the fewest chunks of at most 1024 "
                        "runs; a resumed --out study keeps its own)")
    p.add_argument("--json", metavar="FILE", help="write every number as JSON (strict)")
    p.add_argument("--plot", metavar="FILE",
                   help="PNG: top view of the first run (smoother with 2-sigma ellipses, "
                        "chaining, truth) and RMSE against cycle with the bounds")
    p.add_argument("--out", metavar="DIR", help="stream chunks to DIR (resumable: run the "
                   "same command again after an interruption)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_track)


def _check_args(args) -> None:
    for name in ("cycles", "runs"):
        if getattr(args, name) <= 0:
            raise ValueError(f"--{name} must be positive; got {getattr(args, name)}.")
    if args.window is not None and args.window <= 0:
        raise ValueError(f"--window must be positive; got {args.window}.")
    if args.chunk_size is not None and args.chunk_size <= 0:
        raise ValueError(f"--chunk-size must be positive; got {args.chunk_size}.")
    check_seed_arg("--seed", args.seed)
    check_outputs(args, files=("json",), dirs=("out",))


def _chunk_size(args) -> int:
    from .._study.chunks import read_manifest
    from .._study.engine import balanced_chunk_size

    if args.chunk_size is not None:
        return args.chunk_size
    if args.out is not None:
        manifest = read_manifest(args.out)
        if manifest is not None:
            return int(manifest["chunk_size"])
    return balanced_chunk_size(args.runs, 1024)


def _assumptions(track, args, window: int) -> str:
    s = track.scenario
    return (
        f"Assumptions: {s.strategy} cycles; pixel noise sigma = {s.rig.sigma_text()} px "
        f"({s.rig.noise_model} model); ground odometry sigma = "
        f"{100 * float(s.odometry_sigma_rel):g}% of the distance; climbing robot's odometry "
        f"sigma = {100 * float(track.climber_odometry_sigma_rel):g}% of its step per axis and "
        f"{math.degrees(float(track.climber_odometry_rotation_sigma)):.2g} deg per axis; "
        f"first one-step prior: height sigma {100 * float(track.height_prior_sigma):g} cm, "
        f"tilt sigma {math.degrees(float(track.tilt_prior_sigma)):.3g} deg; smoother window "
        f"{window} cycles; {args.runs} runs of {args.cycles} cycles; seed {args.seed}; "
        f"{s.base.dtype}.\n"
        "Chaining and smoother: end-of-cycle positions in the first cycle's frame (C1's body "
        "frame at the start). One-step: the climbing robot (and the formation at its prior's "
        "scale) at each cycle's first step, in that cycle's frame. Statistics over the runs "
        "whose method succeeded up to that cycle; ratio = RMSE / bound."
    )


def _shown_cycles(K: int) -> list[int]:
    if K <= 25:
        return list(range(K))
    step = max(1, K // 20)
    return sorted(set(list(range(5)) + list(range(step - 1, K, step)) + [K - 1]))


def format_track_table(summary: dict) -> str:
    """The per-robot, per-cycle table of a [`jaxloc.summarize_track`][] summary (cm)."""
    from .._cycle.layout import CAMERAS

    methods = list(summary["methods"])
    K = summary["cycles"]
    lines = []
    head = f"{'cycle':>5} |"
    sub = f"{'':>5} |"
    for m in methods:
        head += f" {_LABELS[m] + ' (' + _BOUNDS[m] + ' bound)':^39} |"
        sub += f" {'median':>7}{'RMSE':>8}{'p90':>8}{'bound':>9}{'ratio':>7} |"
    for cam in CAMERAS:
        lines.append("")
        lines.append(f"Position error of {cam} (cm)")
        lines.append(head)
        lines.append(sub)
        for k in _shown_cycles(K):
            row = f"{k + 1:>5} |"
            for m in methods:
                c = summary["methods"][m][k]
                r = c["robots"][cam]
                if c["n_ok"] == 0:
                    row += f" {'no successful run':^39} |"
                    continue
                p = r["position_m"]
                row += (f" {100 * p['median']:7.2f}{100 * p['rmse']:8.2f}{100 * p['p90']:8.2f}"
                        f"{100 * r['bound_position_rmse_m']:9.2f}{_ratio(r['ratio']):>7} |")
            lines.append(row)
    lines.append("")
    last = K - 1
    for m in methods:
        c = summary["methods"][m][last]
        fails = ", ".join(f"{k} {v}" for k, v in c["failures"].items()) or "none"
        lines.append(f"{_LABELS[m]}: {c['n_ok']} runs successful at cycle {K}; others: {fails}")
    return "\n".join(lines)


def _ratio(x: float) -> str:
    return "n/a" if not np.isfinite(x) else f"{x:.2f}"


def targets(summary: dict) -> dict:
    """The issue's targets, measured: every robot's position RMSE within 1.2x its bound at
    every cycle (chaining against the chained bound, smoother against its window bound),
    and the smoother's RMSE of C at the last cycle against chaining's."""
    from .._cycle.layout import CAMERAS

    out = {}
    for m in ("chain", "smoother"):
        ratios = [c["robots"][cam]["ratio"] for c in summary["methods"][m] for cam in CAMERAS
                  if cam != "C1" or np.isfinite(c["robots"][cam]["ratio"])]  # fmt: skip
        ratios = [r for r in ratios if np.isfinite(r)]
        worst = max(ratios) if ratios else float("nan")
        out[f"{m}_worst_ratio"] = worst
        out[f"{m}_within_1.2"] = bool(worst <= 1.2)
    last = summary["cycles"] - 1
    c_chain = summary["methods"]["chain"][last]["robots"]["C"]["position_m"]["rmse"]
    c_smooth = summary["methods"]["smoother"][last]["robots"]["C"]["position_m"]["rmse"]
    out["smoother_vs_chain_C_last"] = 1.0 - c_smooth / c_chain if c_chain > 0 else float("nan")
    out["smoother_30pct_below_chain"] = bool(out["smoother_vs_chain_C_last"] >= 0.3)
    return out


def plot_track(study: dict, summary: dict, path: str) -> None:
    """[`track_figure`][] written to `path` (PNG or any format matplotlib writes)."""
    track_figure(study, summary).savefig(path, dpi=110)


def track_figure(study: dict, summary: dict):
    """Top view of the first run (truth, chaining, smoother with 2-sigma ellipses) and the
    RMSE of every robot against cycle beside the bounds, as a matplotlib `Figure` (no
    pyplot state: a notebook shows it by displaying the returned figure)."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Ellipse

    from .._cycle.layout import CAMERAS

    fig = Figure(figsize=(13, 5.5))
    ax, ax2 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    truth = study["truth_position"][0]  # (K, 4, 3)
    vec = study["position_vector"][0]  # (K, 3, 4, 3)
    cov = study["covariance_xy"][0]  # (K, 3, 4, 3)
    ok = study["status"][0] == 0  # (K, 3)
    colors = ["tab:red", "tab:blue", "tab:green", "tab:orange"]
    for r, cam in enumerate(CAMERAS):
        ax.plot(truth[:, r, 0], truth[:, r, 1], "-", color=colors[r], lw=1, label=f"{cam} truth")
        for m, (marker, name) in enumerate((("x", "chaining"), ("o", "smoother"))):
            good = ok[:, m]
            est = truth[good, r, :2] + vec[good, m, r, :2]
            ax.plot(est[:, 0], est[:, 1], marker, color=colors[r], ms=4, mfc="none",
                    label=f"{cam} {name}" if r == 0 else None)  # fmt: skip
        for k in np.nonzero(ok[:, 1])[0]:
            xx, xy, yy = cov[k, 1, r]
            P = np.array([[xx, xy], [xy, yy]])
            w, V = np.linalg.eigh(P)
            w = np.maximum(w, 0)
            angle = np.degrees(np.arctan2(V[1, 1], V[0, 1]))
            centre = truth[k, r, :2] + vec[k, 1, r, :2]
            ax.add_patch(Ellipse(centre, 4 * np.sqrt(w[1]), 4 * np.sqrt(w[0]), angle=angle,
                                 fill=False, color=colors[r], lw=0.6))  # fmt: skip
    ax.set_aspect("equal")
    ax.set_xlabel("x in W_0 (m)")
    ax.set_ylabel("y in W_0 (m)")
    ax.set_title("Run 1, top view: end of each cycle (smoother's 2-sigma ellipses)")
    ax.legend(fontsize=7, loc="best")
    K = summary["cycles"]
    cycles = np.arange(1, K + 1)
    styles = {"chain": "-", "smoother": "-", "one_step": ":"}
    for m in summary["methods"]:
        for r, cam in enumerate(CAMERAS):
            if cam == "C1" and m == "one_step":
                continue
            rmse = [100 * c["robots"][cam]["position_m"]["rmse"] for c in summary["methods"][m]]
            bound = [100 * c["robots"][cam]["bound_position_rmse_m"]
                     for c in summary["methods"][m]]  # fmt: skip
            lw = 2 if cam == "C" else 0.8
            ax2.plot(cycles, rmse, styles[m], color=colors[r], lw=lw,
                     marker={"chain": "x", "smoother": "o", "one_step": "."}[m], ms=3,
                     label=f"{_LABELS[m]} {cam}" if r in (0, 1) else None)  # fmt: skip
            ax2.plot(cycles, bound, "--", color=colors[r], lw=0.6)
    ax2.set_yscale("log")
    ax2.set_xlabel("cycle")
    ax2.set_ylabel("position RMSE (cm); dashed: bound")
    ax2.set_title("Error against cycle (chaining x, smoother o, one-step dotted)")
    ax2.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    return fig


def _cmd_track(args) -> int:
    import jax

    _check_args(args)
    from .._track.scenario import load_track_scenario
    from .._track.study import run_track_study, summarize_track
    from .._track.tracker import DEFAULT_WINDOW

    track = load_track_scenario(args.scenario)
    window = DEFAULT_WINDOW if args.window is None else args.window
    chunk_size = _chunk_size(args)
    title = f"jaxloc track — {args.scenario}, {args.cycles} cycles"
    say = chatter(args)
    print(title)
    print(_assumptions(track, args, window))
    t0 = time.perf_counter()
    study = run_track_study(
        track, args.runs, args.cycles, seed=args.seed, chunk_size=chunk_size, window=window,
        out_dir=args.out, progress=not (args.no_progress or args.quiet),
    )  # fmt: skip
    seconds = time.perf_counter() - t0
    summary = summarize_track(study)
    print(format_track_table(summary))
    measured = targets(summary)
    one = summary["one_step"]
    print(
        f"\nSmoother's RMSE of C at cycle {args.cycles}: "
        f"{100 * measured['smoother_vs_chain_C_last']:.0f}% below chaining's. Worst RMSE / "
        f"bound over every cycle and robot: chaining {measured['chain_worst_ratio']:.2f}, "
        f"smoother {measured['smoother_worst_ratio']:.2f}. One-step: the root nearest the "
        f"truth refined in {100 * one['root_correct']:.2f}% of the cycles, "
        f"{100 * one['ambiguous']:.2f}% ambiguous, {one['wrong_root_successful']} wrong "
        "roots marked successful."
    )
    say(f"({seconds:.1f} s including compilation; {jax.device_count()} "
        f"{jax.devices()[0].platform.upper()} devices)")  # fmt: skip
    if args.json:
        report = {
            "title": title, "scenario": os.path.abspath(args.scenario), "runs": args.runs,
            "cycles": args.cycles, "window": window, "seed": args.seed,
            "chunk_size": chunk_size, "devices": jax.device_count(), "seconds": seconds,
            "summary": summary, "targets": measured,
        }  # fmt: skip
        write_report(args.json, report, quiet=args.quiet)
    if args.plot:
        plot_track(study, summary, args.plot)
        say(f"wrote {args.plot}")
    if not any(summary["methods"][m][0]["n_ok"] for m in summary["methods"]):
        print("jaxloc: no run's first cycle succeeded, with any method.", file=sys.stderr)
        return EXIT_NO_RESULT
    return EXIT_OK
