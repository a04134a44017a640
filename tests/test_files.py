"""jaxloc._core.files: the one loader and writer of every jaxloc file (issue 17, cases 6,
11, 13; issue 18, one home for file I/O)."""

import json
import os
import threading
import time
import tracemalloc

import numpy as np
import pytest
from jaxloc._cameras.files import load_camera
from jaxloc._core import files
from jaxloc._core.files import (
    atomic_write,
    check_keys,
    check_output_dir,
    check_output_file,
    dumps_json,
    FileFormatError,
    load_mapping,
    MissingFileError,
    short,
)
from jaxloc._sim.scenario_file import load_scenario
from jaxloc._vision.team import load_team


def alias_bomb(field: str, levels: int = 9, width: int = 9) -> str:
    """A 'billion laughs' YAML file whose only key is `field`: its value, a few hundred
    bytes of text, holds `width**(levels - 1)` strings."""
    nodes = ['&a0 ["lol"]']
    for k in range(1, levels):
        nodes.append(f"&a{k} [" + ", ".join([f"*a{k - 1}"] * width) + "]")
    return f"{field}: [{', '.join(nodes)}]\n"


def _one_line(e: BaseException) -> str:
    text = str(e)
    assert "\n" not in text, text
    return text


# --------------------------------------------------------------------------------------
# Bounded loading.


@pytest.mark.parametrize(
    "loader, name, field",
    [(load_scenario, "scenario.yaml", "strategy"), (load_camera, "camera.yaml", "model"),
     (load_team, "team.yaml", "robots")],
)
def test_alias_bomb_fails_fast_with_small_memory(tmp_path, loader, name, field):
    # Issue 17 case 11: ~70 s and several GB before a MemoryError, because the message
    # formatted the value with repr. This bomb is 9**8 = 43 million strings: the old
    # code took minutes; now it fails at the first alias.
    path = tmp_path / name
    path.write_text(alias_bomb(field))
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(ValueError) as info:
            loader(path)
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert time.perf_counter() - t0 < 1.0
    assert peak < 20e6, peak
    assert str(path) in _one_line(info.value) and "alias" in str(info.value)


