"""The contact component: instruments, obstacles, detection, the LCP and the correction of
one step (paper section 2.3, eq. 3-4; the compliance with cuts, eq. 11-12).

One step after the free motion of eq. (1): detect (:mod:`.detection`), build the Jacobian H
and delta^0, solve the LCP (:mod:`.pgs`) with W from :mod:`.compliance`, correct
x += dt^2 P^-1 H^T lambda and v by the same over dt. Sign convention: lambda and
:meth:`ContactSolver.contact_forces` are forces ON THE TISSUE [N], world frame; the wrench of
an object is the force ON THAT OBJECT, F = -(sum of the contact forces on the tissue from
it), and T = sum (p_c - o) x (-f_c) [N m] about its origin o (an instrument's tool-frame
origin at the step's pose, a plane's point, the world origin for a mesh), p_c the contact
point on the object's surface.
"""

from __future__ import annotations

import math
import sys
import time
from typing import NamedTuple

import numpy as np
import warp as wp

from ..body import BodyView
from ..buffers import GrowArray
from ..instrument import Instrument, MeshObstacle, obstacle_from_config
from ..material import ParameterError
from ..stats import ContactStats
from ..transfer import to_host
from .compliance import compliance, positive_definite
from .device_lcp import DeviceLCP, PendingLCP, launch_args
from .device_rows import DeviceRows
from .detection import SurfaceTopology, collect, launch_detection, launch_min_gap, launch_start, upload_objects
from .geometry import cross, tangent_basis
from .jacobian import ConstraintRows
from .options import friction_finish_on, parse_options
from .pgs import PGS
from .records import ContactResponse, Contacts
from .warm import WarmStart, contact_names


_SIGN = np.array([1.0, -1.0])  # by a row's own (self-collision) flag: the sign of its triangle's weights

wp.set_module_options({"enable_backward": False})  # no gradients are taken


@wp.kernel
def scaled_free_kernel(y: wp.array(dtype=wp.vec3d), s: wp.float64, free: wp.array(dtype=wp.float64),
                       out: wp.array(dtype=wp.vec3d)):
    """out = s y on the free nodes, 0 on the fixed ones (the host LCP's correction on the device)."""
    i = wp.tid()
    out[i] = (s * free[i]) * y[i]


