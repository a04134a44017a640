r"""The team file: a team's cameras, markers, odometry and images of one cycle.

**Team file** (YAML, or JSON with a `.json` suffix; paths relative to the file):

```yaml
strategy: sequential              # or concurrent
robots:
  C:  {camera: overhead.yaml}     # the climbing robot's perspective camera (pinhole file)
  # or a camera of a Kalibr camchain, by name: {camera: {file: camchain.yaml, name: cam1}}
  C1: {camera: ptz.yaml, marker: red, pan: 0.0, tilt: 0.0, zoom: 0.4}   # the PTZ
  C2: {camera: omni2.yaml, marker: green, elevation_deg: [-12, 32]}
  C3: {camera: omni3.yaml, marker: {hue: [105, 130], sat_min: 90, val_min: 40}}
odometry: [0.81, 0.77, 0.92]      # measured distance of each move (m), strategy order
odometry_sigma_rel: 0.01          # relative std of each odometry distance
pixel_sigma: 0.5                  # per-axis std of a detected centroid (px), for the
                                  # refinement's weights and the covariance
steps:                            # the images of each step of the cycle
  - {C: step0_C.png, C1: step0_C1.png, C2: step0_C2.png, C3: step0_C3.png}
  - ...
detection: {min_area: 6, max_area: 5000, max_elongation: 3.0, min_fill: 0.6,
            min_solidity: 0.85, annulus_margin_px: 3, on_ambiguous: error,
            sphere_correction: true}
```

With `sphere_correction` (default), markers are taken to be spheres and each blob's
centroid is moved to the projection of the sphere's centre
([`jaxloc.sphere_center_pixel`][]); set it to `false` for flat or point-like markers.

Camera files are read by [`jaxloc.load_camera`][] (jaxloc's camera dict as JSON/YAML,
OpenCV YAML, Kalibr camchains). A robot's `camera` is a file name, or `{file: <camchain>,
name: <camera>}` for one camera of a Kalibr camchain (`name` defaults to `cam0`).

`C1`'s camera file is either a perspective (pinhole) camera calibrated at the zoom used,
or a `ptz` camera: the two-end model, or the zoom table `jaxloc calibrate --model ptz`
writes. `pan`/`tilt` (rad) are the head's angles (jaxloc's PTZ convention); for a ptz
file they replace the file's own when given, and `zoom` (in `[0, 1]`, default the
file's) picks the zoom the images were taken at, which must lie within a zoom table's
calibrated steps (the table does not extrapolate). The team's C1 is then the PTZ's
pinhole at that zoom, mounted through the head's pan and tilt: the same projection as
the PTZ camera's. `zoom` with a pinhole file is an error. Marker colours are names
(`red`, `green`, `blue`) or HSV ranges ([`jaxloc.MarkerColor`][]). Unknown keys,
anywhere, are errors naming the key and the file.
"""

import dataclasses
import math
import os
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._cameras.files import load_camera, save_camera
from .._cameras.models import AbstractCamera, OmniCamera, PinholeCamera, PTZCamera
from .._core.files import (
    atomic_write,
    check_keys,
    dumps_yaml,
    load_mapping,
    naming_file,
    short,
    short_key,
    syntax_of,
)
from .._cycle.observations import num_moves, num_steps, STRATEGIES
from .markers import (
    MarkerColor,
)


ROBOTS = ("C", "C1", "C2", "C3")
GROUND = ("C1", "C2", "C3")
_TEAM_KEYS = ("strategy", "robots", "odometry", "odometry_sigma_rel", "pixel_sigma", "steps",
              "detection")  # fmt: skip
