r"""Localization from images: a team file -> marker detections -> observations -> poses.

The image front end produces the same [`jaxloc.CycleObservations`][] the simulator does
(DESIGN §6), so the estimators are unchanged: [`jaxloc.localize_cycle`][], then (if
asked) [`jaxloc.refine_cycle`][] and [`jaxloc.cycle_covariance`][].

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

**What is measured.** At step `k`: C1's image gives the bearings of C2 and C3, C2's of C1
and C3, C3's of C1 and C2 (all required: mutual localization needs all six), and C's
image the overhead bearings of all three (at least four distinct robot placements
over the cycle must be seen). A required marker that is missing, an ambiguous colour
(two blobs pass every test), an unreadable image or a failed estimate raise a
`ValueError` naming the team-file field and the value: never a wrong pose.

**PTZ and refinement.** A [`jaxloc.Scenario`][] holds C1's camera as a
[`jaxloc.PTZCamera`][] (square pixels, centred principal point, no distortion), which a
calibrated pinhole generally is not. The refinement therefore sees C1's detections
re-projected into the *equivalent ideal* PTZ camera (same pan/tilt, focal length
`sqrt(fx fy)`): pixel -> calibrated bearing -> ideal pixel. Bearings and residual scale
are preserved to first order.
"""

import dataclasses
import json
import math
import os
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import jaxlie
import numpy as np
import yaml

from .._cameras.models import AbstractCamera, OmniCamera, PinholeCamera, PTZCamera
from .._cameras.presets import R_BODY_OMNI, R_BODY_PTZ
from .._core.poses import ypr_from_rotation
from .._core.results import RESULTS, status_code, status_names
from .._cycle.observations import CycleObservations, num_moves, num_steps, STRATEGIES
from .._refine.covariance import cycle_covariance
from .._refine.cycle import refine_cycle
from .._sim.scenario import Scenario
from .._solvers.strategies import localize_cycle, overhead_point_ids
from .calibrate import load_camera, save_camera
from .markers import (
    annulus_mask,
    check_image,
    DEFAULT_MARKER_COLORS,
    detect_markers,
    MarkerColor,
    MarkerDetection,
    read_image,
)
from .render import annulus_of, sphere_center_pixel


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


# --------------------------------------------------------------------------------------
# Detections -> observations.

# Which robots each camera sees: (observer, targets).
_SEES = {"C": GROUND, "C1": ("C2", "C3"), "C2": ("C1", "C3"), "C3": ("C1", "C2")}


def ptz_equivalent(team: Team) -> PTZCamera:
    """The ideal [`jaxloc.PTZCamera`][] standing in for C1's calibrated camera in the
    refinement (same pan, tilt, image size; focal length `sqrt(fx fy)` at zoom 0)."""
    cam = team.cameras["C1"]
    w, h = cam.image_size
    f = math.sqrt(float(cam.fx) * float(cam.fy))
    hfov = 2.0 * math.atan(0.5 * w / f)
    return PTZCamera(pan=team.pan, tilt=team.tilt, zoom=0.0, hfov_wide=hfov,
                     hfov_tele=0.5 * hfov, image_size=(w, h))  # fmt: skip


def scenario_for(team: Team) -> Scenario:
    """The [`jaxloc.Scenario`][] the refinement and the covariance need: the team's
    cameras (C1 as [`jaxloc.ptz_equivalent`][]), Gaussian pixel noise of
    `team.pixel_sigma` per axis, `team.odometry_sigma_rel`, the strategy."""
    return Scenario(
        overhead=team.cameras["C"], ptz=ptz_equivalent(team), omni2=team.cameras["C2"],
        omni3=team.cameras["C3"], pixel_sigma=team.pixel_sigma, noise_model="gaussian",
        odometry_sigma_rel=team.odometry_sigma_rel, strategy=team.strategy,
    )  # fmt: skip


def _mask_for(team: Team, robot: str, shape_hw) -> np.ndarray | None:
    cam = team.cameras[robot]
    if not isinstance(cam, OmniCamera):
        return None
    margin = float(team.detection.get("annulus_margin_px", 3.0))
    h, w = shape_hw
    return annulus_mask((w, h), annulus_of(cam, margin))


