"""Calibration (issue 7): OpenCV's sample chessboards against the published reference,
omnidirectional calibration on rendered boards, camera files round trip, clear errors."""

import argparse
import glob
import json
import math
import os

import cv2
import jax.numpy as jnp
import jax.random as jr
import jaxlie
import jaxloc
import numpy as np
import pytest
import yaml
from jaxloc._cameras.files import camera_from_kalibr, load_camera, save_camera
from jaxloc._cli.images import register
from jaxloc._vision.calibrate import (
    calibrate_pinhole,
    find_corners,
    object_points,
    omni_initial_guess,
    parse_board,
)
from jaxloc._vision.render import render_chessboard


# The SHARED path idiom of tests/conftest.py.
SHARED = os.path.join(os.path.dirname(__file__), "..", "..", "shared")
DATA = os.path.join(SHARED, "data", "opencv-left-chessboard")
# Published upstream (OpenCV samples/data/left_intrinsics.yml), see the data README.
REF_F, REF_CX, REF_CY = 535.91573396, 342.28315473, 235.57082910
REF_K1 = -0.266372609


def _left_images():
    if not os.path.isdir(DATA):
        if os.environ.get("CI"):
            pytest.fail(f"The shared calibration data {DATA} is required under CI.")
        pytest.skip(f"Shared data not found at {DATA} (../shared absent); skipping.")
    return sorted(glob.glob(os.path.join(DATA, "left*.jpg")))


def test_pinhole_calibration_matches_published_reference(capsys):
    images = _left_images()
    assert len(images) == 13
    cal = calibrate_pinhole(images, (9, 6), 0.025, fix_aspect_ratio=True)
    K, dist, size = cal.camera.to_opencv()
    with capsys.disabled():
        print(f"\nleft01-14: f {K[0, 0]:.4f} ({100 * (K[0, 0] - REF_F) / REF_F:+.4f}% vs "
              f"{REF_F}), cx {K[0, 2]:.4f} ({K[0, 2] - REF_CX:+.4f}), cy {K[1, 2]:.4f} "
              f"({K[1, 2] - REF_CY:+.4f}), k1 {dist[0]:.5f}, RMS {cal.rms:.4f} px")  # fmt: skip
    assert size == (640, 480) and not cal.rejected
    assert abs(K[0, 0] - REF_F) / REF_F < 1e-3
    assert K[0, 0] == K[1, 1]
    assert abs(K[0, 2] - REF_CX) < 1.0 and abs(K[1, 2] - REF_CY) < 1.0
    assert abs(dist[0] - REF_K1) < 0.005
    assert cal.rms < 0.45
    assert all(v > 0 for k, v in cal.std.items())
    assert cal.T_cam_board.shape == (13, 7)


def test_published_opencv_file_loads():
    _left_images()
    cam = load_camera(os.path.join(DATA, "left_intrinsics.yml"))
    assert isinstance(cam, jaxloc.PinholeCamera)
    np.testing.assert_allclose([float(cam.fx), float(cam.cx), float(cam.cy)],
                               [REF_F, REF_CX, REF_CY])  # fmt: skip


def test_cli_calibrate_pinhole(tmp_path, capsys):
    images = _left_images()
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    out = tmp_path / "left.yaml"
    argv = ["calibrate", "--model", "pinhole", "--board", "9x6", "--square", "0.025",
            "--fix-aspect-ratio", "--out", str(out), *images[:6]]  # fmt: skip
    args = parser.parse_args(argv)
    assert args.func(args) == 0
    assert "reprojection RMS" in capsys.readouterr().out
    cam = load_camera(out)
    assert abs(float(cam.fx) - REF_F) / REF_F < 5e-3


# --------------------------------------------------------------------------------------
# Omnidirectional calibration on rendered boards.

OMNI_TRUE = jaxloc.OmniCamera(0.9, 190.0, 188.0, 322.0, 236.0, dist=(-0.02, 0.005, 0.001, -0.0005))
BOARD, SQUARE = (9, 6), 0.03


def _board_pose(az, el, dist, yaw, pitch):
    c = dist * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    zb = c / np.linalg.norm(c)
    xb = np.cross([0.0, 0.0, 1.0], zb)
    xb /= np.linalg.norm(xb)
    R = np.stack([xb, np.cross(zb, xb), zb], 1)
    R = R @ np.asarray(jaxlie.SO3.from_rpy_radians(pitch, yaw, 0.0).as_matrix())
    mid = np.array([(BOARD[0] - 1) * SQUARE / 2, (BOARD[1] - 1) * SQUARE / 2, 0.0])
    return jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.from_matrix(jnp.asarray(R)), jnp.asarray(c - R @ mid)
    )


def _omni_boards(n, camera=OMNI_TRUE, with_poses=False):
    rng = np.random.default_rng(0)
    out = []
    for k in range(n):
        az, el, d = rng.uniform(0, 2 * math.pi), rng.uniform(-0.05, 0.35), rng.uniform(0.35, 0.5)
        T = _board_pose(az, el, d, rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5))
        img, corners, _ = render_chessboard(camera, T, BOARD, SQUARE, key=jr.key(k),
                                            supersample=2)  # fmt: skip
        out.append((img, corners, T) if with_poses else (img, corners))
    return out


