r"""Camera calibration from chessboard images (DESIGN §5).

- **Perspective** (and a PTZ camera at one zoom): `cv2.findChessboardCorners`,
  `cv2.cornerSubPix` and `cv2.calibrateCameraExtended` into a [`jaxloc.PinholeCamera`][]
  ([`jaxloc.calibrate_pinhole`][]; Brown--Conrady or OpenCV's rational model).
- **PTZ** over its zoom range: one perspective calibration per zoom step, gathered into a
  [`jaxloc.ZoomTable`][] ([`jaxloc.calibrate_ptz`][]).
- **Omnidirectional** (Mei's unified model, [`jaxloc.OmniCamera`][]): the
  `opencv-python-headless` wheel has no `cv2.omnidir`, so jaxloc fits the model itself
  ([`jaxloc.calibrate_omni`][]): closed-form initialization (Mei & Rives 2007: with
  `xi = 1` the lifted image points of a straight line satisfy a linear equation that
  gives the generalized focal length; board poses from a homography of lifted bearings),
  then Levenberg--Marquardt (optimistix) over the intrinsics and every board pose.
- Both report the reprojection RMS and the standard deviations of the parameters
  (from the Gauss--Newton covariance scaled by the residual variance).

Board convention (OpenCV): `board = (cols, rows)` inner corners; corner `(row, col)` at
`(col * square, row * square, 0)` metres in the board frame, row-major order.
"""

import dataclasses
import math
import os
from typing import Any

import cv2
import jax
import jax.flatten_util
import jax.numpy as jnp
import jaxlie
import lineax as lx
import numpy as np
import optimistix as optx

from .._cameras.base import compiled_unproject
from .._cameras.files import camera_to_dict
from .._cameras.models import AbstractCamera, OmniCamera, PinholeCamera, PTZCamera, ZoomTable
from .._core.compiler import jit
from .markers import imread


# --------------------------------------------------------------------------------------
# Chessboard corners.


def parse_board(text: str) -> tuple[int, int]:
    """Parse `"COLSxROWS"` (inner corners, e.g. `"9x6"`) into `(cols, rows)`."""
    parts = str(text).lower().split("x")
    try:
        cols, rows = (int(p) for p in parts)
    except ValueError:
        raise ValueError(
            f"`board` must be COLSxROWS inner corners, e.g. 9x6; got {text!r}."
        ) from None
    return check_board((cols, rows))


def check_board(board: Any) -> tuple[int, int]:
    try:
        cols, rows = board
    except (TypeError, ValueError):
        raise ValueError(f"`board` must be (cols, rows) inner corners; got {board!r}.") from None
    if not all(isinstance(n, (int, np.integer)) and n >= 2 for n in (cols, rows)):
        raise ValueError(
            f"`board` must be two integers >= 2 (inner corners per row and column); got {board!r}."
        )
    return int(cols), int(rows)


def object_points(board: tuple[int, int], square: float) -> np.ndarray:
    """Board-frame corner positions `(rows * cols, 3)` (m), OpenCV's order."""
    cols, rows = check_board(board)
    if not (isinstance(square, (int, float)) and math.isfinite(square) and square > 0):
        raise ValueError(f"`square` must be a positive length in metres; got {square!r}.")
    jj, ii = np.mgrid[0:rows, 0:cols]
    return np.stack([ii.ravel() * square, jj.ravel() * square, np.zeros(rows * cols)], -1)


def find_corners(
    image: np.ndarray, board: tuple[int, int], *, window: int = 11, name: str = "image"
) -> np.ndarray | None:
    """Chessboard corners of one greyscale image, refined to sub-pixel accuracy.

    `cv2.findChessboardCorners` (adaptive threshold, normalized image) then
    `cv2.cornerSubPix` with `winSize = (window, window)`: a search window of
    `2 window + 1` pixels per side (11, OpenCV's calibration sample, suits squares of
    ~30 px and more; use less for small squares). Returns `(rows * cols, 2)` pixels in
    OpenCV's order, or `None` if the board is not found.
    """
    cols, rows = check_board(board)
    if not isinstance(image, np.ndarray) or image.ndim not in (2, 3) or image.size == 0:
        raise ValueError(f"`{name}` must be an image array; got {type(image).__name__}.")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.dtype != np.uint8:
        raise ValueError(f"`{name}` must be 8-bit; got dtype {image.dtype}.")
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(image, (cols, rows), flags=flags)
    if not found:
        return None
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
    corners = cv2.cornerSubPix(image, corners, (int(window), int(window)), (-1, -1), crit)
    return corners.reshape(-1, 2).astype(np.float64)


