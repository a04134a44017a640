"""Camera models beyond the paper's defaults: missing data (issue 17.1), dtype (17.15),
closed-form projection Jacobians (issue 19), OpenCV's rational model, equidistant
(fisheye) distortion for the pinhole and the omni camera (issue 20.5), and the
zoom-calibrated PTZ camera (issue 20.4)."""

import math
import os
import subprocess
import sys
import textwrap

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxloc._cameras.models import (
    AbstractCamera,
    OmniCamera,
    PinholeCamera,
    project_with_jacobian_autodiff,
    PTZCamera,
    ZoomTable,
)


# Every distortion model and camera type (the paper's three defaults are covered by
# tests/test_camera.py as well).
LEFT_K = np.array([[535.9157, 0.0, 342.2832], [0.0, 535.9157, 235.5708], [0.0, 0.0, 1.0]])
LEFT_D = np.array([-0.266373, -0.0385889, 0.00178319, -0.000281221, 0.238392])
RATIONAL = (1.8, 0.9, 1e-3, -5e-4, 0.05, 2.1, 1.3, 0.2)  # k1 k2 p1 p2 k3 k4 k5 k6
FISHEYE = (-0.013, 0.02, -0.015, 0.004)  # k1..k4, a ~165 deg fisheye on 640x480
TABLE = ZoomTable(
    [0.0, 0.4, 1.0],
    [420.0, 700.0, 1500.0],
    [421.5, 702.0, 1504.0],
    [321.0, 318.5, 316.0],
    [238.0, 240.5, 243.0],
    [[-0.2, 0.05, 1e-3, -5e-4, 0.0], [-0.1, 0.02, 5e-4, 0.0, 0.0], [-0.02, 0.0, 0.0, 1e-4, 0.0]],
)


def _cameras():
    return {
        "pinhole": PinholeCamera.from_opencv(LEFT_K, LEFT_D, (640, 480)),
        "rational": PinholeCamera(400.0, 402.0, 320.0, 240.0, RATIONAL),
        "equidistant": PinholeCamera(280.0, 281.0, 322.0, 238.0, FISHEYE, distortion="equidistant"),
        "ptz": PTZCamera(pan=0.3, tilt=-0.2, zoom=0.4, dist=(-0.05, 0.01, 1e-3, -5e-4, 0.0)),
        "ptz_table": PTZCamera(pan=-0.4, tilt=0.25, zoom=0.7, zoom_table=TABLE),
        "omni": OmniCamera(
            0.9, 180.0, 182.0, 320.0, 240.0, skew=0.5, dist=(-0.02, 0.003, 1e-3, -1e-3)
        ),
        "omni_equidistant": OmniCamera(
            0.9, 180.0, 182.0, 320.0, 240.0, skew=0.5, dist=(-0.02, 0.003, 1e-3, -1e-3),
            distortion="equidistant",
        ),  # fmt: skip
    }


NAMES = list(_cameras())


@eqx.filter_jit
def _call(camera, method, x):
    return getattr(camera, method)(x)


def _jacobians(camera, p):
    closed = _call(camera, "project_with_jacobian", jnp.asarray(p))
    auto = eqx.filter_jit(project_with_jacobian_autodiff)(camera, jnp.asarray(p))
    return closed, auto


def _points_in_view(camera, n, seed=0):
    rng = np.random.default_rng(seed)
    w, h = camera.image_size
    pts = []
    while sum(len(p) for p in pts) < n:
        uv = rng.uniform([0.0, 0.0], [w - 1.0, h - 1.0], size=(4 * n, 2))
        p = np.asarray(_call(camera, "unproject", jnp.asarray(uv))) * rng.uniform(
            0.5, 5.0, size=(4 * n, 1)
        )
        pts.append(p[np.asarray(_call(camera, "in_view", jnp.asarray(p)))])
    return np.concatenate(pts)[:n]


def _image_grid(w, h, step):
    uu, vv = np.meshgrid(np.arange(-0.5, w, step), np.arange(-0.5, h, step))
    return np.stack([uu, vv], axis=-1).reshape(-1, 2)


def _float32(camera):
    return jax.tree.map(lambda x: x.astype(jnp.float32) if eqx.is_inexact_array(x) else x, camera)


# --------------------------------------------------------------------------------------
# Missing data (issue 17.1): a non-finite pixel is a missing measurement.

_BAD_PIXELS = [[np.nan, np.nan], [np.nan, 100.0], [100.0, np.inf], [-np.inf, 3.0]]
_BAD_POINTS = [[np.nan, 0.0, 1.0], [0.1, np.inf, 2.0], [0.0, 0.0, -np.inf], [np.nan] * 3]


