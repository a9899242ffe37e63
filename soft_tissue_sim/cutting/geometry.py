"""Blade geometry against the tets, on the host, on the tets near the blade (an AABB filter,
then exact tests): which tets a blade triangle crosses, which interior faces a cut separates
(``split``), where mesh edges cross the blade (``subdivide``). The boxes are culled with
NumPy; the exact test of a tet against a blade triangle (:func:`_section_meets`) is a Warp
function run on Warp's CPU device, one launch per question: :func:`faces_cut_kernel` for the
faces a blade's sweep cuts (the split scheme's test of every step while a blade cuts),
:func:`tets_cut_kernel` for the tets a triangle cuts. Each sum and product is its own
statement (no fused multiply-add), so a result is the same on every host.

Invariants: ``tol`` [m] widens every test the same way (a touching blade counts); degenerate
blade triangles are dropped, never divided by; a tet's tests are row-wise arithmetic on its
own nodes, so which other tets are tested with it (the culling) changes no result.
"""

from __future__ import annotations

import sys

import numpy as np
import warp as wp

from ..mesh import cross
from ..mesh import interior_faces as _interior_faces

wp.set_module_options({"enable_backward": False})  # no gradients are taken

WARP_CPU_ONLY = True  # its kernels run on Warp's CPU device alone (warp_modules.build_all)

TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


def _points_in_triangle(p, a, b, c, tol):
    """(k,) whether points p (k,3), already on the plane of (a,b,c), lie in the triangle (+tol).
    (The ``subdivide`` scheme's test; ``split``'s is :func:`_in_triangle`, one point at a time.)"""
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = v0 @ v0, v0 @ v1, v1 @ v1
    d20, d21 = v2 @ v0, v2 @ v1
    den = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    rel = tol / np.sqrt(max(d00, d11))
    return (v >= -rel) & (w >= -rel) & (v + w <= 1.0 + rel)


def _dot(u, v):
    """Row-wise dot products of (..., 3) arrays, summed in a fixed order: a tet's value does
    not depend on the other tets of its batch, so culling cannot change a result."""
    return u[..., 0] * v[..., 0] + u[..., 1] * v[..., 1] + u[..., 2] * v[..., 2]


_LOW_BITS, _HIGH_BITS = np.array([1, 2, 4], np.uint8), np.array([8, 16, 32], np.uint8)


def tets_near_box(points, tets, lo, hi):
    """Indices of the tets whose bounding box meets the box [lo, hi]: a tet is far when all its
    nodes lie beyond the same face of the box (their outcodes share a bit)."""
    code = ((points < lo) @ _LOW_BITS) | ((points > hi) @ _HIGH_BITS)
    c = code[tets]
    return np.flatnonzero((c[:, 0] & c[:, 1] & c[:, 2] & c[:, 3]) == 0)


def _near_blade(points, tets, tri, tol):
    """Indices of the tets whose bounding box meets the triangle's, widened by ``tol``."""
    return tets_near_box(points, tets, tri.min(axis=0) - tol, tri.max(axis=0) + tol)


def _near_triangles(X, tris, tol):
    """The pairs (triangle, tet) whose bounding boxes meet, the triangle's widened by ``tol``:
    (triangle indices, tet indices) of the triangles (T, 3, 3) and the tets X (k, 4, 3),
    ordered by triangle, then tet. The test of :func:`tets_near_box` (a tet is far when all its
    nodes lie beyond the same face of the box), on the tets' coordinates."""
    lo = (tris.min(axis=1) - tol)[:, None, None]  # (T, 1, 1, 3) against X[None]: (1, k, 4, 3)
    hi = (tris.max(axis=1) + tol)[:, None, None]
    far = np.any(np.all(X < lo, axis=2) | np.all(X > hi, axis=2), axis=2)  # (T, k)
    return np.nonzero(~far)


