r"""Localization from a team's images: marker detections -> observations -> poses.

The image front end produces the same [`jaxloc.CycleObservations`][] the simulator does
(DESIGN §6), so the estimators are unchanged: [`jaxloc.localize_cycle`][], then (if asked)
[`jaxloc.refine_cycle`][] and [`jaxloc.cycle_covariance`][]. The team file is read by
[`jaxloc.load_team`][] (`jaxloc._vision.team`).

**What is measured.** At step `k`: C1's image gives the bearings of C2 and C3, C2's of C1
and C3, C3's of C1 and C2, and C's image the overhead bearings of all three. A marker
that was not detected (occluded, out of view) or is cut by the image edge is a missing
sighting: the estimators use every sighting present, and the status says
`unobservable` (or why else) when too little is left. At least four distinct robot
placements over the cycle must be seen by C. An ambiguous colour (two blobs pass every
test), an unreadable image or a failed estimate raise a `ValueError` naming the
team-file field and the value: never a wrong pose.

**The rig.** The team's cameras enter the gates, the refinement and the covariance
exactly as calibrated ([`jaxloc.rig_for`][]): every camera file's model, distortion
included, and C1's calibrated pinhole mounted through the head's pan and tilt; the
detected pixels are the measurements.
"""

import dataclasses
import os
from typing import Any

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, Float

from .._cameras.base import compiled_unproject
from .._cameras.models import OmniCamera
from .._cameras.presets import R_BODY_OMNI, R_BODY_OVERHEAD, R_BODY_PTZ
from .._core.compiler import compiled_ahead, jit
from .._core.files import atomic_write_json
from .._core.poses import ypr_from_rotation
from .._core.results import RESULTS, status_code, status_names
from .._core.robust import robust_loss
from .._cycle.estimate import rejected_sightings
from .._cycle.layout import num_steps, placement_ids
from .._cycle.observations import CycleObservations
from .._cycle.rig import mount_pose, Rig
from .._refine.cycle import refine_cycle
from .._sim.scenario import Scenario
from .._solvers.localize import localize_cycle
from .markers import (
    annulus_mask,
    check_image,
    DEFAULT_MARKER_COLORS,
    detect_markers,
    MarkerDetection,
    read_image,
)
from .render import annulus_of, sphere_center_pixel
from .team import GROUND, ROBOTS, save_team, Team


# Which robots each camera sees: (observer, targets).
_SEES = {"C": GROUND, "C1": ("C2", "C3"), "C2": ("C1", "C3"), "C3": ("C1", "C2")}


def c1_mount(team: Team) -> np.ndarray:
    """`R_body_camera` of C1's calibrated camera: the PTZ mount `R_BODY_PTZ` times the
    head's pan and tilt (`R_base_optical = Ry(pan) Rx(tilt)`, jaxloc's PTZ convention)."""
    R_base_optical = jaxlie.SO3.from_y_radians(team.pan) @ jaxlie.SO3.from_x_radians(team.tilt)
    return R_BODY_PTZ @ np.asarray(R_base_optical.as_matrix())


