"""The contact LCP (paper eq. 3) by projected Gauss-Seidel: a Warp kernel and its launch.

    delta = W lambda + delta^0,   0 <= delta_n  _|_  lambda_n >= 0,
    |lambda_t| <= mu lambda_n     (Coulomb: a disk, or a pyramid per tangent component)

Contact c owns row ``row_start[c]`` (normal) and, with friction, the two tangent rows after
it. Invariants of the result: lambda_n >= 0 and the friction force within its cone; the
residual is the largest change one more (Jacobi) sweep would make [m], 0 exactly at a
solution. The kernel runs on one thread (the sweeps are sequential), on the CPU.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .geometry import F64


@wp.func
def contact_update(
    W: wp.array2d(dtype=wp.float64),
    delta: wp.array(dtype=wp.float64),
    lam: wp.array(dtype=wp.float64),
    r: int,
    rows: int,
    mu: wp.float64,
    pyramid: int,
):
    """Projected Gauss-Seidel update of the contact whose normal row is r, from the current
    lambda and delta = W lambda + d0 (neither written). Returns (lambda_n, lambda_t1,
    lambda_t2, change), the change being the largest W_rr |new - old| of its rows [m]; for an
    active normal row that is |delta_n|."""
    zero = F64(0.0)
    dn = delta[r]
    ln = wp.max(zero, lam[r] - dn / W[r, r])
    change = W[r, r] * wp.abs(ln - lam[r])
    l1 = zero
    l2 = zero
    if rows == 3:
        dln = ln - lam[r]  # the tangential gaps see the new normal force
        t1 = delta[r + 1] + W[r + 1, r] * dln
        t2 = delta[r + 2] + W[r + 2, r] * dln
        a11 = W[r + 1, r + 1]
        a22 = W[r + 2, r + 2]
        a12 = F64(0.5) * (W[r + 1, r + 2] + W[r + 2, r + 1])
        det = a11 * a22 - a12 * a12
        l1 = lam[r + 1]
        l2 = lam[r + 2]
        if det > zero:  # stick: zero tangential displacement
            l1 = l1 - (a22 * t1 - a12 * t2) / det
            l2 = l2 - (a11 * t2 - a12 * t1) / det
        lim = mu * ln
        if pyramid != 0:
            l1 = wp.clamp(l1, -lim, lim)
            l2 = wp.clamp(l2, -lim, lim)
        else:
            lt = wp.sqrt(l1 * l1 + l2 * l2)
            if lt > lim:  # slide: on the disk's rim
                s = zero
                if lt > zero:
                    s = lim / lt
                l1 = l1 * s
                l2 = l2 * s
        change = wp.max(change, wp.max(a11 * wp.abs(l1 - lam[r + 1]), a22 * wp.abs(l2 - lam[r + 2])))
    return ln, l1, l2, change


@wp.func
def exact_delta(W: wp.array2d(dtype=wp.float64), d0: wp.array(dtype=wp.float64), lam: wp.array(dtype=wp.float64),
                delta: wp.array(dtype=wp.float64), m: int):
    """delta = W lambda + d0 over the first m rows, summed afresh (the sweeps update it
    incrementally)."""
    for i in range(m):
        d = d0[i]
        for j in range(m):
            d += W[i, j] * lam[j]
        delta[i] = d


@wp.func
def move(W: wp.array2d(dtype=wp.float64), delta: wp.array(dtype=wp.float64), lam: wp.array(dtype=wp.float64),
         j: int, value: wp.float64, m: int):
    """lambda_j <- value, and delta by W's column j (W symmetric: its row j) times the change."""
    d = value - lam[j]
    if d != F64(0.0):
        for i in range(m):
            delta[i] += W[j, i] * d
        lam[j] = value


@wp.func
def pgs_residual(
    W: wp.array2d(dtype=wp.float64),
    d0: wp.array(dtype=wp.float64),
    lam: wp.array(dtype=wp.float64),
    delta: wp.array(dtype=wp.float64),
    row_start: wp.array(dtype=wp.int32),
    n_rows: wp.array(dtype=wp.int32),
    mu: wp.array(dtype=wp.float64),
    pyramid: int,
    m: int,
    nc: int,
):
    """Largest change a (Jacobi) sweep would make: 0 exactly at a solution of the LCP [m].
    delta is first summed afresh from lambda."""
    exact_delta(W, d0, lam, delta, m)
    res = F64(0.0)
    for c in range(nc):
        ln, l1, l2, ch = contact_update(W, delta, lam, row_start[c], n_rows[c], mu[c], pyramid)
        res = wp.max(res, ch)
    return res


