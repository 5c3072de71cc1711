"""Shape checks of array arguments, with messages that echo what was received (kornia-style).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

MAX_SEED = 2**32 - 1
"""Seeds are what NumPy's and PyTorch's generators both take: integers in 0..2**32-1."""


def check_seed(seed) -> int:
    """A random seed: an integer in 0..`MAX_SEED`.

    Raises:
        OptionError: "seed must be an integer in 0..4294967295, got -1".
    """
    from mvtex.util.errors import OptionError

    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed <= MAX_SEED:
        raise OptionError(f"seed must be an integer in 0..{MAX_SEED}, got {seed!r}")
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
        ValueError: "name must have shape (N,C,2), got (5, 3)" (with N=... where bound).
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
        raise ValueError(f"{name} must have shape ({','.join(map(str, spec))}){' with ' + known if known else ''}, "
                         f"got {tuple(shape)}")
    sizes.update(bound)
    return sizes
