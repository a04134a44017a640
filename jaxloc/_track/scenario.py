r"""A multi-cycle scenario: [`jaxloc.TrackScenario`][], and its section of a scenario file.

The team advances cycle after cycle. Each cycle is an ordinary cycle of the
[`jaxloc.Scenario`][] it holds (same world, cameras, rig, noise, moves and visibility
rules), started where the previous cycle left the ground robots. Between two cycles the
climbing robot moves on the ceiling, following the team, and measures its own motion.

**Formation keeping.** The paper's moves (random directions, N(0.8, 0.2) m, each the
first of `move_candidates` draws that keeps every required sighting) let the triangle
wander, cycle after cycle, into near-collinear shapes: in 256 runs of 20 cycles of the
paper's scenario, the smallest angle of a formation was below 10 degrees in 57 % of the
formations (median 8 degrees). A team on a mission keeps its formation: with
`keep_formation` (default), each move takes, of the same random draws, the feasible one
whose triangle's side lengths are closest to the initial triangle's (the cycle scenario's
`formation_sides`, unless it sets its own; orientation free): below 10 degrees in 3 % of
the formations (median 33 degrees), and 96 % of the runs keep every required sighting for
20 cycles (91 % without). Tried and dropped: the best of 8 whole random cycles by their
distance to the initial triangle (12 % below 10 degrees, at 8 times the simulation's
cost), a smallest-angle rule on each move (the shape hugs the rule's limit, where no move
is feasible: 43 % of the runs lost within 20 cycles), and keeping the side length of each
robot pair (the triangle cannot turn to fit the overhead camera's view: most runs lost).

**The climbing robot's motion.** It heads for the point above the middle of the ground
robots' new bounding box (in `E`'s x-y plane), its step shortened to at most
`climber_step_max`. Branch-free, as the ground robots' moves: `move_candidates` places are
drawn around that point (N(0, `climber_step_std`) per axis, each step shortened to
`climber_step_max`) with headings about its initial heading (N(0, `climber_turn_std`): it
keeps the camera's long side along `E`'s x axis), and the one nearest the point from which
the overhead camera sees all three ground robots is taken. (Aiming at the formation's
centroid plus the initial offset instead, no candidate saw the team at about 8 % of the
transitions, against 2 % at the bounding box, random moves in both cases.) A
transition with no such candidate makes the rest of the run infeasible (`not_visible`).

**Its odometry** (measurement model, and why). The climbing robot measures the relative
pose of its body between the two cycles, `Z = T_body(k-1)^-1 T_body(k)`, as
`Z_true exp(n)` with `n = (n_v, n_omega) ~ N(0, diag(s_v^2 I, s_r^2 I))`:
`s_v = climber_odometry_sigma_rel` times the distance travelled (wheel odometry's error
grows with the distance), `s_r = climber_odometry_rotation_sigma` (rad, per transition:
a gyro's heading drift and an accelerometer's tilt over a short move). A relative pose with
a Gaussian in its tangent is the standard odometry factor of pose-graph estimation (GTSAM's
`BetweenFactor<Pose3>`): it is what a wheel + IMU odometry of a robot on an unknown curved
ceiling reports (the ceiling's slope changes its tilt and height, which the IMU sees and the
wheels do not), its noise per axis is explicit, and the simulator draws from exactly the
model the estimators and the bounds use, so that the bounds are those of the simulated
data. A distance-only model like the ground robots' would leave the climbing robot's
heading and tilt change unknown, and the cycles' overhead poses unlinked.

**The first cycle's prior** for one-step localization (no earlier cycle to propagate): the
height of the overhead camera above the plane of the three ground robots, measured with
standard deviation `height_prior_sigma` (m; e.g. from the known room height), and the
climbing robot's body z along that plane's normal with `tilt_prior_sigma` (rad; it clings
to the ceiling, roughly parallel to the floor).

**File format**: a scenario file (see `jaxloc._sim.scenario_file`) with an optional
`tracking` mapping; every key optional, unknown keys are errors naming the key and file:

```yaml
tracking:
  climber_step_max: 1.0                  # m
  climber_step_std: 0.2                  # m, per axis
  climber_turn_std: 0.1                  # rad
  climber_odometry_sigma_rel: 0.01       # of the distance travelled
  climber_odometry_rotation_sigma: 0.01  # rad, per axis, per transition
  height_prior_sigma: 0.2                # m
  tilt_prior_sigma: 0.1745               # rad
  keep_formation: true                   # moves keep the initial triangle's sides
```
"""

