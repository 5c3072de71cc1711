"""Shape checks of array arguments, with messages that echo what was received (kornia-style).
"""

from __future__ import annotations

import numbers
import os
from pathlib import Path
from typing import Literal, Sequence, overload

import numpy as np

from mvtex.util.errors import OptionError

MAX_SEED = 2**32 - 1
"""Seeds are what NumPy's and PyTorch's generators both take: integers in 0..2**32-1."""


def check_seed(seed) -> int:
    """A random seed: an integer in 0..`MAX_SEED`.

    Raises:
        OptionError: "seed must be an integer in 0..4294967295, got -1".
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed <= MAX_SEED:
        raise OptionError("seed", f"must be an integer in 0..{MAX_SEED}, got {seed!r}")
    return int(seed)


def check_shape(array: np.ndarray, name: str, spec: Sequence[int | str],
                sizes: dict[str, int] | None = None) -> dict[str, int]:
    """Check an array's shape against a spec of ints and named sizes (kornia-style).

    Args:
        array: the array to check.
        name: its argument name, for the message.
        spec: one entry per axis: an int (that size) or a name (any size, the same wherever
            the name recurs in this call or in `sizes`).
        sizes: sizes already bound by earlier checks (updated in place).

    Returns:
        The bound sizes (`sizes`, or a new dict).

    Raises:
        OptionError (a ValueError): "name must have shape (N,C,2), got (5, 3)" (with N=...
            where bound).
    """
    sizes = {} if sizes is None else sizes
    shape = np.shape(array)
    ok = len(shape) == len(spec)
    bound = dict(sizes)
    if ok:
        for size, want in zip(shape, spec):
            if isinstance(want, str):
                if bound.setdefault(want, size) != size:
                    ok = False
            elif size != want:
                ok = False
    if not ok:
        known = ", ".join(f"{k}={v}" for k, v in sizes.items() if k in spec)
        raise OptionError(name, f"must have shape ({','.join(map(str, spec))}){' with ' + known if known else ''}, "
                         f"got {tuple(shape)}")
    sizes.update(bound)
    return sizes


def as_array(value, name: str, dtype=np.float64) -> np.ndarray:
    """`value` as a NumPy array of `dtype`; OptionError naming `name` when it is not an array
    of numbers (None, text, a ragged list, a dict)."""
    if value is None or isinstance(value, (str, bytes, dict, set)):
        raise OptionError(name, f"must be an array of numbers, got {type(value).__name__}")
    try:
        array = np.asarray(value) if not isinstance(value, np.ndarray) else value
    except (TypeError, ValueError, OverflowError):  # ragged nested lists
        raise OptionError(name, f"must be an array of numbers (a regular shape), got {type(value).__name__}") from None
    if array.dtype.kind not in "biuf":
        raise OptionError(name, f"must be an array of numbers, got {array.dtype} values")
    try:
        with np.errstate(over="ignore", invalid="ignore"):  # a value beyond the dtype's range: inf, checked by the caller
            return np.asarray(array, dtype=dtype)
    except (TypeError, ValueError, OverflowError):
        raise OptionError(name, f"must be an array of {np.dtype(dtype).name} values") from None


@overload
def as_path(value: object, name: str, *, optional: Literal[False] = False) -> Path: ...


@overload
def as_path(value: object, name: str, *, optional: bool) -> Path | None: ...


def as_path(value: object, name: str, *, optional: bool = False) -> Path | None:
    """`value` as a `pathlib.Path`; OptionError naming `name` when it is no path (None unless
    `optional`, a number, a list)."""

    if value is None and optional:
        return None
    if not isinstance(value, (str, os.PathLike)) or isinstance(value, bytes):
        raise OptionError(name, f"must be a file or folder path, got {type(value).__name__}")
    try:
        path = Path(value)
    except TypeError:
        raise OptionError(name, f"must be a file or folder path, got {type(value).__name__}") from None
    if "\x00" in str(path):
        raise OptionError(name, f"must be a path without NUL characters, got {str(path)!r}")
    return path


def check_instance(value, cls, name: str):
    """Return `value` if it is a `cls`, else raise OptionError naming `name`."""
    if not isinstance(value, cls):
        raise OptionError(name, f"must be a {cls.__name__}, got {type(value).__name__}")
    return value


def as_index(value, name: str) -> int:
    """An integer argument (a pose index, a count): OptionError naming `name` unless it is an
    integer (not a bool; a float with an integer value will do)."""

    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Integral, numbers.Real)):
        raise OptionError(name, f"must be an integer, got {value!r:.60}")
    if isinstance(value, numbers.Integral):
        return int(value)
    if not np.isfinite(float(value)) or not float(value).is_integer():
        raise OptionError(name, f"must be an integer, got {value!r:.60}")
    return int(value)


def as_indices(values, name: str) -> list[int]:
    """A list of integers (pose indices): OptionError naming `name` unless `values` is a
    sequence of integers."""
    return [as_index(v, name) for v in as_list(values, name, what="integers")]


def as_list(values, name: str, kind: type | tuple[type, ...] | None = None, what: str = "values") -> list:
    """A list from a sequence argument (a list, tuple, 1-d array, any iterable but text, a
    mapping or a 0-d array); with `kind`, every element must be one. OptionError naming
    `name` otherwise."""
    bad = isinstance(values, (str, bytes, dict, set)) or (isinstance(values, np.ndarray) and values.ndim != 1)
    try:
        out = None if bad else list(values)
    except TypeError:
        out = None
    if out is None or (kind is not None and not all(isinstance(v, kind) and not isinstance(v, bool) for v in out)):
        raise OptionError(name, f"must be a list of {what}, got {values!r:.60}")
    return out
