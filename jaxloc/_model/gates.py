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
  definite beyond rounding (with every whitened row scaled to unit norm and the result
  Jacobi-scaled to a unit diagonal, its smallest eigenvalue above
  `MIN_SCALED_EIGENVALUE`, tested through the trace of the scaled inverse: a Cholesky
  alone passes an exactly singular matrix whose pivot rounds to a tiny positive number,
  e.g. a rotation no sighting present touches at a placement that is not an end-of-cycle
  pose; see [`nonsingular_information`][]) and the bound it implies for every
  end-of-cycle pose sensible for the formation: position RMSE below
  `MAX_RELATIVE_POSITION_BOUND` times the formation's size (the RMS distance of the
  ground robots' placements from their centroid) and rotation RMSE below
  `MAX_ROTATION_BOUND`. Singular or absurd: `unobservable` (too few distinct placements
  seen by the overhead camera, a robot no camera sees, zero-length moves, a
  near-collinear formation).
- **One sighting against the rest** (Baarda's data snooping): each pixel sighting's and
  each odometry distance's residual at the linearized optimum, normalized by its own
  redundancy, `T = r_b^T (I - J_b C J_b^T)^-1 r_b` (`C = (J^T J)^-1`: the residual's own
  covariance is `I - J_b C J_b^T`, not `I`), against its quantile at a family-wise
  `1 - CHI2_QUANTILE` over the measurements present ([`sighting_limits`][]). A gross
  error in a measurement that the others control only weakly (an odometry distance
  scaled by 20 %, with redundancy 0.1: whitened residual ~2, normalized ~6) moves the
  estimate by many of its standard deviations yet barely raises the total chi-square;
  this gate sees it. A measurement no other controls (redundancy 0) cannot be tested.
"""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jax.scipy.special import ndtri
from jaxtyping import Array, Float, Int

from .._core.least_squares import solve_spd
from .._core.linalg import (
    adjugate3,
    row_equilibrated_gram,
    scaled_inverse_trace,
    small_spd_inverse,
    spd_inverse,
)
from .._core.results import RESULTS
from .._cycle.estimate import CycleCovariance, CycleEstimate, FitCheck, start_placements
from .._cycle.layout import placement_ids
from .._cycle.rig import Rig
from .covariance import (
    covariance_of_tangent,
    estimate_placements,
    final_offsets,
    final_position_jacobian,
    with_offset,
)
from .measurements import (
    CycleData,
    normal_equations_of_blocks,
    pack,
    unknowns_jacobian,
    unpack,
    whitened_blocks,
)
from .mirrors import CONVERGED_DECREMENT, flip_active, flip_start, mirror_start, MIRROR_STEPS


#: Quantile of the chi-square gate's threshold.
CHI2_QUANTILE = 0.999
_Z_999 = 3.0902  # standard normal quantile of CHI2_QUANTILE
#: Squared whitened norm of one pixel sighting (its two residuals) above which a robust
#: refinement rejects it as an outlier ([`jaxloc.refine_cycle`][] with a `loss`): the
#: `CHI2_QUANTILE` quantile of one sighting's squared norm under the rig's noise model.
#: "gaussian": chi-square(2), `-2 ln(1 - 0.999)` = 13.8155 (norm 3.72 sigma); "paper"
#: (radius ~ N(0, sigma), uniform direction, per-axis sigma `sigma / sqrt(2)`): `2
#: chi-square(1)`, `2 x 3.2905^2` = 21.6551 (norm 4.65). At a fit the residuals are
#: smaller than the noise (by the leverage of the sightings), so clean sightings are
#: rejected at a rate below 0.1% each.
SIGHTING_LIMIT = {"gaussian": 13.8155, "paper": 21.6551}
#: Smallest eigenvalue of the row-equilibrated, Jacobi-scaled Fisher information of an
#: observable estimate, in float64 ([`nonsingular_information`][]; the rule of
#: `jaxloc._study.robustness.nonsingular`): an exactly singular direction sits at
#: rounding level, 1e-16-1e-13. Clean cycles of the paper's scenario sit far above:
#: smallest 4.0e-5 (sequential) and 1.6e-5 (concurrent) over 4096 refined cycles each
#: (1% quantile 1.5e-4 / 1.6e-4, median 2.9e-4 / 2.7e-4); a noiseless cycle 3.4e-4
#: (`benchmarks/observability_rows.py`). In float32 the floor is `eps` (1.2e-7; a floor
#: with float64's margin over rounding would reject clean cycles there); see
#: [`min_scaled_eigenvalue`][].
MIN_SCALED_EIGENVALUE = 1e-10
#: Largest information matrix [`nonsingular_information`][] inverts by Gauss--Jordan
#: elimination (the one-step update's 7 x 7; a cycle's 30-42 unknowns use a Cholesky).
_SMALL_INVERSE_SIZE = 8
#: Largest position bound (RMSE, m) of an end-of-cycle pose, relative to the formation's
#: size, for the pose to count as observable: a pose whose uncertainty is as large as the
#: formation is not known. The paper's formation (size ~0.9 m) has bounds of 1-15 cm
#: (0.01-0.15 of its size); random formations in the tests reach 0.6; a singular or
#: nearly singular information matrix gives bounds of metres to kilometres.
MAX_RELATIVE_POSITION_BOUND = 1.0
#: Largest rotation bound (RMSE, rad) of an end-of-cycle pose for it to count as
#: observable (~57 deg; the paper's bounds are 0.5-2 deg).
MAX_ROTATION_BOUND = 1.0
#: Two distinct minima whose chi-squares differ by less than this (a likelihood ratio
#: below e^2 ~ 7) make an estimate `ambiguous`.
AMBIGUITY_MARGIN = 4.0
#: The margin of `ambiguous` for a refinement that searched a stand-in bearing's azimuth
#: (`jaxloc._refine.azimuth`): its minima are discrete hypotheses the data weigh weakly,
#: and with `AMBIGUITY_MARGIN` the search marked wrong poses `successful` whose rival
#: (the true pose) was 4.5-6.5 above them (concurrent strategy, 5% of the sightings
#: missing, `python benchmarks/missing_data.py`).
STAND_IN_MARGIN = 9.0
#: Two solutions whose overhead cameras are farther apart than this (m) are distinct
#: minima.
DISTINCT_MINIMUM = 0.1
#: Gauss--Newton steps taken from a closed-form estimate towards the maximum-likelihood
#: optimum, to measure the estimate's offset from it (a fixed count, so a batch of gates
#: never waits for a straggler). From a closed form ~1 m away one linearized step
#: misjudges the offset; four reach the optimum to well below its own uncertainty.
POLISH_STEPS = 4


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


#: Redundancy (the unexplained share `1 - h` of a measurement's variance) below which the
#: sighting test treats a measurement as uncontrolled: its residual is then ~0 by
#: construction and dividing by the redundancy would only amplify rounding.
MIN_REDUNDANCY = 1e-3


def sighting_limits(num_measurements, noise_model: str, dtype):
    """`(pixel sighting, odometry distance)` limits of the normalized residual statistic
    `T` (see the module docstring) at a family-wise false-alarm rate `1 - CHI2_QUANTILE`
    over `num_measurements` (Bonferroni: each at `(1 - CHI2_QUANTILE) / n`). A pixel
    sighting's `T` is chi-square(2) for "gaussian" noise, `2 chi-square(1)` for "paper"
    noise (see [`SIGHTING_LIMIT`][]); a distance's is chi-square(1)."""
    alpha = (1.0 - CHI2_QUANTILE) / jnp.maximum(jnp.asarray(num_measurements, dtype), 1.0)
    z2 = ndtri(1.0 - 0.5 * alpha) ** 2
    pixel = 2.0 * z2 if noise_model == "paper" else -2.0 * jnp.log(alpha)
    return pixel, z2


def redundancies(J, covariance, pairs: int, floor):
    """Each measurement's share of its own noise that a least-squares fit does not absorb:
    `(pixel (pairs, 2, 2), single (rows,))`, `(1 + floor) I - P_b` for a pixel sighting
    (`P_b = J_b C J_b^T` its leverage block, its two whitened rows of `J` `(m, n)`; `C =
    covariance = (J^T J)^-1`) and `max(1 - P, 0) + floor` for a single row. Rows as in
    [`standardized_squares`][]."""
    Jb = J[: 2 * pairs].reshape(pairs, 2, -1)
    P = jnp.einsum("sai,ij,sbj->sab", Jb, covariance, Jb)
    Jr = J[2 * pairs :]
    leverage = jnp.einsum("mi,ij,mj->m", Jr, covariance, Jr)
    eye = jnp.eye(2, dtype=J.dtype)[None]
    return eye * (1.0 + floor) - P, jnp.maximum(1.0 - leverage, 0.0) + floor


def standardized_squares(r, J, covariance, pairs: int, floor):
    """Baarda's standardized squared residuals of a least-squares fit: `(pixel (pairs,),
    single (rows,))`. The first `2 pairs` rows of the whitened residuals `r` `(m,)` and
    their Jacobian `J` `(m, n)` are pixel sightings (two rows each), the rest single rows
    (odometry distances); `covariance = (J^T J)^-1` `(n, n)`. A sighting's statistic is
    `r_b^T ((1 + floor) I - P_b)^-1 r_b`, `P_b = J_b C J_b^T` its leverage (the fit
    absorbs `P_b` of its noise), a row's `r^2 / (max(1 - P, 0) + floor)`: `floor` keeps
    a measurement the fit leans on entirely (its residual ~0 by construction) from
    amplifying rounding. Where the 2 x 2 system is not positive, the plain squares."""
    C, redundancy = redundancies(J, covariance, pairs, floor)
    rb = r[: 2 * pairs].reshape(pairs, 2)
    det = C[:, 0, 0] * C[:, 1, 1] - C[:, 0, 1] * C[:, 1, 0]
    quad = C[:, 1, 1] * rb[:, 0] ** 2 - 2.0 * C[:, 0, 1] * rb[:, 0] * rb[:, 1]
    quad = quad + C[:, 0, 0] * rb[:, 1] ** 2
    good = det > 0
    pixel = jnp.where(good, quad / jnp.where(good, det, 1.0), jnp.sum(rb * rb, axis=-1))
    return pixel, r[2 * pairs :] ** 2 / redundancy


def worst_measurement(r, J, covariance, pairs: int, num_measurements, noise_model: str):
    """The largest [`standardized_squares`][] statistic of any one measurement relative to
    its limit ([`sighting_limits`][] over `num_measurements`; above 1: that measurement
    contradicts the others), from whitened residuals `r` `(m,)` at the linearized
    optimum, their Jacobian `J` `(m, n)` and `covariance = (J^T J)^-1` `(n, n)`; the
    first `2 pairs` rows are pixel sightings (row pairs), the rest single rows (odometry
    distances, priors). Rows of a missing measurement (zero weight) score 0."""
    t_pixel, t_single = standardized_squares(r, J, covariance, pairs, MIN_REDUNDANCY)
    pixel, single = sighting_limits(num_measurements, noise_model, r.dtype)
    return jnp.maximum(
        jnp.max(t_pixel, initial=0.0) / pixel, jnp.max(t_single, initial=0.0) / single
    )


def blunder_shifts(J, covariance, position_jacobian, position_covariance, pairs: int,
                   num_measurements, noise_model: str):  # fmt: skip
    """Baarda's external reliability of a least-squares fit, per measurement: `(pixel
    (pairs,), single (rows,))`, the largest NEES that a blunder in that one measurement
    adds to any end-of-cycle position while it stays hidden from
    [`standardized_squares`][]'s test: its noise-free statistic at the test's limit
    ([`sighting_limits`][]; detected about half the time). Rows as in
    [`worst_measurement`][]: whitened Jacobian `J` `(m, n)`, `covariance = (J^T J)^-1`;
    `position_jacobian` `(4, 3, n)` maps the tangent to the end-of-cycle positions, whose
    covariance is `position_covariance` `(4, 3, 3)` (a position with none, the gauge,
    counts 0). A blunder `b` in a sighting's two whitened rows moves the tangent by `C
    J_s^T b` and raises its statistic by `b^T R b`, `R = I - J_s C J_s^T`
    ([`redundancies`][], floored as the test floors it); the largest NEES under `b^T R b
    = limit` is `limit` times the largest eigenvalue of `R^-1 M`, `M` the NEES's
    quadratic form in `b`."""
    W = jnp.einsum("cin,nk,mk->cim", position_jacobian, covariance, J)  # (4, 3, m)
    adj, det = jax.vmap(adjugate3)(position_covariance)
    good = det > 0
    scale = jnp.where(good, 1.0 / jnp.where(good, det, 1.0), 0.0)
    information = adj * scale[:, None, None]
    Wp = W[:, :, : 2 * pairs].reshape(4, 3, pairs, 2)
    M = jnp.einsum("cisa,cij,cjsb->csab", Wp, information, Wp)  # (4, pairs, 2, 2)
    R, redundancy = redundancies(J, covariance, pairs, MIN_REDUNDANCY)
    det_R = R[:, 0, 0] * R[:, 1, 1] - R[:, 0, 1] * R[:, 1, 0]
    det_R = jnp.maximum(det_R, MIN_REDUNDANCY**2)
    # R^-1 M = adj(R) M / det(R), 2 x 2: the larger root of its characteristic polynomial.
    adj_R = jnp.stack(
        [jnp.stack([R[:, 1, 1], -R[:, 0, 1]], -1), jnp.stack([-R[:, 1, 0], R[:, 0, 0]], -1)], -2
    )
    A = jnp.einsum("sab,csbd->csad", adj_R, M) / det_R[None, :, None, None]
    half_trace = 0.5 * (A[..., 0, 0] + A[..., 1, 1])
    det_A = A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0]
    largest = half_trace + jnp.sqrt(jnp.maximum(half_trace**2 - det_A, 0.0))
    Wr = W[:, :, 2 * pairs :]
    row_nees = jnp.einsum("cik,cij,cjk->ck", Wr, information, Wr)  # (4, rows)
    pixel_limit, single_limit = sighting_limits(num_measurements, noise_model, J.dtype)
    return (
        pixel_limit * jnp.max(largest, axis=0),
        single_limit * jnp.max(row_nees, axis=0) / redundancy,
    )


