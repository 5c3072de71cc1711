"""The writer policy: how mvtex writes, and what it never touches.

Every public function that writes (the library's and hence every command's) goes through
this module:

- **Claims.** An output folder is claimed with `claim_output`, a single output file with
  `claim_file`. A claim checks the place (`check_output`), holds it for one run (an
  advisory lock on a hidden ``.NAME.mvtex-lock`` beside it) and turns a failed write
  (a full disk, a file-size limit: an `OSError` often without a file name) into an
  `OutputError` naming the output. Claims nest: a writer called inside a claim of the same
  path (the command line claims, then calls the library writer) adds only its own checks.
- **Never remove what mvtex did not write.** Every folder mvtex writes carries a manifest,
  ``.mvtex-output.json``: the command and every file and folder it wrote there. A folder
  is replaced only when everything in it is listed there (or it is empty); a folder holding
  anything else (a user's notes added after the run, a folder mvtex never wrote) is refused,
  with `overwrite` too. `overwrite` only lets one command replace another command's output.
- **Never write into an input.** An output equal to an input, inside one, or containing
  one (symbolic links resolved) is refused; so is the current directory or a folder above it.
- **Replacing is never delete-then-write.** Everything is written under a temporary name
  beside its target and renamed when complete (`atomic_path`); an older target is renamed
  aside, the new one renamed in, and the old one deleted only then (`replace_path`).
- **Temporaries are unmistakably mvtex's.** They are named ``.NAME.mvtex-XXXX.tmp`` /
  ``.aside`` and hold a stamp file (``.mvtex-temporary``); only folders with both are ever
  cleaned up (`remove_leftovers`).

docs/safety.md says the same for users.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import glob
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, ParamSpec, TypeVar

from mvtex.util.errors import InputError, OptionError, OutputError

MARKER = ".mvtex-output.json"
"""The manifest in every output folder: {"command", "mvtex", "files": [relative paths]}."""

TEMP_STAMP = ".mvtex-temporary"
"""The stamp file inside every temporary folder mvtex makes (``.NAME.mvtex-XXXX.tmp``)."""

_TAG = "mvtex-"
_LOCK_SUFFIX = ".mvtex-lock"

Inputs = Iterable["str | os.PathLike | None"]


# Paths claimed by `claim_output` / `claim_file` in this thread: key -> command.
# `replace_path` writes the manifest into a directory before renaming it onto a claimed
# path, so an output never appears without it, and records what it renames into a claimed
# folder that is written in place.
_CLAIMED: contextvars.ContextVar[dict[str, str]] = contextvars.ContextVar("mvtex_claimed_outputs", default={})


def _key(path: str | os.PathLike) -> str:
    return os.path.normcase(os.path.realpath(path))


# -- temporaries -------------------------------------------------------------------------------

def _temporary(target: Path, kind: str) -> Path:
    """A new hidden folder beside `target`, ``.NAME.mvtex-XXXX.<kind>``, stamped as mvtex's."""
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.{_TAG}", suffix=f".{kind}", dir=target.parent))
    try:
        (tmp / TEMP_STAMP).write_text(json.dumps({"temporary_for": target.name, "pid": os.getpid()}) + "\n")
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return tmp


def is_temporary(entry: str | os.PathLike, name: str | None = None) -> bool:
    """Whether `entry` is a temporary folder mvtex made (for ``name``, if given): named
    ``.NAME.mvtex-XXXX.tmp`` or ``.aside``, a real folder, holding mvtex's stamp file."""
    entry = Path(entry)
    prefix = f".{name}.{_TAG}" if name is not None else "."
    return (entry.name.startswith(prefix) and f".{_TAG}" in entry.name and entry.name.endswith((".tmp", ".aside"))
            and entry.is_dir() and not entry.is_symlink() and (entry / TEMP_STAMP).is_file())


def remove_leftovers(directory: str | os.PathLike, name: str) -> None:
    """Delete the temporaries that `atomic_path` and `replace_path` leave beside
    ``directory/name`` when a process is killed between their renames. Only folders that
    `is_temporary` recognises as mvtex's (name *and* stamp) are touched."""
    for entry in Path(directory).glob(f".{glob.escape(name)}.{_TAG}*"):
        if is_temporary(entry, name):
            shutil.rmtree(entry, ignore_errors=True)


