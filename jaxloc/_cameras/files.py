r"""Camera files and jaxloc's one camera dict format.

**The camera dict** ([`jaxloc.camera_to_dict`][] / [`jaxloc.camera_from_dict`][]) is the
only form in which jaxloc writes a camera: in camera JSON/YAML/OpenCV files and in the
`cameras:` entries of scenario files. Its keys follow OpenCV's calibration files, plus
what OpenCV has no key for (SI units: pixels, radians):

```yaml
model: pinhole                  # pinhole | omni | ptz
image_width: 640
image_height: 480
camera_matrix: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]     # omni: [[fx, skew, cx], ...]
distortion_model: radtan        # radtan | rational | equidistant (see below)
distortion_coefficients: [k1, k2, p1, p2, k3]
# omni only:  xi: 0.9, elevation_min: -0.2094, elevation_max: 0.5585   (rad)
# ptz: no camera_matrix; pan, tilt, zoom (rad; zoom in [0, 1]), and either the
#      two-end model's hfov_wide, hfov_tele (rad) or a zoom_table (below)
```

**Distortion.** `distortion_model` names what `distortion_coefficients` mean:

| `distortion_model` | coefficients | cameras |
|---|---|---|
| `radtan` (default) | `[k1, k2, p1, p2, k3]` (4 = `k3` is 0) | pinhole, ptz |
| `radtan` | `[k1, k2, p1, p2]` | omni |
| `rational` | `[k1, k2, p1, p2, k3, k4, k5, k6]` (OpenCV's rational model) | pinhole, ptz |
| `equidistant` | `[k1, k2, k3, k4]` (`cv2.fisheye`, Kalibr's `equidistant`) | all |

`fisheye` is read as an alias of `equidistant`. jaxloc always writes
`distortion_model`. Without it (OpenCV's own files) the model is `radtan`, except that 8
coefficients are OpenCV's rational model and that `fisheye_model: 1` (what OpenCV's
calibration sample writes for a `cv2.fisheye` calibration) means `equidistant`. A count
that does not fit the model, or a `fisheye_model` that contradicts `distortion_model`,
is an error naming the key, the value and the file: 4 coefficients are never guessed to
be equidistant.

**Zoom table** (a PTZ calibrated at several zoom steps, [`jaxloc.ZoomTable`][]; written
by `jaxloc calibrate --model ptz`):

```yaml
model: ptz
image_width: 640
image_height: 480
distortion_model: radtan
pan: 0.0
tilt: 0.0
zoom: 0.0
zoom_table:
  zooms: [0.0, 0.5, 1.0]        # calibrated steps, strictly increasing in [0, 1]
  fx: [420.1, 640.3, 981.0]     # one value per step (px), likewise fy, cx, cy
  fy: [...]
  cx: [...]
  cy: [...]
  distortion_coefficients: [[...], [...], [...]]   # one row per step, as distortion_model
```

Beside a `zoom_table`, the top-level `distortion_coefficients`, `hfov_wide` and
`hfov_tele` are not used by the camera; they are not written, and reading them is an
error. Every array of the table must have one entry per zoom step.

`distortion_coefficients` may be omitted (no distortion), and so may every ptz key but
the image size and omni's elevation band (the constructors' defaults). Without `model`
the camera is `omni` if it has `xi`, else `pinhole`. Informational keys written by
calibration tools (`INFO_KEYS`: jaxloc's `rms_px`, `num_images`; OpenCV's
`avg_reprojection_error`, `flags`, `extrinsic_parameters`, ...) are read and ignored;
any other key is an error naming it and the file.

**Camera files** ([`jaxloc.save_camera`][], [`jaxloc.load_camera`][]):

- `json` / `yaml`: the camera dict.
- `opencv`: `cv::FileStorage` YAML (`%YAML`, `!!opencv-matrix`), the same camera dict:
  for a pinhole, what `cv2.calibrateCamera` users write (plus `distortion_model`). A PTZ
  is written whole (`model: ptz`, its zoom table as a nested map), so that it reads
  back exactly; save `ptz.pinhole()` for the pinhole at its current zoom. Read from
  files that OpenCV's calibration samples write, too.
- `kalibr`: a Kalibr camchain (`cam0`, `cam1`, ...; `camera_model: pinhole | omni`,
  `distortion_model: radtan | equidistant | none`), import and export. Read with the
  rules of Kalibr's own reader (`kalibr_common/ConfigReader.py`): cameras named `cam0`
  ... `cam<n-1>`, intrinsics and coefficient counts per model, resolution two integers,
  `rostopic` a string, `T_cn_cnm1` a 4x4 rigid transform. Written with a `rostopic` for
  every camera and `T_cn_cnm1` for every camera after the first
  ([`jaxloc.save_camchain`][]). Kalibr's other models (`fov`, `eucm`, `ds`) are refused,
  naming the model, the camera and the file; so is writing a camera Kalibr cannot hold
  (see [`camera_to_kalibr`][]).

A scenario file's `cameras:` entries are read by [`camera_from_spec`][]: a camera dict, a
preset name (`paper_overhead`, `paper_ptz`, `paper_omni`), a preset with overrides
(`{preset: paper_ptz, pan: 0.1}`), or the form scenario files had before the camera dict
(`{type: pinhole, fx: ..., fy: ..., cx: ..., cy: ..., dist: [...], image_size: [w, h]}`:
the constructor's arguments), still read for compatibility.
"""

import dataclasses
import math
import os
import re
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np

from .._core.files import (
    atomic_write,
    check_keys,
    dumps_json,
    dumps_yaml,
    FileFormatError,
    naming_file,
    parse_mapping,
    read_text,
    short,
    short_key,
    syntax_of,
)
from .distortion import DISTORTION_MODELS, EQUIDISTANT, RADTAN
from .models import AbstractCamera, OmniCamera, PinholeCamera, PTZCamera, ZoomTable
from .presets import paper_omni_camera, paper_overhead_camera, paper_ptz_camera