_DETECTION_KEYS = {
    "min_area": float, "max_area": float, "max_elongation": float, "min_fill": float,
    "min_solidity": float,
    "annulus_margin_px": float, "on_ambiguous": str, "sphere_correction": bool,
}  # fmt: skip
#: The keys of each robot's entry in a team file.
ROBOT_KEYS = {
    "C": ("camera",),
    "C1": ("camera", "marker", "pan", "tilt", "zoom"),
    "C2": ("camera", "marker", "elevation_deg"),
    "C3": ("camera", "marker", "elevation_deg"),
}


@dataclasses.dataclass
class Team:
    """A team's cameras, markers, odometry and images for one cycle (see the module
    docstring for the file format; [`jaxloc.load_team`][] reads it).

    **Fields:** `strategy`; `cameras` `{robot: camera}` (`C` pinhole, `C1` pinhole at the
    PTZ's zoom, `C2`/`C3` omni; a [`jaxloc.PTZCamera`][] given for `C1` is replaced by
    its pinhole at its zoom, its pan and tilt becoming the team's unless these are given
    too, and then they must agree); `pan`, `tilt` (rad, C1's head); `markers`
    `{C1|C2|C3: MarkerColor}`; `odometry` `(moves,)` m; `odometry_sigma_rel`;
    `pixel_sigma` (px per axis); `steps`: per step `{robot: image path}` (or `None` when
    images are passed in memory); `detection`: detector options; `source`: the team file.
    """

    strategy: str
    cameras: dict[str, AbstractCamera]
    markers: dict[str, MarkerColor]
    odometry: np.ndarray
    odometry_sigma_rel: float = 0.01
    pixel_sigma: float = 0.5
    pan: float = 0.0
    tilt: float = 0.0
    steps: list[dict[str, str]] | None = None
    detection: dict[str, Any] = dataclasses.field(default_factory=dict)
    source: str = "team"

    def __post_init__(self):
        if self.strategy not in STRATEGIES:
            raise ValueError(
                f"`{self.source}: strategy` must be one of {STRATEGIES}; got "
                f"{short(self.strategy)}."
            )
        self._check_cameras()
        for r in GROUND:
            if r not in self.markers:
                raise ValueError(f"`{self.source}: robots.{r}.marker` is missing.")
        self._check_numbers()
        self._check_detection()
        self._check_steps()

    def _check_cameras(self):
        w = self.source
        for r in ROBOTS:
            if r not in self.cameras:
                raise ValueError(f"`{w}: robots.{r}.camera` is missing.")
        if not isinstance(self.cameras["C"], PinholeCamera):
            raise ValueError(
                f"`{w}: robots.C.camera` must be a perspective (pinhole) camera; got "
                f"{type(self.cameras['C']).__name__}."
            )
        if isinstance(self.cameras["C1"], PTZCamera):
            self.cameras["C1"] = self._ptz_pinhole(self.cameras["C1"])
        if not isinstance(self.cameras["C1"], PinholeCamera):
            raise ValueError(
                f"`{w}: robots.C1.camera` must be a perspective camera (the PTZ at its zoom); "
                f"got {type(self.cameras['C1']).__name__}."
            )
        for r in ("C2", "C3"):
            if not isinstance(self.cameras[r], OmniCamera):
                raise ValueError(
                    f"`{w}: robots.{r}.camera` must be an omnidirectional camera (model omni, "
                    f"with xi); got {type(self.cameras[r]).__name__}."
                )

    def _ptz_pinhole(self, ptz: PTZCamera) -> PinholeCamera:
        """C1's pinhole at the PTZ's zoom; the PTZ's pan and tilt become the team's."""
        w = self.source
        head = (float(ptz.pan), float(ptz.tilt))
        given = (float(self.pan), float(self.tilt))
        if head != (0.0, 0.0) and given != (0.0, 0.0) and head != given:
            raise ValueError(
                f"`{w}: robots.C1`: the head's pan and tilt are given twice and differ: "
                f"{short(list(given))} for the team, {short(list(head))} in its PTZ camera; "
                "give them in one place."
            )
        if head != (0.0, 0.0):
            self.pan, self.tilt = head
        table = ptz.zoom_table
        if table is not None:
            z, lo, hi = float(ptz.zoom), float(table.zooms[0]), float(table.zooms[-1])
            if not lo <= z <= hi:
                raise ValueError(
                    f"`{w}: robots.C1.zoom` must lie within the calibrated zoom steps "
                    f"[{lo!r}, {hi!r}] of C1's zoom table (the table does not "
                    f"extrapolate); got {z!r}."
                )
        return ptz.pinhole()

    def _check_numbers(self):
        w = self.source
        m = num_moves(self.strategy)
        try:
            odo = np.asarray(self.odometry, dtype=np.float64)
        except (TypeError, ValueError):
            odo = np.zeros(0)
        if odo.shape != (m,) or not np.all(np.isfinite(odo)) or not np.all(odo > 0):
            raise ValueError(
                f"`{w}: odometry` must be {m} positive distances (m) for the {self.strategy} "
                f"strategy; got {short(self.odometry)}."
            )
        self.odometry = odo
        for name in ("odometry_sigma_rel", "pixel_sigma"):
            v = getattr(self, name)
            number = isinstance(v, int | float) and not isinstance(v, bool)
            if not number or not math.isfinite(v) or v <= 0:
                raise ValueError(f"`{w}: {name}` must be a positive number; got {short(v)}.")

    def _check_detection(self):
        w = self.source
        check_keys(self.detection, _DETECTION_KEYS, where=f"`{w}: detection`")
        amb = self.detection.get("on_ambiguous", "error")
        if amb not in ("error", "largest"):
            raise ValueError(
                f"`{w}: detection.on_ambiguous` must be 'error' or 'largest'; got {short(amb)}."
            )

    def _check_steps(self):
        if self.steps is None:
            return
        w, n = self.source, num_steps(self.strategy)
        if not isinstance(self.steps, list) or len(self.steps) != n:
            got = len(self.steps) if isinstance(self.steps, list) else short(self.steps)
            raise ValueError(
                f"`{w}: steps` must list {n} steps for the {self.strategy} strategy; got {got}."
            )
        for k, s in enumerate(self.steps):
            if not isinstance(s, dict) or set(s) != set(ROBOTS):
                raise ValueError(
                    f"`{w}: steps[{k}]` must map each of {ROBOTS} to an image file; got "
                    f"{short(s)}."
                )


