r"""Formation parameters of a localization cycle, their placement in the world, and the
design constraints (DESIGN §5, §9).

A [`jaxloc.Formation`][] holds the quantities a formation designer chooses: the initial
triangle, the robots' headings, the moves of the strategy, where the climbing robot waits
on the ceiling and which way it faces, and the PTZ camera's pan, tilt and zoom. Every
field is a floating-point array leaf, so `jax.grad`/`jax.vmap` reach them, and any subset
can be frozen with `equinox` filtering (see [`jaxloc.formation_filter`][]).

Moves come in two kinds:

- **random** (`moves=None`): each move is drawn as [`jaxloc.simulate_cycle`][] draws it,
  length ~ N(`move_mean`, `scenario.move_std`), uniform direction, resampled until every
  required sighting exists.
- **fixed** (`moves` of shape `(moves, 2)`): move `m` has length `moves[m, 0]` (m) and
  direction `moves[m, 1]` (rad, in the mover's body frame, from body x towards body y,
  the same convention as the simulator's random direction): exactly
  [`jaxloc.Scenario`][]'s `moves` field.

The initial triangle is the isosceles one of `base` and `side`, or, with `initial_xy`
given, any triangle (`Scenario.initial_xy`). Every field has its counterpart in a
[`jaxloc.Scenario`][] (the PTZ setting in `scenario.rig.ptz`), so a formation is written as a
scenario file ([`jaxloc.Formation.to_scenario`][]) that `jaxloc simulate` runs unchanged.

The constraints are smooth functions `g >= 0` (feasible) of the placed formation, in
natural units, so that a penalty $\mu \sum \max(0, -g/s)^2$ can be added to any objective.
"""

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._cameras.models import PTZCamera
from .._core.numerics import safe_norm
from .._cycle.layout import move_start_step, moving_robot, num_moves, num_steps
from .._cycle.observations import CyclePoses
from .._cycle.sightings import matvec_t
from .._sim.scenario import Scenario
from .._sim.simulate import camera_points, overhead_frames
from .._sim.world import body_frame_on_surface, formation_xy


FORMATION_FIELDS = (
    "base", "side", "headings", "overhead_xy", "overhead_heading", "pan", "tilt", "zoom",
    "move_mean", "moves", "initial_xy",
)  # fmt: skip
"""Names of the fields of a [`jaxloc.Formation`][], in order."""
#: The optional fields (`None` or an array).
OPTIONAL_FIELDS = ("moves", "initial_xy")
_ARRAY_FIELDS = tuple(n for n in FORMATION_FIELDS if n not in OPTIONAL_FIELDS)


_FROM_SCENARIO: Any = object()  # default of `Formation.from_scenario(moves=...)`


def _as_float(x: ArrayLike) -> Array:
    # Strongly typed (never weak), so that a formation and its updates (`eqx.apply_updates`,
    # `.at[].add`) share one jit signature.
    x = jnp.asarray(x)
    dtype = x.dtype if jnp.issubdtype(x.dtype, jnp.inexact) else jnp.result_type(float)
    return jnp.array(x, dtype=dtype)


