r"""Lens distortion models on normalized image coordinates, their Jacobians and inverses.

A model is chosen statically by a name and the number of its coefficients (the camera's
static `distortion` field and the static shape of its `dist` leaf):

- `("radtan", 5)`: Brown--Conrady `(k1, k2, p1, p2, k3)`, OpenCV's default
  (`cv2.projectPoints` with 5 coefficients; Kalibr's `radtan` is `k3 = 0`),
  $x_d = x\,(1 + k_1 r^2 + k_2 r^4 + k_3 r^6) + 2 p_1 x y + p_2 (r^2 + 2x^2)$,
  $y_d = y\,(1 + k_1 r^2 + k_2 r^4 + k_3 r^6) + p_1 (r^2 + 2y^2) + 2 p_2 x y$.
- `("radtan", 8)`: OpenCV's rational model `(k1, k2, p1, p2, k3, k4, k5, k6)`
  (`cv2.CALIB_RATIONAL_MODEL`): the radial factor becomes
  $(1 + k_1 r^2 + k_2 r^4 + k_3 r^6) / (1 + k_4 r^2 + k_5 r^4 + k_6 r^6)$.
- `("equidistant", 4)`: `(k1, k2, k3, k4)`, OpenCV's `fisheye` and Kalibr's
  `equidistant` (`aslam_cameras/.../EquidistantDistortion.hpp`): with $r = |(x, y)|$,
  $\theta = \operatorname{atan} r$,
  $\theta_d = \theta (1 + k_1 \theta^2 + k_2 \theta^4 + k_3 \theta^6 + k_4 \theta^8)$,
  $(x_d, y_d) = (\theta_d / r)\,(x, y)$ (identity at $r = 0$).

Coefficients enter as a tuple of 0-d arrays `k`; points as element-wise arrays `x`, `y`
(any shape, broadcast). Everything is branch-free with finite values and gradients
(double `where`), and inverses run a fixed number of iterations (jit-friendly, no LAPACK).
"""

import jax
import jax.numpy as jnp

from .._core.numerics import safe_sqrt
from .base import MAX_NORMALIZED


RADTAN = "radtan"
EQUIDISTANT = "equidistant"
DISTORTION_MODELS = (RADTAN, EQUIDISTANT)
"""Names of the distortion models (a camera's static `distortion` field)."""

COEFFICIENT_NAMES = {
    (RADTAN, 5): ("k1", "k2", "p1", "p2", "k3"),
    (RADTAN, 8): ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    (EQUIDISTANT, 4): ("k1", "k2", "k3", "k4"),
}
"""Coefficient names of each `(model, number of coefficients)`, in storage order."""

# Undistortion: OpenCV-style fixed-point iterations give a robust start (they converge
# for any realistic lens), then Newton steps on the 2-D distortion map converge
# quadratically. On the OpenCV sample calibration (k1 = -0.27, k3 = 0.24; 640x480) the
# round trip error over the whole image is 2e-13 px with 2 + 3 iterations, 2.5e-6 px with
# 10 fixed-point iterations alone; 2 + 6 leaves a margin for wide-angle lenses
# (tests/test_camera.py).
_FIXED_POINT_ITERATIONS = 2
_NEWTON_ITERATIONS = 6
# Equidistant: scalar Newton on theta from theta = theta_d (OpenCV's
# `cv::fisheye::undistortPoints` runs up to 10; Kalibr 20 fixed-point steps). The round
# trip over the image reaches rounding (~1e-13 px) after 3 steps on the fisheye and omni
# cameras of tests/test_camera_models.py, after 4 on a strong k1 = 0.1 lens (measured;
# 1e-3 to 0.5 px after 1 step); 10 for margin.
_EQUIDISTANT_ITERATIONS = 10
# A rational model's denominator below this is treated as a pole: the value stays finite
# (and meaningless) and `locally_invertible` is False there.
_POLE = 1e-12