def load_team(path: str | os.PathLike) -> Team:
    """Read and validate a team file (see the module docstring).

    Raises `jaxloc._core.files.FileFormatError` (a `ValueError`; for a missing file also a
    `FileNotFoundError`) naming the file, the field and the value (bounded)."""
    path = os.fspath(path)
    d = load_mapping(path, what="team file", syntax=syntax_of(path, default="yaml"))
    with naming_file(path, "team file"):
        return team_from_dict(d, path)


def team_from_dict(d: Any, source: str) -> Team:
    """Build a [`jaxloc.Team`][] from a team file's mapping; `source` is the team file
    (relative paths are taken from its folder; messages name it)."""
    w = source
    check_keys(d, _TEAM_KEYS, where=f"team file `{w}`")
    base = os.path.dirname(os.path.abspath(source))
    robots = d.get("robots")
    if not isinstance(robots, dict):
        raise ValueError(
            f"`{w}: robots` must map C, C1, C2, C3 to their settings; got {short(robots)}."
        )
    check_keys(robots, ROBOTS, where=f"`{w}: robots`")
    entries = {r: _robot_entry(robots.get(r), r, w) for r in ROBOTS}
    cameras = {r: _robot_camera(entries[r], r, base, w) for r in ROBOTS}
    markers = {r: _robot_marker(entries[r], r, w) for r in GROUND}
    cameras["C1"], (pan, tilt) = _c1_head(cameras["C1"], entries["C1"], w)
    odo = d.get("odometry")
    if not isinstance(odo, list) or not all(_is_number(x) for x in odo):
        raise ValueError(f"`{w}: odometry` must be a list of distances (m); got {short(odo)}.")
    det = d.get("detection", {}) or {}
    if not isinstance(det, dict):
        raise ValueError(f"`{w}: detection` must be a mapping; got {short(det)}.")
    return Team(
        strategy=d.get("strategy", "sequential"), cameras=cameras, markers=markers,
        odometry=np.asarray(odo, np.float64),
        odometry_sigma_rel=d.get("odometry_sigma_rel", 0.01),
        pixel_sigma=d.get("pixel_sigma", 0.5), pan=pan, tilt=tilt,
        steps=_steps(d.get("steps"), base, w), detection=det, source=source,
    )  # fmt: skip


