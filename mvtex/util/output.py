"""Safe output: everything is written under a temporary name beside its target and renamed
when complete (`atomic_path`); an older target is renamed aside before the new one is
renamed in, and deleted only then (`replace_path`). A command's output directory is
claimed with `claim_output`: a directory mvtex's same command did not write is refused
unless overwriting is asked for, one run at a time holds it (an advisory lock), and what is
written there carries a marker file (`MARKER`) naming the command.
"""

from __future__ import annotations

import contextlib
import contextvars
import glob
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

from mvtex.util.errors import InputError

MARKER = ".mvtex-output.json"


# Output directories claimed by `claim_output` in this thread: resolved path -> command.
# `replace_path` puts the marker into a directory before renaming it onto a claimed path,
# so an output never appears without it.
_CLAIMED: contextvars.ContextVar[dict[str, str]] = contextvars.ContextVar("mvtex_claimed_outputs", default={})


def replace_path(source: str | os.PathLike, target: str | os.PathLike) -> None:
    """Move `source` (a file or directory) onto `target`, never deleting first.

    An existing `target` is renamed aside (to a hidden name in its folder), `source` is
    renamed in, and only then is the aside copy deleted; if the rename-in fails the aside
    copy is put back. A kill between the two renames leaves both versions on disk under
    hidden ``.<name>.*.aside`` names, never neither.
    """
    source, target = Path(source), Path(target)
    command = _CLAIMED.get().get(_key(target))
    if command is not None and source.is_dir() and not source.is_symlink():
        _write_marker(source, command)
    if not (target.exists() or target.is_symlink()):
        os.replace(source, target)
        return
    if target.is_dir() and not target.is_symlink() and not source.is_dir():
        raise InputError(target, "is a directory; a file cannot replace it")
    aside_dir = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".aside", dir=target.parent))
    aside = aside_dir / target.name
    os.replace(target, aside)
    try:
        os.replace(source, target)
    except BaseException:
        os.replace(aside, target)
        shutil.rmtree(aside_dir, ignore_errors=True)
        raise
    shutil.rmtree(aside_dir, ignore_errors=True)


def remove_leftovers(directory: str | os.PathLike, name: str) -> None:
    """Delete the hidden folders that `atomic_path` and `replace_path` leave beside
    ``directory/name`` when a process is killed between their renames (``.NAME.*.tmp``,
    ``.NAME.*.aside``). Only for folders mvtex writes (an unfinished set it resumes)."""
    for entry in Path(directory).glob(f".{glob.escape(name)}.*"):
        if entry.is_dir() and not entry.is_symlink() and entry.name.endswith((".tmp", ".aside")):
            shutil.rmtree(entry, ignore_errors=True)


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
    is left as it was; on success an older `path` is replaced by `replace_path` (renamed
    aside, the new one renamed in, then the old one deleted).
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    except OSError as err:
        raise InputError(path, f"cannot write here ({err.strerror or err})") from None
    target = tmp / path.name
    try:
        yield target
        if target.is_file() and not target.is_symlink():
            readable(target)
        replace_path(target, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _key(path: Path) -> str:
    return os.path.normcase(os.path.abspath(path))


def _write_marker(directory: Path, command: str) -> None:
    from mvtex import __version__

    text = json.dumps({"command": command, "mvtex": __version__}) + "\n"
    tmp = directory / (MARKER + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, directory / MARKER)


def output_owner(path: str | os.PathLike) -> str | None:
    """The mvtex command recorded in a directory's marker file, or None."""
    try:
        marker = json.loads((Path(path) / MARKER).read_text())
    except (OSError, ValueError):
        return None
    return marker.get("command") if isinstance(marker, dict) and isinstance(marker.get("command"), str) else None


def check_output(path: str | os.PathLike, command: str, *, overwrite: bool = False) -> Path:
    """Refuse an output path whose current content `command` may not replace.

    Allowed: a path that does not exist, an empty directory, a directory whose marker
    says `command` wrote it, or any directory with `overwrite`. Refused (InputError): an
    existing file or link, and without `overwrite` a non-empty directory mvtex's
    `command` did not write.
    """
    path = Path(path)
    if path.is_symlink():  # replacing it would replace the link, not what it points to
        raise InputError(path, "is a symbolic link; give the real output path")
    if path.exists() and not path.is_dir():
        raise InputError(path, "exists and is not a directory; choose another output path")
    if path.is_dir() and not overwrite:
        owner = output_owner(path)
        if owner != command and any(path.iterdir()):
            what = f"the output of `mvtex {owner}`" if owner else "a directory mvtex did not write"
            raise InputError(path, f"exists and is {what}; its content would be replaced: choose another "
                             "output path or pass --overwrite")
    return path


@contextlib.contextmanager
def claim_output(path: str | os.PathLike, command: str, *, overwrite: bool = False,
                 in_place: bool = False) -> Iterator[Path]:
    """Hold an output directory for one run of `command`.

    Checks the path with `check_output`, then takes an advisory lock (`fcntl.flock` on a
    hidden ``.<name>.lock`` file beside it: a second run on the same output fails at once
    with "in use by pid N"), and marks what is written there as `command`'s output
    (``.mvtex-output.json``) so a later run of the same command may replace or resume it.

    Args:
        path: the output directory.
        command: the mvtex command writing it ("slide", "synth", ...).
        overwrite: allow replacing a directory that is not `command`'s output.
        in_place: the command writes files into the directory (render, demo) instead of
            renaming a finished directory onto it: create it and mark it now.

    Raises:
        InputError: a file there, someone else's directory, an unwritable place, or
            another run holding the lock.
    """
    path = check_output(path, command, overwrite=overwrite)
    with _new_folders(path.parent, path), _locked(path, command):
        if not os.access(path.parent, os.W_OK | os.X_OK):
            raise InputError(path, f"{path.parent} is not writable")
        path = check_output(path, command, overwrite=overwrite)  # may have changed while waiting
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
def claim_file(path: str | os.PathLike, command: str, *, overwrite: bool = False,
               inputs: tuple[str | os.PathLike | None, ...] = ()) -> Iterator[Path]:
    """Hold an output *file* (a rig YAML, a PNG) for one run of `command`.

    A file carries no marker, and a user's file of the same name (last week's calibration,
    a photo) may be indistinguishable from one mvtex wrote, so an existing file is replaced
    only with `overwrite`; one of `inputs` (the same file) never, since the input would be
    gone before the output is made. A link or a directory there is refused. The file's
    folder is created; one run at a time holds the path (as `claim_output`); the caller
    writes the file through `atomic_path`, so it appears whole or not at all.

    Raises:
        InputError: as said above, naming the path.
    """
    path = Path(path)
    if path.is_symlink():
        raise InputError(path, "is a symbolic link; give the real output path")
    if path.is_dir():
        raise InputError(path, "is a directory; give a file name")
    for source in inputs:
        if source is not None and path.exists() and Path(source).exists() and os.path.samefile(path, source):
            raise InputError(path, "is also an input of this command; write the output to another file")
    if path.exists() and not overwrite:
        raise InputError(path, "exists; choose another output file or pass --overwrite to replace it")
    with _new_folders(path.parent, path), _locked(path, command):
        if path.exists() and not overwrite:  # made while we waited for the lock
            raise InputError(path, "exists; choose another output file or pass --overwrite to replace it")
        remove_leftovers(path.parent, path.name)
        yield path


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

    lock = path.with_name(f".{path.name}.lock")
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