def _candidates(points, tets, tris, nrm, tol):
    """The pairs (tet, triangle) that the exact test of :func:`_tets_cut` is left to decide:
    the tets near a (non-degenerate) blade triangle with unit normal ``nrm`` (the box of the
    whole path over all tets with :func:`_near_blade`, then each triangle's box over those,
    :func:`_near_triangles`) that have vertices on both sides of its plane (+tol). Returns
    (tet indices, triangle indices), ordered by triangle, then tet."""
    near = _near_blade(points, tets, tris.reshape(-1, 3), tol)  # the box of the whole path first
    if not len(near):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    Xn = points[tets[near]]  # (k, 4, 3)
    owner, j = _near_triangles(Xn, tris, tol)
    cand, X = near[j], Xn[j]
    d = _dot(X - tris[owner, 0][:, None], nrm[owner][:, None])
    straddle = (d.min(axis=1) <= tol) & (d.max(axis=1) >= -tol)
    return cand[straddle], owner[straddle]


def _tets_cut(points, tets, tris, nrm, tol):
    """The tets that the (non-degenerate) blade triangles with unit normals ``nrm`` cut: the
    :func:`_candidates` whose section by a triangle's plane overlaps it
    (:func:`tets_cut_kernel`). Returns (tet indices, triangle indices) of the pairs, ordered by
    triangle, then tet; the exact tests of all triangles run as one launch."""
    cand, owner = _candidates(points, tets, tris, nrm, tol)
    if not len(cand):
        return cand, owner
    hit = np.zeros(len(cand), np.int32)
    wp.launch(tets_cut_kernel, len(cand),
              [_vec3(points, len(points)), _i64(tets), _i64(cand), _i64(owner), _vec3(tris, tris.shape[:2]),
               _vec3(nrm, len(nrm)), float(tol), _on_cpu(hit, wp.int32)], device="cpu")
    hit = hit.astype(bool)
    return cand[hit], owner[hit]


def tets_cut_by_triangle(points, tets, tri, tol):
    """Indices of tets whose section by the plane of ``tri`` overlaps the triangle, and the
    signed distances (m,) of all tet centroids to that plane (the side of every tet); for a
    degenerate triangle, no tets and None."""
    points, tets = np.asarray(points, np.float64), np.asarray(tets, np.int64)
    tris, nrm = _path_planes(tri)
    if not len(tris):
        return np.zeros(0, np.int64), None
    return _tets_cut(points, tets, tris, nrm, tol)[0], _dot(points[tets].mean(axis=1) - tris[0, 0], nrm[0])


def interior_faces(tets):
    """(f, 2) tets sharing each interior face and (f, 3) its nodes (:func:`..mesh.interior_faces`)."""
    return _interior_faces(tets)[:2]


def sweep_triangles(p0, p1, q0, q1):
    """The two triangles of the quad swept by a blade segment from (p0, p1) to (q0, q1)."""
    p0, p1, q0, q1 = (np.asarray(v, dtype=np.float64) for v in (p0, p1, q0, q1))
    return np.array([[p0, p1, q1], [p0, q1, q0]])


def _path_planes(tris):
    """Unit normals (T, 3) and first vertices (T, 3) of blade triangles; degenerate ones dropped."""
    tris = np.asarray(tris, dtype=np.float64).reshape(-1, 3, 3)
    n = cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
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


@wp.func
def _dot3(u: wp.vec3d, v: wp.vec3d):
    """:func:`_dot`: u0 v0 + u1 v1 + u2 v2 in that order, each operation its own statement."""
    a = u[0] * v[0]
    b = u[1] * v[1]
    c = u[2] * v[2]
    ab = a + b
    return ab + c


@wp.func
def _cross3(u: wp.vec3d, v: wp.vec3d):
    """:func:`..mesh.cross`: u_{j+1} v_{j+2} - u_{j+2} v_{j+1}."""
    x0 = u[1] * v[2]
    x1 = u[2] * v[1]
    y0 = u[2] * v[0]
    y1 = u[0] * v[2]
    z0 = u[0] * v[1]
    z1 = u[1] * v[0]
    return wp.vec3d(x0 - x1, y0 - y1, z0 - z1)


@wp.func
def _in_triangle(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d, tol: wp.float64):
    """Whether the point p, already on the plane of the triangle (a, b, c), lies in it (+tol):
    its barycentric coordinates v, w >= -rel and v + w <= 1 + rel, rel = tol over the longer of
    the two edges from a."""
    v0 = b - a
    v1 = c - a
    v2 = p - a
    d00 = _dot3(v0, v0)
    d01 = _dot3(v0, v1)
    d11 = _dot3(v1, v1)
    d20 = _dot3(v2, v0)
    d21 = _dot3(v2, v1)
    q0 = d00 * d11
    q1 = d01 * d01
    den = q0 - q1
    e0 = d11 * d20
    e1 = d01 * d21
    v = (e0 - e1) / den
    f0 = d00 * d21
    f1 = d01 * d20
    w = (f0 - f1) / den
    rel = tol / wp.sqrt(wp.max(d00, d11))
    one = wp.float64(1.0) + rel
    return v >= -rel and w >= -rel and v + w <= one


