r"""One-step localization of the climbing robot from a single formation and a prior
(issue 21.4; the paper's future work: "to solve the problem in one step").

The ground robots stand still; each sees the two others once (a [`Snapshot`][]) and the
overhead camera sees the three. No robot moves, so there is no odometry: the formation is
known up to scale from the mutual bearings ([`jaxloc.mutual_localization`][], C1's body
frame, circumdiameter 1), and three points give up to four camera poses (P3P,
[`jaxloc.p3p`][]). A prior on the climbing robot (a [`OneStepPrior`][]) supplies what the
bearings cannot:

- the previous estimate propagated by the climbing robot's odometry (a pose with its
  covariance), and the formation's size from the last full cycle (its perimeter with its
  sigma): [`OneStepPrior.pose_prior`][] and [`OneStepPrior.with_scale`][];
- for the first cycle, the overhead camera's height above the ground robots' plane and the
  climbing robot's body z along that plane's normal ([`OneStepPrior.height_prior`][]): the
  height also fixes the scale.

**Algorithm.** At a scale `d` (circumdiameter, m) every P3P root's camera centre is
`d c_i` and its rotation does not change; every prior's residual is linear in `d` to first
order (the pose prior's translation as `R_prior^T (p - p_prior)`), so each root gets its best
scale and its prior misfit in closed form. The root of least misfit is kept; when another
valid root's misfit is within `AMBIGUITY_MARGIN` (chi-square units) the prior cannot
decide and the estimate is `ambiguous` (its best root returned). Its pose and scale are
then refined (maximum a posteriori: the three overhead pixels and the priors, whitened,
with [`levenberg_marquardt`][]; the formation's shape stays the closed form's) and gated:
chi-square of the whitened residuals against their degrees of freedom (the rig's noise
model, `jaxloc._model.gates.chi2_limit`) and observability (its information positive
definite, its position bound below `MAX_RELATIVE_POSITION_BOUND` times the formation's
size). The closed form takes every camera centre and marker to be at its robot's body
origin, as [`jaxloc.localize_cycle`][] does.

**Bound** ([`one_step_bound`][]): the Bayesian Cramér–Rao bound of the whole one-step
problem at the true poses: unknowns C2's and C3's body poses and the climbing robot's, the
mutual and overhead pixels of the formation (`jaxloc._model.measurements`), and the priors.
"""

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._core.compiler import jit
from .._core.least_squares import levenberg_marquardt, normal_equations
from .._core.linalg import cholesky, gram, small_spd_inverse, spd_inverse
from .._core.numerics import safe_normalize
from .._core.poses import compose, identity_params, inverse, quaternion_matrix, rplus
from .._core.results import raise_if_failed, RESULTS
from .._cycle.estimate import FitCheck
from .._cycle.layout import placement_ids
from .._cycle.observations import CycleObservations
from .._cycle.rig import Rig
from .._cycle.sightings import camera_pose_jacobian, in_body, matmul, matvec, skew
from .._model.gates import (
    chi2_limit,
    formation_size,
    MAX_RELATIVE_POSITION_BOUND,
    MAX_ROTATION_BOUND,
    nonsingular_information,
    worst_measurement,
)
from .._model.measurements import CycleData, pixel_weights, rotations, whitened_with_jacobian
from .._solvers.mutual import mutual_localization
from .._solvers.p3p import p3p
from .frames import (
    adjoint,
    body_of_overhead,
    overhead_of_body,
    perimeter,
    plane_normal,
    so3_exp,
    so3_jr_inv,
    so3_log,
)


#: Two P3P roots whose prior misfits (chi-square units) differ by less than this make the
#: estimate `ambiguous` (a likelihood ratio below e^2 ~ 7, as `jaxloc.refine_cycle`'s).
AMBIGUITY_MARGIN = 4.0
#: Iteration cap of the one-step refinement (Levenberg--Marquardt).
ONE_STEP_MAX_STEPS = 40
#: Predicted decrease of the whitened cost (chi-square units) below which the one-step
#: refinement counts as converged (as the smoother's).
NEGLIGIBLE_DECREASE = 1e-4
#: Number of prior residuals: pose (6), height (1), tilt (2), scale (1).
_PRIOR_ROWS = 10