class ContactSolver:
    """Instruments, obstacles, detection and the LCP response of one simulation.

    ``faces``: detect instruments against the surface triangles too (default; False only for
    a control experiment, where a tool thinner than the mesh spacing slips between nodes).

    Built by :class:`soft_tissue_sim.scene.Simulation` only when the scene names
    instruments, obstacles or self-collision. See the module docstring for the method,
    the units and the sign conventions.
    """

    faces: bool = True

    def __init__(self, options: dict, instruments: list, obstacles: list, device, points: np.ndarray):
        """``points``: the tissue's rest positions (an instrument without a pose is parked above
        them). Raises ParameterError on bad options."""
        self.options = parse_options(options or {})
        o = self.options
        self.device = device
        lo, hi = points.min(axis=0), points.max(axis=0)
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
        self._mesh_objects = [oi for oi, obj in enumerate(self.objects) if isinstance(obj, MeshObstacle)]
        self._topo: SurfaceTopology | None = None
        self._warm = WarmStart()  # None: made from _device_read when next needed
        # (record, lambda, node uids, node count) of the last step's contacts where they were solved
        # from device rows: their Contacts and warm start are made from it when asked for
        self._device_read = None
        self._pgs = PGS(o["active_set"],
                        friction_active_set=friction_finish_on(o, gpu=wp.get_device(self.device).is_cuda))
        self._device_lcp: DeviceLCP | None = None  # the device solve's buffers, made at its first use
        self._device_rows: DeviceRows | None = None  # the rows built on the device (device_rows), idem
        self._last_rows = 0  # the last step's constraint rows (where the next step's rows are built)
        self._frictionless = self._friction(np.zeros(0, np.int64)).uniform and self.options["friction"] == 0.0
        self._dx = GrowArray(wp.vec3d, device)  # the device correction, overwritten each step
        # this module's kernel serves the host LCP's path, first taken at a large set, mid-run:
        # built (or loaded from the cache) now
        wp.load_module(sys.modules[__name__], device=device)
        self.contacts = Contacts.empty(responded=True)
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
        return c.point[c.lambda_n > 0.0].copy()

    def contact_forces(self) -> np.ndarray:
        """(k, 3) forces ON THE TISSUE [N] at :meth:`contact_points`, world frame."""
        c = self.contacts
        return c.force[c.lambda_n > 0.0].copy()

    def reset(self) -> None:
        for inst in self.instruments.values():
            inst.reset()
        for obs in self.obstacles.values():
            obs.force[:] = 0.0
            obs.torque[:] = 0.0
        self._retire_topology()
        self._topo = None
        self._warm = WarmStart()
        self._last_rows = 0
        self.contacts = Contacts.empty(responded=True)
        self.compliance_fallbacks = 0

    # ------------------------------------------------------------ detection
    def _retire_topology(self) -> None:
        """Hand the captured detections of the surfaces (kept with their buffers) to
        :mod:`..graphs` (released where no factorization runs): on reset, where the buffers go."""
        if self._topo is not None:
            self._topo.replay.clear()

    def _topology(self, fem) -> SurfaceTopology:
        if self._topo is None or not self._topo.matches(fem):
            old = self._topo  # its arrays and captured detections are kept: a surface that fits them replays these
            self._topo = SurfaceTopology(fem, self.options["self_collision"], self.objects,
                                         None if old is None else old.buffers)
        return self._topo

    def refresh_surface(self, fem) -> float:
        """Bring the tissue surface up to date with ``fem``'s mesh now (after a topology change,
        so that its cost is the change's, not the next detection's); returns the milliseconds
        it took (about none where it was current)."""
        t0 = time.perf_counter()
        self._topology(fem)
        return 1000.0 * (time.perf_counter() - t0)

    def _launch(self, topo: SurfaceTopology, x: wp.array, x_features: wp.array, x_start: wp.array | None) -> None:
        o = self.options
        launch_detection(topo, self.objects, x, x_features, o["distance"], x_start, o["facing"],
                         o["self_depth"], self.device, self.faces)

    def detect(self, body, x: wp.array | None = None, x_features: wp.array | None = None, reach: float = 0.0,
               x_start: wp.array | None = None) -> Contacts:
        """The contacts of the tissue ``body`` (anything with ``fem`` and ``integrator``: the
        simulation) against the objects and itself, object by object. Planes and instruments
        are tested at positions ``x`` (default ``body.integrator.x``) within ``distance``,
        triangle features (self-collision, mesh obstacles) at ``x_features`` (default ``x``)
        within ``distance`` plus how far the tissue may move, ``reach`` for every node (a
        self-collision pair: by both of its sides, ``2 reach``). ``x_start``: the tissue at the
        step's start, where the instruments' previous poses tell which tools were already
        through the surface (their piercings of triangles are then not contacts); without it
        every piercing is one."""
        topo = self._topology(body.fem)
        x = body.integrator.x if x is None else x
        if not len(topo.surface):
            return Contacts.empty()
        topo.motion.fill_(float(reach))
        upload_objects(topo, self.objects)
        self._launch(topo, x, x if x_features is None else x_features, x_start)
        return collect(topo, to_host(*topo.out.arrays))

    def penetration_key(self, body) -> tuple:
        """What :meth:`launch_penetration`'s launches depend on, for a caller that captures them
        (the surface's allocations and capacities, its ``layout``, the positions' and the
        detection's arrays, the options); the surface is brought up to date here, outside any
        capture."""
        topo = self._topology(body.fem)
        return (topo.layout, body.integrator.x.ptr, topo.x_start.ptr, topo.min_gap.ptr, *self._detection_options())

    def _detection_options(self) -> tuple:
        """The options a detection's launches take by value (part of their graphs' keys)."""
        o = self.options
        return o["distance"], o["facing"], o["self_depth"], self.faces

    def launch_penetration(self, body) -> wp.array | None:
        """Launch a detection at the tissue's current positions (after the correction), with the
        objects where this step's detection had them, and the reduction of its smallest gap;
        returns the device array of that gap (+inf: no contact) for the caller to read with its
        other values (``max_penetration = max(0, -gap)``), or None where the tissue has no
        surface."""
        topo = self._topology(body.fem)
        if not len(topo.surface):
            return None
        topo.buffers.motion.buffer.zero_()  # the whole allocation: a captured zeroing covers every node count
        x = body.integrator.x
        self._launch(topo, x, x, topo.x_start)
        return launch_min_gap(topo, self.device)

    # ------------------------------------------------------------------ step
    def prepare(self, body: BodyView, begin: bool = True) -> tuple:
        """The host side of this step's detection: the instruments take their current poses
        (``begin``: once a step), the surface is brought up to date, the objects' geometry
        is staged for the device. Returns the key of :meth:`launch_detection_of`'s launches
        (what they depend on besides the staged geometry, whose buffers are the surface's)."""
        if begin:
            for inst in self.instruments.values():
                inst.begin_step()
        integ = body.integrator
        topo = self._topology(body.fem)
        upload_objects(topo, self.objects)
        return (topo.layout, integ.x.ptr, integ.v.ptr, float(integ.dt), body.fem.free.ptr, *self._detection_options())

    def launch_detection_of(self, body: BodyView) -> list[wp.array]:
        """Launch the detection of the free motion (``body.integrator``'s x and v) prepared by
        :meth:`prepare`; returns the device arrays :meth:`step` reads, unread. Launches only."""
        integ = body.integrator
        topo = self._topology(body.fem)
        # Planes and instruments (exact half-spaces / the tool's new pose) are tested at the
        # free-motion positions, at any depth. Triangle features are found at the step's start
        # and their gap is linearised to the free motion; the search reaches `distance` plus
        # how far the node moved in the free motion (and, for self-collision, the triangle's
        # nodes: both may close in), so that nothing tunnels through a triangle in one step.
        launch_start(topo, integ.x, integ.v, integ.dt, self.device)
        self._launch(topo, integ.x, topo.x_start, topo.x_start)
        return [integ.x, topo.x_start, body.fem.free, *topo.out.arrays]

    def step(self, body: BodyView, host: list | None = None, begin: bool = True,
             device_lcp: bool = True) -> ContactResponse:
        """Detect the contacts of the free motion (``body.integrator``'s x and v), solve the LCP
        and update the wrenches and :attr:`contacts`. Returns the correction of x and v (the
        caller applies it, then may measure the penetration left with
        :meth:`launch_penetration`) and the statistics; ``body`` is only read.

        ``host``: the arrays of :meth:`launch_detection_of` for this state already read to the
        host (their views, valid until the next read of those arrays); else prepared
        (``begin`` as in :meth:`prepare`), launched and read here in one wait.

        Where the LCP is solved on the device (:mod:`.device_lcp`; ``device_lcp`` False: never)
        the response's ``device`` is the pending solve and ``dx`` None: the caller launches it
        with the correction and finishes it with what it reads (see :class:`PendingLCP`)."""
        t0 = time.perf_counter()
        o = self.options
        topo = self._topology(body.fem)
        if host is None:
            self.prepare(body, begin)
            host = to_host(*self.launch_detection_of(body))
        x, x_start, free, *outputs = host
        c = collect(topo, outputs) if len(topo.surface) else Contacts.empty()
        # self-collision rows: the other surface is a tissue triangle (searched pair by pair on the
        # device, within the distance plus the node's and the triangle's motion in the step)
        own = c.obj < 0
        n_own = np.count_nonzero(own)
        tri_feature = own  # rows against triangle features: self-collision, mesh obstacles
        if self._mesh_objects:  # (searched node by node within the distance plus the node's motion)
            tri_feature = own | np.isin(c.obj, self._mesh_objects)
        if np.count_nonzero(tri_feature):
            on_tri = own.nonzero()[0]  # tissue triangles move: their point follows the free motion
            c.point[on_tri] = np.einsum("ks,ksj->kj", c.bary[on_tri], x[c.tri[on_tri]])
            c.gap[tri_feature] = np.einsum("kj,kj->k", c.normal[tri_feature],
                                           x[c.node[tri_feature]] - c.point[tri_feature])
        k = len(c.node)
        # Jacobian blocks: up to 4 nodes per contact with weights: the tissue point moves with
        # +1 on its node, or +w_i on the triangle's nodes where it is a triangle's point
        # (instrument against a face, node -1); a self-collision triangle is the other surface,
        # -w_i. ws4 are these (the tissue point's relative displacement), w4 the same zeroed on
        # fixed nodes. Contacts whose nodes are all fixed cannot be acted on: dropped.
        nodes4 = np.empty((k, 4), np.int32)
        nodes4[:, 0] = c.node
        nodes4[:, 1:] = c.tri
        ws4 = np.empty((k, 4))
        ws4[:, 0] = 1.0
        if n_own:
            np.multiply(_SIGN[own.view(np.int8)][:, None], c.bary, out=ws4[:, 1:])
        else:
            ws4[:, 1:] = c.bary
        ws4 *= nodes4 >= 0
        w4 = ws4 * free[np.maximum(nodes4, 0)]
        keep = np.vecdot(w4, w4) > 0.0  # some weight on a free node (a sum of squares: any order)
        kept = int(np.count_nonzero(keep))
        if kept > o["max_contacts"]:
            order = np.argsort(np.where(keep, c.gap, np.inf), kind="stable")[: o["max_contacts"]]
            keep = np.zeros(k, bool)
            keep[order] = True
            kept = o["max_contacts"]
        if kept < k:
            c = c.take(keep)
            nodes4, w4, ws4, own = nodes4[keep], w4[keep], ws4[keep], own[keep]
            k = kept
            n_own = np.count_nonzero(own)
        on_face = c.node < 0
        stats = ContactStats(contacts=k, self_contacts=int(n_own),
                             face_contacts=int(np.count_nonzero(on_face & ~own if n_own else on_face)))
        for obj in self.objects:
            obj.force, obj.torque = np.zeros(3), np.zeros(3)
        dx = None
        if k == 0:
            self.contacts = Contacts.empty(responded=True)
            self._warm = WarmStart()
        else:
            dx = self._respond(body, c, nodes4, w4, ws4, free, x, x_start, stats, device_lcp)
        self._last_rows = k if self._frictionless else 3 * k
        if self._device_rows is not None:
            self._device_rows.forget()  # the forces kept on the device are not this step's
        stats.contact_ms = 1000.0 * (time.perf_counter() - t0)
        if isinstance(dx, PendingLCP):
            return ContactResponse(None, stats, dx)
        return ContactResponse(dx, stats)

    # ------------------------------------------------- rows on the device
    def device_rows_plan(self, body: BodyView) -> DeviceStep | None:
        """This step's contacts as launches after the free motion (:mod:`.device_rows`: the
        detection, the rows, the LCP and dx on the device), where they can be: the option on, no
        mesh obstacle, the LCP solvable on the device, a surface, and the last step within the
        row limit (a larger set would overflow and be redone on the host). The objects' motion
        and friction for the tangent rows are sent here. Call after :meth:`prepare`; None: the
        host path (:meth:`step`)."""
        o = self.options
        limit = min(o["device_lcp_rows"], o["max_contacts"])
        if not o["device_rows"] or self._mesh_objects or self._last_rows > limit:
            return None
        inner = self._device_solver(body, 1)
        topo = self._topo
        if inner is None or topo is None or not topo.matches(body.fem) or not len(topo.surface):
            return None
        if self._device_rows is None or self._device_rows.rows != o["device_lcp_rows"]:
            self._device_rows = DeviceRows(o["device_lcp_rows"], self.object_friction(), o["friction"], self.device)
        self._device_rows.surface(topo)
        self._device_rows.objects(self.objects, float(body.integrator.dt))
        return DeviceStep(self, body, inner, limit)

    def finish_device_rows(self, body: BodyView, plan: DeviceStep, reads: list) -> ContactStats | None:
        """The host's part of a step made by ``plan`` from what was read after it (``reads``: the
        arrays of :meth:`DeviceStep.launch`): the wrenches, :attr:`contacts` and the host's warm
        start (both made from the record when next asked for) and the statistics, as :meth:`step`
        makes them; None where the device could not solve the step (more contacts than the
        limit, or W not positive definite: nothing was corrected, the caller restores the free
        motion and calls :meth:`step`)."""
        t0 = time.perf_counter()
        out, header, record, wrench = reads
        m = int(header[1])
        if header[2] != 0.0 or (m and out[2] == 0.0):
            self._last_rows = max(int(header[0]), int(header[6]), self._last_rows)
            return None
        self._last_rows = int(header[6])
        self._device_rows.kept = header[5] > 0.0  # pressed contacts' forces kept at their slots
        for oi, obj in enumerate(self.objects):
            obj.force, obj.torque = wrench[oi, :3].copy(), wrench[oi, 3:].copy()
        if m == 0:
            self.contacts = Contacts.empty(responded=True)
            self._warm = WarmStart()
            return ContactStats(rows_device=True, contact_ms=1000.0 * (time.perf_counter() - t0))
        self.contacts = self._warm = None  # made from the read when asked for
        self._device_read = np.array(record[:m]), body.node_uids, body.fem.n_nodes
        stats = ContactStats(contacts=m, self_contacts=int(header[3]), face_contacts=int(header[4]),
                             active_contacts=int(header[5]), lcp_device=True, rows_device=True,
                             compliance_fallbacks=self.compliance_fallbacks, compliance="preconditioner",
                             gs_iterations=int(out[0]), lcp_residual=float(out[1]))
        stats.contact_ms = 1000.0 * (time.perf_counter() - t0)
        return stats

    @property
    def contacts(self) -> Contacts:
        """The last step's contacts with their forces (made from the device rows' record at the
        first ask after a step solved there)."""
        if self._contacts is None:
            rec = self._device_read[0]
            self._contacts = _record_contacts(rec).responded(rec[:, 19].copy(), rec[:, 16:19].copy())
        return self._contacts

    @contacts.setter
    def contacts(self, value: Contacts | None) -> None:
        self._contacts = value

    def _warm_start(self) -> WarmStart:
        """The host's warm start: the last step's forces by contact name (named here, at their
        first use, where that step was solved from device rows)."""
        if self._warm is None:
            c, (*_, uids, n) = self.contacts, self._device_read
            uids = np.arange(n) if uids is None or len(uids) != n else np.asarray(uids)
            self._warm = WarmStart(contact_names(c.obj, c.node, c.tri, uids), c.force, c.lambda_n > 0.0)
        return self._warm

    def _device_solver(self, body: BodyView, m: int):
        """The factor's services where this step's LCP of ``m`` rows is solved on the device, else
        None (see :mod:`.device_lcp`)."""
        rows = self.options["device_lcp_rows"]
        inner = getattr(body.preconditioner, "inner", None)
        if (not rows or m > rows or self.options["compliance"] != "preconditioner"
                or not getattr(inner, "solves_contact_on_device", lambda: False)()):
            return None
        if self._device_lcp is None or self._device_lcp.rows != rows:
            self._device_lcp = DeviceLCP(rows, self.device)
        return inner

    def _respond(self, body: BodyView, c: Contacts, nodes4: np.ndarray, w4: np.ndarray, ws4: np.ndarray,
                 free: np.ndarray, x: np.ndarray, x_start: np.ndarray, stats: ContactStats,
                 device_lcp: bool = True):
        """LCP of eq. (3) for the contacts ``c`` at the free motion ``x``; returns the correction
        dx = dt^2 P^-1 H^T lambda of the positions (on the device where the factor is), or the
        pending device solve (:class:`PendingLCP`, ``device_lcp`` allowing). ``nodes4`` (k, 4):
        the contact's node and triangle nodes (-1: none), ``ws4`` their weights in the tissue
        point's relative displacement, ``w4`` the same zeroed on fixed nodes (the Jacobian's)."""
        o = self.options
        integ = body.integrator
        dt = integ.dt
        n = body.fem.n_nodes
        k = len(c.node)
        normal = c.normal
        fric = self._friction(c.obj)
        if fric.uniform:  # every contact has the same coefficient: one row each, or three
            r = 3 if fric.value > 0.0 else 1
            mu = np.full(k, fric.value)
            rows = np.full(k, r, np.int32)
            row_start = np.arange(0, r * k, r, dtype=np.int32)
            m = r * k
            fr = np.full(k, r == 3)
        else:
            mu = fric.per_contact
            rows = np.where(mu > 0.0, 3, 1).astype(np.int32)
            row_start = (np.cumsum(rows) - rows).astype(np.int32)
            m = int(rows.sum())
            fr = rows == 3
        friction = m > k
        t1, t2 = tangent_basis(normal) if friction else (None, None)  # the tangent rows' directions
        # H (m x 3n) in node form and delta^0 (m): row r moves the nodes of its contact along its
        # direction (the normal, then the two tangents with friction) times their weights
        if not friction:
            d0 = c.gap.copy()
            H = ConstraintRows(nodes4, w4[:, :, None] * normal[:, None, :], n)
        else:
            d0 = np.zeros(m)
            d0[row_start] = c.gap
            dirs = np.empty((m, 3))
            dirs[row_start] = normal
            # relative displacement during the step of the tissue point against the other surface
            f_rows = fr.nonzero()[0]
            nf = np.maximum(nodes4[f_rows], 0)
            rel = np.einsum("ks,ksj->kj", ws4[f_rows], x[nf] - x_start[nf])
            f_obj = c.obj[f_rows]
            for oi, obj in enumerate(self.objects):
                sel = f_obj == oi
                if np.count_nonzero(sel):
                    rel[sel] -= obj.point_displacement(c.point[f_rows[sel]], dt)
            rs = row_start[f_rows]
            t1f, t2f = t1[f_rows], t2[f_rows]
            d0[rs + 1] = np.einsum("kj,kj->k", t1f, rel)
            d0[rs + 2] = np.einsum("kj,kj->k", t2f, rel)
            dirs[rs + 1], dirs[rs + 2] = t1f, t2f
            owner = np.repeat(np.arange(k), rows)
            H = ConstraintRows(nodes4[owner], w4[owner][:, :, None] * dirs[:, None, :], n)
        # warm start from last step's forces on the same (object, node) or (object, triangle)
        # pairs; nodes are named by the simulation's node uids where it keeps them (stable
        # across cuts), else by index
        uids = body.node_uids
        uids = np.arange(n) if uids is None or len(uids) != n else np.asarray(uids)
        names = contact_names(c.obj, c.node, c.tri, uids)
        lam = np.zeros(m)
        warm = self._warm_start()
        found, f = warm.lookup(names)
        if len(f):
            r = row_start[found] if friction else found  # the normal rows of the contacts found
            lam[r] = np.maximum(0.0, np.einsum("kj,kj->k", f, normal[found]))
            if friction:
                ff = fr[found]
                lam[r[ff] + 1] = np.einsum("kj,kj->k", f[ff], t1[found][ff])
                lam[r[ff] + 2] = np.einsum("kj,kj->k", f[ff], t2[found][ff])

        def finish(lam: np.ndarray, its: int, res: float, kind: str = "preconditioner") -> None:
            """Forces on the tissue, wrenches on the objects, warm start, statistics."""
            t0 = time.perf_counter()
            stats.gs_iterations, stats.lcp_residual, stats.compliance = its, res, kind
            ln = lam[row_start] if friction else lam.copy()
            force = ln[:, None] * normal
            if friction:
                rs = row_start[fr]
                force[fr] += lam[rs + 1][:, None] * t1[fr] + lam[rs + 2][:, None] * t2[fr]
            self._set_wrenches(c, force)
            pressed = ln > 0.0
            self._warm = warm.then(names, force, pressed)
            self.contacts = c.responded(ln, force)
            stats.active_contacts = int(np.count_nonzero(pressed))
            stats.contact_ms += 1000.0 * (time.perf_counter() - t0)

        inner = self._device_solver(body, m) if device_lcp else None
        if inner is not None:  # W, the LCP and the correction launched with the correction's graph
            self._device_lcp.stage(H.nodes, H.coef, d0, lam, row_start, rows, mu)
            stats.lcp_device = True
            stats.compliance_fallbacks = self.compliance_fallbacks
            return PendingLCP(self._device_lcp, inner, body.fem.free, dt, o, m, finish)
        W0, apply_y, kind = compliance(H, o["compliance"], body.preconditioner, integ, body.fem)
        W = W0 + W0.T
        W *= dt * dt * 0.5
        if kind != "diagonal" and not positive_definite(W):
            # A factor corrected by many cuts, stale, with identity-padded DOFs, can stop being
            # positive definite on the contact rows; PGS then diverges. The block diagonal of A
            # always is: use it for this step and say so.
            W0, apply_y, _ = compliance(H, "diagonal", body.preconditioner, integ, body.fem)
            W = W0 + W0.T
            W *= dt * dt * 0.5
            kind = f"diagonal ({kind} not positive definite on the contacts)"
            self.compliance_fallbacks += 1
        stats.compliance_fallbacks = self.compliance_fallbacks
        lam, its, res = self._pgs.solve(W, d0, row_start, rows, mu, o["max_iterations"], o["tolerance"],
                                        o["friction_cone"] == "pyramid", lam)
        # correction with the same compliance: dx = dt^2 P^-1 H^T lambda, v += dx / dt
        y = apply_y(lam)
        if isinstance(y, wp.array):  # on the device: scaled there, never read back
            dx = self._dx.view(n)
            wp.launch(scaled_free_kernel, n, [y, float(dt * dt), body.fem.free, dx], device=self.device)
        else:
            dx = (dt * dt) * np.asarray(y).reshape(n, 3)
            dx *= free[:, None]
        finish(lam, its, res, kind)
        return dx

    def object_friction(self) -> list[float]:
        """Each object's Coulomb coefficient: its own, else the scene's."""
        scene = self.options["friction"]
        return [scene if o.friction is None else o.friction for o in self.objects]

    def _friction(self, obj: np.ndarray) -> Friction:
        """The Coulomb coefficient of contacts with the objects ``obj`` (k,) (-1: the tissue
        itself): an object's own, else the scene's."""
        scene = self.options["friction"]
        per_object = self.object_friction()
        if all(v == scene and math.copysign(1.0, v) == math.copysign(1.0, scene) for v in per_object):
            return Friction(True, scene)
        table = np.array(per_object)
        return Friction(False, scene, np.where(obj >= 0, table[np.maximum(obj, 0)], scene))

    def _set_wrenches(self, c: Contacts, force: np.ndarray) -> None:
        """Each object's wrench from the forces ``force`` (k, 3) on the tissue at the contacts
        ``c`` (see the module docstring); zero for an object without contacts."""
        obj, point = c.obj, c.point
        on = obj >= 0
        if np.count_nonzero(on) < len(on):  # self-collision rows act on no object
            on = on.nonzero()[0]
            obj, force, point = obj[on], force[on], point[on]
        origins = np.array([o.origin for o in self.objects], dtype=np.float64).reshape(-1, 3)
        f_obj = -force
        terms = np.concatenate([f_obj, cross(point - origins[obj], f_obj)], axis=1)  # per contact: force, torque
        wrench = np.zeros((len(self.objects), 6))
        np.add.at(wrench, obj, terms)
        for oi, o in enumerate(self.objects):
            o.force, o.torque = wrench[oi, :3], wrench[oi, 3:]