@pytest.mark.parametrize("name", NAMES)
def test_nonfinite_pixels_unproject_to_nan(name):
    # Regression, issue 17.1: `unproject([nan, nan])` returned the optical axis [0, 0, 1],
    # which turned a missed detection into a confident wrong pose.
    cam = _cameras()[name]
    good = np.array([[300.0, 200.0], [100.0, 350.0]])
    uv = np.concatenate([good[:1], _BAD_PIXELS, good[1:]])
    b = np.asarray(_call(cam, "unproject", jnp.asarray(uv)))
    assert np.all(np.isnan(b[1:-1])), b[1:-1]
    # The other rows are those of the same batch without missing pixels, bit for bit.
    filled = np.where(np.isfinite(uv), uv, 250.0)
    np.testing.assert_array_equal(b[[0, -1]], np.asarray(_call(cam, "unproject", filled))[[0, -1]])
    assert np.all(np.isnan(np.asarray(cam.unproject(jnp.array([np.nan, np.nan])))))  # eager
    # The missing bearing is neither projectable nor in view.
    assert not np.any(np.asarray(_call(cam, "in_view", jnp.asarray(b[1:-1]))))
    assert not np.any(np.asarray(_call(cam, "projectable", jnp.asarray(b[1:-1]))))


@pytest.mark.parametrize("name", NAMES)
def test_nonfinite_points_project_to_nan(name):
    cam = _cameras()[name]
    good = _points_in_view(cam, 2)
    p = jnp.asarray(np.concatenate([good[:1], _BAD_POINTS, good[1:]]))
    uv = np.asarray(_call(cam, "project", p))
    assert np.all(np.isnan(uv[1:-1])) and np.all(np.isfinite(uv[[0, -1]]))
    filled = jnp.where(jnp.isfinite(p), p, 0.5)
    np.testing.assert_array_equal(uv[[0, -1]], np.asarray(_call(cam, "project", filled))[[0, -1]])
    uv_j, J = (np.asarray(x) for x in _call(cam, "project_with_jacobian", p))
    assert np.all(np.isnan(uv_j[1:-1])) and np.all(np.isnan(J[1:-1]))
    assert np.all(np.isfinite(J[[0, -1]]))
    expected = [True] + [False] * 4 + [True]
    np.testing.assert_array_equal(np.asarray(_call(cam, "in_view", p)), expected)
    np.testing.assert_array_equal(np.asarray(_call(cam, "projectable", p)), expected)


@pytest.mark.parametrize("name", NAMES)
def test_missing_data_keeps_gradients_finite(name):
    # The double `where`: a missing row changes neither the other rows' values nor any
    # gradient (with respect to the camera's parameters or the finite inputs).
    cam = _cameras()[name]
    good = _points_in_view(cam, 3)
    with_missing = np.concatenate([good[:1], _BAD_POINTS[:2], good[1:]])
    uv_good = np.asarray(_call(cam, "project", good))
    uv_missing = np.concatenate([uv_good[:1], _BAD_PIXELS[:2], uv_good[1:]])

    def masked(x):
        return jnp.where(jnp.isfinite(x), x, 0.0)

    def loss(c, p, uv):
        _, J = c.project_with_jacobian(p)
        return (
            jnp.sum(masked(c.project(p)) ** 2)
            + jnp.sum(masked(c.unproject(uv)) ** 2 * jnp.arange(1.0, 4.0)[None, :])
            + jnp.sum(masked(J) ** 2) * 1e-6
        )

    grad = eqx.filter_jit(eqx.filter_grad(loss))
    g_missing = grad(cam, jnp.asarray(with_missing), jnp.asarray(uv_missing))
    g_clean = grad(cam, jnp.asarray(good), jnp.asarray(uv_good))
    for a, b in zip(jax.tree.leaves(g_missing), jax.tree.leaves(g_clean)):
        assert np.all(np.isfinite(np.asarray(a)))
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-12)
    gp = jax.jit(jax.grad(lambda p: jnp.sum(masked(cam.project(p)))))(jnp.asarray(with_missing))
    gp = np.asarray(gp)
    assert np.all(np.isfinite(gp[[0, 3, 4]]))


# --------------------------------------------------------------------------------------
# dtype (issue 17.15).


