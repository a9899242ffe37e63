"""Blade geometry against the tets, host-side numpy on the tets near the blade (an AABB
filter, then exact tests): which tets a blade triangle crosses, which interior faces a cut
separates (``split``), where mesh edges cross the blade (``subdivide``).

Invariants: ``tol`` [m] widens every test the same way (a touching blade counts); degenerate
blade triangles are dropped, never divided by.
"""

from __future__ import annotations

import numpy as np

from ..mesh import _FACES

TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


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
    for i, j in TET_EDGES:
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
