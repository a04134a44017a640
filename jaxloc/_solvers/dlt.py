r"""The paper's linear overhead-camera pose (Sec. III.A, Eq. 6) and the shared `PoseSolution`.

Eq. 6 of the paper, for each world point $P_i = (X_i, Y_i, Z_i)$ seen at normalized image
coordinates $(x_i, y_i)$ (here $x_i = b_0 / b_2$, $y_i = b_1 / b_2$ from the unit bearing
$b$, i.e. the paper's $x_i / f$):

$$x_i (r_3 \cdot P_i + t_z) = r_1 \cdot P_i + t_x, \qquad
  y_i (r_3 \cdot P_i + t_z) = r_2 \cdot P_i + t_y,$$

a homogeneous linear system in the 12 entries of $[R \mid t]$ (`p_cam = R p_world + t`).
It needs $n \ge 6$ points and is rank deficient when the points are coplanar (a flat floor,
the paper's real experiment), ill conditioned when they are nearly so.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
from jaxtyping import Array, Bool, Float, Scalar

from .._core.linalg import jacobi_svd
from .._core.numerics import adjugate3
from .._core.poses import project_to_so3
from .._core.results import RESULTS


# Eq. 6 is declared rank deficient below this planarity (sigma3 / sigma1 of the centred
# points). The paper's saddle floor (radii +-8 m, 2 m triangle) has planarity ~5e-2: it is
# reported as ill conditioned through `stats` but still solved.
PLANARITY_THRESHOLD = 1e-3
# Points are declared collinear below this collinearity (sigma2 / sigma1).
COLLINEARITY_THRESHOLD = 1e-4


class PoseSolution(eqx.Module):
    """Overhead camera pose with a status code and diagnostics.

    **Attributes:**

    - `pose`: `jaxlie.SE3` `T_cam_world` (maps world points into the camera frame:
        `p_cam = R p_world + t`, metres). The identity pose whenever `result` is not
        successful; never NaN.
    - `result`: a [`jaxloc.RESULTS`][] item; `RESULTS.successful` is the only good outcome.
    - `stats`: diagnostics, scalar arrays:
        - `"planarity"`: sigma3 / sigma1 of the centred unmasked world points (0 = coplanar).
        - `"collinearity"`: sigma2 / sigma1 of the same (0 = collinear).
        - `"num_valid_candidates"`: int32, candidate poses that passed all checks.
        - `"rms_angular_error"`: rad, RMS angle between the observed bearings and the
            directions of the returned pose's predicted points (unmasked points).
        - method `"paper"` also has `"rank_deficiency"` (ratio of the two smallest singular
            values of the normalized Eq. 6 system; near 1 means a >1-dimensional null space).
        - method `"robust"` with `runner_up=True` also has `"runner_up_pose"`
            (`wxyz_xyz`, `(7,)`, unpolished) and `"runner_up_ok"`: the best-scoring
            candidate whose camera centre is more than 0.3 RMS camera-to-point distances
            from the returned one's (another local minimum, e.g. the mirror pose of
            nearly coplanar points; a start for a multi-start refinement), identity and
            False if there is none.
    """

    pose: jaxlie.SE3
    result: RESULTS
    stats: dict[str, Array]


def _sym_eigvals3(C: Float[Array, "3 3"]) -> Float[Array, "3"]:
    """Eigenvalues (descending) of a symmetric PSD 3x3 matrix, trigonometric closed form.

    No LAPACK (DESIGN §8). Absolute accuracy ~eps * largest eigenvalue.
    """
    q = (C[0, 0] + C[1, 1] + C[2, 2]) / 3.0
    p1 = C[0, 1] ** 2 + C[0, 2] ** 2 + C[1, 2] ** 2
    p2 = (C[0, 0] - q) ** 2 + (C[1, 1] - q) ** 2 + (C[2, 2] - q) ** 2 + 2.0 * p1
    ok = p2 > 0
    p = jnp.sqrt(jnp.where(ok, p2, 1.0) / 6.0)
    B = (C - q * jnp.eye(3, dtype=C.dtype)) / p
    detB = (
        B[0, 0] * (B[1, 1] * B[2, 2] - B[1, 2] * B[2, 1])
        - B[0, 1] * (B[1, 0] * B[2, 2] - B[1, 2] * B[2, 0])
        + B[0, 2] * (B[1, 0] * B[2, 1] - B[1, 1] * B[2, 0])
    )
    phi = jnp.arccos(jnp.clip(0.5 * detB, -1.0, 1.0)) / 3.0
    e1 = q + 2.0 * p * jnp.cos(phi)
    e3 = q + 2.0 * p * jnp.cos(phi + 2.0 * jnp.pi / 3.0)
    e2 = 3.0 * q - e1 - e3
    ev = jnp.stack([e1, e2, e3])
    return jnp.where(ok, ev, q)


def point_spread(
    points_world: Float[Array, "n 3"], mask: Bool[Array, " n"]
) -> tuple[Scalar, Scalar]:
    """`(planarity, collinearity)` = (sigma3/sigma1, sigma2/sigma1) of the centred points.

    Diagnostics only: computed under `stop_gradient`, closed form (no LAPACK). Exactly
    coplanar points give ~sqrt(eps) rather than 0 (1e-8 in float64, 3e-4 in float32).
    """
    P = jax.lax.stop_gradient(points_world)
    w = mask.astype(P.dtype)
    count = jnp.maximum(jnp.sum(w), 1.0)
    c = jnp.sum(w[:, None] * P, axis=0) / count
    Q = (P - c[None]) * w[:, None]
    ev = jnp.clip(_sym_eigvals3(Q.T @ Q / count), 0.0, None)
    ok = ev[0] > 0
    e0 = jnp.where(ok, ev[0], 1.0)
    planarity = jnp.where(ok, jnp.sqrt(ev[2] / e0), 0.0)
    collinearity = jnp.where(ok, jnp.sqrt(ev[1] / e0), 0.0)
    return planarity, collinearity


def angular_errors(
    pose: jaxlie.SE3, points_world: Float[Array, "n 3"], bearings: Float[Array, "n 3"]
) -> Float[Array, " n"]:
    """Angle (rad) between each bearing and the direction of `pose @ point` (finite grads)."""

    def one(p, b):
        q = pose @ p
        c = jnp.cross(b, q)
        s2 = jnp.sum(c * c)
        ok = s2 > 0
        s = jnp.where(ok, jnp.sqrt(jnp.where(ok, s2, 1.0)), 0.0)
        return jnp.arctan2(s, jnp.dot(b, q))

    return jax.vmap(one)(points_world, bearings)


def rms(x: Float[Array, " n"], mask: Bool[Array, " n"]) -> Scalar:
    w = mask.astype(x.dtype)
    ms = jnp.sum(w * jnp.where(mask, x, 0.0) ** 2) / jnp.maximum(jnp.sum(w), 1.0)
    ok = ms > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, ms, 1.0)), 0.0)


def identity_like(dtype) -> jaxlie.SE3:
    return jaxlie.SE3(wxyz_xyz=jnp.zeros(7, dtype=dtype).at[0].set(1.0))


def where_pose(cond, a: jaxlie.SE3, b: jaxlie.SE3) -> jaxlie.SE3:
    return jaxlie.SE3(wxyz_xyz=jnp.where(cond, a.wxyz_xyz, b.wxyz_xyz))


def check_inputs(
    points_world, bearings, mask, *, min_points: int, name: str
) -> tuple[Float[Array, "n 3"], Float[Array, "n 3"], Bool[Array, " n"]]:
    """Eager shape validation shared by the overhead solvers (raises `ValueError`)."""
    points_world = jnp.asarray(points_world)
    bearings = jnp.asarray(bearings)
    if points_world.ndim != 2 or points_world.shape[-1] != 3:
        raise ValueError(
            f"`points_world` must have shape (n, 3); got shape {points_world.shape}."
        )
    if bearings.shape != points_world.shape:
        raise ValueError(
            f"`bearings` must have the same shape as `points_world`, {points_world.shape}; "
            f"got shape {bearings.shape}."
        )
    if not (
        jnp.issubdtype(points_world.dtype, jnp.floating)
        and jnp.issubdtype(bearings.dtype, jnp.floating)
    ):
        raise ValueError(
            "`points_world` and `bearings` must be floating-point arrays; got dtypes "
            f"{points_world.dtype} and {bearings.dtype}."
        )
    n = points_world.shape[0]
    if n < min_points:
        raise ValueError(
            f"`{name}` needs at least {min_points} points; `points_world` has {n}."
        )
    if mask is None:
        mask = jnp.ones(n, dtype=bool)
    else:
        mask = jnp.asarray(mask)
        if mask.shape != (n,) or mask.dtype != jnp.bool_:
            raise ValueError(
                f"`mask` must be a boolean array of shape ({n},); got dtype {mask.dtype} "
                f"and shape {mask.shape}."
            )
    dtype = jnp.result_type(points_world, bearings)
    return points_world.astype(dtype), bearings.astype(dtype), mask


def paper_linear_pose(
    points_world: Float[Array, "n 3"],
    bearings: Float[Array, "n 3"],
    mask: Bool[Array, " n"] | None = None,
) -> PoseSolution:
    r"""The paper's linear pose (Eq. 6) with Hartley normalization, for `n >= 6` points.

    Builds the `2n x 12` homogeneous system of Eq. 6 on normalized points (2D points
    translated to their centroid and scaled to mean distance sqrt(2); 3D points to mean
    distance sqrt(3)), takes its null vector from the SVD (masked rows zeroed), undoes the
    normalization, fixes scale and sign so that most points have positive depth, projects
    the 3x3 block onto SO(3) and re-solves `t` by linear least squares given `R`.

    **Arguments:**

    - `points_world`: world points, metres, shape `(n, 3)`, `n >= 6`.
    - `bearings`: unit bearings in the camera frame, shape `(n, 3)`. Normalized image
        coordinates are `(b0 / b2, b1 / b2)`; bearings with `b2 <= 1e-6` (not in front of a
        perspective camera) are treated as masked.
    - `mask`: optional boolean `(n,)`, `False` marks points to ignore.

    **Returns:** a [`jaxloc.PoseSolution`][] (`T_cam_world`). `result` is
    `nonfinite_observation` (NaN/inf in an unmasked point or bearing),
    `too_few_points` (fewer than 6 usable points), `degenerate_configuration` (collinear
    points), `rank_deficient` (planarity below `1e-3`: coplanar points, where Eq. 6 has no
    unique solution; use `method="robust"`), or `successful`. `stats` additionally holds
    `"rank_deficiency"`. The SVDs are one-sided Jacobi in plain JAX operations (no
    LAPACK, so it runs sharded over host devices; DESIGN §8). Single problem; batch with
    `jax.vmap`.
    """
    X, bw, mask = check_inputs(points_world, bearings, mask, min_points=6, name="paper_linear_pose")
    dtype = X.dtype
    n = X.shape[0]
    finite = jnp.all(jnp.isfinite(X), axis=1) & jnp.all(jnp.isfinite(bw), axis=1)
    nonfinite = jnp.any(mask & ~finite)
    front = bw[:, 2] > 1e-6
    use = mask & finite & front
    X = jnp.where(use[:, None], X, 0.0)
    bw = jnp.where(use[:, None], bw, jnp.array([[0.0, 0.0, 1.0]], dtype=dtype))
    w = use.astype(dtype)
    count = jnp.sum(w)
    safe_count = jnp.maximum(count, 1.0)
    x = bw[:, :2] / bw[:, 2:3]

    # Hartley normalization.
    cx = jnp.sum(w[:, None] * x, axis=0) / safe_count
    dx = jnp.sqrt(jnp.sum((x - cx[None]) ** 2, axis=1) + jnp.finfo(dtype).tiny)
    sx = jnp.sqrt(2.0) / jnp.maximum(jnp.sum(w * dx) / safe_count, jnp.finfo(dtype).tiny)
    cX = jnp.sum(w[:, None] * X, axis=0) / safe_count
    dX = jnp.sqrt(jnp.sum((X - cX[None]) ** 2, axis=1) + jnp.finfo(dtype).tiny)
    sX = jnp.sqrt(3.0) / jnp.maximum(jnp.sum(w * dX) / safe_count, jnp.finfo(dtype).tiny)
    xn = (x - cx[None]) * sx
    Xh = jnp.concatenate([(X - cX[None]) * sX, jnp.ones((n, 1), dtype=dtype)], axis=1)

    zeros4 = jnp.zeros((n, 4), dtype=dtype)
    rows_u = jnp.concatenate([Xh, zeros4, -xn[:, 0:1] * Xh], axis=1)
    rows_v = jnp.concatenate([zeros4, Xh, -xn[:, 1:2] * Xh], axis=1)
    A = jnp.concatenate([rows_u, rows_v], axis=0) * jnp.concatenate([w, w])[:, None]
    if 2 * n < 12:  # pragma: no cover - n >= 6 is enforced above
        A = jnp.concatenate([A, jnp.zeros((12 - 2 * n, 12), dtype=dtype)], axis=0)
    svals, V = jacobi_svd(A)
    Pn = V[:, -1].reshape(3, 4)
    # s_min / s_second; when s_second is itself at rounding level (relative to s_max) the
    # null space is numerically >= 2-dimensional: report 1.
    second_ok = svals[-2] > 100.0 * jnp.finfo(dtype).eps * svals[0]
    rank_deficiency = jnp.where(
        second_ok, svals[-1] / jnp.where(second_ok, svals[-2], 1.0), 1.0
    )

    # Undo normalization: x = T2^-1 Pn T3 [X; 1].
    T2inv = jnp.array(
        [[1.0 / sx, 0.0, cx[0]], [0.0, 1.0 / sx, cx[1]], [0.0, 0.0, 1.0]], dtype=dtype
    )
    T3 = jnp.concatenate(
        [
            jnp.concatenate([sX * jnp.eye(3, dtype=dtype), -sX * cX[:, None]], axis=1),
            jnp.array([[0.0, 0.0, 0.0, 1.0]], dtype=dtype),
        ],
        axis=0,
    )
    P = T2inv @ Pn @ T3
    # Sign: positive depth (third row) for the majority of used points.
    depths = (jnp.concatenate([X, jnp.ones((n, 1), dtype=dtype)], axis=1) @ P[2]) * w
    sign = jnp.where(jnp.sum(jnp.sign(depths)) >= 0, 1.0, -1.0)
    M = sign * P[:, :3]
    R = project_to_so3(M)
    Rm = R.as_matrix()
    # Re-solve t given R (linear least squares, 3x3 normal equations):
    # [1, 0, -x] t = x r3.X - r1.X,  [0, 1, -y] t = y r3.X - r2.X.
    RX = X @ Rm.T
    one = jnp.ones_like(x[:, 0])
    zero = jnp.zeros_like(one)
    Au = jnp.stack([one, zero, -x[:, 0]], axis=1) * w[:, None]
    Av = jnp.stack([zero, one, -x[:, 1]], axis=1) * w[:, None]
    bu = (x[:, 0] * RX[:, 2] - RX[:, 0]) * w
    bv = (x[:, 1] * RX[:, 2] - RX[:, 1]) * w
    At = jnp.concatenate([Au, Av], axis=0)
    bt = jnp.concatenate([bu, bv], axis=0)
    adj, det = adjugate3(At.T @ At)
    t = adj @ (At.T @ bt) / jnp.where(det != 0, det, jnp.finfo(dtype).tiny)
    pose = jaxlie.SE3.from_rotation_and_translation(R, t)

    # Point spread from an SVD (accurate to eps, unlike the closed form of `point_spread`).
    Xs = jax.lax.stop_gradient(X)
    Q = (Xs - jnp.sum(w[:, None] * Xs, axis=0, keepdims=True) / safe_count) * w[:, None]
    sv, _ = jacobi_svd(Q)
    sv0 = jnp.where(sv[0] > 0, sv[0], 1.0)
    planarity = jnp.where(sv[0] > 0, sv[2] / sv0, 0.0)
    collinearity = jnp.where(sv[0] > 0, sv[1] / sv0, 0.0)
    ok_pose = jnp.all(jnp.isfinite(pose.wxyz_xyz))
    too_few = count < 6
    collinear = collinearity < COLLINEARITY_THRESHOLD
    planar = planarity < PLANARITY_THRESHOLD
    result = RESULTS.where(
        nonfinite,
        RESULTS.nonfinite_observation,
        RESULTS.where(
            too_few,
            RESULTS.too_few_points,
            RESULTS.where(
                collinear,
                RESULTS.degenerate_configuration,
                RESULTS.where(
                    planar,
                    RESULTS.rank_deficient,
                    RESULTS.where(ok_pose, RESULTS.successful, RESULTS.no_valid_solution),
                ),
            ),
        ),
    )
    success = result == RESULTS.successful
    pose = where_pose(success, pose, identity_like(dtype))
    err = angular_errors(pose, X, bw)
    stats = {
        "planarity": planarity,
        "collinearity": collinearity,
        "num_valid_candidates": success.astype(jnp.int32),
        "rms_angular_error": rms(err, use),
        "rank_deficiency": jax.lax.stop_gradient(rank_deficiency),
    }
    return PoseSolution(pose=pose, result=result, stats=stats)

