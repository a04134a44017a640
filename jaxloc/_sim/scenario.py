r"""A simulation scenario: the world, the formation, the moves, and the team's rig.

A [`jaxloc.Scenario`][] holds everything [`jaxloc.simulate_cycle`][] needs: a
[`jaxloc.Rig`][] (the team's cameras, mounts, markers and pixel noise, which is all the
solvers see) and the world it moves in. Its float
parameters are array leaves (so `jax.grad`/`jax.vmap` reach them, e.g. for formation
design); its configuration (strategy, noise model, candidate count, visibility
requirements) is static.
Its file format (YAML or JSON) is read and written by `jaxloc._sim.scenario_file`.
"""

import dataclasses
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._cameras.models import AbstractCamera
from .._cameras.presets import paper_omni_camera, paper_overhead_camera, paper_ptz_camera
from .._cycle.layout import num_moves, STRATEGIES
from .._cycle.rig import NOISE_MODELS as NOISE_MODELS, Rig
from .world import (
    AbstractSurface,
    FlatSurface,
    formation_xy,
    SaddleSurface,
    SinusoidSurface,
)


#: Surface field names whose file key (and constructor argument) differs.
SURFACE_FIELD_KEYS = {"z0": "height"}


def _as_float(x: Any) -> Array:
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.inexact) else x.astype(float)


def _concrete(x: Any) -> np.ndarray | None:
    """`x` as a NumPy array if its value is known now (not a tracer), else `None`."""
    if isinstance(x, jax.core.Tracer):
        return None
    try:
        return np.asarray(x)
    except Exception:  # pragma: no cover - abstract values
        return None


def _rig_or_cameras(rig, cameras, pixel_sigma, noise_model) -> Rig:
    """`rig`, or (if `None`) the [`jaxloc.Rig`][] of the `cameras` `(overhead, ptz,
    omni2, omni3)` (`None` ones the paper's presets); giving both is an error."""
    if rig is not None:
        if any(x is not None for x in cameras):
            raise ValueError(
                "`Scenario(rig=...)` holds the cameras: give either `rig` or the cameras "
                "(`overhead`, `ptz`, `omni2`, `omni3`), not both."
            )
        return rig
    overhead, ptz, omni2, omni3 = cameras
    return Rig(
        paper_overhead_camera() if overhead is None else overhead,
        paper_ptz_camera() if ptz is None else ptz,
        paper_omni_camera() if omni2 is None else omni2,
        paper_omni_camera() if omni3 is None else omni3,
        pixel_sigma=_as_float(pixel_sigma),
        noise_model=noise_model,
    )


def _bad(name: str, msg: str):
    raise ValueError(f"`Scenario({name}=...)` {msg}")


def _check_config(scenario: "Scenario") -> None:
    """The types of the surfaces, the rig and the static configuration."""
    for name in ("ground", "ceiling"):
        if not isinstance(getattr(scenario, name), AbstractSurface):
            _bad(name, f"must be a surface; got {getattr(scenario, name)!r}.")
    if not isinstance(scenario.rig, Rig):
        _bad("rig", f"must be a Rig; got {type(scenario.rig).__name__}.")
    if scenario.strategy not in STRATEGIES:
        _bad("strategy", f"must be one of {STRATEGIES}; got {scenario.strategy!r}.")
    k = scenario.move_candidates
    if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 1:
        _bad("move_candidates", f"must be a positive integer; got {k!r}.")
    for name in ("require_overhead", "require_ptz", "require_omni"):
        if not isinstance(getattr(scenario, name), bool):
            _bad(name, f"must be a bool; got {getattr(scenario, name)!r}.")


#: Shape of each scalar-or-vector parameter of a `Scenario` (default `()`), and the sign
#: its concrete value must have.
_PARAMETER_SHAPES = {"headings": (3,), "overhead_xy": (2,)}
_PARAMETER_SIGNS = {
    "base": (lambda v: v > 0, "must be positive"),
    "side": (lambda v: v > 0, "must be positive"),
    "move_mean": (lambda v: v > 0, "must be positive"),
    "move_std": (lambda v: v >= 0, "must be nonnegative"),
    "min_separation": (lambda v: v >= 0, "must be nonnegative"),
    "odometry_sigma_rel": (lambda v: v >= 0, "must be nonnegative"),
}


