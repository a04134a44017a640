r"""Simulation of K cycles of a [`jaxloc.TrackScenario`][]: [`jaxloc.simulate_track`][].

Each cycle is [`jaxloc.simulate_cycle`][] of the cycle scenario with its formation set to
where the previous cycle left the ground robots (their headings never change: a move keeps
the heading) and the climbing robot where it moved (see `jaxloc._track.scenario` for its
motion and odometry models). The truth is given in each cycle's own frame `W_k` (C1's
body frame at the start of cycle `k`) and in the first cycle's frame `W_0`, where tracking
reports every estimate.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import jaxlie
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from .._core.compiler import jit
from .._core.numerics import safe_norm
from .._core.poses import compose, inverse, quaternion_matrix, rplus
from .._cycle.observations import CycleObservations
from .._cycle.sightings import in_body, marker_in_world
from .._sim.simulate import CycleTruth, overhead_frames, simulate_cycle, xy_sides
from .._sim.world import body_frame_on_surface
from .frames import plane_normal
from .scenario import TrackScenario


#: Smallest standard deviation of the climbing robot's odometry (m for the translation,
#: rad for the rotation): a noise-free simulation's exact odometry is still a valid,
#: finite-weight observation.
CLIMBER_SIGMA_FLOOR = 1e-6


class TrackTruth(eqx.Module):
    """Ground truth of K simulated cycles.

    **Fields** (leading axis K, the cycles):

    - `cycles`: each cycle's [`jaxloc.CycleTruth`][] (poses in its own frame `W_k`, and in
      the environment frame `E`).
    - `T_world_body`: every ground robot's body pose at every step in the first cycle's
      frame `W_0`, `jaxlie.SE3` of batch `(K, steps, 3)`.
    - `T_world_overhead`: the overhead camera's optical-frame pose in `W_0`, `(K,)`.
    - `T_world_climber`: the climbing robot's body pose in `W_0`, `(K,)`.
    - `height`: the overhead camera centre's height above the plane of the three ground
      robots' markers at the cycle's first step (m), `(K,)`.
    """

    cycles: CycleTruth
    T_world_body: jaxlie.SE3
    T_world_overhead: jaxlie.SE3
    T_world_climber: jaxlie.SE3
    height: Float[Array, " K"]


class TrackObservations(eqx.Module):
    """Everything measured over K cycles.

    **Fields:**

    - `cycles`: each cycle's [`jaxloc.CycleObservations`][], leading axis K.
    - `climber_odometry`: the climbing robot's measured body motion into each cycle,
      `Z_k ~ T_body(k-1)^-1 T_body(k)` (`wxyz_xyz`), `(K, 7)`; row 0 (no motion before the
      first cycle) is the identity and unused.
    - `climber_odometry_sigma`: its per-axis standard deviation (`v` in m, `omega` in rad),
      `(K, 6)`; row 0 unused.
    - `height`, `height_sigma`: the measured height of the overhead camera above the
      ground robots' plane at the first cycle's first step, and its sigma (m).
    - `tilt_sigma`: sigma (rad) of the prior that the climbing robot's body z is along
      that plane's normal.
    """

    cycles: CycleObservations
    climber_odometry: Float[Array, "K 7"]
    climber_odometry_sigma: Float[Array, "K 6"]
    height: Float[Array, ""]
    height_sigma: Float[Array, ""]
    tilt_sigma: Float[Array, ""]


def _cycle_scenario(track: TrackScenario, xy, overhead_xy, overhead_heading):
    """The cycle scenario started at formation `xy` `(3, 2)` with the climbing robot at
    `overhead_xy`, `overhead_heading`, keeping the initial triangle's shape if asked."""
    s = track.scenario
    shape = s.formation_sides
    if shape is None and track.keep_formation:
        shape = xy_sides(s.formation_xy().astype(xy.dtype))
    return eqx.tree_at(
        lambda s: (s.initial_xy, s.overhead_xy, s.overhead_heading, s.formation_sides),
        s,
        (xy, overhead_xy, overhead_heading, shape),
        is_leaf=lambda x: x is None,
    )


