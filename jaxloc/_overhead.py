r"""Overhead (wall-climbing robot) camera pose from the ground robots it sees (Sec. III.A).

The public entry point is [`jaxloc.solve_overhead_pose`][]. Its default method is robust to
the coplanar / near-planar floors where the paper's Eq. 6 is rank deficient: it runs a
branch-free Lambda Twist P3P on every point triplet, scores every candidate on all points
by angular error, keeps the best, and polishes it with a few Gauss--Newton steps on the
chordal bearing error. No `jnp.linalg` on that path (DESIGN §8).
"""

import itertools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Bool, Float

from ._results import raise_if_failed, RESULTS
from ._solvers.dlt import (
    angular_errors,
    check_inputs,
    identity_like,
    paper_linear_pose,
    point_spread,
    PoseSolution,
    rms,
    where_pose,
)
from ._solvers.p3p import p3p


_POLISH_STEPS = 5


def _normalize_rows(v: Float[Array, "n 3"]) -> Float[Array, "n 3"]:
    n2 = jnp.sum(v * v, axis=-1, keepdims=True)
    ok = n2 > 0
    return jnp.where(ok, v / jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)


def _chordal_residuals(
    pose: jaxlie.SE3, X: Float[Array, "n 3"], b: Float[Array, "n 3"], w: Float[Array, " n"]
) -> Float[Array, " 3n"]:
    """`w_i (q_i / |q_i| - b_i)`, q_i = pose @ X_i; |.|^2 = 2 (1 - cos angle) ~ angle^2."""
    q = jax.vmap(pose.apply)(X)
    return (w[:, None] * (_normalize_rows(q) - b)).reshape(-1)


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


def _polish(pose: jaxlie.SE3, X, b, w, steps: int) -> jaxlie.SE3:
    """A few Gauss--Newton steps on the chordal bearing error (each step kept only if it
    lowers the cost). Lightly damped; unrolled, so `grad` differentiates through it."""
    dtype = X.dtype

    def step(_, params):
        pose = jaxlie.SE3(wxyz_xyz=params)

        def res(delta):
            return _chordal_residuals(jaxlie.manifold.rplus(pose, delta), X, b, w)

        zero = jnp.zeros(6, dtype=dtype)
        r = res(zero)
        J = jax.jacfwd(res)(zero)
        H = J.T @ J
        H = H + 1e-9 * jnp.diag(jnp.diag(H)) + jnp.finfo(dtype).eps * jnp.eye(6, dtype=dtype)
        delta, ok = _cholesky_solve6(H, -(J.T @ r))
        delta = jnp.where(ok & jnp.all(jnp.isfinite(delta)), delta, 0.0)
        # jaxlie's exp returns float64 under x64 even for float32 input: cast back.
        new = jaxlie.SE3(wxyz_xyz=jaxlie.manifold.rplus(pose, delta).wxyz_xyz.astype(dtype))
        r_new = _chordal_residuals(new, X, b, w)
        better = jnp.sum(r_new * r_new) < jnp.sum(r * r)
        return jnp.where(better, new.wxyz_xyz, params)

    pose = jaxlie.SE3(wxyz_xyz=jax.lax.fori_loop(0, steps, step, pose.wxyz_xyz))
    return pose