def _detect_all(images, board, window):
    """Corners of every image; a list of `(name, corners)` for the images with a board.
    Raises if no image shows the board, naming the board size and the files."""
    found, missing = [], []
    for k, item in enumerate(images):
        if isinstance(item, (str, os.PathLike)):
            name = os.fspath(item)
            img = imread(name, cv2.IMREAD_GRAYSCALE)
        else:
            name, img = f"images[{k}]", item
        c = find_corners(img, board, window=window, name=name)
        if c is None:
            missing.append(name)
        else:
            found.append((name, c, img.shape[1::-1]))
    if not found:
        cols, rows = board
        shown = ", ".join(missing[:5]) + (", ..." if len(missing) > 5 else "")
        raise ValueError(
            f"No chessboard of `board` = {cols}x{rows} inner corners was found in any of the "
            f"{len(missing)} images ({shown}); "
            "check the board size (inner corners, COLSxROWS) and the images."
        )
    sizes = {s for _, _, s in found}
    if len(sizes) != 1:
        raise ValueError(f"The calibration images have different sizes: {sorted(sizes)}.")
    return found, missing


# --------------------------------------------------------------------------------------
# Results.


@dataclasses.dataclass
class Calibration:
    """Result of a calibration.

    **Fields:**

    - `camera`: the calibrated [`jaxloc.PinholeCamera`][] or [`jaxloc.OmniCamera`][].
    - `rms`: reprojection RMS (px), over all corners (the root of the mean squared
      2-D residual norm, as `cv2.calibrateCamera` reports it).
    - `std`: standard deviation of each intrinsic parameter, `{name: value}` (px or
      unitless).
    - `per_view_rms`: reprojection RMS of each used image (px).
    - `T_cam_board`: board pose in each used image, `(views, 7)` wxyz_xyz.
    - `used`, `rejected`: names of the images with and without a detected board.
    """

    camera: AbstractCamera
    rms: float
    std: dict[str, float]
    per_view_rms: list[float]
    T_cam_board: np.ndarray
    used: list[str]
    rejected: list[str]

    def summary(self) -> dict[str, Any]:
        """Plain-Python summary (JSON-ready)."""
        return {
            "model": "omni" if isinstance(self.camera, OmniCamera) else "pinhole",
            "rms_px": self.rms,
            "std": self.std,
            "per_view_rms_px": dict(zip(self.used, self.per_view_rms)),
            "rejected": self.rejected,
            "camera": camera_to_dict(self.camera),
        }


