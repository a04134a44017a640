import math
import os

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from jaxloc._cameras.models import OmniCamera, PinholeCamera, PTZCamera


SHARED = os.path.join(os.path.dirname(__file__), "..", "..", "shared")
_INTRINSICS = os.path.join(SHARED, "data", "opencv-left-chessboard", "left_intrinsics.yml")


def _opencv_left():
    """K, dist of OpenCV's left01..14 sample calibration (640 x 480)."""
    if os.path.exists(_INTRINSICS):
        fs = cv2.FileStorage(_INTRINSICS, cv2.FILE_STORAGE_READ)
        K = fs.getNode("camera_matrix").mat()
        d = fs.getNode("distortion_coefficients").mat()
        fs.release()
        return K, d
    K = np.array(
        [
            [535.9157339616, 0.0, 342.2831547331],
            [0.0, 535.9157339616, 235.5708290979],
            [0.0, 0.0, 1.0],
        ]
    )
    d = np.array(
        [
            [-0.26637260909660682],
            [-0.038588898922304653],
            [0.0017831947042852964],
            [-0.00028122100441115472],
            [0.23839153080878486],
        ]
    )
    return K, d


@eqx.filter_jit
def _call(camera, method, x):
    """`camera.<method>(x)` under jit (keeps the test file fast: eager mode compiles every
    primitive separately)."""
    return getattr(camera, method)(x)


def _P(camera, x):
    return _call(camera, "project", jnp.asarray(x))


def _U(camera, x):
    return _call(camera, "unproject", jnp.asarray(x))


def _left_camera():
    K, d = _opencv_left()
    return PinholeCamera.from_opencv(K, d, (640, 480)), K, d


def _image_grid(w, h, step=1.0):
    uu, vv = np.meshgrid(np.arange(-0.5, w, step), np.arange(-0.5, h, step))
    return np.stack([uu, vv], axis=-1)


def _cameras():
    K, d = _opencv_left()
    return {
        "pinhole": PinholeCamera.from_opencv(K, d, (640, 480)),
        "ptz": PTZCamera(pan=0.3, tilt=-0.2, zoom=0.4, dist=(-0.05, 0.01, 1e-3, -5e-4, 0.0)),
        "omni": OmniCamera(
            0.9, 180.0, 182.0, 320.0, 240.0, skew=0.5, dist=(-0.02, 0.003, 1e-3, -1e-3)
        ),
    }


def _points_in_view(camera, n, seed=0):
    """Points in view, built by unprojecting random pixels inside the image (and band)."""
    rng = np.random.default_rng(seed)
    w, h = camera.image_size
    pts = []
    while sum(len(p) for p in pts) < n:
        uv = rng.uniform([0.0, 0.0], [w - 1.0, h - 1.0], size=(4 * n, 2))
        p = np.asarray(_U(camera, uv)) * rng.uniform(0.5, 5.0, size=(4 * n, 1))
        pts.append(p[np.asarray(_call(camera, "in_view", jnp.asarray(p)))])
    return np.concatenate(pts)[:n]


# ---------------------------------------------------------------------------------------
# Pinhole vs OpenCV.
# ---------------------------------------------------------------------------------------


def test_pinhole_project_matches_opencv():
    cam, K, d = _left_camera()
    rng = np.random.default_rng(1)
    pts = rng.uniform([-1.0, -0.8, 1.0], [1.0, 0.8, 3.0], size=(500, 3))
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, d)
    uv = np.asarray(_P(cam, pts))
    np.testing.assert_allclose(uv, ref[:, 0], atol=1e-6, rtol=0)


def test_pinhole_unproject_matches_opencv():
    cam, K, d = _left_camera()
    uv = _image_grid(640, 480, step=7.0).reshape(-1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, d, criteria=crit)[:, 0]
    b = np.asarray(_U(cam, uv))
    np.testing.assert_allclose(np.linalg.norm(b, axis=-1), 1.0, atol=1e-12)
    assert np.all(b[:, 2] > 0)
    np.testing.assert_allclose(b[:, :2] / b[:, 2:], ref, atol=1e-9, rtol=0)


