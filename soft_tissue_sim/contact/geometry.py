"""Contact geometry: closest points between points, segments and triangles (Warp functions,
float64, after Ericson's *Real-Time Collision Detection*) and the host-side helpers of the
contact frame (tangent bases) and the surface (edge ownership).

Invariants: barycentric weights returned by the closest-point functions are >= 0 and sum to 1
(``plane_bary`` excepted: unclamped); a degenerate segment is treated as a point.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..mesh import cross, unique_rows

F64 = wp.float64


@wp.func
def closest_on_segment(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d):
    ab = b - a
    l2 = wp.dot(ab, ab)
    t = F64(0.0)
    if l2 > F64(0.0):
        t = wp.clamp(wp.dot(p - a, ab) / l2, F64(0.0), F64(1.0))
    return a + t * ab


@wp.func
def triangle_closest_bary(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d):
    """Barycentric coordinates of the point of triangle abc closest to p (Ericson 5.1.5)."""
    zero = F64(0.0)
    one = F64(1.0)
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= zero and d2 <= zero:
        return wp.vec3d(one, zero, zero)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= zero and d4 <= d3:
        return wp.vec3d(zero, one, zero)
    vc = d1 * d4 - d3 * d2
    if vc <= zero and d1 >= zero and d3 <= zero:
        v = d1 / (d1 - d3)
        return wp.vec3d(one - v, v, zero)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= zero and d5 <= d6:
        return wp.vec3d(zero, zero, one)
    vb = d5 * d2 - d1 * d6
    if vb <= zero and d2 >= zero and d6 <= zero:
        w = d2 / (d2 - d6)
        return wp.vec3d(one - w, zero, w)
    va = d3 * d6 - d5 * d4
    if va <= zero and (d4 - d3) >= zero and (d5 - d6) >= zero:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return wp.vec3d(zero, one - w, w)
    denom = one / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return wp.vec3d(one - v - w, v, w)


@wp.func
def plane_bary(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d):
    """Barycentric coordinates (unclamped) of p's projection on the plane of abc."""
    v0 = b - a
    v1 = c - a
    v2 = p - a
    d00 = wp.dot(v0, v0)
    d01 = wp.dot(v0, v1)
    d11 = wp.dot(v1, v1)
    d20 = wp.dot(v2, v0)
    d21 = wp.dot(v2, v1)
    den = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return wp.vec3d(F64(1.0) - v - w, v, w)


@wp.func
def closest_segment_segment(p1: wp.vec3d, q1: wp.vec3d, p2: wp.vec3d, q2: wp.vec3d):
    """Parameters (s, t) of the closest points p1 + s (q1 - p1) and p2 + t (q2 - p2) of two
    segments (Ericson 5.1.9); either may be a point."""
    zero = F64(0.0)
    one = F64(1.0)
    tiny = F64(1e-30)
    d1 = q1 - p1
    d2 = q2 - p2
    r = p1 - p2
    a = wp.dot(d1, d1)
    e = wp.dot(d2, d2)
    f = wp.dot(d2, r)
    s = zero
    t = zero
    if a <= tiny and e <= tiny:
        return wp.vec2d(s, t)
    if a <= tiny:
        t = wp.clamp(f / e, zero, one)
        return wp.vec2d(s, t)
    c = wp.dot(d1, r)
    if e <= tiny:
        s = wp.clamp(-c / a, zero, one)
        return wp.vec2d(s, t)
    b = wp.dot(d1, d2)
    denom = a * e - b * b
    if denom > zero:
        s = wp.clamp((b * f - c * e) / denom, zero, one)
    t = (b * s + f) / e
    if t < zero:
        t = zero
        s = wp.clamp(-c / a, zero, one)
    elif t > one:
        t = one
        s = wp.clamp((b - c) / a, zero, one)
    return wp.vec2d(s, t)


@wp.func
def to_vec3f(p: wp.vec3d):
    return wp.vec3(wp.float32(p[0]), wp.float32(p[1]), wp.float32(p[2]))



