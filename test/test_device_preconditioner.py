"""The device factor backends (dense inverse, cuDSS) behind the preconditioner interface, the
device-scalar / graph PCG (cg.DevicePCG) and the options that select them.

Runs on Warp's CPU backend by default (the dense backend with NumPy and SciPy's LAPACK);
``STS_TEST_DEVICE=cuda:0`` runs the same tests on a GPU (cuSOLVER, cuBLAS, cuDSS).
"""

import os
import time

import numpy as np
import pytest
import scipy.sparse as sps
import scipy.sparse.linalg as spla
import warp as wp

from soft_tissue_sim import load_scene
from soft_tissue_sim.cg import PCG, DevicePCG
from soft_tissue_sim.device_preconditioner import AsyncDevicePreconditioner, constraint_rows
from test_dense_capacity import lower_symmetric
from soft_tissue_sim.material import ParameterError
from soft_tissue_sim.preconditioner import choose_backend
from soft_tissue_sim.scene import read_scene, resolve_path

DEVICE = os.environ.get("STS_TEST_DEVICE", "cpu")
CUDA = DEVICE.startswith("cuda")
if CUDA and wp.get_cuda_device_count() == 0:
    # a GPU run asked for where there is no GPU is a mistake, not a run to report as passed
    raise RuntimeError(f"STS_TEST_DEVICE={DEVICE} but Warp sees no CUDA device")
BACKENDS = ["dense", "cudss"] if CUDA else ["dense"]


def _brain_without_instruments():
    cfg, base = read_scene("brain_resection.yaml")
    for k in ("instruments", "contact", "cutting"):
        cfg.pop(k, None)
    cfg["mesh"] = {"file": str(resolve_path(cfg["mesh"]["file"], base))}
    return cfg


def _layered_beam():
    """A beam of three materials (stiffness ratio 100), so the factor sees very different scales."""
    return {
        "mesh": {"generator": "beam", "n_long": 14, "n_cross": 3, "spacing": 0.01,
                 "regions": [{"box": {"min": [0.04, -1, -1], "max": [0.09, 1, 1]}, "material": 1},
                             {"box": {"min": [0.09, -1, -1], "max": [1, 1, 1]}, "material": 2}]},
        "materials": [{"id": 0, "young": 5e4, "poisson": 0.3, "density": 1000.0},
                      {"id": 1, "young": 5e6, "poisson": 0.45, "density": 1100.0},
                      {"id": 2, "young": 2e4, "poisson": 0.2, "density": 900.0}],
        "damping": {"mass": 0.2, "stiffness": 0.005},
        "fixed": {"axis": "x", "below": 0.0},
        "time": {"dt": 0.01},
    }


def _scene(name):
    return {"brain": _brain_without_instruments, "layered": _layered_beam}.get(name, lambda: name)()


def _solver(pre="async_ldlt", backend="dense", graph=False, tol=1e-10, **ldlt):
    s = {"preconditioner": pre, "tolerance": tol, "max_iterations": 3000, "graph": graph}
    if pre in ("async_ldlt", "direct"):
        s["ldlt"] = {"backend": backend, "deterministic": True, **ldlt}
    return s


def _apply(pre, r, device):
    z = wp.zeros(len(r), dtype=wp.vec3d, device=device)
    pre.apply(wp.array(r, dtype=wp.vec3d, device=device), z)
    return z.numpy().reshape(-1)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("scene", ["test_small.yaml", "layered", "brain"])
def test_device_factor_solves_like_a_direct_solve(scene, backend):
    """At the state the factor was made (dR = I), P^-1 r = A^-1 r to 1e-10 (SuperLU here as an
    independent direct solve), the dense inverse applied in double precision."""
    ov = {"solver": _solver(backend=backend, apply_precision="float64")}
    with load_scene(_scene(scene), device=DEVICE, overrides=ov) as sim:
        integ = sim.integrator
        sim.step()
        integ.build()
        pre = sim.preconditioner
        assert isinstance(pre, AsyncDevicePreconditioner) and pre.backend.name == backend
        pre.refresh(integ)
        pre.begin_step(integ)
        assert np.abs(pre.dR.numpy() - np.eye(3)).max() < 1e-12
        A = sim.fem.assemble_scipy(integ.m_coef, integ.k_coef).tocsc()
        lu = spla.splu(A)
        rng = np.random.default_rng(3)
        for _ in range(3):
            r = rng.standard_normal((sim.mesh.n_nodes, 3))
            ref = lu.solve(r.reshape(-1))
            z = _apply(pre, r, DEVICE)
            assert np.linalg.norm(z - ref) <= 1e-10 * np.linalg.norm(ref)


