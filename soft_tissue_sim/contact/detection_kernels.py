"""Warp kernels of contact detection: one thread per tissue surface node (against a plane,
a capsule, a static triangle mesh, the tissue's own triangles) or per surface triangle
(against a capsule). Launched by :mod:`soft_tissue_sim.contact.detection`.

Every kernel writes its own output slot ``base + k`` of a :class:`Slots` record shared by all
the launches of one detection (``active`` = 1 with gap, normal and point where it found a
contact within ``distance``, 0 elsewhere), so that one read brings every object's contacts to
the host: the normal is a unit vector pointing the way the tissue is pushed, the gap is < 0
for a penetration, the point lies on the other surface. Search radii that depend on the state
(how far each node moved in the free motion) are read from a device array, not passed from the
host. The kernels are launched over capacities (surface nodes, surface faces, nodes) and read
the counts in use from a device array (``counts`` = [surface nodes, surface faces]), so that a
captured detection holds for every surface that fits the same allocations: the threads past a
count return at once (the self-collision BVH's boxes of the unused face slots sit outside the
faces' bounds, each at its own point: :func:`unused_boxes_kernel`).
"""

from __future__ import annotations

import warp as wp

from .geometry import (
    F64,
    closest_on_segment,
    plane_bary,
    segment_triangle_closest,
    to_vec3f,
    triangle_closest_bary,
)

wp.set_module_options({"enable_backward": False})  # no gradients are taken


@wp.struct
class Slots:
    """The output slots of a detection launch: thread k writes slot ``base + k``; ``active`` 1
    where a contact was found, with its gap, normal, point, and (rows with a triangle) the
    triangle's index and the barycentric weights of the tissue point."""

    base: int
    active: wp.array(dtype=wp.int32)
    gap: wp.array(dtype=wp.float64)
    normal: wp.array(dtype=wp.vec3d)
    point: wp.array(dtype=wp.vec3d)
    tri: wp.array(dtype=wp.int32)
    bary: wp.array(dtype=wp.vec3d)


@wp.func
def clear(out: Slots, k: int):
    """Slot k holds no contact (yet)."""
    out.active[out.base + k] = 0


@wp.func
def emit(out: Slots, k: int, g: wp.float64, n: wp.vec3d, p: wp.vec3d):
    """Slot k holds a contact: gap g, normal n, point p on the other surface."""
    i = out.base + k
    out.active[i] = 1
    out.gap[i] = g
    out.normal[i] = n
    out.point[i] = p


@wp.func
def emit_triangle(out: Slots, k: int, f: int, w: wp.vec3d):
    """Slot k's tissue point (or other surface) is triangle f at barycentric weights w."""
    i = out.base + k
    out.tri[i] = f
    out.bary[i] = w


@wp.func
def search_margin(far: wp.float64, scale: wp.float64):
    """The float32 BVH query radius that covers ``far`` (the float64 test decides)."""
    return wp.float32(far * F64(1.001) + F64(1e-6) * scale)


@wp.kernel
def plane_contacts_kernel(
    counts: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3d),
    nodes: wp.array(dtype=wp.int32),
    geom: wp.array(dtype=wp.vec3d),
    obj: int,
    distance: wp.float64,
    out: Slots,
):
    """Surface node k against the plane of object ``obj`` (point geom[4 obj], unit normal
    geom[4 obj + 1]): gap = n . (x - point)."""
    k = wp.tid()
    if k >= counts[0]:
        return
    point = geom[4 * obj]
    normal = geom[4 * obj + 1]
    xp = x[nodes[k]]
    g = wp.dot(xp - point, normal)
    clear(out, k)
    if g < distance:
        emit(out, k, g, normal, xp - g * normal)


