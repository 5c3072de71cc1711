"""What every command shares: a parser whose usage errors are one line, the common flags
(`--json`, `--quiet`, `--overwrite`, `--workers`/`--scheduler`, `--rig`), and library errors
reported in the words of the flag that set the argument.

The commands only parse and call library functions (the ones Python users call too); every
rule (a limit, a check) lives in the library, whose `OptionError(argument, problem)` names
its argument: `run_command` names the flag whose destination is that argument. The flags of
an options class come from its fields (`mvtex.cli.options`).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from mvtex.util.errors import InputError, OptionError


class UsageError(Exception):
    """A command line argparse refuses: one line, exit code 2."""


class Parser(argparse.ArgumentParser):
    """argparse with one-line usage errors: "mvtex slide: error: ... (see mvtex slide --help)",
    and no abbreviated flags (`--camera` is not `--cameras`: a script's spelling means one flag)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message: str):  # argparse calls this and expects it not to return
        raise UsageError(f"{self.prog}: error: {message} (see {self.prog} --help)")


def add_json(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout (and nothing else there)")


def add_quiet(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true", help="no progress bars on stderr")


def add_overwrite(p: argparse.ArgumentParser) -> None:
    p.add_argument("--overwrite", action="store_true",
                   help="replace an earlier output of another mvtex command at --out (never files mvtex did not "
                   "write, never an input)")


def add_workers(p: argparse.ArgumentParser, default_help: str) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--workers", metavar="N", type=int, default=None, help=f"local worker processes (default: {default_help})")
    g.add_argument("--scheduler", metavar="ADDRESS", help="address of a Dask scheduler (tcp://host:8786) whose workers do the work")


def add_rig(p: argparse.ArgumentParser, what: str = "the cameras", *, from_texcoords: bool = False) -> None:
    """`--rig`; with `from_texcoords` it may be left out when `--texcoords` names a set that
    records its rig (`rig_of`)."""
    default = " (default: the rig recorded in the --texcoords set, TC/rig.yaml)" if from_texcoords else ""
    p.add_argument("--rig", required=not from_texcoords, default=None,
                   help=f"{what}: a rig YAML file or a built-in rig (stereo, square4, trapezoid12){default}")


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


def rig_of(args, *, pinhole: bool = True, names: list[str] | None = None):
    """The command's rig, read once: `--rig` when given, else the rig the `--texcoords` set
    records (`mvtex.data.texcoords.recorded_rig`); neither is the usual missing-argument
    error. With `pinhole` (commands that render) cameras with distortion are refused; with
    `names`, the sub-rig of those cameras.

    Returns:
        A `Rig` whose `source` is its file.
    """
    from mvtex.data.rig import load_rig

    spec = args.rig
    if spec is None:
        from mvtex.data.texcoords import recorded_rig

        tc = getattr(args, "texcoords", None)
        spec = recorded_rig(tc) if tc is not None else None
        if spec is None:
            why = f" ({tc} records no rig)" if tc is not None else ""
            raise UsageError(f"mvtex {args.command}: error: the following arguments are required: --rig{why} "
                             f"(see mvtex {args.command} --help)")
    rig = load_rig(spec)
    if pinhole:
        for camera in rig:
            camera.require_renderable(rig.source)
    return rig.select(names)


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


# -- library errors in the command's words ------------------------------------------------------

def flag_of(parser: argparse.ArgumentParser, argument: str | None) -> str | None:
    """The flag that sets a library argument: the long option whose destination it is
    (`--max-stretch`, not its `--no-max-stretch`); None when no flag sets it."""
    if argument is None:
        return None
    for action in parser._actions:
        longs = [s for s in action.option_strings if s.startswith("--") and not s.startswith("--no-")]
        if action.dest == argument and longs:
            return longs[0]
    return None


def run_command(parser: argparse.ArgumentParser, args) -> None:
    """Run the command of `args`; a library error about an argument a flag sets is reported
    in the flag's name ("--resolution must be ...")."""
    try:
        args.run(args)
    except OptionError as err:
        flag = flag_of(parser, err.argument)
        if flag is None:
            raise
        raise InputError(None, f"{flag} {err.detail}") from None
