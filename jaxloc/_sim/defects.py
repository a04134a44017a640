"""Realistic defects of a cycle's observations, for robustness studies and fuzzing.

A real team's measurements go wrong in a few ways: a detection is missed (NaN, or simply
absent), lands on a distractor (an outlier pixel), two markers are confused (swapped
sightings), a detector returns garbage (an infinite or zero bearing, a bearing pointing
backwards), the odometry is off by a factor or has the wrong sign.
[`jaxloc.corrupt_observations`][] applies one of them to a cycle's observations, branch
free, with the defect chosen by an integer (so that one compiled program serves every
defect and a `vmap` can mix them), through the rig's cameras where a pixel and its
bearing must agree. Whatever the defect, every estimate jaxloc then marks `successful`
must still be right (the gates of `jaxloc._model.gates`).
"""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
from jaxtyping import Array, Bool, Int, PRNGKeyArray

from .._cycle.observations import CycleObservations
from .._cycle.rig import ground_cameras_apply, Rig
from .._cycle.sightings import matvec


DEFECTS = (
    "clean",  # no defect
    "nan",  # one sighting's bearing and pixel NaN, still marked visible
    "inf",  # one sighting's bearing and pixel infinite
    "zero",  # one sighting's bearing the zero vector (its pixel unknown)
    "negated",  # one sighting's bearing pointing backwards (its pixel unknown)
    "swapped",  # two sightings of one image exchanged (confused markers)
    "outlier",  # one sighting's pixel moved 30-100 px (a distractor), bearing to match
    "missing",  # one sighting not made: NaN, and not visible
    "scaled_odometry",  # one odometry distance times a factor in [0.5, 2]
    "negative_odometry",  # one odometry distance with the wrong sign
)
"""The defects of [`jaxloc.corrupt_observations`][], by index: "clean" (none), "nan" and
"inf" (one sighting non-finite, still marked visible), "zero" and "negated" (one bearing
the zero vector or pointing backwards), "swapped" (two sightings of one image exchanged),
"outlier" (one pixel moved 30-100 px), "missing" (one sighting not made),
"scaled_odometry" (one distance times a factor in [0.5, 2]) and "negative_odometry"."""


def _sighting_mask(observations: CycleObservations, key):
    """One random sighting: `(mutual (steps, 3, 3), overhead (steps, 3))` one-hot masks,
    exactly one of them non-zero (off-diagonal for the mutual sightings)."""
    steps = observations.mutual.shape[0]
    off = ~np.eye(3, dtype=bool)
    candidates = np.concatenate([np.tile(off.reshape(-1), steps), np.ones(3 * steps, bool)])
    index = jr.choice(key, candidates.size, p=jnp.asarray(candidates / candidates.sum()))
    hot = jnp.arange(candidates.size) == index
    n_mutual = 9 * steps
    return hot[:n_mutual].reshape(steps, 3, 3), hot[n_mutual:].reshape(steps, 3)


def _set(observations, masks, bearing_value, pixel_value, visible=None):
    m, o = masks
    mutual = jnp.where(m[..., None], bearing_value, observations.mutual)
    overhead = jnp.where(o[..., None], bearing_value, observations.overhead)
    mutual_px = jnp.where(m[..., None], pixel_value, observations.mutual_pixels)
    overhead_px = jnp.where(o[..., None], pixel_value, observations.overhead_pixels)
    vis = observations.overhead_visible
    mutual_vis = observations.mutual_visible
    if visible is not None:
        vis = jnp.where(o, visible, vis)
        mutual_vis = jnp.where(m, visible, mutual_vis)
    return _replace(observations, mutual, overhead, vis, mutual_px, overhead_px,
                    mutual_visible=mutual_vis)  # fmt: skip


def _replace(obs, mutual, overhead, visible, mutual_px, overhead_px, odometry=None,
             mutual_visible=None):  # fmt: skip
    return CycleObservations(
        mutual, overhead, obs.odometry if odometry is None else odometry, obs.odometry_sigma,
        obs.strategy, visible, mutual_px, overhead_px,
        obs.mutual_visible if mutual_visible is None else mutual_visible,
    )  # fmt: skip


