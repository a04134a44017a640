"""A study's folder on disk: its manifest and its chunk files, written atomically and
verified when the study resumes.

A study folder holds `study.json` (the manifest: scenario, seed, chunk size, methods,
format and the study's hash) and one `chunk_NNNNNN.npz` per chunk. A chunk file holds
the chunk's arrays (the fields of [`jaxloc.TrialErrors`][] with a leading trial axis and
`index`, the trial indices), the study's `seed` and `study_hash`: the SHA-256 of the
canonical JSON of the scenario's file representation, the methods, the chunk size and
[`FORMAT`][]. Files are written with `jaxloc._core.files.atomic_write` (unique temporary
name, `fsync`, rename) and read with `allow_pickle=False`.

On resume every chunk file is checked: it must load, hold exactly the expected arrays
with the expected shapes and dtypes, the trial indices of its place in the study, and the
study's seed and hash. A chunk that fails (truncated, bit-flipped, another chunk's
contents copied over it, another study's) is recomputed, with a one-line warning naming
the file on stderr. A manifest that cannot be read is an error naming the file.
"""

import hashlib
import io
import os
import struct
import sys
import zipfile
from collections.abc import Sequence
from typing import Any

import numpy as np

from .._core.files import (
    atomic_write,
    atomic_write_json,
    canonical_json,
    FileFormatError,
    load_mapping,
    short,
)


#: Version of a study folder's layout and of the chunk files' contents; a folder of
#: another version is refused (recomputing it in a new folder is the remedy).
FORMAT = 4
MANIFEST = "study.json"
#: Largest study seed: the seed enters the trial keys as a uint32.
SEED_MAX = 2**32 - 1
#: Arrays of a chunk file that describe the chunk rather than its trials.
_META = ("seed", "study_hash")


def check_seed(seed: Any) -> int:
    """`seed` if it is an integer in `[0, SEED_MAX]`, else a `ValueError` naming it."""
    if isinstance(seed, np.integer):
        seed = int(seed)
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= SEED_MAX:
        raise ValueError(
            f"`seed` must be an integer in [0, {SEED_MAX}] (2**32 - 1); got {short(seed)}."
        )
    return seed


def study_manifest(
    scenario: dict[str, Any], seed: int, chunk_size: int, methods: Sequence[str]
) -> dict[str, Any]:
    """The manifest of a study: `scenario` (its file representation), `seed`,
    `chunk_size`, `methods`, `format` and `study_hash` (see the module docstring)."""
    body = {
        "scenario": scenario,
        "chunk_size": int(chunk_size),
        "methods": list(methods),
        "format": FORMAT,
    }
    digest = hashlib.sha256(canonical_json(body).encode("utf-8")).hexdigest()
    return {**body, "seed": check_seed(seed), "study_hash": digest}


def read_manifest(out_dir: str) -> dict[str, Any] | None:
    """The manifest of the study in `out_dir`, or `None` if there is none yet. A
    manifest that cannot be read is a `jaxloc._core.files.FileFormatError` naming it."""
    path = os.path.join(out_dir, MANIFEST)
    if not os.path.exists(path):
        return None
    manifest = load_mapping(path, what="study manifest", syntax="json")
    if not isinstance(manifest.get("format"), int) or not isinstance(
        manifest.get("chunk_size"), int
    ):
        raise FileFormatError(
            f"study manifest `{path}` is not a jaxloc study manifest (no integer `format` "
            "and `chunk_size`)."
        )
    return manifest


def open_study(out_dir: str, manifest: dict[str, Any]) -> None:
    """Make `out_dir` the folder of the study `manifest`: create it and write the
    manifest, or check that the study already there is the same one.

    Raises `ValueError` naming the first field that differs (resuming a different study
    would mix trials of two studies)."""
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise FileFormatError(f"output folder `{out_dir}` is a file, not a folder.")
    os.makedirs(out_dir, exist_ok=True)
    existing = read_manifest(out_dir)
    if existing is None:
        atomic_write_json(os.path.join(out_dir, MANIFEST), manifest)
        return
    if existing["format"] != FORMAT:
        raise ValueError(
            f"`out_dir` `{out_dir}` holds a study in format {existing['format']} (written by "
            f"another version of jaxloc; this one writes format {FORMAT}); use a new folder."
        )
    for field in ("scenario", "seed", "chunk_size", "methods", "study_hash"):
        if existing.get(field) != manifest[field]:
            raise ValueError(
                f"`out_dir` `{out_dir}` holds a study with a different `{field}`; use a new "
                "folder or the same settings to resume it."
            )


