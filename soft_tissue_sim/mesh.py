"""Linear tetrahedral meshes: validation, meshio I/O, surface extraction, generators.

Conventions: ``points`` (n, 3) float64, ``tets`` (m, 4) int32 positively oriented
(``det[x1-x0, x2-x0, x3-x0] > 0``), ``material_ids`` (m,) int32. Pure numpy + meshio.
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "MeshError",
    "TetMesh",
    "tet_quality",
    "centroids",
    "interior_faces",
    "interior_faces_after_split",
    "interior_faces_after_removal",
    "edge_table",
    "edge_table_after_change",
    "node_ring",
    "validate_mesh",
    "load_mesh",
    "save_mesh",
    "grid_mesh",
    "beam_mesh",
    "brain_mesh",
    "cli",
]

# Faces of a positively oriented tet (local indices), each with its right-hand normal outward.
_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)
_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)
_MATERIAL_KEYS = ("material_id", "material", "gmsh:physical", "medit:ref", "MaterialIds")
# meshio cell types that fill volume; anything else (triangle, line, vertex...) is ignored on load.
_VOLUME_TYPES = ("tetra", "hexahedron", "wedge", "pyramid")


class MeshError(ValueError):
    """A mesh (or mesh file) is unusable; the message names the problem and the cells."""


def unique_rows(rows: np.ndarray, **kw):
    """``np.unique(rows, axis=0, **kw)`` for rows of non-negative integers, as fast as a 1-D
    unique: each row is packed into one int64 key (mixed radix, so the keys sort like the rows)
    when that cannot overflow; the general (structured, several times slower) path otherwise.
    Same outputs as ``np.unique(..., axis=0)``: unique rows (sorted), then index, inverse,
    counts as asked."""
    rows = np.asarray(rows)
    w = rows.shape[1] if rows.ndim == 2 else 0
    base = int(rows.max()) + 1 if rows.size else 1
    if w == 0 or rows.min(initial=0) < 0 or base ** w >= 2**62:
        return np.unique(rows, axis=0, **kw)
    key = np.zeros(len(rows), np.int64)
    for c in range(w):
        key = key * base + rows[:, c].astype(np.int64)
    out = np.unique(key, **kw)
    if not isinstance(out, tuple):
        out = (out,)
    uk, rest = out[0], list(out[1:])
    uniq = np.empty((len(uk), w), dtype=rows.dtype)
    for c in range(w - 1, -1, -1):
        uk, uniq[:, c] = np.divmod(uk, base)
    return (uniq, *rest) if rest else uniq


_NEXT, _AFTER = np.array([1, 2, 0]), np.array([2, 0, 1])  # the components j + 1 and j + 2 (mod 3) of each j


def cross(u: np.ndarray, v: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Row-wise cross products of (..., 3) arrays (broadcast): the products and differences of
    ``np.cross``, u_{j+1} v_{j+2} - u_{j+2} v_{j+1}, on whole arrays of permuted components,
    without its per-call overhead (which dominates on the few rows of a contact step or a
    blade's tets). ``out``: where to write them (not overlapping u or v), else a new array."""
    out = np.multiply(u.take(_NEXT, axis=-1), v.take(_AFTER, axis=-1), out=out)
    out -= u.take(_AFTER, axis=-1) * v.take(_NEXT, axis=-1)
    return out


