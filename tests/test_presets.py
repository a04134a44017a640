import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from jaxloc._cameras.models import OmniCamera, PinholeCamera, PTZCamera
from jaxloc._cameras.presets import (
    field_of_view,
    paper_omni_camera,
    paper_overhead_camera,
    paper_ptz_camera,
    R_BODY_OMNI,
    R_BODY_OVERHEAD,
    R_BODY_PTZ,
)


@eqx.filter_jit
def _call(camera, method, x):
    return getattr(camera, method)(x)


def test_mount_rotations_are_proper():
    for R in (R_BODY_PTZ, R_BODY_OMNI, R_BODY_OVERHEAD):
        assert R.dtype == np.float64 and R.shape == (3, 3)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
        assert np.linalg.det(R) == pytest.approx(1.0)
    # PTZ base: optical z (forward) = body x, optical x (right) = body -y, y (down) = body -z.
    np.testing.assert_array_equal(R_BODY_PTZ @ [0, 0, 1], [1, 0, 0])
    np.testing.assert_array_equal(R_BODY_PTZ @ [1, 0, 0], [0, -1, 0])
    np.testing.assert_array_equal(R_BODY_PTZ @ [0, 1, 0], [0, 0, -1])
    # Overhead camera looks along body -z.
    np.testing.assert_array_equal(R_BODY_OVERHEAD @ [0, 0, 1], [0, 0, -1])


def test_overhead_preset():
    cam = paper_overhead_camera()
    assert isinstance(cam, PinholeCamera)
    assert cam.image_size == (640, 480)
    fov = field_of_view(cam)
    assert fov["horizontal_deg"] == pytest.approx(52.0, abs=1e-9)
    assert fov["vertical_deg"] == pytest.approx(
        2 * math.degrees(math.atan(240 * math.tan(math.radians(26)) / 320)), abs=1e-9
    )
    np.testing.assert_array_equal(cam.dist, 0.0)
    assert float(cam.fx) == float(cam.fy)
    # A point 26 deg to the right of the axis lands on the right edge of the image.
    p = jnp.array([math.tan(math.radians(26.0)), 0.0, 1.0])
    np.testing.assert_allclose(_call(cam, "project", p), [639.5, 239.5], atol=1e-9)


@pytest.mark.parametrize("zoom, hfov", [(0.0, 85.0), (1.0, 15.0)])
def test_ptz_preset_fov(zoom, hfov):
    cam = paper_ptz_camera(zoom=zoom)
    assert isinstance(cam, PTZCamera)
    assert cam.image_size == (640, 480)
    assert field_of_view(cam)["horizontal_deg"] == pytest.approx(hfov, abs=1e-9)


def test_ptz_preset_intermediate_zoom_is_between():
    fovs = [field_of_view(paper_ptz_camera(zoom=z))["horizontal_deg"] for z in (0.0, 0.3, 0.7, 1.0)]
    assert all(a > b for a, b in zip(fovs, fovs[1:]))
    cam = paper_ptz_camera(pan=0.2, tilt=-0.1, zoom=0.5)
    assert float(cam.pan) == 0.2 and float(cam.tilt) == -0.1 and float(cam.zoom) == 0.5


def test_omni_preset_band_inside_image():
    cam = paper_omni_camera()
    assert isinstance(cam, OmniCamera)
    assert cam.image_size == (640, 480)
    fov = field_of_view(cam)
    assert fov["azimuth_deg"] == 360.0
    assert fov["elevation_min_deg"] == pytest.approx(-12.0)
    assert fov["elevation_max_deg"] == pytest.approx(32.0)
    # Every direction in the band, on both band edges and all azimuths, is in view.
    az = np.linspace(-math.pi, math.pi, 721)
    for e_deg in (-12.0 + 1e-9, 0.0, 32.0 - 1e-9):
        e = math.radians(e_deg)
        p = np.stack(
            [np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.full_like(az, np.sin(e))], -1
        )
        assert bool(jnp.all(_call(cam, "in_view", jnp.asarray(p))))
        uv = np.asarray(_call(cam, "project", jnp.asarray(p)))
        r = np.hypot(uv[:, 0] - 319.5, uv[:, 1] - 239.5)
        f, xi = float(cam.fx), float(cam.xi)
        np.testing.assert_allclose(r, f * math.cos(e) / (math.sin(e) + xi), rtol=1e-12)
        # Margin: the outer (-12 deg) circle stays > 10 px inside the image.
        assert np.all(uv[:, 1] > 10.0) and np.all(uv[:, 1] < 469.0)
    # Just outside the band: not in view.
    for e_deg in (-12.5, 32.5):
        e = math.radians(e_deg)
        assert not bool(_call(cam, "in_view", jnp.array([math.cos(e), 0.0, math.sin(e)])))


def test_field_of_view_rejects_other_objects():
    with pytest.raises(ValueError, match="`camera`"):
        field_of_view("not a camera")
