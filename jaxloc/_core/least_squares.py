"""Small dense least-squares linear algebra without LAPACK (DESIGN §8).

A column-by-column Cholesky and its triangular solves in `fori_loop`s, and the lineax
solver that takes optimistix's Gauss--Newton / Levenberg--Marquardt steps through them.
Batched LAPACK calls on tiny matrices run one problem at a time on one core; these loops
vectorize under `vmap`.
"""

import functools as ft

import jax
import jax.flatten_util
import jax.numpy as jnp
import jaxlie
import lineax as lx
import optimistix as optx
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, Float


SOLVERS = ("lm", "gn")


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


# --------------------------------------------------------------------------------------
# Six unknowns (one SE(3) pose): everything unrolled and element-wise, so that under `vmap`
# XLA fuses a whole iteration into a few loops over the batch (no `dot`, no LAPACK).


def _cholesky_solve6(H: Float[Array, "6 6"], g: Float[Array, "6"]):
    """Solve `H x = g` for SPD `H` with an unrolled Cholesky (no LAPACK). Returns (x, ok)."""
    n = 6
    L = [[None] * n for _ in range(n)]
    ok = jnp.array(True)
    tiny = jnp.finfo(H.dtype).tiny
    for j in range(n):
        s = H[j, j] - sum((L[j][k] * L[j][k] for k in range(j)), start=0.0)
        ok = ok & (s > tiny)
        d = jnp.sqrt(jnp.where(s > tiny, s, 1.0))
        L[j][j] = d
        for i in range(j + 1, n):
            L[i][j] = (H[i, j] - sum((L[i][k] * L[j][k] for k in range(j)), start=0.0)) / d
    y = [None] * n
    for i in range(n):
        y[i] = (g[i] - sum((L[i][k] * y[k] for k in range(i)), start=0.0)) / L[i][i]
    x = [None] * n
    for i in reversed(range(n)):
        x[i] = (y[i] - sum((L[k][i] * x[k] for k in range(i + 1, n)), start=0.0)) / L[i][i]
    return jnp.stack(x), ok


def _inverse6(H: Float[Array, "6 6"]):
    """Inverse of an SPD 6x6 matrix by an unrolled Cholesky (no LAPACK); `(inv, ok)`."""
    eye = jnp.eye(6, dtype=H.dtype)
    cols, oks = jax.vmap(lambda e: _cholesky_solve6(H, e))(eye)
    inv = cols.T
    inv = 0.5 * (inv + inv.T)
    ok = jnp.all(oks) & jnp.all(jnp.isfinite(inv))
    return jnp.where(ok, inv, 0.0), ok


def _normal_equations6(r: Float[Array, " m"], J: Float[Array, "m 6"]):
    """`(J^T J, J^T r)` as element-wise products and sums (no `dot`)."""
    H = jnp.sum(J[:, :, None] * J[:, None, :], axis=0)
    g = jnp.sum(J * r[:, None], axis=0)
    return H, g


def _rplus(T: jaxlie.SE3, delta, dtype) -> jaxlie.SE3:
    # jaxlie's exp returns float64 under x64 even for float32 input: cast back.
    return jaxlie.SE3(jaxlie.manifold.rplus(T, delta).wxyz_xyz.astype(dtype))


