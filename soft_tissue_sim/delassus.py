"""The Delassus operator W = H P^-1 H^T from the LDL^T factor (paper eq. 4, 11-12).

CHOLMOD factors the permuted matrix, P A P^T = L D L^T (P: ``f.P()``, L unit lower
triangular), so for a block of constraint columns B = H^T (already rotated into the
factor's frame, eq. 2)

    B^T A^-1 B = (L^-1 P B)^T D^-1 (L^-1 P B) = Y^T D^-1 Y,      Y = L^-1 P B.

Only the forward solve is needed, not the backward one: half the work of the m full solves
of P^-1 H^T. And a contact column has at most 12 non-zeros (one to four nodes, three DOFs
each), so its forward solve only ever touches the rows on the paths from those rows to the
root of the elimination tree (its reach): a column j of L contributes only when y_j != 0,
which is the test the kernel makes. On the brain (5,202 DOFs) a contact column reaches 6-10
times fewer entries of L than the whole factor, so W costs a fraction of what CHOLMOD's
dense-right-hand-side solves cost (``bench contact``).

Why our own kernel: CHOLMOD solves a sparse right-hand side by its reach only for a single
column (``cholmod_solve2`` with ``Bset``), which scikit-sparse 0.4 does not expose, and
scipy's ``spsolve_triangular`` takes dense right-hand sides. The kernel runs on Warp's CPU
backend next to the host factor (a thread per column): the factor lives on the host, and a
column's solve is a sequential walk up the tree, a poor fit for a GPU thread (the device
path for blocks of columns is :meth:`soft_tissue_sim.ldlt_device.DeviceLDLT.solve_columns`).

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
        d = LD.data[ip[:-1]]
        keep = np.ones(LD.nnz, bool)
        keep[ip[:-1]] = False
        Lp = (ip - np.arange(n + 1)).astype(np.int32)
        Li = np.ascontiguousarray(LD.indices[keep], dtype=np.int32)
        Lx = np.ascontiguousarray(LD.data[keep], dtype=np.float64)
        return cls(np.asarray(factor.P(), np.int64), wp.array(Lp, dtype=wp.int32, device=_HOST),
                   wp.array(Li, dtype=wp.int32, device=_HOST), wp.array(Lx, dtype=wp.float64, device=_HOST),
                   1.0 / d)

    def forward(self, B: np.ndarray) -> np.ndarray:
        """Y^T = (L^-1 P B)^T, (c, n), for B (n, c) in the original numbering.

        Columns are grouped GROUP at a time in the order of their first non-zero row: columns
        that start close in the elimination order share most of their way to the root (for
        contacts: the nodes under one instrument)."""
        B = np.asarray(B, dtype=np.float64)
        if B.ndim != 2 or B.shape[0] != self.n:
            raise ValueError(f"factor is for {self.n} DOFs, got a block of shape {B.shape}")
        n, c = B.shape
        Yt = B[self.perm].T
        if c == 0:
            return np.ascontiguousarray(Yt)
        nz = Yt != 0.0
        first = np.where(nz.any(axis=1), nz.argmax(axis=1), n)
        order = np.argsort(first, kind="stable")
        groups = -(-c // GROUP)
        Yg = np.zeros((groups * GROUP, n))
        Yg[:c] = Yt[order]
        first_g = np.full(groups * GROUP, n, np.int64)
        first_g[:c] = first[order]
        first_g = first_g.reshape(groups, GROUP).min(axis=1).astype(np.int32)
        Y_wp = wp.array(np.ascontiguousarray(Yg.reshape(groups, GROUP, n).transpose(0, 2, 1)), dtype=vec_group,
                        device=_HOST)
        wp.launch(forward_columns_kernel, groups,
                  [self.Lp, self.Li, self.Lx, wp.array(first_g, dtype=wp.int32, device=_HOST), Y_wp], device=_HOST)
        out = np.empty((c, n))
        out[order] = Y_wp.numpy().transpose(0, 2, 1).reshape(groups * GROUP, n)[:c]
        return out

    def quadratic(self, B: np.ndarray) -> np.ndarray:
        """B^T A^-1 B = Y^T D^-1 Y (c, c), symmetric, from the forward solves alone."""
        Yt = self.forward(B)
        used = np.flatnonzero(np.any(Yt != 0.0, axis=0))  # the union of the columns' reaches
        Yu = Yt[:, used]
        W = (Yu * self.dinv[used]) @ Yu.T
        return 0.5 * (W + W.T)
