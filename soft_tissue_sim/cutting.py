"""Cutting and element removal by incremental mesh change (paper section 3.1, fig. 1).

Two schemes (``cutting: {scheme: split | subdivide}``); both remove the tets the cut
touches, re-create them with new connectivity and add them back, like the paper's three
steps, and both end by node splitting along the faces of the cut.

``split`` (the default): separation along the existing faces. A blade is one or more
triangles: the quad swept by an instrument's blade segment between two poses, or a plane
patch from a scene script (in the rest or the world frame). For each blade triangle we find
the intersected tets (their section by the triangle's plane overlaps the triangle), give
every tet a side by the sign of its centroid's distance to that plane, and mark as *cut
faces* the interior faces between tets of opposite sides of which at least one is
intersected. At each node of a cut face the incident tets are grouped into the sets that
stay connected through uncut faces; every group beyond the first gets its own copy of the
node (same rest and current position, velocity, fixed flag). Where the blade stops, the
tets around the tip stay connected and the crack ends. Every element keeps its shape (no
sliver, the quality floor holds by construction), the two sides separate for real, mass and
momentum are conserved; the cut surface is a staircase of faces within an element of the
blade.

``subdivide``: the cut on the blade itself, progressively, by subdivision (after Mor &
Kanade, the paper's [7]). At every sweep of the blade, every mesh edge it crosses gets a new
node at the crossing (its rest and current position and its velocity interpolated on the
edge, so the displacement field is unchanged), and every tet holding that edge is bisected
there: the edge bisection of all the tets around an edge keeps the mesh conforming, and
once the crossed edges are split no edge crosses the blade, so the blade inside the body
lies on faces. A crossing closer than ``snap`` (a fraction of its edge) to an end point is
not split: that end point is taken as on the cut, which avoids slivers; ``min_quality``
refuses any change that would still go below the floor. A stroke (the blade while the pedal
is down, a script) keeps its cut state between sweeps: the nodes on its cut, with the
blade's normal there (oriented along the stroke) and their offset from it. A face is
separated, by the node splitting above, once its three nodes are on the cut and its two tets
lie on opposite sides (:func:`faces_on_cut`): a face the blade passed over several sweeps is
separated when its last node reaches the cut, and while the blade is inside an element (some
of its faces keep a node off the cut) the refinement alone is the step's modification: the
crack tip's partial state. A sweep cuts ``lead`` ahead of the blade (its capsule pushes the
tissue ahead of it). More nodes per modification (the new ones), a modification at nearly
every step of a moving blade, and the mesh grows.

Element removal (ablation, aspiration) deletes the tets whose centroid lies in a sphere;
nodes left without a tet are deleted and the rest renumbered (uids keep their identity for
the preconditioner).

Geometry here is host-side numpy on the few tets near the blade (an AABB filter then exact
tests): the topology itself (face adjacency, node groups) changes at every cut, so a Warp
BVH would be rebuilt per cut for a query that numpy answers in well under a millisecond.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sps
from scipy.sparse.csgraph import connected_components

from .material import ParameterError
from .mesh import _FACES, TetMesh, tet_quality, unique_rows
from .sherman_morrison import ShermanMorrisonCorrection, modification_from_blocks

_TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
CORRECTIONS = ("sherman_morrison", "none")
SCHEMES = ("split", "subdivide")
# subdivide: a crossing within this fraction of its edge snaps to the end. At 0.2 the brain took
# 6.2-10.9 PCG iterations and twice the contacts, against 4.3-4.7 at 0.35 (README).
DEFAULT_SNAP = 0.35


@dataclass
class CutResult:
    """What one mesh modification did."""

    changed: bool
    message: str
    tets_changed: int = 0  # removed + re-added (cut) or removed (ablation)
    nodes_added: int = 0
    nodes_removed: int = 0
    affected_nodes: int = 0  # nodes this modification changes (its own term's G)
    perturbation_nodes: int = 0  # nodes of N against the factor in use after it (paper's measure)
    faces_cut: int = 0
    debris_tets: int = 0  # tets of fragments below `min_fragment` removed after the change
    ms: float = 0.0  # whole modification, correction included
    smf_u_ms: float = 0.0  # U = P^-1 G (batched triangular solves)
    smf_q_ms: float = 0.0  # Q = (I + N S)^-1 N


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


@dataclass
class _Stroke:
    """What a stroke (successive sweeps) remembers: the uids of the nodes on its cut with their
    state, and the last sweep's mean normal (to orient the next one)."""

    uids: np.ndarray
    state: CutState
    last: np.ndarray | None


# ---------------------------------------------------------------- geometry
def _points_in_triangle(p, a, b, c, tol):
    """(k,) whether points p (k,3), already on the plane of (a,b,c), lie in the triangle (+tol)."""
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = v0 @ v0, v0 @ v1, v1 @ v1
    d20, d21 = v2 @ v0, v2 @ v1
    den = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    rel = tol / np.sqrt(max(d00, d11))
    return (v >= -rel) & (w >= -rel) & (v + w <= 1.0 + rel)


