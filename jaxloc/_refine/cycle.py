r"""Maximum-likelihood refinement with optimistix (DESIGN §5).

[`jaxloc.refine_cycle`][]: every distinct robot placement of a cycle and the overhead
camera jointly, from every mutual pixel, every overhead pixel and every odometry
distance, each residual whitened by its standard deviation ([`jaxloc.refine_overhead_pose`][],
one camera pose alone, lives in `_refine_pose.py`).

It parametrizes poses in the SE(3) tangent space around their starting value
(`T = T0 exp(delta)`, `delta = (v, omega)`, jaxlie's right perturbation
`jaxlie.manifold.rplus`) and runs a batched Levenberg--Marquardt of its own, or
`optx.least_squares` with Levenberg--Marquardt or
Gauss--Newton. The solvers' linear steps go through the normal equations with a
`fori_loop` Cholesky (no LAPACK in the loop, DESIGN §8). Gradients through a refinement
use optimistix's implicit adjoint (the solve is never unrolled).
"""

import functools as ft
from typing import NamedTuple

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import jaxlie
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from .._core.least_squares import _cholesky, _cholesky_solve, _jvp_nonzero, _make_solver
from .._core.numerics import safe_sqrt
from .._core.results import raise_if_failed, RESULTS
from .._cycle.observations import CycleObservations, CyclePoses
from .._sim.scenario import Scenario
from .._solvers.strategies import CycleEstimate
from .model import (
    _first_occurrence,
    _predict,
    _unpack,
    cycle_data,
    flat_jacobian,
    placement_ids,
    whitened,
    whitened_with_jacobian,
)


#: Solvers of [`jaxloc.refine_cycle`][]: jaxloc's batched Levenberg--Marquardt, or
#: optimistix's Levenberg--Marquardt / Gauss--Newton on the same residuals.
CYCLE_SOLVERS = ("lm", "optx-lm", "optx-gn")
#: Predicted decrease of the whitened cost (chi-square units) below which a step of the
#: batched Levenberg--Marquardt counts as converged, at the default tolerances
#: (`rtol = atol = 1e-6`); it scales with the square of the tighter one.
_NEGLIGIBLE_DECREASE = 1e-4
#: Two distinct converged minima whose costs differ by less than this (chi-square units,
#: a likelihood ratio below e^2 ~ 7) make a multi-start refinement `ambiguous`.
_AMBIGUITY_MARGIN = 4.0
#: Steps of a multi-start refinement's first phase, where every start is refined (the
#: whole refinement still takes at most `max_steps`).
_MULTI_START_STEPS = 6
#: Two converged solutions whose overhead cameras are farther apart than this (m) are
#: distinct minima.
_DISTINCT_MINIMUM = 0.1


# --------------------------------------------------------------------------------------
# Joint refinement of a whole cycle.


@ft.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _cycle_residuals(strategy, theta, T0_place, T0_over, data, scenario):
    """Whitened residuals at `T0 exp(theta)` (placement 0 held at the identity)."""
    T_place, T_over = _unpack(theta, T0_place, T0_over)
    return whitened(T_place, T_over, data, scenario, strategy)


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
    # The Jacobian by the chain rule (jaxloc._cycle_model), ~20x cheaper than forward mode
    # through the whole model; tangents of the other inputs (the implicit adjoint's
    # derivatives w.r.t. observations or the start) by ordinary forward mode.
    theta, *rest = primals
    theta_dot, *rest_dot = tangents
    T0_place, T0_over, data, scenario = rest
    T_place, T_over = _unpack(theta, T0_place, T0_over)
    r, J_local = whitened_with_jacobian(T_place, T_over, data, scenario, strategy)
    Jr = _right_jacobians(theta, T0_place, T0_over, T_place, T_over)
    J = jnp.einsum("mbi,bij->mbj", J_local[:, 1:], Jr).reshape(r.shape[0], -1)
    r_dot = J @ theta_dot
    extra = _jvp_nonzero(
        lambda rest: _cycle_residuals.fun(strategy, theta, *rest), rest, rest_dot
    )
    return r, r_dot if extra is None else r_dot + extra


