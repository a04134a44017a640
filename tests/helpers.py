"""Test helpers: exact observations of a cycle from given true poses (no simulator)."""

import equinox as eqx
import jax.numpy as jnp
import jaxlie
import jaxloc
import jaxloc._cycle.layout as obs_mod
import jaxloc._cycle.observations as observations_mod
import numpy as np
from jaxloc._cycle.rig import mount_pose
from scipy.spatial.transform import Rotation


def tree_allclose(x, y, *, rtol=1e-5, atol=1e-8):
    return eqx.tree_equal(x, y, typematch=True, rtol=rtol, atol=atol)


def _se3(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """wxyz_xyz array of a pose from a rotation matrix and translation."""
    q = Rotation.from_matrix(R).as_quat()  # xyzw
    return np.concatenate([[q[3]], q[:3], t])


def random_cycle_truth(rng: np.random.Generator, strategy: str, *, flat: bool = False):
    """A random cycle near the paper's geometry, as numpy arrays.

    Robots near the paper's triangle on a (tilted, curved-looking or flat) floor, random
    headings, moves of ~0.8 m, the overhead camera ~3.5 m up looking down. Returns
    `(R, t, R_c, t_c)`: body rotations `(steps, 3, 3, 3)` and positions `(steps, 3, 3)` in
    the world frame (C1's body frame at the start), and the overhead camera's
    optical-frame rotation and position in that world frame.
    """
    steps = obs_mod.num_steps(strategy)
    movers = obs_mod.moving_robot(strategy)
    starts = obs_mod.move_start_step(strategy)
    h = np.sqrt(1.5**2 - 1.0**2)
    xy = np.array([[-h, 0.0], [0.0, 1.0], [0.0, -1.0]]) + rng.normal(scale=0.2, size=(3, 2))
    yaws = rng.normal(scale=0.3, size=3)

    def pose(r):
        tilt = np.zeros(2) if flat else rng.normal(scale=0.08, size=2)
        z = 0.0 if flat else 0.1 * rng.normal()
        R = Rotation.from_euler("ZYX", [yaws[r], tilt[1], tilt[0]]).as_matrix()
        return R, np.array([xy[r, 0], xy[r, 1], z])

    Rs, ts = np.zeros((steps, 3, 3, 3)), np.zeros((steps, 3, 3))
    for r in range(3):
        Rs[0, r], ts[0, r] = pose(r)
    for k in range(1, steps):
        Rs[k], ts[k] = Rs[k - 1], ts[k - 1]
        for a, r in zip(starts, movers):
            if a + 1 == k:
                ang = rng.uniform(0, 2 * np.pi)
                length = np.clip(rng.normal(0.8, 0.2), 0.3, 1.3)
                xy[r] = xy[r] + length * np.array([np.cos(ang), np.sin(ang)])
                yaws[r] += rng.normal(scale=0.2)
                Rs[k, r], ts[k, r] = pose(r)
    # Express everything in C1's body frame at the start.
    R0, t0 = Rs[0, 0], ts[0, 0]
    Rs = np.einsum("ji,...jk->...ik", R0, Rs)
    ts = np.einsum("ji,...j->...i", R0, ts - t0)
    cam_xy = xy.mean(axis=0) * 0.3 + rng.normal(scale=0.2, size=2)
    R_c = Rotation.from_euler(
        "ZYX", [rng.uniform(0, 2 * np.pi), rng.normal(scale=0.1), np.pi + rng.normal(scale=0.1)]
    ).as_matrix()
    t_c = np.array([cam_xy[0], cam_xy[1], 3.5 + rng.normal(scale=0.1)])
    R_c, t_c = R0.T @ R_c, R0.T @ (t_c - t0)
    return Rs, ts, R_c, t_c


def cycle_poses(Rs, ts, R_c, t_c) -> observations_mod.CyclePoses:
    wxyz_xyz = np.array([[_se3(Rs[k, r], ts[k, r]) for r in range(3)] for k in range(len(ts))])
    return observations_mod.CyclePoses(
        jaxlie.SE3(jnp.asarray(wxyz_xyz)), jaxlie.SE3(jnp.asarray(_se3(R_c, t_c)))
    )


def exact_arrays(Rs, ts, R_c, t_c, strategy: str, xp=np):
    """Noise-free bearings `(steps,3,3,3)`, overhead bearings `(steps,3,3)` and odometry.

    `xp` is `numpy` or `jax.numpy` (for differentiating through the observations)."""
    diff = ts[:, None, :, :] - ts[:, :, None, :]  # [k, i, j] = p_j - p_i
    diff = diff + xp.eye(3)[None, :, :, None]  # keep the diagonal finite
    local = xp.einsum("kiab,kija->kijb", Rs, diff)  # R_i^T (p_j - p_i)
    mutual = local / xp.linalg.norm(local, axis=-1, keepdims=True)
    mutual = mutual * (1.0 - xp.eye(3))[None, :, :, None]
    cam = xp.einsum("ab,kia->kib", R_c, ts - t_c[None, None, :])
    overhead = cam / xp.linalg.norm(cam, axis=-1, keepdims=True)
    starts, movers = obs_mod.move_start_step(strategy), obs_mod.moving_robot(strategy)
    odometry = xp.stack([xp.linalg.norm(ts[a + 1, r] - ts[a, r]) for a, r in zip(starts, movers)])
    return mutual, overhead, odometry


def exact_observations(Rs, ts, R_c, t_c, strategy: str) -> observations_mod.CycleObservations:
    mutual, overhead, odometry = exact_arrays(Rs, ts, R_c, t_c, strategy)
    return observations_mod.CycleObservations(
        jnp.asarray(mutual),
        jnp.asarray(overhead),
        jnp.asarray(odometry),
        0.01 * jnp.asarray(odometry),
        strategy,
    )


def all_seeing_rig() -> jaxloc.Rig:
    """A rig whose ground cameras see in every direction (the paper's omnidirectional
    camera, mounted upright, on all three ground robots) and the paper's overhead camera:
    the random formations of `random_cycle_truth` have random headings, which the PTZ
    camera's 85 degrees would not cover."""
    eye = mount_pose(np.eye(3))
    mounts = jnp.stack([mount_pose(jaxloc.R_BODY_OVERHEAD), eye, eye, eye])
    omni = jaxloc.paper_omni_camera()
    return jaxloc.Rig(jaxloc.paper_overhead_camera(), omni, omni, omni, mounts=mounts)
