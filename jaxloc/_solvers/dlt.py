r"""The paper's linear overhead-camera pose (Sec. III.A, Eq. 6).

Eq. 6 of the paper, for each world point $P_i = (X_i, Y_i, Z_i)$ seen at normalized image
coordinates $(x_i, y_i)$ (here $x_i = b_0 / b_2$, $y_i = b_1 / b_2$ from the unit bearing
$b$, i.e. the paper's $x_i / f$):

$$x_i (r_3 \cdot P_i + t_z) = r_1 \cdot P_i + t_x, \qquad
  y_i (r_3 \cdot P_i + t_z) = r_2 \cdot P_i + t_y,$$

a homogeneous linear system in the 12 entries of $[R \mid t]$ (`p_cam = R p_world + t`).
It needs $n \ge 6$ points and is rank deficient when the points are coplanar (a flat floor,
the paper's real experiment), ill conditioned when they are nearly so.
"""

import jax
import jax.numpy as jnp
import jaxlie
from jaxtyping import Array, Bool, Float

from .._core.linalg import adjugate3, jacobi_svd
from .._core.poses import project_to_so3
from .._core.results import RESULTS
from .pose_problem import (
    angular_errors,
    check_inputs,
    identity_like,
    no_alternatives,
    PoseSolution,
    rms,
    where_pose,
)


# Eq. 6 is declared rank deficient below this planarity (sigma3 / sigma1 of the centred
# points). The paper's saddle floor (radii +-8 m, 2 m triangle) has planarity ~5e-2: it is
# reported as ill conditioned through `stats` but still solved.
PLANARITY_THRESHOLD = 1e-3
# Points are declared collinear below this collinearity (sigma2 / sigma1).
COLLINEARITY_THRESHOLD = 1e-4


def _usable(X, bw, mask):
    """Which rows Eq. 6 uses: unmasked, finite and in front (`b2 > 1e-6`).

    Returns `(X, bw, x, use, nonfinite)`: the world points (m, `(n, 3)`) and unit
    bearings (`(n, 3)`) with unused rows replaced by harmless values (origin, optical
    axis), the normalized image coordinates `x = (b0 / b2, b1 / b2)` `(n, 2)`, the used
    rows `(n,)` and whether an unmasked row holds NaN/inf.
    """
    finite = jnp.all(jnp.isfinite(X), axis=1) & jnp.all(jnp.isfinite(bw), axis=1)
    nonfinite = jnp.any(mask & ~finite)
    front = bw[:, 2] > 1e-6
    use = mask & finite & front
    X = jnp.where(use[:, None], X, 0.0)
    bw = jnp.where(use[:, None], bw, jnp.array([[0.0, 0.0, 1.0]], dtype=X.dtype))
    x = bw[:, :2] / bw[:, 2:3]
    return X, bw, x, use, nonfinite


def _hartley_normalization(pts, w, safe_count, mean_distance):
    """Centroid `(d,)` and scale of the weighted points `pts` `(n, d)` that bring their
    mean distance to the centroid to `mean_distance` (Hartley)."""
    tiny = jnp.finfo(pts.dtype).tiny
    centre = jnp.sum(w[:, None] * pts, axis=0) / safe_count
    dist = jnp.sqrt(jnp.sum((pts - centre[None]) ** 2, axis=1) + tiny)
    return centre, mean_distance / jnp.maximum(jnp.sum(w * dist) / safe_count, tiny)


def _eq6_null_vector(xn, Xh, w):
    r"""The null vector of Eq. 6's `2n x 12` system on normalized points, as `(3, 4)`.

    `xn`: normalized image coordinates `(n, 2)`; `Xh`: normalized homogeneous world points
    `(n, 4)`; `w`: 0/1 row weights `(n,)`. Returns `(Pn, rank_deficiency)`, the latter
    $s_{min} / s_{second}$ (1 when the null space is numerically >= 2-dimensional).
    """
    n, dtype = Xh.shape[0], Xh.dtype
    zeros4 = jnp.zeros((n, 4), dtype=dtype)
    rows_u = jnp.concatenate([Xh, zeros4, -xn[:, 0:1] * Xh], axis=1)
    rows_v = jnp.concatenate([zeros4, Xh, -xn[:, 1:2] * Xh], axis=1)
    A = jnp.concatenate([rows_u, rows_v], axis=0) * jnp.concatenate([w, w])[:, None]
    if 2 * n < 12:  # pragma: no cover - n >= 6 is enforced above
        A = jnp.concatenate([A, jnp.zeros((12 - 2 * n, 12), dtype=dtype)], axis=0)
    svals, V = jacobi_svd(A)
    # s_min / s_second; when s_second is itself at rounding level (relative to s_max) the
    # null space is numerically >= 2-dimensional: report 1.
    second_ok = svals[-2] > 100.0 * jnp.finfo(dtype).eps * svals[0]
    rank_deficiency = jnp.where(
        second_ok, svals[-1] / jnp.where(second_ok, svals[-2], 1.0), 1.0
    )
    return V[:, -1].reshape(3, 4), rank_deficiency


