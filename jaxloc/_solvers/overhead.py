r"""Overhead (wall-climbing robot) camera pose from the ground robots it sees (Sec. III.A).

The public entry point is [`jaxloc.solve_overhead_pose`][]. Its default method is robust to
the coplanar / near-planar floors where the paper's Eq. 6 is rank deficient: it runs a
branch-free Lambda Twist P3P on the best-conditioned point triplets, scores every candidate
on all points by angular error, keeps the best, and polishes it with jaxloc's
Levenberg--Marquardt (`jaxloc._core.least_squares`) on the chordal bearing error
(chain-rule Jacobian, implicit derivatives). No `jnp.linalg` on that path, and no gathers
or batched `dot`s of tiny matrices (DESIGN §8).
"""

import functools as ft
import itertools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Bool, Float

from .._core.compiler import jit
from .._core.least_squares import implicit_step, levenberg_marquardt, normal_equations
from .._core.numerics import safe_normalize
from .._core.poses import apply, inverse, rplus, rplus_params
from .._core.results import raise_if_failed, RESULTS
from .._cycle.sightings import matmul, matvec, skew
from .dlt import paper_linear_pose
from .p3p import p3p
from .pose_problem import (
    angular_errors,
    check_inputs,
    identity_like,
    point_spread,
    PoseSolution,
    rms,
    where_pose,
)


#: Triplets solved by P3P (the best-conditioned ones), and the polish's iteration limit.
_NUM_TRIPLETS = 4
_POLISH_STEPS = 5
# A candidate is another minimum (the robust solver's runner-up) when its camera centre
# is farther from the winner's than this fraction of the RMS camera-to-point distance.
_DISTINCT_CENTRE = 0.3
#: Number of alternatives a robust solution carries (the other roots of one P3P).
NUM_ALTERNATIVES = 3


def _chordal_model(params, X, b, w):
    r"""Chordal bearing residuals `w_i (q_i / |q_i| - b_i)` `(3n,)`, `q = R X + t` with `T =
    (R, t)` = `T_cam_world` (their squared norm is `2 (1 - cos angle)`, about the squared
    angle), and their Jacobian `(3n, 6)` with respect to the right perturbation
    `T exp(delta)`, by the chain rule: `d(q/|q|)/dq = (I - u u^T) / |q|` and
    `dq/d delta = R [I, -[X]x]`."""
    T = jaxlie.SE3(params)
    R = T.rotation().as_matrix()
    q = matvec(R[None], X) + T.translation()[None]
    n2 = jnp.sum(q * q, axis=-1)
    ok = n2 > 0
    inv = jnp.where(ok, 1.0 / jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)
    u = q * inv[:, None]
    r = w[:, None] * (u - b)
    eye = jnp.eye(3, dtype=X.dtype)
    D = (w * inv)[:, None, None] * (eye[None] - u[:, :, None] * u[:, None, :])
    A = jnp.sum(D[:, :, :, None] * R[None, None, :, :], axis=2)  # d r / d v, (n, 3, 3)
    Jw = -matmul(A, skew(X))
    return r.reshape(-1), jnp.concatenate([A, Jw], axis=-1).reshape(-1, 6)


def _chordal_residuals(params, delta, args, static):
    del static
    X, b, w = args
    T = rplus(jaxlie.SE3(params), delta)
    q = jax.vmap(ft.partial(apply, T))(X)
    return (w[:, None] * (safe_normalize(q) - b)).reshape(-1)


def _polish(pose: jaxlie.SE3, X, b, w, steps: int) -> jaxlie.SE3:
    """Minimise the chordal bearing error from `pose`: the least-squares kernel with the
    chain-rule Jacobian (at most `steps` iterations), not differentiated; derivatives of
    the minimizer w.r.t. `X` and `b` by the implicit function theorem."""
    dtype = X.dtype
    tol = max(1e-8, 100.0 * float(jnp.finfo(dtype).eps))
    stop = jax.lax.stop_gradient
    Xs, bs, ws = stop(X), stop(b), stop(w)
    # Residuals are in rad (~1e-3 at 2 px), not whitened: a damping well below J^T J, and
    # the step test alone.
    out = levenberg_marquardt(
        lambda x: normal_equations(*_chordal_model(x, Xs, bs, ws)),
        rplus_params,
        lambda x: jnp.max(jnp.abs(x[4:])),
        stop(pose.wxyz_xyz),
        num_unknowns=6,
        max_steps=steps,
        rtol=tol,
        atol=tol,
        lam0=1e-9,
        final_gauss_newton=True,
    )
    step = implicit_step(_chordal_residuals, 6, None, out.x, (X, b, w))
    return rplus(jaxlie.SE3(out.x), step)


