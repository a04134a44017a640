r"""Rotation and pose helpers shared by the whole toolkit.

Naming follows DESIGN §1: `T_a_b` is the pose of frame `b` expressed in frame `a`, so
`p_a = T_a_b @ p_b`, and `R_a_b` is its rotation. Poses are `jaxlie.SE3`, rotations
`jaxlie.SO3`. Every function here is written for one item; batch with `jax.vmap`.
Every function is safe under `jit`, `vmap` and `grad`: no NaN gradients at the
identity or at 180°.
"""

import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Scalar

from .linalg import max_trace_rotation
from .numerics import safe_norm


def rotation_angle(R: jaxlie.SO3) -> Scalar:
    r"""Rotation angle of `R` in radians, in $[0, \pi]$.

    Computed as $2\,\mathrm{atan2}(\|q_{xyz}\|, |q_w|)$ from the unit quaternion, which is
    accurate near 0 and near $\pi$ (unlike `acos((tr R - 1) / 2)`).
    """
    q = R.wxyz
    return 2.0 * jnp.arctan2(safe_norm(q[1:]), jnp.abs(q[0]))


def rotation_error(R_a: jaxlie.SO3, R_b: jaxlie.SO3) -> Scalar:
    """Geodesic distance between two rotations, in radians: the angle of `R_a^-1 R_b`."""
    return rotation_angle(R_a.inverse() @ R_b)


def ypr_from_rotation(R: jaxlie.SO3, *, degrees: bool = True) -> Float[Array, "3"]:
    r"""Yaw, pitch, roll (Z-Y-X intrinsic) of `R = Rz(yaw) Ry(pitch) Rx(roll)`.

    Degrees by default, as reports (the paper's Table I) show them; radians with
    `degrees=False`. Pitch lies in $[-90°, 90°]$; at $\pm 90°$ (gimbal lock) yaw and roll
    are not unique.
    """
    rpy = R.as_rpy_radians()
    ypr = jnp.stack([rpy.yaw, rpy.pitch, rpy.roll])
    return jnp.rad2deg(ypr) if degrees else ypr


def rotation_from_ypr(ypr: Float[ArrayLike, "3"], *, degrees: bool = True) -> jaxlie.SO3:
    """Inverse of [`jaxloc.ypr_from_rotation`][]: `Rz(yaw) Ry(pitch) Rx(roll)`."""
    ypr = jnp.asarray(ypr)
    if ypr.shape != (3,):
        raise ValueError(f"`ypr` must have shape (3,); got shape {ypr.shape}.")
    if degrees:
        ypr = jnp.deg2rad(ypr)
    return jaxlie.SO3.from_rpy_radians(roll=ypr[2], pitch=ypr[1], yaw=ypr[0])


def kabsch(
    a: Float[Array, "n 3"],
    b: Float[Array, "n 3"],
    weights: Float[Array, " n"] | None = None,
) -> jaxlie.SO3:
    r"""Weighted Kabsch/Procrustes: the rotation $R$ minimising $\sum_i w_i \|R a_i - b_i\|^2$.

    Solved with the SVD of $H = \sum_i w_i b_i a_i^T = U S V^T$ as
    $R = U \,\mathrm{diag}(1, 1, \det(U V^T))\, V^T$ (a LAPACK-free Jacobi SVD,
    `jaxloc._linalg`), which is always a proper rotation and
    is well defined with only two vector pairs (where the paper's Eq. 5,
    $(M^T M)^{-1/2} M^T$, does not exist because $M$ has rank 2).

    **Arguments:**

    - `a`: vectors in the source frame, shape `(n, 3)`, `n >= 2`.
    - `b`: the same vectors in the target frame, shape `(n, 3)`.
    - `weights`: non-negative weights, shape `(n,)`; all ones if omitted.

    **Returns:** `R_b_a` as a `jaxlie.SO3`, mapping `a`-frame vectors into the `b` frame.
    """
    if a.ndim != 2 or a.shape[-1] != 3 or a.shape != b.shape:
        raise ValueError(
            f"`a` and `b` must both have shape (n, 3); got {a.shape} and {b.shape}."
        )
    if a.shape[0] < 2:
        raise ValueError(f"`kabsch` needs at least 2 vector pairs; got {a.shape[0]}.")
    if weights is None:
        weights = jnp.ones(a.shape[0], dtype=a.dtype)
    H = jnp.einsum("n,ni,nj->ij", weights, b, a)
    return jaxlie.SO3.from_matrix(max_trace_rotation(H))


