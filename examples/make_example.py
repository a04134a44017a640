"""Make `examples/sequential_cycle/`: one cycle of the paper's team, rendered as images.

    python examples/make_example.py        # from the repository root; 1-4 minutes

One sequential cycle (the paper's main strategy: C2 moves, then C3, then C1) of the
paper's simulated world (saddle floor, sinusoidal ceiling), with the triangle's legs at
1.8 m (see tests/test_localize_images.py), simulated with a fixed seed and rendered
through the team's cameras, which have real lens distortion:

- C, the ceiling camera: pinhole, 52 deg field of view, Brown-Conrady k1 k2 p1 p2, its
  principal point off the centre;
- C1, the PTZ at its wide end (85 deg): strong barrel distortion;
- C2, C3, the omnidirectional cameras: unified model (xi = 1) with k1 k2 p1 p2, each
  with its own focal length and principal point.

Every image has defocus blur, sensor noise and its own illumination (a gain between
about 0.7 and 1.3, a gradient and a colour tint: the lighting changes from image to
image). Two defects are placed on purpose:

- an orange ball on the floor beside C1 (a colour next to C1's red marker: hue 18 on
  OpenCV's 0-179 scale, red's range being 170-10), seen by every camera it is in view
  of; the detector must refuse it;
- C2's mirror support rod, fixed to C2's omnidirectional camera, which hides C3 from C2
  at step 1: that sighting is missing, and the cycle is still localized.

Writes the 16 PNG images (`step{k}_{C,C1,C2,C3}.png`), `team.yaml` with its four camera
files (what `jaxloc localize --team` reads: the camera parameters exactly as simulated,
the odometry as measured, with its 1 % noise) and `truth.json` (the true poses, every
marker's true pixel in every image, the ball and the rod, and `end_of_cycle`: each
robot's true end-of-cycle position and orientation in W, C1's body frame at the start).
Then it localizes the team from the written files, as the command does, and prints
the errors against the truth. Deterministic: the same seeds give the same files.
"""

import json
import math
import os
import sys

import jax


jax.config.update("jax_enable_x64", True)  # float64, as the `jaxloc` command runs

import jax.numpy as jnp  # noqa: E402
import jax.random as jr  # noqa: E402
import jaxlie  # noqa: E402
import jaxloc  # noqa: E402
import numpy as np  # noqa: E402
from jaxloc._vision.localize import localize_images, team_from_rendered  # noqa: E402
from jaxloc._vision.render import _camera_points, render_cycle  # noqa: E402
from jaxloc._vision.team import load_team  # noqa: E402


NAME = "sequential_cycle"
OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), NAME)
CYCLE_SEED = 12  # the simulated cycle: moves, odometry noise (see `rod`)
RENDER_SEED = 100  # backgrounds, lighting, sensor noise
# Per-axis standard deviation of a detected marker centre (px) written in the team file
# (the refinement's weights and the covariance): the detector's error on these images,
# measured by this script against the true centres (printed below: RMS 0.015 px per
# axis, largest 0.043 px), rounded up to cover the largest.
PIXEL_SIGMA = 0.05
W, H = 320, 240  # QVGA: see the module docstring
BALL_BGR = (20, 150, 235)  # orange: hue 18 (OpenCV), beside red's 170-10
ROD_BGR = (55, 55, 55)  # dark grey: no colour, no marker
ROBOTS = ("C", "C1", "C2", "C3")


