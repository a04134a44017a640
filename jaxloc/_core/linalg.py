"""Small dense linear algebra written in plain JAX operations, without LAPACK: the one
home of jaxloc's closed-form 3x3 algebra, Cholesky factorizations and solves, SPD
inverses and the Jacobi SVD.

Everything a Monte Carlo trial computes must be free of `jnp.linalg` calls: XLA on CPU
calls LAPACK once per small matrix (slow when batched), and jaxlib 0.10's batched LAPACK
kernels split a batch over the same thread pool that runs the devices' programs, so a
study sharded over two host devices deadlocks at 0% CPU (DESIGN §8). These functions are
branch-free, work under `jit`, `vmap` and `grad`, and in float32 and float64. Singular
or indefinite input never raises: it gives a finite value and a flag (or NaN where
documented).
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Scalar

from .numerics import safe_normalize


# --------------------------------------------------------------------------------------
# 3x3 closed forms.


def det3(M: Float[Array, "3 3"]) -> Scalar:
    """Determinant of a 3x3 matrix by cofactor expansion along the first row."""
    return (
        M[0, 0] * (M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1])
        - M[0, 1] * (M[1, 0] * M[2, 2] - M[1, 2] * M[2, 0])
        + M[0, 2] * (M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0])
    )


def adjugate3(A: Float[Array, "3 3"]) -> tuple[Float[Array, "3 3"], Scalar]:
    """Adjugate and determinant of a 3x3 matrix (`A^-1 = adj / det`, `A adj = det I`)."""
    adj = jnp.stack([jnp.cross(A[1], A[2]), jnp.cross(A[2], A[0]), jnp.cross(A[0], A[1])], axis=1)
    return adj, jnp.dot(A[0], adj[:, 0])


def solve3(A: Float[Array, "3 3"], b: Float[Array, "3"]) -> Float[Array, "3"]:
    """Solve a 3x3 system by the adjugate; 0 where `A` is singular."""
    adj, det = adjugate3(A)
    ok = jnp.abs(det) > jnp.finfo(A.dtype).tiny
    return jnp.where(ok, adj @ b / jnp.where(ok, det, 1.0), 0.0)


def logdet3(P: Float[Array, "3 3"], floor: float = -1e3) -> Scalar:
    """`log det P` of a positive definite 3x3 matrix; `floor` where `det P <= 0`."""
    det = det3(P)
    ok = det > 0
    return jnp.where(ok, jnp.log(jnp.where(ok, det, 1.0)), floor)


def psd_cholesky3(P: Float[Array, "3 3"]) -> Float[Array, "3 3"]:
    """Lower Cholesky factor of a 3x3 positive semi-definite matrix, element-wise; a
    zero pivot (e.g. a fixed reference's zero covariance) gives a zero column."""

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


# --------------------------------------------------------------------------------------
# SPD systems: Cholesky in a loop over columns for any size, Gauss--Jordan for a few
# unknowns.


def cholesky(A: Float[Array, "n n"]) -> Float[Array, "n n"]:
    """Lower Cholesky factor, column by column in a `fori_loop` (traced once whatever
    `n`). NaN if `A` is not positive definite."""
    n = A.shape[0]
    rows = jnp.arange(n)

    def body(j, L):
        v = A[:, j] - L @ L[j, :]  # columns >= j of L are still zero
        d = jnp.sqrt(v[j])
        return L.at[:, j].set(jnp.where(rows >= j, v / d, 0.0))

    return jax.lax.fori_loop(0, n, body, jnp.zeros_like(A))


def cholesky_solve(L: Float[Array, "n n"], b: Float[Array, " n"]) -> Float[Array, " n"]:
    """Solve `L L^T x = b` by forward and back substitution (`fori_loop`s)."""
    n = L.shape[0]

    def fwd(i, y):
        return y.at[i].set((b[i] - L[i] @ y) / L[i, i])  # entries >= i of y still zero

    y = jax.lax.fori_loop(0, n, fwd, jnp.zeros_like(b))

    def bwd(k, x):
        i = n - 1 - k
        return x.at[i].set((y[i] - L[:, i] @ x) / L[i, i])  # entries <= i of x still zero

    return jax.lax.fori_loop(0, n, bwd, jnp.zeros_like(b))


def lower_inverse(L: Float[Array, "n n"]) -> Float[Array, "n n"]:
    """`L^-1` of a lower-triangular `L` by forward substitution."""
    n = L.shape[0]
    eye = jnp.eye(n, dtype=L.dtype)

    def body(i, Y):
        return Y.at[i].set((eye[i] - L[i] @ Y) / L[i, i])  # rows >= i of Y are still zero

    return jax.lax.fori_loop(0, n, body, jnp.zeros_like(L))


def spd_inverse(F: Float[Array, "n n"]) -> tuple[Float[Array, "n n"], Bool[Array, ""]]:
    """Inverse of a symmetric positive definite matrix via a Jacobi-scaled Cholesky
    (scaling to unit diagonal first makes it accurate for badly scaled information
    matrices). Returns `(inverse, ok)`; the inverse is 0 where `ok` is False (not
    positive definite)."""
    dg = jnp.diag(F)
    good = dg > 0
    d = jnp.where(good, 1.0 / jnp.sqrt(jnp.where(good, dg, 1.0)), 0.0)
    Fn = F * d[:, None] * d[None, :]
    Fn = jnp.where(jnp.all(good), Fn, jnp.eye(F.shape[0], dtype=F.dtype))
    L = cholesky(Fn)
    ok = jnp.all(good) & jnp.all(jnp.isfinite(L)) & jnp.all(jnp.diag(L) > 0)
    L = jnp.where(ok, L, jnp.eye(F.shape[0], dtype=F.dtype))
    Y = lower_inverse(L)
    inv = Y.T @ Y  # F_n^-1 = L^-T L^-1
    inv = d[:, None] * inv * d[None, :]
    inv = 0.5 * (inv + inv.T)
    ok = ok & jnp.all(jnp.isfinite(inv))
    return jnp.where(ok, inv, 0.0), ok


def scaled_inverse_trace(
    F: Float[Array, "n n"], inverse: Float[Array, "n n"]
) -> Float[Array, ""]:
    """The trace of the Jacobi-scaled (unit-diagonal) `F`'s inverse, from `F` and its
    inverse (e.g. [`spd_inverse`][]'s): `sum_i F_ii (F^-1)_ii`. Its reciprocal bounds the
    smallest eigenvalue `lambda` of the scaled `F` within a factor `n`: `lambda / n <=
    1 / trace <= lambda`. A relative test of singularity that a Cholesky's pivots are not:
    an exactly singular `F` can factor with a pivot rounded to a tiny positive number,
    and then this trace is ~1/eps. `inf` where `inverse` is zero (not positive definite)
    or not finite."""
    t = jnp.sum(jnp.diag(F) * jnp.diag(inverse))
    return jnp.where(jnp.isfinite(t) & (t > 0), t, jnp.inf)


def row_equilibrated_gram(J: Float[Array, "m n"]) -> Float[Array, "n n"]:
    """`sum_i J_i^T J_i / |J_i|^2` over the nonzero rows `J_i` of `J`: the Gram matrix of
    `J` with every row scaled to unit norm. Its null space is `J^T J`'s, its spread of
    scales is not: a direction no row touches stays singular to rounding, while rows
    weighed many orders of magnitude apart (pixels at a tiny sigma beside odometry) no
    longer push an observable direction down to rounding level."""
    squares = jnp.sum(J * J, axis=1)
    weight = jnp.where(squares > 0, 1.0 / jnp.where(squares > 0, squares, 1.0), 0.0)
    return jnp.einsum("mi,m,mj->ij", J, weight, J)


def gauss_jordan_solve(
    H: Float[Array, "n n"], B: Float[Array, "n ..."]
) -> tuple[Float[Array, "n ..."], Bool[Array, ""]]:
    """Solve `H X = B` for a small SPD `H` (`B` of shape `(n,)` or `(n, k)`) by Gauss--Jordan
    elimination without pivoting in a `fori_loop` over the `n` pivots. Each step is one
    element-wise update of the augmented matrix `[H | B]` (one fused kernel), so the
    program holds a handful of kernels whatever `n`, where a Cholesky and its two
    substitutions written element by element hold ~40 for `n = 7`. Without pivoting the
    pivots are the squares of the Cholesky factor's diagonal: elimination is as stable as
    Cholesky on SPD input, and every pivot is positive exactly when `H` is positive
    definite. Returns `(X, ok)`, `ok` False when a pivot is not positive (then `X` is
    meaningless, and finite where `H` and `B` are: a non-positive pivot is not divided
    by)."""
    n = H.shape[0]
    M = jnp.concatenate([H, B.reshape(n, -1).astype(H.dtype)], axis=1)
    rows = jnp.arange(n)[:, None]
    tiny = jnp.finfo(H.dtype).tiny

    def eliminate(j, M):
        column = jax.lax.dynamic_slice_in_dim(M, j, 1, axis=1)
        pivot = jax.lax.dynamic_slice(M, (j, j), (1, 1))
        factor = column / jnp.where(pivot > tiny, pivot, 1.0)
        row = jax.lax.dynamic_slice_in_dim(M, j, 1, axis=0)
        return jnp.where(rows == j, M, M - factor * row)  # row j kept: its pivot stays

    M = jax.lax.fori_loop(0, n, eliminate, M)
    pivots = jnp.diagonal(M[:, :n])
    ok = jnp.all(pivots > tiny)
    X = M[:, n:] / jnp.where(pivots > tiny, pivots, 1.0)[:, None]
    return X.reshape(B.shape), ok


def small_spd_inverse(H: Float[Array, "n n"]) -> tuple[Float[Array, "n n"], Bool[Array, ""]]:
    """Inverse of a small SPD matrix by [`gauss_jordan_solve`][]; `(inverse, ok)`, 0 where
    not positive definite."""
    inv, ok = gauss_jordan_solve(H, jnp.eye(H.shape[0], dtype=H.dtype))
    inv = 0.5 * (inv + inv.T)
    ok = ok & jnp.all(jnp.isfinite(inv))
    return jnp.where(ok, inv, 0.0), ok


def gram(J: Float[Array, "m n"]) -> Float[Array, "n n"]:
    """`J^T J` as element-wise products and a sum (no `dot`: fuses under `vmap`)."""
    return jnp.sum(J[:, :, None] * J[:, None, :], axis=0)


def gram_dot(J: Float[Array, "m n"]) -> Float[Array, "n n"]:
    """`J^T J` by one `dot`: for Jacobians with dozens of unknowns far faster than
    [`gram`][] on CPU. Measured under `vmap` at batch 32, (234, 72): 4.2 ms against 282 ms
    with the study programs' compiler options (`jaxloc._core.compiler.CPU_OPTIONS`), 1.0
    against 6.2 ms at (171, 60) with XLA's defaults; [`gram`][] wins only on tiny shapes
    ((20, 6): 0.04 against 0.07 ms)."""
    return jnp.einsum("mi,mj->ij", J, J)


# --------------------------------------------------------------------------------------
# Rotations from matrices: Jacobi SVD.


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

