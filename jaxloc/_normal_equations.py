"""Small dense least-squares linear algebra without LAPACK (DESIGN §8).

A column-by-column Cholesky and its triangular solves in `fori_loop`s, and the lineax
solver that takes optimistix's Gauss--Newton / Levenberg--Marquardt steps through them.
Batched LAPACK calls on tiny matrices run one problem at a time on one core; these loops
vectorize under `vmap`.
"""

import jax
import jax.flatten_util
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
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
