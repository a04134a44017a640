r"""Maximum-likelihood refinement of one camera pose from known world points (DESIGN §5).

[`jaxloc.refine_overhead_pose`][] minimises the (optionally robust) reprojection error in
the image over the SE(3) tangent around the current pose (`T = T0 exp(delta)`,
`delta = (v, omega)`, jaxlie's right perturbation `jaxlie.manifold.rplus`). Default
solver: jaxloc's least-squares kernel (`jaxloc._core.least_squares`) with the chain-rule
Jacobian of the residuals (camera projection Jacobian times `dq/d delta = R [I, -[X]x]`),
the 6x6 normal equations as element-wise sums and Gauss--Jordan elimination: no LAPACK, no
batched `dot` (DESIGN §8). Gradients through it by the implicit function theorem; the
optimistix solvers (`"optx-lm"`, `"optx-gn"`) use optimistix's implicit adjoint.
"""

import functools as ft

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Scalar

from .._cameras.models import AbstractCamera
from .._core.compiler import jit
from .._core.least_squares import (
    implicit_step,
    levenberg_marquardt,
    normal_equations,
    optx_solver,
)
from .._core.linalg import gram, small_spd_inverse
from .._core.numerics import safe_sqrt
from .._core.poses import apply, inverse, rplus, rplus_params
from .._core.results import raise_if_failed, RESULTS
from .._cycle.sightings import matmul, skew
from .._solvers.pose_problem import identity_like, no_alternatives, PoseSolution, where_pose


LOSSES = (None, "huber", "cauchy")
POSE_SOLVERS = ("lm", "gn", "optx-lm", "optx-gn")
"""Solvers of [`jaxloc.refine_overhead_pose`][]: jaxloc's batched Levenberg--Marquardt /
Gauss--Newton with the chain-rule Jacobian, or optimistix's on the same residuals."""
#: Default `loss_scale` of each robust loss, in units of `sigma` (95% asymptotic
#: efficiency under Gaussian noise).
DEFAULT_LOSS_SCALE = {"huber": 1.345, "cauchy": 2.3849}


def _robust_factor(s: Float[Array, " n"], loss: str | None, c) -> Float[Array, " n"]:
    r"""`sqrt(rho(s) / s)` for squared whitened residual norms `s`.

    Scaling a residual `e` (with `s = |e|^2`) by this factor makes its squared norm
    `rho(s)`, so the least-squares solver minimises $\sum_i \rho(s_i)$ exactly (rather than
    an IRLS approximation) and the implicit adjoint differentiates the robust optimum.
    Huber: $\rho(s) = s$ for $s \le c^2$, else $2c\sqrt{s} - c^2$.
    Cauchy: $\rho(s) = c^2 \log(1 + s/c^2)$. Both have `rho(s)/s -> 1` as `s -> 0`.
    """
    if loss is None:
        return jnp.ones_like(s)
    c2 = c * c
    if loss == "huber":
        big = s > c2
        safe_s = jnp.where(big, s, 2.0 * c2)
        ratio = 2.0 * c / jnp.sqrt(safe_s) - c2 / safe_s
        return jnp.where(big, jnp.sqrt(ratio), 1.0)
    if loss == "cauchy":
        x = s / c2
        small = x < 1e-6
        safe_x = jnp.where(small, 1.0, x)
        ratio = jnp.where(small, 1.0 - 0.5 * x, jnp.log1p(safe_x) / safe_x)
        return jnp.sqrt(ratio)
    raise ValueError(f'`loss` must be None, "huber" or "cauchy"; got {loss!r}.')


def _point_residuals(T_cam_world: jaxlie.SE3, camera, X, uv, weight):
    """Whitened reprojection residuals `weight_i * (project(T X_i) - uv_i)`, `(n, 2)`."""
    pred = camera.project(jax.vmap(ft.partial(apply, T_cam_world))(X))
    return weight[:, None] * (pred - uv)


