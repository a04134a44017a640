r"""Camera files: OpenCV calibration YAML (`cv::FileStorage`: `camera_matrix`,
`distortion_coefficients`, `xi`, `image_width`, `image_height`), JSON with the same keys,
and Kalibr camchain YAML (`camera_model: pinhole | omni`, `distortion_model: radtan`);
[`jaxloc.save_camera`][], [`jaxloc.load_camera`][].
"""

import json
import os
import tempfile
from typing import Any

import cv2
import numpy as np
import yaml

from .models import AbstractCamera, OmniCamera, PinholeCamera, PTZCamera


FORMATS = ("opencv", "json", "kalibr")


def camera_to_dict(camera: AbstractCamera) -> dict[str, Any]:
    """OpenCV-style dict of a camera: `model` (`pinhole` or `omni`), `image_width`,
    `image_height`, `camera_matrix` (3x3 nested list), `distortion_coefficients`
    (pinhole: k1, k2, p1, p2, k3; omni: k1, k2, p1, p2), and `xi` for omni. A
    [`jaxloc.PTZCamera`][] is written as its pinhole at the current zoom."""
    if isinstance(camera, PTZCamera):
        camera = camera.pinhole()
    if isinstance(camera, PinholeCamera):
        K, dist, (w, h) = camera.to_opencv()
        return {"model": "pinhole", "image_width": w, "image_height": h,
                "camera_matrix": K.tolist(), "distortion_coefficients": dist.tolist()}  # fmt: skip
    if isinstance(camera, OmniCamera):
        K = np.array([[float(camera.fx), float(camera.skew), float(camera.cx)],
                      [0.0, float(camera.fy), float(camera.cy)], [0.0, 0.0, 1.0]])  # fmt: skip
        w, h = camera.image_size
        return {"model": "omni", "image_width": w, "image_height": h, "camera_matrix": K.tolist(),
                "distortion_coefficients": np.asarray(camera.dist, np.float64).tolist(),
                "xi": float(camera.xi)}  # fmt: skip
    raise ValueError(
        f"`camera` must be a PinholeCamera, PTZCamera or OmniCamera; got {type(camera).__name__}."
    )