def check_model(cls: str, distortion: str, shape: tuple[int, ...], allowed: tuple[int, ...]) -> int:
    """The number of coefficients of a `dist` of `shape` (its last axis), or a
    `ValueError` unless `distortion` is a known model taking that many, one of `allowed`
    for the camera `cls`."""
    if distortion not in DISTORTION_MODELS:
        raise ValueError(
            f"`{cls}(distortion=...)` must be one of {DISTORTION_MODELS}; got {distortion!r}."
        )
    n = shape[-1] if len(shape) >= 1 else -1
    if n not in allowed or (distortion, n) not in COEFFICIENT_NAMES:
        sizes = " or ".join(f"({m},)" for m in allowed if (distortion, m) in COEFFICIENT_NAMES)
        names = "; ".join(
            "(" + ", ".join(COEFFICIENT_NAMES[(distortion, m)]) + ")"
            for m in allowed
            if (distortion, m) in COEFFICIENT_NAMES
        )
        raise ValueError(
            f"`{cls}(dist=...)` must have shape {sizes} for distortion={distortion!r} "
            f"({names}); got shape {shape}."
        )
    return n


def split(dist) -> tuple:
    """The coefficients of `dist` `(n,)` as a tuple of n 0-d arrays."""
    return tuple(dist[i] for i in range(dist.shape[-1]))


# --------------------------------------------------------------------------------------
# Brown--Conrady (5 coefficients): the exact expressions jaxloc has always used, so the
# default cameras' outputs stay bit for bit what they were.


def _radtan5(x, y, k1, k2, p1, p2, k3):
    x2, y2, xy = x * x, y * y, x * y
    r2 = x2 + y2
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2)
    yd = y * radial + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy
    return xd, yd


def _radtan5_jacobian(x, y, k1, k2, p1, p2, k3):
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


def _radtan5_fixed_point(xd, yd, k1, k2, p1, p2, k3):
    def step(_, xy):
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

    return step


# --------------------------------------------------------------------------------------
# Rational (8 coefficients), as OpenCV's `cvProjectPoints2Internal`.


def _rational_num_den(r2, k1, k2, k3, k4, k5, k6):
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    return num, den


def _rational_parts(x, y, k1, k2, p1, p2, k3, k4, k5, k6):
    x2, y2, xy = x * x, y * y, x * y
    r2 = x2 + y2
    num, den = _rational_num_den(r2, k1, k2, k3, k4, k5, k6)
    ok = jnp.abs(den) > _POLE
    inv_den = jnp.where(ok, 1.0 / jnp.where(ok, den, 1.0), 1.0)
    radial = num * inv_den
    dnum = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3)
    dden = k4 + r2 * (2.0 * k5 + 3.0 * r2 * k6)
    dradial = (dnum - radial * dden) * inv_den  # d radial / d r2
    return x2, y2, xy, r2, radial, dradial


def _rational(x, y, k1, k2, p1, p2, k3, k4, k5, k6):
    x2, y2, xy, r2, radial, _ = _rational_parts(x, y, k1, k2, p1, p2, k3, k4, k5, k6)
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2)
    yd = y * radial + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy
    return xd, yd


def _rational_jacobian(x, y, k1, k2, p1, p2, k3, k4, k5, k6):
    x2, y2, xy, r2, radial, dradial = _rational_parts(x, y, k1, k2, p1, p2, k3, k4, k5, k6)
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2)
    yd = y * radial + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy
    j01 = 2.0 * xy * dradial + 2.0 * p1 * x + 2.0 * p2 * y
    j00 = radial + 2.0 * x2 * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    j11 = radial + 2.0 * y2 * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    return xd, yd, j00, j01, j01, j11


def _rational_fixed_point(xd, yd, k1, k2, p1, p2, k3, k4, k5, k6):
    # OpenCV's `cvUndistortPointsInternal`: x <- (x_d - tangential(x)) * den / num.
    def step(_, xy):
        x, y = xy
        x2, y2, xy_ = x * x, y * y, x * y
        r2 = x2 + y2
        num, den = _rational_num_den(r2, k1, k2, k3, k4, k5, k6)
        ok = jnp.abs(num) > 1e-6 * jnp.abs(den)
        inv = jnp.where(ok, den / jnp.where(ok, num, 1.0), 1.0)
        dx = 2.0 * p1 * xy_ + p2 * (r2 + 2.0 * x2)
        dy = p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy_
        x_new = (xd - dx) * inv
        y_new = (yd - dy) * inv
        finite = jnp.isfinite(x_new) & jnp.isfinite(y_new)
        return jnp.where(finite, x_new, x), jnp.where(finite, y_new, y)

    return step


