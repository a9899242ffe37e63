"""The contact LCP of eq. (3) solved where the factor is, inside the correction's launches.

For a contact set of at most ``contact.device_lcp_rows`` constraint rows and a factor that
gathers the Delassus operator on the device (the dense inverse), the response of eq. (4) is
a chain of launches with no read in between, which the integrator captures with the
correction, the penetration detection and the guard (one graph a step):

1. the rows (H in node form), delta^0, the warm start and the contacts' friction go up in two
   page-locked buffers (one copy each);
2. W = dt^2 H P^-1 H^T is gathered into a matrix of the buffers' capacity, the row count read
   on the device (:func:`~soft_tissue_sim.dense_inverse.delassus_matrix_kernel`), so that one
   captured graph serves every contact count;
3. :func:`device_pgs_kernel` checks W as :func:`.compliance.positive_definite` does (a Cholesky
   factorization of W + 1e-10 max(diag W) I) and runs the projected Gauss-Seidel sweeps of
   :mod:`.pgs` on one thread, from the warm start;
4. H^T lambda is scattered onto the nodes, P^-1 applied (eq. 2) and dx = dt^2 P^-1 H^T lambda
   zeroed on the fixed nodes.

lambda, the sweeps, the residual and the check's verdict are read with the guard after the
correction. Where W is not positive definite the device solve makes lambda = 0 (no
correction) and says so: the caller restores the free motion and solves the step's contacts
on the host, with the block diagonal of A (as :meth:`.solver.ContactSolver._respond` does).
Sweeps that end above the tolerance stand, as they do on the host with friction: the host's
active-set finish of a frictionless LCP (:func:`.pgs.active_set`) is not run here (redoing
those steps on the host cost them about 3 ms). One thread sweeps in O(m^2) a sweep: the row
limit keeps a sweep within microseconds; larger sets are solved on the host.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..transfer import Staged
from .geometry import F64
from .pgs import pgs_sweeps


@wp.kernel
def scaled_free_kernel(y: wp.array(dtype=wp.vec3d), s: wp.float64, free: wp.array(dtype=wp.float64),
                       out: wp.array(dtype=wp.vec3d)):
    """out = s y on the free nodes, 0 on the fixed ones."""
    i = wp.tid()
    out[i] = (s * free[i]) * y[i]


@wp.func
def positive_definite_rows(W: wp.array2d(dtype=wp.float64), L: wp.array2d(dtype=wp.float64), m: int):
    """1 if the leading m x m block of the symmetric W is usable by Gauss-Seidel (finite, positive
    diagonal, a Cholesky factorization of W + 1e-10 max(diag W) I into L that succeeds), else 0:
    :func:`..compliance.positive_definite` on one thread."""
    dmax = F64(0.0)
    for i in range(m):
        d = W[i, i]
        if not (d > F64(0.0)) or not wp.isfinite(d):
            return 0
        dmax = wp.max(dmax, d)
    shift = F64(1e-10) * dmax
    for j in range(m):
        s = W[j, j] + shift
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not (s > F64(0.0)) or not wp.isfinite(s):
            return 0
        ljj = wp.sqrt(s)
        L[j, j] = ljj
        for i in range(j + 1, m):
            t = W[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / ljj
    return 1


@wp.kernel
def device_pgs_kernel(
    W: wp.array2d(dtype=wp.float64),
    d0: wp.array(dtype=wp.float64),
    lam0: wp.array(dtype=wp.float64),
    row_start: wp.array(dtype=wp.int32),
    n_rows: wp.array(dtype=wp.int32),
    mu: wp.array(dtype=wp.float64),
    sizes: wp.array(dtype=wp.int32),
    max_iterations: int,
    tolerance: wp.float64,
    pyramid: int,
    L: wp.array2d(dtype=wp.float64),
    lam: wp.array(dtype=wp.float64),
    delta: wp.array(dtype=wp.float64),
    info: wp.array(dtype=wp.float64),
):
    """The LCP of :func:`.pgs.pgs_kernel` with m = sizes[0] rows and nc = sizes[1] contacts read
    on the device, W checked first (:func:`positive_definite_rows`). info = [sweeps, residual,
    1 if W was usable else 0]; an unusable W leaves lambda = 0. One thread."""
    m = sizes[0]
    nc = sizes[1]
    for i in range(m):
        lam[i] = F64(0.0)
    info[0] = F64(0.0)
    info[1] = F64(0.0)
    info[2] = F64(0.0)
    if positive_definite_rows(W, L, m) == 0:
        return
    info[2] = F64(1.0)
    for i in range(m):
        lam[i] = lam0[i]
    it, res = pgs_sweeps(W, d0, row_start, n_rows, mu, m, nc, max_iterations, tolerance, pyramid, lam, delta)
    info[0] = F64(it)
    info[1] = res


@wp.kernel
def rows_transpose_times_kernel(nodes: wp.array2d(dtype=wp.int32), coef: wp.array2d(dtype=wp.vec3d),
                                lam: wp.array(dtype=wp.float64), sizes: wp.array(dtype=wp.int32),
                                out: wp.array(dtype=wp.vec3d)):
    """out += H^T lambda for the first sizes[0] rows (out zeroed before): each row's
    coefficients times its lambda, added onto its nodes."""
    r = wp.tid()
    if r < sizes[0]:
        for s in range(4):
            i = nodes[r, s]
            if i >= 0:
                wp.atomic_add(out, i, coef[r, s] * lam[r])


def _view(base: wp.array, offset: int, dtype, shape) -> wp.array:
    """A typed array over ``base``'s memory from element ``offset`` of ``base``'s dtype."""
    return wp.array(ptr=base.ptr + offset * wp.types.type_size_in_bytes(base.dtype), dtype=dtype, shape=shape,
                    device=base.device)


class DeviceLCP:
    """The buffers of the device solve for up to ``rows`` constraint rows (as many contacts),
    kept between steps at fixed addresses (captured graphs stay valid), and the launches.

    Inputs (:meth:`stage`): an int32 buffer [m, nc | row_start | n_rows | nodes (rows, 4)] and
    a float64 one [delta^0 | warm start | mu | coef (rows, 4, 3)], each sent in one copy.
    Output (:attr:`out`): [sweeps, residual, W usable | lambda (rows)].
    """

    def __init__(self, rows: int, device):
        self.rows = cap = int(rows)
        self.device = wp.get_device(device)
        self._i = Staged(2 + 2 * cap + 4 * cap, wp.int32, self.device)
        self._f = Staged(3 * cap + 12 * cap, wp.float64, self.device)
        i, f = self._i.array, self._f.array
        self.sizes = _view(i, 0, wp.int32, (2,))
        self.row_start = _view(i, 2, wp.int32, (cap,))
        self.n_rows = _view(i, 2 + cap, wp.int32, (cap,))
        self.nodes = _view(i, 2 + 2 * cap, wp.int32, (cap, 4))
        self.d0 = _view(f, 0, wp.float64, (cap,))
        self.lam0 = _view(f, cap, wp.float64, (cap,))
        self.mu = _view(f, 2 * cap, wp.float64, (cap,))
        self.coef = _view(f, 3 * cap, wp.vec3d, (cap, 4))
        self.W = wp.zeros((cap, cap), dtype=wp.float64, device=self.device)
        self.L = wp.zeros((cap, cap), dtype=wp.float64, device=self.device)
        self.delta = wp.zeros(cap, dtype=wp.float64, device=self.device)
        self.out = wp.zeros(3 + cap, dtype=wp.float64, device=self.device)
        self.info = _view(self.out, 0, wp.float64, (3,))
        self.lam = _view(self.out, 3, wp.float64, (cap,))
        self._n = -1
        self.r = self.z = self.dx = None  # (n,) vec3d: H^T lambda, P^-1 of it, the correction

    def fits(self, m: int) -> bool:
        return 0 < m <= self.rows

    def stage(self, nodes: np.ndarray, coef: np.ndarray, d0: np.ndarray, lam0: np.ndarray,
              row_start: np.ndarray, n_rows: np.ndarray, mu: np.ndarray) -> None:
        """The problem's m rows and nc contacts into the page-locked buffers, sent (no wait)."""
        m, nc, cap = len(d0), len(row_start), self.rows
        iv, fv = self._i.view(), self._f.view()
        iv[0], iv[1] = m, nc
        iv[2:2 + nc] = row_start
        iv[2 + cap:2 + cap + nc] = n_rows
        iv[2 + 2 * cap:2 + 2 * cap + 4 * m] = nodes.reshape(-1)
        fv[:m] = d0
        fv[cap:cap + m] = lam0
        fv[2 * cap:2 * cap + nc] = mu
        fv[3 * cap:3 * cap + 12 * m] = coef.reshape(-1)
        self._i.send()
        self._f.send()

    def _body_buffers(self, n: int) -> None:
        if n != self._n:
            self.r, self.z, self.dx = (wp.zeros(n, dtype=wp.vec3d, device=self.device) for _ in range(3))
            self._n = n

    def key(self, inner, free: wp.array, dt: float, options: tuple) -> tuple:
        """What :meth:`launch`'s launches depend on (the buffers are fixed while the node count
        holds)."""
        self._body_buffers(free.shape[0])
        return (inner.graph_key(), inner.delassus_key(), free.ptr, self.dx.ptr, float(dt), *options)

    def launch(self, inner, free: wp.array, dt: float, max_iterations: int, tolerance: float,
               pyramid: bool) -> wp.array:
        """W, the LCP, H^T lambda, P^-1 (eq. 2) and dx = dt^2 P^-1 H^T lambda on the free nodes:
        launches only. Returns dx (a (n,) vec3d array kept between steps)."""
        d = self.device
        n = free.shape[0]
        self._body_buffers(n)
        inner.delassus_matrix(self.nodes, self.coef, self.sizes, dt * dt, self.W)
        wp.launch(device_pgs_kernel, 1, [self.W, self.d0, self.lam0, self.row_start, self.n_rows, self.mu,
                                         self.sizes, int(max_iterations), float(tolerance), int(bool(pyramid)),
                                         self.L, self.lam, self.delta, self.info], device=d)
        self.r.zero_()
        wp.launch(rows_transpose_times_kernel, self.rows, [self.nodes, self.coef, self.lam, self.sizes, self.r],
                  device=d)
        inner.apply(self.r, self.z)
        wp.launch(scaled_free_kernel, n, [self.z, float(dt * dt), free, self.dx], device=d)
        return self.dx