@pytest.mark.parametrize("name", NAMES)
def test_float32_stays_float32(name):
    cam = _float32(_cameras()[name])
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(cam))
    p = jnp.asarray(_points_in_view(_cameras()[name], 5), dtype=jnp.float32)
    uv = _call(cam, "project", p)
    assert uv.dtype == jnp.float32
    assert _call(cam, "unproject", uv).dtype == jnp.float32
    assert _call(cam, "in_view", p).dtype == jnp.bool_
    uv_j, J = _call(cam, "project_with_jacobian", p)
    assert uv_j.dtype == jnp.float32 and J.dtype == jnp.float32
    _, J_auto = eqx.filter_jit(project_with_jacobian_autodiff)(cam, p)
    np.testing.assert_allclose(J, J_auto, rtol=2e-3, atol=1e-3 * float(jnp.max(jnp.abs(J_auto))))
    # NaN stays NaN in float32.
    assert _call(cam, "unproject", jnp.full((2,), jnp.nan, jnp.float32)).dtype == jnp.float32


def test_float32_without_x64():
    # jaxloc is about to stop enabling x64 on import: with x64 off, cameras built from
    # Python numbers are float32 and nothing asks for float64 (no warning).
    script = textwrap.dedent(
        """
        import warnings
        warnings.simplefilter("error")
        import jax, jax.numpy as jnp, equinox as eqx, numpy as np
        import jaxloc
        jax.config.update("jax_enable_x64", False)
        from jaxloc import OmniCamera, PinholeCamera, PTZCamera, ZoomTable
        table = ZoomTable([0.0, 1.0], [400.0, 900.0], [400.0, 900.0], [320.0, 321.0],
                          [240.0, 239.0], np.zeros((2, 5)))
        cams = [
            jaxloc.paper_overhead_camera(), jaxloc.paper_ptz_camera(0.1, 0.2, 0.3),
            jaxloc.paper_omni_camera(),
            PinholeCamera(400.0, 400.0, 320.0, 240.0, np.array([0.1, 0.01, 0, 0, 0, 0.2, 0, 0])),
            PinholeCamera(300.0, 300.0, 320.0, 240.0, (0.01, 0, 0, 0), distortion="equidistant"),
            PTZCamera(zoom=0.5, zoom_table=table),
            OmniCamera(0.9, 180.0, 180.0, 320.0, 240.0, dist=(0.01, 0, 0, 0),
                       distortion="equidistant"),
        ]
        p = jnp.array([[0.1, -0.05, 1.0], [0.3, 0.2, 1.0], [1.0, 0.3, 0.1]])
        for cam in cams:
            for leaf in jax.tree.leaves(cam):
                assert leaf.dtype == jnp.float32, (type(cam).__name__, leaf.dtype)
            uv, J = eqx.filter_jit(lambda c, x: c.project_with_jacobian(x))(cam, p)
            b = eqx.filter_jit(lambda c, x: c.unproject(x))(cam, uv)
            v = eqx.filter_jit(lambda c, x: c.in_view(x))(cam, p)
            assert uv.dtype == J.dtype == b.dtype == jnp.float32 and v.dtype == jnp.bool_
            assert bool(jnp.all(jnp.isfinite(J)))
            ok = np.array(eqx.filter_jit(lambda c, x: c.projectable(x))(cam, p))
            ok[2:] = False  # the last point is far off axis: dtype and finiteness only
            want = np.asarray(p / jnp.linalg.norm(p, axis=-1, keepdims=True))
            np.testing.assert_allclose(np.asarray(b)[ok], want[ok], atol=1e-4)
        print("ok")
        """
    )
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=600
    )
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-3000:]


# --------------------------------------------------------------------------------------
# Closed-form projection Jacobians (issue 19).


@pytest.mark.parametrize("name", NAMES)
def test_jacobian_matches_jacfwd(name):
    cam = _cameras()[name]
    rng = np.random.default_rng(1)
    p = _points_in_view(cam, 200, seed=2)
    # Projectable points outside the image (and band) too: the Jacobian is of the model.
    p_out = p * rng.uniform(-2.0, 2.0, size=p.shape)
    pts = np.concatenate([p, p_out, [[1e-3, -2e-3, 1.0], [0.0, 0.0, 1.0]]])
    (uv, J), (uv_auto, J_auto) = _jacobians(cam, pts)
    J, J_auto = np.asarray(J), np.asarray(J_auto)
    np.testing.assert_allclose(uv, uv_auto, rtol=0, atol=1e-9)
    scale = np.abs(J_auto).max(axis=(-1, -2))
    err = np.abs(J - J_auto).max(axis=(-1, -2))
    assert np.all(err <= 1e-10 * scale), (err / scale).max()
    # Eager equals jitted; leading batch axes broadcast.
    tol = 1e-13 * scale.max()
    uv_e, J_e = cam.project_with_jacobian(jnp.asarray(pts[:4]))
    np.testing.assert_allclose(J_e, J[:4], rtol=1e-13, atol=tol)
    uv_b, J_b = _call(cam, "project_with_jacobian", jnp.asarray(pts[:6].reshape(2, 3, 3)))
    assert uv_b.shape == (2, 3, 2) and J_b.shape == (2, 3, 2, 3)
    np.testing.assert_allclose(J_b.reshape(6, 2, 3), J[:6], rtol=1e-13, atol=tol)
    J_one = _call(cam, "project_with_jacobian", jnp.asarray(pts[0]))[1]
    np.testing.assert_allclose(J_one, J[0], rtol=1e-13, atol=tol)


