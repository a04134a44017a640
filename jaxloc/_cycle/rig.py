r"""The team's sensors as calibrated: the [`jaxloc.Rig`][].

A rig is everything the solvers need to know about the robots' hardware, and nothing
about the world: each robot's camera (any camera model, distortion included), the
camera's mount in the robot's body frame, each ground robot's marker (the point the
other cameras see) in its body frame, and each camera's pixel noise. The simulator
([`jaxloc.Scenario`][] holds a rig and the world) and the image front end (the rig is
built from the team's calibration files) produce the same rig, so a real robot's
calibrated cameras enter the refinement, the covariance and the bound exactly.

Robots, here and in every per-robot array, in the order of `jaxloc.CAMERAS`:
C (the climbing robot, index 0), then the ground robots C1, C2, C3.
"""

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._cameras.models import AbstractCamera
from .._cameras.presets import (
    paper_omni_camera,
    paper_overhead_camera,
    paper_ptz_camera,
    R_BODY_OMNI,
    R_BODY_OVERHEAD,
    R_BODY_PTZ,
)
from .._core.poses import quaternion_matrix


#: Pixel noise models: `"paper"`, an offset of radius ~ N(0, sigma) in a uniformly random
#: direction (the paper's Sec. IV.A); `"gaussian"`, N(0, sigma^2) on each pixel axis.
NOISE_MODELS = ("paper", "gaussian")
#: Smallest per-axis pixel sigma (px) the refinement, covariance and bound use: the
#: weight of a noise-free rig's pixels.
PIXEL_SIGMA_FLOOR = 1e-6


def _float_array(x: Any, dtype=None) -> Array:
    x = jnp.asarray(x)
    if dtype is not None:
        return x.astype(dtype)
    return x if jnp.issubdtype(x.dtype, jnp.inexact) else x.astype(float)


def _is_concrete(x: Any) -> bool:
    return not isinstance(x, jax.core.Tracer)


def mount_pose(
    R_body_camera: Float[ArrayLike, "3 3"], t_body_camera=(0.0, 0.0, 0.0), dtype=None
) -> Float[Array, "7"]:
    """`wxyz_xyz` of a camera mount from its rotation matrix and translation (m), in
    `dtype` (default: the default float)."""
    dtype = jnp.result_type(float) if dtype is None else dtype
    R = jnp.asarray(np.asarray(R_body_camera), dtype=dtype)
    t = jnp.asarray(np.asarray(t_body_camera), dtype=dtype)
    return jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.from_matrix(R), t).wxyz_xyz


