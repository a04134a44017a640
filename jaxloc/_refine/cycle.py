r"""Joint maximum-likelihood refinement of a whole cycle: [`jaxloc.refine_cycle`][] (DESIGN §5).

Every distinct robot placement of a cycle and the overhead camera jointly, from every
mutual pixel, every overhead pixel and every odometry distance, each residual whitened by
its standard deviation, with the rig's cameras exactly as calibrated (the measurement
model of `jaxloc._model.measurements`). Poses are parametrized in the SE(3) tangent
space (`T exp(delta)`, `delta = (v, omega)`, jaxlie's right perturbation). The default
solver is jaxloc's least-squares kernel (`jaxloc._core.least_squares`), re-linearized at
the current poses with the model's chain-rule Jacobian; `optx.least_squares` with
Levenberg--Marquardt or Gauss--Newton is offered on the same residuals. Gradients are
implicit (the solve is never unrolled). The refined estimate passes the same gates as
the closed forms (`jaxloc._model.gates`).
"""

import functools as ft

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import optimistix as optx
from jaxtyping import Array

from .._core.compiler import jit
from .._core.least_squares import (
    implicit_step,
    jvp_nonzero,
    KernelLevenbergMarquardt,
    optx_solver,
)
from .._core.numerics import safe_sqrt
from .._core.results import raise_if_failed, RESULTS
from .._core.robust import robust_loss, RobustLoss
from .._cycle.estimate import CycleEstimate, RejectedSightings, start_placements
from .._cycle.layout import placement_ids
from .._cycle.observations import CycleObservations, CyclePoses
from .._cycle.rig import Rig
from .._model.covariance import estimate_placements
from .._model.gates import (
    AMBIGUITY_MARGIN,
    gate_all,
    gate_point,
    gated,
    mark_ambiguous,
    STAND_IN_MARGIN,
)
from .._model.measurements import (
    cycle_data,
    CycleData,
    normal_equations,
    pack,
    predict,
    unpack,
    whitened,
    whitened_with_jacobian,
    without,
)
from .azimuth import azimuth_starts, SEARCHED_STAND_INS
from .kernel import cycle_lm, multi_start, NEGLIGIBLE_DECREASE, position_scale, retract
from .robust import robust_stages


#: Solvers of [`jaxloc.refine_cycle`][]: jaxloc's least-squares kernel, or optimistix's
#: Levenberg--Marquardt / Gauss--Newton on the same residuals.
CYCLE_SOLVERS = ("lm", "optx-kernel", "optx-lm", "optx-gn")
#: The robust stage's tolerances relative to the refinement's: it only has to tell the
#: outliers apart (plain least squares on the inliers then converges fully), and
#: reweighted least squares converges linearly.
_ROBUST_TOLERANCE_FACTOR = 10.0


@ft.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _cycle_residuals(strategy, theta, T0_place, T0_over, data, rig):
    """Whitened residuals at `T0 exp(theta)` (placement 0 held at the identity)."""
    T_place, T_over = unpack(theta, T0_place, T0_over)
    return whitened(T_place, T_over, data, rig, strategy)


def _right_jacobians(theta, T0_place, T0_over, T_place, T_over):
    """`d log(T^-1 T0 exp(theta')) / d theta'` at `theta' = theta` for every unknown pose,
    `(placements, 6, 6)`: maps the tangent step to the local perturbation of `T`."""
    T0 = jnp.concatenate([T0_place[1:], T0_over[None]])
    T = jnp.concatenate([T_place[1:], T_over[None]])

    def one(t0, t, th):
        def local(th2):
            moved = jaxlie.manifold.rplus(jaxlie.SE3(t0), th2)
            return jaxlie.manifold.rminus(jaxlie.SE3(t), moved)  # log(T^-1 moved)

        return jax.jacfwd(local)(th)

    return jax.vmap(one)(T0, T, theta.reshape(-1, 6)).astype(theta.dtype)


