"""`jaxloc calibrate` and `jaxloc localize`: the image front end on the command line.

Wire with `register(sub)` on `jaxloc._cli.main`'s subparsers.
"""

import argparse
import glob
import json
import math
import os

import numpy as np

from .common import (
    chatter,
    check_outputs,
    EXIT_CODES_HELP,
    EXIT_NO_RESULT,
    EXIT_OK,
    HelpFormatter,
    quiet_option,
    write_report,
)


_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")

# Options of one camera model only, with the models they apply to: given for another
# model they are an error, not silently ignored.
_MODEL_OPTIONS = {
    "fix_aspect_ratio": ("pinhole", "ptz"),
    "fix_k3": ("pinhole", "ptz"),
    "zero_tangent": ("pinhole", "ptz"),
    "rational": ("pinhole", "ptz"),
    "fix_xi": ("omni",),
    "xi_init": ("omni",),
    "fix_distortion": ("omni",),
    "fix_coefficients": ("omni",),
    "fix_focal": ("omni",),
    "fix_center": ("omni",),
    "focal_init": ("omni",),
    "dist_init": ("omni",),
    "estimate_skew": ("omni",),
    "principal_point": ("omni",),
    "max_steps": ("omni",),
    "zoom": ("ptz",),
}


def _expand_images(patterns: list[str], what: str) -> list[str]:
    """Image paths from files, glob patterns and directories (every image file in it)."""
    images: list[str] = []
    for pattern in patterns:
        if os.path.isdir(pattern):
            matches = sorted(
                os.path.join(pattern, f)
                for f in os.listdir(pattern)
                if f.lower().endswith(_IMAGE_SUFFIXES)
            )
            if not matches:
                raise FileNotFoundError(f"Directory `{pattern}` ({what}) holds no image file.")
        elif any(c in pattern for c in "*?["):
            matches = sorted(glob.glob(pattern))
            if not matches:
                raise FileNotFoundError(f"No image matches `{pattern}` ({what}).")
        else:
            matches = [pattern]
        images.extend(matches)
    for p in images:
        if not os.path.isfile(p):
            raise FileNotFoundError(f"Image file `{p}` does not exist.")
    return images


_OMNI_COEFFICIENTS = ("k1", "k2", "p1", "p2")


def _coefficient_names(text: str) -> tuple[str, ...]:
    """`--fix-coefficients`: a comma-separated list of omni distortion coefficients."""
    names = tuple(n.strip() for n in text.split(","))
    bad = [n for n in names if n not in _OMNI_COEFFICIENTS]
    if bad or len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(
            f"expected distinct names among {','.join(_OMNI_COEFFICIENTS)}, comma-separated "
            f"(e.g. p1,p2); got {text!r}"
        )
    return names


def _check_model_options(args) -> None:
    for name, models in _MODEL_OPTIONS.items():
        value = getattr(args, name)
        if value not in (None, False, []) and args.model not in models:
            flag = "--" + name.replace("_", "-")
            raise ValueError(
                f"`{flag}` applies to --model {' or '.join(models)}, not --model {args.model}."
            )


def _check_calibrate_args(args) -> tuple[int, int]:
    """Every check of `jaxloc calibrate`'s arguments that needs no image: the board
    `(cols, rows)`, or a `ValueError` naming the option."""
    from .._vision.calibrate import parse_board

    board = parse_board(args.board)
    if not (math.isfinite(args.square) and args.square > 0):
        raise ValueError(f"`--square` must be a positive length in metres; got {args.square}.")
    _check_model_options(args)
    check_outputs(args, files=("out", "json"))
    if args.model == "ptz" and args.format == "kalibr":
        raise ValueError(
            "--model ptz writes one camera file holding the whole zoom table, which Kalibr's "
            "format cannot hold (a Kalibr camera has one set of intrinsics); use --format "
            "opencv, json or yaml."
        )
    if args.estimate_skew and args.format == "kalibr":
        raise ValueError(
            "`--estimate-skew` cannot be saved with `--format kalibr` (Kalibr's omni model "
            "has no skew); use the OpenCV, JSON or YAML format."
        )
    if args.rational and args.format == "kalibr":
        raise ValueError(
            "`--rational` cannot be saved with `--format kalibr` (Kalibr's radtan has 4 "
            "coefficients); use the OpenCV or JSON format."
        )
    return board


