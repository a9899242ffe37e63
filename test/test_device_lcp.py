"""The contact LCP solved where the dense factor is, with the correction
(soft_tissue_sim.contact.device_lcp): the same steps as the host solve, the row limit, the
fallback where W is not positive definite, the kernel against the host PGS.

Warp's CPU backend by default (the dense factor with NumPy and LAPACK); ``STS_TEST_DEVICE=cuda:0``
runs the same on a GPU.
"""

import os

import numpy as np
import pytest
import warp as wp

from soft_tissue_sim import load_scene
from soft_tissue_sim.contact import device_lcp
from soft_tissue_sim.contact.device_lcp import BIG, LANES, SMALL, WIDE_LANES, DeviceLCP
from soft_tissue_sim.contact.pgs import FIRST_SWEEPS, LARGE_FIRST_SWEEPS, LARGE_SET_ROWS, PGS, first_sweeps_of
from soft_tissue_sim.dense_inverse import DenseInverse
from soft_tissue_sim.material import ParameterError
from test_contact import FLOOR_Z, scene

DEVICE = os.environ.get("STS_TEST_DEVICE", "cpu")


def _floor_scene(rows, friction=0.0, cone="disk", graph=False, tol=1e-8, active_set=True, mesh=None, **contact):
    floor = {"type": "plane", "name": "floor", "point": [0.0, 0.0, FLOOR_Z], "normal": [0.0, 0.0, 1.0]}
    cfg = scene(mesh, obstacles=[floor], contact={"tolerance": tol, "device_lcp_rows": rows, "friction": friction,
                                            "friction_cone": cone, "active_set": active_set, **contact})
    cfg["device"] = DEVICE
    cfg["solver"]["ldlt"].update(backend="dense")
    cfg["solver"]["graph"] = graph
    return cfg


def _run(cfg, steps=40):
    with load_scene(cfg) as sim:
        stats = [sim.step().extra for _ in range(steps)]
        return sim.positions(), sim.velocities(), sim.contact.wrench("floor"), stats


def _device_pgs(W, d0, lam0, row_start, rows, mu, cap, tol, pyramid=False, first=FIRST_SWEEPS, max_iterations=200,
                device=None):
    """device_pgs_kernel on one LCP in DeviceLCP's buffers of ``cap`` rows (sizes read on the
    device): (lambda, info = [sweeps, residual, W usable], delta)."""
    lcp = DeviceLCP(cap, device or DEVICE)
    m = len(d0)
    lcp.stage_problem(W, d0, lam0, row_start, rows, mu)
    lcp.solve(max_iterations, tol, pyramid, first)
    return lcp.lam.numpy()[:m], lcp.info.numpy(), lcp.delta.numpy()[:m]


@pytest.mark.parametrize("graph", [False, True])
@pytest.mark.parametrize("friction, cone, rows", [(0.0, "disk", 32), (0.0, "disk", 64), (0.4, "disk", 64),
                                                  (0.4, "pyramid", 64), (0.4, "disk", 32)])
