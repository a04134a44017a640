r"""The scenario file format: reading, validating and writing [`jaxloc.Scenario`][]s.

**File format** (YAML or JSON, same keys as the `Scenario` fields; SI units: metres,
radians, pixels). Surfaces are nested mappings with a `type`; cameras are jaxloc's camera
dicts (`model: pinhole | ptz | omni`, the format of camera files, see
`jaxloc._cameras.files`), a preset name, or a preset with overrides
`{preset: <name>, <key>: <override>, ...}`:

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
  overhead: paper_overhead
  ptz: {preset: paper_ptz, pan: 0.0}
  omni2: paper_omni
  omni3: {model: omni, image_width: 640, image_height: 480, xi: 1.0,
          camera_matrix: [[185.0, 0.0, 319.5], [0.0, 185.0, 239.5], [0.0, 0.0, 1.0]],
          distortion_coefficients: [0.0, 0.0, 0.0, 0.0]}
move_mean: 0.8
move_std: 0.2
# moves: [[0.8, 0.0], [0.8, 0.0], [0.8, 0.0]]   # optional fixed moves: [length, direction]
move_candidates: 32
min_separation: 0.4
# formation_sides: [1.5, 1.5, 2.0]   # optional: side lengths the moves keep (m)
pixel_sigma: 2.0                # px; or one per camera [C, C1, C2, C3]
noise_model: paper              # or gaussian
odometry_sigma_rel: 0.01
require_overhead: true
require_ptz: true
require_omni: true
```

Missing keys take the defaults of [`jaxloc.Scenario`][] (the paper's simulation); in
particular without `initial_xy` the triangle is the isosceles `base`/`side` one, and
without `moves` the moves are random. `initial_xy` and `moves` may also be written as
`null`. An empty file is an error (write `{}` for the paper's scenario). Unknown keys
are errors naming the key (and, from a file, the file); the ceiling must be above the
ground at the initial robots and the overhead robot. An optional `tracking` mapping (the
multi-cycle section: the climbing robot's motion and odometry between cycles) is read and
validated by `jaxloc track` (`jaxloc.load_track_scenario`); one cycle does not use it.
Surface types: `saddle` (`radius_x`, `radius_y`, `height`), `flat` (`height`),
`sinusoid` (`height`, `amplitude`, `period`, `phase`). Camera presets: `paper_overhead`,
`paper_ptz`, `paper_omni`; a preset's overrides use camera-dict keys (`pan`, `xi`, ...)
or the constructor's (`fx`, ...). Scenario files written before the camera dict, with
cameras as `{type: pinhole, fx: ..., fy: ..., cx: ..., cy: ..., dist: [...],
image_size: [w, h]}` (the constructor's arguments), still load.
[`jaxloc.scenario_to_dict`][] always writes full mappings, so
`scenario_from_dict(scenario_to_dict(s))` equals `s` exactly (float64).
"""

import dataclasses
import math
import os
from typing import Any

import numpy as np

from .._cameras.files import camera_from_spec, camera_to_dict, model_of
from .._core.files import (
    atomic_write,
    check_keys,
    dumps_mapping,
    load_mapping,
    naming_file,
    short,
)
from .._cycle.observations import STRATEGIES
from .scenario import (
    check_surface,
    NOISE_MODELS,
    Scenario,
    SURFACE_FIELD_KEYS,
)
from .world import (
    AbstractSurface,
    FlatSurface,
    FunctionSurface,
    SaddleSurface,
    SinusoidSurface,
)


_SURFACE_TYPES = {"saddle": SaddleSurface, "flat": FlatSurface, "sinusoid": SinusoidSurface}
#: The camera model of each camera slot of a scenario.
CAMERA_SLOTS = {"overhead": "pinhole", "ptz": "ptz", "omni2": "omni", "omni3": "omni"}
_FLOAT_KEYS = {
    "base": (), "side": (), "headings": (3,), "overhead_xy": (2,), "overhead_heading": (),
    "move_mean": (), "move_std": (), "min_separation": (), "pixel_sigma": (),
    "odometry_sigma_rel": (),
}  # fmt: skip


