"""A moved robot's mirror placement: the second minimum its line of sight and odometry allow.

A robot's placement after a move is pinned by the rays of the cameras that see it and by
the sphere of its odometry distance about where it started. When the overhead camera does
not see it (the sighting missing, or rejected as an outlier) and the two other ground
robots see it along nearly the same line (the three nearly collinear), the line of sight
meets the sphere twice: two placements fit the measurements almost equally well, often
tens of centimetres apart, and each is a sharp local minimum with a small covariance. A
refinement that lands in the wrong one is confidently wrong, and only finding the other
minimum shows it. [`mirror_start`][] is the other intersection; the gates
(`jaxloc._model.gates`) polish it by Gauss--Newton and call the estimate `ambiguous` when
it converges to a distinct minimum that fits almost as well.
"""

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._core.numerics import safe_normalize
from .._cycle.layout import move_start_step, moving_robot, other_robots, placement_ids
from .measurements import CycleData


#: Gauss--Newton steps from a mirror start to its minimum (the start sits on the
#: minimum's line of sight at its odometry distance, so a few undamped steps converge).
MIRROR_STEPS = 4
#: A polished mirror counts as a minimum when its last Gauss--Newton step predicted a
#: chi-square decrease below this (a point still sliding downhill is not one).
CONVERGED_DECREMENT = 1e-2


def _moves(strategy: str):
    """Per move: the mover's placement before and after, the two other ground robots'
    placements where it arrives `(moves, 2)`, and where the arrived placement occurs
    `(moves, steps, 3)`."""
    ids = placement_ids(strategy)
    movers, starts = moving_robot(strategy), move_start_step(strategy)
    before, after = ids[starts, movers], ids[starts + 1, movers]
    observers = np.array([ids[s + 1, list(other_robots(r))] for s, r in zip(starts, movers)])
    return before, after, observers, ids[None] == after[:, None, None]


def mirror_start(
    T_place: Float[Array, "placements 7"], data: CycleData, strategy: str
) -> tuple[Float[Array, "placements 7"], Int[Array, ""], Bool[Array, ""]]:
    """The placements `T_place` (`wxyz_xyz`, in `W`) with one moved placement replaced by
    its mirror: the first move whose arrival no overhead sighting in `data` sees. The
    mirror is the second point where the line through the placement along the mean of
    the other two robots' lines of sight meets the sphere about the move's start through
    the placement (its orientation kept). Returns `(placements, index of the mirrored
    placement, whether any move qualifies)`."""
    before, after, observers, occurs = _moves(strategy)
    position = T_place[:, 4:]
    p, q = position[after], position[before]
    sight = safe_normalize(p[:, None] - position[observers])
    u = safe_normalize(jnp.sum(sight, axis=1))
    mirrored = p - 2.0 * jnp.sum(u * (p - q), axis=-1, keepdims=True) * u
    unseen = ~jnp.any(occurs & (data.overhead_weight > 0)[None], axis=(1, 2))
    pick = jnp.argmax(unseen)
    index = jnp.asarray(after)[pick]
    return T_place.at[index, 4:].set(mirrored[pick]), index, jnp.any(unseen)
