import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import jaxloc
import numpy as np
import pytest
from helpers import (
    all_seeing_rig,
    cycle_poses,
    exact_arrays,
    exact_observations,
    random_cycle_truth,
)
from jaxloc._cycle.observations import CycleObservations
from jaxloc._solvers.localize import localize_cycle, localize_cycle_methods


RIG = all_seeing_rig()


BATCH = 64  # one batch size for every batched test: one compilation per strategy


@jax.jit
def _solve_batch(obs):
    return jax.vmap(lambda o: localize_cycle_methods(o, RIG, ("robust", "paper")))(obs)


@jax.jit
def _solve_one(obs):
    return localize_cycle(obs, RIG, throw=False)


def _min_angle(ts):
    angles = []
    for p in ts:
        for i in range(3):
            a, b = p[(i + 1) % 3] - p[i], p[(i + 2) % 3] - p[i]
            angles.append(np.arccos(a @ b / np.linalg.norm(a) / np.linalg.norm(b)))
    return min(angles)


def _batch(rng, strategy, n, flat):
    truths = []
    while len(truths) < n:  # keep formations away from collinear (a status test covers that)
        t = random_cycle_truth(rng, strategy, flat=flat)
        if _min_angle(t[1]) > np.deg2rad(5.0):
            truths.append(t)
    arrays = [exact_arrays(*t, strategy) for t in truths]
    mutual, overhead, odometry = (np.stack(a) for a in zip(*arrays))
    obs = CycleObservations(mutual, overhead, odometry, 0.01 * odometry, strategy)
    Rs, ts, R_c, t_c = (np.stack(a) for a in zip(*truths))
    return obs, Rs, ts, R_c, t_c


@pytest.mark.parametrize("strategy", ["sequential", "concurrent"])
@pytest.mark.parametrize("flat", [False, True])
def test_noiseless_exact_over_random_formations(strategy, flat):
    """Hundreds of formations in all: 64 per (strategy, floor) here, plus the other tests."""
    rng = np.random.default_rng(0 if flat else 1)
    obs, Rs, ts, R_c, t_c = _batch(rng, strategy, BATCH, flat)
    est, _ = _solve_batch(obs)
    assert np.all(np.asarray(est.result._value) == 0)
    pos = np.asarray(est.poses.T_world_body.translation())
    np.testing.assert_allclose(pos, ts, atol=1e-8)
    R = np.asarray(est.poses.T_world_body.rotation().as_matrix())
    np.testing.assert_allclose(R, Rs, atol=1e-8)
    cam = np.asarray(est.poses.T_world_overhead.translation())
    np.testing.assert_allclose(cam, t_c, atol=1e-8)
    Rc = np.asarray(est.poses.T_world_overhead.rotation().as_matrix())
    np.testing.assert_allclose(Rc, R_c, atol=1e-8)


@pytest.mark.parametrize("strategy", ["sequential", "concurrent"])
def test_paper_method_exact_on_curved_and_flags_flat(strategy):
    rng = np.random.default_rng(2)
    obs, _, _, _, t_c = _batch(rng, strategy, BATCH, flat=False)
    _, est = _solve_batch(obs)
    assert np.all(np.asarray(est.result._value) == 0)
    np.testing.assert_allclose(np.asarray(est.poses.T_world_overhead.translation()), t_c, atol=1e-6)
    obs, *_ = _batch(rng, strategy, BATCH, flat=True)
    _, est = _solve_batch(obs)
    codes = np.asarray(est.result._value)
    assert np.all(codes == jaxloc.status_code(jaxloc.RESULTS.rank_deficient))


@pytest.mark.parametrize("strategy", ["sequential", "concurrent"])
def test_jit_equals_eager_and_vmap_equals_loop(strategy):
    rng = np.random.default_rng(3)
    obs, *_ = _batch(rng, strategy, BATCH, flat=False)
    noisy = eqx.tree_at(
        lambda o: o.mutual, obs, obs.mutual + 1e-3 * rng.normal(size=obs.mutual.shape)
    )
    batched, _ = _solve_batch(noisy)
    for i in (0, 5):
        one = jax.tree.map(lambda x: x[i], noisy)
        jitted = _solve_one(one)
        if i == 0:  # eager (op by op) is slow: check it once
            eager = localize_cycle(one, RIG, throw=False)
        else:
            eager = jitted
        for got in (jitted, jax.tree.map(lambda x: x[i], batched)):
            np.testing.assert_allclose(
                got.poses.T_world_body.wxyz_xyz, eager.poses.T_world_body.wxyz_xyz, atol=1e-10
            )
            np.testing.assert_allclose(
                got.poses.T_world_overhead.wxyz_xyz,
                eager.poses.T_world_overhead.wxyz_xyz,
                atol=1e-10,
            )


