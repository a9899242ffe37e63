"""Cutting by node splitting and the Sherman-Morrison correction of the preconditioner."""

import numpy as np
import pytest
import warp as wp
import scipy.sparse as sps
import scipy.sparse.linalg as spla

from soft_tissue_sim import load_scene
from soft_tissue_sim.cutting import sweep_triangles, tets_cut_by_triangle
from soft_tissue_sim.cutting.geometry import TET_EDGES, _dot
from soft_tissue_sim.mesh import cross
from soft_tissue_sim.mesh import tet_quality, validate_mesh


def beam_scene(n_long=8, n_cross=3, pre="async_ldlt", correction="sherman_morrison", refresh_every=1000,
               deterministic=True, script=None, fixed=True, gravity=(0.0, 0.0, -9.81), young=5e4, rotate=True,
               backend="cholmod", scheme="split", worker="thread"):
    cut = {"correction": correction, "scheme": scheme}
    if script:
        cut["script"] = script
    return {
        "device": "cpu",
        "mesh": {"generator": "beam", "n_long": n_long, "n_cross": n_cross, "spacing": 0.01},
        "materials": [{"id": 0, "young": young, "poisson": 0.3, "density": 1000.0}],
        "damping": {"mass": 0.2, "stiffness": 0.005},
        "fixed": {"axis": "x", "below": 0.0} if fixed else None,
        "gravity": list(gravity),
        "time": {"dt": 0.01},
        "solver": {"preconditioner": pre, "tolerance": 1e-8, "max_iterations": 3000,
                   "ldlt": {"deterministic": deterministic, "refresh_every": refresh_every, "rotate": rotate,
                            "backend": backend, **({"worker": worker} if backend == "cholmod" else {})}},
        "cutting": cut,
    }


def unrotated_dense_beam(device):
    """:func:`beam_scene` with the dense backend, unrotated (the nodal rotations a cut changes
    are not part of the correction), on ``device``."""
    cfg = beam_scene(rotate=False, backend="dense")
    cfg["device"] = device
    return cfg


def fresh_bound(sim, rng) -> float:
    """The bound on :func:`corrected_vs_fresh` of a corrected dense inverse: as close to
    A_new^-1 as a fresh factor of A_new made on the simulation's device is (each device's
    inverse rounds its own way), at least 1e-8. Installs that fresh factor."""
    sim.preconditioner.refresh(sim.integrator)
    return max(1e-8, 10.0 * corrected_vs_fresh(sim, rng))


def lengthwise(sim, x0, x1, y=None, frame="rest"):
    """A vertical blade patch in the plane y = mid, from x0 to x1, through the whole height."""
    P = sim.mesh.points
    y = 0.5 * (P[:, 1].min() + P[:, 1].max()) if y is None else y
    z0, z1 = P[:, 2].min() - 1e-3, P[:, 2].max() + 1e-3
    return sim.cut_triangles(sweep_triangles([x0, y, z0], [x0, y, z1], [x1, y, z0], [x1, y, z1]), frame=frame)


def crosswise(sim, x, frame="rest", upper_half=False):
    """A blade patch in the plane x, across the whole width, through the whole height (or its
    upper half)."""
    P = sim.mesh.points
    lo, hi = P.min(axis=0) - 1e-3, P.max(axis=0) + 1e-3
    z0 = 0.5 * (lo[2] + hi[2]) if upper_half else lo[2]
    return sim.cut_triangles(sweep_triangles([x, lo[1], z0], [x, lo[1], hi[2]], [x, hi[1], z0],
                                             [x, hi[1], hi[2]]), frame=frame)


def corrected_vs_fresh(sim, rng, k=3):
    """Max relative difference between the corrected preconditioner and A_new^-1 on random vectors."""
    integ = sim.integrator
    sim.fem.update_rotations(integ.x)
    A = sim.fem.assemble_scipy(integ.m_coef, integ.k_coef)
    pre = sim.preconditioner
    pre.begin_step(integ)
    lu = spla.splu(A.tocsc())
    err = 0.0
    n = A.shape[0] // 3
    z = wp.zeros(n, dtype=wp.vec3d, device=sim.device)
    for _ in range(k):
        b = rng.standard_normal(A.shape[0])
        pre.apply(wp.array(b.reshape(n, 3), dtype=wp.vec3d, device=sim.device), z)
        out = z.numpy().reshape(-1)
        ref = lu.solve(b)
        err = max(err, np.linalg.norm(out - ref) / np.linalg.norm(ref))
    return err


@pytest.mark.parametrize("backend, scheme, worker", [("cholmod", "split", "thread"), ("dense", "split", None),
                                                     ("cholmod", "subdivide", "thread"), ("dense", "subdivide", None),
                                                     ("cholmod", "split", "process")])
def test_corrected_preconditioner_equals_inverse_of_modified_matrix(backend, scheme, worker):
    # Unrotated: the averaged nodal rotations of eq. (2) change where a cut changes the elements
    # around a node, which is an approximation by design, not part of the correction.
    # dense: the correction folded into the dense inverse (on Warp's CPU backend here).
    # subdivide: the cut also bisects the crossed tets (new nodes on edges, eq. 10 padding).
    rng = np.random.default_rng(0)
    with load_scene(beam_scene(rotate=False, backend=backend, scheme=scheme, worker=worker)) as sim:
        for _ in range(3):
            sim.step()  # deformed, rotated state; the factor is from step 0 (refresh_every large)
        # make the factor current, so that the only difference is the cut
        sim.fem.update_rotations(sim.integrator.x)
        sim.preconditioner.refresh(sim.integrator)
        inner = sim.preconditioner.inner
        if backend == "dense":  # R(t_u) of eq. (2) copied on the device at the install: no host read
            assert inner._R_ref_np is None and inner._R_ref_src is not None
            np.testing.assert_array_equal(inner.R_ref.numpy(), inner._R_ref_src.numpy())
        assert corrected_vs_fresh(sim, rng) < 1e-10
        n0 = sim.mesh.n_nodes
        res = lengthwise(sim, 0.035, 0.08)
        assert res.changed and res.nodes_added > 0 and sim.mesh.n_nodes == n0 + res.nodes_added
        if backend == "dense":  # read to the host by the fold, the device copy following it
            assert inner._R_ref_src is None and len(inner.R_ref_host) == sim.mesh.n_nodes
            np.testing.assert_array_equal(inner.R_ref.numpy(), inner.R_ref_host)
        if backend == "cholmod":
            assert inner.correction.active
        assert corrected_vs_fresh(sim, rng) < 1e-8
        # a second cut chains a second correction on top of the first
        res2 = crosswise(sim, 0.055)
        assert res2.changed
        if backend == "cholmod":
            assert len(inner.correction.terms) == 2
        else:
            assert inner.correction.folds == 2
        assert corrected_vs_fresh(sim, rng) < 1e-8
        # element removal (nodes vanish, numbering compacts) is corrected as well
        res3 = sim.remove_elements(sim.positions()[-1], 0.012)
        assert res3.changed and res3.nodes_removed > 0
        assert corrected_vs_fresh(sim, rng) < 1e-8
        assert inner.stats()["backend"] == backend


def test_without_correction_the_padded_factor_is_not_the_inverse():
    rng = np.random.default_rng(1)
    with load_scene(beam_scene(correction="none")) as sim:
        sim.step()
        lengthwise(sim, 0.035, 0.08)
        assert corrected_vs_fresh(sim, rng) > 1e-3


def test_iterations_after_a_cut_stay_low_with_the_correction_and_rise_without():
    its = {}
    for corr in ("sherman_morrison", "none"):
        with load_scene(beam_scene(n_long=16, correction=corr, refresh_every=1000)) as sim:
            for _ in range(2):
                sim.step()
            sim.preconditioner.inner._sync_refresh(sim.step_count)
            before = sim.step().iterations
            assert lengthwise(sim, 0.06, 0.16).changed
            its[corr] = (before, sim.step().iterations)
    (b_smf, a_smf), (_b_none, a_none) = its["sherman_morrison"], its["none"]
    assert a_smf <= b_smf + 2, its
    assert a_none > a_smf + 3, its


