"""One detection, one read: every object's contacts from one set of output slots, the step's
start and each node's motion computed on the device, the smallest gap reduced there
(soft_tissue_sim.contact.detection). Warp's CPU backend by default; ``STS_TEST_DEVICE=cuda:0``
runs the same checks on a GPU and compares its contact steps with the CPU's."""

import os

import numpy as np
import pytest
import warp as wp

from soft_tissue_sim import load_scene

DEVICE = os.environ.get("STS_TEST_DEVICE", "cpu")

TOOLS = [{"name": "probe", "shape": "capsule", "radius": 0.004, "length": 0.05},
         {"name": "scalpel", "shape": "capsule", "radius": 0.0005, "length": 0.05, "blade": [[0, 0, 0], [0, 0, 0.01]]}]


def _scene(device):
    return {"name": "pressed", "device": device,
            "mesh": {"generator": "beam", "n_long": 8, "n_cross": 3, "spacing": 0.01},
            "materials": [{"id": 0, "young": 2.0e4, "poisson": 0.4, "density": 1000.0}],
            "fixed": {"axis": "z", "below": 0.001}, "gravity": [0.0, 0.0, -9.81], "time": {"dt": 0.01},
            "solver": {"tolerance": 1e-9, "preconditioner": "async_ldlt", "ldlt": {"deterministic": True}},
            "instruments": TOOLS,
            "obstacles": [{"name": "wall", "type": "plane", "point": [-0.0005, 0.0, 0.0], "normal": [1.0, 0.0, 0.0]}],
            "contact": {"distance": 0.001, "friction": 0.3, "self_collision": True}}


def _press(sim, depth):
    """Probe and scalpel upright over the top, ``depth`` into it."""
    top = float(sim.mesh.points[:, 2].max())
    sim.set_instrument_pose("probe", [0.021, 0.011, top + 0.004 - depth], [0, 0, 0, 1])
    sim.set_instrument_pose("scalpel", [0.052, 0.009, top - depth], [0, 0, 0, 1])


def test_one_read_detection_matches_the_geometry_and_the_reduced_gap():
    """The node rows of the probe are exactly the surface nodes within ``distance`` of its
    capsule (numpy reference), the plane's rows the nodes within ``distance`` of the wall, and
    the device's smallest gap equals the smallest gap of the rows read back."""
    with load_scene(_scene(DEVICE)) as sim:
        _press(sim, 0.002)
        for inst in sim.contact.instruments.values():
            inst.begin_step()
        c = sim.contact.detect(sim)
        x = sim.positions()
        surface = np.unique(sim.mesh.boundary_faces())
        a, b = sim.contact.instrument("probe").segment_world()
        p = x[surface]
        t = np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
        gap = np.linalg.norm(p - (a + t[:, None] * (b - a)), axis=1) - 0.004
        expect = surface[gap < 0.001]
        assert len(expect) > 0
        rows = (c.obj == 0) & (c.node >= 0)
        np.testing.assert_array_equal(np.sort(c.node[rows]), np.sort(expect))
        np.testing.assert_allclose(c.gap[rows][np.argsort(c.node[rows])], gap[gap < 0.001][np.argsort(expect)],
                                   atol=1e-12)
        wall = c.obj == 2
        np.testing.assert_array_equal(np.sort(c.node[wall]), np.sort(surface[x[surface, 0] + 0.0005 < 0.001]))
        # the reduction on the device of the same detection's gaps
        topo = sim.contact._topo
        g = sim.contact.launch_penetration(sim)
        assert float(g.numpy()[0]) == pytest.approx(float(sim.contact.detect(sim, x_start=topo.x_start).gap.min()),
                                                    abs=0.0)


