"""A reference for the contact LCP's friction finish: :func:`soft_tissue_sim.contact.pgs.
friction_finish` (a Warp function, one thread: the host's kernel and the device's block) written
again in NumPy and SciPy's LAPACK, and the solve around it as :meth:`PGS.solve` makes it, the
sweeps by the kernel alone. The tests hold the kernel to it."""

from __future__ import annotations

import numpy as np
from scipy.linalg.lapack import dpotrf, dpotrs

from soft_tissue_sim.contact.pgs import (FIRST_SWEEPS, FRICTION_FINISH_ROWS, FRICTION_FINISHES, FRICTION_STEPS,
                                        FRICTION_SWEEPS, PGS)


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


def solve_reference(W, d0, row_start, rows, mu, max_iterations, tolerance, pyramid, lam0):
    """:meth:`PGS.solve` with ``friction_active_set`` (an LCP with friction) made of the kernel's
    sweeps (``PGS(active_set=False)``) and :func:`friction_active_set`: (lambda, iterations,
    residual)."""
    m, nc = len(d0), len(row_start)
    pgs = PGS(active_set=False)
    if m > FRICTION_FINISH_ROWS:
        return pgs.solve(W, d0, row_start, rows, mu, max_iterations, tolerance, pyramid, lam0)
    pgs.solve(W, d0, row_start, rows, mu, 1, tolerance, pyramid, lam0)  # the buffers filled
    lam, its, res = pgs._sweeps(lam0, m, nc, min(FIRST_SWEEPS, max_iterations), tolerance, pyramid)
    for k in range(FRICTION_FINISHES):
        if res <= tolerance or its >= max_iterations:
            break
        lf, steps, rf = friction_active_set(W, d0, row_start, rows, mu, lam, pyramid, tolerance,
                                            min(FRICTION_STEPS, max_iterations - its))
        its += steps
        if rf < res:
            lam, res = lf, rf
        if res > tolerance and its < max_iterations:
            more = FRICTION_SWEEPS if k + 1 < FRICTION_FINISHES else max_iterations - its
            lam, n, res = pgs._sweeps(lam, m, nc, min(more, max_iterations - its), tolerance, pyramid)
            its += n
    return lam, its, res
