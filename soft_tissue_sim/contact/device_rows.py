"""The contact rows of eq. (3) built on the device from the detection's output slots, so that
a step's detection, LCP, correction and guard follow the free motion with no host work in
between (one read a step).

:meth:`.solver.ContactSolver.step` reads the detection to the host, builds the constraint rows
(H in node form, delta^0, the warm start) with NumPy and stages them for the device LCP
(:mod:`.device_lcp`). For the contact sets the device LCP solves anyway (at most
``contact.device_lcp_rows`` rows, no mesh obstacle) the same rows are made here, launched
right after the detection, the tangent rows of friction with them:

1. :func:`active_slots_kernel` lists the active output slots (an atomic counter, in no order;
   step 2 ranks them by slot, so the rows come in the host's order, slot order);
2. :func:`device_rows_kernel` (one block, each lane its slots, at most ``limit`` rows) reads
   each slot's contact as :func:`.detection.collect` does (node, object, triangle of the surface, the
   barycentric weights), moves a self-collision contact's point and gap to the free motion
   (the triangle's point follows its nodes), drops the contacts whose nodes are all fixed,
   and writes the LCP's inputs into :class:`.device_lcp.DeviceLCP`'s device arrays (with a
   positive friction coefficient, the two tangent rows after the normal one: the tissue
   point's motion in the step against the other surface's, :meth:`DeviceRows.objects`) and
   one record row per contact for the host; more rows than ``limit`` set the overflow flag
   (nothing is solved; the host redoes the step's contacts, as it does beyond the row limit);
3. the warm start: the last step's force of the same slot (an object's node or face, a
   node's self-collision: the host's contact names within one surface), where that step was
   solved here (a stamp per slot against an epoch counter, both on the device);
4. :func:`contact_forces_kernel`, after the LCP, makes the contacts' forces (into the record, a
   thread a contact) and keeps the pressed contacts' forces for the next step;
   :func:`wrench_sums_kernel` the objects' wrenches (a thread an object, in the contacts' order)
   and the counts the statistics report, and advances the epoch.

The host reads the header, the wrenches and the LCP's output with the guard after the
correction; the contact record and the host's warm start are made from the read record only
where they are asked for (:attr:`.solver.ContactSolver.contacts`, a later step on the host).
"""

from __future__ import annotations

import warp as wp

from ..buffers import GrowArray, PackedArrays
from ..transfer import Staged
from .device_lcp import barrier
from .geometry import tangent_frame

wp.set_module_options({"enable_backward": False})  # no gradients are taken

F64 = wp.float64

# one record row per contact: slot, node, obj, point (3), normal (3), gap, tri (3), bary (3), then
# (after the LCP) its force on the tissue (3) and its normal force lambda_n
RECORD = 20
HEADER = 7  # active slots, contacts kept, overflow, self contacts, face contacts, pressed, rows
MOTION = 5  # per object: the rows of M, c (its material point at p moved by M p + c in the step), (mu, 0, 0)
_KIND_NODE, _KIND_FACE, _KIND_SELF = 0, 1, 2  # as detection.SlotMap.kind
ROWS_LANES = 256  # the block of device_rows_kernel (the module's plain launches' block: one build)


@wp.kernel
def active_slots_kernel(active: wp.array(dtype=wp.int32), cap: int, count: wp.array(dtype=wp.int32),
                        slots: wp.array(dtype=wp.int32)):
    """Append each active slot's index to ``slots`` (the first ``cap``); ``count`` counts them all."""
    s = wp.tid()
    if active[s] != 0:
        i = wp.atomic_add(count, 0, 1)
        if i < cap:
            slots[i] = s


