"""One Monte Carlo trial: simulate a cycle, estimate it with every method, score it."""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import jaxlie
from jaxtyping import Array, Float, Int, PRNGKeyArray

from .._core.compiler import jit
from .._core.linalg import adjugate3, psd_cholesky3
from .._core.numerics import safe_norm
from .._core.poses import compose, inverse, rotation_error, ypr_from_rotation
from .._core.results import RESULTS, status_code
from .._core.robust import robust_loss
from .._cycle.observations import CyclePoses
from .._cycle.rig import Rig
from .._model.covariance import crlb_inputs
from .._model.gates import end_poses, gate_all, gate_point, gate_rivals, gated, GatePoint
from .._model.measurements import cycle_data
from .._refine.cycle import finish_refinement, refine_solution, refined_data
from .._sim.scenario import Scenario
from .._sim.simulate import simulate_cycle
from .._solvers.localize import closed_forms


METHODS = ("paper", "robust", "refined")
"""Estimators a study compares by default. "paper": the paper's closed form with its
linear Eq. 6 for the overhead camera; "robust": the same chain with jaxloc's
planar-safe P3P-based overhead pose; "refined": joint maximum-likelihood refinement of
the whole cycle started from "robust". A study may also ask for "robust-refined" (see
`ALL_METHODS`)."""
#: The refinements a study can run, by method name, with their robust loss (`None`:
#: plain least squares; see [`jaxloc.refine_cycle`][]).
REFINEMENTS = {"refined": None, "robust-refined": "huber"}
ALL_METHODS = METHODS + ("robust-refined",)
"""Every estimator a study can compare: `METHODS` and "robust-refined", the refinement
with the Huber loss and outlier rejection (`refine_cycle(..., loss="huber")`), for
studies of corrupted observations."""
#: Levenberg–Marquardt iteration cap of the "refined" method in studies. Under `vmap` a
#: batch runs as many steps as its slowest trial, so a long tail of rare stragglers would
#: set the cost of every chunk; trials that hit the cap are reported as
#: `nonlinear_max_steps_reached`, not silently kept (measured on the paper's scenario:
#: median 8 steps, p99 16).
REFINE_MAX_STEPS = 24


class TrialErrors(eqx.Module):
    """Errors of one trial's end-of-cycle estimates against the truth, per method.

    All arrays have leading shape `(methods,)` and then one entry per camera in the order
    `("C", "C1", "C2", "C3")` (see `jaxloc.CAMERAS`); C's errors are those of its body
    frame (its camera's centre and the climbing robot's orientation).

    **Fields:**

    - `status`: int32 status code per method (0 = successful; see
      [`jaxloc.status_names`][]), shape `(methods,)`: for the closed forms the solver's
      own status (a study measures every estimate a closed form produced), for the
      refinement its final status, gates included.
    - `gated`: every method's final status, gates included (what
      [`jaxloc.localize_cycle`][] and [`jaxloc.refine_cycle`][] return), shape
      `(methods,)`.
    - `position`: Euclidean position error (m), shape `(methods, 4)`.
    - `rotation`: geodesic rotation error (rad), shape `(methods, 4)`.
    - `ypr`: yaw, pitch, roll errors (rad, estimate minus truth, wrapped to
      `(-pi, pi]`), shape `(methods, 4, 3)`.
    - `position_vector`: estimate minus truth (m) in the world frame, shape
      `(methods, 4, 3)`, for covariance checks.
    - `crlb_position_var`, `crlb_rotation_var`: trace of the Cramér–Rao bound's position
      (m^2) and rotation (rad^2) blocks for each camera at this trial's true poses,
      shape `(4,)`; the study's predicted RMSE is the square root of their mean.
    - `crlb_position_sample`, `crlb_rotation_sample`: the norm of one draw from
      `N(0, bound)` of each camera's position (m) and rotation (rad) block, shape `(4,)`:
      the error of an estimator exactly at the bound on this trial's geometry. Their
      distribution over the trials is what an efficient estimator's median, p90 and p99
      would be (its tails included), beside the refined estimate's.
    - `nees`: normalized estimation error squared of each camera's final position under
      the refined estimate's own first-order covariance, `e^T P^-1 e`, shape `(4,)`
      (expected value 3 for a consistent estimator; NaN where not computed).
    """

    status: Int[Array, " methods"]
    gated: Int[Array, " methods"]
    position: Float[Array, "methods 4"]
    rotation: Float[Array, "methods 4"]
    ypr: Float[Array, "methods 4 3"]
    position_vector: Float[Array, "methods 4 3"]
    crlb_position_var: Float[Array, "4"]
    crlb_rotation_var: Float[Array, "4"]
    crlb_position_sample: Float[Array, "4"]
    crlb_rotation_sample: Float[Array, "4"]
    nees: Float[Array, "4"]


