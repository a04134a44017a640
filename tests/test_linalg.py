"""LAPACK-free small linear algebra (jaxloc._core.linalg) against LAPACK (numpy)."""

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from jax.test_util import check_grads
from jaxloc._core.linalg import jacobi_svd, max_trace_rotation


def _kabsch_reference(H):
    U, _, Vt = np.linalg.svd(H)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


@pytest.mark.parametrize("shape", [(12, 12), (20, 12), (6, 3), (3, 3), (7, 5)])
@pytest.mark.parametrize("dtype, tol", [(jnp.float64, 1e-13), (jnp.float32, 2e-6)])
def test_jacobi_svd_matches_lapack(shape, dtype, tol):
    rng = np.random.default_rng(0)
    # Singular values over six decades, as in the Eq. 6 system.
    A = rng.standard_normal((200,) + shape) * np.logspace(0, -6, shape[1])
    s, V = jax.jit(jax.vmap(jacobi_svd))(jnp.asarray(A, dtype))
    s, V = np.asarray(s, np.float64), np.asarray(V, np.float64)
    _, s_ref, Vt_ref = np.linalg.svd(A)
    np.testing.assert_allclose(s, s_ref, atol=tol * s_ref[:, :1].max())
    assert np.all(np.diff(s, axis=1) <= 0)
    eye = np.broadcast_to(np.eye(shape[1]), V.shape)
    np.testing.assert_allclose(V.transpose(0, 2, 1) @ V, eye, atol=10 * tol)
    # A V has orthogonal columns (A = U S V^T), and the last right vector is LAPACK's.
    AV = A @ V
    gram = AV.transpose(0, 2, 1) @ AV
    off = gram - np.einsum("bi,ij->bij", np.diagonal(gram, axis1=1, axis2=2), np.eye(shape[1]))
    assert np.max(np.abs(off)) < 10 * tol * np.max(s_ref) ** 2
    cos = np.abs(np.einsum("bi,bi->b", V[:, :, -1], Vt_ref[:, -1]))
    assert np.min(cos) > 1 - 1e2 * tol


def test_jacobi_svd_needs_a_tall_matrix():
    with pytest.raises(ValueError, match="tall"):
        jacobi_svd(jnp.ones((2, 3)))