def calibrate_pinhole(
    images: Any,
    board: tuple[int, int],
    square: float,
    *,
    fix_aspect_ratio: bool = False,
    fix_k3: bool = False,
    zero_tangent: bool = False,
    rational: bool = False,
    window: int = 11,
) -> Calibration:
    r"""Calibrate a perspective camera (or a PTZ camera at one zoom) with OpenCV.

    **Arguments:**

    - `images`: image file paths or greyscale/BGR `uint8` arrays.
    - `board`: inner corners `(cols, rows)`; `square`: square size (m). Only the
      extrinsics depend on `square`.
    - `fix_aspect_ratio`: `cv2.CALIB_FIX_ASPECT_RATIO` (`fx = fy`). Keyword only, as are
      the following.
    - `fix_k3`, `zero_tangent`: `cv2.CALIB_FIX_K3`, `cv2.CALIB_ZERO_TANGENT_DIST`.
    - `rational`: `cv2.CALIB_RATIONAL_MODEL`: the 8-coefficient rational model
      `(k1, k2, p1, p2, k3, k4, k5, k6)` (wide-angle lenses; needs many well-spread
      views).
    - `window`: `cornerSubPix` half window (px), see [`jaxloc.find_corners`][].

    **Returns:** a [`jaxloc.Calibration`][] whose camera is a [`jaxloc.PinholeCamera`][]
    (`dist` of shape `(5,)`, or `(8,)` with `rational`). Raises `ValueError` if fewer
    than 3 images show the board.
    """
    board = check_board(board)
    obj = object_points(board, square).astype(np.float32)
    found, missing = _detect_all(images, board, window)
    if len(found) < 3:
        raise ValueError(
            f"Pinhole calibration needs the board in at least 3 images; found it in "
            f"{len(found)} ({', '.join(n for n, _, _ in found)})."
        )
    size = found[0][2]
    flags = 0
    if fix_aspect_ratio:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
    if fix_k3:
        flags |= cv2.CALIB_FIX_K3
    if zero_tangent:
        flags |= cv2.CALIB_ZERO_TANGENT_DIST
    if rational:
        flags |= cv2.CALIB_RATIONAL_MODEL
    n_dist = 8 if rational else 5
    img_pts = [c.astype(np.float32).reshape(-1, 1, 2) for _, c, _ in found]
    K0 = np.eye(3)
    out = cv2.calibrateCameraExtended(
        [obj] * len(found), img_pts, tuple(size), K0, np.zeros(n_dist), flags=flags
    )
    rms, K, dist, rvecs, tvecs, std_in, _, per_view = out
    camera = PinholeCamera.from_opencv(K, dist.ravel()[:n_dist], tuple(int(x) for x in size))
    # OpenCV's order of the intrinsics' deviations: fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6 ...
    names = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"]
    names = names[: 4 + n_dist]
    std = {n: float(v) for n, v in zip(names, np.asarray(std_in).ravel()[: len(names)])}
    if fix_aspect_ratio:
        # OpenCV reports the common focal length's deviation under fy only.
        std["fx"] = std["fy"]
    poses = []
    for r, t in zip(rvecs, tvecs):
        T = jaxlie.SE3.from_rotation_and_translation(
            jaxlie.SO3.exp(jnp.asarray(r.ravel(), dtype=float)), jnp.asarray(t.ravel(), dtype=float)
        )
        poses.append(np.asarray(T.wxyz_xyz))
    return Calibration(
        camera=camera,
        rms=float(rms),
        std=std,
        per_view_rms=[float(x) for x in np.asarray(per_view).ravel()],
        T_cam_board=np.stack(poses),
        used=[n for n, _, _ in found],
        rejected=missing,
    )


# --------------------------------------------------------------------------------------
# PTZ calibration over the zoom range.


@dataclasses.dataclass
class ZoomCalibration:
    """Result of [`jaxloc.calibrate_ptz`][].

    **Fields:**

    - `camera`: a [`jaxloc.PTZCamera`][] with the calibrated [`jaxloc.ZoomTable`][]
      (`pan = tilt = 0`, `zoom` at the first step).
    - `zooms`: the calibrated zoom steps, increasing.
    - `steps`: the [`jaxloc.Calibration`][] of each step (same order), with its
      [`jaxloc.PinholeCamera`][], reprojection RMS and standard deviations.
    """

    camera: PTZCamera
    zooms: list[float]
    steps: list[Calibration]

    def summary(self) -> dict[str, Any]:
        """Plain-Python summary (JSON-ready): the table and each step's summary."""
        t = self.camera.zoom_table
        return {
            "model": "ptz",
            "distortion": self.camera.distortion,
            "image_width": self.camera.image_size[0],
            "image_height": self.camera.image_size[1],
            "zoom_table": {
                "zooms": [float(z) for z in np.asarray(t.zooms)],
                "fx": np.asarray(t.fx, np.float64).tolist(),
                "fy": np.asarray(t.fy, np.float64).tolist(),
                "cx": np.asarray(t.cx, np.float64).tolist(),
                "cy": np.asarray(t.cy, np.float64).tolist(),
                "distortion_coefficients": np.asarray(t.dist, np.float64).tolist(),
            },
            "steps": [dict(zoom=z, **c.summary()) for z, c in zip(self.zooms, self.steps)],
        }


