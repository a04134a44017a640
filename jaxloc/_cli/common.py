"""What every `jaxloc` command shares: exit codes, checks of arguments and output paths
made before any work starts, and strict JSON reports."""

import argparse
import contextlib
import os
from collections.abc import Callable, Iterator
from typing import Any

from .._core.files import atomic_write_json, check_output_dir, check_output_file


#: Exit codes of the `jaxloc` command (also in `jaxloc --help`).
EXIT_OK = 0
EXIT_NO_RESULT = 1
EXIT_BAD_INPUT = 2
EXIT_CLUSTER = 3
EXIT_INTERRUPTED = 130
EXIT_CODES_HELP = """\
exit codes:
  0    success
  1    the run finished but found no valid result: every trial of a study failed
       (simulate, table1), no feasible formation (design: its report is written,
       no scenario file), or the localization's status is not successful
       (localize: its poses file is written)
  2    bad input: an argument, or a file that cannot be read, parsed or written
       (one line on stderr names it)
  3    --ray: the Ray cluster cannot be reached, or a task (a study's chunk, a
       design's group of starts) still failed after its retries (a study's chunks
       finished until then are in --out DIR)
  130  interrupted (Ctrl-C); a study run with --out DIR resumes when the same
       command is run again
"""


def check_seed_arg(name: str, seed: int) -> int:
    """`seed` if it is a valid study seed (see `jaxloc._study.chunks.check_seed`), else a
    `ValueError` naming the option `name` (e.g. `--seed`)."""
    from .._study.chunks import check_seed

    try:
        return check_seed(seed)
    except ValueError as e:
        raise ValueError(str(e).replace("`seed`", name, 1)) from None


def check_plot_path(path: str) -> str:
    """Check an image path for `matplotlib`'s `savefig` before a run: writable, and a
    suffix matplotlib can write (`.png`, `.pdf`, `.svg`, ...)."""
    check_output_file(path, what="--plot file")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    kinds = FigureCanvasAgg(Figure()).get_supported_filetypes()
    suffix = os.path.splitext(path)[1].lstrip(".").lower()
    if suffix not in kinds:
        raise ValueError(
            f"--plot file `{path}` must end in one of {', '.join('.' + k for k in kinds)} "
            "(the image format)."
        )
    return path


def check_outputs(
    args: Any, files: tuple[str, ...] = (), dirs: tuple[str, ...] = (), plots=("plot",)
) -> None:
    """Check, before any work, that the output paths given in `args` can be written:
    each attribute in `files` a file, in `dirs` a folder, in `plots` an image file. Raises
    a one-line `ValueError` naming the option and the path."""
    for name in files:
        path = getattr(args, name, None)
        if path is not None:
            check_output_file(path, what=f"--{name.replace('_', '-')} file")
    for name in dirs:
        path = getattr(args, name, None)
        if path is not None:
            check_output_dir(path, what=f"--{name.replace('_', '-')} folder")
    for name in plots:
        path = getattr(args, name, None)
        if path is not None:
            check_plot_path(path)


def write_report(path: str, report: dict, *, quiet: bool = False) -> None:
    """Write a command's report as strict JSON (NaN and infinities as `null`),
    atomically, and say so (unless `quiet`)."""
    atomic_write_json(path, report)
    if not quiet:
        print(f"wrote {path}")


class HelpFormatter(argparse.HelpFormatter):
    """argparse's formatter, except that descriptions and epilogs keep their paragraphs
    (separated by blank lines) and their indented blocks (tables such as the exit codes)
    as written; other paragraphs are wrapped to the terminal's width."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        import textwrap

        blocks = []
        for block in text.strip("\n").split("\n\n"):
            lines = block.split("\n")
            if block.endswith(":") or any(line.startswith("  ") for line in lines[1:]):
                blocks.append("\n".join(indent + line for line in lines))
            else:
                blocks.append(textwrap.fill(" ".join(block.split()), width,
                                            initial_indent=indent, subsequent_indent=indent))
        return "\n\n".join(blocks)


QUIET_HELP = (
    "print only the results (tables, poses, the formation): no progress bar, no timings, "
    "no 'wrote FILE' lines; warnings and errors still go to stderr, one line each"
)


def quiet_option() -> argparse.ArgumentParser:
    """A parent parser holding `--quiet`, shared by every subcommand."""
    parent = argparse.ArgumentParser(add_help=False)
    parent.add_argument("-q", "--quiet", action="store_true", help=QUIET_HELP)
    return parent


def chatter(args: Any) -> Callable[..., None]:
    """`print` for what is not a command's result (timings, progress notes, 'wrote FILE'):
    silent with `--quiet`."""
    if getattr(args, "quiet", False):
        return lambda *a, **k: None
    return print


#: `--ray` given without an address: start a local Ray cluster.
LOCAL_RAY = "local"


def ray_option(p: argparse.ArgumentParser, tasks: str, same: str) -> None:
    """Add `--ray [ADDRESS]` to the command `p`: `tasks` says what runs as one Ray task
    (e.g. "every chunk"), `same` what equals a local run (e.g. "same numbers")."""
    p.add_argument("--ray", nargs="?", const=LOCAL_RAY, default=None, metavar="ADDRESS",
                   help=f"run {tasks} as a task on a Ray cluster: the one at ADDRESS (e.g. "
                   "ray://HEAD:10001, or 'auto' for the cluster this machine is in), or a new "
                   "local one with a worker per core when ADDRESS is omitted; a task whose "
                   f"worker is lost is retried; {same} as a local run; needs pip install "
                   "'jaxloc[cluster]' (and jaxloc on every node)")  # fmt: skip


def check_ray_arg(args: Any) -> None:
    """A one-line `ValueError` if `--ray` was given an empty ADDRESS."""
    ray = getattr(args, "ray", None)
    if ray is not None and ray.strip() == "":
        raise ValueError("--ray ADDRESS must not be empty (omit ADDRESS for a local cluster).")


@contextlib.contextmanager
def ray_cluster(args: Any) -> Iterator[str | None]:
    """With --ray: connect to the cluster (or start a local one) for the duration of the
    block and yield one line describing it; else yield None. A cluster that cannot be
    reached raises `jaxloc._study.cluster.ClusterError` (exit code 3)."""
    if getattr(args, "ray", None) is None:
        yield None
        return
    # No Ray call may start a cluster of its own (Ray's auto-init): after Ctrl-C the
    # command's thread may still call Ray while the main thread disconnects. Read by Ray
    # when it is imported, here (`connect`).
    os.environ.setdefault("RAY_ENABLE_AUTO_CONNECT", "0")
    from .._study.cluster import connect, describe_cluster, disconnect

    address = None if args.ray == LOCAL_RAY else args.ray
    started = connect(address)
    try:
        yield describe_cluster()
    finally:
        if started:
            disconnect()
