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
:func:`active_set`. With friction the Coulomb problem is not a quadratic program, and where
nearly repeated contacts share a force (an instrument's tip: the node it presses and the faces
around it) the sweeps converge slowly. :func:`friction_finish` (``contact.friction_active_set``:
by default the CPU's solves; the device's block has it too) finishes them: it solves the
linear system of the contacts' current states (off, sticking, sliding) and follows the states
the solution asks for, keeping the iterate of least residual, between rounds of sweeps.
"""

from __future__ import annotations

import sys
from typing import Any

import numpy as np
import warp as wp
from scipy.linalg.lapack import dpotrf, dpotrs

from .geometry import F64

wp.set_module_options({"enable_backward": False})  # no gradients are taken
WARP_CPU_ONLY = True  # this module's kernels: the host's solve (its functions are built into device_lcp's)

FIRST_SWEEPS = 10  # the sweeps before an active-set finish (PGS)
FRICTION_STEPS = 10  # with friction: the most steps of one active-set finish (PGS)
FRICTION_FINISHES = 2  # with friction: the most finishes a solve (PGS)
FRICTION_SWEEPS = 20  # with friction: the sweeps between two finishes (PGS)
FRICTION_FINISH_ROWS = 64  # with friction: the most rows finished (one thread's normal equations, O(rows^3))
LARGE_SET_ROWS = 32  # a frictionless set of more rows starts its active-set finish after fewer sweeps:
LARGE_FIRST_SWEEPS = 3  # a sweep costs a contact update per row, a face step from the warm start few


@wp.func
def first_sweeps_of(m: int, first_sweeps: int, max_iterations: int):
    """The sweeps before the active-set finish of a frictionless LCP of m rows (``first_sweeps``
    >= ``max_iterations``: sweeps only): ``first_sweeps``, at most :data:`LARGE_FIRST_SWEEPS`
    beyond :data:`LARGE_SET_ROWS` rows; never more than ``max_iterations``."""
    first = first_sweeps
    if m > LARGE_SET_ROWS and first_sweeps < max_iterations:
        first = wp.min(first_sweeps, LARGE_FIRST_SWEEPS)
    return wp.min(first, max_iterations)


@wp.func
def stick_point(W: wp.array2d(dtype=wp.float64), r: int, l1: wp.float64, l2: wp.float64, t1: wp.float64,
                t2: wp.float64):
    """The tangential forces of the contact whose normal row is r that would make its
    tangential gaps (t1, t2) zero (stick), from (l1, l2): a solve with its 2 x 2 block of W
    (unchanged where that block is singular)."""
    a11 = W[r + 1, r + 1]
    a22 = W[r + 2, r + 2]
    a12 = F64(0.5) * (W[r + 1, r + 2] + W[r + 2, r + 1])
    det = a11 * a22 - a12 * a12
    s1 = l1
    s2 = l2
    if det > F64(0.0):
        s1 = l1 - (a22 * t1 - a12 * t2) / det
        s2 = l2 - (a11 * t2 - a12 * t1) / det
    return s1, s2


@wp.func
def cone_project(l1: wp.float64, l2: wp.float64, lim: wp.float64, pyramid: int):
    """Tangential forces onto their cone of radius ``lim``: each clamped (pyramid), or onto the
    disk's rim where outside it (slide)."""
    out1 = l1
    out2 = l2
    if pyramid != 0:
        out1 = wp.clamp(l1, -lim, lim)
        out2 = wp.clamp(l2, -lim, lim)
    else:
        lt = wp.sqrt(l1 * l1 + l2 * l2)
        if lt > lim:
            s = F64(0.0)
            if lt > F64(0.0):
                s = lim / lt
            out1 = l1 * s
            out2 = l2 * s
    return out1, out2


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
        l1, l2 = stick_point(W, r, lam[r + 1], lam[r + 2], t1, t2)
        l1, l2 = cone_project(l1, l2, mu * ln, pyramid)
        change = wp.max(change, wp.max(W[r + 1, r + 1] * wp.abs(l1 - lam[r + 1]),
                                       W[r + 2, r + 2] * wp.abs(l2 - lam[r + 2])))
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