def _segment_meets_tets(p0, p1, X, tol):
    """Mask (k,): does the segment p0-p1 meet the tets X (k, 4, 3)? (Clipping by the 4 faces.)"""
    e = p1 - p0
    tmin = np.zeros(len(X))
    tmax = np.ones(len(X))
    ok = np.ones(len(X), bool)
    for i in range(4):
        o = [j for j in range(4) if j != i]
        nrm = np.cross(X[:, o[1]] - X[:, o[0]], X[:, o[2]] - X[:, o[0]])
        nrm *= np.sign(np.einsum("kj,kj->k", nrm, X[:, i] - X[:, o[0]]))[:, None]  # inwards
        scale = np.linalg.norm(nrm, axis=1)
        h0 = np.einsum("kj,kj->k", nrm, p0 - X[:, o[0]]) + tol * scale  # >= 0 inside (with tolerance)
        dh = nrm @ e
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -h0 / dh
        ok &= ~((dh == 0.0) & (h0 < 0.0))
        tmin = np.where(dh > 0.0, np.maximum(tmin, t), tmin)
        tmax = np.where(dh < 0.0, np.minimum(tmax, t), tmax)
    return ok & (tmin <= tmax)


def tets_cut_by_triangle(points, tets, tri, tol):
    """Indices of tets whose section by the plane of ``tri`` overlaps the triangle, and the
    signed distances (m,) of all tet centroids to that plane (the side of every tet)."""
    a, b, c = (np.asarray(t, dtype=np.float64) for t in tri)
    n = np.cross(b - a, c - a)
    area2 = np.linalg.norm(n)
    if not area2 > 0.0:
        return np.zeros(0, np.int64), None
    n /= area2
    X = points[tets]  # (m,4,3)
    side = (X.mean(axis=1) - a) @ n
    lo, hi = np.minimum(np.minimum(a, b), c) - tol, np.maximum(np.maximum(a, b), c) + tol
    cand = np.flatnonzero(np.all((X.max(axis=1) >= lo) & (X.min(axis=1) <= hi), axis=1))
    if not len(cand):
        return cand, side
    Xc = X[cand]
    d = (Xc - a) @ n  # (k,4)
    straddle = (d.min(axis=1) <= tol) & (d.max(axis=1) >= -tol)
    cand, Xc, d = cand[straddle], Xc[straddle], d[straddle]
    hit = np.zeros(len(cand), bool)
    # crossing points of the tet edges with the plane, and vertices on it
    for i, j in _TET_EDGES:
        di, dj = d[:, i], d[:, j]
        cross = (di * dj < 0.0)
        t = np.where(cross, di / np.where(cross, di - dj, 1.0), 0.0)
        p = Xc[:, i] + t[:, None] * (Xc[:, j] - Xc[:, i])
        p = p - ((p - a) @ n)[:, None] * n
        hit |= cross & _points_in_triangle(p, a, b, c, tol)
    for i in range(4):
        on = np.abs(d[:, i]) <= tol
        p = Xc[:, i] - ((Xc[:, i] - a) @ n)[:, None] * n
        hit |= on & _points_in_triangle(p, a, b, c, tol)
    # the triangle's edges through the tet: the section polygon overlaps the triangle though
    # none of its corners lies inside it (a blade thinner than the element, or inside it)
    for p0, p1 in ((a, b), (b, c), (c, a)):
        hit |= _segment_meets_tets(p0, p1, Xc, tol)
    return cand[hit], side


def interior_faces(tets):
    """(f, 2) tets sharing each interior face and (f, 3) its nodes."""
    faces = tets[:, _FACES].reshape(-1, 3)
    owner = np.repeat(np.arange(len(tets)), 4)
    key = np.sort(faces, axis=1)
    order = np.lexsort(key.T[::-1])
    ks = key[order]
    same = np.all(ks[1:] == ks[:-1], axis=1)
    first = np.flatnonzero(same)
    pairs = np.stack([owner[order[first]], owner[order[first + 1]]], axis=1)
    return pairs, ks[first]


def sweep_triangles(p0, p1, q0, q1):
    """The two triangles of the quad swept by a blade segment from (p0, p1) to (q0, q1)."""
    p0, p1, q0, q1 = (np.asarray(v, dtype=np.float64) for v in (p0, p1, q0, q1))
    return np.array([[p0, p1, q1], [p0, q1, q0]])