# --------------------------------------------------------------------------------------
# Equidistant (4 coefficients), as Kalibr's `EquidistantDistortion` and OpenCV's fisheye.


def _theta_poly(t2, k1, k2, k3, k4):
    return 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))


def _equidistant(x, y, k1, k2, k3, k4):
    r = safe_sqrt(x * x + y * y)
    theta = jnp.arctan(r)
    theta_d = theta * _theta_poly(theta * theta, k1, k2, k3, k4)
    ok = r > 0
    scale = jnp.where(ok, theta_d / jnp.where(ok, r, 1.0), 1.0)
    return x * scale, y * scale


def _equidistant_jacobian(x, y, k1, k2, k3, k4):
    # (x_d, y_d) = s(r) (x, y) with s = theta_d / r:
    # J = s I + (x, y)(x, y)^T s'(r) / r,  s'(r) / r = (d theta_d / dr - s) / r^2,
    # d theta_d / dr = (1 + 3 k1 t^2 + 5 k2 t^4 + 7 k3 t^6 + 9 k4 t^8) / (1 + r^2).
    # The product with x y (<= r^2) keeps the cancellation near r = 0 at rounding level.
    r2 = x * x + y * y
    r = safe_sqrt(r2)
    theta = jnp.arctan(r)
    t2 = theta * theta
    theta_d = theta * _theta_poly(t2, k1, k2, k3, k4)
    ok = r > 0
    safe_r = jnp.where(ok, r, 1.0)
    scale = jnp.where(ok, theta_d / safe_r, 1.0)
    dtheta_d = (1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))) / (
        1.0 + r2
    )
    c = jnp.where(ok, (dtheta_d - scale) / (safe_r * safe_r), 0.0)
    xy_c = x * y * c
    return x * scale, y * scale, scale + x * x * c, xy_c, xy_c, scale + y * y * c


def _equidistant_inverse(xd, yd, k1, k2, k3, k4):
    theta_d = safe_sqrt(xd * xd + yd * yd)
    theta_max = jnp.arctan(jnp.asarray(MAX_NORMALIZED, dtype=theta_d.dtype))

    def newton(_, theta):
        t2 = theta * theta
        f = theta * _theta_poly(t2, k1, k2, k3, k4) - theta_d
        df = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
        ok = jnp.abs(df) > 1e-12
        new = theta - f * jnp.where(ok, 1.0 / jnp.where(ok, df, 1.0), 0.0)
        new = jnp.clip(new, 0.0, theta_max)
        return jnp.where(jnp.isfinite(new), new, theta)

    theta = jax.lax.fori_loop(0, _EQUIDISTANT_ITERATIONS, newton, jnp.minimum(theta_d, theta_max))
    ok = theta_d > 0
    scale = jnp.where(ok, jnp.tan(theta) / jnp.where(ok, theta_d, 1.0), 1.0)
    return xd * scale, yd * scale


# --------------------------------------------------------------------------------------
# Dispatch.


def _key(distortion: str, k: tuple) -> tuple[str, int]:
    key = (distortion, len(k))
    if key not in COEFFICIENT_NAMES:
        raise ValueError(
            f"Unknown distortion {distortion!r} with {len(k)} coefficients; expected one of "
            f"{sorted(COEFFICIENT_NAMES)}."
        )
    return key


def distort(distortion: str, k: tuple, x, y):
    """Distorted normalized coordinates `(x_d, y_d)` of `(x, y)` (element-wise)."""
    key = _key(distortion, k)
    if key == (RADTAN, 5):
        return _radtan5(x, y, *k)
    if key == (RADTAN, 8):
        return _rational(x, y, *k)
    return _equidistant(x, y, *k)