FORMATS = ("opencv", "json", "yaml", "kalibr")
MODELS = ("pinhole", "omni", "ptz")
_SIZE_KEYS = ("model", "image_width", "image_height")
_DIST_KEYS = ("distortion_model", "distortion_coefficients")
#: The keys of the camera dict of each model (see the module docstring).
CAMERA_KEYS = {
    "pinhole": _SIZE_KEYS + ("camera_matrix",) + _DIST_KEYS,
    "omni": _SIZE_KEYS + ("camera_matrix",) + _DIST_KEYS
    + ("xi", "elevation_min", "elevation_max"),
    "ptz": _SIZE_KEYS + _DIST_KEYS + ("pan", "tilt", "zoom", "hfov_wide", "hfov_tele",
                                      "zoom_table"),
}  # fmt: skip
#: The keys of a ptz camera dict's `zoom_table` (all but `distortion_coefficients`
#: required).
ZOOM_TABLE_KEYS = ("zooms", "fx", "fy", "cx", "cy", "distortion_coefficients")
#: The ptz keys a `zoom_table` replaces (the two-end model's).
_TWO_END_KEYS = ("distortion_coefficients", "hfov_wide", "hfov_tele")
#: A camera dict's `distortion_model` values: the camera's `distortion` and the
#: coefficient counts each takes, per camera model (see the module docstring).
DICT_DISTORTIONS = {
    "radtan": (RADTAN, {"pinhole": (4, 5), "ptz": (4, 5), "omni": (4,)}),
    "rational": (RADTAN, {"pinhole": (8,), "ptz": (8,)}),
    "equidistant": (EQUIDISTANT, {"pinhole": (4,), "ptz": (4,), "omni": (4,)}),
}
#: Other names read as a `distortion_model`.
DISTORTION_ALIASES = {"fisheye": "equidistant"}
_COEFFICIENTS = {
    ("radtan", 4): "k1, k2, p1, p2",
    ("radtan", 5): "k1, k2, p1, p2, k3",
    ("rational", 8): "k1, k2, p1, p2, k3, k4, k5, k6",
    ("equidistant", 4): "k1, k2, k3, k4",
}
#: Informational keys a camera file may carry, read and ignored: jaxloc's calibration
#: report (`rms_px`, `num_images`) and what OpenCV's calibration samples write beside
#: the camera (`fisheye_model: 1` marks a `cv2.fisheye` calibration: read as
#: `distortion_model: equidistant`).
INFO_KEYS = (
    "rms_px", "num_images", "calibration_time", "nframes", "nr_of_frames", "board_width",
    "board_height", "square_size", "marker_size", "aspectRatio", "fix_aspect_ratio",
    "flags", "fisheye_model", "avg_reprojection_error", "per_view_reprojection_errors",
    "extrinsic_parameters", "image_points", "grid_points",
)  # fmt: skip
CAMERA_PRESETS = {
    "paper_overhead": paper_overhead_camera,
    "paper_ptz": paper_ptz_camera,
    "paper_omni": paper_omni_camera,
}
_TYPES = {"pinhole": PinholeCamera, "ptz": PTZCamera, "omni": OmniCamera}


def model_of(camera: AbstractCamera) -> str:
    """`"pinhole"`, `"omni"` or `"ptz"`: the `model` of `camera` in its camera dict."""
    for name, cls in _TYPES.items():
        if type(camera) is cls:
            return name
    raise ValueError(
        f"`camera` must be a PinholeCamera, PTZCamera or OmniCamera; got "
        f"{type(camera).__name__}."
    )


def distortion_model_of(camera: AbstractCamera) -> str:
    """The camera dict's `distortion_model` of `camera`: `"radtan"`, `"rational"` (a
    radtan camera with 8 coefficients, in its zoom table for a PTZ) or
    `"equidistant"`."""
    if camera.distortion == EQUIDISTANT:
        return "equidistant"
    table = getattr(camera, "zoom_table", None)
    n = (camera.dist if table is None else table.dist).shape[-1]
    return "rational" if n == 8 else "radtan"


# --------------------------------------------------------------------------------------
# Values.


def _number(where: str, x: Any) -> float:
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, bool) or not isinstance(x, int | float):
        raise ValueError(f"{where} must be a number; got {short(x)}.")
    if not math.isfinite(x):
        raise ValueError(f"{where} must be finite; got {short(x)}.")
    return float(x)


def _numbers(where: str, x: Any, counts: Sequence[int] | None) -> list[float]:
    """A flat list of finite numbers of one of the lengths `counts` (any length >= 1 if
    `None`; an OpenCV column or row matrix is flattened)."""
    if isinstance(x, np.ndarray) and x.ndim == 2 and 1 in x.shape:
        x = x.reshape(-1).tolist()
    elif isinstance(x, list) and x and all(isinstance(r, list) and len(r) == 1 for r in x):
        x = [r[0] for r in x]  # a column written as nested lists
    elif isinstance(x, list) and len(x) == 1 and isinstance(x[0], list):
        x = x[0]  # a row written as nested lists
    if isinstance(x, np.ndarray):
        x = x.tolist()
    if counts is None:
        if not isinstance(x, list | tuple) or not x:
            raise ValueError(f"{where} must be a list of numbers; got {short(x)}.")
    elif not isinstance(x, list | tuple) or len(x) not in counts:
        want = " or ".join(str(n) for n in counts)
        raise ValueError(f"{where} must be a list of {want} numbers; got {short(x)}.")
    return [_number(f"{where}[{i}]", v) for i, v in enumerate(x)]


def _matrix3(where: str, x: Any) -> np.ndarray:
    rows = x.tolist() if isinstance(x, np.ndarray) else x
    if isinstance(rows, list) and len(rows) == 9 and not any(isinstance(r, list) for r in rows):
        rows = [rows[0:3], rows[3:6], rows[6:9]]
    if not isinstance(rows, list) or len(rows) != 3:
        raise ValueError(f"{where} must be a 3x3 matrix (three rows of three numbers); got "
                         f"{short(x)}.")  # fmt: skip
    return np.array([_numbers(f"{where}[{i}]", r, (3,)) for i, r in enumerate(rows)])


def _size(where: str, x: Any) -> int:
    if isinstance(x, np.integer):
        x = int(x)
    if isinstance(x, bool) or not isinstance(x, int) or x <= 0:
        raise ValueError(f"{where} must be a positive integer (pixels); got {short(x)}.")
    return x


# --------------------------------------------------------------------------------------
# The camera dict.


