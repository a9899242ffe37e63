"""The CHOLMOD LDL^T factor applied on the device (Warp kernels, float64).

CHOLMOD factors P A P^T = L D L^T (L unit lower triangular, D diagonal, P the fill-reducing
permutation, ``f.P()``), so that  A^-1 b = P^T L^-T D^-1 L^-1 P b  (what ``f(b)`` computes).
With the rotation of eq. (2) of the paper the preconditioner applies

    z = dR P^T L^-T D^-1 L^-1 P dR^T r,      dR_n = R_n(t) R_n(t_u)^T  (per node, 3x3).

Host side (once per factor, in the factorization worker): ``f.LD()`` gives L and D in one
CSC matrix (a supernodal factor is converted by CHOLMOD to a simplicial LDL^T there, in
place; the host path keeps working with the converted factor). Once per sparsity pattern we
build the CSR of the strictly lower L (forward solve) and of the strictly upper L^T
(backward solve), the row groups and their level sets; per factor only the values are
gathered (``FactorValues``).

Row groups: the rows of one node (its 3 degrees of freedom) are consecutive in CHOLMOD's
orderings almost always (METIS: all of them on our meshes); each maximal run of consecutive
permuted rows of one node is a group, solved by one thread (or one warp) in order, so the
dependencies inside a node cost no extra level. A group's level is one more than the
highest level of the groups it depends on (forward: the columns of its rows in L; backward:
the columns of its rows in L^T), computed on the group elimination tree and checked against
every entry (a general sweep is the fallback if the check fails).

Device side (:class:`DeviceLDLT`): arrays are allocated per pattern and refilled in place
(``wp.copy`` from host numpy) when a new factor of the same pattern arrives, so a CUDA graph
that captured the launches stays valid. One application is

    forward:  one launch per level (a group per thread or per warp); the first touch of a row
              computes its right-hand side (dR^T r)[P i] in place (permute + rotate in);
    backward: one launch per level, x_i = y_i / D_i - sum_{j>i} L_ji x_j (D^-1 fused);
    out:      z_n = dR_n (x at the node's 3 permuted rows)      (permute + rotate out).

Options: ``lanes`` = 1 (thread per group) or 32 (warp per group, shuffle reduction, CUDA);
``tail_width`` > 0 merges runs of consecutive levels holding at most that many groups into
one single-block launch that loops over them with a block barrier (CUDA ``__syncthreads``;
on the CPU backend the block is a single thread), so the long narrow top of the elimination
tree costs one launch instead of one per level. In that kernel a level of one group is
reduced by the whole block, a wider one by a warp per group.

Measured (bench haptic, NVIDIA H100, see benchmarks/results/haptic_gpu.json): one application
takes 1.38 ms on the 2,000-node beam (METIS, 149 levels, 55 launches) and 2.37 ms on the brain
(242 levels, 41 launches) -- latency-bound, a few microseconds per level -- which is no faster
than CHOLMOD on the host (0.5-1.2 ms, 0.8-1.5 ms with the copies). With AMD ordering it is
3.6-6.4 ms; a thread per row group with one launch per level 23-49 ms.
"""

from __future__ import annotations

import hashlib
import itertools
import threading
from dataclasses import dataclass, field

import numpy as np
import warp as wp

ORDERINGS = ("amd", "metis", "nesdis", "colamd", "natural", "default", "best")

_F64 = wp.float64


# ---------------------------------------------------------------------------------- host
@dataclass
class FactorStructure:
    """Everything about a factor that depends only on its sparsity pattern and permutation."""

    pattern_id: int
    n: int  # scalar rows (degrees of freedom)
    perm: np.ndarray  # permuted row i -> original DOF perm[i]
    pinv: np.ndarray  # original DOF q -> permuted row pinv[q]
    group_start: np.ndarray  # (n_groups + 1,) first row of each group
    lo_off: np.ndarray  # (n_groups,) entries of each row of the group in L before the group (same for its rows)
    up_off: np.ndarray  # (n_groups,) entries of each row of the group in L^T after the group
    lo_indptr: np.ndarray  # CSR of the strictly lower L
    lo_indices: np.ndarray
    lo_src: np.ndarray  # position of each entry in the CSC data of f.LD()
    up_indptr: np.ndarray  # CSR of the strictly upper L^T (= CSC of the strictly lower L)
    up_indices: np.ndarray
    up_src: np.ndarray
    diag_src: np.ndarray
    fwd_order: np.ndarray  # groups in forward level order
    fwd_ptr: np.ndarray  # (n_fwd_levels + 1,) level pointers into fwd_order
    bwd_order: np.ndarray
    bwd_ptr: np.ndarray
    scalar_levels: int  # levels with one row per group (for the record)
    level_method: str  # "etree" or "sweep" (fallback)
    # per group, in each direction's level order (what a thread reads first, in one go):
    fwd_meta: np.ndarray = None  # (ng, 9) g0, size, m, first entry of rows 0..2 in L, original DOF of rows 0..2
    bwd_meta: np.ndarray = None  # (ng, 6) g0, size, m, first off-group entry of rows 0..2 in L^T
    fwd_coef_src: np.ndarray = None  # (ng, 3) LD data index of L[1,0], L[2,0], L[2,1] inside the group (-1: none)
    bwd_coef_src: np.ndarray = None  # (ng, 6) the same and the group's three diagonal entries D

    @property
    def n_groups(self) -> int:
        return len(self.group_start) - 1

    @property
    def fwd_levels(self) -> int:
        return len(self.fwd_ptr) - 1

    @property
    def bwd_levels(self) -> int:
        return len(self.bwd_ptr) - 1

    @property
    def nnz_offdiag(self) -> int:
        return len(self.lo_indices)

    def summary(self) -> dict:
        w = np.diff(self.fwd_ptr)
        return {"dofs": self.n, "groups": self.n_groups, "nnz_L_offdiag": self.nnz_offdiag,
                "fwd_levels": self.fwd_levels, "bwd_levels": self.bwd_levels, "scalar_levels": self.scalar_levels,
                "max_level_width": int(w.max()) if len(w) else 0, "level_method": self.level_method}


@dataclass
class FactorValues:
    """The numbers of one factor: the CSC data of ``f.LD()`` (diagonal first in each column),
    gathered into the device layout of its :class:`FactorStructure` on the device."""

    structure: FactorStructure
    data: np.ndarray
    converted: bool = False  # a supernodal factor converted to simplicial LDL^T by f.LD()

    @property
    def lo_vals(self) -> np.ndarray:
        return self.data[self.structure.lo_src]

    @property
    def up_vals(self) -> np.ndarray:
        return self.data[self.structure.up_src]

    @property
    def dinv(self) -> np.ndarray:
        with np.errstate(divide="ignore"):
            return 1.0 / self.data[self.structure.diag_src]


