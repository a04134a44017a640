r"""First-order covariances of poses, as tracking moves them between frames.

Every covariance here is that of jaxlie's right perturbation: an estimate `T_hat = T
exp(delta)`, `delta = (v, omega)`, with `cov(delta)` a `(6, 6)` matrix (m^2, m rad, rad^2
blocks) in the pose's own body frame (DESIGN §1; the tangent of
[`jaxloc.refine_cycle`][]'s covariance). Composition moves an error by the adjoint:
`T_a exp(xi) T_b = T_a T_b exp(Ad(T_b^-1) xi)`, so chaining two independent errors adds
`Ad(T_b^-1) cov(xi) Ad(T_b^-1)^T` to `cov(delta_b)`. A world-frame position covariance is
`R cov(v) R^T` (the translation of `T exp(delta)` moves by `R v` to first order).
"""

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Float

from .._core.numerics import safe_norm, safe_normalize
from .._core.poses import compose, inverse, quaternion_matrix
from .._cycle.layout import placement_ids


def adjoint(T: Float[Array, "7"]) -> Float[Array, "6 6"]:
    """`Ad(T)` of a `wxyz_xyz` pose, for jaxlie's `(v, omega)` tangent ordering:
    `T exp(xi) T^-1 = exp(Ad(T) xi)`."""
    return jaxlie.SE3(T).adjoint().astype(T.dtype)


def transport(T: Float[Array, "7"], cov: Float[Array, "6 6"]) -> Float[Array, "6 6"]:
    """`Ad(T) cov Ad(T)^T`."""
    A = adjoint(T)
    return A @ cov @ A.T


def position_covariance(T: Float[Array, "7"], cov: Float[Array, "6 6"]) -> Float[Array, "3 3"]:
    """World-frame position covariance (m^2) of a pose `T` with right-perturbation
    covariance `cov`: `R cov_vv R^T`."""
    R = quaternion_matrix(T[:4])
    return R @ cov[:3, :3] @ R.T


def rotation_covariance(cov: Float[Array, "6 6"]) -> Float[Array, "3 3"]:
    """The rotation block `cov_omega` (rad^2) of a right-perturbation covariance."""
    return cov[3:, 3:]


def plane_normal(points: Float[Array, "3 3"], up: Float[Array, "3"]) -> Float[Array, "3"]:
    """Unit normal of the plane of three points, on the side of `up`."""
    n = safe_normalize(jnp.cross(points[1] - points[0], points[2] - points[0]))
    return jnp.where(jnp.sum(n * up) >= 0, n, -n)


def perimeter(p: Float[Array, "3 3"]) -> Float[Array, ""]:
    """Perimeter of the triangle of three points (m)."""
    return jnp.sum(safe_norm(p[jnp.array([1, 2, 2])] - p[jnp.array([0, 0, 1])]))


def body_of_overhead(T_over: Float[Array, "7"], mount: Float[Array, "7"]) -> Float[Array, "7"]:
    """The climbing robot's body pose from its camera's optical-frame pose:
    `T_world_body = T_world_camera @ T_body_camera^-1` (`mount` = the rig's `mounts[0]`)."""
    M = jaxlie.SE3(mount.astype(T_over.dtype))
    return compose(jaxlie.SE3(T_over), inverse(M)).wxyz_xyz


def overhead_of_body(T_body: Float[Array, "7"], mount: Float[Array, "7"]) -> Float[Array, "7"]:
    """Inverse of [`body_of_overhead`][]: `T_world_camera = T_world_body @ T_body_camera`."""
    return compose(jaxlie.SE3(T_body), jaxlie.SE3(mount.astype(T_body.dtype))).wxyz_xyz


def end_selection(strategy: str) -> np.ndarray:
    """Which tangent blocks of a cycle's covariance ([`jaxloc.CycleCovariance`][]`.tangent`:
    placements 1, 2, ... then the overhead camera) are the end-of-cycle poses of (C, C1, C2,
    C3), as a `(4, 6, n)` 0/1 matrix: C's is the overhead camera's (optical) block; a robot
    whose end placement is placement 0 (the gauge: the concurrent strategy's C1) gets zeros."""
    ids = placement_ids(strategy)
    P = int(ids.max()) + 1
    n = 6 * P
    S = np.zeros((4, 6, n))
    S[0, :, n - 6 :] = np.eye(6)
    for r in range(3):
        p = int(ids[-1, r])
        if p > 0:
            S[r + 1, :, 6 * (p - 1) : 6 * p] = np.eye(6)
    return S


