"""Tests of `solve_overhead_pose` (robust all-triplets P3P and the paper's Eq. 6)."""

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from jaxloc._core.batching import map_problems
from jaxloc._core.results import RESULTS, status_code
from jaxloc._solvers.dlt import paper_linear_pose
from jaxloc._solvers.overhead import solve_overhead_pose
from jaxloc._solvers.pose_problem import PoseSolution


F_PX = 656.0  # focal length of the paper-like overhead camera, pixels


def _robust(p, b):
    return solve_overhead_pose(p, b, throw=False)


def _paper(p, b):
    return solve_overhead_pose(p, b, method="paper", throw=False)


_robust_batch = jax.jit(jax.vmap(_robust))
_paper_batch = jax.jit(jax.vmap(_paper))


def _problems(rng, n_problems, kind, noise_px=0.0):
    """Six points per problem: world (N,6,3), bearings (N,6,3), normalized xy (N,6,2),
    true R (N,3,3), t (N,3), camera centre (N,3)."""
    out = {k: [] for k in ("X", "b", "xy", "R", "t", "C")}
    down = np.diag([1.0, -1.0, -1.0])
    while len(out["X"]) < n_problems:
        yaw = jaxlie.SO3.from_z_radians(rng.uniform(-np.pi, np.pi)).as_matrix()
        tilt = jaxlie.SO3.exp(jnp.asarray(rng.normal(size=3) * 0.1)).as_matrix()
        R = np.asarray(down @ np.asarray(tilt) @ np.asarray(yaw))
        if kind == "general":
            X = rng.uniform(-1.5, 1.5, size=(6, 3))
            R = np.asarray(jaxlie.SO3.exp(jnp.asarray(rng.normal(size=3) * 2)).as_matrix())
            t = np.array([0.0, 0.0, 5.0]) + rng.normal(size=3) * 0.5
            C = -R.T @ t
        else:
            if kind == "floor":
                X = np.c_[rng.uniform(-2, 2, size=(6, 2)), np.zeros(6)]
            else:  # paper: triangle base 2 m, sides 1.5 m, three moved robots, saddle floor
                h = np.sqrt(1.5**2 - 1.0)
                base = np.array([[-1.0, 0, 0], [1.0, 0, 0], [0, h, 0]])
                moved = base + np.c_[rng.normal(0, 0.5, (3, 2)), np.zeros(3)]
                X = np.vstack([base, moved])
                X[:, 2] = (X[:, 0] ** 2 - X[:, 1] ** 2) / 16.0
            C = np.array([0.0, 0.0, 3.5]) + rng.normal(size=3) * 0.1
            t = -R @ C
        Xc = X @ R.T + t
        if np.any(Xc[:, 2] < 0.5):
            continue
        xy = Xc[:, :2] / Xc[:, 2:3] + rng.normal(0, noise_px / F_PX, (6, 2))
        b = np.c_[xy, np.ones(6)]
        for k, v in zip(out, (X, b / np.linalg.norm(b, axis=1, keepdims=True), xy, R, t, C)):
            out[k].append(v)
    return {k: np.stack(v) for k, v in out.items()}


def _centres(sol):
    return np.asarray(jax.vmap(lambda T: T.inverse().translation())(sol.pose))


def _matrices(sol):
    return np.asarray(jax.vmap(lambda T: T.as_matrix())(sol.pose))


@pytest.mark.parametrize("kind", ["general", "floor", "paper"])
def test_robust_noiseless_exact(kind):
    d = _problems(np.random.default_rng(0), 200, kind)
    sol = _robust_batch(jnp.asarray(d["X"]), jnp.asarray(d["b"]))
    assert np.all(np.asarray(status_code(sol.result)) == 0)
    M = _matrices(sol)
    assert np.abs(M[:, :3, :3] - d["R"]).max() < 1e-8
    assert np.abs(M[:, :3, 3] - d["t"]).max() < 1e-8
    assert np.asarray(sol.stats["rms_angular_error"]).max() < 1e-8
    assert np.all(np.asarray(sol.stats["num_valid_candidates"]) >= 1)


