"""Observation types: what a localization cycle measures, whoever produced it.

The simulator, the image front end and a real robot all produce these types, and the
solvers consume only these, so real measurements enter exactly where simulated ones do.
Indexing (robots, steps, moves) is that of `jaxloc._cycle.layout`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .layout import (
    check_strategy,
    move_start_step as move_start_step,
    moving_robot as moving_robot,
    num_moves,
    num_steps,
    STRATEGIES as STRATEGIES,
)


#: Relative floor of an odometry sigma under `jit` (a noise-free simulation's exact
#: odometry): sigma >= `ODOMETRY_SIGMA_FLOOR` x the cycle's longest move. Eager
#: observations with a non-positive sigma are rejected by [`jaxloc.CycleObservations`][].
ODOMETRY_SIGMA_FLOOR = 1e-6


def _floating(name: str, x, dtype=None) -> Array:
    """`x` as a floating-point array: float arrays keep their dtype (float32 stays
    float32); anything else (lists, Python or integer numbers) takes `dtype`, or the
    default float."""
    is_float_array = isinstance(x, (jax.Array, np.ndarray, np.generic)) and jnp.issubdtype(
        x.dtype, jnp.floating
    )
    x = jnp.asarray(x)
    if not (jnp.issubdtype(x.dtype, jnp.floating) or jnp.issubdtype(x.dtype, jnp.integer)):
        raise ValueError(
            f"`CycleObservations({name}=...)` must be real numbers; got dtype {x.dtype}."
        )
    if is_float_array:
        return x
    return x.astype(jnp.result_type(float) if dtype is None else dtype)


def _concrete(x) -> np.ndarray | None:
    return None if isinstance(x, jax.core.Tracer) else np.asarray(x)


class CycleObservations(eqx.Module):
    r"""Everything measured during one localization cycle.

    **Fields:**

    - `mutual`: unit bearings between ground robots, shape `(steps, 3, 3, 3)`:
      `mutual[k, i, j]` is the direction from robot `i` to robot `j` at step `k`,
      expressed in robot `i`'s **body** frame (x forward, y left, z up along the
      surface normal): the camera's unprojected bearing rotated by the camera mount.
      The diagonal `i == j` is ignored.
    - `mutual_visible`: whether each mutual sighting exists, shape `(steps, 3, 3)`;
      default: where `mutual` is finite (the diagonal is ignored).
    - `overhead`: unit bearings of the ground robots in the overhead camera's
      optical frame, shape `(steps, 3, 3)`: `overhead[k, j]` points at robot `j` at step `k`.
    - `overhead_visible`: whether each overhead sighting exists, shape `(steps, 3)`;
      default: where `overhead` is finite.
    - `odometry`: travelled straight-line distance of each move (m), shape `(moves,)`;
      finite and positive.
    - `odometry_sigma`: its standard deviation (m), shape `(moves,)` (or a scalar for
      every move); finite and positive.
    - `mutual_pixels`, `overhead_pixels`: the pixels the bearings came from, shapes
      `(steps, 3, 3, 2)` and `(steps, 3, 2)` (NaN where not measured). Used by
      refinement, which weighs residuals in each camera's image.
    - `strategy`: `"sequential"` or `"concurrent"` (static).

    A sighting that was not made (a marker occluded or not detected) is missing data:
    NaN bearings (and pixels), or `False` in `mutual_visible` / `overhead_visible`, never
    a default value. The estimators use every sighting present (see
    [`jaxloc.localize_cycle`][]); a non-finite bearing marked visible is corrupt input
    (`nonfinite_observation`). Arrays are floating point: float
    arrays keep their dtype (float32 stays float32), integers and Python numbers become
    floats. Values are checked when they are known (not under `jit`): non-positive or
    non-finite odometry distances or sigmas raise a `ValueError` naming the field.
    """

    mutual: Float[Array, "steps 3 3 3"]
    overhead: Float[Array, "steps 3 3"]
    overhead_visible: Bool[Array, "steps 3"]
    mutual_visible: Bool[Array, "steps 3 3"]
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
        mutual_visible: Bool[ArrayLike, "steps 3 3"] | None = None,
    ):
        self.strategy = check_strategy(strategy)
        steps, moves = num_steps(strategy), num_moves(strategy)
        self.mutual = _floating("mutual", mutual)
        dtype = self.mutual.dtype
        self.overhead = _floating("overhead", overhead, dtype)
        self.odometry = _floating("odometry", odometry, dtype)
        sigma = _floating("odometry_sigma", odometry_sigma, self.odometry.dtype)
        if sigma.ndim == 0:
            sigma = jnp.broadcast_to(sigma, self.odometry.shape)
        self.odometry_sigma = sigma
        if overhead_visible is None:
            overhead_visible = jnp.all(jnp.isfinite(self.overhead), axis=-1)
        self.overhead_visible = jnp.asarray(overhead_visible, dtype=bool)
        if mutual_visible is None:
            mutual_visible = jnp.all(jnp.isfinite(self.mutual), axis=-1)
        self.mutual_visible = jnp.asarray(mutual_visible, dtype=bool)
        if mutual_pixels is None:
            mutual_pixels = jnp.full(self.mutual.shape[:-1] + (2,), jnp.nan, dtype)
        if overhead_pixels is None:
            overhead_pixels = jnp.full(self.overhead.shape[:-1] + (2,), jnp.nan, dtype)
        self.mutual_pixels = _floating("mutual_pixels", mutual_pixels, dtype)
        self.overhead_pixels = _floating("overhead_pixels", overhead_pixels, dtype)
        expected = {
            "mutual": (steps, 3, 3, 3),
            "overhead": (steps, 3, 3),
            "overhead_visible": (steps, 3),
            "mutual_visible": (steps, 3, 3),
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
        for name in ("odometry", "odometry_sigma"):
            value = _concrete(getattr(self, name))
            if value is not None and not np.all(np.isfinite(value) & (value > 0)):
                what = "distances (m)" if name == "odometry" else "standard deviations (m)"
                raise ValueError(
                    f"`CycleObservations({name}=...)` must be finite positive {what}; got "
                    f"{np.array2string(value, precision=6, threshold=12)}."
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
