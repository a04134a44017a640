"""A study's folder (jaxloc._study.chunks): chunk files that say what they hold, verified
on resume, recomputed when damaged (issue 17 cases 7 and 13; DESIGN §7)."""

import json
import os
import shutil
import zipfile

import jaxloc
import numpy as np
import pytest
from jaxloc._core import files
from jaxloc._core.files import FileFormatError
from jaxloc._study.chunks import FORMAT, study_manifest


# The configuration of tests/test_montecarlo.py and tests/test_cli.py (one compilation).
N, SEED, CHUNK = 96, 3, 32
METHODS = ("paper", "robust")


@pytest.fixture(scope="module")
def scenario():
    return jaxloc.Scenario.paper(strategy="sequential")


@pytest.fixture(scope="module")
def reference(scenario):
    return jaxloc.run_study(
        scenario, N, seed=SEED, chunk_size=CHUNK, methods=METHODS, progress=False
    )


@pytest.fixture(scope="module")
def study_dir(scenario, tmp_path_factory):
    """A finished study folder, copied by each test that damages it."""
    out = tmp_path_factory.mktemp("study") / "seq"
    jaxloc.run_study(scenario, N, seed=SEED, chunk_size=CHUNK, methods=METHODS,
                     out_dir=str(out), progress=False)  # fmt: skip
    return out


def _copy(study_dir, tmp_path):
    dst = tmp_path / "seq"
    shutil.copytree(study_dir, dst)
    return dst


def _resume(scenario, out, capsys):
    """Resume the study in `out`; return its arrays, the chunks recomputed (by the
    warnings) and the stderr lines."""
    arrays = jaxloc.run_study(scenario, N, seed=SEED, chunk_size=CHUNK, methods=METHODS,
                              out_dir=str(out), progress=False)  # fmt: skip
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert "Traceback" not in err
    return arrays, lines


def _same(a, b):
    for k in ("status", "index"):
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    for k in ("position", "rotation", "ypr", "position_vector"):
        np.testing.assert_allclose(a[k], b[k], rtol=1e-6, atol=1e-9, err_msg=k)


