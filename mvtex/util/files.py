"""Safe file input and output.

Output: every file is written through `mvtex.util.output.atomic_path` (a stamped temporary
beside its target, renamed in when complete); the writer policy there (`claim_output`, the
`writer` decorator) decides what may be replaced: never what mvtex did not write, never an
input.

Input: `read_json`, `load_npy`, `load_npz` never unpickle, never accept NaN in JSON, and
turn every malformed or truncated file into an `InputError` naming it.
"""

from __future__ import annotations

import json
import mmap
import os
import threading
import zipfile
import zlib
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.lib import format as npformat
from numpy.lib.format import open_memmap

from mvtex.util.errors import InputError
from mvtex.util.output import atomic_path

"""File mvtex writes into every output directory it makes: {"command": ..., "mvtex": version}."""


def read_rows(array: np.ndarray, start: int, stop: int) -> np.ndarray:
    """Rows start:stop of an array, as a new in-memory array.

    An array memory-mapped by `load_npy` is read through its file, not its map: pages
    read through a map stay in the process's resident memory for as long as the map lives,
    so one pass over a memory-mapped 10,000-pose dataset would add its whole size. Any
    other array (in memory, a slice of a map, Fortran order) is sliced and copied.
    """
    start, stop, _ = slice(start, stop).indices(len(array))
    out = np.empty((max(0, stop - start), *array.shape[1:]), dtype=array.dtype)
    whole_map = isinstance(array, np.memmap) and isinstance(array.base, mmap.mmap) and array.filename
    if not (whole_map and array.flags.c_contiguous and out.size):
        out[...] = array[start:stop]
        return out
    row_bytes = out.nbytes // len(out)
    with open(array.filename, "rb") as file:
        file.seek(array.offset + start * row_bytes)
        if file.readinto(memoryview(out).cast("B")) != out.nbytes:
            raise InputError(array.filename, "shorter than its .npy header says")
    return out


def read_row(array: np.ndarray, index: int) -> np.ndarray:
    """Row `index` of an array as a new in-memory array (`read_rows` of one row)."""
    return read_rows(array, index, index + 1)[0]


def create_npy(path: str | os.PathLike, dtype, shape: tuple[int, ...]) -> None:
    """A new .npy file of `shape`, zero-filled (sparse on disk), for `write_npy_rows`."""

    open_memmap(path, mode="w+", dtype=dtype, shape=shape).flush()


def write_npy_rows(path: str | os.PathLike, rows: Sequence[int], values: np.ndarray) -> None:
    """Write values[i] into row rows[i] of an existing C-order .npy file, through the file
    (positioned writes, then fsync), not a memory map.

    A map opened for the write keeps what it wrote resident while it lives, and flushing
    it (msync) walks the whole mapping: 8 ms for 8 rows of a 1 GB file, against 1 ms here.

    Raises:
        ValueError: values whose dtype or row shape differ from the file's, or a row out of range.
    """
    path = Path(path)
    if len(rows) == 0:
        return
    header = np.load(path, mmap_mode="r")  # parses the header; touches no data page
    offset, dtype, shape = header.offset, header.dtype, header.shape
    del header
    values = np.ascontiguousarray(values)
    rows = np.asarray(rows, dtype=np.int64)
    if values.dtype != dtype or values.shape[1:] != shape[1:] or len(values) != len(rows):
        raise ValueError(f"{path}: rows of {values.dtype} {values.shape} do not fit {dtype} {shape} at {len(rows)} rows")
    if rows.min() < 0 or rows.max() >= shape[0]:
        raise ValueError(f"{path}: rows outside [0, {shape[0]})")
    row_bytes = values[0].nbytes
    fd = os.open(path, os.O_WRONLY)
    try:
        i = 0
        while i < len(rows):  # one write per run of consecutive rows
            j = i + 1
            while j < len(rows) and rows[j] == rows[j - 1] + 1:
                j += 1
            data = memoryview(values[i:j]).cast("B")
            written = 0
            while written < len(data):
                written += os.pwrite(fd, data[written:], offset + int(rows[i]) * row_bytes + written)
            i = j
        os.fsync(fd)
    finally:
        os.close(fd)


