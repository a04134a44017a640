r"""The one projection path: robot `j`'s marker seen by robot `i`'s camera, through its mount.

Every part of jaxloc that predicts a sighting (the simulator, the measurement model of the
refinement, the covariance and the bound, formation design, rendering) goes through
these functions, so that a mount or a marker offset means the same everywhere.

Poses are rotation matrices and positions (columns of `R_world_body` are the body axes in
the world frame; `p_world_body` its origin), written element-wise so that they broadcast
over leading batch axes and fuse under `vmap`. With a robot at `(R, p)`, its camera mount
`(R_m, t_m)` (`p_body = R_m p_camera + t_m`) and a marker `m` in a target's body frame:

$$x = p_j + R_j m_j, \qquad x_\text{camera} = R_m^\top \big(R_i^\top (x - p_i) - t_m\big).$$

Derivatives are with respect to jaxlie's right perturbation `T exp(delta)`,
`delta = (v, omega)`, of each pose: the observer's moves the point by
`R_m^T (-v + [q]x omega)` (`q = R_i^T (x - p_i)`), the target's by
`R_m^T R_i^T R_j (v - [m_j]x omega)`.
"""

import functools as ft

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


def _same_rank(*xs):
    """The arrays with leading axes of size 1 added so that all have the same rank
    (explicit, so that it holds under `jax_numpy_rank_promotion="raise"`)."""
    n = max(x.ndim for x in xs)
    return [x.reshape((1,) * (n - x.ndim) + x.shape) for x in xs]


def _contract(a: Array, b: Array, axis_a: int, axis_b: int) -> Array:
    """`sum_k a[..k..] * b[..k..]` over a small static axis, written out as products and
    sums (no `reduce`: XLA fuses it into the surrounding element-wise loop)."""
    n = a.shape[axis_a]
    terms = [
        jnp.take(a, k, axis=axis_a) * jnp.take(b, k, axis=axis_b) for k in range(n)
    ]
    return ft.reduce(lambda x, y: x + y, terms)


def matvec_t(R: Float[Array, "*b 3 3"], x: Float[Array, "*b 3"]) -> Float[Array, "*b 3"]:
    """`R^T x`, element-wise (broadcasts over leading axes; no `dot`)."""
    R, x = _same_rank(R, x[..., :, None])
    return _contract(R, x, -2, -2)


def matvec(R: Float[Array, "*b 3 3"], x: Float[Array, "*b 3"]) -> Float[Array, "*b 3"]:
    """`R x`, element-wise (broadcasts over leading axes; no `dot`)."""
    R, x = _same_rank(R, x[..., None, :])
    return _contract(R, x, -1, -1)


def matmul(a: Float[Array, "*b x y"], b: Float[Array, "*b y z"]) -> Float[Array, "*b x z"]:
    """Batched small matrix product, element-wise: XLA's CPU `dot` kernels are slow on
    tiny batched shapes, element-wise products fuse. Broadcasts over leading axes."""
    a, b = _same_rank(a[..., :, :, None], b[..., None, :, :])
    return _contract(a, b, -2, -2)


def skew(a: Float[Array, "*b 3"]) -> Float[Array, "*b 3 3"]:
    """`[a]x`, the matrix with `[a]x w = a x w`."""
    z = jnp.zeros_like(a[..., 0])
    return jnp.stack(
        [
            jnp.stack([z, -a[..., 2], a[..., 1]], -1),
            jnp.stack([a[..., 2], z, -a[..., 0]], -1),
            jnp.stack([-a[..., 1], a[..., 0], z], -1),
        ],
        -2,
    )


def marker_in_world(
    R_world_body: Float[Array, "*b 3 3"],
    p_world_body: Float[Array, "*b 3"],
    marker: Float[Array, "*b 3"],
) -> Float[Array, "*b 3"]:
    """A robot's marker in the world frame: `p + R m` (m)."""
    p, Rm = _same_rank(p_world_body, matvec(R_world_body, marker))
    return p + Rm


