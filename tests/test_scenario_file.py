"""Scenario files (jaxloc._sim.scenario_file): one loader, strict keys, bounded messages,
the camera dict of camera files (issue 17 cases 6, 11, 13; issue 18)."""

import os
import time

import equinox as eqx
import pytest
import yaml
from jaxloc._cameras.files import camera_to_dict, save_camera
from jaxloc._cameras.models import OmniCamera, PinholeCamera
from jaxloc._cameras.presets import paper_ptz_camera
from jaxloc._core.files import FileFormatError
from jaxloc._sim.scenario import check_ceiling_above_ground, Scenario
from jaxloc._sim.scenario_file import (
    load_scenario,
    save_scenario,
    scenario_from_dict,
    scenario_to_dict,
)
from jaxloc._sim.world import FlatSurface, SaddleSurface


def test_an_empty_file_is_an_error_not_the_defaults(tmp_path):
    # Issue 17 case 6: an empty scenario YAML silently ran the paper's defaults.
    for text in ("", "\n", "# just a comment\n", "---\n"):
        path = tmp_path / "empty.yaml"
        path.write_text(text)
        with pytest.raises(FileFormatError, match=r"scenario file `.*empty.yaml` is empty"):
            load_scenario(path)
    path.write_text("{}\n")  # the explicit way to ask for the defaults
    assert bool(eqx.tree_equal(load_scenario(path), Scenario.paper()))


def test_a_ceiling_below_the_floor_is_rejected_with_the_fields_and_the_gap(tmp_path):
    # Issue 17 case 6: a ceiling below the floor was accepted.
    d = scenario_to_dict(Scenario.paper())
    d["ceiling"] = {"type": "flat", "height": -1.0}
    with pytest.raises(ValueError) as info:
        scenario_from_dict(d)
    text = str(info.value)
    assert "`ceiling` and `ground`" in text and "C1's initial position" in text
    assert "0.921875 m below" in text  # saddle ground at C1 (-1.118, 0): -0.078125 m
    # Above the robots but below the ground at the overhead robot's place: also refused.
    with pytest.raises(ValueError, match=r"at `overhead_xy` \(x, y\) = \(0, 6\) m it is 1.25 m"):
        Scenario.paper(ground=SaddleSurface(-8.0, 8.0), ceiling=FlatSurface(1.0),
                       overhead_xy=(0.0, 6.0))  # fmt: skip
    path = tmp_path / "low.yaml"
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(FileFormatError, match=r"low.yaml`: Invalid scenario: .*ceiling"):
        load_scenario(path)
    check_ceiling_above_ground(Scenario.paper())
    check_ceiling_above_ground(Scenario.flat_floor())


def test_unknown_keys_name_the_key_and_the_file(tmp_path):
    d = scenario_to_dict(Scenario.paper())
    cams = d["cameras"]["overhead"]
    cams["distortion_coefficient"] = cams.pop("distortion_coefficients")
    path = tmp_path / "typo.yaml"
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(FileFormatError) as info:
        load_scenario(path)
    text = str(info.value)
    assert f"`{path}`" in text and "Unknown key `distortion_coefficient`" in text
    assert "`cameras.overhead`" in text and "did you mean `distortion_coefficients`" in text


def test_messages_show_bounded_values(tmp_path):
    path = tmp_path / "huge.yaml"
    path.write_text("strategy: [" + ", ".join(["sideways"] * 5_000) + "]\n")
    t0 = time.perf_counter()
    with pytest.raises(FileFormatError) as info:
        load_scenario(path)
    assert time.perf_counter() - t0 < 1.0
    assert len(str(info.value)) < 400 and "\n" not in str(info.value)
    d = scenario_to_dict(Scenario.paper())
    d["cameras"]["omni2"]["xi"] = "x" * 100_000
    with pytest.raises(ValueError) as info:
        scenario_from_dict(d)
    assert len(str(info.value)) < 400


def test_os_and_decoding_errors_are_one_line_naming_the_file(tmp_path):
    with pytest.raises(FileFormatError, match=r"is a directory"):
        load_scenario(tmp_path)
    (tmp_path / "binary.yaml").write_bytes(b"\x89PNG\r\n\x1a\n\x00\xff")
    with pytest.raises(FileFormatError, match=r"binary.yaml` is not UTF-8"):
        load_scenario(tmp_path / "binary.yaml")
    with pytest.raises(FileNotFoundError, match="absent.json"):
        load_scenario(tmp_path / "absent.json")


def test_scenario_files_write_cameras_in_the_camera_file_format(tmp_path):
    # Issue 18: one camera dict format. A scenario's `cameras:` entries are camera dicts,
    # and a camera file's contents can be pasted into a scenario file as they are.
    s = Scenario.paper(omni3=OmniCamera(0.9, 180.0, 181.0, 318.0, 241.0, skew=0.1,
                                        dist=(0.01, -0.002, 1e-4, 2e-4)))  # fmt: skip
    d = scenario_to_dict(s)
    for slot in ("overhead", "ptz", "omni2", "omni3"):
        assert d["cameras"][slot] == camera_to_dict(getattr(s.rig, slot))
    assert d["cameras"]["ptz"]["model"] == "ptz" and "camera_matrix" in d["cameras"]["omni3"]
    save_camera(s.rig.omni3, tmp_path / "omni.yaml", "yaml")
    d["cameras"]["omni2"] = yaml.safe_load((tmp_path / "omni.yaml").read_text())
    assert bool(eqx.tree_equal(scenario_from_dict(d).rig.omni2, s.rig.omni3, typematch=True))


def test_the_old_constructor_form_and_presets_still_load(tmp_path):
    text = """
strategy: concurrent
cameras:
  overhead: {type: pinhole, fx: 650.5, fy: 651.25, cx: 320.1, cy: 240.2,
             dist: [0.01, -0.02, 0.0001, 0.0002, 0.003], image_size: [640, 480]}
  ptz: {preset: paper_ptz, pan: 0.25}
  omni2: {preset: paper_omni, fx: 190.0}
  omni3: {type: omni, xi: 0.9, fx: 180.0, fy: 181.0, cx: 318.0, cy: 241.0, skew: 0.1}
"""
    path = tmp_path / "old.yaml"
    path.write_text(text)
    s = load_scenario(path)
    assert bool(eqx.tree_equal(
        s.rig.overhead, PinholeCamera(650.5, 651.25, 320.1, 240.2, (0.01, -0.02, 1e-4, 2e-4, 0.003))
    ))  # fmt: skip
    assert bool(eqx.tree_equal(s.rig.ptz, paper_ptz_camera(pan=0.25)))
    assert float(s.rig.omni2.fx) == 190.0 and float(s.rig.omni3.skew) == 0.1
    # Written back in the camera dict format; reads back the same scenario.
    save_scenario(s, tmp_path / "new.yaml")
    new = yaml.safe_load((tmp_path / "new.yaml").read_text())
    assert new["cameras"]["omni3"]["model"] == "omni"
    assert bool(eqx.tree_equal(load_scenario(tmp_path / "new.yaml"), s, typematch=True))


def test_save_is_atomic_and_leaves_nothing_behind(tmp_path):
    path = tmp_path / "s.json"
    save_scenario(Scenario.paper(), path)
    save_scenario(Scenario.flat_floor(), path)
    assert os.listdir(tmp_path) == ["s.json"]
    assert bool(eqx.tree_equal(load_scenario(path), Scenario.flat_floor()))
