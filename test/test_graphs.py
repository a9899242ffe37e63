"""Replaced CUDA graphs are parked and released where no factorization runs (soft_tissue_sim.graphs).

Releasing a graph waits for the whole device on CUDA; the logic of when that happens runs the
same on Warp's CPU backend, where the PCG is captured as a Warp graph too.
``STS_TEST_DEVICE=cuda:0`` runs these on a GPU.
"""

import os
import warnings

import numpy as np
import pytest
import warp as wp

from soft_tissue_sim import graphs, load_scene
from test_cutting import crosswise

DEVICE = os.environ.get("STS_TEST_DEVICE", "cpu")


@pytest.fixture(autouse=True)
def _empty_park():
    graphs.release()
    yield
    graphs.release()


def _graph():
    """A graph object that owns no CUDA graph (its release is free)."""
    return wp.Graph(wp.get_device("cpu"), 0)


def test_retire_keeps_graphs_until_release_and_ignores_other_values():
    g = _graph()
    graphs.retire(g)
    graphs.retire(None)
    graphs.retire("seen")  # the detection's marker of a key seen once
    graphs.retire_all([False, _graph()])
    assert graphs.parked() == 2
    assert graphs.release() == 2
    assert graphs.parked() == 0


def test_the_park_is_bounded(monkeypatch):
    monkeypatch.setattr(graphs, "MAX_PARKED", 3)
    for _ in range(4):
        graphs.retire(_graph())
    assert graphs.parked() == 0  # the fourth went over the bound: all released
    graphs.retire(_graph())
    assert graphs.parked() == 1


def _captured_sim():
    sim = load_scene("test_small.yaml", device=DEVICE,
                     overrides={"solver": {"graph": "true", "preconditioner": "jacobi"}})
    for _ in range(3):  # uncaptured, captured, replayed
        sim.step()
    assert sim.integrator.cg.captures >= 1 and sim.integrator.cg.replay.latest() is not None
    return sim


def test_a_resized_pcg_parks_its_graph_and_a_step_without_factorization_releases_it():
    with _captured_sim() as sim:
        cg = sim.integrator.cg
        old = cg.replay.latest()
        cg.resize(cg.n + 1)  # within the work vectors' capacity: the graph holds
        assert cg.replay.latest() is old and graphs.parked() == 0
        cg.resize(10 * cg.n)  # beyond it: new vectors, the graph is parked
        assert cg.replay.latest() is None and graphs.parked() == 1
        assert graphs._parked[0] is old
        captures = cg.captures
        sim.step()
        assert graphs.parked() == 0
        assert cg.captures == captures + 1  # a new key is captured at its first solve once kernels are loaded


def test_graphs_stay_parked_while_the_preconditioner_factorizes():
    with _captured_sim() as sim:
        sim.preconditioner.factorizing = lambda: True
        cg = sim.integrator.cg
        cg.replay.clear()
        sim.step()
        assert graphs.parked() == 1  # a release now would wait for the factorization
        sim.preconditioner.factorizing = lambda: False
        sim.step()
        assert graphs.parked() == 0


def test_a_reset_retires_the_captured_detections():
    with load_scene("default.yaml", device=DEVICE) as sim:
        sim.step()
        topo = sim.contact._topo
        assert topo is not None
        topo.replay._graphs[("key",)] = _graph()
        topo.replay._seen[("other",)] = True
        sim.preconditioner.factorizing = lambda: True  # keep them parked to look at them
        sim.contact.reset()
        assert sim.contact._topo is None and graphs.parked() == 1 and not topo.replay._seen


def test_the_same_trajectory_with_graphs_replaced_by_resizes():
    """Parking changes when graphs are released, never what a solve computes."""
    with _captured_sim() as a, _captured_sim() as b:
        for k in range(4):
            if k % 2 == 0:
                b.integrator.cg.replay.clear()  # b re-captures every other step
            a.step()
            b.step()
        # equal up to the order of the FEM kernels' atomic sums on a GPU (bit for bit on the CPU)
        np.testing.assert_allclose(a.positions(), b.positions(), rtol=0.0, atol=1e-12)


