"""Observation types: what a localization cycle measures, whoever produced it.

The simulator, the image front end and a real robot all produce these types, and the
solvers consume only these, so real measurements enter exactly where simulated ones do.

Indexing used throughout jaxloc:

- robots `0, 1, 2` are the ground robots C1 (PTZ camera), C2, C3 (omnidirectional);
- a *step* is one snapshot of the team (one formation). The sequential strategy has
  4 steps (start, after C2 moved, after C3 moved, after C1 moved); the concurrent
  strategy has 3 (start, after move 1 of C2 and C3, after move 2).
- moves, in order: sequential `[C2, C3, C1]`; concurrent `[C2 move 1, C3 move 1,
  C2 move 2, C3 move 2]`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float


STRATEGIES = ("sequential", "concurrent")


def num_steps(strategy: str) -> int:
    """Number of formations (snapshots) in one cycle of `strategy`."""
    return {"sequential": 4, "concurrent": 3}[check_strategy(strategy)]


def num_moves(strategy: str) -> int:
    """Number of odometry-measured moves in one cycle of `strategy`."""
    return {"sequential": 3, "concurrent": 4}[check_strategy(strategy)]


def moving_robot(strategy: str) -> np.ndarray:
    """Index of the robot that makes each move, shape `(moves,)`."""
    return {"sequential": np.array([1, 2, 0]), "concurrent": np.array([1, 2, 1, 2])}[
        check_strategy(strategy)
    ]


def move_start_step(strategy: str) -> np.ndarray:
    """Step at which each move starts (it ends at the next step), shape `(moves,)`."""
    return {"sequential": np.array([0, 1, 2]), "concurrent": np.array([0, 0, 1, 1])}[
        check_strategy(strategy)
    ]


def check_strategy(strategy: str) -> str:
    if strategy not in STRATEGIES:
        raise ValueError(
            f"`strategy` must be one of {STRATEGIES}; got {strategy!r}."
        )
    return strategy


class CycleObservations(eqx.Module):
    r"""Everything measured during one localization cycle.

    **Fields:**

    - `mutual`: unit bearings between ground robots, shape `(steps, 3, 3, 3)`:
      `mutual[k, i, j]` is the direction from robot `i` to robot `j` at step `k`,
      expressed in robot `i`'s **body** frame (x forward, y left, z up along the
      surface normal): the camera's unprojected bearing rotated by the camera mount.
      The diagonal `i == j` is ignored.
    - `overhead`: unit bearings of the ground robots in the overhead camera's
      optical frame, shape `(steps, 3, 3)`: `overhead[k, j]` points at robot `j` at step `k`.
    - `overhead_visible`: whether each overhead sighting exists, shape `(steps, 3)`.
    - `odometry`: travelled straight-line distance of each move (m), shape `(moves,)`.
    - `odometry_sigma`: its standard deviation (m), shape `(moves,)`.
    - `mutual_pixels`, `overhead_pixels`: the pixels the bearings came from, shapes
      `(steps, 3, 3, 2)` and `(steps, 3, 2)` (NaN where not measured). Used by
      refinement, which weighs residuals in each camera's image.
    - `strategy`: `"sequential"` or `"concurrent"` (static).
    """

    mutual: Float[Array, "steps 3 3 3"]
    overhead: Float[Array, "steps 3 3"]
    overhead_visible: Bool[Array, "steps 3"]
    odometry: Float[Array, " moves"]
    odometry_sigma: Float[Array, " moves"]
    mutual_pixels: Float[Array, "steps 3 3 2"]
    overhead_pixels: Float[Array, "steps 3 2"]
    strategy: str = eqx.field(static=True)

    def __init__(
        self,
        mutual: Float[ArrayLike, "steps 3 3 3"],
        overhead: Float[ArrayLike, "steps 3 3"],
        odometry: Float[ArrayLike, " moves"],
        odometry_sigma: Float[ArrayLike, " moves"],
        strategy: str,
        overhead_visible: Bool[ArrayLike, "steps 3"] | None = None,
        mutual_pixels: Float[ArrayLike, "steps 3 3 2"] | None = None,
        overhead_pixels: Float[ArrayLike, "steps 3 2"] | None = None,
    ):
        self.strategy = check_strategy(strategy)
        steps, moves = num_steps(strategy), num_moves(strategy)
        self.mutual = jnp.asarray(mutual)
        self.overhead = jnp.asarray(overhead)
        self.odometry = jnp.asarray(odometry)
        self.odometry_sigma = jnp.broadcast_to(
            jnp.asarray(odometry_sigma, dtype=self.odometry.dtype), self.odometry.shape
        )
        dtype = self.mutual.dtype
        if overhead_visible is None:
            overhead_visible = jnp.ones(self.overhead.shape[:-1], dtype=bool)
        self.overhead_visible = jnp.asarray(overhead_visible, dtype=bool)
        if mutual_pixels is None:
            mutual_pixels = jnp.full(self.mutual.shape[:-1] + (2,), jnp.nan, dtype)
        if overhead_pixels is None:
            overhead_pixels = jnp.full(self.overhead.shape[:-1] + (2,), jnp.nan, dtype)
        self.mutual_pixels = jnp.asarray(mutual_pixels)
        self.overhead_pixels = jnp.asarray(overhead_pixels)
        expected = {
            "mutual": (steps, 3, 3, 3),
            "overhead": (steps, 3, 3),
            "overhead_visible": (steps, 3),
            "odometry": (moves,),
            "odometry_sigma": (moves,),
            "mutual_pixels": (steps, 3, 3, 2),
            "overhead_pixels": (steps, 3, 2),
        }
        for name, shape in expected.items():
            got = getattr(self, name).shape
            # Leading batch axes are allowed (a vmapped study builds batched observations).
            if got[len(got) - len(shape) :] != shape:
                raise ValueError(
                    f"`CycleObservations({name}=...)` must have shape {shape} for the "
                    f"{strategy} strategy; got {got}."
                )

    @property
    def num_steps(self) -> int:
        return num_steps(self.strategy)

    @property
    def num_moves(self) -> int:
        return num_moves(self.strategy)


class CyclePoses(eqx.Module):
    r"""Poses of the whole team during one cycle, in the cycle's world frame.

    The world frame `W` of a cycle is the body frame of C1 at the start of the cycle
    (the paper's choice), metric.

    **Fields:**

    - `T_world_body`: pose of each ground robot's body frame at each step, a `jaxlie.SE3`
      of batch shape `(steps, 3)`. The end-of-cycle poses are `T_world_body[-1]`, and
      `T_world_body[0, 0]` is the identity by definition of `W`.
    - `T_world_overhead`: pose of the overhead camera's **optical** frame (x right,
      y down, z forward) in `W`, a `jaxlie.SE3` (the camera is static during a cycle).
    """

    T_world_body: jaxlie.SE3
    T_world_overhead: jaxlie.SE3

    @property
    def positions(self) -> Float[Array, "steps 3 3"]:
        """Every robot's position (m) at every step, in `W`."""
        return self.T_world_body.translation()

    @property
    def final_body(self) -> jaxlie.SE3:
        """End-of-cycle body poses of C1, C2, C3, batch shape `(3,)`."""
        return jax.tree.map(lambda x: x[..., -1, :, :], self.T_world_body)