@pytest.mark.parametrize("backend", BACKENDS)
def test_rotated_device_apply_equals_the_host_apply(backend):
    """A stale factor rotated by eq. (2): the device backend and CHOLMOD's host preconditioner,
    run on the same deterministic schedule, give the same P^-1 r."""
    sims = {}
    for b in (backend, "cholmod"):
        dev = DEVICE if b != "cholmod" else "cpu"
        sims[b] = load_scene("beam_2000.yaml" if CUDA else _layered_beam(), device=dev,
                             overrides={"solver": _solver(backend=b, refresh_every=1000, apply_precision="float64")})
    try:
        for s in sims.values():
            for _ in range(12):  # swinging down: the factor of step 0 is stale and rotated
                s.step()
            s.integrator.build()
            s.preconditioner.begin_step(s.integrator)
        dev_pre, host_pre = sims[backend].preconditioner, sims["cholmod"].preconditioner
        assert np.abs(dev_pre.dR.numpy() - np.eye(3)).max() > 1e-3  # the rotation matters here
        rng = np.random.default_rng(4)
        n = sims[backend].mesh.n_nodes
        for _ in range(3):
            r = rng.standard_normal((n, 3))
            z = _apply(dev_pre, r, DEVICE)
            ref = np.empty(r.size)
            host_pre.inner.apply(r.reshape(-1), ref)
            assert np.linalg.norm(z - ref) <= 1e-8 * np.linalg.norm(ref)
            plain = host_pre.inner.factor(r.reshape(-1))  # unrotated: another vector
            assert np.linalg.norm(plain - ref) > 1e-6 * np.linalg.norm(ref)
    finally:
        for s in sims.values():
            s.close()


@pytest.mark.parametrize("graph", [False, True])
@pytest.mark.parametrize("pre", ["dense", "jacobi", "none"])
def test_device_scalar_pcg_matches_host_pcg(pre, graph):
    kind = "async_ldlt" if pre == "dense" else pre
    ov = {"solver": _solver(pre=kind, graph=graph, tol=1e-8, refresh_every=1000)}
    with load_scene(_layered_beam(), device=DEVICE, overrides=ov) as sim:
        for _ in range(8):
            sim.step()
        integ = sim.integrator
        n = sim.mesh.n_nodes
        host = PCG(n, DEVICE, integ.cg.tolerance, integ.cg.max_iterations)
        dpcg = DevicePCG(n, DEVICE, integ.cg.tolerance, integ.cg.max_iterations, graph=graph)
        x_h = wp.zeros(n, dtype=wp.vec3d, device=DEVICE)
        x_d = wp.full(n, wp.vec3d(1.0, 2.0, 3.0), dtype=wp.vec3d, device=DEVICE)  # the solve starts from 0
        for _ in range(3):  # third solve: a graph replay (captured at the second) with a new right-hand side
            integ.build()
            integ.preconditioner.begin_step(integ)
            rh = host.solve(integ.matvec, integ.b, x_h, integ.preconditioner)
            rd = dpcg.solve(integ.matvec, integ.b, x_d, integ.preconditioner)
            assert rh.iterations > 1 and rh.converged
            # plain CG and Jacobi take hundreds of iterations: on a GPU the dot products, summed in
            # another order, shift the count by a few percent
            slack = 0 if pre == "dense" else max(1, int(0.05 * rh.iterations)) if CUDA else 1
            assert abs(rd.iterations - rh.iterations) <= slack and rd.converged
            assert rd.residual <= dpcg.tolerance
            assert np.abs(x_d.numpy() - x_h.numpy()).max() <= 1e-6 * np.abs(x_h.numpy()).max()
            integ.step_index += 1
            wp.copy(integ.x, wp.array(integ.x.numpy() + 0.002 * x_h.numpy(), dtype=wp.vec3d, device=DEVICE))
        assert (dpcg.captures, dpcg.replays) == ((1, 2) if graph else (0, 0))


def test_a_failed_capture_runs_uncaptured_and_is_tried_again(monkeypatch):
    """A capture that fails (as one invalidated by another thread's work would) leaves that
    solve correct and uncaptured; the next solves capture again; three failures in a row
    give graphs up."""
    import soft_tissue_sim.cg as cgm

    ov = {"solver": _solver(pre="jacobi", graph=True, tol=1e-8)}
    with load_scene(_layered_beam(), device=DEVICE, overrides=ov) as sim:
        integ = sim.integrator
        n = sim.mesh.n_nodes
        integ.build()
        integ.preconditioner.begin_step(integ)
        ref = PCG(n, DEVICE, 1e-8, integ.cg.max_iterations)
        x_ref = wp.zeros(n, dtype=wp.vec3d, device=DEVICE)
        ref.solve(integ.matvec, integ.b, x_ref, integ.preconditioner)
        real = wp.ScopedCapture
        fails = {"left": 1}

        class Flaky(real):
            def __enter__(self):
                if fails["left"] > 0:
                    fails["left"] -= 1
                    raise RuntimeError("capture invalidated")
                return super().__enter__()

        monkeypatch.setattr(cgm.wp, "ScopedCapture", Flaky)
        dpcg = DevicePCG(n, DEVICE, 1e-8, integ.cg.max_iterations, graph=True)
        x = wp.zeros(n, dtype=wp.vec3d, device=DEVICE)
        for k in range(5):  # seen, capture fails (uncaptured), seen, captured, replayed
            r = dpcg.solve(integ.matvec, integ.b, x, integ.preconditioner)
            assert r.converged and np.abs(x.numpy() - x_ref.numpy()).max() <= 1e-6 * np.abs(x_ref.numpy()).max()
        assert dpcg.graph and dpcg.capture_failures == 0 and (dpcg.captures, dpcg.replays) == (1, 2)
        fails["left"] = 10
        dpcg2 = DevicePCG(n, DEVICE, 1e-8, integ.cg.max_iterations, graph=True)
        with pytest.warns(RuntimeWarning, match="3 times in a row"):
            for k in range(7):
                assert dpcg2.solve(integ.matvec, integ.b, x, integ.preconditioner).converged
        assert not dpcg2.graph and dpcg2.captures == 0


