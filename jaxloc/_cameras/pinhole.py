r"""The perspective camera: OpenCV intrinsics with Brown--Conrady, rational or
equidistant (fisheye) distortion ([`jaxloc.PinholeCamera`][])."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from . import distortion as distortion_models
from .base import (
    AbstractCamera,
    as_float_arrays,
    check_image_size,
    check_leaf,
    finite_pixels,
    finite_points,
    inside_image,
    MAX_NORMALIZED,
    nan_where_missing,
    normalize3,
    safe_ratio,
    safe_ratio_jacobian,
    stack_jacobian,
)
from .distortion import EQUIDISTANT, RADTAN


PINHOLE_DIST_SIZES = (4, 5, 8)
"""Coefficient counts a pinhole camera takes: 5 (Brown--Conrady) or 8 (rational) with
`distortion="radtan"`, 4 with `distortion="equidistant"`."""


def default_dist(distortion: str) -> tuple[float, ...]:
    """No distortion for the model `distortion`: 4 zeros (equidistant) or 5 (radtan)."""
    return (0.0,) * (4 if distortion == EQUIDISTANT else 5)


def _check_K(K) -> np.ndarray:
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
    return K


def finite_pixel_bearings(
    camera: "PinholeCamera", uv: Float[Array, "*b 2"]
) -> Float[Array, "*b 3"]:
    """Unit bearings `(*b, 3)` of finite pixels `uv` `(*b, 2)` through a pinhole, without
    the missing-data mask of [`jaxloc.PinholeCamera.unproject`][].

    For callers that transform the bearings further and mask afterwards (the PTZ
    camera): a `where` between the bearings and their rotation changes how XLA:CPU fuses
    (and contracts into FMAs) the rotation, moving the last bit of ~40% of the PTZ
    bearings (measured); masking after the rotation keeps them bit for bit.
    """
    xd = (uv[..., 0] - camera.cx) / camera.fx
    yd = (uv[..., 1] - camera.cy) / camera.fy
    k = distortion_models.split(camera.dist)
    x, y = distortion_models.undistort(camera.distortion, k, xd, yd)
    return jnp.stack(normalize3(x, y, jnp.ones_like(x)), axis=-1)


class PinholeCamera(AbstractCamera):
    r"""Perspective camera with OpenCV intrinsics and lens distortion.

    A point $X = (X, Y, Z)$ in the optical frame (x right, y down, z forward) maps to
    normalized coordinates $x = X/Z$, $y = Y/Z$, which are distorted to $(x_d, y_d)$
    and mapped to pixels $(u, v) = (f_x x_d + c_x, f_y y_d + c_y)$. The distortion
    (see `jaxloc._cameras.distortion`) is chosen by the static `distortion` field and
    the static length of `dist`:

    - `distortion="radtan"` (default), `dist` of shape `(5,)`: Brown--Conrady
      `(k1, k2, p1, p2, k3)`, with $r^2 = x^2 + y^2$
      $$x_d = x(1 + k_1 r^2 + k_2 r^4 + k_3 r^6) + 2 p_1 x y + p_2 (r^2 + 2x^2)$$
      $$y_d = y(1 + k_1 r^2 + k_2 r^4 + k_3 r^6) + p_1 (r^2 + 2y^2) + 2 p_2 x y,$$
      exactly as `cv2.projectPoints`.
    - `distortion="radtan"`, `dist` of shape `(8,)`: OpenCV's rational model
      `(k1, k2, p1, p2, k3, k4, k5, k6)`, the radial factor
      $(1 + k_1 r^2 + k_2 r^4 + k_3 r^6) / (1 + k_4 r^2 + k_5 r^4 + k_6 r^6)$, as
      `cv2.projectPoints` with 8 coefficients.
    - `distortion="equidistant"`, `dist` of shape `(4,)`: `(k1, k2, k3, k4)`,
      $\theta = \operatorname{atan} r$,
      $\theta_d = \theta (1 + k_1\theta^2 + k_2\theta^4 + k_3\theta^6 + k_4\theta^8)$,
      $(x_d, y_d) = (\theta_d / r)(x, y)$: `cv2.fisheye.projectPoints` (no skew) and
      Kalibr's `pinhole-equi`. With zero coefficients this is the equidistant (f-theta)
      fisheye projection $r_d = \theta$, not the plain pinhole.

    Unprojection inverts the distortion with a fixed number of iterations (OpenCV's
    fixed-point iteration then Newton steps; scalar Newton on $\theta$ for the
    equidistant model), accurate to far below 1e-6 px for realistic lenses.

    **Attributes:**

    - `fx`, `fy`: focal lengths in pixels, shape `()`.
    - `cx`, `cy`: principal point in pixels, shape `()`.
    - `dist`: distortion coefficients, shape `(5,)`, `(8,)` or `(4,)` (see above).
    - `image_size`: `(width, height)` in pixels, static.
    - `distortion`: `"radtan"` or `"equidistant"`, static.
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    dist: Float[Array, " n"]
    image_size: tuple[int, int] = eqx.field(static=True)
    distortion: str = eqx.field(static=True)

    def __init__(
        self,
        fx: Float[ArrayLike, ""],
        fy: Float[ArrayLike, ""],
        cx: Float[ArrayLike, ""],
        cy: Float[ArrayLike, ""],
        dist: Float[ArrayLike, " n"] | None = None,
        image_size: tuple[int, int] = (640, 480),
        distortion: str = RADTAN,
    ):
        if dist is None:
            dist = default_dist(distortion)
        self.fx, self.fy, self.cx, self.cy, self.dist = as_float_arrays(fx, fy, cx, cy, dist)
        self.image_size = check_image_size("PinholeCamera", image_size)
        self.distortion = distortion

    def __check_init__(self):
        c = "PinholeCamera"
        check_leaf(c, "fx", self.fx, positive=True)
        check_leaf(c, "fy", self.fy, positive=True)
        check_leaf(c, "cx", self.cx)
        check_leaf(c, "cy", self.cy)
        n = distortion_models.check_model(c, self.distortion, self.dist.shape, PINHOLE_DIST_SIZES)
        check_leaf(c, "dist", self.dist, vector=n)

    @classmethod
    def from_opencv(
        cls,
        K: Float[ArrayLike, "3 3"],
        dist: Float[ArrayLike, "..."] | None = None,
        image_size: tuple[int, int] = (640, 480),
        *,
        distortion: str = RADTAN,
    ) -> "PinholeCamera":
        """Build from an OpenCV camera matrix and distortion vector.

        **Arguments:**

        - `K`: camera matrix `[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`, shape `(3, 3)`.
          Skew must be zero (`cv2.projectPoints` ignores it).
        - `dist`: of shape `(n,)`, `(1, n)` or `(n, 1)`; `None` for no distortion. With
          `distortion="radtan"` (`cv2.calibrateCamera`): 4 `(k1, k2, p1, p2)` (stored
          with `k3 = 0`), 5 `(k1, k2, p1, p2, k3)` or 8 (rational model, `k4, k5, k6`
          appended). Thin-prism and tilted models (12, 14 coefficients) are not
          supported. With `distortion="equidistant"` (`cv2.fisheye`): 4
          `(k1, k2, k3, k4)`.
        - `image_size`: `(width, height)` in pixels.
        - `distortion`: `"radtan"` (default) or `"equidistant"`. Keyword only.

        **Returns:** a [`jaxloc.PinholeCamera`][].
        """
        K = _check_K(K)
        if distortion not in distortion_models.DISTORTION_MODELS:
            raise ValueError(
                f"`distortion` must be one of {distortion_models.DISTORTION_MODELS}; got "
                f"{distortion!r}."
            )
        if dist is None:
            d = np.zeros(len(default_dist(distortion)))
        else:
            d = np.asarray(dist, dtype=float)
            if d.ndim == 2 and 1 in d.shape:
                d = d.reshape(-1)
            sizes = (4,) if distortion == EQUIDISTANT else (4, 5, 8)
            if d.ndim != 1 or d.shape[0] not in sizes:
                what = (
                    "4 coefficients (k1, k2, k3, k4)"
                    if distortion == EQUIDISTANT
                    else "4, 5 or 8 coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]])"
                )
                raise ValueError(
                    f"`dist` must hold {what} with shape (n,), (1, n) or (n, 1); got shape "
                    f"{np.shape(dist)}."
                )
            if distortion == RADTAN and d.shape[0] == 4:
                d = np.concatenate([d, np.zeros(1)])
        return cls(K[0, 0], K[1, 1], K[0, 2], K[1, 2], d, image_size, distortion=distortion)

    def to_opencv(self) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
        """OpenCV form `(K, dist, image_size)`: `K` of shape `(3, 3)` and `dist` as
        stored, both float64 NumPy arrays: `(5,)` (`k1, k2, p1, p2, k3`) or `(8,)`
        (rational) for `cv2.projectPoints`, `(4,)` (`k1..k4`) for `cv2.fisheye` when
        `distortion="equidistant"`. Eager only."""
        K = np.array(
            [
                [float(self.fx), 0.0, float(self.cx)],
                [0.0, float(self.fy), float(self.cy)],
                [0.0, 0.0, 1.0],
            ]
        )
        return K, np.asarray(self.dist, dtype=np.float64).copy(), self.image_size

    @classmethod
    def from_kalibr(
        cls,
        intrinsics: Float[ArrayLike, "4"],
        distortion_model: str,
        distortion_coeffs: Float[ArrayLike, " n"] | None,
        resolution: tuple[int, int],
    ) -> "PinholeCamera":
        """Build from a Kalibr `camera_model: pinhole` entry: `intrinsics =
        [fu, fv, pu, pv]`, `distortion_model` `radtan` (`distortion_coeffs =
        [k1, k2, r1, r2]`, stored with `k3 = 0`), `equidistant` (`[k1, k2, k3, k4]`)
        or `none`, `resolution = [width, height]`."""
        i = np.asarray(intrinsics, dtype=float)
        if i.shape != (4,):
            raise ValueError(
                f"`intrinsics` must be [fu, fv, pu, pv], shape (4,); got shape {i.shape}."
            )
        if distortion_model == "none":
            return cls(i[0], i[1], i[2], i[3], None, tuple(resolution))
        if distortion_model not in distortion_models.DISTORTION_MODELS:
            raise ValueError(
                "`distortion_model` must be 'radtan', 'equidistant' or 'none'; got "
                f"{distortion_model!r}."
            )
        d = np.asarray(distortion_coeffs, dtype=float).reshape(-1)
        if d.shape != (4,):
            raise ValueError(
                f"`distortion_coeffs` must hold 4 coefficients for Kalibr's "
                f"{distortion_model!r}; got shape {d.shape}."
            )
        if distortion_model == RADTAN:
            d = np.concatenate([d, np.zeros(1)])
        return cls(i[0], i[1], i[2], i[3], d, tuple(resolution), distortion=distortion_model)

    def _k(self):
        return distortion_models.split(self.dist)

    def project(self, points_cam: Float[ArrayLike, "*b 3"]) -> Float[Array, "*b 2"]:
        """Pixels `(u, v)` of points in the optical frame, shape `(*b, 2)`.

        Finite for finite points: points with `Z <= 0` (not projectable) or within
        ~0.006 deg of the image plane get saturated normalized coordinates. NaN for a
        non-finite point.
        """
        p, finite = finite_points(points_cam)
        x, y = safe_ratio(p[..., 0], p[..., 1], p[..., 2])
        xd, yd = distortion_models.distort(self.distortion, self._k(), x, y)
        uv = jnp.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=-1)
        return nan_where_missing(uv, finite)

    def project_with_jacobian(
        self, points_cam: Float[ArrayLike, "*b 3"]
    ) -> tuple[Float[Array, "*b 2"], Float[Array, "*b 2 3"]]:
        """Pixels `(*b, 2)` and `d (u, v) / d points_cam` `(*b, 2, 3)`, in closed form:
        `diag(fx, fy) . D'(x, y) . d(x, y)/dX`, written element-wise."""
        p, finite = finite_points(points_cam)
        x, y, (jx, jy) = safe_ratio_jacobian(p[..., 0], p[..., 1], p[..., 2])
        xd, yd, d00, d01, d10, d11 = distortion_models.distort_jacobian(
            self.distortion, self._k(), x, y
        )
        uv = jnp.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=-1)
        rows = (
            tuple(self.fx * (d00 * a + d01 * b) for a, b in zip(jx, jy)),
            tuple(self.fy * (d10 * a + d11 * b) for a, b in zip(jx, jy)),
        )
        return nan_where_missing(uv, finite), nan_where_missing(stack_jacobian(rows), finite)

    def unproject(self, pixels: Float[ArrayLike, "*b 2"]) -> Float[Array, "*b 3"]:
        """Unit bearings `(X, Y, Z)`, `Z > 0`, in the optical frame, shape `(*b, 3)`;
        NaN for a non-finite pixel."""
        uv, finite = finite_pixels(pixels)
        return nan_where_missing(finite_pixel_bearings(self, uv), finite)

    def projectable(self, points_cam: Float[ArrayLike, "*b 3"]) -> Bool[Array, "*b"]:
        """`Z > 0`: the point is in front of the camera (and finite)."""
        p, finite = finite_points(points_cam)
        return finite & (p[..., 2] > 0)

    def in_view(self, points_cam: Float[ArrayLike, "*b 3"]) -> Bool[Array, "*b"]:
        """Projectable, inside the image, and where the distortion map is locally
        invertible and orientation-preserving (Jacobian with positive determinant and
        trace; for the rational model, a positive denominator).

        The last condition rejects points far outside the field of view that a
        polynomial distortion model would fold back into the image.
        """
        p, finite = finite_points(points_cam)
        x, y = safe_ratio(p[..., 0], p[..., 1], p[..., 2])
        k = self._k()
        xd, yd, j00, j01, j10, j11 = distortion_models.distort_jacobian(self.distortion, k, x, y)
        u = self.fx * xd + self.cx
        v = self.fy * yd + self.cy
        invertible = distortion_models.locally_invertible(
            self.distortion, k, x, y, jacobian=(j00, j01, j10, j11)
        )
        not_saturated = p[..., 2] * MAX_NORMALIZED > jnp.abs(p[..., 0]) + jnp.abs(p[..., 1])
        return (
            finite
            & (p[..., 2] > 0)
            & not_saturated
            & invertible
            & inside_image(u, v, self.image_size)
        )
