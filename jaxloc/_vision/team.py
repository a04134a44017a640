r"""The team file: a team's cameras, markers, odometry and images of one cycle.

**Team file** (YAML, via `yaml.safe_load`; paths relative to the file):

```yaml
strategy: sequential              # or concurrent
robots:
  C:  {camera: overhead.yaml}     # the climbing robot's perspective camera (pinhole file)
  C1: {camera: ptz.yaml, marker: red, pan: 0.0, tilt: 0.0}   # PTZ calibrated at one zoom
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

Camera files are read by [`jaxloc.load_camera`][] (OpenCV YAML/JSON, Kalibr). `C1`'s file
is a perspective camera calibrated at the zoom used; `pan`/`tilt` (rad) are its head's
angles (jaxloc's PTZ convention). Marker colours are names (`red`, `green`, `blue`) or HSV
ranges ([`jaxloc.MarkerColor`][]).
"""

import dataclasses
import math
import os
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import yaml

from .._cameras.files import load_camera, save_camera
from .._cameras.models import AbstractCamera, OmniCamera, PinholeCamera, PTZCamera
from .._cycle.observations import num_moves, num_steps, STRATEGIES
from .markers import (
    MarkerColor,
)


ROBOTS = ("C", "C1", "C2", "C3")
GROUND = ("C1", "C2", "C3")
_DETECTION_KEYS = {
    "min_area": float, "max_area": float, "max_elongation": float, "min_fill": float,
    "min_solidity": float,
    "annulus_margin_px": float, "on_ambiguous": str, "sphere_correction": bool,
}  # fmt: skip


