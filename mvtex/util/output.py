"""The writer policy: how mvtex writes, and what it never touches.

Every public function that writes (the library's and hence every command's) goes through
this module:

- **Claims.** An output folder is claimed with `claim_output`, a single output file with
  `claim_file`. A claim checks the place (`check_output`), holds it for one run (an
  advisory lock on a hidden ``.NAME.mvtex-lock`` beside it, `mvtex.util.lock`) and turns a
  failed write (a full disk, a file-size limit: an `OSError` often without a file name) into
  an `OutputError` naming the output. Claims nest: a writer called inside a claim of the
  same path (the command line claims, then calls the library writer) adds only its own
  checks, and a writer inside a claim made with `overwrite` inherits it.
- **Never remove what mvtex did not write.** Every folder mvtex writes carries a manifest,
  ``.mvtex-output.json`` (`mvtex.util.manifest`): the command and every file and folder it
  wrote there. A folder is replaced only when everything in it is listed there (or it is
  empty); a folder holding anything else (a user's notes added after the run, a link, a
  mount point, a folder mvtex never wrote) is refused, with `overwrite` too. `overwrite`
  only lets one command replace another command's output. A manifest, a lock, a stamp is
  trusted only as a regular file (never through a link) holding what mvtex writes there.
- **Never write into an input.** An output equal to an input, inside one, or containing
  one is refused, compared by path (symbolic links resolved) and by device and inode (a
  bind mount, a hard link); so is the current directory or a folder above it.
- **Replacing is never delete-then-write.** Everything is written under a temporary name
  beside its target and renamed when complete (`atomic_path`); an older target is renamed
  aside, the new one renamed in, and the old one deleted only then (`replace_path`). What
  is renamed into a folder written in place is listed in its manifest *before* the rename,
  so a kill never leaves mvtex's own files unlisted.
- **Temporaries are unmistakably mvtex's.** They are named ``.NAME.mvtex-XXXXXXXX.tmp`` /
  ``.aside`` and hold a stamp file (``.mvtex-temporary``); only folders with both (or
  empty ones of that name: a kill before the stamp) are ever cleaned up (`remove_leftovers`).

docs/safety.md says the same for users.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import functools
import glob
import inspect
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, ParamSpec, TypeVar

from mvtex import __version__
from mvtex.util.errors import InputError, OptionError, OutputError
from mvtex.util.inputs import Inputs, _inside, array_files, check_inputs, check_place, input_paths
from mvtex.util.lock import locked
from mvtex.util.manifest import (
    MARKER,
    TAG,
    TEMP_STAMP,
    is_real_dir,
    is_regular,
    is_temporary,
    lstat,
    output_owner,
    read_manifest,
    temporary_for,
    walk,
    write_manifest,
    written_by_mvtex,
)

__all__ = ["MARKER", "TEMP_STAMP", "array_files", "atomic_path", "check_inputs", "check_output", "claim_file",
           "claim_output", "clear_output", "forget", "foreign_entries", "input_paths", "is_temporary", "mark_output",
           "output_owner", "readable", "remove_leftovers", "replace_path", "writer", "written_by_mvtex"]


@dataclass(frozen=True)
class _Claim:
    command: str
    overwrite: bool


# Paths claimed by `claim_output` / `claim_file` in this thread: key -> claim. `replace_path`
# writes the manifest into a directory before renaming it onto a claimed path, so an output
# never appears without it, and records what it renames into a claimed folder written in place.
_CLAIMED: contextvars.ContextVar[dict[str, _Claim]] = contextvars.ContextVar("mvtex_claimed_outputs", default={})


def _key(path: str | os.PathLike) -> str:
    return os.path.normcase(os.path.realpath(path))


# -- temporaries -------------------------------------------------------------------------------

def _temporary(target: Path, kind: str) -> Path:
    """A new hidden folder beside `target`, ``.NAME.mvtex-XXXXXXXX.<kind>``, stamped as mvtex's."""
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.{TAG}", suffix=f".{kind}", dir=target.parent))
    try:
        import json  # noqa: PLC0415 (loaded on use)

        (tmp / TEMP_STAMP).write_text(json.dumps({"temporary_for": target.name, "pid": os.getpid()}) + "\n")
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return tmp


