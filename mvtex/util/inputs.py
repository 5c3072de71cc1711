"""Never write into an input: what a writer reads (`input_paths`) and the check that keeps
an output out of it, off it and from around it (`check_inputs`), and out of the current
directory (`check_place`).

Paths are compared twice: as text with symbolic links resolved, and by device and inode
(`os.stat`), so neither a link, a bind mount of an input nor a hard link to one hides it.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable

import numpy as np

from mvtex.util.errors import InputError
from mvtex.util.manifest import identity

Inputs = Iterable["str | os.PathLike | None"]


def _inside(real: str, folder: str) -> bool:
    return real.startswith(folder.rstrip(os.sep) + os.sep)


def check_place(path: Path) -> None:
    """Refuse the file system's root, the current directory and the folders above it: a
    new output cannot be renamed onto them."""
    real = os.path.realpath(path)
    cwd = os.path.realpath(os.getcwd())
    if real == os.path.dirname(real):
        raise InputError(path, "is the root of the file system; give a folder below it")
    if cwd == real or _inside(cwd, real) or identity(path) in (identity(cwd), *ancestor_ids(cwd)):
        raise InputError(path, "is the current directory or a folder above it; give a new folder below it "
                         "(for example --out result)")


def ancestor_ids(real: str) -> set[tuple[int, int]]:
    """(device, inode) of every folder above `real` (an absolute path, links resolved)."""
    return {i for i in (identity(p) for p in Path(real).parents) if i is not None}


def check_inputs(out: str | os.PathLike, inputs: Inputs) -> None:
    """Refuse an output that is one of `inputs`, lies inside one or contains one: writing
    it would change or replace that input. Paths are compared with symbolic links resolved
    and by device and inode, so neither a link nor a bind mount nor a hard link hides an
    input.

    Raises:
        InputError: naming the output and the input.
    """
    out_real = os.path.realpath(out)
    out_id = identity(out)
    above_out = None
    for source in inputs:
        if source is None:
            continue
        real, source_id, name = os.path.realpath(source), identity(source), os.fspath(source)
        if real == out_real or (out_id is not None and out_id == source_id):
            raise InputError(out, f"is also an input of this command ({name}); write the output somewhere else")
        if _inside(real, out_real) or (out_id is not None and out_id in ancestor_ids(real)):
            raise InputError(out, f"contains the input {name}; writing the output there would replace it: "
                             "choose another output path")
        if above_out is None:
            above_out = ancestor_ids(out_real)
        if _inside(out_real, real) or (source_id is not None and source_id in above_out):
            raise InputError(out, f"lies inside the input {name}; write the output outside it")


def array_files(*arrays) -> list[str]:
    """The files that memory-mapped arrays among `arrays` read (inputs of a writer)."""

    files = []
    for array in arrays:
        while array is not None:
            if isinstance(array, np.memmap) and getattr(array, "filename", None):
                files.append(array.filename)
                break
            array = getattr(array, "base", None)
    return files


def input_paths(*sources) -> list[str]:
    """The files and folders behind a writer's inputs: paths that exist, `.path` of opened
    datasets, texcoord sets and models, the files of memory-mapped arrays; lists are
    walked, anything else (a `Rig` object, a built-in rig's name) is skipped."""

    out: list[str] = []
    for source in sources:
        if source is None:
            continue
        if isinstance(source, (str, os.PathLike)):
            if os.path.lexists(source):
                out.append(os.fspath(source))
        elif isinstance(source, np.ndarray):
            out.extend(array_files(source))
        elif isinstance(source, (list, tuple, set)):
            out.extend(input_paths(*source))
        elif isinstance(source, dict):
            out.extend(input_paths(*source.values()))
        elif isinstance(getattr(source, "path", None), (str, os.PathLike)):
            out.append(os.fspath(source.path))
        elif isinstance(getattr(source, "source", None), (str, os.PathLike)):  # a Rig read from a file
            out.extend(input_paths(source.source))
    return out