def markers_env(track: TrackScenario, xy: Float[Array, "3 2"]) -> Float[Array, "3 3"]:
    """The ground robots' markers in `E` for formation `xy` (headings of the scenario)."""
    s = track.scenario
    dtype = xy.dtype
    R, p = body_frame_on_surface(s.ground, xy, s.headings.astype(dtype))
    return marker_in_world(R, p, s.rig.markers[1:].astype(dtype))


def plane_height(markers: Float[Array, "3 3"], point: Float[Array, "3"]) -> Float[Array, ""]:
    """Distance of `point` from the plane of three markers, positive on the side of the
    plane's upward normal (the normal's z > 0 in `E`; the normal of [`plane_normal`][])."""
    n = plane_normal(markers, jnp.asarray([0.0, 0.0, 1.0], markers.dtype))
    return jnp.sum(n * (point - markers[0]))


def _climber_step(track: TrackScenario, key, c_xy, heading0, xy_next, target, dtype):
    """The climbing robot's next place `(xy, heading)` and whether the overhead camera sees
    the three ground robots at `xy_next` from there: of `move_candidates` draws (headings
    about its initial heading `heading0`), the one nearest `target` that sees them."""
    s = track.scenario
    K = s.move_candidates
    k_xy, k_turn = jr.split(key)
    step = target[None] - c_xy[None] + track.climber_step_std.astype(dtype) * jr.normal(
        k_xy, (K, 2), dtype
    )
    length = safe_norm(step)
    limit = track.climber_step_max.astype(dtype)
    shrink = jnp.where(length > limit, limit / jnp.where(length > 0, length, 1.0), 1.0)
    cand_xy = c_xy[None] + step * shrink[:, None]
    cand_heading = heading0 + track.climber_turn_std.astype(dtype) * jr.normal(k_turn, (K,), dtype)
    markers = markers_env(track, xy_next)

    def sees(xy, heading):
        _, _, R_over, p_over = overhead_frames(s, xy, heading, dtype)
        return jnp.all(s.rig.overhead.in_view(in_body(R_over, p_over, markers)))

    ok = jax.vmap(sees)(cand_xy, cand_heading)
    miss = jnp.sum((cand_xy - target[None]) ** 2, axis=-1)
    best = jnp.argmin(jnp.where(ok, miss, jnp.inf))
    return cand_xy[best], cand_heading[best], ok[best]


def _climber_odometry(track: TrackScenario, key, T_prev: jaxlie.SE3, T_next: jaxlie.SE3):
    """Noisy relative body pose and its per-axis sigma (module docstring of
    `jaxloc._track.scenario`)."""
    dtype = T_prev.wxyz_xyz.dtype
    Z = compose(inverse(T_prev), T_next)
    dist = safe_norm(Z.translation())
    s_v = jnp.maximum(track.climber_odometry_sigma_rel.astype(dtype) * dist, CLIMBER_SIGMA_FLOOR)
    s_r = jnp.maximum(track.climber_odometry_rotation_sigma.astype(dtype), CLIMBER_SIGMA_FLOOR)
    sigma = jnp.concatenate([jnp.full((3,), s_v, dtype), jnp.full((3,), s_r, dtype)])
    noise = sigma * jr.normal(key, (6,), dtype)
    # A noise-free simulation reports the exact motion (its floor sigma is a weight only).
    noise = jnp.where(sigma > CLIMBER_SIGMA_FLOOR, noise, 0.0)
    return rplus(Z, noise).wxyz_xyz, sigma