@ft.partial(_cycle_residuals.defjvp, symbolic_zeros=True)
def _cycle_residuals_jvp(strategy, primals, tangents):
    # The Jacobian by the chain rule (jaxloc._model.measurements), ~20x cheaper than
    # forward mode through the whole model; tangents of the other inputs (the implicit
    # derivatives w.r.t. observations or the rig) by ordinary forward mode.
    theta, *rest = primals
    theta_dot, *rest_dot = tangents
    T0_place, T0_over, data, rig = rest
    T_place, T_over = unpack(theta, T0_place, T0_over)
    r, J_local = whitened_with_jacobian(T_place, T_over, data, rig, strategy)
    Jr = _right_jacobians(theta, T0_place, T0_over, T_place, T_over)
    J = jnp.einsum("mbi,bij->mbj", J_local[:, 1:], Jr).reshape(r.shape[0], -1)
    r_dot = J @ theta_dot
    extra = jvp_nonzero(lambda rest: _cycle_residuals.fun(strategy, theta, *rest), rest, rest_dot)
    return r, r_dot if extra is None else r_dot + extra


def _implicit_residuals(x, theta, args, strategy):
    return _cycle_residuals(strategy, theta, x[0], x[1], *args)


def _kernel_refine(estimate, T0_place, T0_over, data, rig, strategy, active, settings, loss):
    """The default solver: one start, or the multi-start when the estimate carries other
    starts (its `alternatives`, and the azimuths of its `stand_in` bearings). Returns
    `(T_place, T_over, num_steps, converged, multi_start_stats, runner_up_chi2)` (`inf`
    without other starts; with a robust `loss` the costs are robust ones)."""
    max_steps, rtol, atol = settings
    # The loop is not differentiated: `implicit_step` carries the derivatives.
    T0_place, T0_over, data, rig = jax.tree.map(
        jax.lax.stop_gradient, (T0_place, T0_over, data, rig)
    )
    others = []
    if estimate.alternatives is not None:
        others.append(start_placements(estimate.alternatives, estimate.scales, strategy, T0_place))
    if estimate.stand_in is not None:
        others.append(azimuth_starts(T0_place, T0_over, estimate.stand_in, strategy))
    if not others:
        out = cycle_lm(T0_place, T0_over, data, rig, strategy, max_steps, rtol, atol, active, loss)
        return *out[:4], {}, jnp.array(jnp.inf, T0_place.dtype)
    others = jax.lax.stop_gradient(others)
    starts = (
        jnp.concatenate([T0_place[None]] + [o[0] for o in others]),
        jnp.concatenate([T0_over[None]] + [o[1] for o in others]),
        jnp.concatenate([jnp.ones(1, bool)] + [o[2] for o in others]),
    )
    to_convergence = False if estimate.stand_in is None else jnp.any(estimate.stand_in)
    T_place, T_over, num_steps, converged, picked, runner_up_chi2 = multi_start(
        starts, active, data, rig, strategy, max_steps, rtol, atol, loss, to_convergence
    )
    stats = {"start_picked": picked, "runner_up_chi2": runner_up_chi2}
    return T_place, T_over, num_steps, converged, stats, runner_up_chi2


class _CycleModel(eqx.Module):
    """The cycle's normal equations at the poses `x = (T_place, T_over)` for
    [`KernelLevenbergMarquardt`][jaxloc._core.least_squares.KernelLevenbergMarquardt]
    (`args = (T0_place, T0_over, data, rig)`, as `optx.least_squares` passes them)."""

    strategy: str = eqx.field(static=True)

    def __call__(self, x, args):
        _, _, data, rig = args
        return normal_equations(x[0], x[1], data, rig, self.strategy, None)