@wp.func
def slot_contact(s: int, slot_node: wp.array(dtype=wp.int32), slot_obj: wp.array(dtype=wp.int32),
                 slot_kind: wp.array(dtype=wp.int32), slot_tri_row: wp.array(dtype=wp.int32),
                 tris: wp.array(dtype=wp.vec3i), gap: wp.array(dtype=wp.float64), normal: wp.array(dtype=wp.vec3d),
                 point: wp.array(dtype=wp.vec3d), tri: wp.array(dtype=wp.int32), bary: wp.array(dtype=wp.vec3d),
                 x: wp.array(dtype=wp.vec3d), free: wp.array(dtype=wp.float64), motion: wp.array(dtype=wp.vec3d),
                 scene_mu: wp.float64):
    """The contact of active slot ``s`` as :func:`.detection.collect` reads it: (node, triangle
    nodes, barycentric weights, normal, point, gap, the tissue point's weights on (node,
    triangle nodes) in its relative displacement (zero where a node is absent) and the same
    zeroed on fixed nodes (the Jacobian's), object, Coulomb coefficient, rows: 0 where every
    node is fixed (dropped), 1, or 3 with a positive coefficient). A self contact's point and gap
    follow the free motion ``x`` (the other surface is a tissue triangle)."""
    kind = slot_kind[s]
    node = slot_node[s]
    row = slot_tri_row[s]
    if kind == _KIND_SELF:
        row = tri[s]
    t = tris[row]
    w = bary[s]
    if kind == _KIND_NODE:
        w = wp.vec3d(F64(0.0), F64(0.0), F64(0.0))
    n = normal[s]
    p = point[s]
    g = gap[s]
    sign = F64(1.0)
    if kind == _KIND_SELF:
        sign = F64(-1.0)
        p = w[0] * x[t[0]] + w[1] * x[t[1]] + w[2] * x[t[2]]
        g = wp.dot(n, x[node] - p)
    ws4 = wp.vec4d(F64(0.0), F64(0.0), F64(0.0), F64(0.0))
    w4 = wp.vec4d(F64(0.0), F64(0.0), F64(0.0), F64(0.0))
    if node >= 0:
        ws4[0] = F64(1.0)
        w4[0] = free[node]
    for k in range(3):
        if t[k] >= 0:
            ws4[k + 1] = sign * w[k]
            w4[k + 1] = ws4[k + 1] * free[t[k]]
    obj = slot_obj[s]
    mu_c = scene_mu
    k_rows = int(0)
    if wp.dot(w4, w4) > F64(0.0):
        if obj >= 0:
            mu_c = motion[MOTION * obj + 4][0]
        k_rows = 1
        if mu_c > F64(0.0):
            k_rows = 3
    return node, t, w, n, p, g, ws4, w4, obj, mu_c, k_rows


@wp.func
def rows_below(kr: wp.array(dtype=wp.int32), q: int):
    """(rows, contacts kept) of the first q ranks (``kr``: each rank's rows, 0 for a dropped one)."""
    rows = int(0)
    kept = int(0)
    for u in range(q):
        rows += kr[u]
        if kr[u] > 0:
            kept += 1
    return rows, kept