def test_in_flight_factor_is_corrected_and_corrections_dropped_once_a_factor_postdates_them():
    rng = np.random.default_rng(2)
    with load_scene(beam_scene(deterministic=True, refresh_every=1000, rotate=False)) as sim:
        sim.step()
        pre = sim.preconditioner.inner
        corr = pre.correction
        # a snapshot taken before the cut, factorized "in the background", installed after it
        sim.fem.update_rotations(sim.integrator.x)
        req = pre._snapshot(sim.step_count)
        lengthwise(sim, 0.035, 0.08)
        from soft_tissue_sim.ldlt_preconditioner import _factorize

        pre._install({"factor": _factorize(pre._s, req["A"]), "R": req["R"], "step": req["step"], "ms": 0.0,
                      "meta": req["meta"]})
        assert len(corr.mods) == 1 and len(corr.terms) == 1  # the cut re-applied to the new factor (fig. 2)
        assert corrected_vs_fresh(sim, rng) < 1e-8
        pre._sync_refresh(sim.step_count)  # a factor made after the cut: nothing left to correct
        assert corr.mods == [] and corr.terms == [] and not corr.active


def test_cut_separates_the_two_sides_and_conserves_mass():
    with load_scene(beam_scene(n_long=8)) as sim:
        m0 = sim.fem.total_mass
        q0 = tet_quality(sim.mesh.points, sim.mesh.tets).min()
        res = crosswise(sim, 0.035)
        assert res.changed
        assert abs(sim.fem.total_mass - m0) < 1e-12 * m0
        # the crosswise cut splits the body in two connected components
        from scipy.sparse.csgraph import connected_components

        T = sim.mesh.tets
        rows = np.repeat(T, 4, axis=1).ravel()
        cols = np.tile(T, (1, 4)).ravel()
        g = sps.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(sim.mesh.n_nodes,) * 2)
        assert connected_components(g, directed=False)[0] == 2
        assert tet_quality(sim.mesh.points, sim.mesh.tets).min() >= q0 - 1e-12


def test_a_part_cut_free_falls_freely():
    with load_scene(beam_scene(n_long=10, young=2e5)) as sim:
        for _ in range(30):
            sim.step()  # let it settle a bit
        res = crosswise(sim, 0.045)
        assert res.changed
        x0 = sim.positions()
        free_part = sim.mesh.points[:, 0] > 0.05  # rest coordinates beyond the cut
        v0 = sim.velocities()[free_part].mean(axis=0)
        c0 = x0[free_part].mean(axis=0)
        n = 10
        for _ in range(n):
            s = sim.step()
            assert s.converged
        t = n * sim.dt
        c1 = sim.positions()[free_part].mean(axis=0)
        # centre of mass of the free part: free fall with Rayleigh mass damping alpha = 0.2 (backward Euler)
        vz = v0[2]
        z = c0[2]
        for _ in range(n):
            vz = (vz - 9.81 * sim.dt) / (1.0 + 0.2 * sim.dt)
            z += sim.dt * vz
        assert c1[2] == pytest.approx(z, abs=2e-4)
        assert abs(c1[0] - c0[0] - v0[0] * t) < 2e-3


@pytest.mark.parametrize("tri, expect", [
    # long and thin, through the tet: no corner of the section inside it, its centroid outside the tet
    ([[-1.0, 0.1, 0.2], [3.0, 0.1, 0.2], [3.0, 0.1001, 0.2]], True),
    # small, inside the tet
    ([[0.1, 0.1, 0.2], [0.15, 0.1, 0.2], [0.1, 0.15, 0.2]], True),
    # large, containing the section
    ([[-1.0, -1.0, 0.2], [3.0, -1.0, 0.2], [-1.0, 3.0, 0.2]], True),
    # in the section's plane but beside it, and thin past its corner
    ([[0.7, 0.7, 0.2], [0.9, 0.7, 0.2], [0.7, 0.9, 0.2]], False),
    ([[-1.0, 0.9, 0.2], [3.0, 0.9, 0.2], [3.0, 0.9001, 0.2]], False),
])
def test_blade_triangle_against_a_tet_section(tri, expect):
    P = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    hit, side = tets_cut_by_triangle(P, np.array([[0, 1, 2, 3]]), np.array(tri), 1e-12)
    assert (len(hit) == 1) == expect


def _shave_blade(P):
    """A blade across the top corner edge of the free end of the beam of rest points P, cutting
    off only the tets touching it."""
    hi = P.max(axis=0)
    h = 0.008  # less than the 1 cm spacing: only the corner column's edge tets are cut off (6 tets: the
    # mirrored split cuts each corner cell of this beam along the diagonal plane across that edge)
    a, b = [hi[0] - h - 0.002, hi[1] + 0.002, hi[2] + 0.002], [hi[0] + 0.002, hi[1] - h - 0.002, hi[2] + 0.002]
    return sweep_triangles(a, b, [a[0], a[1], hi[2] - 0.03], [b[0], b[1], hi[2] - 0.03])


def _corner_shave(sim):
    return sim.cut_triangles(_shave_blade(sim.mesh.points), frame="rest")


@pytest.mark.parametrize("min_fragment", [0, 8])
def test_a_sliver_cut_free_is_removed_as_debris_unless_disabled(min_fragment):
    cfg = beam_scene(n_long=6)
    cfg["cutting"]["min_fragment"] = min_fragment
    with load_scene(cfg) as sim:
        n_tets, m0 = sim.mesh.n_tets, sim.fem.total_mass
        res = _corner_shave(sim)
        assert res.changed
        frag = type(sim.cutting).small_fragments(type("C", (), {"min_fragment": 8})(), sim.mesh, sim.fem.free.numpy())
        if min_fragment == 0:  # the shaved-off corner stays, as a free fragment of a few tets
            assert res.debris_tets == 0 and 0 < frag.sum() < 8
            assert sim.mesh.n_tets == n_tets and sim.fem.total_mass == pytest.approx(m0, rel=1e-12)
        else:  # it is removed, said so, and no free fragment is left; the body stays valid
            assert 0 < res.debris_tets < 8 and "debris" in res.message
            assert not frag.any()
            assert sim.mesh.n_tets == n_tets - res.debris_tets and sim.fem.total_mass < m0
            m = sim.mesh
            validate_mesh(m.points, m.tets, m.material_ids)
            assert sim.step().converged


@pytest.mark.parametrize("backend", ["cholmod", "dense"])
def test_the_debris_removal_made_part_of_the_cut_gives_the_two_changes_result(backend):
    """The cut and the removal of the debris it leaves are applied as one change
    (TopologyChange.then): the same mesh, node identities and state as the cut and then the
    removal applied one after the other, and the preconditioner corrected for the one change
    as for the two (exact corrections: the same steps to the solver's tolerance)."""
    sims = []
    for min_fragment in (8, 0):
        cfg = beam_scene(n_long=6, backend=backend)
        cfg["cutting"]["min_fragment"] = min_fragment
        sim = load_scene(cfg)
        for _ in range(3):
            sim.step()
        res = _corner_shave(sim)
        assert res.changed
        if min_fragment == 0:  # the debris removed by a second change
            frag = type(sim.cutting).small_fragments(type("C", (), {"min_fragment": 8})(), sim.mesh,
                                                     sim.fem.free.numpy())
            assert frag.any() and sim.remove_tets(frag).changed
        else:
            assert res.debris_tets > 0 and sim.cutting.modifications == 1
        sims.append(sim)
    try:
        _same_bodies(*sims)
    finally:
        for sim in sims:
            sim.close()


def _same_bodies(one, two):
    """The two simulations hold the same mesh, node identities, state and FEM, and take the
    same next steps (to the solver's tolerance)."""
    np.testing.assert_array_equal(one.mesh.tets, two.mesh.tets)
    np.testing.assert_array_equal(one.mesh.points, two.mesh.points)
    np.testing.assert_array_equal(one.node_uids, two.node_uids)
    np.testing.assert_array_equal(one.positions(), two.positions())
    for name in ("volume", "lumped_mass", "Dm_inv", "free"):
        np.testing.assert_array_equal(getattr(one.fem, name).numpy(), getattr(two.fem, name).numpy())
    for _ in range(3):
        a, b = one.step(), two.step()
        assert a.converged and b.converged and abs(a.iterations - b.iterations) <= 1
    np.testing.assert_allclose(one.positions(), two.positions(), rtol=0, atol=1e-9)


