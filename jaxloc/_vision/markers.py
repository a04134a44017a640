r"""Colour-marker detection with OpenCV (DESIGN §5, image front end).

Each robot wears a marker of its own colour. [`jaxloc.detect_markers`][] finds, in one
BGR image, the marker of every requested robot:

1. **Coarse search** (half resolution, `coarse=2`): HSV thresholding with each robot's
   range ([`jaxloc.MarkerColor`][]; hue may wrap around red), connected components;
   it only proposes regions, so that the full-resolution work is done on a few small
   windows (the whole detection stays under ~2 ms per 640x480 image on one core).
2. **Fine stage** (full resolution, in each window): HSV thresholding, morphological
   opening (removes isolated noise pixels), connected components, rejection by area
   (`min_area`, `max_area`) and shape (elongation from the second moments,
   `max_elongation`, fill ratio of the moment ellipse, `min_fill`, and solidity, the
   area over the convex hull's, `min_solidity`, which rejects crossing stripes), and, for
   omnidirectional images, by an annulus mask (the mirror's elevation band).
3. **Sub-pixel centroid**: intensity-weighted first moments over the blob dilated by
   two pixels, the weight being the pixel's chroma `max(B,G,R) - min(B,G,R)` minus the
   local background chroma. Blending a marker colour with a neutral (grey) background
   makes chroma *linear in the pixel's coverage*, whatever the grey level and the
   illumination gain, so the weighted centroid is that of the anti-aliased, blurred
   marker (unbiased for symmetric blur).

Each robot gets a [`jaxloc.MarkerDetection`][]: pixel `(u, v)` (OpenCV convention, origin
at the centre of the top-left pixel), a detection flag, the blob's spread (intensity-
weighted RMS radius, px), its area and the number of candidate blobs that passed every
test (more than one means an ambiguous image; the largest blob is used).
"""

import dataclasses
import math
import os
from typing import Any

import cv2
import numpy as np

from .._core.files import short, short_key