def camera_to_dict(camera: AbstractCamera) -> dict[str, Any]:
    """The camera dict of `camera` (see the module docstring): plain Python values,
    ready for JSON or YAML; [`jaxloc.camera_from_dict`][] reads it back exactly
    (float64; a float32 camera is written as the float64 values of its leaves), the
    distortion model and a PTZ's zoom table included. (With a zoom table, the PTZ's
    unused two-end fields `hfov_wide`, `hfov_tele` and `dist` are not written: they
    read back as the constructor's defaults.)"""
    model = model_of(camera)
    w, h = camera.image_size
    d: dict[str, Any] = {"model": model, "image_width": int(w), "image_height": int(h)}
    if model == "pinhole":
        d["camera_matrix"] = camera.to_opencv()[0].tolist()
    elif model == "omni":
        fx, fy, cx, cy, skew = (float(camera.fx), float(camera.fy), float(camera.cx),
                                float(camera.cy), float(camera.skew))  # fmt: skip
        d["camera_matrix"] = [[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]
    d["distortion_model"] = distortion_model_of(camera)
    table = camera.zoom_table if model == "ptz" else None
    if table is None:
        d["distortion_coefficients"] = np.asarray(camera.dist, np.float64).tolist()
    names = {"omni": ("xi", "elevation_min", "elevation_max"),
             "ptz": ("pan", "tilt", "zoom") + (("hfov_wide", "hfov_tele") if table is None
                                               else ())}.get(model, ())  # fmt: skip
    for name in names:
        d[name] = float(getattr(camera, name))
    if table is not None:
        d["zoom_table"] = zoom_table_to_dict(table)
    return d


def zoom_table_to_dict(table: ZoomTable) -> dict[str, Any]:
    """The `zoom_table` of a ptz camera dict (see the module docstring), float64 values
    as plain lists."""
    d = {k: np.asarray(getattr(table, k), np.float64).tolist()
         for k in ("zooms", "fx", "fy", "cx", "cy")}  # fmt: skip
    d["distortion_coefficients"] = np.asarray(table.dist, np.float64).tolist()
    return d


def camera_from_dict(d: Any, where: str = "`camera`") -> AbstractCamera:
    """Build a camera from its camera dict (see the module docstring).

    **Arguments:**

    - `d`: the mapping.
    - `where`: how messages name it, verbatim (e.g. ``"camera file `cam.json`"``).

    Raises `ValueError` naming `where`, the key and the bad value (bounded): an unknown
    key, a missing one, a wrong type, a distortion model that does not fit its
    coefficients, an inconsistent zoom table, or a value the camera's constructor
    refuses.
    """
    if not isinstance(d, dict):
        raise ValueError(f"{where} must be a mapping; got {short(d)}.")
    model = d.get("model", "omni" if "xi" in d else "pinhole")
    if not isinstance(model, str) or model not in MODELS:
        raise ValueError(f"{where}: `model` must be one of {MODELS}; got {short(model)}.")
    check_keys(d, CAMERA_KEYS[model] + INFO_KEYS, where=where, listed=CAMERA_KEYS[model])
    for key in ("image_width", "image_height") + (("xi",) if model == "omni" else ()):
        if key not in d:
            raise ValueError(f"{where} is missing `{key}`.")
    size = (_size(f"{where}: `image_width`", d["image_width"]),
            _size(f"{where}: `image_height`", d["image_height"]))  # fmt: skip
    build = {"pinhole": _pinhole_from_dict, "omni": _omni_from_dict, "ptz": _ptz_from_dict}
    try:
        return build[model](d, size, where)
    except ValueError as e:
        if where in str(e):
            raise
        raise ValueError(f"{where} is invalid: {e}") from None


def _distortion_name(d: dict, where: str, model: str) -> str | None:
    """The dict's `distortion_model` (aliases resolved; `fisheye_model: 1` read as
    `equidistant`), checked against the camera `model`; `None` if it names none."""
    name = d.get("distortion_model")
    if name is not None:
        known = tuple(DICT_DISTORTIONS) + tuple(DISTORTION_ALIASES)
        if not isinstance(name, str) or name not in known:
            raise ValueError(
                f"{where}: `distortion_model` must be one of {', '.join(DICT_DISTORTIONS)} "
                f"(or `fisheye`, read as `equidistant`); got {short(name)}."
            )
        name = DISTORTION_ALIASES.get(name, name)
        if model not in DICT_DISTORTIONS[name][1]:
            takes = [n for n, (_, counts) in DICT_DISTORTIONS.items() if model in counts]
            raise ValueError(
                f"{where}: `distortion_model: {name}` is not a distortion of the {model} "
                f"camera; it takes {', '.join(takes)}."
            )
    fisheye = d.get("fisheye_model", 0)
    if isinstance(fisheye, bool) or fisheye not in (0, 1):
        raise ValueError(f"{where}: `fisheye_model` must be 0 or 1; got {short(fisheye)}.")
    if fisheye:
        if model == "omni" or name not in (None, "equidistant"):
            what = f"`distortion_model: {name}`" if name else "an omni camera"
            raise ValueError(
                f"{where} is marked `fisheye_model: 1` (a cv2.fisheye calibration, "
                f"equidistant distortion) but is {what}."
            )
        name = "equidistant"
    return name


def _dist(
    d: dict, where: str, model: str, key: str = "distortion_coefficients"
) -> tuple[str, list[float] | None]:
    """The camera dict's distortion model name (`radtan`, `rational` or `equidistant`)
    and the coefficients under `key` (`None` when absent), checked against each other
    (see the module docstring)."""
    name = _distortion_name(d, where, model)
    v = d.get(key)
    if v is None:
        return name or "radtan", None
    if name is None:  # OpenCV's rule: the count says the model
        coeffs = _numbers(f"{where}: `{key}`", v, _RADTAN_COUNTS[model])
        return ("rational" if len(coeffs) == 8 else "radtan"), coeffs
    return name, _coefficients(f"{where}: `{key}`", v, name, model)


#: Coefficient counts without a `distortion_model` (OpenCV's files), per camera model.
_RADTAN_COUNTS = {"pinhole": (4, 5, 8), "ptz": (4, 5, 8), "omni": (4,)}


def _coefficients(where: str, v: Any, name: str, model: str) -> list[float]:
    """The coefficients `v` of distortion model `name` of a `model` camera, or a
    `ValueError` saying what `name` takes."""
    counts = DICT_DISTORTIONS[name][1][model]
    try:
        return _numbers(where, v, counts)
    except ValueError:
        want = " or ".join(f"{n} ({_COEFFICIENTS[(name, n)]})" for n in counts)
        raise ValueError(
            f"{where} must hold {want} coefficients for `distortion_model: {name}`; got "
            f"{short(v)}."
        ) from None


def _stored(name: str, coeffs: list[float] | None, model: str) -> tuple[str, list[float]]:
    """The camera's static `distortion` and its `dist` as the model stores it: zeros
    when absent, radtan's 4 coefficients with `k3 = 0` for a perspective camera."""
    n = {"radtan": 4 if model == "omni" else 5, "rational": 8, "equidistant": 4}[name]
    coeffs = [0.0] * n if coeffs is None else coeffs
    return DICT_DISTORTIONS[name][0], coeffs + [0.0] * (n - len(coeffs))


def _camera_matrix(d: dict, where: str) -> np.ndarray:
    if "camera_matrix" not in d:
        raise ValueError(f"{where} is missing `camera_matrix`.")
    return _matrix3(f"{where}: `camera_matrix`", d["camera_matrix"])


def _pinhole_from_dict(d: dict, size: tuple[int, int], where: str) -> PinholeCamera:
    K = _camera_matrix(d, where)
    distortion, dist = _stored(*_dist(d, where, "pinhole"), "pinhole")
    return PinholeCamera.from_opencv(K, dist, size, distortion=distortion)


def _omni_from_dict(d: dict, size: tuple[int, int], where: str) -> OmniCamera:
    K = _camera_matrix(d, where)
    if K[1, 0] != 0 or K[2].tolist() != [0.0, 0.0, 1.0]:
        raise ValueError(
            f"{where}: `camera_matrix` must be [[fx, skew, cx], [0, fy, cy], [0, 0, 1]]; got "
            f"{np.array2string(K)}."
        )
    distortion, dist = _stored(*_dist(d, where, "omni"), "omni")
    band = {k: _number(f"{where}: `{k}`", d[k]) for k in ("elevation_min", "elevation_max")
            if k in d}  # fmt: skip
    return OmniCamera.from_opencv(K, dist, _number(f"{where}: `xi`", d["xi"]),
                                  size, distortion=distortion, **band)  # fmt: skip


def _ptz_from_dict(d: dict, size: tuple[int, int], where: str) -> PTZCamera:
    names = ("pan", "tilt", "zoom", "hfov_wide", "hfov_tele")
    kwargs: dict[str, Any] = {k: _number(f"{where}: `{k}`", d[k]) for k in names if k in d}
    if "zoom_table" not in d:
        distortion, dist = _stored(*_dist(d, where, "ptz"), "ptz")
        return PTZCamera(image_size=size, dist=dist, distortion=distortion, **kwargs)
    for key in _TWO_END_KEYS:
        if key in d:
            raise ValueError(
                f"{where}: `{key}` is not used beside a `zoom_table` (the table holds the "
                "intrinsics and distortion of every zoom step); remove it."
            )
    name, table = _zoom_table_from_dict(d["zoom_table"], where, _distortion_name(d, where, "ptz"))
    return PTZCamera(image_size=size, zoom_table=table, distortion=DICT_DISTORTIONS[name][0],
                     **kwargs)  # fmt: skip


def _zoom_table_from_dict(t: Any, where: str, name: str | None) -> tuple[str, ZoomTable]:
    """The distortion model name and the [`jaxloc.ZoomTable`][] of a ptz camera dict's
    `zoom_table` (see the module docstring), each array checked against `zooms`."""
    check_keys(t, ZOOM_TABLE_KEYS, where=f"{where}: `zoom_table`")
    for key in ZOOM_TABLE_KEYS[:5]:
        if key not in t:
            raise ValueError(f"{where}: `zoom_table` is missing `{key}`.")
    zooms = _numbers(f"{where}: `zoom_table.zooms`", t["zooms"], None)
    n = len(zooms)
    if n < 2 or not all(0.0 <= z <= 1.0 for z in zooms) or not all(
        a < b for a, b in zip(zooms, zooms[1:])
    ):
        raise ValueError(
            f"{where}: `zoom_table.zooms` must be at least two zoom steps, strictly "
            f"increasing in [0, 1]; got {short(zooms)}."
        )

    def per_step(key: str, got: int) -> None:
        if got != n:
            raise ValueError(
                f"{where}: `zoom_table.{key}` has {got} entries but `zoom_table.zooms` has {n} "
                "zoom steps; the table needs one entry per step."
            )

    columns = {}
    for key in ("fx", "fy", "cx", "cy"):
        columns[key] = _numbers(f"{where}: `zoom_table.{key}`", t[key], None)
        per_step(key, len(columns[key]))
    rows = t.get("distortion_coefficients")
    at = f"{where}: `zoom_table.distortion_coefficients`"

    def row(i: int) -> str:
        return f"{where}: `zoom_table.distortion_coefficients[{i}]`"

    if rows is None:
        name = name or "radtan"
        dist = [_stored(name, None, "ptz")[1]] * n
    else:
        if isinstance(rows, np.ndarray):
            rows = rows.tolist()
        if not isinstance(rows, list) or not all(isinstance(r, list) for r in rows):
            raise ValueError(
                f"{at} must be one row of coefficients per zoom step; got {short(rows)}."
            )
        per_step("distortion_coefficients", len(rows))
        if name is None:  # OpenCV's rule: the count says the model
            rows = [_numbers(row(i), r, _RADTAN_COUNTS["ptz"]) for i, r in enumerate(rows)]
            name = "rational" if len(rows[0]) == 8 else "radtan"
        else:
            rows = [_coefficients(row(i), r, name, "ptz") for i, r in enumerate(rows)]
        if len({len(r) for r in rows}) != 1:
            raise ValueError(
                f"{at} must have the same number of coefficients at every zoom step; got rows "
                f"of {sorted({len(r) for r in rows})}."
            )
        dist = [_stored(name, r, "ptz")[1] for r in rows]
    return name, ZoomTable(zooms, columns["fx"], columns["fy"], columns["cx"], columns["cy"],
                           np.array(dist, np.float64))  # fmt: skip


# --------------------------------------------------------------------------------------
# Scenario-file camera entries: presets and the constructor-argument form.


def camera_fields(camera: AbstractCamera) -> dict[str, Any]:
    """The constructor-argument form of `camera` (`{type: pinhole, fx: ..., ...}`), which
    scenario files used before the camera dict; kept to apply presets' overrides. A
    PTZ's `zoom_table` is in the camera dict's layout (omitted when `None`)."""
    d: dict[str, Any] = {"type": model_of(camera)}
    for f in dataclasses.fields(camera):
        v = getattr(camera, f.name)
        if v is None:
            continue
        if isinstance(v, ZoomTable):
            d[f.name] = zoom_table_to_dict(v)
        elif isinstance(v, str):
            d[f.name] = v
        else:
            d[f.name] = list(v) if isinstance(v, tuple) else np.asarray(v, np.float64).tolist()
    return d


def camera_from_fields(d: dict, where: str) -> AbstractCamera:
    """Build a camera from its constructor-argument form (`{type: omni, xi: ..., fx: ...}`,
    see [`camera_fields`][]). Raises `ValueError` naming `where` and the field."""
    kind = d.get("type")
    if not isinstance(kind, str) or kind not in _TYPES:
        raise ValueError(f"`{where}.type` must be one of {tuple(_TYPES)}; got {short(kind)}.")
    cls = _TYPES[kind]
    names = [f.name for f in dataclasses.fields(cls)]
    check_keys(d, set(names) | {"type"}, where=f"`{where}`")
    kwargs: dict[str, Any] = {}
    for k, v in d.items():
        if k == "image_size":
            ok = isinstance(v, list | tuple) and len(v) == 2
            if not ok or not all(isinstance(n, int) and not isinstance(n, bool) and n > 0
                                 for n in v):  # fmt: skip
                raise ValueError(f"`{where}.image_size` must be two positive integers "
                                 f"[width, height]; got {short(v)}.")  # fmt: skip
            kwargs[k] = (int(v[0]), int(v[1]))
        elif k == "distortion":
            if not isinstance(v, str) or v not in DISTORTION_MODELS:
                raise ValueError(f"`{where}.distortion` must be one of {DISTORTION_MODELS}; "
                                 f"got {short(v)}.")  # fmt: skip
            kwargs[k] = v
        elif k == "zoom_table":
            name = "equidistant" if d.get("distortion") == EQUIDISTANT else None
            kwargs[k] = _zoom_table_from_dict(v, f"`{where}`", name)[1]
        elif k != "type":
            kwargs[k] = (_numbers(f"`{where}.{k}`", v, (len(v),)) if isinstance(v, list | tuple)
                         else _number(f"`{where}.{k}`", v))  # fmt: skip
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as e:
        raise ValueError(f"`{where}` is invalid: {e}") from None


def _from_preset(d: dict, where: str) -> AbstractCamera:
    name = d["preset"]
    if not isinstance(name, str) or name not in CAMERA_PRESETS:
        raise ValueError(
            f"`{where}.preset` must be one of {tuple(CAMERA_PRESETS)}; got {short(name)}."
        )
    camera = CAMERA_PRESETS[name]()
    overrides = {k: v for k, v in d.items() if k != "preset"}
    base = camera_to_dict(camera)
    if set(overrides) <= set(CAMERA_KEYS[base["model"]]):
        return camera_from_dict({**base, **overrides}, where=f"`{where}`")
    return camera_from_fields({**camera_fields(camera), **overrides}, where)


def camera_from_spec(spec: Any, where: str) -> AbstractCamera:
    """A camera from a scenario file's camera entry: a camera dict (with `model`), a
    preset name, `{preset: <name>, <key>: <override>, ...}` (overrides in either form),
    or the constructor-argument form (with `type`). Raises `ValueError` naming `where`."""
    if isinstance(spec, str):
        spec = {"preset": spec}
    if not isinstance(spec, dict):
        raise ValueError(f"`{where}` must be a preset name or a mapping; got {short(spec)}.")
    if "preset" in spec:
        return _from_preset(spec, where)
    if "type" in spec:
        return camera_from_fields(spec, where)
    return camera_from_dict(spec, where=f"`{where}`")


# --------------------------------------------------------------------------------------
# Kalibr camchains.

#: Keys of a camera in a Kalibr camchain (Kalibr's `CameraParameters` and
#: `CameraChainParameters`); jaxloc reads the intrinsics and checks the rest.
KALIBR_KEYS = (
    "camera_model", "intrinsics", "distortion_model", "distortion_coeffs", "resolution",
    "rostopic", "T_cn_cnm1", "T_cam_imu", "timeshift_cam_imu", "cam_overlaps", "line_delay",
)  # fmt: skip
#: Intrinsics of Kalibr's camera models, and its distortion models' coefficient counts.
KALIBR_INTRINSICS = {
    "pinhole": "[fu, fv, pu, pv]",
    "omni": "[xi, fu, fv, pu, pv]",
    "eucm": "[alpha, beta, fu, fv, pu, pv]",
    "ds": "[xi, alpha, fu, fv, pu, pv]",
}
KALIBR_DISTORTIONS = {"radtan": 4, "equidistant": 4, "fov": 1, "none": 0}


def _kalibr_resolution(camera: AbstractCamera) -> list[int]:
    w, h = camera.image_size
    return [int(w), int(h)]


def camera_to_kalibr(
    camera: AbstractCamera,
    name: str = "cam0",
    *,
    rostopic: str | None = None,
    T_cn_cnm1: Any = None,
) -> dict[str, Any]:
    """Kalibr camchain entry `{name: {camera_model, intrinsics, distortion_model,
    distortion_coeffs, resolution, rostopic[, T_cn_cnm1]}}`.

    **Arguments:**

    - `camera`: a pinhole, a PTZ without a zoom table (its pinhole at the current zoom)
      or an omni camera. Its distortion is written as Kalibr's `equidistant`
      (`[k1, k2, k3, k4]`), `radtan` (`[k1, k2, r1, r2]`) or, when every radtan
      coefficient is zero, `none`. An omni camera with equidistant distortion is
      written as `camera_model: omni, distortion_model: equidistant`, the pair of
      Kalibr's C++ `EquidistantOmniProjection`; Kalibr's own Python reader
      (`ConfigReader.py`, "Omni with equidistant model not yet supported!") will not
      load it, jaxloc does. Kalibr cannot hold the rest, which raises `ValueError`
      naming the camera: a nonzero `k3` (Kalibr's radtan has none), OpenCV's rational
      model (8 coefficients), an omni skew, a PTZ with a zoom table (a Kalibr camera has
      one set of intrinsics).
    - `name`: the camera's name in the chain (`cam0`, `cam1`, ...).
    - `rostopic`: its image topic (Kalibr requires one); default `/<name>/image_raw`.
    - `T_cn_cnm1`: for a camera after the first, the 4x4 transform from the previous
      camera's frame into this one's (Kalibr's `T_cn_cnm1`).
    """
    at = f"`{short_key(name, 40)}`"
    if isinstance(camera, PTZCamera):
        if camera.zoom_table is not None:
            raise ValueError(
                f"Camera {at} is a PTZ camera with a zoom table, which has no Kalibr form (a "
                "Kalibr camera has one set of intrinsics); save it as json, yaml or opencv, "
                "or save `camera.pinhole()`, its pinhole at the current zoom."
            )
        camera = camera.pinhole()
    if isinstance(camera, PinholeCamera):
        d = np.asarray(camera.dist, np.float64)
        if camera.distortion == RADTAN and d.shape[0] == 8:
            raise ValueError(
                f"Camera {at} has OpenCV's rational distortion (8 coefficients), which "
                "Kalibr has no model for; save it as opencv, json or yaml, or calibrate "
                "without `--rational`."
            )
        if camera.distortion == RADTAN and d[4] != 0:
            raise ValueError(
                f"Kalibr's `radtan` distortion has no k3; camera {at} has k3 = "
                f"{float(d[4])!r}. Save it in the OpenCV format, or calibrate with "
                "`fix_k3=True`."
            )
        intrinsics = [float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)]
        entry = {"camera_model": "pinhole", "intrinsics": intrinsics}
    elif isinstance(camera, OmniCamera):
        if float(camera.skew) != 0:
            raise ValueError(
                f"Kalibr's `omni` model has no skew; camera {at} has skew = "
                f"{float(camera.skew)!r}."
            )
        intrinsics = [float(camera.xi), float(camera.fx), float(camera.fy), float(camera.cx),
                      float(camera.cy)]  # fmt: skip
        entry = {"camera_model": "omni", "intrinsics": intrinsics}
        d = np.asarray(camera.dist, np.float64)
    else:
        raise ValueError(f"`camera` of type {type(camera).__name__} has no Kalibr form.")
    if camera.distortion == EQUIDISTANT:
        entry["distortion_model"], entry["distortion_coeffs"] = "equidistant", d.tolist()
    elif np.all(d == 0):
        entry["distortion_model"], entry["distortion_coeffs"] = "none", []
    else:
        entry["distortion_model"], entry["distortion_coeffs"] = "radtan", d[:4].tolist()
    entry["resolution"] = _kalibr_resolution(camera)
    entry["rostopic"] = f"/{name}/image_raw" if rostopic is None else str(rostopic)
    if T_cn_cnm1 is not None:
        entry["T_cn_cnm1"] = _rigid4(f"`T_cn_cnm1` of `{name}`", T_cn_cnm1).tolist()
    return {name: entry}


