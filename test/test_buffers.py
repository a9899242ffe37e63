"""Device arrays kept across mesh changes (soft_tissue_sim.buffers): a change reuses them and
gives the very numbers of arrays made afresh; the cost of a cut is measured whole."""

import hashlib

import numpy as np
import warp as wp

from soft_tissue_sim import buffers, load_scene
from soft_tissue_sim.buffers import GrowArray, PackedArrays
from soft_tissue_sim.contact.detection import SurfaceTopology
from soft_tissue_sim.corotational_fem import CorotationalFEM

from test_cutting import beam_scene, crosswise, lengthwise


def test_a_grow_array_is_a_prefix_of_one_allocation_until_outgrown():
    g = GrowArray(wp.float64, "cpu", fill=1.0)
    a = g.view(10)
    assert a.shape == (10,) and g.capacity >= 12 and g.allocations == 1 and np.all(a.numpy() == 1.0)
    assert g.view(10) is a  # the same view while the size holds
    b = g.view(5)
    assert b.ptr == a.ptr and b.shape == (5,) and g.allocations == 1
    c = g.view(g.capacity + 1)
    assert g.allocations == 2 and c.ptr != a.ptr and np.all(c.numpy() == 1.0)
    ramp = GrowArray(wp.int32, "cpu", fill=lambda cap: np.arange(cap, dtype=np.int32))
    assert np.array_equal(ramp.view(7).numpy(), np.arange(7))


def test_packed_arrays_send_what_was_written_and_reallocate_only_when_outgrown():
    p = PackedArrays({"x": wp.vec3d, "i": wp.int32, "m": wp.mat33d}, "cpu")
    assert p.reserve({"x": 4, "i": 3, "m": 2})
    x, i, m = np.arange(12.0).reshape(4, 3), np.array([7, 8, 9], np.int32), np.arange(18.0).reshape(2, 3, 3)
    for name, v in (("x", x), ("i", i), ("m", m)):
        p.host(name)[...] = v
    p.send(("x", "i", "m"))
    assert np.array_equal(p.array("x").numpy(), x) and np.array_equal(p.array("i").numpy(), i)
    assert np.array_equal(p.array("m").numpy(), m)
    assert all(p.offsets[k] % buffers.ALIGN == 0 for k in p.fields)
    ptr = p.array("x").ptr
    assert not p.reserve({"x": 3, "i": 3, "m": 2})  # smaller: the same allocation, the i and m data kept
    assert p.array("x").ptr == ptr and p.array("x").shape == (3,) and np.array_equal(p.array("m").numpy(), m)
    assert p.reserve({"x": 100, "i": 3, "m": 2}) and p.allocations == 2
    p.host("x")[...] = np.arange(300.0).reshape(100, 3)
    p.send(("x",))
    assert np.array_equal(p.alias("x", wp.float64, 6).numpy(), np.arange(6.0))


def _contact_beam(scheme="split"):
    cfg = beam_scene(n_long=10, n_cross=3, scheme=scheme)
    cfg["instruments"] = [{"name": "probe", "shape": "capsule", "radius": 0.004, "length": 0.05,
                           "pose": {"position": [0.08, 0.015, 0.026], "orientation": [0, 0, 0, 1]}}]
    cfg["contact"] = {"distance": 0.002, "self_collision": True}
    cfg["cutting"]["min_fragment"] = 5
    return cfg


def _changes(sim):
    """A cut, a removal, more cuts (the node count grows past the first allocation's headroom)."""
    P = sim.mesh.points
    yield lambda: lengthwise(sim, 0.045, 0.1)
    yield lambda: sim.remove_elements(P[np.argmax(P[:, 0] + P[:, 2])], 0.012, frame="rest")
    for x in (0.035, 0.055, 0.075):
        yield lambda x=x: crosswise(sim, x)


def _fresh_every_time(monkeypatch):
    """Every view and reserve makes a new allocation, its elements NaN or -1 until written;
    a grow-only array keeps only what its last view held (a view's contents last while the
    size does: the element rotations taken over in place)."""
    def poisoned(n, dtype, device):
        a = wp.empty(n, dtype=dtype, device=device)
        a.numpy().view(np.uint8)[...] = 0xFF  # NaN in floats, -1 in integers
        return a

    def view(self, n):
        if self.fill is None:
            old = self._view
            self.buffer = poisoned(max(buffers.capacity_for(int(n)), self.capacity), self.dtype, self.device)
            self.allocations += 1
            self._view = None
            if old is not None:
                k = min(old.shape[0], int(n))
                wp.copy(self.buffer, old, count=k)
        else:
            self.buffer = None
        return orig_view(self, n)

    def reserve(self, counts):
        self.buffer = None
        grew = orig_reserve(self, counts)
        self.buffer.numpy()[...] = 0xFF
        return grew

    orig_view, orig_reserve = GrowArray.view, PackedArrays.reserve
    monkeypatch.setattr(GrowArray, "view", view)
    monkeypatch.setattr(PackedArrays, "reserve", reserve)


