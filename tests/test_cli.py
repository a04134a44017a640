"""The `jaxloc` command line (jaxloc._cli): studies, outputs checked before work, one-line
errors, exit codes, Ctrl-C (issue 17 cases 8, 9, 10, 12, 13, 14)."""

import glob
import json
import os
import signal
import subprocess
import sys
import time

import jaxloc
import numpy as np
import pytest
import yaml
from jaxloc._cli.main import main
from jaxloc._cli.table import format_table


# The configuration of tests/test_montecarlo.py (one compilation for both files).
N = 96
SEED = 3
METHODS = ("paper", "robust")
STUDY = ["--seed", str(SEED), "--chunk-size", "32", "--no-progress", "--methods",
         ",".join(METHODS)]  # fmt: skip


@pytest.fixture(scope="module")
def scenario():
    return jaxloc.Scenario.paper(strategy="sequential")


@pytest.fixture(scope="module")
def reference(scenario):
    return jaxloc.run_study(scenario, N, seed=SEED, chunk_size=32, methods=METHODS, progress=False)


def _lower_percentile(x, q):
    return float(np.percentile(x, q, method="lower")) if x.size else float("nan")


def _strict_json(path):
    def refuse(constant):
        raise AssertionError(f"{path} holds {constant}: not strict JSON")

    with open(path) as f:
        return json.load(f, parse_constant=refuse)


def _one_error_line(capsys) -> str:
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("jaxloc: error: ") and "Traceback" not in captured.err
    return lines[0]


# --------------------------------------------------------------------------------------
# Studies.


def test_cli_simulate_round_trips_a_scenario_file(scenario, reference, tmp_path, capsys):
    path = str(tmp_path / "scenario.yaml")
    jaxloc.save_scenario(scenario, path)
    out = str(tmp_path / "report.json")
    args = ["simulate", "--scenario", path, "--trials", str(N), *STUDY]
    plot = tmp_path / "cdf.png"
    assert main(args + ["--json", out, "--plot", str(plot)]) == 0
    text = capsys.readouterr().out
    assert "Sequential strategy" in text and "Position error (cm" in text
    assert "paper run" in text  # the paper's own scenario: its single run is shown
    assert f"wrote {out}" in text and os.path.getsize(plot) > 0
    report = _strict_json(out)
    summary = report["strategies"]["sequential"]
    expected = jaxloc.summarize(reference, METHODS)
    assert summary["methods"]["robust"]["cameras"]["C"]["position_m"] == pytest.approx(
        expected["methods"]["robust"]["cameras"]["C"]["position_m"]
    )
    streamed = str(tmp_path / "streamed.json")
    assert main(args + ["--stream", "--json", streamed]) == 0
    got = _strict_json(streamed)["strategies"]["sequential"]["methods"]["robust"]["cameras"]["C"]
    want = expected["methods"]["robust"]["cameras"]["C"]["position_m"]
    assert got["position_m"]["rmse"] == pytest.approx(want["rmse"], rel=1e-12)
    robust = METHODS.index("robust")
    values = reference["position"][reference["status"][:, robust] == 0, robust, 0]
    assert got["position_m"]["median"] == pytest.approx(_lower_percentile(values, 50), rel=0.012)
    capsys.readouterr()
    assert main(args + ["--stream", "--plot", str(tmp_path / "p.png")]) == 2
    assert "--plot" in _one_error_line(capsys)


def test_cli_table1_runs_both_studies_and_prints_them_in_order(reference, tmp_path, capsys):
    # The sequential program compiles first and its study runs while the concurrent one
    # compiles; the tables still print concurrent first, and the numbers are the studies'.
    out = str(tmp_path / "table1.json")
    assert main(["table1", "--trials", str(N), *STUDY, "--json", out]) == 0
    text = capsys.readouterr().out
    assert text.index("Concurrent strategy") < text.index("Sequential strategy")
    assert "until the last was compiled" in text
    report = _strict_json(out)
    assert list(report["strategies"]) == ["concurrent", "sequential"]
    assert report["compile_seconds"] > 0
    expected = jaxloc.summarize(reference, METHODS)["methods"]
    got = report["strategies"]["sequential"]["methods"]
    for method in METHODS:
        assert got[method]["n_ok"] == expected[method]["n_ok"]
        for camera in ("C", "C2"):
            assert got[method]["cameras"][camera]["position_m"] == pytest.approx(
                expected[method]["cameras"][camera]["position_m"]
            )
    concurrent = report["strategies"]["concurrent"]["methods"]["robust"]
    assert concurrent["n_ok"] > 0.9 * N