def _kernel_solver(strategy: str, num_unknowns: int, rtol, atol) -> KernelLevenbergMarquardt:
    """The kernel of `jaxloc._refine.kernel.cycle_lm` (same damping, scale and stopping
    rule) as an optimistix solver over the chart `theta` of [`unpack`][] at the start."""
    return KernelLevenbergMarquardt(
        model=_CycleModel(strategy),
        retract=retract,
        scale=position_scale,
        point=_chart_point,
        coordinates=_chart_coordinates,
        num_unknowns=num_unknowns,
        rtol=rtol,
        atol=atol,
        decrease_tol=NEGLIGIBLE_DECREASE * (jnp.minimum(rtol, atol) / 1e-6) ** 2,
    )


def _chart_point(theta, args):
    return unpack(theta, args[0], args[1])


def _chart_coordinates(x, args):
    return pack(x[0], x[1], args[0], args[1])


def _optx_refine(T0_place, T0_over, data, rig, strategy, solver, settings):
    max_steps, rtol, atol = settings
    num_unknowns = 6 * T0_place.shape[0]
    if solver == "optx-kernel":
        opt, max_steps = _kernel_solver(strategy, num_unknowns, rtol, atol), max_steps + 1
    else:
        opt = optx_solver(solver.removeprefix("optx-"), rtol, atol)
    sol = optx.least_squares(
        lambda theta, args: _cycle_residuals(strategy, theta, *args),
        opt,
        jnp.zeros(num_unknowns, T0_place.dtype),
        args=(T0_place, T0_over, data, rig),
        max_steps=max_steps,
        throw=False,
    )
    T_place, T_over = unpack(sol.value, T0_place, T0_over)
    return T_place, T_over, sol.stats["num_steps"], RESULTS.promote(sol.result)


def _start(estimate: CycleEstimate, strategy: str, multi_start: bool):
    """The estimate's placements as a start (finite: else the identity) and whether the
    refinement may run: the estimate is a usable start, successful or only flagged by the
    fit gate (a refinement may find the consistent minimum the closed form missed),
    `ambiguous` by the gates with its rival minima as the other starts, or (for the
    solver with a `multi_start`) `too_few_points` with one or two `stand_in` bearings,
    whose azimuths the starts search jointly (the multi-start decides). Measured, a
    search over the first of two stand-ins' azimuths alone marked wrong poses
    `successful`; a cycle with three stays `too_few_points`."""
    T0_place, T0_over = estimate_placements(estimate.poses, strategy)
    finite = jnp.all(jnp.isfinite(T0_place)) & jnp.all(jnp.isfinite(T0_over))
    ident = jnp.zeros(7, T0_place.dtype).at[0].set(1.0)
    T0_place = jnp.where(finite, T0_place, ident)
    T0_over = jnp.where(finite, T0_over, ident)
    usable = (estimate.result == RESULTS.successful) | (estimate.result == RESULTS.inconsistent_fit)
    if estimate.alternatives is not None:
        # Ambiguous by the gates (a rival minimum fits almost as well), not by the solver
        # (several exact P3P roots, which no refinement can tell apart).
        rival = estimate.checks.solver_result == RESULTS.successful
        usable = usable | ((estimate.result == RESULTS.ambiguous) & rival)
    if multi_start and estimate.stand_in is not None:
        searched = jnp.sum(estimate.stand_in)
        usable = usable | ((searched >= 1) & (searched <= SEARCHED_STAND_INS))
    return T0_place, T0_over, finite & usable


def _statistics(T_place, T_over, data: CycleData, rig, strategy):
    """Diagnostics of a solution: RMS pixel and odometry residuals."""
    mutual, overhead, lengths = predict(T_place, T_over, rig, strategy)
    m_used = data.mutual_weight > 0
    o_used = data.overhead_weight > 0
    e2 = jnp.sum(jnp.where(m_used, jnp.sum((mutual - data.mutual_pixels) ** 2, -1), 0.0)) + jnp.sum(
        jnp.where(o_used, jnp.sum((overhead - data.overhead_pixels) ** 2, -1), 0.0)
    )
    count = jnp.maximum(jnp.sum(m_used) + jnp.sum(o_used), 1).astype(T_place.dtype)
    return {
        "rms_pixel_error": safe_sqrt(e2 / count),
        "odometry_rms": safe_sqrt(jnp.mean((lengths - data.odometry) ** 2)),
    }


