"""The one exception type for bad input: it names the file and what is wrong with it."""

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