def _denormalize(Pn, cx, sx, cX, sX):
    """`P = T2^-1 Pn T3` `(3, 4)`: the projection matrix in the original coordinates, from
    the one of the normalized points (image centroid `cx`, scale `sx`; world `cX`, `sX`)."""
    dtype = Pn.dtype
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
    return T2inv @ Pn @ T3


def _rotation_in_front(P, X, w) -> jaxlie.SO3:
    """The rotation of the projection matrix `P` `(3, 4)`: its sign chosen so that most
    used points (`X` `(n, 3)` m, weights `w`) have positive depth, then projected onto
    SO(3)."""
    n = X.shape[0]
    depths = (jnp.concatenate([X, jnp.ones((n, 1), dtype=X.dtype)], axis=1) @ P[2]) * w
    sign = jnp.where(jnp.sum(jnp.sign(depths)) >= 0, 1.0, -1.0)
    return project_to_so3(sign * P[:, :3])


def _translation_given_rotation(Rm, X, x, w) -> Float[Array, "3"]:
    """Least-squares `t` (m) of Eq. 6 with the rotation matrix `Rm` fixed (3x3 normal
    equations): `[1, 0, -x] t = x r3.X - r1.X`, `[0, 1, -y] t = y r3.X - r2.X`, for world
    points `X` `(n, 3)`, normalized image coordinates `x` `(n, 2)`, row weights `w`."""
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
    return adj @ (At.T @ bt) / jnp.where(det != 0, det, jnp.finfo(X.dtype).tiny)


def _svd_point_spread(X, w, safe_count):
    """`(planarity, collinearity)` of the used points `X` `(n, 3)` (weights `w`) from an
    SVD: accurate to eps, unlike the closed form of `point_spread`. No gradient."""
    Xs = jax.lax.stop_gradient(X)
    Q = (Xs - jnp.sum(w[:, None] * Xs, axis=0, keepdims=True) / safe_count) * w[:, None]
    sv, _ = jacobi_svd(Q)
    sv0 = jnp.where(sv[0] > 0, sv[0], 1.0)
    planarity = jnp.where(sv[0] > 0, sv[2] / sv0, 0.0)
    collinearity = jnp.where(sv[0] > 0, sv[1] / sv0, 0.0)
    return planarity, collinearity


def _status(nonfinite, count, collinearity, planarity, pose):
    """The `RESULTS` code, the first failure in the order of the docstring."""
    ok_pose = jnp.all(jnp.isfinite(pose.wxyz_xyz))
    result = RESULTS.where(ok_pose, RESULTS.successful, RESULTS.no_valid_solution)
    result = RESULTS.where(planarity < PLANARITY_THRESHOLD, RESULTS.rank_deficient, result)
    result = RESULTS.where(
        collinearity < COLLINEARITY_THRESHOLD, RESULTS.degenerate_configuration, result
    )
    result = RESULTS.where(count < 6, RESULTS.too_few_points, result)
    return RESULTS.where(nonfinite, RESULTS.nonfinite_observation, result)


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
    X, bw, x, use, nonfinite = _usable(X, bw, mask)
    w = use.astype(dtype)
    count = jnp.sum(w)
    safe_count = jnp.maximum(count, 1.0)
    cx, sx = _hartley_normalization(x, w, safe_count, jnp.sqrt(2.0))
    cX, sX = _hartley_normalization(X, w, safe_count, jnp.sqrt(3.0))
    xn = (x - cx[None]) * sx
    Xh = jnp.concatenate([(X - cX[None]) * sX, jnp.ones((n, 1), dtype=dtype)], axis=1)
    Pn, rank_deficiency = _eq6_null_vector(xn, Xh, w)
    R = _rotation_in_front(_denormalize(Pn, cx, sx, cX, sX), X, w)
    t = _translation_given_rotation(R.as_matrix(), X, x, w)
    pose = jaxlie.SE3.from_rotation_and_translation(R, t)
    planarity, collinearity = _svd_point_spread(X, w, safe_count)
    result = _status(nonfinite, count, collinearity, planarity, pose)
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
    return PoseSolution(pose, result, stats, *no_alternatives(dtype, 0))