def cameras():
    """The team's cameras, with distortion (the simulator and the renderer use them
    exactly; the team file records them exactly)."""
    f_c = 0.5 * W / math.tan(math.radians(26.0))
    overhead = jaxloc.PinholeCamera(
        f_c, 1.002 * f_c, 0.5 * (W - 1) + 2.1, 0.5 * (H - 1) - 1.6,
        dist=(-0.11, 0.09, 6e-4, -4e-4, 0.0), image_size=(W, H),
    )  # fmt: skip
    ptz = jaxloc.PTZCamera(
        pan=0.0, tilt=0.0, zoom=0.0, hfov_wide=math.radians(85.0),
        hfov_tele=math.radians(15.0), dist=(-0.28, 0.08, 5e-4, -3e-4, 0.0), image_size=(W, H),
    )  # fmt: skip

    def omni(f, dcx, dcy, dist):
        return jaxloc.OmniCamera(
            xi=1.0, fx=f, fy=1.003 * f, cx=0.5 * (W - 1) + dcx, cy=0.5 * (H - 1) + dcy,
            dist=dist, elevation_min=math.radians(-12.0), elevation_max=math.radians(32.0),
            image_size=(W, H),
        )  # fmt: skip

    return {
        "overhead": overhead, "ptz": ptz,
        "omni2": omni(92.0, 1.3, -0.8, (-0.05, 0.012, 4e-4, -2e-4)),
        "omni3": omni(93.0, -0.9, 1.1, (-0.04, 0.009, -3e-4, 3e-4)),
    }  # fmt: skip


def rod(azimuth: float) -> np.ndarray:
    """C2's mirror support rod, in C2's camera frame (m): a 2.5 cm wide flat strip 12 cm
    from the mirror's axis at `azimuth` (rad), from 4 cm below the mirror's centre to
    9 cm above (elevations -18 to +37 deg: across the whole visible band)."""
    d, half = 0.12, 0.0125
    a = np.array([math.cos(azimuth), math.sin(azimuth), 0.0])
    n = np.array([-math.sin(azimuth), math.cos(azimuth), 0.0])
    z = np.array([0.0, 0.0, 1.0])
    c = d * a
    return np.stack([c - half * n - 0.04 * z, c + half * n - 0.04 * z,
                     c + half * n + 0.09 * z, c - half * n + 0.09 * z])  # fmt: skip


def end_of_cycle(poses) -> dict:
    Tb = np.asarray(poses.T_world_body.wxyz_xyz)
    To = np.asarray(poses.T_world_overhead.wxyz_xyz)
    out = {"C": To}
    out.update({r: Tb[-1, i] for i, r in enumerate(ROBOTS[1:])})
    return {r: {"position_m": T[4:].tolist(), "quaternion_wxyz": T[:4].tolist()}
            for r, T in out.items()}  # fmt: skip


def check_defects(gt: dict) -> None:
    """Exactly one sighting hidden (C2 seeing C3 at step 1, entirely); no other marker
    touched by the rod or cut by an image border; the ball seen, away from every marker
    (a ball touching a marker would merge with it: no colour detector could split
    them)."""
    hidden, ball_seen = [], 0
    for name, v in gt["images"].items():
        for m in v["markers"]:
            if m.get("occluded", 0.0) > 0:
                hidden.append((name, m["name"], m["occluded"], m["visible"]))
            elif not m["visible"] or m.get("truncated"):
                raise SystemExit(f"{name}: marker {m['name']} not wholly in view: {m}")
        for o in v.get("objects", []):
            if not o["visible"]:
                continue
            ball_seen += 1
            r_o = math.sqrt(o["area_px"] / math.pi)
            for m in v["markers"]:
                if m["visible"]:
                    gap = np.hypot(*np.subtract(o["centroid_px"], m["centroid_px"]))
                    if gap < r_o + math.sqrt(m["area_px"] / math.pi) + 6:
                        raise SystemExit(f"{name}: the ball touches {m['name']} ({gap:.1f} px)")
    if hidden != [("step1_C2", "C3", 1.0, False)]:
        raise SystemExit(f"expected only C3 hidden entirely from C2 at step 1; got {hidden}")
    if not ball_seen:
        raise SystemExit("the ball is in no image")
    print(f"defects: C3 hidden from C2 at step 1 by the rod; the ball in {ball_seen} images")


