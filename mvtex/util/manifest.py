"""What mvtex leaves on disk of its own, and how it tells it apart from anything else.

An output folder carries a manifest, ``.mvtex-output.json``: the command that wrote it and
every file and folder it wrote there. Beside it, while a run writes, lie mvtex's transients:
its lock ``.NAME.mvtex-lock``, stamped temporary folders ``.NAME.mvtex-XXXXXXXX.tmp`` /
``.aside`` and the manifest's own temporary ``.mvtex-output.json.XXXXXXXX.tmp``. A killed
run can leave any of them behind.

Nothing here trusts a name alone. A manifest, a stamp or a lock is read only when it is a
regular file (`lstat`; never through a symbolic link: ``O_NOFOLLOW``) whose content is what
mvtex writes there; a transient is recognised by its exact name *and* its content (or, for
what a kill can leave empty, its emptiness). Anything else with such a name, a link
included, is a file mvtex did not write. The claims that use this are `mvtex.util.output`.
"""

from __future__ import annotations

import json
import os
import re
import stat
import tempfile
from pathlib import Path

MARKER = ".mvtex-output.json"
"""The manifest in every output folder: {"command", "mvtex", "files": [relative paths]}."""

TEMP_STAMP = ".mvtex-temporary"
"""The stamp file inside every temporary folder mvtex makes (``.NAME.mvtex-XXXXXXXX.tmp``)."""

LOCK_SUFFIX = ".mvtex-lock"
"""A run's lock beside its output: ``.NAME.mvtex-lock``, holding "mvtex lock, pid N"."""

TAG = "mvtex-"

_RANDOM = r"[a-z0-9_]{8}"  # what `tempfile` puts into the names it makes
_TEMP_NAME = re.compile(rf"^\.(?P<name>.+)\.{TAG}{_RANDOM}\.(?:tmp|aside)$", re.S)
_MARKER_TEMP = re.compile(rf"^{re.escape(MARKER)}(?:\.{_RANDOM})?\.tmp$")
_LOCK_TEXT = re.compile(rb"^(?:mvtex lock, pid )?(\d{1,12})\n$")


def lock_text(pid: int) -> bytes:
    """What a lock file holds while its run lives."""
    return f"mvtex lock, pid {pid}\n".encode()


def lock_pid(content: bytes) -> str:
    """The pid a lock file's content names, "?" when none."""
    match = _LOCK_TEXT.match(content)
    return match.group(1).decode() if match else "?"


def lstat(path: str | os.PathLike) -> os.stat_result | None:
    """`os.lstat`, or None where nothing is (or it cannot be looked at)."""
    try:
        return os.lstat(path)
    except (OSError, ValueError):
        return None


def is_regular(path: str | os.PathLike) -> bool:
    """A regular file itself, not a link to one."""
    info = lstat(path)
    return info is not None and stat.S_ISREG(info.st_mode)


def is_real_dir(path: str | os.PathLike) -> bool:
    """A folder itself, not a link to one."""
    info = lstat(path)
    return info is not None and stat.S_ISDIR(info.st_mode)


def read_regular(path: str | os.PathLike, limit: int = 1 << 24) -> bytes | None:
    """The bytes of `path` when it is a regular file of one name (no link, no hard link
    to elsewhere) of at most `limit` bytes; None for anything else. Never follows a link:
    the file is opened with ``O_NOFOLLOW`` (and ``O_NONBLOCK``, so a FIFO cannot hang us)
    and checked with `fstat`."""
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    if not is_regular(path):  # not even opened: a device's open can have effects
        return None
    try:
        fd = os.open(path, flags)
    except (OSError, ValueError):
        return None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode) or info.st_nlink != 1 or info.st_size > limit:
            return None
        chunks = []
        while True:
            chunk = os.read(fd, 1 << 20)
            if not chunk:
                return b"".join(chunks)
            chunks.append(chunk)
    except OSError:
        return None
    finally:
        os.close(fd)


def _json(path: Path) -> object | None:
    data = read_regular(path)
    if data is None:
        return None
    try:
        return json.loads(data)
    except (ValueError, UnicodeDecodeError, RecursionError):
        return None


# -- manifests -------------------------------------------------------------------------------------

def read_manifest(directory: str | os.PathLike) -> dict | None:
    """The manifest of `directory` as a dict: only a regular file (never read through a
    link), holding a JSON object; None otherwise."""
    marker = _json(Path(directory) / MARKER)
    return marker if isinstance(marker, dict) else None


def _is_manifest(path: Path) -> bool:
    """A regular file holding what mvtex writes as a manifest."""
    marker = _json(path)
    return isinstance(marker, dict) and isinstance(marker.get("files"), list)


def write_manifest(directory: str | os.PathLike, manifest: dict) -> None:
    """Write `directory`'s manifest: into a new file of a fresh name (``O_EXCL``: nothing
    planted there is written through), renamed onto the manifest."""
    directory = Path(directory)
    fd, tmp = tempfile.mkstemp(prefix=MARKER + ".", suffix=".tmp", dir=directory)
    try:
        umask = os.umask(0)
        os.umask(umask)
        os.fchmod(fd, 0o666 & ~umask)  # as any file this process makes (mkstemp's is private)
        with os.fdopen(fd, "w") as file:
            file.write(json.dumps(manifest) + "\n")
        os.replace(tmp, directory / MARKER)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def output_owner(path: str | os.PathLike) -> str | None:
    """The mvtex command recorded in a folder's manifest, or None."""
    marker = read_manifest(path)
    command = marker.get("command") if marker else None
    return command if isinstance(command, str) else None


