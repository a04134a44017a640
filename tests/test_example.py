"""The shipped example (issue 20 item 6): `examples/sequential_cycle/`, rendered by
`examples/make_example.py`, runs through `jaxloc localize --team` as the README shows;
and the renderer's occluders and scene objects that made it."""

import json
import os

import cv2
import jax.random as jr
import jaxloc
import numpy as np
import pytest
from jaxloc._cli.main import main
from jaxloc._vision.render import render_markers


EXAMPLE = os.path.join(os.path.dirname(__file__), "..", "examples", "sequential_cycle")
TEAM = os.path.join(EXAMPLE, "team.yaml")


def test_example_dataset_is_small_and_complete():
    # Without what `jaxloc localize` writes beside the team file (examples/.gitignore).
    files = [f for f in os.listdir(EXAMPLE)
             if not f.endswith(("_poses.json", "_formation.png"))]  # fmt: skip
    pngs = sorted(f for f in files if f.endswith(".png"))
    assert pngs == sorted(f"step{k}_{c}.png" for k in range(4) for c in ("C", "C1", "C2", "C3"))
    for f in pngs:
        img = cv2.imread(os.path.join(EXAMPLE, f))
        assert img is not None and img.shape == (240, 320, 3), f
    assert {"team.yaml", "truth.json"} <= set(files)
    size = sum(os.path.getsize(os.path.join(EXAMPLE, f)) for f in files)
    assert size < 3e6, size


def test_readme_command_on_the_example(tmp_path, capsys):
    """`jaxloc localize --team examples/sequential_cycle/team.yaml` (outputs into
    tmp_path): successful, every end-of-cycle position within 4 reported standard
    deviations of the truth on each axis, the occluded sighting reported missing, no
    sighting rejected, and the plot a PNG image."""
    out, plot = tmp_path / "poses.json", tmp_path / "formation.png"
    code = main(["localize", "--team", TEAM, "--out", str(out), "--plot", str(plot)])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "sequential cycle from" in text and "successful (refined)" in text
    assert "Missing sightings (marker not found in the image): 1\n" in text
    # The fit line: the chi-square against its limit, and the reliability figure.
    fit = next(line for line in text.splitlines() if line.startswith("Fit: chi-square "))
    assert "degrees of freedom (limit " in fit and "of its standard deviations" in fit
    assert "  step 1: C2 seeing C3 (mutual): marker not found\n" in text
    assert "Rejected sightings (least squares, none left out; --loss cauchy leaves " \
        "outliers out): none\n" in text  # fmt: skip
    d = json.loads(out.read_text())
    with open(os.path.join(EXAMPLE, "truth.json")) as f:
        truth = json.load(f)
    assert d["status"] == "successful" and d["method"] == "refined"
    assert d["missing_sightings"] == [{"kind": "mutual", "step": 1, "observer": "C2",
                                       "target": "C3", "reason": "marker not found"}]  # fmt: skip
    assert d["rejected_sightings"] == []
    checks = d["checks"]
    assert checks["chi2"] <= checks["chi2_limit"] and checks["dof"] > 0
    assert checks["worst_sighting"] <= 1.0 and checks["blunder_nees"] > 0
    for r in ("C", "C1", "C2", "C3"):
        p = d["poses"][r]
        err = np.subtract(p["position_m"], truth["end_of_cycle"][r]["position_m"])
        std = np.asarray(p["position_std_m"])
        assert np.all(std > 0) and np.all(std < 0.05), (r, std)
        assert np.all(np.abs(err) <= 4 * std), (r, err, std)
        assert f"  {r:<3} position (" in text
    with open(plot, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    img = cv2.imread(str(plot))
    assert img is not None and img.shape[0] > 300 and img.shape[1] > 300


def test_plot_path_is_checked_before_any_work(tmp_path, capsys):
    bad = tmp_path / "formation.txt"
    assert main(["localize", "--team", TEAM, "--out", str(tmp_path / "p.json"),
                 "--plot", str(bad)]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert "--plot file" in err and "formation.txt" in err
    assert not (tmp_path / "p.json").exists()


def test_occluder_and_object_in_the_rendered_truth():
    """An occluder hiding one marker entirely: `occluded` 1, not visible, and the
    detector does not find it; a half-hidden marker's centroid is that of the part left.
    A scene object is drawn and reported, not as a marker."""
    cam = jaxloc.paper_overhead_camera()
    pts = np.array([[0.0, 0.0, 3.0], [0.6, 0.0, 3.0], [-0.6, 0.3, 3.0]])
    # A square 40 cm in front of the camera, around the ray of marker 0.
    sq = 0.4 * np.array([[-0.03, -0.03, 1.0], [0.03, -0.03, 1.0], [0.03, 0.03, 1.0],
                         [-0.03, 0.03, 1.0]])  # fmt: skip
    # A strip covering the left half of marker 1 (x < 0.6 at 3 m, scaled to 1 m).
    strip = 1.0 * np.array([[0.1, -0.1, 1.0], [0.2, -0.1, 1.0], [0.2, 0.1, 1.0],
                            [0.1, 0.1, 1.0]])  # fmt: skip
    ball = {"center": [0.0, -0.5, 3.0], "radius": 0.06, "bgr": (20, 150, 235), "name": "ball"}
    info = {}
    img, truth = render_markers(
        cam, pts, key=jr.key(0), names=["a", "b", "c"], distractors=0, info=info,
        objects=[ball],
        occluders=[{"polygon": sq, "bgr": (60, 60, 60)}, {"polygon": strip, "bgr": (60, 60, 60)}],
    )  # fmt: skip
    a, b, c = truth
    assert a["occluded"] == 1.0 and not a["visible"] and a["centroid_px"] is None
    assert 0.3 < b["occluded"] < 0.7 and b["visible"]
    assert b["centroid_px"][0] > b["center_px"][0] + 1.0  # the right half is what is left
    assert c["occluded"] == 0.0 and c["visible"]
    (o,) = info["objects"]
    assert o["name"] == "ball" and o["visible"] and o["area_px"] > 20
    np.testing.assert_allclose(o["centroid_px"], cam.project(np.asarray(ball["center"])),
                               atol=1.0)  # fmt: skip
    dets = jaxloc.detect_markers(img, {"a": jaxloc.DEFAULT_MARKER_COLORS["red"]})
    assert not dets["a"].detected
    with pytest.raises(ValueError, match=r"occluders\[0\]\.polygon"):
        render_markers(cam, pts, key=jr.key(0), occluders=[{"polygon": sq[:2], "bgr": (0, 0, 0)}])
