"""Command-line flags built from options classes (`mvtex.util.options`): one flag per field.

- a `bool` field `x` becomes `--x` / `--no-x`;
- a field that may be None becomes `--x V`, and `--no-x` (None) unless None means "decided
  for you" (`Knob.auto`);
- a `Literal[...]` field takes one of its choices, a `tuple[int, ...]` field "A,B,C";
- the help is the knob's, with its unit, limits and default.

A flag that is not given keeps the library's default: nothing is restated here, and the
help prints the default read from the field.
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any, Iterable

from mvtex.util.options import Kind, Knob, option_fields


def flag(name: str) -> str:
    """The flag of a field: `max_stretch` -> `--max-stretch`."""
    return "--" + name.replace("_", "-")


def default_text(value: Any, kind: Kind, spec: Knob, name: str) -> str:
    """How the help shows a field's default."""
    if value is dataclasses.MISSING:
        return "required"
    if kind.base is bool and value is not None:
        return flag(name) if value else f"--no-{flag(name)[2:]}"
    if value is None:
        return spec.auto if spec.auto is not None else f"--no-{flag(name)[2:]}"
    if isinstance(value, tuple):
        return ",".join(map(str, value))
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def notes_text(kind: Kind, spec: Knob) -> str:
    """A knob's unit and limits, "uv; > 0" ("" without either)."""
    notes = [spec.unit] if spec.unit else []
    limits = spec.limits_text()
    if limits and kind.base in (int, float, tuple):
        notes.append(limits)
    return "; ".join(notes)


def help_text(field: dataclasses.Field, kind: Kind, spec: Knob) -> str:
    """The knob's help with its unit, limits and default: "unassign vertices whose |d|
    exceeds this (uv; > 0; default: --no-max-displacement)"."""
    notes = notes_text(kind, spec)
    default = f"default: {default_text(field.default, kind, spec, field.name)}"
    return f"{spec.help} ({notes + '; ' if notes else ''}{default})".replace("%", "%%")


def _convert(kind: Kind, name: str):
    base = kind.item if kind.base is tuple else kind.base
    label = {int: "an integer", float: "a number", str: "text"}[base]

    def one(text: str):
        try:
            return base(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag(name)} takes {label}, got {text!r}") from None

    if kind.base is tuple:
        def many(text: str):
            return tuple(one(part.strip()) for part in text.split(",") if part.strip())
        return many
    return one


def add_options(parser: argparse.ArgumentParser, cls: type, *, skip: Iterable[str] = (),
                only: Iterable[str] | None = None, group: argparse._ArgumentGroup | None = None) -> list[str]:
    """Add a flag for every knob of the options class `cls` that is a flag.

    Args:
        parser: the command's parser.
        cls: an options dataclass (`mvtex.util.options.Options`).
        skip: fields the command sets itself (an input it reads, a value it derives).
        only: just these fields (a command that shares a few knobs of another stage).
        group: add the flags to this argument group (a section of the help).

    Returns:
        The names of the fields that got a flag (`options_from` reads them back).
    """
    target = group if group is not None else parser
    names = []
    for field, kind, spec in option_fields(cls):
        if spec is None or not spec.flag or field.name in skip or (only is not None and field.name not in only):
            continue
        long = flag(field.name)
        text = help_text(field, kind, spec)
        if kind.base is bool:
            action = target.add_argument(long, dest=field.name, action=argparse.BooleanOptionalAction,
                                         default=argparse.SUPPRESS, help=text)
        else:
            metavar = spec.metavar or field.name.upper()
            if kind.choices is not None:
                action = target.add_argument(long, dest=field.name, choices=kind.choices,
                                             type=_convert(kind, field.name), default=argparse.SUPPRESS, help=text,
                                             metavar="{" + ",".join(map(str, kind.choices)) + "}")
            else:
                action = target.add_argument(long, dest=field.name, type=_convert(kind, field.name),
                                             default=argparse.SUPPRESS, metavar=metavar, help=text)
            if kind.optional and spec.auto is None:
                off = " (the default)" if field.default is None else ""
                target.add_argument(f"--no-{long[2:]}", dest=field.name, action="store_const", const=None,
                                    default=argparse.SUPPRESS, help=f"turn {long} off{off}")
        # What docs/cli.md's table shows of the knob (`mvtex.cli.reference`).
        notes = notes_text(kind, spec)
        action.reference = (default_text(field.default, kind, spec, field.name),
                            spec.help + (f" ({notes})" if notes else ""))
        names.append(field.name)
    return names


def options_from(args: argparse.Namespace, cls: type, **fixed: Any):
    """The options of `cls` from the flags that were given (the others keep the library's
    defaults) and the fields the command sets itself (`fixed`)."""
    given = {f.name: getattr(args, f.name) for f, _, _ in option_fields(cls) if hasattr(args, f.name)}
    return cls(**{**given, **fixed})