@wp.kernel
def pgs_kernel(
    W: wp.array2d(dtype=wp.float64),
    d0: wp.array(dtype=wp.float64),
    row_start: wp.array(dtype=wp.int32),
    n_rows: wp.array(dtype=wp.int32),
    mu: wp.array(dtype=wp.float64),
    m: int,
    nc: int,
    max_iterations: int,
    tolerance: wp.float64,
    pyramid: int,
    lam: wp.array(dtype=wp.float64),
    delta: wp.array(dtype=wp.float64),
    info: wp.array(dtype=wp.float64),
):
    """Projected Gauss-Seidel for delta = W lambda + d0 with Signorini-Coulomb contacts.

    Contact c owns row row_start[c] (normal) and, if n_rows[c] == 3, the two tangent rows
    after it. delta is kept equal to W lambda + d0 as lambda changes (a change of lambda_j adds
    W's column j times it), so a contact whose forces do not change (one apart, say) costs
    O(1) a sweep; it is summed afresh for each residual. Sweeps until the largest change (see
    :func:`contact_update`) of a sweep and the residual (:func:`pgs_residual`) are <=
    tolerance. info = [sweeps, residual]. W symmetric. The problem is the first m rows and nc
    contacts of the arrays (which may be larger: reused buffers). One thread: launched with
    dim 1 on the CPU.
    """
    exact_delta(W, d0, lam, delta, m)
    it = int(0)
    res = F64(-1.0)
    for sweep in range(max_iterations):
        change = F64(0.0)
        for c in range(nc):
            r = row_start[c]
            ln, l1, l2, ch = contact_update(W, delta, lam, r, n_rows[c], mu[c], pyramid)
            move(W, delta, lam, r, ln, m)
            if n_rows[c] == 3:
                move(W, delta, lam, r + 1, l1, m)
                move(W, delta, lam, r + 2, l2, m)
            change = wp.max(change, ch)
        it = sweep + 1
        res = F64(-1.0)
        if change <= tolerance:  # converged if the residual (a sweep not applied) agrees
            res = pgs_residual(W, d0, lam, delta, row_start, n_rows, mu, pyramid, m, nc)
            if res <= tolerance:
                break
    if res < F64(0.0):
        res = pgs_residual(W, d0, lam, delta, row_start, n_rows, mu, pyramid, m, nc)
    info[0] = F64(it)
    info[1] = res


class PGS:
    """The projected Gauss-Seidel solver with its CPU buffers kept between solves: they grow to
    the largest problem seen and are filled in place, and the kernel's launch is recorded once
    per set of buffers, so that a solve allocates no Warp array and makes one launch."""

    def __init__(self):
        self.rows_cap = self.contacts_cap = 0
        self._cmd = None

    def _reserve(self, m: int, nc: int) -> None:
        """Buffers for at least m rows and nc contacts (and the recorded launch over them)."""
        if m <= self.rows_cap and nc <= self.contacts_cap:
            return
        self.rows_cap, self.contacts_cap = max(m, self.rows_cap, 16), max(nc, self.contacts_cap, 16)
        rc, cc = self.rows_cap, self.contacts_cap
        z = lambda shape, dtype: wp.zeros(shape, dtype=dtype, device="cpu")  # noqa: E731
        self.W, self.d0, self.lam, self.delta = z((rc, rc), wp.float64), z(rc, wp.float64), z(rc, wp.float64), \
            z(rc, wp.float64)
        self.row_start, self.n_rows, self.mu = z(cc, wp.int32), z(cc, wp.int32), z(cc, wp.float64)
        self.info = z(2, wp.float64)
        self._cmd = wp.launch(pgs_kernel, 1, [self.W, self.d0, self.row_start, self.n_rows, self.mu, 0, 0, 0, 0.0, 0,
                                              self.lam, self.delta, self.info], device="cpu", record_cmd=True)
        self._np = {name: getattr(self, name).numpy() for name in
                    ("W", "d0", "lam", "row_start", "n_rows", "mu", "info")}

    def solve(self, W: np.ndarray, d0: np.ndarray, row_start: np.ndarray, rows: np.ndarray, mu: np.ndarray,
              max_iterations: int, tolerance: float, pyramid: bool,
              lam0: np.ndarray) -> tuple[np.ndarray, int, float]:
        """Solve the LCP from the warm start ``lam0``: (lambda, sweeps, residual [m])."""
        m, nc = len(d0), len(row_start)
        self._reserve(m, nc)
        a = self._np
        a["W"][:m, :m] = W
        a["d0"][:m] = d0
        a["lam"][:m] = lam0
        a["row_start"][:nc] = row_start
        a["n_rows"][:nc] = rows
        a["mu"][:nc] = mu
        cmd = self._cmd
        for index, value in ((5, m), (6, nc), (7, int(max_iterations)), (8, float(tolerance)), (9, int(pyramid))):
            cmd.set_param_at_index(index, value)
        cmd.launch()
        its, res = a["info"]
        return a["lam"][:m].copy(), int(its), float(res)

