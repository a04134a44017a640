"""The `jaxloc` command line: `table1`, `simulate`, `cameras`, `calibrate`, `localize`,
`design`."""

import argparse
import json
import os
import sys
import time

import numpy as np

from . import design as _cli_design, images as _cli_images


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


def _fmt(x: float, width: int = 7) -> str:
    if not np.isfinite(x):
        return "n/a".rjust(width)
    if abs(x) >= 1000:
        return f"{x:{width}.0f}"
    return f"{x:{width}.2f}"


def format_table(strategy: str, summary: dict, methods: tuple[str, ...]) -> str:
    """The paper's Table I layout for one strategy, with jaxloc's distributions beside it."""
    from .._cycle.layout import CAMERAS

    lines = []
    n = summary["n_trials"]
    fails = []
    for m in methods:
        f = summary["methods"][m]["failures"]
        text = ", ".join(f"{k} {v}" for k, v in f.items()) or "none"
        fails.append(f"{METHOD_LABELS.get(m, m)}: {text}")
    lines.append(
        f"{strategy.capitalize()} strategy — {n} trials; failures skipped ({'; '.join(fails)})"
    )
    head = f"{'Camera':<10}{'paper run':>10} |"
    sub = f"{'':<10}{'(1 trial)':>10} |"
    for m in methods:
        head += f" {METHOD_LABELS.get(m, m):^23} |"
        sub += f" {'median':>7}{'RMSE':>8}{'p90':>8} |"
    crlb = summary.get("crlb")
    if crlb is not None:
        head += f" {'Cramér–Rao bound':^23} | {'effic.':>6}"
        sub += f" {'median':>7}{'RMSE':>8}{'p90':>8} | {'':>6}"
    labels = {"C": "C", "C1": "C1", "C2": "C2", "C3": "C3"}
    if strategy == "concurrent":
        labels["C1"] = "C1 (ref)"
    rows = (
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
    for title, key, scale, paper_key, crlb_key in rows:
        lines.append("")
        lines.append(title)
        lines.append(head)
        lines.append(sub)
        for ci, cam in enumerate(CAMERAS):
            paper = PAPER_TABLE1[strategy][paper_key][ci] if paper_key else float("nan")
            row = f"{labels[cam]:<10}{_fmt(paper, 10)} |"
            for m in methods:
                s = summary["methods"][m]["cameras"][cam][key]
                med, rmse, p90 = (s[k] * scale for k in ("median", "rmse", "p90"))
                row += f" {_fmt(med)}{_fmt(rmse, 8)}{_fmt(p90, 8)} |"
            if crlb is not None and crlb_key is not None and cam in crlb:
                bound = crlb[cam][crlb_key] * scale
                sampled = crlb[cam].get(key, {})
                med, p90 = (sampled.get(k, float("nan")) * scale for k in ("median", "p90"))
                best = methods[-1]  # the most refined method run
                mc = summary["methods"][best]["cameras"][cam][key]["rmse"] * scale
                eff = bound / mc if mc > 0 and bound > 0 else float("nan")
                row += f" {_fmt(med)}{_fmt(bound, 8)}{_fmt(p90, 8)} | {_fmt(eff, 6)}"
            lines.append(row)
    if crlb is not None:
        lines.append("")
        lines.append(
            "Cramér–Rao bound: RMSE = sqrt of the mean bound over the trials' true "
            "geometries; median and p90 of one draw from N(0, bound) per trial (an estimator "
            "exactly at the bound, tails included); efficiency = bound RMSE / "
            f"{METHOD_LABELS.get(methods[-1], methods[-1])} RMSE (1 = at the bound)."
        )
    nees = summary.get("nees")
    if nees is not None:
        parts = []
        for cam, d in nees.items():
            if d["n"]:
                lo, hi = d["interval95"]
                parts.append(f"{cam} {d['mean']:.2f}")
        lines.append(
            "Covariance consistency (refined): mean NEES of final positions "
            + ", ".join(parts)
            + f"; expected 3, 95% interval of the mean [{lo:.2f}, {hi:.2f}]."
        )
    return "\n".join(lines)


def _assumptions(scenario, trials: int, seed: int) -> str:
    noise = {
        "paper": "radius ~ N(0, sigma), uniform direction (the paper's model)",
        "gaussian": "isotropic Gaussian, sigma per axis",
    }[scenario.rig.noise_model]
    return (
        f"Assumptions: pixel noise sigma = {scenario.rig.sigma_text()} px, {noise}; "
        f"odometry sigma = {100 * float(scenario.odometry_sigma_rel):g}% of the distance; "
        f"{trials} trials per strategy; seed {seed}; {scenario.base.dtype}.\n"
        "Errors are of the end-of-cycle poses in the cycle's world frame (C1's body frame at "
        "the start). 'paper run' is the paper's single simulated run (Table I)."
    )


def _use_every_core() -> int | None:
    """Expose every core this process may use as a JAX CPU device, so that a study's
    trials are sharded over all of them (XLA runs a CPU device's program on one core).
    Left alone when `XLA_FLAGS` or JAX's `jax_num_cpu_devices` already set a count, or
    when JAX has already started. Returns the count set."""
    import jax

    if "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""):
        return None
    if jax.config.jax_num_cpu_devices != -1:
        return None
    n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    n = n or 1
    try:
        jax.config.update("jax_num_cpu_devices", n)
    except RuntimeError:
        return None
    return n


def _enable_compile_cache() -> str | None:
    """Keep compiled XLA programs on disk between runs (JAX's persistent compilation
    cache), so that only a command's first run pays for compilation. The folder is
    `$JAXLOC_COMPILE_CACHE` (`off` disables it), else `$XDG_CACHE_HOME/jaxloc/xla` or
    `~/.cache/jaxloc/xla`; a cache the user configured for JAX is left as it is."""
    import jax

    if jax.config.jax_compilation_cache_dir:
        return jax.config.jax_compilation_cache_dir
    path = os.environ.get("JAXLOC_COMPILE_CACHE")
    if path is None:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        path = os.path.join(base, "jaxloc", "xla")
    if path.strip().lower() in ("", "0", "off", "none", "false"):
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    return path


def _run(scenarios: dict, args, title: str, compile_order=None) -> int:
    import jax

    from .._study.engine import (
        balanced_chunk_size,
        compile_in_background,
        run_study,
        stream_study,
    )
    from .._study.stats import summarize
    from .._study.trial import METHODS

    methods = tuple(args.methods.split(",")) if args.methods else METHODS
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(
            f"--methods must be a comma-separated subset of {METHODS}; got {args.methods!r}."
        )
    report = {"title": title, "trials": args.trials, "seed": args.seed, "strategies": {}}
    print(title)
    first = next(iter(scenarios.values()))
    print(_assumptions(first, args.trials, args.seed))
    if args.stream and args.plot:
        raise ValueError("--plot needs every trial's errors; it cannot be used with --stream.")
    studies = {}
    chunk_size = args.chunk_size or balanced_chunk_size(args.trials)
    if args.out is not None and args.chunk_size is None:
        for strategy in scenarios:
            manifest = os.path.join(args.out, strategy, "study.json")
            if os.path.exists(manifest):  # resume with the chunks already on disk
                with open(manifest) as f:
                    chunk_size = int(json.load(f)["chunk_size"])
    t_start = time.perf_counter()
    report["devices"] = jax.device_count()
    # Programs compile in background threads, traced in `compile_order` (the fastest to
    # compile first): each study runs as soon as its program is ready, while the others
    # are still compiling. Tables print in the order of `scenarios`.
    compile_order = [s for s in (compile_order or ()) if s in scenarios]
    compile_order += [s for s in scenarios if s not in compile_order]
    compiled_at = {}
    if len(scenarios) > 1:
        threads = compile_in_background(
            [scenarios[s] for s in compile_order], chunk_size, methods
        )
    summaries = {}
    for i, strategy in enumerate(compile_order):
        if len(scenarios) > 1:
            threads[i].join()
            compiled_at[strategy] = time.perf_counter() - t_start
        t0 = time.perf_counter()
        out_dir = None if args.out is None else f"{args.out}/{strategy}"
        kwargs = dict(
            seed=args.seed,
            chunk_size=chunk_size,
            methods=methods,
            out_dir=out_dir,
            progress=not args.no_progress,
        )
        if args.stream:
            summary = stream_study(scenarios[strategy], args.trials, **kwargs)
        else:
            study = run_study(scenarios[strategy], args.trials, **kwargs)
            summary = summarize(study, methods)
            studies[strategy] = study
        summary["seconds"] = time.perf_counter() - t0
        summaries[strategy] = summary
    if compiled_at:
        report["compile_seconds"] = max(compiled_at.values())
        print(
            f"\n(compiled {len(scenarios)} studies in parallel threads, each study running "
            f"as soon as its program was ready: {report['compile_seconds']:.1f} s until the "
            f"last was compiled; trials sharded over {jax.device_count()} "
            f"{jax.devices()[0].platform.upper()} devices)"
        )
    for strategy in scenarios:
        summary = summaries[strategy]
        report["strategies"][strategy] = summary
        print()
        print(format_table(strategy, summary, methods))
        print(f"({summary['seconds']:.1f} s"
              f"{'' if len(scenarios) > 1 else ' including compilation'})")
    report["total_seconds"] = time.perf_counter() - t_start
    print(f"\nTotal {report['total_seconds']:.1f} s.")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=2)
        print(f"\nwrote {args.json}")
    if args.plot:
        _plot(studies, methods, args.plot)
        print(f"wrote {args.plot}")
    return 0