class Snapshot(eqx.Module):
    """One formation of the ground robots, seen once.

    **Fields:** `mutual` `(3, 3, 3)`: unit bearings robot `i` -> robot `j` in robot `i`'s
    body frame (diagonal ignored; as [`jaxloc.CycleObservations`][]`.mutual` at one step);
    `overhead` `(3, 3)`: unit bearings of the three robots in the overhead camera's
    frame; `overhead_pixels` `(3, 2)`: the pixels they came from; `overhead_visible`
    `(3,)`.
    """

    mutual: Float[Array, "3 3 3"]
    overhead: Float[Array, "3 3"]
    overhead_pixels: Float[Array, "3 2"]
    overhead_visible: Bool[Array, " 3"]

    @classmethod
    def of(cls, observations: CycleObservations, step: int = 0) -> "Snapshot":
        """Step `step` of a cycle's observations (pixels derived from the bearings where
        the observations hold none, by [`refine_cycle`][]'s rule, at refinement)."""
        return cls(
            observations.mutual[..., step, :, :, :],
            observations.overhead[..., step, :, :],
            observations.overhead_pixels[..., step, :, :],
            observations.overhead_visible[..., step, :],
        )


class OneStepPrior(eqx.Module):
    """What is known of the climbing robot before the overhead camera's sightings, in the
    formation's frame (C1's body frame).

    **Fields** (a weight 0 switches a prior off):

    - `pose`: the climbing robot's body pose `T_world_climber` (`wxyz_xyz`), with
      `pose_sqrt_information` `(6, 6)`: `S` with `S^T S = cov^-1` of its right
      perturbation (zeros: no pose prior).
    - `height` (m): the overhead camera centre's height above the plane of the three ground
      robots' markers, with weight `height_weight` (1/m); `tilt_weight` (1/rad): the
      climbing robot's body z along that plane's normal.
    - `perimeter` (m): the formation's perimeter (sum of its three sides, body origins),
      with weight `perimeter_weight` (1/m).
    """

    pose: Float[Array, "7"]
    pose_sqrt_information: Float[Array, "6 6"]
    height: Float[Array, ""]
    height_weight: Float[Array, ""]
    tilt_weight: Float[Array, ""]
    perimeter: Float[Array, ""]
    perimeter_weight: Float[Array, ""]

    @classmethod
    def none(cls, dtype=None) -> "OneStepPrior":
        """No prior at all (every weight 0)."""
        dtype = jnp.result_type(float) if dtype is None else dtype
        z = jnp.zeros((), dtype)
        return cls(identity_params(dtype), jnp.zeros((6, 6), dtype), z, z, z, z, z)

    @classmethod
    def pose_prior(cls, pose, covariance) -> "OneStepPrior":
        """A prior on the climbing robot's body pose (mean `wxyz_xyz`, right-perturbation
        covariance `(6, 6)`, positive definite)."""
        pose = jnp.asarray(pose)
        covariance = jnp.asarray(covariance, pose.dtype)
        if pose.shape[-1:] != (7,) or covariance.shape[-2:] != (6, 6):
            raise ValueError(
                "`OneStepPrior.pose_prior` needs `pose` of shape (7,) (wxyz_xyz) and "
                f"`covariance` of shape (6, 6); got {pose.shape} and {covariance.shape}."
            )
        info, _ = small_spd_inverse(0.5 * (covariance + covariance.T))
        S = sqrt_information(info)
        return eqx.tree_at(lambda p: (p.pose, p.pose_sqrt_information), cls.none(pose.dtype),
                           (pose, S))  # fmt: skip

    @classmethod
    def height_prior(cls, height, height_sigma, tilt_sigma, dtype=None) -> "OneStepPrior":
        """The first cycle's prior: the overhead camera's height above the ground robots'
        plane (m) with its sigma (m), and the tilt sigma (rad) of the climbing robot's body
        z about that plane's normal."""
        height = jnp.asarray(height) if dtype is None else jnp.asarray(height, dtype)
        p = cls.none(height.dtype)
        w_h = 1.0 / jnp.asarray(height_sigma, height.dtype)
        w_t = 1.0 / jnp.asarray(tilt_sigma, height.dtype)
        return eqx.tree_at(lambda p: (p.height, p.height_weight, p.tilt_weight), p,
                           (height, w_h, w_t))  # fmt: skip

    def with_scale(self, perimeter, sigma) -> "OneStepPrior":
        """This prior and the formation's perimeter (m) with its sigma (m), e.g. from the
        last full cycle."""
        dtype = self.pose.dtype
        return eqx.tree_at(
            lambda p: (p.perimeter, p.perimeter_weight), self,
            (jnp.asarray(perimeter, dtype), 1.0 / jnp.asarray(sigma, dtype)),
        )  # fmt: skip


def sqrt_information(info: Float[Array, "6 6"]) -> Float[Array, "6 6"]:
    """`S` with `S^T S = info` (the transposed Cholesky factor; symmetric eigen-free)."""
    L = cholesky(0.5 * (info + info.T))
    ok = jnp.all(jnp.isfinite(L))
    return jnp.where(ok, L.T, 0.0)