def test_paper_method():
    d = _problems(np.random.default_rng(1), 50, "general")
    sol = _paper_batch(jnp.asarray(d["X"]), jnp.asarray(d["b"]))
    assert np.all(np.asarray(status_code(sol.result)) == 0)
    M = _matrices(sol)
    assert np.abs(M[:, :3, :3] - d["R"]).max() < 1e-8
    assert np.abs(M[:, :3, 3] - d["t"]).max() < 1e-8
    assert np.asarray(sol.stats["rank_deficiency"]).max() < 1e-6
    # Coplanar floor: rank deficient, identity pose, reported.
    d = _problems(np.random.default_rng(2), 50, "floor")
    sol = _paper_batch(jnp.asarray(d["X"]), jnp.asarray(d["b"]))
    assert np.all(np.asarray(sol.result == RESULTS.rank_deficient))
    assert np.asarray(sol.stats["planarity"]).max() < 1e-12
    assert np.asarray(sol.stats["rank_deficiency"]).min() > 1e-3
    np.testing.assert_allclose(np.asarray(sol.pose.wxyz_xyz), np.tile(np.eye(1, 7), (50, 1)))
    # The paper's near-planar saddle: solved (noiselessly exact), planarity reported.
    d = _problems(np.random.default_rng(3), 50, "paper")
    sol = _paper_batch(jnp.asarray(d["X"]), jnp.asarray(d["b"]))
    assert np.all(np.asarray(status_code(sol.result)) == 0)
    assert np.all(np.asarray(sol.stats["planarity"]) > 1e-3)
    assert np.abs(_centres(sol) - d["C"]).max() < 1e-6
    with pytest.raises(ValueError, match="at least 6"):
        paper_linear_pose(jnp.zeros((5, 3)), jnp.zeros((5, 3)))


def test_robust_no_worse_than_sqpnp():
    n = 1000
    d = _problems(np.random.default_rng(4), n, "paper", noise_px=2.0)
    centres, ok = [], []
    for k in range(0, n, 200):  # same batch size as the other tests: one compilation
        sol = _robust_batch(jnp.asarray(d["X"][k : k + 200]), jnp.asarray(d["b"][k : k + 200]))
        centres.append(_centres(sol))
        ok.append(np.asarray(status_code(sol.result)) == 0)
    assert np.all(np.concatenate(ok))
    err = np.linalg.norm(np.concatenate(centres) - d["C"], axis=1)
    err_cv = []
    for i in range(n):
        _, rvec, tvec = cv2.solvePnP(
            d["X"][i], d["xy"][i].reshape(-1, 1, 2), np.eye(3), None,
            flags=cv2.SOLVEPNP_SQPNP,
        )
        R, _ = cv2.Rodrigues(rvec)
        err_cv.append(np.linalg.norm(-R.T @ tvec.ravel() - d["C"][i]))
    med, med_cv = np.median(err), np.median(err_cv)
    print(f"median position error: robust {med:.4f} m, SQPnP {med_cv:.4f} m")
    assert med <= 1.02 * med_cv


def test_jit_eager_vmap_loop():
    d = _problems(np.random.default_rng(5), 200, "paper", noise_px=2.0)
    X, b = jnp.asarray(d["X"]), jnp.asarray(d["b"])
    batch = _robust_batch(X, b)
    # The eager entry point runs its kernel under an internal `jax.jit`; comparing a Python
    # loop of eager calls with the jit(vmap) batch covers jit == eager and vmap == loop
    # without another (slow) compilation.
    for i in range(3):
        eager = _robust(X[i], b[i])
        single = jax.tree.map(lambda x: x[i], batch)
        assert eqx.tree_equal(eager, single, rtol=1e-9, atol=1e-9)


def test_grad_matches_finite_differences():
    d = _problems(np.random.default_rng(6), 1, "paper", noise_px=2.0)
    X, b = jnp.asarray(d["X"][0]), jnp.asarray(d["b"][0])
    weights = jnp.array([1.0, -2.0, 3.0])

    def f(b):
        sol = solve_overhead_pose(X, b, throw=False)
        return jnp.sum(sol.pose.inverse().translation() * weights)

    value_and_grad = jax.jit(jax.value_and_grad(f))  # one compilation for values and grads
    g = np.asarray(value_and_grad(b)[1])
    assert np.all(np.isfinite(g))
    h = 1e-6
    fd = np.zeros((6, 3))
    for i in range(6):
        for j in range(3):
            e = jnp.zeros((6, 3)).at[i, j].set(h)
            fd[i, j] = (value_and_grad(b + e)[0] - value_and_grad(b - e)[0]) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-3, atol=1e-4)


