r"""Camera models: perspective (OpenCV pinhole + Brown--Conrady), PTZ and catadioptric
omnidirectional (Mei unified model).

Every camera is an `equinox.Module` whose parameters are array leaves (so `jax.grad`,
`jax.vmap` and `jax.jit` reach them) and whose image size is static configuration.
All methods broadcast over leading batch axes of their argument: they are written
element-wise on `p[..., 0]`, `p[..., 1]`, `p[..., 2]`, with 0-d camera parameters. To
batch over *cameras*, `jax.vmap` over the camera.

Conventions (DESIGN §1):

- Units: metres (any consistent length unit: only directions matter) and radians;
  pixels for image coordinates.
- Pixels `(u, v)`: `u` to the right, `v` down, origin at the *centre* of the top-left
  pixel (OpenCV). The image covers `-0.5 <= u <= width - 0.5`,
  `-0.5 <= v <= height - 0.5`.
- Perspective/PTZ optical frame: x right, y down, z forward (OpenCV).
- Omnidirectional camera frame: z along the mirror axis pointing up; azimuth in the
  x--y plane, elevation measured from that plane.

`project` always returns finite pixels, even for points the model cannot project
(behind the camera, at the origin, ...): validity is a separate boolean mask given by
`projectable` (the model's own condition) and `in_view` (projectable and inside the
image, and for the omnidirectional camera inside its elevation band). Singular branches
use a double `where`, so gradients are finite too.
"""

import abc
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._core.numerics import safe_sqrt


# Normalized image coordinates are saturated at this magnitude (|x|, |y| <= 1e4, i.e.
# directions within ~0.006 deg of the image plane). It keeps `project` finite in float32
# (r^6 of the distortion polynomial stays below ~1e25) for points the model cannot or
# can barely project; no real camera sees that close to 90 deg off its axis.
_MAX_NORMALIZED = 1e4

# Undistortion: OpenCV-style fixed-point iterations give a robust start (they converge
# for any realistic lens), then Newton steps on the 2-D distortion map converge
# quadratically. On the OpenCV sample calibration (k1 = -0.27, k3 = 0.24; 640x480) the
# round trip error over the whole image is 2e-13 px with 2 + 3 iterations, 2.5e-6 px with
# 10 fixed-point iterations alone; 2 + 6 leaves a margin for wide-angle lenses
# (tests/test_camera.py).
_FIXED_POINT_ITERATIONS = 2
_NEWTON_ITERATIONS = 6


# --------------------------------------------------------------------------------------
# Construction helpers (eager validation).
# --------------------------------------------------------------------------------------


def _is_inexact_array(x: Any) -> bool:
    return isinstance(x, (jax.Array, np.ndarray, np.generic)) and jnp.issubdtype(
        x.dtype, jnp.inexact
    )


def _as_float_arrays(*args: Any) -> list[Array]:
    """Cast constructor arguments to float arrays.

    Inexact arrays keep their dtype (float32 stays float32). Anything else (Python
    numbers, lists, integer arrays) becomes `jnp.asarray(x, dtype=dtype)`, where `dtype`
    is the common dtype of the inexact arrays given, or the default float (float64
    under x64) if there are none: a camera built from float32 arrays and default
    Python-number arguments is float32 throughout.
    """
    given = [x.dtype for x in args if _is_inexact_array(x)]
    dtype = jnp.result_type(*given) if given else float
    return [jnp.asarray(x) if _is_inexact_array(x) else jnp.asarray(x, dtype=dtype) for x in args]


def _is_concrete(x: Any) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _fmt(value: np.ndarray) -> str:
    return repr(float(value)) if value.ndim == 0 else np.array2string(value)


def _check_image_size(cls: str, image_size: Any) -> tuple[int, int]:
    try:
        w, h = image_size
    except (TypeError, ValueError):
        raise ValueError(
            f"`{cls}(image_size=...)` must be a pair (width, height) of positive "
            f"integers; got {image_size!r}."
        ) from None
    ok = True
    for n in (w, h):
        if isinstance(n, bool) or not isinstance(n, (int, np.integer, float, np.floating)):
            ok = False
        elif not (math.isfinite(n) and n == int(n) and n > 0):
            ok = False
    if not ok:
        raise ValueError(
            f"`{cls}(image_size=...)` must be a pair (width, height) of positive "
            f"integers; got {image_size!r}."
        )
    return int(w), int(h)


