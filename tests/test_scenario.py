import copy
import json
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml
from jaxloc._cameras.models import OmniCamera, PinholeCamera
from jaxloc._cameras.presets import paper_ptz_camera
from jaxloc._sim.scenario import astype, Scenario
from jaxloc._sim.scenario_file import (
    load_scenario,
    save_scenario,
    scenario_from_dict,
    scenario_to_dict,
)
from jaxloc._sim.world import FlatSurface, FunctionSurface, SaddleSurface, SinusoidSurface


def _custom():
    return Scenario.paper(
        "concurrent",
        ground=SaddleSurface(radius_x=-5.5, radius_y=9.25, height=0.1),
        ceiling=SinusoidSurface(height=3.1, amplitude=0.2, period=7.0, phase=0.3),
        base=2.2,
        side=1.7,
        headings=(0.1, -0.2, 0.3),
        overhead_xy=(0.05, -0.1),
        overhead_heading=1.4,
        overhead=PinholeCamera(650.5, 651.25, 320.1, 240.2, (0.01, -0.02, 1e-4, 2e-4, 0.003)),
        ptz=paper_ptz_camera(pan=0.1, tilt=-0.05, zoom=0.2),
        omni3=OmniCamera(0.9, 180.0, 181.0, 318.0, 241.0, skew=0.1),
        move_mean=0.7,
        move_std=0.15,
        move_candidates=16,
        min_separation=0.3,
        pixel_sigma=1.5,
        noise_model="gaussian",
        odometry_sigma_rel=0.02,
        require_omni=False,
    )


def test_paper_defaults():
    s = Scenario.paper()
    assert s.strategy == "sequential" and s.rig.noise_model == "paper"
    assert isinstance(s.ground, SaddleSurface) and isinstance(s.ceiling, SinusoidSurface)
    assert float(s.ground.radius_x) == -8.0 and float(s.ground.radius_y) == 8.0
    assert float(s.ceiling.z0) == 3.5 and float(s.ceiling.period) == 10.0
    assert float(s.ceiling.amplitude) == 0.25
    assert float(s.overhead_heading) == pytest.approx(math.pi / 2)
    assert s.move_candidates == 32
    np.testing.assert_array_equal(s.rig.pixel_sigma, 2.0)
    assert float(s.move_mean) == 0.8 and float(s.move_std) == 0.2
    assert float(s.odometry_sigma_rel) == 0.01
    xy = s.formation_xy()
    np.testing.assert_allclose(xy[0, 0], -math.sqrt(1.25))
    flat = Scenario.flat_floor("concurrent")
    assert isinstance(flat.ground, FlatSurface) and float(flat.ceiling.z0) == 2.95
    assert flat.strategy == "concurrent"


@pytest.mark.parametrize("suffix", [".yaml", ".yml", ".json"])
@pytest.mark.parametrize("make", [Scenario.paper, Scenario.flat_floor, _custom])
def test_file_round_trip(tmp_path, suffix, make):
    s = make()
    path = tmp_path / f"scenario{suffix}"
    save_scenario(s, path)
    s2 = load_scenario(path)
    assert bool(eqx.tree_equal(s, s2, typematch=True))
    assert scenario_to_dict(s2) == scenario_to_dict(s)
    if suffix == ".json":
        json.loads(path.read_text())


def test_presets_and_defaults_in_files(tmp_path):
    text = """
strategy: concurrent
ground: {type: flat, height: 0}
ceiling: {type: flat, height: 3}
cameras:
  overhead: paper_overhead
  ptz: {preset: paper_ptz, pan: 0.25}
  omni2: {preset: paper_omni}
"""
    path = tmp_path / "s.yaml"
    path.write_text(text)
    s = load_scenario(path)
    assert s.strategy == "concurrent" and float(s.ceiling.z0) == 3.0
    assert float(s.rig.ptz.pan) == 0.25
    ref = Scenario.paper("concurrent", ground=FlatSurface(0.0), ceiling=FlatSurface(3.0),
                         ptz=paper_ptz_camera(pan=0.25))
    assert bool(eqx.tree_equal(s, ref))
    # An empty file is an error (issue 17 case 6); `{}` asks for the defaults.
    (tmp_path / "empty.yaml").write_text("")
    with pytest.raises(ValueError, match="empty.yaml` is empty"):
        load_scenario(tmp_path / "empty.yaml")
    (tmp_path / "defaults.yaml").write_text("{}\n")
    assert bool(eqx.tree_equal(load_scenario(tmp_path / "defaults.yaml"), Scenario.paper()))