# -- manifests -----------------------------------------------------------------------------------

def _entries(directory: Path) -> list[str]:
    """Every file, link and folder under `directory` (links not followed), as relative POSIX
    paths, less the manifest itself and mvtex's own transients (lock files and stamped
    temporaries of a run that was killed inside it)."""
    out = []
    for root, dirs, files in os.walk(directory):
        rel = Path(root).relative_to(directory)
        dirs[:] = [d for d in dirs if not is_temporary(Path(root) / d)]
        for name in dirs + files:
            entry = (rel / name).as_posix()
            if name != MARKER and not (name.startswith(".") and name.endswith((_LOCK_SUFFIX, MARKER + ".tmp"))):
                out.append(entry)
    return sorted(out)


def clear_output(path: str | os.PathLike) -> None:
    """Delete what an output folder's manifest lists, when that is all it holds (a run
    written in place that starts over). Refuses (InputError) a folder holding anything else."""
    path = Path(path)
    foreign = foreign_entries(path)
    if foreign:
        raise InputError(path, _foreign_message(path, foreign))
    for entry in path.iterdir():
        if entry.name == MARKER:
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()


def _read_marker(path: Path) -> dict | None:
    try:
        marker = json.loads((path / MARKER).read_text())
    except (OSError, ValueError):
        return None
    return marker if isinstance(marker, dict) else None


def output_owner(path: str | os.PathLike) -> str | None:
    """The mvtex command recorded in a folder's manifest, or None."""
    marker = _read_marker(Path(path))
    command = marker.get("command") if marker else None
    return command if isinstance(command, str) else None


def written_by_mvtex(path: str | os.PathLike) -> set[str] | None:
    """The entries (relative POSIX paths) a folder's manifest lists, or None without one."""
    marker = _read_marker(Path(path))
    files = marker.get("files") if marker else None
    if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
        return None
    return set(files)


def foreign_entries(path: str | os.PathLike) -> list[str]:
    """What is in folder `path` that mvtex did not write: entries its manifest does not
    list (all of them without a manifest). A folder inside a claimed output that is
    written in place is judged by that output's manifest."""
    path = Path(path)
    listed = written_by_mvtex(path)
    prefix = ""
    if listed is None:
        root = _claimed_root(path)
        if root is not None:
            listed = written_by_mvtex(root)
            prefix = Path(os.path.relpath(os.path.realpath(path), os.path.realpath(root))).as_posix() + "/"
    listed = listed or set()
    return [e for e in _entries(path) if prefix + e not in listed]


def _write_marker(directory: Path, command: str) -> None:
    """Write the manifest of `directory`: `command` wrote everything in it now."""
    from mvtex import __version__

    text = json.dumps({"command": command, "mvtex": __version__, "files": _entries(directory)}) + "\n"
    tmp = directory / (MARKER + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, directory / MARKER)


def _claimed_root(path: Path) -> Path | None:
    """The nearest claimed folder, with a manifest, that strictly contains `path`."""
    real = os.path.realpath(path)
    best = None
    for key in _CLAIMED.get():
        if real != key and real.startswith(key.rstrip(os.sep) + os.sep) and (Path(key) / MARKER).is_file():
            if best is None or len(key) > len(best):
                best = key
    return Path(best) if best is not None else None


def _record(target: Path) -> None:
    """Add `target` (and what it holds, and the folders between) to the manifest of the
    claimed folder it was written into in place."""
    root = _claimed_root(target)
    if root is None:
        return
    marker = _read_marker(root) or {}
    files = set(marker.get("files") or [])
    rel = Path(os.path.relpath(os.path.realpath(target), root))
    files.update(p.as_posix() for p in list(rel.parents)[:-1])
    files.add(rel.as_posix())
    if target.is_dir() and not target.is_symlink():
        files.update((rel / e).as_posix() for e in _entries(target))
    marker["files"] = sorted(files)
    tmp = root / (MARKER + ".tmp")
    tmp.write_text(json.dumps(marker) + "\n")
    os.replace(tmp, root / MARKER)