def interior_faces(tets: np.ndarray):
    """The interior faces of tets (m, 4): (f, 2) the two tets sharing each (lower index first),
    (f, 3) its nodes (ascending), and (m, 4) the face of each tet opposite its node k
    (``_FACES[k]``) as an index into those, -1 on the boundary; int64, faces sorted by their
    node triples."""
    tets = np.asarray(tets, dtype=np.int64)
    m = len(tets)
    f0, f1, f2 = (tets[:, _FACES[:, j]].ravel() for j in range(3))  # entry 4 t + k: face k of tet t
    lo, hi = np.minimum(np.minimum(f0, f1), f2), np.maximum(np.maximum(f0, f1), f2)
    key = np.stack([lo, f0 + f1 + f2 - lo - hi, hi], axis=1)  # each face's nodes, ascending
    base = int(hi.max()) + 1 if m else 1
    if base**3 < 2**62:  # one packed int64 key per face, sorted stably: the order of the lexsort
        packed = (lo * base + key[:, 1]) * base + hi
        order = np.argsort(packed, kind="stable")
        ps = packed[order]
        first = np.flatnonzero(ps[1:] == ps[:-1])
    else:
        order = np.lexsort(key.T[::-1])
        ks = key[order]
        first = np.flatnonzero(np.all(ks[1:] == ks[:-1], axis=1))
    a, b = order[first], order[first + 1]
    tet_face = np.full(4 * m, -1, np.int64)
    tet_face[a] = tet_face[b] = np.arange(len(first))
    return np.stack([a // 4, b // 4], axis=1), key[a], tet_face.reshape(m, 4)


def interior_faces_after_split(faces, tets: np.ndarray, new_tets: np.ndarray, copy_of: np.ndarray):
    """:func:`interior_faces` of ``new_tets`` (m, 4), derived from ``faces``, the table of
    ``tets`` (m, 4): the same tets, some of whose nodes were replaced by copies (a node
    split); ``copy_of`` (n_new,) gives the node each node copies (an old node: itself).

    Two tets that share three nodes now shared their originals before, so no face becomes
    interior; a face stays interior where both of its tets still see the same three nodes; a
    face away from the changed tets keeps its nodes. So only the faces of the changed tets are
    looked at, and the changed ones are merged into the sorted order of the others. None where
    ``new_tets`` is no such split of ``tets``, or where packed face keys could overflow (then
    compute the table afresh)."""
    pairs, fnodes, tet_face = faces
    tets, new_tets = np.asarray(tets, np.int64), np.asarray(new_tets, np.int64)
    copy_of = np.asarray(copy_of, np.int64)
    base = int(new_tets.max()) + 1 if len(new_tets) else 1
    if (base**3 >= 2**62 or tets.shape != new_tets.shape or len(copy_of) < base
            or not np.array_equal(np.take(copy_of, new_tets), tets)):
        return None
    changed = np.flatnonzero((tets != new_tets).view(np.uint32))  # a row's 4 flags as one word
    f = np.take(tet_face, changed, axis=0).ravel()
    f = np.unique(f[f >= 0])  # the faces of the changed tets
    seen = []
    for side in (0, 1):  # the face's nodes as each of its two tets sees them now, ascending
        t = pairs[f, side]
        k = np.argmax(tet_face[t] == f[:, None], axis=1)  # the face's local index in that tet
        seen.append(np.sort(new_tets[t[:, None], _FACES[k]], axis=1))
    stays = np.all(seen[0] == seen[1], axis=1)
    moved, moved_nodes = f[stays], seen[0][stays]

    def packed(tri):
        return (tri[:, 0] * base + tri[:, 1]) * base + tri[:, 2]

    others = np.ones(len(pairs), bool)
    others[f] = False  # faces whose nodes are unchanged: still in sorted order
    ko, km = packed(fnodes)[others], packed(moved_nodes)
    om = np.argsort(km)
    moved, moved_nodes, km = moved[om], moved_nodes[om], km[om]
    slot_m = np.searchsorted(ko, km) + np.arange(len(km))  # merged positions
    is_m = np.zeros(len(ko) + len(km), bool)
    is_m[slot_m] = True
    slot_o = np.flatnonzero(~is_m)
    src = np.empty(len(is_m), np.int64)  # the old face at each new position
    src[slot_o], src[slot_m] = np.flatnonzero(others), moved
    new_nodes = np.take(fnodes, src, axis=0)
    new_nodes[slot_m] = moved_nodes
    new_id = np.full(len(pairs) + 1, -1, np.int64)  # old face -> new face (last: the boundary, -1)
    new_id[src] = np.arange(len(src))
    return np.take(pairs, src, axis=0), new_nodes, np.take(new_id, tet_face)


def interior_faces_after_removal(faces, kept_tets: np.ndarray, kept_nodes: np.ndarray, n_nodes: int):
    """:func:`interior_faces` of a mesh that keeps the tets ``kept_tets`` (mask) and the nodes
    ``kept_nodes`` (ascending indices) of a mesh of ``n_nodes`` nodes with table ``faces``,
    both renumbered in order (element removal): the faces whose two tets are kept, renumbered.
    The renumberings keep the order of tets and of nodes, so the faces stay sorted."""
    pairs, fnodes, tet_face = faces
    node_id = np.full(n_nodes, -1, np.int64)
    node_id[kept_nodes] = np.arange(len(kept_nodes))
    tet_id = np.cumsum(kept_tets) - 1
    keep = np.take(kept_tets, pairs[:, 0]) & np.take(kept_tets, pairs[:, 1])
    new_id = np.full(len(pairs) + 1, -1, np.int64)  # old face -> new face (last: the boundary, -1)
    new_id[np.flatnonzero(keep)] = np.arange(int(keep.sum()))
    return (np.take(tet_id, np.compress(keep, pairs, axis=0)), np.take(node_id, np.compress(keep, fnodes, axis=0)),
            np.take(new_id, np.compress(kept_tets, tet_face, axis=0)))


def extent(points: np.ndarray) -> float:
    """The longest side of the points' bounding box, ``np.ptp(points, axis=0).max()``, reduced
    one coordinate column at a time (a reduction across the short rows is many times slower)."""
    return max(float(c.max() - c.min()) for c in np.asarray(points).T)


def all_four(mask: np.ndarray) -> np.ndarray:
    """(k,) whether each row of the boolean ``mask`` (k, 4) is all True: a row's 4 flags (made
    C-ordered) read as one 32-bit word, cheaper than a reduction across short rows."""
    return np.ascontiguousarray(mask, dtype=bool).reshape(-1, 4).view(np.uint32)[:, 0] == 0x01010101


def insert_rows(a: np.ndarray, pos: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``np.insert(a, pos, rows, axis=0)`` for non-decreasing positions ``pos``: each row of
    ``a`` (n, ...) and of ``rows`` (k, ...) moved as one item (a row of several numbers as one
    opaque record), so the copy is a 1-D masked one rather than a row-by-row one."""
    a = np.ascontiguousarray(a)
    width = int(np.prod(a.shape[1:], dtype=np.int64))
    item = np.dtype((np.void, a.dtype.itemsize * width))
    rows = np.ascontiguousarray(rows, dtype=a.dtype).reshape(len(pos), width)
    slots = np.asarray(pos, np.int64) + np.arange(len(pos))
    old = np.ones(len(a) + len(pos), bool)
    old[slots] = False
    out = np.empty(len(old), item)
    out[slots] = rows.view(item).ravel()
    out[old] = a.reshape(len(a), width).view(item).ravel()
    return out.view(a.dtype).reshape((len(old),) + a.shape[1:])


def _edge_keys(tets: np.ndarray, base: int) -> np.ndarray:
    """(6 m,) the packed keys lo * base + hi of the 6 edges of each tet (m, 4), tet-major."""
    T = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
    a, b = T[:, _EDGES[:, 0]].ravel(), T[:, _EDGES[:, 1]].ravel()
    return np.minimum(a, b) * base + np.maximum(a, b)


def edge_table(tets: np.ndarray):
    """The edges of tets (m, 4): (e, 2) int64 unique edges, each as (i, j) with i < j, rows
    sorted, and (e,) int64 how many tets have each (what lets a change of a few tets update the
    table: :func:`edge_table_after_change`)."""
    T = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
    base = int(T.max()) + 1 if len(T) else 1
    if base * base >= 2**62:
        e, counts = unique_rows(np.sort(T[:, _EDGES].reshape(-1, 2), axis=1), return_counts=True)
        return e.astype(np.int64), counts.astype(np.int64)
    key = _edge_keys(T, base)  # one packed key per edge: sorted as the rows are
    key.sort()
    first = np.flatnonzero(np.concatenate(([True], key[1:] != key[:-1]))) if len(key) else np.zeros(0, np.int64)
    counts = np.diff(np.append(first, len(key)))
    key = key[first]
    return np.stack([key // base, key % base], axis=1), counts


def edge_table_after_change(table, removed_tets: np.ndarray, added_tets: np.ndarray, node_id: np.ndarray,
                            n_nodes: int):
    """:func:`edge_table` of a mesh made from one whose table is ``table`` by taking out the tets
    ``removed_tets`` (k, 4) (old numbering), renumbering the nodes by ``node_id`` (old -> new,
    -1: dropped) and putting in the tets ``added_tets`` (j, 4) (new numbering, ``n_nodes``
    nodes): a removal, a node split, a subdivision. An edge's count drops by the removed tets
    that have it (gone at 0) and rises by the added ones (new where it was not there); a
    renumbering that keeps the nodes' order keeps the rows sorted, so only the new edges are
    merged in. None where the change does not fit the table (a removed edge it lacks, a kept
    edge at a dropped node, a renumbering that reorders the kept nodes) or packed keys could
    overflow: then compute the table afresh."""
    edges, counts = table
    node_id = np.asarray(node_id, np.int64)
    base = max(len(node_id), int(n_nodes), 1)
    kept_ids = node_id[node_id >= 0]
    if (base * base >= 2**62 or len(edges) and int(edges[:, 1].max()) >= len(node_id)
            or np.any(kept_ids[1:] <= kept_ids[:-1])):
        return None
    key = edges[:, 0] * base + edges[:, 1]
    rk = _edge_keys(removed_tets, base)
    pos = np.searchsorted(key, rk)
    if len(rk) and (pos.max() >= len(key) or np.any(key[pos] != rk)):
        return None
    counts = counts - np.bincount(pos, minlength=len(key))
    keep = counts > 0
    e = np.compress(keep, edges, axis=0)
    c = counts[keep]
    if np.any(counts < 0):
        return None
    if len(node_id) == len(kept_ids) and (not len(kept_ids) or kept_ids[-1] == len(kept_ids) - 1):
        key = key[keep]  # no node renumbered (the ids ascend from 0 without a gap): the keys stay
    else:
        e = np.take(node_id, e)  # rows stay sorted: the order of the nodes is kept
        if len(e) and e.min() < 0:
            return None
        key = e[:, 0] * base + e[:, 1]
    if len(added_tets):
        ak, acount = np.unique(_edge_keys(added_tets, base), return_counts=True)
        pos = np.searchsorted(key, ak)
        found = pos < len(key)
        found[found] = key[pos[found]] == ak[found]
        c[pos[found]] += acount[found]
        new = ~found
        if new.any():
            ak = ak[new]
            e = insert_rows(e, pos[new], np.stack([ak // base, ak % base], axis=1))
            c = insert_rows(c, pos[new], acount[new])
    return e, c


def node_ring(edges: np.ndarray, n_nodes: int):
    """The neighbours of each node through the edges (e, 2) (unique, i < j, rows sorted, as
    :func:`edge_table` gives them) in compressed rows: (n + 1,) offsets and the neighbours of
    node i, ascending, at [offsets[i], offsets[i + 1]) (int32; the sorted CSR of the symmetric
    adjacency). A node's lower neighbours are the edges ending at it and its higher ones the
    edges starting at it, each already in order, so no sort of the whole adjacency is needed:
    only a stable sort of the edges by their upper node (a radix sort where node ids fit 16 bits)."""
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    lo, hi = edges[:, 0], edges[:, 1]
    n_low, n_high = np.bincount(hi, minlength=n_nodes), np.bincount(lo, minlength=n_nodes)
    offsets = np.zeros(n_nodes + 1, np.int64)
    np.cumsum(n_low + n_high, out=offsets[1:])
    ring = np.empty(2 * len(edges), np.int32)
    i = np.arange(len(edges))
    # higher neighbours: the rows are sorted by lo, then hi; a run of one lo goes after the lower ones
    ring[np.take(offsets[:-1] + n_low - (np.cumsum(n_high) - n_high), lo) + i] = hi
    # lower neighbours: the edges sorted by hi (stable: lo stays ascending), each run first in its row
    o = np.argsort(hi.astype(np.uint16) if n_nodes <= 1 << 16 else hi, kind="stable")
    ring[np.take(offsets[:-1] - (np.cumsum(n_low) - n_low), hi[o]) + i] = lo[o]
    return offsets.astype(np.int32), ring


def ring_components(offsets: np.ndarray, ring: np.ndarray, n_nodes: int) -> np.ndarray:
    """(n,) int32 connected parts of the symmetric adjacency ``offsets``, ``ring`` (compressed
    rows, as :func:`node_ring` gives them), numbered in the order of their lowest node: the
    labels of ``scipy.sparse.csgraph.connected_components(..., directed=False)``. The graph is
    symmetric, so it is its own transpose: scipy's undirected traversal is run on it directly,
    without the matrix, its validation and the transpose that the public function builds
    (the public function where that traversal is not available)."""
    offsets = np.ascontiguousarray(offsets, np.int32)
    ring = np.ascontiguousarray(ring, np.int32)
    if _undirected_traversal is None:
        import scipy.sparse as sps
        from scipy.sparse.csgraph import connected_components

        g = sps.csr_matrix((np.ones(len(ring)), ring, offsets), shape=(n_nodes, n_nodes))
        return connected_components(g, directed=False)[1].astype(np.int32)
    labels = np.empty(n_nodes, np.int32)
    _undirected_traversal(ring, offsets, ring, offsets, labels)
    return labels


def edge_components(n: int, ea: np.ndarray, eb: np.ndarray) -> np.ndarray:
    """(n,) int32 connected parts of the undirected graph of ``n`` vertices and edges (ea[i],
    eb[i]), numbered in the order of their lowest vertex (scipy's labels): the symmetric
    adjacency in compressed rows, then :func:`ring_components`."""
    ea, eb = np.asarray(ea, np.int64), np.asarray(eb, np.int64)
    src, dst = np.concatenate([ea, eb]), np.concatenate([eb, ea])
    order = np.argsort(src, kind="stable")
    offsets = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(src, minlength=n), out=offsets[1:])
    return ring_components(offsets, dst[order], n)


try:  # scipy's traversal behind connected_components (undirected: each node's and its transpose's rows)
    from scipy.sparse.csgraph._traversal import _connected_components_undirected as _undirected_traversal
except ImportError:  # pragma: no cover - another scipy layout
    _undirected_traversal = None


def _list(idx, limit: int = 10) -> str:
    """'[3, 7, 9]' or '[0, 1, ..., 9] and 25 more (35 in all)'."""
    idx = [int(i) for i in np.asarray(idx).ravel()]
    if len(idx) <= limit:
        return str(idx)
    return f"{idx[:limit]} and {len(idx) - limit} more ({len(idx)} in all)"


@dataclass
class TetMesh:
    """A linear tetrahedral mesh (no validation here: use :func:`validate_mesh`)."""

    points: np.ndarray
    tets: np.ndarray
    material_ids: np.ndarray | None = None

    def __post_init__(self):
        self.points = np.ascontiguousarray(self.points, dtype=np.float64)
        self.tets = np.ascontiguousarray(self.tets, dtype=np.int32)
        if self.material_ids is None:
            self.material_ids = np.zeros(len(self.tets), dtype=np.int32)
        self.material_ids = np.ascontiguousarray(self.material_ids, dtype=np.int32)
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise MeshError(f"points must have shape (n, 3), got {self.points.shape}")
        if self.tets.ndim != 2 or self.tets.shape[1] != 4:
            raise MeshError(f"tets must have shape (m, 4), got {self.tets.shape}")
        if self.material_ids.shape != (len(self.tets),):
            raise MeshError(f"material_ids must have shape ({len(self.tets)},), got {self.material_ids.shape}")

    @property
    def n_nodes(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_tets(self) -> int:
        return int(self.tets.shape[0])

    def _tables(self) -> dict:
        """The tables of this mesh's connectivity computed so far (interior faces, edges, node
        ring, components), by name; a new, empty one once ``tets`` or the node count changed
        (it holds a copy of the tets it was made from)."""
        c = self.__dict__.get("_connectivity")
        if c is None or c[1] != self.n_nodes or not np.array_equal(c[0], self.tets):
            c = (self.tets.copy(), self.n_nodes, {})
            self._connectivity = c
        return c[2]

    @staticmethod
    def _frozen(arrays, dtype=np.int64) -> tuple:
        out = tuple(np.asarray(a, dtype) for a in arrays)
        for a in out:
            a.flags.writeable = False
        return out

    def _table(self, name: str, compute, dtype=np.int64) -> tuple:
        """The table ``name`` of this mesh's connectivity (a tuple of read-only ``dtype`` arrays):
        cached, else ``compute()`` cached."""
        tables = self._tables()
        if name not in tables:
            tables[name] = self._frozen(compute(), dtype)
        return tables[name]

    def interior_faces(self):
        """:func:`interior_faces` of this mesh, computed once per connectivity (the cache holds a
        copy of the tets it was made from, so a changed ``tets`` is recomputed). Read-only arrays."""
        return self._table("interior_faces", lambda: interior_faces(self.tets))

    def cached_interior_faces(self):
        """:meth:`interior_faces` where already computed for the current tets, else None."""
        return self._tables().get("interior_faces")

    def set_interior_faces(self, faces) -> None:
        """Install ``faces``, this mesh's :func:`interior_faces` known otherwise (derived from
        the mesh it was made from), as the cache of :meth:`interior_faces`."""
        self._tables()["interior_faces"] = self._frozen(faces)

    def edge_table(self):
        """:func:`edge_table` of this mesh (edges and their tet counts), computed once per
        connectivity like :meth:`interior_faces`. Read-only arrays."""
        return self._table("edge_table", lambda: edge_table(self.tets))

    def cached_edge_table(self):
        """:meth:`edge_table` where already computed (or installed) for the current tets, else None."""
        return self._tables().get("edge_table")

    def set_edge_table(self, table) -> None:
        """Install ``table``, this mesh's :func:`edge_table` known otherwise (derived from the
        mesh it was made from, :func:`edge_table_after_change`), as the cache of :meth:`edge_table`."""
        self._tables()["edge_table"] = self._frozen(table)

    def node_ring(self):
        """:func:`node_ring` of this mesh's edges: (n + 1,) offsets and the sorted neighbours of
        each node (int32, read-only), once per connectivity."""
        return self._table("node_ring", lambda: node_ring(self.edge_table()[0], self.n_nodes), np.int32)

    def copy(self) -> "TetMesh":
        return TetMesh(self.points.copy(), self.tets.copy(), self.material_ids.copy())

    def signed_volumes(self) -> np.ndarray:
        """(m,) signed volumes, det[x1-x0, x2-x0, x3-x0] / 6."""
        return _signed_volumes(self.points, self.tets)

    def centroids(self) -> np.ndarray:
        """(m, 3) tet centroids."""
        return centroids(self.points, self.tets)

    def node_components(self) -> np.ndarray:
        """(n,) label of each node's connected part (nodes joined through shared tets; a node
        in no tet is a part of its own). A tet's part is the label of any of its nodes. The
        parts are numbered in the order of their lowest node (scipy's numbering), once per
        connectivity, from the node ring (the same parts as the tets make). Read-only."""
        return self._table("node_components", lambda: (ring_components(*self.node_ring(), self.n_nodes),),
                           np.int32)[0]

    def boundary_faces(self) -> np.ndarray:
        """(k, 3) int32 faces used by exactly one tet, right-hand normal pointing out of it."""
        tet_face = self.interior_faces()[2]  # cached per connectivity (cutting reads it too)
        k = np.flatnonzero(tet_face.ravel() < 0)  # 4 t + j: face j of tet t, in that order
        j = k & 3
        return self.tets.ravel().take((k - j)[:, None] + _FACES[j])  # entries 4 t + _FACES[j] of the flat tets

    def edges(self) -> np.ndarray:
        """(e, 2) unique edges, each as (i, j) with i < j, rows sorted (int32; from
        :meth:`edge_table`)."""
        return self.edge_table()[0].astype(np.int32)


def centroids(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(m, 3) centroids of the tets (m, 4) of ``points`` (n, 3): the numbers of
    ``points[tets].mean(axis=1)`` (the same sums in the same order, then / 4) without
    gathering the (m, 4, 3) block."""
    T = np.asarray(tets).T
    return (((points[T[0]] + points[T[1]]) + points[T[2]]) + points[T[3]]) / 4.0


def _signed_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    x = np.asarray(points, dtype=np.float64)[np.asarray(tets)]
    d = x[:, 1:] - x[:, :1]  # rows: x1-x0, x2-x0, x3-x0
    return np.einsum("ij,ij->i", d[:, 0], np.cross(d[:, 1], d[:, 2])) / 6.0


def tet_quality(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(m,) shape quality 6*sqrt(2)*V / l_rms^3: 1 regular, 0 flat, < 0 inverted (scale free)."""
    points = np.asarray(points, dtype=np.float64)
    tets = np.asarray(tets).reshape(-1, 4)
    x = points[tets]
    e = x[:, _EDGES[:, 1]] - x[:, _EDGES[:, 0]]
    l_rms = np.sqrt(np.einsum("ijk,ijk->i", e, e) / 6.0)
    vol = _signed_volumes(points, tets)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = 6.0 * math.sqrt(2.0) * vol / l_rms**3
    return np.where(l_rms > 0.0, q, 0.0)


def validate_mesh(points, tets, material_ids=None, *, min_quality: float = 1e-6) -> TetMesh:
    """Check a mesh and return a clean :class:`TetMesh`; raise :class:`MeshError` naming the bad cells.

    Nodes used by no tet are dropped (with a warning) and tet indices remapped.
    """
    try:
        points = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise MeshError(f"points are not numeric: {e}") from None
    if points.ndim != 2 or points.shape[1] != 3:
        raise MeshError(f"points must have shape (n, 3), got {points.shape}")
    tets = np.asarray(tets)
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise MeshError(f"tets must have shape (m, 4), got {tets.shape}")
    if tets.shape[0] == 0:
        raise MeshError("mesh has no tetrahedra")
    if tets.dtype.kind not in "iu":
        if tets.dtype.kind != "f" or not np.all(np.isfinite(tets)) or np.any(tets != np.round(tets)):
            raise MeshError(f"tet node indices must be integers, got dtype {tets.dtype}")
    tets = tets.astype(np.int64)
    m = tets.shape[0]

    bad_nodes = np.flatnonzero(~np.all(np.isfinite(points), axis=1))
    if bad_nodes.size:
        raise MeshError(f"non-finite (NaN/inf) coordinates at nodes {_list(bad_nodes)}")
    bad = np.flatnonzero(np.any((tets < 0) | (tets >= len(points)), axis=1))
    if bad.size:
        raise MeshError(f"node index out of range [0, {len(points)}) in tets {_list(bad)}")
    s = np.sort(tets, axis=1)
    bad = np.flatnonzero(np.any(s[:, 1:] == s[:, :-1], axis=1))
    if bad.size:
        raise MeshError(f"repeated node inside one tet in tets {_list(bad)}")
    _, first, inv = unique_rows(s, return_index=True, return_inverse=True)
    bad = np.flatnonzero(first[inv.ravel()] != np.arange(m))
    if bad.size:
        raise MeshError(
            f"duplicated tets (same nodes as an earlier tet) {_list(bad)}; first copies {_list(first[inv.ravel()][bad])}"
        )

    if material_ids is None:
        mat = np.zeros(m, dtype=np.int32)
    else:
        mat = np.asarray(material_ids)
        if mat.ndim == 2 and mat.shape[1] == 1:
            mat = mat[:, 0]
        if mat.shape != (m,):
            raise MeshError(f"material_ids must have shape ({m},), got {mat.shape}")
        if mat.dtype.kind not in "iu":
            if mat.dtype.kind != "f" or not np.all(np.isfinite(mat)) or np.any(mat != np.round(mat)):
                raise MeshError(f"material ids must be integers, got dtype {mat.dtype}")
        if mat.size and (mat.min() < np.iinfo(np.int32).min or mat.max() > np.iinfo(np.int32).max):
            raise MeshError("material ids do not fit in int32")
        mat = mat.astype(np.int32)

    q = tet_quality(points, tets)
    degenerate = np.abs(q) < min_quality
    bad = np.flatnonzero(~degenerate & (q < 0.0))
    if bad.size:
        raise MeshError(f"inverted tets (negative volume) {_list(bad)}")
    bad = np.flatnonzero(degenerate)
    if bad.size:
        raise MeshError(f"degenerate tets (|quality| < {min_quality:g}) {_list(bad)}; min |quality| {np.abs(q).min():.3g}")

    used = np.zeros(len(points), dtype=bool)
    used[tets.ravel()] = True
    if not used.all():
        n_drop = int((~used).sum())
        warnings.warn(f"dropping {n_drop} node(s) used by no tetrahedron: {_list(np.flatnonzero(~used))}", stacklevel=2)
        remap = np.cumsum(used) - 1
        points, tets = points[used], remap[tets]
    return TetMesh(points.copy(), tets.astype(np.int32), mat)


def _empty_vtk_xml(path: Path) -> str | None:
    """'NumberOfPoints=0 ...' where a VTK XML file declares no points or no cells, else None."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 16).decode("latin-1")
    except OSError:
        return None
    import re

    pts = [int(v) for v in re.findall(r'NumberOfPoints="(\d+)"', head)]
    cells = [int(v) for v in re.findall(r'NumberOfCells="(\d+)"', head)]
    if (pts and sum(pts) == 0) or (cells and sum(cells) == 0):
        return f"NumberOfPoints={sum(pts)}, NumberOfCells={sum(cells)}"
    return None


def _read_error(path: Path, exc: BaseException, printed: str) -> MeshError:
    """A clear MeshError for a file meshio could not read: empty file, empty mesh, or meshio's
    own reasons per format it tried (which it prints, then exits)."""
    import meshio

    formats = meshio.extension_to_filetypes.get("".join(path.suffixes[-1:]).lower(), [])
    what = " or ".join(formats) if formats else "any format meshio knows (unknown suffix)"
    size = path.stat().st_size
    if size == 0:
        return MeshError(f"cannot read mesh file {path}: the file is empty (0 bytes)")
    empty = _empty_vtk_xml(path)
    if empty is not None:
        return MeshError(f"cannot read mesh file {path}: it holds an empty mesh ({empty}); a mesh needs "
                         f"points and tetrahedra")
    printed = printed.split("Error: Couldn't read")[0]  # meshio's own summary (wrapped by rich): dropped
    reasons = "; ".join(line.strip() for line in printed.splitlines() if line.strip())
    if isinstance(exc, SystemExit):
        with open(path, "rb") as fh:
            start = fh.read(32)
        detail = (f"meshio could not parse it as {what}" + (f" ({reasons})" if reasons else "")
                  + f"; it starts with {start!r}")
    else:
        detail = f"meshio failed reading it as {what}: {type(exc).__name__}: {exc}"
    return MeshError(f"cannot read mesh file {path} ({size} bytes): {detail}")


def load_mesh(path, material_key: str | None = None) -> TetMesh:
    """Read any meshio format; keep the 'tetra' blocks; material ids from cell data; validate.

    Raises FileNotFoundError for a missing file and :class:`MeshError` for one that cannot be
    read (empty file, empty mesh, not the format its suffix says), that holds no linear
    tetrahedra, or whose mesh fails :func:`validate_mesh`.
    """
    import contextlib
    import io

    import meshio

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file not found: {path}")
    printed = io.StringIO()
    try:  # meshio prints why each format failed, then calls sys.exit(1): keep both for the message
        with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
            raw = meshio.read(str(path))
    except (Exception, SystemExit) as e:  # meshio raises ReadError, ValueError..., or sys.exit(1)
        raise _read_error(path, e, printed.getvalue()) from None

    if len(raw.points) == 0 or sum(len(b.data) for b in raw.cells) == 0:
        raise MeshError(f"{path}: empty mesh ({len(raw.points)} points, "
                        f"{sum(len(b.data) for b in raw.cells)} cells); a mesh needs points and tetrahedra")
    types = [b.type for b in raw.cells]
    counts = {t: sum(len(b.data) for b in raw.cells if b.type == t) for t in dict.fromkeys(types)}
    have = ", ".join(f"{t} ({n})" for t, n in counts.items()) or "no cells"
    if "tetra10" in counts:
        raise MeshError(f"{path}: quadratic tetrahedra (tetra10) are not supported, only linear 'tetra'; file has {have}")
    other = [t for t in counts if t in _VOLUME_TYPES and t != "tetra"]
    if other:
        raise MeshError(f"{path}: only linear tetrahedra are supported, file also has {have}")
    if "tetra" not in counts:
        raise MeshError(f"{path}: no tetrahedra ('tetra' cells) in file; it has {have}")

    blocks = [i for i, t in enumerate(types) if t == "tetra"]
    tets = np.concatenate([raw.cells[i].data for i in blocks])
    if material_key is not None and material_key not in raw.cell_data:
        raise MeshError(f"{path}: no cell data {material_key!r}; it has {sorted(raw.cell_data)}")
    key = material_key or next((k for k in _MATERIAL_KEYS if k in raw.cell_data), None)
    mat = None
    if key is not None:
        parts = []
        for i in blocks:
            a = np.asarray(raw.cell_data[key][i])
            if a.ndim == 2 and a.shape[1] == 1:
                a = a[:, 0]
            if a.shape != (len(raw.cells[i].data),):
                raise MeshError(f"{path}: cell data {key!r} has shape {a.shape}, expected one value per tet")
            parts.append(a)
        mat = np.concatenate(parts)
    try:
        return validate_mesh(raw.points, tets, mat)
    except MeshError as e:
        raise MeshError(f"{path}: {e}") from None


def save_mesh(mesh: TetMesh, path, file_format: str | None = None) -> None:
    """Write with meshio (format from the suffix unless ``file_format``), cell data 'material_id'.

    '.msh' defaults to Gmsh 2.2 (meshio's 4.1 writer drops the physical tags); Gmsh files
    also get 'gmsh:physical' / 'gmsh:geometrical' set to the material id.
    """
    import meshio

    path = str(path)
    mat = np.asarray(mesh.material_ids, dtype=np.int32)
    cell_data = {"material_id": [mat]}
    if file_format is None and path.lower().endswith(".msh"):
        file_format = "gmsh22"
    if (file_format or "").startswith("gmsh"):
        cell_data["gmsh:physical"] = [mat]
        cell_data["gmsh:geometrical"] = [mat]
    out = meshio.Mesh(np.asarray(mesh.points, dtype=np.float64), [("tetra", np.asarray(mesh.tets, dtype=np.int32))],
                      cell_data=cell_data)
    meshio.write(path, out, file_format=file_format)


# ---------------------------------------------------------------------------- generators


SPLITS = ("mirrored", "uniform")


def _kuhn_corners() -> np.ndarray:
    """(6, 4, 3) corner bits of the Kuhn split of the unit cell: the tets (0, e_p0, e_p0 + e_p1,
    111) for the 6 axis permutations p, each ordered to be positively oriented."""
    tets = []
    for perm in itertools.permutations(range(3)):
        e0, e1 = np.eye(3, dtype=np.int64)[perm[0]], np.eye(3, dtype=np.int64)[perm[1]]
        c = [np.zeros(3, np.int64), e0, e0 + e1, np.ones(3, np.int64)]
        # the parity of the permutation decides the orientation of (0, e_p0, e_p0+e_p1, 111)
        odd = sum(perm[i] > perm[j] for i in range(3) for j in range(i + 1, 3)) % 2
        tets.append([c[0], c[1], c[3], c[2]] if odd else c)
    return np.array(tets)


def _grid_tets(shape: tuple[int, int, int], split: str = "mirrored") -> np.ndarray:
    """6 tets per cell of an (a, b, c)-node grid (node id = (i*b + j)*c + k), positively
    oriented for a right-handed grid mapping, cell-major (a cell's 6 tets are consecutive).

    ``uniform``: every cell split along its (0,0,0)-(1,1,1) diagonal (Kuhn). The same diagonal
    everywhere makes the mesh, and its stiffness, lean along (1,1,1): a beam loaded in a
    symmetry plane bends out of it.
    ``mirrored``: the Kuhn split of cell (i, j, k) mirrored along each axis whose cell index is
    odd. Neighbour cells are mirror images across their shared face, so the split is
    conforming (a face's diagonal is the same seen from both cells), and the whole mesh is
    symmetric under the mirror through the grid's mid-plane of any axis with an even number
    of cells (an odd number leaves a middle layer that no Kuhn split makes symmetric).
    """
    if split not in SPLITS:
        raise MeshError(f"split must be one of {', '.join(SPLITS)}, got {split!r}")
    a, b, c = shape
    ii, jj, kk = (g.ravel() for g in np.meshgrid(np.arange(a - 1), np.arange(b - 1), np.arange(c - 1), indexing="ij"))
    cell = np.stack([ii, jj, kk], axis=1).astype(np.int64)  # (cells, 3)
    corners = _kuhn_corners()  # (6, 4, 3)
    flip = (cell & 1) if split == "mirrored" else np.zeros_like(cell)
    bits = corners[None, :, :, :] ^ flip[:, None, None, :]  # mirrored corner bits per cell
    ijk = cell[:, None, None, :] + bits  # (cells, 6, 4, 3) grid indices of the corners
    tets = (ijk[..., 0] * b + ijk[..., 1]) * c + ijk[..., 2]
    odd = flip.sum(axis=1) % 2 == 1  # an odd number of mirrors reverses the orientation
    tets[odd] = tets[odd][:, :, [0, 2, 1, 3]]
    return tets.reshape(-1, 4).astype(np.int32)


def _positive(name: str, value) -> float:
    x = float(value)
    if not (math.isfinite(x) and x > 0.0):
        raise MeshError(f"{name} must be finite and > 0, got {value!r}")
    return x


def _count(name: str, value, low: int = 2) -> int:
    if isinstance(value, bool) or int(value) != value or int(value) < low:
        raise MeshError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(value)


def beam_mesh(n_long: int, n_cross: int = 5, length: float | None = None, width: float | None = None,
              spacing: float = 0.01, split: str = "mirrored") -> TetMesh:
    """Square beam, long axis x from 0 (clamped end) to ``length``, section centred on y = z = 0.

    ``n_long`` nodes along x, ``n_cross`` x ``n_cross`` in the section; ``length`` defaults to
    (n_long-1)*spacing, ``width`` to (n_cross-1)*spacing. Each hex cell is split into 6 tets
    (``split``: see :func:`_grid_tets`). With an odd ``n_cross`` (an even number of cells
    across) and the default mirrored split the mesh is symmetric under y -> -y and z -> -z, so a
    load in either plane bends the beam in that plane.
    Paper beams: n_long 48 / 64 / 80 -> 1,200 / 1,600 / 2,000 nodes.
    """
    n_long, n_cross = _count("n_long", n_long), _count("n_cross", n_cross)
    spacing = _positive("spacing", spacing)
    length = _positive("length", (n_long - 1) * spacing if length is None else length)
    width = _positive("width", (n_cross - 1) * spacing if width is None else width)
    y = np.linspace(-0.5 * width, 0.5 * width, n_cross)
    return grid_mesh(np.linspace(0.0, length, n_long), y, y, split)


def grid_mesh(x, y, z, split: str = "mirrored") -> TetMesh:
    """The box of a tensor-product grid with node coordinates ``x``, ``y``, ``z`` (each
    strictly increasing, at least 2), every cell split into 6 tets (see :func:`_grid_tets`);
    node id (i * len(y) + j) * len(z) + k. Graded spacings give a mesh fine where it is needed.
    Coordinates symmetric about their middle, with an even number of cells, make the default
    mirrored mesh symmetric under that axis's mirror."""
    axes = []
    for name, c in (("x", x), ("y", y), ("z", z)):
        c = np.asarray(c, dtype=np.float64).reshape(-1)
        if c.size < 2 or not np.all(np.isfinite(c)) or np.any(np.diff(c) <= 0.0):
            raise MeshError(f"grid {name} coordinates must be at least 2 finite, strictly increasing numbers")
        axes.append(c)
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    points = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    return validate_mesh(points, _grid_tets(tuple(len(c) for c in axes), split))


# Brain-like dome: footprint semi-axes, centre height, rim height fraction, tumour.
BRAIN_SEMI_AXES = (0.07, 0.055)
BRAIN_HEIGHT = 0.05
BRAIN_RIM = 0.35
BRAIN_TUMOUR_CENTRE = (0.01, 0.0, 0.6 * BRAIN_HEIGHT)
BRAIN_TUMOUR_RADIUS = 0.014
_DISK_BLEND = 0.75  # < 1 keeps the square-to-disk map regular at the corners


def brain_mesh(split: str = "mirrored") -> TetMesh:
    """Brain-like dome (1,734 nodes, 7,680 tets) on a flat base z = 0; tumour tets have id 1.

    A 17 x 17 x 6 node grid mapped to a rounded footprint (square blended 3:1 towards the
    elliptical square-to-disk map, semi-axes 0.07 x 0.055 m) and a height 0.05 m at the
    centre falling smoothly to 35 % at the rim. Material 1: tets whose centroid lies within
    0.014 m of (0.01, 0, 0.03); the rest 0. With the default mirrored split (16 x 16 cells in
    the footprint) the mesh is symmetric under y -> -y and x -> -x, the tumour under y -> -y.
    """
    nu, nv, nw = 17, 17, 6
    u, v, w = np.meshgrid(np.linspace(-1, 1, nu), np.linspace(-1, 1, nv), np.linspace(0, 1, nw), indexing="ij")
    xd = u * np.sqrt(1.0 - 0.5 * v**2)  # elliptical square-to-disk map
    yd = v * np.sqrt(1.0 - 0.5 * u**2)
    xf = (1.0 - _DISK_BLEND) * u + _DISK_BLEND * xd
    yf = (1.0 - _DISK_BLEND) * v + _DISK_BLEND * yd
    bump = (1.0 - u**2) * (1.0 - v**2)  # 1 at the centre, 0 on the rim
    h = BRAIN_HEIGHT * (BRAIN_RIM + (1.0 - BRAIN_RIM) * bump)
    points = np.stack([BRAIN_SEMI_AXES[0] * xf.ravel(), BRAIN_SEMI_AXES[1] * yf.ravel(), (w * h).ravel()], axis=1)
    tets = _grid_tets((nu, nv, nw), split)
    c = points[tets].mean(axis=1)
    inside = np.linalg.norm(c - np.asarray(BRAIN_TUMOUR_CENTRE), axis=1) < BRAIN_TUMOUR_RADIUS
    return validate_mesh(points, tets, inside.astype(np.int32), min_quality=0.05)


# ---------------------------------------------------------------------------- command line


def _info(mesh: TetMesh, path) -> str:
    ids, counts = np.unique(mesh.material_ids, return_counts=True)
    q = tet_quality(mesh.points, mesh.tets)
    lo, hi = mesh.points.min(axis=0), mesh.points.max(axis=0)
    fmt = lambda a: "(" + ", ".join(f"{x:.6g}" for x in a) + ")"  # noqa: E731
    return "\n".join([
        f"file          {path}",
        f"nodes         {mesh.n_nodes}",
        f"tets          {mesh.n_tets}",
        "material ids  " + ", ".join(f"{i}: {n}" for i, n in zip(ids, counts)),
        f"bbox          min {fmt(lo)} max {fmt(hi)}",
        f"volume        {mesh.signed_volumes().sum():.6g}",
        f"surface faces {len(mesh.boundary_faces())}",
        f"quality       min {q.min():.4f} mean {q.mean():.4f}",
    ])


def cli(argv=None) -> int:
    """``python -m soft_tissue_sim mesh beam|brain|info ...``."""
    ap = argparse.ArgumentParser(prog="python -m soft_tissue_sim mesh", description="generate or inspect tet meshes")
    sub = ap.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("beam", help="structured beam along x, clamped end at x = 0")
    b.add_argument("--long", type=int, required=True, help="nodes along the beam (x)")
    b.add_argument("--cross", type=int, default=5, help="nodes per side of the square section")
    b.add_argument("--spacing", type=float, default=0.01, help="node spacing [m]")
    b.add_argument("--length", type=float, default=None, help="beam length [m] (default (long-1)*spacing)")
    b.add_argument("--width", type=float, default=None, help="section width [m] (default (cross-1)*spacing)")
    b.add_argument("--split", choices=SPLITS, default="mirrored",
                   help="cell split: mirrored per cell parity (symmetric) or uniform (one diagonal)")
    b.add_argument("--out", required=True, help="output file (any meshio format, e.g. .vtu)")
    r = sub.add_parser("brain", help="brain-like dome with a tumour (material 1)")
    r.add_argument("--split", choices=SPLITS, default="mirrored", help="cell split (see beam)")
    r.add_argument("--out", required=True)
    i = sub.add_parser("info", help="print nodes, tets, materials, bbox, quality of a mesh file")
    i.add_argument("file")
    i.add_argument("--material-key", default=None)
    args = ap.parse_args(argv)
    try:
        if args.cmd == "info":
            print(_info(load_mesh(args.file, args.material_key), args.file))
            return 0
        if args.cmd == "beam":
            mesh = beam_mesh(args.long, args.cross, args.length, args.width, args.spacing, args.split)
        else:
            mesh = brain_mesh(args.split)
    except (MeshError, FileNotFoundError) as e:
        ap.exit(2, f"error: {e}\n")
    out = Path(args.out)
    if out.parent and not out.parent.exists():
        os.makedirs(out.parent, exist_ok=True)
    save_mesh(mesh, out)
    print(_info(mesh, out))
    return 0
