"""The sequential strategy's closed form (paper Sec. III.C): a chain of formations, one scale.

C2 moves, then C3, then C1 (4 steps). Each new formation is solved with respect to the
robot that has been still the longest (C3, then C1, then C2), and joined to the previous
one through the two robots that did not move: their distance fixes the new formation's
scale relative to the chain, and the reference robot's pose places it. One global scale
remains, fitted to the three odometry distances in closed form (weighted least squares).
"""

import jax
import jax.numpy as jnp
import jaxlie
from jaxtyping import Array, Float

from .._core.numerics import safe_norm
from .._core.poses import compose as compose_poses
from .._cycle.layout import moving_robot, reference_robots
from .._cycle.observations import CycleObservations
from .._model.measurements import move_lengths
from .mutual import cycle_bearings, mutual_steps


def odometry_weights(observations: CycleObservations) -> Float[Array, " moves"]:
    """Inverse-variance weights of the odometry distances, each sigma floored at 1e-6 of
    the largest distance (a noise-free simulation's exact odometry)."""
    sigma = observations.odometry_sigma
    floor = 1e-9 + 1e-6 * jnp.max(jnp.abs(observations.odometry))
    return 1.0 / jnp.maximum(sigma, floor) ** 2


def compose_scaled(T_w_ref: jaxlie.SE3, scale, T_ref_body: jaxlie.SE3) -> jaxlie.SE3:
    """`T_w_ref @ T_ref_body` for a batch `T_ref_body`, its translations times `scale`."""

    def one(wxyz_xyz):
        T = jaxlie.SE3(wxyz_xyz)
        T = jaxlie.SE3.from_rotation_and_translation(T.rotation(), scale * T.translation())
        return compose_poses(T_w_ref, T).wxyz_xyz

    return jaxlie.SE3(jax.vmap(one)(T_ref_body.wxyz_xyz))


def scale_translations(T: jaxlie.SE3, scale) -> jaxlie.SE3:
    """`T` with its translations multiplied by `scale`."""
    return jaxlie.SE3(T.wxyz_xyz.at[..., 4:].multiply(scale))


def _chain(bearings: Float[Array, "steps 3 3 3"]):
    """Poses of every step in step-0 units (circumdiameter of the first formation = 1),
    from the cycle's mutual bearings as [`cycle_bearings`][] fills them."""
    refs = reference_robots("sequential")
    movers = moving_robot("sequential")
    sols = mutual_steps(bearings, refs)
    T = [sols[0].T_ref_body]
    for k in range(1, 4):
        ref, mover = refs[k], int(movers[k - 1])
        shared = 3 - ref - mover
        prev = T[k - 1]
        chain_dist = safe_norm(prev.translation()[ref] - prev.translation()[shared])
        local = sols[k].T_ref_body.translation()
        local_dist = safe_norm(local[ref] - local[shared])
        ratio = chain_dist / jnp.where(local_dist > 0, local_dist, 1.0)
        T.append(compose_scaled(jaxlie.SE3(prev.wxyz_xyz[ref]), ratio, sols[k].T_ref_body))
    return T, sols


def _fit_scale(observations: CycleObservations, lengths: Float[Array, " moves"]):
    """The chain's metric scale from the odometry (weighted least squares), whether it
    is determined, and the odometry residual RMS (m)."""
    w = odometry_weights(observations)
    d = observations.odometry
    denom = jnp.sum(w * lengths**2)
    ok = denom > 1e-12 * jnp.sum(w * d**2)
    scale = jnp.sum(w * d * lengths) / jnp.where(ok, denom, 1.0)
    ok = ok & (scale > 0)
    scale = jnp.where(ok, scale, 1.0)
    rms = jnp.sqrt(jnp.mean((scale * lengths - d) ** 2))
    return scale, ok, rms


def sequential_formations(observations: CycleObservations, bearings=None):
    """The sequential closed form: `(T_world_body, scales, scale_ok, odometry_rms,
    mutual_solutions)`, the first a `jaxlie.SE3` of batch `(4, 3)` at metric scale in
    `W`, `scales` `(4,)` (all equal). `bearings`: the mutual bearings as
    [`cycle_bearings`][] fills them, if the caller has them already."""
    T, sols = _chain(cycle_bearings(observations)[0] if bearings is None else bearings)
    positions = jnp.stack([Tk.translation() for Tk in T])
    scale, ok, rms = _fit_scale(observations, move_lengths(positions, "sequential"))
    T = jnp.stack([scale_translations(Tk, scale).wxyz_xyz for Tk in T])
    return jaxlie.SE3(T), jnp.full((4,), scale), ok, rms, sols
