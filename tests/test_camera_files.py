"""Camera files (jaxloc._cameras.files): the one camera dict, OpenCV YAML, Kalibr
camchains read with Kalibr's rules (issue 17 cases 6, 11, 13; issue 18; issue 20 items 4
and 5): every camera model and distortion model, and the PTZ's zoom table, exactly."""

import json
import os

import cv2
import equinox as eqx
import jax.numpy as jnp
import jaxloc
import numpy as np
import pytest
import yaml
from jaxloc._cameras.files import (
    camchain_to_kalibr,
    camera_from_dict,
    camera_from_kalibr,
    camera_from_spec,
    camera_to_dict,
    camera_to_kalibr,
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
# Values with every bit of a float64 mantissa in use (1/3, 0.1, ...): exact or not at all.
RATIONAL = (1.8, 0.9, 1e-3, -5e-4, 0.05, 2.1, 1.3, 0.2 / 3)
FISHEYE = (-0.013, 0.02, -0.015, 0.004 / 3)


def _table(m: int) -> jaxloc.ZoomTable:
    rows = np.array([[-0.2, 0.05, 1e-3, -5e-4, 0.01, 0.3, 0.1, 0.02],
                     [-0.1, 0.02, 5e-4, 0.0, 0.0, 0.2, 0.05, 0.01],
                     [-0.02, 0.0, 0.0, 1e-4, 0.0, 0.1, 0.0, 0.0]])[:, :m] / 3  # fmt: skip
    return jaxloc.ZoomTable([0.0, 1 / 3, 1.0], [420.1, 700.0 / 3, 1500.7], [421.5, 702.0, 1504.0],
                            [321.0, 318.5 / 3, 316.0], [238.0, 240.5, 243.1], rows)  # fmt: skip


CAMERAS = {
    "pinhole": PINHOLE,
    "pinhole_rational": jaxloc.PinholeCamera(400.0, 402.0 / 3, 320.0, 240.0, RATIONAL),
    "pinhole_equidistant": jaxloc.PinholeCamera(280.0, 281.0, 322.0 / 3, 238.0, FISHEYE,
                                                distortion="equidistant"),  # fmt: skip
    "omni": OMNI,
    "omni_equidistant": jaxloc.OmniCamera(0.9, 180.0, 182.0 / 3, 320.0, 240.0, skew=0.5,
                                          dist=FISHEYE, distortion="equidistant"),  # fmt: skip
    "ptz": PTZ,
    "ptz_rational": jaxloc.PTZCamera(0.2, 0.1, 0.4, dist=RATIONAL),
    "ptz_equidistant": jaxloc.PTZCamera(0.2, 0.1, 0.4, dist=FISHEYE, distortion="equidistant"),
    "ptz_table": jaxloc.PTZCamera(pan=-0.4, tilt=0.25, zoom=0.7, zoom_table=_table(5)),
    "ptz_table_rational": jaxloc.PTZCamera(zoom=0.5, zoom_table=_table(8)),
    "ptz_table_equidistant": jaxloc.PTZCamera(zoom=1 / 3, zoom_table=_table(4),
                                              distortion="equidistant"),  # fmt: skip
}
FORMATS = [("json", ".json"), ("yaml", ".yaml"), ("opencv", ".yaml")]


@pytest.mark.parametrize("model", list(CAMERAS))
@pytest.mark.parametrize("fmt, suffix", FORMATS)
def test_every_model_and_distortion_round_trips_exactly(tmp_path, model, fmt, suffix):
    camera = CAMERAS[model]
    path = tmp_path / f"camera{suffix}"
    save_camera(camera, path, fmt)
    back = load_camera(path)
    # float64 bit for bit, the static distortion model and a PTZ's zoom table included
    # (an OpenCV file holds a PTZ whole, not its pinhole at the current zoom).
    assert bool(eqx.tree_equal(back, camera, typematch=True)), (back, camera)
    assert bool(eqx.tree_equal(camera_from_dict(camera_to_dict(camera)), camera,
                               typematch=True))  # fmt: skip
    assert os.listdir(tmp_path) == [path.name]  # written atomically, nothing left over


def test_equidistant_is_not_read_back_as_radtan(tmp_path):
    # On df51333 the camera dict had no distortion model: an equidistant camera was
    # written as 4 coefficients that loaded back, silently, as Brown-Conrady.
    fish = CAMERAS["pinhole_equidistant"]
    for fmt, suffix in FORMATS:
        save_camera(fish, tmp_path / f"fish{suffix}", fmt)
        back = load_camera(tmp_path / f"fish{suffix}")
        assert back.distortion == "equidistant" and back.dist.shape == (4,)
        p = np.array([[0.3, -0.2, 1.0], [1.5, 1.0, 1.0]])
        np.testing.assert_array_equal(back.project(p), fish.project(p))
    assert camera_to_dict(fish)["distortion_model"] == "equidistant"
    assert camera_to_dict(CAMERAS["pinhole_rational"])["distortion_model"] == "rational"
    assert camera_to_dict(CAMERAS["omni_equidistant"])["distortion_model"] == "equidistant"


def test_a_ptz_file_holds_its_whole_zoom_table(tmp_path):
    # On df51333 camera_to_dict(PTZCamera) dropped the zoom table without a word.
    cam = CAMERAS["ptz_table"]
    d = camera_to_dict(cam)
    assert list(d) == ["model", "image_width", "image_height", "distortion_model", "pan",
                       "tilt", "zoom", "zoom_table"]  # fmt: skip
    t = d["zoom_table"]
    assert list(t) == ["zooms", "fx", "fy", "cx", "cy", "distortion_coefficients"]
    assert t["zooms"] == [0.0, 1 / 3, 1.0] and t["fx"][1] == 700.0 / 3
    assert np.shape(t["distortion_coefficients"]) == (3, 5)
    # The OpenCV file stores the table as a FileStorage map of matrices, readable by cv2.
    save_camera(cam, tmp_path / "ptz.yaml", "opencv")
    fs = cv2.FileStorage(str(tmp_path / "ptz.yaml"), cv2.FILE_STORAGE_READ)
    np.testing.assert_array_equal(fs.getNode("zoom_table").getNode("fx").mat().ravel(), t["fx"])
    assert fs.getNode("model").string() == "ptz"
    fs.release()
    # Each camera at any zoom is the same camera after the round trip.
    back = load_camera(tmp_path / "ptz.yaml")
    for z in (0.0, 0.2, 1 / 3, 0.9):
        a = eqx.tree_at(lambda c: c.zoom, back, jnp.asarray(z))
        b = eqx.tree_at(lambda c: c.zoom, cam, jnp.asarray(z))
        assert bool(eqx.tree_equal(a.pinhole(), b.pinhole()))


def _pinhole_dict():
    return camera_to_dict(PINHOLE)


def _ptz_table_dict():
    return camera_to_dict(CAMERAS["ptz_table"])


@pytest.mark.parametrize(
    "make, change, match",
    [
        (_pinhole_dict, lambda d: d.update(distortion_model="rational",
                                           distortion_coefficients=[0.1, 0.0, 0.0, 0.0]),
         r"`distortion_coefficients` must hold 8 \(k1, k2, p1, p2, k3, k4, k5, k6\) "
         r"coefficients for `distortion_model: rational`; got \[0.1, 0.0, 0.0, 0.0\]"),
        (_pinhole_dict, lambda d: d.update(distortion_model="equidistant"),
         r"must hold 4 \(k1, k2, k3, k4\) coefficients for `distortion_model: equidistant`"),
        (_pinhole_dict, lambda d: d.update(distortion_coefficients=[0.1] * 8),
         r"must hold 4 \(k1, k2, p1, p2\) or 5 .* for `distortion_model: radtan`"),
        (_pinhole_dict, lambda d: d.update(distortion_model="kannala"),
         r"`distortion_model` must be one of radtan, rational, equidistant .*'kannala'"),
        (_pinhole_dict, lambda d: d.update(fisheye_model=1),
         r"`fisheye_model: 1` .* but is `distortion_model: radtan`"),
        (lambda: camera_to_dict(OMNI), lambda d: d.update(distortion_model="rational"),
         r"`distortion_model: rational` is not a distortion of the omni camera"),
        (_ptz_table_dict, lambda d: d["zoom_table"].update(fx=[1.0, 2.0]),
         r"`zoom_table.fx` has 2 entries but `zoom_table.zooms` has 3 zoom steps"),
        (_ptz_table_dict, lambda d: d["zoom_table"].update(zooms=[0.0, 0.6, 0.5]),
         r"`zoom_table.zooms` must be at least two zoom steps, strictly increasing in "
         r"\[0, 1\]; got \[0.0, 0.6, 0.5\]"),
        (_ptz_table_dict, lambda d: d["zoom_table"].update(zooms=[0.0, 0.5, 1.5]),
         r"strictly increasing in \[0, 1\]"),
        (_ptz_table_dict,
         lambda d: d["zoom_table"].update(distortion_coefficients=[[0.0] * 5] * 2),
         r"`zoom_table.distortion_coefficients` has 2 entries but `zoom_table.zooms` has 3"),
        (_ptz_table_dict,
         lambda d: d["zoom_table"].update(distortion_coefficients=[[0.0] * 5, [0.0] * 4,
                                                                   [0.0] * 5]),
         r"same number of coefficients at every zoom step; got rows of \[4, 5\]"),
        (_ptz_table_dict, lambda d: d.update(distortion_model="equidistant"),
         r"`zoom_table.distortion_coefficients\[0\]` must hold 4 \(k1, k2, k3, k4\)"),
        (_ptz_table_dict, lambda d: d["zoom_table"].pop("cy"), r"`zoom_table` is missing `cy`"),
        (_ptz_table_dict, lambda d: d["zoom_table"].update(fxx=[1.0]),
         r"Unknown key `fxx` in .*`zoom_table` \(did you mean `fx`\?\)"),
        (_ptz_table_dict, lambda d: d.update(hfov_wide=1.0),
         r"`hfov_wide` is not used beside a `zoom_table`"),
        (_ptz_table_dict, lambda d: d.update(distortion_coefficients=[0.0] * 5),
         r"`distortion_coefficients` is not used beside a `zoom_table`"),
    ],
)  # fmt: skip
def test_inconsistent_camera_files_name_the_key_and_the_file(tmp_path, make, change, match):
    d = make()
    change(d)
    for fmt, suffix in (("json", ".json"), ("yaml", ".yaml")):
        path = tmp_path / f"bad{suffix}"
        path.write_text(json.dumps(d) if fmt == "json" else _yaml(d))
        with pytest.raises(FileFormatError, match=match) as info:
            load_camera(path)
        assert f"`{path}`" in str(info.value) and "\n" not in str(info.value)


def test_distortion_model_defaults_and_aliases():
    d = _pinhole_dict()
    del d["distortion_model"]  # OpenCV's files: radtan, or rational by the count
    assert bool(eqx.tree_equal(camera_from_dict(d), PINHOLE))
    d["distortion_coefficients"] = list(RATIONAL)
    assert bool(eqx.tree_equal(camera_from_dict(d), CAMERAS["pinhole_rational"].__class__(
        530.5, 531.25, 320.1, 241.7, RATIONAL)))  # fmt: skip
    d["distortion_coefficients"] = [0.1, 0.2, 0.01, 0.02]  # 4: radtan with k3 = 0
    assert camera_from_dict(d).dist.tolist() == [0.1, 0.2, 0.01, 0.02, 0.0]
    d.update(distortion_model="fisheye", distortion_coefficients=list(FISHEYE))
    fish = camera_from_dict(d)
    assert fish.distortion == "equidistant" and fish.dist.tolist() == list(FISHEYE)
    assert camera_to_dict(fish)["distortion_model"] == "equidistant"  # written canonically
    # OpenCV's calibration sample marks a cv2.fisheye calibration with `fisheye_model: 1`.
    del d["distortion_model"]
    d["fisheye_model"] = 1
    assert bool(eqx.tree_equal(camera_from_dict(d), fish))
    # A model without coefficients is that model without distortion.
    for name, n in (("radtan", 5), ("rational", 8), ("equidistant", 4)):
        e = {"model": "pinhole", "image_width": 640, "image_height": 480,
             "camera_matrix": [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]],
             "distortion_model": name}  # fmt: skip
        assert camera_from_dict(e).dist.tolist() == [0.0] * n


