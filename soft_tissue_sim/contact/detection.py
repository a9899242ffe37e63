"""Host side of contact detection: the tissue surface's device data and the launches of the
detection kernels (:mod:`soft_tissue_sim.contact.detection_kernels`), whose outputs are
collected into :class:`~soft_tissue_sim.contact.records.Contacts`.

What is tested where: planes and instruments at the positions given (the free motion), at any
depth; triangle features (self-collision, mesh obstacles) at the positions given for them
(the step's start) within ``distance`` plus a reach, their gap then linearised to the free
motion by the solver. Instruments against tissue triangles: per surface triangle, the closest
points of the capsule's axis and the triangle; a row only where that point of the triangle is
inside it or on an edge the triangle owns (each surface edge is owned by one of its faces, the
lowest index), vertices being the node contacts' (nothing is counted twice). Where the axis
pierces a triangle, the triangle is pushed inwards until the part of the axis over it is a
radius above it; not a contact: a piercing along an instrument's blade (a cut), and any
piercing by a tool that was already through the surface at the step's start (inside a cut or
a hole).

Invariant: a :class:`SurfaceTopology` belongs to one mesh; it is rebuilt when cutting changes
the mesh (:meth:`SurfaceTopology.matches`), never reused across a change.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sps
import warp as wp
from scipy.sparse.csgraph import connected_components

from ..instrument import Instrument, MeshObstacle, PlaneObstacle
from ..transfer import to_host
from .detection_kernels import (
    capsule_contacts_kernel,
    capsule_crossings_kernel,
    capsule_faces_kernel,
    copy_points_f32_kernel,
    face_normals_kernel,
    Slots,
    plane_contacts_kernel,
    self_contacts_kernel,
    trimesh_contacts_kernel,
)
from .geometry import edge_ownership
from .records import Contacts


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


def _slots(active, gap, normal, point) -> Slots:
    """The kernels' view of a set of output slots."""
    s = Slots()
    s.active, s.gap, s.normal, s.point = active, gap, normal, point
    return s


def _output_slots(n: int, device) -> tuple:
    """(active, gap, normal, point, bary): n output slots of a detection kernel."""
    return (wp.zeros(n, dtype=wp.int32, device=device), wp.zeros(n, dtype=wp.float64, device=device),
            *(wp.zeros(n, dtype=wp.vec3d, device=device) for _ in range(3)))


class SurfaceTopology:
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
        self.active, self.gap, self.normal, self.point, self.bary = _output_slots(ns, dev)
        self.slots = _slots(self.active, self.gap, self.normal, self.point)
        self.tri = wp.zeros(ns, dtype=wp.int32, device=dev)
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
        self.f_active, self.f_gap, self.f_normal, self.f_point, self.f_bary = _output_slots(nf, dev)
        self.f_slots = _slots(self.f_active, self.f_gap, self.f_normal, self.f_point)
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


def _search_radius(topo: SurfaceTopology, far: float) -> float:
    """The float32 BVH query radius that covers ``far`` (the float64 test decides)."""
    return float(far * 1.001 + 1e-6 * topo.scale)


def _collect(topo: SurfaceTopology, obj: int, with_tri: bool) -> Contacts | None:
    """The rows a per-node kernel marked active, as contacts with object index ``obj``."""
    arrays = (topo.active, topo.gap, topo.normal, topo.point) + ((topo.tri, topo.bary) if with_tri else ())
    host = to_host(*arrays)
    act = host[0][: len(topo.surface)].astype(bool)
    if not act.any():
        return None
    act = np.concatenate([act, np.zeros(len(host[0]) - len(act), bool)])
    k = int(act.sum())
    tri = topo.faces[host[4][act]].astype(np.int64) if with_tri else np.full((k, 3), -1, np.int64)
    bary = host[5][act] if with_tri else np.zeros((k, 3))
    return Contacts(topo.surface[act[: len(topo.surface)]].astype(np.int64), np.full(k, obj, np.int64), host[1][act],
                    host[2][act], host[3][act], tri, bary)


