"""What a cycle's solvers return: the estimate, its covariance, its checks, its other starts.

The closed forms ([`jaxloc.localize_cycle`][]) and the refinement ([`jaxloc.refine_cycle`][])
return the same [`jaxloc.CycleEstimate`][]; its typed fields carry what one stage hands
the next (the multi-start alternatives, the status before the gates), so nothing that
code branches on travels through the `stats` dict of diagnostics.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._core.results import RESULTS
from .layout import CAMERAS, first_sighting
from .observations import CyclePoses


class CycleCovariance(eqx.Module):
    """Covariance (or Cramér–Rao bound) of one cycle's estimates.

    **Fields:**

    - `tangent`: covariance of the stacked tangent parameters, shape `(n, n)` with
        `n = 6 (placements - 1) + 6`: placements 1, 2, ... (see
        [`jaxloc.placement_ids`][]; placement 0, C1's start pose, is the gauge) then the
        overhead camera, each `(v, omega)` of `T exp(delta)`.
    - `position`: world-frame position covariance (m^2) of (C, C1, C2, C3) at the end of
        the cycle, shape `(4, 3, 3)`; for C the camera centre. C1's is zero when C1 never
        moved (concurrent strategy: its pose is the world frame).
    - `rotation`: covariance of the rotation tangent `omega` (rad^2) of the same four
        poses, shape `(4, 3, 3)` (C: its optical frame; the body frame's is the same
        up to a fixed rotation, same trace).
    - `ok`: whether the information matrix was positive definite (all entries are 0
        otherwise).
    """

    tangent: Float[Array, "n n"]
    position: Float[Array, "4 3 3"]
    rotation: Float[Array, "4 3 3"]
    ok: Bool[Array, ""]


class FitCheck(eqx.Module):
    """The goodness-of-fit and observability checks of one estimate (the gates).

    **Fields:**

    - `solver_result`: the solver's own status, before the gates (a closed form's
      accuracy is studied on it: a study scores every estimate its solver produced).
    - `chi2`: the sum of squared whitened residuals at the estimate.
    - `chi2_min`: the minimum of the model linearized at the estimate, `chi2 - g^T (J^T
      J)^-1 g`: the misfit no nearby pose explains (equal to `chi2` at a converged
      refinement). The gate's statistic.
    - `dof`: residuals used minus unknowns (int).
    - `chi2_limit`: the 99.9% quantile of `chi2_min` under the rig's noise model; above it
      the estimate is `inconsistent_fit`.
    - `observable`: the information matrix at the estimate is positive definite and every
      final pose's bound is below the documented limits (else `unobservable`).
    - `worst_sighting`: the largest normalized residual of any one measurement (a pixel
      sighting, an odometry distance, a prior's row) relative to its limit
      (`jaxloc._model.gates.worst_measurement`); above 1 the estimate is
      `inconsistent_fit`. NaN where not computed (a start).
    - `blunder_nees`: how far an undetected blunder could have moved the estimate: the
      largest NEES (under the estimate's own position covariance) that a gross error in
      any one measurement adds to an end-of-cycle position while its own normalized
      residual stays at the sighting gate's limit, where that gate catches it only
      about half the time (Baarda's external reliability, to first order;
      `jaxloc._model.gates.blunder_shifts`). Large where some measurement is barely
      checked by the others: the concurrent strategy's C1 bearings (leverage 0.958-0.999
      on the paper's formation) leave a blunder there unseen by any test on the cycle's
      data. Reported, not gated. `inf` where the
      information is singular; NaN where not computed (a start, the tracker).
    """

    solver_result: RESULTS
    chi2: Float[Array, ""]
    chi2_min: Float[Array, ""]
    dof: Int[Array, ""]
    chi2_limit: Float[Array, ""]
    observable: Bool[Array, ""]
    worst_sighting: Float[Array, ""]
    blunder_nees: Float[Array, ""]


class CycleStarts(eqx.Module):
    """Other starts for a refinement: the closed form's other local minima (the concurrent
    strategy's runner-up scales with their own overhead pose, and the winning scales with
    the overhead solver's runner-up pose, e.g. the mirror pose of nearly coplanar points).

    **Fields:** `scales` `(k, steps)`, the formations' metric scales of each start;
    `T_world_overhead` `(k, 7)`, the overhead camera's optical-frame pose (`wxyz_xyz`);
    `ok` `(k,)`, whether each start exists.
    """

    scales: Float[Array, "k steps"]
    T_world_overhead: Float[Array, "k 7"]
    ok: Bool[Array, " k"]


def start_placements(starts: CycleStarts, scales, strategy: str, T0_place):
    """The starts as placements: `(T_place (k, placements, 7), T_over (k, 7), active
    (k,))`, each start's formation the estimate's placements `T0_place` rescaled from the
    estimate's `scales` to the start's (identity where a start does not exist)."""
    ks, _ = first_sighting(strategy)
    factor = starts.scales / scales[None]
    T_place = jnp.concatenate(
        [jnp.broadcast_to(T0_place[:, :4], (factor.shape[0],) + T0_place[:, :4].shape),
         T0_place[None, :, 4:] * factor[:, ks, None]],
        axis=-1,
    )  # fmt: skip
    T_over = starts.T_world_overhead
    active = starts.ok & jnp.all(jnp.isfinite(T_place), axis=(1, 2))
    active = active & jnp.all(jnp.isfinite(T_over), axis=1)
    ident = jnp.zeros(7, T_over.dtype).at[0].set(1.0)
    T_place = jnp.where(active[:, None, None], T_place, T0_place[None])
    return T_place, jnp.where(active[:, None], T_over, ident[None]), active


class RejectedSightings(eqx.Module):
    """The sightings a robust refinement ([`jaxloc.refine_cycle`][] with a `loss`) left
    out as outliers.

    **Fields:** `mutual` `(steps, 3, 3)` bool, `[k, i, j]`: ground robot `i`'s sighting of
    robot `j` at step `k` (robots 0, 1, 2 = C1, C2, C3; the diagonal is False);
    `overhead` `(steps, 3)` bool, `[k, j]`: the overhead camera C's sighting of robot `j`
    at step `k`. List them with [`jaxloc.rejected_sightings`][].
    """

    mutual: Bool[Array, "steps 3 3"]
    overhead: Bool[Array, "steps 3"]


class CycleEstimate(eqx.Module):
    """Estimated poses of one localization cycle.

    **Fields:**

    - `poses`: a [`jaxloc.CyclePoses`][]: every ground robot's body pose at every step,
      and the overhead camera's optical-frame pose, in the world frame `W` (C1's body frame
      at the start of the cycle), metres.
    - `scales`: metric scale applied to each step's formation (circumdiameter-1 units to
      metres), shape `(steps,)`; all equal for the sequential strategy.
    - `result`: a [`jaxloc.RESULTS`][] for the whole cycle, gates included:
      `successful` means consistent with the measurements and observable (DESIGN §7).
    - `stats`: diagnostics only (nothing branches on them): `"min_angle"` (rad, smallest
      triangle angle over the steps), `"odometry_rms"` (m, odometry residual), the
      overhead solver's `"planarity"`, `"collinearity"`, `"num_valid_candidates"`,
      `"rms_angular_error"`; a refinement adds `"num_steps"`, `"rms_pixel_error"` and, for
      a multi-start, `"start_picked"` and `"runner_up_chi2"`.
    - `checks`: a [`jaxloc.FitCheck`][]: the gates' statistics and the status before them.
    - `covariance`: the first-order [`jaxloc.CycleCovariance`][] at the estimate (what the
      observability gate inverted; zeros where not positive definite).
    - `alternatives`: a [`jaxloc.CycleStarts`][] (the concurrent strategy's closed form with the
      robust overhead solver) or `None`.
    - `rejected`: a [`jaxloc.RejectedSightings`][] (a refinement with a robust `loss`: the
      sightings left out as outliers) or `None`.
    - `stand_in`: `(steps, 3, 3)` bool or `None` (a closed form's): `[k, i, j]`, robot
      `i`'s missing bearing of robot `j` at step `k` was filled with a stand-in azimuth on
      the cone the triangle's other bearings put it on (the estimate is `too_few_points`;
      [`jaxloc.refine_cycle`][] searches the azimuth from several starts, and copies
      the mask to its estimate).
    """

    poses: CyclePoses
    scales: Float[Array, " steps"]
    result: RESULTS
    stats: dict[str, Array]
    checks: FitCheck
    covariance: CycleCovariance
    alternatives: CycleStarts | None = None
    rejected: RejectedSightings | None = None
    stand_in: Bool[Array, "steps 3 3"] | None = None

    @classmethod
    def from_poses(
        cls, poses: CyclePoses, *, scales=None, result: RESULTS = RESULTS.successful
    ) -> "CycleEstimate":
        """An estimate made of given poses (e.g. a start for [`jaxloc.refine_cycle`][]
        from your own initial guess): `checks` and `covariance` are not computed (NaN,
        zeros), `scales` default to ones, `result` to `successful`."""
        T = poses.T_world_body.wxyz_xyz
        dtype, steps = T.dtype, T.shape[-3]
        placements = {4: 6, 3: 7}[steps]
        n = 6 * placements
        nan = jnp.full(T.shape[:-3], jnp.nan, dtype)
        checks = FitCheck(
            result, nan, nan, jnp.zeros(T.shape[:-3], jnp.int32), nan,
            jnp.zeros(T.shape[:-3], bool), nan, nan,
        )  # fmt: skip
        zeros = jnp.zeros(T.shape[:-3] + (4, 3, 3), dtype)
        covariance = CycleCovariance(
            jnp.zeros(T.shape[:-3] + (n, n), dtype), zeros, zeros, jnp.zeros(T.shape[:-3], bool)
        )
        scales = jnp.ones(T.shape[:-3] + (steps,), dtype) if scales is None else scales
        return cls(poses, scales, result, {}, checks, covariance)


def rejected_sightings(estimate: CycleEstimate) -> list[tuple[str, int, str, str]]:
    """The sightings a robust refinement rejected, for people: a list of `(kind, step,
    observer, target)`, `kind` `"mutual"` (a ground robot's sighting of another) or
    `"overhead"` (the overhead camera's sighting of a ground robot), `step` the cycle's
    step (int), `observer` and `target` robot names of `jaxloc.CAMERAS` (`"C"`, `"C1"`,
    ...). Empty when `estimate.rejected` is `None` (no robust loss) or nothing was
    rejected. One estimate (not a batch); eager (reads the arrays).

    **Arguments:** `estimate`, a [`jaxloc.CycleEstimate`][].

    **Returns:** the list, mutual sightings first, each kind ordered by step, observer,
    target.
    """
    rejected = estimate.rejected
    if rejected is None:
        return []
    mutual, overhead = np.asarray(rejected.mutual), np.asarray(rejected.overhead)
    if mutual.ndim != 3 or overhead.ndim != 2:
        raise ValueError(
            "`rejected_sightings` lists one estimate's sightings; got a batch of shape "
            f"{mutual.shape[:-3]} (index it first, e.g. `jax.tree.map(lambda x: x[0], est)`)."
        )
    out = [("mutual", int(k), CAMERAS[i + 1], CAMERAS[j + 1]) for k, i, j in np.argwhere(mutual)]
    out += [("overhead", int(k), "C", CAMERAS[j + 1]) for k, j in np.argwhere(overhead)]
    return out
