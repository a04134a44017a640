"""The Rig (jaxloc._cycle.rig): the team's cameras exactly as calibrated, their mounts, the
markers and the pixel noise, entering the simulator, the refinement and the bound alike.

The statistical test refines cycles seen by strongly distorted cameras, with cameras and
markers away from the body origins, and reaches the Cramér–Rao bound computed with that
same rig (issue 18): at 5ebd322 the refinement could only see an approximate, undistorted
PTZ camera."""

import functools as ft

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import jaxloc
import numpy as np
import pytest
from jaxloc._cycle.rig import mount_pose
from jaxloc._study.robustness import final_positions


def test_paper_rig_is_the_scenarios():
    rig = jaxloc.Rig.paper()
    assert eqx.tree_equal(rig, jaxloc.Scenario.paper().rig)
    np.testing.assert_allclose(rig.mount_rotations()[1], jaxloc.R_BODY_PTZ, atol=1e-15)
    np.testing.assert_allclose(rig.mount_translations(), 0.0)
    np.testing.assert_allclose(rig.sigma_per_axis(), 2.0 / np.sqrt(2.0))
    assert not rig.has_offsets


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"noise_model": "laplace"}, r"`Rig\(noise_model=...\)` must be one of"),
        ({"pixel_sigma": -1.0}, r"`Rig\(pixel_sigma=...\)` must be non-negative"),
        ({"pixel_sigma": [1.0, 2.0]}, r"`Rig\(pixel_sigma=...\)` must have shape \(4,\)"),
        ({"markers": np.full((4, 3), np.nan)}, r"`Rig\(markers=...\)` must be finite"),
        ({"mounts": np.zeros((4, 7))}, r"`Rig\(mounts=...\)` must hold unit quaternions"),
    ],
)
def test_bad_rig_names_the_field(kwargs, match):
    cams = jaxloc.Rig.paper().cameras
    with pytest.raises(ValueError, match=match):
        jaxloc.Rig(*cams, **kwargs)


def test_rig_needs_cameras():
    cams = list(jaxloc.Rig.paper().cameras)
    cams[2] = "omni"
    with pytest.raises(ValueError, match=r"`Rig\(omni2=...\)` must be a camera model"):
        jaxloc.Rig(*cams)


def _distorted_rig(offsets: bool) -> jaxloc.Rig:
    """C1 a calibrated pinhole with strong barrel distortion and an off-centre principal
    point (the head's pan and tilt in the mount), C2 and C3 omnidirectional cameras with
    distortion; with `offsets`, every camera 5-30 cm from its body origin and every
    marker 10-25 cm above it."""
    ptz = jaxloc.PinholeCamera(
        349.2, 352.0, 331.0, 244.0, dist=(-0.22, 0.07, 0.002, -0.001, -0.008)
    )
    omni = jaxloc.OmniCamera(1.0, 185.0, 186.5, 321.0, 238.0, dist=(-0.08, 0.02, 0.001, 0.0005))
    rig = jaxloc.Rig(jaxloc.paper_overhead_camera(), ptz, omni, omni, pixel_sigma=1.0)
    if not offsets:
        return rig
    t = jnp.array([[0.0, 0.0, -0.05], [0.12, 0.0, 0.30], [0.0, 0.05, 0.25], [-0.04, 0.0, 0.28]])
    markers = jnp.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.10], [0.05, 0.0, 0.25], [0.0, -0.03, 0.2]])
    mounts = jnp.stack([mount_pose(R, t_) for R, t_ in zip(rig.mount_rotations(), t)])
    return eqx.tree_at(lambda r: (r.mounts, r.markers), rig, (mounts, markers))