class Formation(eqx.Module):
    r"""Design parameters of one localization cycle (SI units: metres, radians).

    **Fields:**

    - `base`, `side`: the initial isosceles triangle (m): base C2–C3, legs C1–C2 and
      C1–C3, placed by [`jaxloc.formation_xy`][] (origin at the middle of the base, C1 at
      `-x`). Unused if `initial_xy` is given.
    - `headings`: initial headings of C1, C2, C3 (rad, from `E` +x towards +y), `(3,)`.
    - `overhead_xy`: `(x, y)` of the climbing robot on the ceiling (m), `(2,)`.
    - `overhead_heading`: its heading (rad). Its camera's tilt follows the ceiling's
      normal there.
    - `pan`, `tilt`, `zoom`: C1's PTZ camera setting (rad, rad, `[0, 1]`).
    - `move_mean`: mean length of the random moves (m); unused with fixed `moves`.
    - `moves`: `None` (random moves) or fixed moves, shape `(moves, 2)`: length (m) and
      direction in the mover's body frame (rad), in the strategy's move order
      (sequential: C2, C3, C1; concurrent: C2, C3, C2, C3).
    - `initial_xy`: `None` (the isosceles triangle of `base`, `side`) or a general initial
      triangle: `(x, y)` of C1, C2, C3 in `E` (m), shape `(3, 2)`.
    """

    base: Float[Array, ""]
    side: Float[Array, ""]
    headings: Float[Array, "3"]
    overhead_xy: Float[Array, "2"]
    overhead_heading: Float[Array, ""]
    pan: Float[Array, ""]
    tilt: Float[Array, ""]
    zoom: Float[Array, ""]
    move_mean: Float[Array, ""]
    moves: Float[Array, "moves 2"] | None
    initial_xy: Float[Array, "3 2"] | None

    def __init__(
        self,
        base: Float[ArrayLike, ""] = 2.0,
        side: Float[ArrayLike, ""] = 1.5,
        headings: Float[ArrayLike, "3"] = (0.0, 0.0, 0.0),
        overhead_xy: Float[ArrayLike, "2"] = (0.0, 0.0),
        overhead_heading: Float[ArrayLike, ""] = 0.5 * math.pi,
        pan: Float[ArrayLike, ""] = 0.0,
        tilt: Float[ArrayLike, ""] = 0.0,
        zoom: Float[ArrayLike, ""] = 0.0,
        move_mean: Float[ArrayLike, ""] = 0.8,
        moves: Float[ArrayLike, "moves 2"] | None = None,
        initial_xy: Float[ArrayLike, "3 2"] | None = None,
    ):
        """**Arguments:** the fields above; the defaults are the paper's formation with
        random moves."""
        self.base = _as_float(base)
        self.side = _as_float(side)
        self.headings = _as_float(headings)
        self.overhead_xy = _as_float(overhead_xy)
        self.overhead_heading = _as_float(overhead_heading)
        self.pan = _as_float(pan)
        self.tilt = _as_float(tilt)
        self.zoom = _as_float(zoom)
        self.move_mean = _as_float(move_mean)
        self.moves = None if moves is None else _as_float(moves)
        self.initial_xy = None if initial_xy is None else _as_float(initial_xy)

    def __check_init__(self):
        shapes = {"headings": (3,), "overhead_xy": (2,)}
        for name in _ARRAY_FIELDS:
            x = getattr(self, name)
            want = shapes.get(name, ())
            # Leading batch axes are allowed (a vmapped multi-start builds batched formations).
            if x.shape[x.ndim - len(want) :] != want:
                raise ValueError(
                    f"`Formation({name}=...)` must have shape {want}; got shape {x.shape}."
                )
        if self.moves is not None and (self.moves.ndim < 2 or self.moves.shape[-1] != 2):
            raise ValueError(
                "`Formation(moves=...)` must have shape (moves, 2) (length, direction) or "
                f"be None; got shape {self.moves.shape}."
            )
        if self.initial_xy is not None and self.initial_xy.shape[-2:] != (3, 2):
            raise ValueError(
                "`Formation(initial_xy=...)` must have shape (3, 2) (C1, C2, C3) or be None; "
                f"got shape {self.initial_xy.shape}."
            )

    @property
    def fixed_moves(self) -> bool:
        """Whether the moves are fixed (`moves` given) rather than random."""
        return self.moves is not None

    @property
    def general_triangle(self) -> bool:
        """Whether the initial triangle is `initial_xy` rather than `base`/`side`."""
        return self.initial_xy is not None

    def triangle_xy(self) -> Float[Array, "3 2"]:
        """Initial `(x, y)` of C1, C2, C3 in `E` (m), shape `(3, 2)`."""
        if self.initial_xy is not None:
            return self.initial_xy
        return formation_xy(self.base, self.side)

    @classmethod
    def from_scenario(
        cls, scenario: Scenario, moves: Any = _FROM_SCENARIO
    ) -> "Formation":
        """The formation of `scenario`: its triangle (`base`, `side`, `initial_xy`),
        headings, overhead placement, PTZ setting, mean move length and moves.

        `moves`: by default the scenario's own (`None`: random, or its fixed moves);
        `None` for random moves, or an array `(moves, 2)` of fixed moves."""
        if moves is _FROM_SCENARIO:
            moves = scenario.moves
        if moves is not None:
            moves = _as_float(moves)
            want = (num_moves(scenario.strategy), 2)
            if moves.shape != want:
                raise ValueError(
                    f"`moves` must have shape {want} for the {scenario.strategy} strategy; "
                    f"got shape {moves.shape}."
                )
        return cls(
            base=scenario.base,
            side=scenario.side,
            headings=scenario.headings,
            overhead_xy=scenario.overhead_xy,
            overhead_heading=scenario.overhead_heading,
            pan=_ptz(scenario).pan,
            tilt=_ptz(scenario).tilt,
            zoom=_ptz(scenario).zoom,
            move_mean=scenario.move_mean,
            moves=moves,
            initial_xy=scenario.initial_xy,
        )

    def apply(self, scenario: Scenario) -> Scenario:
        """`scenario` with this formation's parameters, moves (random or fixed) and
        initial triangle (traceable: usable inside `jit` and `grad`; no validation)."""
        dtype = scenario.base.dtype

        def cast(x):
            return None if x is None else jnp.asarray(x, dtype)

        scenario = eqx.tree_at(
            lambda s: (s.moves, s.initial_xy),
            scenario,
            (cast(self.moves), cast(self.initial_xy)),
            is_leaf=lambda x: x is None,
        )
        return eqx.tree_at(
            lambda s: (
                s.base, s.side, s.headings, s.overhead_xy, s.overhead_heading,
                s.rig.ptz.pan, s.rig.ptz.tilt, s.rig.ptz.zoom, s.move_mean,
            ),
            scenario,
            tuple(
                jnp.asarray(getattr(self, n), dtype)
                for n in ("base", "side", "headings", "overhead_xy", "overhead_heading",
                          "pan", "tilt", "zoom", "move_mean")
            ),
        )  # fmt: skip

    def to_scenario(self, scenario: Scenario) -> Scenario:
        """A validated [`jaxloc.Scenario`][]: `scenario` with this formation's parameters
        (fixed `moves` and a general `initial_xy` included), ready for
        [`jaxloc.save_scenario`][] and `jaxloc simulate`. Eager.

        Raises `ValueError` if a value is out of the scenario's domain (e.g. `zoom`
        outside `[0, 1]`, a non-positive move length).
        """
        _ptz(scenario)
        s = self.apply(scenario)
        # Rebuild through the constructors so that their validation runs on the new values.
        rig = eqx.tree_at(lambda r: r.ptz, s.rig, _revalidated(s.rig.ptz))
        return Scenario(
            ground=s.ground, ceiling=s.ceiling, base=s.base, side=s.side,
            headings=s.headings, overhead_xy=s.overhead_xy,
            overhead_heading=s.overhead_heading, move_mean=s.move_mean, move_std=s.move_std,
            min_separation=s.min_separation, odometry_sigma_rel=s.odometry_sigma_rel,
            strategy=s.strategy, move_candidates=s.move_candidates,
            require_overhead=s.require_overhead, require_ptz=s.require_ptz,
            require_omni=s.require_omni, initial_xy=s.initial_xy, moves=s.moves, rig=rig,
            formation_sides=s.formation_sides,
        )  # fmt: skip


