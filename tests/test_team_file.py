"""Team files (jaxloc._vision.team): the one loader, cameras of a Kalibr camchain by name,
unknown keys named with the file (issue 17 cases 6, 11, 13; issue 20 item 5)."""

import json
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import jaxloc
import numpy as np
import pytest
import yaml
from jaxloc._cameras.files import save_camchain, save_camera
from jaxloc._cameras.presets import R_BODY_PTZ
from jaxloc._core.files import FileFormatError
from jaxloc._vision.localize import rig_for
from jaxloc._vision.team import load_team, save_team, Team


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
        (lambda d: d["robots"]["C1"].update(zoom=0.5),
         r"robots.C1.zoom` applies to a ptz camera file .* C1's camera is a PinholeCamera"),
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


# --------------------------------------------------------------------------------------
# C1 from a zoom-calibrated PTZ file (issue 20.4): the one file `jaxloc calibrate --model
# ptz` writes.

TABLE = jaxloc.ZoomTable(
    [0.1, 0.5, 0.8],
    [420.0, 640.0, 980.0],
    [421.0, 641.5, 982.0],
    [321.0, 318.5, 316.0],
    [238.0, 240.5, 243.0],
    [[-0.12, 0.03, 1e-3, 0.0, 0.0], [-0.06, 0.01, 0.0, 5e-4, 0.0], [-0.02, 0.0, 0.0, 0.0, 0.0]],
)


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_c1_may_be_a_zoom_calibrated_ptz_file(team_dir, suffix):
    # As `jaxloc calibrate --model ptz` writes it: pan = tilt = 0, zoom at the first step.
    save_camera(jaxloc.PTZCamera(zoom=0.1, zoom_table=TABLE), team_dir / f"ptz_table{suffix}")
    d = _team_dict(dict(CAMS, C1=f"ptz_table{suffix}"))
    d["robots"]["C1"]["zoom"] = 0.3  # the zoom the images were taken at
    team = load_team(_write(team_dir / "team.yaml", d))
    ptz = jaxloc.PTZCamera(pan=0.1, tilt=-0.05, zoom=0.3, zoom_table=TABLE)
    assert bool(eqx.tree_equal(team.cameras["C1"], ptz.pinhole(), typematch=True))
    assert (team.pan, team.tilt) == (0.1, -0.05)
    # The team's rig sees through C1 exactly what the PTZ camera on its paper mount sees.
    rig = rig_for(team)
    rng = np.random.default_rng(0)
    p_body = rng.uniform([0.5, -1.0, -0.3], [3.0, 1.0, 0.5], (50, 3))
    T_body_cam = jaxlie.SE3(jnp.asarray(rig.mounts[1]))
    uv_rig = rig.ptz.project(jax.vmap(T_body_cam.inverse().apply)(jnp.asarray(p_body)))
    uv_ptz = ptz.project(jnp.asarray(p_body @ R_BODY_PTZ))  # p_base = R_BODY_PTZ^T p_body
    np.testing.assert_allclose(uv_rig, uv_ptz, rtol=0, atol=1e-9)
    # Without `zoom`, `pan`, `tilt` in the team file, the file's own are used.
    for k in ("zoom", "pan", "tilt"):
        del d["robots"]["C1"][k]
    team = load_team(_write(team_dir / "team.yaml", d))
    assert bool(eqx.tree_equal(team.cameras["C1"], jaxloc.PTZCamera(zoom=0.1, zoom_table=TABLE)
                               .pinhole(), typematch=True))  # fmt: skip
    assert (team.pan, team.tilt) == (0.0, 0.0)


@pytest.mark.parametrize(
    "zoom, match",
    [
        (0.9, r"robots.C1.zoom` must lie within the calibrated zoom steps \[0.1, 0.8\] of C1's "
              r"zoom table \(the table does not extrapolate\); got 0.9"),
        (0.05, r"robots.C1.zoom` must lie within the calibrated zoom steps"),
        (1.5, r"robots.C1.zoom` must be a number in \[0, 1\]"),
        ("tele", r"robots.C1.zoom` must be a number in \[0, 1\]"),
    ],
)  # fmt: skip
def test_c1_zoom_outside_its_table_is_an_error(team_dir, zoom, match):
    save_camera(jaxloc.PTZCamera(zoom=0.1, zoom_table=TABLE), team_dir / "ptz_table.yaml")
    d = _team_dict(dict(CAMS, C1="ptz_table.yaml"))
    d["robots"]["C1"]["zoom"] = zoom
    path = _write(team_dir / "team.yaml", d)
    with pytest.raises(ValueError, match=match) as info:
        load_team(path)
    assert str(path) in str(info.value)


def test_a_ptz_camera_given_to_team_sets_the_head_once(team_dir):
    team = load_team(_write(team_dir / "team.yaml", _team_dict(CAMS)))
    cams = dict(team.cameras, C1=jaxloc.PTZCamera(pan=0.2, zoom=0.3, zoom_table=TABLE))
    kwargs = dict(strategy=team.strategy, markers=team.markers, odometry=team.odometry)
    t = Team(cameras=dict(cams), **kwargs)
    assert (t.pan, t.tilt) == (0.2, 0.0) and isinstance(t.cameras["C1"], jaxloc.PinholeCamera)
    assert Team(cameras=dict(cams), pan=0.2, **kwargs).pan == 0.2
    with pytest.raises(ValueError, match=r"pan and tilt are given twice and differ"):
        Team(cameras=dict(cams), pan=0.3, **kwargs)
    # A calibrated PTZ (pan = tilt = 0) takes the team's head angles.
    cams["C1"] = jaxloc.PTZCamera(zoom=0.3, zoom_table=TABLE)
    assert (Team(cameras=dict(cams), pan=0.3, tilt=0.1, **kwargs).pan) == 0.3
