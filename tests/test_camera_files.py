"""Camera files (jaxloc._cameras.files): the one camera dict, OpenCV YAML, Kalibr
camchains read with Kalibr's rules (issue 17 cases 6, 11, 13; issue 18; issue 20 item 5)."""

import json
import os

import equinox as eqx
import jaxloc
import numpy as np
import pytest
import yaml
from jaxloc._cameras.files import (
    camchain_to_kalibr,
    camera_from_dict,
    camera_from_kalibr,
    camera_to_dict,
    load_camera,
    save_camchain,
    save_camera,
)
from jaxloc._core.files import FileFormatError


PINHOLE = jaxloc.PinholeCamera(530.5, 531.25, 320.1, 241.7, (-0.27, 0.05, 0.001, -0.0003, 0.02))
OMNI = jaxloc.OmniCamera(0.93, 190.2, 188.4, 321.7, 236.9, skew=0.05,
                         dist=(-0.02, 0.004, 1e-3, -5e-4), elevation_min=-0.3,
                         elevation_max=0.6)  # fmt: skip
PTZ = jaxloc.paper_ptz_camera(pan=0.1, tilt=-0.05, zoom=0.3)
CAMERAS = {"pinhole": PINHOLE, "omni": OMNI, "ptz": PTZ}


@pytest.mark.parametrize("model", list(CAMERAS))
@pytest.mark.parametrize("fmt, suffix", [("json", ".json"), ("yaml", ".yaml"),
                                         ("opencv", ".yaml")])  # fmt: skip
def test_every_model_round_trips_exactly(tmp_path, model, fmt, suffix):
    camera = CAMERAS[model]
    path = tmp_path / f"camera{suffix}"
    save_camera(camera, path, fmt)
    back = load_camera(path)
    # OpenCV has no PTZ: its files hold the PTZ's pinhole at the current zoom.
    want = camera.pinhole() if (fmt == "opencv" and model == "ptz") else camera
    assert bool(eqx.tree_equal(back, want, typematch=True))
    assert bool(eqx.tree_equal(camera_from_dict(camera_to_dict(camera)), camera))
    assert os.listdir(tmp_path) == [path.name]  # written atomically, nothing left over


def test_the_camera_dict_has_opencv_keys():
    d = camera_to_dict(PINHOLE)
    assert list(d) == ["model", "image_width", "image_height", "camera_matrix",
                       "distortion_coefficients"]  # fmt: skip
    assert d["camera_matrix"][0] == [530.5, 0.0, 320.1]
    assert camera_to_dict(OMNI)["camera_matrix"][0][1] == 0.05  # omni skew
    assert set(camera_to_dict(PTZ)) >= {"pan", "tilt", "zoom", "hfov_wide", "hfov_tele"}


def test_a_misspelled_key_is_an_error_not_zero_distortion(tmp_path):
    # Issue 17 case 6: `distortion_coefficient` loaded with zero distortion.
    for fmt, suffix in (("json", ".json"), ("yaml", ".yaml"), ("opencv", ".yaml")):
        d = camera_to_dict(PINHOLE)
        d["distortion_coefficient"] = d.pop("distortion_coefficients")
        path = tmp_path / f"typo{suffix}"
        if fmt == "opencv":
            save_camera(PINHOLE, path, "opencv")
            path.write_text(path.read_text().replace("distortion_coefficients",
                                                     "distortion_coefficient"))  # fmt: skip
        else:
            path.write_text(json.dumps(d) if fmt == "json" else yaml.safe_dump(d))
        with pytest.raises(FileFormatError) as info:
            load_camera(path)
        text = str(info.value)
        assert f"`{path}`" in text and "Unknown key `distortion_coefficient`" in text, text
        assert "did you mean `distortion_coefficients`" in text


def test_opencv_sample_files_load_and_fisheye_files_are_refused(tmp_path):
    # What OpenCV's calibration sample writes beside the camera is read and ignored;
    # its fisheye model (4 equidistant coefficients) is not mistaken for Brown-Conrady.
    save_camera(PINHOLE, tmp_path / "c.yaml", "opencv",
                extra={"avg_reprojection_error": 0.3, "nframes": 13, "flags": 2})  # fmt: skip
    assert bool(eqx.tree_equal(load_camera(tmp_path / "c.yaml"), PINHOLE))
    text = (tmp_path / "c.yaml").read_text().replace("flags: 2", "fisheye_model: 1")
    (tmp_path / "c.yaml").write_text(text)
    with pytest.raises(FileFormatError, match="fisheye"):
        load_camera(tmp_path / "c.yaml")
    with pytest.raises(ValueError, match="Unknown key `bogus` in `extra`"):
        save_camera(PINHOLE, tmp_path / "d.yaml", extra={"bogus": 1})


