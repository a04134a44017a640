r"""Maximum-likelihood refinement with optimistix (DESIGN §5).

- [`jaxloc.refine_overhead_pose`][]: one camera pose `T_cam_world` from known world points
  and their pixels, minimising the (optionally robust) reprojection error in the image.
- [`jaxloc.refine_cycle`][]: every distinct robot placement of a cycle and the overhead
  camera jointly, from every mutual pixel, every overhead pixel and every odometry
  distance, each residual whitened by its standard deviation.

Both parametrize poses in the SE(3) tangent space around their starting value
(`T = T0 exp(delta)`, `delta = (v, omega)`, jaxlie's right perturbation
`jaxlie.manifold.rplus`) and call `optx.least_squares` with Levenberg--Marquardt or
Gauss--Newton. The solvers' linear steps go through the normal equations with a
`fori_loop` Cholesky (no LAPACK in the loop, DESIGN §8). Gradients through a refinement
use optimistix's implicit adjoint (the solve is never unrolled).
"""

import functools as ft

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import jaxlie
import lineax as lx
import optimistix as optx
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, ArrayLike, Bool, Float, Scalar

from ._camera import AbstractCamera
from ._cycle_model import (
    _first_occurrence,
    _predict,
    _unpack,
    cycle_data,
    flat_jacobian,
    placement_ids,
    whitened,
    whitened_with_jacobian,
)
from ._misc import safe_sqrt
from ._observations import CycleObservations, CyclePoses
from ._overhead import _cholesky_solve6
from ._results import raise_if_failed, RESULTS
from ._scenario import Scenario
from ._solvers.dlt import identity_like, PoseSolution, where_pose
from ._strategies import CycleEstimate


SOLVERS = ("lm", "gn")
#: Solvers of [`jaxloc.refine_cycle`][]: jaxloc's batched Levenberg--Marquardt, or
#: optimistix's Levenberg--Marquardt / Gauss--Newton on the same residuals.
CYCLE_SOLVERS = ("lm", "optx-lm", "optx-gn")
LOSSES = (None, "huber", "cauchy")
#: Default `loss_scale` of each robust loss, in units of `sigma` (95% asymptotic
#: efficiency under Gaussian noise).
DEFAULT_LOSS_SCALE = {"huber": 1.345, "cauchy": 2.3849}


def _cholesky(A: Float[Array, "n n"]) -> Float[Array, "n n"]:
    """Lower Cholesky factor, column by column in a `fori_loop`: no LAPACK call (DESIGN §8
    reports LAPACK calls hanging when two threads run them, and per-call overhead
    dominates for small matrices). NaN if `A` is not positive definite."""
    n = A.shape[0]
    rows = jnp.arange(n)

    def body(j, L):
        v = A[:, j] - L @ L[j, :]  # columns >= j of L are still zero
        d = jnp.sqrt(v[j])
        return L.at[:, j].set(jnp.where(rows >= j, v / d, 0.0))

    return jax.lax.fori_loop(0, n, body, jnp.zeros_like(A))


def _cholesky_solve(L: Float[Array, "n n"], b: Float[Array, " n"]) -> Float[Array, " n"]:
    """Solve `L L^T x = b` by forward and back substitution (no LAPACK)."""
    n = L.shape[0]

    def fwd(i, y):
        return y.at[i].set((b[i] - L[i] @ y) / L[i, i])  # entries >= i of y still zero

    y = jax.lax.fori_loop(0, n, fwd, jnp.zeros_like(b))

    def bwd(k, x):
        i = n - 1 - k
        return x.at[i].set((y[i] - L[:, i] @ x) / L[i, i])  # entries <= i of x still zero

    return jax.lax.fori_loop(0, n, bwd, jnp.zeros_like(b))


class _NormalCholesky(lx.AbstractLinearSolver):
    """Least-squares solve `min |A x - b|` through the normal equations `A^T A x = A^T b`
    with a `fori_loop` Cholesky: no LAPACK in the refinement loop (lineax's default QR
    calls LAPACK once per problem under `vmap`). For the small, well-scaled systems of a
    pose refinement (6 or ~40 unknowns; Levenberg--Marquardt passes the damped augmented
    Jacobian) squaring the condition number costs nothing in float64."""

    def init(self, operator, options):
        del options
        A = operator.as_matrix()
        return A, _cholesky(A.T @ A)

    def compute(self, state, vector, options):
        del options
        A, L = state
        flat, unflatten = jax.flatten_util.ravel_pytree(vector)
        x = _cholesky_solve(L, A.T @ flat)
        ok = jnp.all(jnp.isfinite(x))
        x = jnp.where(ok, x, 0.0)
        result = lx.RESULTS.where(ok, lx.RESULTS.successful, lx.RESULTS.singular)
        _, unflatten_in = jax.flatten_util.ravel_pytree(
            jnp.zeros(A.shape[1], A.dtype)
        )
        del unflatten
        return unflatten_in(x), result, {}

    def transpose(self, state, options):
        raise NotImplementedError("`_NormalCholesky` is only used inside the solver loop.")

    def conj(self, state, options):
        return state, options

    def assume_full_rank(self):
        return True


