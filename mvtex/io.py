"""Atomic file output: write to a temporary name beside the target, rename when complete."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from .errors import InputError


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it onto `path` on success.

    Works for files and directories. On an exception the temporary is removed and `path`
    is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    target = tmp / path.name
    try:
        yield target
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        os.replace(target, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write JSON atomically, indented, with a trailing newline."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=False) + "\n")


def read_json(path: str | os.PathLike) -> Any:
    """Read JSON; missing or malformed files raise InputError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise InputError(path, f"malformed JSON ({err})") from None


def read_header(directory: str | os.PathLike, filename: str, fmt: str, version: int, what: str) -> dict:
    """The JSON header of an mvtex directory (dataset.json, texcoords.json), checked: the
    directory exists, the file is a JSON object with this "format" and "version".

    Args:
        what: the kind of directory for messages, with its article ("an mvtex dataset").
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(directory, f"{what.split(' ', 1)[1]} directory not found")
    meta = read_json(directory / filename)
    if not isinstance(meta, dict) or meta.get("format") != fmt:
        raise InputError(directory / filename, f'not {what} (format must be "{fmt}")')
    if meta.get("version") != version:
        raise InputError(directory / filename, f"unsupported version {meta.get('version')!r} (expected {version})")
    return meta


def save_npy(path: str | os.PathLike, array: np.ndarray) -> None:
    """np.save atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, np.ascontiguousarray(array), allow_pickle=False)


def save_npz(path: str | os.PathLike, **arrays: np.ndarray) -> None:
    """np.savez_compressed atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)


def load_npy(path: str | os.PathLike, mmap: bool = True) -> np.ndarray:
    """Load a .npy (memory-mapped by default), never unpickling."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise InputError(path, f"not a readable .npy array ({err})") from None


def load_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Load every array of a .npz into memory, never unpickling."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (ValueError, OSError, EOFError) as err:
        raise InputError(path, f"not a readable .npz archive ({err})") from None


def save_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an RGB (H,W,3) or gray (H,W) uint8 image as PNG, atomically."""
    import cv2

    image = np.asarray(image)
    if image.ndim == 3:
        image = image[..., ::-1]  # OpenCV writes BGR
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:
        raise RuntimeError(f"could not encode {path} as PNG")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())