def _check_leaf(
    cls: str,
    name: str,
    x: Array,
    *,
    vector: int | None = None,
    positive: bool = False,
    nonnegative: bool = False,
    interval: tuple[float, float] | None = None,
) -> None:
    """Validate one array leaf if it is concrete (skipped under jit/vmap)."""
    if not _is_concrete(x):
        return
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise ValueError(f"`{cls}({name}=...)` must be real; got dtype {x.dtype}.")
    if vector is not None and (x.ndim < 1 or x.shape[-1] != vector):
        raise ValueError(f"`{cls}({name}=...)` must have shape ({vector},); got shape {x.shape}.")
    value = np.asarray(x)
    if not np.all(np.isfinite(value)):
        raise ValueError(f"`{cls}({name}=...)` must be finite; got {_fmt(value)}.")
    if positive and not np.all(value > 0):
        raise ValueError(f"`{cls}({name}=...)` must be positive; got {_fmt(value)}.")
    if nonnegative and not np.all(value >= 0):
        raise ValueError(f"`{cls}({name}=...)` must be non-negative; got {_fmt(value)}.")
    if interval is not None:
        lo, hi = interval
        if not np.all((value >= lo) & (value <= hi)):
            raise ValueError(
                f"`{cls}({name}=...)` must lie in [{lo:g}, {hi:g}]; got {_fmt(value)}."
            )


# --------------------------------------------------------------------------------------
# Element-wise kernels.
# --------------------------------------------------------------------------------------


def _safe_ratio(x, y, z):
    """`(x / z, y / z)` for `z > 0`, saturated at `_MAX_NORMALIZED` and finite always.

    The denominator is floored at `(|x| + |y|) / _MAX_NORMALIZED`, so directions at or
    behind 90 deg map continuously onto the saturation radius, and the origin (or a
    point on the negative axis) maps to 0. Double `where`: finite gradients everywhere.
    """
    floor = (jnp.abs(x) + jnp.abs(y)) * (1.0 / _MAX_NORMALIZED)
    zc = jnp.maximum(z, floor)
    ok = zc > 0
    safe = jnp.where(ok, zc, 1.0)
    return jnp.where(ok, x / safe, 0.0), jnp.where(ok, y / safe, 0.0)


def _normalize3(x, y, z):
    n = safe_sqrt(x * x + y * y + z * z)
    ok = n > 0
    inv = jnp.where(ok, 1.0 / jnp.where(ok, n, 1.0), 0.0)
    # The zero vector has no direction: return the optical axis (finite, unit).
    return (
        jnp.where(ok, x * inv, 0.0),
        jnp.where(ok, y * inv, 0.0),
        jnp.where(ok, z * inv, 1.0),
    )


def _distort(x, y, k1, k2, p1, p2, k3):
    """Brown--Conrady distortion, exactly as OpenCV's `projectPoints` (5 coefficients)."""
    x2, y2, xy = x * x, y * y, x * y
    r2 = x2 + y2
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2)
    yd = y * radial + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy
    return xd, yd


def _distort_jacobian(x, y, k1, k2, p1, p2, k3):
    """Distorted point and the 2x2 Jacobian of `_distort` with respect to `(x, y)`."""
    x2, y2, xy = x * x, y * y, x * y
    r2 = x2 + y2
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3)  # d radial / d r2
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2)
    yd = y * radial + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy
    j00 = radial + 2.0 * x2 * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    j01 = 2.0 * xy * dradial + 2.0 * p1 * x + 2.0 * p2 * y
    j10 = 2.0 * xy * dradial + 2.0 * p1 * x + 2.0 * p2 * y
    j11 = radial + 2.0 * y2 * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    return xd, yd, j00, j01, j10, j11


def _undistort(xd, yd, k1, k2, p1, p2, k3):
    """Invert `_distort` with a fixed number of iterations (jit-friendly, no LAPACK).

    Starts with OpenCV's fixed-point iteration (`cv::undistortPoints`):
    `x <- (x_d - tangential(x)) / radial(x)`, then Newton steps on
    `D(x) - x_d = 0` with the 2x2 Jacobian solved by Cramer's rule.
    """
    # `lax.fori_loop` (static trip count: a scan, so reverse-mode works) rather than a
    # Python loop: XLA's CPU fusion duplicates the unrolled iterations' shared
    # subexpressions when camera parameters are traced, which made a jitted unproject
    # of 100 pixels take ~50 s (measured, jax 0.10.2).

    def fixed_point(_, xy):
        x, y = xy
        x2, y2, xy_ = x * x, y * y, x * y
        r2 = x2 + y2
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        ok = jnp.abs(radial) > 1e-6
        inv = jnp.where(ok, 1.0 / jnp.where(ok, radial, 1.0), 1.0)
        dx = 2.0 * p1 * xy_ + p2 * (r2 + 2.0 * x2)
        dy = p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy_
        x_new = (xd - dx) * inv
        y_new = (yd - dy) * inv
        finite = jnp.isfinite(x_new) & jnp.isfinite(y_new)
        return jnp.where(finite, x_new, x), jnp.where(finite, y_new, y)

    def newton(_, xy):
        x, y = xy
        fx, fy, j00, j01, j10, j11 = _distort_jacobian(x, y, k1, k2, p1, p2, k3)
        rx, ry = fx - xd, fy - yd
        det = j00 * j11 - j01 * j10
        ok = jnp.abs(det) > 1e-12
        inv_det = jnp.where(ok, 1.0 / jnp.where(ok, det, 1.0), 0.0)
        x_new = x - (j11 * rx - j01 * ry) * inv_det
        y_new = y - (-j10 * rx + j00 * ry) * inv_det
        finite = jnp.isfinite(x_new) & jnp.isfinite(y_new)
        return jnp.where(finite, x_new, x), jnp.where(finite, y_new, y)

    # The carry must have a fixed dtype and shape: that of the broadcast inputs.
    xd, yd = jnp.broadcast_arrays(xd, yd)
    dtype = jnp.result_type(xd, yd, k1, k2, p1, p2, k3)
    xd, yd = xd.astype(dtype), yd.astype(dtype)
    xy = jax.lax.fori_loop(0, _FIXED_POINT_ITERATIONS, fixed_point, (xd, yd))
    x, y = jax.lax.fori_loop(0, _NEWTON_ITERATIONS, newton, xy)
    return x, y


