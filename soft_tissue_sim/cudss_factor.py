"""The ``cudss`` factor backend: A(t_u) factorized by cuDSS (NVIDIA's sparse direct solver on
the GPU, through nvmath-python's ``DirectSolver``) and applied with its solve.

For bodies too large for a dense inverse. A is assembled on the device straight into the
values of a fixed CSR pattern (3x3 block triplets scattered by :func:`csr_scatter_kernel`;
the pattern and each triplet's place in it are found once per topology). Two solver objects
alternate: one serves the solves with the factor in use while the other is refactorized with
the next A; each is planned (ordering and symbolic factorization) once per pattern and
refactorized in place afterwards. An application of eq. (2) is a rotation into
the solver's right-hand side, cuDSS's solve (into a solution buffer of our own), and a
rotation back. cuDSS factorizes and solves on one stream, the simulation's: its solves with a
factor made on another stream are wrong, so a new factor is made in the step that requests
it (the host does not wait; the step's kernels queue behind it).

Not supported here (the factory refuses them): cutting (no correction of a cuDSS factor)
and contact (no gathered Delassus operator); the dense backend serves those scenes.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .buffers import unbounded_count
from .dense_inverse import rotate_in_kernel

wp.set_module_options({"enable_backward": False})  # no gradients are taken


@wp.kernel
def csr_scatter_kernel(rows: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.mat33d),
                       rank: wp.array(dtype=wp.int32), indptr: wp.array(dtype=wp.int32),
                       data: wp.array(dtype=wp.float64)):
    """data += the 3x3 block triplets, block t at rank[t] among the blocks of its block row."""
    t = wp.tid()
    r = 3 * rows[t]
    p = 3 * rank[t]
    v = vals[t]
    for a in range(3):
        base = indptr[r + a] + p
        for b in range(3):
            wp.atomic_add(data, base + b, v[a, b])


@wp.kernel
def rotate_out_kernel(dR: wp.array(dtype=wp.mat33d), y: wp.array(dtype=wp.float64), z: wp.array(dtype=wp.vec3d)):
    """z_i = dR_i y_i (the left rotation of eq. 2)."""
    i = wp.tid()
    z[i] = dR[i] * wp.vec3d(y[3 * i], y[3 * i + 1], y[3 * i + 2])


def block_csr_pattern(rows: np.ndarray, cols: np.ndarray, n_nodes: int):
    """The scalar CSR pattern (indptr, indices, int32) of a matrix of 3x3 blocks given as
    triplets, and each triplet's rank among the distinct blocks of its block row."""
    key = rows.astype(np.int64) * n_nodes + cols
    uniq, inv = np.unique(key, return_inverse=True)
    brow, bcol = uniq // n_nodes, uniq % n_nodes
    start = np.searchsorted(brow, np.arange(n_nodes + 1))
    count = np.diff(start)
    rank_u = np.arange(len(uniq)) - start[brow]
    # scalar row 3I + a holds 3 count_I entries: the blocks' columns 3J + b in block order
    indptr = np.zeros(3 * n_nodes + 1, np.int64)
    indptr[1:] = np.cumsum(np.repeat(3 * count, 3))
    indices = np.empty(indptr[-1], np.int64)
    for a in range(3):
        base = indptr[3 * brow + a] + 3 * rank_u
        for b in range(3):
            indices[base + b] = 3 * bcol + b
    return indptr.astype(np.int32), indices.astype(np.int32), rank_u[inv].astype(np.int32)


class _Slot:
    """One cuDSS solver with its own values and right-hand side (the pattern is shared)."""

    def __init__(self, pattern, device, stream):
        import cupy
        import cupyx.scipy.sparse as csp
        from nvmath.sparse.advanced import (DirectSolver, DirectSolverMatrixType, DirectSolverMatrixViewType,
                                            DirectSolverOptions)

        indptr, indices, n3 = pattern
        values = wp.zeros(int(indices.shape[0]), dtype=wp.float64, device=device)
        b = wp.zeros(n3, dtype=wp.float64, device=device)
        self.A = csp.csr_matrix((cupy.asarray(values), cupy.asarray(indices), cupy.asarray(indptr)), shape=(n3, n3))
        self.rhs = cupy.asarray(b)
        opts = DirectSolverOptions(sparse_system_type=DirectSolverMatrixType.SPD,
                                   sparse_system_view=DirectSolverMatrixViewType.FULL)
        self.solver = DirectSolver(self.A, self.rhs, options=opts, stream=stream.cuda_stream)
        # write where the solver reads (the matrix's values, the right-hand side), whatever it wrapped
        self.values = wp.array(ptr=self.A.data.data.ptr, dtype=wp.float64, shape=(int(indices.shape[0]),),
                               device=device)
        self.b = wp.array(ptr=self.rhs.data.ptr, dtype=wp.float64, shape=(n3,), device=device)
        # the solution in a buffer of our own (nvmath's solve would allocate a new one each call)
        from nvmath.bindings import cudss

        self.x = wp.zeros(n3, dtype=wp.float64, device=device)
        cudss.matrix_set_values(self.solver.x_ptr, self.x.ptr)
        self._keep = (values, b)
        self.planned = False

    def solve(self, stream) -> None:
        """x = A^-1 b with the factor of this solver, enqueued on ``stream``."""
        from nvmath.bindings import cudss

        s = self.solver
        cudss.set_stream(s.handle, stream.cuda_stream)
        cudss.execute(s.handle, cudss.Phase.SOLVE, s.config_ptr, s.data_ptr, s.a_ptr, s.x_ptr, s.b_ptr)

    def free(self):
        self.solver.free()