def worst_sighting(r, J, covariance, data: CycleData, noise_model: str) -> Float[Array, ""]:
    """[`worst_measurement`][] of a cycle's fit, rows as [`whitened_blocks`][] orders them
    (pixel sightings as row pairs, then the odometry distances)."""
    pairs = (r.shape[0] - data.odometry.shape[-1]) // 2
    num_measurements = data.num_sightings + data.num_odometry
    return worst_measurement(r, J, covariance, pairs, num_measurements, noise_model)


def formation_size(T_place: Float[Array, "placements 7"]) -> Float[Array, ""]:
    """RMS distance (m) of the ground robots' placements from their centroid."""
    p = T_place[:, 4:]
    return jnp.sqrt(jnp.mean(jnp.sum((p - jnp.mean(p, axis=0, keepdims=True)) ** 2, axis=-1)))


def min_scaled_eigenvalue(dtype) -> float:
    """The floor of the Jacobi-scaled information's smallest eigenvalue in `dtype`:
    `MIN_SCALED_EIGENVALUE`, or `eps` where that is larger (float32)."""
    return max(MIN_SCALED_EIGENVALUE, float(jnp.finfo(dtype).eps))


def nonsingular_information(J: Float[Array, "m n"]) -> Array:
    """Whether the Fisher information `J^T J` of a whitened Jacobian `J` `(m, n)` is
    nonsingular beyond rounding: the smallest eigenvalue of its row-equilibrated form
    (`jaxloc._core.linalg.row_equilibrated_gram`: each measurement counted once, whatever
    its sigma), Jacobi-scaled to a unit diagonal, above [`min_scaled_eigenvalue`][],
    tested through `1 / trace` of the scaled inverse (a lower bound within a factor `n`;
    `jaxloc._core.linalg.scaled_inverse_trace`). A Cholesky of `J^T J` alone passes an
    exactly singular information whose pivot rounds to a tiny positive number; the
    Jacobi-scaled `J^T J` without the row scaling puts an observable noiseless cycle
    (pixels at the 1e-6 px floor, the scale from 1 % odometry) at 1e-14, beside the 1e-16
    of a free rotation. The one observability test of every estimate's information
    (closed forms, refinements, the one-step update); LAPACK-free."""
    G = row_equilibrated_gram(J)
    invert = small_spd_inverse if G.shape[0] <= _SMALL_INVERSE_SIZE else spd_inverse
    return _beyond_rounding(G, *invert(G))