@wp.func
def _vertex(X0: wp.vec3d, X1: wp.vec3d, X2: wp.vec3d, X3: wp.vec3d, i: int):
    r = X0
    if i == 1:
        r = X1
    elif i == 2:
        r = X2
    elif i == 3:
        r = X3
    return r


@wp.func
def _section_meets(X0: wp.vec3d, X1: wp.vec3d, X2: wp.vec3d, X3: wp.vec3d, a: wp.vec3d, b: wp.vec3d,
                   c: wp.vec3d, n: wp.vec3d, tol: wp.float64):
    """Does the section of the tet (X0..X3) by the plane of the triangle (a, b, c; unit normal
    n) overlap that triangle (+tol)? Yes when a crossing of a tet edge with the plane (in
    :data:`TET_EDGES`' order), or a tet vertex on it, lies inside the triangle, or when an edge
    of the triangle passes through the tet (a blade thinner than the element, or inside it):
    the edge clipped by the tet's faces, each moved out by ``tol``."""
    d = wp.vec4d(_dot3(X0 - a, n), _dot3(X1 - a, n), _dot3(X2 - a, n), _dot3(X3 - a, n))
    for e in range(6):  # the edges' crossings with the plane (TET_EDGES' order)
        i = 0
        j = 1
        if e == 1:
            j = 2
        elif e == 2:
            j = 3
        elif e == 3:
            i = 1
            j = 2
        elif e == 4:
            i = 1
            j = 3
        elif e == 5:
            i = 2
            j = 3
        di = d[i]
        dj = d[j]
        if di * dj < wp.float64(0.0):
            t = di / (di - dj)
            Xi = _vertex(X0, X1, X2, X3, i)
            p = Xi + t * (_vertex(X0, X1, X2, X3, j) - Xi)
            p = p - _dot3(p - a, n) * n
            if _in_triangle(p, a, b, c, tol):
                return True
    for i in range(4):  # the vertices on the plane
        if wp.abs(d[i]) <= tol:
            p = _vertex(X0, X1, X2, X3, i)
            p = p - _dot3(p - a, n) * n
            if _in_triangle(p, a, b, c, tol):
                return True
    # the triangle's edges through the tet: each face's inward normal
    for s in range(3):
        p0 = a
        p1 = b
        if s == 1:
            p0 = b
            p1 = c
        elif s == 2:
            p0 = c
            p1 = a
        tmin = wp.float64(0.0)
        tmax = wp.float64(1.0)
        lo = wp.float64(0.0)
        hi = wp.float64(1.0)
        away = False
        for f in range(4):
            i0 = 0  # the face's vertices: the tet's others, in order
            i1 = 1
            i2 = 2
            if f == 0:
                i0 = 1
            if f <= 1:
                i1 = 2
            if f <= 2:
                i2 = 3
            o0 = _vertex(X0, X1, X2, X3, i0)
            o1 = _vertex(X0, X1, X2, X3, i1)
            o2 = _vertex(X0, X1, X2, X3, i2)
            fn = _cross3(o1 - o0, o2 - o0)
            sg = _dot3(fn, _vertex(X0, X1, X2, X3, f) - o0)
            sign = wp.float64(0.0)
            if sg > wp.float64(0.0):
                sign = wp.float64(1.0)
            elif sg < wp.float64(0.0):
                sign = wp.float64(-1.0)
            fn = fn * sign
            widen = tol * wp.sqrt(_dot3(fn, fn))
            h0 = _dot3(fn, p0 - o0) + widen
            dh = _dot3(fn, p1 - p0)
            if dh > wp.float64(0.0):
                lo = wp.max(lo, -h0 / dh)
            elif dh < wp.float64(0.0):
                hi = wp.min(hi, -h0 / dh)
            elif h0 < wp.float64(0.0):
                away = True
        tmin = wp.max(lo, wp.float64(0.0))
        tmax = wp.min(hi, wp.float64(1.0))
        if not away and tmin <= tmax:
            return True
    return False


