"""The robust stages of the joint refinement ([`jaxloc.refine_cycle`][] with a `loss`),
after its reweighted least-squares solve: outlying sightings rejected one at a time, the
overhead camera solved again from its inliers, a search over swapped inlier sets, and a
consensus search over the overhead camera's pose.
Each stage solves with the cycle's least-squares kernel (`jaxloc._refine.kernel`) and
decides between solutions by the gates' statistics (`jaxloc._model.gates`)."""

import functools as ft
import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from .._core.linalg import gram, spd_inverse
from .._core.poses import apply, inverse
from .._core.results import RESULTS
from .._cycle.estimate import RejectedSightings
from .._cycle.layout import placement_ids
from .._cycle.rig import Rig
from .._model.gates import nonsingular_information, SIGHTING_LIMIT, standardized_squares
from .._model.measurements import (
    CycleData,
    geometry,
    OBSERVER,
    sighting_squares,
    TARGET,
    whitened,
    whitened_cost,
    whitened_with_jacobian,
    without,
)
from .._solvers.overhead import collinearity_free, solve_overhead_pose
from .._solvers.overhead_points import overhead_problem
from .._solvers.p3p import p3p
from .kernel import cycle_lm, multi_start


#: Rounds of outlier rejection after a robust refinement, each rejecting at most one
#: sighting and solving the inliers again (see `_reject_and_resolve`): at most this many
#: outliers per cycle (5% of the sequential cycle's 36 sightings are 1.8 on average,
#: more than 5 in 1% of the cycles).
REJECTION_ROUNDS = 5
#: Floor of `1 - leverage` of a sighting's residual in the rejection test (a sighting the
#: fit leans on entirely is tested as if 1% of its noise showed).
LEVERAGE_FLOOR = 1e-2
#: Least-squares steps that screen each swap of the robust refinement's swap search, and
#: the decrease of the truncated cost (chi-square units) a swap must bring (see
#: `_swap_search`).
_SWAP_SCREEN_STEPS = 4
_SWAP_MARGIN = 1.0


def sighting_statistics(T_place, T_over, data: CycleData, rig: Rig, strategy: str):
    """Each pixel sighting's standardized squared residual `r_i^T (I - P_i)^-1 r_i` at a
    least-squares fit (Baarda's w-test, per two-row block), `(mutual (steps, 6 pairs),
    overhead (steps, 3))`: `r_i` its two whitened residuals, `P_i = J_i H^-1 J_i^T` its
    leverage (`H = J^T J`). A fit absorbs part of each sighting's noise (on the paper's
    cycle about one of its two residuals, on average); standardized, a clean sighting's
    statistic has the distribution of its noise's squared norm, so one threshold
    (`SIGHTING_LIMIT`) tests every sighting at the same false-alarm rate, and an outlier
    on a sighting the fit leans on is not hidden. `1 - leverage` is floored at
    `LEVERAGE_FLOOR`; where `H` is singular the plain squares are returned."""
    steps = data.mutual_pixels.shape[0]
    r, J = whitened_with_jacobian(T_place, T_over, data, rig, strategy)
    J = J[:, 1:].reshape(r.shape[0], -1)
    H_inv, ok = spd_inverse(gram(J))
    n_s = 9 * steps
    t, _ = standardized_squares(r, J, H_inv, n_s, LEVERAGE_FLOOR)
    rb = r[: 2 * n_s].reshape(n_s, 2)
    t = jnp.where(ok, t, jnp.sum(rb * rb, axis=-1))
    return t[: 6 * steps].reshape(steps, 6), t[6 * steps :].reshape(steps, 3)


def _sighting_targets(steps: int) -> np.ndarray:
    """The robot each sighting of a cycle looks at, `(9 steps,)`: the mutual pairs of
    every step (`OBSERVER, TARGET` order), then the overhead sightings of every step."""
    return np.concatenate([np.tile(TARGET, steps), np.tile(np.arange(3), steps)])


def _flat_sightings(mutual, overhead):
    """Masks `(mutual (steps, 3, 3), overhead (steps, 3))` as one `(9 steps,)` vector in
    the order of [`_sighting_targets`][]."""
    return jnp.concatenate([mutual[:, OBSERVER, TARGET].reshape(-1), overhead.reshape(-1)])


