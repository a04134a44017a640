r"""Simulation of one localization cycle: formations, moves, and every measurement.

[`jaxloc.simulate_cycle`][] places the team in the [`jaxloc.Scenario`][]'s world, draws
the strategy's moves with branch-free resampling until every required camera sees every
required robot, and synthesizes every observation through the camera models, the path a
real image takes: point in the observing camera's frame -> `camera.project` -> pixel
noise -> `camera.unproject` -> back through the mount. It returns the ground truth, the
[`jaxloc.CycleObservations`][] the estimators consume, and a feasibility flag.

Frames: environment `E` (z up; see [`jaxloc.formation_xy`][]), robot body frames (x
forward, y left, z up along the surface normal), camera frames through the rig's mounts
(`scenario.rig`), and the cycle's world frame `W` = C1's body frame at the start of the
cycle (DESIGN §1). Every sighting goes through the one projection path of
`jaxloc._cycle.sightings` (marker offsets and camera offsets included).
"""

import functools as ft
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import jaxlie
import numpy as np
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from .._core.compiler import jit
from .._cycle.layout import move_start_step, moving_robot, num_steps
from .._cycle.observations import CycleObservations, CyclePoses, ODOMETRY_SIGMA_FLOOR
from .._cycle.rig import ground_cameras_apply, Rig
from .._cycle.sightings import in_body, marker_in_world, mutual_points
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
    """`scenario` with no pixel noise (`rig.pixel_sigma = 0`) and exact odometry
    (`odometry_sigma_rel = 0`), same dtype: its cycles' observations are exact (for
    exactness tests of the estimators)."""
    return eqx.tree_at(
        lambda s: (s.rig.pixel_sigma, s.odometry_sigma_rel),
        scenario,
        (jnp.zeros_like(scenario.rig.pixel_sigma), jnp.zeros_like(scenario.odometry_sigma_rel)),
    )


def _robot_frames(scenario: Scenario, xy: Float[Array, "*s 3 2"]):
    """Body frames `(R_env_body (*s, 3, 3, 3), p_env_body (*s, 3, 3))` of C1, C2, C3."""
    headings = jnp.broadcast_to(scenario.headings.astype(xy.dtype), xy.shape[:-1])
    return body_frame_on_surface(scenario.ground, xy, headings)


def overhead_frames(scenario: Scenario, overhead_xy, overhead_heading, dtype):
    """The climbing robot's body frame on the ceiling and its camera's optical frame,
    `(R_climber, p_climber, R_overhead, p_overhead)` in `E` (through the rig's mount)."""
    R_climber, p_climber = body_frame_on_surface(
        scenario.ceiling, overhead_xy.astype(dtype), overhead_heading.astype(dtype)
    )
    R_m = scenario.rig.mount_rotations()[0].astype(dtype)
    t_m = scenario.rig.mount_translations()[0].astype(dtype)
    return R_climber, p_climber, R_climber @ R_m, p_climber + R_climber @ t_m


def camera_points(scenario: Scenario, R, p, R_over, p_over):
    """Every sighting of one or more formations in its camera's frame, through the rig's
    mounts and markers (`jaxloc._cycle.sightings`): `(mutual (*s, 3, 3, 3), overhead
    (*s, 3, 3))`, `mutual[..., i, j]` robot `j`'s marker in robot `i`'s camera (diagonal
    a dummy point ahead), `overhead[..., j]` robot `j`'s marker in the overhead camera."""
    rig = scenario.rig
    dtype = p.dtype
    markers = rig.markers[1:].astype(dtype)
    mutual, _ = mutual_points(
        R, p, rig.mount_rotations()[1:].astype(dtype), rig.mount_translations()[1:].astype(dtype),
        markers,
    )  # fmt: skip
    return mutual, in_body(R_over, p_over, marker_in_world(R, p, markers))


def _observer_first(x):
    """`(*s, 3 observers, 3, 3)` -> `(3 observers, *s, 3, 3)`."""
    return jnp.moveaxis(x, -3, 0)


def _observer_back(x, axis):
    return jnp.moveaxis(x, 0, axis)