def _ptz(scenario: Scenario) -> PTZCamera:
    """The scenario's C1 camera, which formation design steers: a `PTZCamera`."""
    if not isinstance(scenario.rig.ptz, PTZCamera):
        raise ValueError(
            "Formation design sets C1's pan, tilt and zoom: `scenario.rig.ptz` must be a "
            f"PTZCamera; got {type(scenario.rig.ptz).__name__}."
        )
    return scenario.rig.ptz


def _revalidated(camera):
    """`camera` rebuilt through its constructor (its checks run on the current values)."""
    fields = {f: getattr(camera, f) for f in camera.__dataclass_fields__}
    return type(camera)(**fields)


def formation_filter(formation: Formation, free: tuple[str, ...] | str = "all") -> Formation:
    """A filter spec (a [`jaxloc.Formation`][] of bools) marking the `free` fields.

    Use with `eqx.partition(formation, spec)` to split the free parameters from the
    frozen ones; `eqx.combine` puts them back.

    **Arguments:**

    - `formation`: the formation (its structure: `moves` present or not).
    - `free`: field names (see `jaxloc.FORMATION_FIELDS`), or `"all"`: every field the
      formation uses (`move_mean` for random moves, `moves` for fixed ones; `base` and
      `side`, or `initial_xy` for a general triangle).
    """
    if free == "all":
        unused = ("move_mean",) if formation.fixed_moves else ("moves",)
        unused += ("base", "side") if formation.general_triangle else ("initial_xy",)
        free = tuple(n for n in FORMATION_FIELDS if n not in unused)
    if isinstance(free, str):
        free = (free,)
    for name in free:
        if name not in FORMATION_FIELDS:
            raise ValueError(
                f"Unknown formation parameter {name!r} in `free`; expected names from "
                f"{FORMATION_FIELDS}."
            )
    if "moves" in free and not formation.fixed_moves:
        raise ValueError(
            "`free` includes 'moves' but the formation's moves are random (`moves=None`); "
            "give fixed moves (e.g. `paper_fixed_moves`) to design them."
        )
    if "initial_xy" in free and not formation.general_triangle:
        raise ValueError(
            "`free` includes 'initial_xy' but the formation's triangle is given by `base` "
            "and `side` (`initial_xy=None`); give `initial_xy` (e.g. "
            "`formation_xy(base, side)`) to design a general triangle."
        )
    spec = jax.tree.map(lambda _: False, formation)
    return eqx.tree_at(
        lambda f: tuple(getattr(f, n) for n in free),
        spec,
        tuple(jax.tree.map(lambda _: True, getattr(formation, n)) for n in free),
    )


