"""The contact rows built on the device (soft_tissue_sim.contact.device_rows): the detection,
the rows, the LCP and the correction launched with the free motion give the steps of the rows
built on the host; the warm start by slot; the fall back to the host beyond the row limit and
where the device cannot build them.

Warp's CPU backend by default (the dense factor with NumPy and LAPACK); ``STS_TEST_DEVICE=cuda:0``
runs the same on a GPU.
"""

import os

import numpy as np
import pytest

from soft_tissue_sim import load_scene
from soft_tissue_sim.contact import solver as contact_solver
from test_contact import u_scene

DEVICE = os.environ.get("STS_TEST_DEVICE", "cpu")
# a self contact's point on the moving triangle is summed in another order than NumPy's (and the GPU
# scatters H^T lambda with atomic adds, its PGS uses FMA): rounding, carried by the sweeps (which
# stop at the 1e-8 m tolerance) from step to step and by a self contact on an edge taking the
# other triangle, under that tolerance
EXACT = 1e-9


def _u_scene(tmp_path, device_rows, rows=64, graph=True, spatula=None, **contact):
    """A U lying on its side (the soft upper arm sags onto the clamped lower arm: self contacts)
    with two capsules' tips pressed into the upper arm's top (node and face contacts),
    frictionless unless ``contact`` says (``spatula``: the spatula's own options)."""
    cfg = u_scene(tmp_path, instruments=[{"name": "probe", "shape": "capsule", "radius": 0.003, "length": 0.05},
                                         {"name": "spatula", "shape": "capsule", "radius": 0.002, "length": 0.05,
                                          **(spatula or {})}],
                  contact={"self_collision": True, "device_lcp_rows": rows, "active_set": False,
                           "device_rows": device_rows, "penetration_every": 3, **contact})
    cfg["device"] = DEVICE
    cfg["solver"]["ldlt"].update(backend="dense")
    cfg["solver"]["graph"] = graph
    return cfg


def _press(cfg, steps=40):
    """The probe's tip (radius 3 mm) lowered into the sagging upper arm's top between its nodes
    over the first 20 steps, then held; the spatula's (2 mm) onto a node beside it, tilted."""
    tilt = [np.sin(0.2), 0.0, 0.0, np.cos(0.2)]
    with load_scene(cfg) as sim:
        top = sim.positions()[:, 2].max()
        out = []
        for k in range(steps):
            s = min(1.0, k / 20)
            sim.set_instrument_pose("probe", [0.025, 0.0, top + 0.0035 - 0.0065 * s], [0.0, 0.0, 0.0, 1.0])
            sim.set_instrument_pose("spatula", [0.015, 0.005, top + 0.0025 - 0.004 * s], tilt)
            s = sim.step().extra
            c = sim.contact.contacts
            wrenches = np.concatenate([np.concatenate(sim.contact.wrench(n)) for n in ("probe", "spatula")])
            out.append((s, sim.positions(), wrenches, c.node.copy(), c.obj.copy(), c.tri.copy(), c.force.copy(),
                        c.normal.copy()))
        return out, sim.integrator._after_replay.replays


FRICTION = {"friction": 0.3}


@pytest.mark.parametrize("graph, rows, contact, spatula", [
    (False, 64, {}, None), (True, 64, {}, None), (True, 32, {}, None),
    (True, 160, FRICTION, None), (False, 160, {**FRICTION, "friction_cone": "pyramid"}, None),
    (True, 160, FRICTION, {"friction": 0.0}),
    (True, 160, {**FRICTION, "active_set": True, "friction_active_set": True}, None)])