def calibrate_ptz(
    image_sets_by_zoom: Any,
    board: tuple[int, int],
    square: float,
    **kwargs: Any,
) -> ZoomCalibration:
    r"""Calibrate a PTZ camera at several zoom steps into a [`jaxloc.ZoomTable`][].

    Each zoom step's images are calibrated on their own with
    [`jaxloc.calibrate_pinhole`][] (pan and tilt do not matter: hold them still while
    the board moves, or move them, the board poses absorb it); the intrinsics and
    distortion of the steps make the table, which the camera interpolates in between
    (focal lengths in `1/f`, the rest linearly; see [`jaxloc.ZoomTable`][]).

    **Arguments:**

    - `image_sets_by_zoom`: `{zoom: images}` or a sequence of `(zoom, images)` pairs,
      at least two distinct zoom steps in `[0, 1]` (in the camera's own zoom units
      mapped to `[0, 1]`, wide to tele); `images` as [`jaxloc.calibrate_pinhole`][]
      takes them (at least 3 showing the board per step), all of the same size.
    - `board`: inner corners `(cols, rows)`; `square`: square size (m).
    - `**kwargs`: passed to [`jaxloc.calibrate_pinhole`][] for every step
      (`fix_aspect_ratio`, `fix_k3`, `zero_tangent`, `rational`, `window`).

    **Returns:** a [`jaxloc.ZoomCalibration`][]. Raises `ValueError` naming the zoom
    step whose images fail.
    """
    if isinstance(image_sets_by_zoom, dict):
        pairs = list(image_sets_by_zoom.items())
    else:
        try:
            pairs = [(z, imgs) for z, imgs in image_sets_by_zoom]
        except (TypeError, ValueError):
            raise ValueError(
                "`image_sets_by_zoom` must be a mapping {zoom: images} or a sequence of "
                f"(zoom, images) pairs; got {type(image_sets_by_zoom).__name__}."
            ) from None
    zooms = []
    for z, _ in pairs:
        if isinstance(z, bool) or not isinstance(z, (int, float, np.integer, np.floating)) or not (
            0.0 <= float(z) <= 1.0
        ):
            raise ValueError(f"Each zoom step must be a number in [0, 1]; got {z!r}.")
        zooms.append(float(z))
    if len(set(zooms)) != len(zooms):
        raise ValueError(f"The zoom steps must be distinct; got {sorted(zooms)}.")
    if len(zooms) < 2:
        raise ValueError(
            f"`calibrate_ptz` needs at least two zoom steps; got {len(zooms)}. A single zoom "
            "is a pinhole calibration (`calibrate_pinhole`)."
        )
    order = np.argsort(zooms)
    steps: list[Calibration] = []
    for i in order:
        try:
            steps.append(calibrate_pinhole(pairs[i][1], board, square, **kwargs))
        except ValueError as e:
            raise ValueError(f"Zoom step {zooms[i]:g}: {e}") from None
    sizes = {c.camera.image_size for c in steps}
    if len(sizes) != 1:
        raise ValueError(f"The images of the zoom steps have different sizes: {sorted(sizes)}.")
    cams = [c.camera for c in steps]
    table = ZoomTable(
        [zooms[i] for i in order],
        [float(c.fx) for c in cams],
        [float(c.fy) for c in cams],
        [float(c.cx) for c in cams],
        [float(c.cy) for c in cams],
        np.stack([np.asarray(c.dist, np.float64) for c in cams]),
    )
    camera = PTZCamera(zoom=zooms[order[0]], image_size=cams[0].image_size, zoom_table=table)
    return ZoomCalibration(camera=camera, zooms=[zooms[i] for i in order], steps=steps)


# --------------------------------------------------------------------------------------
# Omnidirectional (unified model) calibration.

_OMNI_NAMES = ("xi", "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")


def _line_gamma(uv: np.ndarray, scale: float) -> float | None:
    """Generalized focal length (px) from the image of one straight 3-D line, for
    `xi = 1` (Mei & Rives 2007, Sec. 4): the lifted point `(u, v, gamma/2 - rho^2/(2 gamma))`
    of every pixel of the line lies on a plane through the origin, so
    `c1 u + c2 v + c3 + c4 rho^2 = 0` with `gamma^2 = -c3 / c4`."""
    x = uv / scale
    A = np.stack([x[:, 0], x[:, 1], np.ones(len(x)), (x**2).sum(-1)], -1)
    _, s, Vt = np.linalg.svd(A)
    c = Vt[-1]
    if abs(c[3]) < 1e-9 or s[-1] > 1e-2 * s[0]:
        return None
    g2 = -c[2] / c[3]
    if not (g2 > 0):
        return None
    return math.sqrt(g2) * scale