def _check_parameters(scenario: "Scenario") -> None:
    """Shapes, finiteness and signs of the array parameters (values when concrete), and
    that `base`, `side` make an isosceles triangle."""
    for name in (
        "base", "side", "headings", "overhead_xy", "overhead_heading", "move_mean",
        "move_std", "min_separation", "odometry_sigma_rel",
    ):  # fmt: skip
        x = getattr(scenario, name)
        shape = _PARAMETER_SHAPES.get(name, ())
        if x.shape != shape:
            _bad(name, f"must have shape {shape}; got shape {x.shape}.")
        v = _concrete(x)
        if v is not None and not np.all(np.isfinite(v)):
            _bad(name, f"must be finite; got {v}.")
    for name, (ok, msg) in _PARAMETER_SIGNS.items():
        v = _concrete(getattr(scenario, name))
        if v is not None and not ok(v):
            _bad(name, f"{msg}; got {v}.")
    b, s = _concrete(scenario.base), _concrete(scenario.side)
    if b is not None and s is not None and not s > 0.5 * b:
        _bad("side", f"must exceed `base / 2` = {0.5 * b} for a triangle; got {s}.")


def _check_initial_xy(initial_xy) -> None:
    """`initial_xy`: `None` or a finite, non-degenerate triangle `(3, 2)` (m)."""
    if initial_xy is None:
        return
    if initial_xy.shape != (3, 2):
        _bad("initial_xy", f"must have shape (3, 2) (C1, C2, C3); got shape "
             f"{initial_xy.shape}.")  # fmt: skip
    v = _concrete(initial_xy)
    if v is not None:
        if not np.all(np.isfinite(v)):
            _bad("initial_xy", f"must be finite; got {v.tolist()}.")
        u, w = v[1] - v[0], v[2] - v[0]
        if abs(u[0] * w[1] - u[1] * w[0]) <= 1e-9:
            _bad("initial_xy", f"must be a triangle (three non-collinear points); "
                 f"got {v.tolist()}.")  # fmt: skip


def _check_moves(moves, strategy: str) -> None:
    """`moves`: `None` or the strategy's `(num_moves, 2)` finite (length > 0, direction)."""
    if moves is None:
        return
    want = (num_moves(strategy), 2)
    if moves.shape != want:
        _bad("moves", f"must have shape {want} (length, direction) for the "
             f"{strategy} strategy; got shape {moves.shape}.")  # fmt: skip
    v = _concrete(moves)
    if v is not None:
        if not np.all(np.isfinite(v)):
            _bad("moves", f"must be finite; got {v.tolist()}.")
        if not np.all(v[:, 0] > 0):
            _bad("moves", f"lengths (column 0) must be positive; got {v.tolist()}.")


def _check_formation_sides(sides) -> None:
    """`formation_sides`: `None` or three finite positive lengths (m)."""
    if sides is None:
        return
    if sides.shape != (3,):
        _bad("formation_sides", f"must have shape (3,) (three side lengths); got "
             f"shape {sides.shape}.")  # fmt: skip
    v = _concrete(sides)
    if v is not None and not np.all(np.isfinite(v) & (v > 0)):
        _bad("formation_sides", f"must be finite positive lengths (m); got {v.tolist()}.")


