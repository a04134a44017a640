r"""A cycle's observations to poses with the paper's closed forms: [`jaxloc.localize_cycle`][].

Both strategies (`jaxloc._solvers.sequential`, `jaxloc._solvers.concurrent`) give every
ground robot's pose at every step, at metric scale, in the cycle's world frame `W` (C1's
body frame at the start); the overhead camera's pose then comes from every distinct
placement it saw ([`jaxloc.solve_overhead_pose`][]). Every estimate passes the gates of
`jaxloc._model.gates` (goodness of fit and observability, with the rig's noise) before it
is called `successful`.
"""

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from .._core.compiler import jit
from .._core.poses import inverse
from .._core.results import raise_if_failed, RESULTS
from .._cycle.estimate import CycleEstimate, CycleStarts
from .._cycle.observations import CycleObservations, CyclePoses
from .._cycle.rig import Rig
from .._model.gates import gate_all, gate_point, gate_rivals, gated
from .._model.measurements import cycle_data
from .concurrent import concurrent_formations, runner_up_positions
from .mutual import cycle_bearings
from .overhead import solve_overhead_pose
from .overhead_points import overhead_problem
from .sequential import sequential_formations


#: Overhead-pose methods of [`jaxloc.localize_cycle`][].
METHODS = ("robust", "paper")


def _ground_formations(observations: CycleObservations, bearings):
    """The strategy's closed form for the ground robots from the mutual `bearings` as
    [`cycle_bearings`][] fills them: `(T_world_body, scales, scale_ok, odometry_rms,
    mutual_result, min_angle, runner_up)`, `runner_up` the concurrent strategy's
    `(scales, ok)` or `None`."""
    if observations.strategy == "sequential":
        T, scales, scale_ok, rms, sols = sequential_formations(observations, bearings)
        runner_up = None
    else:
        T, scales, scale_ok, rms, second, second_ok, sols = concurrent_formations(
            observations, bearings
        )
        runner_up = (second, second_ok, runner_up_positions(second, sols))
    mutual_result = sols[0].result
    for s in sols[1:]:
        mutual_result = RESULTS.where(s.result == RESULTS.successful, mutual_result, s.result)
    min_angle = jnp.min(jnp.stack([s.stats["min_angle"] for s in sols]))
    return T, scales, scale_ok, rms, mutual_result, min_angle, runner_up


def _observations_ok(observations: CycleObservations):
    """`(finite, valid)`: the odometry and every mutual bearing marked visible are finite
    (a missing bearing is not visible), and the odometry is in its domain (distances >= 0,
    a zero move leaves the scale unobservable; sigmas > 0)."""
    d, s = observations.odometry, observations.odometry_sigma
    off_diagonal = ~np.eye(3, dtype=bool)
    mutual_ok = jnp.all(jnp.isfinite(observations.mutual), axis=-1)
    corrupt = jnp.any(observations.mutual_visible & off_diagonal[None] & ~mutual_ok)
    finite = jnp.all(jnp.isfinite(d)) & jnp.all(jnp.isfinite(s)) & ~corrupt
    return finite, jnp.all(d >= 0) & jnp.all(s > 0)


def _overhead_with_mirror(points, bearings, mask, scales):
    """The robust overhead pose and, as the one other start, the overhead solver's
    runner-up pose (e.g. the mirror pose of nearly coplanar points) with the same
    ground formation."""
    pose_sol = solve_overhead_pose(
        points, bearings, mask, method="robust", throw=False, runner_up=True
    )
    mirror = inverse(jaxlie.SE3(pose_sol.alternatives.wxyz_xyz[0])).wxyz_xyz
    starts = CycleStarts(
        scales=scales[None], T_world_overhead=mirror[None], ok=pose_sol.alternatives_ok[:1]
    )
    return pose_sol, starts