def _unproject_all(observations, rig: Rig, mutual_px, overhead_px):
    """Bearings of every pixel through the rig's cameras (body frames for the mutual
    sightings: camera bearing rotated by the mount)."""
    dtype = mutual_px.dtype
    mount_R = rig.mount_rotations()[1:].astype(dtype)
    b_cam = jnp.swapaxes(
        ground_cameras_apply(rig, lambda cam, x: cam.unproject(x), jnp.swapaxes(mutual_px, 0, 1)),
        0, 1,
    )  # fmt: skip
    mutual = matvec(mount_R[None, :, None], b_cam)
    return mutual, rig.overhead.unproject(overhead_px)


def _outlier(observations, rig, masks, key):
    k_r, k_a = jr.split(key)
    dtype = observations.mutual_pixels.dtype
    radius = jr.uniform(k_r, (), dtype, 30.0, 100.0)
    angle = jr.uniform(k_a, (), dtype, 0.0, 2.0 * np.pi)
    offset = radius * jnp.stack([jnp.cos(angle), jnp.sin(angle)])
    return _moved(observations, rig, masks, (offset, offset))


def add_outliers(
    observations: CycleObservations,
    rig: Rig,
    mutual: Bool[Array, "steps 3 3"],
    overhead: Bool[Array, "steps 3"],
    *,
    key: PRNGKeyArray,
) -> CycleObservations:
    """`observations` with every marked sighting an outlier: its pixel moved 30-100 px
    (uniform) in a uniform direction, each independently, and its bearing unprojected
    through the rig's camera to match (a detection on a distractor). For robustness
    studies of [`jaxloc.refine_cycle`][]'s robust loss; [`jaxloc.corrupt_observations`][]
    makes one such outlier.

    **Arguments:** `observations`, `rig` (the cameras the pixels were taken with),
    `mutual` `(steps, 3, 3)` and `overhead` `(steps, 3)` bool masks of the sightings to
    move (`[k, i, j]`: robot `i` sees robot `j` at step `k`; `[k, j]`: C sees robot `j`),
    `key` (keyword only).
    """
    k_r, k_a = jr.split(key)
    dtype = observations.mutual_pixels.dtype
    steps = observations.mutual_pixels.shape[0]
    n = 12 * steps
    radius = jr.uniform(k_r, (n,), dtype, 30.0, 100.0)
    angle = jr.uniform(k_a, (n,), dtype, 0.0, 2.0 * np.pi)
    offset = radius[:, None] * jnp.stack([jnp.cos(angle), jnp.sin(angle)], axis=-1)
    m_off = offset[: 9 * steps].reshape(steps, 3, 3, 2)
    o_off = offset[9 * steps :].reshape(steps, 3, 2)
    return _moved(observations, rig, (mutual, overhead), (m_off, o_off))


def _moved(observations, rig, masks, offsets):
    """Observations with the masked sightings' pixels moved by `offsets` (broadcast to the
    pixels) and their bearings unprojected to match."""
    m, o = masks
    mutual_px = observations.mutual_pixels + jnp.where(m[..., None], offsets[0], 0.0)
    overhead_px = observations.overhead_pixels + jnp.where(o[..., None], offsets[1], 0.0)
    mutual, overhead = _unproject_all(observations, rig, mutual_px, overhead_px)
    mutual = jnp.where(m[..., None], mutual, observations.mutual)
    overhead = jnp.where(o[..., None], overhead, observations.overhead)
    return _replace(
        observations, mutual, overhead, observations.overhead_visible, mutual_px, overhead_px
    )


def _swapped(observations, key):
    """Two sightings of one image exchanged: in a random step, the overhead camera's two
    robots, or one ground robot's two sightings."""
    k_step, k_which = jr.split(key)
    steps = observations.mutual.shape[0]
    step = jr.randint(k_step, (), 0, steps)
    which = jr.randint(k_which, (), 0, 4)  # 0-2: ground robot `which`; 3: overhead

    def swap_mutual(x):  # x: (steps, 3, 3, d); swap row `which`'s two off-diagonal entries
        i = jnp.minimum(which, 2)
        j, k = (i + 1) % 3, (i + 2) % 3
        row = x[step, i]
        swapped = row.at[j].set(row[k]).at[k].set(row[j])
        return jnp.where(which < 3, x.at[step, i].set(swapped), x)

    def swap_overhead(x):  # x: (steps, 3, d); swap two robots
        row = x[step]
        swapped = row.at[0].set(row[1]).at[1].set(row[0])
        return jnp.where(which == 3, x.at[step].set(swapped), x)

    return _replace(
        observations,
        swap_mutual(observations.mutual),
        swap_overhead(observations.overhead),
        observations.overhead_visible,
        swap_mutual(observations.mutual_pixels),
        swap_overhead(observations.overhead_pixels),
    )