class Scenario(eqx.Module):
    r"""One simulated localization setting: world, formation, cameras, moves and noise.

    Frames: the environment frame `E` (z up, metres), origin at the middle of the
    triangle's base; see [`jaxloc.formation_xy`][] and [`jaxloc.body_pose_on_surface`][].

    **Fields:**

    - `ground`, `ceiling`: [`jaxloc.AbstractSurface`][]s the ground robots and the
      climbing robot stand on.
    - `base`, `side`: initial isosceles triangle (m): base C2–C3, legs C1–C2 and C1–C3,
      placed by [`jaxloc.formation_xy`][]. Ignored if `initial_xy` is given.
    - `initial_xy`: `None` (default: the isosceles triangle of `base`, `side`) or a
      general initial triangle: `(x, y)` of C1, C2, C3 in `E` (m), shape `(3, 2)`. Read
      the triangle in use with [`jaxloc.Scenario.formation_xy`][].
    - `headings`: initial headings of C1, C2, C3 (rad, in the `E` x-y plane from +x
      towards +y), shape `(3,)`. Default 0: all face the base (+x); C1's PTZ then sees
      C2 and C3 at ±41.8° inside its 85° field of view.
    - `overhead_xy`: `(x, y)` of the climbing robot on the ceiling (m), shape `(2,)`.
    - `overhead_heading`: its heading (rad); default 90°, so that the image's long axis
      (camera x = body -y) runs along `E` +x, the triangle's long direction.
    - `rig`: the team's [`jaxloc.Rig`][]: the cameras of C, C1, C2, C3 (`rig.overhead`,
      `rig.ptz`, `rig.omni2`, `rig.omni3`), their mounts, the markers and the pixel noise
      (`rig.pixel_sigma`, `rig.noise_model`). The simulator draws pixel noise from it;
      the solvers see only it. Formation design moves C1's pan, tilt and zoom, so its
      camera must be a [`jaxloc.PTZCamera`][] there.
    - `move_mean`, `move_std`: move length ~ N(mean, std) (m), clipped to at least
      0.05 m. Unused with fixed `moves`.
    - `moves`: `None` (default: random moves, see [`jaxloc.simulate_cycle`][]) or the
      strategy's fixed moves, shape `(num_moves, 2)`: row `m` is move `m`'s length (m,
      > 0) and direction (rad, in the mover's body frame at the start of the move, from
      body x towards body y), in the strategy's move order (sequential: C2, C3, C1;
      concurrent: C2 and C3 together, then C2 and C3 again). Applied exactly: never
      resampled; a cycle whose fixed moves break a required sighting is reported
      infeasible.
    - `min_separation`: smallest allowed distance between two ground robots after a move
      (m), a collision guard (the Pioneer robots are ~0.4 m across). Our addition.
    - `formation_sides`: `None` (default: each move takes the first feasible candidate, the
      paper's random moves) or three side lengths (m, in the `E` x-y plane, shape `(3,)`)
      that the team keeps: each move takes the feasible candidate whose triangle's sides,
      sorted, are closest to them, sorted (least squares: the triangle's size and shape
      are kept, its orientation and which robot stands where are free, so that it can
      turn to stay in view). Our addition: over many cycles the random moves otherwise let
      the triangle drift into near-collinear shapes (`jaxloc._track`).
    - `odometry_sigma_rel`: relative standard deviation of a move's measured distance.
    - `strategy` (static): `"sequential"` or `"concurrent"` (DESIGN §3).
    - `move_candidates` (static): candidates drawn per move for branch-free resampling.
    - `require_overhead`, `require_ptz`, `require_omni` (static): which sightings every
      formation must allow (the overhead camera sees all three robots; C1's PTZ sees C2
      and C3; each omni camera sees the two others inside its elevation band).
    """

    ground: AbstractSurface
    ceiling: AbstractSurface
    base: Float[Array, ""]
    side: Float[Array, ""]
    initial_xy: Float[Array, "3 2"] | None
    headings: Float[Array, "3"]
    overhead_xy: Float[Array, "2"]
    overhead_heading: Float[Array, ""]
    rig: Rig
    move_mean: Float[Array, ""]
    move_std: Float[Array, ""]
    moves: Float[Array, "moves 2"] | None
    formation_sides: Float[Array, "3"] | None
    min_separation: Float[Array, ""]
    odometry_sigma_rel: Float[Array, ""]
    strategy: str = eqx.field(static=True)
    move_candidates: int = eqx.field(static=True)
    require_overhead: bool = eqx.field(static=True)
    require_ptz: bool = eqx.field(static=True)
    require_omni: bool = eqx.field(static=True)

    def __init__(
        self,
        ground: AbstractSurface | None = None,
        ceiling: AbstractSurface | None = None,
        base: Float[ArrayLike, ""] = 2.0,
        side: Float[ArrayLike, ""] = 1.5,
        headings: Float[ArrayLike, "3"] = (0.0, 0.0, 0.0),
        overhead_xy: Float[ArrayLike, "2"] = (0.0, 0.0),
        overhead_heading: Float[ArrayLike, ""] = 0.5 * math.pi,
        overhead: AbstractCamera | None = None,
        ptz: AbstractCamera | None = None,
        omni2: AbstractCamera | None = None,
        omni3: AbstractCamera | None = None,
        move_mean: Float[ArrayLike, ""] = 0.8,
        move_std: Float[ArrayLike, ""] = 0.2,
        min_separation: Float[ArrayLike, ""] = 0.4,
        pixel_sigma: Float[ArrayLike, ""] | Float[ArrayLike, "4"] = 2.0,
        odometry_sigma_rel: Float[ArrayLike, ""] = 0.01,
        strategy: str = "sequential",
        move_candidates: int = 32,
        noise_model: str = "paper",
        require_overhead: bool = True,
        require_ptz: bool = True,
        require_omni: bool = True,
        initial_xy: Float[ArrayLike, "3 2"] | None = None,
        moves: Float[ArrayLike, "moves 2"] | None = None,
        rig: Rig | None = None,
        formation_sides: Float[ArrayLike, "3"] | None = None,
    ):
        """**Arguments:** the fields above; `None` surfaces and cameras take the paper's
        defaults: `SaddleSurface(-8, 8)`, `SinusoidSurface(3.5, 0.25, 10)`,
        `paper_overhead_camera()`, `paper_ptz_camera()`, `paper_omni_camera()`.
        `initial_xy` and `moves` come last (keyword use recommended) so that positional
        calls written before they existed keep their meaning.
        """
        self.ground = SaddleSurface() if ground is None else ground
        self.ceiling = SinusoidSurface() if ceiling is None else ceiling
        self.base = _as_float(base)
        self.side = _as_float(side)
        self.headings = _as_float(headings)
        self.overhead_xy = _as_float(overhead_xy)
        self.overhead_heading = _as_float(overhead_heading)
        self.rig = _rig_or_cameras(rig, (overhead, ptz, omni2, omni3), pixel_sigma, noise_model)
        self.move_mean = _as_float(move_mean)
        self.move_std = _as_float(move_std)
        self.min_separation = _as_float(min_separation)
        self.odometry_sigma_rel = _as_float(odometry_sigma_rel)
        self.strategy = strategy
        self.move_candidates = move_candidates
        self.require_overhead = require_overhead
        self.require_ptz = require_ptz
        self.require_omni = require_omni
        self.initial_xy = None if initial_xy is None else _as_float(initial_xy)
        self.moves = None if moves is None else _as_float(moves)
        self.formation_sides = None if formation_sides is None else _as_float(formation_sides)

    def __check_init__(self):
        _check_config(self)
        _check_parameters(self)
        _check_initial_xy(self.initial_xy)
        _check_moves(self.moves, self.strategy)
        _check_formation_sides(self.formation_sides)
        check_surface("ground", self.ground)
        check_surface("ceiling", self.ceiling)
        check_ceiling_above_ground(self)

    @classmethod
    def paper(cls, strategy: str = "sequential", **overrides: Any) -> "Scenario":
        """The paper's simulation (Sec. IV.A): saddle ground with radii ∓8 m, sinusoidal
        ceiling 3.5 m above the origin (period 10 m, amplitude 0.25 m), triangle 2 m /
        1.5 m, moves N(0.8, 0.2) m, pixel noise 2 px (paper model), odometry 1%.

        **Arguments:**

        - `strategy`: `"sequential"` or `"concurrent"`.
        - `**overrides`: any other [`jaxloc.Scenario`][] field.
        """
        return cls(strategy=strategy, **overrides)

    @classmethod
    def flat_floor(cls, strategy: str = "sequential", **overrides: Any) -> "Scenario":
        """The paper's real experiment (Sec. IV.B, Table II): flat floor and flat ceiling,
        the overhead camera 2.95 m above the floor (Table II: C at z = 295.5 cm).

        The table's robot layout is given in an unstated world frame without
        orientations, so we keep the simulated formation (triangle 2 m / 1.5 m, overhead
        camera above the middle of the base). With a flat floor the six or seven robot
        positions are coplanar: the 12-unknown linear pose method (Eq. 6) is degenerate.

        **Arguments:**

        - `strategy`: `"sequential"` or `"concurrent"`.
        - `**overrides`: any other [`jaxloc.Scenario`][] field.
        """
        overrides.setdefault("ground", FlatSurface(0.0))
        overrides.setdefault("ceiling", FlatSurface(2.95))
        return cls(strategy=strategy, **overrides)

    def formation_xy(self) -> Float[Array, "3 2"]:
        """Initial `(x, y)` of C1, C2, C3 in `E` (m), shape `(3, 2)`: `initial_xy` if
        given, else the isosceles triangle [`jaxloc.formation_xy`][]`(base, side)`."""
        if self.initial_xy is not None:
            return self.initial_xy
        return formation_xy(self.base, self.side)

    @property
    def fixed_moves(self) -> bool:
        """Whether the moves are fixed (`moves` given) rather than random."""
        return self.moves is not None