def remove_leftovers(directory: str | os.PathLike, name: str) -> None:
    """Delete the temporaries that `atomic_path` and `replace_path` leave beside
    ``directory/name`` when a process is killed between their renames. Only folders that
    `is_temporary` recognises as mvtex's (name *and* stamp) are touched."""
    for entry in Path(directory).glob(f".{glob.escape(name)}.{TAG}*"):
        if is_temporary(entry, name):
            shutil.rmtree(entry, ignore_errors=True)


# -- manifests -----------------------------------------------------------------------------------

def foreign_entries(path: str | os.PathLike) -> list[str]:
    """What is in folder `path` that mvtex did not write: entries its manifest does not
    list (all of them without a manifest), and every link, mount point or special file. A folder inside a claimed
    output that is written in place is judged by that output's manifest."""
    path = Path(path)
    listed = written_by_mvtex(path)
    prefix = ""
    if listed is None:
        root = _claimed_root(path)
        if root is not None:
            listed = written_by_mvtex(root)
            prefix = Path(os.path.relpath(os.path.realpath(path), os.path.realpath(root))).as_posix() + "/"
    listed = listed or set()
    found, alien = walk(path)
    return [e for e in found if prefix + e not in listed or e in alien]


def clear_output(path: str | os.PathLike, command: str | None = None) -> None:
    """Delete what an output folder's manifest lists, when that is all it holds (a run
    written in place that starts over), and empty its list (recording `command` as its
    writer when given). Refuses (InputError) a folder holding anything else."""
    path = Path(path)
    foreign = foreign_entries(path)
    if foreign:
        raise InputError(path, _foreign_message(path, foreign))
    marker = read_manifest(path) or {}
    for name in sorted(os.listdir(path)):
        entry = path / name
        if name == MARKER and is_regular(entry):
            continue
        if is_real_dir(entry):
            shutil.rmtree(entry)
        else:
            entry.unlink()
    write_manifest(path, {**marker, "command": command or marker.get("command"), "files": []})


def _write_marker(directory: Path, command: str) -> None:
    """Write the manifest of `directory`: `command` wrote everything in it now."""

    write_manifest(directory, {"command": command, "mvtex": __version__, "files": walk(directory)[0]})


def mark_output(directory: str | os.PathLike, command: str) -> None:
    """Write the manifest of a folder mvtex has just made whole (all it holds is `command`'s)."""
    _write_marker(Path(directory), command)


def _claimed_roots(path: Path) -> list[Path]:
    """The claimed folders, with a manifest, that strictly contain `path`, the nearest first
    (not through one of mvtex's temporaries: what is written there is recorded when the
    temporary is renamed into place). A command that writes in place inside another's
    folder (the demo's models) is recorded in both manifests."""
    real = os.path.realpath(path)
    roots = sorted((key for key in _CLAIMED.get() if _inside(real, key) and is_regular(Path(key) / MARKER)),
                   key=len, reverse=True)
    if not roots:
        return []
    rel = Path(os.path.relpath(real, roots[-1]))
    probe = Path(roots[-1])
    for part in rel.parts[:-1]:
        probe = probe / part
        if is_temporary(probe):
            return []
    return [Path(key) for key in roots]


def _claimed_root(path: Path) -> Path | None:
    """The nearest of `_claimed_roots(path)`, None without one."""
    roots = _claimed_roots(path)
    return roots[0] if roots else None


def _relative_entries(rel: Path, contents: list[str]) -> set[str]:
    return {p.as_posix() for p in list(rel.parents)[:-1]} | {rel.as_posix()} | {(rel / e).as_posix() for e in contents}