def sightings_in_view(scenario: Scenario, mutual_cam, overhead_cam):
    """Which sightings the cameras make, and whether the scenario's required ones exist.

    **Arguments:** camera-frame points from [`camera_points`][]: `mutual_cam`
    `(*s, 3, 3, 3)`, `overhead_cam` `(*s, 3, 3)`.

    **Returns:** `(ok (*s,), overhead_in_view (*s, 3), mutual_in_view (*s, 3, 3))`:
    `ok` holds the `require_*` checks (the overhead camera sees all three robots; C1's
    camera sees C2 and C3; C2's and C3's see the two others)."""
    rig = scenario.rig
    over = rig.overhead.in_view(overhead_cam)
    mutual = _observer_back(
        ground_cameras_apply(rig, lambda cam, x: cam.in_view(x), _observer_first(mutual_cam)),
        -2,
    )
    off = jnp.broadcast_to(~np.eye(3, dtype=bool), mutual.shape)
    ok = jnp.ones(mutual.shape[:-2], dtype=bool)
    if scenario.require_overhead:
        ok = ok & jnp.all(over, axis=-1)
    if scenario.require_ptz:
        ok = ok & jnp.all(mutual[..., 0, 1:], axis=-1)
    if scenario.require_omni:
        ok = ok & jnp.all(jnp.where(off[..., 1:, :], mutual[..., 1:, :], True), axis=(-2, -1))
    return ok, over, mutual & off


def _formations_ok(scenario: Scenario, xy, R_over, p_over):
    """Feasibility of formations `xy` `(n, 3, 2)`: required sightings and separation.

    Returns `(ok (n,), overhead_in_view (n, 3), mutual_in_view (n, 3, 3))`."""
    R, p = _robot_frames(scenario, xy)
    ok, over, mutual = sightings_in_view(scenario, *camera_points(scenario, R, p, R_over, p_over))
    d = p[:, :, None, :] - p[:, None, :, :]
    dist2 = jnp.sum(d * d, axis=-1)
    sep = scenario.min_separation.astype(xy.dtype)
    diag = jnp.broadcast_to(np.eye(3, dtype=bool), dist2.shape)
    ok = ok & jnp.all(jnp.where(diag, True, dist2 >= sep * sep), axis=(-2, -1))
    return ok, over, mutual


def xy_sides(xy: Float[Array, "*s 3 2"]) -> Float[Array, "*s 3"]:
    """Side lengths C1–C2, C1–C3, C2–C3 (m) of formations `xy` in the `E` x-y plane."""
    d = xy[..., jnp.array([1, 2, 2]), :] - xy[..., jnp.array([0, 0, 1]), :]
    return jnp.sqrt(jnp.sum(d * d, axis=-1))


def _pixel_noise(rig: Rig, sigma, key, shape, dtype):
    """Pixel noise of shape `shape + (2,)` with scale `sigma` (px, broadcasting against
    `shape`), under the rig's noise model."""
    sigma = jnp.broadcast_to(jnp.asarray(sigma, dtype), shape)
    if rig.noise_model == "paper":
        # Sec. IV.A: an error of N(0, 2) px "uniformly distributed in isotropic
        # directions": signed radius ~ N(0, sigma), direction ~ U[0, 2 pi).
        k_r, k_a = jr.split(key)
        r = sigma * jr.normal(k_r, shape, dtype)
        a = jr.uniform(k_a, shape, dtype, 0.0, 2.0 * math.pi)
        return jnp.stack([r * jnp.cos(a), r * jnp.sin(a)], axis=-1)
    return sigma[..., None] * jr.normal(key, shape + (2,), dtype)


def _se3(R: Float[Array, "3 3"], p: Float[Array, "3"]) -> jaxlie.SE3:
    return jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.from_matrix(R), p)


def _move_candidates(scenario: Scenario, key, xy, movers_now, fixed_now, length_dist, dtype):
    """Candidate formations `(K, 3, 2)` (m, `E` x-y) after one step's moves from `xy`
    `(3, 2)`: the fixed move (`K = 1`; `fixed_now` `(3, 2)` is each robot's (length,
    direction)), or `scenario.move_candidates` random ones, lengths (m) drawn from
    `length_dist = (mean, std)`. Only `movers_now` `(3,)` move, each along its body
    frame's heading rotated by the move's direction."""
    R, _ = _robot_frames(scenario, xy)  # (3, 3, 3)
    if scenario.moves is not None:
        # The given moves, exactly: one candidate, never resampled (an infeasible one
        # makes the cycle infeasible).
        length, phi = fixed_now[None, :, 0], fixed_now[None, :, 1]  # (1, 3)
    else:
        K = scenario.move_candidates
        mean, std = length_dist
        k_len, k_dir = jr.split(key)
        # Candidates are drawn for all three robots (cheap) and kept for the movers
        # only, so that one scan body serves every step of both strategies.
        length = jnp.maximum(mean + std * jr.normal(k_len, (K, 3), dtype), MIN_MOVE_LENGTH)
        phi = jr.uniform(k_dir, (K, 3), dtype, -math.pi, math.pi)
    d = jnp.cos(phi)[..., None] * R[None, :, :, 0] + jnp.sin(phi)[..., None] * R[None, :, :, 1]
    new = xy[None] + length[..., None] * d[..., :2]  # (K, 3, 2)
    return jnp.where(movers_now[None, :, None], new, xy[None])


