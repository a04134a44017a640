r"""The pan-tilt-zoom camera ([`jaxloc.PTZCamera`][]) and its zoom calibration table
([`jaxloc.ZoomTable`][])."""

import math

import equinox as eqx
import jax.numpy as jnp
import jaxlie
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
    format_value,
    is_concrete,
    nan_where_missing,
    stack_jacobian,
)
from .distortion import RADTAN
from .pinhole import (
    default_dist,
    finite_pixel_bearings,
    PINHOLE_DIST_SIZES,
    PinholeCamera,
)


def _lerp(a, b, t):
    """`a + t (b - a)`, evaluated from the nearer end so that `t = 0` gives `a` and
    `t = 1` gives `b` exactly (a table is exact at its steps)."""
    return jnp.where(t <= 0.5, a + t * (b - a), b - (1.0 - t) * (b - a))


def _lerp_reciprocal(a, b, t):
    """`f` with `1/f` linear in `t` between `1/a` and `1/b` (`a, b > 0`):
    `f = a b / ((1 - t) b + t a)`, written as a correction from the nearer end so that
    `t = 0` gives `a` and `t = 1` gives `b` exactly."""
    d = (1.0 - t) * b + t * a
    return jnp.where(t <= 0.5, a + t * a * (b - a) / d, b - (1.0 - t) * b * (b - a) / d)


class ZoomTable(eqx.Module):
    r"""Intrinsics and distortion of a zoom lens calibrated at several zoom steps.

    At zoom $z$ between two calibrated steps $z_i < z_{i+1}$, with
    $t = (z - z_i) / (z_{i+1} - z_i)$:

    - the focal lengths are interpolated **linearly in $1/f$** (the optical power):
      $1/f(z) = (1 - t)/f_i + t/f_{i+1}$;
    - the principal point and the distortion coefficients linearly.

    Why $1/f$ and not $f$: a zoom lens changes its focal length by moving lens groups
    along the axis, and the power of two groups of powers $P_1$, $P_2$ a distance $d$
    apart is $P = P_1 + P_2 - d P_1 P_2$ (Gullstrand): affine in the separation the zoom
    motor drives. So the power is close to linear in the motor position while $f$ grows
    hyperbolically toward the tele end; that is the convex focal-length-vs-step curve
    PTZ cameras show (e.g. a Sony EVI-D70's 4.1--73.8 mm: most of the focal length is
    gained in the last third of the zoom range). Linear $f$ would put the midpoint of a
    wide pair of steps at their arithmetic mean, too long for such a curve. Between
    closely spaced steps the two rules agree to second order in the step; calibrate
    more steps where the focal length changes fastest.

    Beyond the first and last steps every quantity stays at its end value. The table is
    exact at every step (the interpolation is evaluated from the nearer step).

    **Attributes:**

    - `zooms`: calibrated zoom steps, strictly increasing in `[0, 1]`, shape `(n,)`,
      `n >= 2`.
    - `fx`, `fy`: focal lengths in pixels at each step, shape `(n,)`.
    - `cx`, `cy`: principal point in pixels at each step, shape `(n,)`.
    - `dist`: distortion coefficients at each step, shape `(n, m)` (`m` as the
      [`jaxloc.PTZCamera`][]'s `distortion` model takes: 5 or 8 for radtan, 4 for
      equidistant).
    """

    zooms: Float[Array, " n"]
    fx: Float[Array, " n"]
    fy: Float[Array, " n"]
    cx: Float[Array, " n"]
    cy: Float[Array, " n"]
    dist: Float[Array, "n m"]

    def __init__(
        self,
        zooms: Float[ArrayLike, " n"],
        fx: Float[ArrayLike, " n"],
        fy: Float[ArrayLike, " n"],
        cx: Float[ArrayLike, " n"],
        cy: Float[ArrayLike, " n"],
        dist: Float[ArrayLike, "n m"] | None = None,
    ):
        if dist is None:
            dist = [[0.0] * 5] * (np.shape(zooms)[0] if np.ndim(zooms) == 1 else 0)
        self.zooms, self.fx, self.fy, self.cx, self.cy, self.dist = as_float_arrays(
            zooms, fx, fy, cx, cy, dist
        )

    def __check_init__(self):
        c = "ZoomTable"
        z = self.zooms
        if z.ndim != 1 or z.shape[0] < 2:
            raise ValueError(
                f"`{c}(zooms=...)` must have shape (n,) with n >= 2 calibrated steps; got "
                f"shape {z.shape}. A single zoom is a PinholeCamera."
            )
        n = z.shape[0]
        for name in ("fx", "fy", "cx", "cy"):
            x = getattr(self, name)
            if x.shape != (n,):
                raise ValueError(
                    f"`{c}({name}=...)` must have shape ({n},) like `zooms`; got {x.shape}."
                )
        if self.dist.ndim != 2 or self.dist.shape[0] != n:
            raise ValueError(
                f"`{c}(dist=...)` must have shape ({n}, m), one row of coefficients per "
                f"zoom step; got {self.dist.shape}."
            )
        check_leaf(c, "zooms", z, interval=(0.0, 1.0))
        if is_concrete(z) and not np.all(np.diff(np.asarray(z)) > 0):
            raise ValueError(
                f"`{c}(zooms=...)` must be strictly increasing; got "
                f"{format_value(np.asarray(z))}."
            )
        check_leaf(c, "fx", self.fx, positive=True)
        check_leaf(c, "fy", self.fy, positive=True)
        check_leaf(c, "cx", self.cx)
        check_leaf(c, "cy", self.cy)
        check_leaf(c, "dist", self.dist)

    def at(self, zoom: Float[ArrayLike, ""]) -> tuple[Array, Array, Array, Array, Array]:
        """`(fx, fy, cx, cy, dist)` at `zoom` (0-d each, `dist` of shape `(m,)`),
        interpolated as the class describes; constant beyond the end steps."""
        z = self.zooms
        zc = jnp.clip(zoom, z[0], z[-1])
        # Segment index: the number of interior steps at or below zc (branch-free).
        i = jnp.sum(z[1:-1] <= zc)
        z0, z1 = z[i], z[i + 1]
        t = (zc - z0) / (z1 - z0)
        fx = _lerp_reciprocal(self.fx[i], self.fx[i + 1], t)
        fy = _lerp_reciprocal(self.fy[i], self.fy[i + 1], t)
        cx = _lerp(self.cx[i], self.cx[i + 1], t)
        cy = _lerp(self.cy[i], self.cy[i + 1], t)
        dist = _lerp(self.dist[i], self.dist[i + 1], t)
        return fx, fy, cx, cy, dist