def _batched_lm(T0_place, T0_over, data, scenario, strategy, max_steps, rtol, atol, active):
    """Levenberg--Marquardt re-linearized at the current poses every step.

    Each iteration costs one model evaluation with its chain-rule Jacobian, one normal
    matrix and one `fori_loop` Cholesky: no right Jacobians of the exponential map (the
    step is always taken from the current pose), no LAPACK, no materialization of a
    linear operator. Isotropic damping `lambda I` (the residuals are whitened and the
    tangent is in m and rad, so `lambda` is a prior precision; Marquardt's `diag(J^T J)`
    scaling over-damps every translation that a precise odometry distance touches),
    starting at 1e-2 and updated by Nielsen's rule (by the gain ratio after an accepted
    step, by doubling factors after rejected ones). Converged when a step (accepted, or
    rejected at negligible damping: the minimum within rounding) is below
    `atol + rtol * max |position|` (m, rad), or its predicted cost decrease `-g . delta`
    is below `1e-4 * (min(rtol, atol) / 1e-6)^2` (at the default tolerances, a step of
    ~1e-2 standard deviations).

    An inactive problem (`active` False: a failed start) takes no step, so under `vmap`
    it does not prolong its batch's loop. Returns `(T_place, T_over, num_steps,
    converged)`.
    """
    dtype = T0_place.dtype
    decrease_tol = _NEGLIGIBLE_DECREASE * (jnp.minimum(rtol, atol) / 1e-6) ** 2
    eye = jnp.eye(6 * T0_place.shape[0], dtype=dtype)

    # One model evaluation per iteration, at the top of the loop body, so that the model
    # and its Jacobian are traced and compiled once: iteration 0 evaluates the start,
    # iteration k >= 1 evaluates step k proposed by iteration k - 1 and accepts or
    # rejects it; every iteration then proposes the next step from the current poses.
    def propose(T_place, T_over, r, J, lam):
        H = J.T @ J
        g = J.T @ r
        L = _cholesky(H + lam * eye)
        delta = -_cholesky_solve(L, g)
        finite = jnp.all(jnp.isfinite(delta))
        delta = jnp.where(finite, delta, 0.0)
        T_place_try, T_over_try = _unpack(delta, T_place, T_over)
        small = jnp.max(jnp.abs(delta)) <= atol + rtol * jnp.max(jnp.abs(T_place[:, 4:]))
        # Or statistically negligible: the step's predicted cost decrease (the residuals
        # are whitened, so in chi-square units, ~ the squared step in standard
        # deviations) is negligible. Gauss-Newton converges only linearly along weakly
        # observed directions (a flat floor), where a step-size test alone takes hundreds
        # of iterations to pass.
        small = small | (-jnp.sum(g * delta) <= decrease_tol)
        predicted = -2.0 * jnp.sum(g * delta) - jnp.sum(delta * (H @ delta))
        return T_place_try, T_over_try, finite, small, predicted

    m = data.mutual_pixels.size + data.overhead_pixels.size + data.odometry.shape[0]
    false = jnp.array(False)
    init = _LMState(
        k=jnp.array(0, jnp.int32), T_place=T0_place, T_over=T0_over,
        r=jnp.zeros(m, dtype), J=jnp.zeros((m, eye.shape[0]), dtype),
        lam=jnp.array(1e-2, dtype), nu=jnp.array(2.0, dtype), done=~active, converged=false,
        T_place_try=T0_place, T_over_try=T0_over, finite=jnp.array(True), small=false,
        predicted=jnp.array(0.0, dtype),
    )

    def cond(s: _LMState):
        return (s.k <= max_steps) & ~s.done

    def body(s: _LMState):
        r_new, J_new = _flat_jacobian_model(
            s.T_place_try, s.T_over_try, data, scenario, strategy
        )
        first = s.k == 0
        cost, cost_new = jnp.sum(s.r * s.r), jnp.sum(r_new * r_new)
        accept = first | (s.finite & jnp.isfinite(cost_new) & (cost_new <= cost))
        # A rejected step that is already negligible: the minimum within rounding.
        done = ~first & (accept | (s.lam < 1e-3)) & s.finite & s.small
        pick = lambda a, b: jnp.where(accept, a, b)  # noqa: E731
        # Nielsen's damping update: by the gain ratio (actual / predicted decrease) after
        # an accepted step, doubling factors after rejected ones. Fixed factors of 10
        # oscillate between acceptance and rejection on a curved, weakly observed valley.
        gain = (cost - cost_new) / jnp.where(s.predicted > 0, s.predicted, 1.0)
        shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
        lam = jnp.clip(jnp.where(accept, s.lam * shrink, s.lam * s.nu), 1e-9, 1e12)
        lam = jnp.where(first, s.lam, lam)
        nu = jnp.where(first | accept, 2.0, 2.0 * s.nu).astype(dtype)
        T_place, T_over = pick(s.T_place_try, s.T_place), pick(s.T_over_try, s.T_over)
        r, J = pick(r_new, s.r), pick(J_new, s.J)
        T_place_try, T_over_try, finite, small, predicted = propose(T_place, T_over, r, J, lam)
        return _LMState(
            s.k + 1, T_place, T_over, r, J, lam, nu, done, done,
            T_place_try, T_over_try, finite, small, predicted,
        )

    out = jax.lax.while_loop(cond, body, init)
    return out.T_place, out.T_over, jnp.maximum(out.k - 1, 0), out.converged


