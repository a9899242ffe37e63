"""The LDL^T factor applied on the device (ldlt_device), the device-scalar / graph PCG (cg.DevicePCG)
and the scene options that select them.

Runs on Warp's CPU backend by default; ``STS_TEST_DEVICE=cuda:0`` runs the same tests on a GPU
(then with a warp per row group and the single-block tail kernel, the CUDA defaults).
"""

import os

import numpy as np
import pytest
import scipy.sparse as sps
import warp as wp
from sksparse.cholmod import analyze

from soft_tissue_sim import load_scene
from soft_tissue_sim.cg import PCG, DeviceLDLTPreconditioner, DevicePCG, HostPreconditioner
from soft_tissue_sim.ldlt_device import DeviceLDLT, StructureCache, factor_values, host_solve
from soft_tissue_sim.ldlt_preconditioner import AsyncLDLTPreconditioner
from soft_tissue_sim.material import ParameterError
from soft_tissue_sim.scene import read_scene

DEVICE = os.environ.get("STS_TEST_DEVICE", "cpu")
CUDA = DEVICE.startswith("cuda")
if CUDA and wp.get_cuda_device_count() == 0:
    # a GPU run asked for where there is no GPU is a mistake, not a run to report as passed
    raise RuntimeError(f"STS_TEST_DEVICE={DEVICE} but Warp sees no CUDA device")

# (lanes, tail_width) variants: the per-level launches and the merged narrow tail
VARIANTS = [dict(tail_width=0), dict(tail_width=4)] + ([dict(lanes=1, tail_width=0), dict(lanes=32, tail_width=16)]
                                                        if CUDA else [])


def _matrix(scene, overrides=None):
    """The filtered system matrix A of a scene at rest (scipy CSC), and the simulation's node count."""
    ov = {"solver": {"preconditioner": "none"}}
    ov.update(overrides or {})
    with load_scene(scene, device="cpu", overrides=ov) as sim:
        A = sim._snapshot()[0]
    A = sps.csc_matrix(A)
    A.sort_indices()
    return A


def _brain_without_instruments():
    cfg, base = read_scene("brain_resection.yaml")
    for k in ("instruments", "contact", "cutting"):
        cfg.pop(k, None)
    from soft_tissue_sim.paths import resolve_path

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


def _device_solve(values, b, **opts):
    n = len(b) // 3
    dev = DeviceLDLT(DEVICE, **opts)
    dev.set_factor(values)
    r = wp.array(b.reshape(n, 3), dtype=wp.vec3d, device=DEVICE)
    z = wp.zeros_like(r)
    I = wp.array(np.tile(np.eye(3), (n, 1, 1)), dtype=wp.mat33d, device=DEVICE)
    dev.apply(r, z, I)
    return z.numpy().reshape(-1), dev


def _check_levels(s):
    """Every dependency of a row group lies in an earlier level, forward and backward; each group once."""
    ng = s.n_groups
    gid = np.repeat(np.arange(ng), np.diff(s.group_start))
    for order, ptr, indptr, indices in ((s.fwd_order, s.fwd_ptr, s.lo_indptr, s.lo_indices),
                                        (s.bwd_order, s.bwd_ptr, s.up_indptr, s.up_indices)):
        assert np.array_equal(np.sort(order), np.arange(ng))
        lev = np.empty(ng, dtype=np.int64)
        lev[order] = np.repeat(np.arange(len(ptr) - 1), np.diff(ptr))
        rows = np.repeat(np.arange(s.n), np.diff(indptr))
        gr, gc = gid[rows], gid[indices]
        m = gr != gc
        if not np.all(lev[gr[m]] > lev[gc[m]]):
            return False
    return True


@pytest.mark.parametrize("ordering", ["default", "metis"])
@pytest.mark.parametrize("scene", ["test_small.yaml", "layered", "brain"])
def test_device_solve_equals_cholmod(scene, ordering):
    cfg = {"test_small.yaml": "test_small.yaml", "layered": _layered_beam(), "brain": None}[scene]
    A = _matrix(_brain_without_instruments() if scene == "brain" else cfg)
    f = analyze(A, mode="simplicial", ordering_method=ordering)
    f.cholesky_inplace(A)
    rng = np.random.default_rng(0)
    B = rng.standard_normal((A.shape[0], 2))
    refs = [f(B[:, k]) for k in range(2)]
    vals = factor_values(f, StructureCache())
    # the convention f(b) = P^T L^-T D^-1 L^-1 P b, checked in numpy on the same layout
    for k in range(2):
        assert np.linalg.norm(host_solve(vals, B[:, k]) - refs[k]) <= 1e-12 * np.linalg.norm(refs[k])
    variants = VARIANTS if scene != "brain" else VARIANTS[-1:]  # the brain: one variant (CPU time)
    for opts in variants:
        for k in range(2):
            z, dev = _device_solve(vals, B[:, k], **opts)
            err = np.linalg.norm(z - refs[k]) / np.linalg.norm(refs[k])
            assert err <= 1e-10, (opts, err)
    assert _check_levels(vals.structure)


