"""One Monte Carlo trial: simulate a cycle, estimate it with every method, score it."""

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import jaxlie
from jaxtyping import Array, Float, Int, PRNGKeyArray

from .._cameras.presets import R_BODY_OVERHEAD
from .._core.numerics import adjugate3, safe_norm
from .._core.poses import rotation_error, ypr_from_rotation
from .._core.results import RESULTS, status_code
from .._cycle.observations import CyclePoses
from .._refine.covariance import _covariance_at, _covariance_inputs, _crlb_inputs
from .._refine.cycle import refine_cycle
from .._sim.scenario import Scenario
from .._sim.simulate import simulate_cycle
from .._solvers.strategies import CycleEstimate, localize_cycle_methods


#: Estimators a study can compare. "paper": the paper's closed form with its linear Eq. 6
#: for the overhead camera; "robust": the same chain with jaxloc's planar-safe P3P-based
#: overhead pose; "refined": joint maximum-likelihood refinement of the whole cycle
#: started from "robust".
METHODS = ("paper", "robust", "refined")
#: Levenberg–Marquardt iteration cap of the "refined" method in studies. Under `vmap` a
#: batch runs as many steps as its slowest trial, so a long tail of rare stragglers would
#: set the cost of every chunk; trials that hit the cap are reported as
#: `nonlinear_max_steps_reached`, not silently kept (measured on the paper's scenario:
#: median 8 steps, p99 16).
REFINE_MAX_STEPS = 24
#: Order of the cameras in every per-camera array: overhead C, then C1, C2, C3.
CAMERAS = ("C", "C1", "C2", "C3")


