r"""The scenario file format: reading, validating and writing [`jaxloc.Scenario`][]s.

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

import numpy as np
import yaml

from .._cameras.models import OmniCamera, PinholeCamera, PTZCamera
from .._cameras.presets import paper_omni_camera, paper_overhead_camera, paper_ptz_camera
from .._cycle.observations import STRATEGIES
from .scenario import check_surface, NOISE_MODELS, Scenario, SURFACE_FIELD_KEYS
from .world import (
    AbstractSurface,
    FlatSurface,
    FunctionSurface,
    SaddleSurface,
    SinusoidSurface,
)


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
                d[SURFACE_FIELD_KEYS.get(f.name, f.name)] = _to_builtin(getattr(surface, f.name))
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


def _camera_to_dict(camera: Any) -> dict[str, Any]:
    kind = {cls: name for name, cls in _CAMERA_TYPES.items()}[type(camera)]
    d: dict[str, Any] = {"type": kind}
    for f in dataclasses.fields(camera):
        value = getattr(camera, f.name)
        # The camera models' `distortion` (static name) and `zoom_table` (PTZ) fields are
        # not in this format yet: left out at their defaults, so existing scenarios are
        # written exactly as before, and refused otherwise rather than written wrong.
        if f.name == "distortion" and value == "radtan":
            continue
        if f.name == "zoom_table" and value is None:
            continue
        if f.name in ("distortion", "zoom_table"):
            raise ValueError(
                f"A {type(camera).__name__} with `{f.name}` other than the default has no "
                "scenario-file representation yet."
            )
        d[f.name] = _to_builtin(value)
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