def paper_fixed_moves(strategy: str, length: float = 0.8) -> Array:
    """A feasible starting point for designing fixed moves: every move `length` m
    straight ahead (direction 0, body x). With the paper's formation (all robots facing
    +x) the triangle then shifts by `length` in steps, every sighting staying in view.
    Shape `(moves, 2)`."""
    n = num_moves(strategy)
    return jnp.asarray(np.stack([np.full(n, length), np.zeros(n)], axis=-1))


# --------------------------------------------------------------------------------------
# Placement.


class Placement(eqx.Module):
    """Every pose of a cycle in the environment frame `E`, as matrices.

    **Fields:** `R_body` `(steps, 3, 3, 3)` and `p_body` `(steps, 3, 3)` of the ground
    robots (columns of `R` are body x, y, z in `E`; m), `R_overhead`, `p_overhead`: the
    overhead camera's optical frame `(3, 3)` and centre `(3,)` (m), `R_climber`: the
    climbing robot's body frame `(3, 3)`.
    """

    R_body: Float[Array, "steps 3 3 3"]
    p_body: Float[Array, "steps 3 3"]
    R_overhead: Float[Array, "3 3"]
    p_overhead: Float[Array, "3"]
    R_climber: Float[Array, "3 3"]

    def poses(self) -> CyclePoses:
        """The cycle's [`jaxloc.CyclePoses`][] in its world frame `W` (C1's start pose)."""
        R0, p0 = self.R_body[0, 0], self.p_body[0, 0]
        R_wb = jnp.einsum("ba,kibc->kiac", R0, self.R_body)
        p_wb = jnp.einsum("ba,kib->kia", R0, self.p_body - p0[None, None])
        steps = R_wb.shape[0]

        def se3(R, p):
            return jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.from_matrix(R), p)

        body = jax.vmap(se3)(R_wb.reshape(-1, 3, 3), p_wb.reshape(-1, 3))
        body = jaxlie.SE3(body.wxyz_xyz.reshape(steps, 3, 7))
        over = se3(R0.T @ self.R_overhead, R0.T @ (self.p_overhead - p0))
        return CyclePoses(T_world_body=body, T_world_overhead=over)


