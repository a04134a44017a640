"""What every `jaxloc` command shares: exit codes, checks of arguments and output paths
made before any work starts, and strict JSON reports."""

import argparse
import os
from collections.abc import Callable
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
  3    --ray: the Ray cluster cannot be reached, or a chunk task still failed after
       its retries (the chunks finished until then are in --out DIR)
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