def _sighting_masks(flat):
    """The inverse of [`_flat_sightings`][]."""
    steps = flat.shape[0] // 9
    pairs = flat[: 6 * steps].reshape(steps, 6)
    mutual = jnp.zeros((steps, 3, 3), bool).at[:, OBSERVER, TARGET].set(pairs)
    return mutual, flat[6 * steps :].reshape(steps, 3)


def _worst(t_m, t_o, limit):
    """One-hot masks `(mutual (steps, 3, 3), overhead (steps, 3))` of the sighting with
    the largest statistic, if that exceeds `limit` (else all False)."""
    t = jnp.concatenate([t_m.reshape(-1), t_o.reshape(-1)])
    return _sighting_masks((jnp.arange(t.shape[0]) == jnp.argmax(t)) & (t > limit))


def _reject_and_resolve(T_place, T_over, data, rig, strategy, active, settings, loss,
                        runner_up_cost):  # fmt: skip
    """The robust refinement's second stage, from its converged solution: in each of
    `REJECTION_ROUNDS` rounds the one sighting with the largest statistic above
    `SIGHTING_LIMIT` is left out and the cycle solved again from there by plain least
    squares on the inliers (the maximum-likelihood estimate given them). The statistic
    is the squared whitened residual at the robust solution (first round: an outlier it
    downweighted shows whole), then the standardized residual at each plain fit
    ([`sighting_statistics`][]). One at a time, as in data snooping: an outlier inflates
    the residuals of the sightings that share its unknowns (the other sighting in the
    same image), which fall back once it is gone; a wrong minimum that only many
    rejections would make consistent stays `inconsistent_fit`. Returns `(T_place,
    T_over, num_steps, converged, rejected, runner_up_chi2)`: the runner-up's cost moved
    to the inliers' chi-square by the difference of the two robust costs (what decides
    `ambiguous`)."""
    max_steps, rtol, atol = settings
    sg = jax.lax.stop_gradient
    T_place, T_over, data, rig = sg((T_place, T_over, data, rig))
    steps = data.mutual_pixels.shape[0]
    limit = SIGHTING_LIMIT[rig.noise_model]
    robust_cost = whitened_cost(T_place, T_over, data, rig, strategy, loss)

    def round_(carry, index):
        T_place, T_over, out_m, out_o, num_steps, converged = carry
        inliers = without(data, out_m, out_o)
        s_m, s_o = sighting_squares(whitened(T_place, T_over, inliers, rig, strategy), steps)
        t_m, t_o = sighting_statistics(T_place, T_over, inliers, rig, strategy)
        first = index == 0
        new_m, new_o = _worst(jnp.where(first, s_m, t_m), jnp.where(first, s_o, t_o), limit)
        new_m, new_o = new_m & active, new_o & active
        out_m, out_o = out_m | new_m, out_o | new_o
        # A round that rejects nothing keeps the previous solve (none: solve once).
        run = active & (first | jnp.any(new_m) | jnp.any(new_o))
        T_place2, T_over2, k, converged2, _ = cycle_lm(
            T_place, T_over, without(data, out_m, out_o), rig, strategy, max_steps, rtol,
            atol, run,
        )  # fmt: skip
        converged = jnp.where(run, converged2, converged)
        return (T_place2, T_over2, out_m, out_o, num_steps + k, converged), None

    none_m, none_o = jnp.zeros((steps, 3, 3), bool), jnp.zeros((steps, 3), bool)
    carry = (T_place, T_over, none_m, none_o, jnp.array(0, jnp.int32), jnp.array(False))
    carry, _ = jax.lax.scan(round_, carry, jnp.arange(REJECTION_ROUNDS))
    T_place, T_over, out_m, out_o, num_steps, converged = carry
    chi2 = whitened_cost(T_place, T_over, without(data, out_m, out_o), rig, strategy)
    rejected = RejectedSightings(out_m, out_o)
    return T_place, T_over, num_steps, converged, rejected, chi2 + runner_up_cost - robust_cost