class TrialErrors(eqx.Module):
    """Errors of one trial's end-of-cycle estimates against the truth, per method.

    All arrays have leading shape `(methods,)` and then one entry per camera in the order
    `("C", "C1", "C2", "C3")` (see `jaxloc.CAMERAS`); C's errors are those of its body
    frame (its camera's centre and the climbing robot's orientation).

    **Fields:**

    - `status`: int32 status code per method (0 = successful; see
      [`jaxloc.status_names`][]), shape `(methods,)`.
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
    position: Float[Array, "methods 4"]
    rotation: Float[Array, "methods 4"]
    ypr: Float[Array, "methods 4 3"]
    position_vector: Float[Array, "methods 4 3"]
    crlb_position_var: Float[Array, "4"]
    crlb_rotation_var: Float[Array, "4"]
    crlb_position_sample: Float[Array, "4"]
    crlb_rotation_sample: Float[Array, "4"]
    nees: Float[Array, "4"]


def overhead_body(T_world_overhead: jaxlie.SE3) -> jaxlie.SE3:
    """Climbing robot's body pose from its camera's optical-frame pose (fixed mount)."""
    R_body_cam = jaxlie.SO3.from_matrix(
        jnp.asarray(R_BODY_OVERHEAD, T_world_overhead.wxyz_xyz.dtype)
    )
    return T_world_overhead @ jaxlie.SE3.from_rotation(R_body_cam.inverse())


def final_poses(poses: CyclePoses) -> jaxlie.SE3:
    """End-of-cycle body poses of (C, C1, C2, C3), batch shape `(4,)`."""
    body_c = overhead_body(poses.T_world_overhead)
    ground = poses.T_world_body.wxyz_xyz[-1]
    return jaxlie.SE3(jnp.concatenate([body_c.wxyz_xyz[None], ground], axis=0))


def _wrap(angle):
    return jnp.arctan2(jnp.sin(angle), jnp.cos(angle))


def score(estimate: CyclePoses, truth: CyclePoses):
    """Per-camera errors of `estimate` against `truth` (see [`jaxloc.TrialErrors`][])."""
    est, tru = final_poses(estimate), final_poses(truth)

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
    observations, scenario: Scenario, methods: tuple[str, ...] = METHODS
) -> list[CycleEstimate]:
    """Run every requested estimator on the same observations (shared ground chain)."""
    closed = tuple(m for m in methods if m != "refined")
    if "refined" in methods and "robust" not in closed:
        closed = closed + ("robust",)
    estimates = dict(zip(closed, localize_cycle_methods(observations, closed)))
    if "refined" in methods:
        estimates["refined"] = refine_cycle(
            observations, scenario, estimates["robust"], max_steps=REFINE_MAX_STEPS, throw=False
        )
    return [estimates[m] for m in methods]


def _nees(error: Float[Array, "4 3"], covariance: Float[Array, "4 3 3"]) -> Float[Array, "4"]:
    """`e^T P^-1 e` per camera; NaN where `P` is singular (e.g. the fixed reference)."""

    def one(e, P):
        # Adjugate inverse: no LAPACK call in the hot path (DESIGN §8).
        adj, det = adjugate3(P)
        ok = det > 1e-9 * jnp.trace(P) ** 3
        return jnp.where(ok, e @ (adj @ e) / jnp.where(ok, det, 1.0), jnp.nan)

    return jax.vmap(one)(error, covariance)


def _psd_cholesky3(P: Float[Array, "3 3"]) -> Float[Array, "3 3"]:
    """Lower Cholesky factor of a 3x3 positive semi-definite matrix, element-wise (no
    LAPACK call); a zero pivot (e.g. the fixed reference robot's zero covariance) gives a
    zero column."""

    def root(x):
        ok = x > 0
        return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)

    def div(a, b):
        ok = b > 0
        return jnp.where(ok, a / jnp.where(ok, b, 1.0), 0.0)

    l00 = root(P[0, 0])
    l10, l20 = div(P[1, 0], l00), div(P[2, 0], l00)
    l11 = root(P[1, 1] - l10 * l10)
    l21 = div(P[2, 1] - l20 * l10, l11)
    l22 = root(P[2, 2] - l20 * l20 - l21 * l21)
    zero = jnp.zeros_like(l00)
    return jnp.stack(
        [jnp.stack([l00, zero, zero]), jnp.stack([l10, l11, zero]), jnp.stack([l20, l21, l22])]
    )


def _bound_samples(key, covariance: Float[Array, "4 3 3"]) -> Float[Array, "4"]:
    """Norm of one `N(0, P)` draw per camera."""
    z = jr.normal(key, (4, 3), covariance.dtype)
    L = jax.vmap(_psd_cholesky3)(covariance)
    return safe_norm(jnp.einsum("cij,cj->ci", L, z))


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
    strategy = observations.strategy
    fields = []
    refined_error = None
    # The Cramér–Rao bound (information at the truth) and the refined estimate's
    # covariance (information at the estimate) are one computation at two linearization
    # points: run them as one `vmap` over both, so it is compiled once.
    points = [_crlb_inputs(scenario, truth.poses, strategy)]
    for method, estimate in zip(methods, estimate_all(observations, scenario, methods)):
        result = RESULTS.where(all_visible, estimate.result, RESULTS.not_visible)
        pos, rot, ypr, diff = score(estimate.poses, truth.poses)
        fields.append((status_code(result), pos, rot, ypr, diff))
        if method == "refined":
            refined_error = diff
            points.append(_covariance_inputs(observations, scenario, estimate))
    stacked = [jnp.stack(f) for f in zip(*fields)]
    covs = jax.vmap(lambda T_place, T_over, data: _covariance_at(
        T_place, T_over, data, scenario, strategy
    ))(*jax.tree.map(lambda *x: jnp.stack(x), *points))
    crlb_pos = jnp.trace(covs.position[0], axis1=-2, axis2=-1)
    crlb_rot = jnp.trace(covs.rotation[0], axis1=-2, axis2=-1)
    if refined_error is None:
        nees = jnp.full((4,), jnp.nan, dtype=truth.poses.T_world_overhead.wxyz_xyz.dtype)
    else:
        nees = _nees(refined_error, covs.position[1])
    # A key of its own: the draws change nothing else in the trial.
    k_pos, k_rot = jr.split(jr.fold_in(key, 0x0C7B))
    samples = _bound_samples(k_pos, covs.position[0]), _bound_samples(k_rot, covs.rotation[0])
    return TrialErrors(*stacked, crlb_pos, crlb_rot, *samples, nees)