def forget(root: str | os.PathLike, entries: Iterable[str]) -> None:
    """Drop `entries` (relative POSIX paths mvtex deleted) from folder `root`'s manifest."""
    root = Path(root)
    marker = _read_marker(root)
    if not marker or not isinstance(marker.get("files"), list):
        return
    gone = set(entries)
    marker["files"] = [f for f in marker["files"] if f not in gone]
    tmp = root / (MARKER + ".tmp")
    tmp.write_text(json.dumps(marker) + "\n")
    os.replace(tmp, root / MARKER)


# -- writing ----------------------------------------------------------------------------------

def _check_replaceable(target: Path) -> None:
    """Refuse to replace folder `target` when that would delete something mvtex did not
    write. (A single file is the claim's business: `claim_file` asks for `overwrite`.)"""
    if target.is_symlink() or not target.exists():
        return
    if target.is_dir():
        foreign = foreign_entries(target)
        if foreign:
            raise InputError(target, _foreign_message(target, foreign))
        return


def _foreign_message(path: Path, foreign: list[str]) -> str:
    if (path / MARKER).is_file() and written_by_mvtex(path) is None:
        return ("was written by an older mvtex that kept no list of its files, and mvtex replaces only what it "
                "knows it wrote: move it away or choose another output path")
    shown = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
    return (f"holds files mvtex did not write ({shown}); mvtex never deletes them, even with --overwrite: "
            "move them away or choose another output path")


def replace_path(source: str | os.PathLike, target: str | os.PathLike) -> None:
    """Move `source` (a file or directory) onto `target`, never deleting first, and never
    deleting what mvtex did not write.

    An existing folder `target` must be replaceable: its manifest (or that of the claimed
    output it lies in) lists all it holds, or it is empty (InputError otherwise). It is
    renamed aside (to a hidden, stamped
    ``.<name>.mvtex-*.aside`` folder), `source` is renamed in, and only then is the aside
    copy deleted; if the rename-in fails the aside copy is put back. A kill between the two
    renames leaves both versions on disk, never neither.
    """
    source, target = Path(source), Path(target)
    command = _CLAIMED.get().get(_key(target))
    if command is not None and source.is_dir() and not source.is_symlink():
        _write_marker(source, command)
    if not (target.exists() or target.is_symlink()):
        os.replace(source, target)
        _record(target)
        return
    if target.is_dir() and not target.is_symlink() and not source.is_dir():
        raise InputError(target, "is a directory; a file cannot replace it")
    _check_replaceable(target)
    aside_dir = _temporary(target, "aside")
    aside = aside_dir / target.name
    os.replace(target, aside)
    try:
        os.replace(source, target)
    except BaseException:
        os.replace(aside, target)
        shutil.rmtree(aside_dir, ignore_errors=True)
        raise
    shutil.rmtree(aside_dir, ignore_errors=True)
    _record(target)


