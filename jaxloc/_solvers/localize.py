r"""A cycle's observations to poses with the paper's closed forms: [`jaxloc.localize_cycle`][].

Both strategies (`jaxloc._solvers.sequential`, `jaxloc._solvers.concurrent`) give every
ground robot's pose at every step, at metric scale, in the cycle's world frame `W` (C1's
body frame at the start); the overhead camera's pose then comes from every distinct
placement it saw ([`jaxloc.solve_overhead_pose`][]). Every estimate passes the gates of
`jaxloc._model.gates` (goodness of fit and observability, with the rig's noise) before it
is called `successful`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie

from .._core.poses import inverse
from .._core.results import raise_if_failed, RESULTS
from .._cycle.estimate import CycleEstimate, CycleStarts, start_placements
from .._cycle.observations import CycleObservations, CyclePoses
from .._cycle.rig import Rig
from .._model.covariance import estimate_placements
from .._model.gates import check
from .._model.measurements import cycle_data
from .concurrent import concurrent_formations, runner_up_positions
from .overhead import solve_overhead_pose
from .overhead_points import overhead_problem
from .sequential import sequential_formations


#: Overhead-pose methods of [`jaxloc.localize_cycle`][].
METHODS = ("robust", "paper")


def _ground_formations(observations: CycleObservations):
    """The strategy's closed form for the ground robots: `(T_world_body, scales,
    scale_ok, odometry_rms, mutual_result, min_angle, runner_up)`, `runner_up` the
    concurrent strategy's `(scales, ok)` or `None`."""
    if observations.strategy == "sequential":
        T, scales, scale_ok, rms, sols = sequential_formations(observations)
        runner_up = None
    else:
        T, scales, scale_ok, rms, second, second_ok, sols = concurrent_formations(observations)
        runner_up = (second, second_ok, runner_up_positions(second, sols))
    mutual_result = sols[0].result
    for s in sols[1:]:
        mutual_result = RESULTS.where(s.result == RESULTS.successful, mutual_result, s.result)
    min_angle = jnp.min(jnp.stack([s.stats["min_angle"] for s in sols]))
    return T, scales, scale_ok, rms, mutual_result, min_angle, runner_up


def _observations_ok(observations: CycleObservations):
    """`(finite, valid)`: the odometry is finite, and in its domain (distances >= 0, a zero
    move leaves the scale unobservable; sigmas > 0)."""
    d, s = observations.odometry, observations.odometry_sigma
    finite = jnp.all(jnp.isfinite(d)) & jnp.all(jnp.isfinite(s))
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
    result = RESULTS.where(mutual_result == RESULTS.successful, result, mutual_result)
    result = RESULTS.where(valid, result, RESULTS.invalid_observation)
    return RESULTS.where(finite, result, RESULTS.nonfinite_observation)


def _gated(data, rig, strategy, poses: CyclePoses, solver_result, scales, starts):
    """Apply the gates at the closed-form estimate `poses` (its other `starts`, a
    [`jaxloc.CycleStarts`][] or `None`, as rivals)."""
    T_place, T_over = estimate_placements(poses, strategy)
    finite = jnp.all(jnp.isfinite(T_place)) & jnp.all(jnp.isfinite(T_over))
    ident = jnp.zeros(7, T_place.dtype).at[0].set(1.0)
    T_place = jnp.where(finite, T_place, ident)
    T_over = jnp.where(finite, T_over, ident)
    final = jnp.concatenate(
        [poses.T_world_overhead.wxyz_xyz[None], poses.T_world_body.wxyz_xyz[-1]]
    )
    final = jnp.where(jnp.all(jnp.isfinite(final)), final, ident)
    rivals = None if starts is None else start_placements(starts, scales, strategy, T_place)
    return check(
        T_place, T_over, data, rig, strategy, solver_result, final_poses=final, rivals=rivals
    )


def localize_cycle_methods(
    observations: CycleObservations, rig: Rig, methods: tuple[str, ...]
) -> list[CycleEstimate]:
    """[`jaxloc.localize_cycle`][] for several overhead-pose methods at once.

    The ground robots' chain and the scale fit are computed once and shared; only the
    overhead camera's solve differs; the gates of all methods run as one `vmap`. Never
    raises on traced values (`throw=False`)."""
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        raise ValueError(f"`method` must be one of {METHODS}; got {methods!r}.")
    T, scales, scale_ok, odo_rms, mutual_result, min_angle, runner_up = _ground_formations(
        observations
    )
    points, bearings, mask = overhead_problem(observations, T.translation())
    odometry = _observations_ok(observations)
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
        poses = CyclePoses(T, inverse(pose_sol.pose))
        estimates.append((poses, result, stats, alternatives))
    rivals = [e[3] for e in estimates]
    some = next((r for r in rivals if r is not None), None)
    if some is not None:  # one structure for the vmap: rivals that do not exist
        absent = eqx.tree_at(lambda s: s.ok, some, jnp.zeros_like(some.ok))
        rivals = [absent if r is None else r for r in rivals]
    stacked = jax.tree.map(
        lambda *x: jnp.stack(x), *[(e[0], e[1], r) for e, r in zip(estimates, rivals)]
    )
    data = cycle_data(observations, rig)
    gated, checks, covariance = jax.vmap(
        lambda p, r, starts: _gated(data, rig, observations.strategy, p, r, scales, starts)
    )(*stacked)
    return [
        CycleEstimate(
            poses, scales, jax.tree.map(lambda x, i=i: x[i], gated), stats,
            jax.tree.map(lambda x, i=i: x[i], checks),
            jax.tree.map(lambda x, i=i: x[i], covariance), alternatives,
        )
        for i, (poses, _, stats, alternatives) in enumerate(estimates)
    ]  # fmt: skip


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
      and odometry), from the simulator, the image front end or a real robot.
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
    by the overhead camera), `ambiguous` (three points, several P3P roots), or the
    solver's own failure (`degenerate_configuration`, `nonfinite_observation`,
    `invalid_observation`, `scale_unobservable`, ...). `checks.solver_result` is the
    status before the gates.
    """
    if not isinstance(rig, Rig):
        raise ValueError(
            f"`rig` must be a jaxloc.Rig (the team's cameras and noise; e.g. "
            f"`jaxloc.Rig.paper()` or `scenario.rig`); got {type(rig).__name__}."
        )
    (estimate,) = localize_cycle_methods(observations, rig, (method,))
    return raise_if_failed(estimate, estimate.result, throw)
