"""Scenes: YAML files in ``config/scenes/`` that name the components a simulation needs.

The builder constructs exactly what a scene names: a scene without instruments or
obstacles gets no contact solver, a scene without cutting gets no cutting machinery.

Scene keys (all but ``mesh`` and ``materials`` optional)::

    name: beam_2000
    device: auto                  # auto (CUDA if present, else CPU) | cpu | cuda | cuda:N
    mesh: {file: meshes/beam_2000.vtu}            # path relative to the scene file or the package
      # or {generator: beam, n_long: 80, n_cross: 5, spacing: 0.01} / {generator: brain}
      #   / {generator: grid, x: [..], y: [..], z: [..]} (node coordinates of a box grid);
      #   generators take split: mirrored (default, symmetric) | uniform (see mesh.py)
      # optional: scale: 1.0, translate: [x, y, z],
      #   regions: [{box: {min: [..], max: [..]}, material: 1}]  (material id by tet centroid)
    materials: [{id: 0, young: 1.0e5, poisson: 0.3, density: 1000}]
    mass: lumped                  # lumped | consistent
    damping: {mass: 0.1, stiffness: 0.01}          # Rayleigh alpha [1/s], beta [s]
    gravity: [0, 0, -9.81]
    fixed: {axis: x, below: 0.0}  # or {box: {min: [..], max: [..]}} or {nodes: [..]}, or a list of these
    time: {dt: 0.01}
    solver: {tolerance: 1.0e-7, max_iterations: 1000,
             warm_start: true,                    # each solve starts from the last step's dv
             newton_iterations: 1,                # linearisations of eq. (1) per step (1: the paper's);
             newton_tolerance: null,              #   or until ||g|| / ||b|| is within this (then up to 20)
                                                  #   (see implicit_integration.py)
             preconditioner: async_ldlt,          # none | jacobi | async_ldlt | direct
             ldlt: {backend: auto,                # auto | cholmod | dense | cudss (soft_tissue_sim.preconditioner)
                    rotate: true, refresh_every: 1, deterministic: false,
                    lag: 0,                       # with deterministic: install each factor this many
                                                  #   steps after its request (a background
                                                  #   factorization's delay, reproducibly)
                    dense_max_dofs: 12000,        # auto on a GPU: the dense inverse up to this size
                    apply_precision: auto,        # dense: the matrix the apply reads, float32 | float64
                                                  #   (auto: float32 on a GPU, float64 on the CPU and for direct)
                    mode: auto,                   # cholmod: auto | simplicial | supernodal
                    ordering: default,            # cholmod: default | amd | metis | nesdis | best | ...
                    worker: thread,               # cholmod: thread | process (two factorization processes)
                    release_gil: true,            # cholmod: simplicial factorization with the GIL released
                    reserve_sms: auto},           # dense on a GPU: SMs the factorization leaves to the
                                                  #   steps (auto: 16; 0: it may take them all)
             graph: auto,                         # auto (on CUDA with a device factor) | true | false
             stream_priority: high,               # CUDA: the simulation's stream ahead of the factor's | default
             blas_threads: one}                   # one: a step's host BLAS on one thread (beside the
                                                  #   factorization) | default: the libraries' own

``graph`` captures the PCG solve as a CUDA graph (Warp's API capture on the CPU) replayed each
step, with every scalar on the device (cg.DevicePCG); it needs a preconditioner that applies on
the device (none, jacobi, or a dense factor; cuDSS's solve is not capturable).
"""

from __future__ import annotations

import contextlib
import copy
import math
import time
import warnings
import weakref
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import warp as wp
import yaml

from . import graphs
from . import mesh as mesh_mod
from .blas_threads import one_thread
from .body import BodyView
from .buffers import GrowArray
from .cg import DevicePCG
from .corotational_fem import CorotationalFEM
from .implicit_integration import BackwardEuler, StepStats
from .material import Damping, MaterialTable, ParameterError
from .paths import resolve_path
from .preconditioner import make_preconditioner
from .stats import GuardStats
from .transfer import to_host

if TYPE_CHECKING:  # built only in scenes that name cutting
    from .cutting import CutPlan, CutResult, Tissue

_KNOWN_KEYS = {
    "name", "description", "device", "mesh", "materials", "mass", "damping", "gravity", "fixed", "time",
    "solver", "instruments", "obstacles", "contact", "cutting", "script", "guard",
}


def resolve_device(name: str | None) -> str:
    name = (name or "auto").strip()
    if name == "auto":
        return "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"
    if name.startswith("cuda") and wp.get_cuda_device_count() == 0:
        raise ParameterError(f"device {name!r} asked for, but Warp sees no CUDA device")
    if name not in ("cpu",) and not name.startswith("cuda"):
        raise ParameterError(f"unknown device {name!r}: use auto, cpu, cuda or cuda:N")
    return name


