"""The Delassus operator W = H P^-1 H^T from the LDL^T factor (paper eq. 4, 11-12).

CHOLMOD factors the permuted matrix, P A P^T = L D L^T (P: ``f.P()``, L unit lower
triangular), so for a block of constraint columns B = H^T (already rotated into the
factor's frame, eq. 2)

    B^T A^-1 B = (L^-1 P B)^T D^-1 (L^-1 P B) = Y^T D^-1 Y,      Y = L^-1 P B.

Only the forward solve is needed, not the backward one: half the work of the m full solves
of P^-1 H^T. And a contact column has at most 12 non-zeros (one to four nodes, three DOFs
each), so its forward solve only ever touches the rows on the paths from those rows to the
root of the elimination tree (its reach): a column j of L contributes only when y_j != 0,
which is the test the kernel makes (docs/benchmarks.md has the measured gain).

Why our own kernel: CHOLMOD solves a sparse right-hand side by its reach only for a single
column (``cholmod_solve2`` with ``Bset``), which scikit-sparse 0.4 does not expose, and
scipy's ``spsolve_triangular`` takes dense right-hand sides. The kernel runs on Warp's CPU
backend next to the host factor (a thread per group of 16 columns). On a GPU the dense
backend gathers W from its inverse instead (:mod:`soft_tissue_sim.dense_inverse`).

The displacement correction dx = P^-1 H^T lambda needs one full solve, of one column.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

_HOST = "cpu"
GROUP = 16  # columns solved together by one thread: L's entries are read once per group
vec_group = wp.types.vector(length=GROUP, dtype=wp.float64)


@wp.kernel
def forward_columns_kernel(
    Lp: wp.array(dtype=wp.int32),
    Li: wp.array(dtype=wp.int32),
    Lx: wp.array(dtype=wp.float64),
    first: wp.array(dtype=wp.int32),
    Y: wp.array2d(dtype=vec_group),
):
    """Y[g] <- L^-1 Y[g] for each group g of GROUP columns (Y[g, j]: row j of the group's
    columns), L unit lower triangular, strictly lower part in CSC (Lp, Li, Lx). Rows before
    ``first[g]`` are zero and stay zero; a column j of L is used only where row j of the group
    is not zero, so the work is that of the union of the group's reaches, and each entry of L
    on it is read once for all the group's columns."""
    g = wp.tid()
    n = Y.shape[1]
    for j in range(first[g], n):
        yj = Y[g, j]
        if wp.dot(yj, yj) != wp.float64(0.0):
            for p in range(Lp[j], Lp[j + 1]):
                i = Li[p]
                Y[g, i] = Y[g, i] - Lx[p] * yj


@dataclass
class LowerFactor:
    """The host factor as the forward solves need it: permutation, strictly lower L (CSC, as
    Warp arrays on the CPU) and 1 / D."""

    perm: np.ndarray  # permuted row i -> original DOF perm[i]
    Lp: wp.array
    Li: wp.array
    Lx: wp.array
    dinv: np.ndarray

    @property
    def n(self) -> int:
        return len(self.perm)

    @classmethod
    def from_cholmod(cls, factor) -> "LowerFactor":
        """From a scikit-sparse Factor (a supernodal one is turned into a simplicial LDL^T by
        CHOLMOD, in place: its solves keep working). CHOLMOD stores each column's diagonal
        first: the strictly lower part is each column without its first entry."""
        LD = factor.LD()
        n = LD.shape[0]
        ip = LD.indptr.astype(np.int64)
        keep = np.ones(LD.nnz, bool)
        keep[ip[:-1]] = False
        host = dict(device=_HOST, copy=False)  # Warp uses these new arrays in place
        return cls(np.asarray(factor.P(), np.int64),
                   wp.array((ip - np.arange(n + 1)).astype(np.int32), dtype=wp.int32, **host),
                   wp.array(np.ascontiguousarray(LD.indices[keep], dtype=np.int32), dtype=wp.int32, **host),
                   wp.array(np.ascontiguousarray(LD.data[keep]), dtype=wp.float64, **host),
                   1.0 / LD.data[ip[:-1]])

    def _solve_groups(self, B: np.ndarray):
        """Forward solves of the columns of B (n, c), original numbering, in the kernel's layout:
        (Yg (groups, n, GROUP), slot (c,)), column k of B being lane slot[k] % GROUP of group
        slot[k] // GROUP.

        Columns are grouped GROUP at a time in the order of their first non-zero row: columns
        that start close in the elimination order share most of their way to the root (for
        contacts: the nodes under one instrument). The block is written once into the group
        layout, which Warp then uses in place (no copy on the CPU)."""
        B = np.asarray(B, dtype=np.float64)
        if B.ndim != 2 or B.shape[0] != self.n:
            raise ValueError(f"factor is for {self.n} DOFs, got a block of shape {B.shape}")
        n, c = B.shape
        groups = -(-c // GROUP)
        Yg = np.zeros((groups, n, GROUP))
        slot = np.zeros(c, np.int64)
        if c == 0:
            return Yg, slot
        Pb = B[self.perm]
        nz = Pb != 0.0
        first = np.where(nz.any(axis=0), nz.argmax(axis=0), n)
        order = np.argsort(first, kind="stable")
        slot[order] = np.arange(c)
        Yg[slot // GROUP, :, slot % GROUP] = Pb.T
        first_g = np.full(groups * GROUP, n, np.int64)
        first_g[slot] = first
        first_g = first_g.reshape(groups, GROUP).min(axis=1).astype(np.int32)
        wp.launch(forward_columns_kernel, groups,
                  [self.Lp, self.Li, self.Lx, wp.array(first_g, dtype=wp.int32, device=_HOST),
                   wp.array(Yg, dtype=vec_group, device=_HOST, copy=False)], device=_HOST)
        return Yg, slot

    def forward(self, B: np.ndarray) -> np.ndarray:
        """Y^T = (L^-1 P B)^T, (c, n), for B (n, c) in the original numbering."""
        Yg, slot = self._solve_groups(B)
        return Yg[slot // GROUP, :, slot % GROUP]

    def quadratic(self, B: np.ndarray) -> np.ndarray:
        """B^T A^-1 B = Y^T D^-1 Y (c, c), symmetric, from the forward solves alone, summed over
        the rows the columns' reaches touch."""
        Yg, slot = self._solve_groups(B)
        used = np.flatnonzero(np.any(Yg != 0.0, axis=(0, 2)))
        Z = Yg[:, used, :].transpose(1, 0, 2).reshape(len(used), Yg.shape[0] * GROUP)  # rows j, all lanes
        W = Z.T @ (Z * self.dinv[used, None])
        W = W[np.ix_(slot, slot)]
        return 0.5 * (W + W.T)
