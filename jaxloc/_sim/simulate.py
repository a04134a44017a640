r"""Simulation of one localization cycle: formations, moves, and every measurement.

[`jaxloc.simulate_cycle`][] places the team in the [`jaxloc.Scenario`][]'s world, draws
the strategy's moves with branch-free resampling until every required camera sees every
required robot, and synthesizes every observation through the camera models, the path a
real image takes: point in the observing camera's frame -> `camera.project` -> pixel
noise -> `camera.unproject` -> back through the mount. It returns the ground truth, the
[`jaxloc.CycleObservations`][] the estimators consume, and a feasibility flag.

Frames: environment `E` (z up; see [`jaxloc.formation_xy`][]), robot body frames (x
forward, y left, z up along the surface normal), camera frames through the mounts
`R_BODY_PTZ`, `R_BODY_OMNI`, `R_BODY_OVERHEAD`, and the cycle's world frame `W` = C1's
body frame at the start of the cycle (DESIGN §1).
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import jaxlie
import numpy as np
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from .._cameras.presets import R_BODY_OMNI, R_BODY_OVERHEAD, R_BODY_PTZ
from .._cycle.observations import (
    CycleObservations,
    CyclePoses,
    move_start_step,
    moving_robot,
    num_steps,
)
from .scenario import Scenario
from .world import body_frame_on_surface


MIN_MOVE_LENGTH = 0.05
"""Move lengths drawn from N(move_mean, move_std) are clipped to at least this (m)."""


class CycleTruth(eqx.Module):
    r"""Ground truth of one simulated localization cycle.

    **Fields:**

    - `poses`: a [`jaxloc.CyclePoses`][] in the cycle's world frame `W` (C1's body frame
      at the start): ground robots' body poses, batch shape `(steps, 3)`, and the
      overhead camera's **optical** frame pose. What estimates are compared with.
    - `T_env_world`: pose of `W` in the environment frame `E` (= C1's start body pose),
      for plotting; `T_env_X = T_env_world @ T_world_X`.
    - `T_env_body`: the ground robots' body poses in `E`, batch shape `(steps, 3)`.
    - `T_env_overhead`: the overhead camera's optical-frame pose in `E`.
    - `T_env_climber`: the climbing robot's body pose in `E` (body z into the ceiling);
      `T_env_overhead = T_env_climber @ SE3(R_BODY_OVERHEAD)`.
    - `move_distances`: true straight-line distance between each move's start and end
      positions (m), shape `(moves,)`; what the odometry measures, before noise.
    """

    poses: CyclePoses
    T_env_world: jaxlie.SE3
    T_env_body: jaxlie.SE3
    T_env_overhead: jaxlie.SE3
    T_env_climber: jaxlie.SE3
    move_distances: Float[Array, " moves"]


def noiseless(scenario: Scenario) -> Scenario:
    """`scenario` with `pixel_sigma = 0` and `odometry_sigma_rel = 0` (same dtype): its
    cycles' observations are exact (for exactness tests of the estimators)."""
    return eqx.tree_at(
        lambda s: (s.pixel_sigma, s.odometry_sigma_rel),
        scenario,
        (jnp.zeros_like(scenario.pixel_sigma), jnp.zeros_like(scenario.odometry_sigma_rel)),
    )


def _mat(R: np.ndarray, dtype) -> Array:
    return jnp.asarray(R, dtype=dtype)


def _robot_frames(scenario: Scenario, xy: Float[Array, "*s 3 2"]):
    """Body frames `(R_env_body (*s, 3, 3, 3), p_env_body (*s, 3, 3))` of C1, C2, C3."""
    headings = jnp.broadcast_to(scenario.headings.astype(xy.dtype), xy.shape[:-1])
    return body_frame_on_surface(scenario.ground, xy, headings)


def _relative_points(R: Float[Array, "*s 3 3 3"], p: Float[Array, "*s 3 3"]):
    """`rel[..., i, j] = R_i^T (p_j - p_i)`: robot `j` in robot `i`'s body frame."""
    d = p[..., None, :, :] - p[..., :, None, :]
    return jnp.einsum("...iab,...ija->...ijb", R, d)


def _omni_pair(scenario: Scenario):
    """omni2 and omni3 stacked into one batched camera (one traced call for both, a
    smaller program to compile), or `None` if their static configuration differs."""
    a, b = scenario.omni2, scenario.omni3
    if jax.tree.structure(a) != jax.tree.structure(b):
        return None
    return jax.tree.map(lambda x, y: jnp.stack([x, y]), a, b)


def _omni_call(scenario: Scenario, method: str, x: Array) -> Array:
    """`omni2.<method>(x[..., 0, :, :])` and `omni3.<method>(x[..., 1, :, :])`, stacked
    back on the same axis (`x`'s axis -3 holds the two omni observers)."""
    pair = _omni_pair(scenario)
    if pair is None:
        out = [getattr(cam, method)(x[..., i, :, :]) for i, cam in
               enumerate((scenario.omni2, scenario.omni3))]  # fmt: skip
        return jnp.stack(out, axis=-3 if out[0].ndim == x.ndim - 1 else -2)
    out = jax.vmap(lambda cam, v: getattr(cam, method)(v))(pair, jnp.moveaxis(x, -3, 0))
    return jnp.moveaxis(out, 0, -3 if out.ndim == x.ndim else -2)


def _visibility(scenario: Scenario, rel, p_over_cam):
    """Required-visibility checks of one or more formations.

    `rel`: `(*s, 3, 3, 3)` points of robot `j` in robot `i`'s body frame;
    `p_over_cam`: `(*s, 3, 3)` robots in the overhead camera frame.
    Returns `(ok (*s,), overhead_in_view (*s, 3), mutual_in_view (*s, 3, 3))`.
    """
    dtype = rel.dtype
    over = scenario.overhead.in_view(p_over_cam)
    ptz_pts = jnp.einsum("ab,...a->...b", _mat(R_BODY_PTZ, dtype), rel[..., 0, :, :])
    omni_pts = jnp.einsum("ab,...a->...b", _mat(R_BODY_OMNI, dtype), rel)
    ptz_vis = scenario.ptz.in_view(ptz_pts)[..., None, :]
    omni_vis = _omni_call(scenario, "in_view", omni_pts[..., 1:, :, :])
    mutual = jnp.concatenate([ptz_vis, omni_vis], axis=-2)
    off = jnp.broadcast_to(~np.eye(3, dtype=bool), mutual.shape)
    ok = jnp.ones(rel.shape[:-3], dtype=bool)
    if scenario.require_overhead:
        ok = ok & jnp.all(over, axis=-1)
    if scenario.require_ptz:
        ok = ok & jnp.all(mutual[..., 0, 1:], axis=-1)
    if scenario.require_omni:
        ok = ok & jnp.all(jnp.where(off[..., 1:, :], mutual[..., 1:, :], True), axis=(-2, -1))
    mutual = mutual & off
    return ok, over, mutual


def _formations_ok(scenario: Scenario, xy, R_over, t_over):
    """Feasibility of formations `xy` `(n, 3, 2)`: required sightings and separation.

    Returns `(ok (n,), overhead_in_view (n, 3), mutual_in_view (n, 3, 3))`."""
    R, p = _robot_frames(scenario, xy)
    rel = _relative_points(R, p)
    p_over = jnp.einsum("ab,nja->njb", R_over, p - t_over[None, None, :])
    ok, over, mutual = _visibility(scenario, rel, p_over)
    d = p[:, :, None, :] - p[:, None, :, :]
    dist2 = jnp.sum(d * d, axis=-1)
    sep = scenario.min_separation.astype(xy.dtype)
    diag = jnp.broadcast_to(np.eye(3, dtype=bool), dist2.shape)
    ok = ok & jnp.all(jnp.where(diag, True, dist2 >= sep * sep), axis=(-2, -1))
    return ok, over, mutual


def _pixel_noise(scenario: Scenario, key, shape, dtype):
    sigma = scenario.pixel_sigma.astype(dtype)
    if scenario.noise_model == "paper":
        # Sec. IV.A: an error of N(0, 2) px "uniformly distributed in isotropic
        # directions": signed radius ~ N(0, sigma), direction ~ U[0, 2 pi).
        k_r, k_a = jr.split(key)
        r = sigma * jr.normal(k_r, shape, dtype)
        a = jr.uniform(k_a, shape, dtype, 0.0, 2.0 * math.pi)
        return jnp.stack([r * jnp.cos(a), r * jnp.sin(a)], axis=-1)
    return sigma * jr.normal(key, shape + (2,), dtype)


def _se3(R: Float[Array, "3 3"], p: Float[Array, "3"]) -> jaxlie.SE3:
    return jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.from_matrix(R), p)