def test_the_device_solve_takes_the_host_solves_steps(friction, cone, rows, graph):
    """A block landing on a floor (0 to 12 contacts, 36 rows with friction): the LCP solved on
    the device, in the correction's graph, gives the host solve's positions, velocities,
    forces and sweeps (the sweeps alone on both: the host's active-set finish is the next
    test's); the statistics say where it was solved."""
    cpu = DEVICE == "cpu"
    # within 32 rows the small kernels; with friction a smaller block (4 contacts, 12 rows)
    small = friction > 0.0 and rows <= 32
    mesh = {"generator": "beam", "n_long": 2, "n_cross": 2, "spacing": 0.01} if small else None
    host = _run(_floor_scene(0, friction, cone, graph, active_set=False, mesh=mesh))
    dev = _run(_floor_scene(rows, friction, cone, graph, active_set=False, mesh=mesh))
    assert any(s.get("contacts", 0) == (4 if small else 12) for s in dev[3])
    for sh, sd in zip(host[3], dev[3]):
        assert "lcp_device" not in sh
        if sd.get("contacts", 0):
            assert sd["lcp_device"] is True
            assert sd["gs_iterations"] == sh["gs_iterations"]
            # the residual (a difference of nearly equal terms, far under the 1e-8 m tolerance)
            # shifts with the rounding of another processor's arithmetic
            assert sd["lcp_residual"] == pytest.approx(sh["lcp_residual"], rel=1e-6, abs=1e-15 if cpu else 1e-10)
            assert sd["active_contacts"] == sh["active_contacts"]
    # dx is summed from the contacts' nodes' columns of the inverse (the host applies it whole), and
    # the GPU's PGS uses FMA: equal to rounding, which the sweeps (to 1e-8 m) carry from step to
    # step on the GPU
    tol = 1e-12 if cpu else 1e-9
    np.testing.assert_allclose(dev[0], host[0], rtol=0, atol=tol)
    np.testing.assert_allclose(dev[1], host[1], rtol=0, atol=tol / 0.01)
    np.testing.assert_allclose(dev[2][0], host[2][0], rtol=1e-9 if cpu else 1e-6, atol=1e-12 if cpu else 1e-9)
    assert dev[2][0][2] < 0.0  # the floor carries the block


@pytest.mark.parametrize("cone, rows", [("disk", 64), ("pyramid", 64), ("disk", 32)])
def test_the_device_friction_finish_takes_the_host_finishs_steps(cone, rows):
    """contact.friction_active_set on the device (the finish on the block's lane 0) and on the
    host: a block landing with friction at 1e-10 m (where the sweeps alone stop at their cap),
    the same iterations, residuals to rounding, positions and the floor's force."""
    cpu = DEVICE == "cpu"
    small = rows <= 32
    mesh = {"generator": "beam", "n_long": 2, "n_cross": 2, "spacing": 0.01} if small else None
    kw = dict(friction=0.4, cone=cone, tol=1e-10, mesh=mesh, friction_active_set=True)
    host = _run(_floor_scene(0, **kw))
    dev = _run(_floor_scene(rows, **kw))
    assert any(s.get("contacts", 0) == (4 if small else 12) for s in dev[3])
    finished = steps = other = 0
    for sh, sd in zip(host[3], dev[3]):
        if sd.get("contacts", 0):
            assert sd["lcp_device"] is True and "lcp_device" not in sh
            steps += 1
            # on a GPU (fused multiply-adds) a choice of the finish may fall the other way
            if cpu or sd["gs_iterations"] == sh["gs_iterations"]:
                assert sd["gs_iterations"] == sh["gs_iterations"]
                # the residual is rounding's to the bit on the CPU; on a GPU it is that of the last
                # sweep's own rounding, on the same side of the tolerance
                assert sd["lcp_residual"] == pytest.approx(sh["lcp_residual"], rel=1e-6, abs=1e-15 if cpu else 0.3e-10)
                assert (sd["lcp_residual"] <= 1e-10) == (sh["lcp_residual"] <= 1e-10)
            else:
                other += 1
            finished += sh["gs_iterations"] > FIRST_SWEEPS and sh["lcp_residual"] <= 1e-10
    # some steps went beyond the first sweeps and converged; on a GPU a tenth may have turned
    # another way (a flipped choice changes the iterations of the steps after it too)
    assert finished > 0 and other <= 0.1 * steps
    tol = 1e-12 if cpu else 1e-9
    np.testing.assert_allclose(dev[0], host[0], rtol=0, atol=tol)
    np.testing.assert_allclose(dev[2][0], host[2][0], rtol=1e-9 if cpu else 1e-6, atol=1e-12 if cpu else 1e-9)


