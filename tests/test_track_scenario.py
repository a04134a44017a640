"""Multi-cycle scenarios (issue 21.1): validation, the `tracking` section of scenario files,
and the cycle scenario's formation keeping (`formation_sides`). No compilation."""

import json
import math

import equinox as eqx
import jax.numpy as jnp
import jaxloc
import pytest
import yaml


def test_defaults_and_round_trip(tmp_path):
    track = jaxloc.TrackScenario()
    assert track.strategy == "sequential" and track.keep_formation
    assert float(track.climber_odometry_sigma_rel) == 0.01
    for name in ("t.yaml", "t.json"):
        path = tmp_path / name
        jaxloc.save_track_scenario(track, path)
        back = jaxloc.load_track_scenario(path)
        assert bool(eqx.tree_equal(back, track, typematch=True))
    d = yaml.safe_load((tmp_path / "t.yaml").read_text())
    assert set(d["tracking"]) == {
        "climber_step_max", "climber_step_std", "climber_turn_std",
        "climber_odometry_sigma_rel", "climber_odometry_rotation_sigma",
        "height_prior_sigma", "tilt_prior_sigma", "keep_formation",
    }  # fmt: skip


def test_scenario_file_without_tracking_section_takes_defaults(tmp_path):
    path = tmp_path / "plain.yaml"
    jaxloc.save_scenario(jaxloc.Scenario.paper(), path)
    track = jaxloc.load_track_scenario(path)
    assert bool(eqx.tree_equal(track, jaxloc.TrackScenario(), typematch=True))


def test_one_cycle_loader_accepts_a_tracking_file(tmp_path):
    path = tmp_path / "t.yaml"
    jaxloc.save_track_scenario(jaxloc.TrackScenario(climber_step_max=0.5), path)
    scenario = jaxloc.load_scenario(path)  # `jaxloc simulate` runs one cycle of it
    assert bool(eqx.tree_equal(scenario, jaxloc.Scenario.paper(), typematch=True))
    with pytest.raises(ValueError, match="`tracking` must be a mapping; got 3"):
        jaxloc.scenario_from_dict({"tracking": 3})


@pytest.mark.parametrize(
    "section, message",
    [
        ({"climber_step_maxx": 1.0}, "Unknown key `climber_step_maxx` in `tracking`.*did you mean "
         "`climber_step_max`"),
        ({"climber_step_max": 0.0}, "`tracking.climber_step_max` must be positive; got 0.0"),
        ({"climber_turn_std": -0.1}, "`tracking.climber_turn_std` must be non-negative; got -0.1"),
        ({"height_prior_sigma": "x"}, "`tracking.height_prior_sigma` must be a finite number"),
        ({"keep_formation": 1}, "`tracking.keep_formation` must be true or false; got 1"),
    ],
)  # fmt: skip
def test_tracking_section_errors_name_the_field_and_file(tmp_path, section, message):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({"tracking": section}))
    with pytest.raises(ValueError, match=message) as info:
        jaxloc.load_track_scenario(path)
    assert str(path) in str(info.value)


def test_constructor_validation():
    with pytest.raises(ValueError, match=r"`TrackScenario\(climber_odometry_sigma_rel=...\)` "
                       "must be non-negative; got -0.01"):  # fmt: skip
        jaxloc.TrackScenario(climber_odometry_sigma_rel=-0.01)
    with pytest.raises(ValueError, match=r"`TrackScenario\(tilt_prior_sigma=...\)` must be "
                       "finite; got nan"):  # fmt: skip
        jaxloc.TrackScenario(tilt_prior_sigma=math.nan)
    with pytest.raises(ValueError, match="must be a jaxloc.Scenario"):
        jaxloc.TrackScenario(scenario=3)
    with pytest.raises(ValueError, match=r"keep_formation=...\)` must be a bool"):
        jaxloc.TrackScenario(keep_formation="yes")


def test_float32_scenario_makes_float32_tracking_fields():
    track = jaxloc.TrackScenario(jaxloc.astype(jaxloc.Scenario.paper(), jnp.float32))
    assert track.climber_step_max.dtype == jnp.float32


def test_formation_sides_validation_and_file(tmp_path):
    s = jaxloc.Scenario.paper(formation_sides=[1.5, 1.5, 2.0])
    path = tmp_path / "s.yaml"
    jaxloc.save_scenario(s, path)
    assert "formation_sides" in path.read_text()
    assert bool(eqx.tree_equal(jaxloc.load_scenario(path), s, typematch=True))
    # Without it the file is what it was before the field existed (studies' hashes).
    assert "formation_sides" not in json.dumps(jaxloc.scenario_to_dict(jaxloc.Scenario.paper()))
    with pytest.raises(ValueError, match=r"`Scenario\(formation_sides=...\)` must be finite "
                       r"positive lengths \(m\); got \[1.5, -1.0, 2.0\]"):  # fmt: skip
        jaxloc.Scenario.paper(formation_sides=[1.5, -1.0, 2.0])
    with pytest.raises(ValueError, match=r"must have shape \(3,\)"):
        jaxloc.Scenario.paper(formation_sides=[1.5, 2.0])
    with pytest.raises(ValueError, match="`formation_sides` must be a list of 3 numbers"):
        jaxloc.scenario_from_dict({"formation_sides": [1.0, 2.0]})