@pytest.mark.slow
@pytest.mark.parametrize("strategy", ["sequential", "concurrent"])
def test_grad_wrt_true_positions_matches_finite_differences(strategy):
    rng = np.random.default_rng(4)
    Rs, ts, R_c, t_c = random_cycle_truth(rng, strategy)

    def overhead_height(ts):
        mutual, overhead, odometry = exact_arrays(Rs, ts, R_c, t_c, strategy, xp=jnp)
        obs = CycleObservations(mutual, overhead, odometry, 0.01 * odometry, strategy)
        est = localize_cycle(obs, RIG, throw=False)
        c = est.poses.T_world_overhead.translation()
        return c[2] + 0.3 * c[0] + jnp.sum(est.poses.T_world_body.translation()[-1] ** 2)

    ts = jnp.asarray(ts)
    g = jax.jit(jax.grad(overhead_height))(ts)
    assert np.all(np.isfinite(np.asarray(g)))
    eps = 1e-6
    value = jax.jit(overhead_height)
    for k, r, a in [(1, 1, 0), (0, 2, 1), (len(ts) - 1, 2, 2), (0, 1, 2)]:
        e = jnp.zeros_like(ts).at[k, r, a].set(eps)
        fd = (value(ts + e) - value(ts - e)) / (2 * eps)
        np.testing.assert_allclose(g[k, r, a], fd, rtol=1e-5, atol=1e-6)


def test_degenerate_inputs_give_status_not_nan():
    rng = np.random.default_rng(5)
    truth = random_cycle_truth(rng, "sequential")
    obs = exact_observations(*truth, "sequential")
    # Collinear robots at step 2: every bearing along the x axis.
    line = np.zeros((3, 3, 3))
    line[0, 1] = line[0, 2] = line[2, 0] = line[2, 1] = [1.0, 0, 0]
    line[1, 0] = line[1, 2] = [-1.0, 0, 0]
    line[1, 2] = [1.0, 0, 0]
    bad = eqx.tree_at(lambda o: o.mutual, obs, obs.mutual.at[2].set(jnp.asarray(line)))
    est = localize_cycle(bad, RIG, throw=False)
    assert est.result == jaxloc.RESULTS.degenerate_configuration
    assert np.all(np.isfinite(np.asarray(est.poses.T_world_body.wxyz_xyz)))
    with pytest.raises(Exception, match="collinear"):
        localize_cycle(bad, RIG, throw=True)

    nan = eqx.tree_at(lambda o: o.overhead, obs, obs.overhead.at[1, 1, 0].set(jnp.nan))
    est = localize_cycle(nan, RIG, throw=False)
    assert est.result != jaxloc.RESULTS.successful
    assert np.all(np.isfinite(np.asarray(est.poses.T_world_overhead.wxyz_xyz)))

    nan_odo = eqx.tree_at(lambda o: o.odometry, obs, obs.odometry.at[0].set(jnp.nan))
    assert localize_cycle(nan_odo, RIG, throw=False).result == jaxloc.RESULTS.nonfinite_observation

    zero_odo = eqx.tree_at(lambda o: o.odometry, obs, jnp.zeros(3))
    assert localize_cycle(zero_odo, RIG, throw=False).result == jaxloc.RESULTS.scale_unobservable


@pytest.mark.parametrize("strategy", ["sequential", "concurrent"])
def test_robust_beats_paper_method_with_noise(strategy):
    """On near-planar robots the paper's Eq. 6 is ill conditioned; the default is not."""
    rng = np.random.default_rng(6)
    obs, _, ts, _, t_c = _batch(rng, strategy, BATCH, flat=False)
    noisy = eqx.tree_at(
        lambda o: (o.mutual, o.overhead),
        obs,
        (
            obs.mutual + 1e-3 * rng.normal(size=obs.mutual.shape),
            obs.overhead + 1e-3 * rng.normal(size=obs.overhead.shape),
        ),
    )
    robust, paper = _solve_batch(noisy)
    err = {
        name: np.linalg.norm(np.asarray(e.poses.T_world_overhead.translation()) - t_c, axis=-1)
        for name, e in (("robust", robust), ("paper", paper))
    }
    assert np.median(err["robust"]) < 0.5 * np.median(err["paper"])
    assert np.median(err["robust"]) < 0.25


def test_unknown_method_rejected():
    rng = np.random.default_rng(7)
    obs = exact_observations(*random_cycle_truth(rng, "sequential"), "sequential")
    with pytest.raises(ValueError, match="method"):
        localize_cycle(obs, RIG, method="magic")


def test_cycle_poses_helpers():
    rng = np.random.default_rng(8)
    poses = cycle_poses(*random_cycle_truth(rng, "concurrent"))
    assert poses.positions.shape == (3, 3, 3)
    assert poses.final_body.wxyz_xyz.shape == (3, 7)
    np.testing.assert_allclose(
        jaxlie.SE3(poses.T_world_body.wxyz_xyz[0, 0]).wxyz_xyz,
        jaxlie.SE3.identity().wxyz_xyz,
        atol=1e-12,
    )


def test_mutual_steps_equal_one_solve_per_step():
    # One vmap over the steps, each with its robots reordered so that the reference comes
    # first, gives the same poses as solving each step with its own reference robot.
    from jaxloc._solvers.mutual import mutual_localization, mutual_steps

    rng = np.random.default_rng(5)
    bearings = rng.standard_normal((4, 3, 3, 3))
    bearings /= np.linalg.norm(bearings, axis=-1, keepdims=True)
    refs = (0, 2, 0, 1)
    sols = mutual_steps(jnp.asarray(bearings), refs)
    for k, ref in enumerate(refs):
        want = mutual_localization(jnp.asarray(bearings[k]), ref, throw=False)
        np.testing.assert_allclose(
            sols[k].T_ref_body.wxyz_xyz, want.T_ref_body.wxyz_xyz, rtol=0, atol=1e-14
        )
        assert sols[k].result == want.result
        assert sols[k].stats["min_angle"] == want.stats["min_angle"]
