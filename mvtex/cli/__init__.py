"""The `mvtex` command line: one module per command group, each only parsing arguments and
calling the library functions that Python users call too (`mvtex.slide_dataset`, ...).

Exit codes: 0 success; 2 bad usage or bad input, with one line on stderr naming the file or
flag and the problem; 130 interrupted; anything else is a bug (a traceback, exit 1).
"""

from __future__ import annotations

import sys
from typing import Sequence

from mvtex.cli import apps, calibration, data, evaluation, recon, sliding, tsnn, views
from mvtex.cli.common import Parser, UsageError, run_command
from mvtex.util.errors import InputError

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
        print(str(err), file=sys.stderr)
        return 2
    except SystemExit as exit_:  # --help, --version
        return int(exit_.code or 0)
    try:
        run_command(command_parser, args)
    except UsageError as err:
        print(str(err), file=sys.stderr)
        return 2
    except InputError as err:
        return _fail(args.command, str(err))
    except OSError as err:
        # The file system refused a user's path (permissions, a full disk, a file where a
        # folder should be): a one-line error, not a bug. Other OSErrors carry no filename.
        if err.filename is None:
            raise
        return _fail(args.command, InputError(err.filename, err.strerror or str(err)).args[0])
    except BrokenPipeError:  # stdout closed early (`mvtex ... | head`): nothing left to say
        sys.stderr.close()
        return 1
    except KeyboardInterrupt:
        print(f"mvtex {args.command}: interrupted (rerun the same command to resume where supported)", file=sys.stderr)
        return 130
    return 0


def _fail(command: str, message: str) -> int:
    print(f"mvtex {command}: error: {message}", file=sys.stderr)
    return 2