def check_surface(path: str, surface: AbstractSurface) -> None:
    def bad(field, msg, v):
        raise ValueError(f"Scenario field `{path}.{field}` {msg}; got {v}.")

    leaves = {
        f.name: _concrete(getattr(surface, f.name))
        for f in dataclasses.fields(surface)
        if not f.metadata.get("static", False)
    }
    for name, v in leaves.items():
        if v is not None and not np.all(np.isfinite(v)):
            bad(SURFACE_FIELD_KEYS.get(name, name), "must be finite", v)
    if isinstance(surface, SaddleSurface):
        for name in ("radius_x", "radius_y"):
            v = leaves[name]
            if v is not None and not np.all(v != 0):
                bad(name, "must be nonzero (use a flat surface for zero curvature)", v)
    if isinstance(surface, SinusoidSurface):
        v = leaves["period"]
        if v is not None and not np.all(v > 0):
            bad("period", "must be positive", v)


def astype(scenario: Scenario, dtype: Any) -> Scenario:
    """Cast every floating-point leaf of `scenario` (surfaces, cameras, parameters) to
    `dtype`, e.g. `jnp.float32`. Static configuration is unchanged.
    """
    return jax.tree.map(
        lambda x: x.astype(dtype) if eqx.is_inexact_array(x) else x, scenario
    )