def test_failures():
    d = _problems(np.random.default_rng(7), 1, "paper")
    X, b = jnp.asarray(d["X"][0]), jnp.asarray(d["b"][0])
    ones = jnp.ones(6, dtype=bool)
    identity = np.eye(1, 7)[0]

    def check(sol, item):
        assert sol.result == item
        np.testing.assert_allclose(np.asarray(sol.pose.wxyz_xyz), identity)

    # Too few points (mask).
    mask = ones.at[2:].set(False)
    check(solve_overhead_pose(X, b, mask, throw=False), RESULTS.too_few_points)
    with pytest.raises(Exception, match="Fewer points"):
        solve_overhead_pose(X, b, mask)
    # Masked NaN is ignored; unmasked NaN is reported.
    bn = b.at[5, 0].set(jnp.nan)
    sol = solve_overhead_pose(X, bn, ones.at[5].set(False), throw=False)
    assert sol.result == RESULTS.successful
    check(solve_overhead_pose(X, bn, ones, throw=False), RESULTS.nonfinite_observation)
    check(_paper(X, bn), RESULTS.nonfinite_observation)
    with pytest.raises(Exception, match="NaN"):
        solve_overhead_pose(X, bn, ones)
    # Collinear points.
    Xl = jnp.stack([jnp.linspace(-1.0, 1.0, 6), jnp.zeros(6), jnp.zeros(6)], axis=1)
    bl = Xl - jnp.array([[0.0, 0.0, 3.5]])
    bl = bl / jnp.linalg.norm(bl, axis=1, keepdims=True)
    check(solve_overhead_pose(Xl, bl, ones, throw=False), RESULTS.degenerate_configuration)
    with pytest.raises(Exception, match="collinear"):
        solve_overhead_pose(Xl, bl, ones)
    # Eager validation.
    with pytest.raises(ValueError, match="method"):
        solve_overhead_pose(X, b, method="dlt")
    with pytest.raises(ValueError, match="bearings"):
        solve_overhead_pose(X, b[:5])
    with pytest.raises(ValueError, match="points_world"):
        solve_overhead_pose(X[:, :2], b[:, :2])
    with pytest.raises(ValueError, match="mask"):
        solve_overhead_pose(X, b, jnp.ones(5, dtype=bool))


def test_refine_seam():
    d = _problems(np.random.default_rng(8), 1, "paper")
    X, b = jnp.asarray(d["X"][0]), jnp.asarray(d["b"][0])
    calls = []

    def refine(sol, p, bw, mask):
        calls.append((p.shape, bw.shape, mask.shape))
        assert isinstance(sol, PoseSolution)
        return sol

    solve_overhead_pose(X, b, refine=refine, throw=False)
    assert calls == [((6, 3), (6, 3), (6,))]


@pytest.mark.slow  # a float32 compilation (~8 s cold)
def test_float32():
    d = _problems(np.random.default_rng(9), 200, "paper")
    sol = _robust_batch(jnp.asarray(d["X"], jnp.float32), jnp.asarray(d["b"], jnp.float32))
    assert sol.pose.wxyz_xyz.dtype == jnp.float32
    assert np.all(np.asarray(status_code(sol.result)) == 0)
    M = _matrices(sol)
    assert np.abs(M[:, :3, :3] - d["R"]).max() < 1e-4
    assert np.median(np.abs(M[:, :3, 3] - d["t"]).max(axis=1)) < 1e-4
    assert np.abs(M[:, :3, 3] - d["t"]).max() < 1e-3


def test_map_problems_pads_and_steps():
    """`map_problems` (shard_map over the devices + lax.map steps, padded to the device
    count) returns one row per problem, in order, whatever its step size."""

    def fn(x, y):
        return {"sum": jnp.sum(x) + y, "twice": 2.0 * x}

    x = jnp.arange(21.0 * 3).reshape(21, 3)
    y = jnp.arange(21.0)
    for batch_size in (1, 4, 64):
        out = map_problems(fn, batch_size=batch_size)(x, y)
        np.testing.assert_array_equal(out["sum"], jnp.sum(x, axis=1) + y)
        np.testing.assert_array_equal(out["twice"], 2.0 * x)
    with pytest.raises(ValueError, match="batch_size"):
        map_problems(fn, batch_size=0)


@pytest.mark.slow
def test_map_problems_equals_vmap():
    """The robust solver under `map_problems` gives the `jit(vmap)` numbers (to the
    polish's tolerance: vector widths differ)."""
    d = _problems(np.random.default_rng(10), 200, "paper", noise_px=2.0)
    X, b = jnp.asarray(d["X"]), jnp.asarray(d["b"])
    ref = _robust_batch(X, b)
    out = map_problems(_robust, batch_size=64)(X, b)  # 200 = 3 steps of 64 + 8
    assert eqx.tree_equal(out, ref, rtol=1e-9, atol=1e-9)
