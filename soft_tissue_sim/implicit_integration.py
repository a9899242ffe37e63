"""Backward Euler, linearised once per step (paper eq. 1, after Baraff & Witkin 1998).

    (M - dt B - dt^2 K) dv = dt f(u_t, v_t) + dt^2 K v_t,   v += dv,   u += dt v

With the corotated positive stiffness K (= -df/dx) and Rayleigh damping
B = -(alpha M + beta K) this reads

    A  = (1 + dt alpha) M + (dt beta + dt^2) K
    b  = dt (f_elastic + f_gravity + f_external) - dt alpha M v - (dt beta + dt^2) K v

A is solved matrix-free by PCG (:mod:`soft_tissue_sim.cg`); fixed nodes are filtered out
of the system (zero right-hand side, identity rows) and keep zero velocity.

That single linearisation (the paper's, the default) solves backward Euler exactly only where
f is linear over the step. On stiff bodies and large steps it is not, and the step can create
energy. ``newton_iterations`` N > 1 re-linearises: from the first solution v_1, each further
iteration k evaluates the nonlinear residual of backward Euler at x_k = x_t + dt v_k,

    g(v_k) = M (v_k - v_t) - dt (f_elastic(x_k) + f_gravity + f_external - alpha M v_k - beta K_k v_k),

with the rotations (and K_k) of x_k, and solves A_k dv = -g(v_k) with the same preconditioner
(A_k is A with the rotations of x_k), v_{k+1} = v_k + dv, x_{k+1} = x_k + dt dv. It stops after
N linearisations, or earlier where ``newton_tolerance`` is given and ||g|| / ||b|| (b the first
right-hand side) is within it. Invariants: N = 1 is exactly the paper's step; the fixed nodes
keep zero velocity in every iteration.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, fields

import numpy as np
import warp as wp

from . import graphs
from .buffers import GrowArray, PackedArrays
from .cg import PCG
from .corotational_fem import CorotationalFEM
from .material import Damping, ParameterError
from .stats import ContactStats, CutStats, GuardStats
from .transfer import Readback, to_host

wp.set_module_options({"enable_backward": False})  # no gradients are taken


@wp.kernel
def _gravity_kernel(count: wp.array(dtype=wp.int32), mass: wp.array(dtype=wp.float64), g: wp.vec3d,
                    ext: wp.array(dtype=wp.vec3d), f: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
    if i < count[0]:
        f[i] = mass[i] * g + ext[i]


@wp.kernel
def _copy_state_kernel(count: wp.array(dtype=wp.int32), x: wp.array(dtype=wp.vec3d), v: wp.array(dtype=wp.vec3d),
                       x0: wp.array(dtype=wp.vec3d), v0: wp.array(dtype=wp.vec3d)):
    """x0 = x, v0 = v for the current nodes."""
    i = wp.tid()
    if i < count[0]:
        x0[i] = x[i]
        v0[i] = v[i]


@wp.kernel
def _update_kernel(
    count: wp.array(dtype=wp.int32),
    dv: wp.array(dtype=wp.vec3d),
    free: wp.array(dtype=wp.float64),
    dt: wp.float64,
    v: wp.array(dtype=wp.vec3d),
    x: wp.array(dtype=wp.vec3d),
):
    """v = free (v + dv), x += dt v for the current nodes (launched over a capacity)."""
    i = wp.tid()
    if i >= count[0]:
        return
    vi = free[i] * (v[i] + dv[i])
    v[i] = vi
    x[i] = x[i] + dt * vi


@wp.kernel
def _rhs_kernel(
    count: wp.array(dtype=wp.int32),
    f: wp.array(dtype=wp.vec3d),
    Mdv: wp.array(dtype=wp.vec3d),
    Mv: wp.array(dtype=wp.vec3d),
    Kv: wp.array(dtype=wp.vec3d),
    free: wp.array(dtype=wp.float64),
    dt: wp.float64,
    c_m: wp.float64,
    c_k: wp.float64,
    b: wp.array(dtype=wp.vec3d),
):
    """b = dt f - M dv - c_m M v - c_k K v on free nodes: the right-hand side of eq. (1)
    (dv = 0, c_k = dt beta + dt^2) and, re-linearised, -g(v_k) = dt f(x_k) - M (v_k - v_t)
    - dt alpha M v_k - dt beta K_k v_k (c_k = dt beta)."""
    i = wp.tid()
    if i < count[0]:
        b[i] = free[i] * (dt * f[i] - Mdv[i] - c_m * Mv[i] - c_k * Kv[i])


@wp.kernel
def _difference_kernel(a: wp.array(dtype=wp.vec3d), c: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
    out[i] = a[i] - c[i]


@wp.kernel
def _newton_update_kernel(
    dv: wp.array(dtype=wp.vec3d),
    free: wp.array(dtype=wp.float64),
    dt: wp.float64,
    v: wp.array(dtype=wp.vec3d),
    x: wp.array(dtype=wp.vec3d),
):
    """v_{k+1} = v_k + dv, x_{k+1} = x_k + dt dv (= x_t + dt v_{k+1}); fixed nodes unchanged."""
    i = wp.tid()
    d = free[i] * dv[i]
    v[i] = v[i] + d
    x[i] = x[i] + dt * d


@wp.kernel
def _energy_kernel(
    x: wp.array(dtype=wp.vec3d),
    v: wp.array(dtype=wp.vec3d),
    mass: wp.array(dtype=wp.float64),
    g: wp.vec3d,
    out: wp.array(dtype=wp.float64),
):
    i = wp.tid()
    ke = wp.float64(0.5) * mass[i] * wp.dot(v[i], v[i])
    pe = -mass[i] * wp.dot(g, x[i])
    wp.atomic_add(out, 0, ke)
    wp.atomic_add(out, 1, pe)


@wp.kernel
def _guard_kernel(
    count: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3d),
    v: wp.array(dtype=wp.vec3d),
    mass: wp.array(dtype=wp.float64),
    out: wp.array(dtype=wp.float64),
):
    """out[0] += the kinetic energy, out[1] += the number of nodes with a non-finite x or v
    (the current nodes; launched over a capacity)."""
    i = wp.tid()
    if i >= count[0]:
        return
    wp.atomic_add(out, 0, wp.float64(0.5) * mass[i] * wp.dot(v[i], v[i]))
    s = wp.dot(x[i], x[i]) + wp.dot(v[i], v[i])
    if not wp.isfinite(s):
        wp.atomic_add(out, 1, wp.float64(1.0))


@wp.kernel
def _correct_kernel(
    count: wp.array(dtype=wp.int32),
    dx: wp.array(dtype=wp.vec3d),
    dt: wp.float64,
    x: wp.array(dtype=wp.vec3d),
    v: wp.array(dtype=wp.vec3d),
):
    """x += dx, v += dx / dt: a correction of the positions that the velocities follow (the
    current nodes; launched over a capacity)."""
    i = wp.tid()
    if i >= count[0]:
        return
    x[i] = x[i] + dx[i]
    v[i] = v[i] + dx[i] / dt


_COMPONENT = {"component": True}  # a field holding a record some part of the step adds


@dataclass
class StepStats:
    """What one step did and cost. Times in milliseconds.

    The plain fields are the integrator's (the free motion of eq. 1). ``guard``, ``contact``
    and ``cutting`` are the records (:mod:`soft_tissue_sim.stats`) that the divergence guard
    and the components add, None where the scene has no such component or it had nothing to
    say. :meth:`as_dict` is one flat mapping: the plain fields, then the records' fields that
    are not None. A new plain field needs nothing more; a new record, ``metadata=_COMPONENT``.
    """

    step: int = 0
    time: float = 0.0
    iterations: int = 0  # PCG iterations, summed over the step's linearisations
    residual: float = 0.0  # true relative residual ||b - A x|| / ||b|| of the last linear solve
    converged: bool = True  # every solve within its tolerance (and the nonlinear one, if asked)
    recursive_residual: float = 0.0  # where the recursion of the last solve stopped (may drift)
    residual_floor: float = 0.0  # eps ||A|| ||x|| / ||b||: about the least residual float64 reaches
    tolerance_unreachable: bool = False  # a solve was asked a tolerance below its floor
    newton_iterations: int = 1  # linearisations of eq. (1) in this step
    nonlinear_residual: float | None = None  # with Newton on: ||g|| / ||b|| after the last linearisation
    build_ms: float = 0.0
    solve_ms: float = 0.0
    total_ms: float = 0.0
    precond_ms: float = 0.0
    preconditioner: str = "none"
    factor_age: int = -1
    factorization_ms: float = 0.0
    refresh_interval: float = 0.0
    worker_error: str | None = None
    guard: GuardStats | None = field(default=None, metadata=_COMPONENT)
    contact: ContactStats | None = field(default=None, metadata=_COMPONENT)
    cutting: CutStats | None = field(default=None, metadata=_COMPONENT)

    @property
    def extra(self) -> dict:
        """The records' fields that are not None, flat (a copy: set the records' fields)."""
        out = {}
        for f in fields(self):
            record = getattr(self, f.name)
            if f.metadata.get("component") and record is not None:
                out.update((k, v) for k, v in asdict(record).items() if v is not None)
        return out

    def as_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self) if not f.metadata.get("component")}
        d.update(self.extra)
        return d


class BackwardEuler:
    """State (positions, velocities) and the linearised backward Euler step of one body."""

    def __init__(self, fem: CorotationalFEM, dt: float, damping: Damping, gravity, preconditioner,
                 tolerance: float = 1e-7, max_iterations: int = 1000, newton_iterations: int | None = None,
                 newton_tolerance: float | None = None, warm_start: bool = True):
        dt = float(dt)
        if not np.isfinite(dt) or dt <= 0.0:
            raise ParameterError(f"time step dt must be > 0 and finite, got {dt}")
        if newton_tolerance is not None:
            if isinstance(newton_tolerance, bool):
                raise ParameterError(f"solver newton_tolerance must be a number in (0, 1), got {newton_tolerance!r}")
            try:
                newton_tolerance = float(newton_tolerance)
            except (TypeError, ValueError):
                raise ParameterError(f"solver newton_tolerance must be a number in (0, 1), got {newton_tolerance!r}") from None
            if not 0.0 < newton_tolerance < 1.0:
                raise ParameterError(f"solver newton_tolerance must be in (0, 1), got {newton_tolerance!r}")
        if newton_iterations is None:
            newton_iterations = 1 if newton_tolerance is None else 20
        if isinstance(newton_iterations, bool) or not isinstance(newton_iterations, (int, np.integer)) \
                or newton_iterations < 1:
            raise ParameterError(f"solver newton_iterations must be an integer >= 1, got {newton_iterations!r}")
        self.newton_iterations = int(newton_iterations)
        self.newton_tolerance = newton_tolerance
        g = np.asarray(gravity, dtype=np.float64)
        if g.shape != (3,) or not np.all(np.isfinite(g)):
            raise ParameterError(f"gravity must be 3 finite numbers, got {gravity!r}")
        self.fem = fem
        self.device = fem.device
        self.dt = dt
        self.damping = damping
        self.gravity = g
        self.preconditioner = preconditioner
        # warm_start (:attr:`warm_start`, the PCG's own): each step's solve starts from the last
        # accepted step's dv; a cut carries dv to the new mesh (set_state's dv); set_state
        # without one, reset, the guard's rollback and Newton's later solves start from 0
        self.cg = PCG(fem.n_nodes, fem.device, tolerance, max_iterations, warm_start)
        self.step_index = 0
        self.time = 0.0
        self.last_iterations: int | None = None  # the last step's PCG iterations (the refresh policy reads them)
        # read_guard: a device solve's step also launches the divergence guard (launch_guard) at
        # the new state and reads it with the solve's scalars: guard_reading (kinetic energy,
        # non-finite nodes) of the last step, None where it was not read so
        self.read_guard = False
        self.guard_reading = None
        # after_solve: where the solve is only launched (that path), a callable that prepares on
        # the host what is launched after the free motion and returns (key, launch) or (key,
        # launch, layout) (a name for the list of arrays launch returns): launch()
        # launches it and returns device arrays, read in the step's one wait; key names what
        # the launches depend on (None: not to be captured). after_solve_reading = (the state's
        # name (state_version, step_index), their host views) of the last step, or None
        self.after_solve = None
        self.after_solve_reading = None
        # (the hook may name a layout of its arrays: a read-back each, see _finish_launched)
        self._readbacks = {None: Readback()}
        self._after_replay = graphs.Replayer(self.device, "BackwardEuler after the solve", slots=2)
        # the correction's read-back, one per layout (with a solve's output or without), so that a
        # replayed graph writes into the buffers of the layout it was captured with
        self._correction_reads = {False: Readback(), True: Readback()}
        self._correction_replay = graphs.Replayer(self.device, "BackwardEuler correction", slots=2)
        # the node rotations of eq. (2) launched by build() where the preconditioner takes them
        # from there (its begin_step reads fem's node rotations as build left them)
        self.node_rotations_in_build = bool(getattr(preconditioner, "uses_build_rotations", False))
        # graph_steps: the step's launches between its reads (build, after the solve, and the
        # caller's, e.g. the contact correction) captured as graphs and replayed while their keys hold
        self.graph_steps = False
        self._build_replay = graphs.Replayer(self.device, "BackwardEuler.build", eager=True)
        # keep_start: build() first copies x and v into kept arrays (step_start), in its graph: the
        # state a caller may go back to if the step fails
        self.keep_start = False
        self.state_version = 0  # counts set_state calls: with step_index, names the state (x, v)
        # the work vectors and the state: views into allocations kept across node-count changes
        self._work = {name: GrowArray(wp.float64 if name in self._PAIRS else wp.vec3d, self.device)
                      for name in self._WORK}
        # (x, v and dv, the solve's unknown and the next one's guess, in one allocation)
        self._state = PackedArrays({"x": wp.vec3d, "v": wp.vec3d, "dv": wp.vec3d}, self.device)
        self._allocate()
        self._state.reserve({"x": fem.n_nodes, "v": fem.n_nodes, "dv": fem.n_nodes})
        self.x, self.v, self.dv = (self._state.array(k) for k in ("x", "v", "dv"))
        wp.copy(self.x, fem.rest)
        self.v.zero_()
        self.dv.zero_()

    # coefficients of A = m_coef M + k_coef K
    @property
    def m_coef(self) -> float:
        return 1.0 + self.dt * self.damping.mass

    @property
    def k_coef(self) -> float:
        return self.dt * self.damping.stiffness + self.dt * self.dt

    # f, the external forces, M dv of the first linearisation (zero), b, M v, K v, the energy
    # and guard reductions (2 values each), the step's start velocity (Newton), its dv and M dv
    _WORK = ("f", "f_ext", "_zero", "b", "_Mv", "_Kv", "_energy", "_guard", "_guard_after", "_v_t", "_dvel", "_Mdv",
             "_x0", "_v0")
    _PAIRS = ("_energy", "_guard", "_guard_after")  # two values each

    @property
    def warm_start(self) -> bool:
        """Whether each step's solve starts from the last step's dv (the PCG's setting, kept
        where the simulation puts another PCG)."""
        return self.cg.warm_start

    def _allocate(self) -> None:
        """The work vectors for the current node count, zeroed (views of kept allocations)."""
        n = self.fem.n_nodes
        for name, buf in self._work.items():
            a = buf.view(2 if name in self._PAIRS else n)
            a.zero_()
            setattr(self, name, a)

    def set_state(self, x: np.ndarray, v: np.ndarray, dv: np.ndarray | None = None) -> None:
        """Replace positions and velocities (e.g. after a topology change or a rollback): written
        into the state's kept arrays (their addresses change only where the node count outgrows
        them), sent in one copy. ``dv``: the next solve's guess on the new state (a change
        carries the last one through, :class:`~soft_tissue_sim.cutting.TopologyChange`); None:
        zero."""
        if x.shape[0] != self.fem.n_nodes:
            raise ValueError("state size does not match the mesh")
        n = x.shape[0]
        if n != self.f.shape[0]:
            self._allocate()
            self.cg.resize(n)
        st = self._state
        st.reserve({"x": n, "v": n, "dv": n})
        st.host("x")[...] = x
        st.host("v")[...] = v
        st.host("dv")[...] = dv if dv is not None and self.warm_start else 0.0
        st.send(("x", "v", "dv"))
        self.x, self.v, self.dv = (st.array(k) for k in ("x", "v", "dv"))
        self.state_version += 1

    def matvec(self, p: wp.array, out: wp.array) -> None:
        self.fem.system_product(p, p, out, 1.0, 0.0, self.m_coef, self.k_coef)

    def norm_key(self) -> tuple:
        """What the PCG's cached ||A|| estimate depends on: the coefficients of A (the state
        and cuts change ||A|| little; it sets only the order of the float64 floor)."""
        return (float(self.m_coef), float(self.k_coef))

    def graph_key(self) -> tuple:
        """What a captured ``matvec`` depends on (array addresses, the launches' dimensions,
        coefficients): a graph replay is valid while this is unchanged (see cg.DevicePCG). The
        node and tet counts are not in it: the launches read them on the device, so a topology
        change that keeps the allocations keeps the key."""
        f = self.fem
        arrays = (f.counts, f.tets, f.Dm_inv, f.volume, f.mu, f.lam, f.rho, f.rotations, f.free, f.lumped_mass, f._Kp)
        return (f.node_dim, f.tet_dim, bool(f.consistent_mass), float(self.m_coef), float(self.k_coef),
                tuple(a.ptr for a in arrays))

    def build_key(self) -> tuple:
        """What build()'s launches depend on: the operator's graph_key (FEM arrays, sizes,
        coefficients), the integrator's arrays, gravity, dt and the damping."""
        f = self.fem
        arrays = (self.x, self.v, self.f, self.f_ext, self._zero, self._Mv, self._Kv, self.b, f._ones(),
                  f._rot_acc, f._node_rot)
        return (self.graph_key(), tuple(a.ptr for a in arrays), tuple(float(g) for g in self.gravity),
                float(self.dt), float(self.damping.mass), float(self.damping.stiffness), self.node_rotations_in_build,
                self.keep_start and (self._x0.ptr, self._v0.ptr))

    def build(self) -> None:
        """Rotations at u_t and the right-hand side b of eq. (1) (and the node rotations where
        :attr:`node_rotations_in_build`). Launches only; with :attr:`graph_steps` they are
        captured (a CUDA graph; Warp's API capture on the CPU) once per :meth:`build_key` and
        replayed (:class:`soft_tissue_sim.graphs.Replayer`)."""
        self._build_replay.run(self.build_key() if self.graph_steps else None, self._launch_build)
        self.fem.node_rotations_current = self.node_rotations_in_build  # as the launches leave it

    def step_start(self) -> tuple[wp.array, wp.array]:
        """(x, v) as the last :meth:`build` found them, with :attr:`keep_start` (valid until the
        next build)."""
        return self._x0, self._v0

    def _launch_build(self) -> None:
        """The launches of :meth:`build`."""
        fem, dt = self.fem, self.dt
        if self.keep_start:
            self.copy_state(self._x0, self._v0)
        fem.update_rotations(self.x)
        wp.launch(_gravity_kernel, fem.node_dim,
                  [fem.n_nodes_dev, fem.lumped_mass, wp.vec3d(*self.gravity), self.f_ext, self.f], device=self.device)
        fem.add_elastic_forces(self.x, self.f)
        fem.stiffness_product(self.v, self._Kv)
        if self.damping.mass > 0.0:
            fem.mass_product(self.v, self._Mv)
        else:
            fem.zero_nodes(self._Mv)
        wp.launch(_rhs_kernel, fem.node_dim,
                  [fem.n_nodes_dev, self.f, self._zero, self._Mv, self._Kv, fem.free, dt, dt * self.damping.mass,
                   self.k_coef, self.b], device=self.device)
        if self.node_rotations_in_build:
            fem.update_node_rotations()

    def _norm(self, a: wp.array) -> float:
        return float(np.sqrt(self.cg._inner(a, a)))

    def newton_residual(self) -> None:
        """b = -g(v_k) at the current state x_k = x_t + dt v_k (rotations updated to x_k)."""
        fem, dt = self.fem, self.dt
        fem.update_rotations(self.x)
        wp.launch(_gravity_kernel, fem.node_dim,
                  [fem.n_nodes_dev, fem.lumped_mass, wp.vec3d(*self.gravity), self.f_ext, self.f], device=self.device)
        fem.add_elastic_forces(self.x, self.f)
        wp.launch(_difference_kernel, fem.n_nodes, [self.v, self._v_t, self._dvel], device=self.device)
        fem.mass_product(self._dvel, self._Mdv)
        if self.damping.stiffness > 0.0:
            fem.stiffness_product(self.v, self._Kv)
        else:
            self._Kv.zero_()
        if self.damping.mass > 0.0:
            fem.mass_product(self.v, self._Mv)
        else:
            self._Mv.zero_()
        wp.launch(_rhs_kernel, fem.node_dim,
                  [fem.n_nodes_dev, self.f, self._Mdv, self._Mv, self._Kv, fem.free, dt, dt * self.damping.mass,
                   dt * self.damping.stiffness, self.b], device=self.device)

    def step(self) -> StepStats:
        t0 = time.perf_counter()
        newton = self.newton_iterations > 1 or self.newton_tolerance is not None
        if newton:
            wp.copy(self._v_t, self.v)
        self.build()
        self.preconditioner.begin_step(self)
        t1 = time.perf_counter()
        self.guard_reading = None
        self.after_solve_reading = None
        after = None
        # a device solve is only launched here: its result and the guard's values are read in one wait
        launch = getattr(self.cg, "launch", None) if self.read_guard and not newton else None
        solve = launch if launch is not None else self.cg.solve
        res = solve(self.matvec, self.b, self.dv, self.preconditioner)
        if res is None:
            s, guard, *after = self._finish_launched()
            res = self.cg.result(s)
            self.guard_reading = (float(guard[0]), float(guard[1]))
        else:
            self._launch_update()
        t2 = time.perf_counter()
        solve_s = t2 - t1
        iterations, precond_ms, converged = res.iterations, res.precond_ms, res.converged
        unreachable = res.tolerance_unreachable
        linearisations, nonlinear = 1, float("nan")
        if newton:
            b0 = self._norm(self.b)  # the first right-hand side: the scale of the nonlinear residual
            scale = b0 if b0 > 0.0 else 1.0
            while True:
                self.newton_residual()
                nonlinear = self._norm(self.b) / scale
                if (self.newton_tolerance is not None and nonlinear <= self.newton_tolerance) \
                        or linearisations >= self.newton_iterations or not np.isfinite(nonlinear):
                    break
                ts = time.perf_counter()
                self.dv.zero_()  # a correction: no guess
                res = self.cg.solve(self.matvec, self.b, self.dv, self.preconditioner)
                solve_s += time.perf_counter() - ts
                wp.launch(_newton_update_kernel, self.fem.n_nodes, [self.dv, self.fem.free, self.dt, self.v, self.x],
                          device=self.device)
                linearisations += 1
                iterations += res.iterations
                precond_ms += res.precond_ms
                converged = converged and res.converged
                unreachable = unreachable or res.tolerance_unreachable
            if self.newton_tolerance is not None:
                converged = converged and nonlinear <= self.newton_tolerance
        # the step's own stream only: a factorization in flight on another stream is not waited for
        if wp.get_device(self.device).is_cuda:
            wp.synchronize_stream(wp.get_stream(self.device))
        t3 = time.perf_counter()
        self.step_index += 1
        self.time += self.dt
        if after:
            self.after_solve_reading = ((self.state_version, self.step_index), after)
        self.last_iterations = iterations
        ps = self.preconditioner.stats()
        stats = StepStats(
            step=self.step_index,
            time=self.time,
            iterations=iterations,
            residual=res.residual,
            converged=converged,
            recursive_residual=res.recursive_residual,
            residual_floor=res.residual_floor,
            tolerance_unreachable=unreachable,
            newton_iterations=linearisations,
            build_ms=1000.0 * (t1 - t0),
            solve_ms=1000.0 * solve_s,
            total_ms=1000.0 * (t3 - t0),
            precond_ms=precond_ms,
            preconditioner=self.preconditioner.name,
            factor_age=int(ps.get("factor_age", -1)),
            factorization_ms=float(ps.get("factorization_ms", 0.0)),
            refresh_interval=float(ps.get("refresh_interval", 0.0)),
            worker_error=ps.get("worker_error"),
        )
        if newton:
            stats.nonlinear_residual = nonlinear
        return stats

    def _launch_update(self) -> None:
        f = self.fem
        wp.launch(_update_kernel, f.node_dim, [f.n_nodes_dev, self.dv, f.free, self.dt, self.v, self.x],
                  device=self.device)

    def _finish_launched(self) -> list:
        """After a launched solve: the update of x and v, the guard's reduction and the
        ``after_solve`` hook's launches, their arrays copied to the host with the solve's
        scalars and read in one wait: [scalars, guard, *the hook's arrays]. Where the build is
        graphed these launches are too, one graph per arguments (the hook's key included; a
        hook without a key: plain launches)."""
        hook_key, hook_launch, *layout = self.after_solve() if self.after_solve is not None else ((), None)
        readback = self._readbacks.setdefault(layout[0] if layout else None, Readback())

        def launches():
            self._launch_update()
            guard = self.launch_guard()  # of the free motion, before the hook's launches (which may correct it)
            extra = hook_launch() if hook_launch is not None else []
            readback.copy(self.cg.scalars, guard, *extra)

        key = None
        if self.graph_steps and hook_key is not None:
            key = (self._state_arrays_key(), self.dv.ptr, self.cg.scalars.ptr, hook_key, readback.key())
        self._after_replay.run(key, launches)
        return readback.read(self.device)

    def correct_and_read(self, dx, hook: tuple = ((), None), solve=None) -> list:
        """x += dx, v += dx / dt (:meth:`correct`; ``dx`` None: none), then the guard's reduction
        and ``hook``'s launches (``(key, launch)`` as ``after_solve`` returns them: launched after
        the correction, their arrays read with the guard), in one wait: [guard, *solve's arrays,
        *the hook's arrays]. ``solve``: launches that make dx first (``key()``, ``launch()`` ->
        (dx, arrays to read); dx then None), e.g. a contact LCP solved on the device. Where the
        step is graphed (and dx is on the device) as one graph per arguments."""
        hook_key, hook_launch = hook
        readback = self._correction_reads[solve is not None]

        def launches():
            d, outs = solve.launch() if solve is not None else (dx, [])
            if d is not None:
                self.correct(d)
            extra = hook_launch() if hook_launch is not None else []
            readback.copy(self.launch_guard(), *outs, *extra)

        key = None
        if self.graph_steps and hook_key is not None and (dx is None or isinstance(dx, wp.array)):
            key = (None if dx is None else dx.ptr, None if solve is None else solve.key(), self._state_arrays_key(),
                   hook_key, readback.key())
        self._correction_replay.run(key, launches)
        return readback.read(self.device)

    def replayers(self) -> dict:
        """The step's graph replayers by name (the build, the PCG's where it has one, the
        launches after the solve, the correction's): what they ran, in the benchmarks."""
        reps = {"build": self._build_replay, "after the solve": self._after_replay,
                "correction": self._correction_replay}
        pcg = getattr(self.cg, "replay", None)
        if pcg is not None:
            reps["PCG"] = pcg
        return reps

    def _state_arrays_key(self) -> tuple:
        """What the update, the correction and the guard's launches depend on: the operator's
        graph_key (FEM arrays, launch dimensions, coefficients), the state's and the guard's
        arrays, dt. No node count: these launches run over the FEM's node capacity and read the
        count on the device, so a topology change that keeps the allocations keeps the key."""
        return self.graph_key(), self.x.ptr, self.v.ptr, self._guard.ptr, float(self.dt)

    def copy_state(self, x0: wp.array, v0: wp.array) -> None:
        """x0 = x, v0 = v for the current nodes, launched over the node capacity (x0 and v0 hold
        at least the node count): capturable across node-count changes, unlike a copy of the
        count's elements."""
        f = self.fem
        wp.launch(_copy_state_kernel, f.node_dim, [f.n_nodes_dev, self.x, self.v, x0, v0], device=self.device)

    def energy(self) -> tuple[float, float, float]:
        """(kinetic, gravitational potential, elastic) energy at the current state."""
        self._energy.zero_()
        wp.launch(_energy_kernel, self.fem.n_nodes,
                  [self.x, self.v, self.fem.lumped_mass, wp.vec3d(*self.gravity), self._energy], device=self.device)
        ke, pe = self._energy.numpy()
        return float(ke), float(pe), self.elastic_energy()

    def energy_kinetic(self) -> float:
        """Kinetic energy only (the guard's reduction, one read), for the divergence guard."""
        return float(to_host(self.launch_guard())[0][0])

    def launch_guard(self, out: wp.array | None = None) -> wp.array:
        """Launch the divergence guard's reduction at the current state: a device array
        [kinetic energy, non-finite nodes] (``out``, default the guard's own), returned unread
        (read it with the step's other values)."""
        out = self._guard if out is None else out
        out.zero_()
        f = self.fem
        wp.launch(_guard_kernel, f.node_dim, [f.n_nodes_dev, self.x, self.v, f.lumped_mass, out], device=self.device)
        return out

    @property
    def guard_after(self) -> wp.array:
        """A second guard array, for a reduction launched in the same read as the free motion's
        (a correction launched after the solve, see ``after_solve``)."""
        return self._guard_after

    def correct(self, dx) -> None:
        """x += dx, v += dx / dt (a position correction, e.g. the contact response of eq. 4);
        ``dx`` (n, 3) on the host or a device array."""
        if not isinstance(dx, wp.array):
            dx = wp.array(np.asarray(dx, dtype=np.float64), dtype=wp.vec3d, device=self.device)
        f = self.fem
        wp.launch(_correct_kernel, f.node_dim, [f.n_nodes_dev, dx, float(self.dt), self.x, self.v], device=self.device)

    def elastic_energy(self) -> float:
        """Corotated strain energy sum_e V (mu eps:eps + lambda/2 tr(eps)^2), on the host (diagnostics)."""
        fem = self.fem
        fem.update_rotations(self.x)
        x = self.x.numpy()
        T = fem.mesh.tets
        R = fem.rotations.numpy()
        Dinv = fem.Dm_inv.numpy()
        Ds = np.stack([x[T[:, 1]] - x[T[:, 0]], x[T[:, 2]] - x[T[:, 0]], x[T[:, 3]] - x[T[:, 0]]], axis=2)
        F = Ds @ Dinv
        G = np.einsum("eji,ejk->eik", R, F) - np.eye(3)
        eps = 0.5 * (G + np.transpose(G, (0, 2, 1)))
        tr = np.trace(eps, axis1=1, axis2=2)
        mu, lam, vol = fem.mu.numpy(), fem.lam.numpy(), fem.volume.numpy()
        w = mu * np.einsum("eij,eij->e", eps, eps) + 0.5 * lam * tr * tr
        return float(np.sum(w * vol))