def _inside_image(u, v, image_size: tuple[int, int]):
    w, h = image_size
    return (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)


def _check_last_axis(name: str, x: Array, n: int) -> None:
    if x.ndim < 1 or x.shape[-1] != n:
        raise ValueError(f"`{name}` must have shape (..., {n}); got shape {x.shape}.")


# --------------------------------------------------------------------------------------
# Interface.
# --------------------------------------------------------------------------------------


class AbstractCamera(eqx.Module):
    """Interface of a camera model.

    Every method broadcasts over leading batch axes `*b` of its argument.

    **Attributes:**

    - `image_size`: `(width, height)` in pixels. Static (not a pytree leaf).
    """

    image_size: eqx.AbstractVar[tuple[int, int]]

    @abc.abstractmethod
    def project(self, points_cam: Float[ArrayLike, "*b 3"]) -> Float[Array, "*b 2"]:
        """Project points given in the camera frame to pixels `(u, v)`.

        Always finite, also for points the model cannot project: check them with
        [`jaxloc.AbstractCamera.projectable`][] or [`jaxloc.AbstractCamera.in_view`][].
        """

    @abc.abstractmethod
    def unproject(self, pixels: Float[ArrayLike, "*b 2"]) -> Float[Array, "*b 3"]:
        """Unit bearing vectors, in the camera frame, of pixels `(u, v)`."""

    @abc.abstractmethod
    def projectable(self, points_cam: Float[ArrayLike, "*b 3"]) -> Bool[Array, "*b"]:
        """Whether the model can project each point (its own validity condition)."""

    @abc.abstractmethod
    def in_view(self, points_cam: Float[ArrayLike, "*b 3"]) -> Bool[Array, "*b"]:
        """Whether each point is projectable and lands inside the image (and band)."""


# --------------------------------------------------------------------------------------
# Pinhole.
# --------------------------------------------------------------------------------------


