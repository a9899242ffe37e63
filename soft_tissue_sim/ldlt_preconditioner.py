"""Asynchronous, rotated LDL^T preconditioner (paper section 2.2, eq. 2).

A background worker factorizes A(t_u) with CHOLMOD while the simulation
goes on with the last factor; the factor is applied rotated by the per-node rotations
between now and t_u:  P^-1 r = dR (LDL^T)^-1 dR^T r,  dR_n = R_n(t) R_n(t_u)^T.

The snapshot (what A depends on, and the nodal rotations) is taken on the caller's thread;
A is assembled and factorized in the worker. ``snapshot_fn`` gives A as a scipy sparse
matrix, or as an object with a ``csc()`` method that assembles it (an
:class:`~soft_tissue_sim.host_assembly.AssemblyState`: copies of the element rotations, the
topology and the coefficients, assembled with NumPy alone): then the caller's thread only
copies. The symbolic analysis is reused while the sparsity pattern is unchanged.

Two workers (``worker``):

* ``thread`` (the default): a background thread. The simplicial factorization goes through
  :mod:`soft_tissue_sim.cholmod_nogil` (CHOLMOD's C API by ctypes), which frees the GIL
  while CHOLMOD works, so the thread runs beside the step on another core. scikit-sparse
  0.4 holds the GIL while it factorizes (``release_gil=False``, the supernodal mode, or a
  CHOLMOD other than 3.x): then the thread overlaps only where the main thread is in
  GIL-free code, and on the brain the step was no faster than a synchronous factorization.
* ``process``: two worker processes that swap roles. Each holds its own CHOLMOD factor
  (a scikit-sparse Factor cannot cross processes): one serves the solves with the installed
  factor (the vector goes through a pipe, about 0.2 ms there and back), the other
  factorizes the next snapshot at the same time, on another core, sharing no GIL; when its
  factor is installed the two swap. The process holding the factor also forms contact's W
  from its own L and D (:mod:`soft_tissue_sim.delassus`), so L never leaves it. Host solves
  only.

Both are one interface (``request``, ``poll``, ``run_now``, ``revive``, ``lost_request``,
``cancel``, ``close``, ``error``, ``analyses``, ``restarts``): :class:`_Thread`,
:class:`_Processes`.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
import weakref
from multiprocessing.connection import Connection

import numpy as np
import scipy.sparse as sps
from sksparse.cholmod import analyze

from . import cholmod_nogil


SUPERNODAL_ABOVE = 60_000  # degrees of freedom
ORDERINGS = ("amd", "metis", "nesdis", "colamd", "natural", "default", "best")  # CHOLMOD's fill-reducing orderings


def _worker_loop(state):
    """Factorize requests until told to stop. ``state`` holds no reference to the owner."""
    while True:
        with state["cv"]:
            while state["request"] is None and not state["stop"]:
                state["cv"].wait()
            if state["stop"]:
                return
            req = state["request"]
            state["request"] = None
        try:
            result = _local_result(state, req)
            with state["cv"]:
                state["result"] = result
        except Exception as exc:  # noqa: BLE001 - reported in stats, last good factor kept
            with state["cv"]:
                state["error"] = f"{type(exc).__name__}: {exc}"
                state["result"] = {"failed": True}


def _local_result(state, req):
    """Factorize a snapshot in this process: the result as the preconditioner installs it."""
    factor = _factorize(state, req["A"])
    return {"factor": factor, "R": req["R"], "step": req["step"], "ms": _ms_since(req["t0"]), "gen": req["gen"],
            "meta": req["meta"], "lower": _lower(state, factor)}


def _ms_since(t0):
    return 1000.0 * (time.perf_counter() - t0)


def _drop_decoupled(A: sps.csc_matrix) -> sps.csc_matrix:
    """A without the stored zeros that couple decoupled rows (the identity rows of fixed nodes).

    A block pattern (a matrix handed in sparse) keeps the blocks between fixed and free
    nodes, filled with exact zeros; a state's ``csc()`` leaves them out already, so its A
    does not come here. A row whose off-diagonal values are all zero stays decoupled in the
    factor too, so dropping those entries leaves the matrix -- and the factor's numbers -- unchanged
    while the pattern, the fill and the elimination tree shrink (the brain: 36% fewer
    nonzeros in L, a factorization 1.6-1.9x faster, 242 instead of 280 levels). The test is
    on rows, which are fixed or not for good, so the pattern stays stable between steps."""
    n = A.shape[0]
    cols = np.repeat(np.arange(n), np.diff(A.indptr))
    rows = A.indices
    off = rows != cols
    coupled = np.zeros(n, dtype=bool)
    coupled[cols[off & (A.data != 0.0)]] = True
    if coupled.all():
        return A
    iso = ~coupled
    keep = ~off | ~(iso[rows] | iso[cols])
    indptr = np.concatenate([[0], np.cumsum(np.bincount(cols[keep], minlength=n))])
    return sps.csc_matrix((A.data[keep], rows[keep], indptr), shape=A.shape)


def _factorize(state, A):
    if hasattr(A, "csc"):  # a frozen state: assembled here, in the worker, without the decoupled zeros
        A = A.csc()
    else:
        A = sps.csc_matrix(A)
        A.sort_indices()
        if A.shape[0] == A.shape[1]:
            A = _drop_decoupled(A)
    key = (A.shape, A.indptr.tobytes(), A.indices.tobytes())
    if state.get("pattern") != key:
        mode = state.get("mode", "auto")
        if mode == "auto":  # simplicial LDL^T as in the paper; supernodal LL^T (BLAS) for large bodies
            mode = "simplicial" if A.shape[0] < SUPERNODAL_ABOVE else "supernodal"
        ordering = state.get("ordering") or "default"
        # Simplicial LDL^T through ctypes where it can be (cholmod_nogil: the GIL is free while
        # CHOLMOD works, so a background thread really runs beside the step); else scikit-sparse.
        gil_free = (state.get("release_gil", True) and mode == "simplicial"
                    and ordering in cholmod_nogil.ORDERINGS and cholmod_nogil.available())
        state["symbolic"] = (cholmod_nogil.analyze(A, ordering) if gil_free
                             else analyze(A, mode=mode, ordering_method=ordering))
        state["gil_free"] = gil_free
        state["mode_used"] = mode
        state["pattern"] = key
        state["analyses"] += 1
    if state["gil_free"]:
        return state["symbolic"].factorized(A)
    f = state["symbolic"].copy()
    f.cholesky_inplace(A)
    return f


BLOCK_COLUMNS = 16  # a block of at least this many columns goes to the lower factor's block solve


def block_solver(factor, lower):
    """B -> A^-1 B with ``factor``, where ``lower`` (its :class:`soft_tissue_sim.delassus.
    LowerFactor`, or None) solves a block of at least BLOCK_COLUMNS columns instead
    (:meth:`~soft_tissue_sim.delassus.LowerFactor.solve_block`: by supernodes, where CHOLMOD's
    simplicial solve takes one column after the other)."""
    block = getattr(lower, "solve_block", None)
    if block is None:
        return factor

    def solve(B):
        return block(B) if np.ndim(B) == 2 and B.shape[1] >= BLOCK_COLUMNS else factor(B)

    return solve


def _lower(state, factor):
    """The factor's L and D for the forward solves of the Delassus operator, when asked for."""
    if not state.get("lower_factor"):
        return None
    from .delassus import LowerFactor

    return LowerFactor.from_cholmod(factor)