def _pose_residuals(delta, args, *, loss):
    T0, camera, X, uv, weight, c = args
    T = rplus(T0, delta)
    e = _point_residuals(T, camera, X, uv, weight)
    f = _robust_factor(jnp.sum(e * e, axis=-1), loss, c)
    return (f[:, None] * e).reshape(-1)


def _camera_points(T_cam_world: jaxlie.SE3, X: Float[Array, "n 3"]):
    """`(R, q)`: the rotation matrix and `q_i = R X_i + t`, written element-wise (a batched
    `dot` of 3x3 matrices would be one tiny library call per problem under `vmap`)."""
    R = T_cam_world.rotation().as_matrix()
    q = jnp.sum(X[:, None, :] * R[None, :, :], axis=-1) + T_cam_world.translation()[None]
    return R, q


def _residuals_and_jacobian(T_cam_world: jaxlie.SE3, camera, X, uv, weight, c, loss):
    r"""Robust whitened residuals `r` `(n, 2)` and their Jacobian `(n, 2, 6)` w.r.t. the
    right perturbation `T exp(delta)`, `delta = (v, omega)`, at `delta = 0`.

    Chain rule: $q = R(\exp(\delta) X) + t \approx R(X + v + \omega \times X) + t$, so
    $\partial q / \partial v = R$ and $\partial q / \partial \omega_k = R (e_k \times X)$;
    the camera's own `(2, 3)` projection Jacobian by forward mode (three tangents, one
    point at a time: element-wise under `vmap`). The robust scaling `r = f(s) e`,
    `s = |e|^2`, is differentiated exactly: `dr = (f I + 2 f'(s) e e^T) de`, so the
    solver minimises $\sum \rho$ with its true gradient.
    """
    R, q = _camera_points(T_cam_world, X)
    pred, Jp = camera.project_with_jacobian(q)  # (n, 2), (n, 2, 3)
    e = weight[:, None] * (pred - uv)
    A = weight[:, None, None] * jnp.sum(Jp[:, :, :, None] * R[None, None, :, :], axis=2)
    Jw = -matmul(A, skew(X))
    Je = jnp.concatenate([A, Jw], axis=-1)  # (n, 2, 6)
    if loss is None:
        return e, Je
    s = jnp.sum(e * e, axis=-1)
    f, df = jax.jvp(lambda s: _robust_factor(s, loss, c), (s,), (jnp.ones_like(s),))
    eJ = jnp.sum(e[:, :, None] * Je, axis=1)  # e^T Je, (n, 6)
    J = f[:, None, None] * Je + (2.0 * df)[:, None, None] * e[:, :, None] * eJ[:, None, :]
    return f[:, None] * e, J


def _pose_model(params, camera, X, uv, weight, c, loss):
    r, J = _residuals_and_jacobian(jaxlie.SE3(params), camera, X, uv, weight, c, loss)
    return normal_equations(r.reshape(-1), J.reshape(-1, 6))


def _implicit_residuals(params, delta, args, static):
    loss, camera_static = static
    camera_dyn, X, uv, weight, c = args
    camera = eqx.combine(camera_dyn, camera_static)
    T_cam_world = rplus(jaxlie.SE3(params), delta)
    e = _point_residuals(T_cam_world, camera, X, uv, weight)
    f = _robust_factor(jnp.sum(e * e, axis=-1), loss, c)
    return (f[:, None] * e).reshape(-1)


def _clean_inputs(T0, X, uv, mask, sigma):
    """Replace what the solve must not use by harmless values.

    Returns `(T0, X, uv, weight, use, nonfinite)`: the start `T_cam_world` (identity if
    not finite), the world points `X` `(n, 3)` (m; unused ones moved 1 m in front of the
    start camera, where `project` is smooth, with zero weight), the pixels `uv` `(n, 2)`
    (unused ones 0), the residual weights `1 / sigma` (1/px, 0 for unused points), the
    used points `(n,)` and whether an unmasked input (or the start) holds NaN/inf.
    """
    dtype = X.dtype
    finite = jnp.all(jnp.isfinite(X), axis=1) & jnp.all(jnp.isfinite(uv), axis=1)
    start_ok = jnp.all(jnp.isfinite(T0.wxyz_xyz))
    nonfinite = jnp.any(mask & ~finite) | ~start_ok
    use = mask & finite
    X = jnp.where(use[:, None], X, 0.0)
    uv = jnp.where(use[:, None], uv, 0.0)
    sigma = jnp.asarray(sigma, dtype)
    weight = jnp.where(use, 1.0 / sigma, 0.0).astype(dtype)
    T0 = where_pose(start_ok, T0, identity_like(dtype))
    T0 = jaxlie.SE3(T0.wxyz_xyz.astype(dtype))
    ahead = apply(inverse(T0), jnp.array([0.0, 0.0, 1.0], dtype))
    X = jnp.where(use[:, None], X, ahead)
    return T0, X, uv, weight, use, nonfinite


