"""Zoom-calibrated PTZ camera (issue 20.4): a synthetic zoom series rendered through a
tabled PTZ camera is recovered by `calibrate_ptz` and `jaxloc calibrate --model ptz`;
the command line's omni options (issue 20.5)."""

import argparse
import json
import os

import cv2
import jax.numpy as jnp
import jax.random as jr
import jaxlie
import jaxloc
import numpy as np
import pytest
from jaxloc._cameras.files import load_camera
from jaxloc._cli.images import register
from jaxloc._vision.calibrate import calibrate_ptz, Calibration
from jaxloc._vision.render import render_chessboard


BOARD, SQUARE = (9, 6), 0.03
TRUE_TABLE = jaxloc.ZoomTable(
    [0.0, 0.5, 1.0],
    [420.0, 640.0, 980.0],
    [421.0, 641.5, 982.0],
    [321.0, 318.5, 316.0],
    [238.0, 240.5, 243.0],
    [[-0.12, 0.03, 0.0, 0.0, 0.0], [-0.06, 0.01, 0.0, 0.0, 0.0], [-0.02, 0.0, 0.0, 0.0, 0.0]],
)
VIEWS = 8


def _true_camera(zoom):
    # pan = tilt = 0: the PTZ base frame is the optical frame.
    return jaxloc.PTZCamera(zoom=zoom, zoom_table=TRUE_TABLE)


def _board_pose(rng, f):
    """A board filling about half the image width, tilted up to ~30 deg, all corners in
    view."""
    d = f * 0.3 / (0.5 * 640)
    R = jaxlie.SO3.from_rpy_radians(*rng.uniform(-0.5, 0.5, 2), rng.uniform(-0.3, 0.3))
    mid = np.array([(BOARD[0] - 1) * SQUARE / 2, (BOARD[1] - 1) * SQUARE / 2, 0.0])
    c = np.array([rng.uniform(-0.3, 0.3) * d, rng.uniform(-0.2, 0.2) * d, d])
    t = c - np.asarray(R.as_matrix()) @ mid
    return jaxlie.SE3.from_rotation_and_translation(R, jnp.asarray(t))


@pytest.fixture(scope="module")
def zoom_series():
    rng = np.random.default_rng(3)
    series = {}
    k = 0
    for z in (0.0, 0.5, 1.0):
        cam = _true_camera(z)
        f = float(cam.focal_length())
        images = []
        while len(images) < VIEWS:
            img, corners, _ = render_chessboard(cam, _board_pose(rng, f), BOARD, SQUARE,
                                                key=jr.key(k), supersample=2)  # fmt: skip
            k += 1
            if np.all(np.isfinite(corners)):
                images.append(img)
        series[z] = images
    return series


def _max_bearing_difference_deg(cam_a, cam_b):
    uu, vv = np.meshgrid(np.linspace(0, 639, 33), np.linspace(0, 479, 25))
    uv = jnp.asarray(np.stack([uu, vv], -1).reshape(-1, 2))
    a, b = np.asarray(cam_a.unproject(uv)), np.asarray(cam_b.unproject(uv))
    return float(np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1.0, 1.0))).max())


def test_calibrate_ptz_recovers_a_rendered_zoom_series(zoom_series, capsys):
    cal = calibrate_ptz(zoom_series, BOARD, SQUARE, fix_k3=True, zero_tangent=True)
    est = cal.camera
    assert isinstance(est, jaxloc.PTZCamera) and est.zoom_table is not None
    assert cal.zooms == [0.0, 0.5, 1.0] and len(cal.steps) == 3
    t = est.zoom_table
    with capsys.disabled():
        print("\nzoom series (true / estimated): fx",
              [(float(a), round(float(b), 2)) for a, b in zip(TRUE_TABLE.fx, t.fx)],
              "cx", [(float(a), round(float(b), 2)) for a, b in zip(TRUE_TABLE.cx, t.cx)],
              "k1", [(float(a), round(float(b), 4)) for a, b in zip(TRUE_TABLE.dist[:, 0],
                                                                     t.dist[:, 0])],
              "RMS px", [round(s.rms, 3) for s in cal.steps])  # fmt: skip
    np.testing.assert_allclose(t.zooms, TRUE_TABLE.zooms)
    # Measured: fx within 0.25 %, cx, cy within 0.5 px, k1 within 0.003, RMS < 0.09 px.
    np.testing.assert_allclose(t.fx, TRUE_TABLE.fx, rtol=3e-3)
    np.testing.assert_allclose(t.fy, TRUE_TABLE.fy, rtol=3e-3)
    np.testing.assert_allclose(t.cx, TRUE_TABLE.cx, atol=1.5)
    np.testing.assert_allclose(t.cy, TRUE_TABLE.cy, atol=1.5)
    np.testing.assert_allclose(t.dist[:, 0], TRUE_TABLE.dist[:, 0], atol=0.01)
    assert all(s.rms < 0.2 for s in cal.steps)
    # The recovered camera maps pixels to bearings like the true one over the whole image
    # (measured: 0.12 deg at most, in the corners at the wide end), and between the
    # calibrated steps no worse than at its neighbouring steps: the table interpolates
    # what it was given, it adds no error of its own.
    diff = {}
    for zoom in (0.0, 0.25, 0.5, 0.8, 1.0):
        est_z = jaxloc.PTZCamera(zoom=zoom, image_size=est.image_size, zoom_table=t)
        diff[zoom] = _max_bearing_difference_deg(est_z, _true_camera(zoom))
    assert max(diff.values()) < 0.2, diff
    assert diff[0.25] <= 1.25 * max(diff[0.0], diff[0.5]), diff
    assert diff[0.8] <= 1.25 * max(diff[0.5], diff[1.0]), diff
    s = cal.summary()
    assert s["model"] == "ptz" and s["zoom_table"]["zooms"] == [0.0, 0.5, 1.0]
    assert len(s["steps"]) == 3 and s["steps"][1]["zoom"] == 0.5


