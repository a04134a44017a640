"""Reading and writing jaxloc's files: bounded loading, atomic writes, one-line errors.

Every file jaxloc reads (scenario, camera, team, study manifest) goes through
[`load_mapping`][] or [`read_text`][]: a size limit, YAML by `yaml.safe_load` with aliases
refused (an alias bomb expands a few hundred bytes into gigabytes), and every OS or
decoding error turned into one [`FileFormatError`][] that names the file. Every file
jaxloc writes goes through [`atomic_write`][]: a unique temporary file in the target's
folder, flushed and `fsync`ed, then renamed over the target, so a reader (or a resumed
study) sees the old file or the new one, never half of one, and two writers never
share a temporary name.
"""

import json
import math
import os
import reprlib
import tempfile
from typing import Any

import numpy as np
import yaml


#: Largest text file jaxloc reads (bytes): far above any real scenario, camera or team
#: file, far below what would take noticeable memory.
MAX_FILE_BYTES = 1 << 20


class FileFormatError(ValueError):
    """A file jaxloc cannot use: missing, unreadable, too large, not decodable, or not
    in its format. The message names the file and says why, in one line."""


def short(value: Any, limit: int = 80) -> str:
    """A bounded `repr` of `value` for error messages (at most `limit` characters, a few
    items of each container): a value read from a file may be huge, and formatting it
    whole can take minutes and gigabytes."""
    r = reprlib.Repr()
    r.maxlist = r.maxtuple = r.maxdict = r.maxset = 8
    r.maxstring = r.maxother = 60
    r.maxlevel = 3
    text = r.repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def read_bytes(path: str | os.PathLike, *, what: str = "file", max_bytes: int = MAX_FILE_BYTES):
    """The bytes of `path`, or a [`FileFormatError`][] naming `what` and the file."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as f:
            data = f.read(max_bytes + 1)
    except FileNotFoundError:
        raise FileFormatError(f"{what} `{path}` does not exist.") from None
    except IsADirectoryError:
        raise FileFormatError(f"{what} `{path}` is a directory, not a file.") from None
    except PermissionError:
        raise FileFormatError(f"{what} `{path}` is not readable (permission denied).") from None
    except OSError as e:
        raise FileFormatError(f"{what} `{path}` cannot be read: {e.strerror or e}.") from None
    if len(data) > max_bytes:
        raise FileFormatError(
            f"{what} `{path}` is larger than {max_bytes} bytes; jaxloc's files are small "
            "text files (is this the right file?)."
        )
    return data


def read_text(path: str | os.PathLike, *, what: str = "file", max_bytes: int = MAX_FILE_BYTES):
    """The UTF-8 text of `path`, or a [`FileFormatError`][] naming `what` and the file."""
    data = read_bytes(path, what=what, max_bytes=max_bytes)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise FileFormatError(
            f"{what} `{os.fspath(path)}` is not UTF-8 text (byte {e.start}): is it a binary file?"
        ) from None


class _NoAliasLoader(yaml.SafeLoader):
    """`yaml.SafeLoader` that refuses aliases (`*name`): jaxloc's files never need them,
    and nested aliases expand exponentially (the 'billion laughs' attack)."""

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.YAMLError(
                f"YAML aliases (`*{event.anchor}`) are not allowed in jaxloc's files "
                f"(line {event.start_mark.line + 1}); write the value out"
            )
        return super().compose_node(parent, index)


def parse_yaml(text: str, *, where: str) -> Any:
    """`yaml.safe_load(text)` without aliases; errors name `where`, in one line."""
    try:
        return yaml.load(text, Loader=_NoAliasLoader)  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError as e:
        reason = " ".join(str(e).split())
        raise FileFormatError(f"{where} is not valid YAML: {reason[:300]}") from None
    except RecursionError:
        raise FileFormatError(f"{where} is nested too deeply to be a jaxloc file.") from None


def parse_json(text: str, *, where: str) -> Any:
    """`json.loads(text)`; errors name `where`, in one line."""
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise FileFormatError(f"{where} is not valid JSON: {e}") from None
    except RecursionError:
        raise FileFormatError(f"{where} is nested too deeply to be a jaxloc file.") from None


def load_mapping(path: str | os.PathLike, *, what: str = "file") -> dict:
    """A YAML (`.yaml`, `.yml`) or JSON (any other suffix) file holding one mapping.

    Bounded ([`MAX_FILE_BYTES`][], no YAML aliases); an empty file, or one holding
    anything but a mapping, is a [`FileFormatError`][] naming the file."""
    path = os.fspath(path)
    text = read_text(path, what=what)
    where = f"{what} `{path}`"
    if path.endswith((".yaml", ".yml")):
        data = parse_yaml(text, where=where)
    else:
        data = parse_json(text, where=where)
    if data is None:
        raise FileFormatError(f"{where} is empty.")
    if not isinstance(data, dict):
        raise FileFormatError(
            f"{where} must hold a mapping of keys to values; got a {type(data).__name__}."
        )
    return data


def check_writable(path: str | os.PathLike, *, what: str = "output file") -> str:
    """Check, before a long computation, that a file can be written at `path`: its
    folder exists and is writable and `path` is not a folder. Returns the path."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(path):
        raise FileFormatError(f"{what} `{path}` is a directory; give a file name.")
    if not os.path.isdir(folder):
        raise FileFormatError(f"{what} `{path}`: its folder `{folder}` does not exist.")
    try:
        fd, probe = tempfile.mkstemp(prefix=".jaxloc-probe-", dir=folder)
    except OSError as e:
        raise FileFormatError(
            f"{what} `{path}` cannot be written: {e.strerror or e} in `{folder}`."
        ) from None
    os.close(fd)
    os.unlink(probe)
    return path


def atomic_write(path: str | os.PathLike, data: bytes | str) -> None:
    """Write `data` to `path` atomically and durably: a unique temporary file in the same
    folder, flushed and `fsync`ed, renamed over `path`, then the folder `fsync`ed."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    if isinstance(data, str):
        data = data.encode("utf-8")
    fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    _fsync_folder(folder)


def _fsync_folder(folder: str) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def json_ready(obj: Any) -> Any:
    """`obj` with NumPy scalars and arrays as Python values and non-finite floats as
    `None`, so that strict JSON parsers (jq, JavaScript) accept the file."""
    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, np.generic):
        return json_ready(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def dumps_json(obj: Any) -> str:
    """Strict JSON text of `obj` (see [`json_ready`][]), indented, with a final newline."""
    return json.dumps(json_ready(obj), indent=2, allow_nan=False) + "\n"


def atomic_write_json(path: str | os.PathLike, obj: Any) -> None:
    """[`atomic_write`][] of [`dumps_json`][]`(obj)`."""
    atomic_write(path, dumps_json(obj))


def dumps_yaml(obj: Any) -> str:
    """YAML text of a mapping of plain values, keys in their given order."""
    return yaml.safe_dump(json_ready(obj), sort_keys=False)