def test_the_captured_build_replays_the_plain_launches_and_is_recaptured_for_new_arguments():
    """build()'s launches captured once per build_key (at its second build) and replayed give the
    steps of plain launches; a new key (here dt) is captured anew, the old graph parked."""
    ov = {"solver": {"graph": "true", "preconditioner": "async_ldlt",
                     "ldlt": {"backend": "dense", "deterministic": True}}}
    with load_scene("test_small.yaml", device=DEVICE, overrides=ov) as a, \
            load_scene("test_small.yaml", device=DEVICE, overrides=ov) as b:
        assert a.integrator.graph_steps and a.integrator.node_rotations_in_build
        b.integrator.graph_steps = False
        for _ in range(4):
            a.step()
            b.step()
        key = a.integrator.build_key()
        first = a.integrator._build_replay.graph(key)
        assert first is not None and b.integrator._build_replay.graph(b.integrator.build_key()) is None
        np.testing.assert_allclose(a.positions(), b.positions(), rtol=0.0, atol=1e-12)
        for sim in (a, b):
            sim.integrator.dt *= 0.5
        for _ in range(3):
            a.step()
            b.step()
        replay = a.integrator._build_replay
        assert replay.graph(key) is None and replay.graph(a.integrator.build_key()) is not None
        assert replay.captures == 2 and replay.replays >= 4
        np.testing.assert_allclose(a.positions(), b.positions(), rtol=0.0, atol=1e-12)
        np.testing.assert_allclose(a.velocities(), b.velocities(), rtol=0.0, atol=1e-10)


def test_a_replayer_launches_plainly_then_captures_then_replays_and_retires_beyond_its_slots():
    """Replayer: a key's first run is plain, its second captured and launched, later ones replay
    the graph (same results); the least recently used graph beyond the slots is retired; a capture
    that fails turns capturing off with a warning, launches still done."""
    a = wp.zeros(4, dtype=wp.float64, device=DEVICE)
    runs = []

    def launches(value):
        runs.append(value)
        a.fill_(value)

    rep = graphs.Replayer(DEVICE, "test", slots=1)
    for k in range(3):
        rep.run(("one",), lambda: launches(1.0))
        np.testing.assert_array_equal(a.numpy(), 1.0)
        a.zero_()
    assert runs == [1.0, 1.0] and rep.captures == 1 and rep.replays == 2  # plain, captured, replayed
    first = rep.graph(("one",))
    for _ in range(2):
        rep.run(("two",), lambda: launches(2.0))
    assert rep.graph(("two",)) is not None and rep.graph(("one",)) is None and graphs.parked() == 1
    assert first is not None
    rep.run(None, lambda: launches(3.0))  # no key: plain
    np.testing.assert_array_equal(a.numpy(), 3.0)

    def failing():
        if wp.get_device(DEVICE).is_capturing:
            raise RuntimeError("not capturable")
        launches(4.0)

    bad = graphs.Replayer(DEVICE, "test", slots=1)
    bad.run(("k",), failing)
    with pytest.warns(RuntimeWarning, match="graph capture failed"):
        bad.run(("k",), failing)
    assert not bad.enabled and runs[-1] == 4.0 and bad.captures == 0
    rep.clear()
    assert rep.graph(("two",)) is None and graphs.parked() == 2