def written_by_mvtex(path: str | os.PathLike) -> set[str] | None:
    """The entries (relative POSIX paths) a folder's manifest lists, or None without one."""
    marker = read_manifest(path)
    files = marker.get("files") if marker else None
    if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
        return None
    return set(files)


# -- transients ------------------------------------------------------------------------------------

def temporary_for(name: str) -> str | None:
    """NAME when `name` is named as mvtex names a temporary (``.NAME.mvtex-XXXXXXXX.tmp`` or
    ``.aside``), else None (the name only: `is_temporary` checks the folder)."""
    match = _TEMP_NAME.match(name)
    return match.group("name") if match else None


def is_temporary(entry: str | os.PathLike, name: str | None = None) -> bool:
    """Whether `entry` is a temporary folder mvtex made (for ``name``, if given): named
    ``.NAME.mvtex-XXXXXXXX.tmp`` or ``.aside``, a real folder (not a link), holding mvtex's
    stamp for NAME as a regular file, or empty (a run killed before it stamped it)."""
    entry = Path(entry)
    match = _TEMP_NAME.match(entry.name)
    if not match or (name is not None and match.group("name") != name) or not is_real_dir(entry):
        return False
    stamp = _json(entry / TEMP_STAMP)
    if isinstance(stamp, dict) and stamp.get("temporary_for") == match.group("name"):
        return True
    try:
        return not os.listdir(entry)
    except OSError:
        return False


def is_lock(path: str | os.PathLike) -> bool:
    """Whether `path` is a lock file mvtex made: ``.NAME.mvtex-lock``, a regular file of one
    name holding "mvtex lock, pid N" (or only the pid, or nothing: a run killed between
    creating and writing it)."""
    path = Path(path)
    if not (path.name.startswith(".") and path.name.endswith(LOCK_SUFFIX) and len(path.name) > len(LOCK_SUFFIX) + 1):
        return False
    content = read_regular(path, limit=64)
    return content is not None and (content == b"" or bool(_LOCK_TEXT.match(content)))


def is_manifest_temporary(path: str | os.PathLike) -> bool:
    """Whether `path` is the temporary of a manifest being written (`write_manifest`):
    ``.mvtex-output.json.XXXXXXXX.tmp``, a regular file, empty or holding a manifest."""
    path = Path(path)
    if not _MARKER_TEMP.match(path.name):
        return False
    content = read_regular(path, limit=1 << 26)
    return content is not None and (content == b"" or _is_manifest(path))


def is_transient(path: str | os.PathLike) -> bool:
    """One of mvtex's own transients (a lock, a manifest's temporary, a stamped temporary
    folder): what a killed run leaves and a later run may delete."""
    return is_lock(path) or is_manifest_temporary(path) or is_temporary(path)


# -- listing ---------------------------------------------------------------------------------------

def _mount_points() -> set[str]:
    """The mount points of this system (Linux: /proc/self/mountinfo; elsewhere none)."""
    try:
        with open("/proc/self/mountinfo", "rb") as file:
            lines = file.read().splitlines()
    except OSError:
        return set()
    out = set()
    for line in lines:
        fields = line.split(b" ")
        if len(fields) > 4:  # the mount point, with octal escapes of space, tab, newline, backslash
            out.add(os.fsdecode(re.sub(rb"\\([0-7]{3})", lambda m: bytes([int(m.group(1), 8)]), fields[4])))
    return out


def walk(directory: str | os.PathLike) -> tuple[list[str], list[str]]:
    """Every file, link and folder under `directory`, as relative POSIX paths, sorted, less
    its own manifest and mvtex's transients (each recognised by name *and* content); links
    are listed, never followed.

    Returns:
        (entries, alien): alien are the entries mvtex never writes, whatever a manifest
        lists: symbolic links, mount points (a bind mount, another file system: never
        descended into), FIFOs, sockets and devices.
    """
    directory = Path(directory)
    mounts = _mount_points()
    out, alien = [], []
    for root, dirs, files in os.walk(directory):
        rel = Path(root).relative_to(directory)
        keep = []
        for name in sorted(dirs + files):
            path = Path(root) / name
            entry = (rel / name).as_posix()
            if name == MARKER and is_regular(path) and (rel == Path(".") or _is_manifest(path)):
                continue  # this folder's manifest, or the manifest of an output written inside it
            if name.startswith(".") and is_transient(path):
                continue
            out.append(entry)
            info = lstat(path)
            if info is None or not (stat.S_ISREG(info.st_mode) or stat.S_ISDIR(info.st_mode)):
                alien.append(entry)
            elif stat.S_ISDIR(info.st_mode):
                if os.path.realpath(path) in mounts or os.path.ismount(path):
                    alien.append(entry)
                else:
                    keep.append(name)
        dirs[:] = [d for d in dirs if d in keep]
    return sorted(out), sorted(alien)


def entries(directory: str | os.PathLike) -> list[str]:
    """The entries of `walk`."""
    return walk(directory)[0]


def identity(path: str | os.PathLike) -> tuple[int, int] | None:
    """(device, inode) of what `path` names (links followed), or None where nothing is."""
    try:
        info = os.stat(path)
    except (OSError, ValueError):
        return None
    return info.st_dev, info.st_ino