# ----------------------------------------------------------------- topology
def split_along_faces(tets: np.ndarray, cut_pairs: np.ndarray, cut_nodes_of_faces: np.ndarray,
                      all_pairs: np.ndarray, all_face_nodes: np.ndarray, n_nodes: int):
    """Duplicate the nodes of the cut faces so that the two sides separate.

    Returns (new_tets, source) where ``source`` (n_new,) gives, for each added node, the node it
    copies; new nodes are numbered from ``n_nodes`` on.
    """
    cut_nodes = np.unique(cut_nodes_of_faces)
    if not len(cut_nodes):
        return tets.copy(), np.zeros(0, np.int64)
    is_cut_node = np.zeros(n_nodes, bool)
    is_cut_node[cut_nodes] = True
    # incidences (node, tet) at cut nodes: vertices of a graph
    t_idx, k_idx = np.nonzero(is_cut_node[tets])
    inc_node = tets[t_idx, k_idx].astype(np.int64)
    m = len(tets)
    keys = inc_node * m + t_idx
    order = np.argsort(keys)
    keys_sorted = keys[order]
    # edges: through each uncut interior face, for each of its cut nodes, (v, a) - (v, b)
    cut_set = np.zeros(len(all_pairs), bool)
    if len(cut_pairs):
        # mark faces listed as cut (compare by sorted node triples)
        fk = all_face_nodes[:, 0] * (n_nodes ** 2) + all_face_nodes[:, 1] * n_nodes + all_face_nodes[:, 2]
        ck = cut_nodes_of_faces[:, 0] * (n_nodes ** 2) + cut_nodes_of_faces[:, 1] * n_nodes + cut_nodes_of_faces[:, 2]
        cut_set = np.isin(fk, ck)
    unc_pairs, unc_nodes = all_pairs[~cut_set], all_face_nodes[~cut_set]
    ea, eb = [], []
    for c in range(3):
        v = unc_nodes[:, c].astype(np.int64)
        sel = is_cut_node[v]
        ka = v[sel] * m + unc_pairs[sel, 0]
        kb = v[sel] * m + unc_pairs[sel, 1]
        ea.append(order[np.searchsorted(keys_sorted, ka)])
        eb.append(order[np.searchsorted(keys_sorted, kb)])
    ea, eb = np.concatenate(ea), np.concatenate(eb)
    nv = len(keys)
    g = sps.coo_matrix((np.ones(len(ea)), (ea, eb)), shape=(nv, nv))
    _, label = connected_components(g, directed=False)
    # per node: its distinct groups; the first keeps the node, the others get copies
    new_tets = tets.copy()
    pair = unique_rows(np.stack([inc_node, label], axis=1))  # sorted by node then label
    first_of_node = np.r_[True, pair[1:, 0] != pair[:-1, 0]]
    extra = pair[~first_of_node]
    source = extra[:, 0]
    new_index = n_nodes + np.arange(len(extra))
    # relabel incidences whose (node, label) is an extra group
    ekey = extra[:, 0] * (label.max() + 1) + extra[:, 1]
    ikey = inc_node * (label.max() + 1) + label
    if not len(ekey):
        return new_tets, source
    pos = np.minimum(np.searchsorted(ekey, ikey), len(ekey) - 1)
    hit = ekey[pos] == ikey
    new_tets[t_idx[hit], k_idx[hit]] = new_index[pos[hit]]
    return new_tets, source


# ------------------------------------------------------ subdivision (Mor-Kanade)
def _path_planes(tris):
    """Unit normals (T, 3) and first vertices (T, 3) of blade triangles; degenerate ones dropped."""
    tris = np.asarray(tris, dtype=np.float64).reshape(-1, 3, 3)
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    area2 = np.linalg.norm(n, axis=1)
    ok = area2 > 0.0
    return tris[ok], n[ok] / area2[ok, None]


def edge_crossings(P, edges, tris, tol):
    """For edges (e, 2) of points P: the parameter t in (0, 1) where each crosses one of the
    blade triangles strictly (its end points on opposite sides of the triangle's plane, the
    crossing point inside the triangle up to ``tol``), NaN where it crosses none; and the index
    of that triangle among the non-degenerate ones (-1 where none)."""
    t_out = np.full(len(edges), np.nan)
    which = np.full(len(edges), -1, np.int64)
    if not len(edges):
        return t_out, which
    tris, nrm = _path_planes(tris)
    X0, X1 = P[edges[:, 0]], P[edges[:, 1]]
    for k, ((a, b, c), n) in enumerate(zip(tris, nrm)):
        d0, d1 = (X0 - a) @ n, (X1 - a) @ n
        cross = (d0 * d1 < 0.0) & np.isnan(t_out)
        if not cross.any():
            continue
        idx = np.flatnonzero(cross)
        t = d0[idx] / (d0[idx] - d1[idx])
        q = X0[idx] + t[:, None] * (X1[idx] - X0[idx])
        inside = _points_in_triangle(q, a, b, c, tol)
        t_out[idx[inside]] = t[inside]
        which[idx[inside]] = k
    return t_out, which


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
    E = unique_rows(np.sort(tets[near][:, _TET_EDGES].reshape(-1, 2), axis=1))
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


def faces_cut_by_triangles(P, tets, tris, tol):
    """The interior faces a blade separates (``split``): for each blade triangle, the faces
    between tets on opposite sides of its plane (the sign of their centroid's distance) of which
    at least one is intersected (its section overlaps the triangle). Returns (pairs, face
    nodes, mask)."""
    pairs, fnodes = interior_faces(tets)
    cut = np.zeros(len(pairs), bool)
    for tri in tris:
        hit, side = tets_cut_by_triangle(P, tets, tri, tol)
        if side is None or not len(hit):
            continue
        is_hit = np.zeros(len(tets), bool)
        is_hit[hit] = True
        sa, sb = side[pairs[:, 0]] >= 0.0, side[pairs[:, 1]] >= 0.0
        cut |= (sa != sb) & (is_hit[pairs[:, 0]] | is_hit[pairs[:, 1]])
    return pairs, fnodes, cut


# -------------------------------------------------------------------- cutter
def _vec3(v, what):
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ParameterError(f"{what} must be 3 finite numbers, got {v!r}")
    return a


