r"""Synthetic camera images through jaxloc's own camera models (DESIGN §5, image front end).

Two kinds of image:

- **Marker images**: each robot carries a coloured sphere centred on its reference point
  (the point other cameras see, DESIGN §1); [`jaxloc.render_markers`][] draws the
  spheres seen by one camera, [`jaxloc.render_cycle`][] every image of a simulated cycle
  (PTZ of C1, omni cameras of C2 and C3, overhead camera of C at every step), with
  blur, sensor noise, distractor blobs and a lighting change, and writes PNGs plus the
  ground truth as JSON.
- **Chessboards**: [`jaxloc.render_chessboard`][] draws a planar board seen from a given
  pose through any camera model (pinhole, PTZ, omnidirectional), for calibration tests.

Exactness. A sphere's outline is the image of its tangent cone: rays at angle
$\alpha = \arcsin(r / d)$ around the direction of its centre. Projecting a ring of those
rays with `camera.project` gives the exact silhouette through any central camera model
(distortion and the unified model included), which is rasterized at 8x supersampling and
area-averaged (anti-aliasing). The ground truth keeps both the projection of the sphere's
centre (`center_px`, what localization needs) and the centroid of the rendered silhouette
(`centroid_px`, what a detector measures: an off-axis sphere images as an ellipse whose
centre is pushed outward, up to ~1 px for a close marker at the edge of a wide-angle
image). Blur (symmetric) and noise leave the centroid unbiased.

Randomness: an explicit JAX key, turned into a NumPy generator (`numpy_rng`) for the
OpenCV side; the same key gives the same image.

Colours are OpenCV BGR, images `uint8` `(height, width, 3)`, pixels `(u, v)` with the
origin at the centre of the top-left pixel.
"""

import json
import math
import os
from typing import Any

import cv2
import jax
import jax.numpy as jnp
import jax.random as jr
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._cameras.base import compiled_project, compiled_unproject
from .._cameras.models import AbstractCamera, OmniCamera
from .._core.compiler import jit
from .._cycle.sightings import in_body, marker_in_world, mutual_points
from .._model.measurements import rotations


DEFAULT_MARKER_BGR = ((30, 30, 220), (40, 190, 40), (220, 60, 30))
"""Default marker colours (BGR) of C1, C2, C3: saturated red, green, blue. Their hues
(0, 60, 120 on OpenCV's 0-179 scale) are far from the distractors' (yellow 30,
cyan 90, magenta 150)."""
_DISTRACTOR_BGR = ((30, 210, 230), (220, 200, 40), (200, 40, 200))
_SUPERSAMPLE = 8
_SILHOUETTE_POINTS = 96


def numpy_rng(key: PRNGKeyArray) -> np.random.Generator:
    """A NumPy generator seeded from a JAX key (for the OpenCV side of rendering)."""
    data = np.asarray(jr.key_data(key) if jnp.issubdtype(key.dtype, jax.dtypes.prng_key)
                      else key, dtype=np.uint32).ravel()  # fmt: skip
    return np.random.default_rng([int(x) for x in data])


# --------------------------------------------------------------------------------------
# Sphere silhouettes.


@jit
def _silhouettes(camera: AbstractCamera, centers: Float[Array, "n 3"], radius):
    """Silhouette polygons `(n, m, 2)` px, projected centres `(n, 2)`, and validity `(n,)`
    (the sphere is in front of / projectable by the camera, and the camera outside it)."""
    d = jnp.linalg.norm(centers, axis=-1)
    ok_d = d > 1.05 * radius
    safe_d = jnp.where(ok_d, d, 1.0)
    a = centers / safe_d[:, None]
    sin_a = jnp.where(ok_d, radius / safe_d, 0.0)
    cos_a = jnp.sqrt(1.0 - sin_a**2)
    # Orthonormal basis around each axis (Frisvad-style, with a switch on the pole).
    helper = jnp.where(jnp.abs(a[:, 2:3]) < 0.9, jnp.array([0.0, 0.0, 1.0]),
                       jnp.array([1.0, 0.0, 0.0]))  # fmt: skip
    e1 = jnp.cross(a, helper)
    e1 = e1 / jnp.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = jnp.cross(a, e1)
    phi = jnp.linspace(0.0, 2.0 * math.pi, _SILHOUETTE_POINTS, endpoint=False)
    ring = (
        cos_a[:, None, None] * a[:, None, :]
        + sin_a[:, None, None]
        * (
            jnp.cos(phi)[None, :, None] * e1[:, None, :]
            + jnp.sin(phi)[None, :, None] * e2[:, None, :]
        )
    )
    poly = camera.project(ring)
    center = camera.project(a)
    ok = ok_d & jnp.all(camera.projectable(ring), axis=-1) & camera.projectable(a)
    return poly, center, ok