def _plot(studies: dict, methods, path: str):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .._cycle.layout import CAMERAS

    fig, axes = plt.subplots(len(studies), 4, figsize=(16, 3.6 * len(studies)), squeeze=False)
    for row, (strategy, study) in enumerate(studies.items()):
        for ci, cam in enumerate(CAMERAS):
            ax = axes[row, ci]
            errs = {}
            for mi, m in enumerate(methods):
                ok = study["status"][:, mi] == 0
                err = 100 * study["position"][ok, mi, ci]
                errs[m] = err[err > 0]
            positive = [e for e in errs.values() if e.size]
            if not positive:
                ax.text(0.5, 0.5, "reference robot:\nexact by definition", ha="center",
                        va="center", transform=ax.transAxes)
                ax.set_axis_off()
                continue
            lo = min(np.percentile(e, 0.5) for e in positive)
            hi = max(np.percentile(e, 99.5) for e in positive)
            bins = np.logspace(np.log10(lo), np.log10(hi), 60)
            for m, err in errs.items():
                ax.hist(err, bins=bins, alpha=0.5, label=METHOD_LABELS.get(m, m))
            ax.set_xscale("log")
            ax.set_title(f"{strategy}: {cam}")
            ax.set_xlabel("position error (cm, log scale)")
            ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def _cmd_table1(args) -> int:
    from .._sim.scenario import Scenario

    scenarios = {s: Scenario.paper(strategy=s) for s in ("concurrent", "sequential")}
    # The sequential study's program is the smaller one: it compiles first, and its
    # trials run while the concurrent study's program is still compiling.
    return _run(
        scenarios, args, "jaxloc table1 — the paper's Table I (simulation) as distributions",
        compile_order=("sequential", "concurrent"),
    )