def read_scene(scene) -> tuple[dict, Path | None]:
    """A scene as a dict, and the directory it came from (for relative paths)."""
    if isinstance(scene, dict):
        return copy.deepcopy(scene), None
    path = resolve_path(scene)
    try:
        with open(path) as fh:
            cfg = yaml.safe_load(fh)
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise ParameterError(f"cannot read scene file {path}: {type(exc).__name__}: {exc}") from None
    if not isinstance(cfg, dict):
        raise ParameterError(f"scene file {path} does not hold a mapping"
                             + (" (it is empty)" if cfg is None else f" (it holds a {type(cfg).__name__})"))
    cfg.setdefault("name", path.stem)
    return cfg, path.parent


def build_mesh(spec, base: Path | None) -> mesh_mod.TetMesh:
    if not isinstance(spec, dict):
        raise ParameterError(f"scene 'mesh' must be a mapping, got {spec!r}")
    if "file" in spec:
        m = mesh_mod.load_mesh(resolve_path(spec["file"], base), material_key=spec.get("material_key"))
    elif spec.get("generator") == "beam":
        kw = {k: spec[k] for k in ("n_long", "n_cross", "length", "width", "spacing", "split") if k in spec}
        m = mesh_mod.beam_mesh(**kw)
    elif spec.get("generator") == "brain":
        m = mesh_mod.brain_mesh(**{k: spec[k] for k in ("split",) if k in spec})
    elif spec.get("generator") == "grid":
        if not all(k in spec for k in "xyz"):
            raise ParameterError(f"mesh generator 'grid' needs node coordinates x, y and z, got {spec!r}")
        m = mesh_mod.grid_mesh(spec["x"], spec["y"], spec["z"], **{k: spec[k] for k in ("split",) if k in spec})
    else:
        raise ParameterError(f"scene 'mesh' needs 'file' or generator 'beam'/'brain'/'grid', got {spec!r}")
    regions = spec.get("regions") or []
    if regions:  # material ids by region: [{box: {min: [..], max: [..]}, material: 1}, ...] (tet centroids)
        ids = m.material_ids.copy()
        cen = m.centroids()
        for r in regions:
            if not isinstance(r, dict) or "box" not in r or "material" not in r:
                raise ParameterError(f"mesh region needs 'box' and 'material': {r!r}")
            lo, hi = np.asarray(r["box"]["min"], float), np.asarray(r["box"]["max"], float)
            ids[np.all((cen >= lo) & (cen <= hi), axis=1)] = int(r["material"])
        m = mesh_mod.TetMesh(m.points, m.tets, ids)
    scale = float(spec.get("scale", 1.0))
    shift = np.asarray(spec.get("translate", [0.0, 0.0, 0.0]), dtype=np.float64)
    if scale != 1.0 or np.any(shift):
        if not (scale > 0.0 and math.isfinite(scale)):
            raise ParameterError(f"mesh scale must be > 0, got {scale}")
        m = mesh_mod.validate_mesh(m.points * scale + shift, m.tets, m.material_ids)
    return m


def select_fixed(points: np.ndarray, spec) -> np.ndarray:
    """Node indices fixed by a scene's ``fixed`` entry (a mapping or a list of them)."""
    if spec is None:
        return np.zeros(0, dtype=np.int64)
    items = spec if isinstance(spec, list) else [spec]
    sel = np.zeros(len(points), dtype=bool)
    scale = float(np.ptp(points, axis=0).max()) or 1.0
    tol = 1e-9 * scale
    for it in items:
        if not isinstance(it, dict):
            raise ParameterError(f"fixed entry must be a mapping, got {it!r}")
        if "nodes" in it:
            idx = np.asarray(it["nodes"], dtype=np.int64)
            if idx.size and (idx.min() < 0 or idx.max() >= len(points)):
                raise ParameterError(f"fixed node index out of range 0..{len(points) - 1}")
            sel[idx] = True
        elif "axis" in it:
            ax = "xyz".index(it["axis"])
            if "below" in it:
                sel |= points[:, ax] <= float(it["below"]) + tol
            if "above" in it:
                sel |= points[:, ax] >= float(it["above"]) - tol
        elif "box" in it:
            lo = np.asarray(it["box"]["min"], dtype=float)
            hi = np.asarray(it["box"]["max"], dtype=float)
            sel |= np.all((points >= lo - tol) & (points <= hi + tol), axis=1)
        else:
            raise ParameterError(f"fixed entry needs 'nodes', 'axis' or 'box': {it!r}")
    return np.flatnonzero(sel)


def _graph_option(value) -> str:
    v = {True: "true", False: "false"}.get(value, value) if isinstance(value, bool) else str(value).strip().lower()
    if v not in ("auto", "true", "false"):
        raise ParameterError(f"solver graph must be auto, true or false, got {value!r}")
    return v


def _weak_call(method):
    ref = weakref.WeakMethod(method)
    return lambda: ref()()


