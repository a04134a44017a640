r"""The simulation world: floor and ceiling surfaces, robot poses on them, the formation.

Everything lives in the **environment frame** `E` (z up, metres). Surfaces are height
fields $z = h(x, y)$, so a robot's position is determined by its `(x, y)` and its body
frame by the surface normal there (DESIGN §4, the paper's Sec. IV.A: "the orientation of
each camera parallelly embeds in the tangent plane at their attaching point").

The paper's default world:

- ground: a saddle (hyperbolic paraboloid) with principal radii of curvature $\mp 8$ m at
  the origin, [`jaxloc.SaddleSurface`][];
- ceiling: 3.5 m above the ground at the origin, sinusoidal along `x` with period 10 m
  and amplitude 0.25 m, crest (zero slope) right above the origin,
  [`jaxloc.SinusoidSurface`][];
- formation: an isosceles triangle with base 2 m and legs 1.5 m; the environment origin
  is the middle of the base, right under the overhead camera, see
  [`jaxloc.formation_xy`][].
"""

import abc
import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
from jaxtyping import Array, ArrayLike, Float


def _as_float(x: ArrayLike) -> Array:
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.inexact) else x.astype(float)


class AbstractSurface(eqx.Module):
    r"""A height field $z = h(x, y)$ in the environment frame `E` (z up, metres).

    Every method broadcasts over leading axes of `xy`: `xy` has shape `(*b, 2)`.
    """

    @abc.abstractmethod
    def height(self, xy: Float[ArrayLike, "*b 2"]) -> Float[Array, "*b"]:
        """Height $z = h(x, y)$ (m) of the surface above the points `xy` (m), shape `(*b,)`."""

    @abc.abstractmethod
    def gradient(self, xy: Float[ArrayLike, "*b 2"]) -> Float[Array, "*b 2"]:
        r"""Slope $(\partial h/\partial x, \partial h/\partial y)$ (dimensionless), `(*b, 2)`."""

    def point(self, xy: Float[ArrayLike, "*b 2"]) -> Float[Array, "*b 3"]:
        """The surface point `(x, y, h(x, y))` in `E` (m), shape `(*b, 3)`."""
        xy = _as_float(xy)
        z = self.height(xy)
        return jnp.concatenate([xy, z[..., None].astype(xy.dtype)], axis=-1)

    def normal(self, xy: Float[ArrayLike, "*b 2"]) -> Float[Array, "*b 3"]:
        r"""Unit normal of the surface at `xy`, pointing **up** (+z side), shape `(*b, 3)`.

        $n = (-h_x, -h_y, 1) / \sqrt{1 + h_x^2 + h_y^2}$. For the ceiling this points into
        the ceiling (away from the room), which is the climbing robot's body z.
        """
        g = self.gradient(xy)
        n = jnp.concatenate([-g, jnp.ones_like(g[..., :1])], axis=-1)
        return n / jnp.sqrt(jnp.sum(n * n, axis=-1, keepdims=True))


class FlatSurface(AbstractSurface):
    """A horizontal plane `z = height` (m), stored as `z0`.

    The paper's real experiment (Table II) has a flat floor and a flat ceiling.
    """

    z0: Float[Array, ""]

    def __init__(self, height: Float[ArrayLike, ""] = 0.0):
        """**Arguments:**

        - `height`: the plane's height in `E` (m).
        """
        self.z0 = _as_float(height)

    def height(self, xy):
        xy = _as_float(xy)
        return jnp.broadcast_to(self.z0, xy.shape[:-1]).astype(
            jnp.result_type(xy.dtype, self.z0.dtype)
        )

    def gradient(self, xy):
        xy = _as_float(xy)
        return jnp.zeros(xy.shape, jnp.result_type(xy.dtype, self.z0.dtype))


