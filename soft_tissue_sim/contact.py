"""Contact by Lagrange multipliers with the preconditioner's compliance (paper section 2.3,
eq. 3-4, and 3.4, eq. 11-12).

One step (called by :meth:`Simulation.step` after the free motion of eq. 1):

1. Detection on the free-motion positions (Warp kernels, float64 narrow phase): every
   tissue surface node against each instrument capsule and each obstacle, every tissue
   surface triangle against each instrument capsule (so that a tool thinner than the node
   spacing cannot slip between nodes: see below), and, with ``self_collision``, every
   surface node against the tissue's own surface triangles (a ``wp.Mesh`` over the current
   positions, refitted each step, as the broad phase). A contact has a point on the other
   surface, a unit normal n pointing towards the tissue (the way the tissue is pushed), and
   a gap delta^0 (< 0: penetration). Its Jacobian row H is n^T on the node for
   node-vs-rigid, w_i n^T on the triangle's nodes for triangle-vs-instrument (the tissue
   point sum_i w_i x_i), and n^T on the node minus w_i n^T on the triangle's nodes for
   self-collision. With friction two more rows t1^T, t2^T (tangents) whose "gap" is the
   relative tangential displacement during the step.
2. The LCP of eq. (3),  delta = W lambda + delta^0,  0 <= delta_n  _|_  lambda_n >= 0,
   with Coulomb friction |lambda_t| <= mu lambda_n (disk, or pyramid per component), is
   solved by projected Gauss-Seidel (a single-thread Warp kernel on the CPU).
3. Positions and velocities are corrected with the same compliance:
   dx = dt^2 P^-1 H^T lambda,  x += dx,  v += dx / dt.

Units and the compliance. The step solves A dv = b with A = m_coef M + k_coef K (for the
velocity change, :mod:`soft_tissue_sim.implicit_integration`). A force f [N] held during the
step adds dt f to b, so it changes v by dt A^-1 f and x by dt^2 A^-1 f. Here lambda is that
force [N] (not an impulse): W = dt^2 H P^-1 H^T [m/N] with P ~ A, which is eq. (4) (the paper
factorizes A / dt^2). P^-1 is the asynchronous rotated LDL^T preconditioner,
which includes the Sherman-Morrison cut correction and the identity padding of added nodes
(eq. 11-12). W is built by ``inner.delassus`` from the forward solves L^-1 P H^T alone, each
column walking only its reach in the elimination tree (:mod:`soft_tissue_sim.delassus`),
and dx = dt^2 P^-1 (H^T lambda) is one full solve; where the factor is on the device
(``ldlt.columns_on: device``) the columns P^-1 H^T are computed in one batch there instead
(``apply_columns``). For the ``jacobi`` and ``none``
preconditioners (no factorization), or with ``contact: {compliance: diagonal}``, P is the
block-Jacobi diagonal of A: cheap, but it ignores the coupling between nodes, so the
correction reaches the contact nodes only. It keeps bodies out of each other, but the
contact forces are not the physical ones and a body resting on a contact does not settle
(its support is carried by spurious strain and the contact nodes chatter). ``compliance:
exact`` uses A^-1 itself, one PCG solve per constraint row (correct with any
preconditioner, and costly). At rest, the contact forces balance the other forces exactly
only when P = A (``direct``, or ``async_ldlt`` refreshed every step); a lagging factor
makes them approximate in proportion to its lag. Fixed nodes do not move: their columns
of H are zero.

Sign convention. ``lambda`` and :meth:`ContactSolver.contact_forces` are forces ON THE
TISSUE [N], world frame. The wrench of an instrument or obstacle is the force ON THAT
OBJECT, F = -(sum of the contact forces on the tissue from it), and the torque
T = sum (p_c - o) x (-f_c) [N m] about the object's origin o (an instrument's tool-frame
origin, the tip centre, at the step's pose; a plane's point; the world origin for meshes),
with p_c the contact point on the object's surface.

Detection details: planes and instruments are tested at the free-motion positions (at
any depth; an instrument at the pose set for this step). Triangle features (self-collision,
mesh obstacles) are found at the step's start positions, within ``distance`` plus twice the
largest free-motion displacement of a surface node, and their gap is linearised to the free
motion (the features' normal and barycentric point are kept), so a node cannot tunnel
through a triangle in one step. Instruments against tissue triangles: per surface triangle,
the closest points of the capsule's axis and the triangle; a row only where that point of
the triangle is inside it or on an edge the triangle owns (each surface edge is owned by one
of its faces, the lowest index), vertices being the node contacts' (so nothing is counted
twice). Where the axis pierces a triangle (the tool, or the tissue's free motion, moved
more than the radius into the surface in one step), the triangle is pushed inwards until the
part of the axis over it is a radius above it. Not contacts: a piercing along an
instrument's blade (on the axis), which is a cut, and any piercing by a tool that was
already through the surface at the step's start (its previous pose against the step's start
positions: a tool inside a cut or a hole), around which the triangles are only kept a
radius away from the axis, like the nodes.

Limits: one triangle per node for self-collision (the nearest at the step's start); no
tissue edge-edge contacts; tools are assumed to come from outside the tissue (a piercing
pushes the triangle inwards); one linearisation per step: where the contact geometry turns
during the correction (a pressed triangle tilting under a thin tool), some penetration is
left, of second order in the correction (about 1 % of it in the tests); after the
correction, ``max_penetration`` is measured by a detection within ``distance`` at the
corrected positions.

Scene options (all optional)::

    contact:
      distance: 0.002        # [m] detection distance: pairs closer than this become constraints
      friction: 0.0          # Coulomb coefficient (obstacles / instruments may set their own)
      friction_cone: disk    # disk | pyramid
      max_iterations: 200    # Gauss-Seidel sweeps
      tolerance: 1.0e-8      # [m] LCP residual (largest W_rr |change of lambda_r| in a sweep)
      self_collision: false  # tissue surface nodes against the tissue's own triangles
      facing: 0.5            # same-component self contact only if n_node . n_triangle <= -facing
      self_depth: null       # [m] deepest penetration behind a tissue triangle taken as real
                             # (default 2 x distance); deeper is the far side of the body
      compliance: preconditioner   # preconditioner | diagonal | exact (see above)
      max_contacts: 2048     # keep the deepest ones beyond this
"""

from __future__ import annotations

import time
import warnings

import numpy as np
import scipy.sparse as sps
import warp as wp
from scipy.sparse.csgraph import connected_components

from .instrument import Instrument, MeshObstacle, PlaneObstacle, finite_number, obstacle_from_config
from .material import ParameterError
from .mesh import unique_rows

_F64 = wp.float64
COMPLIANCES = ("preconditioner", "diagonal", "exact")
DEFAULTS = {
    "distance": 0.002,
    "friction": 0.0,
    "friction_cone": "disk",
    "max_iterations": 200,
    "tolerance": 1e-8,
    "self_collision": False,
    "facing": 0.5,
    "self_depth": None,
    "compliance": "preconditioner",
    "max_contacts": 2048,
}


# ----------------------------------------------------------------------------- geometry
@wp.func
def closest_on_segment(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d):
    ab = b - a
    l2 = wp.dot(ab, ab)
    t = _F64(0.0)
    if l2 > _F64(0.0):
        t = wp.clamp(wp.dot(p - a, ab) / l2, _F64(0.0), _F64(1.0))
    return a + t * ab


@wp.func
def triangle_closest_bary(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d):
    """Barycentric coordinates of the point of triangle abc closest to p (Ericson 5.1.5)."""
    zero = _F64(0.0)
    one = _F64(1.0)
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
    return wp.vec3d(_F64(1.0) - v - w, v, w)


