r"""The camera interface ([`jaxloc.AbstractCamera`][]), eager validation shared by every
model, and the element-wise kernels every model builds on.

Every camera is an `equinox.Module` whose parameters are array leaves (so `jax.grad`,
`jax.vmap` and `jax.jit` reach them) and whose image size and model choices are static
configuration. All methods broadcast over leading batch axes of their argument: they are
written element-wise on `p[..., 0]`, `p[..., 1]`, `p[..., 2]`, with 0-d camera
parameters. To batch over *cameras*, `jax.vmap` over the camera.

Conventions (DESIGN §1):

- Units: metres (any consistent length unit: only directions matter) and radians;
  pixels for image coordinates.
- Pixels `(u, v)`: `u` to the right, `v` down, origin at the *centre* of the top-left
  pixel (OpenCV). The image covers `-0.5 <= u <= width - 0.5`,
  `-0.5 <= v <= height - 0.5`.
- Perspective/PTZ optical frame: x right, y down, z forward (OpenCV).
- Omnidirectional camera frame: z along the mirror axis pointing up; azimuth in the
  x--y plane, elevation measured from that plane.

**Finite inputs.** `project` returns finite pixels, even for points the model cannot
project (behind the camera, at the origin, ...): validity is a separate boolean mask given
by `projectable` (the model's own condition) and `in_view` (projectable and inside the
image, and for the omnidirectional camera inside its elevation band). Singular branches
use a double `where`, so gradients are finite too.

**Missing data** (issue 17): a non-finite input (NaN or inf in any coordinate) is a
missing measurement, never a default value. `project` of a non-finite point gives NaN
pixels (and a NaN Jacobian), `unproject` of a non-finite pixel gives a NaN bearing, and
`projectable` / `in_view` are `False`. The non-finite entries are swapped for a harmless
finite value before any arithmetic and the result masked afterwards (double `where`), so
finite entries give exactly the values and gradients they would alone.

**dtype.** The result has the dtype of the input and the camera (float32 points with a
float32 camera stay float32); nothing requests float64, so the models work with
`jax_enable_x64` on or off.
"""

import abc
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._core.compiler import jit
from .._core.numerics import safe_sqrt


MAX_NORMALIZED = 1e4
"""Normalized image coordinates are saturated at this magnitude (`|x|, |y| <= 1e4`, i.e.
directions within ~0.006 deg of the image plane). It keeps `project` finite in float32
(`r^6` of a distortion polynomial stays below ~1e25) for points the model cannot or can
barely project; no real camera sees that close to 90 deg off its axis."""


# --------------------------------------------------------------------------------------
# Construction helpers (eager validation).
# --------------------------------------------------------------------------------------


def _is_inexact_array(x: Any) -> bool:
    return isinstance(x, (jax.Array, np.ndarray, np.generic)) and jnp.issubdtype(
        x.dtype, jnp.inexact
    )


def as_float_arrays(*args: Any) -> list[Array]:
    """Cast constructor arguments to float arrays.

    Inexact arrays keep their dtype (float32 stays float32). Anything else (Python
    numbers, lists, integer arrays) becomes `jnp.asarray(x, dtype=dtype)`, where `dtype`
    is the common dtype of the inexact arrays given, or the default float (float64
    under x64) if there are none: a camera built from float32 arrays and default
    Python-number arguments is float32 throughout.
    """
    # Inexact arrays go through `jnp.asarray` first: a NumPy float64 array (OpenCV's
    # output) becomes the default float without a warning when x64 is off, where asking
    # `jnp.result_type` about float64 itself would warn.
    arrays = [jnp.asarray(x) if _is_inexact_array(x) else None for x in args]
    given = [a.dtype for a in arrays if a is not None]
    dtype = jnp.result_type(*given) if given else float
    return [jnp.asarray(x, dtype=dtype) if a is None else a for a, x in zip(arrays, args)]


def is_concrete(x: Any) -> bool:
    """Whether `x` holds values (not a tracer under `jit`/`vmap`/`grad`)."""
    return not isinstance(x, jax.core.Tracer)