class OneStepEstimate(eqx.Module):
    """The climbing robot's pose from one formation.

    **Fields:**

    - `T_world_climber`: its body pose in the formation's frame `W` (C1's body frame).
    - `T_world_overhead`: its camera's optical-frame pose.
    - `T_world_body`: the formation at metric scale, the ground robots' body poses `(3, 7)`
      (C1 the identity).
    - `scale`: the formation's circumdiameter (m).
    - `result`: a [`jaxloc.RESULTS`][]: `successful`, `ambiguous` (the prior does not
      decide between P3P roots), `inconsistent_fit`, `unobservable`,
      `scale_unobservable` (no prior fixes the scale), `no_valid_solution` (no P3P root),
      `too_few_points` (fewer than three overhead sightings), `nonfinite_observation`,
      `degenerate_configuration` (collinear robots), `nonlinear_max_steps_reached`.
    - `covariance`: of the right perturbation of `T_world_climber` and of the scale,
      `(7, 7)`.
    - `roots`: every P3P root's body pose at its best scale `(4, 7)`, `roots_ok` `(4,)`,
      `root_cost` `(4,)` (prior misfit, chi-square units; inf if invalid), `chosen` (the
      root refined).
    - `checks`: a [`FitCheck`][]; `num_steps`: refinement steps.
    """

    T_world_climber: Float[Array, "7"]
    T_world_overhead: Float[Array, "7"]
    T_world_body: Float[Array, "3 7"]
    scale: Float[Array, ""]
    result: RESULTS
    covariance: Float[Array, "7 7"]
    roots: Float[Array, "4 7"]
    roots_ok: Bool[Array, " 4"]
    root_cost: Float[Array, " 4"]
    chosen: Int[Array, ""]
    checks: FitCheck
    num_steps: Int[Array, ""]

    @property
    def position_covariance(self) -> Float[Array, "3 3"]:
        """World-frame covariance (m^2) of the climbing robot's body position."""
        R = quaternion_matrix(self.T_world_climber[:4]).astype(self.covariance.dtype)
        return R @ self.covariance[:3, :3] @ R.T


def prior_residuals(
    prior: OneStepPrior,
    R_body: Float[Array, "3 3"],
    p_body: Float[Array, "3"],
    positions: Float[Array, "3 3"],
    markers: Float[Array, "3 3"],
    up: Float[Array, "3"],
    mount: Float[Array, "7"],
) -> Float[Array, " 10"]:
    """The whitened prior residuals `(10,)` of the climbing robot's body at `(R_body,
    p_body)` and the ground robots' body origins `positions` and markers `markers` (W):
    pose (6: `S (R_p^T (p - p_p), log(R_p^T R))`, the prior's translation and rotation
    errors in its own frame, which to first order is jaxlie's right perturbation), height
    (1), tilt (2), perimeter (1)."""
    dtype = R_body.dtype
    R_p = rotations(prior.pose)
    xi = jnp.concatenate([R_p.T @ (p_body - prior.pose[4:]), so3_log(R_p.T @ R_body)])
    r_pose = prior.pose_sqrt_information @ xi
    n = plane_normal(markers, up)
    R_m, t_m = rotations(mount.astype(dtype)), mount[4:].astype(dtype)
    centre = p_body + R_body @ t_m
    r_height = prior.height_weight * (jnp.sum(n * (centre - markers[0])) - prior.height)
    r_tilt = prior.tilt_weight * (n @ R_body)[:2]  # (R^T n)_xy
    del R_m
    r_scale = prior.perimeter_weight * (perimeter(positions) - prior.perimeter)
    return jnp.concatenate([r_pose, r_height[None], r_tilt, r_scale[None]])


def _root_costs(prior: OneStepPrior, R_wb, c_unit, u, up, t_m, dtype):
    """Each root's best scale and prior misfit (first order, closed form in the scale)."""
    n = plane_normal(u, up)
    p_prior = prior.pose[4:]
    R_prior = rotations(prior.pose)
    S = prior.pose_sqrt_information
    P_unit = perimeter(u)

    def one(R, c):
        # Body position p(d) = d c - R t_m; camera centre d c.
        v_a = R_prior.T @ (-R @ t_m - p_prior)
        v_b = R_prior.T @ c
        w = so3_log(R_prior.T @ R)
        pose_a = S @ jnp.concatenate([v_a, w])
        pose_b = S[:, :3] @ v_b
        h_a = -prior.height_weight * prior.height
        h_b = prior.height_weight * jnp.sum(n * c)
        tilt = prior.tilt_weight * (n @ R)[:2]
        s_a, s_b = -prior.perimeter_weight * prior.perimeter, prior.perimeter_weight * P_unit
        a = jnp.concatenate([pose_a, h_a[None], tilt, s_a[None]])
        b = jnp.concatenate([pose_b, h_b[None], jnp.zeros(2, dtype), s_b[None]])
        bb = jnp.sum(b * b)
        has_scale = bb > 0
        d = jnp.where(has_scale, -jnp.sum(a * b) / jnp.where(has_scale, bb, 1.0), 1.0)
        ok = has_scale & (d > 0)
        d = jnp.where(ok, d, 1.0)
        return d, jnp.sum((a + b * d) ** 2), ok

    return jax.vmap(one)(R_wb, c_unit)