@pytest.mark.parametrize("first, then", [("remove", "remove"), ("remove", "cut"), ("cut", "remove")])
def test_two_topology_changes_composed_are_the_two_applied_in_turn(first, then):
    """TopologyChange.then: a change and one planned on its result, applied as one change, leave
    the mesh, node identities, state and FEM of the two applied in turn, and a preconditioner
    corrected for the one as for the two (the same steps to the solver's tolerance). Removals
    of original tets and of a cut's new ones, and a cut after a removal."""
    sims = [load_scene({**beam_scene(n_long=6), "cutting": {"min_fragment": 0, "correction": "sherman_morrison"}})
            for _ in range(2)]
    try:
        for sim in sims:
            for _ in range(3):
                sim.step()

        def plan(sim, kind, tissue, k):
            if kind == "cut":
                return sim.cutting.cut_triangles(tissue, _shave_blade(tissue.mesh.points), frame="rest")
            # tets of the free end's last layer, the lowest (first removal) or the next ones (second)
            c = tissue.mesh.points[tissue.mesh.tets].mean(axis=1)
            end = c[:, 0] > c[:, 0].max() - 0.004
            y, z = -0.01 + 0.006 * k, -0.01
            return sim.cutting.remove_tets(tissue, end & (c[:, 1] < y + 0.006) & (c[:, 1] > y) & (c[:, 2] < z + 0.006))

        one, two = sims
        p1 = plan(one, first, one.tissue(), 0)
        p2 = plan(one, then, p1.change.tissue(), 1)
        assert p1.change is not None and p2.change is not None and len(p2.change.removed_tets)
        c1, c2 = p1.change, p2.change
        p1.change = c = c1.then(c2)
        # each created node takes the rotation of the original node the two changes name
        source = dict(zip(c1.created.tolist(), c1.old_uids[c1.rotation_source].tolist()))
        source.update({u: source.get(s, s) for u, s in zip(c2.created.tolist(), c2.old_uids[c2.rotation_source].tolist())})
        assert sorted(c.created.tolist()) == sorted(set(source) & set(c.node_uids.tolist()))
        assert c.old_uids[c.rotation_source].tolist() == [source[u] for u in c.created.tolist()]
        assert one._modify(p1).changed
        for k, kind in enumerate((first, then)):  # the same plans, on the simulation's own tissue each time
            assert two._modify(plan(two, kind, two.tissue(), k)).changed
        _same_bodies(one, two)
    finally:
        for sim in sims:
            sim.close()


@pytest.mark.parametrize("scheme", ["split", "subdivide"])
def test_cut_through_empty_space_changes_nothing_and_says_so(scheme):
    with load_scene(beam_scene(scheme=scheme)) as sim:
        sim.step()
        x = sim.positions()
        T = sim.mesh.tets.copy()
        res = sim.cut_triangles(sweep_triangles([1, 1, 1], [1, 1, 2], [2, 1, 1], [2, 1, 2]))
        assert not res.changed and "no tissue" in res.message
        res = sim.cut_triangles([[[0, 0, 0], [1, 0, 0], [2, 0, 0]]])  # degenerate blade
        assert not res.changed and "no area" in res.message
        res = sim.cut_triangles([[[0, 0, 0], [np.nan, 0, 0], [2, 0, 0]]])
        assert not res.changed and "non-finite" in res.message
        assert np.array_equal(sim.mesh.tets, T) and np.array_equal(sim.positions(), x)
        assert sim.mesh_version == 0