def test_the_device_friction_finish_solves_the_default_scenes_lcps_as_the_host():
    """The default scene's own LCPs (recorded along the node benchmark's trajectory; the
    scalpel's tip, nearly repeated contacts): the kernel with the friction finish makes the
    host's iterations on every set, converges on the same ones, and its contact displacement
    W lambda is the host's to rounding."""
    from soft_tissue_sim.bench.lcp import default_sets

    sets = default_sets(400, 2)
    host = PGS(friction_active_set=True)
    finished = other = 0
    lcp = DeviceLCP(SMALL, DEVICE)
    for W, d0, row_start, rows, mu, lam0, tol, pyramid, max_iterations in sets:
        m = len(d0)
        lh, ih, rh = host.solve(W, d0, row_start, rows, mu, max_iterations, tol, pyramid, lam0)
        lcp.stage_problem(W, d0, lam0, row_start, rows, mu)
        lcp.solve(max_iterations, tol, pyramid, FIRST_SWEEPS, True)
        info = lcp.info.numpy()
        ld = lcp.lam.numpy()[:m]
        if DEVICE == "cpu" or (int(info[0]) == ih and (info[1] <= tol) == (rh <= tol)):
            assert int(info[0]) == ih and (info[1] <= tol) == (rh <= tol)
            assert np.abs(W @ (ld - lh)).max() <= (1e-12 if DEVICE == "cpu" else 1e-9)  # [m], of about 1 mm
        else:  # on a GPU (fused multiply-adds) a choice of the finish may fall the other way
            other += 1
        finished += ih > FIRST_SWEEPS
    assert len(sets) > 100 and finished > 10 and other <= 0.02 * len(sets)


def test_a_contact_set_beyond_the_row_limit_is_solved_on_the_host():
    """The block's 12 resting contacts: 12 rows frictionless (within a limit of 16: on the
    device), 36 with friction (beyond it: on the host)."""
    for friction, device in ((0.0, True), (0.4, False)):
        stats = _run(_floor_scene(16, friction=friction), steps=30)[3]
        resting = [s for s in stats if s.get("contacts", 0) == 12]
        assert resting and all(s.get("lcp_device", False) is device for s in resting)