def rotate_nodes(dR: np.ndarray, B: np.ndarray, transpose: bool = False) -> np.ndarray:
    """dR_n B_n (or dR_n^T B_n) for every node n: a vector (3n,) or a block of columns (3n, c),
    rotated node by node (the rotations of eq. 2 around the factor), as a batched 3x3 matmul
    (for blocks of columns about 4x faster than the same contraction written with np.einsum)."""
    M = np.swapaxes(dR, 1, 2) if transpose else dR
    return np.matmul(M, B.reshape(len(dR), 3, -1)).reshape(B.shape)


def _stop(state):
    with state["cv"]:
        state["stop"] = True
        state["cv"].notify_all()
    t = state.get("thread")
    if t is not None and t.is_alive() and t is not threading.current_thread():
        # a factorization under way cannot be interrupted: the daemon thread ends after it,
        # its result dropped; close() does not wait for it
        t.join(timeout=0.2)


class _Thread:
    """The ``thread`` worker: one background thread (:func:`_worker_loop`) sharing ``state``."""

    restarts = 0

    def __init__(self, state):
        self.state = state

    @property
    def error(self):
        return self.state["error"]

    @property
    def analyses(self):
        return self.state["analyses"]

    def request(self, req) -> None:
        s = self.state
        t = s["thread"]
        if t is None or not t.is_alive():
            s["thread"] = threading.Thread(target=_worker_loop, args=(s,), name="ldlt-factorizer", daemon=True)
            s["thread"].start()
        with s["cv"]:
            s["request"] = req
            s["cv"].notify_all()

    def poll(self):
        with self.state["cv"]:
            res, self.state["result"] = self.state["result"], None
        return res

    def run_now(self, req):
        return _local_result(self.state, req)

    def revive(self) -> bool:
        return False

    def lost_request(self) -> bool:
        return False

    def cancel(self) -> None:
        with self.state["cv"]:
            self.state["request"] = None
            self.state["result"] = None

    def close(self) -> None:
        _stop(self.state)