@wp.kernel
def capsule_contacts_kernel(
    counts: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3d),
    nodes: wp.array(dtype=wp.int32),
    geom: wp.array(dtype=wp.vec3d),
    params: wp.array(dtype=wp.float64),
    obj: int,
    distance: wp.float64,
    out: Slots,
):
    """Surface node k against the capsule of instrument ``obj`` (axis a = geom[4 obj], b =
    geom[4 obj + 1], radius params[3 obj]): gap = |x - closest axis point| - radius."""
    k = wp.tid()
    if k >= counts[0]:
        return
    a = geom[4 * obj]
    b = geom[4 * obj + 1]
    radius = params[3 * obj]
    xp = x[nodes[k]]
    c = closest_on_segment(xp, a, b)
    d = xp - c
    dist = wp.length(d)
    g = dist - radius
    clear(out, k)
    if g < distance:
        n = wp.vec3d(F64(0.0), F64(0.0), F64(-1.0))
        if dist > F64(1e-12) * radius:
            n = d / dist
        else:  # on the axis: push out perpendicular to it
            ax = b - a
            if wp.length(ax) > F64(0.0):
                n = wp.normalize(wp.cross(ax, wp.vec3d(F64(1.0), F64(0.0), F64(0.0))))
                if wp.length(wp.cross(ax, wp.vec3d(F64(1.0), F64(0.0), F64(0.0)))) < F64(1e-6) * wp.length(ax):
                    n = wp.normalize(wp.cross(ax, wp.vec3d(F64(0.0), F64(1.0), F64(0.0))))
        emit(out, k, g, n, c + radius * n)



@wp.kernel
def capsule_faces_kernel(
    counts: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3d),
    faces: wp.array(dtype=wp.vec3i),
    edge_owner: wp.array(dtype=wp.vec3i),
    geom: wp.array(dtype=wp.vec3d),
    params: wp.array(dtype=wp.float64),
    distance: wp.float64,
    inside: wp.array(dtype=wp.int32),
    tool: int,
    out: Slots,
):
    """Surface triangle f (outward normal by the right hand) against the capsule of instrument
    ``tool`` (axis a = geom[4 tool], b = geom[4 tool + 1], radius params[3 tool], blade along
    the axis fractions [blade_lo, blade_hi] = params[3 tool + 1 ...]), so that a tool thinner
    than the mesh spacing cannot slip between nodes.

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
    ``inside[tool]`` (the tool was already through the surface at the step's start, e.g. in a cut:
    the triangles around it are then only kept a radius away from the axis)."""
    f = wp.tid()
    if f >= counts[1]:
        return
    clear(out, f)
    a = geom[4 * tool]
    b = geom[4 * tool + 1]
    radius = params[3 * tool]
    blade_lo = params[3 * tool + 1]
    blade_hi = params[3 * tool + 2]
    t = faces[f]
    va = x[t[0]]
    vb = x[t[1]]
    vc = x[t[2]]
    nf = wp.cross(vb - va, vc - va)
    area2 = wp.length(nf)
    if area2 <= F64(0.0):
        return
    nf = nf / area2
    # quick reject: bounding sphere of the triangle against the capsule
    cen = (va + vb + vc) / F64(3.0)
    rad = wp.max(wp.length(va - cen), wp.max(wp.length(vb - cen), wp.length(vc - cen)))
    if wp.length(cen - closest_on_segment(cen, a, b)) > radius + distance + rad:
        return
    zero = F64(0.0)
    one = F64(1.0)
    s, w, d2, crossing = segment_triangle_closest(a, b, va, vb, vc)
    # vertices belong to the node contacts; an edge to one of its two faces
    tiny = F64(1e-12)
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
            emit(out, f, g, n, p + radius * n)
            emit_triangle(out, f, f, w)
        return
    # pierced or touched
    if inside[tool] != 0 or (crossing != 0 and s >= blade_lo and s <= blade_hi):
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
    emit(out, f, h - radius, n, p + radius * n)
    emit_triangle(out, f, f, wl)


