"""The contact LCP of eq. (3) solved where the factor is, inside the correction's launches.

For a contact set of at most ``contact.device_lcp_rows`` constraint rows and a factor that
gathers the Delassus operator on the device (the dense inverse), the response of eq. (4) is
a chain of launches with no read in between, which the integrator captures with the
correction, the penetration detection and the guard (one graph a step):

1. the rows (H in node form), delta^0, the warm start and the contacts' friction go up in one
   page-locked buffer (one copy);
2. W = dt^2 H P^-1 H^T is gathered into a matrix of the buffers' capacity, the row count read
   on the device (:func:`~soft_tissue_sim.dense_inverse.delassus_matrix_kernel`), so that one
   captured graph serves every contact count;
3. :func:`device_pgs_kernel` (up to :data:`SMALL` rows, a block of :data:`LANES` lanes) and,
   in buffers of more rows, :func:`device_pgs_wide_kernel` (:data:`SMALL` + 1 to :data:`BIG`
   rows, :data:`WIDE_LANES` lanes) are launched together, each returning at once on the
   other's sets (the set's size is read on the device); the kernel checks W as
   :func:`.compliance.positive_definite` does (a Cholesky factorization of W + 1e-10 max(diag
   W) I, a column at a time, the lanes sharing each column's rows; for a frictionless set of
   more than :data:`.pgs.LARGE_SET_ROWS` rows the diagonal only: see below) and runs the projected
   Gauss-Seidel sweeps of :mod:`.pgs` from the warm start: every lane makes each contact's
   update (the same values from the same reads) and the lanes move delta = W lambda + d0,
   held in the block's shared memory, by the changed rows' columns of W together, each lane
   its own elements (:func:`block_pgs_sweeps`); a frictionless set (as many contacts as rows)
   is finished, as the host does, by the active-set method where the sweeps stall
   (:func:`device_active_set`: the host's :func:`.pgs.active_set`, its faces' inverses
   and products shared by the lanes, its scalar steps on lane 0), and a set with
   friction, where ``contact.friction_active_set`` asks, by the host's friction finish on lane
   0 (:func:`friction_finish`). The sweeps make the same operations in the same order as the
   host's kernel, so the same lambda to the bit where no multiply-add is fused differently;
   the finishes are the host's to rounding (the face solves by an updated inverse, the friction
   finish's sums in loop order, the host's by BLAS and LAPACK);
4. dx = dt^2 P^-1 H^T lambda (eq. 2), zeroed on the fixed nodes, from the columns of the rows'
   nodes only (:func:`~soft_tissue_sim.dense_inverse.rows_apply`, in double precision as
   W is gathered).

lambda, the sweeps, the residual and the check's verdict are read with the guard after the
correction. Where W is not positive definite the device solve makes lambda = 0 (no
correction) and says so: the caller restores the free motion and solves the step's contacts
on the host, with the block diagonal of A (as :meth:`.solver.ContactSolver._respond` does).
A frictionless set of more than :data:`.pgs.LARGE_SET_ROWS` rows (the cut faces' self
contacts: a hundred rows and more) is not factorized whole first (O(m^3 / lanes), longer than
its solve): its verdict is its solve's, usable where the sweeps and the active-set finish
(which inverts the faces it visits, and stops where one is not positive definite) end
within the tolerance; otherwise lambda = 0 and the host solves the step's contacts (with its
check). Such a set starts the finish after :data:`.pgs.LARGE_FIRST_SWEEPS` sweeps, as on the
host.
Sweeps with friction that end above the tolerance stand, as they do on the host. The friction
finish is one lane's work (its normal equations O(k^3) for k unknowns), for the sets
:func:`.pgs.finishes_friction` names, as on the host. A sweep
costs O(m) a lane for the rows it changes, the check O(m^3 / lanes); sets beyond the row
limit (at most :data:`BIG`) are solved on the host.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from ..buffers import GrowArray, PackedArrays, typed_view
from .geometry import F64
from .options import friction_finish_on
from .pgs import (_FBEST, _FCOUNT, _FOUT, FIRST_SWEEPS, FIWORK_ROWS, FRICTION_FINISHES, FRICTION_STEPS, FRICTION_SWEEPS,
                  FWORK_ROWS, LARGE_SET_ROWS, contact_update, finishes_friction, first_sweeps_of,
                  friction_finish, jacobi_change, row_delta)

LANES = 32  # the block of device_pgs_kernel
WIDE_LANES = 128  # the block of device_pgs_wide_kernel (W's check and the active set's products shared wider)
SMALL = 32  # the rows of the narrower kernel (the default limit of contact.device_lcp_rows)
BIG = 256  # the most rows of a device LCP (the limit of contact.device_lcp_rows)
# no gradients are taken here; the module is built once per block size launched (LANES, and
# WIDE_LANES where a larger row limit is asked for): its kernels are launched with those only
# (a plain launch, 256 threads on CUDA, would build the whole module once more)
wp.set_module_options({"enable_backward": False, "block_dim": LANES})


@wp.func
def barrier(gate: Any):
    """Every lane of the block waits here (``gate``: a shared tile of zeros, each lane adding 0
    to its own elements); what a lane wrote before it, shared or in the device's memory, the
    others see after it."""
    wp.tile_axpy(F64(0.0), gate, gate)


@wp.func
def cholesky_columns(W: wp.array2d(dtype=wp.float64), L: wp.array2d(dtype=wp.float64), p: int, shift: wp.float64,
                     lane: int, bd: int, gate: Any, col: Any, width: int):
    """The Cholesky factor of W's leading p x p block plus shift I into L's leading p x p block (lower triangle), by the block's lanes (``lane`` of ``bd``; one
    lane: 0 of 1): the rows' lower triangles copied in (each lane its own rows), then a column j
    at a time (right-looking) the column below the pivot sqrt(L_jj) scaled into the shared tile
    ``col`` (``width`` elements, every lane assigning in every round), and the entries right of
    j updated by it, the trailing block's entries dealt out to the lanes, the block waiting
    after each column. Every entry gets the same subtractions in the same order as a
    left-looking factorization (column k's products in order of k), whatever the lanes. 1, or 0
    where it is not positive definite (every lane reads the same pivot and returns alike).
    Every lane calls it."""
    for i in range(lane, p, bd):
        for k in range(i + 1):
            L[i, k] = W[i, k]
        L[i, i] = L[i, i] + shift
    barrier(gate)
    for j in range(p):
        s = L[j, j]
        if not (s > F64(0.0)) or not wp.isfinite(s):
            return 0
        ljj = wp.sqrt(s)
        for base in range(0, width, bd):  # the scaled column, shared (each assignment waits for the block)
            i = base + lane
            v = F64(0.0)
            if i > j and i < p:
                v = L[i, j] / ljj
            col[i] = v
        nn = p - j - 1
        for e in range(lane, nn * nn, bd):  # the trailing block's lower triangle, an entry a lane at a time
            i = j + 1 + e // nn
            k = j + 1 + e % nn
            if k <= i:
                L[i, k] = L[i, k] - col[i] * col[k]
        for i in range(lane, p, bd):
            if i > j:
                L[i, j] = col[i]
            elif i == j:
                L[j, j] = ljj
        barrier(gate)  # the block updated before the next pivot is read
    return 1


@wp.func
def border_inverse(W: wp.array2d(dtype=wp.float64), B: wp.array2d(dtype=wp.float64), P: wp.array(dtype=wp.int32),
                   q: int, shift: wp.float64, y: wp.array(dtype=wp.float64), lane: int, bd: int, gate: Any):
    """B = (W_PP + shift I)^-1 grown by the row P[q] (B symmetric, in its leading q x q block):
    u = B w (w: W's entries of P[q] in the rows P[0..q)), each lane its rows, into ``y``; the
    Schur complement d = W_qq + shift - w . u (every lane alike); then B + u u^T / d, -u / d and
    1 / d, each lane its columns. Two barriers. 1, or 0 where d is not positive and finite
    (every lane reads the same). Every lane calls it."""
    rq = P[q]
    for i in range(lane, q, bd):
        t = F64(0.0)
        for k in range(q):
            t += B[k, i] * W[P[k], rq]
        y[i] = t
    barrier(gate)
    d = W[rq, rq] + shift
    for k in range(q):
        d -= W[P[k], rq] * y[k]
    if not (d > F64(0.0)) or not wp.isfinite(d):
        return 0
    for k in range(lane, q, bd):
        uk = y[k] / d
        for i in range(q):
            B[i, k] = B[i, k] + y[i] * uk
        B[q, k] = -uk
        B[k, q] = -uk
    if lane == 0:
        B[q, q] = F64(1.0) / d
    barrier(gate)
    return 1


@wp.func
def drop_inverse(B: wp.array2d(dtype=wp.float64), p: int, a: int, y: wp.array(dtype=wp.float64), lane: int, bd: int,
                 gate: Any):
    """B = A^-1 (p x p, symmetric) made the inverse of A without row and column a, in place (row
    and column a left as they are): B - B_a B_a^T / B_aa. Two barriers. Every lane calls it."""
    for i in range(lane, p, bd):
        y[i] = B[i, a]
    barrier(gate)
    baa = y[a]
    for k in range(lane, p, bd):
        if k != a:
            uk = y[k] / baa
            for i in range(p):
                if i != a:
                    B[i, k] = B[i, k] - y[i] * uk
    barrier(gate)


@wp.func
def apply_inverse(B: wp.array2d(dtype=wp.float64), b: wp.array(dtype=wp.float64), p: int,
                  x: wp.array(dtype=wp.float64), lane: int, bd: int, gate: Any):
    """x = B b (B symmetric, p x p), each lane its rows, the block waiting before (b written by
    the lanes) and after. Every lane calls it."""
    barrier(gate)
    for i in range(lane, p, bd):
        t = F64(0.0)
        for k in range(p):
            t += B[k, i] * b[k]
        x[i] = t
    barrier(gate)


@wp.func
def block_diagonal(W: wp.array2d(dtype=wp.float64), m: int, part: Any, lane: int, bd: int, gate: Any):
    """The largest diagonal entry of W's leading m x m block, or -1 where one is not positive
    and finite: each lane its own rows, their verdicts in the shared tile ``part`` (one element
    a lane), added up by every lane alike. Every lane calls it."""
    dmax = F64(0.0)
    for i in range(lane, m, bd):
        d = W[i, i]
        if not (d > F64(0.0)) or not wp.isfinite(d):
            dmax = F64(-1.0)
        elif dmax >= F64(0.0):
            dmax = wp.max(dmax, d)
    barrier(gate)  # an earlier call's reads of part are over
    part[lane] = dmax  # (an element's assignment makes the block wait)
    out = F64(0.0)
    for k in range(bd):
        v = part[k]
        if v < F64(0.0) or out < F64(0.0):
            out = F64(-1.0)
        else:
            out = wp.max(out, v)
    return out


@wp.func
def block_positive_definite(W: wp.array2d(dtype=wp.float64), L: wp.array2d(dtype=wp.float64), m: int,
                            factorize: int, dmax: wp.float64, lane: int, bd: int, gate: Any, col: Any, width: int):
    """1 if the leading m x m block of the symmetric W is usable by Gauss-Seidel (finite, positive
    diagonal: ``dmax``, :func:`block_diagonal`'s verdict, and, with ``factorize``, a Cholesky
    factorization of W + 1e-10 max(diag W) I into L that succeeds), else 0:
    :func:`..compliance.positive_definite` by the block (:func:`cholesky_columns`)."""
    if dmax < F64(0.0):
        return 0
    if factorize == 0:
        return 1
    return cholesky_columns(W, L, m, F64(1e-10) * dmax, lane, bd, gate, col, width)


# rows of the active-set method's work arrays (DeviceLCP.work: float64, DeviceLCP.iwork: int32)
# (and _DSW: delta of the frictionless sweeps)
_LAM, _S, _B, _X, _X2, _Y, _R, _RAT, _DELTA, _SCALARS, _DSW = 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10
_PASSIVE, _P, _LOW, _FLAGS = 0, 1, 2, 3
WORK_ROWS, IWORK_ROWS = 11, 4


@wp.func
def block_rows_delta(W: wp.array2d(dtype=wp.float64), d0: wp.array(dtype=wp.float64),
                     lam: wp.array(dtype=wp.float64), m: int, out: wp.array(dtype=wp.float64), lane: int, bd: int,
                     gate: Any):
    """out = W lambda + d0 over the first m rows, summed afresh (:func:`.pgs.row_delta`), each
    lane its own rows; then the block waits (every lane calls it)."""
    for i in range(lane, m, bd):
        out[i] = row_delta(W, d0, lam, i, m)
    barrier(gate)


@wp.func
def face_ratio(m: int, p: int, joined: int, work: wp.array2d(dtype=wp.float64), iwork: wp.array2d(dtype=wp.int32)):
    """The scalar part of a face step of :func:`device_active_set` (one lane), after the face
    solve's x, its residual r and the refinement x2 (L L^T x2 = r; the lanes'): s = x + x2 on P,
    then the ratio test over the rows of P that s leaves <= 0 (marked in ``low``, which the
    lanes cleared), its step alpha into ``work[_SCALARS, 0]``. Returns 0: s is positive on P
    (lambda is to become s); 1: lambda is to move towards s by alpha, the rows reaching 0
    first leaving P (moved by the lanes, a row each); 2: the row that just joined leaves again
    without a step (stop)."""
    zero = F64(0.0)
    lam = work[_LAM]
    s = work[_S]
    x = work[_X]
    x2 = work[_X2]
    rat = work[_RAT]
    P = iwork[_P]
    low = iwork[_LOW]
    for a in range(p):
        s[P[a]] = x[a] + x2[a]
    nlow = int(0)
    alpha = zero
    for a in range(p):
        i = P[a]
        if s[i] <= zero:
            rat[i] = zero
            gap = lam[i] - s[i]
            if gap > zero:
                rat[i] = lam[i] / gap
            if nlow == 0 or rat[i] < alpha:
                alpha = rat[i]
            low[i] = 1
            nlow += 1
    work[_SCALARS, 0] = alpha
    if nlow == 0:
        return 0
    if alpha <= zero and joined >= 0:
        if low[joined] != 0 and rat[joined] <= alpha:
            return 2
    return 1


@wp.func
def device_active_set(W: wp.array2d(dtype=wp.float64), d0: wp.array(dtype=wp.float64),
                      L: wp.array2d(dtype=wp.float64), lam0: wp.array(dtype=wp.float64), m: int,
                      dmax: wp.float64, tolerance: wp.float64, max_steps: int, work: wp.array2d(dtype=wp.float64),
                      iwork: wp.array2d(dtype=wp.int32), lane: int, bd: int, gate: Any, col: Any, part: Any,
                      T: wp.array2d(dtype=wp.float64)):
    """:func:`.pgs.active_set` by the block (Lawson and Hanson's method from ``lam0``, the face
    problems solved with W_PP + 1e-12 max(diag W) I and one step of refinement against W_PP;
    ``dmax`` the largest diagonal entry of W): the same steps in the same order, the face
    solves to their rounding. The face's inverse B = (W_PP + shift I)^-1 is kept in ``L``, so
    that a face solve is one product a barrier (:func:`apply_inverse`) where triangular
    substitutions wait a column at a time: grown a row at a time by the rows of P it does not
    hold (all of them at the start, then each joining row: :func:`border_inverse`), and rid of
    the rows that leave (:func:`drop_inverse`), its kept rows and columns then closed up
    through ``T`` (the friction finish's work matrix, unused by a frictionless set). P keeps its rows in the
    order they joined (``iwork[_P]``, its size in ``iwork[_FLAGS, 0]``), as the host's does.
    B's updates, the products with it, W lambda, the faces' residuals, the moves of lambda,
    the passive list and the search for the row to join are shared by the lanes (a row or a
    column each; ``col`` and ``part`` shared tiles of the lanes' count at least); the ratio
    test and the join's choice among the lanes' candidates are lane 0's (:func:`face_ratio`),
    whose verdicts the others read from ``iwork[_FLAGS]`` after the block's barrier. Every lane
    calls it and gets the face solves made; lambda goes to ``work[_LAM]``."""
    zero = F64(0.0)
    lam = work[_LAM]
    s = work[_S]
    dv = work[_DELTA]
    passive = iwork[_PASSIVE]
    P = iwork[_P]
    flags = iwork[_FLAGS]
    shift = F64(1e-12) * dmax
    for i in range(lane, m, bd):
        lam[i] = wp.max(lam0[i], zero)
        passive[i] = 0
        if lam[i] > zero:
            passive[i] = 1
    steps = int(0)
    joined = int(-1)
    b = work[_B]
    x = work[_X]
    r = work[_R]
    rat = work[_RAT]
    low = iwork[_LOW]
    barrier(gate)  # lambda and the passive set written
    for i in range(lane, m, bd):  # each passive row's place in P: the passive rows before it
        if passive[i] != 0:
            c = int(0)
            for k in range(i):
                c += passive[k]
            P[c] = i
    if lane == 0:
        p0 = int(0)
        for i in range(m):
            p0 += passive[i]
        flags[0] = p0
    held = int(0)  # the rows of P that B holds, P[0..held): those before the rows that joined since
    while steps < max_steps:
        barrier(gate)  # lambda, the passive set and P written
        for i in range(lane, m, bd):
            s[i] = zero
            low[i] = 0
        p = flags[0]
        barrier(gate)
        if p > 0:
            steps += 1
            for q in range(held, p):  # B grown by P's rows it does not hold yet
                if border_inverse(W, L, P, q, shift, work[_Y], lane, bd, gate) == 0:
                    return steps
            held = p
            # the face solve, its residual against W_PP and the refinement (the lanes, a row
            # each), the ratio test (lane 0), the move of lambda (the lanes, a row each)
            for a in range(lane, p, bd):
                b[a] = -d0[P[a]]
            apply_inverse(L, b, p, x, lane, bd, gate)
            for a in range(lane, p, bd):
                t = b[a]
                for c in range(p):
                    t -= W[P[a], P[c]] * x[c]
                r[a] = t
            apply_inverse(L, r, p, work[_X2], lane, bd, gate)
            if lane == 0:
                flags[1] = face_ratio(m, p, joined, work, iwork)
            barrier(gate)
            verdict = flags[1]
            if verdict == 2:
                return steps
            if verdict == 1:
                alpha = work[_SCALARS, 0]
                for i in range(lane, m, bd):
                    lam[i] = lam[i] + alpha * (s[i] - lam[i])
                    if low[i] != 0 and rat[i] <= alpha:
                        lam[i] = zero
                        passive[i] = 0
                barrier(gate)  # every row moved
                # the rows that left, out of B (in place), then B's kept rows and columns
                # closed up (through T) in P's new order
                for a in range(p):
                    if passive[P[a]] == 0:
                        drop_inverse(L, p, a, work[_Y], lane, bd, gate)
                for a in range(lane, p, bd):
                    c = int(-1)
                    if passive[P[a]] != 0:
                        c = int(0)
                        for k in range(a):
                            c += passive[P[k]]
                    low[a] = c  # (low is not read again before the next face clears it)
                barrier(gate)
                for k in range(lane, p, bd):
                    ck = low[k]
                    if ck >= 0:
                        for i in range(p):
                            ci = low[i]
                            if ci >= 0:
                                T[ci, ck] = L[i, k]
                barrier(gate)
                if lane == 0:  # the rows left P: the others keep their order
                    q = int(0)
                    for a in range(p):
                        if passive[P[a]] != 0:
                            P[q] = P[a]
                            q += 1
                    flags[0] = q
                barrier(gate)
                held = flags[0]
                for k in range(lane, held, bd):
                    for i in range(held):
                        L[i, k] = T[i, k]
                joined = -1
                continue
        # lambda = s, and delta = W lambda + d0 from P's columns (s is 0 elsewhere; W symmetric,
        # so that the lanes read rows), each lane its rows
        p = flags[0]
        for i in range(lane, m, bd):
            lam[i] = s[i]
            d = d0[i]
            for a in range(p):
                c = P[a]
                d += W[c, i] * s[c]
            dv[i] = d
        barrier(gate)
        # the row to join: the most negative delta outside P (the first such row), each lane's
        # among its rows, then the lanes' (the largest; of equal ones the first row)
        j = int(-1)
        best = F64(0.0)
        for i in range(lane, m, bd):
            if passive[i] == 0:
                w = -dv[i]
                if j < 0 or w > best:
                    j = i
                    best = w
        part[lane] = best  # (each assignment waits for the block)
        col[lane] = F64(float(j))
        if lane == 0:
            for k in range(bd):
                jk = int(col[k])
                if jk >= 0:
                    wk = part[k]
                    if j < 0 or wk > best or (wk == best and jk < j):
                        j = jk
                        best = wk
            if j >= 0 and best > tolerance:
                passive[j] = 1
                P[flags[0]] = j  # joins P last
                flags[0] = flags[0] + 1
            else:
                j = -1
            flags[2] = j
        barrier(gate)
        j = flags[2]
        if j < 0:
            return steps
        joined = j
    return steps


def _block_solver(width: int) -> wp.Kernel:
    """:func:`device_pgs` for sets of up to ``width`` rows: delta in a shared tile of that many
    elements, and a changed row's column of W read as many (one kernel per width, so that the
    small sets of most steps move no more than their own rows)."""

    @wp.func
    def block_delta(W: wp.array2d(dtype=wp.float64), d0: wp.array(dtype=wp.float64), lam: wp.array(dtype=wp.float64),
                    m: int, lane: int, bd: int, dv: Any, gate: Any):
        """delta = W lambda + d0 over the first m rows into the shared tile ``dv`` (0 beyond), each
        lane its own rows (i = lane + k block_dim, as the tile's operations divide it; each
        :func:`.pgs.row_delta`). Every lane assigns in every round: an element's assignment
        waits at the block's barrier (as the lanes wait before the first)."""
        barrier(gate)
        for base in range(0, width, bd):
            i = base + lane
            d = F64(0.0)
            if i < m:
                d = row_delta(W, d0, lam, i, m)
            dv[i] = d

    @wp.func
    def block_frictionless_change(dv: Any, lam: wp.array(dtype=wp.float64), diag: Any, m: int, part: Any, lane: int,
                                  bd: int, gate: Any):
        """:func:`.pgs.jacobi_change` of a frictionless set (a row a contact) by the block: each
        lane its own rows (``diag``: W's diagonal, a shared tile), the lanes' largest in ``part``,
        taken by every lane alike (a largest is the same in any order)."""
        res = F64(0.0)
        for i in range(lane, m, bd):
            li = lam[i]
            ln = wp.max(F64(0.0), li - dv[i] / diag[i])
            res = wp.max(res, diag[i] * wp.abs(ln - li))
        barrier(gate)  # an earlier use of part is over
        part[lane] = res  # (an element's assignment makes the block wait)
        out = F64(0.0)
        for k in range(bd):
            out = wp.max(out, part[k])
        return out

    @wp.func
    def block_frictionless_sweeps(W: wp.array2d(dtype=wp.float64), d0: wp.array(dtype=wp.float64),
                                  lam: wp.array(dtype=wp.float64), m: int, max_iterations: int,
                                  tolerance: wp.float64, lane: int, bd: int, dv: Any, dg: wp.array(dtype=wp.float64),
                                  diag: Any, part: Any, gate: Any):
        """:func:`block_pgs_sweeps` for a frictionless set (row i the contact i): the same updates
        in the same order, delta in the device array ``dg`` (each lane its own elements, i = lane
        + k bd, written without the block's barrier a shared tile's element costs), W's diagonal
        read from the shared tile ``diag``, and each row of W that moves delta read by the lanes
        into registers (their elements lane and lane + bd) while the row before it is made, so
        that no row waits for the device's memory; a row that does not change costs no barrier;
        the residual by the lanes (:func:`block_frictionless_change`). delta ends in ``dv`` too."""
        zero = F64(0.0)
        barrier(gate)  # lambda written (each lane its own rows)
        block_rows_delta(W, d0, lam, m, dg, lane, bd, gate)
        it = int(0)
        res = F64(-1.0)
        i1 = lane + bd
        for sweep in range(max_iterations):
            change = zero
            nxt0 = zero
            nxt1 = zero
            if lane < m:
                nxt0 = W[0, lane]
            if i1 < m:
                nxt1 = W[0, i1]
            for r in range(m):
                w0 = nxt0
                w1 = nxt1
                if r + 1 < m:  # the next row's elements, in flight while this one is made
                    if lane < m:
                        nxt0 = W[r + 1, lane]
                    if i1 < m:
                        nxt1 = W[r + 1, i1]
                lr = lam[r]
                wr = diag[r]
                ln = wp.max(zero, lr - dg[r] / wr)
                change = wp.max(change, wr * wp.abs(ln - lr))
                d = ln - lr
                if d != zero:  # (the same d in every lane: the block waits, or none does)
                    barrier(gate)  # every lane has read delta and lambda before any writes them
                    if lane < m:
                        dg[lane] = dg[lane] + d * w0
                    if i1 < m:
                        dg[i1] = dg[i1] + d * w1
                    for i in range(lane + 2 * bd, m, bd):
                        dg[i] = dg[i] + d * W[r, i]
                    lam[r] = ln
                    barrier(gate)  # delta moved before the next row reads it
            it = sweep + 1
            res = F64(-1.0)
            if change <= tolerance:  # converged if the residual (a sweep not applied) agrees
                barrier(gate)  # every lane's last reads (rows without a change wait for none) are over
                block_rows_delta(W, d0, lam, m, dg, lane, bd, gate)
                res = block_frictionless_change(dg, lam, diag, m, part, lane, bd, gate)
                if res <= tolerance:
                    break
        if res < zero:  # the sweeps ran out: the residual of where they stopped
            barrier(gate)
            block_rows_delta(W, d0, lam, m, dg, lane, bd, gate)
            res = block_frictionless_change(dg, lam, diag, m, part, lane, bd, gate)
        for base in range(0, width, bd):  # every lane assigns in every round (see block_delta)
            i = base + lane
            v = F64(0.0)
            if i < m:
                v = dg[i]
            dv[i] = v
        return it, res

    @wp.func
    def block_pgs_sweeps(W: wp.array2d(dtype=wp.float64), d0: wp.array(dtype=wp.float64),
                         row_start: wp.array(dtype=wp.int32), n_rows: wp.array(dtype=wp.int32),
                         mu: wp.array(dtype=wp.float64), lam: wp.array(dtype=wp.float64), m: int, nc: int,
                         max_iterations: int, tolerance: wp.float64, pyramid: int, lane: int, bd: int, dv: Any,
                         dg: wp.array(dtype=wp.float64), diag: Any, part: Any, gate: Any):
        """:func:`.pgs.pgs_sweeps` (contacts of one or three rows) by a block, from lambda in ``lam``
        (updated in place): every lane makes each contact's update (the same values from the same
        reads, written alike), and a changed row's column of W goes into delta (the shared tile
        ``dv``) by all of them, each lane its own elements; the same operations in the same order.
        Returns (sweeps, residual); delta stays in ``dv``. A frictionless set (nc == m): by
        :func:`block_frictionless_sweeps`."""
        if nc == m:
            return block_frictionless_sweeps(W, d0, lam, m, max_iterations, tolerance, lane, bd, dv, dg, diag, part,
                                             gate)
        zero = F64(0.0)
        block_delta(W, d0, lam, m, lane, bd, dv, gate)
        it = int(0)
        res = F64(-1.0)
        for sweep in range(max_iterations):
            change = zero
            for c in range(nc):
                r = row_start[c]
                k = n_rows[c]
                ln, l1, l2, ch = contact_update(W, dv, lam, r, k, mu[c], pyramid)
                barrier(gate)  # every lane has read delta and lambda before any writes them
                for q in range(k):
                    j = r + q
                    value = ln
                    if q == 1:
                        value = l1
                    elif q == 2:
                        value = l2
                    d = value - lam[j]
                    if d != zero:
                        wp.tile_axpy(d, wp.tile_load(W[j], shape=width), dv)
                        lam[j] = value
                change = wp.max(change, ch)
            it = sweep + 1
            res = F64(-1.0)
            if change <= tolerance:  # converged if the residual (a sweep not applied) agrees
                block_delta(W, d0, lam, m, lane, bd, dv, gate)
                res = jacobi_change(W, dv, lam, row_start, n_rows, mu, pyramid, nc)
                if res <= tolerance:
                    break
        if res < zero:  # the sweeps ran out: the residual of where they stopped
            block_delta(W, d0, lam, m, lane, bd, dv, gate)
            res = jacobi_change(W, dv, lam, row_start, n_rows, mu, pyramid, nc)
        return it, res

    def device_pgs(
        W: wp.array2d(dtype=wp.float64),
        d0: wp.array(dtype=wp.float64),
        lam0: wp.array(dtype=wp.float64),
        row_start: wp.array(dtype=wp.int32),
        n_rows: wp.array(dtype=wp.int32),
        mu: wp.array(dtype=wp.float64),
        sizes: wp.array(dtype=wp.int32),
        min_rows: int,
        max_iterations: int,
        tolerance: wp.float64,
        pyramid: int,
        first_sweeps: int,
        finish_friction: int,
        L: wp.array2d(dtype=wp.float64),
        work: wp.array2d(dtype=wp.float64),
        iwork: wp.array2d(dtype=wp.int32),
        fwork: wp.array2d(dtype=wp.float64),
        fiwork: wp.array2d(dtype=wp.int32),
        fA: wp.array2d(dtype=wp.float64),
        fN: wp.array2d(dtype=wp.float64),
        lam: wp.array(dtype=wp.float64),
        delta: wp.array(dtype=wp.float64),
        info: wp.array(dtype=wp.float64),
    ):
        """The LCP of :func:`.pgs.pgs_kernel` with m = sizes[0] <= ``width`` rows and nc = sizes[1]
        contacts read on the device, by one block (``wp.launch_tiled`` with :func:`pgs_kernel`'s
        lanes), W checked first (:func:`block_positive_definite`). info = [sweeps, residual, 1 if
        W was usable else 0]; an unusable W leaves lambda = 0. :func:`block_pgs_sweeps`, and a
        frictionless set (nc == m) as the host's :meth:`.pgs.PGS.solve` makes it: up to
        ``first_sweeps`` sweeps, then (not converged) the active-set method
        (:func:`device_active_set`) with what is left of ``max_iterations`` as its steps, the
        better of the two kept, then sweeps for the rest (``first_sweeps`` >= ``max_iterations``:
        sweeps only). A set with friction and ``finish_friction`` as the host's with
        ``friction_active_set`` (where :func:`.pgs.finishes_friction`): ``first_sweeps`` sweeps,
        then up to :data:`.pgs.FRICTION_FINISHES` of :func:`.pgs.friction_finish` (on lane 0,
        the others waiting), each followed by sweeps from the better lambda. Every lane runs the
        scalar work alike (their writes to the device's memory are the same values)."""
        _b, lane = wp.tid()
        bd = wp.block_dim()
        m = sizes[0]
        nc = sizes[1]
        if m < min_rows or m > width:  # the set of the other kernel launched with this one
            return
        dv = wp.tile_zeros(shape=width, dtype=wp.float64, storage="shared")
        gate = wp.tile_zeros(shape=LANES, dtype=wp.float64, storage="shared")
        part = wp.tile_zeros(shape=WIDE_LANES, dtype=wp.float64, storage="shared")
        col = wp.tile_zeros(shape=width, dtype=wp.float64, storage="shared")  # a factorization's column
        info[0] = F64(0.0)
        info[1] = F64(0.0)
        info[2] = F64(0.0)
        frictionless = int(nc == m)
        # a large frictionless set: no factorization of the whole W first; the verdict is the
        # solve's (within the tolerance or not), the active-set finish factorizing its faces
        factorize = int(frictionless == 0 or m <= LARGE_SET_ROWS)
        dmax = block_diagonal(W, m, part, lane, bd, gate)
        diag = wp.tile_zeros(shape=width, dtype=wp.float64, storage="shared")
        if frictionless != 0 and dmax > F64(0.0):  # W's diagonal at hand for the frictionless sweeps
            for base in range(0, width, bd):  # every lane assigns in every round (see block_delta)
                i = base + lane
                v = F64(1.0)
                if i < m:
                    v = W[i, i]
                diag[i] = v
        if block_positive_definite(W, L, m, factorize, dmax, lane, bd, gate, col, width) == 0:
            for i in range(m):
                lam[i] = F64(0.0)
            return
        for i in range(lane, m, bd):  # (read after the barrier that starts the sweeps)
            lam[i] = lam0[i]
        finish = finishes_friction(m, nc, finish_friction)
        first = max_iterations
        if frictionless != 0:
            first = first_sweeps_of(m, first_sweeps, max_iterations)
        elif finish != 0:
            first = wp.min(first_sweeps, max_iterations)
        it, res = block_pgs_sweeps(W, d0, row_start, n_rows, mu, lam, m, nc, first, tolerance, pyramid, lane, bd, dv,
                                   work[_DSW], diag, part, gate)
        if frictionless != 0 and res > tolerance and first < max_iterations and it < max_iterations:
            it += device_active_set(W, d0, L, lam, m, dmax, tolerance, max_iterations - it, work, iwork, lane, bd,
                                    gate, col, part, fA)
            la = work[_LAM]  # (lane 0's last writes precede a barrier)
            block_rows_delta(W, d0, la, m, work[_DELTA], lane, bd, gate)
            ra = block_frictionless_change(work[_DELTA], la, diag, m, part, lane, bd, gate)
            if ra < res:
                res = ra
                for i in range(lane, m, bd):
                    lam[i] = la[i]
                block_delta(W, d0, lam, m, lane, bd, dv, gate)  # (its barrier: lambda written)
            if res > tolerance and it < max_iterations:
                more, res = block_pgs_sweeps(W, d0, row_start, n_rows, mu, lam, m, nc, max_iterations - it, tolerance, 0,
                                             lane, bd, dv, work[_DSW], diag, part, gate)
                it += more
        if finish != 0:
            for k in range(FRICTION_FINISHES):
                if res <= tolerance or it >= max_iterations:
                    break
                barrier(gate)  # every lane's lambda written
                if lane == 0:
                    steps, rf = friction_finish(W, d0, row_start, n_rows, mu, lam, m, nc, pyramid, tolerance,
                                                wp.min(FRICTION_STEPS, max_iterations - it), fwork, fiwork, fA, fN)
                    fiwork[_FCOUNT, 0] = steps
                    fwork[_FOUT, 0] = rf
                barrier(gate)
                it += fiwork[_FCOUNT, 0]
                rf = fwork[_FOUT, 0]
                if rf < res:
                    res = rf
                    for i in range(m):
                        lam[i] = fwork[_FBEST, i]
                    block_delta(W, d0, lam, m, lane, bd, dv, gate)
                if res > tolerance and it < max_iterations:
                    more_sweeps = max_iterations - it
                    if k + 1 < FRICTION_FINISHES:
                        more_sweeps = wp.min(FRICTION_SWEEPS, more_sweeps)
                    more, res = block_pgs_sweeps(W, d0, row_start, n_rows, mu, lam, m, nc, more_sweeps, tolerance,
                                                 pyramid, lane, bd, dv, work[_DSW], diag, part, gate)
                    it += more
        usable = int(factorize != 0 or res <= tolerance)
        barrier(gate)
        for i in range(lane, m, bd):
            delta[i] = dv[i]
            if usable == 0:  # unchecked and not solved within the tolerance: no correction
                lam[i] = F64(0.0)
        if lane == 0:
            info[0] = F64(it)
            info[1] = res
            info[2] = F64(usable)

    return wp.Kernel(device_pgs, key=f"device_pgs_{width}")


device_pgs_kernel = _block_solver(SMALL)  # up to SMALL rows
device_pgs_wide_kernel = _block_solver(BIG)  # up to BIG rows


def pgs_kernels(rows: int) -> list[tuple[wp.Kernel, int, int]]:
    """The kernels of :func:`_block_solver` launched for buffers of ``rows`` rows, each with its
    block's lanes and the fewest rows it solves: the narrow one, and beyond :data:`SMALL` rows
    the wide one for the sets it does not take (each returns at once on the other's sets), so
    that a set is solved by the kernel of its own size in one captured graph."""
    if rows <= SMALL:
        return [(device_pgs_kernel, LANES, 0)]
    return [(device_pgs_kernel, LANES, 0), (device_pgs_wide_kernel, WIDE_LANES, SMALL + 1)]


class DeviceLCP:
    """The buffers of the device solve for up to ``rows`` constraint rows (as many contacts),
    kept between steps at fixed addresses (captured graphs stay valid), and the launches.

    Inputs (:meth:`stage`): one :class:`~soft_tissue_sim.buffers.PackedArrays` of [m, nc],
    row_start, n_rows, the rows' nodes (rows, 4), delta^0, the warm start, mu and the rows'
    coefficients (rows, 4, 3), sent in one copy. Output (:attr:`out`): [sweeps, residual, W
    usable | lambda (rows)]. dx is a :class:`~soft_tissue_sim.buffers.GrowArray` view of the
    body's node count.
    """

    FIELDS = {"sizes": wp.int32, "row_start": wp.int32, "n_rows": wp.int32, "nodes": wp.vec4i,
              "d0": wp.float64, "lam0": wp.float64, "mu": wp.float64, "coef": wp.types.matrix((4, 3), wp.float64)}

    def __init__(self, rows: int, device):
        self.rows = cap = int(rows)
        self.device = wp.get_device(device)
        self._in = PackedArrays(self.FIELDS, self.device)
        self._in.reserve({k: 2 if k == "sizes" else cap for k in self.FIELDS})
        self._host = {k: self._in.host(k) for k in self.FIELDS}  # the host views, fixed with the capacity
        a = self._in.array
        self.sizes, self.row_start, self.n_rows = a("sizes"), a("row_start"), a("n_rows")
        self.d0, self.lam0, self.mu = a("d0"), a("lam0"), a("mu")
        self.nodes = self._in.alias("nodes", wp.int32, (cap, 4))
        self.coef = self._in.alias("coef", wp.vec3d, (cap, 4))
        self.W = wp.zeros((cap, cap), dtype=wp.float64, device=self.device)
        self.L = wp.zeros((cap, cap), dtype=wp.float64, device=self.device)
        cols = max(cap, 3)  # the active-set finish's work arrays (iwork[_FLAGS] holds three verdicts)
        self.work = wp.zeros((WORK_ROWS, cols), dtype=wp.float64, device=self.device)
        self.iwork = wp.zeros((IWORK_ROWS, cols), dtype=wp.int32, device=self.device)
        # the friction finish's (friction_finish)
        self.fwork = wp.zeros((FWORK_ROWS, cols), dtype=wp.float64, device=self.device)
        self.fiwork = wp.zeros((FIWORK_ROWS, cols), dtype=wp.int32, device=self.device)
        self.fA = wp.zeros((cap, cap), dtype=wp.float64, device=self.device)
        self.fN = wp.zeros((cap, cap), dtype=wp.float64, device=self.device)
        self.delta = wp.zeros(cap, dtype=wp.float64, device=self.device)
        self.out = wp.zeros(3 + cap, dtype=wp.float64, device=self.device)
        self.info = typed_view(self.out, 0, wp.float64, 3)
        self.lam = typed_view(self.out, 3 * 8, wp.float64, cap)
        self._dx = GrowArray(wp.vec3d, self.device)

    def stage(self, nodes: np.ndarray, coef: np.ndarray, d0: np.ndarray, lam0: np.ndarray,
              row_start: np.ndarray, n_rows: np.ndarray, mu: np.ndarray) -> None:
        """The problem's m rows and nc contacts into the page-locked buffer, sent (no wait)."""
        m, nc = len(d0), len(row_start)
        self._in.writable()
        h = self._host
        sizes = h["sizes"]
        sizes[0], sizes[1] = m, nc
        h["row_start"][:nc] = row_start
        h["n_rows"][:nc] = n_rows
        h["nodes"][:m] = nodes
        h["d0"][:m] = d0
        h["lam0"][:m] = lam0
        h["mu"][:nc] = mu
        h["coef"][:m] = coef
        self._in.send(self.FIELDS)

    def stage_problem(self, W: np.ndarray, d0: np.ndarray, lam0: np.ndarray, row_start: np.ndarray,
                      n_rows: np.ndarray, mu: np.ndarray) -> None:
        """An LCP given with its W (a recorded one, a test's) into the buffers for :meth:`solve`:
        :meth:`stage` without rows (no dx is made from them), W written in its leading block."""
        m = len(d0)
        self.stage(np.zeros((m, 4), np.int32), np.zeros((m, 4, 3)), d0, lam0, row_start, n_rows, mu)
        padded = np.zeros((self.rows, self.rows))
        padded[:m, :m] = W
        self.W.assign(padded)

    def key(self, inner, free: wp.array, dt: float, options: tuple) -> tuple:
        """What :meth:`launch`'s launches depend on (the buffers are fixed while the node count
        holds; their views for this count are made here, so that the launches allocate
        nothing, even captured at a key's first use)."""
        dx = self._dx.view(free.shape[0])
        return (inner.graph_key(), inner.delassus_key(), free.ptr, dx.ptr, float(dt), *options)

    def launch(self, inner, free: wp.array, dt: float, max_iterations: int, tolerance: float,
               pyramid: bool, first_sweeps: int = FIRST_SWEEPS, friction_finish: bool = False) -> wp.array:
        """W, the LCP (:func:`device_pgs_kernel`: a frictionless set finished by the active-set
        method after ``first_sweeps``, one with friction by the friction finish where
        ``friction_finish``) and dx = dt^2 P^-1 H^T lambda (eq. 2) on the free nodes: launches
        only. Returns dx (a (n,) vec3d array kept between steps)."""
        dx = self._dx.view(free.shape[0])
        inner.delassus_matrix(self.nodes, self.coef, self.sizes, dt * dt, self.W)
        self.solve(max_iterations, tolerance, pyramid, first_sweeps, friction_finish)
        inner.apply_rows(self.nodes, self.coef, self.lam, self.sizes, dt * dt, free, dx)
        return dx

    def solve(self, max_iterations: int, tolerance: float, pyramid: bool, first_sweeps: int = FIRST_SWEEPS,
              friction_finish: bool = False) -> None:
        """The LCP staged (:meth:`stage`) with the W in :attr:`W` (:func:`device_pgs_kernel`):
        lambda, delta and [sweeps, residual, W usable] into :attr:`lam`, :attr:`delta` and
        :attr:`info`. A launch only."""
        for kernel, lanes, min_rows in pgs_kernels(self.rows):
            wp.launch_tiled(kernel, dim=[1],
                            inputs=[self.W, self.d0, self.lam0, self.row_start, self.n_rows, self.mu, self.sizes,
                                    int(min_rows), int(max_iterations), float(tolerance), int(bool(pyramid)),
                                    int(first_sweeps), int(bool(friction_finish)), self.L, self.work, self.iwork,
                                    self.fwork, self.fiwork, self.fA, self.fN, self.lam, self.delta, self.info],
                            block_dim=lanes, device=self.device)


def launch_args(options: dict, gpu: bool) -> tuple:
    """:meth:`DeviceLCP.launch`'s arguments after dt from the contact options (part of a graph's
    key): the frictionless LCP finished by the active-set method after the host's first sweeps
    (option ``active_set``), else sweeps only; one with friction finished as the host does where
    ``friction_active_set`` asks it of a simulation on a GPU (``gpu``) or on the CPU
    (:func:`.options.friction_finish_on`)."""
    o = options
    first = FIRST_SWEEPS if o["active_set"] else int(o["max_iterations"])
    return (int(o["max_iterations"]), float(o["tolerance"]), o["friction_cone"] == "pyramid", first,
            friction_finish_on(o, gpu))


class PendingLCP:
    """A contact step whose LCP is solved on the device: the caller launches it with the
    correction (:meth:`key`, :meth:`launch`, its output read with the guard) and hands the
    read output to :meth:`finish`."""

    def __init__(self, lcp: DeviceLCP, inner, free: wp.array, dt: float, options: dict, m: int, finish):
        self.lcp, self.inner, self.free, self.dt, self.m = lcp, inner, free, float(dt), int(m)
        self._args = launch_args(options, lcp.device.is_cuda)
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