def _is_number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _robot_entry(e: Any, r: str, w: str) -> dict:
    if not isinstance(e, dict) or "camera" not in e:
        raise ValueError(
            f"`{w}: robots.{r}` must be a mapping with a `camera` file; got {short(e)}."
        )
    return check_keys(e, ROBOT_KEYS[r], where=f"`{w}: robots.{r}`")


def _camera_reference(spec: Any, r: str, base: str, w: str) -> tuple[str, str | None]:
    """The camera file (joined to `base`) and camchain camera name of a robot's
    `camera:` entry: a file name, or `{file: <camchain>, name: <camera>}`."""
    at = f"`{w}: robots.{r}.camera`"
    name = None
    if isinstance(spec, dict):
        check_keys(spec, ("file", "name"), where=at)
        if "file" not in spec:
            raise ValueError(f"{at} must give the camchain's `file`; got {short(spec)}.")
        name = spec.get("name")
        if name is not None and not isinstance(name, str):
            raise ValueError(f"{at}: `name` must be a camera name (cam0, ...); got "
                             f"{short(name)}.")  # fmt: skip
        spec = spec["file"]
    if not isinstance(spec, str) or not spec:
        raise ValueError(
            f"{at} must be a camera file name or {{file: <camchain>, name: <camera>}}; got "
            f"{short(spec)}."
        )
    return os.path.join(base, spec), name


def _robot_camera(e: dict, r: str, base: str, w: str) -> AbstractCamera:
    path, name = _camera_reference(e["camera"], r, base, w)
    try:
        cam = load_camera(path, name)
    except (ValueError, FileNotFoundError) as err:
        raise type(err)(f"`{w}: robots.{r}.camera`: {err}") from None
    if "elevation_deg" in e and isinstance(cam, OmniCamera):
        band = e["elevation_deg"]
        numbers = isinstance(band, list) and all(_is_number(x) for x in band)
        if not numbers or len(band) != 2 or not band[0] < band[1]:
            raise ValueError(
                f"`{w}: robots.{r}.elevation_deg` must be [min, max] degrees; got {short(band)}."
            )
        cam = eqx.tree_at(
            lambda c: (c.elevation_min, c.elevation_max), cam,
            (jnp.asarray(math.radians(band[0]), dtype=cam.xi.dtype),
             jnp.asarray(math.radians(band[1]), dtype=cam.xi.dtype)),
        )  # fmt: skip
    return cam


def _robot_marker(e: dict, r: str, w: str) -> MarkerColor:
    if "marker" not in e:
        raise ValueError(f"`{w}: robots.{r}.marker` is missing (a colour name or HSV range).")
    return MarkerColor.from_dict(e["marker"], where=f"{w}: robots.{r}.marker")


def _head_angle(e: dict, name: str, w: str) -> float:
    v = e.get(name, 0.0)
    if not _is_number(v) or not math.isfinite(v):
        raise ValueError(f"`{w}: robots.C1.{name}` must be a number (rad); got {short(v)}.")
    return float(v)