def _set(d, path, value):
    d = copy.deepcopy(d)
    *head, last = path.split(".")
    node = d
    for k in head:
        node = node[k]
    if value is _DELETE:
        del node[last]
    else:
        node[last] = value
    return d


_DELETE = object()

BAD = [
    ("bogus", 1, r"Unknown key `bogus` in the scenario"),
    ("ground.bogus", 1.0, r"Unknown key `bogus` in `ground`"),
    ("cameras.omni2.bogus", 1.0, r"Unknown key `bogus` in `cameras.omni2`"),
    ("cameras.bogus", "paper_omni", r"Unknown key `bogus` in `cameras`"),
    ("strategy", "random", r"`strategy` must be one of .*'random'"),
    ("noise_model", "laplace", r"`noise_model` must be one of .*'laplace'"),
    ("ground.type", "torus", r"`ground.type` must be one of .*'torus'"),
    ("ground", "saddle", r"`ground` must be a mapping with a `type`"),
    ("ceiling.period", -1.0, r"`ceiling.period` must be positive; got -1.0"),
    ("ground.radius_x", 0.0, r"`ground.radius_x` must be nonzero"),
    ("ground.radius_y", "8", r"`ground.radius_y` must be a number; got '8'"),
    ("pixel_sigma", -2.0, r"`Rig\(pixel_sigma=...\)` must be non-negative \(px\); got \[-2\. "),
    ("move_std", -0.1, r"`Scenario\(move_std=...\)` must be nonnegative; got -0.1"),
    ("odometry_sigma_rel", -0.01, r"odometry_sigma_rel=...\)` must be nonnegative"),
    ("move_mean", 0.0, r"`Scenario\(move_mean=...\)` must be positive; got 0.0"),
    ("base", -2.0, r"`Scenario\(base=...\)` must be positive; got -2.0"),
    ("side", 0.9, r"`Scenario\(side=...\)` must exceed `base / 2`"),
    ("pixel_sigma", True, r"`pixel_sigma` must be a number; got True"),
    ("pixel_sigma", float("nan"), r"`pixel_sigma` must be finite; got nan"),
    ("headings", [0.0, 0.0], r"`headings` must be a list of 3 numbers; got \[0.0, 0.0\]"),
    ("overhead_xy", "0 0", r"`overhead_xy` must be a list of 2 numbers"),
    ("move_candidates", 0, r"`move_candidates` must be a positive integer; got 0"),
    ("move_candidates", 2.5, r"`move_candidates` must be a positive integer; got 2.5"),
    ("require_ptz", "yes", r"`require_ptz` must be true or false; got 'yes'"),
    ("cameras.ptz", "paper_omni", r"`cameras.ptz` must be a camera with `model: ptz` for the "
     r"`ptz` slot; got `model: omni`"),
    ("cameras.ptz", "wide_angle", r"`cameras.ptz.preset` must be one of .*'wide_angle'"),
    ("cameras.overhead.type", "fisheye", r"`cameras.overhead.type` must be one of .*fisheye"),
    ("cameras.overhead.camera_matrix", [[-600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0, 0, 1]],
     r"`cameras.overhead` is invalid: .*fx.*-600"),
    ("cameras.overhead.distortion_coefficients", [0.0, 1.0],
     r"`cameras.overhead`: `distortion_coefficients` must hold 4 \(k1, k2, p1, p2\) or 5 "
     r"\(k1, k2, p1, p2, k3\) coefficients for `distortion_model: radtan`; got \[0.0, 1.0\]"),
    ("cameras.overhead.image_width", [640], r"`cameras.overhead`: `image_width` must be a "
     r"positive integer"),
    ("cameras.ptz.zoom", 1.5, r"`cameras.ptz` is invalid: .*zoom.*1.5"),
    ("cameras.omni3", 3, r"`cameras.omni3` must be a preset name or a mapping; got 3"),
    ("moves", [[0.8, 0.0], [0.8, 0.0]], r"`Scenario\(moves=...\)` must have shape \(3, 2\) "
     r".*sequential strategy; got shape \(2, 2\)"),
    ("moves", [[0.8, 0.0], [-0.5, 0.1], [0.8, 0.0]], r"`Scenario\(moves=...\)` lengths "
     r"\(column 0\) must be positive; got \[\[0.8, 0.0\], \[-0.5, 0.1\]"),
    ("moves", [[0.8, 0.0, 1.0]] * 3, r"`moves` must be null or a list of pairs of numbers; "
     r"got \[\[0.8, 0.0, 1.0\]"),
    ("moves", "fixed", r"`moves` must be null or a list of pairs of numbers; got 'fixed'"),
    ("moves", [[0.8, float("inf")]] * 3, r"`moves` must be finite; got \[\[0.8, inf\]"),
    ("moves", [[0.8, True]] * 3, r"`moves` must be null or a list of pairs"),
    ("initial_xy", [[0.0, 0.0], [1.0, 0.0]], r"`initial_xy` must be null or a list of 3 pairs "
     r"of numbers; got \[\[0.0, 0.0\], \[1.0, 0.0\]\]"),
    ("initial_xy", [[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]], r"`Scenario\(initial_xy=...\)` must "
     r"be a triangle \(three non-collinear points\); got \[\[0.0, 0.0\], \[1.0, 0.0\]"),
    ("initial_xy", [[0.0, "a"], [1.0, 0.0], [0.0, 1.0]], r"`initial_xy` must be null or a list"),
]