@jit(inline=True)
def simulate_track(
    track: TrackScenario, key: PRNGKeyArray, cycles: int
) -> tuple[TrackTruth, TrackObservations, Bool[Array, " K"]]:
    r"""Simulate `cycles` consecutive cycles of a multi-cycle scenario.

    Cycle `k + 1` starts with the ground robots where cycle `k` left them and the climbing
    robot at its next place (see `jaxloc._track.scenario`); every cycle is
    [`jaxloc.simulate_cycle`][] of the cycle scenario from there, with its own key. The
    climbing robot's odometry into cycle `k` and the first cycle's height measurement
    (noise `height_prior_sigma`) are drawn from their models.

    Pure, for one run: batch with `jax.vmap`. `cycles` is a static Python int.

    **Returns:** `(truth, observations, feasible)`: a [`jaxloc.TrackTruth`][], a
    [`jaxloc.TrackObservations`][], and `feasible` `(K,)`, whether every formation of
    every cycle up to and including `k` kept the required sightings (and the climbing
    robot found a place seeing the team): once False, it stays False.
    """
    if not isinstance(cycles, int) or isinstance(cycles, bool) or cycles < 1:
        raise ValueError(f"`cycles` must be a positive int; got {cycles!r}.")
    s = track.scenario
    dtype = s.base.dtype
    xy0 = s.formation_xy().astype(dtype)
    c_xy0 = s.overhead_xy.astype(dtype)
    k_height, k_cycles, k_odo = jr.split(key, 3)

    heading0 = s.overhead_heading.astype(dtype)

    def one_cycle(carry, key_k):
        xy, c_xy, c_heading, feasible = carry
        k_sim, k_move = jr.split(key_k)
        truth, obs, cycle_ok = simulate_cycle(_cycle_scenario(track, xy, c_xy, c_heading), k_sim)
        xy_next = truth.T_env_body.translation()[-1, :, :2]
        target = 0.5 * (jnp.min(xy_next, axis=0) + jnp.max(xy_next, axis=0))
        n_xy, n_heading, sees = _climber_step(
            track, k_move, c_xy, heading0, xy_next, target, dtype
        )
        feasible = feasible & cycle_ok
        return (xy_next, n_xy, n_heading, feasible & sees), (truth, obs, feasible)

    init = (xy0, c_xy0, s.overhead_heading.astype(dtype), jnp.array(True))
    _, (truth, obs, feasible) = jax.lax.scan(one_cycle, init, jr.split(k_cycles, cycles))

    # The climbing robot's odometry into each cycle (row 0: none).
    T_climb = truth.T_env_climber.wxyz_xyz
    odo_keys = jr.split(k_odo, cycles)
    Z, sigma = jax.vmap(
        lambda a, b, k: _climber_odometry(track, k, jaxlie.SE3(a), jaxlie.SE3(b))
    )(jnp.concatenate([T_climb[:1], T_climb[:-1]]), T_climb, odo_keys)
    ident = jnp.zeros((1, 7), dtype).at[0, 0].set(1.0)
    Z = jnp.concatenate([ident, Z[1:]])
    sigma = sigma.at[0].set(1.0)

    # Truth in the first cycle's frame W_0.
    T_0_env = inverse(jaxlie.SE3(truth.T_env_world.wxyz_xyz[0]))

    def to_w0(T):
        return compose(T_0_env, jaxlie.SE3(T)).wxyz_xyz

    steps = truth.T_env_body.wxyz_xyz.shape[1]
    body = jax.vmap(to_w0)(truth.T_env_body.wxyz_xyz.reshape(-1, 7)).reshape(cycles, steps, 3, 7)
    over = jax.vmap(to_w0)(truth.T_env_overhead.wxyz_xyz)
    climber = jax.vmap(to_w0)(truth.T_env_climber.wxyz_xyz)
    markers = jax.vmap(lambda T: markers_env_of_poses(track, T))(truth.T_env_body.wxyz_xyz[:, 0])
    height = jax.vmap(plane_height)(markers, truth.T_env_overhead.translation())
    sigma_h = track.height_prior_sigma.astype(dtype)
    measured = height[0] + sigma_h * jr.normal(k_height, (), dtype)
    truth_k = TrackTruth(truth, jaxlie.SE3(body), jaxlie.SE3(over), jaxlie.SE3(climber), height)
    observations = TrackObservations(
        obs, Z, sigma, measured, sigma_h, track.tilt_prior_sigma.astype(dtype)
    )
    return truth_k, observations, feasible


def markers_env_of_poses(track: TrackScenario, T_env_body: Float[Array, "3 7"]):
    """The ground robots' markers in `E` from their body poses `(3, 7)`."""
    R = quaternion_matrix(T_env_body[:, :4])
    return marker_in_world(R, T_env_body[:, 4:], track.rig.markers[1:].astype(T_env_body.dtype))