def _levels_from_parent(parent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Height (forward level) and depth (backward level) of every node of a forest whose
    parents have larger indices (-1: a root)."""
    m = len(parent)
    height = [0] * m
    par = parent.tolist()
    for g in range(m):
        p = par[g]
        if p >= 0 and height[p] < height[g] + 1:
            height[p] = height[g] + 1
    depth = [0] * m
    for g in range(m - 1, -1, -1):
        p = par[g]
        if p >= 0:
            depth[g] = depth[p] + 1
    return np.asarray(height, dtype=np.int64), np.asarray(depth, dtype=np.int64)


def _sweep_levels(n_groups, group_start, gid, indptr, indices, forward: bool) -> np.ndarray:
    """Exact levels by a sweep over the groups (fallback when the tree levels fail the check)."""
    lev = np.zeros(n_groups, dtype=np.int64)
    rng = range(n_groups) if forward else range(n_groups - 1, -1, -1)
    for g in rng:
        a, b = group_start[g], group_start[g + 1]
        dep = gid[indices[indptr[a]:indptr[b]]]
        dep = dep[dep != g]
        lev[g] = lev[dep].max() + 1 if len(dep) else 0
    return lev


def _check_levels(lev, gid, rows, cols) -> bool:
    """Every off-group entry (row depends on col) has its column's group in an earlier level."""
    gr, gc = gid[rows], gid[cols]
    m = gr != gc
    return bool(np.all(lev[gr[m]] > lev[gc[m]]))


def _level_order(lev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    order = np.lexsort((np.arange(len(lev)), lev)).astype(np.int32)
    counts = np.bincount(lev, minlength=int(lev.max()) + 1 if len(lev) else 0)
    ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return order, ptr


def _off_counts(group_start, r_off, c_off, n):
    """Per row: entries of L left of its group, entries of L^T right of its group; per group (row 0's)."""
    ng = len(group_start) - 1
    gid = np.repeat(np.arange(ng, dtype=np.int64), np.diff(group_start))
    lo_row = np.bincount(r_off[c_off < group_start[gid[r_off]]], minlength=n)
    up_row = np.bincount(c_off[r_off >= group_start[gid[c_off] + 1]], minlength=n)
    g0 = group_start[:-1]
    return lo_row[g0].astype(np.int32), up_row[g0].astype(np.int32), lo_row, up_row, gid


def _unshared_groups(group_start, lo_indptr, lo_indices, up_indptr, up_indices, r_off, c_off) -> np.ndarray:
    """Groups whose rows do not all have the same columns outside the group (in L and in L^T)."""
    n = len(lo_indptr) - 1
    _, _, lo_row, up_row, gid = _off_counts(group_start, r_off, c_off, n)
    sizes = np.diff(group_start)
    bad = np.zeros(len(sizes), dtype=bool)
    for r in (1, 2):
        gs = np.flatnonzero(sizes > r)
        if not len(gs):
            continue
        i0 = group_start[gs]
        ir = i0 + r
        for row_cnt, indptr, indices, tail in ((lo_row, lo_indptr, lo_indices, False),
                                               (up_row, up_indptr, up_indices, True)):
            m = row_cnt[i0]
            bad[gs[row_cnt[ir] != m]] = True
            ok = gs[row_cnt[ir] == m]
            if not len(ok):
                continue
            i0o, iro, mo = group_start[ok], group_start[ok] + r, row_cnt[group_start[ok]].astype(np.int64)
            start0 = (indptr[i0o + 1] - mo) if tail else indptr[i0o].astype(np.int64)
            startr = (indptr[iro + 1] - mo) if tail else indptr[iro].astype(np.int64)
            tot = int(mo.sum())
            if tot == 0:
                continue
            first = np.repeat(np.cumsum(mo) - mo, mo)
            k = np.arange(tot) - first
            diff = indices[np.repeat(start0, mo) + k] != indices[np.repeat(startr, mo) + k]
            pair = np.repeat(np.arange(len(ok)), mo)
            bad[ok[np.bincount(pair, weights=diff, minlength=len(ok)) > 0]] = True
        # sizes > 3 cannot happen (3 DOFs per node)
    if np.any(sizes > 3):
        bad[sizes > 3] = True
    return np.flatnonzero(bad)


def build_structure(LD, perm: np.ndarray, pattern_id: int = 0) -> FactorStructure:
    """Device layout of a factor from ``f.LD()`` (CSC, diagonal first in each column) and ``f.P()``."""
    n = LD.shape[0]
    indptr = LD.indptr.astype(np.int64)
    rows = LD.indices.astype(np.int64)
    cols = np.repeat(np.arange(n, dtype=np.int64), np.diff(indptr))
    diag_src = indptr[:-1].copy()
    if n and not np.array_equal(rows[diag_src], np.arange(n)):
        raise ValueError("LD factor: the diagonal is not the first entry of every column")
    off = rows != cols
    if np.any(rows[off] < cols[off]):
        raise ValueError("LD factor is not lower triangular")
    src = np.flatnonzero(off)
    r_off, c_off = rows[off], cols[off]
    # L^T by rows = L by columns: the CSC order of the strictly lower part
    up_counts = np.bincount(c_off, minlength=n)
    up_indptr = np.concatenate([[0], np.cumsum(up_counts)]).astype(np.int32)
    up_indices = r_off.astype(np.int32)
    up_src = src
    # L by rows, columns ascending
    o = np.lexsort((c_off, r_off))
    lo_counts = np.bincount(r_off, minlength=n)
    lo_indptr = np.concatenate([[0], np.cumsum(lo_counts)]).astype(np.int32)
    lo_indices = c_off[o].astype(np.int32)
    lo_src = src[o]
    perm = np.asarray(perm, dtype=np.int64)
    pinv = np.empty(n, dtype=np.int64)
    pinv[perm] = np.arange(n)
    # groups: maximal runs of permuted rows of one node whose rows share their columns outside
    # the group (true of a node's rows in a Cholesky pattern; groups that fail are split)
    node = perm // 3
    brk = np.flatnonzero(np.diff(node) != 0) + 1
    group_start = np.concatenate([[0], brk, [n]]).astype(np.int64) if n else np.zeros(1, np.int64)
    bad = _unshared_groups(group_start, lo_indptr, lo_indices, up_indptr, up_indices, r_off, c_off)
    if len(bad):
        split = np.zeros(len(group_start) - 1, dtype=bool)
        split[bad] = True
        extra = np.concatenate([np.arange(group_start[g] + 1, group_start[g + 1]) for g in np.flatnonzero(split)])
        group_start = np.union1d(group_start, extra)
    lo_off, up_off, _, _, _ = _off_counts(group_start, r_off, c_off, n)
    ng = len(group_start) - 1
    gid = np.repeat(np.arange(ng, dtype=np.int64), np.diff(group_start))
    group_start = group_start.astype(np.int32)
    # group elimination tree: parent = the first later group among the rows below the group
    gr, gc = gid[r_off], gid[c_off]
    m = gr != gc
    parent = np.full(ng, ng, dtype=np.int64)
    np.minimum.at(parent, gc[m], gr[m])
    parent[parent == ng] = -1
    height, depth = _levels_from_parent(parent)
    method = "etree"
    ok_f = _check_levels(height, gid, r_off, c_off)  # forward: row r needs column c
    ok_b = _check_levels(depth, gid, c_off, r_off)  # backward: row c of L^T needs r
    if not ok_f:
        height = _sweep_levels(ng, group_start, gid, lo_indptr, lo_indices, True)
        method = "sweep"
    if not ok_b:
        depth = _sweep_levels(ng, group_start, gid, up_indptr, up_indices, False)
        method = "sweep"
    fwd_order, fwd_ptr = _level_order(height)
    bwd_order, bwd_ptr = _level_order(depth)
    # per-group records in level order, and where the in-group entries and D live in LD's data
    coef_src = np.full((ng, 3), -1, dtype=np.int64)
    ing = ~m
    lr = r_off[ing] - group_start[gr[ing]]
    lc = c_off[ing] - group_start[gr[ing]]
    slot = np.where(lr == 1, 0, np.where(lc == 0, 1, 2))  # (1,0) -> 0, (2,0) -> 1, (2,1) -> 2
    coef_src[gr[ing], slot] = src[ing]
    gs64 = group_start.astype(np.int64)
    sz = np.diff(gs64)
    g0 = gs64[:-1]
    row = [g0 + np.minimum(k, sz - 1) for k in range(3)]  # rows 0..2 (the last one repeated when smaller)
    diag3 = np.stack([np.where(k < sz, diag_src[row[k]], -1) for k in range(3)], axis=1)
    fwd_meta = np.stack([g0, sz, lo_off] + [lo_indptr[row[k]] for k in range(3)] + [perm[row[k]] for k in range(3)],
                        axis=1)
    bwd_meta = np.stack([g0, sz, up_off] + [up_indptr[row[k] + 1] - up_off for k in range(3)], axis=1)
    fwd_meta = np.ascontiguousarray(fwd_meta[fwd_order], dtype=np.int32)
    bwd_meta = np.ascontiguousarray(bwd_meta[bwd_order], dtype=np.int32)
    fwd_coef_src = np.ascontiguousarray(coef_src[fwd_order])
    bwd_coef_src = np.ascontiguousarray(np.concatenate([coef_src, diag3], axis=1)[bwd_order])
    # scalar levels (one row per group), for the record: the height of the row elimination tree
    sparent = np.full(n, n, dtype=np.int64)
    np.minimum.at(sparent, c_off, r_off)
    sparent[sparent == n] = -1
    sh, _ = _levels_from_parent(sparent)
    return FactorStructure(
        pattern_id=pattern_id, n=n, perm=perm.astype(np.int32), pinv=pinv.astype(np.int32),
        group_start=group_start, lo_off=lo_off, up_off=up_off, lo_indptr=lo_indptr, lo_indices=lo_indices, lo_src=lo_src,
        up_indptr=up_indptr, up_indices=up_indices, up_src=up_src, diag_src=diag_src,
        fwd_order=fwd_order, fwd_ptr=fwd_ptr, bwd_order=bwd_order, bwd_ptr=bwd_ptr,
        scalar_levels=int(sh.max()) + 1 if n else 0, level_method=method,
        fwd_meta=fwd_meta, bwd_meta=bwd_meta, fwd_coef_src=fwd_coef_src, bwd_coef_src=bwd_coef_src,
    )


_PATTERN_IDS = itertools.count(1)


class StructureCache:
    """Patterns seen so far (the last few), keyed by the bytes of L's pattern and the permutation."""

    def __init__(self, keep: int = 4):
        self.keep = keep
        self._items: list[tuple[bytes, FactorStructure]] = []
        self._lock = threading.Lock()

    def get(self, LD, perm) -> FactorStructure:
        h = hashlib.blake2b(digest_size=20)
        h.update(np.int64(LD.shape[0]).tobytes())
        h.update(np.ascontiguousarray(LD.indptr).tobytes())
        h.update(np.ascontiguousarray(LD.indices).tobytes())
        h.update(np.ascontiguousarray(perm).tobytes())
        key = h.digest()
        with self._lock:
            for k, s in self._items:
                if k == key:
                    return s
            pid = next(_PATTERN_IDS)  # unique across caches: a DeviceLDLT may see factors of several
        s = build_structure(LD, perm, pid)
        with self._lock:
            self._items = ([(key, s)] + self._items)[: self.keep]
        return s


def factor_values(factor, cache: StructureCache | None = None, supernodal: bool = False) -> FactorValues:
    """Device layout and values of a CHOLMOD factor (host numpy; runs in the factorization worker).

    ``factor.LD()`` converts a supernodal LL^T factor to a simplicial LDL^T one in place
    (``supernodal`` only records that this happened: scikit-sparse does not expose the kind).
    """
    LD = factor.LD()
    LD.sort_indices()
    perm = np.asarray(factor.P())
    s = (cache or StructureCache()).get(LD, perm)
    return FactorValues(s, np.ascontiguousarray(LD.data, dtype=np.float64), converted=supernodal)


def host_solve(values: FactorValues, b: np.ndarray) -> np.ndarray:
    """The same algorithm as the device kernels, in numpy/scipy (reference for tests)."""
    import scipy.sparse as sps
    from scipy.sparse.linalg import spsolve_triangular

    s = values.structure
    n = s.n
    Lo = sps.csr_matrix((values.lo_vals, s.lo_indices, s.lo_indptr), shape=(n, n)) + sps.identity(n, format="csr")
    Up = sps.csr_matrix((values.up_vals, s.up_indices, s.up_indptr), shape=(n, n)) + sps.identity(n, format="csr")
    y = spsolve_triangular(Lo, b[s.perm], lower=True, unit_diagonal=True)
    x = spsolve_triangular(Up, y * values.dinv, lower=False, unit_diagonal=True)
    out = np.empty_like(x)
    out[s.perm] = x
    return out


# -------------------------------------------------------------------------------- kernels
@wp.func_native("""
#if defined(__CUDA_ARCH__)
double a = v.c[0], b = v.c[1], c = v.c[2];
if (nt == lanes) {
    // a warp (or part of one) per group: shuffle reduction, lane 0 gets the sums
    for (int o = lanes / 2; o > 0; o >>= 1) {
        a += __shfl_down_sync(0xffffffff, a, o);
        b += __shfl_down_sync(0xffffffff, b, o);
        c += __shfl_down_sync(0xffffffff, c, o);
    }
} else {
    // the whole block on one group: warp sums, then warp 0 adds the warps' partial sums (thread 0
    // gets the total). No barrier after: the tail kernels reach a block barrier before the next use.
    __shared__ double red[3 * 32];
    for (int o = 16; o > 0; o >>= 1) {
        a += __shfl_down_sync(0xffffffff, a, o);
        b += __shfl_down_sync(0xffffffff, b, o);
        c += __shfl_down_sync(0xffffffff, c, o);
    }
    int w = threadIdx.x >> 5, l = threadIdx.x & 31;
    if (l == 0) { red[3 * w] = a; red[3 * w + 1] = b; red[3 * w + 2] = c; }
    __syncthreads();
    if (w == 0) {
        int nw = (blockDim.x + 31) >> 5;
        a = l < nw ? red[3 * l] : 0.0;
        b = l < nw ? red[3 * l + 1] : 0.0;
        c = l < nw ? red[3 * l + 2] : 0.0;
        for (int o = 16; o > 0; o >>= 1) {
            a += __shfl_down_sync(0xffffffff, a, o);
            b += __shfl_down_sync(0xffffffff, b, o);
            c += __shfl_down_sync(0xffffffff, c, o);
        }
    }
}
return wp::vec_t<3, wp::float64>(a, b, c);
#else
return v;
#endif
""")
def _reduce3(v: wp.vec3d, nt: int, lanes: int) -> wp.vec3d: ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
__syncthreads();
#endif
""")
def _block_sync(): ...


@wp.func
def _rhs(q: int, r: wp.array(dtype=wp.vec3d), dR: wp.array(dtype=wp.mat33d)):
    """(dR^T r) at original DOF q: the permuted, rotated right-hand side of a row."""
    nd = q // 3
    c = q - 3 * nd
    M = dR[nd]
    v = r[nd]
    return M[0, c] * v[0] + M[1, c] * v[1] + M[2, c] * v[2]


@wp.func
def _forward_group(
    q: int, t: int, nt: int, lanes: int,
    meta: wp.array2d(dtype=wp.int32), coef: wp.array2d(dtype=wp.float64),
    indices: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.float64),
    r: wp.array(dtype=wp.vec3d), dR: wp.array(dtype=wp.mat33d), y: wp.array(dtype=wp.float64),
):
    """y_i = (P dR^T r)_i - sum_{j<i} L_ij y_j for the (up to 3) rows of the group at position q.

    Threads t = 0..nt-1 share the m columns left of the group, which all its rows have (first
    in each row, in the same order): one load of y_j serves the three rows. Thread 0 then
    solves the rows with the group's own entries of L (held in ``coef``)."""
    g0 = meta[q, 0]
    sz = meta[q, 1]
    m = meta[q, 2]
    a0 = meta[q, 3]
    a1 = meta[q, 4]
    a2 = meta[q, 5]
    # loaded before the sums (independent of them), so that their latency overlaps the loop
    b0 = _rhs(meta[q, 6], r, dR)
    b1 = _rhs(meta[q, 7], r, dR)
    b2 = _rhs(meta[q, 8], r, dR)
    c10 = coef[q, 0]
    c20 = coef[q, 1]
    c21 = coef[q, 2]
    s0 = _F64(0.0)
    s1 = _F64(0.0)
    s2 = _F64(0.0)
    for k in range(t, m, nt):
        yj = y[indices[a0 + k]]
        s0 += vals[a0 + k] * yj
        if sz > 1:
            s1 += vals[a1 + k] * yj
        if sz > 2:
            s2 += vals[a2 + k] * yj
    sv = _reduce3(wp.vec3d(s0, s1, s2), nt, lanes)
    if t == 0:
        y0 = b0 - sv[0]
        y[g0] = y0
        if sz > 1:
            y1 = b1 - sv[1] - c10 * y0
            y[g0 + 1] = y1
            if sz > 2:
                y[g0 + 2] = b2 - sv[2] - c20 * y0 - c21 * y1


@wp.func
def _backward_group(
    q: int, t: int, nt: int, lanes: int,
    meta: wp.array2d(dtype=wp.int32), coef: wp.array2d(dtype=wp.float64),
    indices: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64), x: wp.array(dtype=wp.float64),
):
    """x_i = y_i / D_i - sum_{j>i} L_ji x_j for the rows of the group at position q (last row
    first); the m columns right of the group are shared by its rows, last in each row."""
    g0 = meta[q, 0]
    sz = meta[q, 1]
    m = meta[q, 2]
    e0 = meta[q, 3]
    e1 = meta[q, 4]
    e2 = meta[q, 5]
    # loaded before the sums (independent of them)
    y0 = y[g0]
    y1 = y[g0 + wp.min(1, sz - 1)]
    y2 = y[g0 + wp.min(2, sz - 1)]
    c10 = coef[q, 0]
    c20 = coef[q, 1]
    c21 = coef[q, 2]
    d0 = coef[q, 3]
    d1 = coef[q, 4]
    d2 = coef[q, 5]
    s0 = _F64(0.0)
    s1 = _F64(0.0)
    s2 = _F64(0.0)
    for k in range(t, m, nt):
        xj = x[indices[e0 + k]]
        s0 += vals[e0 + k] * xj
        if sz > 1:
            s1 += vals[e1 + k] * xj
        if sz > 2:
            s2 += vals[e2 + k] * xj
    sv = _reduce3(wp.vec3d(s0, s1, s2), nt, lanes)
    if t == 0:
        x2 = _F64(0.0)
        x1 = _F64(0.0)
        if sz > 2:
            x2 = y2 * d2 - sv[2]
            x[g0 + 2] = x2
        if sz > 1:
            x1 = y1 * d1 - sv[1] - c21 * x2
            x[g0 + 1] = x1
        x[g0] = y0 * d0 - sv[0] - c10 * x1 - c20 * x2


@wp.kernel
def _forward_level_kernel(
    offset: int, lanes: int, meta: wp.array2d(dtype=wp.int32), coef: wp.array2d(dtype=wp.float64),
    indices: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.float64),
    r: wp.array(dtype=wp.vec3d), dR: wp.array(dtype=wp.mat33d), y: wp.array(dtype=wp.float64),
):
    t = wp.tid()
    _forward_group(offset + t // lanes, t % lanes, lanes, lanes, meta, coef, indices, vals, r, dR, y)


@wp.kernel
def _backward_level_kernel(
    offset: int, lanes: int, meta: wp.array2d(dtype=wp.int32), coef: wp.array2d(dtype=wp.float64),
    indices: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64), x: wp.array(dtype=wp.float64),
):
    t = wp.tid()
    _backward_group(offset + t // lanes, t % lanes, lanes, lanes, meta, coef, indices, vals, y, x)


@wp.kernel
def _forward_tail_kernel(
    level_ptr: wp.array(dtype=wp.int32), lev0: int, lev1: int, lanes: int,
    meta: wp.array2d(dtype=wp.int32), coef: wp.array2d(dtype=wp.float64),
    indices: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.float64),
    r: wp.array(dtype=wp.vec3d), dR: wp.array(dtype=wp.mat33d), y: wp.array(dtype=wp.float64),
):
    """Levels lev0..lev1-1 in one block, a barrier after each: a level of one group is done by
    the whole block (block reduction), a wider one by a warp per group."""
    t = wp.tid()
    nt = wp.block_dim()
    w = t // lanes
    nw = nt // lanes
    a = level_ptr[lev0]
    b = level_ptr[lev0 + 1]
    for lev in range(lev0, lev1):
        bn = b
        if lev + 1 < lev1:
            bn = level_ptr[lev + 2]  # the next level's end, loaded ahead of the barrier
        if b - a == 1:
            _forward_group(a, t, nt, lanes, meta, coef, indices, vals, r, dR, y)
        else:
            for q in range(a + w, b, nw):
                _forward_group(q, t % lanes, lanes, lanes, meta, coef, indices, vals, r, dR, y)
        _block_sync()
        a = b
        b = bn