def _homography_pose(bearings: np.ndarray, obj: np.ndarray) -> np.ndarray:
    """Board pose `T_cam_board` (wxyz_xyz) from unit bearings of the board's corners: DLT
    on `b x (H [X, Y, 1]) = 0`, `H ~ [r1 r2 t]`, rotation projected onto SO(3)."""
    m = obj[:, :2].mean(0)
    s = np.sqrt(((obj[:, :2] - m) ** 2).sum(-1).mean())
    N = np.array([[1 / s, 0, -m[0] / s], [0, 1 / s, -m[1] / s], [0, 0, 1]])
    P = np.c_[obj[:, :2], np.ones(len(obj))] @ N.T
    rows = []
    for b, p in zip(bearings, P):
        bx = np.array([[0, -b[2], b[1]], [b[2], 0, -b[0]], [-b[1], b[0], 0]])
        rows.append(np.kron(bx, p[None, :]))  # (3, 9): bx @ H p with H row-major
    _, _, Vt = np.linalg.svd(np.concatenate(rows))
    H = Vt[-1].reshape(3, 3) @ N
    lam = 0.5 * (np.linalg.norm(H[:, 0]) + np.linalg.norm(H[:, 1]))
    H = H / lam
    q = (np.c_[obj[:, :2], np.ones(len(obj))] @ H.T)
    if np.sum(np.sum(q * bearings, -1)) < 0:
        H = -H
    M = np.c_[H[:, 0], H[:, 1], np.cross(H[:, 0], H[:, 1])]
    U, _, Vt2 = np.linalg.svd(M)
    R = U @ np.diag([1, 1, np.linalg.det(U @ Vt2)]) @ Vt2
    T = jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.from_matrix(jnp.asarray(R)), jnp.asarray(H[:, 2])
    )
    return np.asarray(T.wxyz_xyz)


def _omni_from_theta(theta, f0, image_size, skew):
    # theta: (xi, fx, fy, cx, cy) / f0 except xi, (k1, k2, p1, p2), and skew / f0 when it
    # is estimated (10 entries; else `skew` is the fixed value).
    xi, fx, fy, cx, cy = theta[0], theta[1] * f0, theta[2] * f0, theta[3] * f0, theta[4] * f0
    if theta.shape[0] == 10:
        skew = theta[9] * f0
    return OmniCamera(xi, fx, fy, cx, cy, skew=skew, dist=theta[5:9], elevation_min=-1.5,
                      elevation_max=1.5, image_size=image_size)  # fmt: skip


def _omni_residuals(params, args):
    theta, deltas = params
    T0, obj, uv, weight, f0, image_size, skew, free = args
    theta = jnp.where(free, theta, jax.lax.stop_gradient(theta))
    cam = _omni_from_theta(theta, f0, image_size, skew)

    def one(T0v, dv, uvv, wv):
        T = jaxlie.manifold.rplus(jaxlie.SE3(T0v), dv)
        p = jax.vmap(lambda q: T @ q)(obj)
        return wv[:, None] * (cam.project(p) - uvv)

    return jax.vmap(one)(T0, deltas, uv, weight)


@jit
def _omni_solve(theta0, T0, obj, uv, weight, f0, image_size, skew, free, max_steps):
    args = (T0, obj, uv, weight, f0, image_size, skew, free)
    deltas0 = jnp.zeros((T0.shape[0], 6), T0.dtype)
    sol = optx.least_squares(
        _omni_residuals,
        # Normal equations + Cholesky: the system is small (9 + 6 views unknowns) and
        # well posed after the closed-form start; it compiles ~2x faster than the default
        # QR (measured) and gives the same solution.
        optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10, linear_solver=lx.Normal(lx.Cholesky())),
        (theta0, deltas0),
        args=args,
        max_steps=max_steps,
        throw=False,
    )
    return sol.value, sol.result, sol.stats["num_steps"]


@jit
def _omni_jacobian(params, args):
    flat0, unravel = jax.flatten_util.ravel_pytree(params)
    J = jax.jacfwd(lambda f: _omni_residuals(unravel(f), args).ravel())(flat0)
    return J, _omni_residuals(params, args)


