"""Host side of contact detection: the tissue surface's device data and the launches of the
detection kernels (:mod:`soft_tissue_sim.contact.detection_kernels`), whose outputs are
collected into :class:`~soft_tissue_sim.contact.records.Contacts`.

What is tested where: planes and instruments at the positions given (the free motion), at any
depth; triangle features (self-collision, mesh obstacles) at the positions given for them (the
step's start) within ``distance`` plus how far they can close in during the step (a mesh
obstacle: the node's own motion; self-collision: the node's and the triangle's, pair by pair),
their gap then linearised to the free motion by the solver. Instruments against tissue
triangles: per surface triangle, the closest points of the capsule's axis and the triangle; a
row only where that point of the triangle is inside it or on an edge the triangle owns (each
surface edge is owned by one of its faces, the lowest index), vertices being the node
contacts' (nothing is counted twice). Where the axis pierces a triangle, the triangle is
pushed inwards until the part of the axis over it is a radius above it; not a contact: a
piercing along an instrument's blade (a cut), and any piercing by a tool that was already
through the surface at the step's start (inside a cut or a hole).

Invariant: a :class:`SurfaceTopology` belongs to one mesh; it is rebuilt when cutting changes
the mesh (:meth:`SurfaceTopology.matches`), never reused across a change. Its device arrays
are the kept :class:`SurfaceBuffers`', and the launches run over their capacities, reading the
counts in use on the device: a captured detection replays on the next surface while that fits
the same allocations (:attr:`SurfaceTopology.layout`).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import warp as wp

from .. import graphs
from ..buffers import GrowArray, PackedArrays, typed_view
from ..instrument import Instrument, MeshObstacle, PlaneObstacle
from ..mesh import extent
from ..transfer import Staged
from .detection_kernels import (
    Slots,
    box_corner_init_kernel,
    capsule_contacts_kernel,
    capsule_crossings_kernel,
    capsule_faces_kernel,
    face_bounds_kernel,
    face_normals_kernel,
    min_gap_kernel,
    plane_contacts_kernel,
    self_contacts_kernel,
    step_start_kernel,
    trimesh_contacts_kernel,
    unused_boxes_kernel,
)
from .geometry import edge_ownership
from .records import Contacts


def blade_span(inst: Instrument) -> tuple[float, float]:
    """(lo, hi): the fractions of the capsule's axis along which its blade runs (a piercing
    there is a cut, not a contact), or (1, 0), none, for a tool without a blade on its axis
    (a blade further from the axis than the radius, e.g. beside or below the shaft)."""
    bl = getattr(inst, "blade", None)
    key = (None if bl is None else bl.tobytes(), inst.length, inst.radius)
    known = getattr(inst, "_blade_span", None)
    if known is not None and known[0] == key:  # the tool's shape, unchanged since asked last
        return known[1]
    if bl is None or inst.length <= 0.0 or np.hypot(bl[:, 0], bl[:, 1]).max() > inst.radius:
        span = 1.0, 0.0
    else:
        z = bl[:, 2] / inst.length
        lo, hi = max(float(z.min()), 0.0), min(float(z.max()), 1.0)
        span = (lo, hi) if lo < hi else (1.0, 0.0)
    inst._blade_span = key, span
    return span


@dataclass
class Section:
    """The slots one detection launch writes: ``size`` of them from ``base`` (the capacity the
    launch runs over), of which the first ``count`` are in use, for object ``obj`` (-1: the
    tissue itself); ``kind`` says what a thread is: "node" (a surface node against the object),
    "face" (a surface triangle against an instrument) or "self" (a surface node against the
    tissue's own triangles)."""

    obj: int
    kind: str
    base: int
    size: int
    count: int = -1

    def __post_init__(self):
        if self.count < 0:
            self.count = self.size


_OUTPUTS = (("active", wp.int32), ("gap", wp.float64), ("normal", wp.vec3d), ("point", wp.vec3d), ("tri", wp.int32),
            ("bary", wp.vec3d))


class Outputs:
    """The output slots of every launch of one detection, in one set of device arrays, so that
    one read brings them all to the host (:meth:`read`). ``buffers``: the
    :class:`~soft_tissue_sim.buffers.GrowArray` per array to take them from, kept across
    surfaces; None: new arrays. Only ``active`` is zeroed (as every detection does first): the
    other arrays are read where a slot is active, which its kernel has then written."""

    def __init__(self, sections: list[Section], device, buffers: dict | None = None):
        self.sections = sections
        n = max(sum(s.size for s in sections), 1)
        for name, dtype in _OUTPUTS:
            if buffers is None:
                a = wp.zeros(n, dtype=dtype, device=device)
            else:
                a = buffers[name].view(n)
                if name == "active":
                    a.zero_()
            setattr(self, name, a)
        self.all = self.slots(Section(-2, "all", 0, n))

    @property
    def arrays(self) -> tuple:
        return self.active, self.gap, self.normal, self.point, self.tri, self.bary

    def slots(self, section: Section) -> Slots:
        """The kernels' view of ``section``'s slots."""
        s = Slots()
        s.base = section.base
        s.active, s.gap, s.normal, s.point, s.tri, s.bary = self.arrays
        return s

    def section(self, obj: int, kind: str) -> Section | None:
        for s in self.sections:
            if s.obj == obj and s.kind == kind:
                return s
        return None


_NODE, _FACE, _SELF = 0, 1, 2  # SlotMap.kind: what a slot's thread was (Section.kind)


class SlotMap:
    """What each output slot of a detection stands for, so that its active slots are read in
    one pass: ``obj`` (its section's object), ``kind`` (0 node, 1 face, 2 self), ``node`` (the
    surface node, -1 on a face's slot), ``face`` (the surface face of a face's slot, else 0).

    For :func:`collect`: ``tris`` is the surface's faces (int64) followed by a row of -1 (no
    triangle); ``tri_row`` a slot's row of it (its face on a face's slot, the last row on a
    node's, 0 on a self slot, whose face the kernel writes); ``no_tri`` and ``on_self`` the
    node and self slots; ``self_slots`` whether there are any."""

    def __init__(self, sections: list[Section], n_slots: int, surface: np.ndarray, faces: np.ndarray | None = None):
        """``faces``: the surface's faces (k, 3) (none: an empty table)."""
        self.obj = np.full(n_slots, -2, np.int64)
        self.kind = np.zeros(n_slots, np.int8)
        self.node = np.full(n_slots, -1, np.int64)
        self.face = np.zeros(n_slots, np.int64)
        faces = np.zeros((0, 3), np.int64) if faces is None else np.asarray(faces).reshape(-1, 3)
        self.tris = np.concatenate([faces.astype(np.int64), np.full((1, 3), -1, np.int64)])
        self.tri_row = np.full(n_slots, len(faces), np.int64)
        for sec in sections:  # the slots in use (the rest of a section's capacity: no object, no node)
            sl = slice(sec.base, sec.base + sec.count)
            self.obj[sl] = sec.obj
            if sec.kind == "face":
                self.kind[sl] = _FACE
                self.face[sl] = np.arange(sec.count)
                self.tri_row[sl] = np.arange(sec.count)
            else:
                self.kind[sl] = _SELF if sec.kind == "self" else _NODE
                self.node[sl] = surface[: sec.count]
                if sec.kind == "self":
                    self.tri_row[sl] = 0
        self.no_tri = self.kind == _NODE
        self.on_self = self.kind == _SELF
        self.self_slots = bool(self.on_self.any())


def collect(topo: "SurfaceTopology", host: list) -> Contacts:
    """The contacts of one detection from its outputs read to the host (``host``: the arrays of
    :attr:`Outputs.arrays`), in slot order (section by section in launch order)."""
    active, gap, normal, point, tri, bary = host
    idx = (active != 0).nonzero()[0]
    if not len(idx):
        return Contacts.empty()
    slots = topo.slot_map
    rows = slots.tri_row[idx]  # each contact's row of slots.tris: its face, or none
    if slots.self_slots:
        on_self = slots.on_self[idx]
        if np.count_nonzero(on_self):
            rows[on_self] = tri[idx[on_self]]
    w = bary[idx]
    w[slots.no_tri[idx]] = 0.0
    return Contacts(slots.node[idx], slots.obj[idx], gap[idx], normal[idx], point[idx], slots.tris[rows], w)


_SERIALS = itertools.count()


class SurfaceBuffers:
    """The device arrays of the surfaces one contact solver builds, kept from one surface to
    the next (a cut replaces the surface every few steps): the surface's tables and counts in
    one :class:`~soft_tissue_sim.buffers.PackedArrays` (sent in one copy; each table at a fixed
    place while it fits its capacity), the output slots and the per-node work arrays as
    grow-only views, the self-collision BVH (rebuilt in place for a new surface of the same
    face capacity), the per-object arrays, whose size is the solver's (the same for every
    surface), and the detection's captured graphs (:class:`~soft_tissue_sim.graphs.Replayer`):
    a new surface that fits the same allocations replays them."""

    def __init__(self, n_objects: int, device):
        dev = wp.get_device(device)
        self.tables = PackedArrays({"counts": wp.int32, "nodes": wp.int32, "faces": wp.vec3i,
                                    "edge_owner": wp.vec3i, "node_comp": wp.int32, "face_comp": wp.int32,
                                    "ring_offsets": wp.int32, "ring_nodes": wp.int32}, dev)
        self.bvh: wp.Bvh | None = None  # over the views of self.lowers / uppers it was made with
        self.corner = wp.zeros(6, dtype=wp.float32, device=dev)  # the faces' boxes' bounds (lower, upper)
        self.replay = graphs.Replayer(dev, "contact detection", slots=4, eager=True)
        self.outputs = {name: GrowArray(dtype, dev) for name, dtype in _OUTPUTS}
        self.x_start, self.node_normal = GrowArray(wp.vec3d, dev), GrowArray(wp.vec3d, dev)
        self.motion = GrowArray(wp.float64, dev)
        self.lowers, self.uppers = GrowArray(wp.vec3, dev), GrowArray(wp.vec3, dev)
        self.inside = wp.zeros(max(n_objects, 1), dtype=wp.int32, device=dev)
        self.min_gap = wp.zeros(1, dtype=wp.float64, device=dev)
        # the objects' geometry, parameters and origins, sent in one copy: per object 4 vec3d of
        # geometry, then per object a vec3d of parameters (read by the kernels as 3 float64),
        # then per object its origin (see upload_objects)
        k = max(n_objects, 1)
        self.objects_in = Staged(6 * k, wp.vec3d, dev)
        self.geom = typed_view(self.objects_in.array, 0, wp.vec3d, 4 * k)
        self.params = typed_view(self.objects_in.array, 4 * k * 24, wp.float64, 3 * k)
        self.origins = typed_view(self.objects_in.array, 5 * k * 24, wp.vec3d, k)


class SurfaceTopology:
    """Surface data of one mesh; rebuilt when cutting changes the mesh (never reused across
    a change of node count or tets). Its device arrays are the kept :class:`SurfaceBuffers`'
    and its launches run over their capacities (:attr:`layout` names them), so that graphs
    captured on one surface replay on the next while it fits them."""

    def __init__(self, fem, self_collision: bool, objects: list = (), buffers: SurfaceBuffers | None = None):
        """``objects``: the contact solver's instruments and obstacles, in order (their index is
        the contacts' ``obj``): each gets its output slots. ``buffers``: the device arrays kept
        from the surface this one replaces (the same ``objects``); its arrays become this
        surface's (the replaced one must not be used any more). None: new ones."""
        mesh, dev = fem.mesh, fem.device
        self.buffers = buffers = buffers if buffers is not None else SurfaceBuffers(len(objects), dev)
        self.keys = (fem.mesh, fem.mesh.tets, fem.tets, fem.n_nodes)
        self.n_nodes = n = fem.n_nodes
        self.node_count, self.node_dim = fem.n_nodes_dev, fem.node_dim  # the FEM's node count on the device
        self.faces = mesh.boundary_faces()
        on = np.zeros(fem.n_nodes, bool)
        on[self.faces.ravel()] = True
        self.surface = np.flatnonzero(on).astype(np.int32)  # the surface nodes, ascending
        self.scale = extent(mesh.points) or 1.0
        # the tables, sent in one copy: the counts in use [surface nodes, faces]; the surface
        # nodes; the faces, and which face owns each surface edge: edge_owner[f, k] = 1 where
        # face f owns its edge from vertex k to vertex k + 1, each edge owned by exactly one of
        # the faces sharing it, the lowest index (np.unique's first occurrence, face-major
        # order); for self-collision the parts and the node rings
        faces = self.faces if len(self.faces) else np.zeros((1, 3), np.int32)
        data = {"counts": np.array([len(self.surface), len(self.faces)], np.int32),
                "nodes": self.surface if len(self.surface) else np.zeros(1, np.int32), "faces": faces,
                "edge_owner": edge_ownership(faces) if len(self.faces) else np.zeros((1, 3), np.int32)}
        collide = self_collision and len(self.faces)
        if collide:
            offsets, ring = mesh.node_ring()  # the neighbours through the edges (per connectivity)
            comp = mesh.node_components()  # the same parts as the edges make
            self.n_components = int(comp.max()) + 1
            data.update(node_comp=comp, face_comp=comp[self.faces[:, 0]], ring_offsets=offsets, ring_nodes=ring)
        tables = buffers.tables
        tables.reserve({k: len(data[k]) if k in data else 0 for k in tables.fields})
        for k, v in data.items():
            h = tables.host(k)
            h[...] = v.reshape(h.shape)
        tables.send(data)
        self.counts, self.nodes, self.faces_wp, self.edge_owner = (
            tables.array(k) for k in ("counts", "nodes", "faces", "edge_owner"))
        # the launches' dimensions: the capacities of the surface nodes' and the faces' tables
        ns, nf = tables.capacity["nodes"], tables.capacity["faces"]
        self.node_slots, self.face_slots = ns, nf
        # state of one detection on the device: the step's start, each node's motion in the free
        # motion, which instruments were through the surface at the start, the smallest gap
        # (the per-node arrays are zeroed whole: a captured zeroing covers the allocation)
        self.x_start, self.motion = buffers.x_start.view(n), buffers.motion.view(n)
        self.inside, self.min_gap = buffers.inside, buffers.min_gap
        for a in (buffers.x_start.buffer, buffers.motion.buffer, self.inside, self.min_gap):
            a.zero_()
        self.bvh = None
        if collide:
            self.node_comp, self.face_comp, self.ring_offsets, self.ring_nodes = (
                tables.array(k) for k in ("node_comp", "face_comp", "ring_offsets", "ring_nodes"))
            self.node_normal = buffers.node_normal.view(n)
            buffers.node_normal.buffer.zero_()
            # the triangles' boxes (each detection widens them by their vertices' motion and
            # refits), first at the rest positions, made on the device; the BVH over the face
            # capacity (the unused slots' boxes outside the faces' bounds), rebuilt in place
            # where it fits
            self.lowers, self.uppers = buffers.lowers.view(nf), buffers.uppers.view(nf)
            launch_face_boxes(self, fem.rest, dev)
            if buffers.bvh is None or buffers.bvh.lowers is not self.lowers:  # (a view is kept while its size holds)
                buffers.bvh = wp.Bvh(self.lowers, self.uppers)
            else:
                buffers.bvh.rebuild()
            self.bvh = buffers.bvh
        # output slots: per object, one per surface node and, for an instrument, one per surface
        # face; then one per surface node for self-collision (each section a capacity's worth)
        sections, base = [], 0
        for oi, obj in enumerate(objects):
            sections.append(Section(oi, "node", base, ns, len(self.surface)))
            base += ns
            if isinstance(obj, Instrument):
                sections.append(Section(oi, "face", base, nf, len(self.faces)))
                base += nf
        if self.bvh is not None:
            sections.append(Section(-1, "self", base, ns, len(self.surface)))
        self.out = Outputs(sections, dev, buffers.outputs)
        self.slot_map = SlotMap(sections, self.out.active.shape[0], self.surface, self.faces)
        # the objects' geometry of the step, on the device (see upload_objects)
        self.objects_in, self.geom, self.params, self.origins = (buffers.objects_in, buffers.geom, buffers.params,
                                                                 buffers.origins)
        # captured detections, by arguments: kept with the buffers, across surfaces
        self.replay = buffers.replay
        self.serial = next(_SERIALS)  # names this surface (what was uploaded for it)
        # what the detection's launches depend on besides their arguments: the allocations and
        # the capacities they run over (a new surface that fits them keeps this)
        self.layout = (tables.buffer.ptr, ns, nf, self.out.active.ptr, self.x_start.ptr, self.motion.ptr,
                       self.node_count.ptr, self.node_dim, bool(len(self.surface)),
                       None if self.bvh is None else (self.bvh.id, self.node_normal.ptr, self.lowers.ptr))

    def matches(self, fem) -> bool:
        k = self.keys
        return fem.mesh is k[0] and fem.mesh.tets is k[1] and fem.tets is k[2] and fem.n_nodes == k[3]


def upload_objects(topo: SurfaceTopology, objects: list) -> None:
    """The objects' geometry of this step into ``topo.geom`` / ``topo.params``, where the
    kernels read it (so that a captured detection replays with new poses): per object ``oi``,
    geom[4 oi ...] = an instrument's axis (a, b) at the step's pose and at the previous step's
    pose, or a plane's (point, normal); params[3 oi ...] = (radius, blade_lo, blade_hi);
    origins[oi] = where its torque is taken (the contact solver's wrenches on the device).
    Filled on the host and sent in one copy without a wait (:class:`~soft_tissue_sim.transfer.Staged`)."""
    staged = topo.objects_in.view()
    staged[:] = 0.0
    k = len(staged) // 6
    geom, params, origins = staged[: 4 * k], staged[4 * k: 5 * k].reshape(-1), staged[5 * k:]
    for oi, obj in enumerate(objects):
        origins[oi] = obj.origin
        if isinstance(obj, Instrument):
            geom[4 * oi: 4 * oi + 2] = obj.segment_world()
            geom[4 * oi + 2: 4 * oi + 4] = obj.segment_world(obj.previous_step_pose)
            params[3 * oi: 3 * oi + 3] = (obj.radius, *blade_span(obj))
        elif isinstance(obj, PlaneObstacle):
            geom[4 * oi], geom[4 * oi + 1] = obj.point, obj.normal
    topo.objects_in.send()


def launch_detection(topo: SurfaceTopology, objects: list, x: wp.array, x_features: wp.array, distance: float,
                     x_start: wp.array | None, facing: float, depth: float, device, faces: bool = True) -> None:
    """Launch every detection kernel of one detection into ``topo.out`` (nothing is read back:
    :func:`collect` after a read of ``topo.out.arrays``), for the objects' geometry last given
    to :func:`upload_objects`. Planes and instruments are tested at ``x`` within ``distance``;
    triangle features (mesh obstacles, self-collision) at ``x_features`` within ``distance`` plus
    how far the node (and, for self-collision, the triangle's nodes) may move: ``topo.motion``, a
    device array, so that it comes from the state without a read.
    With ``x_start`` (the tissue at the step's start), an instrument whose axis then, at its
    previous pose, went through the surface is inside: its piercings of triangles are not
    contacts (:mod:`soft_tissue_sim.contact.detection`). ``faces`` False leaves out the
    instruments against the triangles (their slots stay empty).

    On CUDA the launches are captured once per set of arguments and allocations
    (``topo.layout``) as a graph and replayed, across surfaces that fit the same allocations
    (nothing in them depends on the host but the arrays' addresses: ``topo.replay``)."""
    if not len(topo.surface):
        return
    args = (x, x_features, x_start, float(distance), float(facing), float(depth), bool(faces))
    dev = wp.get_device(device)
    key = (topo.layout, x.ptr, x_features.ptr, None if x_start is None else x_start.ptr) + args[3:] if dev.is_cuda \
        else None  # on the CPU: plain launches
    topo.replay.run(key, lambda: _launch_all(topo, objects, *args, dev))


def _launch_all(topo: SurfaceTopology, objects: list, x, x_features, x_start, dist, facing, depth, faces,
                device) -> None:
    """The launches of :func:`launch_detection`, over the surface's capacities (the counts in
    use read on the device)."""
    out = topo.out
    out.active.zero_()
    ns, nf, counts = topo.node_slots, topo.face_slots, topo.counts
    topo.inside.zero_()
    for oi, obj in enumerate(objects):
        sec = out.slots(out.section(oi, "node"))
        if isinstance(obj, Instrument):
            wp.launch(capsule_contacts_kernel, ns, [counts, x, topo.nodes, topo.geom, topo.params, oi, dist],
                      outputs=[sec], device=device)
            if not faces:
                continue
            if x_start is not None:
                wp.launch(capsule_crossings_kernel, nf, [counts, x_start, topo.faces_wp, topo.geom, oi],
                          outputs=[topo.inside], device=device)
            wp.launch(capsule_faces_kernel, nf,
                      [counts, x, topo.faces_wp, topo.edge_owner, topo.geom, topo.params, dist, topo.inside, oi],
                      outputs=[out.slots(out.section(oi, "face"))], device=device)
        elif isinstance(obj, PlaneObstacle):
            wp.launch(plane_contacts_kernel, ns, [counts, x, topo.nodes, topo.geom, oi, dist], outputs=[sec],
                      device=device)
        elif isinstance(obj, MeshObstacle):
            wmesh, verts, tris = obj.warp_mesh(device)
            wp.launch(trimesh_contacts_kernel, ns,
                      [counts, x_features, topo.nodes, wmesh.id, verts, tris, dist, topo.motion, topo.scale],
                      outputs=[sec], device=device)
    if topo.bvh is not None:  # the faces' boxes (the unused slots' stay where the surface put them)
        wp.launch(face_bounds_kernel, nf, [counts, x_features, topo.faces_wp, topo.motion, topo.scale, 0],
                  outputs=[topo.lowers, topo.uppers, topo.buffers.corner], device=device)
        topo.bvh.refit()
        topo.buffers.node_normal.buffer.zero_()
        wp.launch(face_normals_kernel, nf, [counts, x_features, topo.faces_wp, topo.node_normal], device=device)
        wp.launch(self_contacts_kernel, ns,
                  [counts, x_features, topo.nodes, topo.bvh.id, topo.faces_wp, topo.face_comp, topo.node_comp,
                   topo.node_normal, topo.ring_offsets, topo.ring_nodes, dist, topo.motion, topo.scale, facing, depth],
                  outputs=[out.slots(out.section(-1, "self"))], device=device)


def launch_face_boxes(topo: SurfaceTopology, x: wp.array, device) -> None:
    """The self-collision BVH's boxes at ``x`` (widened by ``topo.motion``), made with a new
    surface: the faces' over the face capacity, and those of the slots past the faces in use
    each at its own point outside the faces' bounds
    (:func:`~.detection_kernels.unused_boxes_kernel`). Those points are what the BVH's build
    needs (its Morton codes are made then, not at a refit), and the search skips their slots:
    the detections move the faces' boxes only."""
    corner, nf = topo.buffers.corner, topo.face_slots
    wp.launch(box_corner_init_kernel, 6, [corner], device=device)
    wp.launch(face_bounds_kernel, nf, [topo.counts, x, topo.faces_wp, topo.motion, topo.scale, 1],
              outputs=[topo.lowers, topo.uppers, corner], device=device)
    wp.launch(unused_boxes_kernel, nf, [topo.counts, corner, topo.lowers, topo.uppers], device=device)


def launch_start(topo: SurfaceTopology, x: wp.array, v: wp.array, dt: float, device) -> None:
    """``topo.x_start`` = x - dt v (the step's start from the free motion) and ``topo.motion`` =
    how far each node moved in it (the triangle features' search, node by node), on the device."""
    wp.launch(step_start_kernel, topo.node_dim, [topo.node_count, x, v, float(dt), topo.x_start, topo.motion],
              device=device)


def launch_min_gap(topo: SurfaceTopology, device) -> wp.array:
    """The smallest gap of the last detection's contacts into ``topo.min_gap`` (a device array
    of one value, +inf where there is none); returned, not read."""
    topo.min_gap.fill_(np.inf)
    wp.launch(min_gap_kernel, topo.out.active.shape[0], [topo.out.all], outputs=[topo.min_gap], device=device)
    return topo.min_gap