@ft.partial(jax.jit, static_argnames="strategy")
def _study(rig, keys, strategy):
    scenario = jaxloc.Scenario.paper(strategy, rig=rig)

    def one(key):
        truth, obs, visible = jaxloc.simulate_cycle(scenario, key)
        closed = jaxloc.localize_cycle(obs, rig, throw=False)
        refined = jaxloc.refine_cycle(obs, rig, closed, throw=False)
        bound = jaxloc.cycle_crlb(
            rig, truth.poses, odometry_sigma_rel=scenario.odometry_sigma_rel
        )
        c = refined.poses.T_world_overhead.translation()
        e = c - truth.poses.T_world_overhead.translation()
        return visible, refined.result._value, jnp.sum(e * e), jnp.trace(bound.position[0])

    return jax.vmap(one)(keys)


@pytest.mark.parametrize("offsets", [False, True])
def test_refinement_with_distorted_cameras_reaches_the_bound_of_the_same_rig(offsets):
    rig = _distorted_rig(offsets)
    out = _study(rig, jr.split(jr.key(7), 384), "sequential")
    visible, result, sq, bound = map(np.asarray, out)
    assert visible.mean() > 0.8
    ok = visible & (result == 0)
    assert ok.sum() > 0.95 * visible.sum()
    efficiency = np.sqrt(bound[ok].mean() / sq[ok].mean())
    # 384 trials: the RMSE is known to ~4% (one standard deviation).
    assert 0.85 < efficiency < 1.15, efficiency


@ft.partial(jax.jit, static_argnames="strategy")
def _noiseless_with_offsets(rig, strategy, keys):
    scenario = jaxloc.Scenario.paper(strategy, rig=rig, odometry_sigma_rel=1e-9)

    def one(key):
        truth, obs, visible = jaxloc.simulate_cycle(scenario, key)
        closed = jaxloc.localize_cycle(obs, rig, throw=False)
        refined = jaxloc.refine_cycle(obs, rig, closed, throw=False)
        true_pos = final_positions(truth.poses)
        errors = [
            jnp.max(jnp.abs(final_positions(e.poses) - true_pos)) for e in (closed, refined)
        ]
        sq = jnp.sum((final_positions(closed.poses) - true_pos) ** 2, axis=-1)
        var = jnp.trace(closed.covariance.position, axis1=-2, axis2=-1)
        return visible, closed.result._value, refined.result._value, *errors, sq, var

    return jax.vmap(one)(keys)


@pytest.mark.parametrize("strategy", ["sequential", "concurrent"])
def test_offsets_exact_on_noiseless_data(strategy):
    """Issue 20.3: cameras 5-30 cm from their body origins and markers 10-25 cm above
    them. The closed forms take every camera centre and marker at the body origin (the
    paper's model; a few centimetres off here), flagged by their gates or carrying that
    offset in their covariance; the refinement models the offsets exactly and recovers
    the poses of noise-free data to 1e-8 m."""
    rig = _distorted_rig(True)
    rig = eqx.tree_at(lambda r: r.pixel_sigma, rig, jnp.zeros(4))
    visible, closed, refined, e_closed, e_refined, sq, var = map(
        np.asarray, _noiseless_with_offsets(rig, strategy, jr.split(jr.key(5), 8))
    )
    assert visible.sum() >= 6
    refined_ok = visible & (refined == 0)
    # (Concurrent, seed 5: one of the 7 visible cycles ends `inconsistent_fit`: started
    # from the closed form, which ignores the offsets, the refinement stays in another
    # minimum; flagged, not marked successful.)
    assert refined_ok.sum() >= visible.sum() - 1, refined
    assert np.all(e_refined[refined_ok] < 1e-8), e_refined
    assert np.all(e_closed[visible] > 1e-4)  # the closed forms do not model the offsets ...
    # ... and a successful one carries its offset from the optimum in its covariance (on
    # noise-free data the covariance is nearly rank one, so compare traces, not NEES).
    ok = visible & (closed == 0)
    assert np.all(sq[ok] <= 1.001 * var[ok] + 1e-12), (sq[ok], var[ok])