def format_value(value: np.ndarray) -> str:
    """A short text form of a checked value for an error message."""
    return repr(float(value)) if value.ndim == 0 else np.array2string(value)


def check_image_size(cls: str, image_size: Any) -> tuple[int, int]:
    """`(width, height)` as two positive Python ints, or a `ValueError` naming `cls`."""
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


def check_leaf(
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
    if not is_concrete(x):
        return
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise ValueError(f"`{cls}({name}=...)` must be real; got dtype {x.dtype}.")
    if vector is not None and (x.ndim < 1 or x.shape[-1] != vector):
        raise ValueError(f"`{cls}({name}=...)` must have shape ({vector},); got shape {x.shape}.")
    value = np.asarray(x)
    if not np.all(np.isfinite(value)):
        raise ValueError(f"`{cls}({name}=...)` must be finite; got {format_value(value)}.")
    if positive and not np.all(value > 0):
        raise ValueError(f"`{cls}({name}=...)` must be positive; got {format_value(value)}.")
    if nonnegative and not np.all(value >= 0):
        raise ValueError(f"`{cls}({name}=...)` must be non-negative; got {format_value(value)}.")
    if interval is not None:
        lo, hi = interval
        if not np.all((value >= lo) & (value <= hi)):
            raise ValueError(
                f"`{cls}({name}=...)` must lie in [{lo:g}, {hi:g}]; got {format_value(value)}."
            )


def check_last_axis(name: str, x: Array, n: int) -> None:
    """`ValueError` naming `name` unless `x` has shape `(..., n)`."""
    if x.ndim < 1 or x.shape[-1] != n:
        raise ValueError(f"`{name}` must have shape (..., {n}); got shape {x.shape}.")


# --------------------------------------------------------------------------------------
# Missing data: non-finite inputs.
# --------------------------------------------------------------------------------------


def finite_points(points_cam: Float[ArrayLike, "*b 3"]) -> tuple[Array, Bool[Array, "*b"]]:
    """`(p, finite)`: the points as an array `(*b, 3)` with every row holding a NaN or an
    inf replaced by `(0, 0, 1)` (projectable by every model), and the mask `(*b,)` of the
    rows that were finite. Finite rows are passed through unchanged (bit for bit)."""
    p = jnp.asarray(points_cam)
    check_last_axis("points_cam", p, 3)
    finite = jnp.all(jnp.isfinite(p), axis=-1)
    return jnp.where(finite[..., None], p, jnp.array([0, 0, 1], dtype=p.dtype)), finite


def finite_pixels(pixels: Float[ArrayLike, "*b 2"]) -> tuple[Array, Bool[Array, "*b"]]:
    """`(uv, finite)`: the pixels as an array `(*b, 2)` with every row holding a NaN or
    an inf replaced by `(0, 0)`, and the mask `(*b,)` of the rows that were finite."""
    uv = jnp.asarray(pixels)
    check_last_axis("pixels", uv, 2)
    finite = jnp.all(jnp.isfinite(uv), axis=-1)
    return jnp.where(finite[..., None], uv, 0), finite


def nan_where_missing(x: Array, finite: Bool[Array, "*b"]) -> Array:
    """`x` `(*b, ...)` with NaN wherever the input row was not finite."""
    mask = finite.reshape(finite.shape + (1,) * (x.ndim - finite.ndim))
    return jnp.where(mask, x, jnp.nan)


# --------------------------------------------------------------------------------------
# Element-wise kernels.
# --------------------------------------------------------------------------------------


def safe_ratio(x, y, z):
    """`(x / z, y / z)` for `z > 0`, saturated at `MAX_NORMALIZED` and finite always.

    The denominator is floored at `(|x| + |y|) / MAX_NORMALIZED`, so directions at or
    behind 90 deg map continuously onto the saturation radius, and the origin (or a
    point on the negative axis) maps to 0. Double `where`: finite gradients everywhere.
    """
    floor = (jnp.abs(x) + jnp.abs(y)) * (1.0 / MAX_NORMALIZED)
    zc = jnp.maximum(z, floor)
    ok = zc > 0
    safe = jnp.where(ok, zc, 1.0)
    return jnp.where(ok, x / safe, 0.0), jnp.where(ok, y / safe, 0.0)


def safe_ratio_jacobian(x, y, z):
    """[`safe_ratio`][] and its Jacobian with respect to `(x, y, z)`, element-wise.

    **Returns:** `(rx, ry, ((dx_dx, dx_dy, dx_dz), (dy_dx, dy_dy, dy_dz)))`, every entry
    of the shape of the broadcast inputs. `rx`, `ry` are computed exactly as by
    `safe_ratio`. Where the denominator is saturated, the floor's derivative is used
    (`d|x|/dx = 1` at `x = 0`, as JAX's); at the origin the Jacobian is 0.
    """
    floor = (jnp.abs(x) + jnp.abs(y)) * (1.0 / MAX_NORMALIZED)
    zc = jnp.maximum(z, floor)
    ok = zc > 0
    safe = jnp.where(ok, zc, 1.0)
    rx, ry = jnp.where(ok, x / safe, 0.0), jnp.where(ok, y / safe, 0.0)
    inv = jnp.where(ok, 1.0 / safe, 0.0)
    saturated = floor > z
    # d zc / d(x, y, z): (0, 0, 1) in front, (sign x, sign y, 0) / MAX on the floor.
    dzx = jnp.where(saturated, jnp.where(x >= 0, 1.0, -1.0) * (1.0 / MAX_NORMALIZED), 0.0)
    dzy = jnp.where(saturated, jnp.where(y >= 0, 1.0, -1.0) * (1.0 / MAX_NORMALIZED), 0.0)
    dzz = jnp.where(saturated, 0.0, 1.0)
    jx = (inv * (1.0 - rx * dzx), -inv * rx * dzy, -inv * rx * dzz)
    jy = (-inv * ry * dzx, inv * (1.0 - ry * dzy), -inv * ry * dzz)
    return rx, ry, (jx, jy)


def normalize3(x, y, z):
    """`(x, y, z) / |(x, y, z)|`; the zero vector has no direction and gets the optical
    axis `(0, 0, 1)` (finite, unit; zero gradient)."""
    n = safe_sqrt(x * x + y * y + z * z)
    ok = n > 0
    inv = jnp.where(ok, 1.0 / jnp.where(ok, n, 1.0), 0.0)
    return (
        jnp.where(ok, x * inv, 0.0),
        jnp.where(ok, y * inv, 0.0),
        jnp.where(ok, z * inv, 1.0),
    )


def normalize3_jacobian(x, y, z):
    """[`normalize3`][] and its 3x3 Jacobian `(I - s s^T) / |p|` as nested tuples of
    element-wise entries (0 at the origin)."""
    n = safe_sqrt(x * x + y * y + z * z)
    ok = n > 0
    inv = jnp.where(ok, 1.0 / jnp.where(ok, n, 1.0), 0.0)
    s = (jnp.where(ok, x * inv, 0.0), jnp.where(ok, y * inv, 0.0), jnp.where(ok, z * inv, 1.0))
    jac = tuple(
        tuple(jnp.where(ok, ((1.0 if i == j else 0.0) - s[i] * s[j]) * inv, 0.0) for j in range(3))
        for i in range(3)
    )
    return s, jac


def inside_image(u, v, image_size: tuple[int, int]):
    """Whether pixels `(u, v)` lie inside an image of `(width, height)` (edges included)."""
    w, h = image_size
    return (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)


def stack_jacobian(rows) -> Array:
    """A `(*b, 2, 3)` Jacobian from a pair of triples of `(*b,)` entries."""
    (a, b, c), (d, e, f) = rows
    a, b, c, d, e, f = jnp.broadcast_arrays(a, b, c, d, e, f)
    # Stacked along new leading axes, then moved last: XLA:CPU then computes each entry
    # over the batch (vectorized) and transposes once. Stacked along the last axes, it
    # interleaved the six entries per point and the omni camera's Jacobian of a whole
    # batch ran 2.5x slower than the same under `vmap` (measured, jax 0.10.2).
    J = jnp.stack([jnp.stack([a, b, c], axis=0), jnp.stack([d, e, f], axis=0)], axis=0)
    return jnp.moveaxis(J, (0, 1), (-2, -1))


# --------------------------------------------------------------------------------------
# Interface.
# --------------------------------------------------------------------------------------


def project_with_jacobian_autodiff(
    camera: "AbstractCamera", points_cam: Float[ArrayLike, "*b 3"]
) -> tuple[Float[Array, "*b 2"], Float[Array, "*b 2 3"]]:
    """`camera.project` and its Jacobian by `jax.jacfwd`, one point at a time (vmapped).

    The default of [`jaxloc.AbstractCamera.project_with_jacobian`][] (the reference the
    closed forms are tested and benchmarked against).

    **Returns:** pixels `(*b, 2)` and `d pixels / d points_cam` `(*b, 2, 3)`.
    """
    p = jnp.asarray(points_cam)
    check_last_axis("points_cam", p, 3)
    batch = p.shape[:-1]

    def one(q):
        uv = camera.project(q)
        return uv, uv

    J, uv = jax.vmap(jax.jacfwd(one, has_aux=True))(p.reshape(-1, 3))
    return uv.reshape(*batch, 2), J.reshape(*batch, 2, 3)


class AbstractCamera(eqx.Module):
    """Interface of a camera model.

    Every method broadcasts over leading batch axes `*b` of its argument.

    **Attributes:**

    - `image_size`: `(width, height)` in pixels. Static (not a pytree leaf).
    """

    image_size: eqx.AbstractVar[tuple[int, int]]

    @abc.abstractmethod
    def project(self, points_cam: Float[ArrayLike, "*b 3"]) -> Float[Array, "*b 2"]:
        """Project points given in the camera frame to pixels `(u, v)`, shape `(*b, 2)`.

        Finite for every finite point, also for points the model cannot project: check
        them with [`jaxloc.AbstractCamera.projectable`][] or
        [`jaxloc.AbstractCamera.in_view`][]. NaN for a non-finite point.
        """

    @abc.abstractmethod
    def unproject(self, pixels: Float[ArrayLike, "*b 2"]) -> Float[Array, "*b 3"]:
        """Unit bearing vectors, in the camera frame, of pixels `(u, v)`, shape `(*b, 3)`.
        NaN for a non-finite pixel (a missing measurement)."""

    @abc.abstractmethod
    def projectable(self, points_cam: Float[ArrayLike, "*b 3"]) -> Bool[Array, "*b"]:
        """Whether the model can project each point (its own validity condition); `False`
        for a non-finite point."""

    @abc.abstractmethod
    def in_view(self, points_cam: Float[ArrayLike, "*b 3"]) -> Bool[Array, "*b"]:
        """Whether each point is projectable and lands inside the image (and band);
        `False` for a non-finite point."""

    def project_with_jacobian(
        self, points_cam: Float[ArrayLike, "*b 3"]
    ) -> tuple[Float[Array, "*b 2"], Float[Array, "*b 2 3"]]:
        """Pixels `(*b, 2)` and their Jacobian `d (u, v) / d points_cam`, `(*b, 2, 3)`.

        This default differentiates `project` with `jax.jacfwd` point by point
        ([`jaxloc.project_with_jacobian_autodiff`][]); jaxloc's models override it with
        closed forms written element-wise (no `dot`, no LAPACK), equal to it to
        rounding. Finite wherever `project` is (saturated and unprojectable points
        included); NaN for a non-finite point.
        """
        return project_with_jacobian_autodiff(self, points_cam)


@jit
def compiled_project(camera: AbstractCamera, p: Float[Array, "*n 3"]) -> Float[Array, "*n 2"]:
    """`camera.project(p)` compiled once per camera type and shape, for eager callers (the
    image front end): run op by op, a camera model is ~25 small programs to compile."""
    return camera.project(p)


@jit
def compiled_unproject(camera: AbstractCamera, uv: Float[Array, "*n 2"]) -> Float[Array, "*n 3"]:
    """`camera.unproject(uv)` compiled once per camera type and shape, for eager callers:
    run op by op, its undistortion loops compile again at every call."""
    return camera.unproject(uv)