import math
import os
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._core.files import (
    atomic_write,
    check_keys,
    dumps_mapping,
    load_mapping,
    naming_file,
    short,
)
from .._sim.scenario import Scenario
from .._sim.scenario_file import scenario_from_dict, scenario_to_dict


#: The `tracking` section's keys and their defaults (see the module docstring).
TRACKING_DEFAULTS = {
    "climber_step_max": 1.0,
    "climber_step_std": 0.2,
    "climber_turn_std": 0.1,
    "climber_odometry_sigma_rel": 0.01,
    "climber_odometry_rotation_sigma": 0.01,
    "height_prior_sigma": 0.2,
    "tilt_prior_sigma": math.radians(10.0),
}
#: The `tracking` section's flags and their defaults.
TRACKING_FLAGS = {"keep_formation": True}
#: Keys that must be positive (the others non-negative).
_POSITIVE = ("climber_step_max", "height_prior_sigma", "tilt_prior_sigma")


def _concrete(x: Any) -> np.ndarray | None:
    return None if isinstance(x, jax.core.Tracer) else np.asarray(x)


class TrackScenario(eqx.Module):
    r"""A multi-cycle scenario: one cycle's [`jaxloc.Scenario`][] and the climbing robot's
    motion between cycles (see the module docstring for the models).

    **Fields:**

    - `scenario`: the cycle's scenario; its formation (`initial_xy` or `base`/`side`),
      `headings`, `overhead_xy` and `overhead_heading` are the team's at the start of the
      first cycle.
    - `climber_step_max`: largest step of the climbing robot between cycles (m, > 0).
    - `climber_step_std`: standard deviation of the random part of its step, per axis (m).
    - `climber_turn_std`: standard deviation of its heading change (rad).
    - `climber_odometry_sigma_rel`: its odometry's translation sigma per axis, relative to
      the distance travelled.
    - `climber_odometry_rotation_sigma`: its odometry's rotation sigma per axis (rad).
    - `height_prior_sigma`: sigma of the first cycle's height prior (m, > 0).
    - `tilt_prior_sigma`: sigma of the first cycle's tilt prior (rad, > 0).
    - `keep_formation` (static): the ground robots' moves keep the initial triangle's
      sides (module docstring); `False`: the paper's random moves.
    """

    scenario: Scenario
    climber_step_max: Float[Array, ""]
    climber_step_std: Float[Array, ""]
    climber_turn_std: Float[Array, ""]
    climber_odometry_sigma_rel: Float[Array, ""]
    climber_odometry_rotation_sigma: Float[Array, ""]
    height_prior_sigma: Float[Array, ""]
    tilt_prior_sigma: Float[Array, ""]
    keep_formation: bool = eqx.field(static=True)

    def __init__(
        self,
        scenario: Scenario | None = None,
        climber_step_max: Float[ArrayLike, ""] = TRACKING_DEFAULTS["climber_step_max"],
        climber_step_std: Float[ArrayLike, ""] = TRACKING_DEFAULTS["climber_step_std"],
        climber_turn_std: Float[ArrayLike, ""] = TRACKING_DEFAULTS["climber_turn_std"],
        climber_odometry_sigma_rel: Float[ArrayLike, ""] = TRACKING_DEFAULTS[
            "climber_odometry_sigma_rel"
        ],
        climber_odometry_rotation_sigma: Float[ArrayLike, ""] = TRACKING_DEFAULTS[
            "climber_odometry_rotation_sigma"
        ],
        height_prior_sigma: Float[ArrayLike, ""] = TRACKING_DEFAULTS["height_prior_sigma"],
        tilt_prior_sigma: Float[ArrayLike, ""] = TRACKING_DEFAULTS["tilt_prior_sigma"],
        keep_formation: bool = TRACKING_FLAGS["keep_formation"],
    ):
        """**Arguments:** the fields above; `scenario` defaults to the paper's
        ([`jaxloc.Scenario.paper`][], sequential). Numbers take the scenario's dtype."""
        self.scenario = Scenario.paper() if scenario is None else scenario
        dtype = self.scenario.base.dtype if isinstance(self.scenario, Scenario) else None
        for name, value in (
            ("climber_step_max", climber_step_max),
            ("climber_step_std", climber_step_std),
            ("climber_turn_std", climber_turn_std),
            ("climber_odometry_sigma_rel", climber_odometry_sigma_rel),
            ("climber_odometry_rotation_sigma", climber_odometry_rotation_sigma),
            ("height_prior_sigma", height_prior_sigma),
            ("tilt_prior_sigma", tilt_prior_sigma),
        ):
            x = jnp.asarray(value)
            if not jnp.issubdtype(x.dtype, jnp.inexact) or dtype is not None:
                x = x.astype(dtype if dtype is not None else float)
            setattr(self, name, x)
        self.keep_formation = keep_formation

    def __check_init__(self):
        if not isinstance(self.scenario, Scenario):
            raise ValueError(
                f"`TrackScenario(scenario=...)` must be a jaxloc.Scenario; got "
                f"{type(self.scenario).__name__}."
            )
        if not isinstance(self.keep_formation, bool):
            raise ValueError(
                f"`TrackScenario(keep_formation=...)` must be a bool; got {self.keep_formation!r}."
            )
        for name in TRACKING_DEFAULTS:
            x = getattr(self, name)
            if x.shape != ():
                raise ValueError(
                    f"`TrackScenario({name}=...)` must be a scalar; got shape {x.shape}."
                )
            v = _concrete(x)
            if v is None:
                continue
            if not np.isfinite(v):
                raise ValueError(f"`TrackScenario({name}=...)` must be finite; got {v}.")
            if name in _POSITIVE and not v > 0:
                raise ValueError(f"`TrackScenario({name}=...)` must be positive; got {v}.")
            if not v >= 0:
                raise ValueError(f"`TrackScenario({name}=...)` must be non-negative; got {v}.")


    @property
    def rig(self):
        """The team's [`jaxloc.Rig`][] (the cycle scenario's)."""
        return self.scenario.rig

    @property
    def strategy(self) -> str:
        """The cycles' strategy."""
        return self.scenario.strategy