@pytest.mark.parametrize("scene", ["test_small.yaml", "layered"])
def test_block_solve_of_many_columns_equals_cholmod(scene):
    """solve_columns (every level one launch for all columns; chunked, zero-padded widths)
    gives CHOLMOD's A^-1 B column by column, for widths below, at and across a chunk."""
    A = _matrix({"test_small.yaml": "test_small.yaml", "layered": _layered_beam()}[scene])
    f = analyze(A, mode="simplicial", ordering_method="metis")
    f.cholesky_inplace(A)
    vals = factor_values(f, StructureCache())
    rng = np.random.default_rng(1)
    widths = [1, 3, 8, 13]
    for lanes in ([4, 8, 32] if CUDA else [1]):  # threads per (group, column) pair
        dev = DeviceLDLT(DEVICE, cols_lanes=lanes)
        dev.set_factor(vals)
        dev.COLUMN_WIDTHS = (4, 8)  # force chunking with small buffers (13 columns: 8 + 5)
        for c in widths:
            B = rng.standard_normal((A.shape[0], c))
            X = dev.solve_columns(B)
            ref = f(B)
            assert X.shape == B.shape
            assert np.linalg.norm(X - ref) <= 1e-10 * np.linalg.norm(ref), (lanes, c)
            assert np.linalg.norm(A @ X - B) <= 1e-8 * np.linalg.norm(B), (lanes, c)
    # a single vector comes back as a vector; a block of the wrong height is refused
    b = rng.standard_normal(A.shape[0])
    assert np.allclose(dev.solve_columns(b), f(b), rtol=0, atol=1e-10 * np.abs(f(b)).max())
    with pytest.raises(ValueError):
        dev.solve_columns(np.ones((A.shape[0] + 3, 2)))
    assert dev.column_solves == 1 + 1 + 1 + 2 + 1


def test_block_solve_follows_factors_of_other_patterns_and_sizes():
    """After a cut every factor has a new pattern: the block buffers are kept while big enough
    and the launches recorded again; a bigger factor gets new buffers."""
    mats = [_matrix("test_small.yaml"), _matrix(_layered_beam())]
    facs = []
    for A in mats:
        f = analyze(A, mode="simplicial", ordering_method="metis")
        f.cholesky_inplace(A)
        facs.append((A, f, factor_values(f, StructureCache())))
    assert mats[0].shape[0] < mats[1].shape[0]
    dev = DeviceLDLT(DEVICE)
    rng = np.random.default_rng(2)
    for k in (0, 1, 0, 1):
        A, f, vals = facs[k]
        dev.set_factor(vals)
        B = rng.standard_normal((A.shape[0], 7))
        ref = f(B)
        assert np.linalg.norm(dev.solve_columns(B) - ref) <= 1e-10 * np.linalg.norm(ref), k
    assert dev._col_bufs[8]["rows"] >= mats[1].shape[0]


def test_metis_gives_fewer_levels_than_amd_and_groups_are_nodes():
    A = _matrix("test_small.yaml")
    lv = {}
    for ordering in ("amd", "metis"):
        f = analyze(A, mode="simplicial", ordering_method=ordering)
        f.cholesky_inplace(A)
        s = factor_values(f).structure
        lv[ordering] = s.fwd_levels
        nodes = s.perm // 3
        for g in range(s.n_groups):  # a group: consecutive permuted rows of one node
            assert len(set(nodes[s.group_start[g]:s.group_start[g + 1]])) == 1
        assert s.fwd_levels < s.scalar_levels  # a node's rows cost one level, not three
    assert lv["metis"] < lv["amd"], lv


def test_level_check_detects_a_wrong_schedule():
    A = _matrix("test_small.yaml")
    f = analyze(A, mode="simplicial", ordering_method="metis")
    f.cholesky_inplace(A)
    s = factor_values(f).structure
    assert _check_levels(s)
    bad = factor_values(f).structure  # cached: the same object; corrupt a copy
    import copy

    bad = copy.deepcopy(s)
    bad.fwd_order = bad.fwd_order[::-1].copy()  # every level permuted: dependencies now come later
    assert not _check_levels(bad)