def collinearity_free(Xt, eps):
    """Which triplets `(T, 3, 3)` are not (nearly) collinear: twice the area over the
    longest squared edge (scale free, ~eps for exactly collinear points)."""
    e1 = Xt[:, 1] - Xt[:, 0]
    e2 = Xt[:, 2] - Xt[:, 0]
    e3 = Xt[:, 2] - Xt[:, 1]
    cr = jnp.cross(e1, e2)
    area2 = jnp.sum(cr * cr, axis=-1)
    longest = jnp.maximum(
        jnp.maximum(jnp.sum(e1 * e1, axis=-1), jnp.sum(e2 * e2, axis=-1)),
        jnp.sum(e3 * e3, axis=-1),
    )
    return area2 > (1e-2 * jnp.sqrt(eps) * longest) ** 2, cr, longest


def _select_triplets(Xt, bt, tri_ok, cw, longest, k: int):
    """One-hot weights `(k, T)` of the `k` best-conditioned usable triplets: largest
    product of the bearing triangle's squared area and the world triangle's squared
    relative area (area over longest edge squared). Repeated arg-max, no sort."""
    c = jnp.cross(bt[:, 1] - bt[:, 0], bt[:, 2] - bt[:, 0])
    rel = jnp.sum(cw * cw, axis=-1) / jnp.where(longest > 0, longest, 1.0) ** 2
    score = jnp.where(tri_ok, jnp.sum(c * c, axis=-1) * rel, -1.0)
    idx = jnp.arange(score.shape[0])
    hots = []
    for _ in range(k):
        hot = idx == jnp.argmax(score)
        hots.append(hot)
        score = jnp.where(hot, -jnp.inf, score)
    return jnp.stack(hots)


def _candidates(X, b, use, eps):
    """P3P on the best-conditioned triplets of the usable points, without gradients (the
    polish carries them): candidate poses `(4k, 7)`, which are valid, and whether any
    triplet was usable. One-hot picks: no gather."""
    n = X.shape[0]
    tri = np.array(list(itertools.combinations(range(n), 3)), dtype=np.int32)
    Xs, bs = jax.lax.stop_gradient(X), jax.lax.stop_gradient(b)
    Xt, bt = Xs[tri], bs[tri]
    noncollinear, cw, longest = collinearity_free(Xt, eps)
    tri_ok = jnp.all(use[tri], axis=1) & noncollinear
    k = min(_NUM_TRIPLETS, tri.shape[0])
    hot = _select_triplets(Xt, bt, tri_ok, cw, longest, k).astype(X.dtype)
    Xk = jnp.sum(hot[:, :, None, None] * Xt[None], axis=1)
    bk = jnp.sum(hot[:, :, None, None] * bt[None], axis=1)
    okk = jnp.sum(hot * tri_ok.astype(X.dtype)[None], axis=1) > 0
    sols = jax.vmap(p3p)(Xk, bk)
    params = sols.poses.wxyz_xyz.reshape(-1, 7)
    return params, (sols.valid & okk[:, None]).reshape(-1), jnp.any(tri_ok)


def _score(params, X, b, w, use):
    """Trimmed sum of squared chordal bearing errors of each candidate on the usable
    points (the largest quarter of them left out, so one outlying sighting cannot pull
    the choice towards a wrong candidate), and whether it puts every usable point in
    front of the camera."""
    count = jnp.sum(use)
    kept = count - count // 4

    def one(p):
        T = jaxlie.SE3(wxyz_xyz=p)
        R = T.rotation().as_matrix()
        q = matvec(R[None], X) + T.translation()[None]
        chord2 = jnp.sum((safe_normalize(q) - b) ** 2, axis=-1)
        in_front = jnp.sum(q * b, axis=-1) > 0
        ascending = jnp.sort(jnp.where(use, w * chord2, jnp.inf))
        trimmed = jnp.where(jnp.arange(X.shape[0]) < kept, ascending, 0.0)
        return jnp.sum(trimmed), jnp.all(in_front | ~use)

    return jax.vmap(one)(jax.lax.stop_gradient(params))


