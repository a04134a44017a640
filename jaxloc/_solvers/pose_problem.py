r"""The overhead camera pose problem shared by its solvers: eager input checks, the
[`jaxloc.PoseSolution`][] they return, and their diagnostics.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
from jaxtyping import Array, Bool, Float, Scalar

from .._core.numerics import as_floating
from .._core.poses import apply
from .._core.results import RESULTS


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
    - `alternatives`: other poses the solver found that fit the points, a `jaxlie.SE3` of
        batch shape `(k,)` (`T_cam_world`, unpolished; the identity where there is none),
        with `alternatives_ok` `(k,)` saying which exist. Method `"robust"` (`k = 3`):
        with exactly three usable points, every other valid P3P root (the points do not
        decide between them: `result` is then `ambiguous`); with more points and
        `runner_up=True`, in slot 0 the best-scoring candidate whose camera centre is
        more than 0.3 RMS camera-to-point distances from the returned one's (another
        local minimum, e.g. the mirror pose of nearly coplanar points: a start for a
        multi-start refinement). Method `"paper"`: `k = 0`.
    """

    pose: jaxlie.SE3
    result: RESULTS
    stats: dict[str, Array]
    alternatives: jaxlie.SE3
    alternatives_ok: Bool[Array, " k"]


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
        q = apply(pose, p)
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


def no_alternatives(dtype, k: int) -> tuple[jaxlie.SE3, Bool[Array, " k"]]:
    """`k` identity poses, none valid: a solution's empty `alternatives`."""
    return jaxlie.SE3(jnp.zeros((k, 7), dtype).at[:, 0].set(1.0)), jnp.zeros(k, bool)


def check_inputs(
    points_world, bearings, mask, *, min_points: int, name: str
) -> tuple[Float[Array, "n 3"], Float[Array, "n 3"], Bool[Array, " n"]]:
    """Eager shape validation shared by the overhead solvers (raises `ValueError`). Lists
    and integer arrays become floating point; float32 stays float32."""
    points_world = as_floating(points_world)
    bearings = as_floating(bearings)
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