def refine_solution(
    observations: CycleObservations, rig: Rig, estimate: CycleEstimate, *, solver: str,
    max_steps: int, rtol, atol, loss: RobustLoss | None = None,
) -> tuple[CycleEstimate, Array]:
    """[`jaxloc.refine_cycle`][] before the gates: the refined estimate (`result` the
    solver's status; `checks` and `covariance` not computed) and the cost of another
    distinct minimum a multi-start found (`inf` if none), which decides `ambiguous`
    ([`finish_refinement`][]). With a robust `loss` (solver `"lm"` only) the estimate's
    `rejected` names the sightings left out; gate it on [`refined_data`][]."""
    strategy = observations.strategy
    data = cycle_data(observations, rig)
    T0_place, T0_over, active = _start(estimate, strategy, multi_start=solver == "lm")
    settings = (max_steps, rtol, atol)
    stats = dict(estimate.stats)
    rejected = None
    if solver == "lm":
        first = settings
        if loss is not None:
            first = (max_steps, _ROBUST_TOLERANCE_FACTOR * rtol, _ROBUST_TOLERANCE_FACTOR * atol)
        T_place, T_over, num_steps, converged, multi, runner_up_chi2 = _kernel_refine(
            estimate, T0_place, T0_over, data, rig, strategy, active, first, loss
        )
        stats.update(multi)
        if loss is not None:
            T_place, T_over, k, converged, rejected, data, runner_up_chi2 = robust_stages(
                observations, T_place, T_over, data, rig, active, settings, loss,
                runner_up_chi2,
            )  # fmt: skip
            num_steps = num_steps + k
            if "runner_up_chi2" in stats:
                stats["runner_up_chi2"] = runner_up_chi2
        step = implicit_step(
            _implicit_residuals, 6 * T_place.shape[0], strategy, (T_place, T_over), (data, rig)
        )
        T_place, T_over = unpack(step, T_place, T_over)
        result = RESULTS.where(converged, RESULTS.successful, RESULTS.nonlinear_max_steps_reached)
    else:
        T_place, T_over, num_steps, result = _optx_refine(
            T0_place, T0_over, data, rig, strategy, solver, settings
        )
        runner_up_chi2 = jnp.array(jnp.inf, T0_place.dtype)
    finite = jnp.all(jnp.isfinite(T_place)) & jnp.all(jnp.isfinite(T_over))
    result = RESULTS.where(finite, result, RESULTS.no_valid_solution)
    result = RESULTS.where(active, result, estimate.result)
    ok = result == RESULTS.successful
    T_place = jnp.where(ok, T_place, T0_place)
    T_over = jnp.where(ok, T_over, T0_over)
    ids = placement_ids(strategy)
    T_world_body = jnp.where(ok, T_place[ids], estimate.poses.T_world_body.wxyz_xyz)
    T_world_over = jnp.where(ok, T_over, estimate.poses.T_world_overhead.wxyz_xyz)
    poses = CyclePoses(jaxlie.SE3(T_world_body), jaxlie.SE3(T_world_over))
    stats.update(_statistics(T_place, T_over, data, rig, strategy), num_steps=num_steps)
    if rejected is not None:
        rejected = RejectedSightings(rejected.mutual & ok, rejected.overhead & ok)
    refined = CycleEstimate(
        poses, estimate.scales, result, stats, estimate.checks, estimate.covariance,
        estimate.alternatives, rejected, estimate.stand_in,
    )  # fmt: skip
    return refined, runner_up_chi2


def refined_data(data: CycleData, refined: CycleEstimate) -> CycleData:
    """The measurements a refinement's gates test: every sighting of `data` (the cycle's
    `cycle_data`), less those a robust refinement rejected (`refined.rejected`)."""
    if refined.rejected is None:
        return data
    return without(data, refined.rejected.mutual, refined.rejected.overhead)