def end_covariance(
    tangent: Float[Array, "n n"], strategy: str, mount: Float[Array, "7"]
) -> Float[Array, "24 24"]:
    """Joint right-perturbation covariance of the end-of-cycle body poses of (C, C1, C2,
    C3) from a cycle's tangent covariance, `(24, 24)`: C's optical-frame block turned
    into its body's (`T_body = T_over M^-1`, so `delta_body = Ad(M) delta_over`)."""
    S = jnp.asarray(end_selection(strategy), tangent.dtype).reshape(24, -1)
    A = jnp.eye(24, dtype=tangent.dtype).at[:6, :6].set(adjoint(mount.astype(tangent.dtype)))
    G = A @ S
    return G @ tangent @ G.T


def blocks(joint: Float[Array, "24 24"]) -> Float[Array, "4 6 6"]:
    """The four diagonal `(6, 6)` blocks of a joint covariance of four poses."""
    return jnp.stack([joint[6 * i : 6 * i + 6, 6 * i : 6 * i + 6] for i in range(4)])


def pose_covariances(
    poses: Float[Array, "4 7"], cov: Float[Array, "4 6 6"]
) -> tuple[Float[Array, "4 3 3"], Float[Array, "4 3 3"]]:
    """World position (m^2) and rotation (rad^2) covariances of four poses."""
    pos = jax.vmap(position_covariance)(poses, cov)
    return pos, jax.vmap(rotation_covariance)(cov)


# --------------------------------------------------------------------------------------
# Rotation matrices without quaternions: the one-step update's latency-critical path
# (jaxlie's `SO3.from_matrix` computes four candidate quaternions and selects one; its
# `log` and `exp` go through quaternions; each costs several fused kernels per call).


def so3_exp(w: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """`exp([w]x)` by Rodrigues' formula (Taylor terms below 1e-4 rad)."""
    t2 = jnp.sum(w * w)
    small = t2 < 1e-8
    t = jnp.sqrt(jnp.where(small, 1.0, t2))
    a = jnp.where(small, 1.0 - t2 / 6.0, jnp.sin(t) / t)
    b = jnp.where(small, 0.5 - t2 / 24.0, (1.0 - jnp.cos(t)) / jnp.where(small, 1.0, t2))
    K = _skew(w)
    return jnp.eye(3, dtype=w.dtype) + a * K + b * (K @ K)


def so3_log(R: Float[Array, "3 3"]) -> Float[Array, "3"]:
    """`w` with `exp([w]x) = R`, `|w|` in `[0, pi]`: the angle from `atan2` of the
    antisymmetric part's norm and the trace (accurate everywhere); the axis from the
    antisymmetric part, or near pi (where it vanishes) from the largest column of the
    symmetric part `(R + R^T)/2 - cos(t) I = (1 - cos t) a a^T`, signed by the former."""
    dtype = R.dtype
    v = 0.5 * jnp.stack([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = jnp.sqrt(jnp.sum(v * v))
    c = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    t = jnp.arctan2(s, c)
    small = s < 1e-6
    near_pi = c < 0.0
    # Away from pi: w = t v / sin t (-> v for small angles).
    w_main = jnp.where(small & ~near_pi, 1.0 + s * s / 6.0, t / jnp.where(small, 1.0, s)) * v
    B = 0.5 * (R + R.T) - c * jnp.eye(3, dtype=dtype)
    i = jnp.argmax(jnp.diagonal(B))
    col = B[:, i]
    a = col / jnp.sqrt(jnp.maximum(jnp.sum(col * col), jnp.finfo(dtype).tiny))
    a = jnp.where(jnp.sum(a * v) < 0, -a, a)
    return jnp.where(near_pi, t * a, w_main)


def so3_jr_inv(phi: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """Inverse right Jacobian of SO(3): `d log(exp([phi]x) exp([d]x)) / d d` at `d = 0`,
    `I + [phi]x / 2 + (1/t^2 - (1 + cos t) / (2 t sin t)) [phi]x^2`."""
    t2 = jnp.sum(phi * phi)
    small = t2 < 1e-8
    t = jnp.sqrt(jnp.where(small, 1.0, t2))
    coef = jnp.where(
        small, 1.0 / 12.0 + t2 / 720.0,
        1.0 / jnp.where(small, 1.0, t2) - (1.0 + jnp.cos(t)) / (2.0 * t * jnp.sin(t)),
    )  # fmt: skip
    K = _skew(phi)
    return jnp.eye(3, dtype=phi.dtype) + 0.5 * K + coef * (K @ K)


def _skew(a):
    z = jnp.zeros((), a.dtype)
    return jnp.stack([
        jnp.stack([z, -a[2], a[1]]), jnp.stack([a[2], z, -a[0]]), jnp.stack([-a[1], a[0], z])
    ])  # fmt: skip