def test_rows_built_on_the_device_give_the_host_rows_steps(tmp_path, graph, rows, contact, spatula):
    """Self contacts, an instrument's node and face contacts, a warm start from the step before,
    with friction (tangent rows: the tissue's and the tools' motion in the step; both cones; a
    tool of its own coefficient 0 beside the scene's 0.3) or without: with the rows built on the
    device every step is the host rows' (positions, wrench, contacts and their forces, the
    sweeps, the statistics), in the graph after the solve."""
    host, _ = _press(_u_scene(tmp_path, False, graph=graph, rows=rows, spatula=spatula, **contact))
    dev, replays = _press(_u_scene(tmp_path, True, graph=graph, rows=rows, spatula=spatula, **contact))
    kinds = {"self_contacts": 0, "face_contacts": 0}
    for (sh, xh, wh, *ch), (sd, xd, wd, *cd) in zip(host, dev):
        assert sd["rows_device"] is True and "rows_device" not in sh
        for key in ("contacts", "self_contacts", "face_contacts", "active_contacts", "gs_iterations"):
            assert sd.get(key) == sh.get(key), key
        assert ("max_penetration" in sd) == ("max_penetration" in sh)
        for key in kinds:
            kinds[key] = max(kinds[key], sd.get(key, 0))
        for a, b in zip(cd[:2], ch[:2]):  # the contacts' nodes and objects (a self contact on an edge
            np.testing.assert_array_equal(a, b)  # may take either triangle: the states differ by rounding)
        np.testing.assert_allclose(cd[3], ch[3], rtol=1e-6, atol=1e-7)  # [N]: a contact barely pressed may differ
        np.testing.assert_allclose(xd, xh, rtol=0, atol=EXACT)
        np.testing.assert_allclose(wd, wh, rtol=1e-5, atol=1e-8)  # both tools' forces and torques
    assert kinds["self_contacts"] > 0 and kinds["face_contacts"] > 0
    held = np.array([w for _, _, w, *_ in dev[25:]])
    assert (held[:, 8] > 0.0).all()  # the spatula pushed up by the tissue
    assert (held[:, 2] > 0.0).all() or contact  # the probe too (with friction the arm sags less)
    assert np.abs(held[:, 9:12]).max() > 0.0  # the tilted spatula's contacts are off its axis
    # the tangential part of the contacts' forces: with friction, some
    tangential = max(np.abs(f - np.einsum("kj,kj->k", f, n)[:, None] * n).max(initial=0.0)
                     for *_, f, n in dev[5:])
    assert (tangential > 1e-6) == bool(contact.get("friction")), tangential
    assert all(s["active_contacts"] > 0 for s, *_ in dev[25:])
    assert replays >= (30 if graph else 0)


def test_the_rows_kernels_lanes_give_the_host_rows(tmp_path, monkeypatch):
    """The rows kernel is one block whose lanes rank their slots among the active ones and wait
    before each contact's place is summed from the ranks below it: with Warp's CPU blocks on
    (real lanes, switching at the block's barriers) its rows still give the host rows' steps,
    self and face contacts with friction (a missing wait, or a wrong rank, puts rows in other
    places). On the CPU whatever the test device (a GPU's block is compared above)."""
    import warp as wp

    monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    cfg = lambda rows: {**_u_scene(tmp_path, rows, rows=160, graph=False, **FRICTION), "device": "cpu"}  # noqa: E731
    host, _ = _press(cfg(False), steps=20)
    dev, _ = _press(cfg(True), steps=20)
    selfs = 0
    for (sh, xh, wh, *ch), (sd, xd, wd, *cd) in zip(host, dev):
        assert sd["rows_device"] is True
        for key in ("contacts", "self_contacts", "face_contacts", "active_contacts", "gs_iterations"):
            assert sd.get(key) == sh.get(key), key
        for a, b in zip(cd[:2], ch[:2]):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_allclose(xd, xh, rtol=0, atol=EXACT)
        selfs = max(selfs, sd.get("self_contacts", 0))
    assert selfs > 0 and max(s.get("contacts", 0) for s, *_ in dev) > 8