def _beyond_rounding(G, inverse, ok) -> Array:
    """[`nonsingular_information`][]'s test of a row-equilibrated information `G` and its
    inverse (with the inverse's `ok` flag)."""
    floor = min_scaled_eigenvalue(G.dtype)
    return ok & (scaled_inverse_trace(G, inverse) * floor < 1.0)


def observable(covariance: CycleCovariance, size) -> Array:
    """Whether the covariance describes observable poses (see the module docstring)."""
    pos = jnp.sqrt(jnp.trace(covariance.position, axis1=-2, axis2=-1))
    rot = jnp.sqrt(jnp.trace(covariance.rotation, axis1=-2, axis2=-1))
    ok = covariance.ok & jnp.all(jnp.isfinite(pos)) & jnp.all(jnp.isfinite(rot))
    return (
        ok & jnp.all(pos <= MAX_RELATIVE_POSITION_BOUND * size) & jnp.all(rot <= MAX_ROTATION_BOUND)
    )


def _gauss_newton_move(X, r, B, strategy: str):
    """One undamped Gauss--Newton step from the placements `X = (T_place, T_over)`, whose
    whitened residuals and blocks are `r, B`: `(moved X, predicted decrease, solved)`. A
    step that is not finite is not taken."""
    _, H, g = normal_equations_of_blocks(r, B, strategy)
    delta, solved = solve_spd(H, -g)
    moved = unpack(delta, *X)
    finite = jnp.all(jnp.isfinite(moved[0])) & jnp.all(jnp.isfinite(moved[1]))
    moved = jax.tree.map(lambda a, b: jnp.where(finite, a, b), moved, X)
    return moved, -g @ delta, solved


