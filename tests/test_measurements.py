"""The measurement model's chain-rule Jacobian and its normal equations
(jaxloc._model.measurements) against forward-mode differentiation of the residuals."""

import jax
import jax.numpy as jnp
import jax.random as jr
import jaxloc
import numpy as np
import pytest
from jaxloc._model.covariance import estimate_placements
from jaxloc._model.measurements import (
    cycle_data,
    normal_equations,
    residual_poses,
    unpack,
    whitened,
    whitened_blocks,
    whitened_with_jacobian,
)


def _setup(strategy, offsets):
    scenario = jaxloc.Scenario.paper(strategy)
    rig = scenario.rig
    if offsets:
        rig = jaxloc.Rig(
            rig.overhead, rig.ptz, rig.omni2, rig.omni3,
            mounts=rig.mounts.at[1:, 4:].add(jnp.array([0.05, -0.03, 0.02])),
            markers=rig.markers.at[1:].add(jnp.array([0.02, 0.04, -0.01])),
            pixel_sigma=rig.pixel_sigma, noise_model=rig.noise_model,
        )  # fmt: skip
        scenario = jaxloc.Scenario.paper(strategy, rig=rig)
    truth, obs, _ = jax.jit(jaxloc.simulate_cycle)(scenario, jr.key(1))
    T_place, T_over = estimate_placements(truth.poses, strategy)
    # Away from the truth, so that residuals and their products are not zero.
    theta = 0.01 * jr.normal(jr.key(2), (6 * T_place.shape[0],), T_place.dtype)
    T_place, T_over = unpack(theta, T_place, T_over)
    return rig, cycle_data(obs, rig), T_place, T_over


@pytest.mark.parametrize("strategy", ["sequential", "concurrent"])
@pytest.mark.parametrize("offsets", [False, True])
def test_normal_equations_are_those_of_forward_mode(strategy, offsets):
    rig, data, T_place, T_over = _setup(strategy, offsets)
    n = 6 * T_place.shape[0]

    def residuals(theta):
        return whitened(*unpack(theta, T_place, T_over), data, rig, strategy)

    zero = jnp.zeros(n, T_place.dtype)
    r = residuals(zero)
    J = jax.jacfwd(residuals)(zero)
    assert r.shape[0] == residual_poses(strategy).shape[0]
    cost, H, g = jax.jit(normal_equations, static_argnums=4)(T_place, T_over, data, rig, strategy)
    scale = np.max(np.abs(J.T @ J))
    np.testing.assert_allclose(cost, r @ r, rtol=1e-12)
    np.testing.assert_allclose(H, J.T @ J, atol=1e-10 * scale)
    np.testing.assert_allclose(g, J.T @ r, atol=1e-10 * np.max(np.abs(J.T @ r)))
    r_blocks, B = whitened_blocks(T_place, T_over, data, rig, strategy)
    np.testing.assert_allclose(r_blocks, r, atol=1e-12)
    # Every row depends on its two poses only.
    _, J_dense = whitened_with_jacobian(T_place, T_over, data, rig, strategy)
    poses = residual_poses(strategy)
    other = np.ones(J_dense.shape[:2], bool)
    other[np.arange(len(poses))[:, None], poses] = False
    assert np.all(np.asarray(J_dense)[other] == 0.0)


def test_normal_equations_float32():
    rig, data, T_place, T_over = _setup("sequential", False)
    f32 = jax.tree.map(
        lambda a: a.astype(jnp.float32) if a.dtype == jnp.float64 else a, (T_place, T_over, data)
    )
    cost, H, g = normal_equations(*f32, rig, "sequential")
    assert cost.dtype == H.dtype == g.dtype == jnp.float32
    cost64, H64, _ = normal_equations(T_place, T_over, data, rig, "sequential")
    np.testing.assert_allclose(H, H64, rtol=1e-3, atol=1e-3 * float(jnp.max(jnp.abs(H64))))