@wp.func
def closest_segment_segment(p1: wp.vec3d, q1: wp.vec3d, p2: wp.vec3d, q2: wp.vec3d):
    """Parameters (s, t) of the closest points p1 + s (q1 - p1) and p2 + t (q2 - p2) of two
    segments (Ericson 5.1.9); either may be a point."""
    zero = _F64(0.0)
    one = _F64(1.0)
    tiny = _F64(1e-30)
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


# ----------------------------------------------------------------------------- detection kernels
@wp.kernel
def plane_contacts_kernel(
    x: wp.array(dtype=wp.vec3d),
    nodes: wp.array(dtype=wp.int32),
    point: wp.vec3d,
    normal: wp.vec3d,
    distance: wp.float64,
    active: wp.array(dtype=wp.int32),
    gap: wp.array(dtype=wp.float64),
    nrm: wp.array(dtype=wp.vec3d),
    cpoint: wp.array(dtype=wp.vec3d),
):
    """Surface node k against the plane (point, normal): gap = n . (x - point)."""
    k = wp.tid()
    xp = x[nodes[k]]
    g = wp.dot(xp - point, normal)
    active[k] = 0
    if g < distance:
        active[k] = 1
        gap[k] = g
        nrm[k] = normal
        cpoint[k] = xp - g * normal


@wp.kernel
def capsule_contacts_kernel(
    x: wp.array(dtype=wp.vec3d),
    nodes: wp.array(dtype=wp.int32),
    a: wp.vec3d,
    b: wp.vec3d,
    radius: wp.float64,
    distance: wp.float64,
    active: wp.array(dtype=wp.int32),
    gap: wp.array(dtype=wp.float64),
    nrm: wp.array(dtype=wp.vec3d),
    cpoint: wp.array(dtype=wp.vec3d),
):
    """Surface node k against the capsule of axis ab: gap = |x - closest axis point| - radius."""
    k = wp.tid()
    xp = x[nodes[k]]
    c = closest_on_segment(xp, a, b)
    d = xp - c
    dist = wp.length(d)
    g = dist - radius
    active[k] = 0
    if g < distance:
        n = wp.vec3d(_F64(0.0), _F64(0.0), _F64(-1.0))
        if dist > _F64(1e-12) * radius:
            n = d / dist
        else:  # on the axis: push out perpendicular to it
            ax = b - a
            if wp.length(ax) > _F64(0.0):
                n = wp.normalize(wp.cross(ax, wp.vec3d(_F64(1.0), _F64(0.0), _F64(0.0))))
                if wp.length(wp.cross(ax, wp.vec3d(_F64(1.0), _F64(0.0), _F64(0.0)))) < _F64(1e-6) * wp.length(ax):
                    n = wp.normalize(wp.cross(ax, wp.vec3d(_F64(0.0), _F64(1.0), _F64(0.0))))
        active[k] = 1
        gap[k] = g
        nrm[k] = n
        cpoint[k] = c + radius * n


@wp.func
def segment_triangle_closest(a: wp.vec3d, b: wp.vec3d, va: wp.vec3d, vb: wp.vec3d, vc: wp.vec3d):
    """Closest points of the segment ab (a point if a == b) and the non-degenerate triangle
    (va, vb, vc): (s, w, d2, crossing) with the segment's point a + s (b - a), the triangle's
    point in barycentric coordinates w, their squared distance d2, and crossing = 1 where the
    segment passes through the triangle from one side of its plane to the other (both points
    are then the crossing point, d2 = 0). The minimum over the end points against the
    triangle and the segment against the three edges, unless it crosses."""
    zero = _F64(0.0)
    one = _F64(1.0)
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


@wp.kernel
def capsule_faces_kernel(
    x: wp.array(dtype=wp.vec3d),
    faces: wp.array(dtype=wp.vec3i),
    edge_owner: wp.array(dtype=wp.vec3i),
    a: wp.vec3d,
    b: wp.vec3d,
    radius: wp.float64,
    distance: wp.float64,
    blade_lo: wp.float64,
    blade_hi: wp.float64,
    inside: int,
    active: wp.array(dtype=wp.int32),
    gap: wp.array(dtype=wp.float64),
    nrm: wp.array(dtype=wp.vec3d),
    cpoint: wp.array(dtype=wp.vec3d),
    bary: wp.array(dtype=wp.vec3d),
):
    """Surface triangle f (outward normal by the right hand) against the capsule of axis ab,
    so that a tool thinner than the mesh spacing cannot slip between nodes.

    Only where the triangle's closest point to the axis is inside it, or on an edge this face
    owns (``edge_owner[f][k]`` = 1 for the edge from vertex k to vertex k + 1; one face per
    edge, so each edge counts once); a vertex is the node contacts' business. Normal from the
    axis point to the triangle point (the way the tissue is pushed, like the node contacts),
    gap = their distance - radius, point = on the capsule's surface. Where the axis pierces
    the triangle (or touches it), the tissue is pushed inwards (-face normal) until the part of
    the axis above the triangle (clipped to the triangle's prism) is ``radius`` above it:
    gap = (lowest signed height of that part) - radius, the point and barycentric weights at
    that lowest point. Not a contact, skipped: a piercing at an axis fraction in [blade_lo,
    blade_hi] (the instrument's blade: a cut in progress), and any piercing or touching when
    ``inside`` (the tool was already through the surface at the step's start, e.g. in a cut:
    the triangles around it are then only kept a radius away from the axis)."""
    f = wp.tid()
    active[f] = 0
    t = faces[f]
    va = x[t[0]]
    vb = x[t[1]]
    vc = x[t[2]]
    nf = wp.cross(vb - va, vc - va)
    area2 = wp.length(nf)
    if area2 <= _F64(0.0):
        return
    nf = nf / area2
    # quick reject: bounding sphere of the triangle against the capsule
    cen = (va + vb + vc) / _F64(3.0)
    rad = wp.max(wp.length(va - cen), wp.max(wp.length(vb - cen), wp.length(vc - cen)))
    if wp.length(cen - closest_on_segment(cen, a, b)) > radius + distance + rad:
        return
    zero = _F64(0.0)
    one = _F64(1.0)
    s, w, d2, crossing = segment_triangle_closest(a, b, va, vb, vc)
    # vertices belong to the node contacts; an edge to one of its two faces
    tiny = _F64(1e-12)
    nz = int(0)
    zero_at = int(-1)
    for k in range(3):
        if w[k] > tiny:
            nz += 1
        else:
            zero_at = k
    if nz <= 1:
        return
    if nz == 2 and edge_owner[f][(zero_at + 1) % 3] == 0:
        return
    dist = wp.sqrt(d2)
    if crossing == 0 and dist > tiny * radius:
        g = dist - radius
        if g < distance:
            p = a + s * (b - a)
            n = (w[0] * va + w[1] * vb + w[2] * vc - p) / dist
            active[f] = 1
            gap[f] = g
            nrm[f] = n
            cpoint[f] = p + radius * n
            bary[f] = w
        return
    # pierced or touched
    if inside != 0 or (crossing != 0 and s >= blade_lo and s <= blade_hi):
        return
    # the part of the axis inside the triangle's prism: s0 <= s <= s1
    s0 = zero
    s1 = one
    for k in range(3):
        u = x[t[k]]
        m = wp.cross(nf, x[t[(k + 1) % 3]] - u)  # towards the inside of the triangle
        h0 = wp.dot(a - u, m)
        dh = wp.dot(b - u, m) - h0
        if dh > zero:
            s0 = wp.max(s0, -h0 / dh)
        elif dh < zero:
            s1 = wp.min(s1, -h0 / dh)
        elif h0 < zero:
            s1 = -one
    da = wp.dot(a - va, nf)
    db = wp.dot(b - va, nf)
    sl = s  # rounding left the prism empty: the touching point
    if s0 <= s1:
        sl = s0
        if da + s1 * (db - da) < da + s0 * (db - da):
            sl = s1
    h = wp.min(zero, da + sl * (db - da))
    p = a + sl * (b - a)
    wl = plane_bary(p, va, vb, vc)
    wl = wp.vec3d(wp.max(wl[0], zero), wp.max(wl[1], zero), wp.max(wl[2], zero))
    wl = wl / (wl[0] + wl[1] + wl[2])
    n = -nf
    active[f] = 1
    gap[f] = h - radius
    nrm[f] = n
    cpoint[f] = p + radius * n
    bary[f] = wl


