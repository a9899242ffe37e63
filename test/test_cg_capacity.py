"""DevicePCG's captured solve replays across node counts within its work vectors' capacity
(soft_tissue_sim.cg): the launches read the count on the device, the key holds no count.

Runs on Warp's CPU backend (where the solve is captured as a Warp graph too);
``STS_TEST_DEVICE=cuda:0`` runs it on a GPU.
"""

import os

import numpy as np
import pytest
import warp as wp

from soft_tissue_sim import graphs
from soft_tissue_sim.buffers import capacity_for
from soft_tissue_sim.cg import BlockJacobiPreconditioner, DevicePCG, IdentityPreconditioner, set_count_kernel

DEVICE = os.environ.get("STS_TEST_DEVICE", "cpu")
ROOM = 256  # the test operator's and vectors' capacity (fixed: their addresses hold)
COUPLING = 1.0


@wp.kernel
def _chain_matvec_kernel(count: wp.array(dtype=wp.int32), d: wp.array(dtype=wp.float64), c: wp.float64,
                         p: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.vec3d)):
    """out = A p, A = diag(d) - c (the chain's neighbours), on the first count[0] nodes."""
    i = wp.tid()
    n = count[0]
    if i < n:
        v = d[i] * p[i]
        if i > 0:
            v = v - c * p[i - 1]
        if i + 1 < n:
            v = v - c * p[i + 1]
        out[i] = v


