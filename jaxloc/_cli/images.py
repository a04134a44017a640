"""`jaxloc calibrate` and `jaxloc localize`: the image front end on the command line.

Wire with `register(sub)` on `jaxloc._cli.main`'s subparsers.
"""

import argparse
import glob
import json
import math
import os

from .common import check_outputs, EXIT_NO_RESULT, EXIT_OK, write_report


def _cmd_calibrate(args) -> int:
    from .._cameras.files import save_camera
    from .._vision.calibrate import calibrate_omni, calibrate_pinhole, parse_board

    board = parse_board(args.board)
    if not (math.isfinite(args.square) and args.square > 0):
        raise ValueError(f"`--square` must be a positive length in metres; got {args.square}.")
    check_outputs(args, files=("out", "json"))
    images: list[str] = []
    for pattern in args.images:
        matches = sorted(glob.glob(pattern)) if any(c in pattern for c in "*?[") else [pattern]
        if not matches:
            raise FileNotFoundError(f"No image matches `{pattern}`.")
        images.extend(matches)
    for p in images:
        if not os.path.isfile(p):
            raise FileNotFoundError(f"Image file `{p}` does not exist.")
    if args.model == "pinhole":
        cal = calibrate_pinhole(
            images, board, args.square, fix_aspect_ratio=args.fix_aspect_ratio,
            fix_k3=args.fix_k3 or args.format == "kalibr", window=args.window or 11,
        )  # fmt: skip
    else:
        cal = calibrate_omni(images, board, args.square, window=args.window or 5)
    extra = {"rms_px": cal.rms, "num_images": len(cal.used)}
    save_camera(cal.camera, args.out, args.format,
                extra=None if args.format == "kalibr" else extra)  # fmt: skip
    s = cal.summary()
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
    print(f"  reprojection RMS {cal.rms:.4f} px; wrote {args.out} ({args.format or 'auto'})")
    if args.json:
        write_report(args.json, s)
    return EXIT_OK


def _cmd_localize(args) -> int:
    from .._vision.localize import localize_images
    from .._vision.team import load_team

    out = args.out or os.path.splitext(args.team)[0] + "_poses.json"
    check_outputs(argparse.Namespace(out=out), files=("out",))
    team = load_team(args.team)
    res = localize_images(team, refine=not args.no_refine)
    d = res.to_dict()
    print(f"{team.strategy} cycle from {args.team}: {d['status']} ({d['method']})")
    print("Poses at the end of the cycle, in W = C1's body frame at the start (m, deg):")
    for name, p in d["poses"].items():
        pos = ", ".join(f"{x:8.4f}" for x in p["position_m"])
        ypr = ", ".join(f"{x:7.2f}" for x in p["ypr_deg"])
        std = ""
        if "position_std_m" in p:
            std = "  std " + ", ".join(f"{100 * x:.2f}" for x in p["position_std_m"]) + " cm"
        print(f"  {name:<3} position ({pos})  yaw/pitch/roll ({ypr}){std}")
    for note in d["notes"]:
        print(f"  note: {note}")
    write_report(out, d)
    return EXIT_OK if d["status"] == "successful" else EXIT_NO_RESULT


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `calibrate` and `localize` subcommands to `jaxloc`'s subparsers."""
    p = sub.add_parser(
        "calibrate", help="calibrate a camera from chessboard images (pinhole or omni)"
    )
    p.add_argument("--model", choices=("pinhole", "omni"), required=True)
    p.add_argument("--board", required=True, metavar="COLSxROWS", help="inner corners, e.g. 9x6")
    p.add_argument("--square", type=float, required=True, metavar="METRES")
    p.add_argument("--out", default="camera.yaml", metavar="FILE", help="camera file to write")
    p.add_argument("--format", choices=("opencv", "json", "yaml", "kalibr"), default=None,
                   help="camera file format (default: json for .json, else opencv)")  # fmt: skip
    p.add_argument("--fix-aspect-ratio", action="store_true", help="pinhole: fx = fy")
    p.add_argument("--fix-k3", action="store_true", help="pinhole: k3 = 0 (Kalibr radtan)")
    p.add_argument("--window", type=int, default=None, help="cornerSubPix half window (px)")
    p.add_argument("--json", metavar="FILE", help="also write the calibration report")
    p.add_argument("images", nargs="+", metavar="IMAGES")
    p.set_defaults(func=_cmd_calibrate)
    p = sub.add_parser("localize", help="all four poses from a team's images of one cycle")
    p.add_argument("--team", required=True, metavar="TEAM.yaml")
    p.add_argument("--out", metavar="FILE", help="poses JSON (default: TEAM_poses.json); "
                   "written also when the status is not successful (exit code 1)")
    p.add_argument("--no-refine", action="store_true",
                   help="closed form only (no joint refinement, no covariances)")  # fmt: skip
    p.set_defaults(func=_cmd_localize)