@wp.kernel
def capsule_crossings_kernel(
    x: wp.array(dtype=wp.vec3d),
    faces: wp.array(dtype=wp.vec3i),
    a: wp.vec3d,
    b: wp.vec3d,
    crossed: wp.array(dtype=wp.int32),
):
    """crossed[f] = 1 where the axis ab passes through surface triangle f."""
    f = wp.tid()
    crossed[f] = 0
    t = faces[f]
    va = x[t[0]]
    vb = x[t[1]]
    vc = x[t[2]]
    if wp.length(wp.cross(vb - va, vc - va)) <= _F64(0.0):
        return
    cen = (va + vb + vc) / _F64(3.0)
    rad = wp.max(wp.length(va - cen), wp.max(wp.length(vb - cen), wp.length(vc - cen)))
    if wp.length(cen - closest_on_segment(cen, a, b)) > rad:
        return
    s, w, d2, crossing = segment_triangle_closest(a, b, va, vb, vc)
    crossed[f] = crossing


@wp.kernel
def trimesh_contacts_kernel(
    x: wp.array(dtype=wp.vec3d),
    nodes: wp.array(dtype=wp.int32),
    mesh_id: wp.uint64,
    verts: wp.array(dtype=wp.vec3d),
    tris: wp.array(dtype=wp.vec3i),
    distance: wp.float64,
    search: wp.float32,
    active: wp.array(dtype=wp.int32),
    gap: wp.array(dtype=wp.float64),
    nrm: wp.array(dtype=wp.vec3d),
    cpoint: wp.array(dtype=wp.vec3d),
):
    """Surface node k against a static triangle mesh: the closest face from the float32 BVH
    (inside/outside from the angle-weighted pseudo normal), then the float64 closest point."""
    k = wp.tid()
    xp = x[nodes[k]]
    active[k] = 0
    q = wp.mesh_query_point_sign_normal(mesh_id, to_vec3f(xp), search)
    if q.result:
        t = tris[q.face]
        va = verts[t[0]]
        vb = verts[t[1]]
        vc = verts[t[2]]
        w = triangle_closest_bary(xp, va, vb, vc)
        qp = w[0] * va + w[1] * vb + w[2] * vc
        d = xp - qp
        dist = wp.length(d)
        nf = wp.normalize(wp.cross(vb - va, vc - va))
        # inside/outside: from the face normal in float64 where d is mostly along it (the
        # float32 pseudo-normal sign is unreliable within rounding of the surface), else
        # from the angle-weighted pseudo normal of the float32 query (edges and corners)
        sf = wp.dot(d, nf)
        sgn = _F64(1.0)
        if wp.abs(sf) >= _F64(0.5) * dist:
            if sf < _F64(0.0):
                sgn = _F64(-1.0)
        elif q.sign < wp.float32(0.0):
            sgn = _F64(-1.0)
        g = sgn * dist
        if g < distance:
            n = nf
            if dist > _F64(1e-12) * wp.length(vb - va):
                n = (sgn / dist) * d
            active[k] = 1
            gap[k] = g
            nrm[k] = n
            cpoint[k] = qp


@wp.kernel
def face_normals_kernel(
    x: wp.array(dtype=wp.vec3d),
    faces: wp.array(dtype=wp.vec3i),
    node_normal: wp.array(dtype=wp.vec3d),
):
    """Area-weighted outward normals accumulated on the surface nodes."""
    f = wp.tid()
    t = faces[f]
    n = wp.cross(x[t[1]] - x[t[0]], x[t[2]] - x[t[0]])
    for j in range(3):
        wp.atomic_add(node_normal, t[j], n)