def simulate_cycle(
    scenario: Scenario, key: PRNGKeyArray
) -> tuple[CycleTruth, CycleObservations, Bool[Array, ""]]:
    r"""Simulate one localization cycle of `scenario`.

    1. **Placement.** Ground robots at `scenario.formation_xy()` (`initial_xy` if
       given, else [`jaxloc.formation_xy`][]`(base, side)`) on `scenario.ground` with
       `scenario.headings`; the climbing robot at `overhead_xy`
       on `scenario.ceiling` with `overhead_heading`; the overhead camera's optical
       frame is its body pose composed with `R_BODY_OVERHEAD`. Every pose via
       [`jaxloc.body_pose_on_surface`][].
    2. **Moves** (DESIGN §3; order from `jaxloc._observations.moving_robot`): length
       $L \sim N(\text{move\_mean}, \text{move\_std})$ clipped to >= 0.05 m, direction
       uniform in the robot's tangent plane, $d = \cos\varphi\,x_b + \sin\varphi\,y_b$.
       The end point is the surface point below/above `xy + L d_xy` (a straight
       step in the tangent plane dropped onto the surface, not a geodesic: the
       difference is a few millimetres at most on the paper's gently curved ground),
       with the heading unchanged. Branch-free resampling: `move_candidates` candidates are drawn at
       once for each step (for the concurrent strategy a candidate is a *pair* of moves
       of C2 and C3), each is checked for the required sightings of the formation after
       the step (`scenario.require_*`: the overhead camera sees all three robots; C1's
       PTZ sees C2 and C3; each omni camera sees the two others within its elevation
       band) and for `min_separation`, and the first feasible candidate is taken. If
       none is feasible (or the initial formation is not), the first candidate is kept
       and the returned flag is `False`. **Fixed moves** (`scenario.moves` given): move
       `m` has exactly length `moves[m, 0]` and direction `moves[m, 1]` (no clipping, no
       resampling); if a step's formation breaks a requirement the flag is `False`.
    3. **Observations** through the cameras: the target robot's position (its marker
       = its camera centre) in the observer's camera frame (PTZ base frame
       `R_BODY_PTZ^T p_body`, omni frame = body frame, overhead optical frame),
       `project`, pixel noise (`noise_model` "paper": radius ~ N(0, `pixel_sigma`),
       uniform direction; "gaussian": N(0, `pixel_sigma`^2) per axis), `unproject`,
       rotated back by the mount into the body frame (mutual) or kept in the overhead
       camera's frame (overhead). Visibility decisions use the true points. Pixels of
       sightings outside the camera's view, and of the diagonal `i == j`, are NaN; the
       diagonal bearings are zero.
    4. **Odometry**: the true straight-line distance between each move's start and end
       positions times $(1 + \text{odometry\_sigma\_rel}\,N(0, 1))$;
       `odometry_sigma = odometry_sigma_rel * measured`.

    Pure, for one trial: batch with `jax.vmap(lambda k: simulate_cycle(scenario, k))`.
    All randomness comes from `key` (split per purpose). Runs in the scenario's float
    dtype (cast with [`jaxloc.astype`][] for float32).

    **Arguments:**

    - `scenario`: a [`jaxloc.Scenario`][].
    - `key`: a JAX PRNG key.

    **Returns:** `(truth, observations, all_visible)`: a [`jaxloc.CycleTruth`][], a
    [`jaxloc.CycleObservations`][] (`strategy = scenario.strategy`), and a boolean
    scalar, `True` iff every formation of the cycle satisfies the requirements (mark the
    trial `RESULTS.not_visible` otherwise).
    """
    strategy = scenario.strategy
    steps = num_steps(strategy)
    movers = moving_robot(strategy)
    starts = move_start_step(strategy)
    dtype = jnp.result_type(scenario.base.dtype, scenario.side.dtype)
    K = scenario.move_candidates
    k_moves, k_mutual, k_over, k_odo = jr.split(key, 4)

    # 1. Placement.
    R_climber, t_over = body_frame_on_surface(
        scenario.ceiling,
        scenario.overhead_xy.astype(dtype),
        scenario.overhead_heading.astype(dtype),
    )
    R_over = R_climber @ _mat(R_BODY_OVERHEAD, dtype)  # camera and body share the centre
    xy0 = scenario.formation_xy().astype(dtype)

    # 2. Moves. Which robots move at each step, (steps - 1, 3): one (sequential) or two
    # (concurrent).
    mover_mask = np.zeros((steps - 1, 3), dtype=bool)
    mover_mask[starts, movers] = True
    mean = scenario.move_mean.astype(dtype)
    std = scenario.move_std.astype(dtype)
    fixed = scenario.moves is not None  # static: the pytree structure decides
    if fixed:
        # (length, direction) of each robot at each step (zeros for robots that stay).
        fixed_moves = jnp.zeros((steps - 1, 3, 2), dtype).at[starts, movers].set(
            scenario.moves.astype(dtype)
        )
    else:
        fixed_moves = None  # no scan input: the random path's program is unchanged

    def one_step(carry, inputs):
        xy, feasible = carry
        step_key, movers_now, first, fixed_now = inputs
        R, _ = _robot_frames(scenario, xy)  # (3, 3, 3)
        if fixed:
            # The given moves, exactly: one candidate, never resampled (an infeasible one
            # makes the cycle infeasible).
            length, phi = fixed_now[None, :, 0], fixed_now[None, :, 1]  # (1, 3)
        else:
            k_len, k_dir = jr.split(step_key)
            # Candidates are drawn for all three robots (cheap) and kept for the movers
            # only, so that one scan body serves every step of both strategies.
            length = jnp.maximum(mean + std * jr.normal(k_len, (K, 3), dtype), MIN_MOVE_LENGTH)
            phi = jr.uniform(k_dir, (K, 3), dtype, -math.pi, math.pi)
        d = jnp.cos(phi)[..., None] * R[None, :, :, 0] + jnp.sin(phi)[..., None] * R[None, :, :, 1]
        new = xy[None] + length[..., None] * d[..., :2]  # (K, 3, 2)
        cands = jnp.where(movers_now[None, :, None], new, xy[None])
        # The current formation is checked too: that is the initial formation's check at
        # the first step, at the cost of one extra candidate.
        mask, over, mutual = _formations_ok(
            scenario, jnp.concatenate([xy[None], cands]), R_over, t_over
        )
        best = 0 if fixed else jnp.argmax(mask[1:])
        xy = cands[best]
        feasible = feasible & mask[1 + best] & (mask[0] | ~first)
        # Sightings of the current and of the chosen formation, reused for the pixels.
        vis = (over[0], mutual[0], over[1 + best], mutual[1 + best])
        return (xy, feasible), (xy, vis)

    first = np.arange(steps - 1) == 0
    (_, feasible), (xy_moved, vis) = jax.lax.scan(
        one_step,
        (xy0, jnp.array(True)),
        (
            jr.split(k_moves, steps - 1),
            jnp.asarray(mover_mask),
            jnp.asarray(first),
            fixed_moves,
        ),
    )
    xy_all = jnp.concatenate([xy0[None], xy_moved])  # (steps, 3, 2)
    R_b, p_b = _robot_frames(scenario, xy_all)  # (steps, 3, 3, 3), (steps, 3, 3)

    # 3. Observations.
    rel = _relative_points(R_b, p_b)  # (steps, 3, 3, 3): robot j in robot i's body frame
    p_over = jnp.einsum("ab,kja->kjb", R_over, p_b - t_over[None, None, :])
    over_vis = jnp.concatenate([vis[0][:1], vis[2]])  # (steps, 3)
    mutual_vis = jnp.concatenate([vis[1][:1], vis[3]])  # (steps, 3, 3)
    eye = jnp.broadcast_to(np.eye(3, dtype=bool)[:, :, None], rel.shape)
    # Dummy target (straight ahead) on the diagonal, masked below.
    ahead = jnp.broadcast_to(jnp.array([1.0, 0.0, 0.0], dtype), rel.shape)
    rel = jnp.where(eye, ahead, rel)
    M_ptz = _mat(R_BODY_PTZ, dtype)
    M_omni = _mat(R_BODY_OMNI, dtype)
    k_ptz, k_omni = jr.split(k_mutual)
    # PTZ: body -> base frame, project, noise, unproject (base-frame bearing), -> body.
    uv_ptz = scenario.ptz.project(jnp.einsum("ab,...a->...b", M_ptz, rel[:, 0]))
    uv_ptz = uv_ptz + _pixel_noise(scenario, k_ptz, uv_ptz.shape[:-1], dtype)
    b_ptz = jnp.einsum("ab,...b->...a", M_ptz, scenario.ptz.unproject(uv_ptz))
    # Omni cameras (C2, C3).
    uv_omni = _omni_call(scenario, "project", jnp.einsum("ab,...a->...b", M_omni, rel[:, 1:]))
    uv_omni = uv_omni + _pixel_noise(scenario, k_omni, uv_omni.shape[:-1], dtype)
    b_omni = jnp.einsum("ab,...b->...a", M_omni, _omni_call(scenario, "unproject", uv_omni))
    mutual = jnp.where(eye, 0.0, jnp.concatenate([b_ptz[:, None], b_omni], axis=1))
    mutual_pixels = jnp.concatenate([uv_ptz[:, None], uv_omni], axis=1)
    mutual_pixels = jnp.where(mutual_vis[..., None], mutual_pixels, jnp.nan)
    over_uv = scenario.overhead.project(p_over)
    over_uv = over_uv + _pixel_noise(scenario, k_over, over_uv.shape[:-1], dtype)
    over_b = scenario.overhead.unproject(over_uv)
    over_uv = jnp.where(over_vis[..., None], over_uv, jnp.nan)

    # 4. Odometry.
    dist = jnp.linalg.norm(p_b[starts + 1, movers] - p_b[starts, movers], axis=-1)
    rel_sigma = scenario.odometry_sigma_rel.astype(dtype)
    measured = dist * (1.0 + rel_sigma * jr.normal(k_odo, dist.shape, dtype))
    odometry_sigma = rel_sigma * measured

    # Truth in W = C1's body frame at the start. Composed as matrices, not with jaxlie's
    # `@`, which promotes float32 to float64 under x64 (its `apply` pads with a default
    # dtype zero).
    R0, p0 = R_b[0, 0], p_b[0, 0]
    R_wb = jnp.einsum("ba,kibc->kiac", R0, R_b)
    p_wb = jnp.einsum("ba,kib->kia", R0, p_b - p0[None, None, :])
    # One batched matrix -> quaternion conversion for every pose (a smaller program).
    n = 3 * steps
    Rs = jnp.concatenate(
        [R_wb.reshape(n, 3, 3), R_b.reshape(n, 3, 3), jnp.stack([R0.T @ R_over, R_climber, R_over])]
    )
    ps = jnp.concatenate(
        [p_wb.reshape(n, 3), p_b.reshape(n, 3), jnp.stack([R0.T @ (t_over - p0), t_over, t_over])]
    )
    T_all = jax.vmap(_se3)(Rs, ps)

    def part(i, shape=()):
        return jax.tree.map(lambda x: x[i].reshape(shape + x.shape[1:]), T_all)

    T_world_body = part(slice(0, n), (steps, 3))
    T_env_body = part(slice(n, 2 * n), (steps, 3))
    T_world_overhead, T_env_climber, T_env_overhead = part(2 * n), part(2 * n + 1), part(2 * n + 2)
    T_env_world = part(n)  # C1 at step 0
    poses = CyclePoses(T_world_body=T_world_body, T_world_overhead=T_world_overhead)
    truth = CycleTruth(
        poses=poses,
        T_env_world=T_env_world,
        T_env_body=T_env_body,
        T_env_overhead=T_env_overhead,
        T_env_climber=T_env_climber,
        move_distances=dist,
    )
    obs = CycleObservations(
        mutual=mutual,
        overhead=over_b,
        odometry=measured,
        odometry_sigma=odometry_sigma,
        strategy=strategy,
        overhead_visible=over_vis,
        mutual_pixels=mutual_pixels,
        overhead_pixels=over_uv,
    )
    return truth, obs, feasible
