"""Host assembly of A from a frozen state: equal to the Warp element blocks, after cuts too;
a factor assembled in the background worker equals one assembled on the caller's thread."""

import time

import numpy as np
import pytest
import scipy.sparse as sps
import scipy.sparse.linalg as spla
import warp as wp

from soft_tissue_sim import load_scene
from soft_tissue_sim.corotational_fem import CorotationalFEM
from soft_tissue_sim.host_assembly import ScatterMap, scatter_map
from soft_tissue_sim.ldlt_preconditioner import AsyncLDLTPreconditioner, _drop_decoupled
from soft_tissue_sim.material import Material, MaterialTable
from soft_tissue_sim.mesh import beam_mesh

from test_cutting import beam_scene, crosswise, lengthwise


def warp_matrix(fem, m_coef, k_coef):
    """A summed from the Warp kernel's COO triplets of 3x3 blocks (what the device factors use)."""
    rows, cols, vals = (a.numpy() for a in fem.assemble_triplets(m_coef, k_coef))
    r = (3 * rows[:, None, None] + np.arange(3)[None, :, None]) + 0 * np.arange(3)[None, None, :]
    c = (3 * cols[:, None, None] + np.arange(3)[None, None, :]) + 0 * np.arange(3)[None, :, None]
    n3 = 3 * fem.n_nodes
    return sps.coo_matrix((vals.ravel(), (r.ravel(), c.ravel())), shape=(n3, n3)).tocsc()


def block_pattern(fem):
    """Every 3x3 block of every element pair, and every diagonal block, stored in full (the
    pattern of the Warp assembly), less the stored zeros that couple fixed nodes."""
    T = fem.tets.numpy().astype(np.int64)
    n = fem.n_nodes
    I = np.concatenate([np.repeat(T, 4, axis=1).ravel(), np.arange(n)])
    J = np.concatenate([np.tile(T, (1, 4)).ravel(), np.arange(n)])
    B = sps.coo_matrix((np.ones(len(I)), (I, J)), shape=(n, n)).tocsc()
    B.data[:] = 1.0
    P = sps.kron(B, np.ones((3, 3)), format="csc")
    P.sort_indices()
    fixed = np.repeat(fem.free.numpy() == 0.0, 3)
    cols = np.repeat(np.arange(P.shape[1]), np.diff(P.indptr))
    keep = (P.indices == cols) | ~(fixed[P.indices] | fixed[cols])
    return sps.csc_matrix((P.data[keep], P.indices[keep], np.r_[0, np.cumsum(np.bincount(cols[keep],
                                                                                           minlength=P.shape[1]))]),
                          shape=P.shape)


def assert_assembly_matches(fem, m_coef, k_coef):
    A = fem.assemble_scipy(m_coef, k_coef)
    ref = warp_matrix(fem, m_coef, k_coef)
    assert A.has_sorted_indices and np.all(np.diff(A.indptr) >= 0)
    for j in range(0, A.shape[1], 7):  # sorted rows in each column
        assert np.all(np.diff(A.indices[A.indptr[j]:A.indptr[j + 1]]) > 0)
    P = block_pattern(fem)
    np.testing.assert_array_equal(A.indptr, P.indptr)
    np.testing.assert_array_equal(A.indices, P.indices)
    D = _drop_decoupled(ref)  # what the factorization of a sparse A drops: the same pattern
    np.testing.assert_array_equal(A.indptr, D.indptr)
    np.testing.assert_array_equal(A.indices, D.indices)
    err = abs(A - ref).max() / abs(ref).max()
    assert err < 1e-12, err
    return A