def camchain_to_kalibr(
    cameras: Sequence[AbstractCamera],
    T_cn_cnm1: Sequence[Any] = (),
    rostopics: Sequence[str] | None = None,
) -> dict[str, Any]:
    """A Kalibr camchain of `cameras` (named `cam0`, `cam1`, ...): every camera with a
    `rostopic`, every camera after the first with `T_cn_cnm1` (4x4, from camera `n-1`'s
    frame into camera `n`'s), as Kalibr's `ConfigReader` requires. See
    [`camera_to_kalibr`][]."""
    if not cameras:
        raise ValueError("`cameras` must hold at least one camera.")
    if len(T_cn_cnm1) != len(cameras) - 1:
        raise ValueError(
            f"`T_cn_cnm1` must hold one 4x4 transform per camera after the first "
            f"({len(cameras) - 1}); got {len(T_cn_cnm1)}."
        )
    if rostopics is not None and len(rostopics) != len(cameras):
        raise ValueError(f"`rostopics` must hold one topic per camera; got {short(rostopics)}.")
    chain: dict[str, Any] = {}
    for n, camera in enumerate(cameras):
        topic = None if rostopics is None else rostopics[n]
        T = None if n == 0 else T_cn_cnm1[n - 1]
        chain.update(camera_to_kalibr(camera, f"cam{n}", rostopic=topic, T_cn_cnm1=T))
    return chain