@wp.kernel
def copy_points_f32_kernel(x: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    out[i] = to_vec3f(x[i])


@wp.kernel
def self_contacts_kernel(
    x: wp.array(dtype=wp.vec3d),
    nodes: wp.array(dtype=wp.int32),
    mesh_id: wp.uint64,
    faces: wp.array(dtype=wp.vec3i),
    face_comp: wp.array(dtype=wp.int32),
    node_comp: wp.array(dtype=wp.int32),
    node_normal: wp.array(dtype=wp.vec3d),
    ring_offsets: wp.array(dtype=wp.int32),
    ring_nodes: wp.array(dtype=wp.int32),
    distance: wp.float64,
    margin: wp.float32,
    facing: wp.float64,
    depth: wp.float64,
    active: wp.array(dtype=wp.int32),
    tri: wp.array(dtype=wp.int32),
    bary: wp.array(dtype=wp.vec3d),
    gap: wp.array(dtype=wp.float64),
    nrm: wp.array(dtype=wp.vec3d),
    cpoint: wp.array(dtype=wp.vec3d),
):
    """Surface node k against the tissue's surface triangles within ``distance``.

    Skipped: triangles incident to the node or to its tet neighbours (the node's own
    neighbourhood), and triangles of the same connected component unless they face the node
    (node normal . triangle normal <= -facing, e.g. the two sides of a cut). In front of a
    triangle the gap is the distance to it (normal from the closest point to the node);
    behind it, a penetration counts only if the node projects inside the triangle and lies
    at most ``depth`` behind it (gap = signed plane distance, normal = the triangle's): the
    positions searched are the step's start, where the last correction left at most a
    contact tolerance of penetration, so a node deeper behind a triangle is on the body's
    far side, not in it (taking it pushes the body through itself). The candidate of
    smallest |gap| wins.
    """
    k = wp.tid()
    p = nodes[k]
    xp = x[p]
    active[k] = 0
    xf = to_vec3f(xp)
    lo = wp.vec3(xf[0] - margin, xf[1] - margin, xf[2] - margin)
    hi = wp.vec3(xf[0] + margin, xf[1] + margin, xf[2] + margin)
    nn = node_normal[p]
    nlen = wp.length(nn)
    if nlen > _F64(0.0):
        nn = nn / nlen
    best = distance
    best_face = int(-1)
    best_w = wp.vec3d()
    best_g = _F64(0.0)
    best_n = wp.vec3d()
    best_q = wp.vec3d()
    query = wp.mesh_query_aabb(mesh_id, lo, hi)
    for f in query:
        t = faces[f]
        ok = t[0] != p and t[1] != p and t[2] != p
        if ok:
            for j in range(ring_offsets[p], ring_offsets[p + 1]):
                r = ring_nodes[j]
                if r == t[0] or r == t[1] or r == t[2]:
                    ok = False
        va = x[t[0]]
        vb = x[t[1]]
        vc = x[t[2]]
        nt = wp.cross(vb - va, vc - va)
        area2 = wp.length(nt)
        if area2 <= _F64(0.0):
            ok = False
        if ok:
            nt = nt / area2
            if face_comp[f] == node_comp[p]:
                if nlen <= _F64(0.0) or wp.dot(nn, nt) > -facing:
                    ok = False
        if ok:
            w = triangle_closest_bary(xp, va, vb, vc)
            q = w[0] * va + w[1] * vb + w[2] * vc
            d = xp - q
            s = wp.dot(d, nt)
            g = _F64(0.0)
            n = nt
            valid = False
            if s >= _F64(0.0):
                dist = wp.length(d)
                g = dist
                if dist > _F64(1e-9) * wp.sqrt(area2):
                    n = d / dist
                valid = True
            else:
                wb = plane_bary(xp, va, vb, vc)
                if -s <= depth and wb[0] >= _F64(-1e-9) and wb[1] >= _F64(-1e-9) and wb[2] >= _F64(-1e-9):
                    w = wp.vec3d(wp.max(wb[0], _F64(0.0)), wp.max(wb[1], _F64(0.0)), wp.max(wb[2], _F64(0.0)))
                    w = w / (w[0] + w[1] + w[2])
                    q = w[0] * va + w[1] * vb + w[2] * vc
                    g = s
                    valid = True
            if valid and wp.abs(g) < best:
                best = wp.abs(g)
                best_face = f
                best_w = w
                best_g = g
                best_n = n
                best_q = q
    if best_face >= 0:
        active[k] = 1
        tri[k] = best_face
        bary[k] = best_w
        gap[k] = best_g
        nrm[k] = best_n
        cpoint[k] = best_q


# ----------------------------------------------------------------------------- LCP kernel
@wp.func
def contact_update(
    W: wp.array2d(dtype=wp.float64),
    d0: wp.array(dtype=wp.float64),
    lam: wp.array(dtype=wp.float64),
    r: int,
    rows: int,
    mu: wp.float64,
    pyramid: int,
):
    """Projected Gauss-Seidel update of the contact whose normal row is r, from the current
    lambda (not written). Returns (lambda_n, lambda_t1, lambda_t2, change), the change being
    the largest W_rr |new - old| of its rows [m]; for an active normal row that is |delta_n|."""
    zero = _F64(0.0)
    m = W.shape[0]
    dn = d0[r]
    for j in range(m):
        dn += W[r, j] * lam[j]
    ln = wp.max(zero, lam[r] - dn / W[r, r])
    change = W[r, r] * wp.abs(ln - lam[r])
    l1 = zero
    l2 = zero
    if rows == 3:
        dln = ln - lam[r]  # the tangential gaps see the new normal force
        t1 = d0[r + 1] + W[r + 1, r] * dln
        t2 = d0[r + 2] + W[r + 2, r] * dln
        for j in range(m):
            t1 += W[r + 1, j] * lam[j]
            t2 += W[r + 2, j] * lam[j]
        a11 = W[r + 1, r + 1]
        a22 = W[r + 2, r + 2]
        a12 = _F64(0.5) * (W[r + 1, r + 2] + W[r + 2, r + 1])
        det = a11 * a22 - a12 * a12
        l1 = lam[r + 1]
        l2 = lam[r + 2]
        if det > zero:  # stick: zero tangential displacement
            l1 = l1 - (a22 * t1 - a12 * t2) / det
            l2 = l2 - (a11 * t2 - a12 * t1) / det
        lim = mu * ln
        if pyramid != 0:
            l1 = wp.clamp(l1, -lim, lim)
            l2 = wp.clamp(l2, -lim, lim)
        else:
            lt = wp.sqrt(l1 * l1 + l2 * l2)
            if lt > lim:  # slide: on the disk's rim
                s = zero
                if lt > zero:
                    s = lim / lt
                l1 = l1 * s
                l2 = l2 * s
        change = wp.max(change, wp.max(a11 * wp.abs(l1 - lam[r + 1]), a22 * wp.abs(l2 - lam[r + 2])))
    return ln, l1, l2, change


@wp.func
def pgs_residual(
    W: wp.array2d(dtype=wp.float64),
    d0: wp.array(dtype=wp.float64),
    lam: wp.array(dtype=wp.float64),
    row_start: wp.array(dtype=wp.int32),
    n_rows: wp.array(dtype=wp.int32),
    mu: wp.array(dtype=wp.float64),
    pyramid: int,
):
    """Largest change a (Jacobi) sweep would make: 0 exactly at a solution of the LCP [m]."""
    res = _F64(0.0)
    for c in range(row_start.shape[0]):
        ln, l1, l2, ch = contact_update(W, d0, lam, row_start[c], n_rows[c], mu[c], pyramid)
        res = wp.max(res, ch)
    return res


@wp.kernel
def pgs_kernel(
    W: wp.array2d(dtype=wp.float64),
    d0: wp.array(dtype=wp.float64),
    row_start: wp.array(dtype=wp.int32),
    n_rows: wp.array(dtype=wp.int32),
    mu: wp.array(dtype=wp.float64),
    max_iterations: int,
    tolerance: wp.float64,
    pyramid: int,
    lam: wp.array(dtype=wp.float64),
    info: wp.array(dtype=wp.float64),
):
    """Projected Gauss-Seidel for delta = W lambda + d0 with Signorini-Coulomb contacts.

    Contact c owns row row_start[c] (normal) and, if n_rows[c] == 3, the two tangent rows
    after it. Sweeps until the largest change (see :func:`contact_update`) of a sweep and the
    residual (:func:`pgs_residual`) are <= tolerance. info = [sweeps, residual].
    One thread: launched with dim 1 on the CPU.
    """
    nc = row_start.shape[0]
    it = int(0)
    res = _F64(-1.0)
    for sweep in range(max_iterations):
        change = _F64(0.0)
        for c in range(nc):
            r = row_start[c]
            ln, l1, l2, ch = contact_update(W, d0, lam, r, n_rows[c], mu[c], pyramid)
            lam[r] = ln
            if n_rows[c] == 3:
                lam[r + 1] = l1
                lam[r + 2] = l2
            change = wp.max(change, ch)
        it = sweep + 1
        res = _F64(-1.0)
        if change <= tolerance:  # converged if the residual (a sweep not applied) agrees
            res = pgs_residual(W, d0, lam, row_start, n_rows, mu, pyramid)
            if res <= tolerance:
                break
    if res < _F64(0.0):
        res = pgs_residual(W, d0, lam, row_start, n_rows, mu, pyramid)
    info[0] = _F64(it)
    info[1] = res


# ----------------------------------------------------------------------------- host side
def _options(cfg) -> dict:
    if not isinstance(cfg, dict):
        raise ParameterError(f"scene 'contact' must be a mapping, got {cfg!r}")
    unknown = set(cfg) - set(DEFAULTS)
    if unknown:
        raise ParameterError(f"contact: unknown keys {sorted(unknown)} (allowed: {sorted(DEFAULTS)})")
    o = {**DEFAULTS, **{k: v for k, v in cfg.items() if v is not None}}
    o["distance"] = finite_number("contact distance", o["distance"], minimum=0.0, strict=True)
    o["friction"] = finite_number("contact friction", o["friction"], minimum=0.0)
    o["tolerance"] = finite_number("contact tolerance", o["tolerance"], minimum=0.0, strict=True)
    o["facing"] = finite_number("contact facing", o["facing"], minimum=-1.0)
    if o["facing"] > 1.0:
        raise ParameterError(f"contact facing is a cosine in [-1, 1], got {o['facing']}")
    o["self_depth"] = (2.0 * o["distance"] if o["self_depth"] is None
                       else finite_number("contact self_depth", o["self_depth"], minimum=0.0, strict=True))
    for key in ("max_iterations", "max_contacts"):
        if isinstance(o[key], bool) or not isinstance(o[key], int) or o[key] < 1:
            raise ParameterError(f"contact {key} must be an integer >= 1, got {o[key]!r}")
    if not isinstance(o["self_collision"], bool):
        raise ParameterError(f"contact self_collision must be true or false, got {o['self_collision']!r}")
    if o["friction_cone"] not in ("disk", "pyramid"):
        raise ParameterError(f"contact friction_cone must be 'disk' or 'pyramid', got {o['friction_cone']!r}")
    if o["compliance"] not in COMPLIANCES:
        raise ParameterError(f"contact compliance must be one of {', '.join(COMPLIANCES)}, got {o['compliance']!r}")
    return o


def blade_span(inst: Instrument) -> tuple[float, float]:
    """(lo, hi): the fractions of the capsule's axis along which its blade runs (a piercing
    there is a cut, not a contact), or (1, 0), none, for a tool without a blade on its axis
    (a blade further from the axis than the radius, e.g. beside or below the shaft)."""
    bl = getattr(inst, "blade", None)
    if bl is None or inst.length <= 0.0 or np.hypot(bl[:, 0], bl[:, 1]).max() > inst.radius:
        return 1.0, 0.0
    z = bl[:, 2] / inst.length
    lo, hi = max(float(z.min()), 0.0), min(float(z.max()), 1.0)
    return (lo, hi) if lo < hi else (1.0, 0.0)


def _positive_definite(W: np.ndarray, dense_check_up_to: int = 1500) -> bool:
    """Is the symmetric compliance W usable by Gauss-Seidel: finite, positive diagonal and, for
    sizes up to ``dense_check_up_to``, no negative eigenvalue beyond rounding (a Cholesky
    factorization of W + 1e-10 max(diag W) I that succeeds). Singular is usable: rows that
    repeat a constraint (a node contact and a face contact at that node, each with its two
    tangent rows) make W singular, not indefinite."""
    if not np.all(np.isfinite(W)) or np.any(np.diag(W) <= 0.0):
        return False
    if len(W) > dense_check_up_to:
        return True
    try:
        np.linalg.cholesky(W + (1e-10 * float(np.max(np.diag(W)))) * np.eye(len(W)))
    except np.linalg.LinAlgError:
        return False
    return True


def tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (k, 3) completing the unit normals n (k, 3) to right-handed frames."""
    a = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


def edge_ownership(faces: np.ndarray) -> np.ndarray:
    """(k, 3) int32: 1 where face f owns its edge from vertex j to vertex j + 1 (mod 3). Each
    undirected edge is owned once, by the lowest-index face that has it."""
    faces = np.asarray(faces).reshape(-1, 3)
    owner = np.zeros(3 * len(faces), np.int32)
    if len(faces):
        edges = np.stack([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], axis=1).reshape(-1, 2)
        _, first = unique_rows(np.sort(edges, axis=1), return_index=True)
        owner[first] = 1
    return owner.reshape(-1, 3)


class _Topology:
    """Surface data of one mesh; rebuilt when cutting changes the mesh (never reused across
    a change of node count or tets)."""

    def __init__(self, fem, self_collision: bool):
        mesh, dev = fem.mesh, fem.device
        self.keys = (fem.mesh, fem.mesh.tets, fem.tets, fem.n_nodes)
        self.n_nodes = fem.n_nodes
        self.faces = mesh.boundary_faces()
        self.surface = np.unique(self.faces).astype(np.int32)
        ns = max(len(self.surface), 1)
        self.nodes = wp.array(self.surface, dtype=wp.int32, device=dev)
        # one output slot per surface node, reused by every detection launch
        self.active = wp.zeros(ns, dtype=wp.int32, device=dev)
        self.gap = wp.zeros(ns, dtype=wp.float64, device=dev)
        self.normal = wp.zeros(ns, dtype=wp.vec3d, device=dev)
        self.point = wp.zeros(ns, dtype=wp.vec3d, device=dev)
        self.tri = wp.zeros(ns, dtype=wp.int32, device=dev)
        self.bary = wp.zeros(ns, dtype=wp.vec3d, device=dev)
        self.scale = float(np.ptp(mesh.points, axis=0).max()) or 1.0
        # faces on the device, and which face owns each surface edge: edge_owner[f, k] = 1 where
        # face f owns its edge from vertex k to vertex k + 1, each edge owned by exactly one of
        # the faces sharing it, the lowest index (np.unique's first occurrence, face-major order)
        nf = max(len(self.faces), 1)
        self.faces_wp = wp.array(self.faces if len(self.faces) else np.zeros((1, 3), np.int32), dtype=wp.vec3i,
                                 device=dev)
        self.edge_owner = wp.array(edge_ownership(self.faces) if len(self.faces) else np.zeros((1, 3), np.int32),
                                   dtype=wp.vec3i, device=dev)
        # one output slot per surface face (instrument against triangles)
        self.f_active = wp.zeros(nf, dtype=wp.int32, device=dev)
        self.f_gap = wp.zeros(nf, dtype=wp.float64, device=dev)
        self.f_normal = wp.zeros(nf, dtype=wp.vec3d, device=dev)
        self.f_point = wp.zeros(nf, dtype=wp.vec3d, device=dev)
        self.f_bary = wp.zeros(nf, dtype=wp.vec3d, device=dev)
        self.f_crossed = wp.zeros(nf, dtype=wp.int32, device=dev)
        self.wmesh = None
        if self_collision and len(self.faces):
            n = fem.n_nodes
            e = mesh.edges()
            adj = sps.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
            adj = (adj + adj.T).tocsr()
            adj.sort_indices()
            _, comp = connected_components(adj, directed=False)
            self.n_components = int(comp.max()) + 1
            self.node_comp = wp.array(comp.astype(np.int32), dtype=wp.int32, device=dev)
            self.face_comp = wp.array(comp[self.faces[:, 0]].astype(np.int32), dtype=wp.int32, device=dev)
            self.ring_offsets = wp.array(adj.indptr.astype(np.int32), dtype=wp.int32, device=dev)
            self.ring_nodes = wp.array(adj.indices.astype(np.int32), dtype=wp.int32, device=dev)
            self.points32 = wp.array(mesh.points.astype(np.float32), dtype=wp.vec3, device=dev)
            self.node_normal = wp.zeros(n, dtype=wp.vec3d, device=dev)
            self.wmesh = wp.Mesh(points=self.points32, indices=wp.array(self.faces.reshape(-1), dtype=wp.int32,
                                                                          device=dev))

    def matches(self, fem) -> bool:
        k = self.keys
        return fem.mesh is k[0] and fem.mesh.tets is k[1] and fem.tets is k[2] and fem.n_nodes == k[3]


class ContactSolver:
    """Instruments, obstacles, detection and the LCP response of one simulation.

    Built by :class:`soft_tissue_sim.scene.Simulation` only when the scene names
    instruments, obstacles or self-collision. See the module docstring for the method,
    the units and the sign conventions.
    """

    def __init__(self, sim, options: dict, instruments: list, obstacles: list):
        self.options = _options(options or {})
        o = self.options
        self.device = sim.fem.device
        pts = sim.mesh.points
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        self.instruments: dict[str, Instrument] = {}
        if not isinstance(instruments, list) or not isinstance(obstacles, list):
            raise ParameterError("scene 'instruments' and 'obstacles' must be lists")
        for k, cfg in enumerate(instruments):
            # default pose: shaft up (+z), tip sphere 2 detection distances above the tissue's top centre
            r = cfg.get("radius", 0.0) if isinstance(cfg, dict) else 0.0
            try:
                r = float(r)
            except (TypeError, ValueError):
                r = 0.0
            default = [0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), hi[2] + r + 2.0 * o["distance"]]
            inst = Instrument.from_config(cfg, k, default)
            if inst.name in self.instruments:
                raise ParameterError(f"instrument name {inst.name!r} used twice")
            self.instruments[inst.name] = inst
        self.obstacles = {}
        for k, cfg in enumerate(obstacles):
            obs = obstacle_from_config(cfg, k)
            if obs.name in self.obstacles or obs.name in self.instruments:
                raise ParameterError(f"obstacle name {obs.name!r} used twice (names are shared with instruments)")
            self.obstacles[obs.name] = obs
        self.objects = list(self.instruments.values()) + list(self.obstacles.values())
        self._topo: _Topology | None = None
        self._warm: dict = {}
        self._empty_contacts()
        self.last_stats: dict = {}
        self.compliance_used = "none"
        self.compliance_fallbacks = 0  # steps whose preconditioner compliance was not positive definite

    # ------------------------------------------------------------------ API
    def instrument_names(self) -> list[str]:
        return list(self.instruments)

    def obstacle_names(self) -> list[str]:
        return list(self.obstacles)

    def instrument(self, name: str) -> Instrument:
        try:
            return self.instruments[name]
        except KeyError:
            raise ValueError(f"unknown instrument {name!r}; this scene has {self.instrument_names()}") from None

    def set_instrument_pose(self, name, position, quaternion_xyzw, linear_velocity=None, angular_velocity=None):
        """Pose for the next step (world frame, quaternion x, y, z, w). ValueError on an
        unknown name, NaN/inf, or a non-unit quaternion; the previous pose is then kept."""
        self.instrument(name).set_pose(position, quaternion_xyzw, linear_velocity, angular_velocity)

    def instrument_wrench(self, name) -> tuple[np.ndarray, np.ndarray]:
        """(force, torque) ON the instrument from the last step's contacts, world frame,
        torque about the tool frame's origin [N, N m]."""
        inst = self.instrument(name)
        return inst.force.copy(), inst.torque.copy()

    def wrench(self, name) -> tuple[np.ndarray, np.ndarray]:
        """(force, torque) ON any named instrument or obstacle (see the module docstring)."""
        obj = self.instruments.get(name) or self.obstacles.get(name)
        if obj is None:
            raise ValueError(f"unknown instrument or obstacle {name!r}; this scene has "
                             f"{self.instrument_names() + self.obstacle_names()}")
        return obj.force.copy(), obj.torque.copy()

    def contact_points(self) -> np.ndarray:
        """(k, 3) points (on the other surface) of the last step's contacts that carry force."""
        c = self.contacts
        return c["point"][c["lambda_n"] > 0.0].copy()

    def contact_forces(self) -> np.ndarray:
        """(k, 3) forces ON THE TISSUE [N] at :meth:`contact_points`, world frame."""
        c = self.contacts
        return c["force"][c["lambda_n"] > 0.0].copy()

    def reset(self, sim=None) -> None:
        for inst in self.instruments.values():
            inst.reset()
        for obs in self.obstacles.values():
            obs.force[:] = 0.0
            obs.torque[:] = 0.0
        self._topo = None
        self._warm = {}
        self._empty_contacts()
        self.last_stats = {}
        self.compliance_fallbacks = 0

    # ------------------------------------------------------------ detection
    def _topology(self, sim) -> _Topology:
        if self._topo is None or not self._topo.matches(sim.fem):
            self._topo = _Topology(sim.fem, self.options["self_collision"])
        return self._topo

    def _empty_contacts(self) -> None:
        z3 = np.zeros((0, 3))
        self.contacts = {"node": np.zeros(0, np.int64), "obj": np.zeros(0, np.int64), "gap": np.zeros(0),
                         "normal": z3, "point": z3, "tri": np.zeros((0, 3), np.int64), "bary": z3,
                         "lambda_n": np.zeros(0), "force": z3}

    def _collect(self, topo: _Topology, obj: int, with_tri: bool, parts: list) -> None:
        act = topo.active.numpy()[: len(topo.surface)].astype(bool)
        if not act.any():
            return
        k = int(act.sum())
        part = {"node": topo.surface[act].astype(np.int64), "obj": np.full(k, obj, np.int64),
                "gap": topo.gap.numpy()[act], "normal": topo.normal.numpy()[act], "point": topo.point.numpy()[act],
                "tri": np.full((k, 3), -1, np.int64), "bary": np.zeros((k, 3))}
        if with_tri:
            part["tri"] = topo.faces[topo.tri.numpy()[act]].astype(np.int64)
            part["bary"] = topo.bary.numpy()[act]
        parts.append(part)

    def _capsule_faces(self, topo: _Topology, oi: int, inst: Instrument, x: wp.array, a: np.ndarray, b: np.ndarray,
                       x_start: wp.array | None, parts: list) -> None:
        """Instrument ``oi`` against the surface triangles: rows with node -1, the triangle's
        nodes in ``tri`` and the tissue point's barycentric weights in ``bary``. With
        ``x_start`` (the tissue at the step's start), a tool whose axis then, at its previous
        pose, went through the surface is inside: its piercings are not contacts."""
        nf = len(topo.faces)
        if nf == 0:
            return
        inside = 0
        if x_start is not None:
            pa, pb = inst.segment_world(inst.previous_step_pose)
            wp.launch(capsule_crossings_kernel, nf, [x_start, topo.faces_wp, wp.vec3d(*pa), wp.vec3d(*pb)],
                      outputs=[topo.f_crossed], device=self.device)
            inside = int(topo.f_crossed.numpy()[:nf].any())
        lo, hi = blade_span(inst)
        wp.launch(capsule_faces_kernel, nf,
                  [x, topo.faces_wp, topo.edge_owner, wp.vec3d(*a), wp.vec3d(*b), inst.radius,
                   self.options["distance"], lo, hi, inside],
                  outputs=[topo.f_active, topo.f_gap, topo.f_normal, topo.f_point, topo.f_bary], device=self.device)
        act = topo.f_active.numpy()[:nf].astype(bool)
        if not act.any():
            return
        k = int(act.sum())
        parts.append({"node": np.full(k, -1, np.int64), "obj": np.full(k, oi, np.int64),
                      "gap": topo.f_gap.numpy()[act], "normal": topo.f_normal.numpy()[act],
                      "point": topo.f_point.numpy()[act], "tri": topo.faces[act].astype(np.int64),
                      "bary": topo.f_bary.numpy()[act]})

    def detect(self, sim, x: wp.array | None = None, x_features: wp.array | None = None, reach: float = 0.0,
               x_start: wp.array | None = None) -> dict:
        """Contacts as numpy arrays, one row per contact: node, obj (index in ``objects``, -1
        for self-collision), gap, normal, point, tri, bary. A row is a tissue node (``tri`` -1)
        against an object, a tissue node against a tissue triangle (self-collision: obj -1,
        the node and the triangle), or a tissue triangle against an instrument (node -1, the
        tissue point sum_i bary_i x[tri_i]). Planes and instruments are tested
        at positions ``x`` (default ``sim.integrator.x``) within ``distance``, triangle
        features (self-collision, mesh obstacles) at ``x_features`` (default ``x``) within
        ``distance + reach``. ``x_start``: the tissue at the step's start, where the
        instruments' previous poses tell which tools were already through the surface (their
        piercings of triangles are then not contacts); without it every piercing is one."""
        topo = self._topology(sim)
        dev, dist = self.device, self.options["distance"]
        x = sim.integrator.x if x is None else x
        xf = x if x_features is None else x_features
        far = dist + float(reach)  # search radius of the triangle features
        ns = len(topo.surface)
        out = [topo.active, topo.gap, topo.normal, topo.point]
        parts: list = []
        if ns == 0:
            return self._concat(parts)
        for oi, obj in enumerate(self.objects):
            if isinstance(obj, Instrument):
                a, b = obj.segment_world()
                wp.launch(capsule_contacts_kernel, ns, [x, topo.nodes, wp.vec3d(*a), wp.vec3d(*b), obj.radius, dist],
                          outputs=out, device=dev)
                self._collect(topo, oi, False, parts)
                self._capsule_faces(topo, oi, obj, x, a, b, x_start, parts)
                continue
            elif isinstance(obj, PlaneObstacle):
                wp.launch(plane_contacts_kernel, ns, [x, topo.nodes, wp.vec3d(*obj.point), wp.vec3d(*obj.normal), dist],
                          outputs=out, device=dev)
            elif isinstance(obj, MeshObstacle):
                wmesh, verts, tris = obj.warp_mesh(dev)
                wp.launch(trimesh_contacts_kernel, ns,
                          [xf, topo.nodes, wmesh.id, verts, tris, far, float(far * 1.001 + 1e-6 * topo.scale)],
                          outputs=out, device=dev)
            self._collect(topo, oi, False, parts)
        if topo.wmesh is not None:
            wp.launch(copy_points_f32_kernel, topo.n_nodes, [xf, topo.points32], device=dev)
            topo.wmesh.refit()
            topo.node_normal.zero_()
            wp.launch(face_normals_kernel, len(topo.faces), [xf, topo.faces_wp, topo.node_normal], device=dev)
            wp.launch(self_contacts_kernel, ns,
                      [xf, topo.nodes, topo.wmesh.id, topo.faces_wp, topo.face_comp, topo.node_comp, topo.node_normal,
                       topo.ring_offsets, topo.ring_nodes, far, float(far * 1.001 + 1e-6 * topo.scale),
                       self.options["facing"], self.options["self_depth"]],
                      outputs=[topo.active, topo.tri, topo.bary, topo.gap, topo.normal, topo.point], device=dev)
            self._collect(topo, -1, True, parts)
        return self._concat(parts)

    @staticmethod
    def _concat(parts: list) -> dict:
        keys = ("node", "obj", "gap", "normal", "point", "tri", "bary")
        if not parts:
            z3 = np.zeros((0, 3))
            return {"node": np.zeros(0, np.int64), "obj": np.zeros(0, np.int64), "gap": np.zeros(0), "normal": z3,
                    "point": z3, "tri": np.zeros((0, 3), np.int64), "bary": z3}
        return {k: np.concatenate([p[k] for p in parts]) for k in keys}

    # ------------------------------------------------------------ compliance
    def _compliance(self, sim, H: sps.csr_matrix, mode: str | None = None):
        """(W / dt^2 = H P^-1 H^T dense, a function lam -> P^-1 H^T lam, the kind used)."""
        mode = self.options["compliance"] if mode is None else mode
        inner = getattr(sim.preconditioner, "inner", None)
        if mode == "preconditioner" and inner is None:
            mode = "diagonal"  # jacobi / none: no factorization to use
        Yt = None  # rows: P^-1 applied to the rows of H
        if mode == "preconditioner":
            Hd = H.toarray()  # (m, 3n): one row per constraint
            try:
                W = inner.delassus(Hd.T) if hasattr(inner, "delassus") else None
                if W is not None:  # forward solves alone; dx = P^-1 H^T lambda by one full solve
                    return W, (lambda lam: inner.apply_columns((H.T @ lam)[:, None])[:, 0]), mode
                if hasattr(inner, "apply_columns"):
                    Yt = np.ascontiguousarray(np.asarray(inner.apply_columns(np.ascontiguousarray(Hd.T))).T)
                else:
                    Yt = np.empty_like(Hd)
                    for r in range(Hd.shape[0]):
                        inner.apply(Hd[r], Yt[r])
            except ValueError as exc:  # e.g. the factor is for another DOF count just after a cut
                warnings.warn(f"contact: preconditioner compliance unavailable ({exc}); using the diagonal",
                              stacklevel=2)
                mode, Yt = "diagonal (fallback)", None
        elif mode == "exact":  # A^-1 by one PCG solve per row, to the integrator's tolerance
            integ = sim.integrator
            Hd = H.toarray()
            Yt = np.empty_like(Hd)
            dev = sim.fem.device
            y = wp.zeros(sim.fem.n_nodes, dtype=wp.vec3d, device=dev)
            for r in range(Hd.shape[0]):
                integ.cg.solve(integ.matvec, wp.array(Hd[r].reshape(-1, 3), dtype=wp.vec3d, device=dev), y,
                               integ.preconditioner)
                Yt[r] = y.numpy().reshape(-1)
        if Yt is not None:
            return np.asarray(H @ Yt.T), (lambda lam: Yt.T @ lam), mode
        fem, integ = sim.fem, sim.integrator
        n = fem.n_nodes
        D = wp.zeros(n, dtype=wp.mat33d, device=fem.device)
        fem.diagonal_blocks(integ.m_coef, integ.k_coef, D)
        Dinv = np.linalg.inv(D.numpy())
        B = sps.bsr_matrix((Dinv, np.arange(n), np.arange(n + 1)), shape=(3 * n, 3 * n)).tocsr()
        Y = (B @ H.T).tocsc()
        return (H @ Y).toarray(), (lambda lam: Y @ lam), mode

    # ------------------------------------------------------------------ step
    def step(self, sim) -> dict:
        """Detect, solve the LCP, correct x and v, update the wrenches. Returns statistics."""
        t0 = time.perf_counter()
        o = self.options
        for inst in self.instruments.values():
            inst.begin_step()
        integ, dt = sim.integrator, sim.dt
        x = integ.x.numpy().copy()  # free motion
        v = integ.v.numpy().copy()
        x_start = x - dt * v  # the step's start (x = x_start + dt v)
        # Planes and instruments (exact half-spaces / the tool's new pose) are tested at the
        # free-motion positions, at any depth. Triangle features are found at the step's start
        # and their gap is linearised to the free motion; the search reaches `distance` plus
        # how far surface nodes moved in the free motion (twice: node and triangle may close
        # in on each other), so that nothing tunnels through a triangle in one step.
        surf = self._topology(sim).surface
        moved = float(np.sqrt(np.max(np.sum((x[surf] - x_start[surf]) ** 2, axis=1)))) if len(surf) else 0.0
        xs_wp = wp.array(x_start, dtype=wp.vec3d, device=self.device)
        c = self.detect(sim, integ.x, xs_wp, reach=2.0 * moved, x_start=xs_wp)
        tri_feature = c["obj"] < 0
        for oi, obj in enumerate(self.objects):
            if isinstance(obj, MeshObstacle):
                tri_feature |= c["obj"] == oi
        if tri_feature.any():
            # The search radius is the largest motion of any surface node, so one fast fragment
            # widens it for all. A pair can only close in by the motion of its own node and
            # triangle: farther pairs cannot touch in this step and are dropped before the LCP.
            mv = np.linalg.norm(x - x_start, axis=1)
            tri_mv = np.where(c["obj"] < 0, mv[np.clip(c["tri"], 0, None)].max(axis=1), 0.0)
            reach_row = o["distance"] + mv[np.clip(c["node"], 0, None)] + tri_mv
            near = ~tri_feature | (c["gap"] <= reach_row)
            if not near.all():
                c = {key: val[near] for key, val in c.items()}
                tri_feature = tri_feature[near]
            own = np.flatnonzero(c["obj"] < 0)  # tissue triangles move: their point follows the free motion
            c["point"][own] = np.einsum("ks,ksj->kj", c["bary"][own], x[c["tri"][own]])
            c["gap"][tri_feature] = np.einsum("kj,kj->k", c["normal"][tri_feature],
                                              x[c["node"][tri_feature]] - c["point"][tri_feature])
        free = sim.fem.free.numpy().copy()
        k = len(c["node"])
        # Jacobian blocks: up to 4 nodes per contact with weights: the tissue point moves with
        # +1 on its node, or +w_i on the triangle's nodes where it is a triangle's point
        # (instrument against a face, node -1); a self-collision triangle is the other surface,
        # -w_i. ws4 are these (the tissue point's relative displacement), w4 the same zeroed on
        # fixed nodes. Contacts whose nodes are all fixed cannot be acted on: dropped.
        nodes4 = np.concatenate([c["node"][:, None], c["tri"]], axis=1)
        tri_sign = np.where(c["obj"] < 0, -1.0, 1.0)[:, None]
        ws4 = np.concatenate([np.ones((k, 1)), tri_sign * c["bary"]], axis=1) * (nodes4 >= 0)
        w4 = ws4 * free[np.clip(nodes4, 0, None)]
        keep = np.einsum("ij,ij->i", w4, w4) > 0.0
        if keep.sum() > o["max_contacts"]:
            order = np.argsort(np.where(keep, c["gap"], np.inf), kind="stable")[: o["max_contacts"]]
            keep = np.zeros(k, bool)
            keep[order] = True
        c = {key: val[keep] for key, val in c.items()}
        nodes4, w4, ws4 = nodes4[keep], w4[keep], ws4[keep]
        k = len(c["node"])
        stats = {"contacts": k, "self_contacts": int(np.sum(c["obj"] < 0)),
                 "face_contacts": int(np.sum((c["node"] < 0) & (c["obj"] >= 0))), "active_contacts": 0,
                 "gs_iterations": 0, "lcp_residual": 0.0, "max_penetration": 0.0, "contact_ms": 0.0}
        for obj in self.objects:
            obj.force, obj.torque = np.zeros(3), np.zeros(3)
        if k == 0:
            self._empty_contacts()
            self._warm = {}
        else:
            self._respond(sim, c, nodes4, w4, ws4, free, x, v, x_start, stats)
        # penetration left after the correction: detection again at the corrected positions
        after = self.detect(sim, x_start=xs_wp)
        if len(after["gap"]):
            stats["max_penetration"] = float(max(0.0, -after["gap"].min()))
        stats["contact_ms"] = 1000.0 * (time.perf_counter() - t0)
        self.last_stats = stats
        return stats

    def _respond(self, sim, c: dict, nodes4: np.ndarray, w4: np.ndarray, ws4: np.ndarray, free: np.ndarray,
                 x: np.ndarray, v: np.ndarray, x_start: np.ndarray, stats: dict) -> None:
        """LCP of eq. (3) for the contacts ``c`` and the correction of x and v (free motion in,
        corrected out, also written to the integrator). ``nodes4`` (k, 4): the contact's node
        and triangle nodes (-1: none), ``ws4`` their weights in the tissue point's relative
        displacement, ``w4`` the same zeroed on fixed nodes (the Jacobian's)."""
        o = self.options
        integ, dt = sim.integrator, sim.dt
        n = sim.fem.n_nodes
        k = len(c["node"])
        normal = c["normal"]
        t1, t2 = tangent_basis(normal)
        mu = np.full(k, o["friction"])
        for oi, obj in enumerate(self.objects):
            if obj.friction is not None:
                mu[c["obj"] == oi] = obj.friction
        rows = np.where(mu > 0.0, 3, 1).astype(np.int32)
        row_start = np.concatenate([[0], np.cumsum(rows)[:-1]]).astype(np.int32)
        m = int(rows.sum())
        fr = rows == 3
        # relative displacement during the step of the tissue point against the other surface
        valid = nodes4 >= 0
        disp = x - x_start
        rel = np.einsum("ks,ksj->kj", ws4, disp[np.clip(nodes4, 0, None)])
        for oi, obj in enumerate(self.objects):
            sel = c["obj"] == oi
            if sel.any() and fr[sel].any():
                rel[sel] -= obj.point_displacement(c["point"][sel], dt)
        # H (m x 3n) and delta^0 (m)
        d0 = np.zeros(m)
        d0[row_start] = c["gap"]
        d0[row_start[fr] + 1] = np.einsum("kj,kj->k", t1[fr], rel[fr])
        d0[row_start[fr] + 2] = np.einsum("kj,kj->k", t2[fr], rel[fr])
        ri, ci, vi = [], [], []
        for dirs, rowidx, sel in ((normal, row_start, np.ones(k, bool)), (t1, row_start + 1, fr),
                                  (t2, row_start + 2, fr)):
            cc = np.flatnonzero(sel)
            for s in range(4):
                cs = cc[valid[cc, s]]
                for j in range(3):
                    ri.append(rowidx[cs])
                    ci.append(3 * nodes4[cs, s] + j)
                    vi.append(w4[cs, s] * dirs[cs, j])
        H = sps.coo_matrix((np.concatenate(vi), (np.concatenate(ri), np.concatenate(ci))), shape=(m, 3 * n)).tocsr()
        W0, apply_y, kind = self._compliance(sim, H)
        W = dt * dt * 0.5 * (W0 + W0.T)
        if kind != "diagonal" and not _positive_definite(W):
            # A factor corrected by many cuts, stale, with identity-padded DOFs, can stop being
            # positive definite on the contact rows; PGS then diverges. The block diagonal of A
            # always is: use it for this step and say so.
            W0, apply_y, _ = self._compliance(sim, H, mode="diagonal")
            W = dt * dt * 0.5 * (W0 + W0.T)
            kind = f"diagonal ({kind} not positive definite on the contacts)"
            self.compliance_fallbacks += 1
        self.compliance_used = kind
        stats["compliance_fallbacks"] = self.compliance_fallbacks
        # warm start from last step's forces on the same (object, node) or (object, triangle)
        # pairs; nodes are named by the simulation's node uids where it keeps them (stable
        # across cuts), else by index
        uids = getattr(sim, "node_uids", None)
        uids = np.arange(n) if uids is None or len(uids) != n else np.asarray(uids)
        node_u = uids[np.clip(c["node"], 0, None)]
        tri_u = np.sort(uids[np.clip(c["tri"], 0, None)], axis=1)
        keys = [(int(c["obj"][i]), int(node_u[i])) if c["node"][i] >= 0
                else (int(c["obj"][i]), *(int(u_) for u_ in tri_u[i])) for i in range(k)]
        lam = np.zeros(m)
        for i in range(k):
            f = self._warm.get(keys[i])
            if f is not None:
                r = row_start[i]
                lam[r] = max(0.0, float(f @ normal[i]))
                if fr[i]:
                    lam[r + 1], lam[r + 2] = float(f @ t1[i]), float(f @ t2[i])
        lam_wp = wp.array(lam, dtype=wp.float64, device="cpu")
        info = wp.zeros(2, dtype=wp.float64, device="cpu")
        wp.launch(pgs_kernel, 1,
                  [wp.array(W, dtype=wp.float64, device="cpu"), wp.array(d0, dtype=wp.float64, device="cpu"),
                   wp.array(row_start, dtype=wp.int32, device="cpu"), wp.array(rows, dtype=wp.int32, device="cpu"),
                   wp.array(mu, dtype=wp.float64, device="cpu"), int(o["max_iterations"]), float(o["tolerance"]),
                   int(o["friction_cone"] == "pyramid"), lam_wp, info], device="cpu")
        lam = lam_wp.numpy().copy()
        its, res = info.numpy()
        stats.update(gs_iterations=int(its), lcp_residual=float(res), compliance=kind)
        # correction with the same compliance: dx = dt^2 P^-1 H^T lambda, v += dx / dt
        dx = (dt * dt) * np.asarray(apply_y(lam)).reshape(n, 3) * free[:, None]
        x += dx
        v += dx / dt
        integ.x.assign(x)
        integ.v.assign(v)
        # forces on the tissue, wrenches on the objects, warm start
        ln = lam[row_start]
        force = ln[:, None] * normal
        force[fr] += lam[row_start[fr] + 1][:, None] * t1[fr] + lam[row_start[fr] + 2][:, None] * t2[fr]
        for oi, obj in enumerate(self.objects):
            sel = c["obj"] == oi
            if sel.any():
                f_obj = -force[sel]
                obj.force = f_obj.sum(axis=0)
                obj.torque = np.cross(c["point"][sel] - obj.origin, f_obj).sum(axis=0)
        self._warm = {keys[i]: force[i] for i in range(k) if ln[i] > 0.0}
        self.contacts = {**c, "lambda_n": ln, "force": force}
        stats["active_contacts"] = int(np.sum(ln > 0.0))
