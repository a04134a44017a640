r"""Mount rotations and the nominal cameras of the paper (Sec. II.A and IV.B).

The paper gives fields of view and the image resolution (640 x 480, Sec. IV.B), not
calibrated intrinsics ("the parameters used are the nominal values from the real camera
manuals", Sec. IV.A). Every number below says whether it is from the paper or our
assumption.

Mount rotations `R_BODY_*` map camera-frame vectors into the robot body frame
(`p_body = R_BODY_CAM @ p_cam`; body: x forward, y left, z up along the surface normal).
The camera centre coincides with the robot's reference point (also the marker the other
cameras see).
"""

import math

import numpy as np

from .models import AbstractCamera, OmniCamera, PinholeCamera, PTZCamera


R_BODY_PTZ = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""`R_body_base` of the PTZ camera on a ground robot, shape `(3, 3)`: the PTZ base frame
(optical frame at pan = tilt = 0: x right, y down, z forward) has base z = body x
(forward), base x = body -y (right), base y = body -z (down)."""

R_BODY_OMNI = np.eye(3)
"""`R_body_omni` of an omnidirectional camera on a ground robot, shape `(3, 3)`:
identity (omni z = body z = up along the mirror axis, x forward, y left)."""

R_BODY_OVERHEAD = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
"""`R_body_cam` of the perspective camera on the ceiling (wall-climbing) robot, shape
`(3, 3)`. Body z is the ceiling normal pointing up into the ceiling and the camera looks
along body -z: columns are cam x = body -y, cam y = body -x, cam z = body -z."""

for _R in (R_BODY_PTZ, R_BODY_OMNI, R_BODY_OVERHEAD):
    _R.setflags(write=False)
del _R


def _focal_from_hfov(width: int, hfov_deg: float) -> float:
    return 0.5 * width / math.tan(math.radians(0.5 * hfov_deg))


def paper_overhead_camera() -> PinholeCamera:
    """The overhead camera C on the wall-climbing robot: SPUD 975T wireless camera
    (Videocomm Tech.), a [`jaxloc.PinholeCamera`][].

    - 52 deg horizontal field of view: paper, Sec. II.A.
    - 640 x 480 pixels: paper, Sec. IV.B (image processing on 640 x 480 images).
    - `fx = fy = 320 / tan(26 deg) = 656.10` px: from the two numbers above, with square
      pixels (our assumption); vertical field of view then 40.2 deg.
    - Principal point at the image centre `(319.5, 239.5)`: our assumption.
    - No distortion: our assumption (the paper simulates an ideal camera).
    """
    w, h = 640, 480
    f = _focal_from_hfov(w, 52.0)
    return PinholeCamera(f, f, 0.5 * (w - 1), 0.5 * (h - 1), image_size=(w, h))


def paper_ptz_camera(pan: float = 0.0, tilt: float = 0.0, zoom: float = 0.0) -> PTZCamera:
    """The PTZ camera C1 on a ground robot: Canon VC-C50i, a [`jaxloc.PTZCamera`][].

    - Horizontal field of view 85 deg (wide end, `zoom = 0`) to 15 deg (tele end,
      `zoom = 1`): paper, Sec. II.A. The paper's simulation uses the wide end (Sec. IV.A).
    - 640 x 480 pixels: paper, Sec. IV.B.
    - Focal length linear in `zoom` between `320 / tan(42.5 deg) = 349.2` px and
      `320 / tan(7.5 deg) = 2430.6` px, square pixels, principal point at the image
      centre, no distortion: our assumptions (see [`jaxloc.PTZCamera`][]).

    **Arguments:**

    - `pan`, `tilt`: radians (see [`jaxloc.PTZCamera`][] for the signs).
    - `zoom`: in `[0, 1]`.
    """
    return PTZCamera(
        pan=pan,
        tilt=tilt,
        zoom=zoom,
        hfov_wide=math.radians(85.0),
        hfov_tele=math.radians(15.0),
        image_size=(640, 480),
    )


# Omni preset: paraboloidal mirror (xi = 1, our assumption). The image radius of a
# direction at elevation e is r(e) = f cos(e) / (sin(e) + xi): it decreases with e, so the
# -12 deg circle is the outer one: r(-12 deg) = 1.2349 f, r(+32 deg) = 0.5543 f. With
# f = 185 px: 228.5 px and 102.5 px, the outer circle 11.5 px inside the 480-px height.
_OMNI_XI = 1.0
_OMNI_F = 185.0


def paper_omni_camera() -> OmniCamera:
    r"""An omnidirectional camera C2/C3 on a ground robot: RemoteReality D40 optics with
    a Point Grey Dragonfly sensor, an [`jaxloc.OmniCamera`][].

    - 360 deg in azimuth, elevation band -12 deg to +32 deg: paper, Sec. II.A.
    - 640 x 480 pixels: paper, Sec. IV.B.
    - `xi = 1` (paraboloidal mirror with orthographic optics, the D40's design): our
      assumption.
    - `fx = fy = 185` px: our choice, so that the whole band fits in the image. In the
      unified model a direction at elevation $e$ lands at radius
      $r(e) = f \cos e / (\sin e + \xi)$ from the principal point (no distortion).
      It decreases with $e$, so the band is an annulus between
      $r(+32°) = 0.554 f = 102.5$ px and $r(-12°) = 1.235 f = 228.5$ px, the outer
      circle 11.5 px inside the image's half-height of 240 px.
    - Principal point at the image centre `(319.5, 239.5)`, no skew, no distortion: our
      assumptions.
    """
    w, h = 640, 480
    return OmniCamera(
        xi=_OMNI_XI,
        fx=_OMNI_F,
        fy=_OMNI_F,
        cx=0.5 * (w - 1),
        cy=0.5 * (h - 1),
        elevation_min=math.radians(-12.0),
        elevation_max=math.radians(32.0),
        image_size=(w, h),
    )


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), float(np.dot(a, b))))


def field_of_view(camera: AbstractCamera) -> dict[str, float]:
    """Field of view of a camera, in degrees. Eager (not for use under jit).

    **Arguments:**

    - `camera`: a [`jaxloc.PinholeCamera`][], [`jaxloc.PTZCamera`][] (at its current
      zoom) or [`jaxloc.OmniCamera`][].

    **Returns:** for a perspective camera, `{"horizontal_deg", "vertical_deg"}`: the
    angles between the bearings of the outer edges of the image (`u = -0.5` and
    `u = width - 0.5` on the row `v = cy`; likewise vertically), distortion included.
    For an omnidirectional camera, `{"azimuth_deg": 360.0, "elevation_min_deg",
    "elevation_max_deg"}`.
    """
    if isinstance(camera, OmniCamera):
        return {
            "azimuth_deg": 360.0,
            "elevation_min_deg": math.degrees(float(camera.elevation_min)),
            "elevation_max_deg": math.degrees(float(camera.elevation_max)),
        }
    if isinstance(camera, PTZCamera):
        camera = camera.pinhole()
    if not isinstance(camera, PinholeCamera):
        raise ValueError(
            "`camera` must be a PinholeCamera, PTZCamera or OmniCamera; got "
            f"{type(camera).__name__}."
        )
    w, h = camera.image_size
    cx, cy = float(camera.cx), float(camera.cy)
    edges = np.array([[-0.5, cy], [w - 0.5, cy], [cx, -0.5], [cx, h - 0.5]])
    b = np.asarray(camera.unproject(edges), dtype=np.float64)
    return {
        "horizontal_deg": _angle_deg(b[0], b[1]),
        "vertical_deg": _angle_deg(b[2], b[3]),
    }