def _run(steps_between=2):
    """Changes with steps between and after them: the hash of every state and contact count."""
    h = hashlib.sha256()
    with load_scene(_contact_beam()) as sim:
        for _ in range(3):
            sim.step()
        for change in _changes(sim):
            assert change().changed
            for _ in range(steps_between):
                st = sim.step().as_dict()
                h.update(sim.positions().tobytes() + sim.velocities().tobytes())
                h.update(repr((st["iterations"], st["residual"], st.get("contacts"))).encode())
        return h.hexdigest(), sim.mesh.n_nodes


def test_arrays_kept_across_changes_give_the_results_of_fresh_ones(monkeypatch):
    """The same cuts and removals, with steps and contact between them: the kept allocations
    and allocations made afresh for every change (filled with NaN and -1 until written, so that
    a read of something not written would show) give bit-identical states and statistics."""
    kept, n_kept = _run()
    _fresh_every_time(monkeypatch)
    fresh, n_fresh = _run()
    assert n_kept == n_fresh and kept == fresh


def test_after_changes_every_array_equals_a_fresh_build():
    """After each change the FEM's rest data equals a FEM built on the new mesh, and the
    surface rebuilt on the kept arrays equals a fresh one (and detects the same contacts)."""
    with load_scene(_contact_beam()) as sim:
        sim.step()
        for change in _changes(sim):
            assert change().changed
            fem = sim.fem
            fresh = CorotationalFEM(sim.mesh, sim.materials, "cpu", fixed_nodes=fem.fixed_nodes)
            for name in ("rest", "tets", "Dm_inv", "volume", "mu", "lam", "rho", "lumped_mass", "free"):
                assert np.array_equal(getattr(fem, name).numpy(), getattr(fresh, name).numpy()), name
            topo = sim.contact._topo
            assert topo.matches(fem)  # rebuilt by the change, not left to the next step
            new = SurfaceTopology(fem, True, sim.contact.objects)
            for name in ("counts", "nodes", "faces_wp", "edge_owner", "node_comp", "face_comp", "ring_offsets",
                         "ring_nodes", "x_start"):
                assert np.array_equal(getattr(topo, name).numpy(), getattr(new, name).numpy()), name
            nf = len(new.faces)  # the boxes: those of the faces, then the capacity's unused slots' outside
            for name in ("lowers", "uppers"):
                assert np.array_equal(getattr(topo, name).numpy()[:nf], getattr(new, name).numpy()[:nf]), name
            for t in (topo, new):  # a point below the faces' boxes (beyond every query: their extent away)
                lo, up = t.lowers.numpy(), t.uppers.numpy()
                assert len(lo) >= nf and np.array_equal(lo[nf:], up[nf:]) and np.isfinite(lo).all()
                assert (lo[nf:] < lo[:nf].min(axis=0)).all()
                # each in a cell of its own of the GPU LBVH's Morton grid (1024 a side over the
                # bounds of all boxes): boxes sharing a code make a chain of that builder
                box_lo, box_up = lo.min(axis=0), up.max(axis=0)
                cells = np.clip(((0.5 * (lo + up)[nf:] - box_lo) / (box_up - box_lo) * 1024).astype(int), 0, 1023)
                assert len(np.unique(cells, axis=0)) == len(lo) - nf
            assert len(new.lowers) > nf  # a fresh build has unused slots (headroom)
            assert ([(s.obj, s.kind, s.count) for s in topo.out.sections]
                    == [(s.obj, s.kind, s.count) for s in new.out.sections])
            got = sim.contact.detect(sim)
            sim.contact._topo = new
            ref = sim.contact.detect(sim)
            sim.contact._topo = topo
            for k in ("node", "obj", "gap", "normal", "point", "tri", "bary"):
                assert np.array_equal(getattr(got, k), getattr(ref, k)), k
            sim.step()