class Simulation:
    """One soft body and the components its scene names. See :func:`load_scene`.

    A step: the free motion of eq. (1) under the divergence guard, then the contact
    correction (eq. 3-4), then the topology changes of cutting (eq. 5-12). The components
    read the body (:meth:`view`, :meth:`tissue`) and return what they change; the simulation
    applies it. Invariants: a step that diverges (NaN, runaway kinetic energy) or a contact
    correction that does is not kept (the last good state stands, and the statistics say
    so); bad input raises a clear error and changes nothing.
    """

    @staticmethod
    def _has_contact(config: dict) -> bool:
        return bool(config.get("instruments") or config.get("obstacles")
                    or (config.get("contact") or {}).get("self_collision"))

    def __init__(self, config: dict, base: Path | None = None, device: str | None = None):
        unknown = set(config) - _KNOWN_KEYS
        if unknown:
            raise ParameterError(f"unknown scene keys: {sorted(unknown)}")
        self.config = config
        self.name = str(config.get("name", "scene"))
        self.device = resolve_device(device or config.get("device", "auto"))
        wp.init()
        self.mesh = build_mesh(config.get("mesh"), base)
        self.materials = MaterialTable.from_config(config.get("materials"))
        damp = config.get("damping") or {}
        self.damping = Damping(float(damp.get("mass", 0.0)), float(damp.get("stiffness", 0.0)))
        fixed = select_fixed(self.mesh.points, config.get("fixed"))
        self.fem = CorotationalFEM(self.mesh, self.materials, self.device, mass=config.get("mass", "lumped"),
                                   fixed_nodes=fixed)
        solver = dict(config.get("solver") or {})
        tol, max_it = solver.get("tolerance", 1e-7), solver.get("max_iterations", 1000)
        try:  # YAML 1.1 reads "1.0e-7" as a string
            tol = float(tol)
        except (TypeError, ValueError):
            raise ParameterError(f"solver tolerance must be a number, got {tol!r}") from None
        if not 0.0 < tol < 1.0:
            raise ParameterError(f"solver tolerance must be in (0, 1), got {tol!r}")
        if not (isinstance(max_it, int) and max_it >= 1):
            raise ParameterError(f"solver max_iterations must be an integer >= 1, got {max_it!r}")
        dt = (config.get("time") or {}).get("dt", 0.01)
        warm = solver.get("warm_start", True)
        if not isinstance(warm, bool):
            raise ParameterError(f"solver warm_start must be true or false, got {warm!r}")
        graph = _graph_option(solver.get("graph", "auto"))
        priority = str(solver.get("stream_priority", "high"))
        if priority not in ("high", "default"):
            raise ParameterError(f"solver stream_priority must be high or default, got {priority!r}")
        blas = str(solver.get("blas_threads", "one"))
        if blas not in ("one", "default"):
            raise ParameterError(f"solver blas_threads must be one or default, got {blas!r}")
        self._blas_scope = one_thread if blas == "one" else contextlib.nullcontext
        self.stream = None
        if wp.get_device(self.device).is_cuda and priority == "high":
            # the step's kernels go ahead of a factorization running beside them on another stream
            self.stream = wp.Stream(self.device, priority=-1)
            wp.set_stream(self.stream, device=self.device, sync=True)
        # Node identities across topological changes (the preconditioner maps numberings by them).
        self.node_uids = np.arange(self.mesh.n_nodes, dtype=np.int64)
        self.mesh_version = 0
        self.preconditioner = make_preconditioner(
            str(solver.get("preconditioner", "async_ldlt")), dict(solver.get("ldlt") or {}),
            _weak_call(self._snapshot), _weak_call(self._topology),  # weak: the finalizer owns the preconditioner
            device=self.device, n_dofs=3 * self.mesh.n_nodes, contact=self._has_contact(config),
            cutting=bool(config.get("cutting")),
        )
        self.integrator = BackwardEuler(
            self.fem, dt, self.damping, config.get("gravity", [0.0, 0.0, -9.81]), self.preconditioner,
            tolerance=float(tol), max_iterations=int(max_it),
            newton_iterations=solver.get("newton_iterations"), newton_tolerance=solver.get("newton_tolerance"),
            warm_start=warm,
        )
        device_factor = hasattr(self.preconditioner, "backend")  # a factor that applies on the device
        use_graph = graph == "true" or (graph == "auto" and device_factor and wp.get_device(self.device).is_cuda)
        if device_factor or use_graph:  # PCG with its scalars on the device (captured as a graph if use_graph)
            self.integrator.cg = DevicePCG(self.fem.n_nodes, self.device, float(tol), int(max_it), graph=use_graph,
                                           warm_start=warm)
        self.integrator.graph_steps = use_graph  # the step's other launches as graphs too
        # Optional components: built only when the scene names them.
        self.contact = None
        self.cutting = None
        self._penetration_every = 1  # the contact option penetration_every (see _contact_response)
        if self._has_contact(config):
            from .contact import ContactSolver

            self.contact = ContactSolver(config.get("contact") or {}, config.get("instruments") or [],
                                         config.get("obstacles") or [], self.device, self.mesh.points)
            self._penetration_every = self.contact.options["penetration_every"]
        if config.get("cutting"):
            from .cutting import Cutter

            self.cutting = Cutter(config["cutting"], self.preconditioner)
        self._initial_mesh = self.mesh.copy()
        self._initial_fixed = fixed.copy()
        self.last_stats: StepStats | None = None
        self.rollbacks = 0
        self.contact_rejections = 0
        guard = dict(config.get("guard") or {})
        self.guard_ratio = float(guard.get("energy_ratio", 100.0))  # 0 disables the energy test (NaN only)
        self.guard_retry = bool(guard.get("retry", True))
        if not (self.guard_ratio == 0.0 or self.guard_ratio > 1.0):
            raise ParameterError(f"guard energy_ratio must be 0 (off) or > 1, got {self.guard_ratio}")
        self.integrator.read_guard = self.guard_ratio > 0
        self.integrator.keep_start = True  # the state a failed step goes back to, copied by the step's build
        self._contact_begun = False  # this step's instruments took their poses (ContactSolver.prepare)
        self._device_step = None  # (plan, free-motion copy, measured) of a contact step launched with the free motion
        if self.contact is not None:  # the detection launched after the free motion, read with its result
            self.integrator.after_solve = self._launch_contact
        size = float(np.ptp(self.mesh.points, axis=0).max())
        g = float(np.linalg.norm(self.integrator.gravity))
        self._energy_floor = self.fem.total_mass * (g * size + 0.5)  # weight over the body size + 1 m/s
        self._closed = False
        self._ke_state = None  # (kinetic energy, state key): the last guard's reading, of that state
        self._copies: dict = {}  # device copies of the state a step may go back to, by purpose
        self._finalizer = weakref.finalize(self, self.preconditioner.close)

    # ----------------------------------------------------------- components
    @property
    def has_contact(self) -> bool:
        return self.contact is not None

    @property
    def has_cutting(self) -> bool:
        return self.cutting is not None

    def _snapshot(self):
        """(A at the current state, per-node rotations, topology) for the LDL^T factorization. A is
        an :class:`~soft_tissue_sim.host_assembly.AssemblyState` (copies of what A depends on): the
        worker assembles it (``csc()``), so the simulation thread only copies."""
        integ = self.integrator
        return (self.fem.assembly_state(integ.m_coef, integ.k_coef), self.fem.node_rotations(), self._topology())

    def _topology(self) -> dict:
        """The node uids (stable across cuts) and the mesh version: what a factor was made from."""
        return {"uids": self.node_uids.copy(), "version": self.mesh_version}

    def tissue(self) -> Tissue:
        """The body as cutting reads it: the rest mesh, and copies of the state on it read in one
        transfer when the plan first asks for them (the positions and tets on the device for a
        screen)."""
        from .cutting import Tissue

        integ = self.integrator

        def read():
            guess = (integ.dv,) if integ.warm_start else ()  # the solver's guess goes through a change with the state
            x, v, free, *dv = to_host(integ.x, integ.v, self.fem.free, *guess)
            return x.copy(), v.copy(), free.copy(), dv[0].copy() if dv else None

        return Tissue(self.mesh, node_uids=self.node_uids, read=read, positions=integ.x,
                      device_tets=self.fem.tets)

    def _instruments(self) -> dict:
        return self.contact.instruments if self.contact is not None else {}

    def _modify(self, plan: CutPlan) -> CutResult:
        """Apply a planned topology change with the removal of the debris it leaves, as one
        change; the plan's result, completed, says what was done."""
        if plan.change is None:
            return plan.result
        res = plan.result
        t0 = time.perf_counter()
        res.plan_ms = 1000.0 * (t0 - plan.t0)
        self.cutting.join_debris(plan)
        t1 = time.perf_counter()
        res.debris_ms = 1000.0 * (t1 - t0)
        res.correction_ms = self._apply_topology(plan)
        t2 = time.perf_counter()
        res.apply_ms = 1000.0 * (t2 - t1) - res.correction_ms
        res.ms = 1000.0 * (t2 - plan.t0)
        return res

    def _refresh_surface(self) -> float:
        """The contact surface rebuilt for the current mesh (after a change), in ms (0: no contact)."""
        return self.contact.refresh_surface(self.fem) if self.contact is not None else 0.0

    def _request(self, plan_fn) -> CutResult:
        """A modification asked through the API: ``plan_fn(tissue)`` plans it, then it is
        applied with its debris and the contact surface rebuilt; the result's ``ms`` is the
        wall time of all of it (the state's read included), ``surface_ms`` the rebuild's."""
        t0 = time.perf_counter()
        res = self._modify(plan_fn(self.tissue()))
        if res.changed:
            res.surface_ms = self._refresh_surface()
        res.ms = 1000.0 * (time.perf_counter() - t0)
        return res

    def _apply_topology(self, plan: CutPlan) -> float:
        """Mesh, FEM, state and node identities from ``plan.change``; the modification of A it
        makes (the blocks of the removed and added elements, with the rotations of one state)
        goes to the cutter's correction, or the preconditioner starts afresh without one.
        Returns the correction's wall time [ms].

        The rotations are of the current state, computed for the tets around the change alone:
        the removed tets' and the node rotations of their nodes (and of the nodes new ones copy),
        which is all the modification reads; the other tets keep the step's (the next step
        computes all of them, as it does after every step)."""
        change, fem, integ = plan.change, self.fem, self.integrator
        m_coef, k_coef = integ.m_coef, integ.k_coef
        old_tets = fem.mesh.tets
        need = np.zeros(fem.n_nodes, bool)
        need[old_tets[change.removed_tets].ravel()] = True
        need[np.asarray(change.rotation_source, np.int64)] = True
        around = np.flatnonzero(need[old_tets].any(axis=1))  # every tet of those nodes
        R_nodes = fem.node_rotations_around(integ.x, around, np.flatnonzero(need))
        old_blocks = fem.element_blocks(change.removed_tets, m_coef, k_coef)
        fem.set_mesh(change.mesh, change.fixed, change.tet_source)
        integ.set_state(change.x, change.v, change.dv)
        # the state is the same node for node: the tets that kept their source's shape keep its rotation
        fem.update_rotations(integ.x, changed_only=True)
        new_blocks = fem.element_blocks(change.added_tets, m_coef, k_coef)
        self.mesh, self.node_uids = change.mesh, change.node_uids
        self.mesh_version += 1
        t0 = time.perf_counter()
        if not self.cutting.record(plan, change.modification(self.mesh_version, old_blocks, new_blocks, R_nodes)):
            self.preconditioner.invalidate()
        return 1000.0 * (time.perf_counter() - t0)

    def view(self) -> BodyView:
        """The body as the components read it during a step (they return what they change)."""
        return BodyView(self.integrator, self.fem, self.preconditioner, self.node_uids)

    # --------------------------------------------------------------- public
    @property
    def dt(self) -> float:
        return self.integrator.dt

    @property
    def time(self) -> float:
        return self.integrator.time

    @property
    def step_count(self) -> int:
        return self.integrator.step_index

    def _state_key(self) -> tuple:
        """Names the current state: a step or the integrator's set_state (a cut, set_state,
        reset) makes another."""
        return (self.integrator.state_version, self.integrator.step_index)

    def _known_kinetic_energy(self) -> float:
        """The kinetic energy of the current state: the last guard's reading where it was of this
        state, else measured."""
        known = self._ke_state
        return known[0] if known is not None and known[1] == self._state_key() else self._kinetic_energy()

    def _state_buffers(self, purpose: str) -> tuple:
        """(x, v) buffers kept for ``purpose`` (grow-only, across node count changes too), sized
        for the current node count (see :meth:`_copy_state`)."""
        grow = self._copies.get(purpose)
        if grow is None:
            grow = self._copies[purpose] = (GrowArray(wp.vec3d, self.device), GrowArray(wp.vec3d, self.device))
        n = self.integrator.x.shape[0]
        return grow[0].view(n), grow[1].view(n)

    def _copy_state(self, purpose: str) -> tuple:
        """(x, v) copied on the device into buffers kept for ``purpose``: a state the step may go
        back to."""
        integ = self.integrator
        bufs = self._state_buffers(purpose)
        wp.copy(bufs[0], integ.x)
        wp.copy(bufs[1], integ.v)
        return bufs

    def _restore_state(self, bufs: tuple) -> None:
        """The state copied by :meth:`_copy_state`, back into the integrator's own arrays (their
        addresses, which captured graphs use, are kept)."""
        wp.copy(self.integrator.x, bufs[0])
        wp.copy(self.integrator.v, bufs[1])

    def _kinetic_energy(self) -> float:
        return self.integrator.energy_kinetic()

    def _diverged(self, stats, ke_before: float) -> str | None:
        """Why the step just taken must not stand (NaN, or runaway kinetic energy), or None."""
        reading = self.integrator.guard_reading  # read with the solve's result, where it was
        if reading is None:
            reading = to_host(self.integrator.launch_guard())[0]
        ke, nonfinite = (float(g) for g in reading)
        self._ke_state = (ke, self._state_key())  # the contact guard's, or the next step's, "before"
        if not np.isfinite(stats.residual) or nonfinite != 0.0:
            return "non-finite state"
        if not np.isfinite(ke):
            return "non-finite energy"
        if ke > self.guard_ratio * (ke_before + self._energy_floor):
            return f"runaway energy: kinetic {ke:.3g} J after {ke_before:.3g} J"
        return None

    def _free_motion(self):
        """The integrator step (free motion) under the divergence guard.

        NaN or a kinetic energy jumping above ``guard.energy_ratio`` x (before + a floor of the
        body's weight over its size and 1 m/s of motion) rolls the state back to the last good
        step, then the step is retried with a fresh factor, then with two half steps; if all fail
        the last good state is kept. The event is reported in the step statistics.
        """
        integ = self.integrator
        k0, t0 = integ.step_index, integ.time
        ke_before = self._known_kinetic_energy() if self.guard_ratio > 0 else 0.0
        stats = integ.step()
        reason = self._diverged(stats, ke_before) if self.guard_ratio > 0 else (
            None if np.isfinite(stats.residual) and np.isfinite(to_host(integ.x)[0]).all() else "non-finite state")
        if reason is None:
            return stats, True
        prev = self._state_buffers("last good")  # kept here: the retries' builds copy their own starts
        for dst, src in zip(prev, integ.step_start()):
            wp.copy(dst, src)

        def rollback():
            self._restore_state(prev)
            integ.dv.zero_()  # the rejected step's solution is no guess for the retry
            integ.step_index, integ.time = k0, t0

        self.rollbacks += 1
        rollback()
        self.preconditioner.invalidate()  # remedy 1: a fresh factor
        attempts = ["fresh factor"]
        if self.guard_retry:
            stats = integ.step()
            if self._diverged(stats, ke_before) is None:
                stats.guard = GuardStats(True, self.rollbacks, reason, "fresh factor")
                return stats, True
            rollback()
            dt = integ.dt  # remedy 2: two half steps
            attempts.append("two half steps")
            try:
                integ.dt = 0.5 * dt
                self.preconditioner.invalidate()
                s1 = integ.step()
                ok = self._diverged(s1, ke_before) is None
                if ok:
                    s2 = integ.step()
                    ok = self._diverged(s2, ke_before) is None
            finally:
                integ.dt = dt
                self.preconditioner.invalidate()
            if ok:
                integ.step_index, integ.time = k0 + 1, t0 + dt  # two half steps count as one step
                s2.step, s2.time = k0 + 1, t0 + dt
                s2.iterations += s1.iterations
                s2.guard = GuardStats(True, self.rollbacks, reason, "two half steps")
                return s2, True
            rollback()
        stats.converged = False
        stats.guard = GuardStats(True, self.rollbacks, reason,
                                 "none: last good state kept (tried " + ", ".join(attempts) + ")")
        return stats, False

    def _launch_contact(self) -> tuple:
        """The integrator's after_solve hook: the contact detection of the free motion, prepared
        here and launched by the integrator (which reads its arrays with the solve's result),
        or, where the contact solver builds this step's rows on the device
        (:meth:`~soft_tissue_sim.contact.solver.ContactSolver.device_rows_plan`), the whole
        contact step (finished by :meth:`_contact_response` from the same read); the
        instruments take their poses at the first preparation of a step."""
        view = self.view()
        key = self.contact.prepare(view, begin=not self._contact_begun)
        self._contact_begun = True
        plan = self.contact.device_rows_plan(view)
        if plan is None:
            self._device_step = None
            return key, lambda: self.contact.launch_detection_of(view)
        # the whole contact step too (contact.device_rows): the free motion kept, the detection,
        # the rows, the LCP and the correction, the guard and the penetration left, read with the solve
        integ = self.integrator
        free = self._state_buffers("free motion")
        measure = self._measures_penetration(integ.step_index + 1)  # (the step's index once taken)
        guard = integ.guard_after

        def launches():
            integ.copy_state(free[0], free[1])
            dx, outs = plan.launch()
            integ.correct(dx)
            integ.launch_guard(guard)
            gap = self.contact.launch_penetration(view) if measure else None
            return [*outs, guard, *([] if gap is None else [gap])]

        pen_key = self.contact.penetration_key(view) if measure else None
        self._device_step = (plan, free, measure)
        return (key, plan.key(), free[0].ptr, free[1].ptr, guard.ptr, pen_key), launches, ("device rows", measure)

    def _measures_penetration(self, step: int) -> bool:
        """Whether step ``step`` measures the penetration left after its correction (the contact
        option ``penetration_every``: every n-th step, 0 never)."""
        every = self._penetration_every
        return every > 0 and step % every == 0

    def _correct(self, dx, solve=None, measure: bool = True) -> list:
        """x += dx, v += dx / dt (``dx`` None: no correction; ``solve``: a device LCP that makes
        dx), then the guard's values and, with ``measure``, the smallest gap of a detection at
        the corrected positions, read in one wait: [guard, *solve's output, gap] (no gap where
        the tissue has no surface or nothing is measured); see
        :meth:`BackwardEuler.correct_and_read`."""
        if not measure:
            return self.integrator.correct_and_read(dx, ((), None), solve)
        view = self.view()

        def penetration():
            gap = self.contact.launch_penetration(view)
            return [] if gap is None else [gap]

        key = self.contact.penetration_key(view) if self.integrator.graph_steps else None  # None: not captured
        return self.integrator.correct_and_read(dx, (key, penetration), solve)

    def _contact_response(self, stats: StepStats) -> None:
        """The contact step under the divergence guard: a correction that leaves NaN or a runaway
        kinetic energy is dropped (the free motion stands for this step; the next step detects
        and corrects again) and reported as ``contact_rejected``. Fills ``stats.contact`` (None
        when the solve failed) and the guard's contact fields."""
        integ = self.integrator
        ke_free = 0.0
        if self.guard_ratio > 0:
            ke_free = self._known_kinetic_energy()
        read = integ.after_solve_reading  # the detection read with the free motion, if of this state
        host = read[1] if read is not None and read[0] == self._state_key() else None
        measure = self._measures_penetration(integ.step_index)
        device_step, self._device_step = self._device_step, None
        if device_step is not None:  # the contact step launched with the free motion (contact.device_rows)
            plan, free, measured = device_step
            if host is not None:
                k = plan.READS
                (guard, *gap) = host[k:]
                stats.contact = self.contact.finish_device_rows(self.view(), plan, host[:k])
                if stats.contact is not None:
                    self._judge_contact(stats, guard, gap, measured, ke_free, free, None)
                    return
            self._restore_state(free)  # not solved there: the step's contacts on the host
            host = None
        free = self._copy_state("free motion")
        reason = None
        for device_lcp in (True, False):
            try:
                # the (rare) retry detects again: the correction's penetration detection has
                # overwritten what `host` views on the CPU device
                response = self.contact.step(self.view(), host if device_lcp else None,
                                             begin=device_lcp and not self._contact_begun, device_lcp=device_lcp)
            except (FloatingPointError, np.linalg.LinAlgError, ValueError) as exc:
                reason = f"contact solve failed: {type(exc).__name__}: {exc}"
                break
            stats.contact = response.stats
            if not device_lcp:
                stats.contact.lcp_redone = True
            guard, *rest = self._correct(response.dx, response.device, measure)
            if response.device is None or response.device.finish(rest.pop(0)):
                break
            # the device refused W (nothing corrected): this step's contacts again, on the host
            self._restore_state(free)
        self._judge_contact(stats, None if reason else guard, None if reason else rest, measure, ke_free, free,
                            reason)

    def _judge_contact(self, stats: StepStats, guard, rest, measure: bool, ke_free: float, free: tuple,
                       reason: str | None) -> None:
        """The contact correction under the divergence guard (see :meth:`_contact_response`):
        ``guard`` the guard's reading after it, ``rest`` [the smallest gap] where ``measure``d,
        ``ke_free`` the free motion's kinetic energy, ``free`` its copy, ``reason`` why the
        correction already failed (None: judged here)."""
        integ = self.integrator
        if reason is None:
            ke, nonfinite = float(guard[0]), float(guard[1])
            if not measure:
                stats.contact.max_penetration = None
            elif rest and np.isfinite(rest[0][0]):
                stats.contact.max_penetration = float(max(0.0, -rest[0][0]))
            if nonfinite != 0.0 or not np.isfinite(ke):
                reason = "non-finite state after the contact correction"
            elif self.guard_ratio > 0 and not ke <= self.guard_ratio * (ke_free + self._energy_floor):
                reason = f"runaway energy after the contact correction: kinetic {ke:.3g} J after {ke_free:.3g} J"
        if reason is None:
            self._ke_state = (ke, self._state_key())
        else:
            self._restore_state(free)
            self._ke_state = (ke_free, self._state_key()) if self.guard_ratio > 0 else None
            self.contact_rejections += 1
            warnings.warn(f"step {integ.step_index}: {reason}; the free motion stands for this step", stacklevel=3)
        stats.guard = stats.guard or GuardStats()
        stats.guard.contact_rejected = reason
        stats.guard.contact_rejections = self.contact_rejections

    def step(self) -> StepStats:
        if self._closed:
            raise RuntimeError("simulation is closed")
        with self._blas_scope():  # OpenBLAS spinning on every core slows the step and the factorization
            return self._step()

    def _step(self) -> StepStats:
        self._contact_begun = False
        self._device_step = None
        stats, ok = self._free_motion()
        if not ok:
            self.last_stats = stats
            return stats
        if self.contact is not None:
            self._contact_response(stats)  # LCP correction of x and v, eq. (3)-(4)
        if self.cutting is not None:  # blade motion -> mesh change + SMF, eq. (5)-(12)
            t0 = time.perf_counter()
            ops = self.cutting.step(self.step_count, self._instruments())
            results = [self._modify(op(self.tissue())) for op in ops]
            surface_ms = self._refresh_surface() if any(r.changed for r in results) else 0.0
            stats.cutting = self.cutting.step_stats(results)
            if ops:  # the whole cutting phase: the state's reads, planning, changes, correction, surface
                stats.cutting.cut_ms = 1000.0 * (time.perf_counter() - t0)
                stats.cutting.surface_ms = surface_ms
        if not getattr(self.preconditioner, "factorizing", lambda: False)():
            graphs.release()  # graphs replaced by a cut, now that no factorization runs beside the steps
        self.last_stats = stats
        return stats

    def reset(self) -> None:
        """Back to the initial mesh and state; the preconditioner starts afresh."""
        self.preconditioner.invalidate()
        for comp in (self.contact, self.cutting):
            if comp is not None:
                comp.reset()
        if self.mesh_version != 0 or self.mesh is not self.fem.mesh:
            self.mesh = self._initial_mesh.copy()
            self.fem.set_mesh(self.mesh, self._initial_fixed)
        self.node_uids = np.arange(self.mesh.n_nodes, dtype=np.int64)
        self.mesh_version = 0
        self.integrator.set_state(self._initial_mesh.points.copy(), np.zeros_like(self._initial_mesh.points))
        self.integrator.step_index = 0
        self.integrator.last_iterations = None
        self.integrator.time = 0.0
        self.last_stats = None

    def positions(self) -> np.ndarray:
        """(n, 3) current node positions [m] (a copy)."""
        return self.integrator.x.numpy().copy()

    def velocities(self) -> np.ndarray:
        """(n, 3) current node velocities [m/s] (a copy)."""
        return self.integrator.v.numpy().copy()

    def set_state(self, positions, velocities=None) -> None:
        """Replace the current positions and velocities (world frame, one row per node of the
        current mesh); ``velocities`` None means at rest. :meth:`positions` and
        :meth:`velocities` read them back exactly.

        Fixed nodes take the positions given (a prescribed displacement: they stay there) and
        zero velocity. The rest shape, the mesh, the step count and the time are unchanged; the
        preconditioner keeps its factor (PCG converges with it; a factor far from the new state
        costs iterations until its next refresh).
        Raises ``ValueError`` on a wrong shape or a non-finite value; the simulation then keeps
        its state.
        """
        if self._closed:
            raise RuntimeError("simulation is closed")
        n = self.fem.n_nodes
        arrays = []
        for name, a in (("positions", positions), ("velocities", np.zeros((n, 3)) if velocities is None else velocities)):
            try:
                a = np.array(a, dtype=np.float64)
            except (TypeError, ValueError):
                raise ValueError(f"set_state: {name} must be numeric, shape ({n}, 3)") from None
            if a.shape != (n, 3):
                raise ValueError(f"set_state: {name} must have shape ({n}, 3) (one row per node), got {a.shape}")
            bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
            if bad.size:
                raise ValueError(f"set_state: non-finite {name} at nodes {bad[:10].tolist()}"
                                 + (f" and {bad.size - 10} more" if bad.size > 10 else ""))
            arrays.append(a)
        x, v = arrays
        v[self.fem.free.numpy() == 0.0] = 0.0
        self.integrator.set_state(x, v)

    def surface_triangles(self) -> np.ndarray:
        return self.mesh.boundary_faces()

    # ------------------------------------------- instruments, contact, cutting
    def instrument_names(self) -> list[str]:
        return self.contact.instrument_names() if self.contact is not None else []

    def set_instrument_pose(self, name, position, quaternion_xyzw, linear_velocity=None, angular_velocity=None):
        """Pose (world frame) of a named instrument for the next step. Raises ValueError on bad input."""
        if self.contact is None:
            raise ValueError("this scene has no instruments")
        self.contact.set_instrument_pose(name, position, quaternion_xyzw, linear_velocity, angular_velocity)

    def instrument_wrench(self, name):
        """(force, torque) ON the instrument from the last step's contacts, world frame, torque about
        the instrument frame's origin [N, N m]."""
        if self.contact is None:
            raise ValueError("this scene has no instruments")
        return self.contact.instrument_wrench(name)

    def contact_points(self) -> np.ndarray:
        return self.contact.contact_points() if self.contact is not None else np.zeros((0, 3))

    def cut(self):
        """Cut along the blade path since the last cut. Returns a CutResult (tets_changed, message)."""
        if self.cutting is None:
            raise ValueError("this scene has no cutting")
        return self._request(lambda tissue: self.cutting.cut(tissue, self._instruments()))

    def cut_at_blade(self):
        """One cut where the cutting instrument's blade is now (a stab incision as wide as the
        instrument). Returns a CutResult."""
        if self.cutting is None:
            raise ValueError("this scene has no cutting")
        return self._request(lambda tissue: self.cutting.cut_at_blade(tissue, self._instruments()))

    def blade_triangles(self):
        """The cutting blade where it is now as two triangles (2, 3, 3), world frame, or None."""
        if self.cutting is None:
            raise ValueError("this scene has no cutting")
        return self.cutting.blade_triangles(self._instruments())

    def cut_triangles(self, triangles, frame: str = "world"):
        """Cut along blade triangles (k, 3, 3) in the world (current) or rest frame. Returns a CutResult."""
        if self.cutting is None:
            raise ValueError("this scene has no cutting")
        return self._request(lambda tissue: self.cutting.cut_triangles(tissue, triangles, frame))

    def remove_elements(self, center, radius: float, frame: str = "world"):
        """Ablation / aspiration: delete the elements whose centroid is within radius of center."""
        if self.cutting is None:
            raise ValueError("this scene has no cutting")
        return self._request(lambda tissue: self.cutting.remove_elements(tissue, center, radius, frame))

    def remove_tets(self, tets):
        """Delete given tets (boolean mask or indices): e.g. lift out a part that was cut free."""
        if self.cutting is None:
            raise ValueError("this scene has no cutting")
        return self._request(lambda tissue: self.cutting.remove_tets(tissue, tets))

    def set_cutting(self, active: bool) -> None:
        """Blade active: cut continuously while the instrument moves (like a pedal)."""
        if self.cutting is None:
            raise ValueError("this scene has no cutting")
        self.cutting.set_active(bool(active))

    def energy(self) -> dict:
        ke, pe, ee = self.integrator.energy()
        return {"kinetic": ke, "gravity": pe, "elastic": ee, "total": ke + pe + ee}

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._finalizer()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def load_scene(scene, device: str | None = None, overrides: dict | None = None) -> Simulation:
    """Build the simulation a scene describes.

    ``scene``: a path to a YAML file (absolute, relative to the working directory, or a
    name in ``config/scenes/``) or a dict with the same keys. ``device`` overrides the
    scene's device. ``overrides`` is merged into the scene (one level deep per key).
    """
    cfg, base = read_scene(scene)
    for k, v in (overrides or {}).items():
        if isinstance(v, dict) and isinstance(cfg.get(k), dict):
            cfg[k] = {**cfg[k], **v}
        else:
            cfg[k] = v
    return Simulation(cfg, base, device)
