"""Reading and writing jaxloc's files: bounded loading, atomic writes, one-line errors.

Every file jaxloc reads (scenario, camera, team, study manifest) goes through
[`load_mapping`][] or [`read_text`][]: a size limit, YAML by `yaml.safe_load` with aliases
and duplicate keys refused (an alias bomb expands a few hundred bytes into gigabytes), and
every OS or decoding error turned into one [`FileFormatError`][] that names the file.
Loaders then check their keys with [`check_keys`][] and values with their own rules; the
messages show values through [`short`][], never a whole `repr`.

Every file jaxloc writes goes through [`atomic_write`][]: a unique temporary file in the
target's folder, flushed and `fsync`ed, then renamed over the target, so a reader (or a
resumed study) sees the old file or the new one, never half of one, and two writers never
share a temporary name. Commands check their output paths with [`check_output_file`][]
and [`check_output_dir`][] before they start work.
"""

import contextlib
import difflib
import json
import math
import os
import reprlib
import tempfile
from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np
import yaml


#: Largest text file jaxloc reads (bytes): far above any real scenario, camera or team
#: file, far below what would take noticeable memory.
MAX_FILE_BYTES = 1 << 20


class FileFormatError(ValueError):
    """A file jaxloc cannot use: missing, unreadable, too large, not decodable, or not
    in its format. The message names the file and says why, in one line."""


class MissingFileError(FileFormatError, FileNotFoundError):
    """A [`FileFormatError`][] for a file that does not exist; also a
    `FileNotFoundError`, so that either `except` clause catches it."""


def short(value: Any, limit: int = 80) -> str:
    """A bounded `repr` of `value` for error messages (at most `limit` characters, a few
    items of each container): a value read from a file may be huge, and formatting it
    whole can take minutes and gigabytes."""
    r = reprlib.Repr()
    r.maxlist = r.maxtuple = r.maxdict = r.maxset = 8
    r.maxstring = r.maxother = r.maxlong = 60
    r.maxlevel = 3
    try:
        text = r.repr(value)
    except (ValueError, RecursionError):  # e.g. an int beyond Python's digit limit
        text = f"<a {type(value).__name__}>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def short_key(key: Any, limit: int = 60) -> str:
    """A key or name for a message in backticks: the string itself if it is a short
    string, else [`short`][]`(key)`."""
    return key if isinstance(key, str) and len(key) <= limit else short(key, limit)


def _describe(path: str, what: str) -> str:
    return f"{what} `{path}`"


def read_bytes(path: str | os.PathLike, *, what: str = "file", max_bytes: int = MAX_FILE_BYTES):
    """The bytes of `path` (at most `max_bytes`), or a [`FileFormatError`][] naming
    `what` and the file ([`MissingFileError`][] if it does not exist)."""
    path = os.fspath(path)
    where = _describe(path, what)
    try:
        with open(path, "rb") as f:
            data = f.read(max_bytes + 1)
    except FileNotFoundError:
        raise MissingFileError(f"{where} does not exist.") from None
    except IsADirectoryError:
        raise FileFormatError(f"{where} is a directory, not a file.") from None
    except PermissionError:
        raise FileFormatError(f"{where} is not readable (permission denied).") from None
    except OSError as e:
        raise FileFormatError(f"{where} cannot be read: {e.strerror or e}.") from None
    if len(data) > max_bytes:
        raise FileFormatError(
            f"{where} is larger than {max_bytes} bytes; jaxloc's files are small text files "
            "(is this the right file?)."
        )
    return data


def read_text(path: str | os.PathLike, *, what: str = "file", max_bytes: int = MAX_FILE_BYTES):
    """The UTF-8 text of `path`, or a [`FileFormatError`][] naming `what` and the file."""
    data = read_bytes(path, what=what, max_bytes=max_bytes)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise FileFormatError(
            f"{_describe(os.fspath(path), what)} is not UTF-8 text (byte {e.start}): is it a "
            "binary file?"
        ) from None