@pytest.mark.parametrize("path,value,match", BAD)
def test_validation_errors(path, value, match):
    d = scenario_to_dict(Scenario.paper())
    with pytest.raises(ValueError, match=match):
        scenario_from_dict(_set(d, path, value))


def test_validation_errors_files(tmp_path):
    with pytest.raises(ValueError, match="must be a mapping"):
        scenario_from_dict([1, 2])
    (tmp_path / "bad.yaml").write_text("strategy: [unclosed\n")
    with pytest.raises(ValueError, match="not valid YAML"):
        load_scenario(tmp_path / "bad.yaml")
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_scenario(tmp_path / "bad.json")
    # yaml.safe_load refuses arbitrary Python objects.
    (tmp_path / "evil.yaml").write_text("strategy: !!python/object/apply:os.system ['true']\n")
    with pytest.raises(ValueError, match="not valid YAML"):
        load_scenario(tmp_path / "evil.yaml")
    s = Scenario.paper(ground=FunctionSurface(lambda x, y: 0.0 * x))
    with pytest.raises(ValueError, match="`ground` is a FunctionSurface"):
        save_scenario(s, tmp_path / "f.yaml")


def test_constructor_errors():
    with pytest.raises(ValueError, match=r"`Scenario\(strategy=...\)` must be one of"):
        Scenario.paper("zigzag")
    with pytest.raises(ValueError, match=r"`Scenario\(headings=...\)` must have shape \(3,\)"):
        Scenario.paper(headings=(0.0, 0.0))
    # Any camera model serves C1 (a calibrated pinhole, a PTZ); a non-camera is refused.
    assert isinstance(Scenario.paper(ptz=PinholeCamera(500.0, 500.0, 320.0, 240.0)).rig.ptz,
                      PinholeCamera)  # fmt: skip
    with pytest.raises(ValueError, match=r"`Rig\(ptz=...\)` must be a camera model"):
        Scenario.paper(ptz="wide")
    with pytest.raises(ValueError, match=r"`Scenario\(move_candidates=...\)`"):
        Scenario.paper(move_candidates=True)
    with pytest.raises(ValueError, match=r"`Rig\(pixel_sigma=...\)` must be non-negative"):
        Scenario.paper(pixel_sigma=-1.0)
    # A YAML file with only a wrong value names the field.
    with pytest.raises(ValueError, match="pixel_sigma"):
        scenario_from_dict(yaml.safe_load("pixel_sigma: -3"))


def test_astype_float32():
    s = astype(Scenario.paper(), jnp.float32)
    leaves = [x for x in jax.tree.leaves(s) if eqx.is_array(x)]
    assert leaves and all(x.dtype == jnp.float32 for x in leaves)
    assert s.strategy == "sequential" and s.rig.overhead.image_size == (640, 480)
    back = astype(s, jnp.float64)
    assert all(x.dtype == jnp.float64 for x in jax.tree.leaves(back) if eqx.is_array(x))


def test_scenario_is_a_pytree_for_vmap():
    s = Scenario.paper()
    bases = jnp.array([1.8, 2.0, 2.2])
    out = jax.vmap(lambda b: eqx.tree_at(lambda t: t.base, s, b).formation_xy())(bases)
    assert out.shape == (3, 3, 2)
    np.testing.assert_allclose(out[:, 1, 1], bases / 2)


# --------------------------------------------------------------------------------------
# Fixed moves and a general initial triangle (issue 8).