def test_a_study_where_every_trial_fails_prints_its_table_and_writes_json(tmp_path, capsys):
    # Issue 17 case 9: `format_table` crashed (`lo` unbound) and no --json was written;
    # case 14: --json is strict JSON (the failed statistics are null, not NaN).
    path = tmp_path / "far.yaml"
    jaxloc.save_scenario(jaxloc.Scenario.paper("sequential", overhead_xy=(30.0, 30.0)), path)
    out = tmp_path / "far.json"
    code = main(["simulate", "--scenario", str(path), "--trials", "32", *STUDY,
                 "--json", str(out), "--plot", str(tmp_path / "far.png")])  # fmt: skip
    captured = capsys.readouterr()
    assert code == 1 and "Traceback" not in captured.err
    assert "no trial of the sequential study succeeded" in captured.err
    assert "not_visible 32" in captured.out and "n/a" in captured.out
    assert "paper run" not in captured.out  # not the paper's scenario: no paper column
    report = _strict_json(out)
    summary = report["strategies"]["sequential"]
    assert summary["methods"]["robust"]["n_ok"] == 0
    assert summary["methods"]["robust"]["cameras"]["C"]["position_m"]["rmse"] is None
    assert os.path.getsize(tmp_path / "far.png") > 0


def test_format_table_with_no_successful_trial():
    # Issue 17 case 9, without a study: every method failed every trial.
    n, methods = 8, ("paper", "robust", "refined")
    failed = {
        "status": np.full((n, 3), 15, np.int32), "position": np.ones((n, 3, 4)),
        "rotation": np.ones((n, 3, 4)), "ypr": np.ones((n, 3, 4, 3)),
        "position_vector": np.ones((n, 3, 4, 3)), "crlb_position_var": np.ones((n, 4)),
        "crlb_rotation_var": np.ones((n, 4)), "crlb_position_sample": np.ones((n, 4)),
        "crlb_rotation_sample": np.ones((n, 4)), "nees": np.ones((n, 4)),
    }  # fmt: skip
    text = format_table("concurrent", jaxloc.summarize(failed, methods), methods)
    assert "not_visible 8" in text and "no successful refined trial" in text
    stream = jaxloc.StreamingSummary(methods)
    stream.update(failed)
    assert "not_visible 8" in format_table("sequential", stream.result(), methods)


# --------------------------------------------------------------------------------------
# Bad input: one line, exit code 2, before any work.