def _odometry(observations, key, factor):
    index = jr.randint(key, (), 0, observations.odometry.shape[0])
    odometry = jnp.where(
        jnp.arange(observations.odometry.shape[0]) == index,
        observations.odometry * factor, observations.odometry,
    )  # fmt: skip
    obs = observations
    return _replace(
        obs, obs.mutual, obs.overhead, obs.overhead_visible, obs.mutual_pixels,
        obs.overhead_pixels, odometry,
    )  # fmt: skip


def corrupt_observations(
    observations: CycleObservations, rig: Rig, defect: Int[Array, ""] | int, *, key: PRNGKeyArray
) -> CycleObservations:
    """`observations` with one defect of `DEFECTS` (by index), at a random sighting or
    odometry distance drawn from `key`. Branch free (`lax.switch`): one compiled program
    serves every defect. The rig unprojects an outlier's moved pixel to its bearing.

    **Arguments:**

    - `observations`: a cycle's [`jaxloc.CycleObservations`][].
    - `rig`: the [`jaxloc.Rig`][] the pixels were taken with.
    - `defect`: index into `jaxloc._sim.defects.DEFECTS` (an int or an int array).
    - `key`: a JAX PRNG key (which sighting, how far an outlier). Keyword only.

    **Returns:** the corrupted [`jaxloc.CycleObservations`][].
    """
    k_pick, k_defect = jr.split(key)
    masks = _sighting_mask(observations, k_pick)
    dtype = observations.mutual.dtype
    nan, inf = jnp.full(3, jnp.nan, dtype), jnp.full(3, jnp.inf, dtype)
    nan_px = jnp.full(2, jnp.nan, dtype)
    k_factor = jr.uniform(k_defect, (), dtype, 0.5, 2.0)
    branches = [
        lambda obs: obs,
        lambda obs: _set(obs, masks, nan, nan_px),
        lambda obs: _set(obs, masks, inf, jnp.full(2, jnp.inf, dtype)),
        lambda obs: _set(obs, masks, jnp.zeros(3, dtype), nan_px),
        lambda obs: _negated(obs, masks),
        lambda obs: _swapped(obs, k_defect),
        lambda obs: _outlier(obs, rig, masks, k_defect),
        lambda obs: _set(obs, masks, nan, nan_px, visible=False),
        lambda obs: _odometry(obs, k_defect, k_factor),
        lambda obs: _odometry(obs, k_defect, -1.0),
    ]
    assert len(branches) == len(DEFECTS)
    return jax.lax.switch(jnp.asarray(defect, jnp.int32), branches, observations)


def _negated(observations, masks):
    m, o = masks
    mutual = jnp.where(m[..., None], -observations.mutual, observations.mutual)
    overhead = jnp.where(o[..., None], -observations.overhead, observations.overhead)
    return _replace(
        observations, mutual, overhead, observations.overhead_visible,
        jnp.where(m[..., None], jnp.nan, observations.mutual_pixels),
        jnp.where(o[..., None], jnp.nan, observations.overhead_pixels),
    )  # fmt: skip



def drop_sightings(
    observations: CycleObservations, probability: float | Array, *, key: PRNGKeyArray
) -> CycleObservations:
    """`observations` with each mutual and overhead sighting missing independently with
    `probability`: its bearing and pixel NaN, and marked not visible (a marker occluded
    or not detected). Branch free; `jit`/`vmap` apply.

    **Arguments:**

    - `observations`: a cycle's [`jaxloc.CycleObservations`][].
    - `probability`: chance that each sighting is missing, in `[0, 1]`.
    - `key`: a JAX PRNG key. Keyword only.

    **Returns:** the thinned [`jaxloc.CycleObservations`][].
    """
    k_m, k_o = jr.split(key)
    dtype = observations.mutual.dtype
    shape = observations.mutual_visible.shape
    off = np.broadcast_to(~np.eye(3, dtype=bool), shape)
    m = jr.bernoulli(k_m, probability, shape) & off
    o = jr.bernoulli(k_o, probability, observations.overhead_visible.shape)
    nan, nan_px = jnp.full(3, jnp.nan, dtype), jnp.full(2, jnp.nan, dtype)
    return _set(observations, (m, o), nan, nan_px, visible=False)
