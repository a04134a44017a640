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
minima that fit alike are `ambiguous`. Two stand-in bearings (at two steps, each turning
its own step's formation) are searched together, every pair of turns: the overhead
camera sees both steps, so the fit of one turn depends on the other."""

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
#: Azimuths per bearing when two are stand-ins: every pair of turns is a start, 60
#: degrees apart (every pair of minima has a start within 30 degrees of each). Measured
#: on the 137 such cycles of `benchmarks/missing_data.py` (concurrent): 90 degrees apart
#: localized 68 with one wrong pose, 60 and 45 degrees (127 starts) 67 with none.
PAIR_AZIMUTH_STARTS = 6
#: Stand-in bearings whose azimuths a refinement searches jointly; a cycle with more
#: stays `too_few_points`.
SEARCHED_STAND_INS = 2


def _held_at_one_step(strategy: str) -> np.ndarray:
    """`(steps, 3)` bool: robot `r`'s placement at step `k` is occupied at step `k` only
    (turning it moves no other step's formation)."""
    ids = placement_ids(strategy)
    return np.array([[np.sum(np.any(ids == p, axis=1)) == 1 for p in row] for row in ids])


def _turning(T_place, flat_index, strategy):
    """The turn of a stand-in bearing `[k, a, b]` (`flat_index` into `(steps, 3, 3)`, `c`
    the third robot): `(turned, turns)`, `turned(angle)` the placements `T_place` with
    step `k`'s formation turned about the line from robot `a` to robot `c` by `angle`
    (rad), and `turns` whether any placement moves. Robots `b` and `c` turn where their
    placement is held at step `k` only (the concurrent strategy's movers); `a`, whose
    rotation the other steps fix, stays."""
    ids = jnp.asarray(placement_ids(strategy))
    held = jnp.asarray(_held_at_one_step(strategy))
    k, a, b = flat_index // 9, (flat_index // 3) % 3, flat_index % 3
    c = 3 - a - b
    pivot = T_place[ids[k, a], 4:]
    axis = safe_normalize(T_place[ids[k, c], 4:] - pivot)
    placements = jnp.arange(T_place.shape[0])
    turns = ((placements == ids[k, b]) & held[k, b]) | ((placements == ids[k, c]) & held[k, c])

    def turned(angle):
        q = jnp.concatenate([jnp.cos(0.5 * angle)[None], jnp.sin(0.5 * angle) * axis])
        t = pivot - quaternion_matrix(q) @ pivot
        T_turn = jaxlie.SE3(jnp.concatenate([q, t]))
        moved = jax.vmap(lambda T: compose(T_turn, jaxlie.SE3(T)).wxyz_xyz)(T_place)
        return jnp.where(turns[:, None], moved, T_place)

    return turned, jnp.any(turns)


def _turned_starts(T_place, T_over, stand_in, strategy, count, pair):
    """The starts of one search: `count` turns of the first stand-in bearing (`pair`
    False) or `count x count` turns of the first two (`pair` True, the second turn about
    the line of the first's turned placements), every turn but the zero one with
    `T_over`, every turn with its planar flip. Active only with exactly one (two)
    stand-ins."""
    dtype = T_place.dtype
    flat = stand_in.reshape(-1)
    first = jnp.argmax(flat)
    second = first
    if pair:  # without a second stand-in the starts are inactive; keep them finite
        others = flat & (jnp.arange(flat.shape[0]) != first)
        second = jnp.where(jnp.any(others), jnp.argmax(others), first)
    angles = 2.0 * jnp.pi * jnp.arange(count, dtype=dtype) / count
    angles2 = angles if pair else jnp.zeros(1, dtype)
    turn1, turns1 = _turning(T_place, first, strategy)

    def row(angle1):
        turn2, turns2 = _turning(turn1(angle1), second, strategy)
        return jax.vmap(turn2)(angles2), turns2

    T_grid, turns2 = jax.vmap(row)(angles)
    n = T_grid.shape[0] * T_grid.shape[1]
    T_grid = T_grid.reshape((n,) + T_place.shape)
    flipped, flip_defined = flip_start(T_place, T_over)
    finite = jnp.all(jnp.isfinite(T_place)) & jnp.all(jnp.isfinite(T_over))
    active = (jnp.sum(flat) == (2 if pair else 1)) & turns1 & finite
    if pair:
        active = active & turns2[0]
    return (
        jnp.concatenate([T_grid[1:], T_grid]),
        jnp.concatenate([jnp.broadcast_to(T_over, (n - 1, 7)),
                         jnp.broadcast_to(flipped.astype(dtype), (n, 7))]),
        jnp.concatenate([jnp.full(n - 1, active), jnp.full(n, active & flip_defined)]),
    )


def azimuth_starts(
    T_place: Float[Array, "placements 7"],
    T_over: Float[Array, "7"],
    stand_in: Bool[Array, "steps 3 3"],
    strategy: str,
    count: int = AZIMUTH_STARTS,
    pair_count: int = PAIR_AZIMUTH_STARTS,
) -> tuple[Float[Array, "k placements 7"], Float[Array, "k 7"], Bool[Array, " k"]]:
    r"""Other starts of a refinement from its start `(T_place, T_over)` (`wxyz_xyz`,
    world frame `W`, metres) over the azimuths of its stand-in bearings (`stand_in`, in
    the order `(step, a, b)`). For a stand-in `[k, a, b]` (`c` the third robot) a turn
    by `2 pi m / count` is step `k`'s formation turned about the line from robot `a` to
    robot `c`; the starts are those turns with the overhead camera `T_over` (`m = 1 ..
    count - 1`) and with it flipped about the floor of the placements
    ([`flip_start`][jaxloc._model.mirrors.flip_start]; `m = 0 .. count - 1`). The closed
    form's overhead camera and scales were fitted to the stand-in formation: measured on
    the concurrent strategy, the turns alone miss the true minimum where that camera
    lies near its planar flip.

    With one stand-in, the `2 count - 1` starts of its turns are active; with two, the
    `2 pair_count^2 - 1` starts of every pair of their turns by `2 pi m / pair_count`
    (`m1` major, the second turn about the line of the first's turned placements; with
    the camera, every pair but `(0, 0)`; flipped, every pair). The robots `b` and `c`
    turn with their formation where their placement is held at step `k` only (the
    concurrent strategy's movers); `a`, whose rotation the other steps fix, stays.
    Returns `(T_place (s, placements, 7), T_over (s, 7), active (s,))` with `s = 2
    count - 1 + 2 pair_count^2 - 1`, one-stand-in starts first; inactive where nothing
    can turn, the start is not finite or the flip is not defined."""
    one = _turned_starts(T_place, T_over, stand_in, strategy, count, pair=False)
    two = _turned_starts(T_place, T_over, stand_in, strategy, pair_count, pair=True)
    return tuple(jnp.concatenate([x, y]) for x, y in zip(one, two))
