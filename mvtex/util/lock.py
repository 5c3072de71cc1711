"""One run per output: the advisory lock beside it, ``.NAME.mvtex-lock``.

The lock is a regular file holding "mvtex lock, pid N", locked with `fcntl.flock` for as
long as the run writes and deleted when it ends; the lock dies with its process, so a
killed run never blocks the next one (its file is taken over). The lock file is created
with ``O_CREAT|O_EXCL|O_NOFOLLOW``; one that is already there is opened with
``O_NOFOLLOW`` and used only when it is a regular file of one name holding what mvtex
writes there (`mvtex.util.manifest.is_lock`): a symbolic link, a hard link or a file of
anyone else's at that name is refused, never written through, truncated or removed.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import stat
from pathlib import Path
from typing import Iterator

from mvtex.util.errors import InputError
from mvtex.util.manifest import LOCK_SUFFIX, lock_pid, lock_text

_FLAGS = os.O_RDWR | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)


def lock_path(path: str | os.PathLike) -> Path:
    """The lock file of output `path`: ``.NAME.mvtex-lock`` beside it."""
    path = Path(path)
    return path.with_name(f".{path.name}{LOCK_SUFFIX}")


def _not_ours(path: Path, lock: Path) -> InputError:
    return InputError(path, f"{lock.name} beside it is not mvtex's lock file (a link, or a file mvtex did not "
                      "write); mvtex does not touch it: move it away and rerun")


def _open(path: Path, lock: Path) -> tuple[int, bool] | None:
    """(descriptor, created) of the lock file, None when it vanished while we looked."""
    try:
        return os.open(lock, _FLAGS | os.O_CREAT | os.O_EXCL, 0o644), True
    except FileExistsError:
        pass
    except OSError as err:
        raise InputError(path, f"cannot create the lock file {lock.name} ({err.strerror or err})") from None
    try:
        info = os.lstat(lock)
    except FileNotFoundError:
        return None
    if not stat.S_ISREG(info.st_mode):  # a link, a FIFO, a device: never opened
        raise _not_ours(path, lock)
    try:
        fd = os.open(lock, _FLAGS | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        return None
    except OSError as err:  # ELOOP: a link put there since
        if err.errno == errno.ELOOP:
            raise _not_ours(path, lock) from None
        raise InputError(path, f"cannot open the lock file {lock.name} ({err.strerror or err})") from None
    info = os.fstat(fd)
    content = os.pread(fd, 65, 0)
    if not stat.S_ISREG(info.st_mode) or info.st_nlink != 1 or (content and lock_pid(content) == "?"):
        os.close(fd)
        raise _not_ours(path, lock)
    return fd, False


@contextlib.contextmanager
def locked(path: str | os.PathLike) -> Iterator[None]:
    """Hold output `path` for this run (module docstring).

    Raises:
        InputError: naming `path`: another run holds it ("in use by pid N"), the lock file
            there is not mvtex's, or it cannot be created.
    """

    path = Path(path)
    lock = lock_path(path)
    while True:
        opened = _open(path, lock)
        if opened is None:
            continue
        fd, created = opened
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                pid = lock_pid(os.pread(fd, 65, 0))
            finally:
                os.close(fd)
            raise InputError(path, f"in use by pid {pid} (another mvtex run writes it; wait for it to finish)") \
                from None
        # The holder before us may have deleted the lock file after we opened it: then our
        # lock is on an orphaned inode and a third run could lock a new file. Retry.
        try:
            same = os.path.samestat(os.fstat(fd), os.lstat(lock))
        except FileNotFoundError:
            same = False
        if same and not created:  # checked again under the lock: still a lock file of mvtex's
            content = os.pread(fd, 65, 0)
            if os.fstat(fd).st_nlink != 1 or (content and lock_pid(content) == "?"):
                os.close(fd)
                raise _not_ours(path, lock)
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, lock_text(os.getpid()), 0)
        yield
    finally:
        try:
            if os.path.samestat(os.fstat(fd), os.lstat(lock)):
                os.unlink(lock)  # still holding the lock: nobody else can be between open and check
        except OSError:
            pass
        os.close(fd)