def test_pinhole_round_trip_whole_image():
    cam, _, _ = _left_camera()
    uv = _image_grid(640, 480, step=1.0)  # every pixel (and the outer edges)
    back = jax.jit(lambda x: _P(cam, _U(cam, x)))(uv)
    assert float(jnp.max(jnp.abs(back - uv))) < 1e-6  # 1e-13 seen


def test_from_to_opencv():
    K, d = _opencv_left()
    for dist in (d, d.reshape(1, 5), d.reshape(5), d.reshape(5)[:4]):
        cam = PinholeCamera.from_opencv(K, dist, (640, 480))
        K2, d2, size = cam.to_opencv()
        np.testing.assert_array_equal(K2, K)
        assert d2.shape == (5,)
        n = np.asarray(dist).size
        np.testing.assert_array_equal(d2[:n], np.asarray(dist).reshape(-1))
        assert size == (640, 480)
    # 8 coefficients are OpenCV's rational model (issue 20.5); the thin-prism (12) and
    # tilted (14) models are not supported.
    assert PinholeCamera.from_opencv(K, np.zeros(8)).dist.shape == (8,)
    for n in (3, 6, 12, 14):
        with pytest.raises(ValueError, match="`dist`"):
            PinholeCamera.from_opencv(K, np.zeros(n))
    with pytest.raises(ValueError, match="`K`"):
        PinholeCamera.from_opencv(np.eye(2), d)
    K_skew = K.copy()
    K_skew[0, 1] = 1.0
    with pytest.raises(ValueError, match="no skew"):
        PinholeCamera.from_opencv(K_skew, d)