class SaddleSurface(AbstractSurface):
    r"""Hyperbolic paraboloid $z = z_0 + x^2 / (2 r_x) + y^2 / (2 r_y)$ (m).

    `radius_x`, `radius_y` are the signed principal radii of curvature at the origin
    (m): $\partial^2 h / \partial x^2 = 1 / r_x$. The paper's ground ("hyperboloid ... radius
    of curvature 8 meters") is `radius_x=-8, radius_y=8`: the surface bends *down* along
    `x` and *up* along `y`, so C1 (the triangle's apex, at `-x`) sits below the base, as in
    the paper's Table I (the overhead camera is 3.577 m above C1 but 3.5 m above the
    origin).
    """

    radius_x: Float[Array, ""]
    radius_y: Float[Array, ""]
    z0: Float[Array, ""]

    def __init__(
        self,
        radius_x: Float[ArrayLike, ""] = -8.0,
        radius_y: Float[ArrayLike, ""] = 8.0,
        height: Float[ArrayLike, ""] = 0.0,
    ):
        """**Arguments:**

        - `radius_x`: signed radius of curvature along `x` at the origin (m), nonzero.
        - `radius_y`: signed radius of curvature along `y` at the origin (m), nonzero.
        - `height`: height $z_0$ of the saddle point (m).
        """
        self.radius_x = _as_float(radius_x)
        self.radius_y = _as_float(radius_y)
        self.z0 = _as_float(height)

    def height(self, xy):
        xy = _as_float(xy)
        x, y = xy[..., 0], xy[..., 1]
        return self.z0 + x * x / (2.0 * self.radius_x) + y * y / (2.0 * self.radius_y)

    def gradient(self, xy):
        xy = _as_float(xy)
        return jnp.stack([xy[..., 0] / self.radius_x, xy[..., 1] / self.radius_y], axis=-1)


class SinusoidSurface(AbstractSurface):
    r"""Corrugated surface varying along `x`:
    $z = H + A\,(\cos(2\pi x / P + \varphi) - \cos\varphi)$ (m).

    `height` $H$ is the surface's height **at `x = 0`** (the paper's "distance between the
    ceiling and the ground is 3.5 meters" holds right above the origin, where the overhead
    camera sits; stored as `z0`), `amplitude` $A$ (m), `period` $P$ (m), `phase` $\varphi$
    (rad). With the default `phase=0` the origin is a crest (the highest line of the
    ceiling, zero slope), so a robot there is untilted, as the paper's overhead camera
    (yaw, pitch, roll = (90, 0, 0) in Table I); the ceiling dips to `H - 2A` at `x = ±P/2`.
    """

    z0: Float[Array, ""]
    amplitude: Float[Array, ""]
    period: Float[Array, ""]
    phase: Float[Array, ""]

    def __init__(
        self,
        height: Float[ArrayLike, ""] = 3.5,
        amplitude: Float[ArrayLike, ""] = 0.25,
        period: Float[ArrayLike, ""] = 10.0,
        phase: Float[ArrayLike, ""] = 0.0,
    ):
        """**Arguments:**

        - `height`: height at `x = 0` (m).
        - `amplitude`: amplitude of the corrugation (m).
        - `period`: its wavelength along `x` (m), positive.
        - `phase`: phase (rad); `0` puts a crest at `x = 0`.
        """
        self.z0 = _as_float(height)
        self.amplitude = _as_float(amplitude)
        self.period = _as_float(period)
        self.phase = _as_float(phase)

    def height(self, xy):
        xy = _as_float(xy)
        w = 2.0 * math.pi / self.period
        return self.z0 + self.amplitude * (
            jnp.cos(w * xy[..., 0] + self.phase) - jnp.cos(self.phase)
        )

    def gradient(self, xy):
        xy = _as_float(xy)
        w = 2.0 * math.pi / self.period
        gx = -self.amplitude * w * jnp.sin(w * xy[..., 0] + self.phase)
        return jnp.stack([gx, jnp.zeros_like(gx)], axis=-1)


class FunctionSurface(AbstractSurface):
    r"""A user height field `fn(x, y) -> z` (m), differentiated by autodiff for normals.

    `fn` must be a JAX-traceable, element-wise function of two arrays of equal shape
    (e.g. `lambda x, y: 0.1 * jnp.sin(x) * jnp.cos(y)`). It is a static field: two
    surfaces are equal only if `fn` is the same object. Not serializable to scenario files.
    """

    fn: Callable[[Array, Array], Array] = eqx.field(static=True)

    def __init__(self, fn: Callable[[Array, Array], Array]):
        """**Arguments:**

        - `fn`: height `z = fn(x, y)` (m) in `E`.
        """
        if not callable(fn):
            raise ValueError(f"`FunctionSurface(fn=...)` must be callable; got {fn!r}.")
        self.fn = fn

    def height(self, xy):
        xy = _as_float(xy)
        return jnp.asarray(self.fn(xy[..., 0], xy[..., 1]))

    def gradient(self, xy):
        xy = _as_float(xy)

        def h1(p):
            return jnp.asarray(self.fn(p[0], p[1])).reshape(())

        return jnp.vectorize(jax.grad(h1), signature="(2)->(2)")(xy)