def test_a_part_cut_free_is_lifted_out_and_the_preconditioner_follows():
    """remove_tets: the extraction of a resected part. Exactly the given tets go, the mass
    follows, the corrected preconditioner is still the inverse of the new A; bad input is
    refused and changes nothing."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(4)
    with load_scene(beam_scene(rotate=False)) as sim:
        sim.step()
        sim.fem.update_rotations(sim.integrator.x)  # a current factor: the cuts are the only change
        sim.preconditioner.inner._sync_refresh(sim.step_count)
        assert crosswise(sim, 0.055).changed
        T = sim.mesh.tets
        g = coo_matrix((np.ones(T.size * 4), (np.repeat(T, 4, axis=1).ravel(), np.tile(T, (1, 4)).ravel())),
                       shape=(sim.mesh.n_nodes,) * 2)
        _, lab = connected_components(g, directed=False)
        fixed_parts = np.unique(lab[sim.fem.fixed_nodes])
        free_part = ~np.isin(lab[T[:, 0]], fixed_parts)
        assert 5 < free_part.sum() < len(T)
        n_tets, mass = sim.mesh.n_tets, sim.fem.total_mass
        vol = sim.fem.volume.numpy()
        x_before, v_before, dv_before = sim.positions(), sim.velocities(), sim.integrator.dv.numpy().copy()
        for bad in (np.ones(n_tets + 1, bool), [n_tets], [-1], np.ones(n_tets, bool), [], [0.5]):
            res = sim.remove_tets(bad)
            assert not res.changed and res.message
        assert sim.mesh.n_tets == n_tets and np.array_equal(sim.positions(), x_before)
        res = sim.remove_tets(free_part)
        assert res.changed and res.tets_changed == free_part.sum()
        assert sim.mesh.n_tets == n_tets - free_part.sum()
        assert sim.fem.total_mass == pytest.approx(mass * (1.0 - vol[free_part].sum() / vol.sum()), rel=1e-12)
        kept = np.isin(np.arange(len(x_before)), np.unique(T[~free_part]))
        np.testing.assert_array_equal(sim.velocities(), v_before[kept])
        np.testing.assert_array_equal(sim.integrator.dv.numpy(), dv_before[kept])  # the solver's guess too
        assert corrected_vs_fresh(sim, rng) < 1e-8
        assert sim.step().converged


@pytest.mark.parametrize("scheme, cuts, size", [("split", 500, 0.006), ("subdivide", 25, 0.02)])
def test_five_hundred_cuts_keep_the_mesh_valid_and_the_state_finite(scheme, cuts, size):
    """Random blades anywhere: the mesh stays valid, no node is orphaned, the state finite;
    splitting never lowers the quality, subdivision keeps it above the floor. (Subdivision
    separates only where a blade crosses whole elements: its blades are larger than one.)"""
    rng = np.random.default_rng(3)
    with load_scene(beam_scene(n_long=10, refresh_every=4, deterministic=False, scheme=scheme)) as sim:
        q0 = tet_quality(sim.mesh.points, sim.mesh.tets).min() if scheme == "split" else sim.cutting.min_quality
        changed = 0
        for i in range(cuts):
            P = sim.positions()
            c = P[rng.integers(len(P))]
            d = rng.standard_normal((2, 3)) * size
            tri = np.array([c - d[0] - d[1], c + d[0], c + d[1]])
            changed += sim.cut_triangles([tri]).changed
            if i % 5 == 0:
                s = sim.step()
                assert np.isfinite(s.residual)
        m = sim.mesh
        validate_mesh(m.points, m.tets, m.material_ids)  # raises on a broken mesh
        assert tet_quality(m.points, m.tets).min() >= q0 - 1e-12
        used = np.zeros(m.n_nodes, bool)
        used[m.tets.ravel()] = True
        assert used.all()
        assert np.isfinite(sim.positions()).all()
        assert changed > cuts // 10


def test_scripted_cut_and_reset():
    script = {"frame": "rest", "start_step": 1, "every": 2, "count": 3, "origin": [0.075, 0.0, -0.011],
              "edge": [0, 0, 0.022], "direction": [-1, 0, 0], "advance": 0.01}
    with load_scene(beam_scene(n_long=8, script=script, refresh_every=2, deterministic=False)) as sim:
        n0, m0 = sim.mesh.n_nodes, sim.surface_triangles().shape[0]
        stats = [sim.step() for _ in range(8)]
        assert stats[-1].extra["cuts"] == 3
        assert sim.mesh.n_nodes > n0 and sim.surface_triangles().shape[0] > m0
        assert all(s.converged for s in stats)
        sim.reset()
        assert sim.mesh.n_nodes == n0 and sim.surface_triangles().shape[0] == m0 and sim.mesh_version == 0
        assert sim.step().converged


def test_cutting_machinery_is_absent_where_nothing_is_cut():
    cfg = beam_scene()
    del cfg["cutting"]
    with load_scene(cfg) as sim:
        assert sim.cutting is None and sim.preconditioner.inner.correction is None
        with pytest.raises(ValueError):
            sim.cut()
        assert "cuts" not in sim.step().extra


def test_jacobi_scene_cuts_too():
    with load_scene(beam_scene(pre="jacobi")) as sim:
        sim.step()
        assert lengthwise(sim, 0.035, 0.08).changed
        assert sim.step().converged


# ------------------------------------------------------------ subdivision scheme
def test_subdivision_cuts_at_the_blade_and_conserves_mass_and_volume():
    """A crosswise cut between two layers of nodes: the split scheme would cut along a layer of
    faces; subdivision splits exactly the tets of the crossed layer, puts the new nodes on the
    blade's plane (rest and current positions on their edges at the same parameter), conserves
    mass and volume, parts the body in two, and the free part falls."""
    x_cut = 0.0637  # layers at 0.06 and 0.07
    with load_scene(beam_scene(n_long=10, scheme="subdivide", young=2e5)) as sim:
        for _ in range(5):
            sim.step()
        n0, m0, V0 = sim.mesh.n_nodes, sim.fem.total_mass, sim.mesh.signed_volumes().sum()
        layer = np.all((sim.mesh.points[sim.mesh.tets][:, :, 0] > 0.055) & (sim.mesh.points[sim.mesh.tets][:, :, 0] < 0.075),
                       axis=1)
        x_before, tets_before = sim.positions(), sim.mesh.tets.copy()
        dv_before = sim.integrator.dv.numpy().copy()  # the last solve's, the next one's guess
        assert np.abs(dv_before).max() > 0.0
        res = crosswise(sim, x_cut)
        assert res.changed and "subdivision" in res.message
        assert res.tets_changed == layer.sum()  # exactly the crossed layer
        assert abs(sim.fem.total_mass - m0) < 1e-12 * m0
        assert sim.mesh.signed_volumes().sum() == pytest.approx(V0, rel=1e-12)
        new = sim.mesh.points[n0:]
        assert len(new) == res.nodes_added > 0
        np.testing.assert_allclose(new[:, 0], x_cut, atol=1e-12)  # on the blade
        # the displacement field is unchanged: each new node is where the old (linear) field puts it
        X, DV = sim.positions(), sim.integrator.dv.numpy()
        np.testing.assert_array_equal(DV[:n0], dv_before)
        P0 = sim.mesh.points[:n0][tets_before]  # (m, 4, 3) old tets, rest
        T = np.stack([P0[:, 1] - P0[:, 0], P0[:, 2] - P0[:, 0], P0[:, 3] - P0[:, 0]], axis=2)
        for p in range(n0, sim.mesh.n_nodes):
            b = np.linalg.solve(T, (sim.mesh.points[p] - P0[:, 0])[:, :, None])[:, :, 0]
            w = np.concatenate([1.0 - b.sum(axis=1, keepdims=True), b], axis=1)
            e = int(np.argmax(w.min(axis=1)))  # a tet holding the node (on its edge)
            assert w[e].min() > -1e-9
            np.testing.assert_allclose(X[p], w[e] @ x_before[tets_before[e]], atol=1e-12)
            np.testing.assert_allclose(DV[p], w[e] @ dv_before[tets_before[e]], atol=1e-12)  # the guess alike
        assert len(np.unique(sim.mesh.node_components())) == 2
        assert tet_quality(sim.mesh.points, sim.mesh.tets).min() >= sim.cutting.min_quality
        free = sim.mesh.points[:, 0] > x_cut
        z0 = sim.positions()[free, 2].mean()
        for _ in range(10):
            assert sim.step().converged
        assert sim.positions()[free, 2].mean() < z0 - 0.5 * 9.81 * (10 * sim.dt) ** 2 * 0.8  # it falls


@pytest.mark.parametrize("scheme", ["split", "subdivide"])
def test_a_blade_swept_in_small_steps_cuts_along_its_path(scheme):
    """Continuous cutting (pedal down): the scalpel's blade moves lengthwise 1.2 mm a step,
    less than an element. Both schemes open a crack along its path; subdivision puts it on the
    blade (the new nodes within a fraction of a millimetre of its plane), splitting along the
    faces within about an element."""
    cfg = beam_scene(n_long=12, n_cross=4, scheme=scheme, gravity=(0.0, 0.0, 0.0))
    cfg["cutting"].update({"instrument": "scalpel", "min_fragment": 0})  # nothing hidden as debris
    cfg["instruments"] = [{"name": "scalpel", "shape": "capsule", "radius": 0.0005, "length": 0.08,
                           "blade": [[0, 0, 0], [0, 0, 0.05]],
                           "pose": {"position": [0.0, 0.0, 0.2], "orientation": [0, 0, 0, 1]}}]
    with load_scene(cfg) as sim:
        n0, faces0 = sim.mesh.n_nodes, len(sim.surface_triangles())
        P = sim.mesh.points
        y = P[:, 1].min() + 0.0137
        z = P[:, 2].min() - 0.01
        sim.set_cutting(True)
        for x in np.arange(0.025, P[:, 0].max() + 0.01, 0.0012):
            sim.set_instrument_pose("scalpel", [x, y, z], [0, 0, 0, 1])
            assert sim.step().converged
        sim.set_cutting(False)
        assert sim.cutting.modifications >= 5
        parts = len(np.unique(sim.mesh.node_components()))
        assert len(sim.surface_triangles()) > faces0 + 20  # the crack's two faces
        dy = np.quantile(np.abs(sim.mesh.points[n0:, 1] - y), 0.9)  # the new nodes' distance to the blade
        if scheme == "subdivide":
            assert dy < 0.2 * 0.01  # within the snap distance (a few at the crack's ends may lie off it)
            assert tet_quality(sim.mesh.points, sim.mesh.tets).min() >= sim.cutting.min_quality
            assert parts == 1  # a crack, no loose pieces (the split scheme's staircase shaves some off)
        else:
            assert dy > 0.2 * 0.01  # on faces of the mesh, off the blade


def test_a_closed_ring_cut_parts_a_column_out_of_a_block():
    """Subdivision with the stroke's cut state: a vertical blade taller than a 5 cm block goes
    once around a 15 mm circle (0.6 mm a step, the path closing on itself). The block parts in
    exactly two pieces, no loose fragment, and the inner one is the cylinder of the circle: its
    rest volume within 15 % of pi R^2 h, its nodes within one element of the circle."""
    cfg = beam_scene(n_long=6, n_cross=6, scheme="subdivide", gravity=(0.0, 0.0, 0.0))
    cfg["cutting"].update({"instrument": "scalpel", "min_fragment": 0})  # nothing hidden as debris
    cfg["instruments"] = [{"name": "scalpel", "shape": "capsule", "radius": 0.0005, "length": 0.2,
                           "blade": [[0, 0, 0], [0, 0, 0.1]],
                           "pose": {"position": [0.0, 0.0, 0.3], "orientation": [0, 0, 0, 1]}}]
    with load_scene(cfg) as sim:
        P = sim.mesh.points
        c, R, h = 0.5 * (P.min(axis=0) + P.max(axis=0)), 0.015, np.ptp(P[:, 2])
        zb = P[:, 2].min() - 0.002
        n = int(np.ceil(2 * np.pi * R / 0.0006))
        sim.set_cutting(True)
        for k in range(n + 2):
            a = 2 * np.pi * k / n
            sim.set_instrument_pose("scalpel", [c[0] + R * np.cos(a), c[1] + R * np.sin(a), zb], [0, 0, 0, 1])
            assert sim.step().converged
        sim.set_cutting(False)
        mesh = sim.mesh
        lab = mesh.node_components()
        sizes = np.bincount(lab)
        assert len(sizes) == 2, sizes
        inner = np.argmin(sizes)
        in_tets = lab[mesh.tets[:, 0]] == inner
        vol = np.abs(mesh.signed_volumes()[in_tets]).sum()
        assert abs(vol / (np.pi * R ** 2 * h) - 1.0) < 0.15
        r = np.linalg.norm(mesh.points[:, :2] - c[:2], axis=1)
        assert r[lab == inner].max() < R + 0.01 and r[lab != inner].min() > R - 0.01
        assert tet_quality(mesh.points, mesh.tets).min() >= sim.cutting.min_quality


@pytest.mark.parametrize("extra, match", [
    ({"scheme": "mor-kanade"}, "scheme"), ({"snap": 0.5}, "snap"), ({"snap": 0}, "snap"),
    ({"lead": -0.001}, "lead"), ({"lead": float("nan")}, "lead"), ({"lead": "far"}, "lead"),
])
def test_bad_cutting_options_are_refused(extra, match):
    from soft_tissue_sim import ParameterError

    cfg = beam_scene()
    cfg["cutting"].update(extra)
    with pytest.raises(ParameterError, match=match):
        load_scene(cfg)


def test_a_chain_of_subdivision_sweeps_keeps_the_correction_exact():
    """Twenty sweeps of a blade 1.2 mm apart, each a modification (refinement and separation)
    chained on one factor: the corrected preconditioner stays the inverse of the new A."""
    rng = np.random.default_rng(5)
    cfg = beam_scene(n_long=12, n_cross=4, scheme="subdivide", gravity=(0.0, 0.0, 0.0), rotate=False)
    cfg["cutting"]["min_fragment"] = 0
    with load_scene(cfg) as sim:
        sim.step()
        P = sim.mesh.points
        y, z = P[:, 1].min() + 0.0137, P[:, 2].min() - 0.01
        xs = 0.025 + 0.0012 * np.arange(21)
        for x0, x1 in zip(xs[:-1], xs[1:]):
            sim.cut_triangles(sweep_triangles([x0, y, z], [x0, y, z + 0.05], [x1, y, z], [x1, y, z + 0.05]))
        terms = len(sim.preconditioner.inner.correction.terms)
        assert terms >= 2 and sim.mesh_version == terms
        assert corrected_vs_fresh(sim, rng) < 1e-9
        assert len(np.unique(sim.mesh.node_components())) == 1


@pytest.mark.parametrize("scheme", ["split", "subdivide"])
def test_rotated_correction_is_exact_on_a_rigidly_rotated_body(scheme):
    """Factor at rest, body then turned rigidly by Q (no strain): A = Q A_0 Q^T and every nodal
    rotation is Q, so the rotated preconditioner of eq. (2) is exact, and so must be the
    corrected one after a cut made in that state (eq. 8: the rotations D = Q around N)."""
    rng = np.random.default_rng(7)
    a = np.array([0.3, -1.0, 0.5]) / np.linalg.norm([0.3, -1.0, 0.5])
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    Q = np.eye(3) + np.sin(1.1) * K + (1 - np.cos(1.1)) * K @ K
    with load_scene(beam_scene(n_long=10, scheme=scheme, gravity=(0.0, 0.0, 0.0), fixed=False)) as sim:
        sim.step()  # the factor, at rest
        rest = sim.mesh.points
        sim.integrator.set_state(rest @ Q.T, np.zeros_like(rest))
        assert corrected_vs_fresh(sim, rng) < 1e-9  # eq. (2) exact under a rigid rotation
        res = lengthwise(sim, 0.0337, 0.0837, y=0.0013, frame="rest")
        assert res.changed
        assert corrected_vs_fresh(sim, rng) < 1e-9


def _uid_matrix(A, uids, size):
    """A (3n x 3n) moved to node-uid numbering (3 size x 3 size)."""
    idx = (3 * np.repeat(uids, 3) + np.tile(np.arange(3), len(uids))).astype(np.int64)
    C = A.tocoo()
    return sps.csr_matrix((C.data, (idx[C.row], idx[C.col])), shape=(3 * size, 3 * size))


def test_perturbation_nodes_are_the_nodes_where_the_matrix_left_the_factor():
    """The paper's "affected nodes" (eq. 5: N = G^T (P~ - P) G): every node whose rows of A
    differ from the factor's matrix, accumulated over the cuts since that factor, and back to
    one cut's nodes once a factor contains the earlier ones."""
    with load_scene(beam_scene(n_long=10, deterministic=True, refresh_every=1000, rotate=False)) as sim:
        sim.step()
        integ = sim.integrator
        pre = sim.preconditioner.inner
        sim.fem.update_rotations(integ.x)
        A0, uids0 = sim.fem.assemble_scipy(integ.m_coef, integ.k_coef), sim.node_uids.copy()
        r1 = lengthwise(sim, 0.005, 0.04)
        r2 = lengthwise(sim, 0.06, 0.095)
        assert r1.changed and r2.changed
        assert r1.perturbation_nodes == r1.affected_nodes  # the first change on this factor
        sim.fem.update_rotations(integ.x)
        A2, uids2 = sim.fem.assemble_scipy(integ.m_coef, integ.k_coef), sim.node_uids.copy()
        size = int(max(uids0.max(), uids2.max())) + 1
        D = (_uid_matrix(A2, uids2, size) - _uid_matrix(A0, uids0, size)).tocsr()
        D.data[np.abs(D.data) < 1e-9 * np.abs(A0.data).max()] = 0.0
        D.eliminate_zeros()
        changed = set((np.unique(D.indices) // 3).tolist()) | set(np.setdiff1d(uids2, uids0).tolist())
        pert = set(np.unique(np.concatenate([m.uids for m in pre.correction.mods])).tolist())
        assert changed <= pert  # N covers every change since the factor
        assert r2.perturbation_nodes == len(pert) > max(r1.affected_nodes, r2.affected_nodes)
        assert len(pert) >= 0.9 * len(changed)  # and little else (nodes whose blocks cancelled)
        pre._sync_refresh(sim.step_count)  # a factor containing both cuts
        assert pre.correction.perturbation_nodes() == 0
        r3 = crosswise(sim, 0.075)
        assert r3.changed and r3.perturbation_nodes == r3.affected_nodes


@pytest.mark.parametrize("scheme, step", [
    ("split", 0.0006), ("split", 0.0012), ("subdivide", 0.0012), ("subdivide", 0.0006), ("subdivide", 0.0003),
])
def test_a_blade_swept_across_the_beam_parts_it(scheme, step):
    """A vertical blade swept across the whole width of the beam (pedal down) parts it in two:
    every node ends in one of two connected pieces, each holding about half the nodes."""
    cfg = beam_scene(n_long=12, n_cross=4, scheme=scheme, gravity=(0.0, 0.0, 0.0))
    cfg["cutting"].update({"instrument": "scalpel", "min_fragment": 0})
    cfg["instruments"] = [{"name": "scalpel", "shape": "capsule", "radius": 0.0005, "length": 0.08,
                           "blade": [[0, 0, 0], [0, 0, 0.06]],
                           "pose": {"position": [0.0, 0.0, 0.2], "orientation": [0, 0, 0, 1]}}]
    with load_scene(cfg) as sim:
        P = sim.mesh.points
        x, z = 0.0537, P[:, 2].min() - 0.01
        sim.set_cutting(True)
        for y in np.arange(P[:, 1].min() - 0.003, P[:, 1].max() + 0.003, step):
            sim.set_instrument_pose("scalpel", [x, y, z], [0, 0, 0, 1])
            sim.step()
        sim.set_cutting(False)
        sizes = np.bincount(sim.mesh.node_components())
        assert len(sizes) == 2, sizes
        assert sizes.min() > 0.4 * sizes.sum(), sizes  # the cut at x = 0.054 of 0.12: about half each


# The reference of the exact blade test, in NumPy (the package's is a Warp kernel:
# soft_tissue_sim.cutting.geometry._section_meets): the same arithmetic, whole arrays at a time.
def _in_triangles(p, a, b, c, tol):
    """Whether points p (..., 3), already on the planes of the triangles (a, b, c) (broadcast
    against p), lie in them (+tol)."""
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = _dot(v0, v0), _dot(v0, v1), _dot(v1, v1)
    d20, d21 = _dot(v2, v0), _dot(v2, v1)
    den = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    rel = tol / np.sqrt(np.maximum(d00, d11))
    return (v >= -rel) & (w >= -rel) & (v + w <= 1.0 + rel)


_OTHERS = np.array([[j for j in range(4) if j != i] for i in range(4)])  # face i: the vertices but i


def _segments_meet_tets(segments, X, tol):
    """Mask (k,): does one of the segments (p0[i], p1[i]) (pairs of (k, 3) arrays) meet the tet
    X[i] (k, 4, 3)? (Clipping by the 4 faces, each moved out by ``tol``; all segments at once.)"""
    o = X[:, _OTHERS]  # (k, 4, 3, 3): face i's vertices
    nrm = cross(o[:, :, 1] - o[:, :, 0], o[:, :, 2] - o[:, :, 0])
    nrm *= np.sign(_dot(nrm, X - o[:, :, 0]))[..., None]  # inwards
    widen = tol * np.sqrt(_dot(nrm, nrm))
    p0 = np.stack([p for p, _ in segments], axis=1)  # (k, s, 3)
    p1 = np.stack([p for _, p in segments], axis=1)
    nrm = nrm[:, None]  # (k, 1, 4, 3) against the segments' (k, s, 1, 3)
    h0 = _dot(nrm, p0[:, :, None] - o[:, None, :, 0]) + widen[:, None]  # (k, s, 4): >= 0 inside (with tolerance)
    dh = _dot(nrm, (p1 - p0)[:, :, None])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -h0 / dh
    tmin = np.maximum(np.where(dh > 0.0, t, 0.0).max(axis=2), 0.0)
    tmax = np.minimum(np.where(dh < 0.0, t, 1.0).min(axis=2), 1.0)
    return np.any(~np.any((dh == 0.0) & (h0 < 0.0), axis=2) & (tmin <= tmax), axis=1)


def _sections_meet_triangles(X, tri, n, tol):
    """Mask (k,): does the section of the tet X[i] (k, 4, 3) by the plane of the triangle
    tri[i] (k, 3, 3; unit normal n[i]) overlap that triangle (+tol)? Yes when a crossing of a
    tet edge with the plane, or a tet vertex on it, lies inside the triangle, or when an edge
    of the triangle passes through the tet (a blade thinner than the element, or inside it)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    d = _dot(X - a[:, None], n[:, None])  # (k, 4) signed distances of the vertices
    di, dj = d[:, TET_EDGES[:, 0]], d[:, TET_EDGES[:, 1]]  # (k, 6)
    cross = di * dj < 0.0
    t = np.where(cross, di / np.where(cross, di - dj, 1.0), 0.0)
    Xi = X[:, TET_EDGES[:, 0]]
    p = Xi + t[..., None] * (X[:, TET_EDGES[:, 1]] - Xi)  # the edges' crossings, then the vertices
    p = np.concatenate([p, X], axis=1)
    p = p - _dot(p - a[:, None], n[:, None])[..., None] * n[:, None]  # on the plane
    inside = _in_triangles(p, a[:, None], b[:, None], c[:, None], tol)
    hit = np.any(np.concatenate([cross, np.abs(d) <= tol], axis=1) & inside, axis=1)
    return hit | _segments_meet_tets(((a, b), (b, c), (c, a)), X, tol)


def _reference_faces_cut(P, tets, tris, tol):
    """The split scheme's cut faces by brute force: every interior face found by sorting all
    faces, every tet of each triangle's bounding box (+tol) given the exact section test alone,
    every tet's side, every face looked at (no culling, no cache)."""
    from soft_tissue_sim.cutting.geometry import _path_planes
    from soft_tissue_sim.mesh import _FACES

    faces = tets[:, _FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    order = np.lexsort(key.T[::-1])
    ks = key[order]
    first = np.flatnonzero(np.all(ks[1:] == ks[:-1], axis=1))
    pairs = np.stack([order[first] // 4, order[first + 1] // 4], axis=1)
    cut = np.zeros(len(pairs), bool)
    hits = []
    for tri in tris:
        (a, b, c), n = tri, _path_planes(tri)[1]  # the blade's plane, as the cutter defines it
        if not len(n):
            hits.append(None)
            continue
        n = n[0]
        X = P[tets]
        lo, hi = np.minimum(np.minimum(a, b), c) - tol, np.maximum(np.maximum(a, b), c) + tol
        box = np.all((X.max(axis=1) >= lo) & (X.min(axis=1) <= hi), axis=1)
        d = _dot(X - a, n)
        straddle = (d.min(axis=1) <= tol) & (d.max(axis=1) >= -tol)
        hit = np.array([bool(box[i] and straddle[i] and _sections_meet_triangles(X[i:i + 1], np.array([[a, b, c]]),
                                                                              n[None], tol)[0])
                        for i in range(len(tets))])
        side = _dot(X.mean(axis=1) - a, n) >= 0.0
        cut |= (side[pairs[:, 0]] != side[pairs[:, 1]]) & (hit[pairs[:, 0]] | hit[pairs[:, 1]])
        hits.append(np.flatnonzero(hit))
    return pairs, ks[first], cut, hits


def _random_blades(rng, P, k):
    """Blade triangles around a mesh of points P: random sizes (a tenth of an element to the
    whole mesh), slivers, triangles with corners on nodes and in the planes of the grid."""
    lo, hi = P.min(axis=0), P.max(axis=0)
    h = float(np.min(hi - lo)) / 3.0
    out = []
    for i in range(k):
        kind = i % 4
        a = rng.uniform(lo - 0.1 * h, hi + 0.1 * h)
        if kind == 0:  # random size and shape
            s = h * 10.0 ** rng.uniform(-1.0, 0.7)
            out.append([a, a + s * rng.standard_normal(3), a + s * rng.standard_normal(3)])
        elif kind == 1:  # a sliver
            b = a + 2 * h * rng.standard_normal(3)
            out.append([a, b, b + 1e-4 * h * rng.standard_normal(3)])
        elif kind == 2:  # corners on mesh nodes
            out.append(list(P[rng.choice(len(P), 3, replace=False)]))
        else:  # in a grid plane through nodes, corners at nodes' coordinates
            ax = rng.integers(3)
            q = P[rng.choice(len(P), 3, replace=False)].copy()
            q[:, ax] = P[rng.integers(len(P)), ax]
            out.append(list(q))
    return np.array(out)


@pytest.mark.parametrize("jitter", [0.0, 0.2])
def test_culled_cut_faces_equal_the_brute_force_ones(jitter):
    """faces_cut_by_triangles (tets culled by the blade's box, faces looked up from the cut tets,
    the mesh's cached interior faces) and tets_cut_by_triangle give exactly the faces and tets
    of a brute-force search, on random blades, slivers and blades through nodes and grid planes."""
    from soft_tissue_sim.cutting.geometry import faces_cut_by_triangles
    from soft_tissue_sim.mesh import grid_mesh

    rng = np.random.default_rng(7)
    mesh = grid_mesh(np.linspace(0, 0.04, 5), np.linspace(0, 0.03, 4), np.linspace(0, 0.03, 4))
    P = mesh.points + jitter * 0.01 * rng.uniform(-0.5, 0.5, mesh.points.shape)
    tets = mesh.tets.astype(np.int64)
    n_cut = n_hit = 0
    for tol in (1e-12, 1e-4):
        for _ in range(10):
            tris = _random_blades(rng, P, 4)
            pairs, fnodes, cut, hits = _reference_faces_cut(P, tets, tris, tol)
            got = faces_cut_by_triangles(P, tets, tris, tol, faces=mesh.interior_faces())
            np.testing.assert_array_equal(got[0], pairs)
            np.testing.assert_array_equal(got[1], fnodes)
            np.testing.assert_array_equal(got[2], cut)
            np.testing.assert_array_equal(faces_cut_by_triangles(P, tets, tris, tol)[2], cut)  # faces not given
            for tri, hit in zip(tris, hits):
                mine, side = tets_cut_by_triangle(P, tets, tri, tol)
                if hit is None:
                    assert side is None and not len(mine)
                else:
                    np.testing.assert_array_equal(np.sort(mine), hit)
                    n_hit += len(hit)
            n_cut += int(cut.sum())
    assert n_cut > 100 and n_hit > 100  # the blades did cut


def _touching_blades(rng, P, tol):
    """Blade triangles beyond a face of the box of the points P whose box, widened by ``tol``,
    reaches that face exactly (gap tol), overlaps it (gap 0 or tol / 2) or misses it (gap 2 tol
    or a hair over tol); every third one parallel to the face. Returns the triangles and
    whether each one's widened box reaches the points' box. (Dyadic coordinates and ``tol``
    keep the touching exact.)"""
    lo, hi = P.min(axis=0), P.max(axis=0)
    tris, reach = [], []
    for i in range(48):
        ax, upper = i % 3, (i // 3) % 2 == 0
        gap = (0.0, 0.5 * tol, tol, 2.0 * tol, None)[(i // 6) % 5]
        tri = rng.uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), (3, 3))
        depth = np.zeros(3) if i % 3 == 0 else np.array([0.0, *rng.uniform(0.0, 0.5 * (hi - lo)[ax], 2)])
        face = hi[ax] if upper else lo[ax]
        beyond = face + tol if gap is None else face + gap if upper else face - gap
        if gap is None:  # a hair more than tol away
            beyond = np.nextafter(face + tol, np.inf) if upper else np.nextafter(face - tol, -np.inf)
        tri[:, ax] = beyond + depth if upper else beyond - depth
        tris.append(tri)
        reach.append(gap is not None and gap <= tol)
    return np.array(tris), np.array(reach)


@pytest.mark.parametrize("tol", [0.0, 2.0**-8])
def test_the_blades_box_cull_agrees_with_the_full_tests_on_blades_touching_a_beam(tol):
    """The box cull of the split scheme (one pass over all tets for the whole path, then each
    triangle's box on the tets' coordinates) keeps exactly the tets of a full bounding-box test
    and of :func:`tets_near_box`, and the culled cut (faces, tets) equals the brute-force one:
    on random blades around a beam and on blades whose box just touches, overlaps or misses a
    face of the beam's box (by a hair), some lying flat against it."""
    from soft_tissue_sim.cutting.geometry import _near_triangles, faces_cut_by_triangles, tets_near_box
    from soft_tissue_sim.mesh import beam_mesh

    rng = np.random.default_rng(5)
    mesh = beam_mesh(8, n_cross=4, spacing=0.25)  # coordinates in quarters: exact
    P, tets = mesh.points, mesh.tets.astype(np.int64)
    X = P[tets]
    touching, reached = _touching_blades(rng, P, tol)
    n_touch = 0
    for i in range(0, len(touching), 4):
        for tris in (touching[i:i + 4], _random_blades(rng, P, 4)):
            lo, hi = tris.min(axis=1) - tol, tris.max(axis=1) + tol
            full = np.all((X.max(axis=1)[None] >= lo[:, None]) & (X.min(axis=1)[None] <= hi[:, None]), axis=2)
            owner, j = _near_triangles(X, tris, tol)
            np.testing.assert_array_equal(owner, np.nonzero(full)[0])
            np.testing.assert_array_equal(j, np.nonzero(full)[1])
            for k in range(len(tris)):
                np.testing.assert_array_equal(tets_near_box(P, tets, lo[k], hi[k]), np.flatnonzero(full[k]))
            pairs, fnodes, cut, hits = _reference_faces_cut(P, tets, tris, tol)
            got = faces_cut_by_triangles(P, tets, tris, tol, faces=mesh.interior_faces())
            np.testing.assert_array_equal(got[2], cut)
            for tri, hit in zip(tris, hits):
                if hit is not None:
                    np.testing.assert_array_equal(np.sort(tets_cut_by_triangle(P, tets, tri, tol)[0]), hit)
        lo_t, hi_t = touching[i:i + 4].min(axis=1) - tol, touching[i:i + 4].max(axis=1) + tol
        box = np.all((lo_t <= P.max(axis=0)) & (hi_t >= P.min(axis=0)), axis=1)
        np.testing.assert_array_equal(box, reached[i:i + 4])  # the blades touch and miss as meant
        for k in range(4):
            near = tets_near_box(P, tets, lo_t[k], hi_t[k])
            assert bool(len(near)) == reached[i + k]
            n_touch += len(near)
    assert n_touch > 50  # the touching blades did reach tets


def _beam_at_rest(scheme):
    """A small beam at rest as a cutter's Tissue, and a cutter of ``scheme`` keeping every fragment."""
    from soft_tissue_sim.cutting import Cutter, Tissue
    from soft_tissue_sim.mesh import beam_mesh

    mesh = beam_mesh(8, n_cross=4, spacing=0.01)
    n = mesh.n_nodes
    tissue = Tissue(mesh, mesh.points.copy(), np.zeros((n, 3)), np.arange(n, dtype=np.int64), np.ones(n))
    return tissue, Cutter({"scheme": scheme, "min_fragment": 0})


@pytest.mark.parametrize("scheme", ["split", "subdivide"])
def test_the_face_table_a_cut_or_a_removal_hands_on_equals_the_recomputed_one(scheme):
    """The new mesh of a cut (random blades through a beam, one after the other) and of a
    removal carries its interior-face table where the change derives it: exactly the table
    computed afresh from its tets."""
    from soft_tissue_sim.cutting import Tissue
    from soft_tissue_sim.mesh import interior_faces

    rng = np.random.default_rng(11)
    tissue, cutter = _beam_at_rest(scheme)
    carried = 0
    for _ in range(25):
        P = tissue.mesh.points
        tris = _random_blades(rng, P, 2)
        tissue.mesh.interior_faces()  # as cut_triangles reads it (split); the removal finds it cached
        plan = cutter.cut_triangles(tissue, tris, frame="rest")
        if plan.change is None:
            continue
        gone = np.zeros(plan.change.mesh.n_tets, bool)
        gone[rng.integers(plan.change.mesh.n_tets)] = True
        c = plan.change
        for m in (c.mesh, None):
            if m is None:  # a removal on the mesh the cut made
                c.mesh.interior_faces()
                r = cutter.remove_tets(Tissue(c.mesh, c.x, c.v, c.node_uids, c.free), gone)
                m = r.change.mesh
            got = m.cached_interior_faces()
            if got is not None:
                carried += 1
                for a, b in zip(got, interior_faces(m.tets)):
                    np.testing.assert_array_equal(a, b)
        tissue = Tissue(c.mesh, c.x, c.v, c.node_uids, c.free)
    assert carried >= (20 if scheme == "split" else 3)  # split: the cuts' and removals' tables; subdivide: removals


@pytest.mark.parametrize("scheme", ["split", "subdivide"])
def test_the_edge_table_a_cut_or_a_removal_hands_on_equals_the_recomputed_one(scheme):
    """Every change (a cut of either scheme, a removal with node compaction) gives the new mesh
    the edge table derived from the old one's: exactly the table computed afresh, and the node
    ring and parts that follow from it are those of the new tets."""
    import scipy.sparse as sps
    from scipy.sparse.csgraph import connected_components

    from soft_tissue_sim.cutting import Tissue
    from soft_tissue_sim.mesh import edge_table

    rng = np.random.default_rng(12)
    tissue, cutter = _beam_at_rest(scheme)
    carried = 0
    for _ in range(25):
        tissue.mesh.edge_table()
        plan = cutter.cut_triangles(tissue, _random_blades(rng, tissue.mesh.points, 2), frame="rest")
        if plan.change is None:
            continue
        c = plan.change
        gone = np.zeros(c.mesh.n_tets, bool)
        gone[rng.integers(c.mesh.n_tets, size=3)] = True
        r = cutter.remove_tets(Tissue(c.mesh, c.x, c.v, c.node_uids, c.free), gone)
        for m in (c.mesh, r.change.mesh):
            got = m.cached_edge_table()
            assert got is not None
            carried += 1
            for a, b in zip(got, edge_table(m.tets)):
                np.testing.assert_array_equal(a, b)
            T = m.tets.astype(np.int64)
            g = sps.coo_matrix((np.ones(3 * len(T)), (np.repeat(T[:, 0], 3), T[:, 1:].ravel())), shape=(m.n_nodes,) * 2)
            np.testing.assert_array_equal(m.node_components(), connected_components(g, directed=False)[1])
        tissue = Tissue(c.mesh, c.x, c.v, c.node_uids, c.free)
    assert carried >= (20 if scheme == "split" else 10)


def test_the_removal_sphere_takes_the_tets_of_all_centroids_within_it():
    """remove_elements tests only the tets whose box meets the sphere's: it removes exactly the
    tets whose centroid, computed for every tet, lies within the radius (spheres of every size,
    centred inside, on and beyond the body, some on nodes and tet centroids)."""
    from soft_tissue_sim.mesh import centroids

    rng = np.random.default_rng(5)
    with load_scene(beam_scene(n_long=8, n_cross=4)) as sim:
        tissue = sim.tissue()
        P, T = tissue.mesh.points, tissue.mesh.tets
        cen = centroids(P, T)
        lo, hi = P.min(axis=0), P.max(axis=0)
        centres = [rng.uniform(lo - 0.01, hi + 0.01) for _ in range(40)] + list(P[::17]) + list(cen[::23])
        for c in centres:
            for r in (1e-4, 0.003, 0.006, 0.0125, float(np.linalg.norm(cen[7] - c)), 0.05):
                expect = np.flatnonzero(np.linalg.norm(cen - c, axis=1) <= r)
                plan = sim.cutting.remove_elements(tissue, c, r, frame="rest")
                got = np.zeros(0, np.int64) if plan.change is None else np.sort(plan.change.removed_tets)
                if len(expect) == len(T):  # refused: it would remove every element
                    assert plan.change is None
                else:
                    assert np.array_equal(got, expect), (c, r)


def test_the_edge_list_parts_are_scipys_labels():
    """edge_components gives scipy's connected_components labels of an undirected edge list
    (the parts numbered by their lowest vertex), on random graphs (isolated vertices, repeated
    edges, loops, long paths, none)."""
    from scipy.sparse.csgraph import connected_components

    from soft_tissue_sim.mesh import edge_components

    rng = np.random.default_rng(3)
    for trial in range(60):
        n = int(rng.integers(1, 200))
        m = int(rng.integers(0, 2 * n))
        ea, eb = rng.integers(0, n, m), rng.integers(0, n, m)
        if trial % 5 == 0:  # a path in random order
            perm = rng.permutation(n)
            ea, eb = perm[:-1], perm[1:]
        label = edge_components(n, ea, eb)
        g = sps.coo_matrix((np.ones(len(ea)), (ea, eb)), shape=(n, n))
        ref = connected_components(g, directed=False)[1]
        np.testing.assert_array_equal(label, ref)


def _reference_split(tets, cut, pairs, fnodes, n_nodes):
    """Node splitting node by node: at each node of a cut face (ascending), its tets (ascending)
    grouped by scipy through the uncut interior faces at the node; each group after the first
    (groups in the order of their lowest tet) gets the next copy of the node."""
    from scipy.sparse.csgraph import connected_components

    new, source = tets.copy(), []
    for v in np.unique(fnodes[cut]):
        at = np.flatnonzero(np.any(tets == v, axis=1))
        joins = np.flatnonzero(~cut & np.any(fnodes == v, axis=1))
        a, b = np.searchsorted(at, pairs[joins, 0]), np.searchsorted(at, pairs[joins, 1])
        g = sps.coo_matrix((np.ones(len(joins)), (a, b)), shape=(len(at), len(at)))
        label = connected_components(g, directed=False)[1]
        for part in range(1, label.max() + 1):
            rows = at[label == part]
            new[rows] = np.where(new[rows] == v, n_nodes + len(source), new[rows])
            source.append(v)
    return new, np.array(source, np.int64)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_split_along_faces_equals_a_node_by_node_split(seed):
    """split_along_faces (given the mask of the cut faces, or matching them by their nodes)
    copies exactly the nodes, and relabels exactly the tets, of a plain node-by-node split
    on random face sets of a beam."""
    from soft_tissue_sim.cutting.topology import split_along_faces
    from soft_tissue_sim.mesh import beam_mesh

    rng = np.random.default_rng(seed)
    mesh = beam_mesh(8, n_cross=4, spacing=0.01)
    tets = mesh.tets.astype(np.int64)
    pairs, fnodes, _ = mesh.interior_faces()
    copies = 0
    for _ in range(20):
        cut = rng.random(len(pairs)) < rng.choice([0.0, 0.01, 0.1, 0.5])
        expect = _reference_split(tets, cut, pairs, fnodes, mesh.n_nodes)
        for got in (split_along_faces(tets, pairs[cut], fnodes[cut], pairs, fnodes, mesh.n_nodes),
                    split_along_faces(tets, pairs[cut], fnodes[cut], pairs, fnodes, mesh.n_nodes, cut=cut)):
            np.testing.assert_array_equal(got[0], expect[0])
            np.testing.assert_array_equal(got[1], expect[1])
            assert got[1].dtype == np.int64
            assert (got[0] is tets) == (not len(expect[1]))  # a copy only where nodes are copied
        copies += len(expect[1])
    assert copies > 0


def test_the_planners_row_and_extent_shortcuts_equal_numpys():
    """The planner's equal-rows mask and bounding-box extent give np.all(a == b, axis=1) and
    np.ptp(points, axis=0).max(), for C- and Fortran-ordered tets."""
    from soft_tissue_sim.mesh import all_four, extent

    rng = np.random.default_rng(2)
    for _ in range(10):
        a, b = rng.integers(0, 3, (200, 4)), rng.integers(0, 3, (200, 4))
        for x, y in ((a, b), (np.asfortranarray(a), b), (a, np.asfortranarray(b)), (a, a.copy())):
            np.testing.assert_array_equal(all_four(np.equal(x, y)), np.all(x == y, axis=1))
        p = rng.standard_normal((50, 3)) * rng.uniform(0.1, 10.0, 3)
        assert extent(p) == float(np.ptp(p, axis=0).max())


def test_the_blade_kernel_is_loaded_when_the_cutter_is_made(monkeypatch):
    """A blade's sweep is planned by a kernel on Warp's CPU device (the split scheme's faces):
    its module is loaded when the cutter is made, so that the first plan in the middle of a run
    builds nothing (a build stalls that step by its time). The module is unloaded first, so the
    cutter's construction, not an earlier test, must have loaded it."""
    from warp._src import context

    from soft_tissue_sim.cutting import geometry

    module = context.get_module(geometry.__name__)
    module.unload()
    tissue, cutter = _beam_at_rest("split")
    builds = []
    load = context.Module.load

    def record(self, device, block_dim=None, *args, **kwargs):
        if not self.execs.get((wp.get_device(device).context, block_dim or self.options["block_dim"])):
            builds.append(self.name)
        return load(self, device, block_dim, *args, **kwargs)

    monkeypatch.setattr(context.Module, "load", record)
    lo, hi = tissue.x.min(axis=0), tissue.x.max(axis=0)
    mid = 0.5 * (lo + hi)
    tris = sweep_triangles([hi[0] + 0.001, mid[1], lo[2] - 0.001], [hi[0] + 0.001, mid[1], hi[2] + 0.001],
                           [mid[0], mid[1], lo[2] - 0.001], [mid[0], mid[1], hi[2] + 0.001])
    plan = cutter.cut_triangles(tissue, tris)
    assert plan.result.faces_cut > 0  # the kernel ran and found the blade's faces
    assert not builds, builds


def test_the_integrators_launches_after_the_solve_replay_across_a_cut():
    """The update of x and v, the guard's reduction, a correction and the state's copy run over
    the FEM's node capacity and read the node count on the device: their key holds across a cut
    that keeps the allocations, and a graph of them captured before the cut (Warp's CPU graph
    capture) gives after it what plain launches give."""
    from soft_tissue_sim.buffers import GrowArray

    with load_scene(beam_scene(pre="jacobi"), device="cpu") as sim:
        sim.step()
        integ = sim.integrator
        n0, key0 = sim.fem.n_nodes, integ._state_arrays_key()
        dx_buf, copies = GrowArray(wp.vec3d, "cpu"), (GrowArray(wp.vec3d, "cpu"), GrowArray(wp.vec3d, "cpu"))
        cap = 2 * n0
        dx, x0, v0 = dx_buf.view(cap), copies[0].view(cap), copies[1].view(cap)

        def launches():
            integ._launch_update()
            integ.launch_guard()
            integ.correct(dx)
            integ.copy_state(x0, v0)

        with wp.ScopedCapture(device="cpu") as cap_:
            launches()
        assert lengthwise(sim, 0.015, 0.035).changed
        n1 = sim.fem.n_nodes
        assert n1 > n0 and integ._state_arrays_key() == key0
        rng = np.random.default_rng(3)
        start = [rng.standard_normal((n1, 3)) for _ in range(3)]

        def run(replay):
            integ.x.assign(start[0])
            integ.v.assign(start[1])
            integ.dv.assign(start[2])
            dx.assign(np.concatenate([0.01 * start[0], np.zeros((cap - n1, 3))]))
            if replay:
                wp.capture_launch(cap_.graph)
            else:
                launches()
            return [a.numpy()[:n1].copy() for a in (integ.x, integ.v, x0, v0)] + [integ._guard.numpy().copy()]

        replayed, plain = run(True), run(False)
        for a, b in zip(replayed, plain):
            np.testing.assert_array_equal(a, b)
        assert not np.array_equal(replayed[0], start[0])


@pytest.mark.parametrize("k", [1, 7, 40])
def test_perturbation_is_the_rotated_change_with_the_identity_padding(k):
    """N of eq. (5) equals D^T dA D with D the block diagonal of R_i R_ref_i^T (dense, built
    here), symmetrized, -I on the added free nodes and +I on the removed free ones."""
    from scipy.linalg import block_diag
    from scipy.spatial.transform import Rotation

    from soft_tissue_sim.sherman_morrison import Modification, perturbation

    rng = np.random.default_rng(k)
    uids = np.sort(rng.choice(10 * k + 5, k, replace=False))
    dA = rng.standard_normal((3 * k, 3 * k))
    R = Rotation.random(k, random_state=k).as_matrix()
    R_ref = Rotation.random(k, random_state=k + 1).as_matrix()
    free = (rng.random(k) < 0.8).astype(np.float64)
    created, removed = uids[: (k + 1) // 2], uids[(k + 1) // 2:][:1]
    mod = Modification(3, uids, dA, R, free, created, removed)
    D = block_diag(*(R[i] @ R_ref[i].T for i in range(k)))
    ref = D.T @ dA @ D
    ref = 0.5 * (ref + ref.T)
    pad = np.where(np.isin(uids, created), -1.0, 0.0) + np.where(np.isin(uids, removed), 1.0, 0.0)
    ref += np.diag(np.repeat(pad * free, 3))
    N = perturbation(mod, R_ref, created)
    np.testing.assert_allclose(N, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    assert np.array_equal(N, N.T)
    unrotated = perturbation(mod, R_ref, created, rotate=False)
    ref0 = 0.5 * (dA + dA.T) + np.diag(np.repeat(pad * free, 3))
    np.testing.assert_allclose(unrotated, ref0, rtol=0, atol=1e-12 * np.abs(ref0).max())