def _rigid4(where: str, x: Any) -> np.ndarray:
    rows = x.tolist() if isinstance(x, np.ndarray) else x
    if not isinstance(rows, list | tuple) or len(rows) != 4:
        raise ValueError(f"{where} must be a 4x4 matrix; got {short(x)}.")
    T = np.array([_numbers(f"{where}[{i}]", r, (4,)) for i, r in enumerate(rows)])
    R = T[:3, :3]
    rigid = np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0
    if not rigid or T[3].tolist() != [0.0, 0.0, 0.0, 1.0]:
        raise ValueError(f"{where} must be a rigid transform [[R, t], [0, 0, 0, 1]] with R a "
                         f"rotation; got {short(T.tolist())}.")  # fmt: skip
    return T


def is_camchain(d: Any) -> bool:
    """Whether mapping `d` looks like a Kalibr camchain: keys `cam<n>` or entries with a
    `camera_model`."""
    if not isinstance(d, dict) or not d or not all(isinstance(v, dict) for v in d.values()):
        return False
    named = all(isinstance(k, str) and re.fullmatch(r"cam\d+", k) for k in d)
    return named or any("camera_model" in v for v in d.values())


def _check_chain_names(d: dict, where: str) -> None:
    expected = [f"cam{n}" for n in range(len(d))]
    for k in d:
        if k not in expected:
            raise ValueError(
                f"{where}: camera `{short_key(k, 40)}` is not a Kalibr camera name; a camchain "
                f"names its {len(d)} cameras {', '.join(expected)}."
            )