def _cmd_simulate(args) -> int:
    from .._sim.scenario_file import load_scenario

    scenario = load_scenario(args.scenario)
    return _run({scenario.strategy: scenario}, args, f"jaxloc simulate — {args.scenario}")


def _cmd_cameras(args) -> int:
    import jax.numpy as jnp

    from .._cameras.presets import (
        field_of_view,
        paper_omni_camera,
        paper_overhead_camera,
        paper_ptz_camera,
    )

    cams = {
        "overhead (C, perspective)": paper_overhead_camera(),
        "PTZ (C1, wide end)": paper_ptz_camera(zoom=0.0),
        "PTZ (C1, tele end)": paper_ptz_camera(zoom=1.0),
        "omni (C2, C3)": paper_omni_camera(),
    }
    for name, cam in cams.items():
        w, h = cam.image_size
        u, v = np.meshgrid(np.linspace(0, w - 1, 41), np.linspace(0, h - 1, 31))
        px = jnp.asarray(np.stack([u, v], -1).reshape(-1, 2))
        rays = cam.unproject(px)
        ok = np.asarray(cam.projectable(rays))
        back = np.asarray(cam.project(rays))
        err = np.abs(back - np.asarray(px))[ok].max() if ok.any() else float("nan")
        fov = ", ".join(f"{k} {v:.1f}" for k, v in field_of_view(cam).items())
        print(f"{name:<28} {w}x{h}  {fov}  round-trip max error {err:.1e} px")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="jaxloc", description="Cooperative localization of a heterogeneous robot team."
    )
    sub = parser.add_subparsers(dest="command", required=True)

    def study_args(p):
        p.add_argument("--trials", type=int, default=10_000, help="trials per strategy")
        p.add_argument("--seed", type=int, default=0)
        p.add_argument(
            "--chunk-size",
            type=int,
            help="trials per compiled call (default: the fewest chunks of at most 4096 "
            "trials with the least padding; a resumed --out study keeps its own)",
        )
        p.add_argument("--json", metavar="FILE", help="write every number as JSON")
        p.add_argument("--plot", metavar="FILE", help="error histograms per camera (PNG)")
        p.add_argument("--out", metavar="DIR", help="stream chunks to DIR (resumable)")
        p.add_argument("--no-progress", action="store_true")
        p.add_argument(
            "--stream",
            action="store_true",
            help="bounded memory for any number of trials: keep only running statistics "
            "(percentiles from histograms, within 1.2%%); no --plot",
        )
        p.add_argument(
            "--methods",
            metavar="LIST",
            help="comma-separated estimators to compare (default: paper,robust,refined)",
        )

    p = sub.add_parser("table1", help="the paper's Table I as distributions over many trials")
    study_args(p)
    p.set_defaults(func=_cmd_table1)
    p = sub.add_parser("simulate", help="Monte Carlo study of a scenario file (YAML/JSON)")
    p.add_argument("--scenario", required=True, metavar="FILE")
    study_args(p)
    p.set_defaults(func=_cmd_simulate)
    p = sub.add_parser("cameras", help="the paper's preset cameras and a round-trip check")
    p.set_defaults(func=_cmd_cameras)
    _cli_images.register(sub)
    _cli_design.register(sub)

    args = parser.parse_args(argv)
    if getattr(args, "trials", 1) <= 0:
        parser.error(f"--trials must be positive; got {args.trials}")
    if getattr(args, "chunk_size", None) is not None and args.chunk_size <= 0:
        parser.error(f"--chunk-size must be positive; got {args.chunk_size}")
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError) as e:
        print(f"jaxloc: error: {e}", file=sys.stderr)
        return 2


def console_main() -> int:
    """The `jaxloc` command: `main` in float64 (JAX's 64-bit mode), with every core
    exposed as a JAX CPU device and the persistent compilation cache on. A Python program
    calling `main` keeps its own JAX configuration (and its own dtype)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    _use_every_core()
    _enable_compile_cache()
    return main()


if __name__ == "__main__":
    sys.exit(console_main())