# ---------------------------------------------------------------------------------------
# All models: round trips, jit, vmap, gradients, finiteness.
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["pinhole", "ptz", "omni"])
def test_round_trip_float64(name):
    cam = _cameras()[name]
    w, h = cam.image_size
    uv = _image_grid(w, h, step=9.0).reshape(-1, 2)
    b = _U(cam, uv)
    np.testing.assert_allclose(jnp.linalg.norm(b, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(_P(cam, b), uv, atol=1e-9, rtol=0)
    p = _points_in_view(cam, 300)
    b = _U(cam, _P(cam, p))
    p_unit = p / np.linalg.norm(p, axis=-1, keepdims=True)
    np.testing.assert_allclose(b, p_unit, atol=1e-9, rtol=0)


@pytest.mark.parametrize("name", ["pinhole", "ptz", "omni"])
def test_round_trip_float32(name):
    cam64 = _cameras()[name]
    cam = jax.tree.map(lambda x: x.astype(jnp.float32) if eqx.is_inexact_array(x) else x, cam64)
    p = _points_in_view(cam64, 200).astype(np.float32)
    uv = _P(cam, p)
    assert uv.dtype == jnp.float32
    b = _U(cam, uv)
    assert b.dtype == jnp.float32
    p_unit = p / np.linalg.norm(p, axis=-1, keepdims=True)
    np.testing.assert_allclose(b, p_unit, atol=1e-5, rtol=0)
    np.testing.assert_allclose(_P(cam, b), uv, atol=1e-3, rtol=0)
    np.testing.assert_allclose(uv, _P(cam64, p.astype(np.float64)), atol=1e-3, rtol=0)


def test_float32_leaves_kept():
    cam = PinholeCamera(np.float32(500.0), jnp.float32(500.0), 320, 240)
    assert cam.fx.dtype == jnp.float32 and cam.fy.dtype == jnp.float32
    # Python-number arguments follow the float32 arrays given.
    assert cam.cx.dtype == jnp.float32 and cam.dist.dtype == jnp.float32
    cam64 = PinholeCamera(np.float32(500.0), 500.0, 320.0, np.float64(240.0))
    assert cam64.fx.dtype == jnp.float32 and cam64.fy.dtype == jnp.float64
    assert PinholeCamera(500, 500, 320, 240).fx.dtype == jnp.float64
    assert cam.cx.shape == () and cam.dist.shape == (5,)


@pytest.mark.parametrize("name", ["pinhole", "ptz", "omni"])
def test_jit_equals_eager_and_vmap_equals_loop(name):
    cam = _cameras()[name]
    p = jnp.asarray(_points_in_view(cam, 4))
    uv = _P(cam, p)
    for method, x in (("project", p), ("unproject", uv), ("in_view", p), ("projectable", p)):
        jitted = _call(cam, method, x)
        # Eager mode compiles every primitive: check it on the two main methods only.
        eager = getattr(cam, method)(x) if method in ("project", "unproject") else jitted
        vmapped = jax.vmap(lambda y: getattr(cam, method)(y))(x)
        loop = jnp.stack([_call(cam, method, xi) for xi in x])
        np.testing.assert_allclose(jitted, eager, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(vmapped, eager, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(loop, eager, rtol=1e-12, atol=1e-12)
    # Leading batch axes broadcast.
    np.testing.assert_allclose(_P(cam, p.reshape(2, 2, 3)), uv.reshape(2, 2, 2), atol=1e-12)
    assert _U(cam, uv.reshape(2, 2, 2)).shape == (2, 2, 3)
    assert _call(cam, "in_view", p.reshape(2, 2, 3)).shape == (2, 2)


def test_vmap_over_cameras():
    fs = jnp.array([400.0, 500.0, 600.0])
    cams = jax.vmap(lambda f: PinholeCamera(f, f, 320.0, 240.0))(fs)
    p = jnp.array([0.1, -0.2, 2.0])
    uv = jax.vmap(lambda c: c.project(p))(cams)
    for f, uvi in zip(fs, uv):
        np.testing.assert_allclose(uvi, PinholeCamera(f, f, 320.0, 240.0).project(p))
    pans = jnp.array([-0.1, 0.0, 0.1])
    ptz = jax.jit(jax.vmap(lambda a: PTZCamera(pan=a, zoom=0.5)))(pans)
    assert ptz.pan.shape == (3,)


def _central_fd(f, x, eps=1e-6):
    x = np.asarray(x, dtype=np.float64)
    cols = []
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx.flat[i] = eps
        cols.append((np.asarray(f(x + dx)) - np.asarray(f(x - dx))) / (2 * eps))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("name", ["pinhole", "ptz", "omni"])
def test_jacobian_vs_finite_differences(name):
    cam = _cameras()[name]
    pts = list(_points_in_view(cam, 5))
    if name == "pinhole":
        pts.append(np.array([0.0, 0.0, 2.0]))  # exactly on the optical axis
    if name == "omni":
        pts.append(np.array([1.0, 0.0, 0.0]))  # on the horizon
    jac = jax.jit(jax.jacfwd(cam.project))
    for p in pts:
        J = np.asarray(jac(p))
        assert np.all(np.isfinite(J))
        np.testing.assert_allclose(J, _central_fd(lambda x: _P(cam, x), p), rtol=1e-5, atol=1e-5)
    # Unprojection Jacobian too (through the unrolled undistortion iterations).
    uv = np.asarray(_P(cam, pts[0]))
    Ju = np.asarray(jax.jacfwd(cam.unproject)(uv))
    np.testing.assert_allclose(Ju, _central_fd(lambda x: _U(cam, x), uv, eps=1e-4), atol=1e-7)


@pytest.mark.parametrize("name", ["pinhole", "ptz", "omni"])
def test_gradients_reach_parameters(name):
    cam = _cameras()[name]
    p = jnp.asarray(_points_in_view(cam, 4))
    leaves, treedef = jax.tree.flatten(cam)

    def loss(c):
        return jnp.sum(c.project(p) ** 2)

    grads = eqx.filter_grad(loss)(cam)
    for leaf, g in zip(leaves, jax.tree.leaves(grads)):
        g = np.asarray(g)
        assert np.all(np.isfinite(g))
        # central differences on each entry of each leaf
        for i in range(max(leaf.size, 1)):

            def shifted(eps, i=i, leaf=leaf):
                new = np.array(leaf, dtype=np.float64)
                new.flat[i] += eps
                c = jax.tree.unflatten(
                    treedef, [jnp.asarray(new) if x is leaf else x for x in leaves]
                )
                return float(loss(c))

            fd = (shifted(1e-6) - shifted(-1e-6)) / 2e-6
            assert abs(g.flat[i] - fd) <= 1e-4 * max(1.0, abs(fd)), (i, g.flat[i], fd)


@pytest.mark.parametrize("name", ["pinhole", "ptz", "omni"])
def test_project_finite_for_unprojectable_points(name):
    cam = _cameras()[name]
    pts = jnp.array(
        [
            [0.0, 0.0, 0.0],
            [0.0, 0.0, -1.0],
            [0.3, -0.2, -1.0],
            [1.0, 0.0, 0.0],
            [1e-8, 0.0, 1e-8],
            [1.0, 2.0, 1e-12],
            [0.0, 1e6, 1e-6],
            [1e8, -1e8, 3.0],
        ]
    )
    uv = _P(cam, pts)
    assert np.all(np.isfinite(np.asarray(uv)))
    J = jax.jit(jax.vmap(jax.jacfwd(cam.project)))(pts)
    assert np.all(np.isfinite(np.asarray(J)))
    b = _U(cam, jnp.array([[-1e4, 5e4], [1e6, -1e6], [0.0, 0.0]]))
    assert np.all(np.isfinite(np.asarray(b)))
    assert not bool(_call(cam, "in_view", pts[0])) and not bool(_call(cam, "projectable", pts[0]))


def test_float32_finite_for_unprojectable_points():
    cam = jax.tree.map(
        lambda x: x.astype(jnp.float32) if eqx.is_inexact_array(x) else x, _cameras()["pinhole"]
    )
    pts = jnp.array([[1.0, 2.0, 1e-30], [1e30, 1e30, 1.0], [5.0, 5.0, 0.0]], dtype=jnp.float32)
    assert np.all(np.isfinite(np.asarray(_P(cam, pts))))


# ---------------------------------------------------------------------------------------
# Pinhole in_view / projectable.
# ---------------------------------------------------------------------------------------


def test_pinhole_in_view():
    cam = PinholeCamera(500.0, 500.0, 319.5, 239.5)
    p = jnp.array(
        [
            [0.0, 0.0, 1.0],  # centre
            [0.0, 0.0, -1.0],  # behind
            [319.5 / 500.0 * 0.999, 0.0, 1.0],  # just inside the right edge
            [320.5 / 500.0, 0.0, 1.0],  # just outside
            [0.0, -239.0 / 500.0, 1.0],  # top edge, inside
            [0.0, 241.0 / 500.0, 1.0],  # below the bottom
        ]
    )
    np.testing.assert_array_equal(_call(cam, "in_view", p), [True, False, True, False, True, False])
    np.testing.assert_array_equal(
        _call(cam, "projectable", p), [True, False, True, True, True, True]
    )


def test_pinhole_in_view_rejects_folded_distortion():
    # Strong barrel distortion: the radial map r_d(r) = r (1 + k1 r^2) peaks at
    # r = 1/sqrt(-3 k1) and folds back; far-off points land inside the image again.
    cam = PinholeCamera(300.0, 300.0, 319.5, 239.5, dist=(-0.3, 0.0, 0.0, 0.0, 0.0))
    far = jnp.array([2.2, 0.0, 1.0])  # r_d = 2.2 (1 - 0.3 * 4.84) < 0: lands left of centre
    u = float(_P(cam, far)[0])
    assert -0.5 < u < 319.5
    assert not bool(_call(cam, "in_view", far))
    assert bool(_call(cam, "in_view", jnp.array([0.5, 0.0, 1.0])))


# ---------------------------------------------------------------------------------------
# PTZ.
# ---------------------------------------------------------------------------------------


def test_ptz_pan_sign():
    cam = PTZCamera(pan=math.radians(10.0))
    uv = _P(cam, jnp.array([0.0, 0.0, 5.0]))  # straight ahead in the base frame
    cx, cy = 319.5, 239.5
    assert float(uv[0]) < cx - 1.0  # camera turned right: the point is left of centre
    np.testing.assert_allclose(uv[1], cy, atol=1e-9)
    # The optical axis at pan = +10 deg points toward +x (right) in the base frame.
    axis = _U(cam, jnp.array([cx, cy]))
    np.testing.assert_allclose(
        axis, [math.sin(math.radians(10)), 0.0, math.cos(math.radians(10))], atol=1e-12
    )
    f = float(cam.focal_length())
    np.testing.assert_allclose(uv[0], cx - f * math.tan(math.radians(10.0)), atol=1e-9)


def test_ptz_tilt_sign():
    cam = PTZCamera(tilt=math.radians(10.0))
    uv = _P(cam, jnp.array([0.0, 0.0, 5.0]))
    assert float(uv[1]) > 239.5 + 1.0  # camera turned up: a point straight ahead is low
    np.testing.assert_allclose(uv[0], 319.5, atol=1e-9)
    axis = _U(cam, jnp.array([319.5, 239.5]))
    np.testing.assert_allclose(
        axis, [0.0, -math.sin(math.radians(10)), math.cos(math.radians(10))], atol=1e-12
    )


def test_ptz_rotation_and_pinhole_agree():
    cam = PTZCamera(pan=0.4, tilt=-0.3, zoom=0.6, dist=(-0.05, 0.01, 0.0, 0.0, 0.0))
    R = cam.optical_rotation()
    Ry = jnp.array(
        [[math.cos(0.4), 0, math.sin(0.4)], [0, 1, 0], [-math.sin(0.4), 0, math.cos(0.4)]]
    )
    Rx = jnp.array(
        [[1, 0, 0], [0, math.cos(-0.3), -math.sin(-0.3)], [0, math.sin(-0.3), math.cos(-0.3)]]
    )
    np.testing.assert_allclose(R.as_matrix(), Ry @ Rx, atol=1e-12)
    p = jnp.asarray(_points_in_view(cam, 10))
    p_opt = jax.vmap(R.inverse().apply)(p)
    np.testing.assert_allclose(_P(cam, p), cam.pinhole().project(p_opt), atol=1e-9)
    np.testing.assert_allclose(_call(cam, "in_view", p), cam.pinhole().in_view(p_opt))


def test_ptz_zoom_focal_length():
    w = 640
    f_wide = (w / 2) / math.tan(math.radians(42.5))
    f_tele = (w / 2) / math.tan(math.radians(7.5))
    for z in (0.0, 0.25, 1.0):
        cam = PTZCamera(zoom=z)
        np.testing.assert_allclose(cam.focal_length(), f_wide + z * (f_tele - f_wide))
        pin = cam.pinhole()
        np.testing.assert_allclose([pin.cx, pin.cy], [319.5, 239.5])
        np.testing.assert_allclose(pin.fx, pin.fy)
    # Gradient reaches zoom and the FOV leaves.
    g = eqx.filter_grad(lambda c: c.project(jnp.array([0.3, 0.1, 2.0]))[0])(PTZCamera(zoom=0.5))
    assert float(g.zoom) != 0.0 and float(g.hfov_wide) != 0.0 and float(g.hfov_tele) != 0.0
    assert float(g.pan) != 0.0


# ---------------------------------------------------------------------------------------
# Omni.
# ---------------------------------------------------------------------------------------


def _omni_reference(p, xi, fx, fy, cx, cy, s, k1, k2, p1, p2):
    """Independent NumPy implementation of the unified model (Mei 2007, OpenCV omnidir)."""
    p = np.asarray(p, dtype=np.float64)
    xs = p / np.linalg.norm(p, axis=-1, keepdims=True)
    mx = xs[..., 0] / (xs[..., 2] + xi)
    my = xs[..., 1] / (xs[..., 2] + xi)
    r2 = mx**2 + my**2
    rad = 1 + k1 * r2 + k2 * r2**2
    mxd = mx * rad + 2 * p1 * mx * my + p2 * (r2 + 2 * mx**2)
    myd = my * rad + p1 * (r2 + 2 * my**2) + 2 * p2 * mx * my
    return np.stack([fx * mxd + s * myd + cx, fy * myd + cy], axis=-1)


def test_omni_matches_reference_implementation():
    args = dict(
        xi=0.9, fx=180.0, fy=182.0, cx=320.0, cy=240.0, s=0.5, k1=-0.02, k2=0.003, p1=1e-3, p2=-1e-3
    )
    cam = _cameras()["omni"]
    p = _points_in_view(cam, 100)
    np.testing.assert_allclose(_P(cam, p), _omni_reference(p, **args), atol=1e-10, rtol=0)


def test_omni_xi0_is_pinhole():
    dist = (-0.1, 0.02, 1e-3, -2e-3)
    omni = OmniCamera(
        0.0, 500.0, 510.0, 320.0, 240.0, dist=dist, elevation_min=-1.5, elevation_max=1.5
    )
    pin = PinholeCamera(500.0, 510.0, 320.0, 240.0, dist=(*dist, 0.0))
    rng = np.random.default_rng(3)
    p = rng.uniform([-1.0, -1.0, 1.0], [1.0, 1.0, 4.0], size=(200, 3))
    np.testing.assert_allclose(_P(omni, p), _P(pin, p), atol=1e-9, rtol=0)
    uv = _image_grid(640, 480, step=20.0)
    np.testing.assert_allclose(_U(omni, uv), _U(pin, uv), atol=1e-12)
    np.testing.assert_array_equal(_call(omni, "projectable", p), _call(pin, "projectable", p))
    behind = jnp.array([0.1, 0.2, -1.0])
    assert not bool(_call(omni, "projectable", behind))


def test_omni_xi1_parabolic_radius():
    # xi = 1: r = sin t / (cos t + 1) = tan(t / 2), t the angle from +z.
    f = 150.0
    cam = OmniCamera(1.0, f, f, 319.5, 239.5, elevation_min=-1.5, elevation_max=1.5)
    t = np.linspace(0.0, math.radians(170.0), 35)
    az = np.linspace(0.0, 2 * math.pi, 35)
    p = 3.0 * np.stack([np.sin(t) * np.cos(az), np.sin(t) * np.sin(az), np.cos(t)], axis=-1)
    uv = np.asarray(_P(cam, p))
    r = np.hypot(uv[:, 0] - 319.5, uv[:, 1] - 239.5)
    np.testing.assert_allclose(r, f * np.tan(t / 2), atol=1e-9, rtol=1e-12)
    d_az = np.angle(np.exp(1j * (np.arctan2(uv[:, 1] - 239.5, uv[:, 0] - 319.5) - az)))
    np.testing.assert_allclose(d_az[t > 0], 0.0, atol=1e-9)
    # xi = 1: everything but the -z axis is projectable.
    np.testing.assert_array_equal(_call(cam, "projectable", p), True)
    assert not bool(_call(cam, "projectable", jnp.array([0.0, 0.0, -2.0])))


def test_omni_validity_xi_above_one():
    # xi = 2: projectable iff z_s > -1/xi = -0.5.
    cam = OmniCamera(2.0, 200.0, 200.0, 320.0, 240.0, elevation_min=-1.5, elevation_max=1.5)
    e = np.radians([-29.0, -31.0])  # z_s = sin(e): -0.485 (ok), -0.515 (not)
    p = np.stack([np.cos(e), 0 * e, np.sin(e)], axis=-1)
    np.testing.assert_array_equal(_call(cam, "projectable", p), [True, False])
    # Round trip holds inside the domain.
    p_in = np.array([[np.cos(-0.4), 0.3, np.sin(-0.4)], [0.2, -0.5, 0.9]])
    p_in /= np.linalg.norm(p_in, axis=-1, keepdims=True)
    np.testing.assert_allclose(_U(cam, _P(cam, p_in)), p_in, atol=1e-12)


def test_omni_elevation_band():
    cam = OmniCamera(1.0, 185.0, 185.0, 319.5, 239.5)  # default band [-12, 32] deg
    elev = np.radians([-13.0, -11.9, 0.0, 31.9, 32.1, 80.0])
    az = np.radians([0.0, 45.0, 90.0, 180.0, 270.0, 10.0])
    p = 2.0 * np.stack(
        [np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)], axis=-1
    )
    np.testing.assert_allclose(cam.elevation(p), elev, atol=1e-12)
    np.testing.assert_array_equal(_call(cam, "in_view", p), [False, True, True, True, False, False])
    np.testing.assert_array_equal(_call(cam, "projectable", p), True)
    # A narrow focal length pushes the band outside the image: in_view turns false.
    big = OmniCamera(1.0, 400.0, 400.0, 319.5, 239.5)
    assert not bool(_call(big, "in_view", p[1]))  # -11.9 deg lands at r = 494 px


def test_omni_gradient_finite_on_axis_and_band():
    cam = _cameras()["omni"]
    for p in ([0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.2]):
        J = jax.jacfwd(cam.project)(jnp.array(p))
        assert np.all(np.isfinite(np.asarray(J)))
    g = jax.grad(lambda p: cam.elevation(p))(jnp.array([0.0, 0.0, 1.0]))
    assert np.all(np.isfinite(np.asarray(g)))


def test_omni_from_opencv_and_kalibr():
    K = np.array([[180.0, 0.5, 320.0], [0.0, 182.0, 240.0], [0.0, 0.0, 1.0]])
    D = np.array([[-0.02, 0.003, 1e-3, -1e-3]])
    cam = OmniCamera.from_opencv(K, D, np.array([[0.9]]), (640, 480))
    ref = _cameras()["omni"]
    assert eqx.tree_equal(cam, ref, rtol=0, atol=0)
    cam2 = OmniCamera.from_kalibr([0.9, 180.0, 182.0, 320.0, 240.0], D[0], [640, 480])
    p = _points_in_view(ref, 5)
    np.testing.assert_allclose(
        _P(cam2, p), _omni_reference(p, 0.9, 180.0, 182.0, 320.0, 240.0, 0.0, *D[0])
    )


# ---------------------------------------------------------------------------------------
# Constructors.
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "make, match",
    [
        (
            lambda: PinholeCamera(-3.0, 500.0, 320.0, 240.0),
            r"`PinholeCamera\(fx=...\)` must be positive; got -3.0",
        ),
        (
            lambda: PinholeCamera(500.0, 0.0, 320.0, 240.0),
            r"`PinholeCamera\(fy=...\)` must be positive; got 0.0",
        ),
        (
            lambda: PinholeCamera(500.0, 500.0, float("nan"), 240.0),
            r"`PinholeCamera\(cx=...\)` must be finite; got nan",
        ),
        (
            lambda: PinholeCamera(500.0, 500.0, 320.0, float("inf")),
            r"`PinholeCamera\(cy=...\)` must be finite",
        ),
        (
            lambda: PinholeCamera(500.0, 500.0, 320.0, 240.0, dist=(0.1, 0.0, 0.0)),
            r"`PinholeCamera\(dist=...\)` must have shape \(5,\)",
        ),
        (
            lambda: PinholeCamera(500.0, 500.0, 320.0, 240.0, dist=(0.1, np.nan, 0, 0, 0)),
            r"`PinholeCamera\(dist=...\)` must be finite",
        ),
        (
            lambda: PinholeCamera(500.0, 500.0, 320.0, 240.0, image_size=(0, 480)),
            r"`PinholeCamera\(image_size=...\)`",
        ),
        (
            lambda: PinholeCamera(500.0, 500.0, 320.0, 240.0, image_size=(640,)),
            r"`PinholeCamera\(image_size=...\)`",
        ),
        (
            lambda: PinholeCamera(500.0, 500.0, 320.0, 240.0, image_size=(640.5, 480)),
            r"`PinholeCamera\(image_size=...\)`",
        ),
        (lambda: PTZCamera(zoom=1.5), r"`PTZCamera\(zoom=...\)` must lie in \[0, 1\]; got 1.5"),
        (lambda: PTZCamera(zoom=-0.1), r"`PTZCamera\(zoom=...\)`"),
        (lambda: PTZCamera(pan=float("nan")), r"`PTZCamera\(pan=...\)` must be finite"),
        (lambda: PTZCamera(hfov_wide=-1.0), r"`PTZCamera\(hfov_wide=...\)` must be positive"),
        (lambda: PTZCamera(hfov_tele=4.0), r"`PTZCamera\(hfov_tele=...\)` must be below pi"),
        (lambda: PTZCamera(dist=np.zeros(4)), r"`PTZCamera\(dist=...\)` must have shape \(5,\)"),
        (lambda: PTZCamera(image_size=(640, -1)), r"`PTZCamera\(image_size=...\)`"),
        (
            lambda: OmniCamera(-0.5, 180.0, 180.0, 320.0, 240.0),
            r"`OmniCamera\(xi=...\)` must be non-negative; got -0.5",
        ),
        (
            lambda: OmniCamera(1.0, -180.0, 180.0, 320.0, 240.0),
            r"`OmniCamera\(fx=...\)` must be positive",
        ),
        (
            lambda: OmniCamera(1.0, 180.0, 180.0, 320.0, 240.0, skew=np.inf),
            r"`OmniCamera\(skew=...\)` must be finite",
        ),
        (
            lambda: OmniCamera(1.0, 180.0, 180.0, 320.0, 240.0, dist=np.zeros(5)),
            r"`OmniCamera\(dist=...\)` must have shape \(4,\)",
        ),
        (
            lambda: OmniCamera(
                1.0, 180.0, 180.0, 320.0, 240.0, elevation_min=0.5, elevation_max=0.5
            ),
            r"`OmniCamera\(elevation_min=...\)` must be below `elevation_max`",
        ),
        (
            lambda: OmniCamera(1.0, 180.0, 180.0, 320.0, 240.0, elevation_max=2.0),
            r"`OmniCamera\(elevation_max=...\)` must lie in",
        ),
    ],
)
def test_constructor_rejects_bad_values(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_constructor_under_jit_skips_checks():
    # Leaves are tracers: no concrete check, no error.
    f = jax.jit(lambda fx: PinholeCamera(fx, fx, 320.0, 240.0).project(jnp.array([0.1, 0.2, 1.0])))
    np.testing.assert_allclose(f(500.0), [370.0, 340.0])
    g = jax.grad(lambda z: PTZCamera(zoom=z).project(jnp.array([0.1, 0.2, 1.0]))[0])(0.3)
    assert np.isfinite(float(g)) and float(g) > 0


def test_project_shape_errors():
    cam = PinholeCamera(500.0, 500.0, 320.0, 240.0)
    with pytest.raises(ValueError, match="`points_cam`"):
        _P(cam, jnp.zeros((4, 2)))
    with pytest.raises(ValueError, match="`pixels`"):
        _U(cam, jnp.zeros((4, 3)))


# ---------------------------------------------------------------------------------------
# Property tests.
# ---------------------------------------------------------------------------------------

_unit = st.floats(0.0, 1.0, allow_nan=False)


@settings(deadline=None, max_examples=50)
@given(u=_unit, v=_unit, depth=st.floats(0.1, 100.0))
def test_property_pinhole_round_trip(u, v, depth):
    cam = _left_camera()[0]
    uv = jnp.array([-0.5 + 640.0 * u, -0.5 + 480.0 * v])
    p = depth * _U(cam, uv)
    # Pixels on the outer edge of the image may round either way.
    if 1e-6 < u < 1.0 - 1e-6 and 1e-6 < v < 1.0 - 1e-6:
        assert bool(_call(cam, "in_view", p))
    np.testing.assert_allclose(_P(cam, p), uv, atol=1e-8)


@settings(deadline=None, max_examples=50)
@given(
    az=st.floats(-math.pi, math.pi),
    el=st.floats(-math.radians(12.0), math.radians(32.0)),
    xi=st.floats(0.8, 3.0),
    distorted=st.booleans(),
)
def test_property_omni_round_trip(az, el, xi, distorted):
    # With distortion, xi >= 0.8 keeps the band at normalized radius <= 1.6 (a realistic
    # range for a polynomial distortion model); without, xi down to 0.3 (radius <= 11).
    if not distorted:
        xi = 0.3 + (xi - 0.8) * (2.7 / 2.2)
    p = jnp.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    b = _omni_round_trip(p, xi, 1.0 if distorted else 0.0)
    np.testing.assert_allclose(b, p, atol=1e-9)


@jax.jit
def _omni_round_trip(p, xi, scale):
    dist = scale * jnp.array([-0.02, 0.003, 1e-3, -1e-3])
    cam = OmniCamera(xi, 180.0, 182.0, 320.0, 240.0, skew=0.5, dist=dist)
    return _U(cam, _P(cam, p))