@wp.func
def _near_and_across(X0: wp.vec3d, X1: wp.vec3d, X2: wp.vec3d, X3: wp.vec3d, a: wp.vec3d, b: wp.vec3d,
                     c: wp.vec3d, n: wp.vec3d, tol: wp.float64):
    """Whether the tet (X0..X3) meets the box of the triangle (a, b, c), widened by ``tol``
    (:func:`_near_triangles`), and has vertices on both sides of its plane (unit normal n, +tol):
    the tests before :func:`_section_meets`."""
    for ax in range(3):
        lo = wp.min(wp.min(a[ax], b[ax]), c[ax]) - tol
        hi = wp.max(wp.max(a[ax], b[ax]), c[ax]) + tol
        if X0[ax] < lo and X1[ax] < lo and X2[ax] < lo and X3[ax] < lo:
            return False
        if X0[ax] > hi and X1[ax] > hi and X2[ax] > hi and X3[ax] > hi:
            return False
    d0 = _dot3(X0 - a, n)
    d1 = _dot3(X1 - a, n)
    d2 = _dot3(X2 - a, n)
    d3 = _dot3(X3 - a, n)
    return wp.min(wp.min(d0, d1), wp.min(d2, d3)) <= tol and wp.max(wp.max(d0, d1), wp.max(d2, d3)) >= -tol


@wp.func
def _parts_cut(X0: wp.vec3d, X1: wp.vec3d, X2: wp.vec3d, X3: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d,
               n: wp.vec3d, tol: wp.float64, parts: wp.vec4i):
    """Whether the tet's faces marked in ``parts`` (those between tets on opposite sides of the
    plane) are cut: one is marked and the tet's section by the plane meets the triangle."""
    if parts[0] == 0 and parts[1] == 0 and parts[2] == 0 and parts[3] == 0:
        return False
    return _section_meets(X0, X1, X2, X3, a, b, c, n, tol)


@wp.func
def _centroid_side(X0: wp.vec3d, X1: wp.vec3d, X2: wp.vec3d, X3: wp.vec3d, a: wp.vec3d, n: wp.vec3d):
    """Whether the centroid of the tet (X0..X3, summed in order, over 4) is on the positive side
    of the plane through a with normal n (or on it)."""
    s = X0 + X1
    s = s + X2
    s = s + X3
    return _dot3(s / wp.float64(4.0) - a, n) >= wp.float64(0.0)


@wp.func
def _side(P: wp.array(dtype=wp.vec3d), tets: wp.array2d(dtype=wp.int64), t: wp.int64, a: wp.vec3d, n: wp.vec3d):
    """:func:`_centroid_side` of tet t."""
    return _centroid_side(P[int(tets[t, 0])], P[int(tets[t, 1])], P[int(tets[t, 2])], P[int(tets[t, 3])], a, n)


@wp.kernel
def faces_cut_kernel(P: wp.array(dtype=wp.vec3d), tets: wp.array2d(dtype=wp.int64), near: wp.array(dtype=wp.int64),
                     tris: wp.array2d(dtype=wp.vec3d), nrm: wp.array(dtype=wp.vec3d), tol: wp.float64,
                     tet_face: wp.array2d(dtype=wp.int64), pairs: wp.array2d(dtype=wp.int64),
                     cut: wp.array(dtype=wp.int32)):
    """For the tet near[i] and the blade triangle k: where its box, the triangle's widened by
    ``tol``, meet (:func:`_near_triangles`), its vertices lie on both sides of the triangle's
    plane (+tol), one of its interior faces lies between tets on opposite sides of that plane
    (their centroids) and its section by the plane overlaps the triangle
    (:func:`_section_meets`), those faces are cut (cut[face] = 1)."""
    i, k = wp.tid()
    t = near[i]
    X0 = P[int(tets[t, 0])]
    X1 = P[int(tets[t, 1])]
    X2 = P[int(tets[t, 2])]
    X3 = P[int(tets[t, 3])]
    a = tris[k, 0]
    b = tris[k, 1]
    c = tris[k, 2]
    n = nrm[k]
    if not _near_and_across(X0, X1, X2, X3, a, b, c, n, tol):
        return
    parts = wp.vec4i(0, 0, 0, 0)  # the tet's interior faces between tets on opposite sides
    for q in range(4):
        f = tet_face[t, q]
        if f >= wp.int64(0):  # (nested: the pair is read only for a face)
            if _side(P, tets, pairs[f, 0], a, n) != _side(P, tets, pairs[f, 1], a, n):
                parts[q] = 1
    if _parts_cut(X0, X1, X2, X3, a, b, c, n, tol, parts):
        for q in range(4):
            if parts[q] != 0:
                cut[int(tet_face[t, q])] = 1