@dataclasses.dataclass(frozen=True)
class MarkerColor:
    """HSV range of one robot's marker, on OpenCV's scales (H in 0..179, S and V in
    0..255). If `hue_low > hue_high` the range wraps around 180 (red).

    **Fields:** `hue_low`, `hue_high`, `sat_min`, `val_min`, `sat_max = 255`,
    `val_max = 255`.
    """

    hue_low: int
    hue_high: int
    sat_min: int = 90
    val_min: int = 40
    sat_max: int = 255
    val_max: int = 255

    def __post_init__(self):
        for name, hi in (("hue_low", 179), ("hue_high", 179), ("sat_min", 255),
                         ("val_min", 255), ("sat_max", 255), ("val_max", 255)):  # fmt: skip
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 <= v <= hi:
                raise ValueError(
                    f"`MarkerColor({name}=...)` must be an integer in [0, {hi}] (OpenCV HSV "
                    f"scale); got {v!r}."
                )
        if self.sat_min > self.sat_max or self.val_min > self.val_max:
            raise ValueError(
                "`MarkerColor` needs `sat_min <= sat_max` and `val_min <= val_max`; got "
                f"sat {self.sat_min}..{self.sat_max}, val {self.val_min}..{self.val_max}."
            )

    def ranges(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """`cv2.inRange` bounds: one pair, or two when the hue wraps."""
        lo_sv = (self.sat_min, self.val_min)
        hi_sv = (self.sat_max, self.val_max)
        if self.hue_low <= self.hue_high:
            return [(np.array((self.hue_low, *lo_sv), np.uint8),
                     np.array((self.hue_high, *hi_sv), np.uint8))]  # fmt: skip
        return [
            (np.array((self.hue_low, *lo_sv), np.uint8), np.array((179, *hi_sv), np.uint8)),
            (np.array((0, *lo_sv), np.uint8), np.array((self.hue_high, *hi_sv), np.uint8)),
        ]

    @classmethod
    def from_dict(cls, d: Any, where: str = "marker") -> "MarkerColor":
        """From a mapping `{hue: [low, high], sat_min: .., val_min: .., ...}` or a name
        of [`jaxloc.DEFAULT_MARKER_COLORS`][] (`red`, `green`, `blue`)."""
        if isinstance(d, str):
            if d not in DEFAULT_MARKER_COLORS:
                raise ValueError(
                    f"`{where}` must be one of {sorted(DEFAULT_MARKER_COLORS)} or a mapping "
                    f"with `hue: [low, high]`; got {short(d)}."
                )
            return DEFAULT_MARKER_COLORS[d]
        if not isinstance(d, dict):
            raise ValueError(f"`{where}` must be a colour name or a mapping; got {short(d)}.")
        allowed = {"hue", "sat_min", "val_min", "sat_max", "val_max"}
        for k in d:
            if k not in allowed:
                raise ValueError(
                    f"Unknown key `{where}.{short_key(k)}`; expected one of {sorted(allowed)}."
                )
        hue = d.get("hue")
        if not isinstance(hue, (list, tuple)) or len(hue) != 2:
            raise ValueError(f"`{where}.hue` must be [low, high] (0..179); got {short(hue)}.")
        kw = {k: d[k] for k in allowed - {"hue"} if k in d}
        try:
            return cls(hue[0], hue[1], **kw)
        except ValueError as e:
            raise ValueError(f"`{where}` is invalid: {e}") from None


DEFAULT_MARKER_COLORS = {
    "red": MarkerColor(170, 10),
    "green": MarkerColor(45, 75),
    "blue": MarkerColor(105, 130),
}
"""Ranges matching [`jaxloc.render_cycle`][]'s default marker colours."""


@dataclasses.dataclass(frozen=True)
class MarkerDetection:
    """One robot's marker in one image.

    **Fields:**

    - `pixel`: sub-pixel centroid `(u, v)`, NaN if not detected, shape `(2,)`.
    - `detected`: whether a blob passed every test.
    - `spread`: intensity-weighted RMS radius of the blob (px); NaN if not detected.
    - `area`: pixel count of the blob (px^2); 0 if not detected.
    - `candidates`: blobs of this colour that passed every test (> 1: ambiguous).
    - `truncated`: the blob touches the image border or the edge of `mask`: part of the
      marker is cut off and its centroid is biased (by several pixels for a half-cut
      marker). Callers that need accuracy should treat it as missing.
    """

    pixel: np.ndarray
    detected: bool
    spread: float
    area: float
    candidates: int
    truncated: bool = False


def annulus_mask(image_size: tuple[int, int], annulus) -> np.ndarray:
    """`uint8` mask (255 inside) of `annulus = (cx, cy, r_inner, r_outer)` (px) for an
    image of `image_size = (width, height)`; see [`jaxloc.annulus_of`][]."""
    w, h = image_size
    cx, cy, r_in, r_out = (float(x) for x in annulus)
    if not (0 <= r_in < r_out):
        raise ValueError(
            f"`annulus` radii must satisfy 0 <= r_inner < r_outer; got {r_in}, {r_out}."
        )
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = (xx - cx) ** 2 + (yy - cy) ** 2
    return (((r2 >= r_in**2) & (r2 <= r_out**2)) * 255).astype(np.uint8)


def check_image(image: Any, where: str = "image") -> np.ndarray:
    """Validate a BGR image: `uint8`, shape `(h, w, 3)`, non-empty. Raises `ValueError`."""
    if not isinstance(image, np.ndarray):
        raise ValueError(
            f"`{where}` must be a NumPy array (BGR image); got {type(image).__name__}."
        )
    if image.ndim != 3 or image.shape[2] != 3 or image.shape[0] < 8 or image.shape[1] < 8:
        raise ValueError(
            f"`{where}` must be a colour image of shape (height, width, 3), at least 8x8; "
            f"got shape {image.shape}."
        )
    if image.dtype != np.uint8:
        raise ValueError(f"`{where}` must have dtype uint8; got {image.dtype}.")
    return image


def imread(path: str, flags: int) -> np.ndarray:
    """`cv2.imread(path, flags)`; raise `FileNotFoundError` for a missing file and
    `ValueError` naming the file for an unreadable one."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"Image file `{path}` does not exist.")
    img = cv2.imread(path, flags)
    if img is None:
        raise ValueError(
            f"Image file `{path}` is not a readable image (corrupt or unknown format)."
        )
    return img


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read a colour image file (BGR `uint8`); raise `FileNotFoundError` for a missing
    file and `ValueError` naming the file for an unreadable or non-colour one."""
    path = os.fspath(path)
    img = imread(path, cv2.IMREAD_UNCHANGED)
    if img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 1):
        raise ValueError(
            f"Image file `{path}` is greyscale (shape {img.shape}); colour markers need a "
            "colour (BGR) image."
        )
    if img.dtype != np.uint8:
        raise ValueError(f"Image file `{path}` has {img.dtype} pixels; 8-bit images are expected.")
    if img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return check_image(img, f"image file {path}")