class _Problem(eqx.Module):
    """The one-step refinement's fixed inputs (matrix form, no quaternions)."""

    u: Float[Array, "3 3"]  # robots' body origins, circumdiameter 1
    markers: Float[Array, "3 3"]  # R_r m_r: the markers' offsets in W
    up: Float[Array, "3"]
    pixels: Float[Array, "3 2"]
    weight: Float[Array, " 3"]
    R_m: Float[Array, "3 3"]
    t_m: Float[Array, "3"]
    Ad_m: Float[Array, "6 6"]  # Ad(M^-1): body perturbation -> camera perturbation
    R_p: Float[Array, "3 3"]  # the pose prior's mean
    p_p: Float[Array, "3"]


def _model(x, prior: OneStepPrior, pb: _Problem, camera):
    """Whitened residuals `(16,)` (overhead pixels, priors) at `x = (R_body, p_body, d)` and
    their Jacobian `(16, 7)` w.r.t. the retraction of [`_retract`][], in closed form."""
    R, p, d = x
    dtype = R.dtype
    R_O, p_O = R @ pb.R_m, p + R @ pb.t_m
    X = d * pb.u + pb.markers
    x_cam = in_body(R_O, p_O, X)
    uv, Jp = camera.project_with_jacobian(x_cam)
    r_px = pb.weight[:, None] * (uv - pb.pixels)
    D_pose = matmul(camera_pose_jacobian(x_cam), pb.Ad_m[None])
    D = jnp.concatenate([D_pose, (pb.u @ R_O)[..., None]], axis=-1)  # d/dd: R_O^T u
    J_px = pb.weight[:, None, None] * matmul(Jp, D)
    # Priors.
    Rp_R = pb.R_p.T @ R
    phi = so3_log(Rp_R)
    S = prior.pose_sqrt_information
    r_pose = S @ jnp.concatenate([pb.R_p.T @ (p - pb.p_p), phi])
    J_pose = jnp.concatenate([S[:, :3] @ Rp_R, S[:, 3:] @ so3_jr_inv(phi)], axis=1)
    n = plane_normal(X, pb.up)
    nR = n @ R
    r_height = prior.height_weight * (jnp.sum(n * (p_O - X[0])) - prior.height)
    J_height = prior.height_weight * jnp.concatenate([nR, -nR @ skew(pb.t_m)])
    r_tilt = prior.tilt_weight * nR[:2]
    J_tilt = prior.tilt_weight * jnp.concatenate([jnp.zeros((2, 3), dtype), skew(nR)[:2]], 1)
    P_unit = perimeter(pb.u)
    r_scale = prior.perimeter_weight * (d * P_unit - prior.perimeter)
    z1 = jnp.zeros((1,), dtype)
    r = jnp.concatenate([r_px.reshape(-1), r_pose, r_height[None], r_tilt, r_scale[None]])
    J = jnp.concatenate([
        J_px.reshape(-1, 7),
        jnp.concatenate([J_pose, jnp.zeros((6, 1), dtype)], 1),
        jnp.concatenate([J_height, z1])[None],
        jnp.concatenate([J_tilt, jnp.zeros((2, 1), dtype)], 1),
        jnp.concatenate([jnp.zeros(6, dtype), prior.perimeter_weight * P_unit[None]])[None],
    ])  # fmt: skip
    return r, J


def _retract(x, delta):
    """`(R exp(omega), p + R v, d + delta_d)`: to first order jaxlie's right perturbation."""
    R, p, d = x
    return R @ so3_exp(delta[3:6]), p + R @ delta[:3], d + delta[6]