def check_ceiling_above_ground(scenario: Scenario) -> None:
    """Raise `ValueError` unless `scenario`'s ceiling is above its ground at the initial
    position of each ground robot (C1, C2, C3) and at the overhead robot's `overhead_xy`,
    naming the fields, the place and by how much (m). Skipped for traced values (the
    check is eager; call it from constructors and loaders)."""
    xy = _concrete(scenario.formation_xy())
    c_xy = _concrete(scenario.overhead_xy)
    if xy is None or c_xy is None:
        return
    places = [f"{r}'s initial position" for r in ("C1", "C2", "C3")] + ["`overhead_xy`"]
    points = np.concatenate([np.asarray(xy), np.asarray(c_xy)[None]], axis=0)
    ceiling = _concrete(scenario.ceiling.height(points))
    ground = _concrete(scenario.ground.height(points))
    if ceiling is None or ground is None:
        return
    for place, p, c, g in zip(places, points.tolist(), ceiling.tolist(), ground.tolist()):
        if not c > g:
            raise ValueError(
                f"Scenario fields `ceiling` and `ground`: the ceiling must be above the ground; "
                f"at {place} (x, y) = ({p[0]:.6g}, {p[1]:.6g}) m it is {g - c:.6g} m below it "
                f"(ceiling {c:.6g} m, ground {g:.6g} m)."
            )