def dumps_strict(obj: Any, **kwargs) -> str:
    """JSON with NaN and infinities turned into null (strict JSON, RFC 8259)."""
    return json.dumps(_finite(obj), allow_nan=False, **kwargs)


def _finite(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if np.isfinite(obj) else None
    if isinstance(obj, np.floating):
        return float(obj) if np.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _finite(obj.tolist())
    return obj


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write JSON atomically, indented, with a trailing newline."""
    with atomic_path(path) as tmp:
        tmp.write_text(dumps_strict(obj, indent=2) + "\n")


def read_json(path: str | os.PathLike) -> Any:
    """Read JSON; missing or malformed files raise InputError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    def reject(constant: str):
        raise ValueError(f"{constant} is not a number JSON allows")

    try:
        return json.loads(path.read_text(), parse_constant=reject)
    except (ValueError, UnicodeDecodeError, RecursionError) as err:
        raise InputError(path, f"malformed JSON ({err})") from None
    except OSError as err:
        raise InputError(path, f"cannot read ({err.strerror or err})") from None


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


_HEADER_LOCK = threading.Lock()
"""Held while NumPy reads a .npy header: it parses it with `ast`, and CPython 3.11 before
3.11.8 raises "AST constructor recursion depth mismatch" when threads parse at once (a Dask
worker with several threads)."""


def load_npy(path: str | os.PathLike, mmap: bool = True) -> np.ndarray:
    """Load a .npy (memory-mapped by default), never unpickling."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        with _HEADER_LOCK:
            array = np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (ValueError, OSError, EOFError, MemoryError) as err:
        raise InputError(path, f"not a readable .npy array ({err})") from None
    if not isinstance(array, np.ndarray):  # np.load opens a .npz archive too
        array.close()
        raise InputError(path, "not a .npy array (an .npz archive?)")
    return array


def load_npz(path: str | os.PathLike, max_bytes: int = 1 << 31) -> dict[str, np.ndarray]:
    """Load every array of a .npz into memory, never unpickling.

    Each member's declared shape is checked against its stored size before anything is
    allocated, and the total is capped at `max_bytes`: a corrupt or hostile header raises
    InputError instead of allocating what it declares.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        declared = _npz_sizes(path)
        if sum(declared.values()) > max_bytes:
            raise InputError(path, f"declares {sum(declared.values())} bytes of arrays (more than {max_bytes})")
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except InputError:
        raise
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error, KeyError, MemoryError) as err:
        raise InputError(path, f"not a readable .npz archive ({type(err).__name__}: {err})") from None


def _npz_sizes(path: Path) -> dict[str, int]:
    """Member name -> declared array bytes, checked against the member's stored size."""

    sizes = {}
    with zipfile.ZipFile(path) as archive:
        for info in archive.infolist():
            with archive.open(info) as member:
                version = npformat.read_magic(member)
                if version == (1, 0):
                    shape, _, dtype = npformat.read_array_header_1_0(member)
                else:
                    shape, _, dtype = npformat.read_array_header_2_0(member)
                header = member.tell() if member.seekable() else None
            if dtype.hasobject:
                raise InputError(path, f"{info.filename}: object arrays are not allowed")
            nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
            if header is not None and nbytes != info.file_size - header:
                raise InputError(path, f"{info.filename}: declares shape {shape} {dtype} ({nbytes} bytes) but holds "
                                 f"{info.file_size - header} bytes")
            sizes[info.filename] = nbytes
    return sizes


def save_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an RGB (H,W,3) or gray (H,W) uint8 image as PNG, atomically."""
    import cv2  # noqa: PLC0415 (loaded on use)

    image = np.asarray(image)
    if image.ndim == 3:
        image = image[..., ::-1]  # OpenCV writes BGR
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:
        raise RuntimeError(f"could not encode {path} as PNG")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())
