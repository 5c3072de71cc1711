"""The exceptions for bad input: `InputError` names the file and what is wrong with it;
`OptionError` is an argument value a function refuses."""

from __future__ import annotations

import os


class InputError(ValueError):
    """Bad user input. `str(err)` is a one-line message "PATH: problem".

    The CLI turns it into exit code 2; library users can catch it like a ValueError.
    """

    def __init__(self, path: str | os.PathLike | None, problem: str):
        self.path = None if path is None else os.fspath(path)
        self.problem = " ".join(str(problem).split())
        super().__init__(self.problem if self.path is None else f"{self.path}: {self.problem}")

    def __reduce__(self):
        # Rebuilt from (path, problem), not from the formatted message: an error raised in a
        # worker process (`mvtex.util.parallel`) then reaches the command intact.
        return type(self), (self.path, self.problem)


class OptionError(InputError):
    """A bad argument value (an option of a stage, a count, a weight). The message starts
    with the argument's name, "resolution must be a power of two in 8..2048, got 100", so
    that the command line can say which flag it was. It is an `InputError` (exit code 2 from
    the CLI) and therefore a `ValueError`."""

    def __init__(self, problem: str):
        super().__init__(None, problem)

    def __reduce__(self):
        return type(self), (self.problem,)


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