class _Roots(NamedTuple):
    """The P3P roots of the overhead bearings at unit scale and the prior's choice."""

    bearings: Float[Array, "3 3"]  # unusable sightings replaced by the optical axis
    usable: Bool[Array, " 3"]
    nonfinite: Bool[Array, ""]  # a sighting marked visible is not finite
    R_wb: Float[Array, "4 3 3"]  # each root's body rotation
    p_roots: Float[Array, "4 3"]  # each root's body position at its best scale
    d_root: Float[Array, " 4"]  # each root's best scale
    cost: Float[Array, " 4"]  # prior misfit, inf if invalid
    valid: Bool[Array, " 4"]
    any_p3p: Bool[Array, ""]  # P3P gave a root at all
    any_scaled: Bool[Array, ""]  # a P3P root has a positive scale from the prior
    chosen: Int[Array, ""]
    ambiguous: Bool[Array, ""]


def _formation(snapshot: Snapshot):
    """The formation up to scale (circumdiameter 1) in C1's body frame from the mutual
    bearings: the mutual-localization result, body poses `(3, 7)`, origins `(3, 3)`, body
    rotations `(3, 3, 3)` and the mean body z (`up`)."""
    mutual = mutual_localization(snapshot.mutual, 0, throw=False)
    T_ref = mutual.T_ref_body.wxyz_xyz
    R_robots = rotations(T_ref)
    up = safe_normalize(jnp.sum(R_robots[:, :, 2], axis=0))
    return mutual, T_ref, T_ref[:, 4:], R_robots, up


def _choose_root(snapshot: Snapshot, u, up, mount, prior: OneStepPrior) -> _Roots:
    """P3P on the overhead bearings at unit scale; each root's best scale and prior
    misfit; the root of least misfit and whether another is within `AMBIGUITY_MARGIN`."""
    dtype = snapshot.overhead.dtype
    R_m, t_m = rotations(mount), mount[4:]
    vis = snapshot.overhead_visible
    finite = jnp.all(jnp.isfinite(snapshot.overhead), axis=-1)
    usable = vis & finite
    b = jnp.where(usable[:, None], snapshot.overhead, jnp.array([0.0, 0.0, 1.0], dtype))
    sol = p3p(u, b)
    Tcw = sol.poses.wxyz_xyz
    R_cw = rotations(Tcw)
    c_unit = -jnp.sum(R_cw * Tcw[:, 4:, None], axis=-2)  # -R^T t
    R_wb = jnp.einsum("kji,lj->kil", R_cw, R_m)  # R_cw^T R_m^T
    d_root, cost, scaled = _root_costs(prior, R_wb, c_unit, u, up, t_m, dtype)
    valid = sol.valid & scaled
    cost = jnp.where(valid, cost, jnp.inf)
    chosen = jnp.argmin(cost)
    second = jnp.min(jnp.where(jnp.arange(4) == chosen, jnp.inf, cost))
    p_roots = d_root[:, None] * c_unit - jnp.einsum("kij,j->ki", R_wb, t_m)
    return _Roots(
        b, usable, jnp.any(vis & ~finite), R_wb, p_roots, d_root, cost, valid,
        jnp.any(sol.valid), jnp.any(scaled & sol.valid), chosen,
        second - cost[chosen] < AMBIGUITY_MARGIN,
    )  # fmt: skip


