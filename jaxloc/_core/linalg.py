"""Small dense linear algebra written in plain JAX operations, without LAPACK.

Everything a Monte Carlo trial computes must be free of `jnp.linalg` calls: XLA on CPU
calls LAPACK once per small matrix (slow when batched), and jaxlib 0.10's batched LAPACK
kernels split a batch over the same thread pool that runs the devices' programs, so a
study sharded over two host devices deadlocks at 0% CPU (DESIGN §8). These functions are
branch-free, work under `jit`, `vmap` and `grad`, and in float32 and float64.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .numerics import safe_normalize


def default_sweeps(n: int) -> int:
    """Sweeps of the one-sided Jacobi SVD of an `n`-column matrix. Convergence is
    quadratic once the columns are nearly orthogonal: 4 sweeps reach rounding for 3
    columns and 6 for 12 (random matrices with singular values over 6 decades; measured
    against LAPACK), so 5 and 8 leave a margin."""
    return 5 if n <= 4 else 8


def max_trace_rotation(H: Float[Array, "3 3"]) -> Float[Array, "3 3"]:
    """The rotation matrix `R` maximizing `tr(R^T H)`: Kabsch's solution with the
    determinant fix, `U diag(1, 1, det(U V^T)) V^T` for the SVD `H = U S V^T`, which is
    also the nearest rotation to `H` in the Frobenius norm.

    Built from the two leading singular pairs only, `R = u1 v1^T + u2 v2^T + (u1 x u2)
    (v1 x v2)^T`, so it is proper by construction and well determined whenever `H` has
    rank >= 2 (e.g. two vector pairs), even when the two leading singular values are
    equal. For rank 1 any maximizer is returned, for `H = 0` the identity.
    """
    dtype = H.dtype
    s, V = jacobi_svd(H)
    HV = H @ V[:, :2]
    u1 = safe_normalize(HV[:, 0])
    # When the second singular value vanishes (rank 1) its left vector is any unit vector
    # orthogonal to u1: complete with the axis least aligned with u1.
    axis = jnp.eye(3, dtype=dtype)[jnp.argmin(jnp.abs(u1))]
    rank2 = s[1] > 16.0 * jnp.finfo(dtype).eps * s[0]
    u2 = safe_normalize(jnp.where(rank2, HV[:, 1], jnp.cross(u1, axis)))
    u2 = safe_normalize(u2 - jnp.dot(u1, u2) * u1)
    v1, v2 = V[:, 0], V[:, 1]
    R = jnp.outer(u1, v1) + jnp.outer(u2, v2) + jnp.outer(jnp.cross(u1, u2), jnp.cross(v1, v2))
    return jnp.where(s[0] > 0, R, jnp.eye(3, dtype=dtype))


def jacobi_svd(
    A: Float[Array, "m n"], sweeps: int | None = None
) -> tuple[Float[Array, " n"], Float[Array, "n n"]]:
    """Singular values and right singular vectors of a tall matrix (`m >= n`, `n` small).

    One-sided (Hestenes) Jacobi: plane rotations of column pairs, in rounds of disjoint
    pairs applied together, until the columns are orthogonal; the singular values are
    then their norms, accurate relative to the largest. A fixed number of sweeps
    (default `default_sweeps(n)`), so the cost does not depend on the data.

    **Returns:** `(s, V)` with `s` in descending order and `A ~ U diag(s) V^T`; `V[:, k]`
    belongs to `s[k]`.
    """
    m, n = A.shape
    if m < n:
        raise ValueError(f"`jacobi_svd` needs a tall matrix (m >= n); got shape {A.shape}.")
    dtype = A.dtype
    sweeps = default_sweeps(n) if sweeps is None else sweeps
    padded = n + n % 2
    if padded != n:
        A = jnp.concatenate([A, jnp.zeros((m, 1), dtype)], axis=1)
    h = padded // 2
    # Columns and right vectors stacked, `(m + padded, padded)`, split in two halves whose
    # columns k are the pairs of a round. Between rounds every column but the first moves
    # one place around the circle top[1:] -> bottom (reversed) -> top[1] (the round-robin
    # tournament), so that n - 1 rounds pair every two columns once and restore the order.
    X = jnp.concatenate([A, jnp.eye(padded, dtype=dtype)], axis=0)
    top, bottom = X[:, :h], X[:, h:][:, ::-1]

    def round_(top, bottom):
        a, b = top[:m], bottom[:m]
        alpha, beta, gamma = jnp.sum(a * a, 0), jnp.sum(b * b, 0), jnp.sum(a * b, 0)
        d = beta - alpha
        denominator = d + jnp.where(d >= 0, 1.0, -1.0) * jnp.sqrt(d * d + 4.0 * gamma * gamma)
        nonzero = denominator != 0
        t = jnp.where(nonzero, 2.0 * gamma / jnp.where(nonzero, denominator, 1.0), 0.0)
        c = jax.lax.rsqrt(1.0 + t * t)[None]
        s = c * t[None]
        top, bottom = c * top - s * bottom, s * top + c * bottom
        if h == 1:
            return top, bottom
        return (
            jnp.concatenate([top[:, :1], bottom[:, :1], top[:, 1:-1]], axis=1),
            jnp.concatenate([bottom[:, 1:], top[:, -1:]], axis=1),
        )

    # Every round is the same operation (the moves are a fixed permutation), so one loop
    # over all rounds of all sweeps traces and compiles it once.
    top, bottom = jax.lax.fori_loop(
        0, sweeps * (padded - 1), lambda _, halves: round_(*halves), (top, bottom)
    )
    X = jnp.concatenate([top, bottom[:, ::-1]], axis=1)
    A, V = X[:m], X[m:]
    s = jnp.sqrt(jnp.sum(A * A, axis=0))
    order = jnp.argsort(-s)[:n] if padded == n else _without_padding(s, n)
    return s[order], V[:n][:, order]


def _without_padding(s, n):
    # The zero column added to make the count even stays zero (rotations only mix it with
    # multiples of itself); rank it last by its index, not its norm.
    key = jnp.where(jnp.arange(s.shape[0]) < n, -s, jnp.inf)
    return jnp.argsort(key)[:n]

