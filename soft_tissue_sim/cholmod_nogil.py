"""CHOLMOD's simplicial LDL^T through ctypes, which lets go of the GIL while it factorizes.

Why not only scikit-sparse: scikit-sparse 0.4 holds the GIL while CHOLMOD factorizes, so
the background factorization of the asynchronous preconditioner (eq. 2) stops the
simulation thread for the whole factorization (80-120 ms on the brain), and the method's
point, a factor made beside the steps, is lost. A ctypes call of a C function (``CDLL``)
releases the GIL until the function returns, so here CHOLMOD analyzes and factorizes on
another core while the step goes on. The short calls (solves, copies, frees) keep the GIL
(``PyDLL``), as scikit-sparse does: giving it up for half a millisecond costs up to the
interpreter's switch interval to get it back. It is the same library (the one scikit-sparse
links), called directly; scikit-sparse stays the path wherever this one is not available.

Only what the preconditioner uses is bound: :func:`analyze` (symbolic, once per pattern),
:meth:`Factor.factorized` (numeric, into a copy of the symbolic factor), ``f(b)`` (solve
A x = b), ``f.P()`` (the fill-reducing permutation) and ``f.LD()`` (L and D as scipy CSC,
each column's diagonal D first, the rest L's strictly lower part), with scikit-sparse's
meanings. The struct layouts are those of CHOLMOD 3.0 (SuiteSparse 5.x, Debian 12's 5.12,
the version the install pins); :func:`available` refuses any other major version, and a
library whose cholmod_common does not show CHOLMOD's defaults and status where they are
expected (checked once, at load); the caller then uses scikit-sparse.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import threading
import types

import numpy as np
import scipy.sparse as sps

# CHOLMOD 3.0.x (SuiteSparse 5.x) layouts, checked against cholmod.h 3.0.14 (offsetof).
_COMMON_BYTES = 8192  # sizeof(cholmod_common) is 2664; the margin costs nothing
_C_SUPERNODAL, _C_PRINT, _C_STATUS = 48, 144, 1972  # int fields of cholmod_common
_C_NMETHODS, _C_METHOD0_ORDERING = 168, 316  # nmethods; method[0].ordering
_ORDERINGS = {"natural": 0, "amd": 2, "metis": 3, "nesdis": 4, "colamd": 5}  # CHOLMOD_NATURAL ...
ORDERINGS = ("default", *_ORDERINGS)  # what analyze() takes (scikit-sparse's "best" is not bound)
_SIMPLICIAL = 0  # CHOLMOD_SIMPLICIAL
_CHOLMOD_A = 0  # solve A x = b
_REAL, _DOUBLE, _INT = 1, 0, 0  # CHOLMOD_REAL, CHOLMOD_DOUBLE, CHOLMOD_INT
_OK, _NOT_POSDEF, _INVALID = 0, 1, -4


class _Sparse(ctypes.Structure):
    _fields_ = [("nrow", ctypes.c_size_t), ("ncol", ctypes.c_size_t), ("nzmax", ctypes.c_size_t),
                ("p", ctypes.c_void_p), ("i", ctypes.c_void_p), ("nz", ctypes.c_void_p),
                ("x", ctypes.c_void_p), ("z", ctypes.c_void_p),
                ("stype", ctypes.c_int), ("itype", ctypes.c_int), ("xtype", ctypes.c_int),
                ("dtype", ctypes.c_int), ("sorted", ctypes.c_int), ("packed", ctypes.c_int)]


class _Dense(ctypes.Structure):
    _fields_ = [("nrow", ctypes.c_size_t), ("ncol", ctypes.c_size_t), ("nzmax", ctypes.c_size_t),
                ("d", ctypes.c_size_t), ("x", ctypes.c_void_p), ("z", ctypes.c_void_p),
                ("xtype", ctypes.c_int), ("dtype", ctypes.c_int)]


class _Factor(ctypes.Structure):
    _fields_ = [("n", ctypes.c_size_t), ("minor", ctypes.c_size_t),
                ("Perm", ctypes.c_void_p), ("ColCount", ctypes.c_void_p), ("IPerm", ctypes.c_void_p),
                ("nzmax", ctypes.c_size_t),
                ("p", ctypes.c_void_p), ("i", ctypes.c_void_p), ("x", ctypes.c_void_p), ("z", ctypes.c_void_p),
                ("nz", ctypes.c_void_p), ("next", ctypes.c_void_p), ("prev", ctypes.c_void_p),
                ("nsuper", ctypes.c_size_t), ("ssize", ctypes.c_size_t), ("xsize", ctypes.c_size_t),
                ("maxcsize", ctypes.c_size_t), ("maxesize", ctypes.c_size_t),
                ("super", ctypes.c_void_p), ("pi", ctypes.c_void_p), ("px", ctypes.c_void_p), ("s", ctypes.c_void_p),
                ("ordering", ctypes.c_int), ("is_ll", ctypes.c_int), ("is_super", ctypes.c_int),
                ("is_monotonic", ctypes.c_int), ("itype", ctypes.c_int), ("xtype", ctypes.c_int),
                ("dtype", ctypes.c_int), ("useGPU", ctypes.c_int)]


_lib = None
_why = None
_load_lock = threading.Lock()


def _load():
    global _lib, _why
    with _load_lock:
        if _lib is not None or _why is not None:
            return _lib
        lib, errors = None, []
        # the name ldconfig knows, then SuiteSparse 5's soname (what scikit-sparse links here)
        for name in (ctypes.util.find_library("cholmod"), "libcholmod.so.3", "libcholmod.so"):
            if not name:
                continue
            try:
                lib = ctypes.CDLL(name)  # CDLL (not PyDLL): the GIL is released during its calls
                v = (ctypes.c_int * 3)()
                lib.cholmod_version(v)
                break
            except (OSError, AttributeError) as exc:
                lib = None
                errors.append(f"{name}: {exc}")
        if lib is None:
            _why = "libcholmod not found or unusable" + (f" ({'; '.join(errors)})" if errors else "")
            return None
        if v[0] != 3:
            _why = f"CHOLMOD {v[0]}.{v[1]}.{v[2]}: the bound layouts are CHOLMOD 3.0's"
            return None
        # Only the long calls (analyze, factorize: tens to hundreds of ms) let go of the GIL.
        # The short ones (a solve: 0.5 ms) keep it, through PyDLL on the same library: a thread
        # that gives the GIL up for a short call waits up to the switch interval (5 ms) to get
        # it back whenever the other thread runs Python meanwhile (profiled in the brain
        # resection: 2.9 ms a released solve against 0.5 ms; end to end, two runs each, the
        # difference was within the run-to-run noise).
        held = ctypes.PyDLL(lib._name)
        P, I = ctypes.c_void_p, ctypes.c_int
        bound = types.SimpleNamespace()
        for fn, res, args, dll in [("cholmod_start", I, [P], held), ("cholmod_finish", I, [P], held),
                                   ("cholmod_analyze", P, [P, P], lib), ("cholmod_copy_factor", P, [P, P], held),
                                   ("cholmod_factorize", I, [P, P, P], lib), ("cholmod_solve", P, [I, P, P, P], held),
                                   ("cholmod_free_factor", I, [P, P], held), ("cholmod_free_dense", I, [P, P], held)]:
            f = getattr(dll, fn)
            f.restype, f.argtypes = res, args
            setattr(bound, fn, f)
        _lib = bound
        why = _layout_check()
        if why is not None:
            _lib, _why = None, why
        return _lib


def _layout_check() -> str | None:
    """Check the bound offsets on a fresh common: cholmod_start's defaults where we write
    (supernodal = CHOLMOD_AUTO, print = 3, nmethods = 0), and the status field, read after a
    call CHOLMOD must refuse (an analysis of nothing: CHOLMOD_INVALID). None when all hold."""
    buf = ctypes.create_string_buffer(_COMMON_BYTES)
    ptr = ctypes.cast(buf, ctypes.c_void_p)
    _lib.cholmod_start(ptr)
    try:
        get = lambda off: ctypes.c_int.from_buffer(buf, off).value
        if (get(_C_SUPERNODAL), get(_C_PRINT), get(_C_NMETHODS), get(_C_STATUS)) != (1, 3, 0, _OK):
            return "cholmod_common's layout is not the one bound (defaults differ)"
        ctypes.c_int.from_buffer(buf, _C_PRINT).value = 0
        if _lib.cholmod_analyze(None, ptr) or get(_C_STATUS) != _INVALID:
            return "cholmod_common's layout is not the one bound (status not found)"
    finally:
        _lib.cholmod_finish(ptr)
    return None


def available() -> bool:
    """True when the GIL-free path can be used here (CHOLMOD 3.x found)."""
    return _load() is not None


def unavailable_reason() -> str | None:
    _load()
    return _why


class CholmodError(RuntimeError):
    pass


class NotPositiveDefiniteError(CholmodError):
    pass


class _Common:
    """One cholmod_common (CHOLMOD's settings and workspace): never shared between threads
    at the same time; each factor owns one."""

    def __init__(self):
        self.buf = ctypes.create_string_buffer(_COMMON_BYTES)
        self.ptr = ctypes.cast(self.buf, ctypes.c_void_p)
        _lib.cholmod_start(self.ptr)
        self._set(_C_SUPERNODAL, _SIMPLICIAL)  # simplicial LDL^T, as scikit-sparse's mode="simplicial"
        self._set(_C_PRINT, 0)  # errors come back as status, not printed

    def _set(self, off, value):
        ctypes.c_int.from_buffer(self.buf, off).value = value

    @property
    def status(self) -> int:
        return ctypes.c_int.from_buffer(self.buf, _C_STATUS).value

    def finish(self):
        if self.buf is not None:
            _lib.cholmod_finish(self.ptr)
            self.buf = None


def _sparse_view(A: sps.csc_matrix):
    """A cholmod_sparse over A's own arrays (lower part used: stype -1), and what keeps them alive."""
    indptr = np.ascontiguousarray(A.indptr, dtype=np.int32)
    indices = np.ascontiguousarray(A.indices, dtype=np.int32)
    data = np.ascontiguousarray(A.data, dtype=np.float64)
    s = _Sparse(nrow=A.shape[0], ncol=A.shape[1], nzmax=A.nnz, p=indptr.ctypes.data, i=indices.ctypes.data,
                nz=None, x=data.ctypes.data, z=None, stype=-1, itype=_INT, xtype=_REAL, dtype=_DOUBLE,
                sorted=1, packed=1)
    return s, (indptr, indices, data)


def _check_square(A):
    A = sps.csc_matrix(A)
    if A.shape[0] != A.shape[1]:
        raise ValueError(f"a square matrix is needed, got {A.shape}")
    A.sort_indices()
    return A


class Factor:
    """A CHOLMOD factor (symbolic, or numeric after :meth:`factorized`) with its own common."""

    def __init__(self, ptr, common: _Common, n: int, numeric: bool):
        self._ptr = ctypes.c_void_p(ptr)
        self._common = common
        self.n = n
        self.numeric = numeric

    def __del__(self):
        self.free()

    def free(self):
        if getattr(self, "_ptr", None) is not None and _lib is not None:
            if self._ptr.value:
                _lib.cholmod_free_factor(ctypes.byref(self._ptr), self._common.ptr)
            self._common.finish()
            self._ptr = None

    @property
    def _f(self) -> _Factor:
        return _Factor.from_address(self._ptr.value)

    def factorized(self, A) -> "Factor":
        """A numeric factor of A (same pattern as the analyzed one) in a copy of this symbolic
        factor; this one is left as it was (scikit-sparse's ``copy()`` + ``cholesky_inplace``)."""
        A = _check_square(A)
        common = _Common()
        ptr = _lib.cholmod_copy_factor(self._ptr, common.ptr)
        if not ptr:
            common.finish()
            raise CholmodError(f"cholmod_copy_factor failed (status {common.status})")
        out = Factor(ptr, common, self.n, numeric=True)
        s, keep = _sparse_view(A)
        ok = _lib.cholmod_factorize(ctypes.byref(s), out._ptr, common.ptr)  # the GIL is free meanwhile
        del keep
        f = out._f
        if not ok or common.status < _OK:
            out.free()
            raise CholmodError(f"cholmod_factorize failed (status {common.status})")
        if common.status == _NOT_POSDEF or f.minor < f.n:
            minor = int(f.minor)
            out.free()
            raise NotPositiveDefiniteError(f"the matrix is not positive definite (pivot {minor} of {self.n})")
        return out

    def P(self) -> np.ndarray:
        """The fill-reducing permutation: L D L^T = A[P][:, P]."""
        f = self._f
        return np.ctypeslib.as_array(ctypes.cast(f.Perm, ctypes.POINTER(ctypes.c_int)), shape=(self.n,)).astype(np.int64)

    def __call__(self, b: np.ndarray) -> np.ndarray:
        """x with A x = b, for b of shape (n,) or (n, k)."""
        if not self.numeric:
            raise CholmodError("a symbolic factor cannot solve")
        b = np.asarray(b, dtype=np.float64)
        vec = b.ndim == 1
        B = np.asfortranarray(b.reshape(self.n, -1))
        k = B.shape[1]
        d = _Dense(nrow=self.n, ncol=k, nzmax=self.n * k, d=self.n, x=B.ctypes.data, z=None, xtype=_REAL, dtype=_DOUBLE)
        xp = _lib.cholmod_solve(_CHOLMOD_A, self._ptr, ctypes.byref(d), self._common.ptr)
        if not xp:
            raise CholmodError(f"cholmod_solve failed (status {self._common.status})")
        try:
            X = _Dense.from_address(xp)
            x = np.ctypeslib.as_array(ctypes.cast(X.x, ctypes.POINTER(ctypes.c_double)), shape=(k, self.n)).T.copy()
        finally:
            p = ctypes.c_void_p(xp)
            _lib.cholmod_free_dense(ctypes.byref(p), self._common.ptr)
        return x[:, 0] if vec else x

    def LD(self) -> sps.csc_matrix:
        """L and D in one lower-triangular CSC matrix: column j holds D_jj first, then L's
        strictly lower entries (a simplicial LDL^T factor, read in place, possibly unpacked)."""
        f = self._f
        if not self.numeric or f.is_super or f.is_ll:
            raise CholmodError("LD() needs a numeric simplicial LDL^T factor")
        n = self.n
        ip = lambda ptr, m, ct: np.ctypeslib.as_array(ctypes.cast(ptr, ctypes.POINTER(ct)), shape=(m,))
        p = ip(f.p, n + 1, ctypes.c_int).astype(np.int64)
        nz = ip(f.nz, n, ctypes.c_int).astype(np.int64)
        total = int(f.nzmax)
        rows = ip(f.i, total, ctypes.c_int)
        vals = ip(f.x, total, ctypes.c_double)
        indptr = np.concatenate([[0], np.cumsum(nz)])
        src = np.repeat(p[:n] - indptr[:-1], nz) + np.arange(indptr[-1])
        return sps.csc_matrix((vals[src].copy(), rows[src].astype(np.int32), indptr.astype(np.int32)), shape=(n, n))


def analyze(A, ordering: str = "default") -> Factor:
    """The symbolic factor of A. ``ordering``: ``default`` (CHOLMOD's choice: AMD, METIS
    where it fills less), or one of natural, amd, metis, nesdis, colamd (scikit-sparse's
    ``ordering_method``)."""
    if _load() is None:
        raise CholmodError(f"the GIL-free CHOLMOD path is not available: {_why}")
    if ordering != "default" and ordering not in _ORDERINGS:
        raise ValueError(f"unknown CHOLMOD ordering {ordering!r}")
    A = _check_square(A)
    common = _Common()
    if ordering != "default":
        common._set(_C_NMETHODS, 1)
        common._set(_C_METHOD0_ORDERING, _ORDERINGS[ordering])
    s, keep = _sparse_view(A)
    ptr = _lib.cholmod_analyze(ctypes.byref(s), common.ptr)
    del keep
    if not ptr:
        status = common.status
        common.finish()
        raise CholmodError(f"cholmod_analyze failed (status {status})")
    return Factor(ptr, common, A.shape[0], numeric=False)