@pytest.mark.parametrize(
    "text",
    [
        "%YAML:1.0\n---\ncamera_matrix: !!opencv-matrix\n  rows: 3\n  cols: [\n",
        "%YAML:1.0\n---\n\x01\x02\x03 : : :\n",
        "%YAML:1.0\n",
    ],
)
def test_garbage_opencv_files_are_one_line(tmp_path, text):
    # Issue 17 case 13: cv2.FileStorage raised SystemError.
    path = tmp_path / "garbage.yaml"
    path.write_text(text)
    with pytest.raises(FileFormatError) as info:
        load_camera(path)
    assert f"`{path}`" in str(info.value) and "\n" not in str(info.value)


def test_os_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="absent.yaml"):
        load_camera(tmp_path / "absent.yaml")
    with pytest.raises(FileFormatError, match="is a directory"):
        load_camera(tmp_path)
    (tmp_path / "bin.json").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(FileFormatError, match="bin.json` is not UTF-8"):
        load_camera(tmp_path / "bin.json")
    with pytest.raises(FileFormatError, match="not a Kalibr camchain"):
        save_camera(PINHOLE, tmp_path / "c.json")
        load_camera(tmp_path / "c.json", name="cam1")


# --------------------------------------------------------------------------------------
# Kalibr.


def kalibr_reader_accepts(chain: dict) -> None:
    """The checks of Kalibr's `ConfigReader` (CameraChainParameters / CameraParameters)
    that a camchain written for Kalibr must pass, restated: cameras `cam0..cam<n-1>`; each
    with a string `rostopic`, a known `camera_model` and its number of intrinsics, float
    focal lengths and principal point >= 0, a known `distortion_model` with its number of
    coefficients, two integer `resolution`s; cameras after the first with a 4x4
    `T_cn_cnm1`."""
    counts = {"pinhole": 4, "omni": 5, "eucm": 6, "ds": 6}
    coeffs = {"radtan": 4, "equidistant": 4, "fov": 1, "none": 0}
    assert sorted(chain) == [f"cam{n}" for n in range(len(chain))]
    for n in range(len(chain)):
        cam = chain[f"cam{n}"]
        assert isinstance(cam["rostopic"], str)
        intr = cam["intrinsics"]
        assert len(intr) == counts[cam["camera_model"]]
        f, p = (intr[1:3], intr[3:5]) if cam["camera_model"] == "omni" else (intr[0:2], intr[2:4])
        assert all(isinstance(x, float) and x >= 0 for x in (*f, *p))
        assert len(cam["distortion_coeffs"]) == coeffs[cam["distortion_model"]]
        assert len(cam["resolution"]) == 2 and all(isinstance(x, int) for x in cam["resolution"])
        if n > 0:
            assert np.asarray(cam["T_cn_cnm1"]).shape == (4, 4)


def _yaml(obj) -> str:
    """YAML of `obj` without anchors and aliases (its lists may be shared objects)."""
    return yaml.safe_dump(json.loads(json.dumps(obj)))


def _rigid(angle, t):
    c, s = np.cos(angle), np.sin(angle)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = t
    return T


def test_written_camchains_carry_rostopic_and_baselines(tmp_path):
    pin = jaxloc.PinholeCamera(530.5, 531.25, 320.1, 241.7, (-0.27, 0.05, 0.001, -0.0003, 0.0))
    omni = jaxloc.OmniCamera(0.93, 190.2, 188.4, 321.7, 236.9, dist=(-0.02, 0.004, 1e-3, -5e-4))
    T = _rigid(0.3, [0.1, -0.05, 0.02])
    path = tmp_path / "camchain.yaml"
    save_camchain([pin, omni], path, [T])
    chain = yaml.safe_load(path.read_text())
    kalibr_reader_accepts(chain)
    assert chain["cam0"]["rostopic"] == "/cam0/image_raw" and "T_cn_cnm1" not in chain["cam0"]
    np.testing.assert_array_equal(chain["cam1"]["T_cn_cnm1"], T)
    kalibr_reader_accepts(yaml.safe_load(_single(tmp_path, pin)))
    # Each camera read back by name, exactly (Kalibr's radtan has no k3, omni no skew).
    assert bool(eqx.tree_equal(load_camera(path, name="cam0"), pin))
    assert bool(eqx.tree_equal(load_camera(path, name="cam1"), omni))
    assert bool(eqx.tree_equal(load_camera(path), pin))  # cam0 by default
    with pytest.raises(FileFormatError, match=r"has no camera `cam2`; it has \['cam0', 'cam1'\]"):
        load_camera(path, name="cam2")
    with pytest.raises(ValueError, match="one 4x4 transform per camera after the first"):
        camchain_to_kalibr([pin, omni])
    with pytest.raises(ValueError, match="rigid transform"):
        camchain_to_kalibr([pin, omni], [2 * np.eye(4)])