def _omni_options(args) -> dict:
    """`calibrate_omni`'s keyword arguments from the omni options."""
    omni_options = dict(
        window=args.window or 5, fix_xi=args.fix_xi, fix_distortion=args.fix_distortion,
        fix_skew=not args.estimate_skew,
        principal_point=tuple(args.principal_point) if args.principal_point else None,
    )  # fmt: skip
    # Given only when set, so that calibrate_omni's own defaults apply otherwise.
    for name in ("xi_init", "max_steps", "focal_init", "dist_init", "fix_coefficients"):
        value = getattr(args, name)
        if value is not None:
            omni_options[name] = tuple(value) if isinstance(value, list) else value
    for name in ("fix_focal", "fix_center"):
        if getattr(args, name):
            omni_options[name] = True
    return omni_options


def _cmd_calibrate(args) -> int:
    from .._cameras.files import save_camera
    from .._vision.calibrate import calibrate_omni, calibrate_pinhole

    board = _check_calibrate_args(args)
    pinhole_options = dict(
        fix_aspect_ratio=args.fix_aspect_ratio, fix_k3=args.fix_k3 or args.format == "kalibr",
        zero_tangent=args.zero_tangent, rational=args.rational, window=args.window or 11,
    )  # fmt: skip
    if args.model == "ptz":
        return _calibrate_ptz(args, board, pinhole_options)
    if not args.images:
        raise ValueError(f"--model {args.model} needs IMAGES (files, glob patterns or folders).")
    images = _expand_images(args.images, "IMAGES")
    if args.model == "pinhole":
        cal = calibrate_pinhole(images, board, args.square, **pinhole_options)
    else:
        cal = calibrate_omni(images, board, args.square, **_omni_options(args))
    extra = {"rms_px": cal.rms, "num_images": len(cal.used)}
    save_camera(cal.camera, args.out, args.format,
                extra=None if args.format == "kalibr" else extra)  # fmt: skip
    summary = cal.summary()
    _print_calibration(args, cal, summary, board, images)
    chatter(args)(f"wrote {args.out} ({args.format or 'auto'})")
    if args.json:
        write_report(args.json, summary, quiet=args.quiet)
    return EXIT_OK


def _print_calibration(args, cal, s: dict, board, images) -> None:
    """A pinhole or omni calibration's parameters (from its summary `s`), standard
    deviations and RMS."""
    print(f"{args.model} calibration from {len(cal.used)} of {len(images)} images "
          f"(board {board[0]}x{board[1]}, square {args.square} m)")  # fmt: skip
    if cal.rejected:
        print(f"  no board found in: {', '.join(cal.rejected)}")
    for name, value in s["camera"].items():
        if name in ("camera_matrix", "distortion_coefficients"):
            print(f"  {name}: {json.dumps(value)}")
    if "xi" in s["camera"]:
        print(f"  xi: {s['camera']['xi']:.6f}")
    print("  std: " + ", ".join(f"{k} {v:.3g}" for k, v in cal.std.items()))
    print(f"  reprojection RMS {cal.rms:.4f} px")


