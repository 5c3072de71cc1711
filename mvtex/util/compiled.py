"""`compiled`: the one way mvtex compiles a kernel with numba (imported only by the kernel
modules, so `import mvtex` stays NumPy-only)."""

from __future__ import annotations

from numba import njit


def compiled(fn=None, **options):
    """numba-compile `fn` (no GIL, NumPy's division semantics, `options` passed on, e.g.
    parallel=True), cached on disk where numba finds a writable place for its cache, compiled
    in every process where it finds none. Usable as @compiled or compiled(fn, parallel=True)."""
    if fn is None:
        return lambda f: compiled(f, **options)
    try:
        return njit(cache=True, nogil=True, error_model="numpy", **options)(fn)
    except RuntimeError:  # numba's "cannot cache function ...: no locator available"
        return njit(nogil=True, error_model="numpy", **options)(fn)
