"""Colour-marker detection (issue 7): accuracy on rendered images, rejection, errors."""

import math

import cv2
import jax.random as jr
import jaxloc
import numpy as np
import pytest
from jaxloc._vision.markers import (
    annulus_mask,
    DEFAULT_MARKER_COLORS,
    detect_markers,
    MarkerColor,
    read_image,
)
from jaxloc._vision.render import annulus_of, DEFAULT_MARKER_BGR, render_markers


COLORS = {
    "C1": DEFAULT_MARKER_COLORS["red"],
    "C2": DEFAULT_MARKER_COLORS["green"],
    "C3": DEFAULT_MARKER_COLORS["blue"],
}


def _check(truth, det, tol):
    n = 0
    for t in truth:
        d = det[t["name"]]
        if t["visible"] and not t["truncated"]:
            assert d.detected, t
            assert not d.truncated
            err = np.linalg.norm(d.pixel - np.asarray(t["centroid_px"]))
            assert err < tol, (t, d)
            n += 1
    return n


def test_overhead_detection_within_0p2_px():
    # 640x480, blur, sensor noise (3 grey levels), lighting change, 4 distractors each.
    cam = jaxloc.paper_overhead_camera()
    rng = np.random.default_rng(0)
    n = 0
    for s in range(8):
        pts = np.stack(
            [rng.uniform(-1.0, 1.0, 3), rng.uniform(-0.7, 0.7, 3), rng.uniform(2.8, 3.6, 3)], -1
        )
        img, truth = render_markers(cam, pts, key=jr.key(s), names=["C1", "C2", "C3"])
        assert img.shape == (480, 640, 3) and img.dtype == np.uint8
        n += _check(truth, detect_markers(img, COLORS), 0.2)
    assert n >= 20


def test_omni_detection_within_0p2_px_with_annulus():
    cam = jaxloc.paper_omni_camera()
    mask = annulus_mask(cam.image_size, annulus_of(cam, 3.0))
    rng = np.random.default_rng(1)
    n = 0
    for s in range(6):
        az = rng.uniform(0, 2 * math.pi) + np.array([0.0, math.pi * rng.uniform(0.5, 1.5)])
        d = rng.uniform(1.2, 2.5, 2)
        pts = np.stack([d * np.cos(az), d * np.sin(az), rng.uniform(-0.1, 0.1, 2)], -1)
        img, truth = render_markers(
            cam, pts, key=jr.key(10 + s), names=["C1", "C3"],
            colors=[DEFAULT_MARKER_BGR[0], DEFAULT_MARKER_BGR[2]],
        )  # fmt: skip
        det = detect_markers(img, {"C1": COLORS["C1"], "C3": COLORS["C3"]}, mask=mask)
        n += _check(truth, det, 0.2)
    assert n >= 10


def test_ptz_detection_within_0p2_px():
    cam = jaxloc.paper_ptz_camera()
    pts = np.array([[-0.9, 0.05, 1.4], [0.7, -0.02, 1.9]])  # PTZ base frame
    img, truth = render_markers(cam, pts, key=jr.key(3), names=["C2", "C3"],
                                colors=DEFAULT_MARKER_BGR[1:])  # fmt: skip
    assert _check(truth, detect_markers(img, COLORS), 0.2) == 2


def test_missing_marker_and_distractors_rejected():
    cam = jaxloc.paper_overhead_camera()
    # Only C1 present; distractors include marker-coloured stripes and specks.
    img, truth = render_markers(cam, np.array([[0.2, 0.1, 3.0]]), key=jr.key(5), names=["C1"],
                                distractors=12)  # fmt: skip
    det = detect_markers(img, COLORS)
    assert det["C1"].detected and det["C1"].candidates == 1
    for name in ("C2", "C3"):
        assert not det[name].detected
        assert np.all(np.isnan(det[name].pixel)) and math.isnan(det[name].spread)


def test_truncated_and_ambiguous_flags():
    img = np.full((480, 640, 3), 120, np.uint8)
    cv2.circle(img, (3, 200), 9, DEFAULT_MARKER_BGR[1], -1)  # cut by the left border
    cv2.circle(img, (300, 100), 8, DEFAULT_MARKER_BGR[2], -1)
    cv2.circle(img, (400, 300), 8, DEFAULT_MARKER_BGR[2], -1)  # two blue blobs
    det = detect_markers(img, COLORS)
    assert det["C2"].detected and det["C2"].truncated
    assert det["C3"].candidates == 2
    assert not det["C1"].detected


def test_red_hue_wraps():
    c = MarkerColor(170, 10)
    assert len(c.ranges()) == 2
    img = np.full((100, 100, 3), 100, np.uint8)
    cv2.circle(img, (40, 60), 6, (0, 0, 230), -1)  # hue 0
    cv2.circle(img, (80, 20), 6, (60, 0, 230), -1)  # hue ~172
    det = detect_markers(img, {"r": c}, coarse=1)
    assert det["r"].candidates == 2


def test_spread_and_area():
    img = np.full((200, 200, 3), 110, np.uint8)
    cv2.circle(img, (100, 80), 10, DEFAULT_MARKER_BGR[0], -1)
    d = detect_markers(img, COLORS)["C1"]
    np.testing.assert_allclose(d.pixel, [100, 80], atol=0.05)
    assert abs(d.area - math.pi * 100) < 40
    assert 0.6 * 10 / math.sqrt(2) < d.spread < 1.3 * 10 / math.sqrt(2)


def test_input_errors(tmp_path):
    with pytest.raises(ValueError, match="shape"):
        detect_markers(np.zeros((480, 640), np.uint8), COLORS)
    with pytest.raises(ValueError, match="uint8"):
        detect_markers(np.zeros((480, 640, 3), np.float32), COLORS)
    with pytest.raises(ValueError, match="`mask`"):
        detect_markers(np.zeros((48, 64, 3), np.uint8), COLORS, mask=np.ones((10, 10)))
    with pytest.raises(ValueError, match="hue_low"):
        MarkerColor(200, 10)
    with pytest.raises(ValueError, match="marker"):
        MarkerColor.from_dict("purple")
    with pytest.raises(FileNotFoundError, match="nope.png"):
        read_image(tmp_path / "nope.png")
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not a png at all")
    with pytest.raises(ValueError, match="bad.png"):
        read_image(bad)
    grey = tmp_path / "grey.png"
    cv2.imwrite(str(grey), np.zeros((20, 20), np.uint8))
    with pytest.raises(ValueError, match="greyscale"):
        read_image(grey)