def _calibrate_ptz(args, board, pinhole_options) -> int:
    from .._cameras.files import save_camera
    from .._vision.calibrate import calibrate_ptz

    if args.images:
        raise ValueError(
            "--model ptz takes its images per zoom step (`--zoom Z IMAGES`, repeated), not "
            f"as IMAGES; got {args.images[:3]}."
        )
    if not args.zoom or len(args.zoom) < 2:
        raise ValueError(
            "--model ptz needs at least two zoom steps: `--zoom Z1 IMAGES1 --zoom Z2 IMAGES2`."
        )
    sets = []
    for z_text, pattern in args.zoom:
        try:
            z = float(z_text)
        except ValueError:
            raise ValueError(f"`--zoom` takes a zoom in [0, 1] then images; got {z_text!r}.")
        sets.append((z, _expand_images([pattern], f"--zoom {z_text}")))
    cal = calibrate_ptz(sets, board, args.square, **pinhole_options)
    n_img = sum(len(imgs) for _, imgs in sets)
    print(f"ptz calibration at {len(cal.zooms)} zoom steps from {n_img} images "
          f"(board {board[0]}x{board[1]}, square {args.square} m)")  # fmt: skip
    # One camera file: the PTZ with its whole zoom table (each step's report, with its
    # standard deviations, is in the --json report).
    extra = {"rms_px": [step.rms for step in cal.steps],
             "num_images": [len(step.used) for step in cal.steps]}  # fmt: skip
    save_camera(cal.camera, args.out, args.format, extra=extra)
    for z, step in zip(cal.zooms, cal.steps):
        c = step.camera
        print(f"  zoom {z:.3f}: fx {float(c.fx):.2f}, fy {float(c.fy):.2f}, "
              f"cx {float(c.cx):.2f}, cy {float(c.cy):.2f}, dist "
              f"{json.dumps(np.asarray(c.dist).round(6).tolist())}, RMS {step.rms:.4f} px "
              f"({len(step.used)} images)")  # fmt: skip
        if step.rejected:
            print(f"    no board found in: {', '.join(step.rejected)}")
    chatter(args)(f"  wrote {args.out} ({args.format or 'auto'}): one ptz camera with the "
                  f"{len(cal.zooms)}-step zoom table")  # fmt: skip
    if args.json:
        write_report(args.json, cal.summary(), quiet=args.quiet)
        chatter(args)(f"  zoom table and per-step reports: {args.json}")
    return EXIT_OK


def _check_localize_args(args) -> tuple[str, str]:
    """Every check of `jaxloc localize`'s arguments that needs no image; returns the
    poses JSON and plot paths (defaults beside the team file)."""
    stem = os.path.splitext(args.team)[0]
    out = args.out or stem + "_poses.json"
    plot = args.plot or stem + "_formation.png"
    check_outputs(argparse.Namespace(out=out, plot=plot), files=("out",))
    if args.no_refine and (args.loss is not None or args.loss_scale is not None):
        raise ValueError("--loss and --loss-scale apply to the refinement; drop --no-refine.")
    if args.loss_scale is not None and args.loss is None:
        raise ValueError(f"--loss-scale {args.loss_scale} needs --loss huber or --loss cauchy.")
    if args.loss_scale is not None and not (0 < args.loss_scale < float("inf")):
        raise ValueError(
            f"--loss-scale must be a positive number of standard deviations; got "
            f"{args.loss_scale}."
        )
    return out, plot


def _cmd_localize(args) -> int:
    from .._vision.localize import localize_images
    from .._vision.team import load_team

    out, plot = _check_localize_args(args)
    team = load_team(args.team)
    res = localize_images(
        team, refine=not args.no_refine, loss=args.loss, loss_scale=args.loss_scale
    )
    d = res.to_dict()
    print(f"{team.strategy} cycle from {args.team}: {d['status']} ({d['method']})")
    _print_poses(d)
    _print_fit(d["checks"])
    _print_sightings(d, args)
    for note in d["notes"]:
        print(f"  note: {note}")
    write_report(out, d, quiet=args.quiet)
    plot_formation(d, plot, title=f"{team.strategy} cycle from {os.path.basename(args.team)}")
    chatter(args)(f"wrote {plot}")
    return EXIT_OK if d["status"] == "successful" else EXIT_NO_RESULT


def _print_poses(d: dict) -> None:
    print("Poses at the end of the cycle, in W = C1's body frame at the start (m, deg):")
    for name, p in d["poses"].items():
        pos = ", ".join(f"{x:8.4f}" for x in p["position_m"])
        ypr = ", ".join(f"{x:7.2f}" for x in p["ypr_deg"])
        std = ""
        if "position_std_m" in p:
            std = "  std " + ", ".join(f"{100 * x:.2f}" for x in p["position_std_m"]) + " cm"
        print(f"  {name:<3} position ({pos})  yaw/pitch/roll ({ypr}){std}")


def _print_fit(c: dict) -> None:
    """The fit's chi-square and how far a blunder no test sees could have moved a pose."""
    if c["chi2"] is None or c["chi2_limit"] is None:
        return
    line = (
        f"Fit: chi-square {c['chi2']:.1f} for {c['dof']} degrees of freedom "
        f"(limit {c['chi2_limit']:.1f})"
    )
    if c["blunder_nees"] is not None:
        line += (
            f"; a blunder in one measurement that no test sees could move a position by up "
            f"to {c['blunder_nees'] ** 0.5:.1f} of its standard deviations"
        )
    print(line)


