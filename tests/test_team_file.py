"""Team files (jaxloc._vision.team): the one loader, cameras of a Kalibr camchain by name,
unknown keys named with the file (issue 17 cases 6, 11, 13; issue 20 item 5)."""

import json
import os

import equinox as eqx
import jaxloc
import numpy as np
import pytest
import yaml
from jaxloc._cameras.files import save_camchain, save_camera
from jaxloc._core.files import FileFormatError
from jaxloc._vision.team import load_team, save_team


OVERHEAD = jaxloc.paper_overhead_camera()
PTZ_PINHOLE = jaxloc.paper_ptz_camera().pinhole()
OMNI = jaxloc.OmniCamera(0.93, 190.2, 188.4, 321.7, 236.9, dist=(-0.02, 0.004, 1e-3, -5e-4))


def _team_dict(cameras):
    steps = [{r: f"step{k}_{r}.png" for r in ("C", "C1", "C2", "C3")} for k in range(4)]
    return {
        "strategy": "sequential",
        "robots": {
            "C": {"camera": cameras["C"]},
            "C1": {"camera": cameras["C1"], "marker": "red", "pan": 0.1, "tilt": -0.05},
            "C2": {"camera": cameras["C2"], "marker": "green", "elevation_deg": [-10, 30]},
            "C3": {"camera": cameras["C3"], "marker": {"hue": [105, 130], "sat_min": 90}},
        },
        "odometry": [0.81, 0.77, 0.92],
        "odometry_sigma_rel": 0.01,
        "pixel_sigma": 0.5,
        "steps": steps,
    }


@pytest.fixture
def team_dir(tmp_path):
    save_camera(OVERHEAD, tmp_path / "overhead.yaml")
    save_camera(PTZ_PINHOLE, tmp_path / "ptz.json")
    save_camchain([OVERHEAD, OMNI, OMNI], tmp_path / "camchain.yaml", [np.eye(4), np.eye(4)])
    return tmp_path


def _write(path, d):
    path.write_text(yaml.safe_dump(json.loads(json.dumps(d))))
    return path


def test_a_camera_of_a_camchain_is_chosen_by_name(team_dir):
    cams = {"C": "overhead.yaml", "C1": "ptz.json",
            "C2": {"file": "camchain.yaml", "name": "cam1"},
            "C3": {"file": "camchain.yaml", "name": "cam2"}}  # fmt: skip
    team = load_team(_write(team_dir / "team.yaml", _team_dict(cams)))
    assert bool(eqx.tree_equal(team.cameras["C"], OVERHEAD))
    for r in ("C2", "C3"):
        assert float(team.cameras[r].xi) == 0.93 and float(team.cameras[r].fx) == 190.2
    assert float(team.cameras["C2"].elevation_min) == pytest.approx(np.radians(-10))
    assert team.pan == 0.1 and team.steps[1]["C2"] == os.path.join(team_dir, "step1_C2.png")
    # `name` defaults to cam0 (the pinhole of this chain).
    cams["C"] = {"file": "camchain.yaml"}
    team = load_team(_write(team_dir / "t.yaml", _team_dict(cams)))
    assert bool(eqx.tree_equal(team.cameras["C"], OVERHEAD))


def test_save_and_load_round_trip(team_dir):
    cams = {"C": "overhead.yaml", "C1": "ptz.json", "C2": {"file": "camchain.yaml", "name": "cam1"},
            "C3": {"file": "camchain.yaml", "name": "cam2"}}  # fmt: skip
    team = load_team(_write(team_dir / "team.yaml", _team_dict(cams)))
    out = team_dir / "copy"
    out.mkdir()
    team.steps = [{r: os.path.join(out, os.path.basename(p)) for r, p in s.items()}
                  for s in team.steps]  # fmt: skip
    save_team(team, out / "team.yaml")
    back = load_team(out / "team.yaml")
    for r in ("C", "C1", "C2", "C3"):
        assert bool(eqx.tree_equal(back.cameras[r], team.cameras[r]))
    assert back.steps == team.steps and back.markers == team.markers
    assert sorted(os.listdir(out)) == ["camera_C.yaml", "camera_C1.yaml", "camera_C2.yaml",
                                       "camera_C3.yaml", "team.yaml"]  # fmt: skip


CAMS = {"C": "overhead.yaml", "C1": "ptz.json", "C2": {"file": "camchain.yaml", "name": "cam1"},
        "C3": {"file": "camchain.yaml", "name": "cam2"}}  # fmt: skip


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda d: d.update(colour="red"), r"Unknown key `colour` in team file"),
        (lambda d: d["robots"].update(C4={"camera": "x.yaml"}), r"Unknown key `C4`"),
        (lambda d: d["robots"]["C2"].update(colour="red"), r"Unknown key `colour` in .*robots.C2"),
        (lambda d: d["robots"]["C2"].update(camera={"file": "camchain.yaml", "nam": "cam1"}),
         r"Unknown key `nam` .*did you mean `name`"),
        (lambda d: d["robots"]["C2"].update(camera={"file": "camchain.yaml", "name": "cam9"}),
         r"robots.C2.camera`: camera file .* has no camera `cam9`"),
        (lambda d: d["robots"]["C2"].update(camera={"name": "cam1"}), r"must give the camchain"),
        (lambda d: d["robots"]["C1"].update(camera="absent.yaml"), r"absent.yaml` does not exist"),
        (lambda d: d["robots"]["C1"].update(pan="left"), r"robots.C1.pan` must be a number"),
        (lambda d: d["steps"][2].update(C=7), r"steps\[2\].C` must be an image file name"),
        (lambda d: d.update(odometry=[0.8]), r"odometry` must be 3 positive distances"),
        (lambda d: d.update(detection={"min_aera": 4}), r"Unknown key `min_aera`"),
    ],
)
def test_errors_name_the_field_and_the_file(team_dir, change, match):
    d = _team_dict(CAMS)
    change(d)
    path = _write(team_dir / "team.yaml", d)
    with pytest.raises(ValueError, match=match) as info:
        load_team(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_a_misspelled_camera_file_key_fails_the_team(team_dir):
    d = jaxloc.camera_to_dict(PTZ_PINHOLE)
    d["distortion_coefficient"] = d.pop("distortion_coefficients")
    (team_dir / "ptz.json").write_text(json.dumps(d))
    with pytest.raises(FileFormatError, match=r"robots.C1.camera`: .*Unknown key "
                       r"`distortion_coefficient`"):  # fmt: skip
        load_team(_write(team_dir / "team.yaml", _team_dict(CAMS)))


def test_unreadable_team_files_are_one_line(team_dir):
    (team_dir / "bin.yaml").write_bytes(b"\x89PNG\r\n\x1a\n\x00\xff")
    for path, match in [(team_dir / "bin.yaml", "not UTF-8"), (team_dir, "is a directory"),
                        (team_dir / "absent.yaml", "does not exist")]:  # fmt: skip
        with pytest.raises(FileFormatError, match=match) as info:
            load_team(path)
        assert f"team file `{path}`" in str(info.value)