def test_an_eager_replayer_captures_new_keys_at_their_first_use():
    """eager: the first key as any (plain, then captured), later keys captured at once;
    not eager: every key plain first."""
    a = wp.zeros(4, dtype=wp.float64, device=DEVICE)
    plain = graphs.Replayer(DEVICE, "test")
    eager = graphs.Replayer(DEVICE, "test", eager=True)
    seen = {}
    for rep in (plain, eager):
        captured = []
        for key in ("one", "one", "two", "three"):
            c = rep.captures
            rep.run((key,), lambda: a.fill_(1.0))
            captured.append(rep.captures > c)
        seen[rep] = captured
    assert seen[plain] == [False, True, False, False]
    assert seen[eager] == [False, True, True, True]
    assert [rep.counts() for rep in (plain, eager)] == [
        {"captures": 1, "replays": 1, "plain": 3}, {"captures": 3, "replays": 3, "plain": 1}]
    none = graphs.Replayer(DEVICE, "test")
    none.run(None, lambda: a.fill_(1.0))  # no key: plain launches
    assert none.counts() == {"captures": 0, "replays": 0, "plain": 1}
    for rep in (plain, eager):
        rep.clear()
    # a capture at a key's first use that fails (as an allocation in a capture does): plain
    # launches, the key captured at its next use, capturing left on and nothing warned
    runs = []

    def allocating():
        if wp.get_device(DEVICE).is_capturing and not runs:
            raise RuntimeError("cannot allocate during a capture")
        runs.append(1)
        a.fill_(2.0)

    rep = graphs.Replayer(DEVICE, "test", eager=True)
    for _ in range(2):  # a first key captured: new keys are captured at their first use
        rep.run(("first",), lambda: a.fill_(1.0))
    assert rep.captures == 1 and rep.replays == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rep.run(("new",), allocating)
        assert runs == [1] and rep.captures == 1 and rep.enabled and rep.failures == 0
        rep.run(("new",), allocating)
    assert rep.captures == 2 and rep.replays == 2
    np.testing.assert_array_equal(a.numpy(), 2.0)
    rep.clear()


def test_a_mesh_change_within_the_capacities_keeps_the_step_graphs():
    """A removal changes the node and tet counts, the surface's nodes and faces, but not the
    allocations: the build's, the PCG's and the graph after the solve (the update, the detection
    of the new surface, the rows, the LCP, the correction, the guard: launches over capacities
    that read the counts on the device) replay across it, none captured again; the new surface
    keeps the detection's replayer. The trajectory is that of plain launches
    (test_the_captured_build_... and below)."""
    with _pressed_block(True, cutting=True) as sim:
        top = float(sim.mesh.points[:, 2].max())
        for k in range(4):
            sim.set_instrument_pose("probe", [0.021, 0.011, top + 0.004 - 0.0005 * k], [0, 0, 0, 1])
            sim.step()
        integ = sim.integrator
        build, after, pcg = integ._build_replay, integ._after_replay, integ.cg.replay
        assert build.captures >= 1 and after.captures >= 1 and pcg.captures >= 1
        counts = (build.captures, after.captures, pcg.captures)
        replays = (build.replays, pcg.replays)
        old = sim.contact._topo
        n = (sim.mesh.n_nodes, sim.mesh.n_tets)
        assert sim.remove_elements(sim.positions()[-1], 0.012).changed
        assert (sim.mesh.n_nodes, sim.mesh.n_tets) != n
        after_replays = after.replays
        for _ in range(3):
            sim.step()
        assert (build.captures, after.captures, pcg.captures) == counts
        assert build.replays == replays[0] + 3 and pcg.replays == replays[1] + 3
        assert after.replays == after_replays + 3
        assert sim.contact._topo is not old and sim.contact._topo.replay is old.replay


def _change(sim, kind: str, k: int):
    """A removal of the tets around a node, or a cut across the block's upper half (nodes added)."""
    if kind == "removal":
        return sim.remove_elements(sim.positions()[-1 - k], 0.008)
    return crosswise(sim, 0.005 * k + 0.0175, upper_half=True)