def _make_solver(solver: str, rtol: float, atol: float):
    if solver == "lm":
        return optx.LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=_NormalCholesky())
    if solver == "gn":
        return optx.GaussNewton(rtol=rtol, atol=atol, linear_solver=_NormalCholesky())
    raise ValueError(f'`solver` must be "lm" or "gn"; got {solver!r}.')


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


def _jvp_nonzero(f, primals, tangents):
    """`jax.jvp(f, primals, tangents)[1]` over the pytree `primals`, differentiating only
    the leaves whose tangent is not a `SymbolicZero`; `None` if every tangent is zero."""
    leaves, tree = jax.tree.flatten(primals)
    dots = tree.flatten_up_to(tangents)
    live = [i for i, t in enumerate(dots) if not isinstance(t, SymbolicZero)]
    if not live:
        return None

    def of_live(*values):
        full = list(leaves)
        for i, v in zip(live, values):
            full[i] = v
        return f(tree.unflatten(full))

    return jax.jvp(of_live, [leaves[i] for i in live], [dots[i] for i in live])[1]


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
    starting at 1e-2, divided by 10 after an accepted step, multiplied by 10 after a
    rejected one. Converged when a step (accepted, or rejected at negligible damping:
    the minimum within rounding) is below `atol + rtol * max |position|` (m, rad).

    An inactive problem (`active` False: a failed start) takes no step, so under `vmap`
    it does not prolong its batch's loop. Returns `(T_place, T_over, num_steps,
    converged)`.
    """
    dtype = T0_place.dtype

    def model(T_place, T_over):
        r, J = whitened_with_jacobian(T_place, T_over, data, scenario, strategy)
        return r, flat_jacobian(J)

    r0, J0 = model(T0_place, T0_over)
    init = (
        jnp.array(0, jnp.int32), T0_place, T0_over, r0, J0,
        jnp.array(1e-2, dtype), ~active, jnp.array(False),
    )

    def cond(state):
        k, *_, done, _ = state
        return (k < max_steps) & ~done

    def body(state):
        k, T_place, T_over, r, J, lam, _, _ = state
        H = J.T @ J
        g = J.T @ r
        L = _cholesky(H + lam * jnp.eye(H.shape[0], dtype=dtype))
        delta = -_cholesky_solve(L, g)
        finite = jnp.all(jnp.isfinite(delta))
        delta = jnp.where(finite, delta, 0.0)
        T_place_new, T_over_new = _unpack(delta, T_place, T_over)
        r_new, J_new = model(T_place_new, T_over_new)
        cost, cost_new = jnp.sum(r * r), jnp.sum(r_new * r_new)
        accept = finite & jnp.isfinite(cost_new) & (cost_new <= cost)
        small = jnp.max(jnp.abs(delta)) <= atol + rtol * jnp.max(jnp.abs(T_place[:, 4:]))
        # A rejected step that is already negligible: the minimum within rounding.
        done = (accept | (lam < 1e-3)) & finite & small
        pick = lambda a, b: jnp.where(accept, a, b)  # noqa: E731
        lam = jnp.where(accept, jnp.maximum(lam / 10.0, 1e-9), jnp.minimum(lam * 10.0, 1e12))
        return (
            k + 1, pick(T_place_new, T_place), pick(T_over_new, T_over), pick(r_new, r),
            pick(J_new, J), lam, done, done,
        )

    k, T_place, T_over, *_, converged = jax.lax.while_loop(cond, body, init)
    return T_place, T_over, k, converged


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


@eqx.filter_jit
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
    if solver == "lm":
        # The loop is not differentiated: `_implicit_step` carries the derivatives.
        T0_place, T0_over, lm_data, lm_scenario = jax.tree.map(
            jax.lax.stop_gradient, (T0_place, T0_over, data, scenario)
        )
        T_place, T_over, num_steps, converged = _batched_lm(
            T0_place, T0_over, lm_data, lm_scenario, strategy, max_steps, rtol, atol,
            finite0 & (estimate.result == RESULTS.successful),
        )
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
    stats = dict(estimate.stats)
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
    `"num_steps"`, `"rms_pixel_error"` (px, over all measured pixels), `"chi2"` (the
    final sum of squared whitened residuals) and `"dof"` (residuals minus unknowns), and
    updates `"odometry_rms"` (m). Under the noise model `chi2 ~ chi-square(dof)`: a value
    above its 99.9% quantile flags a wrong local minimum (a bad closed-form start; ~2% of
    the concurrent strategy's paper-scenario cycles).

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