def place_fixed(formation: Formation, scenario: Scenario) -> Placement:
    """Place a formation with fixed moves in the scenario's world, the way
    [`jaxloc.simulate_cycle`][] places a random move: the mover steps `length` along
    `cos(direction) x_body + sin(direction) y_body` in its tangent plane and is dropped
    vertically onto the ground, heading unchanged."""
    if not formation.fixed_moves:
        raise ValueError("`place_fixed` needs a formation with fixed `moves`.")
    strategy = scenario.strategy
    want = (num_moves(strategy), 2)
    if formation.moves.shape != want:
        raise ValueError(
            f"`Formation.moves` must have shape {want} for the {strategy} strategy; got "
            f"shape {formation.moves.shape}."
        )
    dtype = scenario.base.dtype
    headings = formation.headings.astype(dtype)
    xy = formation.triangle_xy().astype(dtype)
    movers, starts = moving_robot(strategy), move_start_step(strategy)
    xys = [xy]
    for k in range(num_steps(strategy) - 1):
        R, _ = body_frame_on_surface(scenario.ground, xy, headings)
        new = xy
        for m in np.flatnonzero(starts == k):
            r = int(movers[m])
            length, phi = formation.moves[m, 0].astype(dtype), formation.moves[m, 1].astype(dtype)
            d = jnp.cos(phi) * R[r, :, 0] + jnp.sin(phi) * R[r, :, 1]
            new = new.at[r].set(xy[r] + length * d[:2])
        xy = new
        xys.append(xy)
    xy_all = jnp.stack(xys)
    R_b, p_b = body_frame_on_surface(
        scenario.ground, xy_all, jnp.broadcast_to(headings, xy_all.shape[:-1])
    )
    R_climber, _, R_over, t_over = overhead_frames(
        scenario, formation.overhead_xy, formation.overhead_heading, dtype
    )
    return Placement(R_b, p_b, R_over, t_over, R_climber)


def placement_from_truth(truth) -> Placement:
    """The [`jaxloc.Placement`][] of a simulated cycle's [`jaxloc.CycleTruth`][] (environment
    frame poses as matrices)."""
    T = truth.T_env_body
    shape = T.wxyz_xyz.shape[:-1]
    flat = T.wxyz_xyz.reshape(-1, 7)
    R = jax.vmap(lambda w: jaxlie.SE3(w).rotation().as_matrix())(flat).reshape(shape + (3, 3))
    return Placement(
        R_body=R,
        p_body=T.wxyz_xyz[..., 4:],
        R_overhead=truth.T_env_overhead.rotation().as_matrix(),
        p_overhead=truth.T_env_overhead.translation(),
        R_climber=truth.T_env_climber.rotation().as_matrix(),
    )


# --------------------------------------------------------------------------------------
# Constraints.


class Limits(eqx.Module):
    """Margins the design constraints require (all static Python floats).

    **Fields:**

    - `image_margin_px`: every required sighting at least this far inside its perspective
      camera's image (overhead camera, PTZ), px.
    - `elevation_margin`: every required omni sighting at least this far inside the
      elevation band, rad.
    - `separation`: extra distance beyond `scenario.min_separation` between any two
      ground robots, m.
    - `move_min`, `move_max`: bounds of the move lengths (fixed moves) or of the mean move
      length (random moves), m.
    - `min_angle`: smallest interior angle of every formation's triangle, rad (not
      near-collinear: mutual localization degenerates on a line).
    - `depth_min`: every sighted point at least this far in front of a perspective camera
      (m), a guard for the pixel margins.
    """

    image_margin_px: float = 10.0
    elevation_margin: float = math.radians(1.0)
    separation: float = 0.1
    move_min: float = 0.3
    move_max: float = 1.5
    min_angle: float = math.radians(20.0)
    depth_min: float = 0.1