class _LMState(NamedTuple):
    k: Int[Array, ""]  # iterations run; iteration k >= 1 decided on step k
    T_place: Float[Array, "placements 7"]  # the current poses ...
    T_over: Float[Array, "7"]
    r: Float[Array, " m"]  # ... with their residuals and Jacobian
    J: Float[Array, "m n"]
    lam: Float[Array, ""]  # the damping the proposed step was solved with
    nu: Float[Array, ""]
    done: Bool[Array, ""]
    converged: Bool[Array, ""]
    T_place_try: Float[Array, "placements 7"]  # the proposed step ...
    T_over_try: Float[Array, "7"]
    finite: Bool[Array, ""]  # ... finite, small enough to stop, and its predicted decrease
    small: Bool[Array, ""]
    predicted: Float[Array, ""]


def _flat_jacobian_model(T_place, T_over, data, scenario, strategy):
    """Whitened residuals `(m,)` and their Jacobian `(m, 6 * placements)` with respect to
    the right perturbations of every placement but the gauge (placement 0), then of the
    overhead camera (the LM's model; the tangent layout of `_unpack`)."""
    r, J = whitened_with_jacobian(T_place, T_over, data, scenario, strategy)
    return r, flat_jacobian(J)


@ft.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _implicit_step(strategy, T_place, T_over, data, scenario):
    """Zero tangent step at a converged solution `(T_place, T_over)`, whose derivative is
    that of the minimizer w.r.t. the measurements and the scenario (implicit function
    theorem on the gradient of the cost). Poses `_unpack(step, T_place, T_over)` are the
    solution with correct derivatives; the solution does not depend on the start."""
    return _zero_step(T_place)


def _zero_step(T_place):
    # Derived from an input so that under `vmap` it is batched like its tangent.
    return jnp.zeros(6 * T_place.shape[0], T_place.dtype) + 0.0 * T_place[0, 0]


@ft.partial(_implicit_step.defjvp, symbolic_zeros=True)
def _implicit_step_jvp(strategy, primals, tangents):
    T_place, T_over, data, scenario = primals
    _, _, data_dot, scenario_dot = tangents
    zero = _zero_step(T_place)

    def gradient(theta, data, scenario):
        def cost(t):
            r = _cycle_residuals(strategy, t, T_place, T_over, data, scenario)
            return 0.5 * jnp.sum(r * r)

        return jax.grad(cost)(theta)

    H = jax.jacfwd(gradient)(zero, data, scenario)
    eye = jnp.eye(zero.shape[0], dtype=zero.dtype)
    H_inv = jax.vmap(lambda e: _cholesky_solve(_cholesky(H), e))(eye).T
    g_dot = _jvp_nonzero(
        lambda ds: gradient(zero, *ds), (data, scenario), (data_dot, scenario_dot)
    )
    return zero, jnp.zeros_like(zero) if g_dot is None else -H_inv @ g_dot