def readable(path: str | os.PathLike) -> None:
    """Give a file the permissions of any file this process creates (0666 less the umask),
    where a library wrote it private (safetensors writes 0600)."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; move it onto `path` on success.

    Works for files and directories. On an exception the temporary is removed and `path`
    is left as it was; on success an older `path` is replaced by `replace_path` (which
    refuses to delete what mvtex did not write).
    """
    path = Path(os.path.abspath(path))
    _check_place(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = _temporary(path, "tmp")
    except OSError as err:
        raise OutputError(path, f"cannot write here ({err.strerror or err})") from None
    target = tmp / path.name
    try:
        yield target
        if target.is_file() and not target.is_symlink():
            readable(target)
        replace_path(target, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# -- claims -----------------------------------------------------------------------------------

def _check_place(path: Path) -> None:
    """Refuse the file system's root, the current directory and the folders above it: a
    new output cannot be renamed onto them."""
    real = os.path.realpath(path)
    cwd = os.path.realpath(os.getcwd())
    if real == os.path.dirname(real):
        raise InputError(path, "is the root of the file system; give a folder below it")
    if cwd == real or cwd.startswith(real.rstrip(os.sep) + os.sep):
        raise InputError(path, "is the current directory or a folder above it; give a new folder below it "
                         "(for example --out result)")


def check_inputs(out: str | os.PathLike, inputs: Inputs) -> None:
    """Refuse an output that is one of `inputs`, lies inside one or contains one (symbolic
    links resolved): writing it would change or replace that input.

    Raises:
        InputError: naming the output and the input.
    """
    out_real = os.path.realpath(out)
    for source in inputs:
        if source is None:
            continue
        real = os.path.realpath(source)
        if real == out_real:
            raise InputError(out, f"is also an input of this command ({os.fspath(source)}); write the output "
                             "somewhere else")
        if real.startswith(out_real.rstrip(os.sep) + os.sep):
            raise InputError(out, f"contains the input {os.fspath(source)}; writing the output there would "
                             "replace it: choose another output path")
        if out_real.startswith(real.rstrip(os.sep) + os.sep):
            raise InputError(out, f"lies inside the input {os.fspath(source)}; write the output outside it")


def array_files(*arrays) -> list[str]:
    """The files that memory-mapped arrays among `arrays` read (inputs of a writer)."""
    import numpy as np

    files = []
    for array in arrays:
        while array is not None:
            if isinstance(array, np.memmap) and getattr(array, "filename", None):
                files.append(array.filename)
                break
            array = getattr(array, "base", None)
    return files


def check_output(path: str | os.PathLike, command: str, *, overwrite: bool = False, inputs: Inputs = ()) -> Path:
    """Refuse an output folder that `command` may not write.

    Allowed: a path that does not exist, an empty folder, a folder whose manifest says
    `command` wrote all it holds, and with `overwrite` a folder another mvtex command
    wrote all of. Refused (InputError): an existing file or link; a folder holding
    anything mvtex did not write (with `overwrite` too); the current directory or one
    above it; an output that is, contains or lies inside one of `inputs`.
    """
    path = Path(path)
    if path.is_symlink():  # replacing it would replace the link, not what it points to
        raise InputError(path, "is a symbolic link; give the real output path")
    if path.exists() and not path.is_dir():
        raise InputError(path, "exists and is not a directory; choose another output path")
    _check_place(path)
    check_inputs(path, inputs)
    if path.is_dir():
        foreign = foreign_entries(path)
        if foreign:
            raise InputError(path, _foreign_message(path, foreign))
        owner = output_owner(path)
        if not overwrite and owner != command and any(p.name != MARKER for p in path.iterdir()):
            raise InputError(path, f"exists and is the output of `mvtex {owner}`; its content would be replaced: "
                             "choose another output path or pass --overwrite")
    return path


@contextlib.contextmanager
def _output_errors(path: Path) -> Iterator[None]:
    """Turn a failed write (ENOSPC, EFBIG, EDQUOT, EROFS, EIO: often with no file name)
    into an `OutputError` naming the output being written."""
    try:
        yield
    except OutputError:
        raise
    except OSError as err:
        if isinstance(err, BrokenPipeError):
            raise
        if not (err.filename is None or _concerns(path, err.filename) or err.errno in _DISK_ERRORS):
            raise
        what = (err.strerror or os.strerror(err.errno)) if err.errno else str(err)
        raise OutputError(path, f"cannot write it ({what})") from err


_DISK_ERRORS = (errno.ENOSPC, errno.EFBIG, errno.EDQUOT, errno.EROFS, errno.EIO)


def _concerns(output: Path, filename) -> bool:
    """Whether `filename` is the output, inside it, or a temporary beside it."""
    try:
        real, out = os.path.realpath(os.fsdecode(filename)), os.path.realpath(output)
    except (TypeError, ValueError):
        return False
    return real == out or real.startswith(out + os.sep) or \
        os.path.basename(real).startswith(f".{os.path.basename(out)}.")


@contextlib.contextmanager
def claim_output(path: str | os.PathLike, command: str, *, overwrite: bool = False, in_place: bool = False,
                 inputs: Inputs = ()) -> Iterator[Path]:
    """Hold an output folder for one run of `command` (the writer policy, module docstring).

    Checks the path with `check_output`, takes an advisory lock (`fcntl.flock` on a hidden
    ``.<name>.mvtex-lock`` beside it: a second run on the same output fails at once with
    "in use by pid N"), removes mvtex's own temporaries of an earlier killed run, and makes
    what is renamed onto the path carry the manifest. A write that fails for lack of space
    (or any `OSError` about the output) becomes an `OutputError` naming it. Inside a claim
    of the same path (the command line's), only the checks run.

    Args:
        path: the output folder.
        command: the mvtex command writing it ("slide", "synth", ...).
        overwrite: allow replacing another mvtex command's output (never a user's files).
        in_place: the command writes files into the folder (demo, `train --cameras a,b`)
            instead of renaming a finished folder onto it: create it and mark it now; every
            file written there through `atomic_path` is added to its manifest.
        inputs: the files and folders the run reads (dataset, texcoord set, models, rig).

    Raises:
        InputError: a file there, a folder holding what mvtex did not write, someone else's
            output without `overwrite`, an input in the way, an unwritable place, or
            another run holding the lock.
    """
    path = Path(path)
    if _key(path) in _CLAIMED.get():
        check_inputs(path, inputs)
        with _output_errors(path):
            yield path
        return
    path = check_output(path, command, overwrite=overwrite, inputs=inputs)
    with _new_folders(path.parent, path), _locked(path, command), _output_errors(path):
        if not os.access(path.parent, os.W_OK | os.X_OK):
            raise InputError(path, f"{path.parent} is not writable")
        path = check_output(path, command, overwrite=overwrite, inputs=inputs)  # may have changed while waiting
        remove_leftovers(path.parent, path.name)  # of a run of this command that was killed
        created = False
        if in_place:
            try:
                created = not path.is_dir()
                path.mkdir(exist_ok=True)
            except OSError as err:
                raise InputError(path, f"cannot create ({err.strerror or err})") from None
            _write_marker(path, command)
        claims = dict(_CLAIMED.get())
        claims[_key(path)] = command
        token = _CLAIMED.set(claims)
        try:
            yield path
        except BaseException:
            if created and [p.name for p in path.iterdir()] == [MARKER]:  # nothing written: leave no trace
                (path / MARKER).unlink()
                path.rmdir()
            raise
        finally:
            _CLAIMED.reset(token)


@contextlib.contextmanager
def claim_file(path: str | os.PathLike, command: str, *, overwrite: bool = False, inputs: Inputs = ()) -> Iterator[Path]:
    """Hold an output *file* (a rig YAML, a PNG) for one run of `command`.

    A file carries no manifest, and a user's file of the same name (last week's
    calibration, a photo) may be indistinguishable from one mvtex wrote, so an existing file
    is replaced only with `overwrite`; one of `inputs` (the same file) never, since the
    input would be gone before the output is made. A file inside a claimed output folder is
    that folder's business (its manifest decides). A link or a directory there is refused.
    The file's folder is created; one run at a time holds the path (as `claim_output`); the
    caller writes the file through `atomic_path`, so it appears whole or not at all.

    Raises:
        InputError: as said above, naming the path.
    """
    path = Path(path)
    if path.is_symlink():
        raise InputError(path, "is a symbolic link; give the real output path")
    if path.is_dir():
        raise InputError(path, "is a directory; give a file name")
    for source in inputs:  # a new file beside an input's files changes none of them: only the same file
        if source is not None and os.path.realpath(source) == os.path.realpath(path):
            raise InputError(path, f"is also an input of this command ({os.fspath(source)}); write the output "
                             "to another file")
    if _key(path) in _CLAIMED.get() or _claimed_root(path) is not None:
        with _output_errors(path):
            yield path
        return
    _check_place(path)
    if path.exists() and not overwrite:
        raise InputError(path, "exists; choose another output file or pass --overwrite to replace it")
    with _new_folders(path.parent, path), _locked(path, command), _output_errors(path):
        if path.exists() and not overwrite:  # made while we waited for the lock
            raise InputError(path, "exists; choose another output file or pass --overwrite to replace it")
        remove_leftovers(path.parent, path.name)
        claims = dict(_CLAIMED.get())
        claims[_key(path)] = command
        token = _CLAIMED.set(claims)
        try:
            yield path
        finally:
            _CLAIMED.reset(token)


@contextlib.contextmanager
def _new_folders(folder: Path, output: Path) -> Iterator[None]:
    """Create `folder` and its missing parents; remove the ones made here, if still empty,
    when the block fails (a refused or failed run leaves no trace). Errors name `output`."""
    missing = []
    probe = Path(folder)
    while not probe.exists() and probe != probe.parent:
        missing.append(probe)
        probe = probe.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(output, f"cannot create its folder ({err.strerror or err})") from None
    try:
        yield
    except BaseException:
        for made in missing:  # deepest first
            try:
                made.rmdir()
            except OSError:
                break
        raise


@contextlib.contextmanager
def _locked(path: Path, command: str) -> Iterator[None]:
    import fcntl

    lock = path.with_name(f".{path.name}{_LOCK_SUFFIX}")
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            raise InputError(path, f"cannot create the lock file {lock.name} ({err.strerror or err})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                pid = os.read(fd, 32).decode(errors="replace").strip() or "?"
            finally:
                os.close(fd)
            raise InputError(path, f"in use by pid {pid} (another mvtex run writes it; wait for it to finish)") \
                from None
        # The holder before us may have deleted the lock file after we opened it: then our
        # lock is on an orphaned inode and a third run could lock a new file. Retry.
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(lock))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        yield
    finally:
        try:
            os.unlink(lock)  # still holding the lock: nobody else can be between open and check
        except OSError:
            pass
        os.close(fd)


def input_paths(*sources) -> list[str]:
    """The files and folders behind a writer's inputs: paths that exist, `.path` of opened
    datasets, texcoord sets and models, the files of memory-mapped arrays; lists are
    walked, the file a `Rig` was read from is one; anything else (a rig made in code, a
    built-in rig's name) is skipped."""
    import numpy as np

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


_P = ParamSpec("_P")
_R = TypeVar("_R")


def writer(command: str, *, out: str = "out", inputs: Callable[[Mapping[str, Any]], Any] | None = None,
           in_place: bool = False, file: bool = False) -> Callable[[Callable[_P, _R]], Callable[_P, _R]]:
    """Make a public function that writes `out` go through the writer policy.

    The decorated function takes an `overwrite` argument (default False) and its output
    argument `out`; the call runs inside `claim_output` (`claim_file` with `file`) of that
    path for `command`, with the inputs that `inputs(arguments)` names (see `input_paths`).
    An output of None (nothing to write) is no claim.
    """
    import functools
    import inspect

    def wrap(function: Callable[_P, _R]) -> Callable[_P, _R]:
        signature = inspect.signature(function)
        if "overwrite" not in signature.parameters:
            raise TypeError(f"{function.__qualname__} must take an overwrite argument")

        @functools.wraps(function)
        def run(*args: _P.args, **kwargs: _P.kwargs) -> _R:
            bound = signature.bind(*args, **kwargs)
            bound.apply_defaults()
            arguments = bound.arguments
            path = arguments[out]
            if path is None:
                return function(*args, **kwargs)
            if not isinstance(path, (str, os.PathLike)):
                raise OptionError(out, f"must be a path, got {type(path).__name__}")
            sources = input_paths(inputs(arguments)) if inputs is not None else []
            overwrite = bool(arguments.get("overwrite", False))
            if file:
                claim = claim_file(path, command, overwrite=overwrite, inputs=sources)
            else:
                claim = claim_output(path, command, overwrite=overwrite, in_place=in_place, inputs=sources)
            with claim:
                return function(*args, **kwargs)

        return run

    return wrap


def mark_output(directory: str | os.PathLike, command: str) -> None:
    """Write the manifest of a folder mvtex has just made whole (all it holds is `command`'s)."""
    _write_marker(Path(directory), command)