def _raster_polygon(poly: np.ndarray, shape_hw: tuple[int, int]):
    """Anti-aliased coverage (float32 in [0, 1]) of a polygon inside an image, computed in
    the polygon's bounding box at 8x supersampling; also the exact centroid of the
    supersampled coverage. Returns `(y0, x0, coverage, centroid_uv, area_px)` or `None`
    when the polygon misses the image."""
    h, w = shape_hw
    s = _SUPERSAMPLE
    lo = np.floor(poly.min(axis=0)).astype(int) - 1
    hi = np.ceil(poly.max(axis=0)).astype(int) + 2
    x0, y0 = max(lo[0], 0), max(lo[1], 0)
    x1, y1 = min(hi[0], w), min(hi[1], h)
    if x1 <= x0 or y1 <= y0:
        return None
    # Supersampled pixel (i, j) centre <-> image coordinate (x0 - 0.5 + (i + 0.5) / s).
    pts = (poly - np.array([x0, y0]) + 0.5) * s - 0.5
    canvas = np.zeros(((y1 - y0) * s, (x1 - x0) * s), np.uint8)
    shift = 4
    cv2.fillPoly(canvas, [np.round(pts * (1 << shift)).astype(np.int32)], 255, cv2.LINE_8,
                 shift)  # fmt: skip
    m = cv2.moments(canvas, binaryImage=True)
    if m["m00"] == 0:
        return None
    cu = (m["m10"] / m["m00"] + 0.5) / s - 0.5 + x0
    cv = (m["m01"] / m["m00"] + 0.5) / s - 0.5 + y0
    cov = cv2.resize(canvas, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA)
    cov = cov.astype(np.float32) / 255.0
    return y0, x0, cov, np.array([cu, cv]), m["m00"] / (s * s)


# --------------------------------------------------------------------------------------
# Backgrounds, lighting, noise.


def annulus_of(camera: OmniCamera, margin: float = 0.0) -> tuple[float, float, float, float]:
    """Image annulus `(cx, cy, r_inner, r_outer)` (px) of an omnidirectional camera's
    elevation band: the circles of `elevation_max` (inner) and `elevation_min` (outer),
    from 72 azimuths through the camera model (distortion included), widened by `margin`
    px on both sides."""
    az = np.linspace(0.0, 2.0 * math.pi, 72, endpoint=False)
    radii = []
    for e in (float(camera.elevation_max), float(camera.elevation_min)):
        p = np.stack([np.cos(az) * math.cos(e), np.sin(az) * math.cos(e),
                      np.full_like(az, math.sin(e))], axis=-1)  # fmt: skip
        uv = np.asarray(compiled_project(camera, jnp.asarray(p)))
        radii.append(np.hypot(uv[:, 0] - float(camera.cx), uv[:, 1] - float(camera.cy)))
    r_in = float(np.min(radii[0])) - margin
    r_out = float(np.max(radii[1])) + margin
    return float(camera.cx), float(camera.cy), max(r_in, 0.0), r_out


