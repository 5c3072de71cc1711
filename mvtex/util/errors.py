"""The exceptions for bad input: `InputError` names the file and what is wrong with it;
`OptionError` is an argument value a function refuses."""

from __future__ import annotations

import os
import unicodedata


def one_line(text: str) -> str:
    """`text` with every control or line-breaking character written as its escape
    ("a\\nb"), so that a file name holding a newline cannot split a one-line message."""
    return "".join(c if c == " " or c.isprintable() or unicodedata.category(c) not in ("Cc", "Zl", "Zp", "Cs")
                   else c.encode("unicode_escape", "backslashreplace").decode("ascii") for c in str(text))


class InputError(ValueError):
    """Bad user input. `str(err)` is a one-line message "PATH: problem" (control characters in
    PATH escaped, white space in the problem folded).

    The CLI turns it into exit code 2; library users can catch it like a ValueError.
    """

    def __init__(self, path: str | os.PathLike | None, problem: str):
        self.path = None if path is None else os.fspath(path)
        self.problem = one_line(" ".join(str(problem).split()))
        shown = None if self.path is None else one_line(os.fsdecode(self.path))
        super().__init__(self.problem if shown is None else f"{shown}: {self.problem}")

    def __reduce__(self):
        # Rebuilt from (path, problem), not from the formatted message: an error raised in a
        # worker process (`mvtex.util.parallel`) then reaches the command intact.
        return type(self), (self.path, self.problem)


class OptionError(InputError):
    """A bad argument value (an option of a stage, a count, a weight).

    `OptionError("resolution", "must be a power of two in 8..2048, got 100")`: `argument`
    names the argument (a field of an options class, a parameter of a function) and
    `detail` says what is wrong with it; `str(err)` joins them, "resolution must be ...".
    The command line reports it in the words of the flag that sets the argument
    ("--resolution must be ..."). It is an `InputError` (exit code 2 from the CLI) and
    therefore a `ValueError`.

    Attributes:
        argument: the argument's name, or None for a problem of several arguments together.
        detail: the problem, without the argument's name.
    """

    def __init__(self, argument: str | None, detail: str):
        self.argument = argument
        self.detail = " ".join(str(detail).split())
        super().__init__(None, self.detail if argument is None else f"{argument} {self.detail}")

    def __reduce__(self):
        return type(self), (self.argument, self.detail)


class OutputError(InputError):
    """An output that cannot be written: the disk is full, a file-size limit is reached, the
    place is read-only. `str(err)` is "OUTPUT: cannot write it (No space left on device)",
    naming the output being written even when the operating system named no file. Nothing
    is left half-written: the temporaries are removed (a resumable run keeps its
    ``OUT.partial``). It is an `InputError` (exit code 2 from the CLI)."""


class NoGroundTruthError(InputError):
    """What needs the ground-truth cloth, asked of a dataset that has none (an inference set,
    DESIGN §4): `str(err)` is "DATASET: an inference set, no ground truth (gt.npy): slide
    needs the ground-truth cloth". It is an `InputError` (exit code 2 from the CLI)."""