@wp.func
def face_substitute(L: wp.array2d(dtype=wp.float64), b: wp.array(dtype=wp.float64), p: int,
                    y: wp.array(dtype=wp.float64), x: wp.array(dtype=wp.float64)):
    """x with L L^T x = b (L's leading p x p block, lower; y: work)."""
    for i in range(p):
        t = b[i]
        for k in range(i):
            t -= L[i, k] * y[k]
        y[i] = t / L[i, i]
    for q in range(p):
        i = p - 1 - q
        t = y[i]
        for k in range(i + 1, p):
            t -= L[k, i] * x[k]
        x[i] = t / L[i, i]


# rows of the friction finish's work arrays (DeviceLCP.fwork: float64, DeviceLCP.fiwork: int32):
# lambda kept, the state's solution, it projected, delta, the solves' vectors, and per contact
# the held tangents (h1, h2) of the state, of the two before it and of the next
(_FBEST, _FNEW, _FSOL, _FDELTA, _FY, _FY2, _FRHS, _FRHS2, _FT,
 _FH1, _FH2, _FH1P, _FH2P, _FH1Q, _FH2Q, _FH1N, _FH2N, _FOUT) = range(18)
# per contact whether on (state, the two before, the next); per unknown its contact and part
# (0: the normal, 1 / 2: a tangent) and its equation's row; the device block's finish hands its
# steps to the other lanes in _FCOUNT (and its residual in fwork[_FOUT])
_FON, _FONP, _FONQ, _FONN, _FUNKC, _FUNKT, _FEQ, _FCOUNT = range(8)
FWORK_ROWS, FIWORK_ROWS = 18, 8


@wp.func
def finishes_friction(m: int, nc: int, asked: int):
    """1 where the friction finish is to run on an LCP of m rows and nc contacts: ``asked``
    (contact.friction_active_set), tangent rows, and at most :data:`FRICTION_FINISH_ROWS` rows
    (its normal equations are one thread's work, O(m^3))."""
    return int(asked != 0 and nc < m and m <= FRICTION_FINISH_ROWS)


@wp.func
def _sign(x: wp.float64):
    """-1, 0 or 1 (NumPy's sign)."""
    out = F64(0.0)
    if x > F64(0.0):
        out = F64(1.0)
    elif x < F64(0.0):
        out = F64(-1.0)
    return out


@wp.func
def _transpose_times(A: wp.array2d(dtype=wp.float64), v: wp.array(dtype=wp.float64), k: int,
                     out: wp.array(dtype=wp.float64)):
    """out = A^T v over A's leading k x k block."""
    for a in range(k):
        acc = F64(0.0)
        for q in range(k):
            acc += A[q, a] * v[q]
        out[a] = acc


@wp.func
def _held_component(h: wp.float64, lt: wp.float64, stick: wp.float64, limc: wp.float64):
    """The pyramid's next state of one tangent component: free (0) beyond the cone becomes held
    at the sign of its force; held becomes free where the Gauss-Seidel point ``stick`` is
    inside the cone, else held at its sign."""
    out = F64(0.0)
    if h == F64(0.0):
        if wp.abs(lt) > limc * (F64(1.0) + F64(1e-9)):
            out = _sign(lt)
    elif wp.abs(stick) > limc:
        out = _sign(stick)
    return out


@wp.func
def _friction_cone(lam: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64),
                   row_start: wp.array(dtype=wp.int32), n_rows: wp.array(dtype=wp.int32),
                   mu: wp.array(dtype=wp.float64), pyramid: int, m: int, nc: int):
    """out = lam projected onto lambda_n >= 0 and the cones (:func:`cone_project`)."""
    for i in range(m):
        out[i] = lam[i]
    for c in range(nc):
        r = row_start[c]
        out[r] = wp.max(out[r], F64(0.0))
        if n_rows[c] == 3:
            l1, l2 = cone_project(out[r + 1], out[r + 2], mu[c] * out[r], pyramid)
            out[r + 1] = l1
            out[r + 2] = l2


@wp.func
def _friction_residual(W: wp.array2d(dtype=wp.float64), d0: wp.array(dtype=wp.float64),
                       lam: wp.array(dtype=wp.float64), delta: wp.array(dtype=wp.float64),
                       row_start: wp.array(dtype=wp.int32), n_rows: wp.array(dtype=wp.int32),
                       mu: wp.array(dtype=wp.float64), pyramid: int, m: int, nc: int):
    """:func:`pgs_residual` of lam (delta = W lam + d0 summed afresh into ``delta``)."""
    for i in range(m):
        delta[i] = row_delta(W, d0, lam, i, m)
    return jacobi_change(W, delta, lam, row_start, n_rows, mu, pyramid, nc)


