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

import functools as ft

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Float, Int

from .._core.least_squares import solve_spd
from .._core.linalg import spd_inverse
from .._core.results import RESULTS
from .._cycle.estimate import CycleCovariance, CycleEstimate, FitCheck, start_placements
from .._cycle.layout import placement_ids
from .._cycle.rig import Rig
from .covariance import covariance_of_tangent, estimate_placements, final_offsets, with_offset
from .measurements import CycleData, normal_equations, pack, unpack


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


def formation_size(T_place: Float[Array, "placements 7"]) -> Float[Array, ""]:
    """RMS distance (m) of the ground robots' placements from their centroid."""
    p = T_place[:, 4:]
    return jnp.sqrt(jnp.mean(jnp.sum((p - jnp.mean(p, axis=0, keepdims=True)) ** 2, axis=-1)))


def observable(covariance: CycleCovariance, size) -> Array:
    """Whether the covariance describes observable poses (see the module docstring)."""
    pos = jnp.sqrt(jnp.trace(covariance.position, axis1=-2, axis2=-1))
    rot = jnp.sqrt(jnp.trace(covariance.rotation, axis1=-2, axis2=-1))
    ok = covariance.ok & jnp.all(jnp.isfinite(pos)) & jnp.all(jnp.isfinite(rot))
    return (
        ok & jnp.all(pos <= MAX_RELATIVE_POSITION_BOUND * size) & jnp.all(rot <= MAX_ROTATION_BOUND)
    )


def polish_point(T_place, T_over, data: CycleData, rig: Rig, strategy: str, steps: int):
    """`steps` undamped Gauss--Newton steps from `(T_place, T_over)` (no step where the
    information is singular or the step not finite): with `POLISH_STEPS`, the nearby
    maximum-likelihood optimum, to well within its uncertainty. Returns `(T_place,
    T_over, chi2)`: the point reached and its chi-square (`inf` without steps).

    One loop of `steps + 1` model evaluations, the last one at the point reached (it
    takes no step), so that the model is traced once."""

    def evaluate(i, carry):
        x = carry[:2]
        cost, H, g = normal_equations(*x, data, rig, strategy)
        delta, _ = solve_spd(H, -g)
        P, O = unpack(delta, *x)
        last = i == steps
        return (jnp.where(last, x[0], P), jnp.where(last, x[1], O), cost)

    # The loop carries the poses and one number: carrying the normal equations out of it
    # as well (for the gates) made localize_cycle 1.3-1.7x slower on CPU (batch 256).
    start = (T_place, T_over, jnp.array(jnp.inf, T_place.dtype))
    return jax.lax.fori_loop(0, steps + 1, evaluate, start) if steps else start


def mark_ambiguous(result: RESULTS, chi2, runner_up_chi2) -> RESULTS:
    """`ambiguous` where a `successful` estimate has a distinct rival minimum whose
    chi-square `runner_up_chi2` is within `AMBIGUITY_MARGIN` of its own."""
    close = runner_up_chi2 - chi2 < AMBIGUITY_MARGIN
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


def _gates_at(point: "GatePoint", polished, P, O, rig: Rig, strategy: str):
    """The gates of `point`, evaluated at `(P, O)`: the estimate itself, or its polished
    optimum where `polished` (a bool, traced: see [`gate_all`][]). Returns `(result,
    checks, covariance)`."""
    T_place, T_over, data = point.T_place, point.T_over, point.data
    dtype = T_place.dtype
    chi2, H, g = normal_equations(P, O, data, rig, strategy)
    ml_covariance, ok_information = spd_inverse(H)
    unknowns = g.shape[0]
    dof = (2 * data.num_sightings + data.num_odometry - unknowns).astype(jnp.int32)
    # The step to the minimum of the model linearized here, and the misfit left there.
    step = -ml_covariance @ g
    chi2_min = jnp.maximum(chi2 + g @ step, 0.0)
    ml = covariance_of_tangent(ml_covariance, ok_information, P, O, strategy)
    offset = -step
    dp, dr = final_offsets(offset, P, O, strategy)
    # A polished point's estimate is away from it: add the estimate's own offset.
    own_dp, own_dr = _pose_differences(point.final_poses, end_poses(P, O, strategy))
    offset = offset + jnp.where(polished, pack(T_place, T_over, P, O), 0.0)
    moved = polished & jnp.asarray(np.r_[True, placement_ids(strategy)[-1] > 0])[:, None]
    dp = dp + jnp.where(moved, own_dp, 0.0)
    dr = dr + jnp.where(moved, own_dr, 0.0)
    covariance = with_offset(ml, offset, dp, dr)
    limit = chi2_limit(dof, data.num_sightings, data.num_odometry, rig.noise_model, dtype)
    is_observable = observable(ml, formation_size(P)) & (dof > 0)
    solver_result = point.solver_result
    ok = solver_result == RESULTS.successful
    result = RESULTS.where(ok & ~is_observable, RESULTS.unobservable, solver_result)
    result = RESULTS.where(
        (result == RESULTS.successful) & ~(chi2_min <= limit), RESULTS.inconsistent_fit, result
    )
    checks = FitCheck(solver_result, chi2, chi2_min, dof, limit, is_observable)
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