def _estimate_placements(estimate: CycleEstimate, strategy: str):
    ks, rs = _first_occurrence(strategy)
    T_body = estimate.poses.T_world_body.wxyz_xyz
    return T_body[ks, rs], estimate.poses.T_world_overhead.wxyz_xyz


def _alternative_starts(estimate: CycleEstimate, strategy: str, T0_place):
    """Other starts of a refinement: the closed form's other local minima (see
    `localize_cycle_methods`), or None. Returns `(T_place, T_over, active)` with a
    leading axis of alternatives."""
    if "alternative_scales" not in estimate.stats:
        return None
    ks, _ = _first_occurrence(strategy)
    factor = estimate.stats["alternative_scales"] / estimate.scales[None]
    T_place = jnp.concatenate(
        [jnp.broadcast_to(T0_place[:, :4], (factor.shape[0],) + T0_place[:, :4].shape),
         T0_place[None, :, 4:] * factor[:, ks, None]],
        axis=-1,
    )
    T_over = estimate.stats["alternative_T_world_overhead"]
    active = estimate.stats["alternative_ok"] & jnp.all(jnp.isfinite(T_place), axis=(1, 2))
    active = active & jnp.all(jnp.isfinite(T_over), axis=1)
    ident = jnp.zeros(7, T_over.dtype).at[0].set(1.0)
    T_place = jnp.where(active[:, None, None], T_place, T0_place[None])
    return T_place, jnp.where(active[:, None], T_over, ident[None]), active