@pytest.mark.parametrize("name", NAMES)
def test_jacobian_finite_where_the_model_cannot_project(name):
    cam = _cameras()[name]
    pts = np.array([
        [0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.3, -0.2, -1.0], [1.0, 0.0, 0.0],
        [1e-8, 0.0, 1e-8], [1.0, 2.0, 1e-12], [0.0, 1e6, 1e-6], [1e8, -1e8, 3.0],
        [0.3, 0.4, -0.01],
    ])  # fmt: skip
    (uv, J), (_, J_auto) = _jacobians(cam, pts)
    J, J_auto = np.asarray(J), np.asarray(J_auto)
    assert np.all(np.isfinite(np.asarray(uv))) and np.all(np.isfinite(J))
    # Saturated: the closed form differentiates the saturation floor as autodiff does.
    scale = np.maximum(np.abs(J_auto).max(axis=(-1, -2)), 1e-300)
    assert np.all(np.abs(J - J_auto).max(axis=(-1, -2)) <= 1e-10 * scale)


def test_default_jacobian_for_a_new_model():
    # A camera model that does not override `project_with_jacobian` gets it by jacfwd.

    class Equirectangular(AbstractCamera):
        f: jax.Array
        image_size: tuple[int, int] = eqx.field(static=True)

        def project(self, points_cam):
            p = jnp.asarray(points_cam)
            az = jnp.arctan2(p[..., 1], p[..., 0])
            el = jnp.arctan2(p[..., 2], jnp.hypot(p[..., 0], p[..., 1]))
            return jnp.stack([self.f * az + 320.0, -self.f * el + 240.0], axis=-1)

        def unproject(self, pixels):
            raise NotImplementedError

        def projectable(self, points_cam):
            return jnp.ones(jnp.shape(points_cam)[:-1], bool)

        def in_view(self, points_cam):
            return self.projectable(points_cam)

    cam = Equirectangular(jnp.asarray(100.0), (640, 480))
    p = jnp.array([[[1.0, 0.5, 0.2], [0.3, -1.0, 0.4]]])
    uv, J = cam.project_with_jacobian(p)
    assert uv.shape == (1, 2, 2) and J.shape == (1, 2, 2, 3)
    for i in range(2):
        np.testing.assert_allclose(J[0, i], jax.jacfwd(cam.project)(p[0, i]), rtol=1e-14)
        np.testing.assert_allclose(uv[0, i], cam.project(p[0, i]), rtol=1e-14)


# --------------------------------------------------------------------------------------
# Round trips of the new models.


@pytest.mark.parametrize("name", ["rational", "equidistant", "ptz_table", "omni_equidistant"])
def test_round_trip(name):
    cam = _cameras()[name]
    p = _points_in_view(cam, 300)
    b = _call(cam, "unproject", _call(cam, "project", jnp.asarray(p)))
    np.testing.assert_allclose(b, p / np.linalg.norm(p, axis=-1, keepdims=True), atol=1e-9)
    if name == "omni_equidistant":
        return  # the image corners lie outside what the model can reach (see below)
    uv = _image_grid(*cam.image_size, step=7.0)
    back = _call(cam, "project", _call(cam, "unproject", jnp.asarray(uv)))
    assert float(jnp.max(jnp.abs(back - uv))) < 1e-9


# --------------------------------------------------------------------------------------
# OpenCV's rational model (issue 20.5).


def test_rational_matches_opencv():
    cam = _cameras()["rational"]
    K, d, size = cam.to_opencv()
    assert d.shape == (8,) and size == (640, 480)
    rng = np.random.default_rng(4)
    pts = rng.uniform([-1.0, -0.8, 0.9], [1.0, 0.8, 3.0], size=(1000, 3))
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, d)
    uv = np.asarray(_call(cam, "project", jnp.asarray(pts)))
    np.testing.assert_allclose(uv, ref[:, 0], atol=1e-6, rtol=0)
    uv = _image_grid(640, 480, step=11.0)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    und = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, d, criteria=crit)[:, 0]
    b = np.asarray(_call(cam, "unproject", jnp.asarray(uv)))
    np.testing.assert_allclose(b[:, :2] / b[:, 2:], und, atol=1e-8, rtol=0)