@wp.kernel
def _diag_apply_kernel(count: wp.array(dtype=wp.int32), d: wp.array(dtype=wp.float64),
                       r: wp.array(dtype=wp.vec3d), z: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
    if i < count[0]:
        z[i] = r[i] / d[i]


@wp.kernel
def _diag_blocks_kernel(count: wp.array(dtype=wp.int32), d: wp.array(dtype=wp.float64), m_coef: wp.float64,
                        k_coef: wp.float64, out: wp.array(dtype=wp.mat33d)):
    i = wp.tid()
    if i < count[0]:
        out[i] = (m_coef + k_coef * d[i]) * wp.identity(n=3, dtype=wp.float64)


class ChainOperator:
    """An SPD operator (a diagonally dominant chain, the same on x, y, z) whose launches read
    the node count on the device and run over a fixed capacity: its graph key holds no count."""

    def __init__(self, device, seed=3):
        self.device = wp.get_device(device)
        rng = np.random.default_rng(seed)
        self.d_host = 2.0 * COUPLING + 0.5 + rng.random(ROOM)
        self.d = wp.array(self.d_host, dtype=wp.float64, device=self.device)
        self.count = wp.zeros(1, dtype=wp.int32, device=self.device)
        self.n = 0
        # the fem the identity and BlockJacobiPreconditioner read in begin_step
        self.free = wp.array(np.ones(ROOM), dtype=wp.float64, device=self.device)
        self.n_nodes_dev, self.node_dim = self.count, ROOM

    def set_n(self, n):
        self.n = n
        wp.launch(set_count_kernel, 1, [self.count, int(n)], device=self.device)

    n_nodes = property(lambda self: self.n)

    def matvec(self, p, out):
        wp.launch(_chain_matvec_kernel, ROOM, [self.count, self.d, COUPLING, p, out], device=self.device)

    def graph_key(self):
        return (self.d.ptr, self.count.ptr)

    def dense(self, n):
        A = np.diag(self.d_host[:n]) - COUPLING * (np.eye(n, k=1) + np.eye(n, k=-1))
        return A

    def diagonal_blocks(self, m_coef, k_coef, out):
        wp.launch(_diag_blocks_kernel, ROOM, [self.count, self.d, float(m_coef), float(k_coef), out],
                  device=self.device)


class DiagPreconditioner:
    """z = diag(A)^-1 r, launched over the capacity, reading the operator's device count."""

    name = "diag"

    def __init__(self, op):
        self.op = op

    def apply(self, r, z):
        wp.launch(_diag_apply_kernel, ROOM, [self.op.count, self.op.d, r, z], device=self.op.device)

    def device_capable(self):
        return True

    def graph_key(self):
        return (self.op.d.ptr, self.op.count.ptr)


class _System:
    """What the preconditioners' begin_step reads: fem (the operator), m_coef, k_coef."""

    def __init__(self, fem):
        self.fem, self.m_coef, self.k_coef = fem, 0.0, 1.0


@pytest.fixture(autouse=True)
def _empty_park():
    graphs.release()
    yield
    graphs.release()


def _rhs(n, seed):
    return np.random.default_rng(seed).standard_normal((n, 3))


class Problem:
    """The operator, a preconditioner, and b, x as prefix views of fixed allocations."""

    def __init__(self, kind="diag"):
        self.op = ChainOperator(DEVICE)
        self.b_buf = wp.zeros(ROOM, dtype=wp.vec3d, device=DEVICE)
        self.x_buf = wp.zeros(ROOM, dtype=wp.vec3d, device=DEVICE)
        self.kind = kind
        if kind == "diag":
            self.pre = DiagPreconditioner(self.op)
        elif kind == "jacobi":
            self.pre = BlockJacobiPreconditioner()
        else:
            self.pre = IdentityPreconditioner()

    def set_n(self, n, seed=None, guess=None):
        self.op.set_n(n)
        if self.kind != "diag":
            self.pre.begin_step(_System(self.op))
        b, x = self.b_buf[:n], self.x_buf[:n]
        b.assign(_rhs(n, n if seed is None else seed))
        x.assign(np.zeros((n, 3)) if guess is None else guess)
        return b, x

    def solve(self, pcg, n, seed=None, guess=None):
        b, x = self.set_n(n, seed, guess)
        res = pcg.solve(self.op.matvec, b, x, self.pre)
        return res, x.numpy().copy()

    def reference(self, n, seed=None):
        return np.linalg.solve(self.op.dense(n), _rhs(n, n if seed is None else seed))


@pytest.mark.parametrize("kind", ["diag", "jacobi", "none"])
@pytest.mark.parametrize("warm_start", [False, True])
def test_a_new_count_within_the_capacity_replays_the_graph(kind, warm_start):
    n0 = 40
    cap = capacity_for(n0)
    prob = Problem(kind)
    pcg = DevicePCG(n0, DEVICE, 1e-12, 500, graph=True, warm_start=warm_start)
    for _ in range(2):  # plain, then captured (and launched)
        res, x = prob.solve(pcg, n0)
        assert res.converged
        np.testing.assert_allclose(x, prob.reference(n0), rtol=0.0, atol=1e-10)
    assert pcg.captures == 1 and pcg.replays == 1
    geometry = pcg._geometry
    for k, n in enumerate((33, cap, 21, n0 + 3)):  # smaller and larger counts within the capacity
        guess = 0.5 * prob.reference(n) if warm_start and k % 2 == 0 else None
        res, x = prob.solve(pcg, n, guess=guess)
        assert pcg.n == n and int(pcg.count.numpy()[0]) == n
        assert pcg._geometry == geometry
        assert pcg.captures == 1 and pcg.replays == 2 + k  # replayed, not captured again
        assert res.converged and res.iterations > 0
        np.testing.assert_allclose(x, prob.reference(n), rtol=0.0, atol=1e-10)
    # beyond the capacity: new buffers, the old graph retired, the new key captured at its first solve
    n = cap + 30
    res, x = prob.solve(pcg, n)
    assert pcg._geometry != geometry and graphs.parked() == 1
    assert pcg.captures == 2 and pcg.replays == 6
    assert res.converged
    np.testing.assert_allclose(x, prob.reference(n), rtol=0.0, atol=1e-10)


@pytest.mark.parametrize("kind", ["diag", "none"])
@pytest.mark.parametrize("warm_start", [False, True])
def test_a_replayed_solve_at_a_new_count_is_the_uncaptured_solve(kind, warm_start):
    """Bit for bit on the CPU: the same launches, captured at one count and replayed at another."""
    n0 = 50
    prob = Problem(kind)
    pcg = DevicePCG(n0, DEVICE, 1e-11, 500, graph=True, warm_start=warm_start)
    for _ in range(2):
        prob.solve(pcg, n0)
    assert pcg.captures == 1
    for n, seed in ((41, 7), (58, 8)):
        guess = 0.25 * prob.reference(n, seed) if warm_start else None
        res, x = prob.solve(pcg, n, seed, guess)
        assert pcg.captures == 1 and pcg.replay.latest() is not None
        s = pcg.scalars.numpy().copy()
        plain = DevicePCG(n, DEVICE, 1e-11, 500, graph=False, warm_start=warm_start)
        res_plain, x_plain = prob.solve(plain, n, seed, guess)
        assert plain.replays == 0
        if DEVICE == "cpu":
            np.testing.assert_array_equal(x, x_plain)
            np.testing.assert_array_equal(s, plain.scalars.numpy())
        else:
            np.testing.assert_allclose(x, x_plain, rtol=0.0, atol=1e-12)
        assert res.iterations == res_plain.iterations and res.converged and res_plain.converged
        np.testing.assert_allclose(x, prob.reference(n, seed), rtol=0.0, atol=1e-9)


def test_the_host_solve_and_the_device_solve_agree_after_resizes():
    """PCG.solve (host scalars) is unchanged: same iterations, solutions to rounding."""
    prob = Problem("diag")
    pcg = DevicePCG(40, DEVICE, 1e-10, 500, graph=True)
    for n in (40, 40, 35, 47):
        res, x = prob.solve(pcg, n)
        b, xh = prob.set_n(n)
        host = super(DevicePCG, pcg).solve(prob.op.matvec, b, xh, prob.pre)
        assert host.iterations == res.iterations and host.converged
        np.testing.assert_allclose(xh.numpy(), x, rtol=0.0, atol=1e-12)
    assert pcg.captures == 1


def test_a_resize_within_the_capacity_keeps_the_graph_and_beyond_it_parks_it():
    prob = Problem("diag")
    pcg = DevicePCG(20, DEVICE, 1e-10, 200, graph=True)
    for _ in range(2):
        prob.solve(pcg, 20)
    g = pcg.replay.latest()
    assert g is not None
    pcg.resize(17)
    pcg.resize(pcg.n)
    assert pcg.replay.latest() is g and graphs.parked() == 0
    pcg.resize(10 * capacity_for(20))
    assert pcg.replay.latest() is None and graphs.parked() == 1 and graphs._parked[0] is g
