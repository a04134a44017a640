r"""A simulation scenario: world, formation, cameras, moves, noise; and its file format.

A [`jaxloc.Scenario`][] holds everything [`jaxloc.simulate_cycle`][] needs. Its float
parameters are array leaves (so `jax.grad`/`jax.vmap` reach them, e.g. for formation
design); its configuration (strategy, noise model, candidate count, visibility
requirements) is static.

**File format** (YAML or JSON, same keys as the `Scenario` fields; SI units: metres,
radians, pixels). Surfaces and cameras are nested mappings with a `type`; a camera may
also be a preset name, or a mapping `{preset: <name>, <field>: <override>, ...}`:

```yaml
strategy: sequential            # or concurrent
ground: {type: saddle, radius_x: -8.0, radius_y: 8.0, height: 0.0}
ceiling: {type: sinusoid, height: 3.5, amplitude: 0.25, period: 10.0, phase: 0.0}
base: 2.0
side: 1.5
# initial_xy: [[-1.1, 0.0], [0.0, 1.0], [0.0, -1.0]]   # optional C1, C2, C3: overrides base, side
headings: [0.0, 0.0, 0.0]       # C1, C2, C3 (rad, from E's +x towards +y)
overhead_xy: [0.0, 0.0]
overhead_heading: 1.5707963267948966
cameras:
  overhead: paper_overhead      # or {type: pinhole, fx: ..., fy: ..., cx: ..., cy: ...,
  ptz: {preset: paper_ptz, pan: 0.0}   #      dist: [k1, k2, p1, p2, k3], image_size: [640, 480]}
  omni2: paper_omni
  omni3: {type: omni, xi: 1.0, fx: 185.0, fy: 185.0, cx: 319.5, cy: 239.5}
move_mean: 0.8
move_std: 0.2
# moves: [[0.8, 0.0], [0.8, 0.0], [0.8, 0.0]]   # optional fixed moves: [length, direction]
move_candidates: 32
min_separation: 0.4
pixel_sigma: 2.0
noise_model: paper              # or gaussian
odometry_sigma_rel: 0.01
require_overhead: true
require_ptz: true
require_omni: true
```

Missing keys take the defaults of [`jaxloc.Scenario`][] (the paper's simulation); in
particular without `initial_xy` the triangle is the isosceles `base`/`side` one, and
without `moves` the moves are random. `initial_xy` and `moves` may also be written as
`null`.
Surface types: `saddle` (`radius_x`, `radius_y`, `height`), `flat` (`height`),
`sinusoid` (`height`, `amplitude`, `period`, `phase`). Camera types: `pinhole`, `ptz`,
`omni`, with the constructor arguments of [`jaxloc.PinholeCamera`][],
[`jaxloc.PTZCamera`][], [`jaxloc.OmniCamera`][] as keys. Presets: `paper_overhead`,
`paper_ptz`, `paper_omni`. [`jaxloc.scenario_to_dict`][] always writes full mappings, so
`scenario_from_dict(scenario_to_dict(s))` equals `s` exactly (float64).
"""

import dataclasses
import json
import math
import os
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import yaml
from jaxtyping import Array, ArrayLike, Float

from .._cameras.models import OmniCamera, PinholeCamera, PTZCamera
from .._cameras.presets import paper_omni_camera, paper_overhead_camera, paper_ptz_camera
from .._cycle.observations import num_moves, STRATEGIES
from .world import (
    AbstractSurface,
    FlatSurface,
    formation_xy,
    FunctionSurface,
    SaddleSurface,
    SinusoidSurface,
)