@wp.kernel
def tets_cut_kernel(P: wp.array(dtype=wp.vec3d), tets: wp.array2d(dtype=wp.int64), cand: wp.array(dtype=wp.int64),
                    owner: wp.array(dtype=wp.int64), tris: wp.array2d(dtype=wp.vec3d), nrm: wp.array(dtype=wp.vec3d),
                    tol: wp.float64, hit: wp.array(dtype=wp.int32)):
    """hit[i] = 1 where the section of the tet cand[i] by the plane of the triangle owner[i]
    overlaps that triangle (:func:`_section_meets`)."""
    i = wp.tid()
    t = cand[i]
    k = owner[i]
    if _section_meets(P[int(tets[t, 0])], P[int(tets[t, 1])], P[int(tets[t, 2])], P[int(tets[t, 3])], tris[k, 0],
                      tris[k, 1], tris[k, 2], nrm[k], tol):
        hit[i] = 1


def _on_cpu(a: np.ndarray, dtype) -> wp.array:
    """An int32 or int64 NumPy array as a Warp array on the CPU, sharing its memory (a copy only
    where it is not contiguous or of another type)."""
    return wp.array(np.ascontiguousarray(a, np.int64 if dtype == wp.int64 else np.int32), dtype=dtype, device="cpu",
                    copy=False)


def _i64(a: np.ndarray) -> wp.array:
    return _on_cpu(a, wp.int64)


def _vec3(a: np.ndarray, shape) -> wp.array:
    """A float64 (..., 3) array as a Warp vec3d array on the CPU (no copy where contiguous)."""
    return wp.array(np.ascontiguousarray(a, np.float64), dtype=wp.vec3d, shape=shape, device="cpu", copy=False)


def load_kernels() -> None:
    """This module's kernel built (or loaded from the cache) for the CPU, where it runs: before a
    simulation's first step, not in the middle of one."""
    wp.load_module(sys.modules[__name__], device="cpu")


def faces_cut_by_triangles(P, tets, tris, tol, faces=None, normals=None):
    """The interior faces a blade separates (``split``): for each blade triangle, the faces
    between tets on opposite sides of its plane (the sign of their centroid's distance) of which
    at least one is intersected (its section overlaps the triangle: :func:`tets_cut_by_triangle`).
    The tets in the box of the whole path are handed to :func:`faces_cut_kernel`, which tests
    each against each triangle's box and plane, and runs the exact test only where the tet has
    such a face.
    ``faces``: :func:`..mesh.interior_faces` of ``tets`` where known (``TetMesh.interior_faces``);
    ``normals``: the unit normals of ``tris`` where known (:func:`_path_planes`: ``tris`` are then
    its non-degenerate triangles). Only the tets near a triangle are looked at, those of all
    triangles in one batch. Returns (pairs, face nodes, mask)."""
    P, tets = np.asarray(P, np.float64), np.asarray(tets, np.int64)
    pairs, fnodes, tet_face = _interior_faces(tets) if faces is None else faces
    cut = np.zeros(len(pairs), bool)
    tris, nrm = _path_planes(tris) if normals is None else (tris, normals)
    if not len(tris):
        return pairs, fnodes, cut
    near = _near_blade(P, tets, tris.reshape(-1, 3), tol)  # the box of the whole path first
    if not len(near):
        return pairs, fnodes, cut
    mask = np.zeros(len(pairs), np.int32)
    wp.launch(faces_cut_kernel, (len(near), len(tris)),
              [_vec3(P, len(P)), _i64(tets), _i64(near), _vec3(tris, tris.shape[:2]), _vec3(nrm, len(nrm)), float(tol),
               _i64(tet_face), _i64(pairs), _on_cpu(mask, wp.int32)], device="cpu")
    return pairs, fnodes, mask.astype(bool)
