"""mkdocs hooks: the command line page shows `jaxloc --help` and every command's help as
the installed jaxloc prints them (so the page cannot drift from the program)."""

import os
import re


_MARKER = re.compile(r"^<!-- jaxloc-help(?: (?P<command>[a-z0-9]+))? -->$", re.MULTILINE)


def _help(command: str | None) -> str:
    from jaxloc._cli.main import build_parser

    os.environ["COLUMNS"] = "96"  # argparse wraps to $COLUMNS: a stable page
    parser = build_parser()
    if command is not None:
        (sub,) = [a for a in parser._actions if command in (getattr(a, "choices", None) or ())]
        parser = sub.choices[command]
    return parser.format_help()


def on_page_markdown(markdown: str, page, config, files) -> str:
    def replace(match: re.Match) -> str:
        command = match.group("command")
        return "```text\n" + _help(command).rstrip() + "\n```"

    return _MARKER.sub(replace, markdown)