NOISE_MODELS = ("paper", "gaussian")


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
    - `overhead`, `ptz`, `omni2`, `omni3`: the cameras of C, C1, C2, C3.
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
    - `pixel_sigma`: pixel noise scale (px), see `noise_model`.
    - `odometry_sigma_rel`: relative standard deviation of a move's measured distance.
    - `strategy` (static): `"sequential"` or `"concurrent"` (DESIGN §3).
    - `move_candidates` (static): candidates drawn per move for branch-free resampling.
    - `noise_model` (static): `"paper"` (offset of radius ~ N(0, sigma), uniform
      direction: the paper's Sec. IV.A) or `"gaussian"` (N(0, sigma^2) per pixel axis).
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
    overhead: PinholeCamera
    ptz: PTZCamera
    omni2: OmniCamera
    omni3: OmniCamera
    move_mean: Float[Array, ""]
    move_std: Float[Array, ""]
    moves: Float[Array, "moves 2"] | None
    min_separation: Float[Array, ""]
    pixel_sigma: Float[Array, ""]
    odometry_sigma_rel: Float[Array, ""]
    strategy: str = eqx.field(static=True)
    move_candidates: int = eqx.field(static=True)
    noise_model: str = eqx.field(static=True)
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
        overhead: PinholeCamera | None = None,
        ptz: PTZCamera | None = None,
        omni2: OmniCamera | None = None,
        omni3: OmniCamera | None = None,
        move_mean: Float[ArrayLike, ""] = 0.8,
        move_std: Float[ArrayLike, ""] = 0.2,
        min_separation: Float[ArrayLike, ""] = 0.4,
        pixel_sigma: Float[ArrayLike, ""] = 2.0,
        odometry_sigma_rel: Float[ArrayLike, ""] = 0.01,
        strategy: str = "sequential",
        move_candidates: int = 32,
        noise_model: str = "paper",
        require_overhead: bool = True,
        require_ptz: bool = True,
        require_omni: bool = True,
        initial_xy: Float[ArrayLike, "3 2"] | None = None,
        moves: Float[ArrayLike, "moves 2"] | None = None,
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
        self.overhead = paper_overhead_camera() if overhead is None else overhead
        self.ptz = paper_ptz_camera() if ptz is None else ptz
        self.omni2 = paper_omni_camera() if omni2 is None else omni2
        self.omni3 = paper_omni_camera() if omni3 is None else omni3
        self.move_mean = _as_float(move_mean)
        self.move_std = _as_float(move_std)
        self.min_separation = _as_float(min_separation)
        self.pixel_sigma = _as_float(pixel_sigma)
        self.odometry_sigma_rel = _as_float(odometry_sigma_rel)
        self.strategy = strategy
        self.move_candidates = move_candidates
        self.noise_model = noise_model
        self.require_overhead = require_overhead
        self.require_ptz = require_ptz
        self.require_omni = require_omni
        self.initial_xy = None if initial_xy is None else _as_float(initial_xy)
        self.moves = None if moves is None else _as_float(moves)

    def __check_init__(self):
        def bad(name, msg):
            raise ValueError(f"`Scenario({name}=...)` {msg}")

        for name in ("ground", "ceiling"):
            if not isinstance(getattr(self, name), AbstractSurface):
                bad(name, f"must be a surface; got {getattr(self, name)!r}.")
        for name, cls in (
            ("overhead", PinholeCamera),
            ("ptz", PTZCamera),
            ("omni2", OmniCamera),
            ("omni3", OmniCamera),
        ):
            if not isinstance(getattr(self, name), cls):
                bad(name, f"must be a {cls.__name__}; got {type(getattr(self, name)).__name__}.")
        if self.strategy not in STRATEGIES:
            bad("strategy", f"must be one of {STRATEGIES}; got {self.strategy!r}.")
        if self.noise_model not in NOISE_MODELS:
            bad("noise_model", f"must be one of {NOISE_MODELS}; got {self.noise_model!r}.")
        if (
            isinstance(self.move_candidates, bool)
            or not isinstance(self.move_candidates, int | np.integer)
            or self.move_candidates < 1
        ):
            bad("move_candidates", f"must be a positive integer; got {self.move_candidates!r}.")
        for name in ("require_overhead", "require_ptz", "require_omni"):
            if not isinstance(getattr(self, name), bool):
                bad(name, f"must be a bool; got {getattr(self, name)!r}.")
        shapes = {"headings": (3,), "overhead_xy": (2,)}
        for name in (
            "base", "side", "headings", "overhead_xy", "overhead_heading", "move_mean",
            "move_std", "min_separation", "pixel_sigma", "odometry_sigma_rel",
        ):  # fmt: skip
            x = getattr(self, name)
            shape = shapes.get(name, ())
            if x.shape != shape:
                bad(name, f"must have shape {shape}; got shape {x.shape}.")
            v = _concrete(x)
            if v is not None and not np.all(np.isfinite(v)):
                bad(name, f"must be finite; got {v}.")
        checks = {
            "base": (lambda v: v > 0, "must be positive"),
            "side": (lambda v: v > 0, "must be positive"),
            "move_mean": (lambda v: v > 0, "must be positive"),
            "move_std": (lambda v: v >= 0, "must be nonnegative"),
            "min_separation": (lambda v: v >= 0, "must be nonnegative"),
            "pixel_sigma": (lambda v: v >= 0, "must be nonnegative"),
            "odometry_sigma_rel": (lambda v: v >= 0, "must be nonnegative"),
        }
        for name, (ok, msg) in checks.items():
            v = _concrete(getattr(self, name))
            if v is not None and not ok(v):
                bad(name, f"{msg}; got {v}.")
        b, s = _concrete(self.base), _concrete(self.side)
        if b is not None and s is not None and not s > 0.5 * b:
            bad("side", f"must exceed `base / 2` = {0.5 * b} for a triangle; got {s}.")
        if self.initial_xy is not None:
            if self.initial_xy.shape != (3, 2):
                bad("initial_xy", f"must have shape (3, 2) (C1, C2, C3); got shape "
                    f"{self.initial_xy.shape}.")  # fmt: skip
            v = _concrete(self.initial_xy)
            if v is not None:
                if not np.all(np.isfinite(v)):
                    bad("initial_xy", f"must be finite; got {v.tolist()}.")
                u, w = v[1] - v[0], v[2] - v[0]
                if abs(u[0] * w[1] - u[1] * w[0]) <= 1e-9:
                    bad("initial_xy", f"must be a triangle (three non-collinear points); "
                        f"got {v.tolist()}.")  # fmt: skip
        if self.moves is not None:
            want = (num_moves(self.strategy), 2)
            if self.moves.shape != want:
                bad("moves", f"must have shape {want} (length, direction) for the "
                    f"{self.strategy} strategy; got shape {self.moves.shape}.")  # fmt: skip
            v = _concrete(self.moves)
            if v is not None:
                if not np.all(np.isfinite(v)):
                    bad("moves", f"must be finite; got {v.tolist()}.")
                if not np.all(v[:, 0] > 0):
                    bad("moves", f"lengths (column 0) must be positive; got {v.tolist()}.")
        _check_surface("ground", self.ground)
        _check_surface("ceiling", self.ceiling)

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


def _check_surface(path: str, surface: AbstractSurface) -> None:
    def bad(field, msg, v):
        raise ValueError(f"Scenario field `{path}.{field}` {msg}; got {v}.")

    leaves = {
        f.name: _concrete(getattr(surface, f.name))
        for f in dataclasses.fields(surface)
        if not f.metadata.get("static", False)
    }
    for name, v in leaves.items():
        if v is not None and not np.all(np.isfinite(v)):
            bad(_FIELD_TO_KEY.get(name, name), "must be finite", v)
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


# ---------------------------------------------------------------------------------------
# File format.

_FIELD_TO_KEY = {"z0": "height"}  # surface field name -> file key / constructor argument
_SURFACE_TYPES = {"saddle": SaddleSurface, "flat": FlatSurface, "sinusoid": SinusoidSurface}
_CAMERA_TYPES = {"pinhole": PinholeCamera, "ptz": PTZCamera, "omni": OmniCamera}
_CAMERA_PRESETS = {
    "paper_overhead": paper_overhead_camera,
    "paper_ptz": paper_ptz_camera,
    "paper_omni": paper_omni_camera,
}
_CAMERA_SLOTS = {"overhead": "pinhole", "ptz": "ptz", "omni2": "omni", "omni3": "omni"}
_FLOAT_KEYS = {
    "base": (), "side": (), "headings": (3,), "overhead_xy": (2,), "overhead_heading": (),
    "move_mean": (), "move_std": (), "min_separation": (), "pixel_sigma": (),
    "odometry_sigma_rel": (),
}  # fmt: skip
#: Optional array keys: absent or `null` means `None`. Written only when set, so that the
#: file (and a study's manifest) of a scenario without them is what it was before they
#: existed.
_OPTIONAL_KEYS = {"initial_xy": 3, "moves": None}  # key -> required row count (None: any)
_STR_KEYS = {"strategy": STRATEGIES, "noise_model": NOISE_MODELS}
_BOOL_KEYS = ("require_overhead", "require_ptz", "require_omni")
_TOP_KEYS = (
    ("ground", "ceiling", "cameras", "move_candidates")
    + tuple(_FLOAT_KEYS)
    + tuple(_OPTIONAL_KEYS)
    + tuple(_STR_KEYS)
    + _BOOL_KEYS
)


def _is_number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _parse_float(path: str, x: Any, shape: tuple[int, ...]) -> Any:
    if shape == ():
        if not _is_number(x):
            raise ValueError(f"Scenario field `{path}` must be a number; got {x!r}.")
        if not math.isfinite(x):
            raise ValueError(f"Scenario field `{path}` must be finite; got {x!r}.")
        return float(x)
    if not isinstance(x, list | tuple) or len(x) != shape[0] or not all(map(_is_number, x)):
        raise ValueError(
            f"Scenario field `{path}` must be a list of {shape[0]} numbers; got {x!r}."
        )
    if not all(math.isfinite(v) for v in x):
        raise ValueError(f"Scenario field `{path}` must be finite; got {x!r}.")
    return [float(v) for v in x]


def _parse_rows(path: str, x: Any, rows: int | None) -> Any:
    """A `null` or a list of `rows` (any number if `None`) pairs of finite numbers."""
    if x is None:
        return None
    count = "" if rows is None else f"{rows} "
    if (
        not isinstance(x, list | tuple)
        or (rows is not None and len(x) != rows)
        or not x
        or not all(
            isinstance(r, list | tuple) and len(r) == 2 and all(map(_is_number, r)) for r in x
        )
    ):
        raise ValueError(
            f"Scenario field `{path}` must be null or a list of {count}pairs of numbers; "
            f"got {x!r}."
        )
    if not all(math.isfinite(v) for r in x for v in r):
        raise ValueError(f"Scenario field `{path}` must be finite; got {x!r}.")
    return [[float(v) for v in r] for r in x]


def _check_keys(path: str, d: Any, allowed) -> None:
    if not isinstance(d, dict):
        raise ValueError(f"Scenario field `{path}` must be a mapping; got {d!r}.")
    for k in d:
        if k not in allowed:
            where = f"`{path}`" if path else "the scenario"
            raise ValueError(
                f"Unknown key `{k}` in {where}; expected one of {sorted(allowed)}."
            )


def _surface_to_dict(path: str, surface: AbstractSurface) -> dict[str, Any]:
    for name, cls in _SURFACE_TYPES.items():
        if type(surface) is cls:
            d: dict[str, Any] = {"type": name}
            for f in dataclasses.fields(surface):
                d[_FIELD_TO_KEY.get(f.name, f.name)] = _to_builtin(getattr(surface, f.name))
            return d
    kind = "a FunctionSurface" if isinstance(surface, FunctionSurface) else repr(surface)
    raise ValueError(
        f"Scenario field `{path}` is {kind}, which has no file representation; use a "
        f"saddle, flat or sinusoid surface to save the scenario."
    )


def _surface_from_dict(path: str, d: Any) -> AbstractSurface:
    if not isinstance(d, dict) or "type" not in d:
        raise ValueError(
            f"Scenario field `{path}` must be a mapping with a `type` "
            f"({', '.join(_SURFACE_TYPES)}); got {d!r}."
        )
    kind = d["type"]
    if kind not in _SURFACE_TYPES:
        raise ValueError(
            f"Scenario field `{path}.type` must be one of {tuple(_SURFACE_TYPES)}; "
            f"got {kind!r}."
        )
    cls = _SURFACE_TYPES[kind]
    keys = [_FIELD_TO_KEY.get(f.name, f.name) for f in dataclasses.fields(cls)]
    _check_keys(path, d, set(keys) | {"type"})
    kwargs = {k: _parse_float(f"{path}.{k}", v, ()) for k, v in d.items() if k != "type"}
    surface = cls(**kwargs)
    _check_surface(path, surface)
    return surface


def _to_builtin(x: Any) -> Any:
    if isinstance(x, tuple):
        return [_to_builtin(v) for v in x]
    a = np.asarray(x)
    if a.dtype == bool:
        return a.tolist()
    if np.issubdtype(a.dtype, np.integer):
        return a.tolist()
    return np.asarray(a, dtype=np.float64).tolist()


def _camera_to_dict(camera: Any) -> dict[str, Any]:
    kind = {cls: name for name, cls in _CAMERA_TYPES.items()}[type(camera)]
    d: dict[str, Any] = {"type": kind}
    for f in dataclasses.fields(camera):
        d[f.name] = _to_builtin(getattr(camera, f.name))
    return d


def _camera_from_dict(path: str, slot: str, d: Any) -> Any:
    expected = _CAMERA_SLOTS[slot]
    if isinstance(d, str):
        d = {"preset": d}
    if not isinstance(d, dict):
        raise ValueError(
            f"Scenario field `{path}` must be a preset name or a mapping; got {d!r}."
        )
    d = dict(d)
    if "preset" in d:
        name = d.pop("preset")
        if name not in _CAMERA_PRESETS:
            raise ValueError(
                f"Scenario field `{path}.preset` must be one of {tuple(_CAMERA_PRESETS)}; "
                f"got {name!r}."
            )
        base = _camera_to_dict(_CAMERA_PRESETS[name]())
        base.update(d)
        d = base
    kind = d.get("type")
    if kind not in _CAMERA_TYPES:
        raise ValueError(
            f"Scenario field `{path}.type` must be one of {tuple(_CAMERA_TYPES)}; got {kind!r}."
        )
    if kind != expected:
        raise ValueError(
            f"Scenario field `{path}.type` must be {expected!r} for the `{slot}` camera; "
            f"got {kind!r}."
        )
    cls = _CAMERA_TYPES[kind]
    fields = {f.name: f for f in dataclasses.fields(cls)}
    _check_keys(path, d, set(fields) | {"type"})
    kwargs = {}
    for k, v in d.items():
        if k == "type":
            continue
        if k == "image_size":
            if (
                not isinstance(v, list | tuple)
                or len(v) != 2
                or not all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in v)
            ):
                raise ValueError(
                    f"Scenario field `{path}.image_size` must be two positive integers "
                    f"[width, height]; got {v!r}."
                )
            kwargs[k] = (int(v[0]), int(v[1]))
        else:
            shape = (len(v),) if isinstance(v, list | tuple) else ()
            kwargs[k] = _parse_float(f"{path}.{k}", v, shape)
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as e:
        raise ValueError(f"Scenario field `{path}` is invalid: {e}") from e


