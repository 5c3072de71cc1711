"""What every command shares: a parser whose usage errors are one line, the common flags
(`--json`, `--quiet`, `--overwrite`, `--workers`/`--scheduler`), renamed spellings that keep
working with a deprecation warning, and the translation of library errors into flag names.

The commands only parse and call library functions (the ones Python users call too); every
rule (a limit, a check) lives in the library, whose errors speak of its own arguments
(`OptionError("resolution must be ...")`): `run_command` maps those names to the command's
flags.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Any, Callable

from mvtex.util.errors import InputError

REMOVED_IN = "0.3"  # renamed spellings keep working until this version


class UsageError(Exception):
    """A command line argparse refuses: one line, exit code 2."""


class Parser(argparse.ArgumentParser):
    """argparse with one-line usage errors: "mvtex slide: error: ... (see mvtex slide --help)"."""

    def error(self, message: str):  # argparse calls this and expects it not to return
        raise UsageError(f"{self.prog}: error: {message} (see {self.prog} --help)")


def add_json(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout (and nothing else there)")


def add_quiet(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true", help="no progress bars on stderr")


def add_overwrite(p: argparse.ArgumentParser) -> None:
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing output that this command did not write")


def add_workers(p: argparse.ArgumentParser, default_help: str) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--workers", type=int, default=None, help=f"local worker processes ({default_help})")
    g.add_argument("--scheduler", help="address of a Dask scheduler (tcp://host:8786) whose workers do the work")


def add_rig(p: argparse.ArgumentParser, what: str = "the cameras", *, from_texcoords: bool = False) -> None:
    """`--rig`; with `from_texcoords` it may be left out when `--texcoords` names a set that
    records its rig (`rig_spec`)."""
    default = "; default: the rig recorded in the --texcoords set (TC/rig.yaml)" if from_texcoords else ""
    p.add_argument("--rig", required=not from_texcoords, default=None,
                   help=f"{what}: a rig YAML file or a built-in rig (stereo, square4, trapezoid12){default}")


def rig_spec(args) -> str:
    """The rig to load: `--rig` when given, else the rig the `--texcoords` set records
    (`mvtex.data.texcoords.recorded_rig`); neither is the usual missing-argument error."""
    if args.rig is not None:
        return args.rig
    from mvtex.data.texcoords import recorded_rig

    tc = getattr(args, "texcoords", None)
    path = recorded_rig(tc) if tc is not None else None
    if path is None:
        why = f" ({tc} records no rig)" if tc is not None else ""
        raise UsageError(f"mvtex {args.command}: error: the following arguments are required: --rig{why} "
                         f"(see mvtex {args.command} --help)")
    return str(path)


def add_common(p: argparse.ArgumentParser, *, json: bool = True, quiet: bool = True, overwrite: bool = True) -> None:
    if overwrite:
        add_overwrite(p)
    if json:
        add_json(p)
    if quiet:
        add_quiet(p)


def cameras(value: str | None) -> list[str] | None:
    """`A,B` -> ["A", "B"] (None for None)."""
    return [c.strip() for c in value.split(",") if c.strip()] if value is not None else None


# -- renamed spellings ------------------------------------------------------------------------

def warn_deprecated(args, old: str, new: str | None) -> None:
    instead = f"; use {new}" if new else " (it has no effect)"
    print(f"mvtex {args.command}: warning: {old} is deprecated and will be removed in mvtex {REMOVED_IN}{instead}",
          file=sys.stderr)


class Deprecated(argparse.Action):
    """An old spelling of an option: stores into the new option's destination and warns.

    Args (to add_argument): new: the current spelling, named in the warning (None: the
    option does nothing any more and its value is dropped); convert: maps the old value to
    the new destination's value (default: unchanged).
    """

    def __init__(self, option_strings, dest, new: str | None, convert: Callable[[str], Any] | None = None, **kwargs):
        self.new, self.convert = new, convert
        kwargs.setdefault("help", f"deprecated spelling of {new}" if new else "deprecated; has no effect")
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        namespace._deprecated = getattr(namespace, "_deprecated", []) + [(option_string, self.new)]
        if self.new is not None:
            setattr(namespace, self.dest, self.convert(values) if self.convert else values)


def positional_out(p: argparse.ArgumentParser, help_out: str) -> None:
    """`--out OUT` (required) for a command whose OUT used to be positional (still accepted)."""
    p.add_argument("out_positional", nargs="?", type=Path, metavar="OUT",
                   help="deprecated spelling of --out OUT")
    p.add_argument("--out", type=Path, help=help_out)


def resolve_positional_out(args) -> None:
    if args.out_positional is not None:
        if args.out is not None:
            raise UsageError(f"mvtex {args.command}: error: give OUT once, as --out OUT")
        warn_deprecated(args, "OUT as a positional argument", "--out OUT")
        args.out = args.out_positional
    if args.out is None:
        raise UsageError(f"mvtex {args.command}: error: the following arguments are required: --out "
                         f"(see mvtex {args.command} --help)")


# -- library errors in the command's words ------------------------------------------------------

def flag_names(parser: argparse.ArgumentParser) -> dict[str, str]:
    """destination -> its long flag ("max_surface_distance_m" style names map to their flag
    when the parser declares them through `argument_of`)."""
    out = {}
    for action in parser._actions:
        longs = [s for s in action.option_strings if s.startswith("--")]
        if longs and not isinstance(action, Deprecated):
            out[action.dest] = longs[0]
        for name in getattr(action, "library_names", ()):
            if longs:
                out[name] = longs[0]
    return out


def in_flags(message: str, flags: dict[str, str]) -> str:
    """A library message with its leading argument name replaced by the flag that sets it
    ("resolution must be ..." -> "--resolution must be ...")."""
    match = re.match(r"^([a-z_][a-z0-9_]*)(\b.*)$", message, flags=re.S)
    if match and match.group(1) in flags:
        return flags[match.group(1)] + match.group(2)
    return message


def library_names(action: argparse.Action, *names: str) -> argparse.Action:
    """Declare which library argument names this flag sets (for `in_flags`)."""
    action.library_names = names
    return action


def emit(args, result: Any, text: str) -> None:
    """Print the result as one JSON object with --json, else the human-readable text."""
    from mvtex.util.files import dumps_strict

    if getattr(args, "json", False):
        print(dumps_strict(result.to_json() if hasattr(result, "to_json") else result))
    else:
        print(text)


INPUT_ARGUMENTS = ("dataset", "texcoords", "model", "images", "rig", "pose_vectors", "from_colmap", "rest_mesh")
"""The arguments that name a command's inputs (paths that exist; a built-in rig's name is none)."""


def command_inputs(args) -> list[str]:
    """The files and folders a command reads, from its arguments and its globs."""
    import glob

    from mvtex.util.output import input_paths

    globs = [glob.glob(str(getattr(args, k))) for k in ("gt", "inferred", "body_glob") if getattr(args, k, None)]
    return input_paths(*(getattr(args, k, None) for k in INPUT_ARGUMENTS), *globs)


def output(args, command: str, path: Path | None = None, in_place: bool = False):
    """Claim the command's output with its inputs (see `mvtex.util.output.claim_output`:
    the library writer called inside claims it again and adds its own checks)."""
    from mvtex.util.output import claim_output

    return claim_output(path if path is not None else args.out, command, overwrite=args.overwrite, in_place=in_place,
                        inputs=command_inputs(args))


def load_rig(spec: str, pinhole: bool = True):
    """The rig and its path; with `pinhole` (commands that render) cameras with distortion
    are refused."""
    from mvtex.data.rig import load_rig as load
    from mvtex.data.rig import resolve_rig

    path = resolve_rig(spec)
    rig = load(path)
    if pinhole:
        for camera in rig:
            camera.require_renderable(path)
    return rig, str(path)


def run_command(parser: argparse.ArgumentParser, args) -> None:
    """Run the command of `args`; a library error about an argument value (an InputError
    without a file, "resolution must be ...") is reported in the flag's name."""
    for old, new in getattr(args, "_deprecated", []):
        warn_deprecated(args, old, new)
    try:
        args.run(args)
    except InputError as err:
        if err.path is not None:
            raise
        raise InputError(None, in_flags(err.problem, flag_names(parser))) from None
