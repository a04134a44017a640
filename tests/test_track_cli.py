"""`jaxloc track` (issue 21.5): the table per cycle and robot for the three methods, strict
JSON with the targets, the PNG, and one-line errors. The study's shape (4 runs of 3 cycles
in one chunk of 4) is the tracking notebook's at its test size: one compilation for both."""

import json
import os

import pytest
import yaml
from jaxloc._cli.main import main


def _strict_json(path):
    def refuse(constant):
        raise AssertionError(f"{path} holds {constant}: not strict JSON")

    with open(path) as f:
        return json.load(f, parse_constant=refuse)


@pytest.fixture
def scenario_file(tmp_path):
    path = tmp_path / "track.yaml"
    path.write_text(yaml.safe_dump({"tracking": {"climber_odometry_sigma_rel": 0.01}}))
    return str(path)


def test_track_prints_the_table_and_writes_json_and_plot(scenario_file, tmp_path, capsys):
    out_json, out_png = str(tmp_path / "t.json"), str(tmp_path / "t.png")
    code = main(["track", "--scenario", scenario_file, "--cycles", "3", "--runs", "4",
                 "--chunk-size", "4", "--json", out_json, "--plot", out_png,
                 "--no-progress"])  # fmt: skip
    assert code == 0
    text = capsys.readouterr().out
    for robot in ("C", "C1", "C2", "C3"):
        assert f"Position error of {robot} (cm)" in text
    for header in ("chaining (chained bound)", "smoother (window bound)", "one-step (own bound)"):
        assert header in text
    assert "median" in text and "RMSE" in text and "p90" in text and "bound" in text
    report = _strict_json(out_json)
    assert report["cycles"] == 3 and report["runs"] == 4
    methods = report["summary"]["methods"]
    assert set(methods) == {"chain", "smoother", "one_step"}
    for per_cycle in methods.values():
        assert len(per_cycle) == 3
        for robot in ("C", "C1", "C2", "C3"):
            stats = per_cycle[-1]["robots"][robot]
            assert {"position_m", "bound_position_rmse_m", "ratio"} <= set(stats)
    assert {"chain_worst_ratio", "smoother_worst_ratio", "smoother_vs_chain_C_last"} <= set(
        report["targets"]
    )
    with open(out_png, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    "args, message",
    [
        (["--cycles", "0"], "--cycles must be positive"),
        (["--runs", "-1"], "--runs must be positive"),
        (["--window", "0"], "--window must be positive"),
    ],
)
def test_track_rejects_bad_arguments_in_one_line(scenario_file, args, message, capsys):
    base = {"--cycles": "3", "--runs": "4"}
    for flag, value in zip(args[::2], args[1::2]):
        base[flag] = value
    argv = ["track", "--scenario", scenario_file] + [x for kv in base.items() for x in kv]
    assert main(argv) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and message in err[0], err


def test_track_names_a_bad_tracking_field_and_the_file(tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"tracking": {"climber_step_max": -1.0}}))
    assert main(["track", "--scenario", str(path), "--cycles", "2", "--runs", "2"]) == 2
    err = capsys.readouterr().err
    assert "tracking.climber_step_max" in err and os.path.basename(str(path)) in err