def _gauss_newton_step(X, data: CycleData, rig: Rig, strategy: str):
    """[`_gauss_newton_move`][] at `X`: `(moved X, r, B, predicted decrease, solved)`,
    `r, B` of [`whitened_blocks`][] at `X`."""
    r, B = whitened_blocks(*X, data, rig, strategy)
    moved, predicted, solved = _gauss_newton_move(X, r, B, strategy)
    return moved, r, B, predicted, solved


def _polished(
    T_place, T_over, data: CycleData, rig: Rig, strategy: str, polish, steps: int, late=None
):  # fmt: skip
    """The point the gates look at and its whitened residuals and blocks: `steps`
    Gauss--Newton steps from `(T_place, T_over)` where `polish` (a boolean, traced or
    not: per lane under `vmap`), else none, then one evaluation, in one `fori_loop` (one
    traced copy of the model, differentiable). Returns `(P, O, r, B)`, `r, B` of
    [`whitened_blocks`][] at `(P, O)`.

    `late`: `None` or another point `(T_place, T_over, data)` evaluated where it is, in
    one more iteration after the first point's evaluation; then the result is a pair
    `((P, O, r, B), (T_place, T_over, r, B))`. Under `vmap` every lane runs the loop's
    whole length: this fills the lanes of a batch of polished points with evaluations
    of unpolished ones, at the cost of one iteration instead of one lane each."""
    at = jnp.where(polish, steps, 0)  # the iteration that evaluates the point
    length = steps + 1 + (late is not None)
    r0, B0 = jax.eval_shape(lambda: whitened_blocks(T_place, T_over, data, rig, strategy))
    zeros = jnp.zeros(r0.shape, r0.dtype), jnp.zeros(B0.shape, B0.dtype)

    def step(i, carry):
        X, r_at, B_at = carry[:3]
        evaluate = (X, data) if late is None else jax.tree.map(
            lambda a, b: jnp.where(i == steps + 1, b, a), (X, data), ((late[0], late[1]), late[2])
        )  # fmt: skip
        r, B = whitened_blocks(*evaluate[0], evaluate[1], rig, strategy)
        # `i` is the same in every lane: the evaluations take no step.
        moved = jax.lax.cond(
            i < steps, lambda: _gauss_newton_move(X, r, B, strategy)[0], lambda: X
        )
        here = i == at
        r_at, B_at = jnp.where(here, r, r_at), jnp.where(here, B, B_at)
        X = jax.tree.map(lambda a, b: jnp.where(i >= at, b, a), moved, X)
        if late is None:
            return X, r_at, B_at
        last = i == steps + 1
        return X, r_at, B_at, jnp.where(last, r, carry[3]), jnp.where(last, B, carry[4])

    carry = ((T_place, T_over), *zeros) + (zeros if late is not None else ())
    out = jax.lax.fori_loop(0, length, step, carry)
    (P, O), r, B = out[:3]
    if late is None:
        return P, O, r, B
    return (P, O, r, B), (late[0], late[1], *out[3:])


