"""Tests of the branch-free Lambda Twist P3P (`jaxloc._solvers.p3p`)."""

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import poselib
import pytest
from jaxloc._solvers.p3p import p3p, P3PSolution


_p3p_batch = jax.jit(jax.vmap(p3p))


def _random_problems(rng, n_problems, kind):
    """World points (N,3,3), bearings (N,3,3), true R (N,3,3), t (N,3)."""
    Xs, ys, Rs, ts = [], [], [], []
    while len(Xs) < n_problems:
        if kind == "general":
            R = np.asarray(jaxlie.SO3.exp(jnp.asarray(rng.normal(size=3) * 2)).as_matrix())
            X = rng.uniform(-1, 1, size=(3, 3))
            t = np.array([0.0, 0.0, 4.0]) + rng.normal(size=3) * 0.5
        elif kind == "floor":  # coplanar z = 0, camera above looking down
            X = np.c_[rng.uniform(-2, 2, size=(3, 2)), np.zeros(3)]
            R = np.diag([1.0, -1.0, -1.0]) @ np.asarray(
                jaxlie.SO3.exp(jnp.asarray(rng.normal(size=3) * 0.2)).as_matrix()
            )
            C = np.array([0.0, 0.0, 3.5]) + rng.normal(size=3) * 0.3
            t = -R @ C
        else:  # paper: base 2 m, sides 1.5 m, camera 3.5 m above the base's middle
            h = np.sqrt(1.5**2 - 1.0)
            X = np.array([[-1.0, 0, 0], [1.0, 0, 0], [0, h, 0]])
            X[:, :2] += rng.normal(0, 0.4, (3, 2))
            X[:, 2] = (X[:, 0] ** 2 - X[:, 1] ** 2) / 16.0
            R = np.diag([1.0, -1.0, -1.0]) @ np.asarray(
                jaxlie.SO3.exp(jnp.asarray(rng.normal(size=3) * 0.1)).as_matrix()
            )
            t = -R @ (np.array([0.0, 0.0, 3.5]) + rng.normal(size=3) * 0.1)
        Xc = X @ R.T + t
        if np.any(Xc[:, 2] < 0.5):
            continue
        Xs.append(X)
        ys.append(Xc / np.linalg.norm(Xc, axis=1, keepdims=True))
        Rs.append(R)
        ts.append(t)
    return tuple(np.stack(v) for v in (Xs, ys, Rs, ts))


def _pose_errors(sol: P3PSolution, R, t):
    """Min over valid candidates of max-abs error of [R|t]; shape (N,)."""
    M = np.asarray(jax.vmap(jax.vmap(lambda T: T.as_matrix()))(sol.poses))
    err = np.abs(M[:, :, :3, :3] - R[:, None]).max(axis=(2, 3)) + np.abs(
        M[:, :, :3, 3] - t[:, None]
    ).max(axis=2)
    return np.where(np.asarray(sol.valid), err, np.inf).min(axis=1)


@pytest.mark.parametrize("kind", ["general", "floor", "paper"])
def test_noiseless_exact(kind):
    rng = np.random.default_rng(0)
    X, y, R, t = _random_problems(rng, 300, kind)
    sol = _p3p_batch(jnp.asarray(X), jnp.asarray(y))
    assert sol.poses.wxyz_xyz.shape == (300, 4, 7)
    assert np.all(np.isfinite(np.asarray(sol.poses.wxyz_xyz)))
    err = _pose_errors(sol, R, t)
    assert np.quantile(err, 0.99) < 1e-8, np.sort(err)[-5:]
    assert np.max(err) < 1e-6


def test_against_poselib():
    rng = np.random.default_rng(1)
    X, y, R, t = _random_problems(rng, 200, "general")
    sol = _p3p_batch(jnp.asarray(X), jnp.asarray(y))
    M = np.asarray(jax.vmap(jax.vmap(lambda T: T.as_matrix()))(sol.poses))
    valid = np.asarray(sol.valid)
    n_checked = 0
    for i in range(len(X)):
        for ps in poselib.p3p(list(y[i]), list(X[i])):
            d = np.abs(M[i, :, :3, :3] - ps.R).max(axis=(1, 2)) + np.abs(
                M[i, :, :3, 3] - ps.t
            ).max(axis=1)
            d = np.where(valid[i], d, np.inf)
            assert d.min() < 1e-6, (i, d)
            n_checked += 1
    assert n_checked >= 200


def test_float32():
    rng = np.random.default_rng(2)
    X, y, R, t = _random_problems(rng, 200, "paper")
    sol = _p3p_batch(jnp.asarray(X, jnp.float32), jnp.asarray(y, jnp.float32))
    assert sol.poses.wxyz_xyz.dtype == jnp.float32
    err = _pose_errors(sol, R, t)
    assert np.median(err) < 1e-4
    assert np.quantile(err, 0.95) < 1e-3


@pytest.mark.slow  # ~5 s cold
def test_degenerate_finite():
    X = jnp.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])  # collinear
    y = jnp.array([[0.0, 0, 1], [0.2, 0, 1], [0.4, 0, 1]])
    sol = p3p(X, y)
    assert np.all(np.isfinite(np.asarray(sol.poses.wxyz_xyz)))
    nan = p3p(X.at[0, 0].set(jnp.nan), y)
    assert not np.any(np.asarray(nan.valid))
    assert np.all(np.isfinite(np.asarray(nan.poses.wxyz_xyz)))
    with pytest.raises(ValueError, match="points_world"):
        p3p(jnp.zeros((4, 3)), jnp.zeros((4, 3)))


@pytest.mark.slow  # ~10 s cold; the robust solver's derivatives no longer go through P3P
def test_grad_matches_finite_differences():
    rng = np.random.default_rng(3)
    X, y, R, t = _random_problems(rng, 1, "paper")
    X, y = jnp.asarray(X[0]), jnp.asarray(y[0])
    sol = p3p(X, y)
    M = np.asarray(jax.vmap(lambda T: T.as_matrix())(sol.poses))
    err = np.abs(M[:, :3, 3] - t[0]).max(axis=1)
    k = int(np.argmin(np.where(np.asarray(sol.valid), err, np.inf)))

    def f(y):
        T = jaxlie.SE3(wxyz_xyz=p3p(X, y).poses.wxyz_xyz[k])
        return jnp.sum(T.inverse().translation() * jnp.array([1.0, 2.0, 3.0]))

    g = jax.jit(jax.grad(f))(y)
    f = jax.jit(f)
    assert np.all(np.isfinite(np.asarray(g)))
    h = 1e-6
    fd = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            e = jnp.zeros((3, 3)).at[i, j].set(h)
            fd[i, j] = (f(y + e) - f(y - e)) / (2 * h)
    np.testing.assert_allclose(np.asarray(g), fd, rtol=1e-4, atol=1e-5)