def test_every_read_error_is_one_line_naming_the_file(tmp_path):
    cases = {}
    cases["does not exist"] = tmp_path / "absent.yaml"
    cases["is a directory"] = tmp_path
    (tmp_path / "latin1.yaml").write_bytes("strategy: séquentiel\n".encode("latin-1"))
    cases["not UTF-8"] = tmp_path / "latin1.yaml"
    (tmp_path / "big.yaml").write_bytes(b"#" * (files.MAX_FILE_BYTES + 1))
    cases["larger than"] = tmp_path / "big.yaml"
    (tmp_path / "bad.json").write_text('{"strategy": "sequential",')
    cases["not valid JSON"] = tmp_path / "bad.json"
    (tmp_path / "bad.yaml").write_text("strategy: [unclosed\n")
    cases["not valid YAML"] = tmp_path / "bad.yaml"
    (tmp_path / "empty.yaml").write_text("# nothing\n")
    cases["is empty"] = tmp_path / "empty.yaml"
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    cases["must hold a mapping"] = tmp_path / "list.yaml"
    (tmp_path / "dup.yaml").write_text("base: 2.0\nbase: 3.0\n")
    cases["duplicate key"] = tmp_path / "dup.yaml"
    (tmp_path / "dup.json").write_text('{"base": 2.0, "base": 3.0}')
    cases["duplicate key "] = tmp_path / "dup.json"
    (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    cases["nested too deeply"] = tmp_path / "deep.json"
    (tmp_path / "digits.yaml").write_text("base: " + "1" * 50_000 + "\n")
    cases["cannot read"] = tmp_path / "digits.yaml"
    if os.path.exists("/proc/self/mem"):
        cases["cannot be read"] = "/proc/self/mem"  # EIO: an OSError of its own kind
    for reason, path in cases.items():
        with pytest.raises(FileFormatError) as info:
            load_mapping(path, what="scenario file")
        text = _one_line(info.value)
        assert f"`{path}`" in text and reason.strip() in text, (reason, text)
        assert len(text) < 500, text
    with pytest.raises(FileNotFoundError):  # a missing file is both kinds of error
        load_mapping(tmp_path / "absent.yaml")
    assert issubclass(MissingFileError, ValueError)


def test_yaml_refuses_python_objects(tmp_path):
    path = tmp_path / "evil.yaml"
    path.write_text("strategy: !!python/object/apply:os.system ['true']\n")
    with pytest.raises(FileFormatError, match="not valid YAML"):
        load_mapping(path)


def test_unknown_keys_are_named_with_a_suggestion():
    with pytest.raises(ValueError) as info:
        check_keys({"distortion_coefficient": 1}, ["distortion_coefficients", "xi"],
                   where="camera file `c.json`")  # fmt: skip
    text = str(info.value)
    assert "Unknown key `distortion_coefficient` in camera file `c.json`" in text
    assert "did you mean `distortion_coefficients`" in text
    with pytest.raises(ValueError, match="must be a mapping; got \\[1, 2\\]"):
        check_keys([1, 2], ["a"], where="`x`")


@pytest.mark.parametrize("kind", ["list", "str", "int", "dict", "array"])
def test_short_is_bounded(kind):
    value = {"list": lambda: list(range(10**6)), "str": lambda: "x" * 10**6,
             "int": lambda: 10**5000, "dict": lambda: {str(i): i for i in range(10**5)},
             "array": lambda: np.zeros(10**6)}[kind]()  # fmt: skip
    t0 = time.perf_counter()
    text = short(value)
    assert len(text) <= 80 and time.perf_counter() - t0 < 0.5


# --------------------------------------------------------------------------------------
# Atomic, durable writes.


def test_atomic_write_is_durable_and_leaves_no_temporary_file(tmp_path, monkeypatch):
    synced = []
    real_fsync = os.fsync
    monkeypatch.setattr(files.os, "fsync", lambda fd: synced.append(fd) or real_fsync(fd))
    path = tmp_path / "out.json"
    atomic_write(path, "old")
    assert path.read_text() == "old" and len(synced) >= 1  # the file (and its folder)

    def fail(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(files.os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        atomic_write(path, "new")
    assert path.read_text() == "old"
    assert os.listdir(tmp_path) == ["out.json"]


def test_concurrent_writers_use_unique_temporary_names(tmp_path):
    path = tmp_path / "shared.txt"
    payloads = [str(k) * 100_000 for k in range(8)]
    threads = [threading.Thread(target=atomic_write, args=(path, p)) for p in payloads]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert path.read_text() in payloads  # one writer's whole file, never a mix
    assert os.listdir(tmp_path) == ["shared.txt"]


def test_strict_json_writes_null_for_nan():
    text = dumps_json({"a": float("nan"), "b": np.float64(np.inf), "c": np.array([1.0, np.nan]),
                       "d": np.int32(3)})  # fmt: skip

    def refuse(constant):
        raise AssertionError(f"non-standard JSON constant {constant}")

    assert json.loads(text, parse_constant=refuse) == {"a": None, "b": None, "c": [1.0, None],
                                                       "d": 3}  # fmt: skip


def test_output_paths_are_checked_before_work(tmp_path):
    assert check_output_file(tmp_path / "a.json")
    assert check_output_dir(tmp_path / "new" / "deeper")
    (tmp_path / "file").write_text("x")
    for bad, match in [
        (lambda: check_output_file(tmp_path), "is a directory"),
        (lambda: check_output_file(tmp_path / "nowhere" / "a.json"), "does not exist"),
        (lambda: check_output_file("/proc/x.json"), "cannot be written"),
        (lambda: check_output_dir(tmp_path / "file"), "is a file"),
        (lambda: check_output_dir(tmp_path / "file" / "sub"), "is a file"),
        (lambda: check_output_dir("/proc/jaxloc-study"), "cannot be written"),
    ]:
        with pytest.raises(FileFormatError, match=match):
            bad()
    assert os.listdir(tmp_path) == ["file"]  # the probes leave nothing behind