def test_supernodal_factor_is_converted_and_applied_on_the_device():
    A = _matrix(_layered_beam())
    fs = analyze(A, mode="supernodal", ordering_method="metis")
    fs.cholesky_inplace(A)
    b = np.random.default_rng(3).standard_normal(A.shape[0])
    ref = fs(b)
    vals = factor_values(fs, supernodal=True)
    assert vals.converted
    z, _ = _device_solve(vals, b)
    assert np.linalg.norm(z - ref) <= 1e-10 * np.linalg.norm(ref)
    assert np.linalg.norm(fs(b) - ref) <= 1e-12 * np.linalg.norm(ref)  # the host factor still works


def _swinging_sim(apply_on="device", graph=False, refresh_every=1000, tol=1e-10, ordering="metis", pre="async_ldlt",
                  extra=None):
    cfg = {
        "device": DEVICE,
        "mesh": {"generator": "beam", "n_long": 16, "n_cross": 3, "spacing": 0.01},
        "materials": [{"id": 0, "young": 5e4, "poisson": 0.3, "density": 1000.0}],
        "damping": {"mass": 0.2, "stiffness": 0.005},
        "fixed": {"axis": "x", "below": 0.0},
        "time": {"dt": 0.01},
        "solver": {"preconditioner": pre, "tolerance": tol, "max_iterations": 2000, "graph": graph,
                   "ldlt": {"deterministic": True, "refresh_every": refresh_every, "apply_on": apply_on,
                            "ordering": ordering, **(extra or {})}},
    }
    return load_scene(cfg)


def test_rotated_device_apply_equals_the_host_apply():
    with _swinging_sim(refresh_every=1000) as sim:
        for _ in range(15):  # the beam swings down: the factor of step 0 is stale and rotated
            sim.step()
        pre = sim.preconditioner
        assert isinstance(pre, DeviceLDLTPreconditioner)
        integ = sim.integrator
        integ.build()
        pre.begin_step(integ)
        assert pre.device_capable()
        dR = pre.inner.dR
        assert np.abs(dR - np.eye(3)).max() > 1e-2  # the rotation matters here
        assert np.allclose(pre._dR.numpy(), dR, atol=1e-14)
        rng = np.random.default_rng(4)
        for _ in range(3):
            r = rng.standard_normal((sim.mesh.n_nodes, 3))
            z = wp.zeros(len(r), dtype=wp.vec3d, device=DEVICE)
            pre.apply(wp.array(r, dtype=wp.vec3d, device=DEVICE), z)
            ref = np.empty(r.size)
            pre.inner.apply(r.reshape(-1), ref)
            assert np.linalg.norm(z.numpy().reshape(-1) - ref) <= 1e-10 * np.linalg.norm(ref)
            # and the rotation is not the identity: the unrotated factor gives another vector
            plain = pre.inner.factor(r.reshape(-1))
            assert np.linalg.norm(plain - ref) > 1e-6 * np.linalg.norm(ref)


@pytest.mark.parametrize("graph", [False, True])
@pytest.mark.parametrize("pre", ["async_ldlt", "jacobi", "none"])
def test_device_scalar_pcg_matches_host_pcg(pre, graph):
    with _swinging_sim(refresh_every=1000, pre=pre, graph=graph, extra={"apply_on": "device"}) as sim:
        for _ in range(8):
            sim.step()
        integ = sim.integrator
        n = sim.mesh.n_nodes
        host = PCG(n, DEVICE, integ.cg.tolerance, integ.cg.max_iterations)
        dpcg = DevicePCG(n, DEVICE, integ.cg.tolerance, integ.cg.max_iterations, graph=graph)
        x_h = wp.zeros(n, dtype=wp.vec3d, device=DEVICE)
        x_d = wp.full(n, wp.vec3d(1.0, 2.0, 3.0), dtype=wp.vec3d, device=DEVICE)  # the solve starts from 0
        for k in range(3):  # third solve: a graph replay (captured at the second) with a new right-hand side
            integ.build()
            integ.preconditioner.begin_step(integ)
            rh = host.solve(integ.matvec, integ.b, x_h, integ.preconditioner)
            rd = dpcg.solve(integ.matvec, integ.b, x_d, integ.preconditioner)
            assert rh.iterations > 1 and rh.converged
            if pre == "async_ldlt" or not CUDA:
                assert rd.iterations == rh.iterations and rd.converged
            else:  # CUDA: Warp's array_inner and our block reductions round differently; 100s of CG iterations
                assert abs(rd.iterations - rh.iterations) <= 1 and rd.converged
            # same recursion, dot products summed in another order: after hundreds of plain CG
            # iterations the tiny recursive residuals differ in their leading digits
            assert rd.residual <= dpcg.tolerance
            if pre == "async_ldlt" or not CUDA:
                assert abs(rd.residual - rh.residual) <= 0.2 * rh.residual
            assert np.abs(x_d.numpy() - x_h.numpy()).max() <= 1e-8 * np.abs(x_h.numpy()).max()
            integ.step_index += 1
            wp.copy(integ.x, wp.array(integ.x.numpy() + 0.002 * x_h.numpy(), dtype=wp.vec3d, device=DEVICE))
        if graph:
            assert dpcg.captures == 1 and dpcg.replays == 2
        else:
            assert dpcg.captures == 0


