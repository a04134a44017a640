"""Second minima the gates look for: a moved robot's mirror placement, the overhead camera's
planar flip.

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

The ground robots stand on a floor, so the overhead camera sees nearly coplanar points,
and a camera reflected through the plane that holds them and their centroid sees them at
almost the same pixels: perspective alone tells the two apart. [`flip_start`][] is that
reflected camera. With every sighting present no flipped minimum was found in 4096 clean
cycles of the paper's scenario (`benchmarks/planar_flip_rival.py`); with sightings missing
a closed form can land in the flipped minimum (C 3.7 m off in missing-data cycle 1129) and
the true one fits better. So the gates look for the flip when a sighting is missing
([`flip_active`][]).
"""

import jax.numpy as jnp
import jaxlie
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


def flip_start(
    T_place: Float[Array, "placements 7"], T_over: Float[Array, "7"]
) -> tuple[Float[Array, "7"], Bool[Array, ""]]:
    """The overhead camera `T_over` (`wxyz_xyz`, in `W`) flipped about the floor of the
    placements `T_place`: with `m` the placements' centroid, `n` their floor normal (the
    direction of least spread, towards the camera's centre `c`) and `v` the unit line of
    sight from `c` to `m`, the camera's centre and orientation rotated about `m` by
    `-2 theta` around `n x (-v)`, `theta` the angle between `n` and `-v`. Returns `(flipped
    camera, whether the flip is defined)`: not when the camera looks along the normal (no
    flip) or the geometry is degenerate."""
    spread = T_place[:, 4:] - jnp.mean(T_place[:, 4:], axis=0, keepdims=True)
    m = jnp.mean(T_place[:, 4:], axis=0)
    _, V = jnp.linalg.eigh(spread.T @ spread)
    c = T_over[4:]
    n = jnp.where(jnp.dot(c - m, V[:, 0]) < 0, -V[:, 0], V[:, 0])
    v = safe_normalize(m - c)
    axis = jnp.cross(n, -v)
    s = jnp.linalg.norm(axis)
    defined = (s > 1e-6) & jnp.all(jnp.isfinite(T_place)) & jnp.all(jnp.isfinite(T_over))
    s = jnp.where(defined, s, 1.0)
    R = jaxlie.SO3.exp(axis / s * (-2.0 * jnp.arctan2(s, jnp.dot(n, -v))))
    flipped = jnp.concatenate([(R @ jaxlie.SE3(T_over).rotation()).wxyz, m + R @ (c - m)])
    return jnp.where(defined, flipped, T_over), defined


def flip_active(data: CycleData) -> Bool[Array, ""]:
    """Whether the gates look for the planar flip: a sighting of `data` is missing (every
    step has six mutual and three overhead sightings when none is)."""
    return data.num_sightings < 9 * data.overhead_weight.shape[0]
