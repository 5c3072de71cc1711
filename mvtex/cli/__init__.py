"""The `mvtex` command line: one module per command group, each only parsing arguments and
calling the library functions that Python users call too (`mvtex.slide_dataset`, ...).

Exit codes: 0 success; 2 bad usage, bad input or an output that cannot be written (a full
disk), with one line on stderr naming the file or flag and the problem; 130 interrupted; 141
when stdout is closed early (as Unix tools killed by SIGPIPE); anything else is a bug (a traceback, exit 1).
"""

from __future__ import annotations

import sys
from typing import Sequence

from mvtex.cli import apps, calibration, data, evaluation, recon, sliding, tsnn, views
from mvtex.cli.common import Parser, UsageError, run_command
from mvtex.util.errors import InputError, one_line

GROUPS = (data, sliding, evaluation, recon, tsnn, views, calibration, apps)


def build_parser() -> Parser:
    """The parser of every command (each group module adds its own)."""
    from mvtex import __version__

    parser = Parser(prog="mvtex", description="Texture sliding for learned cloth: per-camera texture-coordinate "
                    "perturbations, evaluation, multi-view reconstruction, novel views.")
    parser.add_argument("--version", action="version", version=f"mvtex {__version__}",
                        help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=Parser,
                                help="one of these; `mvtex COMMAND --help` lists its options")
    for group in GROUPS:
        group.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command. Returns 0 on success, 2 on bad usage or bad input (one line on
    stderr naming the file and the problem), 130 when interrupted; any other failure is a
    bug and propagates with its traceback (exit 1 from the `mvtex` script)."""
    from mvtex.util.parallel import configure_threads

    configure_threads()
    parser = build_parser()
    try:
        args, extra = parser.parse_known_args(argv)
        command_parser = parser._subparsers._group_actions[0].choices[args.command]
        if extra:
            command_parser.error(f"unrecognized arguments: {' '.join(extra)}")
    except UsageError as err:
        print(one_line(err), file=sys.stderr)
        return 2
    except SystemExit as exit_:  # --help, --version
        return int(exit_.code or 0)
    try:
        run_command(command_parser, args)
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's exit
    except UsageError as err:
        print(one_line(err), file=sys.stderr)
        return 2
    except InputError as err:
        return _fail(args.command, str(err))
    except BrokenPipeError:
        return _closed_pipe()
    except OSError as err:
        # The file system refused a path (permissions, a full disk, a file-size limit, a file
        # where a folder should be): a one-line error naming it, or naming the output being
        # written when the system named no file.
        where = err.filename if err.filename is not None else _output_of(args)
        what = (err.strerror or str(err)) if err.errno else str(err)
        return _fail(args.command, f"{where}: {what}" if where is not None else what)
    except KeyboardInterrupt:
        print(f"mvtex {args.command}: interrupted (rerun the same command to resume where supported)", file=sys.stderr)
        return 130
    return 0


def _closed_pipe() -> int:
    """stdout was closed early (`mvtex eval --json | head`): stop quietly, as Unix tools do
    (status 128 + SIGPIPE), with stdout pointed at /dev/null so that the interpreter's last
    flush cannot complain."""
    import os
    import signal

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):  # stdout replaced by something without a descriptor
        pass
    return 128 + signal.SIGPIPE


def _output_of(args) -> str | None:
    """The output the command was writing (for errors that name no file)."""
    for name in ("out", "heatmaps", "plot"):
        value = getattr(args, name, None)
        if value is not None:
            return str(value)
    return None


def _fail(command: str, message: str) -> int:
    print(f"mvtex {command}: error: {one_line(message)}", file=sys.stderr)
    return 2
