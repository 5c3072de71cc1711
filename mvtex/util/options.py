"""Options classes: each knob is declared once, on its field.

A stage's options are a frozen dataclass derived from `Options` whose fields are made with
`knob(default, help, ...)`. The field carries everything about the knob: its type (which
may be a `Literal[...]` of choices, `X | None`, `tuple[int, ...]`), its default, its
one-line help, its unit and its limits. Everything else is a projection of it:

- `Options.__post_init__` checks every field against its type and limits
  (`check_options`) and raises `OptionError(field, problem)`; a class adds only the rules
  that tie fields together, in `validate()`;
- the command line builds one flag per field (`mvtex.cli.options.add_options`): `--x V`,
  `--x/--no-x` for a bool, `--x V`/`--no-x` for a value that may be None, choices from the
  type, and the help shows the default;
- docs/cli.md's option tables are generated from the parsers (`mvtex.cli.reference`).

Example::

    @dataclass(frozen=True)
    class BlurOptions(Options):
        sigma: float = knob(1.0, "standard deviation of the kernel", unit="px", low=0, low_open=True)
        mode: Literal["reflect", "wrap"] = knob("reflect", "how the border is extended")
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import sys
import types
import typing
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, Literal, Union

import numpy as np

from mvtex.util.errors import OptionError

NO_DEFAULT: Any = dataclasses.MISSING
"""The default of a knob that must be given (a required field)."""


@dataclass(frozen=True)
class Knob:
    """What a field says about itself (the `"knob"` entry of its metadata).

    Attributes:
        help: one line, what the knob does (no default: it is added where shown).
        unit: the unit of its value ("m", "px", "uv"), shown in help and docs.
        low, high: the inclusive limits of a number (None: no limit).
        low_open, high_open: the limit itself is excluded.
        auto: what None means, when None is a value decided for the caller (the help shows
            it as the default); a field that may be None without `auto` reads None as off,
            and the command line gets a `--no-x` flag for it.
        flag: exposed as a command-line flag (False: set only from Python).
        metavar: the value's name in the help (default: the field's name in capitals).
    """

    help: str
    unit: str | None = None
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    auto: str | None = None
    flag: bool = True
    metavar: str | None = None

    def limits_text(self) -> str | None:
        """The limits as an interval, "[0, 3]", "(0, 1]", "≥ 0"; None without limits."""
        if self.low is None and self.high is None:
            return None
        if self.high is None:
            return f"{'>' if self.low_open else '≥'} {_number(self.low)}"
        if self.low is None:
            return f"{'<' if self.high_open else '≤'} {_number(self.high)}"
        return (f"{'(' if self.low_open else '['}{_number(self.low)}, {_number(self.high)}"
                f"{')' if self.high_open else ']'}")


def _number(value: float) -> str:
    """A limit as people write it: 4294967295, not 4.29497e+09; 0.001."""
    return str(int(value)) if float(value).is_integer() and abs(value) < 1e16 else f"{value:g}"


def knob(default: Any, help: str, *, unit: str | None = None, low: float | None = None, high: float | None = None,
         low_open: bool = False, high_open: bool = False, auto: str | None = None, flag: bool = True,
         metavar: str | None = None) -> Any:
    """A dataclass field that declares a knob once: its default and its `Knob` metadata.

    Args:
        default: the value when the caller gives none (`NO_DEFAULT`: required). Immutable
            values only (a tuple, not a list).
        help: one line, what it does.
        unit, low, high, low_open, high_open, auto, flag, metavar: see `Knob`.
    """
    if isinstance(default, (list, dict, set)):
        raise TypeError(f"a knob's default must be immutable, got {type(default).__name__}")
    meta = {"knob": Knob(help, unit, low, high, low_open, high_open, auto, flag, metavar)}
    if default is NO_DEFAULT:
        return field(metadata=meta)
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class Kind:
    """A field's type, read once from its annotation.

    Attributes:
        base: int, float, str, bool, tuple (of `item`), or None for a type the checks leave
            to the class (a dataclass, a path).
        optional: None is allowed.
        choices: the values of a `Literal[...]`, else None.
        item: the element type of a `tuple[X, ...]`.
    """

    base: type | None
    optional: bool = False
    choices: tuple | None = None
    item: type | None = None


def _kind(annotation: Any) -> Kind:
    optional = False
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) in (Union, types.UnionType):
        optional = type(None) in args
        rest = [a for a in args if a is not type(None)]
        if len(rest) != 1:
            return Kind(None, optional)
        annotation, args = rest[0], typing.get_args(rest[0])
    origin = typing.get_origin(annotation)
    if origin is Literal:
        return Kind(type(args[0]), optional, tuple(args))
    if origin is tuple and len(args) == 2 and args[1] is Ellipsis and args[0] in (int, float, str):
        return Kind(tuple, optional, item=args[0])
    if annotation in (int, float, str, bool):
        return Kind(annotation, optional)
    return Kind(None, optional)


@lru_cache(maxsize=None)
def option_fields(cls: type) -> tuple[tuple[dataclasses.Field, Kind, Knob | None], ...]:
    """Each field of an options class with its `Kind` and its `Knob` (None for a field made
    without `knob`)."""
    hints = typing.get_type_hints(cls, vars(sys.modules[cls.__module__]))
    return tuple((f, _kind(hints[f.name]), f.metadata.get("knob")) for f in dataclasses.fields(cls))


_WANT = {int: "an integer", float: "a finite number", str: "a string", bool: "True or False"}


def _matches(value: Any, base: type) -> bool:
    if base is bool:
        return isinstance(value, (bool, np.bool_)) or (
            isinstance(value, (numbers.Integral, np.integer)) and value in (0, 1))
    if isinstance(value, (bool, np.bool_)):
        return False
    if base is int:
        return isinstance(value, (numbers.Integral, np.integer))
    if base is float:
        return isinstance(value, numbers.Real) and math.isfinite(float(value))
    return isinstance(value, base)


def check_value(name: str, value: Any, kind: Kind, spec: Knob | None) -> None:
    """Check one value against its field's kind and knob.

    Raises:
        OptionError: naming the field, "subdiv must be an integer in [0, 3], got 5".
    """
    if value is None:
        if kind.optional or kind.base is None:
            return
        raise OptionError(name, f"must be {_want(kind, spec)}, got None")
    if kind.base is None:
        return
    if kind.choices is not None:
        if not _matches(value, kind.base) or value not in kind.choices:
            raise OptionError(name, f"must be one of {', '.join(map(str, kind.choices))}, got {value!r:.60}")
        return
    if kind.base is tuple:
        if not isinstance(value, tuple) or not all(_matches(v, kind.item) for v in value):
            raise OptionError(name, f"must be a tuple of {_WANT[kind.item].split(' ', 1)[1]}s"
                              f"{' or None' if kind.optional else ''}, got {value!r:.60}")
        for v in value:
            _check_limits(name, v, kind, spec, True)
        return
    if not _matches(value, kind.base):
        raise OptionError(name, f"must be {_want(kind, spec)}, got {value!r:.60}")
    _check_limits(name, value, kind, spec, False)


def _check_limits(name: str, value: Any, kind: Kind, spec: Knob | None, element: bool) -> None:
    if spec is None or kind.base not in (int, float, tuple):
        return
    low_bad = spec.low is not None and (value <= spec.low if spec.low_open else value < spec.low)
    high_bad = spec.high is not None and (value >= spec.high if spec.high_open else value > spec.high)
    if low_bad or high_bad:
        limits = spec.limits_text() or ""
        want = f"each value {'in ' if limits[:1] in '[(' else ''}{limits}" if element else _want(kind, spec)
        raise OptionError(name, f"must {'have' if element else 'be'} {want}, got {value!r:.60}")


def _want(kind: Kind, spec: Knob | None) -> str:
    """"an integer in [0, 3]", "a finite number > 0 or None"."""
    text = _WANT.get(kind.base, "a value")
    limits = spec.limits_text() if spec is not None and kind.base in (int, float) else None
    if limits is not None:
        text += f" in {limits}" if limits.startswith(("[", "(")) else f" {limits}"
    if spec is not None and spec.unit and kind.base in (int, float):
        text += f" ({spec.unit})"
    return text + (" or None" if kind.optional else "")


def check_options(options: Any) -> None:
    """Check every field of an options dataclass against its type and its knob's limits.

    Raises:
        OptionError: naming the first field that is wrong.
    """
    for f, kind, spec in option_fields(type(options)):
        check_value(f.name, getattr(options, f.name), kind, spec)


class Options:
    """Base of the options classes: a frozen dataclass whose fields are `knob`s.

    Construction checks every field (`check_options`), then the class's own `validate()`
    (rules that tie fields together). `to_json()` is the record written beside results.
    """

    def __post_init__(self) -> None:
        check_options(self)
        self.validate()

    def validate(self) -> None:
        """Rules between fields (none by default); raise `OptionError(field, problem)`."""

    def to_json(self) -> dict:
        return dataclasses.asdict(self)  # type: ignore[call-overload]