def scenario_to_dict(scenario: Scenario) -> dict[str, Any]:
    """The file representation of `scenario`: a dict of plain Python values (floats,
    lists, strings, bools), ready for `yaml.safe_dump` or `json.dump`. See the module
    docstring for the format. Float32 scenarios are written as the float64 values of
    their float32 leaves.

    Raises `ValueError` if a surface has no file representation (a
    [`jaxloc.FunctionSurface`][]).
    """
    d: dict[str, Any] = {"strategy": scenario.strategy}
    d["ground"] = _surface_to_dict("ground", scenario.ground)
    d["ceiling"] = _surface_to_dict("ceiling", scenario.ceiling)
    for k in _FLOAT_KEYS:
        d[k] = _to_builtin(getattr(scenario, k))
        if k == "side" and scenario.initial_xy is not None:
            d["initial_xy"] = _to_builtin(scenario.initial_xy)
        if k == "overhead_heading":
            d["cameras"] = {s: _camera_to_dict(getattr(scenario, s)) for s in _CAMERA_SLOTS}
        if k == "move_std" and scenario.moves is not None:
            d["moves"] = _to_builtin(scenario.moves)
    d["move_candidates"] = int(scenario.move_candidates)
    d["noise_model"] = scenario.noise_model
    for k in _BOOL_KEYS:
        d[k] = bool(getattr(scenario, k))
    return d