def _second_minimum(P, O, data: CycleData, rig: Rig, strategy: str):
    """The chi-square of the best second minimum of the point `(P, O)` (`inf` if none):
    `MIRROR_STEPS` Gauss--Newton steps from its [`mirror_start`][] and from its
    [`flip_start`][], then one evaluation each. A start counts when it is active, its
    polished point is a minimum (every solve succeeded and the last step predicted a
    decrease below `CONVERGED_DECREMENT`) and it is more than `DISTINCT_MINIMUM` from
    the point (the mirrored placement, resp. the overhead camera's centre).

    Both starts as one `vmap` over a `while_loop` that runs only while a start is
    active: a batch in which no point lacks a sighting (almost every clean batch) takes
    no step. The starts carry no derivatives (their inputs are stop-gradient'ed: only
    the status depends on them), so the loop need not be reverse-differentiable."""
    P, O, data, rig = jax.lax.stop_gradient((P, O, data, rig))
    mirrored, index, mirror_on = mirror_start(P, data, strategy)
    flipped, flip_defined = flip_start(P, O)
    starts = jnp.stack([mirrored, P]), jnp.stack([O, flipped])
    active = jnp.stack([mirror_on, flip_defined & flip_active(data)])

    def polished(start, active):
        def body(carry):
            i, X, _, decrement, ok = carry
            moved, r, _, predicted, solved = _gauss_newton_step(X, data, rig, strategy)
            last = i == MIRROR_STEPS  # evaluate there, do not move
            X = jax.tree.map(lambda a, b: jnp.where(last, b, a), moved, X)
            decrement = jnp.where(last, decrement, predicted)
            return i + 1, X, jnp.sum(r**2), decrement, ok & (last | solved)

        inf = jnp.array(jnp.inf, P.dtype)
        carry = (jnp.array(0), start, inf, inf, jnp.array(True))
        _, X, chi2, decrement, ok = jax.lax.while_loop(
            lambda c: active & (c[0] <= MIRROR_STEPS), body, carry
        )
        minimum = active & ok & (decrement < CONVERGED_DECREMENT) & jnp.isfinite(chi2)
        return X, jnp.where(minimum, chi2, inf)

    (X_place, X_over), chi2 = jax.vmap(polished)(starts, active)
    distance = jnp.stack([
        jnp.linalg.norm(X_place[0, index, 4:] - P[index, 4:]),
        jnp.linalg.norm(X_over[1, 4:] - O[4:]),
    ])  # fmt: skip
    return jnp.min(jnp.where(distance > DISTINCT_MINIMUM, chi2, jnp.inf))