def _record_contacts(rec: np.ndarray) -> Contacts:
    """The contacts of a device rows' record (:data:`.device_rows.RECORD` columns; their forces
    are added by the caller)."""
    return Contacts(rec[:, 1].astype(np.int64), rec[:, 2].astype(np.int64), rec[:, 9], rec[:, 6:9], rec[:, 3:6],
                    rec[:, 10:13].astype(np.int64), rec[:, 13:16])


class DeviceStep:
    """One step's contacts launched on the device after the free motion (see
    :meth:`ContactSolver.device_rows_plan`): :meth:`launch` launches the detection, the rows, the
    LCP and dx; :meth:`key` names what those launches depend on."""

    READS = 4  # the arrays launch() returns to be read

    def __init__(self, solver: ContactSolver, body: BodyView, inner, limit: int):
        self.solver, self.body, self.inner, self.limit = solver, body, inner, int(limit)
        o = solver.options
        self.lcp, self.rows = solver._device_lcp, solver._device_rows
        self._args = launch_args(o, self.lcp.device.is_cuda)
        self.dt = float(body.integrator.dt)

    def key(self) -> tuple:
        b = self.body
        return (self.lcp.key(self.inner, b.fem.free, self.dt, self._args), self.rows.key(self.limit),
                b.integrator.x.ptr)

    def launch(self) -> tuple[wp.array, list[wp.array]]:
        """Launches only: (dx, the :attr:`READS` arrays to read for
        :meth:`ContactSolver.finish_device_rows`: the LCP's output, the rows' header, record and
        the objects' wrenches)."""
        b = self.body
        self.solver.launch_detection_of(b)
        topo = self.solver._topo
        self.rows.launch(topo, b.integrator.x, b.fem.free, self.lcp, self.limit)
        dx = self.lcp.launch(self.inner, b.fem.free, self.dt, *self._args)
        self.rows.forces(self.lcp, topo.origins)
        return dx, [self.lcp.out, self.rows.header, self.rows.record, self.rows.wrench]


class Friction(NamedTuple):
    """The Coulomb coefficients of a step's contacts: ``uniform`` (all ``value``) or
    ``per_contact`` (k,)."""

    uniform: bool
    value: float
    per_contact: np.ndarray | None = None
