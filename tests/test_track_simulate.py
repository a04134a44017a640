"""Simulation of K cycles (issue 21.1): the team continues where each cycle left it, the
climbing robot's odometry follows its model, the truth in the first cycle's frame. One
jitted program (the scenario is an argument: noisy and noise-free runs share it)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import jaxlie
import jaxloc
import numpy as np
import pytest


CYCLES = 4


@pytest.fixture(scope="module")
def simulate():
    return jax.jit(jax.vmap(lambda track, k: jaxloc.simulate_track(track, k, CYCLES),
                            in_axes=(None, 0)))  # fmt: skip


def _noiseless(track):
    return eqx.tree_at(
        lambda t: (t.scenario, t.climber_odometry_sigma_rel, t.climber_odometry_rotation_sigma),
        track, (jaxloc.noiseless(track.scenario), jnp.zeros(()), jnp.zeros(())),
    )  # fmt: skip


def test_cycles_continue_and_truth_in_first_frame(simulate):
    truth, obs, feasible = simulate(jaxloc.TrackScenario(), jr.split(jr.key(1), 3))
    T = truth.cycles.T_env_body.wxyz_xyz  # (runs, K, steps, 3, 7)
    # Each cycle starts where the previous one ended (ground robots, E frame), exactly.
    np.testing.assert_array_equal(T[:, 1:, 0], T[:, :-1, -1])
    # Cycle 0's truth in W_0 is its own truth; later cycles' frames are C1's end poses.
    np.testing.assert_allclose(truth.T_world_body.wxyz_xyz[:, 0],
                               truth.cycles.poses.T_world_body.wxyz_xyz[:, 0], atol=1e-12)
    c1_end = truth.T_world_body.wxyz_xyz[:, :-1, -1, 0]  # (runs, K-1, 7)
    c1_next = truth.T_world_body.wxyz_xyz[:, 1:, 0, 0]
    np.testing.assert_allclose(c1_next, c1_end, atol=1e-12)
    # Feasibility is sticky, and the paper's scenario keeps every sighting here.
    f = np.asarray(feasible)
    assert np.all(f[:, 1:] <= f[:, :-1]) and f.all()
    # The height of the overhead camera above the robots' plane: about the room's.
    assert np.all(np.abs(np.asarray(truth.height) - 3.45) < 0.3)
    assert obs.cycles.mutual.shape == (3, CYCLES, 4, 3, 3, 3)


def test_climber_odometry_is_its_true_motion_when_noise_free(simulate):
    track = _noiseless(jaxloc.TrackScenario())
    truth, obs, _ = simulate(track, jr.split(jr.key(2), 2))
    T = truth.T_world_climber.wxyz_xyz

    def rel(a, b):
        return (jaxlie.SE3(a).inverse() @ jaxlie.SE3(b)).wxyz_xyz

    true_motion = jax.vmap(jax.vmap(rel))(T[:, :-1], T[:, 1:])
    Z = obs.climber_odometry[:, 1:]
    Z = Z * jnp.sign(Z[..., :1] * true_motion[..., :1])  # quaternion sign
    np.testing.assert_allclose(Z, true_motion, atol=1e-12)
    # Between cycles the climbing robot moves (it follows the team), at most its step limit.
    step = np.linalg.norm(np.asarray(true_motion[..., 4:6]), axis=-1)
    assert np.all(step <= float(track.climber_step_max) + 1e-6)
    # Noise-free odometry keeps a finite weight (the floor sigma).
    assert np.all(np.asarray(obs.climber_odometry_sigma[:, 1:]) > 0)


def test_climber_odometry_noise_matches_its_model(simulate):
    track = jaxloc.TrackScenario(climber_odometry_sigma_rel=0.05,
                                 climber_odometry_rotation_sigma=0.02)  # fmt: skip
    truth, obs, _ = simulate(track, jr.split(jr.key(3), 64))
    T = truth.T_world_climber.wxyz_xyz
    Z = obs.climber_odometry[:, 1:].reshape(-1, 7)
    true_motion = jax.vmap(
        lambda a, b: (jaxlie.SE3(a).inverse() @ jaxlie.SE3(b)).wxyz_xyz
    )(T[:, :-1].reshape(-1, 7), T[:, 1:].reshape(-1, 7))
    noise = jax.vmap(lambda t, z: jaxlie.manifold.rminus(jaxlie.SE3(t), jaxlie.SE3(z)))(
        true_motion, Z
    )
    whitened = np.asarray(noise / obs.climber_odometry_sigma[:, 1:].reshape(-1, 6))
    # 192 draws per axis: the whitened noise has unit variance (chi-square, 3 sigma).
    var = np.mean(whitened**2, axis=0)
    assert np.all(np.abs(var - 1) < 3 * np.sqrt(2 / whitened.shape[0])), var