class PTZCamera(AbstractCamera):
    r"""Pan-tilt-zoom camera: a pinhole whose intrinsics follow zoom, on a pan-tilt
    head.

    **Frames.** Points are given in the PTZ *base* frame, which is the optical frame
    (x right, y down, z forward) at `pan = tilt = 0`. The optical frame is
    `R_base_optical = Ry(pan) @ Rx(tilt)` (standard right-handed `Rx`, `Ry`): pan turns
    about the base y axis (vertical), positive turns the optical axis toward +x (right);
    tilt turns about the panned x axis, positive turns the optical axis up (toward -y).
    `p_optical = R_base_optical^T p_base`. Bearings from `unproject` are in the base
    frame too.

    **Zoom, two-end model** (default, `zoom_table=None`). `zoom` in `[0, 1]`; the focal
    length (pixels, square pixels `fy = fx`) is interpolated linearly in focal length
    between the wide end and the tele end (the paper's nominal camera; kept as it is so
    studies reproduce):
    $f(z) = (1 - z) f_\mathrm{wide} + z f_\mathrm{tele}$,
    $f_\bullet = (w/2) / \tan(\mathrm{hfov}_\bullet / 2)$ with $w$ the image width.
    At intermediate zoom the field of view is therefore
    $2\arctan((w/2)/f(z))$, not a linear blend of the two angles.
    The principal point is the image centre `((w - 1) / 2, (h - 1) / 2)` and `dist`
    serves every zoom.

    **Zoom, calibrated** (`zoom_table` given): `fx`, `fy`, `cx`, `cy` and the distortion
    at the current zoom come from a [`jaxloc.ZoomTable`][] (calibrated steps, focal
    lengths interpolated in `1/f`, the rest linearly; see there). `hfov_wide`,
    `hfov_tele` and `dist` are then not used (`dist` must be left at zero).

    **Attributes:**

    - `pan`, `tilt`: radians, shape `()`.
    - `zoom`: in `[0, 1]` (0 = wide, 1 = tele), shape `()`.
    - `hfov_wide`, `hfov_tele`: horizontal fields of view at the two ends, radians,
      shape `()` (paper, Canon C50i: 85 deg and 15 deg). Two-end model only.
    - `dist`: distortion at every zoom, shape `(5,)` / `(8,)` (radtan, rational) or
      `(4,)` (equidistant), as [`jaxloc.PinholeCamera`][]. Two-end model only.
    - `zoom_table`: a [`jaxloc.ZoomTable`][] or `None` (two-end model).
    - `image_size`: `(width, height)` in pixels, static.
    - `distortion`: `"radtan"` or `"equidistant"`, static.
    """

    pan: Float[Array, ""]
    tilt: Float[Array, ""]
    zoom: Float[Array, ""]
    hfov_wide: Float[Array, ""]
    hfov_tele: Float[Array, ""]
    dist: Float[Array, " n"]
    zoom_table: ZoomTable | None
    image_size: tuple[int, int] = eqx.field(static=True)
    distortion: str = eqx.field(static=True)

    def __init__(
        self,
        pan: Float[ArrayLike, ""] = 0.0,
        tilt: Float[ArrayLike, ""] = 0.0,
        zoom: Float[ArrayLike, ""] = 0.0,
        hfov_wide: Float[ArrayLike, ""] = math.radians(85.0),
        hfov_tele: Float[ArrayLike, ""] = math.radians(15.0),
        dist: Float[ArrayLike, " n"] | None = None,
        image_size: tuple[int, int] = (640, 480),
        *,
        zoom_table: ZoomTable | None = None,
        distortion: str = RADTAN,
    ):
        if dist is None:
            dist = default_dist(distortion)
        (
            self.pan,
            self.tilt,
            self.zoom,
            self.hfov_wide,
            self.hfov_tele,
            self.dist,
        ) = as_float_arrays(pan, tilt, zoom, hfov_wide, hfov_tele, dist)
        self.zoom_table = zoom_table
        self.image_size = check_image_size("PTZCamera", image_size)
        self.distortion = distortion

    def __check_init__(self):
        c = "PTZCamera"
        check_leaf(c, "pan", self.pan)
        check_leaf(c, "tilt", self.tilt)
        check_leaf(c, "zoom", self.zoom, interval=(0.0, 1.0))
        for name in ("hfov_wide", "hfov_tele"):
            x = getattr(self, name)
            check_leaf(c, name, x, positive=True)
            if is_concrete(x) and not np.all(np.asarray(x) < math.pi):
                raise ValueError(
                    f"`{c}({name}=...)` must be below pi (180 deg); got "
                    f"{format_value(np.asarray(x))}."
                )
        n = distortion_models.check_model(c, self.distortion, self.dist.shape, PINHOLE_DIST_SIZES)
        check_leaf(c, "dist", self.dist, vector=n)
        table = self.zoom_table
        if table is not None:
            if not isinstance(table, ZoomTable):
                raise ValueError(
                    f"`{c}(zoom_table=...)` must be a ZoomTable or None; got "
                    f"{type(table).__name__}."
                )
            m = table.dist.shape[-1]
            if m not in PINHOLE_DIST_SIZES or (self.distortion, m) not in (
                distortion_models.COEFFICIENT_NAMES
            ):
                raise ValueError(
                    f"`{c}(zoom_table=...)` holds {m} distortion coefficients per step, which "
                    f"distortion={self.distortion!r} does not take (see PinholeCamera)."
                )
            if is_concrete(self.dist) and np.any(np.asarray(self.dist) != 0):
                raise ValueError(
                    f"`{c}(dist=...)` is not used with a `zoom_table` (the table holds the "
                    f"distortion at each zoom step); leave it at zero. Got "
                    f"{format_value(np.asarray(self.dist))}."
                )

    def focal_length(self) -> Float[Array, ""]:
        """Horizontal focal length `fx` in pixels at the current zoom, shape `()`
        (two-end model: `fx = fy`; with a zoom table see
        [`jaxloc.PTZCamera.pinhole`][] for all the intrinsics)."""
        if self.zoom_table is not None:
            return self.zoom_table.at(self.zoom)[0]
        half_w = 0.5 * self.image_size[0]
        f_wide = half_w / jnp.tan(0.5 * self.hfov_wide)
        f_tele = half_w / jnp.tan(0.5 * self.hfov_tele)
        return f_wide + self.zoom * (f_tele - f_wide)

    def pinhole(self) -> PinholeCamera:
        """The equivalent [`jaxloc.PinholeCamera`][] (optical frame) at the current zoom."""
        if self.zoom_table is not None:
            fx, fy, cx, cy, dist = self.zoom_table.at(self.zoom)
            return PinholeCamera(
                fx, fy, cx, cy, dist, image_size=self.image_size, distortion=self.distortion
            )
        f = self.focal_length()
        w, h = self.image_size
        cx = jnp.asarray(0.5 * (w - 1), dtype=f.dtype)
        cy = jnp.asarray(0.5 * (h - 1), dtype=f.dtype)
        return PinholeCamera(
            f, f, cx, cy, self.dist, image_size=self.image_size, distortion=self.distortion
        )

    def optical_rotation(self) -> jaxlie.SO3:
        """`R_base_optical = Ry(pan) @ Rx(tilt)` as a `jaxlie.SO3`."""
        return jaxlie.SO3.from_y_radians(self.pan) @ jaxlie.SO3.from_x_radians(self.tilt)

    def _optical_from_base(self):
        # Entries of R_base_optical^T = Rx(tilt)^T Ry(pan)^T (rows: optical x, y, z).
        cp, sp = jnp.cos(self.pan), jnp.sin(self.pan)
        ct, st = jnp.cos(self.tilt), jnp.sin(self.tilt)
        return ((cp, None, -sp), (st * sp, ct, st * cp), (ct * sp, -st, ct * cp))

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
        """Pixels `(u, v)` of points in the PTZ *base* frame, shape `(*b, 2)`; NaN for a
        non-finite point."""
        p, finite = finite_points(points_cam)
        return nan_where_missing(self.pinhole().project(self._to_optical(p)), finite)

    def project_with_jacobian(
        self, points_cam: Float[ArrayLike, "*b 3"]
    ) -> tuple[Float[Array, "*b 2"], Float[Array, "*b 2 3"]]:
        """Pixels `(*b, 2)` and `d (u, v) / d p_base` `(*b, 2, 3)`: the pinhole's closed
        form times `R_base_optical^T`, element-wise."""
        p, finite = finite_points(points_cam)
        uv, J = self.pinhole().project_with_jacobian(self._to_optical(p))
        R = self._optical_from_base()
        rows = tuple(
            tuple(
                sum(J[..., i, j] * R[j][k] for j in range(3) if R[j][k] is not None)
                for k in range(3)
            )
            for i in range(2)
        )
        return nan_where_missing(uv, finite), nan_where_missing(stack_jacobian(rows), finite)

    def unproject(self, pixels: Float[ArrayLike, "*b 2"]) -> Float[Array, "*b 3"]:
        """Unit bearings in the PTZ *base* frame, shape `(*b, 3)`; NaN for a non-finite
        pixel."""
        uv, finite = finite_pixels(pixels)
        return nan_where_missing(self._to_base(finite_pixel_bearings(self.pinhole(), uv)), finite)

    def projectable(self, points_cam: Float[ArrayLike, "*b 3"]) -> Bool[Array, "*b"]:
        """In front of the (panned, tilted) camera, and finite. Points in the base frame."""
        p, finite = finite_points(points_cam)
        return finite & self.pinhole().projectable(self._to_optical(p))

    def in_view(self, points_cam: Float[ArrayLike, "*b 3"]) -> Bool[Array, "*b"]:
        """Projectable and inside the image at the current pan, tilt and zoom (see
        [`jaxloc.PinholeCamera.in_view`][]). Points in the base frame."""
        p, finite = finite_points(points_cam)
        return finite & self.pinhole().in_view(self._to_optical(p))
