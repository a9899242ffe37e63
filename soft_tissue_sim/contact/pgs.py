"""The contact LCP (paper eq. 3): projected Gauss-Seidel (a Warp kernel) and, for a
frictionless LCP, an exact active-set finish on the host.

    delta = W lambda + delta^0,   0 <= delta_n  _|_  lambda_n >= 0,
    |lambda_t| <= mu lambda_n     (Coulomb: a disk, or a pyramid per tangent component)

Contact c owns row ``row_start[c]`` (normal) and, with friction, the two tangent rows after
it. Invariants of the result: lambda_n >= 0 and the friction force within its cone; the
residual is the largest change one more (Jacobi) sweep would make [m], 0 exactly at a
solution. The kernel runs on one thread (the sweeps are sequential), on the CPU.

Projected Gauss-Seidel converges slowly where W is near singular: rows that nearly repeat a
constraint (a node contact and face contacts next to it, self-contacts of one fold) share
their force along directions of W with eigenvalues at 1e-6 to 1e-17 of the largest, and the
sweeps move the shares by tiny amounts each. A frictionless LCP with W symmetric positive
semidefinite is the convex quadratic program

    min  1/2 lambda^T W lambda + delta^0 . lambda   subject to  lambda >= 0,

i.e. a non-negative least-squares problem given by its normal equations (W = X^T X,
-delta^0 = X^T y), which Lawson and Hanson's active-set method solves exactly in finitely
many steps; Bro and de Jong (1997, "A fast non-negativity-constrained least squares
algorithm") run it on W and delta^0 themselves. :class:`PGS` makes a few sweeps first (their
passive set is the method's warm start, as in the PGS-subspace-minimization methods of
Kocvara and Zowe, and Morales, Nocedal and Smelyanskiy) and finishes with
:func:`active_set`. With friction the kernel's sweeps run alone: the Coulomb problem is not
a quadratic program, and where nearly repeated contacts share a force the split between
sticking and sliding is itself degenerate.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp
from scipy.linalg.lapack import dpotrf, dpotrs

from .geometry import F64

wp.set_module_options({"enable_backward": False})  # no gradients are taken

FIRST_SWEEPS = 10  # the frictionless LCP's sweeps before the active-set finish (PGS)


@wp.func
def contact_update(
    W: wp.array2d(dtype=wp.float64),
    delta: Any,
    lam: wp.array(dtype=wp.float64),
    r: int,
    rows: int,
    mu: wp.float64,
    pyramid: int,
):
    """Projected Gauss-Seidel update of the contact whose normal row is r, from the current
    lambda and delta = W lambda + d0 (neither written; float64 arrays, or delta a shared tile as
    :mod:`.device_lcp`'s block holds it). Returns
    (lambda_n, lambda_t1, lambda_t2, change), the change being the largest W_rr |new - old| of
    its rows [m]; for an active normal row that is |delta_n|."""
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
def row_delta(W: wp.array2d(dtype=wp.float64), d0: wp.array(dtype=wp.float64), lam: wp.array(dtype=wp.float64),
              i: int, m: int):
    """(W lambda + d0)_i over the first m columns, summed afresh in column order."""
    d = d0[i]
    for j in range(m):
        d += W[i, j] * lam[j]
    return d


@wp.func
def exact_delta(W: wp.array2d(dtype=wp.float64), d0: wp.array(dtype=wp.float64), lam: wp.array(dtype=wp.float64),
                delta: wp.array(dtype=wp.float64), m: int):
    """delta = W lambda + d0 over the first m rows, summed afresh (the sweeps update it
    incrementally)."""
    for i in range(m):
        delta[i] = row_delta(W, d0, lam, i, m)


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
def jacobi_change(
    W: wp.array2d(dtype=wp.float64),
    delta: Any,
    lam: wp.array(dtype=wp.float64),
    row_start: wp.array(dtype=wp.int32),
    n_rows: wp.array(dtype=wp.int32),
    mu: wp.array(dtype=wp.float64),
    pyramid: int,
    nc: int,
):
    """The largest change of :func:`contact_update` over the nc contacts from lambda and delta
    as they are (arrays, or delta the block's shared tile), none applied [m]."""
    res = F64(0.0)
    for c in range(nc):
        ln, l1, l2, ch = contact_update(W, delta, lam, row_start[c], n_rows[c], mu[c], pyramid)
        res = wp.max(res, ch)
    return res


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
    return jacobi_change(W, delta, lam, row_start, n_rows, mu, pyramid, nc)


@wp.func
def pgs_sweeps(
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
):
    """The sweeps of :func:`pgs_kernel` from the lambda given (updated in place); returns
    (sweeps, residual)."""
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
    return it, res


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
    it, res = pgs_sweeps(W, d0, row_start, n_rows, mu, m, nc, max_iterations, tolerance, pyramid, lam, delta)
    info[0] = F64(it)
    info[1] = res


def frictionless_residual(W: np.ndarray, d0: np.ndarray, lam: np.ndarray) -> float:
    """:func:`pgs_residual` of a frictionless LCP (each row a contact's normal), on the host: the
    largest W_ii |max(0, lambda_i - delta_i / W_ii) - lambda_i| [m]."""
    if len(d0) == 0:
        return 0.0
    diag = W.diagonal()
    delta = W @ lam + d0
    return float(np.max(diag * np.abs(np.maximum(0.0, lam - delta / diag) - lam)))


def face_solve(W: np.ndarray, d0: np.ndarray, rows: np.ndarray, shift: float) -> np.ndarray | None:
    """The minimizer of 1/2 lambda^T W lambda + delta^0 . lambda over the face where only
    ``rows`` are free: W_PP s = -delta^0_P, by a Cholesky factor of W_PP + shift I and one
    step of refinement against W_PP itself (so that the shift, there for a singular W_PP,
    leaves an error of order shift^2 only where W_PP is regular). None where W_PP + shift I is
    not positive definite."""
    Wpp = W.take(rows, 0).take(rows, 1)
    b = -d0[rows]
    A = Wpp + shift * np.eye(len(rows))
    c, info = dpotrf(A.T, lower=1, clean=0, overwrite_a=1)  # A symmetric: its transpose is Fortran-ordered
    if info != 0:
        return None
    s = dpotrs(c, b, lower=1)[0]
    return s + dpotrs(c, b - Wpp @ s, lower=1)[0]


def active_set(W: np.ndarray, d0: np.ndarray, lam: np.ndarray, tolerance: float, max_steps: int,
               shift: float = 1e-12) -> tuple[np.ndarray, int]:
    """Lawson and Hanson's active-set method for the frictionless LCP, on W and delta^0 (Bro
    and de Jong's form), from the warm start ``lam`` (projected onto lambda >= 0); returns
    (lambda, face solves made).

    The passive set P starts as the rows with lambda > 0. A step solves the face problem of P
    (:func:`face_solve`, W_PP shifted by ``shift`` times the largest diagonal of W, so that
    repeated rows give a finite, shared force instead of a division by zero). If the solution
    s is positive on P it becomes lambda, and the row with the most negative delta joins P;
    otherwise lambda moves towards s until a row of P reaches 0 (the ratio test, so lambda
    stays feasible and the objective decreases), that row leaves P, and the face is solved
    again. It ends when no row outside P has delta < -tolerance and lambda solves its face
    (then the residual of :func:`pgs_residual` is <= tolerance up to the face solve's
    rounding), or unfinished, with the last feasible iterate: after ``max_steps`` face solves,
    where a face is not positive definite (W indefinite), or where a row that just joined
    leaves again without a step (rounding in a degenerate face). A step costs one Cholesky
    factorization of |P| rows and one product W lambda.
    """
    m = len(d0)
    lam = np.maximum(lam, 0.0)
    if m == 0:
        return lam, 0
    passive = lam > 0.0
    shift *= float(W.diagonal().max())
    steps, joined = 0, -1
    while steps < max_steps:
        P = np.flatnonzero(passive)
        s = np.zeros(m)
        if len(P):
            face = face_solve(W, d0, P, shift)
            steps += 1
            if face is None:
                return lam, steps
            s[P] = face
            low = P[face <= 0.0]
            if len(low):  # to the boundary: the first row of P to reach 0 leaves it
                gap = lam[low] - s[low]  # >= 0; 0 only for a row that just joined and stays at 0
                ratio = np.divide(lam[low], gap, out=np.zeros(len(low)), where=gap > 0.0)
                alpha = ratio.min()
                leave = low[ratio <= alpha]
                if alpha <= 0.0 and joined in leave:
                    return lam, steps
                lam = lam + alpha * (s - lam)
                lam[leave] = 0.0
                passive[leave] = False
                joined = -1
                continue
        lam = s
        w = -(W @ lam + d0)
        w[passive] = -np.inf
        j = int(np.argmax(w))
        if w[j] <= tolerance:
            return lam, steps
        passive[j] = True
        joined = j
    return lam, steps


class PGS:
    """The contact LCP's solver: projected Gauss-Seidel sweeps (:func:`pgs_kernel`) and, for a
    frictionless LCP (every contact one row), :func:`active_set` after ``first_sweeps`` of
    them.

    A frictionless solve sweeps until the tolerance or ``first_sweeps``; if not converged, the
    active-set method continues from the sweeps' lambda with the rest of ``max_iterations`` as
    its steps; if that does not finish within tolerance (see :func:`active_set`), the sweeps
    go on from the better of the two for what is left. A solve with friction rows sweeps up to
    ``max_iterations``. ``active_set=False``: sweeps only, always. The CPU buffers are kept
    between solves: they grow to the largest problem seen and are filled in place, and the
    kernel's launch is recorded once per set of buffers, so that a sweep phase allocates no
    Warp array and makes one launch.
    """

    def __init__(self, active_set: bool = True, first_sweeps: int = FIRST_SWEEPS):
        self.active_set = bool(active_set)
        self.first_sweeps = int(first_sweeps)
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

    def _sweeps(self, lam: np.ndarray, m: int, nc: int, max_iterations: int, tolerance: float,
                pyramid: bool) -> tuple[np.ndarray, int, float]:
        """Up to ``max_iterations`` sweeps from ``lam`` on the problem in the buffers."""
        a = self._np
        a["lam"][:m] = lam
        cmd = self._cmd
        for index, value in ((5, m), (6, nc), (7, int(max_iterations)), (8, float(tolerance)), (9, int(pyramid))):
            cmd.set_param_at_index(index, value)
        cmd.launch()
        its, res = a["info"]
        return a["lam"][:m].copy(), int(its), float(res)

    def solve(self, W: np.ndarray, d0: np.ndarray, row_start: np.ndarray, rows: np.ndarray, mu: np.ndarray,
              max_iterations: int, tolerance: float, pyramid: bool,
              lam0: np.ndarray) -> tuple[np.ndarray, int, float]:
        """Solve the LCP from the warm start ``lam0``: (lambda, sweeps, residual [m]). sweeps:
        the Gauss-Seidel sweeps plus the active-set method's steps (face solves), at most
        ``max_iterations``. The contacts' rows (``rows[c]`` from ``row_start[c]``) partition the
        m rows, as :class:`~soft_tissue_sim.contact.solver.ContactSolver` lays them out."""
        m, nc = len(d0), len(row_start)
        self._reserve(m, nc)
        a = self._np
        a["W"][:m, :m] = W
        a["d0"][:m] = d0
        a["row_start"][:nc] = row_start
        a["n_rows"][:nc] = rows
        a["mu"][:nc] = mu
        finish = self.active_set and nc == m  # the contacts' rows partition the m rows: no friction rows
        first = min(self.first_sweeps, max_iterations) if finish else max_iterations
        lam, its, res = self._sweeps(lam0, m, nc, first, tolerance, pyramid)
        if res <= tolerance or not finish or its >= max_iterations:
            return lam, its, res
        la, steps = active_set(W, d0, lam, tolerance, max_iterations - its)  # every row a contact's normal
        its += steps
        ra = frictionless_residual(W, d0, la)
        if ra < res:
            lam, res = la, ra
        if res <= tolerance or its >= max_iterations:
            return lam, its, res
        lam, more, res = self._sweeps(lam, m, nc, max_iterations - its, tolerance, pyramid)
        return lam, its + more, res