def detect_team_images(
    team: Team, images: dict[tuple[int, str], np.ndarray] | None = None
) -> dict[tuple[int, str], dict[str, MarkerDetection]]:
    """Detect every required marker in every image of the cycle.

    **Arguments:**

    - `team`: a [`jaxloc.Team`][].
    - `images`: optional `{(step, robot): BGR image}`; by default read from `team.steps`.

    **Returns:** `{(step, observer): {target: MarkerDetection}}`. Raises `ValueError`
    naming the image for an unreadable or wrongly sized image, a missing required marker or
    an ambiguous colour (unless `detection.on_ambiguous` is `largest`).
    """
    steps = num_steps(team.strategy)
    keys = ("min_area", "max_area", "max_elongation", "min_fill", "min_solidity")
    opts = {k: team.detection[k] for k in keys if k in team.detection}
    out = {}
    masks: dict[str, np.ndarray | None] = {}
    for k in range(steps):
        for obs in ROBOTS:
            field = f"steps[{k}].{obs}"
            if images is not None:
                if (k, obs) not in images:
                    raise ValueError(f"`images` has no image for {field}.")
                img = check_image(images[(k, obs)], f"image {field}")
                label = field
            else:
                if team.steps is None:
                    raise ValueError("`team.steps` lists no image files; pass `images`.")
                p = team.steps[k][obs]
                label = f"{field} (`{p}`)"
                try:
                    img = read_image(p)
                except (ValueError, FileNotFoundError) as err:
                    raise type(err)(f"`{team.source}: {field}`: {err}") from None
            w, h = team.cameras[obs].image_size
            if img.shape[:2] != (h, w):
                raise ValueError(
                    f"Image {label} is {img.shape[1]}x{img.shape[0]} px but robot {obs}'s "
                    f"camera is calibrated for {w}x{h}."
                )
            if obs not in masks:
                masks[obs] = _mask_for(team, obs, img.shape[:2])
            colors = {t: team.markers[t] for t in _SEES[obs]}
            det = detect_markers(img, colors, mask=masks[obs], **opts)
            if team.detection.get("sphere_correction", True):
                # Spherical markers: centroid -> projection of the sphere's centre.
                det = {
                    t: dataclasses.replace(
                        d, pixel=sphere_center_pixel(team.cameras[obs], d.pixel, d.area)
                    ) if d.detected else d
                    for t, d in det.items()
                }  # fmt: skip
            for t, dt in det.items():
                if dt.candidates > 1 and team.detection.get("on_ambiguous", "error") == "error":
                    raise ValueError(
                        f"Marker of {t} is ambiguous in image {label}: {dt.candidates} blobs "
                        f"pass every test for colour `robots.{t}.marker`; refusing to guess "
                        "(set `detection.on_ambiguous: largest` to take the largest)."
                    )
                if obs != "C" and dt.detected and dt.truncated:
                    raise ValueError(
                        f"Marker of {t} is cut by the edge of image {label} (image border or "
                        "mirror annulus): its centroid would be biased by pixels. Robot "
                        f"{obs} must see {t} whole at step {k}; re-take the image with {t} "
                        "further inside the field of view."
                    )
                if obs != "C" and not dt.detected:
                    raise ValueError(
                        f"Marker of {t} (colour `robots.{t}.marker` = "
                        f"{_color_text(team.markers[t])}) "
                        f"was not found in image {label}: robot {obs} must see {t} at step {k} "
                        "(mutual localization needs all six bearings)."
                    )
            out[(k, obs)] = det
    return out


def _color_text(c: MarkerColor) -> str:
    return f"hue {c.hue_low}..{c.hue_high}, sat >= {c.sat_min}, val >= {c.val_min}"