@wp.kernel
def device_rows_kernel(
    count: wp.array(dtype=wp.int32),
    slots: wp.array(dtype=wp.int32),
    limit: int,
    slot_node: wp.array(dtype=wp.int32),
    slot_obj: wp.array(dtype=wp.int32),
    slot_kind: wp.array(dtype=wp.int32),
    slot_tri_row: wp.array(dtype=wp.int32),
    tris: wp.array(dtype=wp.vec3i),
    gap: wp.array(dtype=wp.float64),
    normal: wp.array(dtype=wp.vec3d),
    point: wp.array(dtype=wp.vec3d),
    tri: wp.array(dtype=wp.int32),
    bary: wp.array(dtype=wp.vec3d),
    x: wp.array(dtype=wp.vec3d),
    x_start: wp.array(dtype=wp.vec3d),
    free: wp.array(dtype=wp.float64),
    motion: wp.array(dtype=wp.vec3d),
    scene_mu: wp.float64,
    warm_force: wp.array(dtype=wp.vec3d),
    warm_stamp: wp.array(dtype=wp.int32),
    epoch: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32),
    kr: wp.array(dtype=wp.int32),
    sizes: wp.array(dtype=wp.int32),
    row_start: wp.array(dtype=wp.int32),
    n_rows: wp.array(dtype=wp.int32),
    nodes: wp.array2d(dtype=wp.int32),
    coef: wp.array2d(dtype=wp.vec3d),
    d0: wp.array(dtype=wp.float64),
    lam0: wp.array(dtype=wp.float64),
    mu: wp.array(dtype=wp.float64),
    record: wp.array2d(dtype=wp.float64),
    header: wp.array(dtype=wp.float64),
):
    """The LCP's rows from the active slots (see the module docstring), by one block
    (``wp.launch_tiled``), each lane its own slots: a contact's normal row and, where its
    coefficient (``motion``'s per object, ``scene_mu`` for a self contact) is positive, its two
    tangent rows, whose delta^0 is the tissue point's motion in the step (``x`` against
    ``x_start``) against the other surface's (an object's M p + c), as
    :meth:`.solver.ContactSolver._respond` makes them, in ascending slot order: each slot's rank
    among the active ones and its rows (:func:`slot_contact`) into ``order`` and ``kr``, the
    block waits, then each contact's first row and index from the ranks below it. header[:3] =
    [active slots, contacts kept, overflow (1: more than ``limit`` rows)], header[6] = the rows
    (on overflow, at least the rows that did not fit)."""
    _b, lane = wp.tid()
    bd = wp.block_dim()
    gate = wp.tile_zeros(shape=32, dtype=wp.float64, storage="shared")
    found = count[0]
    if lane == 0:
        sizes[0] = 0
        sizes[1] = 0
        header[0] = F64(float(found))
        header[1] = F64(0.0)
        header[2] = F64(0.0)
        header[6] = F64(float(found))
    if found > limit:
        if lane == 0:
            header[2] = F64(1.0)
        return
    for i in range(lane, found, bd):
        s = slots[i]
        rank = int(0)
        for j in range(found):
            if slots[j] < s:
                rank += 1
        node, t, w, n, p, g, ws4, w4, obj, mu_c, k_rows = slot_contact(
            s, slot_node, slot_obj, slot_kind, slot_tri_row, tris, gap, normal, point, tri, bary, x, free, motion,
            scene_mu)
        order[rank] = s
        kr[rank] = k_rows
    barrier(gate)  # every slot's rank and rows written before any is read
    total, kept = rows_below(kr, found)
    if total > limit:
        if lane == 0:
            header[2] = F64(1.0)
            header[6] = F64(float(total))
        return
    e = epoch[0]
    for q in range(lane, found, bd):
        k_rows = kr[q]
        if k_rows > 0:
            rows, m = rows_below(kr, q)  # the contact's first row and its index
            s = order[q]
            node, t, w, n, p, g, ws4, w4, obj, mu_c, k_rows = slot_contact(
                s, slot_node, slot_obj, slot_kind, slot_tri_row, tris, gap, normal, point, tri, bary, x, free, motion,
                scene_mu)
            t1, t2 = tangent_frame(n)
            for r in range(k_rows):
                d = n
                if r == 1:
                    d = t1
                elif r == 2:
                    d = t2
                nodes[rows + r, 0] = node
                for k in range(3):
                    nodes[rows + r, k + 1] = t[k]
                for k in range(4):
                    coef[rows + r, k] = w4[k] * d
            d0[rows] = g
            row_start[m] = rows
            n_rows[m] = k_rows
            mu[m] = F64(0.0)
            warm = warm_stamp[s] == e
            lam = F64(0.0)
            if warm:
                lam = wp.max(F64(0.0), wp.dot(warm_force[s], n))
            lam0[rows] = lam
            if k_rows == 3:
                mu[m] = mu_c
                v0 = wp.max(node, 0)
                rel = ws4[0] * (x[v0] - x_start[v0])
                for k in range(3):
                    v = wp.max(t[k], 0)
                    rel = rel + ws4[k + 1] * (x[v] - x_start[v])
                if obj >= 0:
                    b = MOTION * obj
                    rel = rel - (wp.vec3d(wp.dot(motion[b], p), wp.dot(motion[b + 1], p), wp.dot(motion[b + 2], p))
                                 + motion[b + 3])
                d0[rows + 1] = wp.dot(t1, rel)
                d0[rows + 2] = wp.dot(t2, rel)
                l1 = F64(0.0)
                l2 = F64(0.0)
                if warm:
                    l1 = wp.dot(warm_force[s], t1)
                    l2 = wp.dot(warm_force[s], t2)
                lam0[rows + 1] = l1
                lam0[rows + 2] = l2
            record[m, 0] = F64(float(s))
            record[m, 1] = F64(float(node))
            record[m, 2] = F64(float(obj))
            for k in range(3):
                record[m, 3 + k] = p[k]
                record[m, 6 + k] = n[k]
                record[m, 10 + k] = F64(float(t[k]))
                record[m, 13 + k] = w[k]
            record[m, 9] = g
    if lane == 0:
        sizes[0] = total
        sizes[1] = kept
        header[1] = F64(float(kept))
        header[6] = F64(float(total))