def body_pose_on_surface(
    surface: AbstractSurface, xy: Float[ArrayLike, "2"], heading: Float[ArrayLike, ""]
) -> jaxlie.SE3:
    r"""Pose `T_env_body` of a robot standing on `surface` at `xy` with `heading`.

    The body frame (x forward, y left, z up along the local normal; DESIGN §1) has its
    origin at the surface point above/below `xy`, z = the upward unit normal, and x = the
    heading direction $(\cos\psi, \sin\psi, 0)$ projected *vertically* into the tangent
    plane, $(\cos\psi, \sin\psi, \nabla h \cdot (\cos\psi, \sin\psi))$, normalized (so
    the heading is exactly the azimuth of body x); y = z × x. A robot on the ceiling
    therefore also has its z pointing up, into the ceiling (its camera looks along body -z
    through the mount `R_BODY_OVERHEAD`). Never singular for a height field.

    Written for one robot; batch with `jax.vmap`.

    **Arguments:**

    - `surface`: the surface the robot stands on.
    - `xy`: its position's `(x, y)` in `E` (m), shape `(2,)`.
    - `heading`: heading angle in the `E` x-y plane, from +x towards +y (rad), scalar.

    **Returns:** a `jaxlie.SE3` `T_env_body` (`p_env = T_env_body @ p_body`).
    """
    xy = _as_float(xy)
    heading = jnp.asarray(heading, dtype=xy.dtype)
    if xy.shape != (2,) or heading.shape != ():
        raise ValueError(
            "`body_pose_on_surface` takes one robot: `xy` of shape (2,) and a scalar "
            f"`heading`; got shapes {xy.shape} and {heading.shape}. Use `jax.vmap` to batch."
        )
    R, p = body_frame_on_surface(surface, xy, heading)
    return jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.from_matrix(R), p)


def body_frame_on_surface(
    surface: AbstractSurface, xy: Float[ArrayLike, "*b 2"], heading: Float[ArrayLike, "*b"]
) -> tuple[Float[Array, "*b 3 3"], Float[Array, "*b 3"]]:
    """Matrix form of [`jaxloc.body_pose_on_surface`][], broadcasting over leading axes.

    **Returns:** `(R_env_body, p_env_body)`: rotation matrices (columns: body x, y, z in
    `E`), shape `(*b, 3, 3)`, and positions (m), shape `(*b, 3)`. Cheaper than building
    `jaxlie.SE3`s (no matrix-to-quaternion conversion) for inner loops.
    """
    xy = _as_float(xy)
    heading = jnp.asarray(heading, dtype=xy.dtype)
    p = surface.point(xy)
    z = surface.normal(xy).astype(p.dtype)
    c, s = jnp.cos(heading), jnp.sin(heading)
    g = surface.gradient(xy).astype(p.dtype)
    # Vertical (not orthogonal) projection of (c, s, 0) into the tangent plane: the
    # tangent vector whose horizontal part is along the heading. The heading is then
    # exactly the azimuth of body x, and driving "along the heading" moves along it.
    x = jnp.stack([c, s, g[..., 0] * c + g[..., 1] * s], axis=-1)
    x = x / jnp.sqrt(jnp.sum(x * x, axis=-1, keepdims=True))
    y = jnp.cross(z, x)
    return jnp.stack([x, y, z], axis=-1), p


def formation_xy(base: Float[ArrayLike, ""], side: Float[ArrayLike, ""]) -> Float[Array, "3 2"]:
    r"""`(x, y)` of C1, C2, C3 in the paper's initial isosceles formation (m), shape `(3, 2)`.

    The environment origin is the middle of the base C2–C3; C1 (the PTZ robot, apex) is at
    $(-h, 0)$ with $h = \sqrt{\text{side}^2 - (\text{base}/2)^2}$ (1.118 m for the paper's
    base 2 m, legs 1.5 m), C2 at $(0, +\text{base}/2)$ and C3 at $(0, -\text{base}/2)$.
    The distances are measured in the `x-y` plane; on a curved ground the 3D distances
    differ slightly (by < 1 cm for the paper's saddle).

    **Arguments:**

    - `base`: length of the base C2–C3 (m).
    - `side`: length of the legs C1–C2 and C1–C3 (m); must exceed `base / 2`.
    """
    base, side = _as_float(base), _as_float(side)
    half = 0.5 * base
    h = jnp.sqrt(jnp.maximum(side * side - half * half, 0.0))
    zero = jnp.zeros_like(h)
    return jnp.stack(
        [jnp.stack([-h, zero]), jnp.stack([zero, half]), jnp.stack([zero, -half])]
    ).astype(jnp.result_type(base.dtype, side.dtype))