def test_rotations_around_some_nodes_equal_those_of_all_tets():
    """node_rotations_around: the element rotations of the tets around some nodes and those
    nodes' rotations, from those tets alone, are the numbers of the full update (the others
    are NaN); update_rotations of some tets leaves the others as they were."""
    with load_scene(_contact_beam()) as sim:
        for _ in range(4):
            sim.step()
        fem, x = sim.fem, sim.integrator.x
        before = fem.rotations.numpy().copy()
        nodes = np.array([3, 40, 41, 70, fem.n_nodes - 1])
        need = np.zeros(fem.n_nodes, bool)
        need[nodes] = True
        around = np.flatnonzero(need[fem.mesh.tets].any(axis=1))
        R = fem.node_rotations_around(x, around, nodes)
        part = fem.rotations.numpy().copy()
        fem.update_rotations(x)
        full_tets, full_nodes = fem.rotations.numpy().copy(), fem.node_rotations()
        assert np.array_equal(R[nodes], full_nodes[nodes]) and np.isnan(np.delete(R, nodes, axis=0)).all()
        assert np.array_equal(part[around], full_tets[around])
        others = np.setdiff1d(np.arange(fem.n_tets), around)
        assert np.array_equal(part[others], before[others]) and not np.array_equal(before, full_tets)
        fem.rotations.assign(before)
        fem.update_rotations(x, tets=others[::3])
        after = fem.rotations.numpy()
        assert np.array_equal(after[others[::3]], full_tets[others[::3]])
        assert np.array_equal(np.delete(after, others[::3], axis=0), np.delete(before, others[::3], axis=0))


def test_a_change_that_fits_keeps_the_arrays_addresses():
    """Once allocated, a cut keeps the addresses of the FEM's, the state's, the solver's and the
    surface's arrays (views of the kept allocations): nothing is allocated or uploaded anew."""
    with load_scene(_contact_beam()) as sim:
        sim.step()
        assert lengthwise(sim, 0.065, 0.1).changed
        sim.step()
        fem, integ, topo = sim.fem, sim.integrator, sim.contact._topo

        def addresses():
            t = sim.contact._topo
            return [a.ptr for a in (fem.rest, fem.tets, fem.Dm_inv, fem.rotations, fem.free, fem._vals, integ.x,
                                    integ.v, integ.f, integ.b, integ.cg.r, t.nodes, t.faces_wp, t.x_start,
                                    t.out.active, t.ring_nodes)]

        before = addresses()
        assert lengthwise(sim, 0.045, 0.066).changed
        assert sim.contact._topo is not topo and addresses() == before
        assert fem._packed.allocations == 1 and integ._state.allocations == 1


def test_a_cut_step_reports_its_whole_host_cost_and_the_surface_part():
    """The blade cutting in a step: the step's cut_ms holds the surface's rebuild (surface_ms,
    done in the cutting phase, so the next step's detection finds the surface current); a cut
    asked through the API reports the same in its result."""
    cfg = _contact_beam()
    cfg["cutting"].update({"instrument": "scalpel", "min_fragment": 0})
    cfg["instruments"].append({"name": "scalpel", "shape": "capsule", "radius": 0.0005, "length": 0.08,
                               "blade": [[0, 0, 0], [0, 0, 0.05]],
                               "pose": {"position": [0.0, 0.0, 0.2], "orientation": [0, 0, 0, 1]}})
    with load_scene(cfg) as sim:
        P = sim.mesh.points
        y, z = P[:, 1].min() + 0.0137, P[:, 2].min() - 0.01
        sim.set_cutting(True)
        cut_steps = 0
        for x in np.arange(0.03, 0.08, 0.004):
            sim.set_instrument_pose("scalpel", [x, y, z], [0, 0, 0, 1])
            d = sim.step().as_dict()
            assert d["cut_ms"] > 0.0  # the blade's sweep is planned every step
            if d["tets_changed"]:
                cut_steps += 1
                assert d["cut_ms"] >= d["surface_ms"] > 0.0
                # its parts: each measured, together within the phase (its reads and the
                # sweep's planning besides)
                parts = [d[k] for k in ("plan_ms", "apply_ms", "correction_ms", "debris_ms")]
                assert all(p > 0.0 for p in parts) and sum(parts) + d["surface_ms"] <= d["cut_ms"]
                topo = sim.contact._topo
                assert topo.matches(sim.fem)
                sim.set_cutting(False)
                sim.step()
                assert sim.contact._topo is topo  # not rebuilt in the next step
                sim.set_cutting(True)
            else:
                assert d["surface_ms"] == 0.0
                assert d["plan_ms"] == d["apply_ms"] == d["correction_ms"] == d["debris_ms"] == 0.0
        assert cut_steps >= 2
        sim.set_cutting(False)
        r = crosswise(sim, 0.085)
        assert r.changed and r.ms >= r.surface_ms > 0.0
        assert r.ms >= r.plan_ms + r.apply_ms + r.correction_ms + r.debris_ms + r.surface_ms
        assert min(r.plan_ms, r.apply_ms, r.correction_ms, r.debris_ms) > 0.0
        assert sim.contact._topo.matches(sim.fem)
