r"""The gates every cycle estimate passes before it is called `successful` (DESIGN §7).

One mechanism for the closed forms and the refinement alike, at the estimate:

- **Goodness of fit**: the chi-square of the whitened residuals against its degrees of
  freedom, with the residuals' part that a small move of the poses would remove taken
  out: `chi2_min = r^T r - g^T (J^T J)^-1 g` (`g = J^T r`), the minimum of the model
  linearized at the estimate. At a converged refinement `g = 0` and it is the plain
  chi-square; at a closed form (not the maximum-likelihood estimate, so its plain
  residuals are larger than noise explains, by its distance from the optimum) it is the
  misfit no nearby pose can explain, with the same distribution under the noise model.
  Gaussian pixel noise gives `chi2_min ~ chi-square(dof)`. The paper's model
  (radius ~ N(0, sigma), uniform direction) has heavier tails: a whitened sighting is
  `2 chi-square(1)` (mean 2, variance 8, not 4), so `chi2` is matched in mean and
  variance by `c chi-square(dof / c)`, `c = variance / (2 mean)`. Above its 99.9%
  quantile (Wilson--Hilferty) the estimate is `inconsistent_fit`: a wrong local minimum,
  a wrong closed-form branch, an outlier, swapped images. With `dof <= 0` (too few
  measurements to test anything) it is `unobservable`.
- **Observability**: the Fisher information `J^T J` at the estimate must be positive
  definite and the bound it implies for every end-of-cycle pose sensible for the
  formation: position RMSE below `MAX_RELATIVE_POSITION_BOUND` times the formation's
  size (the RMS distance of the ground robots' placements from their centroid) and
  rotation RMSE below `MAX_ROTATION_BOUND`. Singular or absurd: `unobservable` (too
  few distinct placements seen by the overhead camera, a robot no camera sees, zero-length
  moves, a near-collinear formation).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .._core.linalg import spd_inverse
from .._core.results import RESULTS
from .._cycle.estimate import CycleCovariance, CycleEstimate, FitCheck
from .._cycle.rig import Rig
from .covariance import covariance_of_tangent, estimate_placements, with_offset
from .measurements import CycleData, normal_equations


#: Quantile of the chi-square gate's threshold.
CHI2_QUANTILE = 0.999
_Z_999 = 3.0902  # standard normal quantile of CHI2_QUANTILE
#: Largest position bound (RMSE, m) of an end-of-cycle pose, relative to the formation's
#: size, for the pose to count as observable: a pose whose uncertainty is as large as the
#: formation is not known. The paper's formation (size ~0.9 m) has bounds of 1-15 cm
#: (0.01-0.15 of its size); random formations in the tests reach 0.6; a singular or
#: nearly singular information matrix gives bounds of metres to kilometres.
MAX_RELATIVE_POSITION_BOUND = 1.0
#: Largest rotation bound (RMSE, rad) of an end-of-cycle pose for it to count as
#: observable (~57 deg; the paper's bounds are 0.5-2 deg).
MAX_ROTATION_BOUND = 1.0


def chi2_limit(
    dof: Int[Array, ""], num_sightings, num_odometry, noise_model: str, dtype
) -> Float[Array, ""]:
    """The `CHI2_QUANTILE` quantile of the chi-square statistic of `num_sightings` pixel
    sightings (two residuals each) and `num_odometry` distances with `dof` degrees of
    freedom, under the rig's noise model (see the module docstring)."""
    n_sight = jnp.asarray(num_sightings, dtype)
    n_odo = jnp.asarray(num_odometry, dtype)
    per_sight_var = 8.0 if noise_model == "paper" else 4.0
    c = (per_sight_var * n_sight + 2.0 * n_odo) / jnp.maximum(2.0 * (2.0 * n_sight + n_odo), 1.0)
    c = jnp.maximum(c, 1.0)
    k = jnp.maximum(dof, 1).astype(dtype) / c
    return c * k * (1.0 - 2.0 / (9.0 * k) + _Z_999 * jnp.sqrt(2.0 / (9.0 * k))) ** 3


def formation_size(T_place: Float[Array, "placements 7"]) -> Float[Array, ""]:
    """RMS distance (m) of the ground robots' placements from their centroid."""
    p = T_place[:, 4:]
    return jnp.sqrt(jnp.mean(jnp.sum((p - jnp.mean(p, axis=0, keepdims=True)) ** 2, axis=-1)))