def test_device_pcg_zero_and_nonfinite_right_hand_sides():
    with _swinging_sim(pre="jacobi", graph=False) as sim:
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


@pytest.mark.parametrize("graph", [False, True])
def test_simulation_with_device_apply_matches_host_apply(graph):
    runs = {}
    for apply_on in ("host", "device"):
        ov = {"device": DEVICE, "solver": {"preconditioner": "async_ldlt", "tolerance": 1e-10, "max_iterations": 500,
                                           "graph": graph if apply_on == "device" else False,
                                           "ldlt": {"apply_on": apply_on, "ordering": "metis", "deterministic": True,
                                                    "refresh_every": 4}}}
        with load_scene("test_small.yaml", overrides=ov) as sim:
            its = [sim.step().iterations for _ in range(20)]
            st = sim.preconditioner.stats()
            runs[apply_on] = (sim.positions(), its, st, sim.integrator.cg)
    (xh, ih, sh, _), (xd, idv, sd, cg) = runs["host"], runs["device"]
    assert sd["apply_on"] == "device" and sh.get("apply_on") is None
    assert max(ih) > 3  # stale factors between refreshes: several iterations
    assert idv == ih
    assert np.abs(xd - xh).max() <= 1e-8
    with load_scene("test_small.yaml", device=DEVICE) as rest:
        assert np.abs(xh - rest.positions()).max() > 1e-3  # it moved
    if graph:
        assert cg.captures >= 1 and cg.replays >= 15


def test_simulation_with_default_orderings_agrees_to_the_tolerance():
    """Host (CHOLMOD default ordering) vs device (METIS): other preconditioners, same solution."""
    pos = {}
    for apply_on in ("host", "device"):
        ov = {"device": DEVICE, "solver": {"preconditioner": "async_ldlt", "tolerance": 1e-12, "max_iterations": 500,
                                           "ldlt": {"apply_on": apply_on, "deterministic": True, "refresh_every": 3}}}
        with load_scene("test_small.yaml", overrides=ov) as sim:
            for _ in range(20):
                sim.step()
            pos[apply_on] = sim.positions()
    assert np.abs(pos["device"] - pos["host"]).max() <= 1e-8


def test_cut_falls_back_to_the_host_path_then_returns_to_the_device():
    from soft_tissue_sim.cutting import sweep_triangles

    cfg = {
        "device": DEVICE,
        "mesh": {"generator": "beam", "n_long": 12, "n_cross": 3, "spacing": 0.01},
        "materials": [{"id": 0, "young": 5e4, "poisson": 0.3, "density": 1000.0}],
        "damping": {"mass": 0.2, "stiffness": 0.005},
        "fixed": {"axis": "x", "below": 0.0},
        "time": {"dt": 0.01},
        "solver": {"preconditioner": "async_ldlt", "tolerance": 1e-8, "max_iterations": 2000, "graph": True,
                   "ldlt": {"deterministic": True, "refresh_every": 5, "apply_on": "device"}},
        "cutting": {"correction": "sherman_morrison"},
    }
    with load_scene(cfg) as sim:
        for _ in range(3):
            sim.step()
        assert sim.preconditioner.stats()["apply_on"] == "device"
        P = sim.mesh.points
        y = 0.5 * (P[:, 1].min() + P[:, 1].max())
        z0, z1 = P[:, 2].min() - 1e-3, P[:, 2].max() + 1e-3
        res = sim.cut_triangles(sweep_triangles([0.03, y, z0], [0.03, y, z1], [0.08, y, z0], [0.08, y, z1]),
                                frame="rest")
        assert res.changed and sim.preconditioner.inner.correction.active
        s = sim.step()
        st = sim.preconditioner.stats()
        assert st["apply_on"] == "host" and st["device_fallback"] == "Sherman-Morrison correction active"
        assert s.converged
        patterns = st["device_patterns"]
        for _ in range(6):  # the next refresh factorizes the cut mesh: back on the device, new pattern
            s = sim.step()
            assert s.converged
        st = sim.preconditioner.stats()
        assert st["apply_on"] == "device" and st["device_patterns"] == patterns + 1
        assert sim.integrator.cg.captures >= 2  # re-captured for the new size