def test_rational_with_zero_k456_is_brown_conrady():
    five = PinholeCamera.from_opencv(LEFT_K, LEFT_D)
    eight = PinholeCamera.from_opencv(LEFT_K, np.concatenate([LEFT_D, np.zeros(3)]))
    assert eight.dist.shape == (8,)
    p = jnp.asarray(_points_in_view(five, 100))
    np.testing.assert_allclose(_call(eight, "project", p), _call(five, "project", p), atol=1e-10)
    J8 = _call(eight, "project_with_jacobian", p)[1]
    J5 = _call(five, "project_with_jacobian", p)[1]
    np.testing.assert_allclose(J8, J5, rtol=1e-12, atol=1e-9)


def test_rational_in_view_rejects_pole_and_fold():
    # Denominator 1 - 0.5 r^2 vanishes at r^2 = 2: beyond it the model is meaningless
    # (and, near it, blows up and folds back).
    cam = PinholeCamera(200.0, 200.0, 319.5, 239.5, (0.0, 0.0, 0.0, 0.0, 0.0, -0.5, 0.0, 0.0),
                        image_size=(640, 480))  # fmt: skip
    near = jnp.array([0.3, 0.2, 1.0])
    beyond = jnp.array([3.0, 0.0, 1.0])  # r^2 = 9: x_d = 3 / (1 - 4.5) < 0
    u = float(_call(cam, "project", beyond)[0])
    assert -0.5 < u < 639.5  # folded back into the image
    np.testing.assert_array_equal(_call(cam, "in_view", jnp.stack([near, beyond])), [True, False])
    assert np.all(np.isfinite(np.asarray(_call(cam, "project", jnp.array([math.sqrt(2), 0, 1])))))


def test_from_to_opencv_distortion_models():
    K = LEFT_K
    for d in (np.array(RATIONAL), np.array(RATIONAL).reshape(1, 8), np.array(RATIONAL)[:, None]):
        cam = PinholeCamera.from_opencv(K, d, (640, 480))
        K2, d2, _ = cam.to_opencv()
        np.testing.assert_array_equal(K2, K)
        np.testing.assert_array_equal(d2, np.array(RATIONAL))
    fish = PinholeCamera.from_opencv(K, np.array(FISHEYE)[None], distortion="equidistant")
    assert fish.distortion == "equidistant"
    np.testing.assert_array_equal(fish.to_opencv()[1], FISHEYE)
    assert PinholeCamera.from_opencv(K, None, distortion="equidistant").dist.shape == (4,)
    with pytest.raises(ValueError, match=r"`dist` must hold 4 coefficients \(k1, k2, k3, k4\)"):
        PinholeCamera.from_opencv(K, np.zeros(5), distortion="equidistant")
    with pytest.raises(ValueError, match="`distortion`"):
        PinholeCamera.from_opencv(K, np.zeros(5), distortion="fov")


def test_distortion_model_errors():
    with pytest.raises(ValueError, match=r"`PinholeCamera\(dist=...\)` must have shape \(4,\)"):
        PinholeCamera(300.0, 300.0, 320.0, 240.0, np.zeros(5), distortion="equidistant")
    with pytest.raises(ValueError, match=r"must have shape \(5,\) or \(8,\)"):
        PinholeCamera(300.0, 300.0, 320.0, 240.0, np.zeros(6))
    with pytest.raises(ValueError, match=r"`PinholeCamera\(distortion=...\)` must be one of"):
        PinholeCamera(300.0, 300.0, 320.0, 240.0, distortion="kannala")
    with pytest.raises(ValueError, match=r"`OmniCamera\(distortion=...\)` must be one of"):
        OmniCamera(1.0, 180.0, 180.0, 320.0, 240.0, distortion="fov")
    with pytest.raises(ValueError, match=r"`PTZCamera\(dist=...\)` must have shape \(4,\)"):
        PTZCamera(distortion="equidistant", dist=np.zeros(5))
    # No distortion in each model's own size.
    assert PinholeCamera(1.0, 1.0, 0.0, 0.0, distortion="equidistant").dist.shape == (4,)
    assert PTZCamera(distortion="equidistant").pinhole().dist.shape == (4,)


# --------------------------------------------------------------------------------------
# Equidistant distortion (Kalibr `equidistant`, OpenCV `fisheye`; issue 20.5).


