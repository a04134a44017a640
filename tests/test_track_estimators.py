"""Tracking's estimators (issue 21.2-21.4): chaining, the fixed-lag smoother and one-step
localization recover the truth from near-exact data, and one-step localization says why
it fails. One jitted tracking trial and one one-step program."""

import jax
import jax.numpy as jnp
import jax.random as jr
import jaxlie
import jaxloc
import numpy as np
import pytest
from jaxloc._core.results import RESULTS, status_code
from jaxloc._track.frames import body_of_overhead, perimeter


# Past the smoother's window (2) by two cycles: the second marginalization is the first
# whose kept poses carry no gauge (a row layout out of step with the cycle's residuals
# made every smoother cycle from the fourth on `unobservable`).
CYCLES = 4


@pytest.fixture(scope="module")
def near_exact_trial():
    """Runs of `CYCLES` cycles with 1e-3 px pixel noise and 1e-5 odometry noise (the estimators'
    weights match the simulated noise, so the gates apply as usual)."""
    scenario = jaxloc.Scenario.paper(pixel_sigma=1e-3, odometry_sigma_rel=1e-5)
    track = jaxloc.TrackScenario(
        scenario, climber_odometry_sigma_rel=1e-5, climber_odometry_rotation_sigma=1e-5,
        height_prior_sigma=1e-4,  # the tilt prior keeps its default: the ceiling tilts the robot
    )  # fmt: skip
    keys = jr.split(jr.key(7), 2)
    run = jax.jit(jax.vmap(lambda k: jaxloc.run_track_trial(track, k, CYCLES)))
    return jax.tree.map(np.asarray, run(keys))


def test_chain_smoother_and_one_step_recover_the_truth(near_exact_trial):
    e = near_exact_trial
    assert e.status.shape == (2, CYCLES, len(jaxloc.TRACK_METHODS))
    ok = e.status == 0
    assert ok[:, :, :2].all(), e.status  # chaining and the smoother succeed everywhere
    # Every robot at the end of every cycle, in the first cycle's frame: micrometres.
    assert np.max(e.position[:, :, :2]) < 1e-4
    assert np.max(e.rotation[:, :, :2]) < 1e-4
    # One-step: the climbing robot and the formation at the prior's scale.
    assert ok[:, :, 2].all(), e.status
    assert np.max(e.position[:, :, 2]) < 1e-3
    assert e.root_correct.all()
    # Bounds are positive (but one-step's C1: the frame's origin) and the errors within
    # a few of them.
    bound = e.bound_position_var.copy()
    assert np.all(bound[:, :, 2, 1] == 0)
    bound[:, :, 2, 1] = np.inf
    assert np.all(bound > 0) and not np.any(np.isnan(bound))
    assert np.max(e.position**2 / bound) < 100.0


def test_the_smoother_bound_is_below_the_chained_bound(near_exact_trial):
    e = near_exact_trial
    chain = e.bound_position_var[:, :, 0]  # (runs, K, robots)
    smooth = e.bound_position_var[:, :, 1]
    # The smoother uses every measurement the chain uses, and more: its bound is lower,
    # and the same for the first cycle (nothing to share yet).
    assert np.all(smooth <= chain * (1 + 1e-6))
    np.testing.assert_allclose(smooth[:, 0], chain[:, 0], rtol=1e-6)
    assert np.all(smooth[:, -1, 0] < 0.9 * chain[:, -1, 0])


@pytest.fixture(scope="module")
def cycle():
    scenario = jaxloc.Scenario.paper()
    truth, obs, feasible = jax.jit(jaxloc.simulate_cycle)(scenario, jr.key(3))
    assert bool(feasible)
    return scenario, truth, obs


def _true_body(scenario, truth):
    return body_of_overhead(truth.poses.T_world_overhead.wxyz_xyz, scenario.rig.mounts[0])