def test_omni_closed_form_initialization():
    # xi = 1 (the initialization's model), no distortion: the focal length from the
    # boards' straight lines and the homography poses are close to the truth.
    cam = jaxloc.OmniCamera(1.0, 185.0, 185.0, 319.5, 239.5)
    boards = _omni_boards(4, cam, with_poses=True)
    corners = []
    for img, truth, _ in boards:
        c = find_corners(img, BOARD, window=5)
        corners.append(truth if c is None else c)
    cx, cy, gamma, T0 = omni_initial_guess(corners, object_points(BOARD, SQUARE), (640, 480))
    assert (cx, cy) == (319.5, 239.5)
    assert abs(gamma - 185.0) / 185.0 < 0.005, gamma
    for Tv, (_, _, T) in zip(T0, boards):
        est = jaxlie.SE3(jnp.asarray(Tv))
        assert np.linalg.norm(np.asarray(est.translation() - T.translation())) < 0.003
        assert float(jaxloc.rotation_error(est.rotation(), T.rotation())) < np.radians(0.5)


@pytest.mark.slow  # ~15 s on an idle machine, mostly compiling the LM solve
def test_omni_calibration_recovers_true_parameters(tmp_path, capsys):
    boards = _omni_boards(10)
    # The rendered corners, detected by OpenCV, are within a few tenths of a pixel.
    for img, truth in boards[:3]:
        c = find_corners(img, BOARD, window=5)
        if c is not None:
            assert np.nanmax(np.linalg.norm(c - truth, axis=-1)) < 0.3
    paths = []
    for k, (img, _) in enumerate(boards):
        paths.append(str(tmp_path / f"omni{k:02d}.png"))
        cv2.imwrite(paths[-1], img)
    # Through the command line: `jaxloc calibrate --model omni ...`.
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    out, report = tmp_path / "omni.yaml", tmp_path / "omni_report.json"
    argv = ["calibrate", "--model", "omni", "--board", "9x6", "--square", str(SQUARE),
            "--out", str(out), "--json", str(report), *paths]  # fmt: skip
    args = parser.parse_args(argv)
    assert args.func(args) == 0
    capsys.readouterr()
    summary = json.loads(report.read_text())
    std, est = summary["std"], load_camera(out)
    assert isinstance(est, jaxloc.OmniCamera)
    assert len(summary["per_view_rms_px"]) >= 7
    true = {"xi": 0.9, "fx": 190.0, "fy": 188.0, "cx": 322.0, "cy": 236.0}
    with capsys.disabled():
        print("\nomni calibration (true, estimate, std):",
              {n: (v, round(float(getattr(est, n)), 4), round(std[n], 4)) for n, v in true.items()},
              "RMS px", round(summary["rms_px"], 4))  # fmt: skip
    for name, v in true.items():
        got = float(getattr(est, name))
        # Within 4 reported standard deviations, and the deviations are informative.
        assert abs(got - v) < 4 * std[name] + 1e-9, (name, got, v, std[name])
    assert abs(float(est.cx) - 322.0) < 0.5 and abs(float(est.cy) - 236.0) < 0.5
    assert std["xi"] < 0.1 and std["fx"] < 8.0
    assert summary["rms_px"] < 0.15
    # xi, f and k1 are correlated; what matters is the mapping pixels <-> bearings over
    # the elevation band: compare bearings of the same pixels.
    az = np.linspace(0, 2 * math.pi, 36, endpoint=False)
    el = np.radians(np.linspace(-12, 32, 9))
    A, E = np.meshgrid(az, el)
    p = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    uv = np.asarray(OMNI_TRUE.project(jnp.asarray(p)))
    b = np.asarray(est.unproject(jnp.asarray(uv)))
    ang = np.degrees(np.arccos(np.clip(np.sum(b * p, -1), -1, 1)))
    with capsys.disabled():
        print(f"omni calibration: max bearing difference over the band {ang.max():.4f} deg")
    assert ang.max() < 0.15, ang.max()


# --------------------------------------------------------------------------------------
# Camera files.


@pytest.mark.parametrize("fmt,suffix", [("opencv", ".yaml"), ("json", ".json"),
                                        ("kalibr", ".yaml")])  # fmt: skip