def tracking_to_dict(track: TrackScenario) -> dict[str, Any]:
    """The `tracking` section of a scenario file (plain floats)."""
    d: dict[str, Any] = {
        k: float(np.asarray(getattr(track, k), np.float64)) for k in TRACKING_DEFAULTS
    }
    d.update({k: bool(getattr(track, k)) for k in TRACKING_FLAGS})
    return d


def track_scenario_to_dict(track: TrackScenario) -> dict[str, Any]:
    """The file representation of `track`: the cycle scenario's
    ([`jaxloc.scenario_to_dict`][]) with a `tracking` section."""
    d = scenario_to_dict(track.scenario)
    d["tracking"] = tracking_to_dict(track)
    return d


def _tracking_kwargs(section: Any) -> dict[str, Any]:
    check_keys(section, set(TRACKING_DEFAULTS) | set(TRACKING_FLAGS), where="`tracking`")
    kwargs: dict[str, Any] = {}
    for k, v in section.items():
        if k in TRACKING_FLAGS:
            if not isinstance(v, bool):
                raise ValueError(
                    f"Scenario field `tracking.{k}` must be true or false; got {short(v)}."
                )
            kwargs[k] = v
            continue
        if not isinstance(v, int | float) or isinstance(v, bool) or not math.isfinite(v):
            raise ValueError(f"Scenario field `tracking.{k}` must be a finite number; got "
                             f"{short(v)}.")  # fmt: skip
        if k in _POSITIVE and not v > 0:
            raise ValueError(f"Scenario field `tracking.{k}` must be positive; got {short(v)}.")
        if not v >= 0:
            raise ValueError(
                f"Scenario field `tracking.{k}` must be non-negative; got {short(v)}."
            )
        kwargs[k] = float(v)
    return kwargs


def track_scenario_from_dict(d: Any) -> TrackScenario:
    """Build and validate a [`jaxloc.TrackScenario`][] from a scenario file's mapping: the
    cycle scenario by [`jaxloc.scenario_from_dict`][] (its rules and messages), the
    optional `tracking` section by this module's (unknown keys, non-finite or negative
    values raise a `ValueError` naming the field)."""
    if not isinstance(d, dict):
        raise ValueError(f"A scenario must be a mapping; got {short(d)}.")
    d = dict(d)
    kwargs = _tracking_kwargs(d.pop("tracking", None) or {})
    return TrackScenario(scenario_from_dict(d), **kwargs)


def load_track_scenario(path: str | os.PathLike) -> TrackScenario:
    """Read a multi-cycle scenario from a YAML or JSON scenario file (with or without a
    `tracking` section); errors are one line naming the file (see
    [`jaxloc.load_scenario`][])."""
    path = os.fspath(path)
    d = load_mapping(path, what="scenario file")
    with naming_file(path, "scenario file"):
        return track_scenario_from_dict(d)


def save_track_scenario(track: TrackScenario, path: str | os.PathLike) -> None:
    """Write `track` as a scenario file with its `tracking` section (YAML or JSON by the
    suffix), atomically; [`jaxloc.load_track_scenario`][] reads it back exactly."""
    atomic_write(path, dumps_mapping(track_scenario_to_dict(track), path))