def _single(tmp_path, camera):
    save_camera(camera, tmp_path / "single.yaml", "kalibr")
    return (tmp_path / "single.yaml").read_text()


ENTRY = {"camera_model": "pinhole", "intrinsics": [500.0, 501.0, 320.0, 240.0],
         "distortion_model": "radtan", "distortion_coeffs": [0.1, -0.01, 0.001, 0.002],
         "resolution": [640, 480], "rostopic": "/cam0/image_raw"}  # fmt: skip


@pytest.mark.parametrize("model", ["pinhole", "omni"])
@pytest.mark.parametrize("distortion", ["radtan", "none"])
def test_pinhole_and_omni_with_radtan_or_none_are_read(model, distortion):
    e = dict(ENTRY, camera_model=model, distortion_model=distortion)
    if model == "omni":
        e["intrinsics"] = [0.9, *ENTRY["intrinsics"]]
    if distortion == "none":
        e["distortion_coeffs"] = []
    cam = camera_from_kalibr({"cam0": e})
    dist = np.asarray(cam.dist)[:4]
    np.testing.assert_array_equal(dist, e["distortion_coeffs"] or [0.0] * 4)
    assert type(cam) is {"pinhole": jaxloc.PinholeCamera, "omni": jaxloc.OmniCamera}[model]
    assert float(cam.fx) == 500.0 and cam.image_size == (640, 480)


@pytest.mark.parametrize(
    "model, distortion, coeffs, intrinsics, named",
    [
        ("pinhole", "equidistant", [0.1, 0.0, 0.0, 0.0], 4, "equidistant"),
        ("pinhole", "fov", [0.9], 4, "fov"),
        ("omni", "equidistant", [0.1, 0.0, 0.0, 0.0], 5, "equidistant"),
        ("eucm", "none", [], 6, "eucm"),
        ("ds", "none", [], 6, "ds"),
    ],
)
def test_other_kalibr_models_are_refused_by_name(tmp_path, model, distortion, coeffs,
                                                 intrinsics, named):  # fmt: skip
    e = dict(ENTRY, camera_model=model, distortion_model=distortion, distortion_coeffs=coeffs,
             intrinsics=[0.5] * (intrinsics - 4) + ENTRY["intrinsics"])  # fmt: skip
    path = tmp_path / "camchain.yaml"
    path.write_text(_yaml({"cam0": ENTRY, "cam1": dict(e, T_cn_cnm1=np.eye(4).tolist())}))
    with pytest.raises(FileFormatError) as info:
        load_camera(path, name="cam1")
    text = str(info.value)
    assert named in text and "`cam1`" in text and f"`{path}`" in text, text


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda c: c.update(cam2=c.pop("cam1")), "not a Kalibr camera name"),
        (lambda c: c["cam0"].pop("distortion_coeffs"), "missing `distortion_coeffs`"),
        (lambda c: c["cam0"].update(distortion_model="none"), "must be \\[\\] for distortion"),
        (lambda c: c["cam0"].update(distortion_coeffs=[0.1]), "list of 4 numbers"),
        (lambda c: c["cam0"].update(intrinsics=[500.0, 501.0, 320.0]), "list of 4 numbers"),
        (lambda c: c["cam0"].update(intrinsics=[500.0, 501.0, -1.0, 240.0]), "principal point"),
        (lambda c: c["cam0"].update(rostopic=5), "`rostopic` must be a string"),
        (lambda c: c["cam0"].update(resolution=[640.5, 480]), "positive integer"),
        (lambda c: c["cam1"].update(T_cn_cnm1=[[1, 0], [0, 1]]), "4x4"),
        (lambda c: c["cam1"].update(T_cn_cnm1=(2 * np.eye(4)).tolist()), "rigid transform"),
        (lambda c: c["cam0"].update(camera_model="fisheye"), "unknown `camera_model: fisheye`"),
        (lambda c: c["cam0"].update(distortion_coefficients=[0.0] * 4),
         "Unknown key `distortion_coefficients`"),
        (lambda c: c["cam0"].update(cam_overlaps=[3]), "cam_overlaps"),
    ],
)
def test_camchains_are_read_with_kalibrs_rules(tmp_path, change, match):
    chain = {"cam0": dict(ENTRY), "cam1": dict(ENTRY, T_cn_cnm1=np.eye(4).tolist())}
    change(chain)
    path = tmp_path / "camchain.yaml"
    path.write_text(_yaml(chain))
    with pytest.raises(FileFormatError, match=match) as info:
        for name in sorted(chain):  # a camera's own entry is checked when it is read
            load_camera(path, name=name)
    assert f"`{path}`" in str(info.value)
