"""Low-rank (Sherman-Morrison-Woodbury) correction of the asynchronous preconditioner after
topological changes (paper section 3.2-3.4, eq. 5-12, fig. 2).

A cut changes A at once, but the LDL^T factor P = (LDL^T)_{t_u} lags behind until the next
factorization. Between factorizations we correct it on the few nodes a modification touches.

Perturbation. A modification removes and adds elements. Its change of the (filtered) system
matrix, dA = sum(added element blocks) - sum(removed element blocks), lives on the k affected
nodes. G (3n x 3k) selects their degrees of freedom and, in the factor's (unrotated) frame,

    N = D^T dA D,    D = blockdiag(R_i(t_cut) R_i(t_u)^T)     (the rotations of eq. 2)

Degrees of freedom added since the factor (duplicated nodes) are padded with the identity
(eq. 10): P_ext = blockdiag(P, I), so N also gets -I on their diagonal; a node that vanished
(ablation) gets +I and becomes a decoupled identity row.

Woodbury form without N^-1. The paper writes (P + G N G^T)^-1 = P^-1 - U^T Q U with
Q = (N^-1 + G U)^-1 (eq. 5-7). N is the difference of two stiffness matrices: it is singular
in general (rigid modes of the removed elements, a node whose blocks cancel), so we use the
algebraically equivalent form

    (N^-1 + S)^-1 = (N^-1 (I + N S))^-1 = (I + N S)^-1 N,     S = G^T P^-1 G,

    P~^-1 = P^-1 - U Q U^T,   U = P^-1 G (3n x 3k),   Q = (I + N S)^-1 N   (3k x 3k).

I + N S is invertible whenever P + G N G^T is (det(I + N S) = det(P~) / det(P)), which holds
because the modified A is symmetric positive definite. Successive modifications chain:
U_j = P_{j-1}^-1 G_j with the already corrected P_{j-1}, so the corrections add up,
P~^-1 = P^-1 - sum_j U_j Q_j U_j^T, and each costs only the columns of its own nodes.
U is computed by CHOLMOD's triangular solves on all 3k columns at once (batched).

Lifetime (fig. 2). Every modification carries the mesh version it produced; a factor carries
the version of its snapshot. When a factor is installed, modifications it already contains
(version <= the factor's) are dropped; those made while it was being computed are
re-applied to it, so the factor that was running during a cut is corrected too.

Application (eq. 8-10): x = D (P_ext^-1 - sum U Q U^T) D^T b, the rotations around the
corrected operator, with current nodes mapped into the factor's numbering by node uids.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sps

from .blas_threads import one_thread
from .ldlt_preconditioner import rotate_nodes


@dataclass
class Modification:
    """One topological change, in the numbering-free terms of node uids.

    ``uids`` (k,): the affected nodes; ``dA`` (3k, 3k): the change of the filtered A on them,
    world frame, at the time of the change; ``R`` (k, 3, 3): their nodal rotations then;
    ``free`` (k,): 1 free, 0 fixed; ``created`` / ``removed``: uids of nodes added / deleted.
    """

    version: int
    uids: np.ndarray
    dA: np.ndarray
    R: np.ndarray
    free: np.ndarray
    created: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    removed: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


def modification_from_blocks(version, old_blocks, new_blocks, old_uids, new_uids, R_by_uid, free_by_uid,
                             created=(), removed=()) -> Modification:
    """Build a :class:`Modification` from element blocks before and after a change.

    ``old_blocks`` / ``new_blocks``: (rows, cols, values) from ``CorotationalFEM.element_blocks``
    on the removed / added elements, in the old / new node numbering; ``old_uids`` /
    ``new_uids`` map those numberings to uids; ``R_by_uid`` / ``free_by_uid``: callables
    returning the rotations / free flags of a uid array.
    """
    r0, c0, v0 = old_blocks
    r1, c1, v1 = new_blocks
    ur0, uc0 = old_uids[r0], old_uids[c0]
    ur1, uc1 = new_uids[r1], new_uids[c1]
    uids = np.unique(np.concatenate([ur0, uc0, ur1, uc1, np.asarray(created, np.int64), np.asarray(removed, np.int64)]))
    k = len(uids)
    dA = np.zeros((k, 3, k, 3))
    for ur, uc, vals, sign in ((ur0, uc0, v0, -1.0), (ur1, uc1, v1, 1.0)):
        if len(vals):
            i = np.searchsorted(uids, ur)
            j = np.searchsorted(uids, uc)
            np.add.at(dA, (i, slice(None), j, slice(None)), sign * vals)  # dA[i, :, j, :] += blocks
    return Modification(int(version), uids, dA.reshape(3 * k, 3 * k), np.asarray(R_by_uid(uids)),
                        np.asarray(free_by_uid(uids), dtype=np.float64),
                        np.asarray(created, np.int64), np.asarray(removed, np.int64))


def perturbation(mod: Modification, R_ref: np.ndarray, new_uids: np.ndarray, rotate: bool = True) -> np.ndarray:
    """N (3k x 3k, symmetric) of eq. (5) for one modification, in the factor's unrotated frame:
    N = D^T dA D with D = blockdiag(R_i(t_cut) R_ref_i^T) (identity when not ``rotate``), plus
    the identity padding of eq. (10): -I on the free nodes ``new_uids`` that the factor's space
    holds as identity rows (P_ext = blockdiag(P, I), so N = A_new - I there) and +I on removed
    free nodes (a vanished node becomes a decoupled identity row). ``R_ref`` (k, 3, 3): the
    reference rotations of ``mod.uids`` (R(t_u) of factor nodes, R at creation of added ones)."""
    k = len(mod.uids)
    if rotate:
        D = np.matmul(mod.R, np.swapaxes(R_ref, 1, 2))  # R(t_cut) R_ref^T
    else:
        D = np.tile(np.eye(3), (k, 1, 1))
    # D_a^T dA_ab D_b for every block (a, b) as two batches of k products, not k^2: the block
    # rows a of dA times D_a^T, then the block columns b of that times D_b
    T = np.swapaxes(D, 1, 2) @ mod.dA.reshape(k, 3, 3 * k)  # (k, 3, 3k): row block a, D_a^T dA_a:
    T = T.reshape(3 * k, k, 3).transpose(1, 0, 2) @ D  # (k, 3k, 3): column block b, (.) D_b
    N = T.transpose(1, 0, 2).reshape(3 * k, 3 * k)
    N = 0.5 * (N + N.T)
    pad = np.zeros(k)
    pad[np.isin(mod.uids, new_uids)] -= 1.0
    pad[np.isin(mod.uids, mod.removed)] += 1.0
    N += np.kron(np.diag(pad * mod.free), np.eye(3))
    return N


def node_dofs(nodes: np.ndarray) -> np.ndarray:
    """The DOFs 3 i, 3 i + 1, 3 i + 2 of the nodes i, in order (the rows G selects)."""
    return (3 * np.asarray(nodes, np.int64)[:, None] + np.arange(3)).ravel()


def summed_perturbation(parts) -> tuple[np.ndarray, np.ndarray]:
    """(nodes, N): the perturbations N_i of ``parts`` ((node indices, N_i) pairs, each N_i on
    its nodes' DOFs, as :func:`perturbation` makes it) summed on the union of their nodes
    (ascending): sum_i G_i N_i G_i^T = G N G^T. One part is returned as it is."""
    if len(parts) == 1:
        return parts[0]
    nodes = np.unique(np.concatenate([idx for idx, _ in parts]))
    N = np.zeros((3 * len(nodes), 3 * len(nodes)))
    for idx, Ni in parts:
        r = node_dofs(np.searchsorted(nodes, idx))
        N[np.ix_(r, r)] += Ni
    return nodes, N


def woodbury_q(N, S, xp=np):
    """Q = (I + N S)^-1 N (symmetric), the Woodbury form of eq. (7) that needs no N^-1
    (N is singular in general); S = G^T P^-1 G. ``xp``: the array module of N and S (NumPy, or
    CuPy for a factor on the GPU: then Q is made on the device, without reading S)."""
    Q = xp.linalg.solve(xp.eye(len(N)) + N @ S, N)
    return 0.5 * (Q + Q.T)


class ShermanMorrisonCorrection:
    """The state between two factorizations: node map, padding and the U Q U^T terms.

    ``enabled=False`` keeps only the node map and the identity padding of eq. (10), i.e. the
    uncorrected preconditioner after a cut (the comparison of the paper's table and fig. 3).
    """

    def __init__(self, enabled: bool = True, rotate: bool = True):
        self.enabled = bool(enabled)
        self.rotate = bool(rotate)  # False: the preconditioner is not rotated (eq. 2 off), D = I
        self.mods: list[Modification] = []
        # (U, Q, rows): U rows = 3 * n_ext at its time, rows = its G's rows (the affected DOFs)
        self.terms: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.factor = None
        self.factor_version = -1
        self.current_uids: np.ndarray | None = None
        self._reset_factor_space()
        self.u_ms = 0.0  # time spent on U (batched triangular solves), accumulated; the cutter resets it
        self.q_ms = 0.0  # time spent on Q, accumulated
        self.columns = 0  # columns of U in use

    # ------------------------------------------------------------ bookkeeping
    def _reset_factor_space(self):
        self.ext_uids = np.zeros(0, np.int64)  # factor nodes, then nodes added since
        self.R_ref = np.zeros((0, 3, 3))  # R(t_u) of factor nodes, R at creation of added ones
        self.n_factor = 0
        self._lookup = None
        self.cur_to_ext = None
        self.dR = None

    @property
    def active(self) -> bool:
        """True when the current numbering differs from the factor's or corrections exist."""
        return self.factor is not None and (bool(self.terms) or self.cur_to_ext is not None)

    def _ext_index(self, uids: np.ndarray) -> np.ndarray:
        idx = self._lookup[uids] if len(uids) else np.zeros(0, np.int64)
        if np.any(idx < 0):
            raise KeyError("node uid unknown to the preconditioner")
        return idx

    def _grow(self, uids: np.ndarray, R: np.ndarray) -> None:
        """Append nodes new to the extended space (identity-padded, eq. 10)."""
        if not len(uids):
            return
        self.ext_uids = np.concatenate([self.ext_uids, uids])
        self.R_ref = np.concatenate([self.R_ref, R], axis=0)
        need = int(max(self.ext_uids.max() + 1, len(self._lookup)))
        if need > len(self._lookup):
            self._lookup = np.concatenate([self._lookup, np.full(need - len(self._lookup), -1, np.int64)])
        self._lookup[uids] = np.arange(len(self.ext_uids) - len(uids), len(self.ext_uids))

    def _map_current(self) -> None:
        cur = self.current_uids
        if cur is None or (len(cur) == self.n_factor and not self.terms and len(self.ext_uids) == self.n_factor
                           and np.array_equal(cur, self.ext_uids)):
            self.cur_to_ext = None  # identical numbering: the plain path of eq. (2)
        else:
            self.cur_to_ext = self._ext_index(cur)

    # ------------------------------------------------------------- events
    def set_factor(self, factor, R_tu: np.ndarray, uids: np.ndarray | None, version: int) -> None:
        """A new factor was installed: reset the extended space, re-apply later modifications (fig. 2)."""
        self.factor = factor
        self.factor_version = int(version)
        self.terms = []
        self._reset_factor_space()
        n = len(R_tu)
        self.ext_uids = np.arange(n, dtype=np.int64) if uids is None else np.asarray(uids, np.int64).copy()
        self.R_ref = np.asarray(R_tu, dtype=np.float64).copy()
        self.n_factor = n
        size = int(max(self.ext_uids.max(initial=-1), 0 if self.current_uids is None else self.current_uids.max(initial=-1))) + 1
        self._lookup = np.full(size, -1, np.int64)
        self._lookup[self.ext_uids] = np.arange(n)
        self.mods = [m for m in self.mods if m.version > self.factor_version]  # the factor contains the rest
        for m in self.mods:
            self._apply(m)
        self._map_current()

    def add(self, mod: Modification, current_uids: np.ndarray) -> None:
        """A modification happened now; ``current_uids`` is the new numbering of the nodes."""
        self.current_uids = np.asarray(current_uids, np.int64).copy()
        self.mods.append(mod)
        if self.factor is not None:
            self._apply(mod)
            self._map_current()

    def set_current(self, current_uids) -> None:
        self.current_uids = None if current_uids is None else np.asarray(current_uids, np.int64).copy()
        if self.factor is not None:
            self._map_current()

    def clear(self) -> None:
        self.mods, self.terms, self.factor, self.current_uids = [], [], None, None
        self._reset_factor_space()

    # --------------------------------------------------------------- algebra
    def _solve_ext(self, B: np.ndarray) -> np.ndarray:
        """Corrected, unrotated P_ext^-1 B for B (3 n_ext, c): eq. (9)-(10) without rotations.

        The terms chain: P_j^-1 = P_{j-1}^-1 - U_j Q_j U_j^T with U_j = P_{j-1}^-1 G_j, so
        U_j^T B = G_j^T (P_{j-1}^-1 B) is the rows of the solution corrected so far: each term
        costs one product with U_j (not two), the correction's memory traffic halved."""
        nf3 = 3 * self.n_factor
        X = np.empty_like(B)
        X[:nf3] = self.factor(B[:nf3])
        X[nf3:] = B[nf3:]  # identity padding of added DOFs
        for U, Q, rows in self.terms:
            X[: U.shape[0]] -= U @ (Q @ X[rows])
        return X

    def _apply(self, mod: Modification) -> None:
        new = mod.created[self._lookup_or_missing(mod.created)]
        if len(new):
            Rn = mod.R[np.searchsorted(mod.uids, new)]
            self._grow(new, Rn)  # their reference rotation: the one at creation (D = I now)
        idx = self._ext_index(mod.uids)
        k = len(idx)
        N = perturbation(mod, self.R_ref[idx], new, self.rotate)
        if not self.enabled:
            return
        t0 = time.perf_counter()
        n3 = 3 * len(self.ext_uids)
        rows = node_dofs(idx)
        G = np.zeros((n3, 3 * k))
        G[rows, np.arange(3 * k)] = 1.0
        U = self._solve_ext(G)  # eq. (6): all columns in one batched triangular solve
        t1 = time.perf_counter()
        Q = woodbury_q(N, U[rows])
        self.terms.append((U, Q, rows))
        self.columns = sum(u.shape[1] for u, _, _ in self.terms)
        self.u_ms += 1000.0 * (t1 - t0)
        self.q_ms += 1000.0 * (time.perf_counter() - t1)

    def _lookup_or_missing(self, uids: np.ndarray) -> np.ndarray:
        """Mask of the uids not yet in the extended space."""
        uids = np.asarray(uids, np.int64)
        if not len(uids):
            return np.zeros(0, bool)
        out = np.ones(len(uids), bool)
        inside = uids < len(self._lookup)
        out[inside] = self._lookup[uids[inside]] < 0
        if np.any(~inside):
            self._lookup = np.concatenate([self._lookup, np.full(int(uids.max()) + 1 - len(self._lookup), -1, np.int64)])
        return out

    # ----------------------------------------------------------- application
    def prepare(self, R_current: np.ndarray | None) -> None:
        """Per step: the rotations D = R(t) R_ref^T of the extended nodes (identity where vanished);
        ``None`` when the preconditioner is not rotated."""
        if R_current is None:
            self.dR = None
            return
        n_ext = len(self.ext_uids)
        dR = np.tile(np.eye(3), (n_ext, 1, 1))
        idx = self.cur_to_ext if self.cur_to_ext is not None else np.arange(n_ext)
        dR[idx] = np.matmul(np.asarray(R_current, dtype=np.float64), np.swapaxes(self.R_ref[idx], 1, 2))
        self.dR = dR

    def apply(self, r: np.ndarray, out: np.ndarray) -> None:
        """out = D (P_ext^-1 - sum U Q U^T) D^T r, in the current numbering (eq. 8-10)."""
        self.apply_columns(r.reshape(-1, 1), out.reshape(-1, 1))

    def _to_ext(self, B: np.ndarray) -> np.ndarray:
        """D^T B in the extended numbering (3 n_ext, c): current rows scattered, vanished ones 0."""
        n_ext = len(self.ext_uids)
        c = B.shape[1]
        if self.cur_to_ext is None:
            Be = B.reshape(n_ext, 3, c).copy()
        else:
            Be = np.zeros((n_ext, 3, c))
            Be[self.cur_to_ext] = B.reshape(-1, 3, c)
        Be = Be.reshape(3 * n_ext, c)
        return Be if self.dR is None else rotate_nodes(self.dR, Be, transpose=True)

    def apply_columns(self, B: np.ndarray, out: np.ndarray) -> None:
        n_ext = len(self.ext_uids)
        c = B.shape[1]
        X = self._solve_ext(self._to_ext(B))
        if self.dR is not None:
            X = rotate_nodes(self.dR, X)
        X = X.reshape(n_ext, 3, c)
        out[:] = (X if self.cur_to_ext is None else X[self.cur_to_ext]).reshape(-1, c)

    def delassus(self, B, lower) -> np.ndarray:
        """B^T P~^-1 B for constraint columns B (3n, c; dense or sparse) in the current numbering
        (eq. 11-12): W^a from the factor's forward solves (``lower``: a :class:`soft_tissue_sim.
        delassus.LowerFactor` of the installed factor), plus the identity padding of added DOFs
        (eq. 12), minus the corrections W^c = sum (U^T B)^T Q (U^T B), the rotations around all
        (eq. 8). B stays sparse: a constraint column touches a few DOFs."""
        Be = self._to_ext_sparse(B)
        nf3 = 3 * self.n_factor
        c = Be.shape[1]
        inside = Be.row < nf3
        W = lower.quadratic(sps.coo_matrix((Be.data[inside], (Be.row[inside], Be.col[inside])), shape=(nf3, c)))
        Ba = sps.csr_matrix((Be.data[~inside], (Be.col[~inside], Be.row[~inside] - nf3)), shape=(c, Be.shape[0] - nf3))
        W += (Ba @ Ba.T).toarray()
        with one_thread():
            for U, Q, _ in self.terms:
                m = Be.row < U.shape[0]  # U's rows: the DOFs of its time, later ones are zero
                Vt = sps.csr_matrix((Be.data[m], (Be.col[m], Be.row[m])), shape=(c, U.shape[0])) @ U  # (U^T B)^T
                W -= Vt @ (Q @ Vt.T)
        return 0.5 * (W + W.T)

    def _to_ext_sparse(self, B) -> sps.coo_matrix:
        """D^T B in the extended numbering (3 n_ext, c), sparse: what :meth:`_to_ext` does for
        a dense block, on the node blocks B touches only."""
        from .delassus import rotate_columns

        n_cur = len(self.ext_uids) if self.cur_to_ext is None else len(self.cur_to_ext)
        if B.shape[0] != 3 * n_cur:
            raise ValueError(f"the corrected preconditioner is for {3 * n_cur} DOFs, got a block of {B.shape[0]} rows")
        return rotate_columns(B, self.dR, self.cur_to_ext, len(self.ext_uids))

    def perturbation_nodes(self) -> int:
        """Nodes of the perturbation N = G^T (P~ - P) G against the factor in use (eq. 5): every
        node changed by a modification the factor does not contain yet ("the nodes affected
        since the last two updates", sec. 3.2). This is the paper's "affected nodes" (table of
        fig. 3, 24 in the brain resection); our chained terms each carry only their own
        modification's nodes, a subset of these."""
        if not self.mods:
            return 0
        return int(len(np.unique(np.concatenate([m.uids for m in self.mods]))))

    def stats(self) -> dict:
        s = {"smf_terms": len(self.terms), "smf_columns": int(sum(u.shape[1] for u, _, _ in self.terms)),
             "pending_modifications": len(self.mods)}
        return s