def _c1_head(
    cam: AbstractCamera, e: dict, w: str
) -> tuple[AbstractCamera, tuple[float, float]]:
    """C1's camera and the team's `(pan, tilt)` from its team-file entry: for a PTZ
    camera file, the entry's `pan`, `tilt` and `zoom` (when given) set on the camera (the
    team takes its head angles from it); for a pinhole, the entry's angles."""
    angles = {k: _head_angle(e, k, w) for k in ("pan", "tilt") if k in e}
    if not isinstance(cam, PTZCamera):
        if "zoom" in e:
            raise ValueError(
                f"`{w}: robots.C1.zoom` applies to a ptz camera file (e.g. a zoom table from "
                f"`jaxloc calibrate --model ptz`); C1's camera is a {type(cam).__name__}, "
                "calibrated at one zoom."
            )
        return cam, (angles.get("pan", 0.0), angles.get("tilt", 0.0))
    if "zoom" in e:
        z = e["zoom"]
        if not _is_number(z) or not 0.0 <= z <= 1.0:
            raise ValueError(
                f"`{w}: robots.C1.zoom` must be a number in [0, 1] (wide to tele); got "
                f"{short(z)}."
            )
        angles["zoom"] = float(z)
    for k, v in angles.items():
        cam = eqx.tree_at(lambda c: getattr(c, k), cam, jnp.asarray(v, dtype=cam.pan.dtype))
    return cam, (0.0, 0.0)


def _steps(steps: Any, base: str, w: str) -> list:
    """The steps' image paths joined to `base` (their number and robots are checked by
    [`Team`][])."""
    if not isinstance(steps, list):
        raise ValueError(
            f"`{w}: steps` must be a list of {{C, C1, C2, C3: image}} mappings; got "
            f"{short(steps)}."
        )
    out = []
    for k, s in enumerate(steps):
        if isinstance(s, dict):
            for r, v in s.items():
                if not isinstance(v, str) or not v:
                    raise ValueError(
                        f"`{w}: steps[{k}].{short_key(r, 20)}` must be an image file name; got "
                        f"{short(v)}."
                    )
            s = {r: os.path.join(base, v) for r, v in s.items()}
        out.append(s)
    return out


def save_team(team: Team, path: str | os.PathLike, camera_files: dict[str, str] | None = None):
    """Write `team` as a team file at `path` (atomically), with its cameras as OpenCV YAML
    files beside it (`camera_C.yaml`, ...; or the given `camera_files`; the omni cameras'
    elevation bands in them) and its image paths made relative to the file's folder."""
    path = os.fspath(path)
    base = os.path.dirname(os.path.abspath(path))
    robots: dict[str, Any] = {}
    for r in ROBOTS:
        name = (camera_files or {}).get(r, f"camera_{r}.yaml")
        save_camera(team.cameras[r], os.path.join(base, name))
        robots[r] = _robot_to_dict(team, r, name)
    d = {
        "strategy": team.strategy,
        "robots": robots,
        "odometry": [float(x) for x in team.odometry],
        "odometry_sigma_rel": float(team.odometry_sigma_rel),
        "pixel_sigma": float(team.pixel_sigma),
        "steps": [{r: os.path.relpath(p, base) for r, p in s.items()} for s in team.steps or []],
        "detection": dict(team.detection),
    }
    atomic_write(path, dumps_yaml(d))


def _robot_to_dict(team: Team, r: str, camera_file: str) -> dict[str, Any]:
    e: dict[str, Any] = {"camera": camera_file}
    if r != "C":
        m = team.markers[r]
        e["marker"] = {
            "hue": [m.hue_low, m.hue_high], "sat_min": m.sat_min, "val_min": m.val_min,
            "sat_max": m.sat_max, "val_max": m.val_max,
        }  # fmt: skip
    if r == "C1":
        e["pan"], e["tilt"] = float(team.pan), float(team.tilt)
    # C2's and C3's elevation bands are in their camera files (exactly, in radians).
    return e