@wp.kernel
def capsule_crossings_kernel(
    counts: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3d),
    faces: wp.array(dtype=wp.vec3i),
    geom: wp.array(dtype=wp.vec3d),
    tool: int,
    inside: wp.array(dtype=wp.int32),
):
    """inside[tool] = 1 where the axis of instrument ``tool`` at its previous pose (geom[4 tool
    + 2] to geom[4 tool + 3]) passes through any surface triangle (zeroed before)."""
    f = wp.tid()
    if f >= counts[1]:
        return
    a = geom[4 * tool + 2]
    b = geom[4 * tool + 3]
    t = faces[f]
    va = x[t[0]]
    vb = x[t[1]]
    vc = x[t[2]]
    if wp.length(wp.cross(vb - va, vc - va)) <= F64(0.0):
        return
    cen = (va + vb + vc) / F64(3.0)
    rad = wp.max(wp.length(va - cen), wp.max(wp.length(vb - cen), wp.length(vc - cen)))
    if wp.length(cen - closest_on_segment(cen, a, b)) > rad:
        return
    s, w, d2, crossing = segment_triangle_closest(a, b, va, vb, vc)
    if crossing != 0:
        inside[tool] = 1


@wp.kernel
def trimesh_contacts_kernel(
    counts: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3d),
    nodes: wp.array(dtype=wp.int32),
    mesh_id: wp.uint64,
    verts: wp.array(dtype=wp.vec3d),
    tris: wp.array(dtype=wp.vec3i),
    distance: wp.float64,
    motion: wp.array(dtype=wp.float64),
    scale: wp.float64,
    out: Slots,
):
    """Surface node k against a static triangle mesh within distance + the node's own motion
    (the obstacle does not move: the node closes in on it by its motion only): the closest face
    from the float32 BVH (inside/outside from the angle-weighted pseudo normal), then the float64
    closest point."""
    k = wp.tid()
    if k >= counts[0]:
        return
    i = nodes[k]
    xp = x[i]
    clear(out, k)
    far = distance + motion[i]
    q = wp.mesh_query_point_sign_normal(mesh_id, to_vec3f(xp), search_margin(far, scale))
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
        sgn = F64(1.0)
        if wp.abs(sf) >= F64(0.5) * dist:
            if sf < F64(0.0):
                sgn = F64(-1.0)
        elif q.sign < wp.float32(0.0):
            sgn = F64(-1.0)
        g = sgn * dist
        if g < far:
            n = nf
            if dist > F64(1e-12) * wp.length(vb - va):
                n = (sgn / dist) * d
            emit(out, k, g, n, qp)


@wp.kernel
def face_normals_kernel(
    counts: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3d),
    faces: wp.array(dtype=wp.vec3i),
    node_normal: wp.array(dtype=wp.vec3d),
):
    """Area-weighted outward normals accumulated on the surface nodes."""
    f = wp.tid()
    if f >= counts[1]:
        return
    t = faces[f]
    n = wp.cross(x[t[1]] - x[t[0]], x[t[2]] - x[t[0]])
    for j in range(3):
        wp.atomic_add(node_normal, t[j], n)


@wp.func
def triangle_motion(motion: wp.array(dtype=wp.float64), t: wp.vec3i):
    """How far a triangle's vertices moved in the step: the largest of their ``motion``."""
    return wp.max(motion[t[0]], wp.max(motion[t[1]], motion[t[2]]))


@wp.kernel
def face_bounds_kernel(
    counts: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3d),
    faces: wp.array(dtype=wp.vec3i),
    motion: wp.array(dtype=wp.float64),
    scale: wp.float64,
    gather: int,
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
    corner: wp.array(dtype=wp.float32),
):
    """The self-collision BVH's box of surface triangle f: its vertices at x, widened by how far
    its vertices moved in the step (the largest ``motion``), in float32 with a margin
    (:func:`search_margin`) so that the float64 tests decide; with ``gather``, the boxes' bounds
    gathered into ``corner`` (its lower corner, then its upper one: set to +-inf by
    :func:`box_corner_init_kernel` before) for :func:`unused_boxes_kernel`. Nothing past the
    faces in use."""
    f = wp.tid()
    if f >= counts[1]:
        return
    t = faces[f]
    a = x[t[0]]
    b = x[t[1]]
    c = x[t[2]]
    m = triangle_motion(motion, t)
    lo = wp.min(a, wp.min(b, c))  # componentwise
    hi = wp.max(a, wp.max(b, c))
    w = search_margin(m, scale)
    bl = to_vec3f(lo) - wp.vec3(w, w, w)
    bu = to_vec3f(hi) + wp.vec3(w, w, w)
    lowers[f] = bl
    uppers[f] = bu
    if gather != 0:
        for k in range(3):
            wp.atomic_min(corner, k, bl[k])
            wp.atomic_max(corner, 3 + k, bu[k])