def omni_initial_guess(
    corners: list[np.ndarray],
    obj: np.ndarray,
    image_size: tuple[int, int],
    principal_point: tuple[float, float] | None = None,
) -> tuple[float, float, float, list[np.ndarray]]:
    r"""Closed-form start of the omnidirectional calibration (no iteration).

    With `xi = 1` and the principal point at the image centre (or `principal_point`), the
    generalized focal length `gamma` follows linearly from each imaged board row and
    column (a straight 3-D line; Mei & Rives 2007); the median over all lines is used.
    Each board's pose then comes from a homography between the board and the lifted
    bearings (DLT on `b x (H [X, Y, 1]) = 0`, rotation projected onto SO(3)).

    **Returns:** `(cx, cy, gamma, T_cam_board)`, the poses as wxyz_xyz arrays `(7,)`.
    """
    views = [np.asarray(c, np.float64).reshape(-1, 2) for c in corners]
    obj = np.asarray(obj, np.float64)
    w, h = image_size
    cx0, cy0 = principal_point if principal_point is not None else (0.5 * (w - 1), 0.5 * (h - 1))
    # Lines: rows and columns of the board (the object points' distinct y and x values).
    lines = []
    for axis in (0, 1):
        keys = np.round(obj[:, 1 - axis] / max(np.ptp(obj[:, 1 - axis]), 1e-12), 6)
        for key_ in np.unique(keys):
            lines.append(np.flatnonzero(keys == key_))
    gammas = []
    for c in views:
        uv = c - np.array([cx0, cy0])
        for idx in lines:
            sel = idx[np.all(np.isfinite(uv[idx]), -1)]
            if len(sel) >= 4:
                g = _line_gamma(uv[sel], 0.5 * w)
                if g is not None and 0.05 * w < g < 20 * w:
                    gammas.append(g)
    if not gammas:
        raise ValueError(
            "Could not initialize the omnidirectional focal length: no board row or column "
            "gave a usable line (are the corners in the right order?)."
        )
    gamma = float(np.median(gammas))
    init_cam = OmniCamera(1.0, gamma, gamma, cx0, cy0, elevation_min=-1.5, elevation_max=1.5,
                          image_size=(w, h))  # fmt: skip
    T0 = []
    for c in views:
        ok = np.all(np.isfinite(c), -1)
        b = np.asarray(compiled_unproject(init_cam, jnp.asarray(np.where(ok[:, None], c, 0.0))))
        T0.append(_homography_pose(b[ok], obj[ok]))
    return float(cx0), float(cy0), gamma, T0


def _check_omni_inputs(corners, obj, principal_point, focal_init, dist_init, fix_coefficients):
    """Validate [`jaxloc.calibrate_omni_corners`][]' arrays and options (`ValueError`
    naming the argument). Returns `(obj (n, 3), views)`, each view's pixels `(n, 2)`,
    float64."""
    obj = np.asarray(obj, np.float64)
    if obj.ndim != 2 or obj.shape[1] != 3:
        raise ValueError(f"`obj` must have shape (n, 3); got {obj.shape}.")
    views = [np.asarray(c, np.float64).reshape(-1, 2) for c in corners]
    if len(views) < 3:
        raise ValueError(f"Omnidirectional calibration needs at least 3 views; got {len(views)}.")
    for k, c in enumerate(views):
        if c.shape[0] != obj.shape[0]:
            raise ValueError(
                f"`corners[{k}]` must have {obj.shape[0]} rows like `obj`; got {c.shape[0]}."
            )
    unknown = [c for c in fix_coefficients if c not in _OMNI_NAMES[5:]]
    if isinstance(fix_coefficients, str) or unknown:
        raise ValueError(
            f"`fix_coefficients` must name some of {_OMNI_NAMES[5:]}; got {fix_coefficients!r}."
        )
    for arg, value, n in (("focal_init", focal_init, 2), ("dist_init", dist_init, 4),
                          ("principal_point", principal_point, 2)):  # fmt: skip
        if value is not None and (np.shape(value) != (n,) or not np.all(np.isfinite(value))):
            raise ValueError(f"`{arg}` must be {n} finite numbers; got {value!r}.")
    if focal_init is not None and not min(focal_init) > 0:
        raise ValueError(f"`focal_init` must be positive (px); got {focal_init!r}.")
    return obj, views


def _omni_start(views, obj, image_size, principal_point, xi_init, focal_init, dist_init,
                fix_skew):  # fmt: skip
    """The start of the LM solve: `(theta0, f0, T0)`, the camera parameters `theta0`
    (`xi`, then `fx, fy, cx, cy` divided by `f0` (px), `k1, k2, p1, p2`, and the skew / f0
    unless `fix_skew`), the focal scale `f0` (px) and each board's pose `T_cam_board`
    (wxyz_xyz `(7,)`), from [`omni_initial_guess`][] or the given `*_init` values."""
    cx0, cy0, gamma, T0 = omni_initial_guess(views, obj, image_size, principal_point)
    # From xi = 1 to xi_init: keep the image radius of the board's mean direction, so the
    # start stays close (f scales with (z_s + xi)).
    if focal_init is None and xi_init != 1.0:
        zs = []
        for Tv in T0:
            zc = np.asarray(jaxlie.SE3(jnp.asarray(Tv)).translation())
            zs.append(zc[2] / np.linalg.norm(zc))
        zbar = float(np.mean(zs))
        gamma = gamma * (zbar + xi_init) / (zbar + 1.0)
    fx0, fy0 = (gamma, gamma) if focal_init is None else (float(v) for v in focal_init)
    f0 = 0.5 * (fx0 + fy0)
    dist0 = [0.0] * 4 if dist_init is None else [float(v) for v in dist_init]
    theta0 = np.array([xi_init, fx0 / f0, fy0 / f0, cx0 / f0, cy0 / f0, *dist0], np.float64)
    if not fix_skew:
        theta0 = np.append(theta0, 0.0)
    return theta0, f0, T0