@eqx.filter_jit(inline=True)
def _refine_cycle_impl(observations, scenario, estimate, *, solver, max_steps, rtol, atol):
    strategy = observations.strategy
    dtype = observations.mutual_pixels.dtype
    data = cycle_data(observations, scenario)
    T0_place, T0_over = _estimate_placements(estimate, strategy)
    finite0 = jnp.all(jnp.isfinite(T0_place)) & jnp.all(jnp.isfinite(T0_over))
    ident = jnp.zeros(7, dtype).at[0].set(1.0)
    T0_place = jnp.where(finite0, T0_place, ident)
    T0_over = jnp.where(finite0, T0_over, ident)
    T0_place = T0_place.at[0].set(ident)  # the gauge: C1's start pose is the world frame
    n = T0_place.shape[0]
    stats = dict(estimate.stats)
    if solver == "lm":
        # The loop is not differentiated: `_implicit_step` carries the derivatives.
        T0_place, T0_over, lm_data, lm_scenario = jax.tree.map(
            jax.lax.stop_gradient, (T0_place, T0_over, data, scenario)
        )
        active = finite0 & (estimate.result == RESULTS.successful)
        starts = _alternative_starts(estimate, strategy, T0_place)
        if starts is None:
            T_place, T_over, num_steps, converged = _batched_lm(
                T0_place, T0_over, lm_data, lm_scenario, strategy, max_steps, rtol, atol,
                active,
            )
        else:
            # Multi-start in two phases: the primary start and the closed form's other
            # local minima are each refined for a few steps; the one with the lowest
            # cost goes on alone (a second start costs only those few steps). The
            # phases are jobs of one `lax.scan` (one per start, then the last one) so
            # that the LM and the model are traced and compiled once.
            T1_place, T1_over, active1 = jax.lax.stop_gradient(starts)
            lanes = jnp.concatenate([active[None], active & active1])
            start_place = jnp.concatenate([T0_place[None], T1_place])
            start_over = jnp.concatenate([T0_over[None], T1_over])
            n_lanes = lanes.shape[0]
            n_first = min(max_steps, _MULTI_START_STEPS)

            def masked_chi2(chi2):
                return jnp.where(lanes & jnp.isfinite(chi2), chi2, jnp.inf)

            def job(slots, j):
                T_place_j, T_over_j, steps_j, converged_j, chi2_j = slots
                last = j == n_lanes
                pick = jnp.argmin(masked_chi2(chi2_j[:n_lanes]))
                lane = jnp.minimum(j, n_lanes - 1)
                tp = jnp.where(last, T_place_j[pick], start_place[lane])
                to = jnp.where(last, T_over_j[pick], start_over[lane])
                act = jnp.where(last, active & ~converged_j[pick], lanes[lane])
                budget = jnp.where(last, max_steps - n_first, n_first)
                tp, to, k, conv = _batched_lm(
                    tp, to, lm_data, lm_scenario, strategy, budget, rtol, atol, act
                )
                chi2 = jnp.sum(whitened(tp, to, lm_data, lm_scenario, strategy) ** 2)
                slots = (
                    T_place_j.at[j].set(tp), T_over_j.at[j].set(to), steps_j.at[j].set(k),
                    converged_j.at[j].set(conv), chi2_j.at[j].set(chi2),
                )
                return slots, None

            n_jobs = n_lanes + 1
            slots = (
                jnp.zeros((n_jobs,) + T0_place.shape, dtype),
                jnp.zeros((n_jobs,) + T0_over.shape, dtype),
                jnp.zeros(n_jobs, jnp.int32),
                jnp.zeros(n_jobs, bool),
                jnp.full(n_jobs, jnp.inf, dtype),
            )
            (T_all, O_all, steps_all, conv_all, chi2_all), _ = jax.lax.scan(
                job, slots, jnp.arange(n_jobs)
            )
            chi2 = masked_chi2(chi2_all[:n_lanes])
            converged1 = conv_all[:n_lanes]
            pick = jnp.argmin(chi2)
            centres = O_all[:n_lanes, 4:]
            T_place, T_over = T_all[n_lanes], O_all[n_lanes]
            num_steps = steps_all[pick] + steps_all[n_lanes]  # the solution's own steps
            converged = converged1[pick] | conv_all[n_lanes]
            # Another converged minimum, distinct from the solution (camera centres more
            # than `_DISTINCT_MINIMUM` apart): its cost decides whether it is ambiguous.
            distinct = jnp.sum((centres - T_over[None, 4:]) ** 2, axis=-1) > _DISTINCT_MINIMUM**2
            stats["start_picked"] = pick
            stats["runner_up_chi2"] = jnp.min(jnp.where(converged1 & distinct, chi2, jnp.inf))
        step = _implicit_step(strategy, T_place, T_over, data, scenario)
        T_place, T_over = _unpack(step, T_place, T_over)
        result = RESULTS.where(
            converged, RESULTS.successful, RESULTS.nonlinear_max_steps_reached
        )
    else:
        sol = optx.least_squares(
            lambda theta, args: _cycle_residuals(strategy, theta, *args),
            _make_solver(solver.removeprefix("optx-"), rtol, atol),
            jnp.zeros(6 * n, dtype),
            args=(T0_place, T0_over, data, scenario),
            max_steps=max_steps,
            throw=False,
        )
        T_place, T_over = _unpack(sol.value, T0_place, T0_over)
        num_steps = sol.stats["num_steps"]
        result = RESULTS.promote(sol.result)
    finite = jnp.all(jnp.isfinite(T_place)) & jnp.all(jnp.isfinite(T_over))
    result = RESULTS.where(finite, result, RESULTS.no_valid_solution)
    result = RESULTS.where(
        estimate.result == RESULTS.successful, result, estimate.result
    )
    ok = result == RESULTS.successful
    T_place = jnp.where(ok, T_place, T0_place)
    T_over = jnp.where(ok, T_over, T0_over)
    ids = placement_ids(strategy)
    T_world_body = jnp.where(ok, T_place[ids], estimate.poses.T_world_body.wxyz_xyz)
    T_world_over = jnp.where(ok, T_over, estimate.poses.T_world_overhead.wxyz_xyz)
    poses = CyclePoses(jaxlie.SE3(T_world_body), jaxlie.SE3(T_world_over))
    mutual, overhead, lengths = _predict(T_place, T_over, scenario, strategy)
    m_used = data.mutual_weight > 0
    o_used = data.overhead_weight > 0
    e2 = jnp.sum(
        jnp.where(m_used, jnp.sum((mutual - data.mutual_pixels) ** 2, -1), 0.0)
    ) + jnp.sum(jnp.where(o_used, jnp.sum((overhead - data.overhead_pixels) ** 2, -1), 0.0))
    count = jnp.maximum(jnp.sum(m_used) + jnp.sum(o_used), 1).astype(dtype)
    stats["num_steps"] = num_steps
    stats["rms_pixel_error"] = safe_sqrt(e2 / count)
    stats["odometry_rms"] = safe_sqrt(jnp.mean((lengths - data.odometry) ** 2))
    r = whitened(T_place, T_over, data, scenario, strategy)
    stats["chi2"] = jnp.sum(r * r)
    used = 2 * (jnp.sum(m_used) + jnp.sum(o_used)) + jnp.sum(data.odometry_weight > 0)
    stats["dof"] = (used - 6 * n).astype(jnp.int32)
    # Goodness of fit: a cost beyond its 99.9% quantile means a wrong local minimum (a bad
    # closed-form start, e.g. the wrong scale branch of the concurrent strategy) or an
    # outlier: report it instead of returning a confidently wrong pose as successful.
    # Gaussian pixel noise gives chi2 ~ chi-square(dof). The paper's model (radius
    # ~ N(0, sigma), uniform direction) has heavier tails: a whitened sighting is
    # 2 chi-square(1) (mean 2, variance 8, not 4), so chi2 is matched in mean and variance
    # by c * chi-square(dof / c), c = variance / (2 mean). Quantile by Wilson-Hilferty.
    n_sight = (jnp.sum(m_used) + jnp.sum(o_used)).astype(dtype)
    n_odo = jnp.sum(data.odometry_weight > 0).astype(dtype)
    per_sight_var = 8.0 if scenario.noise_model == "paper" else 4.0
    c = (per_sight_var * n_sight + 2.0 * n_odo) / (2.0 * (2.0 * n_sight + n_odo))
    k = jnp.maximum(stats["dof"], 1).astype(dtype) / c
    q999 = c * k * (1.0 - 2.0 / (9.0 * k) + 3.0902 * jnp.sqrt(2.0 / (9.0 * k))) ** 3
    result = RESULTS.where(ok & (stats["chi2"] > q999), RESULTS.inconsistent_fit, result)
    if "runner_up_chi2" in stats:
        ambiguous = stats["runner_up_chi2"] - stats["chi2"] < _AMBIGUITY_MARGIN
        result = RESULTS.where(
            (result == RESULTS.successful) & ambiguous, RESULTS.ambiguous, result
        )
    return CycleEstimate(poses, estimate.scales, result, stats)