def mark_ambiguous(result: RESULTS, chi2, runner_up_chi2, margin=AMBIGUITY_MARGIN) -> RESULTS:
    """`ambiguous` where a `successful` estimate has a distinct rival minimum whose
    chi-square `runner_up_chi2` is within `margin` of its own."""
    close = runner_up_chi2 - chi2 < margin
    return RESULTS.where((result == RESULTS.successful) & close, RESULTS.ambiguous, result)


def end_poses(T_place, T_over, strategy: str) -> Float[Array, "4 7"]:
    """End-of-cycle poses (C's optical frame, C1, C2, C3) of placements `T_place`."""
    return jnp.concatenate([T_over[None], T_place[placement_ids(strategy)[-1]]])


def _pose_differences(T_a, T_b) -> tuple[Float[Array, "4 3"], Float[Array, "4 3"]]:
    """`(position a - b, log(R_b^-1 R_a))` of two stacks of poses `(4, 7)`: the exact
    counterparts of the tangent's position and rotation blocks."""
    a, b = jaxlie.SE3(T_a), jaxlie.SE3(T_b)
    rotation = jax.vmap(lambda ra, rb: (rb.inverse() @ ra).log())(a.rotation(), b.rotation())
    return a.translation() - b.translation(), rotation


def _gates_at(P, O, r, B, T_place, T_over, data: CycleData, rig: Rig, strategy: str,
              solver_result: RESULTS, polished: bool, final_poses):  # fmt: skip
    """The gates of an estimate `(T_place, T_over)` with end-of-cycle poses `final_poses`,
    evaluated at `(P, O)` (whitened residuals `r` and blocks `B` there): the estimate
    itself, or its polished optimum when `polished` (a boolean, traced or not; see
    [`gate_all`][]). Returns `(result, checks, covariance)`."""
    dtype = T_place.dtype
    chi2, H, g = normal_equations_of_blocks(r, B, strategy)
    J = unknowns_jacobian(B, strategy)
    # One batched inverse of the information and its row-equilibrated form: one traced
    # Cholesky (see `nonsingular_information`).
    G = row_equilibrated_gram(J)
    inverses, oks = jax.vmap(spd_inverse)(jnp.stack([H, G]))
    ml_covariance = inverses[0]
    ok_information = oks[0] & _beyond_rounding(G, inverses[1], oks[1])
    ml_covariance = jnp.where(ok_information, ml_covariance, 0.0)
    unknowns = g.shape[0]
    dof = (2 * data.num_sightings + data.num_odometry - unknowns).astype(jnp.int32)
    # The step to the minimum of the model linearized here, and the misfit left there.
    step = -ml_covariance @ g
    chi2_min = jnp.maximum(chi2 + g @ step, 0.0)
    position_jacobian = final_position_jacobian(P, O, strategy)
    ml = covariance_of_tangent(ml_covariance, ok_information, P, O, strategy, position_jacobian)
    offset = -step
    dp, dr = final_offsets(offset, P, O, strategy)
    if polished is not False:
        own_dp, own_dr = _pose_differences(final_poses, end_poses(P, O, strategy))
        offset = offset + jnp.where(polished, pack(T_place, T_over, P, O), 0.0)
        moved = jnp.asarray(np.r_[True, placement_ids(strategy)[-1] > 0])[:, None]
        dp = dp + jnp.where(moved & polished, own_dp, 0.0)
        dr = dr + jnp.where(moved & polished, own_dr, 0.0)
    covariance = with_offset(ml, offset, dp, dr)
    limit = chi2_limit(dof, data.num_sightings, data.num_odometry, rig.noise_model, dtype)
    is_observable = observable(ml, formation_size(P)) & (dof > 0)
    ok = solver_result == RESULTS.successful
    result = RESULTS.where(ok & ~is_observable, RESULTS.unobservable, solver_result)
    worst = worst_sighting(r + J @ step, J, ml_covariance, data, rig.noise_model)
    consistent = (chi2_min <= limit) & (worst <= 1.0)
    result = RESULTS.where(
        (result == RESULTS.successful) & ~consistent, RESULTS.inconsistent_fit, result
    )
    pairs = (r.shape[0] - data.odometry.shape[-1]) // 2
    pixel, single = blunder_shifts(
        J, ml_covariance, position_jacobian, covariance.position, pairs,
        data.num_sightings + data.num_odometry, rig.noise_model,
    )  # fmt: skip
    blunder = jnp.maximum(jnp.max(pixel, initial=0.0), jnp.max(single, initial=0.0))
    blunder = jnp.where(ok_information, blunder, jnp.inf)
    checks = FitCheck(solver_result, chi2, chi2_min, dof, limit, is_observable, worst, blunder)
    return result, checks, covariance