@dataclasses.dataclass
class Team:
    """A team's cameras, markers, odometry and images for one cycle (see the module
    docstring for the file format; [`jaxloc.load_team`][] reads it).

    **Fields:** `strategy`; `cameras` `{robot: camera}` (`C` pinhole, `C1` pinhole at the
    PTZ's zoom, `C2`/`C3` omni); `pan`, `tilt` (rad, C1's head); `markers`
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
        w = self.source
        if self.strategy not in STRATEGIES:
            raise ValueError(f"`{w}: strategy` must be one of {STRATEGIES}; got {self.strategy!r}.")
        for r in ROBOTS:
            if r not in self.cameras:
                raise ValueError(f"`{w}: robots.{r}.camera` is missing.")
        if not isinstance(self.cameras["C"], PinholeCamera):
            raise ValueError(
                f"`{w}: robots.C.camera` must be a perspective (pinhole) camera; got "
                f"{type(self.cameras['C']).__name__}."
            )
        if isinstance(self.cameras["C1"], PTZCamera):
            ptz = self.cameras["C1"]
            self.pan, self.tilt = float(ptz.pan), float(ptz.tilt)
            self.cameras["C1"] = ptz.pinhole()
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
        for r in GROUND:
            if r not in self.markers:
                raise ValueError(f"`{w}: robots.{r}.marker` is missing.")
        odo = np.asarray(self.odometry, dtype=np.float64)
        m = num_moves(self.strategy)
        if odo.shape != (m,) or not np.all(np.isfinite(odo)) or not np.all(odo > 0):
            raise ValueError(
                f"`{w}: odometry` must be {m} positive distances (m) for the {self.strategy} "
                f"strategy; got {self.odometry!r}."
            )
        self.odometry = odo
        for name in ("odometry_sigma_rel", "pixel_sigma"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ValueError(f"`{w}: {name}` must be a positive number; got {v!r}.")
        for k, v in self.detection.items():
            if k not in _DETECTION_KEYS:
                raise ValueError(
                    f"Unknown key `{w}: detection.{k}`; expected one of {sorted(_DETECTION_KEYS)}."
                )
        amb = self.detection.get("on_ambiguous", "error")
        if amb not in ("error", "largest"):
            raise ValueError(
                f"`{w}: detection.on_ambiguous` must be 'error' or 'largest'; got {amb!r}."
            )
        if self.steps is not None:
            n = num_steps(self.strategy)
            if not isinstance(self.steps, list) or len(self.steps) != n:
                got = len(self.steps) if isinstance(self.steps, list) else self.steps
                raise ValueError(
                    f"`{w}: steps` must list {n} steps for the {self.strategy} strategy; "
                    f"got {got!r}."
                )
            for k, s in enumerate(self.steps):
                if not isinstance(s, dict) or set(s) != set(ROBOTS):
                    raise ValueError(
                        f"`{w}: steps[{k}]` must map each of {ROBOTS} to an image file; got {s!r}."
                    )


def _read_yaml(path: str) -> Any:
    if not os.path.isfile(path):
        raise FileNotFoundError(f"Team file `{path}` does not exist.")
    with open(path, encoding="utf-8") as f:
        try:
            return yaml.safe_load(f)
        except yaml.YAMLError as e:
            raise ValueError(f"Team file `{path}` is not valid YAML: {e}") from None


def load_team(path: str | os.PathLike) -> Team:
    """Read and validate a team file (see the module docstring). Raises
    `FileNotFoundError` for missing files and `ValueError` naming the field and value."""
    path = os.fspath(path)
    d = _read_yaml(path)
    w = path
    if not isinstance(d, dict):
        raise ValueError(f"Team file `{path}` must be a mapping; got {type(d).__name__}.")
    allowed = {"strategy", "robots", "odometry", "odometry_sigma_rel", "pixel_sigma", "steps",
               "detection"}  # fmt: skip
    for k in d:
        if k not in allowed:
            raise ValueError(f"Unknown key `{w}: {k}`; expected one of {sorted(allowed)}.")
    base = os.path.dirname(os.path.abspath(path))
    robots = d.get("robots")
    if not isinstance(robots, dict):
        raise ValueError(f"`{w}: robots` must map C, C1, C2, C3 to their settings; got {robots!r}.")
    cameras, markers = {}, {}
    pan = tilt = 0.0
    for r in ROBOTS:
        e = robots.get(r)
        if not isinstance(e, dict) or "camera" not in e:
            raise ValueError(
                f"`{w}: robots.{r}` must be a mapping with a `camera` file; got {e!r}."
            )
        ok_keys = {"camera"} | ({"marker"} if r != "C" else set())
        ok_keys |= {"pan", "tilt"} if r == "C1" else set()
        ok_keys |= {"elevation_deg"} if r in ("C2", "C3") else set()
        for k in e:
            if k not in ok_keys:
                raise ValueError(
                    f"Unknown key `{w}: robots.{r}.{k}`; expected one of {sorted(ok_keys)}."
                )
        cam_path = os.path.join(base, str(e["camera"]))
        try:
            cam = load_camera(cam_path)
        except (ValueError, FileNotFoundError) as err:
            raise type(err)(f"`{w}: robots.{r}.camera`: {err}") from None
        if r in ("C2", "C3") and "elevation_deg" in e and isinstance(cam, OmniCamera):
            band = e["elevation_deg"]
            numbers = isinstance(band, list) and all(isinstance(x, (int, float)) for x in band)
            if not numbers or len(band) != 2 or not band[0] < band[1]:
                raise ValueError(
                    f"`{w}: robots.{r}.elevation_deg` must be [min, max] degrees; got {band!r}."
                )
            cam = eqx.tree_at(
                lambda c: (c.elevation_min, c.elevation_max), cam,
                (jnp.asarray(math.radians(band[0]), dtype=cam.xi.dtype),
                 jnp.asarray(math.radians(band[1]), dtype=cam.xi.dtype)),
            )  # fmt: skip
        cameras[r] = cam
        if r != "C":
            if "marker" not in e:
                raise ValueError(
                    f"`{w}: robots.{r}.marker` is missing (a colour name or HSV range)."
                )
            markers[r] = MarkerColor.from_dict(e["marker"], where=f"{w}: robots.{r}.marker")
        if r == "C1":
            for name in ("pan", "tilt"):
                v = e.get(name, 0.0)
                if not isinstance(v, (int, float)) or not math.isfinite(v):
                    raise ValueError(f"`{w}: robots.C1.{name}` must be a number (rad); got {v!r}.")
            pan, tilt = float(e.get("pan", 0.0)), float(e.get("tilt", 0.0))
    odo = d.get("odometry")
    if not isinstance(odo, list) or not all(isinstance(x, (int, float)) for x in odo):
        raise ValueError(f"`{w}: odometry` must be a list of distances (m); got {odo!r}.")
    steps = d.get("steps")
    if isinstance(steps, list):
        steps = [
            {r: os.path.join(base, str(v)) for r, v in s.items()} if isinstance(s, dict) else s
            for s in steps
        ]
    else:
        raise ValueError(
            f"`{w}: steps` must be a list of {{C, C1, C2, C3: image}} mappings; got {steps!r}."
        )
    det = d.get("detection", {}) or {}
    if not isinstance(det, dict):
        raise ValueError(f"`{w}: detection` must be a mapping; got {det!r}.")
    return Team(
        strategy=d.get("strategy", "sequential"), cameras=cameras, markers=markers,
        odometry=np.asarray(odo, np.float64),
        odometry_sigma_rel=d.get("odometry_sigma_rel", 0.01),
        pixel_sigma=d.get("pixel_sigma", 0.5), pan=pan, tilt=tilt, steps=steps,
        detection=det, source=path,
    )  # fmt: skip


def save_team(team: Team, path: str | os.PathLike, camera_files: dict[str, str] | None = None):
    """Write `team` as a team file at `path`, with its cameras as OpenCV YAML files beside
    it (`camera_C.yaml`, ...; or the given `camera_files`) and its image paths made
    relative to the file's folder."""
    path = os.fspath(path)
    base = os.path.dirname(os.path.abspath(path))
    robots: dict[str, Any] = {}
    for r in ROBOTS:
        name = (camera_files or {}).get(r, f"camera_{r}.yaml")
        save_camera(team.cameras[r], os.path.join(base, name))
        e: dict[str, Any] = {"camera": name}
        if r != "C":
            m = team.markers[r]
            e["marker"] = {
                "hue": [m.hue_low, m.hue_high], "sat_min": m.sat_min, "val_min": m.val_min,
                "sat_max": m.sat_max, "val_max": m.val_max,
            }  # fmt: skip
        if r == "C1":
            e["pan"], e["tilt"] = float(team.pan), float(team.tilt)
        if r in ("C2", "C3"):
            c = team.cameras[r]
            e["elevation_deg"] = [math.degrees(float(c.elevation_min)),
                                  math.degrees(float(c.elevation_max))]  # fmt: skip
        robots[r] = e
    d = {
        "strategy": team.strategy,
        "robots": robots,
        "odometry": [float(x) for x in team.odometry],
        "odometry_sigma_rel": float(team.odometry_sigma_rel),
        "pixel_sigma": float(team.pixel_sigma),
        "steps": [{r: os.path.relpath(p, base) for r, p in s.items()} for s in team.steps or []],
        "detection": dict(team.detection),
    }
    with open(path, "w", encoding="utf-8") as f:
        yaml.safe_dump(d, f, sort_keys=False)