@wp.kernel
def box_corner_init_kernel(corner: wp.array(dtype=wp.float32)):
    """corner = (+inf, +inf, +inf, -inf, -inf, -inf): the bounds of no box."""
    k = wp.tid()
    if k < 3:
        corner[k] = wp.float32(wp.inf)
    else:
        corner[k] = -wp.float32(wp.inf)


@wp.kernel
def unused_boxes_kernel(counts: wp.array(dtype=wp.int32), corner: wp.array(dtype=wp.float32),
                        lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
    """The boxes of the capacity's slots past the faces in use: points on a grid in the cube of
    side e (the faces' largest extent, from ``corner``: :func:`face_bounds_kernel`) beside the
    faces' lower corner, 1 mm off. Beyond every query of the self-contact search (which skips
    such a slot anyway), and near enough that the BVH's Morton codes, quantized over the bounds
    of all boxes, keep their resolution. Distinct points, so distinct codes: the GPU's LBVH
    builder makes a chain (a tree as deep as the slots are many, which its refit climbs one
    level at a time) of boxes that share a code."""
    f = wp.tid()
    nf = counts[1]
    if f < nf:
        return
    e = wp.max(corner[3] - corner[0], wp.max(corner[4] - corner[1], corner[5] - corner[2]))
    if not (e >= wp.float32(0.0)):  # bounds not finite (positions of a diverged step): the origin
        lowers[f] = wp.vec3()
        uppers[f] = wp.vec3()
        return
    j = f - nf
    side = wp.int32(1)  # the grid's points per edge: side^3 >= the unused slots
    while side * side * side < lowers.shape[0] - nf:
        side += 1
    h = e / wp.float32(side)
    g = wp.vec3(wp.float32(j % side), wp.float32((j / side) % side), wp.float32(j / (side * side)))
    p = wp.vec3(corner[0], corner[1], corner[2]) - wp.vec3(e + wp.float32(1.0e-3)) + h * g
    lowers[f] = p
    uppers[f] = p


@wp.kernel
def self_contacts_kernel(
    counts: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3d),
    nodes: wp.array(dtype=wp.int32),
    bvh_id: wp.uint64,
    faces: wp.array(dtype=wp.vec3i),
    face_comp: wp.array(dtype=wp.int32),
    node_comp: wp.array(dtype=wp.int32),
    node_normal: wp.array(dtype=wp.vec3d),
    ring_offsets: wp.array(dtype=wp.int32),
    ring_nodes: wp.array(dtype=wp.int32),
    distance: wp.float64,
    motion: wp.array(dtype=wp.float64),
    scale: wp.float64,
    facing: wp.float64,
    depth: wp.float64,
    out: Slots,
):
    """Surface node k against the tissue's surface triangles within ``distance`` plus how far
    the node and the triangle can close in on each other during the step: ``motion`` of the
    node plus the largest of the triangle's vertices (``bvh_id``: a BVH of the triangles' boxes
    widened by their motion, :func:`face_bounds_kernel`).

    Skipped: triangles incident to the node or to its tet neighbours (the node's own
    neighbourhood), and triangles of the same connected component unless they face the node
    (node normal . triangle normal <= -facing, e.g. the two sides of a cut). In front of a
    triangle the gap is the distance to it (normal from the closest point to the node);
    behind it, a penetration counts only if the node projects inside the triangle and lies
    at most ``depth`` behind it (gap = signed plane distance, normal = the triangle's): the
    positions searched are the step's start, where the last correction left at most a
    contact tolerance of penetration, so a node deeper behind a triangle is on the body's
    far side, not in it (taking it pushes the body through itself). The candidate of
    smallest |gap| wins (of equal ones the lowest face index, whatever the BVH's order).
    """
    k = wp.tid()
    if k >= counts[0]:
        return
    p = nodes[k]
    xp = x[p]
    clear(out, k)
    xf = to_vec3f(xp)
    near = distance + motion[p]  # the node's share of the reach; the triangle's is added below
    margin = search_margin(near, scale)
    lo = wp.vec3(xf[0] - margin, xf[1] - margin, xf[2] - margin)
    hi = wp.vec3(xf[0] + margin, xf[1] + margin, xf[2] + margin)
    nn = node_normal[p]
    nlen = wp.length(nn)
    if nlen > F64(0.0):
        nn = nn / nlen
    best = F64(1.0e300)
    best_face = int(-1)
    best_w = wp.vec3d()
    best_g = F64(0.0)
    best_n = wp.vec3d()
    best_q = wp.vec3d()
    query = wp.bvh_query_aabb(bvh_id, lo, hi)
    f = int(0)
    while wp.bvh_query_next(query, f):
        if f >= counts[1]:  # a slot past the faces in use (its box lies outside every query)
            continue
        t = faces[f]
        if t[0] == p or t[1] == p or t[2] == p:  # the node's own triangles: no vertex read
            continue
        ok = True
        va = x[t[0]]
        vb = x[t[1]]
        vc = x[t[2]]
        nt = wp.cross(vb - va, vc - va)
        area2 = wp.length(nt)
        if area2 <= F64(0.0):
            ok = False
        if ok:
            nt = nt / area2
            if face_comp[f] == node_comp[p]:
                if nlen <= F64(0.0) or wp.dot(nn, nt) > -facing:
                    ok = False
        if ok:
            w = triangle_closest_bary(xp, va, vb, vc)
            q = w[0] * va + w[1] * vb + w[2] * vc
            d = xp - q
            s = wp.dot(d, nt)
            g = F64(0.0)
            n = nt
            valid = False
            if s >= F64(0.0):
                dist = wp.length(d)
                g = dist
                if dist > F64(1e-9) * wp.sqrt(area2):
                    n = d / dist
                valid = True
            else:
                wb = plane_bary(xp, va, vb, vc)
                if -s <= depth and wb[0] >= F64(-1e-9) and wb[1] >= F64(-1e-9) and wb[2] >= F64(-1e-9):
                    w = wp.vec3d(wp.max(wb[0], F64(0.0)), wp.max(wb[1], F64(0.0)), wp.max(wb[2], F64(0.0)))
                    w = w / (w[0] + w[1] + w[2])
                    q = w[0] * va + w[1] * vb + w[2] * vc
                    g = s
                    valid = True
            if valid and wp.abs(g) >= near + triangle_motion(motion, t):
                valid = False  # farther than the pair can close in on each other in the step
            # the smallest |gap| wins, the lowest face index among equal ones: the result does
            # not depend on the order the BVH gives the candidates in
            better = wp.abs(g) < best or (wp.abs(g) == best and f < best_face)
            if valid and better:  # the node's own neighbourhood last: the costliest test
                for j in range(ring_offsets[p], ring_offsets[p + 1]):
                    r = ring_nodes[j]
                    if r == t[0] or r == t[1] or r == t[2]:
                        valid = False
            if valid and better:
                best = wp.abs(g)
                best_face = f
                best_w = w
                best_g = g
                best_n = n
                best_q = q
    if best_face >= 0:
        emit(out, k, best_g, best_n, best_q)
        emit_triangle(out, k, best_face, best_w)


@wp.kernel
def step_start_kernel(
    count: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3d),
    v: wp.array(dtype=wp.vec3d),
    dt: wp.float64,
    x_start: wp.array(dtype=wp.vec3d),
    motion: wp.array(dtype=wp.float64),
):
    """The tissue at the step's start from the free motion: x_start = x - dt v, and how far each
    node moved in it: motion = |dt v|. The nodes i < count[0] (launched over a capacity)."""
    i = wp.tid()
    if i >= count[0]:
        return
    d = dt * v[i]
    x_start[i] = x[i] - d
    motion[i] = wp.length(d)


@wp.kernel
def min_gap_kernel(out: Slots, result: wp.array(dtype=wp.float64)):
    """result[0] = min(result[0], the gap of every active slot)."""
    i = wp.tid()
    if out.active[i] != 0:
        wp.atomic_min(result, 0, out.gap[i])