def observations_from_detections(
    team: Team, detections: dict[tuple[int, str], dict[str, MarkerDetection]]
) -> CycleObservations:
    """Bearings (body frames for the ground robots, camera frame for C), pixels and
    odometry of one cycle from its detections. C1's `mutual_pixels` are expressed in
    [`jaxloc.ptz_equivalent`][]'s image (see the module docstring)."""
    steps = num_steps(team.strategy)
    idx = {"C1": 0, "C2": 1, "C3": 2}
    mutual = np.zeros((steps, 3, 3, 3))
    mpix = np.full((steps, 3, 3, 2), np.nan)
    over = np.zeros((steps, 3, 3))
    over_vis = np.zeros((steps, 3), bool)
    opix = np.full((steps, 3, 2), np.nan)
    ptz = ptz_equivalent(team)
    R_base_opt = np.asarray(ptz.optical_rotation().as_matrix())
    for k in range(steps):
        for obs in GROUND:
            i = idx[obs]
            for t, dt in detections[(k, obs)].items():
                j = idx[t]
                b = np.asarray(_unproject(team.cameras[obs], jnp.asarray(dt.pixel)))
                if obs == "C1":
                    b_base = R_base_opt @ b
                    mutual[k, i, j] = R_BODY_PTZ @ b_base
                    mpix[k, i, j] = np.asarray(_project(ptz, jnp.asarray(b_base)))
                else:
                    mutual[k, i, j] = R_BODY_OMNI @ b
                    mpix[k, i, j] = dt.pixel
        for t, dt in detections[(k, "C")].items():
            # A marker cut by the image border would bias C's pose: dropped (the
            # overhead solve has redundancy; too few remaining placements raise below).
            if dt.detected and not dt.truncated:
                j = idx[t]
                over[k, j] = np.asarray(_unproject(team.cameras["C"], jnp.asarray(dt.pixel)))
                over_vis[k, j] = True
                opix[k, j] = dt.pixel
    # Distinct robot placements seen by C (robots that did not move keep theirs).
    ids = overhead_point_ids(team.strategy)
    seen = {int(ids[k, j]) for k in range(steps) for j in range(3) if over_vis[k, j]}
    if len(seen) < 4:
        raise ValueError(
            f"The overhead camera C saw only {len(seen)} distinct robot placements over the "
            f"cycle (markers found: {int(over_vis.sum())} of {3 * steps}); at least 4 are "
            "needed for an unambiguous pose. Check the `steps[*].C` images and the marker "
            "colours."
        )
    return CycleObservations(
        mutual=jnp.asarray(mutual), overhead=jnp.asarray(over), odometry=jnp.asarray(team.odometry),
        odometry_sigma=jnp.asarray(team.odometry_sigma_rel * team.odometry),
        strategy=team.strategy, overhead_visible=jnp.asarray(over_vis),
        mutual_pixels=jnp.asarray(mpix), overhead_pixels=jnp.asarray(opix),
    )  # fmt: skip


# --------------------------------------------------------------------------------------
# Localization.


@eqx.filter_jit
def _unproject(camera, uv):
    # Jitted: an eager `unproject` recompiles its undistortion loops at every call.
    return camera.unproject(uv)


@eqx.filter_jit
def _project(camera, p):
    return camera.project(p)


@eqx.filter_jit
def _localize(observations: CycleObservations):
    return localize_cycle(observations, throw=False)


@eqx.filter_jit
def _covariance(observations, scenario, estimate):
    return cycle_covariance(observations, scenario, estimate)