@wp.kernel
def _backward_tail_kernel(
    level_ptr: wp.array(dtype=wp.int32), lev0: int, lev1: int, lanes: int,
    meta: wp.array2d(dtype=wp.int32), coef: wp.array2d(dtype=wp.float64),
    indices: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.float64),
    y: wp.array(dtype=wp.float64), x: wp.array(dtype=wp.float64),
):
    t = wp.tid()
    nt = wp.block_dim()
    w = t // lanes
    nw = nt // lanes
    a = level_ptr[lev0]
    b = level_ptr[lev0 + 1]
    for lev in range(lev0, lev1):
        bn = b
        if lev + 1 < lev1:
            bn = level_ptr[lev + 2]  # the next level's end, loaded ahead of the barrier
        if b - a == 1:
            _backward_group(a, t, nt, lanes, meta, coef, indices, vals, y, x)
        else:
            for q in range(a + w, b, nw):
                _backward_group(q, t % lanes, lanes, lanes, meta, coef, indices, vals, y, x)
        _block_sync()
        a = b
        b = bn


# ------------------------------------------------------------ many right-hand sides at once
@wp.func
def _forward_group_cols(
    q: int, col: int, t: int, nt: int, lanes: int,
    meta: wp.array2d(dtype=wp.int32), coef: wp.array2d(dtype=wp.float64),
    indices: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.float64),
    B: wp.array2d(dtype=wp.float64), y: wp.array2d(dtype=wp.float64),
):
    """:func:`_forward_group` for column ``col`` of a block: no rotation, B in original DOFs."""
    g0 = meta[q, 0]
    sz = meta[q, 1]
    m = meta[q, 2]
    a0 = meta[q, 3]
    a1 = meta[q, 4]
    a2 = meta[q, 5]
    b0 = B[meta[q, 6], col]
    b1 = B[meta[q, 7], col]
    b2 = B[meta[q, 8], col]
    c10 = coef[q, 0]
    c20 = coef[q, 1]
    c21 = coef[q, 2]
    s0 = _F64(0.0)
    s1 = _F64(0.0)
    s2 = _F64(0.0)
    for k in range(t, m, nt):
        yj = y[indices[a0 + k], col]
        s0 += vals[a0 + k] * yj
        if sz > 1:
            s1 += vals[a1 + k] * yj
        if sz > 2:
            s2 += vals[a2 + k] * yj
    sv = _reduce3(wp.vec3d(s0, s1, s2), nt, lanes)
    if t == 0:
        y0 = b0 - sv[0]
        y[g0, col] = y0
        if sz > 1:
            y1 = b1 - sv[1] - c10 * y0
            y[g0 + 1, col] = y1
            if sz > 2:
                y[g0 + 2, col] = b2 - sv[2] - c20 * y0 - c21 * y1