def _refine_root(snapshot: Snapshot, rig: Rig, prior: OneStepPrior, roots: _Roots, u,
                 R_robots, up, mount):  # fmt: skip
    """Maximum a posteriori pose and scale from the chosen root: the three overhead pixels
    and the priors, whitened. Returns the solver's output, its start flag, the covariance
    `(7, 7)` with its flag, the final Gauss--Newton step, and the whitened residuals
    `(16,)` and their Jacobian `(16, 7)` where it ends."""
    dtype = snapshot.overhead.dtype
    R_m, t_m = rotations(mount), mount[4:]
    usable = roots.usable
    pixel_ok = jnp.all(jnp.isfinite(snapshot.overhead_pixels), axis=-1)
    derived = rig.overhead.project(roots.bearings)
    pixels = jnp.where(usable[:, None], jnp.where(pixel_ok[:, None], snapshot.overhead_pixels,
                                                  derived), 0.0)  # fmt: skip
    pb = _Problem(
        u, matvec(R_robots, rig.markers[1:].astype(dtype)), up, pixels,
        jnp.where(usable, pixel_weights(rig, dtype)[0], 0.0), R_m, t_m,
        adjoint(inverse(jaxlie.SE3(mount)).wxyz_xyz), rotations(prior.pose), prior.pose[4:],
    )  # fmt: skip
    k = roots.chosen
    start_ok = jnp.isfinite(roots.cost[k]) & (jnp.sum(usable) == 3) & ~roots.nonfinite
    x0 = (jnp.where(start_ok, roots.R_wb[k], jnp.eye(3, dtype=dtype)),
          jnp.where(start_ok, roots.p_roots[k], 0.0), jnp.where(start_ok, roots.d_root[k], 1.0))
    # Levenberg--Marquardt from the root (it fits the bearings exactly and its scale
    # already minimizes the linearized prior misfit). Along the weakly observed combination
    # of a sideways shift and a tilt of the camera, the prior pulls and the pixels are
    # curved: Gauss--Newton converges only linearly there (about tenfold per step on a
    # typical problem, far slower from a root metres off). Two fixed Gauss--Newton steps
    # (tried first) left 24 % of the paper scenario's updates with a 20 cm / 5 deg prior
    # unconverged, rejected by the chi-square gate (median error 0.8 m; measured on 512);
    # iterating to convergence, with the predicted decrease as the stopping test, leaves
    # 0.6 % inconsistent (chi-square 28 against a limit of 27.7) in 5 model evaluations
    # (median; p90 17, largest 30 of 512: hence the cap of 40). The gates' `chi2_min` is
    # the misfit at the final Gauss--Newton step's linearized optimum (as
    # `jaxloc._model.gates.check`).
    camera = rig.overhead
    out = levenberg_marquardt(
        lambda x: normal_equations(*_model(x, prior, pb, camera)), _retract,
        lambda x: jnp.max(jnp.abs(x[1])), x0, num_unknowns=7, max_steps=ONE_STEP_MAX_STEPS,
        rtol=1e-6, atol=1e-6, active=start_ok, lam0=1e-4, decrease_tol=NEGLIGIBLE_DECREASE,
        final_gauss_newton=True,
    )  # fmt: skip
    _, H, g = out.normal  # before the final Gauss--Newton step
    cov, cov_ok = small_spd_inverse(H)
    r, J = _model(out.x, prior, pb, camera)
    cov_ok = cov_ok & nonsingular_information(J)
    step = jnp.where(cov_ok & start_ok, -cov @ g, 0.0)
    return out, start_ok, cov, cov_ok, step, (r, J)


def _gate(rig: Rig, prior: OneStepPrior, mutual, roots: _Roots, out, start_ok, cov, cov_ok,
          step, fit, T_ref):  # fmt: skip
    """The estimate's [`FitCheck`][] and result: the solver's status, observability (its
    position bound against the formation's size), the chi-square gate and the test of
    each overhead sighting and prior row against the rest
    ([`jaxloc._model.gates.worst_measurement`][]; `fit`: the whitened residuals and their
    Jacobian where the refinement ends), then `ambiguous`."""
    dtype = cov.dtype
    cost, _, g = out.normal
    R_b, _, d = out.x
    count = jnp.sum(roots.usable)
    prior_rows = (
        6 * jnp.any(prior.pose_sqrt_information != 0)
        + (prior.height_weight > 0) + 2 * (prior.tilt_weight > 0) + (prior.perimeter_weight > 0)
    ).astype(jnp.int32)
    dof = (2 * count + prior_rows - 7).astype(jnp.int32)
    chi2 = jnp.maximum(cost + jnp.sum(g * step), 0.0)
    limit = chi2_limit(dof, count, prior_rows, rig.noise_model, dtype)
    pos_var = jnp.trace(R_b @ cov[:3, :3] @ R_b.T)
    rot_var = jnp.trace(cov[3:6, 3:6])
    size = formation_size(T_ref) * d
    observable = (cov_ok & (pos_var <= (MAX_RELATIVE_POSITION_BOUND * size) ** 2)
                  & (rot_var <= MAX_ROTATION_BOUND**2) & (dof > 0))  # fmt: skip
    converged = cov_ok & start_ok & out.converged
    solver = RESULTS.where(cov_ok | ~start_ok, RESULTS.successful, RESULTS.unobservable)
    solver = RESULTS.where(converged | ~start_ok | ~cov_ok, solver,
                           RESULTS.nonlinear_max_steps_reached)  # fmt: skip
    solver = RESULTS.where(jnp.any(roots.valid), solver, RESULTS.no_valid_solution)
    solver = RESULTS.where(roots.any_scaled | ~roots.any_p3p, solver,
                           RESULTS.scale_unobservable)  # fmt: skip
    solver = RESULTS.where(count == 3, solver, RESULTS.too_few_points)
    solver = RESULTS.where(mutual.result == RESULTS.successful, solver, mutual.result)
    solver = RESULTS.where(roots.nonfinite, RESULTS.nonfinite_observation, solver)
    result = RESULTS.where((solver == RESULTS.successful) & ~observable, RESULTS.unobservable,
                           solver)  # fmt: skip
    r, J = fit
    worst = worst_measurement(r, J, cov, 3, count + prior_rows, rig.noise_model)
    consistent = (chi2 <= limit) & (worst <= 1.0)
    result = RESULTS.where((result == RESULTS.successful) & ~consistent,
                           RESULTS.inconsistent_fit, result)  # fmt: skip
    result = RESULTS.where((result == RESULTS.successful) & roots.ambiguous, RESULTS.ambiguous,
                           result)  # fmt: skip
    nan = jnp.full((), jnp.nan, cost.dtype)  # blunder_nees: not computed by the tracker
    return FitCheck(solver, cost, chi2, dof, limit, observable, worst, nan), result