WORKERS = ("thread", "process")


def _serve(conn, mode, ordering, want_lower):
    """A factorization process: factorizes the matrices it is sent (with its own symbolic
    analysis, reused while the pattern holds); with its last factor it solves (``solve``) and,
    with ``want_lower``, forms B^T A^-1 B by the forward solves of the Delassus operator
    (``quadratic``, B sent sparse), so that L never has to leave the process. Replies in the
    order of the requests."""
    state = {"pattern": None, "symbolic": None, "analyses": 0, "mode": mode, "ordering": ordering}
    factor = lower = None
    if want_lower:
        import warp as wp

        wp.config.quiet = True  # no start-up banner from the worker
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg[0] == "stop":
            return
        try:
            if msg[0] == "factor":
                t0 = time.perf_counter()
                factor = _factorize(state, msg[1])
                if want_lower:
                    from .delassus import LowerFactor

                    lower = LowerFactor.from_cholmod(factor)
                solve = block_solver(factor, lower)
                conn.send(("factored", _ms_since(t0), state["analyses"]))
            elif factor is None:
                raise RuntimeError("this process holds no factor")
            elif msg[0] == "solve":
                conn.send(("solved", solve(msg[1])))
            else:  # ("quadratic", B sparse)
                conn.send(("quadratic", lower.quadratic(msg[1])))
        except Exception as exc:  # noqa: BLE001 - sent back, the caller reports it
            conn.send(("error", f"{type(exc).__name__}: {exc}"))


# The workers' BLAS: one thread (simplicial CHOLMOD uses none, and idle BLAS threads spinning
# in three processes take the cores the solves wait for: measured on a 2-core CPU). No GPU:
# they solve on the host (Warp's CPU backend for W), and a CUDA context each would be waste.
_WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
               "CUDA_VISIBLE_DEVICES": ""}
_WORKER_MAIN = ("import sys; from multiprocessing.connection import Connection; "
                "from soft_tissue_sim.ldlt_preconditioner import _serve; "
                "_serve(Connection(int(sys.argv[1])), sys.argv[2], sys.argv[3], sys.argv[4] == '1')")


class _Worker:
    """One factorization process and the parent's end of its socket.

    Started as ``python -c`` with one end of a socketpair (what multiprocessing's Pipe is on
    Unix), not through multiprocessing's spawn: that would re-import the user's main script in
    the child, which breaks any script without an ``if __name__ == "__main__"`` guard."""

    def __init__(self, mode, ordering, want_lower):
        parent, child = socket.socketpair()
        env = dict(os.environ, **_WORKER_ENV)
        env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)  # where the parent found us
        self.proc = subprocess.Popen([sys.executable, "-c", _WORKER_MAIN, str(child.fileno()), mode, ordering,
                                      "1" if want_lower else "0"], pass_fds=(child.fileno(),), env=env,
                                     stdin=subprocess.DEVNULL)
        child.close()
        self.conn = Connection(parent.detach())
        self.sent = []  # the factorization requests sent and not answered yet, in order

    def alive(self) -> bool:
        return self.proc.poll() is None

    def ask(self, kind, B):
        """One request to the installed factor (``solve`` or ``quadratic``) and its answer."""
        try:
            self.conn.send((kind, B))
            reply = self.conn.recv()
        except (EOFError, OSError) as exc:
            raise RuntimeError(f"the factorization process is gone ({type(exc).__name__})") from None
        if reply[0] == "error":
            raise ValueError(f"{kind} in the factorization process failed: {reply[-1]}")
        return reply[1]

    def stop(self):
        try:
            self.conn.send(("stop",))
        except (OSError, ValueError):
            pass
        try:  # a process busy factorizing reads no message until it has finished: end it
            self.proc.wait(timeout=0.2)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=5.0)
        self.conn.close()