def _overhead_restarts(observations, rejected, T_place, T_over, data, rig, settings, active):
    """The robust refinement's third stage: the overhead camera solved again by
    [`jaxloc.solve_overhead_pose`][] from its inlier sightings (less the `rejected`) of
    the ground placements `T_place` (its best candidate and the distinct runners-up),
    each refined to convergence by plain least squares on the inliers `data` beside the
    solution itself; the lowest chi-square wins, and a distinct minimum within
    `AMBIGUITY_MARGIN` makes the estimate `ambiguous`. Rejecting overhead sightings can
    leave the camera a second minimum, which the reweighted rounds, started from a
    closed form the outliers pulled, fall into while the ground placements stay right
    (measured on the paper's cycles with 5% outlying sightings; restarting before the
    rejection rounds as well, with the robust cost, picked wrong minima). Returns
    `(T_place, T_over, num_steps, converged, runner_up_chi2)` as `multi_start`."""
    strategy = observations.strategy
    max_steps, rtol, atol = settings
    sg = jax.lax.stop_gradient
    # Not differentiated: the refinement's `implicit_step` carries the derivatives.
    observations, T_place, T_over, data, rig = sg((observations, T_place, T_over, data, rig))
    inliers = eqx.tree_at(
        lambda o: (o.mutual_visible, o.overhead_visible),
        observations,
        (observations.mutual_visible & ~rejected.mutual,
         observations.overhead_visible & ~rejected.overhead),
    )  # fmt: skip
    positions = T_place[placement_ids(strategy)][..., 4:]
    points, bearings, seen = overhead_problem(inliers, positions)
    solution = solve_overhead_pose(
        points, bearings, seen, method="robust", throw=False, runner_up=True
    )
    candidates = jnp.concatenate([solution.pose.wxyz_xyz[None], solution.alternatives.wxyz_xyz])
    T_over_starts = jax.vmap(lambda p: inverse(jaxlie.SE3(p)).wxyz_xyz)(candidates)
    solved = (solution.result == RESULTS.successful) | (solution.result == RESULTS.ambiguous)
    starts = (
        jnp.stack([T_place] * (1 + candidates.shape[0])),
        jnp.concatenate([T_over[None], T_over_starts]),
        jnp.concatenate([jnp.array([True]), solved[None], solution.alternatives_ok]),
    )
    T_place, T_over, num_steps, converged, _, runner_up_chi2 = multi_start(
        starts, active, data, rig, strategy, max_steps, rtol, atol, None,
        to_convergence=True, prefer_converged=True,
    )  # fmt: skip
    return T_place, T_over, num_steps, converged, runner_up_chi2


def truncated_cost(T_place, T_over, data: CycleData, rig: Rig, strategy: str):
    """The cost that decides between inlier sets (MSAC): every sighting's squared whitened
    norm and every odometry row's square, each capped at the sighting gate's
    `SIGHTING_LIMIT`, summed (an outlier costs the cap whether it is rejected or not)."""
    steps = data.mutual_pixels.shape[0]
    limit = SIGHTING_LIMIT[rig.noise_model]
    r = whitened(T_place, T_over, data, rig, strategy)
    s_m, s_o = sighting_squares(r, steps)
    return (
        jnp.sum(jnp.minimum(s_m, limit))
        + jnp.sum(jnp.minimum(s_o, limit))
        + jnp.sum(jnp.minimum(r[18 * steps :] ** 2, limit))
    )


def _one_hot_pick(hot, a):
    """`a[i]` for the one `i` where `hot (k,)` is True (a select, no gather)."""
    return jnp.sum(jnp.where(hot.reshape((-1,) + (1,) * (a.ndim - 1)), a, 0), axis=0)


