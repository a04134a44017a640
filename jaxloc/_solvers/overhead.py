r"""Overhead (wall-climbing robot) camera pose from the ground robots it sees (Sec. III.A).

The public entry point is [`jaxloc.solve_overhead_pose`][]. Its default method is robust to
the coplanar / near-planar floors where the paper's Eq. 6 is rank deficient: it runs a
branch-free Lambda Twist P3P on the best-conditioned point triplets, scores every candidate
on all points by angular error, keeps the best, and polishes it with jaxloc's
Levenberg--Marquardt on the chordal bearing error (chain-rule Jacobian, implicit
derivatives). No `jnp.linalg` on that path, and no gathers or batched `dot`s of tiny
matrices (DESIGN §8). [`map_problems`][] batches any single-problem function over the host
devices in cache-sized `vmap` steps.
"""

import functools as ft
import itertools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Bool, Float

from .._core.least_squares import (
    _cholesky_solve6 as _cholesky_solve6,  # its old home; now in _normal_equations
    _implicit_pose_step,
    _pose_lm,
    _rplus,
)
from .._core.results import raise_if_failed, RESULTS
from .dlt import (
    angular_errors,
    check_inputs,
    identity_like,
    paper_linear_pose,
    point_spread,
    PoseSolution,
    rms,
    where_pose,
)
from .p3p import p3p


#: Triplets solved by P3P (the best-conditioned ones), and the polish's iteration limit.
_NUM_TRIPLETS = 4
_POLISH_STEPS = 5
# A candidate is another minimum (the robust solver's runner-up) when its camera centre
# is farther from the winner's than this fraction of the RMS camera-to-point distance.
_DISTINCT_CENTRE = 0.3


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


def rotation_block(A: Float[Array, "n m 3"], X: Float[Array, "n 3"]) -> Float[Array, "n m 3"]:
    """Jacobian block of a right perturbation's rotation `omega` from the translation block
    `A = d r / d v`: `d r / d omega = A [e_k x X]_k` for world points `X`, element-wise."""
    x0, x1, x2 = X[:, 0], X[:, 1], X[:, 2]
    zero = jnp.zeros_like(x0)
    cross = jnp.stack(
        [jnp.stack([zero, -x2, x1], -1), jnp.stack([x2, zero, -x0], -1),
         jnp.stack([-x1, x0, zero], -1)],
        axis=-1,
    )  # [i, j, k] = (e_k x X_i)_j
    return jnp.sum(A[:, :, :, None] * cross[:, None, :, :], axis=2)


def _chordal_model(T: jaxlie.SE3, X, b, w):
    r"""Chordal residuals `(3n,)` and their Jacobian `(3n, 6)` w.r.t. the right
    perturbation `T exp(delta)` at `delta = 0`, by the chain rule, element-wise:
    `q = R X + t`, `d(q/|q|)/dq = (I - n n^T) / |q|`, `dq/dv = R`,
    `dq/d omega_k = R (e_k x X)`."""
    R = T.rotation().as_matrix()
    q = jnp.sum(X[:, None, :] * R[None, :, :], axis=-1) + T.translation()[None]
    n2 = jnp.sum(q * q, axis=-1)
    ok = n2 > 0
    inv = jnp.where(ok, 1.0 / jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)
    u = q * inv[:, None]
    r = w[:, None] * (u - b)
    eye = jnp.eye(3, dtype=X.dtype)
    D = (w * inv)[:, None, None] * (eye[None] - u[:, :, None] * u[:, None, :])
    A = jnp.sum(D[:, :, :, None] * R[None, None, :, :], axis=2)  # d r / d v, (n, 3, 3)
    Jw = rotation_block(A, X)
    return r.reshape(-1), jnp.concatenate([A, Jw], axis=-1).reshape(-1, 6)


def _chordal_implicit(T, args, static):
    del static
    X, b, w = args
    return _chordal_residuals(T, X, b, w)


def _polish(pose: jaxlie.SE3, X, b, w, steps: int) -> jaxlie.SE3:
    """Minimise the chordal bearing error from `pose`: jaxloc's Levenberg--Marquardt with
    the chain-rule Jacobian (at most `steps` iterations), not differentiated; derivatives
    of the minimizer w.r.t. `X` and `b` by the implicit function theorem."""
    dtype = X.dtype
    tol = max(1e-8, 100.0 * float(jnp.finfo(dtype).eps))
    stop = jax.lax.stop_gradient
    Xs, bs, ws = stop(X), stop(b), stop(w)
    # Residuals are in rad (~1e-3 at 2 px): start with a damping well below J^T J.
    pose, _, _ = _pose_lm(
        lambda T: _chordal_model(T, Xs, bs, ws),
        jaxlie.SE3(stop(pose.wxyz_xyz)),
        damped=True,
        max_steps=steps,
        rtol=tol,
        atol=tol,
        active=jnp.array(True),
        lam0=1e-9,
    )
    step = _implicit_pose_step(_chordal_implicit, None, pose.wxyz_xyz, (X, b, w))
    return _rplus(pose, step, dtype)