MOVES_SEQ = ((0.7, 0.1), (0.9, -0.2), (0.6, 0.3))
MOVES_CONC = ((0.7, 0.1), (0.9, -0.2), (0.6, 0.3), (0.8, 0.05))
TRIANGLE = ((-1.3, 0.1), (0.05, 1.1), (0.0, -0.9))


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
@pytest.mark.parametrize("strategy, moves", [("sequential", MOVES_SEQ),
                                             ("concurrent", MOVES_CONC)])
def test_file_round_trip_with_moves_and_initial_xy(tmp_path, suffix, strategy, moves):
    s = Scenario.paper(strategy, moves=moves, initial_xy=TRIANGLE, base=2.5, side=1.4)
    assert s.fixed_moves and s.moves.shape == (len(moves), 2)
    np.testing.assert_array_equal(s.formation_xy(), np.asarray(TRIANGLE))
    path = tmp_path / f"designed{suffix}"
    save_scenario(s, path)
    back = load_scenario(path)
    assert bool(eqx.tree_equal(s, back, typematch=True))
    np.testing.assert_array_equal(back.moves, np.asarray(moves))
    np.testing.assert_array_equal(back.initial_xy, np.asarray(TRIANGLE))
    d = scenario_to_dict(s)
    assert d["moves"] == [list(m) for m in moves]
    assert d["initial_xy"] == [list(p) for p in TRIANGLE]
    # Either one alone.
    for kwargs in ({"moves": moves}, {"initial_xy": TRIANGLE}):
        one = Scenario.paper(strategy, **kwargs)
        assert bool(eqx.tree_equal(scenario_from_dict(scenario_to_dict(one)), one))


def test_files_without_moves_are_unchanged(tmp_path):
    # Scenarios without the new fields write no new keys (a study's manifest, which holds
    # the scenario dict, still matches one written before they existed); `null` reads as
    # absent.
    d = scenario_to_dict(Scenario.paper())
    assert "moves" not in d and "initial_xy" not in d
    s = scenario_from_dict({**d, "moves": None, "initial_xy": None})
    assert s.moves is None and s.initial_xy is None and not s.fixed_moves
    assert bool(eqx.tree_equal(s, Scenario.paper()))
    (tmp_path / "m.yaml").write_text(
        "strategy: concurrent\nmoves:\n  - [0.8, 0.0]\n  - [0.8, 0.0]\n  - [0.5, 1]\n"
        "  - [1, -0.5]\ninitial_xy: [[-1, 0], [0, 1], [0, -1]]\n"
    )
    s = load_scenario(tmp_path / "m.yaml")
    assert s.moves.dtype == jnp.float64 and s.initial_xy.dtype == jnp.float64
    np.testing.assert_array_equal(s.moves[2:], [[0.5, 1.0], [1.0, -0.5]])
    np.testing.assert_array_equal(s.formation_xy(), [[-1, 0], [0, 1], [0, -1]])


def test_moves_and_initial_xy_constructor_errors():
    with pytest.raises(ValueError, match=r"`Scenario\(moves=...\)` must have shape \(4, 2\)"):
        Scenario.paper("concurrent", moves=MOVES_SEQ)
    with pytest.raises(ValueError, match=r"`Scenario\(moves=...\)` must be finite"):
        Scenario.paper(moves=((0.8, math.nan),) * 3)
    with pytest.raises(ValueError, match=r"lengths \(column 0\) must be positive; got .*0.0"):
        Scenario.paper(moves=((0.0, 0.0),) * 3)
    with pytest.raises(ValueError, match=r"`Scenario\(initial_xy=...\)` must have shape"):
        Scenario.paper(initial_xy=(0.0, 1.0))
    with pytest.raises(ValueError, match=r"`Scenario\(initial_xy=...\)` must be finite"):
        Scenario.paper(initial_xy=((0.0, 0.0), (1.0, math.inf), (0.0, 1.0)))


def test_moves_and_initial_xy_are_array_leaves():
    s = Scenario.paper(moves=MOVES_SEQ, initial_xy=TRIANGLE)
    f32 = astype(s, jnp.float32)
    assert f32.moves.dtype == jnp.float32 and f32.initial_xy.dtype == jnp.float32
    # Differentiable and vmappable like every other parameter.
    g = jax.grad(lambda m: jnp.sum(eqx.tree_at(lambda t: t.moves, s, m).moves ** 2))(s.moves)
    np.testing.assert_allclose(g, 2 * np.asarray(MOVES_SEQ))
    xs = jnp.stack([s.initial_xy, s.initial_xy + 0.1])
    out = jax.vmap(lambda x: eqx.tree_at(lambda t: t.initial_xy, s, x).formation_xy())(xs)
    np.testing.assert_allclose(out[1], np.asarray(TRIANGLE) + 0.1)