def test_equidistant_matches_opencv_fisheye():
    cam = _cameras()["equidistant"]
    K, D, _ = cam.to_opencv()
    rng = np.random.default_rng(5)
    pts = rng.uniform([-3.0, -2.0, 0.2], [3.0, 2.0, 3.0], size=(1000, 3))
    ref, _ = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    uv = np.asarray(_call(cam, "project", jnp.asarray(pts)))
    np.testing.assert_allclose(uv, ref[:, 0], atol=1e-6, rtol=0)
    uv = _image_grid(640, 480, step=11.0)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
    und = cv2.fisheye.undistortPoints(uv.reshape(-1, 1, 2), K, D, criteria=crit)[:, 0]
    b = np.asarray(_call(cam, "unproject", jnp.asarray(uv)))
    np.testing.assert_allclose(b[:, :2] / b[:, 2:], und, rtol=1e-8, atol=1e-9)


def test_equidistant_zero_coefficients_is_the_equidistant_projection():
    # k = 0 is not the identity: theta_d = theta, r_d = atan(r) (an f-theta lens).
    cam = PinholeCamera(300.0, 300.0, 319.5, 239.5, distortion="equidistant")
    t = np.radians([0.0, 10.0, 45.0, 80.0])
    p = np.stack([np.sin(t), 0 * t, np.cos(t)], axis=-1)
    np.testing.assert_allclose(_call(cam, "project", jnp.asarray(p))[:, 0], 319.5 + 300.0 * t,
                               atol=1e-10)  # fmt: skip


def test_equidistant_in_view_rejects_fold():
    # theta_d = theta (1 - 0.5 theta^2) turns back at theta = 0.816 rad (46.8 deg).
    cam = PinholeCamera(500.0, 500.0, 319.5, 239.5, (-0.5, 0.0, 0.0, 0.0), distortion="equidistant")
    t = np.radians([20.0, 40.0, 60.0])
    p = np.stack([np.sin(t), 0 * t, np.cos(t)], axis=-1)
    u = np.asarray(_call(cam, "project", jnp.asarray(p)))[:, 0]
    assert np.all((u > -0.5) & (u < 639.5))
    np.testing.assert_array_equal(_call(cam, "in_view", jnp.asarray(p)), [True, True, False])


def _kalibr_omni_equidistant(p, xi, fu, fv, cu, cv, k):
    """Independent NumPy transcription of Kalibr's `OmniProjection::euclideanToKeypoint`
    with `EquidistantDistortion::distort` (aslam_cameras)."""
    p = np.asarray(p, np.float64)
    d = np.linalg.norm(p, axis=-1)
    rz = 1.0 / (p[:, 2] + xi * d)
    y = p[:, :2] * rz[:, None]
    r = np.linalg.norm(y, axis=-1)
    theta = np.arctan(r)
    thetad = theta * (1 + k[0] * theta**2 + k[1] * theta**4 + k[2] * theta**6 + k[3] * theta**8)
    scaling = np.where(r > 1e-8, thetad / np.where(r > 1e-8, r, 1.0), 1.0)
    y = y * scaling[:, None]
    return np.stack([fu * y[:, 0] + cu, fv * y[:, 1] + cv], axis=-1)


def test_omni_equidistant_matches_kalibr():
    k = (-0.02, 0.003, 1e-3, -1e-3)
    cam = OmniCamera.from_kalibr([0.9, 180.0, 182.0, 320.0, 240.0], k, [640, 480],
                                 distortion_model="equidistant")  # fmt: skip
    assert cam.distortion == "equidistant" and float(cam.skew) == 0.0
    rng = np.random.default_rng(6)
    az, el = rng.uniform(-np.pi, np.pi, 500), rng.uniform(-0.5, 1.4, 500)
    p = rng.uniform(0.5, 4.0, (500, 1)) * np.stack(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1
    )
    ref = _kalibr_omni_equidistant(p, 0.9, 180.0, 182.0, 320.0, 240.0, k)
    np.testing.assert_allclose(_call(cam, "project", jnp.asarray(p)), ref, atol=1e-9, rtol=0)


def test_from_kalibr_distortion_models():
    intr = [461.6, 460.3, 363.0, 248.1]
    pin = PinholeCamera.from_kalibr(intr, "equidistant", FISHEYE, [752, 480])
    assert pin.distortion == "equidistant" and pin.image_size == (752, 480)
    np.testing.assert_array_equal(np.asarray(pin.dist), FISHEYE)
    rad = PinholeCamera.from_kalibr(intr, "radtan", [-0.28, 0.07, 2e-4, 2e-5], [752, 480])
    np.testing.assert_array_equal(np.asarray(rad.dist), [-0.28, 0.07, 2e-4, 2e-5, 0.0])
    none = PinholeCamera.from_kalibr(intr, "none", None, [752, 480])
    assert none.distortion == "radtan" and not np.any(np.asarray(none.dist))
    omni = OmniCamera.from_kalibr([0.8, 267.5, 266.9, 312.3, 243.1], None, [640, 480],
                                  distortion_model="none")  # fmt: skip
    assert omni.distortion == "radtan" and not np.any(np.asarray(omni.dist))
    with pytest.raises(ValueError, match="distortion_model"):
        PinholeCamera.from_kalibr([1.0, 1.0, 0.0, 0.0], "fov", [0.5], [640, 480])
    with pytest.raises(ValueError, match="distortion_model"):
        OmniCamera.from_kalibr([0.8, 1.0, 1.0, 0.0, 0.0], [0.5], [640, 480], distortion_model="fov")