@contextlib.contextmanager
def _recorded(target: Path, contents: list[str], source: Path | None = None) -> Iterator[None]:
    """List `target` (and `contents`, the entries it will hold, and the folders between)
    in the manifest of the claimed folder it is about to be renamed into, in place of what
    was listed there and of `source` when that lay in the folder too; put the list back
    when the block fails. Listing first: a kill after the rename leaves nothing unlisted."""
    saved = []
    try:
        for root in _claimed_roots(target):
            marker = read_manifest(root) or {}
            before = list(marker.get("files") or [])
            saved.append((root, marker, before))
            rel = Path(os.path.relpath(os.path.realpath(target), os.path.realpath(root)))
            gone = [rel.as_posix()]
            if source is not None and root in _claimed_roots(source):
                gone.append(Path(os.path.relpath(os.path.realpath(source), os.path.realpath(root))).as_posix())
            files = {f for f in before if not any(f == g or f.startswith(g + "/") for g in gone)}
            write_manifest(root, {**marker, "files": sorted(files | _relative_entries(rel, contents))})
        yield
    except BaseException:
        for root, marker, before in saved:
            write_manifest(root, {**marker, "files": before})
        raise


def forget(root: str | os.PathLike, entries: Iterable[str]) -> None:
    """Drop `entries` (relative POSIX paths mvtex deleted) from folder `root`'s manifest,
    and from that of the claimed folder `root` lies in."""
    root = Path(root)
    gone = set(entries)
    marker = read_manifest(root)
    if marker and isinstance(marker.get("files"), list):
        write_manifest(root, {**marker, "files": [f for f in marker["files"] if f not in gone]})
    outer = _claimed_root(root)
    marker = read_manifest(outer) if outer is not None else None
    if marker and isinstance(marker.get("files"), list):
        rel = Path(os.path.relpath(os.path.realpath(root), os.path.realpath(outer)))
        drop = {(rel / e).as_posix() for e in gone}
        write_manifest(outer, {**marker, "files": [f for f in marker["files"] if f not in drop]})


# -- writing ----------------------------------------------------------------------------------

def _check_replaceable(target: Path) -> None:
    """Refuse to replace folder `target` when that would delete something mvtex did not
    write. (A single file is the claim's business: `claim_file` asks for `overwrite`.)"""
    if is_real_dir(target):
        foreign = foreign_entries(target)
        if foreign:
            raise InputError(target, _foreign_message(target, foreign))


