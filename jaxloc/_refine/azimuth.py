"""Refinement starts over the azimuth of a missing mutual bearing the closed form could
only put on a cone (`jaxloc._solvers.mutual.fill_missing_bearings`, `stand_in`).

Robot `a` did not see robot `b` at step `k`, and nothing outside the cycle's joint fit
fixes where `b` lies on the cone around `a`'s bearing of the third robot `c`: the closed
form's formation at step `k` is the true one turned about the line from `a` to `c` by an
unknown angle, and the joint fit has a discrete set of minima over that angle (e.g. where
the overhead camera's ray to `b` meets `b`'s circle about the line). The refinement
starts from the closed form's formation turned by evenly spaced angles, each with the
closed form's overhead camera and with its planar flip, refines every start to
convergence and keeps the best fit (`jaxloc._refine.kernel.multi_start`); two distinct
minima that fit alike are `ambiguous`.
"""

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Bool, Float

from .._core.numerics import safe_normalize
from .._core.poses import compose, quaternion_matrix
from .._cycle.layout import placement_ids
from .._model.mirrors import flip_start


#: Azimuths a refinement starts from when a bearing is a stand-in (evenly spaced over the
#: circle, the closed form's own included): consecutive starts 45 degrees apart, so every
#: minimum has a start within 22.5 degrees of it.
AZIMUTH_STARTS = 8


def _held_at_one_step(strategy: str) -> np.ndarray:
    """`(steps, 3)` bool: robot `r`'s placement at step `k` is occupied at step `k` only
    (turning it moves no other step's formation)."""
    ids = placement_ids(strategy)
    return np.array([[np.sum(np.any(ids == p, axis=1)) == 1 for p in row] for row in ids])


def azimuth_starts(
    T_place: Float[Array, "placements 7"],
    T_over: Float[Array, "7"],
    stand_in: Bool[Array, "steps 3 3"],
    strategy: str,
    count: int = AZIMUTH_STARTS,
) -> tuple[Float[Array, "k placements 7"], Float[Array, "k 7"], Bool[Array, " k"]]:
    r"""`2 count - 1` other starts of a refinement from its start `(T_place, T_over)`
    (`wxyz_xyz`, world frame `W`, metres), for the first stand-in bearing `[k, a, b]` of
    `stand_in` (`c` the third robot): step `k`'s formation turned about the line from
    robot `a` to robot `c` by `2 pi m / count`, with the overhead camera `T_over` (`m = 1
    .. count - 1`) and with it flipped about the floor of the placements
    ([`flip_start`][jaxloc._model.mirrors.flip_start]; `m = 0 .. count - 1`). The closed
    form's overhead camera and scales were fitted to the stand-in formation: measured on
    the concurrent strategy, the turns alone miss the true minimum where that camera
    lies near its planar flip.

    The robots `b` and `c` turn with their formation where their placement is held at
    step `k` only (the concurrent strategy's movers); `a`, whose rotation the other steps
    fix, stays. Returns `(T_place (2 count - 1, placements, 7), T_over (2 count - 1, 7),
    active (2 count - 1,))`; inactive where no bearing is a stand-in, nothing can turn,
    the start is not finite or the flip is not defined."""
    dtype = T_place.dtype
    ids = jnp.asarray(placement_ids(strategy))
    held = jnp.asarray(_held_at_one_step(strategy))
    first = jnp.argmax(stand_in.reshape(-1))
    k, a, b = first // 9, (first // 3) % 3, first % 3
    c = 3 - a - b
    pivot = T_place[ids[k, a], 4:]
    axis = safe_normalize(T_place[ids[k, c], 4:] - pivot)
    placements = jnp.arange(T_place.shape[0])
    turns = ((placements == ids[k, b]) & held[k, b]) | ((placements == ids[k, c]) & held[k, c])
    angles = 2.0 * jnp.pi * jnp.arange(count, dtype=dtype) / count

    def turned(angle):
        q = jnp.concatenate([jnp.cos(0.5 * angle)[None], jnp.sin(0.5 * angle) * axis])
        t = pivot - quaternion_matrix(q) @ pivot
        T_turn = jaxlie.SE3(jnp.concatenate([q, t]))
        moved = jax.vmap(lambda T: compose(T_turn, jaxlie.SE3(T)).wxyz_xyz)(T_place)
        return jnp.where(turns[:, None], moved, T_place)

    T_turned = jax.vmap(turned)(angles)
    flipped, flip_defined = flip_start(T_place, T_over)
    finite = jnp.all(jnp.isfinite(T_place)) & jnp.all(jnp.isfinite(T_over))
    active = jnp.any(stand_in) & jnp.any(turns) & finite
    return (
        jnp.concatenate([T_turned[1:], T_turned]),
        jnp.concatenate([jnp.broadcast_to(T_over, (count - 1, 7)),
                         jnp.broadcast_to(flipped.astype(dtype), (count, 7))]),
        jnp.concatenate([jnp.full(count - 1, active), jnp.full(count, active & flip_defined)]),
    )