def _solve_own(T0, camera, X, uv, weight, c, active, *, solver, loss, max_steps, rtol, atol):
    """jaxloc's LM (`solver="lm"`) or Gauss--Newton (`"gn"`) from `T0` (`T_cam_world`),
    then one implicit step that carries the derivatives (the loop is not differentiated).
    Returns `(pose, num_steps, result)`."""
    T0s, cam_s, Xs, uvs, ws, cs = jax.tree.map(
        jax.lax.stop_gradient, (T0, camera, X, uv, weight, c)
    )
    out = levenberg_marquardt(
        lambda x: _pose_model(x, cam_s, Xs, uvs, ws, cs, loss),
        rplus_params,
        lambda x: jnp.max(jnp.abs(x[4:])),
        T0s.wxyz_xyz,
        num_unknowns=6,
        max_steps=max_steps,
        rtol=rtol,
        atol=atol,
        active=active,
        damped=solver == "lm",
        lam0=1e-3 if solver == "lm" else 0.0,
        final_gauss_newton=True,
    )
    camera_dyn, camera_static = eqx.partition(camera, eqx.is_inexact_array)
    step = implicit_step(
        _implicit_residuals, 6, (loss, camera_static), out.x,
        (camera_dyn, X, uv, weight, c),
    )  # fmt: skip
    pose = rplus(jaxlie.SE3(out.x), step)
    result = RESULTS.where(out.converged, RESULTS.successful, RESULTS.nonlinear_max_steps_reached)
    return pose, out.num_steps, result


def _solve_optx(T0, camera, X, uv, weight, c, *, solver, loss, max_steps, rtol, atol):
    """optimistix's LM (`solver="optx-lm"`) or Gauss--Newton (`"optx-gn"`) over the
    tangent at `T0` (`T_cam_world`). Returns `(pose, num_steps, result)`."""
    sol = optx.least_squares(
        ft.partial(_pose_residuals, loss=loss),
        optx_solver(solver.removeprefix("optx-"), rtol, atol),
        jnp.zeros(6, X.dtype),
        args=(T0, camera, X, uv, weight, c),
        max_steps=max_steps,
        throw=False,
    )
    return rplus(T0, sol.value), sol.stats["num_steps"], RESULTS.promote(sol.result)


def _covariance(pose, camera, X, uv, weight, c):
    """First-order covariance `(6, 6)` of the tangent `(v, omega)` at `pose` (Gaussian
    model, no robust weights): `(J^T J)^-1`, J the chain-rule Jacobian of the
    sigma-whitened residuals; and whether `J^T J` was invertible."""
    _, J = _residuals_and_jacobian(pose, camera, X, uv, weight, c, None)
    return small_spd_inverse(gram(J.reshape(-1, 6)))


def _status(result, cov_ok, pose, camera, X, use, count, nonfinite):
    """The solver's `result`, overridden by the first failure in the order of
    [`jaxloc.refine_overhead_pose`][]'s docstring (read last to first here)."""
    result = RESULTS.where(cov_ok, result, RESULTS.degenerate_configuration)
    in_front = jnp.all(camera.projectable(_camera_points(pose, X)[1]) | ~use)
    result = RESULTS.where(
        jnp.all(jnp.isfinite(pose.wxyz_xyz)) & in_front, result, RESULTS.no_valid_solution
    )
    result = RESULTS.where(count < 3, RESULTS.too_few_points, result)
    return RESULTS.where(nonfinite, RESULTS.nonfinite_observation, result)