def _cases(rng, kind):
    if kind == "generic":
        return rng.standard_normal((3, 3))
    if kind == "reflection":
        H = rng.standard_normal((3, 3))
        return H if np.linalg.det(H) < 0 else -H
    if kind == "two pairs":  # rank 2, as in a mutual localization
        a = rng.standard_normal((2, 3))
        R = np.asarray(jaxlie.SO3.exp(jnp.asarray(rng.standard_normal(3))).as_matrix())
        b = a @ R.T + 0.01 * rng.standard_normal((2, 3))
        return b.T @ a
    if kind == "equal singular values":
        R = np.asarray(jaxlie.SO3.exp(jnp.asarray(rng.standard_normal(3))).as_matrix())
        return 2.5 * R
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["generic", "reflection", "two pairs", "equal singular values"])
def test_max_trace_rotation_is_kabsch(kind):
    rng = np.random.default_rng(1)
    H = np.stack([_cases(rng, kind) for _ in range(300)])
    R = np.asarray(jax.jit(jax.vmap(max_trace_rotation))(jnp.asarray(H)))
    R_ref = np.stack([_kabsch_reference(h) for h in H])
    np.testing.assert_allclose(R, R_ref, atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    # float32: as accurate as LAPACK's float32 SVD on the same matrices at the 99th
    # percentile. (The worst of the 300 two-pair cases is ~4x LAPACK's: 5e-5 vs 1.3e-5.)
    R32 = np.asarray(jax.vmap(max_trace_rotation)(jnp.asarray(H, jnp.float32)))
    R32_lapack = np.stack([_kabsch_reference(h) for h in H.astype(np.float32)])
    err = np.abs(R32 - R_ref).max(axis=(1, 2))
    err_lapack = np.abs(R32_lapack - R_ref).max(axis=(1, 2))
    assert np.percentile(err, 99) <= 2 * np.percentile(err_lapack, 99) + 1e-6


def test_max_trace_rotation_degenerate_input_is_a_rotation():
    rank1 = np.outer([1.0, 2.0, 0.5], [0.3, -1.0, 2.0])
    for H in (np.zeros((3, 3)), rank1):
        R = np.asarray(max_trace_rotation(jnp.asarray(H)))
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        # Any maximizer: tr(R^T H) reaches the sum of the singular values.
        assert np.trace(R.T @ H) == pytest.approx(np.linalg.svd(H, compute_uv=False).sum())
    np.testing.assert_array_equal(max_trace_rotation(jnp.zeros((3, 3))), np.eye(3))


def test_max_trace_rotation_gradients():
    rng = np.random.default_rng(2)
    for kind in ("generic", "two pairs"):
        H = jnp.asarray(_cases(rng, kind))
        check_grads(max_trace_rotation, (H,), order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6)


def test_two_pair_rotation_is_kabsch():
    from jaxloc._solvers.mutual import _two_pair_rotation

    rng = np.random.default_rng(3)
    for _ in range(50):
        a = rng.standard_normal((2, 3))
        b = a @ np.asarray(jaxlie.SO3.exp(jnp.asarray(rng.standard_normal(3))).as_matrix()).T
        b += 0.05 * rng.standard_normal((2, 3))  # noisy, so not an exact rotation
        a /= np.linalg.norm(a, axis=1, keepdims=True)
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        R = np.asarray(_two_pair_rotation(*jnp.asarray(a), *jnp.asarray(b)))
        np.testing.assert_allclose(R, _kabsch_reference(b.T @ a), atol=1e-12)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_row_equilibrated_gram_counts_each_row_once(dtype):
    """`row_equilibrated_gram(J)` is `J_n^T J_n`, `J_n` the rows of `J` scaled to unit
    norm, whatever the rows' weights (zero rows left out): the information the gates test
    for singularity."""
    from jaxloc._core.linalg import row_equilibrated_gram

    rng = np.random.default_rng(0)
    J = rng.normal(size=(9, 4))
    J[3] = 0.0  # a missing measurement
    weights = 10.0 ** rng.uniform(-6, 6, size=9)
    norms = np.linalg.norm(J, axis=1, keepdims=True)
    unit = np.divide(J, norms, out=np.zeros_like(J), where=norms > 0)
    got = row_equilibrated_gram(jnp.asarray(J * weights[:, None], dtype))
    assert got.dtype == dtype
    rtol = 1e-12 if dtype == jnp.float64 else 1e-5
    np.testing.assert_allclose(np.asarray(got), unit.T @ unit, rtol=rtol, atol=rtol)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
@pytest.mark.parametrize("rhs", [(), (3,)])
def test_gauss_jordan_solve_matches_lapack(dtype, rhs):
    """The small SPD solve of the least-squares kernel (`solve_spd`) and the covariances:
    equal to LAPACK's on badly scaled SPD systems, vector or matrix right-hand side, in
    the input's dtype, batched by `vmap`."""
    from jaxloc._core.linalg import gauss_jordan_solve

    rng = np.random.default_rng(1)
    for n in (1, 6, 7, 12):
        A = rng.normal(size=(2 * n + 3, n)) * 10.0 ** rng.uniform(-2, 2, size=n)
        H = A.T @ A
        B = rng.normal(size=(n, *rhs))
        X, ok = gauss_jordan_solve(jnp.asarray(H, dtype), jnp.asarray(B, dtype))
        assert bool(ok) and X.dtype == dtype and X.shape == B.shape
        expected = np.linalg.solve(H, B)
        # Column scales over 4 decades (condition numbers up to ~1e7) leave elimination's
        # error at a few eps relative to the solution (measured 4 eps in float32).
        tol = 100 * np.finfo(dtype).eps
        assert np.max(np.abs(np.asarray(X) - expected)) <= tol * np.max(np.abs(expected))
    Hs = jnp.asarray(np.stack([H, 2.0 * H]), dtype)
    Xs, oks = jax.vmap(gauss_jordan_solve)(Hs, jnp.asarray(np.stack([B, B]), dtype))
    assert np.all(np.asarray(oks))
    np.testing.assert_allclose(np.asarray(Xs[1]), np.asarray(Xs[0]) / 2, rtol=1e-4)


def test_gauss_jordan_solve_flags_what_is_not_positive_definite():
    """An indefinite, singular or NaN matrix: `ok` False and a finite (meaningless)
    solution, never a NaN that would leak into a batch; `small_spd_inverse` gives 0."""
    from jaxloc._core.linalg import gauss_jordan_solve, small_spd_inverse

    b = jnp.ones(3)
    for H in (np.diag([1.0, -1.0, 2.0]), np.ones((3, 3)), np.zeros((3, 3))):
        X, ok = gauss_jordan_solve(jnp.asarray(H), b)
        assert not bool(ok) and np.all(np.isfinite(np.asarray(X)))
        inverse, ok = small_spd_inverse(jnp.asarray(H))
        assert not bool(ok) and np.all(np.asarray(inverse) == 0)
    _, ok = gauss_jordan_solve(jnp.full((3, 3), jnp.nan), b)
    assert not bool(ok)


def test_gauss_jordan_solve_gradients():
    """Differentiable in both arguments, forward and reverse (the covariances' derivatives
    in the formation search)."""
    from jaxloc._core.linalg import gauss_jordan_solve

    rng = np.random.default_rng(2)
    A = rng.normal(size=(9, 5))
    H, b = jnp.asarray(A.T @ A), jnp.asarray(rng.normal(size=5))
    check_grads(lambda H, b: gauss_jordan_solve(0.5 * (H + H.T), b)[0], (H, b), order=1)
