"""One BLAS thread while a fit runs.

numpy's bundled OpenBLAS starts one thread per core for every matrix product. The fits here multiply many small
and medium matrices (normal equations of a few hundred unknowns, 9k × 42 Jacobians); on a shared 2-core machine
under load the threaded kernels were measured 3–20× slower than a single thread (local POE at 1,000 rows:
4.0 s threaded, 1.1 s single; issue 13.7), and a single thread also makes the summation order, and so the bits
of a fit, independent of the machine's core count. The switch uses OpenBLAS's own ``set_num_threads`` through
ctypes and restores the previous count; where numpy is not linked to a recognisable OpenBLAS it does nothing.
"""

from __future__ import annotations

import ctypes
import functools
import glob
import os
from collections.abc import Iterator
from contextlib import contextmanager

_SETTERS = ("scipy_openblas_set_num_threads64_", "openblas_set_num_threads64_", "openblas_set_num_threads")
_GETTERS = ("scipy_openblas_get_num_threads64_", "openblas_get_num_threads64_", "openblas_get_num_threads")


@functools.cache
def _openblas():
    import numpy

    root = os.path.dirname(os.path.dirname(numpy.__file__))
    patterns = [
        os.path.join(root, "numpy.libs", "*openblas*"),
        os.path.join(os.path.dirname(numpy.__file__), ".dylibs", "*openblas*"),
    ]
    for path in sorted(p for pattern in patterns for p in glob.glob(pattern)):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        setter = next((getattr(lib, n) for n in _SETTERS if hasattr(lib, n)), None)
        getter = next((getattr(lib, n) for n in _GETTERS if hasattr(lib, n)), None)
        if setter is not None and getter is not None:
            setter.argtypes, setter.restype = [ctypes.c_int], None
            getter.argtypes, getter.restype = [], ctypes.c_int
            return setter, getter
    return None


@contextmanager
def single_blas_thread() -> Iterator[None]:
    """Run the block with one OpenBLAS thread (module docstring); nests, and restores the caller's count."""
    found = _openblas()
    if found is None:
        yield
        return
    setter, getter = found
    before = int(getter())
    setter(1)
    try:
        yield
    finally:
        setter(before)