@wp.func
def _backward_group_cols(
    q: int, col: int, t: int, nt: int, lanes: int,
    meta: wp.array2d(dtype=wp.int32), coef: wp.array2d(dtype=wp.float64),
    indices: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.float64),
    y: wp.array2d(dtype=wp.float64), x: wp.array2d(dtype=wp.float64),
):
    """:func:`_backward_group` for column ``col`` of a block."""
    g0 = meta[q, 0]
    sz = meta[q, 1]
    m = meta[q, 2]
    e0 = meta[q, 3]
    e1 = meta[q, 4]
    e2 = meta[q, 5]
    y0 = y[g0, col]
    y1 = y[g0 + wp.min(1, sz - 1), col]
    y2 = y[g0 + wp.min(2, sz - 1), col]
    c10 = coef[q, 0]
    c20 = coef[q, 1]
    c21 = coef[q, 2]
    d0 = coef[q, 3]
    d1 = coef[q, 4]
    d2 = coef[q, 5]
    s0 = _F64(0.0)
    s1 = _F64(0.0)
    s2 = _F64(0.0)
    for k in range(t, m, nt):
        xj = x[indices[e0 + k], col]
        s0 += vals[e0 + k] * xj
        if sz > 1:
            s1 += vals[e1 + k] * xj
        if sz > 2:
            s2 += vals[e2 + k] * xj
    sv = _reduce3(wp.vec3d(s0, s1, s2), nt, lanes)
    if t == 0:
        x2 = _F64(0.0)
        x1 = _F64(0.0)
        if sz > 2:
            x2 = y2 * d2 - sv[2]
            x[g0 + 2, col] = x2
        if sz > 1:
            x1 = y1 * d1 - sv[1] - c21 * x2
            x[g0 + 1, col] = x1
        x[g0, col] = y0 * d0 - sv[0] - c10 * x1 - c20 * x2