#: Optional array keys: absent or `null` means `None`. Written only when set, so that the
#: file (and a study's manifest) of a scenario without them is what it was before they
#: existed.
_OPTIONAL_KEYS = {"initial_xy": 3, "moves": None}  # key -> required row count (None: any)
#: Optional lists of numbers, written only when set (same reason): key -> length.
_OPTIONAL_VECTORS = {"formation_sides": 3}
_STR_KEYS = {"strategy": STRATEGIES, "noise_model": NOISE_MODELS}
#: The multi-cycle section (`jaxloc._track.scenario`): a mapping that one cycle's scenario
#: does not use; `jaxloc track` reads and validates it (`jaxloc.load_track_scenario`).
TRACKING_KEY = "tracking"
_BOOL_KEYS = ("require_overhead", "require_ptz", "require_omni")
_TOP_KEYS = (
    ("ground", "ceiling", "cameras", "move_candidates")
    + tuple(_FLOAT_KEYS)
    + tuple(_OPTIONAL_KEYS)
    + tuple(_OPTIONAL_VECTORS)
    + tuple(_STR_KEYS)
    + _BOOL_KEYS
    + (TRACKING_KEY,)
)


def _is_number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _parse_float(path: str, x: Any, shape: tuple[int, ...]) -> Any:
    if shape == ():
        if not _is_number(x):
            raise ValueError(f"Scenario field `{path}` must be a number; got {short(x)}.")
        if not math.isfinite(x):
            raise ValueError(f"Scenario field `{path}` must be finite; got {short(x)}.")
        return float(x)
    if not isinstance(x, list | tuple) or len(x) != shape[0] or not all(map(_is_number, x)):
        raise ValueError(
            f"Scenario field `{path}` must be a list of {shape[0]} numbers; got {short(x)}."
        )
    if not all(math.isfinite(v) for v in x):
        raise ValueError(f"Scenario field `{path}` must be finite; got {short(x)}.")
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
            f"got {short(x)}."
        )
    if not all(math.isfinite(v) for r in x for v in r):
        raise ValueError(f"Scenario field `{path}` must be finite; got {short(x)}.")
    return [[float(v) for v in r] for r in x]


def _check_keys(path: str, d: Any, allowed) -> None:
    where = f"`{path}`" if path else "the scenario"
    if not isinstance(d, dict):
        raise ValueError(f"Scenario field {where} must be a mapping; got {short(d)}.")
    check_keys(d, allowed, where=where)


def _surface_to_dict(path: str, surface: AbstractSurface) -> dict[str, Any]:
    for name, cls in _SURFACE_TYPES.items():
        if type(surface) is cls:
            d: dict[str, Any] = {"type": name}
            for f in dataclasses.fields(surface):
                d[SURFACE_FIELD_KEYS.get(f.name, f.name)] = _to_builtin(getattr(surface, f.name))
            return d
    kind = "a FunctionSurface" if isinstance(surface, FunctionSurface) else short(surface)
    raise ValueError(
        f"Scenario field `{path}` is {kind}, which has no file representation; use a "
        f"saddle, flat or sinusoid surface to save the scenario."
    )


def _surface_from_dict(path: str, d: Any) -> AbstractSurface:
    if not isinstance(d, dict) or "type" not in d:
        raise ValueError(
            f"Scenario field `{path}` must be a mapping with a `type` "
            f"({', '.join(_SURFACE_TYPES)}); got {short(d)}."
        )
    kind = d["type"]
    if not isinstance(kind, str) or kind not in _SURFACE_TYPES:
        raise ValueError(
            f"Scenario field `{path}.type` must be one of {tuple(_SURFACE_TYPES)}; "
            f"got {short(kind)}."
        )
    cls = _SURFACE_TYPES[kind]
    keys = [SURFACE_FIELD_KEYS.get(f.name, f.name) for f in dataclasses.fields(cls)]
    _check_keys(path, d, set(keys) | {"type"})
    kwargs = {k: _parse_float(f"{path}.{k}", v, ()) for k, v in d.items() if k != "type"}
    surface = cls(**kwargs)
    check_surface(path, surface)
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


def _camera_from_entry(slot: str, entry: Any) -> Any:
    """The camera of slot `slot` from a scenario file's entry (see
    `jaxloc._cameras.files.camera_from_spec`), of the slot's model."""
    path = f"cameras.{slot}"
    camera = camera_from_spec(entry, path)
    expected, got = CAMERA_SLOTS[slot], model_of(camera)
    if got != expected:
        raise ValueError(
            f"Scenario field `{path}` must be a camera with `model: {expected}` for the "
            f"`{slot}` slot; got `model: {got}`."
        )
    return camera


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
        if k == "pixel_sigma":
            sigma = np.asarray(scenario.rig.pixel_sigma, dtype=np.float64)
            d[k] = float(sigma[0]) if np.all(sigma == sigma[0]) else sigma.tolist()
            continue
        d[k] = _to_builtin(getattr(scenario, k))
        if k == "side" and scenario.initial_xy is not None:
            d["initial_xy"] = _to_builtin(scenario.initial_xy)
        if k == "overhead_heading":
            d["cameras"] = {s: camera_to_dict(getattr(scenario.rig, s)) for s in CAMERA_SLOTS}
        if k == "move_std" and scenario.moves is not None:
            d["moves"] = _to_builtin(scenario.moves)
        if k == "min_separation" and scenario.formation_sides is not None:
            d["formation_sides"] = _to_builtin(scenario.formation_sides)
    d["move_candidates"] = int(scenario.move_candidates)
    d["noise_model"] = scenario.rig.noise_model
    for k in _BOOL_KEYS:
        d[k] = bool(getattr(scenario, k))
    return d