def test_device_pcg_zero_and_nonfinite_right_hand_sides():
    with load_scene(_layered_beam(), device=DEVICE, overrides={"solver": _solver(pre="jacobi")}) as sim:
        integ = sim.integrator
        integ.build()
        integ.preconditioner.begin_step(integ)
        n = sim.mesh.n_nodes
        dpcg = DevicePCG(n, DEVICE, 1e-8, 100)
        x = wp.zeros(n, dtype=wp.vec3d, device=DEVICE)
        b = wp.zeros(n, dtype=wp.vec3d, device=DEVICE)
        res = dpcg.solve(integ.matvec, b, x, integ.preconditioner)
        assert res.iterations == 0 and res.converged and res.residual == 0.0 and np.all(x.numpy() == 0)
        bn = np.zeros((n, 3))
        bn[3, 1] = np.nan
        res = dpcg.solve(integ.matvec, wp.array(bn, dtype=wp.vec3d, device=DEVICE), x, integ.preconditioner)
        assert not res.converged and np.isnan(res.residual)
        dpcg = DevicePCG(n, DEVICE, 1e-14, 3)  # max_iterations reached
        res = dpcg.solve(integ.matvec, integ.b, x, integ.preconditioner)
        assert res.iterations == 3 and not res.converged


@pytest.mark.parametrize("precision", ["float64", "float32"])
@pytest.mark.parametrize("graph", [False, True])
def test_simulation_with_the_dense_backend_follows_the_cholmod_trajectory(graph, precision):
    """The same steps as CHOLMOD's preconditioner on the same schedule: the same iterations
    with the inverse applied in double precision; in single precision a solve that ends at
    its tolerance may take one iteration more or less, the positions the same to 1e-8."""
    runs = {}
    for backend in ("cholmod", "dense"):
        ov = {"solver": _solver(backend=backend, graph=graph and backend == "dense", refresh_every=4,
                                apply_precision=precision)}
        with load_scene("test_small.yaml", device=DEVICE if backend == "dense" else "cpu", overrides=ov) as sim:
            its = [sim.step().iterations for _ in range(20)]
            runs[backend] = (sim.positions(), its, sim.preconditioner.stats(), sim.integrator.cg)
    (xh, ih, sh, _), (xd, idv, sd, cg) = runs["cholmod"], runs["dense"]
    assert sd["backend"] == "dense" and sh["backend"] == "cholmod"
    assert max(ih) > 3  # stale factors between refreshes: several iterations
    if precision == "float64":
        assert idv == ih
    else:
        assert max(abs(a - b) for a, b in zip(idv, ih)) <= 1
    assert np.abs(xd - xh).max() <= 1e-8
    with load_scene("test_small.yaml", device=DEVICE) as rest:
        assert np.abs(xh - rest.positions()).max() > 1e-3  # it moved
    if graph and CUDA:
        assert cg.captures >= 1 and cg.replays >= 15


def test_asynchronous_schedule_installs_each_factor_after_its_request():
    """Without ``deterministic``: a factor requested at step s is installed when it has ended
    (on the CPU at once, so at s + 1; on a GPU when its event says so), and the factor in use is
    never older than its own latency plus the refresh interval."""
    ov = {"solver": {"preconditioner": "async_ldlt", "tolerance": 1e-8,
                     "ldlt": {"backend": "dense", "refresh_every": 3}}}
    with load_scene("test_small.yaml", device=DEVICE, overrides=ov) as sim:
        ages, lat = [], []
        for _ in range(30):
            st = sim.step()
            assert st.converged
            ps = sim.preconditioner.stats()
            ages.append(ps["factor_age"])
            lat.append(ps["factor_latency_steps"])
        assert ps["factor_count"] >= 5 and ps["worker"] == ("device stream" if CUDA else "synchronous")
        assert ps["factorization_ms"] > 0.0
        if not CUDA:
            assert max(lat) == 1 and max(ages) <= 3
        assert max(ages) <= max(lat) + 3
        assert ps["refresh_interval"] >= 3


def test_the_factors_rotations_reach_the_host_as_they_were_requested():
    """R(t_u), which the folds read on the host, is the rotation the factor in use was made
    with: on a GPU from the page-locked copy its request enqueued (no read of the device array
    that would wait for the steps queued since), on the CPU the array itself."""
    ov = {"solver": {"preconditioner": "async_ldlt", "tolerance": 1e-8,
                     "ldlt": {"backend": "dense", "refresh_every": 2, "rotate": True, "deterministic": False}}}
    with load_scene("test_small.yaml", device=DEVICE, overrides=ov) as sim:
        pre = sim.preconditioner
        for _ in range(12):
            sim.step()
        assert pre.factor_count >= 3 and pre.factor_step > 0
        assert (pre._R_ref_copy is not None) == CUDA
        made_with = pre._R_ref_src.numpy().astype(np.float64)
        assert np.abs(made_with - np.eye(3)).max() > 1e-4  # the bent cantilever's nodes have turned
        assert np.array_equal(pre.R_ref_host, made_with)