def _sighting_text(r: dict) -> str:
    what = "overhead camera C" if r["kind"] == "overhead" else r["observer"]
    return f"step {r['step']}: {what} seeing {r['target']} ({r['kind']})"


def _print_sightings(d: dict, args) -> None:
    """The missing sightings (markers not found) and the rejected ones (left out by a
    robust loss), `none` when there are none."""
    missing = d["missing_sightings"]
    print(f"Missing sightings (marker not found in the image): {len(missing) or 'none'}")
    for r in missing:
        print(f"  {_sighting_text(r)}: {r['reason']}")
    rejected = d["rejected_sightings"]
    if args.loss is not None:
        why = f"{args.loss} loss, outliers left out"
    elif args.no_refine:
        why = "closed form only"
    else:
        why = "least squares, none left out; --loss cauchy leaves outliers out"
    print(f"Rejected sightings ({why}): {len(rejected) or 'none'}")
    for r in rejected:
        print(f"  {_sighting_text(r)}")


# 2-D 95 % ellipse: chi-square quantile with 2 degrees of freedom, -2 ln(0.05).
_CHI2_2D_95 = -2.0 * math.log(0.05)


def _ellipse_scale(semi_axes: list[float], extent: float) -> float:
    """Magnification that makes the largest ellipse about 10 % of the plot's extent,
    rounded down to 1, 2 or 5 times a power of ten, at least 1."""
    big = max(semi_axes, default=0.0)
    if not big > 0:
        return 1.0
    raw = 0.1 * extent / big
    if raw <= 1:
        return 1.0
    decade = 10 ** math.floor(math.log10(raw))
    return max(m * decade for m in (1, 2, 5) if m * decade <= raw)