def test_each_chunk_records_its_trials_seed_and_study(study_dir, scenario):
    manifest = json.loads((study_dir / "study.json").read_text())
    want = study_manifest(jaxloc.scenario_to_dict(scenario), SEED, CHUNK, METHODS)
    assert manifest == want and manifest["format"] == FORMAT
    assert len(manifest["study_hash"]) == 64
    for c in range(N // CHUNK):
        with np.load(study_dir / f"chunk_{c:06d}.npz", allow_pickle=False) as z:
            np.testing.assert_array_equal(z["index"], np.arange(c * CHUNK, (c + 1) * CHUNK))
            assert int(z["seed"]) == SEED and str(z["study_hash"]) == manifest["study_hash"]
    # The hash covers the scenario, the methods, the chunk size and the format.
    other = jaxloc.scenario_to_dict(jaxloc.Scenario.paper("sequential", pixel_sigma=1.0))
    for m in (study_manifest(other, SEED, CHUNK, METHODS),
              study_manifest(jaxloc.scenario_to_dict(scenario), SEED, 64, METHODS),
              study_manifest(jaxloc.scenario_to_dict(scenario), SEED, CHUNK, ("robust",))):
        assert m["study_hash"] != want["study_hash"]  # fmt: skip


def test_a_chunk_copied_over_another_is_recomputed_not_counted_twice(
    study_dir, scenario, reference, tmp_path, capsys
):
    # Issue 17 case 7: the resumed study trusted its files and counted trials 0-31 twice.
    out = _copy(study_dir, tmp_path)
    shutil.copyfile(out / "chunk_000000.npz", out / "chunk_000001.npz")
    resumed, lines = _resume(scenario, out, capsys)
    _same(reference, resumed)
    np.testing.assert_array_equal(resumed["index"], np.arange(N))
    assert len(lines) == 1, lines
    assert "chunk_000001.npz" in lines[0] and "holds trials [0, 1, 2]" in lines[0]
    assert lines[0].startswith("jaxloc: warning:") and lines[0].endswith("recomputing it.")
    _, lines = _resume(scenario, out, capsys)  # repaired on disk: nothing to redo
    assert lines == []


@pytest.mark.parametrize("damage", ["truncated", "bit flip", "empty", "not a zip"])
def test_a_damaged_chunk_is_recomputed_with_one_line(
    study_dir, scenario, reference, tmp_path, capsys, damage
):
    # Issue 17 case 13: BadZipFile / EOFError tracebacks that named no file.
    out = _copy(study_dir, tmp_path)
    path = out / "chunk_000002.npz"
    data = bytearray(path.read_bytes())
    if damage == "truncated":
        data = data[: len(data) // 2]
    elif damage == "bit flip":
        data[len(data) // 2] ^= 0x10  # inside an array's data: the zip CRC catches it
    elif damage == "empty":
        data = b""
    else:
        data = b"not a zip file at all"
    path.write_bytes(bytes(data))
    resumed, lines = _resume(scenario, out, capsys)
    _same(reference, resumed)
    assert len(lines) == 1 and "chunk_000002.npz" in lines[0], lines


def _rewrite(path, change):
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    change(arrays)
    np.savez(path, **arrays)


@pytest.mark.parametrize(
    "change, reason",
    [
        (lambda a: a.update(seed=np.int64(SEED + 1)), "seed 4"),
        (lambda a: a.update(study_hash=np.str_("0" * 64)), "another study"),
        (lambda a: a.update(position=a["position"].astype(np.float32)), "`position`"),
        (lambda a: a.update(ypr=a["ypr"][:, :, :2]), "`ypr`"),
        (lambda a: a.pop("nees"), "missing ['nees']"),
        (lambda a: a.update(extra=np.zeros(3)), "unexpected ['extra']"),
    ],
)
def test_a_chunk_of_another_study_or_shape_is_recomputed(
    study_dir, scenario, reference, tmp_path, capsys, change, reason
):
    out = _copy(study_dir, tmp_path)
    _rewrite(out / "chunk_000001.npz", change)
    resumed, lines = _resume(scenario, out, capsys)
    _same(reference, resumed)
    assert len(lines) == 1 and "chunk_000001.npz" in lines[0] and reason in lines[0], lines


def test_chunks_are_never_unpickled(study_dir, scenario, reference, tmp_path, capsys):
    out = _copy(study_dir, tmp_path)
    _rewrite(out / "chunk_000000.npz", lambda a: a.update(status=np.array([{"evil": 1}])))
    resumed, lines = _resume(scenario, out, capsys)
    _same(reference, resumed)
    assert len(lines) == 1 and "chunk_000000.npz" in lines[0] and "pickle" in lines[0], lines


def test_a_corrupt_manifest_is_an_error_naming_the_file(study_dir, scenario, tmp_path):
    out = _copy(study_dir, tmp_path)
    (out / "study.json").write_text('{"scenario": {"strategy": "seq')
    with pytest.raises(FileFormatError, match=r"study manifest `.*study.json` is not valid JSON"):
        jaxloc.run_study(scenario, N, seed=SEED, chunk_size=CHUNK, methods=METHODS,
                         out_dir=str(out), progress=False)  # fmt: skip
    (out / "study.json").write_text('{"format": 2, "chunk_size": 32}')
    with pytest.raises(ValueError, match=r"format 2 .*use a new folder"):
        jaxloc.run_study(scenario, N, seed=SEED, chunk_size=CHUNK, methods=METHODS,
                         out_dir=str(out), progress=False)  # fmt: skip
    (out / "study.json").write_text("[1, 2]")
    with pytest.raises(FileFormatError, match="must hold a mapping"):
        jaxloc.run_study(scenario, N, seed=SEED, chunk_size=CHUNK, methods=METHODS,
                         out_dir=str(out), progress=False)  # fmt: skip


def test_writes_are_atomic_durable_and_uniquely_named(scenario, tmp_path, monkeypatch):
    # Issue 17 case 7: a fixed temporary name (two writers race) and nothing fsynced.
    made, synced = [], []
    real_mkstemp, real_fsync = files.tempfile.mkstemp, files.os.fsync

    def mkstemp(*args, **kwargs):
        fd, name = real_mkstemp(*args, **kwargs)
        made.append(name)
        return fd, name

    monkeypatch.setattr(files.tempfile, "mkstemp", mkstemp)
    monkeypatch.setattr(files.os, "fsync", lambda fd: synced.append(fd) or real_fsync(fd))
    out = tmp_path / "seq"
    jaxloc.run_study(scenario, 2 * CHUNK, seed=SEED, chunk_size=CHUNK, methods=METHODS,
                     out_dir=str(out), progress=False)  # fmt: skip
    written = sorted(os.listdir(out))
    assert written == ["chunk_000000.npz", "chunk_000001.npz", "study.json"]
    temps = [m for m in made if not os.path.basename(m).startswith(".jaxloc-probe")]
    assert len(temps) == 3 and len(set(temps)) == 3
    assert all(os.path.dirname(m) == str(out) for m in temps)  # same folder: atomic rename
    assert len(synced) >= 3
    for name in written[:2]:
        assert zipfile.is_zipfile(out / name)


@pytest.mark.parametrize("seed", [-1, 2**32, 2**70, 1.5, True])
def test_seeds_outside_uint32_are_refused(scenario, seed):
    # Issue 17 case 12: an OverflowError traceback.
    with pytest.raises(ValueError, match=r"`seed` must be an integer in \[0, 4294967295\]"):
        jaxloc.run_study(scenario, 8, seed=seed, methods=METHODS, progress=False)


def test_a_folder_that_is_a_file_is_refused(scenario, tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(FileFormatError, match="is a file, not a folder"):
        jaxloc.run_study(scenario, 8, seed=SEED, chunk_size=CHUNK, methods=METHODS,
                         out_dir=str(tmp_path / "f"), progress=False)  # fmt: skip