class CuDSSFactor:
    """Two cuDSS solvers on one device (see the module docstring)."""

    name = "cudss"
    one_stream = True  # a factor made on one stream and solved on another gives wrong solves: one stream

    def __init__(self, device):
        self.device = wp.get_device(device)
        if not self.device.is_cuda:
            raise ValueError("the cudss backend needs a CUDA device")
        import nvmath.sparse.advanced  # noqa: F401 - fail here, with the import error, when not installed

        self._key = None  # the pattern's identity: the triplets' rows and cols
        self._pattern = None
        self._rank = None
        self._rows = None
        self._slots: list[_Slot | None] = [None, None]
        self._active = None  # index of the slot in use
        self._next = 0

    @property
    def n3(self) -> int:
        return 0 if self._active is None else int(self._pattern[2])

    def _ensure_pattern(self, rows: wp.array, cols: wp.array, n3: int, topology) -> None:
        key = (n3, rows.shape[0], topology)
        if key == self._key and topology is not None:
            return
        r, c = rows.numpy(), cols.numpy()
        indptr, indices, rank = block_csr_pattern(r, c, n3 // 3)
        d = self.device
        self._pattern = (wp.array(indptr, dtype=wp.int32, device=d), wp.array(indices, dtype=wp.int32, device=d), n3)
        self._rank = wp.array(rank, dtype=wp.int32, device=d)
        for s in self._slots:
            if s is not None:
                s.free()
        self._slots = [None, None]
        self._active = None
        self._next = 0
        self._key = key

    def assemble(self, triplets, n3: int, stream=None, topology=None) -> None:
        """The next slot's values = A from 3x3 block triplets, on ``stream``; ``topology``
        identifies the mesh (the pattern is rebuilt when it changes; None: every time)."""
        rows, cols, vals = triplets
        self._ensure_pattern(rows, cols, n3, topology)
        i = self._next
        if self._slots[i] is None:
            self._slots[i] = _Slot(self._pattern, self.device, stream)
        slot = self._slots[i]
        slot.values.zero_()
        wp.launch(csr_scatter_kernel, rows.shape[0], [rows, vals, self._rank, self._pattern[0], slot.values],
                  device=self.device, stream=stream)

    def factorize(self, stream=None) -> None:
        slot = self._slots[self._next]
        s = stream.cuda_stream
        if not slot.planned:
            slot.solver.plan(stream=s)
            slot.planned = True
        slot.solver.factorize(stream=s)

    def install(self, stream=None) -> str | None:
        slot = self._slots[self._next]
        info = getattr(slot.solver.factorization_info, "info", 0)
        if info not in (0, None):
            return f"cuDSS factorization failed (info {info}): A is not positive definite"
        self._active = self._next
        self._next = 1 - self._next
        return None

    def apply(self, r: wp.array, z: wp.array, dR: wp.array) -> None:
        """z = dR A^-1 dR^T r with cuDSS's solve, on the current stream (no allocation)."""
        slot = self._slots[self._active]
        n = r.shape[0]
        wp.launch(rotate_in_kernel, n, [dR, r, slot.b, unbounded_count(self.device)], device=self.device)
        slot.solve(wp.get_stream(self.device))
        wp.launch(rotate_out_kernel, n, [dR, slot.x, z], device=self.device)

    def graph_key(self):
        return None  # cuDSS's solve is not captured in the PCG graph

    def reset(self) -> None:
        self._active = None

    def close(self) -> None:
        for s in self._slots:
            if s is not None:
                s.free()
        self._slots = [None, None]
        self._active = None