def scenario_from_dict(d: Any) -> Scenario:
    """Build and validate a [`jaxloc.Scenario`][] from its file representation.

    Missing keys take the defaults (the paper's simulation). Raises `ValueError` naming
    the field path and the bad value for an unknown key, a wrong type, a bad value
    (negative sigma, non-positive length, ...) or an unknown strategy, noise model,
    surface type, camera type or preset.
    """
    _check_keys("", d, set(_TOP_KEYS))
    kwargs: dict[str, Any] = {}
    for k in ("ground", "ceiling"):
        if k in d:
            kwargs[k] = _surface_from_dict(k, d[k])
    for k, shape in _FLOAT_KEYS.items():
        if k in d:
            kwargs[k] = _parse_float(k, d[k], shape)
    for k, rows in _OPTIONAL_KEYS.items():
        if k in d:
            kwargs[k] = _parse_rows(k, d[k], rows)
    for k, allowed in _STR_KEYS.items():
        if k in d:
            if d[k] not in allowed:
                raise ValueError(f"Scenario field `{k}` must be one of {allowed}; got {d[k]!r}.")
            kwargs[k] = d[k]
    for k in _BOOL_KEYS:
        if k in d:
            if not isinstance(d[k], bool):
                raise ValueError(f"Scenario field `{k}` must be true or false; got {d[k]!r}.")
            kwargs[k] = d[k]
    if "move_candidates" in d:
        v = d["move_candidates"]
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise ValueError(
                f"Scenario field `move_candidates` must be a positive integer; got {v!r}."
            )
        kwargs["move_candidates"] = v
    if "cameras" in d:
        cams = d["cameras"]
        _check_keys("cameras", cams, set(_CAMERA_SLOTS))
        for slot, v in cams.items():
            kwargs[slot] = _camera_from_dict(f"cameras.{slot}", slot, v)
    try:
        return Scenario(**kwargs)
    except ValueError as e:
        raise ValueError(f"Invalid scenario: {e}") from e