def _scenario_kwargs(d: dict) -> dict[str, Any]:
    """The constructor arguments of a scenario dict, each key parsed and checked."""
    kwargs: dict[str, Any] = {}
    for k in ("ground", "ceiling"):
        if k in d:
            kwargs[k] = _surface_from_dict(k, d[k])
    for k, shape in _FLOAT_KEYS.items():
        if k in d:
            if k == "pixel_sigma" and isinstance(d[k], list | tuple):
                shape = (4,)  # one per camera: C, C1, C2, C3
            kwargs[k] = _parse_float(k, d[k], shape)
    for k, rows in _OPTIONAL_KEYS.items():
        if k in d:
            kwargs[k] = _parse_rows(k, d[k], rows)
    for k, n in _OPTIONAL_VECTORS.items():
        if k in d and d[k] is not None:
            kwargs[k] = _parse_float(k, d[k], (n,))
    for k, allowed in _STR_KEYS.items():
        if k in d:
            if not isinstance(d[k], str) or d[k] not in allowed:
                raise ValueError(
                    f"Scenario field `{k}` must be one of {allowed}; got {short(d[k])}."
                )
            kwargs[k] = d[k]
    for k in _BOOL_KEYS:
        if k in d:
            if not isinstance(d[k], bool):
                raise ValueError(
                    f"Scenario field `{k}` must be true or false; got {short(d[k])}."
                )
            kwargs[k] = d[k]
    if "move_candidates" in d:
        v = d["move_candidates"]
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise ValueError(
                f"Scenario field `move_candidates` must be a positive integer; got {short(v)}."
            )
        kwargs["move_candidates"] = v
    if "cameras" in d:
        _check_keys("cameras", d["cameras"], set(CAMERA_SLOTS))
        for slot, entry in d["cameras"].items():
            kwargs[slot] = _camera_from_entry(slot, entry)
    return kwargs


def scenario_from_dict(d: Any) -> Scenario:
    """Build and validate a [`jaxloc.Scenario`][] from its file representation.

    Missing keys take the defaults (the paper's simulation). Raises `ValueError` naming
    the field path and the bad value (bounded) for an unknown key, a wrong type, a bad
    value (negative sigma, non-positive length, a ceiling not above the ground, ...) or
    an unknown strategy, noise model, surface type, camera model or preset.
    """
    _check_keys("", d, set(_TOP_KEYS))
    if TRACKING_KEY in d and not isinstance(d[TRACKING_KEY], dict | None):
        raise ValueError(
            f"Scenario field `{TRACKING_KEY}` must be a mapping; got {short(d[TRACKING_KEY])}."
        )
    kwargs = _scenario_kwargs(d)
    try:
        scenario = Scenario(**kwargs)
    except ValueError as e:
        raise ValueError(f"Invalid scenario: {e}") from e
    return scenario


def load_scenario(path: str | os.PathLike) -> Scenario:
    """Read a scenario from a YAML (`.yaml`/`.yml`) or JSON file (any other suffix); see
    [`jaxloc.scenario_from_dict`][] for validation. Bounded (size, no YAML aliases);
    every error is a `jaxloc._core.files.FileFormatError` (a `ValueError`) naming the
    file in one line.
    """
    path = os.fspath(path)
    d = load_mapping(path, what="scenario file")
    with naming_file(path, "scenario file"):
        return scenario_from_dict(d)


def save_scenario(scenario: Scenario, path: str | os.PathLike) -> None:
    """Write `scenario` to `path` as YAML (`.yaml`/`.yml`) or JSON (any other suffix),
    atomically. Round-trips exactly through [`jaxloc.load_scenario`][] for float64
    scenarios.
    """
    atomic_write(path, dumps_mapping(scenario_to_dict(scenario), path))