def overhead_body(T_world_overhead: jaxlie.SE3, rig: Rig) -> jaxlie.SE3:
    """Climbing robot's body pose from its camera's optical-frame pose, through the rig's
    mount of C: `T_world_body = T_world_camera @ T_body_camera^-1`."""
    dtype = T_world_overhead.wxyz_xyz.dtype
    T_body_cam = jaxlie.SE3(rig.mounts[0].astype(dtype))
    return compose(T_world_overhead, inverse(T_body_cam))


def final_poses(poses: CyclePoses, rig: Rig) -> jaxlie.SE3:
    """End-of-cycle body poses of (C, C1, C2, C3), batch shape `(4,)`."""
    body_c = overhead_body(poses.T_world_overhead, rig)
    ground = poses.T_world_body.wxyz_xyz[-1]
    return jaxlie.SE3(jnp.concatenate([body_c.wxyz_xyz[None], ground], axis=0))


def _wrap(angle):
    return jnp.arctan2(jnp.sin(angle), jnp.cos(angle))


def score(estimate: CyclePoses, truth: CyclePoses, rig: Rig):
    """Per-camera errors of `estimate` against `truth` (see [`jaxloc.TrialErrors`][])."""
    est, tru = final_poses(estimate, rig), final_poses(truth, rig)

    def one(e, t):
        e, t = jaxlie.SE3(e), jaxlie.SE3(t)
        diff = e.translation() - t.translation()
        pos = safe_norm(diff)
        rot = rotation_error(e.rotation(), t.rotation())
        ypr = _wrap(
            ypr_from_rotation(e.rotation(), degrees=False)
            - ypr_from_rotation(t.rotation(), degrees=False)
        )
        return pos, rot, ypr, diff

    return jax.vmap(one)(est.wxyz_xyz, tru.wxyz_xyz)


def estimate_all(
    observations, rig: Rig, methods: tuple[str, ...] = METHODS, *, truth=None,
    odometry_sigma_rel=None,
):  # fmt: skip
    """Every requested estimator on the same observations (shared ground chain), gated
    together: the closed forms, the refinement started from the robust closed form, and
    (with `truth`) the Cramér–Rao bound at the true poses of the sightings present, in
    one `vmap` of the gates (one traced copy of the gates and of the covariance: polished
    for the closed forms, at the point for the converged refinement and the true
    poses).

    **Returns:** `(estimates, bound)`: the estimates in the order of `methods`, and the
    bound's [`jaxloc.CycleCovariance`][] (`None` without `truth`)."""
    strategy = observations.strategy
    refinements = [m for m in methods if m in REFINEMENTS]
    closed_methods = tuple(m for m in methods if m not in REFINEMENTS)
    if refinements and "robust" not in closed_methods:
        closed_methods = closed_methods + ("robust",)
    estimates = dict(zip(closed_methods, closed_forms(observations, closed_methods)))
    runner_up = {}
    for m in refinements:
        estimates[m], runner_up[m] = refine_solution(
            observations, rig, estimates["robust"], solver="lm", max_steps=REFINE_MAX_STEPS,
            rtol=1e-6, atol=1e-6, loss=robust_loss(REFINEMENTS[m], None),
        )  # fmt: skip
    data = cycle_data(observations, rig)
    closed = [m for m in estimates if m not in REFINEMENTS]
    points = [gate_point(estimates[m], data, strategy) for m in closed]
    rivals = [gate_rivals(estimates[m], p, strategy) for m, p in zip(closed, points)]
    # A converged refinement and the true poses are gated where they are.
    points += [
        gate_point(estimates[m], refined_data(data, estimates[m]), strategy) for m in refinements
    ]
    if truth is not None:
        present = (observations.mutual_visible, observations.overhead_visible)
        T_place, T_over, bound_data = crlb_inputs(
            rig, truth, odometry_sigma_rel, strategy, present
        )
        final = end_poses(T_place, T_over, strategy)
        points.append(GatePoint(T_place, T_over, final, bound_data, RESULTS.successful))
    polish = [i < len(closed) for i in range(len(points))]
    rivals += [None] * (len(points) - len(closed))
    gates = gate_all(points, rig, strategy, polish=polish, rivals=rivals)
    for name, gate in zip(closed, gates):
        estimates[name] = gated(estimates[name], gate)
    for m, gate in zip(refinements, gates[len(closed):]):
        estimates[m] = finish_refinement(estimates[m], runner_up[m], gate)
    bound = gates[-1][2] if truth is not None else None
    return [estimates[m] for m in methods], bound