def _swap_search(T_place, T_over, data, rejected, rig, strategy, settings, active):
    """The robust refinement's fourth stage: one rejected sighting restored and another
    sighting of the same robot rejected instead, if that fits the whole cycle better.
    Rejecting one sighting at a time from a fit that absorbed an outlier can name its
    clean partner (two views of a robot disagree; the fit took the outlier's side), and
    the wrong side then fits its inliers (measured on the paper's cycles with 5%
    outlying sightings: most wrong robust poses were one such swap away from the truth).
    Every swap (each rejected sighting x each other present inlier sighting of its
    robot) is screened by `_SWAP_SCREEN_STEPS` least-squares steps from the solution on
    its inliers; the best by [`truncated_cost`][] on every sighting is solved fully and
    taken if its truncated cost is lower than the solution's by `_SWAP_MARGIN`. Returns
    `(T_place, T_over, num_steps, swapped, converged, rejected)`; `converged` is that of
    the swap's solve (meaningful where `swapped`)."""
    max_steps, rtol, atol = settings
    sg = jax.lax.stop_gradient
    T_place, T_over, data, rig = sg((T_place, T_over, data, rig))
    steps = data.mutual_pixels.shape[0]
    targets = _sighting_targets(steps)
    out = _flat_sightings(rejected.mutual, rejected.overhead)
    present = _flat_sightings(data.mutual_weight > 0, data.overhead_weight > 0)
    # Each rejected slot j (at most REJECTION_ROUNDS) against the sightings of its robot.
    slots = jnp.argsort(~out, stable=True)[:REJECTION_ROUNDS]
    slot_ok = out[slots]
    same_robot = np.stack([np.nonzero(targets == r)[0] for r in range(3)])  # (3, 4 steps)
    ks = jnp.asarray(same_robot)[jnp.asarray(targets)[slots]]  # (slots, 4 steps)
    js = jnp.broadcast_to(slots[:, None], ks.shape)
    ok = slot_ok[:, None] & present[ks] & ~out[ks]
    js, ks, ok = js.reshape(-1), ks.reshape(-1), ok.reshape(-1) & active
    index = jnp.arange(out.shape[0])

    def swapped(j, k):
        return (out & (index != j)) | (index == k)

    def screen(j, k, lane_ok):
        m, o = _sighting_masks(swapped(j, k))
        P, O, _, _, _ = cycle_lm(T_place, T_over, without(data, m, o), rig, strategy,
                            _SWAP_SCREEN_STEPS, rtol, atol, lane_ok)  # fmt: skip
        return P, O, jnp.where(lane_ok, truncated_cost(P, O, data, rig, strategy), jnp.inf)

    P, O, costs = jax.vmap(screen)(js, ks, ok)
    best = jnp.argmin(costs)
    hot = jnp.arange(costs.shape[0]) == best
    P, O, j, k = jax.tree.map(lambda a: _one_hot_pick(hot, a), (P, O, js, ks))
    current = truncated_cost(T_place, T_over, data, rig, strategy)
    run = active & (costs[best] < current - _SWAP_MARGIN)
    new_out = swapped(j, k)
    m, o = _sighting_masks(new_out)
    swapped_data = without(data, m, o)
    P, O, num_steps, converged, _ = cycle_lm(P, O, swapped_data, rig, strategy, max_steps, rtol,
                                        atol, run)  # fmt: skip
    r, J = whitened_with_jacobian(P, O, swapped_data, rig, strategy)
    determined = nonsingular_information(J[:, 1:].reshape(r.shape[0], -1))
    take = run & determined & (truncated_cost(P, O, data, rig, strategy) < current - _SWAP_MARGIN)
    T_place = jnp.where(take, P, T_place)
    T_over = jnp.where(take, O, T_over)
    m = jnp.where(take, m, rejected.mutual)
    o = jnp.where(take, o, rejected.overhead)
    return T_place, T_over, jnp.where(run, num_steps, 0), take, converged, RejectedSightings(m, o)


#: Overhead camera poses the consensus search refines (see `_overhead_consensus`), and
#: how far apart their centres must be, as a fraction of the RMS camera-to-marker distance.
_CONSENSUS_CANDIDATES = 4
_CONSENSUS_SEPARATION = 0.05


def _distinct_placement_triplets(strategy: str) -> np.ndarray:
    """Every triplet of a cycle's overhead sightings (flat indices `step * 3 + robot`)
    whose three robots stand at three distinct placements, `(T, 3)` (two sightings of an
    unmoved robot are one point: no P3P)."""
    ids = placement_ids(strategy).reshape(-1)
    triplets = itertools.combinations(range(ids.shape[0]), 3)
    return np.array([t for t in triplets if len(set(ids[list(t)])) == 3], dtype=np.int32)