class Rig(eqx.Module):
    r"""The team's cameras exactly as calibrated, their mounts, the markers and the noise.

    **Fields:**

    - `overhead`, `ptz`, `omni2`, `omni3`: the camera models of C, C1, C2 and C3 (any
      [`jaxloc.AbstractCamera`][]: C1's may be a [`jaxloc.PTZCamera`][] or the pinhole it
      was calibrated as, distortion included).
    - `mounts`: `T_body_camera` of each robot's camera (C, C1, C2, C3) as `wxyz_xyz`,
      shape `(4, 7)`: `p_body = T_body_camera @ p_camera`. The camera's frame is the one
      its model projects from (the PTZ's base frame; the omni camera's mirror frame).
    - `markers`: each robot's marker, the point the other cameras see, in its body frame
      (m), shape `(4, 3)`; C's row is unused (nobody sees C). Zero puts the marker at the
      body origin.
    - `pixel_sigma`: each camera's pixel noise scale (px), shape `(4,)`; its meaning is
      set by `noise_model`. Zero means noise-free pixels (a simulation's exactness
      tests): the refinement then weighs them as 1e-6 px (`PIXEL_SIGMA_FLOOR`).
    - `noise_model` (static): `"paper"` (radius ~ N(0, sigma), uniform direction, so each
      axis has standard deviation `sigma / sqrt(2)`) or `"gaussian"` (N(0, sigma^2) per
      axis).

    The paper's robots ([`jaxloc.Rig.paper`][]) have every camera centre at its robot's
    body origin, which is also its marker.
    """

    overhead: AbstractCamera
    ptz: AbstractCamera
    omni2: AbstractCamera
    omni3: AbstractCamera
    mounts: Float[Array, "4 7"]
    markers: Float[Array, "4 3"]
    pixel_sigma: Float[Array, "4"]
    noise_model: str = eqx.field(static=True)

    def __init__(
        self,
        overhead: AbstractCamera,
        ptz: AbstractCamera,
        omni2: AbstractCamera,
        omni3: AbstractCamera,
        mounts: Float[ArrayLike, "4 7"] | None = None,
        markers: Float[ArrayLike, "4 3"] | None = None,
        pixel_sigma: Float[ArrayLike, "4"] | Float[ArrayLike, ""] = 2.0,
        noise_model: str = "paper",
    ):
        """**Arguments:** the fields above. `mounts` defaults to the paper's mounts
        (`R_BODY_OVERHEAD`, `R_BODY_PTZ`, `R_BODY_OMNI` twice, no offsets), `markers` to
        zeros, and a scalar `pixel_sigma` is used for every camera."""
        self.overhead, self.ptz, self.omni2, self.omni3 = overhead, ptz, omni2, omni3
        dtype = jnp.result_type(*[x for x in jax.tree.leaves(overhead) if eqx.is_inexact_array(x)])
        if mounts is None:
            mounts = jnp.stack([
                mount_pose(R, dtype=dtype)
                for R in (R_BODY_OVERHEAD, R_BODY_PTZ, R_BODY_OMNI, R_BODY_OMNI)
            ])
        self.mounts = _float_array(mounts)
        self.markers = _float_array(jnp.zeros((4, 3), dtype) if markers is None else markers)
        sigma = _float_array(pixel_sigma)
        self.pixel_sigma = jnp.broadcast_to(sigma, (4,)) if sigma.ndim == 0 else sigma
        self.noise_model = noise_model

    def __check_init__(self):
        for name in ("overhead", "ptz", "omni2", "omni3"):
            cam = getattr(self, name)
            if not isinstance(cam, AbstractCamera):
                raise ValueError(
                    f"`Rig({name}=...)` must be a camera model (an AbstractCamera); got "
                    f"{type(cam).__name__}."
                )
        if self.noise_model not in NOISE_MODELS:
            raise ValueError(
                f"`Rig(noise_model=...)` must be one of {NOISE_MODELS}; got {self.noise_model!r}."
            )
        for name, shape in (("mounts", (4, 7)), ("markers", (4, 3)), ("pixel_sigma", (4,))):
            x = getattr(self, name)
            if x.shape[x.ndim - len(shape):] != shape:
                raise ValueError(f"`Rig({name}=...)` must have shape {shape}; got {x.shape}.")
            if _is_concrete(x) and not np.all(np.isfinite(np.asarray(x))):
                raise ValueError(f"`Rig({name}=...)` must be finite; got {np.asarray(x)}.")
        s = self.pixel_sigma
        if _is_concrete(s) and not np.all(np.asarray(s) >= 0):
            raise ValueError(
                f"`Rig(pixel_sigma=...)` must be non-negative (px); got {np.asarray(s)}."
            )
        q = self.mounts[..., :4]
        if _is_concrete(q):
            norm = np.linalg.norm(np.asarray(q, np.float64), axis=-1)
            if not np.allclose(norm, 1.0, atol=1e-4):
                raise ValueError(
                    "`Rig(mounts=...)` must hold unit quaternions in columns 0-3 (wxyz); got "
                    f"norms {norm}."
                )

    @classmethod
    def paper(
        cls, pixel_sigma: Float[ArrayLike, ""] = 2.0, noise_model: str = "paper"
    ) -> "Rig":
        """The paper's robots: its four nominal cameras ([`jaxloc.paper_overhead_camera`][],
        [`jaxloc.paper_ptz_camera`][] at the wide end, [`jaxloc.paper_omni_camera`][]
        twice), the mounts `R_BODY_*` with every camera centre at its body origin, the
        markers there too, and 2 px of the paper's pixel noise."""
        return cls(
            paper_overhead_camera(), paper_ptz_camera(), paper_omni_camera(),
            paper_omni_camera(), pixel_sigma=pixel_sigma, noise_model=noise_model,
        )  # fmt: skip

    @property
    def cameras(self) -> tuple[AbstractCamera, AbstractCamera, AbstractCamera, AbstractCamera]:
        """The four cameras in robot order (C, C1, C2, C3)."""
        return (self.overhead, self.ptz, self.omni2, self.omni3)

    @property
    def dtype(self):
        """The floating-point dtype of the rig's arrays."""
        return self.mounts.dtype

    def mount_rotations(self) -> Float[Array, "4 3 3"]:
        """`R_body_camera` of every camera as matrices, shape `(4, 3, 3)`."""
        return quaternion_matrix(self.mounts[:, :4])

    def mount_translations(self) -> Float[Array, "4 3"]:
        """Each camera centre in its robot's body frame (m), shape `(4, 3)`."""
        return self.mounts[:, 4:]

    def sigma_per_axis(self) -> Float[Array, "4"]:
        """Standard deviation (px) of each pixel coordinate of each camera: `pixel_sigma /
        sqrt(2)` for the paper's model (`E|n|^2 = sigma^2` split over two axes),
        `pixel_sigma` for Gaussian noise."""
        if self.noise_model == "paper":
            return self.pixel_sigma / math.sqrt(2.0)
        return self.pixel_sigma

    def sigma_text(self) -> str:
        """The pixel sigma for a report (px, eager): one number, or one per camera."""
        sigma = np.asarray(self.pixel_sigma, dtype=np.float64)
        if np.all(sigma == sigma[0]):
            return f"{sigma[0]:g}"
        return "/".join(f"{s:g}" for s in sigma) + " (C/C1/C2/C3)"

    @property
    def has_offsets(self) -> bool:
        """Whether any camera centre or marker is away from its body origin (eager)."""
        t = np.asarray(self.mounts[:, 4:])
        m = np.asarray(self.markers[1:])
        return bool(np.any(t != 0) or np.any(m != 0))


def ground_cameras_apply(rig: Rig, fn, x):
    """`fn(camera_i, x[i])` for the ground robots' cameras (C1's `ptz`, `omni2`, `omni3`),
    outputs stacked on a new leading axis of size 3.

    `x` is any pytree whose leaves have a leading axis of size 3 (the observer). C2's and
    C3's cameras run as one `vmap`-ed call when their structure (model and static
    configuration) is the same: one traced copy instead of two, a smaller program."""
    first = fn(rig.ptz, jax.tree.map(lambda a: a[0], x))
    a, b = rig.omni2, rig.omni3
    rest = jax.tree.map(lambda v: v[1:], x)
    if jax.tree.structure(a) == jax.tree.structure(b):
        pair = jax.tree.map(lambda u, v: jnp.stack([u, v]), a, b)
        others = jax.vmap(fn)(pair, rest)
    else:
        outs = [fn(cam, jax.tree.map(lambda v, i=i: v[i], rest)) for i, cam in enumerate((a, b))]
        others = jax.tree.map(lambda *v: jnp.stack(v), *outs)
    return jax.tree.map(lambda u, v: jnp.concatenate([u[None], v]), first, others)