# --------------------------------------------------------------------------------------
# Zoom-calibrated PTZ (issue 20.4).


@pytest.mark.parametrize("jit", [False, True])
def test_zoom_table_is_exact_at_the_steps(jit):
    def intrinsics(zoom):
        pin = PTZCamera(zoom=zoom, zoom_table=TABLE).pinhole()
        return pin.fx, pin.fy, pin.cx, pin.cy, pin.dist

    f = jax.jit(intrinsics) if jit else intrinsics
    for k, z in enumerate(np.asarray(TABLE.zooms)):
        fx, fy, cx, cy, dist = f(jnp.asarray(z))
        assert float(fx) == float(TABLE.fx[k]) and float(fy) == float(TABLE.fy[k])
        assert float(cx) == float(TABLE.cx[k]) and float(cy) == float(TABLE.cy[k])
        np.testing.assert_array_equal(np.asarray(dist), np.asarray(TABLE.dist[k]))


def test_zoom_table_interpolates_reciprocal_focal_length():
    for z0, z1, k in ((0.0, 0.4, 0), (0.4, 1.0, 1)):
        for t in (0.25, 0.5, 0.9):
            fx, fy, cx, cy, dist = TABLE.at(jnp.asarray(z0 + t * (z1 - z0)))
            inv = (1 - t) / TABLE.fx[k] + t / TABLE.fx[k + 1]
            np.testing.assert_allclose(1.0 / float(fx), float(inv), rtol=1e-14)
            inv = (1 - t) / TABLE.fy[k] + t / TABLE.fy[k + 1]
            np.testing.assert_allclose(1.0 / float(fy), float(inv), rtol=1e-14)
            np.testing.assert_allclose(float(cx), (1 - t) * TABLE.cx[k] + t * TABLE.cx[k + 1])
            np.testing.assert_allclose(dist, (1 - t) * TABLE.dist[k] + t * TABLE.dist[k + 1],
                                       atol=1e-16)  # fmt: skip


