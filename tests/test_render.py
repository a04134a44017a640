"""Synthetic images through jaxloc's camera models (issue 7)."""

import math

import jax.numpy as jnp
import jax.random as jr
import jaxlie
import jaxloc
import numpy as np
import pytest
from jaxloc._vision.calibrate import find_corners
from jaxloc._vision.markers import DEFAULT_MARKER_COLORS, detect_markers
from jaxloc._vision.render import (
    annulus_of,
    DEFAULT_MARKER_BGR,
    render_chessboard,
    render_markers,
    sphere_center_pixel,
)


@pytest.mark.parametrize(
    "camera,points",
    [
        (jaxloc.paper_overhead_camera(), [[0.3, -0.2, 3.1], [-0.8, 0.4, 3.4]]),
        (jaxloc.paper_ptz_camera(pan=0.2), [[-0.6, 0.0, 1.5], [0.9, 0.05, 2.0]]),
        (jaxloc.paper_omni_camera(), [[1.5, 0.3, 0.05], [-1.0, -1.2, -0.1]]),
    ],
)
def test_render_markers_truth(camera, points):
    p = np.asarray(points)
    img, truth = render_markers(camera, p, key=jr.key(0), names=["a", "b"])
    w, h = camera.image_size
    assert img.shape == (h, w, 3) and img.dtype == np.uint8
    proj = np.asarray(camera.project(jnp.asarray(p)))
    for t, q in zip(truth, proj):
        assert t["visible"] and not t["truncated"]
        np.testing.assert_allclose(t["center_px"], q, atol=1e-9)
        # The silhouette's centroid is near the centre's projection (sphere bias < 1 px).
        assert np.linalg.norm(np.asarray(t["centroid_px"]) - q) < 1.0
        assert t["area_px"] > 20
    # Same key, same image; another key, another image.
    img2, _ = render_markers(camera, p, key=jr.key(0), names=["a", "b"])
    img3, _ = render_markers(camera, p, key=jr.key(1), names=["a", "b"])
    assert np.array_equal(img, img2) and not np.array_equal(img, img3)


def test_invisible_marker_and_bad_arguments():
    cam = jaxloc.paper_overhead_camera()
    _, truth = render_markers(cam, np.array([[0.0, 0.0, -2.0]]), key=jr.key(0))
    assert not truth[0]["visible"] and truth[0]["centroid_px"] is None
    with pytest.raises(ValueError, match="colors"):
        render_markers(cam, np.zeros((4, 3)) + [0, 0, 3], key=jr.key(0))
    with pytest.raises(ValueError, match="radius"):
        render_markers(cam, np.array([[0.0, 0.0, 3.0]]), key=jr.key(0), radius=-0.1)


def test_sphere_center_correction():
    # A close marker near the edge of the wide PTZ: centroid and centre differ by ~1 px.
    cam = jaxloc.paper_ptz_camera()
    p = np.array([[-1.1, 0.2, 1.4]])
    img, truth = render_markers(cam.pinhole(), p, key=jr.key(2), colors=[DEFAULT_MARKER_BGR[0]],
                                radius=0.08, distractors=0)  # fmt: skip
    t = truth[0]
    bias = np.linalg.norm(np.subtract(t["centroid_px"], t["center_px"]))
    assert bias > 0.5
    d = detect_markers(img, {"r": DEFAULT_MARKER_COLORS["red"]})["r"]
    fixed = sphere_center_pixel(cam.pinhole(), d.pixel, d.area)
    assert np.linalg.norm(fixed - np.asarray(t["center_px"])) < 0.1


def test_annulus_of_paper_omni():
    cx, cy, r_in, r_out = annulus_of(jaxloc.paper_omni_camera())
    assert (cx, cy) == (319.5, 239.5)
    assert abs(r_in - 0.5543 * 185) < 0.5 and abs(r_out - 1.2349 * 185) < 0.5


def test_chessboard_pinhole_corners_detected_accurately():
    cam = jaxloc.PinholeCamera(520.0, 520.0, 318.0, 242.0, (-0.2, 0.05, 0.0, 0.0, 0.0))
    R = jaxlie.SO3.from_rpy_radians(0.3, -0.2, 0.1)
    T = jaxlie.SE3.from_rotation_and_translation(R, jnp.array([-0.1, -0.05, 0.5]))
    img, corners, obj = render_chessboard(cam, T, (9, 6), 0.025, key=jr.key(0))
    assert img.shape == (480, 640) and obj.shape == (54, 3)
    assert np.all(np.isfinite(corners))
    found = find_corners(img, (9, 6))
    assert found is not None
    assert np.max(np.linalg.norm(found - corners, axis=-1)) < 0.1
    # Corners are where the camera model projects the object points.
    p = obj @ np.asarray(R.as_matrix()).T + np.asarray(T.translation())
    np.testing.assert_allclose(corners, np.asarray(cam.project(jnp.asarray(p))), atol=1e-9)


def test_chessboard_omni_is_rendered_in_the_band():
    cam = jaxloc.paper_omni_camera()
    c = np.array([0.4, 0.0, 0.05])
    R = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # board faces -x
    T = jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.from_matrix(jnp.asarray(R)), jnp.asarray(c - R @ np.array([0.1, 0.06, 0.0]))
    )
    img, corners, _ = render_chessboard(cam, T, (9, 6), 0.025, key=jr.key(1), supersample=2)
    assert np.all(np.isfinite(corners))
    r = np.hypot(corners[:, 0] - 319.5, corners[:, 1] - 239.5)
    cx, cy, r_in, r_out = annulus_of(cam)
    assert np.all((r > r_in) & (r < r_out))
    # Dark and light squares are both present around the corners.
    u, v = np.round(corners[22]).astype(int)
    patch = img[v - 3 : v + 4, u - 3 : u + 4]
    assert patch.min() < 80 and patch.max() > 170
    assert math.isfinite(float(img.mean()))
