"""The system matrix A of eq. (1) assembled on the host with NumPy, from a frozen state.

The asynchronous LDL^T preconditioner (eq. 2) factorizes A(t_u). What A(t_u) depends on is
small and cheap to copy: the element rotations R_e, the topology, the rest shape-function
gradients, the material, the fixed flags and the coefficients of eq. (1). The simulation
thread copies those (:class:`AssemblyState`, made by
:meth:`soft_tissue_sim.corotational_fem.CorotationalFEM.assembly_state`); the worker builds the
scipy CSC matrix from them (:meth:`AssemblyState.csc`) with NumPy only, no Warp launch, so
any thread or process may call it.

The element blocks (same formula as ``element_block`` in :mod:`corotational_fem`), with the
rotated gradients h_k = R_e g_k:

    A_ij += k_coef V (mu (g_i . g_j) I + mu h_j h_i^T + lam h_i h_j^T) + mass_ij I,
    mass_ij = m_coef rho V (1 + d_ij) / 20 (consistent)  or  m_coef rho V d_ij / 4 (lumped),

each multiplied by free_i free_j (fixed nodes filtered out), and the identity on the diagonal
block of each fixed node. The pattern is that of the Warp BSR assembly: every 3x3 block of
every element pair (i, j) and every diagonal block, stored in full (zeros kept), columns
sorted. It depends on the topology alone, so it is found once per topology
(:class:`ScatterMap`: the CSC pattern and, for each entry of the element blocks, its place in
the CSC data) and kept in a small cache; each assembly is then the blocks and one ``bincount``
that sums them into place.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sps


@dataclass
class ScatterMap:
    """The CSC pattern of A for one topology (n nodes, tets (m, 4)) and where each entry of
    :meth:`AssemblyState.entries` lands in its data: ``data = bincount(target, entries)``."""

    n: int
    tets: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    target: np.ndarray

    @classmethod
    def build(cls, n: int, tets: np.ndarray) -> "ScatterMap":
        tets = np.array(tets, dtype=np.int64)
        m = len(tets)
        # block (I, J) of each element pair (e, i, j), then each diagonal block; sorted by column, then row
        bi = np.concatenate([np.repeat(tets, 4, axis=1).ravel(), np.arange(n)])
        bj = np.concatenate([np.tile(tets, (1, 4)).ravel(), np.arange(n)])
        blocks, inv = np.unique(bj * n + bi, return_inverse=True)
        col_b, row_b = np.divmod(blocks, n)
        count = np.bincount(col_b, minlength=n)  # blocks per block column
        start = np.concatenate([[0], np.cumsum(count)])[col_b]  # first block of the block's column
        # column 3J+b holds the rows 3I+a of the blocks of block column J, in order: entry (a, b)
        # of a block at 9 start + 3 count b + 3 rank + a, rank = its place in its block column
        base = 9 * start + 3 * (np.arange(len(blocks)) - start)
        stride = 3 * count[col_b]
        a = np.arange(3)
        place = base[:, None, None] + a[:, None] + stride[:, None, None] * a  # (blocks, a, b)
        indices = np.empty(9 * len(blocks), dtype=np.int32)
        indices[place.ravel()] = np.repeat(3 * row_b, 9) + np.tile(np.repeat(a, 3), len(blocks))
        indptr = np.zeros(3 * n + 1, dtype=np.int32)
        indptr[1:] = np.cumsum(np.repeat(3 * count, 3))
        target = place[inv.ravel()]  # (16 m + n, 3, 3)
        elem = target[: 16 * m].reshape(m, 4, 4, 3, 3).transpose(1, 2, 3, 4, 0)  # the order of entries()
        target = np.concatenate([elem.ravel(), target[16 * m:].ravel()]).astype(np.int32)
        return cls(n, tets, indptr, indices, target)

    def matches(self, n: int, tets: np.ndarray) -> bool:
        return n == self.n and tets.shape == self.tets.shape and np.array_equal(tets, self.tets)


_CACHE: list[ScatterMap] = []  # the most recently used first
_CACHE_SIZE = 2  # the topology in use and the one before it (a snapshot taken before a cut)
_CACHE_LOCK = threading.Lock()


def scatter_map(n: int, tets: np.ndarray) -> ScatterMap:
    """The :class:`ScatterMap` of this topology, from the cache or built (and cached)."""
    with _CACHE_LOCK:
        for i, s in enumerate(_CACHE):
            if s.matches(n, tets):
                _CACHE.insert(0, _CACHE.pop(i))
                return s
    s = ScatterMap.build(n, tets)
    with _CACHE_LOCK:
        _CACHE.insert(0, s)
        del _CACHE[_CACHE_SIZE:]
    return s


def shape_gradients(Dm_inv: np.ndarray) -> np.ndarray:
    """(m, 4, 3): the rest gradients g_0..g_3 of each element (rows of Dm^-1; g_0 = -sum)."""
    G = np.empty((len(Dm_inv), 4, 3))
    G[:, 1:] = Dm_inv
    G[:, 0] = -Dm_inv.sum(axis=1)
    return G


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

    def entries(self) -> np.ndarray:
        """Every contribution to A, flat: the element blocks ordered (i, j, a, b, e) (block (i, j)
        of element e, row a, column b; element last, so that each operation runs along the m
        elements), then the diagonal block (a, b) of each node (the identity on fixed nodes)."""
        m = len(self.tets)
        G = shape_gradients(self.Dm_inv)
        w = self.free[self.tets]  # (m, 4): filtering the gradients filters the outer products
        h = np.matmul(G, np.swapaxes(self.R, 1, 2)) * w[:, :, None]  # h_k = R g_k, (m, 4, 3)
        h = np.ascontiguousarray(h.transpose(1, 2, 0))  # (4, 3, m)
        kv = self.k_coef * self.volume
        out = np.empty(144 * m + 9 * self.n)
        blocks = out[: 144 * m].reshape(4, 4, 3, 3, m)
        np.multiply(h[:, None, :, None], (h * (kv * self.lam))[None, :, None, :], out=blocks)  # lam h_i[a] h_j[b]
        blocks += h[None, :, :, None] * (h * (kv * self.mu))[:, None, None, :]  # mu h_j[a] h_i[b]
        diag = np.matmul(G, np.swapaxes(G, 1, 2)).transpose(1, 2, 0) * (kv * self.mu)  # mu (g_i . g_j), (4, 4, m)
        mv = self.m_coef * self.rho * self.volume
        if self.consistent:
            diag += (1.0 + np.eye(4))[:, :, None] * (mv / 20.0)
        else:
            diag += np.eye(4)[:, :, None] * (mv / 4.0)
        diag *= w.T[:, None] * w.T[None, :]
        for a in range(3):
            blocks[:, :, a, a] += diag
        out[144 * m:].reshape(-1, 9)[:] = (1.0 - self.free)[:, None] * np.eye(3).reshape(1, 9)
        return out

    def csc(self) -> sps.csc_matrix:
        """A as scipy CSC (full symmetric pattern, sorted indices)."""
        smap = scatter_map(self.n, self.tets)
        data = np.bincount(smap.target, weights=self.entries(), minlength=len(smap.indices))
        n3 = 3 * self.n
        A = sps.csc_matrix((data, smap.indices, smap.indptr), shape=(n3, n3))
        A.has_sorted_indices = True
        return A