class _StrictLoader(yaml.SafeLoader):
    """`yaml.SafeLoader` that refuses aliases (`*name`) and duplicate keys. jaxloc's files
    never need aliases, and nested aliases expand exponentially (the 'billion laughs'
    attack); a duplicate key silently drops one of its values."""

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.YAMLError(
                f"YAML aliases (`*{short_key(event.anchor, 40)}`) are not allowed in jaxloc's "
                f"files (line {event.start_mark.line + 1}); write the value out"
            )
        return super().compose_node(parent, index)

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                duplicate = key in seen
                seen.add(key)
            except TypeError:  # unhashable: the base class reports it
                continue
            if duplicate:
                raise yaml.YAMLError(
                    f"duplicate key {short(key, 40)} (line {key_node.start_mark.line + 1})"
                )
        return super().construct_mapping(node, deep=deep)


def parse_yaml(text: str, *, where: str) -> Any:
    """`yaml.safe_load(text)` without aliases or duplicate keys; errors name `where`, in
    one line."""
    try:
        return yaml.load(text, Loader=_StrictLoader)  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError as e:
        reason = " ".join(str(e).split())
        raise FileFormatError(f"{where} is not valid YAML: {reason[:300]}") from None
    except RecursionError:
        raise FileFormatError(f"{where} is nested too deeply to be a jaxloc file.") from None
    except ValueError as e:  # e.g. an integer beyond Python's digit limit
        raise FileFormatError(
            f"{where} holds a value jaxloc cannot read: {short(str(e), 200)}"
        ) from None


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict:
    d = {}
    for k, v in pairs:
        if k in d:
            raise ValueError(f"duplicate key {short(k, 40)}")
        d[k] = v
    return d


def parse_json(text: str, *, where: str) -> Any:
    """`json.loads(text)` without duplicate keys; errors name `where`, in one line."""
    try:
        return json.loads(text, object_pairs_hook=_no_duplicates)
    except json.JSONDecodeError as e:
        raise FileFormatError(f"{where} is not valid JSON: {e}") from None
    except RecursionError:
        raise FileFormatError(f"{where} is nested too deeply to be a jaxloc file.") from None
    except ValueError as e:
        raise FileFormatError(f"{where} is not valid JSON: {short(str(e), 200)}") from None


def syntax_of(path: str, *, default: str = "json") -> str:
    """`"yaml"` for a `.yaml`/`.yml` suffix, `"json"` for `.json`, else `default`."""
    if path.endswith((".yaml", ".yml")):
        return "yaml"
    if path.endswith(".json"):
        return "json"
    return default


def parse_mapping(text: str, *, where: str, syntax: str) -> dict:
    """The one mapping in `text` (`syntax` `"yaml"` or `"json"`); an empty text, or one
    holding anything but a mapping, is a [`FileFormatError`][] naming `where`."""
    if not text.strip():
        raise FileFormatError(f"{where} is empty.")
    data = parse_yaml(text, where=where) if syntax == "yaml" else parse_json(text, where=where)
    if data is None:
        raise FileFormatError(f"{where} is empty.")
    if not isinstance(data, dict):
        raise FileFormatError(
            f"{where} must hold a mapping of keys to values; got a {type(data).__name__}."
        )
    return data


def load_mapping(
    path: str | os.PathLike, *, what: str = "file", syntax: str | None = None
) -> dict:
    """A YAML or JSON file holding one mapping.

    **Arguments:**

    - `path`: the file.
    - `what`: what the file is, for messages (`"scenario file"`).
    - `syntax`: `"yaml"` or `"json"`; default from the suffix ([`syntax_of`][]: YAML
      for `.yaml`/`.yml`, else JSON).

    Bounded ([`MAX_FILE_BYTES`][], no YAML aliases, no duplicate keys); an empty file, or
    one holding anything but a mapping, is a [`FileFormatError`][] naming the file.
    """
    path = os.fspath(path)
    text = read_text(path, what=what)
    return parse_mapping(text, where=_describe(path, what), syntax=syntax or syntax_of(path))


