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
             newton_iterations: 1,                # linearisations of eq. (1) per step (1: the paper's);
             newton_tolerance: null,              #   or until ||g|| / ||b|| is within this (then up to 20)
                                                  #   (see implicit_integration.py)
             preconditioner: async_ldlt,          # none | jacobi | async_ldlt | direct
             ldlt: {rotate: true, refresh_every: 1, deterministic: false,
                    lag: 0,                       # with deterministic: install each factor this many
                                                  #   steps after its request (a background
                                                  #   factorization's delay, reproducibly)
                    mode: auto,                   # CHOLMOD: auto | simplicial | supernodal
                    apply_on: auto,               # auto (= host: see bench haptic) | host | device
                    columns_on: auto,             # blocks of columns (U after a cut, contact's W):
                                                  #   auto (= device on CUDA in a scene with contact,
                                                  #   else host: see bench columns) | host | device
                    ordering: auto,               # auto (metis for a device apply, else CHOLMOD's
                                                  #   default) | amd | metis | nesdis | best | ...
                    worker: thread,               # thread | process: two factorization processes
                                                  #   (no GIL shared; host solves only)
                    release_gil: true},           # simplicial factorization through CHOLMOD's C API
                                                  #   (ctypes: the GIL is free meanwhile) where
                                                  #   available; false: scikit-sparse
             graph: auto}                         # auto (on CUDA with a device LDL^T) | true | false

