r"""The measurement model of a localization cycle and its Jacobian (DESIGN §5).

Shared by the joint refinement ([`jaxloc.refine_cycle`][]), the covariance and the
Cramér–Rao bound ([`jaxloc.cycle_covariance`][], [`jaxloc.cycle_crlb`][]). Unknowns:
the pose `T_world_body` of every distinct robot placement (see
[`jaxloc.placement_ids`][]) and the overhead camera's optical-frame pose
`T_world_overhead`, all `wxyz_xyz`. Measurements: every mutual sighting in pixels of the
observing camera, every overhead pixel, every odometry distance, each whitened by its
standard deviation.

The Jacobian is assembled by the chain rule, not by differentiating the whole model:
a sighting depends on two poses only, so with jaxlie's right perturbation
`T exp(delta)`, `delta = (v, omega)`, a point `q = R^T (p - t)` seen from the pose
`(R, t)` moves by `-v + [q]x omega`, a sighted placement's origin moves by `R v`, and
only the camera projection is differentiated (three directions per sighting). This is
about 20x cheaper than `jax.jacfwd` over the ~40 stacked tangent directions.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Float, Scalar

from .._cameras.presets import R_BODY_OMNI, R_BODY_PTZ
from .._core.numerics import safe_norm
from .._cycle.observations import CycleObservations, move_start_step, moving_robot
from .._sim.scenario import Scenario
from .._solvers.strategies import overhead_point_ids


_SIGMA_FLOOR_PX = 1e-6


def placement_ids(strategy: str) -> np.ndarray:
    """Index of the distinct placement (pose) each robot occupies at each step.

    Shape `(steps, 3)`: a robot that does not move keeps its placement (and its pose)
    across steps. Sequential: 6 placements, concurrent: 7. Placement 0 is C1 at the start
    of the cycle, the world frame.
    """
    return overhead_point_ids(strategy)


def _first_occurrence(strategy: str) -> tuple[np.ndarray, np.ndarray]:
    """`(step, robot)` of the first sighting of each placement, two arrays `(placements,)`."""
    ids = placement_ids(strategy)
    n = int(ids.max()) + 1
    ks, rs = np.zeros(n, np.int32), np.zeros(n, np.int32)
    for p in range(n):
        k, r = np.argwhere(ids == p)[0]
        ks[p], rs[p] = k, r
    return ks, rs


def num_placements(strategy: str) -> int:
    """Number of distinct robot placements of a cycle (6 sequential, 7 concurrent)."""
    return int(placement_ids(strategy).max()) + 1


def pixel_sigma_per_axis(scenario: Scenario) -> Scalar:
    """Standard deviation (px) of each pixel coordinate under the scenario's noise model:
    `pixel_sigma / sqrt(2)` for `"paper"` (radius ~ N(0, sigma), uniform direction, so
    `E|n|^2 = sigma^2`), `pixel_sigma` for `"gaussian"`."""
    if scenario.noise_model == "paper":
        return scenario.pixel_sigma / np.sqrt(2.0)
    return scenario.pixel_sigma


def _rotations(T: Float[Array, "... 7"]) -> Float[Array, "... 3 3"]:
    flat = T.reshape(-1, 7)
    R = jax.vmap(lambda w: jaxlie.SE3(w).rotation().as_matrix())(flat)
    return R.reshape(T.shape[:-1] + (3, 3))


def _predict(T_place, T_over, scenario: Scenario, strategy: str):
    """Noise-free measurements of a cycle from its placements' and the overhead camera's
    poses (`wxyz_xyz` arrays `(placements, 7)` and `(7,)`, world frame `W`).

    Returns `(mutual (steps, 3, 3, 2) px, overhead (steps, 3, 2) px, lengths (moves,) m)`;
    the diagonal of `mutual` is a dummy (finite) value.
    """
    dtype = T_place.dtype
    ids = placement_ids(strategy)
    T_body = T_place[ids]  # (steps, 3, 7)
    p = T_body[..., 4:]
    R = _rotations(T_body)
    diff = p[:, None, :, :] - p[:, :, None, :]  # [k, i, j] = p_j - p_i
    rel = jnp.einsum("kiab,kija->kijb", R, diff)  # robot j in robot i's body frame
    eye = np.broadcast_to(np.eye(3, dtype=bool)[None, :, :, None], rel.shape)
    rel = jnp.where(eye, jnp.array([1.0, 0.0, 0.0], dtype), rel)
    M_ptz = jnp.asarray(R_BODY_PTZ, dtype)
    M_omni = jnp.asarray(R_BODY_OMNI, dtype)
    # Camera frames through the mounts: p_cam = M^T p_body (as in the simulator).
    uv_ptz = scenario.ptz.project(jnp.einsum("ab,...a->...b", M_ptz, rel[:, 0]))
    uv_2 = scenario.omni2.project(jnp.einsum("ab,...a->...b", M_omni, rel[:, 1]))
    uv_3 = scenario.omni3.project(jnp.einsum("ab,...a->...b", M_omni, rel[:, 2]))
    mutual = jnp.stack([uv_ptz, uv_2, uv_3], axis=1)
    R_o = _rotations(T_over)
    p_cam = jnp.einsum("ab,kja->kjb", R_o, p - T_over[None, None, 4:])
    overhead = scenario.overhead.project(p_cam)
    starts, movers = move_start_step(strategy), moving_robot(strategy)
    lengths = safe_norm(p[starts + 1, movers] - p[starts, movers])
    return mutual, overhead, lengths


def _visible_masks(T_place, T_over, scenario: Scenario, strategy: str):
    """Which sightings a camera makes at the given poses (`in_view`), like the simulator:
    `(mutual (steps, 3, 3), overhead (steps, 3))`, diagonal False."""
    ids = placement_ids(strategy)
    T_body = T_place[ids]
    p = T_body[..., 4:]
    R = _rotations(T_body)
    diff = p[:, None, :, :] - p[:, :, None, :]
    rel = jnp.einsum("kiab,kija->kijb", R, diff)
    eye = np.broadcast_to(np.eye(3, dtype=bool)[None, :, :, None], rel.shape)
    rel = jnp.where(eye, jnp.array([1.0, 0.0, 0.0], rel.dtype), rel)
    M_ptz = jnp.asarray(R_BODY_PTZ, rel.dtype)
    M_omni = jnp.asarray(R_BODY_OMNI, rel.dtype)
    vis = jnp.stack(
        [
            scenario.ptz.in_view(jnp.einsum("ab,...a->...b", M_ptz, rel[:, 0])),
            scenario.omni2.in_view(jnp.einsum("ab,...a->...b", M_omni, rel[:, 1])),
            scenario.omni3.in_view(jnp.einsum("ab,...a->...b", M_omni, rel[:, 2])),
        ],
        axis=1,
    )
    vis = vis & ~np.eye(3, dtype=bool)[None]
    p_cam = jnp.einsum("ab,kja->kjb", _rotations(T_over), p - T_over[None, None, 4:])
    return vis, scenario.overhead.in_view(p_cam)


class CycleData(eqx.Module):
    """Measurements of a cycle with their whitening weights (1 / sigma; 0 = unused).

    **Fields:** `mutual_pixels` `(steps, 3, 3, 2)` px, `mutual_weight` `(steps, 3, 3)`
    1/px, `overhead_pixels` `(steps, 3, 2)` px, `overhead_weight` `(steps, 3)` 1/px,
    `odometry` `(moves,)` m, `odometry_weight` `(moves,)` 1/m. Unused entries hold 0.
    """

    mutual_pixels: Float[Array, "steps 3 3 2"]
    mutual_weight: Float[Array, "steps 3 3"]
    overhead_pixels: Float[Array, "steps 3 2"]
    overhead_weight: Float[Array, "steps 3"]
    odometry: Float[Array, " moves"]
    odometry_weight: Float[Array, " moves"]


def _odometry_weight(d, sigma):
    # Zero sigmas (noiseless odometry) fall back to a tiny floor, as in the strategies.
    floor = 1e-9 + 1e-6 * jnp.max(jnp.abs(d))
    return 1.0 / jnp.maximum(sigma, floor)


def cycle_data(observations: CycleObservations, scenario: Scenario) -> CycleData:
    """Whitened measurement set of a cycle: NaN pixels (not measured) and the diagonal are
    masked out; pixel sigma per axis from [`jaxloc.pixel_sigma_per_axis`][]; odometry
    sigma from `observations.odometry_sigma`."""
    dtype = observations.mutual_pixels.dtype
    s_px = jnp.maximum(pixel_sigma_per_axis(scenario).astype(dtype), _SIGMA_FLOOR_PX)
    mp = observations.mutual_pixels
    m_ok = jnp.all(jnp.isfinite(mp), axis=-1) & ~np.eye(3, dtype=bool)[None]
    op = observations.overhead_pixels
    o_ok = jnp.all(jnp.isfinite(op), axis=-1) & observations.overhead_visible
    d = observations.odometry
    d_ok = jnp.isfinite(d) & jnp.isfinite(observations.odometry_sigma)
    d = jnp.where(d_ok, d, 0.0)
    return CycleData(
        mutual_pixels=jnp.where(m_ok[..., None], mp, 0.0),
        mutual_weight=jnp.where(m_ok, 1.0 / s_px, 0.0),
        overhead_pixels=jnp.where(o_ok[..., None], op, 0.0),
        overhead_weight=jnp.where(o_ok, 1.0 / s_px, 0.0),
        odometry=d,
        odometry_weight=jnp.where(
            d_ok, _odometry_weight(d, jnp.where(d_ok, observations.odometry_sigma, 0.0)), 0.0
        ),
    )


def _unpack(theta, T0_place, T0_over):
    """Poses from the tangent vector: placement 0 (C1 at the start) is the identity."""
    n = T0_place.shape[0]
    d = theta[:-6].reshape(n - 1, 6)
    moved = jax.vmap(lambda t, dd: jaxlie.manifold.rplus(jaxlie.SE3(t), dd).wxyz_xyz)(
        T0_place[1:], d
    )
    first = jnp.zeros((1, 7), T0_place.dtype).at[0, 0].set(1.0)
    T_place = jnp.concatenate([first, moved.astype(T0_place.dtype)])
    T_over = jaxlie.manifold.rplus(jaxlie.SE3(T0_over), theta[-6:]).wxyz_xyz
    return T_place, T_over.astype(T0_over.dtype)


def whitened(T_place, T_over, data: CycleData, scenario: Scenario, strategy: str):
    mutual, overhead, lengths = _predict(T_place, T_over, scenario, strategy)
    r_m = data.mutual_weight[..., None] * (mutual - data.mutual_pixels)
    r_o = data.overhead_weight[..., None] * (overhead - data.overhead_pixels)
    r_d = data.odometry_weight * (lengths - data.odometry)
    return jnp.concatenate([r_m.reshape(-1), r_o.reshape(-1), r_d])


def _skew(a: Float[Array, "*b 3"]) -> Float[Array, "*b 3 3"]:
    """`[a]x` with `[a]x w = a x w`."""
    z = jnp.zeros_like(a[..., 0])
    return jnp.stack(
        [
            jnp.stack([z, -a[..., 2], a[..., 1]], -1),
            jnp.stack([a[..., 2], z, -a[..., 0]], -1),
            jnp.stack([-a[..., 1], a[..., 0], z], -1),
        ],
        -2,
    )


def _mm(a: Float[Array, "*b x y"], b: Float[Array, "*b y z"]) -> Float[Array, "*b x z"]:
    """Batched small matrix product, element-wise (fuses; XLA's CPU dot is slow here)."""
    rank = max(a.ndim, b.ndim)
    a = a.reshape((1,) * (rank - a.ndim) + a.shape)
    b = b.reshape((1,) * (rank - b.ndim) + b.shape)
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def _project_with_jacobian(camera, points: Float[Array, "*b 3"]):
    """Pixels `(*b, 2)` and `d pixel / d point` `(*b, 2, 3)` of a camera model."""
    flat = points.reshape(-1, 3)
    uv = camera.project(flat)
    J = jax.vmap(jax.jacfwd(camera.project))(flat)
    return uv.reshape(points.shape[:-1] + (2,)), J.reshape(points.shape[:-1] + (2, 3))


def _pose_blocks(q: Float[Array, "*b 3"]) -> Float[Array, "*b 3 6"]:
    """`d q / d delta` for `q = R^T (p - t)` under `(R, t) <- (R, t) exp(delta)`."""
    eye = jnp.broadcast_to(jnp.eye(3, dtype=q.dtype), q.shape + (3,))
    return jnp.concatenate([-eye, _skew(q)], axis=-1)


def _point_blocks(A: Float[Array, "*b 3 3"]) -> Float[Array, "*b 3 6"]:
    """`d q / d delta` of a sighted placement's origin, `q = A p`: `[A R, 0]` (A R given)."""
    return jnp.concatenate([A, jnp.zeros_like(A)], axis=-1)


def whitened_with_jacobian(
    T_place: Float[Array, "placements 7"],
    T_over: Float[Array, "7"],
    data: CycleData,
    scenario: Scenario,
    strategy: str,
):
    """Whitened residuals and their Jacobian w.r.t. a right perturbation of every pose.

    **Returns:** `(r, J)`: `r` as [`whitened`][] `(m,)`; `J` of shape `(m, placements + 1,
    6)`: column block `p < placements` is placement `p`'s `delta = (v, omega)` in
    `T_place[p] exp(delta)`, the last block the overhead camera's.
    """
    dtype = T_place.dtype
    ids = placement_ids(strategy)
    n = T_place.shape[0]
    T_body = T_place[ids]  # (steps, 3, 7)
    p = T_body[..., 4:]
    R = _rotations(T_body)
    diff = p[:, None, :, :] - p[:, :, None, :]  # [k, i, j] = p_j - p_i
    rel = jnp.einsum("kiab,kija->kijb", R, diff)  # j in i's body frame
    eye = np.broadcast_to(np.eye(3, dtype=bool)[None, :, :, None], rel.shape)
    rel = jnp.where(eye, jnp.array([1.0, 0.0, 0.0], dtype), rel)
    Rt = jnp.swapaxes(R, -1, -2)
    RiT_Rj = _mm(Rt[:, :, None], R[:, None, :])  # [k, i, j] = R_i^T R_j
    mounts = (jnp.asarray(R_BODY_PTZ, dtype), jnp.asarray(R_BODY_OMNI, dtype))
    mutual, observer, target = [], [], []
    for i, (camera, M) in enumerate(
        [(scenario.ptz, mounts[0]), (scenario.omni2, mounts[1]), (scenario.omni3, mounts[1])]
    ):
        uv, Jp = _project_with_jacobian(camera, jnp.einsum("ab,...a->...b", M, rel[:, i]))
        JpM = _mm(Jp, M.T)  # d uv / d rel  (rel = M cam)
        mutual.append(uv)
        observer.append(_mm(JpM, _pose_blocks(rel[:, i])))
        target.append(_mm(JpM, _point_blocks(RiT_Rj[:, i])))
    mutual = jnp.stack(mutual, axis=1)  # (steps, 3, 3, 2)
    observer = jnp.stack(observer, axis=1)  # (steps, 3, 3, 2, 6)
    target = jnp.stack(target, axis=1)
    R_o = _rotations(T_over)
    p_cam = jnp.einsum("ab,kja->kjb", R_o, p - T_over[None, None, 4:])
    overhead, Jo = _project_with_jacobian(scenario.overhead, p_cam)
    over_cam = _mm(Jo, _pose_blocks(p_cam))
    over_pt = _mm(Jo, _point_blocks(_mm(R_o.T, R)))
    starts, movers = move_start_step(strategy), moving_robot(strategy)
    step = p[starts + 1, movers] - p[starts, movers]
    lengths = safe_norm(step)
    u = step / jnp.where(lengths > 0, lengths, 1.0)[:, None]
    u_end = jnp.sum(u[:, :, None] * R[starts + 1, movers], axis=-2)  # u^T R
    u_start = -jnp.sum(u[:, :, None] * R[starts, movers], axis=-2)
    zeros3 = jnp.zeros_like(u_end)

    # Residuals, whitened.
    r_m = data.mutual_weight[..., None] * (mutual - data.mutual_pixels)
    r_o = data.overhead_weight[..., None] * (overhead - data.overhead_pixels)
    r_d = data.odometry_weight * (lengths - data.odometry)
    r = jnp.concatenate([r_m.reshape(-1), r_o.reshape(-1), r_d])

    # Place the two-pose blocks in columns (rows, placements + 1, 6) with static masks
    # (element-wise: XLA's CPU dot kernels are slow on these tiny batched shapes).
    cols = np.arange(n + 1)
    at = (ids[..., None] == cols).astype(np.float64)  # (steps, 3, n + 1)
    w_m = data.mutual_weight[..., None, None, None]
    J_m = w_m * (
        jnp.asarray(at[:, :, None, None, :, None], dtype) * observer[..., None, :]
        + jnp.asarray(at[:, None, :, None, :, None], dtype) * target[..., None, :]
    )  # (steps, i, j, 2, n + 1, 6)
    w_o = data.overhead_weight[..., None, None, None]
    is_cam = (cols == n).astype(np.float64)
    J_o = w_o * (
        jnp.asarray(at[:, :, None, :, None], dtype) * over_pt[..., None, :]
        + jnp.asarray(is_cam[None, None, None, :, None], dtype) * over_cam[..., None, :]
    )  # (steps, j, 2, n + 1, 6)
    at_end = (ids[starts + 1, movers][:, None] == cols).astype(np.float64)
    at_start = (ids[starts, movers][:, None] == cols).astype(np.float64)
    d_end = jnp.concatenate([u_end, zeros3], -1)[:, None, :]
    d_start = jnp.concatenate([u_start, zeros3], -1)[:, None, :]
    J_d = data.odometry_weight[:, None, None] * (
        jnp.asarray(at_end[..., None], dtype) * d_end
        + jnp.asarray(at_start[..., None], dtype) * d_start
    )
    J = jnp.concatenate([J_m.reshape(-1, n + 1, 6), J_o.reshape(-1, n + 1, 6), J_d], axis=0)
    return r, J


def cycle_jacobian(T_place, T_over, data: CycleData, scenario: Scenario, strategy: str):
    """Jacobian of the whitened residuals w.r.t. the cycle's tangent parameters at the
    given poses, shape `(residuals, 6 (placements - 1) + 6)`: placements 1, 2, ... then
    the overhead camera (placement 0, C1's start pose, is the gauge)."""
    _, J = whitened_with_jacobian(T_place, T_over, data, scenario, strategy)
    return flat_jacobian(J)


def flat_jacobian(J_local: Float[Array, "m p 6"]) -> Float[Array, "m n"]:
    """Drop placement 0 (the gauge) from a [`whitened_with_jacobian`][] Jacobian and
    flatten it to the tangent layout of `_unpack`: placements 1, 2, ..., overhead."""
    return J_local[:, 1:].reshape(J_local.shape[0], -1)