# Shuffles name the whole warp, so every lane of a warp must reach them: the launches are
# rounded up to whole warps and the loops run a warp-uniform number of times; a lane past the
# last (group, column) pair repeats the last pair (it writes the same values to the same
# places, which is harmless).
@wp.kernel
def _forward_level_cols_kernel(
    offset: int, lanes: int, ncol: int, npairs: int, meta: wp.array2d(dtype=wp.int32),
    coef: wp.array2d(dtype=wp.float64), indices: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.float64),
    B: wp.array2d(dtype=wp.float64), y: wp.array2d(dtype=wp.float64),
):
    """One level, every column: ``lanes`` threads per (group, column) pair, columns fastest."""
    t = wp.tid()
    p = wp.min(t // lanes, npairs - 1)
    _forward_group_cols(offset + p // ncol, p % ncol, t % lanes, lanes, lanes, meta, coef, indices, vals, B, y)


@wp.kernel
def _backward_level_cols_kernel(
    offset: int, lanes: int, ncol: int, npairs: int, meta: wp.array2d(dtype=wp.int32),
    coef: wp.array2d(dtype=wp.float64), indices: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.float64),
    y: wp.array2d(dtype=wp.float64), x: wp.array2d(dtype=wp.float64),
):
    t = wp.tid()
    p = wp.min(t // lanes, npairs - 1)
    _backward_group_cols(offset + p // ncol, p % ncol, t % lanes, lanes, lanes, meta, coef, indices, vals, y, x)


@wp.kernel
def _forward_tail_cols_kernel(
    level_ptr: wp.array(dtype=wp.int32), lev0: int, lev1: int, lanes: int, ncol: int,
    meta: wp.array2d(dtype=wp.int32), coef: wp.array2d(dtype=wp.float64),
    indices: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.float64),
    B: wp.array2d(dtype=wp.float64), y: wp.array2d(dtype=wp.float64),
):
    """Levels lev0..lev1-1 in one block, a barrier after each; the block's warps (of ``lanes``
    threads) take the (group, column) pairs of a level in turn."""
    t = wp.tid()
    nt = wp.block_dim()
    w = t // lanes
    nw = nt // lanes
    a = level_ptr[lev0]
    b = level_ptr[lev0 + 1]
    for lev in range(lev0, lev1):
        bn = b
        if lev + 1 < lev1:
            bn = level_ptr[lev + 2]
        npairs = (b - a) * ncol
        for i in range((npairs + nw - 1) // nw):
            p = wp.min(i * nw + w, npairs - 1)
            _forward_group_cols(a + p // ncol, p % ncol, t % lanes, lanes, lanes, meta, coef, indices, vals, B, y)
        _block_sync()
        a = b
        b = bn


@wp.kernel
def _backward_tail_cols_kernel(
    level_ptr: wp.array(dtype=wp.int32), lev0: int, lev1: int, lanes: int, ncol: int,
    meta: wp.array2d(dtype=wp.int32), coef: wp.array2d(dtype=wp.float64),
    indices: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.float64),
    y: wp.array2d(dtype=wp.float64), x: wp.array2d(dtype=wp.float64),
):
    t = wp.tid()
    nt = wp.block_dim()
    w = t // lanes
    nw = nt // lanes
    a = level_ptr[lev0]
    b = level_ptr[lev0 + 1]
    for lev in range(lev0, lev1):
        bn = b
        if lev + 1 < lev1:
            bn = level_ptr[lev + 2]
        npairs = (b - a) * ncol
        for i in range((npairs + nw - 1) // nw):
            p = wp.min(i * nw + w, npairs - 1)
            _backward_group_cols(a + p // ncol, p % ncol, t % lanes, lanes, lanes, meta, coef, indices, vals, y, x)
        _block_sync()
        a = b
        b = bn


@wp.kernel
def _unpermute_cols_kernel(pinv: wp.array(dtype=wp.int32), x: wp.array2d(dtype=wp.float64),
                           out: wp.array2d(dtype=wp.float64)):
    i, c = wp.tid()
    out[i, c] = x[pinv[i], c]


@wp.kernel
def _rotate_out_kernel(
    pinv: wp.array(dtype=wp.int32), x: wp.array(dtype=wp.float64), dR: wp.array(dtype=wp.mat33d),
    z: wp.array(dtype=wp.vec3d),
):
    n = wp.tid()
    v = wp.vec3d(x[pinv[3 * n]], x[pinv[3 * n + 1]], x[pinv[3 * n + 2]])
    z[n] = dR[n] * v


@wp.kernel
def _gather_kernel(raw: wp.array(dtype=wp.float64), lo_src: wp.array(dtype=wp.int32), up_src: wp.array(dtype=wp.int32),
                   lo_vals: wp.array(dtype=wp.float64), up_vals: wp.array(dtype=wp.float64)):
    """The factor's CSC data into the value arrays of the two CSR matrices."""
    k = wp.tid()
    lo_vals[k] = raw[lo_src[k]]
    up_vals[k] = raw[up_src[k]]


@wp.kernel
def _gather_coef_kernel(raw: wp.array(dtype=wp.float64), src: wp.array2d(dtype=wp.int32), recip_from: int,
                        coef: wp.array2d(dtype=wp.float64)):
    """coef[q, c] = LD data at src[q, c] (0 where absent); columns >= recip_from hold D: 1 / D."""
    q, c = wp.tid()
    k = src[q, c]
    v = _F64(0.0)
    if k >= 0:
        v = raw[k]
        if c >= recip_from:
            v = _F64(1.0) / v
    coef[q, c] = v


@wp.kernel
def relative_rotation_kernel(R: wp.array(dtype=wp.mat33d), R_tu: wp.array(dtype=wp.mat33d),
                             dR: wp.array(dtype=wp.mat33d)):
    """dR_n = R_n(t) R_n(t_u)^T (eq. 2)."""
    n = wp.tid()
    dR[n] = R[n] * wp.transpose(R_tu[n])


@wp.kernel
def identity_kernel(dR: wp.array(dtype=wp.mat33d)):
    dR[wp.tid()] = wp.identity(n=3, dtype=wp.float64)


# --------------------------------------------------------------------------------- device
def _whole_warps(n: int, device) -> int:
    return (n + 31) // 32 * 32 if device.is_cuda else n


def _segments(widths: np.ndarray, tail_width: int) -> list[tuple[str, int, int]]:
    """Split levels into ('level', l, l+1) launches and ('tail', l0, l1) runs of narrow levels."""
    segs = []
    l, nl = 0, len(widths)
    while l < nl:
        if tail_width > 0 and widths[l] <= tail_width:
            l1 = l
            while l1 < nl and widths[l1] <= tail_width:
                l1 += 1
            if l1 - l >= 2:
                segs.append(("tail", l, l1))
                l = l1
                continue
        segs.append(("level", l, l + 1))
        l += 1
    return segs


class DeviceLDLT:
    """A CHOLMOD LDL^T factor on a Warp device; ``apply(r, z, dR)`` only launches kernels."""

    def __init__(self, device, *, lanes: int | None = None, tail_width: int | None = None,
                 tail_block: int | None = None, cols_lanes: int | None = None):
        self.device = wp.get_device(device)
        cuda = self.device.is_cuda
        self.lanes = int(lanes if lanes is not None else (32 if cuda else 1))
        if self.lanes not in (1, 2, 4, 8, 16, 32) or (not cuda and self.lanes != 1):
            raise ValueError(f"lanes must be 1 (CPU) or a power of two up to 32 on CUDA, got {self.lanes}")
        self.tail_block = int(tail_block if tail_block is not None else (512 if cuda else 1))
        if not cuda:
            self.tail_block = self.lanes  # one warp of one thread: sequential, no barrier needed
        if self.tail_block % self.lanes:
            raise ValueError("tail_block must be a multiple of lanes")
        if cuda and not 32 <= self.tail_block <= 512:
            # 1024 threads failed to launch on an H100 (CUDA error 701: too many registers requested)
            raise ValueError(f"tail_block must be 32..512 threads on CUDA, got {self.tail_block}")
        self.tail_width = int(tail_width if tail_width is not None else (self.tail_block // self.lanes if cuda else 0))
        self.structure: FactorStructure | None = None
        self.pattern_version = 0  # bumped when the arrays are reallocated (a captured graph is stale)
        self.factor_count = 0
        self.converted = False
        self._launches = {}
        # many right-hand sides (solve_columns): lanes per (group, column) pair, buffers per width
        self.cols_lanes = int(cols_lanes if cols_lanes is not None else (32 if cuda else 1))
        if self.cols_lanes not in (1, 2, 4, 8, 16, 32) or (not cuda and self.cols_lanes != 1):
            raise ValueError(f"cols_lanes must be 1 (CPU) or a power of two up to 32 on CUDA, got {self.cols_lanes}")
        if cuda and self.tail_block % self.cols_lanes:
            raise ValueError("tail_block must be a multiple of cols_lanes")
        self._col_bufs = {}  # width -> buffers (kept across patterns while big enough) and launches
        self.column_solves = 0  # solve_columns calls (chunks)
        self.raw = None

    # ------------------------------------------------------------------ factor
    def set_factor(self, values: FactorValues) -> bool:
        """Install a factor. Same pattern: values copied in place (True). New pattern: reallocated."""
        s = values.structure
        d = self.device
        same = self.structure is not None and self.structure.pattern_id == s.pattern_id
        if not same:
            i32 = wp.int32
            self.structure = s
            self.pinv = wp.array(s.pinv, dtype=i32, device=d)
            self.lo_indices = wp.array(s.lo_indices, dtype=i32, device=d)
            self.up_indices = wp.array(s.up_indices, dtype=i32, device=d)
            self.fwd_ptr = wp.array(s.fwd_ptr.astype(np.int32), dtype=i32, device=d)
            self.bwd_ptr = wp.array(s.bwd_ptr.astype(np.int32), dtype=i32, device=d)
            self.fwd_meta = wp.array2d(s.fwd_meta, dtype=i32, device=d)
            self.bwd_meta = wp.array2d(s.bwd_meta, dtype=i32, device=d)
            self.fwd_coef_src = wp.array2d(s.fwd_coef_src.astype(np.int32), dtype=i32, device=d)
            self.bwd_coef_src = wp.array2d(s.bwd_coef_src.astype(np.int32), dtype=i32, device=d)
            self.fwd_coef = wp.zeros(s.fwd_coef_src.shape, dtype=wp.float64, device=d)
            self.bwd_coef = wp.zeros(s.bwd_coef_src.shape, dtype=wp.float64, device=d)
            self.lo_src = wp.array(s.lo_src.astype(np.int32), dtype=i32, device=d)
            self.up_src = wp.array(s.up_src.astype(np.int32), dtype=i32, device=d)
            n_raw = len(values.data)
            if getattr(self, "raw", None) is None or self.raw.shape[0] < n_raw:
                # with headroom, kept across patterns: a cut changes the pattern of every later
                # factor, and pinned host memory is slow to allocate
                cap = max(1, int(1.25 * n_raw))
                self.raw = wp.zeros(cap, dtype=wp.float64, device=d)
                # host staging for the factor's values (pinned on CUDA: an asynchronous copy)
                self._staging = wp.zeros(cap, dtype=wp.float64, device="cpu", pinned=d.is_cuda)
            self.lo_vals = wp.zeros(max(1, len(s.lo_indices)), dtype=wp.float64, device=d)
            self.up_vals = wp.zeros(max(1, len(s.up_indices)), dtype=wp.float64, device=d)
            self.y = wp.zeros(max(1, s.n), dtype=wp.float64, device=d)
            self.x = wp.zeros(max(1, s.n), dtype=wp.float64, device=d)
            self.fwd_segments = _segments(np.diff(s.fwd_ptr), self.tail_width)
            self.bwd_segments = _segments(np.diff(s.bwd_ptr), self.tail_width)
            self._launches = {}
            self.pattern_version += 1
        n_raw = len(values.data)
        if n_raw:
            if self.device.is_cuda:
                wp.synchronize_stream(self.device.stream)  # the staging buffer's last copy is done
            self._staging.numpy()[:n_raw] = values.data
            wp.copy(self.raw, self._staging, count=n_raw)
            if len(s.lo_indices):
                wp.launch(_gather_kernel, len(s.lo_indices), [self.raw, self.lo_src, self.up_src, self.lo_vals,
                                                              self.up_vals], device=d)
            if s.n_groups:
                wp.launch(_gather_coef_kernel, s.fwd_coef_src.shape, [self.raw, self.fwd_coef_src, 3, self.fwd_coef],
                          device=d)
                wp.launch(_gather_coef_kernel, s.bwd_coef_src.shape, [self.raw, self.bwd_coef_src, 3, self.bwd_coef],
                          device=d)
        self.factor_count += 1
        self.converted = values.converted
        return same

    @property
    def n_nodes(self) -> int:
        return 0 if self.structure is None else self.structure.n // 3

    def launches_per_apply(self) -> int:
        return len(self.fwd_segments) + len(self.bwd_segments) + 1 if self.structure is not None else 0

    def graph_key(self) -> tuple:
        return (self.pattern_version, self.lanes, self.tail_width, self.tail_block)

    # ------------------------------------------------------------------- apply
    def _record(self, r: wp.array, z: wp.array, dR: wp.array) -> list:
        s, d, L = self.structure, self.device, self.lanes
        bd = 256 if L > 1 else 128
        cmds = []
        for kind, l0, l1 in self.fwd_segments:
            if kind == "level":
                a, b = int(s.fwd_ptr[l0]), int(s.fwd_ptr[l1])
                cmds.append(wp.launch(
                    _forward_level_kernel, (b - a) * L,
                    [a, L, self.fwd_meta, self.fwd_coef, self.lo_indices, self.lo_vals, r, dR, self.y],
                    device=d, block_dim=bd, record_cmd=True))
            else:
                cmds.append(wp.launch(
                    _forward_tail_kernel, self.tail_block,
                    [self.fwd_ptr, l0, l1, L, self.fwd_meta, self.fwd_coef, self.lo_indices, self.lo_vals, r, dR,
                     self.y], device=d, block_dim=self.tail_block, record_cmd=True))
        for kind, l0, l1 in self.bwd_segments:
            if kind == "level":
                a, b = int(s.bwd_ptr[l0]), int(s.bwd_ptr[l1])
                cmds.append(wp.launch(
                    _backward_level_kernel, (b - a) * L,
                    [a, L, self.bwd_meta, self.bwd_coef, self.up_indices, self.up_vals, self.y, self.x],
                    device=d, block_dim=bd, record_cmd=True))
            else:
                cmds.append(wp.launch(
                    _backward_tail_kernel, self.tail_block,
                    [self.bwd_ptr, l0, l1, L, self.bwd_meta, self.bwd_coef, self.up_indices, self.up_vals, self.y,
                     self.x], device=d, block_dim=self.tail_block, record_cmd=True))
        cmds.append(wp.launch(_rotate_out_kernel, s.n // 3, [self.pinv, self.x, dR, z], device=d, record_cmd=True))
        return cmds

    def apply(self, r: wp.array, z: wp.array, dR: wp.array) -> None:
        """z = dR P^T L^-T D^-1 L^-1 P dR^T r (launches only: no host synchronisation)."""
        if self.structure is None:
            raise RuntimeError("no factor installed")
        if 3 * r.shape[0] != self.structure.n or z.shape[0] != r.shape[0] or dR.shape[0] != r.shape[0]:
            raise ValueError(f"device factor is for {self.structure.n} DOFs, got vectors of {3 * r.shape[0]}")
        key = (r.ptr, z.ptr, dR.ptr, r.shape[0])
        cmds = self._launches.get(key)
        if cmds is None:
            if len(self._launches) > 8:
                self._launches.clear()
            cmds = self._launches[key] = self._record(r, z, dR)
        for c in cmds:
            c.launch()

    # ---------------------------------------------------- many right-hand sides
    COLUMN_WIDTHS = (4, 8, 16, 32, 64, 128, 256)

    def max_columns(self) -> int:
        """The widest block solved in one go: at most 256 columns, and about 32M values per buffer."""
        n = max(1, self.structure.n if self.structure is not None else 1)
        fit = [w for w in self.COLUMN_WIDTHS if w * n <= 32_000_000]
        return fit[-1] if fit else self.COLUMN_WIDTHS[0]

    def _col_segments(self, ptr: np.ndarray, width: int) -> list[tuple[str, int, int]]:
        """Levels whose (group, column) pairs fit twice in the tail block's warps run merged."""
        if not self.device.is_cuda:
            return _segments(np.diff(ptr), 0)
        pairs = 2 * (self.tail_block // self.cols_lanes)
        return _segments(np.diff(ptr), max(0, pairs // width))

    def _col_buffers(self, width: int):
        """Buffers of (rows, width), rows >= the factor's DOFs (the kernels touch only those): kept
        across factor patterns while big enough; the launches are recorded again per pattern."""
        buf = self._col_bufs.get(width)
        s, d = self.structure, self.device
        if buf is None or buf["rows"] < s.n:
            rows = max(1, int(1.25 * s.n))
            shape = (rows, width)
            buf = {
                "rows": rows, "pattern": -1,
                "B": wp.zeros(shape, dtype=wp.float64, device=d), "y": wp.zeros(shape, dtype=wp.float64, device=d),
                "x": wp.zeros(shape, dtype=wp.float64, device=d), "out": wp.zeros(shape, dtype=wp.float64, device=d),
                "in": wp.zeros(shape, dtype=wp.float64, device="cpu", pinned=d.is_cuda),
                "back": wp.zeros(shape, dtype=wp.float64, device="cpu", pinned=d.is_cuda),
            }
            self._col_bufs[width] = buf
        if buf["pattern"] != self.pattern_version:
            buf["cmds"] = self._record_cols(buf, width)
            buf["pattern"] = self.pattern_version
        return buf

    def _record_cols(self, buf, width: int) -> list:
        s, d, L = self.structure, self.device, self.cols_lanes
        bd = 256 if L > 1 else 128
        tb = self.tail_block if d.is_cuda else 1
        cmds = []
        for kind, l0, l1 in self._col_segments(s.fwd_ptr, width):
            if kind == "level":
                a, b = int(s.fwd_ptr[l0]), int(s.fwd_ptr[l1])
                cmds.append(wp.launch(
                    _forward_level_cols_kernel, _whole_warps((b - a) * width * L, d),
                    [a, L, width, (b - a) * width, self.fwd_meta, self.fwd_coef, self.lo_indices, self.lo_vals, buf["B"], buf["y"]],
                    device=d, block_dim=bd, record_cmd=True))
            else:
                cmds.append(wp.launch(
                    _forward_tail_cols_kernel, tb,
                    [self.fwd_ptr, l0, l1, L, width, self.fwd_meta, self.fwd_coef, self.lo_indices, self.lo_vals,
                     buf["B"], buf["y"]], device=d, block_dim=tb, record_cmd=True))
        for kind, l0, l1 in self._col_segments(s.bwd_ptr, width):
            if kind == "level":
                a, b = int(s.bwd_ptr[l0]), int(s.bwd_ptr[l1])
                cmds.append(wp.launch(
                    _backward_level_cols_kernel, _whole_warps((b - a) * width * L, d),
                    [a, L, width, (b - a) * width, self.bwd_meta, self.bwd_coef, self.up_indices, self.up_vals, buf["y"], buf["x"]],
                    device=d, block_dim=bd, record_cmd=True))
            else:
                cmds.append(wp.launch(
                    _backward_tail_cols_kernel, tb,
                    [self.bwd_ptr, l0, l1, L, width, self.bwd_meta, self.bwd_coef, self.up_indices, self.up_vals,
                     buf["y"], buf["x"]], device=d, block_dim=tb, record_cmd=True))
        cmds.append(wp.launch(_unpermute_cols_kernel, (s.n, width), [self.pinv, buf["x"], buf["out"]], device=d,
                              record_cmd=True))
        return cmds

    def column_launches(self, ncols: int) -> int:
        """Kernel launches of one block solve of ``ncols`` columns (one chunk)."""
        w = next((w for w in self.COLUMN_WIDTHS if w >= ncols), self.COLUMN_WIDTHS[-1])
        s = self.structure
        return len(self._col_segments(s.fwd_ptr, w)) + len(self._col_segments(s.bwd_ptr, w)) + 1

    def solve_columns(self, B: np.ndarray) -> np.ndarray:
        """X = A^-1 B = P^T L^-T D^-1 L^-1 P B for a block of host columns (no rotation), host in
        and out: every level is one launch for all the columns (each (group, column) pair is
        solved by ``cols_lanes`` threads), so a block costs about what one column does -- the
        columns of U (cutting, eq. 6) and of W (contact, eq. 4) in batches. Blocks wider than
        :meth:`max_columns` go in chunks; a chunk is padded with zero columns to the next
        width in ``COLUMN_WIDTHS`` (one recorded launch sequence per width and pattern)."""
        if self.structure is None:
            raise RuntimeError("no factor installed")
        B = np.asarray(B, dtype=np.float64)
        vec = B.ndim == 1
        if vec:
            B = B[:, None]
        n = self.structure.n
        if B.ndim != 2 or B.shape[0] != n:
            raise ValueError(f"device factor is for {n} DOFs, got a block of shape {B.shape}")
        c = B.shape[1]
        X = np.empty((n, c))
        step = self.max_columns()
        for j0 in range(0, c, step):
            j1 = min(c, j0 + step)
            k = j1 - j0
            width = next(w for w in self.COLUMN_WIDTHS if w >= k)
            buf = self._col_buffers(width)
            if self.device.is_cuda:
                wp.synchronize_stream(self.device.stream)  # the staging buffers' last copies are done
            stage = buf["in"].numpy()
            stage[:n, :k] = B[:, j0:j1]
            stage[:n, k:] = 0.0
            wp.copy(buf["B"], buf["in"], count=n * width)
            for cmd in buf["cmds"]:
                cmd.launch()
            wp.copy(buf["back"], buf["out"], count=n * width)
            if self.device.is_cuda:
                wp.synchronize_stream(self.device.stream)
            X[:, j0:j1] = buf["back"].numpy()[:n, :k]
            self.column_solves += 1
        return X[:, 0] if vec else X
