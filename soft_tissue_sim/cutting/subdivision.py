"""Progressive cutting by subdivision (``subdivide``, after Mor & Kanade, the paper's [7]).

Every mesh edge the blade crosses gets a node at the crossing and every tet around that edge
is bisected there, which keeps the mesh conforming; a crossing within ``snap`` of an edge's
end puts that end on the cut instead. A stroke's :class:`CutState` says which nodes are on
its cut; a face is separated once its three nodes are on it and its two tets lie on opposite
sides. Invariants: bisected tets keep their orientation; no new edge crosses the blade; a tet
with all four nodes on the cut is never shaved off alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..mesh import unique_rows
from .geometry import TET_EDGES, _path_planes, _points_in_triangle, edge_crossings, interior_faces


@dataclass
class CutState:
    """Nodes on a progressive cut (``subdivide``), per node: whether it is on the cut (``on``),
    the blade's normal there, oriented along the stroke (``normals``), and its signed distance
    to the blade (``offsets``: 0 for a crossing, the distance for a node a crossing snapped to)."""

    on: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray

    @classmethod
    def empty(cls, n: int) -> "CutState":
        return cls(np.zeros(n, bool), np.zeros((n, 3)), np.zeros(n))

    def take(self, idx) -> "CutState":
        return CutState(self.on[idx], self.normals[idx], self.offsets[idx])

    def extended(self, more: "CutState") -> "CutState":
        """This state followed by ``more`` (nodes appended)."""
        return CutState(np.concatenate([self.on, more.on]), np.concatenate([self.normals, more.normals]),
                        np.concatenate([self.offsets, more.offsets]))


def subdivide_for_cut(P, tets, tris, snap: float, tol: float, state: CutState | None = None,
                      tri_normals=None):
    """Refine the tets the blade crosses so that its triangles cut no edge of the mesh any more
    (progressive cutting by subdivision, after Mor & Kanade; paper section 3.1).

    Every mesh edge that the blade triangles cross strictly gets a new node at the crossing,
    and every tet holding that edge is bisected there: the edge bisection of all the tets
    around an edge keeps the mesh conforming, a bisected tet keeps its orientation, and no new
    edge crosses the blade (each has an end on it). A crossing closer than ``snap`` (a
    fraction of the edge) to an end point is not split: that end point is taken as on the cut
    (no sliver is created), and no other edge at a node snapped in this sweep is split.

    ``state`` (n nodes): the nodes already on this cut (earlier sweeps of the same stroke); an
    edge with both ends on the cut lies on it and is not split again. ``tri_normals`` (T, 3):
    the oriented normals of the (non-degenerate) blade triangles (default: their own), given to
    the nodes they put on the cut.

    Returns (tets, parent, fresh, edge_a, edge_b, edge_t, state): the new nodes are numbered
    from n on, new node k at (1 - t) P[a_k] + t P[b_k]; ``parent`` (m',) is the old tet each tet
    comes from, ``fresh`` (m',) whether it is a new (bisected) one; ``state`` the cut state of
    all n + k nodes after this sweep (every new node is on the cut, at offset 0).
    """
    tets = np.asarray(tets, dtype=np.int64)
    parent = np.arange(len(tets))
    fresh = np.zeros(len(tets), bool)
    tris, own_normals = _path_planes(tris)
    tri_normals = own_normals if tri_normals is None else np.asarray(tri_normals, np.float64)
    st = CutState.empty(len(P)) if state is None else state
    on, normals, offsets = st.on.copy(), st.normals.copy(), st.offsets.copy()
    none = np.zeros(0, np.int64)
    if not len(tris):
        return tets, parent, fresh, none, none, np.zeros(0), CutState(on, normals, offsets)
    lo, hi = tris.min(axis=(0, 1)) - tol, tris.max(axis=(0, 1)) + tol
    X = P[tets]
    near = np.all((X.max(axis=1) >= lo) & (X.min(axis=1) <= hi), axis=1)
    E = unique_rows(np.sort(tets[near][:, TET_EDGES].reshape(-1, 2), axis=1))
    # nodes lying on a blade triangle are on the cut (a blade through mesh nodes crosses no edge)
    V = np.unique(tets[near])
    for (a, b, c), nk in zip(tris, tri_normals):
        lie = np.abs((P[V] - a) @ nk) <= tol
        if lie.any():
            w = V[lie][_points_in_triangle(P[V[lie]], a, b, c, tol) & ~on[V[lie]]]
            on[w], normals[w], offsets[w] = True, nk, 0.0
    E = E[~(on[E[:, 0]] & on[E[:, 1]])]  # edges lying on the cut already
    t, which = edge_crossings(P, E, tris, tol)
    crossed = np.isfinite(t)
    E, t, which = E[crossed], t[crossed], which[crossed]
    # snapping: a crossing near an end point puts that end point on the cut
    snapped = np.zeros(len(P), bool)
    for end, near_end in ((0, t < snap), (1, t > 1.0 - snap)):
        v = E[near_end, end]
        new = ~on[v]
        snapped[v[new]] = True
        k = which[near_end][new]
        normals[v[new]] = tri_normals[k]
        offsets[v[new]] = np.einsum("kd,kd->k", P[v[new]] - tris[k, 0], tri_normals[k])
    on |= snapped
    split = (t >= snap) & (t <= 1.0 - snap) & ~snapped[E[:, 0]] & ~snapped[E[:, 1]]
    E, t, which = E[split], t[split], which[split]
    for (i, j), p in zip(E, len(P) + np.arange(len(E))):
        has = np.any(tets == i, axis=1) & np.any(tets == j, axis=1)
        T = tets[has]
        tets = np.concatenate([tets[~has], np.where(T == j, p, T), np.where(T == i, p, T)])
        parent = np.concatenate([parent[~has], parent[has], parent[has]])
        fresh = np.concatenate([fresh[~has], np.ones(2 * len(T), bool)])
    state = CutState(on, normals, offsets).extended(CutState(np.ones(len(E), bool), tri_normals[which],
                                                             np.zeros(len(E))))
    return tets, parent, fresh, E[:, 0], E[:, 1], t, state


def tet_sides(P, tets, state: CutState, pairs, fnodes):
    """Side (+1 / -1) of each tet with respect to the cut through its nodes on it (``state``:
    which nodes, the cut's normals there, consistently oriented along a stroke, and offsets).

    A tet with one node off the cut: the sign of that node's offset from the mean of the others
    along their mean normal. A tet with all four nodes on the cut (nodes snapped to it, or
    crossings of sweeps made while the tissue moved): it joins the side it shares the most face
    area with (``pairs``, ``fnodes``: the interior faces' tets and nodes; propagated through
    clusters of such tets), else the sign of its nodes' offsets, else +. So it is never shaved
    off alone. A tet with fewer than three nodes on the cut gets 0 (it holds no face of it)."""
    on_t = state.on[tets]
    k = on_t.sum(axis=1)
    side = np.zeros(len(tets))
    three = np.flatnonzero(k == 3)
    if len(three):
        T, o = tets[three], on_t[three]
        X = P[T]
        m_on = np.einsum("kj,kjd->kd", o, X) / 3.0
        x_off = X[~o].reshape(-1, 3)
        n = np.einsum("kj,kjd->kd", o, state.normals[T])
        side[three] = np.sign(np.einsum("kd,kd->k", x_off - m_on, n))
    undecided = k == 4
    if undecided.any():
        sel = undecided[pairs[:, 0]] | undecided[pairs[:, 1]]
        pa, pb = pairs[sel, 0], pairs[sel, 1]
        F = P[fnodes[sel]]
        area = 0.5 * np.linalg.norm(np.cross(F[:, 1] - F[:, 0], F[:, 2] - F[:, 0]), axis=1)
        for _ in range(64):
            vote = np.zeros(len(tets))
            np.add.at(vote, pa, area * side[pb] * undecided[pa])
            np.add.at(vote, pb, area * side[pa] * undecided[pb])
            now = undecided & (vote != 0.0)
            if not now.any():
                break
            side[now] = np.sign(vote[now])
            undecided &= ~now
        rest = np.flatnonzero(undecided)
        side[rest] = np.where(state.offsets[tets[rest]].sum(axis=1) < 0.0, -1.0, 1.0)
    return side


def faces_on_cut(P, tets, state: CutState):
    """The interior faces a progressive (subdivision) cut separates: faces whose three nodes are
    all on the cut (the crossings of this stroke and the nodes they snapped to) between tets on
    opposite sides of it (:func:`tet_sides`). Topological and over the whole stroke, so a face
    the blade passed over several sweeps is separated once its last node reaches the cut, and
    the crack stops inside the elements the blade is still crossing (their faces have a node off
    the cut). Returns (pairs, face nodes, mask)."""
    pairs, fnodes = interior_faces(tets)
    cut = np.all(state.on[fnodes], axis=1)
    if cut.any():
        k = np.flatnonzero(cut)
        side = tet_sides(P, tets, state, pairs, fnodes)
        cut[k] = side[pairs[k, 0]] * side[pairs[k, 1]] < 0.0
    return pairs, fnodes, cut