def test_the_warm_start_by_slot_is_the_host_warm_start(tmp_path, monkeypatch):
    """Without the kept forces (the epoch advanced before every solve) the device's sweeps
    differ from the host's warm-started ones: the warm start is what made them equal."""
    host, _ = _press(_u_scene(tmp_path, False), steps=30)
    real = contact_solver.DeviceStep.launch

    def cold(self):
        self.rows.forget()
        return real(self)

    monkeypatch.setattr(contact_solver.DeviceStep, "launch", cold)
    dev, _ = _press(_u_scene(tmp_path, True), steps=30)
    sweeps = [(s["gs_iterations"], d["gs_iterations"]) for (s, *_), (d, *_) in zip(host, dev) if s.get("contacts")]
    assert sum(d for _, d in sweeps) > sum(h for h, _ in sweeps)
    # the same contacts, solved to the tolerance either way
    assert [s.get("contacts") for s, *_ in host] == [d.get("contacts") for d, *_ in dev]


def test_beyond_the_row_limit_the_step_is_redone_on_the_host_and_the_next_built_there(tmp_path):
    """With a limit of 4 rows the contact sets overflow the device's: the first such step is
    redone on the host (the free motion restored), the steps after it are built on the host
    while the last step's set exceeds the limit, and every step is the host rows' own."""
    host, _ = _press(_u_scene(tmp_path, False, rows=4), steps=30)
    dev, _ = _press(_u_scene(tmp_path, True, rows=4), steps=30)
    many = [k for k, (s, *_) in enumerate(dev) if s.get("contacts", 0) > 4]
    assert many
    assert not any(dev[k][0].get("rows_device") for k in many)
    assert not dev[many[0] + 1][0].get("rows_device") and not dev[many[-1]][0].get("lcp_device")
    for (sh, xh, *_), (sd, xd, *_) in zip(host, dev):
        assert sd.get("contacts") == sh.get("contacts")
        # on a GPU the device steps' rounding (see EXACT) can move a long host solve of a later
        # step (160 sweeps to the tolerance) by a sweep
        slack = 0 if DEVICE == "cpu" else 2
        assert abs(sd.get("gs_iterations", 0) - sh.get("gs_iterations", 0)) <= slack
        np.testing.assert_allclose(xd, xh, rtol=0, atol=EXACT)


@pytest.mark.parametrize("contact, why", [({"device_lcp_rows": 0}, "no device LCP"),
                                          ({"device_rows": False}, "option off")])
def test_the_rows_stay_on_the_host_where_the_device_does_not_build_them(tmp_path, contact, why):
    """No device LCP, or the option off: the rows are built on the host."""
    contact = dict(contact)
    cfg = _u_scene(tmp_path, contact.pop("device_rows", True), **contact)
    out, _ = _press(cfg, steps=25)
    assert any(s.get("contacts", 0) for s, *_ in out), why
    assert not any(s.get("rows_device") for s, *_ in out), why


def test_a_runaway_correction_from_the_device_rows_is_dropped(tmp_path, monkeypatch):
    """A correction the guard refuses (its kinetic energy made to jump) is dropped as on the
    host path: the free motion stands for the step, counted and said."""
    from soft_tissue_sim.scene import Simulation

    cfg = _u_scene(tmp_path, True, graph=False)
    real = Simulation._judge_contact

    def runaway(self, stats, guard, rest, measure, ke_free, free, reason):
        if guard is not None and stats.contact is not None and stats.contact.rows_device and stats.contact.contacts:
            guard = np.array([1e30, 0.0])
        return real(self, stats, guard, rest, measure, ke_free, free, reason)

    monkeypatch.setattr(Simulation, "_judge_contact", runaway)
    with pytest.warns(UserWarning, match="runaway energy after the contact correction"):
        with load_scene(cfg) as sim:
            top = sim.positions()[:, 2].max()
            for k in range(25):
                z = top + 0.0035 - 0.002 * min(1.0, k / 20)
                sim.set_instrument_pose("probe", [0.035, 0.0, z], [0.0, 0.0, 0.0, 1.0])
                sim.set_instrument_pose("spatula", [0.02, 0.005, top + 0.01], [0.0, 0.0, 0.0, 1.0])
                s = sim.step()
            assert sim.contact_rejections > 0
            assert s.guard.contact_rejected.startswith("runaway energy")
            assert np.isfinite(sim.positions()).all()