def project_to_so3(M: Float[Array, "3 3"]) -> jaxlie.SO3:
    """Nearest rotation to a 3x3 matrix in the Frobenius norm (polar factor, det fixed)."""
    return jaxlie.SO3.from_matrix(max_trace_rotation(M))


def pose_to_opencv(T_cam_world: jaxlie.SE3) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
    """OpenCV `(rvec, tvec)` of a pose: `p_cam = Rodrigues(rvec) @ p_world + tvec`."""
    return T_cam_world.rotation().log(), T_cam_world.translation()


def pose_from_opencv(
    rvec: Float[ArrayLike, "3"], tvec: Float[ArrayLike, "3"]
) -> jaxlie.SE3:
    """Inverse of [`jaxloc.pose_to_opencv`][]: the pose `T_cam_world` from `(rvec, tvec)`.

    Accepts the `(3,)` or `(3, 1)` arrays that OpenCV returns.
    """
    rvec = jnp.reshape(jnp.asarray(rvec), (-1,))
    tvec = jnp.reshape(jnp.asarray(tvec), (-1,))
    if rvec.shape != (3,) or tvec.shape != (3,):
        raise ValueError(
            f"`rvec` and `tvec` must have 3 elements; got shapes {rvec.shape} and {tvec.shape}."
        )
    return jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.exp(rvec), tvec)


def position_error(p_a: Float[Array, "3"], p_b: Float[Array, "3"]) -> Scalar:
    """Euclidean distance between two positions (m), with a finite gradient at zero."""
    return safe_norm(p_a - p_b)




# R_ij = sum_ab _QUAT_TO_MATRIX[i, j, a, b] q_a q_b / |q|^2 for q = (w, x, y, z): the
# rotation matrix as one constant bilinear form (a few fused kernels, where building it
# entry by entry is a stack of nine scalars).
_QUAT_TO_MATRIX = np.zeros((3, 3, 4, 4))
for _i, _j, _terms in [
    (0, 0, [(0, 0, 1), (1, 1, 1), (2, 2, -1), (3, 3, -1)]),
    (1, 1, [(0, 0, 1), (1, 1, -1), (2, 2, 1), (3, 3, -1)]),
    (2, 2, [(0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, 1)]),
    (0, 1, [(1, 2, 2), (0, 3, -2)]), (1, 0, [(1, 2, 2), (0, 3, 2)]),
    (0, 2, [(1, 3, 2), (0, 2, 2)]), (2, 0, [(1, 3, 2), (0, 2, -2)]),
    (1, 2, [(2, 3, 2), (0, 1, -2)]), (2, 1, [(2, 3, 2), (0, 1, 2)]),
]:
    for _a, _b, _c in _terms:
        _QUAT_TO_MATRIX[_i, _j, _a, _b] = _c
# (p q)_i = sum_ab _HAMILTON[i, a, b] p_a q_b, the quaternion product (w, x, y, z).
_HAMILTON = np.zeros((4, 4, 4))
for _i, _a, _b, _c in [
    (0, 0, 0, 1), (0, 1, 1, -1), (0, 2, 2, -1), (0, 3, 3, -1),
    (1, 0, 1, 1), (1, 1, 0, 1), (1, 2, 3, 1), (1, 3, 2, -1),
    (2, 0, 2, 1), (2, 2, 0, 1), (2, 3, 1, 1), (2, 1, 3, -1),
    (3, 0, 3, 1), (3, 3, 0, 1), (3, 1, 2, 1), (3, 2, 1, -1),
]:
    _HAMILTON[_i, _a, _b] = _c