def _consensus_candidates(T_place, T_over, data, rig, strategy, bearings):
    """The consensus search's candidates for the overhead camera at the placements
    `T_place`: P3P ([`jaxloc.p3p`][]) on every triplet of overhead sightings of distinct
    placements (`bearings (steps, 3, 3)`; every sighting `data` holds), each candidate
    scored by the truncated cost of the overhead sightings (squared whitened pixel
    residuals capped at `SIGHTING_LIMIT`; a marker behind the camera costs the cap), and
    the `_CONSENSUS_CANDIDATES` best whose centres are `_CONSENSUS_SEPARATION` apart:
    `(T_over (k, 7), ok (k,))`."""
    limit = SIGHTING_LIMIT[rig.noise_model]
    dtype = T_place.dtype
    X = geometry(T_place, T_over, rig, strategy).markers_world.reshape(-1, 3)
    b = bearings.reshape(-1, 3)
    w = data.overhead_weight.reshape(-1)
    use = (w > 0) & jnp.all(jnp.isfinite(b), axis=-1)
    X = jnp.where(use[:, None], X, 0.0)
    b = jnp.where(use[:, None], b, jnp.array([0.0, 0.0, 1.0], dtype))
    pixels = data.overhead_pixels.reshape(-1, 2)
    tri = _distinct_placement_triplets(strategy)
    noncollinear, _, _ = collinearity_free(X[tri], jnp.finfo(dtype).eps)
    roots = jax.vmap(p3p)(X[tri], b[tri])
    params = roots.poses.wxyz_xyz.reshape(-1, 7)  # T_cam_world
    ok = (roots.valid & (jnp.all(use[tri], axis=1) & noncollinear)[:, None]).reshape(-1)

    def overhead_cost(p):
        q = jax.vmap(ft.partial(apply, jaxlie.SE3(p)))(X)
        s = jnp.sum((w[:, None] * (rig.overhead.project(q) - pixels)) ** 2, axis=-1)
        s = jnp.where((jnp.sum(q * b, axis=-1) > 0) & jnp.isfinite(s), s, limit)
        return jnp.sum(jnp.where(use, jnp.minimum(s, limit), 0.0))

    costs = jnp.where(ok, jax.vmap(overhead_cost)(params), jnp.inf)
    T_overs = jax.vmap(lambda p: inverse(jaxlie.SE3(p)).wxyz_xyz)(params)
    depth2 = jnp.sum(jnp.where(use, jnp.sum((X - T_over[None, 4:]) ** 2, -1), 0.0))
    separation2 = _CONSENSUS_SEPARATION**2 * depth2 / jnp.maximum(jnp.sum(use), 1)
    picks, picked_ok, available = [], [], ok
    for _ in range(_CONSENSUS_CANDIDATES):
        c = jnp.where(available, costs, jnp.inf)
        pick = _one_hot_pick(jnp.arange(c.shape[0]) == jnp.argmin(c), T_overs)
        picks.append(pick)
        picked_ok.append(jnp.isfinite(jnp.min(c)))
        far = jnp.sum((T_overs[:, 4:] - pick[None, 4:]) ** 2, -1) > separation2
        available = available & far
    return jnp.stack(picks), jnp.stack(picked_ok)