def test_scene_options():
    with load_scene("test_small.yaml", device="cpu", overrides={"solver": {"preconditioner": "async_ldlt"}}) as sim:
        # auto on the CPU: today's host path, untouched
        assert type(sim.preconditioner) is HostPreconditioner and type(sim.integrator.cg) is PCG
        assert sim.preconditioner.inner.ordering == "default"
    with load_scene("test_small.yaml", device="cpu",
                    overrides={"solver": {"preconditioner": "async_ldlt", "ldlt": {"apply_on": "device"}}}) as sim:
        assert isinstance(sim.preconditioner, DeviceLDLTPreconditioner)
        assert isinstance(sim.integrator.cg, DevicePCG) and not sim.integrator.cg.graph  # graph auto: off on CPU
        assert sim.preconditioner.inner.ordering == "metis"
    with load_scene("test_small.yaml", device="cpu", overrides={"solver": {"preconditioner": "jacobi",
                                                                           "graph": True}}) as sim:
        assert isinstance(sim.integrator.cg, DevicePCG) and sim.integrator.cg.graph
        assert sim.step().converged
    with load_scene("test_small.yaml", device="cpu",
                    overrides={"solver": {"preconditioner": "async_ldlt", "ldlt": {"columns_on": "device"}}}) as sim:
        inner = sim.preconditioner.inner
        assert type(sim.preconditioner) is HostPreconditioner and inner.ordering == "metis"
        assert inner.stats()["columns_on"] == "cpu" and inner.min_device_columns == 6
    for bad in ({"ldlt": {"apply_on": "gpu"}}, {"ldlt": {"ordering": "fancy"}}, {"graph": "maybe"},
                {"ldlt": {"apply_on": "device", "lanes": 3}}, {"ldlt": {"columns_on": "gpu"}},
                {"ldlt": {"columns_on": "device", "cols_lanes": 8}}):  # the CPU backend takes 1 lane only
        with pytest.raises(ParameterError):
            load_scene("test_small.yaml", device="cpu", overrides={"solver": {"preconditioner": "async_ldlt", **bad}})


def test_new_factor_of_the_same_pattern_is_copied_in_place():
    calls = []
    A = _matrix("test_small.yaml")

    def snap():
        calls.append(1)
        return A * (1.0 + 0.1 * len(calls)), np.tile(np.eye(3), (A.shape[0] // 3, 1, 1))

    inner = AsyncLDLTPreconditioner(snap, deterministic=True, ordering="metis", device_layout=True)
    try:
        dev = DeviceLDLT(DEVICE)
        inner._sync_refresh(0)
        dev.set_factor(inner.factor_data)
        ptrs = (dev.lo_vals.ptr, dev.up_vals.ptr, dev.bwd_coef.ptr)
        inner._sync_refresh(1)
        assert dev.set_factor(inner.factor_data)  # same pattern: in place
        assert (dev.lo_vals.ptr, dev.up_vals.ptr, dev.bwd_coef.ptr) == ptrs and dev.pattern_version == 1
        b = np.random.default_rng(5).standard_normal(A.shape[0])
        z, _ = _device_solve(inner.factor_data, b)
        n = A.shape[0] // 3
        r = wp.array(b.reshape(n, 3), dtype=wp.vec3d, device=DEVICE)
        out = wp.zeros_like(r)
        dev.apply(r, out, wp.array(np.tile(np.eye(3), (n, 1, 1)), dtype=wp.mat33d, device=DEVICE))
        ref = inner.factor(b)
        assert np.linalg.norm(out.numpy().reshape(-1) - ref) <= 1e-10 * np.linalg.norm(ref)
    finally:
        inner.close()
