"""The asynchronous rotated preconditioner made, applied and corrected on the device
(paper section 2.2, eq. 2; section 3, eq. 5-12).

A factor backend (:class:`soft_tissue_sim.dense_inverse.DenseInverse`, or
:class:`soft_tissue_sim.cudss_factor.CuDSSFactor`) holds A(t_u)^-1 on the device. This class
schedules its refreshes and applies it rotated by the nodal rotations:

    P^-1 r = dR A(t_u)^-1 dR^T r,     dR_n = R_n(t) R_n(t_u)^T.

Schedule. A request assembles A at the current state into the backend's work buffer on the
simulation's stream, then enqueues the factorization on a stream of its own, after an event:
the steps go on with the factor in use while the new one is made, as the paper's background
thread does on a CPU. Each step polls the factorization's end event (no host wait) and
installs the factor when it has finished. ``deterministic`` makes and installs it in the step
that requests it, or ``lag`` steps later (a background factorization's delay, reproducibly).
On the CPU (Warp's CPU backend, NumPy and SciPy) the factorization runs in the request and
is installed at the next step.

Topological changes. A modification (:class:`soft_tissue_sim.sherman_morrison.Modification`)
is folded into the inverse in use at once, exactly (eq. 5-7 with a dense inverse): the new
nodes enter as identity rows (eq. 10), vanished ones become decoupled identity rows and are
dropped, so the inverse always has the current numbering and the rotations of eq. (8) are
those of eq. (2) with reference rotations R(t_u) (factor nodes) or R at creation (new ones).
A factor made from an older mesh is brought up to date when it is installed: the
modifications it does not contain are folded into it (fig. 2).

Contact. W = H P^-1 H^T (eq. 4, 11-12) is gathered from the inverse by the backend
(``delassus``) and dx = P^-1 H^T lambda is one application.
"""

from __future__ import annotations

import contextlib
import time
import warnings
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.sparse as sps
import warp as wp

from . import graphs
from .buffers import GrowArray
from .sherman_morrison import Modification, node_dofs, perturbation, summed_perturbation
from .sm_partition import partitioned_stream
from .transfer import PINNED, Staged

wp.set_module_options({"enable_backward": False})  # no gradients are taken


@wp.kernel
def relative_rotation_kernel(R: wp.array(dtype=wp.mat33d), R_ref: wp.array(dtype=wp.mat33d),
                             dR: wp.array(dtype=wp.mat33d)):
    """dR_n = R_n(t) R_ref_n^T (eq. 2 and 8)."""
    n = wp.tid()
    dR[n] = R[n] * wp.transpose(R_ref[n])


@wp.kernel
def identity_kernel(dR: wp.array(dtype=wp.mat33d)):
    dR[wp.tid()] = wp.identity(n=3, dtype=wp.float64)


class _Ticket:
    """One factorization in flight: what it was made from and the events that time it (or the
    future of the background thread that enqueues it and returns those events)."""

    def __init__(self, step, gen, uids, version, R, start=None, done=None, cpu_ms=None, future=None, R_host=None):
        self.step, self.gen, self.uids, self.version, self.R = step, gen, uids, version, R
        self.R_host = R_host  # (page-locked copy of R, the event after its copy), GPU only
        self.start, self.done, self.cpu_ms, self.future = start, done, cpu_ms, future

    def events(self):
        """(start, done) events, waiting for the background enqueue if there is one."""
        if self.future is not None and self.done is None:
            self.start, self.done = self.future.result()
        return self.start, self.done

    def ready(self) -> bool:
        if self.future is not None and not self.future.done():
            return False
        _, done = self.events()
        return done is None or done.is_complete

    def ms(self) -> float:
        start, done = self.events()
        if done is None:
            return float(self.cpu_ms)
        return float(wp.get_event_elapsed_time(start, done))