def test_preset_overrides_in_the_constructor_form():
    # The constructor form of a preset (used for overrides that are not camera-dict
    # keys) failed on df51333 on the static `distortion` field.
    cam = camera_from_spec({"preset": "paper_ptz", "image_size": [800, 600]}, "cameras.ptz")
    assert cam.image_size == (800, 600) and cam.distortion == "radtan"
    fish = camera_from_spec({"preset": "paper_overhead", "distortion": "equidistant",
                             "dist": list(FISHEYE)}, "cameras.overhead")  # fmt: skip
    assert fish.distortion == "equidistant" and fish.dist.tolist() == list(FISHEYE)
    with pytest.raises(ValueError, match=r"`cameras.ptz.distortion` must be one of"):
        camera_from_spec({"preset": "paper_ptz", "distortion": "kb", "image_size": [8, 6]},
                         "cameras.ptz")  # fmt: skip


def test_the_camera_dict_has_opencv_keys():
    d = camera_to_dict(PINHOLE)
    assert list(d) == ["model", "image_width", "image_height", "camera_matrix",
                       "distortion_model", "distortion_coefficients"]  # fmt: skip
    assert d["distortion_model"] == "radtan"
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


def test_opencv_sample_files_load_and_fisheye_files_are_equidistant(tmp_path):
    # What OpenCV's calibration sample writes beside the camera is read and ignored;
    # its fisheye model (`fisheye_model: 1`, 4 equidistant coefficients) is read as
    # equidistant, never mistaken for Brown-Conrady.
    save_camera(PINHOLE, tmp_path / "c.yaml", "opencv",
                extra={"avg_reprojection_error": 0.3, "nframes": 13, "flags": 2})  # fmt: skip
    assert bool(eqx.tree_equal(load_camera(tmp_path / "c.yaml"), PINHOLE))
    text = (tmp_path / "c.yaml").read_text().replace("flags: 2", "fisheye_model: 1")
    (tmp_path / "c.yaml").write_text(text)
    with pytest.raises(FileFormatError, match="fisheye_model: 1.*distortion_model: radtan"):
        load_camera(tmp_path / "c.yaml")
    fish = CAMERAS["pinhole_equidistant"]
    save_camera(fish, tmp_path / "f.yaml", "opencv", extra={"fisheye_model": 1})
    text = (tmp_path / "f.yaml").read_text()
    text = "\n".join(line for line in text.splitlines() if "distortion_model" not in line)
    (tmp_path / "f.yaml").write_text(text + "\n")
    assert bool(eqx.tree_equal(load_camera(tmp_path / "f.yaml"), fish))
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
@pytest.mark.parametrize("distortion", ["radtan", "equidistant", "none"])
def test_pinhole_and_omni_with_every_kalibr_distortion_are_read(model, distortion):
    e = dict(ENTRY, camera_model=model, distortion_model=distortion)
    if model == "omni":
        e["intrinsics"] = [0.9, *ENTRY["intrinsics"]]
    if distortion == "none":
        e["distortion_coeffs"] = []
    cam = camera_from_kalibr({"cam0": e})
    assert type(cam) is {"pinhole": jaxloc.PinholeCamera, "omni": jaxloc.OmniCamera}[model]
    assert cam.distortion == ("equidistant" if distortion == "equidistant" else "radtan")
    dist = np.asarray(cam.dist)
    np.testing.assert_array_equal(dist[:4], e["distortion_coeffs"] or [0.0] * 4)
    if model == "pinhole" and distortion != "equidistant":
        assert dist.tolist()[4:] == [0.0]  # Kalibr's radtan is Brown-Conrady with k3 = 0
    assert float(cam.fx) == 500.0 and cam.image_size == (640, 480)