def _overhead_with_starts(observations, points, bearings, mask, scales, runner_up):
    """The robust overhead pose with the concurrent strategy's other starts: one batched
    solve for the winning and the runner-up scales' points (a smaller program)."""
    second, second_ok, positions = runner_up
    alt_points, _, _ = overhead_problem(observations, positions)
    both = jax.vmap(
        lambda pts: solve_overhead_pose(
            pts, bearings, mask, method="robust", throw=False, runner_up=True
        )
    )(jnp.stack([points, alt_points]))
    pose_sol = jax.tree.map(lambda x: x[0], both)
    mirror = inverse(jaxlie.SE3(both.alternatives.wxyz_xyz[0, 0])).wxyz_xyz
    starts = CycleStarts(
        scales=jnp.stack([second, scales]),
        T_world_overhead=jnp.stack([inverse(jaxlie.SE3(both.pose.wxyz_xyz[1])).wxyz_xyz, mirror]),
        ok=jnp.stack(
            [
                second_ok & (both.result == RESULTS.successful)[1],
                both.alternatives_ok[0, 0],
            ]
        ),
    )
    return pose_sol, starts


def _closed_form_result(pose_result, scale_ok, mutual_result, odometry):
    """The closed form's status before the gates, by priority."""
    finite, valid = odometry
    result = RESULTS.where(scale_ok, pose_result, RESULTS.scale_unobservable)
    # A non-finite bearing left after filling is a missing one the closed form cannot
    # do without (corrupt input is caught below).
    missing = mutual_result == RESULTS.nonfinite_observation
    mutual_result = RESULTS.where(missing, RESULTS.too_few_points, mutual_result)
    result = RESULTS.where(mutual_result == RESULTS.successful, result, mutual_result)
    result = RESULTS.where(valid, result, RESULTS.invalid_observation)
    return RESULTS.where(finite, result, RESULTS.nonfinite_observation)


def closed_forms(
    observations: CycleObservations, methods: tuple[str, ...]
) -> list[CycleEstimate]:
    """The closed forms of [`jaxloc.localize_cycle`][] for several overhead-pose methods,
    before the gates: `result` is the solver's own status, `checks` and `covariance` are
    not computed (see [`jaxloc.CycleEstimate.from_poses`][]). The ground robots' chain
    and the scale fit are computed once and shared; only the overhead camera's solve
    differs."""
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        raise ValueError(f"`method` must be one of {METHODS}; got {methods!r}.")
    filled, free, unresolved, stand_in = cycle_bearings(observations)
    T, scales, scale_ok, odo_rms, mutual_result, min_angle, runner_up = _ground_formations(
        observations, filled
    )
    points, bearings, mask = overhead_problem(observations, T.translation())
    odometry = _observations_ok(observations)
    good = mutual_result == RESULTS.successful
    stand_in = stand_in & good & ~free
    mutual_result = RESULTS.where(good & unresolved, RESULTS.too_few_points, mutual_result)
    mutual_result = RESULTS.where(free, RESULTS.unobservable, mutual_result)
    estimates = []
    for method in methods:
        alternatives = None
        if runner_up is not None and method == "robust":
            pose_sol, alternatives = _overhead_with_starts(
                observations, points, bearings, mask, scales, runner_up
            )
        elif method == "robust":
            pose_sol, alternatives = _overhead_with_mirror(points, bearings, mask, scales)
        else:
            pose_sol = solve_overhead_pose(points, bearings, mask, method=method, throw=False)
        stats = dict(pose_sol.stats, min_angle=min_angle, odometry_rms=odo_rms)
        result = _closed_form_result(pose_sol.result, scale_ok, mutual_result, odometry)
        # A stand-in is searched only where it is all that failed (not on invalid input).
        searchable = stand_in & (result == RESULTS.too_few_points)
        poses = CyclePoses(T, inverse(pose_sol.pose))
        blank = CycleEstimate.from_poses(poses, scales=scales, result=result)
        estimates.append(
            CycleEstimate(
                poses, scales, result, stats, blank.checks, blank.covariance, alternatives,
                stand_in=searchable,
            )
        )
    return estimates