def _omni_free(n, fix_xi, fix_focal, fix_center, fix_distortion, fix_coefficients):
    """Which of the `n` camera parameters (`_OMNI_NAMES`, then the skew) the solve moves."""
    free = np.ones(n, bool)
    free[0] = not fix_xi
    free[1:3] = not fix_focal
    free[3:5] = not fix_center
    free[5:9] = not fix_distortion
    for c in fix_coefficients:
        free[_OMNI_NAMES.index(c)] = False
    return free


def _omni_errors(params, args, free, f0):
    """Reprojection errors and parameter uncertainty at the solution `params`.

    Returns `(rms, per_view, std)`: the RMS reprojection error over all corners and per
    view (px), and the standard deviation of each camera parameter by name (px for the
    focal lengths, centre and skew), `sigma^2 (J^T J)^-1` over the free parameters and the
    board poses."""
    _, deltas = params
    weight = np.asarray(args[3])
    J, r = _omni_jacobian(params, args)
    J, r = np.asarray(J), np.asarray(r)  # (views * n * 2, params), (views, n, 2)
    n_pts = int(weight.sum())
    sq = (r**2).sum(-1)
    rms = math.sqrt(sq.sum() / n_pts)
    per_view = [math.sqrt(sq[v].sum() / max(weight[v].sum(), 1)) for v in range(len(weight))]
    keep = np.concatenate([free, np.ones(deltas.size, bool)])
    Jk = J[:, keep]
    dof = max(2 * n_pts - Jk.shape[1], 1)
    sigma2 = float((r**2).sum()) / dof
    cov = sigma2 * np.linalg.pinv(Jk.T @ Jk)
    std_k = np.sqrt(np.maximum(np.diag(cov), 0.0))
    std_theta = np.zeros(free.shape[0])
    std_theta[free] = std_k[: int(free.sum())]
    scale = np.array([1, f0, f0, f0, f0, 1, 1, 1, 1, f0])
    std = {n: float(s * k) for n, s, k in zip((*_OMNI_NAMES, "skew"), std_theta, scale)}
    return rms, per_view, std