def camera_from_dict(d: Any, where: str = "camera") -> AbstractCamera:
    """Inverse of [`jaxloc.camera_to_dict`][]; also accepts `K`/`D`/`dist` as key
    aliases and a missing `model` (omni if `xi` is present). Raises `ValueError` naming
    the bad field."""
    if not isinstance(d, dict):
        raise ValueError(f"`{where}` must be a mapping; got {type(d).__name__}.")

    def get(*keys, required=True):
        for k in keys:
            if k in d:
                return d[k]
        if required:
            raise ValueError(f"`{where}` is missing `{keys[0]}`.")
        return None

    model = d.get("model", "omni" if "xi" in d else "pinhole")
    if model not in ("pinhole", "omni"):
        raise ValueError(f"`{where}.model` must be 'pinhole' or 'omni'; got {model!r}.")
    try:
        K = np.asarray(get("camera_matrix", "K"), dtype=np.float64).reshape(3, 3)
    except (TypeError, ValueError) as e:
        raise ValueError(f"`{where}.camera_matrix` must be a 3x3 matrix of numbers: {e}") from None
    dist = get("distortion_coefficients", "dist", "D", required=False)
    w = get("image_width")
    h = get("image_height")
    for name, v in (("image_width", w), ("image_height", h)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v <= 0:
            raise ValueError(f"`{where}.{name}` must be a positive integer; got {v!r}.")
    try:
        if model == "pinhole":
            return PinholeCamera.from_opencv(K, dist, (int(w), int(h)))
        xi = get("xi")
        D = np.zeros(4) if dist is None else np.asarray(dist, np.float64).ravel()
        return OmniCamera.from_opencv(K, D, xi, (int(w), int(h)))
    except ValueError as e:
        raise ValueError(f"`{where}` is invalid: {e}") from None


def camera_to_kalibr(camera: AbstractCamera, name: str = "cam0") -> dict[str, Any]:
    """Kalibr camchain entry `{name: {camera_model, intrinsics, distortion_model,
    distortion_coeffs, resolution}}`. Kalibr's `radtan` has no `k3` and its `omni` no
    skew: a camera with either nonzero raises `ValueError`."""
    if isinstance(camera, PTZCamera):
        camera = camera.pinhole()
    w, h = camera.image_size
    if isinstance(camera, PinholeCamera):
        d = np.asarray(camera.dist, np.float64)
        if d[4] != 0:
            raise ValueError(
                f"Kalibr's `radtan` distortion has no k3; this camera has k3 = {d[4]!r}. Save "
                "it in the OpenCV format, or calibrate with `fix_k3=True`."
            )
        entry = {"camera_model": "pinhole",
                 "intrinsics": [float(camera.fx), float(camera.fy), float(camera.cx),
                                float(camera.cy)],
                 "distortion_model": "radtan", "distortion_coeffs": d[:4].tolist()}  # fmt: skip
    elif isinstance(camera, OmniCamera):
        if float(camera.skew) != 0:
            raise ValueError(
                f"Kalibr's `omni` model has no skew; this camera has skew = {float(camera.skew)!r}."
            )
        entry = {"camera_model": "omni",
                 "intrinsics": [float(camera.xi), float(camera.fx), float(camera.fy),
                                float(camera.cx), float(camera.cy)],
                 "distortion_model": "radtan",
                 "distortion_coeffs": np.asarray(camera.dist, np.float64).tolist()}  # fmt: skip
    else:
        raise ValueError(f"`camera` of type {type(camera).__name__} has no Kalibr form.")
    entry["resolution"] = [int(w), int(h)]
    return {name: entry}


def camera_from_kalibr(d: Any, name: str | None = None, where: str = "camchain") -> AbstractCamera:
    """Camera of a Kalibr camchain mapping (`cam0` by default, or the only camera)."""
    if not isinstance(d, dict) or not d:
        raise ValueError(f"`{where}` must be a Kalibr camchain mapping (cam0: ...); got {d!r}.")
    if name is None:
        name = "cam0" if "cam0" in d else sorted(d)[0]
    if name not in d:
        raise ValueError(f"`{where}` has no camera `{name}`; it has {sorted(d)}.")
    e = d[name]
    w = f"{where}.{name}"
    if not isinstance(e, dict):
        raise ValueError(f"`{w}` must be a mapping; got {e!r}.")
    model = e.get("camera_model")
    dm = e.get("distortion_model", "none")
    if dm not in ("radtan", "none"):
        raise ValueError(
            f"`{w}.distortion_model` must be 'radtan' (or 'none'); got {dm!r}: jaxloc has no "
            "equidistant/fov distortion."
        )
    coeffs = e.get("distortion_coeffs", [0.0, 0.0, 0.0, 0.0]) if dm == "radtan" else [0.0] * 4
    if not isinstance(coeffs, list) or len(coeffs) != 4:
        raise ValueError(f"`{w}.distortion_coeffs` must be [k1, k2, r1, r2]; got {coeffs!r}.")
    res = e.get("resolution")
    if not isinstance(res, list) or len(res) != 2:
        raise ValueError(f"`{w}.resolution` must be [width, height]; got {res!r}.")
    intr = e.get("intrinsics")
    try:
        if model == "pinhole":
            if not isinstance(intr, list) or len(intr) != 4:
                raise ValueError(f"`{w}.intrinsics` must be [fu, fv, pu, pv]; got {intr!r}.")
            fu, fv, pu, pv = (float(x) for x in intr)
            return PinholeCamera(fu, fv, pu, pv, [*map(float, coeffs), 0.0], tuple(res))
        if model == "omni":
            return OmniCamera.from_kalibr(intr, coeffs, tuple(res))
    except ValueError as err:
        raise ValueError(f"`{w}` is invalid: {err}") from None
    raise ValueError(f"`{w}.camera_model` must be 'pinhole' or 'omni'; got {model!r}.")


def _write_atomic(path: str, text: str | None = None, writer=None) -> None:
    d = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(dir=d, suffix=os.path.splitext(path)[1])
    os.close(fd)
    try:
        if writer is not None:
            writer(tmp)
        else:
            with open(tmp, "w", encoding="utf-8") as f:
                f.write(text)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def save_camera(
    camera: AbstractCamera,
    path: str | os.PathLike,
    format: str | None = None,
    *,
    extra: dict[str, Any] | None = None,
) -> None:
    """Write a camera file.

    **Arguments:**

    - `camera`: a [`jaxloc.PinholeCamera`][], [`jaxloc.PTZCamera`][] (its pinhole at the
      current zoom) or [`jaxloc.OmniCamera`][].
    - `path`: destination; written atomically.
    - `format`: `"opencv"` (`cv::FileStorage` YAML, as `cv2.calibrateCamera` users write
      it), `"json"` (same keys) or `"kalibr"` (camchain YAML, `cam0`). Default: `json`
      for a `.json` suffix, else `opencv`.
    - `extra`: more keys to store (e.g. `rms`; OpenCV/JSON formats only).
    """
    path = os.fspath(path)
    if format is None:
        format = "json" if path.endswith(".json") else "opencv"
    if format not in FORMATS:
        raise ValueError(f"`format` must be one of {FORMATS}; got {format!r}.")
    if format == "kalibr":
        _write_atomic(path, yaml.safe_dump(camera_to_kalibr(camera), sort_keys=False))
        return
    d = camera_to_dict(camera)
    if extra:
        d.update(extra)
    if format == "json":
        _write_atomic(path, json.dumps(d, indent=2) + "\n")
        return

    def write(tmp):
        fs = cv2.FileStorage(tmp, cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
        for k, v in d.items():
            if k in ("camera_matrix",):
                fs.write(k, np.asarray(v, np.float64))
            elif k == "distortion_coefficients":
                fs.write(k, np.asarray(v, np.float64).reshape(1, -1))
            elif isinstance(v, str):
                fs.write(k, v)
            elif isinstance(v, bool):
                fs.write(k, int(v))
            elif isinstance(v, (int, np.integer)):
                fs.write(k, int(v))
            elif isinstance(v, (float, np.floating)):
                fs.write(k, float(v))
            else:
                fs.write(k, np.asarray(v, np.float64))
        fs.release()

    _write_atomic(path, writer=write)


def load_camera(path: str | os.PathLike, name: str | None = None) -> AbstractCamera:
    """Read a camera file written by [`jaxloc.save_camera`][], OpenCV (`cv::FileStorage`
    YAML with `camera_matrix`, `distortion_coefficients`, optional `xi`, `image_width`,
    `image_height`), JSON with the same keys, or a Kalibr camchain (`cam0`, or `name`).
    Raises `FileNotFoundError` / `ValueError` naming the file and the bad field."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"Camera file `{path}` does not exist.")
    with open(path, encoding="utf-8", errors="replace") as f:
        text = f.read()
    if text.lstrip().startswith("%YAML"):
        fs = cv2.FileStorage(path, cv2.FILE_STORAGE_READ)
        if not fs.isOpened():
            raise ValueError(f"Camera file `{path}` is not a readable OpenCV YAML file.")
        d: dict[str, Any] = {}
        for key in fs.root().keys():
            node = fs.getNode(key)
            if node.isString():
                d[key] = node.string()
            elif node.isInt():
                d[key] = int(node.real())
            elif node.isReal():
                d[key] = float(node.real())
            else:
                m = node.mat()
                if m is not None:
                    d[key] = m.tolist()
        fs.release()
        return camera_from_dict(d, where=f"camera file {path}")
    if path.endswith(".json"):
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise ValueError(f"Camera file `{path}` is not valid JSON: {e}") from None
    else:
        try:
            d = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise ValueError(f"Camera file `{path}` is not valid YAML: {e}") from None
    if isinstance(d, dict) and d and all(isinstance(v, dict) and "camera_model" in v
                                         for v in d.values()):  # fmt: skip
        return camera_from_kalibr(d, name, where=f"camera file {path}")
    return camera_from_dict(d, where=f"camera file {path}")