def test_the_step_reports_the_penetration_left_and_the_device_matches_the_cpu():
    """A pressed block: contacts found and answered, the penetration left after the
    correction a small fraction of the press; on a GPU the same steps as on the CPU."""
    runs = {}
    for dev in dict.fromkeys([DEVICE, "cpu"]):
        with load_scene(_scene(dev)) as sim:
            pens, forces = [], []
            for k in range(6):
                _press(sim, 0.0005 * k)
                st = sim.step()
                pens.append(st.contact.max_penetration)
                forces.append(sim.instrument_wrench("probe")[0])
            runs[dev] = (sim.positions(), np.array(pens), np.array(forces))
    x, pens, forces = runs[DEVICE]
    assert forces[-1][2] > 0.0  # the tissue pushes the probe up
    assert 0.0 <= pens[-1] < 0.2 * 0.0025
    if DEVICE != "cpu":
        xc, pc, fc = runs["cpu"]
        np.testing.assert_allclose(x, xc, atol=1e-9)
        np.testing.assert_allclose(forces, fc, rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(pens, pc, atol=1e-9)


def test_the_detection_read_with_the_free_motion_gives_the_same_steps(monkeypatch):
    """With a device factor (the dense backend; NumPy on the CPU) the solve is only launched, and
    the contact detection is launched after it and read in the same wait (the integrator's
    ``after_solve``): one detection a step, the contact step reads none, and the steps, forces
    and wrenches equal those of a simulation that detects in its contact step."""
    runs = {}
    for early in (True, False):
        cfg = _scene(DEVICE)
        cfg["solver"]["ldlt"] = {"backend": "dense", "deterministic": True}
        cfg["contact"]["device_rows"] = False  # the rows from the read detection, on the host
        with load_scene(cfg) as sim:
            if not early:
                sim.integrator.after_solve = None
            launches = []  # the host side of a detection (its launches may be a replayed graph)
            real = sim.contact.prepare
            monkeypatch.setattr(sim.contact, "prepare", lambda *a, **k: launches.append(1) or real(*a, **k))
            forces, counts = [], []
            for k in range(6):
                _press(sim, 0.0005 * k)
                st = sim.step()
                counts.append(st.contact.contacts)
                forces.append(np.concatenate(sim.instrument_wrench("probe")))
                assert (sim.integrator.after_solve_reading is not None) == early
            assert len(launches) == 6  # one detection a step, wherever it is launched
            runs[early] = (sim.positions(), np.array(forces), counts)
    (x1, f1, c1), (x0, f0, c0) = runs[True], runs[False]
    assert c1 == c0 and c1[-1] > 0
    if DEVICE == "cpu":  # the same arithmetic in the same order
        np.testing.assert_array_equal(x1, x0)
        np.testing.assert_array_equal(f1, f0)
    else:  # a GPU's atomic sums are added in any order
        np.testing.assert_allclose(x1, x0, rtol=0.0, atol=1e-12)
        np.testing.assert_allclose(f1, f0, rtol=1e-8, atol=1e-12)


def test_a_retried_free_motion_keeps_the_instruments_step_poses(monkeypatch):
    """The detection launched with a free motion that the guard then rejects: the retried free
    motion launches it again, and the instruments take their poses once a step (the pose before
    the step stays the previous step's), so the steps equal those of a simulation whose guard
    never fired."""
    runs = {}
    for fire in (True, False):
        cfg = _scene(DEVICE)
        cfg["solver"]["ldlt"] = {"backend": "dense", "deterministic": True}
        with load_scene(cfg) as sim:
            real = sim._diverged
            fired = []

            def diverged(stats, ke_before, real=real, fired=fired):
                if fire and sim.integrator.step_index == 3 and not fired:
                    fired.append(1)
                    return "test: rejected once"
                return real(stats, ke_before)

            monkeypatch.setattr(sim, "_diverged", diverged)
            poses = []
            for k in range(5):
                _press(sim, 0.0005 * k)
                sim.step()
                probe = sim.contact.instrument("probe")
                poses.append((probe.previous_step_pose.position.copy(), probe.step_pose.position.copy()))
            assert bool(fired) == fire
            runs[fire] = (sim.positions(), poses, sim.rollbacks)
    (x1, p1, r1), (x0, p0, r0) = runs[True], runs[False]
    assert r1 == 1 and r0 == 0
    for (a1, b1), (a0, b0) in zip(p1, p0):
        np.testing.assert_array_equal(a1, a0)
        np.testing.assert_array_equal(b1, b0)
    # the retry refactorizes (a fresh factor), so the state differs only within the solver tolerance
    np.testing.assert_allclose(x1, x0, rtol=0.0, atol=1e-8)


def test_the_device_lcp_module_is_built_only_for_its_own_block_sizes(monkeypatch):
    """Warp builds a module once per block size it is launched with. The device LCP's module
    (tile kernels, long to build) is launched by its block alone (LANES, or WIDE_LANES beyond
    the narrow kernel's rows): the host LCP's path, taken here for every set (device_lcp_rows
    0, a dense factor), launches none of its kernels plainly, which would build the whole
    module again for another block size in the middle of a run."""
    from warp._src import context

    from soft_tissue_sim.contact import device_lcp

    loads = []
    load = context.Module.load

    def record(self, device, block_dim=None, *args, **kwargs):
        loads.append((self.name, block_dim))
        return load(self, device, block_dim, *args, **kwargs)

    monkeypatch.setattr(context.Module, "load", record)
    cfg = _scene(DEVICE)
    cfg["solver"]["ldlt"]["backend"] = "dense"
    cfg["contact"]["device_lcp_rows"] = 0
    with load_scene(cfg) as sim:
        for k in range(4):
            _press(sim, 0.0005 * k)
            st = sim.step()
        assert st.as_dict().get("contacts", 0) > 0 and not st.as_dict().get("lcp_device")
    sizes = {b for name, b in loads if name == device_lcp.__name__ and b is not None}
    assert sizes <= {device_lcp.LANES, device_lcp.WIDE_LANES}, sizes


def test_no_kernel_module_is_built_after_the_first_step(monkeypatch):
    """Every module the contact steps launch is loaded by the time the first step ends, even
    where the first contacts come later and go through the host LCP's path (device_lcp_rows 0,
    a dense factor): a build in the middle of a run stalls that step by the build's time."""
    from warp._src import context

    cfg = _scene(DEVICE)
    cfg["solver"]["ldlt"]["backend"] = "dense"
    cfg["contact"]["device_lcp_rows"] = 0
    cfg["obstacles"] = []
    with load_scene(cfg) as sim:
        _press(sim, -0.05)  # far above: no contact in the first step
        assert sim.step().as_dict().get("contacts", 0) == 0
        loads = []
        load = context.Module.load

        def record(self, device, block_dim=None, *args, **kwargs):
            if not self.execs.get((wp.get_device(device).context, block_dim or self.options["block_dim"])):
                loads.append((self.name, block_dim))
            return load(self, device, block_dim, *args, **kwargs)

        monkeypatch.setattr(context.Module, "load", record)
        for k in range(4):
            _press(sim, 0.0005 * k)
            st = sim.step()
        assert st.as_dict().get("contacts", 0) > 0
    assert not loads, loads
