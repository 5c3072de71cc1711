"""Each knob is declared once, on its options field: the checks, the flags, the errors in the
flag's words and docs/cli.md's tables are projections of it."""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import pytest
from helpers import run

from mvtex.cli import build_parser
from mvtex.cli.options import add_options, options_from
from mvtex.cli.reference import render
from mvtex.data.limits import MAX_SUBDIV
from mvtex.sliding.options import SlideOptions
from mvtex.util.errors import OptionError
from mvtex.util.options import Options, knob, option_fields

ROOT = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class _Toy(Options):
    count: int = knob(2, "how many", low=1, high=5)
    scale: float = knob(0.5, "a scale", unit="m", low=0, low_open=True)
    limit: float | None = knob(None, "an optional limit", low=1, low_open=True)
    auto: int | None = knob(None, "decided for the caller", low=0, auto="by the input")
    mode: Literal["a", "b"] = knob("a", "a mode")
    sizes: tuple[int, ...] = knob((1, 2), "sizes", low=1)
    on: bool = knob(True, "a switch")


@pytest.mark.parametrize("value", [-3, 0, 1, 3, 5, 6, 2.0, True, "3", None])
def test_integer_limits_follow_the_closed_interval(value):
    ok = type(value) is int and 1 <= value <= 5
    if ok:
        assert _Toy(count=value).count == value
    else:
        with pytest.raises(OptionError) as raised:
            _Toy(count=value)
        assert raised.value.argument == "count"
        assert str(raised.value).startswith("count must be an integer in [1, 5]")


@pytest.mark.parametrize("value", [0.0, -1e-9, 1e-9, 7.0, float("nan"), float("inf")])
def test_open_limits_and_non_finite_numbers(value):
    ok = value == value and abs(value) != float("inf") and value > 0
    if ok:
        assert _Toy(scale=value).scale == value
    else:
        with pytest.raises(OptionError, match=r"^scale must be a finite number > 0 \(m\)"):
            _Toy(scale=value)


def test_choices_tuples_and_optionals_are_checked():
    with pytest.raises(OptionError, match="^mode must be one of a, b, got 'c'"):
        _Toy(mode="c")
    with pytest.raises(OptionError, match=r"^sizes must have each value ≥ 1, got 0"):
        _Toy(sizes=(1, 0))
    with pytest.raises(OptionError, match="^sizes must be a tuple of integers"):
        _Toy(sizes=[1, 2])
    with pytest.raises(OptionError, match=r"^limit must be a finite number > 1 or None"):
        _Toy(limit=1.0)
    assert _Toy(limit=None).limit is None and _Toy(limit=2).limit == 2


def _toy_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="toy")
    add_options(parser, _Toy)
    return parser


def test_flags_are_made_from_the_fields():
    parser = _toy_parser()
    assert options_from(parser.parse_args([]), _Toy) == _Toy()
    given = parser.parse_args(["--count", "4", "--no-on", "--mode", "b", "--sizes", "3,4", "--limit", "2.5",
                               "--scale", "1e-3"])
    assert options_from(given, _Toy) == _Toy(count=4, on=False, mode="b", sizes=(3, 4), limit=2.5, scale=1e-3)
    assert options_from(parser.parse_args(["--limit", "3", "--no-limit"]), _Toy).limit is None
    flags = {s for a in parser._actions for s in a.option_strings}
    assert {"--on", "--no-on", "--limit", "--no-limit", "--auto"} <= flags
    assert "--no-auto" not in flags  # None is "decided for you", not "off"
    helps = {a.dest: a.help for a in parser._actions}
    assert helps["scale"].endswith("(m; > 0; default: 0.5)")
    assert helps["auto"].endswith("default: by the input)")
    with pytest.raises(SystemExit):
        parser.parse_args(["--mode", "c"])


def _commands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def _options_classes():
    import mvtex

    return [getattr(mvtex, name) for name in dir(mvtex)
            if name.endswith("Options") and dataclasses.is_dataclass(getattr(mvtex, name))]


def test_the_parser_restates_no_default():
    """A flag that sets a field keeps the library's default (argparse's SUPPRESS); no other
    flag holds a value of its own either, except --out of the demo (where to write)."""
    fields = {f.name for cls in _options_classes() for f, _, spec in option_fields(cls) if spec.flag}
    restated = []
    for name, command in _commands().items():
        for action in command._actions:
            if action.default in (None, False, argparse.SUPPRESS) or isinstance(action, argparse._HelpAction):
                continue
            if (name, action.dest) == ("demo", "out"):
                continue
            restated.append(f"{name} {action.option_strings}: {action.default!r}")
        knobs = [a for a in command._actions if a.dest in fields and a.option_strings]
        assert all(a.default is argparse.SUPPRESS for a in knobs), name
    assert restated == []


def test_every_options_class_declares_every_field_once():
    for cls in _options_classes():
        for field, _, spec in option_fields(cls):
            assert spec is not None and spec.help, f"{cls.__name__}.{field.name} has no knob"


def test_subdiv_has_one_limit_everywhere(tmp_path, capsys):
    """`mvtex slide --subdiv N` and `SlideOptions(subdiv=N)` agree, at the one MAX_SUBDIV."""
    assert SlideOptions(subdiv=MAX_SUBDIV).subdiv == MAX_SUBDIV
    args = _commands()["slide"].parse_args(["data", "--rig", "stereo", "--out", "x", "--subdiv", str(MAX_SUBDIV)])
    assert options_from(args, SlideOptions).subdiv == MAX_SUBDIV
    with pytest.raises(OptionError) as raised:
        SlideOptions(subdiv=MAX_SUBDIV + 1)
    code, out, err = run(capsys, "slide", tmp_path / "nodata", "--rig", "stereo", "--out", tmp_path / "ts",
                         "--subdiv", MAX_SUBDIV + 1)
    assert code == 2 and out == ""
    assert err.strip() == f"mvtex slide: error: --{raised.value}"
    assert not (tmp_path / "ts").exists()


def test_library_errors_name_the_flag(tmp_path, capsys):
    code, _, err = run(capsys, "train", tmp_path, "--texcoords", tmp_path, "--cameras", "a", "--resolution", 100,
                       "--out", tmp_path / "m")
    assert code == 2 and err.strip() == "mvtex train: error: --resolution must be a power of two in 8..2048, got 100"
    code, _, err = run(capsys, "triangulate", tmp_path, "--texcoords", tmp_path, "--pose", 0, "--out",
                       tmp_path / "r", "--max-stretch", 0.5)
    assert code == 2 and err.strip().startswith("mvtex triangulate: error: --max-stretch must be")


def test_cli_reference_tables_are_current():
    """docs/cli.md's flag tables are what `python -m mvtex.cli.reference docs/cli.md` makes."""
    doc = ROOT / "docs" / "cli.md"
    text = doc.read_text()
    assert render(text) == text, "docs/cli.md is stale: run python -m mvtex.cli.reference docs/cli.md"
    commands = set(_commands())
    assert {line.split("flags: ")[1].split(" ")[0] for line in text.splitlines() if "<!-- flags: " in line} \
        == commands