def finish_refinement(refined: CycleEstimate, runner_up_chi2, gate) -> CycleEstimate:
    """A [`refine_solution`][] with its gates (`(result, checks, covariance)` of
    `jaxloc._model.gates.gate_all`, unpolished): `ambiguous` when another distinct
    minimum's cost is within `AMBIGUITY_MARGIN` of the solution's (`STAND_IN_MARGIN`
    after a search over a stand-in bearing's azimuth)."""
    refined = gated(refined, gate)
    margin = AMBIGUITY_MARGIN
    if refined.stand_in is not None:
        margin = jnp.where(jnp.any(refined.stand_in), STAND_IN_MARGIN, AMBIGUITY_MARGIN)
    result = mark_ambiguous(refined.result, refined.checks.chi2, runner_up_chi2, margin)
    return eqx.tree_at(lambda e: e.result, refined, result)


@jit(inline=True)
def _refine_cycle_impl(observations, rig, estimate, loss, *, solver, max_steps, rtol, atol):
    refined, runner_up_chi2 = refine_solution(
        observations, rig, estimate, solver=solver, max_steps=max_steps, rtol=rtol, atol=atol,
        loss=loss,
    )  # fmt: skip
    data = refined_data(cycle_data(observations, rig), refined)
    point = gate_point(refined, data, observations.strategy)
    (gate,) = gate_all([point], rig, observations.strategy, polish=False)
    return finish_refinement(refined, runner_up_chi2, gate)