@wp.func
def segment_triangle_closest(a: wp.vec3d, b: wp.vec3d, va: wp.vec3d, vb: wp.vec3d, vc: wp.vec3d):
    """Closest points of the segment ab (a point if a == b) and the non-degenerate triangle
    (va, vb, vc): (s, w, d2, crossing) with the segment's point a + s (b - a), the triangle's
    point in barycentric coordinates w, their squared distance d2, and crossing = 1 where the
    segment passes through the triangle from one side of its plane to the other (both points
    are then the crossing point, d2 = 0). The minimum over the end points against the
    triangle and the segment against the three edges, unless it crosses."""
    zero = F64(0.0)
    one = F64(1.0)
    nf = wp.normalize(wp.cross(vb - va, vc - va))
    da = wp.dot(a - va, nf)
    db = wp.dot(b - va, nf)
    if (da > zero and db < zero) or (da < zero and db > zero):
        sx = da / (da - db)
        wx = plane_bary(a + sx * (b - a), va, vb, vc)
        if wx[0] >= zero and wx[1] >= zero and wx[2] >= zero:
            return sx, wx, zero, 1
    s = zero
    w = triangle_closest_bary(a, va, vb, vc)
    best = wp.length_sq(a - (w[0] * va + w[1] * vb + w[2] * vc))
    w2 = triangle_closest_bary(b, va, vb, vc)
    d2 = wp.length_sq(b - (w2[0] * va + w2[1] * vb + w2[2] * vc))
    if d2 < best:
        best = d2
        s = one
        w = w2
    # edge k joins vertices k and k + 1
    st = closest_segment_segment(a, b, va, vb)
    d2 = wp.length_sq(a + st[0] * (b - a) - (va + st[1] * (vb - va)))
    if d2 < best:
        best = d2
        s = st[0]
        w = wp.vec3d(one - st[1], st[1], zero)
    st = closest_segment_segment(a, b, vb, vc)
    d2 = wp.length_sq(a + st[0] * (b - a) - (vb + st[1] * (vc - vb)))
    if d2 < best:
        best = d2
        s = st[0]
        w = wp.vec3d(zero, one - st[1], st[1])
    st = closest_segment_segment(a, b, vc, va)
    d2 = wp.length_sq(a + st[0] * (b - a) - (vc + st[1] * (va - vc)))
    if d2 < best:
        best = d2
        s = st[0]
        w = wp.vec3d(st[1], zero, one - st[1])
    return s, w, best, 0


_AXES = np.eye(3)[:2]  # e_x, e_y


@wp.func
def tangent_frame(n: wp.vec3d):
    """:func:`tangent_basis` of one unit normal on the device: (t1, t2)."""
    a = wp.vec3d(F64(0.0), F64(1.0), F64(0.0))
    if wp.abs(n[0]) < F64(0.9):
        a = wp.vec3d(F64(1.0), F64(0.0), F64(0.0))
    t1 = wp.cross(n, a)
    t1 = t1 / wp.sqrt(wp.dot(t1, t1))
    return t1, wp.cross(n, t1)


def tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (k, 3) completing the unit normals n (k, 3) to right-handed frames:
    t1 along n x e_x (n x e_y where n is within 0.9 of e_x's direction), t2 = n x t1."""
    a = _AXES[(~(np.abs(n[:, 0]) < 0.9)).view(np.int8)]  # e_y where |n_x| < 0.9 fails (NaN too)
    t1 = cross(n, a)
    t1 /= np.sqrt(np.einsum("ij,ij->i", t1, t1))[:, None]
    return t1, cross(n, t1)


def edge_ownership(faces: np.ndarray) -> np.ndarray:
    """(k, 3) int32: 1 where face f owns its edge from vertex j to vertex j + 1 (mod 3). Each
    undirected edge is owned once, by the lowest-index face that has it: the first of its
    run in a sort of the edges' packed keys, each key followed by the edge's position
    (face-major order) in one int64, so that a plain sort orders each run by position."""
    faces = np.asarray(faces).reshape(-1, 3)
    owner = np.zeros(3 * len(faces), np.int32)
    if len(faces):
        a = faces.astype(np.int64).ravel()
        b = faces[:, [1, 2, 0]].astype(np.int64).ravel()
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        base, n = int(hi.max()) + 1, len(a)
        if base * base * n < 2**62:
            key = (lo * base + hi) * n + np.arange(n)
            key.sort()
            edge, pos = np.divmod(key, n)
            run = np.empty(n, bool)
            run[0] = True
            np.not_equal(edge[1:], edge[:-1], out=run[1:])
            first = pos[run]
        else:
            _, first = unique_rows(np.stack([lo, hi], axis=1), return_index=True)
        owner[first] = 1
    return owner.reshape(-1, 3)