def calibrate_omni_corners(
    corners: list[np.ndarray],
    obj: np.ndarray,
    image_size: tuple[int, int],
    *,
    principal_point: tuple[float, float] | None = None,
    xi_init: float = 1.0,
    focal_init: tuple[float, float] | None = None,
    dist_init: tuple[float, float, float, float] | None = None,
    fix_xi: bool = False,
    fix_focal: bool = False,
    fix_center: bool = False,
    fix_distortion: bool = False,
    fix_coefficients: tuple[str, ...] = (),
    fix_skew: bool = True,
    max_steps: int = 200,
    names: list[str] | None = None,
) -> Calibration:
    r"""Calibrate an omnidirectional camera (unified model) from detected corners.

    Initialization in closed form: principal point at the image centre (or
    `principal_point`), `xi = 1` and the generalized focal length from every board row
    and column (straight lines, [Mei & Rives 2007]), median over lines; each board's pose
    from a homography between the board and the lifted bearings. Then one
    Levenberg--Marquardt solve (optimistix) over `xi, fx, fy, cx, cy, k1, k2, p1, p2`
    (and the skew with `fix_skew=False`) and every board pose (`T exp(delta)`).

    **Arguments:**

    - `corners`: per view, `(n, 2)` pixels of the board's corners (NaN rows ignored).
    - `obj`: board-frame corner positions `(n, 3)` (m), e.g. [`jaxloc.object_points`][].
    - `image_size`: `(width, height)`.
    - `principal_point`: initial `(cx, cy)` in px; default the image centre. Keyword
      only, as are the following.
    - `xi_init`: initial mirror parameter used after the `xi = 1` focal estimate.
    - `focal_init`: initial `(fx, fy)` in px; default the closed-form estimate.
    - `dist_init`: initial `(k1, k2, p1, p2)`; default zeros.
    - The options of OpenCV's `cv2.omnidir.calibrate` flags, each holding parameters at
      their initial values (the `*_init` and `principal_point` arguments play
      `CALIB_USE_GUESS`): `fix_xi` (`CALIB_FIX_XI`), `fix_focal` (`fx`, `fy`;
      `CALIB_FIX_GAMMA`), `fix_center` (`cx`, `cy`; `CALIB_FIX_CENTER`),
      `fix_distortion` (all of `k1, k2, p1, p2`), `fix_coefficients` (some of them by
      name, e.g. `("p1", "p2")`; `CALIB_FIX_K1` ... `CALIB_FIX_P2`).
    - `fix_skew`: hold the skew at 0 (default, as Kalibr's `omni` model, which has no
      skew; `CALIB_FIX_SKEW`); `False` estimates it (OpenCV `omnidir`'s `K[0, 1]`).
    - `max_steps`: LM iteration limit.
    - `names`: label of each view.

    **Returns:** a [`jaxloc.Calibration`][] with an [`jaxloc.OmniCamera`][] (elevation
    band left at the camera's default, -12..32 deg: set yours with `eqx.tree_at`).
    """
    obj, views = _check_omni_inputs(
        corners, obj, principal_point, focal_init, dist_init, fix_coefficients
    )
    w, h = image_size
    theta0, f0, T0 = _omni_start(
        views, obj, (w, h), principal_point, xi_init, focal_init, dist_init, fix_skew
    )
    free = _omni_free(theta0.shape[0], fix_xi, fix_focal, fix_center, fix_distortion,
                      fix_coefficients)  # fmt: skip
    uv = np.stack([np.where(np.isfinite(c), c, 0.0) for c in views])
    weight = np.stack([np.all(np.isfinite(c), -1).astype(np.float64) for c in views])
    (theta, deltas), result, steps = _omni_solve(
        jnp.asarray(theta0), jnp.asarray(np.stack(T0)), jnp.asarray(obj), jnp.asarray(uv),
        jnp.asarray(weight), f0, (int(w), int(h)), 0.0, jnp.asarray(free), max_steps,
    )  # fmt: skip
    args = (jnp.asarray(np.stack(T0)), jnp.asarray(obj), jnp.asarray(uv), jnp.asarray(weight),
            f0, (int(w), int(h)), 0.0, jnp.asarray(free))  # fmt: skip
    rms, per_view, std = _omni_errors((theta, deltas), args, free, f0)
    theta = np.asarray(theta)
    skew = theta[9] * f0 if theta.shape[0] == 10 else 0.0
    camera = OmniCamera(theta[0], theta[1] * f0, theta[2] * f0, theta[3] * f0, theta[4] * f0,
                        skew=skew, dist=theta[5:9], image_size=(int(w), int(h)))  # fmt: skip
    poses = np.stack([
        np.asarray(jaxlie.manifold.rplus(jaxlie.SE3(jnp.asarray(T0[v])), deltas[v]).wxyz_xyz)
        for v in range(len(views))
    ])  # fmt: skip
    if int(result._value) != 0 and rms > 1.0:
        raise ValueError(
            f"Omnidirectional calibration did not converge (LM stopped after {int(steps)} "
            f"steps with reprojection RMS {rms:.3g} px); check the corners and `board`."
        )
    return Calibration(
        camera=camera, rms=rms, std=std, per_view_rms=per_view, T_cam_board=poses,
        used=list(names) if names is not None else [f"view{k}" for k in range(len(views))],
        rejected=[],
    )  # fmt: skip


def calibrate_omni(
    images: Any,
    board: tuple[int, int],
    square: float,
    *,
    window: int = 5,
    **kwargs: Any,
) -> Calibration:
    """Calibrate an omnidirectional camera from chessboard images: corners with
    `cv2.findChessboardCorners` and `cornerSubPix` (`window` px), then
    [`jaxloc.calibrate_omni_corners`][] (`**kwargs` passed on). Needs the board in at
    least 3 images."""
    board = check_board(board)
    obj = object_points(board, square)
    found, missing = _detect_all(images, board, window)
    if len(found) < 3:
        raise ValueError(
            f"Omnidirectional calibration needs the board in at least 3 images; found it in "
            f"{len(found)} ({', '.join(n for n, _, _ in found)})."
        )
    cal = calibrate_omni_corners(
        [c for _, c, _ in found], obj, tuple(int(x) for x in found[0][2]),
        names=[n for n, _, _ in found], **kwargs,
    )  # fmt: skip
    cal.rejected = missing
    return cal
