import math

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from jaxloc._sim.world import (
    body_pose_on_surface,
    FlatSurface,
    formation_xy,
    FunctionSurface,
    SaddleSurface,
    SinusoidSurface,
)


SURFACES = [
    SaddleSurface(),
    SaddleSurface(radius_x=3.0, radius_y=-5.0, height=0.2),
    FlatSurface(0.7),
    SinusoidSurface(),
    SinusoidSurface(height=2.9, amplitude=0.4, period=4.0, phase=1.1),
    FunctionSurface(lambda x, y: 0.1 * jnp.sin(x) * jnp.cos(2.0 * y) + 0.05 * x * y),
]


def test_saddle_principal_curvatures():
    s = SaddleSurface(radius_x=-8.0, radius_y=8.0)
    H = jax.hessian(lambda p: s.height(p))(jnp.zeros(2))
    # Gradient vanishes at the origin, so the Hessian is the shape operator there.
    np.testing.assert_allclose(s.gradient(jnp.zeros(2)), 0.0, atol=0)
    np.testing.assert_allclose(np.linalg.eigvalsh(H), [-1 / 8, 1 / 8], atol=1e-15)
    np.testing.assert_allclose(H, [[-1 / 8, 0], [0, 1 / 8]], atol=1e-15)
    # C1 (apex, at -x) is below the base's middle; C2, C3 (at +-y) are above it.
    xy = formation_xy(2.0, 1.5)
    z = s.height(xy)
    assert z[0] < 0.0 < z[1] and z[1] == z[2]


@pytest.mark.parametrize("surface", SURFACES)
def test_gradient_matches_autodiff_and_normals(surface):
    xy = jax.random.uniform(jax.random.key(0), (4, 5, 2), minval=-3.0, maxval=3.0)
    g_ad = jnp.vectorize(jax.grad(lambda p: surface.height(p)), signature="(2)->(2)")(xy)
    np.testing.assert_allclose(surface.gradient(xy), g_ad, rtol=1e-12, atol=1e-14)
    assert surface.height(xy).shape == (4, 5)
    p = surface.point(xy)
    assert p.shape == (4, 5, 3)
    np.testing.assert_array_equal(p[..., :2], xy)
    n = surface.normal(xy)
    np.testing.assert_allclose(jnp.linalg.norm(n, axis=-1), 1.0, atol=1e-14)
    assert jnp.all(n[..., 2] > 0)
    # Tangent vectors by autodiff of the point map are perpendicular to the normal.
    J = jnp.vectorize(jax.jacfwd(lambda q: surface.point(q)), signature="(2)->(3,2)")(xy)
    np.testing.assert_allclose(jnp.einsum("...i,...ij->...j", n, J), 0.0, atol=1e-14)


def test_sinusoid_ceiling_crest_over_origin():
    c = SinusoidSurface(height=3.5, amplitude=0.25, period=10.0)
    np.testing.assert_allclose(c.height(jnp.zeros(2)), 3.5)
    np.testing.assert_allclose(c.gradient(jnp.zeros(2)), 0.0, atol=1e-15)
    np.testing.assert_allclose(c.height(jnp.array([5.0, 1.0])), 3.0, atol=1e-14)
    np.testing.assert_allclose(c.height(jnp.array([10.0, -2.0])), 3.5, atol=1e-14)
    # Constant along y.
    np.testing.assert_allclose(c.height(jnp.array([1.3, 7.0])), c.height(jnp.array([1.3, 0.0])))


@pytest.mark.parametrize("surface", SURFACES)
def test_body_frames(surface):
    xy = jax.random.uniform(jax.random.key(1), (7, 2), minval=-2.0, maxval=2.0)
    heading = jax.random.uniform(jax.random.key(2), (7,), minval=-math.pi, maxval=math.pi)
    T = jax.vmap(lambda p, h: body_pose_on_surface(surface, p, h))(xy, heading)
    R = T.rotation().as_matrix()
    np.testing.assert_allclose(R @ jnp.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-14)
    np.testing.assert_allclose(jnp.linalg.det(R), 1.0, atol=1e-14)
    np.testing.assert_allclose(R[..., 2], surface.normal(xy), atol=1e-14)
    np.testing.assert_allclose(T.translation(), surface.point(xy), atol=1e-14)
    # Body x is the heading projected into the tangent plane: its horizontal part points
    # along the heading.
    x = R[..., 0]
    np.testing.assert_allclose(jnp.arctan2(x[:, 1], x[:, 0]), heading, atol=1e-12)


def test_flat_body_frame_is_yaw():
    T = body_pose_on_surface(FlatSurface(0.0), jnp.array([1.0, 2.0]), 0.3)
    expected = jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.from_z_radians(0.3), jnp.array([1.0, 2.0, 0.0])
    )
    np.testing.assert_allclose(T.as_matrix(), expected.as_matrix(), atol=1e-15)


def test_body_pose_rejects_batches():
    with pytest.raises(ValueError, match="one robot"):
        body_pose_on_surface(FlatSurface(), jnp.zeros((3, 2)), 0.0)


def test_paper_formation():
    xy = formation_xy(2.0, 1.5)
    np.testing.assert_allclose(xy[0], [-math.sqrt(1.5**2 - 1.0), 0.0])
    np.testing.assert_allclose(xy[0, 0], -1.118, atol=5e-4)
    d = jnp.linalg.norm(xy[:, None] - xy[None], axis=-1)
    np.testing.assert_allclose([d[1, 2], d[0, 1], d[0, 2]], [2.0, 1.5, 1.5], atol=1e-14)
    # On the saddle the 3D distances differ from the planar ones by well under 1 cm.
    p = SaddleSurface().point(xy)
    d3 = jnp.linalg.norm(p[:, None] - p[None], axis=-1)
    np.testing.assert_allclose(d3, d, atol=1e-2)
    # The overhead camera at the origin of the ceiling is 3.5 m above the ground under it.
    np.testing.assert_allclose(
        SinusoidSurface().height(jnp.zeros(2)) - SaddleSurface().height(jnp.zeros(2)), 3.5
    )


def test_float32():
    s = SaddleSurface(jnp.float32(-8.0), jnp.float32(8.0), jnp.float32(0.0))
    xy = jnp.asarray(formation_xy(2.0, 1.5), jnp.float32)
    T = jax.vmap(lambda p: body_pose_on_surface(s, p, jnp.float32(0.0)))(xy)
    assert T.wxyz_xyz.dtype == jnp.float32
    assert s.normal(xy).dtype == jnp.float32