@pytest.mark.parametrize("kind", ["removal", "cut"])
def test_graphs_replayed_across_mesh_changes_give_the_steps_of_plain_launches(kind):
    """Two removals (node counts down) or two cuts (up), the step's graphs (the build's, the
    PCG's, the one after the solve: detection, rows, LCP, correction) replayed across both: the
    same trajectory as plain launches (bit for bit on the CPU; on a GPU up to the order of
    atomic sums)."""
    with _pressed_block(True, cutting=True) as a, _pressed_block(False, cutting=True) as b:
        top = float(a.mesh.points[:, 2].max())
        after = a.integrator._after_replay
        for k in range(9):
            if k == 3:
                captured = after.captures
            for sim in (a, b):
                sim.set_instrument_pose("probe", [0.021, 0.011, top + 0.004 - 0.0005 * k], [0, 0, 0, 1])
                if k in (3, 6):
                    n = sim.mesh.n_nodes
                    assert _change(sim, kind, k).changed
                    assert (sim.mesh.n_nodes > n) == (kind == "cut")
                sim.step()
            assert a.mesh.n_nodes == b.mesh.n_nodes and a.mesh.n_tets == b.mesh.n_tets
            np.testing.assert_allclose(a.positions(), b.positions(), rtol=0.0, atol=1e-12)
            np.testing.assert_allclose(a.velocities(), b.velocities(), rtol=0.0, atol=1e-10)
        assert a.integrator.cg.replay.captures == 1 and a.integrator._build_replay.captures == 1
        assert after.captures == captured >= 1  # the changes kept its key
        assert b.integrator.cg.replay.captures == 0


def _pressed_block(graph: bool, cutting: bool = False, device_rows: bool = True):
    cfg = {"name": "pressed", "device": DEVICE,
           "mesh": {"generator": "beam", "n_long": 8, "n_cross": 3, "spacing": 0.01},
           "materials": [{"id": 0, "young": 2.0e4, "poisson": 0.4, "density": 1000.0}],
           "fixed": {"axis": "z", "below": 0.001}, "gravity": [0.0, 0.0, -9.81], "time": {"dt": 0.01},
           "solver": {"tolerance": 1e-9, "preconditioner": "async_ldlt", "graph": "true" if graph else "false",
                      "ldlt": {"backend": "dense", "deterministic": True}},
           "instruments": [{"name": "probe", "shape": "capsule", "radius": 0.004, "length": 0.05}],
           "contact": {"distance": 0.001, "friction": 0.3, "self_collision": True, "device_rows": device_rows}}
    if cutting:
        cfg["cutting"] = {"correction": "sherman_morrison", "scheme": "split"}
    return load_scene(cfg)


@pytest.mark.parametrize("device_rows", [False, True])
def test_the_captured_contact_launches_give_the_steps_of_plain_launches(device_rows):
    """After the solve (the update, the detection of the free motion, the guard, the copies
    read) and after the contact response (the correction, the detection after it, the guard;
    with the rows on the device, the whole contact step after the solve), captured and
    replayed: the same positions, penetrations and guard readings as plain launches."""
    out = {}
    for graph in (True, False):
        with _pressed_block(graph, device_rows=device_rows) as sim:
            top = float(sim.mesh.points[:, 2].max())
            pens, contacts = [], []
            for k in range(7):
                sim.set_instrument_pose("probe", [0.021, 0.011, top + 0.004 - 0.0005 * k], [0, 0, 0, 1])
                st = sim.step()
                pens.append(st.contact.max_penetration)
                contacts.append(st.contact.contacts)
            rep, after = sim.integrator._correction_replay, sim.integrator._after_replay
            out[graph] = (sim.positions(), np.array(pens), rep.captures, rep.replays, sim._ke_state[0])
            assert contacts[-1] > 0  # the probe is in contact: the correction moves the tissue
            assert (after.captures >= 1 and after.replays >= 2) == graph
    (x1, p1, c1, r1, ke1), (x0, p0, c0, r0, ke0) = out[True], out[False]
    assert (c1 >= 1 and r1 >= 2) != device_rows and c0 == 0 and r0 == 0  # device rows: no correction graph
    np.testing.assert_allclose(x1, x0, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(p1, p0, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(ke1, ke0, rtol=1e-9)