def _threshold(hsv: np.ndarray, color: MarkerColor) -> np.ndarray:
    rs = color.ranges()
    m = cv2.inRange(hsv, rs[0][0], rs[0][1])
    if len(rs) == 2:
        m |= cv2.inRange(hsv, rs[1][0], rs[1][1])
    return m


_KERNEL3 = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
_KERNEL5 = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))


def _moments_shape(mask: np.ndarray):
    """Elongation (major/minor axis ratio) and fill ratio (area over the moment
    ellipse's area) of a binary blob."""
    m = cv2.moments(mask, binaryImage=True)
    a = m["m00"]
    if a <= 0:
        return np.inf, 0.0
    mu20, mu02, mu11 = m["mu20"] / a, m["mu02"] / a, m["mu11"] / a
    tr, det = mu20 + mu02, mu20 * mu02 - mu11 * mu11
    disc = math.sqrt(max(tr * tr / 4 - det, 0.0))
    l1, l2 = tr / 2 + disc, max(tr / 2 - disc, 1e-12)
    # A uniform ellipse of semi-axes (a, b) has variances a^2/4, b^2/4: area 4 pi sqrt(l1 l2).
    ellipse_area = 4.0 * math.pi * math.sqrt(l1 * l2) + 1e-12
    # Pixel quantization: a blob of a few pixels is never a perfect ellipse; add a pixel's
    # variance (1/12 per axis) before judging.
    ellipse_area = 4.0 * math.pi * math.sqrt((l1 + 1 / 12) * (l2 + 1 / 12))
    return math.sqrt((l1 + 1 / 12) / (l2 + 1 / 12)), a / ellipse_area