KALIBR_CAMERAS = {
    ("pinhole", "radtan"): jaxloc.PinholeCamera(530.5, 531.25 / 3, 320.1, 241.7,
                                                (-0.27, 0.05, 0.001, -0.0003 / 3, 0.0)),
    ("pinhole", "equidistant"): CAMERAS["pinhole_equidistant"],
    ("pinhole", "none"): jaxloc.PinholeCamera(530.5, 531.25, 320.1 / 3, 241.7),
    ("omni", "radtan"): jaxloc.OmniCamera(0.93, 190.2, 188.4 / 3, 321.7, 236.9,
                                          dist=(-0.02, 0.004, 1e-3, -5e-4 / 3)),
    ("omni", "equidistant"): jaxloc.OmniCamera(0.93 / 3, 190.2, 188.4, 321.7, 236.9, dist=FISHEYE,
                                               distortion="equidistant"),
    ("omni", "none"): jaxloc.OmniCamera(0.93, 190.2, 188.4, 321.7 / 3, 236.9),
}  # fmt: skip


@pytest.mark.parametrize("model, distortion", list(KALIBR_CAMERAS))
def test_every_kalibr_pair_is_written_and_read_back_exactly(tmp_path, model, distortion):
    camera = KALIBR_CAMERAS[(model, distortion)]
    path = tmp_path / "camchain.yaml"
    save_camchain([PINHOLE.__class__(500.0, 500.0, 320.0, 240.0), camera], path,
                  [_rigid(0.2, [0.1, 0.0, 0.0])])  # fmt: skip
    chain = yaml.safe_load(path.read_text())
    e = chain["cam1"]
    assert (e["camera_model"], e["distortion_model"]) == (model, distortion)
    if (model, distortion) != ("omni", "equidistant"):
        # Kalibr's Python reader refuses omni + equidistant ("not yet supported"), though
        # its C++ has the projection; jaxloc writes and reads it all the same.
        kalibr_reader_accepts(chain)
    back = load_camera(path, name="cam1")
    assert bool(eqx.tree_equal(back, camera, typematch=True)), (back, camera)