def _select_triplets(Xt, bt, tri_ok, k: int):
    """One-hot weights `(k, T)` of the `k` best-conditioned usable triplets: largest
    product of the bearing triangle's squared area and the world triangle's squared
    relative area (area over longest edge squared). Repeated arg-max, no sort."""
    c = jnp.cross(bt[:, 1] - bt[:, 0], bt[:, 2] - bt[:, 0])
    e1 = Xt[:, 1] - Xt[:, 0]
    e2 = Xt[:, 2] - Xt[:, 0]
    e3 = Xt[:, 2] - Xt[:, 1]
    cw = jnp.cross(e1, e2)
    longest = jnp.maximum(
        jnp.maximum(jnp.sum(e1 * e1, axis=-1), jnp.sum(e2 * e2, axis=-1)),
        jnp.sum(e3 * e3, axis=-1),
    )
    rel = jnp.sum(cw * cw, axis=-1) / jnp.where(longest > 0, longest, 1.0) ** 2
    score = jnp.where(tri_ok, jnp.sum(c * c, axis=-1) * rel, -1.0)
    idx = jnp.arange(score.shape[0])
    hots = []
    for _ in range(k):
        hot = idx == jnp.argmax(score)
        hots.append(hot)
        score = jnp.where(hot, -jnp.inf, score)
    return jnp.stack(hots)


def _runner_up(params, costs, best, Xs, w, success, dtype) -> dict:
    """The robust solver's runner-up: the best candidate whose camera centre is far from
    the winner's (another local minimum, e.g. the mirror pose of nearly coplanar points),
    as `{"runner_up_pose": (7,), "runner_up_ok": ()}` (identity and False if none)."""
    centres = jax.vmap(lambda p: jaxlie.SE3(p).inverse().translation())(params)
    best_centre = jnp.sum(jnp.where(best[:, None], centres, 0.0), axis=0)
    depth2 = jnp.sum(w * jnp.sum((Xs - best_centre[None]) ** 2, -1)) / jnp.maximum(jnp.sum(w), 1)
    far = jnp.sum((centres - best_centre[None]) ** 2, -1) > _DISTINCT_CENTRE**2 * depth2
    other_costs = jnp.where(far, costs, jnp.inf)
    other = jnp.arange(costs.shape[0]) == jnp.argmin(other_costs)
    runner_up = jnp.sum(jnp.where(other[:, None], params, 0.0), axis=0)
    runner_up_ok = jnp.isfinite(jnp.min(other_costs)) & jnp.all(jnp.isfinite(runner_up))
    ok = success & runner_up_ok
    return {
        "runner_up_pose": jnp.where(ok, runner_up, identity_like(dtype).wxyz_xyz),
        "runner_up_ok": ok,
    }