@jit
def _refine_pose_impl(
    T0, camera, X, uv, mask, sigma, loss_scale, *, solver, loss, max_steps, rtol, atol
):
    dtype = X.dtype
    T0, X, uv, weight, use, nonfinite = _clean_inputs(T0, X, uv, mask, sigma)
    count = jnp.sum(use)
    c = jnp.asarray(loss_scale, dtype)
    options = dict(solver=solver, loss=loss, max_steps=max_steps, rtol=rtol, atol=atol)
    if solver in ("lm", "gn"):
        active = (count >= 3) & ~nonfinite
        pose, num_steps, result = _solve_own(T0, camera, X, uv, weight, c, active, **options)
    else:
        pose, num_steps, result = _solve_optx(T0, camera, X, uv, weight, c, **options)
    cov, cov_ok = _covariance(pose, camera, X, uv, weight, c)
    e = _point_residuals(pose, camera, X, uv, use.astype(dtype))
    sq = jnp.sum(e * e) / jnp.maximum(count, 1).astype(dtype)
    result = _status(result, cov_ok, pose, camera, X, use, count, nonfinite)
    success = result == RESULTS.successful
    pose = where_pose(success, pose, identity_like(dtype))
    stats = {
        "num_steps": num_steps,
        "rms_pixel_error": safe_sqrt(sq),
        "covariance": jnp.where(success, cov, 0.0),
    }
    return PoseSolution(pose, result, stats, *no_alternatives(dtype, 0))


