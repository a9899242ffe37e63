"""The contact compliance W of eq. (4) and the correction it implies.

    W = dt^2 H P^-1 H^T  [m/N],      dx = dt^2 P^-1 H^T lambda

with H the contacts' Jacobian (one row per constraint, 3n columns) and P ~ A = m_coef M +
k_coef K the step's matrix. A force f [N] held during the step moves x by dt^2 A^-1 f, so
lambda is a force, not an impulse (the paper factorizes A / dt^2). Modes:

- ``preconditioner``: P^-1 is the asynchronous rotated LDL^T preconditioner, Sherman-Morrison
  cut correction and identity padding included (eq. 11-12). W from the forward solves
  L^-1 P H^T alone where the factor offers ``delassus`` (each column walks only its reach in
  the elimination tree, :mod:`soft_tissue_sim.delassus`), else from the columns P^-1 H^T
  (``apply_columns``, on the device where the factor is there); dx by one full solve.
- ``diagonal``: P is the block-Jacobi diagonal of A (also for the ``jacobi`` and ``none``
  preconditioners, which have no factor). Cheap; the correction reaches the contact nodes
  only, so contact forces are not the physical ones.
- ``exact``: A^-1 itself, one PCG solve per constraint row.

Invariant: the functions return W / dt^2 and the map lambda -> P^-1 H^T lambda of the same P
(a host vector (3n,), or a device array (n,) of vec3d where the factor lives on a GPU).
Fixed nodes have zero columns in H, so they never move.
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse as sps
import warp as wp

from .jacobian import ConstraintRows


def compliance(H: ConstraintRows, mode: str, preconditioner, integrator, fem):
    """(W / dt^2 = H P^-1 H^T dense, a function lam -> P^-1 H^T lam, the kind used), for the
    contacts' Jacobian ``H`` in node form: a device factor gathers W from that form, and H^T lam
    is scattered from it; the sparse matrix is made only for the modes that multiply by it."""
    inner = getattr(preconditioner, "inner", None)
    if mode == "preconditioner" and inner is None:
        mode = "diagonal"  # jacobi / none: no factorization to use
    Yt = None  # rows: P^-1 applied to the rows of H
    if mode == "preconditioner":
        try:
            if hasattr(inner, "delassus_rows"):
                W = inner.delassus_rows(H.nodes, H.coef)
            else:
                W = inner.delassus(H.csr().T.tocsc()) if hasattr(inner, "delassus") else None
            if W is not None:  # forward solves alone (host) or gathered (device); dx by one application
                if hasattr(inner, "apply_vector"):  # a device factor: the result stays there
                    return W, (lambda lam: inner.apply_vector(H.transpose_times(lam))), mode
                return W, (lambda lam: inner.apply_columns(H.transpose_times(lam)[:, None])[:, 0]), mode
            Hd = H.csr().toarray()  # (m, 3n): one row per constraint
            if hasattr(inner, "apply_columns"):
                Yt = np.ascontiguousarray(np.asarray(inner.apply_columns(np.ascontiguousarray(Hd.T))).T)
            else:
                Yt = np.empty_like(Hd)
                for r in range(Hd.shape[0]):
                    inner.apply(Hd[r], Yt[r])
        except ValueError as exc:  # e.g. the factor is for another DOF count just after a cut
            warnings.warn(f"contact: preconditioner compliance unavailable ({exc}); using the diagonal",
                          stacklevel=3)
            mode, Yt = "diagonal (fallback)", None
    elif mode == "exact":  # A^-1 by one PCG solve per row, to the integrator's tolerance
        Hd = H.csr().toarray()
        Yt = np.empty_like(Hd)
        y = wp.zeros(fem.n_nodes, dtype=wp.vec3d, device=fem.device)
        for r in range(Hd.shape[0]):
            integrator.cg.solve(integrator.matvec, wp.array(Hd[r].reshape(-1, 3), dtype=wp.vec3d, device=fem.device),
                                y, integrator.preconditioner)
            Yt[r] = y.numpy().reshape(-1)
    if Yt is not None:
        return np.asarray(H.csr() @ Yt.T), (lambda lam: Yt.T @ lam), mode
    n = fem.n_nodes
    D = wp.zeros(n, dtype=wp.mat33d, device=fem.device)
    fem.diagonal_blocks(integrator.m_coef, integrator.k_coef, D)
    Dinv = np.linalg.inv(D.numpy())
    B = sps.bsr_matrix((Dinv, np.arange(n), np.arange(n + 1)), shape=(3 * n, 3 * n)).tocsr()
    Hs = H.csr()
    Y = (B @ Hs.T).tocsc()
    return (Hs @ Y).toarray(), (lambda lam: Y @ lam), mode


def positive_definite(W: np.ndarray, dense_check_up_to: int = 1500) -> bool:
    """Is the symmetric compliance W usable by Gauss-Seidel: finite, positive diagonal and, for
    sizes up to ``dense_check_up_to``, no negative eigenvalue beyond rounding (a Cholesky
    factorization of W + 1e-10 max(diag W) I that succeeds). Singular is usable: rows that
    repeat a constraint (a node contact and a face contact at that node, each with its two
    tangent rows) make W singular, not indefinite."""
    if not np.all(np.isfinite(W)) or np.any(np.diag(W) <= 0.0):
        return False
    if len(W) > dense_check_up_to:
        return True
    try:
        np.linalg.cholesky(W + (1e-10 * float(np.max(np.diag(W)))) * np.eye(len(W)))
    except np.linalg.LinAlgError:
        return False
    return True