class Cutter:
    """Cutting machinery of a scene: blade cuts, element removal, scripted cuts, and the
    preconditioner correction. Scene keys (all optional)::

        cutting:
          instrument: scalpel              # the instrument whose blade cuts (contact's instruments)
          correction: sherman_morrison     # sherman_morrison | none (only identity padding, eq. 10)
          min_quality: 0.01                # quality floor of the tets a cut creates (1 = regular)
          tolerance: 1.0e-9                # geometric tolerance [m]
          min_fragment: 5                  # a free fragment of fewer tets that a change leaves is
                                           # removed as debris (0: keep every fragment)
          scheme: split                    # split: separate along existing faces (node splitting);
                                           # subdivide: split the crossed edges first (Mor-Kanade)
          snap: 0.35                       # subdivide: a crossing closer than this fraction of
                                           # its edge to an end snaps to that end (no slivers)
          lead: 0.001                      # subdivide: a sweep cuts this far ahead of the blade's
                                           # axis [m] (default: twice the instrument's radius)
          script:                          # planned cuts: a plane patch that advances every few steps
            {frame: rest, start_step: 1, every: 3, count: 40,
             origin: [x, y, z], edge: [ex, ey, ez], direction: [dx, dy, dz], advance: 0.01}
    """

    def __init__(self, sim, cfg):
        cfg = dict(cfg) if isinstance(cfg, dict) else {}
        unknown = set(cfg) - {"instrument", "correction", "min_quality", "tolerance", "script", "enabled",
                            "min_fragment", "scheme", "snap", "lead"}
        if unknown:
            raise ParameterError(f"unknown cutting keys: {sorted(unknown)}")
        self.instrument = cfg.get("instrument")
        self.correction_mode = str(cfg.get("correction", "sherman_morrison"))
        if self.correction_mode not in CORRECTIONS:
            raise ParameterError(f"cutting correction must be one of {CORRECTIONS}, got {self.correction_mode!r}")
        self.min_quality = float(cfg.get("min_quality", 0.01))
        if not 0.0 < self.min_quality < 1.0:
            raise ParameterError(f"cutting min_quality must be in (0, 1), got {self.min_quality}")
        self.tolerance = float(cfg.get("tolerance", 1e-9))
        if not (self.tolerance >= 0.0 and np.isfinite(self.tolerance)):
            raise ParameterError(f"cutting tolerance must be >= 0, got {self.tolerance}")
        mf = cfg.get("min_fragment", 5)
        if isinstance(mf, bool) or not isinstance(mf, int) or mf < 0:
            raise ParameterError(f"cutting min_fragment must be an integer >= 0, got {mf!r}")
        self.min_fragment = mf
        self.scheme = str(cfg.get("scheme", "split"))
        if self.scheme not in SCHEMES:
            raise ParameterError(f"cutting scheme must be one of {SCHEMES}, got {self.scheme!r}")
        self.snap = float(cfg.get("snap", DEFAULT_SNAP))
        if not 0.0 < self.snap < 0.5:
            raise ParameterError(f"cutting snap must be in (0, 0.5), got {self.snap}")
        lead = cfg.get("lead")
        if lead is not None and not (isinstance(lead, (int, float)) and np.isfinite(lead) and lead >= 0.0):
            raise ParameterError(f"cutting lead must be a distance >= 0 [m], got {lead!r}")
        self.lead = None if lead is None else float(lead)
        self.script = self._parse_script(cfg.get("script"))
        self.active = False
        self.correction = None
        inner = getattr(sim.preconditioner, "inner", None)
        if inner is not None and hasattr(inner, "correction"):
            self.correction = ShermanMorrisonCorrection(enabled=self.correction_mode == "sherman_morrison",
                                                        rotate=bool(getattr(inner, "rotate", True)))
            inner.correction = self.correction
        self._reset_counters()

    def _reset_counters(self):
        self._strokes: dict[str, _Stroke] = {}  # subdivide: each stroke's cut state
        self.modifications = 0
        self.history: list[CutResult] = []
        self._blade_at_last_cut = None
        self._script_done = 0

    @staticmethod
    def _parse_script(s):
        if not s:
            return None
        if not isinstance(s, dict):
            raise ParameterError(f"cutting script must be a mapping, got {s!r}")
        out = {
            "frame": str(s.get("frame", "rest")),
            "start_step": int(s.get("start_step", 1)),
            "every": int(s.get("every", 3)),
            "count": int(s.get("count", 10)),
            "origin": _vec3(s.get("origin"), "cutting script origin"),
            "edge": _vec3(s.get("edge"), "cutting script edge"),
            "direction": _vec3(s.get("direction"), "cutting script direction"),
            "advance": float(s.get("advance", 0.01)),
        }
        if out["frame"] not in ("rest", "world"):
            raise ParameterError(f"cutting script frame must be rest or world, got {out['frame']!r}")
        if out["every"] < 1 or out["count"] < 0 or not out["advance"] > 0.0:
            raise ParameterError("cutting script needs every >= 1, count >= 0 and advance > 0")
        nrm = np.linalg.norm(out["direction"])
        if not nrm > 0.0:
            raise ParameterError("cutting script direction must be non-zero")
        out["direction"] = out["direction"] / nrm
        return out

    def scripted_triangles(self, k: int) -> np.ndarray:
        """Blade triangles of the k-th scripted cut: the patch from k*advance to (k+1)*advance,
        reaching back a little over the previous one so consecutive cuts join."""
        s = self.script
        d, e = s["direction"], s["edge"]
        a = max(0.0, (k - 0.25) * s["advance"])
        b = (k + 1) * s["advance"]
        p0 = s["origin"] + a * d
        q0 = s["origin"] + b * d
        return sweep_triangles(p0, p0 + e, q0, q0 + e)

    # ----------------------------------------------------------------- API
    def set_active(self, active: bool) -> None:
        self.active = bool(active)

    def reset(self, sim) -> None:
        self._reset_counters()
        self.active = False
        if self.correction is not None:
            self.correction.clear()

    @staticmethod
    def _state_of(st: _Stroke | None, node_uids) -> CutState:
        """A stroke's cut state over the current nodes (by uid; nodes it never met are off it)."""
        state = CutState.empty(len(node_uids))
        if st is not None and len(st.uids):
            order = np.argsort(st.uids)
            k = np.minimum(np.searchsorted(st.uids, node_uids, sorter=order), len(order) - 1)
            hit = st.uids[order[k]] == node_uids
            src = order[k[hit]]
            state.on[hit], state.normals[hit], state.offsets[hit] = True, st.state.normals[src], st.state.offsets[src]
        return state

    def _lead(self, inst) -> float:
        """How far ahead of its axis a sweep of the blade cuts (subdivide): the blade's capsule
        pushes the tissue it meets, so an edge ahead of a slow blade slides along in front of it
        and is never crossed (a beam swept at 0.3-0.6 mm a step stayed whole). Default: twice
        the capsule's radius (its radius alone was not enough there; 2.5 radii put the new
        nodes millimetres off the blade as the crack opened ahead of it)."""
        if self.lead is not None:
            return self.lead
        if self.scheme != "subdivide":
            return 0.0
        return 2.0 * float(getattr(inst, "radius", 0.0))

    def _instrument(self, sim):
        """The cutting instrument and its blade's world end points: the scene's (named)
        instrument that has a blade, as (instrument, (p0, p1)), or None."""
        if sim.contact is None:
            return None
        insts = getattr(sim.contact, "instruments", None)
        if insts is None:
            return None
        items = insts.values() if isinstance(insts, dict) else insts
        for inst in items:
            if self.instrument is None or getattr(inst, "name", None) == self.instrument:
                fn = getattr(inst, "blade_world", None)
                blade = fn() if fn is not None else None
                if blade is not None:
                    return inst, tuple(np.asarray(p, dtype=np.float64) for p in blade)
        return None

    def cut(self, sim) -> CutResult:
        """Cut along the blade's path since the last cut (or since the blade was first seen)."""
        found = self._instrument(sim)
        if found is None:
            return CutResult(False, "no instrument with a blade in this scene: nothing to cut with")
        inst, blade = found
        prev = self._blade_at_last_cut
        self._blade_at_last_cut = blade
        if prev is None:
            self._strokes.pop("blade", None)  # a new stroke of the blade
            return CutResult(False, "blade position recorded; the next cut follows its path from here")
        q0, q1 = blade
        d = 0.5 * ((q0 - prev[0]) + (q1 - prev[1]))
        lead, dn = self._lead(inst), float(np.linalg.norm(d))
        if lead > 0.0 and dn > 0.0:  # cut what the blade's capsule reaches ahead of its axis
            q0, q1 = q0 + lead * d / dn, q1 + lead * d / dn
        return self.cut_triangles(sim, sweep_triangles(prev[0], prev[1], q0, q1), frame="world", stroke="blade")

    def blade_triangles(self, sim) -> np.ndarray | None:
        """The blade where it is now, as two triangles (2, 3, 3), world frame, or None without a
        blade: its segment widened by the instrument's radius to both sides along the tool's x
        axis (the flat of the blade is the tool's x-z plane; the tool's y axis for a blade along x)."""
        found = self._instrument(sim)
        if found is None:
            return None
        inst, (p0, p1) = found
        axis = p1 - p0
        axis = axis / np.linalg.norm(axis)
        pose = getattr(inst, "pose", None)
        R = np.eye(3) if pose is None else np.asarray(pose.R, dtype=np.float64)
        side = R[:, 0] - (R[:, 0] @ axis) * axis
        if np.linalg.norm(side) < 1e-6:  # blade along the tool's x axis
            side = R[:, 1] - (R[:, 1] @ axis) * axis
        side *= float(getattr(inst, "radius", 0.0)) / np.linalg.norm(side)
        return sweep_triangles(p0 - side, p1 - side, p0 + side, p1 + side)

    def cut_at_blade(self, sim) -> CutResult:
        """One cut where the blade is now (:meth:`blade_triangles`), not a sweep: a stab incision
        as wide as the instrument, through the tissue the blade is in."""
        tris = self.blade_triangles(sim)
        if tris is None:
            return CutResult(False, "no instrument with a blade in this scene: nothing to cut with")
        return self.cut_triangles(sim, tris, frame="world")

    def step(self, sim) -> dict:
        """Per step: scripted cuts due now, and the blade's sweep while cutting is active."""
        results = []
        s = self.script
        if s is not None and self._script_done < s["count"]:
            k = sim.step_count - s["start_step"]
            if k >= 0 and k % s["every"] == 0:
                results.append(self.cut_triangles(sim, self.scripted_triangles(self._script_done), frame=s["frame"],
                                                  stroke="script"))
                self._script_done += 1
        if self.active:
            results.append(self.cut(sim))
        else:
            self._blade_at_last_cut = None  # a pedal press starts a new path
        done = [r for r in results if r.changed]
        return {
            "cuts": self.modifications,
            "tets_changed": sum(r.tets_changed for r in done),
            "affected_nodes": sum(r.affected_nodes for r in done),
            "cut_ms": sum(r.ms for r in results),
            "smf_u_ms": sum(r.smf_u_ms for r in done),
            "smf_q_ms": sum(r.smf_q_ms for r in done),
        }

    # ------------------------------------------------------------- cutting
    def cut_triangles(self, sim, triangles, frame: str = "world", stroke: str | None = None) -> CutResult:
        """Cut along blade triangles (k, 3, 3), given in the current (world) or rest frame.

        ``subdivide``: first the crossed edges are split and their tets bisected
        (:func:`subdivide_for_cut`); then, on that mesh, the faces whose nodes are all on the
        cut are split as in the ``split`` scheme (:func:`faces_on_cut`,
        :func:`split_along_faces`). Where the blade is still inside an element the refinement
        alone is the modification: the crack opens once the blade has passed a whole face.
        ``stroke`` names a cut made of successive sweeps (the blade while the pedal is down, a
        script): the nodes on its cut are remembered between sweeps (the per-element cut state
        of progressive cutting); None: this call alone."""
        t0 = time.perf_counter()
        tris = np.asarray(triangles, dtype=np.float64).reshape(-1, 3, 3)
        if not np.all(np.isfinite(tris)):
            return CutResult(False, "blade has non-finite coordinates: no cut")
        if frame not in ("world", "rest"):
            raise ValueError(f"frame must be 'world' or 'rest', got {frame!r}")

        def ms():
            return 1000.0 * (time.perf_counter() - t0)

        tris, tri_n = _path_planes(tris)  # the non-degenerate triangles and their normals
        if not len(tris):
            return CutResult(False, "the blade swept no area: no cut", ms=ms())
        mesh = sim.mesh
        n = mesh.n_nodes
        pts = sim.positions() if frame == "world" else mesh.points
        tets = mesh.tets.astype(np.int64)
        tol = self.tolerance + 1e-9 * float(np.ptp(mesh.points, axis=0).max())
        if self.scheme == "subdivide":
            st = self._strokes.get(stroke) if stroke is not None else None
            ref = st.last if st is not None else (tri_n[0] if len(tri_n) else None)
            if ref is not None:  # orient the blade's normals along the stroke (the motion may reverse)
                tri_n = tri_n * np.where(tri_n @ ref < 0.0, -1.0, 1.0)[:, None]
            work, parent, fresh, ea, eb, et, state = subdivide_for_cut(
                pts, tets, tris, self.snap, tol, self._state_of(st, sim.node_uids), tri_n)
            P = np.concatenate([pts, (1.0 - et)[:, None] * pts[ea] + et[:, None] * pts[eb]])
            pairs, fnodes, cut = faces_on_cut(P, work, state)
            if stroke is not None:  # the old nodes on the cut, whatever happens below (new ones added on commit)
                m = tri_n.sum(axis=0)
                on_old = state.on[:n]
                self._strokes[stroke] = _Stroke(sim.node_uids[on_old], state.take(np.flatnonzero(on_old)),
                                                m / np.linalg.norm(m) if np.linalg.norm(m) > 0 else ref)
        else:
            work, parent, fresh = tets, np.arange(len(tets)), np.zeros(len(tets), bool)
            ea, eb, et = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
            P = pts
            pairs, fnodes, cut = faces_cut_by_triangles(P, work, tris, tol)
        new_tets, dup = work, np.zeros(0, np.int64)
        if cut.any():
            new_tets, dup = split_along_faces(work, pairs[cut], fnodes[cut], pairs, fnodes, len(P))
        if not len(ea) and not len(dup):
            if not cut.any():
                return CutResult(False, "the blade crossed no tissue (no uncut face on its path): nothing changed",
                                 ms=ms())
            return CutResult(False, "the cut faces do not separate anything yet (the blade only grazed the "
                             "tissue): nothing changed", faces_cut=int(cut.sum()), ms=ms())
        # new nodes: the edge nodes, then the copies (of old or of edge nodes), as (a, b, t) of old nodes
        ext_a, ext_b = np.concatenate([np.arange(n), ea]), np.concatenate([np.arange(n), eb])
        ext_t = np.concatenate([np.zeros(n), et])
        a, b, t = (np.concatenate([ea, ext_a[dup]]), np.concatenate([eb, ext_b[dup]]),
                   np.concatenate([et, ext_t[dup]]))
        same = ~fresh & np.all(new_tets == tets[parent], axis=1)
        removed_ids = np.setdiff1d(np.arange(len(tets)), parent[same])
        res = self._commit(sim, new_tets, (a, b, t), removed_ids, np.flatnonzero(~same), keep=np.arange(n),
                           mats=mesh.material_ids[parent])
        res.faces_cut = int(cut.sum())
        if res.changed and stroke is not None and self.scheme == "subdivide":
            # every new node is on the cut: the crossings and the copies of nodes of cut faces
            st = self._strokes[stroke]
            added = state.take(np.concatenate([np.arange(n, n + len(ea)), dup]))  # edge nodes, then copies
            st.uids = np.concatenate([st.uids, sim.node_uids[n:]])  # (debris is removed below)
            st.state = st.state.extended(added)
        if res.changed and len(ea):
            res.message = res.message.replace("cut:", "cut (subdivision):", 1)
            if not len(dup):
                res.message += " (refined inside the elements the blade is crossing, not separated yet)"
        self._remove_debris(sim, res)
        res.ms = ms()
        return res

    def remove_elements(self, sim, center, radius: float, frame: str = "world") -> CutResult:
        """Ablation / aspiration: delete the tets whose centroid lies within ``radius`` of ``center``."""
        t0 = time.perf_counter()
        c = np.asarray(center, dtype=np.float64)
        if c.shape != (3,) or not np.all(np.isfinite(c)) or not (float(radius) > 0.0):
            return CutResult(False, f"element removal needs a finite center and radius > 0, got {center!r}, {radius!r}")
        mesh = sim.mesh
        pts = sim.positions() if frame == "world" else mesh.points
        cen = pts[mesh.tets].mean(axis=1)
        gone = np.linalg.norm(cen - c, axis=1) <= float(radius)
        if not gone.any():
            return CutResult(False, "no element within the removal sphere: nothing changed")
        return self._remove_mask(sim, gone, t0)

    def remove_tets(self, sim, tets) -> CutResult:
        """Delete given tets (a boolean mask over the tets or their indices): the extraction of
        a part cut free (a resected specimen), or any removal decided outside."""
        t0 = time.perf_counter()
        n = sim.mesh.n_tets
        sel = np.asarray(tets)
        if sel.dtype == bool:
            if sel.shape != (n,):
                return CutResult(False, f"tet mask must have one entry per tet ({n}), got shape {sel.shape}")
            gone = sel.copy()
        else:
            if sel.size and (not np.issubdtype(sel.dtype, np.integer) or sel.min() < 0 or sel.max() >= n):
                return CutResult(False, f"tet indices must be integers in [0, {n}), got {tets!r}")
            gone = np.zeros(n, bool)
            gone[sel.astype(np.int64).ravel()] = True
        if not gone.any():
            return CutResult(False, "no tet given: nothing changed")
        return self._remove_mask(sim, gone, t0)

    def _remove_mask(self, sim, gone: np.ndarray, t0: float) -> CutResult:
        if gone.all():
            return CutResult(False, "refused: the removal would delete every element of the body")
        res = self._remove_tets(sim, gone)
        self._remove_debris(sim, res)
        res.ms = 1000.0 * (time.perf_counter() - t0)
        return res

    def _remove_tets(self, sim, gone: np.ndarray) -> CutResult:
        tets = sim.mesh.tets.astype(np.int64)
        used = np.zeros(sim.mesh.n_nodes, bool)
        used[tets[~gone].ravel()] = True
        return self._commit(sim, None, np.zeros(0, np.int64), np.flatnonzero(gone), np.zeros(0, np.int64),
                            keep=np.flatnonzero(used), kept_tets=~gone)

    def small_fragments(self, mesh, free: np.ndarray) -> np.ndarray:
        """Mask of the tets in free fragments (no fixed node) of fewer than ``min_fragment`` tets."""
        if self.min_fragment <= 0 or mesh.n_tets == 0:
            return np.zeros(mesh.n_tets, bool)
        lab = mesh.node_components()
        tet_lab = lab[mesh.tets[:, 0]]
        count = np.bincount(tet_lab, minlength=lab.max() + 1)
        anchored = np.zeros(len(count), bool)
        anchored[lab[free == 0.0]] = True
        small = (count < self.min_fragment) & ~anchored
        return small[tet_lab]

    def _remove_debris(self, sim, res: CutResult) -> None:
        """After a change: remove the small free fragments it left (a lone tet shaved off by the
        blade would otherwise tumble through the cut at free-fall speed) and say so in ``res``."""
        if not res.changed:
            return
        debris = self.small_fragments(sim.mesh, sim.fem.free.numpy())
        if not debris.any() or debris.all():
            return
        r = self._remove_tets(sim, debris)
        if r.changed:
            res.debris_tets = int(debris.sum())
            res.nodes_removed += r.nodes_removed
            res.affected_nodes += r.affected_nodes
            res.perturbation_nodes = r.perturbation_nodes
            res.smf_u_ms += r.smf_u_ms
            res.smf_q_ms += r.smf_q_ms
            res.message += f"; {res.debris_tets} debris tets of fragments under {self.min_fragment} tets removed"

    # ------------------------------------------------------------- commit
    def _commit(self, sim, new_tets, source, removed_ids, added_ids, keep, kept_tets=None, mats=None) -> CutResult:
        """Apply a topology change to mesh, FEM, state and preconditioner, or refuse it unchanged.

        ``new_tets``: the new tets (None: element removal, ``keep`` the nodes kept, ``kept_tets``
        the tets). New nodes are appended after the old ones, node k at (1 - t) a + t b of old
        nodes ``source = (a, b, t)`` (a copy of node a: b = a, t = 0), for its rest and current
        position and its velocity: a node on an edge follows the displacement field exactly.
        ``mats``: the new tets' material ids (default: unchanged)."""
        fem, integ, mesh = sim.fem, sim.integrator, sim.mesh
        old_uids = sim.node_uids
        x, v = sim.positions(), sim.velocities()
        free_old = fem.free.numpy()
        fem.update_rotations(integ.x)  # old and new element blocks with the rotations of the same state
        R_nodes = fem.node_rotations()
        if new_tets is None:  # element removal with compaction
            remap = np.full(mesh.n_nodes, -1, np.int64)
            remap[keep] = np.arange(len(keep))
            tets_new = remap[mesh.tets[kept_tets].astype(np.int64)]
            pts_new, x_new, v_new = mesh.points[keep], x[keep], v[keep]
            uids_new = old_uids[keep]
            free_new = free_old[keep]
            mats = mesh.material_ids[kept_tets]
            created = np.zeros(0, np.int64)
            removed = np.setdiff1d(old_uids, uids_new)
        else:  # node splitting and subdivision: new nodes appended
            a, b, t = source
            t = np.asarray(t, dtype=np.float64)[:, None]

            def along(arr):
                return np.concatenate([arr, (1.0 - t) * arr[a] + t * arr[b]])

            tets_new = new_tets
            pts_new, x_new, v_new = along(mesh.points), along(x), along(v)
            first = int(old_uids.max()) + 1 if len(old_uids) else 0
            created = np.arange(first, first + len(a), dtype=np.int64)
            uids_new = np.concatenate([old_uids, created])
            free_new = np.concatenate([free_old, np.maximum(free_old[a], free_old[b])])  # fixed if both ends are
            mats = mesh.material_ids if mats is None else mats
            removed = np.zeros(0, np.int64)
            source = np.where(t[:, 0] <= 0.5, a, b)  # the old node whose rotation a new one takes
        # the quality floor (node splitting keeps shapes; this guards the invariant) and no orphan node
        q = tet_quality(pts_new, tets_new[added_ids]) if len(added_ids) else np.ones(1)
        used = np.zeros(len(pts_new), bool)
        used[tets_new.ravel()] = True
        if q.min() < self.min_quality or not used.all():
            return CutResult(False, f"refused: the change would create a tet of quality {q.min():.3g} < "
                             f"{self.min_quality} or a node without a tet; mesh unchanged")
        new_mesh = TetMesh(pts_new, tets_new, mats)
        # the local change of A: removed elements' blocks (old numbering, current rotations) ...
        m_coef, k_coef = integ.m_coef, integ.k_coef
        old_blocks = fem.element_blocks(removed_ids, m_coef, k_coef)
        R_by_uid_tab = dict(zip(old_uids.tolist(), range(len(old_uids))))
        fixed_new = np.flatnonzero(free_new == 0.0)
        fem.set_mesh(new_mesh, fixed_new)
        integ.set_state(x_new, v_new)
        fem.update_rotations(integ.x)
        new_blocks = fem.element_blocks(added_ids, m_coef, k_coef)  # ... and the added ones' (new numbering)
        sim.mesh = new_mesh
        sim.node_uids = uids_new
        sim.mesh_version += 1
        self.modifications += 1
        src_of_uid = {int(u): R_by_uid_tab[int(old_uids[s])] for u, s in zip(created, source)}
        free_tab = dict(zip(uids_new.tolist(), free_new.tolist()))
        free_tab.update(zip(old_uids.tolist(), free_old.tolist()))

        def R_of(uids):
            return np.stack([R_nodes[R_by_uid_tab[u] if u in R_by_uid_tab else src_of_uid[u]] for u in uids.tolist()])

        def free_of(uids):
            return np.array([free_tab[u] for u in uids.tolist()])

        mod = modification_from_blocks(sim.mesh_version, old_blocks, new_blocks, old_uids, uids_new, R_of, free_of,
                                       created=created, removed=removed)
        u_ms = q_ms = 0.0
        pert = 0  # no correction, no perturbation to carry
        if self.correction is not None:
            self.correction.u_ms = self.correction.q_ms = 0.0
            self.correction.add(mod, uids_new)
            u_ms, q_ms = self.correction.u_ms, self.correction.q_ms
            pert = self.correction.perturbation_nodes()
        else:  # Jacobi / plain CG rebuild from the mesh every step
            sim.preconditioner.invalidate()
        what = "cut" if new_tets is not None else "removal"
        res = CutResult(True, f"{what}: {len(removed_ids)} tets changed, {len(created)} nodes added, "
                        f"{len(removed)} removed, {len(mod.uids)} affected",
                        tets_changed=int(len(removed_ids)), nodes_added=int(len(created)),
                        nodes_removed=int(len(removed)), affected_nodes=int(len(mod.uids)),
                        perturbation_nodes=pert,
                        smf_u_ms=u_ms, smf_q_ms=q_ms)
        self.history.append(res)
        return res