@wp.kernel
def contact_forces_kernel(sizes: wp.array(dtype=wp.int32), row_start: wp.array(dtype=wp.int32),
                          n_rows: wp.array(dtype=wp.int32), record: wp.array2d(dtype=wp.float64),
                          out: wp.array(dtype=wp.float64), warm_force: wp.array(dtype=wp.vec3d),
                          warm_stamp: wp.array(dtype=wp.int32), epoch: wp.array(dtype=wp.int32)):
    """After the LCP (``out`` = [sweeps, residual, W usable | lambda]), contact c's force on the
    tissue f = lambda_n n (+ lambda_t1 t1 + lambda_t2 t2 with its tangent rows), kept in its
    record row with lambda_n; a pressed contact's force kept at its slot for the next step's
    warm start, stamped with the next epoch (:func:`wrench_sums_kernel` then advances it). A
    thread a contact, over the record's capacity (the count sizes[1] read on the device)."""
    c = wp.tid()
    if c >= sizes[1]:
        return
    r = row_start[c]
    lam = out[3 + r]
    n = wp.vec3d(record[c, 6], record[c, 7], record[c, 8])
    f = lam * n
    if n_rows[c] == 3:
        t1, t2 = tangent_frame(n)
        f = f + (out[3 + r + 1] * t1 + out[3 + r + 2] * t2)
    for k in range(3):
        record[c, 16 + k] = f[k]
    record[c, 19] = lam
    if lam > F64(0.0):
        s = int(record[c, 0])
        warm_force[s] = f
        warm_stamp[s] = epoch[0] + 1


@wp.kernel
def wrench_sums_kernel(sizes: wp.array(dtype=wp.int32), record: wp.array2d(dtype=wp.float64),
                       origins: wp.array(dtype=wp.vec3d), epoch: wp.array(dtype=wp.int32),
                       wrench: wp.array2d(dtype=wp.float64), header: wp.array(dtype=wp.float64)):
    """After :func:`contact_forces_kernel`, thread oi < the objects' count: object oi's wrench
    from the contacts' forces in the record, F = -sum f, T = sum (p - o) x (-f) about its origin
    o (``wrench`` rows: force, torque), summed in the contacts' order; the last thread: the
    counts header[3:6] = [self contacts, face contacts, pressed contacts], then the epoch
    advances (the other slots' forces are no longer current)."""
    oi = wp.tid()
    if oi < wrench.shape[0]:
        F = wp.vec3d()
        T = wp.vec3d()
        o = origins[oi]
        for c in range(sizes[1]):
            if int(record[c, 2]) == oi:
                f = wp.vec3d(record[c, 16], record[c, 17], record[c, 18])
                p = wp.vec3d(record[c, 3], record[c, 4], record[c, 5])
                F = F - f
                T = T + wp.cross(p - o, -f)
        for k in range(3):
            wrench[oi, k] = F[k]
            wrench[oi, 3 + k] = T[k]
        return
    n_self = int(0)
    n_face = int(0)
    n_pressed = int(0)
    for c in range(sizes[1]):
        if int(record[c, 2]) < 0:
            n_self += 1
        elif int(record[c, 1]) < 0:
            n_face += 1
        if record[c, 19] > F64(0.0):
            n_pressed += 1
    header[3] = F64(float(n_self))
    header[4] = F64(float(n_face))
    header[5] = F64(float(n_pressed))
    epoch[0] = epoch[0] + 1