``apply_on: device`` applies the LDL^T factor with Warp kernels (soft_tissue_sim.ldlt_device)
and runs PCG with its scalars on the device (cg.DevicePCG); ``graph`` captures that solve as
a CUDA graph (Warp's API capture on the CPU) replayed each step. ``graph: true`` with the
none/jacobi preconditioners gives the device-scalar PCG too. Advanced device options under
``ldlt``: ``lanes`` (1: a thread per row group, 32: a warp), ``tail_width`` (levels of at
most that many groups run in one single-block launch; 0: one launch per level), ``tail_block``.
"""

from __future__ import annotations

import copy
import math
import os
import warnings
import weakref
from pathlib import Path

import numpy as np
import warp as wp
import yaml

from . import mesh as mesh_mod
from .cg import (
    BlockJacobiPreconditioner,
    DeviceLDLTPreconditioner,
    DevicePCG,
    HostPreconditioner,
    IdentityPreconditioner,
)
from .corotational_fem import CorotationalFEM
from .implicit_integration import BackwardEuler, StepStats
from .material import Damping, MaterialTable, ParameterError

PACKAGE_ROOT = Path(__file__).resolve().parent.parent
SCENES_DIR = PACKAGE_ROOT / "config" / "scenes"
PRECONDITIONERS = ("none", "jacobi", "async_ldlt", "direct")
_KNOWN_KEYS = {
    "name", "description", "device", "mesh", "materials", "mass", "damping", "gravity", "fixed", "time",
    "solver", "instruments", "obstacles", "contact", "cutting", "script", "guard",
}


def share_dirs() -> list[Path]:
    """Where scenes and meshes may live: the source tree, then an installed share/ directory."""
    dirs = [PACKAGE_ROOT]
    try:  # a colcon / ament install
        from ament_index_python.packages import get_package_share_directory

        dirs.append(Path(get_package_share_directory("soft_tissue_sim")))
    except Exception:  # noqa: BLE001 - ament index absent or package not installed: source tree only
        pass
    return dirs


def resolve_path(name: str | os.PathLike, base: Path | None = None) -> Path:
    """Find a scene or mesh file: as given, relative to ``base``, then in the package's dirs."""
    p = Path(name)
    candidates = [p] if p.is_absolute() else [Path.cwd() / p]
    if base is not None and not p.is_absolute():
        candidates.append(base / p)
    for d in share_dirs():
        candidates += [d / p, d / "config" / "scenes" / p, d / "meshes" / p.name]
    for c in candidates:
        if c.is_file():
            return c.resolve()
    raise FileNotFoundError(f"cannot find {str(name)!r} (looked in: {', '.join(str(c) for c in candidates)})")


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


APPLY_ON = ("auto", "host", "device")


def _graph_option(value) -> str:
    v = {True: "true", False: "false"}.get(value, value) if isinstance(value, bool) else str(value).strip().lower()
    if v not in ("auto", "true", "false"):
        raise ParameterError(f"solver graph must be auto, true or false, got {value!r}")
    return v


def make_preconditioner(kind: str, options: dict, snapshot_fn, device="cpu", contact: bool = False):
    if kind == "none":
        return IdentityPreconditioner()
    if kind == "jacobi":
        return BlockJacobiPreconditioner()
    if kind in ("async_ldlt", "direct"):
        from .ldlt_device import ORDERINGS
        from .ldlt_preconditioner import AsyncLDLTPreconditioner

        apply_on = str(options.get("apply_on", "auto"))
        if apply_on not in APPLY_ON:
            raise ParameterError(f"ldlt apply_on must be one of {', '.join(APPLY_ON)}, got {apply_on!r}")
        if apply_on == "auto":  # host: measured on an H100 (bench haptic) the device solve is not faster yet
            apply_on = "host"
        columns_on = str(options.get("columns_on", "auto"))
        if columns_on not in APPLY_ON:
            raise ParameterError(f"ldlt columns_on must be one of {', '.join(APPLY_ON)}, got {columns_on!r}")
        if columns_on == "auto":
            # The device block solve is 5-10x faster than CHOLMOD for blocks of >= 24 columns (bench
            # columns, H100), but each factor must then be converted to the device layout in the
            # worker (a new pattern after every cut: ~0.1 s of numpy holding the GIL). Contact needs a
            # block every step (one column per contact); cutting alone one per cut, which does not
            # pay for the conversion (bench cut-beam on the H100: SMF 96 ms/step with, 70 without).
            columns_on = "device" if (contact and wp.get_device(device).is_cuda) else "host"
        ordering = str(options.get("ordering", "auto"))
        if ordering == "auto":  # METIS: a far shallower elimination tree (fewer levels) for the device solves
            ordering = "metis" if "device" in (apply_on, columns_on) else "default"
        if ordering not in ORDERINGS:
            raise ParameterError(f"ldlt ordering must be auto or one of {', '.join(ORDERINGS)}, got {ordering!r}")
        col_opts = {k: int(options[k]) for k in ("cols_lanes", "tail_block") if k in options}
        # Contact on the host: keep each factor's L and D too, for W by forward solves (delassus.py)
        cols = dict(columns_device=device if columns_on == "device" else None, columns_options=col_opts,
                    min_device_columns=int(options.get("min_device_columns", 6)),
                    lower_factor=contact and columns_on == "host", worker=str(options.get("worker", "thread")),
                    release_gil=bool(options.get("release_gil", True)))
        layout = apply_on == "device"
        try:
            if kind == "direct":  # a fresh exact factor every step: the reference solution
                inner = AsyncLDLTPreconditioner(snapshot_fn, rotate=False, refresh_every=1, deterministic=True,
                                                ordering=ordering, device_layout=layout, **cols)
                inner.name = "direct"
            else:
                inner = AsyncLDLTPreconditioner(
                    snapshot_fn,
                    rotate=bool(options.get("rotate", True)),
                    refresh_every=int(options.get("refresh_every", 1)),
                    deterministic=bool(options.get("deterministic", False)),
                    lag=options.get("lag", 0),
                    mode=str(options.get("mode", "auto")),
                    ordering=ordering,
                    device_layout=layout,
                    **cols,
                )
        except ValueError as exc:  # the device block solve's options, the worker
            raise ParameterError(f"ldlt options: {exc}") from None
        if apply_on == "device":
            dev_opts = {k: int(options[k]) for k in ("lanes", "tail_width", "tail_block", "cols_lanes") if k in options}
            try:
                return DeviceLDLTPreconditioner(inner, device, **dev_opts)
            except ValueError as exc:
                inner.close()
                raise ParameterError(f"ldlt device options: {exc}") from None
        return HostPreconditioner(inner)
    raise ParameterError(f"unknown preconditioner {kind!r}: use one of {', '.join(PRECONDITIONERS)}")


def _weak_call(method):
    ref = weakref.WeakMethod(method)
    return lambda: ref()()


class Simulation:
    """One soft body and the components its scene names. See :func:`load_scene`."""

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
        graph = _graph_option(solver.get("graph", "auto"))
        self.preconditioner = make_preconditioner(
            str(solver.get("preconditioner", "async_ldlt")), dict(solver.get("ldlt") or {}),
            _weak_call(self._snapshot),  # weak: the simulation's finalizer owns the preconditioner
            device=self.device, contact=self._has_contact(config),
        )
        self.integrator = BackwardEuler(
            self.fem, dt, self.damping, config.get("gravity", [0.0, 0.0, -9.81]), self.preconditioner,
            tolerance=float(tol), max_iterations=int(max_it),
            newton_iterations=solver.get("newton_iterations"), newton_tolerance=solver.get("newton_tolerance"),
        )
        device_ldlt = isinstance(self.preconditioner, DeviceLDLTPreconditioner)
        use_graph = graph == "true" or (graph == "auto" and device_ldlt and wp.get_device(self.device).is_cuda)
        if device_ldlt or use_graph:  # PCG with its scalars on the device (captured as a graph if use_graph)
            self.integrator.cg = DevicePCG(self.fem.n_nodes, self.device, float(tol), int(max_it), graph=use_graph)
        # Node identities across topological changes (the preconditioner maps numberings by them).
        self.node_uids = np.arange(self.mesh.n_nodes, dtype=np.int64)
        self.mesh_version = 0
        # Optional components: built only when the scene names them.
        self.contact = None
        self.cutting = None
        if self._has_contact(config):
            from .contact import ContactSolver

            self.contact = ContactSolver(self, config.get("contact") or {}, config.get("instruments") or [],
                                         config.get("obstacles") or [])
        if config.get("cutting"):
            from .cutting import Cutter

            self.cutting = Cutter(self, config["cutting"])
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
        size = float(np.ptp(self.mesh.points, axis=0).max())
        g = float(np.linalg.norm(self.integrator.gravity))
        self._energy_floor = self.fem.total_mass * (g * size + 0.5)  # weight over the body size + 1 m/s
        self._closed = False
        self._finalizer = weakref.finalize(self, self.preconditioner.close)

    # ----------------------------------------------------------- components
    @property
    def has_contact(self) -> bool:
        return self.contact is not None

    @property
    def has_cutting(self) -> bool:
        return self.cutting is not None

    def _snapshot(self):
        """(A at the current state as scipy CSC, per-node rotations, topology) for the LDL^T factorization."""
        integ = self.integrator
        return (self.fem.assemble_scipy(integ.m_coef, integ.k_coef), self.fem.node_rotations(),
                {"uids": self.node_uids.copy(), "version": self.mesh_version})

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

    def _kinetic_energy(self) -> float:
        return self.integrator.energy_kinetic()

    def _diverged(self, stats, ke_before: float) -> str | None:
        """Why the step just taken must not stand (NaN, or runaway kinetic energy), or None."""
        integ = self.integrator
        if not (np.isfinite(stats.residual) and np.isfinite(integ.x.numpy()).all()):
            return "non-finite state"
        ke = self._kinetic_energy()
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
        x_prev, v_prev = wp.clone(integ.x), wp.clone(integ.v)  # last good state
        k0, t0 = integ.step_index, integ.time
        ke_before = self._kinetic_energy() if self.guard_ratio > 0 else 0.0
        stats = integ.step()
        reason = self._diverged(stats, ke_before) if self.guard_ratio > 0 else (
            None if np.isfinite(stats.residual) and np.isfinite(integ.x.numpy()).all() else "non-finite state")
        if reason is None:
            return stats, True

        def rollback():
            integ.x, integ.v = wp.clone(x_prev), wp.clone(v_prev)
            integ.step_index, integ.time = k0, t0

        self.rollbacks += 1
        rollback()
        self.preconditioner.invalidate()  # remedy 1: a fresh factor
        attempts = ["fresh factor"]
        if self.guard_retry:
            stats = integ.step()
            if self._diverged(stats, ke_before) is None:
                stats.extra.update(rolled_back=True, rollbacks=self.rollbacks, guard=reason, remedy="fresh factor")
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
                s2.extra.update(rolled_back=True, rollbacks=self.rollbacks, guard=reason, remedy="two half steps")
                return s2, True
            rollback()
        stats.converged = False
        stats.extra.update(rolled_back=True, rollbacks=self.rollbacks, guard=reason,
                           remedy="none: last good state kept (tried " + ", ".join(attempts) + ")")
        return stats, False

    def _contact_response(self) -> dict:
        """The contact step under the divergence guard: a correction that leaves NaN or a runaway
        kinetic energy is dropped (the free motion stands for this step; the next step detects
        and corrects again) and reported as ``contact_rejected``."""
        integ = self.integrator
        x_free, v_free = wp.clone(integ.x), wp.clone(integ.v)
        ke_free = self._kinetic_energy() if self.guard_ratio > 0 else 0.0
        try:
            cstats = self.contact.step(self)
            reason = None
        except (FloatingPointError, np.linalg.LinAlgError, ValueError) as exc:
            cstats, reason = {}, f"contact solve failed: {type(exc).__name__}: {exc}"
        if reason is None:
            if not np.isfinite(integ.x.numpy()).all() or not np.isfinite(integ.v.numpy()).all():
                reason = "non-finite state after the contact correction"
            elif self.guard_ratio > 0:
                ke = self._kinetic_energy()
                if not ke <= self.guard_ratio * (ke_free + self._energy_floor):
                    reason = f"runaway energy after the contact correction: kinetic {ke:.3g} J after {ke_free:.3g} J"
        if reason is not None:
            integ.x, integ.v = x_free, v_free
            self.contact_rejections += 1
            warnings.warn(f"step {integ.step_index}: {reason}; the free motion stands for this step", stacklevel=2)
            cstats = dict(cstats, contact_rejected=reason)
        cstats["contact_rejections"] = self.contact_rejections
        return cstats

    def step(self) -> StepStats:
        if self._closed:
            raise RuntimeError("simulation is closed")
        stats, ok = self._free_motion()
        if not ok:
            self.last_stats = stats
            return stats
        if self.contact is not None:
            stats.extra.update(self._contact_response())  # LCP correction of x and v, eq. (3)-(4)
        if self.cutting is not None:
            stats.extra.update(self.cutting.step(self))  # blade motion -> mesh change + SMF, eq. (5)-(12)
        self.last_stats = stats
        return stats

    def reset(self) -> None:
        """Back to the initial mesh and state; the preconditioner starts afresh."""
        self.preconditioner.invalidate()
        for comp in (self.contact, self.cutting):
            if comp is not None:
                comp.reset(self)
        if self.mesh_version != 0 or self.mesh is not self.fem.mesh:
            self.mesh = self._initial_mesh.copy()
            self.fem.set_mesh(self.mesh, self._initial_fixed)
        self.node_uids = np.arange(self.mesh.n_nodes, dtype=np.int64)
        self.mesh_version = 0
        self.integrator.set_state(self._initial_mesh.points.copy(), np.zeros_like(self._initial_mesh.points))
        self.integrator.step_index = 0
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
        return self.cutting.cut(self)

    def cut_triangles(self, triangles, frame: str = "world"):
        """Cut along blade triangles (k, 3, 3) in the world (current) or rest frame. Returns a CutResult."""
        if self.cutting is None:
            raise ValueError("this scene has no cutting")
        return self.cutting.cut_triangles(self, triangles, frame)

    def remove_elements(self, center, radius: float, frame: str = "world"):
        """Ablation / aspiration: delete the elements whose centroid is within radius of center."""
        if self.cutting is None:
            raise ValueError("this scene has no cutting")
        return self.cutting.remove_elements(self, center, radius, frame)

    def remove_tets(self, tets):
        """Delete given tets (boolean mask or indices): e.g. lift out a part that was cut free."""
        if self.cutting is None:
            raise ValueError("this scene has no cutting")
        return self.cutting.remove_tets(self, tets)

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