def test_cli_rejects_bad_input(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("strategy: sideways\n")
    assert main(["simulate", "--scenario", str(bad), "--trials", "4"]) == 2
    assert "sideways" in _one_error_line(capsys)
    assert main(["table1", "--trials", "0"]) == 2
    assert "--trials must be positive; got 0" in _one_error_line(capsys)
    assert main(["table1", "--chunk-size", "0"]) == 2
    assert "--chunk-size must be positive; got 0" in _one_error_line(capsys)
    assert main(["table1", "--methods", "paper,magic"]) == 2
    assert "--methods" in _one_error_line(capsys)


@pytest.mark.parametrize("seed", ["-1", str(2**32), str(2**70)])
def test_seeds_outside_the_documented_range_are_one_line(seed, capsys):
    # Issue 17 case 12: OverflowError tracebacks.
    assert main(["table1", "--seed", seed]) == 2
    assert "--seed must be an integer in [0, 4294967295]" in _one_error_line(capsys)


def _not_writable_dir(tmp_path):
    if os.geteuid() == 0:
        return "/sys"  # read-only for everyone, root included
    d = tmp_path / "readonly"
    d.mkdir()
    d.chmod(0o500)
    return str(d)


def test_output_paths_are_checked_before_the_study(tmp_path, capsys):
    # Issue 17 case 10: the study ran first and its results were lost with a traceback.
    readonly = _not_writable_dir(tmp_path)
    (tmp_path / "file").write_text("x")
    cases = [
        (["--json", str(tmp_path)], "is a directory"),
        (["--json", "/proc/x.json"], "cannot be written"),
        (["--json", os.path.join(readonly, "x.json")], "cannot be written"),
        (["--plot", os.path.join(readonly, "x.png")], "cannot be written"),
        (["--plot", str(tmp_path / "x.txt")], "must end in one of"),
        (["--out", str(tmp_path / "file")], "is a file, not a folder"),
        (["--out", "/proc/jaxloc-study"], "cannot be written"),
    ]
    for option, match in cases:
        t0 = time.perf_counter()
        assert main(["table1", "--trials", "8", "--no-progress", *option]) == 2
        assert time.perf_counter() - t0 < 5.0  # no study, no compilation
        line = _one_error_line(capsys)
        assert option[0] in line and option[1] in line and match in line, line


def test_unreadable_inputs_are_one_line_naming_the_file(tmp_path, capsys):
    # Issue 17 case 13: IsADirectoryError, UnicodeDecodeError tracebacks.
    (tmp_path / "latin1.yaml").write_bytes("strategy: séquentiel\n".encode("latin-1"))
    (tmp_path / "empty.yaml").write_text("")
    for path, match in [(tmp_path, "is a directory"), (tmp_path / "latin1.yaml", "UTF-8"),
                        (tmp_path / "empty.yaml", "is empty"),
                        (tmp_path / "absent.yaml", "does not exist")]:  # fmt: skip
        assert main(["simulate", "--scenario", str(path), "--trials", "8"]) == 2
        line = _one_error_line(capsys)
        assert f"`{path}`" in line and match in line, line


def test_a_corrupt_study_manifest_in_out_is_one_line(tmp_path, capsys):
    out = tmp_path / "study"
    (out / "sequential").mkdir(parents=True)
    (out / "sequential" / "study.json").write_bytes(b"\x00\x01 not json")
    path = tmp_path / "s.yaml"
    jaxloc.save_scenario(jaxloc.Scenario.paper("sequential"), path)
    assert main(["simulate", "--scenario", str(path), "--trials", "8", "--out", str(out)]) == 2
    assert "study.json" in _one_error_line(capsys)


def test_quiet_prints_only_the_results(scenario, tmp_path, capsys):
    path = str(tmp_path / "scenario.yaml")
    jaxloc.save_scenario(scenario, path)
    out = str(tmp_path / "report.json")
    args = ["simulate", "--scenario", path, "--trials", str(N), *STUDY, "--quiet"]
    assert main(args + ["--json", out]) == 0
    captured = capsys.readouterr()
    assert "Sequential strategy" in captured.out and "Position error (cm" in captured.out
    for chatter in ("wrote", "Total", " s including compilation"):
        assert chatter not in captured.out, chatter
    assert captured.err == "" and os.path.getsize(out) > 0
    assert main(["simulate", "--scenario", str(tmp_path / "missing.yaml"), "--quiet"]) == 2
    _one_error_line(capsys)  # errors are still one line


def _parsers():
    """Every (name, parser) of the `jaxloc` command: the main one and each subcommand's."""
    import argparse

    from jaxloc._cli.main import build_parser

    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return [("jaxloc", parser), *((f"jaxloc {n}", p) for n, p in sub.choices.items())]


def test_every_command_and_option_explains_itself():
    import argparse

    parsers = _parsers()
    assert {name for name, _ in parsers} >= {
        "jaxloc", "jaxloc table1", "jaxloc simulate", "jaxloc cameras", "jaxloc calibrate",
        "jaxloc localize", "jaxloc design",
    }  # fmt: skip
    for name, parser in parsers:
        assert parser.description and len(parser.description) > 40, name
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for choice in action._choices_actions:
                    assert choice.help, f"{name} {choice.dest}"
                continue
            flag = "/".join(action.option_strings) or action.dest
            assert action.help and action.help.strip() and action.help != argparse.SUPPRESS, (
                f"`{name} {flag}` has no help text"
            )
    helps = {n: {"/".join(a.option_strings): a.help for a in p._actions} for n, p in parsers}
    for method in jaxloc.METHODS:  # --methods lists its choices
        assert method in helps["jaxloc simulate"]["--methods"]
    assert "per strategy" not in helps["jaxloc simulate"]["--trials"]  # one scenario, one study
    assert "two studies" in helps["jaxloc table1"]["--trials"]
    for name in ("jaxloc table1", "jaxloc simulate", "jaxloc design"):
        assert "-q/--quiet" in helps[name] and "--ray" in helps[name]
        assert "a task whose worker is lost is retried" in helps[name]["--ray"]
    assert "every group of starts" in helps["jaxloc design"]["--ray"]


@pytest.mark.parametrize("command", ["simulate", "design"])
def test_ray_option_parses_alike_for_studies_and_design(command):
    # Issue 22: `jaxloc design --ray [ADDRESS]` is the studies' option (one registration).
    from jaxloc._cli.common import LOCAL_RAY
    from jaxloc._cli.main import build_parser

    parser = build_parser()
    head = [command] + (["--scenario", "s.yaml"] if command == "simulate" else [])
    assert parser.parse_args(head).ray is None
    assert parser.parse_args(head + ["--ray"]).ray == LOCAL_RAY
    assert parser.parse_args(head + ["--ray", "auto"]).ray == "auto"
    assert parser.parse_args(head + ["--ray", "ray://head:10001"]).ray == "ray://head:10001"


def test_version_comes_from_the_package_metadata(capsys):
    from importlib.metadata import version

    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"jaxloc {version('jaxloc')}"
    assert jaxloc.__version__ == version("jaxloc")
    run = subprocess.run([sys.executable, "-m", "jaxloc", "--version"], capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert run.returncode == 0 and run.stdout.strip() == f"jaxloc {version('jaxloc')}", run


def test_help_documents_the_exit_codes(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    for code in ("0 ", "1 ", "2 ", "3 ", "130 "):
        assert f"\n  {code}" in text, code
    assert "interrupted" in text


# --------------------------------------------------------------------------------------
# Ctrl-C.


def _jaxloc(args, env):
    """The `jaxloc` program in a child process, started with SIGINT at its default and
    unblocked, as a shell starts it: a child inherits an ignored disposition and a blocked
    mask (Python keeps both, and the program could not be interrupted), and this test
    process may have either from code run before it (the state found is kept in
    `_PARENT_SIGINT` for a failure's message)."""
    global _PARENT_SIGINT
    _PARENT_SIGINT = _sigint_state()
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # SIG_DFL after exec
    mask = signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    try:
        return subprocess.Popen(
            [sys.executable, "-m", "jaxloc._cli.main", *args], text=True,
            env={**env, "PYTHONUNBUFFERED": "1"}, stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )  # fmt: skip
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        signal.signal(signal.SIGINT, previous)


_PARENT_SIGINT = ""


def _sigint_state() -> str:
    """This process's SIGINT handler and whether this thread blocks it."""
    blocked = signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, set())
    return f"handler {signal.getsignal(signal.SIGINT)!r}, blocked {blocked}"


def _signal_lines(pid: int) -> str:
    """Each thread's pending, blocked, ignored and caught signal masks (Linux `/proc`)."""
    lines = []
    for task in sorted(glob.glob(f"/proc/{pid}/task/*")):
        try:
            with open(f"{task}/comm") as f:
                name = f.read().strip()
            with open(f"{task}/status") as f:
                masks = [x for x in f.read().splitlines() if x.startswith(("Sig", "ShdPnd"))]
        except OSError:
            continue
        lines.append(f"{os.path.basename(task)} {name}: {' '.join(masks)}")
    return "\n".join(lines)


def _wait_for(predicate, proc, timeout):
    t0 = time.perf_counter()
    while not predicate():
        assert proc.poll() is None, proc.communicate()
        assert time.perf_counter() - t0 < timeout, "timed out"
        time.sleep(0.1)


def _interrupt(proc):
    proc.send_signal(signal.SIGINT)
    try:
        out, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        threads = _signal_lines(proc.pid)
        proc.kill()  # and close its pipes: a neighbouring test must not see them
        out, err = proc.communicate()
        pytest.fail(
            f"no exit within 60 s of SIGINT; stderr: {err[-2000:]}\nthis process before "
            f"the start: {_PARENT_SIGINT}\nthe program's threads:\n{threads}"
        )
    assert proc.returncode == 130, (proc.returncode, out, err)
    assert "Traceback" not in err and "FATAL" not in err and "Abort" not in err, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("jaxloc: interrupted"), err
    return lines[0]


@pytest.mark.timeout(900)
def test_ctrl_c_stops_with_one_line_and_the_study_resumes(tmp_path):
    # Issue 17 case 12: a 30-line traceback during a study; during compilation the
    # interrupt was swallowed, or the process aborted in C++ (exit 134).
    out = tmp_path / "study"
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    args = ["table1", "--trials", "256", "--chunk-size", "64", "--methods", "robust",
            "--no-progress", "--out", str(out)]  # fmt: skip
    # During compilation: the programs are traced and compiled (or read from the cache)
    # for several seconds after the assumptions are printed.
    proc = _jaxloc(args, env)
    while "Assumptions" not in proc.stdout.readline():
        assert proc.poll() is None, proc.communicate()
    time.sleep(1.0)
    t0 = time.perf_counter()
    line = _interrupt(proc)
    assert time.perf_counter() - t0 < 10  # at once, not after the compilation
    assert str(out) in line and "rerun" in line
    # During the study: once the first chunk is on disk.
    proc = _jaxloc(args, env)
    _wait_for(lambda: (out / "sequential" / "chunk_000000.npz").exists(), proc, 600)
    _interrupt(proc)
    # The folder is resumable: the same command finishes, reusing the chunks on disk.
    done = subprocess.run([sys.executable, "-m", "jaxloc._cli.main", *args], env=env,
                          text=True, capture_output=True, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "warning" not in done.stderr, done.stderr
    assert "Concurrent strategy — 256 trials" in done.stdout
    assert "Sequential strategy — 256 trials" in done.stdout
    chunks = [f for f in os.listdir(out / "sequential") if f.startswith("chunk_")]
    assert sorted(chunks) == [f"chunk_{c:06d}.npz" for c in range(4)]


# --------------------------------------------------------------------------------------
# Other commands.


def test_cli_cameras(capsys):
    assert main(["cameras"]) == 0
    text = capsys.readouterr().out
    assert "52.0" in text and "85.0" in text and "15.0" in text


def test_command_line_uses_every_core_as_a_device():
    script = (
        "import jax, os; from jaxloc._cli.main import _use_every_core; n = _use_every_core(); "
        "assert n == len(os.sched_getaffinity(0)) == jax.device_count(), (n, jax.devices())"
    )
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    subprocess.run([sys.executable, "-c", script], check=True, timeout=120, env=env)
    # An explicit XLA_FLAGS device count is left alone.
    script = (
        "import jax; from jaxloc._cli.main import _use_every_core; "
        "assert _use_every_core() is None and jax.device_count() == 3"
    )
    env["XLA_FLAGS"] = "--xla_force_host_platform_device_count=3"
    subprocess.run([sys.executable, "-c", script], check=True, timeout=120, env=env)


def test_design_says_plainly_when_no_formation_is_feasible(tmp_path, capsys, monkeypatch):
    # Issue 17 case 8: an unchanged, infeasible start printed under "Optimized formation".
    # The search is replaced by its result when nothing is feasible (the real search
    # compiles for a minute; see test_design.py): every start ends with penalty 3.
    import jax.numpy as jnp
    from jaxloc._cli import design as cli_design
    from jaxloc._design import search

    def infeasible(formation, scenario, **kwargs):
        starts = kwargs["num_starts"]
        return search.DesignResult(
            formation=formation, initial=formation, objective=jnp.asarray(1e-4),
            objective_initial=jnp.asarray(1e-4), penalty=jnp.asarray(3.0),
            history=jnp.zeros((starts, 1)), final=jnp.full((starts,), 40.0),
            penalties=jnp.full((starts,), 3.0), best=jnp.asarray(0),
            steps=jnp.ones((starts,), int),
        )  # fmt: skip

    monkeypatch.setattr(search, "design_formation", infeasible)
    monkeypatch.setattr(search, "objective_value", lambda *a, **k: 1e-4)
    monkeypatch.setattr(cli_design, "_margins", lambda *a: ({"image_margin": -250.0}, 0.0))
    out, report = tmp_path / "designed.yaml", tmp_path / "report.json"
    code = main(["design", "--starts", "2", "--image-margin", "400", "--out", str(out),
                 "--json", str(report)])  # fmt: skip
    text = capsys.readouterr().out
    assert code == 1
    assert "No feasible formation found" in text and "Optimized formation:" not in text
    assert "Least infeasible formation (NOT feasible)" in text
    assert not out.exists()
    assert _strict_json(report)["feasible"] is False


@pytest.mark.slow
def test_design_with_impossible_margins_finds_nothing_feasible(tmp_path, capsys):
    # The same, with the real search: no formation keeps 1000 px inside 640x480 images.
    out = tmp_path / "designed.yaml"
    code = main(["design", "--starts", "2", "--draws", "1", "--iterations", "2",
                 "--image-margin", "1000", "--out", str(out)])  # fmt: skip
    assert code == 1 and "No feasible formation found" in capsys.readouterr().out
    assert not out.exists()


def test_localize_checks_its_files_first(tmp_path, capsys):
    bad = tmp_path / "team.yaml"
    bad.write_text(yaml.safe_dump({"strategy": "sequential"}))
    assert main(["localize", "--team", str(bad), "--out", str(tmp_path / "p.json")]) == 2
    assert "robots" in _one_error_line(capsys)
    assert main(["localize", "--team", str(bad), "--out", str(tmp_path)]) == 2
    assert "is a directory" in _one_error_line(capsys)