@jit
def _one_step_impl(snapshot: Snapshot, rig: Rig, prior: OneStepPrior):
    dtype = snapshot.overhead.dtype
    mount = rig.mounts[0].astype(dtype)
    mutual, T_ref, u, R_robots, up = _formation(snapshot)
    roots = _choose_root(snapshot, u, up, mount, prior)
    out, start_ok, cov, cov_ok, step, fit = _refine_root(snapshot, rig, prior, roots, u,
                                                         R_robots, up, mount)  # fmt: skip
    checks, result = _gate(rig, prior, mutual, roots, out, start_ok, cov, cov_ok, step, fit,
                           T_ref)  # fmt: skip
    R_b, p_b, d = out.x
    # Outputs as poses (one batched matrix -> quaternion conversion).
    quats = jax.vmap(lambda R: jaxlie.SO3.from_matrix(R).wxyz)(
        jnp.concatenate([R_b[None], roots.R_wb])
    ).astype(dtype)
    T_climber = jnp.concatenate([quats[0], p_b])
    T_roots = jnp.concatenate([quats[1:], roots.p_roots], axis=1)
    T_roots = jnp.where(roots.valid[:, None], T_roots, identity_params(dtype)[None])
    T_body = jnp.concatenate([T_ref[:, :4], d * u], axis=1)
    return OneStepEstimate(
        T_climber, overhead_of_body(T_climber, mount), T_body, d, result,
        jnp.where(cov_ok, cov, 0.0), T_roots, roots.valid, roots.cost,
        roots.chosen.astype(jnp.int32), checks, out.num_steps + 1,
    )  # fmt: skip


def localize_one_step(
    snapshot: Snapshot, rig: Rig, prior: OneStepPrior, *, throw: bool = True
) -> OneStepEstimate:
    r"""The climbing robot's pose from one formation seen once and a prior (see the module
    docstring).

    **Arguments:**

    - `snapshot`: a [`Snapshot`][] (e.g. `Snapshot.of(observations, 0)`, a cycle's first
      step).
    - `rig`: the team's [`jaxloc.Rig`][].
    - `prior`: a [`OneStepPrior`][] in the formation's frame (C1's body frame): a pose prior
      with the formation's perimeter, or the first cycle's height prior.
    - `throw`: raise if the result is not successful. Keyword only.

    **Returns:** a [`OneStepEstimate`][]. Pure, jitted; `vmap` applies.
    """
    if not isinstance(rig, Rig):
        raise ValueError(f"`rig` must be a jaxloc.Rig; got {type(rig).__name__}.")
    if not isinstance(prior, OneStepPrior):
        raise ValueError(f"`prior` must be a OneStepPrior; got {type(prior).__name__}.")
    shapes = {"mutual": (3, 3, 3), "overhead": (3, 3), "overhead_pixels": (3, 2),
              "overhead_visible": (3,)}  # fmt: skip
    for name, shape in shapes.items():
        got = getattr(snapshot, name).shape
        if got[len(got) - len(shape) :] != shape:
            raise ValueError(f"`Snapshot({name}=...)` must have shape {shape}; got {got}.")
    est = _one_step_impl(snapshot, rig, prior)
    return raise_if_failed(est, est.result, throw)


def snapshot_data(data: CycleData, step: int = 0) -> CycleData:
    """A cycle's whitened measurements with every step but `step` and the odometry left
    out (weights 0): the measurements of one formation, in the cycle's layout."""
    keep = (np.arange(data.mutual_weight.shape[-3]) == step).astype(np.float64)
    k = jnp.asarray(keep, data.mutual_weight.dtype)
    return eqx.tree_at(
        lambda t: (t.mutual_weight, t.overhead_weight, t.odometry_weight), data,
        (data.mutual_weight * k[:, None, None], data.overhead_weight * k[:, None],
         jnp.zeros_like(data.odometry_weight)),
    )  # fmt: skip