@wp.func
def _same_state(fiwork: wp.array2d(dtype=wp.int32), fwork: wp.array2d(dtype=wp.float64), on_a: int, h1_a: int,
                h2_a: int, on_b: int, h1_b: int, h2_b: int, nc: int):
    """1 where two states of the contacts (rows of on and held) are the same."""
    same = int(1)
    for c in range(nc):
        if fiwork[on_a, c] != fiwork[on_b, c] or fwork[h1_a, c] != fwork[h1_b, c] or fwork[h2_a, c] != fwork[h2_b, c]:
            same = 0
    return same


@wp.func
def _unknown_column(W: wp.array2d(dtype=wp.float64), row_start: wp.array(dtype=wp.int32),
                    n_rows: wp.array(dtype=wp.int32), mu: wp.array(dtype=wp.float64),
                    fwork: wp.array2d(dtype=wp.float64), fiwork: wp.array2d(dtype=wp.int32), i: int, j: int):
    """Row i of W times unknown j's column (its normal with the held tangents, or a free tangent)."""
    c = fiwork[_FUNKC, j]
    t = fiwork[_FUNKT, j]
    r = row_start[c]
    v = F64(0.0)
    if t == 0:
        v = W[i, r]
        if n_rows[c] == 3:
            v += mu[c] * (fwork[_FH1, c] * W[i, r + 1] + fwork[_FH2, c] * W[i, r + 2])
    else:
        v = W[i, r + t]
    return v