@pytest.mark.skipif(not CUDA, reason="CuPy's kernels are the GPU fold's (NumPy on the CPU)")
def test_the_first_cut_on_a_gpu_compiles_no_cupy_kernel():
    """A cut's correction calls cuBLAS and cuSOLVER on kept buffers (:class:`LibraryFold`), so the
    first cut of a process makes no CuPy kernel (which took a few hundred milliseconds on a
    machine without CuPy's cache, when the fold was CuPy's). In a process of its own: this one
    may have made them already."""
    import subprocess
    import sys

    here = os.path.dirname(os.path.abspath(__file__))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([here, os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, os.path.join(here, "fold_probe.py"), DEVICE], env=env,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    line = [ln for ln in out.stdout.splitlines() if ln.startswith("changed")][-1]
    changed, folds, compiled = (int(w) for w in line.split()[1::2])
    assert changed == 1 and folds >= 1
    assert compiled == 0


def test_device_refresh_every_sets_the_interval_of_the_device_backends_only():
    """``device_refresh_every`` replaces ``refresh_every`` for a device factor (dense here) and
    leaves CHOLMOD's; a bad value is refused."""
    ldlt = {"backend": "dense", "refresh_every": 2, "device_refresh_every": 5, "deterministic": True}
    with load_scene("test_small.yaml", device=DEVICE,
                    overrides={"solver": {"preconditioner": "async_ldlt", "ldlt": ldlt}}) as sim:
        for _ in range(16):
            sim.step()
        assert sim.preconditioner.refresh_every == 5 and np.all(np.diff(sim.preconditioner.swaps) == 5)
    if not CUDA:
        with load_scene("test_small.yaml", overrides={"solver": {"preconditioner": "async_ldlt",
                                                                 "ldlt": {**ldlt, "backend": "cholmod"}}}) as sim:
            assert sim.preconditioner.inner.refresh_every == 2
    for bad in (0, 2.5, True):
        with pytest.raises(ParameterError, match="device_refresh_every"):
            load_scene("test_small.yaml", device=DEVICE, overrides={"solver": {
                "preconditioner": "async_ldlt", "ldlt": {**ldlt, "device_refresh_every": bad}}})


def test_device_refresh_iterations_requests_a_factor_only_after_a_step_that_needed_more():
    """``device_refresh_iterations``: a factor is requested every ``device_refresh_every`` steps
    only after a step whose PCG took more iterations than the threshold (the small scene's
    steps take 1 to 8). Made in the step that asks (deterministic): each factor after the first
    follows a step above the threshold, and every step due by both rules gets one; with a
    threshold above every step no factor follows the first; 0 is the interval alone. A bad
    value is refused."""
    ldlt = {"backend": "dense", "device_refresh_every": 2, "deterministic": True}
    runs = {}
    for its in (0, 4, 1000):
        with load_scene("test_small.yaml", device=DEVICE, overrides={"solver": {
                "preconditioner": "async_ldlt", "ldlt": {**ldlt, "device_refresh_iterations": its}}}) as sim:
            steps = [sim.step() for _ in range(16)]
            runs[its] = ([s.iterations for s in steps], list(sim.preconditioner.swaps))
    assert runs[0][1] == list(range(0, 16, 2))
    n, swaps = runs[4]
    assert swaps[0] == 0 and all(n[k - 1] > 4 for k in swaps[1:])
    due = [k for k in range(1, 16) if n[k - 1] > 4 and k - max(s for s in swaps if s < k) >= 2]
    assert due and set(due) <= set(swaps)
    assert len(swaps) < len(runs[0][1])
    assert runs[1000][1] == [0] and max(runs[1000][0]) > max(runs[4][0])  # the factor ages, the steps need more
    with pytest.raises(ParameterError, match="device_refresh_iterations"):
        load_scene("test_small.yaml", device=DEVICE, overrides={"solver": {
            "preconditioner": "async_ldlt", "ldlt": {**ldlt, "device_refresh_iterations": -1}}})


def test_the_refresh_waits_for_a_step_above_the_iteration_threshold():
    """The policy alone (:meth:`AsyncDevicePreconditioner._due`): the interval first, then the
    last step's iterations against the threshold; none known yet: due."""
    from types import SimpleNamespace

    from soft_tissue_sim.device_preconditioner import AsyncDevicePreconditioner

    pre = AsyncDevicePreconditioner.__new__(AsyncDevicePreconditioner)
    pre.refresh_every, pre.refresh_iterations, pre.last_request_step, pre.step = 3, 4, 10, 12
    assert not pre._due(SimpleNamespace(last_iterations=9))  # within the interval
    pre.step = 13
    assert pre._due(SimpleNamespace(last_iterations=5)) and pre._due(SimpleNamespace(last_iterations=None))
    assert not pre._due(SimpleNamespace(last_iterations=4))
    pre.refresh_iterations = 0
    assert pre._due(SimpleNamespace(last_iterations=1))


def test_lag_installs_each_factor_lag_steps_later_on_the_device():
    ov = {"solver": _solver(backend="dense", refresh_every=2, lag=3, tol=1e-8)}
    with load_scene("test_small.yaml", device=DEVICE, overrides=ov) as sim:
        for _ in range(16):
            sim.step()
        pre = sim.preconditioner
        assert np.all(np.diff(pre.swaps[1:]) == 3) and pre.stats()["factor_latency_steps"] == 3
    with pytest.raises(ParameterError, match="deterministic"):
        load_scene("test_small.yaml", device=DEVICE,
                   overrides={"solver": {"preconditioner": "async_ldlt", "ldlt": {"backend": "dense", "lag": 2, "deterministic": False}}})


def test_a_matrix_that_is_not_positive_definite_is_refused_and_the_factor_kept():
    with load_scene("test_small.yaml", device=DEVICE, overrides={"solver": _solver(refresh_every=1000)}) as sim:
        sim.step()
        pre = sim.preconditioner
        rng = np.random.default_rng(7)
        r = rng.standard_normal((sim.mesh.n_nodes, 3))
        before = _apply(pre, r, DEVICE)
        n = sim.mesh.n_nodes
        neg = wp.array(np.tile(-np.eye(3), (n, 1, 1)), dtype=wp.mat33d, device=DEVICE)
        idx = wp.array(np.arange(n, dtype=np.int32), dtype=wp.int32, device=DEVICE)
        pre.backend.assemble((idx, idx, neg), 3 * n)
        pre.backend.factorize(stream=pre._side)
        wp.synchronize_device(DEVICE)
        err = pre.backend.install()
        assert err is not None and "positive definite" in err
        assert np.array_equal(_apply(pre, r, DEVICE), before)


def test_close_returns_at_once_with_a_factorization_in_flight():
    cfg = _brain_without_instruments()
    ov = {"solver": {"preconditioner": "async_ldlt", "ldlt": {"backend": "dense", "refresh_every": 1}}}
    sim = load_scene(cfg, device=DEVICE, overrides=ov)
    sim.step()
    sim.step()  # a request in flight (on the CPU: made, waiting to be installed)
    t0 = time.perf_counter()
    sim.close()
    assert time.perf_counter() - t0 < 1.0
    with pytest.raises(RuntimeError, match="closed"):
        sim.step()


def test_close_does_not_wait_for_an_enqueue_that_blocks():
    """An enqueue still running on the background thread (a library's first call there can
    block for a second): close() returns at once, and the backend is freed on that thread once
    the enqueue is over, not before."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from soft_tissue_sim.device_preconditioner import AsyncDevicePreconditioner, _Ticket

    class Backend:
        def __init__(self):
            self.closed = threading.Event()

        def close(self):
            self.closed.set()

    pre = AsyncDevicePreconditioner(Backend(), lambda: {}, "cpu")
    gate = threading.Event()
    pre._pool = ThreadPoolExecutor(max_workers=1)
    pre._busy = _Ticket(0, 0, None, 0, None, future=pre._pool.submit(lambda: (gate.wait(10.0), (None, None))[1]))
    t0 = time.perf_counter()
    pre.close()
    assert time.perf_counter() - t0 < 0.5
    assert not pre.backend.closed.wait(0.2)  # the enqueue still holds the buffers
    gate.set()
    assert pre.backend.closed.wait(5.0)


def test_invalidate_starts_afresh_and_reset_gives_the_same_trajectory():
    ov = {"solver": _solver(refresh_every=5, tol=1e-9)}
    with load_scene("test_small.yaml", device=DEVICE, overrides=ov) as sim:
        first = [sim.step().iterations for _ in range(8)]
        x1 = sim.positions()
        n_factors = sim.preconditioner.factor_count
        sim.reset()
        assert sim.preconditioner.factor_count == 0  # invalidated
        again = [sim.step().iterations for _ in range(8)]
        assert again == first and np.abs(sim.positions() - x1).max() <= 1e-12
        assert n_factors >= 2


def test_constraint_rows_in_node_form_rebuild_the_columns():
    rng = np.random.default_rng(9)
    n, m = 20, 13
    B = np.zeros((3 * n, m))
    for c in range(m):
        nodes = rng.choice(n, rng.integers(1, 5), replace=False)
        for j in nodes:
            B[3 * j:3 * j + 3, c] = rng.standard_normal(3)
    nodes, coef = constraint_rows(sps.csc_matrix(B), n)
    R = np.zeros_like(B)
    for a in range(m):
        for k in range(4):
            if nodes[a, k] >= 0:
                R[3 * nodes[a, k]:3 * nodes[a, k] + 3, a] += coef[a, k]
    np.testing.assert_array_equal(R, B)
    nodes2, coef2 = constraint_rows(B, n)  # dense in, same result
    np.testing.assert_array_equal(nodes2, nodes)
    with pytest.raises(ValueError, match="DOFs"):
        constraint_rows(B[:-3], n)


def test_backend_options():
    base = {"preconditioner": "async_ldlt"}
    with load_scene("test_small.yaml", device="cpu", overrides={"solver": base}) as sim:
        assert sim.preconditioner.stats()["backend"] == "cholmod"  # auto on the CPU
    assert choose_backend("auto", "cpu", 10**6, True, True, 12000) == "cholmod"
    with pytest.raises(ParameterError, match="CUDA"):
        choose_backend("cudss", "cpu", 300, False, False, 12000)
    with pytest.raises(ParameterError, match="backend must be one of"):
        load_scene("test_small.yaml", device="cpu", overrides={"solver": {**base, "ldlt": {"backend": "magma"}}})
    with pytest.raises(ParameterError, match="retired"):
        load_scene("test_small.yaml", device="cpu", overrides={"solver": {**base, "ldlt": {"apply_on": "device"}}})
    with pytest.raises(ParameterError, match="unknown ldlt options"):
        load_scene("test_small.yaml", device="cpu", overrides={"solver": {**base, "ldlt": {"refresh": 2}}})
    with pytest.raises(ParameterError, match="dense_max_dofs"):
        load_scene("test_small.yaml", device="cpu",
                   overrides={"solver": {**base, "ldlt": {"dense_max_dofs": -1}}})
    with pytest.raises(ParameterError, match="apply_precision"):
        load_scene("test_small.yaml", device="cpu",
                   overrides={"solver": {**base, "ldlt": {"backend": "dense", "apply_precision": "float16"}}})
    if CUDA:
        assert choose_backend("auto", DEVICE, 5202, True, True, 12000) == "dense"
        assert choose_backend("auto", DEVICE, 300_000, False, False, 12000) == "cudss"
        assert choose_backend("auto", DEVICE, 300_000, True, False, 12000) == "cholmod"
        with pytest.raises(ParameterError, match="neither contact nor cutting"):
            choose_backend("cudss", DEVICE, 300, True, False, 12000)


def test_reserve_sms_confines_the_factorization_and_changes_no_result():
    """``ldlt.reserve_sms``: checked; on a GPU the factor's stream is a green context's that
    leaves at least that many SMs free, with the same trajectory as an unconfined factor; a
    factorization that fails on it falls back to a plain stream. On the CPU: no partition."""
    for bad in (-1, 2.5, True, "many"):
        with pytest.raises(ParameterError, match="reserve_sms"):
            load_scene("test_small.yaml", device=DEVICE, overrides={"solver": _solver(reserve_sms=bad)})
    runs = {}
    for reserve in (0, 16):
        with load_scene("test_small.yaml", device=DEVICE, overrides={"solver": _solver(refresh_every=2, tol=1e-10,
                                                                                       reserve_sms=reserve)}) as sim:
            for _ in range(8):
                assert sim.step().converged
            pre = sim.preconditioner
            runs[reserve] = sim.positions()
            if reserve and CUDA and pre.partition is not None:
                assert pre.partition.reserved >= reserve and pre.stats()["factor_sms"] == pre.partition.sms
                assert pre.stats()["factor_count"] >= 4
            elif reserve and CUDA:  # the driver cannot partition: said why
                assert pre.partition_error
            else:
                assert pre.partition is None and pre.stats()["factor_sms"] is None
    np.testing.assert_allclose(runs[16], runs[0], rtol=0, atol=1e-9)
    if CUDA:  # a library that refuses the partitioned stream: the next factorizations use a plain one
        ov = {"solver": {"preconditioner": "async_ldlt", "ldlt": {"backend": "dense", "refresh_every": 1,
                                                                   "reserve_sms": 16}}}
        with load_scene("test_small.yaml", device=DEVICE, overrides=ov) as sim:
            sim.step()
            pre = sim.preconditioner
            if pre.partition is not None:
                real = pre.backend.factorize
                part = pre.partition.stream

                def refuse(stream=None):
                    if stream is part:
                        raise RuntimeError("refused")
                    real(stream=stream)

                pre.backend.factorize = refuse
                with pytest.warns(RuntimeWarning, match="plain stream"):
                    assert not pre._install(pre._request(sim.integrator, background=True))
                assert pre.partition is None and pre.failures == 1 and "refused" in pre.worker_error
                count = pre.factor_count
                for _ in range(6):
                    assert sim.step().converged
                assert pre.factor_count > count


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_dense_inverse_after_chained_cuts_equals_a_fresh_factorization(precision):
    """The inverse folded after two cuts and an element removal (rank-3k updates, node numbering
    changes) is the inverse of the modified matrix: applied in double precision to 1e-8, in
    single precision to 1e-5, its copy remade after each fold and regrow of eq. (5)-(10)."""
    from test_cutting import beam_scene, corrected_vs_fresh, crosswise, lengthwise

    tol = 1e-8 if precision == "float64" else 1e-5
    cfg = beam_scene(rotate=False, backend="dense")
    cfg["device"] = DEVICE
    cfg["solver"]["ldlt"]["apply_precision"] = precision
    rng = np.random.default_rng(0)
    with load_scene(cfg) as sim:
        for _ in range(3):
            sim.step()
        sim.fem.update_rotations(sim.integrator.x)
        sim.preconditioner.refresh(sim.integrator)
        assert corrected_vs_fresh(sim, rng) < 1e-2 * tol
        assert lengthwise(sim, 0.035, 0.08).changed
        assert corrected_vs_fresh(sim, rng) < tol
        assert crosswise(sim, 0.055).changed
        assert corrected_vs_fresh(sim, rng) < tol
        assert sim.remove_elements(sim.positions()[-1], 0.012).changed
        assert corrected_vs_fresh(sim, rng) < tol
        P = sim.preconditioner.backend
        assert sim.preconditioner.correction.folds >= 3
        if precision == "float32":
            assert np.array_equal(P.single(), lower_symmetric(P.inv.numpy()).astype(np.float32))


def test_an_install_folds_the_modifications_since_its_request_at_once():
    """A factor requested before two cuts and an element removal and installed after them gets
    the three modifications in one fold, on the union of their DOFs, and is then the inverse of
    the modified matrix (as a fresh factorization of it is). Unrotated, as in
    test_cutting: the nodal rotations a cut changes are not part of the correction."""
    from test_cutting import corrected_vs_fresh, crosswise, fresh_bound, lengthwise, unrotated_dense_beam

    rng = np.random.default_rng(0)
    with load_scene(unrotated_dense_beam(DEVICE)) as sim:
        for _ in range(3):
            sim.step()
        pre = sim.preconditioner
        sim.fem.update_rotations(sim.integrator.x)
        ticket = pre._request(sim.integrator)  # made from the mesh before the changes
        assert lengthwise(sim, 0.035, 0.08).changed
        assert crosswise(sim, 0.055).changed
        assert sim.remove_elements(sim.positions()[-1], 0.012).changed
        mods = list(pre.mods)
        assert len(mods) == 3 and all(m.version > ticket.version for m in mods)
        if ticket.events()[1] is not None:
            wp.synchronize_event(ticket.done)
        folds, fold = [], pre.backend.fold

        def counted(rows, N):
            folds.append(len(rows))
            fold(rows, N)

        pre.backend.fold = counted
        try:
            assert pre._install(ticket)
        finally:
            del pre.backend.fold
        union = np.unique(np.concatenate([m.uids for m in mods]))
        assert folds == [3 * len(union)] and len(union) > max(len(m.uids) for m in mods)
        corrected = corrected_vs_fresh(sim, rng)
        assert corrected < fresh_bound(sim, rng)


@pytest.mark.parametrize("scene", ["layered", "brain"])
def test_single_precision_apply_follows_the_double_precision_inverse(scene):
    """``apply_precision``: auto reads a single-precision copy on a GPU and the inverse itself on
    the CPU; the copy's P^-1 r is the double-precision one to 1e-5 (not to 1e-12: it is
    another matrix), and the copy follows the inverse through installs (same address)."""
    runs = {}
    for precision in ("float64", "float32", "auto"):
        ov = {"solver": _solver(refresh_every=1000, apply_precision=precision)}
        with load_scene(_scene(scene), device=DEVICE, overrides=ov) as sim:
            for _ in range(4):
                sim.step()
            integ, pre = sim.integrator, sim.preconditioner
            integ.build()
            pre.begin_step(integ)
            P = pre.backend
            expect = precision if precision != "auto" else ("float32" if CUDA else "float64")
            assert P.precision == expect
            assert (P.applied is P.packed) == (expect == "float32")
            ptr = P.applied.ptr
            pre.refresh(integ)  # a new factor installed: the copy refreshed in place
            assert P.applied.ptr == ptr
            if expect == "float32":
                assert np.array_equal(P.single(), lower_symmetric(P.inv.numpy()).astype(np.float32))
            pre.begin_step(integ)
            rng = np.random.default_rng(5)
            runs[precision] = [_apply(pre, rng.standard_normal((sim.mesh.n_nodes, 3)), DEVICE) for _ in range(3)]
    for z64, z32 in zip(runs["float64"], runs["float32"]):
        err = np.linalg.norm(z32 - z64) / np.linalg.norm(z64)
        assert 1e-12 < err < 1e-5


@pytest.mark.skipif(not CUDA, reason="the blocked inverse is the GPU's path (LAPACK's potri on the CPU)")
@pytest.mark.parametrize("block", [97, 256])
def test_inverse_by_column_blocks_equals_the_whole_one(block):
    """The GPU's inverse from the Cholesky factor, made by column blocks (a last block shorter
    than the others included), equals the one made whole to rounding, comes out exactly
    symmetric and inverts A."""
    from soft_tissue_sim import dense_inverse as DI

    n = 3 * 211
    rng = np.random.default_rng(11)
    B = rng.standard_normal((n, n))
    A = B @ B.T / n + 0.05 * np.eye(n)
    out = {}
    for b in (0, block):
        D = DI.DenseInverse(DEVICE)
        D.inverse_block = b
        D.work = wp.array(A, dtype=wp.float64, device=DEVICE)
        D._prepare_gpu(n, None)
        D.factorize()
        assert D.install() is None
        out[b] = D.inv.numpy()
        D.close()
    whole, blocked = out[0], out[block]
    assert np.array_equal(blocked, blocked.T)
    assert np.abs(blocked - whole).max() <= 1e-12 * np.abs(whole).max()
    assert np.abs(A @ blocked - np.eye(n)).max() < 1e-10


def test_changes_in_one_scope_make_the_single_precision_copy_once():
    """Inside ``changing()`` an install, a fold and a regrow leave the single-precision copy as
    it was; at the scope's end it is the inverse in use rounded; outside, each change remakes it."""
    from soft_tissue_sim import dense_inverse as DI

    n = 3 * 40
    rng = np.random.default_rng(5)
    B = rng.standard_normal((n, n))
    A = B @ B.T / n + 0.1 * np.eye(n)
    D = DI.DenseInverse(DEVICE, "float32")
    D.work = wp.array(A, dtype=wp.float64, device=DEVICE)
    if D.device.is_cuda:
        D._prepare_gpu(n, None)
    D.factorize()
    assert D.install() is None
    first = D.packed.numpy().copy()
    assert np.array_equal(D.single(), lower_symmetric(D.inv.numpy()).astype(np.float32))
    N = 0.1 * np.eye(3)
    with D.changing():
        D.fold(np.arange(3), N)
        D.regrow(np.arange(n), 3)
        assert D.inv.shape[0] == n + 3
        assert np.array_equal(D.packed.numpy(), first)  # not remade yet
    assert np.array_equal(D.single(), lower_symmetric(D.inv.numpy()).astype(np.float32))
    D.fold(np.arange(3, 6), N)
    assert np.array_equal(D.single(), lower_symmetric(D.inv.numpy()).astype(np.float32))
    D.close()