class GatePoint(eqx.Module):
    """Where and on what an estimate is gated: its placements `(placements, 7)`, overhead
    camera `(7,)` and end-of-cycle poses `(4, 7)` of (C's optical frame, C1, C2, C3)
    (`wxyz_xyz`, in `W`), the whitened measurements, and the solver's own status. Stacked
    along a leading axis, several estimates are gated by one `vmap` ([`gate_all`][]): one
    traced copy of the gates, a smaller program."""

    T_place: Float[Array, "placements 7"]
    T_over: Float[Array, "7"]
    final_poses: Float[Array, "4 7"]
    data: CycleData
    solver_result: RESULTS


def _runner_up_chi2(chi2, T_over, active, own_T_over):
    """The lowest chi-square `chi2 (k,)` of polished rival starts (overhead cameras
    `T_over (k, 7)`, `active (k,)`) among those distinct from the solution whose overhead
    camera is at `own_T_over` (`inf` if none)."""
    distinct = jnp.sum((T_over[:, 4:] - own_T_over[None, 4:]) ** 2, axis=-1) > DISTINCT_MINIMUM**2
    return jnp.min(jnp.where(active & distinct & jnp.isfinite(chi2), chi2, jnp.inf))


def _rival_points(point: GatePoint, rivals) -> GatePoint:
    """A point's rival starts `(T_place (k, placements, 7), T_over (k, 7), active (k,))`
    as `k` stacked [`GatePoint`][]s on the point's measurements."""
    rival_place, rival_over, _ = rivals
    k = rival_place.shape[0]
    shared = jax.tree.map(
        lambda x: jnp.broadcast_to(x, (k,) + jnp.shape(x)),
        (point.final_poses, point.data, point.solver_result),
    )
    return GatePoint(rival_place, rival_over, *shared)


def gate_point(estimate: CycleEstimate, data: CycleData, strategy: str) -> GatePoint:
    """The [`GatePoint`][] of an (ungated) estimate: its placements where each first
    occurs and its end-of-cycle poses (identity where not finite: a failed solver's
    poses), its `result` as the solver's status."""
    T_place, T_over = estimate_placements(estimate.poses, strategy)
    ident = jnp.zeros(7, T_place.dtype).at[0].set(1.0)
    finite = jnp.all(jnp.isfinite(T_place)) & jnp.all(jnp.isfinite(T_over))
    T_place, T_over = jnp.where(finite, T_place, ident), jnp.where(finite, T_over, ident)
    poses = estimate.poses
    final = jnp.concatenate(
        [poses.T_world_overhead.wxyz_xyz[None], poses.T_world_body.wxyz_xyz[-1]]
    )
    final = jnp.where(jnp.all(jnp.isfinite(final)), final, ident)
    return GatePoint(T_place, T_over, final, data, estimate.result)


def gate_rivals(estimate: CycleEstimate, point: GatePoint, strategy: str):
    """The other starts an estimate carries (its `alternatives`) as its `rivals` in
    [`gate_all`][], or `None`."""
    if estimate.alternatives is None:
        return None
    return start_placements(estimate.alternatives, estimate.scales, strategy, point.T_place)


def _evaluate(points: list[GatePoint], rivals, per_point: list[bool], rig: Rig, strategy: str):
    """The [`_polished`][] evaluations of [`gate_all`][]: `(P, O, r, B)` of every point,
    stacked in the points' order, and `(r, O)` of every rival start, in the rivals'
    order. One `vmap` of one loop: the polished points and the rivals are its lanes;
    the points that are not polished are evaluated in one more iteration of the first
    lanes (in lanes of their own only where they outnumber the lanes)."""
    stack = lambda ps: jax.tree.map(lambda *x: jnp.stack(x), *ps)  # noqa: E731
    concat = lambda ps: jax.tree.map(lambda *x: jnp.concatenate(x), *ps)  # noqa: E731
    polished = [p for p, on in zip(points, per_point) if on]
    late = [p for p, on in zip(points, per_point) if not on]
    rival_points = [_rival_points(p, r) for p, r in zip(points, rivals) if r is not None]

    def run(p: GatePoint, on, steps: int, q: GatePoint | None = None):
        second = None if q is None else (q.T_place, q.T_over, q.data)
        return _polished(p.T_place, p.T_over, p.data, rig, strategy, on, steps, second)

    if not polished:
        out = late_out = jax.vmap(lambda p: run(p, False, 0))(stack(late))
    elif not late:
        first = concat([stack(polished)] + rival_points)
        out = jax.vmap(lambda p: run(p, True, POLISH_STEPS))(first)
    else:
        first = concat([stack(polished)] + rival_points)
        lanes = first.T_over.shape[0]
        width = max(lanes, len(late))
        if width > lanes:  # lanes with an evaluation only: a stand-in first point, not polished
            first = concat([first, stack(late[: width - lanes])])
        fillers = [jax.tree.map(lambda x, j=j: x[j], first) for j in range(len(late), width)]
        second = stack(late + fillers)
        on = np.arange(width) < lanes
        out, late_out = jax.vmap(lambda p, q, on: run(p, on, POLISH_STEPS, q))(first, second, on)
    lanes = len(polished) + sum(r.T_over.shape[0] for r in rival_points)
    rival_r, rival_O = out[2][len(polished) : lanes], out[1][len(polished) : lanes]
    taken = {True: 0, False: 0}
    rows = []
    for on in per_point:
        rows.append(jax.tree.map(lambda x, j=taken[on]: x[j], out if on else late_out))
        taken[on] += 1
    P, O, r, B = (jnp.stack(x) for x in zip(*rows))
    return P, O, r, B, rival_r, rival_O