def refine_overhead_pose(
    T0_cam_world: jaxlie.SE3,
    camera: AbstractCamera,
    points_world: Float[ArrayLike, "n 3"],
    pixels: Float[ArrayLike, "n 2"],
    mask: Bool[ArrayLike, " n"] | None = None,
    *,
    sigma: float | Scalar = 1.0,
    solver: str = "lm",
    loss: str | None = None,
    loss_scale: float | Scalar | None = None,
    max_steps: int = 32,
    rtol: float = 1e-6,
    atol: float = 1e-6,
    throw: bool = True,
) -> PoseSolution:
    r"""Refine a camera pose by minimising its reprojection error in the image.

    Solves
    $\min_\delta \sum_i \rho\big(\|\pi(T_0 \exp(\delta)\, X_i) - u_i\|^2 / \sigma^2\big)$
    over the SE(3) tangent `delta = (v, omega)` (jaxlie's right perturbation,
    `jaxlie.manifold.rplus`), where $\pi$ is `camera.project`. A robust
    $\rho$ is applied per point by scaling its whitened 2-vector residual by
    $\sqrt{\rho(s)/s}$, which minimises $\sum \rho$ exactly.

    **Arguments:**

    - `T0_cam_world`: initial pose, a `jaxlie.SE3` mapping world points into the camera
        frame (`p_cam = T @ p_world`), e.g. from [`jaxloc.solve_overhead_pose`][].
    - `camera`: any [`jaxloc.AbstractCamera`][] (pixels in its image; OpenCV convention).
    - `points_world`: world points (m), shape `(n, 3)`.
    - `pixels`: their observed pixels `(u, v)`, shape `(n, 2)`.
    - `mask`: optional boolean `(n,)`; `False` marks points to ignore (their values, even
        NaN, are not used).
    - `sigma`: standard deviation of the pixel noise per image axis (px). It sets the
        covariance's scale and the robust loss's scale, not the optimum of the plain
        least-squares cost. For the paper's noise model (radius ~ N(0, s), uniform
        direction) it is `s / sqrt(2)`. Keyword only (as are all below).
    - `solver`: `"lm"` (default): jaxloc's Levenberg--Marquardt, re-linearized at the
        current pose with the chain-rule Jacobian, element-wise 6x6 normal equations
        and Gauss--Jordan elimination (the fast path under `vmap`; see also
        `jaxloc._overhead.map_problems`); converged when a step is below `atol + rtol *
        |t|_inf`, then one last Gauss--Newton step polishes to rounding. `"gn"`: the same
        loop undamped (Gauss--Newton). `"optx-lm"` / `"optx-gn"`: `optx.LevenbergMarquardt` /
        `optx.GaussNewton` on the same residuals. All reach the same minimum.
    - `loss`: `None` (least squares), `"huber"` or `"cauchy"`.
    - `loss_scale`: the robust loss's threshold `c` in units of `sigma`; default 1.345 for
        Huber and 2.3849 for Cauchy.
    - `max_steps`: iteration limit of the solver (static).
    - `rtol`, `atol`: the solver's termination tolerances (on the tangent step, rad / m,
        and on the whitened residuals).
    - `throw`: if `True`, raise (also under `jit`) when `result` is not successful;
        otherwise inspect `result`.

    **Returns:** a [`jaxloc.PoseSolution`][] whose `pose` is the refined `T_cam_world`
    (identity on failure, never NaN) and whose `result` is the solver's promoted result,
    or `too_few_points` (fewer than 3 unmasked points), `nonfinite_observation` (NaN/inf
    in an unmasked point or pixel, or in `T0_cam_world`), `degenerate_configuration` (the
    information matrix is singular, e.g. collinear points), `no_valid_solution` (the
    solution puts an unmasked point where the camera cannot project it, e.g. behind it). `stats`:

    - `"num_steps"`: solver iterations (model evaluations with a Jacobian).
    - `"rms_pixel_error"`: RMS over unmasked points of the reprojection error norm (px).
    - `"covariance"`: first-order covariance of the tangent `(v, omega)` of the refined
        pose (`T_true ~ T_hat exp(delta)`), $(J^\top J / \sigma^2)^{-1}$ with J the
        Jacobian of the pixel residuals, shape `(6, 6)`; m^2, m rad, rad^2 blocks (zero
        on failure). The translation part `v` is in the camera frame's tangent, not the
        camera centre: propagate with `jax.jacfwd` for the centre.

    Single problem; batch with `jax.vmap`. Works under `jit`, `vmap` and `grad` (implicit
    derivatives of the optimum w.r.t. the points, pixels, camera and `sigma`; none w.r.t.
    the start).
    """
    points_world = jnp.asarray(points_world)
    pixels = jnp.asarray(pixels)
    if points_world.ndim != 2 or points_world.shape[-1] != 3:
        raise ValueError(
            f"`points_world` must have shape (n, 3); got shape {points_world.shape}."
        )
    n = points_world.shape[0]
    if pixels.shape != (n, 2):
        raise ValueError(f"`pixels` must have shape ({n}, 2); got shape {pixels.shape}.")
    if mask is None:
        mask = jnp.ones((n,), dtype=bool)
    mask = jnp.asarray(mask)
    if mask.shape != (n,):
        raise ValueError(f"`mask` must have shape ({n},); got shape {mask.shape}.")
    if solver not in POSE_SOLVERS:
        raise ValueError(
            f'`solver` must be "lm", "gn", "optx-lm" or "optx-gn"; got {solver!r}.'
        )
    if loss not in LOSSES:
        raise ValueError(f'`loss` must be None, "huber" or "cauchy"; got {loss!r}.')
    if not isinstance(max_steps, int) or max_steps < 1:
        raise ValueError(f"`max_steps` must be a positive int; got {max_steps!r}.")
    dtype = jnp.result_type(points_world.dtype, pixels.dtype)
    if loss_scale is None:
        loss_scale = DEFAULT_LOSS_SCALE.get(loss, 1.0)
    sol = _refine_pose_impl(
        T0_cam_world,
        camera,
        points_world.astype(dtype),
        pixels.astype(dtype),
        mask.astype(bool),
        jnp.asarray(sigma, dtype),
        jnp.asarray(loss_scale, dtype),
        solver=solver,
        loss=loss,
        max_steps=max_steps,
        rtol=rtol,
        atol=atol,
    )
    return raise_if_failed(sol, sol.result, throw)