def test_factors_of_changing_sizes_reuse_the_dense_buffers():
    """The work buffer, the GPU's second buffer and the single-precision copy are views of kept
    allocations: factors of a body that shrinks, then grows within the headroom, allocate
    nothing new, and each is the inverse of its own matrix."""
    from soft_tissue_sim import dense_inverse as DI

    rng = np.random.default_rng(8)
    D = DI.DenseInverse(DEVICE, "float32")
    ptrs = None
    for nodes in (40, 36, 44):
        n3 = 3 * nodes
        B = rng.standard_normal((n3, n3))
        A = B @ B.T / n3 + 0.5 * np.eye(n3)
        idx = np.arange(nodes, dtype=np.int32)
        r, c = np.repeat(idx, nodes), np.tile(idx, nodes)
        blocks = A.reshape(nodes, 3, nodes, 3).transpose(0, 2, 1, 3).reshape(-1, 3, 3)
        trip = (wp.array(r, dtype=wp.int32, device=DEVICE), wp.array(c, dtype=wp.int32, device=DEVICE),
                wp.array(blocks, dtype=wp.mat33d, device=DEVICE))
        D.assemble(trip, n3)
        D.factorize()
        assert D.install() is None
        np.testing.assert_allclose(D.inv.numpy() @ A, np.eye(n3), atol=1e-9)
        assert np.array_equal(D.single(), lower_symmetric(D.inv.numpy()).astype(np.float32))
        now = (D.work.ptr, D.packed.ptr) + ((D._rhs.ptr,) if D.device.is_cuda else ())
        assert ptrs is None or now == ptrs
        ptrs = now
    assert D._work_buf.allocations == D._packed_buf.allocations == 1
    D.close()