def test_camera_files_round_trip(tmp_path, fmt, suffix):
    pin = jaxloc.PinholeCamera(530.5, 531.25, 320.1, 241.7, (-0.27, 0.05, 0.001, -0.0003, 0.0))
    omni = jaxloc.OmniCamera(0.93, 190.2, 188.4, 321.7, 236.9, dist=(-0.02, 0.004, 1e-3, -5e-4))
    for cam in (pin, omni):
        path = tmp_path / f"cam{suffix}"
        save_camera(cam, path, fmt)
        back = load_camera(path)
        assert type(back) is type(cam) and back.image_size == cam.image_size
        for f in ("fx", "fy", "cx", "cy", "dist"):
            np.testing.assert_allclose(np.asarray(getattr(back, f)), np.asarray(getattr(cam, f)),
                                       rtol=1e-12, atol=1e-15)  # fmt: skip
        if isinstance(cam, jaxloc.OmniCamera):
            assert float(back.xi) == float(cam.xi)
    if fmt == "kalibr":
        d = yaml.safe_load((tmp_path / f"cam{suffix}").read_text())
        assert d["cam0"]["camera_model"] == "omni" and d["cam0"]["distortion_model"] == "radtan"
        assert d["cam0"]["intrinsics"][0] == 0.93


def test_kalibr_import_of_a_published_style_camchain():
    d = yaml.safe_load("""
cam0:
  camera_model: omni
  intrinsics: [0.80, 267.5, 266.9, 312.3, 243.1]
  distortion_model: radtan
  distortion_coeffs: [-0.05, 0.01, 0.0005, -0.0002]
  resolution: [640, 480]
  rostopic: /cam0/image_raw
""")
    cam = camera_from_kalibr(d)
    assert isinstance(cam, jaxloc.OmniCamera) and float(cam.xi) == 0.8 and float(cam.cy) == 243.1


def test_camera_file_errors(tmp_path):
    pin = jaxloc.PinholeCamera(500.0, 500.0, 320.0, 240.0, (0.1, 0.0, 0.0, 0.0, 0.01))
    with pytest.raises(ValueError, match="k3"):
        save_camera(pin, tmp_path / "k.yaml", "kalibr")
    with pytest.raises(ValueError, match="format"):
        save_camera(pin, tmp_path / "k.yaml", "matlab")
    with pytest.raises(FileNotFoundError, match="missing.yaml"):
        load_camera(tmp_path / "missing.yaml")
    p = tmp_path / "bad.json"
    p.write_text('{"model": "pinhole", "camera_matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], '
                 '"image_width": -640, "image_height": 480}')  # fmt: skip
    with pytest.raises(ValueError, match="image_width"):
        load_camera(p)
    p.write_text('{"model": "fisheye", "camera_matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}')
    with pytest.raises(ValueError, match="model"):
        load_camera(p)
    p2 = tmp_path / "neg.json"
    p2.write_text('{"camera_matrix": [[-5, 0, 3], [0, 5, 3], [0, 0, 1]], "image_width": 6, '
                  '"image_height": 6}')  # fmt: skip
    with pytest.raises(ValueError, match="fx"):
        load_camera(p2)
    kal = tmp_path / "kal.yaml"
    kal.write_text("cam0: {camera_model: omni, intrinsics: [1, 2, 3], distortion_model: radtan, "
                   "distortion_coeffs: [0, 0, 0, 0], resolution: [640, 480]}\n")  # fmt: skip
    with pytest.raises(ValueError, match="intrinsics"):
        load_camera(kal)
    kal.write_text("cam0: {camera_model: pinhole, intrinsics: [1, 2, 3, 4], "
                   "distortion_model: fov, distortion_coeffs: [0.9], "
                   "resolution: [640, 480]}\n")  # fmt: skip
    with pytest.raises(ValueError, match="distortion_model: fov"):
        load_camera(kal)
    kal.write_text("cam0: {camera_model: pinhole, intrinsics: [1, 2, 3, 4], "
                   "distortion_model: equidistant, resolution: [640, 480]}\n")  # fmt: skip
    with pytest.raises(ValueError, match="missing `distortion_coeffs`"):
        load_camera(kal)


def test_board_and_image_errors(tmp_path):
    with pytest.raises(ValueError, match="9by6"):
        parse_board("9by6")
    with pytest.raises(ValueError, match="board"):
        object_points((1, 6), 0.025)
    with pytest.raises(ValueError, match="square"):
        object_points((9, 6), -1.0)
    cam = jaxloc.paper_overhead_camera()
    T = jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.identity(),
                                                 jnp.array([-0.1, -0.06, 0.6]))  # fmt: skip
    img, _, _ = render_chessboard(cam, T, (9, 6), 0.025)
    paths = []
    for k in range(3):
        paths.append(str(tmp_path / f"b{k}.png"))
        cv2.imwrite(paths[-1], img)
    # The wrong board size is never silently accepted: the error names it.
    with pytest.raises(ValueError, match="8x6"):
        calibrate_pinhole(paths, (8, 6), 0.025)
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"\x89PNG garbage")
    with pytest.raises(ValueError, match="broken.png"):
        calibrate_pinhole([*paths, str(bad)], (9, 6), 0.025)
    with pytest.raises(FileNotFoundError, match="absent.png"):
        calibrate_pinhole([str(tmp_path / "absent.png")], (9, 6), 0.025)
    # Fewer than three views.
    with pytest.raises(ValueError, match="at least 3"):
        calibrate_pinhole(paths[:2], (9, 6), 0.025)