def _background(rng: np.random.Generator, h: int, w: int, level: float) -> np.ndarray:
    """Neutral grey floor/ceiling texture: low-frequency variation plus fine texture,
    equal in the three channels (so it carries no hue)."""
    coarse = rng.uniform(-1.0, 1.0, (max(h // 40, 2), max(w // 40, 2))).astype(np.float32)
    low = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    fine = cv2.GaussianBlur(rng.normal(0.0, 1.0, (h, w)).astype(np.float32), (0, 0), 1.5)
    g = level + 25.0 * low + 6.0 * fine
    return np.repeat(g[:, :, None], 3, axis=2)


def _lighting(rng: np.random.Generator, h: int, w: int, strength: float) -> np.ndarray:
    """Smooth multiplicative gain field `(h, w, 3)`: a linear gradient plus a slight
    colour tint (illumination change between images)."""
    if strength == 0:
        return np.ones((h, w, 3), np.float32)
    gu, gv = rng.uniform(-strength, strength, 2)
    base = 1.0 + rng.uniform(-strength, strength)
    u = np.linspace(-0.5, 0.5, w, dtype=np.float32)[None, :]
    v = np.linspace(-0.5, 0.5, h, dtype=np.float32)[:, None]
    g = base + gu * u + gv * v
    tint = 1.0 + rng.uniform(-0.05, 0.05, 3) * strength / 0.3
    return g[:, :, None] * tint[None, None, :].astype(np.float32)


def _finish(img: np.ndarray, rng, blur_sigma: float, noise_sigma: float, gain) -> np.ndarray:
    if gain is not None:
        img = img * gain
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    if noise_sigma > 0:
        img = img + rng.normal(0.0, noise_sigma, img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _paint(img: np.ndarray, y0: int, x0: int, cov: np.ndarray, bgr) -> None:
    h, w = cov.shape
    patch = img[y0 : y0 + h, x0 : x0 + w]
    c = cov[:, :, None]
    patch *= 1.0 - c
    patch += c * np.asarray(bgr, np.float32)[None, None, :]


def _draw_distractors(img, rng, n: int, mask=None, keep_out=()) -> list[dict[str, Any]]:
    """Distractors: blobs of colours no robot wears, plus blobs of the robots' own hues
    that a detector must reject by shape or size (a long thin stripe, a speck). They are
    kept 40 px away from the `keep_out` points (the markers): a distractor touching a
    marker merges with it, which no colour detector can undo."""
    h, w = img.shape[:2]
    out = []
    keep = np.asarray(keep_out, np.float64).reshape(-1, 2)
    for k in range(n):
        kind = k % 4
        for _ in range(100):
            u, v = rng.uniform(20, w - 20), rng.uniform(20, h - 20)
            far = keep.size == 0 or np.min(np.hypot(keep[:, 0] - u, keep[:, 1] - v)) > 40
            if (mask is None or mask[int(v), int(u)]) and far:
                break
        if kind in (0, 1):  # other hue, marker-like disc
            bgr = _DISTRACTOR_BGR[int(rng.integers(len(_DISTRACTOR_BGR)))]
            r = rng.uniform(4.0, 12.0)
            poly = np.stack([u + r * np.cos(np.linspace(0, 2 * math.pi, 48)),
                             v + r * np.sin(np.linspace(0, 2 * math.pi, 48))], -1)  # fmt: skip
            desc = "other-colour disc"
        elif kind == 2:  # robot hue, thin stripe (shape rejection)
            bgr = DEFAULT_MARKER_BGR[int(rng.integers(3))]
            L, t, ang = rng.uniform(30, 60), rng.uniform(2.0, 3.0), rng.uniform(0, math.pi)
            d = np.array([math.cos(ang), math.sin(ang)])
            n_ = np.array([-d[1], d[0]])
            c = np.array([u, v])
            poly = np.stack([c - L / 2 * d - t / 2 * n_, c + L / 2 * d - t / 2 * n_,
                             c + L / 2 * d + t / 2 * n_, c - L / 2 * d + t / 2 * n_])  # fmt: skip
            desc = "marker-colour stripe"
        else:  # robot hue, speck (area rejection)
            bgr = DEFAULT_MARKER_BGR[int(rng.integers(3))]
            r = rng.uniform(0.6, 1.0)
            poly = np.stack([u + r * np.cos(np.linspace(0, 2 * math.pi, 16)),
                             v + r * np.sin(np.linspace(0, 2 * math.pi, 16))], -1)  # fmt: skip
            desc = "marker-colour speck"
        res = _raster_polygon(poly, (h, w))
        if res is not None:
            y0, x0, cov, cen, _ = res
            _paint(img, y0, x0, cov, bgr)
            out.append({"kind": desc, "bgr": list(bgr), "centroid_px": cen.tolist()})
    return out


# --------------------------------------------------------------------------------------
# Marker images.


def render_markers(
    camera: AbstractCamera,
    points_cam: Float[ArrayLike, "n 3"],
    *,
    key: PRNGKeyArray,
    colors: Any = DEFAULT_MARKER_BGR,
    radius: float = 0.06,
    blur_sigma: float = 0.8,
    noise_sigma: float = 3.0,
    distractors: int = 4,
    lighting: float = 0.25,
    background_level: float = 120.0,
    names: Any = None,
    info: dict[str, Any] | None = None,
    objects: Any = None,
    occluders: Any = None,
) -> tuple[np.ndarray, list[dict[str, Any]]]:
    r"""Render coloured spherical markers seen by one camera.

    **Arguments:**

    - `camera`: any jaxloc camera; points are in its frame (a [`jaxloc.PTZCamera`][]'s
      *base* frame, an [`jaxloc.OmniCamera`][]'s mirror frame, a pinhole's optical frame).
    - `points_cam`: marker centres in the camera frame (m), shape `(n, 3)`.
    - `key`: JAX PRNG key (background, lighting, distractors, noise). Keyword only, as
      are the following.
    - `colors`: BGR colour of each marker, `n` triples in 0-255.
    - `radius`: sphere radius (m).
    - `blur_sigma`: Gaussian blur (px, optics/defocus); `noise_sigma`: additive Gaussian
      sensor noise (grey levels); `distractors`: number of distractor blobs;
      `lighting`: strength of the multiplicative illumination change (0 = none).
    - `background_level`: mean grey level of the background.
    - `names`: optional label of each marker for the ground truth.
    - `info`: optional dict that receives `info["distractors"]`, the distractors drawn
      (kind, colour, centroid), and `info["objects"]`, the `objects` drawn.
    - `objects`: other spheres in the scene that are not markers (e.g. a ball of a
      marker-like colour, which the detector must refuse): a sequence of dicts
      `{"center": (3,) in the camera frame (m), "radius": m, "bgr": colour}` (optional
      `"name"`), drawn exactly like the markers and painted with them, far to near.
    - `occluders`: flat things in front of everything else (a mirror's support rod, a
      cable): a sequence of dicts `{"polygon": (m, 3) vertices in the camera frame (m),
      "bgr": colour}` (optional `"name"`); each edge is sampled at 32 points and
      projected through the camera (so straight edges bend with the lens), and they are
      painted last, over every marker and object.

    **Returns:** `(image, truth)`: a `uint8` BGR image `(height, width, 3)` and, per
    marker, a dict with `name`, `visible` (drawn at least partly inside the image and,
    for an omnidirectional camera, the mirror's annulus), `truncated` (partly cut by the
    image border or the annulus), `center_px` (projection of the
    sphere's centre), `centroid_px` (centroid of the drawn silhouette, clipped to the
    image/annulus), `area_px`, `bgr`, and, with `occluders`, `occluded`: the fraction
    of the marker's silhouette they hide (`centroid_px` and `area_px` are then those of
    the part left; a marker with less than half a pixel left is not `visible`). Markers
    are painted far to near (occlusion).
    """
    p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    n = p.shape[0]
    if len(colors) < n:
        raise ValueError(f"`colors` must give one BGR colour per marker ({n}); got {len(colors)}.")
    if not (radius > 0):
        raise ValueError(f"`radius` must be positive; got {radius!r}.")
    rng = numpy_rng(key)
    w, h = camera.image_size
    img = _background(rng, h, w, background_level)
    ring_mask = _mirror_frame(img, camera)
    poly = center = ok = None
    keep_out = []
    if n:
        poly, center, ok = (np.asarray(a) for a in _silhouettes(camera, jnp.asarray(p), radius))
        # Keep distractors clear of every marker's outline (centre and rim points).
        keep_out = [q for i in range(n) if ok[i] for q in poly[i][::8]]
    distractor_info = _draw_distractors(img, rng, distractors, ring_mask, keep_out)
    objs = _object_silhouettes(camera, objects)
    occ_layers = _occluder_coverage(camera, occluders, (h, w), ring_mask)
    occ = np.zeros((h, w), np.float32)
    for _, y0, x0, cov in occ_layers:
        patch = occ[y0 : y0 + cov.shape[0], x0 : x0 + cov.shape[1]]
        np.maximum(patch, cov, out=patch)
    names = [str(i) for i in range(n)] if names is None else names
    truth = _paint_far_to_near(img, camera, p, (poly, center, ok), objs, colors, names,
                               ring_mask, occ, bool(occ_layers))  # fmt: skip
    # Occluders last: in front of every marker and object.
    for bgr, y0, x0, cov in occ_layers:
        _paint(img, y0, x0, cov, bgr)
    gain = _lighting(rng, h, w, lighting)
    image = _finish(img, rng, blur_sigma, noise_sigma, gain)
    if info is not None:
        info["distractors"] = distractor_info
        info["objects"] = [o["entry"] for o in objs]
    return image, truth


def _mirror_frame(img: np.ndarray, camera: AbstractCamera) -> np.ndarray | None:
    """For an omnidirectional camera, darken `img` outside the mirror's annulus (and the
    robot's own reflection inside it) and return the annulus mask (with a 6 px margin);
    `None` for any other camera."""
    if not isinstance(camera, OmniCamera):
        return None
    h, w = img.shape[:2]
    cx, cy, r_in, r_out = annulus_of(camera)
    yy, xx = np.mgrid[0:h, 0:w]
    rr = np.hypot(xx - cx, yy - cy)
    ring_mask = (rr >= r_in - 6) & (rr <= r_out + 6)
    img[~ring_mask] = 8.0  # outside the mirror: dark
    img[rr < r_in - 6] = 45.0  # the robot's own body reflected at the centre
    return ring_mask


def _paint_far_to_near(img, camera, p, markers, objs, colors, names, ring_mask, occ,
                       occluded) -> list[dict[str, Any]]:  # fmt: skip
    """Paint the markers (silhouettes `markers = (poly, center, ok)` of the centres `p`)
    and the other objects far to near, so that the nearer hides the farther, and return
    each marker's truth (see [`render_markers`][]), in the markers' order. The truth keeps
    each marker's own silhouette: overlapping markers are not a centroid test."""
    h, w = img.shape[:2]
    poly, center, ok = markers
    depth = [(float(np.linalg.norm(p[i])), "marker", i) for i in range(len(p))]
    depth += [(float(np.linalg.norm(o["center"])), "object", j) for j, o in enumerate(objs)]
    truth: dict[int, dict[str, Any]] = {}
    for _, kind, i in sorted(depth, key=lambda d: -d[0]):
        if kind == "object":
            o = objs[i]
            if o["ok"]:
                o["entry"].update(_draw_sphere(img, o["poly"], o["bgr"], ring_mask, occ))
            continue
        entry = {"name": names[i], "visible": False, "center_px": None, "centroid_px": None,
                 "area_px": 0.0, "bgr": list(colors[i])}  # fmt: skip
        truth[int(i)] = entry
        if not ok[i]:
            continue
        entry["center_px"] = center[i].tolist()
        pu, pv = poly[i][:, 0], poly[i][:, 1]
        cut = bool(np.any((pu < 0.5) | (pu > w - 1.5) | (pv < 0.5) | (pv > h - 1.5)))
        if ring_mask is not None:
            cx, cy, r_in, r_out = annulus_of(camera)
            rr_p = np.hypot(pu - cx, pv - cy)
            cut = cut or bool(np.any((rr_p < r_in - 6) | (rr_p > r_out + 6)))
        entry["truncated"] = cut
        entry.update(_draw_sphere(img, poly[i], colors[i], ring_mask, occ))
        if occluded and "occluded" not in entry:
            entry["occluded"] = 0.0
    return [truth[i] for i in range(len(p))]


def _draw_sphere(img, poly, bgr, ring_mask, occ) -> dict[str, Any]:
    """Paint one sphere's silhouette `poly` (px) and return its truth: `visible`,
    `area_px` and `centroid_px` of the part that the occluder coverage `occ` leaves
    (and `occluded`, the fraction hidden, when `occ` hides any of it)."""
    h, w = img.shape[:2]
    res = _raster_polygon(poly, (h, w))
    if res is None:
        return {}
    y0, x0, cov, _, _ = res
    if ring_mask is not None:
        cov = cov * ring_mask[y0 : y0 + cov.shape[0], x0 : x0 + cov.shape[1]]
    total = float(cov.sum())
    if total <= 0:
        return {}
    _paint(img, y0, x0, cov, bgr)
    # Centroid of what is actually seen (clipped, not occluded), anti-aliased.
    seen = cov * (1.0 - occ[y0 : y0 + cov.shape[0], x0 : x0 + cov.shape[1]])
    s = float(seen.sum())
    out: dict[str, Any] = {}
    if s < total:
        out["occluded"] = 1.0 - s / total
    if s < 0.5 and s < total:
        return dict(out, area_px=s)
    yy, xx = np.mgrid[y0 : y0 + cov.shape[0], x0 : x0 + cov.shape[1]]
    centroid = [float((seen * xx).sum() / s), float((seen * yy).sum() / s)]
    return dict(out, visible=True, area_px=s, centroid_px=centroid)


def _object_silhouettes(camera: AbstractCamera, objects: Any) -> list[dict[str, Any]]:
    """Silhouettes of `render_markers`' `objects`, each with its truth entry."""
    out = []
    for j, o in enumerate(objects or ()):
        c = np.asarray(o["center"], np.float64).reshape(3)
        r = float(o["radius"])
        if not (r > 0 and np.all(np.isfinite(c))):
            raise ValueError(f"`objects[{j}]` needs a finite `center` and a positive `radius`; "
                             f"got {c.tolist()}, {r!r}.")  # fmt: skip
        poly, center, ok = _silhouettes(camera, jnp.asarray(c[None]), r)
        entry = {"name": o.get("name", f"object{j}"), "visible": False,
                 "center_px": np.asarray(center[0]).tolist() if bool(ok[0]) else None,
                 "centroid_px": None, "area_px": 0.0, "bgr": list(o["bgr"])}  # fmt: skip
        out.append({"center": c, "poly": np.asarray(poly[0]), "ok": bool(ok[0]),
                    "bgr": o["bgr"], "entry": entry})  # fmt: skip
    return out


def _occluder_coverage(camera: AbstractCamera, occluders: Any, shape_hw, ring_mask):
    """`[(bgr, y0, x0, coverage)]` of `render_markers`' `occluders`: each polygon's edges
    sampled at 32 points, projected through the camera and rasterized (anti-aliased),
    clipped to the mirror's annulus for an omnidirectional camera."""
    out = []
    t = np.arange(32) / 32.0
    for j, o in enumerate(occluders or ()):
        v = np.asarray(o["polygon"], np.float64)
        if v.ndim != 2 or v.shape[0] < 3 or v.shape[1] != 3 or not np.all(np.isfinite(v)):
            raise ValueError(f"`occluders[{j}].polygon` must be finite vertices of shape "
                             f"(m >= 3, 3); got shape {v.shape}.")  # fmt: skip
        edges = v[:, None, :] + t[None, :, None] * (np.roll(v, -1, axis=0) - v)[:, None, :]
        pts = jnp.asarray(edges.reshape(-1, 3))
        if not bool(jnp.all(camera.projectable(pts))):
            raise ValueError(f"`occluders[{j}].polygon` is not projectable by the camera "
                             "everywhere (behind it, or outside its model's domain).")  # fmt: skip
        res = _raster_polygon(np.asarray(camera.project(pts)), shape_hw)
        if res is None:
            continue
        y0, x0, cov, _, _ = res
        if ring_mask is not None:
            cov = cov * ring_mask[y0 : y0 + cov.shape[0], x0 : x0 + cov.shape[1]]
        out.append((o["bgr"], y0, x0, cov))
    return out


def _camera_points(rig, poses) -> tuple[np.ndarray, np.ndarray]:
    """Every marker in every camera frame at every step, through the rig's mounts and
    markers (the one projection path, `jaxloc._cycle.sightings`): `(mutual (steps, 3, 3,
    3), overhead (steps, 3, 3))`, `mutual[k, i, j]` robot `j` in robot `i`'s camera."""
    T = poses.T_world_body.wxyz_xyz
    R, p = rotations(T), T[..., 4:]
    dtype = T.dtype
    markers = rig.markers[1:].astype(dtype)
    mutual, _ = mutual_points(
        R, p, rig.mount_rotations()[1:].astype(dtype), rig.mount_translations()[1:].astype(dtype),
        markers,
    )  # fmt: skip
    T_o = poses.T_world_overhead.wxyz_xyz
    over = in_body(rotations(T_o), T_o[4:], marker_in_world(R, p, markers))
    return np.asarray(mutual), np.asarray(over)


def _world_in_cameras(rig, poses, points) -> np.ndarray:
    """World points `(n, 3)` in every camera frame at every step: `(steps, 4, n, 3)`,
    cameras in the order C, C1, C2, C3 (C1: its PTZ's base frame)."""
    T = np.asarray(poses.T_world_body.wxyz_xyz)
    steps = T.shape[0]
    x = np.asarray(points, np.float64).reshape(-1, 3)
    out = np.zeros((steps, 4, x.shape[0], 3))
    if not x.shape[0]:
        return out
    R = np.asarray(rotations(jnp.asarray(T)))
    T_o = np.asarray(poses.T_world_overhead.wxyz_xyz)
    R_o = np.asarray(rotations(jnp.asarray(T_o)))
    mount_R = np.asarray(rig.mount_rotations())[1:]
    mount_t = np.asarray(rig.mount_translations())[1:]
    for k in range(steps):
        out[k, 0] = (x - T_o[4:]) @ R_o
        for i in range(3):
            q = (x - T[k, i, 4:]) @ R[k, i]  # body frame: R^T (x - p)
            out[k, 1 + i] = (q - mount_t[i]) @ mount_R[i]  # camera: R_m^T (q - t_m)
    return out


def _jsonable(d: dict[str, Any]) -> dict[str, Any]:
    return {k: np.asarray(v).tolist() if isinstance(v, np.ndarray | tuple | list) else v
            for k, v in d.items()}  # fmt: skip


def render_cycle(
    scenario,
    truth,
    *,
    key: PRNGKeyArray,
    out_dir: str | os.PathLike | None = None,
    colors: Any = DEFAULT_MARKER_BGR,
    radius: float = 0.06,
    blur_sigma: float = 0.8,
    noise_sigma: float = 3.0,
    distractors: int = 4,
    lighting: float = 0.25,
    objects: Any = None,
    occluders: Any = None,
) -> dict[str, Any]:
    r"""Render every image of one simulated cycle.

    At each step `k` of the cycle: C1's PTZ image (markers of C2, C3), C2's and C3's
    omnidirectional images (the two other ground robots), and the overhead camera's image
    (all three). Robot `i`'s marker has colour `colors[i]` (C1, C2, C3).

    **Arguments:**

    - `scenario`: the [`jaxloc.Scenario`][] (its rig's cameras, mounts and markers).
    - `truth`: the [`jaxloc.CycleTruth`][] of [`jaxloc.simulate_cycle`][].
    - `key`: JAX PRNG key. Keyword only, as are the following.
    - `out_dir`: if given, write `step{k}_{camera}.png` (camera `C`, `C1`, `C2`, `C3`)
      and `truth.json` there.
    - `objects`: spheres standing in the scene, seen by every camera at every step: dicts
      `{"position": (3,) in the cycle's world frame (m), "radius": m, "bgr": colour}`
      (optional `"name"`); see [`jaxloc.render_markers`][].
    - `occluders`: `{camera: [occluder, ...]}`, flat things fixed to a camera (`"C"`,
      `"C1"`, `"C2"`, `"C3"`), in front of it at every step: dicts `{"polygon": (m, 3)
      vertices in that camera's frame (m), "bgr": colour}` as
      [`jaxloc.render_markers`][] takes (C1's frame is its PTZ's base frame).
    - other arguments: as [`jaxloc.render_markers`][].

    **Returns:** `{"images": {(k, cam): uint8 image}, "truth": {...}}` where `truth`
    holds, per image, each marker's `center_px`/`centroid_px`/`visible` (and `occluded`
    when the camera has occluders) and the `objects` seen, and the true poses
    (`T_world_body` `(steps, 3, 7)` wxyz_xyz, `T_world_overhead`) and move distances.
    """
    poses = truth.poses
    steps = poses.T_world_body.wxyz_xyz.shape[0]
    keys = jr.split(key, steps * 4)
    images: dict[tuple[int, str], np.ndarray] = {}
    per_image: dict[str, Any] = {}
    names = ("C1", "C2", "C3")
    rig = scenario.rig
    mutual, over = _camera_points(rig, poses)
    objects = list(objects or ())
    occluders = dict(occluders or {})
    bad = sorted(set(occluders) - {"C", "C1", "C2", "C3"})
    if bad:
        raise ValueError(f"`occluders` keys must be cameras C, C1, C2, C3; got {bad}.")
    where = _world_in_cameras(rig, poses, [o["position"] for o in objects])
    for k in range(steps):
        jobs = [
            ("C", rig.overhead, over[k], (0, 1, 2)),
            ("C1", rig.ptz, mutual[k, 0], (1, 2)),
            ("C2", rig.omni2, mutual[k, 1], (0, 2)),
            ("C3", rig.omni3, mutual[k, 2], (0, 1)),
        ]
        for c, (cam_name, camera, pts, seen) in enumerate(jobs):
            sel = list(seen)
            extra: dict[str, Any] = {}
            objs = [dict(o, center=where[k, c, j]) for j, o in enumerate(objects)]
            img, t = render_markers(
                camera, pts[sel], key=keys[4 * k + c], colors=[colors[j] for j in sel],
                radius=radius, blur_sigma=blur_sigma, noise_sigma=noise_sigma,
                distractors=distractors, lighting=lighting, names=[names[j] for j in sel],
                info=extra, objects=objs, occluders=occluders.get(cam_name),
            )  # fmt: skip
            images[(k, cam_name)] = img
            per_image[f"step{k}_{cam_name}"] = {"step": k, "camera": cam_name, "markers": t,
                                                "distractors": extra["distractors"]}  # fmt: skip
            if objects:
                per_image[f"step{k}_{cam_name}"]["objects"] = extra["objects"]
    gt = {
        "strategy": scenario.strategy,
        "marker_radius_m": radius,
        "marker_bgr": {n: list(c) for n, c in zip(names, colors)},
        "T_world_body_wxyz_xyz": np.asarray(poses.T_world_body.wxyz_xyz).tolist(),
        "T_world_overhead_wxyz_xyz": np.asarray(poses.T_world_overhead.wxyz_xyz).tolist(),
        "move_distances_m": np.asarray(truth.move_distances).tolist(),
        "images": per_image,
    }
    if objects:
        gt["objects"] = [_jsonable(o) for o in objects]
    if occluders:
        gt["occluders"] = {c: [_jsonable(o) for o in v] for c, v in occluders.items()}
    if out_dir is not None:
        out_dir = os.fspath(out_dir)
        os.makedirs(out_dir, exist_ok=True)
        for (k, cam_name), img in images.items():
            path = os.path.join(out_dir, f"step{k}_{cam_name}.png")
            if not cv2.imwrite(path, img, [cv2.IMWRITE_PNG_COMPRESSION, 9]):
                raise ValueError(f"Could not write image `{path}`.")
        with open(os.path.join(out_dir, "truth.json"), "w", encoding="utf-8") as f:
            json.dump(gt, f, indent=1)
    return {"images": images, "truth": gt}


# --------------------------------------------------------------------------------------
# Chessboards.


@jit
def _board_coords(camera: AbstractCamera, T_board_cam: jaxlie.SE3, pixels: Float[Array, "n 2"]):
    """Board-plane coordinates `(n, 2)` (m) hit by the rays of `pixels`, and whether the
    ray hits the board's front (z = 0 plane, ray going towards it)."""
    b = camera.unproject(pixels)  # camera frame
    R = T_board_cam.rotation().as_matrix()
    o = T_board_cam.translation()
    d = b @ R.T  # ray directions in the board frame
    dz = d[:, 2]
    ok = dz * o[2] < 0
    t = jnp.where(ok, -o[2] / jnp.where(ok, dz, 1.0), 0.0)
    xy = o[None, :2] + t[:, None] * d[:, :2]
    return xy, ok


_CHUNK = 32768


def _board_coords_chunked(camera, T_board_cam, pix: np.ndarray):
    n = pix.shape[0]
    xy_out, ok_out = np.empty((n, 2)), np.empty(n, bool)
    for a in range(0, n, _CHUNK):
        part = pix[a : a + _CHUNK]
        m = part.shape[0]
        padded = np.zeros((_CHUNK, 2))
        padded[:m] = part
        xy, ok = _board_coords(camera, T_board_cam, jnp.asarray(padded))
        xy_out[a : a + m] = np.asarray(xy)[:m]
        ok_out[a : a + m] = np.asarray(ok)[:m]
    return xy_out, ok_out


def render_chessboard(
    camera: AbstractCamera,
    T_cam_board: jaxlie.SE3,
    board: tuple[int, int],
    square: float,
    *,
    key: PRNGKeyArray | None = None,
    supersample: int = 3,
    blur_sigma: float = 0.5,
    noise_sigma: float = 2.0,
    border: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""Render a planar chessboard seen through a camera model (grey `uint8` image).

    The board frame has its origin at the first inner corner, x along the columns, y
    along the rows, z out of the board's back (OpenCV's object-point convention:
    corner `(row, col)` at `(col * square, row * square, 0)`). The printed pattern has
    `cols + 1` by `rows + 1` squares (the corner square is black) plus a white margin of
    `border` squares.

    **Arguments:**

    - `camera`: any jaxloc camera.
    - `T_cam_board`: pose of the board in the camera frame (`p_cam = T @ p_board`).
    - `board`: inner corners `(cols, rows)`, as `cv2.findChessboardCorners`' `patternSize`.
    - `square`: square size (m).
    - `key`: JAX PRNG key for the sensor noise (no noise if `None`). Keyword only.
    - `supersample`: rays per pixel side (anti-aliasing).
    - `blur_sigma`, `noise_sigma`: as [`jaxloc.render_markers`][].
    - `border`: white margin around the squares, in squares.

    **Returns:** `(image, corners_px, object_points)`: the image `(height, width)`,
    the true corners' pixels `(rows * cols, 2)` in OpenCV's order (row-major, row 0
    first), NaN where a corner is not visible, and the object points `(rows * cols, 3)`.
    """
    cols, rows = board
    w, h = camera.image_size
    s = int(supersample)
    off = (np.arange(s) + 0.5) / s - 0.5
    T_board_cam = T_cam_board.inverse()
    # Only the pixels near the board's image are traced (its outline, margin included,
    # projected through the camera), in fixed-size chunks: one compilation per camera.
    t = np.linspace(0.0, 1.0, 64)
    lo_x, hi_x = (-1 - border) * square, (cols + border) * square
    lo_y, hi_y = (-1 - border) * square, (rows + border) * square
    edge = np.concatenate([
        np.stack([lo_x + t * (hi_x - lo_x), np.full_like(t, lo_y)], -1),
        np.stack([lo_x + t * (hi_x - lo_x), np.full_like(t, hi_y)], -1),
        np.stack([np.full_like(t, lo_x), lo_y + t * (hi_y - lo_y)], -1),
        np.stack([np.full_like(t, hi_x), lo_y + t * (hi_y - lo_y)], -1),
    ])  # fmt: skip
    edge3 = np.c_[edge, np.zeros(len(edge))]
    p_edge = np.asarray(jax.vmap(lambda q: T_cam_board @ q)(jnp.asarray(edge3)))
    uv_edge = np.asarray(camera.project(jnp.asarray(p_edge)))
    if np.all(np.asarray(camera.projectable(jnp.asarray(p_edge)))):
        x0 = int(max(np.floor(uv_edge[:, 0].min()) - 4, 0))
        x1 = int(min(np.ceil(uv_edge[:, 0].max()) + 5, w))
        y0 = int(max(np.floor(uv_edge[:, 1].min()) - 4, 0))
        y1 = int(min(np.ceil(uv_edge[:, 1].max()) + 5, h))
    else:
        x0, y0, x1, y1 = 0, 0, w, h
    img = np.full((h, w), 90.0)
    if x1 > x0 and y1 > y0:
        uu, vv = np.meshgrid(np.arange(x0, x1, dtype=np.float64),
                             np.arange(y0, y1, dtype=np.float64))  # fmt: skip
        acc = np.zeros(uu.size)
        for dy in off:
            for dx in off:
                pix = np.stack([(uu + dx).ravel(), (vv + dy).ravel()], -1)
                xy, ok = _board_coords_chunked(camera, T_board_cam, pix)
                xy = xy / square
                i = np.floor(xy[:, 0]).astype(np.int64)
                j = np.floor(xy[:, 1]).astype(np.int64)
                inside = ((xy[:, 0] >= -1) & (xy[:, 0] < cols) & (xy[:, 1] >= -1)
                          & (xy[:, 1] < rows))  # fmt: skip
                margin = ((xy[:, 0] >= -1 - border) & (xy[:, 0] < cols + border)
                          & (xy[:, 1] >= -1 - border) & (xy[:, 1] < rows + border))  # fmt: skip
                black = inside & ((i + j) % 2 == 0)
                acc += np.where(ok & margin, np.where(black, 20.0, 235.0), 90.0)
        img[y0:y1, x0:x1] = acc.reshape(uu.shape) / (s * s)
    rng = numpy_rng(key) if key is not None else np.random.default_rng(0)
    out = _finish(img.astype(np.float32), rng, blur_sigma, noise_sigma if key is not None else 0.0,
                  None)  # fmt: skip
    jj, ii = np.mgrid[0:rows, 0:cols]
    obj = np.stack([ii.ravel() * square, jj.ravel() * square, np.zeros(rows * cols)], -1)
    p_cam = np.asarray(jax.vmap(lambda q: T_cam_board @ q)(jnp.asarray(obj)))
    corners = np.asarray(camera.project(jnp.asarray(p_cam)))
    vis = np.asarray(camera.in_view(jnp.asarray(p_cam))) if not isinstance(camera, OmniCamera) \
        else np.asarray(camera.projectable(jnp.asarray(p_cam)))  # fmt: skip
    corners = np.where(vis[:, None], corners, np.nan)
    return out, corners, obj


def _polygon_area_centroid(poly: np.ndarray) -> tuple[float, np.ndarray]:
    x, y = poly[:, 0], poly[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    cross = x * y1 - x1 * y
    a = 0.5 * cross.sum()
    if abs(a) < 1e-12:
        return 0.0, poly.mean(0)
    cx = ((x + x1) * cross).sum() / (6 * a)
    cy = ((y + y1) * cross).sum() / (6 * a)
    return abs(a), np.array([cx, cy])


def sphere_center_pixel(
    camera: AbstractCamera, centroid: Float[ArrayLike, "2"], area: float, iterations: int = 3
) -> np.ndarray:
    r"""Pixel of a spherical marker's centre from the centroid and area of its blob.

    An off-axis sphere images as an (approximately) elliptical blob whose centroid is not
    the projection of the sphere's centre (the outline is the image of the tangent cone,
    wider on the side away from the axis); the offset grows with the angular radius
    squared and with the lens' nonlinearity: 0.2--0.5 px for the paper's cameras at 1--2 m
    with a 6 cm marker. Solved through the camera model: the angular radius from the blob
    area, then fixed-point iterations on the centre direction so that the silhouette's
    area centroid matches the measured one. Works for any central camera model.

    **Arguments:** `camera`; `centroid` `(u, v)` px; `area` of the blob (px^2);
    `iterations` of the fixed point.

    **Returns:** the corrected pixel `(2,)`.
    """
    c = np.asarray(centroid, np.float64)
    x = c.copy()
    a = np.asarray(compiled_unproject(camera, jnp.asarray(x)))
    probe = 0.01
    # Radii as arrays, not Python floats: a float is a static argument of the jitted
    # `_silhouettes`, and every marker's own radius would compile it anew.
    poly, _, ok = (np.asarray(v) for v in _silhouettes(
        camera, jnp.asarray(a[None] * 10.0), jnp.asarray(10.0 * math.sin(probe), a.dtype)
    ))  # fmt: skip
    a1, _ = _polygon_area_centroid(poly[0])
    if not bool(ok[0]) or a1 <= 0 or not area > 0:
        return c
    alpha = probe * math.sqrt(area / a1)
    if not alpha < 0.5:
        return c
    r = 10.0 * math.sin(alpha)
    for _ in range(iterations):
        a = np.asarray(compiled_unproject(camera, jnp.asarray(x)))
        poly, _, ok = (np.asarray(v) for v in _silhouettes(
            camera, jnp.asarray(a[None] * 10.0), jnp.asarray(r, a.dtype)
        ))  # fmt: skip
        if not bool(ok[0]):
            return c
        _, cen = _polygon_area_centroid(poly[0])
        x = x + (c - cen)
    return x