def gate_all(
    points: list[GatePoint], rig: Rig, strategy: str, *, polish: bool | list[bool], rivals=None
):
    """Gate every point: a list of `(result, checks, covariance)`, one per point.
    `result` is the point's `solver_result` when that is a failure; else `unobservable`
    or `inconsistent_fit` when a gate fails, else `successful`.

    With `polish` (per point, or one flag for all; for estimates that are not converged
    refinements, e.g. closed forms) the gates look at the point `POLISH_STEPS`
    Gauss--Newton steps away, the maximum-likelihood optimum to well within its
    uncertainty. The covariance is the estimate's own, to first order: the
    maximum-likelihood estimator's `(J^T J)^-1` there plus `d d^T`, `d` the estimate's
    offset from that point (its own end-of-cycle poses against the optimum's: a closed
    form solves a stationary robot's pose again at every step) and from the optimum of
    the model linearized there (zero at a converged refinement). `rivals`: per point,
    `None` or other starts `(T_place (k, placements, 7), T_over (k, 7), active (k,))` (a
    closed form's other local minima, see [`gate_rivals`][]); polished too, a distinct
    one that fits almost as well makes the estimate `ambiguous`.

    The rivals need no more than their chi-square at their polished point, which the
    polishing loop gives. One `vmap` polishes the polished points and the rivals, one
    gates every point: each traced once, whatever the number of points."""
    if not points:
        return []
    flags = [polish] * len(points) if isinstance(polish, bool) else list(polish)
    rivals = rivals or [None] * len(points)
    # Lanes of the polishing, per kind: (point, index of its point, rival index).
    lanes = {True: [], False: []}
    for i, (point, flag) in enumerate(zip(points, flags)):
        lanes[flag].append((point, i, None))
    for i, (point, rival) in enumerate(zip(points, rivals)):
        if rival is None:
            continue
        if not flags[i]:
            raise ValueError("`rivals` are polished: give them for polished points only.")
        for k in range(rival[0].shape[0]):
            T_place, T_over = rival[0][k], rival[1][k]
            final = end_poses(T_place, T_over, strategy)
            rival_point = GatePoint(T_place, T_over, final, point.data, RESULTS.successful)
            lanes[True].append((rival_point, i, k))
    polished, rival_fits = {}, {}
    for flag, members in lanes.items():
        if not members:
            continue
        steps = POLISH_STEPS if flag else 0
        # Lanes that share their measurements (a cycle's estimates and their rivals)
        # take them unbatched: one copy, not one per lane.
        data = members[0][0].data
        shared = all(m[0].data is data for m in members)
        T_place = jnp.stack([m[0].T_place for m in members])
        T_over = jnp.stack([m[0].T_over for m in members])
        lane_data = data if shared else _stack([m[0].data for m in members])
        P, O, chi2 = jax.vmap(
            lambda P, O, d, steps=steps: polish_point(P, O, d, rig, strategy, steps),
            in_axes=(0, 0, None if shared else 0),
        )(T_place, T_over, lane_data)
        for lane, (_, i, k) in enumerate(members):
            if k is None:
                polished[i] = (P[lane], O[lane])
            else:
                rival_fits.setdefault(i, []).append((k, chi2[lane], O[lane]))
    # The gates proper of the estimates only, in one vmap (the rivals need no more than
    # their polished chi-square).
    P, O = _stack([polished[i] for i in range(len(points))])
    gates = jax.vmap(ft.partial(_gates_at, rig=rig, strategy=strategy))(
        _stack(points), jnp.asarray(flags), P, O
    )
    result = []
    for i, rival in enumerate(rivals):
        gate = jax.tree.map(lambda x, i=i: x[i], gates)
        if rival is not None:
            fits = sorted(rival_fits[i], key=lambda f: f[0])
            chi2 = jnp.stack([f[1] for f in fits])
            O_rival = jnp.stack([f[2] for f in fits])
            distinct = jnp.sum((O_rival[:, 4:] - O[i, None, 4:]) ** 2, -1) > DISTINCT_MINIMUM**2
            usable = rival[2] & distinct & jnp.isfinite(chi2)
            runner_up = jnp.min(jnp.where(usable, chi2, jnp.inf))
            gate = (mark_ambiguous(gate[0], gate[1].chi2, runner_up), *gate[1:])
        result.append(gate)
    return result


def _stack(trees):
    return jax.tree.map(lambda *x: jnp.stack(x), *trees)


def gated(estimate: CycleEstimate, gate) -> CycleEstimate:
    """`estimate` with the result, checks and covariance of its gates."""
    result, checks, covariance = gate
    return eqx.tree_at(
        lambda e: (e.result, e.checks, e.covariance), estimate, (result, checks, covariance)
    )