class PinholeCamera(AbstractCamera):
    r"""Perspective camera with OpenCV intrinsics and Brown--Conrady distortion.

    A point $X = (X, Y, Z)$ in the optical frame (x right, y down, z forward) maps to
    $x = X/Z$, $y = Y/Z$, $r^2 = x^2 + y^2$,

    $$x_d = x(1 + k_1 r^2 + k_2 r^4 + k_3 r^6) + 2 p_1 x y + p_2 (r^2 + 2x^2)$$
    $$y_d = y(1 + k_1 r^2 + k_2 r^4 + k_3 r^6) + p_1 (r^2 + 2y^2) + 2 p_2 x y$$

    and $(u, v) = (f_x x_d + c_x, f_y y_d + c_y)$, exactly as `cv2.projectPoints`.
    Unprojection inverts the distortion with a fixed number of iterations (OpenCV's
    fixed-point iteration, then Newton steps), accurate to far below 1e-6 px for
    realistic lenses.

    **Attributes:**

    - `fx`, `fy`: focal lengths in pixels, shape `()`.
    - `cx`, `cy`: principal point in pixels, shape `()`.
    - `dist`: distortion `(k1, k2, p1, p2, k3)`, shape `(5,)`.
    - `image_size`: `(width, height)` in pixels, static.
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    dist: Float[Array, "5"]
    image_size: tuple[int, int] = eqx.field(static=True)

    def __init__(
        self,
        fx: Float[ArrayLike, ""],
        fy: Float[ArrayLike, ""],
        cx: Float[ArrayLike, ""],
        cy: Float[ArrayLike, ""],
        dist: Float[ArrayLike, "5"] = (0.0, 0.0, 0.0, 0.0, 0.0),
        image_size: tuple[int, int] = (640, 480),
    ):
        self.fx, self.fy, self.cx, self.cy, self.dist = _as_float_arrays(fx, fy, cx, cy, dist)
        self.image_size = _check_image_size("PinholeCamera", image_size)

    def __check_init__(self):
        c = "PinholeCamera"
        _check_leaf(c, "fx", self.fx, positive=True)
        _check_leaf(c, "fy", self.fy, positive=True)
        _check_leaf(c, "cx", self.cx)
        _check_leaf(c, "cy", self.cy)
        _check_leaf(c, "dist", self.dist, vector=5)

    @classmethod
    def from_opencv(
        cls,
        K: Float[ArrayLike, "3 3"],
        dist: Float[ArrayLike, "..."] | None = None,
        image_size: tuple[int, int] = (640, 480),
    ) -> "PinholeCamera":
        """Build from an OpenCV camera matrix and distortion vector.

        **Arguments:**

        - `K`: camera matrix `[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`, shape `(3, 3)`.
          Skew must be zero (`cv2.projectPoints` ignores it).
        - `dist`: `(k1, k2, p1, p2[, k3])`, 4 or 5 coefficients, of shape `(n,)`,
          `(1, n)` or `(n, 1)`; `None` for no distortion. Rational and thin-prism
          models (8+ coefficients) are not supported.
        - `image_size`: `(width, height)` in pixels.

        **Returns:** a [`jaxloc.PinholeCamera`][].
        """
        K = np.asarray(K, dtype=float)
        if K.shape != (3, 3):
            raise ValueError(f"`K` must have shape (3, 3); got shape {K.shape}.")
        if not np.all(np.isfinite(K)):
            raise ValueError(f"`K` must be finite; got {np.array2string(K)}.")
        if K[0, 1] != 0 or K[1, 0] != 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]):
            raise ValueError(
                "`K` must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew); got "
                f"{np.array2string(K)}."
            )
        if dist is None:
            d = np.zeros(5)
        else:
            d = np.asarray(dist, dtype=float)
            if d.ndim == 2 and 1 in d.shape:
                d = d.reshape(-1)
            if d.ndim != 1 or d.shape[0] not in (4, 5):
                raise ValueError(
                    "`dist` must hold 4 or 5 coefficients (k1, k2, p1, p2[, k3]) with "
                    f"shape (n,), (1, n) or (n, 1); got shape {np.shape(dist)}."
                )
            d = np.concatenate([d, np.zeros(5 - d.shape[0])])
        return cls(K[0, 0], K[1, 1], K[0, 2], K[1, 2], d, image_size)

    def to_opencv(self) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
        """OpenCV form `(K, dist, image_size)`: `K` of shape `(3, 3)`, `dist` of shape
        `(5,)` (`k1, k2, p1, p2, k3`), both float64 NumPy arrays. Eager only."""
        K = np.array(
            [
                [float(self.fx), 0.0, float(self.cx)],
                [0.0, float(self.fy), float(self.cy)],
                [0.0, 0.0, 1.0],
            ]
        )
        return K, np.asarray(self.dist, dtype=np.float64).copy(), self.image_size

    def _dist5(self):
        d = self.dist
        return d[0], d[1], d[2], d[3], d[4]

    def project(self, points_cam: Float[ArrayLike, "*b 3"]) -> Float[Array, "*b 2"]:
        """Pixels `(u, v)` of points in the optical frame, shape `(*b, 2)`.

        Always finite: points with `Z <= 0` (not projectable) or within ~0.006 deg of
        the image plane get saturated normalized coordinates.
        """
        p = jnp.asarray(points_cam)
        _check_last_axis("points_cam", p, 3)
        x, y = _safe_ratio(p[..., 0], p[..., 1], p[..., 2])
        xd, yd = _distort(x, y, *self._dist5())
        return jnp.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=-1)

    def unproject(self, pixels: Float[ArrayLike, "*b 2"]) -> Float[Array, "*b 3"]:
        """Unit bearings `(X, Y, Z)`, `Z > 0`, in the optical frame, shape `(*b, 3)`."""
        uv = jnp.asarray(pixels)
        _check_last_axis("pixels", uv, 2)
        xd = (uv[..., 0] - self.cx) / self.fx
        yd = (uv[..., 1] - self.cy) / self.fy
        x, y = _undistort(xd, yd, *self._dist5())
        return jnp.stack(_normalize3(x, y, jnp.ones_like(x)), axis=-1)

    def projectable(self, points_cam: Float[ArrayLike, "*b 3"]) -> Bool[Array, "*b"]:
        """`Z > 0`: the point is in front of the camera."""
        p = jnp.asarray(points_cam)
        _check_last_axis("points_cam", p, 3)
        return p[..., 2] > 0

    def in_view(self, points_cam: Float[ArrayLike, "*b 3"]) -> Bool[Array, "*b"]:
        """Projectable, inside the image, and where the distortion map is locally
        invertible and orientation-preserving (Jacobian with positive determinant and
        trace).

        The last condition rejects points far outside the field of view that a
        polynomial distortion model would fold back into the image.
        """
        p = jnp.asarray(points_cam)
        _check_last_axis("points_cam", p, 3)
        x, y = _safe_ratio(p[..., 0], p[..., 1], p[..., 2])
        xd, yd, j00, j01, j10, j11 = _distort_jacobian(x, y, *self._dist5())
        u = self.fx * xd + self.cx
        v = self.fy * yd + self.cy
        # Both eigenvalues of the distortion Jacobian positive (det > 0 alone would
        # accept a fold in both directions, e.g. radial < 0 with d r_d / d r < 0).
        locally_invertible = (j00 * j11 - j01 * j10 > 0) & (j00 + j11 > 0)
        not_saturated = p[..., 2] * _MAX_NORMALIZED > jnp.abs(p[..., 0]) + jnp.abs(p[..., 1])
        return (
            (p[..., 2] > 0)
            & not_saturated
            & locally_invertible
            & _inside_image(u, v, self.image_size)
        )


# --------------------------------------------------------------------------------------
# PTZ.
# --------------------------------------------------------------------------------------


class PTZCamera(AbstractCamera):
    r"""Pan-tilt-zoom camera: a pinhole whose focal length follows zoom, on a pan-tilt
    head.

    **Frames.** Points are given in the PTZ *base* frame, which is the optical frame
    (x right, y down, z forward) at `pan = tilt = 0`. The optical frame is
    `R_base_optical = Ry(pan) @ Rx(tilt)` (standard right-handed `Rx`, `Ry`): pan turns
    about the base y axis (vertical), positive turns the optical axis toward +x (right);
    tilt turns about the panned x axis, positive turns the optical axis up (toward -y).
    `p_optical = R_base_optical^T p_base`. Bearings from `unproject` are in the base
    frame too.

    **Zoom.** `zoom` in `[0, 1]`; the focal length (pixels, square pixels `fy = fx`) is
    interpolated *linearly in focal length* (as a zoom lens' focal length moves, not
    linearly in angle) between the wide end and the tele end:
    $f(z) = (1 - z) f_\mathrm{wide} + z f_\mathrm{tele}$,
    $f_\bullet = (w/2) / \tan(\mathrm{hfov}_\bullet / 2)$ with $w$ the image width.
    At intermediate zoom the field of view is therefore
    $2\arctan((w/2)/f(z))$, not a linear blend of the two angles.
    The principal point is the image centre `((w - 1) / 2, (h - 1) / 2)`.

    **Attributes:**

    - `pan`, `tilt`: radians, shape `()`.
    - `zoom`: in `[0, 1]` (0 = wide, 1 = tele), shape `()`.
    - `hfov_wide`, `hfov_tele`: horizontal fields of view at the two ends, radians,
      shape `()` (paper, Canon C50i: 85 deg and 15 deg).
    - `dist`: Brown--Conrady `(k1, k2, p1, p2, k3)` (same at every zoom), shape `(5,)`.
    - `image_size`: `(width, height)` in pixels, static.
    """

    pan: Float[Array, ""]
    tilt: Float[Array, ""]
    zoom: Float[Array, ""]
    hfov_wide: Float[Array, ""]
    hfov_tele: Float[Array, ""]
    dist: Float[Array, "5"]
    image_size: tuple[int, int] = eqx.field(static=True)

    def __init__(
        self,
        pan: Float[ArrayLike, ""] = 0.0,
        tilt: Float[ArrayLike, ""] = 0.0,
        zoom: Float[ArrayLike, ""] = 0.0,
        hfov_wide: Float[ArrayLike, ""] = math.radians(85.0),
        hfov_tele: Float[ArrayLike, ""] = math.radians(15.0),
        dist: Float[ArrayLike, "5"] = (0.0, 0.0, 0.0, 0.0, 0.0),
        image_size: tuple[int, int] = (640, 480),
    ):
        (
            self.pan,
            self.tilt,
            self.zoom,
            self.hfov_wide,
            self.hfov_tele,
            self.dist,
        ) = _as_float_arrays(pan, tilt, zoom, hfov_wide, hfov_tele, dist)
        self.image_size = _check_image_size("PTZCamera", image_size)

    def __check_init__(self):
        c = "PTZCamera"
        _check_leaf(c, "pan", self.pan)
        _check_leaf(c, "tilt", self.tilt)
        _check_leaf(c, "zoom", self.zoom, interval=(0.0, 1.0))
        for name in ("hfov_wide", "hfov_tele"):
            x = getattr(self, name)
            _check_leaf(c, name, x, positive=True)
            if _is_concrete(x) and not np.all(np.asarray(x) < math.pi):
                raise ValueError(
                    f"`{c}({name}=...)` must be below pi (180 deg); got {_fmt(np.asarray(x))}."
                )
        _check_leaf(c, "dist", self.dist, vector=5)

    def focal_length(self) -> Float[Array, ""]:
        """Focal length in pixels at the current zoom (`fx = fy`), shape `()`."""
        half_w = 0.5 * self.image_size[0]
        f_wide = half_w / jnp.tan(0.5 * self.hfov_wide)
        f_tele = half_w / jnp.tan(0.5 * self.hfov_tele)
        return f_wide + self.zoom * (f_tele - f_wide)

    def pinhole(self) -> PinholeCamera:
        """The equivalent [`jaxloc.PinholeCamera`][] (optical frame) at the current zoom."""
        f = self.focal_length()
        w, h = self.image_size
        cx = jnp.asarray(0.5 * (w - 1), dtype=f.dtype)
        cy = jnp.asarray(0.5 * (h - 1), dtype=f.dtype)
        return PinholeCamera(f, f, cx, cy, self.dist, image_size=self.image_size)

    def optical_rotation(self) -> jaxlie.SO3:
        """`R_base_optical = Ry(pan) @ Rx(tilt)` as a `jaxlie.SO3`."""
        return jaxlie.SO3.from_y_radians(self.pan) @ jaxlie.SO3.from_x_radians(self.tilt)

    def _to_optical(self, p):
        # p_opt = Rx(tilt)^T Ry(pan)^T p_base, element-wise so it broadcasts.
        cp, sp = jnp.cos(self.pan), jnp.sin(self.pan)
        ct, st = jnp.cos(self.tilt), jnp.sin(self.tilt)
        X, Y, Z = p[..., 0], p[..., 1], p[..., 2]
        qx = cp * X - sp * Z
        qz = sp * X + cp * Z
        return jnp.stack([qx, ct * Y + st * qz, -st * Y + ct * qz], axis=-1)

    def _to_base(self, b):
        # p_base = Ry(pan) Rx(tilt) p_opt.
        cp, sp = jnp.cos(self.pan), jnp.sin(self.pan)
        ct, st = jnp.cos(self.tilt), jnp.sin(self.tilt)
        X, Y, Z = b[..., 0], b[..., 1], b[..., 2]
        qy = ct * Y - st * Z
        qz = st * Y + ct * Z
        return jnp.stack([cp * X + sp * qz, qy, -sp * X + cp * qz], axis=-1)

    def project(self, points_cam: Float[ArrayLike, "*b 3"]) -> Float[Array, "*b 2"]:
        """Pixels `(u, v)` of points in the PTZ *base* frame, shape `(*b, 2)`."""
        p = jnp.asarray(points_cam)
        _check_last_axis("points_cam", p, 3)
        return self.pinhole().project(self._to_optical(p))

    def unproject(self, pixels: Float[ArrayLike, "*b 2"]) -> Float[Array, "*b 3"]:
        """Unit bearings in the PTZ *base* frame, shape `(*b, 3)`."""
        return self._to_base(self.pinhole().unproject(pixels))

    def projectable(self, points_cam: Float[ArrayLike, "*b 3"]) -> Bool[Array, "*b"]:
        """In front of the (panned, tilted) camera. Points in the base frame."""
        p = jnp.asarray(points_cam)
        _check_last_axis("points_cam", p, 3)
        return self.pinhole().projectable(self._to_optical(p))

    def in_view(self, points_cam: Float[ArrayLike, "*b 3"]) -> Bool[Array, "*b"]:
        """Projectable and inside the image at the current pan, tilt and zoom. Points
        in the base frame."""
        p = jnp.asarray(points_cam)
        _check_last_axis("points_cam", p, 3)
        return self.pinhole().in_view(self._to_optical(p))


# --------------------------------------------------------------------------------------
# Omnidirectional (unified model).
# --------------------------------------------------------------------------------------


class OmniCamera(AbstractCamera):
    r"""Catadioptric omnidirectional camera, Mei's unified model with radial-tangential
    distortion: the model of OpenCV's `omnidir` module and of Kalibr's `omni-radtan`.

    A point $X$ in the camera frame (z along the mirror axis, pointing up) is lifted to
    the unit sphere, $x_s = X / \|X\|$, projected from the point $(0, 0, -\xi)$:
    $m = (x_s / (z_s + \xi),\ y_s / (z_s + \xi))$, distorted by $(k_1, k_2, p_1, p_2)$
    (Brown--Conrady without $k_3$), and mapped to pixels
    $u = f_x m_{x,d} + s\, m_{y,d} + c_x$, $v = f_y m_{y,d} + c_y$.
    $\xi = 0$ is a pinhole; $\xi = 1$ a paraboloidal mirror with an orthographic camera.

    Unprojection undistorts with the same fixed-iteration solver as the pinhole, then
    lifts to the sphere in closed form: with $r^2 = m_x^2 + m_y^2$,
    $\lambda = (\xi + \sqrt{1 + (1 - \xi^2) r^2}) / (r^2 + 1)$,
    $X \propto (\lambda m_x, \lambda m_y, \lambda - \xi)$.

    Elevation is $\operatorname{asin}(z_s)$, measured from the camera's x--y plane;
    `in_view` requires it to lie in `[elevation_min, elevation_max]`.

    **Attributes:**

    - `xi`: mirror parameter, `>= 0`, shape `()`.
    - `fx`, `fy`: generalized focal lengths in pixels, shape `()`.
    - `cx`, `cy`: principal point in pixels, shape `()`.
    - `skew`: skew `s` in pixels (OpenCV `K[0, 1]`), shape `()`.
    - `dist`: `(k1, k2, p1, p2)`, shape `(4,)`.
    - `elevation_min`, `elevation_max`: visible elevation band, radians, shape `()`
      (paper: -12 deg to +32 deg).
    - `image_size`: `(width, height)` in pixels, static.
    """

    xi: Float[Array, ""]
    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    skew: Float[Array, ""]
    dist: Float[Array, "4"]
    elevation_min: Float[Array, ""]
    elevation_max: Float[Array, ""]
    image_size: tuple[int, int] = eqx.field(static=True)

    def __init__(
        self,
        xi: Float[ArrayLike, ""],
        fx: Float[ArrayLike, ""],
        fy: Float[ArrayLike, ""],
        cx: Float[ArrayLike, ""],
        cy: Float[ArrayLike, ""],
        skew: Float[ArrayLike, ""] = 0.0,
        dist: Float[ArrayLike, "4"] = (0.0, 0.0, 0.0, 0.0),
        elevation_min: Float[ArrayLike, ""] = math.radians(-12.0),
        elevation_max: Float[ArrayLike, ""] = math.radians(32.0),
        image_size: tuple[int, int] = (640, 480),
    ):
        (
            self.xi,
            self.fx,
            self.fy,
            self.cx,
            self.cy,
            self.skew,
            self.dist,
            self.elevation_min,
            self.elevation_max,
        ) = _as_float_arrays(xi, fx, fy, cx, cy, skew, dist, elevation_min, elevation_max)
        self.image_size = _check_image_size("OmniCamera", image_size)

    def __check_init__(self):
        c = "OmniCamera"
        _check_leaf(c, "xi", self.xi, nonnegative=True)
        _check_leaf(c, "fx", self.fx, positive=True)
        _check_leaf(c, "fy", self.fy, positive=True)
        _check_leaf(c, "cx", self.cx)
        _check_leaf(c, "cy", self.cy)
        _check_leaf(c, "skew", self.skew)
        _check_leaf(c, "dist", self.dist, vector=4)
        half_pi = 0.5 * math.pi
        _check_leaf(c, "elevation_min", self.elevation_min, interval=(-half_pi, half_pi))
        _check_leaf(c, "elevation_max", self.elevation_max, interval=(-half_pi, half_pi))
        lo, hi = self.elevation_min, self.elevation_max
        if _is_concrete(lo) and _is_concrete(hi) and not np.all(np.asarray(lo) < hi):
            raise ValueError(
                f"`{c}(elevation_min=...)` must be below `elevation_max`; got "
                f"elevation_min={_fmt(np.asarray(lo))}, "
                f"elevation_max={_fmt(np.asarray(hi))}."
            )

    @classmethod
    def from_opencv(
        cls,
        K: Float[ArrayLike, "3 3"],
        D: Float[ArrayLike, "..."],
        xi: Float[ArrayLike, "..."],
        image_size: tuple[int, int] = (640, 480),
        **kwargs,
    ) -> "OmniCamera":
        """Build from OpenCV `cv2.omnidir` calibration output.

        **Arguments:**

        - `K`: `[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`, shape `(3, 3)`.
        - `D`: `(k1, k2, p1, p2)`, shape `(4,)`, `(1, 4)` or `(4, 1)`.
        - `xi`: mirror parameter, shape `()`, `(1,)` or `(1, 1)`.
        - `image_size`: `(width, height)` in pixels.
        - `**kwargs`: passed on (`elevation_min`, `elevation_max`).
        """
        K = np.asarray(K, dtype=float)
        if K.shape != (3, 3):
            raise ValueError(f"`K` must have shape (3, 3); got shape {K.shape}.")
        D = np.asarray(D, dtype=float)
        if D.size != 4:
            raise ValueError(f"`D` must hold 4 coefficients; got shape {D.shape}.")
        xi_arr = np.asarray(xi, dtype=float)
        if xi_arr.size != 1:
            raise ValueError(f"`xi` must be a scalar; got shape {xi_arr.shape}.")
        return cls(
            xi_arr.reshape(()),
            K[0, 0],
            K[1, 1],
            K[0, 2],
            K[1, 2],
            skew=K[0, 1],
            dist=D.reshape(4),
            image_size=image_size,
            **kwargs,
        )

    @classmethod
    def from_kalibr(
        cls,
        intrinsics: Float[ArrayLike, "5"],
        distortion_coeffs: Float[ArrayLike, "4"],
        resolution: tuple[int, int],
        **kwargs,
    ) -> "OmniCamera":
        """Build from a Kalibr `camera_model: omni`, `distortion_model: radtan` entry:
        `intrinsics = [xi, fu, fv, pu, pv]`, `distortion_coeffs = [k1, k2, r1, r2]`,
        `resolution = [width, height]`."""
        i = np.asarray(intrinsics, dtype=float)
        if i.shape != (5,):
            raise ValueError(
                f"`intrinsics` must be [xi, fu, fv, pu, pv], shape (5,); got shape {i.shape}."
            )
        return cls(
            i[0], i[1], i[2], i[3], i[4], dist=distortion_coeffs,
            image_size=tuple(resolution), **kwargs,
        )  # fmt: skip

    def _validity_w(self):
        # Projectable iff z_s > -w, w = xi (xi <= 1) or 1/xi (xi > 1): the unified
        # model's domain (e.g. Usenko et al. 2018, "The Double Sphere Camera Model",
        # Eq. 44 with alpha = xi / (1 + xi)).
        safe_xi = jnp.where(self.xi > 1.0, self.xi, 1.0)
        return jnp.where(self.xi > 1.0, 1.0 / safe_xi, self.xi)

    def _sphere(self, p):
        return _normalize3(p[..., 0], p[..., 1], p[..., 2])

    def _project_sphere(self, xs, ys, zs):
        mx, my = _safe_ratio(xs, ys, zs + self.xi)
        k1, k2, p1, p2 = self.dist[0], self.dist[1], self.dist[2], self.dist[3]
        mxd, myd = _distort(mx, my, k1, k2, p1, p2, 0.0)
        u = self.fx * mxd + self.skew * myd + self.cx
        v = self.fy * myd + self.cy
        return u, v

    def project(self, points_cam: Float[ArrayLike, "*b 3"]) -> Float[Array, "*b 2"]:
        """Pixels `(u, v)` of points in the camera frame (z = mirror axis, up), shape
        `(*b, 2)`. Always finite; the origin maps to the principal point."""
        p = jnp.asarray(points_cam)
        _check_last_axis("points_cam", p, 3)
        u, v = self._project_sphere(*self._sphere(p))
        return jnp.stack([u, v], axis=-1)

    def unproject(self, pixels: Float[ArrayLike, "*b 2"]) -> Float[Array, "*b 3"]:
        """Unit bearings in the camera frame, shape `(*b, 3)`.

        For `xi > 1`, pixels outside the image of the model's domain
        (`1 + (1 - xi^2) r^2 < 0`) get the bearing of the domain boundary (finite).
        """
        uv = jnp.asarray(pixels)
        _check_last_axis("pixels", uv, 2)
        myd = (uv[..., 1] - self.cy) / self.fy
        mxd = (uv[..., 0] - self.cx - self.skew * myd) / self.fx
        k1, k2, p1, p2 = self.dist[0], self.dist[1], self.dist[2], self.dist[3]
        mx, my = _undistort(mxd, myd, k1, k2, p1, p2, 0.0)
        r2 = mx * mx + my * my
        disc = 1.0 + (1.0 - self.xi * self.xi) * r2
        lam = (self.xi + safe_sqrt(disc)) / (r2 + 1.0)
        return jnp.stack(_normalize3(lam * mx, lam * my, lam - self.xi), axis=-1)

    def projectable(self, points_cam: Float[ArrayLike, "*b 3"]) -> Bool[Array, "*b"]:
        """The unified model's domain: `z_s > -xi` for `xi <= 1`, `z_s > -1/xi` for
        `xi > 1` (`z_s` the z of the unit bearing); not the origin."""
        p = jnp.asarray(points_cam)
        _check_last_axis("points_cam", p, 3)
        nonzero = jnp.any(p != 0, axis=-1)
        _, _, zs = self._sphere(p)
        return nonzero & (zs > -self._validity_w())

    def elevation(self, points_cam: Float[ArrayLike, "*b 3"]) -> Float[Array, "*b"]:
        """Elevation `asin(z_s)` above the camera's x--y plane, radians, shape `(*b,)`.

        Computed as `atan2(Z, hypot(X, Y))` (accurate everywhere, finite gradients)."""
        p = jnp.asarray(points_cam)
        _check_last_axis("points_cam", p, 3)
        rho = safe_sqrt(p[..., 0] ** 2 + p[..., 1] ** 2)
        z = p[..., 2]
        ok = (rho > 0) | (z != 0)
        return jnp.where(ok, jnp.arctan2(jnp.where(ok, z, 0.0), jnp.where(ok, rho, 1.0)), 0.0)

    def in_view(self, points_cam: Float[ArrayLike, "*b 3"]) -> Bool[Array, "*b"]:
        """Projectable, elevation in `[elevation_min, elevation_max]`, and inside the
        image."""
        p = jnp.asarray(points_cam)
        _check_last_axis("points_cam", p, 3)
        e = self.elevation(p)
        u, v = self._project_sphere(*self._sphere(p))
        return (
            self.projectable(p)
            & (e >= self.elevation_min)
            & (e <= self.elevation_max)
            & _inside_image(u, v, self.image_size)
        )