class PendingLCP:
    """A contact step whose LCP is solved on the device: the caller launches it with the
    correction (:meth:`key`, :meth:`launch`, its output read with the guard) and hands the
    read output to :meth:`finish`."""

    def __init__(self, lcp: DeviceLCP, inner, free: wp.array, dt: float, options: dict, m: int, finish):
        self.lcp, self.inner, self.free, self.dt, self.m = lcp, inner, free, float(dt), int(m)
        o = options
        self._args = (int(o["max_iterations"]), float(o["tolerance"]), o["friction_cone"] == "pyramid")
        self._finish = finish

    def key(self) -> tuple:
        return self.lcp.key(self.inner, self.free, self.dt, self._args)

    def launch(self) -> tuple[wp.array, list[wp.array]]:
        """(dx, the arrays to read after it)."""
        return self.lcp.launch(self.inner, self.free, self.dt, *self._args), [self.lcp.out]

    def finish(self, out: np.ndarray) -> bool:
        """Hand lambda, the sweeps and the residual (``out`` read from :attr:`DeviceLCP.out`) to the
        contact step's finish; False where W was not usable (lambda was 0: nothing corrected) and
        the host must solve the step's contacts instead."""
        if out[2] == 0.0:
            return False
        self._finish(np.array(out[3:3 + self.m]), int(out[0]), float(out[1]))
        return True