def gate_all(
    points: list[GatePoint], rig: Rig, strategy: str, *, polish: bool | Sequence[bool],
    rivals=None,
):  # fmt: skip
    """Gate every point, as one `vmap`: a list of `(result, checks, covariance)`, one per
    point. `result` is the point's `solver_result` when that is a failure; else
    `unobservable` or `inconsistent_fit` when a gate fails, else `successful`.

    Where `polish` (one boolean for every point, or one per point) is true, e.g. for
    closed forms, the gates look at the point `POLISH_STEPS` Gauss--Newton steps away,
    the maximum-likelihood optimum to well within its uncertainty; elsewhere (a converged
    refinement, the true poses of a bound) at the point itself. The covariance is the
    estimate's own, to first order: the maximum-likelihood estimator's `(J^T J)^-1` there
    plus `d d^T`, `d` the estimate's offset from that point (its own end-of-cycle poses
    against the optimum's: a closed form solves a stationary robot's pose again at every
    step) and from the optimum of the model linearized there (zero at a converged
    refinement). `rivals`: per point, `None` or other starts `(T_place (k, placements,
    7), T_over (k, 7), active (k,))` (a closed form's other local minima, see
    [`gate_rivals`][]; only for polished points); polished too, a distinct one that fits
    almost as well makes the estimate `ambiguous`. So does, for every point, a second
    minimum ([`jaxloc._model.mirrors`][]): the mirror of a moved placement the overhead
    camera does not see, or the overhead camera's planar flip when a sighting is missing,
    when it is distinct from the point. The polish, the gates' Jacobian and the rivals'
    polish come from one Gauss--Newton `fori_loop`, mapped over the points and the
    rivals together (a point that is not polished is evaluated at its first iteration);
    the second minima from an early-exit `while_loop` over the points alone, which a
    batch with nothing to look for skips. Gating every estimate of a trial in one call
    traces each of these once."""
    n = len(points)
    rivals = rivals or [None] * n
    per_point = [bool(polish)] * n if isinstance(polish, bool) else [bool(p) for p in polish]
    if len(per_point) != n:
        raise ValueError(f"gate_all: {len(per_point)} polish flags for {n} points")
    if any(r is not None and not p for r, p in zip(rivals, per_point)):
        raise ValueError("gate_all: rivals are compared at their polished optima; polish them")
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *points)
    P, O, r, B, rival_r, rival_O = _evaluate(points, rivals, per_point, rig, strategy)
    mirror = jax.vmap(lambda P, O, data: _second_minimum(P, O, data, rig, strategy))(
        P, O, stacked.data
    )

    uniform = all(per_point) or not any(per_point)

    def one(p: GatePoint, P, O, r, B, polished):
        polished = per_point[0] if uniform else polished
        return _gates_at(
            P, O, r, B, p.T_place, p.T_over, p.data, rig, strategy, p.solver_result, polished,
            p.final_poses,
        )  # fmt: skip

    out = jax.vmap(one)(stacked, P, O, r, B, np.asarray(per_point))
    rival_chi2 = jnp.sum(rival_r**2, axis=-1)
    gates, lane = [], 0
    for i, rival in enumerate(rivals):
        result, checks, covariance = jax.tree.map(lambda x, i=i: x[i], out)
        runner_up = mirror[i]
        if rival is not None:
            k = rival[0].shape[0]
            chi2 = rival_chi2[lane : lane + k]
            runner_up = jnp.minimum(
                runner_up, _runner_up_chi2(chi2, rival_O[lane : lane + k], rival[2], O[i])
            )
            lane += k
        result = mark_ambiguous(result, checks.chi2, runner_up)
        gates.append((result, checks, covariance))
    return gates


def gated(estimate: CycleEstimate, gate) -> CycleEstimate:
    """`estimate` with the result, checks and covariance of its gates."""
    result, checks, covariance = gate
    return eqx.tree_at(
        lambda e: (e.result, e.checks, e.covariance), estimate, (result, checks, covariance)
    )