def rig_for(team: Team) -> Rig:
    """The [`jaxloc.Rig`][] of a team, exactly as calibrated: its four camera files'
    models (distortion included; C1's pinhole at the zoom used, its mount turned by the
    head's pan and tilt), the paper's mounts otherwise, markers at the body origins, and
    Gaussian pixel noise of `team.pixel_sigma` per axis."""
    mounts = np.stack([
        mount_pose(R_BODY_OVERHEAD), mount_pose(c1_mount(team)), mount_pose(R_BODY_OMNI),
        mount_pose(R_BODY_OMNI),
    ])  # fmt: skip
    cams = team.cameras
    return Rig(
        cams["C"], cams["C1"], cams["C2"], cams["C3"], mounts=jnp.asarray(mounts),
        pixel_sigma=team.pixel_sigma, noise_model="gaussian",
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
            out[(k, obs)] = det
    return out


def observations_from_detections(
    team: Team, detections: dict[tuple[int, str], dict[str, MarkerDetection]]
) -> CycleObservations:
    """Bearings (body frames for the ground robots, camera frame for C), pixels (as
    detected, in each calibrated camera's image) and odometry of one cycle from its
    detections; an undetected marker, or one cut by the image edge, is missing (NaN and
    not visible), in any image."""
    steps = num_steps(team.strategy)
    idx = {"C1": 0, "C2": 1, "C3": 2}
    mounts = {"C1": c1_mount(team), "C2": R_BODY_OMNI, "C3": R_BODY_OMNI}
    mutual = np.full((steps, 3, 3, 3), np.nan)
    mpix = np.full((steps, 3, 3, 2), np.nan)
    over = np.full((steps, 3, 3), np.nan)
    over_vis = np.zeros((steps, 3), bool)
    opix = np.full((steps, 3, 2), np.nan)
    for k in range(steps):
        for obs in GROUND:
            i = idx[obs]
            for t, dt in detections[(k, obs)].items():
                # An undetected marker, or one cut by the image edge (its centroid would
                # be biased), is a missing sighting: NaN, and the estimators do without.
                if not dt.detected or dt.truncated:
                    continue
                j = idx[t]
                b = np.asarray(compiled_unproject(team.cameras[obs], jnp.asarray(dt.pixel)))
                mutual[k, i, j] = mounts[obs] @ b
                mpix[k, i, j] = dt.pixel
        for t, dt in detections[(k, "C")].items():
            # A marker cut by the image border would bias C's pose: dropped (the
            # overhead solve has redundancy; too few remaining placements raise below).
            if dt.detected and not dt.truncated:
                j = idx[t]
                pixel = jnp.asarray(dt.pixel)
                over[k, j] = np.asarray(compiled_unproject(team.cameras["C"], pixel))
                over_vis[k, j] = True
                opix[k, j] = dt.pixel
    # Distinct robot placements seen by C (robots that did not move keep theirs).
    ids = placement_ids(team.strategy)
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


@jit
def _localize(observations: CycleObservations, rig: Rig):
    return localize_cycle(observations, rig, throw=False)


@jit
def _ypr_deg(wxyz: Float[Array, "n 4"]) -> Float[Array, "n 3"]:
    return jax.vmap(lambda q: ypr_from_rotation(jaxlie.SO3(q)))(wxyz)


@dataclasses.dataclass
class ImageLocalization:
    """Result of [`jaxloc.localize_images`][].

    **Fields:** `estimate` (the [`jaxloc.CycleEstimate`][] reported: refined if
    refinement ran and succeeded), `closed_form` (the closed-form estimate),
    `covariance` (a [`jaxloc.CycleCovariance`][] or `None`), `observations`,
    `detections`, `method` (`"refined"` or `"closed_form"`), `notes`, `rejected`: the
    sightings a robust refinement left out as outliers, `(kind, step, observer,
    target)` as [`jaxloc.rejected_sightings`][] lists them (empty without a `loss`).
    """

    estimate: Any
    closed_form: Any
    covariance: Any
    observations: CycleObservations
    detections: dict[tuple[int, str], dict[str, MarkerDetection]]
    method: str
    notes: list[str]
    rejected: list[tuple[str, int, str, str]] = dataclasses.field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready report: the four end-of-cycle poses (position m, quaternion wxyz,
        yaw/pitch/roll deg, covariances when available) in the world frame (C1's body
        frame at the start of the cycle), every robot's positions at every step, the
        detections, status and diagnostics."""
        poses = self.estimate.poses
        Tb = np.asarray(poses.T_world_body.wxyz_xyz)
        To = np.asarray(poses.T_world_overhead.wxyz_xyz)
        ends = np.stack([To, Tb[-1, 0], Tb[-1, 1], Tb[-1, 2]])
        ypr = np.asarray(_ypr_deg(jnp.asarray(ends[:, :4])))
        cov = self.covariance
        if cov is not None and bool(cov.ok):
            cov_position, cov_rotation = np.asarray(cov.position), np.asarray(cov.rotation)
        out_poses: dict[str, Any] = {}
        for n, (name, T) in enumerate(zip(("C", "C1", "C2", "C3"), ends)):
            entry = {"position_m": T[4:].tolist(), "quaternion_wxyz": T[:4].tolist(),
                     "ypr_deg": ypr[n].tolist()}  # fmt: skip
            if name == "C":
                entry["frame"] = "optical (x right, y down, z forward)"
            if cov is not None and bool(cov.ok):
                P, Q = cov_position[n], cov_rotation[n]
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
            "checks": _checks_dict(self.estimate.checks),
            "detections": dets,
            "missing_sightings": self.missing(),
            "rejected_sightings": [
                {"kind": kind, "step": step, "observer": observer, "target": target}
                for kind, step, observer, target in self.rejected
            ],
            "notes": self.notes,
        }

    def missing(self) -> list[dict[str, Any]]:
        """The sightings the estimate did without: every marker not found in its image
        (occluded, out of view) or cut by the image border, as `{"kind": "mutual" |
        "overhead", "step", "observer", "target", "reason"}`, in step order."""
        out = []
        for (k, obs), det in sorted(self.detections.items()):
            for t, d in det.items():
                if d.detected and not d.truncated:
                    continue
                out.append({
                    "kind": "overhead" if obs == "C" else "mutual", "step": k,
                    "observer": obs, "target": t,
                    "reason": "cut by the image border" if d.detected else "marker not found",
                })  # fmt: skip
        return out


def _checks_dict(checks) -> dict[str, Any]:
    """The estimate's goodness-of-fit and reliability figures (`jaxloc.FitCheck`), JSON
    ready (non-finite as `None`)."""

    def num(x):
        x = float(x)
        return x if np.isfinite(x) else None

    return {
        "chi2": num(checks.chi2), "dof": int(checks.dof), "chi2_limit": num(checks.chi2_limit),
        "worst_sighting": num(checks.worst_sighting), "blunder_nees": num(checks.blunder_nees),
    }  # fmt: skip


def localize_images(
    team: Team,
    images: dict[tuple[int, str], np.ndarray] | None = None,
    *,
    refine: bool = True,
    covariance: bool = True,
    loss: str | None = None,
    loss_scale: float | None = None,
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
    - `loss`, `loss_scale`: the refinement's robust loss (`"huber"` or `"cauchy"`) and
      its scale, as in [`jaxloc.refine_cycle`][]: a detection that does not fit the
      others (a distractor taken for a marker) is left out and named in `rejected`.
      Default `None`: plain least squares, where such a detection makes the fit
      `inconsistent_fit`. Keyword only.

    **Returns:** an [`jaxloc.ImageLocalization`][]. Raises `ValueError` if detection fails
    (see [`jaxloc.detect_team_images`][]) or the closed-form estimate fails (its status is
    named), or if the refined fit is statistically inconsistent with `team.pixel_sigma`
    (`inconsistent_fit`: an outlier detection, a wrong camera file or a too small sigma).
    If the refinement is `ambiguous` (two poses fit about equally well), the better one is
    reported and `notes` says so. If the refinement fails otherwise (e.g. iteration
    limit), the closed-form estimate is reported and the reason recorded in `notes`.
    """
    robust_loss(loss, loss_scale)  # the arguments' errors before any image is read
    detections = detect_team_images(team, images)
    observations = observations_from_detections(team, detections)
    rig = rig_for(team)
    with compiled_ahead():  # the two programs compile side by side, then run below
        placeholder = _localize(observations, rig)
        if refine:
            refine_cycle(observations, rig, placeholder, loss=loss, loss_scale=loss_scale,
                         throw=False)  # fmt: skip
    closed = _localize(observations, rig)
    usable = (RESULTS.successful, RESULTS.inconsistent_fit) if refine else (RESULTS.successful,)
    if not any(bool(closed.result == r) for r in usable):
        _fail(team, closed, "the closed-form estimate")
    if not refine:
        return ImageLocalization(closed, closed, None, observations, detections, "closed_form", [])
    refined = refine_cycle(observations, rig, closed, loss=loss, loss_scale=loss_scale, throw=False)
    notes: list[str] = []
    rejected = rejected_sightings(refined)
    if bool(refined.result == RESULTS.ambiguous):
        notes.append(
            f"Ambiguous: another pose, more than 10 cm away, fits the images almost as "
            f"well (chi-square {float(refined.stats['runner_up_chi2']):.1f} against "
            f"{float(refined.checks.chi2):.1f}); the better one is reported. Move the robots "
            "to a less symmetric formation to tell them apart."
        )
    elif bool(refined.result == RESULTS.inconsistent_fit):
        _inconsistent(team, refined)
    elif not bool(refined.result == RESULTS.successful):
        if not bool(closed.result == RESULTS.successful):
            _fail(team, refined, "the refinement")
        notes.append(
            f"Refinement did not succeed ({status_names()[int(status_code(refined.result))]}); "
            "the closed-form estimate is reported (check `pixel_sigma` and the detections)."
        )
        method = "closed_form"
        return ImageLocalization(closed, closed, None, observations, detections, method, notes)
    cov = refined.covariance if covariance else None
    if cov is not None and not bool(cov.ok):
        notes.append("The covariance is not available (singular information matrix).")
    return ImageLocalization(
        refined, closed, cov, observations, detections, "refined", notes, rejected
    )


def _fail(team: Team, estimate, what: str):
    code = int(status_code(estimate.result))
    raise ValueError(
        f"Localization from the images of `{team.source}` failed: {what} is "
        f"{status_names()[code]} ({RESULTS[estimate.result]}). No pose is reported."
    )


def _inconsistent(team: Team, refined):
    # The measurements do not fit one geometry at the stated noise: a wrong blob taken
    # for a marker, a wrong camera file, or `pixel_sigma` too small. The closed-form
    # estimate rests on the same measurements: report no pose.
    checks = refined.checks
    raise ValueError(
        f"The images of `{team.source}` are inconsistent: the refined fit has chi-square "
        f"{float(checks.chi2):.1f} for {int(checks.dof)} degrees of freedom (limit "
        f"{float(checks.chi2_limit):.1f}; RMS pixel residual "
        f"{float(refined.stats['rms_pixel_error']):.3f} px against `pixel_sigma` = "
        f"{team.pixel_sigma} px). Check the detections (a wrong blob taken for a marker), "
        "the camera files and `pixel_sigma`."
    )


def write_json_atomic(path: str, data: dict[str, Any]) -> None:
    """Write `data` as strict JSON to `path` atomically (see `jaxloc._core.files`)."""
    atomic_write_json(path, data)


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
        cameras={"C": scenario.rig.overhead, "C1": scenario.rig.ptz.pinhole(),
                 "C2": scenario.rig.omni2, "C3": scenario.rig.omni3},
        markers={"C1": DEFAULT_MARKER_COLORS["red"], "C2": DEFAULT_MARKER_COLORS["green"],
                 "C3": DEFAULT_MARKER_COLORS["blue"]},
        odometry=np.asarray(observations.odometry, np.float64),
        odometry_sigma_rel=float(scenario.odometry_sigma_rel),
        pixel_sigma=pixel_sigma, pan=float(scenario.rig.ptz.pan),
        tilt=float(scenario.rig.ptz.tilt),
        steps=[{r: os.path.join(out_dir, f"step{k}_{r}.png") for r in ROBOTS}
               for k in range(steps)],
        source=os.path.join(out_dir, "team.yaml"),
    )  # fmt: skip
    save_team(team, os.path.join(out_dir, "team.yaml"))
    return team
