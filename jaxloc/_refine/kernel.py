"""The least-squares kernel on a whole cycle: every distinct robot placement and the
overhead camera from whitened residuals (`jaxloc._model.measurements`), by
`jaxloc._core.least_squares.levenberg_marquardt`, from one start or several. What the
joint refinement ([`jaxloc.refine_cycle`][]) and its robust stages solve with."""

import jax
import jax.numpy as jnp

from .._core.least_squares import levenberg_marquardt
from .._model.gates import DISTINCT_MINIMUM
from .._model.measurements import normal_equations, unpack


#: Predicted decrease of the whitened cost (chi-square units) below which a step of the
#: kernel counts as converged, at the default tolerances (`rtol = atol = 1e-6`); it scales
#: with the square of the tighter one.
NEGLIGIBLE_DECREASE = 1e-4
#: Steps of a multi-start refinement's first phase, where every start is refined (the
#: whole refinement still takes at most `max_steps`).
_MULTI_START_STEPS = 6


def retract(x, delta):
    """The poses `x = (T_place, T_over)` moved by the tangent step `delta` (see `unpack`)."""
    return unpack(delta, *x)


def position_scale(x):
    """The scale of the poses' positions (m), for the kernel's tolerances."""
    return jnp.max(jnp.abs(x[0][:, 4:]))


def cycle_lm(T0_place, T0_over, data, rig, strategy, max_steps, rtol, atol, active, loss=None):
    """The least-squares kernel on a cycle: `(T_place, T_over, num_steps, converged,
    cost)`, `cost` the (robust) cost at the solution (0 for an inactive problem).
    Residuals are whitened, so the predicted decrease is in chi-square units (see
    `levenberg_marquardt`'s `decrease_tol`); the damping starts at 1e-2, a prior
    precision of 100 per m^2 / rad^2. A robust `loss` makes each model evaluation one
    reweighting of the iteratively reweighted least squares (`normal_equations`)."""
    n = T0_place.shape[0]
    out = levenberg_marquardt(
        lambda x: normal_equations(x[0], x[1], data, rig, strategy, loss),
        retract,
        position_scale,
        (T0_place, T0_over),
        num_unknowns=6 * n,
        max_steps=max_steps,
        rtol=rtol,
        atol=atol,
        active=active,
        lam0=1e-2,
        decrease_tol=NEGLIGIBLE_DECREASE * (jnp.minimum(rtol, atol) / 1e-6) ** 2,
    )
    return out.x[0], out.x[1], out.num_steps, out.converged, out.normal.cost


def multi_start(starts, active, data, rig, strategy, max_steps, rtol, atol, loss,
                to_convergence=False, prefer_converged=False):  # fmt: skip
    """Refine every start for a few steps; the one with the lowest cost goes on alone.
    With `to_convergence` (bool) every start is refined to convergence: the azimuth
    starts of a stand-in bearing begin far from every minimum, and measured, the lowest
    cost after a few steps often led to the wrong one. With `prefer_converged` (Python
    bool) the lowest cost among the converged starts wins if any converged (on exact
    data a start can stall a rounding error below the others without converging).

    The phases are jobs of one `lax.while_loop` (one per active start, then the last one)
    so that the kernel and the model are traced and compiled once, and a batch pays only
    for the starts its problems have (the azimuth starts exist only with a stand-in).
    Returns `(T_place, T_over, num_steps, converged, picked, runner_up_chi2)`: the
    solution, the start it came from (0 = the estimate's own poses), and the cost of
    another converged minimum distinct from it (some robot placement or the overhead
    camera more than `DISTINCT_MINIMUM` away; `inf` if none)."""
    start_place, start_over, lanes = starts
    lanes = lanes & active
    dtype = start_place.dtype
    n_lanes = lanes.shape[0]
    n_first = min(max_steps, _MULTI_START_STEPS)
    order = jnp.argsort(~lanes, stable=True)  # the active starts first
    n_active = jnp.sum(lanes)
    first_budget = jnp.where(to_convergence, max_steps, n_first)

    def masked_chi2(chi2):
        return jnp.where(lanes & jnp.isfinite(chi2), chi2, jnp.inf)

    def best_lane(chi2, converged):
        chi2 = masked_chi2(chi2)
        if prefer_converged:
            done = converged & jnp.isfinite(chi2)
            chi2 = jnp.where(jnp.any(done) & ~done, jnp.inf, chi2)
        return jnp.argmin(chi2)

    def job(carry):
        j, (T_place_j, T_over_j, steps_j, converged_j, chi2_j) = carry
        last = j == n_active
        pick = best_lane(chi2_j[:n_lanes], converged_j[:n_lanes])
        lane = order[jnp.minimum(j, n_lanes - 1)]
        tp = jnp.where(last, T_place_j[pick], start_place[lane])
        to = jnp.where(last, T_over_j[pick], start_over[lane])
        act = jnp.where(last, active & ~converged_j[pick], lanes[lane])
        budget = jnp.where(last, max_steps - n_first, first_budget)
        tp, to, k, conv, chi2 = cycle_lm(tp, to, data, rig, strategy, budget, rtol, atol, act, loss)
        slot = jnp.where(last, n_lanes, lane)
        slots = (
            T_place_j.at[slot].set(tp), T_over_j.at[slot].set(to), steps_j.at[slot].set(k),
            converged_j.at[slot].set(conv), chi2_j.at[slot].set(chi2),
        )  # fmt: skip
        return j + 1, slots

    n_jobs = n_lanes + 1
    slots = (
        jnp.zeros((n_jobs,) + start_place.shape[1:], dtype),
        jnp.zeros((n_jobs,) + start_over.shape[1:], dtype),
        jnp.zeros(n_jobs, jnp.int32),
        jnp.zeros(n_jobs, bool),
        jnp.full(n_jobs, jnp.inf, dtype),
    )
    _, (T_all, O_all, steps_all, conv_all, chi2_all) = jax.lax.while_loop(
        lambda carry: carry[0] <= n_active, job, (jnp.array(0, n_active.dtype), slots)
    )
    chi2 = masked_chi2(chi2_all[:n_lanes])
    converged1 = conv_all[:n_lanes]
    pick = best_lane(chi2_all[:n_lanes], converged1)
    T_place, T_over = T_all[n_lanes], O_all[n_lanes]
    num_steps = steps_all[pick] + steps_all[n_lanes]  # the solution's own steps
    converged = converged1[pick] | conv_all[n_lanes]
    positions = jnp.concatenate([T_all[..., 4:], O_all[:, None, 4:]], axis=1)
    gaps = jnp.sum((positions[:n_lanes] - positions[n_lanes][None]) ** 2, axis=-1)
    distinct = jnp.max(gaps, axis=-1) > DISTINCT_MINIMUM**2
    runner_up_chi2 = jnp.min(jnp.where(converged1 & distinct, chi2, jnp.inf))
    return T_place, T_over, num_steps, converged, pick, runner_up_chi2