def test_zoom_table_constant_beyond_the_ends_and_differentiable():
    table = ZoomTable([0.2, 0.6, 0.9], [500.0, 800.0, 1300.0], [500.0, 800.0, 1300.0],
                      [320.0, 321.0, 322.0], [240.0, 240.0, 241.0])  # fmt: skip
    for zoom, k in ((0.0, 0), (0.1, 0), (0.95, 2), (1.0, 2)):
        assert float(PTZCamera(zoom=zoom, zoom_table=table).focal_length()) == float(table.fx[k])

    def u(zoom):
        cam = PTZCamera(pan=0.1, zoom=zoom, zoom_table=table)
        return cam.project(jnp.array([0.3, 0.1, 2.0]))[0]

    g = jax.grad(u)
    for zoom in (0.3, 0.7):
        fd = (float(u(zoom + 1e-6)) - float(u(zoom - 1e-6))) / 2e-6
        assert abs(float(g(zoom)) - fd) < 1e-5 * abs(fd) and fd != 0
    assert float(g(0.1)) == 0.0 and float(g(0.95)) == 0.0
    # Gradients reach every table entry of the active segment.
    gt = eqx.filter_grad(lambda c: c.project(jnp.array([0.3, 0.1, 2.0]))[0])(
        PTZCamera(zoom=0.4, zoom_table=table)
    )
    assert float(gt.zoom_table.fx[0]) != 0.0 and float(gt.zoom_table.fx[1]) != 0.0
    assert float(gt.zoom_table.fx[2]) == 0.0


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_zoom_table_is_continuous_and_a_function_of_zoom_under_vmap_jit_grad(dtype):
    # Issue 20.4: the camera stays a pure JAX function of zoom, in both dtypes.
    table = jax.tree.map(lambda x: x.astype(dtype), TABLE)
    p = jnp.asarray([0.3, 0.1, 2.0], dtype)

    def uv(zoom):
        return PTZCamera(pan=0.1, zoom=zoom, zoom_table=table).project(p)

    zooms = jnp.linspace(0.0, 1.0, 2001, dtype=dtype)  # the steps 0, 0.4, 1 are on the grid
    batch = jax.jit(jax.vmap(uv))(zooms)
    assert batch.dtype == dtype
    loop = np.stack([np.asarray(uv(z)) for z in zooms[::100]])
    np.testing.assert_allclose(batch[::100], loop, rtol=1e-6 if dtype == jnp.float32 else 1e-13)
    # Continuous: no jump between neighbouring zooms beyond the slope times the spacing,
    # across the calibrated steps too (the two segments meet at the step's values).
    slope = np.asarray(jax.jit(jax.vmap(jax.jacfwd(uv)))(zooms))
    assert slope.dtype == dtype and np.all(np.isfinite(slope))
    step = np.abs(np.diff(np.asarray(batch, np.float64), axis=0))
    # (The slope at 0 and 1 is one-sided, 0 beyond the table: take the largest of the
    # slopes at the interval's ends and at its neighbours'.)
    a = np.pad(np.abs(slope), ((1, 1), (0, 0)), mode="edge")
    near = np.maximum.reduce([a[:-3], a[1:-2], a[2:-1], a[3:]])
    bound = 5e-4 * near * 1.05 + (1e-3 if dtype == jnp.float32 else 1e-9)
    assert np.all(step <= bound), np.max(step - bound)
    k = int(np.argmin(np.abs(np.asarray(zooms) - 0.4)))
    for eps in (1e-3, 1e-5):
        below, at, above = (np.asarray(uv(jnp.asarray(0.4 + d, dtype))) for d in (-eps, 0, eps))
        assert np.all(np.abs(below - at) < 2e3 * eps + 1e-3)
        assert np.all(np.abs(above - at) < 2e3 * eps + 1e-3)
    np.testing.assert_allclose(batch[k], uv(jnp.asarray(0.4, dtype)), rtol=1e-6)
    # grad through the table in this dtype equals the float64 finite difference.
    g = jax.jit(jax.grad(lambda z: uv(z)[0]))(jnp.asarray(0.7, dtype))
    assert g.dtype == dtype
    u64 = lambda z: float(PTZCamera(pan=0.1, zoom=z, zoom_table=TABLE).project(  # noqa: E731
        jnp.asarray([0.3, 0.1, 2.0]))[0])
    fd = (u64(0.7 + 1e-6) - u64(0.7 - 1e-6)) / 2e-6
    np.testing.assert_allclose(float(g), fd, rtol=1e-3 if dtype == jnp.float32 else 1e-6)


def test_zoom_table_default_model_unchanged():
    # The two-end model stays the default: no table, focal length linear in zoom.
    cam = PTZCamera(zoom=0.25)
    assert cam.zoom_table is None
    w = 640
    f_wide, f_tele = (w / 2) / math.tan(math.radians(42.5)), (w / 2) / math.tan(math.radians(7.5))
    np.testing.assert_allclose(cam.focal_length(), f_wide + 0.25 * (f_tele - f_wide), rtol=1e-15)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: ZoomTable([0.0], [1.0], [1.0], [0.0], [0.0]), r"n >= 2"),
        (lambda: ZoomTable([0.0, 0.5, 0.5], [1.0] * 3, [1.0] * 3, [0.0] * 3, [0.0] * 3),
         r"strictly increasing"),
        (lambda: ZoomTable([0.0, 1.5], [1.0] * 2, [1.0] * 2, [0.0] * 2, [0.0] * 2),
         r"`ZoomTable\(zooms=...\)` must lie in \[0, 1\]"),
        (lambda: ZoomTable([0.0, 1.0], [1.0, -1.0], [1.0] * 2, [0.0] * 2, [0.0] * 2),
         r"`ZoomTable\(fx=...\)` must be positive"),
        (lambda: ZoomTable([0.0, 1.0], [1.0] * 3, [1.0] * 2, [0.0] * 2, [0.0] * 2),
         r"`ZoomTable\(fx=...\)` must have shape \(2,\)"),
        (lambda: ZoomTable([0.0, 1.0], [1.0] * 2, [1.0] * 2, [0.0] * 2, [0.0] * 2, np.zeros(5)),
         r"`ZoomTable\(dist=...\)` must have shape \(2, m\)"),
        (lambda: PTZCamera(zoom_table=TABLE, dist=(0.1, 0, 0, 0, 0)),
         r"`PTZCamera\(dist=...\)` is not used with a `zoom_table`"),
        (lambda: PTZCamera(zoom_table=TABLE, distortion="equidistant"),
         r"`PTZCamera\(zoom_table=...\)` holds 5 distortion coefficients"),
    ],
)  # fmt: skip
def test_zoom_table_rejects_bad_tables(make, match):
    with pytest.raises(ValueError, match=match):
        make()