def in_body(
    R_world_body: Float[Array, "*b 3 3"],
    p_world_body: Float[Array, "*b 3"],
    x_world: Float[Array, "*b 3"],
) -> Float[Array, "*b 3"]:
    """A world point in a body frame: `R^T (x - p)`."""
    x, p = _same_rank(x_world, p_world_body)
    return matvec_t(R_world_body, x - p)


def body_to_camera(
    R_body_camera: Float[Array, "*b 3 3"],
    t_body_camera: Float[Array, "*b 3"],
    q_body: Float[Array, "*b 3"],
) -> Float[Array, "*b 3"]:
    """A body-frame point in the camera mounted there: `R_m^T (q - t_m)`."""
    q, t = _same_rank(q_body, t_body_camera)
    return matvec_t(R_body_camera, q - t)


def mutual_points(
    R: Float[Array, "*s 3 3 3"],
    p: Float[Array, "*s 3 3"],
    mount_R: Float[Array, "3 3 3"],
    mount_t: Float[Array, "3 3"],
    markers: Float[Array, "3 3"],
):
    """Every ground robot's marker in every ground robot's camera frame.

    **Arguments:** body rotations `R` `(*s, 3, 3, 3)` and positions `p` `(*s, 3, 3)` of
    C1, C2, C3 in a common frame; their cameras' mounts (`(3, 3, 3)`, `(3, 3)`) and
    markers `(3, 3)` (the rig's rows 1-3).

    **Returns:** `(x_cam, q_body)`, both `(*s, 3, 3, 3)`: `[..., i, j, :]` is robot `j`'s
    marker in robot `i`'s camera frame and in its body frame. The diagonal `i == j` is a
    dummy point one metre ahead of the camera along its body x axis (finite; callers
    mask it out).
    """
    x = marker_in_world(R, p, markers)  # (*s, 3, 3): markers in the common frame
    q = in_body(R[..., :, None, :, :], p[..., :, None, :], x[..., None, :, :])
    eye = np.eye(3, dtype=bool)[:, :, None]
    ahead = mount_t[:, None, :] + jnp.asarray([[[1.0, 0.0, 0.0]]], q.dtype)
    eye, ahead = _same_rank(eye, jnp.broadcast_to(ahead, (3, 3, 3)))
    q = jnp.where(eye, jnp.broadcast_to(ahead, q.shape), q)
    return body_to_camera(mount_R[:, None], mount_t[:, None], q), q


def observer_jacobian(
    mount_R: Float[Array, "*b 3 3"], q_body: Float[Array, "*b 3"]
) -> Float[Array, "*b 3 6"]:
    """`d x_camera / d delta` of the observing robot's body pose: `R_m^T [-I, [q]x]`."""
    eye = jnp.broadcast_to(jnp.eye(3, dtype=q_body.dtype), q_body.shape + (3,))
    block = jnp.concatenate([-eye, skew(q_body)], axis=-1)
    return matmul(jnp.swapaxes(mount_R, -1, -2), block)


def target_jacobian(
    A: Float[Array, "*b 3 3"], marker: Float[Array, "*b 3"]
) -> Float[Array, "*b 3 6"]:
    """`d x_camera / d delta` of a sighted robot's body pose, given `A = d x_camera /
    d x_world R_j` (e.g. `R_m^T R_i^T R_j`): `A [I, -[m]x]`."""
    A_m = -matmul(A, skew(marker))
    A = jnp.broadcast_to(A, A_m.shape)
    return jnp.concatenate([A, A_m], axis=-1)


def camera_pose_jacobian(x_camera: Float[Array, "*b 3"]) -> Float[Array, "*b 3 6"]:
    """`d x_camera / d delta` of the camera's own pose (no mount: the camera frame is the
    pose's frame): `[-I, [x]x]`."""
    return observer_jacobian(
        jnp.broadcast_to(jnp.eye(3, dtype=x_camera.dtype), x_camera.shape + (3,)), x_camera
    )