def _runners_up(params, costs, best, X, w, success):
    """The `NUM_ALTERNATIVES` best candidates whose camera centres are far from the
    winner's and from each other's (other local minima, e.g. the mirror pose of nearly
    coplanar points; with few points seen there can be several): `(params (k, 7),
    ok (k,))`, best first."""
    Xs = jax.lax.stop_gradient(X)
    centres = jax.vmap(lambda p: inverse(jaxlie.SE3(p)).translation())(params)
    best_centre = jnp.sum(jnp.where(best[:, None], centres, 0.0), axis=0)
    depth2 = jnp.sum(w * jnp.sum((Xs - best_centre[None]) ** 2, -1)) / jnp.maximum(jnp.sum(w), 1)

    def far_from(centre):
        return jnp.sum((centres - centre[None]) ** 2, -1) > _DISTINCT_CENTRE**2 * depth2

    available = far_from(best_centre)
    picks, oks = [], []
    for _ in range(NUM_ALTERNATIVES):
        other_costs = jnp.where(available, costs, jnp.inf)
        other = jnp.arange(costs.shape[0]) == jnp.argmin(other_costs)
        pick = jnp.sum(jnp.where(other[:, None], params, 0.0), axis=0)
        ok = success & jnp.isfinite(jnp.min(other_costs)) & jnp.all(jnp.isfinite(pick))
        picks.append(jnp.where(ok, pick, identity_like(params.dtype).wxyz_xyz))
        oks.append(ok)
        available = available & far_from(jnp.sum(jnp.where(other[:, None], centres, 0.0), axis=0))
    return jnp.stack(picks), jnp.stack(oks)


def _other_roots(params, good, best):
    """The valid candidates of the best triplet other than the winner, `(3, 7)` and their
    flags: with exactly three usable points, the P3P roots the points cannot tell apart."""
    first = params[:4]
    others = good[:4] & ~best[:4]
    # Compact the (up to three) other roots to the front, keeping their order.
    order = jnp.argsort(~others, stable=True)[:NUM_ALTERNATIVES]
    ok = others[order]
    ident = identity_like(params.dtype).wxyz_xyz
    return jnp.where(ok[:, None], first[order], ident[None]), ok


def _status(nonfinite, count, any_triplet, num_valid, pose, ambiguous):
    """The robust solver's status, by priority."""
    result = RESULTS.where(
        (num_valid > 0) & jnp.all(jnp.isfinite(pose.wxyz_xyz)),
        RESULTS.where(ambiguous, RESULTS.ambiguous, RESULTS.successful),
        RESULTS.no_valid_solution,
    )
    result = RESULTS.where(any_triplet, result, RESULTS.degenerate_configuration)
    result = RESULTS.where(count < 3, RESULTS.too_few_points, result)
    return RESULTS.where(nonfinite, RESULTS.nonfinite_observation, result)


@jit(inline=True)
def _robust_pose(X, bw, mask, runner_up: bool = False) -> PoseSolution:
    dtype = X.dtype
    eps = jnp.finfo(dtype).eps
    finite = jnp.all(jnp.isfinite(X), axis=1) & jnp.all(jnp.isfinite(bw), axis=1)
    nonfinite = jnp.any(mask & ~finite)
    use = mask & finite
    X = jnp.where(use[:, None], X, 0.0)
    b = safe_normalize(jnp.where(use[:, None], bw, jnp.array([[0.0, 0.0, 1.0]], dtype=dtype)))
    b = jnp.where(use[:, None], b, jnp.array([[0.0, 0.0, 1.0]], dtype=dtype))
    w = use.astype(dtype)
    params, cand_ok, any_triplet = _candidates(X, b, use, eps)
    costs, front_ok = _score(params, jax.lax.stop_gradient(X), jax.lax.stop_gradient(b), w, use)
    good = cand_ok & front_ok & jnp.isfinite(costs)
    costs = jnp.where(good, costs, jnp.inf)
    best = jnp.arange(costs.shape[0]) == jnp.argmin(costs)
    num_valid = jnp.sum(good).astype(jnp.int32)
    start = jnp.sum(jnp.where(best[:, None], params, 0.0), axis=0)
    pose = _polish(jaxlie.SE3(start), X, b, w, _POLISH_STEPS)
    count = jnp.sum(use)
    roots, roots_ok = _other_roots(params, good, best)
    three_points = count == 3
    ambiguous = three_points & jnp.any(roots_ok)
    result = _status(nonfinite, count, any_triplet, num_valid, pose, ambiguous)
    success = (result == RESULTS.successful) | (result == RESULTS.ambiguous)
    pose = where_pose(success, pose, identity_like(dtype))
    if runner_up:
        others, others_ok = _runners_up(params, costs, best, X, w, success)
        roots = jnp.where(three_points, roots, others)
        roots_ok = jnp.where(three_points, roots_ok, others_ok)
    else:
        roots_ok = roots_ok & three_points
    roots_ok = roots_ok & success
    planarity, collinearity = point_spread(X, use)
    stats = {
        "planarity": planarity,
        "collinearity": collinearity,
        "num_valid_candidates": num_valid,
        "rms_angular_error": rms(angular_errors(pose, X, b), use),
    }
    return PoseSolution(pose, result, stats, jaxlie.SE3(roots), roots_ok)