class RemoteFactor:
    """B -> A^-1 B with the factor a worker process holds: callable like a CHOLMOD Factor; and
    ``quadratic(B)`` = B^T A^-1 B there, as :class:`soft_tissue_sim.delassus.LowerFactor`'s."""

    def __init__(self, worker: _Worker):
        self.worker = worker

    def __call__(self, B):
        return self.worker.ask("solve", np.ascontiguousarray(B, dtype=np.float64))

    def quadratic(self, B):
        return self.worker.ask("quadratic", sps.csc_matrix(B, dtype=np.float64))


class _Processes:
    """The two factorization processes of ``worker: process``: the one whose factor is
    installed serves the solves; the other takes the next factorization request."""

    def __init__(self, mode, ordering, want_lower):
        self._args = (mode, ordering, bool(want_lower))
        self.workers = [_Worker(*self._args) for _ in range(2)]
        self.installed = None  # the worker whose factor is installed
        self.want_lower = bool(want_lower)
        self.error = None
        self.analyses = 0
        self.restarts = 0

    def revive(self) -> bool:
        """Restart a worker that has exited (killed, crashed). Returns True when it was the one
        whose factor was installed: that factor is lost, the caller must factorize anew."""
        lost = False
        for i, w in enumerate(self.workers):
            if not w.alive():
                self.error = f"factorization process {i} exited (code {w.proc.returncode}); restarted"
                lost |= w is self.installed
                w.stop()
                self.workers[i] = _Worker(*self._args)
                self.restarts += 1
        if lost:
            self.installed = None
        return lost

    def free(self) -> _Worker:
        return self.workers[1] if self.installed is self.workers[0] else self.workers[0]

    def request(self, req) -> None:
        w = self.free()
        w.conn.send(("factor", req["A"]))
        w.sent.append(req)

    def _result(self, w, req, reply):
        if reply[0] != "factored":
            self.error = reply[-1]
            return {"failed": True}
        _, ms, analyses = reply
        self.analyses = max(self.analyses, analyses)
        factor = RemoteFactor(w)
        return {"factor": factor, "R": req["R"], "step": req["step"], "ms": ms, "gen": req["gen"],
                "meta": req["meta"], "lower": factor if self.want_lower else None}

    def poll(self):
        """The result of the latest request once it is in (older replies are dropped), else None."""
        w = self.free()
        while w.sent and w.conn.poll():
            req, reply = w.sent.pop(0), w.conn.recv()
            if not w.sent:
                return self._result(w, req, reply)
        return None

    def run_now(self, req):
        """Factorize now (waiting for anything still running in that process first)."""
        w = self.free()
        while w.sent:
            w.sent.pop(0)
            w.conn.recv()
        self.request(req)
        res = self._result(w, w.sent.pop(0), w.conn.recv())
        if res.get("failed"):
            raise RuntimeError(f"factorization failed in the worker process: {self.error}")
        return res

    def lost_request(self) -> bool:
        """True when no factorization is under way any more (its process died and was revived)."""
        return not self.free().sent

    def cancel(self) -> None:
        """Nothing to withdraw: replies to older requests carry an older generation and are dropped."""

    def close(self):
        for w in self.workers:
            w.stop()