def test_cli_calibrate_ptz(zoom_series, tmp_path, capsys):
    argv = ["calibrate", "--model", "ptz", "--board", "9x6", "--square", str(SQUARE),
            "--fix-k3", "--zero-tangent", "--out", str(tmp_path / "ptz.yaml"),
            "--json", str(tmp_path / "ptz.json")]  # fmt: skip
    for z, images in zoom_series.items():
        folder = tmp_path / f"zoom{z}"
        folder.mkdir()
        for i, img in enumerate(images):
            cv2.imwrite(str(folder / f"{i}.png"), img)
        argv += ["--zoom", str(z), str(folder)]
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(argv)
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "ptz calibration at 3 zoom steps from 24 images" in out
    report = json.loads((tmp_path / "ptz.json").read_text())
    np.testing.assert_allclose(report["zoom_table"]["fx"], TRUE_TABLE.fx, rtol=5e-3)
    # One camera file: the PTZ with the whole table, exactly the report's (issue 20.4).
    assert sorted(p.name for p in tmp_path.iterdir() if p.is_file()) == ["ptz.json", "ptz.yaml"]
    cam = load_camera(tmp_path / "ptz.yaml")
    assert isinstance(cam, jaxloc.PTZCamera) and cam.zoom_table is not None
    t = cam.zoom_table
    for key, name in (("zooms", "zooms"), ("fx", "fx"), ("fy", "fy"), ("cx", "cx"),
                      ("cy", "cy"), ("distortion_coefficients", "dist")):  # fmt: skip
        np.testing.assert_array_equal(np.asarray(getattr(t, name)), report["zoom_table"][key])
    assert "wrote " + str(tmp_path / "ptz.yaml") in out


def test_calibrate_ptz_errors(zoom_series):
    one = {0.5: zoom_series[0.5]}
    with pytest.raises(ValueError, match="at least two zoom steps"):
        calibrate_ptz(one, BOARD, SQUARE)
    with pytest.raises(ValueError, match=r"in \[0, 1\]; got 1.5"):
        calibrate_ptz({0.0: zoom_series[0.0], 1.5: zoom_series[1.0]}, BOARD, SQUARE)
    with pytest.raises(ValueError, match="Zoom step 1: Pinhole calibration needs the board in"):
        calibrate_ptz([(0.0, zoom_series[0.0]), (1.0, zoom_series[1.0][:2])], BOARD, SQUARE)
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    base = ["calibrate", "--board", "9x6", "--square", "0.03"]
    for extra, match in (
        (["--model", "ptz", "--zoom", "0", "a"], "at least two zoom steps"),
        (["--model", "ptz", "x.png"], r"--zoom Z IMAGES"),
        (["--model", "pinhole", "--fix-xi", "x.png"], r"`--fix-xi` applies to --model omni"),
        (["--model", "omni", "--rational", "x.png"], r"`--rational` applies to --model pinhole"),
        (["--model", "pinhole", "--zoom", "0", "d", "x.png"], r"`--zoom` applies to --model ptz"),
        (["--model", "pinhole"], "needs IMAGES"),
    ):
        args = parser.parse_args(base + extra)
        with pytest.raises(ValueError, match=match):
            args.func(args)


def test_cli_calibrate_omni_options(tmp_path, monkeypatch, capsys):
    import jaxloc._vision.calibrate as calibrate_module

    seen = {}

    def fake_calibrate_omni(images, board, square, **kwargs):
        seen.update(kwargs, images=images)
        cam = jaxloc.OmniCamera(0.9, 190.0, 188.0, 322.0, 236.0)
        return Calibration(cam, 0.1, {"xi": 0.01}, [0.1], np.zeros((1, 7)), list(images), [])

    monkeypatch.setattr(calibrate_module, "calibrate_omni", fake_calibrate_omni)
    img = tmp_path / "a.png"
    cv2.imwrite(str(img), np.zeros((8, 8), np.uint8))
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    argv = ["calibrate", "--model", "omni", "--board", "9x6", "--square", "0.03",
            "--out", str(tmp_path / "o.yaml"), "--xi-init", "0.8", "--fix-xi",
            "--fix-distortion", "--estimate-skew", "--principal-point", "320", "241",
            "--max-steps", "50", "--window", "4", str(img)]  # fmt: skip
    args = parser.parse_args(argv)
    assert args.func(args) == 0
    assert seen == dict(window=4, fix_xi=True, fix_distortion=True, fix_skew=False,
                        principal_point=(320.0, 241.0), xi_init=0.8, max_steps=50,
                        images=[str(img)])  # fmt: skip
    seen.clear()
    args = parser.parse_args(argv[:9] + [str(img)])
    assert args.func(args) == 0
    # Defaults: calibrate_omni's own (xi from 1, nothing fixed but the skew).
    assert seen == dict(window=5, fix_xi=False, fix_distortion=False, fix_skew=True,
                        principal_point=None, images=[str(img)])  # fmt: skip
    for action in parser._subparsers._group_actions[0].choices["calibrate"]._actions:
        if action.option_strings and action.dest != "help":
            assert action.help, f"{action.option_strings} has no help text"
    assert os.path.exists(tmp_path / "o.yaml")