class FoldedCorrection:
    """The cutter's view of the corrections (``add``, ``clear``, ``perturbation_nodes``,
    ``stats``): each modification is folded into the device inverse when it happens.
    ``enabled=False`` keeps only the identity padding of eq. (10) (the uncorrected
    preconditioner of the paper's comparison)."""

    def __init__(self, owner: "AsyncDevicePreconditioner", enabled: bool = True):
        self.owner = owner
        self.enabled = bool(enabled)
        self.u_ms = 0.0  # time of the rank-3k updates, accumulated; the cutter resets it
        self.q_ms = 0.0
        self.folds = 0

    def add(self, mod: Modification, current_uids: np.ndarray) -> None:
        self.owner._modified(mod, np.asarray(current_uids, np.int64))

    def clear(self) -> None:
        self.owner.mods = []

    def perturbation_nodes(self) -> int:
        """Nodes of every modification the installed factor does not contain (the paper's N)."""
        mods = self.owner.mods
        return int(len(np.unique(np.concatenate([m.uids for m in mods])))) if mods else 0

    def stats(self) -> dict:
        return {"smf_terms": 0, "smf_columns": 0, "pending_modifications": len(self.owner.mods),
                "smf_folds": self.folds}


def constraint_rows(B, n_nodes: int):
    """Constraint columns B (3n x m, dense or sparse) in node form: (nodes (m, 4) int32, -1 for
    none; coef (m, 4, 3)), column a = sum_k e_{nodes[a, k]} (x) coef[a, k]. A column touching
    more than 4 nodes raises ValueError."""
    Bt = sps.csr_matrix(B.T) if sps.issparse(B) else sps.csr_matrix(np.asarray(B, dtype=np.float64).T)
    m = Bt.shape[0]
    if Bt.shape[1] != 3 * n_nodes:
        raise ValueError(f"preconditioner is for {3 * n_nodes} DOFs, got a block of {Bt.shape[1]} rows")
    row = np.repeat(np.arange(m), np.diff(Bt.indptr))
    node = Bt.indices // 3
    comp = Bt.indices % 3
    key = row.astype(np.int64) * n_nodes + node
    uniq, inv = np.unique(key, return_inverse=True)
    urow = uniq // n_nodes
    slot = np.arange(len(uniq)) - np.searchsorted(urow, urow, side="left")
    if len(slot) and slot.max() >= 4:
        raise ValueError("a constraint touches more than 4 nodes")
    nodes = np.full((m, 4), -1, np.int32)
    nodes[urow, slot] = (uniq % n_nodes).astype(np.int32)
    coef = np.zeros((m, 4, 3))
    np.add.at(coef, (row, slot[inv], comp), Bt.data)
    return nodes, coef