class AsyncLDLTPreconditioner:
    name = "async_ldlt"

    def __init__(self, snapshot_fn, *, rotate=True, refresh_every=1, deterministic=False, lag=0, mode="auto",
                 ordering="default", lower_factor=False, worker="thread", release_gil=True):
        """``deterministic``: the factor is made in the step that requests it (no background
        timing), installed at once, or ``lag`` steps later: the schedule of a background
        factorization that takes ``lag`` steps (the paper's took about 5.6), made reproducible.
        With ``lag`` one factor is in flight at a time: requested, installed ``lag`` steps later,
        the next requested ``refresh_every`` steps after the last request at the earliest.
        ``ordering``: CHOLMOD's fill-reducing ordering (default: its AMD-based choice).
        ``lower_factor``: also keep every factor's L and D for :meth:`delassus` (contact's W by
        forward solves alone, :mod:`soft_tissue_sim.delassus`).
        ``worker``: ``thread`` or ``process`` (see the module's docstring; host solves only).
        ``release_gil``: factorize (simplicial) through :mod:`soft_tissue_sim.cholmod_nogil`,
        which frees the GIL while CHOLMOD works, where it is available; False: scikit-sparse."""
        if ordering not in ORDERINGS:
            raise ValueError(f"unknown CHOLMOD ordering {ordering!r}: use one of {', '.join(ORDERINGS)}")
        if worker not in WORKERS:
            raise ValueError(f"ldlt worker must be one of {', '.join(WORKERS)}, got {worker!r}")
        self.worker = worker
        self.snapshot_fn = snapshot_fn
        self.rotate = bool(rotate)
        self.refresh_every = max(1, int(refresh_every))
        self.deterministic = bool(deterministic)
        if isinstance(lag, bool) or not isinstance(lag, (int, np.integer)) or lag < 0:
            raise ValueError(f"lag must be a whole number of steps >= 0, got {lag!r}")
        if lag and not self.deterministic:
            raise ValueError("lag needs deterministic: true (a background factor arrives when it is ready)")
        self.lag = int(lag)
        self.ordering = ordering
        self._s = {"cv": threading.Condition(), "request": None, "result": None, "stop": False, "error": None,
                   "pattern": None, "symbolic": None, "analyses": 0, "thread": None, "mode": mode,
                   "ordering": ordering, "lower_factor": bool(lower_factor),
                   "release_gil": bool(release_gil), "gil_free": None}
        self._workers = (_Processes(mode, ordering, self._s["lower_factor"]) if worker == "process"
                         else _Thread(self._s))
        self._finalizer = weakref.finalize(self, self._workers.close)
        self._gen = 0
        self.correction = None  # a ShermanMorrisonCorrection, attached by the cutter when a scene cuts
        self._reset_counters()

    def _reset_counters(self):
        self.factor = None
        self.lower = None  # the factor's L and D for the Delassus operator (lower_factor=True)
        self.factor_step = -1
        self.R_tu = None
        self.dR = None
        self.step = 0
        self.last_request_step = -10**9
        self.pending = False
        self._held = None  # deterministic with a lag: (the step it is installed at, the factor)
        self.swaps = []
        self.factorization_ms = 0.0
        self.precond_ms = 0.0
        self.factor_count = 0
        self.factor_solve = None  # B -> A_tu^-1 B with the installed factor

    # -------------------------------------------------------------- worker
    def _snapshot(self, step):
        snap = self.snapshot_fn()  # (A, R) or (A, R, meta); A: sparse or with csc(); meta: node uids and mesh version
        A, R = snap[0], snap[1]
        meta = dict(snap[2]) if len(snap) > 2 else {}
        return {"A": A, "R": np.array(R, dtype=np.float64, copy=True), "step": step, "t0": time.perf_counter(),
                "gen": self._gen, "meta": meta}

    def _install(self, res):
        if isinstance(res["factor"], RemoteFactor):  # that process now serves the solves
            self._workers.installed = res["factor"].worker
        self.factor, self.R_tu, self.factor_step = res["factor"], res["R"], res["step"]
        self.lower = res.get("lower")
        self.factor_solve = block_solver(self.factor, self.lower)
        self.factorization_ms = res["ms"]
        self.factor_count += 1
        self.swaps.append(self.step)
        if self.correction is not None:  # drop what the factor contains, re-apply the rest (fig. 2)
            meta = res.get("meta") or {}
            self.correction.set_factor(self.factor_solve, self.R_tu, meta.get("uids"), meta.get("version", -1))

    def _sync_refresh(self, step):
        self._install(self._workers.run_now(self._snapshot(step)))
        self.last_request_step = step

    # ---------------------------------------------------------------- API
    def make_correction(self, enabled: bool = True, rotate: bool = True):
        """The Sherman-Morrison correction a cutter feeds topological changes (eq. 5-12)."""
        from .sherman_morrison import ShermanMorrisonCorrection

        self.correction = ShermanMorrisonCorrection(enabled=enabled, rotate=rotate)
        return self.correction

    def refresh(self, step: int) -> None:
        """Factorize the current state now and install it (waits)."""
        self._sync_refresh(int(step))

    def begin_step(self, step: int, node_rotations: np.ndarray) -> None:
        if self._workers.revive():  # the installed factor died with its process: factorize anew
            self.invalidate()
        elif self.pending and self._workers.lost_request():  # the factorizing one died
            self.pending = False
        self.step = int(step)
        self.precond_ms = 0.0
        if self.factor is None:
            self._sync_refresh(self.step)  # the only wait
        elif self.deterministic and self.lag:
            if self._held is not None and self.step >= self._held[0]:
                self._install(self._held[1])
                self._held = None
            if self._held is None and self.step - self.last_request_step >= self.refresh_every:
                self._held = (self.step + self.lag, self._workers.run_now(self._snapshot(self.step)))
                self.last_request_step = self.step
        elif self.deterministic:
            if self.step - self.last_request_step >= self.refresh_every:
                self._sync_refresh(self.step)
        else:
            res = self._workers.poll()
            if res is not None:
                self.pending = False
                if not res.get("failed") and res.get("gen") == self._gen:
                    self._install(res)
            if not self.pending and self.step - self.last_request_step >= self.refresh_every:
                self._workers.request(self._snapshot(self.step))
                self.pending = True
                self.last_request_step = self.step
        R = np.asarray(node_rotations, dtype=np.float64)
        if self.correction is not None and self.correction.active:
            self.correction.prepare(R if self.rotate else None)  # eq. (8): rotations around the correction
            self.dR = None
        elif self.rotate and R.shape == self.R_tu.shape:
            self.dR = np.matmul(R, np.swapaxes(self.R_tu, 1, 2))
        else:
            self.dR = None

    def apply(self, r: np.ndarray, out: np.ndarray) -> None:
        t0 = time.perf_counter()
        if self.correction is not None and self.correction.active:
            self.correction.apply(r, out)  # eq. (8)-(10)
            self.precond_ms += _ms_since(t0)
            return
        n3 = len(r)
        if self.R_tu is None or 3 * len(self.R_tu) != n3:
            raise ValueError(f"preconditioner is for {3 * (0 if self.R_tu is None else len(self.R_tu))} DOFs, "
                             f"got a vector of {n3}: invalidate() after a size change")
        if self.dR is not None:
            out[:] = rotate_nodes(self.dR, self.factor(rotate_nodes(self.dR, r, transpose=True)))
        else:
            out[:] = self.factor(r)
        self.precond_ms += _ms_since(t0)

    def apply_columns(self, B: np.ndarray) -> np.ndarray:
        """P^-1 B for a block of columns B (3n, k) in one batched solve (contact's W, eq. 4 and 11)."""
        B = np.asarray(B, dtype=np.float64)
        out = np.empty_like(B)
        if self.correction is not None and self.correction.active:
            self.correction.apply_columns(B, out)
            return out
        if self.dR is not None:
            out[:] = rotate_nodes(self.dR, self.factor_solve(rotate_nodes(self.dR, B, transpose=True)))
        else:
            out[:] = self.factor_solve(B)
        return out

    def delassus(self, B: np.ndarray) -> np.ndarray | None:
        """B^T P^-1 B for a block of constraint columns B = H^T (3n, m; dense or sparse): the
        Delassus operator W / dt^2 of eq. (4), corrected after cuts (eq. 11-12), rotated (eq. 2, 8), from the
        factor's forward solves alone (:mod:`soft_tissue_sim.delassus`). None when this
        preconditioner keeps no host L (``lower_factor`` off): use :meth:`apply_columns`."""
        if self.lower is None:
            return None
        from .delassus import rotate_columns

        B = sps.coo_matrix(B)  # a contact column touches 1 to 4 nodes: kept sparse throughout
        if self.correction is not None and self.correction.active:
            return self.correction.delassus(B, self.lower)
        if self.R_tu is None or 3 * len(self.R_tu) != B.shape[0]:
            raise ValueError(f"preconditioner is for {3 * (0 if self.R_tu is None else len(self.R_tu))} DOFs, "
                             f"got a block of {B.shape[0]} rows: invalidate() after a size change")
        if self.dR is not None:
            B = rotate_columns(B, self.dR)
        return self.lower.quadratic(B)

    def invalidate(self) -> None:
        if self.correction is not None:
            self.correction.clear()
        self._gen += 1  # results of requests made before this are ignored
        self._workers.cancel()
        self._reset_counters()

    def stats(self) -> dict:
        sw = self.swaps
        extra = self.correction.stats() if self.correction is not None else {}
        return extra | {
            "factor_age": self.step - self.factor_step if self.factor is not None else -1,
            "factorization_ms": self.factorization_ms,
            "refresh_interval": float(np.mean(np.diff(sw))) if len(sw) > 1 else 0.0,
            "precond_ms": self.precond_ms,
            "worker": self.worker,
            "factorization_gil_free": self._s["gil_free"],  # None: not known here (worker processes)
            "worker_error": self._workers.error,
            "worker_restarts": self._workers.restarts,
            "factor_count": self.factor_count,
            "analyses": self._workers.analyses,
            "backend": "cholmod",
        }

    def close(self) -> None:
        self._finalizer()