#: Scale of each constraint group in the penalty (a violation of one scale unit costs as
#: much as any other group's).
CONSTRAINT_SCALES = {
    "overhead_image": 0.015,  # rad (~10 px of the overhead camera)
    "overhead_depth": 0.1,  # m
    "ptz_image": 0.02,  # rad (~7 px at the PTZ's wide end)
    "ptz_depth": 0.1,  # m
    "omni_elevation": math.radians(1.0),  # rad
    "separation": 0.1,  # m
    "move_length": 0.1,  # m
    "triangle_angle": math.radians(2.0),  # rad
    "zoom": 0.05,
    "triangle": 0.05,  # m, side - base / 2
}


def _image_margins(camera, p_cam, margin_px):
    """Angular distance (rad) of optical-frame points inside each edge of a pinhole
    camera's image, minus `margin_px` converted to an angle; `(*b, 4)`. Bounded and smooth
    everywhere (unlike pixel coordinates, which blow up near the image plane); exact in
    sign for an undistorted camera (the edges are `u = -0.5, w - 0.5`, `v = -0.5, h - 0.5`)."""
    w, h = camera.image_size
    ax = jnp.arctan2(p_cam[..., 0], p_cam[..., 2])
    ay = jnp.arctan2(p_cam[..., 1], p_cam[..., 2])
    left = jnp.arctan((camera.cx + 0.5) / camera.fx)
    right = jnp.arctan((w - 0.5 - camera.cx) / camera.fx)
    top = jnp.arctan((camera.cy + 0.5) / camera.fy)
    bottom = jnp.arctan((h - 0.5 - camera.cy) / camera.fy)
    mx, my = margin_px / camera.fx, margin_px / camera.fy  # margin_px broadcasts like ax
    return jnp.stack([ax + left - mx, right - ax - mx, ay + top - my, bottom - ay - my], -1)


def _triangle_angles(p: Float[Array, "*s 3 3"]) -> Float[Array, "*s 3"]:
    def angle(a, b, c):  # interior angle at a
        u, v = b - a, c - a
        cross = safe_norm(jnp.cross(u, v))
        return jnp.arctan2(cross, jnp.sum(u * v, axis=-1))

    a, b, c = p[..., 0, :], p[..., 1, :], p[..., 2, :]
    return jnp.stack([angle(a, b, c), angle(b, c, a), angle(c, a, b)], axis=-1)


