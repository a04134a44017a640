"""The overhead camera's view of a cycle: each distinct placement once, with its bearing."""

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._core.numerics import safe_normalize
from .._cycle.layout import placement_ids
from .._cycle.observations import CycleObservations


def overhead_problem(
    observations: CycleObservations, positions: Float[Array, "steps 3 3"]
) -> tuple[Float[Array, "placements 3"], Float[Array, "placements 3"], Bool[Array, " placements"]]:
    """The overhead camera's pose problem of a cycle: every distinct placement's position
    (where it first occurs, from `positions`, m), its mean overhead bearing (repeated
    sightings of a robot that did not move averaged), and whether it was seen.

    A sighting is used when `overhead_visible` says it was made; a visible sighting with a
    non-finite bearing makes its placement's bearing NaN (the solver reports
    `nonfinite_observation`), an invisible one is left out (missing)."""
    ids = placement_ids(observations.strategy)
    n_points = int(ids.max()) + 1
    first = {}
    for k in range(ids.shape[0]):
        for r in range(3):
            first.setdefault(int(ids[k, r]), (k, r))
    points = jnp.stack([positions[first[i]] for i in range(n_points)])
    vis = observations.overhead_visible
    bearings = jnp.where(vis[..., None], observations.overhead, 0.0)
    summed = jnp.stack(
        [sum(bearings[k, r] for k, r in zip(*np.nonzero(ids == i))) for i in range(n_points)]
    )
    seen = jnp.stack(
        [sum(vis[k, r] for k, r in zip(*np.nonzero(ids == i))) for i in range(n_points)]
    )
    finite = jnp.all(jnp.isfinite(summed), axis=-1, keepdims=True)
    mean_bearing = jnp.where(finite, safe_normalize(jnp.where(finite, summed, 1.0)), jnp.nan)
    return points, mean_bearing, seen > 0