@wp.func
def friction_finish(W: wp.array2d(dtype=wp.float64), d0: wp.array(dtype=wp.float64),
                    row_start: wp.array(dtype=wp.int32), n_rows: wp.array(dtype=wp.int32),
                    mu: wp.array(dtype=wp.float64), lam: wp.array(dtype=wp.float64), m: int, nc: int,
                    pyramid: int, tolerance: wp.float64, max_steps: int, fwork: wp.array2d(dtype=wp.float64),
                    fiwork: wp.array2d(dtype=wp.int32), A: wp.array2d(dtype=wp.float64),
                    N: wp.array2d(dtype=wp.float64)):
    """The friction finish on one thread (the host's kernel, or a lane of the device's block),
    from ``lam`` (the NumPy reference, ``friction_active_set`` of test/lcp_reference.py, makes
    the same states, steps and choices, its sums by BLAS and LAPACK: equal to rounding). The
    iterate of least residual goes to ``fwork[_FBEST]``; returns (steps, its residual)."""
    zero = F64(0.0)
    one = F64(1.0)
    best = fwork[_FBEST]
    new = fwork[_FNEW]
    sol = fwork[_FSOL]
    dl = fwork[_FDELTA]
    y = fwork[_FY]
    y2 = fwork[_FY2]
    rhs = fwork[_FRHS]
    rhs2 = fwork[_FRHS2]
    tmp = fwork[_FT]
    for i in range(m):
        best[i] = lam[i]
    best_res = _friction_residual(W, d0, best, dl, row_start, n_rows, mu, pyramid, m, nc)
    if m == 0 or best_res <= tolerance:
        return 0, best_res
    tight = F64(1.0) - F64(1e-9)
    for c in range(nc):
        r = row_start[c]
        fiwork[_FON, c] = int(lam[r] > zero)
        fwork[_FH1, c] = zero
        fwork[_FH2, c] = zero
        if n_rows[c] == 3 and lam[r] > zero:
            lim = mu[c] * lam[r]
            t1 = lam[r + 1]
            t2 = lam[r + 2]
            size = wp.sqrt(t1 * t1 + t2 * t2)
            if pyramid != 0:
                size = wp.max(wp.abs(t1), wp.abs(t2))
            if size >= lim * tight and lim > zero:
                if pyramid != 0:
                    if wp.abs(t1) >= lim * tight:
                        fwork[_FH1, c] = _sign(t1)
                    if wp.abs(t2) >= lim * tight:
                        fwork[_FH2, c] = _sign(t2)
                else:
                    n = wp.sqrt(t1 * t1 + t2 * t2)
                    fwork[_FH1, c] = t1 / n
                    fwork[_FH2, c] = t2 / n
    kept = int(0)  # states kept for the cycle check (the last two)
    steps = int(0)
    while steps < max_steps:
        if kept >= 1 and _same_state(fiwork, fwork, _FON, _FH1, _FH2, _FONP, _FH1P, _FH2P, nc) != 0:
            break
        if kept >= 2 and _same_state(fiwork, fwork, _FON, _FH1, _FH2, _FONQ, _FH1Q, _FH2Q, nc) != 0:
            break
        for c in range(nc):  # the state before becomes the one before that, this one the state before
            fiwork[_FONQ, c] = fiwork[_FONP, c]
            fwork[_FH1Q, c] = fwork[_FH1P, c]
            fwork[_FH2Q, c] = fwork[_FH2P, c]
            fiwork[_FONP, c] = fiwork[_FON, c]
            fwork[_FH1P, c] = fwork[_FH1, c]
            fwork[_FH2P, c] = fwork[_FH2, c]
        kept = wp.min(kept + 1, 2)
        # unknowns: each on contact's normal (with its held tangents), then its free tangents
        k = int(0)
        for c in range(nc):
            if fiwork[_FON, c] != 0:
                r = row_start[c]
                fiwork[_FUNKC, k] = c
                fiwork[_FUNKT, k] = 0
                fiwork[_FEQ, k] = r
                k += 1
                if n_rows[c] == 3:
                    for t in range(1, 3):
                        free = int(0)
                        if pyramid != 0:
                            if (t == 1 and fwork[_FH1, c] == zero) or (t == 2 and fwork[_FH2, c] == zero):
                                free = 1
                        elif fwork[_FH1, c] == zero and fwork[_FH2, c] == zero:
                            free = 1
                        if free != 0:
                            fiwork[_FUNKC, k] = c
                            fiwork[_FUNKT, k] = t
                            fiwork[_FEQ, k] = r + t
                            k += 1
        steps += 1
        for i in range(m):
            new[i] = zero
        if k > 0:
            for a in range(k):
                for b in range(k):
                    A[a, b] = _unknown_column(W, row_start, n_rows, mu, fwork, fiwork, fiwork[_FEQ, a], b)
                rhs[a] = -d0[fiwork[_FEQ, a]]
            dmax = zero
            for a in range(k):  # N = A^T A, its lower triangle
                for b in range(a + 1):
                    acc = zero
                    for q in range(k):
                        acc += A[q, a] * A[q, b]
                    N[a, b] = acc
                    N[b, a] = acc
                dmax = wp.max(dmax, wp.abs(N[a, a]))
            shift = F64(1e-12) * dmax
            ok = int(1)
            for a in range(k):  # Cholesky of N + shift I in place (lower)
                acc = N[a, a] + shift
                for q in range(a):
                    acc -= N[a, q] * N[a, q]
                if not (acc > zero):
                    ok = 0
                    break
                d = wp.sqrt(acc)
                N[a, a] = d
                for b in range(a + 1, k):
                    u = N[b, a]
                    for q in range(a):
                        u -= N[b, q] * N[a, q]
                    N[b, a] = u / d
            if ok == 0:
                break
            _transpose_times(A, rhs, k, rhs2)  # y = N^-1 A^T rhs, then one refinement against A
            face_substitute(N, rhs2, k, tmp, y)
            for a in range(k):
                acc = rhs[a]
                for b in range(k):
                    acc -= A[a, b] * y[b]
                tmp[a] = acc
            _transpose_times(A, tmp, k, rhs2)
            face_substitute(N, rhs2, k, tmp, y2)
            for a in range(k):
                y[a] = y[a] + y2[a]
            for j in range(k):  # lambda = B y
                c = fiwork[_FUNKC, j]
                t = fiwork[_FUNKT, j]
                r = row_start[c]
                if t == 0:
                    new[r] += y[j]
                    if n_rows[c] == 3:
                        new[r + 1] += mu[c] * fwork[_FH1, c] * y[j]
                        new[r + 2] += mu[c] * fwork[_FH2, c] * y[j]
                else:
                    new[r + t] += y[j]
        _friction_cone(new, sol, row_start, n_rows, mu, pyramid, m, nc)
        res = _friction_residual(W, d0, sol, dl, row_start, n_rows, mu, pyramid, m, nc)
        if res < best_res:
            best_res = res
            for i in range(m):
                best[i] = sol[i]
        if best_res <= tolerance:
            break
        # the states the solution asks for
        for i in range(m):
            dl[i] = row_delta(W, d0, new, i, m)
        for c in range(nc):
            r = row_start[c]
            on = fiwork[_FON, c]
            on_next = on
            if on != 0 and new[r] < zero:
                on_next = 0
            if on == 0 and dl[r] < -tolerance:
                on_next = 1
            fiwork[_FONN, c] = on_next
            h1 = fwork[_FH1, c]
            h2 = fwork[_FH2, c]
            if on_next == 0 or on == 0:
                h1 = zero
                h2 = zero
            elif n_rows[c] == 3:
                limc = mu[c] * wp.max(new[r], zero)
                lt1 = new[r + 1]
                lt2 = new[r + 2]
                s1, s2 = stick_point(W, r, lt1, lt2, dl[r + 1], dl[r + 2])
                if pyramid != 0:
                    h1 = _held_component(h1, lt1, s1, limc)
                    h2 = _held_component(h2, lt2, s2, limc)
                elif h1 == zero and h2 == zero:
                    n_lt = wp.sqrt(lt1 * lt1 + lt2 * lt2)
                    if n_lt > limc * (one + F64(1e-9)):
                        h1 = lt1 / n_lt
                        h2 = lt2 / n_lt
                else:
                    n_st = wp.sqrt(s1 * s1 + s2 * s2)
                    h1 = zero
                    h2 = zero
                    if n_st > limc and n_st > zero:
                        h1 = s1 / n_st
                        h2 = s2 / n_st
            fwork[_FH1N, c] = h1
            fwork[_FH2N, c] = h2
        for c in range(nc):
            fiwork[_FON, c] = fiwork[_FONN, c]
            fwork[_FH1, c] = fwork[_FH1N, c]
            fwork[_FH2, c] = fwork[_FH2N, c]
    return steps, best_res


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
    first_sweeps: int,
    finish: int,
    fwork: wp.array2d(dtype=wp.float64),
    fiwork: wp.array2d(dtype=wp.int32),
    fA: wp.array2d(dtype=wp.float64),
    fN: wp.array2d(dtype=wp.float64),
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

    ``finish`` (contact.friction_active_set; :func:`finishes_friction` says where it applies):
    ``first_sweeps`` sweeps, then up to
    :data:`FRICTION_FINISHES` of :func:`friction_finish` (its steps counted), each followed by
    sweeps from the better lambda (:data:`FRICTION_SWEEPS` between two, the last one's taking
    what is left of ``max_iterations``); the work arrays are the finish's.
    """
    if finishes_friction(m, nc, finish) == 0:
        it, res = pgs_sweeps(W, d0, row_start, n_rows, mu, m, nc, max_iterations, tolerance, pyramid, lam, delta)
    else:
        it, res = pgs_sweeps(W, d0, row_start, n_rows, mu, m, nc, wp.min(first_sweeps, max_iterations), tolerance,
                             pyramid, lam, delta)
        for k in range(FRICTION_FINISHES):
            if res <= tolerance or it >= max_iterations:
                break
            steps, rf = friction_finish(W, d0, row_start, n_rows, mu, lam, m, nc, pyramid, tolerance,
                                        wp.min(FRICTION_STEPS, max_iterations - it), fwork, fiwork, fA, fN)
            it += steps
            if rf < res:
                res = rf
                for i in range(m):
                    lam[i] = fwork[_FBEST, i]
            if res > tolerance and it < max_iterations:
                more_sweeps = max_iterations - it
                if k + 1 < FRICTION_FINISHES:
                    more_sweeps = wp.min(FRICTION_SWEEPS, more_sweeps)
                more, res = pgs_sweeps(W, d0, row_start, n_rows, mu, m, nc, more_sweeps, tolerance, pyramid, lam, delta)
                it += more
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

    The passive set P starts as the rows with lambda > 0 (ascending), and keeps its rows in the
    order they joined (a row joining goes last; rows leaving keep the others' order), as the
    device's finish keeps it to grow and shrink its face's inverse in place. A step solves the face problem of P
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
    order = [int(i) for i in np.flatnonzero(passive)]  # P in the order its rows joined
    shift *= float(W.diagonal().max())
    steps, joined = 0, -1
    while steps < max_steps:
        P = np.array(order, dtype=np.int64)
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
                order = [i for i in order if passive[i]]
                joined = -1
                continue
        lam = s
        w = -(W @ lam + d0)
        w[passive] = -np.inf
        j = int(np.argmax(w))
        if w[j] <= tolerance:
            return lam, steps
        passive[j] = True
        order.append(j)
        joined = j
    return lam, steps


class PGS:
    """The contact LCP's solver: projected Gauss-Seidel sweeps (:func:`pgs_kernel`) and, for a
    frictionless LCP (every contact one row), :func:`active_set` after ``first_sweeps`` of
    them.

    A frictionless solve sweeps until the tolerance or ``first_sweeps`` (at most
    :data:`LARGE_FIRST_SWEEPS` for a set of more than :data:`LARGE_SET_ROWS` rows:
    :func:`first_sweeps_of`); if not converged, the
    active-set method continues from the sweeps' lambda with the rest of ``max_iterations`` as
    its steps; if that does not finish within tolerance (see :func:`active_set`), the sweeps
    go on from the better of the two for what is left. A solve with friction rows sweeps up to
    ``max_iterations``; with ``friction_active_set`` the kernel sweeps ``first_sweeps``, then,
    where not converged, makes :func:`friction_finish` (its steps counted) and sweeps from the
    better lambda, :data:`FRICTION_SWEEPS` of them between two finishes, at most
    :data:`FRICTION_FINISHES`, the last finish's sweeps taking what is left (one launch), for
    sets of up to :data:`FRICTION_FINISH_ROWS` rows (beyond, the sweeps alone).
    ``active_set=False``: sweeps only, always. The CPU buffers are kept between solves: they
    grow to the largest problem seen and are filled in place, and the kernel's launch is
    recorded once per set of buffers, so that a sweep phase allocates no Warp array and makes
    one launch. The kernel is built (or loaded from the cache) when the solver is made, not at
    its first set: on a GPU that is the first set beyond the device's rows, mid-run.
    """

    def __init__(self, active_set: bool = True, first_sweeps: int = FIRST_SWEEPS, friction_active_set: bool = False):
        self.active_set = bool(active_set)
        self.friction_active_set = bool(friction_active_set)
        self.first_sweeps = int(first_sweeps)
        self.rows_cap = self.contacts_cap = 0
        self._cmd = None
        wp.load_module(sys.modules[__name__], device="cpu")

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
        self.fwork, self.fiwork = z((FWORK_ROWS, rc), wp.float64), z((FIWORK_ROWS, rc), wp.int32)
        self.fA, self.fN = z((rc, rc), wp.float64), z((rc, rc), wp.float64)
        self._cmd = wp.launch(pgs_kernel, 1, [self.W, self.d0, self.row_start, self.n_rows, self.mu, 0, 0, 0, 0.0, 0,
                                              self.lam, self.delta, self.info, 0, 0, self.fwork, self.fiwork, self.fA,
                                              self.fN], device="cpu", record_cmd=True)
        self._np = {name: getattr(self, name).numpy() for name in
                    ("W", "d0", "lam", "row_start", "n_rows", "mu", "info")}

    def _sweeps(self, lam: np.ndarray, m: int, nc: int, max_iterations: int, tolerance: float,
                pyramid: bool, finish: bool = False) -> tuple[np.ndarray, int, float]:
        """Up to ``max_iterations`` sweeps from ``lam`` on the problem in the buffers (``finish``:
        with the friction finish after ``first_sweeps`` of them, :func:`pgs_kernel`)."""
        a = self._np
        a["lam"][:m] = lam
        cmd = self._cmd
        for index, value in ((5, m), (6, nc), (7, int(max_iterations)), (8, float(tolerance)), (9, int(pyramid)),
                             (13, self.first_sweeps), (14, int(finish))):
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
        if self.active_set and self.friction_active_set and nc < m:  # the kernel finishes it (or sweeps alone)
            return self._sweeps(lam0, m, nc, max_iterations, tolerance, pyramid, finish=True)
        first = first_sweeps_of(m, self.first_sweeps, int(max_iterations)) if finish else max_iterations
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