def observable(covariance: CycleCovariance, size) -> Array:
    """Whether the covariance describes observable poses (see the module docstring)."""
    pos = jnp.sqrt(jnp.trace(covariance.position, axis1=-2, axis2=-1))
    rot = jnp.sqrt(jnp.trace(covariance.rotation, axis1=-2, axis2=-1))
    ok = covariance.ok & jnp.all(jnp.isfinite(pos)) & jnp.all(jnp.isfinite(rot))
    return ok & jnp.all(pos <= MAX_RELATIVE_POSITION_BOUND * size) & jnp.all(
        rot <= MAX_ROTATION_BOUND
    )


def check(
    T_place, T_over, data: CycleData, rig: Rig, strategy: str, solver_result: RESULTS
) -> tuple[RESULTS, FitCheck, CycleCovariance]:
    """Gate an estimate whose placements are at `T_place` and whose overhead camera is at
    `T_over`: `(result, checks, covariance)`. `result` is `solver_result` when that is a
    failure; else `unobservable` or `inconsistent_fit` when a gate fails, else
    `successful`. The covariance is the estimate's own, to first order: the
    maximum-likelihood estimator's `(J^T J)^-1` at the estimate plus `d d^T`, `d` the step
    to the linearized optimum (zero at a converged refinement; a closed form's error is
    that offset plus the optimum's own error)."""
    dtype = T_place.dtype
    chi2, H, g = normal_equations(T_place, T_over, data, rig, strategy)
    ml_covariance, ok_information = spd_inverse(H)
    unknowns = g.shape[0]
    dof = (2 * data.num_sightings + data.num_odometry - unknowns).astype(jnp.int32)
    # The step to the minimum of the model linearized here, and the misfit left there.
    step = -ml_covariance @ g
    chi2_min = jnp.maximum(chi2 + g @ step, 0.0)
    ml = covariance_of_tangent(ml_covariance, ok_information, T_place, T_over, strategy)
    # The estimate's own covariance: the maximum-likelihood estimator's, plus the known
    # offset of this estimate from the linearized optimum (zero at a converged refinement;
    # a closed form's error is that offset plus the optimum's error).
    covariance = with_offset(ml, -step, T_place, T_over, strategy)
    limit = chi2_limit(dof, data.num_sightings, data.num_odometry, rig.noise_model, dtype)
    is_observable = observable(ml, formation_size(T_place)) & (dof > 0)
    ok = solver_result == RESULTS.successful
    result = RESULTS.where(ok & ~is_observable, RESULTS.unobservable, solver_result)
    result = RESULTS.where(
        (result == RESULTS.successful) & ~(chi2_min <= limit), RESULTS.inconsistent_fit, result
    )
    checks = FitCheck(solver_result, chi2, chi2_min, dof, limit, is_observable)
    return result, checks, covariance


class GatePoint(eqx.Module):
    """Where and on what an estimate is gated: its placements `(placements, 7)` and
    overhead camera `(7,)` (`wxyz_xyz`), the whitened measurements, and the solver's own
    status. Stacked along a leading axis, several estimates are gated by one `vmap`
    ([`gate_all`][]): one traced copy of the gates, a smaller program."""

    T_place: Float[Array, "placements 7"]
    T_over: Float[Array, "7"]
    data: CycleData
    solver_result: RESULTS


def gate_point(estimate: CycleEstimate, data: CycleData, strategy: str) -> GatePoint:
    """The [`GatePoint`][] of an (ungated) estimate: its placements where each first
    occurs (identity where not finite: a failed solver's poses), its `result` as the
    solver's status."""
    T_place, T_over = estimate_placements(estimate.poses, strategy)
    finite = jnp.all(jnp.isfinite(T_place)) & jnp.all(jnp.isfinite(T_over))
    ident = jnp.zeros(7, T_place.dtype).at[0].set(1.0)
    return GatePoint(
        jnp.where(finite, T_place, ident), jnp.where(finite, T_over, ident), data,
        estimate.result,
    )  # fmt: skip


def gate_all(points: list[GatePoint], rig: Rig, strategy: str):
    """[`check`][] of every point, as one `vmap`: a list of `(result, checks,
    covariance)`, one per point."""
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *points)
    out = jax.vmap(
        lambda p: check(p.T_place, p.T_over, p.data, rig, strategy, p.solver_result)
    )(stacked)
    return [jax.tree.map(lambda x, i=i: x[i], out) for i in range(len(points))]


def gated(estimate: CycleEstimate, gate) -> CycleEstimate:
    """`estimate` with the result, checks and covariance of its gates."""
    result, checks, covariance = gate
    return eqx.tree_at(
        lambda e: (e.result, e.checks, e.covariance), estimate, (result, checks, covariance)
    )