def refine_cycle(
    observations: CycleObservations,
    scenario: Scenario,
    estimate: CycleEstimate,
    *,
    solver: str = "lm",
    max_steps: int = 64,
    rtol: float = 1e-6,
    atol: float = 1e-6,
    throw: bool = True,
) -> CycleEstimate:
    r"""Joint maximum-likelihood refinement of a whole cycle.

    Unknowns: the pose `T_world_body` of every distinct robot placement (a robot that does
    not move keeps one pose: 6 placements for the sequential strategy, 7 for the concurrent
    one; see [`jaxloc.placement_ids`][]) and the overhead camera's optical-frame pose
    `T_world_overhead`, each as `T0 exp(delta)` around `estimate` (jaxlie right
    perturbation). The gauge is fixed by holding C1's start pose at the identity (it is the
    world frame `W`); the metric scale comes from the odometry. Minimises the sum of
    squared whitened residuals:

    - every mutual sighting, in pixels of the observing camera: robot `i`'s camera at step
      `k` sees robot `j` at `project(M^T T_world_body[k, i]^{-1} p_j)` with `M` the mount
      (`R_BODY_PTZ` and `scenario.ptz` for C1, identity and `scenario.omni2/omni3` for C2
      and C3);
    - every overhead pixel, `scenario.overhead.project(T_world_overhead^{-1} p_j)`;
    - every odometry distance, `|p_end - p_start| - d`, sigma `observations.odometry_sigma`.

    Pixel residuals are divided by [`jaxloc.pixel_sigma_per_axis`][]`(scenario)`; NaN
    pixels (not measured) are ignored.

    **Arguments:**

    - `observations`: a [`jaxloc.CycleObservations`][] with its pixels (`mutual_pixels`,
        `overhead_pixels`).
    - `scenario`: a [`jaxloc.Scenario`][]: its cameras (`ptz`, `omni2`, `omni3`,
        `overhead`), `pixel_sigma` and `noise_model` are used.
    - `estimate`: the starting point, usually [`jaxloc.localize_cycle`][]`(observations)`.
    - `solver`: keyword only, as are the following. `"lm"` (default): jaxloc's batched
        Levenberg--Marquardt, re-linearized at the current poses with the model's
        chain-rule Jacobian (the fast path for Monte Carlo); `"optx-lm"` / `"optx-gn"`:
        `optx.LevenbergMarquardt` / `optx.GaussNewton` on the same residuals. All reach
        the same minimum; gradients are implicit (w.r.t. the observations and the
        scenario; the minimizer does not depend on `estimate`).
    - `max_steps`, `rtol`, `atol`: the solver's iteration limit and tolerances.
    - `throw`: raise on failure if `True`; otherwise inspect `result`.

    **Returns:** a [`jaxloc.CycleEstimate`][] (same form as `localize_cycle`'s): poses of
    every robot at every step and of the overhead camera in `W`, metres. `scales` are
    copied from `estimate`. `result` is `estimate.result` if that failed (and then the
    poses are `estimate`'s), else the solver's promoted result. `stats` adds
    `"num_steps"` (the returned solution's steps; at most `max_steps`, also for a
    multi-start), `"rms_pixel_error"` (px, over all measured pixels), `"chi2"` (the
    final sum of squared whitened residuals) and `"dof"` (residuals minus unknowns), and
    updates `"odometry_rms"` (m). Under the noise model `chi2 ~ chi-square(dof)`: a value
    above its 99.9% quantile flags a wrong local minimum (`inconsistent_fit`).

    **Multi-start.** When `estimate.stats` carries the closed form's other local minima
    (`"alternative_scales"`, `"alternative_T_world_overhead"`, `"alternative_ok"`, from
    the concurrent strategy's [`jaxloc.localize_cycle`][]: the runner-up scales, and the
    overhead solver's runner-up pose, e.g. the mirror pose of nearly coplanar points), the
    solver `"lm"` refines each start for a few steps and goes on from the one
    with the lowest cost. If another start converged to a distinct minimum (camera more
    than 10 cm away) whose chi-square is within 4 of the solution's, the data cannot tell
    the two apart: `result` is `ambiguous` (the lower minimum is returned). `stats` then
    adds `"start_picked"` (0 = `estimate`'s own poses) and `"runner_up_chi2"` (that other
    minimum's cost, `inf` if none). On the paper's concurrent scenario (10,000 cycles) the
    single start converged to a wrong minimum metres off, with a plausible cost, in ~1
    cycle in 2,000; the multi-start removes them (`jaxloc table1`).

    Single cycle; batch with `jax.vmap`. Works under `jit`, `vmap` and `grad`.
    """
    if solver not in CYCLE_SOLVERS:
        raise ValueError(
            f'`solver` must be "lm", "optx-lm" or "optx-gn"; got {solver!r}.'
        )
    if not isinstance(max_steps, int) or max_steps < 1:
        raise ValueError(f"`max_steps` must be a positive int; got {max_steps!r}.")
    if scenario.strategy != observations.strategy:
        raise ValueError(
            f"`scenario.strategy` ({scenario.strategy!r}) must match "
            f"`observations.strategy` ({observations.strategy!r})."
        )
    out = _refine_cycle_impl(
        observations, scenario, estimate, solver=solver, max_steps=max_steps, rtol=rtol,
        atol=atol,
    )
    return raise_if_failed(out, out.result, throw)