class AsyncDevicePreconditioner:
    """The preconditioner of eq. (2) with a device factor backend. See the module docstring.

    ``meta_fn()`` returns the simulation's topology ({"uids", "version"}) for the bookkeeping
    of modifications; ``backend`` a factor backend on ``device``.
    """

    uses_build_rotations = True  # begin_step takes the node rotations the integrator's build launched

    def __init__(self, backend, meta_fn, device, *, rotate=True, refresh_every=1, deterministic=False, lag=0,
                 reserve_sms=0, refresh_iterations=0, name="async_ldlt"):
        if isinstance(lag, bool) or not isinstance(lag, (int, np.integer)) or lag < 0:
            raise ValueError(f"lag must be a whole number of steps >= 0, got {lag!r}")
        if lag and not deterministic:
            raise ValueError("lag needs deterministic: true (a background factor arrives when it is ready)")
        self.backend = backend
        self.meta_fn = meta_fn
        self.device = wp.get_device(device)
        self.name = name
        self.rotate = bool(rotate)
        self.refresh_every = max(1, int(refresh_every))
        # > 0: a factor is requested (every refresh_every steps) only after a step whose PCG took
        # more than this many iterations
        self.refresh_iterations = int(refresh_iterations)
        self.deterministic = bool(deterministic)
        self.lag = int(lag)
        # the factor's stream: on a GPU confined to all but `reserve_sms` SMs where the driver can
        # (sm_partition), so that the steps never wait for a factorization's blocks; none for a
        # backend that factorizes on the simulation's stream (cuDSS)
        if getattr(backend, "one_stream", False):
            self.partition, self.partition_error = None, "the backend factorizes on the simulation's stream"
        else:
            self.partition, self.partition_error = partitioned_stream(self.device, int(reserve_sms))
        if self.partition is not None:
            self._side = self.partition.stream
        else:
            self._side = wp.Stream(self.device) if self.device.is_cuda else None
        self._vec = None  # apply_vector: (r staged from the host, z)
        self._rows = None  # delassus_rows: the constraint rows (nodes, coef), staged from the host
        self.correction: FoldedCorrection | None = None
        self.mods: list[Modification] = []
        self._busy = None  # the last factorization enqueued (its work buffer is in use until it ends)
        self._pool = None  # the background thread that enqueues factorizations (CUDA, asynchronous)
        self._gen = 0
        self._rotation_cmd = None  # (its arrays, the recorded launch of the relative rotations)
        # dR: a view of an allocation kept across node-count changes (its address, which a
        # captured apply holds, changes only when the node count outgrows it)
        self._dR_buf = GrowArray(wp.mat33d, self.device)
        self.worker_error = None
        self._reset_counters()

    @property
    def _main(self):
        """The simulation's stream (the device's current one), None on the CPU."""
        return wp.get_stream(self.device) if self.device.is_cuda else None

    @property
    def inner(self):
        """The object contact and cutting ask for the factor's services (this one)."""
        return self

    def _reset_counters(self):
        self.uids = None  # node uids of the inverse's numbering
        self.factor_version = -1
        self._R_ref_np = None  # R(t_u) of the factor in use on the host, made when a fold needs it ...
        self._R_ref_src = None  # ... from this device array (the factor's own R), where not changed since
        self._R_ref_copy = None  # ... or its page-locked copy made at the request (pinned array, event)
        self.R_ref = None  # device copy
        self.dR = None
        self.factor_step = -1
        self.step = 0
        self.last_request_step = -10**9
        self._pending: _Ticket | None = None
        self._held = None
        self.swaps = []
        self.factorization_ms = 0.0
        self.factor_latency_steps = 0
        self.factor_count = 0
        self.precond_ms = float("nan")
        self.failures = 0

    # ------------------------------------------------------------ schedule
    def _enqueue(self, side, ready, start, done):
        """The factorization on ``side`` behind the event ``ready``, timed by the events
        ``start`` and ``done`` (made by the caller): (start, done). Allocates nothing and
        loads no module (its launches go to ``side``, their modules loaded before), so that a
        background thread may run it while the simulation's thread captures graphs on its own
        stream."""
        if ready is not None:
            side.wait_event(ready)
        side.record_event(start)
        self.backend.factorize(stream=side)
        side.record_event(done)
        return start, done

    def _thread_init(self):
        """The enqueueing thread uses the device's primary context (the one Warp uses)."""
        import cupy

        cupy.cuda.runtime.setDevice(self.device.ordinal)

    def _request(self, system, background: bool = False) -> _Ticket:
        fem = system.fem
        meta = dict(self.meta_fn() or {})
        uids = np.asarray(meta.get("uids", np.arange(fem.n_nodes)), np.int64).copy()
        if self._main is not None and self._busy is not None:
            self._main.wait_event(self._busy.events()[1])  # the triplets and work buffer are free once the last one ended
        triplets = fem.assemble_triplets(system.m_coef, system.k_coef)
        self.backend.assemble(triplets, 3 * fem.n_nodes, stream=self._main, topology=meta.get("version"))
        R = wp.clone(fem.current_node_rotations())  # R(t_u) of this factor
        R_host = None
        if self._main is not None:  # read back now, behind the clone: a fold after the install then
            buf = PINNED.empty(R.shape, R.dtype)  # waits for this copy only, not for the steps queued by then
            wp.copy(buf, R, stream=self._main)
            R_host = (buf, self._main.record_event())
        if self._side is None:
            t0 = time.perf_counter()
            self.backend.factorize()
            ticket = _Ticket(self.step, self._gen, uids, int(meta.get("version", -1)), R,
                             cpu_ms=1000.0 * (time.perf_counter() - t0), R_host=R_host)
        else:
            # the factor's own stream, or the simulation's for a backend that must factorize and
            # solve on one stream (cuDSS)
            side = self._main if getattr(self.backend, "one_stream", False) else self._side
            ready = self._main.record_event() if side is not self._main else None
            args = (self.step, self._gen, uids, int(meta.get("version", -1)), R)
            events = (wp.Event(self.device, enable_timing=True), wp.Event(self.device, enable_timing=True))
            if background and side is not self._main:  # cuSOLVER's calls may block the host: a thread makes them
                if self._pool is None:
                    self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="factor-enqueue",
                                                    initializer=self._thread_init)
                ticket = _Ticket(*args, future=self._pool.submit(self._enqueue, side, ready, *events), R_host=R_host)
            else:
                ticket = _Ticket(*args, *self._enqueue(side, ready, *events), R_host=R_host)
            self._busy = ticket
        self.last_request_step = self.step
        return ticket

    def _install(self, t: _Ticket) -> bool:
        if t.gen != self._gen:
            return False
        try:
            _, done = t.events()
        except Exception as exc:  # noqa: BLE001 - the enqueue failed in the thread: keep the factor in use
            self.worker_error = f"{type(exc).__name__}: {exc}"
            self.failures += 1
            self._busy = None
            if self.partition is not None:  # the library refused the partitioned stream: a plain one from now on
                warnings.warn(f"factorization on the SM-partitioned stream failed ({self.worker_error}); "
                              "using a plain stream", RuntimeWarning, stacklevel=2)
                self.partition, self.partition_error = None, self.worker_error
                self._side = wp.Stream(self.device)
            return False
        if done is not None:
            self._main.wait_event(done)
        with self._changing():
            return self._install_changes(t)

    def _changing(self):
        """The backend's scope for a series of changes of its factor (see
        :meth:`~soft_tissue_sim.dense_inverse.DenseInverse.changing`), where it has one."""
        fn = getattr(self.backend, "changing", None)
        return fn() if fn is not None else contextlib.nullcontext()

    def _install_changes(self, t: _Ticket) -> bool:
        """The finished factor of ``t`` in use, the modifications made since its request folded in."""
        err = self.backend.install(stream=self._main)
        if err is not None:  # keep the factor in use (if any) and say why
            self.worker_error = err
            self.failures += 1
            return False
        self.uids = t.uids
        self.factor_version = t.version
        self._R_ref_src, self._R_ref_copy, self._R_ref_np = t.R, t.R_host, None  # on the host once a fold or compaction needs it
        self.factor_step = t.step
        self.factorization_ms = t.ms()
        self.factor_latency_steps = self.step - t.step
        self.factor_count += 1
        self.swaps.append(self.step)
        self.mods = [m for m in self.mods if m.version > self.factor_version]  # the factor contains the rest
        if self.mods:
            self._fold(self.mods)
        current = (self.meta_fn() or {}).get("uids")
        if current is not None:
            self._compact(np.asarray(current, np.int64))
        self._upload_R_ref()
        return True

    def factorizing(self) -> bool:
        """Whether a factorization enqueued on the device has not finished (asks, never waits)."""
        t = self._busy
        if t is None or self._side is None:
            return False
        if t.future is not None and not t.future.done():
            return True
        try:
            _, done = t.events()
        except Exception:  # noqa: BLE001 - a failed enqueue left nothing running
            return False
        return done is not None and not done.is_complete

    def refresh(self, system) -> None:
        """A factor of the current state, made and installed now (waits for it)."""
        self._refresh_now(system)

    def _refresh_now(self, system) -> None:
        t = self._request(system)
        if t.events()[1] is not None:
            wp.synchronize_event(t.done)
        self._install(t)

    def _due(self, system) -> bool:
        """Whether this step requests a new factor: ``refresh_every`` steps after the last request
        and, with ``refresh_iterations``, after a step whose PCG took more iterations than that
        (``system.last_iterations``; none yet: due)."""
        if self.step - self.last_request_step < self.refresh_every:
            return False
        its = getattr(system, "last_iterations", None)
        return self.refresh_iterations <= 0 or its is None or its > self.refresh_iterations

    def begin_step(self, system) -> None:
        fem = system.fem
        R = fem.current_node_rotations()  # launched by the integrator's build (node_rotations_in_build)
        self.step = int(system.step_index)
        if self.backend.n3 == 0 or self.uids is None:
            self._refresh_now(system)  # the only wait
        elif self.deterministic and self.lag:
            if self._held is not None and self.step >= self._held[0]:
                self._install(self._held[1])
                self._held = None
            if self._held is None and self._due(system):
                t = self._request(system)
                if t.done is not None:
                    wp.synchronize_event(t.done)
                self._held = (self.step + self.lag, t)
        elif self.deterministic:
            if self._due(system):
                self._refresh_now(system)
        else:
            t = self._pending
            if t is not None and t.ready():
                self._pending = None
                self._install(t)
            if not self.factorizing():
                graphs.release()  # nothing long in flight: replaced graphs go now, before the next request
            if self._pending is None and self._due(system):
                self._pending = self._request(system, background=True)
        if self.backend.n3 != 3 * fem.n_nodes:  # a size change no modification announced
            self._refresh_now(system)
        n = fem.n_nodes
        if self.dR is None or self.dR.shape[0] != n:
            self.dR = self._dR_buf.view(n)
        if self.rotate:  # the launch's arguments packed once while the arrays hold (a recorded launch)
            key = (R.ptr, self.R_ref.ptr, self.dR.ptr, n)
            if self._rotation_cmd is None or self._rotation_cmd[0] != key:
                self._rotation_cmd = key, wp.launch(relative_rotation_kernel, n, [R, self.R_ref, self.dR],
                                                    device=self.device, record_cmd=True)
            self._rotation_cmd[1].launch()
        else:
            wp.launch(identity_kernel, n, [self.dR], device=self.device)

    # ------------------------------------------------------------ modifications
    def make_correction(self, enabled: bool = True, rotate: bool = True) -> FoldedCorrection:
        """The correction object a cutter feeds modifications to (eq. 5-12)."""
        self.correction = FoldedCorrection(self, enabled)
        return self.correction

    def _modified(self, mod: Modification, current_uids: np.ndarray) -> None:
        self.mods.append(mod)
        if self.uids is not None:
            with self._changing():
                self._fold([mod])
                self._compact(current_uids)
            self._upload_R_ref()

    def _index(self, uids: np.ndarray) -> np.ndarray:
        order = np.argsort(self.uids, kind="stable")
        pos = np.searchsorted(self.uids, uids, sorter=order)
        pos = np.clip(pos, 0, len(order) - 1)
        idx = order[pos]
        if len(uids) and not np.array_equal(self.uids[idx], uids):
            raise KeyError("node uid unknown to the preconditioner")
        return idx

    def _fold(self, mods: list[Modification]) -> None:
        """The modifications ``mods`` (in their order) folded into the inverse in use as one
        update: the new nodes of each padded as identity rows (eq. 10) in turn, then one fold of
        N = sum_i G_i N_i G_i^T on the union of their DOFs. Folding them one by one adds the same
        terms to the inverse's matrix, so the result is the same inverse; an install that brings
        a factor up to date over several modifications makes one Woodbury solve instead of one
        per modification."""
        t0 = time.perf_counter()
        parts = []
        for mod in mods:
            created = mod.created[~np.isin(mod.created, self.uids)]
            if len(created):  # identity rows for the new nodes (eq. 10), their rotation at creation
                self.backend.regrow(np.arange(self.backend.n3), 3 * len(created))
                self.uids = np.concatenate([self.uids, created])
                self.R_ref_host = np.concatenate([self.R_ref_host, mod.R[np.searchsorted(mod.uids, created)]])
            idx = self._index(mod.uids)
            parts.append((idx, perturbation(mod, self.R_ref_host[idx], created, self.rotate)))
        corr = self.correction
        if corr is None or corr.enabled:
            idx, N = summed_perturbation(parts)
            self.backend.fold(node_dofs(idx), N)
        if corr is not None:
            corr.folds += 1
            corr.u_ms += 1000.0 * (time.perf_counter() - t0)

    def _compact(self, current: np.ndarray) -> None:
        if np.array_equal(current, self.uids):
            return
        idx = self._index(current)
        self.backend.regrow(node_dofs(idx), 0)
        self.uids = current.copy()
        self.R_ref_host = self.R_ref_host[idx]

    @property
    def R_ref_host(self) -> np.ndarray | None:
        """R(t_u) of the factor in use, (n, 3, 3) on the host (at the first use after an install:
        from the page-locked copy the request made, once that copy is done, else read from the
        device); set by the folds and the compaction."""
        if self._R_ref_np is None and self._R_ref_src is not None:
            if self._R_ref_copy is not None:
                buf, copied = self._R_ref_copy
                wp.synchronize_event(copied)
                self._R_ref_np = buf.numpy().astype(np.float64)  # (a copy: the buffer goes with the ticket)
            else:
                self._R_ref_np = self._R_ref_src.numpy().astype(np.float64)
        return self._R_ref_np

    @R_ref_host.setter
    def R_ref_host(self, value: np.ndarray) -> None:
        self._R_ref_np, self._R_ref_src, self._R_ref_copy = value, None, None

    def _upload_R_ref(self) -> None:
        """R_ref (device, kept address) := R(t_u): copied on the device from the factor's own R
        where no fold changed it, else uploaded from the host."""
        src = self._R_ref_src if self._R_ref_np is None else None
        n = src.shape[0] if src is not None else len(self._R_ref_np)
        if self.R_ref is None or self.R_ref.shape[0] != n:
            self.R_ref = wp.empty(n, dtype=wp.mat33d, device=self.device)
        if src is not None:
            wp.copy(self.R_ref, src)
        else:
            self.R_ref.assign(np.ascontiguousarray(self._R_ref_np))

    # ----------------------------------------------------------------- apply
    def apply(self, r: wp.array, z: wp.array) -> None:
        self.backend.apply(r, z, self.dR)

    def device_capable(self) -> bool:
        return self.backend.n3 > 0 and self.dR is not None and self.backend.n3 == 3 * self.dR.shape[0]

    def graph_capturable(self) -> bool:
        return self.backend.graph_key() is not None

    def graph_key(self) -> tuple | None:
        """The backend's key and dR's address: no node count (the dense backend's apply reads its
        size on the device; dR keeps its address while the node count holds in its allocation)."""
        k = self.backend.graph_key()
        return None if k is None else k + (self.dR.ptr,)

    def apply_columns(self, B: np.ndarray) -> np.ndarray:
        """P^-1 B for a block of columns B (3n, c), host in and out."""
        B = np.asarray(B, dtype=np.float64)
        n = B.shape[0] // 3
        out = np.empty_like(B)
        r = wp.empty(n, dtype=wp.vec3d, device=self.device)
        z = wp.empty(n, dtype=wp.vec3d, device=self.device)
        for c in range(B.shape[1]):
            r.assign(np.ascontiguousarray(B[:, c]).reshape(n, 3))
            self.apply(r, z)
            out[:, c] = z.numpy().reshape(-1)
        return out

    def apply_vector(self, b: np.ndarray) -> wp.array:
        """P^-1 b for one host vector b (3n,), left on the device: a (n,) vec3d array that the
        next call overwrites (no wait for the device: b goes up as :class:`Staged`)."""
        b = np.asarray(b, dtype=np.float64).reshape(-1, 3)
        if self._vec is None or self._vec[0].array.shape[0] != len(b):
            self._vec = (Staged(len(b), wp.vec3d, self.device), wp.empty(len(b), dtype=wp.vec3d, device=self.device))
        r, z = self._vec
        r.view()[:] = b
        self.apply(r.send(), z)
        return z

    def delassus(self, B) -> np.ndarray | None:
        """B^T P^-1 B for constraint columns B = H^T (3n, m) (W / dt^2 of eq. 4, corrected after
        cuts, rotated), or None when the backend cannot gather it (use apply_columns)."""
        if not hasattr(self.backend, "delassus"):
            return None
        W = self.delassus_rows(*constraint_rows(B, self.dR.shape[0]))
        return 0.5 * (W + W.T)

    def delassus_rows(self, nodes: np.ndarray, coef: np.ndarray) -> np.ndarray | None:
        """:meth:`delassus` for columns given in node form (see :func:`constraint_rows`), as
        gathered: symmetric up to rounding (the caller symmetrizes), a view valid until the next
        call. The rows go up into buffers kept between calls (grown to the largest m seen,
        :class:`Staged`), so that a call allocates nothing in the steady state."""
        if not hasattr(self.backend, "delassus"):
            return None
        m = len(nodes)
        if m == 0:
            return np.zeros((0, 0))
        if self._rows is None or self._rows[0].array.shape[0] < m:
            self._rows = (Staged((m, 4), wp.int32, self.device), Staged((m, 4), wp.vec3d, self.device))
        s_nodes, s_coef = self._rows
        s_nodes.view()[:m] = nodes
        s_coef.view()[:m] = coef
        return self.backend.delassus(s_nodes.send(4 * m), s_coef.send(4 * m), self.dR, m)

    def solves_contact_on_device(self) -> bool:
        """Can the contact LCP be solved where the factor is (:mod:`..contact.device_lcp`): a
        backend that gathers W from a row count on the device and applies P^-1 H^T from the rows
        (the dense inverse), installed."""
        b = self.backend
        return hasattr(b, "delassus_matrix") and hasattr(b, "apply_rows") and self.device_capable()

    def delassus_matrix(self, nodes: wp.array, coef: wp.array, sizes: wp.array, scale: float, W: wp.array) -> None:
        """W[:m, :m] = scale H P^-1 H^T for the first m = sizes[0] constraint rows in node form
        (device arrays): launches only (see :meth:`solves_contact_on_device`)."""
        self.backend.delassus_matrix(nodes, coef, self.dR, sizes, scale, W)

    def apply_rows(self, nodes: wp.array, coef: wp.array, lam: wp.array, sizes: wp.array, scale: float,
                   free: wp.array, out: wp.array) -> None:
        """out = scale P^-1 H^T lambda on the free nodes for the first sizes[0] constraint rows in
        node form (device arrays): launches only (see :meth:`solves_contact_on_device`)."""
        self.backend.apply_rows(nodes, coef, lam, sizes, self.dR, scale, free, out)

    def delassus_key(self) -> tuple:
        """What :meth:`delassus_matrix`'s and :meth:`apply_rows`' launches depend on besides their
        arguments: the inverse's address and leading dimension, dR's address (no size: both are
        launched over capacities and read the sizes on the device)."""
        b = self.backend
        return b.inv.ptr, getattr(b, "ld", None), self.dR.ptr

    # -------------------------------------------------------------- lifecycle
    def invalidate(self) -> None:
        self.mods = []
        self._gen += 1  # a factorization in flight is dropped when it ends
        self._reset_counters()
        self.backend.reset()

    def _close_after(self, busy: _Ticket) -> None:
        """On the enqueueing thread, after the enqueue of ``busy``: wait on the host for that
        factorization to end (so nothing still writes the buffers), then free the backend. Launches
        and allocates nothing of Warp's."""
        try:
            _, done = busy.events()
            if done is not None:
                wp.synchronize_event(done)
        except Exception:  # noqa: BLE001 - a failed enqueue left nothing running
            pass
        self.backend.close()

    def stats(self) -> dict:
        sw = self.swaps
        extra = self.correction.stats() if self.correction is not None else {}
        return extra | {
            "factor_age": self.step - self.factor_step if self.factor_step >= 0 else -1,
            "factorization_ms": self.factorization_ms,
            "factor_latency_steps": self.factor_latency_steps,
            "refresh_interval": (sw[-1] - sw[0]) / (len(sw) - 1) if len(sw) > 1 else 0.0,  # the mean gap
            "precond_ms": self.precond_ms,
            "worker": "device stream" if self._side is not None else "synchronous",
            "factor_sms": self.partition.sms if self.partition is not None else None,
            "backend": self.backend.name,
            "worker_error": self.worker_error,
            "factor_count": self.factor_count,
            "factor_failures": self.failures,
        }

    def close(self) -> None:
        """Returns at once: a factorization in flight is abandoned with the buffers. Where its
        enqueue still runs on the background thread (a library's first call there can block
        for a second), the rest of the close follows it on that thread instead of waiting."""
        self._pending = self._held = None
        busy = self._busy
        if self._pool is not None and busy is not None and busy.future is not None and not busy.future.done():
            self._pool.submit(self._close_after, busy)
            self._pool.shutdown(wait=False)
            return
        if self._pool is not None:
            self._pool.shutdown(wait=True)  # the enqueue is over: returns at once
        if self._busy is not None and self._main is not None:
            try:  # the buffers are freed on the simulation's stream: after the factorization ends there
                self._main.wait_event(self._busy.events()[1])
            except Exception:  # noqa: BLE001 - a failed enqueue left nothing running
                pass
        self.backend.close()