def load_scenario(path: str | os.PathLike) -> Scenario:
    """Read a scenario from a YAML (`.yaml`/`.yml`, via `yaml.safe_load`) or JSON file
    (any other suffix). See [`jaxloc.scenario_from_dict`][] for validation.
    """
    path = os.fspath(path)
    with open(path, encoding="utf-8") as f:
        text = f.read()
    if path.endswith((".yaml", ".yml")):
        try:
            d = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise ValueError(f"`{path}` is not valid YAML: {e}") from e
    else:
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise ValueError(f"`{path}` is not valid JSON: {e}") from e
    if d is None:
        d = {}
    return scenario_from_dict(d)


def save_scenario(scenario: Scenario, path: str | os.PathLike) -> None:
    """Write `scenario` to `path` as YAML (`.yaml`/`.yml`) or JSON (any other suffix),
    atomically (write to a temporary file, then rename). Round-trips exactly through
    [`jaxloc.load_scenario`][] for float64 scenarios.
    """
    path = os.fspath(path)
    d = scenario_to_dict(scenario)
    if path.endswith((".yaml", ".yml")):
        text = yaml.safe_dump(d, sort_keys=False)
    else:
        text = json.dumps(d, indent=2) + "\n"
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text)
    os.replace(tmp, path)
