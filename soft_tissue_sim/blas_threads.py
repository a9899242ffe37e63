"""One BLAS thread for a block of host linear algebra.

OpenBLAS (numpy's and scipy's wheels each bundle their own) splits a product over all cores,
its helper threads waiting by spinning. Beside the background factorization of the LDL^T
preconditioner on a small CPU, the per-step dense products of the Delassus operator then
compete for the core the factorization uses. :func:`one_thread` sets every loaded OpenBLAS
to one thread for the ``with`` block and restores the number it had. The setting is the
library's, for the whole process (``openblas_set_num_threads_local``, OpenBLAS 0.3.27 and
later, returns the previous number but is not per thread in the pthreads builds): a BLAS
call of another thread inside the block runs on one thread too. Where no loaded BLAS offers
that call (another BLAS, another system), it does nothing.
"""

from __future__ import annotations

import contextlib
import ctypes
import threading

_lock = threading.Lock()
_setters: list | None = None
_inside = 0  # blocks under way
_saved: list = []  # the numbers of threads before the first of them


def _find_setters() -> list:
    """``openblas_set_num_threads_local`` of every OpenBLAS loaded in this process (found in
    /proc/self/maps, after numpy's and scipy's have been loaded)."""
    global _setters
    with _lock:
        if _setters is None:
            import numpy  # noqa: F401
            import scipy.linalg.blas  # noqa: F401

            try:
                with open("/proc/self/maps") as fh:
                    paths = sorted({line.split()[-1] for line in fh if "openblas" in line.lower() and "/" in line})
            except OSError:
                paths = []
            found = []
            for path in paths:
                try:
                    f = ctypes.CDLL(path).openblas_set_num_threads_local
                except (OSError, AttributeError):
                    continue
                f.restype, f.argtypes = ctypes.c_int, [ctypes.c_int]
                found.append(f)
            _setters = found
    return _setters


def available() -> bool:
    """True when :func:`one_thread` can set the number of BLAS threads."""
    return bool(_find_setters())


@contextlib.contextmanager
def one_thread():
    """The BLAS calls inside the block run on one thread. Blocks may overlap (threads, nesting):
    the first to enter saves the libraries' numbers, the last to leave restores them."""
    global _inside, _saved
    setters = _find_setters()
    with _lock:
        if _inside == 0:
            _saved = [f(1) for f in setters]
        _inside += 1
    try:
        yield
    finally:
        with _lock:
            _inside -= 1
            if _inside == 0:
                for f, n in zip(setters, _saved):
                    f(n)