def camera_from_kalibr(
    d: Any, name: str | None = None, where: str = "`camchain`"
) -> AbstractCamera:
    """The camera `name` (default `cam0`) of a Kalibr camchain mapping, read with the
    rules of Kalibr's `ConfigReader` (see the module docstring).

    Reads `camera_model` `pinhole` and `omni` with `distortion_model` `radtan`,
    `equidistant` or `none`. `omni` with `equidistant` is read too (Kalibr's C++
    `EquidistantOmniProjection`), although Kalibr's own Python reader refuses that pair
    ("Omni with equidistant model not yet supported!").

    Raises `ValueError` naming `where` (used verbatim in messages), the camera and the bad
    field; Kalibr models jaxloc does not have (`fov`, `eucm`, `ds`) are refused by
    name."""
    if not isinstance(d, dict) or not d:
        raise ValueError(f"{where} must be a Kalibr camchain mapping (cam0: ...); got {short(d)}.")
    _check_chain_names(d, where)
    name = "cam0" if name is None else name
    if name not in d:
        raise ValueError(f"{where} has no camera `{short_key(name, 40)}`; it has {sorted(d)}.")
    at = f"{where}, camera `{name}`"
    e = check_keys(d[name], KALIBR_KEYS, where=at)
    for key in ("camera_model", "distortion_model", "intrinsics", "distortion_coeffs",
                "resolution"):  # fmt: skip
        if key not in e:
            raise ValueError(f"{at} is missing `{key}` (Kalibr requires it).")
        if key == "distortion_model":
            _check_kalibr_models(e["camera_model"], e["distortion_model"], at)
    _check_kalibr_extras(e, at, len(d))
    model, dist_model, intr, coeffs = _kalibr_intrinsics(e, at)
    res = e["resolution"]
    if not isinstance(res, list) or len(res) != 2:
        raise ValueError(f"{at}: `resolution` must be [width, height]; got {short(res)}.")
    size = (_size(f"{at}: `resolution[0]`", res[0]), _size(f"{at}: `resolution[1]`", res[1]))
    try:
        if model == "pinhole":
            return PinholeCamera.from_kalibr(intr, dist_model, coeffs, size)
        return OmniCamera.from_kalibr(intr, coeffs, size, distortion_model=dist_model)
    except ValueError as err:
        raise ValueError(f"{at} is invalid: {err}") from None