def node_contacts(topo: SurfaceTopology, oi: int, obj, x: wp.array, x_features: wp.array, distance: float,
                  far: float, device) -> Contacts | None:
    """Surface nodes against object ``oi``: an instrument's capsule or a plane at ``x`` within
    ``distance``, a static mesh at ``x_features`` within ``far``."""
    out = [topo.slots]
    ns = len(topo.surface)
    if isinstance(obj, Instrument):
        a, b = obj.segment_world()
        wp.launch(capsule_contacts_kernel, ns, [x, topo.nodes, wp.vec3d(*a), wp.vec3d(*b), obj.radius, distance],
                  outputs=out, device=device)
    elif isinstance(obj, PlaneObstacle):
        wp.launch(plane_contacts_kernel, ns, [x, topo.nodes, wp.vec3d(*obj.point), wp.vec3d(*obj.normal), distance],
                  outputs=out, device=device)
    elif isinstance(obj, MeshObstacle):
        wmesh, verts, tris = obj.warp_mesh(device)
        wp.launch(trimesh_contacts_kernel, ns,
                  [x_features, topo.nodes, wmesh.id, verts, tris, far, _search_radius(topo, far)],
                  outputs=out, device=device)
    return _collect(topo, oi, False)


def face_contacts(topo: SurfaceTopology, oi: int, inst: Instrument, x: wp.array, a: np.ndarray, b: np.ndarray,
                  x_start: wp.array | None, distance: float, device) -> Contacts | None:
    """Instrument ``oi`` (axis a-b) against the surface triangles at ``x``: rows with node -1,
    the triangle's nodes in ``tri`` and the tissue point's barycentric weights in ``bary``.
    With ``x_start`` (the tissue at the step's start), a tool whose axis then, at its previous
    pose, went through the surface is inside: its piercings are not contacts."""
    nf = len(topo.faces)
    if nf == 0:
        return None
    inside = 0
    if x_start is not None:
        pa, pb = inst.segment_world(inst.previous_step_pose)
        wp.launch(capsule_crossings_kernel, nf, [x_start, topo.faces_wp, wp.vec3d(*pa), wp.vec3d(*pb)],
                  outputs=[topo.f_crossed], device=device)
        inside = int(to_host(topo.f_crossed)[0][:nf].any())
    lo, hi = blade_span(inst)
    wp.launch(capsule_faces_kernel, nf,
              [x, topo.faces_wp, topo.edge_owner, wp.vec3d(*a), wp.vec3d(*b), inst.radius, distance, lo, hi, inside],
              outputs=[topo.f_slots, topo.f_bary], device=device)
    f_act, f_gap, f_normal, f_point, f_bary = to_host(topo.f_active, topo.f_gap, topo.f_normal, topo.f_point,
                                                     topo.f_bary)
    act = f_act[:nf].astype(bool)
    if not act.any():
        return None
    k = int(act.sum())
    return Contacts(np.full(k, -1, np.int64), np.full(k, oi, np.int64), f_gap[:nf][act], f_normal[:nf][act],
                    f_point[:nf][act], topo.faces[act].astype(np.int64), f_bary[:nf][act])


def self_contacts(topo: SurfaceTopology, x_features: wp.array, far: float, facing: float, depth: float,
                  device) -> Contacts | None:
    """Surface nodes against the tissue's own triangles at ``x_features`` within ``far`` (the
    BVH refitted to these positions first); object index -1."""
    if topo.wmesh is None:
        return None
    wp.launch(copy_points_f32_kernel, topo.n_nodes, [x_features, topo.points32], device=device)
    topo.wmesh.refit()
    topo.node_normal.zero_()
    wp.launch(face_normals_kernel, len(topo.faces), [x_features, topo.faces_wp, topo.node_normal], device=device)
    wp.launch(self_contacts_kernel, len(topo.surface),
              [x_features, topo.nodes, topo.wmesh.id, topo.faces_wp, topo.face_comp, topo.node_comp, topo.node_normal,
               topo.ring_offsets, topo.ring_nodes, far, _search_radius(topo, far), facing, depth],
              outputs=[topo.slots, topo.tri, topo.bary], device=device)
    return _collect(topo, -1, True)