def position_nees(
    error: Float[Array, "4 3"], covariance: Float[Array, "4 3 3"]
) -> Float[Array, "4"]:
    """`e^T P^-1 e` per camera; NaN where `P` is singular (e.g. the fixed reference)."""

    def one(e, P):
        # Adjugate inverse: no LAPACK call in the hot path (DESIGN §8).
        adj, det = adjugate3(P)
        ok = det > 1e-9 * jnp.trace(P) ** 3
        return jnp.where(ok, e @ (adj @ e) / jnp.where(ok, det, 1.0), jnp.nan)

    return jax.vmap(one)(error, covariance)


def _bound_samples(key, covariance: Float[Array, "4 3 3"]) -> Float[Array, "4"]:
    """Norm of one `N(0, P)` draw per camera."""
    z = jr.normal(key, (4, 3), covariance.dtype)
    L = jax.vmap(psd_cholesky3)(covariance)
    return safe_norm(jnp.einsum("cij,cj->ci", L, z))


@jit(inline=True)
def run_trial(
    scenario: Scenario, key: PRNGKeyArray, methods: tuple[str, ...] = METHODS
) -> TrialErrors:
    """Simulate one cycle of `scenario`, estimate it with each of `methods`, score it.

    Pure and branch-free: batch with `jax.vmap(lambda k: run_trial(scenario, k))(keys)`.
    A trial whose moves could not keep every robot in view gets status `not_visible`;
    a failed estimate keeps its solver's status. Errors of failed trials are finite
    but meaningless: statistics must skip them (see [`jaxloc.summarize`][]).
    """
    truth, observations, all_visible = simulate_cycle(scenario, key)
    rig = scenario.rig
    fields = []
    refined_error = refined_covariance = None
    estimates, bound = estimate_all(
        observations, rig, methods, truth=truth.poses,
        odometry_sigma_rel=scenario.odometry_sigma_rel,
    )  # fmt: skip
    for method, estimate in zip(methods, estimates):
        solver = estimate.result if method in REFINEMENTS else estimate.checks.solver_result
        status = RESULTS.where(all_visible, solver, RESULTS.not_visible)
        gated = RESULTS.where(all_visible, estimate.result, RESULTS.not_visible)
        pos, rot, ypr, diff = score(estimate.poses, truth.poses, rig)
        fields.append((status_code(status), status_code(gated), pos, rot, ypr, diff))
        if method == "refined":
            refined_error, refined_covariance = diff, estimate.covariance
    stacked = [jnp.stack(f) for f in zip(*fields)]
    crlb_pos = jnp.trace(bound.position, axis1=-2, axis2=-1)
    crlb_rot = jnp.trace(bound.rotation, axis1=-2, axis2=-1)
    if refined_error is None:
        nees = jnp.full((4,), jnp.nan, dtype=truth.poses.T_world_overhead.wxyz_xyz.dtype)
    else:
        nees = position_nees(refined_error, refined_covariance.position)
    # A key of its own: the draws change nothing else in the trial.
    k_pos, k_rot = jr.split(jr.fold_in(key, 0x0C7B))
    samples = _bound_samples(k_pos, bound.position), _bound_samples(k_rot, bound.rotation)
    return TrialErrors(*stacked, crlb_pos, crlb_rot, *samples, nees)