def localize_cycle_methods(
    observations: CycleObservations, rig: Rig, methods: tuple[str, ...]
) -> list[CycleEstimate]:
    """[`jaxloc.localize_cycle`][] for several overhead-pose methods at once: the
    [`closed_forms`][], then the gates of all methods as one `vmap`. Never raises on
    traced values (`throw=False`)."""
    estimates = closed_forms(observations, methods)
    data = cycle_data(observations, rig)
    strategy = observations.strategy
    points = [gate_point(e, data, strategy) for e in estimates]
    rivals = [gate_rivals(e, p, strategy) for e, p in zip(estimates, points)]
    gates = gate_all(points, rig, strategy, polish=True, rivals=rivals)
    return [gated(e, g) for e, g in zip(estimates, gates)]


def localize_cycle(
    observations: CycleObservations,
    rig: Rig,
    *,
    method: str = "robust",
    throw: bool = True,
) -> CycleEstimate:
    r"""All four robots' poses from one cycle's observations, at metric scale.

    The strategy is read from `observations.strategy`. Pure: `jit`, `vmap` and `grad`
    apply (batch observations with `jax.vmap`).

    **Arguments:**

    - `observations`: a [`jaxloc.CycleObservations`][] (bearings in body/camera frames
      and odometry), from the simulator, the image front end or a real robot. Any
      mutual or overhead sighting may be missing (NaN, or not visible): a missing
      mutual bearing is recovered where the geometry allows (from a step at which the
      same robots stood still, directly or through the triangle's shape; see
      `jaxloc._solvers.mutual.fill_missing_bearings`), the overhead camera's pose uses
      the placements it saw, and the gates count only the sightings present.
    - `rig`: the team's [`jaxloc.Rig`][] (cameras, mounts, markers, pixel noise): the
      gates weigh every residual with it. The closed forms themselves use the bearings
      only (and take every camera centre and marker to be at its body origin; a rig
      with offsets needs [`jaxloc.refine_cycle`][]).
    - `method`: the overhead camera's pose solver, `"robust"` (default: every point
      triplet through P3P, best candidate on all points; correct on a flat floor) or
      `"paper"` (the paper's 12-unknown linear system, Eq. 6; rank deficient on planar
      ground). See [`jaxloc.solve_overhead_pose`][].
    - `throw`: raise on failure if `True`; otherwise inspect `result`. Keyword only.

    **Returns:** a [`jaxloc.CycleEstimate`][] in the world frame `W` = C1's body frame at
    the start of the cycle. `result` is `successful` only if the estimate fits the
    measurements (chi-square gate) and is observable (information gate; see
    `jaxloc._model.gates`): else `inconsistent_fit` (e.g. overhead images swapped between
    steps, a wrong scale branch), `unobservable` (e.g. too few distinct placements seen
    by the overhead camera, or a robot's rotation left free by a missing bearing),
    `too_few_points` (a missing bearing the closed form cannot recover: two from one
    triangle, or one whose robot's rotation only the other steps fix; for the latter
    the bearing is filled with a stand-in azimuth, marked in `stand_in`, and
    [`jaxloc.refine_cycle`][] starts from several azimuths),
    `ambiguous` (three points, several P3P roots), or the
    solver's own failure (`degenerate_configuration`, `nonfinite_observation`,
    `invalid_observation`, `scale_unobservable`, ...). `checks.solver_result` is the
    status before the gates.
    """
    if not isinstance(rig, Rig):
        raise ValueError(
            f"`rig` must be a jaxloc.Rig (the team's cameras and noise; e.g. "
            f"`jaxloc.Rig.paper()` or `scenario.rig`); got {type(rig).__name__}."
        )
    estimate = _localize_cycle_impl(observations, rig, method)
    return raise_if_failed(estimate, estimate.result, throw)


@jit(inline=True)
def _localize_cycle_impl(observations: CycleObservations, rig: Rig, method: str):
    # Compiled once per shape and method for eager callers; inlined into a caller's trace.
    (estimate,) = localize_cycle_methods(observations, rig, (method,))
    return estimate