def chunk_path(out_dir: str, chunk_index: int) -> str:
    """The file of chunk `chunk_index` in `out_dir`."""
    return os.path.join(out_dir, f"chunk_{chunk_index:06d}.npz")


def write_chunk(path: str, arrays: dict[str, np.ndarray], manifest: dict[str, Any]) -> None:
    """Write one chunk's `arrays` (with `index`) and the study's seed and hash to `path`,
    atomically and durably."""
    meta = {"seed": np.int64(manifest["seed"]), "study_hash": np.str_(manifest["study_hash"])}
    buffer = io.BytesIO()
    np.savez(buffer, **arrays, **meta)
    atomic_write(path, buffer.getvalue())


#: What reading a damaged `.npz` can raise: zip errors (truncated, bad CRC), numpy's
#: header and data errors (ValueError, EOFError), a member missing (KeyError), a damaged
#: size field (MemoryError, struct.error).
_READ_ERRORS = (OSError, ValueError, EOFError, KeyError, MemoryError, struct.error,
                zipfile.BadZipFile)  # fmt: skip


def _load_npz(path: str) -> dict[str, np.ndarray]:
    # Our own file object: `np.load(path)` leaks its handle when the zip is damaged.
    with open(path, "rb") as f, np.load(f, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def chunk_problem(
    arrays: dict[str, np.ndarray],
    expected: dict[str, tuple[tuple[int, ...], np.dtype]],
    start: int,
    manifest: dict[str, Any],
) -> str | None:
    """What is wrong with a chunk file's `arrays`, or `None` if it is the chunk of trials
    `start + [0, chunk_size)` of the study `manifest`, holding exactly the arrays of
    `expected` (`name -> (shape, dtype)`, `index` included) and the study's seed and
    hash."""
    names = set(expected) | set(_META)
    if set(arrays) != names:
        missing, extra = sorted(names - set(arrays)), sorted(set(arrays) - names)
        return f"holds other arrays than a chunk's (missing {missing}, unexpected {extra})"
    if arrays["study_hash"].shape != () or str(arrays["study_hash"]) != manifest["study_hash"]:
        return "belongs to another study (its study hash differs)"
    seed = arrays["seed"]
    if seed.shape != () or seed.dtype.kind not in "iu" or int(seed) != manifest["seed"]:
        return f"was computed with seed {short(seed.tolist())}, not {manifest['seed']}"
    for name, (shape, dtype) in expected.items():
        a = arrays[name]
        if a.shape != shape or a.dtype != dtype:
            return f"has `{name}` of shape {a.shape} and dtype {a.dtype}, not {shape} and {dtype}"
    want = np.arange(start, start + expected["index"][0][0], dtype=np.int64)
    if not np.array_equal(arrays["index"], want):
        first = short(arrays["index"][:3].tolist())
        return f"holds trials {first}..., not {start} to {int(want[-1])}"
    return None


def read_chunk(
    path: str,
    expected: dict[str, tuple[tuple[int, ...], np.dtype]],
    start: int,
    manifest: dict[str, Any],
) -> dict[str, np.ndarray] | None:
    """The arrays of the chunk file `path` (those of `expected`), or `None` if there is
    no such file or it fails [`chunk_problem`][]'s checks; a failing file gets a one-line
    warning on stderr, naming it, and is to be recomputed."""
    if not os.path.exists(path):
        return None
    try:
        arrays = _load_npz(path)
    except _READ_ERRORS as e:
        reason = " ".join(str(e).split())[:120] or type(e).__name__
        warn_recompute(f"chunk file `{path}` cannot be read ({type(e).__name__}: {reason})")
        return None
    problem = chunk_problem(arrays, expected, start, manifest)
    if problem is not None:
        warn_recompute(f"chunk file `{path}` {problem}")
        return None
    return {k: arrays[k] for k in expected}


def warn_recompute(message: str) -> None:
    """One line on stderr: `jaxloc: warning: <message>; recomputing it.`"""
    print(f"jaxloc: warning: {message}; recomputing it.", file=sys.stderr, flush=True)