def test_one_step_with_a_pose_prior_and_the_scale(cycle):
    scenario, truth, obs = cycle
    T_body = _true_body(scenario, truth)
    cov = jnp.diag(jnp.array([0.2] * 3 + [np.radians(5.0)] * 3) ** 2)
    true_perimeter = perimeter(truth.poses.T_world_body.wxyz_xyz[0, :, 4:])
    prior = jaxloc.OneStepPrior.pose_prior(T_body, cov).with_scale(true_perimeter, 0.02)
    est = jaxloc.localize_one_step(jaxloc.Snapshot.of(obs, 0), scenario.rig, prior)
    assert est.result == RESULTS.successful
    # Every overhead sighting and prior row agrees with the rest.
    assert 0.0 < float(est.checks.worst_sighting) <= 1.0
    err = np.linalg.norm(np.asarray(est.T_world_climber[4:] - T_body[4:]))
    assert err < 0.1  # 2 px noise, one formation: centimetres
    sigma = np.sqrt(np.trace(np.asarray(est.position_covariance)))
    assert err < 5 * sigma
    # The refined root is the one nearest the truth.
    d = np.linalg.norm(np.asarray(est.roots)[:, 4:] - np.asarray(T_body)[4:], axis=-1)
    d[~np.asarray(est.roots_ok)] = np.inf
    assert int(est.chosen) == int(np.argmin(d))
    # Each root's prior misfit: finite for the valid roots, least for the chosen one.
    cost = np.asarray(est.root_cost)
    assert cost.shape == (4,)
    assert np.all(np.isfinite(cost) == np.asarray(est.roots_ok))
    assert int(est.chosen) == int(np.argmin(cost))
    # The formation at the estimated scale: C1 at the origin, C2 and C3 near the truth.
    np.testing.assert_allclose(est.T_world_body[0], jaxlie.SE3.identity().wxyz_xyz, atol=1e-9)
    true_ground = np.asarray(truth.poses.T_world_body.wxyz_xyz[0, :, 4:])
    assert np.max(np.abs(np.asarray(est.T_world_body[:, 4:]) - true_ground)) < 0.05


def test_one_step_names_a_wrong_prior_row_that_the_total_chi_square_passes():
    """A prior 4.6 sigma off along the body's z (0.92 m) on near-exact sightings: the
    total chi-square stays below its limit (that row's misfit spread over 6 degrees of
    freedom), the per-measurement test of the prior's rows does not, and the update is
    `inconsistent_fit`; the same prior at the truth is `successful`."""
    scenario = jaxloc.Scenario.paper(pixel_sigma=1e-3)
    truth, obs, feasible = jax.jit(jaxloc.simulate_cycle)(scenario, jr.key(3))
    assert bool(feasible)
    rig = jaxloc.Scenario.paper().rig  # weighs the sightings at 2 px
    T_body = _true_body(scenario, truth)
    sigma = np.array([0.2] * 3 + [np.radians(5.0)] * 3)
    true_perimeter = perimeter(truth.poses.T_world_body.wxyz_xyz[0, :, 4:])
    snap = jaxloc.Snapshot.of(obs, 0)
    for offset, expected in [(0.0, RESULTS.successful), (4.6, RESULTS.inconsistent_fit)]:
        delta = jnp.zeros(6).at[2].set(offset * sigma[2])
        T_prior = (jaxlie.SE3(T_body) @ jaxlie.SE3.exp(delta)).wxyz_xyz
        prior = jaxloc.OneStepPrior.pose_prior(T_prior, jnp.diag(jnp.asarray(sigma) ** 2))
        est = jaxloc.localize_one_step(snap, rig, prior.with_scale(true_perimeter, 0.02),
                                       throw=False)  # fmt: skip
        assert est.result == expected
        assert float(est.checks.chi2) <= float(est.checks.chi2_limit)
        assert (float(est.checks.worst_sighting) > 1.0) == (offset > 0)


def test_one_step_without_a_prior_cannot_fix_the_scale(cycle):
    scenario, truth, obs = cycle
    snap = jaxloc.Snapshot.of(obs, 0)
    est = jaxloc.localize_one_step(snap, scenario.rig, jaxloc.OneStepPrior.none(), throw=False)
    assert status_code(est.result) == status_code(RESULTS.scale_unobservable)
    with pytest.raises(Exception, match="scale"):
        jaxloc.localize_one_step(snap, scenario.rig, jaxloc.OneStepPrior.none())


def test_one_step_needs_three_overhead_sightings(cycle):
    scenario, truth, obs = cycle
    snap = jaxloc.Snapshot.of(obs, 0)
    snap = jax.tree.map(lambda a: a, snap)
    import equinox as eqx

    snap = eqx.tree_at(lambda s: s.overhead_visible, snap, snap.overhead_visible.at[1].set(False))
    T_body = _true_body(scenario, truth)
    prior = jaxloc.OneStepPrior.pose_prior(T_body, jnp.eye(6) * 0.01).with_scale(5.0, 0.05)
    est = jaxloc.localize_one_step(snap, scenario.rig, prior, throw=False)
    assert status_code(est.result) == status_code(RESULTS.too_few_points)


def test_one_step_rejects_bad_arguments(cycle):
    scenario, truth, obs = cycle
    snap = jaxloc.Snapshot.of(obs, 0)
    with pytest.raises(ValueError, match="`rig`"):
        jaxloc.localize_one_step(snap, scenario, jaxloc.OneStepPrior.none())
    with pytest.raises(ValueError, match="`prior`"):
        jaxloc.localize_one_step(snap, scenario.rig, None)
    with pytest.raises(ValueError, match="pose_prior"):
        jaxloc.OneStepPrior.pose_prior(jnp.zeros(6), jnp.eye(6))