def detect_markers(
    image: np.ndarray,
    colors: dict[str, MarkerColor],
    *,
    mask: np.ndarray | None = None,
    min_area: float = 6.0,
    max_area: float = 5000.0,
    max_elongation: float = 3.0,
    min_fill: float = 0.6,
    min_solidity: float = 0.85,
    coarse: int = 2,
) -> dict[str, MarkerDetection]:
    r"""Find each robot's colour marker in a BGR image.

    **Arguments:**

    - `image`: `uint8` BGR image `(height, width, 3)` (as `cv2.imread` gives).
    - `colors`: `{robot name: MarkerColor}`.
    - `mask`: optional `uint8` `(height, width)` mask (nonzero = search here), e.g.
      [`jaxloc.annulus_mask`][] for an omnidirectional image. Keyword only, as are the
      following.
    - `min_area`, `max_area`: accepted blob area (px^2, after opening).
    - `max_elongation`: largest major/minor axis ratio of the blob's second moments.
    - `min_solidity`: smallest ratio of the blob's area to that of its convex hull
      (rejects crosses and touching clutter).
    - `min_fill`: smallest ratio of the blob's area to that of its moment ellipse
      (rejects rings, crosses, ragged clutter).
    - `coarse`: downsampling factor of the proposal stage (1 = search at full
      resolution).

    **Returns:** `{robot name: MarkerDetection}`.
    """
    check_image(image)
    h, w = image.shape[:2]
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != (h, w):
            raise ValueError(f"`mask` must have shape {(h, w)} like the image; got {mask.shape}.")
        mask = (mask > 0).astype(np.uint8) * 255
    if not isinstance(coarse, int) or coarse < 1:
        raise ValueError(f"`coarse` must be a positive integer; got {coarse!r}.")
    if coarse > 1:
        small = cv2.resize(image, (w // coarse, h // coarse), interpolation=cv2.INTER_AREA)
        small_mask = None
        if mask is not None:
            small_mask = cv2.resize(
                mask, (w // coarse, h // coarse), interpolation=cv2.INTER_NEAREST
            )
    else:
        small, small_mask = image, mask
    hsv_small = cv2.cvtColor(small, cv2.COLOR_BGR2HSV)
    out = {}
    for name, color in colors.items():
        m = _threshold(hsv_small, color)
        if small_mask is not None:
            m &= small_mask
        # Proposals: outer contours (much cheaper than labelling the whole image),
        # as full-resolution windows, merged when they overlap.
        contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        boxes = []
        pad = 4
        for c in contours:
            x, y, bw, bh = cv2.boundingRect(c)
            if bw * bh * coarse * coarse < 0.25 * min_area:
                continue
            if min(bw, bh) * coarse > 4 * math.sqrt(max_area):
                continue
            x0, y0 = max(x * coarse - pad, 0), max(y * coarse - pad, 0)
            x1, y1 = min((x + bw) * coarse + pad, w), min((y + bh) * coarse + pad, h)
            boxes.append((x0, y0, x1, y1))
        cands = []
        for x0, y0, x1, y1 in _merge_boxes(boxes):
            cands.extend(_fine(image, mask, color, x0, y0, x1, y1, min_area, max_area,
                               max_elongation, min_fill, min_solidity))  # fmt: skip
        if not cands:
            out[name] = MarkerDetection(np.full(2, np.nan), False, math.nan, 0.0, 0)
            continue
        best = max(cands, key=lambda c: c[2])
        out[name] = MarkerDetection(best[0], True, best[1], best[2], len(cands), best[3])
    return out


def _merge_boxes(boxes):
    boxes = list(boxes)
    merged = True
    while merged and len(boxes) > 1:
        merged = False
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                a, b = boxes[i], boxes[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    boxes[i] = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
                    del boxes[j]
                    merged = True
                    break
            if merged:
                break
    return boxes


def _fine(image, mask, color, x0, y0, x1, y1, min_area, max_area, max_elongation, min_fill,
          min_solidity):  # fmt: skip
    """Full-resolution blobs in one window: list of `(pixel, spread, area)`."""
    # Widen the window so that the dilated blob and a background ring fit inside.
    h, w = image.shape[:2]
    x0, y0, x1, y1 = max(x0 - 4, 0), max(y0 - 4, 0), min(x1 + 4, w), min(y1 + 4, h)
    roi = image[y0:y1, x0:x1]
    hsv = cv2.cvtColor(roi, cv2.COLOR_BGR2HSV)
    m = _threshold(hsv, color)
    if mask is not None:
        m &= mask[y0:y1, x0:x1]
    m = cv2.morphologyEx(m, cv2.MORPH_OPEN, _KERNEL3)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    if n <= 1:
        return []
    b, g, r = cv2.split(roi)
    chroma = cv2.subtract(cv2.max(cv2.max(b, g), r), cv2.min(cv2.min(b, g), r))
    chroma = chroma.astype(np.float32)
    roi_mask = None if mask is None else mask[y0:y1, x0:x1]
    out = []
    for lab in range(1, n):
        area = float(stats[lab, cv2.CC_STAT_AREA])
        if not (min_area <= area <= max_area):
            continue
        blob = (labels == lab).astype(np.uint8)
        elong, fill = _moments_shape(blob)
        if elong > max_elongation or fill < min_fill:
            continue
        contours, _ = cv2.findContours(blob, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        hull_area = max(cv2.contourArea(cv2.convexHull(max(contours, key=len))), 1e-9)
        # Contour areas pass through pixel centres: compare with the polygon area of the
        # blob's own contour (not its pixel count), so small discs are not penalized.
        solidity = cv2.contourArea(max(contours, key=len)) / hull_area
        if solidity < min_solidity:
            continue
        # Support of the weighted centroid: the blob dilated by 2 px (its blurred,
        # anti-aliased rim), minus other blobs; background chroma: mean over the ring
        # between 2 and 4 px outside the blob.
        d2 = cv2.dilate(blob, _KERNEL5)
        d4 = cv2.dilate(d2, _KERNEL5)
        free = labels == 0
        support = (d2 > 0) & (free | (labels == lab))
        ring = ((d4 > 0) & (d2 == 0) & free).astype(np.uint8)
        bg = cv2.mean(chroma, mask=ring)[0] if cv2.countNonZero(ring) else 0.0
        wgt = cv2.max(chroma - np.float32(bg), 0.0)
        wgt[~support] = 0.0
        if roi_mask is not None:
            wgt[roi_mask == 0] = 0.0
        mo = cv2.moments(wgt)
        s = mo["m00"]
        if s <= 0:
            continue
        cu, cv = mo["m10"] / s, mo["m01"] / s
        spread = math.sqrt(max((mo["mu20"] + mo["mu02"]) / s, 0.0))
        bx, by, bw, bh = stats[lab, :4]
        truncated = bool(
            bx + x0 <= 0 or by + y0 <= 0 or bx + bw + x0 >= w or by + bh + y0 >= h
            or (roi_mask is not None and np.any(roi_mask[d2 > 0] == 0))
        )
        out.append((np.array([cu + x0, cv + y0]), spread, area, truncated))
    return out