def quaternion_matrix(wxyz: Float[Array, "*b 4"]) -> Float[Array, "*b 3 3"]:
    """Rotation matrices of quaternions `wxyz` (any leading shape; normalized here), in
    their dtype: `jaxlie.SO3(wxyz).as_matrix()` as one bilinear form."""
    q = jnp.asarray(wxyz)
    C = jnp.asarray(_QUAT_TO_MATRIX, q.dtype).reshape((1,) * (q.ndim - 1) + (3, 3, 4, 4))
    outer = q[..., :, None] * q[..., None, :]
    R = jnp.sum(C * outer[..., None, None, :, :], axis=(-2, -1))
    return R / jnp.sum(q * q, axis=-1)[..., None, None]


def _rplus_wxyz_xyz(params: Float[Array, "7"], delta: Float[Array, "6"]) -> Float[Array, "7"]:
    """`params exp(delta)` on `wxyz_xyz`, `delta = (v, omega)` (jaxlie's SE(3) tangent),
    with SE(3)'s exponential written out (Taylor series below `theta^2 = 1e-6`, safe
    gradients at 0)."""
    dtype = params.dtype
    delta = delta.astype(dtype)
    v, w = delta[:3], delta[3:]
    theta2 = jnp.sum(w * w)
    small = theta2 < 1e-6
    t2 = jnp.where(small, 1.0, theta2)
    theta = jnp.sqrt(t2)
    half_sin = jnp.where(small, 0.5 - theta2 / 48.0, jnp.sin(0.5 * theta) / theta)
    q_delta = jnp.concatenate([jnp.where(small, 1.0 - theta2 / 8.0, jnp.cos(0.5 * theta))[None],
                               half_sin * w])  # fmt: skip
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / t2)
    c = jnp.where(small, 1.0 / 6.0 - theta2 / 120.0, (theta - jnp.sin(theta)) / (t2 * theta))
    wv = jnp.cross(w, v)
    t_delta = v + b * wv + c * jnp.cross(w, wv)
    q = params[:4]
    H = jnp.asarray(_HAMILTON, dtype)
    q_new = jnp.sum(H * q[None, :, None] * q_delta[None, None, :], axis=(1, 2))
    t_new = params[4:] + jnp.sum(quaternion_matrix(q) * t_delta[None, :], axis=-1)
    return jnp.concatenate([q_new, t_new])


def rplus(T: jaxlie.SE3, delta: Float[Array, "6"]) -> jaxlie.SE3:
    """`T exp(delta)` (jaxlie's right perturbation `jaxlie.manifold.rplus`, `delta = (v,
    omega)`), in `T`'s dtype (jaxlie's own `exp` returns float64 under x64 even for
    float32 input)."""
    return jaxlie.SE3(_rplus_wxyz_xyz(T.wxyz_xyz, jnp.asarray(delta)))


def rplus_params(params: Float[Array, "7"], delta: Float[Array, "6"]) -> Float[Array, "7"]:
    """[`rplus`][] on `wxyz_xyz` parameters: a retraction for
    `jaxloc._core.least_squares.levenberg_marquardt` over one pose."""
    return _rplus_wxyz_xyz(params, jnp.asarray(delta))


def identity_params(dtype) -> Float[Array, "7"]:
    """`wxyz_xyz` of the identity pose."""
    return jnp.zeros(7, dtype).at[0].set(1.0)


def compose(T_a_b: jaxlie.SE3, T_b_c: jaxlie.SE3) -> jaxlie.SE3:
    """`T_a_b @ T_b_c` in `T_a_b`'s dtype (jaxlie's product computes in the default
    float: float64 under x64, even for float32 poses)."""
    dtype = T_a_b.wxyz_xyz.dtype
    return jaxlie.SE3((T_a_b @ T_b_c).wxyz_xyz.astype(dtype))


def inverse(T: jaxlie.SE3) -> jaxlie.SE3:
    """`T^-1` in `T`'s dtype."""
    return jaxlie.SE3(T.inverse().wxyz_xyz.astype(T.wxyz_xyz.dtype))


def apply(T: jaxlie.SE3, p: Float[Array, "3"]) -> Float[Array, "3"]:
    """`T @ p` in `T`'s dtype."""
    return (T @ p).astype(T.wxyz_xyz.dtype)