@wp.kernel
def advance_epoch_kernel(epoch: wp.array(dtype=wp.int32)):
    """Forget the kept forces (a step solved elsewhere, or a new surface)."""
    epoch[0] = epoch[0] + 1


class DeviceRows:
    """The device side of :mod:`this module <.device_rows>` for one contact solver: the slot
    tables of the current surface and the warm start by slot (grow-only arrays), the active
    slots' list, the record of up to ``rows`` contacts and its header.

    :meth:`surface` uploads a new surface's slot tables (and forgets the kept forces); :meth:`launch`
    launches steps 1-2 for the detection outputs of that surface, :meth:`forces` step 4."""

    TABLES = {"node": wp.int32, "obj": wp.int32, "kind": wp.int32, "tri_row": wp.int32, "tris": wp.vec3i}

    def __init__(self, rows: int, object_friction: list, friction: float, device):
        """``object_friction``: the Coulomb coefficient of each of the contact solver's objects
        (in the slots' object order, :meth:`.solver.ContactSolver.object_friction`);
        ``friction``: the scene's (a self contact's)."""
        self.rows = int(rows)
        n_objects = len(object_friction)
        self.object_friction = [float(v) for v in object_friction]
        self.friction = float(friction)
        # any contact with tangent rows: else the objects' motion is never read (their coefficients
        # stay the staged zeros)
        self.frictional = self.friction > 0.0 or any(v > 0.0 for v in self.object_friction)
        self.device = wp.get_device(device)
        d = self.device
        self.count = wp.zeros(1, dtype=wp.int32, device=d)
        self.epoch = wp.zeros(1, dtype=wp.int32, device=d)
        self.list = wp.zeros(max(self.rows, 1), dtype=wp.int32, device=d)
        self._order = wp.zeros(max(self.rows, 1), dtype=wp.int32, device=d)  # the rows kernel's, by rank
        self._kr = wp.zeros(max(self.rows, 1), dtype=wp.int32, device=d)
        self.record = wp.zeros((max(self.rows, 1), RECORD), dtype=wp.float64, device=d)
        self.header = wp.zeros(HEADER, dtype=wp.float64, device=d)
        self.wrench = wp.zeros((max(int(n_objects), 1), 6), dtype=wp.float64, device=d)
        self._motion = Staged(MOTION * max(int(n_objects), 1), wp.vec3d, d)  # the objects' motion, friction
        self._tables = PackedArrays(self.TABLES, d)  # the surface's slot tables, sent in one copy
        self._warm_force = GrowArray(wp.vec3d, d)
        self._warm_stamp = GrowArray(wp.int32, d)
        self.serial = None  # the surface whose tables are up
        self.kept = False  # whether the last step kept forces for the next one's warm start

    def surface(self, topo) -> None:
        """The slot tables of ``topo`` (a :class:`.detection.SurfaceTopology`) on the device, where
        they are not the ones up; the kept forces are forgotten with the old surface's slots."""
        if self.serial == topo.serial:
            return
        sm = topo.slot_map
        n = len(sm.obj)
        t = self._tables
        t.reserve({"node": n, "obj": n, "kind": n, "tri_row": n, "tris": len(sm.tris)})
        for name in self.TABLES:
            t.host(name)[...] = getattr(sm, name)
        t.send(self.TABLES)
        self.slot_node, self.slot_obj, self.slot_kind, self.slot_tri_row, self.tris = (
            t.array(k) for k in self.TABLES)
        self.warm_force = self._warm_force.view(n)
        self.warm_stamp = self._warm_stamp.view(n)
        self.warm_stamp.fill_(-1)
        self.epoch.zero_()
        self.serial = topo.serial
        self.kept = False

    def forget(self) -> None:
        """The kept forces are not the last step's any more (a step solved on the host): the
        epoch advanced, where the last step kept any (:attr:`kept`, set by the host after a step
        solved here)."""
        if self.kept:
            wp.launch(advance_epoch_kernel, 1, [self.epoch], device=self.device)
            self.kept = False

    def objects(self, objects: list, dt: float) -> None:
        """The objects' motion in the step (``displacement_map``) and friction coefficient for the
        tangent rows, sent (no wait); outside any capture. Nothing where no contact can have
        friction."""
        if not self.frictional:
            return
        staged = self._motion.view()
        staged[:] = 0.0
        for oi, obj in enumerate(objects):
            M, c = obj.displacement_map(dt)
            b = MOTION * oi
            staged[b: b + 3] = M
            staged[b + 3] = c
            staged[b + 4, 0] = self.object_friction[oi]
        self._motion.send()

    def key(self, limit: int) -> tuple:
        return (self._tables.buffer.ptr, int(limit), self.count.ptr, self.list.ptr, self.record.ptr, self.header.ptr,
                self.wrench.ptr, self.slot_node.ptr, self.tris.ptr, self.warm_force.ptr, self.warm_stamp.ptr,
                self._motion.array.ptr)

    def launch(self, topo, x: wp.array, free: wp.array, lcp, limit: int) -> None:
        """Steps 1-2 for the detection just launched into ``topo.out``: the rows (at most
        ``limit``) of the contacts at the free motion ``x`` (from ``topo.x_start``, the step's
        start) into ``lcp``'s (a :class:`.device_lcp.DeviceLCP`) arrays, with the objects' motion
        last given to :meth:`objects`. Launches only."""
        d = self.device
        out = topo.out
        self.count.zero_()
        wp.launch(active_slots_kernel, out.active.shape[0], [out.active, self.list.shape[0], self.count, self.list],
                  device=d)
        wp.launch_tiled(device_rows_kernel, dim=[1],
                        inputs=[self.count, self.list, int(limit), self.slot_node, self.slot_obj, self.slot_kind,
                                self.slot_tri_row, self.tris, out.gap, out.normal, out.point, out.tri, out.bary, x,
                                topo.x_start, free, self._motion.array, self.friction, self.warm_force,
                                self.warm_stamp, self.epoch, self._order, self._kr, lcp.sizes, lcp.row_start,
                                lcp.n_rows, lcp.nodes, lcp.coef, lcp.d0, lcp.lam0, lcp.mu, self.record, self.header],
                        block_dim=ROWS_LANES, device=d)

    def forces(self, lcp, origins: wp.array) -> None:
        """Step 4, after ``lcp``'s launch: the forces, the objects' wrenches about ``origins``
        (one per object), the counts, the warm start kept. Launches only."""
        d = self.device
        wp.launch(contact_forces_kernel, self.record.shape[0],
                  [lcp.sizes, lcp.row_start, lcp.n_rows, self.record, lcp.out, self.warm_force, self.warm_stamp,
                   self.epoch], device=d)
        wp.launch(wrench_sums_kernel, self.wrench.shape[0] + 1,
                  [lcp.sizes, self.record, origins, self.epoch, self.wrench, self.header], device=d)