def _choose_candidate(scenario: Scenario, cands, feasible, dtype):
    """Index of the candidate formation to move to, among `cands` `(K, 3, 2)` with
    feasibility `feasible` `(K,)`: the fixed move, the first feasible one, or (formation
    keeping) the feasible one whose sorted sides are nearest `formation_sides`."""
    if scenario.moves is not None:
        return 0
    if scenario.formation_sides is None:
        return jnp.argmax(feasible)
    sides = jnp.sort(xy_sides(cands), axis=-1)
    keep = jnp.sort(scenario.formation_sides.astype(dtype))[None]
    change = jnp.sum((sides - keep) ** 2, -1)
    return jnp.argmin(jnp.where(feasible, change, jnp.inf))


def _move_step(scenario: Scenario, R_over, p_over, length_dist, dtype, carry, inputs):
    """One step of `_draw_moves`' scan: move from the formation `xy` `(3, 2)` to a chosen
    candidate; carry `(xy, feasible)`, output `(xy, sightings in view)`."""
    xy, feasible = carry
    step_key, movers_now, first, fixed_now = inputs
    cands = _move_candidates(scenario, step_key, xy, movers_now, fixed_now, length_dist, dtype)
    # The current formation is checked too: that is the initial formation's check at
    # the first step, at the cost of one extra candidate.
    mask, over, mutual = _formations_ok(
        scenario, jnp.concatenate([xy[None], cands]), R_over, p_over
    )
    best = _choose_candidate(scenario, cands, mask[1:], dtype)
    xy = cands[best]
    feasible = feasible & mask[1 + best] & (mask[0] | ~first)
    # Sightings of the current and of the chosen formation, reused for the pixels.
    vis = (over[0], mutual[0], over[1 + best], mutual[1 + best])
    return (xy, feasible), (xy, vis)


def _draw_moves(scenario: Scenario, key, xy0, R_over, p_over, dtype):
    """Every step's formation after the strategy's moves (branch-free resampling, or the
    fixed moves), `(steps, 3, 2)`, whether every formation is feasible, and the sightings
    in view at every step `(overhead (steps, 3), mutual (steps, 3, 3))`."""
    strategy = scenario.strategy
    steps, movers, starts = num_steps(strategy), moving_robot(strategy), move_start_step(strategy)
    # Which robots move at each step, (steps - 1, 3): one (sequential) or two (concurrent).
    mover_mask = np.zeros((steps - 1, 3), dtype=bool)
    mover_mask[starts, movers] = True
    length_dist = (scenario.move_mean.astype(dtype), scenario.move_std.astype(dtype))
    if scenario.moves is not None:  # static: the pytree structure decides
        # (length, direction) of each robot at each step (zeros for robots that stay).
        fixed_moves = jnp.zeros((steps - 1, 3, 2), dtype).at[starts, movers].set(
            scenario.moves.astype(dtype)
        )
    else:
        fixed_moves = None  # no scan input: the random path's program is unchanged
    first = np.arange(steps - 1) == 0
    (_, feasible), (xy_moved, vis) = jax.lax.scan(
        ft.partial(_move_step, scenario, R_over, p_over, length_dist, dtype),
        (xy0, jnp.array(True)),
        (jr.split(key, steps - 1), jnp.asarray(mover_mask), jnp.asarray(first), fixed_moves),
    )
    xy_all = jnp.concatenate([xy0[None], xy_moved])  # (steps, 3, 2)
    over_vis = jnp.concatenate([vis[0][:1], vis[2]])  # (steps, 3)
    mutual_vis = jnp.concatenate([vis[1][:1], vis[3]])  # (steps, 3, 3)
    return xy_all, feasible, over_vis, mutual_vis


