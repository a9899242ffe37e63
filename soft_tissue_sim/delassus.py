"""The Delassus operator W = H P^-1 H^T from the LDL^T factor (paper eq. 4, 11-12).

CHOLMOD factors the permuted matrix, P A P^T = L D L^T (P: ``f.P()``, L unit lower
triangular), so for a block of constraint columns B = H^T (already rotated into the
factor's frame, eq. 2)

    B^T A^-1 B = (L^-1 P B)^T D^-1 (L^-1 P B) = Z^T Z,      Z = D^-1/2 L^-1 P B.

Only the forward solve is needed, not the backward one: half the work of the m full solves
of P^-1 H^T. And a contact column has at most 12 non-zeros (one to four nodes, three DOFs
each), so its forward solve only touches the rows on the paths from those rows to the root
of the elimination tree (its reach; L_ij != 0, i > j, makes i an ancestor of j). The block is
solved on the union R of its columns' reaches alone, compacted: Z is dense (|R|, c) and the
rows outside R are zero. B stays sparse until then.

The solve goes up R by supernodes (columns of L that share their pattern below, found once
per factor). Near the root they are large and dense (the separators: most of the work), and
BLAS solves them for all columns at once, a triangular solve and a product for the rows
below. The small ones, near the leaves, go to a Warp kernel that follows each group of
columns' own reach. W = Z^T Z is summed segment by segment (symmetric products), each on the
range of columns not zero there. All of it on one BLAS thread (:mod:`soft_tissue_sim.
blas_threads`), beside the background factorization.

Why not CHOLMOD's solves: it solves a sparse right-hand side by its reach only for a single
column (``cholmod_solve2`` with ``Bset``), which scikit-sparse 0.4 does not expose; its
solves of a block (``solve_L``, dense or sparse) walk all n rows of the simplicial factor,
and scipy's ``spsolve_triangular`` takes dense right-hand sides. On a GPU the dense backend
gathers W from its inverse instead (:mod:`soft_tissue_sim.dense_inverse`).

The displacement correction dx = P^-1 H^T lambda needs one full solve, of one column.

A block of many columns solved in full (the Sherman-Morrison columns U = A^-1 G of a cut,
eq. 6, one column per DOF of its nodes) takes the same way up, D^-1, then the backward solve
L^-T down all n rows by the same supernodes: BLAS for the large ones (a product with the rows
above them, then a triangular solve), :func:`backward_kernel` for the columns between them,
GROUP right-hand sides a thread (:meth:`LowerFactor.solve_block`). CHOLMOD's simplicial solve
takes a block one column after the other.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sps
from scipy.linalg.blas import dtrsm
import warp as wp

from .blas_threads import one_thread

wp.set_module_options({"enable_backward": False})  # no gradients are taken

_HOST = "cpu"
GROUP = 16  # columns solved together by one thread: L's entries are read once per group
vec_group = wp.types.vector(length=GROUP, dtype=wp.float64)


@wp.kernel
def reach_kernel(parent: wp.array(dtype=wp.int32), rows: wp.array(dtype=wp.int32),
                 pos: wp.array(dtype=wp.int32), reach: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32)):
    """One thread. The union of the reaches of ``rows`` (permuted numbering) in the elimination
    tree ``parent`` (-1 at a root): ``reach[:count[0]]`` in increasing order (a topological
    order: a parent comes after its children) and ``pos[j]`` its place there, -1 outside.
    ``pos`` comes in all -1."""
    for k in range(rows.shape[0]):
        j = rows[k]
        while j >= 0:
            if pos[j] != -1:
                break
            pos[j] = 0  # marked; a path already marked leads to the root marked too
            j = parent[j]
    r = int(0)
    for j in range(pos.shape[0]):
        if pos[j] != -1:
            pos[j] = r
            reach[r] = j
            r += 1
    count[0] = r


@wp.kernel
def forward_reach_kernel(
    Lp: wp.array(dtype=wp.int32),
    Li: wp.array(dtype=wp.int32),
    Lx: wp.array(dtype=wp.float64),
    last: wp.array(dtype=wp.int32),
    reach: wp.array(dtype=wp.int32),
    pos: wp.array(dtype=wp.int32),
    first: wp.array(dtype=wp.int32),
    scale: wp.array(dtype=wp.float64),
    begin: wp.int32,
    end: wp.int32,
    Y: wp.array2d(dtype=vec_group),
):
    """Y[:, g] <- diag(scale) L_RR^-1 Y[:, g] for each group g of GROUP columns: row k of Y is
    row reach[k] of the permuted block, L unit lower triangular, strictly lower part in CSC
    (Lp, Li, Lx) in the permuted numbering, ``pos`` its rows' places in the reach; only the
    columns at rows begin..end-1 of Y (whole supernodes), their updates reaching any row below.

    By supernodes: columns j..last[j] of L share their pattern below (column j holds rows
    j+1..last[j], then the same rows as column last[j]), so a row q of column j takes the
    updates of all the supernode's columns at once, accumulated in registers (row q of
    column j + t is entry q - t of that column): each row of Y is read and written once per
    supernode, not once per column. Rows before ``first[g]`` are zero and stay zero; a zero
    row of the group starts nothing (the work is that of the group's reaches). Rows are
    scaled once final, after their use."""
    g = wp.tid()
    k = wp.max(first[g], begin)
    while k < end:
        yk = Y[k, g]
        if wp.dot(yk, yk) == wp.float64(0.0):
            k += 1
            continue
        j = reach[k]
        s = last[j] - j + 1  # columns j..last[j]: rows k..k+s-1 of Y
        p0 = Lp[j]
        for q in range(Lp[j + 1] - p0):
            i = pos[Li[p0 + q]]
            acc = Y[i, g]
            for t in range(wp.min(q + 1, s)):
                acc = acc - Lx[Lp[j + t] + q - t] * Y[k + t, g]
            Y[i, g] = acc
        for t in range(s):
            Y[k + t, g] = scale[k + t] * Y[k + t, g]
        k += s


@wp.kernel
def backward_kernel(Lp: wp.array(dtype=wp.int32), Li: wp.array(dtype=wp.int32), Lx: wp.array(dtype=wp.float64),
                    begin: wp.int32, end: wp.int32, X: wp.array2d(dtype=vec_group)):
    """X[:, g] <- L^-T X[:, g] on rows end-1 down to begin, for each group g of GROUP columns
    (rows from end on final): row j takes column j's entries of the strict L (CSC, permuted
    numbering) times the final rows they name, L unit lower triangular."""
    g = wp.tid()
    j = end - 1
    while j >= begin:
        acc = X[j, g]
        for p in range(Lp[j], Lp[j + 1]):
            acc = acc - Lx[p] * X[Li[p], g]
        X[j, g] = acc
        j -= 1


SNODE_BLAS = 24  # supernodes of at least this many columns are solved by BLAS, all columns at once


@dataclass
class Supernode:
    """A supernode of L solved densely: columns j0..j0+s-1 (permuted numbering) and ``rows``
    (m,), the rows below them (the same for all). ``block`` (s, s + m) holds column j0 + t of
    L in row t: its unit diagonal at t, then its entries (rows j0+t+1..j0+s-1, then
    ``rows``); zeros before. So block[:, :s] is the transpose of the unit lower triangle and
    block[:, s:] that of the rows below."""

    j0: int
    block: np.ndarray
    rows: np.ndarray

    @property
    def size(self) -> int:
        return self.block.shape[0]


@dataclass
class LowerFactor:
    """The host factor as the forward solves need it: permutation, strictly lower L (CSC, as
    Warp arrays on the CPU), its elimination tree and supernodes, and 1 / D."""

    perm: np.ndarray  # permuted row i -> original DOF perm[i]
    Lp: wp.array
    Li: wp.array
    Lx: wp.array
    dinv: np.ndarray
    parent: wp.array  # elimination tree: the first row of column j of the strict L, -1 at a root
    last: wp.array  # the last column of j's supernode (j..last[j] share their pattern below)
    snodes: list  # the supernodes of at least SNODE_BLAS columns (Supernode), in column order

    def __post_init__(self):
        self.iperm = np.empty_like(self.perm)
        self.iperm[self.perm] = np.arange(len(self.perm))  # original DOF -> permuted row
        # Z = D^-1/2 Y where D > 0 (A positive definite); else Y and the signed D^-1 in the product
        self.sqrt_dinv = np.sqrt(self.dinv) if np.all(self.dinv > 0.0) else None
        self.snode_last = np.array([sn.j0 + sn.size - 1 for sn in self.snodes], np.int64)

    @property
    def n(self) -> int:
        return len(self.perm)

    @classmethod
    def from_cholmod(cls, factor) -> "LowerFactor":
        """From a scikit-sparse Factor (a supernodal one is turned into a simplicial LDL^T by
        CHOLMOD, in place: its solves keep working). CHOLMOD stores each column's diagonal
        first, the rows sorted: the strictly lower part is each column without its first
        entry, and its next entry is the column's parent in the elimination tree."""
        LD = factor.LD()
        LD.sort_indices()  # CHOLMOD's simplicial LD is sorted already: then this does nothing
        n = LD.shape[0]
        ip = LD.indptr.astype(np.int64)
        keep = np.ones(LD.nnz, bool)
        keep[ip[:-1]] = False
        count = np.diff(ip) - 1
        Lp = (ip - np.arange(n + 1)).astype(np.int32)
        Li = np.ascontiguousarray(LD.indices[keep], dtype=np.int32)
        Lx = np.ascontiguousarray(LD.data[keep])
        parent = np.full(n, -1, np.int32)
        has = count > 0
        parent[has] = Li[Lp[:-1][has]]
        # fundamental supernodes: j + 1 continues j's when it is j's parent and has one entry less
        ends = np.flatnonzero(np.append((parent[:-1] != np.arange(1, n)) | (count[:-1] != count[1:] + 1), True))
        starts = np.concatenate([[0], ends[:-1] + 1])
        last = np.repeat(ends, ends - starts + 1).astype(np.int32)
        snodes = cls._supernodes(Lp, Li, Lx, starts, ends)
        host = dict(device=_HOST, copy=False)  # Warp uses these new arrays in place
        return cls(np.asarray(factor.P(), np.int64), wp.array(Lp, dtype=wp.int32, **host),
                   wp.array(Li, dtype=wp.int32, **host), wp.array(Lx, dtype=wp.float64, **host),
                   1.0 / LD.data[ip[:-1]], wp.array(parent, dtype=wp.int32, **host),
                   wp.array(last, dtype=wp.int32, **host), snodes)

    @staticmethod
    def _supernodes(Lp, Li, Lx, starts, ends) -> list:
        """The supernodes of columns starts[i]..ends[i] of at least SNODE_BLAS columns and their
        blocks (:class:`Supernode`). Row t of a block from place t + 1 on is column a + t's
        entries, so the strict upper part of the block, read row by row, is the supernode's
        entries of L as CHOLMOD stores them (its columns one after the other)."""
        out = []
        for a, e in zip(starts, ends):
            s = int(e - a + 1)
            if s < SNODE_BLAS:
                continue
            width = s + int(Lp[e + 1] - Lp[e])
            block = np.zeros((s, width))
            block[~np.tri(s, width, 0, dtype=bool)] = Lx[Lp[a]:Lp[e + 1]]
            block[np.arange(s), np.arange(s)] = 1.0
            out.append(Supernode(int(a), block, Li[Lp[e]:Lp[e + 1]].astype(np.int64)))
        return out

    def _solve_reach(self, B, gram: bool):
        """Forward solves of the columns of B (n, c; dense or sparse, original numbering) on
        the union R of their reaches: (Y (|R|, groups * GROUP), reach (|R|,) permuted rows,
        slot (c,), G), column k of B being column slot[k] of Y. Without ``gram``: Y = L^-1 P B
        and G None. With it: G = Y^T D^-1 Y (groups * GROUP square), and Y = D^-1/2 L^-1 P B
        where D > 0 (else unscaled).

        R is walked in order, by segments: a large supernode by BLAS (a triangular solve of its
        rows, then a product updating the rows below it), the rows between two of them by the
        kernel, whose columns are grouped GROUP at a time in the order of their first row in
        R: columns that start close share most of their way to the root (for contacts: the
        nodes under one instrument), so a segment's non-zero columns are mostly one range.
        The BLAS calls and G's products take each segment's range of non-zero columns only;
        G is summed over the segments, each as soon as its rows are final."""
        if sps.issparse(B):
            coo = B.tocoo()
            entries, col, data = coo.row, coo.col, coo.data.astype(np.float64, copy=False)
        else:
            B = np.asarray(B, dtype=np.float64)
            if B.ndim != 2:
                raise ValueError(f"factor is for {self.n} DOFs, got a block of shape {B.shape}")
            entries, col = np.nonzero(B)
            data = B[entries, col]
        if B.shape[0] != self.n:
            raise ValueError(f"factor is for {self.n} DOFs, got a block of shape {B.shape}")
        n, c = B.shape
        groups = -(-c // GROUP)
        nz = data != 0.0
        data, col = data[nz], col[nz]
        rows = self.iperm[entries[nz]].astype(np.int32)
        pos = np.full(n, -1, np.int32)
        reach = np.empty(n, np.int32)
        count = np.zeros(1, np.int32)
        host = dict(device=_HOST, copy=False)
        wp.launch(reach_kernel, 1, [self.parent, wp.array(rows, dtype=wp.int32, **host),
                                    wp.array(pos, dtype=wp.int32, **host), wp.array(reach, dtype=wp.int32, **host),
                                    wp.array(count, dtype=wp.int32, **host)], device=_HOST)
        r = int(count[0])
        reach = reach[:r]
        at = pos[rows]  # the entries' rows in the reach
        first = np.full(c, r, np.int64)
        np.minimum.at(first, col, at)
        order = np.argsort(first, kind="stable")
        slot = np.empty(c, np.int64)
        slot[order] = np.arange(c)
        Y = np.zeros((r, groups * GROUP))
        G = np.zeros((groups * GROUP, groups * GROUP)) if gram else None
        if r == 0:
            return Y, reach, slot, G
        np.add.at(Y, (at, slot[col]), data)
        first_g = np.full(groups * GROUP, r, np.int64)
        first_g[slot] = first
        first_g = first_g.reshape(groups, GROUP).min(axis=1).astype(np.int32)
        scaled = gram and self.sqrt_dinv is not None
        scale = self.sqrt_dinv[reach] if scaled else np.ones(r)
        dinv = None if scaled or not gram else self.dinv[reach]
        solve = wp.launch(forward_reach_kernel, groups,
                          [self.Lp, self.Li, self.Lx, self.last, wp.array(reach, dtype=wp.int32, **host),
                           wp.array(pos, dtype=wp.int32, **host), wp.array(first_g, dtype=wp.int32, **host),
                           wp.array(scale, dtype=wp.float64, **host), 0, r,
                           wp.array(Y.reshape(r, groups, GROUP), dtype=vec_group, **host)],
                          device=_HOST, record_cmd=True)

        def kernel(k0, k1):
            solve.set_param_at_index_from_ctype(8, k0)
            solve.set_param_at_index_from_ctype(9, k1)
            solve.launch()
            product(k0, k1)

        def product(k0, k1):  # G += Z^T Z on the final rows k0..k1-1, their non-zero columns
            if gram:
                lo, hi = _nonzero_columns(Y[k0:k1])
                Z = Y[k0:k1, lo:hi]
                G[lo:hi, lo:hi] += Z.T @ Z if dinv is None else Z.T @ (Z * dinv[k0:k1, None])  # syrk, not gemm

        done = 0
        for b in np.flatnonzero(pos[self.snode_last] >= 0):  # the large supernodes in R, in order
            sn = self.snodes[b]
            inside = pos[sn.j0:self.snode_last[b] + 1]
            a = int(np.argmax(inside >= 0))  # R holds the supernode's columns from j0 + a on
            k0, k1 = int(inside[a]), int(inside[-1]) + 1
            if k0 > done:
                kernel(done, k0)
            lo, hi = _nonzero_columns(Y[k0:k1])  # the other columns stay zero here and below
            Ys = Y[k0:k1, lo:hi]
            # Ys <- T^-1 Ys, as Ys^T <- Ys^T T^-T on its transpose (Fortran order); T^T is C-ordered
            s = sn.size
            Ys[:] = dtrsm(1.0, sn.block[a:, a:s].T, Ys.T, side=1, lower=1, trans_a=1, diag=1).T
            if len(sn.rows):
                Y[pos[sn.rows], lo:hi] -= sn.block[a:, s:].T @ Ys
            Y[k0:k1] *= scale[k0:k1, None]
            product(k0, k1)
            done = k1
        if done < r:
            kernel(done, r)
        return Y, reach, slot, G

    def forward(self, B) -> np.ndarray:
        """Y^T = (L^-1 P B)^T, (c, n), for B (n, c) in the original numbering."""
        with one_thread():
            Y, reach, slot, _ = self._solve_reach(B, gram=False)
        out = np.zeros((B.shape[1], self.n))
        out[:, reach] = Y[:, slot].T
        return out

    def solve_block(self, B) -> np.ndarray:
        """A^-1 B (n, c) for B (n, c) dense or sparse, original numbering: Y = L^-1 P B on the
        union of the columns' reaches (:meth:`_solve_reach`), then D^-1 Y and the backward
        solve L^-T on all rows, from the last: a large supernode by BLAS (its rows take the
        product of its rows below with the final rows there, then the triangular solve), the
        columns between two of them by :func:`backward_kernel`."""
        n, c = B.shape
        if n != self.n:
            raise ValueError(f"factor is for {self.n} DOFs, got a block of shape {B.shape}")
        if c == 0:
            return np.zeros((n, 0))
        groups = -(-c // GROUP)
        with one_thread():
            Y, reach, slot, _ = self._solve_reach(B, gram=False)
            Z = np.zeros((n, groups * GROUP))
            Z[reach[:, None], np.arange(c)] = Y[:, slot] * self.dinv[reach, None]
            Zw = wp.array(Z.reshape(n, groups, GROUP), dtype=vec_group, device=_HOST, copy=False)
            done = n  # rows from here on are final
            for sn in reversed(self.snodes):
                s = sn.size
                k0, k1 = sn.j0, sn.j0 + s
                if k1 < done:
                    wp.launch(backward_kernel, groups, [self.Lp, self.Li, self.Lx, k1, done, Zw], device=_HOST)
                Zs = Z[k0:k1, :c]
                if len(sn.rows):
                    Zs -= sn.block[:, s:] @ Z[sn.rows, :c]
                Zs[:] = dtrsm(1.0, sn.block[:, :s], Zs, side=0, lower=0, trans_a=0, diag=1)  # T^T: upper, unit
                done = k0
            if done > 0:
                wp.launch(backward_kernel, groups, [self.Lp, self.Li, self.Lx, 0, done, Zw], device=_HOST)
        X = np.empty((n, c))
        X[self.perm] = Z[:, :c]
        return X

    def quadratic(self, B) -> np.ndarray:
        """B^T A^-1 B (c, c), symmetric, for B (n, c) dense or sparse: Y^T D^-1 Y, Y = L^-1 P B
        on the union of the columns' reaches, from the forward solves alone."""
        with one_thread():
            _, _, slot, G = self._solve_reach(B, gram=True)
        W = G[np.ix_(slot, slot)]
        return 0.5 * (W + W.T)


def _nonzero_columns(Z: np.ndarray) -> tuple[int, int]:
    """The range lo..hi-1 of the columns of Z that holds all its non-zero ones (0, 0: none)."""
    nonzero = np.flatnonzero(Z.any(axis=0))
    return (int(nonzero[0]), int(nonzero[-1]) + 1) if len(nonzero) else (0, 0)

def rotate_columns(B, dR=None, nodes=None, n_nodes=None) -> sps.coo_matrix:
    """Sparse constraint columns B (3n, c; dense or sparse) node by node into a factor's frame:
    the block of node i of each column goes to node m = ``nodes[i]`` (i without ``nodes``) and
    becomes dR[m]^T b (the rotations of eq. 2, 8; none without ``dR``). Returns (3 n_nodes, c)
    COO, ``n_nodes`` defaulting to n; only the node blocks that B touches are formed."""
    coo = sps.coo_matrix(B)
    c = coo.shape[1]
    node = coo.row.astype(np.int64) // 3
    if nodes is not None:
        node = np.asarray(nodes, np.int64)[node]
    n_nodes = coo.shape[0] // 3 if n_nodes is None else int(n_nodes)
    blocks, inv = np.unique(node * c + coo.col, return_inverse=True)  # the (node, column) blocks touched
    V = np.zeros((len(blocks), 3))
    np.add.at(V, (inv, coo.row % 3), coo.data)
    nd, cl = blocks // c, blocks % c
    if dR is not None:
        V = np.matmul(np.swapaxes(dR[nd], 1, 2), V[:, :, None])[:, :, 0]
    rows = (3 * nd[:, None] + np.arange(3)).ravel()
    return sps.coo_matrix((V.ravel(), (rows, np.repeat(cl, 3))), shape=(3 * n_nodes, c))
