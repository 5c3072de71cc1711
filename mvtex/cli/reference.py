"""docs/cli.md's flag tables, generated from the parsers (and so from the options fields).

Each command's table stands between ``<!-- flags: COMMAND -->`` and ``<!-- /flags -->`` in
docs/cli.md; `python -m mvtex.cli.reference docs/cli.md` rewrites them, and a test fails
when the file differs from what this module makes of it.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from mvtex.cli import build_parser
from mvtex.cli.options import flag

COMMON = ("--help", "--json", "--quiet", "--overwrite")
"""Flags every command shares, described once at the top of docs/cli.md."""

_BLOCK = re.compile(r"(<!-- flags: (?P<command>[a-z]+) -->\n)(?P<table>.*?)(<!-- /flags -->)", re.S)


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _spelling(action: argparse.Action) -> str:
    names = [s for s in action.option_strings if s.startswith("--")]
    if not names:
        return f"`{action.metavar or action.dest.upper()}`"
    if action.nargs == 0:
        return " / ".join(f"`{n}`" for n in names)
    if action.choices is not None:
        return f"`{names[0]} {'|'.join(map(str, action.choices))}`"
    return f"`{names[0]} {action.metavar or action.dest.upper()}`"


def flag_table(command: str) -> str:
    """The markdown table of a command's flags: flag, default, meaning (the flags every
    command shares are left out; they are described once)."""
    parser = _subparsers(build_parser())[command]
    rows = ["| flag | default | meaning |", "|---|---|---|"]
    paired = {}  # dest -> the row of its --x flag, which its --no-x joins
    for action in parser._actions:
        if any(s in COMMON for s in action.option_strings) or not action.option_strings:
            continue
        if hasattr(action, "reference"):  # a knob of an options class (`mvtex.cli.options`)
            default, text = action.reference
        else:
            default, text = _input_default((action.help or "").replace("%%", "%"))
        if action.required:
            default = "required"
        spelling = _spelling(action)
        if action.option_strings[0].startswith("--no-") and action.dest in paired:
            row = paired[action.dest]
            rows[row] = rows[row].replace("` | ", f"` / `{action.option_strings[0]}` | ", 1)
            continue
        paired[action.dest] = len(rows)
        default = f"`{default}`" if default.startswith("--") else default
        rows.append(f"| {_cell(spelling)} | {_cell(default)} | {_cell(text)} |")
    return "\n".join(rows) + "\n"


def _cell(text: str) -> str:
    """Text that stays in its markdown table cell (a `|` would end it)."""
    return text.replace("|", "\\|")


def _input_default(text: str) -> tuple[str, str]:
    """(default, meaning) of a flag that is not a knob (an input, an output, a selection),
    whose help ends in "(default: X)" where it has one."""
    head, sep, tail = text.rpartition(" (default: ")
    if not sep or not tail.endswith(")"):
        return "", text
    return tail[:-1], head


def render(text: str) -> str:
    """docs/cli.md with every flag table made anew."""
    return _BLOCK.sub(lambda m: m.group(1) + flag_table(m.group("command")) + m.group(4), text)


def main(argv: list[str] | None = None) -> int:
    """`python -m mvtex.cli.reference docs/cli.md`: rewrite the tables in place."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m mvtex.cli.reference docs/cli.md", file=sys.stderr)
        return 2
    path = Path(args[0])
    path.write_text(render(path.read_text()))
    return 0


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["flag", "flag_table", "render"]