def _observe(scenario: Scenario, keys, mutual_cam, over_cam, mutual_vis, over_vis, dtype):
    """Pixels and bearings of every sighting: project, add pixel noise, unproject, back
    through the mount. Sightings not in view are NaN (missing), the diagonal zero."""
    rig = scenario.rig
    k_mutual, k_over = keys
    sigma = rig.pixel_sigma.astype(dtype)
    k_ptz, k_omni = jr.split(k_mutual)
    uv = ground_cameras_apply(rig, lambda cam, x: cam.project(x), _observer_first(mutual_cam))
    steps = uv.shape[1]
    # Noise drawn for C1's camera, then for C2's and C3's together (the draws of one
    # `(steps, 2, 3)` call: a seeded study's pixels do not depend on how the cameras
    # are batched).
    noise_ptz = _pixel_noise(rig, sigma[1], k_ptz, (steps, 3), dtype)
    noise_omni = _pixel_noise(rig, sigma[2:, None], k_omni, (steps, 2, 3), dtype)
    uv = uv + jnp.concatenate([noise_ptz[None], jnp.moveaxis(noise_omni, 1, 0)])
    b_cam = ground_cameras_apply(rig, lambda cam, x: cam.unproject(x), uv)
    mount_R = rig.mount_rotations()[1:].astype(dtype)
    b_body = jnp.sum(mount_R[:, None, None] * b_cam[..., None, :], axis=-1)  # R_m b
    mutual_pixels, mutual = _observer_back(uv, 1), _observer_back(b_body, 1)
    eye = np.eye(3, dtype=bool)[None, :, :, None]
    mutual = jnp.where(eye, 0.0, jnp.where(mutual_vis[..., None], mutual, jnp.nan))
    mutual_pixels = jnp.where(mutual_vis[..., None], mutual_pixels, jnp.nan)
    over_uv = rig.overhead.project(over_cam)
    over_uv = over_uv + _pixel_noise(rig, sigma[0], k_over, over_uv.shape[:-1], dtype)
    over_b = rig.overhead.unproject(over_uv)
    over_b = jnp.where(over_vis[..., None], over_b, jnp.nan)
    over_uv = jnp.where(over_vis[..., None], over_uv, jnp.nan)
    return mutual, mutual_pixels, over_b, over_uv


def _odometry(scenario: Scenario, key, p_b, dtype):
    """True move distances between the movers' body origins, their noisy measurements
    and the measurements' sigmas (a noise-free scenario reports a sigma of
    `ODOMETRY_SIGMA_FLOOR` times the longest move: exact, but a valid observation)."""
    starts, movers = move_start_step(scenario.strategy), moving_robot(scenario.strategy)
    dist = jnp.linalg.norm(p_b[starts + 1, movers] - p_b[starts, movers], axis=-1)
    rel_sigma = scenario.odometry_sigma_rel.astype(dtype)
    measured = dist * (1.0 + rel_sigma * jr.normal(key, dist.shape, dtype))
    floor = ODOMETRY_SIGMA_FLOOR * jnp.max(jnp.abs(measured))
    return dist, measured, jnp.maximum(rel_sigma * measured, floor)


def _truth(R_b, p_b, frames, dist) -> CycleTruth:
    """The cycle's true poses in `W` (C1's body frame at the start) and in `E`. Composed
    as matrices, not with jaxlie's `@`, which promotes float32 to float64 under x64 (its
    `apply` pads with a default dtype zero)."""
    R_climber, p_climber, R_over, p_over = frames
    steps = p_b.shape[0]
    R0, p0 = R_b[0, 0], p_b[0, 0]
    R_wb = jnp.einsum("ba,kibc->kiac", R0, R_b)
    p_wb = jnp.einsum("ba,kib->kia", R0, p_b - p0[None, None, :])
    # One batched matrix -> quaternion conversion for every pose (a smaller program).
    n = 3 * steps
    Rs = jnp.concatenate(
        [R_wb.reshape(n, 3, 3), R_b.reshape(n, 3, 3), jnp.stack([R0.T @ R_over, R_climber, R_over])]
    )
    p_special = jnp.stack([R0.T @ (p_over - p0), p_climber, p_over])
    ps = jnp.concatenate([p_wb.reshape(n, 3), p_b.reshape(n, 3), p_special])
    T_all = jax.vmap(_se3)(Rs, ps)

    def part(i, shape=()):
        return jax.tree.map(lambda x: x[i].reshape(shape + x.shape[1:]), T_all)

    T_world_overhead, T_env_climber, T_env_overhead = part(2 * n), part(2 * n + 1), part(2 * n + 2)
    poses = CyclePoses(part(slice(0, n), (steps, 3)), T_world_overhead)
    return CycleTruth(
        poses=poses,
        T_env_world=part(n),  # C1 at step 0
        T_env_body=part(slice(n, 2 * n), (steps, 3)),
        T_env_overhead=T_env_overhead,
        T_env_climber=T_env_climber,
        move_distances=dist,
    )