def plot_formation(d: dict, path: str, title: str = "") -> None:
    """Top view (x, y in W, m) of a `jaxloc localize` report `d`: each ground robot's
    positions at every step joined by its moves, every robot's end-of-cycle position
    (C's too) and its 2-D 95 % uncertainty ellipse from the x-y block of
    `position_cov_m2` (magnified by the factor the legend states), written to `path`
    (any suffix matplotlib writes) with matplotlib's Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse

    colors = {"C": "black", "C1": "tab:red", "C2": "tab:green", "C3": "tab:blue"}
    fig, ax = plt.subplots(figsize=(6.4, 5.6))
    ends = {n: np.asarray(p["position_m"], float) for n, p in d["poses"].items()}
    for name, track in d["positions_m"].items():
        xy = np.asarray(track, float)[:, :2]
        ax.plot(xy[:, 0], xy[:, 1], ":", color=colors[name], lw=1, alpha=0.6)
        ax.plot(xy[:-1, 0], xy[:-1, 1], "o", color=colors[name], ms=4, alpha=0.5, mfc="none")
        for a, b in zip(xy[:-1], xy[1:]):
            if np.linalg.norm(b - a) > 1e-6:  # a move: an arrow from where it started
                ax.annotate("", b, a, arrowprops=dict(arrowstyle="->", color=colors[name]))
    pts = np.concatenate([np.asarray(t, float)[:, :2] for t in d["positions_m"].values()]
                         + [e[None, :2] for e in ends.values()])  # fmt: skip
    extent = float(np.max(np.ptp(pts, axis=0))) or 1.0
    covs = {n: np.asarray(p["position_cov_m2"], float)[:2, :2]
            for n, p in d["poses"].items() if "position_cov_m2" in p}  # fmt: skip
    axes = {n: np.sqrt(np.maximum(np.linalg.eigvalsh(P), 0) * _CHI2_2D_95)
            for n, P in covs.items()}  # fmt: skip
    scale = _ellipse_scale([float(a.max()) for a in axes.values()], extent)
    for name, e in ends.items():
        marker = "s" if name == "C" else "o"
        label = f"{name} (z {e[2]:.2f} m)" if name == "C" else name
        ax.plot(e[0], e[1], marker, color=colors[name], ms=5, label=label)
        if name in covs:
            w, V = np.linalg.eigh(covs[name])
            angle = math.degrees(math.atan2(V[1, 1], V[0, 1]))
            width, height = 2 * scale * axes[name][1], 2 * scale * axes[name][0]
            ax.add_patch(Ellipse((e[0], e[1]), width, height, angle=angle, fill=False,
                                 color=colors[name], lw=1.5))  # fmt: skip
    what = (f"95 % ellipses x{scale:g}" if covs else "no covariance (closed form only)")
    ax.set_title(f"{title}\n{d['status']} ({d['method']}); {what}; arrows: moves", fontsize=9)
    ax.set_xlabel("x in W (m)")
    ax.set_ylabel("y in W (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def register(sub: argparse._SubParsersAction, parents=None) -> None:
    """Add the `calibrate` and `localize` subcommands to `jaxloc`'s subparsers (each with
    the options of the `parents` parsers; default: `--quiet`)."""
    parents = [quiet_option()] if parents is None else list(parents)
    _add_calibrate(sub, parents)
    _add_localize(sub, parents)


def _add_calibrate(sub: argparse._SubParsersAction, parents: list) -> None:
    p = sub.add_parser(
        "calibrate", parents=parents, epilog=EXIT_CODES_HELP,
        formatter_class=HelpFormatter,
        help="calibrate a camera from chessboard images (pinhole, omni, or ptz over zooms)",
        description=(
            "Calibrate one camera from images of a chessboard and write it as a camera file "
            "that jaxloc, OpenCV or Kalibr reads. pinhole: OpenCV's calibrateCamera "
            "(Brown-Conrady distortion, optionally the rational model); omni: the unified "
            "(Mei) omnidirectional model, fitted by jaxloc's own Levenberg-Marquardt from a "
            "closed-form start; ptz: one pinhole calibration per zoom step (--zoom Z IMAGES, "
            "repeated), gathered into a zoom table. Prints the parameters, their standard "
            "deviations and the reprojection RMS."
        ),
    )  # fmt: skip
    p.add_argument("--model", choices=("pinhole", "omni", "ptz"), required=True,
                   help="pinhole (OpenCV), omni (unified model, jaxloc's own fit) or ptz "
                   "(one pinhole calibration per --zoom step, gathered into a zoom "
                   "table)")  # fmt: skip
    p.add_argument("--board", required=True, metavar="COLSxROWS", help="inner corners, e.g. 9x6")
    p.add_argument("--square", type=float, required=True, metavar="METRES",
                   help="side of a chessboard square")  # fmt: skip
    p.add_argument("--out", default="camera.yaml", metavar="FILE",
                   help="camera file to write (ptz: one file, the camera with its whole "
                   "zoom table; rms_px and num_images per zoom step)")  # fmt: skip
    p.add_argument("--format", choices=("opencv", "json", "yaml", "kalibr"), default=None,
                   help="camera file format (default: from the suffix; OpenCV YAML)")  # fmt: skip
    p.add_argument("--window", type=int, default=None,
                   help="cornerSubPix half window in px (default 11; omni 5)")  # fmt: skip
    p.add_argument("--json", metavar="FILE", help="also write the calibration report")
    _add_pinhole_ptz_options(p)
    _add_omni_options(p)
    p.add_argument("images", nargs="*", metavar="IMAGES",
                   help="pinhole and omni: image files, quoted glob patterns or "
                   "folders")  # fmt: skip
    p.set_defaults(func=_cmd_calibrate)


def _add_pinhole_ptz_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("pinhole and ptz options")
    g.add_argument("--fix-aspect-ratio", action="store_true", help="fx = fy")
    g.add_argument("--fix-k3", action="store_true", help="k3 = 0 (as Kalibr's radtan)")
    g.add_argument("--zero-tangent", action="store_true", help="p1 = p2 = 0")
    g.add_argument("--rational", action="store_true",
                   help="OpenCV's 8-coefficient rational model (k1 k2 p1 p2 k3 k4 k5 k6), "
                   "for wide-angle lenses")  # fmt: skip
    g = p.add_argument_group("ptz options")
    g.add_argument("--zoom", nargs=2, action="append", metavar=("Z", "IMAGES"),
                   help="a zoom step in [0, 1] (wide to tele) and its images: a folder, a "
                   "quoted glob pattern or one file; repeat for every step (at least "
                   "two)")  # fmt: skip


def _add_omni_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("omni options")
    g.add_argument("--xi-init", type=float, default=None, metavar="XI",
                   help="starting mirror parameter xi (default 1, a paraboloid)")  # fmt: skip
    g.add_argument("--fix-xi", action="store_true",
                   help="hold xi at its starting value (--xi-init)")  # fmt: skip
    g.add_argument("--focal-init", type=float, nargs=2, default=None, metavar=("FX", "FY"),
                   help="starting generalized focal lengths in px (default: estimated from "
                   "the board's straight lines)")  # fmt: skip
    g.add_argument("--fix-focal", action="store_true",
                   help="hold fx, fy at their starting values (--focal-init; cv2.omnidir's "
                   "CALIB_FIX_GAMMA)")  # fmt: skip
    g.add_argument("--fix-center", action="store_true",
                   help="hold the principal point at --principal-point, or at the image "
                   "centre (cv2.omnidir's CALIB_FIX_CENTER)")  # fmt: skip
    g.add_argument("--dist-init", type=float, nargs=4, default=None,
                   metavar=("K1", "K2", "P1", "P2"),
                   help="starting distortion coefficients (default: 0)")  # fmt: skip
    g.add_argument("--fix-distortion", action="store_true",
                   help="hold k1 k2 p1 p2 at their starting values (--dist-init, default 0: "
                   "no distortion)")  # fmt: skip
    g.add_argument("--fix-coefficients", type=_coefficient_names, default=None,
                   metavar="NAMES",
                   help="hold some distortion coefficients at their starting values, "
                   "comma-separated among k1,k2,p1,p2 (e.g. p1,p2: no tangential "
                   "distortion; cv2.omnidir's CALIB_FIX_K1 ... CALIB_FIX_P2)")  # fmt: skip
    g.add_argument("--estimate-skew", action="store_true",
                   help="estimate the skew K[0, 1] (default: held at 0, as in Kalibr's "
                   "omni model; cv2.omnidir's CALIB_FIX_SKEW)")  # fmt: skip
    g.add_argument("--principal-point", type=float, nargs=2, default=None, metavar=("CX", "CY"),
                   help="starting principal point in px (default: the image centre)")  # fmt: skip
    g.add_argument("--max-steps", type=int, default=None, metavar="N",
                   help="Levenberg-Marquardt iteration limit (default 200)")  # fmt: skip


def _add_localize(sub: argparse._SubParsersAction, parents: list) -> None:
    p = sub.add_parser(
        "localize", parents=parents, epilog=EXIT_CODES_HELP,
        formatter_class=HelpFormatter,
        help="all four poses from a team's images of one cycle",
        description=(
            "Localize the four robots from a team's images of one cycle: detect the colour "
            "markers in every image, turn them into bearings through each calibrated camera, "
            "solve the cycle in closed form and refine it jointly; print every robot's "
            "end-of-cycle position and yaw/pitch/roll in C1's body frame at the start, with "
            "standard deviations, the sightings missing (a marker not found: occluded, out "
            "of view) and those rejected (--loss), write them as JSON and plot the formation "
            "from above with its uncertainty ellipses. The team file names the strategy, "
            "the camera files and the images of every step."
        ),
    )  # fmt: skip
    p.add_argument("--team", required=True, metavar="TEAM.yaml",
                   help="team file (YAML or JSON): strategy, camera files, images per step, "
                   "odometry (see jaxloc.load_team)")  # fmt: skip
    p.add_argument("--out", metavar="FILE", help="poses JSON (default: TEAM_poses.json); "
                   "written also when the status is not successful (exit code 1)")
    p.add_argument("--plot", metavar="FILE",
                   help="top view of the formation: every ground robot's moves, the four "
                   "end-of-cycle positions with their 95%% uncertainty ellipses (default: "
                   "TEAM_formation.png; the suffix picks the format)")  # fmt: skip
    p.add_argument("--no-refine", action="store_true",
                   help="closed form only (no joint refinement, no covariances)")  # fmt: skip
    p.add_argument("--loss", choices=("huber", "cauchy"), default=None,
                   help="robust refinement: sightings that do not fit the others (a "
                   "distractor taken for a marker) are left out, printed and written "
                   "as rejected_sightings (default: plain least squares)")  # fmt: skip
    p.add_argument("--loss-scale", type=float, default=None, metavar="SIGMAS",
                   help="the robust loss's scale in standard deviations of a sighting's "
                   "whitened residual (default 1.345 huber, 2.3849 cauchy)")  # fmt: skip
    p.set_defaults(func=_cmd_localize)