@pytest.mark.parametrize("mass", ["lumped", "consistent"])
def test_host_assembly_equals_the_warp_blocks_with_rotations_fixed_nodes_and_two_materials(mass):
    mesh = beam_mesh(5, n_cross=3, spacing=0.01)
    mesh.material_ids[: mesh.n_tets // 2] = 1
    mat = MaterialTable({0: Material(2e5, 0.35, 1100.0), 1: Material(4e6, 0.0, 900.0)})  # lambda = 0 in one
    fixed = np.flatnonzero(mesh.points[:, 0] <= 1e-12)
    f = CorotationalFEM(mesh, mat, "cpu", mass=mass, fixed_nodes=fixed)
    rng = np.random.default_rng(3)
    x = mesh.points + 0.003 * rng.standard_normal(mesh.points.shape)
    f.update_rotations(wp.array(x, dtype=wp.vec3d))
    assert np.abs(f.rotations.numpy() - np.eye(3)).max() > 1e-2  # rotations that matter
    A = assert_assembly_matches(f, 1.3, 2e-4)
    for i in fixed:
        np.testing.assert_array_equal(A[3 * i:3 * i + 3, 3 * i:3 * i + 3].toarray(), np.eye(3))
    f.set_fixed_nodes(fixed[:2])  # fixed flags changed in place: the next state sees them
    assert_assembly_matches(f, 1.3, 2e-4)


def test_host_assembly_equals_the_warp_blocks_after_cuts():
    with load_scene(beam_scene(n_long=10, deterministic=True, refresh_every=1000)) as sim:
        fem, integ = sim.fem, sim.integrator
        sim.step()
        seen = []
        for cut in (lambda: lengthwise(sim, 0.005, 0.04), lambda: crosswise(sim, 0.075),
                    lambda: lengthwise(sim, 0.06, 0.095)):
            assert cut().changed
            sim.step()
            fem.update_rotations(integ.x)
            assert_assembly_matches(fem, integ.m_coef, integ.k_coef)
            seen.append((fem.n_nodes, fem.tets.numpy().copy(), fem.free.numpy() == 0.0))
        # the cached pattern of an earlier topology is that topology's, built afresh
        assert not ScatterMap.build(*seen[-1]).matches(*seen[-2])  # the cuts changed the topology
        cached, fresh = scatter_map(*seen[-2]), ScatterMap.build(*seen[-2])
        for k in ("indptr", "indices", "pair_block", "transpose", "diag", "place"):
            np.testing.assert_array_equal(getattr(cached, k), getattr(fresh, k))


def test_the_state_is_a_copy_the_simulation_does_not_change():
    with load_scene(beam_scene(n_long=8, deterministic=True, refresh_every=1000)) as sim:
        fem, integ = sim.fem, sim.integrator
        sim.step()
        fem.update_rotations(integ.x)
        state = fem.assembly_state(integ.m_coef, integ.k_coef)
        A0 = warp_matrix(fem, integ.m_coef, integ.k_coef)
        for _ in range(3):
            sim.step()
        assert lengthwise(sim, 0.005, 0.04).changed
        fem.update_rotations(integ.x)
        assert abs(warp_matrix(fem, integ.m_coef, integ.k_coef)[:A0.shape[0], :A0.shape[1]] - A0).max() > 0
        assert abs(state.csc() - A0).max() < 1e-12 * abs(A0).max()


@pytest.mark.parametrize("worker", ["thread", "process"])
def test_a_factor_assembled_in_the_worker_equals_one_assembled_on_the_callers_thread(worker):
    with load_scene(beam_scene(n_long=10, deterministic=True, refresh_every=1000)) as sim:
        fem, integ = sim.fem, sim.integrator
        sim.step()
        assert lengthwise(sim, 0.005, 0.04).changed
        sim.step()
        fem.update_rotations(integ.x)
        state = fem.assembly_state(integ.m_coef, integ.k_coef)
        A_ref = warp_matrix(fem, integ.m_coef, integ.k_coef)
        R = fem.node_rotations()
        n = fem.n_nodes
    factors = {}
    for name, snap in (("worker", lambda: (state, R)), ("caller", lambda: (state.csc(), R))):
        p = AsyncLDLTPreconditioner(snap, refresh_every=1, worker=worker, rotate=False)
        p.begin_step(0, R)  # the first factor: made at once
        p.begin_step(1, R)  # a background request
        deadline = time.time() + 30
        while p.factor_count < 2 and time.time() < deadline:  # installed by a later step
            time.sleep(0.01)
            p.begin_step(p.step + 1, R)
        assert p.factor_count > 1 and p.stats()["worker_error"] is None
        rng = np.random.default_rng(5)
        B = rng.standard_normal((3 * n, 4))
        factors[name] = p.apply_columns(B)
        p.close()
    np.testing.assert_array_equal(factors["worker"], factors["caller"])
    ref = spla.spsolve(A_ref, B)
    assert np.abs(factors["worker"] - ref).max() < 1e-9 * np.abs(ref).max()


@pytest.mark.parametrize("n", [50, 65_535])  # the radix path, to its largest n
def test_unique_pairs_is_numpys_unique_of_the_keys(n):
    from soft_tissue_sim.host_assembly import _unique_pairs

    rng = np.random.default_rng(n)
    rows, cols = rng.integers(0, n, 5000), rng.integers(0, n, 5000)
    rows[:100], cols[:100] = rows[100:200], cols[100:200]  # duplicates
    keys, inv = _unique_pairs(rows, cols, n)
    ref_keys, ref_inv = np.unique(cols * n + rows, return_inverse=True)
    np.testing.assert_array_equal(keys, ref_keys)
    np.testing.assert_array_equal(inv, ref_inv)