def constraint_values(
    formation: Formation,
    scenario: Scenario,
    placement: Placement,
    limits: Limits = Limits(),
    *,
    strict_steps: bool = True,
) -> dict[str, Array]:
    r"""Smooth constraint functions of a placed formation: `g >= 0` means satisfied.

    Groups (each a flat array, natural units): `overhead_image` (rad; the angle by which
    each robot's sighting is inside each image edge, less `image_margin_px` as an angle),
    `overhead_depth` (m), `ptz_image`, `ptz_depth` (C1's PTZ sighting C2 and C3),
    `omni_elevation` (rad; C2 and C3 sighting the two others inside the band, minus
    `elevation_margin`), `separation` (m; pairwise distance minus `min_separation` and
    `separation`), `move_length` (m; fixed moves' lengths or `move_mean` within bounds),
    `triangle_angle` (rad; smallest interior angle of each formation minus `min_angle`),
    `zoom` (within `[0, 1]`), `triangle` (`side - base / 2`: the isosceles triangle
    exists; absent for a general `initial_xy` triangle).
    Sightings a scenario does not require (`require_*`) are left out.

    **Arguments:**

    - `formation`, `scenario`: the design and its world.
    - `placement`: its poses, from [`jaxloc.place_fixed`][] or
      `jaxloc._design.formation.placement_from_truth`.
    - `limits`: a [`jaxloc.Limits`][].
    - `strict_steps`: apply the margins to every step; if `False`, only to the initial
      formation, and the later (randomly resampled) steps need only be just feasible
      (margins 0; the simulator's resampling keeps them in view).
    """
    dtype = placement.p_body.dtype
    R, p = placement.R_body, placement.p_body
    steps = p.shape[0]
    # Per-step margin: full at step 0, or everywhere if strict.
    full = np.ones(steps) if strict_steps else (np.arange(steps) == 0).astype(float)
    out = {}
    rig = scenario.rig
    mutual_cam, p_cam = camera_points(scenario, R, p, placement.R_overhead, placement.p_overhead)
    if scenario.require_overhead:
        m = limits.image_margin_px * full[:, None]
        out["overhead_image"] = _image_margins(rig.overhead, p_cam, m).reshape(-1)
        out["overhead_depth"] = (p_cam[..., 2] - limits.depth_min).reshape(-1)
    if scenario.require_ptz:
        ptz = eqx.tree_at(lambda c: (c.pan, c.tilt, c.zoom), _ptz(scenario),
                          (formation.pan.astype(dtype), formation.tilt.astype(dtype),
                           formation.zoom.astype(dtype)))  # fmt: skip
        # The PTZ's base-frame points into its optical frame: R_base_optical^T p.
        R_opt = ptz.optical_rotation().as_matrix().astype(dtype)
        opt = matvec_t(R_opt, mutual_cam[:, 0, 1:])
        m = limits.image_margin_px * full[:, None]
        out["ptz_image"] = _image_margins(ptz.pinhole(), opt, m).reshape(-1)
        out["ptz_depth"] = (opt[..., 2] - limits.depth_min).reshape(-1)
    if scenario.require_omni:
        g = []
        for i, cam in ((1, rig.omni2), (2, rig.omni3)):
            others = [j for j in range(3) if j != i]
            e = cam.elevation(mutual_cam[:, i, others])
            m = limits.elevation_margin * full[:, None]
            g += [e - cam.elevation_min - m, cam.elevation_max - e - m]  # (steps, 2)
        out["omni_elevation"] = jnp.concatenate([x.reshape(-1) for x in g])
    iu = np.triu_indices(3, 1)
    d = safe_norm(p[:, iu[0]] - p[:, iu[1]])
    sep = scenario.min_separation.astype(dtype) + limits.separation * full[:, None]
    out["separation"] = (d - sep).reshape(-1)
    if formation.fixed_moves:
        length = formation.moves[:, 0].astype(dtype)
    else:
        length = formation.move_mean.astype(dtype)[None]
    out["move_length"] = jnp.concatenate([length - limits.move_min, limits.move_max - length])
    m = limits.min_angle * full[:, None]
    out["triangle_angle"] = (_triangle_angles(p) - m).reshape(-1)
    zoom = formation.zoom.astype(dtype)
    out["zoom"] = jnp.stack([zoom, 1.0 - zoom])
    if not formation.general_triangle:  # (else `triangle_angle` keeps it a triangle)
        out["triangle"] = (formation.side - 0.5 * formation.base).astype(dtype)[None] - 0.05
    return out


def constraint_penalty(values: dict[str, Array]) -> Array:
    r"""$\sum_g \sum_i \max(0, -g_i / s_g)^2$ over the groups of
    [`jaxloc.constraint_values`][], each scaled by `CONSTRAINT_SCALES`. Zero iff feasible;
    continuously differentiable."""
    total = 0.0
    for name, g in values.items():
        total = total + jnp.sum(jnp.square(jnp.minimum(g / CONSTRAINT_SCALES[name], 0.0)))
    return total


def constraint_margins(values: dict[str, Array]) -> dict[str, float]:
    """Smallest `g` of each constraint group (natural units; >= 0 means satisfied). Eager."""
    return {k: float(jnp.min(v)) for k, v in values.items()}