@dataclasses.dataclass
class ImageLocalization:
    """Result of [`jaxloc.localize_images`][].

    **Fields:** `estimate` (the [`jaxloc.CycleEstimate`][] reported: refined if
    refinement ran and succeeded), `closed_form` (the closed-form estimate),
    `covariance` (a [`jaxloc.CycleCovariance`][] or `None`), `observations`,
    `detections`, `method` (`"refined"` or `"closed_form"`), `notes`.
    """

    estimate: Any
    closed_form: Any
    covariance: Any
    observations: CycleObservations
    detections: dict[tuple[int, str], dict[str, MarkerDetection]]
    method: str
    notes: list[str]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready report: the four end-of-cycle poses (position m, quaternion wxyz,
        yaw/pitch/roll deg, covariances when available) in the world frame (C1's body
        frame at the start of the cycle), every robot's positions at every step, the
        detections, status and diagnostics."""
        poses = self.estimate.poses
        Tb = np.asarray(poses.T_world_body.wxyz_xyz)
        To = np.asarray(poses.T_world_overhead.wxyz_xyz)
        out_poses: dict[str, Any] = {}
        for n, (name, T) in enumerate([("C", To), ("C1", Tb[-1, 0]), ("C2", Tb[-1, 1]),
                                       ("C3", Tb[-1, 2])]):  # fmt: skip
            R = jaxlie.SO3(jnp.asarray(T[:4]))
            entry = {"position_m": T[4:].tolist(), "quaternion_wxyz": T[:4].tolist(),
                     "ypr_deg": np.asarray(ypr_from_rotation(R)).tolist()}  # fmt: skip
            if name == "C":
                entry["frame"] = "optical (x right, y down, z forward)"
            if self.covariance is not None and bool(self.covariance.ok):
                P = np.asarray(self.covariance.position[n])
                Q = np.asarray(self.covariance.rotation[n])
                entry["position_cov_m2"] = P.tolist()
                entry["position_std_m"] = np.sqrt(np.maximum(np.diag(P), 0)).tolist()
                entry["rotation_cov_rad2"] = Q.tolist()
            out_poses[name] = entry
        dets = {}
        for (k, obs), d in sorted(self.detections.items()):
            dets[f"steps[{k}].{obs}"] = {
                t: {"pixel": None if not v.detected else v.pixel.tolist(),
                    "detected": v.detected, "spread_px": None if not v.detected else v.spread,
                    "area_px": v.area}  # fmt: skip
                for t, v in d.items()
            }
        code = int(status_code(self.estimate.result))
        return {
            "frame": "W = body frame of C1 at the start of the cycle (x forward, y left, z up); m",
            "strategy": self.observations.strategy,
            "method": self.method,
            "status": status_names()[code],
            "poses": out_poses,
            "positions_m": {r: Tb[:, i, 4:].tolist() for i, r in enumerate(GROUND)},
            "stats": {k: np.asarray(v).tolist() for k, v in self.estimate.stats.items()},
            "detections": dets,
            "notes": self.notes,
        }


def localize_images(
    team: Team,
    images: dict[tuple[int, str], np.ndarray] | None = None,
    *,
    refine: bool = True,
    covariance: bool = True,
) -> ImageLocalization:
    r"""Poses of the whole team from one cycle's images.

    Detection ([`jaxloc.detect_team_images`][]) -> [`jaxloc.CycleObservations`][] ->
    [`jaxloc.localize_cycle`][] (closed form, robust overhead solver) -> optionally
    [`jaxloc.refine_cycle`][] (joint ML over every pixel and odometry distance, weights
    from `team.pixel_sigma`) and [`jaxloc.cycle_covariance`][].

    **Arguments:**

    - `team`: a [`jaxloc.Team`][] (e.g. [`jaxloc.load_team`][]).
    - `images`: optional `{(step, robot): BGR image}`; default: `team.steps`' files.
    - `refine`, `covariance`: run the refinement / the covariance. Keyword only.

    **Returns:** an [`jaxloc.ImageLocalization`][]. Raises `ValueError` if detection fails
    (see [`jaxloc.detect_team_images`][]) or the closed-form estimate fails (its status is
    named), or if the refined fit is statistically inconsistent with `team.pixel_sigma`
    (`inconsistent_fit`: an outlier detection, a wrong camera file or a too small sigma).
    If the refinement is `ambiguous` (two poses fit about equally well), the better one is
    reported and `notes` says so. If the refinement fails otherwise (e.g. iteration
    limit), the closed-form estimate is reported and the reason recorded in `notes`.
    """
    detections = detect_team_images(team, images)
    observations = observations_from_detections(team, detections)
    closed = _localize(observations)
    code = int(status_code(closed.result))
    if code != 0:
        raise ValueError(
            f"Localization from the images of `{team.source}` failed: "
            f"{status_names()[code]} ({RESULTS[closed.result]}). No pose is reported."
        )
    notes: list[str] = []
    estimate, method, cov = closed, "closed_form", None
    if refine:
        scenario = scenario_for(team)
        refined = refine_cycle(observations, scenario, closed, throw=False)
        rcode = int(status_code(refined.result))
        if rcode == 0:
            estimate, method = refined, "refined"
        elif rcode == int(status_code(RESULTS.ambiguous)):
            estimate, method = refined, "refined"
            st = refined.stats
            notes.append(
                f"Ambiguous: another pose, more than 10 cm away, fits the images almost as "
                f"well (chi-square {float(st['runner_up_chi2']):.1f} against "
                f"{float(st['chi2']):.1f}); the better one is reported. Move the robots "
                "to a less symmetric formation to tell them apart."
            )
        elif rcode == int(status_code(RESULTS.inconsistent_fit)):
            # The measurements do not fit one geometry at the stated noise: a wrong blob
            # taken for a marker, a wrong camera file, or `pixel_sigma` too small. The
            # closed-form estimate rests on the same measurements: report no pose.
            st = refined.stats
            raise ValueError(
                f"The images of `{team.source}` are inconsistent: the refined fit has "
                f"chi-square {float(st['chi2']):.1f} for {int(st['dof'])} degrees of freedom "
                f"(RMS pixel residual {float(st['rms_pixel_error']):.3f} px against "
                f"`pixel_sigma` = {team.pixel_sigma} px). Check the detections (a wrong blob "
                "taken for a marker), the camera files and `pixel_sigma`; `--no-refine` "
                "gives the closed-form estimate without this check."
            )
        else:
            notes.append(
                f"Refinement did not succeed ({status_names()[rcode]}); the closed-form "
                "estimate is reported (check `pixel_sigma` and the detections)."
            )
        if covariance and method == "refined":
            cov = _covariance(observations, scenario, estimate)
            if not bool(cov.ok):
                notes.append("The covariance is not available (singular information matrix).")
    return ImageLocalization(estimate, closed, cov, observations, detections, method, notes)


def write_json_atomic(path: str, data: dict[str, Any]) -> None:
    """Write `data` as JSON to `path` atomically (temporary file, then rename)."""
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(data, f, indent=2)
        f.write("\n")
    os.replace(tmp, path)


def team_from_rendered(
    scenario: Scenario,
    observations: CycleObservations,
    out_dir: str | os.PathLike,
    *,
    pixel_sigma: float = 0.3,
) -> Team:
    """A [`jaxloc.Team`][] for a cycle rendered by [`jaxloc.render_cycle`][] into
    `out_dir`: the scenario's cameras (C1's PTZ as its pinhole), the default marker
    colours, the simulated odometry, the PNG paths; also written there as `team.yaml`
    with its camera files, ready for `jaxloc localize --team`."""
    out_dir = os.fspath(out_dir)
    steps = num_steps(scenario.strategy)
    team = Team(
        strategy=scenario.strategy,
        cameras={"C": scenario.overhead, "C1": scenario.ptz.pinhole(), "C2": scenario.omni2,
                 "C3": scenario.omni3},
        markers={"C1": DEFAULT_MARKER_COLORS["red"], "C2": DEFAULT_MARKER_COLORS["green"],
                 "C3": DEFAULT_MARKER_COLORS["blue"]},
        odometry=np.asarray(observations.odometry, np.float64),
        odometry_sigma_rel=float(scenario.odometry_sigma_rel),
        pixel_sigma=pixel_sigma, pan=float(scenario.ptz.pan), tilt=float(scenario.ptz.tilt),
        steps=[{r: os.path.join(out_dir, f"step{k}_{r}.png") for r in ROBOTS}
               for k in range(steps)],
        source=os.path.join(out_dir, "team.yaml"),
    )  # fmt: skip
    save_team(team, os.path.join(out_dir, "team.yaml"))
    return team