def main() -> int:
    cams = cameras()
    scenario = jaxloc.Scenario.paper("sequential", side=1.8, pixel_sigma=PIXEL_SIGMA,
                                     noise_model="gaussian", **cams)  # fmt: skip
    truth, obs, visible = jax.jit(jaxloc.simulate_cycle)(scenario, jr.key(CYCLE_SEED))
    if not bool(visible):
        raise SystemExit(f"cycle seed {CYCLE_SEED}: a required sighting is out of view")
    # The rod at C3's azimuth in C2's camera at step 1.
    mutual, _ = _camera_points(scenario.rig, truth.poses)
    x = mutual[1, 1, 2]
    rods = {"C2": [{"polygon": rod(math.atan2(x[1], x[0])), "bgr": ROD_BGR, "name": "rod"}]}
    # The ball: on the floor, 0.35 m to C1's right at the start (C1 stays there until
    # the last step), at its markers' height.
    T1 = np.asarray(truth.poses.T_world_body.wxyz_xyz)[0, 0]
    R1 = np.asarray(jaxlie.SO3(jnp.asarray(T1[:4])).as_matrix())
    ball = T1[4:] + R1 @ np.array([0.05, -0.35, 0.0])
    objects = [{"position": ball, "radius": 0.06, "bgr": BALL_BGR, "name": "orange ball"}]
    os.makedirs(OUT, exist_ok=True)
    for f in os.listdir(OUT):  # a clean folder: nothing left from an earlier run
        os.remove(os.path.join(OUT, f))
    rendered = render_cycle(scenario, truth, key=jr.key(RENDER_SEED), out_dir=OUT,
                            blur_sigma=0.7, noise_sigma=2.0, distractors=0, lighting=0.3,
                            objects=objects, occluders=rods)  # fmt: skip
    gt = rendered["truth"]
    check_defects(gt)
    gt["end_of_cycle"] = end_of_cycle(truth.poses)
    gt["frame"] = "W = body frame of C1 at the start of the cycle (x forward, y left, z up); m"
    gt["seeds"] = {"cycle": CYCLE_SEED, "render": RENDER_SEED}
    gt["missing_sightings"] = [{"kind": "mutual", "step": 1, "observer": "C2", "target": "C3"}]
    with open(os.path.join(OUT, "truth.json"), "w", encoding="utf-8") as f:
        json.dump(gt, f, indent=1)
    team_from_rendered(scenario, obs, OUT, pixel_sigma=PIXEL_SIGMA)
    report(gt)
    return 0


def report(gt: dict) -> None:
    """Localize from the written files and print the detector's error and the poses'
    errors against the truth."""
    res = localize_images(load_team(os.path.join(OUT, "team.yaml")))
    errs = [np.subtract(res.detections[(v["step"], v["camera"])][m["name"]].pixel,
                        m["center_px"])
            for v in gt["images"].values() for m in v["markers"] if m["visible"]]  # fmt: skip
    errs = np.asarray(errs)
    print(f"detections: {len(errs)}; error vs the true marker centre: RMS per axis "
          f"{np.sqrt(np.mean(errs**2)):.3f} px, largest {np.abs(errs).max():.3f} px "
          f"(team pixel_sigma {PIXEL_SIGMA} px)")  # fmt: skip
    d = res.to_dict()
    print(f"status {d['status']} ({d['method']}); missing {d['missing_sightings']}")
    for r, p in d["poses"].items():
        e = np.subtract(p["position_m"], gt["end_of_cycle"][r]["position_m"])
        std = np.asarray(p.get("position_std_m", [np.nan] * 3))
        print(f"  {r:<3} error {100 * np.linalg.norm(e):6.2f} cm  (x y z "
              f"{np.round(100 * e, 2)} cm; std {np.round(100 * std, 2)} cm)")  # fmt: skip
    size = sum(os.path.getsize(os.path.join(OUT, f)) for f in os.listdir(OUT))
    print(f"wrote {OUT}: {len(os.listdir(OUT))} files, {size / 1e6:.2f} MB")


if __name__ == "__main__":
    sys.exit(main())