def _kalibr_intrinsics(e: dict, at: str) -> tuple[str, str, list[float], list[float]]:
    """Camera model, distortion model, intrinsics and coefficients (`[]` for `none`) of a
    camchain entry, checked as Kalibr's `checkIntrinsics` and `checkDistortion` do."""
    model, dist_model = e["camera_model"], e["distortion_model"]
    layout = KALIBR_INTRINSICS[model]
    intr = _numbers(f"{at}: `intrinsics` {layout}", e["intrinsics"], (layout.count(",") + 1,))
    xi, (fu, fv, pu, pv) = (intr[0], intr[1:]) if model == "omni" else (0.0, intr)
    if xi < 0:
        raise ValueError(f"{at}: `intrinsics` xi must be >= 0; got {xi!r}.")
    if fu <= 0 or fv <= 0:
        raise ValueError(f"{at}: `intrinsics` focal lengths must be positive; got {[fu, fv]}.")
    if pu < 0 or pv < 0:
        raise ValueError(f"{at}: `intrinsics` principal point must be >= 0; got {[pu, pv]}.")
    coeffs = e["distortion_coeffs"]
    if dist_model == "none":
        if coeffs != []:
            raise ValueError(f"{at}: `distortion_coeffs` must be [] for distortion model "
                             f"`none` (Kalibr's rule); got {short(coeffs)}.")  # fmt: skip
        return model, dist_model, intr, []
    n = KALIBR_DISTORTIONS[dist_model]
    return model, dist_model, intr, _numbers(f"{at}: `distortion_coeffs`", coeffs, (n,))


def _check_kalibr_models(model: Any, dist_model: Any, at: str) -> None:
    """Kalibr's camera and distortion model names, and those jaxloc reads."""
    if not isinstance(model, str) or model not in KALIBR_INTRINSICS:
        raise ValueError(f"{at}: unknown `camera_model: {short_key(model, 40)}`; Kalibr's "
                         f"models are {', '.join(KALIBR_INTRINSICS)}.")  # fmt: skip
    if not isinstance(dist_model, str) or dist_model not in KALIBR_DISTORTIONS:
        raise ValueError(f"{at}: unknown `distortion_model: {short_key(dist_model, 40)}`; "
                         f"Kalibr's models are {', '.join(KALIBR_DISTORTIONS)}.")  # fmt: skip
    if model not in ("pinhole", "omni"):
        raise ValueError(f"{at}: `camera_model: {model}` is not supported by jaxloc (Kalibr's "
                         "`pinhole` and `omni` are).")  # fmt: skip
    if dist_model not in ("radtan", "equidistant", "none"):
        raise ValueError(f"{at}: `distortion_model: {dist_model}` is not supported by jaxloc "
                         "(Kalibr's `radtan`, `equidistant` and `none` are).")  # fmt: skip


def _check_kalibr_extras(e: dict, at: str, n_cameras: int) -> None:
    if "rostopic" in e and not isinstance(e["rostopic"], str):
        raise ValueError(f"{at}: `rostopic` must be a string; got {short(e['rostopic'])}.")
    for key in ("T_cn_cnm1", "T_cam_imu"):
        if key in e:
            _rigid4(f"{at}: `{key}`", e[key])
    for key in ("timeshift_cam_imu", "line_delay"):
        if key in e:
            _number(f"{at}: `{key}`", e[key])
    overlaps = e.get("cam_overlaps", [])
    if not isinstance(overlaps, list) or not all(
        isinstance(i, int) and not isinstance(i, bool) and 0 <= i < n_cameras for i in overlaps
    ):
        raise ValueError(f"{at}: `cam_overlaps` must list camera numbers below {n_cameras}; "
                         f"got {short(overlaps)}.")  # fmt: skip


# --------------------------------------------------------------------------------------
# OpenCV FileStorage YAML.


