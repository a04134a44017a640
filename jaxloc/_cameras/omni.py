r"""The catadioptric omnidirectional camera: Mei's unified model with radial-tangential or
equidistant distortion ([`jaxloc.OmniCamera`][])."""

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._core.numerics import safe_sqrt
from . import distortion as distortion_models
from .base import (
    AbstractCamera,
    as_float_arrays,
    check_image_size,
    check_leaf,
    finite_pixels,
    finite_points,
    format_value,
    inside_image,
    is_concrete,
    nan_where_missing,
    normalize3,
    normalize3_jacobian,
    safe_ratio,
    safe_ratio_jacobian,
    stack_jacobian,
)
from .distortion import EQUIDISTANT, RADTAN


class OmniCamera(AbstractCamera):
    r"""Catadioptric omnidirectional camera, Mei's unified model with lens distortion:
    the model of OpenCV's `omnidir` module and of Kalibr's `omni` (`omni-radtan`, and
    the `EquidistantOmniProjection` of Kalibr's C++ library).

    A point $X$ in the camera frame (z along the mirror axis, pointing up) is lifted to
    the unit sphere, $x_s = X / \|X\|$, projected from the point $(0, 0, -\xi)$:
    $m = (x_s / (z_s + \xi),\ y_s / (z_s + \xi))$, distorted, and mapped to pixels
    $u = f_x m_{x,d} + s\, m_{y,d} + c_x$, $v = f_y m_{y,d} + c_y$.
    $\xi = 0$ is a pinhole; $\xi = 1$ a paraboloidal mirror with an orthographic camera.

    Distortion of $m$ (static `distortion` field, `dist` of shape `(4,)` either way):

    - `"radtan"` (default): `(k1, k2, p1, p2)`, Brown--Conrady without $k_3$ (OpenCV
      `omnidir`, Kalibr `radtan`).
    - `"equidistant"`: `(k1, k2, k3, k4)`, Kalibr's `EquidistantDistortion` applied to
      $m$ as to a pinhole's normalized coordinates: $\theta = \operatorname{atan}|m|$,
      $\theta_d = \theta(1 + k_1\theta^2 + k_2\theta^4 + k_3\theta^6 + k_4\theta^8)$,
      $m_d = (\theta_d / |m|)\, m$ (Kalibr's `OmniProjection<EquidistantDistortion>`;
      its Python `ConfigReader` does not load this pair yet). With zero coefficients
      this is not the plain unified model ($|m_d| = \operatorname{atan}|m|$), and the
      image radius it can reach is bounded ($\theta_d(\pi/2)$ in normalized units):
      pixels beyond it unproject to the boundary's bearing.

    Unprojection undistorts with a fixed number of iterations, then lifts to the sphere
    in closed form: with $r^2 = m_x^2 + m_y^2$,
    $\lambda = (\xi + \sqrt{1 + (1 - \xi^2) r^2}) / (r^2 + 1)$,
    $X \propto (\lambda m_x, \lambda m_y, \lambda - \xi)$.

    Elevation is $\operatorname{asin}(z_s)$, measured from the camera's x--y plane;
    `in_view` requires it to lie in `[elevation_min, elevation_max]`.

    **Attributes:**

    - `xi`: mirror parameter, `>= 0`, shape `()`.
    - `fx`, `fy`: generalized focal lengths in pixels, shape `()`.
    - `cx`, `cy`: principal point in pixels, shape `()`.
    - `skew`: skew `s` in pixels (OpenCV `K[0, 1]`), shape `()`.
    - `dist`: `(k1, k2, p1, p2)` (radtan) or `(k1, k2, k3, k4)` (equidistant), shape
      `(4,)`.
    - `elevation_min`, `elevation_max`: visible elevation band, radians, shape `()`
      (paper: -12 deg to +32 deg).
    - `image_size`: `(width, height)` in pixels, static.
    - `distortion`: `"radtan"` or `"equidistant"`, static.
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
    distortion: str = eqx.field(static=True)

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
        distortion: str = RADTAN,
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
        ) = as_float_arrays(xi, fx, fy, cx, cy, skew, dist, elevation_min, elevation_max)
        self.image_size = check_image_size("OmniCamera", image_size)
        self.distortion = distortion

    def __check_init__(self):
        c = "OmniCamera"
        check_leaf(c, "xi", self.xi, nonnegative=True)
        check_leaf(c, "fx", self.fx, positive=True)
        check_leaf(c, "fy", self.fy, positive=True)
        check_leaf(c, "cx", self.cx)
        check_leaf(c, "cy", self.cy)
        check_leaf(c, "skew", self.skew)
        if self.distortion not in distortion_models.DISTORTION_MODELS:
            raise ValueError(
                f"`{c}(distortion=...)` must be one of {distortion_models.DISTORTION_MODELS}; "
                f"got {self.distortion!r}."
            )
        check_leaf(c, "dist", self.dist, vector=4)
        half_pi = 0.5 * math.pi
        check_leaf(c, "elevation_min", self.elevation_min, interval=(-half_pi, half_pi))
        check_leaf(c, "elevation_max", self.elevation_max, interval=(-half_pi, half_pi))
        lo, hi = self.elevation_min, self.elevation_max
        if is_concrete(lo) and is_concrete(hi) and not np.all(np.asarray(lo) < hi):
            raise ValueError(
                f"`{c}(elevation_min=...)` must be below `elevation_max`; got "
                f"elevation_min={format_value(np.asarray(lo))}, "
                f"elevation_max={format_value(np.asarray(hi))}."
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
        distortion_coeffs: Float[ArrayLike, "4"] | None,
        resolution: tuple[int, int],
        *,
        distortion_model: str = RADTAN,
        **kwargs,
    ) -> "OmniCamera":
        """Build from a Kalibr `camera_model: omni` entry: `intrinsics =
        [xi, fu, fv, pu, pv]`, `resolution = [width, height]`, and
        `distortion_model` `radtan` (`distortion_coeffs = [k1, k2, r1, r2]`),
        `equidistant` (`[k1, k2, k3, k4]`) or `none`. `**kwargs` passed on
        (`elevation_min`, `elevation_max`)."""
        i = np.asarray(intrinsics, dtype=float)
        if i.shape != (5,):
            raise ValueError(
                f"`intrinsics` must be [xi, fu, fv, pu, pv], shape (5,); got shape {i.shape}."
            )
        if distortion_model == "none":
            distortion_model, distortion_coeffs = RADTAN, np.zeros(4)
        if distortion_model not in distortion_models.DISTORTION_MODELS:
            raise ValueError(
                "`distortion_model` must be 'radtan', 'equidistant' or 'none'; got "
                f"{distortion_model!r}."
            )
        return cls(
            i[0], i[1], i[2], i[3], i[4], dist=distortion_coeffs,
            image_size=tuple(resolution), distortion=distortion_model, **kwargs,
        )  # fmt: skip

    def _k(self):
        d = self.dist
        if self.distortion == EQUIDISTANT:
            return d[0], d[1], d[2], d[3]
        # Brown--Conrady with k3 = 0 (a literal, as this model has always been computed).
        return d[0], d[1], d[2], d[3], 0.0

    def _validity_w(self):
        # Projectable iff z_s > -w, w = xi (xi <= 1) or 1/xi (xi > 1): the unified
        # model's domain (e.g. Usenko et al. 2018, "The Double Sphere Camera Model",
        # Eq. 44 with alpha = xi / (1 + xi)).
        safe_xi = jnp.where(self.xi > 1.0, self.xi, 1.0)
        return jnp.where(self.xi > 1.0, 1.0 / safe_xi, self.xi)

    def _sphere(self, p):
        return normalize3(p[..., 0], p[..., 1], p[..., 2])

    def _pixels(self, mxd, myd):
        return self.fx * mxd + self.skew * myd + self.cx, self.fy * myd + self.cy

    def _project_sphere(self, xs, ys, zs):
        mx, my = safe_ratio(xs, ys, zs + self.xi)
        mxd, myd = distortion_models.distort(self.distortion, self._k(), mx, my)
        return self._pixels(mxd, myd)

    def project(self, points_cam: Float[ArrayLike, "*b 3"]) -> Float[Array, "*b 2"]:
        """Pixels `(u, v)` of points in the camera frame (z = mirror axis, up), shape
        `(*b, 2)`. Finite for finite points; the origin maps to the principal point.
        NaN for a non-finite point."""
        p, finite = finite_points(points_cam)
        u, v = self._project_sphere(*self._sphere(p))
        return nan_where_missing(jnp.stack([u, v], axis=-1), finite)

    def project_with_jacobian(
        self, points_cam: Float[ArrayLike, "*b 3"]
    ) -> tuple[Float[Array, "*b 2"], Float[Array, "*b 2 3"]]:
        """Pixels `(*b, 2)` and `d (u, v) / d points_cam` `(*b, 2, 3)` in closed form
        (sphere lift, projection from `(0, 0, -xi)`, distortion, `K`; element-wise)."""
        p, finite = finite_points(points_cam)
        (xs, ys, zs), S = normalize3_jacobian(p[..., 0], p[..., 1], p[..., 2])
        mx, my, (jx, jy) = safe_ratio_jacobian(xs, ys, zs + self.xi)
        # d m / d p = (d m / d (xs, ys, zs)) (d (xs, ys, zs) / d p)
        dmx = tuple(sum(jx[a] * S[a][b] for a in range(3)) for b in range(3))
        dmy = tuple(sum(jy[a] * S[a][b] for a in range(3)) for b in range(3))
        mxd, myd, d00, d01, d10, d11 = distortion_models.distort_jacobian(
            self.distortion, self._k(), mx, my
        )
        dxd = tuple(d00 * a + d01 * b for a, b in zip(dmx, dmy))
        dyd = tuple(d10 * a + d11 * b for a, b in zip(dmx, dmy))
        rows = (
            tuple(self.fx * a + self.skew * b for a, b in zip(dxd, dyd)),
            tuple(self.fy * b for b in dyd),
        )
        u, v = self._pixels(mxd, myd)
        uv = jnp.stack([u, v], axis=-1)
        return nan_where_missing(uv, finite), nan_where_missing(stack_jacobian(rows), finite)

    def unproject(self, pixels: Float[ArrayLike, "*b 2"]) -> Float[Array, "*b 3"]:
        """Unit bearings in the camera frame, shape `(*b, 3)`; NaN for a non-finite
        pixel.

        For `xi > 1`, pixels outside the image of the model's domain
        (`1 + (1 - xi^2) r^2 < 0`) get the bearing of the domain boundary (finite).
        """
        uv, finite = finite_pixels(pixels)
        myd = (uv[..., 1] - self.cy) / self.fy
        mxd = (uv[..., 0] - self.cx - self.skew * myd) / self.fx
        mx, my = distortion_models.undistort(self.distortion, self._k(), mxd, myd)
        r2 = mx * mx + my * my
        disc = 1.0 + (1.0 - self.xi * self.xi) * r2
        lam = (self.xi + safe_sqrt(disc)) / (r2 + 1.0)
        b = jnp.stack(normalize3(lam * mx, lam * my, lam - self.xi), axis=-1)
        return nan_where_missing(b, finite)

    def projectable(self, points_cam: Float[ArrayLike, "*b 3"]) -> Bool[Array, "*b"]:
        """The unified model's domain: `z_s > -xi` for `xi <= 1`, `z_s > -1/xi` for
        `xi > 1` (`z_s` the z of the unit bearing); not the origin; finite."""
        p, finite = finite_points(points_cam)
        nonzero = jnp.any(p != 0, axis=-1)
        _, _, zs = self._sphere(p)
        return finite & nonzero & (zs > -self._validity_w())

    def elevation(self, points_cam: Float[ArrayLike, "*b 3"]) -> Float[Array, "*b"]:
        """Elevation `asin(z_s)` above the camera's x--y plane, radians, shape `(*b,)`;
        NaN for a non-finite point.

        Computed as `atan2(Z, hypot(X, Y))` (accurate everywhere, finite gradients)."""
        p, finite = finite_points(points_cam)
        rho = safe_sqrt(p[..., 0] ** 2 + p[..., 1] ** 2)
        z = p[..., 2]
        ok = (rho > 0) | (z != 0)
        e = jnp.where(ok, jnp.arctan2(jnp.where(ok, z, 0.0), jnp.where(ok, rho, 1.0)), 0.0)
        return nan_where_missing(e, finite)

    def in_view(self, points_cam: Float[ArrayLike, "*b 3"]) -> Bool[Array, "*b"]:
        """Projectable, elevation in `[elevation_min, elevation_max]`, inside the image,
        and where the distortion map is locally invertible and orientation-preserving
        (see [`jaxloc.PinholeCamera.in_view`][]; always true without distortion)."""
        p, finite = finite_points(points_cam)
        e = self.elevation(p)
        xs, ys, zs = self._sphere(p)
        mx, my = safe_ratio(xs, ys, zs + self.xi)
        k = self._k()
        mxd, myd, j00, j01, j10, j11 = distortion_models.distort_jacobian(
            self.distortion, k, mx, my
        )
        u, v = self._pixels(mxd, myd)
        invertible = distortion_models.locally_invertible(
            self.distortion, k, mx, my, jacobian=(j00, j01, j10, j11)
        )
        return (
            finite
            & self.projectable(p)
            & (e >= self.elevation_min)
            & (e <= self.elevation_max)
            & invertible
            & inside_image(u, v, self.image_size)
        )