def one_step_bound(
    T_place: Float[Array, "P 7"],
    T_over: Float[Array, "7"],
    data: CycleData,
    rig: Rig,
    strategy: str,
    prior: OneStepPrior,
    step: int = 0,
) -> Float[Array, "18 18"]:
    """Bayesian Cramér–Rao bound of one-step localization at the true poses.

    **Arguments:** the cycle's true placements `T_place` `(P, 7)` and overhead camera
    `T_over` in the formation's frame (C1's body frame at step `step`, so placement 0 is
    the identity), its measurements at the truth `data` (as `crlb_inputs` gives them; only
    step `step` is used), the rig and strategy, and the `prior` (its information).

    **Returns:** the bound on the right perturbations of (C2's body, C3's body, the
    climbing robot's body), `(18, 18)`."""
    dtype = T_place.dtype
    mount = rig.mounts[0].astype(dtype)
    _, J = whitened_with_jacobian(T_place, T_over, snapshot_data(data, step), rig, strategy)
    # Columns: C2, C3 (placements of step `step`), the overhead camera -> the body.
    ids = placement_ids(strategy)[step]
    J = jnp.concatenate([J[:, int(ids[1])], J[:, int(ids[2])],
                         J[:, -1] @ adjoint(inverse(jaxlie.SE3(mount)).wxyz_xyz)], axis=1)
    T_b = body_of_overhead(T_over, mount)
    markers_body = rig.markers[1:].astype(dtype)
    poses = T_place[ids]
    up = jnp.sum(rotations(poses)[:, :, 2], axis=0)

    def priors(delta):
        d = delta.reshape(3, 6)
        P2 = rplus(jaxlie.SE3(poses[1]), d[0]).wxyz_xyz
        P3 = rplus(jaxlie.SE3(poses[2]), d[1]).wxyz_xyz
        B = rplus(jaxlie.SE3(T_b), d[2]).wxyz_xyz
        all3 = jnp.stack([poses[0], P2, P3])
        X = all3[:, 4:] + matvec(rotations(all3), markers_body)
        return prior_residuals(prior, rotations(B), B[4:], all3[:, 4:], X, safe_normalize(up),
                               mount)  # fmt: skip

    J_p = jax.jacfwd(priors)(jnp.zeros(18, dtype))
    info = gram(jnp.concatenate([J, J_p]))
    cov, _ = spd_inverse(info)
    return cov


def one_step_prior_from(
    end_poses: Float[Array, "4 7"],
    end_covariance: Float[Array, "24 24"],
    climber: Float[Array, "7"],
    climber_sigma: Float[Array, "6"],
) -> OneStepPrior:
    """The next cycle's one-step prior from an estimate of a cycle's end (body poses of C,
    C1, C2, C3 in any common frame and their joint covariance, e.g. the smoother's) and the
    climbing robot's odometry into the next cycle: its pose in the next cycle's frame (C1's
    end pose), `T = C1^-1 C Z`, with the first-order covariance of the three, and the end
    formation's perimeter with its sigma. (The two priors are treated as independent.)"""
    dtype = end_poses.dtype

    def pose(delta):
        d = delta.reshape(-1, 6)
        C = rplus(jaxlie.SE3(end_poses[0]), d[0])
        C1 = rplus(jaxlie.SE3(end_poses[1]), d[1])
        Z = rplus(jaxlie.SE3(climber), d[4])
        return compose(compose(inverse(C1), C), Z).wxyz_xyz

    zero = jnp.zeros(30, dtype)
    mean = pose(zero)

    def local(delta):
        return jaxlie.manifold.rminus(jaxlie.SE3(mean), jaxlie.SE3(pose(delta))).astype(dtype)

    G = jax.jacfwd(local)(zero)  # (6, 30)
    cov = jnp.zeros((30, 30), dtype).at[:24, :24].set(end_covariance)
    cov = cov.at[24:, 24:].set(jnp.diag(climber_sigma**2))
    pose_cov = G @ cov @ G.T

    def end_perimeter(delta):
        d = delta.reshape(3, 6)
        p = jnp.stack([rplus(jaxlie.SE3(end_poses[i + 1]), d[i]).wxyz_xyz[4:] for i in range(3)])
        return perimeter(p)

    g = jax.grad(end_perimeter)(jnp.zeros(18, dtype))
    var = g @ end_covariance[6:, 6:] @ g
    sigma = jnp.sqrt(jnp.maximum(var, 1e-12))
    return OneStepPrior.pose_prior(mean, pose_cov).with_scale(end_perimeter(jnp.zeros(18, dtype)),
                                                             sigma)  # fmt: skip