def _opencv_text(d: dict[str, Any]) -> str:
    """`cv::FileStorage` YAML of a camera dict (matrices as `!!opencv-matrix`, vectors as
    one-row matrices, a nested mapping such as `zoom_table` as a FileStorage map)."""
    fs = cv2.FileStorage(
        "camera.yaml",
        cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY | cv2.FILE_STORAGE_FORMAT_YAML,
    )
    _opencv_write(fs, d)
    return fs.releaseAndGetString()


def _opencv_write(fs: Any, d: dict[str, Any]) -> None:
    for k, v in d.items():
        if isinstance(v, dict):
            fs.startWriteStruct(k, cv2.FileNode_MAP)
            _opencv_write(fs, v)
            fs.endWriteStruct()
        elif isinstance(v, str):
            fs.write(k, v)
        elif isinstance(v, bool | int | np.integer):
            fs.write(k, int(v))
        elif isinstance(v, float | np.floating):
            fs.write(k, float(v))
        else:
            m = np.asarray(v, np.float64)
            fs.write(k, m.reshape(1, -1) if m.ndim == 1 else m)


def _opencv_node(node: Any) -> Any:
    if node.isString():
        return node.string()
    if node.isInt():
        return int(node.real())
    if node.isReal():
        return float(node.real())
    if node.isSeq():
        return [_opencv_node(node.at(i)) for i in range(node.size())]
    if node.isMap():
        keys = node.keys()
        if {"dt", "data"} <= set(keys):  # an `!!opencv-matrix` is a map to FileStorage
            m = node.mat()
            return None if m is None else np.asarray(m)
        return {k: _opencv_node(node.getNode(k)) for k in keys}
    return None


def _read_opencv(text: str, where: str) -> dict[str, Any]:
    """The top-level keys of a `cv::FileStorage` YAML text, as Python values."""
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
        if not fs.isOpened():
            raise FileFormatError(f"{where} is not a readable OpenCV YAML file.")
        d = {key: _opencv_node(fs.getNode(key)) for key in fs.root().keys()}
        fs.release()
    except cv2.error as e:
        reason = " ".join(str(e).split())[-200:]
        raise FileFormatError(f"{where} is not a readable OpenCV YAML file: {reason}") from None
    except SystemError:  # cv2.FileStorage's parser fails this way on some garbage
        raise FileFormatError(
            f"{where} is not a readable OpenCV YAML file (OpenCV's parser failed on it)."
        ) from None
    return d


# --------------------------------------------------------------------------------------
# Files.


def save_camera(
    camera: AbstractCamera,
    path: str | os.PathLike,
    format: str | None = None,
    *,
    extra: dict[str, Any] | None = None,
) -> None:
    """Write a camera file, atomically.

    **Arguments:**

    - `camera`: a [`jaxloc.PinholeCamera`][], [`jaxloc.PTZCamera`][] or
      [`jaxloc.OmniCamera`][].
    - `path`: destination.
    - `format`: `"opencv"` (`cv::FileStorage` YAML, as `cv2.calibrateCamera` users
      write it), `"json"` or `"yaml"`: the camera dict, exact for every model (a PTZ
      whole, with its zoom table); or `"kalibr"` (a camchain with one camera, `cam0`;
      see [`camera_to_kalibr`][] for what Kalibr cannot hold). Default: `json` for a
      `.json` suffix, else `opencv`.
    - `extra`: informational keys to store beside the camera (`INFO_KEYS`, e.g.
      `rms_px`; not in the Kalibr format).
    """
    path = os.fspath(path)
    format = ("json" if path.endswith(".json") else "opencv") if format is None else format
    if format not in FORMATS:
        raise ValueError(f"`format` must be one of {FORMATS}; got {short(format)}.")
    if extra:
        check_keys(extra, INFO_KEYS, where="`extra`")
        if format == "kalibr":
            raise ValueError("`extra` cannot be stored in the Kalibr format.")
    if format == "kalibr":
        atomic_write(path, dumps_yaml(camera_to_kalibr(camera)))
        return
    d = {**camera_to_dict(camera), **(extra or {})}
    text = {"json": dumps_json, "yaml": dumps_yaml, "opencv": _opencv_text}[format](d)
    atomic_write(path, text)


def save_camchain(
    cameras: Sequence[AbstractCamera],
    path: str | os.PathLike,
    T_cn_cnm1: Sequence[Any] = (),
    rostopics: Sequence[str] | None = None,
) -> None:
    """Write a Kalibr camchain YAML of `cameras` (`cam0`, `cam1`, ...), atomically; see
    `jaxloc._cameras.files.camchain_to_kalibr` for `T_cn_cnm1` and `rostopics`."""
    atomic_write(path, dumps_yaml(camchain_to_kalibr(cameras, T_cn_cnm1, rostopics)))


def read_camera_mapping(path: str | os.PathLike) -> dict[str, Any]:
    """The mapping in a camera file: OpenCV `FileStorage` YAML (starts with `%YAML`),
    JSON (`.json`) or YAML. Raises `jaxloc._core.files.FileFormatError` naming the
    file."""
    path = os.fspath(path)
    where = f"camera file `{path}`"
    text = read_text(path, what="camera file")
    if text.lstrip().startswith("%YAML"):
        return _read_opencv(text, where)
    return parse_mapping(text, where=where, syntax=syntax_of(path, default="yaml"))


def load_camera(path: str | os.PathLike, name: str | None = None) -> AbstractCamera:
    """Read a camera file: the camera dict as JSON or YAML, OpenCV `cv::FileStorage`
    YAML, or a Kalibr camchain (camera `name`, default `cam0`). See the module docstring.

    Raises `jaxloc._core.files.FileFormatError` (a `ValueError`; for a missing file
    also a `FileNotFoundError`) naming the file, and the bad key or value."""
    path = os.fspath(path)
    d = read_camera_mapping(path)
    where = f"camera file `{path}`"
    with naming_file(path, "camera file"):
        if is_camchain(d):
            return camera_from_kalibr(d, name, where=where)
        if name is not None:
            raise FileFormatError(
                f"{where} is not a Kalibr camchain; a camera `name` ({short_key(name, 40)}) "
                "applies only to camchains."
            )
        return camera_from_dict(d, where=where)