def _pose_lm(
    model, T0: jaxlie.SE3, *, damped: bool, max_steps: int, rtol, atol, active, lam0=1e-3
):
    """Levenberg--Marquardt (or, `damped=False`, Gauss--Newton) on one SE(3) pose,
    re-linearized at the current pose every step.

    `model(T) -> (r, J)`: residuals `(m,)` and their Jacobian `(m, 6)` w.r.t. the right
    perturbation `T exp(delta)` at `delta = 0` (chain rule, by the caller). One model
    evaluation per iteration, the normal equations as element-wise sums, an unrolled
    Cholesky. Isotropic damping `lambda I` (on a whitened problem `lambda` is a prior
    precision on `(v, omega)`), from `lam0`, divided by 10 after an accepted step,
    multiplied by 10 after a rejected one; Gauss--Newton takes every finite step.
    Converged when a step (accepted, or rejected at negligible damping: the minimum within
    rounding) is below `atol + rtol * |t|_inf` (m, rad); then one last Gauss--Newton step
    from the Jacobian at hand (no model evaluation) takes the remaining error to rounding.
    An inactive problem takes no step: under `vmap` it does not prolong its batch's loop.
    Not meant to be differentiated (see `_implicit_pose_step`). Returns
    `(T, num_steps, converged)`.
    """
    dtype = T0.wxyz_xyz.dtype
    r0, J0 = model(T0)
    lam0 = jnp.array(lam0 if damped else 0.0, dtype)
    init = (jnp.array(0, jnp.int32), T0.wxyz_xyz, r0, J0, lam0, ~active, jnp.array(False))

    def cond(state):
        k, *_, done, _ = state
        return (k < max_steps) & ~done

    def body(state):
        k, params, r, J, lam, _, _ = state
        H, g = _normal_equations6(r, J)
        delta, ok = _cholesky_solve6(H + lam * jnp.eye(6, dtype=dtype), -g)
        finite = ok & jnp.all(jnp.isfinite(delta))
        delta = jnp.where(finite, delta, 0.0)
        T_new = _rplus(jaxlie.SE3(params), delta, dtype)
        r_new, J_new = model(T_new)
        cost, cost_new = jnp.sum(r * r), jnp.sum(r_new * r_new)
        accept = finite & jnp.isfinite(cost_new)
        if damped:
            accept = accept & (cost_new <= cost)
        small = jnp.max(jnp.abs(delta)) <= atol + rtol * jnp.max(jnp.abs(params[4:]))
        done = (accept | (lam < 10.0 * lam0)) & finite & small
        pick = lambda a, b: jnp.where(accept, a, b)  # noqa: E731
        if damped:
            lam = jnp.where(
                accept, jnp.maximum(lam / 10.0, 1e-9), jnp.minimum(lam * 10.0, 1e12)
            )
        return (
            k + 1, pick(T_new.wxyz_xyz, params), pick(r_new, r), pick(J_new, J), lam,
            done, done,
        )

    k, params, r, J, _, _, converged = jax.lax.while_loop(cond, body, init)
    H, g = _normal_equations6(r, J)
    delta, ok = _cholesky_solve6(H, -g)
    ok = ok & converged & jnp.all(jnp.isfinite(delta))
    T = jaxlie.SE3(params)
    T_last = _rplus(T, jnp.where(ok, delta, 0.0), dtype)
    return jaxlie.SE3(jnp.where(ok, T_last.wxyz_xyz, params)), k, converged


def _zero_step(params):
    # Derived from an input so that under `vmap` it is batched like its tangent.
    return jnp.zeros(6, params.dtype) + 0.0 * params[0]


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


@ft.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _implicit_pose_step(residuals, static, params, args):
    """Zero tangent step at a converged pose `params` (`wxyz_xyz`) whose derivative is that
    of the minimizer of `|residuals(T exp(delta), args, static)|^2` w.r.t. `args`
    (implicit function theorem on the gradient of the cost; full Hessian). The pose
    `T exp(step)` is the solution with correct derivatives; it does not depend on the
    starting pose. `residuals` and `static` are hashable and not differentiated."""
    return _zero_step(params)


@ft.partial(_implicit_pose_step.defjvp, symbolic_zeros=True)
def _implicit_pose_step_jvp(residuals, static, primals, tangents):
    params, args = primals
    _, args_dot = tangents
    zero = _zero_step(params)
    T = jaxlie.SE3(params)

    def gradient(delta, args):
        def cost(d):
            r = residuals(jaxlie.manifold.rplus(T, d), args, static)
            return 0.5 * jnp.sum(r * r)

        return jax.grad(cost)(delta)

    H = jax.jacfwd(gradient)(zero, args)
    H_inv, _ = _inverse6(0.5 * (H + H.T))
    g_dot = _jvp_nonzero(lambda a: gradient(zero, a), args, args_dot)
    return zero, jnp.zeros_like(zero) if g_dot is None else -H_inv @ g_dot
