"""The system matrix A of eq. (1) assembled on the host with NumPy, from a frozen state.

The asynchronous LDL^T preconditioner (eq. 2) factorizes A(t_u). What A(t_u) depends on is
small and cheap to copy: the element rotations R_e, the topology, the rest shape-function
gradients, the material, the fixed flags and the coefficients of eq. (1). The simulation
thread copies those (:class:`AssemblyState`, made by
:meth:`soft_tissue_sim.corotational_fem.CorotationalFEM.assembly_state`); the worker builds the
scipy CSC matrix from them (:meth:`AssemblyState.csc`) with NumPy only, no Warp launch, so
any thread or process may call it.

The element blocks (the formula of ``element_block`` in :mod:`corotational_fem`), with the
rotated gradients h_k = R_e g_k:

    A_ij += k_coef V (mu (g_i . g_j) I + mu h_j h_i^T + lam h_i h_j^T) + mass_ij I,
    mass_ij = m_coef rho V (1 + d_ij) / 20 (consistent)  or  m_coef rho V d_ij / 4 (lumped),

each multiplied by free_i free_j (fixed nodes filtered out), and the identity on the diagonal
block of each fixed node. Element block (j, i) is block (i, j) transposed, so only the entries
a <= b of each block are computed; entry (b, a) of block (I, J) is entry (a, b) of block (J, I).

The pattern holds every 3x3 block between two free nodes of one element and every diagonal
block of a free node, in full, and the three diagonal entries of a fixed node: the pattern of
the Warp assembly less the stored zeros that couple the decoupled rows of fixed nodes (what
:func:`soft_tissue_sim.ldlt_preconditioner._drop_decoupled` removes). It depends on the
topology and the fixed nodes alone, so it is found once for them (:class:`ScatterMap`: the CSC
pattern, the block of each element pair, where each block entry lands) and kept in a small
cache; each assembly is then, for each entry (a, b), the element entries and one ``bincount``
that sums them per block, and one scatter into the CSC data.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sps


def _unique_pairs(rows: np.ndarray, cols: np.ndarray, n: int):
    """The distinct keys col * n + row, sorted, and the index of each pair's among them
    (``np.unique(keys, return_inverse=True)``); below 2^16 nodes by two stable radix sorts."""
    keys = cols * n + rows
    if n >= 1 << 16:
        return np.unique(keys, return_inverse=True)
    by_row = np.argsort(rows.astype(np.uint16), kind="stable")
    order = by_row[np.argsort(cols[by_row].astype(np.uint16), kind="stable")]
    ks = keys[order]
    first = np.empty(len(ks), dtype=bool)
    first[:1] = True
    np.not_equal(ks[1:], ks[:-1], out=first[1:])
    inv = np.empty(len(ks), dtype=np.int64)
    inv[order] = np.cumsum(first) - 1
    return ks[first], inv


UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))  # the entries (a, b), a <= b, of a 3x3 block


@dataclass
class ScatterMap:
    """The CSC pattern of A for one topology (n nodes, tets (m, 4), the fixed nodes) and how the
    element entries reach its data. Blocks are numbered in CSC order (by column J, then row I);
    number ``nblocks`` is a sink for the element pairs outside the pattern (a fixed node)."""

    n: int
    tets: np.ndarray
    fixed: np.ndarray  # (n,) bool
    indptr: np.ndarray
    indices: np.ndarray
    pair_block: np.ndarray  # (16 m,): the block of element pair (i, j, e), in that order
    transpose: np.ndarray  # (nblocks + 1,): the block (J, I) of block (I, J); the sink's is the sink
    diag: np.ndarray  # (n,): the block (i, i)
    place: np.ndarray  # (9, nblocks + 1): where entry (a, b) of each block lands in the data; nnz: nowhere

    @property
    def nblocks(self) -> int:
        return len(self.transpose) - 1

    @classmethod
    def build(cls, n: int, tets: np.ndarray, fixed: np.ndarray) -> "ScatterMap":
        tets = np.array(tets, dtype=np.int64)
        fixed = np.array(fixed, dtype=bool)
        bi = np.concatenate([np.repeat(tets.T, 4, axis=0).ravel(), np.arange(n)])  # pairs (i, j, e), then (k, k)
        bj = np.concatenate([np.tile(tets.T, (4, 1)).ravel(), np.arange(n)])
        keep = (bi == bj) | ~(fixed[bi] | fixed[bj])
        blocks, inv = _unique_pairs(bi[keep], bj[keep], n)
        nb = len(blocks)
        block = np.full(len(bi), nb, dtype=np.int64)
        block[keep] = inv.ravel()
        col_b, row_b = np.divmod(blocks, n)
        transpose = np.append(np.searchsorted(blocks, row_b * n + col_b), nb)
        # CSC: column 3J + b holds entry (a, b) of the blocks of block column J in block order,
        # rows 3I + a: 3 count_J entries, at 3 rank + a; a fixed J has its diagonal entry alone
        count = np.bincount(col_b, minlength=n)
        free_col = ~fixed
        length = np.repeat(np.where(free_col, 3 * count, 1), 3)
        indptr = np.zeros(3 * n + 1, dtype=np.int64)
        np.cumsum(length, out=indptr[1:])
        nnz = int(indptr[-1])
        rank = np.arange(nb) - np.concatenate([[0], np.cumsum(count)])[col_b]
        a, b = np.divmod(np.arange(9), 3)
        place = indptr[3 * col_b[None, :] + b[:, None]] + np.where(free_col[col_b][None, :],
                                                                  3 * rank[None, :] + a[:, None], 0)
        place[(a != b)[:, None] & fixed[col_b][None, :]] = nnz  # a fixed node: its diagonal alone
        place = np.concatenate([place, np.full((9, 1), nnz)], axis=1)  # the sink
        indices = np.empty(nnz + 1, dtype=np.int32)
        indices[place[:, :nb]] = 3 * row_b[None, :] + a[:, None]
        return cls(n, tets, fixed, indptr.astype(np.int32), indices[:nnz], block[: 16 * len(tets)].astype(np.int32),
                   transpose, block[16 * len(tets):], place)

    def matches(self, n: int, tets: np.ndarray, fixed: np.ndarray) -> bool:
        return (n == self.n and tets.shape == self.tets.shape and np.array_equal(tets, self.tets)
                and np.array_equal(fixed, self.fixed))


_CACHE: list[ScatterMap] = []  # the most recently used first
_CACHE_SIZE = 2  # the topology in use and the one before it (a snapshot taken before a cut)
_CACHE_LOCK = threading.Lock()


def scatter_map(n: int, tets: np.ndarray, fixed: np.ndarray) -> ScatterMap:
    """The :class:`ScatterMap` of this topology and these fixed nodes, from the cache or built (and cached)."""
    with _CACHE_LOCK:
        for i, s in enumerate(_CACHE):
            if s.matches(n, tets, fixed):
                _CACHE.insert(0, _CACHE.pop(i))
                return s
    s = ScatterMap.build(n, tets, fixed)
    with _CACHE_LOCK:
        _CACHE.insert(0, s)
        del _CACHE[_CACHE_SIZE:]
    return s


@dataclass
class AssemblyState:
    """Host copies of what the filtered A = m_coef M + k_coef K depends on at one state.

    ``R``: element rotations (m, 3, 3); ``tets`` (m, 4); ``Dm_inv`` (m, 3, 3); ``volume``,
    ``mu``, ``lam``, ``rho`` (m,); ``free`` (n,), 1 on free nodes and 0 on fixed ones. The
    arrays are owned (copies): the simulation may go on while another thread assembles."""

    n: int
    tets: np.ndarray
    Dm_inv: np.ndarray
    volume: np.ndarray
    mu: np.ndarray
    lam: np.ndarray
    rho: np.ndarray
    free: np.ndarray
    R: np.ndarray
    m_coef: float
    k_coef: float
    consistent: bool

    def _gradients(self):
        """The rotated, filtered gradients h[a, k, e] = (R_e g_k w_k)_a, the filtered g[c, k, e] and
        w (4, m), element last (each operation runs along the m elements)."""
        w = self.free[self.tets].T  # (4, m): filtering the gradients filters their products
        g = np.empty((3, 4, len(self.tets)))
        g[:, 1:] = self.Dm_inv.transpose(2, 1, 0)
        g[:, 0] = -g[:, 1:].sum(axis=1)
        g *= w
        R = self.R.transpose(1, 2, 0)  # R[a, c, e]
        h = R[:, 0, None] * g[0] + R[:, 1, None] * g[1] + R[:, 2, None] * g[2]
        return h, g, w

    def block_sums(self, smap: ScatterMap) -> np.ndarray:
        """(9, nblocks + 1): entry (a, b) of every block of the pattern (the last: the sink).

        Entry (a, b), a <= b, of element block (i, j) is lam' h_i[a] h_j[b] + mu' h_j[a] h_i[b]
        (+ mu' g_i.g_j + mass_ij where a = b), lam' = k_coef V lam, mu' = k_coef V mu; one
        (4, 4, m) buffer at a time, summed per block by ``bincount``."""
        h, g, w = self._gradients()
        kv = self.k_coef * self.volume
        p, q = h * (kv * self.lam), h * (kv * self.mu)
        diag = (g[:, :, None] * g[:, None, :]).sum(axis=0)  # g_i . g_j, filtered, (4, 4, m)
        diag *= kv * self.mu
        mass = (1.0 + np.eye(4)) * (1.0 / 20.0) if self.consistent else np.eye(4) * 0.25
        diag += mass[:, :, None] * (self.m_coef * self.rho * self.volume) * (w[:, None] * w[None, :])
        nb = smap.nblocks
        sums = np.empty((9, nb + 1))
        vals, tmp = np.empty((2, 4, 4, len(self.tets)))
        for a, b in UPPER:
            np.multiply(h[a][:, None], p[b][None, :], out=vals)
            vals += np.multiply(h[a][None, :], q[b][:, None], out=tmp)
            if a == b:
                vals += diag
            sums[3 * a + b] = np.bincount(smap.pair_block, weights=vals.reshape(-1), minlength=nb + 1)
            if a != b:
                sums[3 * b + a] = sums[3 * a + b][smap.transpose]
        sums[::4, smap.diag] += 1.0 - self.free  # the identity on fixed nodes
        return sums

    def csc(self) -> sps.csc_matrix:
        """A as scipy CSC, sorted indices, in the pattern of :class:`ScatterMap`."""
        smap = scatter_map(self.n, self.tets, self.free == 0.0)
        data = np.empty(len(smap.indices) + 1)
        data[smap.place] = self.block_sums(smap)  # entries outside the pattern (exact zeros) go to the last, dropped
        n3 = 3 * self.n
        A = sps.csc_matrix((data[:-1], smap.indices, smap.indptr), shape=(n3, n3))
        A.has_sorted_indices = True
        return A