def _foreign_message(path: Path, foreign: list[str]) -> str:
    if is_regular(path / MARKER) and written_by_mvtex(path) is None:
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
    renamed aside (to a hidden, stamped ``.<name>.mvtex-*.aside`` folder), `source` is
    renamed in, and only then is the aside copy deleted; if the rename-in fails the aside
    copy is put back. A kill between the two renames leaves both versions on disk, never
    neither. Inside a claimed folder written in place, `target` is listed in its manifest
    before the rename.
    """
    source, target = Path(source), Path(target)
    claim = _CLAIMED.get().get(_key(target))
    folder = is_real_dir(source)
    if claim is not None and folder:
        _write_marker(source, claim.command)
    contents = walk(source)[0] if folder else []
    if lstat(target) is None:
        with _recorded(target, contents, source):
            os.replace(source, target)
        return
    if is_real_dir(target) and not folder:
        raise InputError(target, "is a directory; a file cannot replace it")
    _check_replaceable(target)
    aside_dir = _temporary(target, "aside")
    aside = aside_dir / target.name
    os.replace(target, aside)
    try:
        with _recorded(target, contents, source):
            os.replace(source, target)
    except BaseException:
        os.replace(aside, target)
        shutil.rmtree(aside_dir, ignore_errors=True)
        raise
    shutil.rmtree(aside_dir, ignore_errors=True)


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
    check_place(path)
    try:
        _make_folders(path.parent)
        tmp = _temporary(path, "tmp")
    except OSError as err:
        raise OutputError(path, f"cannot write here ({err.strerror or err})") from None
    target = tmp / path.name
    try:
        yield target
        if is_regular(target):
            readable(target)
        replace_path(target, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# -- claims -----------------------------------------------------------------------------------

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
    check_place(path)
    check_inputs(path, inputs)
    if path.is_dir():
        foreign = foreign_entries(path)
        if foreign:
            raise InputError(path, _foreign_message(path, foreign))
        owner = output_owner(path)
        if not overwrite and owner != command and walk(path)[0]:
            what = f"the output of `mvtex {owner}`" if owner else "part of another mvtex output"
            raise InputError(path, f"exists and is {what}; its content would be replaced: "
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
        raise OutputError(_shown(path), f"cannot write it ({what})") from err


def _shown(path: Path) -> Path:
    """`path` as the user knows it: a path inside one of mvtex's temporaries
    (``.NAME.mvtex-XXXXXXXX.tmp/NAME/...``) as where it will be once renamed into place."""
    parts = Path(path).parts
    for i in range(len(parts) - 1):
        if temporary_for(parts[i]) == parts[i + 1]:
            return _shown(Path(*parts[:i], *parts[i + 1:]))
    return Path(path)


_DISK_ERRORS = (errno.ENOSPC, errno.EFBIG, errno.EDQUOT, errno.EROFS, errno.EIO)


def _concerns(output: Path, filename) -> bool:
    """Whether `filename` is the output, inside it, or a temporary beside it."""
    try:
        real, out = os.path.realpath(os.fsdecode(filename)), os.path.realpath(output)
    except (TypeError, ValueError):
        return False
    return real == out or real.startswith(out + os.sep) or \
        os.path.basename(real).startswith(f".{os.path.basename(out)}.")


def _inherited_overwrite(path: Path) -> bool:
    """Whether `path` lies in an output claimed with `overwrite` (the command line's)."""
    real = _key(path)
    return any(claim.overwrite and (real == key or _inside(real, key)) for key, claim in _CLAIMED.get().items())


@contextlib.contextmanager
def _holding(path: Path, command: str, overwrite: bool) -> Iterator[None]:
    claims = dict(_CLAIMED.get())
    claims[_key(path)] = _Claim(command, overwrite)
    token = _CLAIMED.set(claims)
    try:
        yield
    finally:
        _CLAIMED.reset(token)


@contextlib.contextmanager
def claim_output(path: str | os.PathLike, command: str, *, overwrite: bool = False, in_place: bool = False,
                 inputs: Inputs = ()) -> Iterator[Path]:
    """Hold an output folder for one run of `command` (the writer policy, module docstring).

    Checks the path with `check_output`, takes the lock (`mvtex.util.lock.locked`: a second
    run on the same output fails at once with "in use by pid N"), removes mvtex's own
    temporaries of an earlier killed run, and makes what is renamed onto the path carry the
    manifest. A write that fails for lack of space (or any `OSError` about the output)
    becomes an `OutputError` naming it. Inside a claim of the same path (the command
    line's), only the checks run.

    Args:
        path: the output folder.
        command: the mvtex command writing it ("slide", "synth", ...).
        overwrite: allow replacing another mvtex command's output (never a user's files).
        in_place: the command writes files into the folder (demo, `train --cameras a,b`)
            instead of renaming a finished folder onto it: create it and mark it now (a
            folder it already holds keeps its manifest); every file written there through
            `atomic_path` is added to its manifest.
        inputs: the files and folders the run reads (dataset, texcoord set, models, rig).

    Raises:
        InputError: a file there, a folder holding what mvtex did not write, someone else's
            output without `overwrite`, an input in the way, an unwritable place, a lock
            file that is not mvtex's, or another run holding the lock.
    """
    path = Path(path)
    if _key(path) in _CLAIMED.get():
        check_inputs(path, inputs)
        with _output_errors(path):
            yield path
        return
    overwrite = bool(overwrite) or _inherited_overwrite(path)
    path = check_output(path, command, overwrite=overwrite, inputs=inputs)
    with _new_folders(path.parent, path), locked(path), _output_errors(path):
        if not os.access(path.parent, os.W_OK | os.X_OK):
            raise InputError(path, f"{path.parent} is not writable")
        path = check_output(path, command, overwrite=overwrite, inputs=inputs)  # may have changed while waiting
        remove_leftovers(path.parent, path.name)  # of a run of this command that was killed
        created = False
        if in_place:
            try:
                created = not path.is_dir()
                if created:
                    with _recorded(path, []):  # in the manifests of the claimed folders around it
                        _make_folders(path)
            except OSError as err:
                raise InputError(path, f"cannot create ({err.strerror or err})") from None
            _take(path, command)
        try:
            with _holding(path, command, overwrite):
                yield path
        except BaseException:
            if created and os.listdir(path) == [MARKER]:  # nothing written: leave no trace
                (path / MARKER).unlink()
                path.rmdir()
            raise


def _take(path: Path, command: str) -> None:
    """Make folder `path` (checked: empty, or all mvtex's) `command`'s to write in place: a
    new manifest where it has none, its own left as it is, another command's taken over
    (its list kept)."""

    marker = read_manifest(path)
    if marker is None or marker.get("command") != command:
        files = marker.get("files") if marker and isinstance(marker.get("files"), list) else []
        write_manifest(path, {"command": command, "mvtex": __version__, "files": files})


@contextlib.contextmanager
def claim_file(path: str | os.PathLike, command: str, *, overwrite: bool = False, inputs: Inputs = ()) -> Iterator[Path]:
    """Hold an output *file* (a rig YAML, a PNG) for one run of `command`.

    A file carries no manifest, and a user's file of the same name (last week's
    calibration, a photo) may be indistinguishable from one mvtex wrote, so an existing file
    is replaced only with `overwrite`. One of `inputs`, or a file inside an input folder,
    never (`check_inputs`). A file inside a claimed output folder is that folder's business
    (its manifest decides). A link or a directory there is refused. The file's folder is
    created; one run at a time holds the path (as `claim_output`); the caller writes the
    file through `atomic_path`, so it appears whole or not at all.

    Raises:
        InputError: as said above, naming the path.
    """
    path = Path(path)
    if path.is_symlink():
        raise InputError(path, "is a symbolic link; give the real output path")
    if path.is_dir():
        raise InputError(path, "is a directory; give a file name")
    check_inputs(path, inputs)
    if _key(path) in _CLAIMED.get() or _claimed_root(path) is not None:
        with _output_errors(path):
            yield path
        return
    overwrite = bool(overwrite) or _inherited_overwrite(path)
    check_place(path)
    if lstat(path) is not None and not overwrite:
        raise InputError(path, "exists; choose another output file or pass --overwrite to replace it")
    with _new_folders(path.parent, path), locked(path), _output_errors(path):
        if lstat(path) is not None and not overwrite:  # made while we waited for the lock
            raise InputError(path, "exists; choose another output file or pass --overwrite to replace it")
        check_inputs(path, inputs)
        remove_leftovers(path.parent, path.name)
        with _holding(path, command, overwrite):
            yield path


def _make_folders(folder: Path) -> list[Path]:
    """Create `folder` and its missing parents, listing them first in the manifest of a
    claimed folder they lie in. Returns the folders made, deepest first."""
    missing = []
    probe = Path(folder)
    while lstat(probe) is None and probe != probe.parent:
        missing.append(probe)
        probe = probe.parent
    if missing:
        with _recorded(missing[0], []):
            folder.mkdir(parents=True, exist_ok=True)
    return missing


@contextlib.contextmanager
def _new_folders(folder: Path, output: Path) -> Iterator[None]:
    """Create `folder` and its missing parents; remove the ones made here, if still empty,
    when the block fails (a refused or failed run leaves no trace). Errors name `output`."""
    try:
        missing = _make_folders(folder)
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
