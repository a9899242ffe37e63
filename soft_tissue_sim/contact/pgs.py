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
around it) the sweeps converge slowly; by default they run alone. :func:`friction_active_set`
(``contact.friction_active_set``; the device's block has it too) finishes them instead: it
solves the linear system of the contacts' current states (off, sticking, sliding) and follows
the states the solution asks for, keeping the iterate of least residual, between rounds of
sweeps.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp
from scipy.linalg.lapack import dpotrf, dpotrs

from .geometry import F64

wp.set_module_options({"enable_backward": False})  # no gradients are taken

FIRST_SWEEPS = 10  # the sweeps before an active-set finish (PGS)
FRICTION_STEPS = 10  # with friction: the most steps of one active-set finish (PGS)
FRICTION_FINISHES = 2  # with friction: the most finishes a solve (PGS)
FRICTION_SWEEPS = 20  # with friction: the sweeps between two finishes (PGS)


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


def pgs_residual_host(W: np.ndarray, d0: np.ndarray, lam: np.ndarray, row_start: np.ndarray, rows: np.ndarray,
                      mu: np.ndarray, pyramid: bool) -> float:
    """:func:`pgs_residual` on the host, for contacts of one or three rows: the largest change
    :func:`contact_update` would make to any contact from ``lam`` (delta = W lambda + d0 summed
    by BLAS, so equal to the kernel's up to rounding) [m]."""
    if len(d0) == 0 or len(row_start) == 0:
        return 0.0
    delta = W @ lam + d0
    r = np.asarray(row_start, np.int64)
    diag = W[r, r]
    ln = np.maximum(0.0, lam[r] - delta[r] / diag)
    change = diag * np.abs(ln - lam[r])
    f = np.asarray(rows) == 3
    if f.any():
        rf, lnf = r[f], ln[f]
        dln = lnf - lam[rf]
        t1 = delta[rf + 1] + W[rf + 1, rf] * dln
        t2 = delta[rf + 2] + W[rf + 2, rf] * dln
        a11, a22 = W[rf + 1, rf + 1], W[rf + 2, rf + 2]
        a12 = 0.5 * (W[rf + 1, rf + 2] + W[rf + 2, rf + 1])
        det = a11 * a22 - a12 * a12
        ok = det > 0.0
        safe = np.where(ok, det, 1.0)
        l1 = np.where(ok, lam[rf + 1] - (a22 * t1 - a12 * t2) / safe, lam[rf + 1])
        l2 = np.where(ok, lam[rf + 2] - (a11 * t2 - a12 * t1) / safe, lam[rf + 2])
        l1, l2 = _onto_cone(l1, l2, np.asarray(mu)[f] * lnf, pyramid)
        change[f] = np.maximum(change[f], np.maximum(a11 * np.abs(l1 - lam[rf + 1]), a22 * np.abs(l2 - lam[rf + 2])))
    return float(change.max())


def _onto_cone(l1: np.ndarray, l2: np.ndarray, lim: np.ndarray, pyramid: bool) -> tuple[np.ndarray, np.ndarray]:
    """Tangential forces (l1, l2) projected onto their cones of radius ``lim``, as
    :func:`contact_update` projects them: each component clamped (pyramid), or the pair scaled
    onto the disk's rim where outside it."""
    if pyramid:
        return np.clip(l1, -lim, lim), np.clip(l2, -lim, lim)
    lt = np.hypot(l1, l2)
    scale = np.where(lt > lim, np.divide(lim, lt, out=np.zeros_like(lt), where=lt > 0.0), 1.0)
    return l1 * scale, l2 * scale


def _cone(lam: np.ndarray, r: np.ndarray, rows: np.ndarray, mu: np.ndarray, pyramid: bool) -> np.ndarray:
    """``lam`` projected onto lambda_n >= 0 and the friction cones (a copy)."""
    out = lam.copy()
    out[r] = np.maximum(out[r], 0.0)
    f = rows == 3
    if f.any():
        rf = r[f]
        out[rf + 1], out[rf + 2] = _onto_cone(out[rf + 1], out[rf + 2], mu[f] * out[rf], pyramid)
    return out


def friction_active_set(W: np.ndarray, d0: np.ndarray, row_start: np.ndarray, rows: np.ndarray, mu: np.ndarray,
                        lam: np.ndarray, pyramid: bool, tolerance: float, max_steps: int,
                        shift: float = 1e-12) -> tuple[np.ndarray, int, float]:
    """An active-set finish for an LCP with friction (contacts of three rows, or one), from the
    sweeps' ``lam``: returns (lambda, steps, residual of :func:`pgs_residual_host`), lambda the
    step of least residual (``lam`` itself where none does better).

    Each contact has a state: off (every row 0), or on with each tangent either free or held at
    the cone. A step solves the linear system of that state: an on contact's normal gap is 0, a
    free tangent's gap is 0; the disk's held tangents are mu lambda_n along a fixed unit
    direction, the pyramid's each at +-mu lambda_n. Where rows nearly repeat a constraint (a
    node contact and the face contacts around it) the system is near singular: it is solved by
    its normal equations shifted by ``shift`` times their largest diagonal and one refinement
    (the least-squares solution, a shared force). The solution, projected onto the cones, is
    scored by the PGS residual; then the states follow it: a contact pulled (lambda_n < 0) goes
    off, an off contact penetrating beyond the tolerance comes on, a free tangent beyond the cone
    is held there, and a held one takes the cone point a Gauss-Seidel update of its contact would
    project to (free again where that point is inside the cone). It stops at the tolerance, when
    the states repeat one of the last two, or after ``max_steps``. The states start from ``lam``
    (a tangent on the cone held, inside it free). No convergence guarantee (with friction the LCP is not a
    quadratic program): the caller goes on sweeping from the returned lambda where the residual
    is above the tolerance."""
    m = len(d0)
    r = np.asarray(row_start, np.int64)
    rows = np.asarray(rows)
    mu = np.asarray(mu, dtype=np.float64)
    lam = np.asarray(lam, dtype=np.float64)
    best, best_res = lam, pgs_residual_host(W, d0, lam, r, rows, mu, pyramid)
    if m == 0 or best_res <= tolerance:
        return best, 0, best_res
    f = rows == 3
    on = lam[r] > 0.0
    lim = mu * lam[r]
    held = np.zeros((len(r), 2))  # per contact: (0, 0) free; disk: the unit direction held; pyramid: the signs
    if f.any():
        t = np.stack([lam[np.minimum(r + 1, m - 1)], lam[np.minimum(r + 2, m - 1)]], axis=1)
        at = (np.abs(t).max(axis=1) if pyramid else np.hypot(t[:, 0], t[:, 1])) >= lim * (1.0 - 1e-9)
        at &= f & on & (lim > 0.0)
        if pyramid:
            held[at] = np.where(np.abs(t[at]) >= lim[at, None] * (1.0 - 1e-9), np.sign(t[at]), 0.0)
        else:
            held[at] = t[at] / np.hypot(t[at, 0], t[at, 1])[:, None]
    recent = []  # the last two states (a cycle of one or two steps ends the finish)
    steps = 0
    while steps < max_steps:
        key = (on.tobytes(), held.tobytes())
        if key in recent:
            break
        recent = [key] + recent[:1]
        # unknowns: each on contact's normal, and each of its free tangents; equations: their gaps
        cols, eqs = [], []
        for c in np.flatnonzero(on):
            rc = int(r[c])
            col = np.zeros(m)
            col[rc] = 1.0
            if f[c]:
                h = held[c]
                if pyramid:
                    for j in (0, 1):
                        if h[j] != 0.0:
                            col[rc + 1 + j] = mu[c] * h[j]
                elif h.any():
                    col[rc + 1:rc + 3] = mu[c] * h
            cols.append(col)
            eqs.append(rc)
            if f[c]:
                for j in (0, 1):
                    if (pyramid and held[c, j] == 0.0) or (not pyramid and not held[c].any()):
                        col = np.zeros(m)
                        col[rc + 1 + j] = 1.0
                        cols.append(col)
                        eqs.append(rc + 1 + j)
        steps += 1
        new = np.zeros(m)
        if cols:
            B = np.array(cols).T
            y = _least_squares(W[eqs] @ B, -d0[eqs], shift)
            if y is None:
                break
            new = B @ y
        sol = _cone(new, r, rows, mu, pyramid)
        res = pgs_residual_host(W, d0, sol, r, rows, mu, pyramid)
        if res < best_res:
            best, best_res = sol, res
        if best_res <= tolerance:
            break
        # the states the solution asks for
        delta = W @ new + d0
        on_next = on.copy()
        on_next[on & (new[r] < 0.0)] = False
        on_next[~on & (delta[r] < -tolerance)] = True
        held_next = held.copy()
        held_next[~on_next] = 0.0
        for c in np.flatnonzero(on_next & f):
            rc = int(r[c])
            limc = mu[c] * max(new[rc], 0.0)
            lt = new[rc + 1:rc + 3]
            if not on[c]:  # just taken in: free
                held_next[c] = 0.0
                continue
            # the point a Gauss-Seidel update of this contact goes to before its projection
            a11, a22 = W[rc + 1, rc + 1], W[rc + 2, rc + 2]
            a12 = 0.5 * (W[rc + 1, rc + 2] + W[rc + 2, rc + 1])
            det = a11 * a22 - a12 * a12
            tt = delta[rc + 1:rc + 3]
            stick = lt - (np.array([a22 * tt[0] - a12 * tt[1], a11 * tt[1] - a12 * tt[0]]) / det if det > 0.0 else 0.0)
            if pyramid:
                for j in (0, 1):
                    if held[c, j] == 0.0:
                        held_next[c, j] = np.sign(lt[j]) if abs(lt[j]) > limc * (1.0 + 1e-9) else 0.0
                    else:
                        held_next[c, j] = np.sign(stick[j]) if abs(stick[j]) > limc else 0.0
            elif not held[c].any():
                n_lt = float(np.hypot(lt[0], lt[1]))
                if n_lt > limc * (1.0 + 1e-9):
                    held_next[c] = lt / n_lt
            else:
                n_st = float(np.hypot(stick[0], stick[1]))
                held_next[c] = stick / n_st if n_st > limc and n_st > 0.0 else 0.0
        on, held = on_next, held_next
    return best, steps, best_res


def _least_squares(A: np.ndarray, rhs: np.ndarray, shift: float) -> np.ndarray | None:
    """The solution of A y = rhs in the least-squares sense, by the normal equations shifted by
    ``shift`` times their largest diagonal and one step of refinement; None where even shifted
    they are not positive definite."""
    N = A.T @ A
    N[np.diag_indices_from(N)] += shift * float(np.abs(np.diag(N)).max())
    c, info = dpotrf(N, lower=1, clean=0)
    if info != 0:
        return None
    y = dpotrs(c, A.T @ rhs, lower=1)[0]
    return y + dpotrs(c, A.T @ (rhs - A @ y), lower=1)[0]


class PGS:
    """The contact LCP's solver: projected Gauss-Seidel sweeps (:func:`pgs_kernel`) and, for a
    frictionless LCP (every contact one row), :func:`active_set` after ``first_sweeps`` of
    them.

    A frictionless solve sweeps until the tolerance or ``first_sweeps``; if not converged, the
    active-set method continues from the sweeps' lambda with the rest of ``max_iterations`` as
    its steps; if that does not finish within tolerance (see :func:`active_set`), the sweeps
    go on from the better of the two for what is left. A solve with friction rows sweeps up to
    ``max_iterations``; with ``friction_active_set`` it sweeps ``first_sweeps``, then, where not
    converged, makes a :func:`friction_active_set` (its steps counted) and sweeps from the better
    lambda, :data:`FRICTION_SWEEPS` of them between two finishes, at most
    :data:`FRICTION_FINISHES`, the last finish's sweeps taking what is left. ``active_set=False``: sweeps only,
    always. The CPU buffers are kept between solves: they grow to the largest problem seen and
    are filled in place, and the kernel's launch is recorded once per set of buffers, so that a
    sweep phase allocates no Warp array and makes one launch.
    """

    def __init__(self, active_set: bool = True, first_sweeps: int = FIRST_SWEEPS, friction_active_set: bool = False):
        self.active_set = bool(active_set)
        self.friction_active_set = bool(friction_active_set)
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
        friction = self.active_set and self.friction_active_set and nc < m
        first = min(self.first_sweeps, max_iterations) if finish or friction else max_iterations
        lam, its, res = self._sweeps(lam0, m, nc, first, tolerance, pyramid)
        if friction:
            for k in range(FRICTION_FINISHES):
                if res <= tolerance or its >= max_iterations:
                    break
                lf, steps, rf = friction_active_set(W, d0, row_start, rows, mu, lam, pyramid, tolerance,
                                                    min(FRICTION_STEPS, max_iterations - its))
                its += steps
                if rf < res:
                    lam, res = lf, rf
                if res > tolerance and its < max_iterations:  # the last finish's sweeps take what is left
                    more_sweeps = FRICTION_SWEEPS if k + 1 < FRICTION_FINISHES else max_iterations - its
                    lam, more, res = self._sweeps(lam, m, nc, min(more_sweeps, max_iterations - its), tolerance,
                                                  pyramid)
                    its += more
            return lam, its, res
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
