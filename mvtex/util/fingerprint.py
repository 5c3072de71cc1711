"""Content fingerprints: the one hash mvtex records to tell whether inputs changed (resume
keys, the dataset and mesh a texcoord set or a model was made from).
"""

from __future__ import annotations

import hashlib

import numpy as np

from mvtex.util.files import dumps_strict, read_rows


def fingerprint(*arrays: np.ndarray, block_bytes: int = 1 << 24) -> str:
    """A content hash (BLAKE2b, 16 hex digits) of arrays' shapes, dtypes and bytes.

    Reads memory-mapped arrays in blocks of `block_bytes` through `read_rows`, so a large
    dataset is hashed without being loaded whole or left resident.
    """
    h = hashlib.blake2b(digest_size=8)
    for a in arrays:
        a = a if isinstance(a, np.memmap) else np.asarray(a)
        h.update(f"{a.shape}{a.dtype.str}".encode())
        if a.ndim == 0 or a.size == 0:
            h.update(np.asarray(a).tobytes())
            continue
        rows = max(1, block_bytes // max(1, a[0].nbytes))
        for start in range(0, len(a), rows):
            h.update(np.ascontiguousarray(read_rows(a, start, start + rows)).data)
    return h.hexdigest()


def fingerprint_record(record) -> str:
    """`fingerprint` of a JSON-like record (the bytes of its strict JSON, keys sorted): the
    key of a run's settings."""

    return fingerprint(np.frombuffer(dumps_strict(record, sort_keys=True).encode(), np.uint8))