def distort_jacobian(distortion: str, k: tuple, x, y):
    """`(x_d, y_d, j00, j01, j10, j11)`: the distorted point and the 2x2 Jacobian
    `d (x_d, y_d) / d (x, y)`, element-wise. `x_d`, `y_d` equal [`distort`][]'s."""
    key = _key(distortion, k)
    if key == (RADTAN, 5):
        return _radtan5_jacobian(x, y, *k)
    if key == (RADTAN, 8):
        return _rational_jacobian(x, y, *k)
    return _equidistant_jacobian(x, y, *k)


def undistort(distortion: str, k: tuple, xd, yd):
    """Invert [`distort`][] with a fixed number of iterations (jit-friendly, no LAPACK).

    Brown--Conrady and rational: OpenCV's fixed-point iteration
    (`cv::undistortPoints`), `x <- (x_d - tangential(x)) / radial(x)`, then Newton steps
    on `D(x) - x_d = 0` with the 2x2 Jacobian solved by Cramer's rule. Equidistant: the
    radial map is inverted by scalar Newton steps on `theta_d(theta) = |x_d|`, then
    `r = tan(theta)`.
    """
    key = _key(distortion, k)
    # The carry must have a fixed dtype and shape: that of the broadcast inputs.
    xd, yd = jnp.broadcast_arrays(xd, yd)
    dtype = jnp.result_type(xd, yd, *k)
    xd, yd = xd.astype(dtype), yd.astype(dtype)
    if key == (EQUIDISTANT, 4):
        return _equidistant_inverse(xd, yd, *k)
    fixed_point = (_radtan5_fixed_point if key == (RADTAN, 5) else _rational_fixed_point)(
        xd, yd, *k
    )

    def newton(_, xy):
        x, y = xy
        fx, fy, j00, j01, j10, j11 = distort_jacobian(distortion, k, x, y)
        rx, ry = fx - xd, fy - yd
        det = j00 * j11 - j01 * j10
        ok = jnp.abs(det) > 1e-12
        inv_det = jnp.where(ok, 1.0 / jnp.where(ok, det, 1.0), 0.0)
        x_new = x - (j11 * rx - j01 * ry) * inv_det
        y_new = y - (-j10 * rx + j00 * ry) * inv_det
        finite = jnp.isfinite(x_new) & jnp.isfinite(y_new)
        return jnp.where(finite, x_new, x), jnp.where(finite, y_new, y)

    # `lax.fori_loop` (static trip count: a scan, so reverse-mode works) rather than a
    # Python loop: XLA's CPU fusion duplicates the unrolled iterations' shared
    # subexpressions when camera parameters are traced, which made a jitted unproject
    # of 100 pixels take ~50 s (measured, jax 0.10.2).
    xy = jax.lax.fori_loop(0, _FIXED_POINT_ITERATIONS, fixed_point, (xd, yd))
    return jax.lax.fori_loop(0, _NEWTON_ITERATIONS, newton, xy)


def locally_invertible(distortion: str, k: tuple, x, y, jacobian=None):
    """Whether the distortion map is locally invertible and orientation-preserving at
    `(x, y)`: its Jacobian has positive determinant and trace (both eigenvalues positive;
    `det > 0` alone would accept a fold in both directions, e.g. a negative radial factor
    with `d r_d / d r < 0`), and for the rational model the denominator is positive.
    `jacobian`: `(j00, j01, j10, j11)` if already computed."""
    if jacobian is None:
        _, _, *jacobian = distort_jacobian(distortion, k, x, y)
    j00, j01, j10, j11 = jacobian
    ok = (j00 * j11 - j01 * j10 > 0) & (j00 + j11 > 0)
    if _key(distortion, k) == (RADTAN, 8):
        k1, k2, _, _, k3, k4, k5, k6 = k
        _, den = _rational_num_den(x * x + y * y, k1, k2, k3, k4, k5, k6)
        ok = ok & (den > _POLE)
    return ok