def test_on_a_gpu_the_assembly_is_launched_with_the_factorization():
    """``assemble`` writes the work buffer at once on the CPU; on a GPU it leaves the zeroing and
    the scatter to ``factorize`` (on the factorization's stream, none of it on the
    simulation's): the buffer is untouched until then, and the factor is A's inverse."""
    from soft_tissue_sim import dense_inverse as DI

    rng = np.random.default_rng(9)
    nodes = 20
    n3 = 3 * nodes
    B = rng.standard_normal((n3, n3))
    A = B @ B.T / n3 + 0.5 * np.eye(n3)
    idx = np.arange(nodes, dtype=np.int32)
    blocks = A.reshape(nodes, 3, nodes, 3).transpose(0, 2, 1, 3).reshape(-1, 3, 3)
    trip = (wp.array(np.repeat(idx, nodes), dtype=wp.int32, device=DEVICE),
            wp.array(np.tile(idx, nodes), dtype=wp.int32, device=DEVICE),
            wp.array(blocks, dtype=wp.mat33d, device=DEVICE))
    D = DI.DenseInverse(DEVICE)
    D.assemble(trip, n3)
    D.work.fill_(7.0)
    D.assemble(trip, n3)
    if D.device.is_cuda:
        assert np.all(D.work.numpy() == 7.0)
    else:
        np.testing.assert_allclose(D.work.numpy(), A, rtol=0, atol=1e-12)
    stream = wp.Stream(D.device) if D.device.is_cuda else None
    D.factorize(stream=stream)
    if stream is not None:
        wp.synchronize_stream(stream)
    assert D.install() is None
    np.testing.assert_allclose(D.inv.numpy() @ A, np.eye(n3), atol=1e-9)
    D.close()