def solve_overhead_pose(
    points_world: Float[Array, "n 3"],
    bearings: Float[Array, "n 3"],
    mask: Bool[Array, " n"] | None = None,
    *,
    method: str = "robust",
    throw: bool = True,
    refine: Callable[..., PoseSolution] | None = None,
    runner_up: bool = False,
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
        - `"robust"` (default, `n >= 3`): Lambda Twist P3P ([`jaxloc.p3p`][]) on the 4
            best-conditioned of the C(n, 3) triplets (largest bearing-triangle area times
            world-triangle shape; triplets with masked or nearly collinear points are
            skipped; on the paper's 6-point problems as accurate as all 20 triplets),
            every candidate scored on the unmasked points by the sum of squared chordal
            bearing errors |q/|q| - b|^2 (~ squared angular error) without its largest
            quarter (one outlying sighting does not pick the candidate); candidates that put an
            unmasked point behind the camera (`b . q <= 0`) are discarded; the best is
            polished by at most 5 Levenberg--Marquardt steps on the same error. Works on
            coplanar and near-planar points; no LAPACK. Cost grows as C(n, 3) only in
            the cheap triplet scoring.
        - `"paper"` (`n >= 6`): the paper's linear Eq. 6, [`jaxloc.paper_linear_pose`][].
    - `throw`: keyword only. If `True`, raise (at run time, also under `jit`) when `result`
        is not successful; otherwise inspect `result`.
    - `refine`: keyword only, optional seam for a nonlinear refinement. Called as
        `refine(solution, points_world, bearings, mask)` with the initial
        [`jaxloc.PoseSolution`][] and the sanitized inputs (`mask` a boolean `(n,)` array),
        it must return a `PoseSolution`. Called before `throw` is applied.
    - `runner_up`: keyword only, `"robust"` only. With more than three usable points,
        `alternatives` (and `alternatives_ok`) are the best candidates far from the
        solution and from each other, best first: other local minima, e.g. the mirror
        pose of nearly coplanar points, for a multi-start refinement (the closed forms
        use `alternatives[0]`, the robust refinement all of them).

    **Returns:** a [`jaxloc.PoseSolution`][]. `result` is `successful`, `ambiguous` (exactly
    three usable points and several P3P roots in front of the camera: three points do
    not decide; the best-scoring root is `pose`, the others are in `alternatives`),
    `nonfinite_observation` (NaN/inf in an unmasked input), `too_few_points` (fewer than 3
    unmasked points; 6 for `"paper"`), `degenerate_configuration` (collinear points),
    `no_valid_solution` (no candidate of the solved triplets puts every point in front),
    or for `"paper"` `rank_deficient` (coplanar points). On failure the pose is the
    identity, never NaN.

    Single problem; batch with `jax.vmap`. Shapes and `method` are checked eagerly
    (`ValueError`). Safe under `jit`, `vmap` and `grad`: derivatives are those of the
    polished minimum of the chordal error w.r.t. `points_world` and `bearings` (implicit
    function theorem; the candidate choice is piecewise constant). For large batches on
    CPU, [`jaxloc.map_problems`][] is faster than `jax.jit(jax.vmap(...))`.
    """
    if method == "robust":
        X, b, m = check_inputs(
            points_world, bearings, mask, min_points=3, name="solve_overhead_pose"
        )
        sol = _robust_pose(X, b, m, runner_up)
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