def test_w_not_positive_definite_on_the_device_is_solved_again_on_the_host(monkeypatch):
    """The device's check refuses a W that is not positive definite (here the gathered W
    negated): no correction is made from it, the step's contacts are solved on the host and
    the steps are the host solve's."""
    host = _run(_floor_scene(0), steps=25)
    real = DenseInverse.delassus_matrix

    def negated(self, nodes, coef, dR, sizes, scale, W):
        real(self, nodes, coef, dR, sizes, -scale, W)

    monkeypatch.setattr(DenseInverse, "delassus_matrix", negated)
    dev = _run(_floor_scene(32), steps=25)
    assert any(s.get("contacts", 0) for s in dev[3])
    assert all("lcp_device" not in s for s in dev[3])  # every solve redone on the host
    assert all(s["lcp_redone"] for s in dev[3] if s.get("contacts", 0))
    np.testing.assert_allclose(dev[0], host[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(dev[2][0], host[2][0], rtol=1e-9, atol=1e-12)


def test_sweeps_that_end_above_the_tolerance_are_finished_on_the_device_as_on_the_host():
    """At 1e-10 m some of the landing block's frictionless LCPs stop at the 200 sweeps above
    the tolerance: with the active-set finish (the default) the device finishes them as the
    host does, within the tolerance and with the host's steps; without it the sweeps' lambda
    stands, still within 1e-8 m."""
    tol = 1e-10
    runs = {a: _run(_floor_scene(32, tol=tol, active_set=a), steps=30) for a in (True, False)}
    for a, run in runs.items():
        pressed = [s for s in run[3] if s.get("contacts", 0)]
        assert pressed and all(s.get("lcp_device") and not s.get("lcp_redone") for s in pressed)
        worst = max(s["lcp_residual"] for s in pressed)
        if a:
            assert worst <= tol
            assert any(s["gs_iterations"] > FIRST_SWEEPS for s in pressed)  # the finish ran
        else:
            assert worst <= 1e-8 and (tol < worst or DEVICE != "cpu")  # the stall as recorded on the CPU
    host = _run(_floor_scene(0, tol=tol), steps=30)
    assert max(s["lcp_residual"] for s in host[3] if s.get("contacts", 0)) <= tol
    # the face solves' rounding differs from LAPACK's (more so on a GPU, which fuses multiply-adds)
    np.testing.assert_allclose(runs[True][0], host[0], rtol=0, atol=1e-12 if DEVICE == "cpu" else 1e-9)
    assert np.abs(runs[False][0] - host[0]).max() > 0.0 or DEVICE != "cpu"


def _stalling_lcp(rng, m):
    """A random frictionless LCP of m rows whose W is of low rank plus a small multiple of I (the
    nearly repeated rows that stall the sweeps): (W, d0, lam0)."""
    B = rng.standard_normal((m, int(rng.integers(m // 2 + 1, m + 1))))
    W = B @ B.T / m + 10.0 ** rng.uniform(-9, -2) * np.eye(m)
    d0 = rng.standard_normal(m) * 1e-3
    lam0 = np.abs(rng.standard_normal(m)) * 1e-4 * (rng.random(m) < 0.5)
    return W, d0, lam0


@pytest.mark.parametrize("cap, fewest, trials", [(32, 2, 24), (256, 33, 8)])
def test_the_device_kernels_active_set_finish_is_the_hosts(cap, fewest, trials):
    """device_pgs_kernel with the active-set finish against the host's PGS (sweeps, then
    :func:`~soft_tissue_sim.contact.pgs.active_set`) on random frictionless LCPs (up to 32 rows,
    and from 33 to 256: more rows than the block's lanes) that stall the sweeps: the same
    sweeps and face solves, and lambda to the face solves' rounding."""
    rng = np.random.default_rng(5 + cap)
    tol, finished = 1e-10, 0
    pgs = PGS(active_set=True)
    for _ in range(trials):
        m = int(rng.integers(fewest, cap + 1))
        W, d0, lam0 = _stalling_lcp(rng, m)
        one = np.arange(m, dtype=np.int32)  # each row a contact
        ref, its, res = pgs.solve(W, d0, one, np.ones(m, np.int32), np.zeros(m), 200, tol, False, lam0)
        got, inf, _ = _device_pgs(W, d0, lam0, one, np.ones(m, np.int32), np.zeros(m), cap, tol)
        assert inf[2] == 1.0 and int(inf[0]) == its and (got >= 0.0).all()
        assert res <= tol and inf[1] <= tol
        np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-9 * np.abs(ref).max())
        finished += its > first_sweeps_of(m, FIRST_SWEEPS, 200)
    assert finished >= trials // 2  # most needed the finish


@pytest.mark.parametrize("cap, fewest", [(32, 8), (256, 40)])
def test_the_finishs_last_face_inverse_is_its_rows_inverse(cap, fewest):
    """After the device's active-set finish (a face's inverse grown a row at a time as rows join,
    :func:`~soft_tissue_sim.contact.device_lcp.border_inverse`, and rows that leave taken out of
    it, :func:`~soft_tissue_sim.contact.device_lcp.drop_inverse`), the buffers hold
    (W_PP + shift I)^-1 with P's rows in the order they joined."""
    rng = np.random.default_rng(11 + cap)
    checked = dropped = 0
    for trial in range(8):
        m = int(rng.integers(fewest, cap + 1))
        W, d0, lam0 = _stalling_lcp(rng, m)
        W += 1e-3 * np.eye(m)  # conditioned for the check of the inverse itself
        if trial % 2 == 0:
            lam0[:] = 0.0  # from nothing: every row of the last face joined one at a time
        one = np.arange(m, dtype=np.int32)
        lcp = DeviceLCP(cap, DEVICE)
        lcp.stage_problem(W, d0, lam0, one, np.ones(m, np.int32), np.zeros(m))
        lcp.solve(200, 1e-10, False, 0)  # no sweeps first: the finish from the warm start
        p = int(lcp.iwork.numpy()[device_lcp._FLAGS, 0])
        P = lcp.iwork.numpy()[device_lcp._P, :p]
        if p < 2:
            continue
        assert len(set(P.tolist())) == p and P.max() < m
        B = lcp.L.numpy()[:p, :p]
        ref = np.linalg.inv(W[np.ix_(P, P)] + 1e-12 * W.diagonal().max() * np.eye(p))
        np.testing.assert_allclose(B, ref, rtol=1e-7, atol=1e-9 * np.abs(ref).max())
        checked += 1
        dropped += (lam0 > 0).sum() > 0 and not set(np.flatnonzero(lam0 > 0)) <= set(P.tolist())
    assert checked >= 6 and dropped >= 1


@pytest.mark.parametrize("device_rows", [False, True])
def test_steps_with_and_without_a_device_solve_alternate_under_graphs(device_rows):
    """A capsule tapping a clamped block every other step, graphs on: the correction's graphs
    with and without the device solve are replayed in turn (each writes the read-back it was
    captured with) and give the host solve's steps. With the rows built on the device the
    whole contact step is in the graph after the solve, with contacts or without."""
    runs = {}
    for rows in (0, 32):
        cfg = scene(mesh={"generator": "beam", "n_long": 5, "n_cross": 4, "spacing": 0.005},
                    fixed={"axis": "z", "below": -0.007},
                    instruments=[{"name": "probe", "shape": "capsule", "radius": 0.004, "length": 0.05}],
                    contact={"device_lcp_rows": rows, "active_set": False, "device_rows": device_rows})
        cfg["device"] = DEVICE
        cfg["solver"]["ldlt"].update(backend="dense")
        cfg["solver"]["graph"] = True
        q = [0.0, np.sin(np.pi / 4), 0.0, np.cos(np.pi / 4)]  # tool +z along world +x
        with load_scene(cfg) as sim:
            top = sim.positions()[:, 2].max()
            stats = []
            for i in range(24):
                z = top + 0.004 - (0.0008 if i % 2 else -0.003)  # in, out, in, ...
                sim.set_instrument_pose("probe", [-0.006, 0.001, z], q)
                stats.append(sim.step().extra)
            replayer = sim.integrator._after_replay if device_rows else sim.integrator._correction_replay
            runs[rows] = (sim.positions(), stats, replayer.replays)
    (x0, s0, _), (x1, s1, replays) = runs[0], runs[32]
    assert [s.get("contacts", 0) > 0 for s in s1] == [i % 2 == 1 for i in range(24)]
    assert all(s.get("lcp_device") for s in s1 if s.get("contacts", 0))
    assert all(s.get("rows_device", False) is device_rows for s in s1)
    assert not any(s.get("rows_device") for s in s0)  # no device LCP: the rows on the host
    assert replays >= 15
    assert [s.get("active_contacts", 0) for s in s0] == [s.get("active_contacts", 0) for s in s1]
    # dx from the columns of the contacts' nodes (see the first test)
    np.testing.assert_allclose(x1, x0, rtol=0, atol=1e-12 if DEVICE == "cpu" else 1e-9)


def test_the_device_solves_key_makes_its_work_vectors():
    """DeviceLCP.key() makes the views its launches use for this node count, so that the launches
    allocate nothing (memory allocated inside a graph capture would be the graph's)."""
    lcp = DeviceLCP(8, DEVICE)
    free = wp.ones(37, dtype=wp.float64, device=DEVICE)

    class Inner:
        def graph_key(self):
            return ()

        def delassus_key(self):
            return ()

    assert lcp._dx.capacity == 0
    key = lcp.key(Inner(), free, 0.01, ())
    assert lcp._dx.capacity >= 37
    assert lcp.key(Inner(), free, 0.01, ()) == key


@pytest.mark.parametrize("bad", [-1, 257, 2.5, True, "many"])
def test_device_lcp_rows_is_validated(bad):
    with pytest.raises(ParameterError, match="device_lcp_rows"):
        load_scene(_floor_scene(bad))


def _random_lcps(seed, count, most_contacts=7, fewest=2):
    """Random LCPs of contacts of one or three rows (friction 0.3; every other one frictionless),
    W = B B^T / m + 0.05 I: (W, d0, lam0, row_start, rows, mu, pyramid)."""
    rng = np.random.default_rng(seed)
    for trial in range(count):
        nc = int(rng.integers(fewest, most_contacts))
        rows = np.where(rng.random(nc) < 0.5, 3, 1).astype(np.int32) if trial % 2 else np.ones(nc, np.int32)
        row_start = (np.cumsum(rows) - rows).astype(np.int32)
        m = int(rows.sum())
        B = rng.standard_normal((m, m + 2))
        W = B @ B.T / m + 0.05 * np.eye(m)
        d0 = rng.standard_normal(m) * 1e-3
        lam0 = np.abs(rng.standard_normal(m)) * 1e-4 * (rows.repeat(rows) == 1)
        yield W, d0, lam0, row_start, rows, np.full(nc, 0.3), trial % 4 == 3


def test_the_device_kernel_solves_the_hosts_problems():
    """device_pgs_kernel against the host PGS (sweeps only) on random LCPs (frictionless and
    with friction rows, both cones), a padded capacity and the sizes read on the device: the
    same sweeps, residual and lambda (within 32 rows by the block's lanes, beyond by one lane in
    the device's memory); an indefinite W is refused with lambda = 0."""
    pgs = PGS(active_set=False)
    for cap, seed, fewest, most in ((24, 11, 2, 7), (64, 12, 12, 20), (256, 13, 40, 80)):
        sizes = []
        for trial, (W, d0, lam0, row_start, rows, mu, pyramid) in enumerate(_random_lcps(seed, 8, most, fewest)):
            if trial == 7:
                W[0, 0] = -1.0
            got, inf, _ = _device_pgs(W, d0, lam0, row_start, rows, mu, cap, 1e-10, pyramid, first=200)
            if trial == 7:
                assert inf[2] == 0.0 and not got.any()
                continue
            ref, its, res = pgs.solve(W, d0, row_start, rows, mu, 200, 1e-10, pyramid, lam0)
            assert inf[2] == 1.0 and int(inf[0]) == its
            np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-15)
            assert inf[1] == pytest.approx(res, rel=1e-6, abs=1e-18)
            sizes.append(len(d0))
        assert max(sizes) > LANES or cap < LANES  # the larger capacities had sets of more rows than lanes


@pytest.mark.parametrize("cap", [SMALL, BIG])
def test_the_blocks_lanes_give_the_one_lanes_lambda(cap):
    """The block's lanes share delta in shared memory, W's check a column at a time and the
    active-set finish of lane 0, and wait for each other where one reads what another writes:
    with Warp's CPU blocks on (real lanes, switching at the block's barriers) the kernel gives
    one lane's lambda, sweeps and delta to the bit, the narrow kernel and the wide one (sets of
    more rows than its lanes), with friction and frictionless sets that need the finish. A read
    racing a write (any of the three barriers left out) changes them. On the CPU whatever the
    test device (a GPU's block is compared with the host above)."""
    problems = [p for p in _random_lcps(21, 12, 20, 8) if len(p[1]) <= cap]
    rng = np.random.default_rng(22)
    for m in (cap // 2, cap - 7, cap):
        one = np.arange(m, dtype=np.int32)
        problems.append((*_stalling_lcp(rng, m), one, np.ones(m, np.int32), np.zeros(m), False))
    assert max(len(p[1]) for p in problems) > (WIDE_LANES if cap > SMALL else LANES) or cap <= LANES
    solve = lambda p: _device_pgs(*p[:6], cap, 1e-10, p[6], device="cpu")  # noqa: E731
    one = [solve(p) for p in problems]
    assert sum(int(i[0]) > first_sweeps_of(len(p[1]), FIRST_SWEEPS, 200)
               for (_, i, _), p in zip(one[-3:], problems[-3:])) >= 2  # the finish ran
    before = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = True
    try:
        lanes = [solve(p) for p in problems]
    finally:
        wp.config.enable_cpu_blocks = before
    for (l1, i1, d1), (l2, i2, d2) in zip(one, lanes):
        np.testing.assert_array_equal(l2, l1)
        np.testing.assert_array_equal(i2, i1)
        np.testing.assert_array_equal(d2, d1)


def test_the_correction_from_the_rows_columns_is_the_inverse_applied_to_h_transpose_lambda():
    """rows_apply: dt^2 dR P dR^T H^T lambda on the free nodes, summed from the rows' nodes'
    columns, equals the whole product (rows sharing a node, absent nodes, a zero lambda,
    rotated nodes, a fixed node; each node's rows summed by four threads, so that a thread sums
    several, and by the device's default split; a row count read on the device below the rows
    given)."""
    from scipy.spatial.transform import Rotation

    from soft_tissue_sim.dense_inverse import rows_apply, rows_part

    rng = np.random.default_rng(3)
    n, m = 9, 21
    B = rng.standard_normal((3 * n, 3 * n))
    P = B @ B.T + 3 * n * np.eye(3 * n)
    dR = Rotation.random(n, random_state=4).as_matrix()
    nodes = rng.integers(0, n, size=(m, 4)).astype(np.int32)
    nodes[1, 2:] = -1
    nodes[3, 0] = nodes[0, 0]  # two rows on one node
    coef = rng.standard_normal((m, 4, 3))
    lam = rng.random(m)
    lam[2] = 0.0
    m_used = m - 2  # the last two rows past the count the device reads
    free = np.ones(n)
    free[nodes[0, 1]] = 0.0
    r = np.zeros((n, 3))
    for i in range(m_used):
        for k in range(4):
            if nodes[i, k] >= 0:
                r[nodes[i, k]] += lam[i] * coef[i, k]
    s = np.einsum("nji,nj->ni", dR, r).reshape(-1)  # dR^T r, node by node
    z = np.einsum("nij,nj->ni", dR, (P @ s).reshape(n, 3))
    expected = 1e-4 * free[:, None] * z
    d = DEVICE
    cap = n + 5  # launched over a capacity: the nodes past the count (read on the device) untouched
    for split in (4, None):
        out = wp.zeros(cap, dtype=wp.vec3d, device=d)
        rows_apply(wp.array(P, dtype=wp.float64, device=d), wp.array(nodes, dtype=wp.int32, device=d),
                   wp.array(coef, dtype=wp.vec3d, device=d), wp.array(lam, dtype=wp.float64, device=d),
                   wp.array([m_used, m_used], dtype=wp.int32, device=d), wp.array(dR, dtype=wp.mat33d, device=d),
                   1e-4, wp.array(free, dtype=wp.float64, device=d), wp.array([3 * n], dtype=wp.int32, device=d),
                   rows_part(d, cap, split), out, d)
        np.testing.assert_allclose(out.numpy()[:n], expected, rtol=1e-12, atol=1e-18)
        assert not out.numpy()[n:].any()
        assert not out.numpy()[nodes[0, 1]].any()


def test_each_set_is_solved_by_the_kernel_of_its_size():
    """In buffers of more than SMALL rows both kernels are launched; each returns at once on the
    other's sets (the outputs untouched), so a small set gets the narrow kernel's solve (the same
    as in buffers of SMALL rows) and a large one the wide kernel's."""
    rng = np.random.default_rng(31)
    small, large = _stalling_lcp(rng, 20), _stalling_lcp(rng, 90)
    kernels = device_lcp.pgs_kernels(BIG)
    assert [k for k, _l, _r in kernels] == [device_lcp.device_pgs_kernel, device_lcp.device_pgs_wide_kernel]
    assert device_lcp.pgs_kernels(SMALL) == kernels[:1]
    for (W, d0, lam0), alone in ((small, 1), (large, 0)):  # the kernel that must leave this set alone
        m = len(d0)
        one = (np.arange(m, dtype=np.int32), np.ones(m, np.int32), np.zeros(m))
        got, inf, _ = _device_pgs(W, d0, lam0, *one, BIG, 1e-10)
        assert inf[2] == 1.0 and inf[1] <= 1e-10
        if m <= SMALL:
            ref, rinf, _ = _device_pgs(W, d0, lam0, *one, SMALL, 1e-10)
            np.testing.assert_array_equal(got, ref)
            np.testing.assert_array_equal(inf, rinf)
        lcp = DeviceLCP(BIG, DEVICE)
        lcp.stage_problem(W, d0, lam0, *one)
        lcp.out.fill_(-7.0)
        kernel, lanes, fewest = kernels[alone]
        wp.launch_tiled(kernel, dim=[1], inputs=[lcp.W, lcp.d0, lcp.lam0, lcp.row_start, lcp.n_rows, lcp.mu,
                                                 lcp.sizes, fewest, 200, 1e-10, 0, FIRST_SWEEPS, 0, lcp.L, lcp.work,
                                                 lcp.iwork, lcp.fwork, lcp.fiwork, lcp.fA, lcp.fN, lcp.lam, lcp.delta,
                                                 lcp.info], block_dim=lanes, device=DEVICE)
        assert (lcp.out.numpy() == -7.0).all()  # returned without a write


def test_a_large_frictionless_set_is_judged_by_its_solve():
    """A frictionless set of more than LARGE_SET_ROWS rows is not factorized whole first: its
    verdict is the solve's. One that ends within the tolerance is usable (here an indefinite W,
    which the host's check refuses, whose LCP the sweeps solve: lambda >= 0, W lambda + d0 >= 0
    and complementary); one that does not (too few iterations) is refused with lambda = 0, as a
    W that fails the check is; a set of LARGE_SET_ROWS rows keeps the check. The active-set
    finish starts after LARGE_FIRST_SWEEPS sweeps there."""
    from soft_tissue_sim.contact.compliance import positive_definite

    m = LARGE_SET_ROWS + 8
    W = np.eye(m)
    W[0, 1] = W[1, 0] = 2.0  # eigenvalues 3 and -1 in the first two rows, the diagonal positive
    d0 = np.full(m, -1e-3)
    one = (np.arange(m, dtype=np.int32), np.ones(m, np.int32), np.zeros(m))
    assert not positive_definite(W)
    lam, inf, delta = _device_pgs(W, d0, np.zeros(m), *one, BIG, 1e-10)
    assert inf[2] == 1.0 and inf[1] <= 1e-10
    assert (lam >= 0.0).all() and (W @ lam + d0 >= -1e-10).all() and abs(lam @ (W @ lam + d0)) <= 1e-12
    k = LARGE_SET_ROWS  # not large: the whole W's factorization refuses it
    lam, inf, _ = _device_pgs(W[:k, :k], d0[:k], np.zeros(k), *(a[:k] for a in one), BIG, 1e-10)
    assert inf[2] == 0.0 and not lam.any()
    W2, d2, l2 = _stalling_lcp(np.random.default_rng(32), m)
    lam, inf, _ = _device_pgs(W2, d2, l2, *one, BIG, 1e-10, max_iterations=2, first=2)
    assert inf[2] == 0.0 and inf[1] > 1e-10 and not lam.any()
    _, inf, _ = _device_pgs(W2, d2, l2, *one, BIG, 1e-10)
    ref = PGS(first_sweeps=LARGE_FIRST_SWEEPS).solve(W2, d2, *one, 200, 1e-10, False, l2)
    assert int(inf[0]) == ref[1] > LARGE_FIRST_SWEEPS and inf[2] == 1.0
    assert PGS().solve(W2, d2, *one, 200, 1e-10, False, l2)[1] == ref[1]  # the host's rule is the same