def _overhead_consensus(T_place, T_over, data, rejected, rig, strategy, settings, active,
                        loss, bearings):  # fmt: skip
    """The robust refinement's last stage, a consensus search (MSAC) over the overhead
    camera at the fitted ground placements. Measured on the paper's cycles with 5%
    outlying sightings, most wrong robust poses had every ground placement right and C
    in a wrong minimum that fits its inliers, because the rejection rounds had kept an
    overhead outlier or left out a clean overhead sighting: an inlier set no restart from
    those same inliers corrects. Here every overhead sighting present, rejected ones
    included, takes part: the candidates of [`_consensus_candidates`][] are each refined
    (robust `loss` from the candidate, then plain least squares on its inliers: the
    overhead sightings below `SIGHTING_LIMIT` there, and the mutual sightings not
    `rejected`). The refined candidate with the lowest [`truncated_cost`][] on all data
    replaces the solution if that is lower by `_SWAP_MARGIN` and it rejects at most
    `REJECTION_ROUNDS` sightings; one that fits better only by rejecting more makes the
    solution doubtful (measured: taking it made wrong poses consistent). Returns
    `(T_place, T_over, num_steps, taken, converged, rejected, doubtful)`."""
    max_steps, rtol, atol = settings
    sg = jax.lax.stop_gradient
    T_place, T_over, data, rig, bearings = sg((T_place, T_over, data, rig, bearings))
    steps = data.mutual_pixels.shape[0]
    limit = SIGHTING_LIMIT[rig.noise_model]
    starts, starts_ok = _consensus_candidates(T_place, T_over, data, rig, strategy, bearings)
    mutual_inliers = without(data, rejected.mutual, jnp.zeros_like(rejected.overhead))

    def solve(O, lane_ok):
        P, O, k1, _, _ = cycle_lm(T_place, O, mutual_inliers, rig, strategy, max_steps, rtol,
                                  atol, lane_ok, loss)  # fmt: skip
        _, s_o = sighting_squares(whitened(P, O, mutual_inliers, rig, strategy), steps)
        out_o = (s_o > limit) & (data.overhead_weight > 0)
        inliers = without(data, rejected.mutual, out_o)
        P, O, k2, converged, _ = cycle_lm(P, O, inliers, rig, strategy, max_steps, rtol, atol,
                                          lane_ok)  # fmt: skip
        r, J = whitened_with_jacobian(P, O, inliers, rig, strategy)
        determined = nonsingular_information(J[:, 1:].reshape(r.shape[0], -1))
        cost = truncated_cost(P, O, data, rig, strategy)
        count = jnp.sum(rejected.mutual) + jnp.sum(out_o)
        cost = jnp.where(lane_ok & determined & converged, cost, jnp.inf)
        return P, O, k1 + k2, converged, out_o, cost, count <= REJECTION_ROUNDS

    P, O, num_steps, converged, out_o, cost, admissible = jax.vmap(solve)(
        starts, starts_ok & active
    )
    target = truncated_cost(T_place, T_over, data, rig, strategy) - _SWAP_MARGIN
    admitted = jnp.where(admissible, cost, jnp.inf)
    best = jnp.arange(cost.shape[0]) == jnp.argmin(admitted)
    take = active & (jnp.min(admitted) < target)
    doubtful = active & ~take & (jnp.min(cost) < target)
    P, O = jax.tree.map(lambda a: _one_hot_pick(best, a), (P, O))
    T_place = jnp.where(take, P, T_place)
    T_over = jnp.where(take, O, T_over)
    overhead = jnp.where(take, jnp.any(best[:, None, None] & out_o, axis=0), rejected.overhead)
    rejected = RejectedSightings(rejected.mutual, overhead)
    converged = jnp.any(best & converged)
    return T_place, T_over, jnp.sum(num_steps), take, converged, rejected, doubtful


def robust_stages(observations, T_place, T_over, data, rig, active, settings, loss,
                  runner_up_chi2):  # fmt: skip
    """The robust refinement after its reweighted solve `(T_place, T_over)`: the rejection
    rounds, the overhead restarts, the swap search and the consensus search. Returns
    `(T_place, T_over, num_steps, converged, rejected, inliers, runner_up_chi2)`,
    `inliers` the cycle's `data` less the `rejected` sightings."""
    strategy = observations.strategy
    T_place, T_over, k1, converged, rejected, runner_up_chi2 = _reject_and_resolve(
        T_place, T_over, data, rig, strategy, active, settings, loss, runner_up_chi2
    )
    inliers = without(data, rejected.mutual, rejected.overhead)
    T_place, T_over, k2, converged, restart_chi2 = _overhead_restarts(
        observations, rejected, T_place, T_over, inliers, rig, settings, active
    )
    T_place, T_over, k3, swapped, swap_converged, rejected = _swap_search(
        T_place, T_over, data, rejected, rig, strategy, settings, active
    )
    converged = jnp.where(swapped, swap_converged, converged)
    T_place, T_over, k4, moved, moved_converged, rejected, doubtful = _overhead_consensus(
        T_place, T_over, data, rejected, rig, strategy, settings, active, loss,
        observations.overhead,
    )
    converged = jnp.where(moved, moved_converged, converged)
    inliers = without(data, rejected.mutual, rejected.overhead)
    # After a swap or a move the earlier minima had other inliers: their costs do not
    # compare. A doubtful solution is ambiguous.
    runner_up_chi2 = jnp.minimum(runner_up_chi2, restart_chi2)
    runner_up_chi2 = jnp.where(swapped | moved, jnp.inf, runner_up_chi2)
    runner_up_chi2 = jnp.where(doubtful, -jnp.inf, runner_up_chi2)
    return T_place, T_over, k1 + k2 + k3 + k4, converged, rejected, inliers, runner_up_chi2
