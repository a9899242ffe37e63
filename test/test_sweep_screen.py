"""The blade's sweep screened on the body's device (soft_tissue_sim.cutting.screen): its mask is
the host plan's, and a screened plan reads the body's state only for a sweep that cuts. Warp's
CPU backend by default; ``STS_TEST_DEVICE=cuda:0`` runs it on a GPU."""

import os

import numpy as np
import pytest
import warp as wp

from soft_tissue_sim import load_scene
from soft_tissue_sim.cutting import Tissue
from soft_tissue_sim.cutting.geometry import _path_planes, faces_cut_by_triangles
from soft_tissue_sim.cutting.screen import MAX_TRIANGLES, SweepScreen
from soft_tissue_sim.mesh import beam_mesh, grid_mesh
from test_cutting import _random_blades, beam_scene

DEVICE = os.environ.get("STS_TEST_DEVICE", "cpu")


@pytest.mark.parametrize("jitter", [0.0, 0.2])
def test_the_screens_mask_is_the_host_plans(jitter):
    """On random blades (1 to 4 triangles, slivers, corners on nodes, in grid planes) around two
    meshes taken in turn, ten blades each (the screen's tables follow the mesh it is given; its
    marks of one blade are not the next one's, also where its count wraps), the screen's mask
    equals faces_cut_by_triangles' on the same positions, and it declines more triangles than
    it holds."""
    rng = np.random.default_rng(3)
    meshes = [grid_mesh(np.linspace(0, 0.04, 5), np.linspace(0, 0.03, 4), np.linspace(0, 0.03, 4)),
              beam_mesh(6, n_cross=3, spacing=0.01)]
    screen = SweepScreen(DEVICE)
    cut_faces = 0
    for i in range(40):
        mesh = meshes[(i // 10) % 2]
        if i == 25:
            screen._stamp = np.iinfo(np.int32).max - 1  # the count wraps at the next blade but one
        P = mesh.points + jitter * 0.01 * rng.uniform(-0.5, 0.5, mesh.points.shape)
        x = wp.array(P, dtype=wp.vec3d, device=DEVICE)
        tets = wp.array(mesh.tets, dtype=wp.vec4i, device=DEVICE)
        tris, nrm = _path_planes(_random_blades(rng, P, 1 + i % 4))
        tol = (1e-12, 1e-4)[(i // 2) % 2]
        got = screen.faces_cut(x, tets, mesh, tris, nrm, tol)
        want = faces_cut_by_triangles(P, mesh.tets.astype(np.int64), tris, tol, faces=mesh.interior_faces(),
                                      normals=nrm)[2]
        np.testing.assert_array_equal(got, want)
        cut_faces += int(want.sum())
    assert cut_faces > 50  # the blades did cut
    many = np.repeat(tris[:1], MAX_TRIANGLES + 1, axis=0)
    assert screen.faces_cut(x, tets, mesh, many, np.repeat(nrm[:1], MAX_TRIANGLES + 1, axis=0), 1e-12) is None


def test_a_tissue_reads_its_state_once_at_the_first_look():
    """A Tissue made with a read function calls it at the first access of its state, once; one
    made from arrays has its state at hand."""
    mesh = beam_mesh(2, n_cross=2, spacing=0.01)
    n = mesh.n_nodes
    calls = []

    def read():
        calls.append(1)
        return mesh.points + 1.0, np.ones((n, 3)), np.ones(n), None

    t = Tissue(mesh, node_uids=np.arange(n), read=read)
    assert not t.loaded and not calls
    np.testing.assert_array_equal(t.v, np.ones((n, 3)))
    np.testing.assert_array_equal(t.x, mesh.points + 1.0)
    assert t.dv is None and t.loaded and len(calls) == 1
    assert Tissue(mesh, mesh.points, np.zeros((n, 3)), np.arange(n), np.ones(n)).loaded


def _swept_beam(screen):
    """A blade swept lengthwise through a beam in small steps, pedal down, the sweeps screened
    or not; returns the positions, the mesh's tets, the plans' results and whether each plan's
    tissue was read."""
    cfg = beam_scene(n_long=12, n_cross=4, gravity=(0.0, 0.0, 0.0))
    cfg["device"] = DEVICE
    cfg["cutting"].update({"instrument": "scalpel", "min_fragment": 0})
    cfg["instruments"] = [{"name": "scalpel", "shape": "capsule", "radius": 0.0005, "length": 0.08,
                           "blade": [[0, 0, 0], [0, 0, 0.05]],
                           "pose": {"position": [0.0, 0.0, 0.2], "orientation": [0, 0, 0, 1]}}]
    with load_scene(cfg) as sim:
        sim.cutting.screen = screen
        made, results = [], []
        tissue, cut = sim.tissue, sim.cutting.cut

        def keep_tissue():
            made.append(tissue())
            return made[-1]

        def keep_result(t, instruments):
            plan = cut(t, instruments)
            results.append((plan.change is not None, plan.result.message))
            return plan

        sim.tissue, sim.cutting.cut = keep_tissue, keep_result
        P = sim.mesh.points
        y, z = P[:, 1].min() + 0.0137, P[:, 2].min() - 0.01
        sim.set_cutting(True)
        for x in np.arange(0.025, P[:, 0].max() + 0.01, 0.0012):
            sim.set_instrument_pose("scalpel", [x, y, z], [0, 0, 0, 1])
            assert sim.step().converged
        return sim.positions(), sim.mesh.tets.copy(), results, [t.loaded for t in made]


def test_a_screened_sweep_reads_the_state_only_where_it_cuts():
    """The blade's sweeps screened on the device (as on a GPU) give the same cuts, messages and
    trajectory as the host's plans, and only the sweeps that change the mesh read the body's
    state; unscreened, every sweep reads it."""
    x1, tets1, res1, read1 = _swept_beam(True)
    x0, tets0, res0, read0 = _swept_beam(False)
    assert res1 == res0
    np.testing.assert_array_equal(tets1, tets0)
    np.testing.assert_allclose(x1, x0, rtol=0, atol=1e-12)
    changed = [c for c, _ in res1]
    assert sum(changed) >= 5 and len(changed) > sum(changed) + 5  # sweeps that cut, and sweeps that did not
    assert all(read0[1:])  # the first only records the blade
    assert read1 == changed
