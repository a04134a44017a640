r"""Maximum-likelihood refinement of one camera pose from known world points (DESIGN §5).

[`jaxloc.refine_overhead_pose`][] minimises the (optionally robust) reprojection error in
the image over the SE(3) tangent around the starting pose (`T = T0 exp(delta)`,
`delta = (v, omega)`, jaxlie's right perturbation `jaxlie.manifold.rplus`) with
`optx.least_squares`. Gradients through it use optimistix's implicit adjoint.
"""

import functools as ft

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import optimistix as optx
from jaxtyping import Array, ArrayLike, Bool, Float, Scalar

from ._camera import AbstractCamera
from ._misc import safe_sqrt
from ._normal_equations import _make_solver, SOLVERS
from ._overhead import _cholesky_solve6
from ._results import raise_if_failed, RESULTS
from ._solvers.dlt import identity_like, PoseSolution, where_pose


LOSSES = (None, "huber", "cauchy")
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
    pred = camera.project(jax.vmap(T_cam_world.apply)(X))
    return weight[:, None] * (pred - uv)


def _pose_residuals(delta, args, *, loss):
    T0, camera, X, uv, weight, c = args
    T = jaxlie.manifold.rplus(T0, delta)
    e = _point_residuals(T, camera, X, uv, weight)
    f = _robust_factor(jnp.sum(e * e, axis=-1), loss, c)
    return (f[:, None] * e).reshape(-1)


def _inverse6(H: Float[Array, "6 6"]):
    """Inverse of an SPD 6x6 matrix by an unrolled Cholesky (no LAPACK); `(inv, ok)`."""
    eye = jnp.eye(6, dtype=H.dtype)
    cols, oks = jax.vmap(lambda e: _cholesky_solve6(H, e))(eye)
    inv = cols.T
    inv = 0.5 * (inv + inv.T)
    ok = jnp.all(oks) & jnp.all(jnp.isfinite(inv))
    return jnp.where(ok, inv, 0.0), ok


@eqx.filter_jit
def _refine_pose_impl(
    T0, camera, X, uv, mask, sigma, loss_scale, *, solver, loss, max_steps, rtol, atol
):
    dtype = X.dtype
    finite = jnp.all(jnp.isfinite(X), axis=1) & jnp.all(jnp.isfinite(uv), axis=1)
    nonfinite = jnp.any(mask & ~finite) | ~jnp.all(jnp.isfinite(T0.wxyz_xyz))
    use = mask & finite
    count = jnp.sum(use)
    X = jnp.where(use[:, None], X, 0.0)
    uv = jnp.where(use[:, None], uv, 0.0)
    sigma = jnp.asarray(sigma, dtype)
    weight = jnp.where(use, 1.0 / sigma, 0.0).astype(dtype)
    T0 = where_pose(jnp.all(jnp.isfinite(T0.wxyz_xyz)), T0, identity_like(dtype))
    # Masked points sit at the world origin with zero weight: they contribute nothing.
    # Keep them in front of the camera anyway so that `project` stays smooth there.
    ahead = T0.inverse() @ jnp.array([0.0, 0.0, 1.0], dtype)
    X = jnp.where(use[:, None], X, ahead)
    c = jnp.asarray(loss_scale, dtype)
    fn = ft.partial(_pose_residuals, loss=loss)
    sol = optx.least_squares(
        fn,
        _make_solver(solver, rtol, atol),
        jnp.zeros(6, dtype),
        args=(T0, camera, X, uv, weight, c),
        max_steps=max_steps,
        throw=False,
    )
    pose = jaxlie.manifold.rplus(T0, sol.value)
    pose = jaxlie.SE3(pose.wxyz_xyz.astype(dtype))
    # First-order covariance at the solution (Gaussian model, no robust weights):
    # cov(delta) = (J^T J)^-1 with J the Jacobian of the sigma-whitened residuals, delta the
    # tangent of T_cam_world around the refined pose.
    plain = ft.partial(_pose_residuals, loss=None)
    J = jax.jacfwd(plain)(jnp.zeros(6, dtype), (pose, camera, X, uv, weight, c))
    cov, cov_ok = _inverse6(J.T @ J)
    e = _point_residuals(pose, camera, X, uv, use.astype(dtype))
    sq = jnp.sum(e * e) / jnp.maximum(count, 1).astype(dtype)
    result = RESULTS.promote(sol.result)
    result = RESULTS.where(cov_ok, result, RESULTS.degenerate_configuration)
    in_front = jnp.all(camera.projectable(jax.vmap(pose.apply)(X)) | ~use)
    result = RESULTS.where(
        jnp.all(jnp.isfinite(pose.wxyz_xyz)) & in_front, result, RESULTS.no_valid_solution
    )
    result = RESULTS.where(count < 3, RESULTS.too_few_points, result)
    result = RESULTS.where(nonfinite, RESULTS.nonfinite_observation, result)
    success = result == RESULTS.successful
    pose = where_pose(success, pose, identity_like(dtype))
    stats = {
        "num_steps": sol.stats["num_steps"],
        "rms_pixel_error": safe_sqrt(sq),
        "covariance": jnp.where(success, cov, 0.0),
    }
    return PoseSolution(pose=pose, result=result, stats=stats)


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
    with `optx.least_squares` over the SE(3) tangent `delta = (v, omega)` (jaxlie's right
    perturbation, `jaxlie.manifold.rplus`), where $\pi$ is `camera.project`. A robust
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
    - `solver`: `"lm"` (`optx.LevenbergMarquardt`, default) or `"gn"` (`optx.GaussNewton`).
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

    - `"num_steps"`: solver iterations.
    - `"rms_pixel_error"`: RMS over unmasked points of the reprojection error norm (px).
    - `"covariance"`: first-order covariance of the tangent `(v, omega)` of the refined
        pose (`T_true ~ T_hat exp(delta)`), $(J^\top J / \sigma^2)^{-1}$ with J the
        Jacobian of the pixel residuals, shape `(6, 6)`; m^2, m rad, rad^2 blocks (zero
        on failure). The translation part `v` is in the camera frame's tangent, not the
        camera centre: propagate with `jax.jacfwd` for the centre.

    Single problem; batch with `jax.vmap`. Works under `jit`, `vmap` and `grad` (implicit
    adjoint through the optimum).
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
    if solver not in SOLVERS:
        raise ValueError(f'`solver` must be "lm" or "gn"; got {solver!r}.')
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