def refine_cycle(
    observations: CycleObservations,
    rig: Rig,
    estimate: CycleEstimate,
    *,
    solver: str = "lm",
    max_steps: int = 64,
    rtol: float = 1e-6,
    atol: float = 1e-6,
    loss: str | None = None,
    loss_scale: float | Array | None = None,
    throw: bool = True,
) -> CycleEstimate:
    r"""Joint maximum-likelihood refinement of a whole cycle.

    Unknowns: the pose `T_world_body` of every distinct robot placement (a robot that does
    not move keeps one pose: 6 placements for the sequential strategy, 7 for the concurrent
    one; see [`jaxloc.placement_ids`][]) and the overhead camera's optical-frame pose
    `T_world_overhead`, each as `T0 exp(delta)` around `estimate` (jaxlie right
    perturbation). The gauge is fixed by holding C1's start pose at the identity (it is the
    world frame `W`); the metric scale comes from the odometry. Minimises the sum of
    squared whitened residuals, with the rig's cameras, mounts and markers exactly:

    - every mutual sighting, in pixels of the observing camera: robot `j`'s marker in
      robot `i`'s camera through its mount (`jaxloc._cycle.sightings`), projected by the
      rig's camera model of robot `i` (C1: `rig.ptz`, C2, C3: `rig.omni2`, `rig.omni3`);
    - every overhead pixel, `rig.overhead.project(T_world_overhead^{-1} x_j)`;
    - every odometry distance between the mover's body origins, sigma
      `observations.odometry_sigma`.

    Pixel residuals are divided by the camera's per-axis sigma
    ([`jaxloc.Rig.sigma_per_axis`][]). A sighting without pixels but with a bearing (e.g.
    observations built from bearings alone) is projected through its camera to pixels;
    one with neither, or marked not visible, is missing and left out.

    **Arguments:**

    - `observations`: a [`jaxloc.CycleObservations`][].
    - `rig`: the team's [`jaxloc.Rig`][] (a scenario's is `scenario.rig`).
    - `estimate`: the starting point, usually [`jaxloc.localize_cycle`][]'s. The
        refinement runs when the estimate is `successful` or only `inconsistent_fit`
        (a closed form's wrong branch); any other failure is passed through.
    - `solver`: keyword only, as are the following. `"lm"` (default): jaxloc's
        least-squares kernel, re-linearized at the current poses with the model's
        chain-rule Jacobian (the fast path for Monte Carlo); `"optx-kernel"`: the same
        kernel as an optimistix solver through `optx.least_squares` (single start, no
        robust loss; optimistix's implicit adjoint); `"optx-lm"` / `"optx-gn"`:
        `optx.LevenbergMarquardt` / `optx.GaussNewton` on the same residuals. All reach
        the same minimum; gradients are implicit (w.r.t. the observations and the rig;
        the minimizer does not depend on `estimate`).
    - `max_steps`, `rtol`, `atol`: the solver's iteration limit and tolerances.
    - `loss`: `None` (default): plain least squares. `"huber"` or `"cauchy"`: outlier
        rejection with a robust loss of each pixel sighting's whitened norm (solver
        `"lm"` only; see "Robust refinement" below).
    - `loss_scale`: the robust loss's scale in standard deviations of the whitened
        norm (default 1.345 for Huber, 2.3849 for Cauchy); only with a `loss`.
    - `throw`: raise on failure if `True`; otherwise inspect `result`.

    **Returns:** a [`jaxloc.CycleEstimate`][] (same form as `localize_cycle`'s): poses of
    every robot at every step and of the overhead camera in `W`, metres. `scales` and
    `alternatives` are copied from `estimate`. `result` passes the gates of
    `jaxloc._model.gates` at the refined poses: `inconsistent_fit` when the chi-square
    exceeds its 99.9% quantile under the rig's noise model (a wrong local minimum or an
    outlier), `unobservable` when the information is singular, the bound absurd or there
    are no more measurements than unknowns; `checks` holds the chi-square, its degrees
    of freedom and its limit, `covariance` the first-order covariance. `stats` adds
    `"num_steps"` (at most `max_steps`, also for a multi-start), `"rms_pixel_error"`
    (px, over all used pixels) and updates `"odometry_rms"` (m).

    **Multi-start.** When `estimate.alternatives` carries the closed form's other local
    minima (the concurrent strategy's runner-up scales, and the overhead solver's
    runner-up pose, e.g. the mirror pose of nearly coplanar points), the solver `"lm"`
    refines each start for a few steps and goes on from the one with the lowest cost. If
    another start converged to a distinct minimum (camera more than 10 cm away) whose
    chi-square is within 4 of the solution's, the data cannot tell the two apart:
    `result` is `ambiguous` (the lower minimum is returned). `stats` then adds
    `"start_picked"` (0 = `estimate`'s own poses) and `"runner_up_chi2"` (that other
    minimum's cost, `inf` if none). Two minima are distinct when some robot placement or
    the overhead camera lies more than 10 cm apart.

    **A missing bearing on its cone.** When the closed form filled one missing mutual
    bearing with a stand-in azimuth (`estimate.stand_in`; its result `too_few_points`:
    e.g. C1 not seeing C2 in the concurrent strategy), the refinement (solver `"lm"`)
    starts from that formation turned about the line to the third robot by 8 evenly
    spaced angles, each with the closed form's overhead camera and with its planar flip
    (see `jaxloc._refine.azimuth`), refines every start to convergence and keeps the
    best; the multi-start rule above decides `ambiguous`, with a margin of 9
    (`jaxloc._model.gates.STAND_IN_MARGIN`) instead of 4: these minima are discrete
    hypotheses the data weigh weakly. Two stand-in bearings (C1 missing a robot at two
    steps) are searched jointly, every pair of their turns by 6 angles (71 starts); with
    three the result stays `too_few_points`. `stand_in` is copied to the refined
    estimate.

    **Robust refinement.** With a `loss`, the refinement first minimises `sum_i
    rho(|r_i|^2)` over the pixel sightings `i` (each a block of two whitened residuals;
    the odometry stays squared) by iteratively reweighted least squares in the same
    kernel (each step weighs sighting `i` by `rho'(|r_i|^2)`; multi-start included; to
    10x the tolerances, since it only has to tell the outliers apart). Then, one
    sighting at a time for at most 5 rounds (data snooping), the sighting with the
    largest statistic is rejected (left out, as missing data) if that exceeds the 99.9%
    quantile of one sighting's squared whitened noise under the rig's noise model
    (`jaxloc._model.gates.SIGHTING_LIMIT`: 13.82 for `"gaussian"` noise,
    chi-square(2); 21.66 for `"paper"` noise, 2 chi-square(1)), and the cycle is solved
    again from there by plain least squares on the inliers. The statistic is the
    squared whitened residual at the robust solution in the first round, then the
    standardized one `r_i^T (I - P_i)^-1 r_i` (`P_i` the sighting's leverage) at each
    plain fit. Last, the overhead camera is solved again from its inlier sightings of
    the fitted ground placements ([`jaxloc.solve_overhead_pose`][], its best candidate
    and distinct runners-up), each refined to convergence on the inliers beside the
    solution: the lowest chi-square wins (rejections can leave the camera a second
    minimum). Then a swap search: each rejected sighting is restored in turn with
    another present sighting of the same robot rejected instead (screened by 4 steps
    each, the best solved fully), and the swap is taken if it lowers the cycle's
    truncated cost (every sighting's squared whitened norm capped at the sighting limit,
    so an outlier costs the cap whether rejected or not) by more than 1 and leaves the
    information nonsingular: a fit that absorbed an outlier can reject its clean partner
    instead. Last, a consensus search (MSAC) over the overhead camera: P3P on every
    triplet of its sightings of three distinct placements at the fitted placements
    (rejected sightings included), the 4 best candidates by the overhead sightings'
    truncated cost refined (robust, then plain on the overhead sightings within the
    limit), and the best taken if it lowers the cycle's truncated cost by more than 1
    with at most 5 sightings rejected; one that needs more makes the estimate
    `ambiguous` (the rounds can keep an overhead outlier or reject a clean overhead
    sighting and leave C in a wrong minimum of those inliers). The estimate,
    covariance, gates (chi-square and degrees of freedom over the inliers only),
    `ambiguous` (a distinct minimum of the restarts within the
    margin, or the closed form's rival, decided on the difference of the robust costs
    of the two minima) and gradients (implicit, with the rejections held fixed) are those of
    the maximum-likelihood estimate given the inliers. An outlier in a sighting nothing
    else checks (a robot's pose seen in one image only, whose two sightings fix its
    rotation) cannot be told from its partner; rejecting either leaves that rotation
    undetermined: the cycle is `unobservable`. `rejected` names the rejected sightings
    (a [`jaxloc.RejectedSightings`][]; listed by [`jaxloc.rejected_sightings`][]);
    `stats["num_steps"]` counts the steps of every solve (each at most `max_steps`).

    Single cycle; batch with `jax.vmap`. Works under `jit`, `vmap` and `grad`.
    """
    if solver not in CYCLE_SOLVERS:
        raise ValueError(f"`solver` must be one of {CYCLE_SOLVERS}; got {solver!r}.")
    robust = robust_loss(loss, loss_scale)
    if robust is not None and solver != "lm":
        raise ValueError(
            f'`loss` ({loss!r}) needs `solver="lm"` (jaxloc\'s kernel); got {solver!r}.'
        )
    if isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1:
        raise ValueError(f"`max_steps` must be a positive int; got {max_steps!r}.")
    if not isinstance(rig, Rig):
        raise ValueError(
            f"`rig` must be a jaxloc.Rig (e.g. `scenario.rig`); got {type(rig).__name__}."
        )
    if estimate.poses.T_world_body.wxyz_xyz.shape[-3] != observations.num_steps:
        raise ValueError(
            f"`estimate` has {estimate.poses.T_world_body.wxyz_xyz.shape[-3]} steps but "
            f"`observations` are of the {observations.strategy} strategy "
            f"({observations.num_steps} steps)."
        )
    out = _refine_cycle_impl(
        observations, rig, estimate, robust, solver=solver, max_steps=max_steps, rtol=rtol,
        atol=atol,
    )  # fmt: skip
    return raise_if_failed(out, out.result, throw)