@pytest.mark.parametrize(
    "camera, match",
    [
        (CAMERAS["pinhole_rational"], r"`cam0` has OpenCV's rational distortion \(8 "
         r"coefficients\), which Kalibr has no model for"),
        (CAMERAS["ptz_table"],
         "`cam0` is a PTZ camera with a zoom table, which has no Kalibr form"),
        (PINHOLE, r"Kalibr's `radtan` distortion has no k3; camera `cam0` has k3 = 0.02"),
        (OMNI, r"Kalibr's `omni` model has no skew; camera `cam0` has skew = 0.05"),
    ],
)  # fmt: skip
def test_cameras_kalibr_cannot_hold_are_refused_on_write(tmp_path, camera, match):
    # On df51333 an equidistant pinhole raised an IndexError (`d[4]` of 4 coefficients);
    # a rational one and a tabled PTZ must not be written as something else.
    with pytest.raises(ValueError, match=match):
        save_camera(camera, tmp_path / "k.yaml", "kalibr")
    with pytest.raises(ValueError, match=match.replace("cam0", "cam1")):
        camchain_to_kalibr([KALIBR_CAMERAS[("pinhole", "none")], camera], [np.eye(4)])
    assert not os.listdir(tmp_path)
    # A PTZ without a table is its pinhole at the current zoom.
    assert bool(eqx.tree_equal(camera_from_kalibr(camera_to_kalibr(
        CAMERAS["ptz_equidistant"])), CAMERAS["ptz_equidistant"].pinhole()))  # fmt: skip