def simulate_cycle(
    scenario: Scenario, key: PRNGKeyArray
) -> tuple[CycleTruth, CycleObservations, Bool[Array, ""]]:
    r"""Simulate one localization cycle of `scenario`.

    1. **Placement.** Ground robots at `scenario.formation_xy()` (`initial_xy` if
       given, else [`jaxloc.formation_xy`][]`(base, side)`) on `scenario.ground` with
       `scenario.headings`; the climbing robot at `overhead_xy` on `scenario.ceiling`
       with `overhead_heading`; the overhead camera's optical frame is its body pose
       composed with the rig's mount of C. Every pose via
       [`jaxloc.body_pose_on_surface`][].
    2. **Moves** (DESIGN §3; order from `jaxloc._cycle.layout.moving_robot`): length
       $L \sim N(\text{move\_mean}, \text{move\_std})$ clipped to >= 0.05 m, direction
       uniform in the robot's tangent plane, $d = \cos\varphi\,x_b + \sin\varphi\,y_b$.
       The end point is the surface point below/above `xy + L d_xy` (a straight step in
       the tangent plane dropped onto the surface, not a geodesic: the difference is a
       few millimetres at most on the paper's gently curved ground), with the heading
       unchanged. Branch-free resampling: `move_candidates` candidates are drawn at once
       for each step (for the concurrent strategy a candidate is a *pair* of moves of C2
       and C3), each is checked for the required sightings of the formation after the
       step (`scenario.require_*`: the overhead camera sees all three robots; C1's PTZ
       sees C2 and C3; each omni camera sees the two others within its elevation band)
       and for `min_separation`, and the first feasible candidate is taken (with
       `formation_sides`, the feasible one whose triangle's sides are closest to them). If none is
       feasible (or the initial formation is not), the first candidate is kept and the
       returned flag is `False`. **Fixed moves** (`scenario.moves` given): move `m` has
       exactly length `moves[m, 0]` and direction `moves[m, 1]` (no clipping, no
       resampling); if a step's formation breaks a requirement the flag is `False`.
    3. **Observations** through the rig (`scenario.rig`): the target robot's marker in
       the observer's camera frame, through its mount (`jaxloc._cycle.sightings`),
       `project`, pixel noise of the camera's `pixel_sigma` (`noise_model` "paper":
       radius ~ N(0, sigma), uniform direction; "gaussian": N(0, sigma^2) per axis),
       `unproject`, rotated back by the mount into the body frame (mutual) or kept in
       the overhead camera's frame (overhead). Visibility decisions use the true points.
       A sighting outside its camera's view is missing: NaN pixels and NaN bearings
       (`overhead_visible` False for the overhead camera); the diagonal `i == j` has
       NaN pixels and zero bearings.
    4. **Odometry**: the true straight-line distance between each move's start and end
       body origins times $(1 + \text{odometry\_sigma\_rel}\,N(0, 1))$;
       `odometry_sigma = odometry_sigma_rel * measured` (at least 1e-6 of the longest
       move: exact odometry of a noise-free scenario is still a valid observation).

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
    return _simulate_cycle(scenario, key)


@jit(inline=True)
def _simulate_cycle(scenario: Scenario, key: PRNGKeyArray):
    # Compiled once per scenario structure for eager callers (op by op, a call took
    # seconds); inlined into a caller's trace.
    dtype = jnp.result_type(scenario.base.dtype, scenario.side.dtype)
    k_moves, k_mutual, k_over, k_odo = jr.split(key, 4)
    frames = overhead_frames(scenario, scenario.overhead_xy, scenario.overhead_heading, dtype)
    _, _, R_over, p_over = frames
    xy0 = scenario.formation_xy().astype(dtype)
    xy_all, feasible, over_vis, mutual_vis = _draw_moves(
        scenario, k_moves, xy0, R_over, p_over, dtype
    )
    R_b, p_b = _robot_frames(scenario, xy_all)  # (steps, 3, 3, 3), (steps, 3, 3)
    mutual_cam, over_cam = camera_points(scenario, R_b, p_b, R_over, p_over)
    mutual, mutual_pixels, over_b, over_uv = _observe(
        scenario, (k_mutual, k_over), mutual_cam, over_cam, mutual_vis, over_vis, dtype
    )
    dist, measured, odometry_sigma = _odometry(scenario, k_odo, p_b, dtype)
    obs = CycleObservations(
        mutual=mutual,
        overhead=over_b,
        odometry=measured,
        odometry_sigma=odometry_sigma,
        strategy=scenario.strategy,
        overhead_visible=over_vis,
        mutual_pixels=mutual_pixels,
        overhead_pixels=over_uv,
    )
    return _truth(R_b, p_b, frames, dist), obs, feasible