def check_keys(
    d: Any, allowed: Iterable[str], *, where: str, listed: Iterable[str] | None = None
) -> dict:
    """Check that `d` is a mapping whose keys are all in `allowed`; `where` names it in
    messages, verbatim (e.g. ``"`cameras.overhead`"``). Returns `d`.

    Raises `ValueError` naming the first unknown key (bounded), the closest allowed key if
    one is close, and the keys of `listed` (default: `allowed`)."""
    if not isinstance(d, dict):
        raise ValueError(f"{where} must be a mapping; got {short(d)}.")
    allowed = set(allowed)
    for k in d:
        if k not in allowed:
            name = short_key(k)
            close = difflib.get_close_matches(str(name), sorted(allowed), n=1)
            hint = f" (did you mean `{close[0]}`?)" if close else ""
            expected = sorted(allowed if listed is None else listed)
            raise ValueError(
                f"Unknown key `{name}` in {where}{hint}; expected one of {expected}."
            )
    return d


@contextlib.contextmanager
def naming_file(path: str | os.PathLike, what: str) -> Iterator[None]:
    """Turn a `ValueError` raised inside the block into a [`FileFormatError`][] whose
    message starts with `what` and the file (unless it names the file already)."""
    path = os.fspath(path)
    try:
        yield
    except FileFormatError:
        raise
    except ValueError as e:
        text = str(e)
        if path not in text:
            text = f"{_describe(path, what)}: {text}"
        raise FileFormatError(text) from None


def _probe_folder(folder: str, where: str) -> None:
    try:
        fd, probe = tempfile.mkstemp(prefix=".jaxloc-probe-", dir=folder)
    except OSError as e:
        raise FileFormatError(
            f"{where} cannot be written: no file can be created in `{folder}` "
            f"({e.strerror or e})."
        ) from None
    os.close(fd)
    os.unlink(probe)


def check_output_file(path: str | os.PathLike, *, what: str = "output file") -> str:
    """Check, before a long computation, that a file can be written at `path`: it is not
    a folder, its folder exists and a file can be created there. Returns the path.

    Raises a [`FileFormatError`][] naming `what` and the path, in one line."""
    path = os.fspath(path)
    where = _describe(path, what)
    if not path or path.endswith(os.sep):
        raise FileFormatError(f"{where} is not a file name.")
    if os.path.isdir(path):
        raise FileFormatError(f"{where} is a directory; give a file name.")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise FileFormatError(f"{where}: its folder `{folder}` does not exist.")
    _probe_folder(folder, where)
    return path


def check_output_dir(path: str | os.PathLike, *, what: str = "output folder") -> str:
    """Check, before a long computation, that `path` is (or can be made) a writable
    folder: an existing folder where files can be created, or a path whose nearest
    existing ancestor is such a folder. Returns the path.

    Raises a [`FileFormatError`][] naming `what` and the path, in one line."""
    path = os.fspath(path)
    where = _describe(path, what)
    if os.path.exists(path) and not os.path.isdir(path):
        raise FileFormatError(f"{where} is a file, not a folder.")
    existing = os.path.abspath(path)
    while not os.path.exists(existing):
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        raise FileFormatError(f"{where} cannot be created: `{existing}` is a file.")
    _probe_folder(existing, where)
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
    # Makes the rename itself durable; some file systems refuse to fsync a folder.
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


def canonical_json(obj: Any) -> str:
    """Compact JSON of `obj` with sorted keys: equal values give equal text (for hashes)."""
    return json.dumps(json_ready(obj), sort_keys=True, separators=(",", ":"), allow_nan=False)


def atomic_write_json(path: str | os.PathLike, obj: Any) -> None:
    """[`atomic_write`][] of [`dumps_json`][]`(obj)`."""
    atomic_write(path, dumps_json(obj))


def dumps_yaml(obj: Any) -> str:
    """YAML text of a mapping of plain values, keys in their given order, lists of
    numbers on one line (as Kalibr writes its files)."""
    return yaml.safe_dump(json_ready(obj), sort_keys=False, default_flow_style=None)


def dumps_mapping(obj: Any, path: str | os.PathLike, *, default: str = "json") -> str:
    """[`dumps_yaml`][] or [`dumps_json`][] of `obj`, by the suffix of `path` (see
    [`syntax_of`][])."""
    if syntax_of(os.fspath(path), default=default) == "yaml":
        return dumps_yaml(obj)
    return dumps_json(obj)