@ft.partial(jax.jit, static_argnames="runner_up", inline=True)
def _robust_pose(X, bw, mask, runner_up: bool = False) -> PoseSolution:
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
    Xs, bs = jax.lax.stop_gradient(X), jax.lax.stop_gradient(b)
    Xt, bt = Xs[tri], bs[tri]
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
    # P3P on the best-conditioned triplets only (one-hot picks: no gather), without
    # gradients: the polish below carries the derivatives (implicit function theorem).
    k = min(_NUM_TRIPLETS, tri.shape[0])
    hot = _select_triplets(Xt, bt, tri_ok, k).astype(dtype)
    Xk = jnp.sum(hot[:, :, None, None] * Xt[None], axis=1)
    bk = jnp.sum(hot[:, :, None, None] * bt[None], axis=1)
    okk = jnp.sum(hot * tri_ok.astype(dtype)[None], axis=1) > 0
    sols = jax.vmap(p3p)(Xk, bk)
    params = sols.poses.wxyz_xyz.reshape(-1, 7)
    cand_ok = (sols.valid & okk[:, None]).reshape(-1)

    def score(p):
        T = jaxlie.SE3(wxyz_xyz=p)
        R = T.rotation().as_matrix()
        q = jnp.sum(Xs[:, None, :] * R[None, :, :], axis=-1) + T.translation()[None]
        chord2 = jnp.sum((_normalize_rows(q) - bs) ** 2, axis=-1)
        in_front = jnp.sum(q * bs, axis=-1) > 0
        return jnp.sum(w * chord2), jnp.all(in_front | ~use)

    costs, front_ok = jax.vmap(score)(params)
    good = cand_ok & front_ok & jnp.isfinite(costs)
    costs = jnp.where(good, costs, jnp.inf)
    best = jnp.arange(costs.shape[0]) == jnp.argmin(costs)
    num_valid = jnp.sum(good).astype(jnp.int32)
    start = jnp.sum(jnp.where(best[:, None], params, 0.0), axis=0)
    pose = _polish(jaxlie.SE3(start), X, b, w, _POLISH_STEPS)
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
    if runner_up:
        stats.update(_runner_up(params, costs, best, Xs, w, success, dtype))
    return PoseSolution(pose=pose, result=result, stats=stats)


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
            every candidate scored on all unmasked points by the sum of squared chordal
            bearing errors |q/|q| - b|^2 (~ squared angular error); candidates that put an
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
    - `runner_up`: keyword only, `"robust"` only. Also return the best candidate far
        from the solution (`stats["runner_up_pose"]`, `stats["runner_up_ok"]`): another
        local minimum, e.g. the mirror pose of nearly coplanar points, for a multi-start
        refinement (the concurrent strategy uses it).

    **Returns:** a [`jaxloc.PoseSolution`][]. `result` is `successful`,
    `nonfinite_observation` (NaN/inf in an unmasked input), `too_few_points` (fewer than 3
    unmasked points; 6 for `"paper"`), `degenerate_configuration` (collinear points),
    `no_valid_solution` (no candidate of the solved triplets puts every point in front),
    or for `"paper"` `rank_deficient` (coplanar points). On failure the pose is the
    identity, never NaN.

    Single problem; batch with `jax.vmap`. Shapes and `method` are checked eagerly
    (`ValueError`). Safe under `jit`, `vmap` and `grad`: derivatives are those of the
    polished minimum of the chordal error w.r.t. `points_world` and `bearings` (implicit
    function theorem; the candidate choice is piecewise constant). For large batches on
    CPU, [`map_problems`][] is faster than `jax.jit(jax.vmap(...))`.
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


def map_problems(fn: Callable, *, batch_size: int = 128, devices=None) -> Callable:
    r"""Batch a single-problem function the fast way on CPU: shard the problems over the
    host devices and walk each device's share in `lax.map` steps of `batch_size` problems
    `vmap`-ed together.

    `jax.jit(jax.vmap(fn))` runs every problem on one core, and an iterative solver's whole
    batch waits for its slowest problem; small `vmap`-ed steps keep the working set in
    cache and let each step stop with its own slowest problem (DESIGN §8: ~2x for
    element-wise kernels), and `shard_map` over the devices uses every core that XLA
    exposes (set `XLA_FLAGS=--xla_force_host_platform_device_count=N` before JAX starts
    for N CPU devices).

    **Arguments:**

    - `fn`: a function of one problem, `fn(*args) -> pytree of arrays` (e.g. a wrapper
        around [`jaxloc.solve_overhead_pose`][] and [`jaxloc.refine_overhead_pose`][]
        with `throw=False`). It must not call LAPACK (`jnp.linalg`): such programs were
        seen to hang when run from two devices at once (DESIGN §8).
    - `batch_size`: problems per `vmap`-ed step. Keyword only.
    - `devices`: the devices to shard over; default all of `jax.devices()`. Keyword only.

    **Returns:** a jitted function of the batched arguments (leading axis = problems, any
    size: padded internally to a multiple of the device count) returning `fn`'s outputs
    with the same leading axis. Results do not depend on `batch_size` or the devices.
    """
    if not isinstance(batch_size, int) or batch_size < 1:
        raise ValueError(f"`batch_size` must be a positive int; got {batch_size!r}.")
    devs = np.array(jax.devices() if devices is None else list(devices))
    mesh = jax.sharding.Mesh(devs, ("problems",))
    spec = jax.sharding.PartitionSpec("problems")
    nd = devs.size

    def local(*args):
        m = jax.tree.leaves(args)[0].shape[0]
        return jax.lax.map(lambda a: fn(*a), args, batch_size=min(batch_size, m))

    sharded = jax.shard_map(local, mesh=mesh, in_specs=spec, out_specs=spec, check_vma=False)

    @jax.jit
    def run(*args):
        leaves = jax.tree.leaves(args)
        if not leaves:
            raise ValueError("`map_problems`: the batched function needs array arguments.")
        n = leaves[0].shape[0]
        pad = (-n) % nd
        if pad:
            args = jax.tree.map(
                lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]), args
            )
        out = sharded(*args)
        return jax.tree.map(lambda o: o[:n], out) if pad else out

    return run
