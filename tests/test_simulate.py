import functools as ft

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import jaxlie
import numpy as np
import pytest
from jaxloc._cameras.presets import R_BODY_OVERHEAD, R_BODY_PTZ
from jaxloc._cycle.observations import CycleObservations, move_start_step, moving_robot
from jaxloc._sim.scenario import astype, Scenario
from jaxloc._sim.simulate import CycleTruth, noiseless, simulate_cycle


N = 256  # one batch size everywhere, so each strategy compiles once


@eqx.filter_jit
def _batched(scenario, keys):
    return jax.vmap(simulate_cycle, in_axes=(None, 0))(scenario, keys)


@ft.cache
def _run(strategy, noise_free=False, seed=0):
    s = Scenario.paper(strategy)
    if noise_free:
        s = noiseless(s)
    return s, _batched(s, jr.split(jr.key(seed), N))


def _assert_trees_close(a, b, atol):
    # NaN (unmeasured pixels) compares equal to NaN.
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=atol)


def _rows(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


def _true_bearings(truth: CycleTruth):
    """Bearings from the truth poses in W, independently of the simulator's code."""
    R = truth.poses.T_world_body.rotation().as_matrix()  # (steps, 3, 3, 3)
    p = truth.poses.T_world_body.translation()  # (steps, 3, 3)
    d = p[:, None, :, :] - p[:, :, None, :]
    rel = jnp.einsum("kiab,kija->kijb", R, d)
    n = jnp.linalg.norm(rel, axis=-1, keepdims=True)
    mutual = jnp.where(n > 0, rel / jnp.where(n > 0, n, 1.0), 0.0)
    T_ow = truth.poses.T_world_overhead.inverse()
    q = jax.vmap(jax.vmap(lambda x: T_ow @ x))(p)
    over = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return mutual, over


@pytest.mark.parametrize("strategy", ["sequential", "concurrent"])
def test_shapes_frames_and_feasibility(strategy):
    s, (truth, obs, ok) = _run(strategy)
    steps, moves = {"sequential": (4, 3), "concurrent": (3, 4)}[strategy]
    assert isinstance(obs, CycleObservations) and obs.strategy == strategy
    assert obs.mutual.shape == (N, steps, 3, 3, 3)
    assert obs.overhead.shape == (N, steps, 3, 3)
    assert obs.odometry.shape == (N, moves) and obs.odometry_sigma.shape == (N, moves)
    assert truth.poses.T_world_body.wxyz_xyz.shape == (N, steps, 3, 7)
    assert ok.shape == (N,) and ok.dtype == jnp.bool_
    frac = float(jnp.mean(ok))
    print(f"feasible fraction ({strategy}, {s.move_candidates} candidates): {frac:.4f}")
    assert frac > 0.95
    # Diagonal: zero bearings, NaN pixels.
    idx = np.arange(3)
    assert np.all(obs.mutual[:, :, idx, idx] == 0.0)
    assert np.all(np.isnan(obs.mutual_pixels[:, :, idx, idx]))
    # W is C1's body frame at the start; the environment-frame poses agree.
    T00 = _rows(truth.poses.T_world_body, (slice(None), 0, 0))
    np.testing.assert_allclose(T00.as_matrix(), np.broadcast_to(np.eye(4), (N, 4, 4)), atol=1e-12)
    env = jax.vmap(lambda Tw, Tb: jax.vmap(jax.vmap(lambda T: Tw @ T))(Tb))(
        truth.T_env_world, truth.poses.T_world_body
    )
    np.testing.assert_allclose(env.as_matrix(), truth.T_env_body.as_matrix(), atol=1e-12)
    # Who moves: exactly the strategy's robots, the others stay.
    p = truth.T_env_body.translation()
    moved = np.zeros((steps - 1, 3), bool)
    moved[move_start_step(strategy), moving_robot(strategy)] = True
    step_moves = np.linalg.norm(p[:, 1:] - p[:, :-1], axis=-1) > 0
    np.testing.assert_array_equal(step_moves, np.broadcast_to(moved, step_moves.shape))
    # Odometry truth is the straight-line distance of each move.
    st, mv = move_start_step(strategy), moving_robot(strategy)
    dist = np.linalg.norm(p[:, st + 1, mv] - p[:, st, mv], axis=-1)
    np.testing.assert_allclose(truth.move_distances, dist, rtol=1e-12)


@eqx.filter_jit
def _sightings(s, truth):
    """In-view flags recomputed from the truth poses through jaxlie and the mounts, not
    the simulator's einsums."""
    T_eb, T_eo = truth.T_env_body, truth.T_env_overhead
    p = T_eb.translation()  # (N, steps, 3, 3)
    q = jax.vmap(lambda T, x: jax.vmap(jax.vmap(lambda y: T.inverse() @ y))(x))(T_eo, p)

    def rel(Tb, pts):  # one step: robot j in robot i's body frame, (3, 3, 3)
        return jax.vmap(lambda T: jax.vmap(lambda y: T.inverse() @ y)(pts))(Tb)

    r = jax.vmap(jax.vmap(rel))(T_eb, p)  # (N, steps, 3, 3, 3)
    ptz = s.rig.ptz.in_view(r[:, :, 0] @ jnp.asarray(R_BODY_PTZ))  # p_base = R^T p_body
    rig = s.rig
    omni2, omni3 = rig.omni2.in_view(r[:, :, 1]), rig.omni3.in_view(r[:, :, 2])
    return rig.overhead.in_view(q), ptz, omni2, omni3


@pytest.mark.parametrize("strategy", ["sequential", "concurrent"])
def test_required_robots_in_view(strategy):
    s, (truth, obs, ok) = _run(strategy)
    over, ptz, om2, om3 = _sightings(s, truth)
    np.testing.assert_array_equal(over, obs.overhead_visible)
    assert np.all(over[ok])
    assert np.all(ptz[ok][:, :, 1:])
    assert np.all(om2[ok][:, :, [0, 2]]) and np.all(om3[ok][:, :, [0, 1]])
    assert np.all(np.isfinite(obs.mutual_pixels[ok][:, :, [0, 0, 1, 1, 2, 2], [1, 2, 0, 2, 0, 1]]))
    # Separation guard.
    p = np.asarray(truth.T_env_body.translation())
    d = np.linalg.norm(p[:, :, :, None] - p[:, :, None], axis=-1)[ok]
    assert np.all(d[:, :, [0, 0, 1], [1, 2, 2]] >= float(s.min_separation))


@pytest.mark.parametrize("strategy", ["sequential", "concurrent"])
def test_noiseless_observations_are_exact(strategy):
    s, (truth, obs, ok) = _run(strategy, noise_free=True)
    mutual, over = eqx.filter_jit(jax.vmap(_true_bearings))(truth)
    np.testing.assert_allclose(obs.mutual[ok], mutual[ok], atol=1e-9)
    np.testing.assert_allclose(obs.overhead[ok], over[ok], atol=1e-9)
    np.testing.assert_allclose(obs.odometry, truth.move_distances, rtol=1e-14)
    # Exact odometry is still a valid observation: sigma 1e-6 of the longest move.
    floor = 1e-6 * np.max(np.asarray(obs.odometry), axis=-1, keepdims=True)
    np.testing.assert_allclose(obs.odometry_sigma, np.broadcast_to(floor, obs.odometry.shape))
    # Same key, same geometry with and without noise (noise keys are separate).
    _, (truth_noisy, obs_noisy, ok_noisy) = _run(strategy)
    np.testing.assert_array_equal(ok, ok_noisy)
    _assert_trees_close(truth, truth_noisy, atol=0.0)


def test_noise_statistics():
    s, (truth, obs, ok) = _run("sequential")
    _, (_, obs0, _) = _run("sequential", noise_free=True)
    # The paper's model: radius ~ N(0, sigma), uniform direction => E[r^2] = sigma^2.
    e = np.asarray(obs.overhead_pixels - obs0.overhead_pixels)[ok].reshape(-1, 2)
    r2 = np.mean(np.sum(e**2, axis=-1))
    assert abs(np.sqrt(r2) / float(s.rig.pixel_sigma[0]) - 1.0) < 0.1
    off = ~np.eye(3, dtype=bool)
    e = np.asarray(obs.mutual_pixels - obs0.mutual_pixels)[ok][:, :, off].reshape(-1, 2)
    assert abs(np.sqrt(np.mean(np.sum(e**2, axis=-1))) / float(s.rig.pixel_sigma[0]) - 1.0) < 0.1
    # Noisy bearings stay unit vectors.
    seen = np.asarray(obs.overhead_visible)
    np.testing.assert_allclose(np.linalg.norm(obs.overhead, axis=-1)[seen], 1.0, atol=1e-12)
    # A sighting out of view is missing: NaN, not a default value.
    assert np.all(np.isnan(np.asarray(obs.overhead)[~seen]))
    # Odometry: relative error ~ N(0, 1%); sigma = 1% of the measurement.
    rel = np.asarray(obs.odometry / truth.move_distances - 1.0).ravel()
    assert abs(np.std(rel) / 0.01 - 1.0) < 0.15
    np.testing.assert_allclose(obs.odometry_sigma, 0.01 * obs.odometry, rtol=1e-12)
    # Move lengths ~ N(0.8, 0.2) (straight-line distances are within mm of it).
    d = np.asarray(truth.move_distances[ok]).ravel()
    assert abs(d.mean() - 0.8) < 0.05 and abs(d.std() - 0.2) < 0.05


def test_jit_matches_vmap_and_is_deterministic():
    s, batch = _run("sequential")
    keys = jr.split(jr.key(0), N)
    i = 7
    single = eqx.filter_jit(simulate_cycle)(s, keys[i])
    _assert_trees_close(_rows(batch, i), single, atol=1e-12)
    again = _batched(s, keys)
    _assert_trees_close(batch, again, atol=0.0)
    other = _batched(s, jr.split(jr.key(1), N))
    assert not np.allclose(other[1].mutual, batch[1].mutual)


def test_paper_geometry_of_the_overhead_camera():
    s, (truth, obs, ok) = _run("sequential")
    T = _rows(truth.T_env_overhead, 0)
    # Right above the origin, 3.5 m above the ground there, looking straight down, with
    # the image's x axis along E +x (heading 90 deg).
    np.testing.assert_allclose(T.translation(), [0.0, 0.0, 3.5], atol=1e-12)
    R = T.rotation().as_matrix()
    np.testing.assert_allclose(R[:, 2], [0.0, 0.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(R[:, 0], [1.0, 0.0, 0.0], atol=1e-12)
    climber = _rows(truth.T_env_climber, 0)
    np.testing.assert_allclose(
        (climber @ jaxlie.SE3.from_rotation(jaxlie.SO3.from_matrix(R_BODY_OVERHEAD))).as_matrix(),
        T.as_matrix(),
        atol=1e-12,
    )
    # Initial C1 is below the base, 3.578 m under the camera (Table I: 357.73 cm).
    p0 = _rows(truth.T_env_body, 0).translation()[0]
    np.testing.assert_allclose(p0[:, :2], s.formation_xy(), atol=1e-14)
    np.testing.assert_allclose(3.5 - p0[0, 2], 3.578125, atol=1e-12)


def test_float32():
    s = astype(Scenario.paper("concurrent"), jnp.float32)
    truth, obs, ok = _batched(s, jr.split(jr.key(3), N))
    for x in (obs.mutual, obs.overhead, obs.odometry, obs.mutual_pixels, truth.move_distances):
        assert x.dtype == jnp.float32
    assert truth.poses.T_world_body.wxyz_xyz.dtype == jnp.float32
    assert float(jnp.mean(ok)) > 0.95
    assert np.all(np.isfinite(obs.mutual[ok])) and np.all(np.isfinite(obs.overhead[ok]))
    np.testing.assert_allclose(np.linalg.norm(obs.mutual[ok][:, :, 0, 1], axis=-1), 1.0, atol=1e-5)


def test_ptz_unproject_is_in_the_base_frame():
    # Regression guard for the mount convention: the PTZ bearing rotated by R_BODY_PTZ
    # must point from C1 towards C2 in C1's body frame (forward-left).
    _, (truth, obs, ok) = _run("sequential", noise_free=True)
    b = np.asarray(obs.mutual[ok][:, 0, 0, 1])
    assert np.all(b[:, 0] > 0) and np.all(b[:, 1] > 0)
    assert np.allclose(R_BODY_PTZ @ np.array([0.0, 0.0, 1.0]), [1.0, 0.0, 0.0])


# --------------------------------------------------------------------------------------
# Fixed moves and a general initial triangle (issue 8).

TRIANGLE = np.array([[-1.2, 0.05], [0.05, 1.05], [-0.05, -0.95]])
FIXED = {
    "sequential": np.array([[0.7, 0.1], [0.9, -0.2], [0.6, 0.15]]),
    "concurrent": np.array([[0.7, 0.1], [0.9, -0.2], [0.6, 0.3], [0.5, -0.25]]),
}
_single = eqx.filter_jit(simulate_cycle)


def _fixed_scenario(strategy, ground=None, moves=None):
    return Scenario.paper(
        strategy, ground=ground, initial_xy=TRIANGLE,
        moves=FIXED[strategy] if moves is None else moves, headings=(0.02, -0.1, 0.1),
    )  # fmt: skip


@pytest.mark.parametrize("strategy", ["sequential", "concurrent"])
def test_fixed_moves_are_applied_exactly(strategy):
    from jaxloc._sim.world import FlatSurface

    # On a flat ground a move of length L in direction phi (mover's body frame at the
    # start of the move) displaces the robot by exactly L (cos phi, sin phi, 0) in that
    # frame; on the saddle, the same holds for the tangent-plane step's (x, y), and the
    # end point is dropped onto the surface.
    ground = FlatSurface(0.0) if strategy == "concurrent" else None
    s = _fixed_scenario(strategy, ground)
    runs = [_single(s, jr.key(k)) for k in (0, 1)]
    for truth, obs, ok in runs:
        assert bool(ok)
        R = np.asarray(truth.T_env_body.rotation().as_matrix())  # (steps, 3, 3, 3)
        p = np.asarray(truth.T_env_body.translation())  # (steps, 3, 3)
        np.testing.assert_allclose(p[0, :, :2], TRIANGLE, atol=1e-14)
        moved = np.zeros(p.shape[:2], bool)
        for m, (k, r) in enumerate(zip(move_start_step(strategy), moving_robot(strategy))):
            length, phi = FIXED[strategy][m]
            step = length * (np.cos(phi) * R[k, r, :, 0] + np.sin(phi) * R[k, r, :, 1])
            np.testing.assert_allclose(p[k + 1, r, :2] - p[k, r, :2], step[:2], atol=1e-12)
            if ground is not None:
                d_body = R[k, r].T @ (p[k + 1, r] - p[k, r])
                np.testing.assert_allclose(d_body, [length * np.cos(phi),
                                                    length * np.sin(phi), 0.0], atol=1e-12)
                np.testing.assert_allclose(truth.move_distances[m], length, atol=1e-12)
            moved[k + 1, r] = True
        # Robots that do not move stay put, and so do headings.
        for k in range(1, p.shape[0]):
            still = ~moved[k]
            np.testing.assert_allclose(p[k, still], p[k - 1, still], atol=1e-14)
        heading = np.arctan2(R[:, :, 1, 0], R[:, :, 0, 0])  # body x projected on E x-y
        np.testing.assert_allclose(heading, np.broadcast_to([0.02, -0.1, 0.1], heading.shape),
                                   atol=1e-12)
    # The key draws only noise: both cycles have the same geometry.
    _assert_trees_close(runs[0][0].T_env_body, runs[1][0].T_env_body, atol=0.0)
    assert not np.allclose(runs[0][1].mutual, runs[1][1].mutual)


def test_infeasible_fixed_moves_are_flagged_not_resampled():
    # C2 backs off 3 m: it leaves the overhead camera's view. The simulator keeps the move
    # (no resampling) and flags the cycle; the lost sighting's pixels are NaN.
    moves = FIXED["sequential"].copy()
    moves[0] = (3.0, np.pi)
    truth, obs, ok = _single(_fixed_scenario("sequential", moves=moves), jr.key(0))
    assert not bool(ok)
    np.testing.assert_allclose(truth.move_distances[0], 3.0, rtol=0.02)  # 3D, on the saddle
    assert not bool(obs.overhead_visible[1, 1]) and np.all(np.isnan(obs.overhead_pixels[1, 1]))
    assert bool(obs.overhead_visible[0, 1])


def test_fixed_moves_and_triangle_are_differentiable():
    s = _fixed_scenario("sequential")

    def with_(moves, xy):
        return eqx.tree_at(lambda t: (t.moves, t.initial_xy), s, (moves, xy))

    def final(moves, xy):
        return simulate_cycle(with_(moves, xy), jr.key(0))[0].T_env_body.translation()[-1, 0]

    moves, xy = jnp.asarray(FIXED["sequential"]), jnp.asarray(TRIANGLE)
    g_moves, g_xy = jax.jit(jax.jacfwd(final, argnums=(0, 1)))(moves, xy)
    h = 1e-6

    def f(moves, xy):  # the jitted simulation shared with the tests above (no new compile)
        return _single(with_(moves, xy), jr.key(0))[0].T_env_body.translation()[-1, 0]

    fd = (f(moves.at[2, 1].add(h), xy) - f(moves.at[2, 1].add(-h), xy)) / (2 * h)
    np.testing.assert_allclose(g_moves[:, 2, 1], fd, atol=1e-7)
    fd = (f(moves, xy.at[0, 0].add(h)) - f(moves, xy.at[0, 0].add(-h))) / (2 * h)
    np.testing.assert_allclose(g_xy[:, 0, 0], fd, atol=1e-7)
    # C1 moves last (sequential): it follows its start about one for one (the tangent
    # plane turns a little on the saddle); C2's move does not change C1's end.
    np.testing.assert_allclose(g_xy[:2, 0, :], np.eye(2), atol=0.02)
    np.testing.assert_allclose(g_moves[:, 0], 0.0, atol=1e-12)