@jax.jit
def _robust_pose(X, bw, mask) -> PoseSolution:
    dtype = X.dtype
    eps = jnp.finfo(dtype).eps
    n = X.shape[0]
    finite = jnp.all(jnp.isfinite(X), axis=1) & jnp.all(jnp.isfinite(bw), axis=1)
    nonfinite = jnp.any(mask & ~finite)
    use = mask & finite
    X = jnp.where(use[:, None], X, 0.0)
    b = _normalize_rows(jnp.where(use[:, None], bw, jnp.array([[0.0, 0.0, 1.0]], dtype=dtype)))
    b = jnp.where(use[:, None], b, jnp.array([[0.0, 0.0, 1.0]], dtype=dtype))
    w = use.astype(dtype)

    # All C(n, 3) triplets, enumerated at trace time.
    tri = np.array(list(itertools.combinations(range(n), 3)), dtype=np.int32)
    Xt, bt = X[tri], b[tri]
    # Skip triplets with masked points or (nearly) collinear points: twice the area over
    # the longest squared edge (scale free, ~eps for exactly collinear points).
    e1 = Xt[:, 1] - Xt[:, 0]
    e2 = Xt[:, 2] - Xt[:, 0]
    e3 = Xt[:, 2] - Xt[:, 1]
    cr = jnp.cross(e1, e2)
    area2 = jnp.sum(cr * cr, axis=-1)
    longest = jnp.maximum(
        jnp.maximum(jnp.sum(e1 * e1, axis=-1), jnp.sum(e2 * e2, axis=-1)),
        jnp.sum(e3 * e3, axis=-1),
    )
    thr = 1e-2 * jnp.sqrt(eps)
    noncollinear = area2 > (thr * longest) ** 2
    tri_ok = jnp.all(use[tri], axis=1) & noncollinear
    # Candidate search without gradients; the chosen triplet is re-solved below so that
    # `grad` only differentiates one P3P (a much smaller backward graph).
    sols = jax.vmap(p3p)(jax.lax.stop_gradient(Xt), jax.lax.stop_gradient(bt))
    params = sols.poses.wxyz_xyz.reshape(-1, 7)
    cand_ok = (sols.valid & tri_ok[:, None]).reshape(-1)

    def score(p):
        T = jaxlie.SE3(wxyz_xyz=p)
        q = jax.vmap(T.apply)(X)
        chord2 = jnp.sum((_normalize_rows(q) - b) ** 2, axis=-1)
        in_front = jnp.sum(q * b, axis=-1) > 0
        return jnp.sum(w * chord2), jnp.all(in_front | ~use)

    costs, front_ok = jax.vmap(score)(params)
    good = cand_ok & front_ok & jnp.isfinite(costs)
    costs = jnp.where(good, costs, jnp.inf)
    best = jnp.argmin(costs)
    num_valid = jnp.sum(good).astype(jnp.int32)
    best_tri = jnp.asarray(tri)[best // 4]
    chosen = p3p(X[best_tri], b[best_tri])
    pose = jaxlie.SE3(wxyz_xyz=chosen.poses.wxyz_xyz[best % 4])
    pose = _polish(pose, X, b, w, _POLISH_STEPS)

    planarity, collinearity = point_spread(X, use)
    count = jnp.sum(use)
    result = RESULTS.where(
        nonfinite,
        RESULTS.nonfinite_observation,
        RESULTS.where(
            count < 3,
            RESULTS.too_few_points,
            RESULTS.where(
                ~jnp.any(tri_ok),
                RESULTS.degenerate_configuration,
                RESULTS.where(
                    (num_valid > 0) & jnp.all(jnp.isfinite(pose.wxyz_xyz)),
                    RESULTS.successful,
                    RESULTS.no_valid_solution,
                ),
            ),
        ),
    )
    success = result == RESULTS.successful
    pose = where_pose(success, pose, identity_like(dtype))
    stats = {
        "planarity": planarity,
        "collinearity": collinearity,
        "num_valid_candidates": num_valid,
        "rms_angular_error": rms(angular_errors(pose, X, b), use),
    }
    return PoseSolution(pose=pose, result=result, stats=stats)


def solve_overhead_pose(
    points_world: Float[Array, "n 3"],
    bearings: Float[Array, "n 3"],
    mask: Bool[Array, " n"] | None = None,
    *,
    method: str = "robust",
    throw: bool = True,
    refine: Callable[..., PoseSolution] | None = None,
) -> PoseSolution:
    r"""Pose `T_cam_world` of the overhead camera from world points and their bearings.

    **Arguments:**

    - `points_world`: positions of the observed robots (markers) in the world frame, metres,
        shape `(n, 3)`.
    - `bearings`: unit bearings of the same points in the overhead camera frame, shape
        `(n, 3)` (any camera model: unproject the pixels first). Re-normalized internally.
    - `mask`: optional boolean `(n,)`; `False` marks points to ignore (their values, even
        NaN, are not used).
    - `method`: keyword only.
        - `"robust"` (default, `n >= 3`): Lambda Twist P3P ([`jaxloc.p3p`][]) on all
            C(n, 3) triplets (triplets with masked or nearly collinear points are skipped),
            every candidate scored on all unmasked points by the sum of squared chordal
            bearing errors |q/|q| - b|^2 (~ squared angular error); candidates that put an
            unmasked point behind the camera (`b . q <= 0`) are discarded; the best is
            polished with 5 Gauss--Newton steps on the same error. Works on coplanar and
            near-planar points; no LAPACK. Cost grows as C(n, 3).
        - `"paper"` (`n >= 6`): the paper's linear Eq. 6, [`jaxloc.paper_linear_pose`][].
    - `throw`: keyword only. If `True`, raise (at run time, also under `jit`) when `result`
        is not successful; otherwise inspect `result`.
    - `refine`: keyword only, optional seam for a nonlinear refinement. Called as
        `refine(solution, points_world, bearings, mask)` with the initial
        [`jaxloc.PoseSolution`][] and the sanitized inputs (`mask` a boolean `(n,)` array),
        it must return a `PoseSolution`. Called before `throw` is applied.

    **Returns:** a [`jaxloc.PoseSolution`][]. `result` is `successful`,
    `nonfinite_observation` (NaN/inf in an unmasked input), `too_few_points` (fewer than 3
    unmasked points; 6 for `"paper"`), `degenerate_configuration` (collinear points),
    `no_valid_solution` (no candidate puts every point in front), or for `"paper"`
    `rank_deficient` (coplanar points). On failure the pose is the identity, never NaN.

    Single problem; batch with `jax.vmap`. Shapes and `method` are checked eagerly
    (`ValueError`). Safe under `jit`, `vmap` and `grad` (gradients flow through the P3P
    depth polishing and the Gauss--Newton polish; the candidate choice is piecewise
    constant).
    """
    if method == "robust":
        X, b, m = check_inputs(
            points_world, bearings, mask, min_points=3, name="solve_overhead_pose"
        )
        sol = _robust_pose(X, b, m)
    elif method == "paper":
        X, b, m = check_inputs(
            points_world, bearings, mask, min_points=6, name="solve_overhead_pose"
        )
        sol = paper_linear_pose(X, b, m)
    else:
        raise ValueError(
            f"`method` must be \"robust\" or \"paper\"; got {method!r}."
        )
    if refine is not None:
        sol = refine(sol, X, b, m)
    return raise_if_failed(sol, sol.result, throw)