@pytest.mark.parametrize(
    "model, distortion, coeffs, intrinsics, named",
    [
        ("pinhole", "fov", [0.9], 4, "fov"),
        ("omni", "fov", [0.9], 5, "fov"),
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
        (lambda c: c["cam0"].update(distortion_model="equidistant", distortion_coeffs=[0.1] * 5),
         "list of 4 numbers"),
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


# --------------------------------------------------------------------------------------
# `jaxloc calibrate --model ptz`: one camera file with the whole zoom table.


@pytest.fixture
def fake_ptz_calibration(tmp_path, monkeypatch):
    """`jaxloc calibrate --model ptz` over three (empty) image folders, with
    `calibrate_ptz` replaced by one returning `CAMERAS["ptz_table_rational"]`'s table
    (tests/test_calibrate_ptz.py runs the real calibration on rendered images)."""
    import argparse

    import jaxloc._vision.calibrate as calibrate_module
    from jaxloc._cli.images import register
    from jaxloc._vision.calibrate import Calibration, ZoomCalibration

    camera = eqx.tree_at(lambda c: c.zoom, CAMERAS["ptz_table_rational"], jnp.asarray(0.0))
    t = camera.zoom_table
    zooms = [float(z) for z in np.asarray(t.zooms)]

    def fake_calibrate_ptz(sets, board, square, **kwargs):
        assert [z for z, _ in sets] == zooms and kwargs["rational"]
        steps = [
            Calibration(jaxloc.PinholeCamera(t.fx[k], t.fy[k], t.cx[k], t.cy[k], t.dist[k]),
                        0.1 + k, {"fx": 0.01}, [0.1], np.zeros((1, 7)), list(images), [])
            for k, (_, images) in enumerate(sets)
        ]  # fmt: skip
        return ZoomCalibration(camera=camera, zooms=zooms, steps=steps)

    monkeypatch.setattr(calibrate_module, "calibrate_ptz", fake_calibrate_ptz)
    argv = ["calibrate", "--model", "ptz", "--board", "9x6", "--square", "0.03", "--rational"]
    for k, z in enumerate(zooms):
        folder = tmp_path / f"zoom{k}"
        folder.mkdir()
        cv2.imwrite(str(folder / "a.png"), np.zeros((8, 8), np.uint8))
        argv += ["--zoom", repr(z), str(folder)]
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    return lambda extra: parser.parse_args(argv + extra), camera


@pytest.mark.parametrize("fmt, suffix", FORMATS)
def test_calibrate_ptz_writes_one_file_with_the_whole_table(tmp_path, fake_ptz_calibration,
                                                            fmt, suffix, capsys):  # fmt: skip
    # On df51333 `jaxloc calibrate --model ptz` wrote one pinhole file per zoom step.
    parse, camera = fake_ptz_calibration
    out = tmp_path / f"ptz{suffix}"
    args = parse(["--out", str(out), "--format", fmt, "--json", str(tmp_path / "report.json")])
    assert args.func(args) == 0
    files = sorted(p.name for p in tmp_path.iterdir() if p.is_file())
    assert files == sorted([out.name, "report.json"])
    back = load_camera(out)
    assert bool(eqx.tree_equal(back, camera, typematch=True))
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["zoom_table"] == camera_to_dict(back)["zoom_table"]
    assert [s["zoom"] for s in report["steps"]] == report["zoom_table"]["zooms"]
    assert f"wrote {out}" in capsys.readouterr().out


def test_calibrate_ptz_refuses_kalibr_before_calibrating(tmp_path, fake_ptz_calibration):
    parse, _ = fake_ptz_calibration
    args = parse(["--out", str(tmp_path / "k.yaml"), "--format", "kalibr"])
    with pytest.raises(ValueError, match="--model ptz writes one camera file .* Kalibr"):
        args.func(args)
    assert not (tmp_path / "k.yaml").exists()
